//! A generated continent: a geographic DEM of 900 x 500 samples spanning 90 x 50 degrees
//! (135 W to 45 W, 65 N to 15 N; world coordinates reach 10^7 m) with an image draped
//! over it: hypsometric colours and a 10-degree graticule, so a misplaced or missing
//! drape shows. Small in samples (the test suite runs on two cores), full size in extent.

use std::path::{Path, PathBuf};
use std::process::Command;

const WIDTH: u32 = 900;
const HEIGHT: u32 = 500;
/// Degrees per sample.
const STEP: f64 = 0.1;
const WEST: f64 = -135.0;
const NORTH: f64 = 65.0;

fn height(i: u32, j: u32) -> f32 {
    let (u, v) = (f64::from(i) / f64::from(WIDTH) - 0.5, f64::from(j) / f64::from(HEIGHT) - 0.5);
    // Land inside an ellipse, ocean (0 m) outside; two ranges of mountains on the land.
    let land = 1.0 - (u / 0.42).powi(2) - (v / 0.4).powi(2);
    if land <= 0.0 {
        return 0.0;
    }
    let ridges = (u * 23.0).sin() * (v * 17.0).cos() * 0.5 + 0.5;
    let range = (-((u + 0.18) / 0.06).powi(2)).exp() + 0.7 * (-((v - 0.1) / 0.08).powi(2)).exp();
    (land.sqrt() * 900.0 + ridges * 600.0 * land + range * 3500.0) as f32
}

fn colour(i: u32, j: u32) -> [u8; 3] {
    let (lon, lat) = (WEST + (f64::from(i) + 0.5) * STEP, NORTH - (f64::from(j) + 0.5) * STEP);
    let near_line = |deg: f64| (deg / 10.0 - (deg / 10.0).round()).abs() * 10.0 < STEP * 0.8;
    if near_line(lon) || near_line(lat) {
        return [250, 250, 250];
    }
    let h = height(i, j);
    match h {
        h if h <= 0.0 => [30, 70, 140],
        h if h < 800.0 => [70, 130, 60],
        h if h < 1600.0 => [150, 150, 80],
        h if h < 2600.0 => [140, 100, 70],
        _ => [235, 235, 240],
    }
}

fn geotiff(path: &Path, rgb: bool) {
    use tiff::encoder::{TiffEncoder, colortype};
    use tiff::tags::Tag;
    let mut encoder = TiffEncoder::new(std::fs::File::create(path).unwrap()).unwrap();
    let tag = |image: &mut tiff::encoder::DirectoryEncoder<'_, _, _>| {
        image.write_tag(Tag::Unknown(33550), &[STEP, STEP, 0.0][..]).unwrap();
        image.write_tag(Tag::Unknown(33922), &[0.0, 0.0, 0.0, WEST, NORTH, 0.0][..]).unwrap();
        image.write_tag(Tag::Unknown(34735), &[1u16, 1, 0, 2, 1024, 0, 1, 2, 2048, 0, 1, 4326][..]).unwrap();
    };
    let pixels = (0..HEIGHT).flat_map(|j| (0..WIDTH).map(move |i| (i, j)));
    if rgb {
        let mut image = encoder.new_image::<colortype::RGB8>(WIDTH, HEIGHT).unwrap();
        tag(image.encoder());
        let data: Vec<u8> = pixels.flat_map(|(i, j)| colour(i, j)).collect();
        image.write_data(&data).unwrap();
    } else {
        let mut image = encoder.new_image::<colortype::Gray32Float>(WIDTH, HEIGHT).unwrap();
        tag(image.encoder());
        let data: Vec<f32> = pixels.map(|(i, j)| height(i, j)).collect();
        image.write_data(&data).unwrap();
    }
}

/// Writes the DEM and the image under `dir` and tiles them with the `terrastream` binary
/// (64-sample tiles): the archive.
pub fn continent_archive(terrastream: &Path, dir: &Path) -> PathBuf {
    let (dem, image, out) =
        (dir.join("continent-dem.tif"), dir.join("continent-image.tif"), dir.join("continent.tspack"));
    geotiff(&dem, false);
    geotiff(&image, true);
    let status = Command::new(terrastream)
        .args(["-q", "tile", "--elevation"])
        .arg(&dem)
        .arg("--texture")
        .arg(&image)
        .arg("-o")
        .arg(&out)
        .args(["--tile-size", "64", "--texture-tile-size", "64"])
        .status()
        .unwrap();
    assert!(status.success(), "tiling the continent failed");
    out
}
