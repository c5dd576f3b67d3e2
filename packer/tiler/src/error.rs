//! The tiler's error type.

use std::path::PathBuf;

use terrastream_format::TileKey;

/// Everything that can go wrong while tiling rasters into an archive.
///
/// Variants carry the file, option or tile at fault so that a message names it.
#[derive(Debug, thiserror::Error)]
#[non_exhaustive]
pub enum Error {
    /// Writing the archive failed (or was interrupted: `terrastream_pack::Error::Interrupted`,
    /// whose source is the one [`terrastream_format::Interrupted`]).
    #[error(transparent)]
    Pack(#[from] terrastream_pack::Error),
    /// Reading an input raster failed (or was interrupted: `terrastream_raster::Error::Interrupted`,
    /// the same [`terrastream_format::Interrupted`]).
    #[error(transparent)]
    Raster(terrastream_raster::Error),
    /// An option is outside the values it allows.
    #[error("{option} {value}: allowed {allowed}")]
    InvalidOption {
        /// The option, as the CLI names it.
        option: &'static str,
        /// The value given.
        value: String,
        /// What is allowed.
        allowed: &'static str,
    },
    /// Neither an elevation raster nor a texture image was given.
    #[error("nothing to tile: give an elevation raster, a texture image or both")]
    NothingToTile,
    /// An input that cannot be used as given: an archive to edit or merge that does not
    /// fit the others, a manifest's target, inputs of a run that do not fit its options.
    #[error("{path}: {reason}")]
    Input {
        /// The file at fault.
        path: PathBuf,
        /// What is wrong with it.
        reason: String,
    },
    /// An I/O error on a named file (the message carries the OS error itself).
    #[error("{path}: {error}")]
    File {
        /// The file.
        path: PathBuf,
        /// The underlying error.
        error: std::io::Error,
    },
    /// A tile could not be encoded in its layer's format.
    #[error("tile {tile}: cannot encode: {reason}")]
    Encode {
        /// The tile.
        tile: TileKey,
        /// The encoder's message.
        reason: String,
    },
    /// A tile is larger than its format can hold.
    #[error("tile edge {edge} is too large for {format}")]
    TileTooLarge {
        /// Pixels per tile edge.
        edge: usize,
        /// The format's name.
        format: &'static str,
    },
    /// The pyramid was fed against its contract (a bug of the caller, reported rather than
    /// panicking): a row too many or too few, a layer not in the metadata.
    #[error("pyramid of layer {layer}, LOD {lod}: {reason}")]
    Pyramid {
        /// The layer.
        layer: u8,
        /// The level.
        lod: u8,
        /// What went wrong.
        reason: String,
    },
    /// Reading or writing the spool of encoded tiles (a temporary file) failed.
    #[error("the tile spool (a temporary file): {0}")]
    Spool(std::io::Error),
    /// A worker thread panicked; its work is lost and nothing was written.
    #[error("the {thread} thread panicked")]
    Panicked {
        /// Which thread.
        thread: &'static str,
    },
}

impl Error {
    pub(crate) fn file(path: impl Into<PathBuf>, error: std::io::Error) -> Self {
        Self::File { path: path.into(), error }
    }

    pub(crate) fn input(path: impl Into<PathBuf>, reason: impl Into<String>) -> Self {
        Self::Input { path: path.into(), reason: reason.into() }
    }

    pub(crate) fn option(option: &'static str, value: impl ToString, allowed: &'static str) -> Self {
        Self::InvalidOption { option, value: value.to_string(), allowed }
    }

    /// True when the run stopped because it was asked to (Ctrl-C).
    pub fn is_interrupted(&self) -> bool {
        matches!(
            self,
            Self::Pack(terrastream_pack::Error::Interrupted(_))
                | Self::Raster(terrastream_raster::Error::Interrupted(_))
        )
    }
}

impl From<terrastream_format::Error> for Error {
    fn from(error: terrastream_format::Error) -> Self {
        Self::Pack(error.into())
    }
}

/// A raster read's error; the tiler's own error where a tiler step fed by the read failed.
impl From<terrastream_raster::Error> for Error {
    fn from(error: terrastream_raster::Error) -> Self {
        match error {
            terrastream_raster::Error::Consumer(inner) => match inner.downcast::<Self>() {
                Ok(own) => *own,
                Err(other) => Self::Raster(terrastream_raster::Error::Consumer(other)),
            },
            other => Self::Raster(other),
        }
    }
}

impl From<terrastream_raster::UnknownCrs> for Error {
    fn from(error: terrastream_raster::UnknownCrs) -> Self {
        Self::Raster(error.into())
    }
}

/// A tiler step that consumes a raster read's rows stops the read with its own error.
impl From<Error> for terrastream_raster::Error {
    fn from(error: Error) -> Self {
        match error {
            Error::Raster(raster) => raster,
            own => Self::Consumer(Box::new(own)),
        }
    }
}

/// Result alias of this crate.
pub type Result<T, E = Error> = std::result::Result<T, E>;

/// The error of a run stopped on request.
pub(crate) fn interrupted() -> Error {
    Error::Pack(terrastream_format::Interrupted.into())
}
