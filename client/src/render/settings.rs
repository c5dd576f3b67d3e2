//! What a renderer is asked to draw (its settings) and what a frame drew (its stats).

use glam::DVec3;

/// How the terrain is shaded.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Default)]
pub enum Shading {
    /// Textured (or height-tinted), sunlit, hazy.
    #[default]
    Lit,
    /// Plain white, no light, no haze (coverage and crack checks).
    Flat,
    /// One texel read a pixel and nothing else: the cost of the mesh and the pixels
    /// alone, the floor `bench render` measures the lit frame against.
    Baseline,
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
    /// With the atmosphere: the Earth beyond the archive's data drawn from the built-in
    /// whole-Earth picture (continents, oceans, ice), else as plain ground.
    pub earth: bool,
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
            earth: true,
        }
    }
}

impl RenderSettings {
    /// The background colour a pass should clear to.
    pub fn clear_colour(&self) -> wgpu::Color {
        match self.shading {
            Shading::Flat | Shading::Baseline => wgpu::Color::BLACK,
            Shading::Lit => {
                let [r, g, b] = self.sky.map(|c| f64::from(srgb_to_linear(c)));
                wgpu::Color { r, g, b, a: 1.0 }
            }
        }
    }
}

pub(super) fn srgb_to_linear(c: f32) -> f32 {
    if c <= 0.04045 { c / 12.92 } else { ((c + 0.055) / 1.055).powf(2.4) }
}

/// Linear light (0..1) to an 8-bit sRGB value.
pub(super) fn linear_to_srgb_u8(c: f32) -> u8 {
    let c = c.clamp(0.0, 1.0);
    let s = if c <= 0.003_130_8 { c * 12.92 } else { 1.055 * c.powf(1.0 / 2.4) - 0.055 };
    #[allow(clippy::cast_possible_truncation, clippy::cast_sign_loss)]
    let v = (s * 255.0).round() as u8;
    v
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
