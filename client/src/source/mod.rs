//! Byte-range sources.

#[cfg(not(target_arch = "wasm32"))]
pub mod blocking;
pub mod http;

/// Is `location` an `http://` or `https://` URL (rather than a file path)?
pub(crate) fn is_http_url(location: &str) -> bool {
    location.starts_with("http://") || location.starts_with("https://")
}
