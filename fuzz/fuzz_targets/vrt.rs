//! Any bytes as a GDAL virtual raster (`.vrt`), read as a mosaic's inputs: the XML, the
//! GeoTransform, the SRS, every source's file name and rectangles. Must never panic; a
//! source naming a missing file is an error, never a read.
#![no_main]

use libfuzzer_sys::fuzz_target;
use terrastream_raster::read_vrt;

fuzz_target!(|data: &[u8]| {
    let dir = std::env::temp_dir().join(format!("terrastream-fuzz-vrt-{}", std::process::id()));
    let _ = std::fs::create_dir_all(&dir);
    let path = dir.join("input.vrt");
    if std::fs::write(&path, data).is_err() {
        return;
    }
    if let Ok(vrt) = read_vrt(&path) {
        for source in &vrt.sources {
            assert!(source.path.is_file(), "a source that is not a file was accepted");
            assert!(source.pixel.0 > 0.0 && source.pixel.1 > 0.0, "a degenerate pixel was accepted");
        }
    }
});
