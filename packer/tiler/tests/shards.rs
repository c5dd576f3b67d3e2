//! Sharded runs: N shards (`tile_shard`) merged (`merge`) give, tile for tile, the same
//! payload bytes and metadata as one whole run over the same inputs, for N = 1, 3 and 4,
//! elevation (with nodata, its height-range layer) and PNG imagery, odd sizes included.
//! And the merge's refusals: a missing shard, a shard twice, a different grid.
#![allow(
    clippy::unwrap_used,
    clippy::expect_used,
    clippy::cast_possible_truncation,
    clippy::cast_precision_loss,
    missing_docs
)]

mod common;

use common::tiles;

use std::collections::BTreeMap;
use std::path::{Path, PathBuf};

use terrastream_format::{Metadata, Reader, TileKey};
use terrastream_pack::progress::Silent;
use terrastream_tiler::{
    ElevationSource, ElevationStorage, Image, KnownRange, Raster, ShardSpec, TextureFormat, TextureInput, TileOptions,
    merge, tile_shard, tile_terrain,
};

/// 203 x 157 heights (odd sizes: padded tiles at every level), with a hole of nodata and
/// a bumpy surface whose coarser means are not on the quantization grid.
fn dem() -> Raster {
    let (w, h) = (203u32, 157u32);
    let data = (0..h)
        .flat_map(|y| (0..w).map(move |x| (x, y)))
        .map(|(x, y)| {
            if (40..70).contains(&x) && (100..130).contains(&y) {
                f32::NAN
            } else {
                let (fx, fy) = (f64::from(x), f64::from(y));
                (300.0 + 80.0 * (fx / 17.0).sin() * (fy / 23.0).cos() + 0.37 * fx - 0.11 * fy) as f32
            }
        })
        .collect();
    Raster { width: w, height: h, data, spacing: (10.0, 10.0), georeference: None }
}

/// 406 x 314 pixels over the same area, with a transparent corner.
fn image() -> Image {
    let (w, h) = (406u32, 314u32);
    let rgba = (0..h)
        .flat_map(|y| (0..w).map(move |x| (x, y)))
        .flat_map(|(x, y)| {
            let a = if x + y < 60 { 0 } else { 255 };
            [(x * 7 % 256) as u8, (y * 5 % 256) as u8, ((x ^ y) % 256) as u8, a]
        })
        .collect();
    Image { width: w, height: h, rgba, georeference: None }
}

const OPTIONS: TileOptions = TileOptions { tile_size: 16, border: 1, storage: ElevationStorage::Auto };

fn texture(image: &Image) -> TextureInput<'_> {
    TextureInput { source: image, tile_size: 16, format: TextureFormat::Png, pixel_size: 1.0 }
}

fn shards(dir: &Path, n: u32, split_lod: Option<u8>, dem: &Raster, image: &Image) -> Vec<PathBuf> {
    (0..n)
        .map(|i| {
            let out = dir.join(format!("shard-{n}-{i}.tspack"));
            let spec = ShardSpec { index: i, count: n, split_lod, cuts: None };
            tile_shard(Some(dem), Some(texture(image)), "t", &out, OPTIONS, Some(spec), &Silent::default()).unwrap();
            out
        })
        .collect()
}

/// One whole run over `dem` and `image` into `dir`: the archive, its tiles, its metadata.
fn whole_run(dir: &Path, dem: &Raster, image: &Image) -> (PathBuf, BTreeMap<TileKey, Vec<u8>>, Metadata) {
    let whole = dir.join("whole.tspack");
    tile_terrain(Some(dem), Some(texture(image)), "t", &whole, OPTIONS, &Silent::default()).unwrap();
    let metadata = Reader::open_mmap(&whole).unwrap().metadata().clone();
    (whole.clone(), tiles(&whole), metadata)
}

/// Each phase's name, total and units advanced.
#[derive(Default)]
struct Counted {
    phases: std::sync::Mutex<Vec<(String, u64, u64)>>,
}

impl terrastream_pack::progress::Progress for Counted {
    fn start(&self, phase: &str, total: u64) {
        self.phases.lock().unwrap().push((phase.to_owned(), total, 0));
    }
    fn advance(&self, n: u64) {
        if let Some(last) = self.phases.lock().unwrap().last_mut() {
            last.2 += n;
        }
    }
}

#[test]
fn shards_merged_are_the_whole_run_byte_for_byte() {
    let dir = tempfile::tempdir().unwrap();
    let (dem, image) = (dem(), image());
    let (_, expected, expected_meta) = whole_run(dir.path(), &dem, &image);
    // 13 x 10 elevation tiles (4 LODs above LOD 0), 26 x 20 texture tiles.
    assert!(expected.keys().any(|k| k.lod() == 4), "a pyramid several levels deep");
    for (n, split) in [(1, None), (3, None), (4, None), (3, Some(1)), (4, Some(0))] {
        let parts = shards(dir.path(), n, split, &dem, &image);
        // Each shard holds part of the tiles, none above its split LOD.
        let held: usize = parts.iter().map(|p| tiles(p).len()).sum();
        let meta = Reader::open_mmap(&parts[0]).unwrap().metadata().clone();
        let shard = meta.shard.clone().unwrap();
        assert_eq!(shard.count, n);
        if n > 1 {
            assert!(held < expected.len(), "N = {n}: the shards hold {held} of {} tiles", expected.len());
        }
        let merged = dir.path().join(format!("merged-{n}-{split:?}.tspack"));
        let counted = Counted::default();
        let summary = merge(&parts, &merged, &counted).unwrap();
        // Each phase reaches its total and no more (the levels above the split are a phase
        // of their own, not more of the index's).
        let phases = counted.phases.into_inner().unwrap();
        assert!(phases.iter().any(|p| p.0 == "tile"), "N = {n}: {phases:?}");
        assert!(phases.iter().all(|&(_, total, done)| done == total), "N = {n}, split {split:?}: {phases:?}");
        assert_eq!(summary.copied + summary.made, expected.len() as u64);
        assert!(summary.made > 0, "N = {n}: the levels above the split LOD are made by the merge");
        let got = tiles(&merged);
        let missing: Vec<_> = expected.keys().filter(|k| !got.contains_key(k)).take(5).collect();
        let extra: Vec<_> = got.keys().filter(|k| !expected.contains_key(k)).take(5).collect();
        assert!(
            missing.is_empty() && extra.is_empty(),
            "N = {n}, split {split:?}: missing {missing:?}, extra {extra:?}"
        );
        let differ: Vec<_> = expected.iter().filter(|(k, v)| got[k] != **v).map(|(k, _)| *k).take(5).collect();
        assert!(differ.is_empty(), "N = {n}, split {split:?} ({shard:?}): tiles differ: {differ:?}");
        assert_eq!(Reader::open_mmap(&merged).unwrap().metadata(), &expected_meta, "N = {n}");
    }
}

#[test]
fn a_merge_refuses_missing_or_repeated_shards_and_other_grids() {
    let dir = tempfile::tempdir().unwrap();
    let (dem, image) = (dem(), image());
    let parts = shards(dir.path(), 3, None, &dem, &image);
    let out = dir.path().join("out.tspack");
    let err = merge(&parts[..2], &out, &Silent::default()).unwrap_err().to_string();
    assert!(err.contains("shards 2 of 3 are missing"), "{err}");
    let err = merge(&[parts[0].clone(), parts[1].clone(), parts[1].clone()], &out, &Silent::default())
        .unwrap_err()
        .to_string();
    assert!(err.contains("given twice") && err.contains("shard-3-1.tspack"), "{err}");
    // Another tile size: a different grid, named.
    let other = dir.path().join("other.tspack");
    let options = TileOptions { tile_size: 32, ..OPTIONS };
    tile_terrain(Some(&dem), None, "t", &other, options, &Silent::default()).unwrap();
    let whole = dir.path().join("whole.tspack");
    tile_terrain(Some(&dem), None, "t", &whole, OPTIONS, &Silent::default()).unwrap();
    let err = merge(&[whole.clone(), other], &out, &Silent::default()).unwrap_err().to_string();
    assert!(err.contains("other.tspack") && err.contains("layer \"elevation\"") && err.contains("5 there"), "{err}");
    assert!(!out.exists(), "nothing written");
    // The same archive twice: the same bytes replace nothing, nothing is remade.
    let summary = merge(&[whole.clone(), whole.clone()], &out, &Silent::default()).unwrap();
    assert_eq!((summary.replaced, summary.made), (0, 0));
    assert_eq!(tiles(&out), tiles(&whole));
}

/// Elevation tiles (x 4..8, y 3..6 of 16-sample tiles) and texture tiles (x 8..16, y 6..12)
/// where the second terrain differs: the same surface, shifted.
const DEM_RECT: (std::ops::Range<u32>, std::ops::Range<u32>) = (4..8, 3..6);
const IMAGE_RECT: (std::ops::Range<u32>, std::ops::Range<u32>) = (8..16, 6..12);

fn inside(rect: &(std::ops::Range<u32>, std::ops::Range<u32>), x: u32, y: u32) -> bool {
    rect.0.contains(&(x / 16)) && rect.1.contains(&(y / 16))
}

/// `dem()` with the samples in `DEM_RECT` taken 7 right and 3 down (values found elsewhere
/// in it: the height range, so the height encoding, stays the same).
fn changed_dem() -> Raster {
    let mut d = dem();
    let w = d.width as usize;
    let original = d.data.clone();
    for y in 0..d.height {
        for x in 0..d.width {
            if inside(&DEM_RECT, x, y) {
                d.data[y as usize * w + x as usize] = original[(y as usize + 3) * w + x as usize + 7];
            }
        }
    }
    d
}

fn changed_image() -> Image {
    let mut i = image();
    let w = i.width as usize;
    let original = i.rgba.clone();
    for y in 0..i.height {
        for x in 0..i.width {
            if inside(&IMAGE_RECT, x, y) {
                let (to, from) = ((y as usize * w + x as usize) * 4, ((y as usize + 5) * w + x as usize + 11) * 4);
                i.rgba[to..to + 4].copy_from_slice(&original[from..from + 4]);
            }
        }
    }
    i
}

#[test]
fn merging_a_region_remakes_the_tiles_around_and_above_it_as_one_run_would() {
    let dir = tempfile::tempdir().unwrap();
    let silent = Silent::default();
    let base = dir.path().join("base.tspack");
    tile_terrain(Some(&dem()), Some(texture(&image())), "t", &base, OPTIONS, &silent).unwrap();
    // The region: the tiles of a run over the changed terrain that lie inside the changed
    // rectangles, every LOD (a region's own pyramid), written as an archive of the grid.
    let (changed_dem, changed_image) = (changed_dem(), changed_image());
    let full = dir.path().join("changed.tspack");
    tile_terrain(Some(&changed_dem), Some(texture(&changed_image)), "t", &full, OPTIONS, &silent).unwrap();
    let reader = Reader::open_mmap(&full).unwrap();
    let metadata = reader.metadata().clone();
    let region = dir.path().join("region.tspack");
    let mut writer =
        terrastream_pack::Writer::create(&region, metadata.clone(), terrastream_pack::WriterOptions::default())
            .unwrap();
    let mut kept = 0;
    let mut in_order: Vec<_> = tiles(&full).into_iter().collect();
    in_order.sort_by_key(|(k, _)| terrastream_pack::Writer::order_key(&metadata, *k).unwrap());
    for (key, bytes) in in_order {
        let kind = metadata.layers[usize::from(key.layer())].kind;
        let rect = if kind == terrastream_format::LayerKind::Texture { &IMAGE_RECT } else { &DEM_RECT };
        let span = 1u32 << key.lod();
        let (x0, y0) = (key.x() * span, key.y() * span);
        if rect.0.contains(&x0)
            && rect.0.contains(&(x0 + span - 1))
            && rect.1.contains(&y0)
            && rect.1.contains(&(y0 + span - 1))
        {
            writer.add_stored(key, bytes).unwrap();
            kept += 1;
        }
    }
    writer.finish().unwrap();
    assert!(kept > 20, "{kept} tiles in the region");

    let merged = dir.path().join("merged.tspack");
    let summary = merge(&[base.clone(), region], &merged, &silent).unwrap();
    // Every region tile replaces the base's, but for those with the same bytes.
    assert!(summary.replaced <= kept && summary.replaced > kept * 9 / 10, "{} of {kept} replaced", summary.replaced);
    assert!(summary.made > summary.replaced, "the ring around the region and the levels above are remade");

    // One run over the combined terrain: the changed rectangles from the second.
    let (mut combined_dem, mut combined_image) = (dem(), image());
    for (i, v) in changed_dem.data.iter().enumerate() {
        let (x, y) = ((i % changed_dem.width as usize) as u32, (i / changed_dem.width as usize) as u32);
        if inside(&DEM_RECT, x, y) {
            combined_dem.data[i] = *v;
        }
    }
    for (i, p) in changed_image.rgba.chunks_exact(4).enumerate() {
        let (x, y) = ((i % changed_image.width as usize) as u32, (i / changed_image.width as usize) as u32);
        if inside(&IMAGE_RECT, x, y) {
            combined_image.rgba[i * 4..i * 4 + 4].copy_from_slice(p);
        }
    }
    let expected_path = dir.path().join("combined.tspack");
    tile_terrain(Some(&combined_dem), Some(texture(&combined_image)), "t", &expected_path, OPTIONS, &silent).unwrap();
    let (expected, got) = (tiles(&expected_path), tiles(&merged));
    assert_ne!(expected, tiles(&base), "the change shows");
    let missing: Vec<_> = expected.keys().filter(|k| !got.contains_key(k)).take(5).collect();
    let extra: Vec<_> = got.keys().filter(|k| !expected.contains_key(k)).take(5).collect();
    assert!(missing.is_empty() && extra.is_empty(), "missing {missing:?}, extra {extra:?}");
    let differ: Vec<_> = expected.iter().filter(|(k, v)| got[k] != **v).map(|(k, _)| *k).take(8).collect();
    assert!(differ.is_empty(), "tiles differ from one run over the combined terrain: {differ:?}");
}

#[test]
fn shards_given_the_height_range_skip_its_pass_and_check_it() {
    use terrastream_tiler::{ElevationSource, KnownRange};
    let dir = tempfile::tempdir().unwrap();
    let (dem, image) = (dem(), image());
    let whole = dir.path().join("whole.tspack");
    tile_terrain(Some(&dem), Some(texture(&image)), "t", &whole, OPTIONS, &Silent::default()).unwrap();
    let range = dem.height_range(&mut |_| Ok(())).unwrap();
    let known = KnownRange::new(&dem, range);
    let parts: Vec<PathBuf> = (0..3)
        .map(|i| {
            let out = dir.path().join(format!("known-{i}.tspack"));
            let spec = ShardSpec { index: i, count: 3, split_lod: None, cuts: None };
            tile_shard(Some(&known), Some(texture(&image)), "t", &out, OPTIONS, Some(spec), &Silent::default())
                .unwrap();
            out
        })
        .collect();
    let merged = dir.path().join("merged.tspack");
    merge(&parts, &merged, &Silent::default()).unwrap();
    assert_eq!(tiles(&merged), tiles(&whole));
    // A range that leaves heights out: the shard that meets them stops, naming why.
    let narrow = KnownRange::new(&dem, (range.0 + 10.0, range.1));
    let spec = ShardSpec { index: 0, count: 1, split_lod: None, cuts: None };
    let out = dir.path().join("narrow.tspack");
    let err =
        tile_shard(Some(&narrow), None, "t", &out, OPTIONS, Some(spec), &Silent::default()).unwrap_err().to_string();
    assert!(err.contains("outside the given height range"), "{err}");
    assert!(!out.exists());
}

/// `merge --manifest`: the shards stay, a coarse archive gets the levels above the split
/// LOD, and the manifest routes every tile of the whole run to the one archive that holds
/// it, with the whole run's bytes; every tile of every archive is reachable.
#[test]
fn a_manifest_of_shards_routes_every_tile_of_the_whole_run() {
    use terrastream_format::Manifest;
    let dir = tempfile::tempdir().unwrap();
    let (dem, image) = (dem(), image());
    let (whole, expected, expected_meta) = whole_run(dir.path(), &dem, &image);
    let shard_dir = dir.path().join("shards");
    std::fs::create_dir(&shard_dir).unwrap();
    let parts = shards(&shard_dir, 3, None, &dem, &image);
    let published = dir.path().join("pub");
    std::fs::create_dir(&published).unwrap();
    let (coarse, manifest_path) = (published.join("coarse.tspack"), published.join("t.json"));
    let summary = terrastream_tiler::merge_to_manifest(
        &parts,
        &coarse,
        &manifest_path,
        None,
        terrastream_tiler::RunInputs::default(),
        &Silent::default(),
    )
    .unwrap();
    let manifest = Manifest::from_json(&std::fs::read(&manifest_path).unwrap()).unwrap();
    assert_eq!(manifest, summary.manifest);
    assert_eq!(manifest.metadata, expected_meta);
    assert_eq!(manifest.archives.len(), 4, "the coarse archive and three shards");
    assert_eq!(manifest.archives[0].url, "coarse.tspack");
    assert_eq!(manifest.archives[1].url, "../shards/shard-3-0.tspack");
    let held: Vec<_> = manifest
        .archives
        .iter()
        .enumerate()
        .map(|(i, _)| {
            let path = manifest.resolve(manifest_path.to_str().unwrap(), i).unwrap();
            let reader = Reader::open_mmap(&path).unwrap();
            manifest.check_part(i, &reader.header().encode(), reader.metadata()).unwrap();
            tiles(Path::new(&path))
        })
        .collect();
    for (key, bytes) in &expected {
        let route = manifest.route(*key).unwrap_or_else(|| panic!("{key}: no archive"));
        assert_eq!(held[route.part].get(&route.key), Some(bytes), "{key} from archive {}", route.part);
    }
    let reachable: usize = held.iter().map(BTreeMap::len).sum();
    assert_eq!(reachable, expected.len(), "every archive's tiles, each once");
    // Not a complete shard set: refused, nothing written.
    let e = terrastream_tiler::merge_to_manifest(
        &[whole],
        &coarse,
        &dir.path().join("x.json"),
        None,
        terrastream_tiler::RunInputs::default(),
        &Silent::default(),
    )
    .unwrap_err();
    assert!(e.to_string().contains("complete set of shards"), "{e}");
    assert!(!dir.path().join("x.json").exists());
}

/// The shards' DEM as an int16 GeoTIFF of 4-row strips (nodata -32767), with `pit` metres
/// at one sample of row 6: a strip the estimated range does not read. With `degrees`
/// (west, north, step), placed in EPSG:4326 there, so that a run onto a projected CRS
/// warps it.
fn dem_file(path: &Path, pit: i16, degrees: Option<(f64, f64, f64)>) {
    use tiff::encoder::{TiffEncoder, colortype::GrayI16};
    use tiff::tags::Tag;
    let raster = dem();
    let mut data: Vec<i16> = raster.data.iter().map(|h| if h.is_nan() { -32_767 } else { h.round() as i16 }).collect();
    data[6 * raster.width as usize + 150] = pit;
    let mut tiff = TiffEncoder::new(std::fs::File::create(path).unwrap()).unwrap();
    let mut image = tiff.new_image::<GrayI16>(raster.width, raster.height).unwrap();
    image.rows_per_strip(4).unwrap();
    image.encoder().write_tag(Tag::Unknown(42113), "-32767").unwrap();
    if let Some((west, north, step)) = degrees {
        image.encoder().write_tag(Tag::Unknown(33550), &[step, step, 0.0][..]).unwrap();
        image.encoder().write_tag(Tag::Unknown(33922), &[0.0, 0.0, 0.0, west, north, 0.0][..]).unwrap();
        let keys = [1u16, 1, 0, 2, 1024, 0, 1, 2, 2048, 0, 1, 4326];
        image.encoder().write_tag(Tag::Unknown(34735), &keys[..]).unwrap();
    }
    image.write_data(&data).unwrap();
}

/// A whole run over `source` (named `name` in `dir`), and the merge of three shards of
/// it given the exact range `exact`.
fn whole_and_merged(source: &dyn ElevationSource, exact: (f32, f32), dir: &Path, name: &str) -> (PathBuf, PathBuf) {
    let whole = dir.join(format!("{name}-whole.tspack"));
    tile_terrain(Some(source), None, "t", &whole, OPTIONS, &Silent::default()).unwrap();
    let known = KnownRange::new(source, exact);
    let parts: Vec<PathBuf> = (0..3)
        .map(|i| {
            let out = dir.join(format!("{name}-{i}.tspack"));
            let spec = ShardSpec { index: i, count: 3, split_lod: None, cuts: None };
            tile_shard(Some(&known), None, "t", &out, OPTIONS, Some(spec), &Silent::default()).unwrap();
            out
        })
        .collect();
    let merged = dir.join(format!("{name}-merged.tspack"));
    merge(&parts, &merged, &Silent::default()).unwrap();
    (whole, merged)
}

/// A GeoTIFF reprojected (a mosaic of one warped file) estimates its range as the file
/// does, and encodes a whole run by it, as its shards given the exact range do; a mosaic
/// of two files, or of one on its own grid, scans instead (None).
#[test]
fn a_reprojected_geotiff_runs_on_its_files_estimate() {
    use terrastream_tiler::{Crs, Mosaic, MosaicOptions, open_elevation};
    let dir = tempfile::tempdir().unwrap();
    let tif = dir.path().join("geo.tif");
    dem_file(&tif, 250, Some((7.4, 46.6, 0.001)));
    let file_estimate = open_elevation(&tif, None).unwrap().height_range_estimate().unwrap();
    assert!(file_estimate.is_some());
    let utm = MosaicOptions { crs: Some(Crs::parse("EPSG:32632").unwrap()), ..MosaicOptions::default() };
    let warped = Mosaic::open(std::slice::from_ref(&tif), &utm).unwrap();
    assert_eq!(warped.height_range_estimate().unwrap(), file_estimate);
    let degrees = MosaicOptions { crs: Some(Crs::parse("EPSG:4326").unwrap()), ..MosaicOptions::default() };
    let own_grid = Mosaic::open(std::slice::from_ref(&tif), &degrees).unwrap();
    assert_eq!(own_grid.height_range_estimate().unwrap(), None);
    let other = dir.path().join("other.tif");
    dem_file(&other, 260, Some((7.4, 46.6, 0.001)));
    let two = Mosaic::open(&[tif.clone(), other], &utm).unwrap();
    assert_eq!(two.height_range_estimate().unwrap(), None);

    let exact = warped.height_range(&mut |_| Ok(())).unwrap();
    let (whole, merged) = whole_and_merged(&warped, exact, dir.path(), "warped");
    assert_eq!(tiles(&merged), tiles(&whole));
    // The estimate's encoding: half its span and more to spare below the lowest height.
    let metadata = Reader::open_mmap(&whole).unwrap().metadata().clone();
    let (encoding, estimate) = (metadata.layers[0].elevation.unwrap(), file_estimate.unwrap());
    assert!(f64::from(exact.0) - encoding.height(1.0) > f64::from(estimate.1 - estimate.0) / 2.0, "{encoding:?}");
}

/// A whole run over a GeoTIFF encodes heights by the range estimated from some of its
/// strips (it does not scan the range first) and records the exact range; shards given
/// the exact range (the plan step's) choose the same encoding, so their merge is the
/// whole run byte for byte. With a height the estimate's encoding cannot hold, the whole
/// run scans the range and tiles again: still the shards' bytes, and exact heights.
#[test]
fn a_whole_run_on_an_estimated_range_encodes_as_shards_given_the_range() {
    use terrastream_tiler::open_elevation;
    let dir = tempfile::tempdir().unwrap();
    for (name, pit) in [("plain", 250i16), ("pit", -3000)] {
        let tif = dir.path().join(format!("{name}.tif"));
        dem_file(&tif, pit, None);
        let file = open_elevation(&tif, None).unwrap();
        let exact = file.height_range(&mut |_| Ok(())).unwrap();
        let estimate = file.height_range_estimate().unwrap().expect("a GeoTIFF estimates its range");
        assert!(estimate.0 > exact.0 && estimate.1 < exact.1, "{name}: the strips read miss both extremes");

        let (whole, merged) = whole_and_merged(&file, exact, dir.path(), name);
        assert_eq!(tiles(&merged), tiles(&whole), "{name}");

        let metadata = Reader::open_mmap(&whole).unwrap().metadata().clone();
        let t = &metadata.terrain;
        assert_eq!((t.min_elevation, t.max_elevation), (f64::from(exact.0), f64::from(exact.1)), "{name}");
        let encoding = metadata.layers[0].elevation.unwrap();
        assert_eq!(encoding, Reader::open_mmap(&merged).unwrap().metadata().layers[0].elevation.unwrap());
        assert_eq!(encoding.scale, 1.0 / 16.0, "{name}");
        let below = f64::from(exact.0) - encoding.height(1.0);
        if pit < 0 {
            // The pit's own encoding: its lowest height at the first code.
            assert!((0.0..=encoding.scale).contains(&below), "{name}: {encoding:?}");
        } else {
            // The estimate's: half its span and more to spare below.
            assert!(below > f64::from(estimate.1 - estimate.0) / 2.0, "{name}: {encoding:?}");
        }
    }
}
