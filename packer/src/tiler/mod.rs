//! Source rasters -> a LOD pyramid in an archive (`terrastream tile`).
//!
//! Inputs are read a band of rows at a time ([`source`]): an elevation raster (GeoTIFF of
//! numbers, or a PNG whose pixels encode heights), an optional texture image, or a texture
//! alone. Each is resampled along x to square samples in metres when its pixels are more
//! than 1 % from square (a geographic raster is converted to metres at its centre
//! latitude), then streamed through a [`pyramid::Pyramid`]: LOD 0 keeps the source's
//! spacing; each coarser LOD averages 2x2 of the previous one (ignoring nodata for heights,
//! weighted by alpha for imagery); odd edges are padded with no data; tiles that hold only
//! no data are left missing. Only a band of rows per level is held, so memory does not grow
//! with the raster's height; it grows with its width (about `2 x width x (tile + 2 x
//! border + 1)` samples for all levels together) and with the tile count (the spool's index,
//! 24 bytes a tile).
//!
//! Elevation is stored losslessly (quantized u16 with a power-of-two step that keeps integer
//! sources exact at LOD 0, or f32; zstd) beside a height-range layer: each elevation tile's
//! lowest and highest height, for culling before the tile is loaded. Imagery is stored as
//! PNG, JPEG, lossless WebP, or GPU-ready BC1/BC7 blocks (zstd).

mod bc;
pub mod pyramid;
pub mod source;

use std::path::Path;

pub use source::{
    ElevationFile, ElevationSource, Image, ImageFile, ImageSource, ImageWindow, Raster, open_elevation, open_image,
    read_geotiff, read_image,
};

use crate::compression::zstd_compress;
use crate::error::{Error, Result};
use crate::key::TileKey;
use crate::metadata::{
    ElevationEncoding, ElevationScheme, Layer, LayerKind, Metadata, PayloadCompression, TileFormat, levels_to_one,
};
use crate::progress::Progress;
use crate::writer::{WriteSummary, Writer, WriterOptions};
use pyramid::{Encode, Pyramid, Resample, Sample, Spool};

/// How to store elevation samples.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub enum ElevationStorage {
    /// Quantized u16 when the range allows a step of at most 1/16 unit, else f32.
    #[default]
    Auto,
    /// Quantized u16.
    U16,
    /// f32.
    F32,
}

/// Options of [`tile_terrain`].
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct TileOptions {
    /// Samples per tile edge, borders excluded.
    pub tile_size: u32,
    /// Samples copied from the neighbours on each side.
    pub border: u8,
    /// Sample storage.
    pub storage: ElevationStorage,
}

impl Default for TileOptions {
    fn default() -> Self {
        Self { tile_size: 256, border: 1, storage: ElevationStorage::Auto }
    }
}

/// How texture tiles are stored.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub enum TextureFormat {
    /// Lossless PNG (RGB when opaque): exact, what browsers decode.
    #[default]
    Png,
    /// JPEG at a quality of 1..=100: smallest over a network; no alpha (holes turn black).
    Jpeg(u8),
    /// Lossless WebP.
    Webp,
    /// BC1 blocks + zstd: 4 bits a texel on the GPU, cut-out alpha; no CPU decode.
    Bc1,
    /// BC7 blocks + zstd: 8 bits a texel on the GPU, smooth alpha; no CPU decode.
    Bc7,
}

impl TextureFormat {
    fn tile_format(self) -> TileFormat {
        match self {
            Self::Png => TileFormat::Png,
            Self::Jpeg(_) => TileFormat::Jpeg,
            Self::Webp => TileFormat::Webp,
            Self::Bc1 => TileFormat::Bc1,
            Self::Bc7 => TileFormat::Bc7,
        }
    }

    fn compression(self) -> PayloadCompression {
        match self {
            Self::Bc1 | Self::Bc7 => PayloadCompression::Zstd,
            _ => PayloadCompression::None,
        }
    }

    /// Typical stored bytes per texel (for `--dry-run`'s estimate).
    fn typical_bytes_per_texel(self) -> f64 {
        match self {
            Self::Png | Self::Webp => 1.8,
            Self::Jpeg(_) => 0.3,
            Self::Bc1 => 0.4,
            Self::Bc7 => 0.8,
        }
    }
}

/// The texture input of [`tile_terrain`].
#[derive(Clone, Copy)]
pub struct TextureInput<'a> {
    /// The image. With elevation it is stretched over the elevation's extent.
    pub source: &'a dyn ImageSource,
    /// Pixels per tile edge, borders excluded.
    pub tile_size: u32,
    /// Tile encoding.
    pub format: TextureFormat,
    /// Metres per pixel when there is no elevation to take the extent from.
    pub pixel_size: f64,
}

/// Do the elevation and the image both lie, by their georeference, over the same area of
/// one CRS (each edge within 2% of the extent)?
fn same_crs_extent(elevation: &dyn ElevationSource, image: &dyn ImageSource) -> bool {
    // The CRS, and west, north, width and height in its units.
    fn extent(placed: Option<(&str, [f64; 2], (f64, f64))>, (w, h): (u32, u32)) -> Option<(&str, [f64; 4])> {
        placed.map(|(crs, origin, pixel)| (crs, [origin[0], origin[1], f64::from(w) * pixel.0, f64::from(h) * pixel.1]))
    }
    let (Some((a_crs, a)), Some((b_crs, b))) = (
        extent(source::crs_placement(elevation.georeference(), elevation.crs_pixel_size()), elevation.size()),
        extent(source::crs_placement(image.georeference(), image.crs_pixel_size()), image.size()),
    ) else {
        return false;
    };
    let close = |x: f64, y: f64, span: f64| (x - y).abs() <= 0.02 * span;
    a_crs == b_crs
        && close(a[0], b[0], a[2])
        && close(a[0] + a[2], b[0] + b[2], a[2])
        && close(a[1], b[1], a[3])
        && close(a[1] - a[3], b[1] - b[3], a[3])
}

/// What [`plan`] decides: the metadata (grids, LOD counts, encodings) and the work.
#[derive(Clone, Debug)]
pub struct Plan {
    /// The archive's metadata.
    pub metadata: Metadata,
    /// Per layer, in the metadata's order: LOD-0 size in samples after squaring (rows are
    /// resampled to its width), tiles to cut (an upper bound: those with no data are left
    /// out) and typical stored bytes.
    pub layers: Vec<LayerPlan>,
}

/// One layer of a [`Plan`].
#[derive(Clone, Debug, PartialEq)]
pub struct LayerPlan {
    /// Samples across and down at LOD 0.
    pub size: (u32, u32),
    /// Tiles with data or not, every LOD.
    pub tiles: u64,
    /// A rough size of the stored tiles (typical compression ratios; within about 2x).
    pub estimated_bytes: u64,
}

impl Plan {
    /// Typical archive size: the layers' estimates.
    pub fn estimated_bytes(&self) -> u64 {
        self.layers.iter().map(|l| l.estimated_bytes).sum()
    }

    /// Tiles to cut, all layers.
    pub fn tiles(&self) -> u64 {
        self.layers.iter().map(|l| l.tiles).sum()
    }
}

/// Tiles over `size` samples at every LOD of a layer.
fn tiles_over(size: (u32, u32), res: u32, lods: u8) -> u64 {
    (0..lods)
        .map(|lod| {
            let side = |n: u32| u64::from(n.div_ceil(1 << lod).max(1).div_ceil(res));
            side(size.0) * side(size.1)
        })
        .sum()
}

/// The elevation's height range (a pass over the raster, making no rows where the source can).
fn height_range(elevation: &dyn ElevationSource, progress: &dyn Progress) -> Result<(f64, f64)> {
    progress.start("scan", u64::from(elevation.size().1));
    let mut told = 0u32;
    let (min, max) = elevation.height_range(&mut |rows| {
        if rows / 64 != told / 64 {
            progress.check()?;
        }
        progress.advance(u64::from(rows.saturating_sub(told)));
        told = rows;
        Ok(())
    })?;
    let (min, max) = (f64::from(min), f64::from(max));
    if !min.is_finite() {
        return Err(Error::input(elevation.path(), "the raster holds no data (every sample is nodata)"));
    }
    Ok((min, max))
}

/// The lowest and highest of `values`, NaN (nodata) skipped; (inf, -inf) if there are none.
/// Eight independent lanes of `f32::min`/`max` (which skip a NaN): LLVM vectorizes these
/// into min/max instructions, where one running minimum is a serial chain and a
/// compare-and-select per lane compiles to shuffles (measured: 1.5x slower).
fn min_max(values: &[f32]) -> (f32, f32) {
    let (mut lo, mut hi) = ([f32::INFINITY; 8], [f32::NEG_INFINITY; 8]);
    let chunks = values.chunks_exact(8);
    let rest = chunks.remainder();
    for chunk in chunks {
        for i in 0..8 {
            lo[i] = lo[i].min(chunk[i]);
            hi[i] = hi[i].max(chunk[i]);
        }
    }
    for (i, &v) in rest.iter().enumerate() {
        lo[i] = lo[i].min(v);
        hi[i] = hi[i].max(v);
    }
    (lo.into_iter().fold(f32::INFINITY, f32::min), hi.into_iter().fold(f32::NEG_INFINITY, f32::max))
}

/// Decides grids, LOD counts and encodings: everything but the tiles. Reads the elevation
/// once for its height range.
///
/// # Errors
/// Bad options; neither elevation nor texture; a texture whose extent differs from the
/// elevation's ([`Error::Input`] naming it); unreadable input.
pub fn plan(
    elevation: Option<&dyn ElevationSource>,
    texture: Option<&TextureInput<'_>>,
    name: &str,
    options: TileOptions,
    progress: &dyn Progress,
) -> Result<Plan> {
    let res = options.tile_size;
    if !(16..=4096).contains(&res) || options.border > 16 {
        return Err(Error::Writer(format!("tile size {res} (16..=4096) / border {} (0..=16)", options.border)));
    }
    let mut layers = Vec::new();
    let mut plans = Vec::new();
    let mut metadata = Metadata::new(name, Vec::new());
    // The data's extent in metres, when the elevation gives it.
    let mut extent = None;
    if let Some(e) = elevation {
        let (w, h) = e.size();
        if w == 0 || h == 0 {
            return Err(Error::input(e.path(), format!("the raster is empty ({w}x{h})")));
        }
        let (sx, sy) = e.spacing();
        let ratio = sx / sy;
        let (width, spacing) = if (ratio - 1.0).abs() < 0.01 {
            (w, (sx * sy).sqrt())
        } else {
            #[expect(clippy::cast_possible_truncation, clippy::cast_sign_loss, reason = "a sane sample count")]
            let width = ((f64::from(w) * ratio).round() as u32).max(1);
            (width, sy)
        };
        extent = Some((f64::from(width) * spacing, f64::from(h) * spacing, f64::from(w) / f64::from(h)));
        let (min, max) = height_range(e, progress)?;
        let span = max - min;
        // Quantization step: a power of two, at most 1/16, small enough for the span.
        let step = (0..=8).map(|k| f64::from(1u32 << k) / 16.0).find(|s| span / s < 65_000.0);
        let encoding = match (options.storage, step) {
            (ElevationStorage::F32, _) | (ElevationStorage::Auto, None) => {
                ElevationEncoding { scheme: ElevationScheme::Float32, scale: 1.0, offset: 0.0, nodata: None }
            }
            (_, step) => {
                let step = step.unwrap_or(span / 65_000.0);
                // 0 is nodata; heights start at 1.
                let offset = (min / step).floor() * step - step;
                ElevationEncoding { scheme: ElevationScheme::QuantizedU16, scale: step, offset, nodata: Some(0.0) }
            }
        };
        let (nx, ny) = (width.div_ceil(res), h.div_ceil(res));
        let float = encoding.scheme == ElevationScheme::Float32;
        let layer = Layer {
            name: "elevation".into(),
            kind: LayerKind::Elevation,
            format: if float { TileFormat::RawF32 } else { TileFormat::RawU16 },
            compression: PayloadCompression::Zstd,
            tile_resolution: res,
            border: options.border,
            num_x_tiles: nx,
            num_y_tiles: ny,
            num_lods: levels_to_one(nx.max(ny)),
            tile_world_size: f64::from(res) * spacing,
            elevation: Some(encoding),
        };
        let tiles = tiles_over((width, h), res, layer.num_lods);
        let edge = u64::from(res + 2 * u32::from(options.border));
        #[expect(
            clippy::cast_possible_truncation,
            clippy::cast_sign_loss,
            clippy::cast_precision_loss,
            reason = "an estimate"
        )]
        let estimated = (tiles as f64 * (edge * edge) as f64 * if float { 2.4 } else { 1.0 }) as u64;
        plans.push(LayerPlan { size: (width, h), tiles, estimated_bytes: estimated });
        let t = &mut metadata.terrain;
        t.min_elevation = min;
        t.max_elevation = max;
        t.displacement = span;
        t.elevation_range = span;
        t.base_tile_size = spacing;
        t.high_detail_range = spacing * 64.0;
        t.num_detail_levels = u32::from(layer.num_lods) + 6;
        metadata.georeference = e.georeference().cloned();
        layers.push(layer);
    }
    if let Some(t) = texture {
        let path = t.source.path();
        let (w, h) = t.source.size();
        if w == 0 || h == 0 {
            return Err(Error::input(path, format!("the image is empty ({w}x{h})")));
        }
        if !(16..=4096).contains(&t.tile_size) {
            return Err(Error::Writer(format!("texture tile size {} (16..=4096)", t.tile_size)));
        }
        if let TextureFormat::Jpeg(q) = t.format {
            if !(1..=100).contains(&q) {
                return Err(Error::Writer(format!("JPEG quality {q} (1..=100)")));
            }
        }
        let (fw, fh) = (f64::from(w), f64::from(h));
        let (width, world_width) = match extent {
            Some((ex, ez, grid_aspect)) => {
                // The texture covers the elevation's area on the same grid (both geographic,
                // say: its pixels have the DEM's pixel shape) or in metres (square pixels).
                let near = |a: f64, b: f64| (a / b - 1.0).abs() <= 0.02;
                // Or both say where they lie, in one CRS, and cover the same area there
                // (pixels of any shape: degrees square in the image, not in the DEM).
                let same_place = elevation.is_some_and(|e| same_crs_extent(e, t.source));
                if !same_place && !near(fw / fh, grid_aspect) && !near(fw / fh, ex / ez) {
                    return Err(Error::input(
                        path,
                        format!(
                            "mismatched extents: the elevation covers {ex:.0} x {ez:.0} m (aspect {:.3}; its grid \
                             {grid_aspect:.3}), the texture is {w} x {h} px (aspect {:.3}); both must cover the same area",
                            ex / ez,
                            fw / fh
                        ),
                    ));
                }
                // Texels square in metres, as tiles are: resample along x where they are not.
                #[expect(clippy::cast_possible_truncation, clippy::cast_sign_loss, reason = "a pixel count")]
                let width = ((fh * ex / ez).round() as u32).max(1);
                (width, ex)
            }
            None => {
                if !(t.pixel_size.is_finite() && t.pixel_size > 0.0) {
                    return Err(Error::Writer(format!("pixel size {} m", t.pixel_size)));
                }
                (w, fw * t.pixel_size)
            }
        };
        let (nx, ny) = (width.div_ceil(t.tile_size), h.div_ceil(t.tile_size));
        let layer = Layer {
            name: "texture".into(),
            kind: LayerKind::Texture,
            format: t.format.tile_format(),
            compression: t.format.compression(),
            tile_resolution: t.tile_size,
            border: options.border,
            num_x_tiles: nx,
            num_y_tiles: ny,
            num_lods: levels_to_one(nx.max(ny)),
            tile_world_size: f64::from(t.tile_size) * world_width / f64::from(width),
            elevation: None,
        };
        let tiles = tiles_over((width, h), t.tile_size, layer.num_lods);
        let edge = u64::from(t.tile_size + 2 * u32::from(options.border));
        #[expect(
            clippy::cast_possible_truncation,
            clippy::cast_sign_loss,
            clippy::cast_precision_loss,
            reason = "an estimate"
        )]
        let estimated = (tiles as f64 * (edge * edge) as f64 * t.format.typical_bytes_per_texel()) as u64;
        plans.push(LayerPlan { size: (width, h), tiles, estimated_bytes: estimated });
        if elevation.is_none() {
            metadata.georeference = t.source.georeference().cloned();
            metadata.terrain.base_tile_size = layer.tile_world_size / f64::from(t.tile_size);
        }
        layers.push(layer);
    }
    if layers.is_empty() {
        return Err(Error::Writer("nothing to tile: give an elevation raster, a texture image or both".into()));
    }
    // Each elevation tile's height range, on the elevation's grid.
    if let Some(e) = layers.first().filter(|l| l.kind == LayerKind::Elevation) {
        let range = Layer {
            name: "elevation-range".into(),
            kind: LayerKind::HeightRange,
            format: TileFormat::MinMaxF32,
            compression: PayloadCompression::None,
            elevation: None,
            ..e.clone()
        };
        let tiles = plans[0].tiles;
        plans.push(LayerPlan { size: plans[0].size, tiles, estimated_bytes: tiles * 8 });
        layers.push(range);
    }
    metadata.layers = layers;
    metadata.validate()?;
    Ok(Plan { metadata, layers: plans })
}

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
/// [`Error::Interrupted`].
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
    let folder = crate::writer::output_folder(out);
    let mut spool = Spool::new(&folder)?;
    progress.start("tile", plan.tiles());
    let level = WriterOptions::default().zstd_level;
    let find = |kind: LayerKind| metadata.layers.iter().position(|l| l.kind == kind).and_then(|i| u8::try_from(i).ok());

    if let (Some(source), Some(index)) = (elevation, find(LayerKind::Elevation)) {
        let encoding = metadata.layers[usize::from(index)]
            .elevation
            .ok_or_else(|| Error::Writer("no elevation encoding".into()))?;
        let range = find(LayerKind::HeightRange);
        // Each tile's own stored range, gathered as tiles are encoded (8 bytes + key each).
        let ranges = std::sync::Mutex::new(Vec::<(TileKey, f32, f32)>::new());
        let encode = |key: TileKey, samples: &[f32], _edge: usize| -> Result<Vec<(TileKey, Vec<u8>)>> {
            let (raw, lo, hi) = encode_heights(samples, &encoding);
            if range.is_some() && lo <= hi {
                ranges.lock().unwrap_or_else(std::sync::PoisonError::into_inner).push((key, lo, hi));
            }
            Ok(vec![(key, zstd_compress(&raw, level)?)])
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
            let bytes =
                encode_texture(pixels, edge, format, level).map_err(|e| Error::Writer(format!("tile {key}: {e}")))?;
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
    let summary = writer.finish();
    tracing::debug!(elapsed = ?started.elapsed(), "archive written");
    summary
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
fn run_pyramid<S: Sample>(
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
            read(&mut |row| rows.send(row).map_err(|_| Error::Interrupted))
        });
        // Rows of tiles are cut on the pool while this thread halves the next rows.
        rayon::in_place_scope(|cuts| {
            let mut built =
                std::iter::from_fn(|| pyramid::receive(&received)).try_for_each(|row| pyramid.push(row, cuts));
            drop(received);
            let read = reader.join().unwrap_or_else(|_| Err(Error::Writer("the reading thread panicked".into())));
            // The pyramid's error first (it stopped the reader); else the reader's.
            built = built.and(read);
            built?;
            pyramid.finish(cuts)
        })
    })
}

/// Heights -> the layer's raw little-endian samples, and the lowest and highest height as
/// stored (after quantization).
fn encode_heights(samples: &[f32], encoding: &ElevationEncoding) -> (Vec<u8>, f32, f32) {
    if encoding.scheme == ElevationScheme::Float32 {
        let mut raw = Vec::with_capacity(samples.len() * 4);
        for v in samples {
            raw.extend_from_slice(&v.to_le_bytes());
        }
        let (lo, hi) = min_max(samples);
        return (raw, lo, hi);
    }
    // The hot loop of a DEM, without branches so that it vectorizes (measured 3x faster
    // than a scalar loop): f32 arithmetic (4 lanes on baseline x86-64), no libm call, no
    // float-to-int conversion (Rust's saturating `as` stays scalar there) and no height
    // decoded per sample. Steps are powers of two (see `plan`), so the scaling is exact and
    // the one rounding is the subtraction's, under 1/200 of a step on the u16 range.
    // Clamped to 1..=65535, adding 2^23 puts the nearest integer (ties to even) in the low
    // mantissa bits. A NaN (nodata) stays NaN through the clamp and becomes 0. Heights grow
    // with `q`, so the range is that of the lowest and highest `q` other than 0 (`q - 1`
    // wraps 0 to the top, out of the way).
    const TO_INTEGER: f32 = 8_388_608.0;
    #[expect(clippy::cast_possible_truncation, reason = "see above: f32 arithmetic on heights kept as f32")]
    let (offset, inverse) = (encoding.offset as f32, (1.0 / encoding.scale) as f32);
    let (mut lo, mut hi) = (u16::MAX, 0u16);
    let mut raw = vec![0u8; samples.len() * 2];
    for (out, &v) in raw.chunks_exact_mut(2).zip(samples) {
        let x = ((v - offset) * inverse).clamp(1.0, 65_535.0);
        #[expect(clippy::cast_possible_truncation, reason = "the low 16 bits hold the integer")]
        let q = if x.is_nan() { 0 } else { (x + TO_INTEGER).to_bits() as u16 };
        lo = lo.min(q.wrapping_sub(1));
        hi = hi.max(q);
        out.copy_from_slice(&q.to_le_bytes());
    }
    if hi == 0 {
        return (raw, f32::INFINITY, f32::NEG_INFINITY);
    }
    let lo = lo + 1;
    #[expect(clippy::cast_possible_truncation, reason = "heights are f32")]
    let height = |q: u16| encoding.height(f64::from(q)) as f32;
    (raw, height(lo), height(hi))
}

/// One texture tile's stored bytes.
fn encode_texture(pixels: &[[u8; 4]], edge: usize, format: TextureFormat, zstd_level: i32) -> Result<Vec<u8>> {
    let opaque = pixels.iter().all(|p| p[3] == 255);
    let rgb = || -> Vec<u8> {
        // Sized once: a `flat_map` collect cannot know its length and grows by doubling.
        let mut rgb = Vec::with_capacity(pixels.len() * 3);
        for p in pixels {
            rgb.extend_from_slice(&p[..3]);
        }
        rgb
    };
    let side = u32::try_from(edge).map_err(|_| Error::Writer("tile too large".into()))?;
    let err = |e: &dyn std::fmt::Display| Error::Writer(e.to_string());
    Ok(match format {
        TextureFormat::Png => {
            let mut out = Vec::new();
            let mut encoder = png::Encoder::new(&mut out, side, side);
            encoder.set_depth(png::BitDepth::Eight);
            encoder.set_color(if opaque { png::ColorType::Rgb } else { png::ColorType::Rgba });
            encoder.set_compression(png::Compression::Fast);
            encoder.set_filter(png::Filter::Paeth);
            let data = if opaque { rgb() } else { pixels.as_flattened().to_vec() };
            encoder.write_header().map_err(|e| err(&e))?.write_image_data(&data).map_err(|e| err(&e))?;
            out
        }
        TextureFormat::Jpeg(quality) => {
            let side16 = u16::try_from(edge).map_err(|_| Error::Writer("tile too large for JPEG".into()))?;
            let mut out = Vec::new();
            jpeg_encoder::Encoder::new(&mut out, quality)
                .encode(&rgb(), side16, side16, jpeg_encoder::ColorType::Rgb)
                .map_err(|e| err(&e))?;
            out
        }
        TextureFormat::Webp => {
            let mut out = Vec::new();
            let (data, colour) = if opaque {
                (rgb(), image_webp::ColorType::Rgb8)
            } else {
                (pixels.as_flattened().to_vec(), image_webp::ColorType::Rgba8)
            };
            image_webp::WebPEncoder::new(&mut out).encode(&data, side, side, colour).map_err(|e| err(&e))?;
            out
        }
        TextureFormat::Bc1 | TextureFormat::Bc7 => {
            zstd_compress(&bc::encode(pixels, edge, format == TextureFormat::Bc7), zstd_level)?
        }
    })
}

#[cfg(test)]
mod tests;
