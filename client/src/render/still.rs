//! Headless stills: stream a view until it is complete, render it offscreen, read it back.

use std::time::Duration;

use terrastream_format::Metadata;

use super::gpu::{Gpu, GpuError, OFFSCREEN_FORMAT, Offscreen, render_pass};
use super::renderer::{FrameStats, RenderSettings};
use super::session::Session;
pub use crate::fly::{default_camera, terrain_bounds};
use crate::globe::Surface;
use crate::stream::camera::Camera;
use crate::stream::origin::Origin;
use crate::stream::streamer::{StreamOptions, StreamStats, Streamer, UploadBudget};

/// Why a still could not be made.
#[derive(Debug, thiserror::Error)]
#[non_exhaustive]
pub enum StillError {
    /// No GPU.
    #[error(transparent)]
    Gpu(#[from] GpuError),
    /// The archive could not be opened or read.
    #[error(transparent)]
    Archive(#[from] crate::Error),
    /// The camera asked for has no place in the archive.
    #[error("camera: {0}")]
    Camera(String),
    /// The view was not complete in time (`--no-wait` renders what is there).
    #[error(
        "the view was not fully streamed in time: {pending} tiles pending{}",
        last_error.as_ref().map(|e| format!(" (last error: {e})")).unwrap_or_default()
    )]
    Timeout {
        /// Tiles still pending.
        pending: usize,
        /// The streamer's last error, if any.
        last_error: Option<String>,
    },
}

/// How to make a still.
#[derive(Clone, Debug)]
pub struct StillOptions {
    /// Width in pixels.
    pub width: u32,
    /// Height in pixels.
    pub height: u32,
    /// Renderer settings.
    pub settings: RenderSettings,
    /// Streaming settings.
    pub stream: StreamOptions,
    /// Upload budget per frame.
    pub budget: UploadBudget,
    /// Wait until the view is fully streamed (else render the first frame that has data).
    pub wait: bool,
    /// Longest wait.
    pub timeout: Duration,
}

impl Default for StillOptions {
    fn default() -> Self {
        Self {
            width: 800,
            height: 600,
            settings: RenderSettings::default(),
            stream: StreamOptions::default(),
            budget: UploadBudget::default(),
            wait: true,
            timeout: Duration::from_secs(120),
        }
    }
}

/// A rendered still.
#[derive(Clone, Debug)]
pub struct Still {
    /// RGBA8 pixels, rows top to bottom.
    pub rgba: Vec<u8>,
    /// Width.
    pub width: u32,
    /// Height.
    pub height: u32,
    /// Frames stepped until the view was complete.
    pub frames: u32,
    /// Streaming counters.
    pub stream: StreamStats,
    /// What the last frame drew.
    pub frame: FrameStats,
    /// The camera used.
    pub camera: Camera,
    /// The GPU format texture tiles were drawn from (`None`: no texture layer drawn).
    pub texture_format: Option<wgpu::TextureFormat>,
    /// The streamer's last error (a tile that failed or could not be decoded), if any.
    pub last_error: Option<String>,
    /// The name of a layer whose data is in view but none of whose tiles could be
    /// fetched ([`FrameStats::unreached_layer`]): a view that fails.
    pub unreached_layer: Option<String>,
}

/// Streams `origin` for the camera `camera` makes from the archive's metadata and the
/// surface it is drawn on (e.g. `|m, s| Ok(default_camera(m, s, w, h))`) and renders one
/// still.
///
/// # Errors
/// When the archive cannot be opened, there is no GPU, or the view does not complete
/// within `options.timeout` while `options.wait` is set.
pub fn render_still(
    gpu: &Gpu,
    origin: Origin,
    camera: impl FnOnce(&Metadata, &Surface) -> Result<Camera, String>,
    options: &StillOptions,
) -> Result<Still, StillError> {
    let streamer = Streamer::open(origin, options.stream.clone())?;
    let metadata =
        streamer.metadata().ok_or_else(|| crate::Error::NotOpen { why: streamer.last_error().map(str::to_owned) })?;
    let metadata = metadata.clone();
    let mut session = Session::new(streamer, &gpu.device, options.settings, OFFSCREEN_FORMAT, options.budget)?;
    let surface = session.renderer.surface().clone();
    let camera =
        camera(&metadata, &surface).map_err(StillError::Camera)?.enclosing(&crate::fly::scene_box(&metadata, &surface));
    let wait = options.wait;
    let ready = |s: &Session| {
        let resident = s.renderer.stats().resident;
        if wait { s.settled() } else { resident.0 + resident.1 > 0 && !s.renderer.earth_pending() }
    };
    let (stream, frame, frames) = session
        .run_until(&gpu.device, &gpu.queue, &camera, options.timeout, ready)
        .ok_or_else(|| StillError::Timeout {
            pending: session.streamer.pending(),
            last_error: session.streamer.last_error().map(str::to_owned),
        })?;
    let target = Offscreen::new(&gpu.device, options.width, options.height);
    render_pass(
        &gpu.device,
        &gpu.queue,
        &target.colour_view(),
        &target.depth_view(),
        session.renderer.settings().clear_colour(),
        |pass| session.renderer.draw(pass),
    );
    let rgba = target.read_rgba(&gpu.device, &gpu.queue)?;
    let texture_format = session.renderer.texture_format();
    let last_error = session.streamer.last_error().map(str::to_owned);
    let (width, height) = (options.width, options.height);
    let unreached_layer = frame.unreached_layer.map(|i| session.layer_name(i).to_owned());
    Ok(Still { rgba, width, height, frames, stream, frame, camera, texture_format, last_error, unreached_layer })
}

/// Writes RGBA8 pixels as a PNG.
///
/// # Errors
/// When the file cannot be written.
pub fn write_png(path: &std::path::Path, width: u32, height: u32, rgba: &[u8]) -> std::io::Result<()> {
    let file = std::io::BufWriter::new(std::fs::File::create(path)?);
    let mut encoder = png::Encoder::new(file, width, height);
    encoder.set_color(png::ColorType::Rgba);
    encoder.set_depth(png::BitDepth::Eight);
    let mut writer = encoder.write_header().map_err(std::io::Error::other)?;
    writer.write_image_data(rgba).map_err(std::io::Error::other)?;
    writer.finish().map_err(std::io::Error::other)
}
