//! The wgpu renderer: a CDLOD mesh morphing between levels, heights read in the vertex
//! shader from GPU-resident elevation tiles, every texture LOD blended in one pass, tiles
//! found through a page table; offscreen targets for headless rendering.

pub mod atmosphere;
pub mod gpu;
pub mod hud;
pub mod mesh;
pub mod renderer;
pub mod residency;
pub mod session;
#[cfg(not(target_arch = "wasm32"))]
pub mod still;

/// The wgpu version the renderer is built with (hosts create surfaces and passes with it).
pub use wgpu;
