//! Decoded tiles in a byte-budgeted LRU. Tiles the current frame needs are pinned: the
//! cache may run over its budget rather than evict them (coverage beats the budget, and
//! the overrun is visible in the counters).

use std::collections::{BTreeMap, HashMap, HashSet};
use std::sync::Arc;

use terrastream_format::TileKey;

use terrastream_tiles::DecodedTile;

struct Slot {
    tile: Arc<DecodedTile>,
    stamp: u64,
}

/// The cache.
pub struct TileCache {
    budget: usize,
    bytes: usize,
    clock: u64,
    slots: HashMap<TileKey, Slot>,
    order: BTreeMap<u64, TileKey>,
}

impl std::fmt::Debug for TileCache {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("TileCache").field("budget", &self.budget).field("bytes", &self.bytes).finish_non_exhaustive()
    }
}

impl TileCache {
    /// An empty cache of `budget` bytes.
    pub fn new(budget: usize) -> Self {
        Self { budget, bytes: 0, clock: 0, slots: HashMap::new(), order: BTreeMap::new() }
    }

    /// Changes the budget (takes effect at the next [`Self::trim`]).
    pub fn set_budget(&mut self, budget: usize) {
        self.budget = budget;
    }

    /// Bytes held.
    pub fn bytes(&self) -> usize {
        self.bytes
    }

    /// Tiles held.
    pub fn len(&self) -> usize {
        self.slots.len()
    }

    /// True when empty.
    pub fn is_empty(&self) -> bool {
        self.slots.is_empty()
    }

    /// The tile, if held (does not count as a use).
    pub fn peek(&self, key: TileKey) -> Option<&Arc<DecodedTile>> {
        self.slots.get(&key).map(|s| &s.tile)
    }

    /// Is the tile held?
    pub fn contains(&self, key: TileKey) -> bool {
        self.slots.contains_key(&key)
    }

    /// Marks the tile as just used; true if held.
    pub fn touch(&mut self, key: TileKey) -> bool {
        self.clock += 1;
        let clock = self.clock;
        let Some(slot) = self.slots.get_mut(&key) else { return false };
        self.order.remove(&slot.stamp);
        slot.stamp = clock;
        self.order.insert(clock, key);
        true
    }

    /// Adds (or replaces) a tile as the most recently used.
    pub fn insert(&mut self, tile: Arc<DecodedTile>) {
        let key = tile.key;
        self.remove(key);
        self.clock += 1;
        self.bytes += tile.byte_len();
        self.order.insert(self.clock, key);
        self.slots.insert(key, Slot { tile, stamp: self.clock });
    }

    /// Drops a tile.
    pub fn remove(&mut self, key: TileKey) -> Option<Arc<DecodedTile>> {
        let slot = self.slots.remove(&key)?;
        self.order.remove(&slot.stamp);
        self.bytes -= slot.tile.byte_len();
        Some(slot.tile)
    }

    /// Evicts least recently used tiles not in `pinned` until within budget; returns the
    /// evicted keys.
    pub fn trim(&mut self, pinned: &HashSet<TileKey>) -> Vec<TileKey> {
        let mut evicted = Vec::new();
        if self.bytes <= self.budget {
            return evicted;
        }
        let victims: Vec<TileKey> = self.order.values().copied().filter(|k| !pinned.contains(k)).collect();
        for key in victims {
            if self.bytes <= self.budget {
                break;
            }
            self.remove(key);
            evicted.push(key);
        }
        evicted
    }

    /// Drops everything.
    pub fn clear(&mut self) {
        self.slots.clear();
        self.order.clear();
        self.bytes = 0;
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use terrastream_tiles::TileData;

    fn tile(x: u32, bytes: usize) -> Arc<DecodedTile> {
        Arc::new(DecodedTile {
            key: TileKey::new(0, 0, x, 0).unwrap(),
            size: 1,
            border: 0,
            data: TileData::Rgba8(vec![0; bytes]),
        })
    }

    #[test]
    fn evicts_least_recent_first_and_never_pinned() {
        let mut c = TileCache::new(300);
        for x in 0..4 {
            c.insert(tile(x, 100));
        }
        assert!(c.touch(TileKey::new(0, 0, 0, 0).unwrap()));
        let pinned: HashSet<_> = [TileKey::new(0, 0, 1, 0).unwrap()].into();
        let evicted = c.trim(&pinned);
        assert_eq!(evicted, vec![TileKey::new(0, 0, 2, 0).unwrap()]);
        assert_eq!(c.bytes(), 300);
        // Everything pinned: over budget rather than a hole.
        let all: HashSet<_> = (0..4).map(|x| TileKey::new(0, 0, x, 0).unwrap()).collect();
        c.insert(tile(3, 100));
        c.insert(tile(2, 100));
        assert!(c.trim(&all).is_empty());
        assert_eq!(c.bytes(), 400);
    }
}
