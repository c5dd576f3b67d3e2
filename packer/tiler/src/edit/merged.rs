//! One layer of a merge as [`crate::edit::rederive`] sees it ([`MergedTiles`]): where
//! each tile comes from, its stored version decoded, a remade one encoded; for heights
//! (with the height ranges under remade tiles) and for lossless imagery.

use std::collections::{BTreeMap, HashSet};

use terrastream_format::{Metadata, MmapSource, Reader, TileKey};
use terrastream_pack::Writer;

use crate::edit::merge::{Conflicts, Found, Prefer, payload, range_of, unpacked};
use crate::edit::rederive::{MergedTiles, Remade};
use crate::encode::{decode_heights, decode_texture, encode_texture, quantize_heights};
use crate::error::Result;
use crate::options::TextureFormat;
use crate::tile::{HeightEncoder, ZSTD_LEVEL};

/// One layer of a merge: where its tiles come from and their stored bytes.
pub(crate) struct MergeLayer<'a> {
    pub(crate) metadata: &'a Metadata,
    pub(crate) readers: &'a [Reader<MmapSource>],
    pub(crate) winners: &'a BTreeMap<u64, Found>,
    pub(crate) all_conflicts: &'a Conflicts,
    pub(crate) prefer: Prefer,
    pub(crate) index: u8,
    /// This layer's tiles two or more inputs hold.
    pub(crate) conflicts: HashSet<TileKey>,
    /// This layer's tiles not from the first input.
    pub(crate) later: HashSet<TileKey>,
}

impl MergeLayer<'_> {
    fn source(&self, lod: u8, x: u32, y: u32) -> Option<usize> {
        let key = TileKey::new(self.index, lod, x, y).ok()?;
        self.winners.get(&Writer::order_key(self.metadata, key).ok()?).map(|f| f.input)
    }

    /// The winning input's bytes of tile (lod, x, y) of this layer, compression undone.
    fn payload(&self, key: TileKey) -> Result<Option<Vec<u8>>> {
        payload(self.metadata, self.readers, self.winners, key)
    }

    /// With `--prefer pixels`, version `i` of an LOD-0 tile several inputs hold, newest
    /// first, as stored (compression undone).
    fn version(&self, x: u32, y: u32, i: usize) -> Option<Result<Option<Stored>>> {
        if self.prefer != Prefer::Pixels {
            return None;
        }
        let found = || -> Result<Option<Stored>> {
            let key = TileKey::new(self.index, 0, x, y)?;
            let versions =
                self.all_conflicts.get(&Writer::order_key(self.metadata, key)?).map_or(&[][..], Vec::as_slice);
            versions.iter().rev().nth(i).map(|&found| Ok((key, unpacked(self.readers, key, found)?))).transpose()
        };
        Some(found())
    }
}

/// A tile and its stored bytes (compression undone).
type Stored = (TileKey, Vec<u8>);

/// An elevation layer of a merge: heights decoded and encoded as the layer stores them.
pub(crate) struct MergedHeights<'a> {
    pub(crate) merged: MergeLayer<'a>,
    pub(crate) encoder: HeightEncoder,
}

impl MergedTiles<f32> for MergedHeights<'_> {
    fn source(&self, lod: u8, x: u32, y: u32) -> Option<usize> {
        self.merged.source(lod, x, y)
    }
    fn conflicts(&self) -> &HashSet<TileKey> {
        &self.merged.conflicts
    }
    fn later(&self) -> &HashSet<TileKey> {
        &self.merged.later
    }
    fn decode(&self, lod: u8, x: u32, y: u32) -> Result<Option<Vec<f32>>> {
        let key = TileKey::new(self.merged.index, lod, x, y)?;
        Ok(self.merged.payload(key)?.map(|raw| decode_heights(&raw, &self.encoder.encoding)))
    }
    fn encode(&self, key: TileKey, samples: &[f32]) -> Result<Vec<(TileKey, Vec<u8>)>> {
        self.encoder.encode(key, samples)
    }
    fn quantize(&self, row: &mut [f32]) {
        quantize_heights(row, &self.encoder.encoding);
    }
    fn version(&self, x: u32, y: u32, i: usize) -> Option<Result<Option<Vec<f32>>>> {
        let version = self.merged.version(x, y, i)?;
        Some(version.map(|v| v.map(|(_, raw)| decode_heights(&raw, &self.encoder.encoding))))
    }
}

impl MergedHeights<'_> {
    /// The height ranges of the remade tiles' children that were not remade (they widen
    /// the remade tiles' ranges); the range tiles of emptied tiles go into `emptied`.
    pub(crate) fn ranges_below(
        &self,
        remade: &Remade,
        range: Option<u8>,
        emptied: &mut Vec<u64>,
    ) -> Result<Vec<(TileKey, f32, f32)>> {
        let Some(r) = range else { return Ok(Vec::new()) };
        let m = &self.merged;
        let layer = &m.metadata.layers[usize::from(m.index)];
        let made: HashSet<TileKey> =
            remade.entries.iter().map(|(k, _)| *k).chain(remade.emptied.iter().copied()).collect();
        let mut below = Vec::new();
        for key in made.iter().filter(|k| k.lod() > 0) {
            for (cx, cy) in [(0, 0), (1, 0), (0, 1), (1, 1)] {
                let (lod, x, y) = (key.lod() - 1, 2 * key.x() + cx, 2 * key.y() + cy);
                if x >= layer.num_x_tiles.div_ceil(1 << lod) || y >= layer.num_y_tiles.div_ceil(1 << lod) {
                    continue;
                }
                let child = TileKey::new(m.index, lod, x, y)?;
                if made.contains(&child) {
                    continue;
                }
                let bytes = m.payload(TileKey::new(r, child.lod(), child.x(), child.y())?)?;
                if let Some((lo, hi)) = bytes.as_deref().and_then(range_of) {
                    below.push((child, lo, hi));
                }
            }
        }
        for key in &remade.emptied {
            emptied.push(Writer::order_key(m.metadata, TileKey::new(r, key.lod(), key.x(), key.y())?)?);
        }
        Ok(below)
    }
}

/// A texture layer of a merge (PNG or WebP tiles: lossless, decoded and encoded again).
pub(crate) struct MergedTexture<'a> {
    pub(crate) merged: MergeLayer<'a>,
    pub(crate) format: TextureFormat,
    pub(crate) edge: usize,
}

impl MergedTiles<[u8; 4]> for MergedTexture<'_> {
    fn source(&self, lod: u8, x: u32, y: u32) -> Option<usize> {
        self.merged.source(lod, x, y)
    }
    fn conflicts(&self) -> &HashSet<TileKey> {
        &self.merged.conflicts
    }
    fn later(&self) -> &HashSet<TileKey> {
        &self.merged.later
    }
    fn decode(&self, lod: u8, x: u32, y: u32) -> Result<Option<Vec<[u8; 4]>>> {
        let key = TileKey::new(self.merged.index, lod, x, y)?;
        self.merged.payload(key)?.map(|bytes| decode_texture(key, &bytes, self.edge, self.format)).transpose()
    }
    fn encode(&self, key: TileKey, pixels: &[[u8; 4]]) -> Result<Vec<(TileKey, Vec<u8>)>> {
        Ok(vec![(key, encode_texture(key, pixels, self.edge, self.format, ZSTD_LEVEL)?)])
    }
    fn version(&self, x: u32, y: u32, i: usize) -> Option<Result<Option<Vec<[u8; 4]>>>> {
        let version = self.merged.version(x, y, i)?;
        Some(
            version.and_then(|v| v.map(|(key, bytes)| decode_texture(key, &bytes, self.edge, self.format)).transpose()),
        )
    }
}
