//! Reading the inputs: open files kept within a bound (least recently used closed),
//! decoded chunks in a cache bounded in bytes, and the band of rows made from them.

use super::*;

/// Decoded chunks of the inputs (heights, NaN for nodata), least recently used dropped
/// past a byte budget; open files, least recently used closed past the bound [`BandReader::band`] sets.
pub(super) struct BandReader<'m, K: MosaicKind> {
    pub(super) mosaic: &'m Mosaic<K>,
    pub(super) state: Mutex<ReaderState<'m, K::Value>>,
    /// The band of output rows being made: what "recently used" counts in.
    pub(super) band: std::sync::atomic::AtomicU64,
    /// Most files kept open, however many a band reads ([`open_files_limit`], asked once).
    pub(super) open_files_limit: usize,
}

pub(super) struct ReaderState<'m, V> {
    pub(super) files: HashMap<usize, (Arc<Chunks<'m>>, u64)>,
    /// Most files kept open now.
    pub(super) open_files: usize,
    /// Per input and lattice row: input pixel coordinates of the lattice's samples.
    pub(super) lattice: HashMap<(usize, u32), (LatticeRow, u64)>,
    pub(super) chunks: HashMap<ChunkId, (Arc<Chunk<V>>, u64)>,
    pub(super) bytes: usize,
}

/// How an input file is read: by a TIFF's strips or tiles, or (a PNG or JPEG, which
/// cannot be read by parts) by strips of rows from the top.
pub(super) enum Chunks<'m> {
    Tiff(TiffChunks<'m>),
    Rows(RowStrips),
}

impl Chunks<'_> {
    /// Whether chunks are strips (numbered by row only), a chunk's nominal width and height,
    /// and chunks across.
    pub(super) fn layout(&self) -> (bool, (usize, usize), usize) {
        match self {
            Self::Tiff(c) if c.kind == tiff::decoder::ChunkType::Strip => (true, (c.width, c.chunk_h), 1),
            Self::Tiff(c) => (false, (c.chunk_w, c.chunk_h), c.across()),
            Self::Rows(r) => (true, (r.width, STRIP_ROWS), 1),
        }
    }
}

/// An input and one of its strips or tiles.
pub(super) type ChunkId = (usize, usize);

/// What a band of output rows reads: the inputs whose footprints meet it, in order, the
/// decoded chunks under the band's rows of each (None where none are), and the lattice
/// rows the band's rows of inputs not on the output grid interpolate between.
pub(super) struct Band<K: MosaicKind> {
    pub(super) inputs: Vec<usize>,
    pub(super) windows: Vec<Option<FileWindow<K>>>,
    pub(super) lattice: HashMap<(usize, u32), LatticeRow>,
    /// For each input that is resampled, the others of the band of its CRS and pixel size
    /// that meet or touch it (places in `inputs`, in order): where its bilinear corners
    /// fall outside its pixels they are theirs, as if the tiles were one raster.
    pub(super) neighbours: Vec<Vec<usize>>,
}

/// The strips or tiles of an input that could not be decoded, left empty.
#[derive(Debug)]
pub(super) struct Damage {
    /// The first one's error.
    pub(super) first: String,
    /// Whether the chunks are strips (else tiles), and which.
    pub(super) strips: bool,
    pub(super) chunks: std::collections::BTreeSet<usize>,
}

/// For each of `inputs` (of `m`) that is resampled, the places in `inputs` of the others
/// of its CRS and pixel size whose pixels meet or touch its own (see [`Band::neighbours`]).
pub(super) fn neighbours<K: MosaicKind>(m: &Mosaic<K>, inputs: &[usize]) -> Vec<Vec<usize>> {
    // Pixels of each on its grid: first column and row, end column and row (rounded out).
    #[expect(clippy::cast_possible_truncation, reason = "pixel offsets within the grid")]
    let extent = |i: &Input<K>| {
        i.lattice.map(|(id, ox, oy)| {
            let [x, y, w, h] = i.window.map(f64::from);
            let (x0, y0) = ((x + ox).floor() as i64, (y + oy).floor() as i64);
            (id, [x0, y0, (x + ox + w).ceil() as i64, (y + oy + h).ceil() as i64])
        })
    };
    let extents: Vec<_> = inputs.iter().map(|&k| extent(&m.inputs[k])).collect();
    // Each lattice's inputs by first column, and the widest: those that may touch an
    // input start at most that far left of it (thousands of tiles a band, not each
    // against each).
    let mut by_lattice: HashMap<usize, (Vec<(i64, usize)>, i64)> = HashMap::new();
    for (place, e) in extents.iter().enumerate() {
        if let Some((id, [x0, _, x1, _])) = e {
            let (members, widest) = by_lattice.entry(*id).or_default();
            members.push((*x0, place));
            *widest = (*widest).max(x1 - x0);
        }
    }
    for (members, _) in by_lattice.values_mut() {
        members.sort_unstable();
    }
    (inputs.iter().zip(&extents))
        .enumerate()
        .map(|(place, (&k, e))| {
            // Copied inputs read no corners.
            let Some((id, [x0, y0, x1, y1])) = e.filter(|_| !matches!(m.inputs[k].placement, Placement::Aligned(..)))
            else {
                return Vec::new();
            };
            let Some((members, widest)) = by_lattice.get(&id) else { return Vec::new() };
            let first = members.partition_point(|&(a0, _)| a0 < x0 - widest);
            let mut touching: Vec<usize> = members[first..]
                .iter()
                .take_while(|&&(a0, _)| a0 <= x1)
                .map(|&(_, other)| other)
                .filter(|&other| {
                    other != place
                        && extents[other]
                            .is_some_and(|(_, [a0, b0, a1, b1])| a0 <= x1 && a1 >= x0 && b0 <= y1 && b1 >= y0)
                })
                .collect();
            // In input order: the latest with data wins.
            touching.sort_unstable();
            touching
        })
        .collect()
}

impl<'m, K: MosaicKind> BandReader<'m, K> {
    pub(super) fn new(mosaic: &'m Mosaic<K>) -> Self {
        let state = ReaderState {
            files: HashMap::new(),
            open_files: OPEN_FILES,
            lattice: HashMap::new(),
            chunks: HashMap::new(),
            bytes: 0,
        };
        Self {
            mosaic,
            state: Mutex::new(state),
            band: std::sync::atomic::AtomicU64::new(0),
            open_files_limit: open_files_limit().max(OPEN_FILES),
        }
    }

    /// The inputs whose footprints meet output rows `rows` (found from each input's rows:
    /// a band's rows meet a few of thousands), their lattice rows and the chunks under
    /// the band, made and decoded in parallel, once for all the band's rows. Files stay
    /// open for all of them and as many more, as the limit on open files allows: fewer,
    /// and each band would close and open again the files it reads.
    pub(super) fn band(&self, rows: std::ops::Range<u32>) -> Result<Band<K>> {
        let m = self.mosaic;
        let (first, last) = (i64::from(rows.start), i64::from(rows.end) - 1);
        let inputs: Vec<usize> = (m.inputs.iter().enumerate())
            .filter(|(_, i)| i.rows.0 <= last && i.rows.1 >= first && !i.is_dropped())
            .map(|(index, _)| index)
            .collect();
        let open_files = (2 * inputs.len()).clamp(OPEN_FILES, self.open_files_limit);
        self.state.lock().unwrap_or_else(PoisonError::into_inner).open_files = open_files;
        let lattice_rows = rows.start / LATTICE_ROWS..=(rows.end - 1) / LATTICE_ROWS + 1;
        let wanted: Vec<(usize, u32, (usize, usize))> = (inputs.iter())
            .filter(|&&index| m.inputs[index].placement == Placement::Warped)
            .map(|&index| (index, m.columns_of(&m.inputs[index])))
            .filter(|(_, (c0, c1))| c0 <= c1)
            .flat_map(|(index, columns)| lattice_rows.clone().map(move |l| (index, l, columns)))
            .collect();
        let lattice: HashMap<(usize, u32), LatticeRow> = (wanted.into_par_iter())
            .map(|(index, l, columns)| Ok(((index, l), self.lattice(index, l, columns)?)))
            .collect::<Result<_>>()?;
        let windows = (inputs.par_iter())
            .map(|&index| {
                let input = &m.inputs[index];
                let footprint = m.columns_of(input);
                // Only the chunks under the columns rows are made in (see `only_columns`).
                let Some((c0, c1)) = visible(footprint, m.made) else { return Ok(None) };
                // The band's rows of the footprint, in input pixels: the corners for
                // inputs on the grid; for others every lattice point the rows lie
                // between (a row's points are linear between them).
                let (j0, j1) = (first.max(input.rows.0), last.min(input.rows.1));
                #[expect(clippy::cast_precision_loss, reason = "pixel indices are far below 2^52")]
                let corners = |(x, y): (f64, f64)| vec![(c0 as f64 + x, j0 as f64 + y), (c1 as f64 + x, j1 as f64 + y)];
                #[expect(clippy::cast_precision_loss, reason = "pixel offsets are far below 2^52")]
                let points = match input.placement {
                    Placement::Aligned(ox, oy) => corners((ox as f64, oy as f64)),
                    Placement::Shifted(sx, sy) => {
                        // Made across the footprint (see `Mosaic::row`).
                        let (c0, c1) = footprint;
                        vec![(c0 as f64 + sx, j0 as f64 + sy), (c1 as f64 + sx, j1 as f64 + sy)]
                    }
                    Placement::Warped => {
                        // The lattice spans the footprint: the points of the cells made.
                        let (i0, i1) = ((c0 - footprint.0) / LATTICE, (c1 - footprint.0).div_ceil(LATTICE));
                        let rows = lattice_rows.clone().filter_map(|l| lattice.get(&(index, l)));
                        rows.flat_map(|row| row[i0.min(row.len())..(i1 + 1).min(row.len())].iter().copied()).collect()
                    }
                };
                self.window(index, &points)
            })
            .collect::<Result<_>>()?;
        let neighbours = neighbours(m, &inputs);
        Ok(Band { inputs, windows, lattice, neighbours })
    }

    /// The decoded chunks under `points` (input pixel coordinates) of input `index`;
    /// `None` when no point falls inside the raster.
    pub(super) fn window(&self, index: usize, points: &[(f64, f64)]) -> Result<Option<FileWindow<K>>> {
        // The file's pixels this input reads: its window (the whole file, or a VRT's).
        let [wx, wy, ww, wh] = self.mosaic.inputs[index].window;
        let bounds = (i64::from(wx), i64::from(wy), i64::from(wx) + i64::from(ww), i64::from(wy) + i64::from(wh));
        let (mut x0, mut y0, mut x1, mut y1) = (f64::INFINITY, f64::INFINITY, f64::NEG_INFINITY, f64::NEG_INFINITY);
        for &(x, y) in points.iter().filter(|p| p.0.is_finite() && p.1.is_finite()) {
            (x0, y0, x1, y1) = (x0.min(x), y0.min(y), x1.max(x), y1.max(y));
        }
        #[expect(clippy::cast_precision_loss, reason = "pixel indices are far below 2^52")]
        let (fx0, fy0, fx1, fy1) = (bounds.0 as f64, bounds.1 as f64, bounds.2 as f64, bounds.3 as f64);
        if !(x1 > fx0 - 1.0 && y1 > fy0 - 1.0 && x0 < fx1 && y0 < fy1) || ww == 0 || wh == 0 {
            return Ok(None);
        }
        #[expect(clippy::cast_possible_truncation, clippy::cast_sign_loss, reason = "clamped into the window")]
        let clamp = |v: f64, lo: f64, hi: f64| v.clamp(lo, hi - 1.0) as usize;
        let (px0, px1) = (clamp(x0.floor(), fx0, fx1), clamp(x1.floor() + 1.0, fx0, fx1));
        let (py0, py1) = (clamp(y0.floor(), fy0, fy1), clamp(y1.floor() + 1.0, fy0, fy1));
        let chunks = self.file(index)?;
        let (strip, (cw, ch), across) = chunks.layout();
        let (cx0, cx1, cy0, cy1) = (px0 / cw, px1 / cw, py0 / ch, py1 / ch);
        // Decoded in parallel (one input may be all a band reads).
        let ids: Vec<usize> =
            (cy0..=cy1).flat_map(|cy| (cx0..=cx1).map(move |cx| if strip { cy } else { cy * across + cx })).collect();
        let held = ids.into_par_iter().map(|id| self.chunk(index, &chunks, id)).collect::<Result<Vec<_>>>()?;
        Ok(Some(FileWindow { bounds, chunk: (cw, ch), first: (cx0, cy0), across: cx1 - cx0 + 1, held }))
    }

    /// The input pixel coordinates (NaN where the transform fails) of input `index` at
    /// output row `l * LATTICE` and columns `c0, c0 + LATTICE, …` and `c1`.
    pub(super) fn lattice(&self, index: usize, l: u32, (c0, c1): (usize, usize)) -> Result<LatticeRow> {
        let clock = self.band.load(std::sync::atomic::Ordering::Relaxed);
        if let Some((row, used)) =
            self.state.lock().unwrap_or_else(PoisonError::into_inner).lattice.get_mut(&(index, l))
        {
            *used = clock;
            return Ok(row.clone());
        }
        let (m, input) = (self.mosaic, &self.mosaic.inputs[index]);
        #[expect(clippy::cast_precision_loss, reason = "sample indices are far below 2^52")]
        let at = |i: usize| {
            let x = m.origin[0] + (i as f64 + 0.5) * m.pixel.0;
            let y = m.origin[1] - (f64::from(l) * f64::from(LATTICE_ROWS) + 0.5) * m.pixel.1;
            let (wx, wy) = (f64::from(input.window[0]), f64::from(input.window[1]));
            input.to_input.apply(x, y).map_or((f64::NAN, f64::NAN), |(sx, sy)| {
                ((sx - input.origin[0]) / input.pixel.0 - 0.5 + wx, (input.origin[1] - sy) / input.pixel.1 - 0.5 + wy)
            })
        };
        let mut columns: Vec<usize> = (c0..=c1).step_by(LATTICE).collect();
        if columns.last() != Some(&c1) {
            columns.push(c1);
        }
        if columns.len() == 1 {
            columns.push(c1);
        }
        let row = Arc::new(columns.into_iter().map(at).collect::<Vec<_>>());
        self.state.lock().unwrap_or_else(PoisonError::into_inner).lattice.insert((index, l), (row.clone(), clock));
        Ok(row)
    }

    /// The next band of output rows starts: chunks unused in this band and the last one
    /// lie above the rows still to come and are dropped, and files unused as long are
    /// closed (their decoders hold buffers: open, they would make memory follow the
    /// number of inputs read so far, not the output's width).
    pub(super) fn next_band(&self) {
        let band = self.band.fetch_add(1, std::sync::atomic::Ordering::Relaxed) + 1;
        let mut state = self.state.lock().unwrap_or_else(PoisonError::into_inner);
        let mut freed = 0;
        state.chunks.retain(|_, (chunk, used)| {
            let keep = *used + 1 >= band;
            if !keep {
                freed += chunk.bytes();
            }
            keep
        });
        state.bytes -= freed;
        state.lattice.retain(|_, (_, used)| *used + 1 >= band);
        state.files.retain(|_, (_, used)| *used + 1 >= band);
    }

    pub(super) fn file(&self, index: usize) -> Result<Arc<Chunks<'m>>> {
        let clock = self.band.load(std::sync::atomic::Ordering::Relaxed);
        let mut state = self.state.lock().unwrap_or_else(PoisonError::into_inner);
        if let Some((chunks, used)) = state.files.get_mut(&index) {
            *used = clock;
            return Ok(chunks.clone());
        }
        if state.files.len() >= state.open_files
            && let Some(oldest) = state.files.iter().min_by_key(|(_, (_, used))| *used).map(|(k, _)| *k)
        {
            state.files.remove(&oldest);
        }
        let input = &self.mosaic.inputs[index];
        let chunks = Arc::new(if K::read_by_rows(&input.file) {
            let path = K::path(&input.file).to_path_buf();
            Chunks::Rows(RowStrips { path, width: K::size(&input.file).0 as usize, decoder: Mutex::default() })
        } else {
            Chunks::Tiff(TiffChunks::open(K::path(&input.file), K::channels(&input.file))?)
        });
        state.files.insert(index, (chunks.clone(), clock));
        Ok(chunks)
    }

    /// Chunk `id` of input `index`, from the cache or decoded. With `skip_bad_inputs`, a
    /// chunk that cannot be decoded (its file unreadable, its data damaged) is an empty
    /// one, its place a gap as where no input lies, and the input is listed (see
    /// [`Mosaic::skipped`]): rows already made used the rest of it, so the rest of it is
    /// used.
    pub(super) fn chunk(&self, index: usize, chunks: &Chunks<'m>, id: usize) -> Result<Arc<Chunk<K::Value>>> {
        match self.decoded(index, chunks, id) {
            Err(e) if self.mosaic.skip_bad_inputs && e.is_bad_input() => {
                let (strips, (w, h), _) = chunks.layout();
                let mut damaged = self.mosaic.damaged.lock().unwrap_or_else(PoisonError::into_inner);
                let damage = damaged.entry(index).or_insert_with(|| {
                    tracing::warn!("{e}: its {} {id} is left empty", if strips { "strip" } else { "tile" });
                    Damage { first: e.to_string(), strips, chunks: std::collections::BTreeSet::new() }
                });
                damage.chunks.insert(id);
                drop(damaged);
                Ok(self.keep((index, id), Chunk { values: vec![K::NONE; w * h], w }))
            }
            decoded => decoded,
        }
    }

    pub(super) fn decoded(&self, index: usize, chunks: &Chunks<'m>, id: usize) -> Result<Arc<Chunk<K::Value>>> {
        if let Some(chunk) = self.cached((index, id)) {
            return Ok(chunk);
        }
        let input = &self.mosaic.inputs[index];
        match chunks {
            Chunks::Tiff(tiff) => {
                // Decoded outside the lock, so that threads decode in parallel.
                let (data, w, _) = tiff.read(id)?;
                let values = K::values(&input.file, data, input.nodata, input.scale)?;
                Ok(self.keep((index, id), Chunk { values, w }))
            }
            Chunks::Rows(rows) => rows.strip::<K, _>(
                id,
                || self.cached((index, id)),
                |n, data| {
                    let data = tiff::decoder::DecodingResult::U8(data);
                    let values = K::values(&input.file, data, input.nodata, input.scale)?;
                    Ok(self.keep((index, n), Chunk { values, w: rows.width }))
                },
            ),
        }
    }

    /// Chunk `id` if the cache holds it, marked used.
    pub(super) fn cached(&self, id: ChunkId) -> Option<Arc<Chunk<K::Value>>> {
        let clock = self.band.load(std::sync::atomic::Ordering::Relaxed);
        let mut state = self.state.lock().unwrap_or_else(PoisonError::into_inner);
        state.chunks.get_mut(&id).map(|(chunk, used)| {
            *used = clock;
            chunk.clone()
        })
    }

    /// Adds a decoded chunk to the cache (dropping the least recently used past its budget).
    pub(super) fn keep(&self, id: ChunkId, chunk: Chunk<K::Value>) -> Arc<Chunk<K::Value>> {
        let chunk = Arc::new(chunk);
        let mut state = self.state.lock().unwrap_or_else(PoisonError::into_inner);
        state.bytes += chunk.bytes();
        let clock = self.band.load(std::sync::atomic::Ordering::Relaxed);
        if let Some((old, _)) = state.chunks.insert(id, (chunk.clone(), clock)) {
            state.bytes -= old.bytes();
        }
        while state.bytes > self.mosaic.cache_bytes && state.chunks.len() > 1 {
            let Some(oldest) = state.chunks.iter().min_by_key(|(_, (_, used))| *used).map(|(k, _)| *k) else { break };
            if let Some((gone, _)) = state.chunks.remove(&oldest) {
                state.bytes -= gone.bytes();
            }
        }
        chunk
    }
}
