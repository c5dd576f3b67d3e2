//! The webplayer end to end, in headless Chromium driven through chromedriver (WebDriver):
//! - from `terrastream serve` (`/view/{name}`, the player embedded in the binary), on WebGPU;
//! - from nginx serving only static files (`terrastream player -o`, the shipped
//!   `deploy/nginx/tspack-static.conf`), the archive on a second origin (CORS), on WebGL2;
//! - the messages for an archive that does not load and for a browser without WebGL2.
//!
//! Each run streams the committed Tamalpais DEM until the view is complete, compares a
//! screenshot of the canvas with a reference in `tests/golden/`, reads the browser's
//! console (no errors allowed) and counts the HTTP requests at the server against what
//! the page reports and what the tiles need.
//!
//! Needs Debian's `chromium` and `chromium-driver` and a binary built with the player
//! (`scripts/build-player.sh` first); the test command provides all three. Without them
//! the tests fail, unless `TERRASTREAM_ALLOW_NO_BROWSER=1` (then they skip loudly).
#![allow(clippy::unwrap_used, clippy::expect_used, clippy::cast_possible_truncation, missing_docs)]

use std::path::{Path, PathBuf};
use std::process::Command;
use std::time::{Duration, Instant};

use serde_json::{Value, json};
use terrastream_testkit::browser::{Browser, Driver, WEBGL_FLAGS, WEBGPU_FLAGS};

#[path = "support/oracles.rs"]
mod oracles;

const WIDTH: u32 = 640;
const HEIGHT: u32 = 400;
/// Elevation tiles in the archive `tile --tile-size 64` makes of the 320² crop (on its
/// transverse Mercator: 5 x 7 at LOD 0, 12, 4, 1).
const TILES: u64 = 52;

/// Chromium's software rasterizers (SwiftShader) are deterministic for a given build; the
/// allowance covers another Chromium release (anti-aliasing of the silhouette, dithering):
/// mean absolute difference <= 1.5/255 and at most 1.5 % of pixels off by more than 24/255.
/// A missing tile, a wrong LOD or a shifted camera breaks both.
const TOLERANCE: terrastream_testkit::golden::Tolerance =
    terrastream_testkit::golden::Tolerance { mean: 1.5, pixel: 24, off_share: 0.015 };

fn ready() -> bool {
    let mut missing = terrastream_testkit::browser::missing();
    if !terrastream_server::player::available() {
        missing.push("the webplayer in this build (run scripts/build-player.sh, then rebuild)");
    }
    if missing.is_empty() {
        return true;
    }
    terrastream_testkit::browser::skip_or_fail("WEBPLAYER", &missing)
}

/// The player's own state, read from its page.
trait Player {
    fn stats(&self) -> Option<Value>;
    fn status_text(&self) -> (String, bool);
    fn wait_flight(&self, limit: Duration) -> Value;
    fn wait_settled(&self) -> Value;
    fn wait_error(&self) -> String;
    fn flyer(&self) -> ([f64; 3], f64, f64, f64);
    fn flyer_once(&self, done: impl Fn(&[f64; 3]) -> bool) -> ([f64; 3], f64, f64, f64);
}

impl Player for Browser<'_> {
    /// The player's counters, once it runs.
    fn stats(&self) -> Option<Value> {
        let text = self.eval("return window.terrastream ? window.terrastream.stats() : null");
        text.as_str().map(|t| serde_json::from_str(t).unwrap())
    }

    fn status_text(&self) -> (String, bool) {
        let v = self.eval(
            "const s = document.getElementById('status'); \
             return [s.textContent, s.classList.contains('error') && !s.hidden];",
        );
        (v[0].as_str().unwrap_or_default().to_owned(), v[1].as_bool().unwrap_or(false))
    }

    /// Waits until the benchmark flight (`flight=N`) is flown; the player's counters then.
    fn wait_flight(&self, limit: Duration) -> Value {
        let start = Instant::now();
        loop {
            if let Some(stats) = self.stats()
                && stats["flight_done"] == json!(true)
            {
                return stats;
            }
            assert!(start.elapsed() < limit, "the flight did not end: stats {:?}", self.stats());
            std::thread::sleep(Duration::from_millis(250));
        }
    }

    /// Waits until the view is fully streamed; the player's counters then.
    fn wait_settled(&self) -> Value {
        let start = Instant::now();
        loop {
            if let Some(stats) = self.stats()
                && stats["settled"] == json!(true)
                && stats["frames"].as_u64().unwrap_or(0) > 3
            {
                return stats;
            }
            assert!(
                start.elapsed() < Duration::from_secs(120),
                "the view did not complete: stats {:?}, status {:?}, console {:?}",
                self.stats(),
                self.status_text(),
                self.console()
            );
            std::thread::sleep(Duration::from_millis(250));
        }
    }

    /// Waits for the status box to show an error; its text.
    fn wait_error(&self) -> String {
        let start = Instant::now();
        loop {
            let (text, error) = self.status_text();
            if error {
                return text;
            }
            assert!(start.elapsed() < Duration::from_secs(60), "no error shown; status {text:?}");
            std::thread::sleep(Duration::from_millis(200));
        }
    }

    /// The fly camera: eye, yaw, pitch, speed.
    fn flyer(&self) -> ([f64; 3], f64, f64, f64) {
        let s = self.stats().unwrap();
        let eye = [0, 1, 2].map(|i| s["eye"][i].as_f64().unwrap());
        (eye, s["yaw"].as_f64().unwrap(), s["pitch"].as_f64().unwrap(), s["speed"].as_f64().unwrap())
    }

    /// The camera once `done` holds for it, or after 10 s: input that flies is applied by
    /// the next frame, and on a loaded machine a frame can take longer than the input.
    fn flyer_once(&self, done: impl Fn(&[f64; 3]) -> bool) -> ([f64; 3], f64, f64, f64) {
        let started = Instant::now();
        loop {
            let flyer = self.flyer();
            if done(&flyer.0) || started.elapsed() > Duration::from_secs(10) {
                return flyer;
            }
            std::thread::sleep(Duration::from_millis(100));
        }
    }
}

fn terrastream(args: &[&str]) {
    let out = Command::new(env!("CARGO_BIN_EXE_terrastream")).arg("-q").args(args).output().unwrap();
    assert!(out.status.success(), "terrastream {args:?}: {}", String::from_utf8_lossy(&out.stderr));
}

/// `terrastream serve` of `archive` on a free loopback port, answering (stopped when
/// dropped).
fn serve(archive: &Path) -> terrastream_testkit::server::Spawned {
    let exe = Path::new(env!("CARGO_BIN_EXE_terrastream"));
    terrastream_testkit::server::spawn_serve(exe, &[archive.to_str().unwrap()], archive.parent().unwrap())
}

/// The committed DEM crop as an archive, as `terrastream tile --tile-size 64` makes it.
fn archive(dir: &Path) -> PathBuf {
    let path = dir.join("tamalpais.tspack");
    let dem = terrastream_testkit::golden::repo().join("packer/pack/data/srtm-tamalpais-320-public-domain.tif");
    terrastream(&["tile", "--elevation", dem.to_str().unwrap(), "-o", path.to_str().unwrap(), "--tile-size", "64"]);
    path
}

/// What every run checks: the view complete, every tile fetched once, requests no more
/// than the tiles need, uploads within the per-frame budget, the picture, the console.
fn check_run(browser: &Browser<'_>, stats: &Value, golden_name: &str, backend: &str) {
    eprintln!("{golden_name}: {stats}");
    assert_eq!(stats["backend"], json!(backend), "{stats}");
    assert_eq!(stats["missing"], json!(0));
    assert_eq!(stats["failures"], json!(0));
    // Everything the view wants is on the GPU; every tile came at most once (coalesced
    // requests bring neighbours the view may not want yet).
    let wanted = stats["wanted"].as_u64().unwrap();
    assert!(wanted >= 5, "{stats}");
    assert_eq!(stats["resident"][0].as_u64().unwrap(), wanted, "{stats}");
    let fetched = stats["tiles_fetched"].as_u64().unwrap();
    assert!((wanted..=TILES).contains(&fetched), "{stats}");
    let requests = stats["requests"].as_u64().unwrap();
    let http_requests = stats["http_requests"].as_u64().unwrap();
    // Tile requests: coalesced, so fewer than the tiles; the rest opened the archive
    // (one bootstrap read, at most one more for the index). Tiles within the bootstrap's
    // first 16 KiB cost no request of their own (one such request at most).
    assert!((1..=TILES).contains(&requests), "{stats}");
    assert!((requests..=requests + 2).contains(&http_requests), "{stats}");
    assert!(stats["max_uploads_per_frame"].as_u64().unwrap() <= stats["upload_budget"].as_u64().unwrap(), "{stats}");
    assert!(stats["first_frame_ms"].as_f64().is_some(), "{stats}");
    // Decoded in Web Workers, off the page's thread: every tile fetched.
    assert!(stats["workers"].as_u64().unwrap() >= 1, "{stats}");
    assert_eq!(stats["decoded_in_workers"], stats["tiles_fetched"], "{stats}");
    // So was the globe's whole-Earth picture (the view waits for it, as for its tiles).
    assert_eq!(stats["earth_decoded_in_worker"], json!(true), "{stats}");
    // Frames go on while streaming: the page stayed responsive.
    assert!(stats["frames"].as_u64().unwrap() > 3, "{stats}");
    // A few frames more, then the picture.
    std::thread::sleep(Duration::from_millis(500));
    let (w, h, rgba) = browser.screenshot("#terrain");
    terrastream_testkit::golden::assert_golden(golden_name, w, h, &rgba, TOLERANCE);
    let console = browser.console();
    let errors: Vec<_> = console.iter().filter(|(level, _)| level == "SEVERE").collect();
    assert!(errors.is_empty(), "console errors: {errors:?}");
    assert!(console.iter().any(|(_, m)| m.contains("view fully streamed")), "the player logs: {console:?}");
}

/// nginx with the shipped static-host config (`deploy/nginx/tspack-static.conf`) serving
/// `root`, logging requests to `access_log` if given.
fn static_host(root: &Path, access_log: Option<&Path>) -> Option<terrastream_testkit::nginx::Nginx> {
    let shipped =
        std::fs::read_to_string(terrastream_testkit::golden::repo().join("deploy/nginx/tspack-static.conf")).unwrap();
    let mut config = shipped
        .replace("listen 8080;", "listen 127.0.0.1:{port};")
        .replace("root /srv/terrastream;", &format!("root {};", root.display()));
    assert_ne!(config, shipped);
    if let Some(log) = access_log {
        config = config.replacen("{port};", &format!("{{port}};\n    access_log {};", log.display()), 1);
    }
    terrastream_testkit::nginx::start_nginx(root, &config)
}

/// A continent-sized terrain (10^7 m across) on both back ends: the view completes and
/// draws terrain over most of the picture, as `render` and `view` do (tests/continent.rs).
#[test]
fn a_continent_draws_on_webgpu_and_on_webgl2() {
    if !ready() {
        return;
    }
    let dir = tempfile::tempdir().unwrap();
    let archive =
        terrastream_testkit::continent::continent_archive(Path::new(env!("CARGO_BIN_EXE_terrastream")), dir.path());
    let server = serve(&archive);
    let port = server.port;
    let driver = Driver::start();
    for (flags, backend) in [(WEBGPU_FLAGS, "webgpu"), (WEBGL_FLAGS, "webgl2")] {
        let browser = Browser::open(&driver, flags, (WIDTH, HEIGHT));
        browser.goto(&format!("http://127.0.0.1:{port}/view/continent?hud=0"));
        let stats = browser.wait_settled();
        eprintln!("continent on {backend}: {stats}");
        assert_eq!(stats["backend"], json!(backend), "{stats}");
        assert_eq!(stats["failures"], json!(0), "{stats}");
        assert!(stats["patches"].as_u64().unwrap() > 0, "{stats}");
        assert_eq!(stats["drew_nothing_in_view"], json!(false), "{stats}");
        std::thread::sleep(Duration::from_millis(500));
        let (w, h, rgba) = browser.screenshot("#terrain");
        terrastream_testkit::golden::assert_golden(&format!("continent-{backend}"), w, h, &rgba, TOLERANCE);
        // Most of the picture is terrain, not the sky of the top-left corner.
        let sky = &rgba[..3];
        let terrain = rgba.chunks_exact(4).filter(|p| p[..3].iter().zip(sky).any(|(a, b)| a.abs_diff(*b) > 12));
        let share = terrain.count() as f64 / f64::from(w * h);
        assert!(share > 0.2, "{backend}: only {:.0} % of the picture is terrain", share * 100.0);
        let console = browser.console();
        assert!(console.iter().all(|(level, _)| level != "SEVERE"), "{console:?}");
    }
}

#[test]
fn webplayer_from_terrastream_serve_on_webgpu() {
    if !ready() {
        return;
    }
    let dir = tempfile::tempdir().unwrap();
    let archive = archive(dir.path());
    let server = serve(&archive);
    let port = server.port;
    let before = terrastream_testkit::http::archive_requests(port);

    let driver = Driver::start();
    let browser = Browser::open(&driver, WEBGPU_FLAGS, (WIDTH, HEIGHT));
    let started = Instant::now();
    browser.goto(&format!("http://127.0.0.1:{port}/view/tamalpais?hud=0"));
    let stats = browser.wait_settled();
    eprintln!("loaded and streamed in {:.2} s (page load to complete view)", started.elapsed().as_secs_f64());
    // The server saw exactly the archive requests the page made.
    assert_eq!(
        terrastream_testkit::http::archive_requests(port) - before,
        stats["http_requests"].as_u64().unwrap(),
        "{stats}"
    );
    check_run(&browser, &stats, "webplayer-webgpu", "webgpu");
    let sky = |rgba: &[u8]| [rgba[0], rgba[1], rgba[2]];
    let (.., with_air) = browser.screenshot("#terrain");

    // The HUD (H) and flying (W: forward, towards -z from the south).
    browser.hold_key("h", 50);
    // The HUD refreshes a few times a second; on a loaded machine the first refresh can
    // take a while.
    let started = Instant::now();
    let hud = loop {
        std::thread::sleep(Duration::from_millis(250));
        let hud = browser.eval("const h = document.getElementById('hud'); return [h.hidden, h.textContent];");
        if hud[1].as_str().is_some_and(|t| !t.is_empty()) || started.elapsed() > Duration::from_secs(15) {
            break hud;
        }
    };
    assert_eq!(hud[0], json!(false), "H shows the HUD");
    let text = hud[1].as_str().unwrap();
    for field in ["fps", "tiles in flight", "received", "MiB", "WebGPU"] {
        assert!(text.contains(field), "HUD lacks {field:?}: {text}");
    }
    // On the globe: forward is along the view in the frame at the eye (ECEF).
    let (eye, yaw, pitch, _) = browser.flyer();
    let flyer = terrastream_client::FlyCamera { eye: eye.into(), yaw, pitch, speed: 1.0, globe: true };
    let ahead = |after: [f64; 3]| (glam::DVec3::from(after) - flyer.eye).dot(flyer.forward());
    browser.hold_key("w", 600);
    let (after, ..) = browser.flyer_once(|after| ahead(*after) > 1.0);
    assert!(ahead(after) > 1.0, "W flies forward: {eye:?} -> {after:?}");
    // A mouse drag to the right turns right (yaw grows), upwards pitches up.
    let (_, yaw, pitch, speed) = browser.flyer();
    browser.act(json!([Browser::drag("mouse", "mouse", (300, 150), (360, 120), 200)]));
    let (_, yaw2, pitch2, _) = browser.flyer();
    assert!(yaw2 > yaw + 0.1 && pitch2 > pitch + 0.05, "drag: yaw {yaw} -> {yaw2}, pitch {pitch} -> {pitch2}");
    // The wheel (scrolling up) speeds up.
    browser.act(json!([{ "type": "wheel", "id": "wheel", "actions": [
        { "type": "scroll", "x": 300, "y": 120, "deltaX": 0, "deltaY": -300, "origin": "viewport" },
    ]}]));
    let (_, _, _, speed2) = browser.flyer();
    assert!(speed2 > speed * 1.5, "wheel: speed {speed} -> {speed2}");
    // Touch: two fingers spreading fly forward along the view; one finger looks around.
    let (eye, yaw, ..) = browser.flyer();
    browser.act(json!([
        Browser::drag("finger1", "touch", (280, 120), (200, 120), 300),
        Browser::drag("finger2", "touch", (340, 120), (420, 120), 300),
    ]));
    let moved = |after: &[f64; 3]| ((after[0] - eye[0]).powi(2) + (after[2] - eye[2]).powi(2)).sqrt();
    let (after, yaw2, ..) = browser.flyer_once(|after| moved(after) > 1.0);
    let moved = moved(&after);
    assert!(moved > 1.0, "pinch: {eye:?} -> {after:?}");
    assert!((yaw2 - yaw).abs() < 0.05, "a pinch does not turn: {yaw} -> {yaw2}");
    browser.act(json!([Browser::drag("finger3", "touch", (300, 150), (240, 150), 200)]));
    let (_, yaw3, ..) = browser.flyer();
    assert!(yaw3 < yaw2 - 0.1, "one-finger drag to the left turns left: {yaw2} -> {yaw3}");
    assert!(browser.console().iter().all(|(level, _)| level != "SEVERE"));

    // atmosphere=0 and earth=0, as `render --no-atmosphere --no-earth`: the sky in the
    // picture's corner is the plain haze, and no worker decodes the Earth's picture.
    browser.goto(&format!("http://127.0.0.1:{port}/view/tamalpais?hud=0&atmosphere=0&earth=0"));
    let plain = browser.wait_settled();
    assert_eq!(plain["earth_decoded_in_worker"], json!(false), "{plain}");
    let (.., hazy) = browser.screenshot("#terrain");
    let (a, b) = (sky(&with_air), sky(&hazy));
    eprintln!("the corner's sky: {a:?} with the atmosphere, {b:?} without");
    assert!(a.iter().zip(&b).any(|(p, q)| p.abs_diff(*q) > 20), "the same sky: {a:?} and {b:?}");
}

#[test]
fn webplayer_from_nginx_static_files_on_webgl2_with_cors() {
    if !ready() {
        return;
    }
    let dir = tempfile::tempdir().unwrap();
    let site = dir.path().join("site");
    let data = dir.path().join("data");
    std::fs::create_dir_all(&data).unwrap();
    archive(&data);
    terrastream(&["player", "-o", site.to_str().unwrap()]);
    // The shipped static-host config, twice: the player on one origin, the archive on
    // another (so the page's requests are cross-origin and need its CORS headers).
    let log = dir.path().join("archive-access.log");
    let Some(player_host) = static_host(&site, None) else { return };
    let Some(archive_host) = static_host(&data, Some(&log)) else { return };

    let driver = Driver::start();
    let browser = Browser::open(&driver, WEBGL_FLAGS, (WIDTH, HEIGHT));
    let archive_url = format!("http://127.0.0.1:{}/tamalpais.tspack", archive_host.port);
    browser.goto(&format!("http://127.0.0.1:{}/player.html?archive={archive_url}&hud=0", player_host.port));
    let stats = browser.wait_settled();
    // nginx's own log: the archive GETs (preflights apart) are the ones the page made.
    let log = std::fs::read_to_string(&log).unwrap();
    let gets = log.lines().filter(|l| l.contains("\"GET /tamalpais.tspack")).count() as u64;
    let preflights = log.lines().filter(|l| l.contains("\"OPTIONS /tamalpais.tspack")).count();
    eprintln!("nginx: {gets} archive GETs, {preflights} CORS preflights");
    assert_eq!(gets, stats["http_requests"].as_u64().unwrap(), "{stats}\n{log}");
    assert!(log.lines().filter(|l| l.contains("\"GET /tamalpais.tspack")).all(|l| l.contains("\" 206 ")), "{log}");
    check_run(&browser, &stats, "webplayer-webgl2", "webgl2");
    drop(player_host);
    drop(archive_host);
}

#[test]
fn webplayer_explains_what_is_wrong() {
    if !ready() {
        return;
    }
    let dir = tempfile::tempdir().unwrap();
    let site = dir.path().join("site");
    terrastream(&["player", "-o", site.to_str().unwrap()]);
    let Some(host) = static_host(&site, None) else { return };
    let driver = Driver::start();
    let page = |query: &str| format!("http://127.0.0.1:{}/player.html{query}", host.port);

    // An archive that is not there: named, with the server's answer.
    let browser = Browser::open(&driver, WEBGL_FLAGS, (WIDTH, HEIGHT));
    browser.goto(&page("?archive=missing.tspack"));
    let text = browser.wait_error();
    assert!(text.contains("Cannot open the archive") && text.contains("missing.tspack"), "{text}");
    assert!(text.contains("404"), "the server's answer is shown: {text}");
    // No archive at all: how to give one.
    browser.goto(&page(""));
    let text = browser.wait_error();
    assert!(text.contains("player.html?archive="), "{text}");
    // A bad flat= is named.
    browser.goto(&page("?archive=x.tspack&flat=maybe"));
    let text = browser.wait_error();
    assert!(text.contains("flat=\"maybe\""), "{text}");
    browser.goto(&page("?archive=x.tspack&sun=east"));
    let text = browser.wait_error();
    assert!(text.contains("AZIMUTH,ELEVATION"), "{text}");
    drop(browser);

    // A browser with neither WebGPU nor WebGL2.
    let browser = Browser::open(&driver, &["--disable-3d-apis", "--disable-webgpu"], (WIDTH, HEIGHT));
    browser.goto(&page("?archive=missing.tspack"));
    let text = browser.wait_error();
    assert!(text.contains("needs WebGPU or WebGL2"), "{text}");
}

/// A terrain published as a manifest (three shards and the coarse archive) and served
/// by `terrastream serve`: `/view/{manifest}` streams across the four archives and
/// draws the same picture as the single archive.
#[test]
fn webplayer_streams_a_manifest_of_four_archives() {
    if !ready() {
        return;
    }
    let dir = tempfile::tempdir().unwrap();
    let dem = terrastream_testkit::golden::repo().join("packer/pack/data/srtm-tamalpais-320-public-domain.tif");
    let shards: Vec<String> = (0..3).map(|i| dir.path().join(format!("s{i}.tspack")).display().to_string()).collect();
    for (i, shard) in shards.iter().enumerate() {
        let spec = format!("{i}/3");
        terrastream(&[
            "tile",
            "--elevation",
            dem.to_str().unwrap(),
            "-o",
            shard,
            "--tile-size",
            "64",
            "--shard",
            &spec,
        ]);
    }
    let coarse = dir.path().join("coarse.tspack").display().to_string();
    let manifest = dir.path().join("tamalpais.json").display().to_string();
    let mut args = vec!["merge"];
    args.extend(shards.iter().map(String::as_str));
    args.extend(["-o", &coarse, "--manifest", &manifest]);
    terrastream(&args);
    let server = serve(dir.path());
    let port = server.port;

    let driver = Driver::start();
    let browser = Browser::open(&driver, WEBGPU_FLAGS, (WIDTH, HEIGHT));
    browser.goto(&format!("http://127.0.0.1:{port}/view/tamalpais?hud=0"));
    let stats = browser.wait_settled();
    eprintln!("manifest: {stats}");
    assert_eq!(stats["missing"], json!(0), "{stats}");
    assert_eq!(stats["failures"], json!(0), "{stats}");
    let wanted = stats["wanted"].as_u64().unwrap();
    assert!(wanted >= 5, "{stats}");
    assert_eq!(stats["resident"][0].as_u64().unwrap(), wanted, "{stats}");
    std::thread::sleep(Duration::from_millis(500));
    let (w, h, rgba) = browser.screenshot("#terrain");
    terrastream_testkit::golden::assert_golden("webplayer-webgpu", w, h, &rgba, TOLERANCE);
    let errors: Vec<_> = browser.console().into_iter().filter(|(level, _)| level == "SEVERE").collect();
    assert!(errors.is_empty(), "console errors: {errors:?}");
}

/// Private terrain in the player: `/view/{name}?access_token=…` opens a private archive,
/// and a private manifest across its archives, with nothing but that URL (the server
/// carries the key into the page's archive URL and into the manifest's archive URLs);
/// without it the page is refused, saying why.
#[test]
fn webplayer_opens_private_terrain_with_the_key_in_its_url() {
    if !ready() {
        return;
    }
    let dir = tempfile::tempdir().unwrap();
    archive(dir.path());
    let dem = terrastream_testkit::golden::repo().join("packer/pack/data/srtm-tamalpais-320-public-domain.tif");
    let shards: Vec<String> = (0..2).map(|i| dir.path().join(format!("s{i}.tspack")).display().to_string()).collect();
    for (i, shard) in shards.iter().enumerate() {
        let spec = format!("{i}/2");
        let args = ["tile", "--elevation", dem.to_str().unwrap(), "-o", shard, "--tile-size", "64", "--shard", &spec];
        terrastream(&args);
    }
    let (coarse, manifest) = (dir.path().join("coarse.tspack"), dir.path().join("published.json"));
    let (c, m) = (coarse.display().to_string(), manifest.display().to_string());
    terrastream(&["merge", &shards[0], &shards[1], "-o", &c, "--manifest", &m]);
    let out = Command::new(env!("CARGO_BIN_EXE_terrastream"))
        .args(["key", "new", "--archives", "tamalpais", "published", "s*", "coarse", "--keys", "keys.toml"])
        .current_dir(dir.path())
        .output()
        .unwrap();
    assert!(out.status.success(), "{}", String::from_utf8_lossy(&out.stderr));
    let key = String::from_utf8(out.stdout).unwrap().trim().to_owned();
    let exe = Path::new(env!("CARGO_BIN_EXE_terrastream"));
    let served = dir.path().display().to_string();
    let args = [served.as_str(), "--private", "--keys", "keys.toml"];
    let server = terrastream_testkit::server::spawn_serve(exe, &args, dir.path());
    let port = server.port;
    let driver = Driver::start();
    let browser = Browser::open(&driver, WEBGPU_FLAGS, (WIDTH, HEIGHT));
    for name in ["tamalpais", "published"] {
        browser.goto(&format!("http://127.0.0.1:{port}/view/{name}?hud=0&access_token={key}"));
        let stats = browser.wait_settled();
        eprintln!("private {name}: {stats}");
        assert_eq!((stats["missing"].clone(), stats["failures"].clone()), (json!(0), json!(0)), "{stats}");
        assert!(stats["wanted"].as_u64().unwrap() >= 5, "{stats}");
        std::thread::sleep(Duration::from_millis(500));
        let (w, h, rgba) = browser.screenshot("#terrain");
        terrastream_testkit::golden::assert_golden("webplayer-webgpu", w, h, &rgba, TOLERANCE);
    }
    // Without the key: the page itself is refused, with the reason.
    browser.goto(&format!("http://127.0.0.1:{port}/view/tamalpais?hud=0"));
    let text = browser.eval("return document.body.innerText;");
    assert!(text.as_str().is_some_and(|t| t.contains("a key is needed")), "{text}");
}

/// A benchmark, not a test (`scripts/bench-webplayer.sh` runs it): the player over the
/// emulated links of `bench stream` (a user-space shaper in front of the server, for the
/// archive's requests only; the page itself loads directly). Per link it prints the first
/// frame with terrain and the first complete one (since the player started), and the
/// time between frames, p50 and p99, while tiles were coming and once all were resident,
/// from the same browser run. `WORKERS=0` decodes on the page's thread.
// Ignored in the test run on purpose: speed is measured by benchmarks that print numbers,
// never asserted by pass/fail tests, and this one takes minutes of emulated links.
// `scripts/bench-webplayer.sh` runs it (`cargo test --test webplayer -- --ignored`).
#[test]
#[ignore = "a benchmark that prints numbers: scripts/bench-webplayer.sh"]
fn bench_webplayer_over_emulated_links() {
    use terrastream_testkit::shaper::{Link, Shaper};
    if !ready() {
        return;
    }
    let dir = tempfile::tempdir().unwrap();
    let archive = archive(dir.path());
    let server = serve(&archive);
    let port = server.port;
    let runtime = tokio::runtime::Runtime::new().unwrap();
    let upstream: std::net::SocketAddr = format!("127.0.0.1:{port}").parse().unwrap();
    // The flight's terrain: the crop at 4x its resolution (7.5 m, 1280² samples), tiles of
    // 128: 142 elevation tiles, all of which fit the player's GPU slots.
    let flight_archive = dir.path().join("flight.tspack");
    let dem = terrastream_testkit::golden::repo().join("packer/pack/data/srtm-tamalpais-320-public-domain.tif");
    terrastream(&[
        "tile",
        "--elevation",
        dem.to_str().unwrap(),
        "--resolution",
        "7.5",
        "--tile-size",
        "128",
        "-o",
        flight_archive.to_str().unwrap(),
    ]);
    let flight_server = serve(&flight_archive);
    let flight_upstream: std::net::SocketAddr = format!("127.0.0.1:{}", flight_server.port).parse().unwrap();
    let driver = Driver::start();
    let flags: Vec<&str> = match std::env::var("BACKEND").as_deref() {
        Ok("webgl2") => WEBGL_FLAGS.to_vec(),
        _ => WEBGPU_FLAGS.to_vec(),
    };
    let links = [
        ("loopback", None),
        ("(a) 20 ms, 100 Mbit/s", Some(Link::NEAR)),
        ("(b) 80 ms, 20 Mbit/s", Some(Link::FAR)),
        ("(c) 150 ms, 5 Mbit/s, 1 % loss", Some(Link::POOR)),
    ];
    println!(
        "{:<32} {:>9} {:>9} {:>9} {:>7} {:>8} {:>8} {:>7} {:>8} {:>8} {:>6} {:>5}",
        "link",
        "first ms",
        "full ms",
        "setup ms",
        "frames",
        "p50 ms",
        "p99 ms",
        "frames",
        "p50 ms",
        "p99 ms",
        "p99 x",
        "reqs"
    );
    println!("{:<32} {:>19} {:>9} {:>24} {:>24}", "", "(since start)", "", "(streaming)", "(resident)");
    for (name, link) in links {
        let shaper = link.map(|l| runtime.block_on(Shaper::start(upstream, l)).unwrap());
        let archive_port = shaper.as_ref().map_or(port, |s| s.addr.port());
        let browser = Browser::open(&driver, &flags, (WIDTH, HEIGHT));
        // WORKERS=0 decodes on the page's thread (the default: Web Workers).
        let workers = std::env::var("WORKERS").map(|w| format!("&workers={w}")).unwrap_or_default();
        browser.goto(&format!(
            "http://127.0.0.1:{port}/view/tamalpais?hud=0{workers}&archive=http://127.0.0.1:{archive_port}/tamalpais.tspack"
        ));
        browser.wait_settled();
        // Resident frames: the same view, every tile on the GPU.
        std::thread::sleep(Duration::from_secs(4));
        let s = browser.stats().unwrap();
        let ms = |key: &str| s[key].as_f64().map_or("-".to_owned(), |v| format!("{v:.0}"));
        let ratio = match (s["frame_p99_streaming_ms"].as_f64(), s["frame_p99_resident_ms"].as_f64()) {
            (Some(a), Some(b)) if b > 0.0 => format!("{:.2}", a / b),
            _ => "-".into(),
        };
        println!(
            "{name:<32} {:>9} {:>9} {:>9} {:>7} {:>8} {:>8} {:>7} {:>8} {:>8} {ratio:>6} {:>5}",
            ms("first_frame_ms"),
            ms("settled_ms"),
            ms("session_ms"),
            s["frames_streaming"].as_u64().unwrap_or(0),
            ms("frame_p50_streaming_ms"),
            ms("frame_p99_streaming_ms"),
            s["frames_resident"].as_u64().unwrap_or(0),
            ms("frame_p50_resident_ms"),
            ms("frame_p99_resident_ms"),
            s["http_requests"].as_u64().unwrap_or(0),
        );
        println!(
            "{:<32} first frame with terrain: {} ms preparing (streaming, uploads), {} ms encoding and submitting",
            "",
            ms("first_draw_prepare_ms"),
            ms("first_draw_submit_ms")
        );
        assert_eq!(s["missing"], json!(0), "{name}: {s}");
        // The flight: over a terrain whose finer tiles the first view does not want, so
        // they stream in during the first pass and are resident during the second.
        let flight_shaper = link.map(|l| runtime.block_on(Shaper::start(flight_upstream, l)).unwrap());
        let flight_port = flight_shaper.as_ref().map_or(flight_server.port, |s| s.addr.port());
        browser.goto(&format!(
            "http://127.0.0.1:{port}/view/tamalpais?hud=0{workers}&flight={BENCH_FLIGHT}\
             &archive=http://127.0.0.1:{flight_port}/flight.tspack"
        ));
        browser.wait_settled();
        let s = browser.wait_flight(Duration::from_secs(600));
        let flight = |key: &str| s[key].as_f64().map_or("-".to_owned(), |v| format!("{v:.0}"));
        let flight_ratio = match (s["flight_p99_streaming_ms"].as_f64(), s["flight_p99_resident_ms"].as_f64()) {
            (Some(a), Some(b)) if b > 0.0 => format!("{:.2}", a / b),
            _ => "-".into(),
        };
        println!(
            "{:<32} flight of {BENCH_FLIGHT} frames: streaming {} frames p50 {} p99 {} max {} ms; resident {} frames \
             p50 {} p99 {} ms; p99 x {flight_ratio}",
            "",
            s["flight_frames_streaming"].as_u64().unwrap_or(0),
            flight("flight_p50_streaming_ms"),
            flight("flight_p99_streaming_ms"),
            flight("flight_max_streaming_ms"),
            s["flight_frames_resident"].as_u64().unwrap_or(0),
            flight("flight_p50_resident_ms"),
            flight("flight_p99_resident_ms"),
        );
        // One LOD-0 tile of this terrain holds no data (a corner of the reprojection).
        assert_eq!(s["failures"], json!(0), "{name}: {s}");
        drop(browser);
    }
}

/// Frames of the benchmark flight (each flown twice).
const BENCH_FLIGHT: usize = 240;

/// `flight=N` flies the benchmarks' path twice once the view is complete, steering the
/// camera, and counts every frame of both passes, streaming or resident.
#[test]
fn the_benchmark_flight_steers_the_camera_and_counts_its_frames() {
    if !ready() {
        return;
    }
    let dir = tempfile::tempdir().unwrap();
    let archive = archive(dir.path());
    let server = serve(&archive);
    let port = server.port;
    let driver = Driver::start();
    let browser = Browser::open(&driver, WEBGPU_FLAGS, (WIDTH, HEIGHT));
    let frames = 12;
    browser.goto(&format!("http://127.0.0.1:{port}/view/tamalpais?hud=0&flight={frames}"));
    browser.wait_settled();
    let s = browser.wait_flight(Duration::from_secs(120));
    let counted = s["flight_frames_streaming"].as_u64().unwrap() + s["flight_frames_resident"].as_u64().unwrap();
    assert_eq!(counted, 2 * frames as u64, "{s}");
    assert!(s["flight_p99_resident_ms"].as_f64().is_some(), "the second pass has resident frames: {s}");
    // The camera stays where the flight ended: the path's last eye.
    let reader = terrastream_format::Reader::open_mmap(&archive).unwrap();
    let (last, _) = *terrastream_client::fly::bench_flight(reader.metadata(), frames).last().unwrap();
    // On the globe the flight's world points are placed on the ellipsoid.
    let last = terrastream_client::Surface::new(reader.metadata(), true).place(last);
    let (eye, ..) = browser.flyer();
    let off = (glam::DVec3::from(eye) - last).length();
    assert!(off < 1e-6 * last.length(), "the flight ends at {last:?}, the eye is at {eye:?}");
    assert_eq!(s["missing"], json!(0), "{s}");
    // flat=1 keeps the plate: the eye in world units over the crop, not 6 400 km out.
    browser.goto(&format!("http://127.0.0.1:{port}/view/tamalpais?hud=0&flat=1"));
    browser.wait_settled();
    let (eye, ..) = browser.flyer();
    assert!(glam::DVec3::from(eye).length() < 1.0e5, "on the plate the eye is at {eye:?}");
}

/// A host without `decoder.js` (an older copy of the player's files): the workers fail to
/// start and every tile is decoded on the page's thread instead; the view completes.
#[test]
fn without_its_worker_script_the_player_decodes_on_the_page() {
    if !ready() {
        return;
    }
    let dir = tempfile::tempdir().unwrap();
    let site = dir.path().join("site");
    terrastream(&["player", "-o", site.to_str().unwrap()]);
    archive(&site);
    std::fs::remove_file(site.join("decoder.js")).unwrap();
    let Some(host) = static_host(&site, None) else { return };
    let driver = Driver::start();
    let browser = Browser::open(&driver, WEBGL_FLAGS, (WIDTH, HEIGHT));
    browser.goto(&format!("http://127.0.0.1:{}/player.html?archive=tamalpais.tspack&hud=0", host.port));
    let stats = browser.wait_settled();
    assert_eq!(stats["missing"], json!(0), "{stats}");
    assert_eq!(stats["failures"], json!(0), "{stats}");
    assert_eq!(stats["resident"][0], stats["wanted"], "{stats}");
    assert_eq!(stats["decoded_in_workers"], json!(0), "{stats}");
    assert!(stats["tiles_fetched"].as_u64().unwrap() > 0, "{stats}");
}

/// A collection (a 10" base and a 1" patch, each as deep as it reaches: docs/tiling.md,
/// "Collections") in the player: it asks for no tile the archive lacks (the finer levels'
/// rectangles say where they hold tiles), completes the view with no failure, and draws
/// terrain (golden, looked at).
#[test]
fn webplayer_streams_a_collection_asking_for_no_missing_tile() {
    if !ready() {
        return;
    }
    let dir = tempfile::tempdir().unwrap();
    let repo = terrastream_testkit::golden::repo();
    let path = dir.path().join("collection.tspack");
    let (base, patch) =
        (repo.join("tests/data/collection-base-10s-plus3m.tif"), repo.join("tests/data/collection-patch-1s.tif"));
    let (b, p, o) = (base.to_str().unwrap(), patch.to_str().unwrap(), path.to_str().unwrap());
    terrastream(&["tile", "--elevation", b, p, "-o", o, "--tile-size", "64"]);
    let server = serve(&path);
    let driver = Driver::start();
    let browser = Browser::open(&driver, WEBGPU_FLAGS, (WIDTH, HEIGHT));
    browser.goto(&format!("http://127.0.0.1:{}/view/collection?hud=0", server.port));
    let stats = browser.wait_settled();
    eprintln!("collection: {stats}");
    assert_eq!((stats["missing"].clone(), stats["failures"].clone()), (json!(0), json!(0)), "{stats}");
    assert!(stats["wanted"].as_u64().unwrap() >= 5, "{stats}");
    assert_eq!(stats["resident"][0], stats["wanted"], "{stats}");
    assert_eq!(stats["drew_nothing_in_view"], json!(false), "{stats}");
    std::thread::sleep(Duration::from_millis(500));
    let (w, h, rgba) = browser.screenshot("#terrain");
    terrastream_testkit::golden::assert_golden("webplayer-collection", w, h, &rgba, TOLERANCE);
}

/// A coast with a water layer (a lake filling a basin 30 m below sea level, from a mask
/// in UTM: `terrastream water`) in the player on WebGL2, looking straight down on the
/// lake: its water tiles come with the elevation tiles and the lake is drawn as water
/// (the page's decoding in Web Workers, the water applied on the page); the same view of
/// the archive without the layer draws the basin as land.
#[test]
fn the_webplayer_draws_a_lake_from_the_water_layer() {
    if !ready() {
        return;
    }
    if Command::new("gdal_translate").arg("--version").output().is_err() {
        assert!(std::env::var_os("CI").is_none(), "gdal-bin is required on CI");
        return;
    }
    let dir = tempfile::tempdir().unwrap();
    let (dem, bounds) = oracles::coast_dem(dir.path());
    let (mask, (lon, lat)) = oracles::lake_mask(dir.path(), bounds);
    let (plain, wet) = (dir.path().join("coast.tspack"), dir.path().join("lake.tspack"));
    terrastream(&["tile", "--elevation", dem.to_str().unwrap(), "-o", plain.to_str().unwrap()]);
    terrastream(&["water", plain.to_str().unwrap(), "--mask", mask.to_str().unwrap(), "-o", wet.to_str().unwrap()]);
    let exe = Path::new(env!("CARGO_BIN_EXE_terrastream"));
    let server =
        terrastream_testkit::server::spawn_serve(exe, &[plain.to_str().unwrap(), wet.to_str().unwrap()], dir.path());
    let driver = Driver::start();
    let mut blue = vec![];
    for name in ["lake", "coast"] {
        let browser = Browser::open(&driver, WEBGL_FLAGS, (WIDTH, HEIGHT));
        browser.goto(&format!(
            "http://127.0.0.1:{}/view/{name}?hud=0&at={lon},{lat},5000&pitch=-90&heading=0",
            server.port
        ));
        let stats = browser.wait_settled();
        eprintln!("{name}: {stats}");
        assert_eq!((stats["missing"].clone(), stats["failures"].clone()), (json!(0), json!(0)), "{stats}");
        assert_eq!(stats["drew_nothing_in_view"], json!(false), "{stats}");
        std::thread::sleep(Duration::from_millis(500));
        let (w, h, rgba) = browser.screenshot("#terrain");
        // The middle 40 x 40 pixels: the lake's middle.
        let (mut n, mut water) = (0, 0);
        for y in h / 2 - 20..h / 2 + 20 {
            for x in w / 2 - 20..w / 2 + 20 {
                let i = 4 * (y * w + x) as usize;
                let (r, g, b) = (i32::from(rgba[i]), i32::from(rgba[i + 1]), i32::from(rgba[i + 2]));
                n += 1;
                water += usize::from(b > r + 30 && b > g + 10);
            }
        }
        blue.push(water as f64 / f64::from(n));
        let console = browser.console();
        assert!(console.iter().all(|(level, _)| level != "SEVERE"), "{console:?}");
    }
    eprintln!("water-blue in the middle: with the water layer {:.2}, without {:.2}", blue[0], blue[1]);
    assert!(blue[0] > 0.95, "the lake with the water layer: {:.2} water-blue", blue[0]);
    assert!(blue[1] < 0.05, "the basin without it: {:.2} water-blue", blue[1]);
}
