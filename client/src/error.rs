//! The client's error type.

use terrastream_format::TileKey;

/// Everything that can go wrong while opening, streaming, decoding or querying a terrain.
///
/// Variants carry the URL, status, tile or point at fault so that a message names it.
#[derive(Debug, thiserror::Error)]
#[non_exhaustive]
pub enum Error {
    /// Reading the archive failed: a damaged section or tile, a failed byte range (each
    /// named in the message).
    #[error(transparent)]
    Format(terrastream_format::Error),
    /// The archive was replaced while it was being read (its ETag or length changed):
    /// everything cached from it must be dropped, never mixed with the new version.
    #[error("the archive changed while being read ({what})")]
    Changed {
        /// What changed, e.g. `ETag "a" -> "b"`.
        what: String,
    },
    /// A location that is not a URL this client can fetch.
    #[error("{url}: {reason}")]
    BadUrl {
        /// The location given.
        url: String,
        /// What is wrong with it.
        reason: String,
    },
    /// In the browser only URLs can be opened, not files.
    #[error("{location}: the browser opens URLs only, not files")]
    NotAUrl {
        /// The location given.
        location: String,
    },
    /// The HTTP client could not be built (TLS roots, system settings).
    #[error("cannot start an HTTP client: {reason}")]
    HttpClient {
        /// The client library's message.
        reason: String,
    },
    /// A request was answered with an unexpected HTTP status.
    #[error("{url}: HTTP {status}")]
    Status {
        /// The URL requested.
        url: String,
        /// The status received.
        status: u16,
    },
    /// A request failed below HTTP: connection, TLS, timeout, a cut body.
    #[error("{url}: {reason}")]
    Request {
        /// The URL requested.
        url: String,
        /// What failed.
        reason: String,
    },
    /// The archive is not open: its metadata has not arrived yet, or opening it failed.
    #[error("the archive is not open{}", match why { Some(why) => format!(": {why}"), None => " yet".into() })]
    NotOpen {
        /// Why opening failed, if it did.
        why: Option<String>,
    },
    /// The archive has no layer of the kind a query needs.
    #[error("the archive has no {kind} layer")]
    NoLayer {
        /// The kind, e.g. "elevation".
        kind: &'static str,
    },
    /// A ground point outside a layer's extent.
    #[error("({x}, {z}) is outside layer {layer:?}")]
    Outside {
        /// The layer's name.
        layer: String,
        /// East, in world units.
        x: f64,
        /// South, in world units.
        z: f64,
    },
    /// A tile's payload is not what its layer says (format, size, encoding), or what a
    /// decoding thread (a browser's Web Worker) handed back is not a decoded tile.
    #[error(transparent)]
    Tile(terrastream_tiles::Error),
    /// A tile could not be fetched or decoded for a blocking query.
    #[error("tile {key} could not be loaded: {reason}")]
    TileLoad {
        /// The tile.
        key: TileKey,
        /// What failed.
        reason: String,
    },
    /// The worker threads could not be started.
    #[error("cannot start the streamer's worker threads: {0}")]
    Threads(std::io::Error),
}

impl From<terrastream_format::Error> for Error {
    fn from(error: terrastream_format::Error) -> Self {
        match error {
            terrastream_format::Error::Changed { what } => Self::Changed { what },
            other => Self::Format(other),
        }
    }
}

impl From<terrastream_tiles::Error> for Error {
    fn from(error: terrastream_tiles::Error) -> Self {
        match error {
            terrastream_tiles::Error::Format(e) => e.into(),
            other => Self::Tile(other),
        }
    }
}

/// Result alias of this crate.
pub type Result<T, E = Error> = std::result::Result<T, E>;
