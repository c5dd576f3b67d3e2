#![allow(clippy::unwrap_used, clippy::cast_possible_truncation, clippy::cast_sign_loss, clippy::cast_precision_loss)]

use std::path::{Path, PathBuf};

use terrastream_format::{ElevationEncoding, ElevationScheme, LayerKind, Reader, TileFormat, TileKey};
use terrastream_pack::progress::Silent;

use super::*;
use crate::plan::min_max;
use crate::pyramid::*;

fn raster(width: u32, height: u32, f: impl Fn(u32, u32) -> f32) -> Raster {
    let data = (0..height).flat_map(|y| (0..width).map(move |x| (x, y))).map(|(x, y)| f(x, y)).collect();
    Raster { width, height, data, spacing: (30.0, 30.0), georeference: None }
}

fn repo_data(name: &str) -> PathBuf {
    // The 320-sample crop is the built-in demo DEM, kept beside the built-in sample.
    let folder = if name == "srtm-tamalpais-320-public-domain.tif" { "../pack/data" } else { "../../tests/data" };
    Path::new(env!("CARGO_MANIFEST_DIR")).join(folder).join(name)
}

fn png_file(path: &Path, width: u32, height: u32, rgba: &[u8]) {
    png_with(path, width, height, png::ColorType::Rgba, png::BitDepth::Eight, rgba);
}

fn png_with(path: &Path, width: u32, height: u32, colour: png::ColorType, depth: png::BitDepth, data: &[u8]) {
    let file = std::io::BufWriter::new(std::fs::File::create(path).unwrap());
    let mut encoder = png::Encoder::new(file, width, height);
    encoder.set_color(colour);
    encoder.set_depth(depth);
    encoder.write_header().unwrap().write_image_data(data).unwrap();
}

fn decode_png(bytes: &[u8]) -> (u32, Vec<u8>) {
    let mut decoder = png::Decoder::new(std::io::Cursor::new(bytes));
    decoder.set_transformations(png::Transformations::EXPAND | png::Transformations::ALPHA);
    let mut reader = decoder.read_info().unwrap();
    let mut buf = vec![0; reader.output_buffer_size().unwrap()];
    let info = reader.next_frame(&mut buf).unwrap();
    buf.truncate(info.buffer_size());
    (info.width, buf)
}

/// A 64x64 texture: (x*4, y*4, x+y, 255), transparent where x, y >= 48.
fn texture_pixels() -> Vec<u8> {
    (0..64u32)
        .flat_map(|y| (0..64u32).map(move |x| (x, y)))
        .flat_map(|(x, y)| if x >= 48 && y >= 48 { [0; 4] } else { [(x * 4) as u8, (y * 4) as u8, (x + y) as u8, 255] })
        .collect()
}

fn texture(source: &dyn ImageSource, tile_size: u32, format: TextureFormat) -> TextureInput<'_> {
    TextureInput { source, tile_size, format, pixel_size: 1.0 }
}

/// Heights of an elevation tile (NaN for nodata), decoded as a client would.
fn heights(reader: &Reader<terrastream_format::MmapSource>, key: TileKey) -> Option<Vec<f64>> {
    let layer = &reader.metadata().layers[usize::from(key.layer())];
    let enc = layer.elevation.unwrap();
    let stored = reader.tile(key).unwrap()?;
    let raw = terrastream_format::payload_bytes(layer, &stored, "tile").unwrap();
    Some(if layer.format == TileFormat::RawF32 {
        raw.chunks_exact(4).map(|c| f64::from(f32::from_le_bytes([c[0], c[1], c[2], c[3]]))).collect()
    } else {
        raw.chunks_exact(2)
            .map(|c| u16::from_le_bytes([c[0], c[1]]))
            .map(|q| if q == 0 { f64::NAN } else { enc.height(f64::from(q)) })
            .collect()
    })
}

#[test]
fn texture_pyramid_is_aligned_bordered_averaged_and_sparse() {
    let dir = tempfile::tempdir().unwrap();
    let image_path = dir.path().join("ortho.png");
    png_file(&image_path, 64, 64, &texture_pixels());
    let image = open_image(&image_path).unwrap();
    assert_eq!(image.size(), (64, 64));
    let out = dir.path().join("t.tspack");
    let elevation = raster(100, 100, |x, y| (x + y) as f32);
    let options = TileOptions { tile_size: 32, border: 1, storage: ElevationStorage::Auto };
    let t = texture(&image, 16, TextureFormat::Png);
    tile_terrain(Some(&elevation), Some(t), "t", &out, options, &Silent::default()).unwrap();
    let reader = Reader::open_mmap(&out).unwrap();
    let m = reader.metadata();
    assert_eq!(m.layers.len(), 3, "elevation, texture, elevation range");
    let t = &m.layers[1];
    assert_eq!(
        (t.kind, t.format, t.num_x_tiles, t.num_y_tiles, t.num_lods),
        (LayerKind::Texture, TileFormat::Png, 4, 4, 3)
    );
    // The same world extent: 100 samples of 30 m = 64 texels of 46.875 m.
    assert!((t.tile_world_size * 4.0 - 3000.0).abs() < 1e-9, "{}", t.tile_world_size);
    let tile =
        |lod: u8, x: u32, y: u32| reader.tile(TileKey::new(1, lod, x, y).unwrap()).unwrap().map(|b| decode_png(&b));
    let px = |tile: &(u32, Vec<u8>), i: u32, j: u32| {
        let k = ((j * tile.0 + i) * 4) as usize;
        [tile.1[k], tile.1[k + 1], tile.1[k + 2], tile.1[k + 3]]
    };
    let (a, b) = (tile(0, 0, 0).unwrap(), tile(0, 1, 0).unwrap());
    assert_eq!(a.0, 18, "16 px + a border of 1 on each side");
    for j in 1..17 {
        // b's left border column is a's last interior column, and the other way round.
        assert_eq!(px(&b, 0, j), px(&a, 16, j), "row {j}");
        assert_eq!(px(&a, 17, j), px(&b, 1, j), "row {j}");
    }
    // A bottom border row is the next tile's first interior row.
    let below = tile(0, 0, 1).unwrap();
    assert_eq!(px(&a, 5, 17), px(&below, 5, 1));
    assert_eq!(px(&a, 1, 1), [0, 0, 0, 255], "interior starts at texel (0, 0)");
    // LOD 1: each texel the mean of 2x2 (here of (0,0), (1,0), (0,1), (1,1)).
    let c = tile(1, 0, 0).unwrap();
    assert_eq!(px(&c, 1, 1), [2, 2, 1, 255]);
    // The transparent corner tile is left out; its coarser parents exist.
    assert!(tile(0, 3, 3).is_none());
    assert!(tile(0, 2, 3).is_some() && tile(1, 1, 1).is_some() && tile(2, 0, 0).is_some());
}

/// A reference pyramid: the whole raster halved level by level.
fn reference_levels(r: &Raster, lods: usize) -> Vec<Raster> {
    let mut levels = vec![r.clone()];
    while levels.len() < lods {
        let prev = levels.last().unwrap();
        let rows: Vec<&[f32]> = prev.data.chunks_exact(prev.width as usize).collect();
        let mut data = Vec::new();
        for pair in rows.chunks(2) {
            let none = vec![f32::NAN; prev.width as usize];
            data.extend(halve_rows(pair[0], pair.get(1).copied().unwrap_or(&none)));
        }
        let (width, height) = (prev.width.div_ceil(2), prev.height.div_ceil(2));
        levels.push(Raster { width, height, data, spacing: prev.spacing, georeference: None });
    }
    levels
}

#[test]
fn streamed_tiles_equal_a_whole_raster_pyramid_with_borders() {
    // Tall and odd-sized, with a nodata hole: every tile of every LOD, borders included,
    // must equal the same window of a pyramid computed on the whole raster.
    let r = raster(45, 333, |x, y| {
        if (10..20).contains(&x) && (100..140).contains(&y) { f32::NAN } else { (x * 7 + y * 3) as f32 / 4.0 }
    });
    let dir = tempfile::tempdir().unwrap();
    let out = dir.path().join("tall.tspack");
    let options = TileOptions { tile_size: 16, border: 3, storage: ElevationStorage::F32 };
    tile_elevation(&r, "tall", &out, options, &Silent::default()).unwrap();
    let reader = Reader::open_mmap(&out).unwrap();
    let layer = reader.metadata().layers[0].clone();
    let levels = reference_levels(&r, usize::from(layer.num_lods));
    let edge = 16 + 2 * 3;
    let mut checked = 0;
    for (lod, level) in levels.iter().enumerate() {
        let lod = lod as u8;
        for key in layer.tiles_at(0, lod) {
            let got = heights(&reader, key);
            let want: Vec<f64> = (0..edge * edge)
                .map(|k| {
                    let (i, j) = (k % edge, k / edge);
                    let x = i64::from(key.x()) * 16 + i64::from(i) - 3;
                    let y = i64::from(key.y()) * 16 + i64::from(j) - 3;
                    if x < 0 || y < 0 || x >= i64::from(level.width) || y >= i64::from(level.height) {
                        return f64::NAN;
                    }
                    f64::from(level.data[(y * i64::from(level.width) + x) as usize])
                })
                .collect();
            let Some(got) = got else {
                let interior_has_data = (0..edge * edge).any(|k| {
                    let (i, j) = (k % edge, k / edge);
                    (3..19).contains(&i) && (3..19).contains(&j) && !want[k as usize].is_nan()
                });
                assert!(!interior_has_data, "{key} missing but has data");
                continue;
            };
            for (k, (g, w)) in got.iter().zip(&want).enumerate() {
                assert!(g.to_bits() == w.to_bits() || (g.is_nan() && w.is_nan()), "{key} sample {k}: {g} != {w}");
            }
            checked += 1;
        }
    }
    assert!(checked > 60, "{checked} tiles");
}

#[test]
fn memory_is_a_band_of_rows_per_level_whatever_the_height() {
    let metadata_for = |height: u32| {
        let r = raster(64, height, |x, y| (x + y) as f32);
        let plan = plan(
            Some(&r),
            None,
            "m",
            TileOptions { tile_size: 32, border: 2, ..TileOptions::default() },
            &Silent::default(),
        )
        .unwrap();
        (r, plan.metadata)
    };
    for height in [100, 5000] {
        let (r, metadata) = metadata_for(height);
        let dir = tempfile::tempdir().unwrap();
        let mut spool = Spool::new(dir.path()).unwrap();
        let encode = |key: TileKey, _: &[f32], _: usize| Ok(vec![(key, vec![1])]);
        let silent = Silent::default();
        let mut p = Pyramid::new(&metadata, 0, (64, height), &encode, &mut spool, &silent).unwrap();
        let mut peak = 0;
        rayon::in_place_scope(|cuts| {
            r.rows(&mut |row| {
                p.push(row.to_vec(), cuts)?;
                peak = peak.max(p.held_samples());
                Ok(())
            })
            .unwrap();
            p.finish(cuts).unwrap();
        });
        // LOD 0 holds at most 32 + 2 * 2 + 1 rows of 64; each coarser level half as wide.
        assert!(peak <= 2 * 64 * (32 + 2 * 2 + 1), "height {height}: {peak} samples held");
        assert_eq!(
            spool.tiles() as u64,
            plan(
                Some(&r),
                None,
                "m",
                TileOptions { tile_size: 32, border: 2, ..TileOptions::default() },
                &Silent::default()
            )
            .unwrap()
            .layers[0]
                .tiles
        );
    }
}

#[test]
fn height_range_tiles_hold_every_height_under_each_elevation_tile() {
    let r = raster(50, 40, |x, y| if x > 45 { f32::NAN } else { (x * x) as f32 - y as f32 * 0.5 });
    let dir = tempfile::tempdir().unwrap();
    let out = dir.path().join("r.tspack");
    tile_elevation(&r, "r", &out, TileOptions { tile_size: 16, ..TileOptions::default() }, &Silent::default()).unwrap();
    let reader = Reader::open_mmap(&out).unwrap();
    let m = reader.metadata();
    let range = m.layers.iter().position(|l| l.kind == LayerKind::HeightRange).unwrap() as u8;
    assert_eq!(m.layers[usize::from(range)].format, TileFormat::MinMaxF32);
    // Expected: the stored heights of the tile and of every tile under it, finest first.
    let mut expected: std::collections::HashMap<(u8, u32, u32), (f32, f32)> = std::collections::HashMap::new();
    let mut n = 0;
    for lod in 0..m.layers[0].num_lods {
        for key in m.layers[0].tiles_at(0, lod) {
            let range_tile = reader.tile(TileKey::new(range, key.lod(), key.x(), key.y()).unwrap()).unwrap();
            let Some(h) = heights(&reader, key) else {
                assert!(range_tile.is_none(), "{key}: no elevation, no range");
                continue;
            };
            let mut lo = h.iter().copied().filter(|v| !v.is_nan()).fold(f64::INFINITY, f64::min) as f32;
            let mut hi = h.iter().copied().filter(|v| !v.is_nan()).fold(f64::NEG_INFINITY, f64::max) as f32;
            let own = (lo, hi);
            for (dx, dy) in [(0, 0), (1, 0), (0, 1), (1, 1)] {
                if let Some(&(clo, chi)) =
                    lod.checked_sub(1).and_then(|c| expected.get(&(c, key.x() * 2 + dx, key.y() * 2 + dy)))
                {
                    lo = lo.min(clo);
                    hi = hi.max(chi);
                }
            }
            expected.insert((lod, key.x(), key.y()), (lo, hi));
            let b = range_tile.unwrap();
            assert_eq!(b.len(), 8);
            let got = (f32::from_le_bytes(b[..4].try_into().unwrap()), f32::from_le_bytes(b[4..].try_into().unwrap()));
            assert_eq!(got, (lo, hi), "{key}");
            if lod > 0 && (lo, hi) != own {
                // A coarse tile's averages miss its children's extremes: the range is wider.
                assert!(lo <= own.0 && hi >= own.1, "{key}");
                n += 1;
            }
        }
    }
    assert!(n > 0, "no coarse tile was widened by its children");
}

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
        Err(e) => e,
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

/// Encodes `heights` (metres) as an image of `scheme`, returns (file, the heights the file
/// holds as its encoding decodes them).
fn encoded_png(
    dir: &Path,
    scheme: ElevationScheme,
    heights: &[f64],
    w: u32,
    h: u32,
) -> (PathBuf, ElevationEncoding, Vec<f64>) {
    let (min, displacement) = (-400.0, 1300.0);
    let encoding = ElevationEncoding { scheme, scale: displacement, offset: min, nodata: None };
    let path = dir.join(format!("{scheme:?}.png"));
    let mut decoded = Vec::new();
    let mut bytes = Vec::new();
    for &height in heights {
        let (pixel, value): (Vec<u8>, f64) = match scheme {
            ElevationScheme::Gray8 => {
                let v = ((height - min) / displacement * 255.0).round().clamp(0.0, 255.0);
                (vec![v as u8], v)
            }
            ElevationScheme::RgbThirds => {
                let v = ((height - min) / displacement * 765.0).round().clamp(0.0, 765.0) as u32;
                let r = v.min(255);
                let g = (v - r).min(255);
                let b = v - r - g;
                (vec![r as u8, g as u8, b as u8], f64::from(v))
            }
            ElevationScheme::TerrainRgb => {
                let v = ((height + 10_000.0) * 10.0).round() as u32;
                (vec![(v >> 16) as u8, (v >> 8) as u8, v as u8], f64::from(v))
            }
            ElevationScheme::Terrarium => {
                let v = ((height + 32_768.0) * 256.0).round() as u32;
                (vec![(v >> 16) as u8, (v >> 8) as u8, v as u8], f64::from(v) / 256.0)
            }
            ElevationScheme::QuantizedU16 | ElevationScheme::Float32 => {
                let v = ((height + 400.0) * 10.0).round() as u16;
                (v.to_be_bytes().to_vec(), f64::from(v))
            }
        };
        bytes.extend(pixel);
        decoded.push(encoding.height(value));
    }
    let (colour, depth, encoding) = match scheme {
        ElevationScheme::Gray8 => (png::ColorType::Grayscale, png::BitDepth::Eight, encoding),
        ElevationScheme::QuantizedU16 | ElevationScheme::Float32 => {
            let e =
                ElevationEncoding { scheme: ElevationScheme::QuantizedU16, scale: 0.1, offset: -400.0, nodata: None };
            (png::ColorType::Grayscale, png::BitDepth::Sixteen, e)
        }
        _ => (png::ColorType::Rgb, png::BitDepth::Eight, encoding),
    };
    if scheme == ElevationScheme::QuantizedU16 {
        decoded = bytes.chunks_exact(2).map(|c| encoding.height(f64::from(u16::from_be_bytes([c[0], c[1]])))).collect();
    }
    png_with(&path, w, h, colour, depth, &bytes);
    (path, encoding, decoded)
}

#[test]
fn every_elevation_encoding_round_trips_within_its_step() {
    let (w, h) = (40, 30);
    let truth: Vec<f64> = (0..h)
        .flat_map(|y| (0..w).map(move |x| (x, y)))
        .map(|(x, y)| 120.0 + f64::from(x) * 17.3 - f64::from(y * y) * 0.37 + (f64::from(x * y) * 0.7).sin() * 4.0)
        .collect();
    let dir = tempfile::tempdir().unwrap();
    for scheme in [
        ElevationScheme::Gray8,
        ElevationScheme::RgbThirds,
        ElevationScheme::TerrainRgb,
        ElevationScheme::Terrarium,
        ElevationScheme::QuantizedU16,
    ] {
        let (path, encoding, decoded) = encoded_png(dir.path(), scheme, &truth, w, h);
        let source = open_elevation(&path, Some(encoding)).unwrap().with_spacing(10.0);
        let out = dir.path().join(format!("{scheme:?}.tspack"));
        tile_elevation(
            &source,
            "e",
            &out,
            TileOptions { tile_size: 16, border: 0, ..TileOptions::default() },
            &Silent::default(),
        )
        .unwrap();
        let reader = Reader::open_mmap(&out).unwrap();
        let stored = reader.metadata().layers[0].elevation.unwrap();
        assert_eq!(stored.scheme, ElevationScheme::QuantizedU16, "{scheme:?}: stored as u16, never 8-bit");
        let (mut worst_decoded, mut worst_truth) = (0.0f64, 0.0f64);
        for ty in 0..2u32 {
            for tx in 0..3u32 {
                let tile = heights(&reader, TileKey::new(0, 0, tx, ty).unwrap()).unwrap();
                for (k, got) in tile.iter().enumerate() {
                    let (x, y) = (tx * 16 + k as u32 % 16, ty * 16 + k as u32 / 16);
                    if x >= w || y >= h {
                        continue;
                    }
                    let i = (y * w + x) as usize;
                    worst_decoded = worst_decoded.max((got - decoded[i]).abs());
                    worst_truth = worst_truth.max((got - truth[i]).abs());
                }
            }
        }
        // Storage adds at most half its step to what the input held; the input itself was
        // within half of its own step of the truth.
        let (storage, input) = (stored.step() / 2.0, encoding.step() / 2.0);
        assert!(worst_decoded <= storage + 1e-3, "{scheme:?}: {worst_decoded} > {storage}");
        assert!(worst_truth <= storage + input + 1e-3, "{scheme:?}: {worst_truth} > {storage} + {input}");
        if scheme == ElevationScheme::Gray8 {
            assert!(input > 1.0, "8-bit steps are metres: the reason 8-bit is never the stored format");
        }
    }
}

#[test]
fn transparent_pixels_of_an_encoded_png_are_nodata() {
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("terrarium.png");
    // 32x32 RGBA Terrarium at 100 m, the left half transparent.
    let v = (100.0f64 + 32_768.0) as u32;
    let pixels: Vec<u8> =
        (0..32 * 32).flat_map(|i| [(v >> 8) as u8, v as u8, 0, if i % 32 < 16 { 0 } else { 255 }]).collect();
    png_file(&path, 32, 32, &pixels);
    let encoding = ElevationEncoding { scheme: ElevationScheme::Terrarium, scale: 1.0, offset: 0.0, nodata: None };
    let source = open_elevation(&path, Some(encoding)).unwrap();
    let out = dir.path().join("t.tspack");
    tile_elevation(
        &source,
        "t",
        &out,
        TileOptions { tile_size: 16, border: 0, ..TileOptions::default() },
        &Silent::default(),
    )
    .unwrap();
    let reader = Reader::open_mmap(&out).unwrap();
    assert!(reader.tile(TileKey::new(0, 0, 0, 0).unwrap()).unwrap().is_none(), "all nodata: missing");
    let right = heights(&reader, TileKey::new(0, 0, 1, 0).unwrap()).unwrap();
    assert!(right.iter().all(|h| (h - 100.0).abs() < 1e-6), "{:?}", &right[..4]);
}

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
fn the_plan_gives_grids_and_counts_without_writing() {
    let r = raster(1000, 600, |x, y| (x + y) as f32);
    let image = Image { width: 2000, height: 1200, rgba: vec![255; 2000 * 1200 * 4], georeference: None };
    let t = TextureInput { source: &image, tile_size: 256, format: TextureFormat::Bc7, pixel_size: 1.0 };
    let p = plan(Some(&r), Some(&t), "p", TileOptions::default(), &Silent::default()).unwrap();
    let l = &p.metadata.layers;
    assert_eq!((l[0].num_x_tiles, l[0].num_y_tiles, l[0].num_lods), (4, 3, 3));
    assert_eq!((l[1].num_x_tiles, l[1].num_y_tiles, l[1].num_lods), (8, 5, 4));
    // Elevation: 12 + 4 + 1 tiles; texture: 40 + 12 + 4 + 1; the range layer as elevation.
    assert_eq!(p.layers.iter().map(|l| l.tiles).collect::<Vec<_>>(), vec![17, 57, 17]);
    assert!(p.estimated_bytes() > 0);
}

/// A GeoTIFF in EPSG:4326 with the north-west corner at `origin` and `pixel` degrees per
/// pixel: f32 heights (`rgb` = None) or RGB pixels.
fn geotiff(path: &Path, (width, height): (u32, u32), origin: [f64; 2], pixel: f64, rgb: Option<&[u8]>) {
    use tiff::encoder::{TiffEncoder, colortype};
    use tiff::tags::Tag;
    let file = std::fs::File::create(path).unwrap();
    let mut encoder = TiffEncoder::new(file).unwrap();
    let tag = |image: &mut tiff::encoder::DirectoryEncoder<'_, _, _>| {
        image.write_tag(Tag::Unknown(33550), &[pixel, pixel, 0.0][..]).unwrap();
        image.write_tag(Tag::Unknown(33922), &[0.0, 0.0, 0.0, origin[0], origin[1], 0.0][..]).unwrap();
        image.write_tag(Tag::Unknown(34735), &[1u16, 1, 0, 2, 1024, 0, 1, 2, 2048, 0, 1, 4326][..]).unwrap();
    };
    match rgb {
        Some(pixels) => {
            let mut image = encoder.new_image::<colortype::RGB8>(width, height).unwrap();
            tag(image.encoder());
            image.write_data(pixels).unwrap();
        }
        None => {
            let mut image = encoder.new_image::<colortype::Gray32Float>(width, height).unwrap();
            tag(image.encoder());
            let heights: Vec<f32> = (0..width * height).map(|i| (i % 97) as f32).collect();
            image.write_data(&heights).unwrap();
        }
    }
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

#[test]
fn min_max_skips_nodata_in_every_lane_and_the_remainder() {
    assert_eq!(min_max(&[]), (f32::INFINITY, f32::NEG_INFINITY));
    assert_eq!(min_max(&[f32::NAN; 11]), (f32::INFINITY, f32::NEG_INFINITY));
    // 8 lanes + a remainder of 5; the extremes in a lane, in the remainder, beside NaN.
    for at in [0, 3, 7, 9, 12] {
        let mut v: Vec<f32> = (0..13).map(|i| (i % 5) as f32).collect();
        v[(at + 1) % 13] = f32::NAN;
        v[at] = -40.5;
        v[(at + 5) % 13] = 9000.25;
        assert_eq!(min_max(&v), (-40.5, 9000.25), "extremes at {at}: {v:?}");
    }
}

/// The committed SRTM crops: Deflate strips with ocean nodata, LZW float32 tiles (clipped
/// at the edges), Deflate int16 strips.
const SRTM_FIXTURES: [&str; 3] = [
    "srtm-tamalpais-320-public-domain.tif",
    "srtm-tamalpais-150x100-tiled-float32-public-domain.tif",
    "srtm-tamalpais-150x100-strips-int16-public-domain.tif",
];

#[test]
fn the_range_found_while_decoding_is_that_of_the_rows() {
    // Deflate strips with ocean nodata (the range must skip it), LZW tiles with clipped
    // edge tiles, int16 strips: each file's range from its decoding threads (each chunk
    // reduced where it is decoded) against a pass over the rows it hands out.
    for name in SRTM_FIXTURES {
        let file = open_elevation(&repo_data(name), None).unwrap();
        let (mut lo, mut hi, mut nodata, mut rows) = (f32::INFINITY, f32::NEG_INFINITY, 0, 0);
        file.rows(&mut |row| {
            for &v in row {
                if v.is_nan() {
                    nodata += 1;
                } else {
                    (lo, hi) = (lo.min(v), hi.max(v));
                }
            }
            rows += 1;
            Ok(())
        })
        .unwrap();
        assert_eq!(rows, file.size().1, "{name}");
        // The scan that makes no rows (integers compared as integers for int16) finds the
        // same range, and reports rows read up to the last.
        let mut told = Vec::new();
        let scanned = file
            .height_range(&mut |n| {
                told.push(n);
                Ok(())
            })
            .unwrap();
        assert_eq!(scanned, (lo, hi), "{name}");
        assert!(told.windows(2).all(|w| w[0] < w[1]), "{name}: {told:?}");
        assert_eq!(told.last(), Some(&file.size().1), "{name}");
        assert!(lo < hi && lo > -100.0 && hi < 1000.0, "{name}: {lo}..{hi}");
        if name.contains("320") {
            assert!(nodata > 0 && lo > 0.0, "{name}: the ocean is nodata, not a height ({nodata} samples)");
        }
    }
}

#[test]
fn a_jpeg_too_large_to_decode_whole_is_read_by_rows_or_refused_by_name() {
    let path = Path::new("ortho.jpg");
    let never = || -> Result<bool> { panic!("a JPEG that fits is decoded whole") };
    assert!(raster::jpeg_fits(path, 10_800, 5_400, never).is_ok(), "the shaded relief (175 MB decoded) fits");
    assert!(raster::jpeg_fits(path, 40_000, 30_000, || Ok(true)).is_ok(), "a sequential one is read by rows");
    let e = raster::jpeg_fits(path, 40_000, 30_000, || Ok(false)).unwrap_err().to_string();
    assert!(e.contains("ortho.jpg") && e.contains("40000x30000") && e.contains("tiled GeoTIFF"), "{e}");
    assert!(raster::jpeg_fits(path, usize::MAX, 3, || Ok(false)).is_err(), "no overflow");
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

#[test]
fn tiling_from_inside_a_one_thread_pool_finishes() {
    // A caller on one of rayon's own threads (a program tiling several rasters in
    // parallel): waiting for the cuts must not keep that thread from running them.
    // An in-memory raster, and a GeoTIFF (whose reading thread decodes on the global pool).
    let dir = tempfile::tempdir().unwrap();
    for tiff in [false, true] {
        let out = dir.path().join(format!("pooled-{tiff}.tspack"));
        let pool = rayon::ThreadPoolBuilder::new().num_threads(1).build().unwrap();
        let (done, finished) = std::sync::mpsc::channel();
        let job = out.clone();
        std::thread::spawn(move || {
            let options = TileOptions { tile_size: 32, ..TileOptions::default() };
            let result = pool.install(|| {
                if tiff {
                    let source = open_elevation(&repo_data(SRTM_FIXTURES[0]), None)?;
                    tile_elevation(&source, "pooled", &job, options, &Silent::default())
                } else {
                    let r = raster(200, 150, |x, y| (x * 3 + y) as f32);
                    tile_elevation(&r, "pooled", &job, options, &Silent::default())
                }
            });
            let _ = done.send(result.map(|summary| summary.addressed_tiles));
        });
        // A deadlock would leave the thread waiting: fail instead of hanging the test run.
        let tiles = finished.recv_timeout(std::time::Duration::from_secs(60)).expect("tiling finished").unwrap();
        assert!(tiles > 0 && out.exists(), "tiff {tiff}: {tiles} tiles");
    }
}

#[test]
fn integer_samples_give_their_range_without_nodata() {
    use raster::integer_range;
    let none = (f32::INFINITY, f32::NEG_INFINITY);
    // Nodata at either end, in every lane of a vector and the remainder.
    for at in 0..37 {
        let mut v: Vec<i16> = (0..37).map(|i| (i * 7 % 23) as i16 - 5).collect();
        v[at] = -32767;
        v[(at + 11) % 37] = -32767;
        let real: Vec<f32> = v.iter().filter(|&&x| x != -32767).map(|&x| f32::from(x)).collect();
        let want = (
            real.iter().copied().fold(f32::INFINITY, f32::min),
            real.iter().copied().fold(f32::NEG_INFINITY, f32::max),
        );
        assert_eq!(integer_range(&v, Some(-32767.0)), want, "nodata at {at}");
        assert_eq!(integer_range(&v, None), (-32767.0, want.1), "no nodata: it is a height");
    }
    assert_eq!(integer_range::<i16>(&[], None), none);
    assert_eq!(integer_range(&[-32767i16; 19], Some(-32767.0)), none, "all nodata: no range");
    // A nodata no sample of the type can hold skips nothing.
    assert_eq!(integer_range(&[0u8, 255, 7], Some(-1.0)), (0.0, 255.0));
    assert_eq!(integer_range(&[0u8, 255, 7], Some(255.5)), (0.0, 255.0));
    assert_eq!(integer_range(&[3u16, 65_535, 7], Some(1e30)), (3.0, 65_535.0));
    assert_eq!(integer_range(&[3u16, 65_535, 7], Some(65_535.0)), (3.0, 7.0));
    assert_eq!(integer_range(&[-128i8, 127, 0], Some(-128.0)), (0.0, 127.0));
}

#[test]
fn quantized_heights_decode_as_the_encoding_says_for_every_value() {
    let encoding =
        ElevationEncoding { scheme: ElevationScheme::QuantizedU16, scale: 0.0731, offset: -432.17, nodata: None };
    let raw: Vec<u8> = (0..=u16::MAX).flat_map(u16::to_le_bytes).collect();
    let decoded = encode::decode_heights(&raw, &encoding);
    assert!(decoded[0].is_nan(), "0 is no data");
    for (q, &h) in decoded.iter().enumerate().skip(1) {
        #[expect(clippy::cast_possible_truncation, reason = "heights are f32")]
        let expected = encoding.height(q as f64) as f32;
        assert_eq!(h.to_bits(), expected.to_bits(), "raw {q}");
    }
}

#[test]
fn quantized_heights_are_what_a_reader_decodes_bit_for_bit() {
    // Steps and offsets as `plan` makes them (powers of two, whole steps: the f32 path),
    // an offset near that path's limit, and encodings from elsewhere (the f64 path).
    let encodings = [
        (1.0 / 16.0, -26.0 / 16.0),
        (1.0 / 16.0, 4_000.0),
        (0.25, -11_000.25),
        (16.0, -16.0 * 16_000_000.0),
        (0.0731, -432.17),
        (1.0 / 16.0, 3.03),
    ];
    let mut state = 0x2545_f491_4f6c_dd1du64;
    let mut next = move || {
        state ^= state << 13;
        state ^= state >> 7;
        state ^= state << 17;
        state
    };
    for (scale, offset) in encodings {
        let encoding = ElevationEncoding { scheme: ElevationScheme::QuantizedU16, scale, offset, nodata: Some(0.0) };
        let span = scale * 65_535.0;
        let mut heights: Vec<f32> = (0..20_000)
            .map(|_| (offset + (next() % 1_000_000) as f64 / 1e6 * span * 1.1 - span * 0.05) as f32)
            .collect();
        heights.extend([f32::NAN, offset as f32, (offset + span) as f32, (offset + span / 2.0) as f32]);
        let mut quantized = heights.clone();
        encode::quantize_heights(&mut quantized, &encoding);
        let mut raw = Vec::new();
        encode::encode_heights(&heights, &encoding, &mut raw);
        let decoded = encode::decode_heights(&raw, &encoding);
        for ((h, q), d) in heights.iter().zip(&quantized).zip(&decoded) {
            assert_eq!(q.to_bits(), d.to_bits(), "height {h} with step {scale}, offset {offset}");
        }
    }
}

#[test]
fn an_estimated_encoding_spares_half_the_span_each_side_at_most_twice_as_coarse() {
    use crate::options::ElevationStorage;
    use crate::plan::{chosen_encoding, estimated_encoding, holds};
    for span in [0.0, 1.0, 900.0, 2_000.0, 2_100.0, 4_000.0, 4_100.0, 9_000.0, 19_900.0, 500_000.0] {
        for min in [-11_000.0, -66.0, 0.0, 3_217.3] {
            let estimate = (min, min + span);
            let e = estimated_encoding(ElevationStorage::Auto, estimate);
            let own = chosen_encoding(ElevationStorage::Auto, estimate, None);
            assert_eq!(e.scheme, ElevationScheme::QuantizedU16);
            assert!(e.scale == own.scale || e.scale == 2.0 * own.scale, "{estimate:?}: {e:?} against {own:?}");
            if span < 2_000.0 {
                assert_eq!(e.scale, own.scale, "{estimate:?}");
            }
            let (lo, hi) = holds(&e);
            let spare = (span / 2.0).max(e.scale);
            assert!(f64::from(lo) <= min - spare && f64::from(hi) >= min + span + spare, "{estimate:?}: {lo} .. {hi}");
            // The choice: the estimate's encoding while the range fits it, else the range's.
            let inside = (min - spare, min + span + spare);
            assert_eq!(chosen_encoding(ElevationStorage::Auto, inside, Some(estimate)), e);
            let outside = (f64::from(lo) - 1.0, min + span);
            assert_eq!(
                chosen_encoding(ElevationStorage::Auto, outside, Some(estimate)),
                chosen_encoding(ElevationStorage::Auto, outside, None)
            );
        }
    }
    let f32_only = estimated_encoding(ElevationStorage::F32, (0.0, 10.0));
    assert_eq!(f32_only.scheme, ElevationScheme::Float32);
    assert_eq!(holds(&f32_only), (f32::NEG_INFINITY, f32::INFINITY));
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
