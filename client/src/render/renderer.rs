//! The wgpu terrain renderer. It never owns a window or a device: `new(&Device, ..)`,
//! `upload` (within the streaming core's per-frame budget), `prepare(camera)`, `draw(pass)`.

use std::collections::HashSet;

use bytemuck::{Pod, Zeroable};
use glam::{DMat4, DVec3, Mat4};
use terrastream_format::{Layer, LayerKind, Metadata, TileFormat, TileKey};
use wgpu::util::DeviceExt;

use super::atmosphere::{ATMOSPHERE_WGSL, AtmospherePipelines, AtmosphereTables, AtmosphereUniform};
use super::gpu::{self, sampler_entry, texture_entry, uniform_entry, write_layer};
use super::mesh::{MAX_LEVELS, MeshParams, Node, PatchMesh, Scene, select_nodes};
use super::residency::{KIND_ELEVATION, KIND_TEXTURE, PageTable, Residency};
use crate::globe::{Mapping, Surface};
use crate::stream::camera::{Camera, SceneBox};
use crate::stream::decode::TileData;
use crate::stream::streamer::Upload;

/// The shader source.
pub const TERRAIN_WGSL: &str = include_str!("../../../shaders/terrain.wgsl");

/// Depth buffer format (reversed depth: 1 near, 0 at infinity).
pub const DEPTH_FORMAT: wgpu::TextureFormat = wgpu::TextureFormat::Depth32Float;

const NODATA: f32 = -1.0e30;

/// How the terrain is shaded.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Default)]
pub enum Shading {
    /// Textured (or height-tinted), sunlit, hazy.
    #[default]
    Lit,
    /// Plain white, no light, no haze (coverage and crack checks).
    Flat,
}

/// Renderer settings.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct RenderSettings {
    /// GPU slots for elevation tiles (one texture-array layer each).
    pub elevation_slots: u32,
    /// GPU slots for texture tiles.
    pub texture_slots: u32,
    /// Quads per patch edge.
    pub patch: u32,
    /// Shading.
    pub shading: Shading,
    /// Overlay the mesh's edges.
    pub wireframe: bool,
    /// Tint each mesh level.
    pub lod_colours: bool,
    /// Detail texture strength (0: off).
    pub detail: f32,
    /// Direction towards the sun (world axes).
    pub sun: DVec3,
    /// Haze density per world unit; `None`: from the terrain's size.
    pub fog_density: Option<f64>,
    /// Haze and sky colour (sRGB).
    pub sky: [f32; 3],
    /// Draw every archive as a flat plate, even one that says where it lies (else a
    /// georeferenced archive is drawn on the WGS 84 ellipsoid, cameras in ECEF).
    pub flat: bool,
    /// On the globe, lit: the sky and the aerial perspective of a physically based
    /// atmosphere (else the plain haze).
    pub atmosphere: bool,
}

impl Default for RenderSettings {
    fn default() -> Self {
        Self {
            elevation_slots: 512,
            texture_slots: 512,
            patch: 32,
            shading: Shading::Lit,
            wireframe: false,
            lod_colours: false,
            detail: 0.0,
            sun: DVec3::new(-0.45, 0.65, 0.6),
            fog_density: None,
            sky: [0.62, 0.72, 0.84],
            flat: false,
            atmosphere: true,
        }
    }
}

impl RenderSettings {
    /// The background colour a pass should clear to.
    pub fn clear_colour(&self) -> wgpu::Color {
        match self.shading {
            Shading::Flat => wgpu::Color::BLACK,
            Shading::Lit => {
                let [r, g, b] = self.sky.map(|c| f64::from(srgb_to_linear(c)));
                wgpu::Color { r, g, b, a: 1.0 }
            }
        }
    }
}

fn srgb_to_linear(c: f32) -> f32 {
    if c <= 0.04045 { c / 12.92 } else { ((c + 0.055) / 1.055).powf(2.4) }
}

/// What one frame drew.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub struct FrameStats {
    /// Patches drawn.
    pub patches: u32,
    /// Vertices submitted.
    pub vertices: u64,
    /// Triangles submitted.
    pub triangles: u64,
    /// Draw calls.
    pub draw_calls: u32,
    /// Mesh levels in view (finest, coarsest).
    pub levels: (u32, u32),
    /// Resident elevation and texture tiles.
    pub resident: (u32, u32),
    /// GPU memory of the tile arrays and page table, bytes.
    pub gpu_bytes: u64,
    /// Tiles the streaming selection has in view that are on the GPU (set by the session).
    pub in_view_resident: u32,
    /// A drawn layer whose data is in view but none of whose tiles in view is on the GPU
    /// once streaming has settled (set by the session): the view cannot reach its tiles,
    /// a defect reported as [`FrameStats::drew_nothing_in_view`] is.
    pub unreached_layer: Option<u8>,
}

impl FrameStats {
    /// Tiles in view are on the GPU and yet the frame draws no terrain: always a defect
    /// (the front ends warn; `render` fails), never a picture of the sky to accept.
    pub fn drew_nothing_in_view(&self) -> bool {
        self.in_view_resident > 0 && self.patches == 0
    }
}

#[repr(C)]
#[derive(Clone, Copy, Pod, Zeroable)]
struct LodInfo {
    tile: [i32; 4],
    frac: [f32; 4],
}

#[repr(C)]
#[derive(Clone, Copy, Pod, Zeroable)]
struct Globals {
    view_proj: [[f32; 4]; 4],
    camera: [f32; 4],
    sun: [f32; 4],
    fog: [f32; 4],
    terrain: [f32; 4],
    elev: [f32; 4],
    tex: [f32; 4],
    counts: [u32; 4],
    mode: [u32; 4],
    lod: [f32; 4],
    bounds: [f32; 4],
    globe: GlobeInfo,
    ranges: [[f32; 4]; 32],
    elev_lods: [LodInfo; 32],
    tex_lods: [LodInfo; 32],
}

/// How the shader places grid points on the globe (terrain.wgsl's `GlobeInfo`).
#[repr(C)]
#[derive(Clone, Copy, Pod, Zeroable)]
struct GlobeInfo {
    kind: [u32; 4],
    map: [f32; 4],
    anchor: [f32; 4],
}

const GLOBE_FLAT: u32 = 0;
const GLOBE_GEOGRAPHIC: u32 = 1;
const GLOBE_WEB_MERCATOR: u32 = 2;
const GLOBE_LATTICE: u32 = 3;

/// One layer's texture array and its residency.
struct TileArray {
    layer: Layer,
    index: u8,
    kind: u32,
    texture: wgpu::Texture,
    format: wgpu::TextureFormat,
    edge: u32,
    residency: Residency,
    bytes: u64,
}

impl TileArray {
    fn new(device: &wgpu::Device, index: u8, layer: &Layer, kind: u32, slots: u32, bc: bool) -> Option<Self> {
        let edge = layer.tile_resolution + 2 * u32::from(layer.border);
        let (format, texel_bytes) = match (kind, layer.format) {
            (KIND_ELEVATION, _) => (wgpu::TextureFormat::R32Float, 4.0),
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
        #[allow(clippy::cast_possible_truncation, clippy::cast_sign_loss)]
        let bytes = (f64::from(edge) * f64::from(edge) * texel_bytes * f64::from(slots)) as u64;
        Some(Self { layer: layer.clone(), index, kind, texture, format, edge, residency: Residency::new(slots), bytes })
    }

    /// Writes a decoded tile into `slot`; false if its size or kind does not fit.
    fn write(&self, queue: &wgpu::Queue, slot: u32, data: &TileData, size: u32) -> bool {
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

    fn shader_info(&self) -> [f32; 4] {
        #[allow(clippy::cast_precision_loss)]
        let spacing = self.layer.tile_world_size / f64::from(self.layer.tile_resolution);
        #[allow(clippy::cast_possible_truncation)]
        [self.layer.tile_resolution as f32, f32::from(self.layer.border), self.edge as f32, spacing as f32]
    }

    /// Per-LOD tile index and fraction of the anchor.
    fn lods(&self, anchor: (f64, f64)) -> [LodInfo; 32] {
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

/// Draws a streamed terrain.
pub struct TerrainRenderer {
    settings: RenderSettings,
    /// The drawn box `[min x, min z, max x, max z]` in world units ([`crate::fly::terrain_bounds`]).
    extent: [f64; 4],
    /// The terrain's height range (0, 0 without elevation).
    column: (f64, f64),
    elevation: Option<TileArray>,
    texture: Option<TileArray>,
    page_table: PageTable,
    page_texture: wgpu::Texture,
    page_dirty: bool,
    globals: wgpu::Buffer,
    bind_group: wgpu::BindGroup,
    pipeline: wgpu::RenderPipeline,
    vertices: wgpu::Buffer,
    indices: wgpu::Buffer,
    mesh: PatchMesh,
    instances: wgpu::Buffer,
    instance_capacity: u64,
    full: u32,
    quarter: u32,
    frame: u64,
    stats: FrameStats,
    params: MeshParams,
    /// The plate or the globe the terrain is drawn on.
    surface: Surface,
    /// The terrain's box in scene coordinates (camera clip planes enclose it).
    scene_box: SceneBox,
    /// The globe's lattice of longitudes and latitudes (1 x 1 unused elsewhere), and
    /// whether it still has to be written.
    lattice: wgpu::Texture,
    lattice_dirty: bool,
    /// The atmosphere's tables and uniform, its pipelines, and whether this frame draws it.
    air_tables: AtmosphereTables,
    air_pipelines: AtmospherePipelines,
    sky: bool,
}

impl std::fmt::Debug for TerrainRenderer {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("TerrainRenderer").field("settings", &self.settings).field("stats", &self.stats).finish()
    }
}

/// A view of a layer's tile array, or of a 1x1 dummy of `format` standing in for a missing
/// layer, so that one pipeline serves all archives.
fn array_view(device: &wgpu::Device, array: Option<&TileArray>, format: wgpu::TextureFormat) -> wgpu::TextureView {
    let dummy;
    let texture = match array {
        Some(a) => &a.texture,
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

/// Bilinear, clamped: the colour tiles' sampler.
fn colour_sampler(device: &wgpu::Device) -> wgpu::Sampler {
    device.create_sampler(&wgpu::SamplerDescriptor {
        label: Some("sampler.tiles.colour"),
        address_mode_u: wgpu::AddressMode::ClampToEdge,
        address_mode_v: wgpu::AddressMode::ClampToEdge,
        mag_filter: wgpu::FilterMode::Linear,
        min_filter: wgpu::FilterMode::Linear,
        ..Default::default()
    })
}

/// The terrain's bind group layout and pipeline for one colour format: its shaders are
/// compiled when it is made. Renderers of that format share one; a front end may make it
/// before any archive is open, so that the first frame with terrain does not wait for
/// the shaders (wgpu handles are reference-counted: clones share the pipeline).
#[derive(Clone, Debug)]
pub struct TerrainPipeline {
    layout: wgpu::BindGroupLayout,
    pipeline: wgpu::RenderPipeline,
    atmosphere: AtmospherePipelines,
    format: wgpu::TextureFormat,
}

impl TerrainPipeline {
    /// Makes (compiles) the pipelines for `colour_format`: the terrain's, the sky's and
    /// the atmosphere tables'.
    pub fn new(device: &wgpu::Device, colour_format: wgpu::TextureFormat) -> Self {
        let layout = bind_group_layout(device);
        let source = format!("{TERRAIN_WGSL}\n{ATMOSPHERE_WGSL}");
        let module = gpu::shader(device, "terrain", &source);
        let pipeline = terrain_pipeline(device, &module, &layout, colour_format);
        let atmosphere = AtmospherePipelines::new(device, &module, &layout, colour_format);
        Self { layout, pipeline, atmosphere, format: colour_format }
    }

    /// The colour format it draws into.
    pub fn format(&self) -> wgpu::TextureFormat {
        self.format
    }
}

/// Globals, page table, elevation tiles, colour tiles, colour sampler.
fn bind_group_layout(device: &wgpu::Device) -> wgpu::BindGroupLayout {
    device.create_bind_group_layout(&wgpu::BindGroupLayoutDescriptor {
        label: Some("layout.terrain"),
        entries: &[
            uniform_entry(0),
            texture_entry(1, wgpu::TextureSampleType::Uint, wgpu::TextureViewDimension::D2),
            texture_entry(2, wgpu::TextureSampleType::Float { filterable: false }, wgpu::TextureViewDimension::D2Array),
            texture_entry(3, wgpu::TextureSampleType::Float { filterable: true }, wgpu::TextureViewDimension::D2Array),
            sampler_entry(4),
            texture_entry(5, wgpu::TextureSampleType::Float { filterable: false }, wgpu::TextureViewDimension::D2),
            uniform_entry(6),
            texture_entry(7, wgpu::TextureSampleType::Float { filterable: true }, wgpu::TextureViewDimension::D2),
            texture_entry(8, wgpu::TextureSampleType::Float { filterable: true }, wgpu::TextureViewDimension::D2),
            sampler_entry(9),
            texture_entry(10, wgpu::TextureSampleType::Float { filterable: true }, wgpu::TextureViewDimension::D2),
            texture_entry(11, wgpu::TextureSampleType::Float { filterable: true }, wgpu::TextureViewDimension::D2),
        ],
    })
}

/// The terrain pipeline: patch vertices and per-instance patch placement, reversed depth.
fn terrain_pipeline(
    device: &wgpu::Device,
    module: &wgpu::ShaderModule,
    layout: &wgpu::BindGroupLayout,
    colour_format: wgpu::TextureFormat,
) -> wgpu::RenderPipeline {
    gpu::pipeline_in(
        device,
        module,
        &gpu::PipelineDesc {
            name: "terrain",
            wgsl: TERRAIN_WGSL,
            layout,
            buffers: &[
                Some(wgpu::VertexBufferLayout {
                    array_stride: 8,
                    step_mode: wgpu::VertexStepMode::Vertex,
                    attributes: &wgpu::vertex_attr_array![0 => Float32x2],
                }),
                Some(wgpu::VertexBufferLayout {
                    array_stride: 16,
                    step_mode: wgpu::VertexStepMode::Instance,
                    attributes: &wgpu::vertex_attr_array![1 => Float32x4],
                }),
            ],
            topology: wgpu::PrimitiveTopology::TriangleList,
            depth: (true, wgpu::CompareFunction::Greater),
            target: (colour_format, None),
        },
    )
}

/// The patch mesh's vertex and index buffers.
fn patch_buffers(device: &wgpu::Device, mesh: &PatchMesh) -> (wgpu::Buffer, wgpu::Buffer) {
    let vertices = device.create_buffer_init(&wgpu::util::BufferInitDescriptor {
        label: Some("buffer.terrain.patch_vertices"),
        contents: bytemuck::cast_slice(&mesh.vertices),
        usage: wgpu::BufferUsages::VERTEX,
    });
    let indices = device.create_buffer_init(&wgpu::util::BufferInitDescriptor {
        label: Some("buffer.terrain.patch_indices"),
        contents: bytemuck::cast_slice(&mesh.indices),
        usage: wgpu::BufferUsages::INDEX,
    });
    (vertices, indices)
}

fn first_layer(metadata: &Metadata, kind: LayerKind) -> Option<(u8, &Layer)> {
    metadata.layers.iter().enumerate().find(|(_, l)| l.kind == kind).and_then(|(i, l)| Some((u8::try_from(i).ok()?, l)))
}

impl TerrainRenderer {
    /// A renderer for `metadata`'s first elevation and first texture layer, drawing into
    /// targets of `colour_format` with a [`DEPTH_FORMAT`] depth buffer.
    pub fn new(
        device: &wgpu::Device,
        metadata: &Metadata,
        settings: RenderSettings,
        colour_format: wgpu::TextureFormat,
    ) -> Self {
        Self::with_pipeline(device, metadata, settings, &TerrainPipeline::new(device, colour_format))
    }

    /// A renderer drawing with an existing pipeline (of the target's colour format).
    pub fn with_pipeline(
        device: &wgpu::Device,
        metadata: &Metadata,
        settings: RenderSettings,
        shared: &TerrainPipeline,
    ) -> Self {
        let bc = device.features().contains(wgpu::Features::TEXTURE_COMPRESSION_BC);
        let elevation = first_layer(metadata, LayerKind::Elevation)
            .and_then(|(i, l)| TileArray::new(device, i, l, KIND_ELEVATION, settings.elevation_slots, bc));
        let texture = first_layer(metadata, LayerKind::Texture)
            .and_then(|(i, l)| TileArray::new(device, i, l, KIND_TEXTURE, settings.texture_slots, bc));
        let elevation_view = array_view(device, elevation.as_ref(), wgpu::TextureFormat::R32Float);
        let colour_view = array_view(device, texture.as_ref(), wgpu::TextureFormat::Rgba8UnormSrgb);
        let page_table = PageTable::new(settings.elevation_slots + settings.texture_slots);
        let page_texture = gpu::texture(
            device,
            "texture.page_table",
            (page_table.width, page_table.height(), 1),
            wgpu::TextureFormat::Rgba32Uint,
            wgpu::TextureUsages::TEXTURE_BINDING | wgpu::TextureUsages::COPY_DST,
        );
        let globals = gpu::uniform_buffer(device, "buffer.terrain.globals", size_of::<Globals>());
        let sampler = colour_sampler(device);
        let layout = &shared.layout;
        let page_view = page_texture.create_view(&wgpu::TextureViewDescriptor::default());
        let surface = if elevation.is_some() || texture.is_some() {
            Surface::new(metadata, !settings.flat)
        } else {
            Surface::Flat
        };
        let lattice_size = match surface.globe().map(|g| &g.mapping) {
            Some(Mapping::Lattice(l)) => (u32::try_from(l.size.0).unwrap_or(1), u32::try_from(l.size.1).unwrap_or(1)),
            _ => (1, 1),
        };
        let lattice = gpu::texture(
            device,
            "texture.globe_lattice",
            (lattice_size.0, lattice_size.1, 1),
            wgpu::TextureFormat::Rgba32Float,
            wgpu::TextureUsages::TEXTURE_BINDING | wgpu::TextureUsages::COPY_DST,
        );
        let lattice_view = lattice.create_view(&wgpu::TextureViewDescriptor::default());
        let air_tables = AtmosphereTables::new(device);
        let bind_group = gpu::bind_group(
            device,
            "bind_group.terrain",
            layout,
            &[
                globals.as_entire_binding(),
                wgpu::BindingResource::TextureView(&page_view),
                wgpu::BindingResource::TextureView(&elevation_view),
                wgpu::BindingResource::TextureView(&colour_view),
                wgpu::BindingResource::Sampler(&sampler),
                wgpu::BindingResource::TextureView(&lattice_view),
                air_tables.uniform.as_entire_binding(),
                wgpu::BindingResource::TextureView(&air_tables.transmittance_view),
                wgpu::BindingResource::TextureView(&air_tables.multiscattering_view),
                wgpu::BindingResource::Sampler(&air_tables.sampler),
                wgpu::BindingResource::TextureView(&air_tables.sky_view_view),
                wgpu::BindingResource::TextureView(&air_tables.aerial_view),
            ],
        );
        let pipeline = shared.pipeline.clone();
        let mesh = PatchMesh::new(settings.patch);
        let (vertices, indices) = patch_buffers(device, &mesh);
        let instance_capacity = 1024;
        let instances = instance_buffer(device, instance_capacity);
        let terrain = &metadata.terrain;
        let base = if terrain.base_tile_size > 0.0 {
            terrain.base_tile_size
        } else {
            elevation.as_ref().map_or(1.0, |e| e.layer.tile_world_size / f64::from(e.layer.tile_resolution))
        };
        let params = MeshParams::new(base, settings.patch, terrain.high_detail_range, terrain.num_detail_levels);
        // Where the data ends (the grid rounds up to whole tiles): nothing is drawn beyond.
        let extent = match elevation.as_ref().or(texture.as_ref()) {
            Some(_) => crate::fly::terrain_bounds(metadata).0,
            None => [0.0; 4],
        };
        let column = crate::stream::select::drawn_heights(metadata);
        Self {
            settings,
            extent,
            column,
            scene_box: crate::fly::scene_box(metadata, &surface),
            surface,
            lattice,
            lattice_dirty: true,
            air_tables,
            air_pipelines: shared.atmosphere.clone(),
            sky: false,
            elevation,
            texture,
            page_table,
            page_texture,
            page_dirty: true,
            globals,
            bind_group,
            pipeline,
            vertices,
            indices,
            mesh,
            instances,
            instance_capacity,
            full: 0,
            quarter: 0,
            frame: 0,
            stats: FrameStats::default(),
            params,
        }
    }

    /// Settings in use.
    pub fn settings(&self) -> &RenderSettings {
        &self.settings
    }

    /// Changes the settings that need no new GPU resources (shading, overlays, sun, haze).
    pub fn set_view_settings(&mut self, settings: RenderSettings) {
        let (e, t, p) = (self.settings.elevation_slots, self.settings.texture_slots, self.settings.patch);
        self.settings = RenderSettings { elevation_slots: e, texture_slots: t, patch: p, ..settings };
    }

    /// The plate or the globe the terrain is drawn on.
    pub fn surface(&self) -> &Surface {
        &self.surface
    }

    /// The terrain's box in the surface's scene coordinates ([`crate::fly::scene_box`]).
    pub fn scene_box(&self) -> SceneBox {
        self.scene_box
    }

    /// Mesh parameters in use.
    pub fn mesh_params(&self) -> &MeshParams {
        &self.params
    }

    /// What the last prepared frame draws.
    pub fn stats(&self) -> FrameStats {
        self.stats
    }

    /// Most tiles of one layer the GPU keeps: the streaming selection should want no more.
    pub fn max_resident_tiles(&self) -> usize {
        let slots = |a: &Option<TileArray>| a.as_ref().map_or(usize::MAX, |a| a.residency.capacity() as usize);
        slots(&self.elevation).min(slots(&self.texture))
    }

    fn arrays(&self) -> impl Iterator<Item = &TileArray> {
        [&self.elevation, &self.texture].into_iter().flatten()
    }

    fn arrays_mut(&mut self) -> impl Iterator<Item = &mut TileArray> {
        [&mut self.elevation, &mut self.texture].into_iter().flatten()
    }

    /// Drops every resident tile (the archive was replaced).
    pub fn clear(&mut self) {
        for array in self.arrays_mut() {
            array.residency.clear();
        }
        self.page_dirty = true;
    }

    /// Is the tile on the GPU?
    pub fn is_resident(&self, key: TileKey) -> bool {
        self.arrays().any(|a| a.index == key.layer() && a.residency.slot(key).is_some())
    }

    /// Uploads tiles handed over by the streaming core. Returns the tiles the GPU does
    /// not keep (evicted to make room, or refused): hand them to
    /// [`crate::Streamer::release`] so they are offered again when wanted.
    pub fn upload(&mut self, queue: &wgpu::Queue, uploads: &[Upload]) -> Vec<TileKey> {
        let mut dropped = Vec::new();
        let frame = self.frame;
        for upload in uploads {
            let tile = &upload.tile;
            let Some(array) = self.arrays_mut().find(|a| a.index == tile.key.layer()) else {
                continue;
            };
            let range = match &tile.data {
                TileData::Heights { min, max, .. } if min <= max => Some((*min, *max)),
                _ => None,
            };
            let Some(placement) = array.residency.insert(tile.key, frame, range) else {
                dropped.push(tile.key);
                continue;
            };
            dropped.extend(placement.evicted);
            if !array.write(queue, placement.slot, &tile.data, tile.size) {
                tracing::warn!(tile = %tile.key, size = tile.size, "tile does not fit its layer's GPU array: skipped");
                array.residency.remove(tile.key);
            }
            self.page_dirty = true;
        }
        dropped
    }

    /// Chooses the patches for `camera`, marks `wanted` tiles as in use (they are not
    /// evicted) and writes this frame's uniforms, instances and page table.
    pub fn prepare(
        &mut self,
        device: &wgpu::Device,
        queue: &wgpu::Queue,
        camera: &Camera,
        wanted: impl IntoIterator<Item = TileKey>,
    ) -> FrameStats {
        self.frame += 1;
        let wanted: HashSet<TileKey> = wanted.into_iter().collect();
        let frame = self.frame;
        for array in self.arrays_mut() {
            for key in wanted.iter().filter(|k| k.layer() == array.index) {
                array.residency.touch(*key, frame);
            }
        }
        if self.page_dirty {
            let tiles: Vec<(u32, TileKey, u32)> =
                self.arrays().flat_map(|a| a.residency.iter().map(move |(k, slot, _)| (a.kind, k, slot))).collect();
            self.page_table.rebuild(tiles);
            let table = &self.page_table;
            let (width, height) = (table.width, table.height());
            let entries = bytemuck::cast_slice(&table.entries);
            write_layer(queue, &self.page_texture, 0, entries, (width * 16, height), (width, height));
            self.page_dirty = false;
        }
        if self.lattice_dirty {
            self.lattice_dirty = false;
            if let Some(Mapping::Lattice(l)) = self.surface.globe().map(|g| &g.mapping) {
                #[allow(clippy::cast_possible_truncation)]
                let texels: Vec<[f32; 4]> = l.values.iter().map(|v| [v.x as f32, v.y as f32, 0.0, 0.0]).collect();
                let (w, h) = (u32::try_from(l.size.0).unwrap_or(1), u32::try_from(l.size.1).unwrap_or(1));
                write_layer(queue, &self.lattice, 0, bytemuck::cast_slice(&texels), (w * 16, h), (w, h));
            }
        }
        if self.surface.globe().is_some() && self.settings.shading == Shading::Lit && self.settings.atmosphere {
            self.air_tables.make(device, queue, &self.air_pipelines);
        }
        let (nodes, params) = self.select(camera);
        self.write_frame(device, queue, camera, &nodes, &params);
        self.stats
    }

    fn select(&self, camera: &Camera) -> (Vec<Node>, MeshParams) {
        let [x0, z0, x1, z1] = self.extent;
        let column = self.column;
        let eye = camera.position;
        // Enough levels that the coarsest ring reaches the far corner of the data.
        let far = match self.surface {
            Surface::Flat => [(x0, z0), (x1, z0), (x0, z1), (x1, z1)]
                .iter()
                .map(|&(x, z)| DVec3::new(x, eye.y.clamp(column.0, column.1), z).distance(eye))
                .fold(0.0, f64::max),
            Surface::Globe(_) => {
                let b = self.scene_box;
                b.half.length() * 2.0 + b.distance(eye)
            }
        };
        let params = MeshParams { levels: self.params.levels.max(self.params.levels_to_cover(far)), ..self.params };
        // Boxes of the resident elevation tiles, once per frame: a patch's height range
        // (for culling) is the union of those it overlaps.
        let boxes: Vec<[f64; 6]> = self
            .elevation
            .iter()
            .flat_map(|a| {
                a.residency.iter().filter_map(|(key, _, range)| {
                    let (lo, hi) = range?;
                    let size = a.layer.world_size_at(key.lod());
                    let (x0, z0) = (f64::from(key.x()) * size, f64::from(key.y()) * size);
                    Some([x0, z0, x0 + size, z0 + size, f64::from(lo), f64::from(hi)])
                })
            })
            .collect();
        let has_elevation = self.elevation.is_some();
        let heights = |x0: f64, z0: f64, x1: f64, z1: f64| -> (f64, f64) {
            if !has_elevation {
                return column;
            }
            let overlapping = boxes.iter().filter(|b| b[0] < x1 && b[2] > x0 && b[1] < z1 && b[3] > z0);
            overlapping
                .fold(None, |r: Option<(f64, f64)>, b| {
                    Some(r.map_or((b[4], b[5]), |(lo, hi)| (lo.min(b[4]), hi.max(b[5]))))
                })
                .map_or(column, |(lo, hi)| (lo - 1.0, hi + 1.0))
        };
        let frustum = camera.frustum();
        #[allow(clippy::cast_possible_truncation)]
        let extent = (
            ((x0 / params.base).floor() as i64, (z0 / params.base).floor() as i64),
            ((x1 / params.base).ceil() as i64, (z1 / params.base).ceil() as i64),
        );
        let scene = Scene {
            start: extent.0,
            extent: extent.1,
            eye,
            frustum: &frustum,
            column,
            heights: &heights,
            surface: &self.surface,
        };
        let mut nodes = select_nodes(&params, &scene);
        // Full patches first, then quarters: two instanced draws.
        nodes.sort_by_key(|n| (n.quarter, n.level));
        (nodes, params)
    }

    fn write_frame(
        &mut self,
        device: &wgpu::Device,
        queue: &wgpu::Queue,
        camera: &Camera,
        nodes: &[Node],
        params: &MeshParams,
    ) {
        // Positions go to the GPU relative to an anchor on the base grid near the eye, so
        // that f32 keeps centimetres on a continent.
        let base = params.base;
        // On the globe: the grid point under the eye.
        let under = match self.surface.globe() {
            Some(globe) => globe.world_under(camera.position),
            None => glam::DVec2::new(camera.position.x, camera.position.z),
        };
        #[allow(clippy::cast_possible_truncation)]
        let anchor_units = ((under.x / base).floor() as i64, (under.y / base).floor() as i64);
        #[allow(clippy::cast_precision_loss)]
        let anchor = (anchor_units.0 as f64 * base, anchor_units.1 as f64 * base);
        self.write_instances(device, queue, nodes, anchor_units);
        let globals = self.globals(camera, params, anchor);
        queue.write_buffer(&self.globals, 0, bytemuck::bytes_of(&globals));
        let air = self.air(camera, anchor);
        self.sky = air.is_on();
        queue.write_buffer(&self.air_tables.uniform, 0, bytemuck::bytes_of(&air));
        if air.uses_tables() {
            self.air_tables.make_frame(device, queue, &self.air_pipelines);
        }
        self.stats = self.frame_stats(nodes);
    }

    /// One instance per patch, full patches first: (x, z) on the base grid from the
    /// anchor, level.
    fn write_instances(
        &mut self,
        device: &wgpu::Device,
        queue: &wgpu::Queue,
        nodes: &[Node],
        anchor_units: (i64, i64),
    ) {
        #[allow(clippy::cast_precision_loss)]
        let instances: Vec<[f32; 4]> = nodes
            .iter()
            .map(|n| [(n.origin.0 - anchor_units.0) as f32, (n.origin.1 - anchor_units.1) as f32, n.level as f32, 0.0])
            .collect();
        let needed = instances.len().max(1) as u64;
        if needed > self.instance_capacity {
            self.instance_capacity = needed.next_power_of_two();
            self.instances = instance_buffer(device, self.instance_capacity);
        }
        queue.write_buffer(&self.instances, 0, bytemuck::cast_slice(&instances));
        self.full = u32::try_from(nodes.iter().filter(|n| !n.quarter).count()).unwrap_or(u32::MAX);
        self.quarter = u32::try_from(nodes.len()).unwrap_or(u32::MAX) - self.full;
    }

    /// The globe's part of the globals, the eye in the frame drawn in and the camera's
    /// rotation into that frame: on the plate, x and z from the anchor and heights as
    /// they are; on the globe, the local frame at the anchor ([`crate::globe`]).
    fn placement(&self, camera: &Camera, anchor: (f64, f64)) -> (GlobeInfo, DVec3, DMat4) {
        let eye = camera.position;
        let Some(globe) = self.surface.globe() else {
            let rotation = DMat4::look_to_rh(DVec3::ZERO, camera.direction(), camera.up());
            let info = GlobeInfo { kind: [GLOBE_FLAT, 1, 1, 0], map: [0.0; 4], anchor: [0.0; 4] };
            return (info, DVec3::new(eye.x - anchor.0, eye.y, eye.z - anchor.1), rotation);
        };
        let frame = globe.local_frame(glam::DVec2::new(anchor.0, anchor.1));
        let local_eye = frame.to_local(eye);
        let rotation = DMat4::look_to_rh(
            DVec3::ZERO,
            frame.direction_to_local(camera.direction()),
            frame.direction_to_local(camera.up()),
        );
        let (sin, cos) = frame.lon_lat.y.sin_cos();
        let n = crate::globe::A / (1.0 - crate::globe::E2 * sin * sin).sqrt();
        let column = self.surface.height(eye).clamp(self.column.0, self.column.1);
        let (kind, map) = match &globe.mapping {
            Mapping::Geographic { step, .. } => ([GLOBE_GEOGRAPHIC, 1, 1, 0], [step.x, step.y, 0.0, 0.0]),
            Mapping::WebMercator { origin, step } => {
                let v = origin.y + step.y * anchor.1;
                ([GLOBE_WEB_MERCATOR, 1, 1, 0], [step.x, step.y, v, frame.lon_lat.y])
            }
            Mapping::Lattice(l) => {
                let q = l.coordinates(anchor.0, anchor.1);
                let size = [u32::try_from(l.size.0).unwrap_or(1), u32::try_from(l.size.1).unwrap_or(1)];
                ([GLOBE_LATTICE, size[0], size[1], 0], [q.x, q.y, 1.0 / l.cell, 0.0])
            }
        };
        #[allow(clippy::cast_possible_truncation)]
        let info =
            GlobeInfo { kind, map: map.map(|v| v as f32), anchor: [sin as f32, cos as f32, n as f32, column as f32] };
        (info, local_eye, rotation)
    }

    /// The atmosphere's uniform: on for a lit globe, in the frame at the anchor.
    fn air(&self, camera: &Camera, anchor: (f64, f64)) -> AtmosphereUniform {
        let drawn = self.settings.shading == Shading::Lit && self.settings.atmosphere;
        let Some(globe) = self.surface.globe().filter(|_| drawn) else {
            return AtmosphereUniform::off();
        };
        let frame = globe.local_frame(glam::DVec2::new(anchor.0, anchor.1));
        let rotation = DMat4::look_to_rh(
            DVec3::ZERO,
            frame.direction_to_local(camera.direction()),
            frame.direction_to_local(camera.up()),
        );
        let projection = DMat4::perspective_infinite_reverse_rh(camera.fov_y, camera.aspect, camera.near);
        // The planet's centre in the frame; the eye from it.
        let eye = frame.to_local(camera.position) - frame.to_local(DVec3::ZERO);
        let pole = frame.direction_to_local(DVec3::Z);
        let height = self.surface.height(camera.position);
        let viewport = (f64::from(camera.viewport_height) * camera.aspect, f64::from(camera.viewport_height));
        AtmosphereUniform::on(
            eye,
            height,
            frame.origin.length(),
            (projection * rotation, viewport),
            self.settings.sun,
            pole,
        )
    }

    /// The shader's globals for one frame.
    fn globals(&self, camera: &Camera, params: &MeshParams, anchor: (f64, f64)) -> Globals {
        let base = params.base;
        let eye = camera.position;
        let (globe, local_eye, rotation) = self.placement(camera, anchor);
        let projection = DMat4::perspective_infinite_reverse_rh(camera.fov_y, camera.aspect, camera.near);
        let view_proj: Mat4 = (projection * rotation).as_mat4();
        let column = self.column;
        let [x0, z0, x1, z1] = self.extent;
        let flat = self.settings.shading == Shading::Flat;
        let fog =
            if flat { 0.0 } else { self.settings.fog_density.unwrap_or(0.12 / (x1 - x0).hypot(z1 - z0).max(1.0)) };
        let sun = self.settings.sun.try_normalize().unwrap_or(DVec3::Y);
        let [r, g, b] = self.settings.sky.map(srgb_to_linear);
        let elev_info = self.elevation.as_ref().map_or([0.0, 0.0, 1.0, 1.0], TileArray::shader_info);
        let tex_info = self.texture.as_ref().map_or([0.0, 0.0, 1.0, 1.0], TileArray::shader_info);
        // LODs the shader looks through: up to the coarsest that holds tiles (a regional
        // pyramid's levels above it are empty; a far pixel takes the coarsest there is).
        let lods = |a: &Option<TileArray>| a.as_ref().map_or(0, |a| u32::from(a.layer.start_lod()) + 1);
        let mut ranges = [[0.0f32; 4]; 32];
        for (level, r) in (0..MAX_LEVELS).zip(ranges.iter_mut()) {
            let (start, end) = params.morph(level);
            #[allow(clippy::cast_possible_truncation)]
            {
                *r = [start as f32, end as f32, f64::from(level).exp2() as f32, 0.0];
            }
        }
        #[allow(clippy::cast_possible_truncation)]
        Globals {
            view_proj: view_proj.to_cols_array_2d(),
            camera: [local_eye.x as f32, local_eye.y as f32, local_eye.z as f32, base as f32],
            sun: [sun.x as f32, sun.y as f32, sun.z as f32, 0.35],
            fog: [r, g, b, fog as f32],
            terrain: [
                column.0 as f32,
                column.1 as f32,
                (eye.y.clamp(column.0, column.1) - eye.y) as f32,
                self.settings.detail,
            ],
            elev: elev_info,
            tex: tex_info,
            counts: [lods(&self.elevation), lods(&self.texture), self.page_table.mask(), self.page_table.width],
            mode: [
                u32::from(flat),
                u32::from(self.settings.wireframe),
                u32::from(self.settings.lod_colours),
                self.page_table.max_probes,
            ],
            lod: [(base / f64::from(elev_info[3])).log2() as f32, params.range(0) as f32, 0.0, 0.0],
            bounds: [(x0 - anchor.0) as f32, (z0 - anchor.1) as f32, (x1 - anchor.0) as f32, (z1 - anchor.1) as f32],
            globe,
            ranges,
            elev_lods: self.elevation.as_ref().map_or([LodInfo::zeroed(); 32], |a| a.lods(anchor)),
            tex_lods: self.texture.as_ref().map_or([LodInfo::zeroed(); 32], |a| a.lods(anchor)),
        }
    }

    /// What the frame draws.
    fn frame_stats(&self, nodes: &[Node]) -> FrameStats {
        let full_vertices = u64::from((self.settings.patch + 1).pow(2));
        let quarter_vertices = u64::from((self.settings.patch / 2 + 1).pow(2));
        let full_triangles = u64::from(self.settings.patch.pow(2) * 2);
        let resident = |a: &Option<TileArray>| a.as_ref().map_or(0, |a| u32::try_from(a.residency.len()).unwrap_or(0));
        FrameStats {
            patches: self.full + self.quarter,
            vertices: u64::from(self.full) * full_vertices + u64::from(self.quarter) * quarter_vertices,
            triangles: u64::from(self.full) * full_triangles + u64::from(self.quarter) * full_triangles / 4,
            draw_calls: u32::from(self.full > 0) + u32::from(self.quarter > 0),
            levels: (
                nodes.iter().map(|n| n.level).min().unwrap_or(0),
                nodes.iter().map(|n| n.level).max().unwrap_or(0),
            ),
            resident: (resident(&self.elevation), resident(&self.texture)),
            gpu_bytes: self.arrays().map(|a| a.bytes).sum::<u64>() + self.page_table.entries.len() as u64 * 16,
            in_view_resident: 0,
            unreached_layer: None,
        }
    }

    /// The GPU format of the texture tiles (`None` without a drawable texture layer):
    /// `Bc1RgbaUnormSrgb` / `Bc7RgbaUnormSrgb` when compressed tiles go up as blocks.
    pub fn texture_format(&self) -> Option<wgpu::TextureFormat> {
        self.texture.as_ref().map(|t| t.format)
    }

    /// Records the terrain into `pass` (after [`Self::prepare`]).
    pub fn draw(&self, pass: &mut wgpu::RenderPass<'_>) {
        if self.sky {
            pass.set_pipeline(&self.air_pipelines.sky);
            pass.set_bind_group(0, &self.bind_group, &[]);
            pass.draw(0..3, 0..1);
        }
        if self.full + self.quarter == 0 {
            return;
        }
        pass.set_pipeline(&self.pipeline);
        pass.set_bind_group(0, &self.bind_group, &[]);
        pass.set_vertex_buffer(0, self.vertices.slice(..));
        pass.set_vertex_buffer(1, self.instances.slice(..));
        pass.set_index_buffer(self.indices.slice(..), wgpu::IndexFormat::Uint32);
        let total = u32::try_from(self.mesh.indices.len()).unwrap_or(u32::MAX);
        if self.full > 0 {
            pass.draw_indexed(0..self.mesh.full_indices, 0, 0..self.full);
        }
        if self.quarter > 0 {
            // The quarter patches' instances follow the full ones: rebinding at their
            // offset rather than drawing from a first instance > 0, which WebGL2 lacks.
            pass.set_vertex_buffer(1, self.instances.slice(u64::from(self.full) * 16..));
            pass.draw_indexed(self.mesh.full_indices..total, 0, 0..self.quarter);
        }
    }
}

fn instance_buffer(device: &wgpu::Device, capacity: u64) -> wgpu::Buffer {
    device.create_buffer(&wgpu::BufferDescriptor {
        label: Some("buffer.terrain.instances"),
        size: capacity * 16,
        usage: wgpu::BufferUsages::VERTEX | wgpu::BufferUsages::COPY_DST,
        mapped_at_creation: false,
    })
}
