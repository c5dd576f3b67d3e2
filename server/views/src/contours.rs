//! Contour lines as Mapbox Vector Tiles: layer `contours`, properties `ele` (metres or
//! feet) and `major`.
//!
//! A tile's lines are traced (marching squares, saddles split by the cell's mean) on the
//! archive's own samples, as `gdal_contour` traces a DEM: those of the LOD the tile's
//! zoom reads (its samples no larger than the tile's pixels) under the tile and a margin
//! of [`MARGIN`] pixels. The crossings are then placed in the tile: exactly at nodes
//! every [`STRIDES`] samples of the LOD's grid (through the archive's CRS to degrees to
//! Web Mercator), bilinearly between them. Neighbouring tiles trace the same samples and
//! place them through the same nodes, so a line crossing a tile edge is the same curve on
//! both sides and continues without a gap; each tile's lines are clipped to the tile and
//! a buffer of 64 units of 4096 (4 pixels, inside the margin). Where the archive's
//! samples cannot serve (a footprint outside its CRS's domain, or one whose data holds
//! far more samples than the tile's pixels), the tile is traced on its heights resampled
//! to a 256-pixel grid with the margin instead ([`crate::relief`]'s window). Lines run
//! with the higher ground on their right, are simplified to a quarter of a pixel (every
//! vertex dropped within that of the line kept) and end where the data ends (a cell with a
//! corner without data draws nothing).

use std::cell::Cell;

use terrastream_format::{MmapSource, Reader};

use crate::mercator::WebTile;
use crate::mvt::{self, Line, Value};
use crate::relief::{margin_heights, placed_elevation, zoom_lod};
use crate::resample::{DecodedCache, MakeError};

/// Tile units a side.
pub const EXTENT: i32 = 4096;
/// Tile units drawn beyond each edge.
pub const BUFFER: i32 = 64;
/// Samples a side of the grid a tile is traced on.
const GRID: u32 = 256;
/// Samples of the grid's margin beyond each edge: the buffer's 4 and more, so every
/// line inside the buffer is traced whole (what lies beyond is clipped away).
pub const MARGIN: usize = 8;

/// Samples of the archive's grid between the nodes where a traced grid's positions in
/// the tile are exact (bilinear between): the first of these whose interpolation is off
/// by at most [`NODE_ERROR`] at the middles of the corner cells of the nodes, else the
/// last.
pub const STRIDES: [usize; 3] = [64, 16, 4];

/// Largest error of the positions between nodes, in tile units (16 a pixel).
pub const NODE_ERROR: f64 = 0.25;

/// A point in tile units.
type Point = (f64, f64);

/// Metres a foot.
const FOOT: f64 = 0.3048;

/// What a contour tile holds.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct ContourOptions {
    /// Height between lines (in `feet` or metres; finer than [`MIN_INTERVAL`] is taken as
    /// it); None: the zoom's default.
    pub interval: Option<f64>,
    /// Every how many lines a major one is (default 5).
    pub major: u32,
    /// Heights in feet rather than metres.
    pub feet: bool,
}

impl Default for ContourOptions {
    fn default() -> Self {
        Self { interval: None, major: 5, feet: false }
    }
}

/// The default interval of zoom `z` (metres, or feet in `feet`): dense enough to read
/// the terrain at that scale, sparse enough not to fill it (4 pixels apart on a 45-degree
/// slope at 45 degrees of latitude, rounded to 1, 2 or 5 times a power of ten): 100 m at
/// zoom 12, 20 m at zoom 14.
pub fn default_interval(z: u8, feet: bool) -> f64 {
    let metres = 40_075_016.686 * std::f64::consts::FRAC_1_SQRT_2 / (256.0 * f64::from(1u32 << z.min(24))) * 4.0;
    let target = if feet { metres / FOOT } else { metres };
    let power = 10f64.powf(target.log10().floor());
    let nice = [1.0, 2.0, 5.0, 10.0].into_iter().map(|m| m * power).find(|&v| v >= target * 0.7).unwrap_or(power);
    nice.max(1.0)
}

/// The contour tile of `tile`: MVT bytes; None when the tile has no data.
///
/// # Errors
/// [`MakeError::NotPlaced`] without placed elevation, [`MakeError::Tile`].
pub fn contour_tile(
    reader: &Reader<MmapSource>,
    tile: WebTile,
    options: ContourOptions,
    cache: Option<(&DecodedCache, u64)>,
) -> Result<Option<Vec<u8>>, MakeError> {
    let Some(mut grid) = grid_of(reader, tile, cache)? else { return Ok(None) };
    if options.feet {
        #[expect(clippy::cast_possible_truncation, reason = "heights are f32")]
        grid.heights.iter_mut().for_each(|h| *h = (f64::from(*h) / FOOT) as f32);
    }
    let interval = options.interval.filter(|i| *i > 0.0).unwrap_or_else(|| default_interval(tile.z, options.feet));
    let lines = trace(&grid.heights, grid.size, &grid.to_tile, interval, options.major.max(1));
    Ok(Some(mvt::encode("contours", EXTENT.unsigned_abs(), &lines)))
}

/// Samples a side of the resampled grid a contour tile is traced on where the archive's
/// own samples cannot serve (its 256 and the margin).
pub const SPAN: usize = GRID as usize + 2 * MARGIN;

/// The heights a contour tile is traced on, and where they lie.
#[derive(Clone, Debug)]
pub struct TraceGrid {
    /// Row by row (NaN: no data).
    pub heights: Vec<f32>,
    /// Samples across and down.
    pub size: (usize, usize),
    /// For a grid of the archive's own samples: the archive's CRS (as its metadata
    /// names it) and the grid's GDAL geotransform in it (the first sample's outer corner,
    /// then the sample size across and down); None for a resampled one.
    pub georeference: Option<(String, [f64; 6])>,
    to_tile: ToTile,
}

/// The grid a contour tile of `tile` is traced on: for checking the tracer against
/// another one on the same samples.
///
/// # Errors
/// As [`contour_tile`].
pub fn tile_grid(reader: &Reader<MmapSource>, tile: WebTile) -> Result<Option<TraceGrid>, MakeError> {
    grid_of(reader, tile, None)
}

/// The lines [`contour_tile`] draws from `grid`, in tile units.
pub fn trace_grid(grid: &TraceGrid, interval: f64, major: u32) -> Vec<Line> {
    trace(&grid.heights, grid.size, &grid.to_tile, interval, major.max(1))
}

/// Where a grid's samples lie in the tile (in tile units), fractional positions between.
#[derive(Clone, Debug)]
enum ToTile {
    /// Sample `(c, r)` at `((c + offset) * scale, (r + offset) * scale)`.
    Affine { offset: f64, scale: f64 },
    /// Exact at nodes every `stride` samples (node `(i, j)` at sample
    /// `origin + stride x (i, j)`, `across` a row, `down` rows), bilinear between.
    Nodes { origin: (f64, f64), stride: f64, across: usize, down: usize, nodes: Vec<(f64, f64)> },
}

impl ToTile {
    /// The point a fraction `t` along the edge from sample `(c, r)` to the next one
    /// across (`horizontal`) or down. Bilinear interpolation is linear along a grid line,
    /// so this is [`ToTile::at`] of the point, from the node cell of `(c, r)` (whose far
    /// side the edge reaches at most).
    #[expect(clippy::cast_precision_loss, reason = "sample indices of one tile's grid")]
    fn along(&self, tables: &NodeTables, c: usize, r: usize, t: f64, horizontal: bool) -> (f64, f64) {
        match self {
            Self::Affine { .. } => {
                if horizontal {
                    self.at(c as f64 + t, r as f64)
                } else {
                    self.at(c as f64, r as f64 + t)
                }
            }
            &Self::Nodes { across, ref nodes, .. } => {
                let ((i, mut fx), (j, mut fy)) = (tables.columns[c], tables.rows[r]);
                if horizontal {
                    fx += t * tables.inverse;
                } else {
                    fy += t * tables.inverse;
                }
                between_nodes(nodes, across, (i as usize, j as usize), (fx, fy))
            }
        }
    }

    /// Each column's and row's node cell and place in it, for [`ToTile::along`].
    #[expect(clippy::cast_possible_truncation, clippy::cast_sign_loss, reason = "clamped to the nodes")]
    #[expect(clippy::cast_precision_loss, reason = "sample indices of one tile's grid")]
    fn tables(&self, (w, h): (usize, usize)) -> NodeTables {
        let Self::Nodes { origin, stride, across, down, .. } = *self else { return NodeTables::default() };
        let inverse = 1.0 / stride;
        let place = |k: usize, origin: f64, count: usize| {
            let x = (k as f64 - origin) * inverse;
            let i = (x.max(0.0) as usize).min(count - 2);
            (i as u32, x - i as f64)
        };
        NodeTables {
            columns: (0..w).map(|c| place(c, origin.0, across)).collect(),
            rows: (0..h).map(|r| place(r, origin.1, down)).collect(),
            inverse,
        }
    }

    #[expect(clippy::cast_possible_truncation, clippy::cast_sign_loss, reason = "clamped to the nodes")]
    #[expect(clippy::cast_precision_loss, reason = "node indices")]
    fn at(&self, c: f64, r: f64) -> (f64, f64) {
        match self {
            Self::Affine { offset, scale } => ((c + offset) * scale, (r + offset) * scale),
            &Self::Nodes { origin, stride, across, down, ref nodes } => {
                let inverse = 1.0 / stride;
                let (x, y) = ((c - origin.0) * inverse, (r - origin.1) * inverse);
                let i = (x.max(0.0) as usize).min(across - 2);
                let j = (y.max(0.0) as usize).min(down - 2);
                between_nodes(nodes, across, (i, j), (x - i as f64, y - j as f64))
            }
        }
    }
}

/// The point a fraction `(fx, fy)` across node cell `(i, j)` (`across` nodes a row),
/// bilinearly.
fn between_nodes(nodes: &[Point], across: usize, (i, j): (usize, usize), (fx, fy): (f64, f64)) -> Point {
    let at = j * across + i;
    let (a, b, c, d) = (nodes[at], nodes[at + 1], nodes[at + across], nodes[at + across + 1]);
    let top = (a.0 + (b.0 - a.0) * fx, a.1 + (b.1 - a.1) * fx);
    let bottom = (c.0 + (d.0 - c.0) * fx, c.1 + (d.1 - c.1) * fx);
    (top.0 + (bottom.0 - top.0) * fy, top.1 + (bottom.1 - top.1) * fy)
}

/// Where each column and row of a grid lies among the nodes of a [`ToTile::Nodes`]: the
/// node cell's index and the fraction across it; and a node cell's fraction a sample.
#[derive(Default)]
struct NodeTables {
    columns: Vec<(u32, f64)>,
    rows: Vec<(u32, f64)>,
    inverse: f64,
}

/// The grid a contour tile is traced on: the archive's own samples where they can serve,
/// else its heights resampled (see the module's notes); None when the tile has no data.
fn grid_of(
    reader: &Reader<MmapSource>,
    tile: WebTile,
    cache: Option<(&DecodedCache, u64)>,
) -> Result<Option<TraceGrid>, MakeError> {
    match native_grid(reader, tile, cache)? {
        Native::Grid(grid) => return Ok(Some(grid)),
        Native::Empty => return Ok(None),
        Native::Unsuitable => {}
    }
    let Some(heights) = margin_heights(reader, tile, GRID, MARGIN, cache)? else { return Ok(None) };
    #[expect(clippy::cast_precision_loss, reason = "a small margin")]
    let offset = 0.5 - MARGIN as f64;
    let to_tile = ToTile::Affine { offset, scale: f64::from(EXTENT) / f64::from(GRID) };
    Ok(Some(TraceGrid { heights, size: (SPAN, SPAN), georeference: None, to_tile }))
}

/// What the archive's own samples give a tile.
enum Native {
    Grid(TraceGrid),
    /// No data under the tile.
    Empty,
    /// They cannot serve: trace on resampled heights.
    Unsuitable,
}

/// The archive's samples under `tile` and its margin, from the LOD its zoom reads.
#[expect(
    clippy::cast_precision_loss,
    clippy::cast_possible_truncation,
    clippy::cast_possible_wrap,
    clippy::cast_sign_loss,
    reason = "sample and node indices of one tile's window"
)]
fn native_grid(
    reader: &Reader<MmapSource>,
    tile: WebTile,
    cache: Option<(&DecodedCache, u64)>,
) -> Result<Native, MakeError> {
    let placed = placed_elevation(reader, cache)?;
    let metadata = placed.metadata();
    let lod = zoom_lod(&placed, tile, f64::from(GRID));
    let layer = placed.layer();
    let spacing = layer.world_size_at(lod) / f64::from(layer.tile_resolution);
    // The footprint of the tile and its buffer: its outline's points, in world units
    // (what lies beyond is clipped away; a sample more is added below).
    let (size, margin) = (f64::from(GRID), f64::from(BUFFER * GRID.cast_signed() / EXTENT));
    let (mut lo, mut hi) = ((f64::INFINITY, f64::INFINITY), (f64::NEG_INFINITY, f64::NEG_INFINITY));
    // The outline's points on each edge (five: the transforms are what this costs), and
    // how far the outline bulges from a straight line between two of them, measured at
    // the middle of each edge's first stretch.
    const POINTS: u32 = 4;
    let side = size + 2.0 * margin;
    let at = |edge: usize, t: f64| {
        let t = -margin + side * t;
        let (u, v) = [(t, -margin), (t, size + margin), (-margin, t), (size + margin, t)][edge];
        let (lon, lat) = tile.lon_lat(u, v, size);
        placed.world(lon, lat)
    };
    let mut bulge: f64 = 0.0;
    for edge in 0..4 {
        let mut points = [(0.0, 0.0); POINTS as usize + 1];
        for (k, point) in points.iter_mut().enumerate() {
            let Some(p) = at(edge, k as f64 / f64::from(POINTS)) else { return Ok(Native::Unsuitable) };
            *point = p;
            (lo, hi) = ((lo.0.min(p.0), lo.1.min(p.1)), (hi.0.max(p.0), hi.1.max(p.1)));
        }
        let Some(middle) = at(edge, 0.5 / f64::from(POINTS)) else { return Ok(Native::Unsuitable) };
        let (a, b) = (points[0], points[1]);
        bulge = bulge.max((middle.0 - (a.0 + b.0) / 2.0).hypot(middle.1 - (a.1 + b.1) / 2.0));
    }
    // A sample beyond, and twice the bulge.
    let pad = spacing + 2.0 * bulge;
    let (lo, hi) = ((lo.0 - pad, lo.1 - pad), (hi.0 + pad, hi.1 + pad));
    // What of it holds data (a tile far larger than the archive reads only the archive).
    let [wx0, wz0, wx1, wz1] = layer.data_world();
    let (w, h) = ((hi.0.min(wx1) - lo.0.max(wx0)).max(0.0), (hi.1.min(wz1) - lo.1.max(wz0)).max(0.0));
    if w * h > (4 * SPAN * SPAN) as f64 * spacing * spacing {
        return Ok(Native::Unsuitable);
    }
    let Some(samples) = placed.samples_in(lo, hi, lod)? else { return Ok(Native::Empty) };
    if !samples.values.iter().any(|h| h.is_finite()) {
        return Ok(Native::Empty);
    }
    let (w, h) = samples.size;
    if w < 2 || h < 2 {
        return Ok(Native::Empty);
    }
    // Sample (gi, gj) of the LOD's grid in tile units, exactly.
    let (count, extent) = (tile.count(), f64::from(EXTENT));
    let exact = |gi: f64, gj: f64| {
        let (lon, lat) = placed.degrees((gi + 0.5) * spacing, (gj + 0.5) * spacing)?;
        let fx = (lon + 180.0) / 360.0 * count - f64::from(tile.x);
        let fy = (1.0 - lat.to_radians().tan().asinh() / std::f64::consts::PI) / 2.0 * count - f64::from(tile.y);
        (fx.is_finite() && fy.is_finite()).then_some((fx * extent, fy * extent))
    };
    let mut to_tile = None;
    for stride in STRIDES {
        // The nodes: every `stride` samples of the LOD's grid (the same for every tile),
        // from the one at or before the window's first to the one at or after its last.
        let stride = stride as i64;
        let (n0, m0) = (samples.first.0.div_euclid(stride) * stride, samples.first.1.div_euclid(stride) * stride);
        let across = ((samples.first.0 + w as i64 - 1 - n0 + stride - 1) / stride + 1).max(2) as usize;
        let down = ((samples.first.1 + h as i64 - 1 - m0 + stride - 1) / stride + 1).max(2) as usize;
        let mut nodes = Vec::with_capacity(across * down);
        for j in 0..down {
            for i in 0..across {
                let Some(p) = exact((n0 + i as i64 * stride) as f64, (m0 + j as i64 * stride) as f64) else {
                    return Ok(Native::Unsuitable);
                };
                nodes.push(p);
            }
        }
        let origin = ((n0 - samples.first.0) as f64, (m0 - samples.first.1) as f64);
        let nodes = ToTile::Nodes { origin, stride: stride as f64, across, down, nodes };
        // The interpolation checked at the middles of the corner cells of the nodes.
        let half = stride as f64 / 2.0;
        let off = |(gi, gj): (i64, i64)| {
            let (gi, gj) = (gi as f64 + half, gj as f64 + half);
            let (a, b) = (exact(gi, gj), nodes.at(gi - samples.first.0 as f64, gj - samples.first.1 as f64));
            a.map_or(f64::INFINITY, |a| (a.0 - b.0).hypot(a.1 - b.1))
        };
        let (last_i, last_j) = (n0 + (across as i64 - 2) * stride, m0 + (down as i64 - 2) * stride);
        let worst = [(n0, m0), (last_i, m0), (n0, last_j), (last_i, last_j)].map(off).into_iter().fold(0.0, f64::max);
        if worst <= NODE_ERROR || stride == STRIDES[STRIDES.len() - 1] as i64 {
            to_tile = Some(nodes);
            break;
        }
    }
    let Some(to_tile) = to_tile else { return Ok(Native::Unsuitable) };
    let georeference = metadata.georeference.as_ref().and_then(|g| {
        let crs = g.definition.clone().or_else(|| g.crs.clone())?;
        let (x0, y0) = placed.crs_coordinates(samples.first.0 as f64 * spacing, samples.first.1 as f64 * spacing);
        let (x1, y1) =
            placed.crs_coordinates((samples.first.0 + 1) as f64 * spacing, (samples.first.1 + 1) as f64 * spacing);
        Some((crs, [x0, x1 - x0, 0.0, y0, 0.0, y1 - y0]))
    });
    Ok(Native::Grid(TraceGrid { heights: samples.values, size: (w, h), georeference, to_tile }))
}

/// The TileJSON 3.0.0 document of an archive's contours (`name`: its URL name), a vector
/// source whose `vector_layers` name the layer and its fields.
pub fn tilejson(
    name: &str,
    description: &str,
    tiles: String,
    coverage: crate::tilejson::Coverage,
) -> serde_json::Value {
    let [w, s, e, n] = coverage.bounds;
    serde_json::json!({
        "tilejson": "3.0.0",
        "name": format!("{name} contours"),
        "description": description,
        "version": "1.0.0",
        "scheme": "xyz",
        "type": "vector",
        "format": "pbf",
        "tiles": [tiles],
        "minzoom": 0,
        "maxzoom": coverage.maxzoom,
        "bounds": [w, s, e, n],
        "center": [(w + e) / 2.0, (s + n) / 2.0, coverage.maxzoom.saturating_sub(3)],
        "vector_layers": [{
            "id": "contours",
            "description": "Contour lines: ele, the height (metres or feet); major, every fifth (or as asked)",
            "minzoom": 0,
            "maxzoom": coverage.maxzoom,
            "fields": { "ele": "Number", "major": "Boolean" },
        }],
    })
}

/// Every contour of `heights` (`size` samples across and down, placed in the tile by
/// `to_tile`), clipped to the tile and its buffer, in tile units.
#[expect(clippy::cast_possible_truncation, reason = "levels of finite heights; vertices within the buffered tile")]
fn trace(heights: &[f32], size: (usize, usize), to_tile: &ToTile, interval: f64, major: u32) -> Vec<Line> {
    let interval = interval.max(MIN_INTERVAL);
    // The buffers of the tile before on this thread (as large as a tile's grid: new ones
    // would cost their pages' first touch each time); taken, so a panic leaves none.
    let mut scratch = SCRATCH.with(Cell::take);
    bands(heights, interval, &mut scratch.bands);
    let bands = &scratch.bands;
    // The levels some cell crosses lie above the lowest band and up to the highest.
    let Some((lowest, highest)) = band_range(bands) else {
        SCRATCH.with(|s| s.set(scratch));
        return vec![];
    };
    let (first, last) = (i64::from(lowest) + 1, i64::from(highest));
    let mut lines = vec![];
    // Edge keys: a row's columns in `shift` bits (no division to find them again).
    let shift = size.0.next_power_of_two().trailing_zeros();
    let mut levels = std::mem::take(&mut scratch.levels);
    segments(heights, bands, size, shift, interval, (first, last), &mut scratch.crossed, &mut levels);
    let links = &mut scratch.links;
    // Kept when large enough: a walk leaves every entry as it found it.
    let keys = (size.1 << shift) * 2;
    if links.next.len() < keys {
        *links = Links::new(keys);
    }
    let mut chain = std::mem::take(&mut scratch.chain);
    let tables = to_tile.tables(size);
    for (k, segments) in (first..=last).zip(&levels) {
        let level = k as f64 * interval;
        let is_major = k.rem_euclid(i64::from(major)) == 0;
        let grid = (heights, size.0, shift);
        level_chains(grid, (to_tile, &tables), level, segments, links, &mut chain, &mut |chain| {
            clip(chain, &mut |piece| {
                let piece = simplify_anchored(piece, 4.0);
                let points: Vec<(i32, i32)> = dedup(piece.iter().map(|&(x, y)| (x.round() as i32, y.round() as i32)));
                if points.len() >= 2 {
                    lines.push(Line {
                        points,
                        properties: vec![("ele", Value::Number(level)), ("major", Value::Bool(is_major))],
                    });
                }
            });
        });
    }
    scratch.chain = chain;
    scratch.levels = levels;
    SCRATCH.with(|s| s.set(scratch));
    lines
}

/// Buffers a tile's tracing reuses from the tile before on its thread.
#[derive(Default)]
struct Scratch {
    bands: Vec<i32>,
    /// A row's cells some level crosses.
    crossed: Vec<u8>,
    links: Links,
    /// The chain being walked.
    chain: Vec<(f64, f64)>,
    /// Each level's segments.
    levels: Vec<Vec<(u32, u32)>>,
}

thread_local! {
    static SCRATCH: Cell<Scratch> = Cell::new(Scratch::default());
}

/// An edge of the sample grid (`shift` bits for a row's columns): (column, row,
/// horizontal?) as one key, in the grid's order.
#[expect(clippy::cast_possible_truncation, reason = "keys of one tile's grid")]
fn edge_key(shift: u32, c: usize, r: usize, horizontal: bool) -> u32 {
    ((((r << shift) | c) << 1) | usize::from(horizontal)) as u32
}

/// Marching squares over every level `first..=last` (x `interval`) in one pass over the
/// grid: for each level, the segments (pairs of edge keys) its cells hold, in the
/// cells' order. Each sample's band (the highest level at or below it) is found once; a
/// cell then visits only the levels between its corners' bands, and most cells none.
#[expect(clippy::cast_sign_loss, clippy::cast_possible_truncation, reason = "level indices within first..=last")]
#[expect(clippy::too_many_arguments, reason = "the grid, the levels and the buffers reused")]
fn segments(
    h: &[f32],
    bands: &[i32],
    (span, rows): (usize, usize),
    shift: u32,
    interval: f64,
    (first, last): (i64, i64),
    crossed: &mut Vec<u8>,
    out: &mut Vec<Vec<(u32, u32)>>,
) {
    let count = usize::try_from(last - first + 1).unwrap_or(0);
    // The vectors of the tile before, emptied (their room kept).
    out.resize_with(count.max(out.len()), Vec::new);
    out.iter_mut().for_each(Vec::clear);
    out.truncate(count.max(64));
    let key = |c: usize, r: usize, horizontal: bool| edge_key(shift, c, r, horizontal);
    crossed.resize(span, 0);
    for r in 0..rows.saturating_sub(1) {
        let (upper, lower) = (&bands[r * span..(r + 1) * span], &bands[(r + 1) * span..(r + 2) * span]);
        // Most cells lie within one band: no level crosses them. Which do not, for the
        // whole row at once (a loop without branches, which the compiler vectorises).
        for (((flag, u), l), (u1, l1)) in
            crossed.iter_mut().zip(upper).zip(lower).zip(upper[1..].iter().zip(&lower[1..]))
        {
            *flag = u8::from(((u ^ u1) | (u ^ l) | (u ^ l1)) != 0);
        }
        for c in (0..span - 1).filter(|&c| crossed[c] != 0) {
            let at = r * span + c;
            let b = [bands[at], bands[at + 1], bands[at + span + 1], bands[at + span]];
            let (lo, hi) = (b[0].min(b[1]).min(b[2].min(b[3])), b[0].max(b[1]).max(b[2].max(b[3])));
            // A level crosses where a corner lies below it and one at or above it.
            if lo == NO_DATA {
                continue;
            }
            let (lo, hi) = (i64::from(lo), i64::from(hi));
            let edges = [key(c, r, true), key(c + 1, r, false), key(c, r + 1, true), key(c, r, false)];
            let mean = || {
                (f64::from(h[at]) + f64::from(h[at + 1]) + f64::from(h[at + span + 1]) + f64::from(h[at + span])) / 4.0
            };
            for k in (lo + 1).max(first)..=hi.min(last) {
                let case = b.iter().enumerate().fold(0, |m, (i, &band)| m | (usize::from(i64::from(band) >= k) << i));
                let out = &mut out[(k - first) as usize];
                // The case's segments from a table (a jump a case mispredicts), each
                // directed with the ground above the level on its right (north up): a
                // corner's case and its complement's run opposite ways. A saddle's pair by
                // the cell's mean.
                let variant = if case == 5 || case == 10 { usize::from(mean() >= k as f64 * interval) } else { 0 };
                let (n, pairs) = CASES[variant][case];
                for &(from, to) in &pairs[..usize::from(n)] {
                    out.push((edges[usize::from(from)], edges[usize::from(to)]));
                }
            }
        }
    }
}

/// The segments of each marching-squares case (corners above the level: bit 0 top left,
/// 1 top right, 2 bottom right, 3 bottom left), as pairs of a cell's edges (0 top,
/// 1 right, 2 bottom, 3 left) directed with the ground above the level on the right
/// (north up): how many, and the pairs. The saddles (5 and 10) as when the cell's mean lies
/// below the level; `[1]`: as when it lies at or above it.
const CASES: [[CaseSegments; 16]; 2] = {
    const NONE: CaseSegments = (0, [(0, 0); 2]);
    const fn one(from: u8, to: u8) -> CaseSegments {
        (1, [(from, to), (0, 0)])
    }
    let (t, r, b, l) = (0, 1, 2, 3);
    let below = [
        NONE,
        one(t, l),
        one(r, t),
        one(r, l),
        one(b, r),
        (2, [(t, l), (b, r)]),
        one(b, t),
        one(b, l),
        one(l, b),
        one(t, b),
        (2, [(l, b), (r, t)]),
        one(r, b),
        one(l, r),
        one(t, r),
        one(l, t),
        NONE,
    ];
    let mut above = below;
    above[5] = (2, [(b, l), (t, r)]);
    above[10] = (2, [(l, t), (r, b)]);
    [below, above]
};

/// How many segments a case has, and each one's edges (from, to).
type CaseSegments = (u8, [(u8, u8); 2]);

/// A band no sample without data is in (below every level).
const NO_DATA: i32 = i32::MIN;

/// The finest interval traced: finer ones are taken as this (heights of tens of
/// kilometres then still have bands well inside an `i32`).
pub const MIN_INTERVAL: f64 = 1e-3;

/// Each sample's band: the highest `k` with `k x interval` at or below it (exactly as the
/// levels compare: `v >= k as f64 * interval`); [`NO_DATA`] for a value that is not
/// finite. Without a branch or a library call, so the compiler vectorises it: the
/// quotient by a multiplication, rounded down, then made exact by one step either way
/// (the product's rounding is far below one band).
#[expect(clippy::cast_possible_truncation, reason = "bands of heights, clamped to +-2^30")]
fn bands(heights: &[f32], interval: f64, out: &mut Vec<i32>) {
    const LIMIT: f64 = (1u32 << 30) as f64;
    // Added to a whole number below 2^51 in magnitude: the sum's low 32 bits are that
    // number as an i32, and the sum less it is a number rounded to a whole one.
    const MAGIC: f64 = 6_755_399_441_055_744.0;
    let inverse = 1.0 / interval;
    let one = |yes: bool| if yes { 1.0 } else { 0.0 };
    out.clear();
    out.extend(heights.iter().map(|&h| {
        let v = f64::from(h);
        let q = (v * inverse).clamp(-LIMIT, LIMIT);
        let nearest = (q + MAGIC) - MAGIC;
        let k = nearest - one(nearest > q);
        let k = k + one((k + 1.0) * interval <= v) - one(k * interval > v);
        if h.is_finite() { (k + MAGIC).to_bits() as u32 as i32 } else { NO_DATA }
    }));
}

/// The lowest and highest band of the samples with data; None when none has.
fn band_range(bands: &[i32]) -> Option<(i32, i32)> {
    let highest = bands.iter().copied().max()?;
    let lowest = bands.iter().map(|&b| if b == NO_DATA { i32::MAX } else { b }).min()?;
    (highest != NO_DATA).then_some((lowest, highest))
}

/// The crossings of `level` joined into chains, in tile units, from its `segments`: each
/// given to `each` (built in `chain`).
fn level_chains(
    (h, span, shift): (&[f32], usize, u32),
    (to_tile, tables): (&ToTile, &NodeTables),
    level: f64,
    segments: &[(u32, u32)],
    links: &mut Links,
    chain: &mut Vec<(f64, f64)>,
    each: &mut dyn FnMut(&[Point]),
) {
    let value = |c: usize, r: usize| f64::from(h[r * span + c]);
    let crossing = |k: usize| {
        let (horizontal, at) = (k & 1 == 1, k >> 1);
        let (c, r) = (at & ((1 << shift) - 1), at >> shift);
        let (a, b) = if horizontal { (value(c, r), value(c + 1, r)) } else { (value(c, r), value(c, r + 1)) };
        let t = ((level - a) / (b - a)).clamp(0.0, 1.0);
        to_tile.along(tables, c, r, t, horizontal)
    };
    for &(a, b) in segments {
        links.join(a as usize, b);
    }
    // Walk the links: open chains from their starts first (in the cells' order), then
    // the closed loops; each entry walked is emptied.
    for open in [true, false] {
        for &(start, _) in segments {
            let start = start as usize;
            if links.next[start] == NONE || (open && links.entered[start]) {
                continue;
            }
            chain.clear();
            chain.push(crossing(start));
            let mut at = start;
            while links.next[at] != NONE {
                let next = links.next[at] as usize;
                links.next[at] = NONE;
                links.entered[next] = false;
                chain.push(crossing(next));
                at = next;
            }
            if chain.len() >= 2 {
                each(chain);
            }
        }
    }
}

/// No link.
const NONE: u32 = u32::MAX;

/// The links between the edges of a grid that a level's directed segments join, by edge
/// key: an edge is in two cells, and a level crossing it leaves one cell by it and
/// enters the other, so it has at most one link out and one in. Dense, reused from
/// level to level: a walk empties every entry it touches.
#[derive(Default)]
struct Links {
    /// The edge a segment goes on to from this one; [`NONE`].
    next: Vec<u32>,
    /// Whether a segment comes to this edge.
    entered: Vec<bool>,
}

impl Links {
    fn new(keys: usize) -> Self {
        Self { next: vec![NONE; keys], entered: vec![false; keys] }
    }

    fn join(&mut self, from: usize, to: u32) {
        self.next[from] = to;
        self.entered[to as usize] = true;
    }
}

/// The parts of a polyline inside the tile and its buffer, each given to `piece`.
fn clip(line: &[Point], piece: &mut dyn FnMut(&[Point])) {
    let (lo, hi) = (f64::from(-BUFFER), f64::from(EXTENT + BUFFER));
    let inside = |p: (f64, f64)| (lo..=hi).contains(&p.0) && (lo..=hi).contains(&p.1);
    // Most lines lie wholly inside: themselves, as they are.
    if line.iter().all(|&p| inside(p)) {
        if line.len() >= 2 {
            piece(line);
        }
        return;
    }
    // A closed line that leaves the box and starts inside it: its last piece runs on into
    // its first (one line, not two ending at an arbitrary point), so the first is held.
    let closed = line.len() > 2 && line.first() == line.last() && inside(line[0]);
    let mut held: Option<Vec<Point>> = None;
    let mut current: Vec<Point> = Vec::with_capacity(line.len());
    let mut end = |current: &mut Vec<Point>| {
        if closed && held.is_none() {
            held = Some(std::mem::take(current));
        } else if current.len() >= 2 {
            piece(current);
        }
        current.clear();
    };
    let mut a_inside = inside(line[0]);
    for pair in line.windows(2) {
        let (a, b) = (pair[0], pair[1]);
        let b_inside = inside(b);
        if a_inside && b_inside {
            // Wholly inside (what Liang-Barsky gives too, without its divisions).
            if current.is_empty() {
                current.push(a);
            }
            current.push(b);
            continue;
        }
        a_inside = b_inside;
        // Liang-Barsky: the part of segment a-b inside the box.
        let (dx, dy) = (b.0 - a.0, b.1 - a.1);
        let (mut t0, mut t1) = (0.0f64, 1.0f64);
        let mut visible = true;
        for (p, q) in [(-dx, a.0 - lo), (dx, hi - a.0), (-dy, a.1 - lo), (dy, hi - a.1)] {
            if p == 0.0 {
                visible &= q >= 0.0;
            } else if p < 0.0 {
                t0 = t0.max(q / p);
            } else {
                t1 = t1.min(q / p);
            }
        }
        if !visible || t0 > t1 {
            if !current.is_empty() {
                end(&mut current);
            }
            continue;
        }
        let (p0, p1) = ((a.0 + t0 * dx, a.1 + t0 * dy), (a.0 + t1 * dx, a.1 + t1 * dy));
        if current.is_empty() {
            current.push(p0);
        }
        current.push(p1);
        if t1 < 1.0 || !b_inside {
            end(&mut current);
        }
    }
    match held.take() {
        // The last piece (it ends at the line's start, inside) and then the first.
        Some(first) if !current.is_empty() => {
            current.extend(first.into_iter().skip(1));
            if current.len() >= 2 {
                piece(&current);
            }
        }
        Some(first) => {
            if first.len() >= 2 {
                piece(&first);
            }
        }
        None => {
            if current.len() >= 2 {
                piece(&current);
            }
        }
    }
}

/// [`simplify`] between anchors: the points where the line crosses the tile's edges are
/// added and kept, so that neighbours, which trace the same curve, keep the same crossing
/// and the line goes on from it.
fn simplify_anchored(line: &[(f64, f64)], tolerance: f64) -> Vec<(f64, f64)> {
    let edge = f64::from(EXTENT);
    // Strictly between a segment's ends: a cut at a `t` inside (0, 1) (the division,
    // which is monotonic, only where it is).
    let between = |v: f64, a: f64, b: f64| (a < v && v < b) || (b < v && v < a);
    let crosses =
        |a: (f64, f64), b: (f64, f64)| [0.0, edge].iter().any(|&v| between(v, a.0, b.0) || between(v, a.1, b.1));
    // Most lines cross no edge of the tile: one part, nothing added.
    if !line.windows(2).any(|pair| crosses(pair[0], pair[1])) {
        return simplify(line, tolerance);
    }
    let mut points = vec![line[0]];
    let mut anchors = vec![0];
    for pair in line.windows(2) {
        let (a, b) = (pair[0], pair[1]);
        if crosses(a, b) {
            let mut cuts: Vec<f64> = [0.0, edge]
                .iter()
                .flat_map(|&v| [((v - a.0) / (b.0 - a.0)), ((v - a.1) / (b.1 - a.1))])
                .filter(|t| t.is_finite() && *t > 0.0 && *t < 1.0)
                .collect();
            cuts.sort_by(f64::total_cmp);
            for t in cuts {
                points.push((a.0 + t * (b.0 - a.0), a.1 + t * (b.1 - a.1)));
                anchors.push(points.len() - 1);
            }
        }
        points.push(b);
    }
    anchors.push(points.len() - 1);
    anchors.dedup();
    let mut out: Vec<(f64, f64)> = vec![];
    for pair in anchors.windows(2) {
        let part = simplify(&points[pair[0]..=pair[1]], tolerance);
        out.extend(part.into_iter().skip(usize::from(!out.is_empty())));
    }
    out
}

/// The vertices to keep so that no dropped one is further than `tolerance` from the
/// simplified line through its neighbours kept (the distance to that line, as
/// Douglas-Peucker measures it), in one pass (Zhao and Saalfeld's sleeve): from each
/// vertex kept, the directions within `tolerance` of every vertex since narrow to a
/// wedge; the line goes on to the last vertex whose direction lies in the wedge of those
/// before it, which is kept when the next one does not.
fn simplify(line: &[Point], tolerance: f64) -> Vec<Point> {
    let n = line.len();
    if n <= 2 {
        return line.to_vec();
    }
    let cross = |a: Point, b: Point| a.0 * b.1 - a.1 * b.0;
    let mut out = Vec::with_capacity(n);
    out.push(line[0]);
    let mut anchor = line[0];
    // The wedge of directions from the anchor (counter-clockwise from the first to the
    // second, narrower than a half turn); None: any.
    let mut wedge: Option<(Point, Point)> = None;
    let (mut last, mut i) = (0, 1);
    while i < n {
        let p = line[i];
        let v = (p.0 - anchor.0, p.1 - anchor.1);
        let d2 = v.0 * v.0 + v.1 * v.1;
        let near = d2 <= tolerance * tolerance;
        if near && wedge.is_none() {
            // Within the tolerance of the anchor, and all before it: on every line from it.
            last = i;
            i += 1;
            continue;
        }
        if let Some((lo, hi)) = wedge
            && (d2 == 0.0 || cross(lo, v) < 0.0 || cross(v, hi) < 0.0)
        {
            // Beyond the wedge: the line ends at the last vertex inside it.
            anchor = line[last];
            out.push(anchor);
            wedge = None;
            i = last + 1;
            continue;
        }
        if near {
            // A line to it is within the wedge, and any line from the anchor passes
            // within the tolerance of it.
            last = i;
            i += 1;
            continue;
        }
        // The directions within `tolerance` of this vertex: its own, turned either way by
        // the angle whose sine is tolerance / distance (scaled by the distance: only
        // directions count).
        let (sin, cos) = (tolerance, (d2 - tolerance * tolerance).sqrt());
        let (l, h) = ((v.0 * cos + v.1 * sin, v.1 * cos - v.0 * sin), (v.0 * cos - v.1 * sin, v.1 * cos + v.0 * sin));
        wedge = Some(match wedge {
            None => (l, h),
            Some((lo, hi)) => (if cross(lo, l) > 0.0 { l } else { lo }, if cross(h, hi) > 0.0 { h } else { hi }),
        });
        if let Some((lo, hi)) = wedge
            && cross(lo, hi) < 0.0
        {
            // No direction is left: this vertex is the line's end, and the next start.
            anchor = p;
            out.push(anchor);
            wedge = None;
        }
        last = i;
        i += 1;
    }
    if out.last() != line.last() {
        out.push(line[n - 1]);
    }
    out
}

fn dedup(points: impl Iterator<Item = (i32, i32)>) -> Vec<(i32, i32)> {
    let mut out: Vec<(i32, i32)> = vec![];
    for p in points {
        if out.last() != Some(&p) {
            out.push(p);
        }
    }
    out
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A cone: every contour a circle around the middle, closed, at its own level.
    #[test]
    #[expect(clippy::cast_possible_truncation, reason = "test heights")]
    fn a_cone_gives_one_closed_ring_a_level() {
        let span = SPAN;
        let middle = span as f64 / 2.0;
        let heights: Vec<f32> = (0..span * span)
            .map(|i| {
                let (c, r) = ((i % span) as f64, (i / span) as f64);
                (1000.0 - (c - middle).hypot(r - middle) * 10.0) as f32
            })
            .collect();
        let to_tile = ToTile::Affine { offset: 0.5 - MARGIN as f64, scale: 16.0 };
        let lines = trace(&heights, (span, span), &to_tile, 100.0, 5);
        let levels: Vec<f64> = lines.iter().filter_map(|l| l.properties[0].1.number()).collect();
        // Rings of radius 10 to 130 samples lie inside the tile and its buffer; each once.
        for level in [900.0, 800.0, 700.0] {
            assert_eq!(levels.iter().filter(|&&l| l == level).count(), 1, "{level}: {levels:?}");
        }
        let ring = lines.iter().find(|l| l.properties[0].1 == Value::Number(900.0)).unwrap();
        assert_eq!(ring.points.first(), ring.points.last(), "closed");
        // Directed with the higher ground on the right (y down): clockwise round a peak,
        // anticlockwise round a pit.
        let area = |points: &[(i32, i32)]| {
            points
                .windows(2)
                .map(|w| i64::from(w[0].0) * i64::from(w[1].1) - i64::from(w[1].0) * i64::from(w[0].1))
                .sum::<i64>()
        };
        assert!(area(&ring.points) > 0, "clockwise round the peak");
        let pit: Vec<f32> = heights.iter().map(|h| 2000.0 - h).collect();
        let lines = trace(&pit, (span, span), &to_tile, 100.0, 5);
        let ring = lines.iter().find(|l| l.properties[0].1 == Value::Number(1100.0)).unwrap();
        assert!(area(&ring.points) < 0, "anticlockwise round the pit");
        assert!(lines.iter().any(|l| l.properties[1].1 == Value::Bool(true)), "500 m and 1000 m are major");
    }

    /// The bands found without branches are the highest `k` with `k x interval` at or
    /// below the height, as the levels compare, at and next to every level.
    #[test]
    #[expect(clippy::cast_possible_truncation, clippy::cast_precision_loss, reason = "test heights")]
    fn bands_are_exact_at_and_beside_every_level() {
        let reference = |v: f32, interval: f64| {
            let v = f64::from(v);
            let mut k = (v / interval).floor() as i64;
            while (k + 1) as f64 * interval <= v {
                k += 1;
            }
            while k as f64 * interval > v {
                k -= 1;
            }
            i32::try_from(k).unwrap()
        };
        // 0.7: its inverse rounded, -65534 x it lands on -93620 exactly, but -93620 x 0.7
        // lies above -65534 (the band is -93621).
        for interval in [MIN_INTERVAL, 0.1, 0.3, 0.7, 1.0, 7.0, 20.0, 25.4, 100.0, 1000.0] {
            let mut heights = vec![];
            for k in (-40..400).chain(-93_700..-93_500) {
                let at = (f64::from(k) * interval * 23.0 / 7.0) as f32;
                let level = (f64::from(k) * interval) as f32;
                for h in [at, level] {
                    let beside = [f32::from_bits(h.to_bits() + 1), f32::from_bits(h.to_bits().wrapping_sub(1))];
                    heights.extend(std::iter::once(h).chain(beside).filter(|h| h.is_finite()));
                }
            }
            heights.extend([0.0, -0.0, 8848.86, -10_994.0, 1e-7, -1e-7]);
            let mut out = vec![];
            bands(&heights, interval, &mut out);
            for (&h, &b) in heights.iter().zip(&out) {
                assert_eq!(b, reference(h, interval), "{h} at {interval}");
            }
        }
        let mut out = vec![];
        bands(&[f32::NAN, f32::INFINITY, f32::NEG_INFINITY, 5.0], 1.0, &mut out);
        assert_eq!(out, [NO_DATA, NO_DATA, NO_DATA, 5]);
        assert_eq!(band_range(&out), Some((5, 5)));
        assert_eq!(band_range(&out[..3]), None, "no data, no levels");
    }

    fn clipped(line: &[(f64, f64)]) -> Vec<Vec<(f64, f64)>> {
        let mut pieces = vec![];
        clip(line, &mut |p| pieces.push(p.to_vec()));
        pieces
    }

    #[test]
    fn a_closed_line_leaving_the_box_is_one_piece_from_exit_to_exit() {
        let hi = f64::from(EXTENT + BUFFER) + 100.0;
        // A ring starting inside the box, going out across its right edge and back.
        let ring = [(4000.0, 2000.0), (hi, 2000.0), (hi, 2200.0), (4000.0, 2200.0), (4000.0, 2000.0)];
        let pieces = clipped(&ring);
        assert_eq!(pieces.len(), 1, "{pieces:?}");
        let piece = &pieces[0];
        assert_eq!(piece.first().unwrap().0, f64::from(EXTENT + BUFFER));
        assert_eq!(piece.last().unwrap().0, f64::from(EXTENT + BUFFER));
        assert!(piece.contains(&(4000.0, 2000.0)) && piece.contains(&(4000.0, 2200.0)));
        // One wholly inside stays closed.
        let inner = [(100.0, 100.0), (200.0, 100.0), (200.0, 200.0), (100.0, 100.0)];
        assert_eq!(clipped(&inner), vec![inner.to_vec()]);
    }

    #[test]
    fn clipping_keeps_what_is_inside_the_buffer() {
        let line = [(-1000.0, 100.0), (5000.0, 100.0)];
        assert_eq!(clipped(&line), vec![vec![(-64.0, 100.0), (4160.0, 100.0)]]);
        assert!(clipped(&[(-1000.0, -1000.0), (-900.0, -900.0)]).is_empty());
    }

    /// The simplified line keeps the ends and a subsequence of the vertices, and every
    /// vertex dropped lies within the tolerance of the line through the kept ones either
    /// side of it; and it drops most vertices of a gently curving line.
    #[test]
    #[expect(clippy::cast_precision_loss, reason = "test coordinates")]
    fn simplifying_keeps_every_vertex_within_the_tolerance() {
        let mut seed = 12_345u64;
        let mut random = || {
            seed = seed.wrapping_mul(6_364_136_223_846_793_005).wrapping_add(1_442_695_040_888_963_407);
            (seed >> 11) as f64 / (1u64 << 53) as f64
        };
        for case in 0..400 {
            // Random walks: steps of 0 to 30 units, turning a little or a lot.
            let (mut p, mut heading) = ((2000.0, 2000.0), 0.0f64);
            let turn = if case % 2 == 0 { 0.3 } else { 3.0 };
            let line: Vec<Point> = (0..2 + case % 60)
                .map(|_| {
                    heading += (random() - 0.5) * turn;
                    let step = random() * 30.0;
                    p = (p.0 + step * heading.cos(), p.1 + step * heading.sin());
                    p
                })
                .collect();
            let kept = simplify(&line, 4.0);
            assert_eq!((kept.first(), kept.last()), (line.first(), line.last()));
            // Where each kept vertex is in the line, in order.
            let mut at = vec![];
            let mut from = 0;
            for k in &kept {
                let i = from + line[from..].iter().position(|p| p == k).expect("a vertex of the line, in order");
                at.push(i);
                from = i + 1;
            }
            for pair in at.windows(2) {
                let (a, b) = (line[pair[0]], line[pair[1]]);
                let (dx, dy) = (b.0 - a.0, b.1 - a.1);
                let length = dx.hypot(dy);
                for &q in &line[pair[0] + 1..pair[1]] {
                    let d = if length == 0.0 {
                        (q.0 - a.0).hypot(q.1 - a.1)
                    } else {
                        ((q.0 - a.0) * dy - (q.1 - a.1) * dx).abs() / length
                    };
                    assert!(d <= 4.0 + 1e-9, "case {case}: a vertex {d} from the line");
                }
            }
        }
        // A quarter circle of radius 2000 in 200 steps: a few vertices are enough.
        let arc: Vec<Point> = (0..=200)
            .map(|i| {
                let a = f64::from(i) / 200.0 * std::f64::consts::FRAC_PI_2;
                (2000.0 * a.cos(), 2000.0 * a.sin())
            })
            .collect();
        let kept = simplify(&arc, 4.0).len();
        assert!((3..40).contains(&kept), "{kept} of 201 vertices kept");
    }

    #[test]
    fn default_intervals_thin_out_with_the_zoom() {
        assert!(default_interval(14, false) < default_interval(10, false));
        assert_eq!((default_interval(12, false), default_interval(14, false)), (100.0, 20.0));
        assert!(default_interval(16, true) >= 1.0);
    }
}
