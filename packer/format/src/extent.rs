//! Where a layer's data is (FORMAT.md §3.7): its coarsest populated LOD and its bounds.
//!
//! A pyramid need not reach up to one tile: an XYZ tree cut for a city holds zooms 10 to
//! 16 of a grid that is the whole Web Mercator world at zoom 0. Readers start the quadtree
//! at [`LayerExtent::coarsest_lod`], inside [`LayerExtent::world`], and frame the data's
//! bounds rather than the grid around it. Writers record the extent; for archives written
//! before it existed, [`ExtentBuilder`] derives it from the directory on open.

use serde::{Deserialize, Serialize};

use crate::key::TileKey;
use crate::metadata::{Georeference, Layer};

/// A layer's coarsest populated LOD and its data bounds.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct LayerExtent {
    /// The coarsest LOD holding at least one tile: readers start the quadtree here, never
    /// asking for an ancestor above it.
    pub coarsest_lod: u8,
    /// The finest LOD holding at least one tile.
    pub finest_lod: u8,
    /// The data's box in world units: min x, min z, max x, max z (x east, z south, from
    /// the north-west corner of tile (0, 0)). Every tile of the layer lies in it (a
    /// missing tile is drawn from the nearest coarser one, so a coarse tile's area is data).
    pub world: [f64; 4],
    /// Where the detail is: the box of the finest populated LOD's tiles (inside `world`).
    /// Views frame it: a regional tree's coarse tiles reach far beyond its data.
    pub detail: [f64; 4],
    /// The detail box in the archive's CRS (min x, min y, max x, max y), where the
    /// archive is georeferenced with an origin and scale.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub crs: Option<[f64; 4]>,
    /// The detail box's west, south, east, north in degrees, where the CRS is one a
    /// reader can invert (or the writer knew them).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub lon_lat: Option<[f64; 4]>,
    /// Levels that hold tiles only over part of the data (a collection's finer levels,
    /// made only where a fine enough input lies; docs/tiling.md, "Collections"): for each,
    /// rectangles of tiles outside which it holds none. Readers ask for no tile outside
    /// them: the nearest coarser tile stands there. Levels not listed may hold a tile
    /// anywhere over the data.
    #[serde(default, skip_serializing_if = "Vec::is_empty")]
    pub partial: Vec<LevelCover>,
}

/// Where a level of a [`LayerExtent`] holds tiles.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct LevelCover {
    /// The level.
    pub lod: u8,
    /// Rectangles of tiles: first column, first row, last column, last row (inclusive).
    pub tiles: Vec<[u32; 4]>,
    /// Each rectangle's west, south, east, north in degrees, where the writer knew them
    /// (what geographic tile schemes' availability is made from).
    #[serde(default, skip_serializing_if = "Vec::is_empty")]
    pub lon_lat: Vec<[f64; 4]>,
}

impl LayerExtent {
    /// The tiles at `lod` that overlap [`LayerExtent::world`], as inclusive column and row
    /// ranges `(x0, y0, x1, y1)`, clamped to the layer's grid.
    pub fn tile_range(&self, layer: &Layer, lod: u8) -> (u32, u32, u32, u32) {
        let size = layer.world_size_at(lod);
        let (nx, ny) = layer.grid_at(lod);
        let cell = |v: f64, n: u32| -> u32 {
            let t = (v / size).floor();
            if t.is_nan() || t <= 0.0 {
                0
            } else if t >= f64::from(n - 1) {
                n - 1
            } else {
                // In 0..n-1 (checked above).
                #[expect(clippy::cast_possible_truncation, clippy::cast_sign_loss, reason = "range checked above")]
                let t = t as u32;
                t
            }
        };
        // The far edges are exclusive: a box ending on a tile boundary does not reach the next.
        let [x0, z0, x1, z1] = self.world;
        let shrink = |v: f64| v - size * 1e-9;
        (cell(x0, nx), cell(z0, ny), cell(shrink(x1).max(x0), nx), cell(shrink(z1).max(z0), ny))
    }

    /// Fills [`LayerExtent::crs`] and [`LayerExtent::lon_lat`] from the georeference:
    /// the CRS box through its origin and scale; degrees for EPSG:4326 and EPSG:3857, which
    /// need no projection library. Other CRSs keep what the writer gave.
    pub fn georeference(&mut self, georeference: Option<&Georeference>) {
        let Some(g) = georeference else { return };
        let [x0, z0, x1, z1] = self.detail;
        let (Some((a, b)), Some((c, d))) = (g.world_to_crs(x0, z1), g.world_to_crs(x1, z0)) else { return };
        let crs = [a.min(c), b.min(d), a.max(c), b.max(d)];
        self.crs = Some(crs);
        match g.crs.as_deref() {
            Some("EPSG:4326" | "OGC:CRS84") => self.lon_lat = Some(crs),
            Some("EPSG:3857" | "EPSG:900913") => {
                let (w, s) = mercator_to_lon_lat(crs[0], crs[1]);
                let (e, n) = mercator_to_lon_lat(crs[2], crs[3]);
                self.lon_lat = Some([w, s, e, n]);
            }
            _ => {}
        }
    }
}

impl LayerExtent {
    /// Where the data of two parts of one layer is (shards, a coarse archive and its
    /// shards): the coarser start, the finer end, the boxes' union.
    #[must_use]
    pub fn union(&self, other: &Self) -> Self {
        let both = |a: Option<[f64; 4]>, b: Option<[f64; 4]>| a.zip(b).map(|(a, b)| union(a, b));
        Self {
            coarsest_lod: self.coarsest_lod.max(other.coarsest_lod),
            finest_lod: self.finest_lod.min(other.finest_lod),
            world: union(self.world, other.world),
            detail: union(self.detail, other.detail),
            crs: both(self.crs, other.crs),
            lon_lat: both(self.lon_lat, other.lon_lat),
            partial: union_covers(&self.partial, &other.partial),
        }
    }
}

/// Two parts' partial levels joined: a level partial in both keeps both's rectangles; a
/// level partial in only one is whole in the other, so whole in the join.
fn union_covers(a: &[LevelCover], b: &[LevelCover]) -> Vec<LevelCover> {
    (a.iter())
        .filter_map(|x| {
            let y = b.iter().find(|y| y.lod == x.lod)?;
            let lon_lat = if x.lon_lat.len() == x.tiles.len() && y.lon_lat.len() == y.tiles.len() {
                x.lon_lat.iter().chain(&y.lon_lat).copied().collect()
            } else {
                Vec::new()
            };
            // Each rectangle once (the shards of one run all record the run's).
            let mut tiles: Vec<[u32; 4]> = vec![];
            let mut degrees: Vec<[f64; 4]> = vec![];
            for (k, t) in x.tiles.iter().chain(&y.tiles).enumerate() {
                if !tiles.contains(t) {
                    tiles.push(*t);
                    if let Some(d) = lon_lat.get(k) {
                        degrees.push(*d);
                    }
                }
            }
            let lon_lat = if degrees.len() == tiles.len() { degrees } else { Vec::new() };
            Some(LevelCover { lod: x.lod, tiles, lon_lat })
        })
        .collect()
}

impl LayerExtent {
    /// The first level from which every level covers the layer's data (a collection's
    /// base); None where every level does.
    #[must_use]
    pub fn whole_from(&self) -> Option<u8> {
        self.partial.iter().map(|c| c.lod).max().map(|l| l + 1)
    }

    /// Whether tile (`x`, `y`) of level `lod` may be held: false only outside a partial
    /// level's rectangles.
    #[must_use]
    pub fn may_hold(&self, lod: u8, x: u32, y: u32) -> bool {
        self.partial
            .iter()
            .find(|c| c.lod == lod)
            .is_none_or(|c| c.tiles.iter().any(|r| (r[0]..=r[2]).contains(&x) && (r[1]..=r[3]).contains(&y)))
    }
}

/// Web Mercator metres to degrees (the spherical formula EPSG:3857 defines).
pub fn mercator_to_lon_lat(x: f64, y: f64) -> (f64, f64) {
    const R: f64 = 6_378_137.0;
    let lon = (x / R).to_degrees();
    let lat = (2.0 * (y / R).exp().atan() - std::f64::consts::FRAC_PI_2).to_degrees();
    (lon, lat)
}

/// The overlap of two boxes `[min x, min z, max x, max z]`, if they overlap.
pub fn intersect(a: [f64; 4], b: [f64; 4]) -> Option<[f64; 4]> {
    let r = [a[0].max(b[0]), a[1].max(b[1]), a[2].min(b[2]), a[3].min(b[3])];
    (r[0] < r[2] && r[1] < r[3]).then_some(r)
}

/// The smallest box holding both boxes.
pub fn union(a: [f64; 4], b: [f64; 4]) -> [f64; 4] {
    [a[0].min(b[0]), a[1].min(b[1]), a[2].max(b[2]), a[3].max(b[3])]
}

/// Accumulates a layer's extent from the tiles it holds, in any order: the box of all
/// its tiles and that of the finest LOD's, clipped to the layer's grid.
#[derive(Clone, Debug, Default)]
pub struct ExtentBuilder {
    /// Per LOD, tile columns and rows holding tiles: min x, min y, max x, max y (inclusive).
    lods: Vec<Option<[u32; 4]>>,
}

impl ExtentBuilder {
    /// Counts one tile of the layer.
    pub fn add(&mut self, tile: TileKey) {
        let lod = usize::from(tile.lod());
        if self.lods.len() <= lod {
            self.lods.resize(lod + 1, None);
        }
        let (x, y) = (tile.x(), tile.y());
        self.lods[lod] = Some(match self.lods[lod] {
            Some(r) => [r[0].min(x), r[1].min(y), r[2].max(x), r[3].max(y)],
            None => [x, y, x, y],
        });
    }

    /// The layer's extent, `None` if no tile was counted.
    pub fn finish(&self, layer: &Layer) -> Option<LayerExtent> {
        let (ex, ez) = layer.world_extent();
        let boxes: Vec<(u8, [f64; 4])> = self
            .lods
            .iter()
            .enumerate()
            .filter_map(|(lod, r)| {
                let (lod, r) = (u8::try_from(lod).ok()?, (*r)?);
                let size = layer.world_size_at(lod);
                let b = [
                    f64::from(r[0]) * size,
                    f64::from(r[1]) * size,
                    ((f64::from(r[2]) + 1.0) * size).min(ex),
                    ((f64::from(r[3]) + 1.0) * size).min(ez),
                ];
                Some((lod, b))
            })
            .collect();
        let (&(finest_lod, detail), &(coarsest_lod, _)) = (boxes.first()?, boxes.last()?);
        let world = boxes.iter().map(|b| b.1).reduce(union)?;
        Some(LayerExtent { coarsest_lod, finest_lod, world, detail, crs: None, lon_lat: None, partial: Vec::new() })
    }
}

impl ExtentBuilder {
    /// The extent a writer records for `layer` after counting its tiles: the LODs and box
    /// from the tiles, the box narrowed to the one the layer already gives (a tiler knows
    /// where its samples end inside the last tiles), the CRS and degree boxes from the
    /// georeference (degrees the layer gave are kept for other CRSs while its box stands).
    pub fn record(&self, layer: &Layer, georeference: Option<&Georeference>) -> Option<LayerExtent> {
        let mut extent = self.finish(layer)?;
        if let Some(given) = &layer.extent {
            if let Some(world) = intersect(extent.world, given.world) {
                extent.world = world;
            }
            if let Some(detail) = intersect(extent.detail, given.detail) {
                extent.detail = detail;
            }
            if extent.detail == given.detail {
                extent.lon_lat = given.lon_lat;
            }
            extent.partial.clone_from(&given.partial);
        }
        extent.georeference(georeference);
        Some(extent)
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::metadata::{LayerKind, PayloadCompression, TileFormat};

    fn layer() -> Layer {
        Layer {
            name: "texture".into(),
            kind: LayerKind::Texture,
            format: TileFormat::Png,
            compression: PayloadCompression::None,
            tile_resolution: 256,
            border: 0,
            num_x_tiles: 4096,
            num_y_tiles: 4096,
            num_lods: 13,
            tile_world_size: 10.0,
            elevation: None,
            extent: None,
        }
    }

    #[test]
    fn a_regional_pyramid_reports_its_finest_tiles_and_coarsest_level() {
        let mut b = ExtentBuilder::default();
        for (lod, x, y) in [(3, 20, 30), (2, 41, 60), (2, 40, 61), (1, 83, 121), (1, 82, 120), (1, 81, 122)] {
            b.add(TileKey::new(0, lod, x, y).unwrap());
        }
        let e = b.finish(&layer()).unwrap();
        assert_eq!((e.coarsest_lod, e.finest_lod), (3, 1));
        assert_eq!(e.detail, [1620.0, 2400.0, 1680.0, 2460.0]);
        assert_eq!(e.world, [1600.0, 2400.0, 1680.0, 2480.0], "the coarser tiles' area");
        assert_eq!(e.tile_range(&layer(), 3), (20, 30, 20, 30));
        assert!(ExtentBuilder::default().finish(&layer()).is_none());
    }

    #[test]
    fn coarse_tiles_beyond_the_fine_ones_are_data_but_not_detail() {
        // A world at LOD 10 (4 x 4 tiles) and a city at LOD 0.
        let mut b = ExtentBuilder::default();
        for i in 0..16 {
            b.add(TileKey::new(0, 10, i % 4, i / 4).unwrap());
        }
        b.add(TileKey::new(0, 0, 100, 200).unwrap());
        let e = b.finish(&layer()).unwrap();
        assert_eq!((e.coarsest_lod, e.finest_lod), (10, 0));
        assert_eq!(e.world, [0.0, 0.0, 40_960.0, 40_960.0]);
        assert_eq!(e.detail, [1000.0, 2000.0, 1010.0, 2010.0]);
    }

    #[test]
    fn web_mercator_bounds_come_back_in_degrees() {
        let mut e = LayerExtent {
            coarsest_lod: 0,
            finest_lod: 0,
            world: [0.0, 0.0, 1.0, 1.0],
            detail: [0.0, 0.0, 1.0, 1.0],
            crs: None,
            lon_lat: None,
            partial: Vec::new(),
        };
        let half = 20_037_508.342_789_244;
        let g = Georeference {
            crs: Some("EPSG:3857".into()),
            origin: Some([-half, half]),
            scale: Some([2.0 * half, 2.0 * half]),
            ..Georeference::default()
        };
        e.georeference(Some(&g));
        let [w, s, east, n] = e.lon_lat.unwrap();
        assert!((w + 180.0).abs() < 1e-9 && (east - 180.0).abs() < 1e-9, "{w} {east}");
        assert!((n - 85.051_128_78).abs() < 1e-6 && (s + 85.051_128_78).abs() < 1e-6, "{s} {n}");
    }
}
