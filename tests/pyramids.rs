//! Real tile trees from outside the project: a geodetic pyramid (2x1 tiles at zoom 0, as
//! `gdal2tiles.py -p geodetic --tmscompatible` and TMS global-geodetic caches make it) of
//! one-component (gray) JPEG tiles, in the gdal2tiles layout and in a layout of row
//! folders holding `row_col` names. Each packs, extracts byte for byte, and renders: as
//! terrain at a flat height (there is no elevation layer), compared with a reference.
#![allow(clippy::unwrap_used, clippy::expect_used, clippy::cast_possible_truncation, missing_docs)]

#[path = "support/cli.rs"]
mod cli;

use std::collections::BTreeMap;
use std::path::{Path, PathBuf};
use std::process::Output;

const TILE: u16 = 64;
/// lavapipe's output, rendered on another Mesa release: see tests/golden/README.md.
const TOLERANCE: terrastream_testkit::golden::Tolerance =
    terrastream_testkit::golden::Tolerance { mean: 1.5, pixel: 24, off_share: 0.015 };

fn terrastream(args: &[&str], cwd: &Path) -> Output {
    cli::terrastream().args(args).current_dir(cwd).output().unwrap()
}

fn text(o: &Output) -> String {
    format!("{}{}", String::from_utf8_lossy(&o.stdout), String::from_utf8_lossy(&o.stderr))
}

/// The gray level of the world at (lon, lat): 30-degree checkers, brighter to the north
/// and east, with the equator and the prime meridian drawn white.
fn gray(lon: f64, lat: f64) -> u8 {
    if lon.abs() < 1.5 || lat.abs() < 1.5 {
        return 255;
    }
    let checker = ((lon / 30.0).floor() + (lat / 30.0).floor()).rem_euclid(2.0);
    (40.0 + checker * 90.0 + (lon + 180.0) / 360.0 * 60.0 + (lat + 90.0) / 180.0 * 50.0) as u8
}

/// A geodetic TMS tree of gray JPEG tiles, zooms 0..=2 (2x1, 4x2, 8x4 tiles; row 0 at the
/// south): every file by its (z, x, y).
fn geodetic_tiles() -> BTreeMap<(u32, u32, u32), Vec<u8>> {
    let mut tiles = BTreeMap::new();
    for z in 0..=2u32 {
        let degrees = 180.0 / f64::from(1u32 << z);
        for x in 0..2u32 << z {
            for y in 0..1u32 << z {
                let (west, south) = (-180.0 + f64::from(x) * degrees, -90.0 + f64::from(y) * degrees);
                let pixels: Vec<u8> = (0..TILE)
                    .flat_map(|row| (0..TILE).map(move |col| (row, col)))
                    .map(|(row, col)| {
                        let lon = west + (f64::from(col) + 0.5) / f64::from(TILE) * degrees;
                        let lat = south + degrees - (f64::from(row) + 0.5) / f64::from(TILE) * degrees;
                        gray(lon, lat)
                    })
                    .collect();
                let mut jpeg = Vec::new();
                jpeg_encoder::Encoder::new(&mut jpeg, 90)
                    .encode(&pixels, TILE, TILE, jpeg_encoder::ColorType::Luma)
                    .unwrap();
                tiles.insert((z, x, y), jpeg);
            }
        }
    }
    tiles
}

fn write_tree(root: &Path, tiles: &BTreeMap<(u32, u32, u32), Vec<u8>>, name: impl Fn(u32, u32, u32) -> String) {
    for (&(z, x, y), bytes) in tiles {
        let path = root.join(name(z, x, y));
        std::fs::create_dir_all(path.parent().unwrap()).unwrap();
        std::fs::write(path, bytes).unwrap();
    }
}

fn files(root: &Path) -> BTreeMap<PathBuf, Vec<u8>> {
    let mut out = BTreeMap::new();
    let mut stack = vec![root.to_path_buf()];
    while let Some(dir) = stack.pop() {
        for entry in std::fs::read_dir(&dir).unwrap() {
            let path = entry.unwrap().path();
            if path.is_dir() {
                stack.push(path);
            } else {
                out.insert(path.strip_prefix(root).unwrap().to_path_buf(), std::fs::read(&path).unwrap());
            }
        }
    }
    out
}

/// Packs `tree` with `template` (TMS rows), checks the grid and the georeference, extracts
/// it byte for byte; the archive.
fn pack_and_extract(work: &Path, tree: &str, template: &str) -> PathBuf {
    let archive = work.join(format!("{tree}.tspack"));
    let out =
        terrastream(&["pack", tree, "--template", template, "--scheme", "tms", "-o", archive.to_str().unwrap()], work);
    assert!(out.status.success(), "pack {tree}: {}", text(&out));
    let out = terrastream(&["info", archive.to_str().unwrap(), "--json"], work);
    assert!(out.status.success(), "{}", text(&out));
    let info: serde_json::Value = serde_json::from_slice(&out.stdout).unwrap();
    let metadata = &info["metadata"];
    let layer = &metadata["layers"][0];
    assert_eq!((&layer["num_x_tiles"], &layer["num_y_tiles"], &layer["num_lods"]), (&8.into(), &4.into(), &3.into()));
    assert_eq!(metadata["georeference"]["crs"], "EPSG:4326", "{metadata}");
    let back = work.join(format!("{tree}-extracted"));
    let out =
        terrastream(&["extract", archive.to_str().unwrap(), "-o", back.to_str().unwrap(), "--layout", "xyz"], work);
    assert!(out.status.success(), "{}", text(&out));
    assert_eq!(files(&back), files(&work.join(tree)), "{tree}: extracted files differ from the packed ones");
    archive
}

#[test]
fn a_geodetic_tree_of_gray_jpegs_packs_extracts_and_renders() {
    let dir = tempfile::tempdir().unwrap();
    let work = dir.path();
    let tiles = geodetic_tiles();
    // gdal2tiles' layout, and row folders of row_col names, zero-padded.
    write_tree(&work.join("gdal2tiles"), &tiles, |z, x, y| format!("{z}/{x}/{y}.jpg"));
    write_tree(&work.join("rows"), &tiles, |z, x, y| format!("{z}/{y:06}/{y:06}_{x:06}.jpg"));
    let a = pack_and_extract(work, "gdal2tiles", "{z}/{x}/{y}.jpg");
    let b = pack_and_extract(work, "rows", "{z}/{y:06}/{y:06}_{x:06}.jpg");

    let png = work.join("geodetic.png");
    let out = terrastream(&["render", a.to_str().unwrap(), "-o", png.to_str().unwrap(), "--size", "480x270"], work);
    assert!(out.status.success(), "{}", text(&out));
    assert!(text(&out).contains("patches"), "{}", text(&out));
    let (w, h, rgba) = terrastream_testkit::golden::decode_png(&std::fs::read(&png).unwrap());
    terrastream_testkit::golden::assert_golden("geodetic-gray-jpeg", w, h, &rgba, TOLERANCE);
    // The picture is gray terrain (R = G = B) over most of the frame, with both checker
    // shades: a texture drawn, not the untextured tint or the sky.
    let sky = &rgba[..3];
    let terrain: Vec<&[u8]> =
        rgba.chunks_exact(4).filter(|p| p[..3].iter().zip(sky).any(|(a, b)| a.abs_diff(*b) > 12)).collect();
    assert!(terrain.len() as f64 > 0.35 * f64::from(w * h), "{} terrain pixels", terrain.len());
    let grayish = terrain.iter().filter(|p| p[0].abs_diff(p[1]) <= 6 && p[1].abs_diff(p[2]) <= 6).count();
    assert!(grayish as f64 > 0.9 * terrain.len() as f64, "{grayish} of {} terrain pixels gray", terrain.len());
    // Both layouts give the same tiles: the same picture.
    let png_b = work.join("rows.png");
    let out = terrastream(&["render", b.to_str().unwrap(), "-o", png_b.to_str().unwrap(), "--size", "480x270"], work);
    assert!(out.status.success(), "{}", text(&out));
    assert_eq!(terrastream_testkit::golden::decode_png(&std::fs::read(&png_b).unwrap()).2, rgba);
}

/// A tile beyond the grid the coarsest zoom implies is refused, naming the file, and
/// nothing is written.
#[test]
fn a_tile_outside_the_implied_grid_is_refused() {
    let dir = tempfile::tempdir().unwrap();
    let work = dir.path();
    let tiles = geodetic_tiles();
    write_tree(&work.join("tree"), &tiles, |z, x, y| format!("{z}/{x}/{y}.jpg"));
    // Zoom 1 of a 2x1 top is 4x2: x = 4 lies outside.
    std::fs::create_dir_all(work.join("tree/1/4")).unwrap();
    std::fs::write(work.join("tree/1/4/0.jpg"), &tiles[&(1, 0, 0)]).unwrap();
    let out = terrastream(&["pack", "tree", "--template", "{z}/{x}/{y}.jpg", "-o", "out.tspack"], work);
    assert!(!out.status.success());
    let said = text(&out);
    assert!(said.contains("1/4/0.jpg") && said.contains("4x2"), "{said}");
    assert!(!work.join("out.tspack").exists());
}
