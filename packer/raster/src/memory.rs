//! Sources held in memory: a raster of heights, an RGBA image, and a window of an image
//! over an elevation's extent.

use std::path::Path;

use terrastream_format::Georeference;

use super::{ElevationSource, ImageSource, crs_placement};
use crate::error::{Error, Result};

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

impl<'a> ImageWindow<'a> {
    /// The window of `image` over `elevation`'s extent; `None` when they cannot be matched
    /// by georeference (either lacks one, or their CRSs differ) or the window is the whole
    /// image.
    ///
    /// # Errors
    /// [`Error::Mismatch`] naming the image when it does not cover the elevation's extent.
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
            return Err(Error::mismatch(
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
            return Err(Error::mismatch(image.path(), "the elevation covers less than one pixel of the texture"));
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
                return Err(Error::Interrupted(crate::Interrupted));
            }
            Ok(())
        });
        match result {
            Err(e) if done && e.is_interrupted() => Ok(()),
            other => other,
        }
    }
}

fn as_pixels(rgba: &[u8]) -> Vec<[u8; 4]> {
    rgba.chunks_exact(4).map(|p| [p[0], p[1], p[2], p[3]]).collect()
}
