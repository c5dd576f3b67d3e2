//! Longitude and latitude <-> world coordinates: a DEM in EPSG:4326 tiled, then asked for
//! heights at longitudes and latitudes, which must be the DEM's own there.
#![allow(clippy::unwrap_used, clippy::expect_used, clippy::cast_possible_truncation, missing_docs)]

use std::path::Path;

use terrastream_client::{Geo, Origin, StreamOptions, Streamer};
use terrastream_format::MmapSource;
use terrastream_pack::progress::Silent;
use terrastream_tiler::{ElevationSource, TileOptions, open_elevation, read_geotiff, tile_elevation};

#[test]
fn heights_are_found_at_longitudes_and_latitudes() {
    let dem = Path::new(env!("CARGO_MANIFEST_DIR")).join("../packer/pack/data/srtm-tamalpais-320-public-domain.tif");
    let dir = tempfile::tempdir().unwrap();
    let out = dir.path().join("t.tspack");
    let file = open_elevation(&dem, None).unwrap();
    tile_elevation(&file, "t", &out, TileOptions::default(), &Silent::default()).unwrap();
    let raster = read_geotiff(&dem).unwrap();
    let origin = file.georeference().unwrap().origin.unwrap();
    let (step, _) = file.crs_pixel_size().unwrap();

    let mut streamer =
        Streamer::open(Origin::archive(MmapSource::open(&out).unwrap()), StreamOptions::default()).unwrap();
    let metadata = streamer.metadata().unwrap().clone();
    let g = metadata.georeference.as_ref().unwrap();
    assert!(g.definition.as_deref().unwrap().contains("+proj=longlat"), "{g:?}");
    let geo = Geo::new(&metadata).expect("the archive records where it lies");

    let mut errors = Vec::new();
    for (i, j) in [(40, 40), (160, 100), (250, 60), (100, 250), (300, 300), (20, 290), (200, 200), (120, 30)] {
        let (lon, lat) = (origin[0] + (f64::from(i) + 0.5) * step, origin[1] - (f64::from(j) + 0.5) * step);
        let (x, z) = geo.lon_lat_to_world(lon, lat).unwrap();
        let back = geo.world_to_lon_lat(x, z).unwrap();
        assert!((back.0 - lon).abs() < 1e-9 && (back.1 - lat).abs() < 1e-9, "{lon},{lat} came back as {back:?}");
        let expected = raster.data[(j * raster.width + i) as usize];
        if expected.is_nan() {
            continue;
        }
        let h = streamer.height_at_exact(x, z).unwrap().unwrap();
        errors.push((h - f64::from(expected)).abs());
    }
    errors.sort_by(f64::total_cmp);
    // The geographic DEM is resampled along x to square samples: heights at a sample's
    // centre come back interpolated, within a few metres on this terrain.
    assert!(errors.len() >= 5, "too few points on land");
    assert!(errors[errors.len() / 2] < 3.0, "median height error {:?}", errors);
    assert!(streamer.height_at_lon_lat(-10.0, 10.0).is_none(), "a point far outside has no height");
}
