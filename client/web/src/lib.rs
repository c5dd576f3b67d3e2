//! The terrastream webplayer: the client crate compiled to WebAssembly. It streams an
//! archive with Range requests (the browser's `fetch`), renders with wgpu on WebGPU
//! where the browser has it and WebGL2 otherwise, with the same shaders as the native
//! viewer, and flies with the same camera. `static/player.html` is the page around it;
//! `static/decoder.js` the Web Worker that decodes tiles off the page's thread.
//!
//! On targets other than `wasm32` the crate is empty.

#![recursion_limit = "256"]

#[cfg(target_arch = "wasm32")]
mod log;
#[cfg(target_arch = "wasm32")]
mod player;
#[cfg(target_arch = "wasm32")]
mod workers;
