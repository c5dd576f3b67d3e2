//! `terrastream update`: new rasters over part of an archive, without tiling the rest.
//!
//! The new rasters are mosaicked onto the archive's own grid (its CRS, origin, sample
//! spacing and tile size, read from its metadata) and only the rectangle of LOD-0 tiles
//! they touch is tiled, with the archive's height encoding, into a temporary archive. That
//! is merged over the base with `prefer pixels` (where a new raster has no data the base's
//! samples stay), and the merge remakes the tiles around and above the changed ones. The
//! result is appended to the base in place (or to a copy of it): the cost follows the
//! updated area, not the archive.

use std::path::{Path, PathBuf};

use terrastream_format::{ElevationScheme, LayerKind, Reader};
use terrastream_pack::progress::Progress;

use crate::crs::Crs;
use crate::edit::merge::{MergeSummary, Prefer, merge_in_place_as, merge_widened_as};
use crate::error::{Error, Result};
use crate::options::{TextureFormat, TextureInput};
use crate::plan::{LayerPlan, Plan};
use crate::pyramid::Window;
use crate::raster::{ElevationSource, Heights, ImageSource, KnownRange, Mosaic, MosaicKind, Pixels};
use crate::request::{Sources, TileRequest};
use crate::tile::tile_planned;

/// What [`update`] did.
#[derive(Clone, Debug)]
pub struct UpdateSummary {
    /// The merge of the new tiles over the base.
    pub merge: MergeSummary,
    /// LOD-0 tiles made from the new rasters.
    pub tiled: u64,
}

/// Tiles `elevation` and `texture` rasters (files, folders, patterns: see
/// `expand_inputs`) onto `base`'s grid where they lie and writes `base` with them to `out`.
///
/// With `out` the base itself, the archive is updated in place (FORMAT.md §7.1): the
/// changed tiles and new directories are appended, nothing is copied, and readers of the
/// old version keep reading it. Otherwise `out` is a copy of the base updated the same
/// way. An archive without room for that (or whose directories outgrow it) is written
/// anew, as a merge would.
///
/// # Errors
/// [`Error::Input`] naming the base when it has no projected georeference or lacks the
/// layer, a raster that does not fit the grid or the height encoding (naming it), or as
/// [`crate::merge_with`].
pub fn update(
    base: &Path,
    elevation: &[PathBuf],
    texture: &[PathBuf],
    out: &Path,
    progress: &dyn Progress,
) -> Result<UpdateSummary> {
    let phases = crate::phases::Phases::start();
    if let Ok(reader) = Reader::open_mmap(base)
        && crate::edit::merge::is_collection(reader.metadata())
    {
        let made = crate::collection::update::update_collection(reader, base, elevation, texture, None, out, progress)?;
        return Ok(UpdateSummary { merge: made.merge, tiled: made.made });
    }
    let grid = BaseGrid::open(base)?;
    let mut changes = Changes {
        layers: vec![
            LayerPlan { size: (0, 0), offset: (0, 0), tiles: 0, estimated_bytes: 0 };
            grid.metadata.layers.len()
        ],
        windows: vec![Window::empty(); grid.metadata.layers.len()],
    };
    let heights = changes.elevation(&grid, elevation)?;
    let image = changes.texture(&grid, texture)?;
    let mut metadata = grid.metadata;
    metadata.shard = None;
    let plan = Plan { metadata, layers: changes.layers };
    let folder = terrastream_pack::output_folder(out);
    let scratch = tempfile::Builder::new()
        .prefix(".update-")
        .suffix(".tspack")
        .tempdir_in(&folder)
        .map_err(|e| Error::file(&folder, e))?;
    let made = scratch.path().join("changes.tspack");
    let texture_input = image.as_ref().map(|i| TextureInput {
        source: &i.mosaic,
        tile_size: i.tile_size,
        format: i.format,
        pixel_size: 1.0,
    });
    let known = heights
        .as_ref()
        .map(|h| KnownRange::limited(&h.mosaic, h.limits, "the archive's height encoding (tile it again)"));
    let elevation_source = known.as_ref().map(|k| k as &dyn ElevationSource);
    let windows = &changes.windows;
    tracing::debug!(?windows, "new rasters opened");
    let tiled = tile_planned(elevation_source, texture_input, &plan, windows, &made, false, progress, &phases)?;
    let seen = known.as_ref().and_then(KnownRange::seen);
    let merge = merge_changes(base, made, out, seen, progress)?;
    Ok(UpdateSummary { merge, tiled: tiled.tile_entries })
}

/// The archive an update tiles onto: its metadata, and its grid in its (projected) CRS.
struct BaseGrid {
    path: PathBuf,
    metadata: terrastream_format::Metadata,
    /// The CRS as the archive states it (a PROJ definition or a name).
    crs: String,
    origin: [f64; 2],
    scale: [f64; 2],
}

impl BaseGrid {
    /// Reads `base`'s metadata and checks that new rasters can be placed on its grid.
    fn open(base: &Path) -> Result<Self> {
        let reader = Reader::open_mmap(base).map_err(|e| Error::input(base, format!("cannot open archive: {e}")))?;
        let metadata = reader.metadata().clone();
        drop(reader);
        let bad = |why: String| Error::input(base, why);
        // (A collection is updated as one, above; this is one that became one meanwhile.)
        if crate::edit::merge::is_collection(&metadata) {
            return Err(bad("it changed into a collection while it was being opened: run the update again".into()));
        }
        if let Some(shard) = &metadata.shard {
            return Err(bad(format!(
                "it is shard {}/{} of a sharded run: update the merged archive, or tile the shard again and \
                 publish the set again (merge --manifest)",
                shard.index, shard.count
            )));
        }
        let g = metadata
            .georeference
            .clone()
            .ok_or_else(|| bad("it has no georeference: nothing to place new rasters by".into()))?;
        let crs = g.definition.as_deref().or(g.crs.as_deref()).unwrap_or_default().to_owned();
        let parsed = Crs::parse(&crs)?;
        if parsed.is_geographic() {
            return Err(bad(format!(
                "it lies in {}, a geographic CRS: update needs a projected one (tile it with --crs)",
                parsed.name()
            )));
        }
        let (Some(origin), Some(scale)) = (g.origin, g.scale) else {
            return Err(bad(
                "its georeference has no origin and scale: tiled by an older version? tile it again".into()
            ));
        };
        Ok(Self { path: base.to_path_buf(), metadata, crs, origin, scale })
    }

    fn find(&self, kind: LayerKind) -> Option<usize> {
        self.metadata.layers.iter().position(|l| l.kind == kind)
    }

    /// Layer `index`'s LOD-0 grid in the CRS: samples, their spacing, and the extent they
    /// cover.
    fn layer_grid(&self, index: usize) -> Result<((u32, u32), f64, [f64; 4])> {
        let l = &self.metadata.layers[index];
        let spacing = l.sample_spacing(0);
        let (px, py) = (spacing * self.scale[0], spacing * self.scale[1]);
        if ((px / py) - 1.0).abs() > 1e-9 {
            return Err(Error::input(
                &self.path,
                format!("layer {:?} has samples of {px} x {py} CRS units: update needs square ones", l.name),
            ));
        }
        let size = (l.num_x_tiles * l.tile_resolution, l.num_y_tiles * l.tile_resolution);
        let origin = self.origin;
        let extent = [origin[0], origin[1] - f64::from(size.1) * py, origin[0] + f64::from(size.0) * px, origin[1]];
        Ok((size, px, extent))
    }

    /// The tiling request for `elevation` and `texture` inputs on a grid of `spacing` over
    /// `extent`: a mosaic onto exactly that grid.
    fn request(&self, elevation: &[PathBuf], texture: &[PathBuf], spacing: f64, extent: [f64; 4]) -> TileRequest {
        TileRequest {
            elevation: elevation.to_vec(),
            texture: texture.to_vec(),
            crs: Some(self.crs.clone()),
            resolution: Some(spacing),
            extent: Some(extent),
            // New heights of another datum than the archive's are converted to it.
            target_datum: crate::raster::DatumName::of_record(&self.metadata.vertical_datum),
            ..TileRequest::default()
        }
    }

    /// The heights the archive's encoding holds, as f32 rounded outwards (all of them for
    /// f32 storage): checked as the rows are read, with no pass of its own over the inputs.
    fn height_limits(&self, layer: usize) -> (f32, f32) {
        let quantized = self.metadata.layers[layer].elevation.filter(|e| e.scheme == ElevationScheme::QuantizedU16);
        let Some(enc) = quantized else { return (f32::NEG_INFINITY, f32::INFINITY) };
        let (min, max) = (enc.offset + enc.scale, enc.offset + 65_535.0 * enc.scale);
        #[expect(clippy::cast_possible_truncation, reason = "heights are f32")]
        let (lo, hi) = (min as f32, max as f32);
        (if f64::from(lo) > min { lo.next_down() } else { lo }, if f64::from(hi) < max { hi.next_up() } else { hi })
    }
}

/// New heights on an archive's grid.
struct NewHeights {
    mosaic: Mosaic<Heights>,
    /// The heights the archive's encoding holds.
    limits: (f32, f32),
}

/// New imagery on an archive's grid, and how the archive stores its tiles.
struct NewImagery {
    mosaic: Mosaic<Pixels>,
    format: TextureFormat,
    tile_size: u32,
}

/// What an update tiles, per layer of the base: the LOD-0 rectangle and its rows.
struct Changes {
    layers: Vec<LayerPlan>,
    windows: Vec<Window>,
}

impl Changes {
    /// The new heights, cropped to the LOD-0 tiles they touch, with the range the base's
    /// encoding holds; None without elevation inputs or where they touch no tile.
    fn elevation(&mut self, grid: &BaseGrid, inputs: &[PathBuf]) -> Result<Option<NewHeights>> {
        let Some(first) = inputs.first() else { return Ok(None) };
        let e = grid
            .find(LayerKind::Elevation)
            .ok_or_else(|| Error::input(&grid.path, "it has no elevation layer to update"))?;
        let (size, spacing, extent) = grid.layer_grid(e)?;
        let open = |extent| Sources::open(&grid.request(inputs, &[], spacing, extent)).map(|s| s.into_mosaics().0);
        let Some(mosaic) = open(extent)? else { return Ok(None) };
        check_size(first, mosaic.size(), size)?;
        let Some(Crop { offset, size, extent }) = crop(&mosaic, &grid.metadata.layers[e], spacing, extent) else {
            return Ok(None);
        };
        let Some(mosaic) = open(extent)? else { return Ok(None) };
        check_size(first, mosaic.size(), size)?;
        self.layers[e] = LayerPlan { size, offset, tiles: 0, estimated_bytes: 0 };
        self.windows[e] = Window::full(1, size.1 as usize);
        if let Some(r) = grid.find(LayerKind::HeightRange) {
            self.layers[r] = self.layers[e].clone();
        }
        Ok(Some(NewHeights { mosaic, limits: grid.height_limits(e) }))
    }

    /// The new imagery, cropped to the LOD-0 tiles it touches, with the base's texture
    /// format and tile size; None without texture inputs or where they touch no tile.
    fn texture(&mut self, grid: &BaseGrid, inputs: &[PathBuf]) -> Result<Option<NewImagery>> {
        let Some(first) = inputs.first() else { return Ok(None) };
        let t = grid
            .find(LayerKind::Texture)
            .ok_or_else(|| Error::input(&grid.path, "it has no texture layer to update"))?;
        let layer = &grid.metadata.layers[t];
        let format = TextureFormat::decodable(layer.format).ok_or_else(|| {
            Error::input(
                &grid.path,
                format!(
                    "its texture is {:?}: an update merges new imagery per pixel, which needs png or webp tiles",
                    layer.format
                ),
            )
        })?;
        let (size, spacing, extent) = grid.layer_grid(t)?;
        let open = |extent| Sources::open(&grid.request(&[], inputs, spacing, extent)).map(|s| s.into_mosaics().1);
        let Some(mosaic) = open(extent)? else { return Ok(None) };
        check_size(first, ImageSource::size(&mosaic), size)?;
        let Some(Crop { offset, size, extent }) = crop(&mosaic, layer, spacing, extent) else { return Ok(None) };
        let Some(mosaic) = open(extent)? else { return Ok(None) };
        check_size(first, ImageSource::size(&mosaic), size)?;
        self.layers[t] = LayerPlan { size, offset, tiles: 0, estimated_bytes: 0 };
        self.windows[t] = Window::full(1, size.1 as usize);
        Ok(Some(NewImagery { mosaic, format, tile_size: layer.tile_resolution }))
    }
}

/// Merges the tiles made (the archive at `made`) over `base` into `out`: in place when
/// `out` is the base, else into a copy of it renamed to `out` once complete; written anew
/// when the base has no room.
fn merge_changes(
    base: &Path,
    made: PathBuf,
    out: &Path,
    seen: Option<(f32, f32)>,
    progress: &dyn Progress,
) -> Result<MergeSummary> {
    merge_changes_as(base, made, out, seen, None, progress)
}

/// `made`'s tiles over `base`'s as they are (none made again), with `metadata`, written
/// to `out` as an update writes (in place where `out` is `base`): a collection's update.
pub(crate) fn replace_tiles(
    base: &Path,
    made: PathBuf,
    out: &Path,
    metadata: &terrastream_format::Metadata,
    progress: &dyn Progress,
) -> Result<MergeSummary> {
    merge_changes_as(base, made, out, None, Some(metadata), progress)
}

/// Whether `a` and `b` name the same file (an update or a water layer in place).
pub(crate) fn same_file(a: &Path, b: &Path) -> bool {
    std::fs::canonicalize(a).ok().zip(std::fs::canonicalize(b).ok()).is_some_and(|(a, b)| a == b)
}

fn merge_changes_as(
    base: &Path,
    made: PathBuf,
    out: &Path,
    seen: Option<(f32, f32)>,
    as_is: Option<&terrastream_format::Metadata>,
    progress: &dyn Progress,
) -> Result<MergeSummary> {
    let inputs = [base.to_path_buf(), made];
    let rewrite = |why: &str| {
        tracing::info!("{}: {why}: writing the archive anew", base.display());
        merge_widened_as(&inputs, out, Prefer::Pixels, seen, as_is, false, crate::RunInputs::default(), progress)
    };
    if same_file(base, out) {
        return match merge_in_place_as(&inputs, base, Prefer::Pixels, seen, as_is, progress) {
            Err(Error::Pack(terrastream_pack::Error::NoRoom { why, .. })) => rewrite(&why),
            other => other,
        };
    }
    // A copy of the base (its blocks shared where the filesystem can), updated in place
    // and renamed to `out` once complete.
    let folder = terrastream_pack::output_folder(out);
    let name = out.file_name().map(|n| n.to_string_lossy().into_owned()).unwrap_or_default();
    let copy = tempfile::Builder::new()
        .prefix(&format!(".{name}."))
        .suffix(".partial")
        .tempfile_in(&folder)
        .map_err(|e| Error::file(&folder, e))?;
    std::fs::copy(base, copy.path()).map_err(|e| Error::file(copy.path(), e))?;
    match merge_in_place_as(&inputs, copy.path(), Prefer::Pixels, seen, as_is, progress) {
        Err(Error::Pack(terrastream_pack::Error::NoRoom { why, .. })) => rewrite(&why),
        Err(e) => Err(e),
        Ok(mut merge) => {
            copy.persist(out).map_err(|e| Error::file(out, e.error))?;
            merge.write.path = out.to_path_buf();
            Ok(merge)
        }
    }
}

fn check_size(input: &Path, got: (u32, u32), grid: (u32, u32)) -> Result<()> {
    if got == grid {
        return Ok(());
    }
    Err(Error::input(input, format!("mosaicked onto the archive's grid it is {got:?} samples, not {grid:?}")))
}

/// The part of a layer's grid an update tiles.
struct Crop {
    /// Its first LOD-0 tile.
    offset: (u32, u32),
    /// Its samples across and down.
    size: (u32, u32),
    /// Its extent in the CRS.
    extent: [f64; 4],
}

/// The LOD-0 tiles of `layer` (a grid of `spacing` over `extent`) that `source`'s inputs
/// touch, as the rectangle of them; None when they touch none. The tiles around it whose
/// borders reach into it are made again by the merge.
fn crop<K: MosaicKind>(
    source: &Mosaic<K>,
    layer: &terrastream_format::Layer,
    spacing: f64,
    extent: [f64; 4],
) -> Option<Crop> {
    let (columns, rows) = source.footprint_bounds()?;
    let res = layer.tile_resolution;
    let (w, h) = (layer.num_x_tiles * res, layer.num_y_tiles * res);
    let (tx0, ty0) = (columns.start / res, rows.start / res);
    let (x0, y0) = (tx0 * res, ty0 * res);
    let (x1, y1) = ((columns.end.div_ceil(res) * res).min(w), (rows.end.div_ceil(res) * res).min(h));
    let at = |x: u32, y: u32| (extent[0] + f64::from(x) * spacing, extent[3] - f64::from(y) * spacing);
    let ((left, top), (right, bottom)) = (at(x0, y0), at(x1, y1));
    Some(Crop { offset: (tx0, ty0), size: (x1 - x0, y1 - y0), extent: [left, bottom, right, top] })
}
