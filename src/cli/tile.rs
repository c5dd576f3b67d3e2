//! `terrastream tile`: source rasters -> one archive (or, with `--dry-run`, the plan).

use std::path::{Path, PathBuf};
use std::process::ExitCode;

use anyhow::{Context, Result, bail};
use clap::{Args, ValueEnum};
use terrastream_format::{ElevationEncoding, ElevationScheme, LayerKind};
use terrastream_tiler::raster::{DatumName, GridSpec, InputLayout};
use terrastream_tiler::{
    Blend, Collection, Collections, ElevationStorage, Plan, ShardPlan, ShardSpec, Sources, TextureFormat, TileOptions,
    TileRequest, aligned_grid, collection_shard_plan, expand_inputs, is_vrt, plan, plan_layout, shard_plan,
    squared_grid, squared_texture_grid, tile_collection, tile_shard,
};

use super::progress::CliProgress;

#[derive(Debug, Args)]
pub struct TileArgs {
    /// Elevation rasters: single-band GeoTIFFs (int/uint 8-32, float32/64; strips or tiles;
    /// none, LZW or Deflate; GDAL nodata), folders of them (recursive), patterns
    /// (`tiles/*.tif`) or GDAL VRTs (`gdalbuildvrt`: Simple/ComplexSource, SrcRect,
    /// DstRect, NODATA, scale and offset); or one PNG (16-bit gray heights, or 8-bit pixels
    /// in an `--elevation-encoding`; transparent = nodata). Several inputs, or a VRT, in
    /// any CRS, are mosaicked onto one grid: a later input wins where it has data; gaps
    /// are nodata.
    #[arg(long, num_args = 1.., required_unless_present = "texture")]
    elevation: Vec<PathBuf>,
    /// Output CRS of a mosaic (`EPSG:32633`, or a PROJ string): of the heights (the imagery
    /// follows them), or of the imagery when there are none. Default: the first input's if
    /// projected, else a transverse Mercator centred on the data.
    #[arg(long)]
    crs: Option<String>,
    /// Output sample spacing of a mosaic, in metres (of the imagery when there are no
    /// heights). Default: the finest input's.
    #[arg(long)]
    resolution: Option<f64>,
    /// Keep one geographic (degrees) input on its own grid, scaled at its centre latitude,
    /// instead of reprojecting it onto a transverse Mercator centred on it. Faster; but
    /// east-west distances are off by 1 - cos(lat)/cos(centre lat) away from the centre.
    #[arg(long, conflicts_with_all = ["crs", "resolution"])]
    keep_geographic: bool,
    /// Leave out mosaic inputs that cannot be used, or the strips and tiles of them that
    /// cannot be decoded (their places left empty), instead of stopping; listed at the end.
    #[arg(long)]
    skip_bad_inputs: bool,
    /// How the elevation's pixels map to heights. `auto`: GeoTIFF samples and 16-bit PNG
    /// values are heights (times `--height-step`, plus `--min-elevation`).
    #[arg(long, value_enum, default_value_t = EncodingArg::Auto)]
    elevation_encoding: EncodingArg,
    /// Height of value 0 (gray8, rgb-thirds, u16).
    #[arg(long, default_value_t = 0.0)]
    min_elevation: f64,
    /// Height span of the full value range (gray8: 0..255, rgb-thirds: 0..765).
    #[arg(long)]
    displacement: Option<f64>,
    /// Height of one step of a 16-bit PNG's values.
    #[arg(long, default_value_t = 1.0)]
    height_step: f64,
    /// Metres between elevation samples, for inputs that do not say (PNG).
    #[arg(long)]
    sample_spacing: Option<f64>,
    /// Texture image: GeoTIFF (8-bit gray/RGB/RGBA, or YCbCr as in JPEG-compressed
    /// orthophotos), PNG or JPEG, at its own resolution, placed by its georeference (a
    /// PNG's or JPEG's: a world file and `.prj`, or `.aux.xml`; an image without one must
    /// cover the elevation's area), or alone. Several images (files, folders, patterns,
    /// or a VRT of RGB/RGBA GeoTIFFs), in any CRS, are mosaicked over the elevation's
    /// extent: a later one wins where it has pixels.
    #[arg(long, num_args = 1..)]
    texture: Vec<PathBuf>,
    /// Texture tile storage: png and webp are lossless; jpeg is smallest (no alpha); bc1 and
    /// bc7 are GPU blocks (+ zstd) a renderer uploads with no decode.
    #[arg(long, value_enum, default_value_t = TextureFormatArg::Png)]
    texture_format: TextureFormatArg,
    /// JPEG quality (1..=100).
    #[arg(long, default_value_t = 85)]
    jpeg_quality: u8,
    /// Texture pixels per tile edge.
    #[arg(long, default_value_t = 256)]
    texture_tile_size: u32,
    /// Metres per texture pixel, for a texture without elevation (default: the pixel
    /// size its georeference gives, else 1).
    #[arg(long)]
    pixel_size: Option<f64>,
    /// Output archive (written to a temporary name, then renamed).
    #[arg(short, long, required_unless_present_any = ["dry_run", "list_inputs", "shard_plan_out"])]
    output: Option<PathBuf>,
    /// Samples per elevation tile edge.
    #[arg(long, default_value_t = 256)]
    tile_size: u32,
    /// Samples duplicated from the neighbours on each side of a tile.
    #[arg(long, default_value_t = 1)]
    border: u8,
    /// Elevation sample storage: quantized u16 (exact for integer sources) or f32.
    #[arg(long, value_enum, default_value_t = StorageArg::Auto)]
    storage: StorageArg,
    /// What the elevation's heights are measured from, where the inputs do not say (or
    /// say wrongly): an EPSG code (5773 EGM96 as SRTM's, 3855 EGM2008 as Copernicus',
    /// 4979 ellipsoidal), ellipsoid, egm96, egm2008, unknown, or geoid:FILE (a .gtx or
    /// GeoTIFF geoid grid). Default: what the inputs' GeoTIFF keys or WKT name, else
    /// unknown (served as stored).
    #[arg(long, value_parser = super::parse_datum)]
    vertical_datum: Option<DatumName>,
    /// Terrain name in the metadata (default: the input's file name).
    #[arg(long)]
    name: Option<String>,
    /// Print the plan (grids, LODs, tile counts, estimated size) and write nothing.
    #[arg(long)]
    dry_run: bool,
    /// Make shard I of N (`3/8`, 0-based): every tile up to the split LOD in a band of the
    /// grid; `terrastream merge` of all N makes the levels above and the whole archive.
    #[arg(long, value_parser = parse_shard)]
    shard: Option<(u32, u32)>,
    /// The last LOD shards make (default: the coarsest with two rows of tiles a shard).
    #[arg(long)]
    split_lod: Option<u8>,
    /// With `--shard`: print the inputs the shard's rows read (elevation, then imagery; one
    /// a line), found from every input's header (footprints, as the mosaic places them,
    /// with the resampling margin), and write nothing: what to fetch for the shard.
    #[arg(long, requires = "shard")]
    list_inputs: bool,
    /// Plan a run of N shards from the inputs' headers (no height is read) and write it
    /// to this folder: `plan.json` (the mosaics' grids, the bands), `merge.txt` (the
    /// inputs the merge reads: those a collection split finer than its base needs there;
    /// usually none) and `shard-I.txt`, the inputs shard I reads (for `rclone copy
    /// --files-from`). Needs `--shards`.
    #[arg(long, requires = "shards", conflicts_with_all = ["shard", "output"])]
    shard_plan_out: Option<PathBuf>,
    /// Shards in the run `--shard-plan-out` plans.
    #[arg(long, requires = "shard_plan_out")]
    shards: Option<u32>,
    /// Paths in `shard-I.txt` and `plan.json` relative to this folder (where `rclone copy
    /// --files-from` copies them to; a shard matches them against the ends of its inputs'
    /// paths); default: as the inputs were named.
    #[arg(long, requires = "shard_plan_out")]
    relative_to: Option<PathBuf>,
    /// With `--shard`: the plan (`plan.json` of `--shard-plan-out`) of the run: its grids
    /// and bands, so that the shard needs only its own inputs (those of its `shard-I.txt`;
    /// one missing is named).
    #[arg(long, requires = "shard")]
    shard_plan: Option<PathBuf>,
    /// The elevation's lowest and highest height (`-12.5,4810`, or `@FILE` holding that),
    /// instead of a pass over it: what lets the shards of one run skip that pass
    /// (`--dry-run` prints the range; `--height-range-out` writes it to a file). A height
    /// outside it stops the run, naming the file.
    #[arg(long, value_parser = parse_range_arg, allow_hyphen_values = true)]
    height_range: Option<(f32, f32)>,
    /// With `--dry-run`: write the elevation's height range to this file, as
    /// `--height-range @FILE` reads it (a sharded run's plan step).
    #[arg(long, requires = "dry_run")]
    height_range_out: Option<PathBuf>,
    /// With `--height-range-out`: take the range from the inputs' GDAL statistics only,
    /// and fail, naming it, at an input without exact ones, instead of reading its heights
    /// (a plan step given only the inputs' headers).
    #[arg(long, requires = "height_range_out")]
    require_statistics: bool,
    /// Where inputs of different resolutions overlap: `resolution`, the finer wins, and
    /// each input reaches only the levels its resolution supports (the coarsest level no
    /// coarser than its spacing: a base and fine surveys make the base's levels
    /// everywhere and the surveys' only where they lie); `order`, a later input wins, and
    /// every input is tiled at the finest spacing everywhere.
    #[arg(long, value_enum, default_value_t = PriorityArg::Resolution)]
    priority: PriorityArg,
    /// LOD 0's spacing for inputs of different resolutions: `auto`, the finest input's,
    /// or finer by less than 2x where that puts a coarser input's spacing on a level and
    /// makes at least a tenth fewer samples (a 30" base under a 1" survey: LOD 0 at
    /// 30"/32, the base made at its own 30", not upsampled to 16"); `finest`, always the
    /// finest input's (its samples kept as they lie on the grid).
    #[arg(long, value_enum, default_value_t = Lod0Arg::Auto)]
    lod0: Lod0Arg,
    /// The band across which a finer input blends into the coarser data beneath, along
    /// its data's edge, so that no step shows where a survey ends: samples of its level
    /// (`16`, the default) or metres (`500m`); 0 for none.
    #[arg(long, value_parser = parse_blend)]
    blend: Option<Blend>,
    /// Also write a manifest (FORMAT.md §9) naming the archive: what readers open when a
    /// terrain is published as several archives (`merge --manifest` makes the one of a
    /// sharded run).
    #[arg(long)]
    manifest_out: Option<PathBuf>,
    /// A water mask (a raster in any CRS: 0 land, 1 water, no data where it says
    /// nothing) made the archive's water layer once its tiles are written, as `terrastream
    /// water` does: lakes and rivers drawn as water, and in quantized-mesh's water mask.
    /// A shard's: the water tiles of its own tiles (`merge --water` makes the rest).
    #[arg(long, conflicts_with_all = ["shard_plan_out", "dry_run"])]
    water: Option<PathBuf>,
}

/// The shard plan at `path` (`plan.json` of `--shard-plan-out`).
pub(super) fn read_shard_plan(path: &Path) -> Result<ShardPlan> {
    let text =
        std::fs::read_to_string(path).with_context(|| format!("{}: cannot read the shard plan", path.display()))?;
    serde_json::from_str(&text).with_context(|| format!("{}: not a shard plan (plan.json)", path.display()))
}

/// Shard `index` of `count` as `path`'s plan has it: the request goes onto the plan's
/// grids; every input the plan lists for the shard must be among the request's.
fn planned_shard(path: &Path, index: u32, count: u32, request: &mut TileRequest) -> Result<(ShardSpec, ShardPlan)> {
    let plan = read_shard_plan(path)?;
    if plan.count != count {
        bail!("{}: a plan of {} shards, not {count}", path.display(), plan.count);
    }
    let Some(wanted) = plan.shards.get(index as usize) else {
        bail!("{}: no shard {index} in the plan", path.display());
    };
    for (given, wanted, what) in
        [(&request.elevation, &wanted.elevation, "--elevation"), (&request.texture, &wanted.texture, "--texture")]
    {
        // A path the plan gives relative to `--relative-to` is any input ending with it.
        if let Some(missing) = wanted.iter().find(|w| !given.iter().any(|g| g.ends_with(w))) {
            bail!(
                "shard {index}/{count} reads {} (so says {}), which is not among the {what} inputs",
                missing.display(),
                path.display()
            );
        }
    }
    if let Some(g) = &plan.elevation_grid {
        request.crs = Some(g.crs.clone());
        request.elevation_grid = Some(g.spec());
    }
    if let Some(g) = &plan.texture_grid {
        if plan.elevation_grid.is_none() {
            request.crs = Some(g.crs.clone());
        }
        request.texture_grid = Some(g.spec());
    }
    Ok((plan.spec(index), plan))
}

/// The collections a shard plan records, on this shard's plan (the planned grids), their
/// inputs named as this shard's are.
fn planned_collections_of(
    shards: &ShardPlan,
    plan: &Plan,
    sources: &Sources,
    request: &TileRequest,
) -> Result<(Option<Collection>, Option<Collection>)> {
    let of = |kind: LayerKind, grid: Option<GridSpec>| -> Result<Option<Collection>> {
        let Some(planned) = shards.collections.iter().find(|c| c.kind == kind) else { return Ok(None) };
        let Some(grid) = grid else {
            bail!("the shard plan holds a collection of {} but this shard has none of those inputs", people_kind(kind))
        };
        let given = if kind == LayerKind::Texture { &request.texture } else { &request.elevation };
        Ok(Some(Collection::from_planned(planned, &plan.metadata, grid, given)?))
    };
    Ok((
        of(LayerKind::Elevation, sources.height_mosaic().map(|m| m.grid()))?,
        of(LayerKind::Texture, sources.image_mosaic().map(|m| m.grid()))?,
    ))
}

/// A shard plan's inputs are files: a VRT is read whole (a source missing from a pod is an
/// error), so a shard given part of its sources could not open it.
fn refuse_vrts(request: &TileRequest) -> Result<()> {
    if let Some(vrt) = request.elevation.iter().chain(&request.texture).find(|p| is_vrt(p)) {
        bail!(
            "{}: a VRT cannot be split between shards (each would need every source it names); \
             give its source files, or their folder, instead",
            vrt.display()
        );
    }
    Ok(())
}

/// `plan.json` and a `shard-I.txt` per shard in `dir` (made if need be).
fn write_shard_plan(dir: &Path, plan: &ShardPlan, relative_to: Option<&Path>) -> Result<()> {
    std::fs::create_dir_all(dir).with_context(|| format!("{}: cannot make the folder", dir.display()))?;
    let mut plan = plan.clone();
    if let Some(root) = relative_to {
        let collected = plan.collections.iter_mut().flat_map(|c| c.inputs.iter_mut().map(|i| &mut i.path));
        let listed = plan.shards.iter_mut().flat_map(|s| s.elevation.iter_mut().chain(&mut s.texture));
        for input in listed.chain(collected).chain(&mut plan.merge) {
            let relative = input
                .strip_prefix(root)
                .with_context(|| format!("{} is not under --relative-to {}", input.display(), root.display()))?;
            *input = relative.to_path_buf();
        }
    }
    let json = serde_json::to_string_pretty(&plan)?;
    let path = dir.join("plan.json");
    std::fs::write(&path, json + "\n").with_context(|| format!("{}: cannot write", path.display()))?;
    for (i, shard) in plan.shards.iter().enumerate() {
        let mut list = String::new();
        for input in shard.elevation.iter().chain(&shard.texture) {
            list.push_str(&format!("{}\n", input.display()));
        }
        let path = dir.join(format!("shard-{i}.txt"));
        std::fs::write(&path, list).with_context(|| format!("{}: cannot write", path.display()))?;
    }
    // What the merge reads (none unless a collection is split finer than its base).
    let list: String = plan.merge.iter().map(|input| format!("{}\n", input.display())).collect();
    let path = dir.join("merge.txt");
    std::fs::write(&path, list).with_context(|| format!("{}: cannot write", path.display()))?;
    Ok(())
}

/// `MIN,MAX`, or `@FILE` holding that.
fn parse_range_arg(s: &str) -> std::result::Result<(f32, f32), String> {
    let Some(path) = s.strip_prefix('@') else { return parse_range(s) };
    let text = std::fs::read_to_string(path).map_err(|e| format!("{path}: {e}"))?;
    parse_range(text.trim()).map_err(|e| format!("{path}: {e}"))
}

fn parse_range(s: &str) -> std::result::Result<(f32, f32), String> {
    let bad = || format!("{s:?}: expected MIN,MAX in metres (-12.5,4810)");
    let (a, b) = s.split_once(',').ok_or_else(bad)?;
    let (a, b) = (a.trim().parse::<f32>().map_err(|_| bad())?, b.trim().parse::<f32>().map_err(|_| bad())?);
    if a.is_finite() && b.is_finite() && a <= b { Ok((a, b)) } else { Err(bad()) }
}

fn parse_shard(s: &str) -> std::result::Result<(u32, u32), String> {
    let bad = || format!("{s:?}: expected I/N, 0 <= I < N (shard 3 of 8: 3/8)");
    let (i, n) = s.split_once('/').ok_or_else(bad)?;
    let (i, n) = (i.trim().parse::<u32>().map_err(|_| bad())?, n.trim().parse::<u32>().map_err(|_| bad())?);
    if i >= n { Err(bad()) } else { Ok((i, n)) }
}

#[derive(Clone, Copy, Debug, PartialEq, Eq, ValueEnum)]
enum Lod0Arg {
    /// The finest input's spacing, or finer where a coarser input's lands on a level.
    Auto,
    /// The finest input's spacing.
    Finest,
}

#[derive(Clone, Copy, Debug, PartialEq, Eq, ValueEnum)]
enum PriorityArg {
    /// The finer input wins; each input as deep as its resolution allows.
    Resolution,
    /// A later input wins; one resolution (the finest) everywhere.
    Order,
}

/// Says where a collection's LOD 0 is finer than its finest input's spacing.
fn note_aligned(inputs: &[PathBuf], own: GridSpec, grid: GridSpec) {
    let (a, b) = (own.pixel.1, grid.pixel.1);
    if (a - b).abs() > 1e-12 * a {
        tracing::info!(
            "{} inputs of different resolutions: LOD 0 at {:.4}x the finest input's spacing, where a coarser \
             input's lies on a level (--lod0 finest keeps the finest's)",
            inputs.len(),
            b / a
        );
    }
}

/// `16` (samples) or `500m` (metres).
fn parse_blend(s: &str) -> std::result::Result<Blend, String> {
    let bad = || format!("{s:?}: expected samples (16) or metres (500m)");
    match s.trim().strip_suffix('m') {
        Some(m) => {
            m.trim().parse::<f64>().ok().filter(|m| m.is_finite() && *m >= 0.0).map(Blend::Metres).ok_or_else(bad)
        }
        None => s.trim().parse::<u32>().map(Blend::Samples).map_err(|_| bad()),
    }
}

#[derive(Clone, Copy, Debug, ValueEnum)]
enum StorageArg {
    /// u16 when the height range allows a step of 1/16 or finer, else f32.
    Auto,
    /// Quantized u16.
    U16,
    /// f32.
    F32,
}

#[derive(Clone, Copy, Debug, PartialEq, Eq, ValueEnum)]
enum EncodingArg {
    /// Samples are heights.
    Auto,
    /// 8-bit gray over min-elevation..min-elevation+displacement.
    Gray8,
    /// The original engine's RGB thirds: R+G+B over min-elevation..+displacement.
    RgbThirds,
    /// Mapbox Terrain-RGB: -10000 + (R*65536 + G*256 + B) * 0.1.
    TerrainRgb,
    /// Terrarium: R*256 + G + B/256 - 32768.
    Terrarium,
}

#[derive(Clone, Copy, Debug, ValueEnum)]
enum TextureFormatArg {
    Png,
    Jpeg,
    Webp,
    Bc1,
    Bc7,
}

impl TileArgs {
    fn encoding(&self) -> Result<Option<ElevationEncoding>> {
        let with = |scheme, scale, offset| Some(ElevationEncoding { scheme, scale, offset, nodata: None });
        let span = || -> Result<f64> {
            match self.displacement {
                Some(d) if d.is_finite() && d > 0.0 => Ok(d),
                Some(d) => bail!("--displacement {d}: must be a positive height span"),
                None => {
                    bail!("--elevation-encoding {:?} needs --displacement (the height span)", self.elevation_encoding)
                }
            }
        };
        Ok(match self.elevation_encoding {
            EncodingArg::Auto if self.height_step == 1.0 && self.min_elevation == 0.0 => None,
            EncodingArg::Auto => with(ElevationScheme::QuantizedU16, self.height_step, self.min_elevation),
            EncodingArg::Gray8 => with(ElevationScheme::Gray8, span()?, self.min_elevation),
            EncodingArg::RgbThirds => with(ElevationScheme::RgbThirds, span()?, self.min_elevation),
            EncodingArg::TerrainRgb => with(ElevationScheme::TerrainRgb, 1.0, 0.0),
            EncodingArg::Terrarium => with(ElevationScheme::Terrarium, 1.0, 0.0),
        })
    }
}

impl TileArgs {
    /// The tiling request these arguments state.
    fn request(&self) -> Result<TileRequest> {
        let format = match self.texture_format {
            TextureFormatArg::Png => TextureFormat::Png,
            TextureFormatArg::Jpeg => TextureFormat::Jpeg(self.jpeg_quality),
            TextureFormatArg::Webp => TextureFormat::Webp,
            TextureFormatArg::Bc1 => TextureFormat::Bc1,
            TextureFormatArg::Bc7 => TextureFormat::Bc7,
        };
        Ok(TileRequest {
            elevation: expand_inputs(&self.elevation)?,
            texture: expand_inputs(&self.texture)?,
            encoding: self.encoding()?,
            crs: self.crs.clone(),
            resolution: self.resolution,
            extent: None,
            keep_geographic: self.keep_geographic,
            sample_spacing: self.sample_spacing,
            height_range: self.height_range,
            skip_bad_inputs: self.skip_bad_inputs,
            texture_tile_size: self.texture_tile_size,
            texture_format: format,
            pixel_size: self.pixel_size,
            elevation_grid: None,
            texture_grid: None,
            vertical_datum: self.vertical_datum.clone(),
            target_datum: None,
        })
    }

    /// The terrain's name: given, else the first input's file name.
    fn name(&self) -> String {
        self.name.clone().unwrap_or_else(|| {
            let input = self.elevation.first().or(self.texture.first());
            input.and_then(|p| p.file_stem()).and_then(|s| s.to_str()).unwrap_or("terrain").to_owned()
        })
    }

    fn options(&self) -> TileOptions {
        let storage = match self.storage {
            StorageArg::Auto => ElevationStorage::Auto,
            StorageArg::U16 => ElevationStorage::U16,
            StorageArg::F32 => ElevationStorage::F32,
        };
        TileOptions { tile_size: self.tile_size, border: self.border, storage }
    }
}

pub fn run(args: TileArgs, progress: &CliProgress) -> Result<ExitCode> {
    let mut request = args.request()?;
    if args.shard_plan_out.is_some() || args.list_inputs || args.shard_plan.is_some() {
        refuse_vrts(&request)?;
    }
    if args.priority == PriorityArg::Resolution {
        request.vrts_as_their_files()?;
    }
    let planned = match (&args.shard_plan, args.shard) {
        (Some(path), Some((index, count))) => Some(planned_shard(path, index, count, &mut request)?),
        _ => None,
    };
    let mut sources = Sources::open(&request)?;
    // Inputs of different resolutions, each as deep as it reaches (heights, imagery); a
    // planned shard's are the plan's (its own inputs are a part of them).
    let by_resolution = args.priority == PriorityArg::Resolution && planned.is_none();
    // A VRT still among the inputs (not whole files read as they are) makes the run one
    // resolution (said below).
    let vrt = request.elevation.iter().chain(&request.texture).find(|p| is_vrt(p)).cloned();
    // Heights of different resolutions whose samples are not square (a geographic grid)
    // are opened again onto the grid their plan tiles, with the columns that make them
    // square, as `update` opens a survey onto an archive's grid: a collection makes every
    // level on its mosaic's grid, where a run of one resolution resamples its rows.
    // And LOD 0 may be finer than the finest input's spacing where that puts a coarser
    // input's on a level (`aligned_grid`): heights and imagery each on their own grid.
    // (Not where `--resolution` sets LOD 0's spacing.)
    if by_resolution && vrt.is_none() {
        let given = request.resolution.is_some();
        let aligned = |grid: GridSpec, layout: &[InputLayout]| match args.lod0 {
            Lod0Arg::Auto if !given => aligned_grid(layout, grid),
            _ => None,
        };
        if request.elevation_grid.is_none()
            && let Some(m) = sources.height_mosaic().filter(|m| Collection::spans_resolutions(m))
        {
            let square = squared_grid(m, m.grid());
            let grid = aligned(square.unwrap_or_else(|| m.grid()), &m.layout()).or(square);
            if let Some(grid) = grid {
                note_aligned(&request.elevation, m.grid(), grid);
                request.elevation_grid = Some(grid);
                sources = Sources::open(&request)?;
            }
        }
        // Imagery over heights whose samples the plan makes square (a geographic grid)
        // goes onto as many columns as the plan's texture layer has, as the heights do.
        if request.texture_grid.is_none()
            && let Some(m) = sources.image_mosaic().filter(|m| Collection::spans_resolutions(m))
        {
            let inputs = sources.inputs()?;
            let square = inputs.elevation().and_then(|e| squared_texture_grid(e, m.grid()));
            let grid = aligned(square.unwrap_or_else(|| m.grid()), &m.layout()).or(square);
            if let Some(grid) = grid {
                note_aligned(&request.texture, m.grid(), grid);
                request.texture_grid = Some(grid);
                sources = Sources::open(&request)?;
            }
        }
    }
    if args.dry_run && args.height_range_out.is_some() && request.height_range.is_none() {
        range_from_statistics(&mut sources, args.require_statistics)?;
    }
    let inputs = sources.inputs()?;
    let (elevation, texture) = (inputs.elevation(), inputs.texture());
    let (name, options) = (args.name(), args.options());
    let started = std::time::Instant::now();
    let sparse_heights = (by_resolution && vrt.is_none())
        .then(|| sources.height_mosaic())
        .flatten()
        .filter(|m| Collection::spans_resolutions(m));
    let sparse_images = (by_resolution && vrt.is_none())
        .then(|| sources.image_mosaic())
        .flatten()
        .filter(|m| Collection::spans_resolutions(m));
    if let Some(vrt) = &vrt {
        let spans = sources.height_mosaic().is_some_and(Collection::spans_resolutions)
            || sources.image_mosaic().is_some_and(Collection::spans_resolutions);
        if spans {
            tracing::warn!(
                "{}: a VRT among inputs of different resolutions whose sources are not whole files read as they \
                 are (a window, a nodata or a scale of its own): every input is tiled at the finest spacing \
                 (give its files instead, for each to reach only the levels its resolution supports)",
                vrt.display()
            );
        }
    }
    let blend = args.blend.unwrap_or_default();
    // The collections of these inputs (heights, imagery) on a plan's layers.
    let collections_on = |plan: &Plan| {
        (
            sparse_heights.and_then(|m| Collection::plan(m, &plan.metadata, LayerKind::Elevation, blend)),
            sparse_images.and_then(|m| Collection::plan(m, &plan.metadata, LayerKind::Texture, blend)),
        )
    };
    // The shard plan of this run, from the inputs' headers.
    let plan_shards = |count: u32| -> Result<ShardPlan> {
        if sparse_heights.is_none() && sparse_images.is_none() {
            return Ok(shard_plan(elevation, texture.as_ref(), &name, options, count, args.split_lod)?);
        }
        let mut plan = plan_layout(elevation, texture.as_ref(), &name, options)?;
        let (heights, imagery) = collections_on(&plan);
        for c in [&heights, &imagery].into_iter().flatten() {
            c.apply_to(&mut plan);
        }
        let collections = Collections { heights: heights.as_ref(), imagery: imagery.as_ref() };
        Ok(collection_shard_plan(collections, &plan, elevation, texture.as_ref(), count, args.split_lod)?)
    };
    if let Some(dir) = &args.shard_plan_out {
        let count = args.shards.unwrap_or(1);
        let plan = plan_shards(count)?;
        write_shard_plan(dir, &plan, args.relative_to.as_deref())?;
        for (i, shard) in plan.shards.iter().enumerate() {
            println!(
                "shard {i}/{count}: {} elevation inputs, {} imagery inputs",
                shard.elevation.len(),
                shard.texture.len()
            );
        }
        println!("{}: the plan of {count} shards", dir.join("plan.json").display());
        return Ok(ExitCode::SUCCESS);
    }
    if args.list_inputs {
        let Some((index, count)) = args.shard else { bail!("--list-inputs needs --shard I/N") };
        let plan = plan_shards(count)?;
        let shard = &plan.shards[index as usize];
        for path in shard.elevation.iter().chain(&shard.texture) {
            println!("{}", path.display());
        }
        return Ok(ExitCode::SUCCESS);
    }
    let planned_collections = planned.as_ref().is_some_and(|(_, p)| !p.collections.is_empty());
    if sparse_heights.is_some() || sparse_images.is_some() || planned_collections {
        let mut plan = plan(elevation, texture.as_ref(), &name, options, progress)?;
        let (heights, imagery) = match &planned {
            Some((_, shards)) => planned_collections_of(shards, &plan, &sources, &request)?,
            None => collections_on(&plan),
        };
        for c in [&heights, &imagery].into_iter().flatten() {
            c.apply_to(&mut plan);
        }
        if args.dry_run {
            progress.finish();
            print_plan(&name, &plan);
            for c in [&heights, &imagery].into_iter().flatten() {
                print_collection(c);
            }
            if let Some(out) = &args.height_range_out {
                write_height_range(&plan, out)?;
            }
            return Ok(ExitCode::SUCCESS);
        }
        let Some(output) = &args.output else { bail!("--output is required") };
        super::make_parent(output)?;
        let collections = Collections { heights: heights.as_ref(), imagery: imagery.as_ref() };
        let shard = match &planned {
            Some((spec, _)) => Some(spec.clone()),
            None => args.shard.map(|(index, count)| ShardSpec { index, count, split_lod: args.split_lod, cuts: None }),
        };
        let summary =
            tile_collection(collections, &request, &sources, elevation, texture, &plan, output, shard, progress)?;
        add_water(args.water.as_deref(), output, progress)?;
        progress.finish();
        if let Some(manifest) = &args.manifest_out {
            terrastream_tiler::single_manifest(output, manifest)?;
        }
        print_skipped(&sources);
        let deep: Vec<String> = [&heights, &imagery]
            .into_iter()
            .flatten()
            .map(|c| {
                format!(
                    "{}: the whole grid from LOD {}, finer levels where the inputs reach",
                    people_kind(c.kind),
                    c.base
                )
            })
            .collect();
        println!(
            "{}: {} tiles, {} bytes in {:.2} s ({})",
            output.display(),
            summary.addressed_tiles,
            summary.file_len,
            started.elapsed().as_secs_f64(),
            deep.join("; ")
        );
        return Ok(ExitCode::SUCCESS);
    }
    if args.dry_run {
        let plan = plan(elevation, texture.as_ref(), &name, options, progress)?;
        progress.finish();
        print_plan(&name, &plan);
        if let Some(out) = &args.height_range_out {
            write_height_range(&plan, out)?;
        }
        print_skipped(&sources);
        return Ok(ExitCode::SUCCESS);
    }
    let Some(output) = &args.output else { bail!("--output is required") };
    super::make_parent(output)?;
    let shard = match planned {
        Some((spec, _)) => Some(spec),
        None => args.shard.map(|(index, count)| ShardSpec { index, count, split_lod: args.split_lod, cuts: None }),
    };
    let summary = tile_shard(elevation, texture, &name, output, options, shard, progress)?;
    add_water(args.water.as_deref(), output, progress)?;
    progress.finish();
    if let Some(manifest) = &args.manifest_out {
        terrastream_tiler::single_manifest(output, manifest)?;
        println!("{}: manifest of {}", manifest.display(), output.display());
    }
    print_skipped(&sources);
    println!(
        "{}: {} tiles, {} bytes in {:.2} s",
        output.display(),
        summary.addressed_tiles,
        summary.file_len,
        started.elapsed().as_secs_f64()
    );
    Ok(ExitCode::SUCCESS)
}

/// `--water`: the mask made the water layer of the archive just written.
fn add_water(mask: Option<&Path>, output: &Path, progress: &CliProgress) -> Result<()> {
    let Some(mask) = mask else { return Ok(()) };
    let summary = terrastream_tiler::add_water(output, mask, output, progress)?;
    tracing::info!(
        tiles = summary.tiles,
        wet = summary.wet,
        outside = summary.uncovered,
        "water layer from {}",
        mask.display()
    );
    Ok(())
}

/// A plan step's range from the inputs' own statistics, when every one records them: no
/// height read (the shards check every height against it as they tile).
fn range_from_statistics(sources: &mut Sources, required: bool) -> Result<()> {
    let recorded = sources.inputs()?.elevation().map(|e| e.statistics_range());
    if let (Some(Err(without)), true) = (&recorded, required) {
        bail!(
            "{}: no exact GDAL statistics (STATISTICS_MINIMUM/MAXIMUM; gdal_translate -stats or gdalinfo -stats \
             writes them), and --require-statistics reads no height",
            without.display()
        );
    }
    if let Some(Ok(range)) = recorded {
        tracing::info!("height range {range:?}: the inputs' GDAL statistics (no height read)");
        sources.set_height_range(range);
    }
    Ok(())
}

/// Writes a plan's height range, `MIN,MAX` at full precision, for the shards' `--height-range`.
fn write_height_range(plan: &Plan, out: &Path) -> Result<()> {
    anyhow::ensure!(
        plan.metadata.layers.iter().any(|l| l.kind == LayerKind::Elevation),
        "--height-range-out: no elevation to take the range of"
    );
    let t = &plan.metadata.terrain;
    let range = format!("{},{}\n", t.min_elevation, t.max_elevation);
    super::make_parent(out)?;
    std::fs::write(out, range).with_context(|| format!("{}: cannot write the height range", out.display()))
}

/// The plan of a dry run: a line per layer, and the totals.
fn print_plan(name: &str, plan: &Plan) {
    println!("{name}: plan (nothing written)");
    println!(
        "{:<16} {:<14} {:<10} {:>13} {:>6} {:>11} {:>5} {:>9} {:>11}",
        "layer", "kind", "format", "LOD 0 samples", "tile", "grid", "LODs", "tiles", "~bytes"
    );
    for (layer, p) in plan.metadata.layers.iter().zip(&plan.layers) {
        println!(
            "{:<16} {:<14} {:<10} {:>13} {:>6} {:>11} {:>5} {:>9} {:>11}",
            layer.name,
            super::people::name(&layer.kind),
            super::people::name(&layer.format),
            format!("{}x{}", p.size.0, p.size.1),
            format!("{}+{}", layer.tile_resolution, 2 * layer.border),
            format!("{}x{}", layer.num_x_tiles, layer.num_y_tiles),
            layer.num_lods,
            p.tiles,
            p.estimated_bytes
        );
    }
    let t = &plan.metadata.terrain;
    println!(
        "heights {} .. {}, spacing {:.3} m; at most {} tiles, about {:.1} MiB (typical compression)",
        t.min_elevation,
        t.max_elevation,
        t.base_tile_size,
        plan.tiles(),
        plan.estimated_bytes() as f64 / f64::from(1 << 20)
    );
}

/// The layer a collection makes, for people.
fn people_kind(kind: LayerKind) -> &'static str {
    if kind == LayerKind::Texture { "imagery" } else { "elevation" }
}

/// A collection's levels: each input's spacing and depth, and the tiles of each level
/// below the base.
fn print_collection(c: &Collection) {
    let finest = c.grid.pixel.0.min(c.grid.pixel.1);
    println!(
        "{} inputs of different resolutions, each as deep as it reaches (LOD 0 at {} CRS units, level L at 2^L times):",
        people_kind(c.kind),
        significant(finest)
    );
    for i in &c.inputs {
        println!("  {:<40} spacing {:>10}  from LOD {}", i.path.display(), significant(i.spacing), i.depth);
    }
    for l in &c.levels {
        println!("  LOD {:>2}: {} tiles where the finer inputs lie", l.lod, l.tiles.len());
    }
    println!("  LOD {:>2} and up: the whole grid", c.base);
}

/// `v` to four significant digits (a geographic grid's spacings are fractions of a degree).
fn significant(v: f64) -> String {
    if !(v.is_finite() && v > 0.0) {
        return v.to_string();
    }
    #[expect(clippy::cast_possible_truncation, clippy::cast_sign_loss, reason = "clamped to 0..=12")]
    let decimals = (3.0 - v.log10().floor()).clamp(0.0, 12.0) as usize;
    format!("{v:.decimals$}")
}

/// Lists the elevation and imagery inputs left out with `--skip-bad-inputs`, wholly (when
/// opened, or when their heights were scanned) or in part (strips or tiles that could not
/// be decoded when rows were made).
fn print_skipped(sources: &Sources) {
    let skipped = sources.skipped();
    if !skipped.is_empty() {
        println!("skipped {} inputs, wholly or in part, that cannot be used:", skipped.len());
        for (_, why) in skipped {
            println!("  {why}");
        }
    }
}
