//! Made tiles (and decoded archive tiles) kept, least recently used first out, within a
//! byte budget.

use std::collections::{BTreeMap, HashMap};
use std::hash::Hash;
use std::sync::{Arc, Mutex};

use bytes::Bytes;
use terrastream_client::DecodedTile;

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

/// A bounded LRU.
#[derive(Debug)]
pub struct Lru<K, V = Bytes> {
    inner: Mutex<Inner<K, V>>,
    budget: usize,
}

#[derive(Debug)]
struct Inner<K, V> {
    entries: HashMap<K, (V, u64)>,
    /// Use order: tick -> key.
    order: BTreeMap<u64, K>,
    tick: u64,
    bytes: usize,
}

impl<K: Clone + Eq + Hash, V: Weigh> Lru<K, V> {
    /// An empty cache of at most `budget` bytes (0: nothing is kept).
    pub fn new(budget: usize) -> Self {
        Self { inner: Mutex::new(Inner { entries: HashMap::new(), order: BTreeMap::new(), tick: 0, bytes: 0 }), budget }
    }

    fn lock(&self) -> std::sync::MutexGuard<'_, Inner<K, V>> {
        self.inner.lock().unwrap_or_else(std::sync::PoisonError::into_inner)
    }

    /// The value of `key`, now the most recently used.
    pub fn get(&self, key: &K) -> Option<V> {
        let mut inner = self.lock();
        inner.tick += 1;
        let tick = inner.tick;
        let (value, old) = {
            let (value, used) = inner.entries.get_mut(key)?;
            let old = std::mem::replace(used, tick);
            (value.clone(), old)
        };
        inner.order.remove(&old);
        inner.order.insert(tick, key.clone());
        Some(value)
    }

    /// Keeps `value` under `key`, dropping the least recently used past the budget.
    pub fn put(&self, key: K, value: V) {
        let weight = value.weight();
        if weight > self.budget {
            return;
        }
        let mut inner = self.lock();
        inner.tick += 1;
        let tick = inner.tick;
        inner.bytes += weight;
        if let Some((old, used)) = inner.entries.insert(key.clone(), (value, tick)) {
            inner.bytes -= old.weight();
            inner.order.remove(&used);
        }
        inner.order.insert(tick, key);
        while inner.bytes > self.budget {
            let Some((_, oldest)) = inner.order.pop_first() else { break };
            if let Some((gone, _)) = inner.entries.remove(&oldest) {
                inner.bytes -= gone.weight();
            }
        }
    }

    /// Bytes kept.
    pub fn bytes(&self) -> usize {
        self.lock().bytes
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
