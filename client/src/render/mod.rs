//! The wgpu renderer: a CDLOD mesh morphing between levels, heights read in the vertex
//! shader from GPU-resident elevation tiles, every texture LOD blended in one pass, tiles
//! found through a page table; offscreen targets for headless rendering.

pub mod atmosphere;
mod earth;
mod frame;
pub mod gpu;
pub mod hud;
pub mod mesh;
mod pipeline;
pub mod renderer;
pub mod residency;
pub mod session;
mod settings;
#[cfg(not(target_arch = "wasm32"))]
pub mod still;
mod tile_array;

pub use earth::{EarthPicture, decoded_elsewhere, decoding_elsewhere};
/// The wgpu version the renderer is built with (hosts create surfaces and passes with it).
pub use wgpu;
