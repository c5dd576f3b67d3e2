//! The error type of writing, importing, extracting and exporting.

use std::path::PathBuf;

use terrastream_format::TileKey;

/// Everything that can go wrong while writing an archive, importing a tile set into one,
/// or extracting and exporting one.
///
/// Variants carry the file, line or tile at fault so that a message names it.
#[derive(Debug, thiserror::Error)]
#[non_exhaustive]
pub enum Error {
    /// Reading an archive (the input of extract and export, or a written one) failed.
    #[error(transparent)]
    Format(#[from] terrastream_format::Error),
    /// A tile was added before one that sorts earlier (see `Writer::order_key`).
    #[error("{tile} added out of archive order (sort by Writer::order_key)")]
    OutOfOrder {
        /// The tile added.
        tile: TileKey,
    },
    /// A tile was added with no bytes: a missing tile is left out instead.
    #[error("{tile}: empty payload (leave the tile missing instead)")]
    EmptyTile {
        /// The tile added.
        tile: TileKey,
    },
    /// A payload or a directory is over the format's 4 GiB limit for one blob.
    #[error("{what} of {len} bytes is over the format's 4 GiB limit")]
    TooLarge {
        /// What: a tile, a leaf directory, a PMTiles leaf.
        what: String,
        /// Its length.
        len: u64,
    },
    /// `Writer::set_metadata` was given layers with other grids than the archive's.
    #[error("set_metadata may not change the layers' grids (layer {layer:?})")]
    GridChanged {
        /// The first layer whose grid differs.
        layer: String,
    },
    /// A layer named or numbered by the caller is not in the archive.
    #[error("no layer {layer} in the archive")]
    NoSuchLayer {
        /// The name or index asked for.
        layer: String,
    },
    /// A line of an original-engine metadata text could not be parsed.
    #[error("{path}:{line}: {reason}")]
    OriginalMetadata {
        /// The metadata text file.
        path: PathBuf,
        /// 1-based line number.
        line: usize,
        /// What is wrong with the line.
        reason: String,
    },
    /// An input file or folder of an import is unusable.
    #[error("{path}: {reason}")]
    Input {
        /// The file or folder at fault.
        path: PathBuf,
        /// What is wrong with it.
        reason: String,
    },
    /// An I/O error on a named file. The message carries the OS error itself (it is not
    /// also the error's `source`, which would print it twice in a chain of causes).
    #[error("{path}: {error}")]
    File {
        /// The file.
        path: PathBuf,
        /// The underlying error.
        error: std::io::Error,
    },
    /// Compressing a directory or metadata in memory failed (the compressor could not
    /// allocate).
    #[error("cannot compress {what}: {error}")]
    Compress {
        /// What was being compressed.
        what: &'static str,
        /// The compressor's error.
        error: std::io::Error,
    },
    /// An I/O error on a temporary file of the writer (beside the output, so that the
    /// final rename is atomic).
    #[error("temporary file in {folder}: {error}")]
    Temporary {
        /// The folder holding the temporary files.
        folder: PathBuf,
        /// The underlying error.
        error: std::io::Error,
    },
    /// An in-place update does not fit the room the archive has for one (FORMAT.md §7.1);
    /// the archive is as it was. Rewriting it (a merge into a new file) always works.
    #[error("{path}: no room for an update in place: {why}")]
    NoRoom {
        /// The archive.
        path: PathBuf,
        /// What does not fit.
        why: String,
    },
    /// The operation was interrupted (Ctrl-C); nothing was written under the final name.
    #[error("interrupted")]
    Interrupted(#[from] terrastream_format::Interrupted),
}

impl Error {
    pub(crate) fn file(path: impl Into<PathBuf>, error: std::io::Error) -> Self {
        Self::File { path: path.into(), error }
    }

    pub(crate) fn input(path: impl Into<PathBuf>, reason: impl Into<String>) -> Self {
        Self::Input { path: path.into(), reason: reason.into() }
    }

    pub(crate) fn metadata(error: &serde_json::Error) -> Self {
        Self::Format(terrastream_format::Error::Metadata(error.to_string()))
    }

    pub(crate) fn too_large(what: impl Into<String>, len: usize) -> Self {
        Self::TooLarge { what: what.into(), len: len as u64 }
    }
}

/// Result alias of this crate.
pub type Result<T, E = Error> = std::result::Result<T, E>;
