//! Image tiles (PNG, JPEG, WebP) decoded to their samples: 1 to 4 channels of 8 or 16
//! bits, checked against what the decoder says, never trusted.

use terrastream_format::{ElevationScheme, TileFormat};

/// A decoded image: 1 to 4 channels (gray, gray + alpha, RGB, RGBA) of 8 or 16 bits.
#[derive(Clone, Debug)]
pub struct Image {
    width: u32,
    height: u32,
    channels: usize,
    sixteen: bool,
    data: Vec<u8>,
}

impl Image {
    /// An image whose `data` holds exactly `width` x `height` pixels of `channels` (1 to 4)
    /// samples of 8 or 16 bits: what a decoder hands back is checked, never trusted, so
    /// the sample accessors below cannot index out of bounds.
    fn new(
        what: &str,
        (width, height): (u32, u32),
        channels: usize,
        sixteen: bool,
        data: Vec<u8>,
    ) -> Result<Self, String> {
        let expected = u64::from(width) * u64::from(height) * channels as u64 * if sixteen { 2 } else { 1 };
        if !(1..=4).contains(&channels) || data.len() as u64 != expected {
            return Err(format!(
                "{what}: {} bytes for {width}x{height} pixels of {channels} channel(s){}",
                data.len(),
                if sixteen { " of 16 bits" } else { "" }
            ));
        }
        Ok(Self { width, height, channels, sixteen, data })
    }

    /// Decodes a PNG, JPEG or WebP image (`format` says which).
    ///
    /// # Errors
    /// Why the bytes are not an image of their format, naming it.
    pub fn decode(format: TileFormat, bytes: &[u8]) -> Result<Self, String> {
        decode_image(format, bytes)
    }

    /// Pixels a row.
    pub fn width(&self) -> u32 {
        self.width
    }

    /// Rows.
    pub fn height(&self) -> u32 {
        self.height
    }

    /// Samples a pixel: 1 gray, 2 gray + alpha, 3 RGB, 4 RGBA.
    pub fn channels(&self) -> usize {
        self.channels
    }

    /// The index of the alpha channel, if the pixels have one.
    pub fn alpha(&self) -> Option<usize> {
        matches!(self.channels, 2 | 4).then_some(self.channels - 1)
    }

    /// The samples, row-major, `channels` a pixel, each one byte (8-bit images) or two
    /// big-endian bytes (16-bit).
    pub fn data(&self) -> &[u8] {
        &self.data
    }

    /// The image with 8-bit samples: a 16-bit image keeps each sample's high byte (as
    /// PNG's `STRIP_16` does); an 8-bit image is returned as it is.
    pub fn into_eight_bit(self) -> Self {
        if !self.sixteen {
            return self;
        }
        let data = self.data.chunks_exact(2).map(|c| c[0]).collect();
        Self { data, sixteen: false, ..self }
    }

    fn sample(&self, pixel: usize, channel: usize) -> u32 {
        let c = channel.min(self.channels - 1);
        if self.sixteen {
            let i = (pixel * self.channels + c) * 2;
            u32::from(u16::from_be_bytes([self.data[i], self.data[i + 1]]))
        } else {
            u32::from(self.data[pixel * self.channels + c])
        }
    }

    fn pixels(&self) -> usize {
        self.width as usize * self.height as usize
    }

    /// The pixels as 8-bit RGBA (gray spread to RGB, opaque without alpha).
    pub fn rgba8(&self) -> Vec<u8> {
        let mut out = Vec::with_capacity(self.pixels() * 4);
        let eight = |v: u32| u8::try_from(if self.sixteen { v >> 8 } else { v }).unwrap_or(u8::MAX);
        for p in 0..self.pixels() {
            let (r, g, b, a) = match self.channels {
                1 => (0, 0, 0, None),
                2 => (0, 0, 0, Some(1)),
                3 => (0, 1, 2, None),
                _ => (0, 1, 2, Some(3)),
            };
            out.extend_from_slice(&[
                eight(self.sample(p, r)),
                eight(self.sample(p, g)),
                eight(self.sample(p, b)),
                a.map_or(255, |a| eight(self.sample(p, a))),
            ]);
        }
        out
    }

    /// The raw value an elevation scheme reads from each pixel (NaN, no data, where the
    /// pixel is transparent: tile trees cut from a DEM leave its surroundings so).
    pub(crate) fn values(&self, scheme: ElevationScheme) -> Result<Vec<f64>, String> {
        let colour = self.channels >= 3;
        let (r, g, b) = (0, if colour { 1 } else { 0 }, if colour { 2 } else { 0 });
        let alpha = matches!(self.channels, 2 | 4).then_some(self.channels - 1);
        let value = |p: usize| -> f64 {
            if alpha.is_some_and(|a| self.sample(p, a) == 0) {
                return f64::NAN;
            }
            let (rv, gv, bv) =
                (f64::from(self.sample(p, r)), f64::from(self.sample(p, g)), f64::from(self.sample(p, b)));
            scheme.value(rv, gv, bv)
        };
        match scheme {
            _ if scheme.needs_rgb() && !colour => {
                Err(format!("{scheme:?} needs an RGB image, this one has {} channel(s)", self.channels))
            }
            ElevationScheme::Gray8
            | ElevationScheme::RgbThirds
            | ElevationScheme::TerrainRgb
            | ElevationScheme::Terrarium
                if self.sixteen =>
            {
                Err(format!("{scheme:?} needs an 8-bit image, this one is 16-bit"))
            }
            _ => Ok((0..self.pixels()).map(value).collect()),
        }
    }
}

fn decode_image(format: TileFormat, bytes: &[u8]) -> Result<Image, String> {
    match format {
        TileFormat::Png => {
            let mut decoder = png::Decoder::new(std::io::Cursor::new(bytes));
            decoder.set_transformations(png::Transformations::EXPAND);
            let mut reader = decoder.read_info().map_err(|e| format!("PNG: {e}"))?;
            let mut data = vec![0; reader.output_buffer_size().ok_or("PNG: too large")?];
            let info = reader.next_frame(&mut data).map_err(|e| format!("PNG: {e}"))?;
            data.truncate(info.buffer_size());
            let sixteen = info.bit_depth == png::BitDepth::Sixteen;
            Image::new("PNG", (info.width, info.height), info.color_type.samples(), sixteen, data)
        }
        TileFormat::Jpeg => {
            let options = zune_jpeg::zune_core::options::DecoderOptions::default()
                .jpeg_set_out_colorspace(zune_jpeg::zune_core::colorspace::ColorSpace::RGB);
            let mut decoder = zune_jpeg::JpegDecoder::new_with_options(bytes, options);
            let data = decoder.decode().map_err(|e| format!("JPEG: {e:?}"))?;
            let (w, h) = decoder.dimensions().ok_or("JPEG: no dimensions")?;
            let dim = |n: usize| u32::try_from(n).map_err(|_| "JPEG: too large".to_owned());
            // Colour JPEGs (YCbCr, CMYK, YCCK) come out as RGB; a one-component (gray)
            // JPEG stays one channel whatever colour space was asked for.
            let channels = match decoder.get_output_colorspace() {
                Some(space) => space.num_components(),
                None => 3,
            };
            Image::new("JPEG", (dim(w)?, dim(h)?), channels, false, data)
        }
        TileFormat::Webp => {
            let mut decoder =
                image_webp::WebPDecoder::new(std::io::Cursor::new(bytes)).map_err(|e| format!("WebP: {e}"))?;
            let (width, height) = decoder.dimensions();
            let channels = if decoder.has_alpha() { 4 } else { 3 };
            let mut data = vec![0; decoder.output_buffer_size().ok_or("WebP: too large")?];
            decoder.read_image(&mut data).map_err(|e| format!("WebP: {e}"))?;
            Image::new("WebP", (width, height), channels, false, data)
        }
        other => Err(format!("{other:?} is not an image format")),
    }
}
