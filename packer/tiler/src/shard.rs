//! Sharded tile runs: which band of each layer's grid a shard makes.
//!
//! A shard holds, for every layer, the tiles of a band of tile rows from LOD 0 up to the
//! layer's split LOD K. Bands are whole rows of LOD-K tiles, so every tile up to K lies in
//! exactly one shard with all the tiles under it; rows of the raster are read with a margin
//! of `border * 2^K` above and below, so a shard's tiles, borders included, are the bytes a
//! whole run makes. The levels above K are made when the shards are merged, from their
//! LOD-K tiles ([`crate::edit::merge`]).

use terrastream_format::{LayerKind, Shard};

use crate::error::{Error, Result};
use crate::options::ShardSpec;
use crate::plan::Plan;
use crate::pyramid::Window;

/// Samples with data in a layer's LOD-0 rows (see `ElevationSource::data_in_rows`).
pub(crate) type Weight<'a> = dyn Fn(usize, std::ops::Range<u32>) -> f64 + 'a;

/// The shard's metadata record and each layer's window (in layer order). Bands are cut so
/// that each shard gets about as many samples with data (`weight(layer, rows)`) as the
/// others: sparse regions cost little, so their bands are taller.
///
/// # Errors
/// [`Error::InvalidOption`] for a shard out of range.
pub(crate) fn windows(plan: &Plan, spec: ShardSpec, weight: &Weight<'_>) -> Result<(Shard, Vec<Window>)> {
    if spec.count == 0 || spec.index >= spec.count {
        return Err(Error::option("--shard", format!("{}/{}", spec.index, spec.count), "I/N with 0 <= I < N"));
    }
    let layers = &plan.metadata.layers;
    let mut split_lods = Vec::with_capacity(layers.len());
    let mut tile_rows = Vec::with_capacity(layers.len());
    let mut windows = Vec::with_capacity(layers.len());
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
        let cuts = balanced_cuts(rows_k, spec.count, |r| weight(index, sample_rows(r)..sample_rows(r + 1)));
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
        windows.push(Window { input_lod: 0, last_lod: k, encode_from: 0, rows, band });
        // The height-range layer follows its elevation layer's grid; it has no pyramid.
        debug_assert!(layer.kind != LayerKind::HeightRange || windows.len() > 1);
    }
    Ok((Shard { index: spec.index, count: spec.count, split_lods, tile_rows }, windows))
}

/// `count + 1` boundaries splitting `rows` rows into `count` runs of about equal total
/// `weight`; evenly by rows when there is no weight at all.
fn balanced_cuts(rows: u32, count: u32, weight: impl Fn(u32) -> f64) -> Vec<u32> {
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
