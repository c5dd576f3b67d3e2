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

use terrastream_format::{LayerKind, Reader, TileFormat};
use terrastream_pack::progress::Progress;

use crate::crs::Crs;
use crate::error::{Error, Result};
use crate::merge::{MergeSummary, Prefer, merge_in_place, merge_widened};
use crate::options::{TextureFormat, TextureInput};
use crate::plan::{LayerPlan, Plan};
use crate::pyramid::Window;
use crate::raster::{ElevationSource, Heights, ImageSource, KnownRange, Mosaic, MosaicKind, MosaicOptions, Pixels};
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
/// [`merge_with`].
pub fn update(
    base: &Path,
    elevation: &[PathBuf],
    texture: &[PathBuf],
    out: &Path,
    progress: &dyn Progress,
) -> Result<UpdateSummary> {
    let started = std::time::Instant::now();
    let reader = Reader::open_mmap(base).map_err(|e| Error::input(base, format!("cannot open archive: {e}")))?;
    let mut metadata = reader.metadata().clone();
    drop(reader);
    let bad = |why: String| Error::input(base, why);
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
    let crs = Crs::parse(g.definition.as_deref().or(g.crs.as_deref()).unwrap_or_default())?;
    if crs.is_geographic() {
        return Err(bad(format!(
            "it lies in {}, a geographic CRS: update needs a projected one (tile it with --crs)",
            crs.name()
        )));
    }
    let (Some(origin), Some(scale)) = (g.origin, g.scale) else {
        return Err(bad("its georeference has no origin and scale: tiled by an older version? tile it again".into()));
    };
    let find = |kind: LayerKind| metadata.layers.iter().position(|l| l.kind == kind);
    // Each layer's LOD-0 grid in the CRS: samples, and the extent they cover.
    let grid = |index: usize| -> Result<((u32, u32), f64, [f64; 4])> {
        let l = &metadata.layers[index];
        let spacing = l.tile_world_size / f64::from(l.tile_resolution);
        let (px, py) = (spacing * scale[0], spacing * scale[1]);
        if ((px / py) - 1.0).abs() > 1e-9 {
            return Err(bad(format!(
                "layer {:?} has samples of {px} x {py} CRS units: update needs square ones",
                l.name
            )));
        }
        let size = (l.num_x_tiles * l.tile_resolution, l.num_y_tiles * l.tile_resolution);
        let extent = [origin[0], origin[1] - f64::from(size.1) * py, origin[0] + f64::from(size.0) * px, origin[1]];
        Ok((size, px, extent))
    };
    let mosaic_options = |spacing: f64, extent: [f64; 4]| MosaicOptions {
        crs: Some(crs.clone()),
        resolution: Some(spacing),
        extent: Some(extent),
        ..MosaicOptions::default()
    };
    let mut layers: Vec<LayerPlan> =
        vec![LayerPlan { size: (0, 0), offset: (0, 0), tiles: 0, estimated_bytes: 0 }; metadata.layers.len()];
    let mut windows: Vec<Window> = vec![Window::empty(); metadata.layers.len()];

    let mut limits = (f32::NEG_INFINITY, f32::INFINITY);
    let heights = match (elevation.is_empty(), find(LayerKind::Elevation)) {
        (true, _) => None,
        (false, None) => return Err(bad("it has no elevation layer to update".into())),
        (false, Some(e)) => {
            let (size, spacing, extent) = grid(e)?;
            let mosaic = Mosaic::<Heights>::open(elevation, &mosaic_options(spacing, extent))?;
            check_size(&elevation[0], mosaic.size(), size)?;
            // Heights the archive's encoding holds: checked as the rows are read (no pass
            // of its own over the new rasters).
            if let Some(enc) =
                metadata.layers[e].elevation.filter(|e| e.scheme == terrastream_format::ElevationScheme::QuantizedU16)
            {
                let (min, max) = (enc.offset + enc.scale, enc.offset + 65_535.0 * enc.scale);
                // As f32, rounded outwards.
                #[expect(clippy::cast_possible_truncation, reason = "heights are f32")]
                let (lo, hi) = (min as f32, max as f32);
                limits = (
                    if f64::from(lo) > min { lo.next_down() } else { lo },
                    if f64::from(hi) < max { hi.next_up() } else { hi },
                );
            }
            match crop(&mosaic, &metadata.layers[e], spacing, extent) {
                None => None,
                Some(Crop { offset, size, extent }) => {
                    let mosaic = Mosaic::<Heights>::open(elevation, &mosaic_options(spacing, extent))?;
                    check_size(&elevation[0], mosaic.size(), size)?;
                    layers[e] = LayerPlan { size, offset, tiles: 0, estimated_bytes: 0 };
                    windows[e] = Window::full(1, size.1 as usize);
                    if let Some(r) = find(LayerKind::HeightRange) {
                        layers[r] = layers[e].clone();
                    }
                    Some(mosaic)
                }
            }
        }
    };
    let (image, format, tile_size) = match (texture.is_empty(), find(LayerKind::Texture)) {
        (true, _) => (None, TextureFormat::Png, 0),
        (false, None) => return Err(bad("it has no texture layer to update".into())),
        (false, Some(t)) => {
            let layer = &metadata.layers[t];
            let format = match layer.format {
                TileFormat::Png => TextureFormat::Png,
                TileFormat::Webp => TextureFormat::Webp,
                other => {
                    return Err(bad(format!(
                        "its texture is {other:?}: an update merges new imagery per pixel, which needs png or webp tiles"
                    )));
                }
            };
            let (size, spacing, extent) = grid(t)?;
            let mosaic = Mosaic::<Pixels>::open(texture, &mosaic_options(spacing, extent))?;
            check_size(&texture[0], ImageSource::size(&mosaic), size)?;
            match crop(&mosaic, layer, spacing, extent) {
                None => (None, format, 0),
                Some(Crop { offset, size, extent }) => {
                    let mosaic = Mosaic::<Pixels>::open(texture, &mosaic_options(spacing, extent))?;
                    check_size(&texture[0], ImageSource::size(&mosaic), size)?;
                    layers[t] = LayerPlan { size, offset, tiles: 0, estimated_bytes: 0 };
                    windows[t] = Window::full(1, size.1 as usize);
                    (Some(mosaic), format, layer.tile_resolution)
                }
            }
        }
    };
    metadata.shard = None;
    let plan = Plan { metadata, layers };
    let folder = terrastream_pack::output_folder(out);
    let scratch = tempfile::Builder::new()
        .prefix(".update-")
        .suffix(".tspack")
        .tempdir_in(&folder)
        .map_err(|e| Error::file(&folder, e))?;
    let changes = scratch.path().join("changes.tspack");
    let texture_input = image.as_ref().map(|m| TextureInput { source: m, tile_size, format, pixel_size: 1.0 });
    let known =
        heights.as_ref().map(|m| KnownRange::limited(m, limits, "the archive's height encoding (tile it again)"));
    let elevation_source = known.as_ref().map(|k| k as &dyn ElevationSource);
    tracing::debug!(?windows, "new rasters opened");
    let tiled = tile_planned(elevation_source, texture_input, &plan, &windows, &changes, false, progress, started)?;
    let seen = known.as_ref().and_then(KnownRange::seen);
    let inputs = [base.to_path_buf(), changes];
    let rewrite = |why: &str| {
        tracing::info!("{}: {why}: writing the archive anew", base.display());
        merge_widened(&inputs, out, Prefer::Pixels, seen, progress)
    };
    let same = |a: &Path, b: &Path| {
        std::fs::canonicalize(a).ok().zip(std::fs::canonicalize(b).ok()).is_some_and(|(a, b)| a == b)
    };
    let merge = if same(base, out) {
        match merge_in_place(&inputs, base, Prefer::Pixels, seen, progress) {
            Err(Error::Pack(terrastream_pack::Error::NoRoom { why, .. })) => rewrite(&why)?,
            other => other?,
        }
    } else {
        // A copy of the base (its blocks shared where the filesystem can), updated in place
        // and renamed to `out` once complete.
        let name = out.file_name().map(|n| n.to_string_lossy().into_owned()).unwrap_or_default();
        let copy = tempfile::Builder::new()
            .prefix(&format!(".{name}."))
            .suffix(".partial")
            .tempfile_in(&folder)
            .map_err(|e| Error::file(&folder, e))?;
        std::fs::copy(base, copy.path()).map_err(|e| Error::file(copy.path(), e))?;
        match merge_in_place(&inputs, copy.path(), Prefer::Pixels, seen, progress) {
            Err(Error::Pack(terrastream_pack::Error::NoRoom { why, .. })) => rewrite(&why)?,
            Err(e) => return Err(e),
            Ok(mut merge) => {
                copy.persist(out).map_err(|e| Error::file(out, e.error))?;
                merge.write.path = out.to_path_buf();
                merge
            }
        }
    };
    Ok(UpdateSummary { merge, tiled: tiled.tile_entries })
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
