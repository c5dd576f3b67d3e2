//! Image tiles decoded to 8-bit pixels, for what `pack` reads of them as they pass (the
//! height range of an elevation pyramid, where an image pyramid's pixels are opaque).

use terrastream_format::TileFormat;

/// A decoded tile: rows of `channels` bytes per pixel (1 gray, 2 gray + alpha, 3 RGB,
/// 4 RGBA).
#[derive(Clone, Debug)]
pub(crate) struct Pixels {
    pub(crate) width: u32,
    pub(crate) height: u32,
    pub(crate) channels: usize,
    pub(crate) data: Vec<u8>,
}

impl Pixels {
    /// Decodes a PNG (16-bit samples stripped to 8) or a WebP tile; `Ok(None)` for other
    /// formats (JPEG heights are lossy and have no alpha; stored samples are no images).
    ///
    /// # Errors
    /// Why the bytes are not an image of their format.
    pub(crate) fn decode(format: TileFormat, bytes: &[u8]) -> Result<Option<Self>, String> {
        match format {
            TileFormat::Png => {
                let mut decoder = png::Decoder::new(std::io::Cursor::new(bytes));
                decoder.set_transformations(png::Transformations::EXPAND | png::Transformations::STRIP_16);
                let mut reader = decoder.read_info().map_err(|e| format!("PNG: {e}"))?;
                let mut data = vec![0; reader.output_buffer_size().ok_or("PNG: too large")?];
                let info = reader.next_frame(&mut data).map_err(|e| format!("PNG: {e}"))?;
                data.truncate(info.buffer_size());
                let channels = info.color_type.samples();
                Ok(Some(Self { width: info.width, height: info.height, channels, data }))
            }
            TileFormat::Webp => {
                let mut decoder =
                    image_webp::WebPDecoder::new(std::io::Cursor::new(bytes)).map_err(|e| format!("WebP: {e}"))?;
                let (width, height) = decoder.dimensions();
                let channels = if decoder.has_alpha() { 4 } else { 3 };
                let mut data = vec![0; decoder.output_buffer_size().ok_or("WebP: too large")?];
                decoder.read_image(&mut data).map_err(|e| format!("WebP: {e}"))?;
                Ok(Some(Self { width, height, channels, data }))
            }
            _ => Ok(None),
        }
    }

    /// The index of the alpha channel, if the pixels have one.
    pub(crate) fn alpha(&self) -> Option<usize> {
        matches!(self.channels, 2 | 4).then_some(self.channels - 1)
    }
}
