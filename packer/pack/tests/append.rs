//! In-place updates (FORMAT.md §7.1): random archives take random changes through the
//! `Appender` and read back as the changed tile set, through a fresh reader and in
//! `verify`; a reader opened before an update keeps reading its version; an update that
//! does not fit, or that is dropped, leaves the archive's bytes as they were.
#![allow(clippy::unwrap_used, clippy::expect_used, clippy::cast_possible_truncation, missing_docs)]

mod common;

use std::collections::BTreeMap;
use std::path::Path;

use common::{layer, metadata};
use proptest::prelude::*;
use terrastream_format::{Metadata, MmapSource, Reader, TileKey, verify};
use terrastream_pack::{Appender, Error, Writer, WriterOptions};

type Tiles = BTreeMap<(u8, u8, u32, u32), Vec<u8>>;

fn meta(grids: &[(u32, u32)]) -> Metadata {
    metadata(
        grids
            .iter()
            .enumerate()
            .map(|(i, &(nx, ny))| layer(&format!("layer{i}"), nx, ny, terrastream_format::levels_to_one(nx.max(ny))))
            .collect(),
    )
}

fn sorted<'a>(
    meta: &Metadata,
    tiles: impl IntoIterator<Item = (&'a (u8, u8, u32, u32), &'a Vec<u8>)>,
) -> Vec<(u64, TileKey, &'a Vec<u8>)> {
    let mut out: Vec<_> = tiles
        .into_iter()
        .map(|(&(l, lod, x, y), p)| {
            let t = TileKey::new(l, lod, x, y).unwrap();
            (Writer::order_key(meta, t).unwrap(), t, p)
        })
        .collect();
    out.sort_by_key(|s| s.0);
    out
}

fn write(path: &Path, meta: &Metadata, tiles: &Tiles, options: WriterOptions) {
    let mut w = Writer::create(path, meta.clone(), options).unwrap();
    for (_, t, p) in sorted(meta, tiles) {
        w.add(t, p.clone()).unwrap();
    }
    w.finish().unwrap();
}

/// The archive's tiles as they are stored: archive key -> (tile, offset, length).
fn entries(path: &Path) -> BTreeMap<u64, (TileKey, u64, u32)> {
    let reader = Reader::open_mmap(path).unwrap();
    let mut out = BTreeMap::new();
    reader
        .for_each_entry(|e| -> terrastream_format::Result<()> {
            for k in 0..u64::from(e.run_length) {
                let key = e.key + k * terrastream_format::MAX_LAYERS as u64;
                out.insert(key, (reader.archive().tile_of(key)?, e.offset, e.length));
            }
            Ok(())
        })
        .unwrap();
    out
}

/// Applies `changes` (None: the tile goes) in place: unchanged tiles are kept where they are.
fn update(
    path: &Path,
    meta: &Metadata,
    changes: &BTreeMap<(u8, u8, u32, u32), Option<Vec<u8>>>,
    options: WriterOptions,
) -> Result<(), Error> {
    let old = entries(path);
    // Each tile of the new version: kept where it is (offset, length), or new bytes.
    type Version<'a> = BTreeMap<u64, (TileKey, Result<(u64, u32), &'a Vec<u8>>)>;
    let mut new: Version<'_> = old.iter().map(|(&k, &(t, o, l))| (k, (t, Ok((o, l))))).collect();
    for (&(l, lod, x, y), change) in changes {
        let t = TileKey::new(l, lod, x, y).unwrap();
        let key = Writer::order_key(meta, t).unwrap();
        match change {
            Some(bytes) => new.insert(key, (t, Err(bytes))),
            None => new.remove(&key),
        };
    }
    let mut appender = Appender::open(path, options)?;
    for (key, (tile, at)) in new {
        match at {
            Ok((offset, length)) => appender.keep(tile, key, offset, length)?,
            Err(bytes) => appender.add(tile, key, bytes)?,
        }
    }
    appender.finish(meta).map(|_| ())
}

fn check(path: &Path, tiles: &Tiles) {
    let reader = Reader::open_mmap(path).unwrap();
    check_reader(&reader, tiles);
    let report = verify(&reader, |_| {}).unwrap();
    assert!(report.is_ok(), "{:?}", report.problems);
    assert_eq!(report.addressed_tiles, tiles.len() as u64);
}

fn check_reader(reader: &Reader<MmapSource>, tiles: &Tiles) {
    let got: Tiles = {
        let mut got = BTreeMap::new();
        reader
            .for_each_tile(|t, b| -> terrastream_format::Result<()> {
                got.insert((t.layer(), t.lod(), t.x(), t.y()), b.to_vec());
                Ok(())
            })
            .unwrap();
        got
    };
    assert_eq!(got.len(), tiles.len());
    for (k, v) in tiles {
        assert_eq!(got.get(k), Some(v), "{k:?}");
        let t = TileKey::new(k.0, k.1, k.2, k.3).unwrap();
        assert_eq!(reader.tile(t).unwrap().as_deref(), Some(&v[..]), "{k:?} by lookup");
    }
}

fn payload(seed: u64, tag: &str) -> Vec<u8> {
    let mut p = b"\x89PNG\r\n\x1a\n".to_vec();
    p.extend((0..seed % 200 + 50).map(|i| (seed.wrapping_mul(31).wrapping_add(i) % 251) as u8));
    p.extend(tag.bytes());
    p
}

/// A random pyramid and two rounds of random changes to it.
fn case() -> impl Strategy<Value = (Vec<(u32, u32)>, u64, u8, u8)> {
    (prop::collection::vec((1u32..24, 1u32..24), 1..3), any::<u64>(), 10u8..100, 1u8..40)
}

fn random_tiles(grids: &[(u32, u32)], seed: u64, fill: u8) -> Tiles {
    let mut rng = seed | 1;
    let mut tiles = BTreeMap::new();
    for (li, &(nx, ny)) in grids.iter().enumerate() {
        for lod in 0..terrastream_format::levels_to_one(nx.max(ny)) {
            for y in 0..ny.div_ceil(1 << lod) {
                for x in 0..nx.div_ceil(1 << lod) {
                    rng ^= rng << 13;
                    rng ^= rng >> 7;
                    rng ^= rng << 17;
                    if (rng % 100) as u8 >= fill {
                        continue;
                    }
                    // A third are the same "ocean" tile (runs, dedup).
                    let p = if rng.is_multiple_of(3) {
                        b"ocean".to_vec()
                    } else {
                        payload(rng, &format!("{li}/{lod}/{x}/{y}"))
                    };
                    tiles.insert((li as u8, lod, x, y), p);
                }
            }
        }
    }
    tiles
}

/// Changes `percent` of the grid's places: new bytes, removals, tiles where there were none.
fn random_changes(grids: &[(u32, u32)], seed: u64, percent: u8) -> BTreeMap<(u8, u8, u32, u32), Option<Vec<u8>>> {
    let mut rng = seed.rotate_left(17) | 1;
    let mut changes = BTreeMap::new();
    for (li, &(nx, ny)) in grids.iter().enumerate() {
        for lod in 0..terrastream_format::levels_to_one(nx.max(ny)) {
            for y in 0..ny.div_ceil(1 << lod) {
                for x in 0..nx.div_ceil(1 << lod) {
                    rng ^= rng << 13;
                    rng ^= rng >> 7;
                    rng ^= rng << 17;
                    if (rng % 100) as u8 >= percent {
                        continue;
                    }
                    let change = match rng % 5 {
                        0 => None,
                        1 => Some(b"ocean".to_vec()),
                        _ => Some(payload(rng >> 3, &format!("new {li}/{lod}/{x}/{y}"))),
                    };
                    changes.insert((li as u8, lod, x, y), change);
                }
            }
        }
    }
    changes
}

fn apply(tiles: &mut Tiles, changes: &BTreeMap<(u8, u8, u32, u32), Option<Vec<u8>>>) {
    for (k, c) in changes {
        match c {
            Some(b) => tiles.insert(*k, b.clone()),
            None => tiles.remove(k),
        };
    }
}

proptest! {
    #![proptest_config(ProptestConfig { cases: 32, ..ProptestConfig::default() })]

    #[test]
    fn updates_in_place_read_back_and_keep_open_readers_whole((grids, seed, fill, percent) in case(), small_leaves in any::<bool>()) {
        let options = if small_leaves {
            // Leaf directories on small inputs, in every version.
            WriterOptions { leaf_entries: 3, bootstrap_target: 600, ..WriterOptions::default() }
        } else {
            WriterOptions::default()
        };
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("t.tspack");
        let meta = meta(&grids);
        let mut tiles = random_tiles(&grids, seed, fill);
        prop_assume!(!tiles.is_empty());
        write(&path, &meta, &tiles, options.clone());
        // An archive that fits one bootstrap read whole is written without room.
        prop_assume!(std::fs::metadata(&path).unwrap().len() > 16 * 1024);
        let before = Reader::open_mmap(&path).unwrap();
        let v0 = tiles.clone();

        let first = random_changes(&grids, seed, percent);
        update(&path, &meta, &first, options.clone()).unwrap();
        apply(&mut tiles, &first);
        check(&path, &tiles);
        // Opened before: still the old version, every tile.
        check_reader(&before, &v0);

        let between = Reader::open_mmap(&path).unwrap();
        let v1 = tiles.clone();
        let second = random_changes(&grids, seed ^ 0x9e37_79b9, percent);
        update(&path, &meta, &second, options).unwrap();
        apply(&mut tiles, &second);
        check(&path, &tiles);
        check_reader(&between, &v1);
    }
}

#[test]
fn an_archive_without_room_is_refused_untouched() {
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("packed.tspack");
    let grids = [(8, 8)];
    let meta = meta(&grids);
    let tiles = random_tiles(&grids, 7, 80);
    write(&path, &meta, &tiles, WriterOptions { reserve: false, ..WriterOptions::default() });
    let bytes = std::fs::read(&path).unwrap();
    let err = update(&path, &meta, &random_changes(&grids, 7, 30), WriterOptions::default()).unwrap_err();
    assert!(matches!(err, Error::NoRoom { .. }), "{err}");
    assert!(err.to_string().contains("packed.tspack") && err.to_string().contains("without room"), "{err}");
    assert_eq!(std::fs::read(&path).unwrap(), bytes);
}

#[test]
fn directories_that_outgrow_their_room_are_refused_untouched() {
    // A few tiles: every entry in the root, about 4 KiB of leaf area. Then 60 000 new
    // tiles of random lengths: their leaves need far more.
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("small.tspack");
    let grids = [(256, 256)];
    let meta = meta(&grids);
    // (6 KB each: larger than one bootstrap read, so written with room.)
    let tiles: Tiles = (0..4).map(|x| ((0, 0, x, 0), payload(u64::from(x), "a").repeat(100))).collect();
    write(&path, &meta, &tiles, WriterOptions::default());
    let bytes = std::fs::read(&path).unwrap();
    let changes = (0..60_000u32)
        .map(|i| {
            ((0, 0, i % 256, i / 256 + 4), Some(payload(u64::from(i).wrapping_mul(0x9e37_79b9_7f4a_7c15) >> 40, "b")))
        })
        .collect();
    let err = update(&path, &meta, &changes, WriterOptions::default()).unwrap_err();
    assert!(matches!(err, Error::NoRoom { .. }), "{err}");
    assert!(err.to_string().contains("leaf directories"), "{err}");
    unchanged(&path, &bytes);
    check(&path, &tiles);
}

#[test]
fn an_update_dropped_before_finishing_leaves_the_archive_as_it_was() {
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("t.tspack");
    let grids = [(16, 16)];
    let meta = meta(&grids);
    let tiles = random_tiles(&grids, 3, 70);
    write(&path, &meta, &tiles, WriterOptions::default());
    let bytes = std::fs::read(&path).unwrap();
    {
        let mut appender = Appender::open(&path, WriterOptions::default()).unwrap();
        // A second update of the same archive waits for none: it is refused.
        let busy = Appender::open(&path, WriterOptions::default()).unwrap_err();
        assert!(busy.to_string().contains("another update"), "{busy}");
        for (key, t, p) in sorted(&meta, &tiles) {
            appender.add(t, key, &[&p[..], b"changed"].concat()).unwrap();
        }
    }
    unchanged(&path, &bytes);
    check(&path, &tiles);
    // The next update writes over what the dropped one left.
    let changes = random_changes(&grids, 5, 30);
    update(&path, &meta, &changes, WriterOptions::default()).unwrap();
    let mut tiles = tiles;
    apply(&mut tiles, &changes);
    check(&path, &tiles);
}

/// The archive's bytes as they were, any bytes an unfinished update appended after them
/// aside (never cut off: a reader may have mapped them).
fn unchanged(path: &Path, before: &[u8]) {
    let now = std::fs::read(path).unwrap();
    assert!(now.len() >= before.len());
    assert!(now[..before.len()] == *before, "the archive's bytes changed");
}
