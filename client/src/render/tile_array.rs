//! A layer's tiles on the GPU: one texture array, its slots and what each holds.

use bytemuck::Zeroable;
use terrastream_format::{Layer, TileFormat, TileKey};

use super::atmosphere::{fill, fullscreen};
use super::gpu::{texture_entry, uniform_entry};
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
    /// Elevation only: each sample's normal, and whether it lies in a flat sea, made on
    /// the GPU at upload (shaders/shade.wgsl); the same slots as `texture`.
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
                wgpu::TextureUsages::TEXTURE_BINDING | wgpu::TextureUsages::RENDER_ATTACHMENT,
            )
        });
        #[allow(clippy::cast_possible_truncation, clippy::cast_sign_loss)]
        let bytes = (f64::from(edge) * f64::from(edge) * texel_bytes * f64::from(slots)) as u64;
        let residency = Residency::new(slots);
        Some(Self { layer: layer.clone(), index, kind, texture, shade, format, edge, residency, bytes })
    }

    /// Writes a decoded tile into `slot`; false if its size or kind does not fit.
    pub(super) fn write(&self, queue: &wgpu::Queue, slot: u32, data: &TileData, size: u32) -> bool {
        if size != self.edge {
            return false;
        }
        let converted;
        let (bytes, bytes_per_row, rows): (&[u8], u32, u32) = match (data, self.format) {
            (TileData::Heights { heights, .. }, wgpu::TextureFormat::R32Float) => {
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

/// The pass that makes elevation tiles' shade texels (shaders/shade.wgsl), made with the
/// terrain's pipelines.
#[derive(Clone, Debug)]
pub struct ShadePipeline {
    layout: wgpu::BindGroupLayout,
    pipeline: wgpu::RenderPipeline,
}

impl ShadePipeline {
    pub(super) fn new(device: &wgpu::Device) -> Self {
        let layout = device.create_bind_group_layout(&wgpu::BindGroupLayoutDescriptor {
            label: Some("layout.shade"),
            entries: &[
                texture_entry(
                    0,
                    wgpu::TextureSampleType::Float { filterable: false },
                    wgpu::TextureViewDimension::D2Array,
                ),
                uniform_entry(1),
            ],
        });
        let module = gpu::shader(device, "shade", include_str!("../../../shaders/shade.wgsl"));
        let pipeline = fullscreen(device, "shade", &module, &layout, ("vs_main", "fs_shade"), SHADE_FORMAT, false);
        Self { layout, pipeline }
    }

    /// Makes the shade texels of elevation tiles `tiles` (their keys and slots), just
    /// written into `array`, on the GPU.
    pub(super) fn make(&self, device: &wgpu::Device, queue: &wgpu::Queue, array: &TileArray, tiles: &[(TileKey, u32)]) {
        let Some(shade) = &array.shade else { return };
        if tiles.is_empty() {
            return;
        }
        let heights = array_view(device, Some(&array.texture), array.format);
        let mut encoder =
            device.create_command_encoder(&wgpu::CommandEncoderDescriptor { label: Some("encoder.shade") });
        for &(key, slot) in tiles {
            #[allow(clippy::cast_possible_truncation)]
            let spacing = (array.layer.world_size_at(key.lod()) / f64::from(array.layer.tile_resolution)) as f32;
            let job: [u32; 4] = [slot, spacing.to_bits(), array.edge, 0];
            let buffer = wgpu::util::DeviceExt::create_buffer_init(
                device,
                &wgpu::util::BufferInitDescriptor {
                    label: Some("buffer.shade.job"),
                    contents: bytemuck::cast_slice(&job),
                    usage: wgpu::BufferUsages::UNIFORM,
                },
            );
            let group = gpu::bind_group(
                device,
                "bind_group.shade",
                &self.layout,
                &[wgpu::BindingResource::TextureView(&heights), buffer.as_entire_binding()],
            );
            let target = shade.create_view(&wgpu::TextureViewDescriptor {
                label: Some("view.shade.layer"),
                dimension: Some(wgpu::TextureViewDimension::D2),
                base_array_layer: slot,
                array_layer_count: Some(1),
                ..Default::default()
            });
            fill(&mut encoder, &target, &self.pipeline, &group);
        }
        queue.submit([encoder.finish()]);
    }
}

/// The format of an elevation tile's shade texels (shaders/shade.wgsl): filterable and
/// renderable everywhere (WebGL2 too).
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
