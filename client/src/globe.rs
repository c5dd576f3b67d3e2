//! The round Earth: the WGS 84 ellipsoid, and an archive's grid placed on it.
//!
//! The quadtree stays in the archive's own grid (world `(x, z)`, see
//! [`crate::stream::camera`]); a [`GlobeMap`] turns a grid point into longitude and
//! latitude — analytically for geographic and Web Mercator grids, through a lattice of
//! exact PROJ transforms for any other CRS (bilinear between lattice points at most
//! [`LATTICE_CELL`] apart, as GDAL's approximate transformer does) — and that into
//! Earth-centred, Earth-fixed coordinates (ECEF, metres). Every camera, box and distance
//! of a globe view is in ECEF, in f64; the GPU gets positions relative to an anchor near
//! the eye ([`GlobeMap::local_frame`]), so f32 keeps sub-millimetre precision at the
//! ground 6 400 km from the Earth's centre.
//!
//! [`Surface`] is what selection and culling see: the flat plate (scene coordinates are
//! world coordinates, as before) or the globe (scene coordinates are ECEF).

use std::sync::Arc;

use glam::{DMat3, DVec2, DVec3};
use terrastream_format::{Metadata, Undulation};

use crate::geo::Geo;
use crate::stream::camera::{Aabb, SceneBox};

/// Semi-major axis of WGS 84, metres.
pub const A: f64 = 6_378_137.0;
/// First eccentricity squared of WGS 84.
pub const E2: f64 = 0.006_694_379_990_141_317;
/// Semi-minor (polar) axis of WGS 84, metres.
pub const B: f64 = 6_356_752.314_245_179;
/// The sphere Web Mercator projects (EPSG:3857), metres.
const MERCATOR_RADIUS: f64 = 6_378_137.0;
/// Web Mercator's ordinate over the radius at the edge of its world (pi), less a margin:
/// a grid point there is drawn at the pole, so that a world grid closes its polar caps.
pub const MERCATOR_EDGE: f64 = std::f64::consts::PI - 3.0e-6;
/// Largest spacing of a lattice of exact transforms, metres on the grid: bilinear
/// interpolation between its points is within a few centimetres for a transverse
/// Mercator region (the inverse's curvature is about tan(lat) / R).
pub const LATTICE_CELL: f64 = 1000.0;
/// Most lattice points a side (a larger region gets coarser cells).
pub const LATTICE_MAX: usize = 257;

/// ECEF of a point at longitude, latitude (radians) and height above the ellipsoid (metres).
pub fn ecef(lon: f64, lat: f64, height: f64) -> DVec3 {
    let (sl, cl) = lat.sin_cos();
    let n = A / (1.0 - E2 * sl * sl).sqrt();
    let (so, co) = lon.sin_cos();
    DVec3::new((n + height) * cl * co, (n + height) * cl * so, (n * (1.0 - E2) + height) * sl)
}

/// Longitude, latitude (radians) and height (metres) of an ECEF point (iterated to
/// convergence; exact at the poles and the centre's neighbourhood excepted).
pub fn geodetic(p: DVec3) -> (f64, f64, f64) {
    let lon = p.y.atan2(p.x);
    let r = p.x.hypot(p.y);
    let mut lat = p.z.atan2(r * (1.0 - E2));
    for _ in 0..6 {
        let s = lat.sin();
        let n = A / (1.0 - E2 * s * s).sqrt();
        let h = r * lat.cos() + p.z * s - A * A / n;
        lat = p.z.atan2(r * (1.0 - E2 * n / (n + h)));
    }
    let (s, c) = lat.sin_cos();
    let n = A / (1.0 - E2 * s * s).sqrt();
    (lon, lat, r * c + p.z * s - A * A / n)
}

/// East, north and up at a longitude and latitude (radians), as the columns of a matrix
/// (ENU to ECEF).
pub fn enu(lon: f64, lat: f64) -> DMat3 {
    let (so, co) = lon.sin_cos();
    let (sl, cl) = lat.sin_cos();
    DMat3::from_cols(DVec3::new(-so, co, 0.0), DVec3::new(-sl * co, -sl * so, cl), DVec3::new(cl * co, cl * so, sl))
}

/// The frame the renderer draws in: x east, y up, z south (the flat plate's axes) at a
/// point, as the columns of a matrix (frame to ECEF).
pub fn local_axes(lon: f64, lat: f64) -> DMat3 {
    let m = enu(lon, lat);
    DMat3::from_cols(m.x_axis, m.z_axis, -m.y_axis)
}

/// How a grid point becomes longitude and latitude.
#[derive(Clone, Debug)]
pub enum Mapping {
    /// A geographic grid on WGS 84: longitude and latitude linear in `(x, z)`.
    Geographic {
        /// Radians at world (0, 0).
        origin: DVec2,
        /// Radians per world unit along x (east) and z (south; negative).
        step: DVec2,
    },
    /// Web Mercator (EPSG:3857): longitude linear in x, latitude the Gudermannian of a
    /// coordinate linear in z.
    WebMercator {
        /// Longitude (radians) and Mercator ordinate over the sphere's radius at world (0, 0).
        origin: DVec2,
        /// Per world unit, the same (z's negative).
        step: DVec2,
    },
    /// Any other CRS: a lattice of exact transforms.
    Lattice(Lattice),
}

/// Longitude and latitude at grid points, relative to a centre (radians), bilinear between.
#[derive(Clone, Debug)]
pub struct Lattice {
    /// World point of lattice point (0, 0).
    pub origin: DVec2,
    /// World units between lattice points.
    pub cell: f64,
    /// Points per row and per column.
    pub size: (usize, usize),
    /// Longitude and latitude (radians) the values are relative to.
    pub centre: DVec2,
    /// Row-major values, north row first.
    pub values: Vec<DVec2>,
}

impl Lattice {
    /// Continuous lattice coordinates of a world point, clamped to the lattice.
    pub fn coordinates(&self, x: f64, z: f64) -> DVec2 {
        #[expect(clippy::cast_precision_loss, reason = "lattice sizes")]
        let max = DVec2::new((self.size.0 - 1) as f64, (self.size.1 - 1) as f64);
        ((DVec2::new(x, z) - self.origin) / self.cell).clamp(DVec2::ZERO, max)
    }

    /// The bilinear value at lattice coordinates `q`, relative to the centre (the
    /// shader interpolates the same way).
    pub fn at(&self, q: DVec2) -> DVec2 {
        let (w, h) = self.size;
        let i = q.floor();
        let t = q - i;
        #[expect(clippy::cast_possible_truncation, clippy::cast_sign_loss, reason = "clamped coordinates")]
        let (i0, j0) = (i.x as usize, i.y as usize);
        let (i1, j1) = ((i0 + 1).min(w - 1), (j0 + 1).min(h - 1));
        let v = |i: usize, j: usize| self.values[j * w + i];
        let top = v(i0, j0).lerp(v(i1, j0), t.x);
        let bottom = v(i0, j1).lerp(v(i1, j1), t.x);
        top.lerp(bottom, t.y)
    }
}

/// The geoid's undulation N (metres) at the points of a lattice of world points, row-major
/// from the north-west; bilinear between (the shader's way).
#[derive(Clone, Debug)]
pub struct GeoidLattice {
    /// World point of lattice point (0, 0).
    pub origin: DVec2,
    /// World units between lattice points.
    pub cell: f64,
    /// Points per row and per column.
    pub size: (usize, usize),
    /// N at each point.
    pub values: Vec<f32>,
}

/// The points of a lattice over a world box: its origin, cell and size (at most
/// [`LATTICE_MAX`] a side, cells of at least [`LATTICE_CELL`]).
fn lattice_points([x0, z0, x1, z1]: [f64; 4]) -> (DVec2, f64, (usize, usize)) {
    let span = (x1 - x0).max(z1 - z0).max(1e-9);
    #[expect(clippy::cast_precision_loss, reason = "lattice sizes")]
    let cell = LATTICE_CELL.max(span / (LATTICE_MAX - 1) as f64);
    #[expect(clippy::cast_possible_truncation, clippy::cast_sign_loss, reason = "bounded above")]
    let count = |extent: f64| ((extent / cell).ceil() as usize + 1).clamp(2, LATTICE_MAX);
    (DVec2::new(x0, z0), cell, (count(x1 - x0), count(z1 - z0)))
}

/// An archive's grid on the ellipsoid.
#[derive(Clone, Debug)]
pub struct GlobeMap {
    /// Grid to longitude and latitude.
    pub mapping: Mapping,
    /// The drawn box `[min x, min z, max x, max z]` (world units): points are clamped to it.
    pub extent: [f64; 4],
    /// The heights the terrain is drawn between (above the ellipsoid: the archive's
    /// own, plus the geoid's undulation where it has one).
    pub heights: (f64, f64),
    /// The geoid's undulation over the data, for an archive of heights above a geoid:
    /// drawn heights are `H + N` above the ellipsoid, as CesiumJS places them.
    pub geoid: Option<Undulation>,
    /// N at the points of a lattice over the drawn box (the GPU's: on the same points as
    /// a [`Mapping::Lattice`]'s), for an archive with a geoid.
    pub geoid_lattice: Option<GeoidLattice>,
    geo: Arc<Geo>,
}

/// What the renderer needs of the frame it draws a globe view in.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct LocalFrame {
    /// The anchor's longitude and latitude (radians).
    pub lon_lat: DVec2,
    /// The anchor on the ellipsoid, ECEF.
    pub origin: DVec3,
    /// Frame axes (x east, y up, z south) to ECEF.
    pub axes: DMat3,
}

impl LocalFrame {
    /// A frame at a longitude and latitude (radians), on the ellipsoid.
    pub fn at(lon: f64, lat: f64) -> Self {
        Self { lon_lat: DVec2::new(lon, lat), origin: ecef(lon, lat, 0.0), axes: local_axes(lon, lat) }
    }

    /// An ECEF point in the frame.
    pub fn to_local(&self, p: DVec3) -> DVec3 {
        self.axes.transpose() * (p - self.origin)
    }

    /// An ECEF direction in the frame.
    pub fn direction_to_local(&self, d: DVec3) -> DVec3 {
        self.axes.transpose() * d
    }
}

/// Does the PROJ definition describe EPSG:3857's spherical Mercator?
fn is_web_mercator(definition: &str) -> bool {
    let has = |s: &str| definition.split_whitespace().any(|w| w == s);
    has("+proj=merc") && has("+a=6378137") && has("+b=6378137")
}

/// Does a geographic definition use WGS 84 itself (no datum shift to apply)?
fn is_wgs84_geographic(definition: &str) -> bool {
    let has = |s: &str| definition.split_whitespace().any(|w| w == s);
    has("+proj=longlat") && (has("+datum=WGS84") || has("+ellps=WGS84")) && !definition.contains("+towgs84=")
        || has("+proj=longlat") && has("+towgs84=0,0,0,0,0,0,0") && has("+ellps=WGS84")
}

impl GlobeMap {
    /// The grid of `metadata` on the ellipsoid; `None` for an archive that does not say
    /// where it lies (it stays a flat plate).
    pub fn new(metadata: &Metadata) -> Option<Self> {
        let geo = Geo::new(metadata)?;
        let georeference = metadata.georeference.as_ref()?;
        let definition = georeference.definition.as_deref()?;
        let (origin, scale) = (georeference.origin?, georeference.scale?);
        let (extent, (lo, hi)) = crate::fly::terrain_bounds(metadata);
        let datum = &metadata.vertical_datum;
        let geoid = datum.undulation.clone().filter(|_| datum.converts());
        let (n_lo, n_hi) = geoid.as_ref().map_or((0.0, 0.0), Undulation::range);
        let heights = (lo + n_lo, hi + n_hi);
        let mapping = if is_wgs84_geographic(definition) {
            Mapping::Geographic {
                origin: DVec2::new(origin[0], origin[1]) * std::f64::consts::PI / 180.0,
                step: DVec2::new(scale[0], -scale[1]) * std::f64::consts::PI / 180.0,
            }
        } else if is_web_mercator(definition) {
            Mapping::WebMercator {
                origin: DVec2::new(origin[0], origin[1]) / MERCATOR_RADIUS,
                step: DVec2::new(scale[0], -scale[1]) / MERCATOR_RADIUS,
            }
        } else {
            Mapping::Lattice(Self::lattice(&geo, extent)?)
        };
        let mut map = Self { mapping, extent, heights, geoid, geoid_lattice: None, geo: Arc::new(geo) };
        if map.geoid.is_some() {
            let (origin, cell, size) = lattice_points(extent);
            let mut values = Vec::with_capacity(size.0 * size.1);
            for j in 0..size.1 {
                for i in 0..size.0 {
                    #[expect(clippy::cast_precision_loss, reason = "lattice sizes")]
                    let (x, z) = (origin.x + i as f64 * cell, origin.y + j as f64 * cell);
                    #[expect(clippy::cast_possible_truncation, reason = "metres as f32")]
                    values.push(map.undulation_at(map.lon_lat(x, z)) as f32);
                }
            }
            map.geoid_lattice = Some(GeoidLattice { origin, cell, size, values });
        }
        Some(map)
    }

    fn lattice(geo: &Geo, [x0, z0, x1, z1]: [f64; 4]) -> Option<Lattice> {
        let (_, cell, size) = lattice_points([x0, z0, x1, z1]);
        let centre_world = ((x0 + x1) * 0.5, (z0 + z1) * 0.5);
        let (clon, clat) = geo.world_to_lon_lat(centre_world.0, centre_world.1)?;
        let centre = DVec2::new(clon.to_radians(), clat.to_radians());
        let mut values = Vec::with_capacity(size.0 * size.1);
        for j in 0..size.1 {
            for i in 0..size.0 {
                #[expect(clippy::cast_precision_loss, reason = "lattice sizes")]
                let (x, z) = (x0 + i as f64 * cell, z0 + j as f64 * cell);
                let (lon, lat) = geo.world_to_lon_lat(x, z)?;
                let mut d = DVec2::new(lon.to_radians(), lat.to_radians()) - centre;
                // Across the antimeridian, the shorter way round.
                d.x = (d.x + std::f64::consts::PI).rem_euclid(std::f64::consts::TAU) - std::f64::consts::PI;
                values.push(d);
            }
        }
        Some(Lattice { origin: DVec2::new(x0, z0), cell, size, centre, values })
    }

    /// Longitude and latitude (radians) of a world point (clamped to the drawn box).
    pub fn lon_lat(&self, x: f64, z: f64) -> DVec2 {
        let [x0, z0, x1, z1] = self.extent;
        let (x, z) = (x.clamp(x0, x1), z.clamp(z0, z1));
        match &self.mapping {
            Mapping::Geographic { origin, step } => {
                let p = *origin + *step * DVec2::new(x, z);
                DVec2::new(p.x, p.y.clamp(-std::f64::consts::FRAC_PI_2, std::f64::consts::FRAC_PI_2))
            }
            Mapping::WebMercator { origin, step } => {
                let p = *origin + *step * DVec2::new(x, z);
                // The world's edge at 85.05 degrees goes to the pole (the shader's rule).
                let lat = if p.y.abs() >= MERCATOR_EDGE {
                    p.y.signum() * std::f64::consts::FRAC_PI_2
                } else {
                    p.y.sinh().atan()
                };
                DVec2::new(p.x, lat)
            }
            Mapping::Lattice(l) => l.centre + l.at(l.coordinates(x, z)),
        }
    }

    /// ECEF of a world point at a height in the archive's datum (above its geoid, where
    /// it has one: lifted by the undulation there).
    pub fn ecef(&self, x: f64, z: f64, height: f64) -> DVec3 {
        let p = self.lon_lat(x, z);
        ecef(p.x, p.y, height + self.undulation_at(p))
    }

    /// The geoid's undulation N at a longitude and latitude (radians): what lifts the
    /// archive's heights onto the ellipsoid (0 without a geoid).
    pub fn undulation_at(&self, lon_lat: DVec2) -> f64 {
        self.geoid.as_ref().map_or(0.0, |u| u.at(lon_lat.x.to_degrees(), lon_lat.y.to_degrees()))
    }

    /// The world point at a longitude and latitude (radians), if it has one.
    pub fn world(&self, lon: f64, lat: f64) -> Option<DVec2> {
        match &self.mapping {
            Mapping::Geographic { origin, step } => Some((DVec2::new(lon, lat) - *origin) / *step),
            Mapping::WebMercator { origin, step } => {
                let v = lat.clamp(-1.5, 1.5).tan().asinh();
                Some((DVec2::new(lon, v) - *origin) / *step)
            }
            Mapping::Lattice(_) => {
                let (x, z) = self.geo.lon_lat_to_world(lon.to_degrees(), lat.to_degrees())?;
                Some(DVec2::new(x, z))
            }
        }
    }

    /// A box holding the terrain over world rectangle `[x0, z0, x1, z1]` between heights
    /// `lo` and `hi`, turned to the east-north-up frame at its middle (conservative: the
    /// surface between sample points bulges by at most the sagitta of the arc they span,
    /// which pads the box).
    pub fn bounds(&self, rect: [f64; 4], (lo, hi): (f64, f64)) -> SceneBox {
        let [ex0, ez0, ex1, ez1] = self.extent;
        let (x0, z0) = (rect[0].clamp(ex0, ex1), rect[1].clamp(ez0, ez1));
        let (x1, z1) = (rect[2].clamp(ex0, ex1), rect[3].clamp(ez0, ez1));
        // Angular size from the corners: a small box needs only its corners, edges' middles
        // and centre.
        let (a, b) = (self.lon_lat(x0, z0), self.lon_lat(x1, z1));
        let (c, d) = (self.lon_lat(x1, z0), self.lon_lat(x0, z1));
        let span = (a - b).abs().max((c - d).abs());
        let steps: u32 = if span.max_element() < 0.02 { 2 } else { 8 };
        let middle = self.lon_lat((x0 + x1) * 0.5, (z0 + z1) * 0.5);
        let axes = enu(middle.x, middle.y);
        let origin = ecef(middle.x, middle.y, 0.0);
        let n = steps as usize + 1;
        let mut top = Vec::with_capacity(n * n);
        let (mut min, mut max) = (DVec3::splat(f64::MAX), DVec3::splat(f64::MIN));
        for j in 0..=steps {
            for i in 0..=steps {
                let (u, v) = (f64::from(i) / f64::from(steps), f64::from(j) / f64::from(steps));
                let p = self.lon_lat(x0 + (x1 - x0) * u, z0 + (z1 - z0) * v);
                let n = self.undulation_at(p);
                for h in [lo, hi] {
                    let q = axes.transpose() * (ecef(p.x, p.y, h + n) - origin);
                    (min, max) = (min.min(q), max.max(q));
                }
                top.push(ecef(p.x, p.y, hi + n));
            }
        }
        // The longest chord between neighbouring samples, diagonals included.
        let mut chord: f64 = 0.0;
        for j in 0..n {
            for i in 0..n {
                let here = top[j * n + i];
                for (di, dj) in [(1, 0), (0, 1), (1, 1)] {
                    if i + di < n && j + dj < n {
                        chord = chord.max(here.distance(top[(j + dj) * n + i + di]));
                    }
                }
                if i > 0 && j + 1 < n {
                    chord = chord.max(here.distance(top[(j + 1) * n + i - 1]));
                }
            }
        }
        // The arc over a chord c on a sphere of radius r rises r (1 - cos(asin(c / 2r))).
        let r = A + hi.max(0.0);
        let half = (chord / (2.0 * r)).min(1.0);
        let sagitta = r * (1.0 - (1.0 - half * half).sqrt());
        let pad = DVec3::splat(sagitta * 1.5 + 1.0);
        SceneBox { centre: origin + axes * ((min + max) * 0.5), axes, half: (max - min) * 0.5 + pad }
    }

    /// The frame a view is drawn in: at the world point nearest below the eye (the
    /// anchor), on the ellipsoid.
    pub fn local_frame(&self, anchor: DVec2) -> LocalFrame {
        let p = self.lon_lat(anchor.x, anchor.y);
        LocalFrame::at(p.x, p.y)
    }

    /// The world point under an ECEF eye (clamped to the drawn box).
    pub fn world_under(&self, eye: DVec3) -> DVec2 {
        let (lon, lat, _) = geodetic(eye);
        let [x0, z0, x1, z1] = self.extent;
        let w = self.world(lon, lat).unwrap_or(DVec2::new((x0 + x1) * 0.5, (z0 + z1) * 0.5));
        DVec2::new(w.x.clamp(x0, x1), w.y.clamp(z0, z1))
    }
}

/// Is every point of `b` hidden from `eye` by the ellipsoid shrunk by `depth` metres (the
/// terrain's lowest point below it, and a margin)? In coordinates scaled by the
/// ellipsoid's radii it is a ball; what a ball hides from a point is convex, and so is
/// its image, so the box's eight corners decide.
pub fn box_hidden(eye: DVec3, depth: f64, b: &SceneBox) -> bool {
    let scale = DVec3::new(1.0 / A, 1.0 / A, 1.0 / B);
    let radius = 1.0 - depth.max(0.0) / B;
    let eye = eye * scale;
    b.corners().iter().all(|&q| segment_hits_ball(eye, q * scale, radius))
}

/// Does the segment from `a` to `b` meet the ball of radius `r` at the origin?
fn segment_hits_ball(a: DVec3, b: DVec3, r: f64) -> bool {
    let d = b - a;
    let len2 = d.length_squared();
    let t = if len2 > 0.0 { (-a.dot(d) / len2).clamp(0.0, 1.0) } else { 0.0 };
    (a + d * t).length_squared() <= r * r
}

/// The direction towards a sun at `azimuth` (degrees clockwise from north) and
/// `elevation` (degrees above the horizon), in the renderer's axes (x east, y up, z south).
///
/// # Errors
/// A message naming the bad value.
pub fn sun_direction(azimuth: f64, elevation: f64) -> Result<DVec3, String> {
    if !azimuth.is_finite() || !(-90.0..=90.0).contains(&elevation) {
        return Err(format!("sun {azimuth},{elevation}: a finite azimuth, an elevation of -90..90 degrees"));
    }
    let (a, e) = (azimuth.to_radians(), elevation.to_radians());
    Ok(DVec3::new(a.sin() * e.cos(), e.sin(), -a.cos() * e.cos()))
}

/// "AZIMUTH,ELEVATION" (degrees) as [`sun_direction`].
///
/// # Errors
/// A message naming the text.
pub fn parse_sun(text: &str) -> Result<DVec3, String> {
    let v: Vec<f64> = text
        .split(',')
        .map(|p| p.trim().parse::<f64>())
        .collect::<Result<_, _>>()
        .map_err(|_| format!("sun {text:?}: expected AZIMUTH,ELEVATION in degrees"))?;
    let [azimuth, elevation] = v[..] else {
        return Err(format!("sun {text:?}: expected two numbers AZIMUTH,ELEVATION"));
    };
    sun_direction(azimuth, elevation)
}

/// What selection and culling see of the terrain's shape.
#[derive(Clone, Debug, Default)]
pub enum Surface {
    /// The flat plate: scene coordinates are world coordinates.
    #[default]
    Flat,
    /// The globe: scene coordinates are ECEF.
    Globe(Arc<GlobeMap>),
}

impl Surface {
    /// The globe for a georeferenced archive when `globe` is asked for, else the plate.
    pub fn new(metadata: &Metadata, globe: bool) -> Self {
        match GlobeMap::new(metadata).filter(|_| globe) {
            Some(map) => Self::Globe(Arc::new(map)),
            None => Self::Flat,
        }
    }

    /// The globe's map, if this is one.
    pub fn globe(&self) -> Option<&GlobeMap> {
        match self {
            Self::Flat => None,
            Self::Globe(map) => Some(map),
        }
    }

    /// A box in scene coordinates holding the terrain over world rectangle
    /// `[x0, z0, x1, z1]` between heights `lo` and `hi`.
    pub fn bounds(&self, rect: [f64; 4], heights: (f64, f64)) -> SceneBox {
        match self {
            Self::Flat => {
                Aabb { min: DVec3::new(rect[0], heights.0, rect[1]), max: DVec3::new(rect[2], heights.1, rect[3]) }
                    .into()
            }
            Self::Globe(map) => map.bounds(rect, heights),
        }
    }

    /// Is the box hidden from `eye` by the Earth (always false on the plate)? The Earth
    /// is taken as the ball inside the ellipsoid and below the terrain's lowest point.
    pub fn hidden(&self, eye: DVec3, b: &SceneBox) -> bool {
        match self {
            Self::Flat => false,
            Self::Globe(map) => box_hidden(eye, 100.0 - map.heights.0.min(0.0), b),
        }
    }

    /// The up direction at a scene point.
    pub fn up(&self, p: DVec3) -> DVec3 {
        match self {
            Self::Flat => DVec3::Y,
            Self::Globe(_) => {
                let (lon, lat, _) = geodetic(p);
                enu(lon, lat).z_axis
            }
        }
    }

    /// The scene point of a world point (x, z on the grid, y the height): itself on the
    /// plate, on the globe its grid point lifted to its height above the ellipsoid.
    pub fn place(&self, world: DVec3) -> DVec3 {
        match self {
            Self::Flat => world,
            Self::Globe(map) => map.ecef(world.x, world.z, world.y),
        }
    }

    /// The world point `(x, z)` under a scene point (on the globe: at its longitude and
    /// latitude), if the archive's grid has one; unlike [`GlobeMap::world_under`], not
    /// clamped to the data.
    pub fn world_at(&self, p: DVec3) -> Option<DVec2> {
        match self {
            Self::Flat => Some(DVec2::new(p.x, p.z)),
            Self::Globe(map) => {
                let (lon, lat, _) = geodetic(p);
                map.world(lon, lat)
            }
        }
    }

    /// Height of a scene point above the ellipsoid (the plate's y).
    pub fn height(&self, p: DVec3) -> f64 {
        match self {
            Self::Flat => p.y,
            Self::Globe(_) => geodetic(p).2,
        }
    }

    /// Height of a scene point in the archive's datum: above its geoid where it has one
    /// (the ellipsoidal height less the undulation there), else as [`Surface::height`].
    pub fn datum_height(&self, p: DVec3) -> f64 {
        match self {
            Self::Flat => p.y,
            Self::Globe(map) => {
                let (lon, lat, h) = geodetic(p);
                h - map.undulation_at(DVec2::new(lon, lat))
            }
        }
    }

    /// What lifts the archive's heights at a scene point to scene heights: the geoid's
    /// undulation on a globe of an archive above a geoid, else 0.
    pub fn lift(&self, p: DVec3) -> f64 {
        match self {
            Self::Flat => 0.0,
            Self::Globe(map) => {
                let (lon, lat, _) = geodetic(p);
                map.undulation_at(DVec2::new(lon, lat))
            }
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn geodetic_inverts_ecef() {
        for (lon, lat, h) in [(0.0, 0.0, 0.0), (86.925, 27.9881, 8848.0), (-122.6, 37.9, -50.0), (10.0, 89.999, 1e5)] {
            let p = ecef(f64::to_radians(lon), f64::to_radians(lat), h);
            let (lo, la, he) = geodetic(p);
            assert!((lo.to_degrees() - lon).abs() < 1e-9 && (la.to_degrees() - lat).abs() < 1e-9, "{lon} {lat}");
            assert!((he - h).abs() < 1e-6, "{h} -> {he}");
        }
        // The equator and the pole.
        assert!((ecef(0.0, 0.0, 0.0).x - A).abs() < 1e-9);
        assert!((ecef(0.0, std::f64::consts::FRAC_PI_2, 0.0).z - B).abs() < 1e-6);
    }

    #[test]
    fn local_axes_are_east_up_south() {
        let m = local_axes(0.0, 0.0);
        assert!((m.x_axis - DVec3::Y).length() < 1e-12, "east at (0, 0) is +y");
        assert!((m.y_axis - DVec3::X).length() < 1e-12, "up is +x");
        assert!((m.z_axis + DVec3::Z).length() < 1e-12, "south is -z");
    }

    #[test]
    fn a_point_is_hidden_only_behind_the_horizon() {
        let eye = DVec3::new(A + 10_000.0, 0.0, 0.0);
        let tiny = |p: DVec3| SceneBox::from(Aabb { min: p - DVec3::splat(1.0), max: p + DVec3::splat(1.0) });
        // 100 km east along the equator: visible (the horizon from 10 km is 357 km away).
        let near = ecef(0.1_f64.to_radians() * 9.0, 0.0, 0.0);
        assert!(!box_hidden(eye, 0.0, &tiny(near)));
        // The far side.
        assert!(box_hidden(eye, 0.0, &tiny(DVec3::new(-A, 0.0, 0.0))));
        // 450 km east: beyond the horizon (357 km), though not beyond a mountain's.
        let far = ecef(4.05_f64.to_radians(), 0.0, 0.0);
        assert!(box_hidden(eye, 0.0, &tiny(far)));
        let summit = ecef(4.05_f64.to_radians(), 0.0, 8000.0);
        assert!(!box_hidden(eye, 0.0, &tiny(summit)));
    }

    /// terrain.wgsl's `globe_local`, in f32 as the GPU runs it: a point `d` (longitude,
    /// latitude) from the anchor at height `h`, in the anchor's frame.
    #[expect(clippy::many_single_char_names, clippy::cast_possible_truncation, reason = "the shader's f32")]
    fn globe_local_f32(anchor_lat: f64, d: [f32; 2], h: f32) -> [f32; 3] {
        let (sa, ca) = (anchor_lat.sin() as f32, anchor_lat.cos() as f32);
        let na = (A / (1.0 - E2 * anchor_lat.sin().powi(2)).sqrt()) as f32;
        let (a, e2) = (A as f32, E2 as f32);
        let half = (0.5 * d[1]).sin();
        let cos_half = (0.5 * d[1]).cos();
        let dc = -2.0 * half * (sa * cos_half + ca * half);
        let ds = 2.0 * half * (ca * cos_half - sa * half);
        let (s, c) = (sa + ds, ca + dc);
        let w = (1.0 - e2 * s * s).sqrt();
        let wa = a / na;
        let n = a / w;
        let dn = n * e2 * ds * (s + sa) / (wa * (w + wa));
        let sl = (0.5 * d[0]).sin();
        let x = (n + h) * c * (-2.0 * sl * sl) + (dn + h) * c + na * dc;
        let y = (n + h) * c * d[0].sin();
        let z = (dn * (1.0 - e2) + h) * s + na * (1.0 - e2) * ds;
        [y, ca * x + sa * z, sa * x - ca * z]
    }

    #[test]
    #[expect(clippy::cast_possible_truncation, reason = "what the CPU hands the GPU")]
    fn the_shaders_f32_placement_is_within_millimetres_at_the_summit() {
        let (lon, lat) = (86.925_f64.to_radians(), 27.9881_f64.to_radians());
        let frame = LocalFrame::at(lon, lat);
        let mut worst_near: f64 = 0.0;
        let mut worst_far: f64 = 0.0;
        let mut naive: f64 = 0.0;
        for (i, (east, north, h)) in [
            (3.0, -2.0, 8848.0),
            (-7.5, 9.1, 8846.5),
            (0.4, 0.3, 8850.0),
            (25_000.0, -40_000.0, 5000.0),
            (9.0e5, 3.0e5, 100.0),
        ]
        .into_iter()
        .enumerate()
        {
            let d = [east / (A * lat.cos()), north / A];
            let got = globe_local_f32(lat, [d[0] as f32, d[1] as f32], h as f32);
            // The offset f32 can carry exactly is rounded from the f64 one; the rest is the formula's.
            let rounded =
                frame.to_local(ecef(lon + f64::from(d[0] as f32), lat + f64::from(d[1] as f32), f64::from(h as f32)));
            let error = (DVec3::new(f64::from(got[0]), f64::from(got[1]), f64::from(got[2])) - rounded).length();
            if i < 3 {
                worst_near = worst_near.max(error);
                // The same point in f32 ECEF less the anchor's: what camera-relative rendering avoids.
                let p = ecef(lon + d[0], lat + d[1], h).as_vec3() - frame.origin.as_vec3();
                naive = naive.max((p.as_dvec3() - (ecef(lon + d[0], lat + d[1], h) - frame.origin)).length());
            } else {
                let distance = DVec3::new(east, h, north).length();
                worst_far = worst_far.max(error / distance);
            }
        }
        // Heights of 8 848 m carry half a millimetre of f32 rounding themselves.
        assert!(worst_near < 2e-3, "{worst_near} m off within 10 m of the anchor");
        assert!(worst_far < 1e-6, "{worst_far} of the distance off far from it");
        assert!(naive > 0.05, "f32 ECEF would be {naive} m off: the check can tell");
    }
}
