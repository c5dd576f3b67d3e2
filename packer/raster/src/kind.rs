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
    /// [`Self::blend_unit`] at the points `start + (first + k) * step` into each `out[k]`
    /// that has no data yet: a straight line of samples (a warp's, between two exact
    /// points of its lattice), every one of them between rows `y0` and `y0 + 1`, whose
    /// corners `top` and `bottom` hold from column `base` on.
    fn blend_line(
        top: &[Self::Value],
        bottom: &[Self::Value],
        (base, y0): (i64, i64),
        (start, step, first): ((f64, f64), (f64, f64), usize),
        out: &mut [Self::Value],
    ) {
        for (k, o) in out.iter_mut().enumerate() {
            if Self::is_none(o) {
                let p = line_point(start, step, first + k);
                let x0 = floor(p.0);
                #[expect(
                    clippy::cast_sign_loss,
                    clippy::cast_possible_truncation,
                    reason = "on the line: at or after base"
                )]
                let i = (x0 - base) as usize;
                let w = weights(p, x0, y0);
                *o = Self::blend_unit(&[(top[i], w[0]), (top[i + 1], w[1]), (bottom[i], w[2]), (bottom[i + 1], w[3])]);
            }
        }
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
    fn blend_line(
        top: &[f32],
        bottom: &[f32],
        (base, y0): (i64, i64),
        (start, step, first): ((f64, f64), (f64, f64), usize),
        out: &mut [f32],
    ) {
        // As `blend_run`: first the weighted sums, with no branch; then `blend` where a
        // corner has no data. The same bits as `blend_unit` point by point.
        let corners = |k: usize| line_corners(top, bottom, (base, y0), line_point(start, step, first + k));
        // Four points at a time where the processor can (the same operations in the same
        // order: the same bits), then the rest one at a time.
        let done = wide::blend_line(top, bottom, (base, y0), (start, step, first), out);
        for (k, o) in out.iter_mut().enumerate().skip(done) {
            let (v, w) = corners(k);
            #[expect(clippy::cast_possible_truncation, reason = "heights are kept as f32")]
            let sum = weighted_sum(v, w) as f32;
            *o = if o.is_nan() { sum } else { *o };
        }
        for (k, o) in out.iter_mut().enumerate() {
            if o.is_nan() {
                let (v, w) = corners(k);
                *o = Self::blend(&[(v[0], w[0]), (v[1], w[1]), (v[2], w[2]), (v[3], w[3])]);
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

/// Point `k` of a line of sample points.
#[inline]
pub(crate) fn line_point(start: (f64, f64), step: (f64, f64), k: usize) -> (f64, f64) {
    #[expect(clippy::cast_precision_loss, reason = "lines are far shorter than 2^52")]
    let k = k as f64;
    (start.0 + step.0 * k, start.1 + step.1 * k)
}

/// [`MosaicKind::blend_line`] for heights, four points at a time with AVX2 where the
/// processor has it: no gathers, no loads through pointers (the corners are read from the
/// slices, checked, and packed into vectors), so the only unsafe step is the call into a
/// function compiled for AVX2, made after the processor says it has AVX2.
mod wide {
    /// The first samples of `out` made (a multiple of four, or 0 without AVX2); the same
    /// values, bit for bit, as the one-point loop makes.
    pub(super) fn blend_line(
        top: &[f32],
        bottom: &[f32],
        at: (i64, i64),
        line: ((f64, f64), (f64, f64), usize),
        out: &mut [f32],
    ) -> usize {
        #[cfg(target_arch = "x86_64")]
        if out.len() >= 4 && std::arch::is_x86_feature_detected!("avx2") {
            // SAFETY: the function's only requirement is AVX2, detected just above; it
            // reads and writes only through checked slice indexing.
            #[expect(unsafe_code, reason = "a call into AVX2 code, after detecting AVX2")]
            return unsafe { avx2(top, bottom, at, line, out) };
        }
        let _ = (top, bottom, at, line, out);
        0
    }

    #[cfg(target_arch = "x86_64")]
    #[target_feature(enable = "avx2")]
    #[expect(
        clippy::cast_precision_loss,
        clippy::cast_possible_truncation,
        clippy::cast_sign_loss,
        reason = "as the one-point loop"
    )]
    fn avx2(
        top: &[f32],
        bottom: &[f32],
        (base, y0): (i64, i64),
        (start, step, first): ((f64, f64), (f64, f64), usize),
        out: &mut [f32],
    ) -> usize {
        use std::arch::x86_64::{
            _mm_add_epi32, _mm_cvtsi128_si32, _mm_extract_epi32, _mm_set1_epi32, _mm_sub_epi32, _mm256_add_pd,
            _mm256_castps256_ps128, _mm256_cvtpd_ps, _mm256_cvtps_pd, _mm256_cvttpd_epi32, _mm256_extractf128_ps,
            _mm256_floor_pd, _mm256_mul_pd, _mm256_set_m128i, _mm256_set_pd, _mm256_set1_pd, _mm256_sub_pd,
        };
        // Columns as 32-bit lanes: those of any raster this reads (else one point at a time).
        let Ok(base32) = i32::try_from(base) else { return 0 };
        if i32::try_from(base + top.len().max(bottom.len()) as i64).is_err() {
            return 0;
        }
        let (sx, sy, dx, dy) =
            (_mm256_set1_pd(start.0), _mm256_set1_pd(start.1), _mm256_set1_pd(step.0), _mm256_set1_pd(step.1));
        let (one, y0f, base32) = (_mm256_set1_pd(1.0), _mm256_set1_pd(y0 as f64), _mm_set1_epi32(base32));
        let n = out.len() / 4 * 4;
        for k in (0..n).step_by(4) {
            let i = (first + k) as f64;
            let kk = _mm256_set_pd(i + 3.0, i + 2.0, i + 1.0, i);
            // start + k * step, as line_point; floor, as `floor` (the points are finite).
            let (px, py) = (_mm256_add_pd(sx, _mm256_mul_pd(dx, kk)), _mm256_add_pd(sy, _mm256_mul_pd(dy, kk)));
            let x0 = _mm256_floor_pd(px);
            let (fx, fy) = (_mm256_sub_pd(px, x0), _mm256_sub_pd(py, y0f));
            let (gx, gy) = (_mm256_sub_pd(one, fx), _mm256_sub_pd(one, fy));
            // The columns from `base` (whole: the truncation is exact), in order along
            // the line: the first and last bound the four.
            let c = _mm_sub_epi32(_mm256_cvttpd_epi32(x0), base32);
            let (first_c, last_c) = (_mm_cvtsi128_si32(c), _mm_extract_epi32::<3>(c));
            let from = first_c.min(last_c) as usize;
            // Each point's left and right corners in a row: where eight samples from the
            // first column hold them all (the points a sample or so apart), one read of
            // eight and a permutation; else read one by one.
            let (t, b) = if first_c.abs_diff(last_c) < 7 && from + 8 <= top.len().min(bottom.len()) {
                let at = _mm_sub_epi32(c, _mm_set1_epi32(from as i32));
                let lanes = _mm256_set_m128i(_mm_add_epi32(at, _mm_set1_epi32(1)), at);
                (eight(&top[from..from + 8], lanes), eight(&bottom[from..from + 8], lanes))
            } else {
                let c = [first_c, _mm_extract_epi32::<1>(c), _mm_extract_epi32::<2>(c), last_c].map(|c| c as usize);
                (pairs(top, c), pairs(bottom, c))
            };
            let left = |v| _mm256_cvtps_pd(_mm256_castps256_ps128(v));
            let right = |v| _mm256_cvtps_pd(_mm256_extractf128_ps::<1>(v));
            // w0 * a + w1 * b + w2 * c + w3 * d, as weighted_sum.
            let sum = _mm256_add_pd(
                _mm256_add_pd(
                    _mm256_add_pd(
                        _mm256_mul_pd(_mm256_mul_pd(gx, gy), left(t)),
                        _mm256_mul_pd(_mm256_mul_pd(fx, gy), right(t)),
                    ),
                    _mm256_mul_pd(_mm256_mul_pd(gx, fy), left(b)),
                ),
                _mm256_mul_pd(_mm256_mul_pd(fx, fy), right(b)),
            );
            for (o, s) in out[k..k + 4].iter_mut().zip(lanes_ps(_mm256_cvtpd_ps(sum))) {
                *o = if o.is_nan() { s } else { *o };
            }
        }
        n
    }

    /// Samples `row[lanes[i]]` of eight (the left corners in the low lanes, the right
    /// ones in the high lanes).
    #[cfg(target_arch = "x86_64")]
    #[target_feature(enable = "avx2")]
    #[inline]
    fn eight(row: &[f32], lanes: std::arch::x86_64::__m256i) -> std::arch::x86_64::__m256 {
        use std::arch::x86_64::{_mm256_permutevar8x32_ps, _mm256_set_ps};
        let r = &row[..8];
        _mm256_permutevar8x32_ps(_mm256_set_ps(r[7], r[6], r[5], r[4], r[3], r[2], r[1], r[0]), lanes)
    }

    /// The left corners `row[c[i]]` in the low lanes, the right ones `row[c[i] + 1]` in
    /// the high lanes.
    #[cfg(target_arch = "x86_64")]
    #[target_feature(enable = "avx2")]
    #[inline]
    fn pairs(row: &[f32], c: [usize; 4]) -> std::arch::x86_64::__m256 {
        std::arch::x86_64::_mm256_set_ps(
            row[c[3] + 1],
            row[c[2] + 1],
            row[c[1] + 1],
            row[c[0] + 1],
            row[c[3]],
            row[c[2]],
            row[c[1]],
            row[c[0]],
        )
    }

    /// The four lanes of `v`, lowest first.
    #[cfg(target_arch = "x86_64")]
    #[target_feature(enable = "avx2")]
    #[expect(clippy::cast_sign_loss, reason = "the lane's bits")]
    fn lanes_ps(v: std::arch::x86_64::__m128) -> [f32; 4] {
        use std::arch::x86_64::{_mm_cvtss_f32, _mm_extract_ps};
        let bits = |b: i32| f32::from_bits(b as u32);
        [_mm_cvtss_f32(v), bits(_mm_extract_ps::<1>(v)), bits(_mm_extract_ps::<2>(v)), bits(_mm_extract_ps::<3>(v))]
    }
}

/// The four corners of point `p` and their weights (see [`MosaicKind::blend_line`]).
#[inline(always)]
fn line_corners(top: &[f32], bottom: &[f32], (base, y0): (i64, i64), p: (f64, f64)) -> ([f32; 4], [f64; 4]) {
    let x0 = floor(p.0);
    #[expect(clippy::cast_sign_loss, clippy::cast_possible_truncation, reason = "on the line: at or after base")]
    let i = (x0 - base) as usize;
    ([top[i], top[i + 1], bottom[i], bottom[i + 1]], weights(p, x0, y0))
}

/// floor() without a libm call (no SSE4.1 round instruction on the baseline target).
#[inline]
#[expect(clippy::cast_possible_truncation, reason = "pixel coordinates are far below 2^63")]
pub(crate) fn floor(v: f64) -> i64 {
    let i = v as i64;
    #[expect(clippy::cast_precision_loss, reason = "pixel coordinates are far below 2^52")]
    if (i as f64) > v { i - 1 } else { i }
}

/// Bilinear weights of the corners `(x0, y0)`, `(x0 + 1, y0)`, `(x0, y0 + 1)` and `(x0 +
/// 1, y0 + 1)` for point `p`.
#[inline]
pub(crate) fn weights(p: (f64, f64), x0: i64, y0: i64) -> [f64; 4] {
    #[expect(clippy::cast_precision_loss, reason = "pixel coordinates are far below 2^52")]
    let (fx, fy) = (p.0 - x0 as f64, p.1 - y0 as f64);
    [(1.0 - fx) * (1.0 - fy), fx * (1.0 - fy), (1.0 - fx) * fy, fx * fy]
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

#[cfg(test)]
mod tests {
    use super::*;

    /// A line of points sampled by `blend_line` (four at a time where AVX2 is there) gives
    /// the bits `blend_unit` gives one point at a time, with corners without data, samples
    /// that already have data, lines running either way and any first point.
    #[test]
    fn blend_line_is_blend_unit_point_by_point() {
        let width = 200;
        let row = |seed: u32| -> Vec<f32> {
            (0..width)
                .map(|i: u32| {
                    let v = i.wrapping_mul(2_654_435_761_u32).wrapping_add(seed).rotate_left(7);
                    #[expect(clippy::cast_precision_loss, reason = "test values")]
                    if v.is_multiple_of(23) { f32::NAN } else { (v % 100_000) as f32 * 0.037 - 400.0 }
                })
                .collect()
        };
        let (top, bottom) = (row(1), row(2));
        let (base, y0) = (40i64, 7i64);
        let lines = [
            ((41.3, 7.2), (0.97, 0.0), 0usize, 37usize),
            ((45.01, 7.9), (1.31, -0.001), 3, 64),
            ((230.6, 7.5), (-0.55, 0.001), 1, 33),
            ((50.0, 7.0), (1.0, 0.0), 5, 21),
            ((60.25, 7.75), (0.125, 0.0), 0, 7),
            ((42.5, 7.3), (3.1, 0.0), 0, 45),
            ((229.9, 7.4), (-0.3, 0.0), 0, 12),
        ];
        let mut with_gaps = 0;
        for (start, step, first, n) in lines {
            let mut out: Vec<f32> = (0..n).map(|k| if k % 5 == 2 { 1234.5 } else { f32::NAN }).collect();
            let mut expected = out.clone();
            for (k, o) in expected.iter_mut().enumerate() {
                if o.is_nan() {
                    let p = line_point(start, step, first + k);
                    let (v, w) = line_corners(&top, &bottom, (base, y0), p);
                    with_gaps += usize::from(v.iter().any(|c| c.is_nan()));
                    *o = Heights::blend_unit(&[(v[0], w[0]), (v[1], w[1]), (v[2], w[2]), (v[3], w[3])]);
                }
            }
            Heights::blend_line(&top, &bottom, (base, y0), (start, step, first), &mut out);
            let bits = |v: &[f32]| v.iter().map(|f| f.to_bits()).collect::<Vec<_>>();
            assert_eq!(bits(&out), bits(&expected), "line from {start:?} by {step:?}");
            assert!(out.iter().filter(|v| !v.is_nan() && **v != 1234.5).count() > n / 2);
        }
        assert!(with_gaps > 5, "corners without data: {with_gaps}");
    }
}
