//! Elevation encodings: 8-bit schemes, integer samples, the u16 quantization.

use super::*;

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
