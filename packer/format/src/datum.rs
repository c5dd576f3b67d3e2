//! The vertical datum of an archive's heights (FORMAT.md §3.8): what height 0 is, and,
//! for heights above a geoid, the geoid's undulation over the archive's footprint, so
//! that every reader can make heights above the WGS 84 ellipsoid (`h = H + N`) without
//! the geoid model's file.

use serde::{Deserialize, Serialize};

/// What an archive's heights are measured from.
#[derive(Clone, Debug, Default, PartialEq, Serialize, Deserialize)]
pub struct VerticalDatum {
    /// Ellipsoid, geoid or unknown.
    pub reference: HeightReference,
    /// The vertical CRS's EPSG code where it has one: 4979 (WGS 84 ellipsoidal heights),
    /// 5773 (EGM96 height), 3855 (EGM2008 height).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub epsg: Option<u32>,
    /// The geoid model, for heights above a geoid: "EGM96", "EGM2008", or the name of
    /// the grid file it came from.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub geoid: Option<String>,
    /// The grid file the undulation was read from (its file name).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub grid: Option<String>,
    /// The geoid's height above the ellipsoid over the archive's footprint.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub undulation: Option<Undulation>,
}

/// The surface heights are measured from.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum HeightReference {
    /// Heights above the WGS 84 ellipsoid (GPS heights; what CesiumJS places).
    Ellipsoid,
    /// Orthometric heights: above a geoid ("above sea level"; what maps show).
    Geoid,
    /// Not known: served as they are, and said so.
    #[default]
    Unknown,
}

impl HeightReference {
    /// The name used in metadata, URLs and answers.
    pub fn name(self) -> &'static str {
        match self {
            Self::Ellipsoid => "ellipsoid",
            Self::Geoid => "geoid",
            Self::Unknown => "unknown",
        }
    }
}

impl VerticalDatum {
    /// Heights above the WGS 84 ellipsoid.
    pub fn ellipsoid() -> Self {
        Self { reference: HeightReference::Ellipsoid, epsg: Some(4979), ..Self::default() }
    }

    /// Whether nothing is known (older archives read so).
    pub fn is_unknown(&self) -> bool {
        self.reference == HeightReference::Unknown
    }

    /// A person's name for it: "EGM96 geoid (EPSG:5773)", "WGS 84 ellipsoid (EPSG:4979)",
    /// "unknown".
    pub fn describe(&self) -> String {
        let code = self.epsg.map(|c| format!(" (EPSG:{c})")).unwrap_or_default();
        match self.reference {
            HeightReference::Ellipsoid => format!("WGS 84 ellipsoid{code}"),
            HeightReference::Geoid => {
                format!("{} geoid{code}", self.geoid.as_deref().unwrap_or("unnamed"))
            }
            HeightReference::Unknown => "unknown".to_owned(),
        }
    }

    /// What to add to a height at `(lon, lat)` (degrees) to make it ellipsoidal: the
    /// geoid's undulation N for heights above a geoid, 0 for ellipsoidal heights and
    /// where nothing is known (served as they are).
    pub fn to_ellipsoid(&self, lon: f64, lat: f64) -> f64 {
        match (&self.reference, &self.undulation) {
            (HeightReference::Geoid, Some(u)) => u.at(lon, lat),
            _ => 0.0,
        }
    }

    /// Whether heights change on the way to the ellipsoid (a geoid with its undulation).
    pub fn converts(&self) -> bool {
        self.reference == HeightReference::Geoid && self.undulation.is_some()
    }
}

/// A geoid's undulation N (metres above the WGS 84 ellipsoid) on a lattice of longitude
/// and latitude nodes, row by row from the north-west node, read bilinearly (as PROJ reads
/// its geoid grids).
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct Undulation {
    /// Longitude of the first column of nodes, degrees.
    pub west: f64,
    /// Latitude of the first row of nodes, degrees.
    pub north: f64,
    /// Degrees between nodes: along longitude, along latitude (both positive).
    pub step: [f64; 2],
    /// Nodes across.
    pub columns: u32,
    /// Nodes down.
    pub rows: u32,
    /// N at each node, metres (rounded to the millimetre), rows from the north.
    pub metres: Vec<f32>,
}

impl Undulation {
    /// Whether the lattice is well formed: positive finite steps, at least one node, as
    /// many values as nodes.
    pub fn is_valid(&self) -> bool {
        let ok = |v: f64| v.is_finite() && v > 0.0;
        ok(self.step[0])
            && ok(self.step[1])
            && self.west.is_finite()
            && self.north.is_finite()
            && self.columns > 0
            && self.rows > 0
            && self.metres.len() == self.columns as usize * self.rows as usize
    }

    /// N at `(lon, lat)` in degrees: bilinear between the four nodes around it; beyond
    /// the lattice, that of its nearest edge (a reader asks only within the archive's
    /// footprint, which the lattice covers). Longitudes are taken modulo 360 into the
    /// lattice's range where they fall outside it.
    pub fn at(&self, lon: f64, lat: f64) -> f64 {
        if !self.is_valid() {
            return 0.0;
        }
        let (cols, rows) = (f64::from(self.columns), f64::from(self.rows));
        let mut x = (lon - self.west) / self.step[0];
        if x < 0.0 || x > cols - 1.0 {
            let turn = 360.0 / self.step[0];
            let wrapped = x.rem_euclid(turn);
            if wrapped <= cols - 1.0 {
                x = wrapped;
            }
        }
        let x = x.clamp(0.0, cols - 1.0);
        let y = ((self.north - lat) / self.step[1]).clamp(0.0, rows - 1.0);
        #[expect(clippy::cast_possible_truncation, clippy::cast_sign_loss, reason = "clamped into the lattice")]
        let (i, j) =
            ((x.floor() as usize).min(self.columns as usize - 1), (y.floor() as usize).min(self.rows as usize - 1));
        let (i1, j1) = ((i + 1).min(self.columns as usize - 1), (j + 1).min(self.rows as usize - 1));
        #[expect(clippy::cast_precision_loss, reason = "node indices are small")]
        let (fx, fy) = (x - i as f64, y - j as f64);
        let w = self.columns as usize;
        let v = |c: usize, r: usize| f64::from(self.metres[r * w + c]);
        let top = v(i, j) * (1.0 - fx) + v(i1, j) * fx;
        let bottom = v(i, j1) * (1.0 - fx) + v(i1, j1) * fx;
        top * (1.0 - fy) + bottom * fy
    }

    /// The lattice over both footprints, where both are of one grid (same steps, nodes a
    /// whole number of steps apart): each node from whichever holds it (`self` first),
    /// nodes neither holds from the nearest one that does. None for lattices of
    /// different grids.
    pub fn union(&self, other: &Self) -> Option<Self> {
        if !(self.is_valid() && other.is_valid()) || self.step != other.step {
            return None;
        }
        let [sx, sy] = self.step;
        let offset = |a: f64, b: f64, step: f64| {
            let k = (a - b) / step;
            #[expect(clippy::cast_possible_truncation, reason = "node offsets are small")]
            ((k - k.round()).abs() < 1e-6).then_some(k.round() as i64)
        };
        // Node offsets of `other`'s first node from `self`'s (columns east, rows south).
        let (dx, dy) = (offset(other.west, self.west, sx)?, offset(self.north, other.north, sy)?);
        let (c0, r0) = (dx.min(0), dy.min(0));
        let c1 = (i64::from(self.columns)).max(dx + i64::from(other.columns));
        let r1 = (i64::from(self.rows)).max(dy + i64::from(other.rows));
        let (columns, rows) = (u32::try_from(c1 - c0).ok()?, u32::try_from(r1 - r0).ok()?);
        let get = |u: &Self, c: i64, r: i64| -> Option<f32> {
            let (c, r) = (u32::try_from(c).ok()?, u32::try_from(r).ok()?);
            (c < u.columns && r < u.rows).then(|| u.metres[(r * u.columns + c) as usize])
        };
        #[expect(clippy::cast_precision_loss, reason = "node offsets are small")]
        let (west, north) = (self.west + c0 as f64 * sx, self.north - r0 as f64 * sy);
        let mut metres = Vec::with_capacity(columns as usize * rows as usize);
        for r in r0..r1 {
            for c in c0..c1 {
                let v = get(self, c, r).or_else(|| get(other, c - dx, r - dy));
                #[expect(clippy::cast_precision_loss, reason = "node offsets are small")]
                let fill = || {
                    let (lon, lat) = (west + (c - c0) as f64 * sx, north - (r - r0) as f64 * sy);
                    #[expect(clippy::cast_possible_truncation, reason = "metres fit f32")]
                    let v = if self.contains(lon, lat) { self.at(lon, lat) } else { other.at(lon, lat) } as f32;
                    v
                };
                metres.push(v.unwrap_or_else(fill));
            }
        }
        Some(Self { west, north, step: self.step, columns, rows, metres })
    }

    /// Whether `(lon, lat)` lies on the lattice (edges included).
    fn contains(&self, lon: f64, lat: f64) -> bool {
        let x = (lon - self.west) / self.step[0];
        let y = (self.north - lat) / self.step[1];
        (0.0..=f64::from(self.columns - 1)).contains(&x) && (0.0..=f64::from(self.rows - 1)).contains(&y)
    }

    /// The lowest and highest N on the lattice.
    pub fn range(&self) -> (f64, f64) {
        self.metres
            .iter()
            .fold((f64::INFINITY, f64::NEG_INFINITY), |(lo, hi), &v| (lo.min(f64::from(v)), hi.max(f64::from(v))))
    }
}

#[cfg(test)]
#[allow(clippy::cast_possible_truncation, reason = "test values")]
mod tests {
    use super::*;

    fn lattice() -> Undulation {
        // 3 x 2 nodes, 1 degree apart, from (10 E, 50 N): N = lon - 2 * lat.
        let metres =
            [50.0, 49.0].iter().flat_map(|&lat| [10.0, 11.0, 12.0].map(|lon: f64| (lon - 2.0 * lat) as f32)).collect();
        Undulation { west: 10.0, north: 50.0, step: [1.0, 1.0], columns: 3, rows: 2, metres }
    }

    #[test]
    fn bilinear_between_nodes_and_clamped_beyond() {
        let u = lattice();
        // A plane is reproduced exactly inside.
        assert!((u.at(10.25, 49.5) - (10.25 - 99.0)).abs() < 1e-9);
        assert!((u.at(11.9, 49.1) - (11.9 - 98.2)).abs() < 1e-9);
        // Outside: the nearest edge's value.
        assert!((u.at(20.0, 49.5) - (12.0 - 99.0)).abs() < 1e-9);
        assert!((u.at(10.0, 60.0) - (10.0 - 100.0)).abs() < 1e-9);
        // A longitude 360 away reads the same node.
        assert!((u.at(371.0, 50.0) - u.at(11.0, 50.0)).abs() < 1e-9);
    }

    #[test]
    fn lattices_of_one_grid_join() {
        let a = lattice();
        let mut b = lattice();
        // b: two columns further east, one row further south, values of the same plane.
        b.west += 2.0;
        b.north -= 1.0;
        b.metres =
            [49.0, 48.0].iter().flat_map(|&lat| [12.0, 13.0, 14.0].map(|lon: f64| (lon - 2.0 * lat) as f32)).collect();
        let u = a.union(&b).unwrap();
        assert_eq!((u.columns, u.rows, u.west, u.north), (5, 3, 10.0, 50.0));
        for (lon, lat) in [(10.0, 50.0), (14.0, 48.0), (12.5, 49.0), (11.0, 48.5)] {
            let want = if lon < 12.0 && lat < 49.0 { u.at(lon, lat) } else { lon - 2.0 * lat };
            assert!((u.at(lon, lat) - want).abs() < 1e-4, "{lon},{lat}: {}", u.at(lon, lat));
        }
        b.west += 0.5;
        assert!(a.union(&b).is_none(), "nodes of another lattice");
    }

    #[test]
    fn only_geoid_heights_change() {
        let mut d = VerticalDatum {
            reference: HeightReference::Geoid,
            epsg: Some(5773),
            geoid: Some("EGM96".into()),
            grid: None,
            undulation: Some(lattice()),
        };
        assert!(d.converts());
        assert!((d.to_ellipsoid(11.0, 50.0) - (11.0 - 100.0)).abs() < 1e-9);
        assert_eq!(d.describe(), "EGM96 geoid (EPSG:5773)");
        d.reference = HeightReference::Unknown;
        assert_eq!(d.to_ellipsoid(11.0, 50.0), 0.0);
        assert_eq!(VerticalDatum::ellipsoid().to_ellipsoid(11.0, 50.0), 0.0);
        assert_eq!(VerticalDatum::ellipsoid().describe(), "WGS 84 ellipsoid (EPSG:4979)");
    }

    #[test]
    fn older_documents_read_as_unknown() {
        let d: VerticalDatum = serde_json::from_str(r#"{"reference":"unknown"}"#).unwrap();
        assert!(d.is_unknown());
        let g: VerticalDatum = serde_json::from_str(r#"{"reference":"geoid","epsg":5773,"geoid":"EGM96"}"#).unwrap();
        assert_eq!(g.reference, HeightReference::Geoid);
        assert!(!g.converts(), "no undulation: nothing to add");
    }
}
