//! Plans and height ranges.

use super::*;

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
