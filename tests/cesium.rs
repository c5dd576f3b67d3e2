//! CesiumJS flies our archives: quantized-mesh terrain checked with an independent decoder
//! and with the real client.
//! - Every tile of the committed SRTM crop's export decoded by PyPI `quantized-mesh-tile`
//!   (installed by `scripts/test.sh`): header bounds, bounding sphere, horizon-occlusion
//!   point, edge lists, triangles covering the tile once, the vertical error within the
//!   level's bound, equal heights on shared edges; the export bit for bit what the server
//!   sends.
//! - CesiumJS (npm `cesium`, pinned in `scripts/test.sh`, its built files unchanged) in
//!   headless Chromium on the served archive and on the export served by nginx:
//!   `sampleTerrainMostDetailed` at random points against GDAL's bilinear value of the
//!   source, no `errorEvent`, all tiles loaded, a screenshot against a golden.
#![allow(clippy::unwrap_used, clippy::expect_used, clippy::cast_possible_truncation, missing_docs)]

use std::path::{Path, PathBuf};
use std::process::Command;

use serde_json::{Value, json};
use terrastream_server::web::quantized::geodetic::GeoTile;
use terrastream_server::web::quantized::{GRID, Terrain, geometric_error};

#[path = "support/oracles.rs"]
mod oracles;
use oracles::{archive, terrastream};

/// The Python of the tools' virtual environment (`scripts/test.sh` makes it), when it has
/// the decoder.
fn decoder_python() -> Option<PathBuf> {
    let venv = std::env::var_os("TERRASTREAM_TOOLS_VENV").map(PathBuf::from).unwrap_or_else(|| {
        PathBuf::from(std::env::var_os("HOME").unwrap_or_default()).join(".cache/terrastream-tools")
    });
    let python = venv.join("bin/python");
    let ok = Command::new(&python).args(["-c", "import quantized_mesh_tile"]).status().is_ok_and(|s| s.success());
    ok.then_some(python)
}

/// Every `{z}/{x}/{y}.terrain` under `dir`.
fn exported_tiles(dir: &Path) -> Vec<GeoTile> {
    let mut tiles = vec![];
    for z in std::fs::read_dir(dir).unwrap().flatten() {
        let Ok(z_level) = z.file_name().to_string_lossy().parse::<u8>() else { continue };
        for x in std::fs::read_dir(z.path()).unwrap().flatten() {
            let column: u32 = x.file_name().to_string_lossy().parse().unwrap();
            for y in std::fs::read_dir(x.path()).unwrap().flatten() {
                let name = y.file_name().to_string_lossy().into_owned();
                let row: u32 = name.strip_suffix(".terrain").unwrap().parse().unwrap();
                tiles.push(GeoTile::new(z_level, column, row).unwrap());
            }
        }
    }
    tiles.sort_by_key(|t| (t.z, t.x, t.y));
    tiles
}

/// `curl` of a path with headers: status line and headers (lower-cased), body.
fn curl(port: u16, path: &str, headers: &[&str]) -> (String, Vec<u8>) {
    let dir = tempfile::tempdir().unwrap();
    let (head, body) = (dir.path().join("head"), dir.path().join("body"));
    let mut command = Command::new("curl");
    command.args(["-s", "-D", head.to_str().unwrap(), "-o", body.to_str().unwrap()]);
    for h in headers {
        command.args(["-H", h]);
    }
    let status = command.arg(format!("http://127.0.0.1:{port}{path}")).status().unwrap();
    assert!(status.success(), "curl {path}");
    (std::fs::read_to_string(head).unwrap().to_ascii_lowercase(), std::fs::read(body).unwrap_or_default())
}

const CESIUM_ACCEPT: &str = "Accept: application/vnd.quantized-mesh;extensions=octvertexnormals-metadata,application/octet-stream;q=0.9,*/*;q=0.01";

#[test]
fn every_terrain_tile_passes_an_independent_decoder_and_the_export_is_what_is_served() {
    let Some(python) = decoder_python() else {
        assert!(
            std::env::var_os("CI").is_none(),
            "quantized-mesh-tile is required on CI (scripts/test.sh installs it)"
        );
        eprintln!("\n*** SKIPPING: PyPI quantized-mesh-tile is not installed (scripts/test.sh) ***\n");
        return;
    };
    let dir = tempfile::tempdir().unwrap();
    let archive = archive(dir.path());
    let export = dir.path().join("terrain");
    terrastream(&["export", archive.to_str().unwrap(), "--to", "quantized-mesh", "-o", export.to_str().unwrap()]);
    let tiles = exported_tiles(&export);

    // The heights each tile was meant to hold, for the decoder's error check.
    let reader = terrastream_format::Reader::open_mmap(&archive).unwrap();
    let terrain = Terrain::new(&reader, None).unwrap();
    let meant = dir.path().join("meant");
    for &tile in &tiles {
        let folder = meant.join(tile.z.to_string()).join(tile.x.to_string());
        std::fs::create_dir_all(&folder).unwrap();
        let heights: Vec<u8> = terrain.heights(tile).unwrap().iter().flat_map(|h| h.to_le_bytes()).collect();
        std::fs::write(folder.join(format!("{}.f32", tile.y)), heights).unwrap();
    }
    let bounds: serde_json::Map<String, Value> =
        (0..=terrain.maxzoom()).map(|z| (z.to_string(), json!(geometric_error(z)))).collect();
    std::fs::write(meant.join("bounds.json"), Value::Object(bounds).to_string()).unwrap();
    let script = oracles::repo().join("tests/support/quantized_mesh_check.py");
    let out = Command::new(&python)
        .args([script.to_str().unwrap(), export.to_str().unwrap(), meant.to_str().unwrap(), &GRID.to_string()])
        .output()
        .unwrap();
    let summary: Value = serde_json::from_slice(&out.stdout)
        .unwrap_or_else(|_| panic!("the decoder failed: {}", String::from_utf8_lossy(&out.stderr)));
    eprintln!("quantized-mesh-tile: {summary}");
    assert!(out.status.success(), "{}", summary["failures"]);
    assert_eq!(summary["tiles"], json!(tiles.len()));
    assert!(summary["shared_edges"].as_u64().unwrap() > 20, "{summary}");
    assert!(summary["worst_error_over_bound"].as_f64().unwrap() <= 1.0, "{summary}");

    // layer.json: every listed tile exported, every exported tile listed.
    let layer: Value = serde_json::from_slice(&std::fs::read(export.join("layer.json")).unwrap()).unwrap();
    assert_eq!(layer["format"], json!("quantized-mesh-1.0"));
    let mut listed = 0;
    for (z, ranges) in layer["available"].as_array().unwrap().iter().enumerate() {
        for r in ranges.as_array().unwrap() {
            let (x0, x1, y0, y1) = (r["startX"].as_u64(), r["endX"].as_u64(), r["startY"].as_u64(), r["endY"].as_u64());
            for x in x0.unwrap()..=x1.unwrap() {
                for y in y0.unwrap()..=y1.unwrap() {
                    listed += 1;
                    let file = export.join(format!("{z}/{x}/{y}.terrain"));
                    assert!(file.exists(), "{} is listed but not written", file.display());
                }
            }
        }
    }
    assert_eq!(listed, tiles.len(), "tiles written but not listed");

    // The server sends the very bytes, with the headers Cesium and browsers need.
    let exe = Path::new(env!("CARGO_BIN_EXE_terrastream"));
    let server = terrastream_testkit::server::spawn_serve(exe, &[archive.to_str().unwrap()], dir.path());
    let (head, body) = curl(server.port, "/tamalpais/layer.json", &[]);
    assert!(head.starts_with("http/1.1 200"), "{head}");
    let served: Value = serde_json::from_slice(&body).unwrap();
    assert_eq!((&served["available"], &served["tiles"]), (&layer["available"], &layer["tiles"]));
    let deepest = *tiles.last().unwrap();
    for tile in [tiles[0], tiles[tiles.len() / 2], deepest] {
        let path = format!("/tamalpais/{}/{}/{}.terrain", tile.z, tile.x, tile.y);
        let (head, body) = curl(server.port, &path, &[CESIUM_ACCEPT, "Accept-Encoding: gzip, deflate"]);
        assert!(head.starts_with("http/1.1 200"), "{path}: {head}");
        for header in [
            "content-type: application/vnd.quantized-mesh;extensions=octvertexnormals-metadata",
            "content-encoding: gzip",
            "access-control-allow-origin: *",
            "vary: accept, accept-encoding",
        ] {
            assert!(head.contains(header), "{path}: no {header:?} in {head}");
        }
        let file = std::fs::read(export.join(format!("{}/{}/{}.terrain", tile.z, tile.x, tile.y))).unwrap();
        assert!(body == file, "{path}: the server's bytes are not the export's");
        // Without extensions asked, none sent; without gzip accepted, plain bytes.
        let (head, plain) = curl(server.port, &path, &["Accept: application/vnd.quantized-mesh"]);
        assert!(head.contains("content-type: application/vnd.quantized-mesh\r\n"), "{head}");
        let expected = terrain.tile(tile, Default::default()).unwrap().unwrap();
        assert!(plain == expected, "{path}: the tile without extensions differs");
        // Revalidation.
        let etag = head.lines().find_map(|l| l.strip_prefix("etag: ")).unwrap().trim().to_owned();
        let (head, _) =
            curl(server.port, &path, &["Accept: application/vnd.quantized-mesh", &format!("If-None-Match: {etag}")]);
        assert!(head.starts_with("http/1.1 304"), "{head}");
    }
    // Outside the available tiles: 404; not a tile: 400.
    let beyond = format!("/tamalpais/{}/0/0.terrain", deepest.z);
    for (path, status) in
        [(beyond.as_str(), "404"), ("/tamalpais/40/0/0.terrain", "400"), ("/tamalpais/3/99/0.terrain", "400")]
    {
        let (head, _) = curl(server.port, path, &[]);
        assert!(head.starts_with(&format!("http/1.1 {status}")), "{path}: {head}");
    }
}

/// The CesiumJS release the tests load (its built files, installed by `scripts/test.sh`).
const CESIUM: &str = "1.145.0";
const WIDTH: u32 = 640;
const HEIGHT: u32 = 400;
/// Random points inside the data.
const POINTS: usize = 50;
/// Cesium draws with SwiftShader's WebGL: deterministic for one Chromium build; the
/// allowance covers another release's anti-aliasing.
const TOLERANCE: terrastream_testkit::golden::Tolerance =
    terrastream_testkit::golden::Tolerance { mean: 2.0, pixel: 32, off_share: 0.02 };

/// CesiumJS's built files (`Build/Cesium` of the npm package).
fn cesium_build() -> Option<PathBuf> {
    let build = oracles::npm_cache().join(format!("cesium-{CESIUM}"));
    build.join("Cesium.js").exists().then_some(build)
}

/// Loads `page`, waits until the globe has loaded every tile of the view, and returns
/// Cesium's heights at `points` (`sampleTerrainMostDetailed`, as documented) and a
/// screenshot; fails on any `errorEvent` or failed request.
fn cesium_run(
    browser: &terrastream_testkit::browser::Browser<'_>,
    page: &str,
    points: &[(f64, f64)],
) -> (Vec<f64>, (u32, u32, Vec<u8>)) {
    use std::time::{Duration, Instant};
    browser.goto(page);
    let started = Instant::now();
    loop {
        let state = browser.eval(
            "return [!!(window.viewer && viewer.scene.globe.tilesLoaded && viewer.scene.frameState.frameNumber > 5), window.failures];",
        );
        assert_eq!(state[1], json!([]), "Cesium reported errors on {page}: console {:?}", browser.console());
        if state[0] == json!(true) {
            break;
        }
        assert!(started.elapsed() < Duration::from_secs(120), "Cesium never loaded its view: {:?}", browser.console());
        std::thread::sleep(Duration::from_millis(250));
    }
    browser.eval("viewer.cesiumWidget.creditContainer.style.display = 'none'; viewer.scene.requestRender(); return 0;");
    std::thread::sleep(Duration::from_millis(500));
    let picture = browser.screenshot("#globe");
    let sample = oracles::snippet("cesium-sample");
    let list: Vec<[f64; 2]> = points.iter().map(|&(lon, lat)| [lon, lat]).collect();
    // The documented call, on the test's points, handing its heights back.
    let script = sample.replace("[[-122.5965, 37.9235], [-122.6, 37.9]]", &json!(list).to_string()).replace(
        "console.log(done.map(p => p.height)));",
        "arguments[0](done.map(p => p.height))).catch(e => arguments[0](String(e)));",
    );
    assert!(script.contains("arguments[0]"), "the cesium-sample snippet changed: {sample}");
    browser.call("POST", "/timeouts", Some(json!({ "script": 120_000 })));
    let heights = browser.eval_async(&script);
    let failures = browser.eval("return window.failures;");
    assert_eq!(failures, json!([]), "Cesium reported errors on {page}: console {:?}", browser.console());
    let heights =
        heights.as_array().unwrap_or_else(|| panic!("{heights}")).iter().map(|h| h.as_f64().unwrap()).collect();
    (heights, picture)
}

#[test]
fn cesium_flies_the_served_and_the_exported_terrain() {
    use terrastream_testkit::browser::{Browser, Driver, WEBGL_FLAGS};
    let mut missing = terrastream_testkit::browser::missing();
    let build = cesium_build();
    if build.is_none() {
        missing.push("CesiumJS's built files (scripts/test.sh: npm pack cesium@1.145.0)");
    }
    for tool in ["gdaltransform", "gdallocationinfo"] {
        if Command::new(tool).arg("--version").output().is_err() {
            missing.push("GDAL's command-line tools (apt-get install gdal-bin)");
        }
    }
    if !terrastream_testkit::browser::skip_or_fail("CESIUM", &missing) {
        return;
    }
    let dir = tempfile::tempdir().unwrap();
    let archive = archive(dir.path());
    let exe = Path::new(env!("CARGO_BIN_EXE_terrastream"));
    let server = terrastream_testkit::server::spawn_serve(exe, &[archive.to_str().unwrap()], dir.path());
    let (_, body) = curl(server.port, "/tamalpais/layer.json", &[]);
    let layer: Value = serde_json::from_slice(&body).unwrap();
    let bounds: [f64; 4] = serde_json::from_value(layer["bounds"].clone()).unwrap();
    let points = oracles::random_points(bounds, POINTS);
    let truth = oracles::gdal_bilinear(&points);

    // The static host: the page, Cesium's files and the export, served by nginx as
    // documented.
    let root = dir.path().join("www");
    std::fs::create_dir_all(&root).unwrap();
    std::os::unix::fs::symlink(build.unwrap(), root.join("cesium")).unwrap();
    let page = oracles::snippet("cesium-page");
    assert!(page.contains(&format!("width: {WIDTH}px; height: {HEIGHT}px")), "the globe's size changed");
    std::fs::write(root.join("index.html"), page).unwrap();
    let terrain = root.join("terrain");
    terrastream(&["export", archive.to_str().unwrap(), "--to", "quantized-mesh", "-o", terrain.to_str().unwrap()]);
    let location = oracles::snippet("quantized-mesh-nginx");
    let Some(nginx) = terrastream_testkit::nginx::start_nginx(
        &root,
        &format!(
            "server {{ listen 127.0.0.1:{{port}}; root {{root}}; types {{ application/json json; text/html html; \
             application/javascript js; text/css css; image/png png; application/wasm wasm; }} {location} }}"
        ),
    ) else {
        return;
    };
    let driver = Driver::start();
    let browser = Browser::open(&driver, WEBGL_FLAGS, (WIDTH, HEIGHT));
    let served =
        format!("http://127.0.0.1:{}/index.html?terrain=http://127.0.0.1:{}/tamalpais", nginx.port, server.port);
    let exported = format!("http://127.0.0.1:{0}/index.html?terrain=http://127.0.0.1:{0}/terrain", nginx.port);
    let mut pictures = vec![];
    for (name, page) in [("served", served), ("exported", exported)] {
        let (heights, picture) = cesium_run(&browser, &page, &points);
        let (median, p90) = oracles::errors(&heights, &truth);
        eprintln!("Cesium {name}: |height - GDAL bilinear| median {median:.2} m, 90 % within {p90:.2} m");
        assert!(median <= 3.0 && p90 <= 20.0, "{name}: median {median:.2} m, p90 {p90:.2} m");
        pictures.push(picture);
    }
    let (w, h, rgba) = &pictures[0];
    // Terrain drawn: the lit globe, not the empty sky, over most of the lower half.
    let lower = &rgba[(*w * *h * 2) as usize..];
    let lit = lower.chunks_exact(4).filter(|p| u32::from(p[0]) + u32::from(p[1]) + u32::from(p[2]) > 60).count();
    assert!(lit * 2 > (w * h / 2) as usize, "Cesium drew terrain over only {lit} of the lower half's pixels");
    terrastream_testkit::golden::assert_golden("cesium-terrain", *w, *h, rgba, TOLERANCE);
    let (mean, _) = terrastream_testkit::golden::difference(rgba, &pictures[1].2, 0);
    assert!(mean < 0.01, "the exported terrain draws differently from the served: mean difference {mean}");
}
