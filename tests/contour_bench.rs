//! Contour tiles a second against maplibre-contour (npm), which makes the same tiles in
//! the visitor's browser from Terrarium tiles: both one tile at a time (one core each),
//! the same tiles, the same interval, in one headless Chromium run. A benchmark that
//! prints numbers: `scripts/bench-contours.sh` runs it (it packs the DEM and fetches the
//! package).
#![allow(clippy::unwrap_used, clippy::expect_used, clippy::cast_possible_truncation, missing_docs)]

use std::path::{Path, PathBuf};
use std::time::{Duration, Instant};

use terrastream_testkit::browser::{Browser, Driver};

/// The maplibre-contour release measured.
const VERSION: &str = "0.1.1";

/// The page: maplibre-contour on the page's own thread (`worker: false`: one core, as
/// ours are counted), its DEM tiles fetched and decoded once first (its isolines then
/// measured alone); then, when the harness calls `ours()` (having read the server's CPU
/// time), our contour tiles fetched one at a time from a server that keeps no tile it
/// made (each made on request: cold; the archive's tiles it reads were decoded when it
/// made maplibre-contour's Terrarium tiles, as maplibre-contour's DEM tiles are).
const PAGE: &str = r#"<!doctype html><meta charset="utf-8"><script src="mlcontour.js"></script>
<script src="tiles.js"></script><script>
window.result = null;
(async () => {
  try {
    const src = new mlcontour.DemSource({ url: BASE + "/xyz/elevation/{z}/{x}/{y}.png?size=256&encoding=terrarium",
      encoding: "terrarium", maxzoom: MAXZOOM, worker: false, cacheSize: 100000 });
    const options = (levels) => ({ levels, extent: 4096, buffer: 1, elevationKey: "ele", levelKey: "level",
      contourLayer: "contours" });
    let t = performance.now();
    for (const [z, x, y] of TILES) await src.manager.fetchContourTile(z, x, y, options([10000]), new AbortController());
    const warm = performance.now() - t;
    let bytes = 0;
    t = performance.now();
    for (const [z, x, y] of TILES) {
      const tile = await src.manager.fetchContourTile(z, x, y, options([INTERVAL]), new AbortController());
      bytes += tile.arrayBuffer.byteLength;
    }
    const theirs = performance.now() - t;
    window.result = { warm, theirs, bytes };
  } catch (e) { window.result = { error: String(e) }; }
})();
window.ours = async (workers) => {
  try {
    let ours_bytes = 0, next = 0;
    const t = performance.now();
    // `workers` requests in flight at once, each taking the next tile of the list.
    const work = async () => {
      while (next < TILES.length) {
        const [z, x, y] = TILES[next++];
        const r = await fetch(BASE + `/contours/${z}/${x}/${y}.pbf?interval=${INTERVAL}`, { cache: "no-store" });
        if (r.status !== 200 && r.status !== 404) throw new Error(`${z}/${x}/${y}: ${r.status}`);
        ours_bytes += (await r.arrayBuffer()).byteLength;
      }
    };
    await Promise.all(Array.from({ length: workers }, work));
    window.ours_result = { ours: performance.now() - t, ours_bytes };
  } catch (e) { window.ours_result = { error: String(e) }; }
};
</script>"#;

// Ignored in the test run on purpose: speed is measured by benchmarks that print numbers,
// never asserted by pass/fail tests; and this one needs a DEM from outside the repository
// (the SRTM tile) and the maplibre-contour package, which `scripts/bench-contours.sh`
// provides before running it (`cargo test --test contour_bench -- --ignored`).
#[test]
#[ignore = "a benchmark that prints numbers: scripts/bench-contours.sh"]
fn bench_contours_against_maplibre_contour() {
    let archive = PathBuf::from(std::env::var("BENCH_ARCHIVE").expect("BENCH_ARCHIVE: the archive to measure"));
    let name = archive.file_stem().unwrap().to_str().unwrap().to_owned();
    let interval: f64 = std::env::var("INTERVAL").map_or(20.0, |v| v.parse().unwrap());
    let npm = std::env::var_os("TERRASTREAM_NPM")
        .map_or_else(|| PathBuf::from(std::env::var("HOME").unwrap()).join(".cache/terrastream-npm"), PathBuf::from);
    let lib = npm.join(format!("maplibre-contour-{VERSION}/package/dist/index.js"));
    assert!(lib.exists(), "{} (scripts/bench-contours.sh fetches it)", lib.display());
    let dir = tempfile::tempdir().unwrap();
    std::fs::write(dir.path().join("cold.toml"), "web_cache_bytes = 0\n").unwrap();
    let exe = Path::new(env!("CARGO_BIN_EXE_terrastream"));
    let server = terrastream_testkit::server::spawn_serve(
        exe,
        &[archive.to_str().unwrap(), "--config", "cold.toml"],
        dir.path(),
    );
    let (status, body) =
        terrastream_testkit::http::request(server.port, "GET", &format!("/{name}/tiles.json?size=256"), None);
    assert_eq!(status, 200, "{}", String::from_utf8_lossy(&body));
    let doc: serde_json::Value = serde_json::from_slice(&body).unwrap();
    let tiles = tiles(&doc);
    let maxzoom = doc["maxzoom"].as_u64().unwrap();
    let root = dir.path().join("www");
    std::fs::create_dir_all(&root).unwrap();
    std::fs::copy(&lib, root.join("mlcontour.js")).unwrap();
    std::fs::write(root.join("index.html"), PAGE).unwrap();
    let list: Vec<String> = tiles.iter().map(|(z, x, y)| format!("[{z},{x},{y}]")).collect();
    let base = format!("http://127.0.0.1:{}/{name}", server.port);
    let script = format!(
        "const BASE = {base:?}; const MAXZOOM = {maxzoom}; const INTERVAL = {interval};\nconst TILES = [{}];\n",
        list.join(",")
    );
    std::fs::write(root.join("tiles.js"), script).unwrap();
    let nginx = terrastream_testkit::nginx::start_nginx(
        &root,
        "server { listen 127.0.0.1:{port}; root {root}; types { text/html html; application/javascript js; } }",
    )
    .expect("nginx");
    let driver = Driver::start();
    let browser = Browser::open(&driver, &[], (800, 600));
    browser.goto(&format!("http://127.0.0.1:{}/index.html", nginx.port));
    let wait = |name: &str| {
        let start = Instant::now();
        loop {
            let r = browser.eval(&format!("return window.{name};"));
            if !r.is_null() {
                assert!(r["error"].is_null(), "{r}: {:?}", browser.console());
                break r;
            }
            assert!(start.elapsed() < Duration::from_secs(1800), "the page did not finish");
            std::thread::sleep(Duration::from_millis(200));
        }
    };
    let result = wait("result");
    // The server's CPU time while it makes our tiles (and nothing else): asked one at a
    // time, then six at a time (as a map asks for a view's tiles: a browser's
    // connections to one host), where the server is busy rather than woken for each.
    let ours_run = |workers: u32| {
        let before = cpu_seconds(server.child.id());
        browser.eval(&format!("window.ours_result = null; window.ours({workers}); return null;"));
        let ours_result = wait("ours_result");
        (ours_result, cpu_seconds(server.child.id()) - before)
    };
    let (ours_result, one_cpu) = ours_run(1);
    let (six_result, server_cpu) = ours_run(6);
    // And from this harness, six keep-alive connections at once, three times over the
    // tiles: the server's own cost a tile without the browser beside it on the machine's
    // cores (it asks from the page's thread and the network stack at 700 tiles a second).
    let paths: Vec<String> =
        tiles.iter().map(|(z, x, y)| format!("/{name}/contours/{z}/{x}/{y}.pbf?interval={interval}")).collect();
    let before = cpu_seconds(server.child.id());
    let light = keep_alive_load(server.port, &paths, 6, 3);
    let light_cpu = cpu_seconds(server.child.id()) - before;
    let n = tiles.len() as f64;
    let rate = |ms: &serde_json::Value| n / (ms.as_f64().unwrap() / 1000.0);
    let (ours, theirs) = (rate(&ours_result["ours"]), rate(&result["theirs"]));
    let per_core = n / server_cpu;
    println!(
        "{} tiles of zooms {}-{maxzoom}, every {interval} m (maplibre-contour on one core):",
        tiles.len(),
        maxzoom - 4
    );
    println!(
        "{:<58} {:>9.1} tiles/s  {:>9} bytes",
        "terrastream, cold (fetched from the page)", ours, ours_result["ours_bytes"]
    );
    println!(
        "{:<58} {:>9.1} tiles/s  ({:.3} ms of the server's CPU a tile)",
        "terrastream, per second of the server's CPU, one at a time",
        n / one_cpu,
        one_cpu * 1000.0 / n
    );
    println!(
        "{:<58} {:>9.1} tiles/s  ({:.3} ms of the server's CPU a tile; {:.1} tiles/s)",
        "terrastream, per second of the server's CPU, six at a time",
        per_core,
        server_cpu * 1000.0 / n,
        rate(&six_result["ours"])
    );
    #[expect(clippy::cast_precision_loss, reason = "a count of tiles")]
    let light_per_core = light as f64 / light_cpu;
    println!(
        "{:<58} {:>9.1} tiles/s  ({:.3} ms of the server's CPU a tile)",
        "terrastream, the same, six keep-alive connections, no browser",
        light_per_core,
        1000.0 / light_per_core
    );
    println!(
        "{:<58} {:>9.1} tiles/s  {:>9} bytes",
        format!("maplibre-contour {VERSION}, isolines only (DEM decoded)"),
        theirs,
        result["bytes"]
    );
    println!(
        "terrastream: {:.1}x maplibre-contour per core (the server's CPU time, six at a time without the \
         browser; {:.1}x from the page six at a time, {:.1}x one at a time), {:.1}x fetched one at a time from \
         the page (its first pass, fetching and decoding: {:.1} s)",
        light_per_core / theirs,
        per_core / theirs,
        n / one_cpu / theirs,
        ours / theirs,
        result["warm"].as_f64().unwrap() / 1000.0
    );
}

/// Asks the server on `port` for every one of `paths`, `rounds` times, over `connections`
/// keep-alive connections at once (each taking every `connections`th path); the tiles
/// answered 200.
fn keep_alive_load(port: u16, paths: &[String], connections: usize, rounds: usize) -> usize {
    use std::io::{Read, Write};
    std::thread::scope(|scope| {
        let workers: Vec<_> = (0..connections)
            .map(|c| {
                scope.spawn(move || {
                    let mut stream = std::net::TcpStream::connect(("127.0.0.1", port)).unwrap();
                    stream.set_nodelay(true).unwrap();
                    let (mut answered, mut buffer) = (0, Vec::new());
                    for path in (0..rounds).flat_map(|_| paths.iter().skip(c).step_by(connections)) {
                        write!(stream, "GET {path} HTTP/1.1\r\nHost: 127.0.0.1:{port}\r\n\r\n").unwrap();
                        // The head, then the body by its length.
                        buffer.clear();
                        let mut chunk = [0u8; 16 * 1024];
                        let end = loop {
                            if let Some(end) = buffer.windows(4).position(|w| w == b"\r\n\r\n") {
                                break end + 4;
                            }
                            let n = stream.read(&mut chunk).unwrap();
                            assert!(n > 0, "the server closed the connection");
                            buffer.extend_from_slice(&chunk[..n]);
                        };
                        let head = String::from_utf8_lossy(&buffer[..end]).to_ascii_lowercase();
                        let length: usize = head
                            .lines()
                            .find_map(|l| l.strip_prefix("content-length:"))
                            .and_then(|v| v.trim().parse().ok())
                            .unwrap_or(0);
                        while buffer.len() < end + length {
                            let n = stream.read(&mut chunk).unwrap();
                            assert!(n > 0, "the server closed the connection mid-body");
                            buffer.extend_from_slice(&chunk[..n]);
                        }
                        answered += usize::from(head.starts_with("http/1.1 200"));
                    }
                    answered
                })
            })
            .collect();
        workers.into_iter().map(|w| w.join().unwrap()).sum()
    })
}

/// User and system CPU time of process `pid` so far, in seconds (`/proc/PID/stat`).
fn cpu_seconds(pid: u32) -> f64 {
    let stat = std::fs::read_to_string(format!("/proc/{pid}/stat")).unwrap();
    // Fields after the command's closing parenthesis: utime and stime are the 12th and 13th.
    let rest = &stat[stat.rfind(')').unwrap() + 2..];
    let fields: Vec<&str> = rest.split_whitespace().collect();
    let ticks: f64 = fields[11].parse::<f64>().unwrap() + fields[12].parse::<f64>().unwrap();
    let out = std::process::Command::new("getconf").arg("CLK_TCK").output().unwrap();
    let per_second: f64 = String::from_utf8_lossy(&out.stdout).trim().parse().unwrap();
    ticks / per_second
}

/// The tiles of the data's five finest zooms at 256 px whose eight neighbours lie over
/// the data too (maplibre-contour fails a tile whose neighbour has no data: 404).
fn tiles(doc: &serde_json::Value) -> Vec<(u32, u32, u32)> {
    let bounds: [f64; 4] = serde_json::from_value(doc["bounds"].clone()).unwrap();
    let maxzoom = doc["maxzoom"].as_u64().unwrap() as u8;
    let mut out = vec![];
    for z in maxzoom.saturating_sub(4)..=maxzoom {
        let (columns, rows) = terrastream_views::mercator::tiles_over(z, bounds);
        let (columns, rows) = (columns.start() + 1..*columns.end(), rows.start() + 1..*rows.end());
        out.extend(columns.flat_map(|x| rows.clone().map(move |y| (u32::from(z), x, y))));
    }
    out
}
