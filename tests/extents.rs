//! The data's own extent, with pyramids nobody here made: a regional XYZ tree and a
//! regional geodetic TMS tree cut by `gdal2tiles.py` (zooms 9 and up only) pack, draw and
//! are framed; a tree whose tiles the view cannot reach fails `render` naming the layer;
//! a Terrarium WebP PMTiles of heights and an XYZ imagery tree of another depth become one
//! archive whose heights are the source's; `extract --layout original` of an archive with
//! tile borders packs back to the same tiles.
//!
//! Needs GDAL's command-line tools (Debian `gdal-bin`, installed by the test command) and
//! a software Vulkan (lavapipe).
#![allow(
    clippy::unwrap_used,
    clippy::expect_used,
    clippy::cast_possible_truncation,
    clippy::cast_precision_loss,
    clippy::cast_sign_loss,
    missing_docs
)]

#[path = "support/cli.rs"]
mod cli;

use std::path::{Path, PathBuf};
use std::process::{Command, Output};

use terrastream_client::{Origin, StreamOptions, Streamer};
use terrastream_format::{LayerKind, Reader, TileKey};
use terrastream_testkit::golden::{Tolerance, assert_golden, decode_png};

const WIDTH: u32 = 480;
const HEIGHT: u32 = 320;
/// lavapipe is deterministic for a given Mesa; the allowance covers another Mesa release
/// (mean <= 1.5/255, at most 1.5 % of pixels off by more than 24/255). A tree drawn
/// elsewhere, unframed or with its margins shows far more.
const TOLERANCE: Tolerance = Tolerance { mean: 1.5, pixel: 24, off_share: 0.015 };

fn text(o: &Output) -> String {
    format!("{}{}", String::from_utf8_lossy(&o.stdout), String::from_utf8_lossy(&o.stderr))
}

fn terrastream(args: &[&str], cwd: &Path) -> Output {
    cli::terrastream().arg("-q").args(args).current_dir(cwd).output().unwrap()
}

fn ok(args: &[&str], cwd: &Path) -> String {
    let out = terrastream(args, cwd);
    assert!(out.status.success(), "terrastream {args:?}: {}", text(&out));
    text(&out)
}

fn tool(program: &str, args: &[&str], cwd: &Path) {
    let out = Command::new(program).args(args).current_dir(cwd).output().unwrap_or_else(|e| {
        panic!("{program} (Debian gdal-bin, installed by scripts/test.sh): {e}");
    });
    assert!(out.status.success(), "{program} {args:?}: {}", text(&out));
}

/// Writes `name.tif`: a 600 x 600 RGB image (coloured checkers, a white frame two pixels
/// wide) placed by GDAL over `[west, south, east, north]` in EPSG:4326.
fn image_over(cwd: &Path, name: &str, [west, south, east, north]: [f64; 4]) -> PathBuf {
    const N: u32 = 600;
    let rgb: Vec<u8> = (0..N * N)
        .flat_map(|i| {
            let (x, y) = (i % N, i / N);
            if x < 2 || y < 2 || x >= N - 2 || y >= N - 2 {
                return [255, 255, 255];
            }
            let checker = (x / 60 + y / 60) % 2 == 0;
            let (r, g) = ((x * 200 / N) as u8 + 30, (y * 200 / N) as u8 + 30);
            if checker { [r, g, 60] } else { [g, 90, r] }
        })
        .collect();
    let png = cwd.join(format!("{name}.png"));
    let mut bytes = Vec::new();
    let mut encoder = png::Encoder::new(&mut bytes, N, N);
    encoder.set_color(png::ColorType::Rgb);
    encoder.write_header().unwrap().write_image_data(&rgb).unwrap();
    std::fs::write(&png, bytes).unwrap();
    let tif = format!("{name}.tif");
    let box_ = [west, north, east, south].map(|v| v.to_string());
    tool(
        "gdal_translate",
        &["-q", "-a_srs", "EPSG:4326", "-a_ullr", &box_[0], &box_[1], &box_[2], &box_[3], png.to_str().unwrap(), &tif],
        cwd,
    );
    cwd.join(tif)
}

/// Share of pixels that are not the sky colour of the top-left corner.
fn drawn_share(rgba: &[u8]) -> f64 {
    let sky = &rgba[..3];
    let drawn = rgba.chunks_exact(4).filter(|p| p[..3].iter().zip(sky).any(|(a, b)| a.abs_diff(*b) > 12)).count();
    drawn as f64 / (rgba.len() / 4) as f64
}

/// Renders `archive` with its default view; the picture and what `render` said.
fn render(archive: &str, cwd: &Path, name: &str) -> (Vec<u8>, String) {
    let png = cwd.join(format!("{name}.png"));
    let said = ok(&["render", archive, "-o", png.to_str().unwrap(), &format!("--size={WIDTH}x{HEIGHT}")], cwd);
    let (w, h, rgba) = decode_png(&std::fs::read(&png).unwrap());
    assert_eq!((w, h), (WIDTH, HEIGHT));
    (rgba, said)
}

#[test]
fn regional_gdal2tiles_trees_draw_framed_on_their_data() {
    let dir = tempfile::tempdir().unwrap();
    let cwd = dir.path();
    let image = image_over(cwd, "region", [-122.7, 37.6, -122.2, 38.0]);
    let image = image.to_str().unwrap();
    // Web Mercator XYZ, zooms 9-11: the coarsest tiles are zoom 9's, far from zoom 0.
    tool("gdal2tiles.py", &["-q", "--xyz", "-z", "9-11", "-w", "none", image, "xyz"], cwd);
    ok(&["pack", "xyz", "--template", "{z}/{x}/{y}.png", "-o", "xyz.tspack"], cwd);
    let reader = Reader::open_mmap(cwd.join("xyz.tspack")).unwrap();
    let extent = reader.metadata().layers[0].extent.clone().expect("the layer says where its data is");
    assert_eq!((extent.finest_lod, extent.coarsest_lod), (0, 2), "zooms 11..9 on an 11-zoom grid");
    let [w, s, e, n] = extent.lon_lat.expect("Web Mercator bounds in degrees");
    // The finest tiles' box, within a zoom-11 tile (0.18 degrees) of the image.
    assert!((w - -122.7).abs() < 0.18 && (e - -122.2).abs() < 0.18, "{w} {e}");
    assert!((s - 37.6).abs() < 0.18 && (n - 38.0).abs() < 0.18, "{s} {n}");
    let info = ok(&["info", "xyz.tspack"], cwd);
    assert!(info.contains("data LOD0..=LOD2") && info.contains("122.") && info.contains("°W to 122."), "{info}");

    let (rgba, said) = render("xyz.tspack", cwd, "xyz");
    assert!(!said.contains(" 0 tiles fetched"), "{said}");
    assert_golden("extent-xyz-regional", WIDTH, HEIGHT, &rgba, TOLERANCE);
    let share = drawn_share(&rgba);
    assert!(share > 0.4, "the tree covers only {:.0} % of the frame: {said}", share * 100.0);

    // Geodetic TMS (2 x 1 tiles at zoom 0), zooms 8-10.
    tool("gdal2tiles.py", &["-q", "-p", "geodetic", "--tmscompatible", "-z", "8-10", "-w", "none", image, "tms"], cwd);
    ok(&["pack", "tms", "--template", "{z}/{x}/{y}.png", "--scheme", "tms", "-o", "tms.tspack"], cwd);
    let reader = Reader::open_mmap(cwd.join("tms.tspack")).unwrap();
    let g = reader.metadata().georeference.clone().unwrap();
    assert_eq!(g.crs.as_deref(), Some("EPSG:4326"));
    let [w, s, e, n] = reader.metadata().layers[0].extent.clone().unwrap().lon_lat.unwrap();
    let step = 180.0 / 1024.0; // a zoom-10 tile
    assert!((w - -122.7).abs() < step && (e - -122.2).abs() < step && (s - 37.6).abs() < step, "{w} {s} {e} {n}");
    let (rgba, said) = render("tms.tspack", cwd, "tms");
    assert_golden("extent-tms-regional", WIDTH, HEIGHT, &rgba, TOLERANCE);
    let share = drawn_share(&rgba);
    assert!(share > 0.4, "the tree covers only {:.0} % of the frame: {said}", share * 100.0);
}

/// A PNG tile of one colour, `size` pixels square.
fn solid_png(size: u32, rgb: [u8; 3]) -> Vec<u8> {
    let mut bytes = Vec::new();
    let mut encoder = png::Encoder::new(&mut bytes, size, size);
    encoder.set_color(png::ColorType::Rgb);
    let data: Vec<u8> = (0..size * size).flat_map(|_| rgb).collect();
    encoder.write_header().unwrap().write_image_data(&data).unwrap();
    bytes
}

#[test]
fn tiles_the_view_cannot_reach_fail_render_naming_the_layer() {
    let dir = tempfile::tempdir().unwrap();
    let cwd = dir.path();
    // A zoom-3 tile in the north-west and zoom-6 tiles far from it: no tile above them,
    // and no ancestor of theirs where the selection starts.
    let put = |z: u32, x: u32, y: u32| {
        let path = cwd.join(format!("tree/{z}/{x}/{y}.png"));
        std::fs::create_dir_all(path.parent().unwrap()).unwrap();
        std::fs::write(path, solid_png(32, [200, 80, 40])).unwrap();
    };
    put(3, 0, 0);
    for (x, y) in [(40, 40), (41, 40), (40, 41), (41, 41)] {
        put(6, x, y);
    }
    ok(&["pack", "tree", "--template", "{z}/{x}/{y}.png", "-o", "t.tspack"], cwd);
    let out = terrastream(&["render", "t.tspack", "-o", "t.png", &format!("--size={WIDTH}x{HEIGHT}")], cwd);
    let said = text(&out);
    assert_eq!(out.status.code(), Some(1), "{said}");
    assert!(said.contains("layer \"texture\"") && said.contains("could be fetched"), "{said}");
}

/// Terrarium RGB of a height: h + 32768 = R * 256 + G + B / 256, rounded to the nearest
/// 1/256.
fn terrarium(h: f64) -> [u8; 3] {
    let v = ((h + 32_768.0) * 256.0).round() as u32;
    [(v >> 16) as u8, (v >> 8) as u8, v as u8]
}

/// The committed DEM crop: heights (nodata and sea as `None`), its west and north edges
/// and its pixel size, in degrees.
struct Dem {
    heights: Vec<Option<f64>>,
    size: (usize, usize),
    west: f64,
    north: f64,
    step: f64,
}

impl Dem {
    fn read() -> Self {
        let path = terrastream_testkit::golden::repo().join("packer/pack/data/srtm-tamalpais-320-public-domain.tif");
        let mut decoder = tiff::decoder::Decoder::new(std::fs::File::open(path).unwrap()).unwrap();
        let (w, h) = decoder.dimensions().unwrap();
        let heights = match decoder.read_image().unwrap() {
            tiff::decoder::DecodingResult::I16(v) => {
                v.into_iter().map(|s| (s > -32_000).then_some(f64::from(s))).collect()
            }
            other => panic!("int16 expected, got {:?}", std::mem::discriminant(&other)),
        };
        // gdalinfo: origin (-122.641805..., 37.966805...), 1 arc-second pixels.
        Self {
            heights,
            size: (w as usize, h as usize),
            west: -122.641_805_555_555_55,
            north: 37.966_805_555_555_55,
            step: 1.0 / 3600.0,
        }
    }

    /// Bilinear height at (lon, lat) between pixel centres, `None` outside or by nodata.
    fn at(&self, lon: f64, lat: f64) -> Option<f64> {
        let (fx, fy) = ((lon - self.west) / self.step - 0.5, (self.north - lat) / self.step - 0.5);
        if fx < 0.0 || fy < 0.0 || fx >= (self.size.0 - 1) as f64 || fy >= (self.size.1 - 1) as f64 {
            return None;
        }
        let (x0, y0) = (fx.floor() as usize, fy.floor() as usize);
        let (tx, ty) = (fx - x0 as f64, fy - y0 as f64);
        let h = |x: usize, y: usize| self.heights[y * self.size.0 + x];
        let (a, b, c, d) = (h(x0, y0)?, h(x0 + 1, y0)?, h(x0, y0 + 1)?, h(x0 + 1, y0 + 1)?);
        Some((a * (1.0 - tx) + b * tx) * (1.0 - ty) + (c * (1.0 - tx) + d * tx) * ty)
    }
}

/// Longitude and latitude of a point of the Web Mercator zoom-`z` tile grid (in tiles).
fn lon_lat(z: u32, tx: f64, ty: f64) -> (f64, f64) {
    let n = f64::from(1u32 << z);
    let lon = tx / n * 360.0 - 180.0;
    let lat = (std::f64::consts::PI * (1.0 - 2.0 * ty / n)).sinh().atan().to_degrees();
    (lon, lat)
}

const TILE: u32 = 256;

/// Writes the DEM's heights as a Web Mercator XYZ tree of lossless Terrarium WebP tiles
/// (zooms `zooms`; pixels outside the data transparent).
fn terrarium_tree(dem: &Dem, root: &Path, zooms: std::ops::RangeInclusive<u32>) {
    let (east, south) = (dem.west + dem.size.0 as f64 * dem.step, dem.north - dem.size.1 as f64 * dem.step);
    for z in zooms {
        let n = f64::from(1u32 << z);
        let col = |lon: f64| ((lon + 180.0) / 360.0 * n).floor() as u32;
        let row = |lat: f64| {
            let r = lat.to_radians();
            ((1.0 - (r.tan() + 1.0 / r.cos()).ln() / std::f64::consts::PI) / 2.0 * n).floor() as u32
        };
        for ty in row(dem.north)..=row(south) {
            for tx in col(dem.west)..=col(east) {
                let mut rgba = Vec::with_capacity((TILE * TILE * 4) as usize);
                for j in 0..TILE {
                    for i in 0..TILE {
                        let (lon, lat) = lon_lat(
                            z,
                            f64::from(tx) + (f64::from(i) + 0.5) / f64::from(TILE),
                            f64::from(ty) + (f64::from(j) + 0.5) / f64::from(TILE),
                        );
                        match dem.at(lon, lat) {
                            Some(h) => rgba.extend(terrarium(h).into_iter().chain([255])),
                            None => rgba.extend([0, 0, 0, 0]),
                        }
                    }
                }
                let path = root.join(format!("{z}/{tx}/{ty}.webp"));
                std::fs::create_dir_all(path.parent().unwrap()).unwrap();
                let mut webp = Vec::new();
                image_webp::WebPEncoder::new(&mut webp)
                    .encode(&rgba, TILE, TILE, image_webp::ColorType::Rgba8)
                    .unwrap();
                std::fs::write(path, webp).unwrap();
            }
        }
    }
}

#[test]
fn a_terrarium_pmtiles_and_an_imagery_tree_become_one_archive() {
    let dir = tempfile::tempdir().unwrap();
    let cwd = dir.path();
    let dem = Dem::read();
    // Heights: Terrarium WebP at zooms 11-14, made a PMTiles (as planet-wide terrain is
    // published) by way of an archive and `export`.
    terrarium_tree(&dem, &cwd.join("heights"), 11..=14);
    ok(
        &[
            "pack",
            "heights",
            "--template",
            "{z}/{x}/{y}.webp",
            "--kind",
            "elevation",
            "--elevation-encoding",
            "terrarium",
            "-o",
            "heights.tspack",
        ],
        cwd,
    );
    ok(&["export", "heights.tspack", "--layer", "elevation", "--to", "pmtiles", "-o", "heights.pmtiles"], cwd);
    // Imagery: gdal2tiles of an image over the same area, one zoom deeper.
    let (east, south) = (dem.west + 320.0 * dem.step, dem.north - 320.0 * dem.step);
    let image = image_over(cwd, "imagery", [dem.west, south, east, dem.north]);
    tool("gdal2tiles.py", &["-q", "--xyz", "-z", "12-15", "-w", "none", image.to_str().unwrap(), "imagery"], cwd);

    let said = ok(
        &[
            "pack",
            "--elevation",
            "heights.pmtiles",
            "--elevation-encoding",
            "terrarium",
            "--texture",
            "imagery",
            "--texture-template",
            "{z}/{x}/{y}.png",
            "-o",
            "both.tspack",
        ],
        cwd,
    );
    assert!(said.contains("in 2 layers"), "{said}");
    let reader = Reader::open_mmap(cwd.join("both.tspack")).unwrap();
    let m = reader.metadata().clone();
    let kinds: Vec<LayerKind> = m.layers.iter().map(|l| l.kind).collect();
    assert_eq!(kinds, [LayerKind::Elevation, LayerKind::Texture]);
    assert_eq!((m.layers[0].num_lods, m.layers[1].num_lods), (15, 16), "grids of zooms 0-14 and 0-15");
    // The height range is read from the tiles: the crop's 0..~780 m.
    assert!(m.terrain.min_elevation >= -1.0 && m.terrain.min_elevation < 60.0, "{:?}", m.terrain);
    assert!(m.terrain.max_elevation > 700.0 && m.terrain.max_elevation < 800.0, "{:?}", m.terrain);

    // Heights at 20 pixel centres of zoom 14 are the source's within one Terrarium step.
    let mut streamer =
        Streamer::open(Origin::parse(cwd.join("both.tspack").to_str().unwrap()).unwrap(), StreamOptions::default())
            .unwrap();
    let elevation = &m.layers[0];
    let tile_size = elevation.tile_world_size;
    let (x0, y0, x1, y1) = elevation.data_tiles_at(0);
    let mut compared = 0;
    let mut seed = 7u64;
    let mut next = |n: u32| {
        seed = seed.wrapping_mul(6_364_136_223_846_793_005).wrapping_add(1_442_695_040_888_963_407);
        ((seed >> 33) % u64::from(n)) as u32
    };
    while compared < 20 {
        let (tx, ty) = (x0 + next(x1 - x0 + 1), y0 + next(y1 - y0 + 1));
        let (i, j) = (next(TILE), next(TILE));
        let (fx, fy) = (f64::from(tx) + (f64::from(i) + 0.5) / 256.0, f64::from(ty) + (f64::from(j) + 0.5) / 256.0);
        let (lon, lat) = lon_lat(14, fx, fy);
        let Some(want) = dem.at(lon, lat) else { continue };
        assert!(reader.tile(TileKey::new(0, 0, tx, ty).unwrap()).unwrap().is_some());
        let got = streamer.height_at_exact(fx * tile_size, fy * tile_size).unwrap().expect("a height in the data");
        assert!((got - want).abs() <= 1.0 / 256.0 + 1e-9, "z14 tile {tx},{ty} pixel {i},{j}: {got} vs {want}");
        compared += 1;
    }

    let (rgba, said) = render("both.tspack", cwd, "both");
    assert_golden("extent-terrarium-and-imagery", WIDTH, HEIGHT, &rgba, TOLERANCE);
    let share = drawn_share(&rgba);
    assert!(share > 0.4, "the terrain covers only {:.0} % of the frame: {said}", share * 100.0);

    // Pyramids on other CRSs cannot be one archive: named.
    tool("gdal2tiles.py", &["-q", "-p", "geodetic", "-z", "10-11", "-w", "none", image.to_str().unwrap(), "geo"], cwd);
    let out = terrastream(
        &["pack", "--elevation", "heights.pmtiles", "--texture", "geo", "--scheme", "tms", "-o", "bad.tspack"],
        cwd,
    );
    let said = text(&out);
    assert!(!out.status.success() && said.contains("geo") && said.contains("EPSG:4326"), "{said}");
    assert!(!cwd.join("bad.tspack").exists());
}

#[test]
fn extract_of_a_bordered_archive_packs_back_to_the_same_tiles() {
    let dir = tempfile::tempdir().unwrap();
    let cwd = dir.path();
    let image =
        image_over(cwd, "ortho", [-122.641_805_555_555_55, 37.878_0, -122.552_916_666_666_66, 37.966_805_555_555_55]);
    // Imagery alone: the original layout's folders hold images (elevation tiles of the
    // tiler are stored samples, packed back by `merge`, not by `pack`).
    ok(
        &["tile", "--texture", image.to_str().unwrap(), "--texture-tile-size", "64", "--border", "1", "-o", "b.tspack"],
        cwd,
    );
    // The tiler records where the imagery lies, in degrees, whatever grid it made.
    let tiled = Reader::open_mmap(cwd.join("b.tspack")).unwrap();
    let [w, s, e, n] = tiled.metadata().layers[0].extent.clone().unwrap().lon_lat.expect("degrees");
    let near = |a: f64, b: f64| (a - b).abs() < 2e-4;
    assert!(
        near(w, -122.641_805) && near(s, 37.878) && near(e, -122.552_916) && near(n, 37.966_805),
        "{w} {s} {e} {n}"
    );
    ok(&["extract", "b.tspack", "--layout", "original", "-o", "out"], cwd);
    ok(&["pack", "out", "-o", "back.tspack"], cwd);
    let (a, b) =
        (Reader::open_mmap(cwd.join("b.tspack")).unwrap(), Reader::open_mmap(cwd.join("back.tspack")).unwrap());
    let texture = |r: &Reader<terrastream_format::MmapSource>| {
        r.metadata().layers.iter().position(|l| l.kind == LayerKind::Texture).unwrap()
    };
    let (ta, tb) = (texture(&a), texture(&b));
    let (la, lb) = (&a.metadata().layers[ta], &b.metadata().layers[tb]);
    assert_eq!((lb.tile_resolution, lb.border), (la.tile_resolution, la.border), "the layer comes back as it was");
    let mut compared = 0;
    for lod in 0..la.num_lods {
        for key in la.tiles_at(ta as u8, lod) {
            let Some(want) = a.tile(key).unwrap() else { continue };
            let got = b.tile(TileKey::new(tb as u8, lod, key.x(), key.y()).unwrap()).unwrap();
            assert_eq!(got.as_deref(), Some(&want[..]), "{key}");
            compared += 1;
        }
    }
    assert!(compared > 4, "{compared} tiles compared");
}
