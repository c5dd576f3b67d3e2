//! `update`: new rasters over part of an archive give, byte for byte, the archive one run
//! over all the rasters makes (the new ones last: they win where they have data, and
//! their holes keep the old samples); the work is the touched rows only; bad updates are
//! refused naming what is wrong, with nothing written.
#![allow(clippy::unwrap_used, clippy::expect_used, clippy::cast_possible_truncation, missing_docs)]

mod common;

use common::tiles;

use std::path::{Path, PathBuf};

use terrastream_format::Reader;
use terrastream_pack::progress::Silent;
use terrastream_tiler::{ElevationStorage, Mosaic, MosaicOptions, TileOptions, tile_elevation, update};
use tiff::encoder::{TiffEncoder, colortype};
use tiff::tags::Tag;

const OPTIONS: TileOptions = TileOptions { tile_size: 32, border: 1, storage: ElevationStorage::Auto };

/// A UTM 33N GeoTIFF of f32 heights, `(w, h)` samples of 10 m from (east, north);
/// `height(x, y)` in metres east and north, NaN for nodata (written as -9999).
fn geotiff(path: &Path, (w, h): (u32, u32), (east, north): (f64, f64), height: impl Fn(f64, f64) -> f32) {
    let mut encoder = TiffEncoder::new(std::fs::File::create(path).unwrap()).unwrap();
    let mut image = encoder.new_image::<colortype::Gray32Float>(w, h).unwrap();
    image.encoder().write_tag(Tag::Unknown(33550), &[10.0, 10.0, 0.0][..]).unwrap();
    image.encoder().write_tag(Tag::Unknown(33922), &[0.0, 0.0, 0.0, east, north, 0.0][..]).unwrap();
    image.encoder().write_tag(Tag::Unknown(34735), &[1u16, 1, 0, 2, 1024, 0, 1, 1, 3072, 0, 1, 32633][..]).unwrap();
    image.encoder().write_tag(Tag::Unknown(42113), "-9999").unwrap();
    let data: Vec<f32> = (0..h)
        .flat_map(|j| (0..w).map(move |i| (i, j)))
        .map(|(i, j)| height(east + (f64::from(i) + 0.5) * 10.0, north - (f64::from(j) + 0.5) * 10.0))
        .map(|v| if v.is_nan() { -9999.0 } else { v })
        .collect();
    image.write_data(&data).unwrap();
}

fn base_height(x: f64, y: f64) -> f32 {
    (500.0 + 120.0 * ((x - 500_000.0) / 300.0).sin() * ((y - 5_000_000.0) / 230.0).cos()) as f32
}

fn tile(inputs: &[PathBuf], out: &Path) {
    let mosaic = Mosaic::open(inputs, &MosaicOptions::default()).unwrap();
    tile_elevation(&mosaic, "t", out, OPTIONS, &Silent::default()).unwrap();
}

#[test]
fn an_update_is_the_run_over_all_the_rasters() {
    let dir = tempfile::tempdir().unwrap();
    // The base: 330 x 270 samples (11 x 9 tiles of 32, partly padded).
    let base_tif = dir.path().join("base.tif");
    geotiff(&base_tif, (330, 270), (500_000.0, 5_002_700.0), base_height);
    let base = dir.path().join("base.tspack");
    tile(std::slice::from_ref(&base_tif), &base);
    // The change: 70 x 50 samples on the same grid, offset 100 and 90 samples, other
    // heights within the base's range, and a hole of nodata that keeps the base's heights.
    let new_tif = dir.path().join("resurvey.tif");
    let (east, north) = (500_000.0 + 100.0 * 10.0, 5_002_700.0 - 90.0 * 10.0);
    geotiff(&new_tif, (70, 50), (east, north), |x, y| {
        let (i, j) = ((x - east) / 10.0, (north - y) / 10.0);
        if (20.0..35.0).contains(&i) && (10.0..22.0).contains(&j) { f32::NAN } else { 450.0 + ((i * j) % 97.0) as f32 }
    });
    let out = dir.path().join("updated.tspack");
    let summary = update(&base, std::slice::from_ref(&new_tif), &[], &out, &Silent::default()).unwrap();
    // 70 x 50 samples touch 4 x 3 LOD-0 tiles; their rows are 3 of the 9 rows of tiles.
    assert!(summary.tiled > 0 && summary.tiled <= 2 * 11 * 4, "{} tiles from the new raster", summary.tiled);
    assert!(summary.merge.replaced > 0);

    let expected_path = dir.path().join("expected.tspack");
    tile(&[base_tif, new_tif.clone()], &expected_path);
    let (expected, got) = (tiles(&expected_path), tiles(&out));
    assert_ne!(expected, tiles(&base), "the change shows");
    let missing: Vec<_> = expected.keys().filter(|k| !got.contains_key(k)).take(5).collect();
    let extra: Vec<_> = got.keys().filter(|k| !expected.contains_key(k)).take(5).collect();
    assert!(missing.is_empty() && extra.is_empty(), "missing {missing:?}, extra {extra:?}");
    let differ: Vec<_> = expected.iter().filter(|(k, v)| got[k] != **v).map(|(k, _)| *k).take(8).collect();
    assert!(differ.is_empty(), "tiles differ from one run over both rasters: {differ:?}");
    assert_eq!(Reader::open_mmap(&out).unwrap().metadata(), Reader::open_mmap(&expected_path).unwrap().metadata());
}

#[test]
fn updates_that_cannot_fit_are_refused_and_write_nothing() {
    let dir = tempfile::tempdir().unwrap();
    let base_tif = dir.path().join("base.tif");
    geotiff(&base_tif, (200, 150), (500_000.0, 5_001_500.0), base_height);
    let base = dir.path().join("base.tspack");
    tile(std::slice::from_ref(&base_tif), &base);
    let out = dir.path().join("out.tspack");
    // Heights far above the base's encoding.
    let high = dir.path().join("high.tif");
    geotiff(&high, (20, 20), (500_500.0, 5_001_000.0), |_, _| 9_000.0);
    let err = update(&base, std::slice::from_ref(&high), &[], &out, &Silent::default()).unwrap_err().to_string();
    assert!(err.contains("high.tif") && err.contains("do not fit the archive's height encoding"), "{err}");
    // A texture update on an archive without imagery.
    let err = update(&base, &[], std::slice::from_ref(&base_tif), &out, &Silent::default()).unwrap_err().to_string();
    assert!(err.contains("base.tspack") && err.contains("no texture layer"), "{err}");
    // A geographic base (a single EPSG:4326 raster): no grid to place new rasters on.
    let geo = dir.path().join("geo.tspack");
    let raster = {
        let tif = dir.path().join("geo.tif");
        let mut encoder = TiffEncoder::new(std::fs::File::create(&tif).unwrap()).unwrap();
        let mut image = encoder.new_image::<colortype::Gray32Float>(40, 30).unwrap();
        image.encoder().write_tag(Tag::Unknown(33550), &[0.001, 0.001, 0.0][..]).unwrap();
        image.encoder().write_tag(Tag::Unknown(33922), &[0.0, 0.0, 0.0, 11.0, 46.0, 0.0][..]).unwrap();
        image.encoder().write_tag(Tag::Unknown(34735), &[1u16, 1, 0, 2, 1024, 0, 1, 2, 2048, 0, 1, 4326][..]).unwrap();
        image.write_data(&vec![100.0f32; 1200]).unwrap();
        terrastream_tiler::read_geotiff(&tif).unwrap()
    };
    tile_elevation(&raster, "g", &geo, OPTIONS, &Silent::default()).unwrap();
    let err = update(&geo, std::slice::from_ref(&high), &[], &out, &Silent::default()).unwrap_err().to_string();
    assert!(err.contains("geo.tspack") && err.contains("geographic"), "{err}");
    assert!(!out.exists(), "nothing written");
    let leftovers: Vec<_> = std::fs::read_dir(dir.path()).unwrap().map(|e| e.unwrap().file_name()).collect();
    assert!(leftovers.iter().all(|n| !n.to_string_lossy().starts_with(".update-")), "{leftovers:?}");
}
