//! Image files: GeoTIFF, PNG or JPEG pixels as rows of RGBA8.

use std::path::{Path, PathBuf};

use terrastream_format::Georeference;

use super::geotiff::GeoTags;
use super::jpeg::{decode_jpeg, decoded_whole, jpeg_header};
use super::jpegrows::jpeg_rows;
use super::memory::Image;
use super::png::{png_header, png_rows};
use super::tiff::{PLANAR_CONFIGURATION, open_input_tiff, tiff_rows};
use super::worldfile::read_sidecar;
use super::{ImageSource, Sniffed, sniff};
use crate::error::{Error, Result};

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
        /// Y, Cb, Cr samples (JPEG-compressed orthophotos): converted to RGB as read.
        ycbcr: bool,
    },
    Png,
    /// A JPEG: decoded whole when read, or by rows if too large for that.
    Jpeg,
}

/// Opens an image for reading by rows: GeoTIFF (8-bit gray, gray+alpha, RGB, RGBA or YCbCr;
/// strips or tiles; none, LZW, Deflate or JPEG) or PNG (any colour type; 16-bit is reduced to 8), or
/// JPEG (decoded whole when read; by rows past 1 GiB of pixels); told apart by content. A PNG, a JPEG or a TIFF without
/// GeoTIFF tags is placed by a world file or GDAL `.aux.xml` beside it, with its CRS from a
/// `.prj` or the `.aux.xml`.
///
/// # Errors
/// [`Error::Unsupported`] naming the file for anything not read here, other variants for
/// unreadable or damaged data.
pub fn open_image(path: &Path) -> Result<ImageFile> {
    let bad = |why: String| Error::unsupported(path, why);
    let mut crs_pixel = None;
    let (width, height, georeference, kind) = match sniff(path)? {
        Sniffed::Png => {
            let (_, (w, h)) = png_header(path)?;
            (w, h, None, ImageKind::Png)
        }
        Sniffed::Jpeg => {
            let (w, h) = jpeg_header(path)?;
            (w, h, None, ImageKind::Jpeg)
        }
        Sniffed::Tiff => {
            let mut decoder = open_input_tiff(path)?;
            let (width, height) = decoder.dimensions().map_err(|e| Error::tiff(path, "", e))?;
            let colour = decoder.colortype().map_err(|e| Error::tiff(path, "", e))?;
            let channels = match colour {
                tiff::ColorType::Gray(8) => 1,
                tiff::ColorType::GrayA(8) => 2,
                tiff::ColorType::RGB(8) | tiff::ColorType::YCbCr(8) => 3,
                tiff::ColorType::RGBA(8) => 4,
                other => {
                    return Err(bad(format!("{other:?} pixels: textures must be 8-bit gray, RGB, RGBA or YCbCr")));
                }
            };
            let ycbcr = matches!(colour, tiff::ColorType::YCbCr(_));
            let planar = decoder.find_tag_unsigned::<u16>(tiff::tags::Tag::Unknown(PLANAR_CONFIGURATION));
            if channels > 1 && matches!(planar, Ok(Some(2))) {
                return Err(bad("planar (band-separate) pixels: store the bands interleaved".into()));
            }
            let tags = GeoTags::read(&mut decoder);
            let georeference = tags.placement(path, width, height).ok().and_then(|(_, g)| g);
            crs_pixel = georeference.as_ref().and_then(|_| tags.crs_pixel());
            (width, height, georeference, ImageKind::Tiff { channels, ycbcr })
        }
    };
    if width == 0 || height == 0 {
        return Err(Error::damaged(path, format!("the image is empty ({width}x{height} pixels)")));
    }
    let mut georeference = georeference;
    if georeference.is_none()
        && let Some(sidecar) = read_sidecar(path, (width, height))?
    {
        georeference = Some(sidecar.georeference);
        crs_pixel = Some(sidecar.crs_pixel);
    }
    Ok(ImageFile { path: path.to_path_buf(), width, height, georeference, crs_pixel, kind })
}

/// Reads a whole image into memory (small images, tests); [`open_image`] streams.
///
/// # Errors
/// As [`open_image`].
pub fn read_image(path: &Path) -> Result<Image> {
    let file = open_image(path)?;
    let rgba = file.rgba()?;
    Ok(Image { width: file.width, height: file.height, rgba, georeference: file.georeference })
}

impl ImageFile {
    /// Samples per pixel of a GeoTIFF, read by strips or tiles; `None` for PNG and JPEG.
    pub(super) fn tiff_channels(&self) -> Option<usize> {
        match self.kind {
            ImageKind::Tiff { channels, .. } => Some(channels),
            ImageKind::Png | ImageKind::Jpeg => None,
        }
    }
}

impl ImageFile {
    /// The pixels of a PNG or JPEG row after row, as RGBA8, decoding as little at a time as
    /// the file allows: a PNG or a sequential JPEG by rows, a progressive JPEG whole (it
    /// cannot be read by rows; one too large for that is refused when opened). What a
    /// mosaic reads of one, a band of rows at a time.
    ///
    /// # Errors
    /// [`Error::Input`] naming the file for unreadable data, or for a GeoTIFF (read by
    /// strips or tiles).
    pub(super) fn streamed_rows(&self, row: &mut dyn FnMut(&[[u8; 4]]) -> Result<()>) -> Result<()> {
        match self.kind {
            ImageKind::Tiff { .. } => Err(Error::unsupported(&self.path, "read by strips or tiles, not by rows")),
            ImageKind::Jpeg => self.rows_by(super::jpegrows::reads_by_rows(&self.path)?, row),
            ImageKind::Png => self.rows_by(false, row),
        }
    }

    /// Every pixel, row after row, as RGBA8.
    fn rgba(&self) -> Result<Vec<u8>> {
        let mut rgba = Vec::with_capacity(self.width as usize * self.height as usize * 4);
        self.rows(&mut |row| {
            rgba.extend_from_slice(row.as_flattened());
            Ok(())
        })?;
        Ok(rgba)
    }

    /// A JPEG's RGB pixels, checked to be as many as its header says.
    fn decode_jpeg(&self) -> Result<Vec<u8>> {
        let (w, h, rgb) = decode_jpeg(&self.path)?;
        if (w, h) != (self.width, self.height) || rgb.len() != w as usize * h as usize * 3 {
            let (width, height) = (self.width, self.height);
            return Err(Error::damaged(&self.path, format!("{} bytes of pixels for {width}x{height}", rgb.len())));
        }
        Ok(rgb)
    }

    /// Are its samples Y, Cb, Cr (converted to RGB as they are read)?
    pub(super) fn ycbcr(&self) -> bool {
        matches!(self.kind, ImageKind::Tiff { ycbcr: true, .. })
    }
}

/// One pixel's Y, Cb, Cr -> R, G, B, as libjpeg converts them (JFIF, full range, 16-bit
/// fixed point, rounded, clamped): what GDAL shows of a JPEG-compressed YCbCr GeoTIFF.
/// Always inlined: a call a pixel, left out of line even with a hint, took 12 % of a JPEG
/// mosaic's CPU.
#[inline(always)]
pub(super) fn ycbcr_to_rgb([y, cb, cr]: [u8; 3]) -> [u8; 3] {
    const HALF: i32 = 1 << 15;
    // libjpeg's FIX(): the coefficient in 16.16 fixed point, rounded.
    const fn fix(x: f64) -> i32 {
        #[expect(clippy::cast_possible_truncation, reason = "coefficients under 2")]
        let v = (x * 65_536.0 + 0.5) as i32;
        v
    }
    let (y, cb, cr) = (i32::from(y), i32::from(cb) - 128, i32::from(cr) - 128);
    let r = y + ((fix(1.402) * cr + HALF) >> 16);
    let g = y + ((-fix(0.344_14) * cb - fix(0.714_14) * cr + HALF) >> 16);
    let b = y + ((fix(1.772) * cb + HALF) >> 16);
    let clamp = |v: i32| u8::try_from(v.clamp(0, 255)).unwrap_or(u8::MAX);
    [clamp(r), clamp(g), clamp(b)]
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
        self.rows_by(false, row)
    }
}

impl ImageFile {
    /// [`ImageSource::rows`]; a JPEG by rows if `jpeg_by_rows`, else only when too large
    /// to decode whole.
    fn rows_by(&self, jpeg_by_rows: bool, row: &mut dyn FnMut(&[[u8; 4]]) -> Result<()>) -> Result<()> {
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
            ImageKind::Jpeg if !jpeg_by_rows && decoded_whole(width, self.height as usize) => {
                self.decode_jpeg()?.chunks_exact(width * 3).try_for_each(|r| emit(r, 3))
            }
            ImageKind::Jpeg => jpeg_rows(&self.path, &mut |r| emit(r, 3)),
            ImageKind::Png => png_rows(&self.path, self.width, |values, channels, sixteen| {
                if sixteen {
                    let eight: Vec<u8> = values.chunks_exact(2).map(|v| v[0]).collect();
                    emit(&eight, channels)
                } else {
                    emit(values, channels)
                }
            }),
            ImageKind::Tiff { channels, ycbcr } => {
                let mut bytes = vec![0u8; width * channels];
                #[expect(clippy::cast_possible_truncation, clippy::cast_sign_loss, reason = "8-bit samples")]
                let mut eight = |r: &[f32]| -> Result<()> {
                    for (b, &v) in bytes.iter_mut().zip(r) {
                        *b = v as u8;
                    }
                    if *ycbcr {
                        for px in bytes.chunks_exact_mut(3) {
                            px.copy_from_slice(&ycbcr_to_rgb([px[0], px[1], px[2]]));
                        }
                    }
                    emit(&bytes, *channels)
                };
                tiff_rows(&self.path, *channels, &|_| {}, &mut eight)
            }
        }
    }
}
