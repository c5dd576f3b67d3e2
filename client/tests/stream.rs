//! The streaming core in a simulated frame loop: coverage without holes, coarse-first
//! arrival, per-frame budgets, cancellation, coalescing, the same tiles from every origin
//! (mmap, HTTP Range against our server and nginx, our tile endpoint, host-fed tiles),
//! height queries, and faults (server stopped, 500s, truncated and corrupted bodies,
//! timeouts, the archive replaced mid-stream).
#![allow(clippy::unwrap_used, clippy::expect_used, clippy::cast_possible_truncation, missing_docs)]

use std::collections::HashMap;
use std::path::Path;
use std::sync::Arc;
use std::sync::atomic::{AtomicU8, Ordering};
use std::time::{Duration, Instant};

use axum::body::Body;
use axum::http::{Request, StatusCode};
use axum::middleware::Next;
use axum::response::{IntoResponse, Response};
use bytes::Bytes;
use glam::DVec3;
use terrastream_client::{
    Camera, DecodedTile, HostTiles, HttpSource, Origin, RetryPolicy, StreamOptions, Streamer, TileData, UploadBudget,
};
use terrastream_format::{AsyncRangeSource, MemorySource, Metadata, Reader, TileKey};
use terrastream_server::app;
use terrastream_testkit::labelled::{LabelledSpec, label_colour, label_height, write_labelled_archive};
use terrastream_testkit::server::{serve_router as serve, state};

const BUDGET: UploadBudget = UploadBudget { max_tiles: 6, max_bytes: 5 * 1024 };

fn labelled(dir: &Path, spec: &LabelledSpec) -> std::path::PathBuf {
    let path = dir.join("terrain.tspack");
    write_labelled_archive(&path, spec).unwrap();
    path
}

/// A camera `height` m above ground point `(x, z)`, looking `ahead` m further south-east.
fn camera(x: f64, z: f64, height: f64, ahead: f64) -> Camera {
    Camera::look_at(DVec3::new(x, 150.0 + height, z), DVec3::new(x + ahead, 150.0, z + ahead), 800, 600)
}

/// What the renderer holds, and the checks every frame must pass.
#[derive(Default)]
struct Gpu {
    tiles: HashMap<TileKey, Arc<DecodedTile>>,
    generation: u64,
    frames: usize,
    max_tiles_per_frame: usize,
    max_bytes_per_frame: usize,
}

impl Gpu {
    /// One frame: update, drain within the budget, check what arrived.
    fn frame(&mut self, s: &mut Streamer, cam: &Camera) -> usize {
        s.update(cam);
        if s.generation() != self.generation {
            // A replaced archive: everything of the old version goes.
            self.tiles.clear();
            self.generation = s.generation();
        }
        let uploads = s.drain_uploads(BUDGET);
        let bytes: usize = uploads.iter().map(|u| u.tile.byte_len()).sum();
        assert!(uploads.len() <= BUDGET.max_tiles && bytes <= BUDGET.max_bytes, "budget exceeded");
        self.max_tiles_per_frame = self.max_tiles_per_frame.max(uploads.len());
        self.max_bytes_per_frame = self.max_bytes_per_frame.max(bytes);
        let Some(meta) = s.metadata().cloned() else {
            assert!(uploads.is_empty());
            self.frames += 1;
            return 0;
        };
        for u in &uploads {
            assert_eq!(u.generation, self.generation);
            let key = u.tile.key;
            let num_lods = meta.layers[usize::from(key.layer())].num_lods;
            if let Some(p) = key.parent().filter(|p| p.lod() < num_lods) {
                assert!(self.tiles.contains_key(&p) || s.is_unavailable(p), "{key} arrived before its parent");
            }
            self.tiles.insert(key, u.tile.clone());
        }
        self.frames += 1;
        uploads.len()
    }

    /// Every tile held is the right one, of `version`.
    fn check_content(&self, meta: &Metadata, version: u8) {
        for (key, tile) in &self.tiles {
            check_tile(meta, *key, tile, version);
        }
    }

    /// Every wanted area is covered by a held tile at some LOD (its own or an ancestor's).
    fn assert_covered(&self, s: &Streamer) {
        for w in s.wanted().iter().filter(|w| w.leaf && w.in_view) {
            let mut k = Some(w.key);
            let mut covered = false;
            while let Some(key) = k {
                if self.tiles.contains_key(&key) {
                    covered = true;
                    break;
                }
                k = key.parent();
            }
            let sparse = s.is_missing(w.key) || w.key.parent().is_some_and(|p| s.is_missing(p));
            assert!(covered || sparse, "frame {}: a hole at {}", self.frames, w.key);
        }
    }

    /// Frames until the view is fully streamed.
    fn settle(&mut self, s: &mut Streamer, cam: &Camera) -> usize {
        let start = Instant::now();
        let mut frames = 0;
        loop {
            self.frame(s, cam);
            frames += 1;
            if s.pending() == 0 && s.metadata().is_some() {
                return frames;
            }
            assert!(start.elapsed() < Duration::from_secs(30), "not settled: {:?} {:?}", s.stats(), s.last_error());
            std::thread::sleep(Duration::from_millis(1));
        }
    }
}

fn check_tile(meta: &Metadata, key: TileKey, tile: &DecodedTile, version: u8) {
    match &tile.data {
        TileData::Rgba8(p) => {
            let [r, g, b] = label_colour(key.lod(), key.x(), key.y(), version);
            assert_eq!(&p[..4], &[r, g, b, 255], "tile {key} shows another tile's pixels");
        }
        TileData::Heights { .. } => {
            let layer = &meta.layers[usize::from(key.layer())];
            let size = layer.world_size_at(key.lod());
            let step = size / f64::from(layer.tile_resolution);
            let want =
                label_height(f64::from(key.x()) * size + step / 2.0, f64::from(key.y()) * size + step / 2.0, version);
            assert!((f64::from(tile.height(0, 0).unwrap()) - want).abs() < 1e-2, "tile {key} heights");
        }
        TileData::Compressed { .. } => panic!("no compressed tiles here"),
    }
}

fn options() -> StreamOptions {
    // 16-pixel tiles: a coarse pixel error keeps the view's working set realistic.
    let select = terrastream_client::SelectOptions { pixel_error: 8.0, ..Default::default() };
    StreamOptions {
        select,
        retry_backoff: Duration::from_millis(5),
        max_retry_backoff: Duration::from_millis(50),
        ..StreamOptions::default()
    }
}

#[test]
fn a_camera_jump_keeps_coverage_and_refines_coarse_first_within_budget() {
    let dir = tempfile::tempdir().unwrap();
    let spec = LabelledSpec::default();
    let path = labelled(dir.path(), &spec);
    let mut s = Streamer::open(Origin::parse(path.to_str().unwrap()).unwrap(), options()).unwrap();
    let meta = s.metadata().unwrap().clone();
    let mut gpu = Gpu::default();
    let a = camera(200.0, 200.0, 30.0, 200.0);
    gpu.settle(&mut s, &a);
    assert!(gpu.tiles.keys().any(|k| k.lod() == 0 && k.layer() == 0), "full detail near the eye");
    // Jump across the terrain: from the first frame on, no hole.
    let b = camera(1400.0, 1300.0, 20.0, -300.0);
    let before = gpu.tiles.len();
    let start = Instant::now();
    loop {
        gpu.frame(&mut s, &b);
        gpu.assert_covered(&s);
        if s.pending() == 0 {
            break;
        }
        assert!(start.elapsed() < Duration::from_secs(30), "{:?}", s.stats());
        std::thread::sleep(Duration::from_millis(1));
    }
    assert!(gpu.tiles.len() > before);
    let near_b = TileKey::new(0, 0, 1400 / 50, 1300 / 50).unwrap();
    assert!(gpu.tiles.contains_key(&near_b), "full detail at the new place");
    gpu.check_content(&meta, 1);
    assert_eq!(gpu.max_bytes_per_frame, BUDGET.max_bytes, "the budget was the limit at times");
    let stats = s.stats();
    assert_eq!(stats.failures, 0);
    assert!(stats.coalesced > 0, "neighbouring tiles were coalesced: {stats:?}");
}

/// A source that takes `delay` per request (a slow network).
struct Slow {
    inner: MemorySource,
    delay: Duration,
}

impl AsyncRangeSource for Slow {
    async fn size(&self) -> terrastream_format::Result<u64> {
        Ok(terrastream_format::RangeSource::len(&self.inner))
    }
    async fn fetch(&self, offset: u64, len: u64) -> terrastream_format::Result<Bytes> {
        if offset > 0 {
            tokio::time::sleep(self.delay).await;
        }
        terrastream_format::RangeSource::read_range(&self.inner, offset, len)
    }
}

#[test]
fn requests_the_camera_no_longer_needs_are_cancelled() {
    let dir = tempfile::tempdir().unwrap();
    let path = labelled(dir.path(), &LabelledSpec::default());
    let slow = Slow { inner: MemorySource::new(std::fs::read(&path).unwrap()), delay: Duration::from_millis(100) };
    let opts = StreamOptions { coalesce: false, max_in_flight: 4, ..options() };
    let mut s = Streamer::open(Origin::archive(slow), opts).unwrap();
    let mut gpu = Gpu::default();
    let a = camera(100.0, 100.0, 20.0, 100.0);
    gpu.settle(&mut s, &a);
    // Move on to a far corner and, before those requests finish, move back home.
    let b = camera(1500.0, 1500.0, 10.0, -60.0);
    gpu.frame(&mut s, &b);
    assert_eq!(s.stats().in_flight, 4, "the in-flight cap holds");
    gpu.frame(&mut s, &a);
    let stats = s.stats();
    assert!(stats.cancelled >= 1, "requests for the far corner were cancelled: {stats:?}");
    assert!(stats.in_flight < 4, "{stats:?}");
    gpu.settle(&mut s, &a);
}

/// Flies a short path, waiting at each stop until streamed; returns every tile shown.
fn fly(origin: Origin, opts: StreamOptions) -> (HashMap<TileKey, Arc<DecodedTile>>, terrastream_client::StreamStats) {
    let mut s = Streamer::new(origin, opts).unwrap();
    let mut gpu = Gpu::default();
    for (x, z) in [(100.0, 100.0), (700.0, 300.0), (1500.0, 1500.0)] {
        gpu.settle(&mut s, &camera(x, z, 25.0, 150.0));
    }
    (gpu.tiles, s.stats())
}

#[test]
fn the_same_tiles_come_from_mmap_http_nginx_the_tile_endpoint_and_host_tiles() {
    let dir = tempfile::tempdir().unwrap();
    let spec = LabelledSpec { sparse_from: Some(24), ..LabelledSpec::default() };
    let path = labelled(dir.path(), &spec);
    let server = tokio::runtime::Runtime::new().unwrap();
    let (addr, _task) = server.block_on(serve(app(state(dir.path())), "127.0.0.1:0"));

    let (reference, mmap_stats) = fly(Origin::parse(path.to_str().unwrap()).unwrap(), options());
    assert!(reference.len() > 100, "{}", reference.len());
    assert!(mmap_stats.missing > 0, "the sparse area was found missing");
    let meta = Reader::open_mmap(&path).unwrap().metadata().clone();
    for (k, t) in &reference {
        check_tile(&meta, *k, t, 1);
    }
    let same = |name: &str, tiles: &HashMap<TileKey, Arc<DecodedTile>>| {
        assert_eq!(tiles.len(), reference.len(), "{name}");
        for (k, t) in tiles {
            assert_eq!(Some(t), reference.get(k), "{name}: tile {k}");
        }
    };
    let (http, http_stats) = fly(Origin::parse(&format!("http://{addr}/terrain.tspack")).unwrap(), options());
    same("HTTP Range, our server", &http);
    assert!(http_stats.requests < http_stats.tiles_fetched, "coalesced: {http_stats:?}");
    let (endpoint, _) = fly(Origin::parse(&format!("http://{addr}/terrain")).unwrap(), options());
    same("tile endpoint", &endpoint);

    let shipped =
        std::fs::read_to_string(concat!(env!("CARGO_MANIFEST_DIR"), "/../deploy/nginx/tspack-static.conf")).unwrap();
    let config =
        shipped.replace("listen 8080;", "listen 127.0.0.1:{port};").replace("root /srv/terrastream;", "root {root};");
    if let Some(nginx) = terrastream_testkit::nginx::start_nginx(dir.path(), &config) {
        let url = format!("http://127.0.0.1:{}/terrain.tspack", nginx.port);
        let (tiles, _) = fly(Origin::parse(&url).unwrap(), options());
        same("HTTP Range, nginx", &tiles);
    }

    // The host application hands tiles in itself.
    let reader = Reader::open_mmap(&path).unwrap();
    let host = Arc::new(HostTiles::new(reader.metadata().clone()).unwrap());
    reader
        .for_each_entry(|e| -> terrastream_format::Result<()> {
            for i in 0..e.run_length {
                let key = reader.archive().tile_of(e.key + u64::from(i) * 16).unwrap();
                host.insert(key, reader.tile(key).unwrap().unwrap()).unwrap();
            }
            Ok(())
        })
        .unwrap();
    let (hosted, _) = fly(Origin::Host(host), options());
    same("host tiles", &hosted);
}

#[test]
fn coalescing_at_least_halves_requests_per_tile() {
    let dir = tempfile::tempdir().unwrap();
    let path = labelled(dir.path(), &LabelledSpec::default());
    let origin = || Origin::parse(path.to_str().unwrap()).unwrap();
    let (with, on) = fly(origin(), options());
    let (without, off) = fly(origin(), StreamOptions { coalesce: false, ..options() });
    assert_eq!(with.len(), without.len());
    let per_tile = |s: &terrastream_client::StreamStats| s.requests as f64 / s.tiles_fetched as f64;
    assert!(per_tile(&on) * 2.0 <= per_tile(&off), "{on:?} vs {off:?}");
}

#[test]
fn heights_and_normals_match_the_data() {
    let dir = tempfile::tempdir().unwrap();
    let path = labelled(dir.path(), &LabelledSpec::default());
    let mut s = Streamer::open(Origin::parse(path.to_str().unwrap()).unwrap(), options()).unwrap();
    // Nothing loaded: no answer, but the exact query fetches LOD 0.
    assert_eq!(s.height_at(333.3, 444.4), None);
    let exact = s.height_at_exact(333.3, 444.4).unwrap().unwrap();
    assert!((exact - label_height(333.3, 444.4, 1)).abs() < 1e-3, "{exact}");
    let mut gpu = Gpu::default();
    gpu.settle(&mut s, &camera(300.0, 300.0, 30.0, 100.0));
    // The data is a plane: bilinear sampling is exact at any LOD, across tile edges too.
    for (x, z) in [(310.0, 320.0), (400.0, 400.0), (1000.5, 57.25), (1500.0, 100.0)] {
        let h = s.height_at(x, z).unwrap();
        assert!((h - label_height(x, z, 1)).abs() < 1e-2, "({x}, {z}): {h}");
        let n = s.normal_at(x, z).unwrap();
        let want = DVec3::new(-0.05, 1.0, -0.02).normalize();
        assert!((DVec3::from_array(n) - want).length() < 1e-4, "({x}, {z}): {n:?}");
    }
    assert_eq!(s.height_at(-5.0, 10.0), None, "outside the terrain");
    assert!(s.height_at_exact(-5.0, 10.0).is_err());
}

/// What the fault-injecting proxy does to the next responses.
const NORMAL: u8 = 0;
const ERROR_500: u8 = 1;
const TRUNCATE: u8 = 2;
const CORRUPT: u8 = 3;
const STALL: u8 = 4;

#[test]
fn faults_never_show_a_wrong_tile_and_streaming_recovers() {
    let dir = tempfile::tempdir().unwrap();
    let path = labelled(dir.path(), &LabelledSpec::default());
    let meta = Reader::open_mmap(&path).unwrap().metadata().clone();
    let runtime = tokio::runtime::Runtime::new().unwrap();
    let app_state = state(dir.path());
    let mode = Arc::new(AtomicU8::new(NORMAL));
    let router = {
        let mode = mode.clone();
        app(app_state.clone()).layer(axum::middleware::from_fn(move |req: Request<Body>, next: Next| {
            let m = mode.load(Ordering::SeqCst);
            async move {
                let large = req.headers().get("range").is_some_and(|r| r.to_str().unwrap_or("") != "bytes=0-16383");
                match m {
                    ERROR_500 if large => return StatusCode::INTERNAL_SERVER_ERROR.into_response(),
                    STALL if large => tokio::time::sleep(Duration::from_secs(2)).await,
                    _ => {}
                }
                let response: Response = next.run(req).await;
                if !(large && matches!(m, TRUNCATE | CORRUPT)) || response.status() != StatusCode::PARTIAL_CONTENT {
                    return response;
                }
                let (mut parts, body) = response.into_parts();
                let mut bytes = axum::body::to_bytes(body, usize::MAX).await.unwrap().to_vec();
                if m == TRUNCATE {
                    parts.headers.remove("content-length");
                    bytes.truncate(bytes.len() / 2);
                } else {
                    // Flip a byte in every tile's payload region.
                    for b in bytes.iter_mut().step_by(7) {
                        *b ^= 0x5a;
                    }
                }
                Response::from_parts(parts, Body::from(bytes))
            }
        }))
    };
    let (addr, task) = runtime.block_on(serve(router.clone(), "127.0.0.1:0"));
    let url = format!("http://{addr}/terrain.tspack");
    let policy =
        RetryPolicy { attempts: 2, first_backoff: Duration::from_millis(5), timeout: Duration::from_millis(400) };
    let source = HttpSource::with_client(reqwest::Client::new(), &url, policy).unwrap();
    let mut s = Streamer::new(Origin::archive(source), options()).unwrap();
    let mut gpu = Gpu::default();
    let places = [(100.0, 100.0), (800.0, 200.0), (300.0, 900.0), (1200.0, 1200.0), (1500.0, 300.0), (600.0, 1500.0)];
    let cam = |i: usize| camera(places[i].0, places[i].1, 20.0, 120.0);
    gpu.settle(&mut s, &cam(0));

    // Each fault in turn while the camera moves on: frames keep coming, nothing wrong is
    // shown; once the fault ends the new view streams in full.
    let mut task = Some(task);
    for (i, fault) in [ERROR_500, TRUNCATE, CORRUPT, STALL, 99].into_iter().enumerate() {
        let failures = s.stats().failures;
        if fault == 99 {
            // The server stops mid-stream, then comes back on the same port.
            let t = task.take().unwrap();
            t.abort();
            let _ = runtime.block_on(t);
        } else {
            mode.store(fault, Ordering::SeqCst);
        }
        let c = cam(i + 1);
        let until = Instant::now() + Duration::from_millis(if fault == STALL { 1500 } else { 400 });
        while Instant::now() < until {
            gpu.frame(&mut s, &c);
            gpu.assert_covered(&s);
            std::thread::sleep(Duration::from_millis(2));
        }
        gpu.check_content(&meta, 1);
        assert!(s.stats().failures > failures, "fault {fault} was noticed: {:?}", s.stats());
        assert!(s.pending() > 0, "fault {fault}: the new view could not be complete");
        if fault == 99 {
            task = Some(runtime.block_on(serve(router.clone(), &addr.to_string())).1);
        }
        mode.store(NORMAL, Ordering::SeqCst);
        gpu.settle(&mut s, &c);
        gpu.check_content(&meta, 1);
    }

    // The archive is replaced (atomic rename) mid-stream: the old version's tiles are all
    // dropped, and only the new version's are shown from then on.
    let generation = s.generation();
    let next = dir.path().join("next.tmp");
    write_labelled_archive(&next, &LabelledSpec { version: 2, ..LabelledSpec::default() }).unwrap();
    std::fs::rename(&next, &path).unwrap();
    app_state.catalog.reload();
    let far = camera(50.0, 1500.0, 15.0, 80.0);
    gpu.settle(&mut s, &far);
    assert!(s.generation() > generation, "the replacement was noticed");
    assert_eq!(s.stats().reloads, 1);
    let meta2 = Reader::open_mmap(&path).unwrap().metadata().clone();
    gpu.check_content(&meta2, 2);
    assert!(!gpu.tiles.is_empty());
    drop(task);
}

/// Prefetch along the camera's motion: flying at a steady speed, the tiles coming into
/// view were fetched before they were wanted, so more of each new view is found in the
/// cache than without prefetch; a stationary camera prefetches nothing.
#[test]
fn a_moving_camera_finds_the_tiles_ahead_already_fetched() {
    let dir = tempfile::tempdir().unwrap();
    let path = labelled(dir.path(), &LabelledSpec::default());
    let fly = |prefetch: Duration| {
        let opts = StreamOptions { prefetch_ahead: prefetch, ..options() };
        let mut s = Streamer::open(Origin::parse(path.to_str().unwrap()).unwrap(), opts).unwrap();
        let mut gpu = Gpu::default();
        gpu.settle(&mut s, &camera(200.0, 200.0, 30.0, 200.0));
        let settled = s.stats().hits;
        // 20 steps of 40 m, 50 ms apart (800 m/s), each given time to fetch.
        for i in 1..=20 {
            std::thread::sleep(Duration::from_millis(50));
            gpu.frame(&mut s, &camera(200.0 + 40.0 * f64::from(i), 200.0, 30.0, 200.0));
        }
        // Then stationary: nothing ahead to fetch.
        std::thread::sleep(Duration::from_millis(50));
        let here = camera(1000.0, 200.0, 30.0, 200.0);
        gpu.frame(&mut s, &here);
        gpu.frame(&mut s, &here);
        (s.stats().hits - settled, s.stats())
    };
    let (with, stats) = fly(Duration::from_millis(500));
    let (without, _) = fly(Duration::ZERO);
    assert!(with > without, "wanted tiles found in the cache while flying: {with} with prefetch, {without} without");
    assert_eq!(stats.prefetch, 0, "a stationary camera prefetches nothing: {stats:?}");
}
