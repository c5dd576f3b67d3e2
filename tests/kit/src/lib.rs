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
pub mod continent;
pub mod golden;
pub mod http;
pub mod labelled;
pub mod nginx;
pub mod server;
pub mod shaper;
