//! `terrastream view`: a window, a fly camera, the terrain streaming in, and a HUD.

use std::process::ExitCode;
use std::sync::Arc;
use std::time::{Duration, Instant};

use anyhow::{Context, Result};
use clap::Args;
use terrastream_client::fly::{Pose, start_camera, terrain_bounds};
use terrastream_client::input::CONTROLS;
use terrastream_client::render::gpu::{Gpu, depth_target, next_frame};
use terrastream_client::render::hud::{FrameTimes, Hud, Status, status_lines};
use terrastream_client::render::session::Session;
use terrastream_client::render::wgpu;
use terrastream_client::{Action, Camera, FlyCamera, Keys, Origin, Streamer};
use winit::application::ApplicationHandler;
use winit::event::{ElementState, MouseButton, MouseScrollDelta, WindowEvent};
use winit::event_loop::{ActiveEventLoop, ControlFlow, EventLoop};
use winit::keyboard::PhysicalKey;
use winit::window::{Window, WindowId};

use super::render::{LookArgs, parse_camera, parse_size};

#[derive(Debug, Args)]
pub struct ViewArgs {
    /// The archive: a path, an http(s):// URL of a .tspack, or a server's tile endpoint URL.
    pub archive: String,
    /// Start at eye and target "ex,ey,ez,tx,ty,tz" (default: the whole dataset from the south).
    #[arg(long)]
    pub camera: Option<String>,
    /// Start at "LON,LAT,HEIGHT" (degrees, metres), looking along --heading and --pitch
    /// (CesiumJS's conventions; an archive that says where it lies).
    #[arg(long, conflicts_with = "camera", allow_hyphen_values = true)]
    pub at: Option<String>,
    /// With --at: degrees clockwise from north.
    #[arg(long, default_value_t = 0.0, allow_hyphen_values = true)]
    pub heading: f64,
    /// With --at: degrees from the horizontal, negative looking down.
    #[arg(long, default_value_t = -30.0, allow_hyphen_values = true)]
    pub pitch: f64,
    /// Window size, WxH.
    #[arg(long, default_value = "1280x720")]
    pub size: String,
    /// Close the window after this many seconds (scripted screenshots, smoke tests).
    #[arg(long)]
    pub exit_after: Option<f64>,
    /// Start with the HUD hidden (H shows it).
    #[arg(long)]
    pub no_hud: bool,
    #[command(flatten)]
    pub look: LookArgs,
}

struct Running {
    window: Arc<Window>,
    surface: wgpu::Surface<'static>,
    config: wgpu::SurfaceConfiguration,
    gpu: Gpu,
    depth: wgpu::TextureView,
    session: Session,
    hud: Hud,
}

struct App {
    args: ViewArgs,
    streamer: Option<Streamer>,
    size: (u32, u32),
    /// The eye and target asked for (world units, on the plate), or a pose.
    start: Option<(glam::DVec3, glam::DVec3)>,
    pose: Option<Pose>,
    fly: FlyCamera,
    running: Option<Running>,
    error: Option<anyhow::Error>,
    keys: Keys,
    dragging: bool,
    cursor: Option<(f64, f64)>,
    show_hud: bool,
    /// The view has been complete once (logged then, for scripts and tests).
    settled_once: bool,
    last_frame: Instant,
    frame_times: FrameTimes,
    uploads_last: u64,
    started: Instant,
}

fn depth_view(device: &wgpu::Device, width: u32, height: u32) -> wgpu::TextureView {
    depth_target(device, "texture.window.depth", width, height).create_view(&wgpu::TextureViewDescriptor::default())
}

impl App {
    fn start(&mut self, event_loop: &ActiveEventLoop) -> Result<()> {
        let attributes = Window::default_attributes()
            .with_title(format!("terrastream — {}", self.args.archive))
            .with_inner_size(winit::dpi::PhysicalSize::new(self.size.0, self.size.1));
        let window = Arc::new(event_loop.create_window(attributes).context("opening a window")?);
        let instance = wgpu::Instance::new(wgpu::InstanceDescriptor::new_with_display_handle_from_env(Box::new(
            event_loop.owned_display_handle(),
        )));
        let surface = instance.create_surface(window.clone()).context("creating a drawing surface")?;
        let gpu = pollster::block_on(Gpu::new(&instance, Some(&surface)))?;
        tracing::info!(adapter = %gpu.describe(), "viewer");
        let size = window.inner_size();
        let mut config = surface
            .get_default_config(&gpu.adapter, size.width.max(1), size.height.max(1))
            .context("the surface does not fit the adapter")?;
        config.present_mode = wgpu::PresentMode::AutoVsync;
        surface.configure(&gpu.device, &config);
        let streamer = self.streamer.take().context("viewer started twice")?;
        // A camera in world units is on the plate.
        let mut settings = self.args.look.settings();
        settings.flat |= self.start.is_some();
        let session = Session::new(streamer, &gpu.device, settings, config.format, self.args.look.budget())?;
        // The start, on the plate or the globe the session draws.
        let metadata = session.streamer.metadata().cloned().context("the archive has no metadata")?;
        let shape = session.renderer.surface();
        let start = match self.pose {
            Some(pose) => Some(pose.eye_target(&metadata, shape).map_err(anyhow::Error::msg)?),
            None => self.start,
        };
        self.fly = FlyCamera::from_camera(&start_camera(&metadata, shape, start, self.size.0, self.size.1));
        let hud = Hud::new(&gpu.device, config.format);
        let depth = depth_view(&gpu.device, config.width, config.height);
        self.running = Some(Running { window, surface, config, gpu, depth, session, hud });
        Ok(())
    }

    fn step(&mut self, dt: f64) {
        let Some(r) = &self.running else { return };
        let session = &r.session;
        self.fly.step(dt, self.keys.fly(), |p| session.ground(p));
    }

    fn redraw(&mut self) -> Result<()> {
        let now = Instant::now();
        let dt = now.duration_since(self.last_frame).as_secs_f64().min(0.25);
        self.last_frame = now;
        self.step(dt);
        let Some(r) = &mut self.running else { return Ok(()) };
        let camera = self.fly.camera(r.config.width, r.config.height);
        let (stream, frame) = r.session.frame(&r.gpu.device, &r.gpu.queue, &camera);
        if !self.settled_once && r.session.settled() {
            self.settled_once = true;
            tracing::info!(
                patches = frame.patches,
                tiles = stream.tiles_fetched,
                "view fully streamed in {:.2} s",
                self.started.elapsed().as_secs_f64()
            );
        }
        self.frame_times.push(dt);
        let uploads = stream.uploads - self.uploads_last;
        self.uploads_last = stream.uploads;
        let Some(surface_texture) = next_frame(&r.surface, &r.gpu.device, &r.config) else { return Ok(()) };
        if self.show_hud {
            let mut lines = status_lines(&Status {
                times: &self.frame_times,
                api: &r.gpu.describe(),
                stream: &stream,
                pending: r.session.streamer.pending(),
                frame: &frame,
                uploads,
                budget: r.session.budget,
                received: (stream.bytes_fetched, stream.requests),
                eye: camera.position,
                globe: r.session.renderer.surface().globe().is_some(),
                speed: self.fly.speed,
            });
            lines.push(format!("{CONTROLS}  Esc quit"));
            let scale = if r.config.width >= 1800 { 2 } else { 1 };
            r.hud.set_text(&r.gpu.queue, &lines, (r.config.width, r.config.height), scale);
        }
        let view = surface_texture.texture.create_view(&wgpu::TextureViewDescriptor::default());
        let show_hud = self.show_hud;
        let (renderer, hud) = (&r.session.renderer, &r.hud);
        terrastream_client::render::gpu::render_pass(
            &r.gpu.device,
            &r.gpu.queue,
            &view,
            &r.depth,
            renderer.settings().clear_colour(),
            |pass| {
                renderer.draw(pass);
                if show_hud {
                    hud.draw(pass);
                }
            },
        );
        r.window.pre_present_notify();
        r.gpu.queue.present(surface_texture);
        Ok(())
    }
}

impl ApplicationHandler for App {
    fn resumed(&mut self, event_loop: &ActiveEventLoop) {
        if self.running.is_none()
            && let Err(e) = self.start(event_loop)
        {
            self.error = Some(e);
            event_loop.exit();
        }
    }

    fn window_event(&mut self, event_loop: &ActiveEventLoop, _: WindowId, event: WindowEvent) {
        match event {
            WindowEvent::CloseRequested => event_loop.exit(),
            WindowEvent::Focused(false) => self.keys.release_all(),
            WindowEvent::Resized(size) => {
                if let Some(r) = &mut self.running {
                    r.config.width = size.width.max(1);
                    r.config.height = size.height.max(1);
                    r.surface.configure(&r.gpu.device, &r.config);
                    r.depth = depth_view(&r.gpu.device, r.config.width, r.config.height);
                }
            }
            WindowEvent::KeyboardInput { event, .. } => {
                let PhysicalKey::Code(code) = event.physical_key else { return };
                // winit's key names are the DOM's `code` names the shared key map uses.
                let name = format!("{code:?}");
                if event.state != ElementState::Pressed {
                    self.keys.release(&name);
                    return;
                }
                match self.keys.press(&name, event.repeat) {
                    Some(Action::Quit) => event_loop.exit(),
                    Some(action) => {
                        if let Some(r) = &mut self.running {
                            let mut s = *r.session.renderer.settings();
                            action.toggle(&mut s, &mut self.show_hud);
                            r.session.renderer.set_view_settings(s);
                        }
                    }
                    None => {}
                }
            }
            WindowEvent::MouseInput { state, button: MouseButton::Left | MouseButton::Right, .. } => {
                self.dragging = state == ElementState::Pressed;
            }
            WindowEvent::CursorMoved { position, .. } => {
                if let (true, Some((x, y))) = (self.dragging, self.cursor) {
                    self.fly.look(position.x - x, position.y - y);
                }
                self.cursor = Some((position.x, position.y));
            }
            WindowEvent::MouseWheel { delta, .. } => {
                let lines = match delta {
                    MouseScrollDelta::LineDelta(_, y) => f64::from(y),
                    MouseScrollDelta::PixelDelta(p) => p.y / 40.0,
                };
                self.fly.scale_speed(lines);
            }
            WindowEvent::RedrawRequested => {
                if let Err(e) = self.redraw() {
                    self.error = Some(e);
                    event_loop.exit();
                }
                if self.args.exit_after.is_some_and(|s| self.started.elapsed() > Duration::from_secs_f64(s)) {
                    event_loop.exit();
                }
                if let Some(r) = &self.running {
                    r.window.request_redraw();
                }
            }
            _ => {}
        }
    }
}

/// The viewer on `url` with default settings (the demo).
pub fn run_url(url: &str) -> Result<()> {
    use clap::Parser;
    #[derive(Parser)]
    struct Wrapper {
        #[command(flatten)]
        view: ViewArgs,
    }
    let wrapper = Wrapper::try_parse_from(["view", url])?;
    run(wrapper.view).map(|_| ())
}

pub fn run(args: ViewArgs) -> Result<ExitCode> {
    let (width, height) = parse_size(&args.size)?;
    let start = args.camera.as_deref().map(parse_camera).transpose()?;
    let pose = args
        .at
        .as_deref()
        .map(|at| Pose::parse(at, args.heading, args.pitch))
        .transpose()
        .map_err(anyhow::Error::msg)?;
    let origin = Origin::parse(&args.archive).with_context(|| format!("opening {}", args.archive))?;
    let streamer = Streamer::open(origin, args.look.stream()).with_context(|| format!("opening {}", args.archive))?;
    let metadata = streamer.metadata().cloned().context("the archive has no metadata")?;
    let ([x0, z0, x1, z1], _) = terrain_bounds(&metadata);
    let (ex, ez) = (x1 - x0, z1 - z0);
    tracing::info!(extent_m = format!("{ex:.0} x {ez:.0}"), "viewing {}", args.archive);
    // Any thread: the demo opens the viewer beside the server's runtime.
    #[cfg(target_os = "linux")]
    let event_loop = {
        use winit::platform::x11::EventLoopBuilderExtX11;
        EventLoop::builder().with_any_thread(true).build()
    };
    #[cfg(not(target_os = "linux"))]
    let event_loop = EventLoop::new();
    let event_loop = event_loop.context("no display to open a window on (try `terrastream render`)")?;
    event_loop.set_control_flow(ControlFlow::Poll);
    let show_hud = !args.no_hud;
    let mut app = App {
        args,
        streamer: Some(streamer),
        size: (width, height),
        start,
        pose,
        // Placed when the window opens, on the surface the session draws.
        fly: FlyCamera::from_camera(&Camera::look_at(glam::DVec3::Y, glam::DVec3::ZERO, width, height)),
        running: None,
        error: None,
        keys: Keys::default(),
        dragging: false,
        cursor: None,
        show_hud,
        settled_once: false,
        last_frame: Instant::now(),
        frame_times: FrameTimes::default(),
        uploads_last: 0,
        started: Instant::now(),
    };
    event_loop.run_app(&mut app).context("window event loop")?;
    match app.error {
        Some(e) => Err(e),
        None => Ok(ExitCode::SUCCESS),
    }
}

#[cfg(test)]
mod tests {
    use winit::keyboard::KeyCode;

    /// The shared key map names keys as the DOM does; winit's names must be the same.
    #[test]
    fn winit_key_names_are_the_dom_codes_the_key_map_uses() {
        let pairs = [
            (KeyCode::KeyW, "KeyW"),
            (KeyCode::ArrowUp, "ArrowUp"),
            (KeyCode::PageDown, "PageDown"),
            (KeyCode::KeyG, "KeyG"),
            (KeyCode::Escape, "Escape"),
        ];
        for (code, dom) in pairs {
            assert_eq!(format!("{code:?}"), dom);
        }
    }
}
