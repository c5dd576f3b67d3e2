//! Cameras in geographic terms, with CesiumJS's conventions (`render --at LON,LAT,HEIGHT
//! --heading --pitch`): on the globe the eye lands where PROJ puts the point in ECEF, on
//! the plate where GDAL puts it in the archive's CRS, and bad poses are named. Needs GDAL's command-line tools and a software Vulkan (lavapipe).
#![allow(clippy::unwrap_used, clippy::expect_used, missing_docs)]

use std::process::{Command, Stdio};

#[path = "support/oracles.rs"]
mod oracles;

#[test]
fn a_posed_render_puts_the_eye_where_gdal_puts_the_point() {
    if Command::new("gdaltransform").arg("--version").output().is_err() {
        assert!(std::env::var_os("CI").is_none(), "gdal-bin is required on CI");
        return;
    }
    let dir = tempfile::tempdir().unwrap();
    let archive = oracles::archive(dir.path());
    let png = dir.path().join("posed.png");
    let (lon, lat, height) = (-122.5965, 37.87, 1200.0);
    let eye = |flat: bool| -> Vec<f64> {
        let out = Command::new(env!("CARGO_BIN_EXE_terrastream"))
            .args(["render", archive.to_str().unwrap(), "--size", "320x200", "-o", png.to_str().unwrap()])
            .args(["--at", &format!("{lon},{lat},{height}"), "--heading", "0", "--pitch", "-15"])
            .args(flat.then_some("--flat"))
            .env("XDG_RUNTIME_DIR", std::env::var_os("XDG_RUNTIME_DIR").unwrap_or_else(|| dir.path().into()))
            .output()
            .unwrap();
        let said = String::from_utf8_lossy(&out.stdout).into_owned();
        assert!(out.status.success(), "{said}{}", String::from_utf8_lossy(&out.stderr));
        said.rsplit("eye ").next().unwrap().trim().split(',').map(|v| v.trim().parse().unwrap()).collect()
    };
    let gdal = |from: &str, to: &str, input: String| -> Vec<f64> {
        let mut child = Command::new("gdaltransform")
            .args(["-s_srs", from, "-t_srs", to])
            .stdin(Stdio::piped())
            .stdout(Stdio::piped())
            .spawn()
            .unwrap();
        std::io::Write::write_all(&mut child.stdin.take().unwrap(), input.as_bytes()).unwrap();
        String::from_utf8(child.wait_with_output().unwrap().stdout)
            .unwrap()
            .split_whitespace()
            .map(|v| v.parse().unwrap())
            .collect()
    };
    let wgs84 = "+proj=longlat +datum=WGS84 +no_defs";

    // On the globe (the default): the eye in ECEF, where PROJ puts the point.
    let ecef = gdal(wgs84, "+proj=geocent +datum=WGS84 +no_defs", format!("{lon} {lat} {height}\n"));
    let globe = eye(false);
    for k in 0..3 {
        assert!((globe[k] - ecef[k]).abs() < 0.5, "eye {globe:?}, PROJ's point {ecef:?}");
    }

    // On the plate: GDAL's place of the point in the archive's CRS, then its world units.
    let reader = terrastream_format::Reader::open_mmap(&archive).unwrap();
    let g = reader.metadata().georeference.clone().unwrap();
    let xy = gdal(wgs84, g.definition.as_deref().unwrap(), format!("{lon} {lat}\n"));
    let (origin, scale) = (g.origin.unwrap(), g.scale.unwrap());
    let world = [(xy[0] - origin[0]) / scale[0], height, (origin[1] - xy[1]) / scale[1]];
    let flat = eye(true);
    for k in 0..3 {
        assert!((flat[k] - world[k]).abs() < 0.5, "eye {flat:?}, GDAL's point {world:?}");
    }
    // A pose off the Earth is named.
    let out = Command::new(env!("CARGO_BIN_EXE_terrastream"))
        .args(["render", archive.to_str().unwrap(), "-o", png.to_str().unwrap(), "--at", "-200,37.9,100"])
        .output()
        .unwrap();
    assert!(!out.status.success());
    assert!(String::from_utf8_lossy(&out.stderr).contains("longitude -180..180"));
}
