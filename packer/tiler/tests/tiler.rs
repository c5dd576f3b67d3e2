//! `tile`: a generated int16 GeoTIFF (geographic, with nodata) -> pyramid: LOD counts and
//! extents, exact LOD-0 round trip, borders equal the neighbours' interior samples, nodata
//! tiles missing, georeference in the metadata.
#![allow(clippy::unwrap_used, clippy::expect_used, clippy::cast_possible_truncation, missing_docs)]

use terrastream_format::{ElevationScheme, Reader, TileKey};
use terrastream_pack::progress::Silent;
use terrastream_tiler::{ElevationStorage, TileOptions, read_geotiff, tile_elevation};
use tiff::encoder::{TiffEncoder, colortype::GrayI16};
use tiff::tags::Tag;

const W: u32 = 100;
const H: u32 = 70;
const NODATA: i16 = -32767;

fn height(x: u32, y: u32) -> i16 {
    // Nodata on the right-hand strip x >= 80.
    if x >= 80 { NODATA } else { (x as i16) * 3 - (y as i16) * 2 + 100 }
}

fn write_dem(path: &std::path::Path) {
    let data: Vec<i16> = (0..H).flat_map(|y| (0..W).map(move |x| height(x, y))).collect();
    let mut tiff = TiffEncoder::new(std::fs::File::create(path).unwrap()).unwrap();
    let mut image = tiff.new_image::<GrayI16>(W, H).unwrap();
    let enc = image.encoder();
    // Square pixels at the equator: 1/3600 degree.
    enc.write_tag(Tag::Unknown(33550), &[1.0 / 3600.0, 1.0 / 3600.0, 0.0][..]).unwrap();
    enc.write_tag(Tag::Unknown(33922), &[0.0, 0.0, 0.0, 10.0, 0.01, 0.0][..]).unwrap();
    enc.write_tag(Tag::Unknown(34735), &[1u16, 1, 0, 2, 1024, 0, 1, 2, 2048, 0, 1, 4326][..]).unwrap();
    enc.write_tag(Tag::Unknown(42113), "-32767").unwrap();
    image.write_data(&data).unwrap();
}

#[test]
fn a_geotiff_becomes_a_pyramid_with_borders_nodata_and_georeference() {
    let dir = tempfile::tempdir().unwrap();
    let tif = dir.path().join("dem.tif");
    write_dem(&tif);
    let raster = read_geotiff(&tif).unwrap();
    assert_eq!((raster.width, raster.height), (W, H));
    assert!((raster.spacing.0 / raster.spacing.1 - 1.0).abs() < 0.01, "{:?}", raster.spacing);
    let out = dir.path().join("dem.tspack");
    let options = TileOptions { tile_size: 16, border: 2, storage: ElevationStorage::Auto };
    tile_elevation(&raster, "dem", &out, options, &Silent::default()).unwrap();
    let reader = Reader::open_mmap(&out).unwrap();
    let meta = reader.metadata();
    let layer = &meta.layers[0];
    // 100 x 70 samples in 16-sample tiles: 7 x 5 at LOD 0, down to 1 x 1 at LOD 3.
    assert_eq!((layer.num_x_tiles, layer.num_y_tiles, layer.num_lods), (7, 5, 4));
    let enc = layer.elevation.unwrap();
    assert_eq!(enc.scheme, ElevationScheme::QuantizedU16);
    let g = meta.georeference.as_ref().unwrap();
    assert_eq!(g.crs.as_deref(), Some("EPSG:4326"));
    let b = g.lat_lon_bounds.unwrap();
    assert!((b[0] - 10.0).abs() < 1e-9 && (b[3] - 0.01).abs() < 1e-9, "{b:?}");
    assert!((meta.terrain.min_elevation - f64::from(100 - 2 * 69)).abs() < 1e-9);

    let edge = 16 + 2 * 2;
    let sample = |key: TileKey, i: i64, j: i64| -> Option<f64> {
        let raw = reader.tile(key).unwrap()?;
        let bytes = terrastream_format::payload_bytes(&meta.layers[0], &raw, "t").unwrap();
        let at = ((j + 2) * edge + i + 2) as usize * 2;
        let q = u16::from_le_bytes([bytes[at], bytes[at + 1]]);
        Some(if q == 0 { f64::NAN } else { enc.offset + f64::from(q) * enc.scale })
    };
    // LOD 0 is exact, borders included, and a border sample equals the neighbour's interior.
    for (tx, ty) in [(0u32, 0u32), (2, 3), (4, 1)] {
        let key = TileKey::new(0, 0, tx, ty).unwrap();
        for (i, j) in [(0i64, 0i64), (15, 15), (7, 3), (-1, 5), (16, 9), (-2, -2)] {
            let (x, y) = (i64::from(tx) * 16 + i, i64::from(ty) * 16 + j);
            let got = sample(key, i, j).unwrap();
            if x < 0 || y < 0 || x >= i64::from(W) || y >= i64::from(H) || height(x as u32, y as u32) == NODATA {
                assert!(got.is_nan(), "outside the raster is nodata");
            } else {
                assert_eq!(got, f64::from(height(x as u32, y as u32)), "tile ({tx},{ty}) sample ({i},{j})");
            }
        }
        let right = TileKey::new(0, 0, tx + 1, ty).unwrap();
        if let Some(r) = sample(right, 0, 4) {
            assert_eq!(sample(key, 16, 4).unwrap().to_bits(), r.to_bits(), "border = neighbour's interior");
        }
    }
    // The strip x >= 80 is nodata: LOD-0 tiles x = 5 (80..96) and 6 are missing.
    assert!(reader.tile(TileKey::new(0, 0, 5, 0).unwrap()).unwrap().is_none());
    assert!(reader.tile(TileKey::new(0, 0, 6, 4).unwrap()).unwrap().is_none());
    assert!(reader.tile(TileKey::new(0, 0, 4, 4).unwrap()).unwrap().is_some());
    // LOD 1 averages 2x2: sample (0,0) of tile (0,0) = mean of the four finest samples.
    let want =
        (f64::from(height(0, 0)) + f64::from(height(1, 0)) + f64::from(height(0, 1)) + f64::from(height(1, 1))) / 4.0;
    let got = sample(TileKey::new(0, 1, 0, 0).unwrap(), 0, 0).unwrap();
    assert!((got - want).abs() <= enc.scale / 2.0, "{got} vs {want}");
    assert!(reader.tile(TileKey::new(0, 3, 0, 0).unwrap()).unwrap().is_some());
}

#[test]
fn unreadable_input_names_the_file() {
    let dir = tempfile::tempdir().unwrap();
    let bad = dir.path().join("bad.tif");
    std::fs::write(&bad, b"II*\0garbage").unwrap();
    let err = read_geotiff(&bad).unwrap_err().to_string();
    assert!(err.contains("bad.tif"), "{err}");
}
