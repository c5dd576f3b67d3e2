//! Keeping a merged pyramid consistent: the tiles a merge must make again.
//!
//! When archives of one grid are merged (not shards), a later input's tile replaces an
//! earlier one's, which leaves three kinds of stale tiles: a tile whose borders copy a
//! neighbour that now comes from another input; a coarser tile averaged from children
//! that were replaced; a coarse tile that two inputs both hold, each with only its own
//! region's data. All of them are made again here, and only they: level by level, a tile
//! is remade when its 3 x 3 neighbourhood mixes inputs, when two inputs hold it, or when
//! the samples it is averaged from (its children, and theirs under its borders) were
//! remade. LOD 0 keeps every interior as stored and takes its borders from the
//! neighbours; coarser tiles are 2 x 2 means of the level below as stored, quantized as the
//! layer stores them, exactly as the tiler makes them. So the merge of an archive and a
//! region of another is, byte for byte, the archive the tiler makes of the combined
//! raster; and the work follows the changed area, not the archive.

use std::collections::{HashMap, HashSet};

use terrastream_format::TileKey;

use crate::error::Result;
use crate::pyramid::{Pixel, Quantize, halve_rows};

/// One layer's grid.
pub(crate) struct Grid {
    pub(crate) layer: u8,
    pub(crate) lods: u8,
    pub(crate) res: usize,
    pub(crate) border: usize,
    /// Tiles across and down at LOD 0.
    pub(crate) tiles: (u32, u32),
}

impl Grid {
    fn edge(&self) -> usize {
        self.res + 2 * self.border
    }
    /// Tiles across and down at `lod`.
    fn tiles_at(&self, lod: u8) -> (u32, u32) {
        (self.tiles.0.div_ceil(1 << lod), self.tiles.1.div_ceil(1 << lod))
    }
    /// Samples across and down at `lod` (the grid's, padded to whole LOD-0 tiles).
    #[expect(clippy::cast_possible_wrap, reason = "a grid's samples are far below 2^63")]
    fn samples_at(&self, lod: u8) -> (i64, i64) {
        let n = |t: u32| (t as usize * self.res).div_ceil(1 << lod) as i64;
        (n(self.tiles.0), n(self.tiles.1))
    }
}

/// Encodes a tile's samples into its archive entries.
pub(crate) type EncodeTile<'a, S> = dyn Fn(TileKey, &[S]) -> Result<Vec<(TileKey, Vec<u8>)>> + Sync + 'a;

/// What the merge knows of one layer's tiles.
pub(crate) struct Tiles<'a, S> {
    /// The input each tile comes from (after `prefer last`), by (lod, x, y).
    pub(crate) source: &'a dyn Fn(u8, u32, u32) -> Option<usize>,
    /// Tiles two or more inputs hold.
    pub(crate) conflicts: &'a HashSet<(u8, u32, u32)>,
    /// The stored tile (lod, x, y), decoded (`edge` x `edge` samples).
    pub(crate) decode: &'a (dyn Fn(u8, u32, u32) -> Result<Option<Vec<S>>> + Sync),
    /// Encodes a remade tile into its entries.
    pub(crate) encode: &'a EncodeTile<'a, S>,
    pub(crate) quantize: Option<&'a Quantize<'a, S>>,
    /// `--prefer pixels`: every input's version of an LOD-0 tile two inputs hold, in input
    /// order; the tile becomes their composite (a later one's samples with data win).
    pub(crate) versions: Option<&'a Versions<'a, S>>,
}

/// Every input's version of LOD-0 tile (x, y), decoded, in input order.
pub(crate) type Versions<'a, S> = dyn Fn(u32, u32) -> Result<Vec<Vec<S>>> + Sync + 'a;

/// What was remade: the entries of remade tiles, and the keys of tiles that hold no data
/// once remade (to be left out).
#[derive(Default)]
pub(crate) struct Remade {
    pub(crate) entries: Vec<(TileKey, Vec<u8>)>,
    pub(crate) emptied: Vec<TileKey>,
}

/// Remakes the stale tiles of one layer (see the module's documentation).
pub(crate) fn rederive<S: Pixel>(grid: &Grid, tiles: &Tiles<'_, S>, remade: &mut Remade) -> Result<()> {
    let (res, border, edge) = (grid.res, grid.border, grid.edge());
    // Samples of the level below as they end up: remade tiles (kept for the next level)
    // or stored ones (decoded on demand, cached while a level is made).
    let mut made_below: HashMap<(u32, u32), Option<Vec<S>>> = HashMap::new();
    let mut dirty_below: HashSet<(u32, u32)> = HashSet::new();
    // Composites of the LOD-0 tiles several inputs hold, when pixels are preferred.
    let mut composite: HashMap<(u32, u32), Option<Vec<S>>> = HashMap::new();
    if let Some(versions) = tiles.versions {
        for &(_, x, y) in tiles.conflicts.iter().filter(|(l, ..)| *l == 0) {
            let mut out: Option<Vec<S>> = None;
            for version in versions(x, y)? {
                match &mut out {
                    None => out = Some(version),
                    Some(o) => {
                        for (a, b) in o.iter_mut().zip(&version) {
                            if b.has_data() {
                                *a = *b;
                            }
                        }
                    }
                }
            }
            composite.insert((x, y), out);
        }
    }
    for lod in 0..grid.lods {
        let (cols, rows) = grid.tiles_at(lod);
        let mut dirty: HashSet<(u32, u32)> =
            tiles.conflicts.iter().filter(|(l, ..)| *l == lod).map(|&(_, x, y)| (x, y)).collect();
        if lod == 0 {
            dirty.extend(mixed_neighbourhoods(tiles, cols, rows));
        } else {
            for &(cx, cy) in &dirty_below {
                for x in (cx / 2).saturating_sub(1)..=(cx / 2 + 1).min(cols - 1) {
                    for y in (cy / 2).saturating_sub(1)..=(cy / 2 + 1).min(rows - 1) {
                        if covers(grid, x, cx) && covers(grid, y, cy) {
                            dirty.insert((x, y));
                        }
                    }
                }
            }
        }
        let mut cache: HashMap<(u32, u32), Option<Vec<S>>> = HashMap::new();
        let mut made_here: HashMap<(u32, u32), Option<Vec<S>>> = HashMap::new();
        let mut order: Vec<(u32, u32)> = dirty.iter().copied().collect();
        order.sort_unstable_by_key(|&(x, y)| (y, x));
        for &(x, y) in &order {
            let samples = if lod == 0 {
                // The interior as stored, the borders from the neighbours' interiors.
                window(grid, 0, (x, y), 1, &mut |tx, ty| match composite.get(&(tx, ty)) {
                    Some(c) => Ok(c.clone()),
                    None => stored(tiles, &mut cache, 0, tx, ty),
                })?
            } else {
                let below = lod - 1;
                let wide = window(grid, below, (x, y), 2, &mut |tx, ty| match made_below.get(&(tx, ty)) {
                    Some(made) => Ok(made.clone()),
                    None => stored(tiles, &mut cache, below, tx, ty),
                })?;
                let side = 2 * edge;
                let mut out = Vec::with_capacity(edge * edge);
                for pair in wide.chunks_exact(2 * side) {
                    let mut row = halve_rows(&pair[..side], &pair[side..]);
                    if let Some(q) = tiles.quantize {
                        q(&mut row);
                    }
                    out.extend_from_slice(&row);
                }
                out
            };
            let key = TileKey::new(grid.layer, lod, x, y)?;
            let has_data = (border..border + res)
                .any(|j| samples[j * edge + border..j * edge + border + res].iter().any(S::has_data));
            if has_data {
                remade.entries.extend((tiles.encode)(key, &samples)?);
                made_here.insert((x, y), Some(samples));
            } else {
                if (tiles.source)(lod, x, y).is_some() {
                    remade.emptied.push(key);
                }
                made_here.insert((x, y), None);
            }
        }
        made_below = made_here;
        dirty_below = dirty;
    }
    Ok(())
}

/// Does tile `x`'s window (its samples and borders, at the level below: `2 * (x * res -
/// border) .. 2 * ((x + 1) * res + border)`) reach the level below's tile `child`?
#[expect(clippy::cast_possible_wrap, reason = "a tile's samples")]
fn covers(grid: &Grid, x: u32, child: u32) -> bool {
    let (res, b) = (grid.res as i64, grid.border as i64);
    let (from, to) = (2 * (i64::from(x) * res - b), 2 * ((i64::from(x) + 1) * res + b));
    let (c0, c1) = (i64::from(child) * res, (i64::from(child) + 1) * res);
    from < c1 && c0 < to
}

/// LOD-0 tiles whose 3 x 3 neighbourhood holds tiles of more than one input.
fn mixed_neighbourhoods<S>(tiles: &Tiles<'_, S>, cols: u32, rows: u32) -> Vec<(u32, u32)> {
    let mut out = Vec::new();
    for y in 0..rows {
        for x in 0..cols {
            let Some(own) = (tiles.source)(0, x, y) else { continue };
            let mixed = (y.saturating_sub(1)..=(y + 1).min(rows - 1))
                .flat_map(|ny| (x.saturating_sub(1)..=(x + 1).min(cols - 1)).map(move |nx| (nx, ny)))
                .any(|(nx, ny)| (tiles.source)(0, nx, ny).is_some_and(|s| s != own));
            if mixed {
                out.push((x, y));
            }
        }
    }
    out
}

/// A stored tile's samples, decoded once per level.
fn stored<S: Pixel>(
    tiles: &Tiles<'_, S>,
    cache: &mut HashMap<(u32, u32), Option<Vec<S>>>,
    lod: u8,
    x: u32,
    y: u32,
) -> Result<Option<Vec<S>>> {
    if let Some(hit) = cache.get(&(x, y)) {
        return Ok(hit.clone());
    }
    let samples = match (tiles.source)(lod, x, y) {
        Some(_) => (tiles.decode)(lod, x, y)?,
        None => None,
    };
    cache.insert((x, y), samples.clone());
    Ok(samples)
}

/// The samples of level `lod` under tile (x, y) of the level `scale` times coarser, with
/// borders: `scale * edge` x `scale * edge`, starting at `scale * (x * res - border)`;
/// no data outside the level. `tile(tx, ty)` gives a level tile's stored samples (with
/// borders), or None.
#[expect(
    clippy::cast_possible_truncation,
    clippy::cast_possible_wrap,
    clippy::cast_sign_loss,
    reason = "sample indices of one tile's window: small, and >= 0 where cast to usize"
)]
fn window<S: Pixel>(
    grid: &Grid,
    lod: u8,
    (x, y): (u32, u32),
    scale: i64,
    tile: &mut dyn FnMut(u32, u32) -> Result<Option<Vec<S>>>,
) -> Result<Vec<S>> {
    let (res, b, edge) = (grid.res as i64, grid.border as i64, grid.edge());
    let side = scale as usize * edge;
    let (w, h) = grid.samples_at(lod);
    let (x0, y0) = (scale * (i64::from(x) * res - b), scale * (i64::from(y) * res - b));
    let mut out = vec![S::NONE; side * side];
    let tile_range = |from: i64, len: i64, limit: i64| {
        let first = from.max(0) / res;
        let last = (from + len - 1).min(limit - 1).max(0) / res;
        first..=last
    };
    for ty in tile_range(y0, side as i64, h) {
        for tx in tile_range(x0, side as i64, w) {
            let (Ok(ux), Ok(uy)) = (u32::try_from(tx), u32::try_from(ty)) else { continue };
            let Some(samples) = tile(ux, uy)? else { continue };
            // The tile's interior, clipped to the window and the level.
            for j in 0..res {
                let gy = ty * res + j;
                if gy < y0 || gy >= y0 + side as i64 || gy >= h {
                    continue;
                }
                for i in 0..res {
                    let gx = tx * res + i;
                    if gx < x0 || gx >= x0 + side as i64 || gx >= w {
                        continue;
                    }
                    let at = (grid.border + j as usize) * edge + grid.border + i as usize;
                    if let Some(&v) = samples.get(at) {
                        out[(gy - y0) as usize * side + (gx - x0) as usize] = v;
                    }
                }
            }
        }
    }
    Ok(out)
}
