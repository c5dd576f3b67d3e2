//! `terrastream pack`.

use std::path::{Path, PathBuf};
use std::process::ExitCode;

use anyhow::{Context, Result, bail};
use clap::{Args, ValueEnum};
use terrastream_format::{ElevationScheme, LayerKind};
use terrastream_pack::WriterOptions;
use terrastream_pack::import::{
    LayerInput, OriginalLayout, PyramidSource, ScannedPyramid, Scheme, TilesetInput, XyzOptions, pack, pack_layers,
    pack_mbtiles, pack_pmtiles, scan_original, scan_xyz,
};

use super::CliProgress;

#[derive(Debug, Args)]
pub struct PackArgs {
    /// Input: a folder of original LOD folders (with their metadata text) or an XYZ/TMS
    /// tree, or a PMTiles v3 or MBTiles raster tileset. Or, instead, one source per layer
    /// with --elevation and --texture.
    #[arg(required_unless_present_any = ["elevation", "texture"], conflicts_with_all = ["elevation", "texture"])]
    input: Option<PathBuf>,
    /// The elevation layer's tiles: an XYZ/TMS tree, a PMTiles or an MBTiles file (heights
    /// as --elevation-encoding says). With --texture: one archive with both layers, each
    /// on its own grid of one CRS.
    #[arg(long)]
    elevation: Option<PathBuf>,
    /// The texture layer's tiles: an XYZ/TMS tree, a PMTiles or an MBTiles file.
    #[arg(long)]
    texture: Option<PathBuf>,
    /// Path template of the --elevation tree (as --template).
    #[arg(long)]
    elevation_template: Option<String>,
    /// Path template of the --texture tree (as --template).
    #[arg(long)]
    texture_template: Option<String>,
    /// Output archive (written to a temporary name, then renamed).
    #[arg(short, long)]
    output: PathBuf,
    /// What the elevation's heights are measured from: an EPSG code (5773 EGM96, 3855
    /// EGM2008, 4979 ellipsoidal), ellipsoid, egm96, egm2008, unknown, or geoid:FILE (a
    /// .gtx or GeoTIFF geoid grid). Default: unknown (served as stored). Terrain-RGB and
    /// Terrarium tile sets are usually above EGM96 or EGM2008.
    #[arg(long, value_parser = super::parse_datum)]
    vertical_datum: Option<terrastream_tiler::raster::DatumName>,
    /// Path template of an XYZ/TMS tree, relative to the input folder, e.g. "{z}/{x}/{y}.png"
    /// (z = 0 is the coarsest zoom). Each of {z}, {x}, {y} appears at least once; a repeated
    /// one must agree; {y:06} is y zero-padded to 6 digits. Rows of `row_col` names under
    /// row folders: "{z}/{y:06}/{y:06}_{x:06}.jpg". The grid is what the coarsest zoom's
    /// tiles imply (1x1 at zoom 0 for Web Mercator, 2x1 for the geodetic profile), doubled
    /// at each finer zoom.
    #[arg(long, verbatim_doc_comment)]
    template: Option<String>,
    /// Row order of the XYZ tree.
    #[arg(long, value_enum, default_value_t = SchemeArg::Xyz)]
    scheme: SchemeArg,
    /// Kind of a single-layer input.
    #[arg(long, value_enum, default_value_t = KindArg::Texture)]
    kind: KindArg,
    /// Height encoding of elevation tiles in an XYZ tree.
    #[arg(long, value_enum)]
    elevation_encoding: Option<EncodingArg>,
    /// Tile file names give y before x (original layout).
    #[arg(long)]
    swap_xy: bool,
}

#[derive(Clone, Copy, Debug, ValueEnum)]
enum SchemeArg {
    Xyz,
    Tms,
}

#[derive(Clone, Copy, Debug, ValueEnum)]
enum KindArg {
    Texture,
    Elevation,
}

#[derive(Clone, Copy, Debug, ValueEnum)]
enum EncodingArg {
    TerrainRgb,
    Terrarium,
    Gray8,
}

fn has_lod_folders(dir: &Path) -> bool {
    let is_lod = |p: &Path| p.is_dir() && p.file_name().and_then(|n| n.to_str()).is_some_and(|n| n.starts_with("LOD"));
    let children: Vec<PathBuf> =
        std::fs::read_dir(dir).map(|r| r.filter_map(|e| e.ok().map(|e| e.path())).collect()).unwrap_or_default();
    children.iter().any(|c| is_lod(c))
        || children
            .iter()
            .filter(|c| c.is_dir())
            .any(|c| std::fs::read_dir(c).map(|r| r.filter_map(|e| e.ok()).any(|e| is_lod(&e.path()))).unwrap_or(false))
}

/// What a single-file tileset is, by its first bytes (or, for an unreadable or short
/// file, its extension, so that the importer names what is wrong with it).
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
enum Tileset {
    Pmtiles,
    Mbtiles,
}

fn tileset(path: &Path) -> Option<Tileset> {
    use std::io::Read;
    let mut magic = [0u8; 16];
    let read = std::fs::File::open(path).and_then(|mut f| f.read_exact(&mut magic)).is_ok();
    let ext = path.extension().and_then(|e| e.to_str()).map(str::to_ascii_lowercase);
    if read && magic.starts_with(b"PMTiles") {
        Some(Tileset::Pmtiles)
    } else if read && &magic == b"SQLite format 3\0" {
        Some(Tileset::Mbtiles)
    } else {
        match ext.as_deref() {
            Some("pmtiles") => Some(Tileset::Pmtiles),
            Some("mbtiles") => Some(Tileset::Mbtiles),
            _ => None,
        }
    }
}

/// One layer's source for [`pack_layers`]: a tileset file or a tree (its template given,
/// else `{z}/{x}/{y}` with the extension of the first image found).
fn layer_source(path: &Path, template: Option<&str>, scheme: Scheme, tileset_kind: TilesetInput) -> Result<LayerInput> {
    let source = match tileset(path).filter(|_| !path.is_dir()) {
        Some(Tileset::Pmtiles) => PyramidSource::Pmtiles(path.to_path_buf()),
        Some(Tileset::Mbtiles) => PyramidSource::Mbtiles(path.to_path_buf()),
        None if path.is_dir() => {
            let template = match template {
                Some(t) => t.to_owned(),
                None => {
                    let ext = first_image_extension(path)
                        .with_context(|| format!("{}: no PNG, JPEG or WebP tiles (see --template)", path.display()))?;
                    format!("{{z}}/{{x}}/{{y}}.{ext}")
                }
            };
            PyramidSource::Tree(
                path.to_path_buf(),
                XyzOptions { template, scheme, kind: tileset_kind.kind, elevation: tileset_kind.elevation },
            )
        }
        None => bail!("{}: not a folder, a PMTiles or an MBTiles file", path.display()),
    };
    Ok(LayerInput { tileset: tileset_kind, source })
}

/// The extension of the first PNG, JPEG or WebP file under `dir` (depth-first, sorted).
fn first_image_extension(dir: &Path) -> Option<String> {
    let mut entries: Vec<PathBuf> = std::fs::read_dir(dir).ok()?.filter_map(|e| e.ok().map(|e| e.path())).collect();
    entries.sort();
    entries.iter().find_map(|p| {
        if p.is_dir() {
            first_image_extension(p)
        } else {
            let ext = p.extension()?.to_str()?.to_ascii_lowercase();
            ["png", "jpg", "jpeg", "webp"].contains(&ext.as_str()).then_some(ext)
        }
    })
}

/// The writer's options: the vertical datum named, its geoid grid read now (a missing
/// grid stops the run before anything is packed).
fn writer_options(args: &PackArgs) -> Result<WriterOptions> {
    let mut options = WriterOptions::default();
    if let Some(name) = &args.vertical_datum {
        let loaded = name.load()?;
        options.vertical_datum = Some(terrastream_pack::DatumOver(std::sync::Arc::new(move |b| loaded.over(b))));
    }
    Ok(options)
}

fn run_layers(args: &PackArgs, elevation: Option<ElevationScheme>, progress: &CliProgress) -> Result<ExitCode> {
    let scheme = match args.scheme {
        SchemeArg::Xyz => Scheme::Xyz,
        SchemeArg::Tms => Scheme::Tms,
    };
    let mut inputs = Vec::new();
    if let Some(path) = &args.elevation {
        let kind = TilesetInput {
            kind: LayerKind::Elevation,
            elevation: Some(elevation.unwrap_or(ElevationScheme::Terrarium)),
        };
        inputs.push(layer_source(path, args.elevation_template.as_deref(), scheme, kind)?);
    }
    if let Some(path) = &args.texture {
        let kind = TilesetInput { kind: LayerKind::Texture, elevation: None };
        inputs.push(layer_source(path, args.texture_template.as_deref(), scheme, kind)?);
    }
    let started = std::time::Instant::now();
    let summary = pack_layers(&inputs, &args.output, writer_options(args)?, progress)?;
    progress.finish();
    println!(
        "{}: {} tiles ({} distinct) in {} layers, {} bytes in {:.2} s",
        summary.path.display(),
        summary.addressed_tiles,
        summary.tile_contents,
        inputs.len(),
        summary.file_len,
        started.elapsed().as_secs_f64()
    );
    Ok(ExitCode::SUCCESS)
}

pub fn run(args: PackArgs, progress: &CliProgress) -> Result<ExitCode> {
    let kind = match args.kind {
        KindArg::Texture => LayerKind::Texture,
        KindArg::Elevation => LayerKind::Elevation,
    };
    let elevation = args.elevation_encoding.map(|e| match e {
        EncodingArg::TerrainRgb => ElevationScheme::TerrainRgb,
        EncodingArg::Terrarium => ElevationScheme::Terrarium,
        EncodingArg::Gray8 => ElevationScheme::Gray8,
    });
    let Some(input) = args.input.clone() else {
        return run_layers(&args, elevation, progress);
    };
    if let Some(set) = tileset(&input).filter(|_| !input.is_dir()) {
        return run_tileset(&args, &input, set, TilesetInput { kind, elevation }, progress);
    }
    if !input.is_dir() {
        bail!(
            "{}: not a folder, a PMTiles or an MBTiles file (pack takes tile pyramids; rasters are tiled by `terrastream tile`)",
            input.display()
        );
    }
    let scanned = if args.template.is_none() && has_lod_folders(&input) {
        scan_original(&input, &OriginalLayout { kind, swap_xy: args.swap_xy })?
    } else {
        scan_tree(&args, &input, kind, elevation)?
    };
    let tiles = scanned.tiles.len();
    tracing::info!(tiles, layers = scanned.metadata.layers.len(), "packing {}", input.display());
    let started = std::time::Instant::now();
    let summary = pack(scanned, &args.output, writer_options(&args)?, progress)?;
    progress.finish();
    let secs = started.elapsed().as_secs_f64();
    println!(
        "{}: {} tiles ({} distinct), {} bytes, {:.1} directory bytes/tile, in {:.2} s ({:.0} tiles/s)",
        summary.path.display(),
        summary.addressed_tiles,
        summary.tile_contents,
        summary.file_len,
        summary.directory_bytes as f64 / summary.addressed_tiles.max(1) as f64,
        secs,
        tiles as f64 / secs.max(1e-9),
    );
    Ok(ExitCode::SUCCESS)
}

/// Packs a PMTiles or MBTiles file.
fn run_tileset(
    args: &PackArgs,
    input: &Path,
    set: Tileset,
    tileset: TilesetInput,
    progress: &CliProgress,
) -> Result<ExitCode> {
    let started = std::time::Instant::now();
    let (summary, from) = match set {
        Tileset::Pmtiles => (pack_pmtiles(input, tileset, &args.output, writer_options(args)?, progress)?, "PMTiles"),
        Tileset::Mbtiles => (pack_mbtiles(input, tileset, &args.output, writer_options(args)?, progress)?, "MBTiles"),
    };
    progress.finish();
    println!(
        "{}: {} tiles ({} distinct) from {from}, {} bytes in {:.2} s",
        summary.path.display(),
        summary.addressed_tiles,
        summary.tile_contents,
        summary.file_len,
        started.elapsed().as_secs_f64()
    );
    Ok(ExitCode::SUCCESS)
}

/// Scans an XYZ or TMS tree by the template given, else by the first of the usual ones
/// that finds tiles.
fn scan_tree(
    args: &PackArgs,
    input: &Path,
    kind: LayerKind,
    elevation: Option<ElevationScheme>,
) -> Result<ScannedPyramid> {
    let templates = match &args.template {
        Some(t) => vec![t.clone()],
        None => ["png", "jpg", "jpeg", "webp"].iter().map(|e| format!("{{z}}/{{x}}/{{y}}.{e}")).collect(),
    };
    let options = |template: String| XyzOptions {
        template,
        scheme: match args.scheme {
            SchemeArg::Xyz => Scheme::Xyz,
            SchemeArg::Tms => Scheme::Tms,
        },
        kind,
        elevation,
    };
    let mut last_err = None;
    for t in templates {
        match scan_xyz(input, &options(t)) {
            Ok(s) => return Ok(s),
            Err(e) => last_err = Some(e),
        }
    }
    match last_err {
        Some(e) => Err(e).context("no LOD folders, and not an XYZ tree either (see --template)"),
        None => bail!("{}: nothing to pack", input.display()),
    }
}
