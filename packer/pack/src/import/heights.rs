//! The height range of an elevation pyramid, read from its tiles (Terrain-RGB, Terrarium,
//! gray): a pyramid's files say nothing of it, and readers frame and cull by it.

#[cfg(test)]
use terrastream_format::TileFormat;
use terrastream_format::{ElevationEncoding, Metadata};

use super::pixels::Pixels;

/// The lowest and highest height seen, over any number of tiles.
#[derive(Clone, Copy, Debug, Default, PartialEq)]
pub struct HeightRange {
    /// Lowest and highest height, `None` before any sample.
    pub range: Option<(f64, f64)>,
}

impl HeightRange {
    /// Widens the range by another.
    pub fn merge(self, other: Self) -> Self {
        match (self.range, other.range) {
            (Some(a), Some(b)) => Self { range: Some((a.0.min(b.0), a.1.max(b.1))) },
            (a, b) => Self { range: a.or(b) },
        }
    }

    /// Writes the range into the metadata's terrain (kept as it was when no sample was seen).
    pub fn record(self, metadata: &mut Metadata) {
        if let Some((lo, hi)) = self.range {
            let t = &mut metadata.terrain;
            (t.min_elevation, t.max_elevation) = (lo, hi);
            t.elevation_range = hi - lo;
        }
    }
}

/// The heights of one image tile of an elevation layer (pixels with alpha 0 are no data).
#[cfg(test)]
fn tile_heights(format: TileFormat, bytes: &[u8], encoding: &ElevationEncoding) -> Result<HeightRange, String> {
    Ok(super::pixels::decode(format, bytes)?.map(|p| pixel_heights(&p, encoding)).transpose()?.unwrap_or_default())
}

/// The heights of a decoded elevation tile (pixels with alpha 0 are no data).
pub(crate) fn pixel_heights(pixels: &Pixels, encoding: &ElevationEncoding) -> Result<HeightRange, String> {
    let (channels, scheme) = (pixels.channels(), encoding.scheme);
    if scheme.needs_rgb() && channels < 3 {
        return Err(format!("{scheme:?} needs an RGB image, this one has {channels} channel(s)"));
    }
    let alpha = pixels.alpha();
    let mut range: Option<(f64, f64)> = None;
    for px in pixels.data().chunks_exact(channels) {
        if alpha.is_some_and(|a| px[a] == 0) {
            continue;
        }
        let (r, g, b) = if channels >= 3 { (px[0], px[1], px[2]) } else { (px[0], px[0], px[0]) };
        let v = scheme.value(f64::from(r), f64::from(g), f64::from(b));
        if encoding.nodata == Some(v) {
            continue;
        }
        let h = encoding.height(v);
        range = Some(range.map_or((h, h), |(lo, hi)| (lo.min(h), hi.max(h))));
    }
    Ok(HeightRange { range })
}

#[cfg(test)]
mod tests {
    use terrastream_format::ElevationScheme;

    use super::*;

    fn terrarium_png(heights: &[f64], alpha: bool) -> Vec<u8> {
        let mut data = Vec::new();
        for &h in heights {
            let v = h + 32_768.0;
            #[expect(clippy::cast_possible_truncation, clippy::cast_sign_loss, reason = "test heights in range")]
            let (r, g, b) = ((v / 256.0).floor() as u8, (v % 256.0).floor() as u8, ((v.fract()) * 256.0) as u8);
            data.extend([r, g, b]);
            if alpha {
                data.push(if h < -1000.0 { 0 } else { 255 });
            }
        }
        let mut out = Vec::new();
        let mut encoder = png::Encoder::new(&mut out, 2, 2);
        encoder.set_color(if alpha { png::ColorType::Rgba } else { png::ColorType::Rgb });
        encoder.write_header().unwrap().write_image_data(&data).unwrap();
        out
    }

    #[test]
    fn terrarium_tiles_give_their_heights_and_transparent_pixels_none() {
        let encoding = ElevationEncoding { scheme: ElevationScheme::Terrarium, scale: 1.0, offset: 0.0, nodata: None };
        let a = tile_heights(TileFormat::Png, &terrarium_png(&[12.5, 300.0, -20.0, 4000.25], false), &encoding);
        assert_eq!(a.unwrap().range, Some((-20.0, 4000.25)));
        let b = tile_heights(TileFormat::Png, &terrarium_png(&[-5000.0, 10.0, 20.0, 30.0], true), &encoding);
        assert_eq!(b.unwrap().range, Some((10.0, 30.0)), "the transparent pixel is no data");
        assert!(tile_heights(TileFormat::Png, b"\x89PNG\r\n\x1a\nbroken", &encoding).is_err());
    }
}
