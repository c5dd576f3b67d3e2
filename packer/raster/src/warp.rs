//! An image in another CRS than the elevation, resampled onto the elevation's extent by
//! both georeferences: each texel's centre goes from the elevation's CRS to the image's
//! and is sampled there (bilinear, weighted by alpha). The image is read once, top to
//! bottom, holding only the band of its rows that the current output row needs.

use std::collections::VecDeque;
use std::path::Path;
use std::sync::mpsc;

use rayon::prelude::*;

use crate::mosaic::ROWS_AT_ONCE;

use terrastream_format::Georeference;

use super::{ElevationSource, ImageSource, MosaicKind, Pixels, crs_placement};
use crate::crs::{Crs, Transform};
use crate::error::{Error, Result};

/// Output texels between exact transforms along a row and down a column; bilinear in
/// between (well under a texel apart for any smooth projection at this spacing).
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

    /// Where the lattice of exact transforms lies: every [`LATTICE`] texels along rows
    /// `0, LATTICE, …` and the last row, at columns `0, LATTICE, …` and the last column.
    fn lattice(&self) -> Lattice {
        let stops = |n: usize| {
            (0..n).step_by(LATTICE).chain((n > 1 && !(n - 1).is_multiple_of(LATTICE)).then_some(n - 1)).collect()
        };
        Lattice { columns: stops(self.size.0 as usize), rows: stops(self.size.1 as usize) }
    }

    /// The image pixel coordinates of lattice row `index`'s points (NaN where a point has
    /// no image).
    fn lattice_row(&self, lattice: &Lattice, index: usize) -> Vec<(f64, f64)> {
        #[expect(clippy::cast_precision_loss, reason = "texel indices are far below 2^52")]
        let (j, exact) = (lattice.rows[index] as f64, |i: usize| i as f64);
        lattice.columns.iter().map(|&i| self.source_of(exact(i), j).unwrap_or((f64::NAN, f64::NAN))).collect()
    }

    /// The image pixel coordinates of every texel centre of row `j`: bilinear between the
    /// points of the lattice rows around it, which `rows` holds (by index).
    fn row_sources(&self, lattice: &Lattice, rows: &LatticeRows, j: u32) -> Vec<(f64, f64)> {
        let j = j as usize;
        let (a, b) = lattice.around(j);
        let (ra, rb) = (lattice.rows[a], lattice.rows[b]);
        #[expect(clippy::cast_precision_loss, reason = "texel indices are far below 2^52")]
        let t = if rb > ra { (j - ra) as f64 / (rb - ra) as f64 } else { 0.0 };
        let mix = |p: (f64, f64), q: (f64, f64), t: f64| (p.0 + (q.0 - p.0) * t, p.1 + (q.1 - p.1) * t);
        let exact: Vec<(f64, f64)> = rows[&a].iter().zip(&rows[&b]).map(|(&p, &q)| mix(p, q, t)).collect();
        let mut out = Vec::with_capacity(self.size.0 as usize);
        for (k, pair) in lattice.columns.windows(2).enumerate() {
            let (from, to) = (pair[0], pair[1]);
            #[expect(clippy::cast_precision_loss, reason = "at most LATTICE texels")]
            out.extend((from..to).map(|i| mix(exact[k], exact[k + 1], (i - from) as f64 / (to - from) as f64)));
        }
        out.push(exact[exact.len() - 1]);
        out.truncate(self.size.0 as usize);
        out
    }

    /// The first and last image rows each output row needs. A row between two lattice
    /// rows lies, by interpolation, within those rows' points: it needs no image rows
    /// beyond theirs. Found a band of lattice rows at a time, in parallel (memory follows
    /// the width, not the height).
    fn needs(&self, lattice: &Lattice) -> Vec<(i64, i64)> {
        let spans: Vec<(i64, i64)> = (0..lattice.rows.len())
            .collect::<Vec<_>>()
            .par_chunks(64)
            .flat_map_iter(|indices| indices.iter().map(|&index| span(&self.lattice_row(lattice, index))))
            .collect();
        (0..self.size.1 as usize)
            .map(|j| {
                let (a, b) = lattice.around(j);
                (spans[a].0.min(spans[b].0), spans[a].1.max(spans[b].1))
            })
            .collect()
    }

    /// Keeps in `held` the lattice rows that output rows `rows` need, and those alone: the
    /// ones it lacks made in parallel (rows go down, so a row above is not needed again).
    fn lattice_rows(&self, lattice: &Lattice, rows: std::ops::Range<u32>, held: &mut LatticeRows) {
        let (first, _) = lattice.around(rows.start as usize);
        let (_, last) = lattice.around(rows.end.saturating_sub(1) as usize);
        held.retain(|&index, _| (first..=last).contains(&index));
        let missing: Vec<usize> = (first..=last).filter(|index| !held.contains_key(index)).collect();
        let made: Vec<_> = missing.into_par_iter().map(|index| (index, self.lattice_row(lattice, index))).collect();
        held.extend(made);
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
        let lattice = self.lattice();
        let needs = self.needs(&lattice);
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
            let mut result = Ok(());
            let mut points = LatticeRows::new();
            let mut j0 = 0u32;
            'rows: while j0 < self.size.1 {
                // A group of output rows, made at once on every core from the image rows
                // they need.
                let j1 = (j0 + ROWS_AT_ONCE).min(self.size.1);
                let last = needs[j0 as usize..j1 as usize].iter().map(|n| n.1).max().unwrap_or(i64::MIN);
                while first + (band.len() as i64) <= last.min(i64::from(ih) - 1) {
                    let Ok(r) = rows.recv() else { break };
                    band.push_back(r);
                    // Rows above what this group and every later row need are dropped
                    // as they arrive.
                    while first < keep_from[j0 as usize] && !band.is_empty() {
                        band.pop_front();
                        first += 1;
                    }
                }
                self.lattice_rows(&lattice, j0..j1, &mut points);
                let made: Vec<Vec<[u8; 4]>> = (j0..j1)
                    .into_par_iter()
                    .map(|j| {
                        let sources = self.row_sources(&lattice, &points, j);
                        sources.into_iter().map(|p| sample(&band, first, iw, p)).collect()
                    })
                    .collect();
                for out in &made {
                    if let Err(e) = row(out) {
                        result = Err(e);
                        break 'rows;
                    }
                }
                while first < keep_from[j1 as usize] && !band.is_empty() {
                    band.pop_front();
                    first += 1;
                }
                j0 = j1;
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

/// Where a warp's lattice of exact transforms lies (see `Warped::lattice`).
struct Lattice {
    /// The texel columns and rows of its points.
    columns: Vec<usize>,
    rows: Vec<usize>,
}

impl Lattice {
    /// The indices of the lattice rows at or above texel row `j` and below it (the same
    /// index for a lattice row and the last).
    fn around(&self, j: usize) -> (usize, usize) {
        let below = self.rows.partition_point(|&r| r <= j).clamp(1, self.rows.len());
        (below - 1, below.min(self.rows.len() - 1))
    }
}

/// Some lattice rows' points, by index.
type LatticeRows = std::collections::HashMap<usize, Vec<(f64, f64)>>;

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

#[cfg(test)]
mod tests {
    use super::*;

    /// A source placed at `origin` in `crs`, pixels `pixel` in its units; no samples.
    #[derive(Debug)]
    struct Placed {
        size: (u32, u32),
        pixel: (f64, f64),
        georeference: Georeference,
    }

    impl Placed {
        fn new(crs: &str, origin: [f64; 2], pixel: (f64, f64), size: (u32, u32)) -> Self {
            let georeference = Georeference { crs: Some(crs.into()), origin: Some(origin), ..Georeference::default() };
            Self { size, pixel, georeference }
        }
    }

    impl ElevationSource for Placed {
        fn path(&self) -> &Path {
            Path::new("dem")
        }
        fn size(&self) -> (u32, u32) {
            self.size
        }
        fn spacing(&self) -> (f64, f64) {
            self.pixel
        }
        fn georeference(&self) -> Option<&Georeference> {
            Some(&self.georeference)
        }
        fn crs_pixel_size(&self) -> Option<(f64, f64)> {
            Some(self.pixel)
        }
        fn rows(&self, _: &mut dyn FnMut(&[f32]) -> Result<()>) -> Result<()> {
            Ok(())
        }
    }

    impl ImageSource for Placed {
        fn path(&self) -> &Path {
            Path::new("image")
        }
        fn size(&self) -> (u32, u32) {
            self.size
        }
        fn georeference(&self) -> Option<&Georeference> {
            Some(&self.georeference)
        }
        fn crs_pixel_size(&self) -> Option<(f64, f64)> {
            Some(self.pixel)
        }
        fn rows(&self, _: &mut dyn FnMut(&[[u8; 4]]) -> Result<()>) -> Result<()> {
            Ok(())
        }
    }

    /// Every texel of a geographic image warped onto a UTM DEM lies, by the lattice, within
    /// 1/1000 of an image pixel of where its exact transform puts it, and on the lattice's
    /// own points exactly there; the image rows each row needs are found from its lattice
    /// rows.
    #[test]
    fn the_lattice_places_every_texel_as_its_exact_transform() {
        let dem = Placed::new("EPSG:32632", [500_000.0, 5_200_000.0], (30.0, 30.0), (600, 450));
        let image = Placed::new("EPSG:4326", [8.9, 46.95], (0.0002, 0.0002), (2000, 1500));
        let warped = Warped::over(&dem, &image).unwrap().expect("two CRSs: warped");
        let (w, h) = warped.size;
        assert!(w > 500 && h > 500, "{w} x {h}");
        let lattice = warped.lattice();
        let mut points = LatticeRows::new();
        warped.lattice_rows(&lattice, 0..h, &mut points);
        let needs = warped.needs(&lattice);
        let mut worst: f64 = 0.0;
        for j in (0..h).step_by(7).chain([h - 1]) {
            let row = warped.row_sources(&lattice, &points, j);
            assert_eq!(row.len(), w as usize);
            // The image rows the row reads lie within those its lattice rows need.
            let ((lo, hi), (need_lo, need_hi)) = (span(&row), needs[j as usize]);
            assert!(need_lo <= lo && hi <= need_hi && hi - lo < 40, "row {j}: {lo}..{hi} in {need_lo}..{need_hi}");
            for (i, &(x, y)) in row.iter().enumerate() {
                #[expect(clippy::cast_precision_loss, reason = "texel indices")]
                let (ex, ey) = warped.source_of(i as f64, f64::from(j)).unwrap();
                let off = (x - ex).hypot(y - ey);
                if (j as usize).is_multiple_of(LATTICE) && i.is_multiple_of(LATTICE) {
                    assert!(off < 1e-9, "lattice point {i}, {j}: {off}");
                }
                worst = worst.max(off);
            }
        }
        assert!(worst < 1e-3, "{worst} image pixels off");
    }
}
