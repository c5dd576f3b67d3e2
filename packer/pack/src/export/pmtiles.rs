//! `terrastream export --to pmtiles`: one layer as a PMTiles v3 archive that any PMTiles
//! reader opens. Our directory keys are PMTiles tile ids times 16 plus the layer, so this
//! re-encodes the directory and copies the (checked) payloads in the same order.

use std::collections::HashMap;
use std::io::Write;
use std::path::Path;

use terrastream_format::{
    Entry, Layer, MAX_LAYERS, Metadata, PayloadCompression, RangeSource, Reader, TileFormat, layer_of, tile_id_to_zxy,
};

use crate::error::{Error, Result};
use crate::progress::Progress;

const HEADER_LEN: u64 = 127;
/// The root directory must end within the first 16 KiB.
const ROOT_LIMIT: usize = 16_384 - 127;

/// What [`export_pmtiles`] wrote.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub struct PmtilesSummary {
    /// Tiles addressed.
    pub addressed_tiles: u64,
    /// Directory entries.
    pub tile_entries: u64,
    /// Distinct tile contents.
    pub tile_contents: u64,
    /// File size.
    pub file_len: u64,
}

/// (tile id, run length, offset, length) as PMTiles stores them.
pub type Row = (u64, u32, u64, u32);

fn varint(out: &mut Vec<u8>, v: u64) {
    terrastream_format::write_varint(out, v);
}

/// PMTiles v3 directory: columnar varints (offset 0 = right after the previous entry), gzip.
fn encode_directory(rows: &[Row]) -> Result<Vec<u8>> {
    let mut raw = Vec::with_capacity(rows.len() * 5 + 8);
    varint(&mut raw, rows.len() as u64);
    let mut last = 0;
    for r in rows {
        varint(&mut raw, r.0 - last);
        last = r.0;
    }
    for r in rows {
        varint(&mut raw, u64::from(r.1));
    }
    for r in rows {
        varint(&mut raw, u64::from(r.3));
    }
    for (i, r) in rows.iter().enumerate() {
        let contiguous = i > 0 && r.2 == rows[i - 1].2 + u64::from(rows[i - 1].3);
        varint(&mut raw, if contiguous { 0 } else { r.2 + 1 });
    }
    gzip(&raw)
}

fn gzip(bytes: &[u8]) -> Result<Vec<u8>> {
    let mut gz = flate2::write::GzEncoder::new(Vec::new(), flate2::Compression::best());
    let compress = |error| Error::Compress { what: "a PMTiles section", error };
    gz.write_all(bytes).map_err(compress)?;
    gz.finish().map_err(compress)
}

/// Root (and leaves) as the PMTiles reference writer lays them out: everything in the root
/// if it fits, else leaves of at least 4096 entries grown by 1.2x until the root fits.
///
/// # Errors
/// Only if compression fails or a leaf exceeds 4 GiB.
pub fn directories(rows: &[Row]) -> Result<(Vec<u8>, Vec<u8>)> {
    let root = encode_directory(rows)?;
    if root.len() <= ROOT_LIMIT {
        return Ok((root, Vec::new()));
    }
    let mut leaf_size = (rows.len() / 3500).max(4096);
    loop {
        let mut leaves = Vec::new();
        let mut pointers = Vec::new();
        for chunk in rows.chunks(leaf_size) {
            let leaf = encode_directory(chunk)?;
            let len =
                u32::try_from(leaf.len()).map_err(|_| Error::too_large("a PMTiles leaf directory", leaf.len()))?;
            pointers.push((chunk[0].0, 0, leaves.len() as u64, len));
            leaves.extend(leaf);
        }
        let root = encode_directory(&pointers)?;
        if root.len() <= ROOT_LIMIT {
            return Ok((root, leaves));
        }
        leaf_size += leaf_size / 5;
    }
}

fn e7(degrees: f64) -> i32 {
    // Degrees are within ±180, so ×1e7 fits an i32.
    let v = (degrees * 1e7).round().clamp(f64::from(i32::MIN), f64::from(i32::MAX));
    #[expect(clippy::cast_possible_truncation, reason = "clamped to the i32 range")]
    let v = v as i32;
    v
}

/// Writes layer `layer` of the archive as a PMTiles v3 file at `out` (temporary name,
/// fsync, rename). Tiles are checked against their CRC32C on the way.
///
/// # Errors
/// Archive read errors (a damaged tile names itself), [`Error::File`] on write failure,
/// [`Error::Interrupted`] on cancel.
pub fn export_pmtiles<S: RangeSource>(
    reader: &Reader<S>,
    layer: u8,
    out: &Path,
    progress: &dyn Progress,
) -> Result<PmtilesSummary> {
    let meta = reader.metadata();
    let info = meta.layers.get(usize::from(layer)).ok_or_else(|| Error::NoSuchLayer { layer: layer.to_string() })?;
    // Entries of the layer in key order = PMTiles tile-id order.
    let mut entries: Vec<Entry> = Vec::new();
    reader.for_each_entry(|e| -> Result<()> {
        if layer_of(e.key) == layer {
            entries.push(*e);
        }
        Ok(())
    })?;
    let layout = Layout::of(&entries);
    let metadata = metadata_json(meta, info)?;
    let bounds = meta.georeference.as_ref().and_then(|g| g.lat_lon_bounds);
    progress.start("export", entries.len() as u64);
    write_file(
        out,
        &layout,
        &metadata,
        |layout, sections| header(layout, sections, info, bounds),
        |w| {
            for (e, fresh) in entries.iter().zip(&layout.first_use) {
                progress.check()?;
                if *fresh {
                    w.write_all(&reader.entry_payload(e)?).map_err(|e| Error::file(out, e))?;
                }
                progress.advance(1);
            }
            Ok(())
        },
    )
}

/// Writes `tiles` (PMTiles tile id and file bytes, in id order) as a PMTiles v3 file at
/// `out` (temporary name, fsync, rename): identical tiles stored once (and runs of them
/// addressed by one entry), `tile_type` as PMTiles numbers it (2 PNG, 4 WebP), uncompressed
/// tiles, `metadata` as its JSON metadata. What `export --to pmtiles --encoding` writes of
/// web tiles.
///
/// # Errors
/// [`Error::File`] on write failure.
pub fn write_pmtiles(
    out: &Path,
    tiles: &[(u64, Vec<u8>)],
    tile_type: u8,
    bounds: [f64; 4],
    metadata: &serde_json::Value,
) -> Result<PmtilesSummary> {
    let mut offsets: HashMap<&[u8], u64> = HashMap::new();
    let mut rows: Vec<Row> = Vec::new();
    let mut first_use = Vec::new();
    let mut data_len = 0u64;
    for (id, bytes) in tiles {
        let len = u32::try_from(bytes.len()).map_err(|_| Error::too_large("a PMTiles tile", bytes.len()))?;
        let fresh = !offsets.contains_key(bytes.as_slice());
        let offset = *offsets.entry(bytes.as_slice()).or_insert_with(|| {
            let o = data_len;
            data_len += u64::from(len);
            o
        });
        match rows.last_mut() {
            Some(last) if !fresh && last.2 == offset && last.0 + u64::from(last.1) == *id => last.1 += 1,
            _ => rows.push((*id, 1, offset, len)),
        }
        first_use.push(fresh);
    }
    let layout = Layout { rows, first_use, data_len, contents: offsets.len() as u64 };
    let metadata = gzip(&serde_json::to_vec(metadata).map_err(|e| Error::metadata(&e))?)?;
    write_file(
        out,
        &layout,
        &metadata,
        |layout, sections| header_of(layout, sections, (tile_type, 1), Some(bounds)),
        |w| {
            for ((_, bytes), fresh) in tiles.iter().zip(&layout.first_use) {
                if *fresh {
                    w.write_all(bytes).map_err(|e| Error::file(out, e))?;
                }
            }
            Ok(())
        },
    )
}

/// Writes a PMTiles file of `layout` at `out` (temporary name, fsync, rename): the header
/// `header` makes of the layout and its sections' lengths, the directories, `metadata`
/// (gzipped), then the tiles `blobs` writes, in the layout's order.
fn write_file(
    out: &Path,
    layout: &Layout,
    metadata: &[u8],
    header: impl FnOnce(&Layout, [u64; 3]) -> Vec<u8>,
    blobs: impl FnOnce(&mut dyn Write) -> Result<()>,
) -> Result<PmtilesSummary> {
    let (root, leaves) = directories(&layout.rows)?;
    let sections = [root.len(), metadata.len(), leaves.len()].map(|n| n as u64);
    let header = header(layout, sections);
    let folder = crate::publish::output_folder(out);
    let mut file = crate::publish::published(tempfile::Builder::new().prefix(".pmtiles.").suffix(".partial"))
        .tempfile_in(&folder)
        .map_err(|e| Error::file(&folder, e))?;
    let io = |e: std::io::Error| Error::file(out, e);
    {
        let mut w = std::io::BufWriter::with_capacity(1 << 20, file.as_file_mut());
        for part in [&header[..], &root, metadata, &leaves] {
            w.write_all(part).map_err(io)?;
        }
        blobs(&mut w)?;
        w.flush().map_err(io)?;
    }
    file.as_file().sync_all().map_err(io)?;
    file.persist(out).map_err(|e| Error::file(out, e.error))?;
    Ok(PmtilesSummary {
        addressed_tiles: layout.addressed(),
        tile_entries: layout.rows.len() as u64,
        tile_contents: layout.contents,
        file_len: HEADER_LEN + sections.iter().sum::<u64>() + layout.data_len,
    })
}

/// Where the layer's blobs go in the PMTiles file: without our checksum trailer, back to
/// back, each at its first use.
struct Layout {
    /// One directory row per entry.
    rows: Vec<Row>,
    /// Per entry: is its blob written here (else it repeats an earlier one)?
    first_use: Vec<bool>,
    /// Bytes of tile data.
    data_len: u64,
    /// Distinct blobs.
    contents: u64,
}

impl Layout {
    fn of(entries: &[Entry]) -> Self {
        let mut new_offset: HashMap<u64, u64> = HashMap::new();
        let mut data_len = 0u64;
        let mut rows: Vec<Row> = Vec::with_capacity(entries.len());
        let mut first_use = Vec::with_capacity(entries.len());
        for e in entries {
            let fresh = !new_offset.contains_key(&e.offset);
            let offset = *new_offset.entry(e.offset).or_insert_with(|| {
                let o = data_len;
                data_len += u64::from(e.length);
                o
            });
            first_use.push(fresh);
            rows.push((e.key / MAX_LAYERS as u64, e.run_length, offset, e.length));
        }
        Self { rows, first_use, data_len, contents: new_offset.len() as u64 }
    }

    fn addressed(&self) -> u64 {
        self.rows.iter().map(|r| u64::from(r.1)).sum()
    }
}

/// The PMTiles metadata: the usual fields plus ours (layer, terrain, georeference), gzipped.
fn metadata_json(meta: &Metadata, info: &Layer) -> Result<Vec<u8>> {
    let json = serde_json::json!({
        "name": meta.name,
        "description": meta.description,
        "type": "baselayer",
        "format": info.format.extension().replace("jpg", "jpeg"),
        "terrastream": { "layer": info, "terrain": meta.terrain, "georeference": meta.georeference },
    });
    gzip(&serde_json::to_vec(&json).map_err(|e| Error::metadata(&e))?)
}

/// The 127-byte PMTiles v3 header: sections (root, metadata, leaves) in that order after
/// it, then the data; zooms, bounds (the world's Web Mercator range without them), centre.
fn header(layout: &Layout, sections: [u64; 3], info: &Layer, bounds: Option<[f64; 4]>) -> Vec<u8> {
    let tile_type = match info.format {
        TileFormat::Png => 2,
        TileFormat::Jpeg => 3,
        TileFormat::Webp => 4,
        _ => 0,
    };
    // PMTiles has no name for gradient-coded samples: "unknown", and the layer in the
    // metadata (`terrastream.layer.compression`) says what they are.
    let tile_compression = match info.compression {
        PayloadCompression::None => 1,
        PayloadCompression::Zstd => 4,
        PayloadCompression::ZstdGradient => 0,
    };
    header_of(layout, sections, (tile_type, tile_compression), bounds)
}

/// The header of `layout` with sections of these lengths, tiles of PMTiles type and
/// compression `kind`.
fn header_of(layout: &Layout, [root, metadata, leaves]: [u64; 3], kind: (u8, u8), bounds: Option<[f64; 4]>) -> Vec<u8> {
    let bounds = bounds.unwrap_or([-180.0, -85.051_13, 180.0, 85.051_13]);
    let zooms = layout.rows.iter().map(|r| tile_id_to_zxy(r.0).0);
    let (min_zoom, max_zoom) = (zooms.clone().min().unwrap_or(0), zooms.max().unwrap_or(0));
    let root_offset = HEADER_LEN;
    let metadata_offset = root_offset + root;
    let leaves_offset = metadata_offset + metadata;
    let data_offset = leaves_offset + leaves;
    let mut h = Vec::with_capacity(127);
    h.extend_from_slice(b"PMTiles");
    h.push(3);
    for v in [
        root_offset,
        root,
        metadata_offset,
        metadata,
        leaves_offset,
        leaves,
        data_offset,
        layout.data_len,
        layout.addressed(),
        layout.rows.len() as u64,
        layout.contents,
    ] {
        h.extend_from_slice(&v.to_le_bytes());
    }
    h.extend_from_slice(&[1, 2, kind.1, kind.0, min_zoom, max_zoom]);
    for v in [bounds[0], bounds[1], bounds[2], bounds[3]] {
        h.extend_from_slice(&e7(v).to_le_bytes());
    }
    h.push(min_zoom);
    h.extend_from_slice(&e7((bounds[0] + bounds[2]) / 2.0).to_le_bytes());
    h.extend_from_slice(&e7((bounds[1] + bounds[3]) / 2.0).to_le_bytes());
    debug_assert_eq!(h.len(), 127);
    h
}
