//! Any bytes as the tiler's inputs: an elevation raster (GeoTIFF or PNG, every encoding)
//! and an image (GeoTIFF, PNG, JPEG), read row by row. Must never panic, and must not
//! allocate from sizes the file claims without reading the data behind them.
#![no_main]

use libfuzzer_sys::fuzz_target;
use terrastream_format::{ElevationEncoding, ElevationScheme};
use terrastream_raster::{ElevationSource, ImageSource, open_elevation, open_image};

/// Rows read per input at most: enough to cross strips and tile rows, quick per run.
const ROWS: usize = 64;

fuzz_target!(|data: &[u8]| {
    let dir = std::env::temp_dir().join(format!("terrastream-fuzz-rasters-{}", std::process::id()));
    let _ = std::fs::create_dir_all(&dir);
    let path = dir.join("input");
    if std::fs::write(&path, data).is_err() {
        return;
    }
    let stop = || terrastream_raster::Error::Interrupted(terrastream_format::Interrupted);
    let encodings = [None, Some(ElevationScheme::TerrainRgb), Some(ElevationScheme::Terrarium), Some(ElevationScheme::Gray8)];
    for scheme in encodings {
        let encoding = scheme.map(|scheme| ElevationEncoding { scheme, scale: 1.0, offset: 0.0, nodata: None });
        if let Ok(dem) = open_elevation(&path, encoding) {
            let mut n = 0;
            let _ = dem.rows(&mut |row| {
                assert_eq!(row.len(), dem.size().0 as usize);
                n += 1;
                if n >= ROWS { Err(stop()) } else { Ok(()) }
            });
        }
    }
    if let Ok(image) = open_image(&path) {
        let mut n = 0;
        let _ = image.rows(&mut |row| {
            assert_eq!(row.len(), image.size().0 as usize);
            n += 1;
            if n >= ROWS { Err(stop()) } else { Ok(()) }
        });
    }
});
