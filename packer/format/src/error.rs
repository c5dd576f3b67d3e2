//! The reader's error type.

use std::path::PathBuf;

use crate::key::TileKey;

/// Everything that can go wrong while reading an archive.
///
/// Variants carry the offset, section, tile or path at fault so that a message names it.
#[derive(Debug, thiserror::Error)]
#[non_exhaustive]
pub enum Error {
    /// The first bytes are not a terrastream archive.
    #[error("not a tspack archive (bad magic bytes)")]
    BadMagic,
    /// The archive's major version is one this reader does not understand.
    #[error("unsupported tspack version {major}.{minor} (this reader reads 1.x and 2.x)")]
    UnsupportedVersion {
        /// Major version found in the header.
        major: u16,
        /// Minor version found in the header.
        minor: u16,
    },
    /// A structural field of a section is inconsistent or out of range.
    #[error("corrupt {section}: {reason}")]
    Corrupt {
        /// Which section: "header", "metadata", "root directory", "leaf directory at offset N", ...
        section: String,
        /// What is wrong with it.
        reason: String,
    },
    /// A section's stored checksum does not match its bytes.
    #[error("checksum mismatch in {section}: stored {stored:#010x}, computed {computed:#010x}")]
    SectionChecksum {
        /// The damaged section.
        section: String,
        /// Checksum found in the file.
        stored: u32,
        /// Checksum of the bytes read.
        computed: u32,
    },
    /// A tile's stored checksum does not match its payload.
    #[error(
        "checksum mismatch in tile {key} at data offset {offset}: stored {stored:#010x}, computed {computed:#010x}"
    )]
    TileChecksum {
        /// The damaged tile (first tile that refers to the damaged bytes).
        key: TileKey,
        /// Offset of the tile relative to the data section.
        offset: u64,
        /// Checksum found in the file.
        stored: u32,
        /// Checksum of the payload read.
        computed: u32,
    },
    /// A range points outside the file or the section it belongs to.
    #[error("{what} [{offset}, +{len}) lies outside the {limit_name} ({limit} bytes)")]
    OutOfBounds {
        /// What was being read.
        what: String,
        /// Start of the range.
        offset: u64,
        /// Length of the range.
        len: u64,
        /// Name of the enclosing region.
        limit_name: &'static str,
        /// Size of the enclosing region.
        limit: u64,
    },
    /// A tile key is outside the limits of the format or of its layer's grid.
    #[error("invalid tile {what}")]
    InvalidTile {
        /// Description of the tile and the violated limit.
        what: String,
    },
    /// Decompression failed or exceeded its size limit.
    #[error("cannot decompress {section}: {reason}")]
    Decompress {
        /// Section being decompressed.
        section: String,
        /// Decoder message.
        reason: String,
    },
    /// The metadata JSON is invalid.
    #[error("invalid metadata: {0}")]
    Metadata(String),
    /// A manifest (FORMAT.md §9) is invalid, or an archive it names is not the one found.
    #[error("manifest: {0}")]
    Manifest(String),
    /// An I/O error on a named file. The message carries the OS error itself (it is not
    /// also the error's `source`, which would print it twice in a chain of causes).
    #[error("{path}: {error}")]
    File {
        /// The file.
        path: PathBuf,
        /// The underlying error.
        error: std::io::Error,
    },
    /// An I/O error from a byte source (file, mmap, network).
    #[error("read error at [{offset}, +{len}): {reason}")]
    Source {
        /// Start of the failed read.
        offset: u64,
        /// Length of the failed read.
        len: u64,
        /// The backend's message.
        reason: String,
    },
    /// The archive was replaced while it was being read (its ETag or length changed):
    /// everything cached from it must be dropped, never mixed with the new version.
    #[error("the archive changed while being read ({what})")]
    Changed {
        /// What changed, e.g. `ETag "a" -> "b"`.
        what: String,
    },
    /// Any other I/O error.
    #[error(transparent)]
    Io(#[from] std::io::Error),
}

impl Error {
    pub(crate) fn corrupt(section: impl Into<String>, reason: impl Into<String>) -> Self {
        Self::Corrupt { section: section.into(), reason: reason.into() }
    }

    #[cfg_attr(target_arch = "wasm32", expect(dead_code, reason = "file backends"))]
    pub(crate) fn file(path: impl Into<PathBuf>, error: std::io::Error) -> Self {
        Self::File { path: path.into(), error }
    }
}

/// A long operation stopped because it was asked to (Ctrl-C): the one cancellation type
/// of every crate. Their errors carry it as their source, so a caller finds it in any
/// error's chain of causes, whichever crate stopped.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, thiserror::Error)]
#[error("interrupted")]
pub struct Interrupted;

/// Result alias of this crate.
pub type Result<T, E = Error> = std::result::Result<T, E>;
