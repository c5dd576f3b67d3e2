//! Blocking reader over any [`RangeSource`] (memory, file, mmap).

use std::sync::Arc;

use bytes::Bytes;

use crate::archive::{Archive, Bootstrap, Locate, TileLocation};
use crate::directory::{Directory, Entry, LeafPointer};
use crate::error::{Error, Result};
use crate::header::Header;
use crate::key::TileKey;
use crate::metadata::Metadata;
use crate::ranges::RangeSource;

/// Reads tiles from an archive: one read to open, at most two more per cold tile.
#[derive(Debug)]
pub struct Reader<S> {
    source: S,
    archive: Archive,
}

impl<S: RangeSource> Reader<S> {
    /// Opens an archive: reads and checks header, metadata and root directory.
    ///
    /// # Errors
    /// Any [`Error`] describing why the bytes are not a valid archive.
    pub fn new(source: S) -> Result<Self> {
        let file_len = source.len();
        let first = source.read_range(0, Archive::first_read_len(file_len))?;
        let archive = match Archive::open(&first, file_len)? {
            Bootstrap::Ready(a) => *a,
            Bootstrap::NeedBytes(n) => match Archive::open(&source.read_range(0, n)?, file_len)? {
                Bootstrap::Ready(a) => *a,
                Bootstrap::NeedBytes(_) => {
                    return Err(Error::corrupt("header", "bootstrap length is unstable"));
                }
            },
        };
        let mut reader = Self { source, archive };
        reader.derive_extents_from_leaves()?;
        Ok(reader)
    }

    /// Older archives with leaf directories: their extents from every leaf (one read of
    /// the leaf section).
    fn derive_extents_from_leaves(&mut self) -> Result<()> {
        if let Some(section) = self.archive.leaves_for_extents() {
            let bytes = self.source.read_range(section.offset, section.len)?;
            self.archive.derive_extents_from_leaves(&bytes)?;
        }
        Ok(())
    }

    /// Sets how many decoded leaf directories are kept (at least 1; by default
    /// [`crate::DEFAULT_LEAF_CACHE`]).
    pub fn set_leaf_cache_capacity(&mut self, capacity: usize) {
        self.archive.set_leaf_cache_capacity(capacity);
    }

    /// The parsed archive core.
    pub fn archive(&self) -> &Archive {
        &self.archive
    }
    /// Mutable access to the core (cache settings).
    pub fn archive_mut(&mut self) -> &mut Archive {
        &mut self.archive
    }
    /// The header.
    pub fn header(&self) -> &Header {
        self.archive.header()
    }
    /// The metadata.
    pub fn metadata(&self) -> &Metadata {
        self.archive.metadata()
    }
    /// The byte source.
    pub fn source(&self) -> &S {
        &self.source
    }

    /// Where a tile is stored, fetching its leaf directory if needed.
    ///
    /// # Errors
    /// I/O errors, a damaged leaf, or a tile outside its layer's grid.
    pub fn locate(&self, tile: TileKey) -> Result<Option<TileLocation>> {
        loop {
            match self.archive.locate(tile)? {
                Locate::Found(location) => return Ok(Some(location)),
                Locate::Missing => return Ok(None),
                Locate::NeedLeaf { offset, len } => {
                    self.archive.add_leaf(offset, &self.source.read_range(offset, len)?)?;
                }
            }
        }
    }

    /// A tile's payload, checked against its CRC32C; `None` if the tile is missing.
    ///
    /// # Errors
    /// I/O errors, [`Error::TileChecksum`] for a damaged tile, [`Error::InvalidTile`].
    pub fn tile(&self, tile: TileKey) -> Result<Option<Bytes>> {
        let Some(location) = self.locate(tile)? else {
            return Ok(None);
        };
        self.read(&location).map(Some)
    }

    /// The checked payload of a located tile (servers answer 304s between the two steps).
    ///
    /// # Errors
    /// I/O errors, [`Error::TileChecksum`] for a damaged tile.
    pub fn read(&self, location: &TileLocation) -> Result<Bytes> {
        let blob = self.source.read_range(location.offset, location.blob_len())?;
        self.archive.payload(location, blob)
    }

    /// The payload of a located tile, *not* checked: for a caller that checked this very
    /// blob (same source, same offset) with [`Reader::read`] before, such as a server
    /// answering the same tile many times from an immutable mapping.
    ///
    /// # Errors
    /// I/O errors; a short read.
    pub fn read_unchecked(&self, location: &TileLocation) -> Result<Bytes> {
        let payload = self.source.read_range(location.offset, u64::from(location.length))?;
        if payload.len() as u64 != u64::from(location.length) {
            return Err(Error::corrupt(
                format!("tile {}", location.key),
                format!("{} bytes read, {} expected", payload.len(), location.length),
            ));
        }
        Ok(payload)
    }

    /// The tile, or the nearest coarser tile that exists (the fallback rule everywhere).
    ///
    /// # Errors
    /// As [`Reader::tile`].
    pub fn tile_or_coarser(&self, tile: TileKey) -> Result<Option<(TileKey, Bytes)>> {
        let num_lods = self.metadata().layers.get(usize::from(tile.layer())).map_or(0, |l| l.num_lods);
        let mut current = Some(tile);
        while let Some(t) = current.filter(|t| t.lod() < num_lods) {
            if let Some(bytes) = self.tile(t)? {
                return Ok(Some((t, bytes)));
            }
            current = t.parent();
        }
        Ok(None)
    }

    /// Calls `f` with every tile entry of the archive in key order, reading each leaf once
    /// (without filling the lookup cache).
    ///
    /// # Errors
    /// The first error of a leaf read or decode, or of `f`.
    pub fn for_each_entry<E: From<Error>>(&self, mut f: impl FnMut(&Entry) -> Result<(), E>) -> Result<(), E> {
        match self.archive.root() {
            Directory::Tiles(entries) => entries.iter().try_for_each(&mut f),
            Directory::Leaves(leaves) => {
                for leaf in leaves {
                    for entry in self.leaf(leaf)?.iter() {
                        f(entry)?;
                    }
                }
                Ok(())
            }
        }
    }

    /// Calls `f` with every addressed tile and its checked payload (stored bytes), runs of
    /// tiles sharing one blob expanded, in archive order; each blob is read once.
    ///
    /// # Errors
    /// As [`Reader::for_each_entry`] and [`Reader::entry_payload`]; `f`'s errors.
    pub fn for_each_tile<E: From<Error>>(&self, mut f: impl FnMut(TileKey, &Bytes) -> Result<(), E>) -> Result<(), E> {
        let step = crate::MAX_LAYERS as u64;
        self.for_each_entry(|entry| -> Result<(), E> {
            let payload = self.entry_payload(entry)?;
            for i in 0..u64::from(entry.run_length) {
                f(self.archive.tile_of(entry.key + i * step)?, &payload)?;
            }
            Ok(())
        })
    }

    /// Reads and decodes one leaf directory.
    ///
    /// # Errors
    /// I/O errors, [`Error::SectionChecksum`] or [`Error::Corrupt`] naming the leaf.
    pub fn leaf(&self, leaf: &LeafPointer) -> Result<Arc<Vec<Entry>>> {
        let offset = self.header().leaf_dirs.offset + leaf.offset;
        let bytes = self.source.read_range(offset, u64::from(leaf.length))?;
        self.archive.decode_leaf(*leaf, &bytes)
    }

    /// Reads and checks the blob of an entry (payload without trailer).
    ///
    /// # Errors
    /// I/O errors, [`Error::TileChecksum`] naming the entry's first tile.
    pub fn entry_payload(&self, entry: &Entry) -> Result<Bytes> {
        let key = self.archive.tile_of(entry.key)?;
        let location = TileLocation { key, offset: self.header().data.offset + entry.offset, length: entry.length };
        let blob = self.source.read_range(location.offset, location.blob_len())?;
        self.archive.payload(&location, blob)
    }
}

#[cfg(not(target_arch = "wasm32"))]
impl Reader<crate::ranges::MmapSource> {
    /// Opens a file by memory mapping it.
    ///
    /// # Errors
    /// [`Error::File`] if it cannot be mapped, or any archive error.
    pub fn open_mmap(path: impl AsRef<std::path::Path>) -> Result<Self> {
        Self::new(crate::ranges::MmapSource::open(path)?)
    }
}
