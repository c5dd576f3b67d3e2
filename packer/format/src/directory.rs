//! Directories: sorted, run-length, delta + varint, columnar, compressed lists of entries
//! (FORMAT.md §4).

use crate::compression::decompress;
use crate::error::{Error, Result};
use crate::header::Compression;
use crate::key::MAX_LAYERS;
use crate::varint::{Cursor, write_varint};

/// Bytes of the CRC32C trailer stored after each tile payload.
pub const TILE_TRAILER_LEN: u64 = 4;
/// A directory never inflates past this many bytes (64 MiB, about 10 million entries).
pub const MAX_DIRECTORY_BYTES: u64 = 64 << 20;

/// One directory entry pointing at tile data.
///
/// It addresses `run_length` tiles of one layer whose keys are `key, key + 16, ...`
/// (consecutive tile ids), all with the same content.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct Entry {
    /// Directory key of the first tile.
    pub key: u64,
    /// Number of consecutive tiles (>= 1) sharing this content.
    pub run_length: u32,
    /// Offset of the blob relative to the data section.
    pub offset: u64,
    /// Payload length, without the 4-byte checksum trailer.
    pub length: u32,
}

impl Entry {
    /// Does this entry address `key`?
    pub fn covers(&self, key: u64) -> bool {
        let step = MAX_LAYERS as u64;
        key >= self.key && (key - self.key).is_multiple_of(step) && (key - self.key) / step < u64::from(self.run_length)
    }

    /// Last key addressed by this entry.
    pub fn last_key(&self) -> u64 {
        self.key + (u64::from(self.run_length) - 1) * MAX_LAYERS as u64
    }

    /// Bytes of the stored blob (payload + trailer).
    pub fn stored_len(&self) -> u64 {
        u64::from(self.length) + TILE_TRAILER_LEN
    }
}

/// One root-directory entry pointing at a leaf directory.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct LeafPointer {
    /// Key of the first entry in the leaf.
    pub first_key: u64,
    /// Offset of the leaf relative to the leaf-directories section.
    pub offset: u64,
    /// Stored (compressed) length of the leaf.
    pub length: u32,
    /// CRC32C of the stored leaf bytes.
    pub crc: u32,
}

/// A decoded directory: either tile entries or (root only) pointers to leaves.
#[derive(Clone, Debug, PartialEq, Eq)]
pub enum Directory {
    /// Entries pointing at tile data, sorted by key.
    Tiles(Vec<Entry>),
    /// Pointers to leaf directories, sorted by first key.
    Leaves(Vec<LeafPointer>),
}

impl Directory {
    /// Number of entries.
    pub fn len(&self) -> usize {
        match self {
            Self::Tiles(e) => e.len(),
            Self::Leaves(l) => l.len(),
        }
    }

    /// True when there are no entries.
    pub fn is_empty(&self) -> bool {
        self.len() == 0
    }

    /// Serializes to the uncompressed columnar form.
    pub fn encode_raw(&self) -> Vec<u8> {
        let mut out = Vec::with_capacity(self.len() * 6 + 8);
        write_varint(&mut out, self.len() as u64);
        // (key, run, length, offset, stored length) of each entry, tiles or leaves alike.
        let rows: Vec<(u64, u64, u64, u64, u64)> = match self {
            Self::Tiles(entries) => entries
                .iter()
                .map(|e| (e.key, u64::from(e.run_length), u64::from(e.length), e.offset, e.stored_len()))
                .collect(),
            Self::Leaves(leaves) => {
                leaves.iter().map(|l| (l.first_key, 0, u64::from(l.length), l.offset, u64::from(l.length))).collect()
            }
        };
        let mut last_key = 0;
        for &(key, ..) in &rows {
            write_varint(&mut out, key - last_key);
            last_key = key;
        }
        for &(_, run, ..) in &rows {
            write_varint(&mut out, run);
        }
        for &(_, _, length, ..) in &rows {
            write_varint(&mut out, length);
        }
        // Code 0 = "right after the furthest blob so far": new blobs are written in
        // entry order, so only entries re-using earlier content need an explicit offset.
        let mut furthest_end = 0u64;
        for &(_, _, _, offset, stored) in &rows {
            if offset == furthest_end {
                write_varint(&mut out, 0);
            } else {
                write_varint(&mut out, offset + 1);
            }
            furthest_end = furthest_end.max(offset + stored);
        }
        if let Self::Leaves(leaves) = self {
            for l in leaves {
                out.extend_from_slice(&l.crc.to_le_bytes());
            }
        }
        out
    }

    /// Parses a stored directory and validates every entry against the section its
    /// offsets point into (`target_len` bytes: the data section for tile entries, the
    /// leaf-directories section for leaf pointers).
    ///
    /// # Errors
    /// [`Error::Decompress`] / [`Error::Corrupt`] / [`Error::OutOfBounds`] naming `section`.
    pub fn decode(
        stored: &[u8],
        compression: Compression,
        section: &str,
        data_len: u64,
        leaf_dirs_len: u64,
    ) -> Result<Self> {
        let raw = decompress(stored, compression, MAX_DIRECTORY_BYTES, section)?;
        Self::decode_raw(&raw, section, data_len, leaf_dirs_len)
    }

    /// As [`Directory::decode`], on uncompressed bytes.
    ///
    /// # Errors
    /// [`Error::Corrupt`] / [`Error::OutOfBounds`] naming `section`.
    pub fn decode_raw(raw: &[u8], section: &str, data_len: u64, leaf_dirs_len: u64) -> Result<Self> {
        let mut c = Cursor::new(raw, section);
        let columns = Columns::read(&mut c, raw.len(), section, data_len, leaf_dirs_len)?;
        let trailing = |c: &Cursor<'_>| match c.remaining() {
            0 => Ok(()),
            n => Err(Error::corrupt(section, format!("{n} trailing bytes"))),
        };
        if columns.is_leaves() {
            let leaves = columns.leaf_pointers(&mut c, section)?;
            trailing(&c)?;
            return Ok(Self::Leaves(leaves));
        }
        trailing(&c)?;
        Ok(Self::Tiles(columns.tile_entries(section)?))
    }

    /// The entry addressing `key`, if this is a tile directory holding it.
    pub fn find_tile(entries: &[Entry], key: u64) -> Option<Entry> {
        let i = entries.partition_point(|e| e.key <= key).checked_sub(1)?;
        let e = entries[i];
        e.covers(key).then_some(e)
    }

    /// The leaf that may hold `key`.
    pub fn find_leaf(leaves: &[LeafPointer], key: u64) -> Option<LeafPointer> {
        let i = leaves.partition_point(|l| l.first_key <= key).checked_sub(1)?;
        Some(leaves[i])
    }
}

/// A directory's columns as stored (keys delta-coded, run lengths, lengths, offsets with
/// "follows the previous" coded as 0), each checked on its own as it is read.
struct Columns {
    keys: Vec<u64>,
    runs: Vec<u64>,
    lengths: Vec<u32>,
    offsets: Vec<u64>,
}

impl Columns {
    fn read(c: &mut Cursor<'_>, total: usize, section: &str, data_len: u64, leaf_dirs_len: u64) -> Result<Self> {
        let corrupt = |reason: String| Error::corrupt(section, reason);
        let n = c.varint()?;
        // Each entry takes at least 4 bytes (one per column): bound n before allocating.
        if n > (c.remaining() / 4) as u64 {
            return Err(corrupt(format!("{n} entries cannot fit in {total} bytes")));
        }
        let n = usize::try_from(n).map_err(|_| corrupt("entry count overflows".into()))?;
        let mut keys = Vec::with_capacity(n);
        let mut key = 0u64;
        for i in 0..n {
            let delta = c.varint()?;
            if i > 0 && delta == 0 {
                return Err(corrupt(format!("entry {i}: keys not strictly increasing")));
            }
            key = key.checked_add(delta).ok_or_else(|| corrupt(format!("entry {i}: key overflows")))?;
            keys.push(key);
        }
        let mut runs = Vec::with_capacity(n);
        for _ in 0..n {
            runs.push(c.varint()?);
        }
        let mut lengths = Vec::with_capacity(n);
        for i in 0..n {
            let length = c.varint()?;
            let length = u32::try_from(length)
                .ok()
                .filter(|&l| l > 0)
                .ok_or_else(|| corrupt(format!("entry {i}: length {length} out of range")))?;
            lengths.push(length);
        }
        let is_leaves = runs.first() == Some(&0);
        let (stored_extra, limit, limit_name) = if is_leaves {
            (0, leaf_dirs_len, "leaf-directories section")
        } else {
            (TILE_TRAILER_LEN, data_len, "data section")
        };
        let mut offsets = Vec::with_capacity(n);
        let mut furthest_end = 0u64;
        for (i, &length) in lengths.iter().enumerate() {
            let code = c.varint()?;
            let offset = if code == 0 { furthest_end } else { code - 1 };
            let stored = u64::from(length) + stored_extra;
            let end = offset.checked_add(stored).filter(|&e| e <= limit).ok_or_else(|| Error::OutOfBounds {
                what: format!("{section} entry {i}"),
                offset,
                len: stored,
                limit_name,
                limit,
            })?;
            offsets.push(offset);
            furthest_end = furthest_end.max(end);
        }
        Ok(Self { keys, runs, lengths, offsets })
    }

    /// A directory of leaf pointers has a run length of 0 first (tile runs are at least 1).
    fn is_leaves(&self) -> bool {
        self.runs.first() == Some(&0)
    }

    /// The leaf pointers, each followed in the stream by its leaf's CRC32C.
    fn leaf_pointers(&self, c: &mut Cursor<'_>, section: &str) -> Result<Vec<LeafPointer>> {
        let mut leaves = Vec::with_capacity(self.keys.len());
        for i in 0..self.keys.len() {
            if self.runs[i] != 0 {
                return Err(Error::corrupt(section, format!("entry {i}: tile entry in a directory of leaf pointers")));
            }
            leaves.push(LeafPointer {
                first_key: self.keys[i],
                offset: self.offsets[i],
                length: self.lengths[i],
                crc: c.u32_le()?,
            });
        }
        Ok(leaves)
    }

    /// The tile entries: runs within the key space, not overlapping.
    fn tile_entries(&self, section: &str) -> Result<Vec<Entry>> {
        let corrupt = |reason: String| Error::corrupt(section, reason);
        let mut entries = Vec::with_capacity(self.keys.len());
        let mut previous_last: Option<u64> = None;
        for i in 0..self.keys.len() {
            let run_length = u32::try_from(self.runs[i])
                .ok()
                .filter(|&r| r > 0)
                .ok_or_else(|| corrupt(format!("entry {i}: run length {} out of range", self.runs[i])))?;
            let entry = Entry { key: self.keys[i], run_length, offset: self.offsets[i], length: self.lengths[i] };
            let span = (u64::from(run_length) - 1).checked_mul(MAX_LAYERS as u64);
            if span.and_then(|s| entry.key.checked_add(s)).is_none() {
                return Err(corrupt(format!("entry {i}: run overflows the key space")));
            }
            if previous_last.is_some_and(|last| entry.key <= last) {
                return Err(corrupt(format!("entry {i}: overlaps the run of the previous entry")));
            }
            previous_last = Some(entry.last_key());
            entries.push(entry);
        }
        Ok(entries)
    }
}

#[cfg(test)]
mod tests {
    use proptest::prelude::*;

    use super::*;

    fn entries_strategy() -> impl Strategy<Value = Vec<Entry>> {
        prop::collection::vec((1u64..1000, 1u32..5, 1u32..100_000, any::<bool>()), 0..300).prop_map(|rows| {
            let mut key = 0;
            let mut offset = 0u64;
            let mut out: Vec<Entry> = Vec::new();
            for (gap, run, length, reuse) in rows {
                key += gap * 16 + if let Some(last) = out.last() { last.last_key() - last.key } else { 0 };
                // Dedup: point back at the first blob now and then.
                let (off, len) = match (reuse, out.first()) {
                    (true, Some(first)) => (first.offset, first.length),
                    _ => {
                        let o = offset;
                        offset += u64::from(length) + 4;
                        (o, length)
                    }
                };
                out.push(Entry { key, run_length: run, offset: off, length: len });
            }
            out
        })
    }

    proptest! {
        #[test]
        fn tiles_round_trip(entries in entries_strategy()) {
            let dir = Directory::Tiles(entries);
            let raw = dir.encode_raw();
            prop_assert_eq!(Directory::decode_raw(&raw, "t", u64::MAX / 2, 0).unwrap(), dir);
        }

        #[test]
        fn decoding_garbage_never_panics(bytes in prop::collection::vec(any::<u8>(), 0..200)) {
            let _ = Directory::decode_raw(&bytes, "t", 1 << 40, 1 << 40);
        }
    }

    #[test]
    fn leaves_round_trip_with_offsets_past_4_gib() {
        let dir = Directory::Leaves(vec![
            LeafPointer { first_key: 3, offset: 5 << 32, length: 10, crc: 0xdead_beef },
            LeafPointer { first_key: 900, offset: (5 << 32) + 10, length: 7, crc: 1 },
        ]);
        let raw = dir.encode_raw();
        assert_eq!(Directory::decode_raw(&raw, "root", 0, 6 << 32).unwrap(), dir);
        // The same bytes are out of bounds for a smaller section.
        assert!(matches!(Directory::decode_raw(&raw, "root", 0, 5 << 32), Err(Error::OutOfBounds { .. })));
    }

    #[test]
    fn finds_tiles_inside_runs_only_in_their_layer() {
        let entries = [
            Entry { key: 16, run_length: 3, offset: 0, length: 5 },
            Entry { key: 81, run_length: 1, offset: 9, length: 5 },
        ];
        assert_eq!(Directory::find_tile(&entries, 48).map(|e| e.offset), Some(0));
        assert_eq!(Directory::find_tile(&entries, 64), None);
        assert_eq!(Directory::find_tile(&entries, 17), None);
        assert_eq!(Directory::find_tile(&entries, 81).map(|e| e.offset), Some(9));
        assert_eq!(Directory::find_tile(&entries, 0), None);
    }

    #[test]
    fn contiguous_offsets_cost_one_byte() {
        let entries: Vec<Entry> =
            (0..1000u64).map(|i| Entry { key: i * 16, run_length: 1, offset: i * 104, length: 100 }).collect();
        let raw = Directory::Tiles(entries).encode_raw();
        // key delta + run + length + offset code: 1 byte each, plus the count.
        assert_eq!(raw.len(), 4 * 1000 + 2);
    }

    #[test]
    fn only_reused_content_pays_for_its_offset() {
        let mut entries: Vec<Entry> =
            (0..100u64).map(|i| Entry { key: i * 32, run_length: 1, offset: i * 104, length: 100 }).collect();
        let plain = Directory::Tiles(entries.clone()).encode_raw().len();
        // Interleave entries that re-use blob 0: each costs its own offset, the next new one not.
        for i in 0..10u64 {
            entries.push(Entry { key: i * 320 + 16, run_length: 1, offset: 0, length: 100 });
        }
        entries.sort_by_key(|e| e.key);
        let with_dups = Directory::Tiles(entries).encode_raw().len();
        assert_eq!(with_dups - plain, 10 * 4, "4 bytes per extra entry, no offset for the entry after it");
    }
}
