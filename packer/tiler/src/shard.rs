//! Sharded tile runs: which band of each layer's grid a shard makes.
//!
//! A shard holds, for every layer, the tiles of a band of tile rows from LOD 0 up to the
//! layer's split LOD K. Bands are whole rows of LOD-K tiles, so every tile up to K lies in
//! exactly one shard with all the tiles under it; rows of the raster are read with a margin
//! of `border * 2^K` above and below, so a shard's tiles, borders included, are the bytes a
//! whole run makes. The levels above K are made when the shards are merged, from their
//! LOD-K tiles ([`crate::merge`]).

use terrastream_format::{LayerKind, Shard};

use crate::error::{Error, Result};
use crate::options::ShardSpec;
use crate::plan::Plan;
use crate::pyramid::Window;

/// The shard's metadata record and each layer's window (in layer order).
///
/// # Errors
/// [`Error::Option`] for a shard out of range.
pub(crate) fn windows(plan: &Plan, spec: ShardSpec) -> Result<(Shard, Vec<Window>)> {
    if spec.count == 0 || spec.index >= spec.count {
        return Err(Error::option("--shard", format!("{}/{}", spec.index, spec.count), "I/N with 0 <= I < N"));
    }
    let layers = &plan.metadata.layers;
    let mut split_lods = Vec::with_capacity(layers.len());
    let mut tile_rows = Vec::with_capacity(layers.len());
    let mut windows = Vec::with_capacity(layers.len());
    for (layer, lp) in layers.iter().zip(&plan.layers) {
        let last = layer.num_lods.saturating_sub(1);
        let rows_at = |k: u8| layer.num_y_tiles.div_ceil(1 << k);
        let k = match spec.split_lod {
            Some(k) => k.min(last),
            None => (0..=last).rev().find(|&k| rows_at(k) >= 2 * spec.count).unwrap_or(0),
        };
        // Rows of LOD-K tiles, split evenly (each row of a layer's grid holds data
        // across: the rasters are rectangles).
        let rows_k = rows_at(k);
        let cut = |i: u32| u32::try_from(u64::from(rows_k) * u64::from(i) / u64::from(spec.count)).unwrap_or(rows_k);
        let (r0, r1) = (cut(spec.index), cut(spec.index + 1));
        let lod0 = |r: u32| (r << k).min(layer.num_y_tiles);
        tile_rows.push([lod0(r0), lod0(r1)]);
        split_lods.push(k);
        let height = lp.size.1 as usize;
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
