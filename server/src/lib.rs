//! HTTP hosting of terrastream archives (tokio + axum): Range requests on the archive, a tile endpoint.
#![forbid(unsafe_code)]
