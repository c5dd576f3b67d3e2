//! Several tile pyramids into one archive, one layer each: `pack --elevation SRC
//! --texture SRC`, so that, say, a Terrarium PMTiles of the planet's heights and an XYZ
//! tree of a region's imagery become one terrain.
//!
//! Each source is opened as one layer ([`Opened`]): its grid (which may differ from the
//! others' in depth and extent), its tiles in that layer's archive order, and a reader.
//! The layers must lie on one CRS and origin; the archive's tiles are then merged in
//! archive order, each read once from its source.

use std::path::{Path, PathBuf};

use bytes::Bytes;
use terrastream_format::{LayerKind, Metadata, TileKey};

use super::mbtiles::open_mbtiles;
use super::pmtiles::open_pmtiles;
use super::scan::TileScan;
use super::xyz::{TilesetInput, XYZ_KEY, XyzOptions, scan_xyz};
use crate::error::{Error, Result};
use crate::progress::Progress;
use crate::writer::{WriteSummary, Writer, WriterOptions};

/// Reads tile `index` of an [`Opened`] source; the text names the tile for errors.
type ReadTile<'a> = Box<dyn FnMut(usize, &str) -> Result<Bytes> + 'a>;

/// One tile pyramid opened as one layer.
pub(crate) struct Opened<'a> {
    /// The file or folder, for errors.
    pub input: PathBuf,
    /// A document with the one layer (index 0) and the source's georeference.
    pub metadata: Metadata,
    /// Its tiles (on layer 0) in archive order, with a name for errors.
    pub tiles: Vec<(TileKey, String)>,
    /// Reads the tile at an index of `tiles`.
    pub read: ReadTile<'a>,
}

/// Where one layer's tiles come from.
#[derive(Clone, Debug)]
pub enum PyramidSource {
    /// An XYZ / TMS folder tree, with its template and row order.
    Tree(PathBuf, XyzOptions),
    /// A PMTiles v3 raster archive.
    Pmtiles(PathBuf),
    /// An MBTiles raster tileset.
    Mbtiles(PathBuf),
}

/// One layer of [`pack_layers`]: what it holds and where its tiles are.
#[derive(Clone, Debug)]
pub struct LayerInput {
    /// Kind and height encoding of the layer.
    pub tileset: TilesetInput,
    /// Its tiles.
    pub source: PyramidSource,
}

/// Packs one pyramid per layer into one archive at `out`: each source becomes a layer
/// (named after its kind) with its own grid; tiles are stored unchanged; an elevation
/// layer's height range is read from its tiles.
///
/// # Errors
/// [`Error::Input`] naming the source at fault: one that cannot be read, two sources of
/// one kind, or sources whose CRSs or tile grids cannot be one archive (another CRS,
/// origin or scale); writer and I/O errors; [`Error::Interrupted`]. Nothing is written
/// under `out` on error.
pub fn pack_layers(
    inputs: &[LayerInput],
    out: &Path,
    options: WriterOptions,
    progress: &dyn Progress,
) -> Result<WriteSummary> {
    let opened = inputs.iter().map(|input| open(input, progress)).collect::<Result<Vec<_>>>()?;
    write_layers(opened, out, options, progress)
}

fn open(input: &LayerInput, progress: &dyn Progress) -> Result<Opened<'static>> {
    match &input.source {
        PyramidSource::Pmtiles(path) => open_pmtiles(path, input.tileset, progress),
        PyramidSource::Mbtiles(path) => open_mbtiles(path, input.tileset, progress),
        PyramidSource::Tree(root, options) => {
            let options =
                XyzOptions { kind: input.tileset.kind, elevation: input.tileset.elevation, ..options.clone() };
            let scanned = scan_xyz(root, &options)?;
            let format = scanned.metadata.layers[0].format;
            let (tiles, paths): (Vec<(TileKey, String)>, Vec<PathBuf>) =
                scanned.tiles.into_iter().map(|(key, path)| ((key, path.display().to_string()), path)).unzip();
            let read = move |index: usize, what: &str| -> Result<Bytes> {
                let path = paths.get(index).ok_or_else(|| Error::input(what, "no such tile"))?;
                super::read_tile(path, format).map(Bytes::from)
            };
            Ok(Opened { input: root.clone(), metadata: scanned.metadata, tiles, read: Box::new(read) })
        }
    }
}

/// Tiles read and scanned (heights, opaque rims) per step.
const BATCH: usize = 256;

/// Writes opened sources as the layers of one archive, in the order given.
///
/// # Errors
/// As [`pack_layers`].
pub(crate) fn write_layers(
    mut sources: Vec<Opened<'_>>,
    out: &Path,
    options: WriterOptions,
    progress: &dyn Progress,
) -> Result<WriteSummary> {
    let metadata = combined(&sources)?;
    // Every tile of every source on its layer, in archive order.
    let mut order = Vec::new();
    for (source, opened) in sources.iter().enumerate() {
        let layer = u8::try_from(source).map_err(|_| Error::input(&opened.input, "too many layers"))?;
        for (index, (key, _)) in opened.tiles.iter().enumerate() {
            let key = TileKey::new(layer, key.lod(), key.x(), key.y())?;
            order.push((Writer::order_key(&metadata, key)?, key, source, index));
        }
    }
    order.sort_unstable_by_key(|t| t.0);
    let mut scan = TileScan::new(&metadata, order.iter().map(|t| t.1));
    let mut writer = Writer::create(out, metadata, options)?;
    progress.start("pack", order.len() as u64);
    for batch in order.chunks(BATCH) {
        progress.check()?;
        let mut read = Vec::with_capacity(batch.len());
        for &(_, key, source, index) in batch {
            let opened = &mut sources[source];
            let what = &opened.tiles[index].1;
            read.push((key, (opened.read)(index, what)?));
        }
        let tiles: Vec<(TileKey, &[u8])> = read.iter().map(|(key, bytes)| (*key, &bytes[..])).collect();
        scan.scan(writer.metadata(), &tiles).map_err(|(i, why)| {
            let (_, _, source, index) = batch[i];
            Error::input(&sources[source].input, format!("{}: {why}", sources[source].tiles[index].1))
        })?;
        let count = read.len() as u64;
        for (key, bytes) in read {
            writer.add_stored(key, bytes.into())?;
        }
        progress.advance(count);
    }
    progress.check()?;
    scan.record(&mut writer)?;
    writer.finish()
}

/// The archive's metadata: the first source's, with every source's layer in order; the
/// layers must lie on one CRS, origin and scale.
fn combined(sources: &[Opened<'_>]) -> Result<Metadata> {
    let Some(first) = sources.first() else {
        return Err(Error::input(".", "nothing to pack"));
    };
    if sources.len() == 1 {
        return Ok(first.metadata.clone());
    }
    let mut metadata = first.metadata.clone();
    metadata.layers.clear();
    // The XYZ record describes a one-layer tree (for `extract --layout xyz`).
    metadata.extra.remove(XYZ_KEY);
    for opened in sources {
        let mut layer = opened.metadata.layers[0].clone();
        layer.name = match layer.kind {
            LayerKind::Elevation => "elevation".into(),
            _ => "texture".into(),
        };
        if let Some(other) = metadata.layers.iter().position(|l| l.name == layer.name) {
            return Err(Error::input(
                &opened.input,
                format!("a second {} source (the first: {})", layer.name, sources[other].input.display()),
            ));
        }
        let place = |m: &Metadata| m.georeference.as_ref().map(|g| (g.crs.clone(), g.origin, g.scale));
        if place(&opened.metadata) != place(&first.metadata) {
            let show = |m: &Metadata| {
                m.georeference.as_ref().map_or("no georeference".to_owned(), |g| {
                    format!("{} at origin {:?}", g.crs.as_deref().unwrap_or("no CRS"), g.origin)
                })
            };
            return Err(Error::input(
                &opened.input,
                format!(
                    "its tiles lie in {}, those of {} in {}: the layers of one archive share a CRS and tile grid",
                    show(&opened.metadata),
                    first.input.display(),
                    show(&first.metadata)
                ),
            ));
        }
        // Both grids must cover the same world: the same world units per LOD-0 tile edge
        // times tiles across (trees of other depths over one world scale exactly).
        let (ex, ez) = layer.world_extent();
        let (fx, fz) = first.metadata.layers[0].world_extent();
        if ((ex - fx).abs() > 1e-6 * fx.abs().max(1.0)) || ((ez - fz).abs() > 1e-6 * fz.abs().max(1.0)) {
            return Err(Error::input(
                &opened.input,
                format!(
                    "its grid covers {ex:.0} x {ez:.0} world units, that of {} {fx:.0} x {fz:.0}: the layers of one \
                     archive share a tile grid",
                    first.input.display()
                ),
            ));
        }
        metadata.layers.push(layer);
    }
    // Heights are what the elevation source says (read from its tiles when packed).
    if let Some(e) = sources.iter().find(|s| s.metadata.layers[0].kind == LayerKind::Elevation) {
        metadata.terrain = e.metadata.terrain.clone();
    }
    metadata.validate()?;
    Ok(metadata)
}
