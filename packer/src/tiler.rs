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
    let tags = GeoTags::read(&mut decoder);
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
    let (spacing, georeference) = tags.placement(width, height).map_err(bad)?;
    Ok(Raster { width, height, data, spacing, georeference })
}

/// The GeoTIFF tags that place a raster on the Earth.
struct GeoTags {
    scale: Option<Vec<f64>>,
    tiepoint: Option<Vec<f64>>,
    keys: Option<Vec<f64>>,
}

impl GeoTags {
    fn read<R: std::io::Read + std::io::Seek>(decoder: &mut tiff::decoder::Decoder<R>) -> Self {
        use tiff::tags::Tag;
        let mut tag = |t: u16| -> Option<Vec<f64>> { decoder.find_tag(Tag::Unknown(t)).ok()??.into_f64_vec().ok() };
        let scale = tag(MODEL_PIXEL_SCALE);
        let tiepoint = tag(MODEL_TIEPOINT);
        let keys: Option<Vec<f64>> = decoder
            .find_tag(Tag::Unknown(GEO_KEY_DIRECTORY))
            .ok()
            .flatten()
            .and_then(|v| v.into_u64_vec().ok())
            .map(|v| v.into_iter().map(|k| k as f64).collect());
        Self { scale, tiepoint, keys }
    }

    /// Sample spacing in metres (x, y) and the georeference; (1, 1) and none without tags.
    fn placement(&self, width: u32, height: u32) -> std::result::Result<((f64, f64), Option<Georeference>), String> {
        let (scale, tiepoint, keys) = (&self.scale, &self.tiepoint, &self.keys);
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
            return Err(format!("bad pixel scale {spacing:?}"));
        }
        Ok((spacing, georeference))
    }
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

/// Packs an elevation raster into a pyramid archive at `out` (no texture: see
/// [`tile_terrain`]).
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
    tile_terrain(raster, None, name, out, options, progress)
}

/// The elevation layer (metadata with it as layer 0) and its levels, finest first.
fn elevation_plan(raster: Raster, name: &str, options: TileOptions) -> Result<(Metadata, Vec<Raster>)> {
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

    // Every level, finest first.
    let mut levels = vec![raster];
    while levels.len() < usize::from(layer.num_lods) {
        let next = levels[levels.len() - 1].halve();
        levels.push(next);
    }
    Ok((metadata, levels))
}

/// An RGBA8 image: the texture input (orthophoto, satellite scene, shaded relief).
#[derive(Clone, Debug, PartialEq)]
pub struct Image {
    /// Pixels across.
    pub width: u32,
    /// Pixels down.
    pub height: u32,
    /// Row-major RGBA8 pixels; alpha 0 where there is no data.
    pub rgba: Vec<u8>,
    /// Where the image lies, when the file says (GeoTIFF).
    pub georeference: Option<Georeference>,
}

/// Reads an image: GeoTIFF (8-bit gray, RGB or RGBA; strips or tiles; none, LZW or
/// Deflate), PNG (any colour type; 16-bit is reduced to 8) or JPEG; told apart by content.
///
/// # Errors
/// [`Error::Input`] naming the file for anything unreadable or unsupported.
pub fn read_image(path: &Path) -> Result<Image> {
    let bad = |why: String| Error::input(path, why);
    let bytes = std::fs::read(path).map_err(|e| Error::file(path, e))?;
    let rgba_of = |pixels: Vec<u8>, channels: usize| -> Vec<u8> {
        match channels {
            4 => pixels,
            3 => pixels.chunks_exact(3).flat_map(|p| [p[0], p[1], p[2], 255]).collect(),
            2 => pixels.chunks_exact(2).flat_map(|p| [p[0], p[0], p[0], p[1]]).collect(),
            _ => pixels.iter().flat_map(|&g| [g, g, g, 255]).collect(),
        }
    };
    let image = if bytes.starts_with(b"\x89PNG") {
        let mut decoder = png::Decoder::new(std::io::Cursor::new(&bytes));
        decoder.set_transformations(png::Transformations::EXPAND | png::Transformations::STRIP_16);
        let mut reader = decoder.read_info().map_err(|e| bad(format!("PNG: {e}")))?;
        let mut buf = vec![0; reader.output_buffer_size().ok_or_else(|| bad("PNG: too large".into()))?];
        let info = reader.next_frame(&mut buf).map_err(|e| bad(format!("PNG: {e}")))?;
        buf.truncate(info.buffer_size());
        let channels = info.color_type.samples();
        Image { width: info.width, height: info.height, rgba: rgba_of(buf, channels), georeference: None }
    } else if bytes.starts_with(&[0xFF, 0xD8]) {
        let options = zune_jpeg::zune_core::options::DecoderOptions::default()
            .jpeg_set_out_colorspace(zune_jpeg::zune_core::colorspace::ColorSpace::RGB);
        let mut decoder = zune_jpeg::JpegDecoder::new_with_options(&bytes, options);
        let pixels = decoder.decode().map_err(|e| bad(format!("JPEG: {e:?}")))?;
        let (w, h) = decoder.dimensions().ok_or_else(|| bad("JPEG: no dimensions".into()))?;
        let dim = |n: usize| u32::try_from(n).map_err(|_| bad("JPEG: too large".into()));
        Image { width: dim(w)?, height: dim(h)?, rgba: rgba_of(pixels, 3), georeference: None }
    } else if bytes.starts_with(b"II*\0") || bytes.starts_with(b"MM\0*") {
        use tiff::decoder::{Decoder, DecodingResult};
        let mut decoder =
            Decoder::new(std::io::Cursor::new(&bytes)).map_err(|e| bad(format!("not a readable TIFF: {e}")))?;
        let (width, height) = decoder.dimensions().map_err(|e| bad(e.to_string()))?;
        let tags = GeoTags::read(&mut decoder);
        let channels = match decoder.colortype().map_err(|e| bad(e.to_string()))? {
            tiff::ColorType::Gray(8) => 1,
            tiff::ColorType::GrayA(8) => 2,
            tiff::ColorType::RGB(8) => 3,
            tiff::ColorType::RGBA(8) => 4,
            other => return Err(bad(format!("{other:?} pixels: textures must be 8-bit gray, RGB or RGBA"))),
        };
        let DecodingResult::U8(pixels) = decoder.read_image().map_err(|e| bad(format!("reading pixels: {e}")))? else {
            return Err(bad("textures must have 8-bit samples".into()));
        };
        let georeference = tags.placement(width, height).ok().and_then(|(_, g)| g);
        Image { width, height, rgba: rgba_of(pixels, channels), georeference }
    } else {
        return Err(bad("not a GeoTIFF, PNG or JPEG image".into()));
    };
    if image.width == 0 || image.height == 0 {
        return Err(bad("the image is empty (0 pixels)".into()));
    }
    if image.rgba.len() != image.width as usize * image.height as usize * 4 {
        return Err(bad(format!("{} bytes of pixels for {}x{}", image.rgba.len(), image.width, image.height)));
    }
    Ok(image)
}

impl Image {
    fn at(&self, x: i64, y: i64) -> [u8; 4] {
        if x < 0 || y < 0 || x >= i64::from(self.width) || y >= i64::from(self.height) {
            return [0; 4];
        }
        let i = usize::try_from(y * i64::from(self.width) + x).unwrap_or(0) * 4;
        [self.rgba[i], self.rgba[i + 1], self.rgba[i + 2], self.rgba[i + 3]]
    }

    /// Resampled along x (linear, alpha-weighted) to `width` pixels.
    #[must_use]
    pub fn resample_width(&self, width: u32) -> Self {
        let ratio = f64::from(width) / f64::from(self.width);
        let mut rgba = Vec::with_capacity(width as usize * self.height as usize * 4);
        for y in 0..i64::from(self.height) {
            for x in 0..width {
                let sx = ((f64::from(x) + 0.5) / ratio - 0.5).max(0.0);
                let x0 = sx.floor();
                let f = sx - x0;
                #[expect(clippy::cast_possible_truncation, reason = "a pixel index")]
                let x0 = (x0 as i64).min(i64::from(self.width) - 1);
                let (a, b) = (self.at(x0, y), self.at((x0 + 1).min(i64::from(self.width) - 1), y));
                let (wa, wb) = (f64::from(a[3]) * (1.0 - f), f64::from(b[3]) * f);
                let alpha = wa + wb;
                for c in 0..3 {
                    let v = if alpha > 0.0 { (f64::from(a[c]) * wa + f64::from(b[c]) * wb) / alpha } else { 0.0 };
                    #[expect(clippy::cast_possible_truncation, clippy::cast_sign_loss, reason = "0..=255")]
                    rgba.push(v.round().clamp(0.0, 255.0) as u8);
                }
                #[expect(clippy::cast_possible_truncation, clippy::cast_sign_loss, reason = "0..=255")]
                rgba.push((f64::from(a[3]) * (1.0 - f) + f64::from(b[3]) * f).round().clamp(0.0, 255.0) as u8);
            }
        }
        Self { width, height: self.height, rgba, georeference: self.georeference.clone() }
    }

    /// The next coarser level: each pixel the alpha-weighted mean of 2x2 (area
    /// averaging); odd edges are padded with transparent pixels.
    #[must_use]
    pub fn halve(&self) -> Self {
        let (width, height) = (self.width.div_ceil(2), self.height.div_ceil(2));
        let mut rgba = Vec::with_capacity(width as usize * height as usize * 4);
        for y in 0..i64::from(height) {
            for x in 0..i64::from(width) {
                let mut sum = [0u32; 4];
                for (dx, dy) in [(0, 0), (1, 0), (0, 1), (1, 1)] {
                    let p = self.at(2 * x + dx, 2 * y + dy);
                    let a = u32::from(p[3]);
                    for c in 0..3 {
                        sum[c] += u32::from(p[c]) * a;
                    }
                    sum[3] += a;
                }
                if sum[3] == 0 {
                    rgba.extend_from_slice(&[0; 4]);
                    continue;
                }
                #[expect(clippy::cast_possible_truncation, reason = "means of u8 values")]
                let mean = |c: usize| ((sum[c] + sum[3] / 2) / sum[3]) as u8;
                #[expect(clippy::cast_possible_truncation, reason = "a mean of four u8 values")]
                let alpha = ((sum[3] + 2) / 4) as u8;
                rgba.extend_from_slice(&[mean(0), mean(1), mean(2), alpha]);
            }
        }
        Self { width, height, rgba, georeference: self.georeference.clone() }
    }
}

/// The texture input of [`tile_terrain`].
#[derive(Clone, Debug)]
pub struct TextureInput {
    /// The image; it is stretched over the elevation's extent.
    pub image: Image,
    /// Where it came from (for errors).
    pub path: std::path::PathBuf,
    /// Pixels per tile edge, borders excluded.
    pub tile_size: u32,
}

/// Packs an elevation raster and, optionally, a texture image covering the same extent
/// into one archive at `out`: layer 0 the elevation pyramid, layer 1 the texture pyramid
/// (PNG tiles, area-averaged LODs, the elevation's border width). The texture's grid is
/// independent of the elevation's: its own resolution, its own tile size.
///
/// # Errors
/// Bad options, a texture whose aspect ratio differs from the elevation's by more than
/// 2 % ([`Error::Input`] naming it), writer and I/O errors, [`Error::Interrupted`].
pub fn tile_terrain(
    raster: Raster,
    texture: Option<TextureInput>,
    name: &str,
    out: &Path,
    options: TileOptions,
    progress: &dyn Progress,
) -> Result<WriteSummary> {
    let grid_aspect = f64::from(raster.width) / f64::from(raster.height);
    let raster = raster.square();
    let (mut metadata, elevation_levels) = elevation_plan(raster, name, options)?;
    let mut texture_levels = Vec::new();
    if let Some(t) = texture {
        // The data's extent (the layer's grid is padded to whole tiles).
        let dem = &elevation_levels[0];
        let (ex, ez) = (f64::from(dem.width) * dem.spacing.0, f64::from(dem.height) * dem.spacing.1);
        let (w, h) = (f64::from(t.image.width), f64::from(t.image.height));
        // The texture covers the elevation's area on the same grid (both geographic, say:
        // its pixels have the DEM's pixel shape) or in metres (square pixels).
        let near = |a: f64, b: f64| (a / b - 1.0).abs() <= 0.02;
        if !near(w / h, grid_aspect) && !near(w / h, ex / ez) {
            return Err(Error::input(
                &t.path,
                format!(
                    "mismatched extents: the elevation covers {ex:.0} x {ez:.0} m (aspect {:.3}; its grid {:.3}), \
                     the texture is {w} x {h} px (aspect {:.3}); both must cover the same area",
                    ex / ez,
                    grid_aspect,
                    w / h
                ),
            ));
        }
        // Texels square in metres, as tiles are: resample along x where they are not.
        #[expect(clippy::cast_possible_truncation, clippy::cast_sign_loss, reason = "a pixel count")]
        let square_width = ((h * ex / ez).round() as u32).max(1);
        let mut t = t;
        if square_width != t.image.width {
            t.image = t.image.resample_width(square_width);
        }
        let w = f64::from(t.image.width);
        if !(16..=4096).contains(&t.tile_size) {
            return Err(Error::Writer(format!("texture tile size {} (16..=4096)", t.tile_size)));
        }
        let (nx, ny) = (t.image.width.div_ceil(t.tile_size), t.image.height.div_ceil(t.tile_size));
        metadata.layers.push(Layer {
            name: "texture".into(),
            kind: LayerKind::Texture,
            format: TileFormat::Png,
            compression: PayloadCompression::None,
            tile_resolution: t.tile_size,
            border: options.border,
            num_x_tiles: nx,
            num_y_tiles: ny,
            num_lods: levels_to_one(nx.max(ny)),
            tile_world_size: f64::from(t.tile_size) * ex / w,
            elevation: None,
        });
        texture_levels.push(t.image);
        while texture_levels.len() < usize::from(metadata.layers[1].num_lods) {
            let next = texture_levels[texture_levels.len() - 1].halve();
            texture_levels.push(next);
        }
    }
    let total = metadata.layers.iter().map(Layer::grid_tiles).sum();
    progress.start("tile", total);
    let encoding = metadata.layers[0].elevation.ok_or_else(|| Error::Writer("no elevation encoding".into()))?;
    let mut tiles = encode_layer(&metadata, 0, &elevation_levels, options.border, progress, |_, samples, _| {
        Ok(encode(samples, &encoding))
    })?;
    drop(elevation_levels);
    tiles.extend(encode_layer(&metadata, 1, &texture_levels, options.border, progress, |key, pixels, edge| {
        let opaque = pixels.iter().all(|p| p[3] == 255);
        encode_png(pixels.as_flattened(), edge, opaque).map_err(|e| Error::Writer(format!("tile {key}: {e}")))
    })?);
    drop(texture_levels);
    tiles.sort_unstable_by_key(|t| t.0);
    let mut writer = Writer::create(out, metadata, WriterOptions::default())?;
    for (_, key, payload) in tiles {
        writer.add(key, payload)?;
    }
    writer.finish()
}

type EncodedTile = (u64, TileKey, Vec<u8>);

/// The levels of a pyramid, sampled by pixel with borders outside the raster.
trait Samples: Sync {
    type Sample: Copy + Send;
    fn sample(&self, x: i64, y: i64) -> Self::Sample;
    fn has_data(sample: &Self::Sample) -> bool;
}

impl Samples for Raster {
    type Sample = f32;
    fn sample(&self, x: i64, y: i64) -> f32 {
        self.at(x, y)
    }
    fn has_data(sample: &f32) -> bool {
        !sample.is_nan()
    }
}

impl Samples for Image {
    type Sample = [u8; 4];
    fn sample(&self, x: i64, y: i64) -> [u8; 4] {
        self.at(x, y)
    }
    fn has_data(sample: &[u8; 4]) -> bool {
        sample[3] > 0
    }
}

/// Every tile of layer `index`, one level of `levels` per LOD (finest first), cut with
/// `border` samples from the neighbours and encoded in parallel by `encode(key, samples,
/// edge)`. Tiles with no data inside their border are left out.
fn encode_layer<L: Samples>(
    metadata: &Metadata,
    index: u8,
    levels: &[L],
    border: u8,
    progress: &dyn Progress,
    encode: impl Fn(TileKey, &[L::Sample], i64) -> Result<Vec<u8>> + Sync,
) -> Result<Vec<EncodedTile>> {
    let Some(layer) = metadata.layers.get(usize::from(index)) else { return Ok(Vec::new()) };
    let res = i64::from(layer.tile_resolution);
    let border = i64::from(border);
    let edge = res + 2 * border;
    let mut tiles = Vec::new();
    for (lod, level) in levels.iter().enumerate() {
        let lod = u8::try_from(lod).map_err(|_| Error::Writer("too many levels".into()))?;
        progress.check()?;
        let keys: Vec<TileKey> = layer.tiles_at(index, lod).collect();
        let encoded: Vec<Option<EncodedTile>> = keys
            .par_iter()
            .map(|&key| {
                let (x0, y0) = (i64::from(key.x()) * res, i64::from(key.y()) * res);
                let mut any = false;
                let mut samples = Vec::with_capacity(usize::try_from(edge * edge).unwrap_or(0));
                for j in 0..edge {
                    for i in 0..edge {
                        let v = level.sample(x0 + i - border, y0 + j - border);
                        let inside = (border..border + res).contains(&i) && (border..border + res).contains(&j);
                        any |= inside && L::has_data(&v);
                        samples.push(v);
                    }
                }
                progress.advance(1);
                if !any {
                    return Ok(None);
                }
                Ok(Some((Writer::order_key(metadata, key)?, key, encode(key, &samples, edge)?)))
            })
            .collect::<Result<_>>()?;
        tiles.extend(encoded.into_iter().flatten());
    }
    Ok(tiles)
}

/// A square RGBA8 tile as PNG: RGB when every pixel is opaque.
fn encode_png(rgba: &[u8], edge: i64, opaque: bool) -> std::result::Result<Vec<u8>, png::EncodingError> {
    let edge = u32::try_from(edge).unwrap_or(0);
    let mut out = Vec::new();
    let mut encoder = png::Encoder::new(&mut out, edge, edge);
    encoder.set_depth(png::BitDepth::Eight);
    if opaque {
        encoder.set_color(png::ColorType::Rgb);
        let rgb: Vec<u8> = rgba.chunks_exact(4).flat_map(|p| [p[0], p[1], p[2]]).collect();
        encoder.write_header()?.write_image_data(&rgb)?;
    } else {
        encoder.set_color(png::ColorType::Rgba);
        encoder.write_header()?.write_image_data(rgba)?;
    }
    Ok(out)
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

    fn png_file(path: &Path, width: u32, height: u32, rgba: &[u8]) {
        let file = std::io::BufWriter::new(std::fs::File::create(path).unwrap());
        let mut encoder = png::Encoder::new(file, width, height);
        encoder.set_color(png::ColorType::Rgba);
        encoder.set_depth(png::BitDepth::Eight);
        encoder.write_header().unwrap().write_image_data(rgba).unwrap();
    }

    fn decode_png(bytes: &[u8]) -> (u32, Vec<u8>) {
        let mut decoder = png::Decoder::new(std::io::Cursor::new(bytes));
        decoder.set_transformations(png::Transformations::EXPAND | png::Transformations::ALPHA);
        let mut reader = decoder.read_info().unwrap();
        let mut buf = vec![0; reader.output_buffer_size().unwrap()];
        let info = reader.next_frame(&mut buf).unwrap();
        buf.truncate(info.buffer_size());
        (info.width, buf)
    }

    /// A 64x64 texture: (x*4, y*4, x+y, 255), transparent where x, y >= 48.
    #[allow(clippy::cast_possible_truncation)]
    fn texture_pixels() -> Vec<u8> {
        (0..64u32)
            .flat_map(|y| (0..64u32).map(move |x| (x, y)))
            .flat_map(
                |(x, y)| {
                    if x >= 48 && y >= 48 { [0; 4] } else { [(x * 4) as u8, (y * 4) as u8, (x + y) as u8, 255] }
                },
            )
            .collect()
    }

    #[test]
    fn texture_pyramid_is_aligned_bordered_averaged_and_sparse() {
        let dir = tempfile::tempdir().unwrap();
        let image_path = dir.path().join("ortho.png");
        png_file(&image_path, 64, 64, &texture_pixels());
        let image = read_image(&image_path).unwrap();
        assert_eq!((image.width, image.height), (64, 64));
        let texture = TextureInput { image, path: image_path, tile_size: 16 };
        let out = dir.path().join("t.tspack");
        let elevation = raster(100, 100, |x, y| (x + y) as f32);
        let options = TileOptions { tile_size: 32, border: 1, storage: ElevationStorage::Auto };
        tile_terrain(elevation, Some(texture), "t", &out, options, &crate::progress::Silent::default()).unwrap();
        let reader = crate::Reader::open_mmap(&out).unwrap();
        let m = reader.metadata();
        assert_eq!(m.layers.len(), 2);
        let t = &m.layers[1];
        assert_eq!(
            (t.kind, t.format, t.num_x_tiles, t.num_y_tiles, t.num_lods),
            (LayerKind::Texture, TileFormat::Png, 4, 4, 3)
        );
        // The same world extent: 100 samples of 30 m = 64 texels of 46.875 m.
        assert!((t.tile_world_size * 4.0 - 3000.0).abs() < 1e-9, "{}", t.tile_world_size);
        let tile =
            |lod: u8, x: u32, y: u32| reader.tile(TileKey::new(1, lod, x, y).unwrap()).unwrap().map(|b| decode_png(&b));
        let px = |tile: &(u32, Vec<u8>), i: u32, j: u32| {
            let k = ((j * tile.0 + i) * 4) as usize;
            [tile.1[k], tile.1[k + 1], tile.1[k + 2], tile.1[k + 3]]
        };
        let (a, b) = (tile(0, 0, 0).unwrap(), tile(0, 1, 0).unwrap());
        assert_eq!(a.0, 18, "16 px + a border of 1 on each side");
        for j in 1..17 {
            // b's left border column is a's last interior column, and the other way round.
            assert_eq!(px(&b, 0, j), px(&a, 16, j), "row {j}");
            assert_eq!(px(&a, 17, j), px(&b, 1, j), "row {j}");
        }
        assert_eq!(px(&a, 1, 1), [0, 0, 0, 255], "interior starts at texel (0, 0)");
        // LOD 1: each texel the mean of 2x2 (here of (0,0), (1,0), (0,1), (1,1)).
        let c = tile(1, 0, 0).unwrap();
        assert_eq!(px(&c, 1, 1), [2, 2, 1, 255]);
        // The transparent corner tile is left out; its coarser parents exist.
        assert!(tile(0, 3, 3).is_none());
        assert!(tile(0, 2, 3).is_some() && tile(1, 1, 1).is_some() && tile(2, 0, 0).is_some());
    }

    #[test]
    fn a_texture_of_another_shape_is_refused_and_nothing_written() {
        let dir = tempfile::tempdir().unwrap();
        let image_path = dir.path().join("wide.png");
        png_file(&image_path, 64, 32, &vec![255; 64 * 32 * 4]);
        let texture = TextureInput { image: read_image(&image_path).unwrap(), path: image_path.clone(), tile_size: 16 };
        let out = dir.path().join("t.tspack");
        let err = tile_terrain(
            raster(50, 50, |_, _| 1.0),
            Some(texture),
            "t",
            &out,
            TileOptions::default(),
            &crate::progress::Silent::default(),
        )
        .unwrap_err();
        let text = err.to_string();
        assert!(text.contains("wide.png") && text.contains("mismatched extents"), "{text}");
        assert!(!out.exists());
        assert_eq!(std::fs::read_dir(dir.path()).unwrap().count(), 1, "no temporary file left behind");
    }

    #[test]
    fn images_are_read_from_tiff_and_png_and_bad_ones_named() {
        let dir = tempfile::tempdir().unwrap();
        // An RGB GeoTIFF.
        let tif = dir.path().join("rgb.tif");
        {
            let file = std::fs::File::create(&tif).unwrap();
            let mut encoder = tiff::encoder::TiffEncoder::new(file).unwrap();
            let rgb: Vec<u8> = (0..6u8 * 4 * 3).collect();
            encoder.write_image::<tiff::encoder::colortype::RGB8>(6, 4, &rgb).unwrap();
        }
        let image = read_image(&tif).unwrap();
        assert_eq!((image.width, image.height), (6, 4));
        assert_eq!(&image.rgba[..8], &[0, 1, 2, 255, 3, 4, 5, 255]);
        // Not an image; a truncated PNG.
        let junk = dir.path().join("junk.png");
        std::fs::write(&junk, b"hello").unwrap();
        let e = read_image(&junk).unwrap_err().to_string();
        assert!(e.contains("junk.png") && e.contains("not a GeoTIFF, PNG or JPEG"), "{e}");
        let png_path = dir.path().join("cut.png");
        png_file(&png_path, 8, 8, &[7; 8 * 8 * 4]);
        let bytes = std::fs::read(&png_path).unwrap();
        std::fs::write(&png_path, &bytes[..bytes.len() / 2]).unwrap();
        let e = read_image(&png_path).unwrap_err().to_string();
        assert!(e.contains("cut.png") && e.contains("PNG"), "{e}");
    }

    #[test]
    fn halving_an_image_weights_by_alpha() {
        let image =
            Image { width: 3, height: 1, rgba: vec![200, 0, 0, 255, 0, 0, 0, 0, 10, 20, 30, 255], georeference: None };
        let h = image.halve();
        assert_eq!((h.width, h.height), (2, 1));
        // (200,0,0) opaque with a transparent pixel: its colour, a quarter... of the area's alpha.
        assert_eq!(&h.rgba[..4], &[200, 0, 0, 64]);
        assert_eq!(&h.rgba[4..], &[10, 20, 30, 64]);
    }

    #[test]
    fn a_texture_on_the_dem_grid_is_resampled_to_square_texels() {
        // A DEM with pixels twice as wide in degrees as in metres (a geographic grid), and
        // a texture on that same grid: accepted, resampled along x to square texels.
        let dir = tempfile::tempdir().unwrap();
        let image_path = dir.path().join("grid.png");
        png_file(&image_path, 64, 32, &vec![200; 64 * 32 * 4]);
        let texture = TextureInput { image: read_image(&image_path).unwrap(), path: image_path, tile_size: 16 };
        let mut elevation = raster(100, 50, |_, _| 1.0);
        elevation.spacing = (15.0, 30.0);
        let out = dir.path().join("g.tspack");
        let options = TileOptions { tile_size: 16, ..TileOptions::default() };
        tile_terrain(elevation, Some(texture), "g", &out, options, &crate::progress::Silent::default()).unwrap();
        let reader = crate::Reader::open_mmap(&out).unwrap();
        let t = &reader.metadata().layers[1];
        // 1500 x 1500 m: 32 x 32 texels of 46.875 m.
        assert_eq!((t.num_x_tiles, t.num_y_tiles), (2, 2));
        assert!((t.tile_world_size - 750.0).abs() < 1e-9, "{}", t.tile_world_size);
    }
}
