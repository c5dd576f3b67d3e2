//! `terrastream verify`: every structure and every checksum of an archive.

use std::collections::HashSet;

use serde::Serialize;

use crate::directory::{Directory, Entry};
use crate::error::{Error, Result};
use crate::key::MAX_LAYERS;
use crate::ranges::RangeSource;
use crate::reader::Reader;

/// Stop listing problems after this many (the archive is broken either way).
const MAX_PROBLEMS: usize = 100;

/// What [`verify`] found.
#[derive(Clone, Debug, Default, Serialize)]
pub struct VerifyReport {
    /// Directory entries checked.
    pub entries: u64,
    /// Tiles addressed by them.
    pub addressed_tiles: u64,
    /// Distinct blobs whose checksum was checked.
    pub blobs_checked: u64,
    /// Payload bytes checked.
    pub bytes_checked: u64,
    /// Leaf directories checked.
    pub leaves_checked: u64,
    /// Bytes of the data section no entry points at: blobs that updates in place replaced
    /// (FORMAT.md §7.1). A merge of the archive writes a copy without them.
    pub unreferenced_bytes: u64,
    /// One line per problem, naming the section or tile; empty when the archive is sound.
    pub problems: Vec<String>,
}

impl VerifyReport {
    /// True when no problem was found.
    pub fn is_ok(&self) -> bool {
        self.problems.is_empty()
    }

    fn problem(&mut self, p: impl Into<String>) {
        if self.problems.len() < MAX_PROBLEMS {
            self.problems.push(p.into());
        }
    }
}

/// Checks an opened archive: header, metadata and root were checked by opening it; this
/// checks every leaf directory, every entry against its layer's grid, the header's counts,
/// and the CRC32C of every distinct tile blob. `progress` is called with bytes checked.
///
/// # Errors
/// Only for failures to read at all; damage is reported in [`VerifyReport::problems`].
pub fn verify<S: RangeSource>(reader: &Reader<S>, mut progress: impl FnMut(u64)) -> Result<VerifyReport> {
    let mut report = VerifyReport::default();
    let archive = reader.archive();
    let mut seen_blobs = HashSet::new();
    let mut stored = 0u64;
    let mut check_entries = |entries: &[Entry], report: &mut VerifyReport| {
        for e in entries {
            report.entries += 1;
            report.addressed_tiles += u64::from(e.run_length);
            if let Err(err) = check_entry(reader, e) {
                report.problem(err.to_string());
                continue;
            }
            if seen_blobs.insert(e.offset) {
                match reader.entry_payload(e) {
                    Ok(_) => {
                        report.blobs_checked += 1;
                        report.bytes_checked += u64::from(e.length);
                        stored += u64::from(e.length) + crate::directory::TILE_TRAILER_LEN;
                        progress(report.bytes_checked);
                    }
                    Err(err) => report.problem(err.to_string()),
                }
            }
        }
    };
    match archive.root() {
        Directory::Tiles(entries) => check_entries(entries, &mut report),
        Directory::Leaves(leaves) => {
            for leaf in leaves {
                match reader.leaf(leaf) {
                    Ok(entries) => {
                        report.leaves_checked += 1;
                        check_entries(&entries, &mut report);
                    }
                    Err(err) => report.problem(err.to_string()),
                }
            }
        }
    }
    let h = reader.header();
    report.unreferenced_bytes = h.data.len.saturating_sub(stored);
    if report.problems.is_empty() {
        let counts = [
            ("addressed tiles", h.addressed_tiles, report.addressed_tiles),
            ("tile entries", h.tile_entries, report.entries),
            ("tile contents", h.tile_contents, report.blobs_checked),
        ];
        for (what, header, found) in counts {
            if header != found {
                report.problem(format!("corrupt header: says {header} {what}, directories hold {found}"));
            }
        }
    }
    Ok(report)
}

/// Every tile of the entry's run must lie in its layer's grid.
fn check_entry<S: RangeSource>(reader: &Reader<S>, e: &Entry) -> Result<()> {
    let archive = reader.archive();
    for i in 0..u64::from(e.run_length) {
        let key = e.key + i * MAX_LAYERS as u64;
        let tile = archive.tile_of(key)?;
        let layer = &archive.metadata().layers[usize::from(tile.layer())];
        if !layer.contains(tile) {
            return Err(Error::InvalidTile {
                what: format!("{tile}: directory entry outside layer {:?}'s grid", layer.name),
            });
        }
    }
    Ok(())
}
