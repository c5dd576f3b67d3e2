//! The terrastream client: byte-range sources, tile scheduler, cache, renderer.
#![forbid(unsafe_code)]
