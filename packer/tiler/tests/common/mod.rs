//! Helpers the tiler's integration tests share.
#![allow(clippy::unwrap_used, dead_code)]

use std::collections::BTreeMap;
use std::path::Path;

use terrastream_format::{Reader, TileKey};

/// Every tile's stored payload, by key.
pub fn tiles(path: &Path) -> BTreeMap<TileKey, Vec<u8>> {
    let mut out = BTreeMap::new();
    Reader::open_mmap(path)
        .unwrap()
        .for_each_tile(|key, payload| -> terrastream_format::Result<()> {
            out.insert(key, payload.to_vec());
            Ok(())
        })
        .unwrap();
    out
}
