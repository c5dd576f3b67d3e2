//! Longitude and latitude to world coordinates and back, from the archive's
//! georeference: its CRS's PROJ definition, the CRS coordinates of the north-west corner,
//! and CRS units per world unit. Pure Rust, so it works in the browser too.

use proj4rs::Proj;
use terrastream_format::{Georeference, Metadata};

/// An archive's placement on the Earth.
pub struct Geo {
    crs: Proj,
    wgs84: Proj,
    georeference: Georeference,
}

impl std::fmt::Debug for Geo {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("Geo").field("georeference", &self.georeference).finish_non_exhaustive()
    }
}

impl Geo {
    /// The placement of `metadata`'s terrain; `None` when the archive does not record its
    /// CRS definition, origin and scale (archives written before they were recorded, or
    /// data that never said where it lies).
    pub fn new(metadata: &Metadata) -> Option<Self> {
        let georeference = metadata.georeference.clone()?;
        georeference.origin?;
        georeference.scale?;
        let crs = Proj::from_proj_string(georeference.definition.as_deref()?).ok()?;
        let wgs84 = Proj::from_proj_string("+proj=longlat +datum=WGS84 +no_defs").ok()?;
        Some(Self { crs, wgs84, georeference })
    }

    /// The longitude and latitude (degrees, WGS 84) of world point `(x, z)`.
    pub fn world_to_lon_lat(&self, x: f64, z: f64) -> Option<(f64, f64)> {
        let (cx, cy) = self.georeference.world_to_crs(x, z)?;
        let (lon, lat) = transform(&self.crs, &self.wgs84, cx, cy)?;
        Some((lon, lat))
    }

    /// The world point `(x, z)` at a longitude and latitude (degrees, WGS 84).
    pub fn lon_lat_to_world(&self, lon: f64, lat: f64) -> Option<(f64, f64)> {
        let (cx, cy) = transform(&self.wgs84, &self.crs, lon, lat)?;
        self.georeference.crs_to_world(cx, cy)
    }
}

/// `(x, y)` from `from` to `to`, geographic coordinates in degrees.
fn transform(from: &Proj, to: &Proj, x: f64, y: f64) -> Option<(f64, f64)> {
    let mut p = if from.is_latlong() { (x.to_radians(), y.to_radians(), 0.0) } else { (x, y, 0.0) };
    proj4rs::transform::transform(from, to, &mut p).ok()?;
    let out = if to.is_latlong() { (p.0.to_degrees(), p.1.to_degrees()) } else { (p.0, p.1) };
    (out.0.is_finite() && out.1.is_finite()).then_some(out)
}
