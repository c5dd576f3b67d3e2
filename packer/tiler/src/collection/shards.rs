//! A collection's run in shards: the bands each shard holds (balanced by work), the inputs
//! each reads, and the plan that lets a shard given only those make the tiles a shard
//! given every input makes (`tile --shards N --shard-plan-out`, then `--shard-plan`).

use std::path::{Path, PathBuf};

use terrastream_format::{LayerKind, Metadata, Shard};

use super::{Collection, CollectionInput, Collections, ShardPart, sparse_levels};
use crate::error::{Error, Result};
use crate::options::{ShardSpec, TextureInput};
use crate::plan::Plan;
use crate::pyramid::Window;
use crate::raster::{ElevationSource, GridSpec};
use crate::shard::{ShardInputs, ShardPlan};

/// What a shard plan records of a collection: enough for a shard given only some of the
/// inputs to make the levels a run given all of them makes (the depths come from every
/// input's spacing, the base from the coarsest: a shard's own inputs would say otherwise).
#[derive(Clone, Debug, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct PlannedCollection {
    /// The layer it makes (`elevation` or `texture`).
    pub kind: LayerKind,
    /// From this level up every level covers the grid.
    pub base: u8,
    /// Blend band, samples of each finer input's level.
    pub blend: u32,
    /// Every input, in the order given, with its spacing, depth and footprint.
    pub inputs: Vec<CollectionInput>,
}

impl Collection {
    /// What a shard plan records of it.
    #[must_use]
    pub fn planned(&self) -> PlannedCollection {
        PlannedCollection { kind: self.kind, base: self.base, blend: self.blend, inputs: self.inputs.clone() }
    }

    /// The collection `planned` records, on `metadata`'s layer of its kind and the
    /// mosaic's LOD-0 `grid` (the plan's), each input named as the one of `given` (this
    /// shard's inputs of that kind) whose path ends with the recorded one (a plan's paths
    /// may be relative to a root); inputs not given keep the recorded path (a shard's rows
    /// do not read them).
    ///
    /// # Errors
    /// [`Error::InvalidOption`] when `metadata` has no layer of the collection's kind;
    /// [`Error::Input`] for an input given that the plan does not record (its depth and
    /// footprint are unknown to the other shards).
    pub fn from_planned(
        planned: &PlannedCollection,
        metadata: &Metadata,
        grid: GridSpec,
        given: &[PathBuf],
    ) -> Result<Self> {
        let layer = metadata.layers.iter().find(|l| l.kind == planned.kind).ok_or_else(|| {
            Error::option("--shard-plan", format!("a collection of {:?}", planned.kind), "a plan of these inputs")
        })?;
        if let Some(stray) = given.iter().find(|g| !planned.inputs.iter().any(|i| g.ends_with(&i.path))) {
            return Err(Error::input(stray, "not among the inputs the shard plan records: plan the run with it"));
        }
        let named = |p: &Path| given.iter().find(|g| g.ends_with(p)).cloned().unwrap_or_else(|| p.to_path_buf());
        let inputs: Vec<CollectionInput> =
            (planned.inputs.iter()).map(|i| CollectionInput { path: named(&i.path), ..i.clone() }).collect();
        let levels = sparse_levels(&inputs, layer, planned.base);
        Ok(Self { inputs, base: planned.base, levels, grid, blend: planned.blend, kind: planned.kind })
    }

    /// The inputs shard `part` of this collection reads, each once, in order: those of
    /// its levels' rectangles (the fine inputs and the coarser ones beneath) and those of
    /// its band of the base.
    pub(crate) fn inputs_of(&self, res: u32, num_lods: u8, part: &ShardPart) -> Vec<PathBuf> {
        let mut read: std::collections::HashSet<PathBuf> = std::collections::HashSet::new();
        for (l, rects) in self.levels.iter().zip(super::needed_rects(self, res, part)) {
            for rect in rects {
                // The part of it that is made, as the shard makes it.
                let Some((corner, grid)) = self.live_grid(l, rect, res) else { continue };
                let (fine, below, _) = self.level_inputs(l.lod, corner, &grid);
                read.extend(fine.into_iter().chain(below));
            }
        }
        if part.split >= self.base {
            read.extend(self.base_inputs(&self.base_window(Some(part), num_lods)));
        }
        self.inputs.iter().map(|i| &i.path).filter(|p| read.contains(*p)).cloned().collect()
    }
}

/// Shard `spec` of `collections`' run on `planned`: its split LOD ([`split_lod`]), its
/// record, every layer's window, and every layer's bands.
pub(crate) fn windows(
    collections: Collections<'_>,
    planned: &Plan,
    mut spec: ShardSpec,
    elevation: Option<&dyn ElevationSource>,
    texture: Option<&TextureInput<'_>>,
) -> Result<(Shard, Vec<Window>, Vec<Vec<u32>>)> {
    let split = split_lod(collections, planned, &spec);
    spec.split_lod = Some(split);
    // Bands are whole rows of the split level's tiles (said once: where the bands are
    // cut, not where a plan gives them).
    if let Some(layer) = planned.metadata.layers.first() {
        let rows = layer.num_y_tiles.div_ceil(1 << split.min(layer.num_lods.saturating_sub(1)));
        if rows < spec.count && spec.cuts.is_none() {
            tracing::warn!(
                "{} shards of a collection split at LOD {split}: its {rows} rows of tiles leave {} shards nothing to \
                 make (a finer `--split-lod` cuts more bands; docs/tiling.md, \"Shards\")",
                spec.count,
                spec.count - rows
            );
        }
    }
    if spec.cuts.is_none()
        && let Some(base) = bases(collections).filter(|&b| split < b)
    {
        tracing::info!(
            "shards split at LOD {split}, finer than the collection's base (LOD {base}): `terrastream merge` of them \
             makes the levels from LOD {} up from their tiles and the inputs as deep (give it those with \
             `--elevation`/`--texture`)",
            split + 1
        );
    }
    let samples = crate::shard::data_weight(planned, elevation, texture);
    // Balanced by work: each input's samples at the level it reaches (a survey 2^d times
    // finer than its level counts 4^d times its area's share).
    let kinds: Vec<LayerKind> = planned.metadata.layers.iter().map(|l| l.kind).collect();
    let of = |kind: LayerKind| [collections.heights, collections.imagery].into_iter().flatten().find(|c| c.makes(kind));
    let weight = |index: usize, rows: std::ops::Range<u32>| match kinds.get(index).and_then(|&k| of(k)) {
        Some(c) => c.work(rows, split),
        None => samples(index, rows),
    };
    crate::shard::windows_and_cuts(planned, &spec, &weight)
}

/// The collections' coarsest base.
fn bases(collections: Collections<'_>) -> Option<u8> {
    [collections.heights, collections.imagery].into_iter().flatten().map(|c| c.base).max()
}

/// The most work a shard may get, against the mean, before the default split goes finer
/// than the base.
const MOST_AGAINST_MEAN: f64 = 1.25;

/// The split LOD of shard `spec` of `collections`' run: the one asked for; by default the
/// run's default raised to the collections' bases, where the merge needs only the shards
/// (the levels above are every tile's children's means), unless the base's rows of tiles
/// cannot share the work out: fewer rows than shards, or bands of them of which one gets
/// more than [`MOST_AGAINST_MEAN`] times the mean (a survey within a row or two of the
/// base). Then the default itself, finer, and the merge makes the levels up to the base
/// from the inputs as deep. Tiles of an odd number of samples keep the bases (a mean there
/// spans two tiles, which a merge does not read together).
fn split_lod(collections: Collections<'_>, planned: &Plan, spec: &ShardSpec) -> u8 {
    let least = bases(collections).unwrap_or(0);
    let odd = planned.metadata.layers.iter().any(|l| l.tile_resolution % 2 == 1);
    let default = crate::shard::default_split(planned, spec.count);
    match spec.split_lod {
        Some(k) if !odd => k,
        Some(k) => k.max(least),
        None if default < least && !odd && !shares_out(collections, planned, least, spec.count) => default,
        None => default.max(least),
    }
}

/// Whether `count` bands of whole rows of level `k`'s tiles share the collections' work
/// out: as many rows as shards at least, and no band given more than
/// [`MOST_AGAINST_MEAN`] times the mean work.
fn shares_out(collections: Collections<'_>, planned: &Plan, k: u8, count: u32) -> bool {
    let Some(layer) = planned.metadata.layers.first() else { return true };
    let rows = layer.num_y_tiles.div_ceil(1 << k.min(layer.num_lods.saturating_sub(1)));
    if rows < count {
        return false;
    }
    let res = layer.tile_resolution;
    let height = planned.layers.first().map_or(u32::MAX, |p| p.size.1);
    let lod0 = |r: u32| (r << k).min(layer.num_y_tiles).saturating_mul(res).min(height);
    let all = [collections.heights, collections.imagery];
    let work = |from: u32, to: u32| all.iter().flatten().map(|c| c.work(lod0(from)..lod0(to), k)).sum::<f64>();
    let cuts = crate::shard::balanced_cuts(rows, count, |r| work(r, r + 1));
    let bands: Vec<f64> = cuts.windows(2).map(|w| work(w[0], w[1])).collect();
    let mean = bands.iter().sum::<f64>() / f64::from(count.max(1));
    mean <= 0.0 || bands.iter().all(|&b| b <= MOST_AGAINST_MEAN * mean)
}

/// Collection `c`'s part of a shard (None for a whole run): its layer's band and window.
pub(crate) fn part(c: &Collection, metadata: &Metadata, windows: &[Window]) -> Option<ShardPart> {
    let info = metadata.shard.as_ref()?;
    let index = metadata.layers.iter().position(|l| l.kind == c.kind)?;
    Some(ShardPart { split: info.split_lods[index], tile_rows: info.tile_rows[index], window: windows[index].clone() })
}

/// The plan of `count` shards of `collections`' run on `plan` (made from the inputs'
/// headers): the grids, every layer's bands (balanced by work, the split LOD no finer than
/// the bases), the collections (every input's depth), and each shard's inputs: those its
/// levels' rectangles and its band of the base read (a layer of one resolution: those its
/// rows read, as [`crate::shard_plan`] lists them).
///
/// # Errors
/// [`Error::InvalidOption`] for no shard, or a lossy texture format (shards are merged
/// from their decoded tiles).
pub fn collection_shard_plan(
    collections: Collections<'_>,
    plan: &Plan,
    elevation: Option<&dyn ElevationSource>,
    texture: Option<&TextureInput<'_>>,
    count: u32,
    split_lod: Option<u8>,
) -> Result<ShardPlan> {
    if let Some(t) = texture.filter(|t| !t.format.lossless()) {
        return Err(Error::option("--texture-format", t.format.name(), "png or webp with --shard"));
    }
    let first = ShardSpec { index: 0, count, split_lod, cuts: None };
    let k = self::split_lod(collections, plan, &first);
    let split = Some(k);
    let (_, _, cuts) = windows(collections, plan, first, elevation, texture)?;
    let mut shards = Vec::with_capacity(count as usize);
    for index in 0..count {
        let spec = ShardSpec { index, count, split_lod: split, cuts: Some(cuts.clone()) };
        let (info, bands, _) = windows(collections, plan, spec, elevation, texture)?;
        let mut metadata = plan.metadata.clone();
        metadata.shard = Some(info);
        let mut inputs = ShardInputs::default();
        for (layer, window) in plan.metadata.layers.iter().zip(&bands) {
            let kind = layer.kind;
            if !matches!(kind, LayerKind::Elevation | LayerKind::Texture) {
                continue;
            }
            // The inputs of the layer's source in rows of its grid.
            let in_rows = |rows: std::ops::Range<u32>| match kind {
                LayerKind::Texture => texture.map_or_else(Vec::new, |t| t.source.inputs_in_rows(rows)),
                _ => elevation.map_or_else(Vec::new, |e| e.inputs_in_rows(rows)),
            };
            let collection = [collections.heights, collections.imagery].into_iter().flatten().find(|c| c.kind == kind);
            let list = match collection {
                Some(c) => part(c, &metadata, &bands)
                    .map_or_else(Vec::new, |p| c.inputs_of(layer.tile_resolution, layer.num_lods, &p)),
                None => in_rows(to_u32(window.rows.start)..to_u32(window.rows.end)),
            };
            // A shard that reads nothing still opens its sources on the planned grid: its
            // list holds the first input.
            let list = if list.is_empty() { in_rows(0..u32::MAX).into_iter().take(1).collect() } else { list };
            match kind {
                LayerKind::Texture => inputs.texture = list,
                _ => inputs.elevation = list,
            }
        }
        shards.push(inputs);
    }
    let all = [collections.heights, collections.imagery].into_iter().flatten();
    let planned = all.clone().map(Collection::planned).collect();
    // Split finer than a base: the merge reads the inputs deeper than the split.
    let merge = all.flat_map(|c| c.inputs.iter().filter(|i| i.depth > k && k < c.base).map(|i| i.path.clone()));
    let merge = merge.fold(Vec::new(), |mut list: Vec<PathBuf>, p| {
        if !list.contains(&p) {
            list.push(p);
        }
        list
    });
    Ok(ShardPlan {
        collections: planned,
        merge,
        ..ShardPlan::of_sources(count, split, elevation, texture, cuts, shards)
    })
}

fn to_u32(n: usize) -> u32 {
    u32::try_from(n).unwrap_or(u32::MAX)
}
