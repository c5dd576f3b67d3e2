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
use crate::geoid::DatumShift;

mod range;
mod reader;
mod strips;
mod window;

use reader::*;
use strips::*;
use window::*;

/// Input files kept open at least (more while a band of rows reads more, as the limit on
/// open files allows; see `open_files_limit`).
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
/// than 16 made that mosaic's rows 9 % faster. A part of a grid opened on its own (its
/// corner a whole number of lattice cells from the grid's) makes the grid's samples there.
pub const LATTICE: usize = 32;

/// [`LATTICE`], for row numbers.
const LATTICE_ROWS: u32 = 32;

/// Output rows made at once (in parallel), by a mosaic and by the imagery warp.
pub(crate) const ROWS_AT_ONCE: u32 = 32;

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
    /// The output grid, given whole (over `crs`, which must then be given too): what a
    /// shard of a planned run opens its part of the inputs onto, so that its grid is the
    /// one all the inputs make. Overrides `extent` and `resolution`.
    pub grid: Option<GridSpec>,
}

/// An output grid: north-west corner and sample size in the output CRS, samples across
/// and down.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct GridSpec {
    /// North-west corner (x, y).
    pub origin: [f64; 2],
    /// Sample size (x, y).
    pub pixel: (f64, f64),
    /// Samples across and down.
    pub size: (u32, u32),
}

/// Where an input lies on a mosaic's output grid ([`Mosaic::layout`]).
#[derive(Clone, Debug, PartialEq)]
pub struct InputLayout {
    /// The file (a VRT source's file for a VRT).
    pub path: PathBuf,
    /// Its spacing in output CRS units (the finer of its two axes).
    pub spacing: f64,
    /// Its footprint in output samples, first and last column (inclusive), with one
    /// sample of margin each side (what its bilinear samples reach).
    pub columns: (i64, i64),
    /// Its first and last row, as `columns`.
    pub rows: (i64, i64),
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
    /// Its spacing in output CRS units (the finer of its two axes).
    spacing: f64,
    /// Footprint in output pixels: first and last column and row (inclusive).
    columns: (i64, i64),
    rows: (i64, i64),
    /// How the input's pixels lie on the output grid.
    placement: Placement,
    /// Inputs of one CRS and pixel size share a number, and a pixel grid: file pixel +
    /// this offset. Those whole pixels apart lie on one lattice (tiles cut from one
    /// raster); others (tiles each warped onto its own origin) a fraction of a pixel off.
    lattice: Option<(usize, f64, f64)>,
    /// Left out once open: its data could not be decoded when its height range was
    /// scanned (with `skip_bad_inputs`).
    dropped: std::sync::atomic::AtomicBool,
    /// Heights of another vertical datum than the mosaic's: what to add to them
    /// ([`Mosaic::convert_datums`]).
    shift: Option<Arc<DatumShift>>,
}

impl<K: MosaicKind> Input<K> {
    fn is_dropped(&self) -> bool {
        self.dropped.load(std::sync::atomic::Ordering::Relaxed)
    }
}

/// What [`Mosaic::make_rows_with`] calls with each row (its own) and what was found in it.
pub(crate) type FoundRow<'a, V, T> = dyn FnMut(Vec<V>, T) -> Result<()> + 'a;

/// How an input's pixels lie on the output grid.
#[derive(Clone, Copy, Debug, PartialEq)]
enum Placement {
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

/// The inputs' headers, read on every core (thousands of files: most of the time before
/// the first row), then taken in order: the first bad one is the one named (or, with
/// `skip_bad_inputs`, each bad one is left out, with why).
#[expect(clippy::type_complexity, reason = "the files, and the skipped ones with why")]
fn open_all<K: MosaicKind>(
    paths: &[PathBuf],
    skip_bad_inputs: bool,
) -> Result<(Vec<Opened<K>>, Vec<(PathBuf, String)>)> {
    let mut files = Vec::with_capacity(paths.len());
    let mut skipped = Vec::new();
    let opened: Vec<Result<Vec<Opened<K>>>> = paths.par_iter().map(|path| open_inputs::<K>(path)).collect();
    for (path, opened) in paths.iter().zip(opened) {
        match opened {
            Ok(opened) => files.extend(opened),
            Err(e) if skip_bad_inputs => {
                tracing::warn!("skipping {e}");
                skipped.push((path.clone(), e.to_string()));
            }
            Err(e) => return Err(e),
        }
    }
    Ok((files, skipped))
}

/// The inputs' footprints in the output CRS.
struct Footprints {
    /// Each input's (min x, min y, max x, max y).
    each: Vec<[f64; 4]>,
    /// Each input's spacing in output CRS units (the finer of its two axes).
    spacings: Vec<f64>,
    /// Their union.
    union: [f64; 4],
    /// The finest input spacing, in output CRS units.
    finest: f64,
}

impl Footprints {
    fn of<K: MosaicKind>(files: &[Opened<K>], crs: &Crs) -> Result<Self> {
        let mut union = [f64::INFINITY, f64::INFINITY, f64::NEG_INFINITY, f64::NEG_INFINITY];
        let mut finest = f64::INFINITY;
        let mut each = Vec::with_capacity(files.len());
        let mut spacings = Vec::with_capacity(files.len());
        let found: Vec<Option<[f64; 4]>> = (files.par_iter())
            .map(|o| footprint(&Transform::new(&o.crs, crs), o.origin, o.pixel, (o.window[2], o.window[3])))
            .collect();
        for (o, fp) in files.iter().zip(found) {
            let (w, h) = (o.window[2], o.window[3]);
            let fp = fp.ok_or_else(|| {
                Error::georeference(K::path(&o.file), format!("it lies outside what {} can hold", crs.name()))
            })?;
            union = [union[0].min(fp[0]), union[1].min(fp[1]), union[2].max(fp[2]), union[3].max(fp[3])];
            let metres = ((fp[2] - fp[0]) / f64::from(w)).min((fp[3] - fp[1]) / f64::from(h));
            finest = finest.min(metres);
            each.push(fp);
            spacings.push(metres);
        }
        Ok(Self { each, spacings, union, finest })
    }
}

/// The mosaic's grid in the output CRS.
struct OutputGrid {
    /// North-west corner.
    origin: [f64; 2],
    /// Sample size (x, y).
    pixel: (f64, f64),
    /// Samples across and down.
    size: (u32, u32),
}

impl OutputGrid {
    /// The extent asked for, covered exactly (pixels a little off square); otherwise the
    /// footprints' union, rounded out to whole pixels of the spacing asked for (else the
    /// finest input's).
    fn over<K: MosaicKind>(
        footprints: &Footprints,
        files: &[Opened<K>],
        crs: &Crs,
        options: &MosaicOptions,
        first: &Path,
    ) -> Result<Self> {
        if let Some(g) = options.grid {
            return Ok(Self { origin: g.origin, pixel: g.pixel, size: g.size });
        }
        let mut bounds = options.extent.unwrap_or(footprints.union);
        let spacing = options.resolution.unwrap_or(footprints.finest);
        if !(spacing.is_finite() && spacing > 0.0) {
            return Err(Error::InvalidOption {
                option: "--resolution",
                value: spacing.to_string(),
                allowed: "a positive number of metres",
            });
        }
        // No extent given, and the first input already in the output CRS at this spacing:
        // the grid continues its pixels (its north-west corner moved out onto them), so
        // that inputs on one lattice are copied, not resampled.
        if options.extent.is_none()
            && let Some(o) = files.first().filter(|o| o.crs == *crs)
        {
            let same = |a: f64| (a - spacing).abs() <= 1e-9 * spacing;
            if same(o.pixel.0) && same(o.pixel.1) {
                let steps = |d: f64| (d / spacing + 1e-9).floor();
                bounds[0] = o.origin[0] + steps(bounds[0] - o.origin[0]) * spacing;
                bounds[3] = o.origin[1] - steps(o.origin[1] - bounds[3]) * spacing;
            }
        }
        #[expect(clippy::cast_possible_truncation, clippy::cast_sign_loss, reason = "checked below")]
        let side = |span: f64| {
            let n = if options.extent.is_some() { (span / spacing).round() } else { (span / spacing).ceil() };
            n.max(1.0) as u64
        };
        let (w, h) = (side(bounds[2] - bounds[0]), side(bounds[3] - bounds[1]));
        let (Ok(w), Ok(h)) = (u32::try_from(w), u32::try_from(h)) else {
            return Err(Error::mismatch(
                first,
                format!("the mosaic would be {w} x {h} samples: set a coarser --resolution"),
            ));
        };
        let pixel = if options.extent.is_some() {
            ((bounds[2] - bounds[0]) / f64::from(w), (bounds[3] - bounds[1]) / f64::from(h))
        } else {
            (spacing, spacing)
        };
        Ok(Self { origin: [bounds[0], bounds[3]], pixel, size: (w, h) })
    }
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
    /// What the heights are measured from ([`Mosaic::set_datum`]).
    datum: Option<crate::DatumName>,
    /// The output columns rows are made in ([`Mosaic::only_columns`]): first and last,
    /// inclusive. None: every column.
    made: Option<(usize, usize)>,
}

/// The part of an input's footprint columns `(c0, c1)` (as [`Mosaic::columns_of`] gives
/// them) that rows made only in `made` need: whole cells of its lattice
/// ([`LATTICE`], from `c0`), so that each sample made is the one a row across the whole
/// footprint makes. None where they do not meet.
fn visible((f0, f1): (usize, usize), made: Option<(usize, usize)>) -> Option<(usize, usize)> {
    let Some((m0, m1)) = made else { return (f0 <= f1).then_some((f0, f1)) };
    let (v0, v1) = (f0.max(m0), f1.min(m1));
    if v0 > v1 {
        return None;
    }
    // Cell `k` is [f0 + k·LATTICE, f0 + (k + 1)·LATTICE), the last one ending at f1.
    let cells = (f1 - f0).div_ceil(LATTICE).max(1);
    let cell = |v: usize| ((v - f0) / LATTICE).min(cells - 1);
    Some((f0 + cell(v0) * LATTICE, (f0 + (cell(v1) + 1) * LATTICE).min(f1)))
}

impl<K: MosaicKind> Mosaic<K> {
    /// Rows are made only in output columns `columns` (others are no data), and only the
    /// inputs' chunks under them are decoded: a part of a wide grid, each of its samples
    /// the one a row across the whole grid holds.
    pub fn only_columns(&mut self, columns: std::ops::Range<u32>) {
        let (a, b) = (columns.start as usize, (columns.end as usize).min(self.size.0 as usize));
        // An empty window is one whose first column lies past its last: nothing is made.
        self.made = Some(if a < b { (a, b - 1) } else { (1, 0) });
    }

    /// The mosaic of `paths` (GeoTIFFs of heights, each georeferenced in a CRS the tiler
    /// knows), in the order given: a later input wins where inputs overlap.
    ///
    /// # Errors
    /// An error naming a file that cannot be read, is not a georeferenced GeoTIFF
    /// of heights, or lies where the output CRS cannot reach; [`Error::UnknownCrs`].
    pub fn open(paths: &[PathBuf], options: &MosaicOptions) -> Result<Self> {
        let first = paths.first().ok_or(Error::NoInput)?;
        let (files, skipped) = open_all::<K>(paths, options.skip_bad_inputs)?;
        if files.is_empty() {
            return Err(Error::mismatch(first, "no input can be used (every one was skipped)"));
        }
        let crs = match &options.crs {
            Some(crs) => crs.clone(),
            None if !files[0].crs.is_geographic() => files[0].crs.clone(),
            None => {
                let (w, s, e, n) = lon_lat_bounds(&files);
                Crs::for_geographic(w, s, e, n)
            }
        };
        let footprints = Footprints::of(&files, &crs)?;
        let grid = OutputGrid::over(&footprints, &files, &crs, options, first)?;
        let (origin, pixel) = (grid.origin, grid.pixel);
        let lattices = lattices(&files);
        let inputs = (files.into_par_iter())
            .zip(footprints.each)
            .zip(footprints.spacings)
            .zip(lattices)
            .map(|(((o, fp), spacing), lattice)| {
                #[expect(clippy::cast_possible_truncation, reason = "within the u32 grid checked above")]
                let cell = |v: f64| v.floor() as i64;
                let to_input = Transform::new(&crs, &o.crs);
                let placement = placement_of(&to_input, (origin, pixel), (o.origin, o.pixel), o.window);
                Input {
                    placement,
                    spacing,
                    lattice,
                    dropped: std::sync::atomic::AtomicBool::new(false),
                    shift: None,
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
            size: grid.size,
            georeference,
            cache_bytes: options.cache_bytes.unwrap_or(512 << 20),
            datum: None,
            made: None,
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

    /// Records what the heights are measured from.
    pub fn set_datum(&mut self, datum: Option<crate::DatumName>) {
        self.datum = datum;
    }

    /// Converts the heights of inputs of other vertical datums to `to`'s, the mosaic's:
    /// `datum_of` says an input file's datum (None: the mosaic's). Each converted
    /// sample gains the difference of the two geoids' undulations there (an ellipsoid's
    /// being 0), exact every 32 output samples and rows, bilinear between.
    /// Returns how many inputs are converted.
    pub fn convert_datums(
        &mut self,
        datum_of: &dyn Fn(&Path) -> Option<crate::LoadedDatum>,
        to: &crate::LoadedDatum,
    ) -> usize {
        let to_lon_lat = Transform::new(&self.crs, &Crs::wgs84());
        let (origin, pixel) = (self.origin, self.pixel);
        let mut converted = 0;
        for input in &mut self.inputs {
            let Some(from) = datum_of(K::path(&input.file)).filter(|d| d.name() != to.name()) else { continue };
            let shift = DatumShift::new(&from, to, &to_lon_lat, (origin, pixel), (input.columns, input.rows));
            input.shift = Some(Arc::new(shift));
            converted += 1;
        }
        converted
    }

    /// What the heights are measured from, as recorded.
    pub fn datum(&self) -> Option<&crate::DatumName> {
        self.datum.as_ref()
    }

    /// The output CRS.
    pub fn crs(&self) -> &Crs {
        &self.crs
    }

    /// Makes every row, in order, 32 at a time in parallel.
    fn make_rows(&self, rows: std::ops::Range<u32>, row: &mut dyn FnMut(&[K::Value]) -> Result<()>) -> Result<()> {
        self.make_rows_with(rows, &|_| (), &mut |r, ()| row(&r))
    }

    /// [`Self::make_rows`], each row with what `of` finds in it where the row is made (on
    /// the pool, not on the thread that hands rows on).
    pub(crate) fn make_rows_with<T: Send>(
        &self,
        rows: std::ops::Range<u32>,
        of: &(dyn Fn(&[K::Value]) -> T + Sync),
        row: &mut FoundRow<'_, K::Value, T>,
    ) -> Result<()> {
        let reader = BandReader::new(self);
        let last = rows.end.min(self.size.1);
        let mut j = rows.start.min(last);
        while j < last {
            let end = (j + ROWS_AT_ONCE).min(last);
            let inputs = reader.band(j..end)?;
            let band: Vec<(Vec<K::Value>, T)> = (j..end)
                .into_par_iter()
                .map(|r| {
                    let made = self.row(r, &inputs);
                    let found = of(&made);
                    (made, found)
                })
                .collect();
            drop(inputs);
            for (r, found) in band {
                row(r, found)?;
            }
            reader.next_band();
            j = end;
        }
        Ok(())
    }

    /// Output rows `rows`, in order, made as [`ElevationSource::rows_in`] and
    /// [`ImageSource::rows_in`] make them, for either kind.
    ///
    /// # Errors
    /// As those.
    pub fn rows_of(&self, rows: std::ops::Range<u32>, row: &mut dyn FnMut(&[K::Value]) -> Result<()>) -> Result<()> {
        self.make_rows(rows, row)
    }

    /// [`Self::rows_of`], each row handed over (for a caller that keeps it: no copy).
    ///
    /// # Errors
    /// As those.
    pub fn rows_owned(
        &self,
        rows: std::ops::Range<u32>,
        row: &mut dyn FnMut(Vec<K::Value>) -> Result<()>,
    ) -> Result<()> {
        self.make_rows_with(rows, &|_| (), &mut |r, ()| row(r))
    }

    /// Inputs, in order.
    pub fn inputs(&self) -> impl Iterator<Item = &Path> {
        self.inputs.iter().map(|i| K::path(&i.file))
    }

    /// Where each input lies on the output grid and how fine it is, in order (a VRT's
    /// sources one by one): what a collection's levels are planned from.
    pub fn layout(&self) -> Vec<InputLayout> {
        (self.inputs.iter())
            .filter(|i| !i.is_dropped())
            .map(|i| InputLayout {
                path: K::path(&i.file).to_path_buf(),
                spacing: i.spacing,
                columns: i.columns,
                rows: i.rows,
            })
            .collect()
    }

    /// The output grid (to give a shard: [`MosaicOptions::grid`]).
    pub fn grid(&self) -> GridSpec {
        GridSpec { origin: self.origin, pixel: self.pixel, size: self.size }
    }

    /// The inputs (in order, each file once) that output rows `rows` read: those whose
    /// footprint, with the bilinear margin the rows are made with, touches them. Known
    /// from the inputs' headers alone.
    pub fn inputs_in_rows(&self, rows: std::ops::Range<u32>) -> Vec<PathBuf> {
        let (start, end) = (i64::from(rows.start), i64::from(rows.end));
        let mut out: Vec<PathBuf> = vec![];
        for input in &self.inputs {
            let path = K::path(&input.file);
            if start < end && input.rows.0 < end && input.rows.1 >= start && !out.iter().any(|p| p == path) {
                out.push(path.to_path_buf());
            }
        }
        out
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
            let footprint = self.columns_of(input);
            // Whole lattice cells of the footprint over the columns made (the footprint
            // where rows are made across it: see `only_columns`).
            let Some((c0, c1)) = visible(footprint, self.made) else { continue };
            if out[c0..=c1].iter().all(|v| !K::is_none(v)) {
                continue;
            }
            let empty: Option<Vec<bool>> = input.shift.as_ref().map(|_| out[c0..=c1].iter().map(K::is_none).collect());
            // A corner beyond this input's pixels: the latest neighbour's of its CRS and
            // pixel size with data there (its pixel, on one lattice; else bilinear there).
            let edge = |x: i64, y: i64| {
                let Some((_, ox, oy)) = input.lattice else { return K::NONE };
                for &other in band.neighbours[place].iter().rev() {
                    let neighbour = &self.inputs[band.inputs[other]];
                    // Only heights of this input's datum blend with its own.
                    if !DatumShift::same(neighbour.shift.as_deref(), input.shift.as_deref()) {
                        continue;
                    }
                    let (Some(w), Some((_, nx, ny))) = (&band.windows[other], neighbour.lattice) else {
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
            match input.placement {
                Placement::Shifted(sx, sy) => {
                    // From the footprint's first column, as a row across it makes them.
                    let (c0, c1) = footprint;
                    #[expect(clippy::cast_precision_loss, reason = "pixel indices are far below 2^52")]
                    window.shifted_into(c0 as f64 + sx, f64::from(j) + sy, &mut out[c0..=c1], &edge);
                }
                // The input's own pixels: a copy of its row.
                Placement::Aligned(ox, oy) => window.fill_row(c0 as i64 + ox, i64::from(j) + oy, &mut out[c0..=c1]),
                Placement::Warped => {
                    // The input pixel coordinates of every sample of the row in this
                    // input's footprint: exact on a lattice every LATTICE samples and
                    // rows, bilinear between (see LATTICE for how far off that is).
                    let l = j / LATTICE_ROWS;
                    let (Some(top), Some(bottom)) = (band.lattice.get(&(index, l)), band.lattice.get(&(index, l + 1)))
                    else {
                        continue;
                    };
                    let fy = f64::from(j % LATTICE_ROWS) / f64::from(LATTICE_ROWS);
                    let mut pair = None;
                    // The lattice spans the footprint; the cells over the visible columns.
                    let (f0, f1) = footprint;
                    let first = (c0 - f0) / LATTICE;
                    for k in first..top.len().saturating_sub(1) {
                        let (from, to) = (f0 + k * LATTICE, (f0 + (k + 1) * LATTICE).min(f1));
                        if k > first && from >= c1 {
                            break;
                        }
                        let mix = |p: (f64, f64), q: (f64, f64), t: f64| (p.0 + (q.0 - p.0) * t, p.1 + (q.1 - p.1) * t);
                        let (a, b) = (mix(top[k], bottom[k], fy), mix(top[k + 1], bottom[k + 1], fy));
                        let last = if to == c1 { to } else { to - 1 };
                        #[expect(clippy::cast_precision_loss, reason = "offsets of at most LATTICE")]
                        let step = 1.0 / (to - from).max(1) as f64;
                        let d = ((b.0 - a.0) * step, (b.1 - a.1) * step);
                        window.line_into((a, d), &mut out[from..=last], &edge, &mut pair);
                        if to == f1 {
                            break;
                        }
                    }
                }
            }
            if let (Some(shift), Some(empty)) = (&input.shift, empty) {
                shift.lift::<K>(j, c0, &mut out[c0..=c1], &empty);
            }
        }
        out
    }
}

/// How an input's pixels lie on the output grid: [`Placement::Aligned`] when they are the
/// output's (the same CRS and spacing, to 1e-9; its origin a whole number of pixels away,
/// to 1e-6 of a pixel), [`Placement::Shifted`] when only the offset has a fraction. Output grid
/// and input as (origin, pixel size); `window` the file's pixels read (a VRT source's).
#[expect(clippy::cast_possible_truncation, reason = "checked to be near a whole number of pixels")]
fn placement_of(
    to_input: &Transform,
    (origin, pixel): ([f64; 2], (f64, f64)),
    (input_origin, input_pixel): ([f64; 2], (f64, f64)),
    window: [u32; 4],
) -> Placement {
    let same = |a: f64, b: f64| (a - b).abs() <= 1e-9 * a.abs().max(b.abs());
    if !to_input.is_identity() || !same(pixel.0, input_pixel.0) || !same(pixel.1, input_pixel.1) {
        return Placement::Warped;
    }
    let dx = (origin[0] - input_origin[0]) / pixel.0;
    let dy = (input_origin[1] - origin[1]) / pixel.1;
    if !(dx.is_finite() && dy.is_finite() && dx.abs() < 1e12 && dy.abs() < 1e12) {
        return Placement::Warped;
    }
    let whole = |v: f64| ((v - v.round()).abs() <= 1e-6).then(|| v.round() as i64);
    match (whole(dx), whole(dy)) {
        (Some(x), Some(y)) => Placement::Aligned(x + i64::from(window[0]), y + i64::from(window[1])),
        _ => Placement::Shifted(dx + f64::from(window[0]), dy + f64::from(window[1])),
    }
}

/// The files of the VRT at `path`, when reading them as inputs of their own is reading the
/// VRT: every source is a whole file, read as it is (no window or scale of the VRT's own,
/// no nodata but the file's own), and placed where the file's own georeference places it,
/// in the VRT's CRS.
/// Ok(None) otherwise, or when its sources are all of one resolution. A collection takes
/// such files each as deep as its resolution reaches, where a VRT would be one input at
/// its finest source's spacing.
///
/// # Errors
/// What [`read_vrt`] or opening a source reports.
pub fn vrt_files_by_resolution<K: MosaicKind>(path: &Path) -> Result<Option<Vec<PathBuf>>> {
    let vrt = read_vrt(path)?;
    let Ok(crs) = Crs::parse(&vrt.crs) else { return Ok(None) };
    let same = |a: f64, b: f64| (a - b).abs() <= 1e-9 * a.abs().max(b.abs()).max(1e-300);
    let first = vrt.sources.first().map(|s| s.pixel);
    if vrt.sources.iter().all(|s| first.is_some_and(|p| same(s.pixel.0, p.0) && same(s.pixel.1, p.1))) {
        return Ok(None);
    }
    let mut files = Vec::new();
    for source in &vrt.sources {
        let file = K::open(&source.path)?;
        #[expect(clippy::cast_possible_truncation, reason = "nodata is compared as f32, as samples are kept")]
        let own = |n: f64| K::nodata(&file).is_some_and(|m| m as f32 == n as f32);
        if source.nodata.is_some_and(|n| !own(n)) || source.scale.is_some() {
            return Ok(None);
        }
        let (w, h) = K::size(&file);
        let Some((file_crs, origin, pixel)) = crs_placement(K::georeference(&file), K::crs_pixel(&file)) else {
            return Ok(None);
        };
        let placed = |a: f64, b: f64, unit: f64| (a - b).abs() <= 1e-6 * unit;
        let whole = source.window == [0, 0, w, h];
        let here = Crs::parse(file_crs).is_ok_and(|c| c == crs)
            && placed(origin[0], source.origin[0], pixel.0)
            && placed(origin[1], source.origin[1], pixel.1)
            && same(pixel.0, source.pixel.0)
            && same(pixel.1, source.pixel.1);
        if !(whole && here) {
            return Ok(None);
        }
        files.push(source.path.clone());
    }
    Ok(Some(files))
}

/// Opens one input: a georeferenced GeoTIFF of heights in a CRS the tiler knows, or a
/// VRT's sources (each a window of a GeoTIFF, placed by the VRT).
fn open_inputs<K: MosaicKind>(path: &Path) -> Result<Vec<Opened<K>>> {
    let plain = K::open;
    if is_vrt(path) {
        let vrt = read_vrt(path)?;
        let crs =
            Crs::parse(&vrt.crs).map_err(|e| Error::georeference(path, format!("its SRS cannot be used: {e}")))?;
        return vrt
            .sources
            .into_iter()
            .map(|source| {
                let file = plain(&source.path)?;
                K::check_bands(&file, vrt.bands, path)?;
                let (w, h) = K::size(&file);
                let [x, y, sw, sh] = source.window;
                if x.saturating_add(sw) > w || y.saturating_add(sh) > h {
                    return Err(Error::damaged(
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
        return Err(Error::georeference(
            path,
            "it does not say where it lies (no GeoTIFF georeference, world file or .aux.xml with a CRS)",
        ));
    };
    let crs =
        Crs::parse(crs).map_err(|e| Error::georeference(path, format!("its georeference cannot be used: {e}")))?;
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
