//! The terrastream client: byte-range sources for archives anywhere — a local file
//! (mmap), any HTTP server or CDN that honours `Range` — and the streaming core that
//! turns a camera into a per-frame stream of decoded tiles.
#![forbid(unsafe_code)]

mod error;
pub mod fly;
pub mod geo;
pub mod globe;
pub mod input;
#[cfg(feature = "render")]
pub mod render;
mod source;
pub mod stream;

pub use error::{Error, Result};
pub use fly::{FlyCamera, FlyInput};
pub use geo::Geo;
pub use globe::{GlobeMap, Surface};
pub use input::{Action, Keys};
#[cfg(not(target_arch = "wasm32"))]
pub use source::blocking::{AnySource, BlockingSource, open_source};
pub use source::http::{HttpSource, HttpStats, RetryPolicy};
pub use stream::cache::TileCache;
pub use stream::camera::{Aabb, Camera, Frustum, SceneBox};
pub use stream::origin::{DynSource, EndpointSource, HostTiles, ManifestSource, Origin};
pub use stream::select::{SelectOptions, Want, select};
pub use stream::streamer::{
    DecodeFailure, DecodeResult, Decoder, StreamOptions, StreamStats, Streamer, Upload, UploadBudget,
};
pub use terrastream_format::is_manifest_location;
pub use terrastream_tiles::{DecodedTile, Interpolation, TileData, decode, height_on_lod};
