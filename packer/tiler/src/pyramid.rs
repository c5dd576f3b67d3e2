//! A LOD pyramid built from a stream of rows, keeping only a band of rows per level.
//!
//! Rows of LOD 0 are pushed in from the top. Each level keeps the rows its next row of
//! tiles needs (tile size + two borders) and halves pairs of rows into the level above as
//! they arrive; a row of tiles is cut and encoded (its tiles in parallel, on the pool, while
//! the caller goes on halving) as soon as its rows, borders included, are all in. Memory
//! per level is one band of about `tile + 2 * border + 1` rows of that level's width, so
//! the whole pyramid holds under two LOD-0 bands whatever the raster's height (the tiler
//! keeps one more band in flight from its reading thread, and the rows of tiles being cut
//! on the pool hold up to two more). Encoded tiles go to a [`Spool`] on disk, then into the
//! archive in the archive's order.

use std::collections::VecDeque;
use std::fs::File;
use std::io::{BufWriter, Read, Seek, SeekFrom, Write};
use std::path::Path;
use std::sync::{Arc, mpsc};

use rayon::prelude::*;
use terrastream_format::{Metadata, TileKey};
use terrastream_pack::Writer;
use terrastream_pack::progress::Progress;

use crate::error::{Error, Result};

/// The samples of tile column `tx` of a band of `res + 2 * border` rows (`None`: above or
/// below the raster), each row holding the level's columns from `first` on (as many as it
/// is long): columns `tx * res - border .. tx * res + res + border`, clipped to the
/// level's `width` and padded with no data outside it and outside the rows' columns.
/// `None` when the tile proper (the border aside) holds no data.
fn tile_samples<S: Pixel>(
    band: &[Option<Arc<Vec<S>>>],
    tx: usize,
    res: usize,
    border: usize,
    width: usize,
    first: usize,
) -> Option<Vec<S>> {
    let edge = res + 2 * border;
    let mut any = false;
    let mut samples = Vec::with_capacity(edge * edge);
    let (from, to) = ((tx * res).saturating_sub(border), (tx * res + res + border).min(width));
    let pad_left = border.saturating_sub(tx * res);
    let pad_right = edge - pad_left - (to - from);
    for (j, row) in band.iter().enumerate() {
        let Some(row) = row else {
            samples.resize(samples.len() + edge, S::NONE);
            continue;
        };
        // The columns `a..b` of the row's that the tile takes (none: `a >= b`).
        let end = first + row.len();
        if (border..border + res).contains(&j) {
            let (a, b) = ((tx * res).max(first), (tx * res + res).min(to).min(end));
            any |= a < b && row[a - first..b - first].iter().any(S::has_data);
        }
        let (a, b) = (from.max(first), to.min(end));
        if a < b {
            samples.resize(samples.len() + pad_left + (a - from), S::NONE);
            samples.extend_from_slice(&row[a - first..b - first]);
            samples.resize(samples.len() + (to - b) + pad_right, S::NONE);
        } else {
            samples.resize(samples.len() + edge, S::NONE);
        }
    }
    any.then_some(samples)
}

/// A sample of a pyramid: a height (NaN = nodata) or an RGBA8 pixel (alpha 0 = none).
pub trait Pixel: Copy + Send + Sync + 'static {
    /// No data.
    const NONE: Self;
    /// Is this a real sample?
    fn has_data(&self) -> bool;
    /// The mean of up to four samples, ignoring (height) or weighting by (alpha) the
    /// missing ones: the 2x2 area average of the next coarser level.
    fn mean4(s: [Self; 4]) -> Self;
    /// Linear interpolation between `a` and `b` at `f` in 0..1 (resampling along x).
    fn lerp(a: Self, b: Self, f: f32) -> Self;
    /// `row` at `taps` (see [`Resample`]): [`Pixel::lerp`] of each tap's two samples.
    fn resample(row: &[Self], taps: &[(u32, u32, f32)]) -> Vec<Self> {
        taps.iter().map(|&(i, j, frac)| Self::lerp(row[i as usize], row[j as usize], frac)).collect()
    }
    /// The same sample, bit for bit (no data equals no data).
    fn same(&self, other: &Self) -> bool;
}

impl Pixel for f32 {
    fn same(&self, other: &Self) -> bool {
        self.to_bits() == other.to_bits()
    }
    const NONE: Self = f32::NAN;
    fn has_data(&self) -> bool {
        !self.is_nan()
    }
    fn mean4(s: [Self; 4]) -> Self {
        if !s.iter().any(|v| v.is_nan()) {
            // The usual case, summed in the same order as below.
            let sum = f64::from(s[0]) + f64::from(s[1]) + f64::from(s[2]) + f64::from(s[3]);
            #[expect(clippy::cast_possible_truncation, reason = "heights are f32")]
            return (sum / 4.0) as f32;
        }
        let (mut sum, mut n) = (0.0f64, 0u32);
        for v in s.into_iter().filter(|v| !v.is_nan()) {
            sum += f64::from(v);
            n += 1;
        }
        #[expect(clippy::cast_possible_truncation, reason = "heights are f32")]
        if n == 0 { f32::NAN } else { (sum / f64::from(n)) as f32 }
    }
    fn lerp(a: Self, b: Self, f: f32) -> Self {
        // NaN exactly when either is: then the other (or NaN). Selects, not branches, in
        // the usual case.
        let v = a + (b - a) * f;
        let other = if a.is_nan() { b } else { a };
        if v.is_nan() { other } else { v }
    }
    fn resample(row: &[Self], taps: &[(u32, u32, f32)]) -> Vec<Self> {
        if row.iter().any(|v| v.is_nan()) {
            return taps.iter().map(|&(i, j, frac)| Self::lerp(row[i as usize], row[j as usize], frac)).collect();
        }
        // No nodata in the row (the usual case): `lerp`'s first value, whose NaN test and
        // selects were a third of the resampling's time.
        taps.iter()
            .map(|&(i, j, frac)| {
                let (a, b) = (row[i as usize], row[j as usize]);
                a + (b - a) * frac
            })
            .collect()
    }
}

impl Pixel for [u8; 4] {
    fn same(&self, other: &Self) -> bool {
        self == other
    }
    const NONE: Self = [0; 4];
    fn has_data(&self) -> bool {
        self[3] > 0
    }
    fn mean4(s: [Self; 4]) -> Self {
        if s.iter().all(|p| p[3] == 255) {
            // All opaque (the usual case): the weighted mean below reduces exactly to
            // (sum + 2) / 4 per channel.
            let mean = |c: usize| {
                let sum = u16::from(s[0][c]) + u16::from(s[1][c]) + u16::from(s[2][c]) + u16::from(s[3][c]);
                #[expect(clippy::cast_possible_truncation, reason = "a mean of four u8 values")]
                let mean = ((sum + 2) / 4) as u8;
                mean
            };
            return [mean(0), mean(1), mean(2), 255];
        }
        let mut sum = [0u32; 4];
        for p in s {
            let a = u32::from(p[3]);
            for c in 0..3 {
                sum[c] += u32::from(p[c]) * a;
            }
            sum[3] += a;
        }
        if sum[3] == 0 {
            return [0; 4];
        }
        #[expect(clippy::cast_possible_truncation, reason = "means of u8 values")]
        let mean = |c: usize| ((sum[c] + sum[3] / 2) / sum[3]) as u8;
        #[expect(clippy::cast_possible_truncation, reason = "a mean of four u8 values")]
        let alpha = ((sum[3] + 2) / 4) as u8;
        [mean(0), mean(1), mean(2), alpha]
    }
    fn lerp(a: Self, b: Self, f: f32) -> Self {
        let f = f64::from(f);
        let (wa, wb) = (f64::from(a[3]) * (1.0 - f), f64::from(b[3]) * f);
        let alpha = wa + wb;
        let mut out = [0u8; 4];
        for c in 0..3 {
            let v = if alpha > 0.0 { (f64::from(a[c]) * wa + f64::from(b[c]) * wb) / alpha } else { 0.0 };
            #[expect(clippy::cast_possible_truncation, clippy::cast_sign_loss, reason = "0..=255")]
            let v = v.round().clamp(0.0, 255.0) as u8;
            out[c] = v;
        }
        #[expect(clippy::cast_possible_truncation, clippy::cast_sign_loss, reason = "0..=255")]
        let a = alpha.round().clamp(0.0, 255.0) as u8;
        out[3] = a;
        out
    }
}

/// Linear resampling of rows along x (edges clamped), from one width to another: each
/// output sample's source index and weight, computed once for every row of a raster.
pub struct Resample {
    /// (left source sample, right source sample, weight of the right one) per output
    /// sample.
    taps: Vec<(u32, u32, f32)>,
    from: usize,
}

impl Resample {
    /// Resamples rows of `from` samples to `to` samples.
    #[must_use]
    pub fn new(from: usize, to: usize) -> Self {
        // Rows are a raster's: u32 samples at most (a wider one is copied as it is).
        if from == to || from == 0 || u32::try_from(from).is_err() {
            return Self { taps: Vec::new(), from };
        }
        #[expect(clippy::cast_precision_loss, reason = "pixel counts")]
        let ratio = to as f64 / from as f64;
        let last = from - 1;
        let taps = (0..to)
            .map(|x| {
                #[expect(clippy::cast_precision_loss, reason = "a pixel index")]
                let sx = ((x as f64 + 0.5) / ratio - 0.5).max(0.0);
                // sx >= 0: truncation is its floor.
                #[expect(clippy::cast_possible_truncation, clippy::cast_sign_loss, reason = "a pixel index >= 0")]
                let x0 = sx as usize;
                #[expect(clippy::cast_precision_loss, reason = "a pixel index")]
                let frac = sx - x0 as f64;
                #[expect(clippy::cast_possible_truncation, reason = "below `from`, a u32; a weight")]
                (x0.min(last) as u32, (x0 + 1).min(last) as u32, frac as f32)
            })
            .collect();
        Self { taps, from }
    }

    /// Whether rows keep their width (each [`Self::row`] is a copy).
    #[must_use]
    pub fn is_identity(&self) -> bool {
        self.taps.is_empty()
    }

    /// `row` (of the width this was made for) at the new width.
    #[must_use]
    pub fn row<S: Pixel>(&self, row: &[S]) -> Vec<S> {
        if self.taps.is_empty() || row.len() != self.from {
            return row.to_vec();
        }
        S::resample(row, &self.taps)
    }
}

/// Two rows of a level -> one row of the next (2x2 means; an odd last column is padded
/// with no data).
pub fn halve_rows<S: Pixel>(a: &[S], b: &[S]) -> Vec<S> {
    let mut out: Vec<S> =
        a.chunks_exact(2).zip(b.chunks_exact(2)).map(|(a, b)| S::mean4([a[0], a[1], b[0], b[1]])).collect();
    if a.len() % 2 == 1 {
        let at = |r: &[S], x: usize| r.get(x).copied().unwrap_or(S::NONE);
        let x = a.len() - 1;
        out.push(S::mean4([at(a, x), S::NONE, at(b, x), S::NONE]));
    }
    out
}

/// Encodes one cut tile into the archive entries it makes (the tile, and for elevation its
/// height range), or none when it should be left missing.
pub type Encode<'a, S> = dyn Fn(TileKey, &[S], usize) -> Result<Vec<(TileKey, Vec<u8>)>> + Sync + 'a;

/// Rounds a row to the precision its tiles store, in place (see [`Pyramid::with_quantize`]).
pub type Quantize<'a, S> = dyn Fn(&mut [S]) + Sync + 'a;

struct Level<S> {
    lod: u8,
    width: usize,
    height: usize,
    /// Rows this level will receive, counted from its top (its `height` unless a
    /// [`Window`] ends above the bottom).
    end: usize,
    /// Rows of tiles cut from it: `cut..cut_end` (none below [`Window::encode_from`]).
    cut_end: usize,
    /// Absolute index of `rows[0]`.
    first: usize,
    /// Shared with the cuts in flight that need them.
    rows: VecDeque<Arc<Vec<S>>>,
    received: usize,
    /// Rows of tiles cut so far.
    cut: usize,
    /// An even row waiting for its odd partner, to be halved into the next level.
    pending: Option<Arc<Vec<S>>>,
}

/// The entries of one cut row of tiles.
type Cut = Result<Vec<(TileKey, Vec<u8>)>>;

/// The part of a layer's pyramid one run builds: all of it ([`Window::full`]), a shard's
/// band of rows up to a split LOD, or the levels above a split LOD made from its rows
/// (the reduce step). Row and tile-row indices are absolute, so a band cut here holds
/// exactly the tiles, bytes and all, that a full run cuts there.
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct Window {
    /// The LOD of the rows pushed in (0; the split LOD for a reduce).
    pub input_lod: u8,
    /// The last LOD built (inclusive).
    pub last_lod: u8,
    /// Tiles are cut from this LOD up; below it levels only pass rows on.
    pub encode_from: u8,
    /// Rows of the input level that will be pushed: from `rows.start` (a multiple of
    /// 2^(last_lod - input_lod)) to `rows.end` (the same, or the level's height).
    pub rows: std::ops::Range<usize>,
    /// Input-level rows whose tiles are cut (tile rows of every level built, aligned as
    /// `rows` is, times the tile size).
    pub band: std::ops::Range<usize>,
    /// The column of the level each row pushed in starts at: a row holds that column and
    /// the next as many as it is long, and no data elsewhere (0, rows as wide as the
    /// level: every window but one level's part; a single level only).
    pub first_column: usize,
}

impl Window {
    /// Nothing: no rows read, no tiles cut.
    pub fn empty() -> Self {
        Self { input_lod: 0, last_lod: 0, encode_from: 0, rows: 0..0, band: 0..0, first_column: 0 }
    }

    /// Every level of a layer of `num_lods` levels over `height` rows of LOD 0.
    pub fn full(num_lods: u8, height: usize) -> Self {
        Self {
            input_lod: 0,
            last_lod: num_lods.saturating_sub(1),
            encode_from: 0,
            rows: 0..height,
            band: 0..height,
            first_column: 0,
        }
    }
}

/// Cuts one layer's tiles out of a stream of LOD-0 rows.
pub struct Pyramid<'a, S: Pixel> {
    layer: u8,
    /// Applied to each row as it enters a level: the precision tiles store (heights
    /// quantized as the layer encodes them), so that each level is the 2x2 mean of the
    /// level below *as stored*, and a reduce from decoded tiles gives the same bytes.
    quantize: Option<&'a Quantize<'a, S>>,
    res: usize,
    border: usize,
    levels: Vec<Level<S>>,
    /// The level's column each row starts at (see [`Window::first_column`]).
    first_column: usize,
    encode: &'a Encode<'a, S>,
    metadata: &'a Metadata,
    spool: &'a mut Spool,
    progress: &'a dyn Progress,
    /// Rows of tiles being cut and encoded on the pool, and where they report.
    in_flight: usize,
    done: (mpsc::Sender<Cut>, mpsc::Receiver<Cut>),
}

/// Rows of tiles cut at once, all levels: a cut runs on the pool while the next rows are
/// halved and the next band is read; each holds its band's rows until it is done.
const CUTS_IN_FLIGHT: usize = 2;

impl<'a, S: Pixel> Pyramid<'a, S> {
    /// A pyramid of `lods` levels over a `width` x `height` LOD 0, for layer `layer` of
    /// `metadata` (its tile size and border).
    pub fn new(
        metadata: &'a Metadata,
        layer: u8,
        (width, height): (u32, u32),
        encode: &'a Encode<'a, S>,
        spool: &'a mut Spool,
        progress: &'a dyn Progress,
    ) -> Result<Self> {
        let lods = metadata.layers.get(usize::from(layer)).map_or(1, |l| l.num_lods);
        Self::window(metadata, layer, (width, height), &Window::full(lods, height as usize), encode, spool, progress)
    }

    /// The part `window` of the pyramid over a `width` x `height` LOD 0; rows pushed in
    /// are those of `window.rows` at `window.input_lod`.
    ///
    /// # Errors
    /// [`Error::Pyramid`] for a layer not in the metadata or a window that does not fit it.
    pub fn window(
        metadata: &'a Metadata,
        layer: u8,
        (width, height): (u32, u32),
        window: &Window,
        encode: &'a Encode<'a, S>,
        spool: &'a mut Spool,
        progress: &'a dyn Progress,
    ) -> Result<Self> {
        let bad = |reason: String| Error::Pyramid { layer, lod: window.input_lod, reason };
        let l = metadata.layers.get(usize::from(layer)).ok_or_else(|| bad("no such layer in the metadata".into()))?;
        let res = l.tile_resolution as usize;
        let Window { input_lod, last_lod, encode_from, rows, band, first_column } = window.clone();
        let input_height = (height as usize).div_ceil(1 << input_lod).max(1);
        let step = 1usize << last_lod.saturating_sub(input_lod);
        let aligned = |n: usize, unit: usize| n.is_multiple_of(unit) || n == input_height;
        if last_lod >= l.num_lods
            || input_lod > last_lod
            || rows.end > input_height
            || !aligned(rows.start, step)
            || !aligned(rows.end, step)
            || !aligned(band.start, step * res)
            || !aligned(band.end, step * res)
            || band.start < rows.start
            || band.end > rows.end
            || (first_column > 0 && last_lod > input_lod)
        {
            return Err(bad(format!("window {window:?} does not fit {} LODs of {input_height} rows", l.num_lods)));
        }
        let levels = (input_lod..=last_lod)
            .map(|lod| {
                let shrink = |n: u32| (n.div_ceil(1 << lod)).max(1) as usize;
                let down = 1usize << (lod - input_lod);
                let level_height = shrink(height);
                let end = if rows.end == input_height { level_height } else { rows.end / down };
                let cuts = lod >= encode_from;
                let tile_rows = level_height.div_ceil(res);
                let cut = if cuts { band.start / down / res } else { tile_rows };
                let cut_end = if !cuts || band.end == input_height { tile_rows } else { band.end / down / res };
                Level {
                    lod,
                    width: shrink(width),
                    height: level_height,
                    end,
                    cut_end,
                    first: rows.start / down,
                    rows: VecDeque::new(),
                    received: rows.start / down,
                    cut,
                    pending: None,
                }
            })
            .collect();
        Ok(Self {
            layer,
            quantize: None,
            res,
            border: usize::from(l.border),
            levels,
            first_column,
            encode,
            metadata,
            spool,
            progress,
            in_flight: 0,
            done: mpsc::channel(),
        })
    }

    /// Rows entering each level go through `quantize` first (see the field).
    #[must_use]
    pub fn with_quantize(mut self, quantize: &'a Quantize<'a, S>) -> Self {
        self.quantize = Some(quantize);
        self
    }

    /// Rows of LOD 0 that one row of tiles is cut from, borders included.
    pub fn band_rows(&self) -> usize {
        self.res + 2 * self.border
    }

    /// Samples held now, all levels (the band each keeps, and rows waiting to be halved;
    /// the cuts in flight hold up to two bands more).
    pub fn held_samples(&self) -> usize {
        self.levels.iter().map(|l| (l.rows.len() + usize::from(l.pending.is_some())) * l.width).sum()
    }

    /// Adds the next row of LOD 0. Rows of tiles are cut on `scope`'s pool while the
    /// caller goes on.
    ///
    /// # Errors
    /// Encoding and spool errors, an interrupted error (Ctrl-C).
    pub fn push<'s>(&mut self, row: Vec<S>, scope: &rayon::Scope<'s>) -> Result<()>
    where
        'a: 's,
    {
        self.push_rows(vec![row], scope)
    }

    /// Adds the next rows of LOD 0, top first: the same as pushing them one by one, but
    /// their rounding and their halving into every level above run in parallel on the
    /// pool, where one row at a time leaves that work to the calling thread alone (it was
    /// the part of a run that more cores did not shorten).
    ///
    /// # Errors
    /// As [`Pyramid::push`].
    pub fn push_rows<'s>(&mut self, mut rows: Vec<Vec<S>>, scope: &rayon::Scope<'s>) -> Result<()>
    where
        'a: 's,
    {
        if !rows_in_parallel() {
            // One row at a time through every level, while it is in the cache.
            for mut row in rows {
                if let Some(quantize) = self.quantize {
                    quantize(&mut row);
                }
                self.push_at(0, vec![Arc::new(row)], scope)?;
            }
            return Ok(());
        }
        if let Some(quantize) = self.quantize {
            rows.par_iter_mut().for_each(|row| quantize(row));
        }
        self.push_at(0, rows.into_iter().map(Arc::new).collect(), scope)
    }

    /// Rows entering level `l` (already rounded), top first.
    fn push_at<'s>(&mut self, l: usize, rows: Vec<Arc<Vec<S>>>, scope: &rayon::Scope<'s>) -> Result<()>
    where
        'a: 's,
    {
        if rows.is_empty() {
            return Ok(());
        }
        let has_next = l + 1 < self.levels.len();
        let level = &mut self.levels[l];
        if level.received + rows.len() > level.end {
            return Err(Error::Pyramid {
                layer: self.layer,
                lod: level.lod,
                reason: format!("more than {} rows", level.end),
            });
        }
        // Pairs of rows (the first may be the even row left waiting by the last call).
        let mut pairs = Vec::new();
        if has_next {
            for row in &rows {
                match level.pending.take() {
                    None => level.pending = Some(Arc::clone(row)),
                    Some(even) => pairs.push((even, Arc::clone(row))),
                }
            }
        }
        let quantize = self.quantize;
        let halve = |(even, odd): (Arc<Vec<S>>, Arc<Vec<S>>)| Arc::new(rounded_half(&even, &odd, quantize));
        let halves: Vec<Arc<Vec<S>>> = if rows_in_parallel() {
            pairs.into_par_iter().map(halve).collect()
        } else {
            pairs.into_iter().map(halve).collect()
        };
        for row in rows {
            let level = &mut self.levels[l];
            // A level no tiles are cut from keeps no rows (only the one waiting for its pair).
            if level.cut < level.cut_end {
                level.rows.push_back(row);
            } else {
                level.first += 1;
            }
            level.received += 1;
            self.cut_ready(l, scope)?;
        }
        self.push_at(l + 1, halves, scope)
    }

    /// Ends the stream: pads odd levels, cuts what is left, and waits for every cut.
    ///
    /// # Errors
    /// As [`Pyramid::push`]; [`Error::Pyramid`] if rows are missing.
    pub fn finish<'s>(mut self, scope: &rayon::Scope<'s>) -> Result<()>
    where
        'a: 's,
    {
        for l in 0..self.levels.len() {
            let level = &self.levels[l];
            if level.received != level.end {
                return Err(Error::Pyramid {
                    layer: self.layer,
                    lod: level.lod,
                    reason: format!("{} of {} rows arrived", level.received, level.end),
                });
            }
            if let Some(even) = self.levels[l].pending.take() {
                let half = rounded_half(&even, &vec![S::NONE; even.len()], self.quantize);
                self.push_at(l + 1, vec![Arc::new(half)], scope)?;
            }
        }
        while self.in_flight > 0 {
            self.collect_one()?;
        }
        Ok(())
    }

    /// Waits for one cut in flight and spools its tiles.
    fn collect_one(&mut self) -> Result<()> {
        let tiles = receive(&self.done.1).ok_or(Error::Panicked { thread: "tile cutting" })?;
        self.in_flight -= 1;
        for (key, bytes) in tiles? {
            self.spool.add(self.metadata, key, &bytes)?;
        }
        Ok(())
    }

    /// Starts cutting every row of tiles of level `l` whose rows (and lower border) have
    /// arrived, on `scope`'s pool (the tiles of a row in parallel); first waits for older
    /// cuts while [`CUTS_IN_FLIGHT`] are running.
    fn cut_ready<'s>(&mut self, l: usize, scope: &rayon::Scope<'s>) -> Result<()>
    where
        'a: 's,
    {
        let (res, border, first) = (self.res, self.border, self.first_column);
        loop {
            let level = &self.levels[l];
            if level.cut >= level.cut_end {
                return Ok(());
            }
            let need = ((level.cut + 1) * res + border).min(level.height);
            if level.received < need {
                return Ok(());
            }
            self.progress.check()?;
            while self.in_flight >= CUTS_IN_FLIGHT {
                self.collect_one()?;
            }
            let level = &self.levels[l];
            let ty = level.cut;
            let edge = res + 2 * border;
            let (width, cols) = (level.width, level.width.div_ceil(res));
            // The band: row `j` of the tiles is the level's row `ty * res + j - border`,
            // none above or below the raster.
            let band: Vec<Option<Arc<Vec<S>>>> = (0..edge)
                .map(|j| {
                    (ty * res + j)
                        .checked_sub(border)
                        .filter(|&y| y >= level.first && y < level.height)
                        .and_then(|y| level.rows.get(y - level.first).cloned())
                })
                .collect();
            let (encode, progress, sender) = (self.encode, self.progress, self.done.0.clone());
            let (layer, lod) = (self.layer, level.lod);
            self.in_flight += 1;
            scope.spawn(move |_| {
                let tiles = (0..cols)
                    .into_par_iter()
                    .map(|tx| {
                        let samples = tile_samples(&band, tx, res, border, width, first);
                        progress.advance(1);
                        let Some(samples) = samples else { return Ok(Vec::new()) };
                        let coordinate = |n: usize| {
                            u32::try_from(n).map_err(|_| Error::Pyramid {
                                layer,
                                lod,
                                reason: format!("tile coordinate {n} out of range"),
                            })
                        };
                        let key = TileKey::new(layer, lod, coordinate(tx)?, coordinate(ty)?)?;
                        encode(key, &samples, edge)
                    })
                    .collect::<Result<Vec<_>>>()
                    .map(|tiles| tiles.into_iter().flatten().collect());
                // The receiver lives until every cut is collected.
                let _ = sender.send(tiles);
            });
            let level = &mut self.levels[l];
            level.cut += 1;
            let keep_from = (level.cut * res).saturating_sub(border);
            while level.first < keep_from && !level.rows.is_empty() {
                level.rows.pop_front();
                level.first += 1;
            }
        }
    }
}

/// Two rows of a level -> one row of the next, rounded as the layer stores it.
fn rounded_half<S: Pixel>(even: &[S], odd: &[S], quantize: Option<&Quantize<'_, S>>) -> Vec<S> {
    let mut half = halve_rows(even, odd);
    if let Some(quantize) = quantize {
        quantize(&mut half);
    }
    half
}

/// Whether [`Pyramid::push_rows`] rounds and halves rows on the pool, or on the calling
/// thread as they come. On the pool, that work stops being the one thread that more cores
/// do not shorten; but each batch then waits for the pool, which costs more than it saves
/// where the pool is small and the calling thread is one more core at work beside it.
/// Measured on 16 cores (a 151 M-sample DEM): with 16 threads 0.29 s against 0.50 s, with 8
/// 0.35 against 0.44, with 4 the same, with 2 0.78 against 0.64 (docs/BENCHMARKS.md).
fn rows_in_parallel() -> bool {
    rayon::current_num_threads() > 4
}

/// The next message of `from`, None once every sender is gone. On one of rayon's own
/// threads (a caller tiling from inside the pool), blocking would keep that thread from
/// running the pool work the message waits for (the cuts, the reader's decoding), so it
/// runs pool work until the message comes.
pub(crate) fn receive<T>(from: &mpsc::Receiver<T>) -> Option<T> {
    if rayon::current_thread_index().is_none() {
        return from.recv().ok();
    }
    loop {
        match from.try_recv() {
            Ok(message) => return Some(message),
            Err(mpsc::TryRecvError::Empty) => {
                if rayon::yield_now() != Some(rayon::Yield::Executed) {
                    std::thread::yield_now();
                }
            }
            Err(mpsc::TryRecvError::Disconnected) => return None,
        }
    }
}

/// Encoded tiles on disk, in the order they were cut, with an in-memory index (about
/// 24 bytes a tile) to hand them to the archive writer in archive order.
pub struct Spool {
    file: BufWriter<File>,
    len: u64,
    index: Vec<(u64, TileKey, u64, u32)>,
}

impl Spool {
    /// A spool in a temporary file in `folder` (removed when dropped).
    ///
    /// # Errors
    /// [`Error::File`] if the folder is not writable.
    pub fn new(folder: &Path) -> Result<Self> {
        let file = tempfile::tempfile_in(folder).map_err(|e| Error::file(folder, e))?;
        Ok(Self { file: BufWriter::with_capacity(1 << 20, file), len: 0, index: Vec::new() })
    }

    pub(crate) fn add(&mut self, metadata: &Metadata, key: TileKey, bytes: &[u8]) -> Result<()> {
        let order = Writer::order_key(metadata, key)?;
        let len = u32::try_from(bytes.len())
            .map_err(|_| terrastream_pack::Error::TooLarge { what: format!("tile {key}"), len: bytes.len() as u64 })?;
        self.file.write_all(bytes).map_err(Error::Spool)?;
        self.index.push((order, key, self.len, len));
        self.len += u64::from(len);
        Ok(())
    }

    /// Tiles spooled so far.
    pub fn tiles(&self) -> usize {
        self.index.len()
    }

    /// The keys of the tiles spooled so far, in the order they came.
    pub(crate) fn keys(&self) -> impl Iterator<Item = TileKey> + '_ {
        self.index.iter().map(|t| t.1)
    }

    /// Hands every tile, in archive order, to `writer` as stored bytes.
    ///
    /// # Errors
    /// I/O and writer errors, an interrupted error (Ctrl-C).
    pub fn drain_into(self, writer: &mut Writer, progress: &dyn Progress) -> Result<()> {
        let mut sorted = self.into_sorted()?;
        progress.start("write", sorted.len() as u64);
        let mut n = 0u64;
        while let Some((_, key, bytes)) = sorted.next_tile()? {
            if n.is_multiple_of(1024) {
                progress.check()?;
            }
            n += 1;
            writer.add_stored(key, bytes)?;
            progress.advance(1);
        }
        Ok(())
    }

    /// The spooled tiles in archive order, read back one at a time.
    ///
    /// # Errors
    /// [`Error::Spool`] if the spool cannot be flushed.
    pub fn into_sorted(self) -> Result<SortedSpool> {
        let Self { file, mut index, .. } = self;
        let file = file.into_inner().map_err(|e| Error::Spool(e.into_error()))?;
        index.sort_unstable_by_key(|t| t.0);
        Ok(SortedSpool { file, index: index.into_iter() })
    }
}

/// A [`Spool`]'s tiles in archive order.
pub struct SortedSpool {
    file: File,
    index: std::vec::IntoIter<(u64, TileKey, u64, u32)>,
}

impl SortedSpool {
    /// Tiles left.
    pub fn len(&self) -> usize {
        self.index.len()
    }

    /// True when every tile has been read.
    pub fn is_empty(&self) -> bool {
        self.index.len() == 0
    }

    /// The next tile's archive order key, key and stored bytes.
    ///
    /// # Errors
    /// [`Error::Spool`] on a read error.
    pub fn next_tile(&mut self) -> Result<Option<(u64, TileKey, Vec<u8>)>> {
        let Some((order, key, offset, len)) = self.index.next() else { return Ok(None) };
        let mut bytes = vec![0; len as usize];
        self.file.seek(SeekFrom::Start(offset)).map_err(Error::Spool)?;
        self.file.read_exact(&mut bytes).map_err(Error::Spool)?;
        Ok(Some((order, key, bytes)))
    }

    /// The next tile's archive order key, without reading it.
    pub fn peek_order(&self) -> Option<u64> {
        self.index.as_slice().first().map(|t| t.0)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// `row` resampled linearly along x to `width` samples (edges clamped).
    fn resample_row<S: Pixel>(row: &[S], width: usize) -> Vec<S> {
        Resample::new(row.len(), width).row(row)
    }

    /// Rows that hold only some columns (from `first`) cut into the tiles that rows as wide
    /// as the level, with no data outside those columns, cut into: of every tile column,
    /// where the rows' columns end inside a tile, at its border, or before or after it.
    #[test]
    fn rows_of_some_columns_cut_as_rows_of_all_with_no_data_elsewhere() {
        let (res, border, width) = (8usize, 2usize, 45usize);
        let value = |x: usize, j: usize| if (x * 7 + j).is_multiple_of(5) { f32::NAN } else { (x * 10 + j) as f32 };
        for (first, len) in [(0, 45), (3, 20), (10, 6), (16, 0), (17, 28), (40, 5), (0, 1)] {
            let full: Vec<Option<Arc<Vec<f32>>>> = (0..res + 2 * border)
                .map(|j| {
                    let row =
                        (0..width).map(|x| if (first..first + len).contains(&x) { value(x, j) } else { f32::NAN });
                    Some(Arc::new(row.collect()))
                })
                .collect();
            let part: Vec<Option<Arc<Vec<f32>>>> = (0..res + 2 * border)
                .map(|j| Some(Arc::new((first..first + len).map(|x| value(x, j)).collect())))
                .collect();
            for tx in 0..width.div_ceil(res) {
                let (a, b) = (
                    tile_samples(&full, tx, res, border, width, 0),
                    tile_samples(&part, tx, res, border, width, first),
                );
                assert_eq!(a.is_some(), b.is_some(), "columns {first}+{len}, tile {tx}");
                let (Some(a), Some(b)) = (a, b) else { continue };
                assert_eq!(a.len(), (res + 2 * border).pow(2));
                assert!(a.iter().zip(&b).all(|(p, q)| p.to_bits() == q.to_bits()), "columns {first}+{len}, tile {tx}");
            }
        }
    }

    #[test]
    fn halving_averages_and_ignores_nodata() {
        let a = [0.0, f32::NAN, 2.0];
        let b = [10.0, 11.0, 12.0];
        let h = halve_rows(&a, &b);
        assert_eq!(h.len(), 2);
        assert_eq!(h[0], (0.0 + 10.0 + 11.0) / 3.0);
        assert_eq!(h[1], (2.0 + 12.0) / 2.0);
    }

    #[test]
    fn resampling_interpolates_and_clamps() {
        let row: Vec<f32> = (0..10).map(|x| x as f32).collect();
        let half = resample_row(&row, 5);
        assert!((half[1] - 2.5).abs() < 1e-6, "{half:?}");
        assert_eq!(half[0], 0.5);
        let px = resample_row(&[[200, 0, 0, 255], [0, 0, 0, 0]], 4);
        assert_eq!(px[0], [200, 0, 0, 255], "clamped at the left edge");
        assert_eq!(px[3], [0, 0, 0, 0], "clamped at the right edge");
        assert_eq!(px[1][0], 200, "colour weighted by alpha: the transparent pixel adds none");
    }

    #[test]
    fn halving_an_image_weights_by_alpha() {
        let h = halve_rows(&[[200, 0, 0, 255], [0, 0, 0, 0], [10, 20, 30, 255]], &[[0; 4]; 3]);
        assert_eq!(h, vec![[200, 0, 0, 64], [10, 20, 30, 64]]);
    }
}
