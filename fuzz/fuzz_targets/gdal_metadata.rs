//! Any text as GDAL's metadata tag (GDAL_METADATA, 42112) of an input GeoTIFF, read for the
//! exact statistics a plan takes the height range from. Must never panic; what it accepts
//! is a finite minimum no larger than the maximum.
#![no_main]

use libfuzzer_sys::fuzz_target;
use terrastream_raster::gdal_statistics_in;

fuzz_target!(|data: &[u8]| {
    let Ok(xml) = std::str::from_utf8(data) else { return };
    if let Some((min, max)) = gdal_statistics_in(xml) {
        assert!(min.is_finite() && max.is_finite() && min <= max, "accepted {min} .. {max}");
    }
});
