//! The I/O-free core of every reader: parses the bootstrap bytes, caches leaf directories,
//! and says which bytes to fetch next. The blocking [`crate::Reader`], the async
//! [`crate::AsyncReader`] and the client's HTTP reader are thin loops around it.

use std::collections::HashMap;
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::{Arc, PoisonError, RwLock};

use bytes::Bytes;

use crate::checksum::crc32c;
use crate::compression::decompress;
use crate::directory::{Directory, Entry, LeafPointer, TILE_TRAILER_LEN};
use crate::error::{Error, Result};
use crate::extent::ExtentBuilder;
use crate::header::{BOOTSTRAP_READ, Header, Section};
use crate::key::TileKey;
use crate::metadata::Metadata;

/// Metadata never inflates past this (16 MiB).
pub const MAX_METADATA_BYTES: u64 = 16 << 20;
/// Runs of identical tiles longer than this count their first and last tile only when a
/// layer's extent is derived from the directory.
pub const MAX_DERIVED_RUN: u32 = 4096;
/// Largest leaf section read on open to derive the extents of an archive that does not
/// record them (4 MiB, about 600 000 tiles).
pub const MAX_LEAVES_READ_FOR_EXTENTS: u64 = 4 << 20;
/// Leaf directories kept decoded by default.
pub const DEFAULT_LEAF_CACHE: usize = 64;

/// Where a tile's blob lies in the file.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct TileLocation {
    /// The tile asked for.
    pub key: TileKey,
    /// Absolute offset of the blob (payload + 4-byte CRC32C trailer).
    pub offset: u64,
    /// Payload length.
    pub length: u32,
}

impl TileLocation {
    /// Bytes to fetch: payload and trailer.
    pub fn blob_len(&self) -> u64 {
        u64::from(self.length) + TILE_TRAILER_LEN
    }
}

/// Answer of [`Archive::locate`].
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Locate {
    /// The tile is stored here.
    Found(TileLocation),
    /// No such tile (missing tiles are normal: fall back to a coarser LOD).
    Missing,
    /// Fetch this leaf directory (absolute range) and hand it to [`Archive::add_leaf`].
    NeedLeaf {
        /// Absolute offset of the leaf.
        offset: u64,
        /// Stored length of the leaf.
        len: u64,
    },
}

/// Result of [`Archive::open`] on the first bytes of a file.
#[derive(Debug)]
pub enum Bootstrap {
    /// Everything needed was in the bytes given.
    Ready(Box<Archive>),
    /// Read `[0, len)` and call [`Archive::open`] again (metadata + root exceed the first read).
    NeedBytes(u64),
}

/// A parsed archive: header, metadata, root directory and a small cache of leaves.
#[derive(Debug)]
pub struct Archive {
    header: Header,
    metadata: Metadata,
    root: Directory,
    depths: Vec<u8>,
    file_len: u64,
    leaves: RwLock<LeafCache>,
    leaf_cache_capacity: usize,
    /// Offsets of the root's leaf pointers, sorted, with each one's index (FORMAT.md orders
    /// leaves by key, not by offset): a fetched leaf is found by its offset in a bisection,
    /// not a scan of every pointer (thousands in a planet's archive).
    leaf_offsets: Vec<(u64, usize)>,
}

/// Decoded leaves, by their offset in the leaf section, evicted by CLOCK (second chance):
/// a hit takes a shared lock and sets the leaf's bit, so readers on many threads never
/// wait for each other; a miss sweeps the hand past leaves used since its last turn.
#[derive(Debug, Default)]
struct LeafCache {
    slots: Vec<(u64, Arc<Vec<Entry>>, AtomicBool)>,
    by_offset: HashMap<u64, usize>,
    hand: usize,
}

impl LeafCache {
    /// Runs `f` on the leaf at `offset`, if cached.
    fn with<R>(&self, offset: u64, f: impl FnOnce(&[Entry]) -> R) -> Option<R> {
        let (_, entries, used) = &self.slots[*self.by_offset.get(&offset)?];
        used.store(true, Ordering::Relaxed);
        Some(f(entries))
    }

    /// Keeps `entries` as the leaf at `offset`, within `capacity` leaves.
    fn insert(&mut self, offset: u64, entries: Arc<Vec<Entry>>, capacity: usize) {
        if self.by_offset.contains_key(&offset) {
            return;
        }
        if self.slots.len() < capacity {
            self.by_offset.insert(offset, self.slots.len());
            self.slots.push((offset, entries, AtomicBool::new(false)));
            return;
        }
        // At most one full turn clears every bit; the next slot is then the victim.
        while self.slots[self.hand].2.swap(false, Ordering::Relaxed) {
            self.hand = (self.hand + 1) % self.slots.len();
        }
        let victim = self.hand;
        self.by_offset.remove(&self.slots[victim].0);
        self.by_offset.insert(offset, victim);
        self.slots[victim] = (offset, entries, AtomicBool::new(false));
        self.hand = (victim + 1) % self.slots.len();
    }
}

impl Archive {
    /// How many bytes to read at offset 0 before calling [`Archive::open`].
    pub fn first_read_len(file_len: u64) -> u64 {
        BOOTSTRAP_READ.min(file_len)
    }

    /// Parses the bytes read at offset 0 (at least [`Archive::first_read_len`] of them).
    ///
    /// # Errors
    /// Any [`Error`] describing the damaged header, metadata or root directory.
    pub fn open(first_bytes: &[u8], file_len: u64) -> Result<Bootstrap> {
        let header = Header::decode(first_bytes, file_len)?;
        let needed = header.bootstrap_len();
        if (first_bytes.len() as u64) < needed {
            return Ok(Bootstrap::NeedBytes(needed));
        }
        // Both sections end at or before bootstrap_len <= first_bytes.len() (checked above).
        let slice = |s: Section, name: &str| -> Result<&[u8]> {
            let range = usize::try_from(s.offset).ok().zip(s.end().and_then(|e| usize::try_from(e).ok()));
            range
                .and_then(|(start, end)| first_bytes.get(start..end))
                .ok_or_else(|| Error::corrupt("header", format!("{name} outside the bootstrap bytes")))
        };
        let meta_bytes = slice(header.metadata, "metadata")?;
        check_crc(meta_bytes, header.metadata_crc, "metadata")?;
        let json = decompress(meta_bytes, header.metadata_compression, MAX_METADATA_BYTES, "metadata")?;
        let metadata = Metadata::from_json(&json)?;
        let root_bytes = slice(header.root_dir, "root directory")?;
        check_crc(root_bytes, header.root_dir_crc, "root directory")?;
        let root = Directory::decode(
            root_bytes,
            header.directory_compression,
            "root directory",
            header.data.len,
            header.leaf_dirs.len,
        )?;
        let depths = metadata.depths();
        let mut leaf_offsets = match &root {
            Directory::Leaves(leaves) => leaves.iter().enumerate().map(|(i, l)| (l.offset, i)).collect(),
            Directory::Tiles(_) => Vec::new(),
        };
        leaf_offsets.sort_unstable();
        let mut archive = Self {
            header,
            metadata,
            root,
            depths,
            file_len,
            leaves: RwLock::new(LeafCache::default()),
            leaf_cache_capacity: DEFAULT_LEAF_CACHE,
            leaf_offsets,
        };
        if let Directory::Tiles(entries) = &archive.root
            && archive.lacks_extents()
        {
            let entries = entries.clone();
            archive.derive_extents(&entries);
        }
        Ok(Bootstrap::Ready(Box::new(archive)))
    }

    /// True when the metadata does not say where the layers' data is (archives written
    /// before FORMAT.md §3.7): a reader with leaf directories calls
    /// [`Archive::derive_extents`] with every entry (the root's are used on open).
    pub fn lacks_extents(&self) -> bool {
        // Writers record the extent of every layer that has a tile: an archive where no
        // layer has one was written before, one where some layer has none has an empty layer.
        self.metadata.layers.iter().all(|l| l.extent.is_none())
    }

    /// The leaf section to read so that [`Archive::derive_extents_from_leaves`] can derive
    /// the layers' extents: `Some` for an archive that records none, has leaf directories,
    /// and whose leaf section is at most [`MAX_LEAVES_READ_FOR_EXTENTS`] (beyond it, its
    /// layers are taken as their whole grids: opening a planet reads no gigabytes).
    pub fn leaves_for_extents(&self) -> Option<Section> {
        let section = self.header.leaf_dirs;
        (matches!(self.root, Directory::Leaves(_))
            && self.lacks_extents()
            && section.len <= MAX_LEAVES_READ_FOR_EXTENTS)
            .then_some(section)
    }

    /// Derives the layers' extents from the leaf section [`Archive::leaves_for_extents`]
    /// named, read whole.
    ///
    /// # Errors
    /// [`Error::Corrupt`] or [`Error::SectionChecksum`] naming a damaged leaf.
    pub fn derive_extents_from_leaves(&mut self, section: &[u8]) -> Result<()> {
        let Directory::Leaves(leaves) = &self.root else { return Ok(()) };
        let entries = entries_of_leaves(self, leaves, section)?;
        self.derive_extents(&entries);
        Ok(())
    }

    /// Fills the extent of every layer that has none from directory entries (all of the
    /// archive's): coarsest populated LOD and the box of the finest tiles. Runs longer than
    /// 4096 tiles (`MAX_DERIVED_RUN`) count their first and last tile only.
    pub fn derive_extents(&mut self, entries: &[Entry]) {
        let step = crate::key::MAX_LAYERS as u64;
        let mut builders = vec![ExtentBuilder::default(); self.metadata.layers.len()];
        let mut add = |key: u64| {
            if let Ok(tile) = self.tile_of(key)
                && let Some(b) = builders.get_mut(usize::from(tile.layer()))
            {
                b.add(tile);
            }
        };
        for e in entries {
            if e.run_length <= MAX_DERIVED_RUN {
                (0..u64::from(e.run_length)).for_each(|i| add(e.key + i * step));
            } else {
                add(e.key);
                add(e.last_key());
            }
        }
        let georeference = self.metadata.georeference.clone();
        for (layer, builder) in self.metadata.layers.iter_mut().zip(&builders) {
            if layer.extent.is_none() {
                layer.extent = builder.finish(layer).map(|mut e| {
                    e.georeference(georeference.as_ref());
                    e
                });
            }
        }
    }

    /// The header.
    pub fn header(&self) -> &Header {
        &self.header
    }
    /// The metadata.
    pub fn metadata(&self) -> &Metadata {
        &self.metadata
    }
    /// The root directory.
    pub fn root(&self) -> &Directory {
        &self.root
    }
    /// Length of the file.
    pub fn file_len(&self) -> u64 {
        self.file_len
    }

    /// Sets how many decoded leaves are kept (at least 1).
    pub fn set_leaf_cache_capacity(&mut self, capacity: usize) {
        self.leaf_cache_capacity = capacity.max(1);
    }

    /// Directory key of a tile, checked against its layer's grid.
    ///
    /// # Errors
    /// [`Error::InvalidTile`] for an unknown layer or a tile outside the layer's grid.
    pub fn key_of(&self, key: TileKey) -> Result<u64> {
        self.metadata.directory_key(key)
    }

    /// Decodes a directory key back to a tile.
    ///
    /// # Errors
    /// [`Error::InvalidTile`] if the key does not belong to any layer.
    pub fn tile_of(&self, key: u64) -> Result<TileKey> {
        TileKey::from_archive_key(key, &self.depths)
    }

    /// Finds a tile, or says which leaf to fetch first.
    ///
    /// # Errors
    /// [`Error::InvalidTile`] for a tile outside its layer's grid.
    pub fn locate(&self, tile: TileKey) -> Result<Locate> {
        let key = self.key_of(tile)?;
        match &self.root {
            Directory::Tiles(entries) => Ok(self.found(tile, Directory::find_tile(entries, key))),
            Directory::Leaves(leaves) => {
                let Some(leaf) = Directory::find_leaf(leaves, key) else {
                    return Ok(Locate::Missing);
                };
                let cache = self.leaves.read().unwrap_or_else(PoisonError::into_inner);
                match cache.with(leaf.offset, |entries| Directory::find_tile(entries, key)) {
                    Some(entry) => Ok(self.found(tile, entry)),
                    None => Ok(Locate::NeedLeaf {
                        offset: self.header.leaf_dirs.offset + leaf.offset,
                        len: u64::from(leaf.length),
                    }),
                }
            }
        }
    }

    fn found(&self, tile: TileKey, entry: Option<Entry>) -> Locate {
        match entry {
            Some(e) => {
                Locate::Found(TileLocation { key: tile, offset: self.header.data.offset + e.offset, length: e.length })
            }
            None => Locate::Missing,
        }
    }

    /// The leaf pointer whose stored bytes start at absolute `offset`.
    fn leaf_at(&self, offset: u64) -> Option<LeafPointer> {
        let Directory::Leaves(leaves) = &self.root else {
            return None;
        };
        let relative = offset.checked_sub(self.header.leaf_dirs.offset)?;
        let at = self.leaf_offsets.partition_point(|&(o, _)| o < relative);
        let &(found, index) = self.leaf_offsets.get(at)?;
        (found == relative).then(|| leaves[index])
    }

    /// Checks, decodes and caches a leaf fetched after [`Locate::NeedLeaf`].
    ///
    /// # Errors
    /// [`Error::SectionChecksum`] / [`Error::Corrupt`] naming the leaf.
    pub fn add_leaf(&self, offset: u64, bytes: &[u8]) -> Result<Arc<Vec<Entry>>> {
        let section = format!("leaf directory at offset {offset}");
        let leaf = self.leaf_at(offset).ok_or_else(|| Error::corrupt(&section, "no root entry points here"))?;
        let entries = self.decode_leaf(leaf, bytes)?;
        let mut cache = self.leaves.write().unwrap_or_else(PoisonError::into_inner);
        cache.insert(leaf.offset, Arc::clone(&entries), self.leaf_cache_capacity);
        Ok(entries)
    }

    /// Checks and decodes a leaf without caching it (bulk walks: verify, extract).
    ///
    /// # Errors
    /// [`Error::SectionChecksum`] / [`Error::Corrupt`] naming the leaf.
    pub fn decode_leaf(&self, leaf: LeafPointer, bytes: &[u8]) -> Result<Arc<Vec<Entry>>> {
        let section = format!("leaf directory at offset {}", self.header.leaf_dirs.offset + leaf.offset);
        if bytes.len() as u64 != u64::from(leaf.length) {
            return Err(Error::corrupt(&section, format!("{} bytes given, {} expected", bytes.len(), leaf.length)));
        }
        check_crc(bytes, leaf.crc, &section)?;
        match Directory::decode(bytes, self.header.directory_compression, &section, self.header.data.len, 0)? {
            Directory::Tiles(entries) => {
                let (first, last) = (entries.first(), entries.last());
                if first.is_none_or(|e| e.key != leaf.first_key) {
                    return Err(Error::corrupt(&section, "first key differs from its root entry"));
                }
                if let (Some(next), Some(last)) = (self.next_leaf_key(leaf), last)
                    && last.last_key() >= next
                {
                    return Err(Error::corrupt(&section, "entries run into the next leaf"));
                }
                Ok(Arc::new(entries))
            }
            Directory::Leaves(_) => Err(Error::corrupt(&section, "a leaf may not point at further leaves")),
        }
    }

    fn next_leaf_key(&self, leaf: LeafPointer) -> Option<u64> {
        let Directory::Leaves(leaves) = &self.root else {
            return None;
        };
        let i = leaves.partition_point(|l| l.first_key <= leaf.first_key);
        leaves.get(i).map(|l| l.first_key)
    }

    /// Checks a fetched blob against its trailer and returns the payload (zero-copy).
    ///
    /// # Errors
    /// [`Error::TileChecksum`] naming the tile if the bytes are damaged.
    pub fn payload(&self, location: &TileLocation, blob: Bytes) -> Result<Bytes> {
        let length = usize::try_from(location.length).unwrap_or(usize::MAX);
        if blob.len() as u64 != location.blob_len() {
            return Err(Error::corrupt(
                format!("tile {}", location.key),
                format!("{} bytes read, {} expected", blob.len(), location.blob_len()),
            ));
        }
        let stored = u32::from_le_bytes([blob[length], blob[length + 1], blob[length + 2], blob[length + 3]]);
        let payload = blob.slice(..length);
        let computed = crc32c(&payload);
        if stored != computed {
            return Err(Error::TileChecksum {
                key: location.key,
                offset: location.offset - self.header.data.offset,
                stored,
                computed,
            });
        }
        Ok(payload)
    }
}

fn check_crc(bytes: &[u8], stored: u32, section: &str) -> Result<()> {
    let computed = crc32c(bytes);
    if computed != stored {
        return Err(Error::SectionChecksum { section: section.to_owned(), stored, computed });
    }
    Ok(())
}

/// Every entry of the given leaves, decoded from the whole leaf section's `bytes`.
///
/// # Errors
/// [`Error::Corrupt`] or [`Error::SectionChecksum`] naming a leaf outside the section or
/// damaged.
fn entries_of_leaves(archive: &Archive, leaves: &[LeafPointer], bytes: &[u8]) -> Result<Vec<Entry>> {
    let mut entries = Vec::new();
    for leaf in leaves {
        let range = usize::try_from(leaf.offset)
            .ok()
            .and_then(|start| Some(start..start.checked_add(usize::try_from(leaf.length).ok()?)?));
        let slice = range.and_then(|r| bytes.get(r)).ok_or_else(|| {
            Error::corrupt(format!("leaf directory at offset {}", leaf.offset), "outside the leaf section")
        })?;
        entries.extend(archive.decode_leaf(*leaf, slice)?.iter().copied());
    }
    Ok(entries)
}

#[cfg(test)]
mod tests {
    use super::*;

    fn leaf(first_key: u64) -> Arc<Vec<Entry>> {
        Arc::new(vec![Entry { key: first_key, offset: 0, length: 1, run_length: 1 }])
    }

    fn cached(cache: &LeafCache) -> Vec<u64> {
        let mut offsets: Vec<u64> = cache.slots.iter().map(|s| s.0).collect();
        offsets.sort_unstable();
        offsets
    }

    /// CLOCK keeps the leaves used since the hand last passed and evicts the others, in
    /// the hand's order; it never holds more than its capacity, nor a leaf twice.
    #[test]
    fn the_leaf_cache_evicts_leaves_not_used_since_the_hand_passed() {
        let mut cache = LeafCache::default();
        for offset in [10, 20, 30] {
            cache.insert(offset, leaf(offset), 3);
        }
        cache.insert(20, leaf(20), 3);
        assert_eq!(cached(&cache), [10, 20, 30]);
        assert_eq!(cache.with(20, |e| e[0].key), Some(20));
        assert_eq!(cache.with(40, |e| e[0].key), None);
        // 20 was used: 10, the first unused one from the hand, goes.
        cache.insert(40, leaf(40), 3);
        assert_eq!(cached(&cache), [20, 30, 40]);
        // The hand moved past 10's slot: 20's bit is cleared on this turn, 30 goes.
        cache.insert(50, leaf(50), 3);
        assert_eq!(cached(&cache), [20, 40, 50]);
        // Every leaf used: a full turn clears them all and the hand's next one goes.
        for offset in [20, 40, 50] {
            cache.with(offset, |_| ());
        }
        cache.insert(60, leaf(60), 3);
        assert_eq!(cache.slots.len(), 3);
        assert_eq!(cache.by_offset.len(), 3);
        assert!(cache.with(60, |_| ()).is_some());
        for (i, (offset, ..)) in cache.slots.iter().enumerate() {
            assert_eq!(cache.by_offset[offset], i);
        }
    }
}
