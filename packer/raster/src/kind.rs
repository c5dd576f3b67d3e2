//! What a mosaic is made of: heights (elevation) or RGBA pixels (imagery). The mosaic
//! reads, caches and samples either the same way; a kind says how its files open, how a
//! decoded strip or tile becomes values, and how four neighbours blend.

use std::path::Path;

use terrastream_format::Georeference;

use super::elevation::{ElevationFile, open_elevation};
use super::image::{ImageFile, open_image};
use super::tiff::samples_f32;
use super::{ElevationSource, ImageSource};
use crate::error::{Error, Result};

/// The samples of a mosaic and the files they come from.
pub trait MosaicKind: Send + Sync + 'static {
    /// One sample.
    type Value: Copy + Send + Sync + 'static;
    /// An input file, opened.
    type File: Send + Sync + std::fmt::Debug;
    /// No data.
    const NONE: Self::Value;
    /// Whether `v` is no data.
    fn is_none(v: &Self::Value) -> bool;
    /// Raises a height by `by` (another vertical datum's); other kinds stay as they are.
    fn lift(_v: &mut Self::Value, _by: f32) {}
    /// Opens an input: a GeoTIFF this kind reads by strips or tiles, or (imagery) a PNG or
    /// JPEG read by rows.
    ///
    /// # Errors
    /// An error naming a file of another kind.
    fn open(path: &Path) -> Result<Self::File>;
    /// The file's path.
    fn path(file: &Self::File) -> &Path;
    /// Pixels across and down.
    fn size(file: &Self::File) -> (u32, u32);
    /// Where the file lies, when it says.
    fn georeference(file: &Self::File) -> Option<&Georeference>;
    /// A pixel's size in CRS units, when the file says.
    fn crs_pixel(file: &Self::File) -> Option<(f64, f64)>;
    /// Samples per pixel.
    fn channels(file: &Self::File) -> usize;
    /// The file's own nodata value, if it names one.
    fn nodata(_file: &Self::File) -> Option<f64> {
        None
    }
    /// Whether the VRT at `vrt`, of `bands` bands, can read `file` band for band.
    ///
    /// # Errors
    /// [`Error::Mismatch`] naming the VRT and the file, if it cannot.
    fn check_bands(file: &Self::File, bands: usize, vrt: &Path) -> Result<()> {
        let channels = Self::channels(file);
        if bands == channels {
            return Ok(());
        }
        let reason = format!("a {bands}-band VRT over a file of {channels} band(s) ({})", Self::path(file).display());
        Err(Error::mismatch(vrt, reason))
    }
    /// Is the file read by rows from its top (a PNG or JPEG), not by strips or tiles?
    fn read_by_rows(_file: &Self::File) -> bool {
        false
    }
    /// A file read by rows ([`Self::read_by_rows`]): each row's samples, [`Self::channels`]
    /// bytes per pixel, from the top.
    ///
    /// # Errors
    /// An error naming the file for unreadable data, or for a file that
    /// [`Self::read_by_rows`] does not say is read by rows; the error `row` returns.
    fn file_rows(file: &Self::File, _row: &mut dyn FnMut(&[u8]) -> Result<()>) -> Result<()> {
        Err(Error::unsupported(Self::path(file), "read by strips or tiles, not by rows"))
    }
    /// A decoded strip or tile as values; samples equal to `nodata` are no data.
    ///
    /// # Errors
    /// An error naming the file for a sample type this kind does not read.
    /// `nodata`: raw samples equal to it are no data; `scale`: (ratio, offset) applied to
    /// the others (a VRT source's).
    fn values(
        file: &Self::File,
        data: tiff::decoder::DecodingResult,
        nodata: Option<f32>,
        scale: Option<(f32, f32)>,
    ) -> Result<Vec<Self::Value>>;
    /// The blend of up to four neighbours with bilinear weights, over those with data.
    fn blend(corners: &[(Self::Value, f64); 4]) -> Self::Value;
    /// [`Self::blend`] for bilinear weights, which sum to 1 up to rounding: cheaper where
    /// a kind can tell (heights: no division when all four corners have data; the value
    /// may differ from [`Self::blend`]'s in the last bit).
    fn blend_unit(corners: &[(Self::Value, f64); 4]) -> Self::Value {
        Self::blend(corners)
    }
    /// [`Self::blend`] of `top[k]`, `top[k + 1]`, `bottom[k]`, `bottom[k + 1]` with weights
    /// `w` into each `out[k]` that has no data yet (`top` and `bottom` hold one more value
    /// than `out`): a run of samples with the same weights.
    fn blend_run(top: &[Self::Value], bottom: &[Self::Value], w: [f64; 4], out: &mut [Self::Value]) {
        for (k, o) in out.iter_mut().enumerate() {
            if Self::is_none(o) {
                *o = Self::blend(&[(top[k], w[0]), (top[k + 1], w[1]), (bottom[k], w[2]), (bottom[k + 1], w[3])]);
            }
        }
    }
}

/// Heights: f32, NaN for no data.
#[derive(Debug)]
pub struct Heights;

/// RGBA8 pixels, alpha 0 for no data.
#[derive(Debug)]
pub struct Pixels;

impl MosaicKind for Heights {
    type Value = f32;
    type File = ElevationFile;
    const NONE: f32 = f32::NAN;
    fn lift(v: &mut f32, by: f32) {
        *v += by;
    }
    fn is_none(v: &f32) -> bool {
        v.is_nan()
    }
    fn open(path: &Path) -> Result<ElevationFile> {
        let file = open_elevation(path, None)?;
        if !file.is_plain_tiff() {
            return Err(Error::unsupported(path, "a mosaic reads GeoTIFFs of heights (not PNG)"));
        }
        Ok(file)
    }
    fn path(file: &ElevationFile) -> &Path {
        file.path()
    }
    fn size(file: &ElevationFile) -> (u32, u32) {
        file.size()
    }
    fn georeference(file: &ElevationFile) -> Option<&Georeference> {
        file.georeference()
    }
    fn crs_pixel(file: &ElevationFile) -> Option<(f64, f64)> {
        file.crs_pixel_size()
    }
    fn channels(_: &ElevationFile) -> usize {
        1
    }
    fn nodata(file: &ElevationFile) -> Option<f64> {
        file.nodata
    }
    fn values(
        file: &ElevationFile,
        data: tiff::decoder::DecodingResult,
        nodata: Option<f32>,
        scale: Option<(f32, f32)>,
    ) -> Result<Vec<f32>> {
        let mut heights =
            samples_f32(data).ok_or_else(|| Error::unsupported(file.path(), "unsupported sample type"))?;
        file.heights(&mut heights);
        if let Some(nodata) = nodata {
            for v in heights.iter_mut().filter(|v| **v == nodata) {
                *v = f32::NAN;
            }
        }
        if let Some((ratio, offset)) = scale {
            // NaN (nodata) stays NaN.
            for v in &mut heights {
                *v = *v * ratio + offset;
            }
        }
        Ok(heights)
    }
    #[inline]
    fn blend(corners: &[(f32, f64); 4]) -> f32 {
        // Branch-free (corners with and without data mix unpredictably at a coast).
        let (mut sum, mut weight) = (0.0, 0.0);
        for &(v, w) in corners {
            let w = if v.is_nan() { 0.0 } else { w };
            sum += w * f64::from(if v.is_nan() { 0.0 } else { v });
            weight += w;
        }
        #[expect(clippy::cast_possible_truncation, reason = "heights are kept as f32")]
        if weight > 1e-9 { (sum / weight) as f32 } else { f32::NAN }
    }
    fn blend_run(top: &[f32], bottom: &[f32], w: [f64; 4], out: &mut [f32]) {
        // First `blend_unit`'s weighted sum where all four corners have data, with no
        // branch (the compiler vectorizes it); then `blend` for the samples left with
        // none, where a corner has none (the edges of an input's data).
        let n = out.len();
        let (a, b, c, d) = (&top[..n], &top[1..=n], &bottom[..n], &bottom[1..=n]);
        for k in 0..n {
            #[expect(clippy::cast_possible_truncation, reason = "heights are kept as f32")]
            let sum = weighted_sum([a[k], b[k], c[k], d[k]], w) as f32;
            out[k] = if out[k].is_nan() { sum } else { out[k] };
        }
        for k in 0..n {
            if out[k].is_nan() {
                out[k] = Self::blend(&[(a[k], w[0]), (b[k], w[1]), (c[k], w[2]), (d[k], w[3])]);
            }
        }
    }
    #[inline]
    fn blend_unit(corners: &[(f32, f64); 4]) -> f32 {
        // With every corner's data the weights sum to 1: the division would change the
        // last bit at most. A NaN corner makes the sum NaN: blend then.
        let [(a, wa), (b, wb), (c, wc), (d, wd)] = *corners;
        let sum = weighted_sum([a, b, c, d], [wa, wb, wc, wd]);
        #[expect(clippy::cast_possible_truncation, reason = "heights are kept as f32")]
        if sum.is_nan() { Self::blend(corners) } else { sum as f32 }
    }
}

/// The bilinear sum of four heights: NaN if one is. What [`Heights::blend_unit`] and
/// [`Heights::blend_run`] keep where all four corners have data, the same bits in both.
#[inline]
fn weighted_sum(v: [f32; 4], w: [f64; 4]) -> f64 {
    w[0] * f64::from(v[0]) + w[1] * f64::from(v[1]) + w[2] * f64::from(v[2]) + w[3] * f64::from(v[3])
}

impl MosaicKind for Pixels {
    type Value = [u8; 4];
    type File = ImageFile;
    const NONE: [u8; 4] = [0; 4];
    fn is_none(v: &[u8; 4]) -> bool {
        v[3] == 0
    }
    fn open(path: &Path) -> Result<ImageFile> {
        open_image(path)
    }
    fn path(file: &ImageFile) -> &Path {
        file.path()
    }
    fn size(file: &ImageFile) -> (u32, u32) {
        file.size()
    }
    fn georeference(file: &ImageFile) -> Option<&Georeference> {
        file.georeference()
    }
    fn crs_pixel(file: &ImageFile) -> Option<(f64, f64)> {
        file.crs_pixel_size()
    }
    fn channels(file: &ImageFile) -> usize {
        // PNG and JPEG are read by rows, as RGBA.
        file.tiff_channels().unwrap_or(4)
    }
    fn check_bands(file: &ImageFile, bands: usize, vrt: &Path) -> Result<()> {
        match file.tiff_channels() {
            Some(channels) if channels != bands => Err(Error::mismatch(
                vrt,
                format!(
                    "a {bands}-band VRT over an image of {channels} band(s): each band must be the image's own ({})",
                    file.path().display()
                ),
            )),
            // A PNG or JPEG is read as RGBA whatever it holds.
            _ => Ok(()),
        }
    }
    fn read_by_rows(file: &ImageFile) -> bool {
        file.tiff_channels().is_none()
    }
    fn file_rows(file: &ImageFile, row: &mut dyn FnMut(&[u8]) -> Result<()>) -> Result<()> {
        file.streamed_rows(&mut |r| row(r.as_flattened()))
    }
    fn values(
        file: &ImageFile,
        data: tiff::decoder::DecodingResult,
        nodata: Option<f32>,
        scale: Option<(f32, f32)>,
    ) -> Result<Vec<[u8; 4]>> {
        let tiff::decoder::DecodingResult::U8(bytes) = data else {
            return Err(Error::unsupported(file.path(), "only 8-bit images are read"));
        };
        // Colour bands scaled as GDAL does (rounded, clamped to 0..=255); alpha is not.
        #[expect(clippy::cast_possible_truncation, clippy::cast_sign_loss, reason = "clamped to 0..=255")]
        let scaled = |c: u8| match scale {
            Some((ratio, offset)) => (f32::from(c) * ratio + offset).round().clamp(0.0, 255.0) as u8,
            None => c,
        };
        #[expect(clippy::cast_possible_truncation, clippy::cast_sign_loss, reason = "an 8-bit nodata value")]
        let nodata = nodata.filter(|n| (0.0..=255.0).contains(n)).map(|n| n as u8);
        let channels = Self::channels(file);
        let ycbcr = file.ycbcr();
        Ok(bytes
            .chunks_exact(channels)
            .map(|p| {
                let rgb;
                let p = if ycbcr && channels == 3 {
                    rgb = super::image::ycbcr_to_rgb([p[0], p[1], p[2]]);
                    &rgb[..]
                } else {
                    p
                };
                let px = match channels {
                    4 => [scaled(p[0]), scaled(p[1]), scaled(p[2]), p[3]],
                    3 => [scaled(p[0]), scaled(p[1]), scaled(p[2]), 255],
                    2 => [scaled(p[0]), scaled(p[0]), scaled(p[0]), p[1]],
                    _ => [scaled(p[0]), scaled(p[0]), scaled(p[0]), 255],
                };
                // A NODATA value of a VRT source: every band at it is no data.
                if nodata.is_some_and(|n| p.iter().take(channels.min(3)).all(|&c| c == n)) { [0; 4] } else { px }
            })
            .collect())
    }
    fn blend(corners: &[([u8; 4], f64); 4]) -> [u8; 4] {
        // Weighted by alpha: colours of transparent pixels do not bleed in.
        let mut acc = [0f64; 4];
        for &(p, w) in corners {
            let a = w * f64::from(p[3]);
            for c in 0..3 {
                acc[c] += a * f64::from(p[c]);
            }
            acc[3] += a;
        }
        if acc[3] <= 0.0 {
            return [0; 4];
        }
        #[expect(clippy::cast_possible_truncation, clippy::cast_sign_loss, reason = "rounded into 0..=255")]
        let c = |v: f64| v.round().clamp(0.0, 255.0) as u8;
        [c(acc[0] / acc[3]), c(acc[1] / acc[3]), c(acc[2] / acc[3]), c(acc[3])]
    }
}
