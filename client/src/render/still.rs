//! Headless stills: stream a view until it is complete, render it offscreen, read it back.

use std::fmt;
use std::time::Duration;

use glam::DVec3;
use terrastream_packer::{LayerKind, Metadata};
use web_time::Instant;

use super::gpu::{Gpu, GpuError, OFFSCREEN_FORMAT, Offscreen, render_pass};
use super::renderer::{FrameStats, RenderSettings};
use super::session::Session;
use crate::stream::camera::Camera;
use crate::stream::origin::Origin;
use crate::stream::streamer::{StreamOptions, StreamStats, Streamer, UploadBudget};

/// Why a still could not be made.
#[derive(Debug)]
pub enum StillError {
    /// No GPU.
    Gpu(GpuError),
    /// The archive could not be opened or read.
    Archive(terrastream_packer::Error),
    /// The view was not complete in time (`--no-wait` renders what is there).
    Timeout {
        /// Tiles still pending.
        pending: usize,
        /// The streamer's last error, if any.
        last_error: Option<String>,
    },
}

impl fmt::Display for StillError {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        match self {
            Self::Gpu(e) => write!(f, "{e}"),
            Self::Archive(e) => write!(f, "{e}"),
            Self::Timeout { pending, last_error } => {
                write!(f, "the view was not fully streamed in time: {pending} tiles pending")?;
                if let Some(e) = last_error {
                    write!(f, " (last error: {e})")?;
                }
                Ok(())
            }
        }
    }
}

impl std::error::Error for StillError {}

impl From<GpuError> for StillError {
    fn from(e: GpuError) -> Self {
        Self::Gpu(e)
    }
}

impl From<terrastream_packer::Error> for StillError {
    fn from(e: terrastream_packer::Error) -> Self {
        Self::Archive(e)
    }
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
}

/// The terrain's extent (x, z) in world units and its height range.
pub fn terrain_bounds(metadata: &Metadata) -> ((f64, f64), (f64, f64)) {
    let layer = metadata
        .layers
        .iter()
        .find(|l| l.kind == LayerKind::Elevation)
        .or_else(|| metadata.layers.iter().find(|l| l.kind == LayerKind::Texture))
        .or(metadata.layers.first());
    let extent = layer.map_or((1.0, 1.0), |l| {
        (f64::from(l.num_x_tiles) * l.tile_world_size, f64::from(l.num_y_tiles) * l.tile_world_size)
    });
    let t = &metadata.terrain;
    (extent, (t.min_elevation.min(t.max_elevation), t.max_elevation.max(t.min_elevation)))
}

/// An oblique view from the south framing the whole dataset.
pub fn default_camera(metadata: &Metadata, width: u32, height: u32) -> Camera {
    let ((ex, ez), (lo, hi)) = terrain_bounds(metadata);
    let centre = DVec3::new(ex / 2.0, (lo + hi) / 2.0, ez / 2.0);
    let distance = ex.max(ez) * 1.1;
    let pitch = 40f64.to_radians();
    let eye = centre + DVec3::new(0.0, distance * pitch.sin(), distance * pitch.cos());
    Camera::look_at(eye, centre, width, height)
}

/// Streams `origin` for `camera` (default: [`default_camera`]) and renders one still.
///
/// # Errors
/// When the archive cannot be opened, there is no GPU, or the view does not complete
/// within `options.timeout` while `options.wait` is set.
pub fn render_still(
    gpu: &Gpu,
    origin: Origin,
    camera: Option<&dyn Fn(&Metadata) -> Camera>,
    options: &StillOptions,
) -> Result<Still, StillError> {
    let streamer = Streamer::open(origin, options.stream.clone())?;
    let metadata = streamer
        .metadata()
        .cloned()
        .ok_or_else(|| terrastream_packer::Error::InvalidTile { what: "the archive opened without metadata".into() })?;
    let camera = camera.map_or_else(|| default_camera(&metadata, options.width, options.height), |f| f(&metadata));
    let mut session = Session::new(streamer, &gpu.device, options.settings, OFFSCREEN_FORMAT, options.budget)?;
    let start = Instant::now();
    let mut frames = 0u32;
    let (stream, frame) = loop {
        let (stream, frame) = session.frame(&gpu.device, &gpu.queue, &camera);
        gpu.queue.submit([]);
        frames += 1;
        let has_data = session.renderer.stats().resident.0 + session.renderer.stats().resident.1 > 0;
        if (options.wait && session.settled()) || (!options.wait && has_data) {
            break (stream, frame);
        }
        if start.elapsed() > options.timeout {
            return Err(StillError::Timeout {
                pending: session.streamer.pending(),
                last_error: session.streamer.last_error().map(str::to_owned),
            });
        }
        std::thread::sleep(Duration::from_millis(1));
    };
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
    Ok(Still { rgba, width: options.width, height: options.height, frames, stream, frame, camera })
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
