//! Adding a survey to a collection: `terrastream update` of an archive whose finer levels
//! hold tiles only where its finer inputs lie (docs/tiling.md, "Collections").
//!
//! The new inputs reach the levels their resolution supports on the archive's grid. Their
//! levels are made as a run with every input makes them: over rectangles of tiles with a
//! ring, from the new inputs, completed from the archive's base level as it stores it
//! (what such a run completes them from), blended into it, each level the mean of the
//! finer one. Then the base level's tiles under them (and the tiles whose borders reach
//! them) take the finest level's means, and every tile above those is made again from its
//! children as stored. The rest of the archive is untouched, byte for byte.

use std::collections::{BTreeMap, HashMap, HashSet};
use std::path::{Path, PathBuf};
use std::sync::{Arc, Mutex, PoisonError};

use terrastream_format::{
    ElevationEncoding, LayerKind, LevelCover, Metadata, MmapSource, Reader, TileKey, payload_bytes,
};
use terrastream_pack::progress::Progress;

use super::{Blend, CoarseRows, Collection, CollectionInput, LevelSources, coarse_grid, depth_of};
use crate::encode::{decode_heights, quantize_heights};
use crate::error::{Error, Result};
use crate::pyramid::{Spool, halve_rows};
use crate::raster::{DatumName, ElevationSource, GridSpec, Heights, InputLayout, Mosaic};
use crate::tile::{HeightEncoder, write_spool};

/// An archive's stored samples of one level over a grid of that level's samples (its
/// first column and row may lie outside the level: no data there).
pub(crate) struct StoredLevel<'a> {
    stored: &'a Stored<'a>,
    lod: u8,
    first: (i64, i64),
    size: (u32, u32),
}

impl CoarseRows<f32> for StoredLevel<'_> {
    fn size(&self) -> (u32, u32) {
        self.size
    }

    fn rows(&self, rows: std::ops::Range<u32>, each: &mut dyn FnMut(Vec<f32>) -> Result<()>) -> Result<()> {
        for r in i64::from(rows.start)..i64::from(rows.end.min(self.size.1)) {
            let row = (0..i64::from(self.size.0))
                .map(|c| self.stored.sample(self.lod, self.first.0 + c, self.first.1 + r))
                .collect::<Result<Vec<f32>>>()?;
            each(row)?;
        }
        Ok(())
    }
}

/// An archive's elevation tiles, decoded on demand (and the ones an update made, which
/// stand in for them).
pub(crate) struct Stored<'a> {
    reader: &'a Reader<MmapSource>,
    index: u8,
    encoding: ElevationEncoding,
    res: i64,
    border: i64,
    /// Samples of each level, across and down.
    sizes: Vec<(i64, i64)>,
    decoded: Mutex<HashMap<TileKey, Option<Arc<Vec<f32>>>>>,
}

impl<'a> Stored<'a> {
    fn new(reader: &'a Reader<MmapSource>, index: u8, grid: (u32, u32)) -> Result<Self> {
        let layer = &reader.metadata().layers[usize::from(index)];
        let encoding = layer.elevation.ok_or(Error::NothingToTile)?;
        let sizes = (0..layer.num_lods)
            .map(|lod| (i64::from(grid.0.div_ceil(1 << lod).max(1)), i64::from(grid.1.div_ceil(1 << lod).max(1))))
            .collect();
        Ok(Self {
            reader,
            index,
            encoding,
            res: i64::from(layer.tile_resolution),
            border: i64::from(layer.border),
            sizes,
            decoded: Mutex::new(HashMap::new()),
        })
    }

    /// A tile's samples (borders included), None where the archive has none.
    fn tile(&self, key: TileKey) -> Result<Option<Arc<Vec<f32>>>> {
        if let Some(t) = self.decoded.lock().unwrap_or_else(PoisonError::into_inner).get(&key) {
            return Ok(t.clone());
        }
        let layer = &self.reader.metadata().layers[usize::from(self.index)];
        let decoded = match self.reader.tile(key)? {
            Some(stored) => {
                let raw = payload_bytes(layer, &stored, &format!("tile {key}"))?;
                Some(Arc::new(decode_heights(&raw, &self.encoding)))
            }
            None => None,
        };
        self.decoded.lock().unwrap_or_else(PoisonError::into_inner).insert(key, decoded.clone());
        Ok(decoded)
    }

    /// Sample (`x`, `y`) of level `lod` as stored (NaN outside the level or its tiles).
    fn sample(&self, lod: u8, x: i64, y: i64) -> Result<f32> {
        let (w, h) = self.sizes[usize::from(lod)];
        if x < 0 || y < 0 || x >= w || y >= h {
            return Ok(f32::NAN);
        }
        let (tx, ty) = (x / self.res, y / self.res);
        let key = TileKey::new(self.index, lod, u32::try_from(tx).unwrap_or(0), u32::try_from(ty).unwrap_or(0))?;
        let Some(tile) = self.tile(key)? else { return Ok(f32::NAN) };
        let edge = self.res + 2 * self.border;
        let at = (y - ty * self.res + self.border) * edge + (x - tx * self.res + self.border);
        Ok(usize::try_from(at).ok().and_then(|i| tile.get(i).copied()).unwrap_or(f32::NAN))
    }
}

/// Samples of a level being remade: over a region (first column and row, end column and
/// row), those changed (None: the archive's stand).
struct Level<'s> {
    stored: &'s Stored<'s>,
    lod: u8,
    region: [i64; 4],
    changed: Vec<Option<f32>>,
}

impl<'s> Level<'s> {
    fn new(stored: &'s Stored<'s>, lod: u8, region: [i64; 4]) -> Self {
        let len = usize::try_from((region[2] - region[0]).max(0) * (region[3] - region[1]).max(0)).unwrap_or(0);
        Self { stored, lod, region, changed: vec![None; len] }
    }

    /// Where sample (`x`, `y`) lies in `changed`.
    fn at(&self, x: i64, y: i64) -> Option<usize> {
        let [x0, y0, x1, y1] = self.region;
        ((x0..x1).contains(&x) && (y0..y1).contains(&y)).then(|| usize::try_from((y - y0) * (x1 - x0) + x - x0).ok())?
    }

    fn set(&mut self, x: i64, y: i64, v: f32) {
        if let Some(i) = self.at(x, y) {
            self.changed[i] = Some(v);
        }
    }

    fn sample(&self, x: i64, y: i64) -> Result<f32> {
        match self.at(x, y).and_then(|i| self.changed[i]) {
            Some(v) => Ok(v),
            None => self.stored.sample(self.lod, x, y),
        }
    }
}

/// What [`update_collection`] did.
#[derive(Debug)]
pub struct CollectionUpdate {
    /// The new version written.
    pub merge: crate::edit::merge::MergeSummary,
    /// Tiles made or made again (elevation and height ranges).
    pub made: u64,
}

/// Adds `elevation` rasters to the collection `base` (see the module; `reader` has it
/// open), written to `out` (`base` itself: in place).
///
/// # Errors
/// [`Error::Input`] naming the base or a raster: a raster as coarse as the archive's base
/// level, one over tiles the archive's finer levels already hold, heights the archive's
/// encoding cannot hold; as [`crate::update`].
pub(crate) fn update_collection(
    reader: Reader<MmapSource>,
    base: &Path,
    elevation: &[PathBuf],
    blend: Option<Blend>,
    out: &Path,
    progress: &dyn Progress,
) -> Result<CollectionUpdate> {
    let old = reader.metadata().clone();
    let bad = |why: String| Error::input(base, why);
    let find = |kind: LayerKind| old.layers.iter().position(|l| l.kind == kind).and_then(|i| u8::try_from(i).ok());
    let index = find(LayerKind::Elevation).ok_or_else(|| bad("it has no elevation layer".into()))?;
    let layer = old.layers[usize::from(index)].clone();
    let extent = layer.extent.clone().ok_or_else(|| bad("its elevation layer records no extent".into()))?;
    let base_lod = extent.partial.iter().map(|c| c.lod).max().map_or(0, |l| l + 1);
    let g = old.georeference.clone().ok_or_else(|| bad("it has no georeference".into()))?;
    let (Some(origin), Some(scale)) = (g.origin, g.scale) else {
        return Err(bad("its georeference has no origin and scale".into()));
    };
    let crs = g.definition.clone().or(g.crs.clone()).unwrap_or_default();
    let sample = layer.sample_spacing(0);
    let [w_m, h_m] = old.terrain.data_extent.ok_or_else(|| bad("it records no data extent".into()))?;
    #[expect(clippy::cast_possible_truncation, clippy::cast_sign_loss, reason = "a grid's samples")]
    let size = ((w_m / sample).round() as u32, (h_m / sample).round() as u32);
    let grid = GridSpec { origin, pixel: (sample * scale[0], sample * scale[1]), size };
    let finest = grid.pixel.0.min(grid.pixel.1);
    let datum = DatumName::of_record(&old.vertical_datum);
    let open = |paths: Vec<PathBuf>, grid: GridSpec| -> Result<Option<Mosaic<Heights>>> {
        super::open_heights(&super::heights_on(paths, grid, &crs, datum.as_ref(), None))
    };
    let whole = open(elevation.to_vec(), grid)?.ok_or(Error::NothingToTile)?;
    // The new heights must fit the archive's encoding.
    let (lo, hi) = whole.height_range(&mut |_| progress.check().map_err(Error::from).map_err(Into::into))?;
    if let Some(e) = layer.elevation.filter(|e| e.scheme == terrastream_format::ElevationScheme::QuantizedU16) {
        let (min, max) = (e.offset + e.scale, e.offset + 65_535.0 * e.scale);
        if f64::from(lo) < min || f64::from(hi) > max {
            return Err(Error::input(
                &elevation[0],
                format!(
                    "heights {lo} to {hi} outside what {} holds ({min} to {max}): tile every input again",
                    base.display()
                ),
            ));
        }
    }
    let mut inputs: Vec<CollectionInput> = vec![];
    for InputLayout { path, spacing, columns, rows } in whole.layout() {
        let depth = depth_of(spacing, finest);
        if depth >= base_lod {
            return Err(Error::input(
                &path,
                format!(
                    "reaches LOD {depth}, no finer than {}'s base (LOD {base_lod}): update adds finer surveys; \
                     tile every input again",
                    base.display()
                ),
            ));
        }
        inputs.push(CollectionInput { path, spacing, depth, columns, rows });
    }
    let depth = inputs.iter().map(|i| i.depth).min().ok_or(Error::NothingToTile)?;
    let levels = super::sparse_levels(&inputs, &layer, base_lod);
    // The band the archive's surveys were joined with, unless another is asked for.
    let blend = match (blend, old.sources.iter().find_map(|s| s.blend)) {
        (None, Some(recorded)) => recorded,
        (asked, _) => super::blend_samples(asked.unwrap_or_default(), finest),
    };
    let c = Collection { inputs, base: base_lod, levels, grid, blend, kind: LayerKind::Elevation };
    for level in &c.levels {
        for &(x, y) in &level.tiles {
            if reader.locate(TileKey::new(index, level.lod, x, y)?)?.is_some() {
                return Err(bad(format!(
                    "the new rasters reach tile {x}, {y} of LOD {}, which it holds already (an earlier survey's): \
                     tile every input again",
                    level.lod
                )));
            }
        }
    }

    // The new levels, completed from the base level as stored.
    let mut metadata = old.clone();
    record(&c, &mut metadata);
    // Where the finest data is, as the writer finds it anew from the tiles.
    for layer in &mut metadata.layers {
        if let Some(e) = &mut layer.extent {
            e.detail = e.world;
            e.lon_lat = None;
            e.crs = None;
        }
    }
    let stored = Stored::new(&reader, index, size)?;
    let heights = HeightEncoder::new(&metadata, index, find(LayerKind::HeightRange))?;
    let encoding = heights.encoding;
    let quantize = move |row: &mut [f32]| quantize_heights(row, &encoding);
    let folder = terrastream_pack::output_folder(out);
    let mut spool = Spool::new(&folder)?;
    let sources_of = |lod: u8, corner: (u32, u32), g: &GridSpec| -> Result<LevelSources<'_>> {
        let fine = open(c.reaching(lod, corner, g, &|d| d == lod), *g)?;
        let shift = u32::from(base_lod - lod);
        let scale = f64::from(1u32 << lod);
        let (first, coarse) =
            coarse_grid(grid.origin, (grid.pixel.0 * scale, grid.pixel.1 * scale), corner, g.size, shift);
        let level = StoredLevel { stored: &stored, lod: base_lod, first, size: coarse.size };
        let level: Box<dyn CoarseRows<f32> + '_> = Box::new(level);
        Ok(LevelSources { fine, coarse: Some((level, shift, first)) })
    };
    let encode_tile = |key: TileKey, samples: &[f32], _edge: usize| heights.encode(key, samples);
    let overrides = super::make_levels(
        &c,
        &metadata,
        index,
        &encode_tile,
        Some(&quantize),
        &folder,
        &mut spool,
        progress,
        &sources_of,
        None,
    )?;

    // The base level under them, and every level above, made again where they changed.
    let res = i64::from(layer.tile_resolution);
    let border = i64::from(layer.border);
    let region = (overrides.iter())
        .map(|o| {
            let (x1, y1) = (o.x0 + o.rows.first().map_or(0, Vec::len), o.y0 + o.rows.len());
            [to_i64(o.x0), to_i64(o.y0), to_i64(x1), to_i64(y1)]
        })
        .reduce(|a, r| [a[0].min(r[0]), a[1].min(r[1]), a[2].max(r[2]), a[3].max(r[3])]);
    let Some(mut region) = region else { return Err(Error::NothingToTile) };
    // The base level: the survey's means where they lie (a later rectangle's over an
    // earlier's, as the rows take them).
    let mut level = Level::new(&stored, base_lod, region);
    for o in &overrides {
        for (r, row) in o.rows.iter().enumerate() {
            for (k, &v) in row.iter().enumerate() {
                if !v.is_nan() {
                    level.set(to_i64(o.x0 + k), to_i64(o.y0 + r), v);
                }
            }
        }
    }
    let mut remade: Vec<TileKey> = vec![];
    for lod in base_lod..layer.num_lods {
        if lod > base_lod {
            // This level's samples over the region, the 2x2 means of the level below, as
            // the pyramid makes them.
            region = [region[0] / 2, region[1] / 2, (region[2] + 1) / 2, (region[3] + 1) / 2];
            let (w, h) = stored.sizes[usize::from(lod)];
            let mut next = Level::new(&stored, lod, region);
            let columns = 2 * region[0].max(0)..2 * region[2].min(w);
            for y in region[1].max(0)..region[3].min(h) {
                let row = |j: i64| columns.clone().map(|x| level.sample(x, j)).collect::<Result<Vec<f32>>>();
                let mut half = halve_rows(&row(2 * y)?, &row(2 * y + 1)?);
                quantize(&mut half);
                for (k, v) in half.into_iter().enumerate() {
                    next.set(region[0].max(0) + to_i64(k), y, v);
                }
            }
            level = next;
        }
        // Tiles whose samples, borders included, reach the region.
        let (tx0, ty0) = ((region[0] - border).div_euclid(res).max(0), (region[1] - border).div_euclid(res).max(0));
        let (tx1, ty1) = ((region[2] + border).div_euclid(res), (region[3] + border).div_euclid(res));
        let (nx, ny) = layer.grid_at(lod);
        for ty in ty0..=ty1.min(i64::from(ny) - 1) {
            for tx in tx0..=tx1.min(i64::from(nx) - 1) {
                let edge = res + 2 * border;
                let mut samples = Vec::with_capacity(usize::try_from(edge * edge).unwrap_or(0));
                let mut any = false;
                for j in 0..edge {
                    for i in 0..edge {
                        let (x, y) = (tx * res + i - border, ty * res + j - border);
                        let v = level.sample(x, y)?;
                        any |=
                            !v.is_nan() && (border..border + res).contains(&i) && (border..border + res).contains(&j);
                        samples.push(v);
                    }
                }
                let key = TileKey::new(index, lod, u32::try_from(tx).unwrap_or(0), u32::try_from(ty).unwrap_or(0))?;
                if any {
                    for (k, bytes) in heights.encode(key, &samples)? {
                        spool.add(&metadata, k, &bytes)?;
                    }
                    remade.push(key);
                }
            }
        }
    }
    // Height ranges: the archive's, for the tiles not made again.
    let ours: HashSet<TileKey> = remade.iter().copied().chain(made_keys(&c, index)?).collect();
    let mut below = vec![];
    if let Some(r) = find(LayerKind::HeightRange) {
        reader.for_each_tile(|key, bytes| -> Result<()> {
            if key.layer() == r && bytes.len() >= 8 {
                let elevation = TileKey::new(index, key.lod(), key.x(), key.y())?;
                if !ours.contains(&elevation) {
                    let lo = f32::from_le_bytes([bytes[0], bytes[1], bytes[2], bytes[3]]);
                    let hi = f32::from_le_bytes([bytes[4], bytes[5], bytes[6], bytes[7]]);
                    below.push((elevation, lo, hi));
                }
            }
            Ok(())
        })?;
    }
    heights.finish(&metadata, below, &mut spool)?;
    let made = spool.tiles() as u64;
    drop(level);
    let changes = tempfile::Builder::new()
        .prefix(".update-")
        .suffix(".tspack")
        .tempdir_in(&folder)
        .map_err(|e| Error::file(&folder, e))?;
    let path = changes.path().join("changes.tspack");
    write_spool(spool, &metadata, &path, false, progress, &crate::phases::Phases::start())?;
    drop(stored);
    drop(reader);
    let merge = crate::edit::update::replace_tiles(base, path, out, &metadata, progress)?;
    tracing::info!(depth, made, "new inputs reach LOD {depth}");
    Ok(CollectionUpdate { merge, made })
}

fn to_i64(n: usize) -> i64 {
    i64::try_from(n).unwrap_or(i64::MAX)
}

/// The elevation tiles of `c`'s levels.
fn made_keys(c: &Collection, index: u8) -> Result<Vec<TileKey>> {
    let mut keys = vec![];
    for l in &c.levels {
        for &(x, y) in &l.tiles {
            keys.push(TileKey::new(index, l.lod, x, y)?);
        }
    }
    Ok(keys)
}

/// Records `c`'s inputs and partial levels in `metadata`, beside what it holds.
fn record(c: &Collection, metadata: &mut Metadata) {
    let (sources, covers) = super::records(c, metadata);
    metadata.sources.extend(sources);
    for layer in &mut metadata.layers {
        if let (Some(extent), LayerKind::Elevation | LayerKind::HeightRange) = (&mut layer.extent, layer.kind) {
            let mut by_lod: BTreeMap<u8, LevelCover> = extent.partial.drain(..).map(|c| (c.lod, c)).collect();
            for cover in &covers {
                let entry = by_lod.entry(cover.lod).or_insert_with(|| LevelCover {
                    lod: cover.lod,
                    tiles: vec![],
                    lon_lat: vec![],
                });
                let keep_degrees = entry.lon_lat.len() == entry.tiles.len() && cover.lon_lat.len() == cover.tiles.len();
                entry.tiles.extend(&cover.tiles);
                if keep_degrees {
                    entry.lon_lat.extend(&cover.lon_lat);
                } else {
                    entry.lon_lat.clear();
                }
            }
            extent.partial = by_lod.into_values().collect();
        }
    }
}
