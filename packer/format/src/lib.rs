//! The terrastream archive format (`*.tspack`): one file holding every layer and LOD of a
//! terrain, indexed so that any tile is at most three reads away (one with directories
//! cached). The byte-level specification is `FORMAT.md` beside this crate.
//!
//! This crate is everything a reader needs, and nothing more: [`Reader`], [`AsyncReader`],
//! the I/O-free [`Archive`] core they share, [`verify`], [`ArchiveStats`], and the wire
//! protocol of the tile endpoint ([`protocol`]) that server and client share. It has no
//! features and builds for `wasm32-unknown-unknown`. Writing lives in `terrastream-pack`,
//! tiling rasters in `terrastream-tiler`.
//!
//! ```
//! # fn main() -> Result<(), terrastream_format::Error> {
//! use terrastream_format::{MemorySource, Reader, TileKey};
//! # let bytes = terrastream_testkit::archives::tiny_archive();
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
mod datum;
mod directory;
mod error;
mod extent;
mod gradient;
mod header;
mod key;
mod manifest;
mod metadata;
pub mod protocol;
mod ranges;
mod reader;
mod stats;
mod varint;
mod verify;

pub use archive::{
    Archive, Bootstrap, DEFAULT_LEAF_CACHE, Locate, MAX_LEAVES_READ_FOR_EXTENTS, MAX_METADATA_BYTES, TileLocation,
};
pub use async_reader::AsyncReader;
pub use checksum::crc32c;
pub use compression::{decompress, zstd_decompress};
pub use datum::{HeightReference, Undulation, VerticalDatum};
pub use directory::{Directory, Entry, LeafPointer, MAX_DIRECTORY_BYTES, TILE_TRAILER_LEN};
pub use error::{Error, Interrupted, Result};
pub use extent::{ExtentBuilder, LayerExtent, LevelCover, intersect, mercator_to_lon_lat, union};
pub use gradient::{gradient_decode, gradient_encode, gradient_encode_into, payload_bytes};
pub use header::{BOOTSTRAP_READ, Compression, HEADER_LEN, Header, MAGIC, Section, VERSION_MAJOR, VERSION_MINOR};
pub use key::{MAX_LAYERS, MAX_LODS, TileKey, layer_of, tile_id_to_zxy, zxy_to_tile_id};
pub use manifest::{
    Coverage, MANIFEST_FORMAT, MAX_MANIFEST_BYTES, Manifest, Part, PartLayer, Route, content_tag, is_manifest_location,
};
pub use metadata::{
    ElevationEncoding, ElevationScheme, Georeference, Layer, LayerKind, Metadata, OriginalField, PayloadCompression,
    Shard, SourceRecord, Terrain, TileFormat, levels_to_one,
};
pub use ranges::{AsyncRangeSource, MaybeSend, MaybeSync, MemorySource, RangeSource};
#[cfg(not(target_arch = "wasm32"))]
pub use ranges::{FileSource, MmapSource};
pub use reader::Reader;
pub use stats::{ArchiveStats, LayerStats};
pub use varint::{Cursor, write_varint};
pub use verify::{VerifyReport, verify};
