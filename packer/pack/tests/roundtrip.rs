//! Write -> read round trips on random pyramids, through every backend.
#![allow(clippy::unwrap_used, clippy::expect_used, clippy::cast_possible_truncation, missing_docs)]

mod common;

use std::collections::BTreeMap;

use common::{block_on, layer, metadata};
use proptest::prelude::*;
use terrastream_format::{
    ArchiveStats, AsyncReader, FileSource, MemorySource, MmapSource, PayloadCompression, RangeSource, Reader, TileKey,
    verify,
};
use terrastream_pack::{Writer, WriterOptions};

/// A random sparse pyramid: per layer a grid, per tile present / duplicate / unique payload.
#[derive(Debug, Clone)]
struct Case {
    grids: Vec<(u32, u32)>,
    tiles: BTreeMap<(u8, u8, u32, u32), Vec<u8>>,
    zstd_layer: bool,
}

fn case() -> impl Strategy<Value = Case> {
    (prop::collection::vec((1u32..20, 1u32..20), 1..4), any::<u64>(), 0u8..100, 0u8..100, any::<bool>()).prop_map(
        |(grids, seed, fill, dup, zstd_layer)| {
            let mut rng = seed | 1;
            let mut next = move || {
                rng ^= rng << 13;
                rng ^= rng >> 7;
                rng ^= rng << 17;
                rng
            };
            let mut tiles = BTreeMap::new();
            for (li, &(nx, ny)) in grids.iter().enumerate() {
                let lods = terrastream_format::levels_to_one(nx.max(ny));
                for lod in 0..lods {
                    let (gx, gy) = (nx.div_ceil(1 << lod), ny.div_ceil(1 << lod));
                    for y in 0..gy {
                        for x in 0..gx {
                            if (next() % 100) as u8 >= fill {
                                continue; // missing tile
                            }
                            let payload = if (next() % 100) as u8 <= dup {
                                b"\x89PNG\r\n\x1a\nsame ocean tile".to_vec()
                            } else {
                                let mut p = b"\x89PNG\r\n\x1a\n".to_vec();
                                p.extend((0..next() % 300).map(|_| next() as u8));
                                p.extend(format!("{li}/{lod}/{x}/{y}").bytes());
                                p
                            };
                            tiles.insert((li as u8, lod, x, y), payload);
                        }
                    }
                }
            }
            Case { grids, tiles, zstd_layer }
        },
    )
}

fn write(case: &Case, options: WriterOptions) -> (tempfile::TempDir, std::path::PathBuf) {
    let mut layers: Vec<_> = case
        .grids
        .iter()
        .enumerate()
        .map(|(i, &(nx, ny))| layer(&format!("layer{i}"), nx, ny, terrastream_format::levels_to_one(nx.max(ny))))
        .collect();
    if case.zstd_layer {
        layers[0].compression = PayloadCompression::Zstd;
    }
    let meta = metadata(layers);
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("t.tspack");
    let mut sorted: Vec<(u64, TileKey, &Vec<u8>)> = case
        .tiles
        .iter()
        .map(|(&(l, lod, x, y), p)| {
            let t = TileKey::new(l, lod, x, y).unwrap();
            (Writer::order_key(&meta, t).unwrap(), t, p)
        })
        .collect();
    sorted.sort_by_key(|s| s.0);
    let mut w = Writer::create(&path, meta, options).unwrap();
    for (_, t, p) in sorted {
        w.add(t, p.clone()).unwrap();
    }
    let summary = w.finish().unwrap();
    assert_eq!(summary.addressed_tiles, case.tiles.len() as u64);
    (dir, path)
}

fn check_all_tiles<S: RangeSource>(case: &Case, reader: &Reader<S>) {
    for (li, &(nx, ny)) in case.grids.iter().enumerate() {
        let depth = terrastream_format::levels_to_one(nx.max(ny));
        for lod in 0..depth {
            let (gx, gy) = (nx.div_ceil(1 << lod), ny.div_ceil(1 << lod));
            for y in 0..gy {
                for x in 0..gx {
                    let key = TileKey::new(li as u8, lod, x, y).unwrap();
                    let got = reader.tile(key).unwrap();
                    let got = match (got, case.zstd_layer && li == 0) {
                        (Some(b), true) => Some(terrastream_format::zstd_decompress(&b, 1 << 20, "t").unwrap()),
                        (b, _) => b.map(|b| b.to_vec()),
                    };
                    assert_eq!(got.as_ref(), case.tiles.get(&(li as u8, lod, x, y)), "{key}");
                }
            }
            // Outside the grid is an error, not a missing tile.
            assert!(reader.tile(TileKey::new(li as u8, lod, gx, 0).unwrap()).is_err());
        }
    }
}

proptest! {
    #![proptest_config(ProptestConfig { cases: 48, ..ProptestConfig::default() })]

    #[test]
    fn every_tile_comes_back_through_every_backend(case in case(), small_leaves in any::<bool>()) {
        let options = if small_leaves {
            // Force leaf directories and the leaf-size doubling loop on small inputs.
            WriterOptions { leaf_entries: 3, bootstrap_target: 600, batch_tiles: 7, ..WriterOptions::default() }
        } else {
            WriterOptions::default()
        };
        let (_dir, path) = write(&case, options);
        let bytes = std::fs::read(&path).unwrap();
        check_all_tiles(&case, &Reader::new(MemorySource::new(bytes.clone())).unwrap());
        check_all_tiles(&case, &Reader::new(FileSource::open(&path).unwrap()).unwrap());
        let mmap = Reader::new(MmapSource::open(&path).unwrap()).unwrap();
        check_all_tiles(&case, &mmap);
        // One leaf kept: every other lookup evicts it.
        let mut one_leaf = Reader::new(MmapSource::open(&path).unwrap()).unwrap();
        one_leaf.set_leaf_cache_capacity(1);
        check_all_tiles(&case, &one_leaf);

        let report = verify(&mmap, |_| {}).unwrap();
        prop_assert!(report.is_ok(), "{:?}", report.problems);
        prop_assert_eq!(report.addressed_tiles, case.tiles.len() as u64);
        let distinct: std::collections::HashSet<_> = case.tiles.values().collect();
        if !case.zstd_layer {
            prop_assert_eq!(report.blobs_checked, distinct.len() as u64, "identical tiles are stored once");
        }
        let stats = ArchiveStats::collect(&mmap).unwrap();
        for (li, l) in stats.layers.iter().enumerate() {
            for (lod, &n) in l.tiles_per_lod.iter().enumerate() {
                let expected = case.tiles.keys().filter(|k| usize::from(k.0) == li && usize::from(k.1) == lod).count();
                prop_assert_eq!(n, expected as u64);
            }
        }
        // The async reader over the same bytes agrees.
        let r = block_on(AsyncReader::new(MemorySource::new(bytes))).unwrap();
        for (&(l, lod, x, y), payload) in &case.tiles {
            let got = block_on(r.tile(TileKey::new(l, lod, x, y).unwrap())).unwrap().unwrap();
            if !(case.zstd_layer && l == 0) {
                prop_assert_eq!(&got[..], &payload[..]);
            }
        }
    }
}

#[test]
fn header_metadata_and_root_fit_the_first_16_kib() {
    // 100x100 LOD 0 plus its pyramid: 13 000+ tiles, far more than one root can hold.
    let mut tiles = BTreeMap::new();
    for lod in 0..7u8 {
        let n = 100u32.div_ceil(1 << lod);
        for y in 0..n {
            for x in 0..n {
                // Lengths vary like real tiles, so the directory does not compress to nothing.
                let len = (x.wrapping_mul(7919) ^ y.wrapping_mul(104_729) ^ u32::from(lod)) % 3000 + 10;
                let mut payload = format!("\u{89}PNG{lod}/{x}/{y}").into_bytes();
                payload.resize(len as usize + payload.len(), b'.');
                tiles.insert((0u8, lod, x, y), payload);
            }
        }
    }
    let case = Case { grids: vec![(100, 100)], tiles, zstd_layer: false };
    let (_dir, path) = write(&case, WriterOptions::default());
    let reader = Reader::new(MmapSource::open(&path).unwrap()).unwrap();
    assert!(reader.header().bootstrap_len() <= 16 * 1024, "bootstrap {}", reader.header().bootstrap_len());
    assert!(matches!(reader.archive().root(), terrastream_format::Directory::Leaves(_)));
    check_all_tiles(&case, &reader);
}

#[test]
fn tiles_out_of_order_are_refused() {
    let meta = metadata(vec![layer("texture", 4, 4, 3)]);
    let dir = tempfile::tempdir().unwrap();
    let mut w = Writer::create(dir.path().join("x.tspack"), meta, WriterOptions::default()).unwrap();
    w.add(TileKey::new(0, 0, 0, 0).unwrap(), b"a".to_vec()).unwrap();
    let err = w.add(TileKey::new(0, 2, 0, 0).unwrap(), b"b".to_vec()).unwrap_err();
    assert!(err.to_string().contains("out of archive order"), "{err}");
    assert!(w.add(TileKey::new(0, 0, 9, 0).unwrap(), b"c".to_vec()).is_err(), "outside the grid");
}

#[test]
fn runs_of_identical_neighbours_take_one_entry() {
    let meta = metadata(vec![layer("texture", 64, 64, 1)]);
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("ocean.tspack");
    let mut keys: Vec<(u64, TileKey)> = (0..64u32)
        .flat_map(|y| (0..64u32).map(move |x| TileKey::new(0, 0, x, y).unwrap()))
        .map(|t| (Writer::order_key(&meta, t).unwrap(), t))
        .collect();
    keys.sort();
    let mut w = Writer::create(&path, meta, WriterOptions::default()).unwrap();
    for (_, t) in &keys {
        w.add(*t, b"ocean".to_vec()).unwrap();
    }
    let s = w.finish().unwrap();
    assert_eq!((s.addressed_tiles, s.tile_entries, s.tile_contents), (4096, 1, 1));
    let r = Reader::new(MmapSource::open(&path).unwrap()).unwrap();
    assert_eq!(&r.tile(TileKey::new(0, 0, 63, 17).unwrap()).unwrap().unwrap()[..], b"ocean");
}
