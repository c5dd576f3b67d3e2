//! `terrastream water`: a water mask raster carried into an archive as its water layer.
//!
//! The mask is any single-band raster the tiler reads (a GeoTIFF, in any CRS): 0 is land,
//! 1 water (larger values count as 1, fractions between as partial cover, as an
//! anti-aliased rasterization gives them), no data where the mask says nothing. Each pixel
//! becomes a fraction (one byte), averaged 2 x 2 into a pyramid of its own.
//!
//! The mask is read once, top to bottom, and only its rows and columns under the
//! archive's tiles: each tile's footprint (the level it reads, and that level's rows and
//! columns around its samples) is found first, and a tile is made as soon as the rows it
//! reads are in, on the worker threads. Each level keeps only the rows a tile still to be
//! made reads, so memory follows a band of rows of the window read, not the mask: a
//! planet-wide mask over a valley's archive reads the valley's rows.
//!
//! Every elevation tile of the archive gets a water tile with the same LOD, x and y and
//! the same samples (borders included): each sample's position on the archive's grid is
//! taken into the mask's CRS (exactly at every [`KNOT`]-th sample of a tile, bilinear
//! between: a tile spans a few kilometres, where a projection is smooth to far below a
//! pixel), and the mask is read there bilinearly from the level of its pyramid whose pixels
//! are no larger than the sample. A tile wholly outside the mask (or over its no data) is
//! left missing: readers then take the sea from the heights (a flat 0), as without a water
//! layer. A tile the mask covers is authoritative, land included: a polder stored at 0 m
//! stays land.
//!
//! Tiles are 8-bit gray PNGs: `v / 254` the fraction, 255 no data (FORMAT.md §3.1).
//! Into the archive itself, they are appended in place where it has room for updates
//! (FORMAT.md §7.1: its own tiles stay where they are); otherwise the archive is written
//! anew beside the output and renamed over it once complete. Either way an error or
//! Ctrl-C leaves it as it was.

use std::collections::BTreeMap;
use std::path::Path;

use rayon::prelude::*;

use terrastream_format::{
    ElevationEncoding, ElevationScheme, Layer, LayerKind, PayloadCompression, Reader, TileFormat, TileKey,
};
use terrastream_pack::progress::Progress;
use terrastream_pack::{Writer, WriterOptions};

use crate::crs::{Crs, Transform};
use crate::error::{Error, Result};
use crate::raster::ElevationSource;

/// Samples between the exact transforms of a tile's positions into the mask's CRS.
pub const KNOT: usize = 16;

/// The stored value of a sample the mask says nothing about.
pub const NO_WATER_DATA: u8 = 255;

/// The stored value of a sample wholly water.
pub const ALL_WATER: u8 = 254;

/// A made water tile: its place in the archive's order, its key, its PNG, whether it has
/// any water.
struct Made {
    order: u64,
    key: TileKey,
    png: Vec<u8>,
    wet: bool,
}

/// The name the water layer is given.
pub const WATER_LAYER: &str = "water";

/// What [`add_water`] did.
#[derive(Clone, Debug)]
pub struct WaterSummary {
    /// Water tiles written (elevation tiles the mask covers).
    pub tiles: u64,
    /// Of them, tiles with some water.
    pub wet: u64,
    /// Elevation tiles the mask does not cover (left to the flat-sea rule).
    pub uncovered: u64,
    /// Bytes of the water tiles.
    pub bytes: u64,
    /// The archive written.
    pub write: terrastream_pack::WriteSummary,
}

/// The encoding of a water layer's samples: `v / 254`, 255 no data.
#[must_use]
pub fn water_encoding() -> ElevationEncoding {
    ElevationEncoding {
        scheme: ElevationScheme::Gray8,
        scale: 255.0 / f64::from(ALL_WATER),
        offset: 0.0,
        nodata: Some(f64::from(NO_WATER_DATA)),
    }
}

/// Adds (or replaces) the water layer of the archive `base`, from the mask raster `mask`,
/// and writes the archive to `out` (which may be `base`). A shard's water layer holds the
/// water tiles of its own elevation tiles, with the elevation's split LOD and band.
///
/// # Errors
/// [`Error::Input`] naming the archive when it has no elevation layer or no georeference
/// to place the mask by, or naming the mask when it cannot be read, has no georeference,
/// or says nothing of any elevation tile (a shard's may lie beyond it: its layer then holds
/// no tiles); I/O and archive errors; an interrupted error ([`Error::is_interrupted`])
/// when `progress` is cancelled (the output is then as it was).
pub fn add_water(base: &Path, mask_path: &Path, out: &Path, progress: &dyn Progress) -> Result<WaterSummary> {
    let reader = Reader::open_mmap(base).map_err(|e| Error::input(base, format!("cannot open archive: {e}")))?;
    let metadata = reader.metadata().clone();
    let bad = |why: &str| Error::input(base, why.to_owned());
    let elevation = metadata
        .layers
        .iter()
        .position(|l| l.kind == LayerKind::Elevation)
        .ok_or_else(|| bad("it has no elevation layer: a water layer follows its grid"))?;
    let grid = metadata.layers[elevation].clone();
    let g =
        metadata.georeference.as_ref().ok_or_else(|| bad("it has no georeference: nothing to place the mask by"))?;
    let (Some(origin), Some(scale), Some(definition)) =
        (g.origin, g.scale, g.definition.as_deref().or(g.crs.as_deref()))
    else {
        return Err(bad("its georeference has no CRS, origin and scale: tile it again"));
    };
    let archive_crs = Crs::parse(definition).map_err(|e| Error::input(base, format!("its CRS: {e}")))?;
    let mask = MaskFile::open(mask_path)?;
    let place = Placement {
        origin,
        scale,
        to_mask: Transform::new(&archive_crs, &mask.crs),
        mask_origin: mask.origin,
        mask_pixel: mask.pixel,
        levels: mask.levels(),
        size: (mask.width, mask.height),
    };

    // The elevation tiles, in archive order.
    let mut keys = Vec::new();
    let step = terrastream_format::MAX_LAYERS as u64;
    reader.for_each_entry(|entry| -> Result<()> {
        for i in 0..u64::from(entry.run_length) {
            let key = reader.archive().tile_of(entry.key + i * step)?;
            if usize::from(key.layer()) == elevation {
                keys.push(key);
            }
        }
        Ok(())
    })?;
    let existing = metadata.layers.iter().position(|l| l.kind == LayerKind::Water);
    let index = existing.unwrap_or(metadata.layers.len());
    let mut metadata = metadata;
    let layer = Layer {
        name: WATER_LAYER.into(),
        kind: LayerKind::Water,
        format: TileFormat::Png,
        compression: PayloadCompression::None,
        elevation: Some(water_encoding()),
        // The writer narrows the box of the tiles written to the elevation's (whose last
        // tiles' samples end inside them); the water's levels are its own.
        extent: grid.extent.clone().map(|e| terrastream_format::LayerExtent { partial: Vec::new(), ..e }),
        ..grid.clone()
    };
    match existing {
        Some(i) => metadata.layers[i] = layer,
        None if metadata.layers.len() < terrastream_format::MAX_LAYERS => metadata.layers.push(layer),
        None => return Err(bad("it has 16 layers already, the most an archive holds")),
    }
    // A shard's water tiles are those of its elevation tiles: the same split LOD and band
    // (the merge of the shards, or the coarse archive of their manifest, takes the water
    // above the split from the mask again).
    if let Some(shard) = metadata.shard.as_mut() {
        let (split, rows) = (shard.split_lods.get(elevation).copied(), shard.tile_rows.get(elevation).copied());
        let (Some(split), Some(rows)) = (split, rows) else {
            return Err(bad("its shard record names no split for the elevation layer: tile the shard again"));
        };
        shard.split_lods.resize(metadata.layers.len(), split);
        shard.tile_rows.resize(metadata.layers.len(), rows);
        shard.split_lods[index] = split;
        shard.tile_rows[index] = rows;
    }
    metadata.validate().map_err(|e| Error::input(base, e.to_string()))?;

    progress.start("water", keys.len() as u64);
    let index_u8 = u8::try_from(index).unwrap_or(u8::MAX);
    let mut tiles: BTreeMap<u64, Made> = BTreeMap::new();
    let make = |i: usize, values: Vec<u8>| -> Result<Option<Made>> {
        if values.iter().all(|&v| v == NO_WATER_DATA) {
            return Ok(None);
        }
        let key = keys[i];
        let wet = values.iter().any(|&v| v != 0 && v != NO_WATER_DATA);
        let water = TileKey::new(index_u8, key.lod(), key.x(), key.y())?;
        let order = Writer::order_key(&metadata, water)?;
        Ok(Some(Made { order, key: water, png: gray_png(&values, grid.stored_edge()), wet }))
    };
    stream_tiles(&mask, &place, &grid, &keys, progress, &make, &mut |done| {
        tiles.extend(done.into_iter().filter_map(|(_, made)| made).map(|m| (m.order, m)));
        Ok(())
    })?;
    let uncovered = (keys.len() - tiles.len()) as u64;
    // (A shard's band may lie beyond the mask, as one of a planet's beyond a continent's
    // mask: it holds the layer, without tiles, as its siblings do.)
    if tiles.is_empty() && metadata.shard.is_none() {
        return Err(Error::input(
            mask_path,
            format!(
                "the mask says nothing of any of {}'s {} elevation tiles: it lies elsewhere, or is all no data",
                base.display(),
                keys.len()
            ),
        ));
    }
    let wet = tiles.values().filter(|t| t.wet).count() as u64;
    let bytes = tiles.values().map(|t| t.png.len() as u64).sum();

    let summary = |write| WaterSummary { tiles: keys.len() as u64 - uncovered, wet, uncovered, bytes, write };
    if crate::edit::update::same_file(base, out) {
        // In place (FORMAT.md §7.1): the water tiles appended, the archive's own tiles
        // kept where they are; the archive written anew where it has no room for that.
        match append_water(&reader, &metadata, existing, &tiles, base) {
            Err(Error::Pack(terrastream_pack::Error::NoRoom { why, .. })) => {
                tracing::info!("{}: {why}: writing the archive anew", base.display());
            }
            other => return other.map(summary),
        }
    }
    write_water(reader, &metadata, existing, tiles, out, progress).map(summary)
}

/// The archive's tiles as they are stored (an old water layer's left out), with the water
/// tiles `water` (by archive order) in their places among them, in archive order.
fn in_order(
    reader: &Reader<terrastream_format::MmapSource>,
    existing: Option<usize>,
    water: &BTreeMap<u64, Made>,
    sink: &mut dyn FnMut(Tile<'_>) -> Result<()>,
) -> Result<()> {
    let step = terrastream_format::MAX_LAYERS as u64;
    let mut pending = water.iter().peekable();
    reader.for_each_entry(|entry| -> Result<()> {
        for i in 0..u64::from(entry.run_length) {
            let order = entry.key + i * step;
            let key = reader.archive().tile_of(order)?;
            if Some(usize::from(key.layer())) == existing {
                continue;
            }
            while let Some((&at, water)) = pending.next_if(|(o, _)| **o < order) {
                sink(Tile::Water(at, water))?;
            }
            sink(Tile::Stored(key, order, entry))?;
        }
        Ok(())
    })?;
    for (&at, water) in pending {
        sink(Tile::Water(at, water))?;
    }
    Ok(())
}

/// A tile of the archive with its water layer, in archive order.
enum Tile<'a> {
    /// One of the archive's own, at its archive order, and its directory entry.
    Stored(TileKey, u64, &'a terrastream_format::Entry),
    /// A water tile, at its archive order.
    Water(u64, &'a Made),
}

/// Writes the archive with its water layer anew at `out`, renamed into place once complete.
fn write_water(
    reader: Reader<terrastream_format::MmapSource>,
    metadata: &terrastream_format::Metadata,
    existing: Option<usize>,
    water: BTreeMap<u64, Made>,
    out: &Path,
    progress: &dyn Progress,
) -> Result<terrastream_pack::WriteSummary> {
    let options = WriterOptions { batch_bytes: 4 << 20, ..WriterOptions::default() };
    let mut writer = Writer::create(out, metadata.clone(), options)?;
    in_order(&reader, existing, &water, &mut |tile| {
        match tile {
            Tile::Stored(key, _, entry) => {
                progress.check()?;
                writer.add_stored(key, reader.entry_payload(entry)?.to_vec())?;
            }
            Tile::Water(_, water) => writer.add_stored(water.key, water.png.clone())?,
        }
        Ok(())
    })?;
    drop(reader);
    Ok(writer.finish()?)
}

/// Appends the water tiles to the archive at `path` in place, keeping its own tiles where
/// they are: only the water tiles and the new directories are written.
///
/// # Errors
/// `terrastream_pack::Error::NoRoom` (in [`Error::Pack`]) where the archive was written
/// without room for updates or its directories outgrow it: it is then as it was.
fn append_water(
    reader: &Reader<terrastream_format::MmapSource>,
    metadata: &terrastream_format::Metadata,
    existing: Option<usize>,
    water: &BTreeMap<u64, Made>,
    path: &Path,
) -> Result<terrastream_pack::WriteSummary> {
    let mut appender = terrastream_pack::Appender::open(path, WriterOptions::default())?;
    if appender.header() != reader.header() {
        return Err(Error::input(path, "it changed while the water was being made"));
    }
    in_order(reader, existing, water, &mut |tile| {
        match tile {
            Tile::Stored(key, order, entry) => appender.keep(key, order, entry.offset, entry.length)?,
            Tile::Water(order, water) => appender.add(water.key, order, &water.png)?,
        }
        Ok(())
    })?;
    Ok(appender.finish(metadata)?)
}

/// Opens the mask at `path` as [`add_water`] will (before a long job that ends with it).
///
/// # Errors
/// As [`add_water`] for the mask.
pub(crate) fn check_mask(path: &Path) -> Result<()> {
    MaskFile::open(path).map(|_| ())
}

/// A water mask file: where it lies, and its size.
struct MaskFile {
    file: crate::raster::ElevationFile,
    crs: Crs,
    /// The north-west corner of pixel (0, 0) and the pixel size, in the mask's CRS.
    origin: [f64; 2],
    pixel: (f64, f64),
    width: usize,
    height: usize,
}

impl MaskFile {
    fn open(path: &Path) -> Result<Self> {
        let file = crate::raster::open_elevation(path, None)?;
        let no_place =
            || Error::input(path, "the mask has no georeference (a CRS and where it lies): nothing to place it by");
        let g = file.georeference().ok_or_else(no_place)?;
        let (crs, origin) =
            (g.definition.as_deref().or(g.crs.as_deref()).ok_or_else(no_place)?, g.origin.ok_or_else(no_place)?);
        let crs = Crs::parse(crs).map_err(|e| Error::input(path, format!("the mask's CRS: {e}")))?;
        let pixel = file.crs_pixel_size().ok_or_else(no_place)?;
        let (width, height) = file.size();
        Ok(Self { file, crs, origin, pixel, width: width as usize, height: height as usize })
    }

    /// Levels of its pyramid: level 0 its pixels, each next one half the size (rounded
    /// up), down to one pixel.
    fn levels(&self) -> usize {
        let mut levels = 1;
        let (mut w, mut h) = (self.width, self.height);
        while w > 1 || h > 1 {
            (w, h) = (w.div_ceil(2), h.div_ceil(2));
            levels += 1;
        }
        levels
    }
}

/// A mask sample as stored: 0 land, [`ALL_WATER`] water, fractions between; no data and
/// non-numbers [`NO_WATER_DATA`].
fn fraction(v: f32) -> u8 {
    if v.is_nan() {
        return NO_WATER_DATA;
    }
    #[expect(clippy::cast_possible_truncation, clippy::cast_sign_loss, reason = "clamped to 0..=254")]
    let stored = (v.clamp(0.0, 1.0) * f32::from(ALL_WATER)).round() as u8;
    stored
}

/// The mean of each 2 x 2 block of known pixels of rows `a` and `b` (`b` none past the
/// last row), `width` out: a row of the next level (no data where none is known).
fn halved_row(a: &[u8], b: Option<&[u8]>, width: usize) -> Vec<u8> {
    let mut out = Vec::with_capacity(width);
    for x in 0..width {
        let (mut sum, mut n) = (0u32, 0u32);
        for row in [Some(a), b].into_iter().flatten() {
            for &v in row.iter().skip(2 * x).take(2) {
                if v != NO_WATER_DATA {
                    sum += u32::from(v);
                    n += 1;
                }
            }
        }
        #[expect(clippy::cast_possible_truncation, reason = "a mean of bytes up to 254")]
        out.push((sum + n / 2).checked_div(n).map_or(NO_WATER_DATA, |mean| mean as u8));
    }
    out
}

/// The rows of one level of the mask's pyramid held while tiles need them: rows
/// `first..first + rows.len()` of a level `width` x `height` (columns from the read
/// window's first).
struct Level {
    width: usize,
    height: usize,
    first: usize,
    rows: std::collections::VecDeque<Vec<u8>>,
}

impl Level {
    fn row(&self, j: usize) -> Option<&[u8]> {
        j.checked_sub(self.first).and_then(|k| self.rows.get(k)).map(Vec::as_slice)
    }

    /// Bilinear at pixel coordinates (`u`, `v`; pixel (i, j)'s centre at `i + 0.5`), over
    /// the known pixels around; no data where less than half the weight is known.
    fn bilinear(&self, u: f64, v: f64) -> u8 {
        let (x, y) = (u - 0.5, v - 0.5);
        // Inside, with the four pixels known (nearly every sample): no branch a corner.
        if x >= 0.0 && y >= 0.0 {
            #[expect(clippy::cast_possible_truncation, clippy::cast_sign_loss, reason = "non-negative, checked below")]
            let (i, j) = (x as usize, y as usize);
            if i + 1 < self.width
                && j + 1 < self.height
                && let (Some(top), Some(bottom)) = (self.row(j), self.row(j + 1))
            {
                let [a, b, c, d] = [top[i], top[i + 1], bottom[i], bottom[i + 1]];
                if a == b && b == c && c == d {
                    return a;
                }
                if a != NO_WATER_DATA && b != NO_WATER_DATA && c != NO_WATER_DATA && d != NO_WATER_DATA {
                    #[expect(clippy::cast_precision_loss, reason = "pixel indices")]
                    let (fx, fy) = (x - i as f64, y - j as f64);
                    let lerp = |p: u8, q: u8, f: f64| f64::from(p) + (f64::from(q) - f64::from(p)) * f;
                    let (top, bottom) = (lerp(a, b, fx), lerp(c, d, fx));
                    #[expect(
                        clippy::cast_possible_truncation,
                        clippy::cast_sign_loss,
                        reason = "between bytes up to 254"
                    )]
                    let rounded = (top + (bottom - top) * fy + 0.5) as u8;
                    return rounded;
                }
            }
        }
        let (x0, y0) = (x.floor(), y.floor());
        let (fx, fy) = (x - x0, y - y0);
        let (mut sum, mut weight) = (0.0, 0.0);
        for (dx, dy, w) in [
            (0.0, 0.0, (1.0 - fx) * (1.0 - fy)),
            (1.0, 0.0, fx * (1.0 - fy)),
            (0.0, 1.0, (1.0 - fx) * fy),
            (1.0, 1.0, fx * fy),
        ] {
            let (px, py) = (x0 + dx, y0 + dy);
            #[expect(clippy::cast_precision_loss, reason = "raster sizes")]
            let inside = px >= 0.0 && py >= 0.0 && px < self.width as f64 && py < self.height as f64;
            if w > 0.0 && inside {
                #[expect(clippy::cast_possible_truncation, clippy::cast_sign_loss, reason = "inside the level")]
                let value = self.row(py as usize).map_or(NO_WATER_DATA, |row| row[px as usize]);
                if value != NO_WATER_DATA {
                    sum += w * f64::from(value);
                    weight += w;
                }
            }
        }
        if weight < 0.5 {
            return NO_WATER_DATA;
        }
        #[expect(clippy::cast_possible_truncation, clippy::cast_sign_loss, reason = "a mean of bytes up to 254")]
        let mean = (sum / weight).round() as u8;
        mean
    }
}

/// What a tile reads of the mask: the level of its pyramid, and the rows and columns of
/// that level around its samples (a pixel beyond them on every side).
#[derive(Clone, Copy, Debug)]
struct Footprint {
    level: usize,
    rows: (usize, usize),
    columns: (usize, usize),
}

/// How the archive's grid lies in the mask's CRS.
struct Placement {
    origin: [f64; 2],
    scale: [f64; 2],
    to_mask: Transform,
    mask_origin: [f64; 2],
    mask_pixel: (f64, f64),
    /// Levels of the mask's pyramid, and level 0's size.
    levels: usize,
    size: (usize, usize),
}

/// The positions of a tile's samples in the mask (level-0 pixel coordinates), row by row;
/// None where the transform cannot take one.
struct Samples {
    edge: usize,
    points: Vec<Option<(f64, f64)>>,
    /// The pyramid's level whose pixels are no larger than a sample.
    level: usize,
}

impl Placement {
    /// The mask's pixel coordinates (level 0) of world point (`x`, `z`).
    fn mask_pixel(&self, x: f64, z: f64) -> Option<(f64, f64)> {
        let (cx, cy) = (self.origin[0] + x * self.scale[0], self.origin[1] - z * self.scale[1]);
        let (mx, my) = self.to_mask.apply(cx, cy)?;
        Some(((mx - self.mask_origin[0]) / self.mask_pixel.0, (self.mask_origin[1] - my) / self.mask_pixel.1))
    }

    /// The tile's knots' exact positions in the mask (see [`Placement::samples`]), row by
    /// row, and the level its samples read.
    fn knots(&self, grid: &Layer, key: TileKey) -> (Vec<Option<(f64, f64)>>, usize) {
        let s = self.samples_with(grid, key, false);
        (s.points, s.level)
    }

    /// Where the samples of the tile of `grid` at `key`'s LOD, x and y lie in the mask:
    /// exact at the knots (every [`KNOT`]-th sample and the last), bilinear between.
    fn samples(&self, grid: &Layer, key: TileKey) -> Samples {
        self.samples_with(grid, key, true)
    }

    /// [`Placement::samples`], or with `all` false the knots alone (`points` then holds
    /// the knots' positions).
    fn samples_with(&self, grid: &Layer, key: TileKey, all: bool) -> Samples {
        let edge = grid.stored_edge();
        let res = f64::from(grid.tile_resolution);
        let spacing = grid.world_size_at(key.lod()) / res;
        let (first_x, first_z) =
            (f64::from(key.x()) * res - f64::from(grid.border), f64::from(key.y()) * res - f64::from(grid.border));
        #[expect(clippy::cast_precision_loss, reason = "sample indices of one tile")]
        let world = |a: usize, b: usize| ((first_x + a as f64 + 0.5) * spacing, (first_z + b as f64 + 0.5) * spacing);
        let knots: Vec<usize> =
            (0..edge).step_by(KNOT).chain((!(edge - 1).is_multiple_of(KNOT)).then_some(edge - 1)).collect();
        let n = knots.len();
        let exact: Vec<Option<(f64, f64)>> = knots
            .iter()
            .flat_map(|&b| knots.iter().map(move |&a| (a, b)))
            .map(|(a, b)| {
                let (x, z) = world(a, b);
                self.mask_pixel(x, z)
            })
            .collect();
        // The level whose pixels are no larger than a sample, measured at the tile's middle.
        let middle = edge / 2;
        let (x, z) = world(middle, middle);
        let level = match (self.mask_pixel(x, z), self.mask_pixel(x + spacing, z), self.mask_pixel(x, z + spacing)) {
            (Some(p), Some(px), Some(pz)) => {
                let size = (px.0 - p.0).hypot(px.1 - p.1).min((pz.0 - p.0).hypot(pz.1 - p.1));
                #[expect(clippy::cast_possible_truncation, clippy::cast_sign_loss, reason = "clamped to the levels")]
                let l = if size > 1.0 { size.log2().floor().min(63.0) as usize } else { 0 };
                l.min(self.levels - 1)
            }
            _ => 0,
        };
        if !all {
            return Samples { edge, points: exact, level };
        }
        let mut points = vec![None; edge * edge];
        if n < 2 {
            return Samples { edge, points, level };
        }
        // Each sample's knot cell and its place in it, along either axis.
        let spans: Vec<(usize, f64)> = (0..edge)
            .map(|i| {
                let k = knots.partition_point(|&k| k <= i).clamp(1, n - 1) - 1;
                #[expect(clippy::cast_precision_loss, reason = "sample indices of one tile")]
                let f = (i - knots[k]) as f64 / (knots[k + 1] - knots[k]) as f64;
                (k, f)
            })
            .collect();
        let lerp = |p: f64, q: f64, f: f64| p + (q - p) * f;
        // A row's positions at the knot columns, then linear between them.
        let mut knot_row: Vec<Option<(f64, f64)>> = vec![None; n];
        for (b, &(kb, fb)) in spans.iter().enumerate() {
            for (ka, point) in knot_row.iter_mut().enumerate() {
                *point = match (exact[kb * n + ka], exact[(kb + 1) * n + ka]) {
                    (Some(p), Some(q)) => Some((lerp(p.0, q.0, fb), lerp(p.1, q.1, fb))),
                    _ => None,
                };
            }
            for (a, &(ka, fa)) in spans.iter().enumerate() {
                points[b * edge + a] = match (knot_row[ka], knot_row[ka + 1]) {
                    (Some(p), Some(q)) => Some((lerp(p.0, q.0, fa), lerp(p.1, q.1, fa))),
                    // A point the transform cannot take between knots: exactly, if it can.
                    _ => {
                        let (x, z) = world(a, b);
                        self.mask_pixel(x, z)
                    }
                };
            }
        }
        Samples { edge, points, level }
    }

    /// The rows and columns of its level that the tile of `grid` at `key` reads (None:
    /// none inside the mask): around its exact knots, whose box holds the positions
    /// interpolated between them; from every sample where a knot has no position.
    fn footprint(&self, grid: &Layer, key: TileKey) -> Option<Footprint> {
        let (knots, level) = self.knots(grid, key);
        let full;
        let points: &[Option<(f64, f64)>] = if knots.iter().all(Option::is_some) {
            &knots
        } else {
            full = self.samples(grid, key).points;
            &full
        };
        #[expect(clippy::cast_precision_loss, reason = "a level's power of two")]
        let shrink = 1.0 / (1u64 << level) as f64;
        let (mut lo, mut hi) = ((f64::INFINITY, f64::INFINITY), (f64::NEG_INFINITY, f64::NEG_INFINITY));
        for &(u, v) in points.iter().flatten() {
            lo = (lo.0.min(u), lo.1.min(v));
            hi = (hi.0.max(u), hi.1.max(v));
        }
        let (width, height) = level_size(self.size, level);
        // Bilinear reads the pixels whose centres are around a point: floor(x - 0.5) and
        // the next; one more on either side for the rounding of the positions.
        let span = |lo: f64, hi: f64, n: usize| -> Option<(usize, usize)> {
            let (first, last) = ((lo * shrink - 0.5).floor() - 1.0, (hi * shrink - 0.5).floor() + 2.0);
            #[expect(clippy::cast_precision_loss, reason = "raster sizes")]
            let beyond = n as f64 - 1.0;
            if !(first <= beyond && last >= 0.0) {
                return None;
            }
            #[expect(clippy::cast_possible_truncation, clippy::cast_sign_loss, reason = "clamped to the level")]
            let (first, last) = (first.max(0.0) as usize, last.min(beyond) as usize);
            Some((first, last))
        };
        Some(Footprint { level, rows: span(lo.1, hi.1, height)?, columns: span(lo.0, hi.0, width)? })
    }

    /// The water samples of `samples` from `at`, the level of the pyramid they read
    /// (`offset` the level-0 pixel of the read window's first column and row).
    fn fill(samples: &Samples, at: &Level, offset: (usize, usize)) -> Vec<u8> {
        #[expect(clippy::cast_precision_loss, reason = "a level's power of two")]
        let shrink = 1.0 / (1u64 << samples.level) as f64;
        #[expect(clippy::cast_precision_loss, reason = "raster sizes")]
        let (dx, dy) = ((offset.0 >> samples.level) as f64, (offset.1 >> samples.level) as f64);
        let mut out = vec![NO_WATER_DATA; samples.edge * samples.edge];
        for (value, point) in out.iter_mut().zip(&samples.points) {
            if let Some((u, v)) = point {
                *value = at.bilinear(u * shrink - dx, v * shrink - dy);
            }
        }
        out
    }
}

/// Pixels across and down of level `level` of a pyramid whose level 0 is `size`.
fn level_size(size: (usize, usize), level: usize) -> (usize, usize) {
    (size.0.div_ceil(1 << level), size.1.div_ceil(1 << level))
}

/// Rows of the mask read before the tiles they complete are made.
const BATCH_ROWS: usize = 256;

/// Makes the water tile of each of `keys` (of `grid`): reads the mask's rows once, top to
/// bottom, only those under some tile, and keeps of each level of its pyramid only the
/// rows a tile still to be made reads. Each tile's samples go through `make` (on the
/// worker threads), and `made` gets the results with each tile's index in `keys`; tiles
/// that lie wholly outside the mask are left out.
fn stream_tiles<T: Send>(
    mask: &MaskFile,
    place: &Placement,
    grid: &Layer,
    keys: &[TileKey],
    progress: &dyn Progress,
    make: &(dyn Fn(usize, Vec<u8>) -> Result<T> + Sync),
    made: &mut dyn FnMut(Vec<(usize, T)>) -> Result<()>,
) -> Result<()> {
    let footprints: Vec<Option<Footprint>> = keys
        .par_iter()
        .map(|&key| -> Result<_> {
            progress.check()?;
            Ok(place.footprint(grid, key))
        })
        .collect::<Result<_>>()?;
    let outside = footprints.iter().filter(|f| f.is_none()).count();
    progress.advance(outside as u64);
    let Some(top) = footprints.iter().flatten().map(|f| f.level).max() else { return Ok(()) };
    // The read window: every tile's rows and columns at level 0, aligned to the coarsest
    // level read, so that each level's 2 x 2 blocks are the whole pyramid's.
    let block = 1usize << top;
    let to_zero = |f: &Footprint, (a, b): (usize, usize)| (a << f.level, (b + 1) << f.level);
    let bounds = |pick: fn(&Footprint) -> (usize, usize), n: usize| {
        let spans = footprints.iter().flatten().map(|f| to_zero(f, pick(f)));
        let (a, b) = spans.fold((usize::MAX, 0), |(a, b), (x, y)| (a.min(x), b.max(y)));
        ((a / block) * block, b.min(n))
    };
    let (rows, columns) = (bounds(|f| f.rows, mask.height), bounds(|f| f.columns, mask.width));
    let window = (columns.1 - columns.0, rows.1 - rows.0);
    // Per level: its rows held, the next row it expects, a row waiting for its pair, and
    // its tiles by their last row.
    let mut levels: Vec<Level> = (0..=top)
        .map(|l| {
            let (w, h) = level_size(window, l);
            // The mask's own edge where the window reaches it (its odd last pixel).
            let full = level_size((mask.width, mask.height), l);
            let width = if columns.1 == mask.width { full.0 - (columns.0 >> l) } else { w };
            let height = if rows.1 == mask.height { full.1 - (rows.0 >> l) } else { h };
            Level { width, height, first: 0, rows: std::collections::VecDeque::new() }
        })
        .collect();
    let mut waiting: Vec<Option<Vec<u8>>> = vec![None; top + 1];
    let mut received = vec![0usize; top + 1];
    let mut pending: Vec<Vec<usize>> = vec![Vec::new(); top + 1];
    for (i, f) in footprints.iter().enumerate() {
        if let Some(f) = f {
            pending[f.level].push(i);
        }
    }
    let offset_rows = |f: &Footprint| {
        let shift = rows.0 >> f.level;
        (f.rows.0.saturating_sub(shift), f.rows.1.saturating_sub(shift))
    };
    for p in &mut pending {
        p.sort_by_key(|&i| footprints[i].map_or(0, |f| offset_rows(&f).1));
        p.reverse();
    }
    // A level's row in: kept, and paired for the next level.
    fn push(levels: &mut [Level], waiting: &mut [Option<Vec<u8>>], received: &mut [usize], l: usize, row: Vec<u8>) {
        received[l] += 1;
        if l + 1 < levels.len() {
            let width = levels[l + 1].width;
            match waiting[l].take() {
                None if received[l] == levels[l].height => {
                    let next = halved_row(&row, None, width);
                    push(levels, waiting, received, l + 1, next);
                }
                None => waiting[l] = Some(row.clone()),
                Some(first) => {
                    let next = halved_row(&first, Some(&row), width);
                    push(levels, waiting, received, l + 1, next);
                }
            }
        }
        levels[l].rows.push_back(row);
    }
    // Makes the tiles whose rows are all in, then lets go of the rows no tile left needs.
    let mut finish = |levels: &mut [Level], received: &[usize], pending: &mut [Vec<usize>]| -> Result<()> {
        let mut ready = Vec::new();
        for (l, tiles) in pending.iter_mut().enumerate() {
            while let Some(&i) = tiles.last() {
                let f = footprints[i].as_ref().map(offset_rows).unwrap_or_default();
                if f.1 >= received[l] {
                    break;
                }
                ready.push(i);
                tiles.pop();
            }
        }
        let done: Vec<(usize, T)> = ready
            .par_iter()
            .map(|&i| -> Result<_> {
                progress.check()?;
                let samples = place.samples(grid, keys[i]);
                let values = Placement::fill(&samples, &levels[samples.level], (columns.0, rows.0));
                progress.advance(1);
                Ok((i, make(i, values)?))
            })
            .collect::<Result<_>>()?;
        made(done)?;
        for (l, level) in levels.iter_mut().enumerate() {
            let keep = pending[l]
                .iter()
                .map(|&i| footprints[i].as_ref().map_or(usize::MAX, |f| offset_rows(f).0))
                .min()
                .unwrap_or(received[l]);
            while level.first < keep && !level.rows.is_empty() {
                level.rows.pop_front();
                level.first += 1;
            }
        }
        Ok(())
    };
    let (c0, c1) = columns;
    let mut since = 0;
    #[expect(clippy::cast_possible_truncation, reason = "a raster's rows fit a u32")]
    let range = rows.0 as u32..rows.1 as u32;
    mask.file.rows_in(range, &mut |row| {
        let values: Vec<u8> = row[c0..c1].iter().map(|&v| fraction(v)).collect();
        push(&mut levels, &mut waiting, &mut received, 0, values);
        since += 1;
        if since == BATCH_ROWS {
            since = 0;
            finish(&mut levels, &received, &mut pending).map_err(|e| crate::raster::Error::Consumer(Box::new(e)))?;
        }
        Ok(())
    })?;
    // A level whose last row waits for a pair that will not come: halved alone.
    for l in 0..top {
        if let Some(row) = waiting[l].take() {
            let next = halved_row(&row, None, levels[l + 1].width);
            push(&mut levels, &mut waiting, &mut received, l + 1, next);
        }
    }
    finish(&mut levels, &received, &mut pending)
}

/// An 8-bit gray PNG of `edge` x `edge` values.
fn gray_png(values: &[u8], edge: usize) -> Vec<u8> {
    let mut out = Vec::new();
    let side = u32::try_from(edge).unwrap_or(u32::MAX);
    let mut encoder = png::Encoder::new(&mut out, side, side);
    encoder.set_color(png::ColorType::Grayscale);
    encoder.set_depth(png::BitDepth::Eight);
    encoder.set_compression(png::Compression::Balanced);
    // Writing into a Vec cannot fail for a buffer of the stated size.
    if let Ok(mut w) = encoder.write_header() {
        let _ = w.write_image_data(values);
    }
    out
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A level held whole, as tests read it.
    fn level(width: usize, values: &[u8]) -> Level {
        let height = values.len() / width;
        Level { width, height, first: 0, rows: values.chunks(width).map(<[u8]>::to_vec).collect() }
    }

    #[test]
    fn the_pyramid_averages_known_pixels_and_keeps_no_data_apart() {
        let (top, bottom) = ([0, 254, NO_WATER_DATA], [254, 254, NO_WATER_DATA]);
        assert_eq!(halved_row(&top, Some(&bottom), 2), vec![191, NO_WATER_DATA]);
        // The last row of an odd level, alone; the last column of an odd row, alone.
        assert_eq!(halved_row(&[254, 0, 100], None, 2), vec![127, 100]);
    }

    #[test]
    fn fractions_clamp_and_no_data_stays_apart() {
        assert_eq!(fraction(0.0), 0);
        assert_eq!(fraction(1.0), ALL_WATER);
        assert_eq!(fraction(255.0), ALL_WATER);
        assert_eq!(fraction(-3.0), 0);
        assert_eq!(fraction(0.5), 127);
        assert_eq!(fraction(f32::NAN), NO_WATER_DATA);
        let e = water_encoding();
        assert!((e.height(f64::from(ALL_WATER)) - 1.0).abs() < 1e-12);
    }

    #[test]
    fn bilinear_reads_between_pixels_and_past_the_edge() {
        let l = level(2, &[0, 254]);
        assert_eq!(l.bilinear(0.5, 0.5), 0);
        assert_eq!(l.bilinear(1.5, 0.5), 254);
        assert_eq!(l.bilinear(1.0, 0.5), 127);
        // Half a pixel past the edge: the edge pixel alone.
        assert_eq!(l.bilinear(2.0, 0.5), 254);
        assert_eq!(l.bilinear(5.0, 0.5), NO_WATER_DATA);
    }

    /// Inside the level, between four known pixels, the bilinear mean of the four, rounded
    /// (within a step, as rounding at a half may go either way), over many positions.
    #[test]
    #[expect(
        clippy::cast_possible_truncation,
        clippy::cast_sign_loss,
        clippy::cast_precision_loss,
        reason = "small test grids"
    )]
    fn bilinear_inside_is_the_mean_of_the_four_pixels() {
        let (width, height) = (7, 5);
        let values: Vec<u8> = (0..width * height).map(|i| ((i * 97) % 255) as u8).collect();
        let l = level(width, &values);
        assert_eq!(l.height, height);
        for k in 0..2000 {
            let (u, v) = (0.5 + (k as f64 * 0.6180339) % 6.0, 0.5 + (k as f64 * 0.4142136) % 4.0);
            let (x, y) = (u - 0.5, v - 0.5);
            let (i, j) = (x.floor() as usize, y.floor() as usize);
            let (fx, fy) = (x - i as f64, y - j as f64);
            let at = |i: usize, j: usize| f64::from(values[j * width + i]);
            let exact = at(i, j) * (1.0 - fx) * (1.0 - fy)
                + at(i + 1, j) * fx * (1.0 - fy)
                + at(i, j + 1) * (1.0 - fx) * fy
                + at(i + 1, j + 1) * fx * fy;
            let got = f64::from(l.bilinear(u, v));
            assert!((got - exact).abs() <= 0.5 + 1e-9, "at ({u}, {v}): {got} for {exact}");
        }
    }
}
