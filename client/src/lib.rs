//! The terrastream client: byte-range sources for archives anywhere — a local file
//! (mmap), any HTTP server or CDN that honours `Range` — behind the archive reader's
//! [`terrastream_packer::AsyncRangeSource`] trait.
#![forbid(unsafe_code)]

mod source;

#[cfg(not(target_arch = "wasm32"))]
pub use source::blocking::{AnySource, BlockingSource, open_source};
pub use source::http::{HttpSource, HttpStats, RetryPolicy};
