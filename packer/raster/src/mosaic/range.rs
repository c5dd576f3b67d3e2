//! The mosaic as a source: its extent in samples, its height range (inputs scanned in
//! parallel, small ones at once), its rows.

use super::*;

impl<K: MosaicKind> Mosaic<K> {
    /// The smallest rectangle of samples (columns, rows) holding every input's footprint,
    /// clipped to the mosaic; None when no input lies on it.
    #[expect(clippy::cast_possible_truncation, clippy::cast_sign_loss, reason = "clipped to the u32 grid")]
    pub fn footprint_bounds(&self) -> Option<(std::ops::Range<u32>, std::ops::Range<u32>)> {
        let (w, h) = (i64::from(self.size.0), i64::from(self.size.1));
        let mut bounds: Option<[i64; 4]> = None;
        for i in self.inputs.iter().filter(|i| !i.is_dropped()) {
            let (c0, c1) = (i.columns.0.max(0), (i.columns.1 + 1).min(w));
            let (r0, r1) = (i.rows.0.max(0), (i.rows.1 + 1).min(h));
            if c0 >= c1 || r0 >= r1 {
                continue;
            }
            bounds = Some(match bounds {
                None => [c0, r0, c1, r1],
                Some(b) => [b[0].min(c0), b[1].min(r0), b[2].max(c1), b[3].max(r1)],
            });
        }
        bounds.map(|[c0, r0, c1, r1]| (c0 as u32..c1 as u32, r0 as u32..r1 as u32))
    }

    /// Samples of rows `rows` inside an input's footprint (overlaps counted once per input).
    #[expect(clippy::cast_precision_loss, reason = "a weight")]
    pub(crate) fn footprint_samples(&self, rows: std::ops::Range<u32>) -> f64 {
        let (width, start, end) = (i64::from(self.size.0), i64::from(rows.start), i64::from(rows.end));
        self.inputs
            .iter()
            .filter(|i| !i.is_dropped())
            .map(|i| {
                let down = (i.rows.1 + 1).min(end) - i.rows.0.max(start);
                let across = (i.columns.1 + 1).min(width) - i.columns.0.max(0);
                (down.max(0) * across.max(0)) as f64
            })
            .sum()
    }
}

/// The range of `input`'s heights as a mosaic reads them, its VRT source's NODATA and
/// scale applied (which the file's own range knows nothing of): every chunk decoded, in
/// parallel, a batch at a time, `progress` told the file's rows read after each.
pub(super) fn values_range(input: &Input<Heights>, progress: &mut dyn FnMut(u32) -> Result<()>) -> Result<(f32, f32)> {
    let chunks = TiffChunks::open(Heights::path(&input.file), 1)?;
    crate::elevation::range_by_batches(&chunks, progress, |i| {
        let (data, w, h) = chunks.read(i)?;
        let mut heights = Heights::values(&input.file, data, input.nodata, input.scale)?;
        heights.truncate(w * h);
        Ok(crate::min_max(&heights))
    })
}

/// Inputs of at most this many samples (what one batch of chunks reads at least) have
/// their height range scanned many at once.
pub(super) const SMALL_INPUT: u64 = 1 << 18;

/// Most small inputs scanned at once.
pub(super) const SCAN_AT_ONCE: usize = 256;

/// The height range of `input` as a mosaic reads it (see [`values_range`]), `progress`
/// told the file's rows read.
pub(super) fn input_range(input: &Input<Heights>, progress: &mut dyn FnMut(u32) -> Result<()>) -> Result<(f32, f32)> {
    if input.nodata.is_none() && input.scale.is_none() {
        input.file.height_range(progress)
    } else {
        values_range(input, progress)
    }
}

impl ElevationSource for Mosaic<Heights> {
    fn path(&self) -> &Path {
        &self.path
    }
    fn vertical_datum(&self) -> Option<&crate::DatumName> {
        self.datum()
    }
    fn size(&self) -> (u32, u32) {
        self.size
    }
    fn spacing(&self) -> (f64, f64) {
        if self.crs.is_geographic() {
            // Degrees: metres at the centre latitude, as for a geographic GeoTIFF.
            let lat = (self.origin[1] - f64::from(self.size.1) * self.pixel.1 / 2.0).to_radians();
            (self.pixel.0 * 111_320.0 * lat.cos(), self.pixel.1 * 110_574.0)
        } else {
            self.pixel
        }
    }
    fn georeference(&self) -> Option<&Georeference> {
        Some(&self.georeference)
    }
    fn crs_pixel_size(&self) -> Option<(f64, f64)> {
        Some(self.pixel)
    }
    /// The union of the inputs' height ranges, each found where its chunks are decoded
    /// (a bilinear sample never leaves the range of its corners), without making a row.
    /// With `skip_bad_inputs`, an input whose data cannot be decoded is left out here
    /// (every chunk is decoded once, before any row is made): the grid stays the one its
    /// footprint helped make, and its place is a gap.
    fn height_range(&self, progress: &mut dyn FnMut(u32) -> Result<()>) -> Result<(f32, f32)> {
        let (mut lo, mut hi) = (f32::INFINITY, f32::NEG_INFINITY);
        let count = u64::try_from(self.inputs.len().max(1)).unwrap_or(u64::MAX);
        let small = |input: &Input<Heights>| {
            let (w, h) = Heights::size(&input.file);
            u64::from(w) * u64::from(h) <= SMALL_INPUT
        };
        let mut k = 0;
        while k < self.inputs.len() {
            // Small inputs, many at once on every core (thousands of small files are not
            // read one after another), progress told after them. A larger one is told as
            // its rows are read (a batch of chunks at a time): the bar moves and Ctrl-C
            // is heard within it too. The scan's progress is in output rows, a share for
            // each input.
            let run = self.inputs[k..].iter().take(SCAN_AT_ONCE).take_while(|i| small(i)).count();
            let ranges: Vec<Result<(f32, f32)>> = if run > 0 {
                (k..k + run).into_par_iter().map(|i| input_range(&self.inputs[i], &mut |_| Ok(()))).collect()
            } else {
                let rows = u64::from(self.inputs[k].window[3].max(1));
                let mut within = |read: u32| {
                    let done = (k as u64 * rows + u64::from(read).min(rows)) * u64::from(self.size.1) / (count * rows);
                    progress(u32::try_from(done).unwrap_or(u32::MAX))
                };
                vec![input_range(&self.inputs[k], &mut within)]
            };
            let next = k + ranges.len();
            for (input, range) in self.inputs[k..next].iter().zip(ranges) {
                let (l, h) = match range {
                    Err(e) if self.skip_bad_inputs && e.is_bad_input() => {
                        tracing::warn!("skipping {e}");
                        input.dropped.store(true, std::sync::atomic::Ordering::Relaxed);
                        let mut dropped = self.dropped.lock().unwrap_or_else(PoisonError::into_inner);
                        dropped.push((Heights::path(&input.file).to_path_buf(), e.to_string()));
                        continue;
                    }
                    other => other?,
                };
                let (sl, sh) = input.shift.as_ref().map_or((0.0, 0.0), |s| s.range);
                (lo, hi) = (lo.min(l + sl), hi.max(h + sh));
            }
            k = next;
            if run > 0 {
                progress(u32::try_from(k as u64 * u64::from(self.size.1) / count).unwrap_or(u32::MAX))?;
            }
        }
        if self.inputs.iter().all(Input::is_dropped) {
            return Err(Error::mismatch(&self.path, "no input can be used (every one was skipped)"));
        }
        Ok((lo, hi))
    }

    fn data_in_rows(&self, rows: std::ops::Range<u32>) -> f64 {
        self.footprint_samples(rows)
    }
    /// The union of every input's GDAL statistics (a VRT source's scale applied; its
    /// NODATA, if any, can only narrow the true range): None if one has none.
    fn statistics_range(&self) -> std::result::Result<(f32, f32), PathBuf> {
        let (mut lo, mut hi) = (f64::INFINITY, f64::NEG_INFINITY);
        for input in self.inputs.iter().filter(|i| !i.is_dropped()) {
            let (mut a, mut b) = input.file.statistics().ok_or_else(|| Heights::path(&input.file).to_path_buf())?;
            if let Some((ratio, offset)) = input.scale {
                (a, b) = (a * f64::from(ratio) + f64::from(offset), b * f64::from(ratio) + f64::from(offset));
                (a, b) = (a.min(b), a.max(b));
            }
            let (sl, sh) = input.shift.as_ref().map_or((0.0, 0.0), |s| s.range);
            (lo, hi) = (lo.min(a + f64::from(sl)), hi.max(b + f64::from(sh)));
        }
        if lo <= hi { Ok(crate::nearest_f32((lo, hi))) } else { Err(self.path.clone()) }
    }
    /// A reprojected GeoTIFF's (a mosaic of that one file, warped): the file's own estimate
    /// (its datum shift's range added, as [`Self::height_range`] adds it), inside the
    /// file's range, which is the mosaic's. None for a mosaic of several inputs, or of a
    /// VRT's window, nodata or scale, or one on the file's own grid: the estimate of
    /// several inputs changes with the set of them, which a shard fetching only its own
    /// inputs, and an update matching the run over all its rasters, must not see (the
    /// exact range of a union is the union of the exact ranges). None too with
    /// `skip_bad_inputs`: the scan is where bad inputs are found and left out, before
    /// any row is made.
    fn height_range_estimate(&self) -> Result<Option<(f32, f32)>> {
        let [input] = self.inputs.as_slice() else { return Ok(None) };
        let (w, h) = Heights::size(&input.file);
        let whole = input.nodata.is_none() && input.scale.is_none() && input.window == [0, 0, w, h];
        if self.skip_bad_inputs || !whole || !matches!(input.placement, Placement::Warped) {
            return Ok(None);
        }
        let (sl, sh) = input.shift.as_ref().map_or((0.0, 0.0), |s| s.range);
        Ok(input.file.height_range_estimate()?.map(|(l, h)| (l + sl, h + sh)))
    }
    fn inputs_in_rows(&self, rows: std::ops::Range<u32>) -> Vec<PathBuf> {
        Mosaic::inputs_in_rows(self, rows)
    }
    fn input_at(&self, column: u32, row: u32) -> Option<PathBuf> {
        let (x, y) = (i64::from(column), i64::from(row));
        let holds = |i: &&Input<Heights>| {
            !i.is_dropped() && (i.rows.0..=i.rows.1).contains(&y) && (i.columns.0..=i.columns.1).contains(&x)
        };
        self.inputs.iter().rev().find(holds).map(|i| Heights::path(&i.file).to_path_buf())
    }
    fn mosaic_grid(&self) -> Option<GridSpec> {
        Some(self.grid())
    }
    fn rows(&self, row: &mut dyn FnMut(&[f32]) -> Result<()>) -> Result<()> {
        self.make_rows(0..self.size.1, row)
    }
    fn rows_in(&self, rows: std::ops::Range<u32>, row: &mut dyn FnMut(&[f32]) -> Result<()>) -> Result<()> {
        self.make_rows(rows, row)
    }
    fn rows_mapped(
        &self,
        rows: std::ops::Range<u32>,
        map: Option<&crate::RowMap<'_>>,
        row: &mut crate::MappedRow<'_>,
    ) -> Result<()> {
        // Rows are made on the pool: mapped there, and handed over (no copy without a map).
        let Some(map) = map else { return self.make_rows_with(rows, &crate::min_max, row) };
        self.make_rows_with(rows, &|r| (map(r), crate::min_max(r)), &mut |_, (mapped, range)| row(mapped, range))
    }
}

impl ImageSource for Mosaic<Pixels> {
    fn path(&self) -> &Path {
        &self.path
    }
    fn size(&self) -> (u32, u32) {
        self.size
    }
    fn georeference(&self) -> Option<&Georeference> {
        Some(&self.georeference)
    }
    fn crs_pixel_size(&self) -> Option<(f64, f64)> {
        Some(self.pixel)
    }
    fn data_in_rows(&self, rows: std::ops::Range<u32>) -> f64 {
        self.footprint_samples(rows)
    }
    fn inputs_in_rows(&self, rows: std::ops::Range<u32>) -> Vec<PathBuf> {
        Mosaic::inputs_in_rows(self, rows)
    }
    fn mosaic_grid(&self) -> Option<GridSpec> {
        Some(self.grid())
    }
    fn rows(&self, row: &mut dyn FnMut(&[[u8; 4]]) -> Result<()>) -> Result<()> {
        self.make_rows(0..self.size.1, row)
    }
    fn rows_in(&self, rows: std::ops::Range<u32>, row: &mut dyn FnMut(&[[u8; 4]]) -> Result<()>) -> Result<()> {
        self.make_rows(rows, row)
    }
}
