//! `terrastream bench render`: frame times along a scripted flight, with streaming active
//! versus with every tile already resident, on whatever adapter is present.

use std::path::PathBuf;
use std::time::{Duration, Instant};

use anyhow::{Context, Result};
use clap::Args;
use terrastream_client::fly::bench_flight;
use terrastream_client::render::gpu::{Gpu, OFFSCREEN_FORMAT, Offscreen, render_pass};
use terrastream_client::render::renderer::{RenderSettings, Shading};
use terrastream_client::render::session::Session;
use terrastream_client::render::wgpu;
use terrastream_client::{Camera, Origin, StreamOptions, Streamer, UploadBudget};

use super::CliProgress;

#[derive(Debug, Args)]
pub struct RenderBench {
    /// Archive to fly over (path or URL); default: the built-in SRTM crop.
    #[arg(long)]
    archive: Option<String>,
    /// Frames along the flight.
    #[arg(long, default_value_t = 240)]
    frames: usize,
    /// Frame size, WxH.
    #[arg(long, default_value = "640x360")]
    size: String,
    /// Most tiles uploaded per frame.
    #[arg(long, default_value_t = 8)]
    max_upload_tiles: usize,
    /// Working folder (a temporary one by default).
    #[arg(long)]
    dir: Option<PathBuf>,
}

/// [`bench_flight`] as cameras of `w` x `h`.
fn flight(metadata: &terrastream_format::Metadata, frames: usize, w: u32, h: u32) -> Vec<Camera> {
    bench_flight(metadata, frames).into_iter().map(|(eye, target)| Camera::look_at(eye, target, w, h)).collect()
}

struct Run {
    frame_ms: Vec<f64>,
    vertices: Vec<u64>,
    draw_calls: Vec<u32>,
    uploads_max: u64,
}

/// Flies `cameras`, timing each whole frame (stream update, uploads, draw, GPU finish).
fn fly(gpu: &Gpu, session: &mut Session, cameras: &[Camera], target: &Offscreen) -> Result<Run> {
    let mut runs = fly_in_turn(gpu, &mut [session], cameras, target)?;
    Ok(runs.remove(0))
}

/// Flies `cameras` with each of `sessions` in turn, a frame of each at every camera: two
/// ways of drawing compared frame by frame, under the same spells of a shared machine.
fn fly_in_turn(gpu: &Gpu, sessions: &mut [&mut Session], cameras: &[Camera], target: &Offscreen) -> Result<Vec<Run>> {
    let (colour, depth) = (target.colour_view(), target.depth_view());
    let mut runs: Vec<Run> = (sessions.iter())
        .map(|_| Run { frame_ms: Vec::new(), vertices: Vec::new(), draw_calls: Vec::new(), uploads_max: 0 })
        .collect();
    // Each session's uploads before its last frame.
    let mut uploads: Vec<u64> = sessions.iter().map(|s| s.streamer.stats().uploads).collect();
    for camera in cameras {
        for ((session, run), uploads) in sessions.iter_mut().zip(&mut runs).zip(&mut uploads) {
            let start = Instant::now();
            let (stream, frame) = session.frame(&gpu.device, &gpu.queue, camera);
            render_pass(&gpu.device, &gpu.queue, &colour, &depth, session.renderer.settings().clear_colour(), |pass| {
                session.renderer.draw(pass);
            });
            gpu.device.poll(wgpu::PollType::wait_indefinitely()).context("waiting for the GPU")?;
            run.frame_ms.push(start.elapsed().as_secs_f64() * 1e3);
            run.vertices.push(frame.vertices);
            run.draw_calls.push(frame.draw_calls);
            run.uploads_max = run.uploads_max.max(stream.uploads - *uploads);
            *uploads = stream.uploads;
        }
    }
    Ok(runs)
}

fn percentile(sorted: &[f64], p: f64) -> f64 {
    #[allow(clippy::cast_possible_truncation, clippy::cast_sign_loss)]
    let i = ((sorted.len() as f64 - 1.0) * p).round() as usize;
    sorted.get(i).copied().unwrap_or(f64::NAN)
}

/// What every run of the benchmark shares: the adapter, the archive, the frame.
struct Bench<'a> {
    gpu: &'a Gpu,
    location: &'a str,
    budget: UploadBudget,
    target: Offscreen,
    size: (u32, u32),
}

impl Bench<'_> {
    fn open(&self, settings: RenderSettings) -> Result<Session> {
        let streamer = Streamer::open(Origin::parse(self.location)?, StreamOptions::default())?;
        Ok(Session::new(streamer, &self.gpu.device, settings, OFFSCREEN_FORMAT, self.budget)?)
    }

    /// A session that has streamed every view of `cameras` to completion.
    fn settled(&self, settings: RenderSettings, cameras: &[Camera]) -> Result<Session> {
        let mut session = self.open(settings)?;
        for camera in cameras {
            session.run_until(&self.gpu.device, &self.gpu.queue, camera, Duration::from_secs(30), Session::settled);
        }
        Ok(session)
    }

    fn fly(&self, session: &mut Session, cameras: &[Camera]) -> Result<Run> {
        fly(self.gpu, session, cameras, &self.target)
    }
}

/// Median and p99 frame times, printed with the run's geometry and uploads.
fn stats(name: &str, r: &Run) -> (f64, f64) {
    let mut sorted = r.frame_ms.clone();
    sorted.sort_by(f64::total_cmp);
    let (p50, p99, max) = (percentile(&sorted, 0.5), percentile(&sorted, 0.99), percentile(&sorted, 1.0));
    let mean_vertices = r.vertices.iter().sum::<u64>() as f64 / r.vertices.len().max(1) as f64;
    println!(
        "  {name:<10} frame ms median {p50:7.2}  p99 {p99:7.2}  max {max:7.2} | vertices/frame mean {mean_vertices:8.0} max {:7} | draw calls/frame max {} | uploads/frame max {}",
        r.vertices.iter().max().unwrap_or(&0),
        r.draw_calls.iter().max().unwrap_or(&0),
        r.uploads_max
    );
    (p50, p99)
}

pub fn run(args: RenderBench, progress: &CliProgress) -> Result<()> {
    let (w, h) = super::render::parse_size(&args.size)?;
    let dir = match &args.dir {
        Some(d) => {
            std::fs::create_dir_all(d)?;
            tempfile::TempDir::new_in(d)?
        }
        None => tempfile::tempdir()?,
    };
    let location = match &args.archive {
        Some(a) => a.clone(),
        None => {
            let path = dir.path().join("tamalpais.tspack");
            super::demo::tile_builtin_dem(dir.path(), &path, progress)?;
            path.display().to_string()
        }
    };
    let gpu = Gpu::headless().context("the render benchmark needs a graphics adapter")?;
    let budget = UploadBudget { max_tiles: args.max_upload_tiles.max(1), ..UploadBudget::default() };
    let bench =
        Bench { gpu: &gpu, location: &location, budget, target: Offscreen::new(&gpu.device, w, h), size: (w, h) };
    let plate = RenderSettings { flat: true, ..RenderSettings::default() };
    let mut streaming = bench.open(plate)?;
    let metadata = streaming.streamer.metadata().cloned().context("no metadata")?;
    let cameras = flight(&metadata, args.frames, w, h);
    println!("bench render: {location}, {} frames of {w}x{h} on {}", cameras.len(), gpu.describe());
    // Warm-up outside the timings: pipelines compiled, caches of the driver filled.
    bench.fly(&mut bench.open(plate)?, &cameras[..cameras.len().min(5)])?;
    // Streaming: a fresh session; tiles arrive while it flies.
    let streamed = bench.fly(&mut streaming, &cameras)?;
    // Resident: a session that has already streamed every view of the flight to completion.
    let mut resident = bench.settled(plate, &cameras)?;
    let before = resident.streamer.stats();
    let settled = bench.fly(&mut resident, &cameras)?;
    let after = resident.streamer.stats();
    println!(
        "  resident run fetched {} tiles during the flight (0 = everything was resident)",
        after.tiles_fetched - before.tiles_fetched
    );
    let (s50, s99) = stats("streaming", &streamed);
    let flat = stats("resident", &settled);
    println!(
        "  streaming / resident: median {:.2}x, p99 {:.2}x (target: p99 within 1.25x)",
        s50 / flat.0,
        s99 / flat.1
    );
    let floor = baseline(&bench, plate, &cameras, "baseline", flat)?;
    // The plate's sessions end here: their streamers' threads must not share the
    // machine with the globe's runs (on a software rasterizer they are its cores).
    drop((streaming, resident));
    on_the_globe(&bench, &metadata, &cameras, (flat, floor), before.tiles_fetched)
}

/// The same flight, resident, drawn with one texel read a pixel and nothing else (the
/// same mesh and cameras: the floor of this mesh at this size), and the lit frame's
/// ratio to it.
fn baseline(
    bench: &Bench<'_>,
    settings: RenderSettings,
    cameras: &[Camera],
    name: &str,
    (l50, l99): (f64, f64),
) -> Result<(f64, f64)> {
    let floor = RenderSettings { shading: Shading::Baseline, ..settings };
    let mut session = bench.settled(floor, cameras)?;
    let run = bench.fly(&mut session, cameras)?;
    let (b50, b99) = stats(name, &run);
    println!("  lit / {name}: median {:.2}x, p99 {:.2}x (target: 1.5x)", l50 / b50, l99 / b99);
    Ok((b50, b99))
}

/// The same views on the globe (a georeferenced archive): each eye and target placed on
/// the ellipsoid at its grid point and height; without the atmosphere first (the plate
/// has none), then with it: its share; then the descent from orbit.
fn on_the_globe(
    bench: &Bench<'_>,
    metadata: &terrastream_format::Metadata,
    cameras: &[Camera],
    ((r50, r99), plate_floor): ((f64, f64), (f64, f64)),
    flat_fetched: u64,
) -> Result<()> {
    let (w, h) = bench.size;
    let mut globe = bench.open(RenderSettings { atmosphere: false, ..RenderSettings::default() })?;
    let surface = globe.renderer.surface().clone();
    if surface.globe().is_none() {
        println!("  globe: the archive does not say where it lies");
        return Ok(());
    }
    let on_globe: Vec<Camera> = cameras
        .iter()
        .map(|c| {
            let eye = surface.place(c.position);
            let mut camera = Camera::look_at(eye, surface.place(c.position + c.direction() * 100.0), w, h);
            camera.zenith = surface.up(eye);
            camera
        })
        .collect();
    // Warm-up outside the timings, as for the plate: the globe's and the sky's pipelines
    // drawn once (a first draw can compile them inside whichever row comes first).
    for atmosphere in [false, true] {
        let warm = &on_globe[..on_globe.len().min(5)];
        bench.fly(&mut bench.open(RenderSettings { atmosphere, ..RenderSettings::default() })?, warm)?;
    }
    for camera in &on_globe {
        globe.run_until(&bench.gpu.device, &bench.gpu.queue, camera, Duration::from_secs(30), Session::settled);
    }
    let globe_fetched = globe.streamer.stats().tiles_fetched;
    let on_the_globe = bench.fly(&mut globe, &on_globe)?;
    let (g50, g99) = stats("globe", &on_the_globe);
    println!(
        "  globe / flat (resident): median {:.2}x, p99 {:.2}x (target: 1.1x); tiles fetched to settle the flight {} / {} = {:.2}x",
        g50 / r50,
        g99 / r99,
        globe_fetched,
        flat_fetched,
        globe_fetched as f64 / flat_fetched.max(1) as f64
    );
    let bare = RenderSettings { atmosphere: false, ..RenderSettings::default() };
    let (f50, f99) = baseline(bench, bare, &on_globe, "globe baseline", (g50, g99))?;
    println!("  globe baseline / plate baseline: median {:.2}x, p99 {:.2}x", f50 / plate_floor.0, f99 / plate_floor.1);
    // With and without the atmosphere a frame of each in turn: flown one after the
    // other, this machine's spells move a whole run by more than the atmosphere costs.
    let mut air = bench.settled(RenderSettings::default(), &on_globe)?;
    let mut runs = fly_in_turn(bench.gpu, &mut [&mut globe, &mut air], &on_globe, &bench.target)?.into_iter();
    let (without, with_air) = (runs.next().context("the globe's run")?, runs.next().context("the atmosphere's run")?);
    let (a50, a99) = stats("atmosphere", &with_air);
    let (w50, _) = stats("globe, in turn", &without);
    println!(
        "  the atmosphere's share of the globe's frame (median, frames in turn): {:.0} % ({a50:.2} ms with it, {w50:.2} ms \
         without; target: 10 %); with it / globe baseline: median {:.2}x, p99 {:.2}x",
        (a50 - w50) / a50 * 100.0,
        a50 / f50,
        a99 / f99
    );
    fly_descent(bench, &descent(metadata, &surface, w, h))
}

/// From 20 000 km down to 2 m above the terrain's highest point over the data's middle,
/// and back: every frame must draw terrain (a NaN anywhere drops its triangles).
fn fly_descent(bench: &Bench<'_>, descent: &[Camera]) -> Result<()> {
    let gpu = bench.gpu;
    let target = &bench.target;
    let mut down = bench.open(RenderSettings::default())?;
    let mut bare = 0;
    let mut frame_ms = Vec::new();
    for camera in descent {
        let start = Instant::now();
        let settled = down.run_until(&gpu.device, &gpu.queue, camera, Duration::from_secs(30), Session::settled);
        let Some((_, frame, _)) = settled else {
            anyhow::bail!("the descent's view at {:?} never settled", camera.position)
        };
        render_pass(&gpu.device, &gpu.queue, &target.colour_view(), &target.depth_view(), wgpu::Color::BLACK, |pass| {
            down.renderer.draw(pass);
        });
        gpu.device.poll(wgpu::PollType::wait_indefinitely()).context("waiting for the GPU")?;
        frame_ms.push(start.elapsed().as_secs_f64() * 1e3);
        bare += usize::from(frame.patches == 0);
    }
    frame_ms.sort_by(f64::total_cmp);
    println!(
        "  descent from 20 000 km to 2 m and back: {} frames, {bare} without terrain; settled frame ms median {:.1}, max {:.1}",
        descent.len(),
        percentile(&frame_ms, 0.5),
        percentile(&frame_ms, 1.0)
    );
    Ok(())
}

/// Cameras straight down from 20 000 km to 2 m above the highest height over the data's
/// middle (log-spaced), then back up, looking ever more level near the ground.
fn descent(
    metadata: &terrastream_format::Metadata,
    surface: &terrastream_client::Surface,
    w: u32,
    h: u32,
) -> Vec<Camera> {
    let ([x0, z0, x1, z1], (_, hi)) = terrastream_client::fly::terrain_bounds(metadata);
    let (x, z) = ((x0 + x1) * 0.5, (z0 + z1) * 0.5);
    let steps = 24;
    let down: Vec<Camera> = (0..steps)
        .map(|i| {
            let t = f64::from(i) / f64::from(steps - 1);
            let above = 2.0e7 * (2.0 / 2.0e7_f64).powf(t);
            let eye = surface.place(glam::DVec3::new(x, hi + above, z));
            // Straight down from orbit, 20 degrees below the horizon at the end.
            let pitch = (-90.0 + 70.0 * t).to_radians();
            let up = surface.up(eye);
            let north = (glam::DVec3::Z - up * up.z).try_normalize().unwrap_or(glam::DVec3::X);
            let direction = north * pitch.cos() + up * pitch.sin();
            let mut camera = Camera::look_at(eye, eye + direction * 100.0, w, h);
            camera.zenith = up;
            camera
        })
        .collect();
    down.iter().chain(down.iter().rev()).copied().collect()
}
