//! What the client tests share: the committed 1" SRTM crop tiled as `terrastream tile`
//! does by default, GDAL's bilinear heights of it (the oracle), random points, error
//! percentiles, and the snippets of `docs/clients.md` (the documented code is the code run).
#![allow(dead_code, clippy::cast_possible_truncation)]

use std::path::{Path, PathBuf};
use std::process::{Command, Stdio};

/// The DEM the client tests read.
pub const DEM: &str = "packer/pack/data/srtm-tamalpais-320-public-domain.tif";

pub fn repo() -> PathBuf {
    terrastream_testkit::golden::repo()
}

/// The npm cache `scripts/test.sh` fills with the browser clients' packages.
pub fn npm_cache() -> PathBuf {
    std::env::var_os("TERRASTREAM_NPM")
        .map(PathBuf::from)
        .unwrap_or_else(|| PathBuf::from(std::env::var_os("HOME").unwrap_or_default()).join(".cache/terrastream-npm"))
}

pub fn terrastream(args: &[&str]) {
    let out = Command::new(env!("CARGO_BIN_EXE_terrastream")).arg("-q").args(args).output().unwrap();
    assert!(out.status.success(), "terrastream {args:?}: {}", String::from_utf8_lossy(&out.stderr));
}

/// `terrastream args`, with a private runtime folder for lavapipe (`dir` where the
/// environment names none).
pub fn run_in(args: &[&str], dir: &Path) -> std::process::Output {
    Command::new(env!("CARGO_BIN_EXE_terrastream"))
        .args(args)
        .env("XDG_RUNTIME_DIR", std::env::var_os("XDG_RUNTIME_DIR").unwrap_or_else(|| dir.into()))
        .output()
        .unwrap()
}

/// [`run_in`], which must succeed: its standard output.
pub fn ok_in(args: &[&str], dir: &Path) -> String {
    let out = run_in(args, dir);
    let said = String::from_utf8_lossy(&out.stdout).into_owned();
    assert!(out.status.success(), "terrastream {args:?}: {said}{}", String::from_utf8_lossy(&out.stderr));
    said
}

/// The DEM tiled as `terrastream tile` does by default, in `dir`, its heights named as
/// SRTM's are: above the EGM96 geoid (EPSG:5773).
pub fn archive(dir: &Path) -> PathBuf {
    let path = dir.join("tamalpais.tspack");
    let dem = repo().join(DEM);
    terrastream(&[
        "tile",
        "--elevation",
        dem.to_str().unwrap(),
        "-o",
        path.to_str().unwrap(),
        "--vertical-datum",
        "5773",
    ]);
    path
}

/// PROJ's EGM96 undulation N at each point (lon, lat): `cct` shifting a zero height by
/// the grid `egm96_15.gtx` (Debian `proj-data`), named explicitly.
pub fn proj_undulation(points: &[(f64, f64)]) -> Vec<f64> {
    let input: String = points.iter().map(|(lon, lat)| format!("{lon} {lat} 0 0\n")).collect();
    let mut child = Command::new("cct")
        .args(["-d", "6", "+proj=vgridshift", "+grids=egm96_15.gtx", "+multiplier=1"])
        .stdin(Stdio::piped())
        .stdout(Stdio::piped())
        .stderr(Stdio::inherit())
        .spawn()
        .expect("PROJ's cct (apt-get install proj-bin)");
    std::io::Write::write_all(&mut child.stdin.take().unwrap(), input.as_bytes()).unwrap();
    let out = child.wait_with_output().unwrap();
    assert!(out.status.success(), "cct");
    let n: Vec<f64> = String::from_utf8(out.stdout)
        .unwrap()
        .lines()
        .map(|l| l.split_whitespace().nth(2).unwrap().parse().unwrap())
        .collect();
    assert_eq!(n.len(), points.len(), "cct answered {} of {} points", n.len(), points.len());
    n
}

/// `count` points (lon, lat) spread at random over the middle 80 % of `bounds`.
pub fn random_points(bounds: [f64; 4], count: usize) -> Vec<(f64, f64)> {
    let mut state = 0x2545_f491_4f6c_dd1du64;
    let mut next = || {
        state ^= state << 13;
        state ^= state >> 7;
        state ^= state << 17;
        (state >> 11) as f64 / (1u64 << 53) as f64
    };
    let [w, s, e, n] = bounds;
    (0..count).map(|_| (w + (e - w) * (0.1 + 0.8 * next()), s + (n - s) * (0.1 + 0.8 * next()))).collect()
}

/// GDAL's bilinear height of the source at each point: the point's fractional pixel
/// position (`gdaltransform -i`), the four samples around it (`gdallocationinfo`), and
/// their bilinear mean, computed here (GDAL 3.6's tools have no bilinear option).
pub fn gdal_bilinear(points: &[(f64, f64)]) -> Vec<f64> {
    let dem = repo().join(DEM);
    let run = |program: &str, args: &[&str], input: String| -> String {
        let mut child = Command::new(program)
            .args(args)
            .stdin(Stdio::piped())
            .stdout(Stdio::piped())
            .stderr(Stdio::inherit())
            .spawn()
            .unwrap();
        std::io::Write::write_all(&mut child.stdin.take().unwrap(), input.as_bytes()).unwrap();
        let out = child.wait_with_output().unwrap();
        assert!(out.status.success(), "{program} {args:?}");
        String::from_utf8(out.stdout).unwrap()
    };
    let lonlat: String = points.iter().map(|(lon, lat)| format!("{lon} {lat}\n")).collect();
    let pixels: Vec<(f64, f64)> = run("gdaltransform", &["-i", dem.to_str().unwrap()], lonlat)
        .lines()
        .map(|l| {
            let v: Vec<f64> = l.split_whitespace().map(|v| v.parse().unwrap()).collect();
            (v[0] - 0.5, v[1] - 0.5)
        })
        .collect();
    let mut corners = String::new();
    for (px, py) in &pixels {
        let (i, j) = (px.floor() as i64, py.floor() as i64);
        for (di, dj) in [(0, 0), (1, 0), (0, 1), (1, 1)] {
            corners.push_str(&format!("{} {}\n", i + di, j + dj));
        }
    }
    let values: Vec<f64> = run("gdallocationinfo", &["-valonly", dem.to_str().unwrap()], corners)
        .lines()
        .map(|l| l.trim().parse().unwrap())
        .collect();
    pixels
        .iter()
        .zip(values.chunks_exact(4))
        .map(|((px, py), v)| {
            let (fx, fy) = (px - px.floor(), py - py.floor());
            v[0] * (1.0 - fx) * (1.0 - fy) + v[1] * fx * (1.0 - fy) + v[2] * (1.0 - fx) * fy + v[3] * fx * fy
        })
        .collect()
}

/// The median and the 90th percentile of |a - b|.
pub fn errors(a: &[f64], b: &[f64]) -> (f64, f64) {
    let mut e: Vec<f64> = a.iter().zip(b).map(|(x, y)| (x - y).abs()).collect();
    e.sort_by(f64::total_cmp);
    (e[e.len() / 2], e[e.len() * 9 / 10])
}

/// The fenced block that follows `<!-- snippet: NAME -->` in `docs/clients.md`: the
/// documented snippets are the ones run here.
pub fn snippet(name: &str) -> String {
    let doc = std::fs::read_to_string(repo().join("docs/clients.md")).unwrap();
    let marker = format!("<!-- snippet: {name} -->");
    let after = &doc[doc.find(&marker).unwrap_or_else(|| panic!("docs/clients.md has no snippet {name}"))..];
    let start = after.find("```").unwrap();
    let body = &after[start..];
    let body = &body[body.find('\n').unwrap() + 1..];
    body[..body.find("```").unwrap()].to_owned()
}

/// Everest's summit, longitude and latitude (degrees).
pub const EVEREST: (f64, f64) = (86.9250, 27.9881);
/// Its height, metres.
pub const SUMMIT: f64 = 8848.86;

/// A peak whose top is the summit at Everest's coordinates, rippled 40 m.
pub fn everest_height(lon: f64, lat: f64) -> f64 {
    let dx = (lon - EVEREST.0) * 111_320.0 * EVEREST.1.to_radians().cos();
    let dy = (lat - EVEREST.1) * 110_950.0;
    let r2 = (dx * dx + dy * dy) / (3_000.0f64 * 3_000.0);
    1200.0 + (SUMMIT - 1240.0) * (-r2).exp() + 40.0 * (dx / 37.0).cos() * (dy / 31.0).cos()
}

/// An ESRI ASCII grid of `degrees` x `degrees` from (`west`, `south`) with `per_degree`
/// samples a degree, turned into a GeoTIFF by GDAL.
pub fn dem(dir: &Path, west: f64, south: f64, degrees: f64, per_degree: f64) -> PathBuf {
    grid_tif(dir, &format!("dem-{degrees}"), [west, south, degrees, per_degree], &everest_height)
}

/// A sea stored as a flat 0 with an island in its north-east corner, 720 samples a side
/// (three tiles of 256 across): `dir/sea.tif` and its west, south and side in degrees, and
/// the corner where its first tiles meet (longitude, latitude).
pub fn sea_dem(dir: &Path) -> (PathBuf, [f64; 3], (f64, f64)) {
    let (west, south, degrees, per_degree) = (-20.2, 30.0, 0.3, 2400.0);
    let island = |lon: f64, lat: f64| {
        let d = ((lon - (west + 0.27)).powi(2) + (lat - (south + 0.27)).powi(2)).sqrt();
        (300.0 - d * 20_000.0).max(0.0)
    };
    let corner = (west + 256.0 / per_degree, south + degrees - 256.0 / per_degree);
    (grid_tif(dir, "sea", [west, south, degrees, per_degree], &island), [west, south, degrees], corner)
}

/// The radius in degrees of the lake [`lake_mask`] draws.
#[allow(dead_code, reason = "not every test binary uses it")]
pub const LAKE_RADIUS: f64 = 0.012;

/// A water mask for [`coast_dem`]'s land (`bounds` its west, south and size): a lake of
/// [`LAKE_RADIUS`] filling its basin (30 m below sea level, like the Dead Sea: no flat 0
/// says it is water), no data over the sea; rasterized in degrees, then warped by GDAL to
/// UTM zone 28 at 20 m with an area average (the shore holds fractions). Returns the mask
/// and the lake's centre (lon, lat).
#[allow(dead_code, reason = "not every test binary uses it")]
pub fn lake_mask(dir: &Path, [west, south, degrees]: [f64; 3]) -> (PathBuf, (f64, f64)) {
    let mid = west + degrees / 2.0;
    let centre = (mid + 0.025, south + 0.05);
    let lake = |lon: f64, lat: f64| {
        if lon < mid {
            return -9999.0;
        }
        if (lon - centre.0).hypot(lat - centre.1) < LAKE_RADIUS { 1.0 } else { 0.0 }
    };
    let degrees_mask = grid_tif(dir, "lake-degrees", [west, south, degrees, 2400.0], &lake);
    let mask = dir.join("lake-utm.tif");
    let out = Command::new("gdalwarp")
        .args(["-q", "-overwrite", "-t_srs", "EPSG:32628", "-tr", "20", "20", "-r", "average"])
        .args(["-srcnodata", "-9999", "-dstnodata", "-1"])
        .args([degrees_mask.to_str().unwrap(), mask.to_str().unwrap()])
        .output()
        .unwrap();
    assert!(out.status.success(), "gdalwarp: {}", String::from_utf8_lossy(&out.stderr));
    (mask, centre)
}

/// A geographic Float32 GeoTIFF `dir/{name}.tif` (GDAL's `gdal_translate` of an ASCII
/// grid), `degrees` a side from `west`, `south` at `per_degree` samples a degree, of
/// `height` at each sample's centre (longitude, latitude).
#[allow(dead_code, reason = "not every test binary uses it")]
pub fn grid_tif(
    dir: &Path,
    name: &str,
    [west, south, degrees, per_degree]: [f64; 4],
    height: &dyn Fn(f64, f64) -> f64,
) -> PathBuf {
    let n = (degrees * per_degree).round() as usize;
    let cell = 1.0 / per_degree;
    let mut asc =
        format!("ncols {n}\nnrows {n}\nxllcorner {west}\nyllcorner {south}\ncellsize {cell:.12}\nNODATA_value -9999\n");
    for row in 0..n {
        let lat = south + degrees - (row as f64 + 0.5) * cell;
        let line: Vec<String> =
            (0..n).map(|col| format!("{:.2}", height(west + (col as f64 + 0.5) * cell, lat))).collect();
        asc.push_str(&line.join(" "));
        asc.push('\n');
    }
    let source = dir.join(format!("{name}.asc"));
    std::fs::write(&source, asc).unwrap();
    let tif = dir.join(format!("{name}.tif"));
    let out = Command::new("gdal_translate")
        .args(["-q", "-a_srs", "EPSG:4326", "-ot", "Float32"])
        .args([source.to_str().unwrap(), tif.to_str().unwrap()])
        .output()
        .unwrap();
    assert!(out.status.success(), "gdal_translate: {}", String::from_utf8_lossy(&out.stderr));
    tif
}

/// A coast, made a GeoTIFF by GDAL: 0.1 x 0.1 degrees at 1.5" from 20.05°W 30°N, the west
/// half a flat sea stored as 0 (as SRTM and Copernicus store it), the east half land
/// rising from 2 m, with a round basin 30 m below sea level in it (centre 0.025° east of
/// the coast, 0.05° north of the south edge, radius 0.012°). Returns the file and its
/// west, south and size in degrees.
#[allow(dead_code, reason = "not every test binary uses it")]
pub fn coast_dem(dir: &Path) -> (PathBuf, [f64; 3]) {
    let (west, south, degrees, per_degree) = (-20.05, 30.0, 0.1, 2400.0);
    let mid = west + degrees / 2.0;
    let height = |lon: f64, lat: f64| {
        if lon < mid {
            return 0.0;
        }
        let basin = ((lon - (mid + 0.025)).powi(2) + (lat - (south + 0.05)).powi(2)).sqrt() < 0.012;
        if basin { -30.0 } else { 2.0 + (lon - mid) * 8000.0 + ((lat * 300.0).sin() * 5.0).abs() }
    };
    (grid_tif(dir, "coast", [west, south, degrees, per_degree], &height), [west, south, degrees])
}
