//! Command-line wiring: argument parsing, progress bars, Ctrl-C, output formatting.

mod bench;
mod bench_render;
mod bench_stream;
mod demo;
mod info;
mod manifest;
mod pack;
mod progress;
mod render;
mod serve;
mod tile;
mod view;

use std::path::PathBuf;
use std::process::ExitCode;

use anyhow::{Context, Result};
use clap::{Parser, Subcommand, ValueEnum};
use terrastream_client::{AnySource, open_source};
use terrastream_format::{Reader, verify};
use terrastream_pack::extract::{Layout, extract};

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
    #[command(subcommand)]
    command: Command,
}

#[derive(Debug, Subcommand)]
enum Command {
    /// Pack an existing tile pyramid (original LOD folders or an XYZ/TMS tree) into one archive.
    Pack(pack::PackArgs),
    /// Describe an archive: layers, grids, tiles per LOD, sizes, dedup (a manifest: its
    /// archives and what each holds).
    Info {
        /// The archive or manifest (`.json`): a path or an http(s):// URL.
        archive: String,
        /// Print JSON instead of text.
        #[arg(long)]
        json: bool,
        /// List every tile: layer, lod, x, y, absolute byte offset and length of its blob
        /// (payload + 4-byte checksum), tab-separated.
        #[arg(long, conflicts_with = "json")]
        tiles: bool,
    },
    /// Check an archive's structure and every checksum; non-zero exit if damaged (a
    /// manifest: every archive, each the one named, each tile where it routes).
    Verify {
        /// The archive or manifest (`.json`): a path or an http(s):// URL.
        archive: String,
    },
    /// Write an archive's tiles back as files.
    Extract {
        /// The archive: a path or an http(s):// URL.
        archive: String,
        /// Output folder.
        #[arg(short, long)]
        output: PathBuf,
        /// Folder layout to write.
        #[arg(long, value_enum, default_value_t = LayoutArg::Original)]
        layout: LayoutArg,
    },
    /// Export one layer to another tile-archive format (the original folder layout: `extract`).
    Export {
        /// The archive: a path or an http(s):// URL.
        archive: String,
        /// Layer name (or index).
        #[arg(long)]
        layer: String,
        /// Target format.
        #[arg(long, value_enum)]
        to: ExportFormat,
        /// Output file (written to a temporary name, then renamed).
        #[arg(short, long)]
        output: PathBuf,
    },
    /// Build a LOD pyramid archive from an elevation raster and/or imagery (GeoTIFF, PNG,
    /// JPEG), read a band of rows at a time.
    Tile(tile::TileArgs),
    /// Serve archives over HTTP: Range requests on the files, tiles, metadata, metrics.
    Serve(serve::ServeArgs),
    /// Exit 0 if a server answers 200 on its health URL (container health checks; no
    /// shell or curl needed in the image).
    Health {
        /// The URL to ask (plain http).
        #[arg(default_value = "http://127.0.0.1:8080/healthz")]
        url: String,
        /// Seconds to wait for the answer.
        #[arg(long, default_value_t = 3)]
        timeout: u64,
    },
    /// Fly over an archive (path or URL) in a window: WASD + mouse, HUD.
    View(view::ViewArgs),
    /// Render one view of an archive (path or URL) to a PNG, headless.
    Render(render::RenderArgs),
    /// Write the webplayer's files (page, JS, wasm) into a folder, for any static host or
    /// CDN: open `player.html?archive=<URL of a .tspack>` there.
    Player {
        /// Output folder (created if missing).
        #[arg(short, long)]
        output: PathBuf,
    },
    /// Merge archives of one grid into one: the shards of a sharded `tile` run (making
    /// the levels above their split LOD), or archives where a later one's tiles win (the
    /// tiles around and above them are made again).
    Merge {
        /// Archives, in order: a later one's tile replaces an earlier one's. A folder stands
        /// for the `*.tspack` files in it, by name.
        #[arg(required = true)]
        inputs: Vec<PathBuf>,
        /// Output archive (written to a temporary name, then renamed).
        #[arg(short, long)]
        output: PathBuf,
        /// Tiles several archives hold: `last` (a later archive's tile replaces the
        /// tile), or `pixels` (a later archive's samples with data replace, its nodata
        /// and transparent samples keep the earlier ones).
        #[arg(long, value_enum, default_value_t = PreferArg::Last)]
        prefer: PreferArg,
        /// Publish the shards of a run as they are instead of one archive: the output
        /// gets only the levels above their split LOD, and this manifest names it and
        /// every shard (URLs relative to the manifest; FORMAT.md §9).
        #[arg(long, conflicts_with = "prefer")]
        manifest: Option<PathBuf>,
    },
    /// Tile new rasters over the part of an archive they cover, keeping the rest: the
    /// archive's grid, CRS and height encoding; tiles around and above are made again.
    #[command(group = clap::ArgGroup::new("target").required(true))]
    Update {
        /// The archive to update (a projected CRS: tiled from a mosaic or with --crs).
        base: PathBuf,
        /// New elevation rasters (files, folders, patterns; any CRS).
        #[arg(long, num_args = 1..)]
        elevation: Vec<PathBuf>,
        /// New imagery (GeoTIFFs; any CRS).
        #[arg(long, num_args = 1..)]
        texture: Vec<PathBuf>,
        /// Output archive: a copy of the base, updated.
        #[arg(short, long, group = "target")]
        output: Option<PathBuf>,
        /// Update the base itself: only the changed tiles and the new directories are
        /// written (FORMAT.md §7.1); readers of the old version keep reading it.
        #[arg(long, group = "target")]
        in_place: bool,
        /// Also write a manifest (FORMAT.md §9) naming the updated archive: a manifest names
        /// an archive by its content tag, which every update changes, so publish it again.
        #[arg(long)]
        manifest_out: Option<PathBuf>,
    },
    /// Pack the built-in sample terrain and show what is in it.
    Demo(demo::DemoArgs),
    /// Benchmarks that print numbers.
    #[command(subcommand)]
    Bench(bench::BenchCommand),
}

/// Paths with each folder replaced by the `*.tspack` files in it, sorted by name.
fn archives_in(paths: &[PathBuf]) -> Result<Vec<PathBuf>> {
    let mut out = Vec::new();
    for path in paths {
        if !path.is_dir() {
            out.push(path.clone());
            continue;
        }
        let mut found: Vec<PathBuf> = std::fs::read_dir(path)
            .with_context(|| format!("cannot list {}", path.display()))?
            .filter_map(|e| e.ok().map(|e| e.path()))
            .filter(|p| p.extension().is_some_and(|e| e == "tspack") && p.is_file())
            .collect();
        anyhow::ensure!(!found.is_empty(), "{}: no .tspack archives in this folder", path.display());
        found.sort();
        out.extend(found);
    }
    Ok(out)
}

/// `terrastream player -o DIR`.
fn write_player(output: &std::path::Path) -> Result<ExitCode> {
    use terrastream_server::player;
    anyhow::ensure!(
        player::available(),
        "this terrastream binary was built without the webplayer: run scripts/build-player.sh, then rebuild"
    );
    std::fs::create_dir_all(output).with_context(|| format!("creating {}", output.display()))?;
    for (name, bytes) in player::files() {
        let path = output.join(name);
        // Written beside, then renamed: a host never serves half a file.
        let partial = output.join(format!(".{name}.partial"));
        std::fs::write(&partial, bytes).with_context(|| format!("writing {}", partial.display()))?;
        std::fs::rename(&partial, &path).with_context(|| format!("writing {}", path.display()))?;
        println!("{}  {} bytes", path.display(), bytes.len());
    }
    println!("open <host>/player.html?archive=<URL of a .tspack> (CORS needed when the archive is on another host)");
    Ok(ExitCode::SUCCESS)
}

#[derive(Clone, Copy, Debug, PartialEq, Eq, ValueEnum)]
enum PreferArg {
    /// A later archive's tile replaces the tile.
    Last,
    /// A later archive's samples with data replace, per sample (LOD 0).
    Pixels,
}

#[derive(Clone, Copy, Debug, ValueEnum)]
enum ExportFormat {
    /// PMTiles v3 (web zoom z = coarsest 0), readable by any PMTiles reader.
    Pmtiles,
}

#[derive(Clone, Copy, Debug, ValueEnum)]
enum LayoutArg {
    /// LOD0, LOD1, ... folders per layer plus the metadata text.
    Original,
    /// {z}/{x}/{y} tree (web zoom: z = 0 coarsest).
    Xyz,
}

/// Logs go to stderr through `tracing`; `RUST_LOG` overrides the flags.
pub fn init_logging(verbose: u8, quiet: bool) {
    let level = match (quiet, verbose) {
        (true, _) => "error",
        (false, 0) => "info",
        (false, 1) => "debug",
        _ => "trace",
    };
    let filter = tracing_subscriber::EnvFilter::try_from_default_env()
        .unwrap_or_else(|_| tracing_subscriber::EnvFilter::new(level));
    tracing_subscriber::fmt().with_env_filter(filter).with_writer(std::io::stderr).with_target(false).init();
}

/// Runs a parsed command line.
///
/// # Errors
/// Whatever the command failed with.
pub fn run(cli: Cli) -> Result<ExitCode> {
    match cli.command {
        // The server handles Ctrl-C / SIGTERM itself (graceful drain), without the progress bar's handler.
        Command::Serve(args) => serve::run(args),
        other => run_with_progress(other, cli.quiet),
    }
}

fn run_with_progress(command: Command, quiet: bool) -> Result<ExitCode> {
    let progress = CliProgress::install(quiet);
    match command {
        Command::Pack(args) => pack::run(args, &progress),
        Command::Info { archive, json, tiles: false } if terrastream_format::is_manifest_location(&archive) => {
            manifest::info(&archive, json)
        }
        Command::Info { archive, json, tiles } => info::run(&archive, json, tiles),
        Command::Verify { archive } if terrastream_format::is_manifest_location(&archive) => {
            manifest::verify_all(&archive, &progress)
        }
        Command::Verify { archive } => {
            let reader = open(&archive)?;
            progress.start_bytes("verify", reader.header().data.len);
            let report = verify(&reader, |bytes| progress.set_position(bytes))?;
            progress.finish();
            if report.is_ok() {
                println!(
                    "{archive}: OK — {} tiles, {} blobs, {} leaves, {} payload bytes checked",
                    report.addressed_tiles, report.blobs_checked, report.leaves_checked, report.bytes_checked
                );
                if report.unreferenced_bytes > 0 {
                    println!(
                        "{archive}: {} bytes of replaced tiles left by updates in place (`terrastream merge {archive} -o …` writes a compact copy)",
                        report.unreferenced_bytes
                    );
                }
                Ok(ExitCode::SUCCESS)
            } else {
                for p in &report.problems {
                    eprintln!("{archive}: {p}");
                }
                eprintln!("{archive}: DAMAGED — {} problem(s)", report.problems.len());
                Ok(ExitCode::from(2))
            }
        }
        Command::Extract { archive, output, layout } => {
            let reader = open(&archive)?;
            let layout = match layout {
                LayoutArg::Original => Layout::Original,
                LayoutArg::Xyz => Layout::Xyz,
            };
            let summary = extract(&reader, &output, layout, &progress)?;
            progress.finish();
            println!("wrote {} tiles ({} bytes) under {}", summary.files, summary.bytes, output.display());
            Ok(ExitCode::SUCCESS)
        }
        Command::Serve(args) => serve::run(args),
        Command::Export { archive, layer, to: ExportFormat::Pmtiles, output } => {
            let reader = open(&archive)?;
            let meta = reader.metadata();
            let index = meta.resolve_layer(&layer).with_context(|| {
                let names: Vec<&str> = meta.layers.iter().map(|l| l.name.as_str()).collect();
                format!("{archive} has no layer {layer:?} (layers: {})", names.join(", "))
            })?;
            let summary = terrastream_pack::export::pmtiles::export_pmtiles(&reader, index, &output, &progress)?;
            progress.finish();
            println!(
                "{}: PMTiles v3, {} tiles ({} distinct), {} bytes",
                output.display(),
                summary.addressed_tiles,
                summary.tile_contents,
                summary.file_len
            );
            Ok(ExitCode::SUCCESS)
        }
        Command::Update { base, elevation, texture, output, manifest_out, .. } => {
            anyhow::ensure!(
                !elevation.is_empty() || !texture.is_empty(),
                "nothing to update: give --elevation or --texture"
            );
            let output = output.unwrap_or_else(|| base.clone());
            let elevation = terrastream_tiler::expand_inputs(&elevation)?;
            let texture = terrastream_tiler::expand_inputs(&texture)?;
            let summary = terrastream_tiler::update(&base, &elevation, &texture, &output, &progress)?;
            progress.finish();
            println!(
                "{}: {} tiles from the new rasters, {} base tiles replaced, {} made again around and above them, {} bytes",
                output.display(),
                summary.tiled,
                summary.merge.replaced,
                summary.merge.made,
                summary.merge.write.file_len
            );
            if let Some(manifest) = &manifest_out {
                terrastream_tiler::single_manifest(&output, manifest)?;
                println!("{}: manifest of {}", manifest.display(), output.display());
            }
            Ok(ExitCode::SUCCESS)
        }
        Command::Merge { inputs, output, manifest: Some(manifest), .. } => {
            // The coarse archive of an earlier run in the shards' folder is not an input.
            let earlier = std::fs::canonicalize(&output).ok();
            let mut inputs = archives_in(&inputs)?;
            inputs.retain(|p| earlier.is_none() || std::fs::canonicalize(p).ok() != earlier);
            let summary = terrastream_tiler::merge_to_manifest(&inputs, &output, &manifest, &progress)?;
            progress.finish();
            println!(
                "{}: {} archives ({} tiles above the split LOD made into {}, {} bytes)",
                manifest.display(),
                summary.manifest.archives.len(),
                summary.coarse.addressed_tiles,
                output.display(),
                summary.coarse.file_len
            );
            Ok(ExitCode::SUCCESS)
        }
        Command::Merge { inputs, output, prefer, manifest: None } => {
            let inputs = archives_in(&inputs)?;
            let prefer = match prefer {
                PreferArg::Last => terrastream_tiler::Prefer::Last,
                PreferArg::Pixels => terrastream_tiler::Prefer::Pixels,
            };
            let summary = terrastream_tiler::merge_with(&inputs, &output, prefer, &progress)?;
            progress.finish();
            println!(
                "{}: {} tiles copied from {} archives ({} replaced by a later one), {} made, {} bytes",
                output.display(),
                summary.copied,
                inputs.len(),
                summary.replaced,
                summary.made,
                summary.write.file_len
            );
            Ok(ExitCode::SUCCESS)
        }
        Command::Demo(args) => demo::run(args, &progress),
        Command::Player { output } => write_player(&output),
        Command::Render(args) => render::run(args),
        Command::View(args) => view::run(args),
        Command::Tile(args) => tile::run(args, &progress),
        Command::Health { url, timeout } => health(&url, std::time::Duration::from_secs(timeout)),
        Command::Bench(cmd) => bench::run(cmd, &progress),
    }
}

/// `GET url` over plain HTTP/1.1 with std only; success on a 200 status line.
fn health(url: &str, timeout: std::time::Duration) -> Result<ExitCode> {
    use std::io::{Read, Write};
    let rest = url.strip_prefix("http://").with_context(|| format!("{url}: only http:// URLs"))?;
    let (authority, path) = rest.split_once('/').map_or((rest, "/".to_owned()), |(a, p)| (a, format!("/{p}")));
    let addr = std::net::ToSocketAddrs::to_socket_addrs(authority)
        .with_context(|| format!("{url}: bad address"))?
        .next()
        .with_context(|| format!("{url}: no address"))?;
    let mut stream =
        std::net::TcpStream::connect_timeout(&addr, timeout).with_context(|| format!("{url}: cannot connect"))?;
    stream.set_read_timeout(Some(timeout))?;
    stream.set_write_timeout(Some(timeout))?;
    write!(stream, "GET {path} HTTP/1.1\r\nHost: {authority}\r\nConnection: close\r\n\r\n")?;
    let mut head = [0u8; 64];
    let n = stream.read(&mut head).with_context(|| format!("{url}: no answer"))?;
    let status = String::from_utf8_lossy(&head[..n]);
    let ok = status.starts_with("HTTP/1.1 200") || status.starts_with("HTTP/1.0 200");
    let line = status.lines().next().unwrap_or("").to_owned();
    if ok {
        println!("{url}: {line}");
        Ok(ExitCode::SUCCESS)
    } else {
        eprintln!("{url}: unhealthy: {line}");
        Ok(ExitCode::FAILURE)
    }
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
