//! What a terrastream archive becomes for the clients people already use, with no HTTP in
//! it: Web Mercator XYZ tiles and TileJSON documents (MapLibre GL JS, deck.gl,
//! OpenLayers), quantized-mesh terrain with its `layer.json` (CesiumJS), heights at
//! points (an elevation API shaped like Open Topo Data's), and the exports that write
//! them to folders for static hosting.
//!
//! Products are functions of an archive ([`terrastream_format::Reader`]); the server
//! (`terrastream-server`) routes, caches, pools and limits requests over them, and the
//! command line's `export` writes them to files. Archive tiles are decoded by
//! `terrastream-tiles`, the CRS math is `terrastream-crs`'s.
#![forbid(unsafe_code)]

pub mod cache;
pub mod contours;
pub mod elevation;
pub mod encode;
pub mod export;
pub mod glyphs;
pub mod mercator;
pub mod mvt;
#[cfg(feature = "pmtiles")]
pub mod pmtiles;
pub mod quantized;
pub mod relief;
pub mod resample;
pub mod tilejson;
pub mod xyz;

pub use resample::{MakeError, Samples};
pub use xyz::{WebTileRequest, make_tile, make_tile_cached, tile_samples};
