//! The globe from the command line: a geographic DEM of Everest (generated: a peak with
//! ripples, 0.2 x 0.2 degrees at 3", made a GeoTIFF by GDAL) is drawn on the ellipsoid
//! 6 400 km from the Earth's centre without jitter 2 m above the summit;
//! a geographic input larger than a region keeps its own grid by default. Needs GDAL's
//! command-line tools and a software Vulkan (lavapipe).
#![allow(clippy::unwrap_used, clippy::expect_used, clippy::cast_precision_loss, clippy::cast_possible_truncation)]
#![allow(clippy::cast_sign_loss, missing_docs)]

use std::path::{Path, PathBuf};
use std::process::Command;

#[path = "support/oracles.rs"]
mod oracles;
use oracles::{EVEREST, SUMMIT, dem, ok_in as terrastream, run_in};

fn gdal() -> bool {
    let found = Command::new("gdal_translate").arg("--version").output().is_ok();
    assert!(found || std::env::var_os("CI").is_none(), "gdal-bin is required on CI");
    found
}

/// A generated DEM (`oracles::dem`: west, south, degrees, samples a degree) tiled into
/// `dir/{name}.tspack` with `args` added.
fn tiled(dir: &Path, name: &str, (west, south, degrees, per_degree): (f64, f64, f64, f64), args: &[&str]) -> PathBuf {
    let tif = dem(dir, west, south, degrees, per_degree);
    let archive = dir.join(format!("{name}.tspack"));
    let mut all = vec!["-q", "tile", "--elevation", tif.to_str().unwrap(), "-o", archive.to_str().unwrap()];
    all.extend(args);
    terrastream(&all, dir);
    archive
}

/// 12 degrees at 30" around Everest: more than a region, so it keeps its geographic grid.
fn himalaya(dir: &Path) -> PathBuf {
    tiled(dir, "himalaya", (EVEREST.0 - 6.0, EVEREST.1 - 6.0, 12.0, 120.0), &[])
}

fn decode(path: &Path) -> (u32, u32, Vec<u8>) {
    terrastream_testkit::golden::decode_png(&std::fs::read(path).unwrap())
}

/// Renders 2 m above the summit and again 1 mm higher: the pictures differ in at most
/// 0.5 % of their pixels (f32 positions 6 400 km from the Earth's centre would move the
/// ground by half a metre and back as the eye moves).
#[test]
fn no_jitter_two_metres_above_the_summit() {
    if !gdal() {
        return;
    }
    let dir = tempfile::tempdir().unwrap();
    let archive = tiled(dir.path(), "everest", (EVEREST.0 - 0.1, EVEREST.1 - 0.1, 0.2, 1200.0), &["--keep-geographic"]);
    let render = |name: &str, above: f64| {
        let png = dir.path().join(name);
        let at = format!("{},{},{}", EVEREST.0, EVEREST.1, SUMMIT + above);
        let said = terrastream(
            &["render", archive.to_str().unwrap(), "-o", png.to_str().unwrap(), "--size", "400x300"]
                .into_iter()
                .chain(["--at", &at, "--heading", "30", "--pitch", "-25"])
                .collect::<Vec<_>>(),
            dir.path(),
        );
        eprintln!("{said}");
        decode(&png)
    };
    let (w, h, a) = render("a.png", 2.0);
    let (_, _, b) = render("b.png", 2.001);
    let pixels = (w * h) as usize;
    let sky = a[..4].to_vec();
    let ground = a.chunks_exact(4).filter(|p| p[..3] != sky[..3]).count();
    assert!(ground > pixels / 2, "the summit fills the view: {ground} of {pixels} pixels");
    let differ = a
        .chunks_exact(4)
        .zip(b.chunks_exact(4))
        .filter(|(p, q)| p.iter().zip(*q).any(|(x, y)| x.abs_diff(*y) > 8))
        .count();
    assert!(differ * 200 <= pixels, "{differ} of {pixels} pixels differ with the eye 1 mm higher");
}

/// A geographic DEM spanning more than a region keeps its own grid; a region goes onto a
/// transverse Mercator centred on it.
#[test]
fn a_continent_keeps_its_geographic_grid() {
    if !gdal() {
        return;
    }
    let dir = tempfile::tempdir().unwrap();
    for (degrees, geographic) in [(12.0, true), (2.0, false)] {
        let archive = tiled(dir.path(), &degrees.to_string(), (86.0 - degrees / 2.0 + 1.0, 27.0, degrees, 60.0), &[]);
        let reader = terrastream_format::Reader::open_mmap(&archive).unwrap();
        let definition = reader.metadata().georeference.as_ref().unwrap().definition.clone().unwrap();
        assert_eq!(definition.contains("+proj=longlat"), geographic, "{degrees} degrees: {definition}");
        assert_eq!(definition.contains("+proj=tmerc"), !geographic, "{degrees} degrees: {definition}");
    }
}

/// A grazing view over a region fetches no more tiles on the globe than on the plate: the
/// globe's boxes follow the ground's tangent plane, and the curved Earth hides the rest.
#[test]
fn a_grazing_view_fetches_no_more_tiles_on_the_globe() {
    if !gdal() {
        return;
    }
    let dir = tempfile::tempdir().unwrap();
    let archive = tiled(dir.path(), "everest", (EVEREST.0 - 0.1, EVEREST.1 - 0.1, 0.2, 1200.0), &["--tile-size", "32"]);
    let (a, p) = (archive.to_str().unwrap(), dir.path().join("v.png"));
    let fetched = |flat: bool| -> u64 {
        let mut args = vec!["render", a, "-o", p.to_str().unwrap(), "--size", "640x360"];
        args.extend(["--at", "86.83,27.9,5200", "--heading", "45", "--pitch", "-4"]);
        if flat {
            args.push("--flat");
        }
        let said = terrastream(&args, dir.path());
        let before = said.split(" tiles fetched").next().unwrap();
        before.rsplit(' ').next().unwrap().parse().unwrap()
    };
    let (globe, flat) = (fetched(false), fetched(true));
    assert!(flat > 10, "the view reaches several LODs: {flat} tiles");
    assert!(globe <= flat, "the globe fetched {globe} tiles, the plate {flat}");
}

/// From 20 000 km down to 2 m above the summit: every view draws terrain (a NaN placed
/// anywhere would drop its triangles, and `render` fails a view that draws none).
#[test]
fn from_orbit_to_the_summit_every_view_draws_terrain() {
    if !gdal() {
        return;
    }
    let dir = tempfile::tempdir().unwrap();
    let archive = himalaya(dir.path());
    let a = archive.to_str().unwrap();
    let png = dir.path().join("v.png");
    for (above, pitch, share) in
        [(2.0e7, -90.0, 0.0005), (2.0e6, -90.0, 0.02), (2.0e5, -60.0, 0.3), (2.0e4, -30.0, 0.3), (2.0, -30.0, 0.3)]
    {
        let at = format!("{},{},{}", EVEREST.0, EVEREST.1, SUMMIT + above);
        let args = ["render", a, "-o", png.to_str().unwrap(), "--size", "320x240", "--at", &at];
        terrastream(&[&args[..], &["--heading", "20", "--pitch", &pitch.to_string()]].concat(), dir.path());
        let (w, h, rgba) = decode(&png);
        let sky = [rgba[0], rgba[1], rgba[2]];
        let ground = rgba.chunks_exact(4).filter(|p| p[..3] != sky).count();
        let drawn = ground as f64 / f64::from(w * h);
        assert!(drawn >= share, "{above} m above the summit: {drawn:.4} of the view is terrain");
    }
}

/// Views of the whole Earth are not errors: with the data behind the Earth (the far side,
/// just past the limb) nothing of it is in view, and `render` succeeds drawing no terrain;
/// with it just inside the limb, or seen from above a pole, it is drawn.
#[test]
fn data_behind_the_horizon_is_not_in_view() {
    if !gdal() {
        return;
    }
    let dir = tempfile::tempdir().unwrap();
    let archive = himalaya(dir.path());
    let a = archive.to_str().unwrap();
    let png = dir.path().join("v.png");
    // From 20 000 km the Earth's visible cap reaches 76 degrees of arc from the point
    // below (77 for the data's 1 200 m): the data's nearest edge 89 degrees away along
    // the meridian is behind the limb, its farthest 61 degrees away inside it; from the
    // pole, 56 to 68 degrees.
    for (name, lon, lat, drawn) in [
        ("the far side", EVEREST.0 - 180.0, -EVEREST.1, false),
        ("past the limb", EVEREST.0, EVEREST.1 - 95.0, false),
        ("inside the limb", EVEREST.0, EVEREST.1 - 55.0, true),
        ("above the north pole", 0.0, 90.0, true),
    ] {
        let at = format!("{lon},{lat},20000000");
        let args = ["render", a, "-o", png.to_str().unwrap(), "--size", "320x240", "--at", &at, "--pitch", "-90"];
        let out = run_in(&[&args[..], &["--shading", "flat", "--no-atmosphere"]].concat(), dir.path());
        let said = String::from_utf8_lossy(&out.stderr);
        assert!(out.status.success(), "{name}: {said}");
        let (w, h, rgba) = decode(&png);
        let white = rgba.chunks_exact(4).filter(|p| p[0] > 200 && p[1] > 200 && p[2] > 200).count();
        assert_eq!(white > 0, drawn, "{name}: {white} of {} pixels are terrain", w * h);
    }
}

/// From 20 000 km over the Arabian Sea the Earth reads as continents and oceans (the
/// built-in picture beyond the data): the disc holds both sea-blue and land-green pixels;
/// with `--no-earth` it is one plain ground.
#[test]
fn from_orbit_the_earth_shows_continents_and_oceans() {
    if !gdal() {
        return;
    }
    let dir = tempfile::tempdir().unwrap();
    let archive = tiled(dir.path(), "everest", (EVEREST.0 - 0.1, EVEREST.1 - 0.1, 0.2, 1200.0), &["--keep-geographic"]);
    let a = archive.to_str().unwrap();
    let shares = |extra: &[&str]| {
        let png = dir.path().join("earth.png");
        let args = ["render", a, "-o", png.to_str().unwrap(), "--size", "320x240", "--at", "60,10,20000000"];
        terrastream(&[&args[..], &["--pitch", "-90"], extra].concat(), dir.path());
        let (w, h, rgba) = decode(&png);
        let lit: Vec<&[u8]> =
            rgba.chunks_exact(4).filter(|p| u32::from(p[0]) + u32::from(p[1]) + u32::from(p[2]) > 90).collect();
        let c = |p: &[u8], i: usize| i32::from(p[i]);
        let sea = lit.iter().filter(|p| c(p, 2) > c(p, 1) + 25 && c(p, 2) > c(p, 0) + 40).count();
        let land = lit.iter().filter(|p| c(p, 1) + 5 >= c(p, 2) && c(p, 0) + 60 >= c(p, 2)).count();
        let n = f64::from(w * h);
        (lit.len() as f64 / n, sea as f64 / n, land as f64 / n)
    };
    let (disc, sea, land) = shares(&[]);
    eprintln!("the Earth from 20 000 km: disc {disc:.3}, sea {sea:.3}, land {land:.3} of the view");
    assert!(disc > 0.08, "the Earth fills {disc:.3} of the view");
    assert!(sea > 0.03 && land > 0.01, "sea {sea:.3} and land {land:.3} of the view");
    let (_, _, plain_land) = shares(&["--no-earth"]);
    assert!(plain_land < 0.002, "--no-earth: {plain_land:.3} of the view is land");
}

/// A flat archive of `height` metres over `[west, south, degrees, samples a degree]` in
/// `d`, and a renderer of it: the view from `--at` `at` (`--heading`, `--pitch`, `--fov`)
/// with the sun from 160°, 40° up, and `extra` options, at 320 x 180 (width, height and
/// RGBA).
fn flat_views(
    d: &Path,
    name: &str,
    area: [f64; 4],
    height: f64,
) -> impl Fn(&str, [&str; 3], &[&str]) -> (u32, u32, Vec<u8>) {
    let tif = oracles::grid_tif(d, name, area, &|_, _| height);
    let archive = d.join(format!("{name}.tspack"));
    terrastream(&["-q", "tile", "--elevation", tif.to_str().unwrap(), "-o", archive.to_str().unwrap()], d);
    move |at: &str, [heading, pitch, fov]: [&str; 3], extra: &[&str]| {
        let png = d.join(format!("{name}.png"));
        let args = ["render", archive.to_str().unwrap(), "-o", png.to_str().unwrap(), "--size", "320x180"];
        let view = ["--at", at, "--heading", heading, "--pitch", pitch, "--fov", fov, "--sun", "160,40"];
        terrastream(&[&args[..], &view, extra].concat(), d);
        decode(&png)
    }
}

/// Beyond an archive's data the ground stands on the built-in heights: from 2 500 m over
/// the plain south of the Himalaya (a small flat archive there, 150 m), looking north, the
/// mountains 100-150 km away rise above where the sea's horizon is (`--no-earth` draws the
/// plain ground on the sphere): the sky ends higher up the picture's middle column. Without
/// the heights the two horizons are the same row.
#[test]
fn beyond_the_data_the_ground_stands_on_the_earths_heights() {
    if !gdal() {
        return;
    }
    let dir = tempfile::tempdir().unwrap();
    let view = flat_views(dir.path(), "plain", [86.0, 26.6, 0.1, 600.0], 150.0);
    // Where the middle column steps from the bright sky near the horizon down to the
    // ground seen through the haze: its largest drop in brightness from one row to the
    // next (the sky darkens upwards, the ground downwards, both gradually).
    let horizon = |extra: &[&str]| {
        let (w, h, rgba) = view("86.9,26.7,2500", ["0", "0.5", "12"], extra);
        let bright = |y: u32| rgba[((y * w + w / 2) * 4) as usize..][..3].iter().map(|&c| i32::from(c)).sum::<i32>();
        let (row, drop) = (1..h).map(|y| (y, bright(y - 1) - bright(y))).max_by_key(|&(_, drop)| drop).unwrap();
        assert!(drop > 40, "no horizon in the middle column: its largest step is {drop}");
        row
    };
    let (raised, sea) = (horizon(&[]), horizon(&["--no-earth"]));
    eprintln!("the ground's horizon at row {raised}, the sea's at row {sea} of 180");
    assert!(sea > 90 && sea < 170, "the sea's horizon at row {sea}");
    assert!(raised + 15 < sea, "the mountains' top at row {raised}, the sea's horizon at {sea}");
}

/// An eye lower than the built-in heights at its own place (60 m over a small flat
/// archive at 2 500 m in the Colorado Rockies, in a 20 km cell of the heights that
/// averages 3 181 m) still sees the ground beyond the data, rising around it: it saw none
/// (every ray started below that ground, and the sky came down to the data's edge). In
/// the picture's middle column, rows of that ground (pale and yellower than the sky: red
/// over blue; the data's green is not) lie between the sky and the data.
#[test]
fn an_eye_below_the_earths_heights_sees_them_rise_around_it() {
    if !gdal() {
        return;
    }
    let dir = tempfile::tempdir().unwrap();
    let view = flat_views(dir.path(), "valley", [-106.35, 39.55, 0.1, 600.0], 2500.0);
    let ground_rows = |extra: &[&str]| {
        let (w, h, rgba) = view("-106.30,39.60,2560", ["0", "2", "20"], extra);
        let beyond = |y: u32| {
            let p = &rgba[((y * w + w / 2) * 4) as usize..][..3];
            i32::from(p[0]) > i32::from(p[2]) + 15 && p[1] > 170
        };
        (0..h).filter(|&y| beyond(y)).count()
    };
    let (earth, plain) = (ground_rows(&[]), ground_rows(&["--no-earth"]));
    eprintln!("rows of ground beyond the data: {earth} on the Earth's heights, {plain} on the plain ground");
    assert_eq!(plain, 0, "the plain ground beyond the data is below the horizon");
    assert!(earth >= 5, "only {earth} rows of the heights' ground beyond the data");
}

/// A coast (0.1 x 0.1 degrees at 3"): the west half a flat sea stored as 0, as SRTM and
/// Copernicus store it; the east half land rising from 2 m, with a basin 30 m below sea
/// level in it. Drawn from above with the height tint, the sea is water-blue and the land
/// and the basin (below sea level, but not a flat 0) are not.
#[test]
fn the_sea_is_water_across_the_edges_of_its_tiles() {
    // Each tile's outermost samples have neighbours in the next tile: the sea's test must
    // not draw them as a line of land (it did, once its flag came from each tile alone).
    if !gdal() {
        return;
    }
    let dir = tempfile::tempdir().unwrap();
    let (tif, _, (lon, lat)) = oracles::sea_dem(dir.path());
    let archive = dir.path().join("sea.tspack");
    terrastream(&["-q", "tile", "--elevation", tif.to_str().unwrap(), "-o", archive.to_str().unwrap()], dir.path());
    let png = dir.path().join("sea.png");
    // Looking straight down on the corner where four tiles of LOD 0 meet.
    let at = format!("{lon},{lat},6000");
    let args = ["render", archive.to_str().unwrap(), "-o", png.to_str().unwrap(), "--size", "320x240", "--at", &at];
    terrastream(&[&args[..], &["--pitch", "-90", "--heading", "0", "--sun", SUN_OUT_OF_VIEW]].concat(), dir.path());
    let (w, h, rgba) = decode(&png);
    let (mut n, mut land) = (0, Vec::new());
    for y in h / 10..h * 9 / 10 {
        for x in w / 10..w * 9 / 10 {
            let i = 4 * (y * w + x) as usize;
            let (r, g, b) = (i32::from(rgba[i]), i32::from(rgba[i + 1]), i32::from(rgba[i + 2]));
            n += 1;
            if !(b > r + 30 && b > g + 10) {
                land.push((x, y, (r, g, b)));
            }
        }
    }
    eprintln!("{} of {n} pixels not water", land.len());
    assert!(land.is_empty(), "{} of {n} sea pixels drawn as land, first {:?}", land.len(), &land[..land.len().min(5)]);
}

/// A sun for views straight down on water: 25 degrees up, so its glint lies 65 degrees
/// from the nadir, outside the view (whose water the tests tell by its blue).
const SUN_OUT_OF_VIEW: &str = "135,25";

/// `archive` (of [`oracles::coast_dem`], `bounds` its west, south and size) rendered
/// 320 x 240 from 7 km straight down on the data's middle, where the coast runs: width,
/// height, RGBA.
fn coast_from_above(archive: &Path, dir: &Path, [west, south, degrees]: [f64; 3]) -> (u32, u32, Vec<u8>) {
    let png = dir.join("coast.png");
    let at = format!("{},{},7000", west + degrees / 2.0, south + degrees / 2.0);
    let args = ["render", archive.to_str().unwrap(), "-o", png.to_str().unwrap(), "--size", "320x240", "--at", &at];
    terrastream(&[&args[..], &["--pitch", "-90", "--heading", "0", "--sun", SUN_OUT_OF_VIEW]].concat(), dir);
    decode(&png)
}

/// The share of the pixels in columns `x` and rows `y` of a picture `w` wide drawn
/// water-blue (the height tint has no such blue).
fn water_blue(w: u32, rgba: &[u8], x: std::ops::Range<u32>, y: std::ops::Range<u32>) -> f64 {
    let (mut n, mut water) = (0, 0);
    for row in y {
        for column in x.clone() {
            let i = 4 * (row * w + column) as usize;
            let (r, g, b) = (i32::from(rgba[i]), i32::from(rgba[i + 1]), i32::from(rgba[i + 2]));
            n += 1;
            water += usize::from(b > r + 30 && b > g + 10);
        }
    }
    water as f64 / f64::from(n)
}

#[test]
fn the_sea_stored_as_zero_is_drawn_as_water() {
    if !gdal() {
        return;
    }
    let dir = tempfile::tempdir().unwrap();
    let (tif, bounds) = oracles::coast_dem(dir.path());
    let archive = dir.path().join("coast.tspack");
    terrastream(&["-q", "tile", "--elevation", tif.to_str().unwrap(), "-o", archive.to_str().unwrap()], dir.path());
    let (w, h, rgba) = coast_from_above(&archive, dir.path(), bounds);
    // The middle third of rows: a band of columns inside each half, and the basin.
    // (At 7 km the view is a little narrower than the data: no ground beyond it in these.)
    let band = |x: std::ops::Range<u32>| water_blue(w, &rgba, x, h / 3..2 * h / 3);
    let (sea, land) = (band(w / 10..w / 3), band(w * 11 / 20..w * 13 / 20));
    let basin = water_blue(w, &rgba, w * 3 / 4..w * 3 / 4 + 1, h / 2..h / 2 + 1);
    eprintln!("sea {sea:.2}, land {land:.2} of their bands water-blue; basin {basin}");
    assert!(sea > 0.95, "the sea: {sea:.2} water-blue");
    assert!(land < 0.05, "the land: {land:.2} water-blue");
    assert_eq!(basin, 0.0, "the basin below sea level is land");
}

/// The same coast with a water layer from a mask of a lake filling the basin
/// (`terrastream water`): the lake is drawn as water, though its heights (30 m below sea
/// level, not a flat 0) alone are land; the sea, which the mask says nothing of, stays
/// water by the flat-0 rule; the land stays land.
#[test]
fn a_lake_from_the_water_layer_is_drawn_as_water() {
    if !gdal() {
        return;
    }
    let dir = tempfile::tempdir().unwrap();
    let (tif, bounds) = oracles::coast_dem(dir.path());
    let (mask, _) = oracles::lake_mask(dir.path(), bounds);
    let (plain, wet) = (dir.path().join("coast.tspack"), dir.path().join("coast-water.tspack"));
    terrastream(&["-q", "tile", "--elevation", tif.to_str().unwrap(), "-o", plain.to_str().unwrap()], dir.path());
    let water = ["-q", "water", plain.to_str().unwrap(), "--mask", mask.to_str().unwrap(), "-o", wet.to_str().unwrap()];
    terrastream(&water, dir.path());
    let (w, h, rgba) = coast_from_above(&wet, dir.path(), bounds);
    // The lake's middle (the basin: about 70 px across here, from x = 0.62 w to 0.85 w),
    // the sea, and the land between them and east of the lake.
    let rows = h / 3..2 * h / 3;
    let lake = water_blue(w, &rgba, w * 3 / 4 - 10..w * 3 / 4 + 10, h / 2 - 10..h / 2 + 10);
    let sea = water_blue(w, &rgba, w / 10..w / 3, rows.clone());
    let land = water_blue(w, &rgba, w * 53 / 100..w * 58 / 100, rows.clone()).max(water_blue(
        w,
        &rgba,
        w * 9 / 10..w * 19 / 20,
        rows,
    ));
    eprintln!("water-blue: lake {lake:.2}, sea {sea:.2}, land {land:.2}");
    assert!(lake > 0.95, "the lake: {lake:.2} water-blue");
    assert!(sea > 0.95, "the sea: {sea:.2} water-blue");
    assert!(land < 0.05, "the land: {land:.2} water-blue");
}

/// Water mirrors the sun: over the coast's sea from 1 500 m, looking west with the sun 15
/// degrees up ahead, the sea under the sun (the middle columns, between the horizon and
/// the bottom of the view) is far brighter than the sea to either side: the glint. With
/// the sun behind the eye there is none, and the middle is as dark as the sides.
#[test]
fn the_sea_shows_the_suns_glint_ahead_and_none_behind() {
    if !gdal() {
        return;
    }
    let dir = tempfile::tempdir().unwrap();
    let (tif, [west, south, degrees]) = oracles::coast_dem(dir.path());
    let archive = dir.path().join("coast.tspack");
    terrastream(&["-q", "tile", "--elevation", tif.to_str().unwrap(), "-o", archive.to_str().unwrap()], dir.path());
    let at = format!("{},{},1500", west + degrees * 0.6, south + degrees / 2.0);
    let lightness = |sun: &str| {
        let png = dir.path().join("glint.png");
        let args = ["render", archive.to_str().unwrap(), "-o", png.to_str().unwrap(), "--size", "320x200", "--at", &at];
        terrastream(&[&args[..], &["--heading", "270", "--pitch", "-12", "--sun", sun]].concat(), dir.path());
        let (w, h, rgba) = decode(&png);
        // Mean of r + g + b over columns `x` of the rows from 60 % to 85 % of the height.
        let band = |x: std::ops::Range<u32>| {
            let (mut sum, mut n) = (0.0, 0.0);
            for y in h * 3 / 5..h * 17 / 20 {
                for column in x.clone() {
                    let i = 4 * (y * w + column) as usize;
                    sum += f64::from(rgba[i]) + f64::from(rgba[i + 1]) + f64::from(rgba[i + 2]);
                    n += 1.0;
                }
            }
            sum / n
        };
        let middle = band(w / 2 - 8..w / 2 + 8);
        let sides = (band(0..w / 6) + band(w * 5 / 6..w)) / 2.0;
        middle / sides
    };
    let (ahead, behind) = (lightness("270,15"), lightness("90,15"));
    eprintln!("the sea under the sun against its sides: sun ahead {ahead:.2}x, behind {behind:.2}x");
    assert!(ahead > 2.0, "no glint under the sun: {ahead:.2}x");
    assert!((0.8..1.25).contains(&behind), "a glint with the sun behind: {behind:.2}x");
}
