//! The tiler's coordinate transforms against PROJ's own `cs2cs` (Debian `proj-bin`): a grid
//! of points in the area of each CRS the tiler is documented to read agrees within 1 cm
//! (projected) or 1e-7 degrees (geographic), both ways.
#![allow(clippy::unwrap_used, clippy::expect_used, missing_docs)]

use std::io::Write;
use std::process::{Command, Stdio};

use terrastream_crs::{Crs, Transform};

/// EPSG code, and the area of use to sample (west, south, east, north, degrees).
const CASES: &[(u16, [f64; 4])] = &[
    (4326, [-179.0, -85.0, 179.0, 85.0]),
    (4269, [-170.0, 15.0, -50.0, 80.0]),
    (32610, [-126.0, 1.0, -120.0, 80.0]),
    (32633, [12.0, 1.0, 18.0, 80.0]),
    (32733, [12.0, -79.0, 18.0, -1.0]),
    (32756, [150.0, -79.0, 156.0, -1.0]),
    (26910, [-126.0, 31.0, -120.0, 70.0]),
    (26917, [-84.0, 24.0, -78.0, 60.0]),
    (3857, [-179.0, -84.0, 179.0, 84.0]),
    (2056, [6.0, 45.9, 10.4, 47.7]),
    (27700, [-7.5, 50.0, 1.7, 60.5]),
    (25832, [6.0, 38.0, 12.0, 80.0]),
];

fn cs2cs() -> Option<()> {
    match Command::new("cs2cs").stdin(Stdio::null()).stdout(Stdio::null()).stderr(Stdio::null()).status() {
        Ok(_) => Some(()),
        Err(_) => {
            assert!(std::env::var_os("CI").is_none(), "cs2cs is not installed (apt-get install proj-bin)");
            eprintln!("\n*** SKIPPING: cs2cs is not installed (apt-get install proj-bin) ***\n");
            None
        }
    }
}

/// `cs2cs` on `points` (in the axis order of `from` as PROJ's EPSG definitions say:
/// latitude first for geographic CRSs), `-d 10` decimals.
fn oracle(from: &str, to: &str, points: &[(f64, f64)]) -> Vec<(f64, f64)> {
    let mut child = Command::new("cs2cs")
        .args(["-d", "10", from, to])
        .stdin(Stdio::piped())
        .stdout(Stdio::piped())
        .spawn()
        .unwrap();
    {
        let mut stdin = child.stdin.take().unwrap();
        for (a, b) in points {
            writeln!(stdin, "{a:.12} {b:.12}").unwrap();
        }
    }
    let out = child.wait_with_output().unwrap();
    String::from_utf8(out.stdout)
        .unwrap()
        .lines()
        .map(|l| {
            let v: Vec<f64> = l.split_whitespace().take(2).map(|x| x.parse().unwrap()).collect();
            (v[0], v[1])
        })
        .collect()
}

fn grid([w, s, e, n]: [f64; 4]) -> Vec<(f64, f64)> {
    let steps = 6;
    (0..=steps)
        .flat_map(|i| (0..=steps).map(move |j| (i, j)))
        .map(|(i, j)| (w + (e - w) * f64::from(i) / f64::from(steps), s + (n - s) * f64::from(j) / f64::from(steps)))
        .collect()
}

#[test]
fn transforms_agree_with_proj_both_ways() {
    if cs2cs().is_none() {
        return;
    }
    let wgs84 = Crs::wgs84();
    for &(code, area) in CASES {
        let crs = Crs::epsg(code).unwrap();
        let (geographic, tolerance) = if crs.is_geographic() { (true, 1e-7) } else { (false, 0.01) };
        let lon_lat = grid(area);
        // Forward: WGS 84 -> the CRS.
        let forward = Transform::new(&wgs84, &crs);
        let ours: Vec<(f64, f64)> = lon_lat.iter().map(|&(x, y)| forward.apply(x, y).unwrap()).collect();
        let lat_lon: Vec<(f64, f64)> = lon_lat.iter().map(|&(x, y)| (y, x)).collect();
        let proj = oracle("EPSG:4326", &format!("EPSG:{code}"), &lat_lon);
        for ((p, o), q) in lon_lat.iter().zip(&ours).zip(&proj) {
            // PROJ gives geographic CRSs latitude first.
            let q = if geographic { (q.1, q.0) } else { *q };
            let d = (o.0 - q.0).abs().max((o.1 - q.1).abs());
            assert!(d <= tolerance, "EPSG:{code} at {p:?}: ours {o:?}, PROJ {q:?} ({d:e} apart)");
        }
        // Inverse: the CRS -> WGS 84, from PROJ's own coordinates.
        let inverse = Transform::new(&crs, &wgs84);
        let input: Vec<(f64, f64)> = proj.iter().map(|q| if geographic { (q.1, q.0) } else { *q }).collect();
        let back = oracle(&format!("EPSG:{code}"), "EPSG:4326", &proj);
        for (p, q) in input.iter().zip(&back) {
            let o = inverse.apply(p.0, p.1).unwrap();
            let d = (o.0 - q.1).abs().max((o.1 - q.0).abs());
            assert!(d <= 1e-7, "EPSG:{code} inverse at {p:?}: ours {o:?}, PROJ ({}, {}) ({d:e} apart)", q.1, q.0);
        }
    }
}

#[test]
fn unknown_crs_are_named() {
    let e = Crs::parse("EPSG:1").unwrap_err().to_string();
    assert!(e.contains("EPSG:1"), "{e}");
    let e = Crs::parse("+proj=nonsense").unwrap_err().to_string();
    assert!(e.contains("+proj=nonsense"), "{e}");
    let e = Crs::parse("Lambert somewhere").unwrap_err().to_string();
    assert!(e.contains("Lambert somewhere"), "{e}");
    assert_eq!(Crs::parse("EPSG:32610").unwrap().code(), Some(32610));
    assert_eq!(Crs::parse("25832").unwrap().code(), Some(25832));
}
