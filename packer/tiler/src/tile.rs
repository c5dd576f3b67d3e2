//! Running a plan: the sources through the pyramid into the archive.

use std::path::Path;

use terrastream_format::{ElevationEncoding, LayerKind, Metadata, PayloadCompression, TileKey};
use terrastream_pack::progress::Progress;
use terrastream_pack::{WriteSummary, Writer, WriterOptions, compress_heights};

use crate::encode::{encode_heights, encode_texture, quantize_heights};
use crate::error::{Error, Result};
use crate::options::{ShardSpec, TextureInput, TileOptions};
use crate::phases::Phases;
use crate::plan::{Plan, estimated_encoding, holds, plan, set_height_range};
use crate::pyramid::{self, Encode, Pixel, Pyramid, Quantize, Resample, Spool, Window};
use crate::raster::{ElevationSource, KnownRange};
use crate::shard;

/// Packs an elevation raster into a pyramid archive at `out` (no texture: see
/// [`tile_terrain`]).
///
/// # Errors
/// As [`tile_terrain`].
pub fn tile_elevation(
    elevation: &dyn ElevationSource,
    name: &str,
    out: &Path,
    options: TileOptions,
    progress: &dyn Progress,
) -> Result<WriteSummary> {
    tile_terrain(Some(elevation), None, name, out, options, progress)
}

/// Packs an elevation raster and/or a texture image into one archive at `out`: the
/// elevation pyramid (layer 0, with its height-range layer last), the texture pyramid
/// (area-averaged LODs, the elevation's border width). With both, the texture covers the
/// elevation's extent; its grid is independent: its own resolution, its own tile size.
/// Nothing is written under `out` unless the whole archive is.
///
/// # Errors
/// Bad options, a texture whose aspect ratio differs from the elevation's by more than
/// 2 % ([`Error::Input`] naming it), unreadable input (named), writer and I/O errors,
/// an interrupted error (Ctrl-C).
pub fn tile_terrain(
    elevation: Option<&dyn ElevationSource>,
    texture: Option<TextureInput<'_>>,
    name: &str,
    out: &Path,
    options: TileOptions,
    progress: &dyn Progress,
) -> Result<WriteSummary> {
    tile_shard(elevation, texture, name, out, options, None, progress)
}

/// As [`tile_terrain`], or with `shard`, one shard of a sharded run: every layer's tiles
/// from LOD 0 up to its split LOD in the shard's band of tile rows, exactly the bytes a
/// whole run makes there ([`crate::merge`] makes the levels above from all shards).
///
/// # Errors
/// As [`tile_terrain`]; [`Error::InvalidOption`] for a shard out of range or a lossy texture
/// format with shards.
pub fn tile_shard(
    elevation: Option<&dyn ElevationSource>,
    texture: Option<TextureInput<'_>>,
    name: &str,
    out: &Path,
    options: TileOptions,
    shard: Option<ShardSpec>,
    progress: &dyn Progress,
) -> Result<WriteSummary> {
    let phases = Phases::start();
    if shard.is_none()
        && let Some(source) = elevation
        && source.given_height_range().is_none()
        && let Some(estimate) = source.height_range_estimate()?
    {
        if let Some(summary) = tile_on_estimate(source, estimate, texture, name, out, options, progress, &phases)? {
            return Ok(summary);
        }
        tracing::info!(
            "{}: heights outside what the estimated range's encoding holds: scanning the range, tiling again",
            source.path().display()
        );
    }
    let mut plan = plan(elevation, texture.as_ref(), name, options, progress)?;
    phases.mark("planned (height range scanned)");
    let windows = match shard {
        Some(spec) => {
            if let Some(t) = texture.as_ref().filter(|t| !t.format.lossless()) {
                return Err(Error::option("--texture-format", t.format.name(), "png or webp with --shard"));
            }
            let weight = shard::data_weight(&plan, elevation, texture.as_ref());
            let (info, windows) = shard::windows(&plan, &spec, &weight)?;
            plan.metadata.shard = Some(info);
            windows
        }
        None => full_windows(&plan),
    };
    tile_planned(elevation, texture, &plan, &windows, out, true, progress, &phases)
}

/// A whole run on the encoding of the elevation's estimated height range (see
/// [`crate::plan::chosen_encoding`]), its range tracked as rows are read instead of
/// scanned first: the archive, or None (nothing written) as soon as a height falls
/// outside what that encoding holds.
#[expect(clippy::too_many_arguments, reason = "tile_shard's inputs, and the estimate")]
fn tile_on_estimate(
    source: &dyn ElevationSource,
    estimate: (f32, f32),
    texture: Option<TextureInput<'_>>,
    name: &str,
    out: &Path,
    options: TileOptions,
    progress: &dyn Progress,
    phases: &Phases,
) -> Result<Option<WriteSummary>> {
    let widened = (f64::from(estimate.0), f64::from(estimate.1));
    let tracked = KnownRange::estimated(source, estimate, holds(&estimated_encoding(options.storage, widened)));
    let mut plan = plan(Some(&tracked), texture.as_ref(), name, options, progress)?;
    phases.mark(&format!("planned (height range estimated: {} to {})", estimate.0, estimate.1));
    let windows = full_windows(&plan);
    let folder = terrastream_pack::output_folder(out);
    let spool = match cut_planned(&folder, Some(&tracked), texture, &plan, &windows, progress) {
        Err(_) if tracked.went_outside() => return Ok(None),
        cut => cut?,
    };
    let seen = tracked.seen().ok_or_else(|| Error::input(source.path(), "the raster holds no data"))?;
    set_height_range(&mut plan.metadata.terrain, (f64::from(seen.0), f64::from(seen.1)));
    phases.mark(&format!("{} tiles cut and encoded", spool.tiles()));
    let written = write_spool(spool, &plan.metadata, out, true, progress, phases)?;
    phases.finish();
    Ok(Some(written))
}

/// Every level of every layer of `plan`.
pub(crate) fn full_windows(plan: &Plan) -> Vec<Window> {
    plan.metadata.layers.iter().zip(&plan.layers).map(|(l, p)| Window::full(l.num_lods, p.size.1 as usize)).collect()
}

/// `key` moved by a plan's LOD-0 tile offset (see [`crate::plan::LayerPlan::offset`]).
fn shifted(key: TileKey, (dx, dy): (u32, u32)) -> Result<TileKey> {
    if (dx, dy) == (0, 0) {
        return Ok(key);
    }
    let moved = |v: u32, d: u32| v.saturating_add(d >> key.lod());
    Ok(TileKey::new(key.layer(), key.lod(), moved(key.x(), dx), moved(key.y(), dy))?)
}

/// Runs `plan` over the sources, each layer's pyramid limited to its window (in layer
/// order), into the archive at `out`.
#[expect(clippy::too_many_arguments, reason = "the inputs, the plan, and where and how to write")]
pub(crate) fn tile_planned(
    elevation: Option<&dyn ElevationSource>,
    texture: Option<TextureInput<'_>>,
    plan: &Plan,
    windows: &[Window],
    out: &Path,
    durable: bool,
    progress: &dyn Progress,
    phases: &Phases,
) -> Result<WriteSummary> {
    let spool = cut_planned(&terrastream_pack::output_folder(out), elevation, texture, plan, windows, progress)?;
    phases.mark(&format!("{} tiles cut and encoded", spool.tiles()));
    let written = write_spool(spool, &plan.metadata, out, durable, progress, phases)?;
    phases.finish();
    Ok(written)
}

/// Cuts and encodes `plan`'s tiles (as [`tile_planned`]) into a spool in `folder`.
pub(crate) fn cut_planned(
    folder: &Path,
    elevation: Option<&dyn ElevationSource>,
    texture: Option<TextureInput<'_>>,
    plan: &Plan,
    windows: &[Window],
    progress: &dyn Progress,
) -> Result<Spool> {
    let metadata = &plan.metadata;
    let mut spool = Spool::new(folder)?;
    progress.start("tile", plan.tiles());
    let find = |kind: LayerKind| metadata.layers.iter().position(|l| l.kind == kind).and_then(|i| u8::try_from(i).ok());

    if let (Some(source), Some(index)) = (elevation, find(LayerKind::Elevation)) {
        let heights = HeightEncoder::new(metadata, index, find(LayerKind::HeightRange))?;
        let offset = plan.layers[usize::from(index)].offset;
        let encode = |key: TileKey, samples: &[f32], _edge: usize| heights.encode(shifted(key, offset)?, samples);
        let window = &windows[usize::from(index)];
        let size = plan.layers[usize::from(index)].size;
        let resample = Resample::new(source.size().0 as usize, size.0 as usize);
        let quantize = |row: &mut [f32]| quantize_heights(row, &heights.encoding);
        let rows = window_rows(window);
        // Rows resampled (or handed over) where the source makes them, on every core.
        let map = |row: &[f32]| resample.row(row);
        let map: Option<&crate::raster::RowMap<'_>> = (!resample.is_identity()).then_some(&map);
        run_pyramid(metadata, index, size, window, &encode, Some(&quantize), &mut spool, progress, |push| {
            Ok(source.rows_mapped(rows, map, &mut |row, _| Ok(push(row)?))?)
        })?;
        heights.finish(metadata, Vec::new(), &mut spool)?;
    }
    if let Some(t) = texture {
        cut_texture(t, plan, windows, &mut spool, progress)?;
    }
    Ok(spool)
}

/// Cuts and encodes the texture layer's tiles of `plan` (in its window) into `spool`.
pub(crate) fn cut_texture(
    t: TextureInput<'_>,
    plan: &Plan,
    windows: &[Window],
    spool: &mut Spool,
    progress: &dyn Progress,
) -> Result<()> {
    let metadata = &plan.metadata;
    let Some(index) =
        metadata.layers.iter().position(|l| l.kind == LayerKind::Texture).and_then(|i| u8::try_from(i).ok())
    else {
        return Ok(());
    };
    let format = t.format;
    let offset = plan.layers[usize::from(index)].offset;
    let encode = move |key: TileKey, pixels: &[[u8; 4]], edge: usize| -> Result<Vec<(TileKey, Vec<u8>)>> {
        let key = shifted(key, offset)?;
        Ok(vec![(key, encode_texture(key, pixels, edge, format, ZSTD_LEVEL)?)])
    };
    let size = plan.layers[usize::from(index)].size;
    let resample = Resample::new(t.source.size().0 as usize, size.0 as usize);
    let window = &windows[usize::from(index)];
    let rows = window_rows(window);
    run_pyramid(metadata, index, size, window, &encode, None, spool, progress, |push| {
        Ok(t.source.rows_in(rows, &mut |row| Ok(push(resample.row(row))?))?)
    })?;
    Ok(())
}

/// Writes the spooled tiles into the archive at `out`, with `metadata`.
pub(crate) fn write_spool(
    spool: Spool,
    metadata: &Metadata,
    out: &Path,
    durable: bool,
    progress: &dyn Progress,
    phases: &Phases,
) -> Result<WriteSummary> {
    // Tiles come already compressed: small batches are enough for the writer's hashing.
    let options = WriterOptions { batch_bytes: 4 << 20, durable, ..WriterOptions::default() };
    let mut writer = Writer::create(out, metadata.clone(), options)?;
    spool.drain_into(&mut writer, progress)?;
    phases.mark("tiles handed to the writer in archive order");
    let summary = writer.finish()?;
    phases.mark("archive written");
    Ok(summary)
}

/// A window's LOD-0 rows as a source's row range.
fn window_rows(window: &Window) -> std::ops::Range<u32> {
    let at = |n: usize| u32::try_from(n).unwrap_or(u32::MAX);
    at(window.rows.start)..at(window.rows.end)
}

/// The zstd level of BC texture tiles (the writer's default); elevation tiles: see
/// [`compress_heights`].
pub(crate) const ZSTD_LEVEL: i32 = 3;

/// Encodes elevation tiles, gathering each one's stored height range for the height-range
/// layer (8 bytes + key a tile) until [`HeightEncoder::finish`] spools that layer.
pub(crate) struct HeightEncoder {
    pub(crate) encoding: ElevationEncoding,
    /// The elevation layer's compression, and its stored tiles' edge.
    compression: PayloadCompression,
    edge: usize,
    range: Option<u8>,
    ranges: std::sync::Mutex<Vec<(TileKey, f32, f32)>>,
}

impl HeightEncoder {
    /// For elevation layer `index` of `metadata`, and its height-range layer `range`.
    pub(crate) fn new(metadata: &Metadata, index: u8, range: Option<u8>) -> Result<Self> {
        let layer = &metadata.layers[usize::from(index)];
        let encoding = layer.elevation.ok_or(Error::Pyramid {
            layer: index,
            lod: 0,
            reason: "the elevation layer has no encoding".into(),
        })?;
        Ok(Self {
            encoding,
            compression: layer.compression,
            edge: layer.stored_edge(),
            range,
            ranges: std::sync::Mutex::new(Vec::new()),
        })
    }

    /// One cut tile -> its stored bytes (u16 or f32, compressed as the layer says).
    pub(crate) fn encode(&self, key: TileKey, samples: &[f32]) -> Result<Vec<(TileKey, Vec<u8>)>> {
        thread_local! {
            /// The raw samples of this thread's last tile: reused, not zeroed anew a tile.
            static RAW: std::cell::RefCell<Vec<u8>> = const { std::cell::RefCell::new(Vec::new()) };
        }
        let (stored, lo, hi) = RAW.with_borrow_mut(|raw| {
            let (lo, hi) = encode_heights(samples, &self.encoding, raw);
            (compress_heights(self.compression, raw, self.edge), lo, hi)
        });
        if self.range.is_some() && lo <= hi {
            self.ranges.lock().unwrap_or_else(std::sync::PoisonError::into_inner).push((key, lo, hi));
        }
        let stored = stored.map_err(|e| Error::Encode { tile: key, reason: e.to_string() })?;
        Ok(vec![(key, stored)])
    }

    /// Spools the height-range tiles of the tiles encoded: each widened by its children's
    /// (theirs, and `below`: ranges of tiles made elsewhere, such as a shard's split LOD,
    /// which are not spooled again).
    pub(crate) fn finish(self, metadata: &Metadata, below: Vec<(TileKey, f32, f32)>, spool: &mut Spool) -> Result<()> {
        let Some(r) = self.range else { return Ok(()) };
        let mut ranges = self.ranges.into_inner().unwrap_or_else(std::sync::PoisonError::into_inner);
        let ours: std::collections::HashSet<TileKey> = ranges.iter().map(|(k, ..)| *k).collect();
        ranges.extend(below);
        for (key, lo, hi) in conservative_ranges(ranges).into_iter().filter(|(k, ..)| ours.contains(k)) {
            let bounds = [lo.to_le_bytes(), hi.to_le_bytes()].concat();
            spool.add(metadata, TileKey::new(r, key.lod(), key.x(), key.y())?, &bounds)?;
        }
        Ok(())
    }
}

/// Height ranges for culling: a tile's range must hold every height drawn anywhere under
/// it, at any LOD. A coarser tile's own samples are averages, which never reach its finer
/// tiles' extremes, so each tile's range is widened by its children's, finest LOD first.
fn conservative_ranges(mut ranges: Vec<(TileKey, f32, f32)>) -> Vec<(TileKey, f32, f32)> {
    ranges.sort_unstable_by_key(|(k, ..)| (k.lod(), k.y(), k.x()));
    let index: std::collections::HashMap<TileKey, usize> =
        ranges.iter().enumerate().map(|(i, (k, ..))| (*k, i)).collect();
    for i in 0..ranges.len() {
        let (key, lo, hi) = ranges[i];
        if let Some(&p) = key.parent().as_ref().and_then(|p| index.get(p)) {
            let parent = &mut ranges[p];
            parent.1 = parent.1.min(lo);
            parent.2 = parent.2.max(hi);
        }
    }
    ranges
}

/// LOD-0 rows handed from the reading thread to the pyramid at once.
const ROWS_A_BATCH: usize = 128;

/// Streams `read`'s rows through a pyramid for layer `index`. Reading (decompression,
/// conversion, resampling) runs on its own thread, overlapping the cutting and encoding,
/// with at most one band of LOD-0 rows (a row of tiles and its borders) between them: the
/// reader fills the next band while the pyramid cuts and encodes this one. (With fewer,
/// the reader stalls during each cut, and the encoders while it catches up.)
#[expect(clippy::too_many_arguments, reason = "one layer's pyramid run, all of it")]
pub(crate) fn run_pyramid<S: Pixel>(
    metadata: &Metadata,
    index: u8,
    size: (u32, u32),
    window: &Window,
    encode: &Encode<'_, S>,
    quantize: Option<&Quantize<'_, S>>,
    spool: &mut Spool,
    progress: &dyn Progress,
    read: impl FnOnce(&mut dyn FnMut(Vec<S>) -> Result<()>) -> Result<()> + Send,
) -> Result<()> {
    if window.band.is_empty() {
        return Ok(());
    }
    let mut pyramid = Pyramid::window(metadata, index, size, window, encode, spool, progress)?;
    if let Some(q) = quantize {
        pyramid = pyramid.with_quantize(q);
    }
    // Rows travel in batches, which the pyramid rounds and halves in parallel.
    let (rows, received) = std::sync::mpsc::sync_channel::<Vec<Vec<S>>>(pyramid.band_rows().div_ceil(ROWS_A_BATCH));
    std::thread::scope(|scope| {
        let reader = scope.spawn(move || {
            // A send fails only once the pyramid has stopped, with its own error.
            let send = |batch| rows.send(batch).map_err(|_| crate::error::interrupted());
            let mut batch = Vec::with_capacity(ROWS_A_BATCH);
            read(&mut |row| {
                batch.push(row);
                if batch.len() == ROWS_A_BATCH {
                    send(std::mem::replace(&mut batch, Vec::with_capacity(ROWS_A_BATCH)))?;
                }
                Ok(())
            })?;
            if batch.is_empty() { Ok(()) } else { send(batch) }
        });
        // Rows of tiles are cut on the pool while this thread halves the next rows.
        rayon::in_place_scope(|cuts| {
            let mut built =
                std::iter::from_fn(|| pyramid::receive(&received)).try_for_each(|batch| pyramid.push_rows(batch, cuts));
            drop(received);
            let read = reader.join().unwrap_or(Err(Error::Panicked { thread: "raster reading" }));
            // The pyramid's error first (it stopped the reader); else the reader's.
            built = built.and(read);
            built?;
            pyramid.finish(cuts)
        })
    })
}
