//! Heights as the pixels web maps read (Terrarium, Mapbox Terrain-RGB) and made tiles as
//! image files (lossless WebP or PNG).

/// How heights are packed into RGB.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash)]
pub enum HeightEncoding {
    /// Mapzen's Terrarium: `h = R * 256 + G + B / 256 - 32768` (steps of 1/256 m).
    Terrarium,
    /// Mapbox Terrain-RGB: `h = -10000 + (R * 65536 + G * 256 + B) * 0.1` (0.1 m steps).
    Mapbox,
}

impl HeightEncoding {
    /// The name TileJSON and MapLibre give it.
    pub fn name(self) -> &'static str {
        match self {
            Self::Terrarium => "terrarium",
            Self::Mapbox => "mapbox",
        }
    }

    /// The encoding of a name.
    pub fn parse(name: &str) -> Option<Self> {
        match name {
            "terrarium" => Some(Self::Terrarium),
            "mapbox" | "terrain-rgb" => Some(Self::Mapbox),
            _ => None,
        }
    }

    /// A height as RGB, rounded to the nearest step (not truncated: truncation would
    /// bias every height down by half a step), clamped to what the encoding holds.
    #[expect(clippy::cast_possible_truncation, clippy::cast_sign_loss, reason = "clamped to the encoding's range")]
    pub fn rgb(self, height: f32) -> [u8; 3] {
        let h = f64::from(height);
        let steps = match self {
            Self::Terrarium => (h + 32_768.0) * 256.0,
            Self::Mapbox => (h + 10_000.0) * 10.0,
        };
        // Half up, by adding a half and truncating a value clamped to be positive (`round`
        // would call the C library for every pixel); the same as `round` there.
        let v = (steps.clamp(0.0, 16_777_215.0) + 0.5) as u32;
        [(v >> 16) as u8, (v >> 8) as u8, v as u8]
    }

    /// The height an RGB pixel holds.
    pub fn height(self, [r, g, b]: [u8; 3]) -> f64 {
        let v = f64::from(u32::from(r) << 16 | u32::from(g) << 8 | u32::from(b));
        match self {
            Self::Terrarium => v / 256.0 - 32_768.0,
            Self::Mapbox => v / 10.0 - 10_000.0,
        }
    }

    /// Heights that all hold data as RGB pixels; None when one has no data.
    pub fn rgb_pixels(self, heights: &[f32]) -> Option<Vec<u8>> {
        if !heights.iter().all(|h| h.is_finite()) {
            return None;
        }
        let mut out = vec![0; heights.len() * 3];
        for (pixel, &h) in out.chunks_exact_mut(3).zip(heights) {
            let [r, g, b] = self.rgb(h);
            (pixel[0], pixel[1], pixel[2]) = (r, g, b);
        }
        Some(out)
    }

    /// Heights (NaN: no data) as RGBA pixels: no data is transparent (and holds 0 m).
    pub fn pixels(self, heights: &[f32]) -> Vec<u8> {
        let mut out = Vec::with_capacity(heights.len() * 4);
        for &h in heights {
            if h.is_finite() {
                let [r, g, b] = self.rgb(h);
                out.extend_from_slice(&[r, g, b, 255]);
            } else {
                let [r, g, b] = self.rgb(0.0);
                out.extend_from_slice(&[r, g, b, 0]);
            }
        }
        out
    }
}

/// The image format of a made tile.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash)]
pub enum ImageFormat {
    /// Lossless WebP: about two thirds of the PNG's bytes for terrain.
    Webp,
    /// PNG.
    Png,
}

impl ImageFormat {
    /// The file extension.
    pub fn extension(self) -> &'static str {
        match self {
            Self::Webp => "webp",
            Self::Png => "png",
        }
    }

    /// The media type.
    pub fn media_type(self) -> &'static str {
        match self {
            Self::Webp => "image/webp",
            Self::Png => "image/png",
        }
    }

    /// The format of an extension.
    pub fn parse(extension: &str) -> Option<Self> {
        match extension {
            "webp" => Some(Self::Webp),
            "png" => Some(Self::Png),
            _ => None,
        }
    }

    /// `rgba` (`size` x `size` pixels) as a file of this format; opaque tiles are
    /// written as RGB.
    ///
    /// # Errors
    /// The encoder's message.
    pub fn encode(self, rgba: &[u8], size: u32) -> Result<Vec<u8>, String> {
        if rgba.chunks_exact(4).all(|p| p[3] == 255) {
            let rgb: Vec<u8> = rgba.chunks_exact(4).flat_map(|p| [p[0], p[1], p[2]]).collect();
            return self.encode_raw(&rgb, size, Layout::Rgb);
        }
        self.encode_raw(rgba, size, Layout::Rgba)
    }

    /// `gray_alpha` (`size` x `size`, two bytes a pixel: gray and alpha) as a file of this
    /// format: a gray image, with alpha only where some pixel is not opaque (a third of
    /// the bytes of RGB for the encoder to go through).
    ///
    /// # Errors
    /// The encoder's message.
    pub fn encode_gray(self, gray_alpha: &[u8], size: u32) -> Result<Vec<u8>, String> {
        if gray_alpha.chunks_exact(2).any(|p| p[1] != 255) {
            return self.encode_raw(gray_alpha, size, Layout::GrayAlpha);
        }
        let gray: Vec<u8> = gray_alpha.iter().step_by(2).copied().collect();
        self.encode_raw(&gray, size, Layout::Gray)
    }

    /// `pixels` (`size` x `size`, laid out as `layout` says) as a file of this format.
    ///
    /// # Errors
    /// The encoder's message.
    pub fn encode_raw(self, pixels: &[u8], size: u32, layout: Layout) -> Result<Vec<u8>, String> {
        let mut out = Vec::new();
        match self {
            Self::Png => {
                let mut encoder = png::Encoder::new(&mut out, size, size);
                encoder.set_color(match layout {
                    Layout::Gray => png::ColorType::Grayscale,
                    Layout::GrayAlpha => png::ColorType::GrayscaleAlpha,
                    Layout::Rgb => png::ColorType::Rgb,
                    Layout::Rgba => png::ColorType::Rgba,
                });
                encoder.set_depth(png::BitDepth::Eight);
                encoder.set_compression(png::Compression::Fast);
                let mut writer = encoder.write_header().map_err(|e| e.to_string())?;
                writer.write_image_data(pixels).map_err(|e| e.to_string())?;
            }
            Self::Webp => {
                let colour = match layout {
                    Layout::Gray => image_webp::ColorType::L8,
                    Layout::GrayAlpha => image_webp::ColorType::La8,
                    Layout::Rgb => image_webp::ColorType::Rgb8,
                    Layout::Rgba => image_webp::ColorType::Rgba8,
                };
                image_webp::WebPEncoder::new(&mut out).encode(pixels, size, size, colour).map_err(|e| e.to_string())?;
            }
        }
        Ok(out)
    }
}

/// How an image's bytes hold its pixels: 8 bits a channel.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Layout {
    /// One byte a pixel.
    Gray,
    /// Gray, then alpha.
    GrayAlpha,
    /// Red, green, blue.
    Rgb,
    /// Red, green, blue, alpha.
    Rgba,
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn heights_round_trip_to_the_step_by_rounding() {
        for enc in [HeightEncoding::Terrarium, HeightEncoding::Mapbox] {
            let step = if enc == HeightEncoding::Terrarium { 1.0 / 256.0 } else { 0.1 };
            for h in [-432.17_f32, -0.04, 0.0, 0.04, 12.3456, 784.9, 4_808.33, 8_848.86] {
                let back = enc.height(enc.rgb(h));
                assert!((back - f64::from(h)).abs() <= step / 2.0 + 1e-6, "{enc:?} {h} -> {back}");
            }
        }
        // Rounding, not truncation: 0.06 m is 0.1 in Terrain-RGB, not 0.0.
        assert!((HeightEncoding::Mapbox.height(HeightEncoding::Mapbox.rgb(0.06)) - 0.1).abs() < 1e-9);
        assert_eq!(HeightEncoding::Terrarium.rgb(0.0), [128, 0, 0]);
        assert_eq!(HeightEncoding::Mapbox.rgb(0.0), [1, 134, 160]);
    }
}
