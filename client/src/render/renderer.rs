//! The wgpu terrain renderer. It never owns a window or a device: `new(&Device, ..)`,
//! `upload` (within the streaming core's per-frame budget), `prepare(camera)`, `draw(pass)`.

//!
//! Split by concern: `super::pipeline` (shaders, layouts, pipelines), `super::frame`
//! (each frame's uniforms and instances), `super::tile_array` (the tiles on the GPU);
//! this file holds the renderer itself: its resources, uploads, selection and draws.

use std::collections::HashSet;

use glam::DVec3;
use terrastream_format::{Layer, LayerKind, Metadata, TileKey};
use terrastream_tiles::TileData;

use super::atmosphere::{AtmospherePipelines, AtmosphereTables};
use super::frame::{Globals, instance_buffer};
use super::gpu::{self, write_layer};
use super::mesh::{MeshParams, Node, PatchMesh, Scene, select_nodes};
pub use super::pipeline::{DEPTH_FORMAT, TERRAIN_WGSL, TerrainPipeline};
use super::pipeline::{colour_sampler, patch_buffers};
use super::residency::{KIND_ELEVATION, KIND_TEXTURE, PageTable};
pub use super::settings::{FrameStats, RenderSettings, Shading};
use super::tile_array::{SHADE_FORMAT, TileArray, array_view};
use crate::globe::{Mapping, Surface};
use crate::stream::camera::{Camera, SceneBox};
use crate::stream::streamer::Upload;

/// Draws a streamed terrain.
pub struct TerrainRenderer {
    pub(super) settings: RenderSettings,
    /// The drawn box `[min x, min z, max x, max z]` in world units ([`crate::fly::terrain_bounds`]).
    pub(super) extent: [f64; 4],
    /// The terrain's height range (0, 0 without elevation).
    pub(super) column: (f64, f64),
    pub(super) elevation: Option<TileArray>,
    pub(super) texture: Option<TileArray>,
    pub(super) page_table: PageTable,
    pub(super) page_texture: wgpu::Texture,
    pub(super) page_dirty: bool,
    pub(super) globals: wgpu::Buffer,
    pub(super) bind_group: wgpu::BindGroup,
    pub(super) pipeline: wgpu::RenderPipeline,
    pub(super) vertices: wgpu::Buffer,
    pub(super) indices: wgpu::Buffer,
    pub(super) mesh: PatchMesh,
    pub(super) instances: wgpu::Buffer,
    pub(super) instance_capacity: u64,
    pub(super) full: u32,
    pub(super) quarter: u32,
    pub(super) frame: u64,
    pub(super) stats: FrameStats,
    pub(super) params: MeshParams,
    /// The plate or the globe the terrain is drawn on.
    pub(super) surface: Surface,
    /// The terrain's box in scene coordinates (camera clip planes enclose it).
    pub(super) scene_box: SceneBox,
    /// The globe's lattice of longitudes and latitudes (1 x 1 unused elsewhere), and
    /// whether it still has to be written.
    pub(super) lattice: wgpu::Texture,
    pub(super) lattice_dirty: bool,
    /// The whole-Earth picture, written at the first frame that draws the sky once it is
    /// decoded (a thread of its own started with the renderer): None until then, then
    /// whether it was written (false: it did not decode).
    pub(super) earth: wgpu::Texture,
    pub(super) earth_drawn: Option<bool>,
    /// The atmosphere's tables and uniform, its pipelines, and whether this frame draws it.
    pub(super) air_tables: AtmosphereTables,
    pub(super) air_pipelines: AtmospherePipelines,
    pub(super) sky: bool,
}

impl std::fmt::Debug for TerrainRenderer {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("TerrainRenderer").field("settings", &self.settings).field("stats", &self.stats).finish()
    }
}

fn first_layer(metadata: &Metadata, kind: LayerKind) -> Option<(u8, &Layer)> {
    metadata.layers.iter().enumerate().find(|(_, l)| l.kind == kind).and_then(|(i, l)| Some((u8::try_from(i).ok()?, l)))
}

/// Points a side of the globe's lattice texture: its lattice of longitudes and latitudes
/// and of the geoid's undulation (both on the same points), or 1 x 1 (unused).
pub(super) fn lattice_size(surface: &Surface) -> (u32, u32) {
    let size = match surface.globe() {
        Some(g) => match (&g.mapping, &g.geoid_lattice) {
            (Mapping::Lattice(l), _) => Some(l.size),
            (_, Some(n)) => Some(n.size),
            _ => None,
        },
        None => None,
    };
    size.map_or((1, 1), |(w, h)| (u32::try_from(w).unwrap_or(1), u32::try_from(h).unwrap_or(1)))
}

/// The globe's lattice of longitudes and latitudes (rg) and of the geoid's undulation (b)
/// as a texture (1 x 1, unused, where there is neither); written at the first frame.
fn lattice_texture(device: &wgpu::Device, surface: &Surface) -> wgpu::Texture {
    let size = lattice_size(surface);
    gpu::texture(
        device,
        "texture.globe_lattice",
        (size.0, size.1, 1),
        wgpu::TextureFormat::Rgba32Float,
        wgpu::TextureUsages::TEXTURE_BINDING | wgpu::TextureUsages::COPY_DST,
    )
}

/// The mesh's parameters: the terrain's own, its base spacing from the elevation's
/// samples when the metadata gives none.
fn mesh_params(metadata: &Metadata, elevation: Option<&TileArray>, patch: u32) -> MeshParams {
    let terrain = &metadata.terrain;
    let base = if terrain.base_tile_size > 0.0 {
        terrain.base_tile_size
    } else {
        elevation.map_or(1.0, |e| e.layer.sample_spacing(0))
    };
    MeshParams::new(base, patch, terrain.high_detail_range, terrain.num_detail_levels)
}

/// What the terrain's bind group binds, in the layout's order.
struct BoundResources<'a> {
    globals: &'a wgpu::Buffer,
    page_table: &'a wgpu::Texture,
    elevation: &'a wgpu::TextureView,
    elevation_shade: &'a wgpu::TextureView,
    colour: &'a wgpu::TextureView,
    lattice: &'a wgpu::Texture,
    air: &'a AtmosphereTables,
    earth: &'a wgpu::Texture,
}

impl BoundResources<'_> {
    fn bind_group(&self, device: &wgpu::Device, layout: &wgpu::BindGroupLayout) -> wgpu::BindGroup {
        let page_view = self.page_table.create_view(&wgpu::TextureViewDescriptor::default());
        let lattice_view = self.lattice.create_view(&wgpu::TextureViewDescriptor::default());
        let earth_view = self.earth.create_view(&wgpu::TextureViewDescriptor::default());
        let sampler = colour_sampler(device);
        let air = self.air;
        gpu::bind_group(
            device,
            "bind_group.terrain",
            layout,
            &[
                self.globals.as_entire_binding(),
                wgpu::BindingResource::TextureView(&page_view),
                wgpu::BindingResource::TextureView(self.elevation),
                wgpu::BindingResource::TextureView(self.colour),
                wgpu::BindingResource::Sampler(&sampler),
                wgpu::BindingResource::TextureView(&lattice_view),
                air.uniform.as_entire_binding(),
                wgpu::BindingResource::TextureView(&air.transmittance_view),
                wgpu::BindingResource::TextureView(&air.multiscattering_view),
                wgpu::BindingResource::Sampler(&air.sampler),
                wgpu::BindingResource::TextureView(&air.sky_view_view),
                wgpu::BindingResource::TextureView(&air.aerial_view),
                wgpu::BindingResource::TextureView(&earth_view),
                wgpu::BindingResource::TextureView(self.elevation_shade),
            ],
        )
    }
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
        let page_table = PageTable::new(settings.elevation_slots + settings.texture_slots);
        let page_texture = gpu::texture(
            device,
            "texture.page_table",
            (page_table.width, page_table.height(), 1),
            wgpu::TextureFormat::Rgba32Uint,
            wgpu::TextureUsages::TEXTURE_BINDING | wgpu::TextureUsages::COPY_DST,
        );
        let globals = gpu::uniform_buffer(device, "buffer.terrain.globals", size_of::<Globals>());
        let surface = if elevation.is_some() || texture.is_some() {
            Surface::new(metadata, !settings.flat)
        } else {
            Surface::Flat
        };
        let lattice = lattice_texture(device, &surface);
        let air_tables = AtmosphereTables::new(device);
        let earth = super::earth::earth_texture(device);
        if Self::draws_earth(&settings, &surface) {
            super::earth::start_decoding();
        }
        let resources = BoundResources {
            globals: &globals,
            page_table: &page_texture,
            elevation: &array_view(device, elevation.as_ref().map(|a| &a.texture), wgpu::TextureFormat::R32Float),
            elevation_shade: &array_view(device, elevation.as_ref().and_then(|a| a.shade.as_ref()), SHADE_FORMAT),
            colour: &array_view(device, texture.as_ref().map(|a| &a.texture), wgpu::TextureFormat::Rgba8UnormSrgb),
            lattice: &lattice,
            air: &air_tables,
            earth: &earth,
        };
        let bind_group = resources.bind_group(device, &shared.layout);
        let pipeline = shared.pipeline.clone();
        let mesh = PatchMesh::new(settings.patch);
        let (vertices, indices) = patch_buffers(device, &mesh);
        let instance_capacity = 1024;
        let instances = instance_buffer(device, instance_capacity);
        let params = mesh_params(metadata, elevation.as_ref(), settings.patch);
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
            earth,
            earth_drawn: None,
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

    /// Does a frame with `settings` on `surface` draw the whole-Earth picture (where it
    /// draws the sky)?
    fn draws_earth(settings: &RenderSettings, surface: &Surface) -> bool {
        surface.globe().is_some() && settings.shading == Shading::Lit && settings.atmosphere && settings.earth
    }

    /// Is the whole-Earth picture that frames draw still to come (decoded elsewhere and not
    /// yet written)? Until it is, they draw the plain ground beyond the data: a still
    /// waits for it as for its tiles.
    pub fn earth_pending(&self) -> bool {
        Self::draws_earth(&self.settings, &self.surface) && self.earth_drawn.is_none()
    }

    /// Most tiles of one layer the GPU keeps: the streaming selection should want no more.
    pub fn max_resident_tiles(&self) -> usize {
        let slots = |a: &Option<TileArray>| a.as_ref().map_or(usize::MAX, |a| a.residency.capacity() as usize);
        slots(&self.elevation).min(slots(&self.texture))
    }

    pub(super) fn arrays(&self) -> impl Iterator<Item = &TileArray> {
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
            if !array.write(queue, placement.slot, tile.key, &tile.data, tile.size) {
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
            if let Some(globe) = self.surface.globe() {
                let (w, h) = lattice_size(&self.surface);
                let mut texels = vec![[0.0f32; 4]; w as usize * h as usize];
                if let Mapping::Lattice(l) = &globe.mapping {
                    for (t, v) in texels.iter_mut().zip(&l.values) {
                        #[allow(clippy::cast_possible_truncation)]
                        let lon_lat = [v.x as f32, v.y as f32];
                        t[..2].copy_from_slice(&lon_lat);
                    }
                }
                if let Some(n) = &globe.geoid_lattice {
                    for (t, v) in texels.iter_mut().zip(&n.values) {
                        t[2] = *v;
                    }
                }
                if (w, h) != (1, 1) {
                    write_layer(queue, &self.lattice, 0, bytemuck::cast_slice(&texels), (w * 16, h), (w, h));
                }
            }
        }
        if self.surface.globe().is_some() && self.settings.shading == Shading::Lit && self.settings.atmosphere {
            if self.earth_pending() {
                self.earth_drawn = super::earth::write_earth(queue, &self.earth);
            }
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
        // Full patches first, then quarters: two instanced draws; within each, nearest
        // first, so that the depth test rejects what nearer patches cover before it is
        // shaded.
        let distance = |n: &Node| {
            let units = params.node_units(n.level);
            #[allow(clippy::cast_precision_loss)]
            let centre = DVec3::new(
                (n.origin.0 as f64 + units as f64 * 0.5) * params.base,
                (column.0 + column.1) * 0.5,
                (n.origin.1 as f64 + units as f64 * 0.5) * params.base,
            );
            #[allow(clippy::cast_possible_truncation, clippy::cast_sign_loss)]
            let d = self.surface.place(centre).distance(eye) as u64;
            d
        };
        nodes.sort_by_cached_key(|n| (n.quarter, distance(n)));
        (nodes, params)
    }

    /// The GPU format of the texture tiles (`None` without a drawable texture layer):
    /// `Bc1RgbaUnormSrgb` / `Bc7RgbaUnormSrgb` when compressed tiles go up as blocks.
    pub fn texture_format(&self) -> Option<wgpu::TextureFormat> {
        self.texture.as_ref().map(|t| t.format)
    }

    /// Records the terrain into `pass` (after [`Self::prepare`]).
    pub fn draw(&self, pass: &mut wgpu::RenderPass<'_>) {
        self.draw_terrain(pass);
        // The sky last, where no terrain was drawn (its depth test keeps it there).
        if self.sky {
            pass.set_pipeline(&self.air_pipelines.sky);
            pass.set_bind_group(0, &self.bind_group, &[]);
            pass.draw(0..3, 0..1);
        }
    }

    fn draw_terrain(&self, pass: &mut wgpu::RenderPass<'_>) {
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
