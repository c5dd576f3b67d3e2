//! A layer's tiles on the GPU: one texture array, its slots and what each holds.

use bytemuck::Zeroable;
use terrastream_format::{Layer, TileFormat, TileKey};

use terrastream_tiles::{TileData, shade_texels};

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
    /// Elevation only: each sample's normal, and whether it lies in a flat sea (the
    /// decoded tile's shade texels, [`terrastream_tiles::DecodedTile::shade`]); the same
    /// slots as `texture`.
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
            (TileData::Heights { heights, shade, .. }, wgpu::TextureFormat::R32Float) => {
                if let Some(array) = &self.shade {
                    let made;
                    let texels = match shade {
                        Some(texels) if texels.len() == heights.len() * 4 => texels,
                        // A tile decoded without them (a streamer told not to make them):
                        // made here, on the frame's thread.
                        _ => {
                            #[allow(clippy::cast_possible_truncation)]
                            let spacing = self.layer.sample_spacing(key.lod()) as f32;
                            made = shade_texels(heights, size as usize, spacing);
                            &made
                        }
                    };
                    if texels.len() < (size * size * 4) as usize {
                        return false;
                    }
                    write_layer(queue, array, slot, texels, (size * 4, size), (size, size));
                }
                converted = heights.iter().map(|h| if h.is_finite() { *h } else { NODATA }).collect::<Vec<f32>>();
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
        let spacing = self.layer.sample_spacing(0);
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
pub(super) const SHADE_FORMAT: wgpu::TextureFormat = wgpu::TextureFormat::Rgba8Unorm;

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
