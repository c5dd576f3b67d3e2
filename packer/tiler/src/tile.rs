//! Running a plan: the sources through the pyramid into the archive.

use std::path::Path;

use terrastream_format::{LayerKind, Metadata, TileKey};
use terrastream_pack::progress::Progress;
use terrastream_pack::{WriteSummary, Writer, WriterOptions, zstd_compress};

use crate::encode::{encode_heights, encode_texture};
use crate::error::{Error, Result};
use crate::options::{TextureInput, TileOptions};
use crate::plan::plan;
use crate::pyramid::{self, Encode, Pixel, Pyramid, Resample, Spool};
use crate::raster::ElevationSource;

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
    let started = std::time::Instant::now();
    let plan = plan(elevation, texture.as_ref(), name, options, progress)?;
    tracing::debug!(elapsed = ?started.elapsed(), "planned (height range scanned)");
    let metadata = &plan.metadata;
    let folder = terrastream_pack::output_folder(out);
    let mut spool = Spool::new(&folder)?;
    progress.start("tile", plan.tiles());
    let level = WriterOptions::default().zstd_level;
    let find = |kind: LayerKind| metadata.layers.iter().position(|l| l.kind == kind).and_then(|i| u8::try_from(i).ok());

    if let (Some(source), Some(index)) = (elevation, find(LayerKind::Elevation)) {
        let encoding = metadata.layers[usize::from(index)].elevation.ok_or(Error::Pyramid {
            layer: index,
            lod: 0,
            reason: "the elevation layer has no encoding".into(),
        })?;
        let range = find(LayerKind::HeightRange);
        // Each tile's own stored range, gathered as tiles are encoded (8 bytes + key each).
        let ranges = std::sync::Mutex::new(Vec::<(TileKey, f32, f32)>::new());
        let encode = |key: TileKey, samples: &[f32], _edge: usize| -> Result<Vec<(TileKey, Vec<u8>)>> {
            let (raw, lo, hi) = encode_heights(samples, &encoding);
            if range.is_some() && lo <= hi {
                ranges.lock().unwrap_or_else(std::sync::PoisonError::into_inner).push((key, lo, hi));
            }
            let stored = zstd_compress(&raw, level).map_err(|e| Error::Encode { tile: key, reason: e.to_string() })?;
            Ok(vec![(key, stored)])
        };
        let size = plan.layers[usize::from(index)].size;
        let resample = Resample::new(source.size().0 as usize, size.0 as usize);
        run_pyramid(metadata, index, size, &encode, &mut spool, progress, |push| {
            source.rows(&mut |row| push(resample.row(row)))
        })?;
        if let Some(r) = range {
            let ranges = ranges.into_inner().unwrap_or_else(std::sync::PoisonError::into_inner);
            for (key, lo, hi) in conservative_ranges(ranges) {
                let bounds = [lo.to_le_bytes(), hi.to_le_bytes()].concat();
                spool.add(metadata, TileKey::new(r, key.lod(), key.x(), key.y())?, &bounds)?;
            }
        }
    }
    if let (Some(t), Some(index)) = (texture, find(LayerKind::Texture)) {
        let format = t.format;
        let encode = move |key: TileKey, pixels: &[[u8; 4]], edge: usize| -> Result<Vec<(TileKey, Vec<u8>)>> {
            let bytes = encode_texture(key, pixels, edge, format, level)?;
            Ok(vec![(key, bytes)])
        };
        let size = plan.layers[usize::from(index)].size;
        let resample = Resample::new(t.source.size().0 as usize, size.0 as usize);
        run_pyramid(metadata, index, size, &encode, &mut spool, progress, |push| {
            t.source.rows(&mut |row| push(resample.row(row)))
        })?;
    }
    tracing::debug!(elapsed = ?started.elapsed(), tiles = spool.tiles(), "tiles cut and encoded");
    // Tiles come already compressed: small batches are enough for the writer's hashing.
    let options = WriterOptions { batch_bytes: 4 << 20, ..WriterOptions::default() };
    let mut writer = Writer::create(out, plan.metadata.clone(), options)?;
    spool.drain_into(&mut writer, progress)?;
    tracing::debug!(elapsed = ?started.elapsed(), "tiles handed to the writer in archive order");
    let summary = writer.finish()?;
    tracing::debug!(elapsed = ?started.elapsed(), "archive written");
    Ok(summary)
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

/// Streams `read`'s rows through a pyramid for layer `index`. Reading (decompression,
/// conversion, resampling) runs on its own thread, overlapping the cutting and encoding,
/// with at most one band of LOD-0 rows (a row of tiles and its borders) between them: the
/// reader fills the next band while the pyramid cuts and encodes this one. (With fewer,
/// the reader stalls during each cut, and the encoders while it catches up.)
fn run_pyramid<S: Pixel>(
    metadata: &Metadata,
    index: u8,
    size: (u32, u32),
    encode: &Encode<'_, S>,
    spool: &mut Spool,
    progress: &dyn Progress,
    read: impl FnOnce(&mut dyn FnMut(Vec<S>) -> Result<()>) -> Result<()> + Send,
) -> Result<()> {
    let mut pyramid = Pyramid::new(metadata, index, size, encode, spool, progress)?;
    let (rows, received) = std::sync::mpsc::sync_channel::<Vec<S>>(pyramid.band_rows());
    std::thread::scope(|scope| {
        let reader = scope.spawn(move || {
            // A send fails only once the pyramid has stopped, with its own error.
            read(&mut |row| rows.send(row).map_err(|_| crate::error::interrupted()))
        });
        // Rows of tiles are cut on the pool while this thread halves the next rows.
        rayon::in_place_scope(|cuts| {
            let mut built =
                std::iter::from_fn(|| pyramid::receive(&received)).try_for_each(|row| pyramid.push(row, cuts));
            drop(received);
            let read = reader.join().unwrap_or(Err(Error::Panicked { thread: "raster reading" }));
            // The pyramid's error first (it stopped the reader); else the reader's.
            built = built.and(read);
            built?;
            pyramid.finish(cuts)
        })
    })
}
