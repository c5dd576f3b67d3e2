//! Elevation files: a GeoTIFF of numbers, or a PNG whose pixels encode heights.

use std::path::{Path, PathBuf};

use terrastream_format::{ElevationEncoding, ElevationScheme, Georeference};

use super::geotiff::{GeoTags, gdal_nodata, gdal_statistics};
use super::memory::Raster;
use super::png::{png_header, png_rows};
use super::tiff::{TiffChunks, open_input_tiff, samples_f32, tiff_rows, tiff_rows_in, tiff_rows_mapped};
use super::worldfile::read_sidecar;
use super::{ElevationSource, Sniffed, range_of_rows, sniff};
use crate::error::{Error, Result};

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
    pub(crate) nodata: Option<f64>,
    /// How PNG pixels (or 8-bit TIFF samples) map to heights; None: samples are heights.
    encoding: Option<ElevationEncoding>,
    png: bool,
    /// The exact range of the samples GDAL recorded in the file, if it did.
    statistics: Option<(f64, f64)>,
    /// The GeoTIFF's `VerticalCSTypeGeoKey`, if it has one.
    vertical: Option<u32>,
    /// The vertical datum, as the tiler decided it ([`ElevationFile::with_datum`]).
    datum: Option<crate::DatumName>,
}

/// Reads a single-band GeoTIFF whole (small rasters, tests); [`open_elevation`] streams.
///
/// # Errors
/// An error naming the file for anything unreadable or unsupported.
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
/// An error naming the file: unreadable, not an elevation raster, a PNG whose
/// pixels need an encoding that was not given or does not fit them.
pub fn open_elevation(path: &Path, encoding: Option<ElevationEncoding>) -> Result<ElevationFile> {
    match sniff(path)? {
        Sniffed::Jpeg => Err(Error::unsupported(path, "JPEG is lossy: elevation must come from a GeoTIFF or a PNG")),
        Sniffed::Png => open_png(path, encoding),
        Sniffed::Tiff => open_tiff(path, encoding),
    }
}

/// A PNG of heights: its pixels need an encoding (16-bit gray is read as heights).
fn open_png(path: &Path, encoding: Option<ElevationEncoding>) -> Result<ElevationFile> {
    let bad = |why: String| Error::unsupported(path, why);
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
    // A world file beside it says where it lies (and the spacing).
    let sidecar = read_sidecar(path, (width, height))?;
    Ok(ElevationFile {
        path: path.to_path_buf(),
        width,
        height,
        spacing: sidecar.as_ref().map_or((1.0, 1.0), |s| s.spacing),
        crs_pixel: sidecar.as_ref().map(|s| s.crs_pixel),
        georeference: sidecar.map(|s| s.georeference),
        nodata: encoding.nodata,
        encoding: Some(encoding),
        png: true,
        statistics: None,
        vertical: None,
        datum: None,
    })
}

/// A single-band GeoTIFF of heights, placed by its GeoTIFF tags or a world file beside it.
fn open_tiff(path: &Path, encoding: Option<ElevationEncoding>) -> Result<ElevationFile> {
    let bad = |why: String| Error::unsupported(path, why);
    let mut decoder = open_input_tiff(path)?;
    let (width, height) = decoder.dimensions().map_err(|e| Error::tiff(path, "", e))?;
    if width == 0 || height == 0 {
        return Err(Error::damaged(path, format!("the raster is empty ({width}x{height})")));
    }
    let colour = decoder.colortype().map_err(|e| Error::tiff(path, "", e))?;
    let eight = matches!(colour, tiff::ColorType::Gray(8));
    match colour {
        tiff::ColorType::Gray(_) => {}
        other => {
            return Err(bad(format!("{other:?} samples: an elevation GeoTIFF has a single band of numbers")));
        }
    }
    if let Some(e) = encoding
        && (e.scheme.needs_rgb() || (e.scheme == ElevationScheme::Gray8 && !eight))
    {
        return Err(bad(format!("{:?} does not apply to a single-band {colour:?} GeoTIFF", e.scheme)));
    }
    let nodata = gdal_nodata(&mut decoder);
    let statistics = gdal_statistics(&mut decoder);
    let tags = GeoTags::read(&mut decoder);
    let (mut spacing, mut georeference) = tags.placement(path, width, height)?;
    let mut crs_pixel = georeference.as_ref().and_then(|_| tags.crs_pixel());
    // No GeoTIFF tags: a world file beside it may say where it lies.
    if georeference.is_none()
        && let Some(sidecar) = read_sidecar(path, (width, height))?
    {
        (spacing, georeference, crs_pixel) = (sidecar.spacing, Some(sidecar.georeference), Some(sidecar.crs_pixel));
    }
    Ok(ElevationFile {
        path: path.to_path_buf(),
        width,
        height,
        spacing,
        crs_pixel,
        georeference,
        nodata,
        // Statistics are of the samples: heights only where samples are heights.
        statistics: statistics.filter(|_| encoding.is_none()),
        vertical: tags.vertical_code(),
        datum: None,
        encoding,
        png: false,
    })
}

impl ElevationFile {
    /// The exact range of the samples GDAL recorded in the file (its statistics), if it did.
    pub fn statistics(&self) -> Option<(f64, f64)> {
        self.statistics
    }

    /// The EPSG code of the heights' vertical CRS the file names (GeoTIFF
    /// `VerticalCSTypeGeoKey`), if it does.
    pub fn vertical_code(&self) -> Option<u32> {
        self.vertical
    }

    /// Records what the heights are measured from.
    #[must_use]
    pub fn with_datum(mut self, datum: Option<crate::DatumName>) -> Self {
        self.datum = datum;
        self
    }

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
    fn statistics_range(&self) -> std::result::Result<(f32, f32), PathBuf> {
        self.statistics.map(crate::nearest_f32).ok_or_else(|| self.path.clone())
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
    fn vertical_datum(&self) -> Option<&crate::DatumName> {
        self.datum.as_ref()
    }
    fn rows(&self, row: &mut dyn FnMut(&[f32]) -> Result<()>) -> Result<()> {
        if self.png {
            return self.png_heights(row);
        }
        tiff_rows(&self.path, 1, &|samples: &mut [f32]| self.heights(samples), row)
    }

    fn rows_in(&self, rows: std::ops::Range<u32>, row: &mut dyn FnMut(&[f32]) -> Result<()>) -> Result<()> {
        if self.png {
            return super::rows_window(rows, |r| self.png_heights(r), row);
        }
        let wanted = rows.start as usize..rows.end as usize;
        tiff_rows_in(&self.path, 1, wanted, &|samples: &mut [f32]| self.heights(samples), row)
    }

    fn rows_mapped(
        &self,
        rows: std::ops::Range<u32>,
        map: Option<&crate::RowMap<'_>>,
        row: &mut crate::MappedRow<'_>,
    ) -> Result<()> {
        if self.png {
            return self.rows_in(rows, &mut |r| row(map.map_or_else(|| r.to_vec(), |m| m(r)), crate::min_max(r)));
        }
        let wanted = rows.start as usize..rows.end as usize;
        tiff_rows_mapped(&self.path, wanted, &|samples: &mut [f32]| self.heights(samples), map, row)
    }

    fn height_range(&self, progress: &mut dyn FnMut(u32) -> Result<()>) -> Result<(f32, f32)> {
        if self.png {
            return range_of_rows(progress, |row| self.png_heights(row));
        }
        // Every strip or tile, in parallel and in any order, reduced to its range where
        // it is decoded; no rows are made.
        let chunks = TiffChunks::open(&self.path, 1)?;
        range_by_batches(&chunks, progress, |i| self.range_of_chunk(&chunks, i))
    }

    fn height_range_estimate(&self) -> Result<Option<(f32, f32)>> {
        if self.png {
            return Ok(None);
        }
        // Every eighth strip or tile in file order: a lattice over the raster.
        let chunks = TiffChunks::open(&self.path, 1)?;
        let (lo, hi) = self.chunks_range(&chunks, 0..chunks.needed(), ESTIMATE_STRIDE)?;
        Ok((lo <= hi).then_some((lo, hi)))
    }
}

/// The union of the height ranges `range` gives chunks `chunks`, found in parallel
/// (infinities reversed for none).
pub(super) fn union_of_chunks(
    chunks: impl Iterator<Item = usize>,
    range: impl Fn(usize) -> Result<(f32, f32)> + Sync,
) -> Result<(f32, f32)> {
    use rayon::prelude::*;
    let ranges: Vec<Result<(f32, f32)>> = chunks.collect::<Vec<_>>().into_par_iter().map(&range).collect();
    let (mut lo, mut hi) = (f32::INFINITY, f32::NEG_INFINITY);
    for range in ranges {
        let (l, h) = range?;
        (lo, hi) = (lo.min(l), hi.max(h));
    }
    Ok((lo, hi))
}

/// Chunks a thread reduces to their ranges between two words to `progress` (a decoded
/// chunk is dropped once reduced, so the batch holds no more memory for being larger:
/// only fewer waits for the batch's slowest chunk).
const RANGE_CHUNKS_A_THREAD: usize = 16;

/// The union of the ranges `range` gives every chunk of `chunks`, a batch at a time (in
/// parallel within it), `progress` told the raster's rows read after each batch.
pub(super) fn range_by_batches(
    chunks: &TiffChunks<'_>,
    progress: &mut dyn FnMut(u32) -> Result<()>,
    range: impl Fn(usize) -> Result<(f32, f32)> + Sync,
) -> Result<(f32, f32)> {
    let (mut lo, mut hi) = (f32::INFINITY, f32::NEG_INFINITY);
    let least = RANGE_CHUNKS_A_THREAD * rayon::current_num_threads();
    let (batch, needed) = (chunks.batch().max(least), chunks.needed());
    for first in (0..needed).step_by(batch) {
        let end = needed.min(first + batch);
        let (l, h) = union_of_chunks(first..end, &range)?;
        (lo, hi) = (lo.min(l), hi.max(h));
        progress(chunks.rows_before(end))?;
    }
    Ok((lo, hi))
}

/// An estimated height range reads every this many strips or tiles.
const ESTIMATE_STRIDE: usize = 8;

impl ElevationFile {
    /// A GeoTIFF of heights in a geographic CRS (degrees): what `tile` reprojects onto a
    /// local transverse Mercator by default, through a mosaic.
    pub fn is_geographic_tiff(&self) -> bool {
        let crs = self.georeference.as_ref().and_then(|g| g.crs.as_deref());
        self.is_plain_tiff() && crs.and_then(|c| crate::crs::Crs::parse(c).ok()).is_some_and(|c| c.is_geographic())
    }

    /// A GeoTIFF of heights as stored (no PNG, no encoding): what a mosaic reads by chunks.
    pub(super) fn is_plain_tiff(&self) -> bool {
        !self.png && self.encoding.is_none()
    }

    /// Stored samples -> heights in place (NaN for nodata and non-finite values).
    pub(super) fn heights(&self, samples: &mut [f32]) {
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

    /// The height range of every `step`th chunk of `range`, read in parallel.
    fn chunks_range(&self, chunks: &TiffChunks<'_>, range: std::ops::Range<usize>, step: usize) -> Result<(f32, f32)> {
        union_of_chunks(range.step_by(step), |i| self.range_of_chunk(chunks, i))
    }

    /// The height range of chunk `i`, read and decoded.
    fn range_of_chunk(&self, chunks: &TiffChunks<'_>, i: usize) -> Result<(f32, f32)> {
        let (data, w, h) = chunks.read(i)?;
        self.chunk_range(data, w * h).ok_or_else(|| Error::unsupported(&self.path, "unsupported sample type"))
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
        Some(crate::min_max(&samples))
    }
}

/// Integer samples of at most 16 bits, and the arithmetic their range needs.
pub(crate) trait Small: Copy + Ord + Into<f32> + TryFrom<i32> {
    const LOWEST: Self;
    const HIGHEST: Self;
}

macro_rules! small {
    ($($t:ty),*) => {$(impl Small for $t { const LOWEST: Self = <$t>::MIN; const HIGHEST: Self = <$t>::MAX; })*};
}
small!(u8, i8, u16, i16);

/// The range of integer samples as heights (those equal to `nodata` skipped; infinities
/// when none is left). A nodata that no sample of the type can equal skips nothing.
pub(crate) fn integer_range<T: Small>(values: &[T], nodata: Option<f32>) -> (f32, f32) {
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

#[cfg(test)]
mod tests {
    #![allow(clippy::unwrap_used, clippy::cast_possible_truncation)]

    use super::*;

    #[test]
    fn integer_samples_give_their_range_without_nodata() {
        let none = (f32::INFINITY, f32::NEG_INFINITY);
        // Nodata at either end, in every lane of a vector and the remainder.
        for at in 0..37 {
            let mut v: Vec<i16> = (0..37).map(|i| (i * 7 % 23) as i16 - 5).collect();
            v[at] = -32767;
            v[(at + 11) % 37] = -32767;
            let real: Vec<f32> = v.iter().filter(|&&x| x != -32767).map(|&x| f32::from(x)).collect();
            let want = (
                real.iter().copied().fold(f32::INFINITY, f32::min),
                real.iter().copied().fold(f32::NEG_INFINITY, f32::max),
            );
            assert_eq!(integer_range(&v, Some(-32767.0)), want, "nodata at {at}");
            assert_eq!(integer_range(&v, None), (-32767.0, want.1), "no nodata: it is a height");
        }
        assert_eq!(integer_range::<i16>(&[], None), none);
        assert_eq!(integer_range(&[-32767i16; 19], Some(-32767.0)), none, "all nodata: no range");
        // A nodata no sample of the type can hold skips nothing.
        assert_eq!(integer_range(&[0u8, 255, 7], Some(-1.0)), (0.0, 255.0));
        assert_eq!(integer_range(&[0u8, 255, 7], Some(255.5)), (0.0, 255.0));
        assert_eq!(integer_range(&[3u16, 65_535, 7], Some(1e30)), (3.0, 65_535.0));
        assert_eq!(integer_range(&[3u16, 65_535, 7], Some(65_535.0)), (3.0, 7.0));
        assert_eq!(integer_range(&[-128i8, 127, 0], Some(-128.0)), (0.0, 127.0));
    }
}
