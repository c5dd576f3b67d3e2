//! `terrastream render` (headless PNG) and the options it shares with `terrastream view`.

use std::path::PathBuf;
use std::process::ExitCode;
use std::time::Duration;

use anyhow::{Context, Result, bail};
use clap::{Args, ValueEnum};
use glam::DVec3;
use terrastream_client::fly::{Pose, start_camera};
use terrastream_client::render::gpu::Gpu;
use terrastream_client::render::renderer::{RenderSettings, Shading};
use terrastream_client::render::still::{Still, StillOptions, render_still, write_png};
use terrastream_client::{Camera, Origin, StreamOptions, UploadBudget};

/// Renderer and streaming settings shared by `render` and `view`.
#[derive(Debug, Args)]
pub struct LookArgs {
    /// Shading: lit (textured or height-tinted, sunlit, hazy) or flat (white, for coverage checks).
    #[arg(long, value_enum, default_value_t = ShadingArg::Lit)]
    shading: ShadingArg,
    /// Overlay the mesh's edges.
    #[arg(long)]
    wireframe: bool,
    /// Tint each mesh level.
    #[arg(long)]
    lod_colours: bool,
    /// Detail texture strength (0 = off).
    #[arg(long, default_value_t = 0.0)]
    detail: f32,
    /// Quads per mesh patch edge.
    #[arg(long, default_value_t = 32)]
    patch: u32,
    /// GPU slots per layer (texture-array layers).
    #[arg(long, default_value_t = 512)]
    gpu_tiles: u32,
    /// Most tile requests in flight.
    #[arg(long, default_value_t = 8)]
    max_in_flight: usize,
    /// Most tiles uploaded to the GPU per frame.
    #[arg(long, default_value_t = 8)]
    max_upload_tiles: usize,
    /// Most bytes uploaded to the GPU per frame.
    #[arg(long, default_value_t = 4 * 1024 * 1024)]
    max_upload_bytes: usize,
    /// Decoded-tile cache budget in MiB.
    #[arg(long, default_value_t = 512)]
    cache_mib: usize,
    /// Draw the archive as a flat plate, even one that says where it lies (else it is
    /// drawn on the WGS 84 ellipsoid).
    #[arg(long)]
    flat: bool,
    /// On the globe: a plain haze instead of the physically based sky and aerial perspective.
    #[arg(long)]
    no_atmosphere: bool,
    /// On the globe: plain ground on the sphere beyond the archive's data instead of the
    /// built-in whole-Earth picture (continents, oceans, ice) on its heights.
    #[arg(long)]
    no_earth: bool,
    /// The sun: "AZIMUTH,ELEVATION" in degrees (clockwise from north; above the horizon)
    /// at the view's anchor.
    #[arg(long, value_parser = terrastream_client::globe::parse_sun, allow_hyphen_values = true)]
    sun: Option<DVec3>,
}

#[derive(Clone, Copy, Debug, ValueEnum)]
enum ShadingArg {
    Lit,
    Flat,
}

impl LookArgs {
    pub fn settings(&self) -> RenderSettings {
        RenderSettings {
            elevation_slots: self.gpu_tiles,
            texture_slots: self.gpu_tiles,
            patch: self.patch,
            shading: match self.shading {
                ShadingArg::Lit => Shading::Lit,
                ShadingArg::Flat => Shading::Flat,
            },
            wireframe: self.wireframe,
            lod_colours: self.lod_colours,
            detail: self.detail,
            flat: self.flat,
            atmosphere: !self.no_atmosphere,
            earth: !self.no_earth,
            sun: self.sun.unwrap_or(RenderSettings::default().sun),
            ..RenderSettings::default()
        }
    }

    pub fn stream(&self) -> StreamOptions {
        StreamOptions {
            max_in_flight: self.max_in_flight.max(1),
            cache_bytes: self.cache_mib * 1024 * 1024,
            ..StreamOptions::default()
        }
    }

    pub fn budget(&self) -> UploadBudget {
        UploadBudget { max_tiles: self.max_upload_tiles.max(1), max_bytes: self.max_upload_bytes }
    }
}

#[derive(Debug, Args)]
pub struct RenderArgs {
    /// The archive: a path, an http(s):// URL of a .tspack, or a server's tile endpoint URL.
    archive: String,
    /// Eye and target in world units on the flat plate: "ex,ey,ez,tx,ty,tz" (x east, y up,
    /// z south; implies --flat). Default: an oblique view from the south framing the data.
    #[arg(long)]
    camera: Option<String>,
    /// The eye in geographic terms, as CesiumJS places cameras: "LON,LAT,HEIGHT" (degrees,
    /// metres), looking along --heading and --pitch (an archive that says where it lies).
    #[arg(long, conflicts_with = "camera", allow_hyphen_values = true)]
    at: Option<String>,
    /// With --at: degrees clockwise from north.
    #[arg(long, default_value_t = 0.0, allow_hyphen_values = true)]
    heading: f64,
    /// With --at: degrees from the horizontal, negative looking down.
    #[arg(long, default_value_t = -30.0, allow_hyphen_values = true)]
    pitch: f64,
    /// Vertical field of view in degrees.
    #[arg(long, default_value_t = 60.0)]
    fov: f64,
    /// Image size, WxH.
    #[arg(long, default_value = "1280x720")]
    size: String,
    /// Output PNG.
    #[arg(short, long)]
    output: PathBuf,
    /// Render the first frame that has data (and, on the globe, the whole-Earth picture)
    /// instead of waiting for the full view.
    #[arg(long)]
    no_wait: bool,
    /// Seconds to wait for the full view.
    #[arg(long, default_value_t = 120)]
    timeout: u64,
    #[command(flatten)]
    look: LookArgs,
}

/// "WxH".
pub fn parse_size(s: &str) -> Result<(u32, u32)> {
    let (w, h) = s.split_once(['x', 'X']).with_context(|| format!("size {s:?}: expected WxH"))?;
    let (w, h): (u32, u32) = (w.trim().parse()?, h.trim().parse()?);
    if !(1..=16384).contains(&w) || !(1..=16384).contains(&h) {
        bail!("size {s:?}: each side must be 1..=16384");
    }
    Ok((w, h))
}

/// "ex,ey,ez,tx,ty,tz" -> eye, target.
pub fn parse_camera(s: &str) -> Result<(DVec3, DVec3)> {
    let v: Vec<f64> = s
        .split(',')
        .map(|p| p.trim().parse::<f64>())
        .collect::<Result<_, _>>()
        .with_context(|| format!("camera {s:?}: expected six numbers ex,ey,ez,tx,ty,tz"))?;
    if v.len() != 6 || v.iter().any(|x| !x.is_finite()) {
        bail!("camera {s:?}: expected six finite numbers ex,ey,ez,tx,ty,tz");
    }
    let (eye, target) = (DVec3::new(v[0], v[1], v[2]), DVec3::new(v[3], v[4], v[5]));
    if eye.distance(target) < 1e-9 {
        bail!("camera {s:?}: eye and target coincide");
    }
    Ok((eye, target))
}

pub fn run(args: RenderArgs) -> Result<ExitCode> {
    let (width, height) = parse_size(&args.size)?;
    let camera = args.camera.as_deref().map(parse_camera).transpose()?;
    let pose = args
        .at
        .as_deref()
        .map(|at| Pose::parse(at, args.heading, args.pitch))
        .transpose()
        .map_err(anyhow::Error::msg)?;
    let origin = Origin::parse(&args.archive).with_context(|| format!("opening {}", args.archive))?;
    let gpu =
        Gpu::headless().context("rendering needs a graphics adapter (a software one will do: Mesa's lavapipe)")?;
    tracing::info!(adapter = %gpu.describe(), "rendering");
    let mut settings = args.look.settings();
    settings.flat |= camera.is_some();
    let options = StillOptions {
        width,
        height,
        settings,
        stream: args.look.stream(),
        budget: args.look.budget(),
        wait: !args.no_wait,
        timeout: Duration::from_secs(args.timeout),
    };
    let fov = args.fov.clamp(1.0, 170.0).to_radians();
    let make_camera = |metadata: &terrastream_format::Metadata, surface: &terrastream_client::Surface| {
        let asked = match pose {
            Some(pose) => Some(pose.eye_target(metadata, surface)?),
            None => camera,
        };
        let start = start_camera(metadata, surface, asked, width, height);
        Ok(if asked.is_some() { Camera { fov_y: fov, ..start } } else { start })
    };
    let started = std::time::Instant::now();
    let still =
        render_still(&gpu, origin, make_camera, &options).with_context(|| format!("rendering {}", args.archive))?;
    write_png(&args.output, still.width, still.height, &still.rgba)
        .with_context(|| format!("writing {}", args.output.display()))?;
    Ok(report(&still, &args.output, started, &gpu.describe()))
}

/// What a render drew, on standard output; FAILURE when the picture is not of the
/// terrain (tiles in view but nothing drawn, or a layer in view that cannot be reached).
fn report(still: &Still, output: &std::path::Path, started: std::time::Instant, adapter: &str) -> ExitCode {
    if still.stream.undecodable > 0 {
        tracing::warn!(
            "{} tiles could not be decoded and were drawn from coarser ones (last: {})",
            still.stream.undecodable,
            still.last_error.as_deref().unwrap_or("?")
        );
    }
    let p = still.camera.position;
    println!(
        "wrote {} ({}x{}) in {:.2} s on {}: {} frames, {} tiles fetched in {} requests, {} patches, {} triangles, mesh levels {}..={}, eye {:.1},{:.1},{:.1}",
        output.display(),
        still.width,
        still.height,
        started.elapsed().as_secs_f64(),
        adapter,
        still.frames,
        still.stream.tiles_fetched,
        still.stream.requests,
        still.frame.patches,
        still.frame.triangles,
        still.frame.levels.0,
        still.frame.levels.1,
        p.x,
        p.y,
        p.z
    );
    if still.frame.drew_nothing_in_view() {
        eprintln!(
            "error: {} tiles in view were on the GPU but no terrain was drawn: {} shows only sky",
            still.frame.in_view_resident,
            output.display()
        );
        return ExitCode::FAILURE;
    }
    if let Some(layer) = &still.unreached_layer {
        eprintln!(
            "error: layer {layer:?} has data in view but none of its tiles in view could be fetched (the view cannot \
             reach them): {} does not show it",
            output.display()
        );
        return ExitCode::FAILURE;
    }
    ExitCode::SUCCESS
}
