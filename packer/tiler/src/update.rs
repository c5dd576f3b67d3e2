//! `terrastream update`: new rasters over part of an archive, without tiling the rest.
//!
//! The new rasters are mosaicked onto the archive's own grid (its CRS, origin, sample
//! spacing and tile size, read from its metadata) and only the rows of LOD-0 tiles they
//! touch are tiled, with the archive's height encoding, into a temporary archive. That is
//! merged over the base with `prefer pixels` (where a new raster has no data the base's
//! samples stay), and the merge remakes the tiles around and above the changed ones. The
//! cost follows the updated rows, not the archive (plus one copy of the archive's bytes).

use std::path::{Path, PathBuf};

use terrastream_format::{LayerKind, Reader, TileFormat};
use terrastream_pack::progress::Progress;

use crate::crs::Crs;
use crate::error::{Error, Result};
use crate::merge::{MergeSummary, Prefer, merge_with};
use crate::options::{TextureFormat, TextureInput};
use crate::plan::{LayerPlan, Plan};
use crate::pyramid::Window;
use crate::raster::{ElevationSource, Heights, ImageSource, Mosaic, MosaicKind, MosaicOptions, Pixels};
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
    let mut sizes: Vec<(u32, u32)> = vec![(0, 0); metadata.layers.len()];
    let mut windows: Vec<Window> = vec![Window::empty(); metadata.layers.len()];

    let heights = match (elevation.is_empty(), find(LayerKind::Elevation)) {
        (true, _) => None,
        (false, None) => return Err(bad("it has no elevation layer to update".into())),
        (false, Some(e)) => {
            let (size, spacing, extent) = grid(e)?;
            let mosaic = Mosaic::<Heights>::open(elevation, &mosaic_options(spacing, extent))?;
            check_size(&elevation[0], mosaic.size(), size)?;
            let (lo, hi) = mosaic.height_range(&mut |_| Ok(()))?;
            if let Some(enc) =
                metadata.layers[e].elevation.filter(|e| e.scheme == terrastream_format::ElevationScheme::QuantizedU16)
            {
                let (min, max) = (enc.offset + enc.scale, enc.offset + 65_535.0 * enc.scale);
                if f64::from(lo) < min || f64::from(hi) > max {
                    return Err(Error::input(
                        &elevation[0],
                        format!(
                            "heights {lo} .. {hi} do not fit the archive's height encoding ({min} .. {max}): tile it again"
                        ),
                    ));
                }
            }
            if lo <= hi {
                metadata.terrain.min_elevation = metadata.terrain.min_elevation.min(f64::from(lo));
                metadata.terrain.max_elevation = metadata.terrain.max_elevation.max(f64::from(hi));
            }
            sizes[e] = size;
            windows[e] = touched(&mosaic, size.1, &metadata.layers[e]);
            if let Some(r) = find(LayerKind::HeightRange) {
                sizes[r] = size;
            }
            Some(mosaic)
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
            sizes[t] = size;
            windows[t] = touched(&mosaic, size.1, layer);
            (Some(mosaic), format, layer.tile_resolution)
        }
    };
    let layers = sizes.iter().map(|&size| LayerPlan { size, tiles: 0, estimated_bytes: 0 }).collect();
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
    let elevation_source = heights.as_ref().map(|m| m as &dyn ElevationSource);
    let tiled = tile_planned(elevation_source, texture_input, &plan, &windows, &changes, progress, started)?;
    let merge = merge_with(&[base.to_path_buf(), changes], out, Prefer::Pixels, progress)?;
    Ok(UpdateSummary { merge, tiled: tiled.tile_entries })
}

fn check_size(input: &Path, got: (u32, u32), grid: (u32, u32)) -> Result<()> {
    if got == grid {
        return Ok(());
    }
    Err(Error::input(input, format!("mosaicked onto the archive's grid it is {got:?} samples, not {grid:?}")))
}

/// The window of LOD-0 tile rows where `source` has data (its inputs' footprints), or an
/// empty one.
fn touched<K: MosaicKind>(source: &Mosaic<K>, height: u32, layer: &terrastream_format::Layer) -> Window {
    let res = layer.tile_resolution as usize;
    let step = 64u32;
    let mut first = None;
    let mut last = 0;
    for start in (0..height).step_by(step as usize) {
        if source.footprint_samples(start..(start + step).min(height)) > 0.0 {
            first.get_or_insert(start);
            last = (start + step).min(height);
        }
    }
    let Some(first) = first else { return Window::empty() };
    let height = height as usize;
    let band = (first as usize / res * res)..(last as usize).div_ceil(res).saturating_mul(res).min(height);
    let border = usize::from(layer.border);
    let rows = band.start.saturating_sub(border)..(band.end + border).min(height);
    Window { input_lod: 0, last_lod: 0, encode_from: 0, rows, band }
}
