//! Fixtures shared by the tests of every terrastream crate: small archives written on the
//! spot, labelled archives, a generated continent, the server and nginx on loopback ports,
//! a plain HTTP client, and comparison of rendered images with committed references.
//!
//! Test code: it panics on failure instead of returning errors.
#![allow(
    missing_docs,
    clippy::unwrap_used,
    clippy::expect_used,
    clippy::missing_panics_doc,
    clippy::cast_possible_truncation
)]

pub mod archives;
pub mod browser;
pub mod continent;
pub mod golden;
pub mod http;
/// Labelled archives (they live in `terrastream-pack`: `bench stream` streams them).
pub use terrastream_pack::labelled;
pub mod nginx;
pub mod server;
/// The emulated link (it lives in `terrastream-server`: `bench stream` runs over it).
pub use terrastream_server::shaper;
