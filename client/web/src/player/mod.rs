//! The player: the page's canvas, a fly camera driven by keyboard, mouse and touch, the
//! streaming session stepped once per animation frame, a HUD and a loading indicator.
//!
//! The page (`static/player.html`) has a `<canvas id="terrain">`, a `<pre id="hud">` and
//! a `<div id="status">`, and calls [`run`]. URL parameters:
//! - `archive`: URL of a `.tspack` or of a manifest `.json` (relative to the page); without it, the page's
//!   `<meta name="terrastream-archive">` (what `terrastream serve` fills in at `/view/{name}`);
//! - `camera=ex,ey,ez,tx,ty,tz`: start there (default: the whole dataset from the south);
//! - `at=LON,LAT,HEIGHT`, `heading=DEG`, `pitch=DEG`: start there in geographic terms
//!   (CesiumJS's conventions: heading clockwise from north, pitch negative looking down);
//! - `backend=webgpu|webgl2`: only that one (default: WebGPU if the browser has it, else WebGL2);
//! - `hud=0`: start with the HUD hidden (H toggles it);
//! - `flight=N`: 4 s after the first view is complete, fly the benchmarks' path of N frames
//!   twice (tiles stream in during the first pass, are resident during the second) and
//!   report the frame times of each (`flight_*` in the stats); then fly on as usual.

use std::cell::RefCell;
use std::collections::HashMap;
use std::rc::Rc;
use std::sync::Arc;
use std::sync::atomic::Ordering::Relaxed;

use glam::DVec3;
use terrastream_client::fly::{bench_flight, start_camera};
use terrastream_client::input::CONTROLS;
use terrastream_client::render::gpu::{Gpu, depth_target, next_frame, render_pass};
use terrastream_client::render::hud::{FrameTimes, Status, status_lines};
use terrastream_client::render::renderer::{FrameStats, RenderSettings, TerrainPipeline};
use terrastream_client::render::session::Session;
use terrastream_client::render::wgpu;
use terrastream_client::{
    Camera, FlyCamera, FlyInput, HttpSource, HttpStats, Keys, ManifestSource, Origin, StreamOptions, StreamStats,
    Streamer, UploadBudget,
};
use wasm_bindgen::JsCast;
use wasm_bindgen::prelude::*;
use web_sys::{Document, HtmlCanvasElement, HtmlElement, KeyboardEvent, PointerEvent, WheelEvent, Window};

/// GPU slots per layer: 256 is WebGL2's guaranteed texture-array depth.
const GPU_SLOTS: u32 = 256;
/// HUD refreshes per second.
const HUD_HZ: f64 = 4.0;

mod flight;
mod input;
mod page;
mod stats;
mod surface;

use flight::*;
use input::*;
use page::*;
use surface::*;

/// Where the player is: opening the archive, showing it, or stopped with the reason on
/// the page.
enum Phase {
    /// Until the archive's metadata is in.
    Opening(Box<Streamer>),
    /// Streaming, drawing and flying.
    Running { session: Box<Session>, fly: FlyCamera },
    /// The archive opened but cannot be shown.
    Failed,
}

struct State {
    page: Page,
    params: Params,
    gpu: Gpu,
    surface: Surface,
    /// The terrain pipeline, made at start.
    pipeline: TerrainPipeline,
    /// The Web Workers decoding tiles, if they started.
    workers: Option<Rc<crate::workers::Pool>>,
    phase: Phase,
    http: Arc<HttpStats>,
    input: Input,
    show_hud: bool,
    frame_times: FrameTimes,
    started_ms: f64,
    last_frame_ms: f64,
    hud_at_ms: f64,
    uploads_seen: u64,
    uploads_last_frame: u64,
    timings: Timings,
    last: Option<(StreamStats, FrameStats)>,
    /// The benchmark flight, once started.
    flight: Option<Flight>,
}

impl State {
    fn frame(&mut self, now: f64) {
        let interval_ms = (now - self.last_frame_ms).max(0.0);
        let dt = (interval_ms / 1000.0).min(0.25);
        self.last_frame_ms = now;
        self.frame_times.push(dt);
        let size = self.page.canvas_size(self.gpu.device.limits().max_texture_dimension_2d);
        if size != (self.surface.config.width, self.surface.config.height) {
            self.surface.configure(&self.gpu.device, size);
        }
        if !matches!(self.phase, Phase::Running { .. }) && !self.open_session() {
            return;
        }
        let Some((camera, flying)) = self.steer(dt, now, size) else { return };
        let Phase::Running { session, .. } = &mut self.phase else { return };
        let cpu_started = self.page.now_ms();
        let (stream, frame) = session.frame(&self.gpu.device, &self.gpu.queue, &camera);
        let present_started = self.page.now_ms();
        self.uploads_last_frame = stream.uploads - self.uploads_seen;
        self.uploads_seen = stream.uploads;
        self.timings.max_uploads_per_frame = self.timings.max_uploads_per_frame.max(self.uploads_last_frame);
        self.timings.frames += 1;
        self.present();
        if self.timings.first_draw.is_none() && frame.resident.0 + frame.resident.1 > 0 {
            let now = self.page.now_ms();
            self.timings.first_draw = Some((present_started - cpu_started, now - present_started));
        }
        if frame.resident.0 + frame.resident.1 > 0 && self.timings.first_frame_at.is_none() {
            self.timings.first_frame_at = Some(now);
            tracing::info!("first frame with terrain after {:.0} ms", now - self.started_ms);
        }
        self.record(now, interval_ms, stream.in_flight, flying);
        self.last = Some((stream, frame));
        if now - self.hud_at_ms >= 1000.0 / HUD_HZ {
            self.hud_at_ms = now;
            self.update_hud(&camera);
        }
    }

    /// Moves the camera by the input and, from the first complete view on, by the
    /// benchmark flight: the frame's camera, and whether the flight steered it.
    fn steer(&mut self, dt: f64, now: f64, size: (u32, u32)) -> Option<(Camera, bool)> {
        let Phase::Running { session, fly } = &mut self.phase else { return None };
        let mut input = self.input.keys.fly();
        if self.input.pinch_seconds != 0.0 {
            // A pinch moves along the view as far as that many seconds of flight would.
            fly.step(
                self.input.pinch_seconds.abs(),
                FlyInput { forward: self.input.pinch_seconds.signum(), ..input },
                |p| session.ground(p),
            );
            self.input.pinch_seconds = 0.0;
            input = FlyInput::default();
        }
        fly.step(dt, input, |p| session.ground(p));
        let flying = match &mut self.flight {
            Some(flight) => flight.next(),
            None if self.timings.settled_at.is_some_and(|at| now - at >= FLIGHT_AFTER_MS) => {
                self.params.flight.and_then(|frames| {
                    let metadata = session.streamer.metadata()?;
                    let surface = session.renderer.surface();
                    let path = bench_flight(metadata, frames)
                        .into_iter()
                        .map(|(eye, target)| (surface.place(eye), surface.place(target)))
                        .collect();
                    let mut flight = Flight { path, pass: 0, at: 0, streaming_ms: Vec::new(), resident_ms: Vec::new() };
                    let first = flight.next();
                    self.flight = Some(flight);
                    first
                })
            }
            None => None,
        };
        if let Some((eye, target)) = flying {
            let mut camera = Camera::look_at(eye, target, size.0, size.1);
            camera.zenith = session.renderer.surface().up(eye);
            *fly = FlyCamera { speed: fly.speed, ..FlyCamera::from_camera(&camera) };
        }
        Some((fly.camera(size.0, size.1), flying.is_some()))
    }

    /// The frame's timings, kept apart while tiles stream and once they are resident (for
    /// the first view, and for the benchmark flight), and the status line.
    fn record(&mut self, now: f64, interval_ms: f64, in_flight: u64, flying: bool) {
        let Phase::Running { session, .. } = &self.phase else { return };
        let pending = session.streamer.pending();
        let streaming = pending > 0 || in_flight > 0;
        if streaming {
            self.timings.max_frame_ms_streaming = self.timings.max_frame_ms_streaming.max(interval_ms);
        }
        // The first view's frames, until a benchmark flight starts.
        let kept = if streaming { &mut self.timings.streaming_ms } else { &mut self.timings.resident_ms };
        if kept.len() < MAX_FRAME_SAMPLES && self.flight.is_none() {
            kept.push(interval_ms);
        }
        if let (Some(flight), true) = (&mut self.flight, flying) {
            let kept = if streaming { &mut flight.streaming_ms } else { &mut flight.resident_ms };
            kept.push(interval_ms);
        }
        if session.settled() && self.timings.settled_at.is_none() {
            self.timings.settled_at = Some(now);
            tracing::info!("view fully streamed after {:.0} ms", now - self.started_ms);
        }
        if pending > 0 {
            self.page.status(Some(&format!("Loading terrain… {pending} tiles to go")), false);
        } else {
            self.page.status(None, false);
        }
    }

    /// Steps the opening streamer; once the archive is open, makes the session. False
    /// while there is nothing to draw yet.
    fn open_session(&mut self) -> bool {
        let (width, height) = (self.surface.config.width, self.surface.config.height);
        let Phase::Opening(streamer) = &mut self.phase else { return false };
        streamer.update(&Camera::look_at(DVec3::ONE, DVec3::ZERO, width, height));
        let Some(metadata) = streamer.metadata().cloned() else {
            match streamer.last_error() {
                Some(e) => self
                    .page
                    .status(Some(&format!("Cannot open the archive {}:\n{e}\n(retrying)", self.params.archive)), true),
                None => self.page.status(Some(&format!("Opening {}…", self.params.archive)), false),
            }
            self.present();
            return false;
        };
        let Phase::Opening(streamer) = std::mem::replace(&mut self.phase, Phase::Failed) else { return false };
        let settings = RenderSettings {
            elevation_slots: GPU_SLOTS,
            texture_slots: GPU_SLOTS,
            flat: self.params.flat,
            atmosphere: self.params.atmosphere,
            earth: self.params.earth,
            sun: self.params.sun.unwrap_or(RenderSettings::default().sun),
            ..RenderSettings::default()
        };
        let started = self.page.now_ms();
        let made =
            Session::with_pipeline(*streamer, &self.gpu.device, settings, &self.pipeline, UploadBudget::default());
        self.timings.session_ms = Some(self.page.now_ms() - started);
        match made {
            Ok(session) => {
                let surface = session.renderer.surface().clone();
                let start = match self.params.pose.map(|pose| pose.eye_target(&metadata, &surface)) {
                    Some(Ok(start)) => Some(start),
                    Some(Err(why)) => {
                        tracing::error!("at=: {why}; starting from the default view");
                        None
                    }
                    None => self.params.camera,
                };
                let camera = start_camera(&metadata, &surface, start, width, height);
                self.phase = Phase::Running { session: Box::new(session), fly: FlyCamera::from_camera(&camera) };
                tracing::info!(archive = %self.params.archive, "opened: {} layers", metadata.layers.len());
                true
            }
            Err(e) => {
                self.page.status(Some(&format!("Cannot show {}: {e}", self.params.archive)), true);
                false
            }
        }
    }

    /// Draws the terrain (or the sky alone before the archive opens) and shows it.
    fn present(&mut self) {
        let Some(texture) = next_frame(&self.surface.surface, &self.gpu.device, &self.surface.config) else {
            return;
        };
        let view = texture.texture.create_view(&wgpu::TextureViewDescriptor {
            format: Some(self.surface.view_format),
            ..wgpu::TextureViewDescriptor::default()
        });
        let renderer = match &self.phase {
            Phase::Running { session, .. } => Some(&session.renderer),
            Phase::Opening(_) | Phase::Failed => None,
        };
        let sky = renderer.map_or_else(|| RenderSettings::default().clear_colour(), |r| r.settings().clear_colour());
        render_pass(&self.gpu.device, &self.gpu.queue, &view, &self.surface.depth, sky, |pass| {
            if let Some(renderer) = renderer {
                renderer.draw(pass);
            }
        });
        self.gpu.queue.present(texture);
    }

    /// "WebGPU" or "WebGL2", and the adapter's name where the browser tells it.
    fn backend(&self) -> String {
        let api = if self.gpu.info.backend == wgpu::Backend::Gl { "WebGL2" } else { "WebGPU" };
        if self.gpu.info.name.is_empty() { api.to_owned() } else { format!("{api} on {}", self.gpu.info.name) }
    }

    fn update_hud(&self, camera: &Camera) {
        let Some(hud) = &self.page.hud else { return };
        hud.set_hidden(!self.show_hud);
        let (Phase::Running { session, fly }, Some((stream, frame))) = (&self.phase, &self.last) else { return };
        if !self.show_hud {
            return;
        }
        let mut lines = status_lines(&Status {
            times: &self.frame_times,
            api: &self.backend(),
            stream,
            pending: session.streamer.pending(),
            frame,
            uploads: self.uploads_last_frame,
            budget: session.budget,
            received: (self.http.bytes.load(Relaxed), self.http.requests.load(Relaxed)),
            eye: camera.position,
            globe: session.renderer.surface().globe().is_some(),
            speed: fly.speed,
        });
        lines.push(format!("{CONTROLS}  pinch move"));
        hud.set_text_content(Some(&lines.join("\n")));
    }
}

/// The running player, as the page sees it (`window.terrastream`).
#[wasm_bindgen]
pub struct Player {
    state: Rc<RefCell<State>>,
}

#[wasm_bindgen]
impl Player {
    /// Counters as JSON: timings, HTTP requests and bytes, tiles fetched, uploads, what
    /// is resident, whether the view is fully streamed, the last error.
    pub fn stats(&self) -> String {
        self.state.borrow().stats()
    }
}

/// Starts the player on the page: reads the URL's parameters, opens a WebGPU or WebGL2
/// device on `#terrain`, starts streaming, and draws every animation frame. On failure
/// the message is shown on the page and returned.
#[wasm_bindgen]
pub async fn run() -> Result<Player, JsValue> {
    crate::log::init();
    let page = Page::find().map_err(|e| JsValue::from_str(&e))?;
    std::panic::set_hook(Box::new(|info| {
        let text = format!("The player stopped: {info}");
        web_sys::console::error_1(&JsValue::from_str(&text));
        if let Ok(page) = Page::find() {
            page.status(Some(&text), true);
        }
    }));
    match start(page).await {
        Ok(player) => Ok(player),
        Err((page, message)) => {
            tracing::error!("{message}");
            if let Some(page) = page {
                page.status(Some(&message), true);
            }
            Err(JsValue::from_str(&message))
        }
    }
}

async fn start(page: Page) -> Result<Player, (Option<Page>, String)> {
    let started_ms = page.now_ms();
    let params = match params(&page.window) {
        Ok(p) => p,
        Err(e) => return Err((Some(page), e)),
    };
    page.status(Some("Starting the graphics device…"), false);
    let (gpu, surface) = match open_gpu(&page, params.backends).await {
        Ok(v) => v,
        Err(e) => return Err((Some(page), e)),
    };
    tracing::info!(adapter = %gpu.describe(), "webplayer");
    // A manifest (`….json`) streams its archives as one terrain.
    let opened = if terrastream_client::is_manifest_location(&params.archive) {
        ManifestSource::new(&params.archive).map(|s| (s.shared_stats(), Origin::Manifest(Arc::new(s))))
    } else {
        HttpSource::new(&params.archive).map(|s| (s.shared_stats(), Origin::archive(s)))
    };
    let (http, origin) = match opened {
        Ok(v) => v,
        Err(e) => return Err((Some(page), format!("Cannot read {}: {e}", params.archive))),
    };
    let options = StreamOptions { cache_bytes: 256 * 1024 * 1024, ..StreamOptions::default() };
    let mut streamer = match Streamer::new(origin, options) {
        Ok(s) => s,
        Err(e) => return Err((Some(page), format!("Cannot stream {}: {e}", params.archive))),
    };
    // Decoding in Web Workers, off the page's thread.
    #[expect(clippy::cast_possible_truncation, clippy::cast_sign_loss, reason = "a small core count")]
    let cores = page.window.navigator().hardware_concurrency() as usize;
    let count = params.workers.unwrap_or_else(|| cores.saturating_sub(1).clamp(1, 4));
    let workers = if count == 0 {
        None
    } else {
        match crate::workers::Pool::start(count) {
            Ok(pool) => {
                streamer.set_decoder(Some(pool.decoder()));
                // The globe's whole-Earth picture, decoded while the archive opens.
                if !params.flat && params.atmosphere && params.earth {
                    pool.decode_earth();
                }
                Some(pool)
            }
            Err(e) => {
                tracing::warn!("no decoding workers ({e:?}): decoding on the page's thread");
                None
            }
        }
    };
    let show_hud = params.hud;
    // Made now, while the archive opens: the shaders are compiled by the time the first
    // tiles arrive, not in the first frame that draws them.
    let pipeline = TerrainPipeline::new(&gpu.device, surface.view_format);
    let state = Rc::new(RefCell::new(State {
        page,
        params,
        gpu,
        surface,
        pipeline,
        workers,
        phase: Phase::Opening(Box::new(streamer)),
        http,
        input: Input::default(),
        show_hud,
        frame_times: FrameTimes::default(),
        started_ms,
        last_frame_ms: started_ms,
        hud_at_ms: f64::NEG_INFINITY,
        uploads_seen: 0,
        uploads_last_frame: 0,
        timings: Timings::default(),
        last: None,
        flight: None,
    }));
    listen(&state);
    animate(state.clone());
    Ok(Player { state })
}

/// A device on WebGPU (when allowed and the browser has it) or else WebGL2, and the
/// canvas configured for it.
async fn open_gpu(page: &Page, backends: wgpu::Backends) -> Result<(Gpu, Surface), String> {
    let mut tried = Vec::new();
    for backend in [wgpu::Backends::BROWSER_WEBGPU, wgpu::Backends::GL].into_iter().filter(|b| backends.contains(*b)) {
        let name = if backend == wgpu::Backends::GL { "WebGL2" } else { "WebGPU" };
        // WebGPU must be known to work before an instance is made for it: the choice of
        // backend is made at instance creation.
        if backend == wgpu::Backends::BROWSER_WEBGPU && !wgpu::util::is_browser_webgpu_supported().await {
            tried.push(format!("{name}: not in this browser"));
            continue;
        }
        let mut desc = wgpu::InstanceDescriptor::new_without_display_handle();
        desc.backends = backend;
        let instance = wgpu::Instance::new(desc);
        let surface = match instance.create_surface(wgpu::SurfaceTarget::Canvas(page.canvas.clone())) {
            Ok(s) => s,
            Err(e) => {
                tried.push(format!("{name}: {e}"));
                continue;
            }
        };
        let gpu = match Gpu::new(&instance, Some(&surface)).await {
            Ok(g) => g,
            Err(e) => {
                tried.push(format!("{name}: {e}"));
                continue;
            }
        };
        let (width, height) = page.canvas_size(gpu.device.limits().max_texture_dimension_2d);
        let Some(mut config) = surface.get_default_config(&gpu.adapter, width, height) else {
            tried.push(format!("{name}: the canvas does not fit the adapter"));
            continue;
        };
        let view_format = config.format.add_srgb_suffix();
        if view_format != config.format {
            config.view_formats.push(view_format);
        }
        surface.configure(&gpu.device, &config);
        let depth = depth_view(&gpu.device, (width, height));
        return Ok((gpu, Surface { surface, config, view_format, depth }));
    }
    Err(format!(
        "This browser cannot draw the terrain: it needs WebGPU or WebGL2 ({}). \
         Try a current Chrome, Edge, Firefox or Safari, with hardware acceleration on.",
        tried.join("; ")
    ))
}

/// Steps a frame on every animation frame, for as long as the page lives.
fn animate(state: Rc<RefCell<State>>) {
    type Callback = Closure<dyn FnMut(f64)>;
    let slot: Rc<RefCell<Option<Callback>>> = Rc::new(RefCell::new(None));
    let again = slot.clone();
    let window = state.borrow().page.window.clone();
    *slot.borrow_mut() = Some(Closure::wrap(Box::new(move |now: f64| {
        state.borrow_mut().frame(now);
        if let Some(callback) = again.borrow().as_ref() {
            let window = state.borrow().page.window.clone();
            let _ = window.request_animation_frame(callback.as_ref().unchecked_ref());
        }
    }) as Box<dyn FnMut(f64)>));
    if let Some(callback) = slot.borrow().as_ref() {
        let _ = window.request_animation_frame(callback.as_ref().unchecked_ref());
    }
}
