//! Vertical datums: geoid models read from their grid files (PROJ's `.gtx`, or a
//! GeoTIFF), found where PROJ keeps them, read bilinearly as PROJ reads them; the datum an
//! input's file names (GeoTIFF `VerticalCSTypeGeoKey`, a compound CRS's WKT in a `.prj`,
//! `.aux.xml` or VRT); and the datum a person names (`--vertical-datum`).

use std::path::{Path, PathBuf};

use terrastream_format::{HeightReference, Undulation, VerticalDatum};

use crate::error::{Error, Result};

/// Nodes of a geoid lattice an archive carries at most (1 MiB of f32 values); a footprint
/// that needs more carries every second (third, ...) node.
pub const MAX_UNDULATION_NODES: usize = 1 << 18;

/// A vertical datum as named, before its geoid grid is read.
#[derive(Clone, Debug, PartialEq, Eq)]
pub enum DatumName {
    /// Heights above the WGS 84 ellipsoid (EPSG:4979).
    Ellipsoid,
    /// Heights above a geoid model.
    Geoid {
        /// "EGM96", "EGM2008", or the grid's file name.
        model: String,
        /// The vertical CRS's EPSG code, where it has one.
        epsg: Option<u32>,
        /// Grid files that hold the model, in the order they are looked for: file names
        /// looked up where PROJ keeps its grids, or paths.
        grids: Vec<String>,
    },
    /// Nothing known.
    Unknown,
}

impl DatumName {
    /// EGM96 height (EPSG:5773): SRTM's, most global DEMs'.
    pub fn egm96() -> Self {
        Self::Geoid {
            model: "EGM96".into(),
            epsg: Some(5773),
            grids: vec!["egm96_15.gtx".into(), "us_nga_egm96_15.tif".into()],
        }
    }

    /// EGM2008 height (EPSG:3855): Copernicus GLO-30's.
    pub fn egm2008() -> Self {
        Self::Geoid {
            model: "EGM2008".into(),
            epsg: Some(3855),
            grids: vec!["us_nga_egm08_25.tif".into(), "egm08_25.gtx".into()],
        }
    }

    /// A datum by its EPSG code: 4979 (and 4326, 7030 as GeoTIFF writers put them)
    /// ellipsoidal, 5773 EGM96, 3855 EGM2008; None for codes with no model here.
    pub fn from_epsg(code: u32) -> Option<Self> {
        match code {
            4979 | 4326 | 4937 | 7030 | 6326 => Some(Self::Ellipsoid),
            5773 | 5798 => Some(Self::egm96()),
            3855 => Some(Self::egm2008()),
            _ => None,
        }
    }

    /// The datum an archive records, as a name to load again (its geoid's grid by the
    /// file name recorded); None for an unknown one.
    pub fn of_record(d: &VerticalDatum) -> Option<Self> {
        match d.reference {
            HeightReference::Unknown => None,
            HeightReference::Ellipsoid => Some(Self::Ellipsoid),
            HeightReference::Geoid => d.epsg.and_then(Self::from_epsg).or_else(|| {
                let model = d.geoid.clone().unwrap_or_else(|| "unnamed".into());
                Some(Self::Geoid { model, epsg: d.epsg, grids: d.grid.iter().cloned().collect() })
            }),
        }
    }

    /// Parses what a person writes: `4979`, `EPSG:5773`, `3855`, `ellipsoid`, `egm96`,
    /// `egm2008`, `unknown`, or `geoid:FILE` (a `.gtx` or GeoTIFF geoid grid).
    ///
    /// # Errors
    /// A line saying what is accepted.
    pub fn parse(text: &str) -> std::result::Result<Self, String> {
        let t = text.trim();
        if let Some(file) = t.strip_prefix("geoid:") {
            if file.is_empty() {
                return Err("geoid: needs a grid file, as in geoid:egm96_15.gtx".into());
            }
            let model =
                Path::new(file).file_name().map_or_else(|| file.to_owned(), |n| n.to_string_lossy().into_owned());
            return Ok(Self::Geoid { model, epsg: None, grids: vec![file.to_owned()] });
        }
        let lower = t.to_ascii_lowercase();
        match lower.as_str() {
            "ellipsoid" | "ellipsoidal" | "wgs84" => return Ok(Self::Ellipsoid),
            "egm96" => return Ok(Self::egm96()),
            "egm2008" | "egm08" => return Ok(Self::egm2008()),
            "unknown" => return Ok(Self::Unknown),
            _ => {}
        }
        let code = lower.strip_prefix("epsg:").unwrap_or(&lower);
        let code: u32 = code.parse().map_err(|_| {
            format!("{t:?} is not a vertical datum: give an EPSG code (4979, 5773, 3855), ellipsoid, egm96, egm2008, unknown or geoid:FILE")
        })?;
        Self::from_epsg(code).ok_or_else(|| {
            format!("EPSG:{code} has no geoid model here: name its grid with geoid:FILE (a .gtx or GeoTIFF), or use 4979, 5773, 3855")
        })
    }

    /// Reads what the datum needs (a geoid's grid) and makes the archive's record of it,
    /// with the undulation over `lon_lat` (west, south, east, north in degrees).
    ///
    /// # Errors
    /// As [`DatumName::load`].
    pub fn resolve(&self, lon_lat: Option<[f64; 4]>) -> Result<VerticalDatum> {
        Ok(self.load()?.over(lon_lat))
    }

    /// Reads what the datum needs: a geoid's grid, found as [`GeoidGrid::find`] finds it.
    ///
    /// # Errors
    /// [`Error::GeoidMissing`] naming the grid and where it was looked for; the grid's
    /// own errors.
    pub fn load(&self) -> Result<LoadedDatum> {
        let grid = match self {
            Self::Geoid { grids, .. } => Some(GeoidGrid::find(grids)?),
            _ => None,
        };
        Ok(LoadedDatum { name: self.clone(), grid })
    }

    /// The person's name of it.
    pub fn describe(&self) -> String {
        match self {
            Self::Ellipsoid => "WGS 84 ellipsoid (EPSG:4979)".into(),
            Self::Geoid { model, epsg: Some(c), .. } => format!("{model} geoid (EPSG:{c})"),
            Self::Geoid { model, .. } => format!("{model} geoid"),
            Self::Unknown => "unknown".into(),
        }
    }
}

/// A datum with what it needs read: the archive's record of it over any footprint.
#[derive(Clone, Debug)]
pub struct LoadedDatum {
    name: DatumName,
    grid: Option<GeoidGrid>,
}

impl LoadedDatum {
    /// The archive's record: the datum, and a geoid's undulation over `lon_lat` (west,
    /// south, east, north in degrees) where it is known.
    pub fn over(&self, lon_lat: Option<[f64; 4]>) -> VerticalDatum {
        match (&self.name, &self.grid) {
            (DatumName::Ellipsoid, _) => VerticalDatum::ellipsoid(),
            (DatumName::Geoid { model, epsg, .. }, grid) => VerticalDatum {
                reference: HeightReference::Geoid,
                epsg: *epsg,
                geoid: Some(model.clone()),
                grid: grid.as_ref().and_then(|g| g.path.file_name()).map(|n| n.to_string_lossy().into_owned()),
                undulation: grid.as_ref().zip(lon_lat).map(|(g, b)| g.over(b)),
            },
            (DatumName::Unknown, _) => VerticalDatum::default(),
        }
    }

    /// The grid read, for a geoid.
    pub fn grid(&self) -> Option<&GeoidGrid> {
        self.grid.as_ref()
    }

    /// The datum as named.
    pub fn name(&self) -> &DatumName {
        &self.name
    }

    /// Its surface's height above the WGS 84 ellipsoid at `(lon, lat)`: N for a geoid
    /// (0 off its grid), 0 for the ellipsoid.
    pub fn undulation(&self, lon: f64, lat: f64) -> f64 {
        self.grid.as_ref().and_then(|g| g.at(lon, lat)).unwrap_or(0.0)
    }
}

/// What turns heights of one vertical datum into another's on a mosaic's output grid:
/// `N_from - N_to` at each output sample, exact on a lattice every [`SHIFT_CELL`] samples
/// over the input's footprint, bilinear between (the undulation bends little over that).
pub(crate) struct DatumShift {
    from: DatumName,
    /// Output column and row of lattice point (0, 0).
    corner: (i64, i64),
    /// Lattice points across and down.
    size: (usize, usize),
    values: Vec<f32>,
    /// The lowest and highest shift over the input's footprint (a metre's margin).
    pub(crate) range: (f32, f32),
}

/// Output samples between the exact shifts of a [`DatumShift`].
const SHIFT_CELL: i64 = 32;

impl std::fmt::Debug for DatumShift {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        write!(f, "DatumShift(from {})", self.from.describe())
    }
}

impl DatumShift {
    /// The shift from `from` to `to` over output columns and rows `columns`, `rows`
    /// (inclusive) of a grid whose north-west corner is `origin` and whose samples are
    /// `pixel` apart in the CRS that `to_lon_lat` takes to longitude and latitude.
    pub(crate) fn new(
        from: &LoadedDatum,
        to: &LoadedDatum,
        to_lon_lat: &crate::Transform,
        (origin, pixel): ([f64; 2], (f64, f64)),
        (columns, rows): ((i64, i64), (i64, i64)),
    ) -> Self {
        let count = |a: i64, b: i64| usize::try_from((b - a).max(0) / SHIFT_CELL + 2).unwrap_or(2);
        let size = (count(columns.0, columns.1), count(rows.0, rows.1));
        let mut values = Vec::with_capacity(size.0 * size.1);
        let (mut lo, mut hi) = (f64::INFINITY, f64::NEG_INFINITY);
        for j in 0..size.1 {
            for i in 0..size.0 {
                #[expect(clippy::cast_precision_loss, reason = "pixel indices")]
                let (c, r) = ((columns.0 + i as i64 * SHIFT_CELL) as f64, (rows.0 + j as i64 * SHIFT_CELL) as f64);
                let (x, y) = (origin[0] + (c + 0.5) * pixel.0, origin[1] - (r + 0.5) * pixel.1);
                let v = to_lon_lat
                    .apply(x, y)
                    .map_or(0.0, |(lon, lat)| from.undulation(lon, lat) - to.undulation(lon, lat));
                (lo, hi) = (lo.min(v), hi.max(v));
                #[expect(clippy::cast_possible_truncation, reason = "metres")]
                values.push(v as f32);
            }
        }
        #[expect(clippy::cast_possible_truncation, reason = "metres")]
        let range = ((lo - 1.0) as f32, (hi + 1.0) as f32);
        Self { from: from.name.clone(), corner: (columns.0, rows.0), size, values, range }
    }

    /// Whether two inputs' heights are of one datum (both unconverted, or converted from
    /// the same).
    pub(crate) fn same(a: Option<&Self>, b: Option<&Self>) -> bool {
        match (a, b) {
            (None, None) => true,
            (Some(a), Some(b)) => a.from == b.from,
            _ => false,
        }
    }

    /// The shift at output sample `(column, row)`: bilinear on the lattice.
    fn at(&self, column: i64, row: i64) -> f32 {
        #[expect(clippy::cast_precision_loss, reason = "pixel offsets")]
        let (x, y) =
            ((column - self.corner.0) as f32 / SHIFT_CELL as f32, (row - self.corner.1) as f32 / SHIFT_CELL as f32);
        #[expect(clippy::cast_precision_loss, reason = "lattice sizes")]
        let (x, y) = (x.clamp(0.0, (self.size.0 - 1) as f32), y.clamp(0.0, (self.size.1 - 1) as f32));
        #[expect(clippy::cast_possible_truncation, clippy::cast_sign_loss, reason = "clamped")]
        let (i, j) = ((x as usize).min(self.size.0 - 2), (y as usize).min(self.size.1 - 2));
        #[expect(clippy::cast_precision_loss, reason = "lattice indices")]
        let (fx, fy) = (x - i as f32, y - j as f32);
        let v = |i: usize, j: usize| self.values[j * self.size.0 + i];
        let top = v(i, j) + (v(i + 1, j) - v(i, j)) * fx;
        let bottom = v(i, j + 1) + (v(i + 1, j + 1) - v(i, j + 1)) * fx;
        top + (bottom - top) * fy
    }

    /// Adds the shift to the samples of output row `row` from column `c0` that `empty`
    /// says this input just filled.
    pub(crate) fn lift<K: crate::MosaicKind>(&self, row: u32, c0: usize, out: &mut [K::Value], empty: &[bool]) {
        let (row, c0) = (i64::from(row), i64::try_from(c0).unwrap_or(i64::MAX));
        // Exact (on the lattice) every SHIFT_CELL samples, linear between.
        let cell = usize::try_from(SHIFT_CELL).unwrap_or(32);
        for (s, (values, empty)) in out.chunks_mut(cell).zip(empty.chunks(cell)).enumerate() {
            let start = c0 + i64::try_from(s * cell).unwrap_or(0);
            let a = self.at(start, row);
            #[expect(clippy::cast_precision_loss, reason = "at most SHIFT_CELL")]
            let step = (self.at(start + SHIFT_CELL, row) - a) / SHIFT_CELL as f32;
            let mut shift = a;
            // A sample still without data stays so (NaN plus the shift is NaN).
            for (v, &was_empty) in values.iter_mut().zip(empty) {
                if was_empty {
                    K::lift(v, shift);
                }
                shift += step;
            }
        }
    }
}

/// Folders where PROJ keeps its grids, in the order PROJ looks: `$PROJ_DATA` (or the older
/// `$PROJ_LIB`), the user's PROJ folder, then the system's.
pub fn proj_data_dirs() -> Vec<PathBuf> {
    let mut dirs = vec![];
    for var in ["PROJ_DATA", "PROJ_LIB"] {
        if let Some(v) = std::env::var_os(var) {
            dirs.extend(std::env::split_paths(&v));
        }
    }
    if let Some(xdg) = std::env::var_os("XDG_DATA_HOME") {
        dirs.push(PathBuf::from(xdg).join("proj"));
    } else if let Some(home) = std::env::var_os("HOME") {
        dirs.push(PathBuf::from(home).join(".local/share/proj"));
    }
    dirs.extend(["/usr/local/share/proj", "/usr/share/proj"].map(PathBuf::from));
    dirs
}

/// A geoid model's grid: N (metres above the WGS 84 ellipsoid) on a lattice of longitude
/// and latitude nodes.
#[derive(Clone, Debug)]
pub struct GeoidGrid {
    path: PathBuf,
    /// Longitude and latitude of the south-west node.
    west: f64,
    south: f64,
    /// Degrees between nodes (lon, lat).
    step: [f64; 2],
    columns: usize,
    rows: usize,
    /// Rows from the south.
    values: Vec<f32>,
}

/// Values of a `.gtx` that mean "no value" (NOAA's grids).
const GTX_NODATA: f32 = -88.8888;

impl GeoidGrid {
    /// The first of `grids` found: a path as given, else a file name in
    /// [`proj_data_dirs`].
    ///
    /// # Errors
    /// [`Error::GeoidMissing`] naming the grids and every folder looked in.
    pub fn find(grids: &[String]) -> Result<Self> {
        let dirs = proj_data_dirs();
        for g in grids {
            let p = Path::new(g);
            if p.components().count() > 1 || p.is_file() {
                if p.is_file() {
                    return Self::open(p);
                }
                continue;
            }
            if let Some(found) = dirs.iter().map(|d| d.join(g)).find(|p| p.is_file()) {
                return Self::open(&found);
            }
        }
        Err(Error::GeoidMissing { grids: grids.to_vec(), looked: dirs })
    }

    /// Reads a grid file: NOAA/PROJ `.gtx`, or a single-band geographic GeoTIFF.
    ///
    /// # Errors
    /// An error naming the file: unreadable, cut short, not a geographic lattice.
    pub fn open(path: &Path) -> Result<Self> {
        let ext = path.extension().map(|e| e.to_string_lossy().to_ascii_lowercase());
        match ext.as_deref() {
            Some("gtx") => Self::gtx(path),
            Some("tif" | "tiff") => Self::geotiff(path),
            _ => Err(Error::unsupported(path, "a geoid grid is a .gtx or a GeoTIFF (.tif)")),
        }
    }

    fn gtx(path: &Path) -> Result<Self> {
        let bytes = std::fs::read(path).map_err(|e| Error::file(path, e))?;
        let damaged = |why: String| Error::damaged(path, why);
        if bytes.len() < 40 {
            return Err(damaged(format!("{} bytes: a .gtx has a 40-byte header", bytes.len())));
        }
        let f = |i: usize| f64::from_be_bytes(bytes[i..i + 8].try_into().unwrap_or_default());
        let n = |i: usize| i32::from_be_bytes(bytes[i..i + 4].try_into().unwrap_or_default());
        let (south, mut west, dlat, dlon, rows, columns) = (f(0), f(8), f(16), f(24), n(32), n(36));
        let (Ok(rows), Ok(columns)) = (usize::try_from(rows), usize::try_from(columns)) else {
            return Err(damaged(format!("{rows} x {columns} nodes")));
        };
        let ok = |v: f64| v.is_finite() && v > 0.0;
        if rows == 0 || columns == 0 || !ok(dlat) || !ok(dlon) || !south.is_finite() || !west.is_finite() {
            return Err(damaged(format!("header: {rows} x {columns} nodes, steps {dlon} x {dlat}")));
        }
        let need = rows.checked_mul(columns).and_then(|c| c.checked_mul(4)).and_then(|c| c.checked_add(40));
        if need != Some(bytes.len()) {
            return Err(damaged(format!("{} bytes where {rows} x {columns} nodes need {need:?}", bytes.len())));
        }
        if west >= 180.0 {
            west -= 360.0;
        }
        let values = bytes[40..]
            .chunks_exact(4)
            .map(|c| {
                let v = f32::from_be_bytes([c[0], c[1], c[2], c[3]]);
                if v == GTX_NODATA { f32::NAN } else { v }
            })
            .collect();
        Ok(Self { path: path.to_path_buf(), west, south, step: [dlon, dlat], columns, rows, values })
    }

    fn geotiff(path: &Path) -> Result<Self> {
        let raster = crate::read_geotiff(path)?;
        let bounds = raster.georeference.as_ref().and_then(|g| g.lat_lon_bounds).ok_or_else(|| {
            Error::unsupported(path, "a geoid grid must be a GeoTIFF in longitude and latitude (a geographic CRS)")
        })?;
        let [w, s, e, n] = bounds;
        let (columns, rows) = (raster.width as usize, raster.height as usize);
        let step = [(e - w) / f64::from(raster.width), (n - s) / f64::from(raster.height)];
        // Nodes at pixel centres; rows from the south.
        let mut values = Vec::with_capacity(raster.data.len());
        for r in (0..rows).rev() {
            values.extend_from_slice(&raster.data[r * columns..(r + 1) * columns]);
        }
        let (west, south) = (w + step[0] / 2.0, s + step[1] / 2.0);
        Ok(Self { path: path.to_path_buf(), west, south, step, columns, rows, values })
    }

    /// Whether the columns go round the Earth (the last wraps to the first).
    fn global(&self) -> bool {
        #[expect(clippy::cast_precision_loss, reason = "node counts are small")]
        let span = self.columns as f64 * self.step[0];
        span >= 360.0 - self.step[0] * 0.5
    }

    /// The file read.
    pub fn path(&self) -> &Path {
        &self.path
    }

    /// N at node `(i, j)` (column from the west, row from the south), wrapping columns
    /// round a global grid; None off the grid or where it has no value.
    fn node(&self, i: i64, j: i64) -> Option<f64> {
        let (cols, rows) = (i64::try_from(self.columns).ok()?, i64::try_from(self.rows).ok()?);
        let i = if self.global() { i.rem_euclid(cols) } else { i };
        if !(0..cols).contains(&i) || !(0..rows).contains(&j) {
            return None;
        }
        let v = self.values[usize::try_from(j * cols + i).ok()?];
        v.is_finite().then_some(f64::from(v))
    }

    /// N at `(lon, lat)` in degrees, bilinear between the four nodes around it, as PROJ
    /// interpolates its vertical grids; None outside the grid or next to a node without
    /// a value.
    pub fn at(&self, lon: f64, lat: f64) -> Option<f64> {
        let mut x = (lon - self.west) / self.step[0];
        if self.global() {
            x = x.rem_euclid(360.0 / self.step[0]);
        }
        let y = (lat - self.south) / self.step[1];
        #[expect(clippy::cast_precision_loss, reason = "node counts are small")]
        let (cols, rows) = (self.columns as f64, self.rows as f64);
        let eps = 1e-9;
        if !(x.is_finite() && y.is_finite())
            || y < -eps
            || y > rows - 1.0 + eps
            || (!self.global() && (x < -eps || x > cols - 1.0 + eps))
        {
            return None;
        }
        let (x, y) = (x.max(0.0), y.clamp(0.0, rows - 1.0));
        #[expect(clippy::cast_possible_truncation, reason = "within the grid")]
        let (i, j) = (x.floor() as i64, (y.floor() as i64).min(i64::try_from(self.rows).ok()? - 1));
        let (fx, fy) = (x - x.floor(), y - y.floor());
        let j1 = if fy > 0.0 { j + 1 } else { j };
        let i1 = if fx > 0.0 { i + 1 } else { i };
        let bottom = self.node(i, j)? * (1.0 - fx) + self.node(i1, j)? * fx;
        let top = self.node(i, j1)? * (1.0 - fx) + self.node(i1, j1)? * fx;
        Some(bottom * (1.0 - fy) + top * fy)
    }

    /// The grid's nodes over `[west, south, east, north]` (degrees) and one more on
    /// every side, rows from the north, as an archive carries them; every k-th node
    /// where more than [`MAX_UNDULATION_NODES`] would be needed. Nodes without a value
    /// (or off a regional grid) take the nearest row's or column's value.
    pub fn over(&self, [w, s, e, n]: [f64; 4]) -> Undulation {
        #[expect(clippy::cast_possible_truncation, reason = "degrees over steps: small")]
        let index = |v: f64, origin: f64, step: f64, up: bool| {
            let f = (v - origin) / step;
            (if up { f.ceil() } else { f.floor() }) as i64
        };
        let (mut i0, mut i1) =
            (index(w, self.west, self.step[0], false) - 1, index(e, self.west, self.step[0], true) + 1);
        let (mut j0, mut j1) =
            (index(s, self.south, self.step[1], false) - 1, index(n, self.south, self.step[1], true) + 1);
        let (cols, rows) =
            (i64::try_from(self.columns).unwrap_or(i64::MAX), i64::try_from(self.rows).unwrap_or(i64::MAX));
        j0 = j0.max(0);
        j1 = j1.min(rows - 1).max(j0);
        if !self.global() {
            i0 = i0.max(0);
            i1 = i1.min(cols - 1).max(i0);
        } else if i1 - i0 >= cols {
            i1 = i0 + cols;
        }
        let mut stride = 1_i64;
        while ((i1 - i0) / stride + 1) * ((j1 - j0) / stride + 1)
            > i64::try_from(MAX_UNDULATION_NODES).unwrap_or(i64::MAX)
        {
            stride += 1;
        }
        let across: Vec<i64> = (0..=(i1 - i0) / stride).map(|k| i0 + k * stride).collect();
        let down: Vec<i64> = (0..=(j1 - j0) / stride).map(|k| j1 - k * stride).collect();
        let mut metres = Vec::with_capacity(across.len() * down.len());
        for &j in &down {
            for &i in &across {
                let v = self.node(i, j).or_else(|| self.nearest(i, j)).unwrap_or(0.0);
                #[expect(clippy::cast_possible_truncation, reason = "metres to the millimetre fit f32")]
                metres.push(((v * 1000.0).round() / 1000.0) as f32);
            }
        }
        #[expect(clippy::cast_precision_loss, reason = "node indices are small")]
        let (west, north, step) = (
            self.west + i0 as f64 * self.step[0],
            self.south + j1 as f64 * self.step[1],
            [self.step[0] * stride as f64, self.step[1] * stride as f64],
        );
        Undulation {
            west,
            north,
            step,
            columns: u32::try_from(across.len()).unwrap_or(u32::MAX),
            rows: u32::try_from(down.len()).unwrap_or(u32::MAX),
            metres,
        }
    }

    /// The value of the nearest node with one along the row, then the column.
    fn nearest(&self, i: i64, j: i64) -> Option<f64> {
        let (cols, rows) = (i64::try_from(self.columns).ok()?, i64::try_from(self.rows).ok()?);
        let (ci, cj) = (i.clamp(0, cols - 1), j.clamp(0, rows - 1));
        (0..cols.max(rows)).find_map(|d| {
            [(ci - d, cj), (ci + d, cj), (ci, cj - d), (ci, cj + d)].into_iter().find_map(|(a, b)| self.node(a, b))
        })
    }
}

/// The vertical datum `path`'s own files name, if any: a GeoTIFF's
/// `VerticalCSTypeGeoKey`, or the vertical part of a compound CRS in the WKT of a VRT's
/// `<SRS>`, a `.prj` or a GDAL `.aux.xml` beside it.
///
/// # Errors
/// An error naming the file for a vertical CRS the tiler has no model of (with how to
/// name its grid), or a file that cannot be read.
pub fn datum_of_input(path: &Path) -> Result<Option<DatumName>> {
    let mut texts: Vec<(PathBuf, String)> = vec![];
    if crate::is_vrt(path) {
        let text = std::fs::read_to_string(path).map_err(|e| Error::file(path, e))?;
        texts.push((path.to_path_buf(), text));
    } else {
        let lower = path.extension().map(|e| e.to_string_lossy().to_ascii_lowercase());
        if matches!(lower.as_deref(), Some("tif" | "tiff"))
            && let Ok(file) = crate::open_elevation(path, None)
            && let Some(code) = file.vertical_code()
        {
            return DatumName::from_epsg(code).map(Some).ok_or_else(|| unmodelled(path, &format!("EPSG:{code}")));
        }
        let mut aux = path.as_os_str().to_owned();
        aux.push(".aux.xml");
        for side in [path.with_extension("prj"), path.with_extension("PRJ"), PathBuf::from(aux)] {
            if side.is_file() {
                let text = std::fs::read_to_string(&side).map_err(|e| Error::file(&side, e))?;
                texts.push((side, text));
            }
        }
    }
    for (file, text) in texts {
        if let Some(found) = datum_of_wkt(&text) {
            return found.map(Some).map_err(|what| unmodelled(&file, &what));
        }
    }
    Ok(None)
}

fn unmodelled(path: &Path, what: &str) -> Error {
    Error::unsupported(
        path,
        format!(
            "its heights are in {what}, which has no geoid model here: name its grid with --vertical-datum geoid:FILE"
        ),
    )
}

/// The vertical datum of a WKT (1 or 2) CRS that has a vertical part: None where it has
/// none; an error naming it where it has one with no model here.
pub fn datum_of_wkt(wkt: &str) -> Option<std::result::Result<DatumName, String>> {
    let upper = wkt.to_ascii_uppercase();
    let at = ["VERT_CS[", "VERTCRS[", "VERTICALCRS["].iter().filter_map(|k| upper.find(k)).min()?;
    let vertical = &upper[at..];
    let compact: String = vertical.chars().filter(|c| !c.is_whitespace()).collect();
    // The vertical CRS's own identifier is its last AUTHORITY/ID before the text ends.
    let code = ["AUTHORITY[\"EPSG\",\"", "ID[\"EPSG\","]
        .iter()
        .filter_map(|k| compact.rfind(k).map(|i| &compact[i + k.len()..]))
        .filter_map(|rest| {
            rest.trim_start_matches('"').split(|c: char| !c.is_ascii_digit()).next()?.parse::<u32>().ok()
        })
        .next();
    if compact.contains("EGM2008") || code == Some(3855) {
        return Some(Ok(DatumName::egm2008()));
    }
    if compact.contains("EGM96") || code == Some(5773) {
        return Some(Ok(DatumName::egm96()));
    }
    if compact.contains("ELLIPSOID")
        && !compact.contains("GEOID")
        && code.is_none_or(|c| DatumName::from_epsg(c) == Some(DatumName::Ellipsoid))
    {
        return Some(Ok(DatumName::Ellipsoid));
    }
    let name = vertical.split('"').nth(1).unwrap_or("a vertical CRS").to_owned();
    Some(code.and_then(DatumName::from_epsg).ok_or(match code {
        Some(c) => format!("{name} (EPSG:{c})"),
        None => name,
    }))
}

#[cfg(test)]
#[allow(clippy::cast_possible_truncation, reason = "test values")]
mod tests {
    use super::*;

    #[test]
    fn names_parse() {
        assert_eq!(DatumName::parse("4979"), Ok(DatumName::Ellipsoid));
        assert_eq!(DatumName::parse("EPSG:5773"), Ok(DatumName::egm96()));
        assert_eq!(DatumName::parse("epsg:3855"), Ok(DatumName::egm2008()));
        assert_eq!(DatumName::parse("unknown"), Ok(DatumName::Unknown));
        let DatumName::Geoid { model, grids, epsg } = DatumName::parse("geoid:/data/g2018u0.gtx").unwrap() else {
            panic!("a geoid")
        };
        assert_eq!((model.as_str(), grids, epsg), ("g2018u0.gtx", vec!["/data/g2018u0.gtx".to_owned()], None));
        let e = DatumName::parse("5703").unwrap_err();
        assert!(e.contains("EPSG:5703") && e.contains("geoid:FILE"), "{e}");
        assert!(DatumName::parse("sea").unwrap_err().contains("EPSG code"));
    }

    #[test]
    fn compound_wkt_names_its_vertical_part() {
        let wkt1 = r#"COMPD_CS["WGS 84 + EGM96 height",GEOGCS["WGS 84",DATUM["WGS_1984",SPHEROID["WGS 84",6378137,298.257223563]],AUTHORITY["EPSG","4326"]],VERT_CS["EGM96 height",VERT_DATUM["EGM96 geoid",2005],UNIT["metre",1],AUTHORITY["EPSG","5773"]]]"#;
        assert_eq!(datum_of_wkt(wkt1), Some(Ok(DatumName::egm96())));
        let wkt2 = r#"COMPOUNDCRS["x",GEOGCRS["WGS 84",DATUM["World Geodetic System 1984",ELLIPSOID["WGS 84",6378137,298.257223563]]],VERTCRS["EGM2008 height",VDATUM["EGM2008 geoid"],CS[vertical,1],AXIS["gravity-related height (H)",up],ID["EPSG",3855]]]"#;
        assert_eq!(datum_of_wkt(wkt2), Some(Ok(DatumName::egm2008())));
        let navd = r#"COMPD_CS["NAD83 + NAVD88",GEOGCS["NAD83"],VERT_CS["NAVD88 height",VERT_DATUM["North American Vertical Datum 1988",2005],AUTHORITY["EPSG","5703"]]]"#;
        assert_eq!(datum_of_wkt(navd), Some(Err("NAVD88 HEIGHT (EPSG:5703)".to_owned())));
        assert_eq!(datum_of_wkt(r#"GEOGCS["WGS 84",DATUM["WGS_1984"]]"#), None);
    }

    fn write_gtx(path: &Path, south: f64, west: f64, step: f64, rows: i32, cols: i32, f: impl Fn(f64, f64) -> f32) {
        let mut b = vec![];
        for v in [south, west, step, step] {
            b.extend_from_slice(&v.to_be_bytes());
        }
        b.extend_from_slice(&rows.to_be_bytes());
        b.extend_from_slice(&cols.to_be_bytes());
        for j in 0..rows {
            for i in 0..cols {
                b.extend_from_slice(&f(west + f64::from(i) * step, south + f64::from(j) * step).to_be_bytes());
            }
        }
        std::fs::write(path, b).unwrap();
    }

    #[test]
    fn gtx_reads_bilinear_and_wraps_round_the_earth() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("plane.gtx");
        // A global 1-degree grid from 0 E (as some .gtx start): N = lat / 10 + 1.
        write_gtx(&path, -90.0, 0.0, 1.0, 181, 360, |_, lat| (lat / 10.0 + 1.0) as f32);
        let g = GeoidGrid::open(&path).unwrap();
        for (lon, lat) in [(0.0, 0.0), (-122.6, 37.9), (179.7, -45.25), (359.9, 89.5), (-180.0, -90.0)] {
            let n = g.at(lon, lat).unwrap();
            assert!((n - (lat / 10.0 + 1.0)).abs() < 1e-5, "{lon},{lat}: {n}");
        }
        let u = g.over([-123.0, 37.0, -122.0, 38.0]);
        assert_eq!((u.columns, u.rows), (4, 4), "{u:?}");
        assert!((u.at(-122.6, 37.9) - 4.79).abs() < 1e-3, "{}", u.at(-122.6, 37.9));
        assert!(g.over([-180.0, -90.0, 180.0, 90.0]).metres.len() <= MAX_UNDULATION_NODES);
        // Cut short: an error naming the file.
        let bytes = std::fs::read(&path).unwrap();
        std::fs::write(&path, &bytes[..1000]).unwrap();
        let e = GeoidGrid::open(&path).unwrap_err().to_string();
        assert!(e.contains("plane.gtx") && e.contains("bytes"), "{e}");
    }

    #[test]
    fn a_missing_grid_names_itself_and_where_it_was_looked_for() {
        let e = GeoidGrid::find(&["no_such_geoid.gtx".to_owned()]).unwrap_err().to_string();
        assert!(e.contains("no_such_geoid.gtx") && e.contains("/usr/share/proj"), "{e}");
    }
}
