//! An elevation tile's shade texels: what the renderer's lit shader reads for a pixel's
//! normal and whether it lies in a flat sea, made once per tile where the tile is decoded
//! (a worker thread, or a browser's Web Worker), never on the frame's thread.
//!
//! For each sample, four bytes (`Rgba8Unorm` on the GPU):
//! - x and z of the terrain's normal there (y is the rest of a unit vector), stored as
//!   `n * 0.5 + 0.5`, from the four neighbours: `normalize(h west - h east, 2 spacing,
//!   h north - h south)`. Beside the tile's outermost samples (whose neighbours lie in the
//!   next tile) and the data's edge the difference is one-sided, doubled; with neither
//!   neighbour, 0.
//! - 1 where the sample and its four neighbours are one height within half a metre of 0
//!   (a flat sea, as SRTM and Copernicus store it). Neighbours past the tile's rim or the
//!   data are left out of that test, or every tile's rim would draw a line of land across
//!   the sea.
//! - 1 where the sample has data (the normal is there), else 0.
//!
//! Where the archive has a water layer, its tile of the same LOD, x and y says where the
//! water is ([`DecodedTile::set_water`]): the sea byte is then its fraction of water at
//! each sample it has data for (lakes at any height; land at 0 m stays land), the flat-0
//! rule only where it has none.
//!
//! Filtered bilinearly, one texel gives a pixel what twelve height loads gave it:
//! interpolation and the neighbours' differences commute.

use terrastream_format::{Layer, LayerKind};

use crate::decode::{DecodedTile, TileData};

/// The texel of a sample without data: a level normal, no sea, no data.
const NONE: [u8; 4] = [128, 128, 0, 0];

impl DecodedTile {
    /// Makes the shade texels of an elevation tile of `layer` (see the module), where it
    /// has none; other tiles are left as they are.
    pub fn shade(&mut self, layer: &Layer) {
        if layer.kind != LayerKind::Elevation {
            return;
        }
        let size = self.size;
        let TileData::Heights { heights, shade, .. } = &mut self.data else { return };
        if shade.is_some() {
            return;
        }
        #[expect(clippy::cast_possible_truncation, reason = "a sample's spacing in metres fits an f32")]
        let spacing = layer.sample_spacing(self.key.lod()) as f32;
        *shade = Some(shade_texels(heights, size as usize, spacing));
    }
}

impl DecodedTile {
    /// Takes the sea byte of this elevation tile's shade texels from `water`, the water
    /// layer's tile of the same LOD, x and y (its samples the fraction of water, NaN where
    /// it has none): the fraction where it has one, the flat-0 rule elsewhere. The shade
    /// texels are made first where the tile has none. A tile of another size, or one that
    /// is not heights, changes nothing.
    pub fn set_water(&mut self, layer: &Layer, water: &DecodedTile) {
        let TileData::Heights { heights: fractions, .. } = &water.data else { return };
        if water.size != self.size {
            return;
        }
        self.shade(layer);
        let TileData::Heights { shade: Some(shade), .. } = &mut self.data else { return };
        for (texel, &f) in shade.chunks_exact_mut(4).zip(fractions) {
            if f.is_finite() {
                #[expect(clippy::cast_possible_truncation, clippy::cast_sign_loss, reason = "clamped to 0..=255")]
                let byte = (f.clamp(0.0, 1.0) * 255.0).round() as u8;
                texel[2] = byte;
            }
        }
    }
}

/// The shade texels (see the module) of `edge` x `edge` heights, row-major, NaN where
/// there is no data, whose samples lie `spacing` metres apart.
pub fn shade_texels(heights: &[f32], edge: usize, spacing: f32) -> Vec<u8> {
    let mut out = vec![0u8; edge * edge * 4];
    if heights.len() < edge * edge || edge == 0 {
        return out;
    }
    let two_spacing_squared = 4.0 * spacing * spacing;
    let row = |y: usize| &heights[y * edge..(y + 1) * edge];
    for (y, texels) in out.chunks_exact_mut(edge * 4).enumerate() {
        let (north, here, south) = ((y > 0).then(|| row(y - 1)), row(y), (y + 1 < edge).then(|| row(y + 1)));
        for (x, texel) in texels.chunks_exact_mut(4).enumerate() {
            let h = here[x];
            if !h.is_finite() {
                texel.copy_from_slice(&NONE);
                continue;
            }
            let w = if x > 0 { here[x - 1] } else { f32::NAN };
            let e = here.get(x + 1).copied().unwrap_or(f32::NAN);
            let (n, s) = (north.map_or(f32::NAN, |r| r[x]), south.map_or(f32::NAN, |r| r[x]));
            let (gx, gz) = (difference(w, h, e), difference(n, h, s));
            let scale = 1.0 / (gx * gx + two_spacing_squared + gz * gz).sqrt();
            let sea = flat_sea(h, [w, e, n, s]);
            texel.copy_from_slice(&[unorm(gx * scale), unorm(gz * scale), if sea { 255 } else { 0 }, 255]);
        }
    }
    out
}

/// Whether a sample of height `h` lies in a flat sea, as SRTM and Copernicus store the
/// sea: within half a metre of 0, and its `neighbours` (west, east, north, south) at the
/// same height. A neighbour without data (NaN), or past a grid's rim, is left out, or
/// every tile's rim and every coast beside missing data would draw a line of land.
pub fn flat_sea(h: f32, neighbours: [f32; 4]) -> bool {
    h.abs() < 0.5 && neighbours.iter().all(|&v| v == h || !v.is_finite())
}

/// The central difference `before - after` across a sample `h`; where one of them has no
/// data, the one-sided difference, doubled; where neither has, 0.
fn difference(before: f32, h: f32, after: f32) -> f32 {
    match (before.is_finite(), after.is_finite()) {
        (true, true) => before - after,
        (true, false) => 2.0 * (before - h),
        (false, true) => 2.0 * (h - after),
        (false, false) => 0.0,
    }
}

/// A component of a unit vector as a unorm byte, `v * 0.5 + 0.5` rounded.
fn unorm(v: f32) -> u8 {
    #[expect(clippy::cast_possible_truncation, clippy::cast_sign_loss, reason = "clamped to 0..=255")]
    let byte = ((v * 0.5 + 0.5) * 255.0).round().clamp(0.0, 255.0) as u8;
    byte
}

#[cfg(test)]
mod tests {
    use super::*;

    fn texel(t: &[u8], edge: usize, x: usize, y: usize) -> [u8; 4] {
        let i = (y * edge + x) * 4;
        [t[i], t[i + 1], t[i + 2], t[i + 3]]
    }

    #[test]
    fn a_slope_rising_east_leans_its_normal_west() {
        // h = 2 x on a 1 m grid: normal ∝ (-2, 1, 0) after the doubling, (w - e, 2, 0).
        let edge = 4;
        let heights: Vec<f32> = (0..edge * edge).map(|i| 2.0 * (i % edge) as f32 + 10.0).collect();
        let t = shade_texels(&heights, edge, 1.0);
        let expected = unorm(-4.0 / (16.0f32 + 4.0).sqrt());
        for y in 0..edge {
            for x in 0..edge {
                // The rim's one-sided differences, doubled, equal the interior's here.
                assert_eq!(texel(&t, edge, x, y), [expected, 128, 0, 255], "at {x},{y}");
            }
        }
    }

    #[test]
    fn no_data_is_no_normal_and_its_neighbours_take_one_sided_differences() {
        let edge = 3;
        let mut heights = vec![0.0f32; 9];
        heights[3] = f32::NAN; // west of the middle
        heights[5] = 4.0; // east of the middle
        let t = shade_texels(&heights, edge, 1.0);
        assert_eq!(texel(&t, edge, 0, 1), NONE);
        // Middle: one-sided (h - e) doubled = -8, vertical 0.
        let expected = unorm(-8.0 / (64.0f32 + 4.0).sqrt());
        assert_eq!(texel(&t, edge, 1, 1)[..2], [expected, 128]);
        assert_eq!(texel(&t, edge, 1, 1)[3], 255);
    }

    #[test]
    fn a_flat_zero_is_sea_up_to_the_rim_and_a_step_is_not() {
        let edge = 4;
        let mut heights = vec![0.0f32; 16];
        let t = shade_texels(&heights, edge, 30.0);
        assert!((0..16).all(|i| t[i * 4 + 2] == 255), "every sample of a flat 0 is sea, rims included");
        heights[5] = 0.25;
        let t = shade_texels(&heights, edge, 30.0);
        assert_eq!(texel(&t, edge, 1, 1)[2], 0, "the step itself");
        assert_eq!(texel(&t, edge, 2, 1)[2], 0, "beside the step");
        assert_eq!(texel(&t, edge, 3, 3)[2], 255, "away from it");
        heights.fill(3.0);
        assert!(shade_texels(&heights, edge, 30.0).chunks(4).all(|c| c[2] == 0), "flat land above 0.5 m");
    }

    #[test]
    fn a_water_tile_sets_the_sea_byte_where_it_has_data() {
        use terrastream_format::{ElevationEncoding, ElevationScheme, PayloadCompression, TileFormat, TileKey};
        let layer = Layer {
            name: "elevation".into(),
            kind: LayerKind::Elevation,
            format: TileFormat::RawF32,
            compression: PayloadCompression::None,
            tile_resolution: 2,
            border: 1,
            num_x_tiles: 1,
            num_y_tiles: 1,
            num_lods: 1,
            tile_world_size: 60.0,
            elevation: Some(ElevationEncoding {
                scheme: ElevationScheme::Float32,
                scale: 1.0,
                offset: 0.0,
                nodata: None,
            }),
            extent: None,
        };
        let key = TileKey::new(0, 0, 0, 0).unwrap();
        let tile = |heights: Vec<f32>| DecodedTile {
            key,
            size: 4,
            border: 1,
            data: TileData::Heights { heights, min: 0.0, max: 0.0, shade: None },
        };
        // A lake at 300 m in the first row, land at 0 m (a polder) in the second, and a
        // flat 0 in the last two rows, which the layer says nothing of.
        let mut heights = vec![300.0f32; 16];
        heights[4..8].fill(0.0);
        heights[8..].fill(0.0);
        let mut water = vec![0.0f32; 16];
        water[..4].fill(1.0);
        water[2] = 0.5;
        water[8..].fill(f32::NAN);
        let mut elevation = tile(heights);
        elevation.set_water(&layer, &tile(water));
        let TileData::Heights { shade: Some(shade), .. } = &elevation.data else { panic!("no shade") };
        let sea: Vec<u8> = shade.chunks(4).map(|t| t[2]).collect();
        assert_eq!(&sea[..4], &[255, 255, 128, 255], "the lake, its shore half water");
        assert_eq!(&sea[4..8], &[0; 4], "the polder at 0 m: land, as the layer says");
        assert_eq!(&sea[12..], &[255; 4], "where the layer says nothing: the sea by the flat-0 rule");
    }
}
