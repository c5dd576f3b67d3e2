//! Any bytes as the files beside a PNG that say where it lies: a world file, a `.prj` and
//! GDAL's `.aux.xml` (the input split in three at `0xFF` bytes). Must never panic; what is
//! accepted places the image north-up with positive, finite pixel sizes.
#![no_main]

use libfuzzer_sys::fuzz_target;
use terrastream_raster::{ImageSource, open_image};

/// A 1 x 1 RGBA PNG.
const PNG: [u8; 70] = [
    137, 80, 78, 71, 13, 10, 26, 10, 0, 0, 0, 13, 73, 72, 68, 82, 0, 0, 0, 1, 0, 0, 0, 1, 8, 6, 0, 0, 0, 31, 21, 196,
    137, 0, 0, 0, 13, 73, 68, 65, 84, 120, 218, 99, 100, 96, 248, 95, 15, 0, 2, 135, 1, 128, 235, 71, 186, 146, 0, 0,
    0, 0, 73, 69, 78, 68, 174, 66, 96, 130,
];

fuzz_target!(|data: &[u8]| {
    let dir = std::env::temp_dir().join(format!("terrastream-fuzz-sidecars-{}", std::process::id()));
    let _ = std::fs::create_dir_all(&dir);
    let image = dir.join("image.png");
    let mut parts = data.splitn(3, |&b| b == 0xFF);
    let files = [dir.join("image.pgw"), dir.join("image.prj"), dir.join("image.png.aux.xml")];
    for file in &files {
        let _ = std::fs::remove_file(file);
        if let Some(part) = parts.next() {
            let _ = std::fs::write(file, part);
        }
    }
    if std::fs::write(&image, PNG).is_err() {
        return;
    }
    if let Ok(file) = open_image(&image)
        && let Some(g) = file.georeference()
    {
        let (px, py) = file.crs_pixel_size().expect("a placed image has a pixel size");
        assert!(px > 0.0 && py > 0.0 && px.is_finite() && py.is_finite(), "pixel {px} x {py}");
        assert!(g.origin.is_some_and(|o| o.iter().all(|v| v.is_finite())), "origin {:?}", g.origin);
        assert!(g.crs.is_some(), "placed without a CRS");
    }
});
