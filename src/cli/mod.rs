//! Command-line wiring: argument parsing, progress bars, Ctrl-C, output formatting.

mod bench;
mod bench_mesh;
mod bench_render;
mod bench_stream;
mod demo;
mod export;
mod extract;
mod health;
mod info;
mod key;
mod manifest;
mod merge;
mod pack;
mod people;
mod player;
mod progress;
mod render;
mod serve;
mod tile;
mod update;
mod verify;
mod view;
mod water;

use std::process::ExitCode;

use anyhow::{Context, Result};
use clap::{Parser, Subcommand};
use terrastream_client::{AnySource, open_source};
use terrastream_format::Reader;

pub use progress::CliProgress;

/// Stream very large terrains from one packed, indexed archive.
#[derive(Debug, Parser)]
#[command(name = "terrastream", version, about)]
pub struct Cli {
    /// More log output (-v: debug, -vv: trace).
    #[arg(short, long, global = true, action = clap::ArgAction::Count)]
    pub verbose: u8,
    /// Only errors.
    #[arg(short, long, global = true)]
    pub quiet: bool,
    /// Where stderr is not a terminal (a pod's or a service's log), a progress line every
    /// this many seconds instead of a bar (0: at every step).
    #[arg(long, global = true, default_value_t = 30.0, value_name = "SECONDS")]
    pub log_progress: f64,
    #[command(subcommand)]
    command: Command,
}

#[derive(Debug, Subcommand)]
enum Command {
    /// Pack existing tile pyramids (original LOD folders, XYZ/TMS trees, PMTiles, MBTiles;
    /// one per layer with --elevation and --texture) into one archive.
    Pack(pack::PackArgs),
    /// Describe an archive: layers, grids, tiles per LOD, sizes, dedup (a manifest: its
    /// archives and what each holds).
    Info(info::InfoArgs),
    /// Check an archive's structure and every checksum; non-zero exit if damaged (a
    /// manifest: every archive, each the one named, each tile where it routes).
    Verify(verify::VerifyArgs),
    /// Write an archive's tiles back as files.
    Extract(extract::ExtractArgs),
    /// Export one layer to another tile-archive format (the original folder layout: `extract`).
    Export(export::ExportArgs),
    /// Build a LOD pyramid archive from an elevation raster and/or imagery (GeoTIFF, PNG,
    /// JPEG), read a band of rows at a time.
    Tile(tile::TileArgs),
    /// Serve archives over HTTP: Range requests on the files, tiles, metadata, metrics.
    Serve(serve::ServeArgs),
    /// API keys for private archives: make, list, revoke (a keys file of hashes).
    #[command(subcommand)]
    Key(key::KeyCommand),
    /// Make a signed, expiring token for one archive or path prefix (a link or a CDN URL
    /// that needs no key).
    Sign(key::SignArgs),
    /// Exit 0 if a server answers 200 on its health URL (container health checks; no
    /// shell or curl needed in the image).
    Health(health::HealthArgs),
    /// Fly over an archive (path or URL) in a window: WASD + mouse, HUD.
    View(view::ViewArgs),
    /// Render one view of an archive (path or URL) to a PNG, headless.
    Render(render::RenderArgs),
    /// Write the webplayer's files (page, JS, wasm) into a folder, for any static host or
    /// CDN: open `player.html?archive=<URL of a .tspack>` there.
    Player(player::PlayerArgs),
    /// Merge archives of one grid into one: the shards of a sharded `tile` run (making
    /// the levels above their split LOD), or archives where a later one's tiles win (the
    /// tiles around and above them are made again).
    Merge(merge::MergeArgs),
    /// Tile new rasters over the part of an archive they cover, keeping the rest: the
    /// archive's grid, CRS and height encoding; tiles around and above are made again.
    Update(update::UpdateArgs),
    /// Add a water layer to an archive from a water mask raster (lakes, rivers, the sea):
    /// drawn as water, and served as quantized-mesh's water mask.
    Water(water::WaterArgs),
    /// Pack the built-in sample terrain and show what is in it.
    Demo(demo::DemoArgs),
    /// Benchmarks that print numbers.
    #[command(subcommand)]
    Bench(bench::BenchCommand),
}

/// Makes the folder `path` is to be written in, as a fresh pod's empty volume lacks it.
///
/// # Errors
/// The folder cannot be made.
pub(crate) fn make_parent(path: &std::path::Path) -> Result<()> {
    match path.parent().filter(|p| !p.as_os_str().is_empty()) {
        Some(parent) => std::fs::create_dir_all(parent)
            .with_context(|| format!("{}: cannot make the folder to write it in", path.display())),
        None => Ok(()),
    }
}

/// Logs go to stderr through `tracing`; `RUST_LOG` overrides the flags. Colours only on a
/// terminal (and not with `NO_COLOR` set): a pod's log or a file gets plain text.
pub fn init_logging(verbose: u8, quiet: bool) {
    let level = match (quiet, verbose) {
        (true, _) => "error",
        (false, 0) => "info",
        (false, 1) => "debug",
        _ => "trace",
    };
    let filter = tracing_subscriber::EnvFilter::try_from_default_env()
        .unwrap_or_else(|_| tracing_subscriber::EnvFilter::new(level));
    let colour = std::io::IsTerminal::is_terminal(&std::io::stderr()) && std::env::var_os("NO_COLOR").is_none();
    tracing_subscriber::fmt()
        .with_env_filter(filter)
        .with_writer(std::io::stderr)
        .with_target(false)
        .with_ansi(colour)
        .init();
}

/// Runs a parsed command line.
///
/// # Errors
/// Whatever the command failed with.
pub fn run(cli: Cli) -> Result<ExitCode> {
    // Commands that show progress get the progress bar and its Ctrl-C handler; the server
    // handles Ctrl-C / SIGTERM itself (a graceful drain), and the viewers and health
    // checks show none.
    let progress = || CliProgress::install(cli.quiet, cli.log_progress);
    match cli.command {
        Command::Serve(args) => serve::run(args),
        Command::Key(command) => key::run(command),
        Command::Sign(args) => key::sign(args),
        Command::Info(args) => info::run(args),
        Command::Player(args) => player::run(args),
        Command::Render(args) => render::run(args),
        Command::View(args) => view::run(args),
        Command::Health(args) => health::run(args),
        Command::Pack(args) => pack::run(args, &progress()),
        Command::Verify(args) => verify::run(args, &progress()),
        Command::Extract(args) => extract::run(args, &progress()),
        Command::Export(args) => export::run(args, &progress()),
        Command::Update(args) => update::run(args, &progress()),
        Command::Water(args) => water::run(args, &progress()),
        Command::Merge(args) => merge::run(args, &progress()),
        Command::Demo(args) => demo::run(args, &progress()),
        Command::Tile(args) => tile::run(args, &progress()),
        Command::Bench(cmd) => bench::run(cmd, &progress()),
    }
}

/// `--vertical-datum`'s value.
pub fn parse_datum(s: &str) -> std::result::Result<terrastream_tiler::raster::DatumName, String> {
    terrastream_tiler::raster::DatumName::parse(s)
}

/// Opens an archive: a file (memory-mapped) or an `http(s)://` URL (Range requests).
///
/// # Errors
/// Names the file or URL when it cannot be read or is not a valid archive.
pub fn open(location: &str) -> Result<Reader<AnySource>> {
    // A file error names the file, a URL error the URL: anything else gets the location.
    let context = |e: &terrastream_client::Error| match e {
        terrastream_client::Error::Format(terrastream_format::Error::File { .. })
        | terrastream_client::Error::BadUrl { .. }
        | terrastream_client::Error::Status { .. }
        | terrastream_client::Error::Request { .. } => "cannot open archive".to_owned(),
        _ => format!("cannot open archive {location}"),
    };
    let source = open_source(location).map_err(|e| {
        let context = context(&e);
        anyhow::Error::new(e).context(context)
    })?;
    Reader::new(source).with_context(|| format!("cannot open archive {location}"))
}
