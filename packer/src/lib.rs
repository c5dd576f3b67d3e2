//! The terrastream archive format (`*.tspack`): one file holding every layer and LOD of a
//! terrain, indexed so that any tile is at most three reads away (one with directories
//! cached). The byte-level specification is `FORMAT.md` beside this crate.
//!
//! The reader ([`Reader`], [`AsyncReader`], and the I/O-free [`Archive`] core they share)
//! builds without default features and for `wasm32-unknown-unknown`; the `write` feature
//! adds the streaming [`Writer`] and the importers and exporters behind `terrastream pack`
//! and `terrastream extract`.
//!
//! ```
//! # fn main() -> Result<(), terrastream_packer::Error> {
//! use terrastream_packer::{MemorySource, Reader, TileKey};
//! # let bytes = terrastream_packer::sample::tiny_archive()?;
//! let reader = Reader::new(MemorySource::new(bytes))?;
//! let texture = reader.metadata().layer_index("texture").unwrap_or(0);
//! let coarsest = reader.metadata().layers[usize::from(texture)].num_lods - 1;
//! let tile = reader.tile(TileKey::new(texture, coarsest, 0, 0)?)?;
//! assert!(tile.is_some());
//! # Ok(()) }
//! ```

mod archive;
mod async_reader;
mod checksum;
mod compression;
mod directory;
mod error;
mod header;
mod key;
mod metadata;
pub mod progress;
pub mod protocol;
mod reader;
mod source;
mod stats;
mod varint;
mod verify;

#[cfg(feature = "write")]
pub mod export;
#[cfg(feature = "write")]
pub mod import;
#[cfg(feature = "write")]
pub mod original_metadata;
#[cfg(feature = "write")]
pub mod pmtiles;
#[cfg(feature = "write")]
pub mod sample;
#[cfg(feature = "write")]
pub mod tiler;
#[cfg(feature = "write")]
mod writer;

pub use archive::{Archive, Bootstrap, DEFAULT_LEAF_CACHE, Locate, MAX_METADATA_BYTES, TileLocation};
pub use async_reader::AsyncReader;
pub use checksum::crc32c;
#[cfg(feature = "write")]
pub use compression::zstd_compress;
pub use compression::{decompress, zstd_decompress};
pub use directory::{Directory, Entry, LeafPointer, MAX_DIRECTORY_BYTES, TILE_TRAILER_LEN};
pub use error::{Error, Result};
pub use header::{BOOTSTRAP_READ, Compression, HEADER_LEN, Header, MAGIC, Section, VERSION_MAJOR, VERSION_MINOR};
pub use key::{MAX_LAYERS, MAX_LODS, TileKey, tile_id_to_zxy, zxy_to_tile_id};
pub use metadata::{
    ElevationEncoding, ElevationScheme, Georeference, Layer, LayerKind, Metadata, OriginalField, PayloadCompression,
    Terrain, TileFormat, levels_to_one,
};
pub use reader::Reader;
pub use source::{AsyncRangeSource, MaybeSend, MaybeSync, MemorySource, RangeSource};
#[cfg(not(target_arch = "wasm32"))]
pub use source::{FileSource, MmapSource};
pub use stats::{ArchiveStats, LayerStats};
pub use varint::write_varint;
pub use verify::{VerifyReport, verify};
#[cfg(feature = "write")]
pub use writer::{WriteSummary, Writer, WriterOptions};
