//! HTTP hosting of terrastream archives (tokio + axum): the raw archive with RFC 9110
//! Range and conditional requests (any HTTP client, browser or CDN can stream from it),
//! a tile endpoint, metadata, listing, health and Prometheus metrics; and the ecosystem's
//! protocols ([`web`]): TileJSON, Web Mercator XYZ tiles made from any archive, an
//! elevation API shaped like Open Topo Data's. Archives are memory-mapped and
//! hot-reloaded; bodies are slices of the mapping.
#![forbid(unsafe_code)]

pub mod access;
mod app;
mod body;
mod catalog;
mod config;
mod edge;
mod h1;
mod metrics;
pub mod player;
mod range;
mod route;
mod sendfile;
mod serve;
pub mod shaper;
pub mod web;

pub use app::{ARCHIVE_ETAG, AppError, AppInner, AppState, FALLBACK_LOD, StartError, app, service};
pub use catalog::{Catalog, Served, archive_name};
pub use config::ServerConfig;
pub use edge::Edge;
#[doc(hidden)]
pub use h1::inspect_head;
pub use metrics::Metrics;
pub use range::{Precondition, RangeOutcome, if_range_allows, parse_range, preconditions};
pub use route::Route;
pub use serve::{serve, serve_workers, shutdown_signal};
