//! The tiler's inputs, read a band of rows at a time: GeoTIFF by strips or by rows of
//! tiles, PNG row by row, never the whole raster (JPEG, which cannot be read by rows
//! here, is the one exception). Each pass over a source reopens its file, so a source can
//! be read twice (statistics, then tiles) with memory bounded by one band.

use std::path::{Path, PathBuf};

use crate::error::{Error, Result};
use crate::metadata::{ElevationEncoding, ElevationScheme, Georeference};

/// Rows of heights: the elevation input of the tiler.
pub trait ElevationSource: Sync {
    /// Where the samples come from (named in errors).
    fn path(&self) -> &Path;
    /// Samples across and down.
    fn size(&self) -> (u32, u32);
    /// Sample spacing in metres (x, y).
    fn spacing(&self) -> (f64, f64);
    /// Where the raster lies, when the file says.
    fn georeference(&self) -> Option<&Georeference>;
    /// Size of a sample in the georeference's CRS units (x, y), when the file says.
    fn crs_pixel_size(&self) -> Option<(f64, f64)> {
        None
    }
    /// Calls `row` with each row of heights, top to bottom; NaN where there is no data.
    ///
    /// # Errors
    /// [`Error::Input`] naming the file for unreadable data; `row`'s errors.
    fn rows(&self, row: &mut dyn FnMut(&[f32]) -> Result<()>) -> Result<()>;
    /// The lowest and highest height (NaN skipped; infinities when there is no data),
    /// telling `progress` how many rows have been read so far, now and then. A source may
    /// find them without making rows of heights.
    ///
    /// # Errors
    /// As [`ElevationSource::rows`]; `progress`'s errors.
    fn height_range(&self, progress: &mut dyn FnMut(u32) -> Result<()>) -> Result<(f32, f32)> {
        range_of_rows(progress, |row| self.rows(row))
    }
}

/// The range of the rows `read` passes on, `progress` told after each one.
fn range_of_rows(
    progress: &mut dyn FnMut(u32) -> Result<()>,
    read: impl FnOnce(&mut dyn FnMut(&[f32]) -> Result<()>) -> Result<()>,
) -> Result<(f32, f32)> {
    let (mut lo, mut hi, mut n) = (f32::INFINITY, f32::NEG_INFINITY, 0);
    read(&mut |r| {
        let (l, h) = super::min_max(r);
        (lo, hi) = (lo.min(l), hi.max(h));
        n += 1;
        progress(n)
    })?;
    Ok((lo, hi))
}

/// Rows of RGBA8 pixels: the texture input of the tiler.
pub trait ImageSource: Sync {
    /// Where the pixels come from (named in errors).
    fn path(&self) -> &Path;
    /// Pixels across and down.
    fn size(&self) -> (u32, u32);
    /// Where the image lies, when the file says.
    fn georeference(&self) -> Option<&Georeference>;
    /// Size of a pixel in the georeference's CRS units (x, y), when the file says.
    fn crs_pixel_size(&self) -> Option<(f64, f64)> {
        None
    }
    /// Calls `row` with each row of pixels, top to bottom; alpha 0 where there is no data.
    ///
    /// # Errors
    /// [`Error::Input`] naming the file for unreadable data; `row`'s errors.
    fn rows(&self, row: &mut dyn FnMut(&[[u8; 4]]) -> Result<()>) -> Result<()>;
}

/// A single-band raster in memory; NaN where there is no data.
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

impl ElevationSource for Raster {
    fn path(&self) -> &Path {
        Path::new("<raster in memory>")
    }
    fn size(&self) -> (u32, u32) {
        (self.width, self.height)
    }
    fn spacing(&self) -> (f64, f64) {
        self.spacing
    }
    fn georeference(&self) -> Option<&Georeference> {
        self.georeference.as_ref()
    }
    fn rows(&self, row: &mut dyn FnMut(&[f32]) -> Result<()>) -> Result<()> {
        self.data.chunks_exact(self.width.max(1) as usize).try_for_each(row)
    }
}

/// An RGBA8 image in memory: the texture input (orthophoto, satellite scene, shaded relief).
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

impl ImageSource for Image {
    fn path(&self) -> &Path {
        Path::new("<image in memory>")
    }
    fn size(&self) -> (u32, u32) {
        (self.width, self.height)
    }
    fn georeference(&self) -> Option<&Georeference> {
        self.georeference.as_ref()
    }
    fn rows(&self, row: &mut dyn FnMut(&[[u8; 4]]) -> Result<()>) -> Result<()> {
        self.rgba.chunks_exact(self.width.max(1) as usize * 4).try_for_each(|r| row(&as_pixels(r)))
    }
}

/// The part of an image that lies over an elevation raster, when both are georeferenced
/// in one CRS: an aerial image is usually cut wider than the DEM (or the other way round).
/// Read through [`ImageSource`] like the whole image; rows above the window are skipped and
/// reading stops after its last row.
#[derive(Debug)]
pub struct ImageWindow<'a> {
    inner: &'a dyn ImageSource,
    /// First column and row, width and height, in the image's pixels.
    x0: u32,
    y0: u32,
    width: u32,
    height: u32,
    georeference: Option<Georeference>,
}

impl std::fmt::Debug for dyn ImageSource + '_ {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        write!(f, "ImageSource({})", self.path().display())
    }
}

/// Where a raster lies in its CRS, when its file says: the CRS, the north-west corner and
/// the pixel size in CRS units.
pub(crate) fn crs_placement(
    georeference: Option<&Georeference>,
    pixel: Option<(f64, f64)>,
) -> Option<(&str, [f64; 2], (f64, f64))> {
    let g = georeference?;
    Some((g.crs.as_deref()?, g.origin?, pixel?))
}

impl<'a> ImageWindow<'a> {
    /// The window of `image` over `elevation`'s extent; `None` when they cannot be matched
    /// by georeference (either lacks one, or their CRSs differ) or the window is the whole
    /// image.
    ///
    /// # Errors
    /// [`Error::Input`] naming the image when it does not cover the elevation's extent.
    pub fn over(elevation: &dyn ElevationSource, image: &'a dyn ImageSource) -> Result<Option<Self>> {
        let (Some((dem_crs, dem_origin, dem_px)), Some((img_crs, img_origin, img_px))) = (
            crs_placement(elevation.georeference(), elevation.crs_pixel_size()),
            crs_placement(image.georeference(), image.crs_pixel_size()),
        ) else {
            return Ok(None);
        };
        if dem_crs != img_crs {
            return Ok(None);
        }
        let (dw, dh) = elevation.size();
        let (iw, ih) = image.size();
        // The DEM's edges in the image's pixel coordinates (CRS y grows north, rows south).
        let left = (dem_origin[0] - img_origin[0]) / img_px.0;
        let right = (dem_origin[0] + f64::from(dw) * dem_px.0 - img_origin[0]) / img_px.0;
        let top = (img_origin[1] - dem_origin[1]) / img_px.1;
        let bottom = (img_origin[1] - (dem_origin[1] - f64::from(dh) * dem_px.1)) / img_px.1;
        let (fw, fh) = (f64::from(iw), f64::from(ih));
        if left < -0.5 || top < -0.5 || right > fw + 0.5 || bottom > fh + 0.5 {
            return Err(Error::input(
                image.path(),
                format!(
                    "mismatched extents: the elevation lies over pixels x {left:.1}..{right:.1}, y {top:.1}..{bottom:.1} \
                     of this {iw}x{ih} image ({dem_crs}); the texture must cover the whole elevation"
                ),
            ));
        }
        #[expect(clippy::cast_possible_truncation, clippy::cast_sign_loss, reason = "clamped to the image")]
        let edge = |v: f64, max: f64| v.round().clamp(0.0, max) as u32;
        let (x0, x1, y0, y1) = (edge(left, fw), edge(right, fw), edge(top, fh), edge(bottom, fh));
        if x1 <= x0 || y1 <= y0 {
            return Err(Error::input(image.path(), "the elevation covers less than one pixel of the texture"));
        }
        if (x0, y0, x1, y1) == (0, 0, iw, ih) {
            return Ok(None);
        }
        let georeference = image.georeference().map(|g| Georeference {
            origin: Some([img_origin[0] + f64::from(x0) * img_px.0, img_origin[1] - f64::from(y0) * img_px.1]),
            lat_lon_bounds: None,
            ..g.clone()
        });
        Ok(Some(Self { inner: image, x0, y0, width: x1 - x0, height: y1 - y0, georeference }))
    }

    /// First column and row of the window in the image, and its size.
    pub fn bounds(&self) -> (u32, u32, u32, u32) {
        (self.x0, self.y0, self.width, self.height)
    }
}

impl ImageSource for ImageWindow<'_> {
    fn path(&self) -> &Path {
        self.inner.path()
    }
    fn size(&self) -> (u32, u32) {
        (self.width, self.height)
    }
    fn georeference(&self) -> Option<&Georeference> {
        self.georeference.as_ref()
    }
    fn crs_pixel_size(&self) -> Option<(f64, f64)> {
        self.inner.crs_pixel_size()
    }
    fn rows(&self, row: &mut dyn FnMut(&[[u8; 4]]) -> Result<()>) -> Result<()> {
        let (columns, rows) = (self.x0 as usize..(self.x0 + self.width) as usize, self.y0..self.y0 + self.height);
        let (mut y, mut done) = (0u32, false);
        let result = self.inner.rows(&mut |pixels| {
            let here = y;
            y += 1;
            if here < rows.start {
                return Ok(());
            }
            row(&pixels[columns.clone()])?;
            if here + 1 == rows.end {
                // Past the window: stop reading the file (told apart from a real interrupt).
                done = true;
                return Err(Error::Interrupted);
            }
            Ok(())
        });
        match result {
            Err(Error::Interrupted) if done => Ok(()),
            other => other,
        }
    }
}

fn as_pixels(rgba: &[u8]) -> Vec<[u8; 4]> {
    rgba.chunks_exact(4).map(|p| [p[0], p[1], p[2], p[3]]).collect()
}

/// An image file read row by row (GeoTIFF, PNG) or, for JPEG, decoded once when opened.
#[derive(Debug)]
pub struct ImageFile {
    path: PathBuf,
    width: u32,
    height: u32,
    georeference: Option<Georeference>,
    crs_pixel: Option<(f64, f64)>,
    kind: ImageKind,
}

#[derive(Debug)]
enum ImageKind {
    Tiff {
        channels: usize,
    },
    Png,
    /// RGB pixels of a JPEG, decoded when opened.
    Decoded(Vec<u8>),
}

/// An elevation file read row by row: a GeoTIFF of numbers or a PNG whose pixels encode
/// heights (16-bit gray, or 8-bit gray / RGB in one of the [`ElevationScheme`]s).
#[derive(Debug)]
pub struct ElevationFile {
    path: PathBuf,
    width: u32,
    height: u32,
    spacing: (f64, f64),
    georeference: Option<Georeference>,
    crs_pixel: Option<(f64, f64)>,
    nodata: Option<f64>,
    /// How PNG pixels (or 8-bit TIFF samples) map to heights; None: samples are heights.
    encoding: Option<ElevationEncoding>,
    png: bool,
}

const MODEL_PIXEL_SCALE: u16 = 33550;
const MODEL_TIEPOINT: u16 = 33922;
const GEO_KEY_DIRECTORY: u16 = 34735;
const GDAL_NODATA: u16 = 42113;
const PLANAR_CONFIGURATION: u16 = 284;

type TiffDecoder = tiff::decoder::Decoder<std::io::BufReader<std::fs::File>>;

fn open_tiff(path: &Path) -> Result<TiffDecoder> {
    use tiff::decoder::{Decoder, Limits};
    let file = std::fs::File::open(path).map_err(|e| Error::file(path, e))?;
    let mut limits = Limits::default();
    // One chunk (a strip or a tile) is decoded at a time: allow big ones, not the image.
    limits.decoding_buffer_size = 1 << 30;
    limits.intermediate_buffer_size = 1 << 30;
    Ok(Decoder::new(std::io::BufReader::new(file))
        .map_err(|e| Error::input(path, format!("not a readable TIFF: {e}")))?
        .with_limits(limits))
}

/// The kind of file, by its first bytes.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
enum Sniffed {
    Tiff,
    Png,
    Jpeg,
}

fn sniff(path: &Path) -> Result<Sniffed> {
    use std::io::Read;
    let mut head = [0u8; 8];
    let mut file = std::fs::File::open(path).map_err(|e| Error::file(path, e))?;
    let n = file.read(&mut head).map_err(|e| Error::file(path, e))?;
    let head = &head[..n];
    if head.starts_with(b"II*\0") || head.starts_with(b"MM\0*") || head.starts_with(b"II+\0") {
        Ok(Sniffed::Tiff)
    } else if head.starts_with(b"\x89PNG") {
        Ok(Sniffed::Png)
    } else if head.starts_with(&[0xFF, 0xD8]) {
        Ok(Sniffed::Jpeg)
    } else if n == 0 {
        Err(Error::input(path, "the file is empty (0 bytes)"))
    } else {
        Err(Error::input(path, "not a GeoTIFF, PNG or JPEG image"))
    }
}

/// Reads a single-band GeoTIFF whole (small rasters, tests); [`open_elevation`] streams.
///
/// # Errors
/// [`Error::Input`] naming the file for anything unreadable or unsupported.
pub fn read_geotiff(path: &Path) -> Result<Raster> {
    let file = open_elevation(path, None)?;
    let (width, height) = file.size();
    let mut data = Vec::with_capacity(width as usize * height as usize);
    file.rows(&mut |row| {
        data.extend_from_slice(row);
        Ok(())
    })?;
    Ok(Raster { width, height, data, spacing: file.spacing, georeference: file.georeference })
}

/// Opens an elevation raster for reading by rows: a single-band GeoTIFF (int8..32,
/// uint8..32, float32/64; strips or tiles; none, LZW or Deflate; GDAL nodata), whose
/// samples are heights unless `encoding` maps them; or a PNG: 16-bit gray (heights, or
/// mapped by a `quantized_u16` encoding), 8-bit gray (`gray8`) or RGB (`rgb_thirds`,
/// `terrain_rgb`, `terrarium`), transparent pixels being nodata.
///
/// # Errors
/// [`Error::Input`] naming the file: unreadable, not an elevation raster, a PNG whose
/// pixels need an encoding that was not given or does not fit them.
pub fn open_elevation(path: &Path, encoding: Option<ElevationEncoding>) -> Result<ElevationFile> {
    let bad = |why: String| Error::input(path, why);
    match sniff(path)? {
        Sniffed::Jpeg => Err(bad("JPEG is lossy: elevation must come from a GeoTIFF or a PNG".into())),
        Sniffed::Png => {
            let ((colour, depth), (width, height)) = png_header(path)?;
            let channels = colour.samples();
            let rgb = channels >= 3;
            let sixteen = depth == png::BitDepth::Sixteen;
            let encoding = match encoding {
                Some(e) if e.scheme.needs_rgb() && !rgb => {
                    return Err(bad(format!("{:?} needs RGB pixels; this PNG is {colour:?}", e.scheme)));
                }
                Some(e) if e.scheme.needs_rgb() || e.scheme == ElevationScheme::Gray8 => {
                    if sixteen {
                        return Err(bad(format!("{:?} needs 8-bit pixels; this PNG is 16-bit", e.scheme)));
                    }
                    e
                }
                Some(e) if e.scheme == ElevationScheme::QuantizedU16 && sixteen && !rgb => e,
                Some(e) => return Err(bad(format!("{:?} does not apply to a {colour:?} {depth:?} PNG", e.scheme))),
                None if sixteen && !rgb => {
                    ElevationEncoding { scheme: ElevationScheme::QuantizedU16, scale: 1.0, offset: 0.0, nodata: None }
                }
                None => {
                    return Err(bad(format!(
                        "a {depth:?}-bit {colour:?} PNG: say how its pixels map to heights (an elevation encoding: \
                         gray8 with a minimum and displacement, rgb-thirds, terrain-rgb or terrarium)"
                    )));
                }
            };
            Ok(ElevationFile {
                path: path.to_path_buf(),
                width,
                height,
                spacing: (1.0, 1.0),
                georeference: None,
                crs_pixel: None,
                nodata: encoding.nodata,
                encoding: Some(encoding),
                png: true,
            })
        }
        Sniffed::Tiff => {
            let mut decoder = open_tiff(path)?;
            let (width, height) = decoder.dimensions().map_err(|e| bad(e.to_string()))?;
            if width == 0 || height == 0 {
                return Err(bad(format!("the raster is empty ({width}x{height})")));
            }
            let colour = decoder.colortype().map_err(|e| bad(e.to_string()))?;
            let eight = matches!(colour, tiff::ColorType::Gray(8));
            match colour {
                tiff::ColorType::Gray(_) => {}
                other => {
                    return Err(bad(format!("{other:?} samples: an elevation GeoTIFF has a single band of numbers")));
                }
            }
            if let Some(e) = encoding {
                if e.scheme.needs_rgb() || (e.scheme == ElevationScheme::Gray8 && !eight) {
                    return Err(bad(format!("{:?} does not apply to a single-band {colour:?} GeoTIFF", e.scheme)));
                }
            }
            let nodata: Option<f64> = decoder
                .find_tag(tiff::tags::Tag::Unknown(GDAL_NODATA))
                .ok()
                .flatten()
                .and_then(|v| v.into_string().ok())
                .and_then(|s| s.trim_matches(char::from(0)).trim().parse().ok());
            let tags = GeoTags::read(&mut decoder);
            let (spacing, georeference) = tags.placement(width, height).map_err(bad)?;
            Ok(ElevationFile {
                path: path.to_path_buf(),
                width,
                height,
                spacing,
                crs_pixel: georeference.as_ref().and_then(|_| tags.crs_pixel()),
                georeference,
                nodata,
                encoding,
                png: false,
            })
        }
    }
}

impl ElevationFile {
    /// Replaces the sample spacing (metres), e.g. for a PNG, which carries none.
    #[must_use]
    pub fn with_spacing(mut self, spacing: f64) -> Self {
        self.spacing = (spacing, spacing);
        self
    }

    /// Does the file place itself (GeoTIFF georeference) or is its spacing a default?
    pub fn is_georeferenced(&self) -> bool {
        self.georeference.is_some()
    }

    /// A stored value -> its height (NaN for nodata and non-finite values).
    fn convert(&self) -> impl Fn(f64) -> f32 + Sync + '_ {
        // Nodata is compared as f32, as samples are kept (a GDAL nodata of "3.40282e+38"
        // is f32::MAX only once rounded to f32).
        #[expect(clippy::cast_possible_truncation, reason = "nodata and heights are kept as f32")]
        let nodata = self.nodata.map(|n| n as f32);
        #[expect(clippy::cast_possible_truncation, reason = "heights are kept as f32")]
        move |raw: f64| -> f32 {
            if !raw.is_finite() || nodata == Some(raw as f32) {
                return f32::NAN;
            }
            match &self.encoding {
                Some(e) => e.height(raw) as f32,
                None => raw as f32,
            }
        }
    }

    /// A PNG's rows of heights (16-bit values, or 8-bit encodings; transparent = nodata).
    fn png_heights(&self, row: &mut dyn FnMut(&[f32]) -> Result<()>) -> Result<()> {
        let mut out = vec![0f32; self.width as usize];
        let convert = self.convert();
        let scheme = self.encoding.map_or(ElevationScheme::QuantizedU16, |e| e.scheme);
        png_rows(&self.path, self.width, |values, channels, sixteen| {
            let sample = |i: usize| -> f64 {
                if sixteen {
                    f64::from(u16::from_be_bytes([values[2 * i], values[2 * i + 1]]))
                } else {
                    f64::from(values[i])
                }
            };
            let alpha = matches!(channels, 2 | 4);
            for (x, h) in out.iter_mut().enumerate() {
                let p = x * channels;
                let opaque = !alpha || sample(p + channels - 1) > 0.0;
                let (r, g, b) =
                    if channels >= 3 { (sample(p), sample(p + 1), sample(p + 2)) } else { (sample(p), 0.0, 0.0) };
                *h = if opaque { convert(scheme.value(r, g, b)) } else { f32::NAN };
            }
            row(&out)
        })
    }
}

impl ElevationSource for ElevationFile {
    fn path(&self) -> &Path {
        &self.path
    }
    fn size(&self) -> (u32, u32) {
        (self.width, self.height)
    }
    fn spacing(&self) -> (f64, f64) {
        self.spacing
    }
    fn georeference(&self) -> Option<&Georeference> {
        self.georeference.as_ref()
    }
    fn crs_pixel_size(&self) -> Option<(f64, f64)> {
        self.crs_pixel
    }
    fn rows(&self, row: &mut dyn FnMut(&[f32]) -> Result<()>) -> Result<()> {
        if self.png {
            return self.png_heights(row);
        }
        tiff_rows(&self.path, 1, &|samples: &mut [f32]| self.heights(samples), row)
    }

    fn height_range(&self, progress: &mut dyn FnMut(u32) -> Result<()>) -> Result<(f32, f32)> {
        if self.png {
            return range_of_rows(progress, |row| self.png_heights(row));
        }
        // Every strip or tile, in parallel and in any order, reduced to its range where
        // it is decoded; no rows are made.
        let chunks = TiffChunks::open(&self.path, 1)?;
        let (mut lo, mut hi) = (f32::INFINITY, f32::NEG_INFINITY);
        let batch = chunks.batch();
        let needed = chunks.needed();
        for first in (0..needed).step_by(batch) {
            let end = needed.min(first + batch);
            let ranges: Vec<Result<(f32, f32)>> = {
                use rayon::prelude::*;
                (first..end)
                    .into_par_iter()
                    .map(|i| {
                        let (data, w, h) = chunks.read(i)?;
                        self.chunk_range(data, w * h)
                            .ok_or_else(|| Error::input(&self.path, "unsupported sample type".to_string()))
                    })
                    .collect()
            };
            for range in ranges {
                let (l, h) = range?;
                (lo, hi) = (lo.min(l), hi.max(h));
            }
            progress(chunks.rows_before(end))?;
        }
        Ok((lo, hi))
    }
}

impl ElevationFile {
    /// Stored samples -> heights in place (NaN for nodata and non-finite values).
    fn heights(&self, samples: &mut [f32]) {
        #[expect(clippy::cast_possible_truncation, reason = "nodata and heights are kept as f32")]
        let nodata = self.nodata.map(|n| n as f32);
        if self.encoding.is_none() {
            // Heights as stored (the usual DEM): a branch-free loop. NaN as "no nodata"
            // equals nothing; `&`, not `&&`: both compares, no branch. NaN and infinities
            // fail the first.
            let nodata = nodata.unwrap_or(f32::NAN);
            for v in samples.iter_mut() {
                *v = if (v.abs() < f32::INFINITY) & (*v != nodata) { *v } else { f32::NAN };
            }
        } else {
            let convert = self.convert();
            for v in samples.iter_mut() {
                *v = convert(f64::from(*v));
            }
        }
    }

    /// The range of heights in the first `n` samples of a decoded chunk (which holds at
    /// least `n`, see [`TiffChunks::read`]); None for a sample type heights are not read
    /// from. 8- and 16-bit samples stored as heights are compared as integers, as they are
    /// (no conversion, 8 or 16 lanes a vector).
    fn chunk_range(&self, data: tiff::decoder::DecodingResult, n: usize) -> Option<(f32, f32)> {
        use tiff::decoder::DecodingResult as D;
        #[expect(clippy::cast_possible_truncation, reason = "nodata is compared as f32, as samples are kept")]
        let nodata = self.nodata.map(|n| n as f32);
        if self.encoding.is_none() {
            match &data {
                D::U8(v) => return Some(integer_range(&v[..n], nodata)),
                D::I8(v) => return Some(integer_range(&v[..n], nodata)),
                D::U16(v) => return Some(integer_range(&v[..n], nodata)),
                D::I16(v) => return Some(integer_range(&v[..n], nodata)),
                _ => {}
            }
        }
        let mut samples = samples_f32(data)?;
        samples.truncate(n);
        self.heights(&mut samples);
        Some(super::min_max(&samples))
    }
}

/// Integer samples of at most 16 bits, and the arithmetic their range needs.
pub(super) trait Small: Copy + Ord + Into<f32> + TryFrom<i32> {
    const LOWEST: Self;
    const HIGHEST: Self;
}
macro_rules! small {
    ($($t:ty),*) => {$(impl Small for $t { const LOWEST: Self = <$t>::MIN; const HIGHEST: Self = <$t>::MAX; })*};
}
small!(u8, i8, u16, i16);

/// The range of integer samples as heights (those equal to `nodata` skipped; infinities
/// when none is left). A nodata that no sample of the type can equal skips nothing.
pub(super) fn integer_range<T: Small>(values: &[T], nodata: Option<f32>) -> (f32, f32) {
    #[expect(clippy::cast_possible_truncation, reason = "an integral f32 within the type's range")]
    let nodata = nodata
        .filter(|n| n.fract() == 0.0 && (T::LOWEST.into()..=T::HIGHEST.into()).contains(n))
        .and_then(|n| T::try_from(n as i32).ok());
    // Is there a sample to take? (Usually the first says.) Then the lowest and highest
    // with selects, not branches, so that the loops vectorize.
    if !values.iter().any(|&v| Some(v) != nodata) {
        return (f32::INFINITY, f32::NEG_INFINITY);
    }
    let (mut lo, mut hi) = (T::HIGHEST, T::LOWEST);
    match nodata {
        Some(skip) => {
            for &v in values {
                lo = lo.min(if v == skip { T::HIGHEST } else { v });
                hi = hi.max(if v == skip { T::LOWEST } else { v });
            }
        }
        None => {
            for &v in values {
                lo = lo.min(v);
                hi = hi.max(v);
            }
        }
    }
    (lo.into(), hi.into())
}

/// Opens an image for reading by rows: GeoTIFF (8-bit gray, gray+alpha, RGB or RGBA; strips
/// or tiles; none, LZW or Deflate) or PNG (any colour type; 16-bit is reduced to 8), or
/// JPEG (decoded here, whole); told apart by content.
///
/// # Errors
/// [`Error::Input`] naming the file for anything unreadable or unsupported.
pub fn open_image(path: &Path) -> Result<ImageFile> {
    let bad = |why: String| Error::input(path, why);
    let mut crs_pixel = None;
    let (width, height, georeference, kind) = match sniff(path)? {
        Sniffed::Png => {
            let (_, (w, h)) = png_header(path)?;
            (w, h, None, ImageKind::Png)
        }
        Sniffed::Jpeg => {
            let bytes = std::fs::read(path).map_err(|e| Error::file(path, e))?;
            let options = zune_jpeg::zune_core::options::DecoderOptions::default()
                .jpeg_set_out_colorspace(zune_jpeg::zune_core::colorspace::ColorSpace::RGB)
                .set_max_width(1 << 16)
                .set_max_height(1 << 16);
            let mut decoder = zune_jpeg::JpegDecoder::new_with_options(&bytes, options);
            decoder.decode_headers().map_err(|e| bad(format!("JPEG: {e:?}")))?;
            let (w, h) = decoder.dimensions().ok_or_else(|| bad("JPEG: no dimensions".into()))?;
            jpeg_fits(path, w, h)?;
            let pixels = decoder.decode().map_err(|e| bad(format!("JPEG: {e:?}")))?;
            let dim = |n: usize| u32::try_from(n).map_err(|_| bad("JPEG: too large".into()));
            (dim(w)?, dim(h)?, None, ImageKind::Decoded(pixels))
        }
        Sniffed::Tiff => {
            let mut decoder = open_tiff(path)?;
            let (width, height) = decoder.dimensions().map_err(|e| bad(e.to_string()))?;
            let channels = match decoder.colortype().map_err(|e| bad(e.to_string()))? {
                tiff::ColorType::Gray(8) => 1,
                tiff::ColorType::GrayA(8) => 2,
                tiff::ColorType::RGB(8) => 3,
                tiff::ColorType::RGBA(8) => 4,
                other => return Err(bad(format!("{other:?} pixels: textures must be 8-bit gray, RGB or RGBA"))),
            };
            let planar = decoder.find_tag_unsigned::<u16>(tiff::tags::Tag::Unknown(PLANAR_CONFIGURATION));
            if channels > 1 && matches!(planar, Ok(Some(2))) {
                return Err(bad("planar (band-separate) pixels: store the bands interleaved".into()));
            }
            let tags = GeoTags::read(&mut decoder);
            let georeference = tags.placement(width, height).ok().and_then(|(_, g)| g);
            crs_pixel = georeference.as_ref().and_then(|_| tags.crs_pixel());
            (width, height, georeference, ImageKind::Tiff { channels })
        }
    };
    if width == 0 || height == 0 {
        return Err(bad(format!("the image is empty ({width}x{height} pixels)")));
    }
    if let ImageKind::Decoded(rgb) = &kind {
        if rgb.len() != width as usize * height as usize * 3 {
            return Err(bad(format!("{} bytes of pixels for {width}x{height}", rgb.len())));
        }
    }
    Ok(ImageFile { path: path.to_path_buf(), width, height, georeference, crs_pixel, kind })
}

/// Most bytes a JPEG may take decoded. A JPEG is decoded whole (it cannot be read by rows,
/// unlike every other input), so this bounds the tiler's memory for one.
pub const JPEG_MAX_DECODED_BYTES: usize = 1 << 30;

/// Refuses a JPEG too large to decode whole, naming the way out.
pub(super) fn jpeg_fits(path: &Path, width: usize, height: usize) -> Result<()> {
    let bytes = width.saturating_mul(height).saturating_mul(3);
    if bytes > JPEG_MAX_DECODED_BYTES {
        return Err(Error::input(
            path,
            format!(
                "a {width}x{height} JPEG takes {} MiB decoded, over the {} MiB a JPEG may take (it cannot be \
                 read by rows): convert it to a tiled GeoTIFF, which is streamed (gdal_translate -co TILED=YES \
                 -co COMPRESS=JPEG in.jpg out.tif)",
                bytes >> 20,
                JPEG_MAX_DECODED_BYTES >> 20
            ),
        ));
    }
    Ok(())
}

/// Reads a whole image into memory (small images, tests); [`open_image`] streams.
///
/// # Errors
/// As [`open_image`].
pub fn read_image(path: &Path) -> Result<Image> {
    let file = open_image(path)?;
    let mut rgba = Vec::with_capacity(file.width as usize * file.height as usize * 4);
    file.rows(&mut |row| {
        rgba.extend_from_slice(row.as_flattened());
        Ok(())
    })?;
    Ok(Image { width: file.width, height: file.height, rgba, georeference: file.georeference })
}

impl ImageSource for ImageFile {
    fn path(&self) -> &Path {
        &self.path
    }
    fn size(&self) -> (u32, u32) {
        (self.width, self.height)
    }
    fn georeference(&self) -> Option<&Georeference> {
        self.georeference.as_ref()
    }
    fn crs_pixel_size(&self) -> Option<(f64, f64)> {
        self.crs_pixel
    }
    fn rows(&self, row: &mut dyn FnMut(&[[u8; 4]]) -> Result<()>) -> Result<()> {
        let width = self.width as usize;
        let mut out = vec![[0u8; 4]; width];
        let mut emit = |values: &[u8], channels: usize| {
            for (p, px) in out.iter_mut().zip(values.chunks_exact(channels)) {
                *p = match channels {
                    4 => [px[0], px[1], px[2], px[3]],
                    3 => [px[0], px[1], px[2], 255],
                    2 => [px[0], px[0], px[0], px[1]],
                    _ => [px[0], px[0], px[0], 255],
                };
            }
            row(&out)
        };
        match &self.kind {
            ImageKind::Decoded(rgb) => rgb.chunks_exact(width * 3).try_for_each(|r| emit(r, 3)),
            ImageKind::Png => png_rows(&self.path, self.width, |values, channels, sixteen| {
                if sixteen {
                    let eight: Vec<u8> = values.chunks_exact(2).map(|v| v[0]).collect();
                    emit(&eight, channels)
                } else {
                    emit(values, channels)
                }
            }),
            ImageKind::Tiff { channels } => {
                let mut bytes = vec![0u8; width * channels];
                #[expect(clippy::cast_possible_truncation, clippy::cast_sign_loss, reason = "8-bit samples")]
                let mut eight = |r: &[f32]| -> Result<()> {
                    for (b, &v) in bytes.iter_mut().zip(r) {
                        *b = v as u8;
                    }
                    emit(&bytes, *channels)
                };
                tiff_rows(&self.path, *channels, &|_| {}, &mut eight)
            }
        }
    }
}

/// A PNG's (colour type, bit depth) after expansion, and its size.
fn png_header(path: &Path) -> Result<((png::ColorType, png::BitDepth), (u32, u32))> {
    let file = std::fs::File::open(path).map_err(|e| Error::file(path, e))?;
    let mut decoder = png::Decoder::new(std::io::BufReader::new(file));
    decoder.set_transformations(png::Transformations::EXPAND);
    let reader = decoder.read_info().map_err(|e| Error::input(path, format!("PNG: {e}")))?;
    let info = reader.info();
    let size = (info.width, info.height);
    if size.0 == 0 || size.1 == 0 {
        return Err(Error::input(path, "the image is empty (0 pixels)"));
    }
    Ok((reader.output_color_type(), size))
}

/// Calls `row(values, channels, sixteen)` for each row of a PNG (palette and low bit
/// depths expanded; 16-bit samples big-endian).
fn png_rows(path: &Path, width: u32, mut row: impl FnMut(&[u8], usize, bool) -> Result<()>) -> Result<()> {
    let file = std::fs::File::open(path).map_err(|e| Error::file(path, e))?;
    let mut decoder = png::Decoder::new(std::io::BufReader::new(file));
    decoder.set_transformations(png::Transformations::EXPAND);
    let mut reader = decoder.read_info().map_err(|e| Error::input(path, format!("PNG: {e}")))?;
    let (colour, depth) = reader.output_color_type();
    let channels = colour.samples();
    let sixteen = depth == png::BitDepth::Sixteen;
    let expected = width as usize * channels * if sixteen { 2 } else { 1 };
    let mut y = 0u32;
    while let Some(r) = reader.next_row().map_err(|e| Error::input(path, format!("PNG, row {y}: {e}")))? {
        let data = r.data();
        if data.len() < expected {
            return Err(Error::input(path, format!("PNG, row {y}: {} bytes, {expected} expected", data.len())));
        }
        row(&data[..expected], channels, sixteen)?;
        y += 1;
    }
    Ok(())
}

/// Bytes of samples decoded per batch of strips (at least two strips a thread).
const STRIP_BATCH_BYTES: usize = 1 << 20;

/// A TIFF's strips or tiles, read and decoded by any thread: each read takes a spare
/// decoder (or opens one) and gives it back, so that chunks decode in parallel.
struct TiffChunks<'p> {
    path: &'p Path,
    /// Decoders not in use.
    spare: std::sync::Mutex<Vec<TiffDecoder>>,
    kind: tiff::decoder::ChunkType,
    count: usize,
    /// Samples per pixel.
    channels: usize,
    width: usize,
    height: usize,
    chunk_w: usize,
    chunk_h: usize,
}

impl<'p> TiffChunks<'p> {
    fn open(path: &'p Path, channels: usize) -> Result<Self> {
        use tiff::decoder::ChunkType;
        let bad = |why: String| Error::input(path, why);
        let mut decoder = open_tiff(path)?;
        let (width, height) = decoder.dimensions().map_err(|e| bad(e.to_string()))?;
        let (chunk_w, chunk_h) = decoder.chunk_dimensions();
        if chunk_w == 0 || chunk_h == 0 {
            return Err(bad("zero-size strips or tiles".into()));
        }
        let kind = decoder.get_chunk_type();
        let count = match kind {
            ChunkType::Strip => decoder.strip_count(),
            ChunkType::Tile => decoder.tile_count(),
        }
        .map_err(|e| bad(format!("{}s: {e}", Self::name(kind))))? as usize;
        Ok(Self {
            path,
            spare: std::sync::Mutex::new(vec![decoder]),
            kind,
            count,
            channels,
            width: width as usize,
            height: height as usize,
            chunk_w: chunk_w as usize,
            chunk_h: chunk_h as usize,
        })
    }

    fn name(kind: tiff::decoder::ChunkType) -> &'static str {
        if kind == tiff::decoder::ChunkType::Strip { "strip" } else { "tile" }
    }

    /// Strips decoded at a time: about [`STRIP_BATCH_BYTES`] of samples, at least two a
    /// thread.
    fn batch(&self) -> usize {
        let strip_bytes = (self.width * self.channels * self.chunk_h * 4).max(1);
        (STRIP_BATCH_BYTES / strip_bytes).max(2 * rayon::current_num_threads())
    }

    /// Chunks across the raster: one strip, or a row of tiles.
    fn across(&self) -> usize {
        if self.kind == tiff::decoder::ChunkType::Strip { 1 } else { self.width.div_ceil(self.chunk_w) }
    }

    /// The chunks the raster needs.
    fn needed(&self) -> usize {
        self.height.div_ceil(self.chunk_h) * self.across()
    }

    /// Rows of the raster read once chunks `..end` (in file order) are.
    fn rows_before(&self, end: usize) -> u32 {
        u32::try_from((end / self.across().max(1) * self.chunk_h).min(self.height)).unwrap_or(u32::MAX)
    }

    /// Chunk `index` decoded, and the pixels across and down it holds.
    fn read(&self, index: usize) -> Result<(tiff::decoder::DecodingResult, usize, usize)> {
        let what = Self::name(self.kind);
        let bad = |why: String| Error::input(self.path, why);
        let i = u32::try_from(index).map_err(|_| bad("too many chunks".into()))?;
        if index >= self.count {
            return Err(bad(format!("{what} {index} is missing (the file lists {})", self.count)));
        }
        let spare = self.spare.lock().unwrap_or_else(std::sync::PoisonError::into_inner).pop();
        let mut decoder = match spare {
            Some(d) => d,
            None => open_tiff(self.path)?,
        };
        let (w, h) = decoder.chunk_data_dimensions(i);
        let data = decoder.read_chunk(i).map_err(|e| bad(format!("reading {what} {index}: {e}")));
        self.spare.lock().unwrap_or_else(std::sync::PoisonError::into_inner).push(decoder);
        let data = data?;
        let (w, h) = (w as usize, h as usize);
        let (held, expected) = (samples_in(&data), w * h * self.channels);
        if held < expected {
            return Err(bad(format!("{what} {index}: {held} samples, {expected} expected")));
        }
        Ok((data, w, h))
    }
}

/// How many samples a decoded chunk holds.
fn samples_in(data: &tiff::decoder::DecodingResult) -> usize {
    use tiff::decoder::DecodingResult as D;
    match data {
        D::U8(v) => v.len(),
        D::I8(v) => v.len(),
        D::U16(v) => v.len(),
        D::I16(v) => v.len(),
        D::U32(v) => v.len(),
        D::I32(v) => v.len(),
        D::U64(v) => v.len(),
        D::I64(v) => v.len(),
        D::F32(v) => v.len(),
        D::F64(v) => v.len(),
        _ => 0,
    }
}

/// Calls `row` with each row of a TIFF's samples (`channels` per pixel), in order, after
/// `prepare` has seen them (in the decoding threads: a conversion in place). Strips
/// (a batch of about [`STRIP_BATCH_BYTES`]) or tiles (one per thread) are read and decoded
/// in parallel, each thread with a decoder of its own, so decompression (LZW, Deflate) and
/// conversion use every core; memory is one batch of strips, or a row of tiles and one
/// tile per thread. Samples are f32: exact for 8- and 16-bit values, and heights are kept
/// as f32 anyway.
fn tiff_rows(
    path: &Path,
    channels: usize,
    prepare: &(dyn Fn(&mut [f32]) + Sync),
    row: &mut dyn FnMut(&[f32]) -> Result<()>,
) -> Result<()> {
    use rayon::prelude::*;
    use tiff::decoder::ChunkType;
    let bad = |why: String| Error::input(path, why);
    let chunks = TiffChunks::open(path, channels)?;
    let (width, height, kind) = (chunks.width, chunks.height, chunks.kind);
    let stride = width * channels;
    let (chunk_w, chunk_h) = (chunks.chunk_w, chunks.chunk_h);
    let chunk = |index: usize| -> Result<(Vec<f32>, usize, usize)> {
        let (data, w, h) = chunks.read(index)?;
        let mut values = samples_f32(data).ok_or_else(|| bad("unsupported sample type".into()))?;
        prepare(&mut values);
        Ok((values, w, h))
    };
    // Chunks `range`, decoded in parallel; the first failure in file order is the error.
    let decode = |range: std::ops::Range<usize>| -> Result<Vec<(Vec<f32>, usize, usize)>> {
        range.into_par_iter().map(chunk).collect::<Vec<_>>().into_iter().collect()
    };
    match kind {
        ChunkType::Strip => {
            let strips = height.div_ceil(chunk_h);
            let batch = chunks.batch();
            let mut y = 0;
            for first in (0..strips).step_by(batch) {
                for (values, _, h) in decode(first..strips.min(first + batch))? {
                    for r in values.chunks_exact(stride).take(h.min(height - y)) {
                        row(r)?;
                    }
                    y += h;
                }
            }
            if y < height {
                return Err(bad(format!("strips hold {y} of {height} rows")));
            }
        }
        ChunkType::Tile => {
            let across = chunks.across();
            let mut band = vec![0f32; stride * chunk_h];
            for ty in 0..height.div_ceil(chunk_h) {
                let mut rows_here = chunk_h.min(height - ty * chunk_h);
                // A tile per thread at a time: the decoded tiles held are as many as threads.
                let group = rayon::current_num_threads().max(1);
                for first in (0..across).step_by(group) {
                    let tiles = decode(ty * across + first..ty * across + across.min(first + group))?;
                    for (tx, (values, w, h)) in (first..).zip(tiles) {
                        rows_here = rows_here.min(h);
                        let x0 = tx * chunk_w * channels;
                        let w = w.min(width - tx * chunk_w) * channels;
                        for (j, src) in values.chunks_exact(w.max(1)).take(h).enumerate() {
                            band[j * stride + x0..j * stride + x0 + w].copy_from_slice(&src[..w]);
                        }
                    }
                }
                for r in band.chunks_exact(stride).take(rows_here) {
                    row(r)?;
                }
            }
        }
    }
    Ok(())
}

#[expect(
    clippy::cast_precision_loss,
    clippy::cast_possible_truncation,
    reason = "samples are kept as f32: exact up to 24 bits, heights need no more"
)]
fn samples_f32(data: tiff::decoder::DecodingResult) -> Option<Vec<f32>> {
    use tiff::decoder::DecodingResult as D;
    Some(match data {
        D::U8(v) => v.into_iter().map(f32::from).collect(),
        D::I8(v) => v.into_iter().map(f32::from).collect(),
        D::U16(v) => v.into_iter().map(f32::from).collect(),
        D::I16(v) => v.into_iter().map(f32::from).collect(),
        D::U32(v) => v.into_iter().map(|x| x as f32).collect(),
        D::I32(v) => v.into_iter().map(|x| x as f32).collect(),
        D::U64(v) => v.into_iter().map(|x| x as f32).collect(),
        D::I64(v) => v.into_iter().map(|x| x as f32).collect(),
        D::F32(v) => v,
        D::F64(v) => v.into_iter().map(|x| x as f32).collect(),
        _ => return None,
    })
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
        #[expect(clippy::cast_precision_loss, reason = "GeoKey values are u16")]
        let keys: Option<Vec<f64>> = decoder
            .find_tag(Tag::Unknown(GEO_KEY_DIRECTORY))
            .ok()
            .flatten()
            .and_then(|v| v.into_u64_vec().ok())
            .map(|v| v.into_iter().map(|k| k as f64).collect());
        Self { scale, tiepoint, keys }
    }

    /// The pixel scale in CRS units, when it is a usable one.
    fn crs_pixel(&self) -> Option<(f64, f64)> {
        let s = self.scale.as_ref()?;
        (s.len() >= 2 && s[0].is_finite() && s[1].is_finite() && s[0] > 0.0 && s[1] > 0.0).then(|| (s[0], s[1]))
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
                // GTRasterTypeGeoKey 2 = PixelIsPoint (SRTM, most DEMs): the tiepoint is a
                // sample's centre, so the raster's corner is half a sample further out (as
                // GDAL reads it).
                let half = if key(1025.0) == Some(2.0) { 0.5 } else { 0.0 };
                let (west, north) = (t[3] - (t[0] + half) * s[0], t[4] + (t[1] + half) * s[1]);
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
