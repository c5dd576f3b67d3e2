//! Elevation rasters (GeoTIFF) -> a LOD pyramid in an archive (`terrastream tile`).
//!
//! The raster is read whole (int8/16/32, uint8/16/32, float32/64; strips or tiles;
//! uncompressed, LZW, Deflate; GDAL nodata), georeferenced from its GeoTIFF tags, and
//! resampled along x to square samples in metres when its pixels are more than 1 % from
//! square (a geographic raster is converted to metres at its centre latitude). LOD 0 keeps the
//! source's sample spacing; each coarser LOD averages 2x2 samples of the previous one,
//! ignoring nodata; odd edges are padded with nodata; tiles that hold only nodata are left
//! missing. Tiles are stored losslessly: quantized u16 (a power-of-two step that keeps
//! integer sources exact at LOD 0) or f32, then zstd.

use std::path::Path;

use rayon::prelude::*;

use crate::error::{Error, Result};
use crate::key::TileKey;
use crate::metadata::{
    ElevationEncoding, ElevationScheme, Georeference, Layer, LayerKind, Metadata, PayloadCompression, TileFormat,
    levels_to_one,
};
use crate::progress::Progress;
use crate::writer::{WriteSummary, Writer, WriterOptions};

/// A single-band raster; NaN where there is no data.
#[derive(Clone, Debug, PartialEq)]
pub struct Raster {
    /// Samples across.
    pub width: u32,
    /// Samples down.
    pub height: u32,
    /// Row-major samples.
    pub data: Vec<f32>,
    /// Sample spacing in metres (x, y).
    pub spacing: (f64, f64),
    /// Where the raster lies, when the file says.
    pub georeference: Option<Georeference>,
}

/// How to store elevation samples.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub enum ElevationStorage {
    /// Quantized u16 when the range allows a step of at most 1/16 unit, else f32.
    #[default]
    Auto,
    /// Quantized u16.
    U16,
    /// f32.
    F32,
}

/// Options of [`tile_elevation`].
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct TileOptions {
    /// Samples per tile edge, borders excluded.
    pub tile_size: u32,
    /// Samples copied from the neighbours on each side.
    pub border: u8,
    /// Sample storage.
    pub storage: ElevationStorage,
}

impl Default for TileOptions {
    fn default() -> Self {
        Self { tile_size: 256, border: 1, storage: ElevationStorage::Auto }
    }
}

const MODEL_PIXEL_SCALE: u16 = 33550;
const MODEL_TIEPOINT: u16 = 33922;
const GEO_KEY_DIRECTORY: u16 = 34735;
const GDAL_NODATA: u16 = 42113;

/// Reads a single-band GeoTIFF.
///
/// # Errors
/// [`Error::Input`] naming the file for anything unreadable or unsupported.
pub fn read_geotiff(path: &Path) -> Result<Raster> {
    use tiff::decoder::{Decoder, DecodingResult, Limits};
    use tiff::tags::Tag;
    let bad = |why: String| Error::input(path, why);
    let file = std::fs::File::open(path).map_err(|e| Error::file(path, e))?;
    let mut decoder =
        Decoder::new(std::io::BufReader::new(file)).map_err(|e| bad(format!("not a TIFF: {e}")))?.with_limits({
            let mut limits = Limits::default();
            limits.decoding_buffer_size = 4 << 30;
            limits.intermediate_buffer_size = 4 << 30;
            limits
        });
    let (width, height) = decoder.dimensions().map_err(|e| bad(e.to_string()))?;
    let mut tag = |t: u16| -> Option<Vec<f64>> { decoder.find_tag(Tag::Unknown(t)).ok()??.into_f64_vec().ok() };
    let scale = tag(MODEL_PIXEL_SCALE);
    let tiepoint = tag(MODEL_TIEPOINT);
    let keys: Option<Vec<f64>> = decoder
        .find_tag(Tag::Unknown(GEO_KEY_DIRECTORY))
        .ok()
        .flatten()
        .and_then(|v| v.into_u64_vec().ok())
        .map(|v| v.into_iter().map(|k| k as f64).collect());
    let nodata: Option<f64> = decoder
        .find_tag(Tag::Unknown(GDAL_NODATA))
        .ok()
        .flatten()
        .and_then(|v| v.into_string().ok())
        .and_then(|s| s.trim_matches(char::from(0)).trim().parse().ok());
    let image = decoder.read_image().map_err(|e| bad(format!("reading samples: {e}")))?;
    #[expect(clippy::cast_possible_truncation, reason = "heights are kept as f32")]
    let mut data: Vec<f32> = match image {
        DecodingResult::U8(v) => v.into_iter().map(f32::from).collect(),
        DecodingResult::I8(v) => v.into_iter().map(f32::from).collect(),
        DecodingResult::U16(v) => v.into_iter().map(f32::from).collect(),
        DecodingResult::I16(v) => v.into_iter().map(f32::from).collect(),
        DecodingResult::U32(v) => v.into_iter().map(|x| x as f32).collect(),
        DecodingResult::I32(v) => v.into_iter().map(|x| x as f32).collect(),
        DecodingResult::F32(v) => v,
        DecodingResult::F64(v) => v.into_iter().map(|x| x as f32).collect(),
        _ => return Err(bad("unsupported sample type (use int8..32, uint8..32, float32/64)".into())),
    };
    let samples = width as usize * height as usize;
    if data.len() != samples {
        return Err(bad(format!(
            "{} samples for {width}x{height}: only single-band elevation rasters are supported",
            data.len()
        )));
    }
    #[expect(clippy::cast_possible_truncation, reason = "nodata compared as f32, as stored")]
    if let Some(nd) = nodata.map(|n| n as f32) {
        for v in &mut data {
            if *v == nd {
                *v = f32::NAN;
            }
        }
    }
    // Georeference: model type 2 = geographic (degrees), else projected (metres assumed).
    let key = |id: f64| -> Option<f64> {
        let k = keys.as_ref()?;
        k.chunks_exact(4).skip(1).find(|e| e[0] == id).map(|e| e[3])
    };
    let geographic = key(1024.0) == Some(2.0);
    let epsg = key(2048.0).or_else(|| key(3072.0)).filter(|&c| c > 0.0 && c < 32767.0);
    let (mut spacing, mut georeference) = ((1.0, 1.0), None);
    if let (Some(s), Some(t)) = (&scale, &tiepoint) {
        if s.len() >= 2 && t.len() >= 6 && s[0] > 0.0 && s[1] > 0.0 {
            let (west, north) = (t[3] - t[0] * s[0], t[4] + t[1] * s[1]);
            spacing = (s[0], s[1]);
            let mut g = Georeference {
                crs: epsg.map(|c| format!("EPSG:{c}")),
                origin: Some([west, north]),
                lat_lon_bounds: None,
            };
            if geographic {
                let (east, south) = (west + s[0] * f64::from(width), north - s[1] * f64::from(height));
                g.lat_lon_bounds = Some([west, south, east, north]);
                let lat = ((north + south) / 2.0).to_radians();
                spacing = (s[0] * 111_320.0 * lat.cos(), s[1] * 110_574.0);
            }
            georeference = Some(g);
        }
    }
    if !(spacing.0.is_finite() && spacing.1.is_finite() && spacing.0 > 0.0 && spacing.1 > 0.0) {
        return Err(bad(format!("bad pixel scale {spacing:?}")));
    }
    Ok(Raster { width, height, data, spacing, georeference })
}

impl Raster {
    fn at(&self, x: i64, y: i64) -> f32 {
        if x < 0 || y < 0 || x >= i64::from(self.width) || y >= i64::from(self.height) {
            return f32::NAN;
        }
        self.data[usize::try_from(y * i64::from(self.width) + x).unwrap_or(0)]
    }

    /// Resamples along x (linear) so that samples are square at the y spacing. Samples
    /// within 1 % of square are kept as they are (exact) at their mean spacing.
    #[must_use]
    pub fn square(self) -> Self {
        let ratio = self.spacing.0 / self.spacing.1;
        if (ratio - 1.0).abs() < 0.01 {
            let mean = (self.spacing.0 * self.spacing.1).sqrt();
            return Self { spacing: (mean, mean), ..self };
        }
        #[expect(clippy::cast_possible_truncation, reason = "bounded by the source width times a sane ratio")]
        let width = ((f64::from(self.width) * ratio).round() as u32).max(1);
        let mut data = Vec::with_capacity(width as usize * self.height as usize);
        for y in 0..self.height {
            for x in 0..width {
                let sx = (f64::from(x) + 0.5) / ratio - 0.5;
                let x0 = sx.floor();
                let f = sx - x0;
                #[expect(clippy::cast_possible_truncation, reason = "a pixel index")]
                let (a, b) = (self.at(x0 as i64, i64::from(y)), self.at(x0 as i64 + 1, i64::from(y)));
                #[expect(clippy::cast_possible_truncation, reason = "heights are f32")]
                let v = match (a.is_nan(), b.is_nan()) {
                    (false, false) => (f64::from(a) * (1.0 - f) + f64::from(b) * f) as f32,
                    (false, true) => a,
                    (true, false) => b,
                    (true, true) => f32::NAN,
                };
                data.push(v);
            }
        }
        Self { width, data, spacing: (self.spacing.1, self.spacing.1), ..self }
    }

    /// The next coarser level: 2x2 averages (nodata ignored), odd edges padded.
    fn halve(&self) -> Self {
        let (width, height) = (self.width.div_ceil(2), self.height.div_ceil(2));
        let mut data = Vec::with_capacity(width as usize * height as usize);
        for y in 0..i64::from(height) {
            for x in 0..i64::from(width) {
                let (mut sum, mut n) = (0.0f64, 0u32);
                for (dx, dy) in [(0, 0), (1, 0), (0, 1), (1, 1)] {
                    let v = self.at(2 * x + dx, 2 * y + dy);
                    if !v.is_nan() {
                        sum += f64::from(v);
                        n += 1;
                    }
                }
                #[expect(clippy::cast_possible_truncation, reason = "heights are f32")]
                data.push(if n == 0 { f32::NAN } else { (sum / f64::from(n)) as f32 });
            }
        }
        Self { width, height, data, spacing: (self.spacing.0 * 2.0, self.spacing.1 * 2.0), georeference: None }
    }
}

/// Packs an elevation raster into a pyramid archive at `out`.
///
/// # Errors
/// Bad options, writer and I/O errors, [`Error::Interrupted`].
pub fn tile_elevation(
    raster: Raster,
    name: &str,
    out: &Path,
    options: TileOptions,
    progress: &dyn Progress,
) -> Result<WriteSummary> {
    let raster = raster.square();
    let res = options.tile_size;
    if !(16..=4096).contains(&res) || options.border > 16 {
        return Err(Error::Writer(format!("tile size {res} (16..=4096) / border {} (0..=16)", options.border)));
    }
    let (min, max) = raster
        .data
        .iter()
        .filter(|v| !v.is_nan())
        .fold((f64::INFINITY, f64::NEG_INFINITY), |(lo, hi), &v| (lo.min(f64::from(v)), hi.max(f64::from(v))));
    if !min.is_finite() {
        return Err(Error::Writer(format!("{name}: the raster holds no data")));
    }
    let span = max - min;
    // Quantization step: a power of two, at most 1/16, small enough for the span.
    let step = (0..=8).map(|k| f64::from(1u32 << k) / 16.0).find(|s| span / s < 65_000.0);
    let encoding = match (options.storage, step) {
        (ElevationStorage::F32, _) | (ElevationStorage::Auto, None) => {
            ElevationEncoding { scheme: ElevationScheme::Float32, scale: 1.0, offset: 0.0, nodata: None }
        }
        (_, step) => {
            let step = step.unwrap_or(span / 65_000.0);
            // 0 is nodata; heights start at 1.
            let offset = (min / step).floor() * step - step;
            ElevationEncoding { scheme: ElevationScheme::QuantizedU16, scale: step, offset, nodata: Some(0.0) }
        }
    };
    let (nx, ny) = (raster.width.div_ceil(res), raster.height.div_ceil(res));
    let layer = Layer {
        name: "elevation".into(),
        kind: LayerKind::Elevation,
        format: if encoding.scheme == ElevationScheme::Float32 { TileFormat::RawF32 } else { TileFormat::RawU16 },
        compression: PayloadCompression::Zstd,
        tile_resolution: res,
        border: options.border,
        num_x_tiles: nx,
        num_y_tiles: ny,
        num_lods: levels_to_one(nx.max(ny)),
        tile_world_size: f64::from(res) * raster.spacing.0,
        elevation: Some(encoding),
    };
    let mut metadata = Metadata::new(name, vec![layer.clone()]);
    metadata.terrain.min_elevation = min;
    metadata.terrain.max_elevation = max;
    metadata.terrain.displacement = span;
    metadata.terrain.elevation_range = span;
    metadata.terrain.base_tile_size = raster.spacing.0;
    metadata.terrain.high_detail_range = raster.spacing.0 * 64.0;
    metadata.terrain.num_detail_levels = u32::from(layer.num_lods) + 6;
    metadata.georeference.clone_from(&raster.georeference);

    // Every level, finest first; every tile of every level encoded in parallel.
    let mut levels = vec![raster];
    while levels.len() < usize::from(layer.num_lods) {
        let next = levels[levels.len() - 1].halve();
        levels.push(next);
    }
    let total = layer.grid_tiles();
    progress.start("tile", total);
    let border = i64::from(options.border);
    let mut tiles: Vec<(u64, TileKey, Vec<u8>)> = Vec::new();
    for (lod, level) in levels.iter().enumerate() {
        let lod = u8::try_from(lod).map_err(|_| Error::Writer("too many levels".into()))?;
        progress.check()?;
        let keys: Vec<TileKey> = layer.tiles_at(0, lod).collect();
        let encoded: Vec<Option<(u64, TileKey, Vec<u8>)>> = keys
            .par_iter()
            .map(|&key| {
                let (x0, y0) = (i64::from(key.x()) * i64::from(res), i64::from(key.y()) * i64::from(res));
                let edge = i64::from(res) + 2 * border;
                let mut any = false;
                let mut samples = Vec::with_capacity(usize::try_from(edge * edge).unwrap_or(0));
                for j in 0..edge {
                    for i in 0..edge {
                        let v = level.at(x0 + i - border, y0 + j - border);
                        any |= !v.is_nan()
                            && (border..border + i64::from(res)).contains(&i)
                            && (border..border + i64::from(res)).contains(&j);
                        samples.push(v);
                    }
                }
                progress.advance(1);
                if !any {
                    return Ok(None);
                }
                let payload = encode(&samples, &encoding);
                Ok(Some((Writer::order_key(&metadata, key)?, key, payload)))
            })
            .collect::<Result<_>>()?;
        tiles.extend(encoded.into_iter().flatten());
    }
    drop(levels);
    tiles.sort_unstable_by_key(|t| t.0);
    let mut writer = Writer::create(out, metadata, WriterOptions::default())?;
    for (_, key, payload) in tiles {
        writer.add(key, payload)?;
    }
    writer.finish()
}

fn encode(samples: &[f32], encoding: &ElevationEncoding) -> Vec<u8> {
    if encoding.scheme == ElevationScheme::Float32 {
        return samples.iter().flat_map(|v| v.to_le_bytes()).collect();
    }
    samples
        .iter()
        .flat_map(|&v| {
            let q = if v.is_nan() {
                0
            } else {
                #[expect(clippy::cast_possible_truncation, reason = "clamped to 1..=65535 first")]
                let q = ((f64::from(v) - encoding.offset) / encoding.scale).round().clamp(1.0, 65_535.0) as u16;
                q
            };
            q.to_le_bytes()
        })
        .collect()
}

#[cfg(test)]
mod tests {
    use super::*;

    fn raster(width: u32, height: u32, f: impl Fn(u32, u32) -> f32) -> Raster {
        let data = (0..height).flat_map(|y| (0..width).map(move |x| (x, y))).map(|(x, y)| f(x, y)).collect();
        Raster { width, height, data, spacing: (30.0, 30.0), georeference: None }
    }

    #[test]
    fn halving_averages_and_ignores_nodata() {
        let r = raster(3, 2, |x, y| if (x, y) == (1, 0) { f32::NAN } else { (x + 10 * y) as f32 });
        let h = r.halve();
        assert_eq!((h.width, h.height), (2, 1));
        assert_eq!(h.data[0], (0.0 + 10.0 + 11.0) / 3.0);
        assert_eq!(h.data[1], (2.0 + 12.0) / 2.0);
    }

    #[test]
    fn non_square_pixels_are_resampled_along_x() {
        let mut r = raster(10, 4, |x, _| x as f32);
        r.spacing = (15.0, 30.0);
        let s = r.square();
        assert_eq!((s.width, s.height, s.spacing), (5, 4, (30.0, 30.0)));
        assert!((s.data[1] - 2.5).abs() < 1e-6, "{:?}", &s.data[..5]);
    }
}
