//! Made tiles (and decoded archive tiles) kept, least recently used first out (nearly),
//! within a byte budget.

use std::collections::{HashMap, VecDeque};
use std::hash::Hash;
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::{Arc, RwLock};

use bytes::Bytes;
use terrastream_tiles::DecodedTile;

/// What a kept value weighs.
pub trait Weigh: Clone {
    /// Bytes it holds.
    fn weight(&self) -> usize;
}

impl Weigh for Bytes {
    fn weight(&self) -> usize {
        self.len()
    }
}

impl Weigh for Arc<DecodedTile> {
    fn weight(&self) -> usize {
        self.byte_len() + 64
    }
}

/// A bounded cache, least recently used out first (approximately: the "second chance"
/// clock of operating systems' page caches). A hit takes a shared lock and sets a flag,
/// so that hits on many threads do not queue behind one another; an insertion takes the
/// exclusive lock and, past the budget, sweeps the oldest entries, sparing (once) those
/// used since the last sweep.
#[derive(Debug)]
pub struct Lru<K, V = Bytes> {
    inner: RwLock<Inner<K, V>>,
    budget: usize,
}

#[derive(Debug)]
struct Inner<K, V> {
    entries: HashMap<K, (V, AtomicBool)>,
    /// Keys, oldest first: the clock.
    order: VecDeque<K>,
    bytes: usize,
}

impl<K: Clone + Eq + Hash, V: Weigh> Lru<K, V> {
    /// An empty cache of at most `budget` bytes (0: nothing is kept).
    pub fn new(budget: usize) -> Self {
        Self { inner: RwLock::new(Inner { entries: HashMap::new(), order: VecDeque::new(), bytes: 0 }), budget }
    }

    /// The value of `key`, marked used.
    pub fn get(&self, key: &K) -> Option<V> {
        let inner = self.inner.read().unwrap_or_else(std::sync::PoisonError::into_inner);
        let (value, used) = inner.entries.get(key)?;
        used.store(true, Ordering::Relaxed);
        Some(value.clone())
    }

    /// Keeps `value` under `key`, sweeping out the least recently used past the budget.
    pub fn put(&self, key: K, value: V) {
        let weight = value.weight();
        if weight > self.budget {
            return;
        }
        let mut inner = self.inner.write().unwrap_or_else(std::sync::PoisonError::into_inner);
        inner.bytes += weight;
        match inner.entries.insert(key.clone(), (value, AtomicBool::new(false))) {
            Some((old, _)) => inner.bytes -= old.weight(),
            None => inner.order.push_back(key),
        }
        // Each entry is looked at most twice: once to clear its flag, once to go.
        let mut spared = inner.order.len();
        while inner.bytes > self.budget {
            let Some(oldest) = inner.order.pop_front() else { break };
            let used = inner.entries.get(&oldest).is_some_and(|(_, used)| used.swap(false, Ordering::Relaxed));
            if used && spared > 0 {
                spared -= 1;
                inner.order.push_back(oldest);
            } else if let Some((gone, _)) = inner.entries.remove(&oldest) {
                inner.bytes -= gone.weight();
            }
        }
    }

    /// Bytes kept.
    pub fn bytes(&self) -> usize {
        self.inner.read().unwrap_or_else(std::sync::PoisonError::into_inner).bytes
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_least_recently_used_go_first_within_the_budget() {
        let lru: Lru<i32> = Lru::new(10);
        lru.put(1, Bytes::from_static(b"aaaa"));
        lru.put(2, Bytes::from_static(b"bbbb"));
        assert!(lru.get(&1).is_some()); // 2 is now the oldest
        lru.put(3, Bytes::from_static(b"cccc"));
        assert!(lru.get(&2).is_none() && lru.get(&1).is_some() && lru.get(&3).is_some());
        assert_eq!(lru.bytes(), 8);
        lru.put(3, Bytes::from_static(b"c"));
        assert_eq!(lru.bytes(), 5);
        lru.put(4, Bytes::from_static(b"this is too long"));
        assert!(lru.get(&4).is_none());
    }
}
