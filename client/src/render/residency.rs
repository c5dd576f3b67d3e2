//! Which tiles live in which slot of the GPU texture arrays, and the page table the
//! shaders find them with.
//!
//! Every resident tile of a layer occupies one layer ("slot") of that layer's texture
//! array. The shaders find a tile's slot through a hash table kept in a small integer
//! texture: entry `(x, y, lod | kind << 8, slot + 1)`, open addressing with linear probing.
//! A hash table rather than one page-table texel per tile of the grid: its size follows
//! the GPU budget, not the dataset, so a planet-sized grid costs the same as a valley.

use std::collections::HashMap;

use terrastream_format::TileKey;

/// Layer kind in a page-table key: elevation.
pub const KIND_ELEVATION: u32 = 0;
/// Layer kind in a page-table key: texture.
pub const KIND_TEXTURE: u32 = 1;

/// The shaders' hash (`hash_key` in `terrain.wgsl`).
pub fn hash_key(x: u32, y: u32, k: u32) -> u32 {
    let mut h = x.wrapping_mul(0x9E37_79B1) ^ y.wrapping_mul(0x85EB_CA77) ^ k.wrapping_mul(0xC2B2_AE3D);
    h ^= h >> 15;
    h = h.wrapping_mul(0x2C1B_3C6D);
    h ^= h >> 12;
    h
}

#[derive(Clone, Copy, Debug)]
struct Slot {
    index: u32,
    last_used: u64,
    range: Option<(f32, f32)>,
}

/// Slots of one texture array.
#[derive(Debug)]
pub struct Residency {
    capacity: u32,
    slots: HashMap<TileKey, Slot>,
    free: Vec<u32>,
}

/// Where an inserted tile went.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct Placement {
    /// Its slot.
    pub slot: u32,
    /// The tile that slot held before, now dropped.
    pub evicted: Option<TileKey>,
}

impl Residency {
    /// `capacity` slots, all free.
    pub fn new(capacity: u32) -> Self {
        Self { capacity, slots: HashMap::new(), free: (0..capacity).rev().collect() }
    }

    /// Number of slots.
    pub fn capacity(&self) -> u32 {
        self.capacity
    }

    /// Resident tiles.
    pub fn len(&self) -> usize {
        self.slots.len()
    }

    /// No tile resident.
    pub fn is_empty(&self) -> bool {
        self.slots.is_empty()
    }

    /// The slot of a resident tile.
    pub fn slot(&self, key: TileKey) -> Option<u32> {
        self.slots.get(&key).map(|s| s.index)
    }

    /// Resident tiles with their slots and height ranges.
    pub fn iter(&self) -> impl Iterator<Item = (TileKey, u32, Option<(f32, f32)>)> + '_ {
        self.slots.iter().map(|(k, s)| (*k, s.index, s.range))
    }

    /// Marks a resident tile as used in `frame` (eviction drops the least recently used).
    pub fn touch(&mut self, key: TileKey, frame: u64) {
        if let Some(s) = self.slots.get_mut(&key) {
            s.last_used = frame;
        }
    }

    /// Gives `key` a slot: its own if resident, a free one, or the least recently used
    /// tile's — unless that tile was used in `frame` (still in view), then `None`.
    pub fn insert(&mut self, key: TileKey, frame: u64, range: Option<(f32, f32)>) -> Option<Placement> {
        if let Some(s) = self.slots.get_mut(&key) {
            s.last_used = frame;
            s.range = range;
            return Some(Placement { slot: s.index, evicted: None });
        }
        let (index, evicted) = if let Some(index) = self.free.pop() {
            (index, None)
        } else {
            let (&victim, slot) = self.slots.iter().min_by_key(|(k, s)| (s.last_used, k.lod() == 0, **k))?;
            if slot.last_used >= frame {
                return None;
            }
            let index = slot.index;
            self.slots.remove(&victim);
            (index, Some(victim))
        };
        self.slots.insert(key, Slot { index, last_used: frame, range });
        Some(Placement { slot: index, evicted })
    }

    /// Drops one tile.
    pub fn remove(&mut self, key: TileKey) {
        if let Some(s) = self.slots.remove(&key) {
            self.free.push(s.index);
        }
    }

    /// Drops every tile.
    pub fn clear(&mut self) {
        self.slots.clear();
        self.free = (0..self.capacity).rev().collect();
    }
}

/// The page table: a power-of-two hash table stored as `width` x `height` RGBA32Uint texels.
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct PageTable {
    /// Entries `[x, y, lod | kind << 8, slot + 1]`; `slot + 1 == 0` is an empty entry.
    pub entries: Vec<[u32; 4]>,
    /// Texels per row of the texture.
    pub width: u32,
    /// Longest probe sequence any key needs (the shaders stop after it).
    pub max_probes: u32,
}

impl PageTable {
    /// A table for at most `tiles` entries, kept at most half full.
    pub fn new(tiles: u32) -> Self {
        let len = (tiles.max(1) * 2).next_power_of_two().max(64);
        let width = len.min(256);
        Self { entries: vec![[0; 4]; len as usize], width, max_probes: 1 }
    }

    /// Rows of the texture.
    pub fn height(&self) -> u32 {
        u32::try_from(self.entries.len()).unwrap_or(u32::MAX) / self.width
    }

    /// Bitmask the shaders apply to a hash.
    pub fn mask(&self) -> u32 {
        u32::try_from(self.entries.len()).unwrap_or(u32::MAX) - 1
    }

    /// Refills the table from `(kind, key, slot)` triples. Each entry also names the slot of
    /// its tile's parent where that is resident (0 where not): a pixel blending two LODs
    /// finds the coarser tile with the finer one's probe.
    pub fn rebuild(&mut self, tiles: impl IntoIterator<Item = (u32, TileKey, u32)>) {
        let tiles: Vec<(u32, TileKey, u32)> = tiles.into_iter().collect();
        let slots: HashMap<(u32, TileKey), u32> = tiles.iter().map(|&(kind, key, slot)| ((kind, key), slot)).collect();
        self.entries.fill([0; 4]);
        self.max_probes = 1;
        let mask = self.mask();
        for (kind, key, slot) in tiles {
            let k = u32::from(key.lod()) | (kind << 8);
            let parent = key.parent().and_then(|p| slots.get(&(kind, p))).map(|&s| s + 1);
            let parent = parent.filter(|&p| p < PARENT_NONE_ABOVE).unwrap_or(0);
            let mut h = hash_key(key.x(), key.y(), k) & mask;
            let mut probes = 1;
            while self.entries[h as usize][3] != 0 {
                h = (h + 1) & mask;
                probes += 1;
            }
            self.entries[h as usize] = [key.x(), key.y(), k | (parent << 16), slot + 1];
            self.max_probes = self.max_probes.max(probes);
        }
    }

    /// What the shaders' `find_slots` returns: the tile's slot and its parent's.
    pub fn lookup_with_parent(&self, kind: u32, lod: u8, x: u32, y: u32) -> Option<(u32, Option<u32>)> {
        let k = u32::from(lod) | (kind << 8);
        let mask = self.mask();
        let mut h = hash_key(x, y, k) & mask;
        for _ in 0..self.max_probes {
            let e = self.entries[h as usize];
            if e[3] == 0 {
                return None;
            }
            if e[0] == x && e[1] == y && e[2] & 0xFFFF == k {
                return Some((e[3] - 1, (e[2] >> 16).checked_sub(1)));
            }
            h = (h + 1) & mask;
        }
        None
    }

    /// What the shaders' `find_slot` returns.
    pub fn lookup(&self, kind: u32, lod: u8, x: u32, y: u32) -> Option<u32> {
        self.lookup_with_parent(kind, lod, x, y).map(|(slot, _)| slot)
    }
}

/// A parent's slot + 1 is kept in an entry's upper 16 bits: slots from here on are not
/// named (texture arrays hold 2048 layers at most on the adapters seen).
const PARENT_NONE_ABOVE: u32 = 0xFFFF;

#[cfg(test)]
mod tests {
    #![allow(clippy::unwrap_used)]
    use super::*;

    fn key(lod: u8, x: u32, y: u32) -> TileKey {
        TileKey::new(0, lod, x, y).unwrap()
    }

    #[test]
    fn least_recently_used_tile_is_evicted_but_never_one_in_view() {
        let mut r = Residency::new(2);
        assert_eq!(r.insert(key(0, 0, 0), 1, None).unwrap().evicted, None);
        assert_eq!(r.insert(key(0, 1, 0), 2, None).unwrap().evicted, None);
        r.touch(key(0, 0, 0), 3);
        let p = r.insert(key(0, 2, 0), 4, None).unwrap();
        assert_eq!(p.evicted, Some(key(0, 1, 0)));
        assert_eq!(r.slot(key(0, 2, 0)), Some(p.slot));
        // Both residents used this frame: no room.
        r.touch(key(0, 0, 0), 5);
        r.touch(key(0, 2, 0), 5);
        assert_eq!(r.insert(key(0, 3, 0), 5, None), None);
        assert_eq!(r.len(), 2);
    }

    #[test]
    fn page_table_finds_every_tile_and_nothing_else() {
        let mut table = PageTable::new(300);
        let tiles: Vec<_> = (0..300u32)
            .map(|i| ((i % 2, key(u8::try_from(i % 7).unwrap(), i * 31 % 97, i * 17 % 89)), i))
            .collect::<HashMap<_, _>>()
            .into_iter()
            .map(|((kind, k), s)| (kind, k, s))
            .collect();
        table.rebuild(tiles.iter().copied());
        for &(kind, k, slot) in &tiles {
            assert_eq!(table.lookup(kind, k.lod(), k.x(), k.y()), Some(slot));
        }
        assert_eq!(table.lookup(0, 9, 1, 1), None);
        assert_eq!(table.lookup(2, 0, 0, 0), None);
        // Each entry names its parent's slot where the parent is resident, of its own kind.
        let slots: HashMap<(u32, TileKey), u32> = tiles.iter().map(|&(kind, k, s)| ((kind, k), s)).collect();
        let mut parents = 0;
        for &(kind, k, slot) in &tiles {
            let parent = k.parent().and_then(|p| slots.get(&(kind, p)).copied());
            parents += usize::from(parent.is_some());
            assert_eq!(table.lookup_with_parent(kind, k.lod(), k.x(), k.y()), Some((slot, parent)), "{k}");
        }
        assert!(parents > 0, "no tile had its parent resident");
        assert!(table.max_probes < 16, "probe sequences stay short: {}", table.max_probes);
        assert_eq!(table.entries.len(), (table.width * table.height()) as usize);
    }
}
