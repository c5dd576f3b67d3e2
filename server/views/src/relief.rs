//! Maps from the heights as Web Mercator raster tiles: hillshade, slope, aspect and colour
//! relief, with `gdaldem`'s definitions (Horn's 3 x 3 gradient; the hillshade's azimuth,
//! altitude, z factor and multidirectional shading; slope in degrees or percent; aspect
//! in degrees from north; a colour table in `gdaldem color-relief`'s text format).
//!
//! A tile's heights are sampled on its own pixel grid with a margin of one pixel around
//! it, through the same approximate transform as every web tile, on a lattice one cell
//! (64 pixels) wider than the tile: the margin's cells are the neighbours' own cells (the
//! lattice is aligned to the global 64-pixel grid), so the window around an edge pixel
//! holds exactly the heights its neighbour samples there, and tiles join without a seam. The horizontal spacing is the
//! pixel's size on the ground at its row's latitude (Web Mercator's scale).

use terrastream_format::{LayerKind, MmapSource, Reader};

use crate::encode::ImageFormat;
use crate::mercator::WebTile;
use crate::resample::{DecodedCache, LATTICE, MakeError, Placed};

/// What a relief tile shows.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash)]
pub enum Product {
    /// Shaded relief: gray 1 (in shadow) to 255 (facing the light), `gdaldem hillshade`.
    Hillshade,
    /// Steepness: gray, 255 flat to 0 vertical (degrees / 90, or percent / 100 clamped).
    Slope,
    /// Direction of the steepest descent: gray 0-255 over 0-360 degrees from north,
    /// clockwise; flat ground transparent.
    Aspect,
    /// Heights through a colour table (hypsometric tints).
    ColorRelief,
}

impl Product {
    /// The product a path names (`hillshade`, `slope`, `aspect`, `color-relief`).
    pub fn parse(name: &str) -> Option<Self> {
        match name {
            "hillshade" => Some(Self::Hillshade),
            "slope" => Some(Self::Slope),
            "aspect" => Some(Self::Aspect),
            "color-relief" => Some(Self::ColorRelief),
            _ => None,
        }
    }

    /// Its name in paths.
    pub fn name(self) -> &'static str {
        match self {
            Self::Hillshade => "hillshade",
            Self::Slope => "slope",
            Self::Aspect => "aspect",
            Self::ColorRelief => "color-relief",
        }
    }

    /// Every product.
    pub const ALL: [Self; 4] = [Self::Hillshade, Self::Slope, Self::Aspect, Self::ColorRelief];
}

/// `gdaldem`'s parameters.
#[derive(Clone, Debug, PartialEq)]
pub struct ReliefOptions {
    /// Vertical exaggeration (`-z`).
    pub z_factor: f64,
    /// Direction of the light, degrees clockwise from north (`-az`).
    pub azimuth: f64,
    /// Height of the light above the horizon, degrees (`-alt`).
    pub altitude: f64,
    /// Light from four directions, as `gdaldem hillshade -multidirectional`.
    pub multidirectional: bool,
    /// Slope in percent rather than degrees (`-p`).
    pub slope_percent: bool,
    /// The colour table of `color-relief`.
    pub table: ColorTable,
}

impl Default for ReliefOptions {
    fn default() -> Self {
        Self {
            z_factor: 1.0,
            azimuth: 315.0,
            altitude: 45.0,
            multidirectional: false,
            slope_percent: false,
            table: ColorTable::default(),
        }
    }
}

/// A colour table in `gdaldem color-relief`'s text format: lines of `height R G B [A]`
/// (heights ascending or not; `nv` for no data; `#` comments), colours interpolated
/// linearly between entries and clamped beyond the ends.
#[derive(Clone, Debug, PartialEq)]
pub struct ColorTable {
    entries: Vec<(f64, [u8; 4])>,
    nodata: [u8; 4],
}

impl Default for ColorTable {
    /// Hypsometric tints from the sea floor to high mountains.
    fn default() -> Self {
        #[expect(clippy::expect_used, reason = "a constant table that parses")]
        Self::parse(DEFAULT_TABLE).expect("the built-in colour table parses")
    }
}

/// The built-in colour table (metres).
pub const DEFAULT_TABLE: &str = "\
# height  R   G   B
-10000   12  38  88
-200     46  92 148
0        94 148 190
0.01    112 162  98
200     168 198 112
600     226 214 140
1200    196 156  98
2000    156 112  84
3000    200 196 190
5000    255 255 255
nv        0   0   0   0
";

impl ColorTable {
    /// Reads a table in `gdaldem`'s format.
    ///
    /// # Errors
    /// The line at fault and why.
    pub fn parse(text: &str) -> Result<Self, String> {
        let mut entries = Vec::new();
        let mut nodata = [0, 0, 0, 0];
        for (number, line) in text.lines().enumerate() {
            let line = line.split('#').next().unwrap_or("").trim();
            if line.is_empty() {
                continue;
            }
            let fields: Vec<&str> = line.split([' ', '\t', ',', ':']).filter(|f| !f.is_empty()).collect();
            let bad = || format!("colour table line {}: {line:?}: expected HEIGHT R G B [A]", number + 1);
            if fields.len() < 4 || fields.len() > 5 {
                return Err(bad());
            }
            let channel = |f: &str| f.parse::<u8>().map_err(|_| bad());
            let alpha = fields.get(4).map_or(Ok(255), |a| channel(a))?;
            let colour = [channel(fields[1])?, channel(fields[2])?, channel(fields[3])?, alpha];
            if fields[0].eq_ignore_ascii_case("nv") {
                nodata = colour;
                continue;
            }
            let height: f64 = fields[0].parse().map_err(|_| bad())?;
            if !height.is_finite() {
                return Err(bad());
            }
            entries.push((height, colour));
        }
        if entries.is_empty() {
            return Err("colour table: no entry".into());
        }
        entries.sort_by(|a, b| a.0.total_cmp(&b.0));
        Ok(Self { entries, nodata })
    }

    /// The colour of height `h` (NaN: the table's no-data colour).
    pub fn colour(&self, h: f32) -> [u8; 4] {
        if !h.is_finite() {
            return self.nodata;
        }
        let h = f64::from(h);
        let above = self.entries.partition_point(|(e, _)| *e < h);
        match (above.checked_sub(1).map(|i| self.entries[i]), self.entries.get(above)) {
            (None, Some(&(_, c))) | (Some((_, c)), None) => c,
            (Some((h0, c0)), Some(&(h1, c1))) => {
                let t = if h1 > h0 { (h - h0) / (h1 - h0) } else { 1.0 };
                #[expect(clippy::cast_possible_truncation, clippy::cast_sign_loss, reason = "between two u8 values")]
                std::array::from_fn(|k| (f64::from(c0[k]) + (f64::from(c1[k]) - f64::from(c0[k])) * t).round() as u8)
            }
            (None, None) => self.nodata,
        }
    }
}

/// The 3 x 3 heights around a pixel, row by row from the north-west (`gdaldem`'s `a` to
/// `i`); None when one has no data.
pub type Window = [f64; 9];

/// Horn's gradient of a window: (dz/dx east, dz/dy north) in height per ground unit, for
/// pixels `ewres` wide and `nsres` tall (ground units).
fn horn(w: &Window, ewres: f64, nsres: f64) -> (f64, f64) {
    let dx = ((w[2] + 2.0 * w[5] + w[8]) - (w[0] + 2.0 * w[3] + w[6])) / (8.0 * ewres);
    let dy = ((w[0] + 2.0 * w[1] + w[2]) - (w[6] + 2.0 * w[7] + w[8])) / (8.0 * nsres);
    (dx, dy)
}

/// `gdaldem hillshade`'s value of a window: 1 + 254 x the cosine of the angle between the
/// light and the surface's normal (1 in shadow); with `multidirectional`, gdaldem's four
/// lights (225, 270, 315 and 360 degrees) weighted by the slope's aspect, 1 + 127 x it
/// (1 + 254 x the light's sine on flat ground, as gdaldem does).
pub fn hillshade(w: &Window, res: (f64, f64), o: &ReliefOptions) -> f64 {
    Light::new(o).shade(w, res)
}

/// A hillshade's light, its sines and cosines worked out once for a whole tile.
#[derive(Clone, Copy, Debug)]
struct Light {
    z_factor: f64,
    multidirectional: bool,
    sin_alt: f64,
    cos_alt: f64,
    sin_az: f64,
    cos_az: f64,
}

impl Light {
    fn new(o: &ReliefOptions) -> Self {
        let (sin_alt, cos_alt) = o.altitude.to_radians().sin_cos();
        let (sin_az, cos_az) = o.azimuth.to_radians().sin_cos();
        Self { z_factor: o.z_factor, multidirectional: o.multidirectional, sin_alt, cos_alt, sin_az, cos_az }
    }

    /// A row of single-light hillshade as gray and alpha (two bytes a pixel; 0, 0 where
    /// a window is not all data) from the three rows of heights around it, each two
    /// longer than the row: [`Light::shade`]'s arithmetic in the same order (so the same
    /// values), without the per-pixel calls and branches, for the compiler to vectorise.
    #[expect(clippy::cast_possible_truncation, clippy::cast_sign_loss, reason = "clamped to 0..=255.5")]
    fn shade_row(&self, [top, middle, bottom]: [&[f32]; 3], (ewres, nsres): (f64, f64), out: &mut [u8]) {
        let (z, sin_alt, cos_alt) = (self.z_factor, self.sin_alt, self.cos_alt);
        let (y_weight, x_weight) = (self.cos_az * cos_alt, self.sin_az * cos_alt);
        let (ew8, ns8) = (8.0 * ewres, 8.0 * nsres);
        let rows = top.windows(3).zip(middle.windows(3)).zip(bottom.windows(3));
        for (((t, m), b), pixel) in rows.zip(out.chunks_exact_mut(2)) {
            let w = |v: &[f32], k: usize| f64::from(v[k]);
            let (w0, w1, w2, w3, w4, w5) = (w(t, 0), w(t, 1), w(t, 2), w(m, 0), w(m, 1), w(m, 2));
            let (w6, w7, w8) = (w(b, 0), w(b, 1), w(b, 2));
            let dx = ((w2 + 2.0 * w5 + w8) - (w0 + 2.0 * w3 + w6)) / ew8;
            let dy = ((w0 + 2.0 * w1 + w2) - (w6 + 2.0 * w7 + w8)) / ns8;
            let (x, y) = (-dx * z, dy * z);
            let norm = (1.0 + (x * x + y * y)).sqrt();
            let cang = (sin_alt - (y * y_weight - x * x_weight)) / norm;
            let value = if cang <= 0.0 { 1.0 } else { 1.0 + 254.0 * cang };
            let gray = (value.clamp(0.0, 255.0) + 0.5) as u8;
            let data = (w0 + w1 + w2 + w3 + w4 + w5 + w6 + w7 + w8).is_finite();
            pixel.copy_from_slice(&if data { [gray, 255] } else { [0, 0] });
        }
    }

    /// [`hillshade`] of a window.
    fn shade(&self, w: &Window, (ewres, nsres): (f64, f64)) -> f64 {
        let (dx, dy) = horn(w, ewres, nsres);
        // gdaldem's x is the descent towards the east, y the rise towards the north.
        let (x, y) = (-dx * self.z_factor, dy * self.z_factor);
        let (sin_alt, cos_alt) = (self.sin_alt, self.cos_alt);
        let xx_plus_yy = x * x + y * y;
        let norm = (1.0 + xx_plus_yy).sqrt();
        if !self.multidirectional {
            let cang = (sin_alt - (y * (self.cos_az * cos_alt) - x * (self.sin_az * cos_alt))) / norm;
            return if cang <= 0.0 { 1.0 } else { 1.0 + 254.0 * cang };
        }
        if xx_plus_yy == 0.0 {
            return 1.0 + 254.0 * sin_alt;
        }
        // cos(225 degrees) x cos(altitude): the 225 and 315 degree lights' share.
        let diagonal = -cos_alt * std::f64::consts::FRAC_1_SQRT_2;
        let val225 = (sin_alt + (x - y) * diagonal).max(0.0);
        let val270 = (sin_alt - x * cos_alt).max(0.0);
        let val315 = (sin_alt + (x + y) * diagonal).max(0.0);
        let val360 = (sin_alt - y * cos_alt).max(0.0);
        let w225 = 0.5 * xx_plus_yy - x * y;
        let (w270, w315, w360) = (x * x, xx_plus_yy - w225, y * y);
        let cang = (w225 * val225 + w270 * val270 + w315 * val315 + w360 * val360) / xx_plus_yy / norm;
        1.0 + 127.0 * cang
    }
}

/// `gdaldem slope`'s value of a window: degrees (or percent) of steepness.
pub fn slope(w: &Window, (ewres, nsres): (f64, f64), percent: bool) -> f64 {
    let (dx, dy) = horn(w, ewres, nsres);
    let rise = dx.hypot(dy);
    if percent { 100.0 * rise } else { rise.atan().to_degrees() }
}

/// `gdaldem aspect`'s value of a window: degrees clockwise from north of the steepest
/// descent; None on flat ground (gdaldem's -9999).
pub fn aspect(w: &Window) -> Option<f64> {
    let dx = (w[2] + 2.0 * w[5] + w[8]) - (w[0] + 2.0 * w[3] + w[6]);
    let dy = (w[6] + 2.0 * w[7] + w[8]) - (w[0] + 2.0 * w[1] + w[2]);
    if dx == 0.0 && dy == 0.0 {
        return None;
    }
    let angle = dy.atan2(-dx).to_degrees();
    let aspect = if angle > 90.0 { 450.0 - angle } else { 90.0 - angle };
    Some(if aspect >= 360.0 { aspect - 360.0 } else { aspect })
}

/// A relief tile to make.
#[derive(Clone, Debug, PartialEq)]
pub struct ReliefRequest {
    /// What it shows.
    pub product: Product,
    /// The tile.
    pub tile: WebTile,
    /// The file's format.
    pub format: ImageFormat,
    /// Pixels a side.
    pub size: u32,
    /// `gdaldem`'s parameters.
    pub options: ReliefOptions,
}

/// Makes a relief tile of the archive's elevation: the file's bytes; None when the tile
/// holds no data. Archive tiles decoded are kept in `cache` when given.
///
/// # Errors
/// [`MakeError::NotPlaced`] for an archive without placed elevation, [`MakeError::Tile`]
/// for an archive tile that cannot be read, [`MakeError::Encode`].
pub fn relief_tile(
    reader: &Reader<MmapSource>,
    request: &ReliefRequest,
    cache: Option<(&DecodedCache, u64)>,
) -> Result<Option<Vec<u8>>, MakeError> {
    let Some(heights) = margin_heights(reader, request.tile, request.size, 1, cache)? else { return Ok(None) };
    let size = request.size as usize;
    let span = size + 2;
    if request.product == Product::ColorRelief {
        let table = &request.options.table;
        let mut rgba = vec![0u8; size * size * 4];
        for (row, out) in rgba.chunks_exact_mut(size * 4).enumerate() {
            let heights = &heights[(row + 1) * span + 1..][..size];
            out.chunks_exact_mut(4).zip(heights).for_each(|(p, h)| p.copy_from_slice(&table.colour(*h)));
        }
        return request.format.encode(&rgba, request.size).map(Some).map_err(MakeError::Encode);
    }
    let light = Light::new(&request.options);
    // Gray and alpha, two bytes a pixel.
    let mut gray = vec![0u8; size * size * 2];
    for row in 0..size {
        // The ground size of a pixel at this row's latitude.
        let (_, lat) = request.tile.lon_lat(0.0, row as f64 + 0.5, size as f64);
        let res = request.tile.pixel_metres(lat, f64::from(request.size));
        if request.product == Product::Hillshade && !request.options.multidirectional {
            let rows = [0, 1, 2].map(|k| &heights[(row + k) * span..][..span]);
            light.shade_row(rows, (res, res), &mut gray[row * size * 2..][..size * 2]);
            continue;
        }
        for column in 0..size {
            let h = |dr: usize, dc: usize| f64::from(heights[(row + dr) * span + column + dc]);
            let window: Window = [h(0, 0), h(0, 1), h(0, 2), h(1, 0), h(1, 1), h(1, 2), h(2, 0), h(2, 1), h(2, 2)];
            if window.iter().all(|v| v.is_finite())
                && let Some(g) = level(request, &light, &window, res)
            {
                let at = (row * size + column) * 2;
                gray[at..at + 2].copy_from_slice(&[g, 255]);
            }
        }
    }
    request.format.encode_gray(&gray, request.size).map(Some).map_err(MakeError::Encode)
}

/// One pixel's gray level of a gray product from its window (`res`: the pixel's ground
/// size, metres).
#[expect(clippy::cast_possible_truncation, clippy::cast_sign_loss, reason = "rounded and clamped to 0..=255")]
fn level(request: &ReliefRequest, light: &Light, window: &Window, res: f64) -> Option<u8> {
    // Rounded half up (values are not negative), without a call to the C library.
    let gray = |v: f64| (v.clamp(0.0, 255.0) + 0.5) as u8;
    let o = &request.options;
    match request.product {
        Product::Hillshade => Some(gray(light.shade(window, (res, res)))),
        Product::Slope => {
            let s = slope(window, (res, res), o.slope_percent);
            let full = if o.slope_percent { 100.0 } else { 90.0 };
            Some(gray(255.0 * (1.0 - (s / full).min(1.0))))
        }
        Product::Aspect => aspect(window).map(|a| gray(a / 360.0 * 255.0)),
        Product::ColorRelief => None,
    }
}

/// The archive's heights on `tile`'s pixel grid (`size` a side) and `margin` pixels
/// around it (at most a lattice cell), row by row ((size + 2 margin) a side); NaN without
/// data; None when none has data. The positions are those of the lattice one cell around
/// the tile, cropped: the margin's are the neighbours' own. One LOD for every tile of a
/// zoom (chosen at the data's centre, as quantized-mesh levels are), so that neighbours
/// sample the same heights where their windows overlap.
///
/// # Errors
/// [`MakeError::NotPlaced`] without placed elevation, [`MakeError::Tile`].
pub(crate) fn margin_heights(
    reader: &Reader<MmapSource>,
    tile: WebTile,
    size: u32,
    margin: usize,
    cache: Option<(&DecodedCache, u64)>,
) -> Result<Option<Vec<f32>>, MakeError> {
    let placed = placed_elevation(reader, cache)?;
    let margin = margin.min(LATTICE);
    let (pixels, span) = (size as usize, size as usize + 2 * LATTICE);
    let (size, cell) = (f64::from(size), LATTICE as f64);
    let (first, last) = (LATTICE - margin, LATTICE + pixels + margin);
    let positions = placed
        .lattice(span, &|u, v| {
            let (lon, lat) = tile.lon_lat(u - cell, v - cell, size);
            placed.world(lon, lat)
        })
        .crop(span, [first, first, last, last]);
    placed.sample(&positions, zoom_lod(&placed, tile, size))
}

/// The archive's elevation on the Earth, its decoded tiles kept in `cache`.
///
/// # Errors
/// [`MakeError::NotPlaced`] without an elevation layer that says where it lies.
pub(crate) fn placed_elevation<'a>(
    reader: &'a Reader<MmapSource>,
    cache: Option<(&'a DecodedCache, u64)>,
) -> Result<Placed<'a>, MakeError> {
    let index = reader.metadata().layers.iter().position(|l| l.kind == LayerKind::Elevation);
    let index = index.and_then(|i| u8::try_from(i).ok()).ok_or(MakeError::NotPlaced)?;
    let placed = Placed::new(reader, index).ok_or(MakeError::NotPlaced)?;
    Ok(match cache {
        Some((cache, version)) => placed.with_cache(cache, version),
        None => placed,
    })
}

/// The LOD the tiles of `tile`'s zoom read (`size` pixels a side): the one for a pixel's
/// size at the middle of the layer's data, so that every tile of a zoom reads the same
/// one and neighbours join.
pub(crate) fn zoom_lod(placed: &Placed<'_>, tile: WebTile, size: f64) -> u8 {
    let per_pixel = crate::tilejson::coverage(placed.metadata(), placed.layer(), 256).map_or(f64::INFINITY, |c| {
        let [w, s, e, n] = c.bounds;
        let (lon, lat) = ((w + e) / 2.0, (s + n) / 2.0);
        let step = 360.0 / (tile.count() * size);
        match (placed.world(lon, lat), placed.world(lon + step, lat)) {
            (Some(a), Some(b)) => (b.0 - a.0).hypot(b.1 - a.1),
            _ => f64::INFINITY,
        }
    });
    placed.lod_for(per_pixel)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn gdaldem_definitions_on_simple_slopes() {
        // A plane rising 1 m a metre to the east, 1 m pixels.
        let east: Window = [0.0, 1.0, 2.0, 0.0, 1.0, 2.0, 0.0, 1.0, 2.0];
        assert!((slope(&east, (1.0, 1.0), false) - 45.0).abs() < 1e-9);
        assert!((slope(&east, (1.0, 1.0), true) - 100.0).abs() < 1e-9);
        // Rising to the east: the steepest descent faces west.
        assert_eq!(aspect(&east), Some(270.0));
        let north: Window = [2.0, 2.0, 2.0, 1.0, 1.0, 1.0, 0.0, 0.0, 0.0];
        assert_eq!(aspect(&north), Some(180.0), "rising to the north faces south");
        assert_eq!(aspect(&[5.0; 9]), None);
        // Flat ground under a light 45 degrees up: 1 + 254 sin 45.
        let flat = hillshade(&[5.0; 9], (1.0, 1.0), &ReliefOptions::default());
        assert!((flat - (1.0 + 254.0 * 45f64.to_radians().sin())).abs() < 1e-9, "{flat}");
        // A slope facing the light (north-west, descending that way) is brighter than flat.
        let facing: Window = [0.0, 0.5, 1.0, 0.5, 1.0, 1.5, 1.0, 1.5, 2.0];
        assert!(hillshade(&facing, (1.0, 1.0), &ReliefOptions::default()) > flat);
    }

    /// The row fast path gives [`hillshade`]'s values, rounded, and no data where a
    /// window has a hole.
    #[test]
    #[expect(clippy::cast_possible_truncation, clippy::cast_sign_loss, reason = "test values")]
    fn a_row_of_hillshade_is_the_windows_hillshade() {
        let width = 40;
        let height = |r: usize, c: usize| {
            if (r, c) == (1, 17) { f32::NAN } else { ((c * 37 + r * 101) % 23) as f32 * 7.5 - (c as f32).sin() * 30.0 }
        };
        let rows: Vec<Vec<f32>> = (0..3).map(|r| (0..width + 2).map(|c| height(r, c)).collect()).collect();
        for options in [
            ReliefOptions::default(),
            ReliefOptions { z_factor: 3.0, azimuth: 120.0, altitude: 30.0, ..ReliefOptions::default() },
        ] {
            let light = Light::new(&options);
            let mut out = vec![9u8; width * 2];
            light.shade_row([&rows[0], &rows[1], &rows[2]], (12.5, 12.5), &mut out);
            for c in 0..width {
                let window: Window = std::array::from_fn(|k| f64::from(rows[k / 3][c + k % 3]));
                let expected = if window.iter().all(|v| v.is_finite()) {
                    [hillshade(&window, (12.5, 12.5), &options).round() as u8, 255]
                } else {
                    [0, 0]
                };
                assert_eq!(out[c * 2..c * 2 + 2], expected, "column {c}");
            }
            assert!(out.chunks(2).filter(|p| p[1] == 0).count() == 3, "the hole's three windows");
        }
    }

    #[test]
    fn colour_tables_read_gdaldem_text_and_interpolate() {
        let t = ColorTable::parse("# a comment\n0 0 0 0\n100 200 100 50 128\nnv 1 2 3 0\n").unwrap();
        assert_eq!(t.colour(50.0), [100, 50, 25, 192]);
        assert_eq!(t.colour(-10.0), [0, 0, 0, 255]);
        assert_eq!(t.colour(1000.0), [200, 100, 50, 128]);
        assert_eq!(t.colour(f32::NAN), [1, 2, 3, 0]);
        assert!(ColorTable::parse("0 0 0").unwrap_err().contains("line 1"));
        assert!(ColorTable::parse("# nothing\n").is_err());
        assert_eq!(ColorTable::default().colour(0.0), [94, 148, 190, 255]);
    }
}
