//! Collections: a coarse base and a fine patch in one `tile` run, each as deep as its own
//! resolution allows (docs/tiling.md, "Collections").
//!
//! The base is the committed SRTM crop averaged to 10" (about 244 m) and raised 3 m, as a
//! second survey of other age would disagree; the patch is the crop's central 160 x 160
//! samples at 1" (about 24 m). Checked:
//! - levels finer than the base's hold tiles only over the patch (and the tiles its edges
//!   touch); the archive records where, and the inputs' spacings;
//! - inside the patch, beyond the blend band, heights are the patch's, sample for sample
//!   (a run with `--priority order`, which puts the patch over the base at LOD 0
//!   everywhere, is the oracle); outside it, the base's within its resampling;
//! - across the patch's edge the heights blend: the step between neighbouring samples of
//!   (collection - base) is a fraction of the one a run with `--blend 0` leaves;
//! - the elevation API answers the finest data at each point and says its spacing;
//!   quantized-mesh availability lists only the patch's rectangle at the patch's levels,
//!   and every tile it lists is served;
//! - a grazing render across the patch's edge matches its golden (looked at).
#![allow(clippy::unwrap_used, clippy::expect_used, clippy::cast_possible_truncation, clippy::cast_precision_loss)]
#![allow(missing_docs)]

use std::collections::BTreeMap;
use std::path::{Path, PathBuf};

use terrastream_format::{MmapSource, Reader};

#[path = "support/oracles.rs"]
mod oracles;
use oracles::{ok_in as ok, random_points, repo};

const BASE: &str = "tests/data/collection-base-10s-plus3m.tif";
const PATCH: &str = "tests/data/collection-patch-1s.tif";
/// The patch's west, south, east, north (pixels 80..240 of the 1" crop).
const PATCH_BOX: [f64; 4] = [-122.619_583, 37.900_139, -122.575_139, 37.944_583];

fn tile(dir: &Path, name: &str, inputs: &[&str], extra: &[&str]) -> PathBuf {
    let out = dir.join(name);
    let mut args = vec!["tile", "--elevation"];
    let paths: Vec<String> = inputs.iter().map(|i| repo().join(i).to_str().unwrap().to_owned()).collect();
    args.extend(paths.iter().map(String::as_str));
    if !extra.contains(&"--tile-size") {
        args.extend(["--tile-size", "32"]);
    }
    args.extend(["--vertical-datum", "5773", "-o", out.to_str().unwrap()]);
    args.extend(extra);
    ok(&args, dir);
    out
}

/// A collection wider than a region keeps the geographic grid, whose samples a plan
/// makes square by adding columns: the collection is made on that grid (it failed with a
/// tile outside the layer's grid when its levels were made on the inputs' own), and
/// inside the fine survey its heights are a one-resolution run's on the same grid.
#[test]
fn a_geographic_collection_wider_than_a_region_is_made_on_square_samples() {
    let dir = tempfile::tempdir().unwrap();
    let d = dir.path();
    // A 12 x 12 degree base at 0.1 degree and a quarter-degree survey at 15" in it.
    let base = oracles::grid_tif(d, "wide-base", [40.0, 20.0, 12.0, 10.0], &oracles::everest_height);
    let patch = oracles::grid_tif(d, "survey", [45.0, 25.0, 0.25, 240.0], &oracles::everest_height);
    // Absolute paths: `tile` joins them to the repository's unchanged.
    let both = [base.to_str().unwrap(), patch.to_str().unwrap()];
    // LOD 0 at the survey's spacing (the base is then made at 0.1 / 1.5 degrees, on LOD
    // 4): the same grid as the run in order's (`--lod0 auto` would put LOD 0 at 0.75 of
    // it, the base on LOD 5 at its own spacing: the next test).
    let run = |name: &str, extra: &[&str]| tile(d, name, &both, &[extra, &["--lod0", "finest"]].concat());
    let (col, order) = (run("wide.tspack", &[]), run("wide-order.tspack", &["--priority", "order"]));
    let info = ok(&["info", col.to_str().unwrap()], d);
    assert!(info.contains("longitude/latitude"), "kept geographic: {info}");
    assert!(info.contains("wide-base.tif") && info.contains("from LOD4"), "{info}");
    ok(&["verify", col.to_str().unwrap()], d);
    let (rc, ro) = (Reader::open_mmap(&col).unwrap(), Reader::open_mmap(&order).unwrap());
    let (lc, lo) = (&rc.metadata().layers[0], &ro.metadata().layers[0]);
    assert_eq!((lc.num_x_tiles, lc.num_y_tiles), (lo.num_x_tiles, lo.num_y_tiles), "one grid");
    assert!(lc.num_x_tiles * 4 < lc.num_y_tiles * 5, "squared: fewer columns than rows at 25°N");
    let per_lod = per_lod(&col);
    assert!(per_lod[&0] * 20 < (lc.num_x_tiles * lc.num_y_tiles) as usize, "LOD 0 is sparse: {per_lod:?}");
    // Inside the survey beyond the band: the one-resolution run's heights, within a step
    // of the encoding (both resample the survey's columns linearly onto the same grid).
    let step = lc.elevation.unwrap().scale;
    let deep = random_points([45.08, 25.08, 45.17, 25.17], 200);
    for ((a, b), p) in heights(&rc, &deep).iter().zip(heights(&ro, &deep)).zip(&deep) {
        assert!((a.0 - b.0).abs() <= 1.5 * step, "{p:?}: {} in the collection, {} at one resolution", a.0, b.0);
    }
    // A second survey added by `update` (which opens it onto the archive's grid): the run
    // with both, tile for tile.
    let second = oracles::grid_tif(d, "survey2", [48.0, 22.0, 0.25, 240.0], &oracles::everest_height);
    let all = tile(d, "wide-all.tspack", &[both[0], both[1], second.to_str().unwrap()], &["--lod0", "finest"]);
    let updated = d.join("wide-updated.tspack");
    ok(&["update", col.to_str().unwrap(), "--elevation", second.to_str().unwrap(), "-o", updated.to_str().unwrap()], d);
    assert!(tiles_of(&all) == tiles_of(&updated), "the update is not the run with both surveys");
    // Three shards of it, merged: the single run.
    let merged = three_shards_merged(d, "wide", &both, &["--lod0", "finest"]);
    assert!(tiles_of(&col) == tiles_of(&merged), "the shards merged are not the single run");
    // A picture given as a VRT that is no whole file read as it is (a nodata of its own)
    // makes the whole run one resolution: the heights are then the run in order's, not
    // opened again on the square grid a collection is made on.
    let Some(gdal) = colour_relief(d) else { return };
    gdal(&["gdaldem", "color-relief", "-q", both[0], "ramp.txt", "wide-rgb.tif"]);
    gdal(&["gdalbuildvrt", "-q", "-srcnodata", "0 0 0", "picture.vrt", "wide-rgb.tif"]);
    let picture = d.join("picture.vrt");
    let with_picture = |name: &str, extra: &[&str]| {
        let mut args = vec!["--texture", picture.to_str().unwrap(), "--texture-tile-size", "32"];
        args.extend(extra);
        run(name, &args)
    };
    let heights = |p: &Path| -> BTreeMap<terrastream_format::TileKey, Vec<u8>> {
        tiles_of(p).into_iter().filter(|(k, _)| k.layer() == 0).collect()
    };
    let (given, ordered) = (with_picture("pv.tspack", &[]), with_picture("pvo.tspack", &["--priority", "order"]));
    let (a, b) = (heights(&given), heights(&ordered));
    assert_eq!(a.len(), b.len(), "as many height tiles as the run in order");
    assert!(a == b, "the heights of the run in order, byte for byte");
}

/// A base whose spacing is not a power of two of the survey's: by default LOD 0 is made
/// finer than the survey by less than 2x, so that the base lies on a level at its own
/// spacing instead of being upsampled by up to 2x each way. Fewer tiles; the survey's
/// heights resampled finer, the same within its own interpolation; `update` and shards
/// find the same grid.
#[test]
fn a_wide_base_is_made_at_its_own_spacing() {
    let dir = tempfile::tempdir().unwrap();
    let d = dir.path();
    // Smooth ground: resampling the survey 4/3 finer moves its heights by millimetres.
    let ground = |lon: f64, lat: f64| 1500.0 + 400.0 * (lon * 3.0).sin() * (lat * 2.0).cos();
    // A 12 x 12 degree base at 0.1 degree, raised 5 m, and a quarter-degree survey at 15".
    let base = oracles::grid_tif(d, "wide-base", [40.0, 20.0, 12.0, 10.0], &|x, y| ground(x, y) + 5.0);
    let patch = oracles::grid_tif(d, "survey", [45.0, 25.0, 0.25, 240.0], &ground);
    let both = [base.to_str().unwrap(), patch.to_str().unwrap()];
    let auto = tile(d, "auto.tspack", &both, &[]);
    let finest = tile(d, "finest.tspack", &both, &["--lod0", "finest"]);
    let info = ok(&["info", auto.to_str().unwrap()], d);
    assert!(
        info.contains("wide-base.tif") && info.contains("from LOD5"),
        "the base on LOD 5 (0.1 / 32 = 11.25\"): {info}"
    );
    ok(&["verify", auto.to_str().unwrap()], d);
    let (ra, rf) = (Reader::open_mmap(&auto).unwrap(), Reader::open_mmap(&finest).unwrap());
    let (la, lf) = (&ra.metadata().layers[0], &rf.metadata().layers[0]);
    let (pa, pf) = (per_lod(&auto), per_lod(&finest));
    let whole = |l: &terrastream_format::Layer, lod: u8| {
        let (x, y) = l.grid_at(lod);
        (x * y) as usize
    };
    assert_eq!(pa[&5], whole(la, 5), "LOD 5 covers the grid: {pa:?}");
    assert_eq!(pf[&4], whole(lf, 4), "at the survey's spacing the base is LOD 4: {pf:?}");
    // The base made at 0.1 degree in latitude, not 0.0667: a 1.5x finer grid holds 2.25x
    // its samples (the columns are squared alike in both).
    let ratio = pf[&4] as f64 / pa[&5] as f64;
    assert!(ratio > 1.8, "{ratio:.2}x the base's tiles at the survey's spacing: {pf:?} against {pa:?}");
    let sum = |m: &BTreeMap<u8, usize>| m.values().sum::<usize>();
    assert!(sum(&pa) < sum(&pf), "{} tiles against {}", sum(&pa), sum(&pf));
    // Inside the survey, beyond the blend band: the survey's ground within centimetres.
    let step = la.elevation.unwrap().scale;
    let level0 = la.sample_spacing(0);
    let deep = random_points([45.08, 25.08, 45.17, 25.17], 200);
    for ((a, f), &(lon, lat)) in heights(&ra, &deep).iter().zip(heights(&rf, &deep)).zip(&deep) {
        let want = ground(lon, lat);
        assert!((a.0 - want).abs() <= 0.05 + step, "({lon}, {lat}): {} where the survey has {want}", a.0);
        assert!((a.0 - f.0).abs() <= 0.05 + 2.0 * step, "({lon}, {lat}): {} against {} at its spacing", a.0, f.0);
        // The spacing named is the survey's own, not LOD 0's finer one.
        assert!(a.1 > 1.15 * level0 && a.1 <= f.1, "({lon}, {lat}): {} m named, LOD 0 at {level0} m", a.1);
    }
    // Far from it: the base's (5 m above).
    let far = random_points([41.0, 21.0, 43.0, 23.0], 50);
    for (a, &(lon, lat)) in heights(&ra, &far).iter().zip(&far) {
        assert!((a.0 - ground(lon, lat) - 5.0).abs() < 15.0, "({lon}, {lat}): {}", a.0);
    }
    // `update` opens a second survey onto the archive's grid: the run with both.
    let second = oracles::grid_tif(d, "survey2", [48.0, 22.0, 0.25, 240.0], &ground);
    let all = tile(d, "auto-all.tspack", &[both[0], both[1], second.to_str().unwrap()], &[]);
    let updated = d.join("auto-updated.tspack");
    ok(
        &["update", auto.to_str().unwrap(), "--elevation", second.to_str().unwrap(), "-o", updated.to_str().unwrap()],
        d,
    );
    assert!(tiles_of(&all) == tiles_of(&updated), "the update is not the run with both surveys");
    // Shards each find the same grid: merged, the single run.
    let merged = three_shards_merged(d, "auto", &both, &[]);
    assert!(tiles_of(&auto) == tiles_of(&merged), "the shards merged are not the single run");
    // Pictures of the two (GDAL's colour relief): the imagery goes onto the square grid
    // the plan's texture layer has, as the heights do (its tiles fell outside that layer
    // when made on the pictures' own geographic grid), its base on a level of its own.
    // A grey ramp over the ground's heights (1 100 to 1 905 m): a picture's grey is a
    // linear function of its height, which resampling and means keep, so where the
    // archive's texels lie over its heights, one says the other.
    let Some(gdal) = colour_relief(d) else { return };
    std::fs::write(d.join("grey.txt"), "1000 0 0 0\n2000 250 250 250\n").unwrap();
    for (dem, rgb) in [(both[0], "wide-rgb.tif"), (both[1], "survey-rgb.tif")] {
        gdal(&["gdaldem", "color-relief", "-q", dem, "grey.txt", rgb]);
    }
    let (wide_rgb, survey_rgb) = (d.join("wide-rgb.tif"), d.join("survey-rgb.tif"));
    let (wide_rgb, survey_rgb) = (wide_rgb.to_str().unwrap(), survey_rgb.to_str().unwrap());
    let pictures = ["--texture", wide_rgb, survey_rgb, "--texture-tile-size", "32"];
    let pictured = tile(d, "pictured.tspack", &both, &pictures);
    ok(&["verify", pictured.to_str().unwrap()], d);
    let info = ok(&["info", pictured.to_str().unwrap()], d);
    assert!(info.contains("wide-rgb.tif") && info.contains("from LOD5 (texture)"), "{info}");
    let reader = Reader::open_mmap(&pictured).unwrap();
    let texture = reader.metadata().layers.iter().find(|l| l.kind == terrastream_format::LayerKind::Texture).unwrap();
    let elevation = &reader.metadata().layers[0];
    let (tw, ew) = (texture.world_extent(), elevation.world_extent());
    assert!(((tw.0 / tw.1) / (ew.0 / ew.1) - 1.0).abs() < 0.02, "the pictures cover the heights' area: {tw:?} {ew:?}");
    assert!((texture.tile_world_size / elevation.tile_world_size - 1.0).abs() < 1e-3, "one texel a sample");
    // Every texel of the base's level and the next, against the height beneath it.
    let index = reader.metadata().layers.iter().position(|l| l.kind == terrastream_format::LayerKind::Texture).unwrap();
    let mut decoded: BTreeMap<(u8, u8, u32, u32), terrastream_tiles::TileData> = BTreeMap::new();
    reader
        .for_each_tile(|key, stored| -> Result<(), terrastream_format::Error> {
            let layer = usize::from(key.layer());
            if (layer == 0 || layer == index) && (5..=6).contains(&key.lod()) {
                let meta = &reader.metadata().layers[layer];
                let tile = terrastream_tiles::decode(meta, key, stored, true).unwrap();
                decoded.insert((key.layer(), key.lod(), key.x(), key.y()), tile.data);
            }
            Ok(())
        })
        .unwrap();
    let (mut compared, mut worst, mut sum) = (0usize, 0f64, 0f64);
    for ((layer, lod, x, y), data) in &decoded {
        let terrastream_tiles::TileData::Rgba8(texels) = data else { continue };
        assert_eq!(usize::from(*layer), index);
        let Some(terrastream_tiles::TileData::Heights { heights, .. }) = decoded.get(&(0, *lod, *x, *y)) else {
            panic!("no height tile under texture tile {lod}/{x}/{y}")
        };
        assert_eq!(heights.len() * 4, texels.len(), "{lod}/{x}/{y}: one texel a sample");
        for (h, t) in heights.iter().zip(texels.chunks_exact(4)) {
            if h.is_nan() || t[3] < 255 {
                continue;
            }
            let grey = f64::from((h - 1000.0) * 0.25);
            let off = (f64::from(t[0]) - grey).abs();
            (compared, worst, sum) = (compared + 1, worst.max(off), sum + off);
        }
    }
    let mean = sum / compared as f64;
    eprintln!("texels against heights: {compared} compared, mean {mean:.2}, worst {worst:.1} grey levels");
    assert!(compared > 10_000, "{compared} texels compared");
    assert!(
        mean < 2.0 && worst < 16.0,
        "the pictures lie elsewhere than the heights: mean {mean:.2}, worst {worst:.1}"
    );
}

/// A level's rows are made in bands, a worker a core, from four cores, and in one run
/// below: the same archive either way.
#[test]
fn a_collection_tiled_on_one_core_and_on_eight_is_the_same_archive() {
    let dir = tempfile::tempdir().unwrap();
    let run = |threads: &str| {
        let out = dir.path().join(format!("on-{threads}.tspack"));
        let (base, patch) = (repo().join(BASE), repo().join(PATCH));
        let args = [base.to_str().unwrap(), patch.to_str().unwrap(), "--tile-size", "32", "-o", out.to_str().unwrap()];
        let made = std::process::Command::new(env!("CARGO_BIN_EXE_terrastream"))
            .args(["-v", "tile", "--vertical-datum", "5773", "--elevation"])
            .args(args)
            .env("RAYON_NUM_THREADS", threads)
            .output()
            .unwrap();
        let said = String::from_utf8_lossy(&made.stderr).into_owned();
        assert!(made.status.success(), "{said}");
        (std::fs::read(&out).unwrap(), said)
    };
    let ((one, said_one), (eight, said_eight)) = (run("1"), run("8"));
    assert!(said_eight.contains("a level's rows made in bands bands=3 threads=8"), "{said_eight}");
    assert!(!said_one.contains("made in bands"), "{said_one}");
    assert!(one == eight, "{} and {} bytes: not the same archive", one.len(), eight.len());
}

/// Three shards of a `tile` run over the heights `inputs` (`extra` its other arguments),
/// merged with the run's inputs (the merge of a collection split finer than its base
/// reads them).
fn three_shards_merged(d: &Path, name: &str, inputs: &[&str], extra: &[&str]) -> PathBuf {
    let shards: Vec<PathBuf> = (0..3)
        .map(|i| tile(d, &format!("{name}-{i}.tspack"), inputs, &[extra, &["--shard", &format!("{i}/3")]].concat()))
        .collect();
    let merged = d.join(format!("{name}-merged.tspack"));
    let mut args: Vec<&str> = vec!["merge"];
    args.extend(shards.iter().map(|p| p.to_str().unwrap()));
    args.extend(["-o", merged.to_str().unwrap(), "--elevation"]);
    args.extend(inputs);
    ok(&args, d);
    merged
}

/// Elevation tiles per LOD.
fn per_lod(path: &Path) -> BTreeMap<u8, usize> {
    let mut counts = BTreeMap::new();
    for key in tiles_of(path).keys().filter(|k| k.layer() == 0) {
        *counts.entry(key.lod()).or_default() += 1;
    }
    counts
}

/// Heights (and the spacing they came from) at (lon, lat) points, as the elevation API
/// reads them.
fn heights(reader: &Reader<MmapSource>, points: &[(f64, f64)]) -> Vec<(f64, f64)> {
    let latlng: Vec<(f64, f64)> = points.iter().map(|&(lon, lat)| (lat, lon)).collect();
    let h = terrastream_views::elevation::Heights::new(reader).unwrap();
    h.found(&latlng, terrastream_tiles::Interpolation::Bilinear).unwrap().into_iter().map(Option::unwrap).collect()
}

fn inside(b: [f64; 4], margin: (f64, f64)) -> [f64; 4] {
    [b[0] + margin.0, b[1] + margin.1, b[2] - margin.0, b[3] - margin.1]
}

#[test]
fn a_base_and_a_patch_each_reach_their_own_depth_and_meet_without_a_step() {
    let dir = tempfile::tempdir().unwrap();
    let d = dir.path();
    let col = tile(d, "col.tspack", &[BASE, PATCH], &[]);
    let flat = tile(d, "noblend.tspack", &[BASE, PATCH], &["--blend", "0"]);
    let order = tile(d, "order.tspack", &[BASE, PATCH], &["--priority", "order"]);
    let base = tile(d, "base.tspack", &[BASE], &[]);
    let patch = tile(d, "patch.tspack", &[PATCH], &[]);

    // Depth: LOD 0-2 only over the patch, LOD 3 up (the base's) everywhere.
    let (c, o, p) = (per_lod(&col), per_lod(&order), per_lod(&patch));
    eprintln!(
        "tiles per LOD: collection {c:?}, one resolution {o:?}, patch alone {p:?}, base alone {:?}",
        per_lod(&base)
    );
    let grid = Reader::open_mmap(&col).unwrap().metadata().layers[0].clone();
    for lod in 0..3u8 {
        let (nx, ny) = grid.grid_at(lod);
        // The patch's tiles at this level (its own grid), one more each way for its edges.
        let alone = p.get(&lod).copied().unwrap_or(1);
        let side = (alone as f64).sqrt().ceil() as usize + 2;
        assert!(c[&lod] <= side * side, "LOD {lod}: {} tiles, the patch covers about {alone}", c[&lod]);
        assert!(c[&lod] < o[&lod], "LOD {lod}: {} tiles, as many as over the whole grid", c[&lod]);
        if lod == 0 {
            assert!(c[&lod] * 3 < (nx * ny) as usize, "LOD 0: {} of {} tiles: not sparse", c[&lod], nx * ny);
        }
    }
    for lod in 3..grid.num_lods {
        assert_eq!(c[&lod], o[&lod], "LOD {lod} covers the whole grid");
    }
    let bytes = |p: &Path| std::fs::metadata(p).unwrap().len();
    let ratio = bytes(&col) as f64 / (bytes(&base) + bytes(&patch)) as f64;
    eprintln!(
        "bytes: collection {}, base + patch alone {} ({ratio:.2}x), one resolution {}",
        bytes(&col),
        bytes(&base) + bytes(&patch),
        bytes(&order)
    );
    // 32-sample tiles over a 160-sample patch: the edge tiles are a third of its tiles.
    assert!(ratio <= 1.3, "the collection is {ratio:.2}x its parts");
    let info = ok(&["info", col.to_str().unwrap()], d);
    assert!(info.contains("collection-patch-1s.tif · 24.43 m between samples · from LOD0"), "{info}");
    assert!(info.contains("only where fine inputs lie: LOD0 in 1 rectangle"), "{info}");

    let (rc, rf, ro) =
        (Reader::open_mmap(&col).unwrap(), Reader::open_mmap(&flat).unwrap(), Reader::open_mmap(&order).unwrap());
    // Inside the patch beyond the band (17 samples of 1" and a margin): the patch's heights.
    let deep = random_points(inside(PATCH_BOX, (0.008, 0.006)), 300);
    let (hc, ho) = (heights(&rc, &deep), heights(&ro, &deep));
    for ((a, b), p) in hc.iter().zip(&ho).zip(&deep) {
        assert!((a.0 - b.0).abs() < 1e-6, "{p:?}: {} in the collection, {} from the patch", a.0, b.0);
        assert!((a.1 - 24.43).abs() < 0.01, "{p:?}: from a spacing of {} m", a.1);
    }
    // Outside it: the base's (from LOD 3, 195 m), as the one-resolution run resamples it.
    let around: Vec<(f64, f64)> = random_points([-122.64, 37.88, -122.555, 37.965], 600)
        .into_iter()
        .filter(|&(lon, lat)| {
            let o = inside(PATCH_BOX, (-0.004, -0.004));
            !(lon > o[0] && lon < o[2] && lat > o[1] && lat < o[3])
        })
        .take(200)
        .collect();
    let (hc, ho) = (heights(&rc, &around), heights(&ro, &around));
    let mut off: Vec<f64> = hc.iter().zip(&ho).map(|(a, b)| (a.0 - b.0).abs()).collect();
    off.sort_by(f64::total_cmp);
    // The base as the collection holds it (sampled at its own level, 195 m, then brought
    // to the finer levels' samples bilinearly, then read bilinearly) against one
    // resampling to 24 m: they part most on ridges.
    eprintln!(
        "outside the patch: |collection - base at LOD 0| median {:.2} m, p95 {:.2} m, max {:.2} m",
        off[100], off[190], off[199]
    );
    assert!(off[100] < 3.0 && off[190] < 12.0 && off[199] < 20.0, "outside the patch: {off:?}");
    assert!(hc.iter().all(|h| h.1 > 190.0), "outside the patch the base's spacing answers");

    // Across the west and south edges: the jump between the samples either side of the
    // edge beyond what the ground's slope makes there (the mean of the jumps beside it),
    // with and without the blend.
    let step = |r: &Reader<MmapSource>, inward: f64| {
        let arc = 1.0 / 3600.0;
        let edge = (PATCH_BOX[0] + inward, PATCH_BOX[1] + inward);
        let mut excess = Vec::new();
        for k in 0..24 {
            let t = (f64::from(k) + 0.5) / 24.0;
            let lat = PATCH_BOX[1] + 0.004 + t * (PATCH_BOX[3] - PATCH_BOX[1] - 0.008);
            let lon = PATCH_BOX[0] + 0.004 + t * (PATCH_BOX[2] - PATCH_BOX[0] - 0.008);
            let west: Vec<(f64, f64)> = (-3..3).map(|i| (edge.0 + (f64::from(i) + 0.5) * arc, lat)).collect();
            let south: Vec<(f64, f64)> = (-3..3).map(|i| (lon, edge.1 + (f64::from(i) + 0.5) * arc)).collect();
            for line in [west, south] {
                let h: Vec<f64> = heights(r, &line).iter().map(|h| h.0).collect();
                let j: Vec<f64> = h.windows(2).map(|w| w[1] - w[0]).collect();
                excess.push((j[2] - (j[1] + j[3]) / 2.0).abs());
            }
        }
        excess.iter().sum::<f64>() / excess.len() as f64
    };
    // The same measure 40 samples inside the patch: what the ground's curvature alone gives.
    let (blended, stepped, ground) = (step(&rc, 0.0), step(&rf, 0.0), step(&rc, 40.0 / 3600.0));
    eprintln!(
        "mean jump at the patch's edge beyond the slope: blended {blended:.2} m, --blend 0 {stepped:.2} m \
         (the ground inside the patch: {ground:.2} m)"
    );
    assert!(stepped > ground + 1.0, "without the blend the surveys' disagreement shows as a step ({stepped:.2} m)");
    assert!(blended < ground * 1.25, "the blend leaves a step of {blended:.2} m (ground: {ground:.2} m)");
}

#[test]
fn readers_follow_sparse_depth() {
    let dir = tempfile::tempdir().unwrap();
    let d = dir.path();
    let col = tile(d, "col.tspack", &[BASE, PATCH], &[]);
    let order = tile(d, "order.tspack", &[BASE, PATCH], &["--priority", "order"]);
    let exe = Path::new(env!("CARGO_BIN_EXE_terrastream"));
    let server = terrastream_testkit::server::spawn_serve(exe, &[col.to_str().unwrap(), order.to_str().unwrap()], d);
    let get = |path: &str| terrastream_testkit::http::request(server.port, "GET", path, None);
    let json = |path: &str| {
        let (status, body) = get(path);
        assert_eq!(status, 200, "{path}: {}", String::from_utf8_lossy(&body));
        serde_json::from_slice::<serde_json::Value>(&body).unwrap()
    };

    // Quantized mesh: the deepest levels list the patch's rectangle, not the base's box.
    let layer = json("/col/layer.json");
    let bounds: Vec<f64> = serde_json::from_value(layer["bounds"].clone()).unwrap();
    let max = layer["maxzoom"].as_u64().unwrap() as usize;
    let available = layer["available"].as_array().unwrap();
    let count = |ranges: &serde_json::Value| -> u64 {
        (ranges.as_array().unwrap().iter())
            .map(|r| {
                (r["endX"].as_u64().unwrap() - r["startX"].as_u64().unwrap() + 1)
                    * (r["endY"].as_u64().unwrap() - r["startY"].as_u64().unwrap() + 1)
            })
            .sum()
    };
    let deepest = &available[max];
    let ([x0, x1], [y0, y1]) = (
        [
            ((bounds[0] + 180.0) / 180.0 * f64::from(1u32 << max)).floor() as u64,
            ((bounds[2] + 180.0) / 180.0 * f64::from(1u32 << max)).floor() as u64,
        ],
        [
            ((bounds[1] + 90.0) / 180.0 * f64::from(1u32 << max)).floor() as u64,
            ((bounds[3] + 90.0) / 180.0 * f64::from(1u32 << max)).floor() as u64,
        ],
    );
    let whole = (x1 - x0 + 1) * (y1 - y0 + 1);
    eprintln!("layer.json level {max}: {} tiles listed, {whole} over the data's box", count(deepest));
    assert!(count(deepest) * 2 < whole, "level {max} lists {deepest} of the box's {whole} tiles");
    // Every listed tile of the deepest level is served; one outside the list is not.
    let r = &deepest[0];
    let (sx, sy) = (r["startX"].as_u64().unwrap(), r["startY"].as_u64().unwrap());
    let (status, _) = get(&format!("/col/{max}/{sx}/{sy}.terrain"));
    assert_eq!(status, 200, "a listed tile");
    let outside = (x0..=x1)
        .flat_map(|x| (y0..=y1).map(move |y| (x, y)))
        .find(|&(x, y)| {
            !deepest.as_array().unwrap().iter().any(|r| {
                (r["startX"].as_u64().unwrap()..=r["endX"].as_u64().unwrap()).contains(&x)
                    && (r["startY"].as_u64().unwrap()..=r["endY"].as_u64().unwrap()).contains(&y)
            })
        })
        .unwrap();
    let (status, _) = get(&format!("/col/{max}/{}/{}.terrain", outside.0, outside.1));
    assert_eq!(status, 404, "tile {outside:?} of level {max} is not listed");

    // The elevation API: the finest data at each point, and its spacing.
    let answer = json(&format!(
        "/v1/col?locations={},{}|{},{}",
        (PATCH_BOX[1] + PATCH_BOX[3]) / 2.0,
        (PATCH_BOX[0] + PATCH_BOX[2]) / 2.0,
        37.96,
        -122.635
    ));
    let resolution = |i: usize| answer["results"][i]["resolution"].as_f64().unwrap();
    assert!((resolution(0) - 24.43).abs() < 0.01, "{answer}");
    assert!(resolution(1) > 190.0, "{answer}");

    // Web tiles: the deepest level with data under each pixel: a zoom that samples LOD 0
    // over the patch is served over the base as well (from LOD 3 there), with no hole.
    let tiles = json("/col/tiles.json");
    let z = tiles["maxzoom"].as_u64().unwrap() as u32;
    let n = f64::from(1u32 << z);
    let tx = ((-122.632 + 180.0) / 360.0 * n).floor() as u32;
    let lat = 37.955f64.to_radians();
    let ty = ((1.0 - (lat.tan() + 1.0 / lat.cos()).ln() / std::f64::consts::PI) / 2.0 * n).floor() as u32;
    let opaque = |name: &str| {
        let (status, body) = get(&format!("/{name}/xyz/elevation/{z}/{tx}/{ty}.png"));
        assert_eq!(status, 200, "web tile {z}/{tx}/{ty} of {name} over the base only");
        let (_, _, rgba) = terrastream_testkit::golden::decode_png(&body);
        rgba.chunks_exact(4).filter(|p| p[3] == 255).count()
    };
    let (ours, theirs) = (opaque("col"), opaque("order"));
    eprintln!("web tile {z}/{tx}/{ty} over the base: {ours} pixels with heights, {theirs} in one resolution");
    assert!(ours > 0 && ours * 100 >= theirs * 99, "{ours} pixels with heights, {theirs} in one resolution");
}

#[test]
fn a_grazing_view_across_the_patch_edge_matches_its_golden() {
    let dir = tempfile::tempdir().unwrap();
    let d = dir.path();
    let col = tile(d, "col.tspack", &[BASE, PATCH], &[]);
    let png = d.join("edge.png");
    ok(
        &[
            "render",
            col.to_str().unwrap(),
            "-o",
            png.to_str().unwrap(),
            "--at=-122.628,37.912,800",
            "--heading",
            "80",
            "--pitch",
            "-12",
            "--size",
            "480x300",
            "--no-atmosphere",
            "--no-earth",
        ],
        d,
    );
    let (w, h, rgba) = terrastream_testkit::golden::decode_png(&std::fs::read(&png).unwrap());
    // Terrain fills the lower half: a view with tiles but no ground is a failure.
    let sky = rgba[((h - 2) * w * 4) as usize..((h - 1) * w * 4) as usize]
        .chunks_exact(4)
        .filter(|p| p[2] > p[0] + 40)
        .count();
    assert!(sky < (w / 10) as usize, "the bottom row is sky: no ground drawn");
    let tolerance = terrastream_testkit::golden::Tolerance { mean: 2.0, pixel: 24, off_share: 0.02 };
    terrastream_testkit::golden::assert_golden("collection-edge", w, h, &rgba, tolerance);
}

/// Every tile of an archive, by key.
fn tiles_of(path: &Path) -> BTreeMap<terrastream_format::TileKey, Vec<u8>> {
    let reader = Reader::open_mmap(path).unwrap();
    let mut tiles = BTreeMap::new();
    reader
        .for_each_tile(|key, bytes| -> Result<(), terrastream_format::Error> {
            tiles.insert(key, bytes.to_vec());
            Ok(())
        })
        .unwrap();
    tiles
}

/// A 6" base raised 3 m, and two 1" surveys far apart (the crop's pixels 60..120 and
/// 250..310 each way).
const BASE6: &str = "tests/data/collection-base-6s-plus3m.tif";
const SURVEY_A: &str = "tests/data/collection-survey-a-1s.tif";
const SURVEY_B: &str = "tests/data/collection-survey-b-1s.tif";

/// A survey added to a collection by `update` (in place and into a copy) makes the
/// archive one run with every input makes, tile for tile, byte for byte; the tiles it does
/// not reach stay as they were.
#[test]
fn a_survey_added_by_update_equals_a_run_with_every_input() {
    let dir = tempfile::tempdir().unwrap();
    let d = dir.path();
    let extra = ["--tile-size", "16"];
    let all = tile(d, "all.tspack", &[BASE6, SURVEY_A, SURVEY_B], &extra);
    let before = tile(d, "a.tspack", &[BASE6, SURVEY_A], &extra);
    let old = tiles_of(&before);
    let b = repo().join(SURVEY_B);
    let copy = d.join("copy.tspack");
    ok(&["update", before.to_str().unwrap(), "--elevation", b.to_str().unwrap(), "-o", copy.to_str().unwrap()], d);
    assert_eq!(tiles_of(&before), old, "-o leaves the archive as it was");
    let in_place = d.join("in-place.tspack");
    std::fs::copy(&before, &in_place).unwrap();
    ok(&["update", in_place.to_str().unwrap(), "--elevation", b.to_str().unwrap(), "--in-place"], d);
    let whole = tiles_of(&all);
    for updated in [&copy, &in_place] {
        let ours = tiles_of(updated);
        assert_eq!(ours.len(), whole.len(), "{}: tiles", updated.display());
        let differ: Vec<_> = whole.iter().filter(|(k, v)| ours.get(k) != Some(v)).map(|(k, _)| *k).collect();
        assert!(
            differ.is_empty(),
            "{}: {} tiles differ from a run with every input: {differ:?}",
            updated.display(),
            differ.len()
        );
    }
    // Untouched: every tile of the archive but those under and above the survey.
    let ours = tiles_of(&in_place);
    let kept = old.iter().filter(|(k, v)| ours.get(k) == Some(v)).count();
    let changed = old.len() - kept;
    eprintln!(
        "update: {} tiles added, {changed} of {} made again, {kept} untouched",
        ours.len() - old.len(),
        old.len()
    );
    assert!(changed > 0 && changed * 3 < old.len(), "{changed} of {} tiles changed", old.len());
    let info = ok(&["info", in_place.to_str().unwrap()], d);
    assert!(info.contains("collection-survey-b-1s.tif") && info.contains("LOD0 in 2 rectangles"), "{info}");
    // Its layers' bytes (what `info` says) are every distinct tile's, as `verify` reads
    // them, though the new ones lie after the old.
    let reader = Reader::open_mmap(&in_place).unwrap();
    let stats = terrastream_format::ArchiveStats::collect(&reader).unwrap();
    let checked = terrastream_format::verify(&reader, |_| {}).unwrap();
    assert_eq!(stats.layers.iter().map(|l| l.data_bytes).sum::<u64>(), checked.bytes_checked);
    drop(reader);
    // The compact copy `verify` suggests after updates in place: the same tiles.
    let said = ok(&["verify", in_place.to_str().unwrap()], d);
    assert!(said.contains("OK") && said.contains("merge"), "{said}");
    let compact = d.join("compact.tspack");
    ok(&["merge", in_place.to_str().unwrap(), "-o", compact.to_str().unwrap()], d);
    assert_eq!(tiles_of(&compact), whole);
    assert!(std::fs::metadata(&compact).unwrap().len() < std::fs::metadata(&in_place).unwrap().len());
    // Heights where the survey lies: those of the run with every input.
    let points = random_points([-122.565, 37.888, -122.552, 37.898], 50);
    let (r, w) = (Reader::open_mmap(&in_place).unwrap(), Reader::open_mmap(&all).unwrap());
    assert_eq!(heights(&r, &points), heights(&w, &points));
}

/// Two collections of one grid (a fixed CRS and spacing), each a survey over the same
/// base, merged: the run with every input, tile for tile, byte for byte (the surveys lie
/// apart), and the inputs of both recorded.
#[test]
fn two_collections_of_one_grid_merge_into_the_run_with_every_input() {
    let dir = tempfile::tempdir().unwrap();
    let d = dir.path();
    let extra = ["--tile-size", "16", "--crs", "EPSG:32610", "--resolution", "25", "--height-range", "0,1000"];
    let all = tile(d, "all.tspack", &[BASE6, SURVEY_A, SURVEY_B], &extra);
    let a = tile(d, "a.tspack", &[BASE6, SURVEY_A], &extra);
    let b = tile(d, "b.tspack", &[BASE6, SURVEY_B], &extra);
    let merged = d.join("ab.tspack");
    ok(&["merge", a.to_str().unwrap(), b.to_str().unwrap(), "-o", merged.to_str().unwrap()], d);
    let (ours, whole) = (tiles_of(&merged), tiles_of(&all));
    let missing: Vec<_> = whole.keys().filter(|k| !ours.contains_key(k)).collect();
    let extra_tiles: Vec<_> = ours.keys().filter(|k| !whole.contains_key(k)).collect();
    let differ: Vec<_> = whole.iter().filter(|(k, v)| ours.get(k).is_some_and(|o| o != *v)).map(|(k, _)| *k).collect();
    assert!(
        missing.is_empty() && extra_tiles.is_empty() && differ.is_empty(),
        "missing {missing:?}, extra {extra_tiles:?}, differ {differ:?}"
    );
    let info = ok(&["info", merged.to_str().unwrap()], d);
    assert!(info.contains("survey-a") && info.contains("survey-b"), "{info}");
    // Inputs given to a merge that reads none: said, and the same archive.
    let again = d.join("again.tspack");
    let base = repo().join(BASE6);
    let args = ["merge", a.to_str().unwrap(), b.to_str().unwrap(), "-o", again.to_str().unwrap(), "--elevation"];
    let out = oracles::run_in(&[&args[..], &[base.to_str().unwrap()]].concat(), d);
    let said = String::from_utf8_lossy(&out.stderr);
    assert!(out.status.success() && said.contains("inputs given are not read"), "{said}");
    assert!(tiles_of(&again) == ours);
}

#[test]
fn update_refuses_what_it_cannot_add() {
    let dir = tempfile::tempdir().unwrap();
    let d = dir.path();
    let col = tile(d, "col.tspack", &[BASE6, SURVEY_A], &["--tile-size", "16"]);
    let before = std::fs::read(&col).unwrap();
    let (a, base) = (repo().join(SURVEY_A), repo().join(BASE6));
    for (args, says) in [
        // Over tiles its finer levels hold already.
        (vec!["update", col.to_str().unwrap(), "--elevation", a.to_str().unwrap(), "--in-place"], "holds already"),
        // No finer than its base.
        (vec!["update", col.to_str().unwrap(), "--elevation", base.to_str().unwrap(), "--in-place"], "no finer than"),
    ] {
        let out = oracles::run_in(&args, d);
        let said = String::from_utf8_lossy(&out.stderr);
        assert!(!out.status.success(), "{args:?} succeeded");
        assert!(said.contains(says), "{args:?}: {said}");
    }
    assert_eq!(std::fs::read(&col).unwrap(), before, "the archive is as it was");
}

/// GDAL's colour relief of the committed crop, `rgb.tif` in `d`, and a runner of GDAL's
/// tools there; None without gdal-bin (which CI has).
fn colour_relief(d: &Path) -> Option<impl Fn(&[&str]) + '_> {
    if std::process::Command::new("gdaldem").arg("--version").output().is_err() {
        assert!(std::env::var_os("CI").is_none(), "gdal-bin is required on CI");
        return None;
    }
    let gdal = move |args: &[&str]| {
        let out = std::process::Command::new(args[0]).args(&args[1..]).current_dir(d).output().unwrap();
        assert!(out.status.success(), "{args:?}: {}", String::from_utf8_lossy(&out.stderr));
    };
    let dem = repo().join(oracles::DEM);
    std::fs::write(d.join("ramp.txt"), "0 20 60 20\n300 140 160 60\n600 200 200 200\n800 255 255 255\n").unwrap();
    gdal(&["gdaldem", "color-relief", "-q", dem.to_str().unwrap(), "ramp.txt", "rgb.tif"]);
    Some(gdal)
}

/// Imagery follows the same rules: a 10" picture and a 1" one of its middle (GDAL's colour
/// relief of the committed crop, made here) over the crop's heights. The texture's finer
/// levels hold tiles only over the fine picture; inside it, beyond the blend band, its
/// tiles are those a one-resolution run makes, byte for byte.
#[test]
fn imagery_of_different_resolutions_reaches_its_own_depth() {
    let dir = tempfile::tempdir().unwrap();
    let d = dir.path();
    let dem = repo().join(oracles::DEM);
    let Some(gdal) = colour_relief(d) else { return };
    gdal(&["gdal_translate", "-q", "-srcwin", "80", "80", "160", "160", "rgb.tif", "fine.tif"]);
    let ten = format!("{}", 10.0 / 3600.0);
    gdal(&["gdalwarp", "-q", "-tr", &ten, &ten, "-r", "average", "rgb.tif", "coarse.tif"]);
    let (coarse, fine) = (d.join("coarse.tif"), d.join("fine.tif"));
    let run = |name: &str, extra: &[&str]| {
        let out = d.join(name);
        let (c, f) = (coarse.to_str().unwrap(), fine.to_str().unwrap());
        let mut args = vec!["tile", "--elevation", dem.to_str().unwrap(), "--texture", c, f];
        args.extend(["--tile-size", "32", "--texture-tile-size", "32", "-o", out.to_str().unwrap()]);
        args.extend(extra);
        ok(&args, d);
        out
    };
    let (col, one) = (run("col.tspack", &[]), run("one.tspack", &["--priority", "order"]));
    let texture = |p: &Path| -> BTreeMap<terrastream_format::TileKey, Vec<u8>> {
        tiles_of(p).into_iter().filter(|(k, _)| k.layer() == 1).collect()
    };
    let (ours, theirs) = (texture(&col), texture(&one));
    let lod0: Vec<_> = ours.keys().filter(|k| k.lod() == 0).copied().collect();
    let all0 = theirs.keys().filter(|k| k.lod() == 0).count();
    eprintln!(
        "imagery: LOD 0 holds {} tiles, {all0} at one resolution; {} against {} in all",
        lod0.len(),
        ours.len(),
        theirs.len()
    );
    assert!(lod0.len() * 2 < all0, "LOD 0: {} of {all0} tiles", lod0.len());
    let info = ok(&["info", col.to_str().unwrap()], d);
    let texture_layer = info.split("layer 1").nth(1).unwrap_or_default().split("layer 2").next().unwrap_or_default();
    assert!(texture_layer.contains("only where fine inputs lie: LOD0"), "{info}");
    assert!(info.contains("fine.tif") && info.contains("from LOD0 (texture)"), "{info}");
    // Two tiles in from the fine picture's tiles: beyond the blend band.
    let (x0, x1) = (lod0.iter().map(|k| k.x()).min().unwrap(), lod0.iter().map(|k| k.x()).max().unwrap());
    let (y0, y1) = (lod0.iter().map(|k| k.y()).min().unwrap(), lod0.iter().map(|k| k.y()).max().unwrap());
    let inner: Vec<_> =
        lod0.iter().filter(|k| k.x() >= x0 + 2 && k.x() + 2 <= x1 && k.y() >= y0 + 2 && k.y() + 2 <= y1).collect();
    assert!(inner.len() >= 4, "{inner:?}");
    for k in inner {
        assert_eq!(ours[k], theirs[k], "tile {k} inside the fine picture");
    }
    // In four shards split at LOD 0, finer than the pictures' base: merged with the
    // pictures given, the single run's tiles, every layer (the heights of one resolution
    // made above the split from their tiles, the imagery's levels from the pictures).
    let whole = run("png.tspack", &["--texture-format", "png"]);
    let mut shards = vec![];
    for i in 0..4 {
        let spec = format!("{i}/4");
        shards.push(run(&format!("s{i}.tspack"), &["--texture-format", "png", "--shard", &spec, "--split-lod", "0"]));
    }
    let merged = d.join("merged.tspack");
    let mut args = vec!["merge"];
    args.extend(shards.iter().map(|s| s.to_str().unwrap()));
    args.extend(["-o", merged.to_str().unwrap(), "--texture", coarse.to_str().unwrap(), fine.to_str().unwrap()]);
    ok(&args, d);
    assert!(tiles_of(&merged) == tiles_of(&whole), "the merged shards' tiles are the single run's");
}

/// Imagery added to a collection of images by `update` (GDAL's colour relief of the crop:
/// a 6" picture with a 1" one of its north-west, then a 1" one of its south-east added)
/// makes the archive a run with all three makes, tile for tile, byte for byte, in place
/// and into a copy; the heights are untouched. A picture no finer than the base is
/// refused, naming it.
#[test]
fn imagery_added_by_update_equals_a_run_with_every_picture() {
    let dir = tempfile::tempdir().unwrap();
    let d = dir.path();
    let dem = repo().join(oracles::DEM);
    let Some(gdal) = colour_relief(d) else { return };
    // Far enough apart that no level's ring of tiles joins them (docs/tiling.md).
    gdal(&["gdal_translate", "-q", "-srcwin", "20", "20", "70", "70", "rgb.tif", "a.tif"]);
    gdal(&["gdal_translate", "-q", "-srcwin", "230", "230", "70", "70", "rgb.tif", "b.tif"]);
    let six = format!("{}", 6.0 / 3600.0);
    gdal(&["gdalwarp", "-q", "-tr", &six, &six, "-r", "average", "rgb.tif", "coarse.tif"]);
    let path = |name: &str| d.join(name).to_str().unwrap().to_owned();
    let run = |name: &str, pictures: &[&str]| {
        let mut args = vec!["tile".to_owned(), "--elevation".into(), dem.to_str().unwrap().into(), "--texture".into()];
        args.extend(pictures.iter().map(|p| path(p)));
        args.extend(["--tile-size", "32", "--texture-tile-size", "16", "-o"].map(str::to_owned));
        args.push(path(name));
        ok(&args.iter().map(String::as_str).collect::<Vec<_>>(), d);
        d.join(name)
    };
    let all = run("all.tspack", &["coarse.tif", "a.tif", "b.tif"]);
    let before = run("a.tspack", &["coarse.tif", "a.tif"]);
    let old = tiles_of(&before);
    let copy = path("copy.tspack");
    ok(&["update", before.to_str().unwrap(), "--texture", &path("b.tif"), "-o", &copy], d);
    assert_eq!(tiles_of(&before), old, "-o leaves the archive as it was");
    let in_place = d.join("in-place.tspack");
    std::fs::copy(&before, &in_place).unwrap();
    ok(&["update", in_place.to_str().unwrap(), "--texture", &path("b.tif"), "--in-place"], d);
    let whole = tiles_of(&all);
    for updated in [Path::new(&copy), &in_place] {
        let ours = tiles_of(updated);
        let differ: Vec<_> = whole.iter().filter(|(k, v)| ours.get(k) != Some(v)).map(|(k, _)| *k).collect();
        assert!(
            differ.is_empty(),
            "{}: {} tiles differ from a run with every picture: {differ:?}",
            updated.display(),
            differ.len()
        );
        assert_eq!(ours.len(), whole.len(), "{}: tiles", updated.display());
    }
    // The same two pictures tiled apart, each over the coarse one, and merged: the run
    // with every picture too.
    let other = run("b.tspack", &["coarse.tif", "b.tif"]);
    let merged = path("ab.tspack");
    ok(&["merge", before.to_str().unwrap(), other.to_str().unwrap(), "-o", &merged], d);
    assert!(tiles_of(Path::new(&merged)) == whole, "the merge of the two is the run with every picture");
    let ours = tiles_of(&in_place);
    let kept = old.iter().filter(|(k, v)| ours.get(k) == Some(v)).count();
    eprintln!(
        "imagery update: {} tiles added, {} of {} made again",
        ours.len() - old.len(),
        old.len() - kept,
        old.len()
    );
    assert!(
        old.iter().filter(|(k, _)| k.layer() != 1).all(|(k, v)| ours.get(k) == Some(v)),
        "the heights are as they were"
    );
    let info = ok(&["info", in_place.to_str().unwrap()], d);
    assert!(info.contains("b.tif") && info.contains("from LOD0 (texture)"), "{info}");
    // A picture as coarse as the base: refused, naming it, the archive as it was.
    let out =
        oracles::run_in(&["update", in_place.to_str().unwrap(), "--texture", &path("coarse.tif"), "--in-place"], d);
    let said = String::from_utf8_lossy(&out.stderr);
    assert!(!out.status.success() && said.contains("coarse.tif") && said.contains("no finer than"), "{said}");
    assert_eq!(tiles_of(&in_place), ours);
}

/// A collection tiled in shards (`tile --shard I/N`, every shard given every input) and
/// merged: the same tiles, byte for byte, as one run, and the same partial levels; split
/// at the base (the merge needs only the shards) and finer (the merge needs the inputs
/// too, and says so; by default where the base has fewer rows of tiles than shards).
#[test]
fn shards_of_a_collection_merge_into_the_single_run() {
    let dir = tempfile::tempdir().unwrap();
    let d = dir.path();
    let whole = tile(d, "whole.tspack", &[BASE, PATCH], &[]);
    let mut shards = vec![];
    for i in 0..3 {
        let spec = format!("{i}/3");
        shards.push(tile(d, &format!("s{i}.tspack"), &[BASE, PATCH], &["--shard", &spec, "--split-lod", "3"]));
    }
    let merged = d.join("merged.tspack");
    let mut args = vec!["merge"];
    args.extend(shards.iter().map(|s| s.to_str().unwrap()));
    args.extend(["-o", merged.to_str().unwrap()]);
    ok(&args, d);
    assert_eq!(tiles_of(&merged), tiles_of(&whole), "the merged shards' tiles are the single run's");
    let partial = |p: &Path| {
        let r = Reader::open_mmap(p).unwrap();
        r.metadata().layers.iter().map(|l| l.extent.as_ref().map(|e| e.partial.clone())).collect::<Vec<_>>()
    };
    assert_eq!(partial(&merged), partial(&whole));
    let held: Vec<usize> = shards.iter().map(|s| tiles_of(s).len()).collect();
    eprintln!("shards hold {held:?} tiles; the single run {}", tiles_of(&whole).len());

    // Split finer than the base (LOD 3): the shards hold LOD 0 to K in their bands, and
    // the merge makes the levels between from their LOD-K tiles and the run's inputs.
    let inputs: Vec<String> = [BASE, PATCH].iter().map(|p| repo().join(p).to_str().unwrap().to_owned()).collect();
    for split in ["0", "2", "default"] {
        let mut shards = vec![];
        for i in 0..4 {
            let (spec, name) = (format!("{i}/4"), format!("k{split}-s{i}.tspack"));
            let mut extra = vec!["--shard", &spec];
            if split != "default" {
                extra.extend(["--split-lod", split]);
            }
            shards.push(tile(d, &name, &[BASE, PATCH], &extra));
        }
        let k = Reader::open_mmap(&shards[0]).unwrap().metadata().shard.as_ref().unwrap().split_lods[0];
        assert!(k < 3, "split {split}: LOD {k}, finer than the base");
        let held: Vec<usize> = shards.iter().map(|s| tiles_of(s).len()).collect();
        eprintln!("split at LOD {k}: shards hold {held:?} tiles");
        for s in &shards {
            let above = tiles_of(s).keys().filter(|key| key.lod() > k).count();
            assert_eq!(above, 0, "{}: no tile above the split", s.display());
        }
        let merged = d.join(format!("merged-{split}.tspack"));
        let mut args = vec!["merge"];
        args.extend(shards.iter().map(|s| s.to_str().unwrap()));
        args.extend(["-o", merged.to_str().unwrap()]);
        // Without the inputs: refused, saying what to give.
        let out = oracles::run_in(&args, d);
        let said = String::from_utf8_lossy(&out.stderr);
        assert!(!out.status.success() && said.contains("--elevation") && said.contains("base (LOD 3)"), "{said}");
        assert!(!merged.exists(), "nothing written");
        // With other inputs than the run's, or the run's in another order: refused.
        for given in [vec![inputs[0].as_str()], vec![inputs[1].as_str(), inputs[0].as_str()]] {
            let mut wrong = args.clone();
            wrong.push("--elevation");
            wrong.extend(given);
            let out = oracles::run_in(&wrong, d);
            let said = String::from_utf8_lossy(&out.stderr);
            assert!(!out.status.success() && said.contains("not the shards' run's"), "{said}");
        }
        args.push("--elevation");
        args.extend(inputs.iter().map(String::as_str));
        ok(&args, d);
        assert!(tiles_of(&merged) == tiles_of(&whole), "split at LOD {split}: the merge is the single run's tiles");
        assert_eq!(partial(&merged), partial(&whole));
        // Published as a manifest: the coarse archive and the shards hold the run's tiles.
        let (coarse, manifest) = (d.join(format!("coarse-{split}.tspack")), d.join(format!("m-{split}.json")));
        let mut args = vec!["merge", "--manifest", manifest.to_str().unwrap(), "-o", coarse.to_str().unwrap()];
        args.extend(shards.iter().map(|s| s.to_str().unwrap()));
        args.push("--elevation");
        args.extend(inputs.iter().map(String::as_str));
        ok(&args, d);
        let mut all = tiles_of(&coarse);
        for s in &shards {
            all.extend(tiles_of(s));
        }
        assert!(all == tiles_of(&whole), "split at LOD {split}: the manifest's archives hold the single run's tiles");
        ok(&["verify", manifest.to_str().unwrap()], d);
    }
}

/// The options of the planned runs below (the range known, as a plan step gives it).
const PLANNED: [&str; 6] = ["--tile-size", "16", "--vertical-datum", "5773", "--height-range", "0,1000"];

/// The 6" base and both surveys copied into folder `in` of `d` (the bucket a planned run
/// fetches from): the folder, and the files' names (base first).
fn base_and_surveys_in(d: &Path) -> (PathBuf, [String; 3]) {
    let inputs = d.join("in");
    std::fs::create_dir(&inputs).unwrap();
    let names = [BASE6, SURVEY_A, SURVEY_B].map(|p| Path::new(p).file_name().unwrap().to_str().unwrap().to_owned());
    for (path, name) in [BASE6, SURVEY_A, SURVEY_B].iter().zip(&names) {
        std::fs::copy(repo().join(path), inputs.join(name)).unwrap();
    }
    (inputs, names)
}

/// The default split goes finer than the base where the base's rows of tiles cannot
/// share the work out: the 6" base (LOD 2: 7 rows of 16-sample tiles) with two 1" surveys
/// in four shards would give one band both surveys' rows; split at LOD 1 the surveys'
/// tiles spread over the shards, and the merge (given the inputs) is the single run.
#[test]
fn the_default_split_goes_finer_where_the_bases_rows_cannot_share_the_work() {
    let dir = tempfile::tempdir().unwrap();
    let d = dir.path();
    let extra = ["--tile-size", "16", "--height-range", "0,1000"];
    let whole = tile(d, "whole.tspack", &[BASE6, SURVEY_A, SURVEY_B], &extra);
    let mut shards = vec![];
    for i in 0..4 {
        let spec = format!("{i}/4");
        let mut args = extra.to_vec();
        args.extend(["--shard", &spec]);
        shards.push(tile(d, &format!("s{i}.tspack"), &[BASE6, SURVEY_A, SURVEY_B], &args));
    }
    let split = Reader::open_mmap(&shards[0]).unwrap().metadata().shard.as_ref().unwrap().split_lods[0];
    assert_eq!(split, 1, "finer than the base, LOD 2");
    // `info` of a shard says what its merge needs.
    let info = ok(&["info", shards[0].to_str().unwrap()], d);
    assert!(info.contains("shard       0/4") && info.contains("needs the run's inputs"), "{info}");
    // The surveys' tiles (LOD 0) spread over the shards.
    let lod0: Vec<usize> = shards.iter().map(|s| tiles_of(s).keys().filter(|k| k.lod() == 0).count()).collect();
    let total: usize = lod0.iter().sum();
    assert!(lod0.iter().all(|&n| n * 2 < total), "LOD 0 tiles per shard: {lod0:?}");
    let merged = d.join("merged.tspack");
    let mut args = vec!["merge"];
    args.extend(shards.iter().map(|s| s.to_str().unwrap()));
    args.extend(["-o", merged.to_str().unwrap(), "--elevation"]);
    let inputs: Vec<String> =
        [BASE6, SURVEY_A, SURVEY_B].iter().map(|p| repo().join(p).to_str().unwrap().to_owned()).collect();
    args.extend(inputs.iter().map(String::as_str));
    ok(&args, d);
    assert!(tiles_of(&merged) == tiles_of(&whole), "the merge is the single run's tiles");
    // And where the data is: the base's levels, which the merge made, reach beyond the
    // surveys' box that the shards' extents held; the finest level's box and its degrees
    // are the run's. So the whole archive is the single run's.
    assert_eq!(extents(&merged), extents(&whole), "the merge records the single run's extents");
    assert!(extents(&whole).iter().all(|e| e.as_ref().is_some_and(|e| e.lon_lat.is_some())), "degrees recorded");
    assert!(std::fs::read(&merged).unwrap() == std::fs::read(&whole).unwrap(), "the single run, byte for byte");
}

/// Each layer's recorded extent.
fn extents(path: &Path) -> Vec<Option<terrastream_format::LayerExtent>> {
    Reader::open_mmap(path).unwrap().metadata().layers.iter().map(|l| l.extent.clone()).collect()
}

/// A collection's planned run, as the cluster Job runs it: the plan, from the inputs'
/// headers, records every input's depth and lists for each shard the inputs its levels
/// and its band of the base read (a survey only where its band reaches it); a shard given
/// only those and the plan makes the tiles a shard given every input makes, byte for byte,
/// and their merge is the single run. `--list-inputs` says the same lists.
#[test]
fn a_planned_shard_of_a_collection_needs_only_the_inputs_its_plan_lists() {
    let dir = tempfile::tempdir().unwrap();
    let d = dir.path();
    let (inputs, names) = base_and_surveys_in(d);
    let common = PLANNED;
    let tile_in = |folder: &Path, out: &Path, extra: &[&str]| {
        let mut args = vec!["tile", "--elevation", folder.to_str().unwrap(), "-o", out.to_str().unwrap()];
        args.extend(common);
        args.extend(extra);
        ok(&args, d)
    };
    let plan = d.join("plan");
    let mut args = vec!["tile", "--elevation", inputs.to_str().unwrap(), "--shards", "3"];
    args.extend(["--shard-plan-out", plan.to_str().unwrap(), "--relative-to", inputs.to_str().unwrap()]);
    args.extend(common);
    ok(&args, d);
    let lists: Vec<Vec<String>> = (0..3)
        .map(|i| {
            std::fs::read_to_string(plan.join(format!("shard-{i}.txt"))).unwrap().lines().map(str::to_owned).collect()
        })
        .collect();
    let mut union: Vec<&String> = lists.iter().flatten().collect();
    union.sort();
    union.dedup();
    assert_eq!(union.len(), 3, "every input is some shard's: {lists:?}");
    assert!(lists.iter().all(|l| l.contains(&names[0])), "every shard reads the base beneath: {lists:?}");
    assert!(lists.iter().filter(|l| l.len() < 3).count() >= 2, "the surveys are read only where they lie: {lists:?}");
    let plan_file = plan.join("plan.json");
    let mut planned = vec![];
    for (i, list) in lists.iter().enumerate() {
        let spec = format!("{i}/3");
        let mut args = vec!["tile", "--elevation", inputs.to_str().unwrap(), "--shard", &spec, "--list-inputs"];
        args.extend(common);
        let said = ok(&args, d);
        let said: Vec<String> =
            said.lines().map(|l| Path::new(l).file_name().unwrap().to_str().unwrap().to_owned()).collect();
        assert_eq!(&said, list, "--list-inputs of shard {i}");
        // In a folder of its own holding only its inputs (as a pod fetches them).
        let pod = d.join(format!("pod{i}"));
        std::fs::create_dir(&pod).unwrap();
        for name in list {
            std::fs::copy(inputs.join(name), pod.join(name)).unwrap();
        }
        let (ours, everyone) = (d.join(format!("p{i}.tspack")), d.join(format!("w{i}.tspack")));
        tile_in(&pod, &ours, &["--shard", &spec, "--shard-plan", plan_file.to_str().unwrap()]);
        tile_in(&inputs, &everyone, &["--shard", &spec]);
        let (a, b) = (tiles_of(&ours), tiles_of(&everyone));
        assert!(!a.is_empty());
        assert!(a == b, "shard {i}: {} tiles from its inputs, {} from all; they differ", a.len(), b.len());
        planned.push(ours);
    }
    let merged = d.join("merged.tspack");
    let mut args = vec!["merge"];
    args.extend(planned.iter().map(|p| p.to_str().unwrap()));
    args.extend(["-o", merged.to_str().unwrap()]);
    ok(&args, d);
    let whole = d.join("whole.tspack");
    tile_in(&inputs, &whole, &[]);
    assert_eq!(tiles_of(&merged), tiles_of(&whole), "the merged planned shards' tiles are the single run's");
    // Shard `i` made from its pod folder as it now is: whether it failed, and what it said.
    let refused = |i: usize| {
        let (pod, out) = (d.join(format!("pod{i}")), d.join("refused.tspack"));
        let shard = format!("{i}/3");
        let mut args = vec!["tile", "--elevation", pod.to_str().unwrap(), "--shard", &shard];
        args.extend(["--shard-plan", plan_file.to_str().unwrap(), "-o", out.to_str().unwrap()]);
        args.extend(common);
        let out = oracles::run_in(&args, d);
        (!out.status.success(), String::from_utf8_lossy(&out.stderr).into_owned())
    };
    // A shard given an input the plan does not record is told which (the other shards
    // know nothing of it).
    std::fs::copy(repo().join(PATCH), d.join("pod2").join("stray.tif")).unwrap();
    let (failed, said) = refused(2);
    assert!(failed && said.contains("stray.tif") && said.contains("plan records"), "{said}");
    // A shard missing a listed input is told which.
    std::fs::remove_file(d.join("pod0").join(&lists[0][1])).unwrap();
    let (failed, said) = refused(0);
    assert!(failed && said.contains(&lists[0][1]), "{said}");
}

/// A planned run split finer than the base: the plan lists in `merge.txt` the inputs the
/// merge reads (the base, deeper than the split); the shards, each made from its own
/// list, merge, given the plan and a folder holding only `merge.txt`'s inputs, into the
/// single run, byte for byte.
#[test]
fn a_planned_merge_of_shards_split_finer_than_the_base_reads_only_the_base() {
    let dir = tempfile::tempdir().unwrap();
    let d = dir.path();
    let (inputs, names) = base_and_surveys_in(d);
    let common = PLANNED;
    let plan = d.join("plan");
    let mut args = vec!["tile", "--elevation", inputs.to_str().unwrap(), "--shards", "3", "--split-lod", "0"];
    args.extend(["--shard-plan-out", plan.to_str().unwrap(), "--relative-to", inputs.to_str().unwrap()]);
    args.extend(common);
    ok(&args, d);
    let merge_list = std::fs::read_to_string(plan.join("merge.txt")).unwrap();
    assert_eq!(merge_list.lines().collect::<Vec<_>>(), [names[0].as_str()], "the merge reads the base alone");
    let plan_file = plan.join("plan.json");
    let mut shards = vec![];
    for i in 0..3 {
        let list = std::fs::read_to_string(plan.join(format!("shard-{i}.txt"))).unwrap();
        let pod = d.join(format!("pod{i}"));
        std::fs::create_dir(&pod).unwrap();
        for name in list.lines() {
            std::fs::copy(inputs.join(name), pod.join(name)).unwrap();
        }
        let out = d.join(format!("s{i}.tspack"));
        let spec = format!("{i}/3");
        let mut args = vec!["tile", "--elevation", pod.to_str().unwrap(), "-o", out.to_str().unwrap()];
        args.extend(["--shard", &spec, "--shard-plan", plan_file.to_str().unwrap()]);
        args.extend(common);
        ok(&args, d);
        shards.push(out);
    }
    let pod = d.join("merge-pod");
    std::fs::create_dir(&pod).unwrap();
    let merged = d.join("merged.tspack");
    let mut args = vec!["merge"];
    args.extend(shards.iter().map(|p| p.to_str().unwrap()));
    args.extend(["-o", merged.to_str().unwrap(), "--shard-plan", plan_file.to_str().unwrap()]);
    args.extend(["--inputs", pod.to_str().unwrap()]);
    // Before the base is fetched: refused, naming it and what lists it.
    let out = oracles::run_in(&args, d);
    let said = String::from_utf8_lossy(&out.stderr);
    assert!(!out.status.success() && said.contains(&names[0]) && said.contains("merge.txt"), "{said}");
    std::fs::copy(inputs.join(&names[0]), pod.join(&names[0])).unwrap();
    ok(&args, d);
    let whole = d.join("whole.tspack");
    let mut args = vec!["tile", "--elevation", inputs.to_str().unwrap(), "-o", whole.to_str().unwrap()];
    args.extend(common);
    ok(&args, d);
    assert!(tiles_of(&merged) == tiles_of(&whole), "the planned merge is the single run's tiles");
    assert_eq!(extents(&merged), extents(&whole), "the planned merge records the single run's extents");
}

/// A VRT of the base and the patch (`gdalbuildvrt -resolution highest`, each source a
/// whole file read as it is) is tiled as its two files, each as deep as it reaches: tile
/// for tile, byte for byte, the run given the files, and its levels finer than the base's
/// hold tiles only over the patch. A VRT that gives a source a nodata of its own is one
/// input at its finest spacing, as before, and says so.
#[test]
fn a_vrt_of_a_base_and_a_patch_is_tiled_as_its_files() {
    let dir = tempfile::tempdir().unwrap();
    let d = dir.path();
    // gdalbuildvrt takes sources of one data type: the patch as Float32, as the base is.
    let patch = d.join("patch-f32.tif");
    let made = std::process::Command::new("gdal_translate")
        .args(["-q", "-ot", "Float32"])
        .args([repo().join(PATCH), patch.clone()])
        .output()
        .unwrap();
    assert!(made.status.success(), "gdal_translate: {}", String::from_utf8_lossy(&made.stderr));
    let patch = patch.to_str().unwrap();
    let vrt = |name: &str, extra: &[&str]| {
        let path = d.join(name);
        let built = std::process::Command::new("gdalbuildvrt")
            .args(["-q", "-resolution", "highest"])
            .args(extra)
            .arg(&path)
            .args([repo().join(BASE).to_str().unwrap(), patch])
            .output()
            .unwrap();
        assert!(built.status.success(), "gdalbuildvrt: {}", String::from_utf8_lossy(&built.stderr));
        let text = std::fs::read_to_string(&path).unwrap();
        assert_eq!(text.matches("<SourceFilename").count(), 2, "both sources in the VRT: {text}");
        path.to_str().unwrap().to_owned()
    };
    let files = tile(d, "files.tspack", &[BASE, patch], &[]);
    let plain = vrt("plain.vrt", &[]);
    let from_vrt = tile(d, "vrt.tspack", &[&plain], &[]);
    let (a, b) = (tiles_of(&files), tiles_of(&from_vrt));
    assert_eq!(a.len(), b.len(), "as many tiles");
    assert!(a == b, "the VRT's archive holds the files' tiles, byte for byte");
    let lods = per_lod(&from_vrt);
    let one_resolution = per_lod(&tile(d, "order.tspack", &[BASE, patch], &["--priority", "order"]));
    assert!(lods[&0] < one_resolution[&0], "LOD 0 only over the patch: {lods:?} against {one_resolution:?}");
    let info = ok(&["info", "--json", from_vrt.to_str().unwrap()], d);
    assert!(info.contains("patch-f32.tif") && info.contains("collection-base-10s-plus3m.tif"), "{info}");
    // A nodata of the VRT's own: read as the VRT, every input at the finest spacing.
    let nodata = vrt("nodata.vrt", &["-srcnodata", "-1000"]);
    let out = d.join("nodata.tspack");
    let run = oracles::run_in(&["tile", "--elevation", &nodata, "--tile-size", "32", "-o", out.to_str().unwrap()], d);
    let said = String::from_utf8_lossy(&run.stderr);
    assert!(run.status.success(), "{said}");
    assert!(said.contains("nodata.vrt") && said.contains("finest spacing"), "{said}");
    assert_eq!(per_lod(&out)[&0], one_resolution[&0], "one resolution everywhere");
}
