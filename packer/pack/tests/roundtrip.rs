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

/// A `zstd_gradient` layer: the writer codes u16 samples, the archive says major 2, every
/// reader's [`terrastream_format::payload_bytes`] gives them back bit for bit, and terrain
/// takes far fewer bytes than under plain zstd. A payload that is not a tile's samples is
/// refused naming the tile, and nothing is written.
#[test]
fn gradient_coded_elevation_comes_back_exactly_in_fewer_bytes() {
    use terrastream_format::{Header, TileFormat};
    let edge = 18usize;
    let mut elevation = layer("elevation", 2, 2, 2);
    (elevation.format, elevation.tile_resolution, elevation.border) = (TileFormat::RawU16, 16, 1);
    // A smooth hill with a little noise, and a wrapping checkerboard of the extremes.
    let mut noise = 7u32;
    let tile = |t: u32, noise: &mut u32| -> Vec<u8> {
        (0..edge * edge)
            .flat_map(|i| {
                *noise = noise.wrapping_mul(1_664_525).wrapping_add(1_013_904_223);
                let (x, y) = ((i % edge) as f64, (i / edge) as f64);
                let v = if t == 3 {
                    if (i % edge + i / edge).is_multiple_of(2) { 0 } else { u16::MAX }
                } else {
                    (30_000.0 + 900.0 * ((x + 3.0 * f64::from(t)) / 5.0).sin() * (y / 7.0).cos()) as u16
                        + (*noise >> 30) as u16
                };
                v.to_le_bytes()
            })
            .collect()
    };
    let tiles: Vec<(TileKey, Vec<u8>)> =
        (0..4).map(|t| (TileKey::new(0, 0, t % 2, t / 2).unwrap(), tile(t, &mut noise))).collect();
    let sizes = [PayloadCompression::Zstd, PayloadCompression::ZstdGradient].map(|compression| {
        let mut l = elevation.clone();
        l.compression = compression;
        let meta = metadata(vec![l]);
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("e.tspack");
        let mut w = Writer::create(&path, meta.clone(), WriterOptions::default()).unwrap();
        let mut ordered: Vec<_> = tiles.iter().collect();
        ordered.sort_by_key(|(key, _)| Writer::order_key(&meta, *key).unwrap());
        for (key, samples) in ordered {
            w.add(*key, samples.clone()).unwrap();
        }
        w.finish().unwrap();
        let bytes = std::fs::read(&path).unwrap();
        let header = Header::decode(&bytes, bytes.len() as u64).unwrap();
        let major = if compression == PayloadCompression::ZstdGradient { 2 } else { 1 };
        assert_eq!(header.version_major, major, "{compression:?}");
        let reader = Reader::open_mmap(&path).unwrap();
        assert!(verify(&reader, |_| {}).unwrap().is_ok());
        let mut stored = 0;
        for (key, samples) in &tiles {
            let got = reader.tile(*key).unwrap().unwrap();
            stored += got.len();
            let back = terrastream_format::payload_bytes(&meta.layers[0], &got, "t").unwrap();
            assert_eq!(&back[..], &samples[..], "{key} {compression:?}");
        }
        stored
    });
    assert!(sizes[1] * 3 < sizes[0] * 2, "gradient {} bytes against zstd's {}", sizes[1], sizes[0]);

    // Not a tile's samples: refused, naming the tile; no archive left behind.
    let mut l = elevation.clone();
    l.compression = PayloadCompression::ZstdGradient;
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("bad.tspack");
    let mut w = Writer::create(&path, metadata(vec![l]), WriterOptions::default()).unwrap();
    let key = TileKey::new(0, 0, 1, 0).unwrap();
    let e = w.add(key, vec![1; 17]).and_then(|()| w.finish().map(|_| ())).unwrap_err().to_string();
    assert!(e.contains(&key.to_string()) && e.contains("17 bytes"), "{e}");
    assert!(!path.exists());
    assert_eq!(std::fs::read_dir(dir.path()).unwrap().count(), 0, "a partial file was left");

    // A gradient layer must be raw u16.
    let mut l = layer("elevation", 2, 2, 2);
    l.compression = PayloadCompression::ZstdGradient;
    let e = metadata(vec![l]).validate().unwrap_err().to_string();
    assert!(e.contains("zstd_gradient") && e.contains("Png"), "{e}");
}
