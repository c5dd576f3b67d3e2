//! `terrastream bench stream`: flies a scripted camera path over an archive, from a local
//! file (mmap) and over HTTP on loopback and emulated links (our server, Range requests on
//! the archive), with our scheduler and with a baseline client (one request per tile, six
//! at once, as a PMTiles-style reader in a browser), and prints time to full detail after each jump, requests per
//! tile, bytes fetched vs needed, and uploads per frame against the budget.

use std::path::PathBuf;
use std::time::{Duration, Instant};

use anyhow::{Context, Result};
use clap::Args;
use terrastream_client::{Camera, Origin, SelectOptions, StreamOptions, StreamStats, Streamer, UploadBudget};
use terrastream_format::Metadata;
use terrastream_pack::labelled::{LabelledSpec, write_labelled_archive};
use terrastream_server::shaper::{Link, Shaper};
use terrastream_server::{AppState, ServerConfig};

#[derive(Debug, Args)]
pub struct StreamBench {
    /// Archive to fly over (default: a generated 64x64-tile terrain).
    #[arg(long)]
    archive: Option<PathBuf>,
    /// Most tiles uploaded per frame.
    #[arg(long, default_value_t = 8)]
    max_tiles_per_frame: usize,
    /// Most bytes uploaded per frame.
    #[arg(long, default_value_t = 1 << 20)]
    max_upload_bytes_per_frame: usize,
    /// Most requests in flight (the adaptive limit stays under it).
    #[arg(long, default_value_t = StreamOptions::default().max_in_flight)]
    max_in_flight: usize,
    /// Keep `--max-in-flight` requests in flight instead of adapting the limit to the link.
    #[arg(long)]
    fixed_in_flight: bool,
    /// Also fly every HTTP location over HTTP/2 (h2c: one multiplexed connection).
    #[arg(long)]
    http2: bool,
    /// Fetch only what the current view wants (no prefetch along the camera's motion).
    #[arg(long)]
    no_prefetch: bool,
    /// Frames of continuous flight between jumps.
    #[arg(long, default_value_t = 60)]
    flight_frames: usize,
    /// Largest gap in bytes between two tiles that still merges them into one request.
    #[arg(long, default_value_t = StreamOptions::default().coalesce_gap)]
    coalesce_gap: u64,
    /// Largest coalesced request in bytes.
    #[arg(long, default_value_t = StreamOptions::default().max_request_bytes)]
    max_request_bytes: u64,
    /// Viewport height in pixels (the selection's screen-space error depends on it).
    #[arg(long, default_value_t = 720)]
    viewport_height: u32,
    /// Links to fly HTTP over besides loopback, emulated by a shaping proxy in front of the
    /// server: `a` (20 ms RTT, 100 Mbit/s), `b` (80 ms, 20 Mbit/s), `c` (150 ms, 5 Mbit/s,
    /// 1 % loss). Comma-separated, e.g. `--links a,b,c`.
    #[arg(long, value_delimiter = ',')]
    links: Vec<LinkArg>,
}

#[derive(Clone, Copy, Debug, clap::ValueEnum)]
enum LinkArg {
    A,
    B,
    C,
}

impl LinkArg {
    fn link(self) -> Link {
        match self {
            Self::A => Link::NEAR,
            Self::B => Link::FAR,
            Self::C => Link::POOR,
        }
    }
}

/// Requests in flight of the baseline client.
const BASELINE_IN_FLIGHT: usize = 6;

struct Run {
    name: String,
    /// From opening the archive to the first view complete (every wanted tile shown).
    first_frame: Duration,
    time_to_detail: Vec<Duration>,
    uploads_per_frame: Vec<usize>,
    bytes_per_frame: Vec<usize>,
    /// Frames from the first complete one on, and those of them with a hole (an area in
    /// view that no delivered tile covers at any LOD).
    frames_shown: usize,
    frames_with_hole: usize,
    stats: StreamStats,
}

impl Run {
    fn median_ttd(&self) -> Duration {
        let mut t = self.time_to_detail.clone();
        t.sort();
        t.get(t.len() / 2).copied().unwrap_or_default()
    }
    fn requests_per_tile(&self) -> f64 {
        self.stats.requests as f64 / self.stats.tiles_fetched.max(1) as f64
    }
}

pub fn run(args: StreamBench) -> Result<()> {
    let dir = tempfile::tempdir()?;
    let path = match &args.archive {
        Some(p) => p.clone(),
        None => generated_archive(dir.path())?,
    };
    let name = path.file_stem().and_then(|s| s.to_str()).context("archive name")?.to_owned();
    // Our server on a loopback port, in its own runtime.
    let server = tokio::runtime::Runtime::new()?;
    let state = AppState::new(ServerConfig { paths: vec![path.clone()], ..ServerConfig::default() });
    state.catalog.reload();
    let listener = server.block_on(tokio::net::TcpListener::bind("127.0.0.1:0"))?;
    let addr = listener.local_addr()?;
    server.spawn(terrastream_server::serve(listener, state, std::future::pending()));
    let url = format!("http://{addr}/{name}.tspack");

    let budget = UploadBudget { max_tiles: args.max_tiles_per_frame, max_bytes: args.max_upload_bytes_per_frame };
    // A shaping proxy in front of the server for each emulated link.
    let mut shapers = Vec::new();
    let mut locations = vec![("mmap".to_owned(), path.display().to_string()), ("HTTP".to_owned(), url.clone())];
    for link in &args.links {
        let shaper = server.block_on(Shaper::start(addr, link.link()))?;
        let l = link.link();
        let label = format!("HTTP {:?} {}ms/{}M", link, l.rtt.as_millis(), l.rate / 1_000_000);
        locations.push((label, format!("http://{}/{name}.tspack", shaper.addr)));
        shapers.push(shaper);
    }
    if args.http2 {
        let h2: Vec<(String, String)> = locations
            .iter()
            .filter(|(_, l)| l.starts_with("http://"))
            .map(|(label, l)| (format!("{label}, HTTP/2"), format!("h2c:{l}")))
            .collect();
        locations.extend(h2);
    }
    let mut runs = Vec::new();
    for (label, location) in locations {
        for coalesce in [true, false] {
            let origin = match location.strip_prefix("h2c:") {
                Some(url) => Origin::archive(terrastream_client::HttpSource::new_http2(url)?),
                None => Origin::parse(&location)?,
            };
            let name = format!("{label}{}", if coalesce { "" } else { ", baseline" });
            eprintln!("flying: {name}");
            runs.push(fly(name, origin, stream_options(&args, coalesce), budget, &args)?);
        }
    }
    println!("archive: {} ({url} on loopback)", path.display());
    println!(
        "budget: {} tiles / {} bytes per frame; {} requests in flight at most ({})\n",
        budget.max_tiles,
        budget.max_bytes,
        args.max_in_flight,
        if args.fixed_in_flight { "fixed" } else { "adaptive limit under it" }
    );
    print_runs(&runs);
    print_ratios(&runs, budget);
    drop(shapers);
    drop(server);
    Ok(())
}

/// A generated terrain of 64 x 64 texture tiles in `dir`, when no archive is given.
fn generated_archive(dir: &std::path::Path) -> Result<PathBuf> {
    let p = dir.join("terrain.tspack");
    let spec = LabelledSpec {
        texture_grid: 64,
        texture_res: 64,
        elevation_grid: 16,
        elevation_res: 64,
        ..LabelledSpec::default()
    };
    eprintln!("generating a {0}x{0}-tile terrain ({1} px tiles)...", spec.texture_grid, spec.texture_res);
    write_labelled_archive(&p, &spec)?;
    Ok(p)
}

/// The streamer's options for a run: ours (`coalesce`), or the baseline, which fetches
/// the way PMTiles-style readers in a browser do: one request per tile, directories on
/// demand (and cached), at most 6 at once (a browser's connections per host over
/// HTTP/1.1).
fn stream_options(args: &StreamBench, coalesce: bool) -> StreamOptions {
    StreamOptions {
        coalesce,
        coalesce_gap: args.coalesce_gap,
        max_request_bytes: args.max_request_bytes,
        max_in_flight: if coalesce { args.max_in_flight } else { BASELINE_IN_FLIGHT },
        adaptive_in_flight: coalesce && !args.fixed_in_flight,
        prefetch_ahead: if args.no_prefetch || !coalesce {
            Duration::ZERO
        } else {
            StreamOptions::default().prefetch_ahead
        },
        select: SelectOptions::default(),
        ..StreamOptions::default()
    }
}

/// A line per run.
fn print_runs(runs: &[Run]) {
    println!(
        "{:<40} {:>10} {:>10} {:>10} {:>9} {:>9} {:>12} {:>12} {:>8} {:>8} {:>10} {:>6} {:>11}",
        "run",
        "1st frame",
        "ttd med",
        "ttd max",
        "req/tile",
        "tiles",
        "fetched B",
        "needed B",
        "up max",
        "up p99",
        "B/frm max",
        "limit",
        "hole frames"
    );
    for r in runs {
        let mut ups = r.uploads_per_frame.clone();
        ups.sort_unstable();
        let p99 = ups.get(ups.len() * 99 / 100).copied().unwrap_or(0);
        println!(
            "{:<40} {:>8.1}ms {:>8.1}ms {:>8.1}ms {:>9.3} {:>9} {:>12} {:>12} {:>8} {:>8} {:>10} {:>6} {:>11}",
            r.name,
            r.first_frame.as_secs_f64() * 1e3,
            r.median_ttd().as_secs_f64() * 1e3,
            r.time_to_detail.iter().max().copied().unwrap_or_default().as_secs_f64() * 1e3,
            r.requests_per_tile(),
            r.stats.tiles_fetched,
            r.stats.bytes_fetched,
            r.stats.bytes_needed,
            ups.last().copied().unwrap_or(0),
            p99,
            r.bytes_per_frame.iter().max().copied().unwrap_or(0),
            r.stats.in_flight_limit,
            format!("{}/{}", r.frames_with_hole, r.frames_shown),
        );
    }
}

/// The ratios against mmap and the baseline (runs: mmap, its baseline, HTTP, its
/// baseline, then each link and its baseline).
fn print_ratios(runs: &[Run], budget: UploadBudget) {
    let [mmap, mmap_raw, http, http_raw, ..] = runs else { return };
    println!();
    println!(
        "time to full detail, HTTP / mmap (median over jumps): {:.2}x  (target <= 1.3x)",
        http.median_ttd().as_secs_f64() / mmap.median_ttd().as_secs_f64().max(1e-9)
    );
    println!(
        "requests per tile, ours / the baseline: HTTP {:.2}x, mmap {:.2}x  (target <= 0.5x)",
        http.requests_per_tile() / http_raw.requests_per_tile().max(1e-9),
        mmap.requests_per_tile() / mmap_raw.requests_per_tile().max(1e-9)
    );
    println!(
        "bytes fetched / needed (HTTP, coalesced): {:.2}x",
        http.stats.bytes_fetched as f64 / http.stats.bytes_needed.max(1) as f64
    );
    let over = runs.iter().any(|r| {
        r.uploads_per_frame.iter().any(|&n| n > budget.max_tiles)
            || r.bytes_per_frame.iter().any(|&b| b > budget.max_bytes)
    });
    println!("upload budget exceeded in any frame: {}", if over { "YES" } else { "no" });
    for pair in runs[4..].chunks(2) {
        if let [linked, raw] = pair {
            println!(
                "{}: first complete frame {:.0} ms; time to full detail {:.2}x mmap's, {:.2}x the baseline's; {:.2} requests per tile; \
                 frames with a hole after the first complete one: {} of {}",
                linked.name,
                linked.first_frame.as_secs_f64() * 1e3,
                linked.median_ttd().as_secs_f64() / mmap.median_ttd().as_secs_f64().max(1e-9),
                linked.median_ttd().as_secs_f64() / raw.median_ttd().as_secs_f64().max(1e-9),
                linked.requests_per_tile(),
                linked.frames_with_hole,
                linked.frames_shown,
            );
        }
    }
}

/// Does the view have a hole: a wanted tile in view that neither it nor any coarser tile
/// over it covers (the renderer draws a tile's nearest delivered ancestor), where the
/// origin has data?
fn has_hole(s: &Streamer) -> bool {
    s.wanted().iter().filter(|w| w.leaf && w.in_view).any(|w| {
        let covered = std::iter::successors(Some(w.key), |k| k.parent()).any(|k| s.is_delivered(k));
        let sparse = s.is_missing(w.key) || w.key.parent().is_some_and(|p| s.is_missing(p));
        !covered && !sparse
    })
}

/// Camera stops across the terrain's extent: (x, z) fractions and a look direction.
const STOPS: [(f64, f64, f64, f64); 5] = [
    (0.1, 0.1, 1.0, 1.0),
    (0.8, 0.3, -1.0, 0.6),
    (0.3, 0.85, 0.7, -1.0),
    (0.9, 0.9, -1.0, -1.0),
    (0.5, 0.45, 0.2, 1.0),
];

fn camera_at(meta: &Metadata, (fx, fz, dx, dz): (f64, f64, f64, f64), viewport_height: u32) -> Camera {
    let layer = &meta.layers[0];
    let world = layer.tile_world_size * f64::from(layer.num_x_tiles.max(layer.num_y_tiles));
    let ground = meta.terrain.max_elevation;
    let eye = glam::DVec3::new(fx * world, ground + world * 0.01, fz * world);
    let target = eye + glam::DVec3::new(dx * world * 0.1, -world * 0.01, dz * world * 0.1);
    let width = viewport_height * 16 / 9;
    Camera::look_at(eye, target, width, viewport_height)
}

fn fly(name: String, origin: Origin, options: StreamOptions, budget: UploadBudget, args: &StreamBench) -> Result<Run> {
    let opened = Instant::now();
    let mut streamer = Streamer::open(origin, options)?;
    let meta = streamer.metadata().context("metadata")?.clone();
    let mut run = Run {
        name,
        first_frame: Duration::ZERO,
        time_to_detail: Vec::new(),
        uploads_per_frame: Vec::new(),
        bytes_per_frame: Vec::new(),
        frames_shown: 0,
        frames_with_hole: 0,
        stats: StreamStats::default(),
    };
    let frame = |s: &mut Streamer, cam: &Camera, run: &mut Run| {
        s.update(cam);
        let uploads = s.drain_uploads(budget);
        run.uploads_per_frame.push(uploads.len());
        run.bytes_per_frame.push(uploads.iter().map(|u| u.tile.byte_len()).sum());
        if !run.time_to_detail.is_empty() {
            run.frames_shown += 1;
            run.frames_with_hole += usize::from(has_hole(s));
        }
    };
    for (i, stop) in STOPS.iter().enumerate() {
        let cam = camera_at(&meta, *stop, args.viewport_height);
        // Jump, then frames (1 ms apart) until every wanted tile is shown.
        let start = Instant::now();
        loop {
            frame(&mut streamer, &cam, &mut run);
            if streamer.pending() == 0 {
                break;
            }
            anyhow::ensure!(start.elapsed() < Duration::from_secs(120), "{}: no full detail after 120 s", run.name);
            std::thread::sleep(Duration::from_millis(1));
        }
        run.time_to_detail.push(start.elapsed());
        if i == 0 {
            run.first_frame = opened.elapsed();
        }
        // Then fly towards the next stop at 60 frames per second, streaming as we go.
        let next = camera_at(&meta, STOPS[(i + 1) % STOPS.len()], args.viewport_height);
        for f in 0..args.flight_frames {
            let t = (f as f64 + 1.0) / (args.flight_frames as f64 + 1.0) * 0.5;
            let cam = Camera {
                position: cam.position.lerp(next.position, t),
                forward: cam.forward.lerp(next.forward, t),
                ..cam
            };
            frame(&mut streamer, &cam, &mut run);
            std::thread::sleep(Duration::from_millis(16));
        }
    }
    run.stats = streamer.stats();
    Ok(run)
}
