//! The Web Mercator XYZ grid (EPSG:3857, the grid of OSM, Google and every web map):
//! tile `(z, x, y)` covers 1/2^z of the world's width, `y` counted from the north.

use std::f64::consts::PI;

/// Half the world's width in metres (the sphere of radius 6 378 137 m).
pub const HALF_WORLD: f64 = 20_037_508.342_789_244;

/// The latitude beyond which the grid does not go (atan(sinh(pi)), in degrees).
pub const MAX_LATITUDE: f64 = 85.051_128_779_806_59;

/// A tile of the grid.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash)]
pub struct WebTile {
    /// Zoom level (0: one tile for the world).
    pub z: u8,
    /// Column, from the west.
    pub x: u32,
    /// Row, from the north.
    pub y: u32,
}

impl WebTile {
    /// The tile, when `x` and `y` lie in the grid of zoom `z` (at most 30).
    pub fn new(z: u8, x: u32, y: u32) -> Option<Self> {
        let n = 1u64 << z.min(31);
        (z <= 30 && u64::from(x) < n && u64::from(y) < n).then_some(Self { z, x, y })
    }

    /// Tiles across (and down) at this zoom.
    pub fn count(self) -> f64 {
        f64::from(1u32 << self.z)
    }

    /// Longitude and latitude (degrees) of a point given in tile pixels: `(u, v)` from
    /// the tile's north-west corner, `size` pixels a side.
    pub fn lon_lat(self, u: f64, v: f64, size: f64) -> (f64, f64) {
        let n = self.count();
        let (fx, fy) = ((f64::from(self.x) + u / size) / n, (f64::from(self.y) + v / size) / n);
        (fx * 360.0 - 180.0, (PI * (1.0 - 2.0 * fy)).sinh().atan().to_degrees())
    }

    /// The tile's west, south, east and north edges in degrees.
    pub fn bounds(self) -> [f64; 4] {
        let (west, north) = self.lon_lat(0.0, 0.0, 1.0);
        let (east, south) = self.lon_lat(1.0, 1.0, 1.0);
        [west, south, east, north]
    }

    /// The size of a pixel on the ground at latitude `lat` (metres), `size` pixels a side.
    pub fn pixel_metres(self, lat: f64, size: f64) -> f64 {
        2.0 * HALF_WORLD * lat.to_radians().cos() / (self.count() * size)
    }
}

/// The tiles of zoom `z` that a box of degrees (west, south, east, north) touches: the
/// columns and the rows (inclusive).
pub fn tiles_over(
    z: u8,
    [west, south, east, north]: [f64; 4],
) -> (std::ops::RangeInclusive<u32>, std::ops::RangeInclusive<u32>) {
    let n = f64::from(1u32 << z);
    let column = |lon: f64| ((lon + 180.0) / 360.0 * n).floor().clamp(0.0, n - 1.0);
    let row = |lat: f64| {
        let lat = lat.clamp(-MAX_LATITUDE, MAX_LATITUDE).to_radians();
        ((1.0 - (lat.tan() + 1.0 / lat.cos()).ln() / PI) / 2.0 * n).floor().clamp(0.0, n - 1.0)
    };
    #[expect(clippy::cast_possible_truncation, clippy::cast_sign_loss, reason = "clamped to the grid")]
    let cell = |v: f64| v as u32;
    (cell(column(west))..=cell(column(east)), cell(row(north))..=cell(row(south)))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn tile_corners_and_the_tiles_over_a_box_agree() {
        let world = WebTile::new(0, 0, 0).unwrap();
        let [w, s, e, n] = world.bounds();
        assert!((w + 180.0).abs() < 1e-9 && (e - 180.0).abs() < 1e-9);
        assert!((n - MAX_LATITUDE).abs() < 1e-9 && (s + MAX_LATITUDE).abs() < 1e-9);
        // Mount Tamalpais at z12: the tile's bounds hold it, and the box of those bounds
        // (pulled in a little) is that one tile.
        let (lon, lat) = (-122.5965, 37.9235);
        let (cols, rows) = tiles_over(12, [lon, lat, lon, lat]);
        assert_eq!(cols.clone().count(), 1);
        let tile = WebTile::new(12, *cols.start(), *rows.start()).unwrap();
        let [w, s, e, n] = tile.bounds();
        assert!(w <= lon && lon < e && s < lat && lat <= n, "{:?}", tile.bounds());
        let inner = [w + 1e-9, s + 1e-9, e - 1e-9, n - 1e-9];
        assert_eq!(tiles_over(12, inner), (tile.x..=tile.x, tile.y..=tile.y));
        assert!(WebTile::new(3, 8, 0).is_none() && WebTile::new(31, 0, 0).is_none());
        // A pixel at the equator, z0, 256 px: 156 543 m.
        assert!((world.pixel_metres(0.0, 256.0) - 156_543.033_928).abs() < 1e-3);
    }
}
