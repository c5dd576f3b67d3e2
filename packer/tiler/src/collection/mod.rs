//! Collections: inputs of different resolutions in one archive, each only as deep as its
//! own resolution allows (sparse depth; docs/tiling.md, "Collections").
//!
//! LOD 0 has the finest input's spacing `f` (or, where that makes fewer samples, a
//! spacing finer by less than 2x that puts a coarser input's own on a level:
//! [`aligned_grid`]); level `L` spacing `f · 2^L`. An input of spacing `s` reaches down
//! to its *depth*, the coarsest level no coarser than its own spacing (upsampled by less
//! than 2x; an input whose spacing is a level's is that level's samples): `floor(log2(s /
//! f))`, 0 at least. The coarsest inputs' depth is the *base*: from there up every level covers the whole grid, built as a
//! pyramid of 2x2 means as a single-resolution run builds it. Below the base, level `L`
//! holds only the tiles touching an input as deep as `L` (its footprint, and the tiles
//! its edges touch), each made on its own grid at `L`'s spacing:
//!
//! - where a finer level holds tiles, the 2x2 mean of them, as stored (so every level is
//!   the mean of the level below wherever that level exists, as in a single run);
//! - elsewhere the inputs of depth `L` (later wins among them), completed from the coarser
//!   inputs beneath (resampled) where they have no data, and blended into them across a
//!   band along their data's edge (`blend` samples, smoothstep), so no step shows where
//!   a survey ends.
//!
//! So tiles, bytes and work follow the data: a continent at 1 km with a valley at 2 m
//! makes the continent's levels and the valley's, not the continent at 2 m.

pub(crate) mod merge;
mod shards;
pub(crate) mod update;

pub use merge::RunInputs;
pub use shards::{PlannedCollection, collection_shard_plan};

use rayon::prelude::*;
use std::collections::{HashSet, VecDeque};
use std::path::{Path, PathBuf};

use terrastream_format::{LayerKind, LevelCover, Metadata, SourceRecord, TileKey};
use terrastream_pack::WriteSummary;
use terrastream_pack::progress::Progress;

use crate::encode::quantize_heights;
use crate::error::{Error, Result};
use crate::options::TextureInput;
use crate::plan::Plan;
use crate::pyramid::{Pixel, Spool, Window, halve_rows};
use crate::raster::{DatumName, GridSpec, Heights, InputLayout, Mosaic, MosaicKind, Pixels};
use crate::request::{Sources, TileRequest};
use crate::tile::{HeightEncoder, cut_texture, full_windows, run_pyramid, write_spool};

/// How a collection's inputs meet.
#[derive(Clone, Copy, Debug, PartialEq)]
pub enum Blend {
    /// Across this many samples of the finer input's level.
    Samples(u32),
    /// Across this many metres (output CRS units), rounded to samples of the finer level.
    Metres(f64),
}

impl Default for Blend {
    fn default() -> Self {
        Self::Samples(DEFAULT_BLEND)
    }
}

/// Samples of a finer input's level across which it blends into the coarser data beneath
/// by default: wide enough to hide metres of disagreement between surveys on gentle
/// ground (a 4 m step over 16 samples is a slope of a quarter of a sample's spacing per
/// metre), narrow enough to keep nearly all of a survey as surveyed.
pub const DEFAULT_BLEND: u32 = 16;

/// One input of a collection: its file, spacing and depth.
#[derive(Clone, Debug, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct CollectionInput {
    /// The file.
    pub path: PathBuf,
    /// Its spacing in output CRS units (the finest of its parts).
    pub spacing: f64,
    /// The finest level it reaches.
    pub depth: u8,
    /// Its footprint in LOD-0 samples: first and last column and row (inclusive).
    pub columns: (i64, i64),
    /// As `columns`.
    pub rows: (i64, i64),
}

/// One level below the base: the tiles it holds, and the rectangles of tiles made to
/// make them (each with a ring of tiles around, for the borders).
#[derive(Clone, Debug)]
pub struct SparseLevel {
    /// The level.
    pub lod: u8,
    /// Tiles held (column, row).
    pub tiles: HashSet<(u32, u32)>,
    /// Rectangles of tiles made: first and last column and row (inclusive).
    pub rects: Vec<[u32; 4]>,
    /// Rectangles holding the tiles held (as `rects`, without their rings).
    pub cover: Vec<[u32; 4]>,
}

/// The levels of a collection ([`Collection::plan`]).
#[derive(Clone, Debug)]
pub struct Collection {
    /// The inputs, in the order given, with their depths.
    pub inputs: Vec<CollectionInput>,
    /// From this level up every level covers the grid.
    pub base: u8,
    /// The levels below the base, finest first.
    pub levels: Vec<SparseLevel>,
    /// The LOD-0 grid.
    pub grid: GridSpec,
    /// Blend band, samples of each finer input's level.
    pub blend: u32,
    /// The layer it makes: elevation (with its height ranges) or imagery.
    pub kind: LayerKind,
}

/// The depth of an input of spacing `spacing` on a LOD 0 of spacing `finest`: the
/// coarsest level whose spacing is no coarser than the input's (a spacing within a
/// billionth of a level's is that level's).
#[must_use]
pub fn depth_of(spacing: f64, finest: f64) -> u8 {
    let ratio = spacing / finest;
    if !(ratio.is_finite() && ratio > 1.0) {
        return 0;
    }
    #[expect(clippy::cast_possible_truncation, clippy::cast_sign_loss, reason = "clamped to 0..=60")]
    let d = (ratio.log2() + 1e-9).floor().clamp(0.0, 60.0) as u8;
    d
}

/// Least share of a collection's samples that a LOD 0 finer than the finest input's
/// must save for [`aligned_grid`] to choose it: below it the finest input's samples
/// are kept as they lie.
const ALIGNED_GAIN: f64 = 0.9;

/// The grid a collection of inputs laid out as `layout` on `grid` (LOD 0 at the finest
/// input's spacing `f`) makes the fewest samples on, where that is another: LOD 0 at a
/// spacing `c·f` finer by less than 2x (`c` in (0.5, 1)) that puts a coarser input's own
/// spacing exactly on a level, so that input is made at its own resolution rather than
/// upsampled by up to 2x each way (up to 4x its samples), at the price of the finer
/// inputs' upsampled by `1 / c`. A 30" base under a 1" survey: LOD 0 at 30"/32, the base
/// made at its own 30" on LOD 5, where 1" put it on LOD 4 at 16" (3.5x its samples).
/// Samples are counted as each input's footprint at its level; the grid is chosen only
/// when it makes at most [`ALIGNED_GAIN`] of them. None: keep `grid`.
#[must_use]
pub fn aligned_grid(layout: &[InputLayout], grid: GridSpec) -> Option<GridSpec> {
    let finest = grid.pixel.0.min(grid.pixel.1);
    if !(finest.is_finite() && finest > 0.0) {
        return None;
    }
    #[expect(clippy::cast_precision_loss, reason = "a sample count")]
    let samples = |c: f64| -> f64 {
        (layout.iter())
            .map(|i| {
                let area = ((i.columns.1 - i.columns.0 + 1).max(0) * (i.rows.1 - i.rows.0 + 1).max(0)) as f64;
                let level = c * f64::from(1u32 << depth_of(i.spacing, c * finest).min(30));
                area / (level * level)
            })
            .sum()
    };
    let candidates = layout.iter().filter_map(|i| {
        let ratio = i.spacing / finest;
        if !(ratio.is_finite() && ratio > 2.0) {
            return None;
        }
        let c = ratio / (ratio.log2() - 1e-9).ceil().exp2();
        (c > 0.5 && c < 1.0 - 1e-9).then_some(c)
    });
    let own = samples(1.0);
    let (c, least) = candidates.map(|c| (c, samples(c))).min_by(|a, b| a.1.total_cmp(&b.1))?;
    if least > own * ALIGNED_GAIN {
        return None;
    }
    #[expect(clippy::cast_possible_truncation, clippy::cast_sign_loss, reason = "at most 2x a u32 grid's size")]
    let more = |n: u32| (f64::from(n) / c - 1e-9).ceil().min(f64::from(u32::MAX)) as u32;
    Some(GridSpec {
        origin: grid.origin,
        pixel: (grid.pixel.0 * c, grid.pixel.1 * c),
        size: (more(grid.size.0), more(grid.size.1)),
    })
}

impl Collection {
    /// The levels of `mosaic`'s inputs on `metadata`'s layer of `kind` (elevation or
    /// texture: its tile size and LOD count): None when every input reaches LOD 0 (a
    /// single-resolution run).
    #[must_use]
    pub fn plan<K: MosaicKind>(mosaic: &Mosaic<K>, metadata: &Metadata, kind: LayerKind, blend: Blend) -> Option<Self> {
        let layer = metadata.layers.iter().find(|l| l.kind == kind)?;
        let grid = mosaic.grid();
        let finest = grid.pixel.0.min(grid.pixel.1);
        let top = layer.num_lods.saturating_sub(1);
        let layout = mosaic.layout();
        let mut inputs: Vec<CollectionInput> = Vec::new();
        let mut seen: std::collections::HashMap<PathBuf, usize> = std::collections::HashMap::new();
        for InputLayout { path, spacing, columns, rows } in layout {
            // A file read as several parts (a VRT's sources) keeps its finest part's depth.
            if let Some(known) = seen.get(&path).map(|&i| &mut inputs[i]) {
                known.spacing = known.spacing.min(spacing);
                known.columns = (known.columns.0.min(columns.0), known.columns.1.max(columns.1));
                known.rows = (known.rows.0.min(rows.0), known.rows.1.max(rows.1));
                continue;
            }
            seen.insert(path.clone(), inputs.len());
            inputs.push(CollectionInput { path, spacing, depth: 0, columns, rows });
        }
        for i in &mut inputs {
            i.depth = depth_of(i.spacing, finest);
        }
        let least = inputs.iter().map(|i| i.depth).min()?;
        for i in &mut inputs {
            i.depth = (i.depth - least).min(top);
        }
        let base = inputs.iter().map(|i| i.depth).max()?;
        if base == 0 {
            return None;
        }
        let levels = sparse_levels(&inputs, layer, base);
        let blend = blend_samples(blend, finest);
        Some(Self { inputs, base, levels, grid, blend, kind })
    }

    /// Whether `mosaic`'s inputs reach different levels (some more than 2x coarser than
    /// the finest): known from their headers.
    #[must_use]
    pub fn spans_resolutions<K: MosaicKind>(mosaic: &Mosaic<K>) -> bool {
        let grid = mosaic.grid();
        let finest = grid.pixel.0.min(grid.pixel.1);
        let depths: HashSet<u8> = mosaic.layout().iter().map(|i| depth_of(i.spacing, finest)).collect();
        depths.len() > 1
    }

    /// Makes `plan`'s counts those of the collection: its layer's tiles (and the height
    /// ranges' with the elevation's), the estimated bytes scaled alike.
    pub fn apply_to(&self, plan: &mut Plan) {
        let tiles = self.tiles(&plan.metadata);
        for (layer, p) in plan.metadata.layers.iter().zip(&mut plan.layers) {
            if self.makes(layer.kind) && p.tiles > 0 {
                #[expect(
                    clippy::cast_precision_loss,
                    clippy::cast_possible_truncation,
                    clippy::cast_sign_loss,
                    reason = "an estimate"
                )]
                let bytes = (p.estimated_bytes as f64 * tiles as f64 / p.tiles as f64) as u64;
                p.estimated_bytes = bytes;
                p.tiles = tiles;
            }
        }
    }

    /// The samples made from the inputs over LOD-0 rows `rows`: each input's area there
    /// at the level it reaches (the work a shard of those rows split at LOD `split` does:
    /// the inputs deeper than it are the merge's).
    #[must_use]
    pub fn work(&self, rows: std::ops::Range<u32>, split: u8) -> f64 {
        let (start, end) = (i64::from(rows.start), i64::from(rows.end));
        (self.inputs.iter())
            .filter(|i| i.depth <= split)
            .map(|i| {
                let down = (i.rows.1 + 1).min(end) - i.rows.0.max(start);
                let across = i.columns.1 - i.columns.0 + 1;
                #[expect(clippy::cast_precision_loss, reason = "a weight")]
                let area = (down.max(0) * across.max(0)) as f64;
                area / 4f64.powi(i32::from(i.depth))
            })
            .sum()
    }

    /// Whether a layer of `kind` is this collection's (the height ranges go with the
    /// elevation).
    #[must_use]
    pub fn makes(&self, kind: LayerKind) -> bool {
        kind == self.kind || (self.kind == LayerKind::Elevation && kind == LayerKind::HeightRange)
    }

    /// Tiles of the collection's layer, every level: those below the base, and the base's
    /// whole pyramid.
    #[must_use]
    pub fn tiles(&self, metadata: &Metadata) -> u64 {
        let Some(layer) = metadata.layers.iter().find(|l| l.kind == self.kind) else { return 0 };
        let sparse: u64 = self.levels.iter().map(|l| l.tiles.len() as u64).sum();
        sparse + self.full_tiles(layer)
    }

    /// The inputs (by `depth`) whose footprints reach level `lod`'s `grid` (corner sample
    /// `corner`), with a sample of the level around for the bilinear samples at its edge.
    pub(crate) fn reaching(
        &self,
        lod: u8,
        corner: (u32, u32),
        grid: &GridSpec,
        depth: &dyn Fn(u8) -> bool,
    ) -> Vec<PathBuf> {
        self.reaching_inputs(lod, corner, grid, depth).into_iter().map(|i| i.path.clone()).collect()
    }

    /// [`Self::reaching`]'s inputs.
    fn reaching_inputs(
        &self,
        lod: u8,
        corner: (u32, u32),
        grid: &GridSpec,
        depth: &dyn Fn(u8) -> bool,
    ) -> Vec<&CollectionInput> {
        let scale = 1i64 << lod;
        let (c0, r0) = (i64::from(corner.0) * scale, i64::from(corner.1) * scale);
        let (c1, r1) = (c0 + i64::from(grid.size.0) * scale, r0 + i64::from(grid.size.1) * scale);
        let (c0, r0, c1, r1) = (c0 - scale, r0 - scale, c1 + scale, r1 + scale);
        (self.inputs.iter())
            .filter(|i| depth(i.depth) && i.columns.0 <= c1 && i.columns.1 >= c0 && i.rows.0 <= r1 && i.rows.1 >= r0)
            .collect()
    }

    /// The inputs level `lod`'s rectangle (corner sample `corner`, `grid`) is made from:
    /// those as deep as the level, the coarser ones beneath, and how many levels coarser
    /// the finest of those reaches (0: none).
    pub(crate) fn level_inputs(
        &self,
        lod: u8,
        corner: (u32, u32),
        grid: &GridSpec,
    ) -> (Vec<PathBuf>, Vec<PathBuf>, u32) {
        let fine = self.reaching(lod, corner, grid, &|d| d == lod);
        let beneath = self.reaching_inputs(lod, corner, grid, &|d| d > lod);
        let shift = beneath.iter().map(|i| u32::from(i.depth - lod)).min().unwrap_or(0);
        let below = beneath.into_iter().map(|i| i.path.clone()).collect();
        (fine, below, shift)
    }

    /// The base level's window: its whole grid, or a shard's band of it (`part`), from
    /// the base up to the last level (a layer of `num_lods`) or the shard's split LOD.
    pub(crate) fn base_window(&self, part: Option<&ShardPart>, num_lods: u8) -> Window {
        let (base, size) = (self.base, self.level_grid(self.base).size);
        match part {
            Some(p) => {
                let down = |n: usize| n >> base;
                let up = |n: usize, end: usize| if n >= end { size.1 as usize } else { n >> base };
                let height = self.grid.size.1 as usize;
                Window {
                    input_lod: base,
                    last_lod: p.split,
                    encode_from: base,
                    rows: down(p.window.rows.start)..up(p.window.rows.end, height),
                    band: down(p.window.band.start)..up(p.window.band.end, height),
                    first_column: 0,
                }
            }
            None => Window {
                input_lod: base,
                last_lod: num_lods - 1,
                encode_from: base,
                rows: 0..size.1 as usize,
                band: 0..size.1 as usize,
                first_column: 0,
            },
        }
    }

    /// The inputs the base level's rows in `window` are made from.
    pub(crate) fn base_inputs(&self, window: &Window) -> Vec<PathBuf> {
        let grid = self.level_grid(self.base);
        let rows =
            u32::try_from(window.rows.start).unwrap_or(u32::MAX)..u32::try_from(window.rows.end).unwrap_or(u32::MAX);
        let band = GridSpec { size: (grid.size.0, rows.end.saturating_sub(rows.start)), ..grid };
        self.reaching(self.base, (0, rows.start), &band, &|d| d >= self.base)
    }

    /// Level `lod`'s whole grid.
    pub(crate) fn level_grid(&self, lod: u8) -> GridSpec {
        let g = self.grid;
        let size = (g.size.0.div_ceil(1 << lod).max(1), g.size.1.div_ceil(1 << lod).max(1));
        let scale = f64::from(1u32 << lod);
        GridSpec { origin: g.origin, pixel: (g.pixel.0 * scale, g.pixel.1 * scale), size }
    }

    /// Tiles of the levels from the base up, over the whole grid.
    fn full_tiles(&self, layer: &terrastream_format::Layer) -> u64 {
        (self.base..layer.num_lods)
            .map(|lod| {
                let (nx, ny) = layer.grid_at(lod);
                u64::from(nx) * u64::from(ny)
            })
            .sum()
    }

    /// Tiles cut, every level: the rectangles' (rings included) and the base's pyramid.
    fn cut_tiles(&self, metadata: &Metadata) -> u64 {
        let Some(layer) = metadata.layers.iter().find(|l| l.kind == self.kind) else { return 0 };
        let rects: u64 = (self.levels.iter().flat_map(|l| &l.rects))
            .map(|r| u64::from(r[2] - r[0] + 1) * u64::from(r[3] - r[1] + 1))
            .sum();
        rects + self.full_tiles(layer)
    }

    /// The level-`lod` grid over tile rectangle `rect` (with `res`-sample tiles), clipped
    /// to the level's samples: its corner sample, and the grid.
    fn rect_grid(&self, lod: u8, rect: [u32; 4], res: u32) -> ((u32, u32), GridSpec) {
        let (w, h) = (self.grid.size.0.div_ceil(1 << lod).max(1), self.grid.size.1.div_ceil(1 << lod).max(1));
        let (c0, r0) = (rect[0] * res, rect[1] * res);
        let (c1, r1) = (((rect[2] + 1) * res).min(w), ((rect[3] + 1) * res).min(h));
        ((c0, r0), self.sample_grid(lod, (c0, r0), (c1 - c0, r1 - r0)))
    }

    /// The part of `level`'s rectangle `rect` that is made (see [`live_part`]): its corner
    /// sample on the level, and its grid; None when the rectangle holds no tile.
    pub(crate) fn live_grid(&self, level: &SparseLevel, rect: [u32; 4], res: u32) -> Option<((u32, u32), GridSpec)> {
        let (corner, grid) = self.rect_grid(level.lod, rect, res);
        let live = live_part(level, rect, res, corner, &grid)?;
        let at = (corner.0 + live[0], corner.1 + live[1]);
        Some((at, self.sample_grid(level.lod, at, (live[2] - live[0], live[3] - live[1]))))
    }

    /// The level-`lod` grid of `size` samples from its sample `corner` (its corner placed
    /// from the whole grid's, as every part of the level is: the same samples).
    fn sample_grid(&self, lod: u8, corner: (u32, u32), size: (u32, u32)) -> GridSpec {
        let g = self.grid;
        let scale = f64::from(1u32 << lod);
        let pixel = (g.pixel.0 * scale, g.pixel.1 * scale);
        let origin = [g.origin[0] + f64::from(corner.0) * pixel.0, g.origin[1] - f64::from(corner.1) * pixel.1];
        GridSpec { origin, pixel, size }
    }
}

/// The levels below `base` of `inputs` on `layer`'s grid: the tiles each holds (those its
/// inputs as deep touch), and the rectangles made to make them.
pub(crate) fn sparse_levels(
    inputs: &[CollectionInput],
    layer: &terrastream_format::Layer,
    base: u8,
) -> Vec<SparseLevel> {
    let res = u64::from(layer.tile_resolution);
    (0..base)
        .map(|lod| {
            let (nx, ny) = layer.grid_at(lod);
            let span = res << lod;
            let cell = |v: i64, n: u32| u32::try_from(v.max(0).unsigned_abs() / span).unwrap_or(u32::MAX).min(n - 1);
            let mut tiles = HashSet::new();
            let mut rects: Vec<[u32; 4]> = Vec::new();
            let mut cover: Vec<[u32; 4]> = Vec::new();
            for i in inputs.iter().filter(|i| i.depth <= lod) {
                let (x0, x1) = (cell(i.columns.0, nx), cell(i.columns.1, nx));
                let (y0, y1) = (cell(i.rows.0, ny), cell(i.rows.1, ny));
                tiles.extend((y0..=y1).flat_map(|y| (x0..=x1).map(move |x| (x, y))));
                cover.push([x0, y0, x1, y1]);
                rects.push([x0.saturating_sub(1), y0.saturating_sub(1), (x1 + 1).min(nx - 1), (y1 + 1).min(ny - 1)]);
            }
            SparseLevel { lod, tiles, rects: merged(rects, false), cover: merged(cover, true) }
        })
        .collect()
}

/// A blend band in samples of a LOD 0 of spacing `finest`.
pub(crate) fn blend_samples(blend: Blend, finest: f64) -> u32 {
    match blend {
        Blend::Samples(n) => n,
        #[expect(clippy::cast_possible_truncation, clippy::cast_sign_loss, reason = "clamped")]
        Blend::Metres(m) => {
            // Of the finest level's samples (each finer input's own level's are coarser; a
            // band in metres would be narrower there, so the finest's).
            (m / finest).round().clamp(0.0, 4096.0) as u32
        }
    }
}

/// What the archive records of `c` (on `metadata`'s grid and georeference): its inputs
/// and the rectangles of its partial levels.
pub(crate) fn records(c: &Collection, metadata: &Metadata) -> (Vec<SourceRecord>, Vec<LevelCover>) {
    let georeference = metadata.georeference.clone();
    // Output CRS units per world metre (the spacings are CRS units).
    let per_metre = georeference.as_ref().and_then(|g| g.scale).map_or(1.0, |s| s[0]);
    let Some(layer) = metadata.layers.iter().find(|l| l.kind == c.kind) else {
        return (vec![], vec![]);
    };
    let sample = layer.sample_spacing(0);
    let sources = (c.inputs.iter())
        .map(|i| SourceRecord {
            // Its samples, less the margin the layout counts each side.
            #[expect(clippy::cast_precision_loss, reason = "sample indices")]
            world: Some([
                (i.columns.0 + 1).max(0) as f64 * sample,
                (i.rows.0 + 1).max(0) as f64 * sample,
                i.columns.1 as f64 * sample,
                i.rows.1 as f64 * sample,
            ]),
            name: i.path.file_name().map_or_else(|| i.path.display().to_string(), |n| n.to_string_lossy().into_owned()),
            spacing: i.spacing / per_metre,
            lod: i.depth,
            blend: Some(c.blend),
            layer: (c.kind == LayerKind::Texture).then(|| "texture".to_owned()),
        })
        .collect();
    let covers = (c.levels.iter())
        .filter(|l| !l.cover.is_empty())
        .map(|l| {
            let s = layer.world_size_at(l.lod);
            let boxes = (l.cover.iter()).map(|r| {
                let world =
                    [f64::from(r[0]) * s, f64::from(r[1]) * s, f64::from(r[2] + 1) * s, f64::from(r[3] + 1) * s];
                georeference.as_ref().and_then(|g| crate::plan::lon_lat_box(g, world))
            });
            let lon_lat: Option<Vec<[f64; 4]>> = boxes.collect();
            LevelCover { lod: l.lod, tiles: l.cover.clone(), lon_lat: lon_lat.unwrap_or_default() }
        })
        .collect();
    (sources, covers)
}

/// Rectangles (inclusive) merged until none overlaps (or, with `touching`, touches)
/// another, in the order of each group's first rectangle. The rectangles a level is made
/// over merge only where they overlap: apart, each is made as a later update would make it
/// alone.
///
/// A sweep across the columns (each rectangle met only by those still open at its first
/// column), the overlapping ones joined, then their bounding boxes swept again until none
/// joins: a survey of many thousand scattered tiles costs about n log n, not n squared.
fn merged(rects: Vec<[u32; 4]>, touching: bool) -> Vec<[u32; 4]> {
    fn root(parent: &mut [usize], mut i: usize) -> usize {
        while parent[i] != i {
            parent[i] = parent[parent[i]];
            i = parent[i];
        }
        i
    }
    let gap = u32::from(touching);
    // Each box with the index of the first rectangle in it.
    let mut boxes: Vec<([u32; 4], usize)> = rects.into_iter().enumerate().map(|(i, r)| (r, i)).collect();
    loop {
        let n = boxes.len();
        let mut parent: Vec<usize> = (0..n).collect();
        let mut order: Vec<usize> = (0..n).collect();
        order.sort_by_key(|&i| boxes[i].0[0]);
        // Boxes whose columns reach the sweep's (with the gap): every one that can meet the
        // next, which starts at or after theirs.
        let mut open: Vec<usize> = Vec::new();
        for &i in &order {
            let r = boxes[i].0;
            open.retain(|&a| boxes[a].0[2].saturating_add(gap) >= r[0]);
            for &a in &open {
                let o = boxes[a].0;
                if o[1] <= r[3].saturating_add(gap) && r[1] <= o[3].saturating_add(gap) {
                    let (x, y) = (root(&mut parent, a), root(&mut parent, i));
                    parent[x.max(y)] = x.min(y);
                }
            }
            open.push(i);
        }
        let mut joined: Vec<Option<([u32; 4], usize)>> = vec![None; n];
        for i in 0..n {
            let (r, first) = boxes[i];
            let slot = &mut joined[root(&mut parent, i)];
            *slot = Some(match *slot {
                Some((o, f)) => ([o[0].min(r[0]), o[1].min(r[1]), o[2].max(r[2]), o[3].max(r[3])], f.min(first)),
                None => (r, first),
            });
        }
        let mut next: Vec<([u32; 4], usize)> = joined.into_iter().flatten().collect();
        next.sort_by_key(|&(_, first)| first);
        if next.len() == n {
            return next.into_iter().map(|(r, _)| r).collect();
        }
        boxes = next;
    }
}

/// A level's rows over a rectangle, halved: what the next coarser level takes where it
/// lies (the 2x2 mean of the finer level as stored).
pub(crate) struct Override<S = f32> {
    /// First column and row at the coarser level.
    x0: usize,
    y0: usize,
    rows: Vec<Vec<S>>,
}

impl<S: Pixel> Override<S> {
    /// Keeps only the means whose first sample lies in a tile `level` holds (the rest: no
    /// data), so that what the coarser level takes is what the archive stores: a merge of
    /// shards or an update can take it from the stored tiles alone.
    fn keep_held(&mut self, level: &SparseLevel, res: u32) {
        let res = res.max(1) as usize;
        for (j, row) in self.rows.iter_mut().enumerate() {
            let ty = u32::try_from(2 * (self.y0 + j) / res).unwrap_or(u32::MAX);
            let mut at = 0;
            while at < row.len() {
                // The run of means whose first samples lie in one tile.
                let tx = 2 * (self.x0 + at) / res;
                let end = ((tx + 1) * res).div_ceil(2) - self.x0;
                let run = at..end.min(row.len());
                if !level.tiles.contains(&(u32::try_from(tx).unwrap_or(u32::MAX), ty)) {
                    row[run.clone()].fill(S::NONE);
                }
                at = run.end;
            }
        }
    }
}

/// The collections of one run: of the heights, of the imagery, or both.
#[derive(Clone, Copy, Debug, Default)]
pub struct Collections<'c> {
    /// The heights' (None: tiled as one resolution).
    pub heights: Option<&'c Collection>,
    /// The imagery's (None: tiled as one resolution).
    pub imagery: Option<&'c Collection>,
}

/// Tiles `request`'s inputs (opened as `sources`; `elevation` and `texture` as
/// [`crate::Inputs`] gives them), each layer of `collections` as a collection and the others
/// as a single run tiles them, into the archive at `out`, on `plan` (made from the whole
/// mosaics: their grids, LOD counts and height encoding).
///
/// # Errors
/// As [`crate::tile_terrain`]; inputs that cannot be opened again on a level's grid.
#[expect(clippy::too_many_arguments, reason = "the request, its sources, its plan, and where to write")]
pub fn tile_collection(
    collections: Collections<'_>,
    request: &TileRequest,
    sources: &Sources,
    elevation: Option<&dyn crate::raster::ElevationSource>,
    texture: Option<TextureInput<'_>>,
    plan: &Plan,
    out: &Path,
    shard: Option<crate::options::ShardSpec>,
    progress: &dyn Progress,
) -> Result<WriteSummary> {
    let phases = crate::phases::Phases::start();
    let mut recorded = plan.metadata.clone();
    for c in [collections.heights, collections.imagery].into_iter().flatten() {
        let (inputs, covers) = records(c, &recorded);
        recorded.sources.extend(inputs);
        for layer in &mut recorded.layers {
            if let (Some(extent), true) = (&mut layer.extent, c.makes(layer.kind)) {
                extent.partial.clone_from(&covers);
            }
        }
    }
    let mut planned = Plan { metadata: recorded, layers: plan.layers.clone() };
    // A shard: every layer's band up to a split LOD no finer than the collections' bases
    // (above them the merge makes the levels from the shards' tiles, as for any run).
    let windows = match shard {
        Some(spec) => {
            if let Some(t) = texture.as_ref().filter(|t| !t.format.lossless()) {
                return Err(Error::option("--texture-format", t.format.name(), "png or webp with --shard"));
            }
            let (info, windows, _) = shards::windows(collections, &planned, spec, elevation, texture.as_ref())?;
            planned.metadata.shard = Some(info);
            windows
        }
        None => full_windows(&planned),
    };
    let part_of = |c: &Collection| shards::part(c, &planned.metadata, &windows);
    let metadata = &planned.metadata;
    let folder = terrastream_pack::output_folder(out);
    let mut spool = match (collections.heights, elevation) {
        (Some(c), _) => {
            let mut spool = Spool::new(&folder)?;
            let part = part_of(c);
            cut_heights(c, request, sources, metadata, &mut spool, progress, part.as_ref())?;
            spool
        }
        (None, Some(e)) => crate::tile::cut_planned(&folder, Some(e), None, &planned, &windows, progress)?,
        (None, None) => Spool::new(&folder)?,
    };
    phases.mark(&format!("{} tiles of heights cut", spool.tiles()));
    match (collections.imagery, texture) {
        (Some(c), Some(t)) => {
            let part = part_of(c);
            cut_imagery(c, request, sources, t.format, metadata, &mut spool, progress, part.as_ref())?;
        }
        (None, Some(t)) => cut_texture(t, &planned, &windows, &mut spool, progress)?,
        _ => {}
    }
    crate::plan::settle_details(&mut planned.metadata, spool.keys());
    let written = write_spool(spool, &planned.metadata, out, true, progress, &phases)?;
    phases.finish();
    Ok(written)
}

/// The request that opens a collection's height inputs `paths` onto `grid` in `crs`: in
/// the heights' `datum` (the one `named` by the person, else the whole mosaic's; named
/// for each level, so that the warning about an unknown one is not repeated).
pub(crate) fn heights_on(
    paths: Vec<PathBuf>,
    grid: GridSpec,
    crs: &str,
    datum: Option<&DatumName>,
    named: Option<&DatumName>,
) -> TileRequest {
    TileRequest {
        elevation: paths,
        crs: Some(crs.to_owned()),
        elevation_grid: Some(grid),
        vertical_datum: named.cloned().or_else(|| Some(datum.cloned().unwrap_or(DatumName::Unknown))),
        target_datum: datum.cloned(),
        ..TileRequest::default()
    }
}

/// The mosaic of a [`heights_on`] request (None without inputs).
pub(crate) fn open_heights(request: &TileRequest) -> Result<Option<Mosaic<Heights>>> {
    if request.elevation.is_empty() {
        return Ok(None);
    }
    Ok(Sources::open(request)?.into_mosaics().0)
}

/// A collection's images `paths` opened onto `grid` in `crs` (None without inputs),
/// leaving out the ones that cannot be read where `skip_bad_inputs` says so.
pub(crate) fn open_images(
    paths: Vec<PathBuf>,
    grid: GridSpec,
    crs: &str,
    skip_bad_inputs: bool,
) -> Result<Option<Mosaic<Pixels>>> {
    if paths.is_empty() {
        return Ok(None);
    }
    let request = TileRequest {
        texture: paths,
        crs: Some(crs.to_owned()),
        texture_grid: Some(grid),
        skip_bad_inputs,
        ..TileRequest::default()
    };
    Ok(Sources::open(&request)?.into_mosaics().1)
}

/// Cuts the heights' collection `c` (and its height ranges) into `spool`.
fn cut_heights(
    c: &Collection,
    request: &TileRequest,
    sources: &Sources,
    metadata: &Metadata,
    spool: &mut Spool,
    progress: &dyn Progress,
    part: Option<&ShardPart>,
) -> Result<()> {
    let find = |kind: LayerKind| metadata.layers.iter().position(|l| l.kind == kind).and_then(|i| u8::try_from(i).ok());
    let index = find(LayerKind::Elevation).ok_or(Error::NothingToTile)?;
    let heights = HeightEncoder::new(metadata, index, find(LayerKind::HeightRange))?;
    let encoding = heights.encoding;
    let quantize = move |row: &mut [f32]| quantize_heights(row, &encoding);
    let main = sources.height_mosaic().ok_or(Error::NothingToTile)?;
    let datum = main.datum().cloned();
    let crs = main.crs().definition().to_owned();
    let range = (metadata.terrain.min_elevation, metadata.terrain.max_elevation);
    #[expect(clippy::cast_possible_truncation, reason = "heights are f32")]
    let range = ((range.0 as f32).next_down(), (range.1 as f32).next_up());
    // Inputs of the collection on a grid.
    let open = |paths: Vec<PathBuf>, grid: GridSpec| -> Result<Option<Mosaic<Heights>>> {
        let sub = TileRequest {
            encoding: request.encoding,
            height_range: Some(range),
            skip_bad_inputs: request.skip_bad_inputs,
            ..heights_on(paths, grid, &crs, datum.as_ref(), request.vertical_datum.as_ref())
        };
        open_heights(&sub)
    };
    let encode_tile = |key: TileKey, samples: &[f32], _edge: usize| heights.encode(key, samples);
    let cut = part.map_or(Cut::Whole, Cut::Shard);
    cut_levels(c, metadata, index, &open, &encode_tile, Some(&quantize), spool, progress, cut)?;
    heights.finish(metadata, Vec::new(), spool)
}

/// Cuts the imagery's collection `c` into `spool`, its tiles stored as `format`.
#[expect(clippy::too_many_arguments, reason = "the collection, its sources, and where tiles go")]
fn cut_imagery(
    c: &Collection,
    request: &TileRequest,
    sources: &Sources,
    format: crate::options::TextureFormat,
    metadata: &Metadata,
    spool: &mut Spool,
    progress: &dyn Progress,
    part: Option<&ShardPart>,
) -> Result<()> {
    let index = (metadata.layers.iter().position(|l| l.kind == LayerKind::Texture))
        .and_then(|i| u8::try_from(i).ok())
        .ok_or(Error::NothingToTile)?;
    let main = sources.image_mosaic().ok_or(Error::NothingToTile)?;
    let crs = main.crs().definition().to_owned();
    let open = |paths: Vec<PathBuf>, grid: GridSpec| open_images(paths, grid, &crs, request.skip_bad_inputs);
    let encode_tile = |key: TileKey, pixels: &[[u8; 4]], edge: usize| -> Result<Vec<(TileKey, Vec<u8>)>> {
        Ok(vec![(key, crate::encode::encode_texture(key, pixels, edge, format, crate::tile::ZSTD_LEVEL)?)])
    };
    cut_levels(c, metadata, index, &open, &encode_tile, None, spool, progress, part.map_or(Cut::Whole, Cut::Shard))
}

/// Which of a collection's levels a cut makes.
pub(crate) enum Cut<'p, S> {
    /// Every level (a whole run).
    Whole,
    /// A shard's band up to its split LOD.
    Shard(&'p ShardPart),
    /// The levels above `lod` (a merge of shards split there), from that level's means
    /// as its tiles store them (see [`merge`]).
    Above(u8, Vec<Override<S>>),
}

/// Cuts collection `c`'s levels of layer `index` (those `cut` says): those below its base
/// from the inputs `open` opens on each rectangle's grid, and the base's pyramid over the
/// whole grid.
#[expect(clippy::too_many_arguments, reason = "the collection, how to read and encode, and where tiles go")]
pub(crate) fn cut_levels<K: MosaicKind>(
    c: &Collection,
    metadata: &Metadata,
    index: u8,
    open: &(dyn Fn(Vec<PathBuf>, GridSpec) -> Result<Option<Mosaic<K>>> + Sync),
    encode_tile: &EncodeTile<'_, K::Value>,
    quantize: Option<&QuantizeRow<'_, K::Value>>,
    spool: &mut Spool,
    progress: &dyn Progress,
    cut: Cut<'_, K::Value>,
) -> Result<()>
where
    K::Value: Pixel,
{
    let (part, from) = match cut {
        Cut::Whole => (None, None),
        Cut::Shard(p) => (Some(p), None),
        Cut::Above(lod, means) => (None, Some((lod, means))),
    };
    let phases = crate::phases::Phases::start();
    let layer = &metadata.layers[usize::from(index)];
    progress.start("tile", c.cut_tiles(metadata));
    let sources_of = |lod: u8, corner: (u32, u32), grid: &GridSpec| -> Result<LevelSources<'static, K>> {
        let (fine, below, shift) = c.level_inputs(lod, corner, grid);
        let fine = open(fine, *grid)?;
        // The coarser inputs, on the grid of the level they reach (as it stores them).
        let scale = f64::from(1u32 << lod);
        let (first, part) =
            coarse_grid(c.grid.origin, (c.grid.pixel.0 * scale, c.grid.pixel.1 * scale), corner, grid.size, shift);
        let coarse_lod = lod + u8::try_from(shift).unwrap_or(0);
        let coarse = open(below, c.level_grid(coarse_lod))?.map(|mut mosaic| {
            // Only the part's columns are made (and their chunks decoded), each sample
            // the one the whole grid's row holds: a survey's levels over a continent's
            // base read the base under the survey, not across the continent.
            let columns = |n: i64| u32::try_from(n.max(0)).unwrap_or(u32::MAX);
            mosaic.only_columns(columns(first.0)..columns(first.0 + i64::from(part.size.0)));
            let part: Box<dyn CoarseRows<K::Value>> = Box::new(MosaicPart { mosaic, first, size: part.size });
            (part, shift, first)
        });
        Ok(LevelSources { fine, coarse })
    };
    let overrides = make_levels(c, metadata, index, encode_tile, quantize, spool, progress, &sources_of, part, from)?;
    phases.mark(&format!("layer {index}: the levels below the base made"));
    if part.is_some_and(|p| p.split < c.base) {
        // A shard split below the base: the base is the merge's.
        return Ok(());
    }

    // The base: every level from here up over the whole grid, a pyramid as a single run's
    // (a shard's band of it: made from the inputs its rows read).
    let base = c.base;
    let grid = c.level_grid(base);
    let window = c.base_window(part, layer.num_lods);
    let mosaic = open(c.base_inputs(&window), grid)?;
    let encode = |key: TileKey, samples: &[K::Value], edge: usize| encode_tile(key, samples, edge);
    let rows = u32::try_from(window.rows.start).unwrap_or(0)..u32::try_from(window.rows.end).unwrap_or(0);
    let finer: Vec<&Override<K::Value>> = overrides.iter().collect();
    run_pyramid(metadata, index, c.grid.size, &window, &encode, quantize, spool, progress, |push| {
        level_rows(mosaic.as_ref(), None, &grid, (0, rows.start), rows.clone(), &finer, 0, push)
    })?;
    phases.mark(&format!("layer {index}: the collection cut, {} tiles in all", spool.tiles()));
    Ok(())
}

/// One shard's part of a collection's layer: the band of tile rows it holds at every level
/// up to its split LOD, and the base's window (LOD-0 rows, as [`crate::shard`] cuts it).
#[derive(Clone, Debug)]
pub(crate) struct ShardPart {
    /// The split LOD (below the collection's base: the levels above are the merge's).
    pub(crate) split: u8,
    /// LOD-0 tile rows held: `[start, end)`.
    pub(crate) tile_rows: [u32; 2],
    /// The layer's window over LOD-0 rows.
    pub(crate) window: Window,
}

impl ShardPart {
    /// Tile rows of level `lod` this shard holds.
    fn rows_at(&self, lod: u8) -> std::ops::Range<u32> {
        // The last band ends at the grid's last row, which a coarser level's last row
        // covers in part.
        (self.tile_rows[0] >> lod)..self.tile_rows[1].div_ceil(1 << lod)
    }

    /// Whether tile row `y` of level `lod` is this shard's.
    fn holds(&self, lod: u8, y: u32) -> bool {
        let (y0, y1) = (self.tile_rows[0], self.tile_rows[1]);
        // Level `lod`'s tile `y` covers LOD-0 tile rows y << lod ..: whole bands at the split.
        let first = y << lod;
        first >= y0 && first < y1.max(y0 + 1) && y0 < y1
    }
}

/// Per level below `c`'s base (finest first), the rectangles `part` needs made: those
/// whose rows its tiles lie in, and those whose means the rectangles above it take.
fn needed_rects(c: &Collection, res: u32, part: &ShardPart) -> Vec<Vec<[u32; 4]>> {
    let border = 1u64;
    let mut out: Vec<Vec<[u32; 4]>> = vec![Vec::new(); c.levels.len()];
    // Sample rows (of the level above) whose values the level above needs: the base's
    // window, then each chosen rectangle's rows.
    let base_rows = part.window.rows.start as u64 >> c.base..(part.window.rows.end as u64).div_ceil(1 << c.base);
    // Split below the base: the levels above the split are the merge's.
    let mut wanted: Vec<std::ops::Range<u64>> = if part.split >= c.base { vec![base_rows] } else { vec![] };
    for (i, level) in c.levels.iter().enumerate().rev() {
        if level.lod > part.split {
            continue;
        }
        let res64 = u64::from(res);
        let band = part.rows_at(level.lod);
        let mut rows: Vec<std::ops::Range<u64>> =
            wanted.iter().map(|r| (r.start * 2).saturating_sub(2)..r.end * 2 + 2).collect();
        rows.push((u64::from(band.start) * res64).saturating_sub(border)..u64::from(band.end) * res64 + border);
        let chosen: Vec<[u32; 4]> = (level.rects.iter())
            .filter(|r| {
                let (a, b) = (u64::from(r[1]) * res64, (u64::from(r[3]) + 1) * res64);
                rows.iter().any(|w| w.start < b && a < w.end)
            })
            .copied()
            .collect();
        wanted = chosen.iter().map(|r| u64::from(r[1]) * res64..(u64::from(r[3]) + 1) * res64).collect();
        out[i] = chosen;
    }
    out
}

/// Opens what level `lod`'s rectangle (corner sample, grid) is made from.
pub(crate) type OpenLevel<'f, 's, K> = dyn Fn(u8, (u32, u32), &GridSpec) -> Result<LevelSources<'s, K>> + 'f;

/// What a level's rectangle is made from: the inputs as deep as the level, and the
/// coarser data beneath (with its grid's shift and first sample).
pub(crate) struct LevelSources<'a, K: MosaicKind = Heights> {
    pub(crate) fine: Option<Mosaic<K>>,
    pub(crate) coarse: Option<CoarseSource<'a, K::Value>>,
}

/// Coarser data beneath a level's rectangle: its rows, its grid's shift (levels coarser)
/// and its first sample (on the level's grid, divided by 2^shift).
pub(crate) type CoarseSource<'a, S> = (Box<dyn CoarseRows<S> + 'a>, u32, (i64, i64));

/// Encodes a tile of a level (its global key) into the archive entries it makes.
pub(crate) type EncodeTile<'a, S> = dyn Fn(TileKey, &[S], usize) -> Result<Vec<(TileKey, Vec<u8>)>> + Sync + 'a;

/// Rounds a row to the precision its tiles store (heights; imagery as it is).
pub(crate) type QuantizeRow<'a, S> = dyn Fn(&mut [S]) + Sync + 'a;

/// Makes `c`'s levels below its base, finest first, into `spool` (tiles `c` holds, with
/// the height ranges gathered by `heights`): each rectangle from what `sources` opens for
/// it, and the finer level's means. With `from` (a level and its means), only the levels
/// above it, from those means. Returns the last level's rectangles halved: what the base
/// takes where they lie.
#[expect(clippy::too_many_arguments, reason = "the collection, its encoding and where tiles go")]
pub(crate) fn make_levels<'s, K: MosaicKind>(
    c: &Collection,
    metadata: &Metadata,
    index: u8,
    encode_tile: &EncodeTile<'_, K::Value>,
    quantize: Option<&QuantizeRow<'_, K::Value>>,
    spool: &mut Spool,
    progress: &dyn Progress,
    sources: &OpenLevel<'_, 's, K>,
    part: Option<&ShardPart>,
    from: Option<(u8, Vec<Override<K::Value>>)>,
) -> Result<Vec<Override<K::Value>>>
where
    K::Value: Pixel,
{
    let res = metadata.layers[usize::from(index)].tile_resolution;
    let needed = part.map(|p| needed_rects(c, res, p));
    // As many as the pool's (`RAYON_NUM_THREADS`, else the cores).
    let threads = rayon::current_num_threads().min(8);
    let (after, mut overrides) = match from {
        Some((lod, means)) => (Some(lod), means),
        None => (None, Vec::new()),
    };
    for (l, level) in c.levels.iter().enumerate() {
        let lod = level.lod;
        if after.is_some_and(|a| lod <= a) {
            continue;
        }
        let mut next: Vec<Override<K::Value>> = Vec::new();
        let rects = needed.as_ref().map_or(&level.rects, |n| &n[l]);
        for &rect in rects {
            progress.check()?;
            let (corner, grid) = c.rect_grid(lod, rect, res);
            // Only the part of the rectangle its tiles (and their borders) need is made:
            // the rest of its ring of tiles, which no tile holds, stays empty.
            let Some((live_corner, live_grid)) = c.live_grid(level, rect, res) else { continue };
            let live = [live_corner.0 - corner.0, live_corner.1 - corner.1];
            let LevelSources { fine, coarse } = sources(lod, live_corner, &live_grid)?;
            let coarse = coarse.map(|(source, shift, first)| Coarse { source, shift, first, quantize });
            // The finer level's means that reach this part (of every survey's).
            let near = |o: &&Override<K::Value>| {
                let (w, h) = (o.rows.first().map_or(0, Vec::len), o.rows.len());
                let (x0, y0) = (live_corner.0 as usize, live_corner.1 as usize);
                let (x1, y1) = (x0 + live_grid.size.0 as usize, y0 + live_grid.size.1 as usize);
                o.x0 < x1 && x0 < o.x0 + w && o.y0 < y1 && y0 < o.y0 + h
            };
            let finer: Vec<&Override<K::Value>> = overrides.iter().filter(near).collect();
            if fine.is_none() {
                // No input as deep as this level: only its tiles are made, each on its own.
                let border = u32::from(metadata.layers[usize::from(index)].border);
                let at = Beneath { level, rect, res, border, corner: live_corner, size: live_grid.size };
                let encode = |x: u32, y: u32, samples: &[K::Value], edge: usize| {
                    if part.is_some_and(|p| !p.holds(lod, y)) {
                        return Ok(Vec::new());
                    }
                    encode_tile(TileKey::new(index, lod, x, y)?, samples, edge)
                };
                let mut add = |key: TileKey, bytes: &[u8]| spool.add(metadata, key, bytes);
                next.push(tiles_beneath(&at, coarse.as_ref(), &finer, quantize, &encode, &mut add, progress)?);
                tracing::debug!(lod, ?rect, "level of the collection made over a rectangle, tile by tile");
                continue;
            }
            // The tiles go straight to `spool` under their keys on the whole grid (the
            // pyramid cuts the rectangle's, from its corner).
            let encode = |key: TileKey, samples: &[K::Value], edge: usize| -> Result<Vec<(TileKey, Vec<u8>)>> {
                let (x, y) = (rect[0] + key.x(), rect[1] + key.y());
                if !level.tiles.contains(&(x, y)) || part.is_some_and(|p| !p.holds(lod, y)) {
                    return Ok(Vec::new());
                }
                encode_tile(TileKey::new(index, lod, x, y)?, samples, edge)
            };
            let mut halved =
                Override { x0: live_corner.0 as usize / 2, y0: live_corner.1 as usize / 2, rows: Vec::new() };
            {
                let (fine, coarse, halved) = (fine.as_ref(), coarse.as_ref(), &mut halved);
                let (overrides, blend) = (&finer, c.blend);
                let h = grid.size.1 as usize;
                let (x0, y0, lh) = (live[0] as usize, live[1] as usize, live_grid.size.1 as usize);
                // Rows are made (read, blended, rounded, halved) across the part while the
                // pyramid cuts the ones before (one level: nothing for it to round
                // again). Its rows hold the part's columns, from `x0`; those above and
                // below it hold none.
                let finish = RowFinish { quantize };
                let window = Window { first_column: x0, ..Window::full(1, h) };
                run_pyramid(metadata, index, grid.size, &window, &encode, None, spool, progress, move |push| {
                    for _ in 0..y0 {
                        push(Vec::new())?;
                    }
                    let finish = &finish;
                    level_rows_in_bands(
                        fine,
                        coarse,
                        &live_grid,
                        live_corner,
                        overrides,
                        blend,
                        finish,
                        threads,
                        &mut |(row, half)| {
                            halved.rows.extend(half);
                            push(row)
                        },
                    )?;
                    for _ in y0 + lh..h {
                        push(Vec::new())?;
                    }
                    Ok(())
                })?;
            }
            halved.keep_held(level, res);
            next.push(halved);
            tracing::debug!(lod, ?rect, "level of the collection made over a rectangle");
        }
        overrides = next;
    }
    Ok(overrides)
}

/// Where [`tiles_beneath`] makes a level's rectangle: the level, the rectangle, its tiles'
/// size and border, and its live part (first sample on the level, and size; see
/// [`live_part`]).
struct Beneath<'l> {
    level: &'l SparseLevel,
    rect: [u32; 4],
    res: u32,
    border: u32,
    corner: (u32, u32),
    size: (u32, u32),
}

/// A tile [`tiles_beneath`] cut: its column and row, archive entries, and 2x2 means.
type CutTile<S> = (u32, u32, Vec<(TileKey, Vec<u8>)>, Vec<S>);

/// Encodes a level's tile (its column and row, samples and edge) into its archive entries.
type EncodeAt<'e, S> = dyn Fn(u32, u32, &[S], usize) -> Result<Vec<(TileKey, Vec<u8>)>> + Sync + 'e;

/// The tiles `at.level` holds in rectangle `at.rect` where no input is as deep as the
/// level: each sample the finer level's means where they lie (`overrides`), else the
/// `coarse` data beneath, rounded (`quantize`); no data outside the live part. The same
/// samples as [`level_rows`] makes across the live part, but no sample depends on another
/// (nothing to blend): only the held tiles are made, not the rows across the rectangle,
/// a row of tiles at a time on every core while the coarse rows they read are pulled in
/// order and let go. Each tile with data goes to `encode`, its entries to `add`. Returns
/// the tiles' 2x2 means, rounded: what the next level takes where they lie (as
/// [`RowFinish`] and [`Override::keep_held`] leave them).
fn tiles_beneath<S: Pixel>(
    at: &Beneath<'_>,
    coarse: Option<&Coarse<'_, '_, S>>,
    overrides: &[&Override<S>],
    quantize: Option<&QuantizeRow<'_, S>>,
    encode: &EncodeAt<'_, S>,
    add: &mut dyn FnMut(TileKey, &[u8]) -> Result<()>,
    progress: &dyn Progress,
) -> Result<Override<S>> {
    let (res, border) = (at.res as usize, at.border as usize);
    let (edge, half) = (res + 2 * border, res / 2);
    let (x0, y0) = (at.corner.0 as usize, at.corner.1 as usize);
    let (w, h) = (at.size.0 as usize, at.size.1 as usize);
    let mut halved = Override { x0: x0 / 2, y0: y0 / 2, rows: vec![vec![S::NONE; w.div_ceil(2)]; h.div_ceil(2)] };
    let level_row = |y: usize| u32::try_from(y).unwrap_or(u32::MAX);
    let (mut up, pulled) = match coarse {
        Some(c) => {
            let (up, pulled) = Upsample::new(c, at.corner, w, at.size.1);
            (Some(up), Some((c, pulled)))
        }
        None => (None, None),
    };
    let (send, receive) = std::sync::mpsc::sync_channel::<Vec<S>>(64);
    std::thread::scope(|scope| -> Result<()> {
        let reader = pulled.map(|(c, pulled)| scope.spawn(move || c.send_rows(pulled, &send)));
        let mut pull = || receive.recv().map_err(|_| crate::error::interrupted());
        // Rows of tiles in batches of at least a few tiles a core, the coarse rows
        // each batch reads held while it is cut.
        let batch_tiles = 4 * rayon::current_num_threads();
        let mut ty = at.rect[1];
        let mut made = || -> Result<()> {
            while ty <= at.rect[3] {
                progress.check()?;
                let first_row = ty;
                let mut batch: Vec<(u32, u32)> = Vec::new();
                while ty <= at.rect[3] && batch.len() < batch_tiles {
                    progress.advance(u64::from(at.rect[2] - at.rect[0] + 1));
                    batch.extend(
                        (at.rect[0]..=at.rect[2]).filter(|&tx| at.level.tiles.contains(&(tx, ty))).map(|tx| (tx, ty)),
                    );
                    ty += 1;
                }
                // The level rows a row of tiles reads (borders included) in the live part.
                let rows = |ty: u32| {
                    let top = ty as usize * res;
                    (top.saturating_sub(border).max(y0), (top + res + border).min(y0 + h))
                };
                let end = rows(ty - 1).1;
                if batch.is_empty() || rows(first_row).0 >= end {
                    continue;
                }
                if let Some(up) = up.as_mut() {
                    up.reach(level_row(end - 1), &mut pull)?;
                }
                let held = up.as_ref();
                let cut = |samples: &mut Vec<S>, &(tx, ty): &(u32, u32)| -> Result<CutTile<S>> {
                    let (left, top) = (tx as usize * res, ty as usize * res);
                    samples.fill(S::NONE);
                    // The live part's columns the tile reads; its first column is `left - border`.
                    let (c0, c1) = (left.saturating_sub(border).max(x0), (left + res + border).min(x0 + w));
                    let (first, end) = rows(ty);
                    for y in (first..end).filter(|_| c0 < c1) {
                        let at = (y + border - top) * edge + (c0 + border - left);
                        overridden_into(overrides, c0, y, &mut samples[at..at + (c1 - c0)], &|out, columns| {
                            if let Some(up) = held {
                                let from = c0 - x0;
                                up.fill_into(
                                    level_row(y),
                                    &mut out[columns.clone()],
                                    from + columns.start..from + columns.end,
                                );
                            }
                        });
                    }
                    if let Some(q) = quantize {
                        q(samples);
                    }
                    let interior =
                        |j: usize| &samples[(border + j) * edge + border..(border + j) * edge + border + res];
                    let entries = if (0..res).any(|j| interior(j).iter().any(S::has_data)) {
                        encode(tx, ty, samples, edge)?
                    } else {
                        Vec::new()
                    };
                    let mut means = Vec::with_capacity(half * half);
                    for r in 0..half {
                        let mut m = halve_rows(interior(2 * r), interior(2 * r + 1));
                        if let Some(q) = quantize {
                            q(&mut m);
                        }
                        means.extend(m);
                    }
                    Ok((tx, ty, entries, means))
                };
                // A tile's samples in a buffer each worker reuses (not fresh memory a tile).
                let cuts =
                    (batch.par_iter()).map_init(|| vec![S::NONE; edge * edge], cut).collect::<Result<Vec<_>>>()?;
                for (tx, ty, entries, means) in cuts {
                    for (key, bytes) in entries {
                        add(key, &bytes)?;
                    }
                    // The means in the live part's.
                    let hx = tx as usize * half;
                    let (from, to) = (hx.max(halved.x0), (hx + half).min(halved.x0 + w.div_ceil(2)));
                    for r in (0..half).filter(|_| from < to) {
                        let Some(row) =
                            (ty as usize * half + r).checked_sub(halved.y0).and_then(|j| halved.rows.get_mut(j))
                        else {
                            continue;
                        };
                        row[from - halved.x0..to - halved.x0]
                            .copy_from_slice(&means[r * half + from - hx..r * half + to - hx]);
                    }
                }
                if let Some(up) = up.as_mut() {
                    up.release(level_row(rows(ty).0));
                }
            }
            Ok(())
        };
        let made = made();
        drop(receive);
        let read = reader.map_or(Ok(()), |r| r.join().unwrap_or(Err(Error::Panicked { thread: "coarse rows" })));
        the_cause(made, [read])
    })?;
    Ok(halved)
}

/// What stopped a level made on one thread from rows that others read (`readers`, each
/// stopping quietly or with [`crate::error::interrupted`] once nobody pulls its rows):
/// the maker's own error, unless it is only the rows' end, an interruption that a reader's
/// failure caused (its channel closed): then that reader's error, which names what failed.
fn the_cause<const N: usize>(made: Result<()>, readers: [Result<()>; N]) -> Result<()> {
    match made {
        Err(e) if e.is_interrupted() => {
            Err(readers.into_iter().filter_map(Result::err).find(|r| !r.is_interrupted()).unwrap_or(e))
        }
        Err(e) => Err(e),
        Ok(()) => readers.into_iter().collect(),
    }
}

/// The part of a level's rectangle `rect` (corner sample `corner`, `grid`) that its tiles
/// need made: the tiles `level` holds there, with a margin of two samples (their borders,
/// and the edge beyond the fine data the blend measures from), its corner on the mosaics'
/// lattice (an even sample of the level: its 2x2 means fall on the next level's): its
/// first and end column and row in the rectangle; None when it holds no tile.
fn live_part(level: &SparseLevel, rect: [u32; 4], res: u32, corner: (u32, u32), grid: &GridSpec) -> Option<[u32; 4]> {
    const MARGIN: u32 = 2;
    // The rectangle's own tiles looked up, as many as making it costs (filtering the
    // level's whole set would cost every survey's tiles for each rectangle).
    let held: Vec<(u32, u32)> = (rect[1]..=rect[3])
        .flat_map(|y| (rect[0]..=rect[2]).map(move |x| (x, y)))
        .filter(|t| level.tiles.contains(t))
        .collect();
    let (tx0, tx1) = (held.iter().map(|t| t.0).min()?, held.iter().map(|t| t.0).max()?);
    let (ty0, ty1) = (held.iter().map(|t| t.1).min()?, held.iter().map(|t| t.1).max()?);
    // From the rectangle's corner, on the mosaic's lattice of exact transforms from the
    // level's corner (so that the part's samples are the whole level's; even, too).
    let lattice = u32::try_from(crate::raster::LATTICE).unwrap_or(32);
    let start = |t: u32, first: u32, corner: u32| {
        let s = ((t - first) * res).saturating_sub(MARGIN);
        ((corner + s) / lattice * lattice).max(corner) - corner
    };
    let end = |t: u32, first: u32, size: u32| ((t + 1 - first) * res + MARGIN).min(size);
    let (x0, y0) = (start(tx0, rect[0], corner.0), start(ty0, rect[1], corner.1));
    let (x1, y1) = (end(tx1, rect[0], grid.size.0), end(ty1, rect[1], grid.size.1));
    (x1 > x0 && y1 > y0).then_some([x0, y0, x1, y1])
}

/// The coarser inputs beneath a level, sampled on a grid `2^shift` times coarser than the
/// level's (no coarser than their own spacing: their detail is all there) and brought
/// to the level's samples bilinearly, which costs a level's row a few operations a sample
/// instead of a transform and a bilinear read of the inputs each.
struct Coarse<'a, 'q, S> {
    source: Box<dyn CoarseRows<S> + 'a>,
    shift: u32,
    /// The stored precision (a level's values as its tiles hold them).
    quantize: Option<&'q QuantizeRow<'q, S>>,
    /// The level's sample of the coarse grid's first column and row (its corner).
    first: (i64, i64),
}

impl<S: Pixel> Coarse<'_, '_, S> {
    /// Rows `rows` of the coarse grid, rounded as the level stores them, sent in order to
    /// `send` (from a thread of their own, for [`Upsample::reach`] to pull); stops once
    /// the receiver is gone. That is no error: the receiver drops it when it has pulled
    /// all it needs (`rows` reaches a row past the last it reads), or on an error of its
    /// own, which its caller reports.
    fn send_rows(&self, rows: std::ops::Range<u32>, send: &std::sync::mpsc::SyncSender<Vec<S>>) -> Result<()> {
        let mut gone = false;
        let read = self.source.rows(rows, &mut |mut r| {
            if let Some(q) = self.quantize {
                q(&mut r);
            }
            send.send(r).map_err(|_| {
                gone = true;
                crate::error::interrupted()
            })
        });
        if gone { Ok(()) } else { read }
    }
}

/// Where a [`Coarse`] grid's values come from: the coarser inputs ([`MosaicPart`]), or an
/// archive's stored level (an update's).
pub(crate) trait CoarseRows<S>: Send + Sync {
    /// Samples across and down.
    fn size(&self) -> (u32, u32);
    /// Rows `rows`, in order.
    fn rows(&self, rows: std::ops::Range<u32>, each: &mut dyn FnMut(Vec<S>) -> Result<()>) -> Result<()>;
}

/// The coarser inputs on their level's whole grid (so that each sample is the one the
/// level stores: the mosaic's transforms are exact on a lattice from its corner), and the
/// part of it wanted: first column and row, columns and rows.
pub(crate) struct MosaicPart<K: MosaicKind> {
    pub(crate) mosaic: Mosaic<K>,
    pub(crate) first: (i64, i64),
    pub(crate) size: (u32, u32),
}

impl<K: MosaicKind> CoarseRows<K::Value> for MosaicPart<K>
where
    K::Value: Pixel,
{
    fn size(&self) -> (u32, u32) {
        self.size
    }

    fn rows(&self, rows: std::ops::Range<u32>, each: &mut dyn FnMut(Vec<K::Value>) -> Result<()>) -> Result<()> {
        let (first, size) = (self.first, self.size);
        let (w, h) = (i64::from(self.mosaic.grid().size.0), i64::from(self.mosaic.grid().size.1));
        let crop = |r: &[K::Value]| -> Vec<K::Value> {
            (0..i64::from(size.0))
                .map(|c| {
                    let x = first.0 + c;
                    if (0..w).contains(&x) { r[usize::try_from(x).unwrap_or(0)] } else { K::Value::NONE }
                })
                .collect()
        };
        let none = || vec![K::Value::NONE; size.0 as usize];
        let (r0, r1) = (first.1 + i64::from(rows.start), first.1 + i64::from(rows.end.min(size.1)));
        // Rows above and below the grid: none.
        for _ in r0..r1.min(0) {
            each(none())?;
        }
        let inside = u32::try_from(r0.clamp(0, h)).unwrap_or(0)..u32::try_from(r1.clamp(0, h)).unwrap_or(0);
        self.mosaic.rows_of(inside, &mut |r| Ok(each(crop(r))?))?;
        for _ in r0.max(h)..r1 {
            each(none())?;
        }
        Ok(())
    }
}

/// The coarse grid over a level's rectangle (corner `corner`, size `size` samples of a
/// level of spacing `pixel` from `origin`): `shift` levels coarser, a sample of margin each
/// way for the bilinear reads at the edges.
pub(crate) fn coarse_grid(
    origin: [f64; 2],
    pixel: (f64, f64),
    corner: (u32, u32),
    size: (u32, u32),
    shift: u32,
) -> ((i64, i64), GridSpec) {
    let k = 1i64 << shift;
    let (c0, r0) = (i64::from(corner.0).div_euclid(k) - 1, i64::from(corner.1).div_euclid(k) - 1);
    let (c1, r1) = (
        (i64::from(corner.0) + i64::from(size.0)).div_euclid(k) + 2,
        (i64::from(corner.1) + i64::from(size.1)).div_euclid(k) + 2,
    );
    #[expect(clippy::cast_precision_loss, reason = "sample indices")]
    let scale = k as f64;
    let cell = (pixel.0 * scale, pixel.1 * scale);
    #[expect(clippy::cast_precision_loss, reason = "sample indices")]
    let at = [origin[0] + c0 as f64 * cell.0, origin[1] - r0 as f64 * cell.1];
    let side = |n: i64| u32::try_from(n).unwrap_or(u32::MAX);
    ((c0, r0), GridSpec { origin: at, pixel: cell, size: (side(c1 - c0), side(r1 - r0)) })
}

/// Rows of a [`Coarse`] grid brought to a level's samples.
struct Upsample<S> {
    shift: u32,
    first: (i64, i64),
    size: (usize, usize),
    /// Per output column: the coarse column left of it and the weight of the right one.
    columns: Vec<(usize, f32)>,
    held: VecDeque<Vec<S>>,
    /// Coarse row index of `held[0]`.
    front: usize,
}

impl<S: Pixel> Upsample<S> {
    /// For `height` level rows from `corner` (its first column and row), `width` across;
    /// with the coarse rows they read (the rows to pull, in order).
    fn new(coarse: &Coarse<'_, '_, S>, corner: (u32, u32), width: usize, height: u32) -> (Self, std::ops::Range<u32>) {
        let grid = coarse.source.size();
        let size = (grid.0 as usize, grid.1 as usize);
        let columns = (0..width)
            .map(|i| Self::at(u32::try_from(i).unwrap_or(u32::MAX) + corner.0, coarse.shift, coarse.first.0, size.0))
            .collect();
        let top = Self::at(corner.1, coarse.shift, coarse.first.1, size.1).0;
        let bottom = Self::at(corner.1 + height.saturating_sub(1), coarse.shift, coarse.first.1, size.1).0;
        let pulled =
            u32::try_from(top).unwrap_or(u32::MAX)..u32::try_from((bottom + 2).min(size.1)).unwrap_or(u32::MAX);
        (Self { shift: coarse.shift, first: coarse.first, size, columns, held: VecDeque::new(), front: top }, pulled)
    }

    /// Level sample `n`'s coarse cell (clamped) and weight of the next one.
    fn at(n: u32, shift: u32, first: i64, len: usize) -> (usize, f32) {
        let k = f64::from(1u32 << shift);
        #[expect(clippy::cast_precision_loss, reason = "sample indices")]
        let u = (f64::from(n) + 0.5) / k - 0.5 - first as f64;
        let fl = u.floor();
        #[expect(clippy::cast_possible_truncation, clippy::cast_sign_loss, reason = "clamped to the grid")]
        let c = (fl.max(0.0) as usize).min(len.saturating_sub(2));
        #[expect(clippy::cast_possible_truncation, clippy::cast_precision_loss, reason = "a weight")]
        let f = ((u - c as f64).clamp(0.0, 1.0)) as f32;
        (c, f)
    }

    /// Pulls the coarse rows level row `gy` (absolute) reads.
    fn reach(&mut self, gy: u32, pull: &mut dyn FnMut() -> Result<Vec<S>>) -> Result<()> {
        let (r, _) = Self::at(gy, self.shift, self.first.1, self.size.1);
        while self.front + self.held.len() < (r + 2).min(self.size.1) {
            self.held.push_back(pull()?);
        }
        Ok(())
    }

    /// Lets go of the coarse rows no level row from `gy` on reads.
    fn release(&mut self, gy: u32) {
        let (r, _) = Self::at(gy, self.shift, self.first.1, self.size.1);
        while self.front < r && self.held.len() > 2 {
            self.held.pop_front();
            self.front += 1;
        }
    }

    /// Columns `columns` of level row `gy` (absolute) into `row`, between the rows
    /// [`Self::reach`] pulled and [`Self::release`] kept.
    fn fill(&self, gy: u32, row: &mut [S], columns: std::ops::Range<usize>) {
        self.fill_into(gy, &mut row[columns.clone()], columns);
    }

    /// [`Self::fill`] of `columns` into `out` (as many samples).
    fn fill_into(&self, gy: u32, out: &mut [S], columns: std::ops::Range<usize>) {
        let Some(&(c0, _)) = self.columns.get(columns.start) else { return };
        let (r, fy) = Self::at(gy, self.shift, self.first.1, self.size.1);
        let top = &self.held[r - self.front];
        let bottom = self.held.get(r + 1 - self.front).unwrap_or(top);
        // Down first (the coarse columns these read), then across; where one of two
        // values is missing, the other stands.
        let last = self.size.0.saturating_sub(1);
        let c1 = self.columns.get(columns.end.saturating_sub(1)).map_or(c0, |&(c, _)| c);
        let (c1, c1_next) = (c1.min(last), (c1 + 1).min(last));
        let between: Vec<S> = (c0..=c1_next.max(c1)).map(|c| S::lerp(top[c], bottom[c], fy)).collect();
        let at = |c: usize| between[c - c0];
        for (out, &(c, fx)) in out.iter_mut().zip(&self.columns[columns]) {
            *out = S::lerp(at(c), at((c + 1).min(last)), fx);
        }
    }
}

/// How [`level_rows_in_bands`] finishes each row where it is made: rounded to the stored
/// precision (`quantize`), and the 2x2 means of each pair of rows taken from it (with the
/// grid's first row even on the level).
pub(crate) struct RowFinish<'f, S> {
    quantize: Option<&'f QuantizeRow<'f, S>>,
}

/// A row as [`level_rows_in_bands`] hands it over: the row, and after each pair (or a
/// last row alone), the pair's 2x2 means.
type Finished<S> = (Vec<S>, Option<Vec<S>>);

impl<S: Pixel> RowFinish<'_, S> {
    /// Rows `rows` (the grid's from an even one) finished.
    fn rows(&self, rows: Vec<Vec<S>>, emit: &mut dyn FnMut(Finished<S>) -> Result<()>) -> Result<()> {
        let mut rows = rows.into_iter();
        while let Some(mut a) = rows.next() {
            let q = |row: &mut Vec<S>| {
                if let Some(q) = self.quantize {
                    q(row);
                }
            };
            q(&mut a);
            let b = rows.next().map(|mut b| {
                q(&mut b);
                b
            });
            let mut half = halve_rows(&a, b.as_deref().unwrap_or(&vec![S::NONE; a.len()]));
            q(&mut half);
            match b {
                Some(b) => {
                    emit((a, None))?;
                    emit((b, Some(half)))?;
                }
                None => emit((a, Some(half)))?,
            }
        }
        Ok(())
    }
}

/// Cores from which a level's rows are made in bands, one worker a core: below, in one
/// run. There the rows' warp (on every core) keeps the cores busy, and what runs on one
/// thread (the blend, the coarse data in the survey's gaps, the finishing: 29 % of the
/// level's CPU time in `perf record` of `scripts/bench-collection.sh`) keeps up; bands
/// would add their margins' rows, a band's memory a worker, and workers that contend with
/// the warp's (that bench on 2 cores: 0.85x the CPU time and 0.82x the wall time in one
/// run). Bands cost some 15 % more work, so with that thread's share they break even at
/// about four cores; from there it would be the bottleneck.
pub(crate) const BANDS_FROM: usize = 4;

/// [`level_rows`] of a whole rectangle's `grid`, handed to `emit` in order, each pair of
/// rows finished (`finish`) where it is made. With [`BANDS_FROM`] `threads` or more, made
/// in bands of rows on as many workers (each band with `blend` rows more above and below,
/// for the blend's distances); else in one run. The rows are those [`level_rows`] makes
/// in one run.
#[expect(clippy::too_many_arguments, reason = "the sources, where the rows lie, what to blend and finish")]
fn level_rows_in_bands<K: MosaicKind>(
    fine: Option<&Mosaic<K>>,
    coarse: Option<&Coarse<'_, '_, K::Value>>,
    grid: &GridSpec,
    corner: (u32, u32),
    overrides: &[&Override<K::Value>],
    blend: u32,
    finish: &RowFinish<'_, K::Value>,
    threads: usize,
    emit: &mut dyn FnMut(Finished<K::Value>) -> Result<()>,
) -> Result<()>
where
    K::Value: Pixel,
{
    /// Rows a band holds (at least; more where the blend's margin would outweigh it).
    const BAND: u32 = 128;
    /// Samples a band holds at most (unless its least rows are more): each worker holds
    /// one being made and one made.
    const BAND_SAMPLES: u32 = 1 << 24;
    let h = grid.size.1;
    // Each band is made with the blend's rows above and below it again: a few bands a
    // worker, as tall as memory allows, so that those are few. An even number of rows,
    // so that each pair of rows lies in one band.
    let least = BAND.max(blend.saturating_mul(4));
    let most = least.max(BAND_SAMPLES / grid.size.0.max(1));
    let band = h.div_ceil(u32::try_from(threads * 3).unwrap_or(u32::MAX)).clamp(least, most).next_multiple_of(2);
    let bands: Vec<std::ops::Range<u32>> = (0..h).step_by(band as usize).map(|a| a..(a + band).min(h)).collect();
    let make = |b: &std::ops::Range<u32>| -> Result<Vec<Finished<K::Value>>> {
        let read = b.start.saturating_sub(blend)..b.end.saturating_add(blend).min(h);
        let mut rows = Vec::with_capacity(read.len());
        let at = (corner.0, corner.1 + read.start);
        level_rows(fine, coarse, grid, at, read.clone(), overrides, blend, &mut |r| {
            rows.push(r);
            Ok(())
        })?;
        let rows: Vec<Vec<K::Value>> = rows.into_iter().skip((b.start - read.start) as usize).take(b.len()).collect();
        let mut made = Vec::with_capacity(rows.len());
        finish.rows(rows, &mut |r| {
            made.push(r);
            Ok(())
        })?;
        Ok(made)
    };
    if threads < BANDS_FROM || bands.len() < 2 {
        // One run, each pair of rows finished as it is made.
        let mut pending: Option<Vec<K::Value>> = None;
        level_rows(fine, coarse, grid, corner, 0..h, overrides, blend, &mut |r| match pending.take() {
            None => {
                pending = Some(r);
                Ok(())
            }
            Some(a) => finish.rows(vec![a, r], emit),
        })?;
        return pending.map_or(Ok(()), |a| finish.rows(vec![a], emit));
    }
    tracing::debug!(bands = bands.len(), threads, "a level's rows made in bands");
    std::thread::scope(|scope| -> Result<()> {
        // Worker t makes bands t, t + threads, …; each hands them over one at a time, so
        // at most a band a worker waits made ahead of the one being emitted.
        let (bands, make) = (&bands, &make);
        let mut workers = Vec::with_capacity(threads);
        let mut receivers = Vec::with_capacity(threads);
        for t in 0..threads {
            let (send, receive) = std::sync::mpsc::sync_channel::<Result<Vec<Finished<K::Value>>>>(1);
            receivers.push(receive);
            workers.push(scope.spawn(move || {
                for b in bands.iter().skip(t).step_by(threads) {
                    let made = make(b);
                    let failed = made.is_err();
                    // A send fails once the rows' consumer has stopped.
                    if send.send(made).is_err() || failed {
                        break;
                    }
                }
            }));
        }
        let emitted = (0..bands.len()).try_for_each(|i| -> Result<()> {
            let rows = receivers[i % threads].recv().map_err(|_| crate::error::interrupted())??;
            rows.into_iter().try_for_each(&mut *emit)
        });
        drop(receivers);
        let joined = workers.into_iter().map(std::thread::ScopedJoinHandle::join).collect::<Vec<_>>();
        // A worker that panicked dropped its channel: say so rather than "interrupted".
        if joined.iter().any(std::result::Result::is_err) {
            return Err(Error::Panicked { thread: "collection rows" });
        }
        emitted
    })
}

/// Makes rows `rows` of a level's `grid` (its first column the level's `corner.0`, row
/// `rows.start` the level's `corner.1`): the finer level's halved rows where they lie
/// (`overrides`), else the `fine` inputs' samples, completed from the `coarse` ones where
/// they have none and blended into them across `blend` samples along their data's edge.
#[expect(clippy::too_many_arguments, reason = "the sources, where the rows lie, and what to blend")]
fn level_rows<K: MosaicKind>(
    fine: Option<&Mosaic<K>>,
    coarse: Option<&Coarse<'_, '_, K::Value>>,
    grid: &GridSpec,
    corner: (u32, u32),
    rows: std::ops::Range<u32>,
    overrides: &[&Override<K::Value>],
    blend: u32,
    emit: &mut dyn FnMut(Vec<K::Value>) -> Result<()>,
) -> Result<()>
where
    K::Value: Pixel,
{
    let (w, h) = (grid.size.0 as usize, rows.len());
    // No fine data: nothing to blend (and no distances to find).
    let mut ring = Blender::new(w, if fine.is_some() { blend as usize } else { 0 }, corner, overrides);
    let Some(coarse) = coarse else {
        let no_coarse = |_: usize, _: &mut [K::Value], _: std::ops::Range<usize>| {};
        match fine {
            Some(m) => m.rows_of(rows.clone(), &mut |r| Ok(ring.push(r.to_vec(), &no_coarse, emit)?))?,
            None => {
                for j in 0..h {
                    emit(overridden(overrides, corner.0 as usize, corner.1 as usize + j, w, &|_, _| {}))?;
                }
            }
        }
        return ring.finish(h, &no_coarse, emit);
    };
    let (mut up, pulled) = Upsample::new(coarse, corner, w, u32::try_from(h).unwrap_or(u32::MAX));
    let (send, receive) = std::sync::mpsc::sync_channel::<Vec<K::Value>>(64);
    let level_row = |y: usize| corner.1 + u32::try_from(y).unwrap_or(u32::MAX);
    std::thread::scope(|scope| -> Result<()> {
        let reader = scope.spawn(move || coarse.send_rows(pulled, &send));
        let mut pull = || receive.recv().map_err(|_| crate::error::interrupted());
        // The fine rows are made on a thread of their own too, while this one blends the
        // rows before.
        let (fine_send, fine_receive) = std::sync::mpsc::sync_channel::<Vec<K::Value>>(64);
        let fine_reader = fine.map(|f| {
            scope.spawn(move || {
                f.rows_owned(rows.clone(), &mut |r| Ok(fine_send.send(r).map_err(|_| crate::error::interrupted())?))
            })
        });
        let made = (0..u32::try_from(h).unwrap_or(u32::MAX)).try_for_each(|j| -> Result<()> {
            let gy = corner.1 + j;
            up.reach(gy, &mut pull)?;
            if fine_reader.is_none() {
                // No fine data: the finer level's means where they lie, else the coarser
                // data beneath (nothing to blend, nothing held). Runs make such a level
                // tile by tile ([`tiles_beneath`]); these rows are what its test holds
                // it to.
                let row = overridden(overrides, corner.0 as usize, gy as usize, w, &|row, columns| {
                    up.fill(gy, row, columns);
                });
                up.release(gy);
                return emit(row);
            }
            let fine_row = fine_receive.recv().map_err(|_| crate::error::interrupted())?;
            // The coarse rows stay until the rows the blend holds are out: a row inside
            // a survey reads them only near its edge, when it is emitted.
            ring.push(fine_row, &|y, row: &mut [K::Value], columns| up.fill(level_row(y), row, columns), emit)?;
            up.release(level_row(ring.emitted));
            Ok(())
        });
        drop(receive);
        drop(fine_receive);
        let read = reader.join().unwrap_or(Err(Error::Panicked { thread: "coarse rows" }));
        let fine_read = fine_reader.map_or(Ok(()), |r| {
            r.join().map_or(Err(Error::Panicked { thread: "fine rows" }), |r| r.map_err(Error::from))
        });
        the_cause(made, [fine_read, read])
    })?;
    ring.finish(h, &|y, row: &mut [K::Value], columns| up.fill(level_row(y), row, columns), emit)
}

/// Row `gy` (absolute) of a level without fine data, `w` columns from `gx0`: the finer
/// level's means where they lie (`overrides`), else the coarser data beneath (`fill` of
/// those columns).
fn overridden<S: Pixel>(
    overrides: &[&Override<S>],
    gx0: usize,
    gy: usize,
    w: usize,
    fill: &dyn Fn(&mut [S], std::ops::Range<usize>),
) -> Vec<S> {
    let mut out = vec![S::NONE; w];
    overridden_into(overrides, gx0, gy, &mut out, fill);
    out
}

/// [`overridden`] into `out` (no data on entry), as many samples from `gx0`.
fn overridden_into<S: Pixel>(
    overrides: &[&Override<S>],
    gx0: usize,
    gy: usize,
    out: &mut [S],
    fill: &dyn Fn(&mut [S], std::ops::Range<usize>),
) {
    apply_overrides(overrides, gx0, gy, out);
    let mut x = 0;
    while let Some(start) = next_where(out, x, false) {
        let end = next_where(out, start, true).unwrap_or(out.len());
        fill(out, start..end);
        x = end;
    }
}

/// The finer level's means (`overrides`) where they lie over row `gy` (absolute) of a
/// level, `out` from column `gx0`.
fn apply_overrides<S: Pixel>(overrides: &[&Override<S>], gx0: usize, gy: usize, out: &mut [S]) {
    let w = out.len();
    for o in overrides {
        let Some(src) = gy.checked_sub(o.y0).and_then(|r| o.rows.get(r)) else { continue };
        let (from, to) = (o.x0.max(gx0), (o.x0 + src.len()).min(gx0 + w));
        if from >= to {
            continue;
        }
        // A select, not a branch, for each sample (the compiler vectorizes it).
        for (d, &v) in out[from - gx0..to - gx0].iter_mut().zip(&src[from - o.x0..to - o.x0]) {
            *d = if v.has_data() { v } else { *d };
        }
    }
}

/// The first sample of `row` from `from` on that has data (`data`) or has none; None if
/// no sample does. Sixteen samples are tested at once, with no branch among them (the
/// compiler vectorizes it): a run of either kind is passed over at memory's speed.
fn next_where<S: Pixel>(row: &[S], from: usize, data: bool) -> Option<usize> {
    const STEP: usize = 16;
    let mut at = from.min(row.len());
    while let Some(chunk) = row.get(at..at + STEP) {
        if chunk.iter().fold(false, |found, v| found | (v.has_data() == data)) {
            break;
        }
        at += STEP;
    }
    row[at..].iter().position(|v| v.has_data() == data).map(|p| p + at)
}

/// A level's rows held until the rows `band` below them are in (for the blend's distance
/// to the fine data's edge), with each row's distance along it.
struct Blender<'a, S> {
    width: usize,
    band: usize,
    corner: (u32, u32),
    overrides: &'a [&'a Override<S>],
    /// Rows `front..`.
    held: VecDeque<Held<S>>,
    front: usize,
    emitted: usize,
}

/// A row a [`Blender`] holds.
struct Held<S> {
    fine: Vec<S>,
    /// The coarser data beneath where the fine data has none, and where the blend
    /// reaches (else none; empty: none at all).
    coarse: Vec<S>,
    /// The runs of columns within the band of an edge, in order.
    near: Vec<Near>,
    /// Distance along the row to the fine data's edge (at most the band), for the columns
    /// of each run of `near` in turn.
    across: Vec<u32>,
    /// The runs of columns where the fine data has none (first, end), in order.
    gaps: Vec<(usize, usize)>,
}

/// Columns `from..to` of a row within the band of an edge, their distances in the row's
/// `across` from `at`.
#[derive(Clone, Copy, Debug)]
struct Near {
    from: usize,
    to: usize,
    at: usize,
}

/// Fills columns of a [`Blender`]'s row `y` (of the rows it is given) with the coarser
/// data beneath.
type CoarseOf<'c, S> = dyn Fn(usize, &mut [S], std::ops::Range<usize>) + 'c;

impl<'a, S: Pixel> Blender<'a, S> {
    /// Rows `width` across from level column `corner.0`, row `corner.1`, blended across
    /// `band` samples, the finer level's means `overrides` over them.
    fn new(width: usize, band: usize, corner: (u32, u32), overrides: &'a [&'a Override<S>]) -> Self {
        Self { width, band, corner, overrides, held: VecDeque::new(), front: 0, emitted: 0 }
    }

    /// Takes the next row's fine data (the coarser data beneath read from `coarse_of` as
    /// needed); emits the rows whose blend is known.
    fn push(
        &mut self,
        fine: Vec<S>,
        coarse_of: &CoarseOf<'_, S>,
        emit: &mut dyn FnMut(Vec<S>) -> Result<()>,
    ) -> Result<()> {
        let y = self.front + self.held.len();
        // The coarser data where the fine data has none; where the blend reaches the
        // fine data from an edge, once the rows around are in (most of a survey: none).
        let (mut coarse, mut gaps) = (Vec::new(), Vec::new());
        let mut x = 0;
        while let Some(start) = next_where(&fine, x, false) {
            let end = next_where(&fine, start, true).unwrap_or(fine.len());
            if coarse.is_empty() {
                coarse = vec![S::NONE; self.width];
            }
            coarse_of(y, &mut coarse, start..end);
            gaps.push((start, end));
            x = end;
        }
        let (near, across) = if self.band > 0 { self.edge(&coarse, &gaps) } else { (Vec::new(), Vec::new()) };
        self.held.push_back(Held { fine, coarse, near, across, gaps });
        if y + 1 > self.emitted + self.band {
            self.emit_next(coarse_of, emit)?;
        }
        Ok(())
    }

    /// Along a row: the runs of columns within the band of the fine data's edge (a
    /// sample where the coarse data has heights and the fine data none, so only in the
    /// row's `gaps`), touching ones joined, in order; and there, the distance along the
    /// row to the nearest edge. The work follows the gaps, not the row's width. (A row
    /// with no fine data is all edge where the coarse data has heights: the rows above
    /// and below a survey count as much as those beside it.)
    fn edge(&self, coarse: &[S], gaps: &[(usize, usize)]) -> (Vec<Near>, Vec<u32>) {
        let (w, band) = (self.width, self.band);
        let cap = u32::try_from(band + 1).unwrap_or(u32::MAX);
        let distance = |n: usize| u32::try_from(n).unwrap_or(u32::MAX);
        let (mut near, mut across): (Vec<Near>, Vec<u32>) = (Vec::new(), Vec::new());
        for &(from, to) in gaps {
            // Each run of edge samples in the gap, and the band each side of it.
            let mut x = from;
            while let Some(a) = next_where(&coarse[..to], x, true) {
                let b = next_where(&coarse[..to], a, false).unwrap_or(to);
                x = b;
                let (lo, hi) = (a.saturating_sub(band), (b + band).min(w));
                match near.last_mut() {
                    Some(last) if last.to >= lo => {
                        across.resize(across.len() + hi.saturating_sub(last.to), cap);
                        last.to = last.to.max(hi);
                    }
                    _ => {
                        near.push(Near { from: lo, to: hi, at: across.len() });
                        across.resize(across.len() + (hi - lo), cap);
                    }
                }
                let run = near[near.len() - 1];
                let (d, o) = (&mut across[run.at..], run.from);
                for (d, i) in d[lo - o..a - o].iter_mut().zip(lo..) {
                    *d = (*d).min(distance(a - i));
                }
                d[a - o..b - o].fill(0);
                for (d, i) in d[b - o..hi - o].iter_mut().zip(b..) {
                    *d = (*d).min(distance(i + 1 - b));
                }
            }
        }
        (near, across)
    }

    fn finish(
        mut self,
        h: usize,
        coarse_of: &CoarseOf<'_, S>,
        emit: &mut dyn FnMut(Vec<S>) -> Result<()>,
    ) -> Result<()> {
        while self.emitted < h.min(self.front + self.held.len()) {
            self.emit_next(coarse_of, emit)?;
        }
        Ok(())
    }

    /// Emits row `emitted`, then drops the rows no later row needs.
    fn emit_next(&mut self, coarse_of: &CoarseOf<'_, S>, emit: &mut dyn FnMut(Vec<S>) -> Result<()>) -> Result<()> {
        let y = self.emitted;
        let (band, w) = (self.band, self.width);
        let f = &self.held[y - self.front].fine;
        // Where this row has fine data to blend, the blend reaches it within the runs
        // near an edge of the rows held (every distance there is within the band), and
        // only there: elsewhere (most of a survey) nothing is done to the row.
        let cap = u32::try_from(band + 1).unwrap_or(u32::MAX);
        let mut reach: Vec<(usize, usize)> = Vec::new();
        if let (true, Some(first)) = (band > 0, f.iter().position(Pixel::has_data)) {
            let last = f.iter().rposition(Pixel::has_data).map_or(0, |l| l + 1);
            let mut runs: Vec<(usize, usize)> = (self.held.iter().flat_map(|held| &held.near))
                .map(|n| (n.from.max(first), n.to.min(last)))
                .filter(|(from, to)| from < to)
                .collect();
            runs.sort_unstable();
            for (from, to) in runs {
                match reach.last_mut() {
                    Some(last) if last.1 >= from => last.1 = last.1.max(to),
                    _ => reach.push((from, to)),
                }
            }
        }
        // Chessboard distance to the fine data's edge over the rows held: per row, the
        // larger of its distance along the row and its distance in rows; the least of
        // those (runs at once, which the compiler vectorizes). For each run of `reach`
        // in turn.
        let mut distance: Vec<u32> = Vec::new();
        for &(from, to) in &reach {
            let at = distance.len();
            distance.resize(at + (to - from), cap);
            let d = &mut distance[at..];
            for (j, held) in self.held.iter().enumerate() {
                let dy = u32::try_from((self.front + j).abs_diff(y)).unwrap_or(u32::MAX);
                for n in &held.near {
                    let (a, b) = (n.from.max(from), n.to.min(to));
                    if a >= b {
                        continue;
                    }
                    let across = &held.across[n.at + a - n.from..n.at + b - n.from];
                    for (d, &x) in d[a - from..b - from].iter_mut().zip(across) {
                        *d = (*d).min(x.max(dy));
                    }
                }
            }
        }
        let row = &mut self.held[y - self.front];
        // The fine data as it is (taken, not copied: no later row reads it), blended into
        // the coarser data where the blend reaches, and the coarser data where it has
        // none.
        let mut out = std::mem::take(&mut row.fine);
        if !reach.is_empty() && row.coarse.is_empty() {
            row.coarse = vec![S::NONE; w];
        }
        #[expect(clippy::cast_precision_loss, reason = "small counts")]
        let scale = 1.0 / (band as f32 + 1.0);
        let mut at = 0;
        for &(from, to) in &reach {
            coarse_of(y, &mut row.coarse, from..to);
            let runs = out[from..to].iter_mut().zip(&row.coarse[from..to]).zip(&distance[at..at + (to - from)]);
            for ((a, &b), &d) in runs {
                if a.has_data() && b.has_data() {
                    #[expect(clippy::cast_precision_loss, reason = "small counts")]
                    let t = d as f32 * scale;
                    *a = S::lerp(b, *a, t * t * (3.0 - 2.0 * t));
                }
            }
            at += to - from;
        }
        for &(from, to) in &row.gaps {
            out[from..to].copy_from_slice(&row.coarse[from..to]);
        }
        // The finer level's means, where it lies.
        apply_overrides(self.overrides, self.corner.0 as usize, self.corner.1 as usize + y, &mut out);
        emit(out)?;
        self.emitted += 1;
        while self.front + band < self.emitted && !self.held.is_empty() {
            self.held.pop_front();
            self.front += 1;
        }
        Ok(())
    }
}

#[cfg(test)]
#[allow(clippy::cast_possible_truncation, clippy::cast_precision_loss, reason = "small test grids")]
mod tests {
    use super::*;

    #[test]
    fn an_input_reaches_the_coarsest_level_no_coarser_than_its_spacing() {
        assert_eq!(depth_of(30.0, 30.0), 0);
        assert_eq!(depth_of(59.0, 30.0), 0, "under 2x: upsampled at LOD 0");
        assert_eq!(depth_of(60.0, 30.0), 1, "2x: LOD 1's own samples");
        assert_eq!(depth_of(60.0 - 1e-12, 30.0), 1, "within rounding of a level");
        assert_eq!(depth_of(1000.0, 200.0), 2, "a 1 km base over 200 m reaches 800 m");
        assert_eq!(depth_of(30.0, 1.0), 4, "30 over 1 reaches 16");
        assert_eq!(depth_of(f64::NAN, 1.0), 0);
    }

    fn laid_out(spacing: f64, columns: (i64, i64), rows: (i64, i64)) -> InputLayout {
        InputLayout { path: PathBuf::from(format!("{spacing}.tif")), spacing, columns, rows }
    }

    /// A 30" base under a 1" survey: the base at 16" (LOD 4 of 1") makes 3.5x its own
    /// samples; LOD 0 at 30"/32 puts it on LOD 5 at its own spacing.
    #[test]
    fn a_wide_base_puts_lod_0_where_its_spacing_is_a_level() {
        let (s, f) = (30.0 / 3600.0, 1.0 / 3600.0);
        let grid = GridSpec { origin: [-126.0, 45.0], pixel: (f, f), size: (93_600, 54_000) };
        let layout = [laid_out(s, (-1, 93_600), (-1, 54_000)), laid_out(f, (11_000, 13_400), (25_000, 27_400))];
        let aligned = aligned_grid(&layout, grid).expect("the base's spacing on a level");
        let c = aligned.pixel.1 / f;
        assert!((c - 30.0 / 32.0).abs() < 1e-12, "{c}");
        assert_eq!(aligned.origin, grid.origin);
        assert_eq!(aligned.size, (99_840, 57_600));
        assert_eq!(depth_of(s, aligned.pixel.1), 5);
        assert!((s / (aligned.pixel.1 * 32.0) - 1.0).abs() < 1e-12);
        // Over a small base the survey's samples count most: its spacing is kept.
        let small = [laid_out(s, (-1, 3_600), (-1, 3_600)), laid_out(f, (600, 3_000), (600, 3_000))];
        assert_eq!(aligned_grid(&small, GridSpec { size: (3_600, 3_600), ..grid }), None);
        // A base whose spacing is a level's already, or within 2x of the finest: kept.
        let even = [laid_out(32.0 * f, (-1, 93_600), (-1, 54_000)), layout[1].clone()];
        assert_eq!(aligned_grid(&even, grid), None);
        let near = [laid_out(1.5 * f, (-1, 93_600), (-1, 54_000)), layout[1].clone()];
        assert_eq!(aligned_grid(&near, grid), None);
    }

    #[test]
    fn rectangles_that_touch_merge_and_others_stay_apart() {
        let m = merged(vec![[0, 0, 2, 2], [3, 0, 4, 1], [10, 10, 11, 11]], true);
        assert_eq!(merged(vec![[0, 0, 2, 2], [3, 0, 4, 1]], false), vec![[0, 0, 2, 2], [3, 0, 4, 1]]);
        assert_eq!(merged(vec![[0, 0, 2, 2], [3, 0, 4, 1], [2, 1, 5, 5]], false), vec![[0, 0, 5, 5]]);
        assert_eq!(m, vec![[0, 0, 4, 2], [10, 10, 11, 11]]);
    }

    /// The sweep gives what joining any two overlapping rectangles until none overlaps
    /// gives (the pairwise merge it replaced), on scattered and chained rectangles.
    #[test]
    fn the_sweep_merges_as_pairwise_joining_does() {
        fn pairwise(mut rects: Vec<[u32; 4]>, touching: bool) -> Vec<[u32; 4]> {
            let gap = u32::from(touching);
            let touch = |a: &[u32; 4], b: &[u32; 4]| {
                a[0] <= b[2] + gap && b[0] <= a[2] + gap && a[1] <= b[3] + gap && b[1] <= a[3] + gap
            };
            loop {
                let mut changed = false;
                let mut out: Vec<[u32; 4]> = Vec::new();
                for r in rects {
                    if let Some(o) = out.iter_mut().find(|o| touch(o, &r)) {
                        *o = [o[0].min(r[0]), o[1].min(r[1]), o[2].max(r[2]), o[3].max(r[3])];
                        changed = true;
                    } else {
                        out.push(r);
                    }
                }
                rects = out;
                if !changed {
                    return rects;
                }
            }
        }
        // A small generator of its own (deterministic): rectangles of 1 to 6 a side over
        // 200 x 200, few enough to leave many apart.
        let mut state = 0x9e37_79b9_7f4a_7c15_u64;
        let mut next = |n: u64| {
            state ^= state << 13;
            state ^= state >> 7;
            state ^= state << 17;
            u32::try_from(state % n).unwrap()
        };
        for count in [0, 1, 5, 50, 400, 1500] {
            let rects: Vec<[u32; 4]> = (0..count)
                .map(|_| {
                    let (x, y) = (next(200), next(200));
                    [x, y, x + next(6), y + next(6)]
                })
                .collect();
            for touching in [false, true] {
                assert_eq!(merged(rects.clone(), touching), pairwise(rects.clone(), touching), "{count} {touching}");
            }
        }
        // A chain whose boxes join only once joined: an L whose arms meet through a third.
        let chain = vec![[0, 0, 1, 10], [20, 0, 21, 1], [5, 5, 25, 6], [2, 9, 4, 9]];
        assert_eq!(merged(chain.clone(), false), pairwise(chain, false));
    }

    /// The rows a [`Blender`] makes of `fine` and `coarse` (as many rows each) across
    /// `band` samples.
    fn blended(fine: &[Vec<f32>], coarse: &[Vec<f32>], band: usize) -> Vec<Vec<f32>> {
        let mut ring = Blender::new(fine[0].len(), band, (0, 0), &[]);
        let mut rows = vec![];
        let mut emit = |r: Vec<f32>| {
            rows.push(r);
            Ok(())
        };
        let coarse_of = |y: usize, row: &mut [f32], columns: std::ops::Range<usize>| {
            row[columns.clone()].copy_from_slice(&coarse[y][columns]);
        };
        for f in fine {
            ring.push(f.clone(), &coarse_of, &mut emit).unwrap();
        }
        ring.finish(fine.len(), &coarse_of, &mut emit).unwrap();
        rows
    }

    /// A fine square 3 m above a coarse ramp, blended over 4 samples: no step between
    /// neighbours above the ramp's own plus a share of the offset, where without a band
    /// the offset shows whole.
    #[test]
    #[expect(clippy::needless_range_loop, reason = "a small test grid")]
    fn a_finer_input_blends_into_the_coarser_across_its_edge() {
        let (w, h) = (40usize, 40usize);
        let coarse: Vec<Vec<f32>> = (0..h).map(|_| (0..w).map(|x| x as f32 * 0.1).collect()).collect();
        let fine: Vec<Vec<f32>> =
            (0..h)
                .map(|y| {
                    (0..w)
                        .map(|x| {
                            if (10..30).contains(&x) && (10..30).contains(&y) { x as f32 * 0.1 + 3.0 } else { f32::NAN }
                        })
                        .collect()
                })
                .collect();
        let run = |band: u32| blended(&fine, &coarse, band as usize);
        let worst = |rows: &[Vec<f32>]| {
            let mut worst = 0f32;
            for y in 0..h {
                for x in 1..w {
                    worst = worst.max((rows[y][x] - rows[y][x - 1]).abs());
                    worst = worst.max((rows[x][y] - rows[x - 1][y]).abs());
                }
            }
            worst
        };
        let (blended, stepped) = (run(4), run(0));
        assert_eq!(blended.len(), h);
        assert!(worst(&stepped) >= 3.0, "no band: the 3 m offset is a step");
        assert!(worst(&blended) < 1.2, "band of 4: largest step {}", worst(&blended));
        // The middle is the fine input's own, the outside the coarse's.
        assert_eq!(blended[20][20], 20.0 * 0.1 + 3.0);
        assert_eq!(blended[5][5], 0.5);
    }

    /// A deterministic pattern: fine data in blocks with holes, coarse data nearly
    /// everywhere.
    fn pattern(w: usize, h: usize) -> (Vec<Vec<f32>>, Vec<Vec<f32>>) {
        let hash = |x: usize, y: usize| (x.wrapping_mul(73_856_093) ^ y.wrapping_mul(19_349_663)) % 97;
        let fine = (0..h)
            .map(|y| {
                (0..w)
                    .map(|x| {
                        let inside = (5..w - 7).contains(&x) && (4..h - 6).contains(&y) && hash(x, y) > 6;
                        if inside { (x * 3 + y) as f32 * 0.25 + 3.0 } else { f32::NAN }
                    })
                    .collect()
            })
            .collect();
        let coarse = (0..h)
            .map(|y| (0..w).map(|x| if hash(y, x) == 0 { f32::NAN } else { (x + y) as f32 * 0.5 }).collect())
            .collect();
        (fine, coarse)
    }

    #[test]
    fn the_blend_is_the_chessboard_distance_to_the_nearest_edge() {
        let (w, h, band) = (47usize, 39usize, 3usize);
        let (fine, coarse) = pattern(w, h);
        let rows = blended(&fine, &coarse, band);
        // By brute force: every sample's distance to every edge sample (no fine data where
        // the coarse has some).
        let edges: Vec<(usize, usize)> = (0..h)
            .flat_map(|y| (0..w).map(move |x| (x, y)))
            .filter(|&(x, y)| fine[y][x].is_nan() && !coarse[y][x].is_nan())
            .collect();
        let cap = band as u32 + 1;
        let scale = 1.0 / (band as f32 + 1.0);
        for y in 0..h {
            for x in 0..w {
                let (a, b) = (fine[y][x], coarse[y][x]);
                let d = edges
                    .iter()
                    .map(|&(ex, ey)| x.abs_diff(ex).max(y.abs_diff(ey)) as u32)
                    .min()
                    .unwrap_or(cap)
                    .min(cap);
                let expected = if a.is_nan() {
                    b
                } else if b.is_nan() || d >= cap {
                    a
                } else {
                    let t = d as f32 * scale;
                    f32::lerp(b, a, t * t * (3.0 - 2.0 * t))
                };
                let got = rows[y][x];
                assert!(got == expected || (got.is_nan() && expected.is_nan()), "({x}, {y}): {got} against {expected}");
            }
        }
    }

    /// A level without fine data made tile by tile is what its rows across the live
    /// part make: every held tile's samples (borders, the live part's edges, rounding),
    /// and the means the next level takes.
    #[test]
    fn tiles_made_on_their_own_are_the_rows_made_across_the_rectangle() {
        let (res, border) = (8u32, 1u32);
        let rect = [2u32, 1, 6, 4];
        let held = [(3u32, 1u32), (4, 1), (2, 2), (3, 2), (5, 2), (6, 3), (4, 4), (6, 4)];
        let level = SparseLevel { lod: 1, tiles: held.iter().copied().collect(), rects: vec![rect], cover: vec![] };
        // The live part: from the rectangle's corner, short of its last column and row.
        let (corner, size) = ((16u32, 8u32), (38u32, 30u32));
        let grid = GridSpec { origin: [0.0, 0.0], pixel: (1.0, 1.0), size };
        let (_, coarse_rows) = pattern(30, 40);
        let overrides = [Override {
            x0: 20,
            y0: 12,
            rows: (0..14)
                .map(|y| (0..20).map(|x| if (x + 2 * y) % 7 == 0 { f32::NAN } else { 40.0 + x as f32 * 0.3 }).collect())
                .collect(),
        }];
        let finer: Vec<&Override<f32>> = overrides.iter().collect();
        let round =
            |row: &mut [f32]| row.iter_mut().filter(|v| !v.is_nan()).for_each(|v| *v = (*v * 4.0).round() / 4.0);
        let coarse = || Coarse {
            source: Box::new(Rows(coarse_rows.clone(), std::sync::atomic::AtomicUsize::new(0))),
            shift: 1,
            quantize: None,
            first: (6, 2),
        };

        // The rows across the live part, rounded, and their means.
        let mut rows: Vec<Vec<f32>> = vec![];
        level_rows::<Heights>(None, Some(&coarse()), &grid, corner, 0..size.1, &finer, 0, &mut |r| {
            rows.push(r);
            Ok(())
        })
        .unwrap();
        rows.iter_mut().for_each(|r| round(r));
        let none = vec![f32::NAN; size.0 as usize];
        let mut means = Override {
            x0: 8,
            y0: 4,
            rows: rows
                .chunks(2)
                .map(|pair| {
                    let mut m = halve_rows(&pair[0], pair.get(1).unwrap_or(&none));
                    round(&mut m);
                    m
                })
                .collect(),
        };
        means.keep_held(&level, res);

        let cut = std::sync::Mutex::new(std::collections::BTreeMap::new());
        let encode = |x: u32, y: u32, samples: &[f32], edge: usize| {
            assert_eq!(edge, 10);
            cut.lock().unwrap().insert((x, y), samples.to_vec());
            Ok(vec![(TileKey::new(0, 1, x, y)?, vec![1u8])])
        };
        let mut added = vec![];
        let at = Beneath { level: &level, rect, res, border, corner, size };
        let progress = terrastream_pack::progress::Silent::default();
        let made = tiles_beneath(
            &at,
            Some(&coarse()),
            &finer,
            Some(&round),
            &encode,
            &mut |key, _| {
                added.push(key);
                Ok(())
            },
            &progress,
        )
        .unwrap();

        let cut = cut.into_inner().unwrap();
        let same = |a: f32, b: f32| a.to_bits() == b.to_bits() || (a.is_nan() && b.is_nan());
        for &(tx, ty) in &held {
            let samples = &cut[&(tx, ty)];
            for j in 0..10i64 {
                for i in 0..10i64 {
                    let (gx, gy) = (i64::from(tx * res) + i - 1, i64::from(ty * res) + j - 1);
                    let (lx, ly) = (gx - i64::from(corner.0), gy - i64::from(corner.1));
                    let inside = (0..i64::from(size.0)).contains(&lx) && (0..i64::from(size.1)).contains(&ly);
                    let expected = if inside { rows[ly as usize][lx as usize] } else { f32::NAN };
                    let got = samples[(j * 10 + i) as usize];
                    assert!(same(got, expected), "tile ({tx}, {ty}) sample ({i}, {j}): {got} against {expected}");
                }
            }
        }
        assert_eq!(cut.len(), held.len(), "only the held tiles");
        assert_eq!(added.len(), held.len());
        assert!(cut.values().flatten().any(|&v| (40.0..47.0).contains(&v)), "the finer means are in");
        assert_eq!((made.x0, made.y0, made.rows.len()), (means.x0, means.y0, means.rows.len()));
        for (y, (a, b)) in made.rows.iter().zip(&means.rows).enumerate() {
            assert_eq!(a.len(), b.len());
            assert!(a.iter().zip(b).all(|(&p, &q)| same(p, q)), "means row {y}: {a:?} against {b:?}");
        }
    }

    /// Coarse rows from memory, counting the rows read.
    struct Rows(Vec<Vec<f32>>, std::sync::atomic::AtomicUsize);

    impl CoarseRows<f32> for Rows {
        fn size(&self) -> (u32, u32) {
            (self.0[0].len() as u32, self.0.len() as u32)
        }

        fn rows(&self, rows: std::ops::Range<u32>, each: &mut dyn FnMut(Vec<f32>) -> Result<()>) -> Result<()> {
            for r in rows {
                self.1.fetch_add(1, std::sync::atomic::Ordering::Relaxed);
                each(self.0[r as usize].clone())?;
            }
            Ok(())
        }
    }

    /// A receiver that stops pulling before the last row (it has all it needs) does not
    /// make the reader fail: a run whose tiles are all made failed now and then, when the
    /// reader had not yet sent its last rows as the receiver was dropped.
    #[test]
    fn the_coarse_rows_stop_without_error_once_nobody_pulls_them() {
        let rows: Vec<Vec<f32>> = (0..10).map(|y| vec![y as f32; 4]).collect();
        let coarse = Coarse {
            source: Box::new(Rows(rows, std::sync::atomic::AtomicUsize::new(0))),
            shift: 1,
            quantize: None,
            first: (0, 0),
        };
        // Room for one row: the reader blocks on the second until the receiver goes.
        let (send, receive) = std::sync::mpsc::sync_channel::<Vec<f32>>(1);
        let read = std::thread::scope(|scope| {
            let reader = scope.spawn(|| coarse.send_rows(0..10, &send));
            assert_eq!(receive.recv().unwrap(), vec![0.0; 4]);
            drop(receive);
            reader.join().unwrap()
        });
        assert!(read.is_ok(), "{read:?}");
    }

    /// Coarse rows that fail after `0.1` of them, as a file that cannot be read further.
    struct Failing(Rows, u32);

    impl CoarseRows<f32> for Failing {
        fn size(&self) -> (u32, u32) {
            self.0.size()
        }

        fn rows(&self, rows: std::ops::Range<u32>, each: &mut dyn FnMut(Vec<f32>) -> Result<()>) -> Result<()> {
            let ok = rows.start..rows.end.min(self.1);
            self.0.rows(ok, each)?;
            Err(Error::input("base.tif", "strip 3 cannot be read"))
        }
    }

    /// A coarse reader's own failure is what a level's run reports, not the "interrupted"
    /// its maker sees when the rows stop coming.
    #[test]
    fn a_failing_coarse_reader_names_its_own_error() {
        let (w, h) = (40u32, 60u32);
        let (_, coarse_rows) = pattern(20, 40);
        let grid = GridSpec { origin: [0.0, 0.0], pixel: (1.0, 1.0), size: (w, h) };
        let source = Failing(Rows(coarse_rows, std::sync::atomic::AtomicUsize::new(0)), 5);
        let coarse = Coarse { source: Box::new(source), shift: 1, quantize: None, first: (0, 0) };
        let mut emit = |_: Vec<f32>| Ok(());
        let made = level_rows::<Heights>(None, Some(&coarse), &grid, (0, 0), 0..h, &[], 0, &mut emit);
        let error = made.expect_err("the rows cannot all be made");
        assert!(!error.is_interrupted(), "{error}");
        assert!(error.to_string().contains("strip 3 cannot be read"), "{error}");
    }

    #[test]
    fn rows_made_in_bands_are_the_rows_made_in_one_run() {
        // A level 700 rows high (six bands) over coarse data two levels coarser, with a
        // finer level's means over part of it.
        let (w, h) = (90u32, 700u32);
        let (_, coarse_rows) = pattern(30, 180);
        let grid = GridSpec { origin: [0.0, 0.0], pixel: (1.0, 1.0), size: (w, h) };
        let corner = (8, 12);
        let overrides = [Override {
            x0: 20,
            y0: 200,
            rows: (0..300)
                .map(|y| (0..40).map(|x| if (x + y) % 11 == 0 { f32::NAN } else { 7.0 + x as f32 }).collect())
                .collect(),
        }];
        let finer: Vec<&Override<f32>> = overrides.iter().collect();
        let make = |threads: Option<usize>| {
            let source = Rows(coarse_rows.clone(), std::sync::atomic::AtomicUsize::new(0));
            let coarse = Coarse { source: Box::new(source), shift: 2, quantize: None, first: (1, 2) };
            let (mut rows, mut halves) = (vec![], vec![]);
            if let Some(threads) = threads {
                let finish = RowFinish { quantize: None };
                let mut emit = |(r, half): Finished<f32>| {
                    rows.push(r);
                    halves.extend(half);
                    Ok(())
                };
                level_rows_in_bands::<Heights>(
                    None,
                    Some(&coarse),
                    &grid,
                    corner,
                    &finer,
                    0,
                    &finish,
                    threads,
                    &mut emit,
                )
                .unwrap();
            } else {
                let mut emit = |r: Vec<f32>| {
                    rows.push(r);
                    Ok(())
                };
                level_rows::<Heights>(None, Some(&coarse), &grid, corner, 0..h, &finer, 0, &mut emit).unwrap();
            }
            (rows, halves)
        };
        let (one, _) = make(None);
        assert_eq!(one.len(), h as usize);
        let same =
            |a: &[f32], b: &[f32]| a.len() == b.len() && a.iter().zip(b).all(|(p, q)| p.to_bits() == q.to_bits());
        // In bands (on as many workers as from BANDS_FROM cores), and streamed: the same
        // rows, and the same means of each pair.
        let (banded, banded_halves) = make(Some(BANDS_FROM));
        let (streamed, streamed_halves) = make(Some(1));
        for made in [&banded, &streamed] {
            assert_eq!(made.len(), one.len());
            for (y, (a, b)) in one.iter().zip(made).enumerate() {
                assert!(same(a, b), "row {y} differs");
            }
        }
        assert_eq!(banded_halves.len(), (h as usize).div_ceil(2));
        assert!(banded_halves.iter().zip(&streamed_halves).all(|(a, b)| same(a, b)));
        assert_eq!(banded_halves.len(), streamed_halves.len());
        assert!(one.iter().flatten().any(|v| *v == 7.0 + 5.0), "the overrides are in");
    }
}
