//! The server's Web Mercator tiles as a host relies on them: `export --to xyz` writes the
//! server's tiles bit for bit, and an archive packed from a Web Mercator pyramid serves its
//! own tiles as stored (export -> pack -> serve gives back the exported files bit for bit); ETags are strong and a replaced archive never serves
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
    terrastream(&[
        "export",
        a,
        "--to",
        "xyz",
        "--format",
        "png",
        "--size",
        "256",
        "--base-url",
        "https://t/xyz",
        "-o",
        x,
    ]);
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
    // The export is what the server of the archive itself answers, bit for bit.
    let source = terrastream_testkit::server::spawn_serve(exe(), &[a], dir.path());
    let mut same = 0;
    for entry in walk(&xyz).iter().filter(|e| e.extension().is_some_and(|x| x == "png")).step_by(3) {
        let zxy = entry.strip_prefix(&xyz).unwrap().to_str().unwrap().strip_suffix(".png").unwrap().to_owned();
        let (status, head, body) = get(source.port, &format!("/tm/xyz/elevation/{zxy}.png?size=256"), &[]);
        assert_eq!(status, 200, "{zxy}: {head}");
        assert_eq!(body, std::fs::read(entry).unwrap(), "{zxy}: the export differs from the server's tile");
        same += 1;
    }
    assert!(same >= 5, "{same} tiles compared");
    drop(source);
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

/// An imagery layer is a `raster` source too, whatever its tiles' format (PNG, or GPU
/// blocks: BC1, BC7): its web tile's pixels are the source image's at the same places
/// (GDAL's value of the image, bilinear between its pixels).
#[test]
fn imagery_web_tiles_hold_the_source_images_pixels() {
    if Command::new("gdalinfo").arg("--version").output().is_err() {
        assert!(std::env::var_os("CI").is_none(), "gdal-bin is required on CI");
        return;
    }
    let dir = tempfile::tempdir().unwrap();
    let dem = terrastream_testkit::golden::repo().join(DEM);
    // The DEM's hillshade: an image on the DEM's own grid, made by GDAL.
    let shade = dir.path().join("shade.tif");
    let out = Command::new("gdaldem").args(["hillshade", "-q"]).arg(&dem).arg(&shade).output().unwrap();
    assert!(out.status.success(), "{}", String::from_utf8_lossy(&out.stderr));
    // GDAL's values at a grid of pixel centres of the tile over the summit.
    let (z, x, y) = (13u32, 1306u32, 3162u32);
    let n = f64::from(1u32 << z);
    let lon_lat = |u: f64, v: f64| {
        let (fx, fy) = ((f64::from(x) + u / 256.0) / n, (f64::from(y) + v / 256.0) / n);
        (fx * 360.0 - 180.0, (std::f64::consts::PI * (1.0 - 2.0 * fy)).sinh().atan().to_degrees())
    };
    let points: Vec<(u32, u32)> = (0..64).map(|k| (k % 8 * 32 + 16, k / 8 * 32 + 16)).collect();
    let input: String = points
        .iter()
        .map(|&(u, v)| {
            let (lon, lat) = lon_lat(f64::from(u) + 0.5, f64::from(v) + 0.5);
            format!("{lon} {lat}\n")
        })
        .collect();
    let mut child = Command::new("gdallocationinfo")
        .args(["-valonly", "-wgs84", shade.to_str().unwrap()])
        .stdin(std::process::Stdio::piped())
        .stdout(std::process::Stdio::piped())
        .spawn()
        .unwrap();
    std::io::Write::write_all(&mut child.stdin.take().unwrap(), input.as_bytes()).unwrap();
    let out = child.wait_with_output().unwrap();
    let gdal: Vec<Option<f64>> =
        String::from_utf8(out.stdout).unwrap().lines().map(|l| l.trim().parse().ok()).collect();
    assert_eq!(gdal.len(), points.len());
    // GDAL's value is its nearest pixel; ours is bilinear between pixels (and BC1 keeps 5-6
    // bits a channel): a few levels.
    // (BC1 stores green with one bit more than red and blue: a gray is off by a few there.)
    for (format, allowed, spread) in [("png", 12.0, 2), ("bc7", 12.0, 2), ("bc1", 16.0, 8)] {
        let archive = dir.path().join(format!("shaded-{format}.tspack"));
        let (d, s, a) = (dem.to_str().unwrap(), shade.to_str().unwrap(), archive.to_str().unwrap());
        terrastream(&["tile", "--elevation", d, "--texture", s, "--texture-format", format, "-o", a]);
        let server = terrastream_testkit::server::spawn_serve(exe(), &[a], dir.path());
        let name = format!("shaded-{format}");
        let (status, head, body) = get(server.port, &format!("/{name}/texture/tiles.json"), &[]);
        assert_eq!(status, 200, "{head}");
        let tilejson: serde_json::Value = serde_json::from_slice(&body).unwrap();
        assert_eq!(tilejson["type"], serde_json::json!("raster"), "{tilejson}");
        assert!(tilejson.get("encoding").is_none(), "{tilejson}");
        let (status, head, png) = get(server.port, &format!("/{name}/xyz/texture/{z}/{x}/{y}.png?size=256"), &[]);
        assert_eq!(status, 200, "{format}: {head}");
        let (w, h, rgba) = terrastream_testkit::golden::decode_png(&png);
        assert_eq!((w, h), (256, 256));
        let mut compared = 0;
        let mut total = 0.0;
        for (&(u, v), g) in points.iter().zip(&gdal) {
            let px = &rgba[(v as usize * 256 + u as usize) * 4..][..4];
            // hillshade leaves its edge pixels without data (0): those are not compared.
            let Some(g) = g.filter(|&g| g > 0.0) else { continue };
            if px[3] == 0 {
                continue;
            }
            let gray = px[0].abs_diff(px[1]) <= spread && px[1].abs_diff(px[2]) <= spread;
            assert!(gray, "{format}: a gray image stays gray: {px:?}");
            total += (f64::from(px[0]) - g).abs();
            compared += 1;
        }
        assert!(compared >= 40, "{format}: {compared} points compared");
        let mean = total / f64::from(compared);
        eprintln!("{format} imagery web tile against GDAL's nearest image pixel: mean |difference| {mean:.1} of 255");
        assert!(mean < allowed, "{format}: mean difference {mean:.1} of 255");
    }
}

/// The approximate transform of web tiles against the exact one, pixel by pixel, on a
/// transverse-Mercator archive: within 1/8 of an output pixel everywhere, at the finest
/// zooms and at coarse ones where the cells must split.
#[test]
fn the_approximate_transform_stays_within_an_eighth_of_a_pixel() {
    use terrastream_crs::{Crs, Transform};
    use terrastream_views::mercator::{WebTile, tiles_over};
    use terrastream_views::resample::Placed;
    let dir = tempfile::tempdir().unwrap();
    let archive = dir.path().join("tm.tspack");
    tile(DEM, &archive);
    let reader = terrastream_format::Reader::open_mmap(&archive).unwrap();
    let layer = reader.metadata().resolve_layer("elevation").unwrap();
    let placed = Placed::new(&reader, layer).unwrap();
    let g = reader.metadata().georeference.clone().unwrap();
    let to = Transform::new(&Crs::wgs84(), &Crs::parse(g.definition.as_deref().unwrap()).unwrap());
    let (origin, scale) = (g.origin.unwrap(), g.scale.unwrap());
    for z in [3u8, 8, 12, 14] {
        let (columns, rows) = tiles_over(z, [-122.5965, 37.9235, -122.5965, 37.9235]);
        let tile = WebTile::new(z, *columns.start(), *rows.start()).unwrap();
        let size = 256usize;
        let approx = placed.positions(tile, size);
        let exact = |u: f64, v: f64| {
            let (lon, lat) = tile.lon_lat(u, v, size as f64);
            let (cx, cy) = to.apply(lon, lat).unwrap();
            ((cx - origin[0]) / scale[0], (origin[1] - cy) / scale[1])
        };
        let mut worst = 0f64;
        for v in 0..size {
            for u in 0..size {
                let (pu, pv) = (u as f64 + 0.5, v as f64 + 0.5);
                let truth = exact(pu, pv);
                let next = exact(pu + 1.0, pv);
                let pixel = (next.0 - truth.0).hypot(next.1 - truth.1);
                let got = approx.point(v * size + u).unwrap();
                worst = worst.max((got.0 - truth.0).hypot(got.1 - truth.1) / pixel);
            }
        }
        eprintln!("zoom {z}: the approximate transform is within {worst:.4} pixels of the exact one");
        assert!(worst <= 0.125, "zoom {z}: {worst} pixels off");
    }
}

/// An export asked for zooms far finer than the data says so (how far, the data's finest
/// zoom, how many tiles of upsampled data), and still writes what was asked; two zooms
/// beyond the data pass without a word.
#[test]
fn an_export_far_finer_than_the_data_warns() {
    let dir = tempfile::tempdir().unwrap();
    let archive = dir.path().join("dem.tspack");
    tile(OTHER_DEM, &archive);
    let export = |maxzoom: u8| {
        let out = dir.path().join(format!("z{maxzoom}"));
        let (a, o, z) = (archive.to_str().unwrap(), out.to_str().unwrap(), maxzoom.to_string());
        let args = [
            "export",
            a,
            "--to",
            "xyz",
            "--size",
            "256",
            "--minzoom",
            &z,
            "--maxzoom",
            &z,
            "--base-url",
            "https://t/",
            "-o",
            o,
        ];
        let run = Command::new(exe()).args(args).output().unwrap();
        assert!(run.status.success(), "{}", String::from_utf8_lossy(&run.stderr));
        (String::from_utf8_lossy(&run.stderr).into_owned(), walk(&out).len())
    };
    // The data's finest zoom, as its TileJSON says (an export without --maxzoom).
    let probe = dir.path().join("probe");
    let (a, p) = (archive.to_str().unwrap(), probe.to_str().unwrap());
    terrastream(&["export", a, "--to", "xyz", "--size", "256", "--minzoom", "30", "--base-url", "https://t/", "-o", p]);
    let tilejson: serde_json::Value =
        serde_json::from_slice(&std::fs::read(probe.join("tiles.json")).unwrap()).unwrap();
    let finest = u8::try_from(tilejson["maxzoom"].as_u64().unwrap()).unwrap_or(0);
    // Without --base-url, no tiles.json of relative URLs: refused, saying what to give.
    let out = Command::new(exe())
        .args(["export", a, "--to", "xyz", "-o", "nowhere"])
        .current_dir(dir.path())
        .output()
        .unwrap();
    assert!(!out.status.success() && String::from_utf8_lossy(&out.stderr).contains("--base-url"));
    assert!(!dir.path().join("nowhere").exists());
    let (quiet, _) = export(finest + 2);
    assert!(!quiet.contains("finer than the data"), "two zooms beyond the data: {quiet}");
    let (warned, files) = export(finest + 3);
    assert!(
        warned.contains("is 3 zooms finer than the data") && warned.contains(&format!("its finest is zoom {finest}")),
        "{warned}"
    );
    assert!(files > 1, "the zoom asked for is still written: {files} files");
}
