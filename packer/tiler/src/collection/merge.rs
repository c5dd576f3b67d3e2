//! Merging the shards of a collection split finer than its base (docs/tiling.md,
//! "Shards"): the shards hold every level up to their split LOD K in their bands; the
//! levels from K + 1 up are made here as a run with every input makes them, from the
//! level-K tiles as stored (the means a coarser level takes where they lie: a run takes
//! them only over the tiles it stores, so the stored tiles are all it needs) and the
//! inputs as deep as those levels (the surveys between K and the base, and the base's).

use std::path::{Path, PathBuf};

use rayon::prelude::*;
use terrastream_format::{LayerKind, Metadata, TileKey};
use terrastream_pack::progress::Progress;

use super::{Blend, Collection, Cut, Override};
use crate::encode::{decode_heights, decode_texture, encode_texture, quantize_heights};
use crate::error::{Error, Result};
use crate::options::TextureFormat;
use crate::pyramid::{Pixel, Spool, halve_rows};
use crate::raster::{DatumName, GridSpec, Heights, Mosaic, MosaicKind};
use crate::tile::HeightEncoder;

/// A merged tile's payload (its compression undone), None where no shard holds it.
pub(crate) type Payload<'a> = dyn Fn(TileKey) -> Result<Option<Vec<u8>>> + Sync + 'a;

/// The inputs of the run whose shards are merged: as `tile` took them, or as its shard
/// plan records them.
#[derive(Clone, Copy, Debug, Default)]
pub struct RunInputs<'a> {
    /// `--elevation`.
    pub elevation: &'a [PathBuf],
    /// `--texture`.
    pub texture: &'a [PathBuf],
    /// The run's shard plan's collections: with them the merge opens only the inputs it
    /// reads (those deeper than the split), at their recorded paths under `root`.
    pub planned: &'a [super::PlannedCollection],
    /// The folder the plan's paths are under (None: as recorded).
    pub root: Option<&'a Path>,
}

/// A collection layer's base level, as `metadata` records it (the first that covers the
/// grid): None for a layer of one resolution.
pub(crate) fn recorded_base(metadata: &Metadata, index: usize) -> Option<u8> {
    metadata.layers.get(index)?.extent.as_ref()?.whole_from()
}

/// Whether the merge of shards split at `split_lods` makes layer `index`'s levels above
/// the split here (a collection's layer, or its height ranges, split below its base).
pub(crate) fn made_here(metadata: &Metadata, split_lods: &[u8], index: usize) -> bool {
    let kind = metadata.layers[index].kind;
    let of = match kind {
        LayerKind::HeightRange => metadata.layers.iter().position(|l| l.kind == LayerKind::Elevation),
        LayerKind::Elevation | LayerKind::Texture => Some(index),
        _ => None,
    };
    of.is_some_and(|i| recorded_base(metadata, i).is_some_and(|b| split_lods.get(i).is_some_and(|&k| k < b)))
}

/// Widens the extents the merge of shards split at `split_lods` records for the layers
/// it makes above the split ([`made_here`]) to their whole data, as a run gives its
/// writer: those shards hold only the surveys' levels, and a shard that holds none of
/// them records no extent, so the union of theirs is the surveys' box, and the writer,
/// which narrows the box its tiles cover to the one it is given, recorded the base's
/// levels as if they ended there (the data's box a reader draws and serves within).
///
/// # Errors
/// As [`super::update::layer_grid`].
pub(crate) fn widen_to_the_data(metadata: &mut Metadata, split_lods: &[u8], named: &Path) -> Result<()> {
    for index in 0..metadata.layers.len() {
        if !made_here(metadata, split_lods, index) {
            continue;
        }
        let layer = &metadata.layers[index];
        // Where a run's plan says the layer's samples end (see `plan`).
        let (w, h) = match (layer.kind, metadata.terrain.data_extent) {
            (LayerKind::Elevation | LayerKind::HeightRange, Some([w, h])) => (w, h),
            _ => {
                let (grid, _, _) = super::update::layer_grid(metadata, named, u8::try_from(index).unwrap_or(u8::MAX))?;
                let texel = layer.sample_spacing(0);
                (f64::from(grid.size.0) * texel, f64::from(grid.size.1) * texel)
            }
        };
        if let Some(extent) = metadata.layers[index].extent.as_mut() {
            extent.world = terrastream_format::union(extent.world, [0.0, 0.0, w, h]);
        }
    }
    Ok(())
}

/// Warns that the run's `inputs` given to a merge are not read: none of `metadata`'s
/// layers, merged from shards split at `split_lods` (None: not shards), is a collection
/// split finer than its base, the one merge that reads them.
pub(crate) fn warn_unread(metadata: &Metadata, split_lods: Option<&[u8]>, inputs: &RunInputs<'_>) {
    let given = !(inputs.elevation.is_empty() && inputs.texture.is_empty());
    let read = split_lods.is_some_and(|s| (0..metadata.layers.len()).any(|i| made_here(metadata, s, i)));
    if given && !read {
        tracing::warn!(
            "the inputs given are not read: only the shards of a collection split finer than its base take them"
        );
    }
}

/// Makes the levels above the split of every collection layer of `metadata` split below
/// its base ([`made_here`]) into `spool`, from the merged shards'
/// tiles (`payload`) and the run's `inputs`. `named`: the archive errors name.
///
/// # Errors
/// [`Error::Input`] naming `named` when such a layer's inputs are not given, or make
/// other levels than the shards' run did (other inputs); the inputs' and the tiles'
/// errors.
pub(crate) fn make_above_split(
    metadata: &Metadata,
    split_lods: &[u8],
    inputs: RunInputs<'_>,
    payload: &Payload<'_>,
    named: &Path,
    spool: &mut Spool,
    progress: &dyn Progress,
) -> Result<()> {
    let find = |kind: LayerKind| metadata.layers.iter().position(|l| l.kind == kind).and_then(|i| u8::try_from(i).ok());
    warn_unread(metadata, Some(split_lods), &inputs);
    for (index, layer) in metadata.layers.iter().enumerate() {
        if !matches!(layer.kind, LayerKind::Elevation | LayerKind::Texture) || !made_here(metadata, split_lods, index) {
            continue;
        }
        let index = u8::try_from(index).map_err(|_| Error::NothingToTile)?;
        let k = split_lods[usize::from(index)];
        let (grid, crs, base) = super::update::layer_grid(metadata, named, index)?;
        let texture = layer.kind == LayerKind::Texture;
        let (flag, paths) = if texture { ("--texture", inputs.texture) } else { ("--elevation", inputs.elevation) };
        let planned = inputs.planned.iter().find(|p| p.kind == layer.kind);
        if paths.is_empty() && planned.is_none() {
            return Err(Error::input(
                named,
                format!(
                    "its layer {:?} is a collection whose shards hold LOD 0 to {k}, finer than its base (LOD {base}): \
                     the merge makes LOD {} up from their tiles and the run's inputs, so give it those ({flag} FILE…, \
                     or the run's --shard-plan)",
                    layer.name,
                    k + 1
                ),
            ));
        }
        // With the plan: the inputs deeper than the split, where it records them.
        let deeper: Vec<PathBuf> = planned
            .map(|p| p.inputs.iter().filter(|i| i.depth > k))
            .into_iter()
            .flatten()
            .map(|i| inputs.root.map_or_else(|| i.path.clone(), |r| r.join(&i.path)))
            .collect();
        if let Some(missing) = deeper.iter().find(|p| !p.is_file()) {
            return Err(Error::input(
                missing,
                "the merge of these shards reads it (the plan's merge.txt lists it): fetch it into the folder \
                 --inputs names",
            ));
        }
        let planned = match planned {
            Some(p) => Some(Collection::from_planned(p, metadata, grid, &deeper)?),
            None => None,
        };
        let stand = Stand { metadata, index, k, named, payload };
        if texture {
            let format = TextureFormat::decodable(layer.format).ok_or_else(|| Error::Pyramid {
                layer: index,
                lod: k,
                reason: format!("{:?} tiles are lossy: shards need png or webp", layer.format),
            })?;
            let open = |paths: Vec<PathBuf>, grid: GridSpec| super::open_images(paths, grid, &crs, false);
            let c = match planned {
                Some(c) => stand.same(c, base)?,
                None => stand.collection(open(paths.to_vec(), grid)?.as_ref(), base)?,
            };
            let edge = (layer.tile_resolution + 2 * u32::from(layer.border)) as usize;
            let decode = |key: TileKey, raw: &[u8]| decode_texture(key, raw, edge, format);
            let means = stand.means(&c, &decode, None)?;
            let encode_tile = |key: TileKey, pixels: &[[u8; 4]], edge: usize| -> Result<Vec<(TileKey, Vec<u8>)>> {
                Ok(vec![(key, encode_texture(key, pixels, edge, format, crate::tile::ZSTD_LEVEL)?)])
            };
            super::cut_levels(&c, metadata, index, &open, &encode_tile, None, spool, progress, means)?;
        } else {
            let datum = DatumName::of_record(&metadata.vertical_datum);
            let range = (metadata.terrain.min_elevation, metadata.terrain.max_elevation);
            #[expect(clippy::cast_possible_truncation, reason = "heights are f32")]
            let range = ((range.0 as f32).next_down(), (range.1 as f32).next_up());
            let open = |paths: Vec<PathBuf>, grid: GridSpec| -> Result<Option<Mosaic<Heights>>> {
                let request = crate::TileRequest {
                    height_range: Some(range),
                    ..super::heights_on(paths, grid, &crs, datum.as_ref(), None)
                };
                super::open_heights(&request)
            };
            let c = match planned {
                Some(c) => stand.same(c, base)?,
                None => stand.collection(open(paths.to_vec(), grid)?.as_ref(), base)?,
            };
            let heights = HeightEncoder::new(metadata, index, find(LayerKind::HeightRange))?;
            let encoding = heights.encoding;
            let quantize = move |row: &mut [f32]| quantize_heights(row, &encoding);
            let decode = |_: TileKey, raw: &[u8]| Ok(decode_heights(raw, &encoding));
            let means = stand.means(&c, &decode, Some(&quantize))?;
            let encode_tile = |key: TileKey, samples: &[f32], _edge: usize| heights.encode(key, samples);
            let q: &super::QuantizeRow<'_, f32> = &quantize;
            super::cut_levels(&c, metadata, index, &open, &encode_tile, Some(q), spool, progress, means)?;
            // The split level's ranges (the shards') widen those above them.
            let below = match find(LayerKind::HeightRange) {
                Some(r) => {
                    let held = c.levels[usize::from(k)].tiles.iter().copied();
                    crate::edit::merge::split_ranges(payload, (index, r), k, held)?
                }
                None => Vec::new(),
            };
            heights.finish(metadata, below, spool)?;
        }
    }
    Ok(())
}

/// A layer whose levels above split LOD `k` are made from the merged tiles.
struct Stand<'a> {
    metadata: &'a Metadata,
    index: u8,
    k: u8,
    named: &'a Path,
    payload: &'a Payload<'a>,
}

impl Stand<'_> {
    /// The collection of the run's inputs (`mosaic`, on the layer's grid) as the shards'
    /// run planned it: refused where its base or levels differ from those recorded.
    fn collection<K: MosaicKind>(&self, mosaic: Option<&Mosaic<K>>, base: u8) -> Result<Collection> {
        let layer = &self.metadata.layers[usize::from(self.index)];
        let recorded = (self.metadata.sources.iter())
            .filter(|s| (s.layer.as_deref() == Some("texture")) == (layer.kind == LayerKind::Texture))
            .find_map(|s| s.blend);
        let blend = Blend::Samples(recorded.unwrap_or(super::DEFAULT_BLEND));
        match mosaic.and_then(|m| Collection::plan(m, self.metadata, layer.kind, blend)) {
            Some(c) => self.same(c, base),
            None => Err(self.other(base)),
        }
    }

    /// `c`, when its inputs (their names, in order: the later wins among inputs as deep),
    /// base and levels are those the shards record; else refused.
    fn same(&self, c: Collection, base: u8) -> Result<Collection> {
        let layer = &self.metadata.layers[usize::from(self.index)];
        let covers = layer.extent.as_ref().map(|e| e.partial.as_slice()).unwrap_or_default();
        let texture = layer.kind == LayerKind::Texture;
        let recorded = (self.metadata.sources.iter())
            .filter(|s| (s.layer.as_deref() == Some("texture")) == texture)
            .map(|s| s.name.as_str());
        let names = c.inputs.iter().map(|i| i.path.file_name().and_then(|n| n.to_str()).unwrap_or_default());
        let same = c.base == base
            && names.eq(recorded)
            && (c.levels.iter().filter(|l| !l.cover.is_empty()))
                .map(|l| (l.lod, l.cover.clone()))
                .eq(covers.iter().map(|c| (c.lod, c.tiles.clone())));
        if same { Ok(c) } else { Err(self.other(base)) }
    }

    fn other(&self, base: u8) -> Error {
        let layer = &self.metadata.layers[usize::from(self.index)];
        Error::input(
            self.named,
            format!(
                "the inputs given for layer {:?} are not the shards' run's (the same files, in the same order: the \
                 run's base LOD {base}, and finer levels where its surveys lie): give the merge the run's inputs",
                layer.name
            ),
        )
    }

    /// Level `k`'s means, a row of its tiles at a time, as a run hands them to the level
    /// above (`quantize`d as stored), from its tiles as the shards stored them.
    fn means<S: Pixel + Send + Sync>(
        &self,
        c: &Collection,
        decode: &super::update::Decode<'_, S>,
        quantize: Option<&super::QuantizeRow<'_, S>>,
    ) -> Result<Cut<'static, S>> {
        let layer = &self.metadata.layers[usize::from(self.index)];
        let (res, border) = (layer.tile_resolution as usize, usize::from(layer.border));
        let edge = res + 2 * border;
        let level = &c.levels[usize::from(self.k)];
        let (width, height) = (c.level_grid(self.k).size.0 as usize, c.level_grid(self.k).size.1 as usize);
        let mut rows: std::collections::BTreeMap<u32, Vec<u32>> = std::collections::BTreeMap::new();
        for &(x, y) in &level.tiles {
            rows.entry(y).or_default().push(x);
        }
        let mut means = Vec::with_capacity(rows.len());
        for (ty, xs) in rows {
            let (first, last) = (xs.iter().copied().min().unwrap_or(0), xs.iter().copied().max().unwrap_or(0));
            let tiles: Vec<Option<Vec<S>>> = (first..=last)
                .into_par_iter()
                .map(|tx| {
                    let key = TileKey::new(self.index, self.k, tx, ty)?;
                    if !level.tiles.contains(&(tx, ty)) {
                        return Ok(None);
                    }
                    (self.payload)(key)?.map(|raw| decode(key, &raw)).transpose()
                })
                .collect::<Result<_>>()?;
            let x0 = first as usize * res;
            let x1 = ((last as usize + 1) * res).min(width);
            let y0 = ty as usize * res;
            let row = |j: usize| -> Vec<S> {
                let mut out = vec![S::NONE; x1 - x0];
                for (i, tile) in tiles.iter().enumerate() {
                    let (a, b) = (i * res, ((i + 1) * res).min(x1 - x0));
                    let from = (border + j) * edge + border;
                    if let Some(src) = tile.as_ref().and_then(|t| t.get(from..from + (b - a))) {
                        out[a..b].copy_from_slice(src);
                    }
                }
                out
            };
            let down = res.min(height.saturating_sub(y0));
            let mut halves = Vec::with_capacity(down.div_ceil(2));
            for j in (0..down).step_by(2) {
                let b = if j + 1 < down { row(j + 1) } else { vec![S::NONE; x1 - x0] };
                let mut half = halve_rows(&row(j), &b);
                if let Some(q) = quantize {
                    q(&mut half);
                }
                halves.push(half);
            }
            // Only the held tiles' samples have data here, so the means are those a run
            // keeps (`Override::keep_held`) without more ado.
            means.push(Override { x0: x0 / 2, y0: y0 / 2, rows: halves });
        }
        Ok(Cut::Above(self.k, means))
    }
}
