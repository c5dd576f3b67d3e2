//! Reading rasters: formats, layouts, damaged and misplaced inputs named.

use super::*;

#[test]
fn a_texture_of_another_shape_is_refused_and_nothing_written() {
    let dir = tempfile::tempdir().unwrap();
    let image_path = dir.path().join("wide.png");
    png_file(&image_path, 64, 32, &vec![255; 64 * 32 * 4]);
    let image = open_image(&image_path).unwrap();
    let out = dir.path().join("t.tspack");
    let err = tile_terrain(
        Some(&raster(50, 50, |_, _| 1.0)),
        Some(texture(&image, 16, TextureFormat::Png)),
        "t",
        &out,
        TileOptions::default(),
        &Silent::default(),
    )
    .unwrap_err();
    let text = err.to_string();
    assert!(text.contains("wide.png") && text.contains("mismatched extents"), "{text}");
    assert!(!out.exists());
    assert_eq!(std::fs::read_dir(dir.path()).unwrap().count(), 1, "no temporary file left behind");
}

#[test]
fn images_are_read_from_tiff_and_png_and_bad_ones_named() {
    let dir = tempfile::tempdir().unwrap();
    // An RGB TIFF.
    let tif = dir.path().join("rgb.tif");
    {
        let file = std::fs::File::create(&tif).unwrap();
        let mut encoder = tiff::encoder::TiffEncoder::new(file).unwrap();
        let rgb: Vec<u8> = (0..6u8 * 4 * 3).collect();
        encoder.write_image::<tiff::encoder::colortype::RGB8>(6, 4, &rgb).unwrap();
    }
    let image = read_image(&tif).unwrap();
    assert_eq!((image.width, image.height), (6, 4));
    assert_eq!(&image.rgba[..8], &[0, 1, 2, 255, 3, 4, 5, 255]);
    // Not an image; a truncated PNG; an empty file.
    let junk = dir.path().join("junk.png");
    std::fs::write(&junk, b"hello").unwrap();
    let e = read_image(&junk).unwrap_err().to_string();
    assert!(e.contains("junk.png") && e.contains("not a GeoTIFF, PNG or JPEG"), "{e}");
    let png_path = dir.path().join("cut.png");
    png_file(&png_path, 8, 8, &[7; 8 * 8 * 4]);
    let bytes = std::fs::read(&png_path).unwrap();
    std::fs::write(&png_path, &bytes[..bytes.len() / 2]).unwrap();
    let e = read_image(&png_path).unwrap_err().to_string();
    assert!(e.contains("cut.png") && e.contains("PNG"), "{e}");
    let empty = dir.path().join("empty.tif");
    std::fs::write(&empty, b"").unwrap();
    let e = open_elevation(&empty, None).unwrap_err().to_string();
    assert!(e.contains("empty.tif") && e.contains("empty"), "{e}");
}

#[test]
fn bad_elevation_inputs_are_named_and_nothing_is_written() {
    let dir = tempfile::tempdir().unwrap();
    // An RGB TIFF is not a band of heights.
    let rgb = dir.path().join("photo.tif");
    {
        let file = std::fs::File::create(&rgb).unwrap();
        let mut encoder = tiff::encoder::TiffEncoder::new(file).unwrap();
        encoder.write_image::<tiff::encoder::colortype::RGB8>(4, 4, &[9; 48]).unwrap();
    }
    let e = open_elevation(&rgb, None).unwrap_err().to_string();
    assert!(e.contains("photo.tif") && e.contains("single band"), "{e}");
    // A truncated GeoTIFF: opens, then fails on its strips, naming the file; nothing written.
    let cut = dir.path().join("cut.tif");
    let bytes = std::fs::read(repo_data("srtm-tamalpais-150x100-strips-int16-public-domain.tif")).unwrap();
    std::fs::write(&cut, &bytes[..bytes.len() * 2 / 3]).unwrap();
    let out = dir.path().join("cut.tspack");
    let e = match open_elevation(&cut, None) {
        Err(e) => e.into(),
        Ok(source) => tile_elevation(&source, "cut", &out, TileOptions::default(), &Silent::default()).unwrap_err(),
    }
    .to_string();
    assert!(e.contains("cut.tif"), "{e}");
    assert!(!out.exists());
    // An 8-bit PNG needs an encoding; a JPEG is refused as lossy.
    let gray = dir.path().join("gray.png");
    png_with(&gray, 4, 4, png::ColorType::Grayscale, png::BitDepth::Eight, &[1; 16]);
    let e = open_elevation(&gray, None).unwrap_err().to_string();
    assert!(e.contains("gray.png") && e.contains("gray8"), "{e}");
    let jpeg = dir.path().join("dem.jpg");
    std::fs::write(&jpeg, [0xFF, 0xD8, 0xFF, 0xE0, 0, 0]).unwrap();
    let e = open_elevation(&jpeg, None).unwrap_err().to_string();
    assert!(e.contains("dem.jpg") && e.contains("lossy"), "{e}");
    // A raster of nodata only.
    let none = raster(20, 20, |_, _| f32::NAN);
    let e = tile_elevation(&none, "none", &out, TileOptions::default(), &Silent::default()).unwrap_err().to_string();
    assert!(e.contains("no data"), "{e}");
    assert_eq!(std::fs::read_dir(dir.path()).unwrap().count(), 4, "only the inputs are left");
}

#[test]
fn tiled_and_striped_geotiffs_read_the_same() {
    let tiled = open_elevation(&repo_data("srtm-tamalpais-150x100-tiled-float32-public-domain.tif"), None).unwrap();
    let strips = open_elevation(&repo_data("srtm-tamalpais-150x100-strips-int16-public-domain.tif"), None).unwrap();
    assert_eq!(tiled.size(), (150, 100));
    let (a, b) = (read_geotiff(tiled.path()).unwrap(), read_geotiff(strips.path()).unwrap());
    assert_eq!(a.data.len(), 15_000);
    let same = a.data.iter().zip(&b.data).all(|(x, y)| x.to_bits() == y.to_bits() || (x.is_nan() && y.is_nan()));
    assert!(same, "64x32 LZW float32 tiles and 7-row Deflate int16 strips differ");
    let (lo, hi) = a.data.iter().fold((f32::MAX, f32::MIN), |(l, h), &v| (l.min(v), h.max(v)));
    assert_eq!((lo, hi), (148.0, 464.0), "the heights gdalinfo reports");
    assert_eq!(a.georeference, b.georeference);
}

#[test]
fn a_pixel_is_point_raster_is_placed_by_its_corner_as_gdal_reads_it() {
    // SRTM marks its tiepoint as a sample's centre (GTRasterTypeGeoKey = PixelIsPoint): the
    // raster's corner is half a sample further out. gdalinfo reports the upper-left corner
    // of all three fixtures as (-122.6418056, 37.9668056).
    for name in SRTM_FIXTURES {
        let file = open_elevation(&repo_data(name), None).unwrap();
        let g = file.georeference().unwrap();
        let [west, north] = g.origin.unwrap();
        assert!((west + 122.641_805_6).abs() < 1e-7 && (north - 37.966_805_6).abs() < 1e-7, "{name}: {west}, {north}");
        let bounds = g.lat_lon_bounds.unwrap();
        let (w, h) = file.size();
        let step = 1.0 / 3600.0;
        assert!((bounds[2] - (west + f64::from(w) * step)).abs() < 1e-9, "{name}: {bounds:?}");
        assert!((bounds[1] - (north - f64::from(h) * step)).abs() < 1e-9, "{name}: {bounds:?}");
    }
}

/// A PNG and a JPEG in a mosaic are read a strip of rows at a time from the top, on a
/// decoder thread each: the rows come out as the images hold them, also when every strip
/// must be decoded again (a cache of one chunk), and a damaged image is named.
#[test]
fn png_and_jpeg_in_a_mosaic_are_read_by_strips_of_rows() {
    let dir = tempfile::tempdir().unwrap();
    let p = |name: &str| dir.path().join(name);
    // 150 x 330: five strips of 64 rows and one of 10.
    let (w, h) = (150u32, 330u32);
    let rgb: Vec<u8> =
        (0..h).flat_map(|y| (0..w).flat_map(move |x| [(x * 7) as u8, (y * 3) as u8, (x ^ y) as u8])).collect();
    let place = |name: &str, world: &str| {
        // Pixel centres 10 m apart from (500 005, 5 000 995) in UTM 32N.
        std::fs::write(p(world), "10\n0\n0\n-10\n500005\n5000995\n").unwrap();
        std::fs::write(p(name).with_extension("prj"), "EPSG:32632").unwrap();
    };
    png_with(&p("a.png"), w, h, png::ColorType::Rgb, png::BitDepth::Eight, &rgb);
    place("a.png", "a.pgw");
    let mut jpeg = Vec::new();
    let mut encoder = jpeg_encoder::Encoder::new(&mut jpeg, 90);
    encoder.set_sampling_factor(jpeg_encoder::SamplingFactor::R_4_2_0);
    encoder.encode(&rgb, w as u16, h as u16, jpeg_encoder::ColorType::Rgb).unwrap();
    std::fs::write(p("b.jpg"), &jpeg).unwrap();
    place("b.jpg", "b.jgw");
    let rgba = |rows: &[u8]| rows.chunks_exact(3).map(|c| [c[0], c[1], c[2], 255]).collect::<Vec<_>>();
    let mut jpeg_rgb = Vec::new();
    jpeg_rows(&p("b.jpg"), &mut |r| {
        jpeg_rgb.extend_from_slice(r);
        Ok(())
    })
    .unwrap();
    for cache_bytes in [None, Some(1)] {
        let options = MosaicOptions { crs: Some(Crs::epsg(32632).unwrap()), cache_bytes, ..MosaicOptions::default() };
        for (image, expected) in [("a.png", rgba(&rgb)), ("b.jpg", rgba(&jpeg_rgb))] {
            let mosaic = Mosaic::<Pixels>::open(&[p(image)], &options).unwrap();
            assert_eq!(ImageSource::size(&mosaic), (w, h), "{image}: on the image's own grid");
            let mut made = Vec::new();
            ImageSource::rows(&mosaic, &mut |r| {
                made.extend_from_slice(r);
                Ok(())
            })
            .unwrap();
            assert!(made == expected, "{image}, cache {cache_bytes:?}: the mosaic's rows are not the image's");
            // A band further down alone, then one above it.
            for rows in [200..330, 10..140] {
                let mut band = Vec::new();
                ImageSource::rows_in(&mosaic, rows.clone(), &mut |r| {
                    band.extend_from_slice(r);
                    Ok(())
                })
                .unwrap();
                let (a, b) = (rows.start as usize * w as usize, rows.end as usize * w as usize);
                assert!(band == expected[a..b], "{image}, cache {cache_bytes:?}, rows {rows:?}");
            }
        }
    }
    // The JPEG cut short: its rows stop with an error naming it.
    std::fs::write(p("b.jpg"), &jpeg[..jpeg.len() / 2]).unwrap();
    let options = MosaicOptions { crs: Some(Crs::epsg(32632).unwrap()), ..MosaicOptions::default() };
    let mosaic = Mosaic::<Pixels>::open(&[p("b.jpg")], &options).unwrap();
    let err = ImageSource::rows(&mosaic, &mut |_| Ok(())).unwrap_err().to_string();
    eprintln!("{err}");
    assert!(err.contains("b.jpg"), "{err}");
}
