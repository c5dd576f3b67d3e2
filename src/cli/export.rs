//! `terrastream export`.

use std::path::PathBuf;
use std::process::ExitCode;

use anyhow::{Context, Result, bail};
use clap::{Args, ValueEnum};
use terrastream_format::{LayerKind, MmapSource, Reader};
use terrastream_pack::progress::Progress;
use terrastream_views::contours::ContourOptions;
use terrastream_views::encode::{HeightEncoding, ImageFormat};
use terrastream_views::export::{WebExport, export_xyz};
use terrastream_views::mercator::tiles_over;
use terrastream_views::pmtiles::{export_contours_pmtiles, export_web_pmtiles};
use terrastream_views::quantized::export::export_quantized_mesh;
use terrastream_views::relief::{ColorTable, Product, ReliefOptions};
use terrastream_views::tilejson::coverage;

use super::CliProgress;

#[derive(Debug, Args)]
pub struct ExportArgs {
    /// The archive: a path (or, for `--to pmtiles` of the archive's own tiles, an
    /// http(s):// URL).
    archive: String,
    /// Layer name (or index); web tiles default to the elevation.
    #[arg(long)]
    layer: Option<String>,
    /// Target format.
    #[arg(long, value_enum)]
    to: ExportFormat,
    /// Output file (pmtiles) or folder (xyz, quantized-mesh); written under a temporary
    /// name, then renamed.
    #[arg(short, long)]
    output: PathBuf,
    /// Web tiles' height encoding (`--to xyz`; with `--to pmtiles`, Web Mercator tiles
    /// instead of the archive's own: a `raster-dem` for MapLibre's pmtiles protocol).
    #[arg(long, value_enum)]
    encoding: Option<EncodingArg>,
    /// Web tiles' image format.
    #[arg(long, value_enum, default_value = "webp")]
    format: FormatArg,
    /// Web tiles' pixels a side (256 or 512).
    #[arg(long, default_value_t = 512)]
    size: u32,
    /// The coarsest web zoom (or terrain level) written.
    #[arg(long, default_value_t = 0)]
    minzoom: u8,
    /// The finest web zoom (or terrain level) written (default: the layer's, as its
    /// TileJSON or layer.json says).
    #[arg(long)]
    maxzoom: Option<u8>,
    /// `--to xyz`: the absolute URL the folder will be served at, for tiles.json's tile
    /// URLs (`https://cdn.example.com/terrain/`; TileJSON needs absolute ones).
    #[arg(long)]
    base_url: Option<String>,
    /// `--to xyz|pmtiles`: a map made from the elevation instead of a layer's own tiles.
    #[arg(long, value_enum)]
    product: Option<ProductArg>,
    #[command(flatten)]
    relief: ReliefArgs,
}

/// `gdaldem`'s parameters of `--product`.
#[derive(Debug, Args)]
struct ReliefArgs {
    /// Vertical exaggeration (gdaldem -z).
    #[arg(long, default_value_t = 1.0)]
    z_factor: f64,
    /// The light's azimuth, degrees clockwise from north (gdaldem -az).
    #[arg(long, default_value_t = 315.0)]
    azimuth: f64,
    /// The light's altitude above the horizon, degrees (gdaldem -alt).
    #[arg(long, default_value_t = 45.0)]
    altitude: f64,
    /// Four lights, as gdaldem hillshade -multidirectional.
    #[arg(long)]
    multidirectional: bool,
    /// Slope in percent rather than degrees (gdaldem slope -p).
    #[arg(long)]
    slope_percent: bool,
    /// A colour table in gdaldem color-relief's text format (default: built-in tints).
    #[arg(long)]
    color_table: Option<PathBuf>,
    /// `--to contours`: the height between lines [default: the zoom's].
    #[arg(long)]
    interval: Option<f64>,
    /// `--to contours`: every how many lines a major one is.
    #[arg(long, default_value_t = 5)]
    major: u32,
    /// `--to contours`: heights in feet.
    #[arg(long)]
    feet: bool,
}

#[derive(Clone, Copy, Debug, ValueEnum)]
enum ProductArg {
    Hillshade,
    Slope,
    Aspect,
    ColorRelief,
}

#[derive(Clone, Copy, Debug, ValueEnum)]
enum ExportFormat {
    /// PMTiles v3 (web zoom z = coarsest 0), readable by any PMTiles reader.
    Pmtiles,
    /// An XYZ tree of Web Mercator tiles and its tiles.json, for any static host.
    Xyz,
    /// Quantized-mesh terrain (CesiumJS): layer.json and a gzipped {z}/{x}/{y}.terrain
    /// tree, for any static host that sends `Content-Encoding: gzip` with them.
    QuantizedMesh,
    /// Contour lines as a PMTiles file of vector tiles (layer `contours`: `ele`, `major`),
    /// for MapLibre's pmtiles protocol.
    Contours,
}

#[derive(Clone, Copy, Debug, ValueEnum)]
enum EncodingArg {
    Terrarium,
    Mapbox,
}

#[derive(Clone, Copy, Debug, ValueEnum)]
enum FormatArg {
    Webp,
    Png,
}

pub fn run(args: ExportArgs, progress: &CliProgress) -> Result<ExitCode> {
    match args.to {
        ExportFormat::Pmtiles if args.encoding.is_none() && args.product.is_none() => run_pmtiles(&args, progress),
        ExportFormat::Pmtiles | ExportFormat::Xyz => run_web(&args, progress),
        ExportFormat::QuantizedMesh => run_quantized_mesh(&args, progress),
        ExportFormat::Contours => run_contours(&args, progress),
    }
}

/// Contour lines as a PMTiles file of vector tiles.
fn run_contours(args: &ExportArgs, progress: &CliProgress) -> Result<ExitCode> {
    let reader = Reader::open_mmap(&args.archive).with_context(|| format!("cannot open archive {}", args.archive))?;
    anyhow::ensure!(args.relief.interval.is_none_or(|i| i.is_finite() && i >= 0.1), "--interval: at least 0.1");
    anyhow::ensure!(args.relief.major >= 1, "--major: at least 1");
    let options = ContourOptions { interval: args.relief.interval, major: args.relief.major, feet: args.relief.feet };
    let started = std::time::Instant::now();
    let tick = |total: Option<u64>| {
        match total {
            Some(total) => progress.start("tiles", total),
            None => progress.advance(1),
        }
        progress.check().map_err(|_| terrastream_format::Interrupted)
    };
    let (summary, zooms) = export_contours_pmtiles(&reader, options, (args.minzoom, args.maxzoom), &args.output, &tick)
        .with_context(|| format!("exporting {} to {}", args.archive, args.output.display()))?;
    progress.finish();
    print_pmtiles(&args.output, "contour vector tiles", zooms, &summary, started);
    Ok(ExitCode::SUCCESS)
}

/// The elevation as quantized-mesh terrain in a folder.
fn run_quantized_mesh(args: &ExportArgs, progress: &CliProgress) -> Result<ExitCode> {
    let reader = Reader::open_mmap(&args.archive).with_context(|| format!("cannot open archive {}", args.archive))?;
    let started = std::time::Instant::now();
    let tick = |done: u64, total: u64| {
        if done == 1 {
            progress.start("tiles", total);
        }
        progress.advance(1);
        progress.check().map_err(|_| terrastream_format::Interrupted)
    };
    let summary = export_quantized_mesh(&reader, &args.output, args.minzoom, args.maxzoom, &tick)
        .with_context(|| format!("exporting {} to {}", args.archive, args.output.display()))?;
    progress.finish();
    println!(
        "{}: quantized-mesh levels {}..{}, {} tiles, {} bytes gzipped in {:.2} s",
        args.output.display(),
        summary.zooms.0,
        summary.zooms.1,
        summary.tiles,
        summary.bytes,
        started.elapsed().as_secs_f64()
    );
    Ok(ExitCode::SUCCESS)
}

/// The archive's own tiles of one layer as PMTiles.
fn run_pmtiles(args: &ExportArgs, progress: &CliProgress) -> Result<ExitCode> {
    let reader = super::open(&args.archive)?;
    let meta = reader.metadata();
    let Some(layer) = &args.layer else { bail!("--to pmtiles needs --layer") };
    let index = meta.resolve_layer(layer).with_context(|| {
        let names: Vec<&str> = meta.layers.iter().map(|l| l.name.as_str()).collect();
        format!("{} has no layer {layer:?} (layers: {})", args.archive, names.join(", "))
    })?;
    let summary = terrastream_pack::export::pmtiles::export_pmtiles(&reader, index, &args.output, progress)?;
    progress.finish();
    println!(
        "{}: PMTiles v3, {} tiles ({} distinct), {} bytes",
        args.output.display(),
        summary.addressed_tiles,
        summary.tile_contents,
        summary.file_len
    );
    Ok(ExitCode::SUCCESS)
}

/// Web Mercator tiles: with their TileJSON in a folder, or as a PMTiles file.
fn run_web(args: &ExportArgs, progress: &CliProgress) -> Result<ExitCode> {
    let reader = Reader::open_mmap(&args.archive).with_context(|| format!("cannot open archive {}", args.archive))?;
    let meta = reader.metadata();
    let index = match &args.layer {
        Some(l) => meta.resolve_layer(l).with_context(|| format!("{} has no layer {l:?}", args.archive))?,
        None => meta
            .layers
            .iter()
            .position(|l| l.kind == LayerKind::Elevation)
            .and_then(|i| u8::try_from(i).ok())
            .with_context(|| format!("{} has no elevation layer: name one with --layer", args.archive))?,
    };
    let elevation = meta.layers[usize::from(index)].kind == LayerKind::Elevation;
    let encoding = elevation.then_some(match args.encoding {
        Some(EncodingArg::Mapbox) => HeightEncoding::Mapbox,
        _ => HeightEncoding::Terrarium,
    });
    anyhow::ensure!(matches!(args.size, 256 | 512), "--size {}: use 256 or 512", args.size);
    let format = match args.format {
        FormatArg::Webp => ImageFormat::Webp,
        FormatArg::Png => ImageFormat::Png,
    };
    let relief = args.product.map(|p| relief(p, &args.relief)).transpose()?;
    let encoding = if relief.is_some() { None } else { encoding };
    let (minzoom, maxzoom) = (args.minzoom, args.maxzoom);
    let export = WebExport { layer: index, encoding, format, size: args.size, minzoom, maxzoom, relief };
    warn_if_far_finer(&reader, &export);
    let started = std::time::Instant::now();
    let tick = |done: u64, total: u64| {
        if done == 1 {
            progress.start("tiles", total);
        }
        progress.advance(1);
        progress.check().map_err(|_| terrastream_format::Interrupted)
    };
    if matches!(args.to, ExportFormat::Pmtiles) {
        return web_pmtiles(&reader, &export, args, progress, started);
    }
    let Some(base_url) = args.base_url.as_deref() else {
        bail!(
            "--to xyz needs --base-url: the absolute URL {} will be served at (https://host/path/), for the tile \
             URLs of its tiles.json (TileJSON needs absolute URLs; MapLibre resolves relative ones against the page)",
            args.output.display()
        );
    };
    let summary = export_xyz(&reader, &export, &args.output, base_url, &tick)
        .with_context(|| format!("exporting {} to {}", args.archive, args.output.display()))?;
    progress.finish();
    println!(
        "{}: zooms {}..{}, {} tiles ({} without data left out), {} bytes in {:.2} s",
        args.output.display(),
        summary.zooms.0,
        summary.zooms.1,
        summary.tiles,
        summary.empty,
        summary.bytes,
        started.elapsed().as_secs_f64()
    );
    Ok(ExitCode::SUCCESS)
}

/// A relief product and its `gdaldem` parameters.
fn relief(product: ProductArg, a: &ReliefArgs) -> Result<(Product, ReliefOptions)> {
    let table = match &a.color_table {
        Some(path) => {
            let text = std::fs::read_to_string(path).with_context(|| format!("reading {}", path.display()))?;
            ColorTable::parse(&text).map_err(|e| anyhow::anyhow!("{}: {e}", path.display()))?
        }
        None => ColorTable::default(),
    };
    anyhow::ensure!((0.0..=90.0).contains(&a.altitude), "--altitude {}: degrees from 0 to 90", a.altitude);
    let product = match product {
        ProductArg::Hillshade => Product::Hillshade,
        ProductArg::Slope => Product::Slope,
        ProductArg::Aspect => Product::Aspect,
        ProductArg::ColorRelief => Product::ColorRelief,
    };
    let options = ReliefOptions {
        z_factor: a.z_factor,
        azimuth: a.azimuth,
        altitude: a.altitude,
        multidirectional: a.multidirectional,
        slope_percent: a.slope_percent,
        table,
    };
    Ok((product, options))
}

/// The web tiles as a PMTiles file (a `raster-dem` for MapLibre's pmtiles protocol).
fn web_pmtiles(
    reader: &Reader<MmapSource>,
    export: &WebExport,
    args: &ExportArgs,
    progress: &CliProgress,
    started: std::time::Instant,
) -> Result<ExitCode> {
    let tick = |total: Option<u64>| {
        match total {
            Some(total) => progress.start("tiles", total),
            None => progress.advance(1),
        }
        progress.check().map_err(|_| terrastream_format::Interrupted)
    };
    let (summary, zooms) = export_web_pmtiles(reader, export, &args.output, &tick)
        .with_context(|| format!("exporting {} to {}", args.archive, args.output.display()))?;
    progress.finish();
    print_pmtiles(&args.output, "web tiles", zooms, &summary, started);
    Ok(ExitCode::SUCCESS)
}

/// Warns when the zooms asked for are far finer than the layer's data (its TileJSON's
/// `maxzoom`): each zoom beyond it makes four times the tiles of upsampled data.
fn warn_if_far_finer(reader: &Reader<MmapSource>, export: &WebExport) {
    let meta = reader.metadata();
    let Some(info) = meta.layers.get(usize::from(export.layer)) else { return };
    let (Some(asked), Some(cover)) = (export.maxzoom, coverage(meta, info, export.size)) else { return };
    if asked > cover.maxzoom.saturating_add(FINER_ZOOMS_WARNED) {
        let tiles: u64 = (cover.maxzoom + 1..=asked)
            .map(|z| {
                let (columns, rows) = tiles_over(z, cover.bounds);
                u64::from(columns.end() - columns.start() + 1) * u64::from(rows.end() - rows.start() + 1)
            })
            .sum();
        tracing::warn!(
            "--maxzoom {asked} is {} zooms finer than the data of layer {:?} (its finest is zoom {}): {tiles} more \
             tiles of upsampled data, each zoom four times the one before",
            asked - cover.maxzoom,
            info.name,
            cover.maxzoom
        );
    }
}

/// Zooms beyond the data's finest that an export makes without a warning.
const FINER_ZOOMS_WARNED: u8 = 2;

/// What a PMTiles export wrote: the file, its zooms, tiles (distinct), bytes and time.
fn print_pmtiles(
    output: &std::path::Path,
    what: &str,
    zooms: (u8, u8),
    summary: &terrastream_views::pmtiles::PmtilesSummary,
    started: std::time::Instant,
) {
    println!(
        "{}: PMTiles v3 of {what}, zooms {}..{}, {} tiles ({} distinct), {} bytes in {:.2} s",
        output.display(),
        zooms.0,
        zooms.1,
        summary.addressed_tiles,
        summary.tile_contents,
        summary.file_len,
        started.elapsed().as_secs_f64()
    );
}
