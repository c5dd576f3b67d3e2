//! Adding a survey to a collection: `terrastream update` of an archive whose finer levels
//! hold tiles only where its finer inputs lie (docs/tiling.md, "Collections").
//!
//! The new inputs reach the levels their resolution supports on the archive's grid. Their
//! levels are made as a run with every input makes them: over rectangles of tiles with a
//! ring, from the new inputs, completed from the archive's base level as it stores it
//! (what such a run completes them from), blended into it, each level the mean of the
//! finer one. Then the base level's tiles under them (and the tiles whose borders reach
//! them) take the finest level's means, and every tile above those is made again from its
//! children as stored. The rest of the archive is untouched, byte for byte. Imagery
//! follows the same rules on the texture layer's grid (its tiles PNG or WebP: decoded
//! back to the pixels a run completes from).

use std::collections::{BTreeMap, HashMap, HashSet};
use std::path::{Path, PathBuf};
use std::sync::{Arc, Mutex, PoisonError};

use terrastream_format::{LayerKind, LevelCover, Metadata, MmapSource, Reader, TileKey, payload_bytes};
use terrastream_pack::progress::Progress;

use super::{
    Blend, CoarseRows, Collection, CollectionInput, EncodeTile, LevelSources, QuantizeRow, coarse_grid, depth_of,
};
use crate::encode::{decode_heights, decode_texture, encode_texture, quantize_heights};
use crate::error::{Error, Result};
use crate::options::TextureFormat;
use crate::pyramid::{Pixel, Spool, halve_rows};
use crate::raster::{DatumName, ElevationSource, GridSpec, Heights, InputLayout, Mosaic, MosaicKind};
use crate::tile::{HeightEncoder, write_spool};

/// An archive's stored samples of one level over a grid of that level's samples (its
/// first column and row may lie outside the level: no data there).
pub(crate) struct StoredLevel<'a, S> {
    stored: &'a Stored<'a, S>,
    lod: u8,
    first: (i64, i64),
    size: (u32, u32),
}

impl<S: Pixel> CoarseRows<S> for StoredLevel<'_, S> {
    fn size(&self) -> (u32, u32) {
        self.size
    }

    fn rows(&self, rows: std::ops::Range<u32>, each: &mut dyn FnMut(Vec<S>) -> Result<()>) -> Result<()> {
        for r in i64::from(rows.start)..i64::from(rows.end.min(self.size.1)) {
            let row = (0..i64::from(self.size.0))
                .map(|c| self.stored.sample(self.lod, self.first.0 + c, self.first.1 + r))
                .collect::<Result<Vec<S>>>()?;
            each(row)?;
        }
        Ok(())
    }
}

/// A stored tile's payload (decompressed) -> its samples, borders included.
pub(crate) type Decode<'a, S> = dyn Fn(TileKey, &[u8]) -> Result<Vec<S>> + Send + Sync + 'a;

/// An archive's tiles of one layer, decoded on demand.
pub(crate) struct Stored<'a, S> {
    reader: &'a Reader<MmapSource>,
    index: u8,
    decode: Box<Decode<'a, S>>,
    res: i64,
    border: i64,
    /// Samples of each level, across and down.
    sizes: Vec<(i64, i64)>,
    decoded: Mutex<HashMap<TileKey, Option<Arc<Vec<S>>>>>,
}

impl<'a, S: Pixel> Stored<'a, S> {
    fn new(reader: &'a Reader<MmapSource>, index: u8, grid: (u32, u32), decode: Box<Decode<'a, S>>) -> Self {
        let layer = &reader.metadata().layers[usize::from(index)];
        let sizes = (0..layer.num_lods)
            .map(|lod| (i64::from(grid.0.div_ceil(1 << lod).max(1)), i64::from(grid.1.div_ceil(1 << lod).max(1))))
            .collect();
        Self {
            reader,
            index,
            decode,
            res: i64::from(layer.tile_resolution),
            border: i64::from(layer.border),
            sizes,
            decoded: Mutex::new(HashMap::new()),
        }
    }

    /// A tile's samples (borders included), None where the archive has none.
    fn tile(&self, key: TileKey) -> Result<Option<Arc<Vec<S>>>> {
        if let Some(t) = self.decoded.lock().unwrap_or_else(PoisonError::into_inner).get(&key) {
            return Ok(t.clone());
        }
        let layer = &self.reader.metadata().layers[usize::from(self.index)];
        let decoded = match self.reader.tile(key)? {
            Some(stored) => {
                let raw = payload_bytes(layer, &stored, &format!("tile {key}"))?;
                Some(Arc::new((self.decode)(key, &raw)?))
            }
            None => None,
        };
        self.decoded.lock().unwrap_or_else(PoisonError::into_inner).insert(key, decoded.clone());
        Ok(decoded)
    }

    /// Sample (`x`, `y`) of level `lod` as stored (none outside the level or its tiles).
    fn sample(&self, lod: u8, x: i64, y: i64) -> Result<S> {
        let (w, h) = self.sizes[usize::from(lod)];
        if x < 0 || y < 0 || x >= w || y >= h {
            return Ok(S::NONE);
        }
        let (tx, ty) = (x / self.res, y / self.res);
        let key = TileKey::new(self.index, lod, u32::try_from(tx).unwrap_or(0), u32::try_from(ty).unwrap_or(0))?;
        let Some(tile) = self.tile(key)? else { return Ok(S::NONE) };
        let edge = self.res + 2 * self.border;
        let at = (y - ty * self.res + self.border) * edge + (x - tx * self.res + self.border);
        Ok(usize::try_from(at).ok().and_then(|i| tile.get(i).copied()).unwrap_or(S::NONE))
    }
}

/// Samples of a level being remade: over a region (first column and row, end column and
/// row), those changed (None: the archive's stand).
struct Level<'s, S> {
    stored: &'s Stored<'s, S>,
    lod: u8,
    region: [i64; 4],
    changed: Vec<Option<S>>,
}

impl<'s, S: Pixel> Level<'s, S> {
    fn new(stored: &'s Stored<'s, S>, lod: u8, region: [i64; 4]) -> Self {
        let len = usize::try_from((region[2] - region[0]).max(0) * (region[3] - region[1]).max(0)).unwrap_or(0);
        Self { stored, lod, region, changed: vec![None; len] }
    }

    /// Where sample (`x`, `y`) lies in `changed`.
    fn at(&self, x: i64, y: i64) -> Option<usize> {
        let [x0, y0, x1, y1] = self.region;
        ((x0..x1).contains(&x) && (y0..y1).contains(&y)).then(|| usize::try_from((y - y0) * (x1 - x0) + x - x0).ok())?
    }

    fn set(&mut self, x: i64, y: i64, v: S) {
        if let Some(i) = self.at(x, y) {
            self.changed[i] = Some(v);
        }
    }

    fn sample(&self, x: i64, y: i64) -> Result<S> {
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
    /// Tiles made or made again (elevation and height ranges, imagery).
    pub made: u64,
}

/// Adds `elevation` and `texture` rasters to the collection `base` (see the module;
/// `reader` has it open), written to `out` (`base` itself: in place): the heights first,
/// then the imagery over what they made.
///
/// # Errors
/// [`Error::Input`] naming the base or a raster: a raster as coarse as its layer's base
/// level, one over tiles the layer's finer levels already hold, heights the archive's
/// encoding cannot hold, imagery over a layer of one resolution or stored lossy; as
/// [`crate::update`].
pub(crate) fn update_collection(
    reader: Reader<MmapSource>,
    base: &Path,
    elevation: &[PathBuf],
    texture: &[PathBuf],
    blend: Option<Blend>,
    out: &Path,
    progress: &dyn Progress,
) -> Result<CollectionUpdate> {
    let heights =
        if elevation.is_empty() { None } else { Some(update_heights(reader, base, elevation, blend, out, progress)?) };
    if texture.is_empty() {
        return heights.ok_or(Error::NothingToTile);
    }
    // The imagery over the archive the heights were added to (in place there).
    let from = if heights.is_some() { out } else { base };
    let reader = Reader::open_mmap(from).map_err(|e| Error::input(from, format!("cannot open archive: {e}")))?;
    let imagery = update_imagery(reader, from, texture, blend, out, progress)?;
    Ok(CollectionUpdate { made: imagery.made + heights.map_or(0, |h| h.made), merge: imagery.merge })
}

/// A collection layer's grid, as the archive records it: the level-0 grid in its CRS, the
/// CRS, and the layer's base level (the first that covers the grid).
pub(crate) fn layer_grid(old: &Metadata, base: &Path, index: u8) -> Result<(GridSpec, String, u8)> {
    let bad = |why: String| Error::input(base, why);
    let layer = &old.layers[usize::from(index)];
    let extent = layer.extent.clone().ok_or_else(|| bad(format!("its {} layer records no extent", layer.name)))?;
    let base_lod = extent.whole_from().unwrap_or(0);
    let g = old.georeference.clone().ok_or_else(|| bad("it has no georeference".into()))?;
    let (Some(origin), Some(scale)) = (g.origin, g.scale) else {
        return Err(bad("its georeference has no origin and scale".into()));
    };
    let crs = g.definition.clone().or(g.crs.clone()).unwrap_or_default();
    let sample = layer.sample_spacing(0);
    let [w_m, h_m] = old.terrain.data_extent.ok_or_else(|| bad("it records no data extent".into()))?;
    #[expect(clippy::cast_possible_truncation, clippy::cast_sign_loss, reason = "a grid's samples")]
    let size = ((w_m / sample).round() as u32, (h_m / sample).round() as u32);
    Ok((GridSpec { origin, pixel: (sample * scale[0], sample * scale[1]), size }, crs, base_lod))
}

/// Adds `elevation` rasters to the heights of the collection `base`.
fn update_heights(
    reader: Reader<MmapSource>,
    base: &Path,
    elevation: &[PathBuf],
    blend: Option<Blend>,
    out: &Path,
    progress: &dyn Progress,
) -> Result<CollectionUpdate> {
    let old = reader.metadata().clone();
    let find = |kind: LayerKind| old.layers.iter().position(|l| l.kind == kind).and_then(|i| u8::try_from(i).ok());
    let index = find(LayerKind::Elevation).ok_or_else(|| Error::input(base, "it has no elevation layer"))?;
    let layer = old.layers[usize::from(index)].clone();
    let (grid, crs, base_lod) = layer_grid(&old, base, index)?;
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
    let folder = terrastream_pack::output_folder(out);
    let target = Target { reader: &reader, base, index, kind: LayerKind::Elevation, grid, base_lod };
    let c = target.collection(&whole, blend)?;
    let metadata = target.metadata(&c);
    let encoding = layer.elevation.ok_or(Error::NothingToTile)?;
    let stored = Stored::new(&reader, index, grid.size, Box::new(move |_, raw| Ok(decode_heights(raw, &encoding))));
    let heights = HeightEncoder::new(&metadata, index, find(LayerKind::HeightRange))?;
    let encoding = heights.encoding;
    let quantize = move |row: &mut [f32]| quantize_heights(row, &encoding);
    let mut spool = Spool::new(&folder)?;
    let encode_tile = |key: TileKey, samples: &[f32], _edge: usize| heights.encode(key, samples);
    let remade = target.make(&c, &metadata, &stored, &open, Some(&quantize), &encode_tile, &mut spool, progress)?;
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
    drop(stored);
    written(spool, &metadata, reader, base, out, c.base, progress)
}

/// Adds `texture` rasters to the imagery of the collection `base` (its texture layer of
/// levels of different resolutions, stored as PNG or WebP).
fn update_imagery(
    reader: Reader<MmapSource>,
    base: &Path,
    texture: &[PathBuf],
    blend: Option<Blend>,
    out: &Path,
    progress: &dyn Progress,
) -> Result<CollectionUpdate> {
    let old = reader.metadata().clone();
    let bad = |why: &str| Error::input(base, why);
    let index = (old.layers.iter().position(|l| l.kind == LayerKind::Texture))
        .and_then(|i| u8::try_from(i).ok())
        .ok_or_else(|| bad("it has no texture layer to update"))?;
    let layer = old.layers[usize::from(index)].clone();
    if layer.extent.as_ref().is_none_or(|e| e.partial.is_empty()) {
        return Err(bad(
            "its imagery is of one resolution (its heights a collection): imagery is added to a collection of \
             images; tile every input again",
        ));
    }
    let format = TextureFormat::decodable(layer.format).ok_or_else(|| {
        Error::input(
            base,
            format!(
                "its texture is {:?}: an update completes new imagery from the stored tiles, which needs png or webp",
                layer.format
            ),
        )
    })?;
    let (grid, crs, base_lod) = layer_grid(&old, base, index)?;
    let open = |paths: Vec<PathBuf>, grid: GridSpec| super::open_images(paths, grid, &crs, false);
    let whole = open(texture.to_vec(), grid)?.ok_or(Error::NothingToTile)?;
    let folder = terrastream_pack::output_folder(out);
    let target = Target { reader: &reader, base, index, kind: LayerKind::Texture, grid, base_lod };
    let c = target.collection(&whole, blend)?;
    let metadata = target.metadata(&c);
    let edge = usize::try_from(layer.tile_resolution + 2 * u32::from(layer.border)).unwrap_or(0);
    let stored =
        Stored::new(&reader, index, grid.size, Box::new(move |key, raw| decode_texture(key, raw, edge, format)));
    let mut spool = Spool::new(&folder)?;
    let encode_tile = |key: TileKey, pixels: &[[u8; 4]], edge: usize| -> Result<Vec<(TileKey, Vec<u8>)>> {
        Ok(vec![(key, encode_texture(key, pixels, edge, format, crate::tile::ZSTD_LEVEL)?)])
    };
    target.make(&c, &metadata, &stored, &open, None, &encode_tile, &mut spool, progress)?;
    drop(stored);
    written(spool, &metadata, reader, base, out, c.base, progress)
}

/// The tiles made (`spool`) written over `base` to `out`, with `metadata`.
fn written(
    spool: Spool,
    metadata: &Metadata,
    reader: Reader<MmapSource>,
    base: &Path,
    out: &Path,
    base_lod: u8,
    progress: &dyn Progress,
) -> Result<CollectionUpdate> {
    let made = spool.tiles() as u64;
    let folder = terrastream_pack::output_folder(out);
    let changes = tempfile::Builder::new()
        .prefix(".update-")
        .suffix(".tspack")
        .tempdir_in(&folder)
        .map_err(|e| Error::file(&folder, e))?;
    let path = changes.path().join("changes.tspack");
    write_spool(spool, metadata, &path, false, progress, &crate::phases::Phases::start())?;
    drop(reader);
    let merge = crate::edit::update::replace_tiles(base, path, out, metadata, progress)?;
    tracing::info!(made, "new inputs added below LOD {base_lod}");
    Ok(CollectionUpdate { merge, made })
}

/// A collection layer an update adds to: the archive, the layer, its LOD-0 grid and its
/// base level.
struct Target<'r> {
    reader: &'r Reader<MmapSource>,
    base: &'r Path,
    index: u8,
    kind: LayerKind,
    grid: GridSpec,
    base_lod: u8,
}

impl Target<'_> {
    /// The collection of the new inputs (`whole`, on the layer's grid) below the base:
    /// refused where one is no finer than the base, or reaches tiles the layer holds.
    fn collection<K: MosaicKind>(&self, whole: &Mosaic<K>, blend: Option<Blend>) -> Result<Collection> {
        let old = self.reader.metadata();
        let layer = &old.layers[usize::from(self.index)];
        let finest = self.grid.pixel.0.min(self.grid.pixel.1);
        let mut inputs: Vec<CollectionInput> = vec![];
        for InputLayout { path, spacing, columns, rows } in whole.layout() {
            let depth = depth_of(spacing, finest);
            if depth >= self.base_lod {
                return Err(Error::input(
                    &path,
                    format!(
                        "reaches LOD {depth}, no finer than {}'s base (LOD {}): update adds finer surveys; tile every \
                         input again",
                        self.base.display(),
                        self.base_lod
                    ),
                ));
            }
            inputs.push(CollectionInput { path, spacing, depth, columns, rows });
        }
        let levels = super::sparse_levels(&inputs, layer, self.base_lod);
        // The band the archive's surveys were joined with, unless another is asked for.
        let texture = self.kind == LayerKind::Texture;
        let recorded = old.sources.iter().filter(|s| (s.layer.as_deref() == Some("texture")) == texture);
        let blend = match (blend, recorded.filter_map(|s| s.blend).next()) {
            (None, Some(recorded)) => recorded,
            (asked, _) => super::blend_samples(asked.unwrap_or_default(), finest),
        };
        let c = Collection { inputs, base: self.base_lod, levels, grid: self.grid, blend, kind: self.kind };
        for level in &c.levels {
            for &(x, y) in &level.tiles {
                if self.reader.locate(TileKey::new(self.index, level.lod, x, y)?)?.is_some() {
                    return Err(Error::input(
                        self.base,
                        format!(
                            "the new rasters reach tile {x}, {y} of LOD {} of its {} layer, which it holds already (an \
                             earlier survey's): tile every input again",
                            level.lod, layer.name
                        ),
                    ));
                }
            }
        }
        Ok(c)
    }

    /// The archive's metadata with `c`'s inputs and levels recorded, and its layers'
    /// finest data to be found anew from the tiles (as the writer does).
    fn metadata(&self, c: &Collection) -> Metadata {
        let mut metadata = self.reader.metadata().clone();
        record(c, &mut metadata);
        for layer in &mut metadata.layers {
            if let Some(e) = &mut layer.extent {
                e.detail = e.world;
                e.lon_lat = None;
                e.crs = None;
            }
        }
        metadata
    }

    /// Makes `c`'s levels (completed from the base level as `stored`), then the base level
    /// under them and every level above where they changed, into `spool`: the keys of the
    /// tiles made again from the base up.
    #[expect(clippy::too_many_arguments, reason = "the collection, how to read, round and encode, and where to")]
    fn make<K: MosaicKind>(
        &self,
        c: &Collection,
        metadata: &Metadata,
        stored: &Stored<'_, K::Value>,
        open: &(dyn Fn(Vec<PathBuf>, GridSpec) -> Result<Option<Mosaic<K>>> + Sync),
        quantize: Option<&QuantizeRow<'_, K::Value>>,
        encode_tile: &EncodeTile<'_, K::Value>,
        spool: &mut Spool,
        progress: &dyn Progress,
    ) -> Result<Vec<TileKey>>
    where
        K::Value: Pixel,
    {
        let (grid, base_lod, index) = (self.grid, self.base_lod, self.index);
        let layer = &metadata.layers[usize::from(index)];
        let sources_of = |lod: u8, corner: (u32, u32), g: &GridSpec| -> Result<LevelSources<'_, K>> {
            let fine = open(c.reaching(lod, corner, g, &|d| d == lod), *g)?;
            let shift = u32::from(base_lod - lod);
            let scale = f64::from(1u32 << lod);
            let (first, coarse) =
                coarse_grid(grid.origin, (grid.pixel.0 * scale, grid.pixel.1 * scale), corner, g.size, shift);
            let level = StoredLevel { stored, lod: base_lod, first, size: coarse.size };
            let level: Box<dyn CoarseRows<K::Value> + '_> = Box::new(level);
            Ok(LevelSources { fine, coarse: Some((level, shift, first)) })
        };
        let overrides =
            super::make_levels(c, metadata, index, encode_tile, quantize, spool, progress, &sources_of, None, None)?;

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
        let mut level = Level::new(stored, base_lod, region);
        for o in &overrides {
            for (r, row) in o.rows.iter().enumerate() {
                for (k, &v) in row.iter().enumerate() {
                    if v.has_data() {
                        level.set(to_i64(o.x0 + k), to_i64(o.y0 + r), v);
                    }
                }
            }
        }
        let mut remade: Vec<TileKey> = vec![];
        for lod in base_lod..layer.num_lods {
            if lod > base_lod {
                // This level's samples over the region, the 2x2 means of the level below,
                // as the pyramid makes them.
                region = [region[0] / 2, region[1] / 2, (region[2] + 1) / 2, (region[3] + 1) / 2];
                let (w, h) = stored.sizes[usize::from(lod)];
                let mut next = Level::new(stored, lod, region);
                let columns = 2 * region[0].max(0)..2 * region[2].min(w);
                for y in region[1].max(0)..region[3].min(h) {
                    let row = |j: i64| columns.clone().map(|x| level.sample(x, j)).collect::<Result<Vec<_>>>();
                    let mut half = halve_rows(&row(2 * y)?, &row(2 * y + 1)?);
                    if let Some(q) = quantize {
                        q(&mut half);
                    }
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
            let edge = res + 2 * border;
            for ty in ty0..=ty1.min(i64::from(ny) - 1) {
                for tx in tx0..=tx1.min(i64::from(nx) - 1) {
                    let mut samples = Vec::with_capacity(usize::try_from(edge * edge).unwrap_or(0));
                    let mut any = false;
                    for j in 0..edge {
                        for i in 0..edge {
                            let (x, y) = (tx * res + i - border, ty * res + j - border);
                            let v = level.sample(x, y)?;
                            let inner = (border..border + res).contains(&i) && (border..border + res).contains(&j);
                            any |= v.has_data() && inner;
                            samples.push(v);
                        }
                    }
                    let key = TileKey::new(index, lod, u32::try_from(tx).unwrap_or(0), u32::try_from(ty).unwrap_or(0))?;
                    if any {
                        for (k, bytes) in encode_tile(key, &samples, usize::try_from(edge).unwrap_or(0))? {
                            spool.add(metadata, k, &bytes)?;
                        }
                        remade.push(key);
                    }
                }
            }
        }
        Ok(remade)
    }
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
        if let (Some(extent), true) = (&mut layer.extent, c.makes(layer.kind)) {
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
