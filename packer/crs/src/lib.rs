//! Coordinate reference systems: EPSG codes to definitions, and transforms between them.
//!
//! Pure Rust ([`proj4rs`] with the EPSG table of `crs-definitions`), so it builds for every
//! target the tiler and the server do and needs no system library; PROJ's command-line tools are the
//! tests' oracle. Where the EPSG table's definition leaves out the datum shift to WGS 84 of
//! a national grid, the shift PROJ itself applies without transformation grids is added
//! ([`DATUM_SHIFTS`]).

use std::fmt;

use proj4rs::Proj;

/// A coordinate reference system that cannot be used.
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
#[error("unknown CRS {crs}: {reason}")]
pub struct UnknownCrs {
    /// The CRS as given.
    pub crs: String,
    /// Why it cannot be used.
    pub reason: String,
}

/// Result alias of this crate.
pub type Result<T, E = UnknownCrs> = std::result::Result<T, E>;

/// Datum shifts (`+towgs84`, metres and arc-seconds) for definitions of the EPSG table
/// that omit them: the Helmert transformations PROJ uses for these grids when no grid
/// files are installed.
pub const DATUM_SHIFTS: &[(u16, &str)] = &[
    // CH1903+ / LV95: "CH1903+ to WGS 84 (1)", EPSG:1676.
    (2056, "+towgs84=674.374,15.056,405.346,0,0,0,0"),
    // CH1903 / LV03: "CH1903 to WGS 84 (1)", EPSG:1753.
    (21781, "+towgs84=674.4,15.1,405.3,0,0,0,0"),
    // OSGB36 / British National Grid: "OSGB36 to WGS 84 (6)", EPSG:1314.
    (27700, "+towgs84=446.448,-125.157,542.06,0.15,0.247,0.842,-20.489"),
];

/// A coordinate reference system.
#[derive(Clone)]
pub struct Crs {
    code: Option<u16>,
    definition: String,
    proj: Proj,
}

impl fmt::Debug for Crs {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.debug_struct("Crs").field("code", &self.code).field("definition", &self.definition).finish()
    }
}

impl PartialEq for Crs {
    fn eq(&self, other: &Self) -> bool {
        self.definition == other.definition
    }
}

impl Crs {
    /// The CRS of an EPSG code.
    ///
    /// # Errors
    /// [`UnknownCrs`] for a code the table does not hold or a projection the
    /// library does not implement.
    pub fn epsg(code: u16) -> Result<Self> {
        let def = crs_definitions::from_code(code)
            .ok_or_else(|| UnknownCrs { crs: format!("EPSG:{code}"), reason: "not in the EPSG table".into() })?;
        let mut definition = def.proj4.replace(" +type=crs", "");
        if let Some((_, shift)) = DATUM_SHIFTS.iter().find(|(c, _)| *c == code) {
            definition = format!("{definition} {shift}");
        }
        let proj = Proj::from_proj_string(&definition)
            .map_err(|e| UnknownCrs { crs: format!("EPSG:{code}"), reason: e.to_string() })?;
        Ok(Self { code: Some(code), definition, proj })
    }

    /// A CRS as a user or a file names it: `EPSG:32610` (or a bare code) or a PROJ string.
    ///
    /// # Errors
    /// [`UnknownCrs`] naming the text.
    pub fn parse(text: &str) -> Result<Self> {
        // The CRSs parsed last on this thread, kept: a server parses its archives' CRSs
        // for every web tile, and parsing is most of what such a tile's transform costs.
        thread_local! {
            static PARSED: std::cell::RefCell<Vec<(String, Crs)>> = const { std::cell::RefCell::new(Vec::new()) };
        }
        if let Some(crs) = PARSED.with(|p| p.borrow().iter().find(|(t, _)| t == text).map(|(_, c)| c.clone())) {
            return Ok(crs);
        }
        let crs = Self::parse_text(text)?;
        PARSED.with(|p| {
            let mut p = p.borrow_mut();
            if p.len() >= 8 {
                p.remove(0);
            }
            p.push((text.to_owned(), crs.clone()));
        });
        Ok(crs)
    }

    fn parse_text(text: &str) -> Result<Self> {
        let t = text.trim();
        let code = t.strip_prefix("EPSG:").or_else(|| t.strip_prefix("epsg:")).unwrap_or(t);
        if let Ok(code) = code.parse::<u16>() {
            return Self::epsg(code);
        }
        if t.starts_with('+') {
            let proj =
                Proj::from_proj_string(t).map_err(|e| UnknownCrs { crs: t.to_owned(), reason: e.to_string() })?;
            return Ok(Self { code: None, definition: t.to_owned(), proj });
        }
        Err(UnknownCrs { crs: t.to_owned(), reason: "neither EPSG:<code> nor a PROJ string".into() })
    }

    /// WGS 84 longitude and latitude (EPSG:4326).
    pub fn wgs84() -> Self {
        thread_local! {
            static WGS84: Crs = {
                let definition = "+proj=longlat +datum=WGS84 +no_defs".to_owned();
                #[expect(clippy::expect_used, reason = "a constant definition the library parses")]
                let proj = Proj::from_proj_string(&definition).expect("the WGS 84 definition parses");
                Crs { code: Some(4326), definition, proj }
            };
        }
        WGS84.with(Clone::clone)
    }

    /// The CRS a geographic input goes onto by default, given its bounds (west, south,
    /// east, north; degrees): a transverse Mercator centred on a region, where a metre is
    /// a metre across it; WGS 84's own grid beyond [`REGION_DEGREES`], where a transverse
    /// Mercator's scale error grows (30-40 % at the corners of 90 x 50 degrees) and the
    /// globe draws the geographic grid without distortion.
    pub fn for_geographic(west: f64, south: f64, east: f64, north: f64) -> Self {
        if spans_more_than_region(west, south, east, north) {
            Self::wgs84()
        } else {
            Self::local_transverse_mercator((west + east) / 2.0, (south + north) / 2.0)
        }
    }

    /// A transverse Mercator on WGS 84 centred on `(lon, lat)` (scale 1, no false origin):
    /// metres that are metres across a region, for data given in degrees.
    pub fn local_transverse_mercator(lon: f64, lat: f64) -> Self {
        let definition =
            format!("+proj=tmerc +lat_0={lat:.9} +lon_0={lon:.9} +k=1 +x_0=0 +y_0=0 +datum=WGS84 +units=m +no_defs");
        #[expect(clippy::expect_used, reason = "a transverse Mercator with finite parameters parses")]
        let proj = Proj::from_proj_string(&definition).expect("a transverse Mercator definition parses");
        Self { code: None, definition, proj }
    }

    /// The EPSG code, when the CRS has one.
    pub fn code(&self) -> Option<u16> {
        self.code
    }

    /// The PROJ definition.
    pub fn definition(&self) -> &str {
        &self.definition
    }

    /// Longitude and latitude (degrees), not metres?
    pub fn is_geographic(&self) -> bool {
        self.proj.is_latlong()
    }

    /// `EPSG:code`, or the definition.
    pub fn name(&self) -> String {
        self.code.map_or_else(|| self.definition.clone(), |c| format!("EPSG:{c}"))
    }

    /// The CRS for people: what it is, from its definition, and its EPSG code
    /// (`UTM zone 10N, WGS 84 (EPSG:32610)`, `transverse Mercator centred on 37.9120°N
    /// 122.5830°W, WGS 84`); a projection it does not name by its PROJ definition.
    pub fn label(&self) -> String {
        let param = |key: &str| self.definition.split_whitespace().find_map(|w| w.strip_prefix(key));
        let number = |key: &str| param(key).and_then(|v| v.parse::<f64>().ok());
        let datum = match (param("+datum="), param("+ellps=")) {
            (Some("WGS84"), _) | (None, Some("WGS84")) => "WGS 84".to_owned(),
            (Some(d), _) => d.to_owned(),
            (None, Some("GRS80")) => "GRS 1980".to_owned(),
            (None, Some(e)) => e.to_owned(),
            (None, None) if number("+a=") == Some(6_378_137.0) && number("+b=") == Some(6_378_137.0) => {
                "a sphere of WGS 84's radius".to_owned()
            }
            (None, None) => "an unnamed ellipsoid".to_owned(),
        };
        let what = match param("+proj=") {
            Some("longlat") => Some(format!("longitude/latitude, {datum}")),
            Some("utm") => param("+zone=").map(|zone| {
                let hemisphere = if self.definition.contains("+south") { 'S' } else { 'N' };
                format!("UTM zone {zone}{hemisphere}, {datum}")
            }),
            Some("merc") if self.code == Some(3857) => Some("Web Mercator".to_owned()),
            Some("tmerc") => match (number("+lat_0="), number("+lon_0=")) {
                (Some(lat), Some(lon)) if self.code.is_none() => {
                    let ns = if lat < 0.0 { 'S' } else { 'N' };
                    let ew = if lon < 0.0 { 'W' } else { 'E' };
                    Some(format!("transverse Mercator centred on {:.4}°{ns} {:.4}°{ew}, {datum}", lat.abs(), lon.abs()))
                }
                _ => Some(format!("transverse Mercator, {datum}")),
            },
            _ => None,
        };
        match (what, self.code) {
            (Some(w), Some(c)) => format!("{w} (EPSG:{c})"),
            (Some(w), None) => w,
            (None, Some(c)) => format!("EPSG:{c} ({})", self.definition),
            (None, None) => self.definition.clone(),
        }
    }
}

/// A transform from one CRS to another; geographic coordinates in degrees (x = longitude).
#[derive(Clone, Debug)]
pub struct Transform {
    from: Crs,
    to: Crs,
    identity: bool,
}

impl Transform {
    /// From `from` to `to`.
    pub fn new(from: &Crs, to: &Crs) -> Self {
        Self { identity: from == to, from: from.clone(), to: to.clone() }
    }

    /// True when both CRSs are the same (points pass unchanged).
    pub fn is_identity(&self) -> bool {
        self.identity
    }

    /// `(x, y)` in `to`; `None` where the point has no image (outside a projection's domain).
    pub fn apply(&self, x: f64, y: f64) -> Option<(f64, f64)> {
        if self.identity {
            return Some((x, y));
        }
        let mut p = if self.from.is_geographic() { (x.to_radians(), y.to_radians(), 0.0) } else { (x, y, 0.0) };
        proj4rs::transform::transform(&self.from.proj, &self.to.proj, &mut p).ok()?;
        let out = if self.to.is_geographic() { (p.0.to_degrees(), p.1.to_degrees()) } else { (p.0, p.1) };
        (out.0.is_finite() && out.1.is_finite()).then_some(out)
    }
}

/// The CRS that an `SRS` text names, as [`Crs::parse`] takes it: `EPSG:xxxx` or a PROJ
/// string as they are (a compound `EPSG:h+v` by its horizontal code); WKT by its last
/// `AUTHORITY` or `ID` with an EPSG code (the CRS's own, after those of its parts; of a
/// compound CRS, its horizontal part's), or, for the ESRI WKT of `.prj` files, which carries no
/// code, by the name of a CRS of the families the tiler knows (WGS 84, NAD83 and ETRS89
/// UTM zones, Web Mercator, WGS 84 and NAD83 geographic, the Swiss and British grids).
/// `None` when it names none of these.
pub fn crs_of_srs(srs: &str) -> Option<String> {
    let t = srs.trim();
    if t.starts_with('+') {
        return Some(t.to_owned());
    }
    if t.to_ascii_uppercase().starts_with("EPSG:") {
        // A compound code (`EPSG:4326+5773`): its horizontal part.
        return Some(t.split('+').next().unwrap_or(t).to_owned());
    }
    // A compound CRS: the horizontal part comes first; the vertical part and the
    // compound's own identifier are not it.
    let upper = t.to_ascii_uppercase();
    let t =
        ["VERT_CS[", "VERTCRS[", "VERTICALCRS["].iter().filter_map(|k| upper.find(k)).min().map_or(t, |at| &t[..at]);
    let last = ["AUTHORITY[\"EPSG\",\"", "ID[\"EPSG\","]
        .iter()
        .filter_map(|key| t.rfind(key).map(|at| (at, &t[at + key.len()..])))
        .max_by_key(|(at, _)| *at);
    if let Some((_, rest)) = last {
        let code: String = rest.chars().skip_while(|c| !c.is_ascii_digit()).take_while(char::is_ascii_digit).collect();
        return (!code.is_empty()).then(|| format!("EPSG:{code}"));
    }
    esri_name(t).map(|code| format!("EPSG:{code}"))
}

/// The EPSG code of an ESRI WKT by the name of its outermost CRS (`PROJCS["…"` or
/// `GEOGCS["…"`).
fn esri_name(wkt: &str) -> Option<u16> {
    let name = ["PROJCS[\"", "GEOGCS[\""]
        .iter()
        .find_map(|key| wkt.strip_prefix(key))
        .and_then(|rest| rest.split('"').next())?
        .to_ascii_uppercase();
    let fixed = [
        ("GCS_WGS_1984", 4326),
        ("GCS_NORTH_AMERICAN_1983", 4269),
        ("WGS_1984_WEB_MERCATOR_AUXILIARY_SPHERE", 3857),
        ("WGS_1984_WEB_MERCATOR", 3857),
        ("CH1903+_LV95", 2056),
        ("CH1903_LV03", 21781),
        ("BRITISH_NATIONAL_GRID", 27700),
    ];
    if let Some((_, code)) = fixed.iter().find(|(n, _)| *n == name) {
        return Some(*code);
    }
    // UTM zones: "<datum>_UTM_ZONE_<n><N|S>".
    let (datum, zone) = name.split_once("_UTM_ZONE_")?;
    let (n, hemisphere) = zone.split_at(zone.len().checked_sub(1)?);
    let n: u16 = n.parse().ok().filter(|n| (1..=60).contains(n))?;
    match (datum, hemisphere) {
        ("WGS_1984", "N") => Some(32600 + n),
        ("WGS_1984", "S") => Some(32700 + n),
        ("NAD_1983", "N") if (1..=23).contains(&n) => Some(26900 + n),
        ("ETRS_1989", "N") if (28..=38).contains(&n) => Some(25800 + n),
        _ => None,
    }
}

/// Degrees across beyond which geographic data is more than a region: the larger of its
/// longitude span (at its middle latitude's scale) and its latitude span. A transverse
/// Mercator centred on 10 degrees has a scale error of 0.4 % at its edges, 5 degrees
/// from the central meridian.
pub const REGION_DEGREES: f64 = 10.0;

/// Does a box (west, south, east, north; degrees) span more than a region?
pub fn spans_more_than_region(west: f64, south: f64, east: f64, north: f64) -> bool {
    let middle = ((south + north) / 2.0).to_radians();
    let across = ((east - west) * middle.cos()).max(north - south);
    across > REGION_DEGREES
}

#[cfg(test)]
mod tests {
    use super::{Crs, Transform, crs_of_srs};

    #[test]
    fn the_crs_is_the_last_epsg_authority() {
        let wkt1 =
            r#"PROJCS["WGS 84 / UTM zone 33N",GEOGCS["WGS 84",AUTHORITY["EPSG","4326"]],AUTHORITY["EPSG","32633"]]"#;
        assert_eq!(crs_of_srs(wkt1).as_deref(), Some("EPSG:32633"));
        let wkt2 = r#"PROJCRS["x",BASEGEOGCRS["y",ID["EPSG",4326]],ID["EPSG",25832]]"#;
        assert_eq!(crs_of_srs(wkt2).as_deref(), Some("EPSG:25832"));
        assert_eq!(crs_of_srs(" EPSG:2056 ").as_deref(), Some("EPSG:2056"));
        // Compound CRSs: their horizontal part.
        assert_eq!(crs_of_srs("EPSG:4326+5773").as_deref(), Some("EPSG:4326"));
        let compound = r#"COMPD_CS["WGS 84 + EGM96 height",GEOGCS["WGS 84",AUTHORITY["EPSG","4326"]],VERT_CS["EGM96 height",AUTHORITY["EPSG","5773"]]]"#;
        assert_eq!(crs_of_srs(compound).as_deref(), Some("EPSG:4326"));
        let compound2 = r#"COMPOUNDCRS["x",PROJCRS["ETRS89 / UTM 32N",ID["EPSG",25832]],VERTCRS["DHHN2016 height",ID["EPSG",7837]],ID["EPSG",4647]]"#;
        assert_eq!(crs_of_srs(compound2).as_deref(), Some("EPSG:25832"));
        assert_eq!(crs_of_srs(r#"LOCAL_CS["somewhere"]"#), None);
    }

    #[test]
    fn a_crs_parsed_again_is_the_same_and_errors_are_not_kept() {
        let tm = "+proj=tmerc +lat_0=37.5 +lon_0=-122.5 +k=1 +x_0=0 +y_0=0 +datum=WGS84 +units=m +no_defs";
        let (a, b) = (Crs::parse(tm).unwrap(), Crs::parse(tm).unwrap());
        assert_eq!((a.definition(), a.code()), (b.definition(), b.code()));
        let to = Transform::new(&b, &Crs::wgs84());
        let (lon, lat) = to.apply(0.0, 0.0).unwrap();
        assert!((lon + 122.5).abs() < 1e-9 && (lat - 37.5).abs() < 1e-9, "{lon} {lat}");
        // Other texts, more than the few kept, then the first again.
        for code in [4326, 3857, 32610, 32611, 2056, 27700, 21781, 25832, 25833] {
            assert_eq!(Crs::parse(&format!("EPSG:{code}")).unwrap().code(), Some(code));
        }
        assert_eq!(Crs::parse(tm).unwrap().definition(), tm);
        for _ in 0..2 {
            assert!(Crs::parse("+proj=nonesuch").is_err());
        }
    }

    #[test]
    fn crs_are_labelled_for_people() {
        use crate::Crs;
        assert_eq!(Crs::wgs84().label(), "longitude/latitude, WGS 84 (EPSG:4326)");
        assert_eq!(Crs::parse("EPSG:32610").unwrap().label(), "UTM zone 10N, WGS 84 (EPSG:32610)");
        assert_eq!(Crs::parse("EPSG:3857").unwrap().label(), "Web Mercator (EPSG:3857)");
        let tm = Crs::local_transverse_mercator(-122.583, 37.912);
        assert_eq!(tm.label(), "transverse Mercator centred on 37.9120°N 122.5830°W, WGS 84");
        let other = Crs::parse("+proj=merc +datum=WGS84 +units=m").unwrap();
        assert_eq!(other.label(), "+proj=merc +datum=WGS84 +units=m");
    }

    #[test]
    fn esri_wkt_is_known_by_its_name() {
        let utm = r#"PROJCS["WGS_1984_UTM_Zone_10N",GEOGCS["GCS_WGS_1984",DATUM["D_WGS_1984"]],UNIT["Meter",1.0]]"#;
        assert_eq!(crs_of_srs(utm).as_deref(), Some("EPSG:32610"));
        assert_eq!(crs_of_srs(r#"PROJCS["WGS_1984_UTM_Zone_23S",x]"#).as_deref(), Some("EPSG:32723"));
        assert_eq!(crs_of_srs(r#"PROJCS["NAD_1983_UTM_Zone_11N",x]"#).as_deref(), Some("EPSG:26911"));
        assert_eq!(crs_of_srs(r#"PROJCS["ETRS_1989_UTM_Zone_32N",x]"#).as_deref(), Some("EPSG:25832"));
        assert_eq!(crs_of_srs(r#"GEOGCS["GCS_WGS_1984",DATUM["D_WGS_1984"]]"#).as_deref(), Some("EPSG:4326"));
        assert_eq!(crs_of_srs(r#"PROJCS["CH1903+_LV95",x]"#).as_deref(), Some("EPSG:2056"));
        // Names the table does not hold, or zones out of a datum's range.
        assert_eq!(crs_of_srs(r#"PROJCS["NAD_1983_UTM_Zone_40N",x]"#), None);
        assert_eq!(crs_of_srs(r#"PROJCS["WGS_1984_UTM_Zone_61N",x]"#), None);
        assert_eq!(crs_of_srs(r#"PROJCS["Lambert_Somewhere",x]"#), None);
    }
}
