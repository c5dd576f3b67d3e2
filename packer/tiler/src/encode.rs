//! Encoding tiles: heights (quantized u16 or f32) and imagery (PNG, JPEG, WebP, BC1/BC7).

use terrastream_format::{ElevationEncoding, ElevationScheme, TileKey};
use terrastream_pack::zstd_compress;

use crate::bc;
use crate::error::{Error, Result};
use crate::options::TextureFormat;
use terrastream_raster::min_max;

/// Heights -> the layer's raw little-endian samples, into `raw` (replacing what it held),
/// and the lowest and highest height as stored (after quantization).
pub(crate) fn encode_heights(samples: &[f32], encoding: &ElevationEncoding, raw: &mut Vec<u8>) -> (f32, f32) {
    if encoding.scheme == ElevationScheme::Float32 {
        raw.clear();
        for v in samples {
            raw.extend_from_slice(&v.to_le_bytes());
        }
        return min_max(samples);
    }
    // The hot loop of a DEM, without branches so that it vectorizes (measured 3x faster
    // than a scalar loop): f32 arithmetic (4 lanes on baseline x86-64), no libm call, no
    // float-to-int conversion (Rust's saturating `as` stays scalar there) and no height
    // decoded per sample. Steps are powers of two (see `plan`), so the scaling is exact and
    // the one rounding is the subtraction's, under 1/200 of a step on the u16 range.
    // Clamped to 1..=65535, adding 2^23 puts the nearest integer (ties to even) in the low
    // mantissa bits. A NaN (nodata) stays NaN through the clamp and becomes 0. Heights grow
    // with `q`, so the range is that of the lowest and highest `q` other than 0 (`q - 1`
    // wraps 0 to the top, out of the way).
    const TO_INTEGER: f32 = 8_388_608.0;
    #[expect(clippy::cast_possible_truncation, reason = "see above: f32 arithmetic on heights kept as f32")]
    let (offset, inverse) = (encoding.offset as f32, (1.0 / encoding.scale) as f32);
    let (mut lo, mut hi) = (u16::MAX, 0u16);
    // Every byte is written below: zeroed only where it grows past any tile before it
    // (clearing it first zeroed all of it for every tile).
    raw.truncate(samples.len() * 2);
    raw.resize(samples.len() * 2, 0);
    for (out, &v) in raw.chunks_exact_mut(2).zip(samples) {
        let x = ((v - offset) * inverse).clamp(1.0, 65_535.0);
        #[expect(clippy::cast_possible_truncation, reason = "the low 16 bits hold the integer")]
        let q = if x.is_nan() { 0 } else { (x + TO_INTEGER).to_bits() as u16 };
        lo = lo.min(q.wrapping_sub(1));
        hi = hi.max(q);
        out.copy_from_slice(&q.to_le_bytes());
    }
    if hi == 0 {
        return (f32::INFINITY, f32::NEG_INFINITY);
    }
    let lo = lo + 1;
    #[expect(clippy::cast_possible_truncation, reason = "heights are f32")]
    let height = |q: u16| encoding.height(f64::from(q)) as f32;
    (height(lo), height(hi))
}

/// Heights as a reader decodes them once stored: each sample through the encoding and
/// back (the same arithmetic as [`encode_heights`]), NaN kept. What a pyramid level is made
/// of, so that the levels above a split LOD come out the same from decoded tiles.
pub(crate) fn quantize_heights(samples: &mut [f32], encoding: &ElevationEncoding) {
    if encoding.scheme == ElevationScheme::Float32 {
        return;
    }
    const TO_INTEGER: f32 = 8_388_608.0;
    #[expect(clippy::cast_possible_truncation, reason = "as in encode_heights")]
    let (offset, inverse) = (encoding.offset as f32, (1.0 / encoding.scale) as f32);
    let quantized = |x: f32| {
        #[expect(clippy::cast_possible_truncation, reason = "the low 16 bits hold the integer")]
        let q = (x + TO_INTEGER).to_bits() as u16;
        f64::from(q)
    };
    if let Some((base, step)) = f32_exact(encoding) {
        // As below, in f32 (twice the lanes, no conversions): the rounded `x` is `q`
        // exactly, and `(base + q) * step` is the f64 result, which f32 holds exactly.
        for v in samples {
            let x = ((*v - offset) * inverse).clamp(1.0, 65_535.0);
            let h = (base + ((x + TO_INTEGER) - TO_INTEGER)) * step;
            *v = if v.is_nan() { *v } else { h };
        }
        return;
    }
    if encoding.scheme == ElevationScheme::QuantizedU16 {
        // `encoding.height` hoisted, and no branch (a NaN is kept by the select): it
        // vectorizes. Every LOD-0 row goes through this on the pyramid's thread.
        let (offset64, scale) = (encoding.offset, encoding.scale);
        for v in samples {
            let x = ((*v - offset) * inverse).clamp(1.0, 65_535.0);
            #[expect(clippy::cast_possible_truncation, reason = "heights are f32")]
            let h = (offset64 + quantized(x) * scale) as f32;
            *v = if v.is_nan() { *v } else { h };
        }
        return;
    }
    for v in samples {
        let x = ((*v - offset) * inverse).clamp(1.0, 65_535.0);
        if !x.is_nan() {
            #[expect(clippy::cast_possible_truncation, reason = "heights are f32")]
            let h = encoding.height(quantized(x)) as f32;
            *v = h;
        }
    }
}

/// A u16 encoding whose heights f32 computes exactly, as `(base + q) * step`: a
/// power-of-two step (what `plan` makes) and an offset a whole number of steps, small
/// enough that `base + q` stays below 2^24. Then each stored height is that integer times
/// a power of two, in f64 and in f32 alike.
fn f32_exact(encoding: &ElevationEncoding) -> Option<(f32, f32)> {
    let (offset, scale) = (encoding.offset, encoding.scale);
    let power_of_two = (2f64.powi(-60)..=2f64.powi(60)).contains(&scale) && scale.to_bits().trailing_zeros() >= 52;
    let base = offset / scale;
    let whole = base.fract() == 0.0 && base.abs() < f64::from((1u32 << 24) - (1 << 16));
    #[expect(clippy::cast_possible_truncation, reason = "both are exact in f32 (checked above)")]
    (encoding.scheme == ElevationScheme::QuantizedU16 && power_of_two && whole).then_some((base as f32, scale as f32))
}

/// A stored elevation tile's raw samples (zstd already undone) -> heights, NaN for
/// nodata: the inverse of [`encode_heights`] after [`quantize_heights`].
pub(crate) fn decode_heights(raw: &[u8], encoding: &ElevationEncoding) -> Vec<f32> {
    if encoding.scheme == ElevationScheme::Float32 {
        return raw.chunks_exact(4).map(|b| f32::from_le_bytes([b[0], b[1], b[2], b[3]])).collect();
    }
    if encoding.scheme == ElevationScheme::QuantizedU16 {
        // `encoding.height` for this scheme, hoisted and branch-free (it vectorizes): what
        // the merge's re-derivation of tiles around an update spends most of its time on.
        let (offset, scale) = (encoding.offset, encoding.scale);
        return raw
            .chunks_exact(2)
            .map(|b| {
                let q = u16::from_le_bytes([b[0], b[1]]);
                #[expect(clippy::cast_possible_truncation, reason = "heights are f32")]
                let h = (offset + f64::from(q) * scale) as f32;
                if q == 0 { f32::NAN } else { h }
            })
            .collect();
    }
    raw.chunks_exact(2)
        .map(|b| match u16::from_le_bytes([b[0], b[1]]) {
            0 => f32::NAN,
            #[expect(clippy::cast_possible_truncation, reason = "heights are f32")]
            q => encoding.height(f64::from(q)) as f32,
        })
        .collect()
}

/// A stored PNG or WebP texture tile -> its RGBA pixels (`edge` x `edge`); None for
/// another format (lossy ones are not decoded back: the levels above them would differ).
pub(crate) fn decode_texture(key: TileKey, bytes: &[u8], edge: usize, format: TextureFormat) -> Result<Vec<[u8; 4]>> {
    let err = |e: &dyn std::fmt::Display| Error::Encode { tile: key, reason: format!("decoding: {e}") };
    let (data, channels) = match format {
        TextureFormat::Png => {
            let mut decoder = png::Decoder::new(std::io::Cursor::new(bytes));
            decoder.set_transformations(png::Transformations::EXPAND);
            let mut reader = decoder.read_info().map_err(|e| err(&e))?;
            let mut data = vec![0; reader.output_buffer_size().ok_or_else(|| err(&"too large"))?];
            let info = reader.next_frame(&mut data).map_err(|e| err(&e))?;
            data.truncate(info.buffer_size());
            let channels = info.color_type.samples();
            if info.bit_depth != png::BitDepth::Eight || info.width as usize != edge || info.height as usize != edge {
                return Err(err(&format!(
                    "{}x{} {:?}, {edge}x{edge} 8-bit expected",
                    info.width, info.height, info.bit_depth
                )));
            }
            (data, channels)
        }
        TextureFormat::Webp => {
            let mut decoder = image_webp::WebPDecoder::new(std::io::Cursor::new(bytes)).map_err(|e| err(&e))?;
            let (w, h) = decoder.dimensions();
            if w as usize != edge || h as usize != edge {
                return Err(err(&format!("{w}x{h}, {edge}x{edge} expected")));
            }
            let mut data = vec![0; decoder.output_buffer_size().ok_or_else(|| err(&"too large"))?];
            decoder.read_image(&mut data).map_err(|e| err(&e))?;
            let channels = if decoder.has_alpha() { 4 } else { 3 };
            (data, channels)
        }
        _ => return Err(err(&format!("{} tiles are lossy: not decoded to make coarser levels", format.name()))),
    };
    Ok(data
        .chunks_exact(channels)
        .map(|p| match *p {
            [r, g, b, a] => [r, g, b, a],
            [r, g, b] => [r, g, b, 255],
            [g, a] => [g, g, g, a],
            [g] => [g, g, g, 255],
            _ => [0; 4],
        })
        .take(edge * edge)
        .collect())
}

/// One texture tile's stored bytes.
pub(crate) fn encode_texture(
    key: TileKey,
    pixels: &[[u8; 4]],
    edge: usize,
    format: TextureFormat,
    zstd_level: i32,
) -> Result<Vec<u8>> {
    let opaque = pixels.iter().all(|p| p[3] == 255);
    let rgb = || -> Vec<u8> {
        // Sized once: a `flat_map` collect cannot know its length and grows by doubling.
        let mut rgb = Vec::with_capacity(pixels.len() * 3);
        for p in pixels {
            rgb.extend_from_slice(&p[..3]);
        }
        rgb
    };
    let side = u32::try_from(edge).map_err(|_| Error::TileTooLarge { edge, format: format.name() })?;
    let err = |e: &dyn std::fmt::Display| Error::Encode { tile: key, reason: e.to_string() };
    Ok(match format {
        TextureFormat::Png => {
            let mut out = Vec::new();
            let mut encoder = png::Encoder::new(&mut out, side, side);
            encoder.set_depth(png::BitDepth::Eight);
            encoder.set_color(if opaque { png::ColorType::Rgb } else { png::ColorType::Rgba });
            encoder.set_compression(png::Compression::Fast);
            encoder.set_filter(png::Filter::Paeth);
            let data = if opaque { rgb() } else { pixels.as_flattened().to_vec() };
            encoder.write_header().map_err(|e| err(&e))?.write_image_data(&data).map_err(|e| err(&e))?;
            out
        }
        TextureFormat::Jpeg(quality) => {
            let side16 = u16::try_from(edge).map_err(|_| Error::TileTooLarge { edge, format: "JPEG" })?;
            let mut out = Vec::new();
            jpeg_encoder::Encoder::new(&mut out, quality)
                .encode(&rgb(), side16, side16, jpeg_encoder::ColorType::Rgb)
                .map_err(|e| err(&e))?;
            out
        }
        TextureFormat::Webp => {
            let mut out = Vec::new();
            let (data, colour) = if opaque {
                (rgb(), image_webp::ColorType::Rgb8)
            } else {
                (pixels.as_flattened().to_vec(), image_webp::ColorType::Rgba8)
            };
            image_webp::WebPEncoder::new(&mut out).encode(&data, side, side, colour).map_err(|e| err(&e))?;
            out
        }
        TextureFormat::Bc1 | TextureFormat::Bc7 => {
            zstd_compress(&bc::encode(pixels, edge, format == TextureFormat::Bc7), zstd_level).map_err(|e| err(&e))?
        }
    })
}
