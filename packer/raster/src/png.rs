//! PNG images, read row by row.

use std::path::Path;

use crate::error::{Error, Result};

/// A PNG's (colour type, bit depth) after expansion, and its size.
pub(super) fn png_header(path: &Path) -> Result<((png::ColorType, png::BitDepth), (u32, u32))> {
    let file = std::fs::File::open(path).map_err(|e| Error::file(path, e))?;
    let mut decoder = png::Decoder::new(std::io::BufReader::new(file));
    decoder.set_transformations(png::Transformations::EXPAND);
    let reader = decoder.read_info().map_err(|error| Error::Png { path: path.to_owned(), row: None, error })?;
    let info = reader.info();
    let size = (info.width, info.height);
    if size.0 == 0 || size.1 == 0 {
        return Err(Error::damaged(path, "the image is empty (0 pixels)"));
    }
    Ok((reader.output_color_type(), size))
}

/// Calls `row(values, channels, sixteen)` for each row of a PNG (palette and low bit
/// depths expanded; 16-bit samples big-endian).
pub(super) fn png_rows(path: &Path, width: u32, mut row: impl FnMut(&[u8], usize, bool) -> Result<()>) -> Result<()> {
    let file = std::fs::File::open(path).map_err(|e| Error::file(path, e))?;
    let mut decoder = png::Decoder::new(std::io::BufReader::new(file));
    decoder.set_transformations(png::Transformations::EXPAND);
    let mut reader = decoder.read_info().map_err(|error| Error::Png { path: path.to_owned(), row: None, error })?;
    let (colour, depth) = reader.output_color_type();
    let channels = colour.samples();
    let sixteen = depth == png::BitDepth::Sixteen;
    let expected = width as usize * channels * if sixteen { 2 } else { 1 };
    let mut y = 0u32;
    while let Some(r) = reader.next_row().map_err(|error| Error::Png { path: path.to_owned(), row: Some(y), error })? {
        let data = r.data();
        if data.len() < expected {
            return Err(Error::damaged(path, format!("PNG, row {y}: {} bytes, {expected} expected", data.len())));
        }
        row(&data[..expected], channels, sixteen)?;
        y += 1;
    }
    Ok(())
}
