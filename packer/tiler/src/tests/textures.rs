//! Texture tiles: their formats, square texels, imagery cut to the elevation.

use super::*;

fn decode_texture(format: TextureFormat, bytes: &[u8], edge: usize) -> Vec<[u8; 4]> {
    match format {
        TextureFormat::Png => {
            let (_, rgba) = decode_png(bytes);
            rgba.chunks_exact(4).map(|p| [p[0], p[1], p[2], p[3]]).collect()
        }
        TextureFormat::Jpeg(_) => {
            let mut d = zune_jpeg::JpegDecoder::new(bytes);
            d.decode().unwrap().chunks_exact(3).map(|p| [p[0], p[1], p[2], 255]).collect()
        }
        TextureFormat::Webp => {
            let mut d = image_webp::WebPDecoder::new(std::io::Cursor::new(bytes)).unwrap();
            let mut buf = vec![0; d.output_buffer_size().unwrap()];
            d.read_image(&mut buf).unwrap();
            let channels = if d.has_alpha() { 4 } else { 3 };
            buf.chunks_exact(channels).map(|p| [p[0], p[1], p[2], if channels == 4 { p[3] } else { 255 }]).collect()
        }
        TextureFormat::Bc1 | TextureFormat::Bc7 => {
            let raw = terrastream_format::zstd_decompress(bytes, 1 << 20, "tile").unwrap();
            let blocks = edge.div_ceil(4);
            let size = if format == TextureFormat::Bc1 { 8 } else { 16 };
            let mut texels = vec![[0u8; 4]; edge * edge];
            for (b, block) in raw.chunks_exact(size).enumerate() {
                let decoded = if format == TextureFormat::Bc1 {
                    bc::tests::decode_bc1(block)
                } else {
                    bc::tests::decode_bc7_mode6(block)
                };
                for (i, t) in decoded.iter().enumerate() {
                    let (x, y) = ((b % blocks) * 4 + i % 4, (b / blocks) * 4 + i / 4);
                    if x < edge && y < edge {
                        texels[y * edge + x] = *t;
                    }
                }
            }
            texels
        }
    }
}

#[test]
fn texture_formats_store_tiles_that_decode_close_to_the_image() {
    let dir = tempfile::tempdir().unwrap();
    // A smooth 64x64 opaque image alone (no elevation): 2 m pixels.
    let pixels: Vec<u8> = (0..64u32 * 64)
        .flat_map(|i| {
            let (x, y) = (i % 64, i / 64);
            [(x * 3 + 20) as u8, (y * 3 + 10) as u8, (200 - x - y) as u8, 255]
        })
        .collect();
    let image = Image { width: 64, height: 64, rgba: pixels, georeference: None };
    let options = TileOptions { tile_size: 32, border: 1, ..TileOptions::default() };
    for (format, tolerance) in [
        (TextureFormat::Png, 0.0),
        (TextureFormat::Webp, 0.0),
        (TextureFormat::Jpeg(90), 3.0),
        (TextureFormat::Bc1, 4.0),
        (TextureFormat::Bc7, 2.0),
    ] {
        let out = dir.path().join(format!("{format:?}.tspack"));
        let t = TextureInput { source: &image, tile_size: 32, format, pixel_size: 2.0 };
        tile_terrain(None, Some(t), "img", &out, options, &Silent::default()).unwrap();
        let reader = Reader::open_mmap(&out).unwrap();
        let layer = &reader.metadata().layers[0];
        assert_eq!(reader.metadata().layers.len(), 1, "texture only");
        assert_eq!((layer.format, layer.num_x_tiles, layer.num_lods), (format.tile_format(), 2, 2));
        assert!((layer.tile_world_size - 64.0).abs() < 1e-9);
        let bytes = reader.tile(TileKey::new(0, 0, 1, 1).unwrap()).unwrap().unwrap();
        let texels = decode_texture(format, &bytes, 34);
        assert_eq!(texels.len(), 34 * 34, "{format:?}");
        // Mean absolute error over the interior against the source pixels.
        let mut sum = 0.0;
        for j in 1..33 {
            for i in 1..33 {
                let (x, y) = (32 + i - 1, 32 + j - 1);
                let want = &image.rgba[(y * 64 + x) * 4..][..3];
                let got = texels[j * 34 + i];
                sum += (0..3).map(|c| f64::from(got[c].abs_diff(want[c]))).sum::<f64>();
            }
        }
        let mean = sum / (32.0 * 32.0 * 3.0);
        assert!(mean <= tolerance, "{format:?}: mean error {mean} > {tolerance}");
    }
}

#[test]
fn a_texture_on_the_dem_grid_is_resampled_to_square_texels() {
    // A DEM with pixels twice as wide in degrees as in metres (a geographic grid), and
    // a texture on that same grid: accepted, resampled along x to square texels.
    let dir = tempfile::tempdir().unwrap();
    let image_path = dir.path().join("grid.png");
    png_file(&image_path, 64, 32, &vec![200; 64 * 32 * 4]);
    let image = open_image(&image_path).unwrap();
    let mut elevation = raster(100, 50, |_, _| 1.0);
    elevation.spacing = (15.0, 30.0);
    let out = dir.path().join("g.tspack");
    let options = TileOptions { tile_size: 16, ..TileOptions::default() };
    tile_terrain(
        Some(&elevation),
        Some(texture(&image, 16, TextureFormat::Png)),
        "g",
        &out,
        options,
        &Silent::default(),
    )
    .unwrap();
    let reader = Reader::open_mmap(&out).unwrap();
    let t = &reader.metadata().layers[1];
    // 1500 x 1500 m: 32 x 32 texels of 46.875 m.
    assert_eq!((t.num_x_tiles, t.num_y_tiles), (2, 2));
    assert!((t.tile_world_size - 750.0).abs() < 1e-9, "{}", t.tile_world_size);
}

#[test]
fn a_wider_georeferenced_texture_is_cut_to_the_elevation() {
    let dir = tempfile::tempdir().unwrap();
    let dem_path = dir.path().join("dem.tif");
    // 20 x 10 samples of 0.01 degrees from (-106.0, 40.5): to -105.8 east, 40.4 south.
    geotiff(&dem_path, (20, 10), [-106.0, 40.5], 0.01, None);
    let dem = open_elevation(&dem_path, None).unwrap();
    // A 60 x 40 image of 0.005 degrees from (-106.05, 40.55); red = column, green = row.
    let (iw, ih) = (60u32, 40u32);
    let pixels: Vec<u8> = (0..ih).flat_map(|y| (0..iw).flat_map(move |x| [x as u8, y as u8, 7])).collect();
    let image_path = dir.path().join("image.tif");
    geotiff(&image_path, (iw, ih), [-106.05, 40.55], 0.005, Some(&pixels));
    let image = open_image(&image_path).unwrap();
    let window = ImageWindow::over(&dem, &image).unwrap().expect("a window");
    assert_eq!(window.bounds(), (10, 10, 40, 20));
    let origin = window.georeference().unwrap().origin.unwrap();
    assert!((origin[0] + 106.0).abs() < 1e-9 && (origin[1] - 40.5).abs() < 1e-9, "{origin:?}");
    let mut rows = Vec::new();
    window
        .rows(&mut |r| {
            rows.push(r.to_vec());
            Ok(())
        })
        .unwrap();
    assert_eq!(rows.len(), 20);
    assert!(rows.iter().all(|r| r.len() == 40));
    assert_eq!((rows[0][0], rows[19][39]), ([10, 10, 7, 255], [49, 29, 7, 255]));
    // Tiled with the window: the texture's LOD 0 is the window's 20 rows, its columns
    // resampled to square texels in metres (0.005 deg is 424 x 553 m here): 31 x 20 px.
    let out = dir.path().join("t.tspack");
    let input = TextureInput { source: &window, tile_size: 16, format: TextureFormat::Png, pixel_size: 1.0 };
    let options = TileOptions { tile_size: 16, border: 0, storage: ElevationStorage::Auto };
    tile_terrain(Some(&dem), Some(input), "t", &out, options, &Silent::default()).unwrap();
    let reader = Reader::open_mmap(&out).unwrap();
    let t = reader.metadata().layers.iter().find(|l| l.kind == LayerKind::Texture).unwrap();
    assert_eq!((t.num_x_tiles, t.num_y_tiles), (2, 2));
    let lod0 = t.tile_world_size / 16.0;
    assert!((lod0 - 553.0).abs() < 5.0, "texel {lod0} m");

    // The whole image exactly over the DEM: no window needed.
    let exact = dir.path().join("exact.tif");
    let small: Vec<u8> = vec![9; 40 * 20 * 3];
    geotiff(&exact, (40, 20), [-106.0, 40.5], 0.005, Some(&small));
    assert!(ImageWindow::over(&dem, &open_image(&exact).unwrap()).unwrap().is_none());
    // An image that misses part of the DEM: named, with where the DEM would lie.
    let short = dir.path().join("short.tif");
    geotiff(&short, (30, 40), [-106.05, 40.55], 0.005, Some(&vec![1; 30 * 40 * 3]));
    let e = ImageWindow::over(&dem, &open_image(&short).unwrap()).unwrap_err().to_string();
    assert!(e.contains("short.tif") && e.contains("mismatched extents") && e.contains("10.0..50.0"), "{e}");
    // No georeference on one side (a PNG): not matched by place.
    let png_path = dir.path().join("plain.png");
    png_file(&png_path, 8, 4, &[5; 8 * 4 * 4]);
    assert!(ImageWindow::over(&dem, &open_image(&png_path).unwrap()).unwrap().is_none());
}
