//! Many elevation rasters, in any CRS the tiler knows, as one raster on one output grid.
//!
//! Each output sample's centre goes from the output CRS into each input that covers it
//! (later inputs first: a later input wins where it has data, nodata never overwrites
//! data) and is sampled there, bilinear over the corners that have data. Inputs are read
//! by strips or tiles on demand (a PNG or JPEG by strips of rows from its top, on a thread
//! of its own), never whole. Rows are made in bands, in order: each band finds the inputs
//! whose footprints it crosses, decodes the chunks under its rows of each once (in
//! parallel, into a cache bounded in bytes), and its rows sample them with no lock.
//! Files stay open while bands read them: at least [`OPEN_FILES`], twice as many as a
//! band reads within a share of the limit on open files (the least recently used is
//! closed, and reopened if needed again; files the last two bands did not read are
//! closed too). The chunks in use are those under a band of output rows: memory
//! follows the output's width and the cache, not the number or size of the inputs.

use std::collections::HashMap;
use std::path::{Path, PathBuf};
use std::sync::{Arc, Mutex, PoisonError, mpsc};

use rayon::prelude::*;
use terrastream_format::Georeference;

use super::kind::{Heights, MosaicKind, Pixels};
use super::tiff::TiffChunks;
use super::vrt::{is_vrt, read_vrt};
use super::{ElevationSource, ImageSource, crs_placement};
use crate::crs::{Crs, Transform};
use crate::error::{Error, Result};

/// Input files kept open at least (more while a band of rows reads more, as the limit on
/// open files allows; see [`open_files_limit`]).
pub const OPEN_FILES: usize = 64;

/// Files the mosaic may keep open: half the process's limit on open files shared among
/// what one open file may hold (a reader, and a decoder for each thread reading it at
/// once); the other half is the archive's, the spool's and the rest. 256 where the limit
/// is not known.
fn open_files_limit() -> usize {
    #[cfg(unix)]
    {
        let limit = rustix::process::getrlimit(rustix::process::Resource::Nofile).current;
        let per_file = 2 * (rayon::current_num_threads() as u64 + 1);
        limit.map_or(usize::MAX, |n| usize::try_from(n / per_file).unwrap_or(usize::MAX))
    }
    #[cfg(not(unix))]
    {
        256
    }
}

/// Output texels between exact transforms along a row; linear in between. The error of
/// that grows with the square of the lattice's cell: on the 64-file mosaic of two UTM
/// zones at 6.8 m, heights differ from a lattice of 16's by 0.18 mm at most (measured),
/// where GDAL's warper allows 1/8 of a pixel of position error by default. 32 rather
/// than 16 made that mosaic's rows 9 % faster.
const LATTICE: usize = 32;

/// [`LATTICE`], for row numbers.
const LATTICE_ROWS: u32 = 32;

/// Output rows made at once (in parallel).
const ROWS_AT_ONCE: u32 = 32;

/// How to build a mosaic.
#[derive(Clone, Debug, Default)]
pub struct MosaicOptions {
    /// Output CRS; default: the first input's if projected, else a transverse Mercator
    /// centred on the data.
    pub crs: Option<Crs>,
    /// Output sample spacing in metres (output CRS units); default: the finest input's.
    pub resolution: Option<f64>,
    /// Bytes of decoded input chunks kept (default 512 MiB).
    pub cache_bytes: Option<usize>,
    /// The area to cover, in the output CRS (min x, min y, max x, max y); default: every
    /// input's footprint. Imagery over an elevation covers the elevation's extent.
    pub extent: Option<[f64; 4]>,
    /// Leave out inputs that cannot be used (listed by [`Mosaic::skipped`]) instead of
    /// stopping at the first.
    pub skip_bad_inputs: bool,
}

/// An input as opened: a window of a file (the whole file, or a VRT source's), its CRS,
/// the window's north-west corner and pixel size there, and a nodata value of the VRT.
struct Opened<K: MosaicKind> {
    file: K::File,
    crs: Crs,
    origin: [f64; 2],
    pixel: (f64, f64),
    window: [u32; 4],
    nodata: Option<f32>,
    scale: Option<(f32, f32)>,
}

/// One input raster.
#[derive(Debug)]
struct Input<K: MosaicKind> {
    file: K::File,
    /// North-west corner and pixel size in the input's CRS.
    origin: [f64; 2],
    pixel: (f64, f64),
    /// The window of the file read: first column and row, width and height.
    window: [u32; 4],
    /// Samples equal to this are nodata too (a VRT source's NODATA).
    nodata: Option<f32>,
    /// A VRT source's ScaleRatio and ScaleOffset.
    scale: Option<(f32, f32)>,
    /// Output CRS -> the input's.
    to_input: Transform,
    /// Footprint in output pixels: first and last column and row (inclusive).
    columns: (i64, i64),
    rows: (i64, i64),
    /// How the input's pixels lie on the output grid.
    grid: Grid,
    /// Inputs of one CRS and pixel size share a number, and a pixel grid: file pixel +
    /// this offset. Those whole pixels apart lie on one lattice (tiles cut from one
    /// raster); others (tiles each warped onto its own origin) a fraction of a pixel off.
    lattice: Option<(usize, f64, f64)>,
    /// Left out once open: its data could not be decoded when its height range was
    /// scanned (with `skip_bad_inputs`).
    dropped: std::sync::atomic::AtomicBool,
}

impl<K: MosaicKind> Input<K> {
    fn is_dropped(&self) -> bool {
        self.dropped.load(std::sync::atomic::Ordering::Relaxed)
    }
}

/// How an input's pixels lie on the output grid.
#[derive(Clone, Copy, Debug, PartialEq)]
enum Grid {
    /// Its pixels are the output's (same CRS and spacing, a whole number of pixels apart):
    /// the file pixel of output sample (0, 0). Its rows are copied, not resampled.
    Aligned(i64, i64),
    /// The same CRS and spacing, a fraction of a pixel apart: the file pixel coordinates
    /// (centres at integers) of output sample (0, 0). Every sample has the same bilinear
    /// weights, and the points need no transform.
    Shifted(f64, f64),
    /// Anything else: each sample's point comes through the transform (on a lattice).
    Warped,
}

/// Several elevation rasters on one output grid (see the module's documentation).
#[derive(Debug)]
pub struct Mosaic<K: MosaicKind = Heights> {
    path: PathBuf,
    skipped: Vec<(PathBuf, String)>,
    skip_bad_inputs: bool,
    /// Inputs left out after the grid was made (see [`Input::dropped`]), and why.
    dropped: Mutex<Vec<(PathBuf, String)>>,
    /// Per input, strips or tiles that could not be decoded while rows were made and were
    /// left empty instead (with `skip_bad_inputs`).
    damaged: Mutex<std::collections::BTreeMap<usize, Damage>>,
    inputs: Vec<Input<K>>,
    crs: Crs,
    origin: [f64; 2],
    /// Output pixel size in CRS units (x, y).
    pixel: (f64, f64),
    size: (u32, u32),
    georeference: Georeference,
    cache_bytes: usize,
}

impl<K: MosaicKind> Mosaic<K> {
    /// The mosaic of `paths` (GeoTIFFs of heights, each georeferenced in a CRS the tiler
    /// knows), in the order given: a later input wins where inputs overlap.
    ///
    /// # Errors
    /// [`Error::Input`] naming a file that cannot be read, is not a georeferenced GeoTIFF
    /// of heights, or lies where the output CRS cannot reach; [`Error::UnknownCrs`].
    pub fn open(paths: &[PathBuf], options: &MosaicOptions) -> Result<Self> {
        let first = paths.first().ok_or(Error::NothingToTile)?;
        let mut files = Vec::with_capacity(paths.len());
        let mut skipped = Vec::new();
        // Headers read on every core (thousands of files: most of the time before the
        // first row), then taken in order: the first bad one is the one named.
        let opened: Vec<Result<Vec<Opened<K>>>> = paths.par_iter().map(|path| open_inputs::<K>(path)).collect();
        for (path, opened) in paths.iter().zip(opened) {
            match opened {
                Ok(opened) => files.extend(opened),
                Err(e) if options.skip_bad_inputs => {
                    tracing::warn!("skipping {e}");
                    skipped.push((path.clone(), e.to_string()));
                }
                Err(e) => return Err(e),
            }
        }
        if files.is_empty() {
            return Err(Error::input(first, "no input can be used (every one was skipped)"));
        }
        let crs = match &options.crs {
            Some(crs) => crs.clone(),
            None if !files[0].crs.is_geographic() => files[0].crs.clone(),
            None => {
                let (w, s, e, n) = lon_lat_bounds(&files);
                Crs::local_transverse_mercator((w + e) / 2.0, (s + n) / 2.0)
            }
        };
        // Footprints in the output CRS, and the finest spacing in metres.
        let mut bounds = [f64::INFINITY, f64::INFINITY, f64::NEG_INFINITY, f64::NEG_INFINITY];
        let mut finest = f64::INFINITY;
        let mut footprints = Vec::with_capacity(files.len());
        let found: Vec<Option<[f64; 4]>> = (files.par_iter())
            .map(|o| footprint(&Transform::new(&o.crs, &crs), o.origin, o.pixel, (o.window[2], o.window[3])))
            .collect();
        for (o, fp) in files.iter().zip(found) {
            let (w, h) = (o.window[2], o.window[3]);
            let fp = fp.ok_or_else(|| {
                Error::input(K::path(&o.file), format!("it lies outside what {} can hold", crs.name()))
            })?;
            bounds = [bounds[0].min(fp[0]), bounds[1].min(fp[1]), bounds[2].max(fp[2]), bounds[3].max(fp[3])];
            let metres = ((fp[2] - fp[0]) / f64::from(w)).min((fp[3] - fp[1]) / f64::from(h));
            finest = finest.min(metres);
            footprints.push(fp);
        }
        if let Some(extent) = options.extent {
            bounds = extent;
        }
        let spacing = options.resolution.unwrap_or(finest);
        if !(spacing.is_finite() && spacing > 0.0) {
            return Err(Error::option("--resolution", spacing, "a positive number of metres"));
        }
        // No extent given, and the first input already in the output CRS at this spacing:
        // the grid continues its pixels (its north-west corner moved out onto them), so
        // that inputs on one lattice are copied, not resampled.
        if options.extent.is_none()
            && let Some(o) = files.first().filter(|o| o.crs == crs)
        {
            let same = |a: f64| (a - spacing).abs() <= 1e-9 * spacing;
            if same(o.pixel.0) && same(o.pixel.1) {
                let steps = |d: f64| (d / spacing + 1e-9).floor();
                bounds[0] = o.origin[0] + steps(bounds[0] - o.origin[0]) * spacing;
                bounds[3] = o.origin[1] - steps(o.origin[1] - bounds[3]) * spacing;
            }
        }
        // A given extent is covered exactly (pixels a little off square); otherwise the
        // footprints' union, rounded out to whole pixels.
        #[expect(clippy::cast_possible_truncation, clippy::cast_sign_loss, reason = "checked below")]
        let side = |span: f64| {
            let n = if options.extent.is_some() { (span / spacing).round() } else { (span / spacing).ceil() };
            n.max(1.0) as u64
        };
        let (w, h) = (side(bounds[2] - bounds[0]), side(bounds[3] - bounds[1]));
        let (Ok(w), Ok(h)) = (u32::try_from(w), u32::try_from(h)) else {
            return Err(Error::input(
                first,
                format!("the mosaic would be {w} x {h} samples: set a coarser --resolution"),
            ));
        };
        let pixel = if options.extent.is_some() {
            ((bounds[2] - bounds[0]) / f64::from(w), (bounds[3] - bounds[1]) / f64::from(h))
        } else {
            (spacing, spacing)
        };
        let origin = [bounds[0], bounds[3]];
        let lattices = lattices(&files);
        let inputs = (files.into_par_iter())
            .zip(footprints)
            .zip(lattices)
            .map(|((o, fp), lattice)| {
                #[expect(clippy::cast_possible_truncation, reason = "within the u32 grid checked above")]
                let cell = |v: f64| v.floor() as i64;
                let to_input = Transform::new(&crs, &o.crs);
                let grid = grid_of(&to_input, (origin, pixel), (o.origin, o.pixel), o.window);
                Input {
                    grid,
                    lattice,
                    dropped: std::sync::atomic::AtomicBool::new(false),
                    columns: (cell((fp[0] - origin[0]) / pixel.0) - 1, cell((fp[2] - origin[0]) / pixel.0) + 1),
                    rows: (cell((origin[1] - fp[3]) / pixel.1) - 1, cell((origin[1] - fp[1]) / pixel.1) + 1),
                    to_input,
                    origin: o.origin,
                    pixel: o.pixel,
                    window: o.window,
                    nodata: o.nodata,
                    scale: o.scale,
                    file: o.file,
                }
            })
            .collect();
        let georeference = Georeference {
            crs: Some(crs.name()),
            origin: Some(origin),
            lat_lon_bounds: None,
            ..Georeference::default()
        };
        Ok(Self {
            path: first.clone(),
            skipped,
            skip_bad_inputs: options.skip_bad_inputs,
            dropped: Mutex::new(Vec::new()),
            damaged: Mutex::new(std::collections::BTreeMap::new()),
            inputs,
            crs,
            origin,
            pixel,
            size: (w, h),
            georeference,
            cache_bytes: options.cache_bytes.unwrap_or(512 << 20),
        })
    }

    /// Inputs left out with `skip_bad_inputs`, wholly or in part, and why: those that
    /// could not be opened, those whose heights could not be decoded when their range was
    /// scanned, and those with strips or tiles that could not be decoded when rows were
    /// made (where no scan decodes them first: imagery, heights with a given range),
    /// whose places were left empty.
    pub fn skipped(&self) -> Vec<(PathBuf, String)> {
        let dropped = self.dropped.lock().unwrap_or_else(PoisonError::into_inner);
        let damaged = self.damaged.lock().unwrap_or_else(PoisonError::into_inner);
        let damaged = damaged.iter().map(|(&index, damage)| {
            let n = damage.chunks.len();
            let what = if damage.strips { "strip" } else { "tile" };
            let why = format!("{} ({n} {what}{} of it left empty)", damage.first, if n == 1 { "" } else { "s" });
            (K::path(&self.inputs[index].file).to_path_buf(), why)
        });
        self.skipped.iter().chain(dropped.iter()).cloned().chain(damaged).collect()
    }

    /// The output CRS.
    pub fn crs(&self) -> &Crs {
        &self.crs
    }

    /// Makes every row, in order, 32 at a time in parallel.
    fn make_rows(&self, rows: std::ops::Range<u32>, row: &mut dyn FnMut(&[K::Value]) -> Result<()>) -> Result<()> {
        let reader = Reader::new(self);
        let last = rows.end.min(self.size.1);
        let mut j = rows.start.min(last);
        while j < last {
            let end = (j + ROWS_AT_ONCE).min(last);
            let inputs = reader.band(j..end)?;
            let band: Vec<Vec<K::Value>> = (j..end).into_par_iter().map(|r| self.row(r, &inputs)).collect();
            drop(inputs);
            for r in band {
                row(&r)?;
            }
            reader.next_band();
            j = end;
        }
        Ok(())
    }

    /// Inputs, in order.
    pub fn inputs(&self) -> impl Iterator<Item = &Path> {
        self.inputs.iter().map(|i| K::path(&i.file))
    }

    /// The output columns of `input`'s footprint (first, last; last < first for none).
    #[expect(clippy::cast_sign_loss, clippy::cast_possible_truncation, reason = "clamped to the row")]
    fn columns_of(&self, input: &Input<K>) -> (usize, usize) {
        let width = i64::from(self.size.0);
        (input.columns.0.clamp(0, width) as usize, input.columns.1.min(width - 1).max(0) as usize)
    }

    /// Makes output row `j` of `band`, whose inputs' chunks it holds.
    fn row(&self, j: u32, band: &Band<K>) -> Vec<K::Value> {
        let width = self.size.0 as usize;
        let mut out = vec![K::NONE; width];
        // Later inputs first: the first value found wins.
        for (place, (&index, window)) in band.inputs.iter().zip(&band.windows).enumerate().rev() {
            let input = &self.inputs[index];
            let Some(window) = window.as_ref().filter(|_| i64::from(j) >= input.rows.0 && i64::from(j) <= input.rows.1)
            else {
                continue;
            };
            let (c0, c1) = self.columns_of(input);
            if c1 < c0 || out[c0..=c1].iter().all(|v| !K::is_none(v)) {
                continue;
            }
            // A corner beyond this input's pixels: the latest neighbour's of its CRS and
            // pixel size with data there (its pixel, on one lattice; else bilinear there).
            let edge = |x: i64, y: i64| {
                let Some((_, ox, oy)) = input.lattice else { return K::NONE };
                for &other in band.neighbours[place].iter().rev() {
                    let (Some(w), Some((_, nx, ny))) = (&band.windows[other], self.inputs[band.inputs[other]].lattice)
                    else {
                        continue;
                    };
                    #[expect(clippy::cast_precision_loss, reason = "pixel indices are far below 2^52")]
                    let (px, py) = (x as f64 + ox - nx, y as f64 + oy - ny);
                    let (rx, ry) = (px.round(), py.round());
                    #[expect(clippy::cast_possible_truncation, reason = "whole, and within the grid")]
                    let v = if (px - rx).abs() < 1e-6 && (py - ry).abs() < 1e-6 {
                        w.get(rx as i64, ry as i64)
                    } else {
                        w.bilinear((px, py), &|_, _| K::NONE)
                    };
                    if !K::is_none(&v) {
                        return v;
                    }
                }
                K::NONE
            };
            match input.grid {
                Grid::Shifted(sx, sy) => {
                    #[expect(clippy::cast_precision_loss, reason = "pixel indices are far below 2^52")]
                    window.shifted_into(c0 as f64 + sx, f64::from(j) + sy, &mut out[c0..=c1], &edge);
                }
                // The input's own pixels: a copy of its row.
                Grid::Aligned(ox, oy) => window.fill_row(c0 as i64 + ox, i64::from(j) + oy, &mut out[c0..=c1]),
                Grid::Warped => {
                    // The input pixel coordinates of every sample of the row in this
                    // input's footprint: exact on a lattice every LATTICE samples and
                    // rows, bilinear between (see LATTICE for how far off that is).
                    let l = j / LATTICE_ROWS;
                    let (Some(top), Some(bottom)) = (band.lattice.get(&(index, l)), band.lattice.get(&(index, l + 1)))
                    else {
                        continue;
                    };
                    let fy = f64::from(j % LATTICE_ROWS) / f64::from(LATTICE_ROWS);
                    let mut points = Vec::with_capacity(c1 - c0 + 1);
                    for k in 0..top.len().saturating_sub(1) {
                        let (from, to) = (c0 + k * LATTICE, (c0 + (k + 1) * LATTICE).min(c1));
                        let mix = |p: (f64, f64), q: (f64, f64), t: f64| (p.0 + (q.0 - p.0) * t, p.1 + (q.1 - p.1) * t);
                        let (a, b) = (mix(top[k], bottom[k], fy), mix(top[k + 1], bottom[k + 1], fy));
                        let last = if to == c1 { to } else { to - 1 };
                        #[expect(clippy::cast_precision_loss, reason = "offsets of at most LATTICE")]
                        let step = 1.0 / (to - from).max(1) as f64;
                        let d = ((b.0 - a.0) * step, (b.1 - a.1) * step);
                        #[expect(clippy::cast_precision_loss, reason = "offsets of at most LATTICE")]
                        points.extend((0..=last - from).map(|k| (a.0 + d.0 * k as f64, a.1 + d.1 * k as f64)));
                    }
                    if points.len() != c1 - c0 + 1 {
                        points.resize(c1 - c0 + 1, (f64::NAN, f64::NAN));
                    }
                    window.bilinear_into(&points, &mut out[c0..c0 + points.len()], &edge);
                }
            }
        }
        out
    }
}

/// How an input's pixels lie on the output grid: [`Grid::Aligned`] when they are the
/// output's (the same CRS and spacing, to 1e-9; its origin a whole number of pixels away,
/// to 1e-6 of a pixel), [`Grid::Shifted`] when only the offset has a fraction. Output grid
/// and input as (origin, pixel size); `window` the file's pixels read (a VRT source's).
#[expect(clippy::cast_possible_truncation, reason = "checked to be near a whole number of pixels")]
fn grid_of(
    to_input: &Transform,
    (origin, pixel): ([f64; 2], (f64, f64)),
    (input_origin, input_pixel): ([f64; 2], (f64, f64)),
    window: [u32; 4],
) -> Grid {
    let same = |a: f64, b: f64| (a - b).abs() <= 1e-9 * a.abs().max(b.abs());
    if !to_input.is_identity() || !same(pixel.0, input_pixel.0) || !same(pixel.1, input_pixel.1) {
        return Grid::Warped;
    }
    let dx = (origin[0] - input_origin[0]) / pixel.0;
    let dy = (input_origin[1] - origin[1]) / pixel.1;
    if !(dx.is_finite() && dy.is_finite() && dx.abs() < 1e12 && dy.abs() < 1e12) {
        return Grid::Warped;
    }
    let whole = |v: f64| ((v - v.round()).abs() <= 1e-6).then(|| v.round() as i64);
    match (whole(dx), whole(dy)) {
        (Some(x), Some(y)) => Grid::Aligned(x + i64::from(window[0]), y + i64::from(window[1])),
        _ => Grid::Shifted(dx + f64::from(window[0]), dy + f64::from(window[1])),
    }
}

/// Opens one input: a georeferenced GeoTIFF of heights in a CRS the tiler knows, or a
/// VRT's sources (each a window of a GeoTIFF, placed by the VRT).
fn open_inputs<K: MosaicKind>(path: &Path) -> Result<Vec<Opened<K>>> {
    let plain = K::open;
    if is_vrt(path) {
        let vrt = read_vrt(path)?;
        let crs = Crs::parse(&vrt.crs).map_err(|e| Error::input(path, format!("its SRS cannot be used: {e}")))?;
        return vrt
            .sources
            .into_iter()
            .map(|source| {
                let file = plain(&source.path)?;
                K::check_bands(&file, vrt.bands)
                    .map_err(|why| Error::input(path, format!("{why} ({})", source.path.display())))?;
                let (w, h) = K::size(&file);
                let [x, y, sw, sh] = source.window;
                if x.saturating_add(sw) > w || y.saturating_add(sh) > h {
                    return Err(Error::input(
                        &source.path,
                        format!("{} reads pixels {x}+{sw} x {y}+{sh} of this {w}x{h} raster", path.display()),
                    ));
                }
                #[expect(
                    clippy::cast_possible_truncation,
                    reason = "nodata and scales are applied as f32, as samples are kept"
                )]
                let (nodata, scale) =
                    (source.nodata.map(|n| n as f32), source.scale.map(|(r, o)| (r as f32, o as f32)));
                Ok(Opened {
                    file,
                    crs: crs.clone(),
                    origin: source.origin,
                    pixel: source.pixel,
                    window: source.window,
                    nodata,
                    scale,
                })
            })
            .collect();
    }
    let file = plain(path)?;
    let Some((crs, origin, pixel)) = crs_placement(K::georeference(&file), K::crs_pixel(&file)) else {
        return Err(Error::input(
            path,
            "it does not say where it lies (no GeoTIFF georeference, world file or .aux.xml with a CRS)",
        ));
    };
    let crs = Crs::parse(crs).map_err(|e| Error::input(path, format!("its georeference cannot be used: {e}")))?;
    let (w, h) = K::size(&file);
    Ok(vec![Opened { file, crs, origin, pixel, window: [0, 0, w, h], nodata: None, scale: None }])
}

/// Each input's pixel grid (see [`Input::lattice`]): the number of its CRS and pixel
/// size, and the offset from its file's pixels to the grid's (whose pixel 0 is the first
/// such input's corner), whole where it is within a millionth of a pixel of whole.
fn lattices<K: MosaicKind>(files: &[Opened<K>]) -> Vec<Option<(usize, f64, f64)>> {
    let mut found: HashMap<(String, u64, u64), (usize, [f64; 2])> = HashMap::new();
    let snap = |v: f64| if (v - v.round()).abs() <= 1e-6 { v.round() } else { v };
    files
        .iter()
        .map(|o| {
            let (px, py) = o.pixel;
            if !(px > 0.0 && py > 0.0 && o.origin[0].is_finite() && o.origin[1].is_finite()) {
                return None;
            }
            let next = found.len();
            let key = (o.crs.definition().to_owned(), px.to_bits(), py.to_bits());
            let (id, reference) = *found.entry(key).or_insert((next, o.origin));
            let (dx, dy) = ((o.origin[0] - reference[0]) / px, (reference[1] - o.origin[1]) / py);
            if dx.abs().max(dy.abs()) > 1e15 {
                return None;
            }
            Some((id, snap(dx) - f64::from(o.window[0]), snap(dy) - f64::from(o.window[1])))
        })
        .collect()
}

/// West, south, east and north of geographic inputs' corners (degrees).
fn lon_lat_bounds<K: MosaicKind>(files: &[Opened<K>]) -> (f64, f64, f64, f64) {
    let mut b = (f64::INFINITY, f64::INFINITY, f64::NEG_INFINITY, f64::NEG_INFINITY);
    let wgs84 = Crs::wgs84();
    for Opened { crs, origin, pixel, window, .. } in files {
        let (w, h) = (window[2], window[3]);
        let t = Transform::new(crs, &wgs84);
        for (fx, fy) in [(0.0, 0.0), (1.0, 0.0), (0.0, 1.0), (1.0, 1.0)] {
            let (x, y) = (origin[0] + fx * f64::from(w) * pixel.0, origin[1] - fy * f64::from(h) * pixel.1);
            if let Some((lon, lat)) = t.apply(x, y) {
                b = (b.0.min(lon), b.1.min(lat), b.2.max(lon), b.3.max(lat));
            }
        }
    }
    b
}

/// The bounding box (min x, min y, max x, max y) in the output CRS of a raster's edges,
/// 16 points an edge; `None` if a point has no image there.
fn footprint(to_output: &Transform, origin: [f64; 2], pixel: (f64, f64), (w, h): (u32, u32)) -> Option<[f64; 4]> {
    let mut b = [f64::INFINITY, f64::INFINITY, f64::NEG_INFINITY, f64::NEG_INFINITY];
    let steps = 16;
    for k in 0..=steps {
        let t = f64::from(k) / f64::from(steps);
        for (fx, fy) in [(t, 0.0), (t, 1.0), (0.0, t), (1.0, t)] {
            let (x, y) = (origin[0] + fx * f64::from(w) * pixel.0, origin[1] - fy * f64::from(h) * pixel.1);
            let (ox, oy) = to_output.apply(x, y)?;
            b = [b[0].min(ox), b[1].min(oy), b[2].max(ox), b[3].max(oy)];
        }
    }
    Some(b)
}

/// Decoded chunks of the inputs (heights, NaN for nodata), least recently used dropped
/// past a byte budget; open files, least recently used closed past the bound [`Reader::band`] sets.
struct Reader<'m, K: MosaicKind> {
    mosaic: &'m Mosaic<K>,
    state: Mutex<ReaderState<'m, K::Value>>,
    /// The band of output rows being made: what "recently used" counts in.
    band: std::sync::atomic::AtomicU64,
    /// Most files kept open, however many a band reads ([`open_files_limit`], asked once).
    open_files_limit: usize,
}

struct ReaderState<'m, V> {
    files: HashMap<usize, (Arc<Chunks<'m>>, u64)>,
    /// Most files kept open now.
    open_files: usize,
    /// Per input and lattice row: input pixel coordinates of the lattice's samples.
    lattice: HashMap<(usize, u32), (LatticeRow, u64)>,
    chunks: HashMap<ChunkId, (Arc<Chunk<V>>, u64)>,
    bytes: usize,
}

/// How an input file is read: by a TIFF's strips or tiles, or (a PNG or JPEG, which
/// cannot be read by parts) by strips of rows from the top.
enum Chunks<'m> {
    Tiff(TiffChunks<'m>),
    Rows(RowStrips),
}

impl Chunks<'_> {
    /// Whether chunks are strips (numbered by row only), a chunk's nominal width and height,
    /// and chunks across.
    fn layout(&self) -> (bool, (usize, usize), usize) {
        match self {
            Self::Tiff(c) if c.kind == tiff::decoder::ChunkType::Strip => (true, (c.width, c.chunk_h), 1),
            Self::Tiff(c) => (false, (c.chunk_w, c.chunk_h), c.across()),
            Self::Rows(r) => (true, (r.width, STRIP_ROWS), 1),
        }
    }
}

/// Rows of a PNG or JPEG input a strip holds.
const STRIP_ROWS: usize = 64;

/// Strips skipped to reach a later one that are still kept: other threads may be about to
/// ask for them (the strips of one window are asked for at once).
const KEPT_BEHIND: usize = 8;

/// A PNG or JPEG input decoded from the top, [`STRIP_ROWS`] rows at a time, on a thread of
/// its own that runs a strip ahead: memory follows the image's width, not its size. A
/// strip above the next one, asked for again once dropped from the cache, starts the
/// decoding over.
struct RowStrips {
    path: PathBuf,
    width: usize,
    decoder: Mutex<Decoding>,
}

/// Where a [`RowStrips`]' decoding stands.
#[derive(Default)]
struct Decoding {
    /// The next strip the decoder hands over, and the decoder.
    next: usize,
    strips: Option<Strips>,
    /// The strip at which decoding failed: it and those below are not asked of a new
    /// decoder (which would decode from the top again only to fail there).
    failed: Option<usize>,
}

/// The strips a decoder thread hands over, top down.
type Strips = mpsc::Receiver<Result<Vec<u8>>>;

impl RowStrips {
    /// Starts decoding `path`, opened as kind `K`, from its first row.
    fn start<K: MosaicKind>(path: &Path) -> Strips {
        let (sender, receiver) = mpsc::sync_channel(1);
        let spawned = std::thread::Builder::new().name("mosaic rows".into()).spawn({
            let (sender, path) = (sender.clone(), path.to_path_buf());
            move || {
                let mut strip = Vec::new();
                let mut rows = 0;
                let decoded = K::open(&path).and_then(|file| {
                    K::file_rows(&file, &mut |row| {
                        strip.extend_from_slice(row);
                        rows += 1;
                        if rows == STRIP_ROWS {
                            rows = 0;
                            // Nobody waits for it any more: stop decoding.
                            sender.send(Ok(std::mem::take(&mut strip))).map_err(|_| crate::error::interrupted())?;
                        }
                        Ok(())
                    })
                });
                let last = match decoded {
                    Ok(()) if strip.is_empty() => return,
                    Ok(()) => Ok(strip),
                    Err(e) => Err(e),
                };
                let _ = sender.send(last);
            }
        });
        if let Err(e) = spawned {
            let _ = sender.send(Err(Error::file(path, e)));
        }
        receiver
    }

    /// Strip `id`, made by `keep` from its bytes, as are the strips decoded on the way to
    /// it [`KEPT_BEHIND`] or fewer above it (`keep` takes a strip's number); or what
    /// `cached` finds once the decoder is this thread's (another thread that held it may
    /// have made the strip meanwhile). Strips are kept while the decoder is held, so a
    /// thread waiting for it finds them.
    fn strip<K: MosaicKind, C>(
        &self,
        id: usize,
        cached: impl FnOnce() -> Option<C>,
        mut keep: impl FnMut(usize, Vec<u8>) -> Result<C>,
    ) -> Result<C> {
        let mut decoder = self.decoder.lock().unwrap_or_else(PoisonError::into_inner);
        if let Some(chunk) = cached() {
            return Ok(chunk);
        }
        let Decoding { next, strips: receiver, failed } = &mut *decoder;
        if let Some(at) = failed.filter(|&at| at <= id) {
            return Err(Error::input(
                &self.path,
                format!("strip {id}: the image could not be decoded past strip {at}"),
            ));
        }
        if *next > id || receiver.is_none() {
            if *next > 0 {
                tracing::debug!(path = %self.path.display(), strip = id, "decoding again from the top");
            }
            (*next, *receiver) = (0, Some(Self::start::<K>(&self.path)));
        }
        loop {
            let received = receiver.as_ref().and_then(|r| r.recv().ok());
            let Some(strip) = received else {
                *receiver = None;
                *failed = Some(*next);
                let why = format!("strip {id} of {STRIP_ROWS} rows: the image ended (or its decoder stopped) first");
                return Err(Error::input(&self.path, why));
            };
            let strip = strip.inspect_err(|e| {
                *receiver = None;
                if matches!(e, Error::Input { .. } | Error::File { .. }) {
                    *failed = Some(*next);
                }
            })?;
            let n = *next;
            *next += 1;
            if n == id {
                return keep(n, strip);
            }
            if n + KEPT_BEHIND >= id {
                keep(n, strip)?;
            }
        }
    }
}

/// An input and one of its strips or tiles.
type ChunkId = (usize, usize);

/// What a band of output rows reads: the inputs whose footprints meet it, in order, the
/// decoded chunks under the band's rows of each (None where none are), and the lattice
/// rows the band's rows of inputs not on the output grid interpolate between.
struct Band<K: MosaicKind> {
    inputs: Vec<usize>,
    windows: Vec<Option<Window<K>>>,
    lattice: HashMap<(usize, u32), LatticeRow>,
    /// For each input that is resampled, the others of the band of its CRS and pixel size
    /// that meet or touch it (places in `inputs`, in order): where its bilinear corners
    /// fall outside its pixels they are theirs, as if the tiles were one raster.
    neighbours: Vec<Vec<usize>>,
}

/// The strips or tiles of an input that could not be decoded, left empty.
#[derive(Debug)]
struct Damage {
    /// The first one's error.
    first: String,
    /// Whether the chunks are strips (else tiles), and which.
    strips: bool,
    chunks: std::collections::BTreeSet<usize>,
}

/// For each of `inputs` (of `m`) that is resampled, the places in `inputs` of the others
/// of its CRS and pixel size whose pixels meet or touch its own (see [`Band::neighbours`]).
fn neighbours<K: MosaicKind>(m: &Mosaic<K>, inputs: &[usize]) -> Vec<Vec<usize>> {
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
            let Some((id, [x0, y0, x1, y1])) = e.filter(|_| !matches!(m.inputs[k].grid, Grid::Aligned(..))) else {
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

/// The value of a pixel beyond an input's own, by its pixel coordinates: its neighbours'
/// of its CRS and pixel size, or no data.
type Edge<'a, V> = dyn Fn(i64, i64) -> V + 'a;

/// Input pixel coordinates along one lattice row.
type LatticeRow = Arc<Vec<(f64, f64)>>;

/// One decoded strip or tile: values, `w` across.
struct Chunk<V> {
    values: Vec<V>,
    w: usize,
}

impl<V> Chunk<V> {
    fn bytes(&self) -> usize {
        self.values.len() * size_of::<V>()
    }
}

/// The chunks under a row's sample points, held for lock-free sampling.
struct Window<K: MosaicKind> {
    /// The pixels that may be read: first column and row, end column and row (exclusive).
    bounds: (i64, i64, i64, i64),
    /// A chunk's nominal width and height (a strip: the raster's width).
    chunk: (usize, usize),
    /// First chunk column and row held, and chunk columns held.
    first: (usize, usize),
    across: usize,
    held: Vec<Arc<Chunk<K::Value>>>,
}

impl<K: MosaicKind> Window<K> {
    /// The value of pixel `(x, y)`; no data outside the window, for nodata, or outside
    /// the chunks held.
    fn get(&self, x: i64, y: i64) -> K::Value {
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
    fn fill_row(&self, x0: i64, y: i64, out: &mut [K::Value]) {
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
    fn quad(&self, x: i64, y: i64) -> Option<[K::Value; 4]> {
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
    fn bilinear(&self, p: (f64, f64), edge: &Edge<'_, K::Value>) -> K::Value {
        if !(p.0.is_finite() && p.1.is_finite()) {
            return K::NONE;
        }
        let (x0, y0) = (floor(p.0), floor(p.1));
        self.blend_at(x0, y0, weights(p, x0, y0), edge)
    }

    /// The blend of pixels `(x0, y0)`, `(x0 + 1, y0)`, `(x0, y0 + 1)` and `(x0 + 1, y0 + 1)`
    /// with weights `w`; those beyond the raster's pixels are `edge`'s.
    fn blend_at(&self, x0: i64, y0: i64, w: [f64; 4], edge: &Edge<'_, K::Value>) -> K::Value {
        let b = self.bounds;
        let get = |x: i64, y: i64| if x < b.0 || y < b.1 || x >= b.2 || y >= b.3 { edge(x, y) } else { self.get(x, y) };
        // Usually all four corners lie in one chunk: read them with one lookup.
        let [a, b, c, d] =
            self.quad(x0, y0).unwrap_or_else(|| [get(x0, y0), get(x0 + 1, y0), get(x0, y0 + 1), get(x0 + 1, y0 + 1)]);
        K::blend(&[(a, w[0]), (b, w[1]), (c, w[2]), (d, w[3])])
    }

    /// [`Self::bilinear_into`] for the points `(x0 + k, y)`, `k` = 0, 1, …: an input a
    /// fraction of a pixel off the output grid. The weights are the same for all.
    fn shifted_into(&self, x0: f64, y: f64, out: &mut [K::Value], edge: &Edge<'_, K::Value>) {
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

    /// [`Self::bilinear`] at each of `points` whose sample in `out` has no data yet (the
    /// same values, up to the last bit where [`MosaicKind::blend_unit`] sums four corners
    /// with data). Consecutive points of a row mostly fall between the same two rows of
    /// one chunk column: those are found once, not with two divisions and a lookup a point,
    /// and sampled in a loop of their own.
    fn bilinear_into(&self, points: &[(f64, f64)], out: &mut [K::Value], edge: &Edge<'_, K::Value>) {
        let n = out.len().min(points.len());
        let mut pair: Option<RowPair<'_, K::Value>> = None;
        let mut k = 0;
        while k < n {
            let p = points[k];
            if !(K::is_none(&out[k]) && p.0.is_finite() && p.1.is_finite()) {
                k += 1;
                continue;
            }
            let (x0, y0) = (floor(p.0), floor(p.1));
            if !pair.as_ref().is_some_and(|r| r.holds(x0, y0)) {
                pair = self.row_pair(x0, y0);
                if let Some(r) = &pair {
                    r.prefetch_ahead(x0);
                }
            }
            let Some(r) = &pair else {
                // Outside the window by a pixel or more: no corner has data.
                if x0 >= self.bounds.0 - 1 && y0 >= self.bounds.1 - 1 && x0 < self.bounds.2 && y0 < self.bounds.3 {
                    out[k] = self.bilinear(p, edge);
                }
                k += 1;
                continue;
            };
            // This point and those after it between the same two rows, in a loop of
            // their own.
            let (mut p, mut x0) = (p, x0);
            loop {
                let ([a, b], [c, d], w) = (r.top(x0), r.bottom(x0), weights(p, x0, y0));
                out[k] = K::blend_unit(&[(a, w[0]), (b, w[1]), (c, w[2]), (d, w[3])]);
                k += 1;
                if k >= n {
                    break;
                }
                p = points[k];
                x0 = floor(p.0);
                // (A NaN point floors to 0 and leaves the pair: `holds` fails on its row.)
                if !(r.holds(x0, floor(p.1)) && K::is_none(&out[k])) {
                    break;
                }
            }
        }
    }

    /// The two chunk rows [`Self::quad`] reads for `(x, y)`, and every `x` it reads them
    /// for at this `y`.
    fn row_pair(&self, x: i64, y: i64) -> Option<RowPair<'_, K::Value>> {
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
struct RowPair<'w, V> {
    y: i64,
    /// First and end (exclusive) of the left corners' columns.
    from: i64,
    end: i64,
    /// The column of `top[0]`.
    base: i64,
    top: &'w [V],
    bottom: &'w [V],
    /// The row after `bottom` (and what follows it in its chunk), if held.
    ahead: &'w [V],
}

impl<V: Copy> RowPair<'_, V> {
    fn holds(&self, x: i64, y: i64) -> bool {
        y == self.y && x >= self.from && x < self.end
    }
    #[expect(clippy::cast_sign_loss, clippy::cast_possible_truncation, reason = "held: at or after base")]
    fn top(&self, x: i64) -> [V; 2] {
        let i = (x - self.base) as usize;
        [self.top[i], self.top[i + 1]]
    }
    #[expect(clippy::cast_sign_loss, clippy::cast_possible_truncation, reason = "held: at or after base")]
    fn bottom(&self, x: i64) -> [V; 2] {
        let i = (x - self.base) as usize;
        [self.bottom[i], self.bottom[i + 1]]
    }
    /// Asks for the two cache lines of the row after `bottom` from column `x` on. A
    /// reprojected row crosses the input's rows at a slant (one every ~16 samples for
    /// two UTM zones): the next output row needs those lines as its lower corners, and
    /// the hardware's own prefetchers do not see a pattern in these steps. Without
    /// this, that load misses the cache every ~16 samples (measured: 11–16 % of the
    /// CPU time of making a two-zone mosaic's rows).
    #[expect(clippy::cast_sign_loss, clippy::cast_possible_truncation, reason = "held: at or after base")]
    fn prefetch_ahead(&self, x: i64) {
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
fn prefetch<V>(v: &V) {
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

/// floor() without a libm call (no SSE4.1 round instruction on the baseline target).
#[expect(clippy::cast_possible_truncation, reason = "pixel coordinates are far below 2^63")]
fn floor(v: f64) -> i64 {
    let i = v as i64;
    #[expect(clippy::cast_precision_loss, reason = "pixel coordinates are far below 2^52")]
    if (i as f64) > v { i - 1 } else { i }
}

/// Bilinear weights of the corners `(x0, y0)`, `(x0 + 1, y0)`, `(x0, y0 + 1)` and `(x0 +
/// 1, y0 + 1)` for point `p`.
fn weights(p: (f64, f64), x0: i64, y0: i64) -> [f64; 4] {
    #[expect(clippy::cast_precision_loss, reason = "pixel coordinates are far below 2^52")]
    let (fx, fy) = (p.0 - x0 as f64, p.1 - y0 as f64);
    [(1.0 - fx) * (1.0 - fy), fx * (1.0 - fy), (1.0 - fx) * fy, fx * fy]
}

impl<'m, K: MosaicKind> Reader<'m, K> {
    fn new(mosaic: &'m Mosaic<K>) -> Self {
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
    fn band(&self, rows: std::ops::Range<u32>) -> Result<Band<K>> {
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
            .filter(|&&index| m.inputs[index].grid == Grid::Warped)
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
                let (c0, c1) = m.columns_of(input);
                if c1 < c0 {
                    return Ok(None);
                }
                // The band's rows of the footprint, in input pixels: the corners for
                // inputs on the grid; for others every lattice point the rows lie
                // between (a row's points are linear between them).
                let (j0, j1) = (first.max(input.rows.0), last.min(input.rows.1));
                #[expect(clippy::cast_precision_loss, reason = "pixel indices are far below 2^52")]
                let corners = |(x, y): (f64, f64)| vec![(c0 as f64 + x, j0 as f64 + y), (c1 as f64 + x, j1 as f64 + y)];
                #[expect(clippy::cast_precision_loss, reason = "pixel offsets are far below 2^52")]
                let points = match input.grid {
                    Grid::Aligned(ox, oy) => corners((ox as f64, oy as f64)),
                    Grid::Shifted(sx, sy) => corners((sx, sy)),
                    Grid::Warped => {
                        let rows = lattice_rows.clone().filter_map(|l| lattice.get(&(index, l)));
                        rows.flat_map(|row| row.iter().copied()).collect()
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
    fn window(&self, index: usize, points: &[(f64, f64)]) -> Result<Option<Window<K>>> {
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
        Ok(Some(Window { bounds, chunk: (cw, ch), first: (cx0, cy0), across: cx1 - cx0 + 1, held }))
    }

    /// The input pixel coordinates (NaN where the transform fails) of input `index` at
    /// output row `l * LATTICE` and columns `c0, c0 + LATTICE, …` and `c1`.
    fn lattice(&self, index: usize, l: u32, (c0, c1): (usize, usize)) -> Result<LatticeRow> {
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
    fn next_band(&self) {
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

    fn file(&self, index: usize) -> Result<Arc<Chunks<'m>>> {
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
    fn chunk(&self, index: usize, chunks: &Chunks<'m>, id: usize) -> Result<Arc<Chunk<K::Value>>> {
        match self.decoded(index, chunks, id) {
            Err(e @ (Error::Input { .. } | Error::File { .. })) if self.mosaic.skip_bad_inputs => {
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

    fn decoded(&self, index: usize, chunks: &Chunks<'m>, id: usize) -> Result<Arc<Chunk<K::Value>>> {
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
    fn cached(&self, id: ChunkId) -> Option<Arc<Chunk<K::Value>>> {
        let clock = self.band.load(std::sync::atomic::Ordering::Relaxed);
        let mut state = self.state.lock().unwrap_or_else(PoisonError::into_inner);
        state.chunks.get_mut(&id).map(|(chunk, used)| {
            *used = clock;
            chunk.clone()
        })
    }

    /// Adds a decoded chunk to the cache (dropping the least recently used past its budget).
    fn keep(&self, id: ChunkId, chunk: Chunk<K::Value>) -> Arc<Chunk<K::Value>> {
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

impl<K: MosaicKind> Mosaic<K> {
    /// The smallest rectangle of samples (columns, rows) holding every input's footprint,
    /// clipped to the mosaic; None when no input lies on it.
    #[expect(clippy::cast_possible_truncation, clippy::cast_sign_loss, reason = "clipped to the u32 grid")]
    pub(crate) fn footprint_bounds(&self) -> Option<(std::ops::Range<u32>, std::ops::Range<u32>)> {
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
fn values_range(input: &Input<Heights>, progress: &mut dyn FnMut(u32) -> Result<()>) -> Result<(f32, f32)> {
    let chunks = TiffChunks::open(Heights::path(&input.file), 1)?;
    super::elevation::range_by_batches(&chunks, progress, |i| {
        let (data, w, h) = chunks.read(i)?;
        let mut heights = Heights::values(&input.file, data, input.nodata, input.scale)?;
        heights.truncate(w * h);
        Ok(crate::plan::min_max(&heights))
    })
}

/// Inputs of at most this many samples (what one batch of chunks reads at least) have
/// their height range scanned many at once.
const SMALL_INPUT: u64 = 1 << 18;

/// Most small inputs scanned at once.
const SCAN_AT_ONCE: usize = 256;

/// The height range of `input` as a mosaic reads it (see [`values_range`]), `progress`
/// told the file's rows read.
fn input_range(input: &Input<Heights>, progress: &mut dyn FnMut(u32) -> Result<()>) -> Result<(f32, f32)> {
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
                    Err(e @ (Error::Input { .. } | Error::File { .. })) if self.skip_bad_inputs => {
                        tracing::warn!("skipping {e}");
                        input.dropped.store(true, std::sync::atomic::Ordering::Relaxed);
                        let mut dropped = self.dropped.lock().unwrap_or_else(PoisonError::into_inner);
                        dropped.push((Heights::path(&input.file).to_path_buf(), e.to_string()));
                        continue;
                    }
                    other => other?,
                };
                (lo, hi) = (lo.min(l), hi.max(h));
            }
            k = next;
            if run > 0 {
                progress(u32::try_from(k as u64 * u64::from(self.size.1) / count).unwrap_or(u32::MAX))?;
            }
        }
        if self.inputs.iter().all(Input::is_dropped) {
            return Err(Error::input(&self.path, "no input can be used (every one was skipped)"));
        }
        Ok((lo, hi))
    }

    fn data_in_rows(&self, rows: std::ops::Range<u32>) -> f64 {
        self.footprint_samples(rows)
    }
    fn rows(&self, row: &mut dyn FnMut(&[f32]) -> Result<()>) -> Result<()> {
        self.make_rows(0..self.size.1, row)
    }
    fn rows_in(&self, rows: std::ops::Range<u32>, row: &mut dyn FnMut(&[f32]) -> Result<()>) -> Result<()> {
        self.make_rows(rows, row)
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
    fn rows(&self, row: &mut dyn FnMut(&[[u8; 4]]) -> Result<()>) -> Result<()> {
        self.make_rows(0..self.size.1, row)
    }
    fn rows_in(&self, rows: std::ops::Range<u32>, row: &mut dyn FnMut(&[[u8; 4]]) -> Result<()>) -> Result<()> {
        self.make_rows(rows, row)
    }
}
