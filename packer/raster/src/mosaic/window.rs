//! Sampling: the chunks under a row's sample points, held for lock-free bilinear reads.

use super::*;
use crate::kind::{floor, line_point, weights};

/// The value of a pixel beyond an input's own, by its pixel coordinates: its neighbours'
/// of its CRS and pixel size, or no data.
pub(super) type Edge<'a, V> = dyn Fn(i64, i64) -> V + 'a;

/// Input pixel coordinates along one lattice row.
pub(super) type LatticeRow = Arc<Vec<(f64, f64)>>;

/// One decoded strip or tile: values, `w` across.
pub(super) struct Chunk<V> {
    pub(super) values: Vec<V>,
    pub(super) w: usize,
}

impl<V> Chunk<V> {
    pub(super) fn bytes(&self) -> usize {
        self.values.len() * size_of::<V>()
    }
}

/// The chunks under a row's sample points, held for lock-free sampling.
pub(super) struct FileWindow<K: MosaicKind> {
    /// The pixels that may be read: first column and row, end column and row (exclusive).
    pub(super) bounds: (i64, i64, i64, i64),
    /// A chunk's nominal width and height (a strip: the raster's width).
    pub(super) chunk: (usize, usize),
    /// First chunk column and row held, and chunk columns held.
    pub(super) first: (usize, usize),
    pub(super) across: usize,
    pub(super) held: Vec<Arc<Chunk<K::Value>>>,
}

impl<K: MosaicKind> FileWindow<K> {
    /// The value of pixel `(x, y)`; no data outside the window, for nodata, or outside
    /// the chunks held.
    pub(super) fn get(&self, x: i64, y: i64) -> K::Value {
        if x < self.bounds.0 || y < self.bounds.1 || x >= self.bounds.2 || y >= self.bounds.3 {
            return K::NONE;
        }
        #[expect(clippy::cast_sign_loss, clippy::cast_possible_truncation, reason = "checked in range above")]
        let (x, y) = (x as usize, y as usize);
        let (cx, cy) = (x / self.chunk.0, y / self.chunk.1);
        let (Some(dx), Some(dy)) = (cx.checked_sub(self.first.0), cy.checked_sub(self.first.1)) else {
            return K::NONE;
        };
        if dx >= self.across {
            return K::NONE;
        }
        let Some(chunk) = self.held.get(dy * self.across + dx) else { return K::NONE };
        let (lx, ly) = (x - cx * self.chunk.0, y - cy * self.chunk.1);
        chunk.values.get(ly * chunk.w + lx).copied().unwrap_or(K::NONE)
    }

    /// Fills the no-data samples of `out` with pixels `x0 ..` of row `y`; those outside the
    /// window or the chunks held stay as they are.
    #[expect(clippy::cast_sign_loss, clippy::cast_possible_truncation, reason = "clamped into the window")]
    pub(super) fn fill_row(&self, x0: i64, y: i64, out: &mut [K::Value]) {
        if y < self.bounds.1 || y >= self.bounds.3 {
            return;
        }
        let y = y as usize;
        let cy = y / self.chunk.1;
        let Some(dy) = cy.checked_sub(self.first.1) else { return };
        let ly = y - cy * self.chunk.1;
        let (from, to) = (x0.max(self.bounds.0), (x0 + out.len() as i64).min(self.bounds.2));
        let mut x = from;
        while x < to {
            let cx = x as usize / self.chunk.0;
            let lx = x as usize - cx * self.chunk.0;
            let n = (self.chunk.0 - lx).min((to - x) as usize);
            let chunk = cx
                .checked_sub(self.first.0)
                .filter(|&d| d < self.across)
                .and_then(|dx| self.held.get(dy * self.across + dx));
            if let Some(chunk) = chunk {
                let at = ly * chunk.w + lx;
                let src = chunk.values.get(at..at + n.min(chunk.w.saturating_sub(lx))).unwrap_or_default();
                let dst = &mut out[(x - x0) as usize..];
                for (d, s) in dst.iter_mut().zip(src) {
                    if K::is_none(d) {
                        *d = *s;
                    }
                }
            }
            x += n as i64;
        }
    }

    /// Pixels `(x, y)`, `(x + 1, y)`, `(x, y + 1)` and `(x + 1, y + 1)` when all four lie
    /// inside the window, in one column of chunks held: in one chunk, or the lower two in
    /// the chunk below (strips one row high, GDAL's default, always are).
    pub(super) fn quad(&self, x: i64, y: i64) -> Option<[K::Value; 4]> {
        if x < self.bounds.0 || y < self.bounds.1 || x + 1 >= self.bounds.2 || y + 1 >= self.bounds.3 {
            return None;
        }
        #[expect(clippy::cast_sign_loss, clippy::cast_possible_truncation, reason = "checked in range above")]
        let (x, y) = (x as usize, y as usize);
        let (cx, cy) = (x / self.chunk.0, y / self.chunk.1);
        let (lx, ly) = (x - cx * self.chunk.0, y - cy * self.chunk.1);
        if lx + 1 >= self.chunk.0 {
            return None;
        }
        let (dx, dy) = (cx.checked_sub(self.first.0)?, cy.checked_sub(self.first.1)?);
        if dx >= self.across {
            return None;
        }
        let chunk = self.held.get(dy * self.across + dx)?;
        if lx + 1 >= chunk.w {
            return None;
        }
        let at = ly * chunk.w + lx;
        let row = chunk.values.get(at..at + 2)?;
        let next = if ly + 1 < self.chunk.1 {
            chunk.values.get(at + chunk.w..at + chunk.w + 2)?
        } else {
            let below = self.held.get((dy + 1) * self.across + dx)?;
            below.values.get(lx..lx + 2)?
        };
        Some([row[0], row[1], next[0], next[1]])
    }

    /// Bilinear value at pixel coordinates `p` (centres at integers) over the corners with
    /// data (`edge`'s beyond the raster's pixels); no data where none has.
    pub(super) fn bilinear(&self, p: (f64, f64), edge: &Edge<'_, K::Value>) -> K::Value {
        if !(p.0.is_finite() && p.1.is_finite()) {
            return K::NONE;
        }
        let (x0, y0) = (floor(p.0), floor(p.1));
        self.blend_at(x0, y0, weights(p, x0, y0), edge)
    }

    /// The blend of pixels `(x0, y0)`, `(x0 + 1, y0)`, `(x0, y0 + 1)` and `(x0 + 1, y0 + 1)`
    /// with weights `w`; those beyond the raster's pixels are `edge`'s.
    pub(super) fn blend_at(&self, x0: i64, y0: i64, w: [f64; 4], edge: &Edge<'_, K::Value>) -> K::Value {
        let b = self.bounds;
        let get = |x: i64, y: i64| if x < b.0 || y < b.1 || x >= b.2 || y >= b.3 { edge(x, y) } else { self.get(x, y) };
        // Usually all four corners lie in one chunk: read them with one lookup.
        let [a, b, c, d] =
            self.quad(x0, y0).unwrap_or_else(|| [get(x0, y0), get(x0 + 1, y0), get(x0, y0 + 1), get(x0 + 1, y0 + 1)]);
        K::blend(&[(a, w[0]), (b, w[1]), (c, w[2]), (d, w[3])])
    }

    /// [`Self::bilinear`] into each sample of `out` with no data yet, at the points
    /// `(x0 + k, y)`, `k` = 0, 1, …: an input a fraction of a pixel off the output grid.
    /// The weights are the same for all.
    pub(super) fn shifted_into(&self, x0: f64, y: f64, out: &mut [K::Value], edge: &Edge<'_, K::Value>) {
        let (ix, iy) = (floor(x0), floor(y));
        let w = weights((x0, y), ix, iy);
        let mut k = 0;
        while k < out.len() {
            #[expect(clippy::cast_possible_wrap, reason = "row lengths are far below 2^63")]
            let x = ix + k as i64;
            match self.row_pair(x, iy) {
                // The run of samples whose corners these two rows hold, blended at once.
                Some(r) => {
                    #[expect(clippy::cast_sign_loss, clippy::cast_possible_truncation, reason = "x is held")]
                    let (i, n) = ((x - r.base) as usize, ((r.end - x) as usize).min(out.len() - k));
                    K::blend_run(&r.top[i..=i + n], &r.bottom[i..=i + n], w, &mut out[k..k + n]);
                    k += n;
                }
                None => {
                    if K::is_none(&out[k]) {
                        out[k] = self.blend_at(x, iy, w, edge);
                    }
                    k += 1;
                }
            }
        }
    }

    /// [`Self::bilinear`] at each point `start + k * step`, `k` = 0, 1, …, whose sample in
    /// `out` has no data yet: a warp's samples between two exact points of its lattice.
    /// Each run of them between the same two rows of one chunk column (most lines are one
    /// run: a lattice cell is some 32 samples) is found with a few tests, not one a point,
    /// and sampled at once ([`MosaicKind::blend_line`]).
    ///
    /// `pair` keeps the last pair of rows found, for the next line of the row.
    pub(super) fn line_into<'w>(
        &'w self,
        (start, step): ((f64, f64), (f64, f64)),
        out: &mut [K::Value],
        edge: &Edge<'_, K::Value>,
        pair: &mut Option<RowPair<'w, K::Value>>,
    ) {
        let n = out.len();
        let mut k = 0;
        while k < n {
            let p = line_point(start, step, k);
            let (x0, y0) = (floor(p.0), floor(p.1));
            let finite = p.0.is_finite() && p.1.is_finite();
            if finite && !pair.as_ref().is_some_and(|r| r.holds(x0, y0)) {
                *pair = self.row_pair(x0, y0);
            }
            let Some(r) = pair.as_ref().filter(|_| finite) else {
                // Outside the window by a pixel or more: no corner has data.
                let b = self.bounds;
                if finite && K::is_none(&out[k]) && x0 >= b.0 - 1 && y0 >= b.1 - 1 && x0 < b.2 && y0 < b.3 {
                    out[k] = self.bilinear(p, edge);
                }
                k += 1;
                continue;
            };
            // The points' columns and rows move one way along the line (a multiple of
            // one step added to the start is monotonic, rounding included): the pair
            // holds a run of them from this one on, found by bisection.
            let held = |i: usize| {
                let q = line_point(start, step, i);
                q.0.is_finite() && q.1.is_finite() && r.holds(floor(q.0), floor(q.1))
            };
            let end = if held(n - 1) {
                n
            } else {
                // held(lo - 1), not held(hi).
                let (mut lo, mut hi) = (k + 1, n - 1);
                while lo < hi {
                    let mid = usize::midpoint(lo, hi);
                    if held(mid) {
                        lo = mid + 1;
                    } else {
                        hi = mid;
                    }
                }
                lo
            };
            r.prefetch_ahead(x0);
            K::blend_line(r.top, r.bottom, (r.base, y0), (start, step, k), &mut out[k..end]);
            k = end;
        }
    }

    /// The two chunk rows [`Self::quad`] reads for `(x, y)`, and every `x` it reads them
    /// for at this `y`.
    pub(super) fn row_pair(&self, x: i64, y: i64) -> Option<RowPair<'_, K::Value>> {
        if x < self.bounds.0 || y < self.bounds.1 || x + 1 >= self.bounds.2 || y + 1 >= self.bounds.3 {
            return None;
        }
        #[expect(clippy::cast_sign_loss, clippy::cast_possible_truncation, reason = "checked in range above")]
        let (xu, yu) = (x as usize, y as usize);
        let (cx, cy) = (xu / self.chunk.0, yu / self.chunk.1);
        let ly = yu - cy * self.chunk.1;
        let (dx, dy) = (cx.checked_sub(self.first.0)?, cy.checked_sub(self.first.1)?);
        if dx >= self.across {
            return None;
        }
        let chunk = self.held.get(dy * self.across + dx)?;
        let top = chunk.values.get(ly * chunk.w..(ly + 1) * chunk.w)?;
        let below = || self.held.get((dy + 1) * self.across + dx);
        let (bottom, ahead) = if ly + 1 < self.chunk.1 {
            let ahead = if ly + 2 < self.chunk.1 {
                chunk.values.get((ly + 2) * chunk.w..)
            } else {
                below().map(|b| b.values.as_slice())
            };
            (chunk.values.get((ly + 1) * chunk.w..(ly + 2) * chunk.w)?, ahead)
        } else {
            let below = below()?;
            (below.values.get(..chunk.w.min(below.w))?, below.values.get(below.w..))
        };
        #[expect(clippy::cast_possible_wrap, reason = "pixel indices are far below 2^63")]
        let base = (cx * self.chunk.0) as i64;
        #[expect(clippy::cast_possible_wrap, reason = "chunk widths are far below 2^63")]
        let width = self.chunk.0.min(top.len()).min(bottom.len()) as i64;
        let pair = RowPair {
            y,
            from: base.max(self.bounds.0),
            end: (base + width).min(self.bounds.2) - 1,
            base,
            top,
            bottom,
            ahead: ahead.unwrap_or_default(),
        };
        pair.holds(x, y).then_some(pair)
    }
}

/// Two rows of pixels of one chunk column (the second may come from the chunk below): the
/// corners of every bilinear sample between rows `y` and `y + 1` and columns `from ..
/// end + 1`.
pub(super) struct RowPair<'w, V> {
    pub(super) y: i64,
    /// First and end (exclusive) of the left corners' columns.
    pub(super) from: i64,
    pub(super) end: i64,
    /// The column of `top[0]`.
    pub(super) base: i64,
    pub(super) top: &'w [V],
    pub(super) bottom: &'w [V],
    /// The row after `bottom` (and what follows it in its chunk), if held.
    pub(super) ahead: &'w [V],
}

impl<V: Copy> RowPair<'_, V> {
    pub(super) fn holds(&self, x: i64, y: i64) -> bool {
        y == self.y && x >= self.from && x < self.end
    }
    /// Asks for the two cache lines of the row after `bottom` from column `x` on. A
    /// reprojected row crosses the input's rows at a slant (one every ~16 samples for
    /// two UTM zones): the next output row needs those lines as its lower corners, and
    /// the hardware's own prefetchers do not see a pattern in these steps. Without
    /// this, that load misses the cache every ~16 samples (measured: 11–16 % of the
    /// CPU time of making a two-zone mosaic's rows).
    #[expect(clippy::cast_sign_loss, clippy::cast_possible_truncation, reason = "held: at or after base")]
    pub(super) fn prefetch_ahead(&self, x: i64) {
        let i = (x - self.base) as usize;
        for at in [i, i + 64 / size_of::<V>()] {
            if let Some(v) = self.ahead.get(at) {
                prefetch(v);
            }
        }
    }
}

/// A hint to bring the cache line holding `v` closer; nothing else happens.
#[inline]
pub(super) fn prefetch<V>(v: &V) {
    #[cfg(target_arch = "x86_64")]
    // SAFETY: a prefetch reads nothing into the program and cannot fault; `v` is a
    // valid reference besides. (Unsafe only for the target-feature rule: SSE is part
    // of every x86-64 target.)
    #[expect(unsafe_code, reason = "a prefetch hint: reads nothing, cannot fault")]
    unsafe {
        std::arch::x86_64::_mm_prefetch::<{ std::arch::x86_64::_MM_HINT_T0 }>(std::ptr::from_ref(v).cast());
    }
    #[cfg(not(target_arch = "x86_64"))]
    let _ = v;
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A window of 5 x 5 chunks of 8 x 4 heights (some without data) over 40 x 20 pixels.
    fn window() -> FileWindow<Heights> {
        let (cw, ch) = (8usize, 4usize);
        let held = (0..25)
            .map(|c| {
                let (cx, cy) = (c % 5, c / 5);
                let values = (0..cw * ch)
                    .map(|i| {
                        let (x, y) = (cx * cw + i % cw, cy * ch + i / cw);
                        #[expect(clippy::cast_precision_loss, reason = "test values")]
                        if (x * 7 + y * 13) % 29 == 0 {
                            f32::NAN
                        } else {
                            (x * x) as f32 * 0.31 - (y * 3) as f32 + 0.013
                        }
                    })
                    .collect();
                Arc::new(Chunk { values, w: cw })
            })
            .collect();
        FileWindow { bounds: (0, 0, 40, 20), chunk: (cw, ch), first: (0, 0), across: 5, held }
    }

    /// A line of points sampled by `line_into` (runs found by bisection, the pair of rows
    /// kept from one line to the next) gives what sampling each point on its own gives:
    /// `blend_unit` over its four corners where one pair of chunk rows holds them, else
    /// `bilinear` within a pixel of the window, else nothing; samples with data kept.
    /// Lines cross chunk columns and rows, run either way, and leave the window.
    #[test]
    fn a_line_is_its_points_sampled_one_by_one() {
        let w = window();
        let edge = |_: i64, _: i64| 100.0f32;
        let mut seed = 7u64;
        let mut next = move || {
            seed = seed.wrapping_mul(6_364_136_223_846_793_005).wrapping_add(1_442_695_040_888_963_407);
            #[expect(clippy::cast_precision_loss, reason = "a test's random fraction")]
            let f = (seed >> 11) as f64 / (1u64 << 53) as f64;
            f
        };
        let (mut runs, mut outside) = (0, 0);
        let mut pair = None;
        for line in 0..400 {
            let start = (next() * 46.0 - 3.0, next() * 24.0 - 2.0);
            let step = (next() * 3.0 - 1.5, (next() - 0.5) * 0.2);
            #[expect(clippy::cast_possible_truncation, clippy::cast_sign_loss, reason = "a test's length")]
            let n = 1 + (next() * 40.0) as usize;
            let mut out: Vec<f32> = (0..n).map(|k| if k % 7 == 3 { -5.0 } else { f32::NAN }).collect();
            let mut expected = out.clone();
            for (k, o) in expected.iter_mut().enumerate() {
                let p = line_point(start, step, k);
                let (x0, y0) = (floor(p.0), floor(p.1));
                if !o.is_nan() {
                    continue;
                }
                if let Some(r) = w.row_pair(x0, y0) {
                    #[expect(clippy::cast_sign_loss, clippy::cast_possible_truncation, reason = "held by the pair")]
                    let i = (x0 - r.base) as usize;
                    let c = weights(p, x0, y0);
                    *o = Heights::blend_unit(&[
                        (r.top[i], c[0]),
                        (r.top[i + 1], c[1]),
                        (r.bottom[i], c[2]),
                        (r.bottom[i + 1], c[3]),
                    ]);
                    runs += 1;
                } else if x0 >= -1 && y0 >= -1 && x0 < 40 && y0 < 20 {
                    *o = w.bilinear(p, &edge);
                    outside += 1;
                }
            }
            w.line_into((start, step), &mut out, &edge, &mut pair);
            let bits = |v: &[f32]| v.iter().map(|f| f.to_bits()).collect::<Vec<_>>();
            assert_eq!(bits(&out), bits(&expected), "line {line} from {start:?} by {step:?}");
        }
        assert!(runs > 2000 && outside > 50, "{runs} points in pairs, {outside} at the edges");
    }
}
