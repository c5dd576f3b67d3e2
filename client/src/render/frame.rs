//! One frame's GPU resources: the shader's globals (camera, sun, haze, LODs, the globe's
//! placement), the atmosphere's uniform, the patch instances, and what the frame draws.

use bytemuck::{Pod, Zeroable};
use glam::{DMat4, DVec3, Mat4};

use super::atmosphere::AtmosphereUniform;
use super::mesh::{MAX_LEVELS, MeshParams, Node};
use super::renderer::TerrainRenderer;
use super::settings::{FrameStats, Shading, srgb_to_linear};
use super::tile_array::TileArray;
use crate::globe::Mapping;
use crate::stream::camera::Camera;

#[repr(C)]
#[derive(Clone, Copy, Pod, Zeroable)]
/// Where the anchor lies on one LOD of a layer: its tile and the fraction into it.
pub(super) struct LodInfo {
    pub(super) tile: [i32; 4],
    pub(super) frac: [f32; 4],
}

#[repr(C)]
#[derive(Clone, Copy, Pod, Zeroable)]
pub(super) struct Globals {
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
    geoid: [f32; 4],
    earth: [f32; 4],
}

const GLOBE_FLAT: u32 = 0;
const GLOBE_GEOGRAPHIC: u32 = 1;
const GLOBE_WEB_MERCATOR: u32 = 2;
const GLOBE_LATTICE: u32 = 3;

impl TerrainRenderer {
    /// Writes the frame's uniforms and instances for `nodes`, and its stats.
    pub(super) fn write_frame(
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
            let info = GlobeInfo {
                kind: [GLOBE_FLAT, 1, 1, 0],
                map: [0.0; 4],
                anchor: [0.0; 4],
                geoid: [0.0; 4],
                earth: [0.0; 4],
            };
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
        let column = self.surface.datum_height(eye).clamp(self.column.0, self.column.1);
        let (w, h) = super::renderer::lattice_size(&self.surface);
        let (kind, map) = match &globe.mapping {
            Mapping::Geographic { step, .. } => ([GLOBE_GEOGRAPHIC, w, h, 0], [step.x, step.y, 0.0, 0.0]),
            Mapping::WebMercator { origin, step } => {
                let v = origin.y + step.y * anchor.1;
                ([GLOBE_WEB_MERCATOR, w, h, 0], [step.x, step.y, v, frame.lon_lat.y])
            }
            Mapping::Lattice(l) => {
                let q = l.coordinates(anchor.0, anchor.1);
                ([GLOBE_LATTICE, w, h, 0], [q.x, q.y, 1.0 / l.cell, 0.0])
            }
        };
        // The anchor's coordinates on the geoid's lattice, its points per world unit, 1.
        let geoid = globe.geoid_lattice.as_ref().map_or([0.0; 4], |g| {
            let q = (glam::DVec2::new(anchor.0, anchor.1) - g.origin) / g.cell;
            [q.x, q.y, 1.0 / g.cell, 1.0]
        });
        // A ball inside the ellipsoid (its polar radius) and a kilometre below the
        // terrain's lowest point: what it hides, the Earth hides.
        let centre = frame.to_local(DVec3::ZERO);
        let radius = crate::globe::B - 1000.0 - (-globe.heights.0).max(0.0);
        #[allow(clippy::cast_possible_truncation)]
        let info = GlobeInfo {
            kind,
            map: map.map(|v| v as f32),
            anchor: [sin as f32, cos as f32, n as f32, column as f32],
            geoid: geoid.map(|v| v as f32),
            earth: [centre.x as f32, centre.y as f32, centre.z as f32, radius as f32],
        };
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
            (
                pole,
                frame.direction_to_local(DVec3::X),
                // Written only where the settings draw it.
                (self.earth_drawn == Some(true)).then(|| {
                    let (lon, lat, _) = crate::globe::geodetic(camera.position);
                    (lon.to_degrees(), lat.to_degrees())
                }),
            ),
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
        let flat = self.settings.shading != Shading::Lit;
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
                match self.settings.shading {
                    Shading::Lit => 0,
                    Shading::Flat => 1,
                    Shading::Baseline => 2,
                },
                u32::from(self.settings.wireframe),
                u32::from(self.settings.lod_colours),
                self.page_table.max_probes,
            ],
            lod: [
                (base / f64::from(elev_info[3])).log2() as f32,
                params.range(0) as f32,
                self.page_table.width.trailing_zeros() as f32,
                0.0,
            ],
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
}

pub(super) fn instance_buffer(device: &wgpu::Device, capacity: u64) -> wgpu::Buffer {
    device.create_buffer(&wgpu::BufferDescriptor {
        label: Some("buffer.terrain.instances"),
        size: capacity * 16,
        usage: wgpu::BufferUsages::VERTEX | wgpu::BufferUsages::COPY_DST,
        mapped_at_creation: false,
    })
}
