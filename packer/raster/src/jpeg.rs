//! JPEG images: headers read when opened; pixels decoded whole when read, or, for a JPEG
//! too large for that, a row of MCUs at a time ([`super::jpegrows`]).

use std::path::Path;

use crate::error::{Error, Result};

/// Most bytes a JPEG may take decoded to be decoded whole (the fast way, with interpolated
/// chroma). A larger one is read a row of MCUs at a time, if it is sequential; a larger
/// progressive one is refused.
pub const JPEG_MAX_DECODED_BYTES: usize = 1 << 30;

/// Is a `width` x `height` JPEG decoded whole (else by rows)?
pub(crate) fn decoded_whole(width: usize, height: usize) -> bool {
    width.saturating_mul(height).saturating_mul(3) <= JPEG_MAX_DECODED_BYTES
}

/// Refuses a JPEG too large to decode whole that cannot be read by rows either, naming the
/// way out.
pub(crate) fn jpeg_fits(
    path: &Path,
    width: usize,
    height: usize,
    by_rows: impl FnOnce() -> Result<bool>,
) -> Result<()> {
    if decoded_whole(width, height) || by_rows()? {
        return Ok(());
    }
    let bytes = width.saturating_mul(height).saturating_mul(3);
    Err(Error::unsupported(
        path,
        format!(
            "a {width}x{height} JPEG takes {} MiB decoded, over the {} MiB a JPEG may take whole, and it cannot \
             be read by rows (progressive, lossless, arithmetic-coded, 12-bit or CMYK): convert it to a tiled \
             GeoTIFF, which is streamed (gdal_translate -co TILED=YES -co COMPRESS=JPEG in.jpg out.tif)",
            bytes >> 20,
            JPEG_MAX_DECODED_BYTES >> 20
        ),
    ))
}

/// A JPEG's width and height, from its headers, checked to be readable (see [`jpeg_fits`]).
pub(super) fn jpeg_header(path: &Path) -> Result<(u32, u32)> {
    use std::io::Read;
    let bad = |why: String| Error::damaged(path, why);
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
    jpeg_fits(path, w, h, || super::jpegrows::reads_by_rows(path))?;
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
    let bad = |why: String| Error::damaged(path, why);
    let bytes = std::fs::read(path).map_err(|e| Error::file(path, e))?;
    let mut decoder = zune_jpeg::JpegDecoder::new_with_options(&bytes, options());
    decoder.decode_headers().map_err(|e| bad(format!("JPEG: {e:?}")))?;
    let (w, h) = decoder.dimensions().ok_or_else(|| bad("JPEG: no dimensions".into()))?;
    if !decoded_whole(w, h) {
        return Err(bad(format!("a {w}x{h} JPEG is read by rows, not whole")));
    }
    let mut pixels = decoder.decode().map_err(|e| bad(format!("JPEG: {e:?}")))?;
    // A gray JPEG comes out gray whatever colour space is asked for.
    if pixels.len() == w * h {
        pixels = pixels.iter().flat_map(|&v| [v; 3]).collect();
    }
    let dim = |n: usize| u32::try_from(n).map_err(|_| bad("JPEG: too large".into()));
    Ok((dim(w)?, dim(h)?, pixels))
}

#[cfg(test)]
mod tests {
    #![allow(clippy::unwrap_used, clippy::cast_possible_truncation)]

    use super::*;

    #[test]
    fn a_jpeg_too_large_to_decode_whole_is_read_by_rows_or_refused_by_name() {
        let path = Path::new("ortho.jpg");
        let never = || -> Result<bool> { panic!("a JPEG that fits is decoded whole") };
        assert!(jpeg_fits(path, 10_800, 5_400, never).is_ok(), "the shaded relief (175 MB decoded) fits");
        assert!(jpeg_fits(path, 40_000, 30_000, || Ok(true)).is_ok(), "a sequential one is read by rows");
        let e = jpeg_fits(path, 40_000, 30_000, || Ok(false)).unwrap_err().to_string();
        assert!(e.contains("ortho.jpg") && e.contains("40000x30000") && e.contains("tiled GeoTIFF"), "{e}");
        assert!(jpeg_fits(path, usize::MAX, 3, || Ok(false)).is_err(), "no overflow");
    }
}
