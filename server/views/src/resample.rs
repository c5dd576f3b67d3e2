//! Web Mercator tiles made from an archive in any CRS: each output pixel's centre goes
//! through the archive's CRS (an approximate transform: exact at the corners of cells of
//! [`LATTICE`] pixels, interpolated between, each cell checked at its middle and the
//! middles of its edges against the exact transform and split where the interpolation is
//! off by more than 1/8 of a pixel,
//! down to [`SMALLEST_CELL`] pixels and then exact, as GDAL's warper does) into the
//! archive's world coordinates, and is sampled there from the LOD whose
//! samples are no larger than the output pixel: bilinear and nodata-aware for heights and
//! imagery alike.
//!
//! The samples a tile needs are first gathered into one window of that LOD (decoding each
//! archive tile once; a missing tile filled from the nearest coarser LOD that has one), so
//! the per-pixel work is a lookup in one array, not in a map of tiles.

use std::collections::HashMap;
use std::sync::Arc;

use terrastream_crs::{Crs, Transform};
use terrastream_format::{Layer, MmapSource, Reader, TileKey};
use terrastream_tiles::{DecodedTile, TileData, decode};

use crate::mercator::WebTile;

/// Output pixels a side of the approximate transform's cells before they are checked
/// (and split, down to [`SMALLEST_CELL`], where the check fails).
pub const LATTICE: usize = 64;

/// The smallest cell: one whose check fails is transformed pixel by pixel.
pub const SMALLEST_CELL: usize = 8;

/// Largest interpolation error of the approximate transform, in output pixels.
pub const MAX_ERROR: f64 = 0.125;

/// What a layer's samples are.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Samples {
    /// One height a sample (NaN: no data).
    Heights,
    /// RGBA (alpha 0: no data).
    Rgba,
}

/// Why a tile could not be made.
#[derive(Debug, thiserror::Error)]
pub enum MakeError {
    /// The layer has no web tiles: the archive does not say where it lies, or its tiles
    /// are neither heights nor images.
    #[error(
        "the layer has no web tiles: the archive does not say where it lies, or its tiles are not heights or images"
    )]
    NotPlaced,
    /// The tile could not be encoded.
    #[error("cannot encode the tile: {0}")]
    Encode(String),
    /// An archive tile that cannot be read or decoded (the archive is damaged).
    #[error("tile {key}: {reason}")]
    Tile {
        /// The archive tile.
        key: TileKey,
        /// Why.
        reason: String,
    },
}

/// Decoded archive tiles kept between web tiles (neighbouring web tiles and zooms read the
/// same archive tiles), by the archive's version and the tile.
pub type DecodedCache = crate::cache::Lru<(u64, TileKey), Arc<DecodedTile>>;

/// Bytes of decoded archive tiles kept by default: the server's `web_decoded_bytes` and
/// what an export keeps.
pub const DECODED_BYTES: usize = 256 << 20;

/// An archive layer on the Earth: what web tiles are made from.
pub struct Placed<'a> {
    reader: &'a Reader<MmapSource>,
    /// Decoded tiles kept, and this archive version's number in it.
    cache: Option<(&'a DecodedCache, u64)>,
    index: u8,
    layer: &'a Layer,
    samples: Samples,
    /// Degrees (WGS 84) to the archive's CRS, and back.
    to_archive: Transform,
    to_degrees: Transform,
    /// The archive's CRS coordinates to world units: origin and CRS units per world unit.
    origin: [f64; 2],
    scale: [f64; 2],
}

impl<'a> Placed<'a> {
    /// Layer `index` of the archive, when the archive says where it lies (a CRS
    /// definition, origin and scale) and the layer's samples are heights or RGBA.
    pub fn new(reader: &'a Reader<MmapSource>, index: u8) -> Option<Self> {
        let metadata = reader.metadata();
        let layer = metadata.layers.get(usize::from(index))?;
        let samples = match layer.kind {
            // A water layer's samples decode as heights do: the fraction of water.
            terrastream_format::LayerKind::Elevation | terrastream_format::LayerKind::Water => Samples::Heights,
            terrastream_format::LayerKind::Texture => match layer.format {
                terrastream_format::TileFormat::Png
                | terrastream_format::TileFormat::Jpeg
                | terrastream_format::TileFormat::Webp
                | terrastream_format::TileFormat::Bc1
                | terrastream_format::TileFormat::Bc7 => Samples::Rgba,
                _ => return None,
            },
            _ => return None,
        };
        let g = metadata.georeference.as_ref()?;
        let crs = Crs::parse(g.definition.as_deref().or(g.crs.as_deref())?).ok()?;
        let (to_archive, to_degrees) = (Transform::new(&Crs::wgs84(), &crs), Transform::new(&crs, &Crs::wgs84()));
        Some(Self {
            reader,
            cache: None,
            index,
            layer,
            samples,
            to_archive,
            to_degrees,
            origin: g.origin?,
            scale: g.scale?,
        })
    }

    /// Keeps decoded archive tiles in `cache`, under `version` (the archive's content tag:
    /// a replaced archive's tiles are other entries).
    #[must_use]
    pub fn with_cache(mut self, cache: &'a DecodedCache, version: u64) -> Self {
        self.cache = Some((cache, version));
        self
    }

    /// The archive's metadata.
    pub fn metadata(&self) -> &'a terrastream_format::Metadata {
        self.reader.metadata()
    }

    /// The layer.
    pub fn layer(&self) -> &'a Layer {
        self.layer
    }

    /// What the layer's samples are.
    pub fn samples(&self) -> Samples {
        self.samples
    }

    /// World coordinates of a point in degrees.
    pub fn world(&self, lon: f64, lat: f64) -> Option<(f64, f64)> {
        let (cx, cy) = self.to_archive.apply(lon, lat)?;
        let (x, z) = ((cx - self.origin[0]) / self.scale[0], (self.origin[1] - cy) / self.scale[1]);
        (x.is_finite() && z.is_finite()).then_some((x, z))
    }

    /// Degrees of a point in world coordinates (the inverse of [`Placed::world`]).
    pub fn degrees(&self, x: f64, z: f64) -> Option<(f64, f64)> {
        let (cx, cy) = self.crs_coordinates(x, z);
        self.to_degrees.apply(cx, cy)
    }

    /// The archive's CRS coordinates of a point in world coordinates.
    pub fn crs_coordinates(&self, x: f64, z: f64) -> (f64, f64) {
        (self.origin[0] + x * self.scale[0], self.origin[1] - z * self.scale[1])
    }

    /// The samples of `lod` whose cells meet the world box `lo`..`hi` (a sample's cell
    /// is its spacing around it; clipped to the LOD's grid and the data), as they are
    /// (a missing tile's from the nearest coarser LOD that has one, resampled): heights
    /// (NaN: no data) or RGBA. None when the box misses the data.
    ///
    /// # Errors
    /// [`MakeError::Tile`] for an archive tile that cannot be read or decoded.
    pub fn samples_in(&self, lo: (f64, f64), hi: (f64, f64), lod: u8) -> Result<Option<SampleGrid>, MakeError> {
        let [wx0, wz0, wx1, wz1] = self.layer.data_world();
        let (lo, hi) = ((lo.0.max(wx0), lo.1.max(wz0)), (hi.0.min(wx1), hi.1.min(wz1)));
        Ok(Window::gather_box(self, lo, hi, lod)?.map(|w| SampleGrid {
            first: w.first,
            size: w.size,
            spacing: w.spacing,
            values: w.values,
        }))
    }

    /// The world position of every pixel centre of `tile` (`size` a side), row by row;
    /// none where the point has no place in the archive's CRS.
    pub fn positions(&self, tile: WebTile, size: usize) -> Positions {
        self.lattice(size, &|u, v| {
            let (lon, lat) = tile.lon_lat(u, v, size as f64);
            self.world(lon, lat)
        })
    }

    /// The world positions of the pixel centres of a grid of `size` x `size` pixels whose
    /// pixel-edge coordinates (`u` across, `v` down) go to world positions by `exact`,
    /// through the approximate transform.
    pub fn lattice(&self, size: usize, exact: &dyn Fn(f64, f64) -> Option<(f64, f64)>) -> Positions {
        let mut out = Positions { len: size * size, runs: vec![] };
        let mut v0 = 0;
        while v0 < size {
            let mut u0 = 0;
            while u0 < size {
                let (u1, v1) = ((u0 + LATTICE).min(size), (v0 + LATTICE).min(size));
                let corners = [
                    exact(u0 as f64, v0 as f64),
                    exact(u1 as f64, v0 as f64),
                    exact(u0 as f64, v1 as f64),
                    exact(u1 as f64, v1 as f64),
                ];
                cell(exact, &mut out.runs, size, [u0, v0, u1, v1], corners);
                u0 = u1;
            }
            v0 = (v0 + LATTICE).min(size);
        }
        out
    }

    /// The LOD to sample for output pixels of `world_per_pixel` world units: the coarsest
    /// whose samples are no larger than that (so no detail the pixel shows is lost),
    /// within the LODs that hold tiles.
    pub fn lod_for(&self, world_per_pixel: f64) -> u8 {
        let spacing = self.layer.sample_spacing(0);
        let (finest, coarsest) = self
            .layer
            .extent
            .as_ref()
            .map_or((0, self.layer.num_lods.saturating_sub(1)), |e| (e.finest_lod, e.coarsest_lod));
        let levels = (world_per_pixel / spacing).log2().floor();
        #[expect(clippy::cast_possible_truncation, clippy::cast_sign_loss, reason = "clamped to the LODs")]
        let lod = if levels.is_finite() { levels.max(0.0).min(f64::from(coarsest)) as u8 } else { coarsest };
        lod.max(finest).min(coarsest)
    }

    /// The samples of `positions` from `lod`: `channels` values a point (1 for heights,
    /// 4 for RGBA), bilinear; NaN heights and transparent pixels where there is no data.
    /// None when no point has data (the tile is empty).
    ///
    /// # Errors
    /// [`MakeError::Tile`] for an archive tile that cannot be read or decoded.
    pub fn sample(&self, positions: &Positions, lod: u8) -> Result<Option<Vec<f32>>, MakeError> {
        let Some(window) = Window::gather(self, positions, lod)? else { return Ok(None) };
        if self.samples == Samples::Heights {
            return Ok(window.heights(positions));
        }
        let mut out = vec![0.0; positions.len * 4];
        let mut any = false;
        for run in &positions.runs {
            for k in 0..run.len {
                let (x, z) = run.point(k);
                if let Some(v) = window.bilinear(x, z) {
                    any = true;
                    let at = (run.at + k) * 4;
                    out[at..at + 4].copy_from_slice(&v);
                }
            }
        }
        Ok(any.then_some(out))
    }
}

/// Samples of one LOD over a rectangle: sample `(c, r)` (of `size`) is the LOD's sample
/// `first + (c, r)`, at world `((first.0 + c + 0.5) * spacing, (first.1 + r + 0.5) * spacing)`.
#[derive(Clone, Debug)]
pub struct SampleGrid {
    /// The first sample's column and row in the LOD's grid.
    pub first: (i64, i64),
    /// Samples across and down.
    pub size: (usize, usize),
    /// World units between samples.
    pub spacing: f64,
    /// Row by row; one value a sample for heights, four for RGBA.
    pub values: Vec<f32>,
}

/// World positions of a grid of points, row by row: runs of consecutive points whose
/// positions step evenly (along a row of a cell of the approximate transform), or one
/// point alone. A point in no run has no position.
#[derive(Clone, Debug, Default)]
pub struct Positions {
    len: usize,
    runs: Vec<Run>,
}

/// Points `at`, `at + 1`, ... `at + len - 1` at `origin + step * (k + offset)`.
#[derive(Clone, Copy, Debug)]
struct Run {
    at: usize,
    len: usize,
    origin: (f64, f64),
    step: (f64, f64),
    offset: f64,
}

impl Run {
    #[expect(clippy::cast_precision_loss, reason = "offsets within one tile")]
    fn point(&self, k: usize) -> (f64, f64) {
        let t = k as f64 + self.offset;
        (self.origin.0 + self.step.0 * t, self.origin.1 + self.step.1 * t)
    }
}

impl Positions {
    /// The same positions but for the outermost points of the grid (`size` a side), which
    /// are `exact(column, row)`'s.
    #[must_use]
    pub fn with_exact_border(self, size: usize, exact: impl Fn(usize, usize) -> Option<(f64, f64)>) -> Self {
        if size < 2 {
            return self;
        }
        let last = size - 1;
        let mut runs = Vec::with_capacity(self.runs.len() + 4 * size);
        for mut run in self.runs {
            // A run lies in one row.
            let (row, column) = (run.at / size, run.at % size);
            if row == 0 || row == last {
                continue;
            }
            if column == 0 {
                (run.at, run.len, run.offset) = (run.at + 1, run.len - 1, run.offset + 1.0);
            }
            if run.len > 0 && (run.at + run.len - 1) % size == last {
                run.len -= 1;
            }
            if run.len > 0 {
                runs.push(run);
            }
        }
        let border = (0..size).flat_map(|c| [(c, 0), (c, last)]).chain((1..last).flat_map(|r| [(0, r), (last, r)]));
        for (column, row) in border {
            if let Some(origin) = exact(column, row) {
                runs.push(Run { at: row * size + column, len: 1, origin, step: (0.0, 0.0), offset: 0.0 });
            }
        }
        Self { len: self.len, runs }
    }

    /// The points of the window `[c0, r0, c1, r1]` (columns `c0..c1` of rows `r0..r1`)
    /// of this grid of `size` points a side, as a grid of their own, row by row: the same
    /// positions, so a window's samples are the whole grid's there.
    #[must_use]
    #[expect(clippy::cast_precision_loss, reason = "offsets within one tile")]
    pub fn crop(self, size: usize, [c0, r0, c1, r1]: [usize; 4]) -> Self {
        let width = c1.saturating_sub(c0);
        let mut runs = Vec::with_capacity(self.runs.len());
        for run in self.runs {
            let (row, column) = (run.at / size, run.at % size);
            let (start, end) = (column.max(c0), (column + run.len).min(c1));
            if !(r0..r1).contains(&row) || start >= end {
                continue;
            }
            runs.push(Run {
                at: (row - r0) * width + (start - c0),
                len: end - start,
                offset: run.offset + (start - column) as f64,
                ..run
            });
        }
        Self { len: width * r1.saturating_sub(r0), runs }
    }

    /// How many points.
    pub fn len(&self) -> usize {
        self.len
    }

    /// Whether there are no points.
    pub fn is_empty(&self) -> bool {
        self.len == 0
    }

    /// Point `i`'s position; None where it has none (or beyond the points).
    pub fn point(&self, i: usize) -> Option<(f64, f64)> {
        self.runs.iter().find(|r| (r.at..r.at + r.len).contains(&i)).map(|r| r.point(i - r.at))
    }
}

/// Fills the positions of the pixels of cell `[u0, v0, u1, v1]` (pixel edges) whose
/// corners go to `corners` (north-west, north-east, south-west, south-east): bilinear
/// between them when that is within [`MAX_ERROR`] pixels of the exact transform at the
/// cell's middle and at the middles of its edges; else split in four there (down to
/// [`SMALLEST_CELL`]), or exact per pixel.
#[expect(clippy::cast_precision_loss, reason = "pixel coordinates of one tile")]
fn cell(
    exact: &dyn Fn(f64, f64) -> Option<(f64, f64)>,
    out: &mut Vec<Run>,
    size: usize,
    [u0, v0, u1, v1]: [usize; 4],
    corners: [Option<(f64, f64)>; 4],
) {
    let (w, h) = ((u1 - u0) as f64, (v1 - v0) as f64);
    let lerp = |fu: f64, fv: f64| -> Option<(f64, f64)> {
        let [a, b, c, d] = corners;
        let (a, b, c, d) = (a?, b?, c?, d?);
        let top = (a.0 + (b.0 - a.0) * fu, a.1 + (b.1 - a.1) * fu);
        let bottom = (c.0 + (d.0 - c.0) * fu, c.1 + (d.1 - c.1) * fu);
        Some((top.0 + (bottom.0 - top.0) * fv, top.1 + (bottom.1 - top.1) * fv))
    };
    // Where the cell would split: its middle and the middles of its edges, exact.
    let (um, vm) = ((u0 + u1) / 2, (v0 + v1) / 2);
    let at = |u: usize, v: usize| exact(u as f64, v as f64);
    let (middle, n, s, west, east) = (at(um, vm), at(um, v0), at(um, v1), at(u0, vm), at(u1, vm));
    // World units per output pixel, from the cell's top edge.
    let per_pixel = match (corners[0], corners[1]) {
        (Some(a), Some(b)) => (b.0 - a.0).hypot(b.1 - a.1) / w,
        _ => f64::NAN,
    };
    let (fu, fv) = ((um - u0) as f64 / w, (vm - v0) as f64 / h);
    let checks = [((fu, fv), middle), ((fu, 0.0), n), ((fu, 1.0), s), ((0.0, fv), west), ((1.0, fv), east)];
    let good = per_pixel > 0.0
        && checks.iter().all(|&((fu, fv), truth)| match (lerp(fu, fv), truth) {
            (Some(approx), Some(truth)) => (approx.0 - truth.0).hypot(approx.1 - truth.1) / per_pixel <= MAX_ERROR,
            _ => false,
        });
    if good && let [Some(a), Some(b), Some(c), Some(d)] = corners {
        // Bilinear, as a row's start and step (linear along a row).
        for v in v0..v1 {
            let fv = (v as f64 + 0.5 - v0 as f64) / h;
            let left = (a.0 + (c.0 - a.0) * fv, a.1 + (c.1 - a.1) * fv);
            let right = (b.0 + (d.0 - b.0) * fv, b.1 + (d.1 - b.1) * fv);
            let step = ((right.0 - left.0) / w, (right.1 - left.1) / w);
            out.push(Run { at: v * size + u0, len: u1 - u0, origin: left, step, offset: 0.5 });
        }
        return;
    }
    if u1 - u0 > SMALLEST_CELL && v1 - v0 > SMALLEST_CELL {
        let [nw, ne, sw, se] = corners;
        cell(exact, out, size, [u0, v0, um, vm], [nw, n, west, middle]);
        cell(exact, out, size, [um, v0, u1, vm], [n, ne, middle, east]);
        cell(exact, out, size, [u0, vm, um, v1], [west, middle, sw, s]);
        cell(exact, out, size, [um, vm, u1, v1], [middle, east, s, se]);
        return;
    }
    for v in v0..v1 {
        for u in u0..u1 {
            if let Some(origin) = exact(u as f64 + 0.5, v as f64 + 0.5) {
                out.push(Run { at: v * size + u, len: 1, origin, step: (0.0, 0.0), offset: 0.0 });
            }
        }
    }
}

/// Samples of one LOD over a rectangle, gathered from its tiles (a missing tile's from
/// the nearest coarser LOD that has one): `channels` f32 values a sample, NaN where there
/// is no data (alpha 0 for imagery).
struct Window {
    /// World units between samples.
    spacing: f64,
    /// The first sample's column and row in the LOD's grid.
    first: (i64, i64),
    /// Samples across and down.
    size: (usize, usize),
    channels: usize,
    values: Vec<f32>,
    /// Samples of the LOD's grid (its tiles' interiors, across and down).
    grid: (i64, i64),
}

impl Window {
    fn gather(placed: &Placed<'_>, positions: &Positions, lod: u8) -> Result<Option<Self>, MakeError> {
        let [wx0, wz0, wx1, wz1] = placed.layer.data_world();
        // The samples under the points (and their bilinear neighbours), inside the data:
        // the box of the points inside it, then its samples.
        let (mut lo, mut hi) = ((f64::INFINITY, f64::INFINITY), (f64::NEG_INFINITY, f64::NEG_INFINITY));
        let inside = |(x, z): (f64, f64)| x >= wx0 && x <= wx1 && z >= wz0 && z <= wz1;
        let mut grow = |(x, z): (f64, f64)| {
            // Plain comparisons, not f64::min/max (whose NaN rules cost a blend a point).
            lo.0 = if x < lo.0 { x } else { lo.0 };
            lo.1 = if z < lo.1 { z } else { lo.1 };
            hi.0 = if x > hi.0 { x } else { hi.0 };
            hi.1 = if z > hi.1 { z } else { hi.1 };
        };
        for run in &positions.runs {
            let (first, last) = (run.point(0), run.point(run.len - 1));
            if inside(first) && inside(last) {
                // A run's points move monotonically from one end to the other, and the
                // data's box is convex: the ends bound the whole run, and all lie inside.
                grow(first);
                grow(last);
            } else {
                (0..run.len).map(|k| run.point(k)).filter(|&p| inside(p)).for_each(&mut grow);
            }
        }
        if lo.0 > hi.0 {
            return Ok(None);
        }
        Self::gather_box(placed, lo, hi, lod)
    }

    /// The window of `lod` over the samples whose cells meet the world box `lo`..`hi`
    /// (and their bilinear neighbours), clipped to the LOD's grid.
    fn gather_box(placed: &Placed<'_>, lo: (f64, f64), hi: (f64, f64), lod: u8) -> Result<Option<Self>, MakeError> {
        let layer = placed.layer;
        let res = i64::from(layer.tile_resolution);
        let spacing = layer.world_size_at(lod) / res as f64;
        let (tiles_x, tiles_y) = layer.grid_at(lod);
        let grid = (i64::from(tiles_x) * res, i64::from(tiles_y) * res);
        if !(lo.0 <= hi.0 && lo.1 <= hi.1) {
            return Ok(None);
        }
        let inverse = 1.0 / spacing;
        #[expect(clippy::cast_possible_truncation, reason = "inside the layer's grid")]
        let bounds = (
            floor(lo.0 * inverse - 0.5) as i64,
            floor(lo.1 * inverse - 0.5) as i64,
            floor(hi.0 * inverse - 0.5) as i64 + 1,
            floor(hi.1 * inverse - 0.5) as i64 + 1,
        );
        if bounds.0 > bounds.2 {
            return Ok(None);
        }
        let (i0, j0) = (bounds.0.max(0), bounds.1.max(0));
        let (i1, j1) = (bounds.2.min(grid.0 - 1), bounds.3.min(grid.1 - 1));
        if i0 > i1 || j0 > j1 {
            return Ok(None);
        }
        let channels = if placed.samples == Samples::Heights { 1 } else { 4 };
        #[expect(clippy::cast_sign_loss, clippy::cast_possible_truncation, reason = "i1 >= i0, j1 >= j0")]
        let size = ((i1 - i0 + 1) as usize, (j1 - j0 + 1) as usize);
        let mut window =
            Self { spacing, first: (i0, j0), size, channels, values: vec![f32::NAN; size.0 * size.1 * channels], grid };
        let mut tiles = Tiles { placed, decoded: HashMap::new() };
        #[expect(clippy::cast_sign_loss, clippy::cast_possible_truncation, reason = "non-negative tile indices")]
        for ty in (j0 / res) as u32..=(j1 / res) as u32 {
            for tx in (i0 / res) as u32..=(i1 / res) as u32 {
                window.fill_tile(&mut tiles, lod, (tx, ty))?;
            }
        }
        Ok(Some(window))
    }

    /// Copies tile (tx, ty) of `lod` into the window; where the LOD lacks it, resamples
    /// the nearest coarser tile that covers it.
    #[expect(
        clippy::cast_possible_truncation,
        clippy::cast_sign_loss,
        clippy::cast_possible_wrap,
        clippy::cast_precision_loss,
        reason = "sample indices inside one window, far below 2^52"
    )]
    fn fill_tile(&mut self, tiles: &mut Tiles<'_, '_>, lod: u8, (tx, ty): (u32, u32)) -> Result<(), MakeError> {
        let layer = tiles.placed.layer;
        let res = i64::from(layer.tile_resolution);
        let (gx0, gy0) = (i64::from(tx) * res, i64::from(ty) * res);
        let (x0, y0) = (gx0.max(self.first.0), gy0.max(self.first.1));
        let x1 = (gx0 + res).min(self.first.0 + self.size.0 as i64);
        let y1 = (gy0 + res).min(self.first.1 + self.size.1 as i64);
        // This LOD's tile, or the nearest coarser one over it.
        let mut source = None;
        for up in lod..layer.num_lods {
            let shift = up - lod;
            let Ok(key) = TileKey::new(tiles.placed.index, up, tx >> shift, ty >> shift) else { break };
            if let Some(tile) = tiles.get(key)? {
                source = Some((shift, tile));
                break;
            }
        }
        let Some((shift, tile)) = source else { return Ok(()) };
        let border = i64::from(tile.border);
        if shift == 0
            && x0 < x1
            && let TileData::Heights { heights, .. } = &tile.data
        {
            // The tile's own samples: a row at a time (NaN is no data in both).
            let size = tile.size as usize;
            let len = (x1 - x0) as usize;
            for gy in y0..y1 {
                let src = (gy - gy0 + border) as usize * size + (x0 - gx0 + border) as usize;
                let dst = (gy - self.first.1) as usize * self.size.0 + (x0 - self.first.0) as usize;
                if let (Some(from), Some(to)) = (heights.get(src..src + len), self.values.get_mut(dst..dst + len)) {
                    to.copy_from_slice(from);
                }
            }
            return Ok(());
        }
        let scale = f64::from(1u32 << shift);
        let (ox, oy) = (i64::from(tile.key.x()) * res, i64::from(tile.key.y()) * res);
        for gy in y0..y1 {
            for gx in x0..x1 {
                let at = ((gy - self.first.1) as usize * self.size.0 + (gx - self.first.0) as usize) * self.channels;
                let v = if shift == 0 {
                    texel(&tile, gx - gx0 + border, gy - gy0 + border)
                } else {
                    // The coarser tile's bilinear value at this sample's centre.
                    let (cx, cy) =
                        ((gx as f64 + 0.5) / scale - 0.5 - ox as f64, (gy as f64 + 0.5) / scale - 0.5 - oy as f64);
                    coarse(&tile, cx, cy, res)
                };
                if let Some(v) = v {
                    self.values[at..at + self.channels].copy_from_slice(&v[..self.channels]);
                }
            }
        }
        Ok(())
    }

    /// The bilinear value at world `(x, z)` (sample `i` at `(i + 0.5)` spacings): no-data
    /// corners drop out and the others are re-weighted; None with no corner.
    #[expect(
        clippy::cast_possible_truncation,
        clippy::cast_sign_loss,
        clippy::cast_possible_wrap,
        reason = "sample indices inside one window"
    )]
    fn bilinear(&self, x: f64, z: f64) -> Option<[f32; 4]> {
        let (gx, gz) = (x / self.spacing - 0.5, z / self.spacing - 0.5);
        let (fi, fj) = (floor(gx), floor(gz));
        if self.channels == 1
            && let Some(h) = self.height_inside(fi as i64, fj as i64, (gx - fi) as f32, (gz - fj) as f32)
        {
            return Some([h, 0.0, 0.0, 0.0]);
        }
        let (fx, fz) = (gx - fi, gz - fj);
        let (i, j) = (fi as i64, fj as i64);
        if i < -1 || j < -1 || i >= self.grid.0 || j >= self.grid.1 {
            return None;
        }
        // No corner (clamped to the grid) in the window: none with data, known before the
        // weights (most points beyond a tile's data come here).
        #[expect(clippy::cast_possible_wrap, reason = "window sizes are far below 2^63")]
        let held = |k: i64, grid: i64, first: i64, size: usize| {
            [k, k + 1].iter().any(|&c| (0..size as i64).contains(&(c.clamp(0, grid - 1) - first)))
        };
        if !held(i, self.grid.0, self.first.0, self.size.0) || !held(j, self.grid.1, self.first.1, self.size.1) {
            return None;
        }
        let mut sum = [0f64; 4];
        let mut weight = 0.0;
        for (di, dj, w) in
            [(0, 0, (1.0 - fx) * (1.0 - fz)), (1, 0, fx * (1.0 - fz)), (0, 1, (1.0 - fx) * fz), (1, 1, fx * fz)]
        {
            // Clamped to the grid: the edge sample holds out to the grid's edge.
            let (si, sj) = ((i + di).clamp(0, self.grid.0 - 1), (j + dj).clamp(0, self.grid.1 - 1));
            let (wi, wj) = (si - self.first.0, sj - self.first.1);
            if wi < 0 || wj < 0 || wi >= self.size.0 as i64 || wj >= self.size.1 as i64 || w <= 0.0 {
                continue;
            }
            let at = (wj as usize * self.size.0 + wi as usize) * self.channels;
            let v = &self.values[at..at + self.channels];
            let has = if self.channels == 1 { v[0].is_finite() } else { v[3] > 0.0 };
            if !has {
                continue;
            }
            for (s, &c) in sum.iter_mut().zip(v) {
                *s += f64::from(c) * w;
            }
            weight += w;
        }
        if weight < 1e-9 {
            return None;
        }
        #[expect(clippy::cast_possible_truncation, reason = "samples are f32")]
        let out = sum.map(|s| (s / weight) as f32);
        Some(out)
    }
}

impl Window {
    /// The heights at `positions` (NaN: no data); None when none has data. The common
    /// case (four corners with data inside the window) in a loop of its own.
    #[expect(clippy::cast_possible_truncation, clippy::cast_sign_loss, reason = "checked to be inside the window")]
    fn heights(&self, positions: &Positions) -> Option<Vec<f32>> {
        let inverse = 1.0 / self.spacing;
        let (w, h) = (self.size.0 as i64, self.size.1 as i64);
        // Sample coordinates from one sample before the window's first: non-negative for
        // every point the fast path takes, so truncation is the floor (one conversion).
        let (ox, oz) = ((self.first.0 - 1) as f64 + 0.5, (self.first.1 - 1) as f64 + 0.5);
        let mut out = vec![f32::NAN; positions.len];
        let mut any = false;
        for run in &positions.runs {
            for (k, o) in out[run.at..run.at + run.len].iter_mut().enumerate() {
                let (x, z) = run.point(k);
                let (gx, gz) = (x * inverse - ox, z * inverse - oz);
                if gx >= 1.0 && gz >= 1.0 {
                    let (ix, iz) = (gx as i64, gz as i64);
                    let (wi, wj) = (ix - 1, iz - 1);
                    if wi + 1 < w && wj + 1 < h {
                        let at = wj as usize * self.size.0 + wi as usize;
                        let (fx, fz) = ((gx - ix as f64) as f32, (gz - iz as f64) as f32);
                        let v = &self.values;
                        let (a, b, c, d) = (v[at], v[at + 1], v[at + self.size.0], v[at + self.size.0 + 1]);
                        let value = (a + (b - a) * fx) * (1.0 - fz) + (c + (d - c) * fx) * fz;
                        if value.is_finite() {
                            *o = value;
                            any = true;
                            continue;
                        }
                    }
                }
                if let Some(v) = self.bilinear(x, z) {
                    *o = v[0];
                    any = true;
                }
            }
        }
        any.then_some(out)
    }

    /// The bilinear height at sample position `(i + fx, j + fz)` when its four samples lie
    /// in the window and all hold data (the common case, without the general path's
    /// per-corner checks); None otherwise.
    #[expect(clippy::cast_sign_loss, clippy::cast_possible_truncation, reason = "checked to be inside the window")]
    fn height_inside(&self, i: i64, j: i64, fx: f32, fz: f32) -> Option<f32> {
        let (wi, wj) = (i - self.first.0, j - self.first.1);
        if wi < 0 || wj < 0 || wi + 1 >= self.size.0 as i64 || wj + 1 >= self.size.1 as i64 {
            return None;
        }
        let at = wj as usize * self.size.0 + wi as usize;
        let (top, bottom) = (self.values.get(at..at + 2)?, self.values.get(at + self.size.0..at + self.size.0 + 2)?);
        let h = (top[0] * (1.0 - fx) + top[1] * fx) * (1.0 - fz) + (bottom[0] * (1.0 - fx) + bottom[1] * fx) * fz;
        // A NaN corner (no data) makes the sum NaN: the general path re-weights then.
        h.is_finite().then_some(h)
    }
}

/// `v` rounded down, without a call to the C library (x86-64's baseline has no rounding
/// instruction, and `f64::floor` became a call per sample).
#[expect(clippy::cast_possible_truncation, clippy::cast_precision_loss, reason = "sample positions, far below 2^52")]
fn floor(v: f64) -> f64 {
    let t = v as i64 as f64;
    if t > v { t - 1.0 } else { t }
}

/// Texel `(i, j)` of a decoded tile (borders included) as up to four values; None
/// without data.
fn texel(tile: &DecodedTile, i: i64, j: i64) -> Option<[f32; 4]> {
    let (Ok(i), Ok(j)) = (u32::try_from(i), u32::try_from(j)) else { return None };
    if i >= tile.size || j >= tile.size {
        return None;
    }
    let at = j as usize * tile.size as usize + i as usize;
    match &tile.data {
        TileData::Heights { heights, .. } => heights.get(at).filter(|h| h.is_finite()).map(|&h| [h, 0.0, 0.0, 0.0]),
        TileData::Rgba8(p) => {
            let px = p.get(at * 4..at * 4 + 4)?;
            (px[3] > 0).then(|| [f32::from(px[0]), f32::from(px[1]), f32::from(px[2]), f32::from(px[3])])
        }
        TileData::Compressed { .. } => None,
    }
}

/// A coarser tile's bilinear value at `(cx, cy)` in its interior's samples.
fn coarse(tile: &DecodedTile, cx: f64, cy: f64, res: i64) -> Option<[f32; 4]> {
    let border = i64::from(tile.border);
    let (fi, fj) = (cx.floor(), cy.floor());
    let (fx, fy) = (cx - fi, cy - fj);
    #[expect(clippy::cast_possible_truncation, reason = "inside one tile")]
    let (i, j) = (fi as i64, fj as i64);
    let mut sum = [0f64; 4];
    let mut weight = 0.0;
    for (di, dj, w) in
        [(0, 0, (1.0 - fx) * (1.0 - fy)), (1, 0, fx * (1.0 - fy)), (0, 1, (1.0 - fx) * fy), (1, 1, fx * fy)]
    {
        let (si, sj) = ((i + di).clamp(-border, res - 1 + border), (j + dj).clamp(-border, res - 1 + border));
        let Some(v) = texel(tile, si + border, sj + border) else { continue };
        for (s, c) in sum.iter_mut().zip(v) {
            *s += f64::from(c) * w;
        }
        weight += w;
    }
    #[expect(clippy::cast_possible_truncation, reason = "samples are f32")]
    (weight > 1e-9).then(|| sum.map(|s| (s / weight) as f32))
}

/// Archive tile `key` of `layer` decoded (GPU blocks to RGBA), from `cache` when it holds
/// it (and kept there when not): what web tiles and the elevation API read.
///
/// # Errors
/// [`MakeError::Tile`] for a tile that cannot be read or decoded.
pub(crate) fn load_tile(
    reader: &Reader<MmapSource>,
    layer: &Layer,
    key: TileKey,
    cache: Option<(&DecodedCache, u64)>,
) -> Result<Option<Arc<DecodedTile>>, MakeError> {
    if let Some((cache, version)) = cache
        && let Some(t) = cache.get(&(version, key))
    {
        return Ok(Some(t));
    }
    let bad = |reason: String| MakeError::Tile { key, reason };
    let Some(bytes) = reader.tile(key).map_err(|e| bad(e.to_string()))? else { return Ok(None) };
    let tile = decode(layer, key, &bytes, true).map_err(|e| bad(e.to_string()))?;
    let tile = Arc::new(tile.unblocked().map_err(|e| bad(e.to_owned()))?);
    if let Some((cache, version)) = cache {
        cache.put((version, key), Arc::clone(&tile));
    }
    Ok(Some(tile))
}

/// The archive tiles a web tile reads, decoded once each.
struct Tiles<'p, 'a> {
    placed: &'p Placed<'a>,
    decoded: HashMap<TileKey, Option<Arc<DecodedTile>>>,
}

impl Tiles<'_, '_> {
    fn get(&mut self, key: TileKey) -> Result<Option<Arc<DecodedTile>>, MakeError> {
        if let Some(t) = self.decoded.get(&key) {
            return Ok(t.clone());
        }
        let tile = load_tile(self.placed.reader, self.placed.layer, key, self.placed.cache)?;
        self.decoded.insert(key, tile.clone());
        Ok(tile)
    }
}

#[cfg(test)]
#[allow(clippy::cast_precision_loss, clippy::unwrap_used)]
mod tests {
    use super::*;

    /// A grid's positions through the approximate transform, then its border made exact:
    /// every point has one position, the border's are the exact ones bit for bit, the
    /// others unchanged.
    #[test]
    fn the_border_of_a_grid_is_exact_and_the_rest_unchanged() {
        let size = 17;
        // Pixel-edge coordinates to world; point (i, j) is at edge coordinates + 0.5.
        // Curved a little: the lattice's interpolation passes the 1/8-pixel check but
        // is not the exact transform.
        let exact = |u: f64, v: f64| Some((u + u * u * 1e-4 + v * 0.01, v + u * 0.02 + v * v * 1e-4));
        let mut approx = Positions { len: size * size, runs: vec![] };
        let corners = [exact(0.0, 0.0), exact(17.0, 0.0), exact(0.0, 17.0), exact(17.0, 17.0)];
        cell(&exact, &mut approx.runs, size, [0, 0, size, size], corners);
        let grid = |c: usize, r: usize| exact(c as f64 + 0.5, r as f64 + 0.5);
        let bordered = approx.clone().with_exact_border(size, grid);
        let mut seen = vec![0; size * size];
        for run in &bordered.runs {
            for k in 0..run.len {
                seen[run.at + k] += 1;
            }
        }
        assert!(seen.iter().all(|&n| n == 1), "every point once: {seen:?}");
        for i in 0..size * size {
            let (c, r) = (i % size, i / size);
            let got = bordered.point(i).unwrap();
            if c == 0 || r == 0 || c == size - 1 || r == size - 1 {
                assert_eq!(got, grid(c, r).unwrap(), "border point {c},{r}");
            } else {
                assert_eq!(got, approx.point(i).unwrap(), "inner point {c},{r}");
            }
        }
        // The approximation is not exact inside (or the test shows nothing).
        let inner = (1..size - 1).flat_map(|r| (1..size - 1).map(move |c| (c, r)));
        assert!(inner.clone().any(|(c, r)| approx.point(r * size + c) != grid(c, r)));
    }

    /// A window cropped out of a lattice holds the lattice's positions there, bit for
    /// bit, every point once.
    #[test]
    fn a_cropped_window_keeps_the_lattice_positions() {
        let size = 3 * LATTICE / 2;
        let exact = |u: f64, v: f64| Some((u + u * v * 1e-3, v - u * u * 2e-4));
        let mut whole = Positions { len: size * size, runs: vec![] };
        let corners = [exact(0.0, 0.0), exact(96.0, 0.0), exact(0.0, 96.0), exact(96.0, 96.0)];
        cell(&exact, &mut whole.runs, size, [0, 0, size, size], corners);
        assert!(whole.runs.len() > size, "the transform splits the cell (or the test shows little)");
        let [c0, r0, c1, r1] = [5, 7, 70, 90];
        let window = whole.clone().crop(size, [c0, r0, c1, r1]);
        let width = c1 - c0;
        assert_eq!(window.len(), width * (r1 - r0));
        let mut seen = vec![0; window.len()];
        for run in &window.runs {
            (run.at..run.at + run.len).for_each(|i| seen[i] += 1);
        }
        assert!(seen.iter().all(|&n| n == 1), "every point once");
        for i in 0..window.len() {
            let (c, r) = (c0 + i % width, r0 + i / width);
            assert_eq!(window.point(i), whole.point(r * size + c), "point {c},{r}");
        }
    }
}
