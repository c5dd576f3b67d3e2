//! Sharded tile runs: which band of each layer's grid a shard makes.
//!
//! A shard holds, for every layer, the tiles of a band of tile rows from LOD 0 up to the
//! layer's split LOD K. Bands are whole rows of LOD-K tiles, so every tile up to K lies in
//! exactly one shard with all the tiles under it; rows of the raster are read with a margin
//! of `border * 2^K` above and below, so a shard's tiles, borders included, are the bytes a
//! whole run makes. The levels above K are made when the shards are merged, from their
//! LOD-K tiles ([`crate::edit::merge`]).

use std::path::PathBuf;

use terrastream_format::{LayerKind, Shard};

use crate::error::{Error, Result};
use crate::options::{ShardSpec, TextureInput, TileOptions};
use crate::plan::{Plan, plan_layout};
use crate::pyramid::Window;
use crate::raster::{ElevationSource, GridSpec};

/// Samples with data in a layer's LOD-0 rows (see `ElevationSource::data_in_rows`).
pub(crate) type Weight<'a> = dyn Fn(usize, std::ops::Range<u32>) -> f64 + 'a;

/// The [`Weight`] of `plan`'s layers: the samples with data their source knows of.
pub(crate) fn data_weight<'a>(
    plan: &Plan,
    elevation: Option<&'a dyn ElevationSource>,
    texture: Option<&'a TextureInput<'a>>,
) -> impl Fn(usize, std::ops::Range<u32>) -> f64 + 'a {
    let kinds: Vec<LayerKind> = plan.metadata.layers.iter().map(|l| l.kind).collect();
    move |layer, rows| match kinds[layer] {
        LayerKind::Texture => texture.map_or(0.0, |t| t.source.data_in_rows(rows)),
        _ => elevation.map_or(0.0, |e| e.data_in_rows(rows)),
    }
}

/// The shard's metadata record and each layer's window (in layer order). Bands are cut so
/// that each shard gets about as many samples with data (`weight(layer, rows)`) as the
/// others: sparse regions cost little, so their bands are taller.
///
/// # Errors
/// [`Error::InvalidOption`] for a shard out of range.
pub(crate) fn windows(plan: &Plan, spec: &ShardSpec, weight: &Weight<'_>) -> Result<(Shard, Vec<Window>)> {
    windows_and_cuts(plan, spec, weight).map(|(shard, windows, _)| (shard, windows))
}

/// The split LOD a run of `count` shards takes by default: the coarsest with at least two
/// rows of tiles a shard, of the first layer.
pub(crate) fn default_split(plan: &Plan, count: u32) -> u8 {
    let Some(layer) = plan.metadata.layers.first() else { return 0 };
    let last = layer.num_lods.saturating_sub(1);
    let rows_at = |k: u8| layer.num_y_tiles.div_ceil(1 << k);
    (0..=last).rev().find(|&k| rows_at(k) >= 2 * count).unwrap_or(0)
}

/// [`windows`], and every layer's band boundaries (`count + 1` tile rows at its split LOD).
pub(crate) fn windows_and_cuts(
    plan: &Plan,
    spec: &ShardSpec,
    weight: &Weight<'_>,
) -> Result<(Shard, Vec<Window>, Vec<Vec<u32>>)> {
    if spec.count == 0 || spec.index >= spec.count {
        return Err(Error::option("--shard", format!("{}/{}", spec.index, spec.count), "I/N with 0 <= I < N"));
    }
    let layers = &plan.metadata.layers;
    let mut split_lods = Vec::with_capacity(layers.len());
    let mut tile_rows = Vec::with_capacity(layers.len());
    let mut windows = Vec::with_capacity(layers.len());
    let mut all_cuts = Vec::with_capacity(layers.len());
    for (index, (layer, lp)) in layers.iter().zip(&plan.layers).enumerate() {
        let last = layer.num_lods.saturating_sub(1);
        let rows_at = |k: u8| layer.num_y_tiles.div_ceil(1 << k);
        let k = match spec.split_lod {
            Some(k) => k.min(last),
            None => (0..=last).rev().find(|&k| rows_at(k) >= 2 * spec.count).unwrap_or(0),
        };
        let rows_k = rows_at(k);
        let lod0 = |r: u32| (r << k).min(layer.num_y_tiles);
        let height = lp.size.1;
        let sample_rows = |r: u32| lod0(r).saturating_mul(layer.tile_resolution).min(height);
        let cuts = match &spec.cuts {
            Some(given) => {
                let cuts = given.get(index).cloned().unwrap_or_default();
                let valid = cuts.len() == spec.count as usize + 1
                    && cuts.first() == Some(&0)
                    && cuts.last() == Some(&rows_k)
                    && cuts.windows(2).all(|w| w[0] <= w[1]);
                if !valid {
                    return Err(Error::option(
                        "--shard-plan",
                        format!("layer {}: bands {cuts:?}", layer.name),
                        "the plan of these inputs and options: N + 1 rising tile rows from 0 to the split LOD's",
                    ));
                }
                cuts
            }
            None => balanced_cuts(rows_k, spec.count, |r| weight(index, sample_rows(r)..sample_rows(r + 1))),
        };
        all_cuts.push(cuts.clone());
        let (r0, r1) = (cuts[spec.index as usize], cuts[spec.index as usize + 1]);
        tile_rows.push([lod0(r0), lod0(r1)]);
        split_lods.push(k);
        let height = height as usize;
        let res = layer.tile_resolution as usize;
        let to_rows = |r: u32| (lod0(r) as usize * res).min(height);
        let margin = usize::from(layer.border) << k;
        let band = to_rows(r0)..to_rows(r1);
        let rows = band.start.saturating_sub(margin)..(band.end + margin).min(height);
        let rows = if band.is_empty() { 0..0 } else { rows };
        windows.push(Window { input_lod: 0, last_lod: k, encode_from: 0, rows, band, first_column: 0 });
        // The height-range layer follows its elevation layer's grid; it has no pyramid.
        debug_assert!(layer.kind != LayerKind::HeightRange || windows.len() > 1);
    }
    Ok((Shard { index: spec.index, count: spec.count, split_lods, tile_rows }, windows, all_cuts))
}

/// The plan of a sharded run made where only its shards' own inputs are fetched: the
/// mosaics' grids and the bands, fixed from every input's header, and the inputs each
/// shard's rows read (`terrastream tile --shards N --shard-plan-out`). A shard given its
/// inputs and this plan makes the tiles a shard given every input makes.
#[derive(Clone, Debug, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct ShardPlan {
    /// Shards in the run.
    pub count: u32,
    /// The split LOD asked for (see [`ShardSpec::split_lod`]).
    pub split_lod: Option<u8>,
    /// The elevation mosaic's grid, when the elevation is one.
    pub elevation_grid: Option<PlannedGrid>,
    /// The imagery mosaic's grid, when the imagery is one.
    pub texture_grid: Option<PlannedGrid>,
    /// Per layer, the band boundaries ([`ShardSpec::cuts`]).
    pub cuts: Vec<Vec<u32>>,
    /// Per shard, the inputs its rows read.
    pub shards: Vec<ShardInputs>,
    /// The collections of the run (inputs of different resolutions, each as deep as it
    /// reaches): none for a run of one resolution.
    #[serde(default, skip_serializing_if = "Vec::is_empty")]
    pub collections: Vec<crate::collection::PlannedCollection>,
    /// The inputs the merge of the shards reads: those of a collection split finer than
    /// its base that are deeper than the split (the merge makes their levels).
    #[serde(default, skip_serializing_if = "Vec::is_empty")]
    pub merge: Vec<PathBuf>,
}

/// A mosaic's output grid, with its CRS.
#[derive(Clone, Debug, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct PlannedGrid {
    /// The CRS (as `Crs::parse` reads it).
    pub crs: String,
    /// North-west corner.
    pub origin: [f64; 2],
    /// Sample size (x, y).
    pub pixel: [f64; 2],
    /// Samples across and down.
    pub size: [u32; 2],
}

impl PlannedGrid {
    fn of(crs: Option<String>, grid: Option<GridSpec>) -> Option<Self> {
        let (crs, g) = (crs?, grid?);
        Some(Self { crs, origin: g.origin, pixel: [g.pixel.0, g.pixel.1], size: [g.size.0, g.size.1] })
    }

    /// The grid, for [`crate::TileRequest::elevation_grid`] or `texture_grid`.
    pub fn spec(&self) -> GridSpec {
        GridSpec { origin: self.origin, pixel: (self.pixel[0], self.pixel[1]), size: (self.size[0], self.size[1]) }
    }
}

/// The inputs one shard reads, in the order given.
#[derive(Clone, Debug, Default, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct ShardInputs {
    /// Elevation inputs.
    pub elevation: Vec<PathBuf>,
    /// Imagery inputs.
    pub texture: Vec<PathBuf>,
}

impl ShardPlan {
    /// Shard `index`'s spec: its bands as planned.
    pub fn spec(&self, index: u32) -> ShardSpec {
        ShardSpec { index, count: self.count, split_lod: self.split_lod, cuts: Some(self.cuts.clone()) }
    }
}

/// The plan of `count` shards over these sources, from the inputs' headers alone (no
/// height is read).
///
/// # Errors
/// As [`crate::plan()`]; [`Error::InvalidOption`] for no shard.
pub fn shard_plan(
    elevation: Option<&dyn ElevationSource>,
    texture: Option<&TextureInput<'_>>,
    name: &str,
    options: TileOptions,
    count: u32,
    split_lod: Option<u8>,
) -> Result<ShardPlan> {
    let plan = plan_layout(elevation, texture, name, options)?;
    let weight = data_weight(&plan, elevation, texture);
    // The bands, balanced once (every shard's are the same); then each shard's windows.
    let first = ShardSpec { index: 0, count, split_lod, cuts: None };
    let (_, _, cuts) = windows_and_cuts(&plan, &first, &weight)?;
    let mut shards = vec![];
    for index in 0..count {
        let spec = ShardSpec { index, count, split_lod, cuts: Some(cuts.clone()) };
        let (_, bands) = windows(&plan, &spec, &weight)?;
        let mut inputs = ShardInputs::default();
        for (layer, window) in plan.metadata.layers.iter().zip(&bands) {
            let rows = to_u32(window.rows.start)..to_u32(window.rows.end);
            // A band that reads nothing (more shards than rows of data) still opens its
            // sources on the planned grid: its list holds the first input.
            let listed = |of: &dyn Fn(std::ops::Range<u32>) -> Vec<PathBuf>| {
                let list = of(rows.clone());
                if list.is_empty() { of(0..1) } else { list }
            };
            match layer.kind {
                LayerKind::Elevation => {
                    inputs.elevation = elevation.map_or(vec![], |e| listed(&|r| e.inputs_in_rows(r)))
                }
                LayerKind::Texture => {
                    inputs.texture = texture.map_or(vec![], |t| listed(&|r| t.source.inputs_in_rows(r)))
                }
                _ => {}
            }
        }
        shards.push(inputs);
    }
    Ok(ShardPlan::of_sources(count, split_lod, elevation, texture, cuts, shards))
}

impl ShardPlan {
    /// The plan of `count` shards with these `cuts` and `shards`' inputs, the mosaics'
    /// grids taken from the sources (no collection: see
    /// [`crate::collection_shard_plan`]).
    pub(crate) fn of_sources(
        count: u32,
        split_lod: Option<u8>,
        elevation: Option<&dyn ElevationSource>,
        texture: Option<&TextureInput<'_>>,
        cuts: Vec<Vec<u32>>,
        shards: Vec<ShardInputs>,
    ) -> Self {
        let crs_of = |g: Option<&terrastream_format::Georeference>| g.and_then(|g| g.crs.clone());
        Self {
            count,
            split_lod,
            elevation_grid: elevation.and_then(|e| PlannedGrid::of(crs_of(e.georeference()), e.mosaic_grid())),
            texture_grid: texture
                .and_then(|t| PlannedGrid::of(crs_of(t.source.georeference()), t.source.mosaic_grid())),
            cuts,
            shards,
            collections: Vec::new(),
            merge: Vec::new(),
        }
    }
}

fn to_u32(n: usize) -> u32 {
    u32::try_from(n).unwrap_or(u32::MAX)
}

/// `count + 1` boundaries splitting `rows` rows into `count` runs of about equal total
/// `weight`; evenly by rows when there is no weight at all.
pub(crate) fn balanced_cuts(rows: u32, count: u32, weight: impl Fn(u32) -> f64) -> Vec<u32> {
    let weights: Vec<f64> = (0..rows).map(|r| weight(r).max(0.0)).collect();
    let total: f64 = weights.iter().sum();
    let even = |i: u32| u32::try_from(u64::from(rows) * u64::from(i) / u64::from(count)).unwrap_or(rows);
    if total <= 0.0 {
        return (0..=count).map(even).collect();
    }
    let mut cuts = vec![0];
    let mut sum = 0.0;
    let mut r = 0u32;
    for i in 1..count {
        // The first row boundary at or past the i-th share of the weight.
        let share = total * f64::from(i) / f64::from(count);
        while r < rows && sum + weights[r as usize] / 2.0 < share {
            sum += weights[r as usize];
            r += 1;
        }
        cuts.push(r);
    }
    cuts.push(rows);
    cuts
}

#[cfg(test)]
mod tests {
    use super::balanced_cuts;

    #[test]
    fn bands_balance_data_not_rows() {
        // Uniform: even bands.
        assert_eq!(balanced_cuts(8, 4, |_| 1.0), [0, 2, 4, 6, 8]);
        // All the data in the last four rows: the empty rows go to the first shard.
        assert_eq!(balanced_cuts(8, 2, |r| if r >= 4 { 1.0 } else { 0.0 }), [0, 6, 8]);
        // No data known: even by rows; more shards than rows: some get none.
        assert_eq!(balanced_cuts(6, 3, |_| 0.0), [0, 2, 4, 6]);
        assert_eq!(balanced_cuts(2, 4, |_| 1.0), [0, 0, 1, 1, 2]);
    }
}
