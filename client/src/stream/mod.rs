//! The streaming core: which tiles the camera needs, fetching them (coalesced, capped,
//! cancelled when stale, retried), decoding them off the frame thread, caching them, and
//! handing them to the renderer within a per-frame budget. GPU-independent.

pub mod cache;
pub mod camera;
pub mod heights;
pub mod origin;
pub mod select;
pub mod streamer;
