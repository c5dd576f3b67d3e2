//! `export --to pmtiles` output opened by an independent PMTiles v3 reader.
#![allow(clippy::unwrap_used, clippy::expect_used, clippy::cast_possible_truncation, missing_docs)]

mod common;

use pmtiles::{AsyncPmTilesReader, TileCoord, TileType};
use terrastream_format::{MemorySource, RangeSource, Reader, TileKey};
use terrastream_pack::export::pmtiles::export_pmtiles;
use terrastream_pack::progress::Silent;
use terrastream_pack::{Writer, WriterOptions};

/// Every tile of `layer` (and every missing one) reads the same through the PMTiles reader.
async fn check_same<S: RangeSource>(ours: &Reader<S>, layer: u8, path: &std::path::Path) -> u64 {
    let pm = AsyncPmTilesReader::new_with_path(path).await.unwrap();
    let l = &ours.metadata().layers[usize::from(layer)];
    let depth = l.depth();
    let mut present = 0;
    for lod in 0..l.num_lods {
        let (nx, ny) = l.grid_at(lod);
        for y in 0..ny {
            for x in 0..nx {
                let ours = ours.tile(TileKey::new(layer, lod, x, y).unwrap()).unwrap();
                let theirs = pm.get_tile(TileCoord::new(depth - 1 - lod, x, y).unwrap()).await.unwrap();
                assert_eq!(ours, theirs, "lod {lod} ({x}, {y})");
                present += u64::from(ours.is_some());
            }
        }
    }
    present
}

#[tokio::test]
async fn the_sample_texture_layer_opens_in_a_pmtiles_reader() {
    let bytes = terrastream_testkit::archives::tiny_archive();
    let reader = Reader::new(MemorySource::new(bytes)).unwrap();
    let dir = tempfile::tempdir().unwrap();
    let out = dir.path().join("texture.pmtiles");
    let summary = export_pmtiles(&reader, 0, &out, &Silent::default()).unwrap();
    let pm = AsyncPmTilesReader::new_with_path(&out).await.unwrap();
    let h = pm.get_header();
    assert_eq!(h.tile_type, TileType::Png);
    assert_eq!((h.min_zoom, h.max_zoom), (0, 3));
    assert_eq!(summary.addressed_tiles, 64);
    assert_eq!(check_same(&reader, 0, &out).await, 64);
    let meta: serde_json::Value = serde_json::from_str(&pm.get_metadata().await.unwrap()).unwrap();
    assert_eq!(meta["terrastream"]["layer"]["num_x_tiles"], 8);
    assert_eq!(std::fs::read_dir(dir.path()).unwrap().count(), 1, "no temporary file left");
}

#[tokio::test]
async fn large_layers_get_leaf_directories_that_the_reader_follows() {
    let meta = common::metadata(vec![common::layer("texture", 120, 120, 8)]);
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("big.tspack");
    let mut tiles: Vec<(u64, TileKey)> = Vec::new();
    for lod in 0..8u8 {
        let (nx, ny) = meta.layers[0].grid_at(lod);
        for y in 0..ny {
            for x in 0..nx {
                if (x * 7 + y * 3) % 11 == 0 && lod == 0 {
                    continue; // sparse
                }
                let t = TileKey::new(0, lod, x, y).unwrap();
                tiles.push((Writer::order_key(&meta, t).unwrap(), t));
            }
        }
    }
    tiles.sort();
    let mut w = Writer::create(&path, meta, WriterOptions::default()).unwrap();
    for (_, t) in &tiles {
        let len = (t.x().wrapping_mul(7919) ^ t.y().wrapping_mul(104_729)) % 2000 + 20;
        let mut payload = format!("{t}").into_bytes();
        payload.resize(payload.len() + len as usize, if t.x() % 5 == 0 { b'=' } else { b'.' });
        if (t.x() + t.y()) % 9 == 0 {
            payload = b"duplicate".to_vec();
        }
        w.add(*t, payload).unwrap();
    }
    w.finish().unwrap();
    let reader = Reader::open_mmap(&path).unwrap();
    let out = dir.path().join("big.pmtiles");
    let summary = export_pmtiles(&reader, 0, &out, &Silent::default()).unwrap();
    let bytes = std::fs::read(&out).unwrap();
    let leaves_len = u64::from_le_bytes(bytes[48..56].try_into().unwrap());
    assert!(leaves_len > 0, "this layer needs leaf directories");
    assert!(summary.tile_contents < summary.addressed_tiles, "duplicates stored once");
    assert_eq!(check_same(&reader, 0, &out).await, tiles.len() as u64);
}

/// Elevation tiles as they are stored: zstd ones say zstd, gradient-coded ones (which
/// PMTiles has no name for) "unknown", with the layer in the metadata saying what they are.
#[tokio::test]
async fn stored_compression_is_named_or_unknown() {
    use pmtiles::Compression;
    use terrastream_format::PayloadCompression;
    for (compression, named) in
        [(PayloadCompression::Zstd, Compression::Zstd), (PayloadCompression::ZstdGradient, Compression::Unknown)]
    {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("e.tspack");
        terrastream_testkit::archives::write_u16_archive(&path, 1, compression);
        let reader = Reader::open_mmap(&path).unwrap();
        let out = dir.path().join("e.pmtiles");
        export_pmtiles(&reader, 0, &out, &Silent::default()).unwrap();
        let pm = AsyncPmTilesReader::new_with_path(&out).await.unwrap();
        assert_eq!(pm.get_header().tile_compression, named, "{compression:?}");
        let meta: serde_json::Value = serde_json::from_str(&pm.get_metadata().await.unwrap()).unwrap();
        assert_eq!(meta["terrastream"]["layer"]["compression"], compression.name());
        assert_eq!(check_same(&reader, 0, &out).await, 4);
    }
}
