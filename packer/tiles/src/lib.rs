//! Decoded terrastream tiles and the heights they hold: every stored encoding (PNG, WebP,
//! JPEG, raw u16/f32, zstd and gradient-coded payloads, GPU blocks) decoded into
//! [`DecodedTile`]s, nodata as NaN, bilinear/bicubic height sampling, and which tile of
//! which LOD holds a ground point.
//!
//! The one place tiles are decoded: the client (its streamer and the webplayer's
//! workers), the pack crate (reading pyramids it imports) and the views (web tiles,
//! quantized-mesh, elevation points) all use it. No I/O, no async; builds for wasm32.
#![forbid(unsafe_code)]

mod decode;
mod error;
mod image;
mod sample;
mod shade;

pub use decode::{DecodedTile, TileData, decode};
pub use error::{Error, Result};
pub use image::Image;
pub use sample::{Interpolation, height_on_lod, tile_of};
pub use shade::{flat_sea, shade_texels};
