//! The raster crate's error type.

use std::path::PathBuf;

pub use terrastream_format::Interrupted;

pub use crate::jpegrows::JpegError;
pub use crate::rawchunk::ChunkError;

/// Everything that can go wrong while reading rasters.
///
/// Every variant that concerns a file names it, so that a message says which of thousands
/// of inputs is at fault; decoders' own errors are kept as sources, not flattened to text.
#[derive(Debug, thiserror::Error)]
#[non_exhaustive]
pub enum Error {
    /// An I/O error on a named file (the message carries the OS error itself).
    #[error("{path}: {error}")]
    File {
        /// The file.
        path: PathBuf,
        /// The underlying error.
        error: std::io::Error,
    },
    /// An input that is not there: no such file, a pattern or folder that matches nothing.
    #[error("{path}: {reason}")]
    NotFound {
        /// The input as given.
        path: PathBuf,
        /// What was looked for.
        reason: &'static str,
    },
    /// A file that another (a VRT) names, and that is not there.
    #[error("{path}: named by {} but missing", named_by.display())]
    NamedButMissing {
        /// The file named.
        path: PathBuf,
        /// The file that names it.
        named_by: PathBuf,
    },
    /// A geoid model's grid that is nowhere to be found.
    #[error("geoid grid {} not found: looked in {} (install Debian's proj-data, put the grid in one of them or set PROJ_DATA, or name the file with --vertical-datum geoid:FILE)", grids.join(" or "), looked.iter().map(|p| p.display().to_string()).collect::<Vec<_>>().join(", "))]
    GeoidMissing {
        /// The grid files that hold the model.
        grids: Vec<String>,
        /// The folders looked in.
        looked: Vec<PathBuf>,
    },
    /// A file in a format, or using a feature of one, that is not read here.
    #[error("{path}: {what}")]
    Unsupported {
        /// The file.
        path: PathBuf,
        /// What is not read.
        what: String,
    },
    /// A file whose content contradicts itself or its format: damaged or cut short.
    #[error("{path}: {reason}")]
    Damaged {
        /// The file.
        path: PathBuf,
        /// What is wrong with it.
        reason: String,
    },
    /// The TIFF decoder refused the file, or one of its strips or tiles.
    #[error("{path}: {at}{error}")]
    Tiff {
        /// The file.
        path: PathBuf,
        /// What was being read (empty, or ending in ": ").
        at: String,
        /// The decoder's error.
        error: tiff::TiffError,
    },
    /// A strip or tile read directly from the file failed.
    #[error("{path}: reading {what} {index}: {error}")]
    Chunk {
        /// The file.
        path: PathBuf,
        /// "strip" or "tile".
        what: &'static str,
        /// The chunk's index in the file's offset table.
        index: usize,
        /// What went wrong.
        error: ChunkError,
    },
    /// The PNG decoder refused the file or one of its rows.
    #[error("{path}: PNG{}: {error}", row.map(|r| format!(", row {r}")).unwrap_or_default())]
    Png {
        /// The file.
        path: PathBuf,
        /// The row being read, once past the header.
        row: Option<u32>,
        /// The decoder's error.
        error: png::DecodingError,
    },
    /// A JPEG that cannot be read (by rows, or at all).
    #[error("{path}: JPEG: {error}")]
    Jpeg {
        /// The file.
        path: PathBuf,
        /// What is wrong with it.
        error: JpegError,
    },
    /// An XML side file (VRT, `.aux.xml`) that is not well-formed.
    #[error("{path}: {what}: {error}")]
    Xml {
        /// The file.
        path: PathBuf,
        /// What it should have been.
        what: &'static str,
        /// The parser's error.
        error: roxmltree::Error,
    },
    /// Where a file lies is missing, malformed, or cannot be used.
    #[error("{path}: {reason}")]
    Georeference {
        /// The file (or its world file, `.prj` or `.aux.xml`).
        path: PathBuf,
        /// What is wrong.
        reason: String,
    },
    /// Inputs that do not fit together: an image that does not cover the elevation, a
    /// height outside a range given, a mosaic larger than can be made.
    #[error("{path}: {reason}")]
    Mismatch {
        /// The input that does not fit.
        path: PathBuf,
        /// How.
        reason: String,
    },
    /// A coordinate reference system that cannot be used.
    #[error("unknown CRS {crs}: {reason}")]
    UnknownCrs {
        /// The CRS as given.
        crs: String,
        /// Why it cannot be used.
        reason: String,
    },
    /// An option outside the values it allows.
    #[error("{option} {value}: allowed {allowed}")]
    InvalidOption {
        /// The option, as the command line names it.
        option: &'static str,
        /// The value given.
        value: String,
        /// What is allowed.
        allowed: &'static str,
    },
    /// A mosaic of no files.
    #[error("no input raster given")]
    NoInput,
    /// A worker thread panicked; its work is lost.
    #[error("the {thread} thread panicked")]
    Panicked {
        /// Which thread.
        thread: &'static str,
    },
    /// The consumer of the rows (a callback given to a read) failed: its own error, kept
    /// whole so that the consumer gets it back (the tiler turns it into its own again).
    #[error(transparent)]
    Consumer(Box<dyn std::error::Error + Send + Sync>),
    /// The read was stopped on request (Ctrl-C, or a consumer that went away).
    #[error(transparent)]
    Interrupted(#[from] Interrupted),
}

impl Error {
    pub(crate) fn file(path: impl Into<PathBuf>, error: std::io::Error) -> Self {
        Self::File { path: path.into(), error }
    }

    pub(crate) fn unsupported(path: impl Into<PathBuf>, what: impl Into<String>) -> Self {
        Self::Unsupported { path: path.into(), what: what.into() }
    }

    pub(crate) fn damaged(path: impl Into<PathBuf>, reason: impl Into<String>) -> Self {
        Self::Damaged { path: path.into(), reason: reason.into() }
    }

    pub(crate) fn georeference(path: impl Into<PathBuf>, reason: impl Into<String>) -> Self {
        Self::Georeference { path: path.into(), reason: reason.into() }
    }

    pub(crate) fn mismatch(path: impl Into<PathBuf>, reason: impl Into<String>) -> Self {
        Self::Mismatch { path: path.into(), reason: reason.into() }
    }

    pub(crate) fn tiff(path: impl Into<PathBuf>, at: impl Into<String>, error: tiff::TiffError) -> Self {
        Self::Tiff { path: path.into(), at: at.into(), error }
    }

    /// True when the run stopped because it was asked to.
    pub fn is_interrupted(&self) -> bool {
        matches!(self, Self::Interrupted(_))
    }

    /// True for a fault of one input file (unreadable, damaged, unsupported, misplaced),
    /// as opposed to a stop, an option or a CRS: what a mosaic that skips bad inputs skips.
    pub fn is_bad_input(&self) -> bool {
        matches!(
            self,
            Self::File { .. }
                | Self::NotFound { .. }
                | Self::NamedButMissing { .. }
                | Self::Unsupported { .. }
                | Self::Damaged { .. }
                | Self::Tiff { .. }
                | Self::Chunk { .. }
                | Self::Png { .. }
                | Self::Jpeg { .. }
                | Self::Xml { .. }
                | Self::Georeference { .. }
                | Self::Mismatch { .. }
        )
    }
}

impl From<terrastream_crs::UnknownCrs> for Error {
    fn from(e: terrastream_crs::UnknownCrs) -> Self {
        Self::UnknownCrs { crs: e.crs, reason: e.reason }
    }
}

/// Result alias of this crate.
pub type Result<T, E = Error> = std::result::Result<T, E>;
