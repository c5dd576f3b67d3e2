//! The pyramid: aligned, bordered, averaged, sparse tiles, streamed a band at a time.

use super::*;

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
fn the_archive_is_the_same_with_rows_halved_on_one_thread_or_on_many() {
    // Pools of over four threads round and halve rows in parallel batches
    // (`pyramid::rows_in_parallel`), smaller ones a row at a time on the calling thread:
    // both must write the same bytes, odd sizes, no data and a quantized encoding included.
    let r = raster(301, 517, |x, y| {
        if (x + 2 * y) % 97 == 0 || (x > 250 && y < 40) {
            f32::NAN
        } else {
            (x as f32 * 0.37).sin() * 90.0 + y as f32 * 0.3
        }
    });
    let dir = tempfile::tempdir().unwrap();
    let archive = |threads: usize| {
        let out = dir.path().join(format!("threads-{threads}.tspack"));
        let pool = rayon::ThreadPoolBuilder::new().num_threads(threads).build().unwrap();
        let options = TileOptions { tile_size: 32, ..TileOptions::default() };
        pool.install(|| {
            assert_eq!(rayon::current_num_threads(), threads);
            tile_elevation(&r, "pooled", &out, options, &Silent::default()).unwrap();
        });
        std::fs::read(&out).unwrap()
    };
    let (one, many) = (archive(1), archive(8));
    assert!(one.len() > 10_000, "{} bytes", one.len());
    assert!(one == many, "the archives differ: {} and {} bytes", one.len(), many.len());
}
