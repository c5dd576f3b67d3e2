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

/// The DEM tiled as `terrastream tile` does by default, in `dir`.
pub fn archive(dir: &Path) -> PathBuf {
    let path = dir.join("tamalpais.tspack");
    let dem = repo().join(DEM);
    terrastream(&["tile", "--elevation", dem.to_str().unwrap(), "-o", path.to_str().unwrap()]);
    path
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
