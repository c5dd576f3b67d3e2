//! The clients people already use read our archives, checked with those clients and with
//! GDAL as the oracle of the source's heights:
//! - MapLibre GL JS (npm, pinned in `scripts/test.sh`), unchanged, in headless Chromium:
//!   a style with the served TileJSON as `terrain` and `hillshade`; its
//!   `queryTerrainElevation` at random points against GDAL's bilinear value of the source
//!   DEM; no tile request fails; a screenshot against a golden. The same page against the
//!   `export --to xyz` folder served by nginx, and against the PMTiles export (npm
//!   `pmtiles` protocol).
//! - The elevation API at the same points, and its error answers.
//! - A Terrarium PNG tile decoded by Pillow (an independent decoder) against the heights
//!   the server meant.
//!
//! The source is the committed 1" SRTM crop, tiled with the default settings (a
//! transverse Mercator: every web tile is reprojected).
#![allow(clippy::unwrap_used, clippy::expect_used, clippy::cast_possible_truncation, missing_docs)]

use std::path::{Path, PathBuf};
use std::process::Command;
use std::time::{Duration, Instant};

use serde_json::{Value, json};
use terrastream_testkit::browser::{Browser, Driver, WEBGL_FLAGS};

#[path = "support/oracles.rs"]
mod oracles;
use oracles::{archive, errors, gdal_bilinear, npm_cache, random_points, snippet, terrastream};

/// The MapLibre GL JS release the tests load (installed by `scripts/test.sh`).
const MAPLIBRE: &str = "5.24.1";
/// The deck.gl release the tests load (its bundle, installed by `scripts/test.sh`).
const DECKGL: &str = "9.2.6";
const WIDTH: u32 = 640;
const HEIGHT: u32 = 400;
/// Random points inside the data.
const POINTS: usize = 40;

/// MapLibre draws with SwiftShader's WebGL: deterministic for one Chromium build; the
/// allowance covers another release's anti-aliasing and dithering.
const TOLERANCE: terrastream_testkit::golden::Tolerance =
    terrastream_testkit::golden::Tolerance { mean: 2.0, pixel: 32, off_share: 0.02 };

/// MapLibre GL JS's `dist` folder, from the npm cache `scripts/test.sh` fills.
fn maplibre_dist() -> Option<PathBuf> {
    let root = npm_cache();
    let dist = root.join("node_modules/maplibre-gl/dist");
    let package = std::fs::read_to_string(root.join("node_modules/maplibre-gl/package.json")).ok()?;
    let version: Value = serde_json::from_str(&package).ok()?;
    let pmtiles = root.join("node_modules/pmtiles/dist/pmtiles.js").exists();
    (version["version"] == json!(MAPLIBRE) && dist.join("maplibre-gl.js").exists() && pmtiles).then_some(dist)
}

fn ready() -> Option<PathBuf> {
    let mut missing = terrastream_testkit::browser::missing();
    let dist = maplibre_dist();
    if dist.is_none() {
        missing.push(
            "maplibre-gl and pmtiles (npm install --prefix ~/.cache/terrastream-npm maplibre-gl@5.24.1 pmtiles@4.5.0)",
        );
    }
    for tool in ["gdaltransform", "gdallocationinfo"] {
        if Command::new(tool).arg("--version").output().is_err() {
            missing.push("GDAL's command-line tools (apt-get install gdal-bin)");
        }
    }
    terrastream_testkit::browser::skip_or_fail("MAPLIBRE", &missing).then(|| dist.unwrap())
}

/// The documented MapLibre pages, in `folder` (MapLibre's and pmtiles' files beside
/// them): `index.html` reads a TileJSON, `pmtiles.html` a PMTiles file.
fn write_page(folder: &Path, dist: &Path) {
    std::fs::create_dir_all(folder).unwrap();
    for file in ["maplibre-gl.js", "maplibre-gl.css"] {
        std::fs::copy(dist.join(file), folder.join(file)).unwrap();
    }
    let pmtiles = dist.join("../../pmtiles/dist/pmtiles.js");
    std::fs::copy(&pmtiles, folder.join("pmtiles.js")).unwrap_or_else(|e| panic!("{}: {e}", pmtiles.display()));
    for (name, file) in [("maplibre-page", "index.html"), ("maplibre-pmtiles-page", "pmtiles.html")] {
        let page = snippet(name);
        assert!(page.contains(&format!("width: {WIDTH}px; height: {HEIGHT}px")), "{name}: the map's size changed");
        std::fs::write(folder.join(file), page).unwrap();
    }
}

/// Loads the page with `tilejson`, waits until MapLibre is idle, and returns its
/// elevations at `points` (after checking no request failed) and a screenshot.
fn maplibre_run(browser: &Browser<'_>, page: &str, points: &[(f64, f64)]) -> (Vec<Option<f64>>, (u32, u32, Vec<u8>)) {
    browser.goto(page);
    let started = Instant::now();
    loop {
        let state = browser.eval("return [window.idle === true, window.failures];");
        assert_eq!(state[1], json!([]), "MapLibre reported errors on {page}: console {:?}", browser.console());
        if state[0] == json!(true) {
            break;
        }
        assert!(started.elapsed() < Duration::from_secs(90), "MapLibre never became idle on {page}");
        std::thread::sleep(Duration::from_millis(200));
    }
    let picture = browser.screenshot("#map");
    // The points looked at closely (zoom 13: the terrain's finest tiles, which MapLibre
    // takes a zoom coarser than the view's): a view is moved only for a point outside
    // the middle of the current one.
    browser.call("POST", "/timeouts", Some(json!({ "script": 300_000 })));
    let list: Vec<[f64; 2]> = points.iter().map(|&(lon, lat)| [lon, lat]).collect();
    let heights = browser.eval_async(&format!(
        "const done = arguments[0]; const map = window.map; const points = {};
         const out = new Array(points.length).fill(null);
         const order = points.map((p, i) => i).sort((a, b) => points[a][1] - points[b][1] || points[a][0] - points[b][0]);
         window.views = 0;
         (async () => {{
           for (const i of order) {{
             const p = points[i];
             const b = map.getBounds();
             const [w, s, e, n] = [b.getWest(), b.getSouth(), b.getEast(), b.getNorth()];
             const inside = map.getZoom() >= 13 && p[0] > w + (e - w) * 0.1 && p[0] < e - (e - w) * 0.1
               && p[1] > s + (n - s) * 0.1 && p[1] < n - (n - s) * 0.1;
             if (!inside) {{
               map.jumpTo({{ center: p, zoom: 13 }});
               window.views += 1;
               await new Promise(r => map.once('idle', r));
             }}
             out[i] = map.queryTerrainElevation(p);
           }}
           done(out);
         }})().catch(e => done(String(e)));",
        json!(list)
    ));
    eprintln!("{page}: {} views to query {} points", browser.eval("return window.views;"), points.len());
    let failures = browser.eval("return window.failures;");
    assert_eq!(failures, json!([]), "MapLibre reported errors on {page}: console {:?}", browser.console());
    let heights = heights.as_array().unwrap_or_else(|| panic!("{heights}")).iter().map(Value::as_f64).collect();
    (heights, picture)
}

#[test]
fn maplibre_reads_the_served_and_the_exported_terrain() {
    let Some(dist) = ready() else { return };
    let dir = tempfile::tempdir().unwrap();
    let archive = archive(dir.path());
    let exe = Path::new(env!("CARGO_BIN_EXE_terrastream"));
    let server = terrastream_testkit::server::spawn_serve(exe, &[archive.to_str().unwrap()], dir.path());
    let (status, body) = terrastream_testkit::http::request(server.port, "GET", "/tamalpais/tiles.json", None);
    assert_eq!(status, 200, "{}", String::from_utf8_lossy(&body));
    let tilejson: Value = serde_json::from_slice(&body).unwrap();
    assert_eq!((tilejson["type"].as_str(), tilejson["encoding"].as_str()), (Some("raster-dem"), Some("terrarium")));
    let bounds: [f64; 4] = serde_json::from_value(tilejson["bounds"].clone()).unwrap();
    let points = random_points(bounds, POINTS);
    let truth = gdal_bilinear(&points);

    // The static host, the export under a sub-path (/xyz/) and the page at the root: the
    // export's tiles.json holds absolute tile URLs under its --base-url.
    let root = dir.path().join("www");
    std::fs::create_dir_all(&root).unwrap();
    write_page(&root, &dist);
    let Some(nginx) = terrastream_testkit::nginx::start_nginx(
        &root,
        "server { listen 127.0.0.1:{port}; root {root}; types { image/webp webp; application/json json; \
         text/html html; application/javascript js; text/css css; } add_header Access-Control-Allow-Origin *; }",
    ) else {
        return;
    };
    let xyz = root.join("xyz");
    let base = format!("http://127.0.0.1:{}/xyz/", nginx.port);
    terrastream(&[
        "export",
        archive.to_str().unwrap(),
        "--to",
        "xyz",
        "--base-url",
        &base,
        "-o",
        xyz.to_str().unwrap(),
    ]);
    let pmtiles_file = root.join("tamalpais.pmtiles");
    let (a, p) = (archive.to_str().unwrap(), pmtiles_file.to_str().unwrap());
    terrastream(&["export", a, "--to", "pmtiles", "--encoding", "terrarium", "-o", p]);
    let driver = Driver::start();
    let browser = Browser::open(&driver, WEBGL_FLAGS, (WIDTH, HEIGHT));
    let served = format!(
        "http://127.0.0.1:{}/index.html?tilejson=http://127.0.0.1:{}/tamalpais/tiles.json",
        nginx.port, server.port
    );
    let exported = format!("http://127.0.0.1:{0}/index.html?tilejson=http://127.0.0.1:{0}/xyz/tiles.json", nginx.port);
    let pmtiles =
        format!("http://127.0.0.1:{0}/pmtiles.html?pmtiles=http://127.0.0.1:{0}/tamalpais.pmtiles", nginx.port);
    let mut pictures = Vec::new();
    for (name, page) in [("served", served), ("exported", exported), ("PMTiles", pmtiles)] {
        let (heights, picture) = maplibre_run(&browser, &page, &points);
        assert!(heights.iter().all(Option::is_some), "{name}: MapLibre has no height at some points: {heights:?}");
        let heights: Vec<f64> = heights.into_iter().flatten().collect();
        let (median, p90) = errors(&heights, &truth);
        eprintln!("MapLibre {name}: |height - GDAL bilinear| median {median:.2} m, 90 % within {p90:.2} m");
        assert!(median <= 2.0 && p90 <= 15.0, "{name}: median {median:.2} m, p90 {p90:.2} m");
        pictures.push(picture);
    }
    let (w, h, rgba) = &pictures[0];
    terrastream_testkit::golden::assert_golden("maplibre-hillshade", *w, *h, rgba, TOLERANCE);
    // Bit for bit the same tiles: the pictures are one.
    for (name, picture) in ["exported", "PMTiles"].iter().zip(&pictures[1..]) {
        let (mean, _) = terrastream_testkit::golden::difference(rgba, &picture.2, 0);
        assert!(mean < 0.01, "the {name} tiles draw differently from the served ones: mean difference {mean}");
    }
}

/// A key of `terrastream key new` for `archives`, in `dir`'s keys file.
fn new_key(dir: &Path, archives: &str) -> String {
    let out = Command::new(env!("CARGO_BIN_EXE_terrastream"))
        .args(["key", "new", "--archives", archives, "--keys", "keys.toml"])
        .current_dir(dir)
        .output()
        .unwrap();
    assert!(out.status.success(), "{}", String::from_utf8_lossy(&out.stderr));
    String::from_utf8(out.stdout).unwrap().trim().to_owned()
}

/// A private archive read by MapLibre, as documented: with the key only in the TileJSON's
/// URL (carried into the tile URLs by the server), and with `transformRequest` sending it
/// in a header (across origins: the preflight allows it). Both draw the public archive's
/// picture, with heights as close to GDAL's; without a key, MapLibre gets nothing.
#[test]
fn maplibre_reads_private_terrain_with_a_key_in_the_url_or_a_header() {
    let Some(dist) = ready() else { return };
    let dir = tempfile::tempdir().unwrap();
    let archive = archive(dir.path());
    let key = new_key(dir.path(), "tamalpais");
    let exe = Path::new(env!("CARGO_BIN_EXE_terrastream"));
    let args = [archive.to_str().unwrap(), "--private", "--keys", "keys.toml"];
    let server = terrastream_testkit::server::spawn_serve(exe, &args, dir.path());
    let (status, _) = terrastream_testkit::http::request(server.port, "GET", "/tamalpais/tiles.json", None);
    assert_eq!(status, 401, "no key, no TileJSON");
    let (_, body) = terrastream_testkit::http::request(
        server.port,
        "GET",
        &format!("/tamalpais/tiles.json?access_token={key}"),
        None,
    );
    let tilejson: Value = serde_json::from_slice(&body).unwrap();
    let bounds: [f64; 4] = serde_json::from_value(tilejson["bounds"].clone()).unwrap();
    let points = random_points(bounds, POINTS / 4);
    let truth = gdal_bilinear(&points);
    let root = dir.path().join("www");
    write_page(&root, &dist);
    std::fs::write(root.join("key.html"), snippet("maplibre-key-page")).unwrap();
    let Some(nginx) = terrastream_testkit::nginx::start_nginx(
        &root,
        "server { listen 127.0.0.1:{port}; root {root}; types { text/html html; application/javascript js; \
         text/css css; } }",
    ) else {
        return;
    };
    let driver = Driver::start();
    let browser = Browser::open(&driver, WEBGL_FLAGS, (WIDTH, HEIGHT));
    let tiles = format!("http://127.0.0.1:{}/tamalpais/tiles.json", server.port);
    let in_url = format!("http://127.0.0.1:{}/index.html?tilejson={tiles}?access_token={key}", nginx.port);
    let in_header = format!("http://127.0.0.1:{}/key.html?tilejson={tiles}&key={key}", nginx.port);
    for (name, page) in [("key in the URL", in_url), ("key in a header", in_header)] {
        let (heights, (w, h, rgba)) = maplibre_run(&browser, &page, &points);
        assert!(heights.iter().all(Option::is_some), "{name}: MapLibre has no height at some points: {heights:?}");
        let heights: Vec<f64> = heights.into_iter().flatten().collect();
        let (median, p90) = errors(&heights, &truth);
        eprintln!("MapLibre, private, {name}: median {median:.2} m, 90 % within {p90:.2} m");
        assert!(median <= 2.0 && p90 <= 15.0, "{name}: median {median:.2} m, p90 {p90:.2} m");
        terrastream_testkit::golden::assert_golden("maplibre-hillshade", w, h, &rgba, TOLERANCE);
    }
}

/// The documented topographic page: MapLibre draws our terrain in 3D with the hillshade
/// raster and the contour lines over it (metres and feet), no request failing; the
/// picture against a golden, and contours drawn (the brown of the lines is on screen).
#[test]
fn maplibre_draws_a_topographic_map_of_hillshade_and_contours() {
    let Some(dist) = ready() else { return };
    let dir = tempfile::tempdir().unwrap();
    let archive = archive(dir.path());
    let exe = Path::new(env!("CARGO_BIN_EXE_terrastream"));
    let fonts = Path::new("/usr/share/fonts/truetype/dejavu");
    assert!(fonts.join("DejaVuSans.ttf").exists(), "DejaVu's fonts (apt-get install fonts-dejavu-core)");
    let args = [archive.to_str().unwrap(), "--fonts", fonts.to_str().unwrap()];
    let server = terrastream_testkit::server::spawn_serve(exe, &args, dir.path());
    let root = dir.path().join("www");
    write_page(&root, &dist);
    std::fs::write(root.join("topo.html"), snippet("maplibre-topo-page")).unwrap();
    let Some(nginx) = terrastream_testkit::nginx::start_nginx(
        &root,
        "server { listen 127.0.0.1:{port}; root {root}; types { text/html html; application/javascript js; \
         text/css css; } }",
    ) else {
        return;
    };
    let driver = Driver::start();
    let browser = Browser::open(&driver, WEBGL_FLAGS, (WIDTH, HEIGHT));
    let base = format!("http://127.0.0.1:{}/tamalpais", server.port);
    // Labels' glyphs from the same server (DejaVu Sans for any stack it does not hold).
    let glyphs = format!("http://127.0.0.1:{}/fonts/{{fontstack}}/{{range}}.pbf", server.port);
    let brown =
        |rgba: &[u8]| rgba.chunks_exact(4).filter(|p| u16::from(p[0]) > u16::from(p[2]) + 40 && p[1] > p[2]).count();
    let mut unlabelled = Vec::new();
    for (units, golden, labels) in
        [("m", "maplibre-topo", false), ("ft", "maplibre-topo-feet", false), ("ft", "maplibre-topo-labels", true)]
    {
        let mut page = format!("http://127.0.0.1:{}/topo.html?archive={base}&units={units}", nginx.port);
        if labels {
            page.push_str(&format!("&labels=all&glyphs={}", glyphs.replace('{', "%7B").replace('}', "%7D")));
        }
        let (_, (w, h, rgba)) = maplibre_run(&browser, &page, &[]);
        // Contour lines drawn: pixels of their brown, not only the hillshade's grays.
        let lines = brown(&rgba);
        assert!(lines > 500, "{units}: {lines} pixels of contour lines");
        if labels {
            // Labels placed and drawn where the unlabelled map of the same units has
            // none, with glyphs from us (MapLibre draws a range it cannot load with the
            // browser's own font instead: the server's count of glyph ranges says).
            let (_, metrics) = terrastream_testkit::http::request(server.port, "GET", "/metrics", None);
            let metrics = String::from_utf8_lossy(&metrics);
            let served = "terrastream_requests_total{route=\"/fonts/{fontstack}/{range}\",status=\"200\"}";
            assert!(metrics.contains(served), "no glyph range served: {metrics}");
            let changed = rgba.chunks_exact(4).zip(unlabelled.chunks_exact(4)).filter(|(a, b)| a != b).count();
            let placed = browser.eval("return window.map.queryRenderedFeatures({ layers: ['labels'] }).length;");
            assert!(
                changed > 300 && placed.as_u64().is_some_and(|n| n > 0),
                "labels: {placed} placed, {changed} pixels changed; console {:?}",
                browser.console()
            );
        } else {
            unlabelled = rgba.clone();
        }
        terrastream_testkit::golden::assert_golden(golden, w, h, &rgba, TOLERANCE);
    }
}

/// deck.gl's standalone bundle, from the npm cache `scripts/test.sh` fills.
fn deckgl_bundle() -> Option<PathBuf> {
    let root = npm_cache();
    let bundle = root.join(format!("deck.gl-{DECKGL}/dist.min.js"));
    (bundle.exists() && bundle.with_file_name("terrain-worker.js").exists()).then_some(bundle)
}

#[test]
fn deckgl_meshes_the_served_terrain() {
    let mut missing = terrastream_testkit::browser::missing();
    let bundle = deckgl_bundle();
    if bundle.is_none() {
        missing.push("deck.gl's bundle (scripts/test.sh: npm pack deck.gl@9.2.6)");
    }
    if !terrastream_testkit::browser::skip_or_fail("DECK.GL", &missing) {
        return;
    }
    let dir = tempfile::tempdir().unwrap();
    let archive = archive(dir.path());
    let exe = Path::new(env!("CARGO_BIN_EXE_terrastream"));
    let server = terrastream_testkit::server::spawn_serve(exe, &[archive.to_str().unwrap()], dir.path());
    let root = dir.path().join("www");
    std::fs::create_dir_all(&root).unwrap();
    let bundle = bundle.unwrap();
    std::fs::copy(&bundle, root.join("deck.gl.min.js")).unwrap();
    std::fs::copy(bundle.with_file_name("terrain-worker.js"), root.join("terrain-worker.js")).unwrap();
    let page = snippet("deckgl-page");
    assert!(page.contains(&format!("width: {WIDTH}px; height: {HEIGHT}px")), "the map's size changed");
    std::fs::write(root.join("index.html"), page).unwrap();
    let Some(nginx) = terrastream_testkit::nginx::start_nginx(
        &root,
        "server { listen 127.0.0.1:{port}; root {root}; types { text/html html; application/javascript js; } }",
    ) else {
        return;
    };
    let driver = Driver::start();
    let browser = Browser::open(&driver, WEBGL_FLAGS, (WIDTH, HEIGHT));
    browser.goto(&format!(
        "http://127.0.0.1:{}/index.html?tilejson=http://127.0.0.1:{}/tamalpais/tiles.json",
        nginx.port, server.port
    ));
    let started = Instant::now();
    loop {
        let state = browser.eval("return [!!(window.terrain && window.terrain.isLoaded), window.failures];");
        assert_eq!(state[1], json!([]), "deck.gl reported errors: console {:?}", browser.console());
        if state[0] == json!(true) {
            break;
        }
        assert!(started.elapsed() < Duration::from_secs(90), "deck.gl never loaded its view: {:?}", browser.console());
        std::thread::sleep(Duration::from_millis(200));
    }
    std::thread::sleep(Duration::from_millis(500));
    let (w, h, rgba) = browser.screenshot("#map");
    // Terrain drawn: most of the view is the mesh's colour, not the empty background.
    let drawn = rgba.chunks_exact(4).filter(|p| p[3] > 0 && (p[0], p[1], p[2]) != (255, 255, 255)).count();
    assert!(drawn * 3 > (w * h) as usize, "deck.gl drew terrain over only {drawn} of {} pixels", w * h);
    terrastream_testkit::golden::assert_golden("deckgl-terrain", w, h, &rgba, TOLERANCE);
}

#[test]
fn the_elevation_api_agrees_with_gdal_and_names_bad_requests() {
    if Command::new("gdaltransform").arg("--version").output().is_err() {
        assert!(std::env::var_os("CI").is_none(), "gdal-bin is required on CI");
        return;
    }
    let dir = tempfile::tempdir().unwrap();
    let archive = archive(dir.path());
    let exe = Path::new(env!("CARGO_BIN_EXE_terrastream"));
    let server = terrastream_testkit::server::spawn_serve(exe, &[archive.to_str().unwrap()], dir.path());
    let get = |path: &str| {
        let (status, body) = terrastream_testkit::http::request(server.port, "GET", path, None);
        (status, serde_json::from_slice::<Value>(&body).unwrap_or(Value::Null))
    };
    let (_, tilejson) = get("/tamalpais/tiles.json");
    let bounds: [f64; 4] = serde_json::from_value(tilejson["bounds"].clone()).unwrap();
    let points = random_points(bounds, POINTS);
    let truth = gdal_bilinear(&points);
    let locations: Vec<String> = points.iter().map(|(lon, lat)| format!("{lat},{lon}")).collect();
    let (status, answer) = get(&format!("/v1/tamalpais?locations={}", locations.join("|")));
    assert_eq!(status, 200, "{answer}");
    assert_eq!(answer["status"], json!("OK"));
    let results = answer["results"].as_array().unwrap();
    assert_eq!(results.len(), POINTS);
    assert!(results.iter().all(|r| r["dataset"] == json!("tamalpais")));
    let heights: Vec<f64> = results.iter().map(|r| r["elevation"].as_f64().unwrap()).collect();
    let (median, p90) = errors(&heights, &truth);
    eprintln!("elevation API: |height - GDAL bilinear| median {median:.2} m, 90 % within {p90:.2} m");
    assert!(median <= 1.0 && p90 <= 3.0, "median {median:.2} m, p90 {p90:.2} m");
    // The same by POST, with [lat, lng] pairs; a profile along them; nearest and cubic.
    let pairs: Vec<[f64; 2]> = points.iter().map(|&(lon, lat)| [lat, lon]).collect();
    let body = json!({ "locations": pairs, "interpolation": "cubic" });
    let (status, bytes) = terrastream_testkit::http::request(server.port, "POST", "/v1/tamalpais", Some(&body));
    let posted: Value = serde_json::from_slice(&bytes).unwrap();
    assert_eq!(status, 200, "{posted}");
    let cubic: Vec<f64> =
        posted["results"].as_array().unwrap().iter().map(|r| r["elevation"].as_f64().unwrap()).collect();
    let (median, _) = errors(&cubic, &truth);
    assert!(median <= 1.5, "cubic: median {median:.2} m");
    let (_, profile) = get(&format!("/v1/tamalpais?locations={}|{}&samples=11", locations[0], locations[1]));
    assert_eq!(profile["results"].as_array().map(Vec::len), Some(11), "{profile}");
    // The documented curl calls.
    let calls = snippet("elevation-curl")
        .replace("\\\n", " ")
        .replace("http://localhost:8080", &format!("http://127.0.0.1:{}", server.port));
    let calls: Vec<&str> = calls.lines().filter(|l| l.starts_with("curl ")).collect();
    assert_eq!(calls.len(), 3, "{calls:?}");
    for call in calls {
        let out = Command::new("sh").args(["-c", &format!("{call} --silent --show-error --fail")]).output().unwrap();
        assert!(out.status.success(), "{call}: {}", String::from_utf8_lossy(&out.stderr));
        let answer: Value = serde_json::from_slice(&out.stdout).unwrap();
        assert_eq!(answer["status"], json!("OK"), "{call}: {answer}");
    }
    // Outside the data: null.
    let (_, far) = get("/v1/tamalpais?locations=10,10");
    assert_eq!(far["results"][0]["elevation"], Value::Null, "{far}");
    // Every bad request: 400 (404 for an unknown archive) naming its bad part.
    let too_many = vec!["37.9,-122.6"; 101].join("|");
    for (path, status, says) in [
        ("/v1/tamalpais?locations=91,0".to_owned(), 400, "latitude 91"),
        ("/v1/tamalpais?locations=37.9,-200".to_owned(), 400, "longitude -200"),
        ("/v1/tamalpais?locations=37.9".to_owned(), 400, "polyline"),
        (format!("/v1/tamalpais?locations={too_many}"), 400, "Too many locations provided (101)"),
        ("/v1/tamalpais?locations=37.9,-122.6&interpolation=spline".to_owned(), 400, "interpolation 'spline'"),
        ("/v1/tamalpais?locations=37.9,-122.6|37.91,-122.6&samples=0".to_owned(), 400, "samples"),
        ("/v1/tamalpais".to_owned(), 400, "No locations"),
        ("/v1/nowhere?locations=37.9,-122.6".to_owned(), 404, "nowhere"),
    ] {
        let (got, answer) = get(&path);
        assert_eq!(got, status, "{path}: {answer}");
        let expected = if status == 404 { "NOT_FOUND" } else { "INVALID_REQUEST" };
        assert_eq!(answer["status"], json!(expected), "{path}: {answer}");
        assert!(answer["error"].as_str().unwrap().contains(says), "{path}: {answer}");
    }
    let (status, bytes) =
        terrastream_testkit::http::request(server.port, "POST", "/v1/tamalpais", Some(&json!({"locations": 5})));
    assert_eq!(status, 400, "{}", String::from_utf8_lossy(&bytes));
}

#[test]
fn a_terrarium_tile_decoded_by_pillow_holds_the_heights_meant() {
    let pillow = Command::new("/usr/bin/python3").args(["-c", "import PIL"]).status().is_ok_and(|s| s.success());
    if !pillow {
        assert!(std::env::var_os("CI").is_none(), "python3-pil is required on CI");
        eprintln!("\n*** SKIPPING: Pillow (python3-pil) is not installed ***\n");
        return;
    }
    let dir = tempfile::tempdir().unwrap();
    let archive = archive(dir.path());
    let exe = Path::new(env!("CARGO_BIN_EXE_terrastream"));
    let server = terrastream_testkit::server::spawn_serve(exe, &[archive.to_str().unwrap()], dir.path());
    // The tile over Mount Tamalpais's summit at the finest zoom, as PNG.
    use terrastream_views::encode::{HeightEncoding, ImageFormat};
    use terrastream_views::mercator::{WebTile, tiles_over};
    use terrastream_views::{WebTileRequest, tile_samples};
    let (columns, rows) = tiles_over(12, [-122.5965, 37.9235, -122.5965, 37.9235]);
    let tile = WebTile::new(12, *columns.start(), *rows.start()).unwrap();
    let path = format!("/tamalpais/xyz/elevation/{}/{}/{}.png", tile.z, tile.x, tile.y);
    let (status, png) = terrastream_testkit::http::request(server.port, "GET", &path, None);
    assert_eq!(status, 200);
    let file = dir.path().join("tile.png");
    std::fs::write(&file, &png).unwrap();
    let script = "import sys\nfrom PIL import Image\nim = Image.open(sys.argv[1]).convert('RGBA')\n\
                  for r, g, b, a in im.getdata():\n    print(r * 256 + g + b / 256 - 32768 if a else 'nan')\n";
    let out = Command::new("/usr/bin/python3").args(["-c", script, file.to_str().unwrap()]).output().unwrap();
    assert!(out.status.success(), "{}", String::from_utf8_lossy(&out.stderr));
    let decoded: Vec<f64> = String::from_utf8(out.stdout).unwrap().lines().map(|l| l.parse().unwrap()).collect();
    let reader = terrastream_format::Reader::open_mmap(&archive).unwrap();
    let request = WebTileRequest {
        layer: reader.metadata().resolve_layer("elevation").unwrap(),
        tile,
        encoding: Some(HeightEncoding::Terrarium),
        format: ImageFormat::Png,
        size: 512,
    };
    let (meant, _) = tile_samples(&reader, &request).unwrap().unwrap();
    assert_eq!(decoded.len(), meant.len());
    let mut with_data = 0;
    for (d, m) in decoded.iter().zip(&meant) {
        assert_eq!(d.is_nan(), m.is_nan(), "no data in one and not the other");
        if m.is_finite() {
            with_data += 1;
            assert!((d - f64::from(*m)).abs() <= 0.5 / 256.0 + 1e-9, "Pillow reads {d}, the server meant {m}");
        }
    }
    assert!(with_data > 1000, "the summit's tile holds data: {with_data} pixels");
}

/// A collection (a 10" base raised 3 m and a 1" patch: docs/tiling.md, "Collections") read
/// by MapLibre through its TileJSON: every tile it asks for is served (no failed request,
/// the base's area included, whose finest level is coarser), and inside the patch its
/// heights are those it reads from the same inputs tiled at one resolution (where the
/// patch wins at LOD 0), and GDAL's bilinear heights of the 1" DEM within MapLibre's own
/// sampling on that steep ground.
#[test]
fn maplibre_reads_a_collection_of_a_base_and_a_patch() {
    let Some(dist) = ready() else { return };
    let dir = tempfile::tempdir().unwrap();
    let repo = oracles::repo();
    let (collection, one) = (dir.path().join("collection.tspack"), dir.path().join("one.tspack"));
    for (out, priority) in [(&collection, "resolution"), (&one, "order")] {
        terrastream(&[
            "tile",
            "--elevation",
            repo.join("tests/data/collection-base-10s-plus3m.tif").to_str().unwrap(),
            repo.join("tests/data/collection-patch-1s.tif").to_str().unwrap(),
            "--tile-size",
            "64",
            "--priority",
            priority,
            "-o",
            out.to_str().unwrap(),
        ]);
    }
    let exe = Path::new(env!("CARGO_BIN_EXE_terrastream"));
    let server = terrastream_testkit::server::spawn_serve(
        exe,
        &[collection.to_str().unwrap(), one.to_str().unwrap()],
        dir.path(),
    );
    let root = dir.path().join("www");
    write_page(&root, &dist);
    let Some(nginx) = terrastream_testkit::nginx::start_nginx(
        &root,
        "server { listen 127.0.0.1:{port}; root {root}; types { application/json json; text/html html; \
         application/javascript js; text/css css; } }",
    ) else {
        return;
    };
    // Inside the patch (pixels 80..240 of the 1" crop) beyond its blend band, and over the
    // base beyond the patch.
    let inside = random_points([-122.611, 37.906, -122.583, 37.938], POINTS / 2);
    let outside: Vec<(f64, f64)> = random_points([-122.64, 37.87, -122.555, 37.965], POINTS * 2)
        .into_iter()
        .filter(|&(lon, lat)| !(-122.624..=-122.571).contains(&lon) || !(37.896..=37.949).contains(&lat))
        .take(POINTS / 2)
        .collect();
    let points: Vec<(f64, f64)> = inside.iter().chain(&outside).copied().collect();
    let truth = gdal_bilinear(&inside);
    let driver = Driver::start();
    let browser = Browser::open(&driver, WEBGL_FLAGS, (WIDTH, HEIGHT));
    let read = |name: &str| {
        let page = format!(
            "http://127.0.0.1:{}/index.html?tilejson=http://127.0.0.1:{}/{name}/tiles.json",
            nginx.port, server.port
        );
        let (heights, _) = maplibre_run(&browser, &page, &points);
        assert!(heights.iter().all(Option::is_some), "{name}: MapLibre has no height at some points: {heights:?}");
        heights.into_iter().flatten().collect::<Vec<f64>>()
    };
    let (ours, theirs) = (read("collection"), read("one"));
    let (median, p90) = errors(&ours[..inside.len()], &theirs[..inside.len()]);
    let (gdal, gdal90) = errors(&ours[..inside.len()], &truth);
    eprintln!(
        "MapLibre on a collection, inside the patch: |height - one resolution's| median {median:.2} m, \
         90 % within {p90:.2} m; |height - GDAL bilinear| median {gdal:.2} m, 90 % within {gdal90:.2} m"
    );
    assert!(median <= 0.1 && p90 <= 0.5, "against one resolution: median {median:.2} m, p90 {p90:.2} m");
    assert!(gdal <= 4.0 && gdal90 <= 15.0, "against GDAL: median {gdal:.2} m, p90 {gdal90:.2} m");
}
