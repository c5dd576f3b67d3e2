//! The geographic TMS grid of quantized-mesh terrain (EPSG:4326, two root tiles: level z
//! has 2^(z+1) columns from 180 W and 2^z rows from 90 S), and the WGS 84 ellipsoid.

/// Semi-major axis and first eccentricity squared of WGS 84.
const A: f64 = 6_378_137.0;
const E2: f64 = 0.006_694_379_990_141_317;
/// The semi-minor axis.
const B: f64 = 6_356_752.314_245_179;

/// Levels whose tiles carry the availability of the levels below them (the `metadata`
/// extension): tiles of levels 0, 10, 20... each give the next ten levels of their own
/// subtree.
pub const METADATA_LEVELS: u8 = 10;

/// A tile of the grid.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash)]
pub struct GeoTile {
    /// Level (0: two tiles for the world).
    pub z: u8,
    /// Column, from 180 W.
    pub x: u32,
    /// Row, from 90 S.
    pub y: u32,
}

impl GeoTile {
    /// The tile, when `x` and `y` lie in the grid of level `z` (at most 30).
    pub fn new(z: u8, x: u32, y: u32) -> Option<Self> {
        let rows = 1u64 << z.min(31);
        (z <= 30 && u64::from(x) < 2 * rows && u64::from(y) < rows).then_some(Self { z, x, y })
    }

    /// Degrees a side.
    pub fn degrees(self) -> f64 {
        180.0 / f64::from(1u32 << self.z)
    }

    /// West, south, east, north in degrees.
    pub fn bounds(self) -> [f64; 4] {
        let d = self.degrees();
        let (west, south) = (f64::from(self.x) * d - 180.0, f64::from(self.y) * d - 90.0);
        [west, south, west + d, south + d]
    }

    /// Longitude and latitude of grid point (`column`, `row` from the north) of a tile
    /// sampled `size` points a side. Computed from the point's place in the whole level's
    /// grid, so that tiles sharing an edge compute the very same points on it.
    pub fn grid_point(self, column: usize, row: usize, size: usize) -> (f64, f64) {
        self.grid_point_at(column as f64, row as f64, size)
    }

    /// [`Self::grid_point`] anywhere in the grid: `column` and `row` in grid steps.
    pub fn grid_point_at(self, column: f64, row: f64, size: usize) -> (f64, f64) {
        let steps = (size.max(2) - 1) as f64;
        let step = self.degrees() / steps;
        let gx = f64::from(self.x) * steps + column;
        let gy = f64::from(self.y) * steps + (steps - row);
        (gx * step - 180.0, gy * step - 90.0)
    }

    /// The tiles of level `z` that a box (west, south, east, north; degrees) touches:
    /// columns and rows, inclusive.
    pub fn range(z: u8, [west, south, east, north]: [f64; 4]) -> ([u32; 2], [u32; 2]) {
        let n = f64::from(1u32 << z.min(30));
        let d = 180.0 / n;
        #[expect(clippy::cast_possible_truncation, clippy::cast_sign_loss, reason = "clamped to the grid")]
        let cell = |v: f64, count: f64| ((v / d).floor().clamp(0.0, count - 1.0)) as u32;
        // A box edge on a tile edge does not reach into the next tile.
        let upper = |v: f64, count: f64| {
            let c = cell(v, count);
            if c > 0 && (v / d - (v / d).floor()).abs() < 1e-12 { c - 1 } else { c }
        };
        let columns = [cell(west + 180.0, 2.0 * n), upper(east + 180.0, 2.0 * n)];
        let rows = [cell(south + 90.0, n), upper(north + 90.0, n)];
        (columns, rows)
    }
}

/// Earth-centred, Earth-fixed coordinates (metres) of a point in degrees and metres above
/// the ellipsoid.
pub fn ecef(lon: f64, lat: f64, height: f64) -> [f64; 3] {
    let (lon, lat) = (lon.to_radians(), lat.to_radians());
    let n = A / (1.0 - E2 * lat.sin().powi(2)).sqrt();
    [(n + height) * lat.cos() * lon.cos(), (n + height) * lat.cos() * lon.sin(), (n * (1.0 - E2) + height) * lat.sin()]
}

/// The ellipsoid's unit normal under an ECEF point.
pub fn surface_normal(p: [f64; 3]) -> [f64; 3] {
    let n = [p[0] / (A * A), p[1] / (A * A), p[2] / (B * B)];
    let len = (n[0] * n[0] + n[1] * n[1] + n[2] * n[2]).sqrt();
    if len > 0.0 { n.map(|c| c / len) } else { [0.0, 0.0, 1.0] }
}

/// The horizon-occlusion point of a set of ECEF points seen in the direction of `centre`
/// (Cesium's `EllipsoidalOccluder.computeHorizonCullingPoint`, in the ellipsoid-scaled
/// space the format stores it in): a point that is below the horizon only when all of
/// them are. Where no such point exists on that ray (a tile spanning a hemisphere), a
/// point far out on it, visible from everywhere above the tile.
pub fn horizon_occlusion_point(points: impl Iterator<Item = [f64; 3]>, centre: [f64; 3]) -> [f64; 3] {
    let scale = |p: [f64; 3]| [p[0] / A, p[1] / A, p[2] / B];
    let c = scale(centre);
    let len = (c[0] * c[0] + c[1] * c[1] + c[2] * c[2]).sqrt();
    if len == 0.0 {
        return [0.0; 3];
    }
    let dir = c.map(|v| v / len);
    let mut magnitude: f64 = 0.0;
    for p in points {
        let s = scale(p);
        let m2 = s[0] * s[0] + s[1] * s[1] + s[2] * s[2];
        let m = m2.sqrt();
        if m == 0.0 {
            continue;
        }
        let d = s.map(|v| v / m);
        let (m2, m) = (m2.max(1.0), m.max(1.0));
        let cos_alpha = d[0] * dir[0] + d[1] * dir[1] + d[2] * dir[2];
        let cross = [d[1] * dir[2] - d[2] * dir[1], d[2] * dir[0] - d[0] * dir[2], d[0] * dir[1] - d[1] * dir[0]];
        let sin_alpha = (cross[0] * cross[0] + cross[1] * cross[1] + cross[2] * cross[2]).sqrt();
        let cos_beta = 1.0 / m;
        let sin_beta = (m2 - 1.0).sqrt() * cos_beta;
        let denominator = cos_alpha * cos_beta - sin_alpha * sin_beta;
        let this = if denominator > 1e-9 { 1.0 / denominator } else { f64::INFINITY };
        magnitude = magnitude.max(this);
    }
    let magnitude = if magnitude.is_finite() { magnitude.max(1.0) } else { 1000.0 };
    dir.map(|v| v * magnitude)
}
