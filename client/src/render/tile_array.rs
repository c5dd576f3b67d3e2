//! A layer's tiles on the GPU: one texture array, its slots and what each holds.

use bytemuck::Zeroable;
use terrastream_format::{Layer, TileFormat, TileKey};
use terrastream_tiles::TileData;

use super::frame::LodInfo;
use super::gpu::{self, write_layer};
use super::residency::{KIND_ELEVATION, Residency};

/// What an elevation texel holds where the data has none (the shader tests for it).
const NODATA: f32 = -1.0e30;

/// One layer's texture array and its residency.
pub(super) struct TileArray {
    pub(super) layer: Layer,
    pub(super) index: u8,
    pub(super) kind: u32,
    pub(super) texture: wgpu::Texture,
    /// Elevation only: each sample's normal, and whether it lies in a flat sea, made at
    /// upload ([`shade_texels`]); the same slots as `texture`.
    pub(super) shade: Option<wgpu::Texture>,
    pub(super) format: wgpu::TextureFormat,
    pub(super) edge: u32,
    pub(super) residency: Residency,
    pub(super) bytes: u64,
}

impl TileArray {
    pub(super) fn new(
        device: &wgpu::Device,
        index: u8,
        layer: &Layer,
        kind: u32,
        slots: u32,
        bc: bool,
    ) -> Option<Self> {
        let edge = layer.tile_resolution + 2 * u32::from(layer.border);
        let (format, texel_bytes) = match (kind, layer.format) {
            // Heights, and their shade texels beside them.
            (KIND_ELEVATION, _) => (wgpu::TextureFormat::R32Float, 8.0),
            (_, TileFormat::Bc1) if bc => (wgpu::TextureFormat::Bc1RgbaUnormSrgb, 0.5),
            (_, TileFormat::Bc7) if bc => (wgpu::TextureFormat::Bc7RgbaUnormSrgb, 1.0),
            (_, TileFormat::Bc1 | TileFormat::Bc7) => {
                tracing::warn!(layer = %layer.name, "the adapter has no BC texture support: layer not drawn");
                return None;
            }
            _ => (wgpu::TextureFormat::Rgba8UnormSrgb, 4.0),
        };
        let max_layers = device.limits().max_texture_array_layers;
        let slots = slots.clamp(1, max_layers);
        let texture = gpu::texture(
            device,
            if kind == KIND_ELEVATION { "texture.tiles.elevation" } else { "texture.tiles.colour" },
            (edge, edge, slots),
            format,
            wgpu::TextureUsages::TEXTURE_BINDING | wgpu::TextureUsages::COPY_DST,
        );
        let shade = (kind == KIND_ELEVATION).then(|| {
            gpu::texture(
                device,
                "texture.tiles.elevation_shade",
                (edge, edge, slots),
                SHADE_FORMAT,
                wgpu::TextureUsages::TEXTURE_BINDING | wgpu::TextureUsages::COPY_DST,
            )
        });
        #[allow(clippy::cast_possible_truncation, clippy::cast_sign_loss)]
        let bytes = (f64::from(edge) * f64::from(edge) * texel_bytes * f64::from(slots)) as u64;
        let residency = Residency::new(slots);
        Some(Self { layer: layer.clone(), index, kind, texture, shade, format, edge, residency, bytes })
    }

    /// Writes decoded tile `key` into `slot`; false if its size or kind does not fit.
    pub(super) fn write(&self, queue: &wgpu::Queue, slot: u32, key: TileKey, data: &TileData, size: u32) -> bool {
        if size != self.edge {
            return false;
        }
        let converted;
        let (bytes, bytes_per_row, rows): (&[u8], u32, u32) = match (data, self.format) {
            (TileData::Heights { heights, .. }, wgpu::TextureFormat::R32Float) => {
                converted = heights.iter().map(|h| if h.is_finite() { *h } else { NODATA }).collect::<Vec<f32>>();
                if let Some(shade) = &self.shade {
                    #[allow(clippy::cast_possible_truncation)]
                    let spacing = (self.layer.world_size_at(key.lod()) / f64::from(self.layer.tile_resolution)) as f32;
                    let texels = shade_texels(&converted, size as usize, spacing);
                    write_layer(queue, shade, slot, bytemuck::cast_slice(&texels), (size * 4, size), (size, size));
                }
                (bytemuck::cast_slice(&converted), size * 4, size)
            }
            (TileData::Rgba8(pixels), wgpu::TextureFormat::Rgba8UnormSrgb) => (pixels, size * 4, size),
            (TileData::Compressed { format, blocks }, f) => {
                let block_bytes = match (format, f) {
                    (TileFormat::Bc1, wgpu::TextureFormat::Bc1RgbaUnormSrgb) => 8,
                    (TileFormat::Bc7, wgpu::TextureFormat::Bc7RgbaUnormSrgb) => 16,
                    _ => return false,
                };
                (blocks, size.div_ceil(4) * block_bytes, size.div_ceil(4))
            }
            _ => return false,
        };
        if bytes.len() < (bytes_per_row as usize) * (rows as usize) {
            return false;
        }
        write_layer(queue, &self.texture, slot, bytes, (bytes_per_row, rows), (size, size));
        true
    }

    pub(super) fn shader_info(&self) -> [f32; 4] {
        #[allow(clippy::cast_precision_loss)]
        let spacing = self.layer.tile_world_size / f64::from(self.layer.tile_resolution);
        #[allow(clippy::cast_possible_truncation)]
        [self.layer.tile_resolution as f32, f32::from(self.layer.border), self.edge as f32, spacing as f32]
    }

    /// Per-LOD tile index and fraction of the anchor.
    pub(super) fn lods(&self, anchor: (f64, f64)) -> [LodInfo; 32] {
        let mut out = [LodInfo::zeroed(); 32];
        for (lod, info) in out.iter_mut().enumerate().take(usize::from(self.layer.num_lods)) {
            let size = self.layer.world_size_at(u8::try_from(lod).unwrap_or(u8::MAX));
            let (qx, qz) = (anchor.0 / size, anchor.1 / size);
            #[allow(clippy::cast_possible_truncation)]
            {
                *info = LodInfo {
                    tile: [qx.floor() as i32, qz.floor() as i32, 0, 0],
                    frac: [(qx - qx.floor()) as f32, (qz - qz.floor()) as f32, (1.0 / size) as f32, size as f32],
                };
            }
        }
        out
    }
}

/// The format of an elevation tile's shade texels: filterable everywhere (WebGL2 too).
pub(super) const SHADE_FORMAT: wgpu::TextureFormat = wgpu::TextureFormat::Rgba8Snorm;

/// The shade texels of an `edge` x `edge` tile of heights (NODATA where none) whose samples
/// lie `spacing` metres apart: for each sample, x and z of the terrain's normal there (y is
/// the rest of a unit vector), made as the lit shader made it from the four neighbours,
/// `normalize(h west - h east, 2 spacing, h north - h south)`; then 1 where the sample and
/// its four neighbours are one height within half a metre of 0 (a flat sea, as SRTM and
/// Copernicus store it), and 1 where the sample and its four neighbours have data (the
/// normal is there), else 0: along the tile's outermost samples, whose neighbours lie in
/// other tiles, and beside no data. Filtered bilinearly, one sample gives what twelve
/// height loads gave a pixel (the shader falls back to them where the last is under 1).
pub(super) fn shade_texels(heights: &[f32], edge: usize, spacing: f32) -> Vec<[i8; 4]> {
    let mut out = vec![[0i8; 4]; edge * edge];
    let has = |h: f32| h > NODATA * 0.5;
    #[allow(clippy::cast_possible_truncation)]
    let snorm = |v: f32| (v.clamp(-1.0, 1.0) * 127.0).round() as i8;
    for y in 1..edge.saturating_sub(1) {
        for x in 1..edge - 1 {
            let h = heights[y * edge + x];
            let (w, e) = (heights[y * edge + x - 1], heights[y * edge + x + 1]);
            let (n, s) = (heights[(y - 1) * edge + x], heights[(y + 1) * edge + x]);
            if !(has(h) && has(w) && has(e) && has(n) && has(s)) {
                continue;
            }
            let (gx, gz) = (w - e, n - s);
            let scale = 1.0 / (gx * gx + 4.0 * spacing * spacing + gz * gz).sqrt();
            let sea = h.abs() < 0.5 && w == h && e == h && n == h && s == h;
            out[y * edge + x] = [snorm(gx * scale), snorm(gz * scale), if sea { 127 } else { 0 }, 127];
        }
    }
    out
}

/// A view of a layer's tile array, or of a 1x1 dummy of `format` standing in for a missing
/// layer, so that one pipeline serves all archives.
pub(super) fn array_view(
    device: &wgpu::Device,
    array: Option<&wgpu::Texture>,
    format: wgpu::TextureFormat,
) -> wgpu::TextureView {
    let dummy;
    let texture = match array {
        Some(a) => a,
        None => {
            dummy = gpu::texture(device, "texture.tiles.none", (1, 1, 1), format, wgpu::TextureUsages::TEXTURE_BINDING);
            &dummy
        }
    };
    texture.create_view(&wgpu::TextureViewDescriptor {
        label: Some("view.tiles"),
        dimension: Some(wgpu::TextureViewDimension::D2Array),
        ..Default::default()
    })
}

#[cfg(test)]
mod tests {
    #![allow(clippy::unwrap_used, clippy::cast_precision_loss)]
    use super::*;

    #[test]
    fn shade_texels_hold_the_lit_shaders_normal_and_sea() {
        let edge = 9;
        let spacing = 30.0;
        // A slope with a bump, a flat sea at 0 in the south-west, a hole of no data.
        let mut h: Vec<f32> = (0..edge * edge)
            .map(|i| {
                let (x, y) = ((i % edge) as f32, (i / edge) as f32);
                if x < 4.0 && y > 4.0 { 0.0 } else { 3.0 * x * x - 40.0 * y + 5.0 }
            })
            .collect();
        h[2 * edge + 6] = NODATA;
        let texels = shade_texels(&h, edge, spacing);
        let at = |x: usize, y: usize| h[y * edge + x];
        for y in 0..edge {
            for x in 0..edge {
                let t = texels[y * edge + x];
                let rim = x == 0 || y == 0 || x == edge - 1 || y == edge - 1;
                let beside_hole = x.abs_diff(6) + y.abs_diff(2) <= 1;
                if rim || beside_hole {
                    assert_eq!(t, [0; 4], "({x}, {y}) has no normal");
                    continue;
                }
                assert_eq!(t[3], 127, "({x}, {y}) has a normal");
                let (gx, gz) = (at(x - 1, y) - at(x + 1, y), at(x, y - 1) - at(x, y + 1));
                let len = (gx * gx + 4.0 * spacing * spacing + gz * gz).sqrt();
                let (nx, nz) = (f32::from(t[0]) / 127.0, f32::from(t[1]) / 127.0);
                assert!((nx - gx / len).abs() <= 0.5 / 127.0 && (nz - gz / len).abs() <= 0.5 / 127.0, "({x}, {y})");
                let sea = x < 3 && y > 5 && y < edge - 1;
                assert_eq!(t[2], if sea { 127 } else { 0 }, "({x}, {y}) sea {sea}");
            }
        }
    }
}
