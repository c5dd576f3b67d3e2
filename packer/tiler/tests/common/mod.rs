//! Helpers the tiler's integration tests share.
#![allow(clippy::unwrap_used, dead_code)]

use std::collections::BTreeMap;
use std::path::Path;
use std::process::Command;

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

/// Is the command-line tool `name` (an independent oracle) installed? Where it is not, the
/// test is skipped, saying so; in CI it fails.
pub fn tool(name: &str, package: &str) -> bool {
    if Command::new(name).arg("--version").output().is_ok() {
        return true;
    }
    assert!(std::env::var_os("CI").is_none(), "{name} is not installed (apt-get install {package})");
    eprintln!("\n*** SKIPPING: {name} is not installed (apt-get install {package}) ***\n");
    false
}
