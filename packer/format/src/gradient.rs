//! The `zstd_gradient` payload compression of `raw_u16` tiles (FORMAT.md §3.6): each
//! sample replaced by its difference from the plane through its west, north and
//! north-west neighbours, zigzag-coded, the low bytes of all samples then the high bytes,
//! in one zstd frame.
//!
//! Terrain is smooth at any scale a tile holds: the plane's guess is within a few steps of
//! most samples, so nearly every high byte is zero and the low bytes are small, which zstd
//! packs about twice as tightly as the samples themselves (docs/BENCHMARKS.md, "Elevation
//! tiles: the gradient coding"). The coding is exact, and wraps: any u16 grid comes back
//! bit for bit.

use std::borrow::Cow;

use crate::compression::zstd_decompress;
use crate::error::{Error, Result};
use crate::metadata::{Layer, PayloadCompression};

/// Zigzag: 0, -1, 1, -2, ... -> 0, 1, 2, 3, ..., so that small differences of either sign
/// have a zero high byte.
fn zigzag(d: u16) -> u16 {
    (d << 1) ^ 0u16.wrapping_sub(d >> 15)
}

fn unzigzag(z: u16) -> u16 {
    (z >> 1) ^ 0u16.wrapping_sub(z & 1)
}

/// Codes `samples` (little-endian u16, `edge` x `edge`, row-major) into byte planes,
/// ready for zstd: `2 * edge^2` bytes, the low bytes of the coded samples then the high.
/// The first row is coded from its west neighbour (the first sample from zero), the first
/// column from its north neighbour, the rest from west + north - north-west.
///
/// # Panics
/// If `samples` is not `2 * edge^2` bytes.
pub fn gradient_encode(samples: &[u8], edge: usize) -> Vec<u8> {
    let mut out = Vec::new();
    gradient_encode_into(samples, edge, &mut out);
    out
}

/// [`gradient_encode`] into `out` (resized; a buffer kept from tile to tile is neither
/// allocated nor cleared again).
///
/// # Panics
/// If `samples` is not `2 * edge^2` bytes.
pub fn gradient_encode_into(samples: &[u8], edge: usize, out: &mut Vec<u8>) {
    let n = edge * edge;
    assert_eq!(samples.len(), 2 * n, "gradient_encode: {} bytes for {edge}x{edge} samples", samples.len());
    out.resize(2 * n, 0);
    if edge == 0 {
        return;
    }
    let (low, high) = out.split_at_mut(n);
    let (mut north, mut row) = (vec![0u16; edge], vec![0u16; edge]);
    let mut guess = vec![0u16; edge];
    for (r, bytes) in samples.chunks_exact(2 * edge).enumerate() {
        load(&mut row, bytes);
        if r == 0 {
            // West neighbours: the row shifted by one, zero first.
            guess[1..].copy_from_slice(&row[..edge - 1]);
        } else {
            guess[0] = north[0];
            // Every guess from samples known before the row: a loop without carried state.
            for (((g, &w), &nn), &nw) in
                guess[1..].iter_mut().zip(&row[..edge - 1]).zip(&north[1..]).zip(&north[..edge - 1])
            {
                *g = w.wrapping_add(nn).wrapping_sub(nw);
            }
        }
        let at = r * edge;
        for (((l, h), &v), &g) in low[at..at + edge].iter_mut().zip(&mut high[at..at + edge]).zip(&row).zip(&guess) {
            let [a, b] = zigzag(v.wrapping_sub(g)).to_le_bytes();
            (*l, *h) = (a, b);
        }
        std::mem::swap(&mut north, &mut row);
    }
}

/// Undoes [`gradient_encode`]: `2 * edge^2` bytes of planes -> the samples, little-endian.
///
/// # Errors
/// [`Error::Decompress`] naming `what` if `planes` is not `2 * edge^2` bytes.
pub fn gradient_decode(planes: &[u8], edge: usize, what: &str) -> Result<Vec<u8>> {
    let n = edge * edge;
    if planes.len() != 2 * n {
        return Err(Error::Decompress {
            section: what.into(),
            reason: format!("{} bytes of gradient-coded samples, {} expected for {edge}x{edge}", planes.len(), 2 * n),
        });
    }
    let mut out = vec![0u8; 2 * n];
    if edge == 0 {
        return Ok(out);
    }
    let (low, high) = planes.split_at(n);
    let (mut north, mut row) = (vec![0u16; edge], vec![0u16; edge]);
    for (r, bytes) in out.chunks_exact_mut(2 * edge).enumerate() {
        let at = r * edge;
        for ((v, &l), &h) in row.iter_mut().zip(&low[at..at + edge]).zip(&high[at..at + edge]) {
            *v = unzigzag(u16::from_le_bytes([l, h]));
        }
        // sample[c] = sample[c-1] + (north[c] - north[c-1]) + d[c]: the north steps added
        // in a loop without carried state, then one running sum along the row.
        if r > 0 {
            row[0] = row[0].wrapping_add(north[0]);
            for ((v, &nn), &nw) in row[1..].iter_mut().zip(&north[1..]).zip(&north[..edge - 1]) {
                *v = v.wrapping_add(nn.wrapping_sub(nw));
            }
        }
        let mut west = 0u16;
        for v in &mut row {
            west = west.wrapping_add(*v);
            *v = west;
        }
        for (o, v) in bytes.chunks_exact_mut(2).zip(&row) {
            o.copy_from_slice(&v.to_le_bytes());
        }
        std::mem::swap(&mut north, &mut row);
    }
    Ok(out)
}

fn load(row: &mut [u16], bytes: &[u8]) {
    for (v, b) in row.iter_mut().zip(bytes.chunks_exact(2)) {
        *v = u16::from_le_bytes([b[0], b[1]]);
    }
}

/// A stored tile of `layer` -> the bytes of its format: its payload compression undone
/// (borrowed when there is none). `what` names the tile in errors.
///
/// # Errors
/// [`Error::Decompress`] naming `what` if the payload is not a frame of the layer's
/// compression, inflates past what its tiles can hold, or (`zstd_gradient`) is not a
/// tile's worth of samples.
pub fn payload_bytes<'a>(layer: &Layer, stored: &'a [u8], what: &str) -> Result<Cow<'a, [u8]>> {
    match layer.compression {
        PayloadCompression::None => Ok(Cow::Borrowed(stored)),
        PayloadCompression::Zstd => Ok(Cow::Owned(zstd_decompress(stored, layer.max_payload_bytes(), what)?)),
        PayloadCompression::ZstdGradient => {
            let edge = layer.stored_edge();
            let planes = zstd_decompress(stored, 2 * (edge as u64) * (edge as u64), what)?;
            Ok(Cow::Owned(gradient_decode(&planes, edge, what)?))
        }
    }
}

#[cfg(test)]
#[expect(clippy::cast_possible_truncation, reason = "test grids: values chosen to fit")]
mod tests {
    use super::*;

    fn grid(edge: usize, f: impl Fn(usize, usize) -> u16) -> Vec<u8> {
        (0..edge * edge).flat_map(|i| f(i % edge, i / edge).to_le_bytes()).collect()
    }

    #[test]
    fn zigzag_round_trips_every_value() {
        for d in 0..=u16::MAX {
            assert_eq!(unzigzag(zigzag(d)), d);
        }
        assert_eq!([zigzag(0), zigzag(u16::MAX), zigzag(1), zigzag(0u16.wrapping_sub(2))], [0, 1, 2, 3]);
    }

    /// Any grid comes back bit for bit: smooth, noisy, wrapping at both ends of u16.
    #[test]
    fn grids_round_trip_exactly() {
        let mut seed = 0x9e37_79b9_u32;
        let mut noise = move || {
            seed ^= seed << 13;
            seed ^= seed >> 17;
            seed ^= seed << 5;
            seed as u16
        };
        let noisy: Vec<u16> = (0..65 * 65).map(|_| noise()).collect();
        let cases = [
            (0, grid(0, |_, _| 0)),
            (1, grid(1, |_, _| 40_000)),
            (2, grid(2, |x, y| [0, u16::MAX, 1, 32_768][x + 2 * y])),
            (65, grid(65, |x, y| (1000 + 7 * x + 13 * y) as u16)),
            (65, grid(65, |x, y| noisy[y * 65 + x])),
            (65, grid(65, |x, y| if (x + y).is_multiple_of(2) { 0 } else { u16::MAX })),
        ];
        for (edge, samples) in cases {
            let coded = gradient_encode(&samples, edge);
            assert_eq!(coded.len(), samples.len());
            assert_eq!(gradient_decode(&coded, edge, "t").unwrap(), samples, "edge {edge}");
        }
    }

    /// A plane of samples codes to its first row's steps and zeros below: what makes the
    /// coding pay.
    #[test]
    fn a_sloping_plane_codes_to_zeros_below_its_first_row() {
        let edge = 9;
        let coded = gradient_encode(&grid(edge, |x, y| (500 + 3 * x + 5 * y) as u16), edge);
        let (low, high) = coded.split_at(edge * edge);
        // The first sample from zero (500 -> 1000 zigzagged), then steps of 3 (-> 6).
        assert_eq!((low[0], high[0]), (1000u16.to_le_bytes()[0], 1000u16.to_le_bytes()[1]));
        assert!(high[1..].iter().all(|&b| b == 0));
        assert!(low[1..edge].iter().all(|&b| b == 6), "{:?}", &low[..edge]);
        for row in low.chunks(edge).skip(1) {
            // The first column: the north step, 5, zigzagged; the rest: on the plane.
            assert_eq!(row[0], 10);
            assert!(row[1..].iter().all(|&b| b == 0), "{row:?}");
        }
    }

    #[test]
    fn wrong_sizes_name_the_tile() {
        let e = gradient_decode(&[0; 7], 2, "tile 0/1/2/3").unwrap_err().to_string();
        assert!(e.contains("tile 0/1/2/3") && e.contains("7 bytes"), "{e}");
    }
}
