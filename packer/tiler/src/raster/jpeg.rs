//! JPEG images: headers read when opened, pixels decoded whole when read (a JPEG cannot
//! be read by rows here).

use std::path::Path;

use crate::error::{Error, Result};

/// Most bytes a JPEG may take decoded. A JPEG is decoded whole (it cannot be read by rows,
/// unlike every other input), so this bounds the tiler's memory for one.
pub const JPEG_MAX_DECODED_BYTES: usize = 1 << 30;

/// Refuses a JPEG too large to decode whole, naming the way out.
pub(crate) fn jpeg_fits(path: &Path, width: usize, height: usize) -> Result<()> {
    let bytes = width.saturating_mul(height).saturating_mul(3);
    if bytes > JPEG_MAX_DECODED_BYTES {
        return Err(Error::input(
            path,
            format!(
                "a {width}x{height} JPEG takes {} MiB decoded, over the {} MiB a JPEG may take (it cannot be \
                 read by rows): convert it to a tiled GeoTIFF, which is streamed (gdal_translate -co TILED=YES \
                 -co COMPRESS=JPEG in.jpg out.tif)",
                bytes >> 20,
                JPEG_MAX_DECODED_BYTES >> 20
            ),
        ));
    }
    Ok(())
}

/// A JPEG's width and height, from its headers, checked to fit [`JPEG_MAX_DECODED_BYTES`].
pub(super) fn jpeg_header(path: &Path) -> Result<(u32, u32)> {
    use std::io::Read;
    let bad = |why: String| Error::input(path, why);
    // The headers come first: a prefix is enough unless metadata segments are larger.
    let mut head = Vec::new();
    let file = std::fs::File::open(path).map_err(|e| Error::file(path, e))?;
    file.take(1 << 20).read_to_end(&mut head).map_err(|e| Error::file(path, e))?;
    let headers = |bytes: &[u8]| {
        let mut decoder = zune_jpeg::JpegDecoder::new_with_options(bytes, options());
        decoder.decode_headers().map_err(|e| bad(format!("JPEG: {e:?}")))?;
        decoder.dimensions().ok_or_else(|| bad("JPEG: no dimensions".into()))
    };
    let (w, h) = match headers(&head) {
        Ok(size) => size,
        Err(_) => headers(&std::fs::read(path).map_err(|e| Error::file(path, e))?)?,
    };
    jpeg_fits(path, w, h)?;
    let dim = |n: usize| u32::try_from(n).map_err(|_| bad("JPEG: too large".into()));
    Ok((dim(w)?, dim(h)?))
}

fn options() -> zune_jpeg::zune_core::options::DecoderOptions {
    zune_jpeg::zune_core::options::DecoderOptions::default()
        .jpeg_set_out_colorspace(zune_jpeg::zune_core::colorspace::ColorSpace::RGB)
        .set_max_width(1 << 16)
        .set_max_height(1 << 16)
}

/// Decodes a JPEG to RGB8: (width, height, pixels).
pub(super) fn decode_jpeg(path: &Path) -> Result<(u32, u32, Vec<u8>)> {
    let bad = |why: String| Error::input(path, why);
    let bytes = std::fs::read(path).map_err(|e| Error::file(path, e))?;
    let mut decoder = zune_jpeg::JpegDecoder::new_with_options(&bytes, options());
    decoder.decode_headers().map_err(|e| bad(format!("JPEG: {e:?}")))?;
    let (w, h) = decoder.dimensions().ok_or_else(|| bad("JPEG: no dimensions".into()))?;
    jpeg_fits(path, w, h)?;
    let pixels = decoder.decode().map_err(|e| bad(format!("JPEG: {e:?}")))?;
    let dim = |n: usize| u32::try_from(n).map_err(|_| bad("JPEG: too large".into()));
    Ok((dim(w)?, dim(h)?, pixels))
}
