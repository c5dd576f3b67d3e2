//! The server's Web Mercator tiles as a host relies on them: an archive packed from a
//! Web Mercator pyramid serves its own tiles as stored (export -> pack -> serve gives back
//! the exported files bit for bit); ETags are strong and a replaced archive never serves
//! its predecessor's tiles; a flood of cold tiles is bounded (503 with `Retry-After`
//! beyond the queue) while health checks, Range reads and cached tiles keep answering.
#![allow(clippy::unwrap_used, clippy::expect_used, clippy::cast_possible_truncation, missing_docs)]

use std::path::{Path, PathBuf};
use std::process::Command;
use std::sync::Arc;
use std::sync::atomic::{AtomicBool, Ordering};
use std::time::{Duration, Instant};

const DEM: &str = "packer/pack/data/srtm-tamalpais-320-public-domain.tif";
const OTHER_DEM: &str = "tests/data/srtm-tamalpais-150x100-strips-int16-public-domain.tif";

fn exe() -> &'static Path {
    Path::new(env!("CARGO_BIN_EXE_terrastream"))
}

fn terrastream(args: &[&str]) {
    let out = Command::new(exe()).arg("-q").args(args).output().unwrap();
    assert!(out.status.success(), "terrastream {args:?}: {}", String::from_utf8_lossy(&out.stderr));
}

fn tile(dem: &str, out: &Path) {
    let dem = terrastream_testkit::golden::repo().join(dem);
    terrastream(&["tile", "--elevation", dem.to_str().unwrap(), "-o", out.to_str().unwrap()]);
}

/// One GET: status, the raw head (lowercase) and the body.
fn get(port: u16, path: &str, headers: &[(&str, &str)]) -> (u16, String, Vec<u8>) {
    use std::io::{Read, Write};
    let mut s = std::net::TcpStream::connect(("127.0.0.1", port)).unwrap();
    s.set_read_timeout(Some(Duration::from_secs(60))).unwrap();
    let extra: String = headers.iter().map(|(k, v)| format!("{k}: {v}\r\n")).collect();
    write!(s, "GET {path} HTTP/1.1\r\nHost: 127.0.0.1:{port}\r\n{extra}Connection: close\r\n\r\n").unwrap();
    let mut answer = Vec::new();
    s.read_to_end(&mut answer).unwrap();
    let end = answer.windows(4).position(|w| w == b"\r\n\r\n").expect("an HTTP head");
    let head = String::from_utf8_lossy(&answer[..end]).to_lowercase();
    let status = head.split(' ').nth(1).and_then(|s| s.parse().ok()).unwrap_or(0);
    let mut body = answer[end + 4..].to_vec();
    if head.contains("transfer-encoding: chunked") {
        body = dechunk(&body);
    }
    (status, head, body)
}

fn dechunk(mut b: &[u8]) -> Vec<u8> {
    let mut out = Vec::new();
    loop {
        let line_end = b.windows(2).position(|w| w == b"\r\n").unwrap();
        let size = usize::from_str_radix(std::str::from_utf8(&b[..line_end]).unwrap().trim(), 16).unwrap();
        if size == 0 {
            return out;
        }
        out.extend_from_slice(&b[line_end + 2..line_end + 2 + size]);
        b = &b[line_end + 4 + size..];
    }
}

fn header<'a>(head: &'a str, name: &str) -> Option<&'a str> {
    head.lines().find_map(|l| l.strip_prefix(&format!("{name}: ")))
}

#[test]
fn a_web_mercator_archive_serves_its_own_tiles_as_stored() {
    let dir = tempfile::tempdir().unwrap();
    let archive = dir.path().join("tm.tspack");
    tile(DEM, &archive);
    // Exported as 256-px Terrarium PNGs, packed as an XYZ tree: the archive's grid is the
    // Web Mercator grid, and its tiles are what the export wrote.
    let xyz = dir.path().join("xyz");
    let packed = dir.path().join("mercator.tspack");
    let (a, x, p) = (archive.to_str().unwrap(), xyz.to_str().unwrap(), packed.to_str().unwrap());
    terrastream(&["export", a, "--to", "xyz", "--format", "png", "--size", "256", "-o", x]);
    terrastream(&[
        "pack",
        x,
        "--kind",
        "elevation",
        "--elevation-encoding",
        "terrarium",
        "--template",
        "{z}/{x}/{y}.png",
        "-o",
        p,
    ]);
    let server = terrastream_testkit::server::spawn_serve(exe(), &[p], dir.path());
    let mut compared = 0;
    for entry in walk(&xyz) {
        let relative = entry.strip_prefix(&xyz).unwrap().to_str().unwrap().to_owned();
        let Some(zxy) = relative.strip_suffix(".png") else { continue };
        let (status, head, body) = get(server.port, &format!("/mercator/xyz/elevation/{zxy}.png?size=256"), &[]);
        assert_eq!(status, 200, "{zxy}: {head}");
        assert_eq!(body, std::fs::read(&entry).unwrap(), "{zxy}: not the stored tile");
        compared += 1;
    }
    assert!(compared >= 10, "{compared} tiles compared");
    // Asked otherwise (WebP, 512 px, Terrain-RGB), the tiles are made from the stored ones.
    let (status, head, _) = get(server.port, "/mercator/xyz/elevation/12/653/1581.webp?encoding=mapbox", &[]);
    assert_eq!(status, 200, "{head}");
    assert_eq!(header(&head, "content-type"), Some("image/webp"));
}

fn walk(dir: &Path) -> Vec<PathBuf> {
    let mut out = Vec::new();
    for entry in std::fs::read_dir(dir).unwrap() {
        let path = entry.unwrap().path();
        if path.is_dir() {
            out.extend(walk(&path));
        } else {
            out.push(path);
        }
    }
    out.sort();
    out
}

#[test]
fn etags_are_strong_and_a_replaced_archive_serves_no_stale_tile() {
    let dir = tempfile::tempdir().unwrap();
    let served = dir.path().join("t.tspack");
    tile(DEM, &served);
    let server = terrastream_testkit::server::spawn_serve(exe(), &[served.to_str().unwrap()], dir.path());
    let path = "/t/xyz/elevation/12/653/1581.png";
    let (status, head, first) = get(server.port, path, &[]);
    assert_eq!(status, 200, "{head}");
    let etag = header(&head, "etag").unwrap().to_owned();
    assert!(etag.starts_with('"') && !etag.starts_with("w/"), "a strong ETag: {etag}");
    assert_eq!(header(&head, "access-control-allow-origin"), Some("*"), "{head}");
    let (status, _, _) = get(server.port, path, &[("If-None-Match", &etag)]);
    assert_eq!(status, 304);
    // Replaced by another terrain (renamed over it, as a deploy does).
    let next = dir.path().join("next.tspack");
    tile(OTHER_DEM, &next);
    std::fs::rename(&next, &served).unwrap();
    let started = Instant::now();
    loop {
        let (status, head, body) = get(server.port, path, &[("If-None-Match", &etag)]);
        let new_etag = header(&head, "etag").unwrap_or_default().to_owned();
        if new_etag != etag {
            assert!(status == 200 || status == 404, "{head}");
            assert_ne!(body, first, "the replaced archive's tile");
            break;
        }
        assert_eq!(status, 304, "same ETag, so the same tile: {head}");
        assert!(started.elapsed() < Duration::from_secs(20), "the replacement was never picked up");
        std::thread::sleep(Duration::from_millis(100));
    }
}

#[test]
fn a_flood_of_cold_tiles_is_bounded_and_the_rest_keeps_answering() {
    let dir = tempfile::tempdir().unwrap();
    let served = dir.path().join("t.tspack");
    tile(DEM, &served);
    let config = dir.path().join("server.toml");
    std::fs::write(&config, "web_threads = 1\nweb_queue = 4\nweb_cache_bytes = 0\n").unwrap();
    let args = [served.to_str().unwrap(), "--config", config.to_str().unwrap()];
    let server = terrastream_testkit::server::spawn_serve(exe(), &args, dir.path());
    let port = server.port;
    // The routes that must stay fast, timed alone first.
    let quick = [("/healthz", vec![]), ("/t.tspack", vec![("Range", "bytes=0-16383")]), ("/t/metadata", vec![])];
    let time = |rounds: usize| -> Vec<f64> {
        let mut ms = Vec::new();
        for _ in 0..rounds {
            for (path, headers) in &quick {
                let started = Instant::now();
                let (status, head, _) = get(port, path, headers);
                assert!(status == 200 || status == 206, "{path}: {head}");
                ms.push(started.elapsed().as_secs_f64() * 1e3);
            }
        }
        ms.sort_by(f64::total_cmp);
        ms
    };
    let p99 = |ms: &[f64]| ms[ms.len() * 99 / 100];
    let alone = time(30);
    // The flood: 32 clients asking for distinct cold tiles (no cache) as fast as they can.
    let stop = Arc::new(AtomicBool::new(false));
    let flooders: Vec<_> = (0..32u32)
        .map(|c| {
            let stop = Arc::clone(&stop);
            std::thread::spawn(move || {
                let (mut ok, mut busy) = (0u32, 0u32);
                let mut i = 0u32;
                while !stop.load(Ordering::Relaxed) {
                    let (x, y) = (1300 + (c * 7 + i) % 16, 3156 + (c + i * 3) % 16);
                    let (status, head, _) = get(port, &format!("/t/xyz/elevation/13/{x}/{y}.webp?size=256"), &[]);
                    match status {
                        200 | 404 => ok += 1,
                        503 => {
                            assert_eq!(header(&head, "retry-after"), Some("1"), "{head}");
                            busy += 1;
                        }
                        other => panic!("a flooded tile answered {other}: {head}"),
                    }
                    i += 1;
                }
                (ok, busy)
            })
        })
        .collect();
    std::thread::sleep(Duration::from_millis(300));
    let flooded = time(30);
    stop.store(true, Ordering::Relaxed);
    let (ok, busy) = flooders.into_iter().map(|t| t.join().unwrap()).fold((0, 0), |a, b| (a.0 + b.0, a.1 + b.1));
    eprintln!(
        "p99 of health, Range and metadata: {:.2} ms alone, {:.2} ms under a flood of cold tiles ({ok} made, {busy} refused with 503)",
        p99(&alone),
        p99(&flooded)
    );
    assert!(ok > 0, "no flooded tile was made");
    assert!(busy > 0, "a queue of 4 behind one thread never filled under 32 clients");
    // Within a few times their usual p99 (not behind the queue of cold tiles, which take
    // tens of milliseconds each).
    assert!(p99(&flooded) <= (4.0 * p99(&alone)).max(100.0), "{:.2} ms vs {:.2} ms", p99(&flooded), p99(&alone));
}
