//! Orthophotos as they are usually published: JPEG-compressed GeoTIFFs with YCbCr pixels
//! (`gdal_translate -co COMPRESS=JPEG -co PHOTOMETRIC=YCBCR`). They are read as RGB, the
//! colours GDAL itself shows of them (the independent oracle), alone and in a mosaic.
#![allow(clippy::unwrap_used, clippy::cast_possible_truncation, clippy::cast_precision_loss, missing_docs)]

mod common;

use std::path::Path;
use std::process::Command;

use terrastream_tiler::{ImageSource, Mosaic, MosaicOptions, Pixels, read_image};
use tiff::encoder::{TiffEncoder, colortype};
use tiff::tags::Tag;

fn gdal() -> bool {
    common::tool("gdal_translate", "gdal-bin")
}

fn translate(args: &[&str], from: &Path, to: &Path) {
    let status = Command::new("gdal_translate").arg("-q").args(args).arg(from).arg(to).status().unwrap();
    assert!(status.success(), "gdal_translate {args:?} failed");
}

/// A colourful RGB GeoTIFF in UTM 33N (smooth hues, so that JPEG keeps them).
fn rgb_tile(path: &Path, (w, h): (u32, u32)) {
    let mut encoder = TiffEncoder::new(std::fs::File::create(path).unwrap()).unwrap();
    let mut image = encoder.new_image::<colortype::RGB8>(w, h).unwrap();
    image.encoder().write_tag(Tag::Unknown(33550), &[2.0, 2.0, 0.0][..]).unwrap();
    image.encoder().write_tag(Tag::Unknown(33922), &[0.0, 0.0, 0.0, 500_000.0, 5_100_000.0, 0.0][..]).unwrap();
    image.encoder().write_tag(Tag::Unknown(34735), &[1u16, 1, 0, 2, 1024, 0, 1, 1, 3072, 0, 1, 32633][..]).unwrap();
    let data: Vec<u8> = (0..h)
        .flat_map(|j| (0..w).map(move |i| (i, j)))
        .flat_map(|(i, j)| {
            let (x, y) = (f64::from(i) / f64::from(w), f64::from(j) / f64::from(h));
            [(40.0 + 200.0 * x) as u8, (220.0 - 180.0 * y) as u8, (128.0 + 100.0 * ((x + y) * 6.0).sin()) as u8]
        })
        .collect();
    image.write_data(&data).unwrap();
}

/// Mean and largest difference of two RGBA pixel runs, over R, G and B.
fn difference(a: &[u8], b: &[u8]) -> (f64, u8) {
    assert_eq!(a.len(), b.len());
    let (mut sum, mut most, mut n) = (0u64, 0u8, 0u64);
    for (pa, pb) in a.chunks_exact(4).zip(b.chunks_exact(4)) {
        for c in 0..3 {
            let d = pa[c].abs_diff(pb[c]);
            sum += u64::from(d);
            most = most.max(d);
            n += 1;
        }
    }
    (sum as f64 / n as f64, most)
}

#[test]
fn a_jpeg_ycbcr_geotiff_reads_as_the_rgb_gdal_shows() {
    if !gdal() {
        return;
    }
    let dir = tempfile::tempdir().unwrap();
    let (source, photo, shown) =
        (dir.path().join("rgb.tif"), dir.path().join("photo.tif"), dir.path().join("shown.tif"));
    rgb_tile(&source, (300, 200));
    translate(&["-co", "COMPRESS=JPEG", "-co", "PHOTOMETRIC=YCBCR", "-co", "TILED=YES"], &source, &photo);
    // What GDAL shows of it, written as plain RGB.
    translate(&["-co", "COMPRESS=NONE"], &photo, &shown);
    let (ours, gdal) = (read_image(&photo).unwrap(), read_image(&shown).unwrap());
    assert_eq!((ours.width, ours.height), (300, 200));
    assert!(ours.georeference.is_some(), "placed by its georeference");
    // The same JPEG data; only the chroma upsampling may differ (libjpeg's is smoothed).
    let (mean, most) = difference(&ours.rgba, &gdal.rgba);
    assert!(mean < 0.6 && most <= 8, "mean {mean}, largest {most}");
    // Against the colours before JPEG: close (a JPEG's loss), where Y, Cb, Cr read as
    // R, G, B would be far.
    let before = read_image(&source).unwrap();
    let (mean, _) = difference(&ours.rgba, &before.rgba);
    assert!(mean < 3.0, "mean {mean} from the source colours");

    // In a mosaic (a folder of such photos), the same colours.
    let mosaic = Mosaic::<Pixels>::open(&[photo], &MosaicOptions::default()).unwrap();
    assert_eq!(ImageSource::size(&mosaic), (300, 200));
    let mut rows = Vec::new();
    ImageSource::rows(&mosaic, &mut |r| {
        rows.extend_from_slice(r.as_flattened());
        Ok(())
    })
    .unwrap();
    let (mean, most) = difference(&rows, &gdal.rgba);
    assert!(mean < 0.6 && most <= 8, "mosaic: mean {mean}, largest {most}");
}
