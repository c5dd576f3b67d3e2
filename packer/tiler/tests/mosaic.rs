//! A mosaic of rasters in two UTM zones, with overlaps and a gap, against GDAL's
//! `gdalwarp` of the same files onto the same grid (the independent oracle), and against
//! the analytic surface the rasters sample.
#![allow(
    clippy::unwrap_used,
    clippy::expect_used,
    clippy::cast_possible_truncation,
    clippy::cast_precision_loss,
    missing_docs
)]

mod common;

use std::path::{Path, PathBuf};
use std::process::Command;

use terrastream_format::{Reader, TileKey};
use terrastream_pack::progress::Silent;
use terrastream_tiler::{
    Crs, ElevationSource, ElevationStorage, Heights, Mosaic, MosaicOptions, Pixels, TileOptions, Transform,
    read_geotiff, tile_elevation,
};
use tiff::encoder::{TiffEncoder, colortype};
use tiff::tags::Tag;

/// Heights of the surface at a longitude and latitude: smooth, a few hundred metres.
fn surface(lon: f64, lat: f64) -> f64 {
    500.0 + 300.0 * ((lon - 11.5) * 3.0).sin() * ((lat - 46.0) * 4.0).cos() + 40.0 * (lon * 25.0).sin()
}

/// A geographic GeoTIFF of the surface: west, north, degrees per sample, size.
fn geographic_tile(path: &Path, west: f64, north: f64, step: f64, (w, h): (u32, u32)) {
    let mut encoder = TiffEncoder::new(std::fs::File::create(path).unwrap()).unwrap();
    let mut image = encoder.new_image::<colortype::Gray32Float>(w, h).unwrap();
    image.encoder().write_tag(Tag::Unknown(33550), &[step, step, 0.0][..]).unwrap();
    image.encoder().write_tag(Tag::Unknown(33922), &[0.0, 0.0, 0.0, west, north, 0.0][..]).unwrap();
    image.encoder().write_tag(Tag::Unknown(34735), &[1u16, 1, 0, 2, 1024, 0, 1, 2, 2048, 0, 1, 4326][..]).unwrap();
    let data: Vec<f32> = (0..h)
        .flat_map(|j| (0..w).map(move |i| (i, j)))
        .map(|(i, j)| surface(west + (f64::from(i) + 0.5) * step, north - (f64::from(j) + 0.5) * step) as f32)
        .collect();
    image.write_data(&data).unwrap();
}

fn gdal() -> bool {
    common::tool("gdalwarp", "gdal-bin")
}

fn warp(args: &[&str], inputs: &[PathBuf], out: &Path) {
    let status = Command::new("gdalwarp").args(["-q", "-overwrite"]).args(args).args(inputs).arg(out).status().unwrap();
    assert!(status.success(), "gdalwarp {args:?} failed");
}

#[test]
fn a_mosaic_across_two_utm_zones_matches_gdalwarp() {
    if !gdal() {
        return;
    }
    let dir = tempfile::tempdir().unwrap();
    // 2 x 2 tiles of 0.25 x 0.2 degrees astride 12 E (the UTM 32/33 boundary), overlapping
    // by 16 samples; the west column warped to UTM 32N, the east one to UTM 33N. The
    // north-east tile leaves a gap at its east edge that nothing fills.
    let step = 0.0005;
    let overlap = 16.0 * step;
    let mut tiles = Vec::new();
    for (k, (west, north, zone)) in [
        (11.75, 46.4, 32632),
        (12.0 - overlap, 46.4, 32633),
        (11.75, 46.2 + overlap, 32632),
        (12.0 - overlap, 46.2 + overlap, 32633),
    ]
    .into_iter()
    .enumerate()
    {
        let (w, h) = (((0.25 + overlap) / step) as u32, ((0.2 + overlap) / step) as u32);
        let w = if k == 1 { w - 60 } else { w };
        let geo = dir.path().join(format!("geo-{k}.tif"));
        geographic_tile(&geo, west, north, step, (w, h));
        let utm = dir.path().join(format!("tile-{k}.tif"));
        warp(
            &["-t_srs", &format!("EPSG:{zone}"), "-r", "bilinear", "-tr", "40", "40", "-dstnodata", "-9999"],
            &[geo],
            &utm,
        );
        tiles.push(utm);
    }

    let options = MosaicOptions {
        crs: Some(Crs::epsg(32632).unwrap()),
        resolution: Some(60.0),
        cache_bytes: Some(1 << 20),
        ..MosaicOptions::default()
    };
    let mosaic = Mosaic::open(&tiles, &options).unwrap();
    let (w, h) = mosaic.size();
    let origin = mosaic.georeference().unwrap().origin.unwrap();
    let ours = rows_of(&mosaic).concat();

    // GDAL onto the same grid: same CRS, extent and spacing, bilinear, later file wins.
    let te = [origin[0], origin[1] - f64::from(h) * 60.0, origin[0] + f64::from(w) * 60.0, origin[1]]
        .map(|v| format!("{v:.6}"));
    let oracle = dir.path().join("oracle.tif");
    let mut args = vec![
        "-t_srs",
        "EPSG:32632",
        "-tr",
        "60",
        "60",
        "-r",
        "bilinear",
        "-ot",
        "Float32",
        "-dstnodata",
        "-9999",
        "-te",
    ];
    args.extend(te.iter().map(String::as_str));
    warp(&args, &tiles, &oracle);
    let gdal = read_geotiff(&oracle).unwrap();
    assert_eq!(gdal.size(), (w, h), "GDAL made a grid of another size");
    let gdal = &gdal.data;

    let (mut both, mut only_ours, mut only_gdal, mut sum, mut worst) = (0usize, 0usize, 0usize, 0.0, 0.0f64);
    for (a, b) in ours.iter().zip(gdal) {
        match (a.is_nan(), b.is_nan()) {
            (false, false) => {
                both += 1;
                let d = f64::from((a - b).abs());
                sum += d;
                worst = worst.max(d);
            }
            (false, true) => only_ours += 1,
            (true, false) => only_gdal += 1,
            (true, true) => {}
        }
    }
    let mean = sum / both as f64;
    eprintln!(
        "{both} samples with data in both: mean |difference| {mean:.3} m, worst {worst:.2} m; data only here {only_ours}, only in GDAL's {only_gdal}"
    );
    assert!(both as f64 > 0.8 * f64::from(w * h), "too few samples with data: {both} of {}", w * h);
    assert!(mean < 0.5, "mean difference from gdalwarp {mean} m");
    // Along the edges of nodata, bilinear over the corners with data differs from GDAL's
    // rule; those samples are few.
    assert!(((only_ours + only_gdal) as f64) < 0.01 * f64::from(w * h), "coverage differs: {only_ours} / {only_gdal}");

    // Against the surface itself, at the samples' centres.
    let to_lon_lat = Transform::new(&Crs::epsg(32632).unwrap(), &Crs::wgs84());
    let mut errors = Vec::new();
    for j in (0..h).step_by(3) {
        for i in (0..w).step_by(3) {
            let v = ours[(j * w + i) as usize];
            if v.is_nan() {
                continue;
            }
            let (x, y) = (origin[0] + (f64::from(i) + 0.5) * 60.0, origin[1] - (f64::from(j) + 0.5) * 60.0);
            let (lon, lat) = to_lon_lat.apply(x, y).unwrap();
            errors.push((f64::from(v) - surface(lon, lat)).abs());
        }
    }
    errors.sort_by(f64::total_cmp);
    let median = errors[errors.len() / 2];
    eprintln!("against the surface: median error {median:.3} m over {} samples", errors.len());
    assert!(median < 1.0, "median error against the surface {median} m");
    // The gap east of the north-east tile stays nodata.
    let gap = ours[(h / 4 * w + w - 2) as usize];
    assert!(gap.is_nan(), "the gap holds {gap}");
}

#[test]
fn a_bad_input_is_named_or_skipped_and_listed() {
    let dir = tempfile::tempdir().unwrap();
    let (a, b) = (dir.path().join("a.tif"), dir.path().join("b.tif"));
    geographic_tile(&a, 11.0, 46.0, 0.001, (100, 100));
    geographic_tile(&b, 11.1, 46.0, 0.001, (100, 100));
    let broken = dir.path().join("broken.tif");
    std::fs::write(&broken, b"II*\0 not really a TIFF").unwrap();
    let inputs = vec![a, broken.clone(), b];
    let err = Mosaic::<Heights>::open(&inputs, &MosaicOptions::default()).unwrap_err().to_string();
    assert!(err.contains("broken.tif"), "{err}");
    let options = MosaicOptions { skip_bad_inputs: true, ..MosaicOptions::default() };
    let mosaic = Mosaic::open(&inputs, &options).unwrap();
    assert_eq!(mosaic.skipped().len(), 1);
    assert_eq!(mosaic.skipped()[0].0, broken);
    assert_eq!(mosaic.inputs().count(), 2);
    // Geographic inputs: a transverse Mercator centred on them, about 15.5 km x 11 km.
    assert!(mosaic.crs().definition().starts_with("+proj=tmerc"), "{:?}", mosaic.crs());
    let (w, h) = mosaic.size();
    let spacing = mosaic.spacing().0;
    assert!(
        (f64::from(w) * spacing - 15_480.0).abs() < 300.0 && (f64::from(h) * spacing - 11_120.0).abs() < 300.0,
        "{w}x{h} at {spacing} m"
    );
}

/// `utm_tile`'s heights (`height` and up to 49 m more) as DEMs are published: int16,
/// 32 x 32 tiles, Deflate (by `gdal_translate`, which writes the tiles after the
/// directory, so that cutting the file short cuts a tile).
fn deflate_tile(dir: &Path, name: &str, east: f64, height: f32) -> PathBuf {
    let plain = dir.join(format!("{name}-plain.tif"));
    // Varied, so that each tile's stream holds Huffman tables to garble.
    utm_tile(&plain, (east, 5_100_000.0), (64, 64), |i, j| height + ((i * 7 + j * 13) % 50) as f32);
    let path = dir.join(name);
    let tiling = ["-co", "TILED=YES", "-co", "BLOCKXSIZE=32", "-co", "BLOCKYSIZE=32", "-co", "COMPRESS=DEFLATE"];
    int16_copy(&plain, &path, &tiling);
    std::fs::remove_file(plain).unwrap();
    path
}

/// `gdal_translate -ot Int16` of `from` to `to`, with `options`.
fn int16_copy(from: &Path, to: &Path, options: &[&str]) {
    let status =
        Command::new("gdal_translate").args(["-q", "-ot", "Int16"]).args(options).arg(from).arg(to).status().unwrap();
    assert!(status.success(), "gdal_translate {options:?} failed");
}

#[test]
fn a_truncated_or_undecodable_input_is_named_or_skipped_and_listed() {
    if !gdal() {
        return;
    }
    let dir = tempfile::tempdir().unwrap();
    let good = dir.path().join("good.tif");
    utm_tile(&good, (500_000.0, 5_100_000.0), (64, 64), |_, _| 100.0);
    let skip = MosaicOptions { skip_bad_inputs: true, ..MosaicOptions::default() };

    // Cut short, as a download or copy can be: found when it is opened (its last tile
    // lies past the end), before any work.
    let cut = deflate_tile(dir.path(), "cut.tif", 500_640.0, 200.0);
    let bytes = std::fs::read(&cut).unwrap();
    std::fs::write(&cut, &bytes[..bytes.len() - 20]).unwrap();
    let err = Mosaic::<Heights>::open(&[good.clone(), cut.clone()], &MosaicOptions::default()).unwrap_err().to_string();
    assert!(err.contains("cut.tif") && err.contains("truncated"), "{err}");
    let mosaic = Mosaic::<Heights>::open(&[good.clone(), cut.clone()], &skip).unwrap();
    assert_eq!(mosaic.skipped().len(), 1);
    assert_eq!(mosaic.skipped()[0].0, cut);

    // Whole, but a tile's Deflate stream garbled: found when its heights are scanned
    // (every tile decoded once, before any row is made).
    let garbled = deflate_tile(dir.path(), "garbled.tif", 500_640.0, 200.0);
    let mut bytes = std::fs::read(&garbled).unwrap();
    garble(&mut bytes, &tile_places(&garbled));
    std::fs::write(&garbled, bytes).unwrap();
    let inputs = [good.clone(), garbled.clone()];
    let mosaic = Mosaic::<Heights>::open(&inputs, &MosaicOptions::default()).unwrap();
    let err = mosaic.height_range(&mut |_| Ok(())).unwrap_err().to_string();
    assert!(err.contains("garbled.tif") && err.contains("Deflate"), "{err}");
    let mosaic = Mosaic::<Heights>::open(&inputs, &skip).unwrap();
    assert!(mosaic.skipped().is_empty(), "nothing is decoded when opened");
    assert_eq!(mosaic.height_range(&mut |_| Ok(())).unwrap(), (100.0, 100.0), "the good input's heights alone");
    let skipped = mosaic.skipped();
    assert_eq!(skipped.len(), 1);
    assert_eq!(skipped[0].0, garbled);
    assert!(skipped[0].1.contains("Deflate"), "{}", skipped[0].1);
    // Its place is a gap: the grid still spans both, the good input's samples are kept.
    let (w, _) = mosaic.size();
    assert_eq!(w, 128, "the grid made from both footprints");
    let rows = rows_of(&mosaic);
    assert!(rows.iter().all(|r| r[..64].iter().all(|&v| v == 100.0)), "the good input's samples");
    assert!(rows.iter().all(|r| r[64..].iter().all(|v| v.is_nan())), "nodata where the garbled input lay");

    // Nothing usable at all: an error, not an empty archive.
    let alone = Mosaic::<Heights>::open(std::slice::from_ref(&garbled), &skip).unwrap();
    let err = alone.height_range(&mut |_| Ok(())).unwrap_err().to_string();
    assert!(err.contains("no input can be used"), "{err}");
}

/// The offsets and byte counts of `path`'s tiles.
fn tile_places(path: &Path) -> Vec<(usize, usize)> {
    let mut decoder = tiff::decoder::Decoder::new(std::fs::File::open(path).unwrap()).unwrap();
    let offsets = decoder.get_tag_u64_vec(Tag::TileOffsets).unwrap();
    let counts = decoder.get_tag_u64_vec(Tag::TileByteCounts).unwrap();
    offsets.into_iter().zip(counts).map(|(a, n)| (a as usize, n as usize)).collect()
}

/// Garbles the code lengths of the Deflate streams at `places` in `bytes`.
fn garble(bytes: &mut [u8], places: &[(usize, usize)]) {
    for &(at, count) in places {
        // Past the zlib header: the first block's code lengths.
        for k in 2..40.min(count) {
            bytes[at + k] = (k * 37 + 11) as u8;
        }
    }
}

/// An RGB GeoTIFF in UTM 33N at 10 m, its north-west corner at `east`, 5 100 000 m.
fn utm_rgb(path: &Path, east: f64, (w, h): (u32, u32), rgb: impl Fn(u32, u32) -> [u8; 3]) {
    let mut encoder = TiffEncoder::new(std::fs::File::create(path).unwrap()).unwrap();
    let mut image = encoder.new_image::<colortype::RGB8>(w, h).unwrap();
    image.encoder().write_tag(Tag::Unknown(33550), &[10.0, 10.0, 0.0][..]).unwrap();
    image.encoder().write_tag(Tag::Unknown(33922), &[0.0, 0.0, 0.0, east, 5_100_000.0, 0.0][..]).unwrap();
    image.encoder().write_tag(Tag::Unknown(34735), &[1u16, 1, 0, 2, 1024, 0, 1, 1, 3072, 0, 1, 32633][..]).unwrap();
    let rgb = &rgb;
    let data: Vec<u8> = (0..h).flat_map(|j| (0..w).flat_map(move |i| rgb(i, j))).collect();
    image.write_data(&data).unwrap();
}

/// Imagery is not decoded before rows are made (no height scan): with `skip_bad_inputs`,
/// a tile or strip found damaged then is left empty (a gap, as where no input lies), the
/// rest of its input used, and the input listed with how much of it was left out;
/// without it, the first such tile stops the run naming the file.
#[test]
fn imagery_damaged_within_is_named_or_left_empty_where_damaged_and_listed() {
    if !gdal() {
        return;
    }
    let dir = tempfile::tempdir().unwrap();
    let p = |name: &str| dir.path().join(name);
    // Three images side by side: red, green (32 x 32 Deflate tiles, the second garbled),
    // blue (a PNG cut short: its lower rows cannot be decoded). Varied, so that each
    // stream holds Huffman tables to garble.
    let vary = |i: u32, j: u32| 100 + ((i * 7 + j * 13) % 50) as u8;
    utm_rgb(&p("red.tif"), 500_000.0, (64, 256), |i, j| [vary(i, j), 0, 0]);
    utm_rgb(&p("green-plain.tif"), 500_640.0, (64, 256), |i, j| [0, vary(i, j), 0]);
    utm_rgb(&p("blue.tif"), 501_280.0, (64, 256), |i, j| [0, 0, vary(i, j)]);
    let green = p("green.tif");
    let tiling = ["-q", "-co", "TILED=YES", "-co", "BLOCKXSIZE=32", "-co", "BLOCKYSIZE=32", "-co", "COMPRESS=DEFLATE"];
    let status = Command::new("gdal_translate").args(tiling).arg(p("green-plain.tif")).arg(&green).status().unwrap();
    assert!(status.success());
    let mut bytes = std::fs::read(&green).unwrap();
    garble(&mut bytes, &tile_places(&green)[1..2]);
    std::fs::write(&green, bytes).unwrap();
    let blue = p("blue.png");
    let png = ["-q", "-of", "PNG", "-co", "WORLDFILE=YES"];
    let status = Command::new("gdal_translate").args(png).arg(p("blue.tif")).arg(&blue).status().unwrap();
    assert!(status.success());
    let bytes = std::fs::read(&blue).unwrap();
    std::fs::write(&blue, &bytes[..bytes.len() / 2]).unwrap();
    let inputs = [p("red.tif"), green.clone(), blue.clone()];
    let rows = |mosaic: &Mosaic<Pixels>| {
        let mut rows = Vec::new();
        terrastream_tiler::ImageSource::rows(mosaic, &mut |row| {
            rows.push(row.to_vec());
            Ok(())
        })
        .map(|()| rows)
    };

    let mosaic = Mosaic::<Pixels>::open(&inputs, &MosaicOptions::default()).unwrap();
    let err = rows(&mosaic).unwrap_err().to_string();
    assert!(err.contains("green.tif"), "{err}");

    let skip = MosaicOptions { skip_bad_inputs: true, ..MosaicOptions::default() };
    let mosaic = Mosaic::<Pixels>::open(&inputs, &skip).unwrap();
    assert!(mosaic.skipped().is_empty(), "nothing is decoded when opened");
    let rows = rows(&mosaic).unwrap();
    assert_eq!((rows.len(), rows[0].len()), (256, 192));
    let lit = |px: [u8; 4], channel: usize| px[3] == 255 && px[channel] >= 100;
    for (j, row) in rows.iter().enumerate() {
        assert!(row[..64].iter().all(|&px| lit(px, 0)), "red, row {j}");
        for (i, &px) in row[64..128].iter().enumerate() {
            let gap = j < 32 && i >= 32;
            assert!(if gap { px == [0; 4] } else { lit(px, 1) }, "green at {i}, {j}: {px:?}");
        }
    }
    // The PNG's rows up to where it was cut, then nothing.
    let decoded = rows.iter().take_while(|r| r[128..].iter().all(|&px| lit(px, 2))).count();
    assert!((64..256).contains(&decoded), "{decoded} rows of the cut PNG");
    assert!(rows[decoded..].iter().all(|r| r[128..].iter().all(|&px| px == [0; 4])), "after row {decoded}");
    let skipped = mosaic.skipped();
    assert_eq!(skipped.iter().map(|(path, _)| path.clone()).collect::<Vec<_>>(), [green, blue], "{skipped:?}");
    assert!(skipped[0].1.contains("Deflate") && skipped[0].1.contains("(1 tile of it left empty)"), "{skipped:?}");
    assert!(skipped[1].1.contains("strips of it left empty"), "{skipped:?}");
}

#[test]
fn a_mosaics_height_scan_shows_progress_within_an_input_and_stops_on_request() {
    if !gdal() {
        return;
    }
    let dir = tempfile::tempdir().unwrap();
    // One input of 1024 one-row strips: the scan reads it in several batches.
    let plain = dir.path().join("plain.tif");
    utm_tile(&plain, (500_000.0, 5_100_000.0), (1024, 1024), |i, j| ((i + j) % 300) as f32);
    let strips = dir.path().join("strips.tif");
    int16_copy(&plain, &strips, &["-co", "BLOCKYSIZE=1"]);
    let small = dir.path().join("small.tif");
    utm_tile(&small, (510_240.0, 5_100_000.0), (64, 64), |_, _| 1000.0);
    let mosaic = Mosaic::<Heights>::open(&[strips, small], &MosaicOptions::default()).unwrap();
    let rows = mosaic.size().1;
    let mut told = Vec::new();
    let range = mosaic
        .height_range(&mut |done| {
            told.push(done);
            Ok(())
        })
        .unwrap();
    assert_eq!(range, (0.0, 1000.0));
    assert!(told.windows(2).all(|w| w[0] <= w[1]), "{told:?}");
    assert_eq!(told.last(), Some(&rows), "{told:?}");
    let within_first = told.iter().filter(|&&d| d < rows / 2).count();
    assert!(within_first >= 2, "the bar moves within the first input: {told:?}");
    // Stopped (Ctrl-C) at the first report: nothing more is read.
    let mut calls = 0;
    let stopped = mosaic.height_range(&mut |_| {
        calls += 1;
        Err(terrastream_format::Interrupted.into())
    });
    assert!(stopped.is_err());
    assert_eq!(calls, 1);
}

/// Our mosaic of `inputs` and gdalwarp's onto the same grid: (samples with data in both,
/// mean |difference|, samples with data in only one).
fn against_gdal(dir: &Path, inputs: &[PathBuf], crs: u16, spacing: f64) -> (usize, f64, usize) {
    let options =
        MosaicOptions { crs: Some(Crs::epsg(crs).unwrap()), resolution: Some(spacing), ..MosaicOptions::default() };
    let mosaic = Mosaic::open(inputs, &options).unwrap();
    let (w, h) = mosaic.size();
    let origin = mosaic.georeference().unwrap().origin.unwrap();
    let ours = rows_of(&mosaic).concat();
    let te = [origin[0], origin[1] - f64::from(h) * spacing, origin[0] + f64::from(w) * spacing, origin[1]]
        .map(|v| format!("{v:.6}"));
    let oracle = dir.join("oracle-vrt.tif");
    let (srs, tr) = (format!("EPSG:{crs}"), format!("{spacing}"));
    let mut args =
        vec!["-t_srs", &srs, "-tr", &tr, &tr, "-r", "bilinear", "-ot", "Float32", "-dstnodata", "-9999", "-te"];
    args.extend(te.iter().map(String::as_str));
    warp(&args, inputs, &oracle);
    let gdal = read_geotiff(&oracle).unwrap();
    assert_eq!(gdal.size(), (w, h));
    let (mut both, mut one, mut sum) = (0, 0, 0.0);
    for (a, b) in ours.iter().zip(&gdal.data) {
        match (a.is_nan(), b.is_nan()) {
            (false, false) => {
                both += 1;
                sum += f64::from((a - b).abs());
            }
            (true, true) => {}
            _ => one += 1,
        }
    }
    (both, sum / both.max(1) as f64, one)
}

#[test]
fn gdal_virtual_rasters_are_read_as_gdal_reads_them() {
    if !gdal() {
        return;
    }
    let dir = tempfile::tempdir().unwrap();
    let dem = Path::new(env!("CARGO_MANIFEST_DIR")).join("../../packer/pack/data/srtm-tamalpais-320-public-domain.tif");
    let run = |args: &[&str]| {
        let status = Command::new(args[0]).args(&args[1..]).current_dir(dir.path()).status().unwrap();
        assert!(status.success(), "{args:?}");
    };
    let dem = dem.to_str().unwrap();
    // Two overlapping windows of the SRTM crop, then a VRT of both (ComplexSources with
    // NODATA, file names relative to the VRT) and a VRT of a window of one (a SrcRect).
    run(&["gdal_translate", "-q", "-srcwin", "0", "0", "216", "216", "-a_nodata", "-32768", dem, "t0.tif"]);
    run(&["gdal_translate", "-q", "-srcwin", "200", "40", "120", "216", "-a_nodata", "-32768", dem, "t1.tif"]);
    run(&["gdalbuildvrt", "-q", "both.vrt", "t0.tif", "t1.tif"]);
    run(&["gdal_translate", "-q", "-of", "VRT", "-srcwin", "30", "50", "120", "90", "t0.tif", "crop.vrt"]);
    // A ComplexSource with ScaleRatio and ScaleOffset: heights 0..1000 -> 50..650.
    run(&[
        "gdal_translate",
        "-q",
        "-of",
        "VRT",
        "-ot",
        "Float32",
        "-scale",
        "0",
        "1000",
        "50",
        "650",
        "-srcwin",
        "10",
        "20",
        "150",
        "120",
        "t0.tif",
        "scaled.vrt",
    ]);
    let scaled = std::fs::read_to_string(dir.path().join("scaled.vrt")).unwrap();
    assert!(scaled.contains("<ScaleRatio>") && scaled.contains("<ScaleOffset>"), "{scaled}");
    let vrt = std::fs::read_to_string(dir.path().join("both.vrt")).unwrap();
    assert!(vrt.contains("<DstRect xOff=\"200\" yOff=\"40\""), "{vrt}");

    for name in ["both.vrt", "crop.vrt", "scaled.vrt"] {
        let (both, mean, one) = against_gdal(dir.path(), &[dir.path().join(name)], 32610, 30.0);
        eprintln!("{name}: {both} samples in both, mean |difference| {mean:.3} m, {one} in only one");
        assert!(both > 1000 && mean < 0.5 && (one as f64) < 0.02 * both as f64, "{name}: {both} / {mean} / {one}");
    }

    // A VRT naming a file that is not there: an error naming the file.
    let broken = vrt.replace("t1.tif", "gone.tif");
    std::fs::write(dir.path().join("broken.vrt"), broken).unwrap();
    let err =
        Mosaic::<Heights>::open(&[dir.path().join("broken.vrt")], &MosaicOptions::default()).unwrap_err().to_string();
    assert!(err.contains("gone.tif") && err.contains("broken.vrt"), "{err}");
}

/// A UTM 33N GeoTIFF of f32 heights `height(i, j)`, 10 m samples from (east, north).
/// Every row of `mosaic`, in order.
fn rows_of(mosaic: &Mosaic<Heights>) -> Vec<Vec<f32>> {
    let mut rows = Vec::new();
    mosaic
        .rows(&mut |r| {
            rows.push(r.to_vec());
            Ok(())
        })
        .unwrap();
    rows
}

fn utm_tile(path: &Path, (east, north): (f64, f64), (w, h): (u32, u32), height: impl Fn(u32, u32) -> f32) {
    let mut encoder = TiffEncoder::new(std::fs::File::create(path).unwrap()).unwrap();
    let mut image = encoder.new_image::<colortype::Gray32Float>(w, h).unwrap();
    image.encoder().write_tag(Tag::Unknown(33550), &[10.0, 10.0, 0.0][..]).unwrap();
    image.encoder().write_tag(Tag::Unknown(33922), &[0.0, 0.0, 0.0, east, north, 0.0][..]).unwrap();
    image.encoder().write_tag(Tag::Unknown(34735), &[1u16, 1, 0, 2, 1024, 0, 1, 1, 3072, 0, 1, 32633][..]).unwrap();
    let data: Vec<f32> = (0..h).flat_map(|j| (0..w).map(move |i| (i, j))).map(|(i, j)| height(i, j)).collect();
    image.write_data(&data).unwrap();
}

#[test]
fn an_input_on_the_output_crs_and_spacing_is_copied_sample_for_sample() {
    // The first input in UTM 33N on a 10 m lattice; a geographic one north-west of it
    // moves the mosaic's corner off that lattice, which the grid snaps back onto.
    let dir = tempfile::tempdir().unwrap();
    let a = dir.path().join("a.tif");
    let height = |i: u32, j: u32| 300.0 + (i as f32 * 0.37).sin() * 40.0 + j as f32 * 0.61;
    utm_tile(&a, (500_000.0, 5_100_000.0), (200, 200), height);
    let b = dir.path().join("b.tif");
    geographic_tile(&b, 14.95, 46.06, 0.0002, (100, 50));
    let mosaic = Mosaic::<Heights>::open(&[a, b], &MosaicOptions::default()).unwrap();
    let origin = mosaic.georeference().unwrap().origin.unwrap();
    let (dx, dy) = ((500_000.0 - origin[0]) / 10.0, (origin[1] - 5_100_000.0) / 10.0);
    assert!(dx > 1.0 && dy > 1.0, "the geographic input lies north-west: {origin:?}");
    assert!((dx - dx.round()).abs() < 1e-6 && (dy - dy.round()).abs() < 1e-6, "off the lattice: {dx}, {dy}");
    let (dx, dy) = (dx.round() as usize, dy.round() as usize);
    let rows = rows_of(&mosaic);
    for j in 0..200u32 {
        for i in 0..200u32 {
            let got = rows[dy + j as usize][dx + i as usize];
            assert_eq!(got.to_bits(), height(i, j).to_bits(), "sample ({i}, {j}): {got}");
        }
    }
}

/// A surface cut into 24 x 8 files of 8 x 8 samples: each band of 32 output rows crosses
/// 96 files, more than the 64 always kept open. Copied sample for sample (the files are
/// on the output's lattice), its height range scanned from all of them; and the same as
/// one file when both are reprojected (a given CRS): the cut leaves no seam.
#[test]
fn a_band_across_more_files_than_are_kept_open_reads_them_all() {
    let dir = tempfile::tempdir().unwrap();
    let height = |i: u32, j: u32| 300.0 + (i as f32 * 0.37).sin() * 40.0 + j as f32 * 0.61;
    let (across, down, side) = (24u32, 8u32, 8u32);
    assert!(4 * across as usize > terrastream_tiler::OPEN_FILES);
    let mut inputs = Vec::new();
    for y in 0..down {
        for x in 0..across {
            let path = dir.path().join(format!("t{y:02}_{x:02}.tif"));
            let corner = (500_000.0 + f64::from(x * side) * 10.0, 5_100_000.0 - f64::from(y * side) * 10.0);
            utm_tile(&path, corner, (side, side), |i, j| height(x * side + i, y * side + j));
            inputs.push(path);
        }
    }
    let whole = dir.path().join("whole.tif");
    utm_tile(&whole, (500_000.0, 5_100_000.0), (across * side, down * side), height);

    let mosaic = Mosaic::<Heights>::open(&inputs, &MosaicOptions::default()).unwrap();
    assert_eq!(mosaic.size(), (across * side, down * side));
    let rows = rows_of(&mosaic);
    for (j, row) in rows.iter().enumerate() {
        for (i, &got) in row.iter().enumerate() {
            assert_eq!(got.to_bits(), height(i as u32, j as u32).to_bits(), "sample ({i}, {j}): {got}");
        }
    }
    let one = Mosaic::<Heights>::open(std::slice::from_ref(&whole), &MosaicOptions::default()).unwrap();
    let range = mosaic.height_range(&mut |_| Ok(())).unwrap();
    assert_eq!(range, one.height_range(&mut |_| Ok(())).unwrap());

    let utm32 =
        MosaicOptions { crs: Some(Crs::epsg(32632).unwrap()), resolution: Some(10.0), ..MosaicOptions::default() };
    let (cut, one) =
        (Mosaic::<Heights>::open(&inputs, &utm32).unwrap(), Mosaic::<Heights>::open(&[whole], &utm32).unwrap());
    assert_eq!(cut.size(), one.size());
    assert_eq!(cut.georeference().unwrap().origin, one.georeference().unwrap().origin);
    let (a, b) = (rows_of(&cut), rows_of(&one));
    let mut compared = 0;
    for (ra, rb) in a.iter().zip(&b) {
        for (&x, &y) in ra.iter().zip(rb) {
            assert_eq!(x.is_nan(), y.is_nan());
            if !x.is_nan() {
                assert!((x - y).abs() < 1e-3, "{x} against {y}");
                compared += 1;
            }
        }
    }
    assert!(compared > a.len() * a[0].len() / 2, "{compared} samples with data");
}

/// Tiles of one CRS and pixel size, each on its own origin (as tiles warped one by one
/// are), overlapping by a third of a pixel: a sample between two of them is bilinear over
/// both, as if they were one raster, not interpolated from one side.
#[test]
fn tiles_a_fraction_of_a_pixel_apart_are_sampled_across_their_seams() {
    let dir = tempfile::tempdir().unwrap();
    // A surface in metres east and south of the corner: steep east-west.
    let surface = |east: f64, south: f64| 300.0 + (east * 0.037).sin() * 40.0 + south * 0.061;
    let mut inputs = Vec::new();
    for k in 0..24u32 {
        let path = dir.path().join(format!("t{k:02}.tif"));
        // Every 7.7 pixels (77 m), 8 pixels wide; the first on the output's lattice.
        let west = f64::from(k) * 77.0;
        let height = |i: u32, j: u32| surface(west + (f64::from(i) + 0.5) * 10.0, (f64::from(j) + 0.5) * 10.0) as f32;
        utm_tile(&path, (500_000.0 + west, 5_100_000.0), (8, 32), height);
        inputs.push(path);
    }
    // The first input first: a later one is sampled at the seams where it starts.
    let mosaic = Mosaic::<Heights>::open(&inputs, &MosaicOptions::default()).unwrap();
    let origin = mosaic.georeference().unwrap().origin.unwrap();
    assert_eq!(origin, [500_000.0, 5_100_000.0]);
    let (mut worst, mut compared) = (0.0f64, 0);
    for (j, row) in rows_of(&mosaic).iter().enumerate() {
        for (i, &v) in row.iter().enumerate() {
            let (east, south) = ((i as f64 + 0.5) * 10.0, (j as f64 + 0.5) * 10.0);
            // Within the tiles' pixel centres (beyond them there is one side only).
            if v.is_nan() || east > 23.0 * 77.0 + 75.0 || j >= 31 {
                continue;
            }
            worst = worst.max((f64::from(v) - surface(east, south)).abs());
            compared += 1;
        }
    }
    assert!(compared > 150 * 30, "{compared} samples");
    // Bilinear over a 10 m lattice of this surface is off by 0.7 m at most, twice that
    // at a seam, where a corner is itself interpolated in the neighbour; from one side of
    // a seam (each tile sampled alone), by 10 m.
    assert!(worst < 1.5, "{worst} m from the surface");
}

#[test]
fn an_input_a_fraction_of_a_pixel_off_the_grid_is_sampled_bilinearly() {
    // The first input sets the lattice; the second, in the same CRS and spacing, lies
    // 200.37 pixels east and 100.62 pixels south of it, with a hole of nodata. Every
    // output sample over it is the nodata-aware bilinear blend of its four pixels.
    let dir = tempfile::tempdir().unwrap();
    let a = dir.path().join("a.tif");
    utm_tile(&a, (500_000.0, 5_100_000.0), (200, 200), |i, j| 300.0 + i as f32 + j as f32);
    let c = dir.path().join("c.tif");
    let (east, north) = (502_003.7, 5_098_993.8);
    let height = |i: u32, j: u32| {
        if (40..47).contains(&i) && (30..34).contains(&j) {
            f32::NAN
        } else {
            100.0 + (i as f32 * 0.21).sin() * 30.0 + (j * j) as f32 * 0.013
        }
    };
    utm_tile(&c, (east, north), (120, 90), height);
    let mosaic = Mosaic::<Heights>::open(&[a, c], &MosaicOptions::default()).unwrap();
    let origin = mosaic.georeference().unwrap().origin.unwrap();
    let rows = rows_of(&mosaic);
    let (mut checked, mut blended_over_holes) = (0, 0);
    for (y, row) in rows.iter().enumerate() {
        for (x, got) in row.iter().enumerate() {
            // The sample's centre in the second input's pixels (centres at integers).
            let px = (origin[0] + (x as f64 + 0.5) * 10.0 - east) / 10.0 - 0.5;
            let py = (north - (origin[1] - (y as f64 + 0.5) * 10.0)) / 10.0 - 0.5;
            if !(px >= 0.0 && py >= 0.0 && px < 119.0 && py < 89.0) {
                continue;
            }
            let (i, j) = (px.floor() as u32, py.floor() as u32);
            let (fx, fy) = (px - f64::from(i), py - f64::from(j));
            let corners = [
                (height(i, j), (1.0 - fx) * (1.0 - fy)),
                (height(i + 1, j), fx * (1.0 - fy)),
                (height(i, j + 1), (1.0 - fx) * fy),
                (height(i + 1, j + 1), fx * fy),
            ];
            let with_data = corners.iter().filter(|(v, _)| !v.is_nan());
            let weight: f64 = with_data.clone().map(|(_, w)| w).sum();
            let want = with_data.map(|(v, w)| f64::from(*v) * w).sum::<f64>() / weight;
            if weight < 1e-9 {
                assert!(got.is_nan(), "({x}, {y}): {got}, no data expected");
                continue;
            }
            blended_over_holes += usize::from(corners.iter().any(|(v, _)| v.is_nan()));
            assert!((f64::from(*got) - want).abs() < 1e-3, "({x}, {y}): {got}, expected {want}");
            checked += 1;
        }
    }
    assert!(checked > 119 * 89 - 40, "only {checked} samples checked");
    assert!(blended_over_holes > 10, "the hole's rim: {blended_over_holes}");
}

/// A VRT source's NODATA, ScaleRatio and ScaleOffset hold for the height range as for the
/// rows: the archive's encoding follows that range, so a range of the file's own samples
/// would clamp every height (here all 3 000 m above it).
#[test]
fn a_vrt_sources_scale_and_nodata_give_the_range_and_the_tiles() {
    let dir = tempfile::tempdir().unwrap();
    let a = dir.path().join("a.tif");
    let raw = |i: u32, j: u32| if (i, j) == (3, 4) { -9999.0 } else { (i + 2 * j) as f32 };
    utm_tile(&a, (500_000.0, 5_100_000.0), (40, 30), raw);
    let vrt = dir.path().join("scaled.vrt");
    let text = r#"<VRTDataset rasterXSize="40" rasterYSize="30">
  <SRS>EPSG:32633</SRS>
  <GeoTransform>500000, 10, 0, 5100000, 0, -10</GeoTransform>
  <VRTRasterBand dataType="Float32" band="1">
    <ComplexSource>
      <SourceFilename relativeToVRT="1">a.tif</SourceFilename>
      <SourceBand>1</SourceBand>
      <SrcRect xOff="0" yOff="0" xSize="40" ySize="30"/>
      <DstRect xOff="0" yOff="0" xSize="40" ySize="30"/>
      <NODATA>-9999</NODATA>
      <ScaleOffset>3000</ScaleOffset>
      <ScaleRatio>0.5</ScaleRatio>
    </ComplexSource>
  </VRTRasterBand>
</VRTDataset>"#;
    std::fs::write(&vrt, text).unwrap();
    let mosaic = Mosaic::<Heights>::open(&[vrt], &MosaicOptions::default()).unwrap();
    let height = |i: u32, j: u32| if (i, j) == (3, 4) { f64::NAN } else { 3000.0 + f64::from(raw(i, j)) * 0.5 };
    let (lo, hi) = mosaic.height_range(&mut |_| Ok(())).unwrap();
    assert_eq!((lo, hi), (3000.0, 3000.0 + (39.0 + 2.0 * 29.0) * 0.5), "the range of the scaled heights");

    let out = dir.path().join("scaled.tspack");
    let options = TileOptions { tile_size: 16, border: 1, storage: ElevationStorage::Auto };
    tile_elevation(&mosaic, "scaled", &out, options, &Silent::default()).unwrap();
    let reader = Reader::open_mmap(&out).unwrap();
    let meta = reader.metadata();
    assert_eq!((meta.terrain.min_elevation, meta.terrain.max_elevation), (f64::from(lo), f64::from(hi)));
    let enc = meta.layers[0].elevation.unwrap();
    let edge = 16 + 2;
    for (tx, ty) in [(0u32, 0u32), (2, 1)] {
        let stored = reader.tile(TileKey::new(0, 0, tx, ty).unwrap()).unwrap().unwrap();
        let bytes = terrastream_format::payload_bytes(&meta.layers[0], &stored, "tile").unwrap();
        for j in 0..16u32 {
            for i in 0..16u32 {
                let (x, y) = (tx * 16 + i, ty * 16 + j);
                let at = (((j + 1) * edge + i + 1) * 2) as usize;
                let q = u16::from_le_bytes([bytes[at], bytes[at + 1]]);
                let got = if q == 0 { f64::NAN } else { enc.height(f64::from(q)) };
                if x >= 40 || y >= 30 || height(x, y).is_nan() {
                    assert!(got.is_nan(), "({x}, {y}): nodata, not {got}");
                } else {
                    assert!((got - height(x, y)).abs() <= enc.scale / 2.0, "({x}, {y}): {got}, not {}", height(x, y));
                }
            }
        }
    }
}

/// Rows made only in a window of columns (a collection's coarse data under a survey) are
/// the whole rows there, bit for bit: for an input warped onto the grid (on its lattice
/// of exact transforms, anchored at its footprint), one on the grid's own lattice, and
/// one a fraction of a pixel off it; windows across lattice cells, one column wide, at
/// the grid's edges.
#[test]
fn rows_made_in_a_window_of_columns_are_the_whole_rows_there() {
    let dir = tempfile::tempdir().unwrap();
    let a = dir.path().join("a.tif");
    utm_tile(&a, (500_000.0, 5_100_000.0), (300, 120), |i, j| 300.0 + (i as f32 * 0.37).sin() * 40.0 + j as f32);
    let b = dir.path().join("b.tif");
    geographic_tile(&b, 15.0, 46.04, 0.0002, (120, 60));
    let c = dir.path().join("c.tif");
    utm_tile(&c, (501_203.7, 5_099_493.8), (90, 40), |i, j| 100.0 + (i as f32 * 0.21).sin() * 30.0 + j as f32);
    let inputs = [a, b, c];
    let open = || Mosaic::<Heights>::open(&inputs, &MosaicOptions::default()).unwrap();
    let whole = rows_of(&open());
    let width = whole[0].len() as u32;
    assert!(width >= 300, "{width} columns");
    let mut compared = 0;
    for window in [0..1, 5..70, 31..33, 32..64, 63..65, 140..141, 150..260, width - 1..width, 0..width] {
        let mut part = open();
        part.only_columns(window.clone());
        for (j, (row, full)) in rows_of(&part).iter().zip(&whole).enumerate() {
            for i in window.clone().map(|i| i as usize) {
                assert_eq!(row[i].to_bits(), full[i].to_bits(), "window {window:?}, sample ({i}, {j})");
                compared += usize::from(!full[i].is_nan());
            }
        }
    }
    assert!(compared > 10_000, "{compared} samples with data compared");
}
