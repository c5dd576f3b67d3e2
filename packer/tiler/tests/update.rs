//! `update`: new rasters over part of an archive give, byte for byte, the archive one run
//! over all the rasters makes (the new ones last: they win where they have data, and
//! their holes keep the old samples); the work is the touched rows only; bad updates are
//! refused naming what is wrong, with nothing written.
#![allow(clippy::unwrap_used, clippy::expect_used, clippy::cast_possible_truncation, missing_docs)]

mod common;

use common::tiles;

use std::collections::BTreeMap;
use std::path::{Path, PathBuf};

use terrastream_format::Reader;
use terrastream_pack::progress::Silent;
use terrastream_pack::{Writer, WriterOptions};
use terrastream_tiler::{
    ElevationStorage, Mosaic, MosaicOptions, TextureFormat, TextureInput, TileOptions, tile_elevation, tile_terrain,
    update,
};
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

/// How an update is written.
#[derive(Clone, Copy, Debug, PartialEq)]
enum Mode {
    /// `-o` another file: a copy of the base, appended to.
    Copy,
    /// The base itself, appended to.
    InPlace,
    /// The base itself, written by a version without room for updates: written anew.
    InPlaceNoRoom,
}

fn update_gives_the_run_over_all_the_rasters(mode: Mode) {
    let dir = tempfile::tempdir().unwrap();
    // The base: 330 x 270 samples (11 x 9 tiles of 32, partly padded).
    let base_tif = dir.path().join("base.tif");
    geotiff(&base_tif, (330, 270), (500_000.0, 5_002_700.0), base_height);
    let base = dir.path().join("base.tspack");
    tile(std::slice::from_ref(&base_tif), &base);
    if mode == Mode::InPlaceNoRoom {
        rewrite_without_room(&base);
    }
    let original = tiles(&base);
    let original_len = std::fs::metadata(&base).unwrap().len();
    let inode = |p: &Path| std::os::unix::fs::MetadataExt::ino(&std::fs::metadata(p).unwrap());
    let original_inode = inode(&base);
    let opened_before = Reader::open_mmap(&base).unwrap();
    // The change: 70 x 50 samples on the same grid, offset 100 and 90 samples, other
    // heights within the base's range, and a hole of nodata that keeps the base's heights.
    let new_tif = dir.path().join("resurvey.tif");
    let (east, north) = (500_000.0 + 100.0 * 10.0, 5_002_700.0 - 90.0 * 10.0);
    geotiff(&new_tif, (70, 50), (east, north), |x, y| {
        let (i, j) = ((x - east) / 10.0, (north - y) / 10.0);
        if (20.0..35.0).contains(&i) && (10.0..22.0).contains(&j) { f32::NAN } else { 450.0 + ((i * j) % 97.0) as f32 }
    });
    let out = if mode == Mode::Copy { dir.path().join("updated.tspack") } else { base.clone() };
    let summary = update(&base, std::slice::from_ref(&new_tif), &[], &out, &Silent::default()).unwrap();
    // 70 x 50 samples touch 4 x 3 LOD-0 tiles; their rows are 3 of the 9 rows of tiles.
    assert!(summary.tiled > 0 && summary.tiled <= 2 * 11 * 4, "{} tiles from the new raster", summary.tiled);
    assert!(summary.merge.replaced > 0);
    assert_eq!(summary.merge.write.path, out);

    let expected_path = dir.path().join("expected.tspack");
    tile(&[base_tif, new_tif.clone()], &expected_path);
    let (expected, got) = (tiles(&expected_path), tiles(&out));
    assert_ne!(expected, original, "the change shows");
    let missing: Vec<_> = expected.keys().filter(|k| !got.contains_key(k)).take(5).collect();
    let extra: Vec<_> = got.keys().filter(|k| !expected.contains_key(k)).take(5).collect();
    assert!(missing.is_empty() && extra.is_empty(), "missing {missing:?}, extra {extra:?}");
    let differ: Vec<_> = expected.iter().filter(|(k, v)| got[k] != **v).map(|(k, _)| *k).take(8).collect();
    assert!(differ.is_empty(), "tiles differ from one run over both rasters: {differ:?}");
    assert_eq!(Reader::open_mmap(&out).unwrap().metadata(), Reader::open_mmap(&expected_path).unwrap().metadata());
    let report = terrastream_format::verify(&Reader::open_mmap(&out).unwrap(), |_| {}).unwrap();
    assert!(report.is_ok(), "{:?}", report.problems);

    match mode {
        Mode::Copy => assert_eq!(tiles(&base), original, "the base is untouched"),
        Mode::InPlace => {
            // Appended: the changed tiles' bytes and no more than a few of the others'.
            let changed: u64 =
                got.iter().filter(|(k, v)| original.get(k) != Some(v)).map(|(_, v)| v.len() as u64 + 4).sum();
            let grown = std::fs::metadata(&base).unwrap().len() - original_len;
            assert!(grown <= changed, "the archive grew by {grown} bytes for {changed} bytes of changed tiles");
            assert_eq!(inode(&base), original_inode, "the same file, appended to");
        }
        Mode::InPlaceNoRoom => assert_ne!(inode(&base), original_inode, "a new file renamed over the base"),
    }
    // A reader that opened the base before reads the old version, every tile (an archive
    // written anew is a new file; the reader keeps the old one).
    let mut old = BTreeMap::new();
    opened_before
        .for_each_tile(|key, payload| -> terrastream_format::Result<()> {
            old.insert(key, payload.to_vec());
            Ok(())
        })
        .unwrap();
    assert_eq!(old, original);
}

/// Writes `path` again as a version without room for in-place updates did.
fn rewrite_without_room(path: &Path) {
    let reader = Reader::open_mmap(path).unwrap();
    let options = WriterOptions { reserve: false, ..WriterOptions::default() };
    let mut writer = Writer::create(path, reader.metadata().clone(), options).unwrap();
    let mut stored = Vec::new();
    reader
        .for_each_entry(|e| -> terrastream_format::Result<()> {
            for k in 0..u64::from(e.run_length) {
                let key = e.key + k * terrastream_format::MAX_LAYERS as u64;
                let tile = reader.archive().tile_of(key)?;
                let at = terrastream_format::TileLocation {
                    key: tile,
                    offset: reader.header().data.offset + e.offset,
                    length: e.length,
                };
                stored.push((tile, reader.read(&at)?.to_vec()));
            }
            Ok(())
        })
        .unwrap();
    for (tile, bytes) in stored {
        writer.add_stored(tile, bytes).unwrap();
    }
    writer.finish().unwrap();
    let header = Reader::open_mmap(path).unwrap().header().clone();
    assert!(header.data.offset < 16 * 1024, "written without room: data at {}", header.data.offset);
}

#[test]
fn an_update_is_the_run_over_all_the_rasters() {
    update_gives_the_run_over_all_the_rasters(Mode::Copy);
}

#[test]
fn an_update_in_place_appends_only_what_changed() {
    update_gives_the_run_over_all_the_rasters(Mode::InPlace);
}

#[test]
fn an_archive_without_room_is_updated_by_writing_it_anew() {
    update_gives_the_run_over_all_the_rasters(Mode::InPlaceNoRoom);
}

#[test]
fn an_update_that_fills_a_hole_makes_every_level_above_it() {
    // A base with a hole of 240 x 200 samples (many whole tiles of no data at LOD 0 and 1),
    // filled by the update: the tiles above its middle, which no stored tile had, are made.
    let dir = tempfile::tempdir().unwrap();
    let base_tif = dir.path().join("holed.tif");
    let hole = |x: f64, y: f64| (500_400.0..502_800.0).contains(&x) && (5_000_300.0..5_002_300.0).contains(&y);
    geotiff(
        &base_tif,
        (330, 270),
        (500_000.0, 5_002_700.0),
        |x, y| if hole(x, y) { f32::NAN } else { base_height(x, y) },
    );
    let base = dir.path().join("base.tspack");
    tile(std::slice::from_ref(&base_tif), &base);
    let fill = dir.path().join("fill.tif");
    geotiff(&fill, (240, 200), (500_400.0, 5_002_300.0), |x, y| base_height(x, y) + 7.0);
    update(&base, std::slice::from_ref(&fill), &[], &base, &Silent::default()).unwrap();
    let expected_path = dir.path().join("expected.tspack");
    tile(&[base_tif, fill], &expected_path);
    let (expected, got) = (tiles(&expected_path), tiles(&base));
    let missing: Vec<_> = expected.keys().filter(|k| !got.contains_key(k)).take(5).collect();
    assert!(missing.is_empty(), "missing {missing:?}");
    let differ: Vec<_> = expected.iter().filter(|(k, v)| got.get(k) != Some(v)).map(|(k, _)| *k).take(8).collect();
    assert!(differ.is_empty() && expected.len() == got.len(), "tiles differ from one run: {differ:?}");
    // The new heights reach above the base's: the terrain's range says so, as one run's.
    let terrain = |p: &Path| Reader::open_mmap(p).unwrap().metadata().terrain.clone();
    assert!(terrain(&base).max_elevation > base_height_max(), "{:?}", terrain(&base));
    assert_eq!(terrain(&base), terrain(&expected_path));
}

/// The highest height of [`base_height`].
fn base_height_max() -> f64 {
    620.0
}

/// A UTM 33N RGB GeoTIFF, `(w, h)` pixels of 10 m from (east, north), colour by pixel.
fn image(path: &Path, (w, h): (u32, u32), (east, north): (f64, f64), colour: impl Fn(u32, u32) -> [u8; 3]) {
    let mut encoder = TiffEncoder::new(std::fs::File::create(path).unwrap()).unwrap();
    let mut image = encoder.new_image::<colortype::RGB8>(w, h).unwrap();
    image.encoder().write_tag(Tag::Unknown(33550), &[10.0, 10.0, 0.0][..]).unwrap();
    image.encoder().write_tag(Tag::Unknown(33922), &[0.0, 0.0, 0.0, east, north, 0.0][..]).unwrap();
    image.encoder().write_tag(Tag::Unknown(34735), &[1u16, 1, 0, 2, 1024, 0, 1, 1, 3072, 0, 1, 32633][..]).unwrap();
    let pixels: Vec<u8> = (0..h).flat_map(|j| (0..w).map(move |i| (i, j))).flat_map(|(i, j)| colour(i, j)).collect();
    image.write_data(&pixels).unwrap();
}

/// Elevation and imagery over the same 10 m grid, imagery from `images` (a later one wins).
fn tile_with_imagery(dem: &Path, images: &[PathBuf], out: &Path) {
    let elevation =
        Mosaic::<terrastream_tiler::Heights>::open(&[dem.to_path_buf()], &MosaicOptions::default()).unwrap();
    let g = terrastream_tiler::ElevationSource::georeference(&elevation).unwrap().clone();
    let (w, h) = terrastream_tiler::ElevationSource::size(&elevation);
    let origin = g.origin.unwrap();
    let extent = [origin[0], origin[1] - f64::from(h) * 10.0, origin[0] + f64::from(w) * 10.0, origin[1]];
    let options = MosaicOptions { extent: Some(extent), ..MosaicOptions::default() };
    let mosaic = Mosaic::<terrastream_tiler::Pixels>::open(images, &options).unwrap();
    let texture = TextureInput { source: &mosaic, tile_size: 32, format: TextureFormat::Png, pixel_size: 1.0 };
    tile_terrain(Some(&elevation), Some(texture), "t", out, OPTIONS, &Silent::default()).unwrap();
}

#[test]
fn an_imagery_update_in_place_is_the_run_over_all_the_images() {
    let dir = tempfile::tempdir().unwrap();
    let dem = dir.path().join("dem.tif");
    geotiff(&dem, (330, 270), (500_000.0, 5_002_700.0), base_height);
    let photo = dir.path().join("photo.tif");
    image(&photo, (330, 270), (500_000.0, 5_002_700.0), |i, j| [(i % 256) as u8, (j % 256) as u8, 90]);
    let base = dir.path().join("base.tspack");
    tile_with_imagery(&dem, std::slice::from_ref(&photo), &base);
    // A re-flown patch of 60 x 40 pixels, 120 and 70 pixels in.
    let reflown = dir.path().join("reflown.tif");
    image(&reflown, (60, 40), (500_000.0 + 1_200.0, 5_002_700.0 - 700.0), |i, j| [200, (i * 4) as u8, (j * 6) as u8]);
    let original = tiles(&base);
    let summary = update(&base, &[], std::slice::from_ref(&reflown), &base, &Silent::default()).unwrap();
    assert!(summary.tiled > 0 && summary.merge.replaced > 0, "{summary:?}");

    let expected_path = dir.path().join("expected.tspack");
    tile_with_imagery(&dem, &[photo, reflown], &expected_path);
    let (expected, got) = (tiles(&expected_path), tiles(&base));
    assert_ne!(expected, original, "the change shows");
    assert_eq!(expected.len(), got.len());
    let differ: Vec<_> = expected.iter().filter(|(k, v)| got.get(k) != Some(v)).map(|(k, _)| *k).take(8).collect();
    assert!(differ.is_empty(), "tiles differ from one run over both images: {differ:?}");
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
    assert!(err.contains("high.tif") && err.contains("outside the archive's height encoding"), "{err}");
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
    // A shard of a sharded run: its set would no longer hold together.
    let shard = dir.path().join("shard.tspack");
    let mosaic = Mosaic::open(std::slice::from_ref(&base_tif), &MosaicOptions::default()).unwrap();
    terrastream_tiler::tile_shard(
        Some(&mosaic),
        None,
        "s",
        &shard,
        OPTIONS,
        Some(terrastream_tiler::ShardSpec { index: 0, count: 2, split_lod: None, cuts: None }),
        &Silent::default(),
    )
    .unwrap();
    let err = update(&shard, std::slice::from_ref(&high), &[], &shard, &Silent::default()).unwrap_err().to_string();
    assert!(err.contains("shard.tspack") && err.contains("shard 0/2 of a sharded run"), "{err}");
    assert!(!out.exists(), "nothing written");
    let leftovers: Vec<_> = std::fs::read_dir(dir.path()).unwrap().map(|e| e.unwrap().file_name()).collect();
    assert!(leftovers.iter().all(|n| !n.to_string_lossy().starts_with(".update-")), "{leftovers:?}");
}

/// Every tile's payload with its layer's compression undone, by key.
fn payloads(path: &Path) -> BTreeMap<terrastream_format::TileKey, Vec<u8>> {
    let reader = Reader::open_mmap(path).unwrap();
    let meta = reader.metadata().clone();
    tiles(path)
        .into_iter()
        .map(|(key, stored)| {
            let layer = &meta.layers[usize::from(key.layer())];
            (key, terrastream_format::payload_bytes(layer, &stored, "t").unwrap().into_owned())
        })
        .collect()
}

/// `path` written again as archives were before gradient coding: u16 heights in plain
/// zstd, format major 1.
fn rewrite_as_zstd(path: &Path) {
    use terrastream_format::PayloadCompression;
    let payloads = payloads(path);
    let mut meta = Reader::open_mmap(path).unwrap().metadata().clone();
    for l in &mut meta.layers {
        if l.compression == PayloadCompression::ZstdGradient {
            l.compression = PayloadCompression::Zstd;
        }
    }
    let mut ordered: Vec<_> = payloads.into_iter().collect();
    ordered.sort_by_key(|(key, _)| Writer::order_key(&meta, *key).unwrap());
    let mut writer = Writer::create(path, meta, WriterOptions::default()).unwrap();
    for (key, payload) in ordered {
        writer.add(key, payload).unwrap();
    }
    writer.finish().unwrap();
    assert_eq!(Reader::open_mmap(path).unwrap().header().version_major, 1);
}

/// An archive made before gradient coding (zstd heights) and one made after merge either
/// way round: each tile stored as the first input stores its kind, the payloads those of
/// the merge of two archives made alike.
#[test]
fn archives_before_and_after_gradient_coding_merge_either_way() {
    use terrastream_format::PayloadCompression;
    let dir = tempfile::tempdir().unwrap();
    let base_tif = dir.path().join("base.tif");
    geotiff(&base_tif, (330, 270), (500_000.0, 5_002_700.0), base_height);
    let new_tif = dir.path().join("resurvey.tif");
    let (east, north) = (500_000.0 + 100.0 * 10.0, 5_002_700.0 - 90.0 * 10.0);
    geotiff(&new_tif, (70, 50), (east, north), |x, y| 450.0 + ((x - east) * (north - y) / 100.0 % 97.0) as f32);
    // Two archives of one grid: the base, and the base with the resurvey over it.
    let (old, new) = (dir.path().join("old.tspack"), dir.path().join("new.tspack"));
    tile(std::slice::from_ref(&base_tif), &old);
    tile(&[base_tif, new_tif], &new);
    let old_gradient = dir.path().join("old-gradient.tspack");
    std::fs::copy(&old, &old_gradient).unwrap();
    rewrite_as_zstd(&old);
    for (inputs, first) in [([&old, &new], PayloadCompression::Zstd), ([&new, &old], PayloadCompression::ZstdGradient)]
    {
        let out = dir.path().join("merged.tspack");
        terrastream_tiler::merge(&[inputs[0].clone(), inputs[1].clone()], &out, &Silent::default()).unwrap();
        let alike = dir.path().join("alike.tspack");
        let same_kind: Vec<PathBuf> =
            inputs.iter().map(|p| if *p == &old { old_gradient.clone() } else { (*p).clone() }).collect();
        terrastream_tiler::merge(&same_kind, &alike, &Silent::default()).unwrap();
        let reader = Reader::open_mmap(&out).unwrap();
        assert_eq!(reader.metadata().layers[0].compression, first);
        assert_eq!(reader.header().version_major, reader.metadata().format_major());
        assert!(terrastream_format::verify(&reader, |_| {}).unwrap().is_ok());
        let (got, want) = (payloads(&out), payloads(&alike));
        assert_eq!(got.len(), want.len());
        let differ: Vec<_> = want.iter().filter(|(k, v)| got.get(k) != Some(v)).map(|(k, _)| *k).take(8).collect();
        assert!(differ.is_empty(), "{first:?} first: tiles differ from a merge of alike archives: {differ:?}");
    }
}
