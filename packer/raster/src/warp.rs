//! An image in another CRS than the elevation, resampled onto the elevation's extent by
//! both georeferences: each texel's centre goes from the elevation's CRS to the image's
//! and is sampled there (bilinear, weighted by alpha). The image is read once, top to
//! bottom, holding only the band of its rows that the current output row needs.

use std::collections::VecDeque;
use std::path::Path;
use std::sync::mpsc;

use terrastream_format::Georeference;

use super::{ElevationSource, ImageSource, MosaicKind, Pixels, crs_placement};
use crate::crs::{Crs, Transform};
use crate::error::{Error, Result};

/// Output texels between exact transforms along a row; linear in between (well under a
/// texel apart for any smooth projection at this spacing).
const LATTICE: usize = 16;

/// Most texels across or down a warped texture.
const MAX_SIDE: f64 = 65_536.0;

/// Where a raster lies in its CRS: the north-west corner and a pixel's size.
#[derive(Clone, Copy, Debug)]
struct Placement {
    origin: [f64; 2],
    pixel: (f64, f64),
}

/// An image placed onto an elevation's extent by their georeferences.
#[derive(Debug)]
pub struct Warped<'a> {
    image: &'a dyn ImageSource,
    size: (u32, u32),
    /// The elevation's extent in its CRS: west, north, width, height.
    extent: [f64; 4],
    image_at: Placement,
    transform: Transform,
    georeference: Option<Georeference>,
}

impl<'a> Warped<'a> {
    /// `image` resampled onto `elevation`'s extent when both say where they lie in two
    /// different CRSs; `None` when either lacks a georeference or both share a CRS (then
    /// [`super::ImageWindow`] cuts the image, no resampling needed). The texels are about
    /// the image's pixels in size, square in metres.
    ///
    /// # Errors
    /// [`Error::UnknownCrs`] naming a CRS the tiler does not know; [`Error::Mismatch`]
    /// naming the image when it does not cover the elevation.
    pub fn over(elevation: &dyn ElevationSource, image: &'a dyn ImageSource) -> Result<Option<Self>> {
        let (Some((dem_crs, dem_origin, dem_px)), Some((img_crs, img_origin, img_px))) = (
            crs_placement(elevation.georeference(), elevation.crs_pixel_size()),
            crs_placement(image.georeference(), image.crs_pixel_size()),
        ) else {
            return Ok(None);
        };
        if dem_crs == img_crs {
            return Ok(None);
        }
        let named = |crs: &str, path: &Path| {
            Crs::parse(crs).map_err(|e| Error::georeference(path, format!("its georeference cannot be used: {e}")))
        };
        let (from, to) = (named(dem_crs, elevation.path())?, named(img_crs, image.path())?);
        let (dw, dh) = elevation.size();
        let extent = [dem_origin[0], dem_origin[1], f64::from(dw) * dem_px.0, f64::from(dh) * dem_px.1];
        let image_at = Placement { origin: img_origin, pixel: img_px };
        let transform = Transform::new(&from, &to);
        // Texels of about the image's pixel size, square in metres, over the elevation.
        let (ex, ez) = (f64::from(dw) * elevation.spacing().0, f64::from(dh) * elevation.spacing().1);
        let texel = pixel_metres(&to, image_at, image.size().1).ok_or_else(|| {
            Error::georeference(image.path(), format!("its pixels cannot be measured in {}", to.name()))
        })?;
        #[expect(clippy::cast_possible_truncation, clippy::cast_sign_loss, reason = "clamped to 1..=MAX_SIDE")]
        let side = |metres: f64| (metres / texel).round().clamp(1.0, MAX_SIDE) as u32;
        let warped = Self {
            image,
            size: (side(ex), side(ez)),
            extent,
            image_at,
            transform,
            georeference: elevation.georeference().cloned(),
        };
        warped.check_cover()?;
        Ok(Some(warped))
    }

    /// Image pixel coordinates (x, y; centres at +0.5) of texel centre `(i, j)`.
    fn source_of(&self, i: f64, j: f64) -> Option<(f64, f64)> {
        let [west, north, width, height] = self.extent;
        let x = west + (i + 0.5) / f64::from(self.size.0) * width;
        let y = north - (j + 0.5) / f64::from(self.size.1) * height;
        let (sx, sy) = self.transform.apply(x, y)?;
        let p = self.image_at;
        Some(((sx - p.origin[0]) / p.pixel.0 - 0.5, (p.origin[1] - sy) / p.pixel.1 - 0.5))
    }

    /// The image pixel coordinates of every texel centre of row `j` (exact every
    /// [`LATTICE`] texels, linear between); NaN where a point has no image.
    fn row_sources(&self, j: u32) -> Vec<(f64, f64)> {
        let w = self.size.0 as usize;
        let exact = |i: usize| {
            #[expect(clippy::cast_precision_loss, reason = "texel indices are far below 2^52")]
            self.source_of(i as f64, f64::from(j)).unwrap_or((f64::NAN, f64::NAN))
        };
        let mut out = Vec::with_capacity(w);
        let mut a = exact(0);
        let mut start = 0;
        while start < w {
            let end = (start + LATTICE).min(w - 1);
            let b = if end == start { a } else { exact(end) };
            let n = end - start;
            for k in 0..n.max(1) {
                #[expect(clippy::cast_precision_loss, reason = "k and n are at most LATTICE")]
                let t = if n == 0 { 0.0 } else { k as f64 / n as f64 };
                out.push((a.0 + (b.0 - a.0) * t, a.1 + (b.1 - a.1) * t));
            }
            if end == w - 1 {
                out.push(b);
                break;
            }
            a = b;
            start = end;
        }
        out.truncate(w);
        out
    }

    /// The image must reach the elevation: some of a 9 x 9 lattice of its texels lie
    /// inside the image. Where it does not reach, the texture is transparent: an
    /// elevation reprojected from degrees has corners with no data, which an image of
    /// the same area leaves out, as it should.
    fn check_cover(&self) -> Result<()> {
        let (w, h) = (f64::from(self.size.0), f64::from(self.size.1));
        let (iw, ih) = self.image.size();
        let (fw, fh) = (f64::from(iw), f64::from(ih));
        let steps = (0..9).map(|k| f64::from(k) / 8.0);
        let inside = steps
            .clone()
            .flat_map(|u| steps.clone().map(move |v| (u * (w - 1.0), v * (h - 1.0))))
            .filter(|&(i, j)| self.source_of(i, j).is_some_and(|(x, y)| x >= -1.0 && y >= -1.0 && x <= fw && y <= fh))
            .count();
        if inside == 0 {
            return Err(Error::mismatch(
                self.image.path(),
                format!(
                    "mismatched extents: this {iw}x{ih} image, placed by its georeference, lies nowhere over \
                     the elevation"
                ),
            ));
        }
        Ok(())
    }
}

/// A pixel's size in metres near the centre of an image `height` pixels tall: in a
/// projected CRS its units; in degrees, measured at the centre latitude (the geometric mean
/// of across and down).
fn pixel_metres(crs: &Crs, at: Placement, height: u32) -> Option<f64> {
    if !crs.is_geographic() {
        return Some((at.pixel.0 * at.pixel.1).sqrt()).filter(|m| m.is_finite() && *m > 0.0);
    }
    let lat = (at.origin[1] - f64::from(height) / 2.0 * at.pixel.1).to_radians();
    let m = (at.pixel.0 * 111_320.0 * lat.cos() * at.pixel.1 * 110_574.0).sqrt();
    (m.is_finite() && m > 0.0).then_some(m)
}

/// The pixel size in metres of an image that says where it lies (see `pixel_metres`);
/// `None` without a georeference in a CRS the tiler knows.
pub fn image_pixel_metres(image: &dyn ImageSource) -> Option<f64> {
    let (crs, origin, pixel) = crs_placement(image.georeference(), image.crs_pixel_size())?;
    pixel_metres(&Crs::parse(crs).ok()?, Placement { origin, pixel }, image.size().1)
}

impl ImageSource for Warped<'_> {
    fn path(&self) -> &Path {
        self.image.path()
    }
    fn size(&self) -> (u32, u32) {
        self.size
    }
    fn georeference(&self) -> Option<&Georeference> {
        self.georeference.as_ref()
    }
    fn rows(&self, row: &mut dyn FnMut(&[[u8; 4]]) -> Result<()>) -> Result<()> {
        // The image rows each output row needs, and for each output row the first image
        // row any later one needs: rows before it are dropped.
        let needs: Vec<(i64, i64)> = (0..self.size.1).map(|j| span(&self.row_sources(j))).collect();
        let mut keep_from = vec![i64::MAX; needs.len() + 1];
        for j in (0..needs.len()).rev() {
            keep_from[j] = keep_from[j + 1].min(needs[j].0);
        }
        let (iw, ih) = self.image.size();
        std::thread::scope(|scope| {
            // The image is read on its own thread, a few rows ahead.
            let (sender, rows) = mpsc::sync_channel::<Vec<[u8; 4]>>(64);
            let reader = scope.spawn(move || {
                self.image.rows(&mut |r| sender.send(r.to_vec()).map_err(|_| Error::Interrupted(crate::Interrupted)))
            });
            let mut band: VecDeque<Vec<[u8; 4]>> = VecDeque::new();
            let mut first = 0i64;
            let mut out = vec![[0u8; 4]; self.size.0 as usize];
            let mut result = Ok(());
            for j in 0..self.size.1 {
                let (_, last) = needs[j as usize];
                while first + (band.len() as i64) <= last.min(i64::from(ih) - 1) {
                    let Ok(r) = rows.recv() else { break };
                    band.push_back(r);
                    // Rows above what this and every later output row need are dropped
                    // as they arrive.
                    while first < keep_from[j as usize] && !band.is_empty() {
                        band.pop_front();
                        first += 1;
                    }
                }
                let sources = self.row_sources(j);
                for (texel, &(x, y)) in out.iter_mut().zip(&sources) {
                    *texel = sample(&band, first, iw, (x, y));
                }
                if let Err(e) = row(&out) {
                    result = Err(e);
                    break;
                }
                while first < keep_from[j as usize + 1] && !band.is_empty() {
                    band.pop_front();
                    first += 1;
                }
            }
            drop(rows);
            match reader.join() {
                Ok(Err(e)) if result.is_ok() && !e.is_interrupted() => Err(e),
                Err(_) => Err(Error::Panicked { thread: "image reading" }),
                _ => result,
            }
        })
    }
}

/// The first and last image rows a row of sample points touches (bilinear: the rows
/// either side of each point).
fn span(points: &[(f64, f64)]) -> (i64, i64) {
    let ys = points.iter().map(|p| p.1).filter(|y| y.is_finite());
    let (lo, hi) = ys.fold((f64::INFINITY, f64::NEG_INFINITY), |(a, b), y| (a.min(y), b.max(y)));
    if lo > hi {
        return (i64::MAX, i64::MIN);
    }
    #[expect(clippy::cast_possible_truncation, reason = "pixel rows are far below 2^63")]
    (lo.floor().max(0.0) as i64, hi.floor() as i64 + 1)
}

/// Bilinear sample at image pixel coordinates `(x, y)` (centres at integers), weighted by
/// alpha: colours of transparent pixels do not bleed in; alpha 0 outside the image.
fn sample(band: &VecDeque<Vec<[u8; 4]>>, first: i64, width: u32, (x, y): (f64, f64)) -> [u8; 4] {
    if !(x.is_finite() && y.is_finite()) {
        return [0; 4];
    }
    let (x0, y0) = (x.floor(), y.floor());
    let (fx, fy) = (x - x0, y - y0);
    #[expect(clippy::cast_possible_truncation, reason = "pixel coordinates are far below 2^63")]
    let (x0, y0) = (x0 as i64, y0 as i64);
    // The four neighbours with their weights; outside the image or the band, no data.
    let corner = |dx: i64, dy: i64, w: f64| {
        let (px, py) = (x0 + dx, y0 + dy);
        if w <= 0.0 || px < 0 || px >= i64::from(width) || py < first {
            return ([0; 4], 0.0);
        }
        #[expect(clippy::cast_possible_truncation, clippy::cast_sign_loss, reason = "checked non-negative above")]
        let p = band.get((py - first) as usize).and_then(|r| r.get(px as usize)).copied();
        p.map_or(([0; 4], 0.0), |p| (p, w))
    };
    Pixels::blend(&[
        corner(0, 0, (1.0 - fx) * (1.0 - fy)),
        corner(1, 0, fx * (1.0 - fy)),
        corner(0, 1, (1.0 - fx) * fy),
        corner(1, 1, fx * fy),
    ])
}
