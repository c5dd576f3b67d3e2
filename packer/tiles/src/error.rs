//! The tile decoder's error type.

use terrastream_format::TileKey;

/// Why a tile's bytes are not the tile its layer says.
#[derive(Debug, thiserror::Error)]
#[non_exhaustive]
pub enum Error {
    /// The payload's compression could not be undone (named in the message).
    #[error(transparent)]
    Format(#[from] terrastream_format::Error),
    /// A tile's payload is not what its layer says (format, size, encoding).
    #[error("tile {key} of layer {layer:?}: {reason}")]
    BadTile {
        /// The tile.
        key: TileKey,
        /// Its layer's name.
        layer: String,
        /// What is wrong.
        reason: String,
    },
    /// What a decoding thread (a browser's Web Worker) handed back is not a decoded tile.
    #[error("a decoded tile from a worker: {reason}")]
    Wire {
        /// What is wrong with it.
        reason: String,
    },
}

/// Result alias of this crate.
pub type Result<T, E = Error> = std::result::Result<T, E>;
