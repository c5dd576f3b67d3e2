//! `terrastream demo`: the README's first command.

use std::path::PathBuf;
use std::process::ExitCode;

use anyhow::{Context, Result};
use clap::Args;
use terrastream_format::{ArchiveStats, verify};
use terrastream_pack::WriterOptions;
use terrastream_pack::import::{OriginalLayout, pack, scan_original};
use terrastream_pack::sample::write_sample_pyramid;

use super::CliProgress;

#[derive(Debug, Args)]
pub struct DemoArgs {
    /// Working folder for the sample pyramid and its archive.
    #[arg(long, default_value = "target/terrastream-demo")]
    dir: PathBuf,
    /// Where to serve the sample (port 0: any free port).
    #[arg(long, default_value = "127.0.0.1:0")]
    addr: std::net::SocketAddr,
    /// Keep serving after the demo, until Ctrl-C.
    #[arg(long)]
    keep_serving: bool,
    /// Render PNG views even when a display is available (instead of opening the viewer).
    #[arg(long)]
    no_window: bool,
}

/// The built-in real terrain: SRTM 1" around Mt Tamalpais (public domain), 320 x 320 samples.
use terrastream_pack::sample::TAMALPAIS_TIF;

/// One HTTP/1.1 GET over a plain socket: (status line, headers, body).
fn fetch(addr: std::net::SocketAddr, path: &str, extra: &str) -> Result<(String, String, Vec<u8>)> {
    use std::io::{Read, Write};
    let mut s = std::net::TcpStream::connect(addr)?;
    write!(s, "GET {path} HTTP/1.1\r\nHost: {addr}\r\n{extra}Connection: close\r\n\r\n")?;
    let mut answer = Vec::new();
    s.read_to_end(&mut answer)?;
    let end = answer.windows(4).position(|w| w == b"\r\n\r\n").context("malformed HTTP answer")?;
    let head = String::from_utf8_lossy(&answer[..end]).into_owned();
    let (status, headers) = head.split_once("\r\n").unwrap_or((&head, ""));
    Ok((status.to_owned(), headers.to_owned(), answer[end + 4..].to_vec()))
}

/// Serves the archive on a loopback port and shows a client's first requests.
fn serve_and_show(args: &DemoArgs) -> Result<()> {
    use terrastream_server::{AppState, ServerConfig, serve};
    let runtime = tokio::runtime::Builder::new_multi_thread().worker_threads(2).enable_all().build()?;
    runtime.block_on(async {
        let config = ServerConfig {
            paths: vec![args.dir.join("sample.tspack"), args.dir.join("tamalpais.tspack")],
            ..ServerConfig::default()
        };
        let state = AppState::new(config);
        state.catalog.reload();
        let listener =
            tokio::net::TcpListener::bind(args.addr).await.with_context(|| format!("binding {}", args.addr))?;
        let addr = listener.local_addr()?;
        let (stop, stopped) = tokio::sync::oneshot::channel::<()>();
        let server = tokio::spawn(serve(listener, state, async {
            let _ = stopped.await;
        }));
        println!("\nserving http://{addr}/sample.tspack");
        if terrastream_server::player::available() {
            println!(
                "webplayer: http://{addr}/view/tamalpais and http://{addr}/view/sample \
                 (open in a browser; --keep-serving keeps them up)"
            );
        } else {
            println!("webplayer: not in this build (scripts/build-player.sh, then rebuild)");
        }
        let shown = tokio::task::spawn_blocking(move || -> Result<()> {
            for (what, path, extra) in [
                ("bootstrap (first 16 KiB)", "/sample.tspack", "Range: bytes=0-16383\r\n"),
                ("metadata", "/sample/metadata", ""),
                ("coarsest texture tile", "/sample/texture/3/0/0", ""),
                ("missing lake tile", "/sample/texture/0/1/4", ""),
            ] {
                let (status, headers, body) = fetch(addr, path, extra)?;
                let pick = |name: &str| {
                    headers.lines().find_map(|l| {
                        l.split_once(':')
                            .filter(|(k, _)| k.eq_ignore_ascii_case(name))
                            .map(|(_, v)| v.trim().to_owned())
                    })
                };
                let detail = [
                    pick("content-range"),
                    pick("content-type"),
                    pick(terrastream_format::protocol::FALLBACK_LOD_HEADER).map(|l| format!("use LOD {l}")),
                ]
                .into_iter()
                .flatten()
                .collect::<Vec<_>>()
                .join(", ");
                println!("  GET {path:<28} {status:<28} {:>7} bytes  {detail}   ({what})", body.len());
            }
            Ok(())
        })
        .await?;
        shown?;
        let base = format!("http://{addr}");
        tokio::task::spawn_blocking({
            let dir = args.dir.clone();
            let no_window = args.no_window;
            move || look(&base, &dir, no_window)
        })
        .await??;
        if args.keep_serving {
            println!("serving until Ctrl-C: http://{addr}/");
            let _ = tokio::signal::ctrl_c().await;
        }
        let _ = stop.send(());
        server.await??;
        anyhow::Ok(())
    })
}

/// Opens the viewer on the served DEM when there is a display, else renders PNG views
/// of both served archives over HTTP.
fn look(base: &str, dir: &std::path::Path, no_window: bool) -> Result<()> {
    use terrastream_client::Origin;
    use terrastream_client::fly::start_camera;
    use terrastream_client::render::gpu::Gpu;
    use terrastream_client::render::renderer::RenderSettings;
    use terrastream_client::render::still::{StillOptions, render_still, write_png};
    let url = format!("{base}/tamalpais.tspack");
    let display = ["DISPLAY", "WAYLAND_DISPLAY"].iter().any(|v| std::env::var_os(v).is_some_and(|s| !s.is_empty()));
    if display && !no_window {
        println!("\nopening the viewer on {url} (WASD/QE fly, drag to look, Esc quits)");
        // The viewer's event loop must own the main thread on some platforms; here the
        // server runs on the runtime's workers, so a window opened from this thread works
        // on X11 and Wayland.
        return super::view::run_url(&url);
    }
    let gpu = Gpu::headless().context("rendering the demo views needs a graphics adapter (Mesa's lavapipe will do)")?;
    let out = dir.join("views");
    std::fs::create_dir_all(&out).with_context(|| format!("creating {}", out.display()))?;
    println!("\nrendering over HTTP on {} (no display: PNG views instead of the viewer)", gpu.describe());
    let (w, h) = (960, 540);
    // A descent on the globe from the whole Earth to the summit (LON,LAT,HEIGHT above the
    // ellipsoid, heading, pitch), then the sample pyramid, which does not say where it lies.
    // LON,LAT,HEIGHT, heading, pitch.
    type At<'a> = Option<(&'a str, f64, f64)>;
    let views: [(&str, String, At<'_>); 5] = [
        ("earth", url.clone(), Some(("-122.6,37.9,20000000", 0.0, -90.0))),
        ("tamalpais-whole", url.clone(), Some(("-122.60,37.80,9000", 0.0, -38.0))),
        ("tamalpais-grazing", url.clone(), Some(("-122.665,37.875,1100", 50.0, -9.0))),
        ("tamalpais-summit", url.clone(), Some(("-122.590,37.922,900", 225.0, -14.0))),
        ("sample-whole", format!("{base}/sample.tspack"), None),
    ];
    for (name, location, at) in views {
        let started = std::time::Instant::now();
        let pose = at.map(|(at, heading, pitch)| terrastream_client::fly::Pose::parse(at, heading, pitch)).transpose();
        let pose = pose.map_err(anyhow::Error::msg)?;
        let camera = |metadata: &terrastream_format::Metadata, surface: &terrastream_client::Surface| {
            let posed = pose.map(|p| p.eye_target(metadata, surface)).transpose()?;
            let start = start_camera(metadata, surface, posed, w, h);
            Ok(terrastream_client::Camera { fov_y: 50f64.to_radians(), ..start })
        };
        let settings = RenderSettings::default();
        let options = StillOptions { width: w, height: h, settings, ..StillOptions::default() };
        let still = render_still(&gpu, Origin::parse(&location)?, camera, &options)
            .with_context(|| format!("rendering {location}"))?;
        let path = out.join(format!("{name}.png"));
        write_png(&path, w, h, &still.rgba).with_context(|| format!("writing {}", path.display()))?;
        println!(
            "  {:<48} {} tiles in {} requests, {} triangles, {:.2} s",
            path.display(),
            still.stream.tiles_fetched,
            still.stream.requests,
            still.frame.triangles,
            started.elapsed().as_secs_f64()
        );
    }
    Ok(())
}

/// Tiles the built-in DEM into `archive` (once), as `terrastream tile` does: onto a
/// transverse Mercator centred on it, its heights named as SRTM's are (above EGM96) where
/// PROJ's EGM96 grid is at hand (else of unknown datum, with the tiler's warning).
pub(super) fn tile_builtin_dem(dir: &std::path::Path, archive: &std::path::Path, progress: &CliProgress) -> Result<()> {
    use terrastream_tiler::raster::DatumName;
    use terrastream_tiler::{Sources, TileOptions, TileRequest, tile_terrain};
    if archive.exists() {
        return Ok(());
    }
    let tif = dir.join("srtm-tamalpais-320-public-domain.tif");
    std::fs::write(&tif, TAMALPAIS_TIF).with_context(|| format!("writing {}", tif.display()))?;
    let egm96 = DatumName::egm96();
    let request = TileRequest {
        elevation: vec![tif],
        vertical_datum: egm96.load().is_ok().then_some(egm96),
        ..TileRequest::default()
    };
    let sources = Sources::open(&request)?;
    let inputs = sources.inputs()?;
    let options = TileOptions { tile_size: 64, border: 1, ..TileOptions::default() };
    tile_terrain(inputs.elevation(), None, "tamalpais", archive, options, progress)?;
    progress.finish();
    println!("tiled the built-in SRTM 1\" DEM (Mt Tamalpais, public domain) into {}", archive.display());
    Ok(())
}

pub fn run(args: DemoArgs, progress: &CliProgress) -> Result<ExitCode> {
    let input = args.dir.join("sample");
    let archive = args.dir.join("sample.tspack");
    if !input.join("metadata.txt").exists() {
        write_sample_pyramid(&input).with_context(|| format!("writing the sample pyramid to {}", input.display()))?;
        println!("wrote the built-in sample pyramid (original LOD-folder layout) to {}", input.display());
    }
    let scanned = scan_original(&input, &OriginalLayout::default())?;
    let summary = pack(scanned, &archive, WriterOptions::default(), progress)?;
    progress.finish();
    println!("packed {} tiles into {} ({} bytes)\n", summary.addressed_tiles, archive.display(), summary.file_len);
    let location = archive.display().to_string();
    let reader = super::open(&location)?;
    print!("{}", super::info::render(&location, &ArchiveStats::collect(&reader)?, reader.metadata()));
    let report = verify(&reader, |_| {})?;
    println!(
        "\nverify: {} ({} tiles, {} blobs checked)",
        if report.is_ok() { "OK" } else { "DAMAGED" },
        report.addressed_tiles,
        report.blobs_checked
    );
    if !report.is_ok() {
        return Ok(ExitCode::FAILURE);
    }
    tile_builtin_dem(&args.dir, &args.dir.join("tamalpais.tspack"), progress)?;
    serve_and_show(&args)?;
    println!(
        "\nnext: terrastream serve {} (or --keep-serving), terrastream extract {} -o <dir>",
        archive.display(),
        archive.display()
    );
    Ok(ExitCode::SUCCESS)
}
