//! Image tiles decoded to 8-bit pixels (by the one tile decoder, `terrastream-tiles`),
//! for what `pack` reads of them as they pass: the height range of an elevation pyramid,
//! where an image pyramid's pixels are opaque.

use terrastream_format::TileFormat;
pub(crate) use terrastream_tiles::Image as Pixels;

/// Decodes a PNG (16-bit samples stripped to 8) or a WebP tile; `Ok(None)` for other
/// formats (JPEG heights are lossy and have no alpha; stored samples are no images).
///
/// # Errors
/// Why the bytes are not an image of their format.
pub(crate) fn decode(format: TileFormat, bytes: &[u8]) -> Result<Option<Pixels>, String> {
    match format {
        TileFormat::Png | TileFormat::Webp => Ok(Some(Pixels::decode(format, bytes)?.into_eight_bit())),
        _ => Ok(None),
    }
}
