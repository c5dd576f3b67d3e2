//! Keeping a merged pyramid consistent: the tiles a merge must make again.
//!
//! When archives of one grid are merged (not shards), a later input's tile replaces an
//! earlier one's, which leaves three kinds of stale tiles: a tile whose borders copy a
//! neighbour that now comes from another input; a coarser tile averaged from children
//! that were replaced; a coarse tile that two inputs both hold, each with only its own
//! region's data. All of them are made again here, and only they: level by level, a tile
//! is remade when its 3 x 3 neighbourhood mixes inputs (LOD 0), when two inputs hold it,
//! or when the samples it is averaged from (its children's interiors, and their
//! neighbours' under its borders) changed: remade with a new interior, or from another
//! input than the tile's own. A tile remade only for its borders keeps its interior, so
//! the work around a changed region stays one ring of tiles per level. LOD 0 keeps every
//! interior as stored and takes its borders from the neighbours; coarser tiles are 2 x 2
//! means of the level below as stored, quantized as the layer stores them, exactly as the
//! tiler makes them, and keep their own stored samples where the level below holds no
//! tile (a collection's finer levels hold tiles only where its surveys lie). So the merge
//! of an archive and a region of another is, byte for byte, the archive the tiler makes of
//! the combined raster; and the work follows the changed area, not the archive.

use std::collections::{HashMap, HashSet};
use std::sync::Arc;

use rayon::prelude::*;

use terrastream_format::TileKey;

use crate::error::Result;
use crate::pyramid::{Pixel, halve_rows};

/// One layer's grid.
pub(crate) struct LayerGrid {
    pub(crate) layer: u8,
    pub(crate) lods: u8,
    pub(crate) res: usize,
    pub(crate) border: usize,
    /// Tiles across and down at LOD 0.
    pub(crate) tiles: (u32, u32),
}

impl LayerGrid {
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
    /// Whether `samples` (a tile with borders) hold data inside the borders.
    fn interior_has_data<S: Pixel>(&self, samples: &[S]) -> bool {
        let (res, border, edge) = (self.res, self.border, self.edge());
        (border..border + res).any(|j| samples[j * edge + border..j * edge + border + res].iter().any(S::has_data))
    }
    /// Whether every sample inside the borders holds data.
    fn interior_whole<S: Pixel>(&self, samples: &[S]) -> bool {
        let (res, border, edge) = (self.res, self.border, self.edge());
        (border..border + res).all(|j| samples[j * edge + border..j * edge + border + res].iter().all(S::has_data))
    }
}

/// What a merge knows of one layer's tiles: where each comes from, how its stored
/// version decodes, and how a remade one encodes.
pub(crate) trait MergedTiles<S>: Sync {
    /// The input tile (lod, x, y) comes from (after `prefer last`); None where no input
    /// holds it.
    fn source(&self, lod: u8, x: u32, y: u32) -> Option<usize>;
    /// The layer's tiles two or more inputs hold.
    fn conflicts(&self) -> &HashSet<TileKey>;
    /// The layer's tiles that come from another input than the first. Inputs are whole
    /// pyramids, so a tile of the first input has a parent there: only these tiles, and
    /// their neighbours, can sit beside or under a tile of another input.
    fn later(&self) -> &HashSet<TileKey>;
    /// The stored tile (lod, x, y), decoded (`edge` x `edge` samples).
    fn decode(&self, lod: u8, x: u32, y: u32) -> Result<Option<Vec<S>>>;
    /// A remade tile's archive entries.
    fn encode(&self, key: TileKey, samples: &[S]) -> Result<Vec<(TileKey, Vec<u8>)>>;
    /// Rounds a row of averaged samples as the layer stores them (heights are quantized).
    fn quantize(&self, _row: &mut [S]) {}
    /// With `--prefer pixels`: version `newest_first` of LOD-0 tile (x, y) counting from
    /// the newest (0: the last input's that holds it), decoded; None past the oldest. The
    /// tile becomes their composite (a later one's samples with data win). None: the
    /// newest version wins whole.
    fn version(&self, x: u32, y: u32, newest_first: usize) -> Option<Result<Option<Vec<S>>>>;
}

/// What was remade: the entries of remade tiles, and the keys of tiles that hold no data
/// once remade (to be left out).
#[derive(Default)]
pub(crate) struct Remade {
    pub(crate) entries: Vec<(TileKey, Vec<u8>)>,
    pub(crate) emptied: Vec<TileKey>,
}

/// A level's tile samples by position: None where the tile holds no data.
type LevelTiles<S> = HashMap<(u32, u32), Option<Arc<Vec<S>>>>;

/// One entry of a [`LevelTiles`].
type Placed<S> = ((u32, u32), Option<Arc<Vec<S>>>);

/// The (x, y) of the tiles of `set` at `lod`.
fn at_lod(set: &HashSet<TileKey>, lod: u8) -> impl Iterator<Item = (u32, u32)> + '_ {
    set.iter().filter(move |k| k.lod() == lod).map(|k| (k.x(), k.y()))
}

/// Remakes the stale tiles of one layer (see the module's documentation). Each level's
/// tiles are made in parallel, from the level below decoded in parallel first.
pub(crate) fn rederive<S: Pixel>(grid: &LayerGrid, tiles: &dyn MergedTiles<S>, remade: &mut Remade) -> Result<()> {
    // The level below as it ends up: its remade tiles (the stored ones are decoded as
    // each level needs them); LOD-0 tiles known as their winning input stores them,
    // without decoding them again.
    let Composites { made: mut made_below, as_stored } = composites(grid, tiles)?;
    let mut changed_below: HashSet<(u32, u32)> = HashSet::new();
    for lod in 0..grid.lods {
        let Stale { dirty, changed } = stale(grid, tiles, lod, &changed_below);
        let below = std::mem::take(&mut made_below);
        let level = Level { grid, tiles, lod, below: &below, as_stored: &as_stored };
        for ((x, y), samples, entries) in level.remake(&dirty)? {
            let held = tiles.source(lod, x, y).is_some();
            if samples.is_none() && held {
                remade.emptied.push(TileKey::new(grid.layer, lod, x, y)?);
            }
            remade.entries.extend(entries);
            // A tile no input holds, made again without data, is still none: the level
            // above keeps its own samples over it (a collection's coarser tile where the
            // finer level holds no tile).
            if samples.is_some() || held {
                made_below.insert((x, y), samples);
            }
        }
        changed_below = changed;
    }
    Ok(())
}

/// LOD-0 tiles that several inputs hold, as made from all their versions.
struct Composites<S> {
    /// The composites (with `--prefer pixels`; none otherwise).
    made: LevelTiles<S>,
    /// Those that are their newest version alone: the tile as its winning input stores it.
    as_stored: HashMap<(u32, u32), Arc<Vec<S>>>,
}

/// With `--prefer pixels`, the composites of the LOD-0 tiles several inputs hold.
fn composites<S: Pixel>(grid: &LayerGrid, tiles: &dyn MergedTiles<S>) -> Result<Composites<S>> {
    let (mut made, mut as_stored) = (HashMap::new(), HashMap::new());
    let conflicts: Vec<(u32, u32)> = at_lod(tiles.conflicts(), 0).collect();
    let composites = conflicts
        .par_iter()
        .map(|&(x, y)| -> Result<Option<(Placed<S>, bool)>> {
            // Newest first, each older one filling the samples still without data: the
            // same as laying them over each other oldest first, and an older one is not
            // read once the interior is whole (what the merge takes of it).
            let mut out: Option<Vec<S>> = None;
            let mut read = 0;
            for i in 0.. {
                let Some(version) = tiles.version(x, y, i) else { return Ok(None) };
                let Some(version) = version? else { break };
                read += 1;
                match &mut out {
                    None => out = Some(version),
                    Some(o) => {
                        for (a, b) in o.iter_mut().zip(&version) {
                            if !a.has_data() {
                                *a = *b;
                            }
                        }
                    }
                }
                if out.as_deref().is_some_and(|o| grid.interior_whole(o)) {
                    break;
                }
            }
            Ok(Some((((x, y), out.map(Arc::new)), read == 1)))
        })
        .collect::<Result<Vec<_>>>()?;
    for ((at, samples), newest_alone) in composites.into_iter().flatten() {
        if newest_alone && let Some(samples) = &samples {
            as_stored.insert(at, Arc::clone(samples));
        }
        made.insert(at, samples);
    }
    Ok(Composites { made, as_stored })
}

/// The tiles of a level to remake.
struct Stale {
    /// Every tile to remake.
    dirty: HashSet<(u32, u32)>,
    /// Those whose interior (not only their borders) is made from changed samples.
    changed: HashSet<(u32, u32)>,
}

/// The tiles of `lod` to remake, given the level below's changed tiles.
fn stale<S>(grid: &LayerGrid, tiles: &dyn MergedTiles<S>, lod: u8, changed_below: &HashSet<(u32, u32)>) -> Stale {
    let (cols, rows) = grid.tiles_at(lod);
    let mut dirty: HashSet<(u32, u32)> = at_lod(tiles.conflicts(), lod).collect();
    let mut changed = dirty.clone();
    if lod == 0 {
        dirty.extend(mixed_neighbourhoods(tiles, cols, rows));
        return Stale { dirty, changed };
    }
    // A tile of the level below changes its parents' samples when its interior was
    // remade, or when it comes from another input than a parent (which was averaged from
    // its own input's version, or is missing).
    let mut mark = |(cx, cy): (u32, u32), only_if: Option<usize>| {
        for x in (cx / 2).saturating_sub(1)..=(cx / 2 + 1).min(cols - 1) {
            for y in (cy / 2).saturating_sub(1)..=(cy / 2 + 1).min(rows - 1) {
                if covers(grid, x, cx)
                    && covers(grid, y, cy)
                    && only_if.is_none_or(|input| tiles.source(lod, x, y) != Some(input))
                {
                    dirty.insert((x, y));
                    if (x, y) == (cx / 2, cy / 2) {
                        changed.insert((x, y));
                    }
                }
            }
        }
    };
    for &tile in changed_below {
        mark(tile, None);
    }
    // (A tile of the first input under a parent of another: that parent is in the first
    // input too, so two inputs hold it, and it is remade anyway.)
    for (cx, cy) in at_lod(tiles.later(), lod - 1) {
        if let Some(input) = tiles.source(lod - 1, cx, cy)
            && !changed_below.contains(&(cx, cy))
        {
            mark((cx, cy), Some(input));
        }
    }
    Stale { dirty, changed }
}

/// A remade tile: its position, its samples (None: no data) and its new entries (none
/// where it is remade as stored).
type Made<S> = ((u32, u32), Option<Arc<Vec<S>>>, Vec<(TileKey, Vec<u8>)>);

/// One level being remade, over the level below as it ends up.
struct Level<'a, S> {
    grid: &'a LayerGrid,
    tiles: &'a dyn MergedTiles<S>,
    lod: u8,
    /// The level below's remade tiles.
    below: &'a LevelTiles<S>,
    /// LOD-0 tiles as their winning input stores them.
    as_stored: &'a HashMap<(u32, u32), Arc<Vec<S>>>,
}

impl<S: Pixel> Level<'_, S> {
    /// The level's source level, and how many times coarser this one is: LOD 0 is cut
    /// from its own tiles (the composites standing in for theirs); the others are averaged
    /// from the level below.
    fn from(&self) -> (u8, i64) {
        if self.lod == 0 { (0, 1) } else { (self.lod - 1, 2) }
    }

    fn decode_all(&self, level: u8, set: Vec<(u32, u32)>) -> Result<LevelTiles<S>> {
        let decoded = set
            .into_par_iter()
            .map(|(x, y)| -> Result<Placed<S>> { Ok(((x, y), self.tiles.decode(level, x, y)?.map(Arc::new))) })
            .collect::<Result<Vec<_>>>()?;
        Ok(decoded.into_iter().collect())
    }

    /// Remakes the `dirty` tiles. A tile's samples come from the tiles under it that
    /// changed (remade, or from another input than its own); the rest are its stored
    /// version's, which the same samples made: so only those tiles and the tile itself
    /// are decoded, not every tile under it.
    fn remake(&self, dirty: &HashSet<(u32, u32)>) -> Result<Vec<Made<S>>> {
        let (grid, tiles, lod) = (self.grid, self.tiles, self.lod);
        let (from, scale) = self.from();
        let own = |&(x, y): &(u32, u32)| tiles.source(lod, x, y);
        let needed: HashSet<(u32, u32)> = dirty
            .iter()
            .flat_map(|t| {
                let own = own(t);
                window_tiles(grid, from, *t, scale).into_iter().filter(move |&(cx, cy)| {
                    let source = tiles.source(from, cx, cy);
                    source.is_some() && (own.is_none() || source != own)
                })
            })
            .filter(|t| !self.below.contains_key(t))
            .collect();
        // A tile's stored version is read only when some part of the level under it is
        // not taken: a tile there as stored, or none at all (a collection's coarser tile
        // holds its own samples where the finer level holds no tile).
        let partly_stored = |t: &(u32, u32)| {
            own(t).is_some()
                && !(lod == 0 && self.as_stored.contains_key(t))
                && window_tiles(grid, from, *t, scale)
                    .into_iter()
                    .any(|c| !self.below.contains_key(&c) && !needed.contains(&c))
        };
        let mut stored = self.decode_all(lod, dirty.iter().copied().filter(partly_stored).collect())?;
        if lod == 0 {
            for t in dirty {
                if let Some(samples) = self.as_stored.get(t) {
                    stored.insert(*t, Some(Arc::clone(samples)));
                }
            }
        }
        let fresh = self.decode_all(from, needed.into_iter().collect())?;
        tracing::debug!(layer = grid.layer, lod, remade = dirty.len(), decoded = fresh.len() + stored.len(), "level");
        let lookup = |x: u32, y: u32| -> Option<Option<&[S]>> {
            self.below.get(&(x, y)).or_else(|| fresh.get(&(x, y))).map(|t| t.as_ref().map(|t| t.as_slice()))
        };
        let mut order: Vec<(u32, u32)> = dirty.iter().copied().collect();
        order.sort_unstable_by_key(|&(x, y)| (y, x));
        order
            .par_iter()
            .map(|&at| self.remake_tile(at, &lookup, stored.get(&at).and_then(|s| s.as_deref().map(Vec::as_slice))))
            .collect()
    }

    /// Tile `at` made again from the level below (`lookup`), keeping its `stored`
    /// samples where none of the tiles under them was taken.
    fn remake_tile<'t>(
        &self,
        (x, y): (u32, u32),
        lookup: &(dyn Fn(u32, u32) -> Option<Option<&'t [S]>> + Sync),
        stored: Option<&[S]>,
    ) -> Result<Made<S>> {
        let (grid, edge) = (self.grid, self.grid.edge());
        let (mut samples, taken) = if self.lod == 0 {
            // The interior as stored (or composited), the borders from the neighbours'
            // interiors.
            window(grid, 0, (x, y), 1, lookup)
        } else {
            let (wide, taken_wide) = window(grid, self.lod - 1, (x, y), 2, lookup);
            let side = 2 * edge;
            let mut out = Vec::with_capacity(edge * edge);
            for pair in wide.chunks_exact(2 * side) {
                let mut row = halve_rows(&pair[..side], &pair[side..]);
                self.tiles.quantize(&mut row);
                out.extend_from_slice(&row);
            }
            // A 2 x 2 block never straddles two tiles below (it starts on an even sample,
            // tiles on multiples of an even size): its first sample says.
            let taken = (0..edge * edge).map(|i| taken_wide[(i / edge) * 2 * side + (i % edge) * 2]).collect();
            (out, taken)
        };
        if let Some(stored) = stored {
            for ((v, &taken), &s) in samples.iter_mut().zip(&taken).zip(stored.iter()) {
                if !taken {
                    *v = s;
                }
            }
            // Remade as it is stored: the stored tile stays, nothing to encode.
            if samples.len() == stored.len() && samples.iter().zip(stored.iter()).all(|(a, b)| a.same(b)) {
                return Ok(((x, y), Some(Arc::new(samples)), Vec::new()));
            }
        }
        if !grid.interior_has_data(&samples) {
            return Ok(((x, y), None, Vec::new()));
        }
        let entries = self.tiles.encode(TileKey::new(grid.layer, self.lod, x, y)?, &samples)?;
        Ok(((x, y), Some(Arc::new(samples)), entries))
    }
}

/// The tiles of level `lod` that [`window`] reads for tile `(x, y)` of the level `scale`
/// times coarser.
#[expect(clippy::cast_possible_wrap, clippy::cast_possible_truncation, clippy::cast_sign_loss, reason = "tile indices")]
fn window_tiles(grid: &LayerGrid, lod: u8, (x, y): (u32, u32), scale: i64) -> Vec<(u32, u32)> {
    let (res, b) = (grid.res as i64, grid.border as i64);
    let side = scale * grid.edge() as i64;
    let (w, h) = grid.samples_at(lod);
    let (x0, y0) = (scale * (i64::from(x) * res - b), scale * (i64::from(y) * res - b));
    let range = |from: i64, limit: i64| (from.max(0) / res)..=((from + side - 1).min(limit - 1).max(0) / res);
    range(y0, h).flat_map(|ty| range(x0, w).map(move |tx| (tx as u32, ty as u32))).collect()
}

/// Does tile `x`'s window (its samples and borders, at the level below: `2 * (x * res -
/// border) .. 2 * ((x + 1) * res + border)`) reach the level below's tile `child`?
#[expect(clippy::cast_possible_wrap, reason = "a tile's samples")]
fn covers(grid: &LayerGrid, x: u32, child: u32) -> bool {
    let (res, b) = (grid.res as i64, grid.border as i64);
    let (from, to) = (2 * (i64::from(x) * res - b), 2 * ((i64::from(x) + 1) * res + b));
    let (c0, c1) = (i64::from(child) * res, (i64::from(child) + 1) * res);
    from < c1 && c0 < to
}

/// LOD-0 tiles whose 3 x 3 neighbourhood holds tiles of more than one input: some of the
/// tiles not from the first input and their neighbours.
fn mixed_neighbourhoods<S>(tiles: &dyn MergedTiles<S>, cols: u32, rows: u32) -> Vec<(u32, u32)> {
    let near = |x: u32, y: u32| {
        (y.saturating_sub(1)..=(y + 1).min(rows - 1))
            .flat_map(move |ny| (x.saturating_sub(1)..=(x + 1).min(cols - 1)).map(move |nx| (nx, ny)))
    };
    let candidates: HashSet<(u32, u32)> = at_lod(tiles.later(), 0).flat_map(|(x, y)| near(x, y)).collect();
    let mut out = Vec::new();
    for (x, y) in candidates {
        let Some(own) = tiles.source(0, x, y) else { continue };
        if near(x, y).any(|(nx, ny)| tiles.source(0, nx, ny).is_some_and(|s| s != own)) {
            out.push((x, y));
        }
    }
    out
}

/// The samples of level `lod` under tile (x, y) of the level `scale` times coarser, with
/// borders: `scale * edge` x `scale * edge`, starting at `scale * (x * res - border)`;
/// no data outside the level. `tile(tx, ty)` gives a level tile's samples (with borders)
/// when the window takes them: `Some(None)` for a tile that holds no data, `None` for one
/// it does not take. Also says which samples were taken (lie in a tile taken).
#[expect(
    clippy::cast_possible_truncation,
    clippy::cast_possible_wrap,
    clippy::cast_sign_loss,
    reason = "sample indices of one tile's window: small, and >= 0 where cast to usize"
)]
fn window<'t, S: Pixel>(
    grid: &LayerGrid,
    lod: u8,
    (x, y): (u32, u32),
    scale: i64,
    tile: &(dyn Fn(u32, u32) -> Option<Option<&'t [S]>> + Sync),
) -> (Vec<S>, Vec<bool>) {
    let (res, b, edge) = (grid.res as i64, grid.border as i64, grid.edge());
    let side = scale as usize * edge;
    let (w, h) = grid.samples_at(lod);
    let (x0, y0) = (scale * (i64::from(x) * res - b), scale * (i64::from(y) * res - b));
    let mut out = vec![S::NONE; side * side];
    let mut taken = vec![false; side * side];
    let tile_range = |from: i64, len: i64, limit: i64| {
        let first = from.max(0) / res;
        let last = (from + len - 1).min(limit - 1).max(0) / res;
        first..=last
    };
    for ty in tile_range(y0, side as i64, h) {
        for tx in tile_range(x0, side as i64, w) {
            let (Ok(ux), Ok(uy)) = (u32::try_from(tx), u32::try_from(ty)) else { continue };
            let Some(samples) = tile(ux, uy) else { continue };
            // The tile's interior, clipped to the window and the level, a row at a time.
            let (gx, gy) = (tx * res, ty * res);
            let (i0, i1) = ((x0 - gx).max(0), (x0 + side as i64 - gx).min(res).min(w - gx));
            let (j0, j1) = ((y0 - gy).max(0), (y0 + side as i64 - gy).min(res).min(h - gy));
            if i0 >= i1 {
                continue;
            }
            let len = (i1 - i0) as usize;
            for j in j0..j1 {
                let to = (gy + j - y0) as usize * side + (gx + i0 - x0) as usize;
                if let Some(mark) = taken.get_mut(to..to + len) {
                    mark.fill(true);
                }
                let from = (grid.border + j as usize) * edge + grid.border + i0 as usize;
                let src = samples.and_then(|s| s.get(from..from + len));
                if let (Some(src), Some(dst)) = (src, out.get_mut(to..to + len)) {
                    dst.copy_from_slice(src);
                }
            }
        }
    }
    (out, taken)
}
