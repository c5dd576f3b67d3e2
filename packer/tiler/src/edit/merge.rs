//! Merging archives (`terrastream merge`): the shards of a sharded run, or archives of
//! the same grid.
//!
//! Inputs must agree on their layers (grid, tile size, border, format, compression, height
//! encoding) and CRS; the first difference is the error, naming both files. One difference
//! is allowed: u16 heights stored with plain zstd (archives made before gradient coding)
//! and gradient-coded ones merge, each tile stored the first input's way. Tiles are
//! copied as stored (no decoding, but for that), a later input's tile replacing an earlier one's with
//! the same key (`prefer last`), and written through the writer, which deduplicates
//! payloads and rebuilds the directories; the output appears only once complete. The tiles
//! a replacement leaves stale (borders, coarser levels) are made again ([`crate::edit::rederive`]).
//!
//! Shards (`tile --shard I/N`) hold every layer up to its split LOD K. When all N shards
//! of a run are given, the levels above K are made here: the shards' LOD-K tiles are
//! decoded into rows of LOD K (heights exactly as stored; PNG and WebP pixels exactly),
//! which go through the same pyramid as a whole run's, from LOD K up. Because a whole run
//! builds each level from the level below *as stored*, the result is, byte for byte, the
//! archive one run makes.

use std::collections::{BTreeMap, HashMap};
use std::path::{Path, PathBuf};

use rayon::prelude::*;
use terrastream_format::{
    Layer, LayerKind, Metadata, MmapSource, PayloadCompression, Reader, TileFormat, TileKey, TileLocation,
    payload_bytes,
};
use terrastream_pack::progress::Progress;
use terrastream_pack::{Appender, WriteSummary, Writer, WriterOptions, compress_heights};

use crate::collection::RunInputs;
use crate::edit::merged::{MergeLayer, MergedHeights, MergedTexture};
use crate::edit::rederive::{LayerGrid, Remade, rederive};
use crate::encode::{decode_heights, decode_texture, encode_texture, quantize_heights};
use crate::error::{Error, Result};
use crate::options::TextureFormat;
use crate::pyramid::{Pixel, SortedSpool, Spool, Window};
use crate::tile::{HeightEncoder, ZSTD_LEVEL, run_pyramid};
use crate::water::WaterSummary;

/// What [`merge`] did.
#[derive(Clone, Debug)]
pub struct MergeSummary {
    /// The archive written.
    pub write: WriteSummary,
    /// Tiles copied from the inputs.
    pub copied: u64,
    /// Tiles of an earlier input replaced by a later one's.
    pub replaced: u64,
    /// Tiles made from the shards' split-LOD tiles (the levels above it).
    pub made: u64,
}

/// Where a winning tile's bytes are.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub(crate) struct Found {
    /// The input (its index in the merge's inputs).
    pub(crate) input: usize,
    /// The blob's absolute offset in the input's file.
    offset: u64,
    /// The payload's length.
    length: u32,
}

impl Found {
    fn location(self, key: TileKey) -> TileLocation {
        TileLocation { key, offset: self.offset, length: self.length }
    }
}

/// Tiles several inputs hold with different bytes: every version, in input order.
pub(crate) type Conflicts = HashMap<u64, Vec<Found>>;

/// How tiles that several inputs hold are merged.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub enum Prefer {
    /// A later input's tile replaces an earlier one's.
    #[default]
    Last,
    /// Per sample, at LOD 0: a later input's samples with data replace an earlier one's;
    /// its nodata (transparent) samples keep them. What an update of a region with rasters
    /// that do not fill their tiles needs.
    Pixels,
}

/// Merges `inputs` into `out` (see the module's documentation).
///
/// # Errors
/// [`Error::Input`] naming an archive that cannot be read or that differs from the first
/// (what differs), or an incomplete set of shards; writer and I/O errors; an interrupted
/// error (Ctrl-C), with nothing written.
pub fn merge(inputs: &[PathBuf], out: &Path, progress: &dyn Progress) -> Result<MergeSummary> {
    merge_with(inputs, out, Prefer::Last, progress)
}

/// [`merge`], tiles several inputs hold merged as `prefer` says.
///
/// # Errors
/// As [`merge`].
pub fn merge_with(inputs: &[PathBuf], out: &Path, prefer: Prefer, progress: &dyn Progress) -> Result<MergeSummary> {
    merge_with_water(inputs, out, prefer, None, RunInputs::default(), progress).map(|(summary, _)| summary)
}

/// [`merge_with`], then, with `water`, the merged archive's water layer made from that mask
/// as [`crate::add_water`] makes it: what shards that hold a water layer need for the
/// levels above their split LOD (a water tile is the mask's, not its children's means).
///
/// # Errors
/// As [`merge_with`] and [`crate::add_water`]; a mask that cannot be opened is named before
/// anything is merged.
pub fn merge_with_water(
    inputs: &[PathBuf],
    out: &Path,
    prefer: Prefer,
    water: Option<&Path>,
    run: RunInputs<'_>,
    progress: &dyn Progress,
) -> Result<(MergeSummary, Option<WaterSummary>)> {
    if let Some(mask) = water {
        crate::water::check_mask(mask)?;
    }
    // One collection alone: copied as it is (the compact copy of an archive updated in
    // place), its tiles made again from none.
    let summary = if let [one] = inputs
        && let Ok(reader) = Reader::open_mmap(one)
        && is_collection(reader.metadata())
    {
        let metadata = reader.metadata().clone();
        drop(reader);
        merge_widened_as(inputs, out, prefer, None, Some(&metadata), water.is_some(), run, progress)?
    } else {
        merge_widened_as(inputs, out, prefer, None, None, water.is_some(), run, progress)?
    };
    let water = water.map(|mask| crate::add_water(out, mask, out, progress)).transpose()?;
    Ok((summary, water))
}

/// Warns where shards hold a water layer whose levels above their split LOD a merge does
/// not make (they are the mask's: `merge --water` makes them).
pub(crate) fn warn_water_above_split(metadata: &Metadata, split_lods: &[u8]) {
    for (index, layer) in metadata.layers.iter().enumerate() {
        let k = split_lods.get(index).copied().unwrap_or(0);
        if layer.kind == LayerKind::Water && k + 1 < layer.num_lods {
            tracing::warn!(
                "layer {:?}: the shards hold water tiles up to LOD {k}; those above are made from the mask, not from \
                 them: give the merge `--water MASK` (or run `terrastream water` on its output), else readers take \
                 the sea from the heights there",
                layer.name
            );
        }
    }
}

/// [`merge_with`], the terrain's height range widened to hold `heights` (an update's new
/// heights, seen while tiling them); with `as_is`, as [`merge_in_place_as`]. `water_follows`: the
/// output's water layer is made next (no warning that shards' water stops at their split).
#[expect(clippy::too_many_arguments, reason = "the inputs, how to merge them, and what follows")]
pub(crate) fn merge_widened_as(
    inputs: &[PathBuf],
    out: &Path,
    prefer: Prefer,
    heights: Option<(f32, f32)>,
    as_is: Option<&Metadata>,
    water_follows: bool,
    run: RunInputs<'_>,
    progress: &dyn Progress,
) -> Result<MergeSummary> {
    let mut prepared = prepare(inputs, progress)?;
    widen(&mut prepared.metadata, heights);
    if let Some(m) = as_is {
        prepared.metadata = m.clone();
    }
    let folder = terrastream_pack::output_folder(out);
    let mut spool = Spool::new(&folder)?;
    if as_is.is_some() {
        // The second input's tiles stand as they are.
    } else if let Some(split_lods) = prepared.shards.clone() {
        prepared.make_above(&split_lods, run, &inputs[0], &mut spool, progress)?;
        crate::collection::merge::widen_to_the_data(&mut prepared.metadata, &split_lods, &inputs[0])?;
        if !water_follows {
            warn_water_above_split(&prepared.metadata, &split_lods);
        }
    } else {
        crate::collection::merge::warn_unread(&prepared.metadata, None, &run);
        let Prepared { readers, metadata, winners, conflicts, .. } = &mut prepared;
        for order in rederive_layers(metadata, readers, winners, conflicts, prefer, &mut spool)? {
            winners.remove(&order);
        }
    }
    let Prepared { readers, mut metadata, winners, conflicts, .. } = prepared;
    if as_is.is_none() {
        // Each layer's finest box and its degrees from every tile the output holds, as a
        // run records them (the inputs' boxes are each their own).
        let held = winners.iter().filter_map(|(&order, found)| readers[found.input].archive().tile_of(order).ok());
        crate::plan::settle_details(&mut metadata, held.chain(spool.keys()));
    }
    let made = spool.tiles() as u64;
    let options = WriterOptions { batch_bytes: 4 << 20, ..WriterOptions::default() };
    let mut writer = Writer::create(out, metadata.clone(), options)?;
    let copied = write(&mut writer, &readers, &winners, spool.into_sorted()?, progress)?;
    Ok(MergeSummary { write: writer.finish()?, copied, replaced: conflicts.len() as u64, made })
}

/// [`merge_widened_as`] of `inputs` = `[base, changes]` written into `target` in place
/// (FORMAT.md §7.1): `target` is `base` itself or a byte copy of it. The base's tiles stay
/// where they are; only the changes' tiles and the remade ones are appended.
///
/// # Errors
/// `terrastream_pack::Error::NoRoom` (in [`Error::Pack`]) when `target` was written
/// without room for updates or the new directories outgrow it: `target` is then as it
/// was. Otherwise as [`merge_with`].
///
/// With `as_is`, the second input's tiles replace the first's as they are (none made
/// again) and the result has that metadata.
pub(crate) fn merge_in_place_as(
    inputs: &[PathBuf; 2],
    target: &Path,
    prefer: Prefer,
    heights: Option<(f32, f32)>,
    as_is: Option<&Metadata>,
    progress: &dyn Progress,
) -> Result<MergeSummary> {
    let Prepared { readers, mut metadata, mut winners, conflicts, .. } = prepare(inputs, progress)?;
    widen(&mut metadata, heights);
    if let Some(m) = as_is {
        metadata = m.clone();
    }
    tracing::debug!(tiles = winners.len(), replaced = conflicts.len(), "archives indexed");
    let mut appender = Appender::open(target, WriterOptions::default())?;
    if appender.header() != readers[0].header() {
        return Err(Error::input(target, format!("is not {} (it changed while updating?)", inputs[0].display())));
    }
    let mut spool = Spool::new(&terrastream_pack::output_folder(target))?;
    if as_is.is_none() {
        for order in rederive_layers(&metadata, &readers, &winners, &conflicts, prefer, &mut spool)? {
            winners.remove(&order);
        }
    }
    let made = spool.tiles() as u64;
    tracing::debug!(made, "tiles around and above the changes made again");
    let copied = append(&mut appender, &readers, &winners, spool.into_sorted()?, progress)?;
    tracing::debug!("tiles appended");
    let write = appender.finish(&metadata)?;
    tracing::debug!(file_len = write.file_len, "new version published in place");
    Ok(MergeSummary { write, copied, replaced: conflicts.len() as u64, made })
}

/// [`write()`] into an [`Appender`] over `readers[0]`'s bytes: its tiles are kept where
/// they are, as is a made tile whose bytes it already holds; the rest is appended.
fn append(
    appender: &mut Appender,
    readers: &[Reader<MmapSource>],
    winners: &BTreeMap<u64, Found>,
    made: SortedSpool,
    progress: &dyn Progress,
) -> Result<u64> {
    let base = &readers[0];
    let data = base.header().data.offset;
    // New bytes are appended unless the base holds the same for the tile already.
    let add = |appender: &mut Appender, key: TileKey, order: u64, bytes: &[u8]| -> Result<()> {
        match base.locate(key)? {
            Some(at) if at.length as usize == bytes.len() && base.read(&at)?[..] == bytes[..] => {
                Ok(appender.keep(key, order, at.offset - data, at.length)?)
            }
            _ => Ok(appender.add(key, order, bytes)?),
        }
    };
    in_order(readers, winners, made, progress, |next| match next {
        Next::Input { key, order, found: Found { input: 0, offset, length } } => {
            Ok(appender.keep(key, order, offset - data, length)?)
        }
        Next::Input { key, order, found } => add(appender, key, order, &stored_as_first(readers, key, found)?),
        Next::Made { key, order, bytes } => add(appender, key, order, &bytes),
    })
}

/// The next tile of a merge, in archive order.
enum Next {
    /// An input's tile.
    Input {
        /// The tile.
        key: TileKey,
        /// Its position in archive order.
        order: u64,
        /// Where its bytes are.
        found: Found,
    },
    /// A made tile, replacing any input's.
    Made {
        /// The tile.
        key: TileKey,
        /// Its position in archive order.
        order: u64,
        /// Its stored bytes.
        bytes: Vec<u8>,
    },
}

/// Hands the inputs' winning tiles and the spooled (made) tiles to `sink` in archive
/// order; a made tile replaces an input's with the same key. Returns the inputs' tiles
/// handed.
fn in_order(
    readers: &[Reader<MmapSource>],
    winners: &BTreeMap<u64, Found>,
    mut made: SortedSpool,
    progress: &dyn Progress,
    mut sink: impl FnMut(Next) -> Result<()>,
) -> Result<u64> {
    progress.start("write", (winners.len() + made.len()) as u64);
    let mut copied = 0u64;
    for (&order, &found) in winners {
        while made.peek_order().is_some_and(|o| o < order) {
            if let Some((order, key, bytes)) = made.next_tile()? {
                sink(Next::Made { key, order, bytes })?;
                progress.advance(1);
            }
        }
        if made.peek_order() == Some(order) {
            continue;
        }
        if copied.is_multiple_of(1024) {
            progress.check()?;
        }
        let key = readers[found.input].archive().tile_of(order)?;
        sink(Next::Input { key, order, found })?;
        copied += 1;
        progress.advance(1);
    }
    while let Some((order, key, bytes)) = made.next_tile()? {
        sink(Next::Made { key, order, bytes })?;
        progress.advance(1);
    }
    progress.check()?;
    Ok(copied)
}

/// Widens the terrain's height range to hold `heights`, its span as a run over all the
/// heights sets it (`plan`).
fn widen(metadata: &mut Metadata, heights: Option<(f32, f32)>) {
    if let Some((lo, hi)) = heights.filter(|(lo, hi)| lo <= hi) {
        let t = &mut metadata.terrain;
        (t.min_elevation, t.max_elevation) = (t.min_elevation.min(f64::from(lo)), t.max_elevation.max(f64::from(hi)));
        let span = t.max_elevation - t.min_elevation;
        (t.displacement, t.elevation_range) = (span, span);
    }
}

/// Merge inputs, opened and checked, and their tiles indexed.
pub(crate) struct Prepared {
    pub(crate) readers: Vec<Reader<MmapSource>>,
    /// The merged archive's metadata.
    pub(crate) metadata: Metadata,
    /// With a complete set of shards: their split LODs.
    pub(crate) shards: Option<Vec<u8>>,
    winners: BTreeMap<u64, Found>,
    conflicts: Conflicts,
}

impl Prepared {
    /// Makes the levels above the split LODs into `spool`: those
    /// of a collection split below its base from the level's tiles and the run's inputs
    /// (`run`; [`crate::collection::merge`]), the others from their children (see
    /// [`reduce`]). `named`: the archive errors name.
    pub(crate) fn make_above(
        &self,
        split_lods: &[u8],
        run: RunInputs<'_>,
        named: &Path,
        spool: &mut Spool,
        progress: &dyn Progress,
    ) -> Result<()> {
        let payload = |key: TileKey| payload(&self.metadata, &self.readers, &self.winners, key);
        crate::collection::merge::make_above_split(&self.metadata, split_lods, run, &payload, named, spool, progress)?;
        reduce(&self.metadata, &self.readers, &self.winners, split_lods, spool, progress)
    }
}

/// Whether an archive's levels do not all cover its data (a collection's).
pub(crate) fn is_collection(metadata: &Metadata) -> bool {
    metadata.layers.iter().any(|l| l.extent.as_ref().is_some_and(|e| !e.partial.is_empty()))
}

/// Opens and checks the inputs, and indexes their tiles.
pub(crate) fn prepare(inputs: &[PathBuf], progress: &dyn Progress) -> Result<Prepared> {
    let Some(first) = inputs.first() else {
        return Err(Error::NothingToTile);
    };
    let readers = inputs
        .iter()
        .map(|p| Reader::open_mmap(p).map_err(|e| Error::input(p, format!("cannot open archive: {e}"))))
        .collect::<Result<Vec<_>>>()?;
    let base = readers[0].metadata();
    for (path, reader) in inputs.iter().zip(&readers).skip(1) {
        if let Some(why) = difference(base, reader.metadata()) {
            return Err(Error::input(path, format!("cannot merge with {}: {why}", first.display())));
        }
    }
    let shards = shard_set(inputs, &readers)?;
    let mut metadata = base.clone();
    metadata.shard = None;
    // Every input's sources (collections of other surveys over one base), each once.
    for reader in &readers[1..] {
        for source in &reader.metadata().sources {
            if !metadata.sources.contains(source) {
                metadata.sources.push(source.clone());
            }
        }
    }
    // Heights of all inputs (archives of one grid may come from runs over other areas).
    let terrain = readers.iter().map(|r| &r.metadata().terrain);
    metadata.terrain.min_elevation = terrain.clone().map(|t| t.min_elevation).fold(f64::INFINITY, f64::min);
    metadata.terrain.max_elevation = terrain.map(|t| t.max_elevation).fold(f64::NEG_INFINITY, f64::max);
    // Where the data is: all inputs' (a shard's extent is its band); the writer narrows it
    // to the tiles it gets.
    for (index, layer) in metadata.layers.iter_mut().enumerate() {
        layer.extent =
            readers.iter().filter_map(|r| r.metadata().layers.get(index)?.extent.clone()).reduce(|a, b| a.union(&b));
        // Degrees of the whole box, as one run over all the inputs makes them (a union
        // of the bands' degree boxes would differ by the curvature between samples).
        if let (Some(extent), Some(g)) = (&mut layer.extent, &metadata.georeference)
            && let Some(lon_lat) = crate::plan::lon_lat_box(g, extent.detail)
        {
            extent.lon_lat = Some(lon_lat);
        }
    }
    // The known datum, with a geoid's undulation over all the inputs' footprints (one
    // grid's nodes).
    if let Some(known) = readers.iter().map(|r| &r.metadata().vertical_datum).find(|d| !d.is_unknown()) {
        metadata.vertical_datum = known.clone();
    }
    let lattices = readers.iter().filter_map(|r| r.metadata().vertical_datum.undulation.clone());
    metadata.vertical_datum.undulation = lattices.reduce(|a, b| a.union(&b).unwrap_or(a));
    let (winners, conflicts) = winners(&readers, progress)?;
    Ok(Prepared { readers, metadata, shards, winners, conflicts })
}

/// The first way `other` cannot be merged with `base`, or None.
fn difference(base: &Metadata, other: &Metadata) -> Option<String> {
    if base.layers.len() != other.layers.len() {
        return Some(format!("{} layers, not {}", other.layers.len(), base.layers.len()));
    }
    for (a, b) in base.layers.iter().zip(&other.layers) {
        let (ja, jb) = (serde_json::to_value(a).ok()?, serde_json::to_value(b).ok()?);
        if let (Some(ja), Some(jb)) = (ja.as_object(), jb.as_object()) {
            let keys = ja.keys().chain(jb.keys().filter(|k| !ja.contains_key(*k)));
            for key in keys {
                let (va, vb) = (ja.get(key), jb.get(key));
                // Where the data is may differ (a shard holds a band): the union is kept.
                if va != vb && key != "extent" && !(key == "compression" && transcodable(a, b)) {
                    let show = |v: Option<&serde_json::Value>| v.map_or("none".to_owned(), ToString::to_string);
                    return Some(format!("layer {:?}: {key} {} here, {} there", a.name, show(vb), show(va)));
                }
            }
        }
    }
    let crs = |m: &Metadata| m.georeference.as_ref().map(|g| (g.crs.clone(), g.origin));
    if crs(base) != crs(other) {
        let show = |m: &Metadata| {
            m.georeference.as_ref().map_or("no georeference".to_owned(), |g| {
                format!("{} at origin {:?}", g.crs.as_deref().unwrap_or("no CRS"), g.origin)
            })
        };
        return Some(format!("CRS {} here, {} there", show(other), show(base)));
    }
    // Heights of unknown datum merge with any (the known one is kept).
    let (da, db) = (&base.vertical_datum, &other.vertical_datum);
    if !da.is_unknown() && !db.is_unknown() && (da.reference, &da.geoid) != (db.reference, &db.geoid) {
        return Some(format!("heights above the {} here, the {} there", db.describe(), da.describe()));
    }
    None
}

/// With shards: every input is one, all of one run, each once; their split LODs. Without
/// any shard: None.
fn shard_set(inputs: &[PathBuf], readers: &[Reader<MmapSource>]) -> Result<Option<Vec<u8>>> {
    let shards: Vec<_> = readers.iter().map(|r| r.metadata().shard.clone()).collect();
    let Some(first) = shards.iter().flatten().next().cloned() else { return Ok(None) };
    let mut seen = vec![false; first.count as usize];
    for (path, shard) in inputs.iter().zip(&shards) {
        let Some(s) = shard else {
            return Err(Error::input(path, "not a shard, merged with shards (merge those first)"));
        };
        if s.count != first.count || s.split_lods != first.split_lods {
            return Err(Error::input(path, format!("shard {}/{} of another run", s.index, s.count)));
        }
        let slot = seen.get_mut(s.index as usize).ok_or_else(|| Error::input(path, "shard index out of range"))?;
        if std::mem::replace(slot, true) {
            return Err(Error::input(path, format!("shard {}/{} given twice", s.index, s.count)));
        }
    }
    let missing: Vec<String> = (0..first.count).filter(|&i| !seen[i as usize]).map(|i| i.to_string()).collect();
    if !missing.is_empty() {
        return Err(Error::input(
            &inputs[0],
            format!(
                "shards {} of {} are missing: a merge of shards needs all of them",
                missing.join(", "),
                first.count
            ),
        ));
    }
    Ok(Some(first.split_lods))
}

/// Every tile of every input, by archive key; a later input's replaces an earlier one's.
/// Also the keys of the tiles more than one input holds.
fn winners(readers: &[Reader<MmapSource>], progress: &dyn Progress) -> Result<(BTreeMap<u64, Found>, Conflicts)> {
    let step = terrastream_format::MAX_LAYERS as u64;
    let mut winners = BTreeMap::new();
    let mut replaced: Conflicts = HashMap::new();
    progress.start("index", readers.iter().map(|r| r.header().addressed_tiles).sum());
    for (i, reader) in readers.iter().enumerate() {
        let data = reader.header().data.offset;
        reader.for_each_entry(|e| -> Result<()> {
            progress.check()?;
            for k in 0..u64::from(e.run_length) {
                let order = e.key + k * step;
                let found = Found { input: i, offset: data + e.offset, length: e.length };
                if let Some(before) = winners.insert(order, found) {
                    // The same bytes again (an archive merged with itself, a shared tile)
                    // replace nothing.
                    if !same_bytes(readers, order, before, found)? {
                        replaced.entry(order).or_insert_with(|| vec![before]).push(found);
                    }
                }
            }
            progress.advance(u64::from(e.run_length));
            Ok(())
        })?;
    }
    Ok((winners, replaced))
}

/// Do two inputs' tiles hold the same bytes (the same stored bytes, or where the two
/// inputs compress the layer differently, the same payload)?
fn same_bytes(readers: &[Reader<MmapSource>], order: u64, a: Found, b: Found) -> Result<bool> {
    let key = readers[a.input].archive().tile_of(order)?;
    let compression = |input: usize| readers[input].metadata().layers[usize::from(key.layer())].compression;
    if compression(a.input) != compression(b.input) {
        return Ok(unpacked(readers, key, a)? == unpacked(readers, key, b)?);
    }
    if a.length != b.length {
        return Ok(false);
    }
    let read = |found: Found| -> Result<Vec<u8>> { Ok(readers[found.input].read(&found.location(key))?.to_vec()) };
    Ok(read(a)? == read(b)?)
}

/// Writes the inputs' winning tiles and the spooled (made) tiles in archive order; a made
/// tile replaces an input's with the same key. Returns the tiles copied.
pub(crate) fn write(
    writer: &mut Writer,
    readers: &[Reader<MmapSource>],
    winners: &BTreeMap<u64, Found>,
    made: SortedSpool,
    progress: &dyn Progress,
) -> Result<u64> {
    in_order(readers, winners, made, progress, |next| match next {
        Next::Input { key, found, .. } => Ok(writer.add_stored(key, stored_as_first(readers, key, found)?)?),
        Next::Made { key, bytes, .. } => Ok(writer.add_stored(key, bytes)?),
    })
}

/// The stored bytes of a tile if any input has it, its layer's compression undone.
pub(crate) fn payload(
    metadata: &Metadata,
    readers: &[Reader<MmapSource>],
    winners: &BTreeMap<u64, Found>,
    key: TileKey,
) -> Result<Option<Vec<u8>>> {
    let order = Writer::order_key(metadata, key)?;
    let Some(&found) = winners.get(&order) else { return Ok(None) };
    unpacked(readers, key, found).map(Some)
}

/// A tile's bytes where `found` says they are, its input's compression undone.
pub(crate) fn unpacked(readers: &[Reader<MmapSource>], key: TileKey, found: Found) -> Result<Vec<u8>> {
    let stored = readers[found.input].read(&found.location(key))?;
    let layer = &readers[found.input].metadata().layers[usize::from(key.layer())];
    Ok(payload_bytes(layer, &stored, &format!("tile {key}"))?.into_owned())
}

/// A tile's stored bytes where `found` says they are, as the merged archive (the first
/// input's layers) stores them: as they are, or, from an input whose u16 heights are
/// compressed another way (`zstd` before gradient coding, see [`transcodable`]), decoded
/// and compressed again the first input's way.
fn stored_as_first(readers: &[Reader<MmapSource>], key: TileKey, found: Found) -> Result<Vec<u8>> {
    let input = found.input;
    let stored = readers[input].read(&found.location(key))?;
    let layer = |i: usize| &readers[i].metadata().layers[usize::from(key.layer())];
    let (ours, theirs) = (layer(0), layer(input));
    if ours.compression == theirs.compression {
        return Ok(stored.to_vec());
    }
    let raw = payload_bytes(theirs, &stored, &format!("tile {key}"))?;
    compress_heights(ours.compression, &raw, ours.stored_edge())
        .map_err(|e| Error::Encode { tile: key, reason: e.to_string() })
}

/// May layers `a` and `b`, alike otherwise, differ in their compression? Yes for u16
/// heights, plain zstd or gradient-coded: a merge stores them the first input's way.
fn transcodable(a: &Layer, b: &Layer) -> bool {
    let u16_heights = |l: &Layer| {
        l.format == TileFormat::RawU16
            && matches!(l.compression, PayloadCompression::Zstd | PayloadCompression::ZstdGradient)
    };
    u16_heights(a) && u16_heights(b)
}

/// A height-range tile's lowest and highest height.
pub(crate) fn range_of(bytes: &[u8]) -> Option<(f32, f32)> {
    let [a, b, c, d, e, f, g, h] = bytes[..] else { return None };
    Some((f32::from_le_bytes([a, b, c, d]), f32::from_le_bytes([e, f, g, h])))
}

/// Remakes, in every layer, the tiles the merge left stale ([`crate::edit::rederive`]) into
/// `spool`; returns the archive keys of stored tiles that hold no data once remade.
fn rederive_layers(
    metadata: &Metadata,
    readers: &[Reader<MmapSource>],
    winners: &BTreeMap<u64, Found>,
    conflicts: &Conflicts,
    prefer: Prefer,
    spool: &mut Spool,
) -> Result<Vec<u64>> {
    let archive = readers[0].archive();
    let keys: Vec<TileKey> =
        conflicts.keys().map(|&k| archive.tile_of(k)).collect::<terrastream_format::Result<_>>()?;
    // The tiles not from the first input: where the merge can have made others stale.
    let later: Vec<TileKey> = winners
        .iter()
        .filter(|(_, found)| found.input != 0)
        .map(|(&k, _)| archive.tile_of(k))
        .collect::<terrastream_format::Result<_>>()?;
    let mut emptied = Vec::new();
    for (index, layer) in metadata.layers.iter().enumerate() {
        let index = u8::try_from(index).map_err(|_| Error::NothingToTile)?;
        let grid = LayerGrid {
            layer: index,
            lods: layer.num_lods,
            res: layer.tile_resolution as usize,
            border: usize::from(layer.border),
            tiles: (layer.num_x_tiles, layer.num_y_tiles),
        };
        let of_layer = |keys: &[TileKey]| keys.iter().filter(|k| k.layer() == index).copied().collect();
        let merged = MergeLayer {
            metadata,
            readers,
            winners,
            all_conflicts: conflicts,
            prefer,
            index,
            conflicts: of_layer(&keys),
            later: of_layer(&later),
        };
        let mut remade = Remade::default();
        match layer.kind {
            LayerKind::Elevation => {
                let range = find_layer(metadata, LayerKind::HeightRange);
                let heights = MergedHeights { merged, encoder: HeightEncoder::new(metadata, index, range)? };
                rederive(&grid, &heights, &mut remade)?;
                let below = heights.ranges_below(&remade, range, &mut emptied)?;
                heights.encoder.finish(metadata, below, spool)?;
            }
            LayerKind::Texture => {
                let format = match TextureFormat::decodable(layer.format) {
                    Some(format) => format,
                    // Lossy tiles are not decoded back: stale tiles stay as they are.
                    None if conflicts.is_empty() => continue,
                    None => {
                        let other = layer.format;
                        tracing::warn!(
                            "layer {:?}: {other:?} tiles are lossy; the tiles around and above replaced ones are kept, not remade",
                            layer.name
                        );
                        continue;
                    }
                };
                let texture = MergedTexture { merged, format, edge: grid.res + 2 * grid.border };
                rederive(&grid, &texture, &mut remade)?;
            }
            // A water tile depends on its mask alone, not on its neighbours: it is taken
            // as it is. Only a coarse tile two inputs both hold loses one's part.
            LayerKind::Water if !merged.conflicts.is_empty() => {
                tracing::warn!(
                    "layer {:?}: {} water tiles are held by two inputs and the later one's is kept: add the water \
                     again to the merged archive (`terrastream water`) from a mask that covers it all",
                    layer.name,
                    merged.conflicts.len()
                );
                continue;
            }
            _ => continue,
        }
        for (key, bytes) in remade.entries {
            spool.add(metadata, key, &bytes)?;
        }
        for key in remade.emptied {
            emptied.push(Writer::order_key(metadata, key)?);
        }
    }
    Ok(emptied)
}

/// The index of `metadata`'s first layer of `kind`.
fn find_layer(metadata: &Metadata, kind: LayerKind) -> Option<u8> {
    metadata.layers.iter().position(|l| l.kind == kind).and_then(|i| u8::try_from(i).ok())
}

/// Makes every layer's levels above its split LOD from the LOD-K tiles (see the module).
fn reduce(
    metadata: &Metadata,
    readers: &[Reader<MmapSource>],
    winners: &BTreeMap<u64, Found>,
    split_lods: &[u8],
    spool: &mut Spool,
    progress: &dyn Progress,
) -> Result<()> {
    let find = |kind: LayerKind| metadata.layers.iter().position(|l| l.kind == kind).and_then(|i| u8::try_from(i).ok());
    let split = |index: usize| split_lods.get(index).copied().unwrap_or(0);
    let reduced = |index: usize, layer: &Layer| {
        split(index) + 1 < layer.num_lods && !crate::collection::merge::made_here(metadata, split_lods, index)
    };
    // The tiles above the splits, which the pyramids count as they make them (the height
    // ranges are made with their elevation).
    let above: u64 = (metadata.layers.iter().enumerate())
        .filter(|&(index, layer)| {
            reduced(index, layer) && matches!(layer.kind, LayerKind::Elevation | LayerKind::Texture)
        })
        .flat_map(|(index, layer)| (split(index) + 1..layer.num_lods).map(|lod| layer.grid_at(lod)))
        .map(|(x, y)| u64::from(x) * u64::from(y))
        .sum();
    if above > 0 {
        progress.start("tile", above);
    }
    for (index, layer) in metadata.layers.iter().enumerate() {
        if !reduced(index, layer) {
            continue;
        }
        let k = split(index);
        let index = u8::try_from(index).map_err(|_| Error::NothingToTile)?;
        let res = layer.tile_resolution as usize;
        let border = usize::from(layer.border);
        let edge = res + 2 * border;
        // The grid's samples at LOD 0: the raster's, padded to whole tiles with no data,
        // which the levels above treat as the raster's own padding.
        let size = (layer.num_x_tiles * layer.tile_resolution, layer.num_y_tiles * layer.tile_resolution);
        let height_k = (size.1 as usize).div_ceil(1 << k);
        let window = Window {
            input_lod: k,
            last_lod: layer.num_lods - 1,
            encode_from: k + 1,
            rows: 0..height_k,
            band: 0..height_k,
            first_column: 0,
        };
        let (cols, rows_k) = (layer.num_x_tiles.div_ceil(1 << k), layer.num_y_tiles.div_ceil(1 << k));
        match layer.kind {
            LayerKind::Elevation => {
                let heights = HeightEncoder::new(metadata, index, find(LayerKind::HeightRange))?;
                let encoding = heights.encoding;
                let decode = |key: TileKey| -> Result<Option<Vec<f32>>> {
                    Ok(payload(metadata, readers, winners, key)?.map(|raw| decode_heights(&raw, &encoding)))
                };
                let encode = |key: TileKey, samples: &[f32], _edge: usize| heights.encode(key, samples);
                let quantize = |row: &mut [f32]| quantize_heights(row, &encoding);
                run_pyramid(metadata, index, size, &window, &encode, Some(&quantize), spool, progress, |push| {
                    level_rows(index, k, (cols, rows_k), (size, res, border, edge), &decode, push)
                })?;
                // The split LOD's ranges (the shards' own) widen the ranges above them.
                let below = match find(LayerKind::HeightRange) {
                    Some(r) => {
                        let payload = |key: TileKey| payload(metadata, readers, winners, key);
                        let all = (0..rows_k).flat_map(|y| (0..cols).map(move |x| (x, y)));
                        split_ranges(&payload, (index, r), k, all)?
                    }
                    None => Vec::new(),
                };
                heights.finish(metadata, below, spool)?;
            }
            LayerKind::Texture => {
                let format = TextureFormat::decodable(layer.format).ok_or_else(|| Error::Pyramid {
                    layer: index,
                    lod: k,
                    reason: format!("{:?} tiles are lossy: shards need png or webp", layer.format),
                })?;
                let decode = |key: TileKey| -> Result<Option<Vec<[u8; 4]>>> {
                    payload(metadata, readers, winners, key)?
                        .map(|bytes| decode_texture(key, &bytes, edge, format))
                        .transpose()
                };
                let encode = move |key: TileKey, pixels: &[[u8; 4]], edge: usize| -> Result<Vec<(TileKey, Vec<u8>)>> {
                    Ok(vec![(key, encode_texture(key, pixels, edge, format, ZSTD_LEVEL)?)])
                };
                run_pyramid(metadata, index, size, &window, &encode, None, spool, progress, |push| {
                    level_rows(index, k, (cols, rows_k), (size, res, border, edge), &decode, push)
                })?;
            }
            // Made with their elevation layer.
            _ => {}
        }
    }
    Ok(())
}

/// Pushes LOD `k`'s rows, assembled from its tiles' interiors (decoded a row of tiles at
/// a time, in parallel); a missing tile is no data.
fn level_rows<S: Pixel>(
    layer: u8,
    k: u8,
    (cols, rows): (u32, u32),
    (size, res, border, edge): ((u32, u32), usize, usize, usize),
    decode: &(dyn Fn(TileKey) -> Result<Option<Vec<S>>> + Sync),
    push: &mut dyn FnMut(Vec<S>) -> Result<()>,
) -> Result<()> {
    // The level's size, as the pyramid has it.
    let (width, height) = ((size.0 as usize).div_ceil(1 << k), (size.1 as usize).div_ceil(1 << k));
    for ty in 0..rows {
        let tiles: Vec<Option<Vec<S>>> =
            (0..cols).into_par_iter().map(|tx| decode(TileKey::new(layer, k, tx, ty)?)).collect::<Result<_>>()?;
        for j in 0..res.min(height.saturating_sub(ty as usize * res)) {
            let mut row = vec![S::NONE; width];
            for (tx, tile) in tiles.iter().enumerate() {
                let (x0, x1) = (tx * res, ((tx + 1) * res).min(width));
                let from = (border + j) * edge + border;
                if let Some(src) = tile.as_ref().and_then(|t| t.get(from..from + (x1 - x0))) {
                    row[x0..x1].copy_from_slice(src);
                }
            }
            push(row)?;
        }
    }
    Ok(())
}

/// The height-range tiles of LOD `k` at `tiles` (as the shards stored them: `payload`).
pub(crate) fn split_ranges(
    payload: &crate::collection::merge::Payload<'_>,
    (elevation, range_layer): (u8, u8),
    k: u8,
    tiles: impl IntoIterator<Item = (u32, u32)>,
) -> Result<Vec<(TileKey, f32, f32)>> {
    let mut out = Vec::new();
    for (tx, ty) in tiles {
        if let Some((lo, hi)) = payload(TileKey::new(range_layer, k, tx, ty)?)?.as_deref().and_then(range_of) {
            // Keyed by the elevation tile, as the encoder gathers them.
            out.push((TileKey::new(elevation, k, tx, ty)?, lo, hi));
        }
    }
    Ok(out)
}
