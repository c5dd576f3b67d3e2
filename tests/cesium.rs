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
//!   source (above EGM96) plus PROJ's EGM96 undulation (Cesium places heights above the
//!   ellipsoid), no `errorEvent`, all tiles loaded, a screenshot against a golden.
//! - Our globe beside Cesium's bare ellipsoid at three poses: the silhouette or horizon
//!   of every column within 3 px.
//! - Our sky and haze beside Cesium's atmosphere at one pose and sun: each band's mean
//!   colour within a stated CIE76 distance.
#![allow(clippy::unwrap_used, clippy::expect_used, clippy::cast_possible_truncation, missing_docs)]

use std::path::{Path, PathBuf};
use std::process::Command;

use serde_json::{Value, json};
use terrastream_views::quantized::geodetic::GeoTile;
use terrastream_views::quantized::{GRID, Terrain, geometric_error};

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

const CESIUM_ACCEPT: &str = "Accept: application/vnd.quantized-mesh;extensions=octvertexnormals-watermask-metadata,application/octet-stream;q=0.9,*/*;q=0.01";

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
            "content-type: application/vnd.quantized-mesh;extensions=octvertexnormals-watermask-metadata",
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

/// The heights CesiumJS should place at `points` (lon, lat): above the WGS 84 ellipsoid,
/// GDAL's bilinear height of the source (above EGM96, as SRTM's are) plus PROJ's
/// undulation N of EGM96 there.
fn ellipsoidal_truth(points: &[(f64, f64)]) -> Vec<f64> {
    let (h, n) = (oracles::gdal_bilinear(points), oracles::proj_undulation(points));
    h.iter().zip(&n).map(|(h, n)| h + n).collect()
}

/// CesiumJS's built files (`Build/Cesium` of the npm package).
fn cesium_build() -> Option<PathBuf> {
    let build = oracles::npm_cache().join(format!("cesium-{CESIUM}"));
    build.join("Cesium.js").exists().then_some(build)
}

/// CesiumJS's built files and what a test lacks (the browser's needs, and those files).
fn cesium_build_or_missing() -> (Option<PathBuf>, Vec<&'static str>) {
    let mut missing = terrastream_testkit::browser::missing();
    let build = cesium_build();
    if build.is_none() {
        missing.push("CesiumJS's built files (scripts/test.sh: npm pack cesium@1.145.0)");
    }
    (build, missing)
}

/// CesiumJS's built files, when they, the browser and the GDAL and PROJ oracles are here
/// (else None, the test skipped, or failed on CI).
fn cesium_with_oracles() -> Option<PathBuf> {
    let (build, mut missing) = cesium_build_or_missing();
    for tool in ["gdaltransform", "gdallocationinfo"] {
        if Command::new(tool).arg("--version").output().is_err() {
            missing.push("GDAL's command-line tools (apt-get install gdal-bin)");
        }
    }
    if Command::new("cct").arg("--version").output().is_err() {
        missing.push("PROJ's command-line tools (apt-get install proj-bin)");
    }
    terrastream_testkit::browser::skip_or_fail("CESIUM", &missing).then_some(build).flatten()
}

/// CesiumJS's built files (`build`) and `page` as `name`, served by nginx from `dir/www`
/// (None where nginx is missing: the test is skipped).
fn cesium_host(dir: &Path, build: &Path, name: &str, page: &str) -> Option<terrastream_testkit::nginx::Nginx> {
    let root = dir.join("www");
    std::fs::create_dir_all(&root).unwrap();
    std::os::unix::fs::symlink(build, root.join("cesium")).unwrap();
    std::fs::write(root.join(name), page).unwrap();
    terrastream_testkit::nginx::start_nginx(
        &root,
        "server { listen 127.0.0.1:{port}; root {root}; types { application/json json; text/html html; \
         application/javascript js; text/css css; image/png png; application/wasm wasm; } }",
    )
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
    let Some(build) = cesium_with_oracles() else { return };
    let dir = tempfile::tempdir().unwrap();
    let archive = archive(dir.path());
    let exe = Path::new(env!("CARGO_BIN_EXE_terrastream"));
    let server = terrastream_testkit::server::spawn_serve(exe, &[archive.to_str().unwrap()], dir.path());
    let (_, body) = curl(server.port, "/tamalpais/layer.json", &[]);
    let layer: Value = serde_json::from_slice(&body).unwrap();
    let bounds: [f64; 4] = serde_json::from_value(layer["bounds"].clone()).unwrap();
    let points = oracles::random_points(bounds, POINTS);
    let truth = ellipsoidal_truth(&points);

    // The static host: the page, Cesium's files and the export, served by nginx as
    // documented.
    let root = dir.path().join("www");
    std::fs::create_dir_all(&root).unwrap();
    std::os::unix::fs::symlink(&build, root.join("cesium")).unwrap();
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
        eprintln!("Cesium {name}: |height - (GDAL bilinear H + PROJ N)| median {median:.2} m, 90 % within {p90:.2} m");
        assert!(median <= 1.5 && p90 <= 3.0, "{name}: median {median:.2} m, p90 {p90:.2} m");
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

/// A private archive read by CesiumJS, as documented: a `Resource` with a signed token as
/// its `access_token` query parameter (carried into every tile request), and one with a
/// key in an `Authorization` header. Every tile loads, no error, heights as public.
#[test]
fn cesium_reads_private_terrain_with_a_token_or_a_header() {
    use terrastream_testkit::browser::{Browser, Driver, WEBGL_FLAGS};
    let Some(build) = cesium_with_oracles() else { return };
    let dir = tempfile::tempdir().unwrap();
    let archive = archive(dir.path());
    let cli = |args: &[&str]| {
        let out = Command::new(env!("CARGO_BIN_EXE_terrastream")).args(args).current_dir(dir.path()).output().unwrap();
        assert!(out.status.success(), "{args:?}: {}", String::from_utf8_lossy(&out.stderr));
        String::from_utf8(out.stdout).unwrap().trim().to_owned()
    };
    std::fs::write(dir.path().join("secret"), "a secret the operator keeps to itself").unwrap();
    let key = cli(&["key", "new", "--archives", "tamalpais", "--keys", "keys.toml"]);
    let token = cli(&["sign", "--secret-file", "secret", "--archive", "tamalpais", "--expires", "2h"]);
    let exe = Path::new(env!("CARGO_BIN_EXE_terrastream"));
    let args = [archive.to_str().unwrap(), "--private", "--keys", "keys.toml", "--secret-file", "secret"];
    let server = terrastream_testkit::server::spawn_serve(exe, &args, dir.path());
    assert!(curl(server.port, "/tamalpais/layer.json", &[]).0.contains(" 401"), "no key, no layer.json");
    let (_, body) = curl(server.port, &format!("/tamalpais/layer.json?access_token={token}"), &[]);
    let layer: Value = serde_json::from_slice(&body).unwrap();
    assert_eq!(layer["tiles"][0], format!("{{z}}/{{x}}/{{y}}.terrain?access_token={token}"));
    let bounds: [f64; 4] = serde_json::from_value(layer["bounds"].clone()).unwrap();
    let points = oracles::random_points(bounds, POINTS / 5);
    let truth = ellipsoidal_truth(&points);
    let Some(nginx) = cesium_host(dir.path(), &build, "key.html", &oracles::snippet("cesium-key-page")) else {
        return;
    };
    let driver = Driver::start();
    let browser = Browser::open(&driver, WEBGL_FLAGS, (WIDTH, HEIGHT));
    let terrain = format!("http://127.0.0.1:{}/tamalpais", server.port);
    let page = format!("http://127.0.0.1:{}/key.html?terrain={terrain}", nginx.port);
    for (name, page) in
        [("signed token", format!("{page}&key={token}")), ("key in a header", format!("{page}&key={key}&header=1"))]
    {
        let (heights, (w, h, rgba)) = cesium_run(&browser, &page, &points);
        let (median, p90) = oracles::errors(&heights, &truth);
        eprintln!("Cesium, private, {name}: median {median:.2} m, 90 % within {p90:.2} m");
        // The terrain of the test above at a fifth of its points: a noisier median.
        assert!(median <= 2.0 && p90 <= 3.0, "{name}: median {median:.2} m, p90 {p90:.2} m");
        terrastream_testkit::golden::assert_golden("cesium-terrain", w, h, &rgba, TOLERANCE);
    }
}

/// A page of CesiumJS's built files with a 640 x 400 `#globe` on black: `script` runs
/// with `q` (the page's query), `lon`, `lat` and `height` (from `at=LON,LAT,HEIGHT`),
/// `window.failures` (what the tests check is empty) and `posedViewer` (the viewer at the
/// page's pose) defined.
macro_rules! cesium_page {
    ($script:literal) => {
        concat!(
            r#"<!doctype html><html><head><meta charset="utf-8">
<script src="cesium/Cesium.js"></script>
<link rel="stylesheet" href="cesium/Widgets/widgets.css">
<style>html, body { margin: 0; background: #000 } #globe { width: 640px; height: 400px }</style></head>
<body><div id="globe"></div><script>
const q = new URLSearchParams(location.search);
const [lon, lat, height] = q.get('at').split(',').map(Number);
window.failures = [];
// A viewer of `options` without widgets, stars, sun, moon, FXAA or credits, its camera at
// at=, heading= and pitch= (degrees) with a vertical field of view of 60 degrees (Cesium's
// `fov` is the wider side's); and the camera's place.
function posedViewer(options) {
  const viewer = new Cesium.Viewer('globe', Object.assign({ baseLayerPicker: false,
    geocoder: false, timeline: false, animation: false, homeButton: false, sceneModePicker: false,
    navigationHelpButton: false, fullscreenButton: false, infoBox: false, selectionIndicator: false,
    skyBox: false, contextOptions: { webgl: { antialias: false } } }, options));
  const scene = viewer.scene;
  if (scene.sun) scene.sun.show = false;
  if (scene.moon) scene.moon.show = false;
  scene.postProcessStages.fxaa.enabled = false;
  viewer.cesiumWidget.creditContainer.style.display = 'none';
  scene.camera.frustum.fov = 2 * Math.atan(Math.tan(Math.PI / 6) * 640 / 400);
  const at = Cesium.Cartesian3.fromDegrees(lon, lat, height);
  scene.camera.setView({ destination: at,
    orientation: { heading: Cesium.Math.toRadians(Number(q.get('heading'))),
                   pitch: Cesium.Math.toRadians(Number(q.get('pitch'))), roll: 0 } });
  return [viewer, at];
}
"#,
            $script,
            "</script></body></html>"
        )
    };
}

/// The page of the side-by-side: CesiumJS's bare ellipsoid (`EllipsoidTerrainProvider`),
/// or the quantized-mesh terrain at `terrain=`, a white globe on black, no imagery, lighting, sky, sun, moon, fog or atmosphere, the
/// camera at `at=LON,LAT,HEIGHT` with `heading=` and `pitch=` (degrees) and a vertical
/// field of view of 60 degrees (Cesium's `fov` is the wider side's).
const BARE_GLOBE_PAGE: &str = cesium_page!(
    r#"const url = q.get('terrain');
(url ? Cesium.CesiumTerrainProvider.fromUrl(url) : Promise.resolve(new Cesium.EllipsoidTerrainProvider()))
.then(terrainProvider => {
if (terrainProvider.errorEvent) terrainProvider.errorEvent.addEventListener(e => window.failures.push(String(e.message || e)));
const [viewer] = posedViewer({ terrainProvider, baseLayer: false, skyAtmosphere: false });
const scene = viewer.scene;
scene.backgroundColor = Cesium.Color.BLACK;
scene.globe.baseColor = Cesium.Color.WHITE;
scene.globe.enableLighting = false;
scene.globe.showGroundAtmosphere = false;
scene.globe.depthTestAgainstTerrain = true;
scene.fog.enabled = false;
window.viewer = viewer;
}).catch(e => window.failures.push('terrain: ' + e));
"#
);

/// Waits until Cesium's page has drawn a few frames and `ready` (a JavaScript
/// expression) holds, failing on any failure the page reports or after 60 s.
fn wait_for_cesium(browser: &terrastream_testkit::browser::Browser<'_>, ready: &str) {
    let started = std::time::Instant::now();
    let script = format!("return !!(window.viewer && viewer.scene.frameState.frameNumber > 5 && {ready});");
    while browser.eval(&script) != json!(true) {
        assert_eq!(browser.eval("return window.failures;"), json!([]), "Cesium: {:?}", browser.console());
        assert!(started.elapsed().as_secs() < 60, "Cesium never loaded its view: {:?}", browser.console());
        std::thread::sleep(std::time::Duration::from_millis(100));
    }
}

/// Our render of the pose `(name, archive, at, heading, pitch)` at Cesium's picture's size
/// and field of view, with `extra` arguments; both pictures are written to look at in
/// `target/tmp/{folder}/`.
fn ours_beside(
    dir: &Path,
    (name, archive, at, heading, pitch): (&str, &Path, &str, f64, f64),
    extra: &[&str],
    (cw, ch, cesium): (u32, u32, &[u8]),
    folder: &str,
) -> (u32, u32, Vec<u8>) {
    let png = dir.join(format!("{name}.png"));
    let out = Command::new(env!("CARGO_BIN_EXE_terrastream"))
        .args(["-q", "render", archive.to_str().unwrap(), "-o", png.to_str().unwrap()])
        .args(["--size", &format!("{WIDTH}x{HEIGHT}"), "--fov", "60", "--at", at])
        .args(["--heading", &heading.to_string(), "--pitch", &pitch.to_string()])
        .args(extra)
        .env("XDG_RUNTIME_DIR", std::env::var_os("XDG_RUNTIME_DIR").unwrap_or_else(|| dir.into()))
        .output()
        .unwrap();
    assert!(out.status.success(), "render: {}", String::from_utf8_lossy(&out.stderr));
    let (w, h, ours) = terrastream_testkit::golden::decode_png(&std::fs::read(&png).unwrap());
    assert_eq!((w, h), (cw, ch), "the same picture size");
    let look = Path::new(env!("CARGO_TARGET_TMPDIR")).join(folder);
    std::fs::create_dir_all(&look).unwrap();
    std::fs::copy(&png, look.join(format!("{name}-terrastream.png"))).unwrap();
    terrastream_testkit::golden::write_png(&look.join(format!("{name}-cesium.png")), cw, ch, cesium);
    (w, h, ours)
}

/// The topmost and bottommost lit rows of each column (`None`: the column is empty).
fn column_edges(w: u32, h: u32, rgba: &[u8]) -> Vec<Option<(u32, u32)>> {
    let lit = |x: u32, y: u32| {
        let i = ((y * w + x) * 4) as usize;
        u32::from(rgba[i]) + u32::from(rgba[i + 1]) + u32::from(rgba[i + 2]) > 3 * 128
    };
    (0..w).map(|x| Some(((0..h).find(|&y| lit(x, y))?, (0..h).rev().find(|&y| lit(x, y))?))).collect()
}

/// Our `--shading flat` render of a texture-only world archive (EPSG:4326) and CesiumJS's
/// bare ellipsoid at the same pose and field of view: the silhouette or horizon of every
/// column agrees within 3 px, at three poses (the whole Earth from 20 000 km, 2 000 km
/// oblique, 10 km looking at the horizon).
#[test]
fn the_globe_matches_cesiums_ellipsoid_column_by_column() {
    use terrastream_testkit::browser::{Browser, Driver, WEBGL_FLAGS};
    let (build, mut missing) = cesium_build_or_missing();
    if Command::new("gdal_create").arg("--version").output().is_err() {
        missing.push("GDAL's command-line tools (apt-get install gdal-bin)");
    }
    if !terrastream_testkit::browser::skip_or_fail("CESIUM", &missing) {
        return;
    }
    let dir = tempfile::tempdir().unwrap();
    // A white world in EPSG:4326, tiled as a texture-only archive.
    let tif = dir.path().join("world.tif");
    let made = Command::new("gdal_create")
        .args(["-q", "-of", "GTiff", "-outsize", "720", "360", "-bands", "3", "-burn", "255", "-ot", "Byte"])
        .args(["-a_srs", "EPSG:4326", "-a_ullr", "-180", "90", "180", "-90", tif.to_str().unwrap()])
        .status()
        .unwrap();
    assert!(made.success(), "gdal_create");
    let world = dir.path().join("world.tspack");
    terrastream(&["tile", "--texture", tif.to_str().unwrap(), "-o", world.to_str().unwrap()]);
    // And a DEM of 12 x 12 degrees around Everest (kept geographic), served to Cesium as
    // quantized-mesh terrain.
    let dem = oracles::dem(dir.path(), oracles::EVEREST.0 - 6.0, oracles::EVEREST.1 - 6.0, 12.0, 120.0);
    let himalaya = dir.path().join("himalaya.tspack");
    terrastream(&["tile", "--elevation", dem.to_str().unwrap(), "-o", himalaya.to_str().unwrap()]);
    let exe = Path::new(env!("CARGO_BIN_EXE_terrastream"));
    let server = terrastream_testkit::server::spawn_serve(exe, &[himalaya.to_str().unwrap()], dir.path());
    let terrain = format!("http://127.0.0.1:{}/himalaya", server.port);

    let Some(nginx) = cesium_host(dir.path(), &build.unwrap(), "globe.html", BARE_GLOBE_PAGE) else {
        return;
    };
    let driver = Driver::start();
    // A window larger than the globe's element, which the screenshot takes whole.
    let browser = Browser::open(&driver, WEBGL_FLAGS, (WIDTH + 200, HEIGHT + 300));
    for (name, archive, at, heading, pitch) in [
        ("whole", &world, "0,0,20000000", 0.0, -90.0),
        ("oblique", &world, "10,20,2000000", 30.0, -30.0),
        ("horizon", &world, "0,0,10000", 90.0, 0.0),
        // Grazing over the Himalaya, Everest 50 km ahead: the terrain's own skyline.
        ("himalaya", &himalaya, "86.55,27.75,9000", 50.0, 0.0),
    ] {
        let terrain = if *archive == himalaya { format!("&terrain={terrain}") } else { String::new() };
        browser.goto(&format!(
            "http://127.0.0.1:{}/globe.html?at={at}&heading={heading}&pitch={pitch}{terrain}",
            nginx.port
        ));
        wait_for_cesium(&browser, "viewer.scene.globe.tilesLoaded");
        let (cw, ch, cesium) = browser.screenshot("#globe");
        let pose = (name, archive.as_path(), at, heading, pitch);
        let (w, h, ours) = ours_beside(dir.path(), pose, &["--shading", "flat"], (cw, ch, &cesium), "side-by-side");
        let (theirs, mine) = (column_edges(cw, ch, &cesium), column_edges(w, h, &ours));
        // Where the silhouette is steep (the sides of the disc), a row is the same edge a
        // column over: the tolerance grows by Cesium's row change to the next column.
        let steepness = |x: usize, pick: fn((u32, u32)) -> u32| {
            let row = |i: usize| theirs.get(i).copied().flatten().map(pick);
            let here = row(x).unwrap_or(0);
            [x.wrapping_sub(1), x + 1].into_iter().filter_map(row).map(|r| r.abs_diff(here)).max().unwrap_or(0)
        };
        let (mut compared, mut one_sided) = (0, 0);
        let mut disagree = Vec::new();
        for (x, (a, b)) in theirs.iter().zip(&mine).enumerate() {
            match (a, b) {
                (Some(a), Some(b)) => {
                    compared += 1;
                    let top = a.0.abs_diff(b.0) <= 3 + steepness(x, |e| e.0);
                    let bottom = a.1.abs_diff(b.1) <= 3 + steepness(x, |e| e.1);
                    if !(top && bottom) {
                        disagree.push((x, *a, *b));
                    }
                }
                (None, None) => {}
                // The outermost column of a side, lit in one picture only.
                _ => one_sided += 1,
            }
        }
        let worst = theirs.iter().zip(&mine).filter_map(|(a, b)| Some(a.as_ref()?.0.abs_diff(b.as_ref()?.0))).max();
        eprintln!(
            "{name}: {compared} columns compared, {} disagree, {one_sided} lit in one only; top rows differ by at most {worst:?} px",
            disagree.len()
        );
        assert!(compared > 100, "{name}: the globe is in both pictures ({compared} columns)");
        assert!(disagree.is_empty(), "{name}: (column, Cesium's rows, ours) {:?}", &disagree[..disagree.len().min(12)]);
        assert!(one_sided <= 4, "{name}: {one_sided} columns lit in one picture only");
    }
}

/// A collection (a 10" base raised 3 m and a 1" patch, each as deep as it reaches:
/// docs/tiling.md, "Collections") read by CesiumJS: `layer.json` lists the patch's
/// rectangle at the patch's levels, so Cesium asks for no tile that is not there (no
/// `errorEvent`, every tile of the view loaded), and its most detailed heights inside the
/// patch are the patch's (GDAL's bilinear height of the 1" DEM plus PROJ's N).
#[test]
fn cesium_flies_a_collection_of_a_base_and_a_patch() {
    use terrastream_testkit::browser::{Browser, Driver, WEBGL_FLAGS};
    let Some(build) = cesium_with_oracles() else { return };
    let dir = tempfile::tempdir().unwrap();
    let repo = oracles::repo();
    let collection = dir.path().join("collection.tspack");
    terrastream(&[
        "tile",
        "--elevation",
        repo.join("tests/data/collection-base-10s-plus3m.tif").to_str().unwrap(),
        repo.join("tests/data/collection-patch-1s.tif").to_str().unwrap(),
        "--vertical-datum",
        "5773",
        "--tile-size",
        "64",
        "-o",
        collection.to_str().unwrap(),
    ]);
    let exe = Path::new(env!("CARGO_BIN_EXE_terrastream"));
    let server = terrastream_testkit::server::spawn_serve(exe, &[collection.to_str().unwrap()], dir.path());
    let (_, body) = curl(server.port, "/collection/layer.json", &[]);
    let layer: Value = serde_json::from_slice(&body).unwrap();
    let deepest = &layer["available"][layer["maxzoom"].as_u64().unwrap() as usize];
    assert_eq!(deepest.as_array().unwrap().len(), 1, "the deepest level lists the patch alone: {deepest}");
    // Inside the patch (pixels 80..240 of the 1" crop), beyond its blend band.
    let points = oracles::random_points([-122.611, 37.906, -122.583, 37.938], POINTS);
    let truth = ellipsoidal_truth(&points);
    let Some(nginx) = cesium_host(dir.path(), &build, "index.html", &oracles::snippet("cesium-page")) else {
        return;
    };
    let driver = Driver::start();
    let browser = Browser::open(&driver, WEBGL_FLAGS, (WIDTH, HEIGHT));
    let page =
        format!("http://127.0.0.1:{}/index.html?terrain=http://127.0.0.1:{}/collection", nginx.port, server.port);
    let (heights, _) = cesium_run(&browser, &page, &points);
    let (median, p90) = oracles::errors(&heights, &truth);
    eprintln!(
        "Cesium on a collection, inside the patch: |height - (GDAL bilinear H + PROJ N)| median {median:.2} m, 90 % within {p90:.2} m"
    );
    assert!(median <= 1.5 && p90 <= 3.0, "median {median:.2} m, p90 {p90:.2} m");
}

/// The coast (`oracles::coast_dem`) tiled as `coast`, and the same with a water layer
/// as `lake` (a lake filling the basin, from a mask in UTM), both served.
struct Coast {
    server: terrastream_testkit::server::Spawned,
    /// The lake's centre (longitude, latitude).
    lake_centre: (f64, f64),
    /// West, south and side of the DEM, in degrees.
    bounds: [f64; 3],
}

fn coast_and_lake(dir: &Path) -> Coast {
    let (tif, bounds) = oracles::coast_dem(dir);
    let archive = dir.join("coast.tspack");
    terrastream(&["tile", "--elevation", tif.to_str().unwrap(), "-o", archive.to_str().unwrap()]);
    let (mask, lake_centre) = oracles::lake_mask(dir, bounds);
    let wet = dir.join("lake.tspack");
    terrastream(&["water", archive.to_str().unwrap(), "--mask", mask.to_str().unwrap(), "-o", wet.to_str().unwrap()]);
    let exe = Path::new(env!("CARGO_BIN_EXE_terrastream"));
    let server =
        terrastream_testkit::server::spawn_serve(exe, &[archive.to_str().unwrap(), wet.to_str().unwrap()], dir);
    Coast { server, lake_centre, bounds }
}

/// The sea as CesiumJS reads it: a coast whose sea is stored as a flat 0 (and a basin
/// below sea level on land), served; Cesium, asked for the water mask
/// (`requestWaterMask: true`), decodes a sea tile as all water, a land tile as all land,
/// and the coast's tile as water in the west and land in the east, from our tiles.
#[test]
fn cesium_reads_the_water_mask_of_a_coast() {
    use terrastream_testkit::browser::{Browser, Driver, WEBGL_FLAGS};
    let Some(build) = cesium_with_oracles() else { return };
    let dir = tempfile::tempdir().unwrap();
    let Coast { server, lake_centre, bounds: [west, south, degrees] } = coast_and_lake(dir.path());
    let (_, body) = curl(server.port, "/coast/layer.json", &[]);
    let layer: Value = serde_json::from_slice(&body).unwrap();
    assert!(layer["extensions"].as_array().unwrap().contains(&json!("watermask")), "{layer}");
    let deepest = u8::try_from(layer["available"].as_array().unwrap().len() - 1).unwrap();
    // The tile holding a point at the deepest level; the sea's west of the coast at
    // `west + degrees / 2`, the land's east of it.
    let holding = |lon: f64, lat: f64, z: u8| {
        let d = 180.0 / f64::from(1u32 << z);
        [((lon + 180.0) / d).floor() as u32, ((lat + 90.0) / d).floor() as u32, u32::from(z)]
    };
    let (mid, lat) = (west + degrees / 2.0, south + degrees / 2.0);
    let d = 180.0 / f64::from(1u32 << deepest);
    // A sea tile wholly inside the sea, a land tile wholly on land (the basin below sea
    // level in it), and the one the coast crosses.
    let sea = holding(west + degrees / 4.0, lat, deepest);
    let land = holding(mid + degrees / 4.0, lat, deepest);
    let coast = holding(mid, lat, deepest);
    let inside = |[x, y, _]: [u32; 3], [w, s, e, n]: [f64; 4]| {
        let (x0, y0) = (f64::from(x) * d - 180.0, f64::from(y) * d - 90.0);
        x0 >= w && x0 + d <= e && y0 >= s && y0 + d <= n
    };
    assert!(inside(sea, [west, south, mid, south + degrees]), "level {deepest} too coarse for a sea tile");
    assert!(inside(land, [mid, south, west + degrees, south + degrees]), "level {deepest} too coarse for a land tile");
    let page = "<!doctype html><html><head><script src=\"cesium/Cesium.js\"></script></head><body></body></html>";
    let Some(nginx) = cesium_host(dir.path(), &build, "index.html", page) else { return };
    let driver = Driver::start();
    let browser = Browser::open(&driver, WEBGL_FLAGS, (WIDTH, HEIGHT));
    browser.goto(&format!("http://127.0.0.1:{}/index.html", nginx.port));
    browser.call("POST", "/timeouts", Some(json!({ "script": 60_000 })));
    let masks = browser.eval_async(&format!(
        "const done = arguments[0];
         (async () => {{
           const provider = await Cesium.CesiumTerrainProvider.fromUrl('http://127.0.0.1:{port}/coast', {{ requestWaterMask: true }});
           const out = [];
           for (const [x, y, z] of {tiles}) {{
             // Cesium counts rows from the north; the tiles' URLs (TMS) from the south.
             const data = await provider.requestTileGeometry(x, (2 ** z) - 1 - y, z);
             const m = data.waterMask;
             if (!m) {{ out.push(null); continue; }}
             const column = c => Array.from({{ length: m.length === 1 ? 1 : 256 }}, (_, r) => m[m.length === 1 ? 0 : r * 256 + c]);
             const mean = a => a.reduce((s, v) => s + v, 0) / a.length;
             out.push([m.length, mean(column(0)), mean(column(m.length === 1 ? 0 : 255))]);
           }}
           done([provider.hasWaterMask, out]);
         }})().catch(e => done(String(e)));",
        port = server.port,
        tiles = json!([sea, land, coast])
    ));
    eprintln!("Cesium's water masks (length, mean of the west column, of the east column): {masks}");
    assert_eq!(masks[0], json!(true), "Cesium sees no water mask: {masks}; console {:?}", browser.console());
    let mask = |i: usize| {
        masks[1][i]
            .as_array()
            .unwrap_or_else(|| panic!("{masks}"))
            .iter()
            .map(|v| v.as_f64().unwrap())
            .collect::<Vec<_>>()
    };
    assert_eq!(mask(0), vec![1.0, 255.0, 255.0], "the sea tile");
    assert_eq!(mask(1), vec![1.0, 0.0, 0.0], "the land tile");
    let coast = mask(2);
    assert_eq!(coast[0], 65_536.0, "the coast's tile holds a mask of 256 x 256");
    assert!(coast[1] > 250.0 && coast[2] < 5.0, "the coast's tile: west {} east {}", coast[1], coast[2]);

    // With the water layer, the land tile's basin is a lake: Cesium decodes the mask at
    // the lake's centre as water, the tile's corners (outside the lake) as land, and the
    // sea tile (which the mask says nothing of) still as all water.
    let [x, y, _] = land;
    let (x0, y0) = (f64::from(x) * d - 180.0, f64::from(y) * d - 90.0);
    let u = ((lake_centre.0 - x0) / d * 256.0) as usize;
    let v = ((y0 + d - lake_centre.1) / d * 256.0) as usize;
    let lake = browser.eval_async(&format!(
        "const done = arguments[0];
         (async () => {{
           const provider = await Cesium.CesiumTerrainProvider.fromUrl('http://127.0.0.1:{port}/lake', {{ requestWaterMask: true }});
           const out = [];
           for (const [x, y, z] of {tiles}) {{
             const data = await provider.requestTileGeometry(x, (2 ** z) - 1 - y, z);
             const m = data.waterMask;
             out.push(m ? [m.length, m.length === 1 ? m[0] : m[{v} * 256 + {u}], m.length === 1 ? m[0] : m[0], m.length === 1 ? m[0] : m[65535]] : null);
           }}
           done(out);
         }})().catch(e => done(String(e)));",
        port = server.port,
        tiles = json!([land, sea])
    ));
    eprintln!(
        "Cesium's water masks with the water layer (length, the lake's centre, north-west and south-east corners): {lake}"
    );
    let values = |i: usize| {
        lake[i].as_array().unwrap_or_else(|| panic!("{lake}")).iter().map(|v| v.as_f64().unwrap()).collect::<Vec<_>>()
    };
    let basin = values(0);
    assert_eq!(basin[0], 65_536.0, "the lake's tile holds a mask of 256 x 256: {lake}");
    assert_eq!(basin[1], 255.0, "the lake's centre at ({u}, {v}): {lake}");
    assert!(basin[2] == 0.0 && basin[3] == 0.0, "the corners, land: {lake}");
    assert_eq!(values(1), vec![1.0, 255.0, 255.0, 255.0], "the sea tile: {lake}");
}

/// The page of the water's picture: the quantized-mesh terrain at `terrain=` with its
/// water mask (`requestWaterMask`), a tan ground lit by the sun of the March equinox at
/// 13:20 UTC (noon at 20 W), no imagery, sky, fog or ground atmosphere, and Cesium's water
/// effect on, its waves made still by a flat normal map (`flat-normal.png`): without it
/// they move with the frame count and no two pictures agree.
const WATER_PAGE: &str = cesium_page!(
    r#"Cesium.CesiumTerrainProvider.fromUrl(q.get('terrain'), { requestWaterMask: true })
.then(terrainProvider => {
if (terrainProvider.errorEvent) terrainProvider.errorEvent.addEventListener(e => window.failures.push(String(e.message || e)));
const [viewer] = posedViewer({ terrainProvider, baseLayer: false, skyAtmosphere: false });
const scene = viewer.scene;
scene.backgroundColor = Cesium.Color.BLACK;
scene.globe.baseColor = Cesium.Color.fromCssColorString('#8c7b5c');
viewer.clock.shouldAnimate = false;
viewer.clock.currentTime = Cesium.JulianDate.fromIso8601('2024-03-20T13:20:00Z');
scene.globe.enableLighting = true;
scene.globe.showGroundAtmosphere = false;
scene.globe.showWaterEffect = true;
scene.globe.oceanNormalMapUrl = 'flat-normal.png';
scene.fog.enabled = false;
window.viewer = viewer;
}).catch(e => window.failures.push('terrain: ' + e));
"#
);

/// CesiumJS's water effect drawn from our water layer: the coast and its basin seen from
/// 6 km straight above the lake's centre, without the layer (the basin, 30 m below sea
/// level, is land by the flat-0 rule) and with it. Cesium lights its water with a blue
/// highlight and a specular term where the mask says water: the lake's pixels turn bluer
/// with the layer, the land around it and the sea to the west stay as they were, and the
/// picture with the layer matches a golden (`tests/golden/cesium-water.png`).
#[test]
fn cesium_draws_the_lake_of_the_water_layer_as_water() {
    use terrastream_testkit::browser::{Browser, Driver, WEBGL_FLAGS};
    let Some(build) = cesium_with_oracles() else { return };
    let dir = tempfile::tempdir().unwrap();
    let Coast { server, lake_centre: (lon, lat), .. } = coast_and_lake(dir.path());
    let Some(nginx) = cesium_host(dir.path(), &build, "water.html", WATER_PAGE) else { return };
    // A flat normal map (the tangent space's up), 4 x 4.
    let flat: Vec<u8> = [128, 128, 255, 255].repeat(16);
    terrastream_testkit::golden::write_png(&dir.path().join("www/flat-normal.png"), 4, 4, &flat);
    let driver = Driver::start();
    // A window larger than the globe's element, which the screenshot takes whole.
    let browser = Browser::open(&driver, WEBGL_FLAGS, (WIDTH + 200, HEIGHT + 300));
    // Both pictures, to look at.
    let look = Path::new(env!("CARGO_TARGET_TMPDIR")).join("cesium-water");
    std::fs::create_dir_all(&look).unwrap();
    let mut pictures = vec![];
    for name in ["coast", "lake"] {
        browser.goto(&format!(
            "http://127.0.0.1:{}/water.html?at={lon},{lat},6000&heading=0&pitch=-90&terrain=http://127.0.0.1:{}/{name}",
            nginx.port, server.port
        ));
        wait_for_cesium(&browser, "viewer.scene.globe.tilesLoaded");
        browser.eval("viewer.scene.requestRender(); return 0;");
        std::thread::sleep(std::time::Duration::from_millis(500));
        let picture = browser.screenshot("#globe");
        terrastream_testkit::golden::write_png(&look.join(format!("{name}.png")), picture.0, picture.1, &picture.2);
        pictures.push(picture);
    }
    let (w, h, _) = pictures[0];
    assert_eq!((w, h), (WIDTH, HEIGHT), "the globe's size");
    // The mean colour of a 30 x 30 pixel square centred on (x, y), in 0-255.
    let mean = |rgba: &[u8], (x, y): (u32, u32)| {
        let mut sum = [0.0f64; 3];
        for row in y - 15..y + 15 {
            for column in x - 15..x + 15 {
                let i = ((row * w + column) * 4) as usize;
                for c in 0..3 {
                    sum[c] += f64::from(rgba[i + c]) / 900.0;
                }
            }
        }
        sum
    };
    let blueness = |c: [f64; 3]| c[2] - c[0];
    // Straight above the lake's centre: the picture's centre. The coast lies 2.4 km west
    // (about 140 px at this height), the lake's shore 1.2 km around (about 65 px).
    let (centre, land, sea) = ((w / 2, h / 2), (w / 2 + 160, h / 2), (w / 2 - 250, h / 2));
    let [(coast_centre, coast_land, coast_sea), (lake_centre, lake_land, lake_sea)] =
        [&pictures[0].2, &pictures[1].2].map(|p| (mean(p, centre), mean(p, land), mean(p, sea)));
    eprintln!(
        "Cesium's mean colours (centre, land east, sea west): without the layer {coast_centre:.0?} {coast_land:.0?} \
         {coast_sea:.0?}, with it {lake_centre:.0?} {lake_land:.0?} {lake_sea:.0?}"
    );
    assert!(
        blueness(lake_centre) > blueness(coast_centre) + 30.0,
        "the lake is not drawn as water: {lake_centre:?} against the land {coast_centre:?}"
    );
    assert!(blueness(coast_sea) > blueness(coast_land) + 30.0, "the sea is water: {coast_sea:?}, {coast_land:?}");
    for (a, b, what) in [(coast_land, lake_land, "the land east of the lake"), (coast_sea, lake_sea, "the sea")] {
        assert!((0..3).all(|c| (a[c] - b[c]).abs() < 3.0), "{what} changed with the layer: {a:?} against {b:?}");
    }
    terrastream_testkit::golden::assert_golden("cesium-water", w, h, &pictures[1].2, TOLERANCE);
}

/// CesiumJS's globe as it draws itself: its sky atmosphere, its ground atmosphere and fog,
/// lit by the sun of the clock's time (`time`), over the Natural Earth II imagery it ships
/// (the picture our globe draws beyond the data). The page answers the sun's azimuth and
/// elevation at the camera (`window.sun`), to give our renderer the same sun.
const SKY_PAGE: &str = cesium_page!(
    r#"Cesium.TileMapServiceImageryProvider.fromUrl(Cesium.buildModuleUrl('Assets/Textures/NaturalEarthII'))
.then(imagery => {
const [viewer, at] = posedViewer({ baseLayer: new Cesium.ImageryLayer(imagery) });
const scene = viewer.scene;
viewer.clock.shouldAnimate = false;
viewer.clock.currentTime = Cesium.JulianDate.fromIso8601(q.get('time'));
scene.globe.enableLighting = true;
scene.postRender.addEventListener(() => {
  const sun = scene.context.uniformState.sunDirectionWC;
  const toEnu = Cesium.Matrix4.inverseTransformation(Cesium.Transforms.eastNorthUpToFixedFrame(at), new Cesium.Matrix4());
  const d = Cesium.Matrix4.multiplyByPointAsVector(toEnu, sun, new Cesium.Cartesian3());
  Cesium.Cartesian3.normalize(d, d);
  window.sun = [Cesium.Math.toDegrees(Math.atan2(d.x, d.y)), Cesium.Math.toDegrees(Math.asin(d.z))];
});
window.viewer = viewer;
}).catch(e => window.failures.push('imagery: ' + e));
"#
);

/// The mean colour of rows `rows` of a picture, in CIE L*a*b* (D65) from its sRGB.
fn mean_lab(w: u32, rgba: &[u8], rows: std::ops::Range<u32>) -> [f64; 3] {
    let linear = |c: u8| {
        let c = f64::from(c) / 255.0;
        if c <= 0.04045 { c / 12.92 } else { ((c + 0.055) / 1.055).powf(2.4) }
    };
    let mut sum = [0.0; 3];
    let mut n = 0.0;
    for y in rows {
        for x in 0..w {
            let i = ((y * w + x) * 4) as usize;
            for (s, c) in sum.iter_mut().zip(&rgba[i..i + 3]) {
                *s += linear(*c);
            }
            n += 1.0;
        }
    }
    let [r, g, b] = sum.map(|s| s / n);
    let xyz = [
        (0.4124 * r + 0.3576 * g + 0.1805 * b) / 0.95047,
        0.2126 * r + 0.7152 * g + 0.0722 * b,
        (0.0193 * r + 0.1192 * g + 0.9505 * b) / 1.08883,
    ];
    let f = |t: f64| if t > 216.0 / 24389.0 { t.cbrt() } else { (24389.0 / 27.0 * t + 16.0) / 116.0 };
    let [fx, fy, fz] = xyz.map(f);
    [116.0 * fy - 16.0, 500.0 * (fx - fy), 200.0 * (fy - fz)]
}

/// CIE76 colour distance.
fn delta_e(a: [f64; 3], b: [f64; 3]) -> f64 {
    a.iter().zip(&b).map(|(a, b)| (a - b).powi(2)).sum::<f64>().sqrt()
}

/// The sky and the haze beside CesiumJS's: the same pose and sun (Cesium's, from its
/// clock) over the Nevada desert, where both draw Natural Earth II; the sky near the
/// horizon, the haze on the ground below it and the sky at the zenith, each a band's
/// mean colour, within a stated CIE76 distance of Cesium's (measured: zenith 3.2,
/// horizon 14.0, ground haze 17.3; docs/rendering.md says where the rest comes from).
/// Both pictures, to look at: target/tmp/sky-beside-cesium/.
#[test]
fn the_sky_and_the_haze_look_like_cesiums() {
    use terrastream_testkit::browser::{Browser, Driver, WEBGL_FLAGS};
    let (build, missing) = cesium_build_or_missing();
    if !terrastream_testkit::browser::skip_or_fail("CESIUM", &missing) {
        return;
    }
    let dir = tempfile::tempdir().unwrap();
    // Our archive lies far from the view (the Tamalpais crop, in California): both
    // globes show their Natural Earth II picture there.
    let archive = archive(dir.path());
    let Some(nginx) = cesium_host(dir.path(), &build.unwrap(), "sky.html", SKY_PAGE) else {
        return;
    };
    let driver = Driver::start();
    let browser = Browser::open(&driver, WEBGL_FLAGS, (WIDTH + 200, HEIGHT + 300));
    // Three in the afternoon, local time, at the March equinox: the sun in the south-west.
    let (at, time) = ("-116,39,3000", "2026-03-20T22:44:00Z");
    let centre = HEIGHT / 2;
    let mut worst = Vec::new();
    for (name, heading, pitch, bands) in [
        // Looking north, level: the sky from 1° to 5° above the horizontal, the ground
        // from 2.5° to 4° below it (40 to 70 km away).
        (
            "level",
            0.0,
            0.0,
            vec![("horizon sky", centre - 33..centre - 7, 16.0), ("ground haze", centre + 17..centre + 27, 20.0)],
        ),
        ("zenith", 0.0, 90.0, vec![("zenith sky", centre - 40..centre + 40, 6.0)]),
    ] {
        browser.goto(&format!(
            "http://127.0.0.1:{}/sky.html?at={at}&heading={heading}&pitch={pitch}&time={time}",
            nginx.port
        ));
        wait_for_cesium(&browser, "window.sun && viewer.scene.globe.tilesLoaded");
        let sun = browser.eval("return window.sun;");
        let (azimuth, elevation) = (sun[0].as_f64().unwrap(), sun[1].as_f64().unwrap());
        let (cw, ch, cesium) = browser.screenshot("#globe");
        let sun = format!("{azimuth:.3},{elevation:.3}");
        let pose = (name, archive.as_path(), at, heading, pitch);
        let (w, _, ours) = ours_beside(dir.path(), pose, &["--sun", &sun], (cw, ch, &cesium), "sky-beside-cesium");
        for (band, rows, bound) in bands {
            let (theirs, mine) = (mean_lab(cw, &cesium, rows.clone()), mean_lab(w, &ours, rows));
            let distance = delta_e(theirs, mine);
            eprintln!(
                "{band} (sun {azimuth:.1}° azimuth, {elevation:.1}° up): Cesium L*a*b* {theirs:.1?}, ours {mine:.1?}: ΔE {distance:.1}"
            );
            worst.push((band, distance, bound));
        }
    }
    for (band, distance, bound) in worst {
        assert!(distance <= bound, "{band}: ΔE {distance:.1} from Cesium's, more than {bound}");
    }
}
