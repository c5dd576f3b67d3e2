//! Tile addressing: [`TileKey`] (layer, lod, x, y) and its position on the archive's
//! space-filling curve (the directory key).
//!
//! The directory key of a tile is `tile_id * 16 + layer`, where `tile_id` is the PMTiles v3
//! tile id of the tile on its layer's pyramid, with web zoom `z = num_lods - 1 - lod`:
//! coarsest LOD first, Hilbert order inside a LOD, and the layers of one place side by side.

use std::fmt;

use crate::error::{Error, Result};

/// At most this many layers per archive (the key reserves 4 bits for the layer).
pub const MAX_LAYERS: usize = 16;
/// At most this many LODs per layer: z = 0..=28 keeps `tile_id * 16` inside u64.
pub const MAX_LODS: u8 = 29;

/// One tile: layer index, LOD (0 = finest), x to the east, y to the south.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash, PartialOrd, Ord)]
pub struct TileKey {
    layer: u8,
    lod: u8,
    x: u32,
    y: u32,
}

impl TileKey {
    /// A tile key, checked against the limits of the format (not yet against a layer's grid).
    ///
    /// # Errors
    /// [`Error::InvalidTile`] if the layer, LOD or coordinates exceed the format's limits.
    pub fn new(layer: u8, lod: u8, x: u32, y: u32) -> Result<Self> {
        if usize::from(layer) >= MAX_LAYERS || lod >= MAX_LODS || x >= 1 << 28 || y >= 1 << 28 {
            return Err(Error::InvalidTile {
                what: format!("layer {layer} lod {lod} ({x}, {y}): beyond the format's limits"),
            });
        }
        Ok(Self { layer, lod, x, y })
    }

    /// Layer index (position in the metadata's layer list).
    pub fn layer(self) -> u8 {
        self.layer
    }
    /// LOD, 0 = finest.
    pub fn lod(self) -> u8 {
        self.lod
    }
    /// Column, 0 = west.
    pub fn x(self) -> u32 {
        self.x
    }
    /// Row, 0 = north.
    pub fn y(self) -> u32 {
        self.y
    }

    /// The tile one LOD coarser that covers this one, if any.
    pub fn parent(self) -> Option<Self> {
        let lod = self.lod.checked_add(1).filter(|&l| l < MAX_LODS)?;
        Some(Self { layer: self.layer, lod, x: self.x / 2, y: self.y / 2 })
    }

    /// Directory key of this tile in a layer whose quadtree has `depth` levels
    /// (LOD `depth - 1` is 1x1; see [`crate::Layer::depth`]).
    ///
    /// # Errors
    /// [`Error::InvalidTile`] if the LOD is not below `depth` or the coordinates do not fit
    /// the LOD's `2^z x 2^z` quadtree level.
    pub fn archive_key(self, depth: u8) -> Result<u64> {
        if self.lod >= depth || depth > MAX_LODS {
            return Err(Error::InvalidTile { what: format!("{self}: layer quadtree has {depth} levels") });
        }
        let z = depth - 1 - self.lod;
        if u64::from(self.x) >= 1 << z || u64::from(self.y) >= 1 << z {
            return Err(Error::InvalidTile { what: format!("{self}: outside the 2^{z} quadtree level") });
        }
        Ok(zxy_to_tile_id(z, self.x, self.y) * MAX_LAYERS as u64 + u64::from(self.layer))
    }

    /// The tile of a directory key, given the quadtree depth of each layer.
    ///
    /// # Errors
    /// [`Error::InvalidTile`] if the key names an unknown layer or a level beyond its depth.
    pub fn from_archive_key(key: u64, depth_per_layer: &[u8]) -> Result<Self> {
        let layer = layer_of(key);
        let num_lods = *depth_per_layer
            .get(usize::from(layer))
            .ok_or_else(|| Error::InvalidTile { what: format!("key {key}: unknown layer {layer}") })?;
        let (z, x, y) = tile_id_to_zxy(key / MAX_LAYERS as u64);
        if z >= num_lods {
            return Err(Error::InvalidTile {
                what: format!("key {key}: z {z} beyond layer {layer}'s {num_lods} LODs"),
            });
        }
        Self::new(layer, num_lods - 1 - z, x, y)
    }
}

impl fmt::Display for TileKey {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        write!(f, "layer {} lod {} x {} y {}", self.layer, self.lod, self.x, self.y)
    }
}

/// Layer index of a directory key (its low 4 bits).
#[expect(clippy::cast_possible_truncation, reason = "a remainder modulo 16")]
pub fn layer_of(key: u64) -> u8 {
    (key % MAX_LAYERS as u64) as u8
}

/// Number of tiles in all quadtree levels above `z`: (4^z - 1) / 3.
pub(crate) fn level_base(z: u8) -> u64 {
    ((1u64 << (2 * u32::from(z))) - 1) / 3
}

fn rotate(n: u64, x: &mut u64, y: &mut u64, rx: u64, ry: u64) {
    if ry == 0 {
        if rx == 1 {
            *x = n - 1 - *x;
            *y = n - 1 - *y;
        }
        std::mem::swap(x, y);
    }
}

/// PMTiles v3 tile id: the tiles of all coarser levels, plus the Hilbert index inside level z.
pub fn zxy_to_tile_id(z: u8, x: u32, y: u32) -> u64 {
    let mut d = 0u64;
    let (mut tx, mut ty) = (u64::from(x), u64::from(y));
    let n = 1u64 << z;
    let mut s = n / 2;
    while s > 0 {
        let rx = u64::from(tx & s > 0);
        let ry = u64::from(ty & s > 0);
        d += s * s * ((3 * rx) ^ ry);
        rotate(n, &mut tx, &mut ty, rx, ry);
        s /= 2;
    }
    level_base(z) + d
}

/// Inverse of [`zxy_to_tile_id`]. Total for any id below the level base of z = 32.
#[expect(clippy::cast_possible_truncation, reason = "x and y are below 2^z <= 2^31")]
pub fn tile_id_to_zxy(id: u64) -> (u8, u32, u32) {
    let mut z = 0u8;
    while z < 31 && id >= level_base(z + 1) {
        z += 1;
    }
    let mut t = id - level_base(z);
    let n = 1u64 << z;
    let (mut x, mut y) = (0u64, 0u64);
    let mut s = 1u64;
    while s < n {
        let rx = 1 & (t / 2);
        let ry = 1 & (t ^ rx);
        rotate(s, &mut x, &mut y, rx, ry);
        x += s * rx;
        y += s * ry;
        t /= 4;
        s *= 2;
    }
    (z, x as u32, y as u32)
}

#[cfg(test)]
mod tests {
    use proptest::prelude::*;

    use super::*;

    #[test]
    fn matches_pmtiles_reference_ids() {
        // Values from the PMTiles v3 specification's test suite.
        assert_eq!(zxy_to_tile_id(0, 0, 0), 0);
        assert_eq!(zxy_to_tile_id(1, 0, 0), 1);
        assert_eq!(zxy_to_tile_id(1, 0, 1), 2);
        assert_eq!(zxy_to_tile_id(1, 1, 1), 3);
        assert_eq!(zxy_to_tile_id(1, 1, 0), 4);
        assert_eq!(zxy_to_tile_id(2, 0, 0), 5);
        assert_eq!(zxy_to_tile_id(12, 3423, 1763), 19_078_479);
    }

    #[test]
    fn coarse_lods_come_first() {
        let fine = TileKey::new(0, 0, 0, 0).unwrap().archive_key(4).unwrap();
        let coarse = TileKey::new(0, 1, 3, 3).unwrap().archive_key(4).unwrap();
        assert!(coarse < fine);
    }

    #[test]
    fn rejects_tiles_outside_their_level() {
        assert!(TileKey::new(0, 0, 8, 0).unwrap().archive_key(4).is_err());
        assert!(TileKey::new(0, 4, 0, 0).unwrap().archive_key(4).is_err());
        assert!(TileKey::new(16, 0, 0, 0).is_err());
        assert!(TileKey::new(0, 29, 0, 0).is_err());
    }

    proptest! {
        #[test]
        fn key_round_trips(layer in 0u8..16, z in 0u8..29, xs in any::<u32>(), ys in any::<u32>()) {
            let side = 1u32 << z;
            let (x, y) = (xs % side, ys % side);
            let num_lods = 29u8;
            let key = TileKey::new(layer, num_lods - 1 - z, x, y).unwrap();
            let encoded = key.archive_key(num_lods).unwrap();
            let lods = [num_lods; 16];
            prop_assert_eq!(TileKey::from_archive_key(encoded, &lods).unwrap(), key);
        }

        #[test]
        fn arbitrary_keys_never_panic(key in any::<u64>()) {
            let _ = TileKey::from_archive_key(key, &[29u8; 16]);
        }
    }
}
