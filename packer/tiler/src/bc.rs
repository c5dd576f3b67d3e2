//! BC1 and BC7 block encoders for texture tiles a GPU samples with no CPU decode.
//!
//! Both fit each 4x4 block's colours along their principal axis (a few power iterations
//! on the covariance), quantize the two endpoints, then give every texel the palette entry
//! nearest to it. BC1 stores 5:6:5 endpoints and 2-bit indices (4 colours, or 3 and
//! transparent for blocks with cut-out alpha); BC7 uses mode 6: RGBA endpoints of 7 bits
//! plus a p-bit each, 4-bit indices, so alpha is smooth and colours keep 8-bit precision.
//! Texels are sRGB-encoded values, as the GPU's `*UnormSrgb` formats expect.

/// Texels of one block, row-major.
type Block = [[u8; 4]; 16];

/// `edge` x `edge` RGBA texels -> blocks, row-major, `ceil(edge / 4)` a side; a partial
/// block at the right or bottom repeats the last column or row.
pub fn encode(texels: &[[u8; 4]], edge: usize, bc7: bool) -> Vec<u8> {
    let blocks = edge.div_ceil(4);
    let mut out = Vec::with_capacity(blocks * blocks * if bc7 { 16 } else { 8 });
    for by in 0..blocks {
        for bx in 0..blocks {
            let mut block: Block = [[0; 4]; 16];
            for (i, t) in block.iter_mut().enumerate() {
                let x = (bx * 4 + i % 4).min(edge - 1);
                let y = (by * 4 + i / 4).min(edge - 1);
                *t = texels[y * edge + x];
            }
            if bc7 {
                out.extend_from_slice(&bc7_block(&block));
            } else {
                out.extend_from_slice(&bc1_block(&block));
            }
        }
    }
    out
}

/// The two ends of the block's colours along their principal axis over `channels`
/// channels, for the texels `use_texel` keeps.
fn principal_ends(block: &Block, channels: usize, use_texel: impl Fn(&[u8; 4]) -> bool) -> ([f64; 4], [f64; 4]) {
    let texels: Vec<[f64; 4]> =
        block.iter().filter(|t| use_texel(t)).map(|t| [t[0], t[1], t[2], t[3]].map(f64::from)).collect();
    if texels.is_empty() {
        return ([0.0; 4], [0.0; 4]);
    }
    #[expect(clippy::cast_precision_loss, reason = "at most 16 texels")]
    let n = texels.len() as f64;
    let mut mean = [0.0; 4];
    for t in &texels {
        for c in 0..channels {
            mean[c] += t[c] / n;
        }
    }
    let mut cov = [[0.0; 4]; 4];
    for t in &texels {
        for i in 0..channels {
            for j in 0..channels {
                cov[i][j] += (t[i] - mean[i]) * (t[j] - mean[j]);
            }
        }
    }
    // Power iteration from the diagonal of largest spread.
    let mut axis = [0.0; 4];
    axis[..channels].fill(1.0);
    for _ in 0..8 {
        let mut next = [0.0; 4];
        for i in 0..channels {
            for j in 0..channels {
                next[i] += cov[i][j] * axis[j];
            }
        }
        let norm = next.iter().map(|v| v * v).sum::<f64>().sqrt();
        if norm < 1e-9 {
            break;
        }
        axis = next.map(|v| v / norm);
    }
    let project = |t: &[f64; 4]| (0..channels).map(|c| (t[c] - mean[c]) * axis[c]).sum::<f64>();
    let (mut lo, mut hi) = (f64::INFINITY, f64::NEG_INFINITY);
    for t in &texels {
        let p = project(t);
        lo = lo.min(p);
        hi = hi.max(p);
    }
    let end = |p: f64| {
        let mut e = mean;
        for c in 0..channels {
            e[c] = (mean[c] + axis[c] * p).clamp(0.0, 255.0);
        }
        e
    };
    (end(lo), end(hi))
}

fn distance(a: &[f64; 4], b: &[u8; 4], channels: usize) -> f64 {
    (0..channels).map(|c| (a[c] - f64::from(b[c])).powi(2)).sum()
}

/// One BC1 block.
pub fn bc1_block(block: &Block) -> [u8; 8] {
    let cut_out = block.iter().any(|t| t[3] < 128);
    let (e0, e1) = principal_ends(block, 3, |t| t[3] >= 128);
    #[expect(clippy::cast_possible_truncation, clippy::cast_sign_loss, reason = "0..=31 / 0..=63")]
    let pack = |e: [f64; 4]| -> u16 {
        let q = |v: f64, max: f64| (v / 255.0 * max).round().clamp(0.0, max) as u16;
        (q(e[0], 31.0) << 11) | (q(e[1], 63.0) << 5) | q(e[2], 31.0)
    };
    let unpack = |c: u16| -> [f64; 4] {
        let (r, g, b) = (f64::from(c >> 11), f64::from((c >> 5) & 63), f64::from(c & 31));
        [(r * 255.0 / 31.0).round(), (g * 255.0 / 63.0).round(), (b * 255.0 / 31.0).round(), 255.0]
    };
    let (mut c0, mut c1) = (pack(e0), pack(e1));
    // 4-colour blocks need c0 > c1, 3-colour (cut-out) blocks c0 <= c1.
    if (cut_out && c0 > c1) || (!cut_out && c0 < c1) {
        std::mem::swap(&mut c0, &mut c1);
    }
    let (p0, p1) = (unpack(c0), unpack(c1));
    let mix = |a: f64, b: f64, wa: f64, wb: f64| (a * wa + b * wb) / (wa + wb);
    let palette: Vec<[f64; 4]> = if cut_out || c0 == c1 {
        vec![p0, p1, [0, 1, 2, 3].map(|c| mix(p0[c], p1[c], 1.0, 1.0))]
    } else {
        vec![
            p0,
            p1,
            [0, 1, 2, 3].map(|c| mix(p0[c], p1[c], 2.0, 1.0)),
            [0, 1, 2, 3].map(|c| mix(p0[c], p1[c], 1.0, 2.0)),
        ]
    };
    let mut indices = 0u32;
    for (i, t) in block.iter().enumerate() {
        let index = if cut_out && t[3] < 128 {
            3
        } else {
            (0..palette.len())
                .min_by(|&a, &b| distance(&palette[a], t, 3).total_cmp(&distance(&palette[b], t, 3)))
                .unwrap_or(0)
        };
        indices |= u32::try_from(index).unwrap_or(0) << (2 * i);
    }
    let mut out = [0u8; 8];
    out[0..2].copy_from_slice(&c0.to_le_bytes());
    out[2..4].copy_from_slice(&c1.to_le_bytes());
    out[4..8].copy_from_slice(&indices.to_le_bytes());
    out
}

const BC7_WEIGHTS: [u32; 16] = [0, 4, 9, 13, 17, 21, 26, 30, 34, 38, 43, 47, 51, 55, 60, 64];

/// One BC7 block in mode 6.
pub fn bc7_block(block: &Block) -> [u8; 16] {
    let (e0, e1) = principal_ends(block, 4, |_| true);
    // Each endpoint: 7 bits per channel plus one p-bit shared by its channels.
    #[expect(clippy::cast_possible_truncation, clippy::cast_sign_loss, reason = "0..=127")]
    let quantize = |e: [f64; 4]| -> ([u32; 4], u32) {
        let mut best = ([0u32; 4], 0u32, f64::INFINITY);
        for p in 0..2u32 {
            let q = e.map(|v| ((v - f64::from(p)) / 2.0).round().clamp(0.0, 127.0) as u32);
            let err: f64 = (0..4).map(|c| (f64::from((q[c] << 1) | p) - e[c]).powi(2)).sum();
            if err < best.2 {
                best = (q, p, err);
            }
        }
        (best.0, best.1)
    };
    let (mut q0, mut p0) = quantize(e0);
    let (mut q1, mut p1) = quantize(e1);
    let colour = |q: [u32; 4], p: u32| q.map(|v| (v << 1) | p);
    let indices_for = |a: [u32; 4], b: [u32; 4]| -> [u32; 16] {
        let palette: Vec<[f64; 4]> = BC7_WEIGHTS
            .iter()
            .map(|&w| [0, 1, 2, 3].map(|c| f64::from(((64 - w) * a[c] + w * b[c] + 32) >> 6)))
            .collect();
        let mut out = [0u32; 16];
        for (o, t) in out.iter_mut().zip(block) {
            let best = (0..16usize)
                .min_by(|&i, &j| distance(&palette[i], t, 4).total_cmp(&distance(&palette[j], t, 4)))
                .unwrap_or(0);
            *o = u32::try_from(best).unwrap_or(0);
        }
        out
    };
    let mut indices = indices_for(colour(q0, p0), colour(q1, p1));
    // The anchor (texel 0) index has an implicit top bit of 0: swap the ends if needed.
    if indices[0] >= 8 {
        std::mem::swap(&mut q0, &mut q1);
        std::mem::swap(&mut p0, &mut p1);
        indices = indices.map(|i| 15 - i);
    }
    let mut bits: u128 = 1 << 6;
    let mut at = 7;
    let mut put = |value: u32, width: u32| {
        bits |= u128::from(value) << at;
        at += width;
    };
    for c in 0..4 {
        put(q0[c], 7);
        put(q1[c], 7);
    }
    put(p0, 1);
    put(p1, 1);
    put(indices[0], 3);
    for &i in &indices[1..] {
        put(i, 4);
    }
    bits.to_le_bytes()
}

#[cfg(test)]
#[allow(clippy::cast_possible_truncation, clippy::needless_range_loop)]
pub(crate) mod tests {
    use super::*;

    /// Reference BC1 decoder.
    pub(crate) fn decode_bc1(b: &[u8]) -> Block {
        let c0 = u16::from_le_bytes([b[0], b[1]]);
        let c1 = u16::from_le_bytes([b[2], b[3]]);
        let rgb = |c: u16| -> [u32; 3] {
            [u32::from(c >> 11) * 255 / 31, u32::from((c >> 5) & 63) * 255 / 63, u32::from(c & 31) * 255 / 31]
        };
        let (a, z) = (rgb(c0), rgb(c1));
        #[expect(clippy::cast_possible_truncation, reason = "0..=255")]
        let px = |v: [u32; 3], alpha: u8| [v[0] as u8, v[1] as u8, v[2] as u8, alpha];
        let palette = if c0 > c1 {
            [
                px(a, 255),
                px(z, 255),
                px([0, 1, 2].map(|c| (2 * a[c] + z[c]) / 3), 255),
                px([0, 1, 2].map(|c| (a[c] + 2 * z[c]) / 3), 255),
            ]
        } else {
            [px(a, 255), px(z, 255), px([0, 1, 2].map(|c| (a[c] + z[c]) / 2), 255), [0; 4]]
        };
        let indices = u32::from_le_bytes([b[4], b[5], b[6], b[7]]);
        std::array::from_fn(|i| palette[((indices >> (2 * i)) & 3) as usize])
    }

    /// Reference BC7 mode-6 decoder.
    pub(crate) fn decode_bc7_mode6(b: &[u8]) -> Block {
        let bits = u128::from_le_bytes(b.try_into().unwrap());
        assert_eq!(bits & 0x7f, 1 << 6, "mode 6");
        let mut at = 7;
        let mut take = |w: u32| {
            let v = ((bits >> at) & ((1 << w) - 1)) as u32;
            at += w;
            v
        };
        let mut e = [[0u32; 4]; 2];
        for c in 0..4 {
            e[0][c] = take(7);
            e[1][c] = take(7);
        }
        let (p0, p1) = (take(1), take(1));
        let e0 = e[0].map(|v| (v << 1) | p0);
        let e1 = e[1].map(|v| (v << 1) | p1);
        std::array::from_fn(|i| {
            let index = take(if i == 0 { 3 } else { 4 });
            let w = BC7_WEIGHTS[index as usize];
            #[expect(clippy::cast_possible_truncation, reason = "0..=255")]
            [0, 1, 2, 3].map(|c| (((64 - w) * e0[c] + w * e1[c] + 32) >> 6) as u8)
        })
    }

    /// Colours along one line through RGB (as in most blocks of real imagery), in a
    /// shuffled order, with a little noise off the line.
    fn gradient(seed: u32) -> Block {
        #[expect(clippy::cast_possible_truncation, reason = "0..=255")]
        std::array::from_fn(|i| {
            let t = (i as u32 * 7 + seed) % 16;
            let noise = (i as u32 * 13 + seed * 5) % 5;
            [(seed * 5 + t * 9 + noise) as u8, (30 + seed * 3 + t * 6) as u8, (220 - t * 8 - noise) as u8, 255]
        })
    }

    fn max_error(a: &Block, b: &Block, channels: usize) -> u8 {
        a.iter().zip(b).flat_map(|(p, q)| (0..channels).map(move |c| p[c].abs_diff(q[c]))).max().unwrap()
    }

    #[test]
    fn bc1_blocks_decode_close_to_their_texels() {
        for seed in 0..20 {
            let block = gradient(seed);
            let decoded = decode_bc1(&bc1_block(&block));
            // 5:6:5 endpoints and 4 levels along a line of 135/255: within 24/255.
            assert!(max_error(&block, &decoded, 3) <= 24, "seed {seed}: {block:?} -> {decoded:?}");
        }
        let solid = [[90, 120, 30, 255]; 16];
        assert!(max_error(&solid, &decode_bc1(&bc1_block(&solid)), 3) <= 4);
    }

    #[test]
    fn bc1_cut_out_alpha_becomes_transparent_texels() {
        let mut block = [[250, 10, 10, 255]; 16];
        block[5] = [0; 4];
        let decoded = decode_bc1(&bc1_block(&block));
        assert_eq!(decoded[5][3], 0);
        assert!(max_error(&block, &decoded, 3) <= 8 || decoded[0][0] >= 240, "{decoded:?}");
        assert_eq!(decoded[0][3], 255);
    }

    #[test]
    fn bc7_blocks_decode_within_a_few_levels() {
        for seed in 0..20 {
            // Alpha along the same line (an edge fading out).
            let block = gradient(seed).map(|t| [t[0], t[1], t[2], 255 - (220 - t[2]) / 2]);
            let decoded = decode_bc7_mode6(&bc7_block(&block));
            assert!(max_error(&block, &decoded, 4) <= 12, "seed {seed}: {block:?} -> {decoded:?}");
        }
        let solid = [[91, 121, 31, 200]; 16];
        assert!(max_error(&solid, &decode_bc7_mode6(&bc7_block(&solid)), 4) <= 1);
    }

    #[test]
    fn partial_blocks_repeat_the_edge() {
        let edge = 6;
        let texels: Vec<[u8; 4]> = (0..edge * edge).map(|i| [(i * 7) as u8, 0, 0, 255]).collect();
        let blocks = encode(&texels, edge, true);
        assert_eq!(blocks.len(), 2 * 2 * 16);
        let last = decode_bc7_mode6(&blocks[48..64]);
        // Block (1, 1) covers texels 4..8; 6 and 7 repeat texel 5.
        assert!(last[3][0].abs_diff(texels[4 * edge + 5][0]) <= 4, "{last:?}");
    }
}
