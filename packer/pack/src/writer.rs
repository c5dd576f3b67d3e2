//! The streaming archive writer.
//!
//! Memory stays bounded whatever the archive size: tile blobs go straight to a temporary
//! data file, directory entries are spilled to a second temporary file as fixed-size
//! records, and only one batch of tiles (compressed in parallel), the dedup table (capped)
//! and the root directory (one entry per leaf) live in memory. `finish` builds the
//! directories, writes the final file under a temporary name in the destination folder,
//! fsyncs it and renames it into place: a crash or Ctrl-C never leaves a partial archive
//! under the final name.
//!
//! The data file is that temporary file: where the filesystem can insert a range at the
//! start of a file (Linux ext4 and XFS: `FALLOC_FL_INSERT_RANGE`, which shifts extents and
//! copies no byte), `finish` makes room for the header, metadata and directories before
//! the data and writes them there; elsewhere it copies the data after them into a new
//! file. Both give the same bytes.

use std::collections::HashMap;
use std::fs::File;
use std::io::{BufReader, BufWriter, Read, Seek, SeekFrom, Write};
use std::path::{Path, PathBuf};

use rayon::prelude::*;
use terrastream_format::{
    BOOTSTRAP_READ, Compression, Directory, Entry, ExtentBuilder, HEADER_LEN, Header, LeafPointer, MAX_LAYERS,
    Metadata, PayloadCompression, Section, TILE_TRAILER_LEN, TileKey, VERSION_MINOR, crc32c,
};

use crate::compress::{zstd_compress, zstd_compress_gradient};
use crate::error::{Error, Result};
use crate::publish::{
    Part, Syncer, WRITE_BACK_BYTES, insert_range, output_folder, partial_file, publish, put_in_place, temporary,
    write_parts,
};

/// Tunables of the writer. The defaults suit archives from kilobytes to terabytes.
#[derive(Clone, Debug)]
pub struct WriterOptions {
    /// zstd level for payloads of layers with `compression: zstd`.
    pub zstd_level: i32,
    /// zstd level for directories and metadata (small, read often: compress hard).
    pub directory_zstd_level: i32,
    /// Distinct contents remembered for dedup (~48 bytes each). Past it, new contents are
    /// still written but no longer deduplicated against.
    pub dedup_capacity: usize,
    /// Input bytes gathered before a batch is compressed in parallel.
    pub batch_bytes: usize,
    /// Tiles gathered before a batch is compressed in parallel.
    pub batch_tiles: usize,
    /// Entries per leaf directory to start with; doubled until the root fits the bootstrap.
    pub leaf_entries: usize,
    /// Bytes the header, metadata and root directory should fit in.
    pub bootstrap_target: u64,
    /// Leave room for in-place updates (FORMAT.md §7.1): a second bootstrap slot in the
    /// first 16 KiB (so the root's budget is half of it) and a second leaf-directory slot.
    /// Costs at most 32 KiB plus 4x the directories, and makes `Appender` possible;
    /// an archive that fits one bootstrap read whole is written without it.
    pub reserve: bool,
    /// Sync the archive to disk before renaming it into place. Off only for scratch
    /// archives that a crash may lose (an update's tiles before they are merged).
    pub durable: bool,
    /// The heights' vertical datum, recorded when the archive is finished: made over the
    /// footprint its tiles turned out to cover (a geoid's undulation there).
    pub vertical_datum: Option<DatumOver>,
}

/// Makes the record of a vertical datum over a footprint (west, south, east, north in
/// degrees, when known): see [`WriterOptions::vertical_datum`].
#[derive(Clone)]
pub struct DatumOver(pub std::sync::Arc<dyn Fn(Option<[f64; 4]>) -> terrastream_format::VerticalDatum + Send + Sync>);

impl std::fmt::Debug for DatumOver {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str("DatumOver")
    }
}

impl Default for WriterOptions {
    fn default() -> Self {
        Self {
            zstd_level: 3,
            directory_zstd_level: 19,
            dedup_capacity: 1 << 22,
            batch_bytes: 32 << 20,
            batch_tiles: 2048,
            leaf_entries: 4096,
            bootstrap_target: BOOTSTRAP_READ,
            reserve: true,
            durable: true,
            vertical_datum: None,
        }
    }
}

/// What [`Writer::finish`] wrote.
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct WriteSummary {
    /// Final path.
    pub path: PathBuf,
    /// Size of the archive.
    pub file_len: u64,
    /// Tiles addressed (runs expanded).
    pub addressed_tiles: u64,
    /// Directory entries.
    pub tile_entries: u64,
    /// Distinct blobs stored.
    pub tile_contents: u64,
    /// Bytes of the data section.
    pub data_bytes: u64,
    /// Bytes of the root and leaf directories.
    pub directory_bytes: u64,
    /// Bytes of the stored metadata.
    pub metadata_bytes: u64,
    /// Number of leaf directories.
    pub leaf_count: u64,
}

pub(crate) const SPILL_RECORD: usize = 24;

/// A tile compressed and hashed, ready to be appended.
struct Prepared {
    /// Its position in archive order.
    key: u64,
    tile: TileKey,
    /// The stored bytes.
    bytes: Vec<u8>,
    /// Their 128-bit hash (for deduplication).
    hash: u128,
}

struct Pending {
    key: u64,
    tile: TileKey,
    bytes: Vec<u8>,
    /// The layer's compression still to apply (`None` for stored bytes).
    compression: PayloadCompression,
}

/// Streams tiles into a new archive. Tiles must arrive in archive order
/// (see [`Writer::order_key`]); each batch is compressed on all cores.
pub struct Writer {
    path: PathBuf,
    folder: PathBuf,
    metadata: Metadata,
    options: WriterOptions,
    data: BufWriter<File>,
    /// The data file's name (deleted if the writer is dropped unfinished).
    data_path: tempfile::TempPath,
    data_len: u64,
    /// Bytes of data whose write to disk has been started.
    written_back: u64,
    /// Syncs the data written so far as the archive grows (durable archives).
    syncer: Option<Syncer>,
    /// Try to move the data into place without copying it (off: always copy; tests).
    insert_range: bool,
    spill: BufWriter<File>,
    spilled: u64,
    open: Option<(Entry, u128)>,
    dedup: HashMap<u128, (u64, u32)>,
    batch: Vec<Pending>,
    batch_bytes: usize,
    last_key: Option<u64>,
    addressed: u64,
    contents: u64,
    /// Where each layer's tiles are, recorded in the metadata at the end.
    extents: Vec<ExtentBuilder>,
}

impl std::fmt::Debug for Writer {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("Writer").field("path", &self.path).field("addressed", &self.addressed).finish_non_exhaustive()
    }
}

impl Writer {
    /// Starts an archive that will be published at `path` by [`Writer::finish`].
    /// Temporary files live next to it (same filesystem, so the final rename is atomic).
    ///
    /// # Errors
    /// [`Error::Format`] for invalid metadata, [`Error::File`] if the folder is not writable.
    pub fn create(path: impl AsRef<Path>, metadata: Metadata, options: WriterOptions) -> Result<Self> {
        metadata.validate()?;
        let path = path.as_ref().to_path_buf();
        let extents = vec![ExtentBuilder::default(); metadata.layers.len()];
        let folder = output_folder(&path);
        let temp = || tempfile::tempfile_in(&folder).map_err(|e| Error::file(&folder, e));
        let (data, data_path) = partial_file(&path, &folder)?.into_parts();
        Ok(Self {
            data: BufWriter::with_capacity(1 << 20, data),
            data_path,
            insert_range: true,
            written_back: 0,
            syncer: None,
            spill: BufWriter::with_capacity(1 << 16, temp()?),
            path,
            folder,
            metadata,
            options,
            data_len: 0,
            spilled: 0,
            open: None,
            dedup: HashMap::new(),
            batch: Vec::new(),
            batch_bytes: 0,
            last_key: None,
            addressed: 0,
            contents: 0,
            extents,
        })
    }

    /// The position of `tile` in archive order: sort tiles by it before adding them.
    ///
    /// # Errors
    /// [`Error::Format`] if the tile is outside its layer's grid.
    pub fn order_key(metadata: &Metadata, tile: TileKey) -> Result<u64> {
        Ok(metadata.directory_key(tile)?)
    }

    /// The metadata that will be written.
    pub fn metadata(&self) -> &Metadata {
        &self.metadata
    }

    /// Replaces the metadata (e.g. with statistics known only at the end). The layers' grids
    /// must not change: tiles already added were placed by them.
    ///
    /// # Errors
    /// [`Error::GridChanged`] if a layer's grid differs, a metadata error if invalid.
    pub fn set_metadata(&mut self, metadata: Metadata) -> Result<()> {
        metadata.validate()?;
        let grid = |l: &terrastream_format::Layer| (l.num_x_tiles, l.num_y_tiles, l.num_lods, l.compression);
        if metadata.layers.len() != self.metadata.layers.len() {
            return Err(Error::GridChanged {
                layer: format!("{} layers instead of {}", metadata.layers.len(), self.metadata.layers.len()),
            });
        }
        if let Some((a, _)) = metadata.layers.iter().zip(&self.metadata.layers).find(|(a, b)| grid(a) != grid(b)) {
            return Err(Error::GridChanged { layer: a.name.clone() });
        }
        self.metadata = metadata;
        Ok(())
    }

    /// Adds a tile's payload in its layer's format; the writer applies the layer's
    /// compression (`zstd`: zstd at the options' level; `zstd_gradient`: the payload must be
    /// a tile's u16 samples).
    ///
    /// # Errors
    /// [`Error::OutOfOrder`], [`Error::EmptyTile`] or [`Error::TooLarge`] for a tile out of
    /// order, empty or too large, [`Error::Format`] for one outside its layer's grid, I/O
    /// errors.
    pub fn add(&mut self, tile: TileKey, payload: Vec<u8>) -> Result<()> {
        let compression =
            self.metadata.layers.get(usize::from(tile.layer())).map_or_else(Default::default, |l| l.compression);
        self.push(tile, payload, compression)
    }

    /// Adds a tile's stored bytes exactly as given (already compressed if the layer says so).
    ///
    /// # Errors
    /// As [`Writer::add`].
    pub fn add_stored(&mut self, tile: TileKey, stored: Vec<u8>) -> Result<()> {
        self.push(tile, stored, PayloadCompression::None)
    }

    fn push(&mut self, tile: TileKey, bytes: Vec<u8>, compression: PayloadCompression) -> Result<()> {
        let key = Self::order_key(&self.metadata, tile)?;
        if self.last_key.is_some_and(|last| key <= last) {
            return Err(Error::OutOfOrder { tile });
        }
        if bytes.is_empty() {
            return Err(Error::EmptyTile { tile });
        }
        if u32::try_from(bytes.len()).is_err() {
            return Err(Error::too_large(format!("tile {tile}"), bytes.len()));
        }
        self.last_key = Some(key);
        if let Some(extent) = self.extents.get_mut(usize::from(tile.layer())) {
            extent.add(tile);
        }
        self.batch_bytes += bytes.len();
        self.batch.push(Pending { key, tile, bytes, compression });
        if self.batch_bytes >= self.options.batch_bytes || self.batch.len() >= self.options.batch_tiles {
            self.flush_batch()?;
        }
        Ok(())
    }

    fn flush_batch(&mut self) -> Result<()> {
        let level = self.options.zstd_level;
        let batch = std::mem::take(&mut self.batch);
        self.batch_bytes = 0;
        let prepared: Vec<Result<Prepared>> = batch
            .into_par_iter()
            .map(|p| {
                let bytes = match p.compression {
                    PayloadCompression::None => p.bytes,
                    PayloadCompression::Zstd => {
                        zstd_compress(&p.bytes, level).map_err(|error| Error::Compress { what: "a tile", error })?
                    }
                    PayloadCompression::ZstdGradient => {
                        let edge = self.metadata.layers[usize::from(p.tile.layer())].stored_edge();
                        zstd_compress_gradient(&p.bytes, edge).map_err(|e| {
                            Error::Format(terrastream_format::Error::InvalidTile {
                                what: format!("{}: zstd_gradient layer, payload {e}", p.tile),
                            })
                        })?
                    }
                };
                let hash = xxhash_rust::xxh3::xxh3_128(&bytes);
                Ok(Prepared { key: p.key, tile: p.tile, bytes, hash })
            })
            .collect();
        for item in prepared {
            let Prepared { key, tile, bytes, hash } = item?;
            self.append(key, tile, &bytes, hash)?;
        }
        Ok(())
    }

    fn append(&mut self, key: u64, tile: TileKey, bytes: &[u8], hash: u128) -> Result<()> {
        let length = u32::try_from(bytes.len()).map_err(|_| Error::too_large(format!("tile {tile}"), bytes.len()))?;
        self.addressed += 1;
        // Extend the open run: next tile of the same layer, same content.
        if let Some((open, open_hash)) = &mut self.open
            && *open_hash == hash
            && open.last_key().checked_add(MAX_LAYERS as u64) == Some(key)
            && open.run_length < u32::MAX
        {
            open.run_length += 1;
            return Ok(());
        }
        let offset = match self.dedup.get(&hash) {
            Some(&(offset, _)) => offset,
            None => {
                let offset = self.data_len;
                let temp = |e| temporary(&self.folder, e);
                self.data.write_all(bytes).map_err(temp)?;
                self.data.write_all(&crc32c(bytes).to_le_bytes()).map_err(temp)?;
                self.data_len += u64::from(length) + TILE_TRAILER_LEN;
                if self.options.durable && self.data_len >= self.written_back + WRITE_BACK_BYTES {
                    self.write_back().map_err(|e| temporary(&self.folder, e))?;
                }
                self.contents += 1;
                if self.dedup.len() < self.options.dedup_capacity {
                    self.dedup.insert(hash, (offset, length));
                }
                offset
            }
        };
        self.close_run()?;
        self.open = Some((Entry { key, run_length: 1, offset, length }, hash));
        Ok(())
    }

    /// Starts making the data written so far durable, without waiting: the sync at the
    /// end then finds little left to write, and the disk works while tiles are added.
    fn write_back(&mut self) -> std::io::Result<()> {
        self.data.flush()?;
        match &self.syncer {
            Some(syncer) => syncer.wake(),
            None => self.syncer = Some(Syncer::start(self.data.get_ref())?),
        }
        self.written_back = self.data_len;
        Ok(())
    }

    fn close_run(&mut self) -> Result<()> {
        if let Some((e, _)) = self.open.take() {
            let mut record = [0u8; SPILL_RECORD];
            record[0..8].copy_from_slice(&e.key.to_le_bytes());
            record[8..12].copy_from_slice(&e.run_length.to_le_bytes());
            record[12..20].copy_from_slice(&e.offset.to_le_bytes());
            record[20..24].copy_from_slice(&e.length.to_le_bytes());
            self.spill.write_all(&record).map_err(|e| temporary(&self.folder, e))?;
            self.spilled += 1;
        }
        Ok(())
    }

    /// Builds the directories, writes the archive and renames it into place.
    ///
    /// # Errors
    /// I/O errors; nothing is left under the final name on error.
    pub fn finish(mut self) -> Result<WriteSummary> {
        self.flush_batch()?;
        self.close_run()?;
        // Its last sync runs while the directories are built.
        let mut syncer = self.syncer.take();
        let temp = |e| temporary(&self.folder, e);
        let level = self.options.directory_zstd_level;
        record_extents(&mut self.metadata, &self.extents);
        if let Some(datum) = &self.options.vertical_datum {
            let lon_lat = self
                .metadata
                .layers
                .iter()
                .filter_map(|l| l.extent.as_ref()?.lon_lat)
                .reduce(|a, b| [a[0].min(b[0]), a[1].min(b[1]), a[2].max(b[2]), a[3].max(b[3])]);
            self.metadata.vertical_datum =
                (datum.0)(lon_lat.or(self.metadata.georeference.as_ref().and_then(|g| g.lat_lon_bounds)));
        }
        let metadata_bytes = zstd_compress(&self.metadata.to_json(), level)
            .map_err(|error| Error::Compress { what: "the metadata", error })?;
        let target = if self.options.reserve {
            self.options.bootstrap_target.min(HEADER_LEN as u64 + BOOTSTRAP_SLOT)
        } else {
            self.options.bootstrap_target
        };
        let budget = target.saturating_sub(HEADER_LEN as u64 + metadata_bytes.len() as u64);
        let mut spill = self.spill.into_inner().map_err(|e| temp(e.into_error()))?;
        let mut directories =
            build_directories(&mut spill, self.spilled, &self.options, budget, &self.folder).map_err(temp)?;
        let [metadata, root_dir, leaf_dirs, data] = layout(
            metadata_bytes.len() as u64,
            directories.root.len() as u64,
            directories.leaves_len,
            self.data_len,
            self.options.reserve,
        );
        let header = Header {
            version_major: self.metadata.format_major(),
            version_minor: VERSION_MINOR,
            metadata,
            root_dir,
            leaf_dirs,
            data,
            addressed_tiles: self.addressed,
            tile_entries: self.spilled,
            tile_contents: self.contents,
            metadata_crc: crc32c(&metadata_bytes),
            root_dir_crc: crc32c(&directories.root),
            metadata_compression: Compression::Zstd,
            directory_compression: Compression::Zstd,
        };
        let mut data_file = self.data.into_inner().map_err(|e| temporary(&self.folder, e.into_error()))?;
        if let Some(syncer) = syncer.as_mut() {
            syncer.stop().map_err(|e| Error::file(&self.path, e))?;
        }
        let header = header.encode();
        let front = [
            Part::Bytes(&header),
            Part::Bytes(&metadata_bytes),
            Part::Bytes(&directories.root),
            Part::Gap(leaf_dirs.offset - root_dir.offset - root_dir.len),
            Part::File(&mut directories.leaves, directories.leaves_len),
        ];
        let len = data.end().unwrap_or(u64::MAX);
        if self.insert_range && self.data_len > 0 && insert_range(&data_file, data.offset) {
            // The data now starts at its offset; the front goes before it.
            data_file.seek(SeekFrom::Start(0)).map_err(|e| Error::file(&self.path, e))?;
            write_parts(&self.path, &self.folder, &mut data_file, front)?;
            put_in_place(&self.path, &self.folder, (&data_file, self.data_path), len, self.options.durable)?;
        } else {
            let data_part =
                [Part::Gap(data.offset - leaf_dirs.offset - leaf_dirs.len), Part::File(&mut data_file, self.data_len)];
            publish(&self.path, &self.folder, front.into_iter().chain(data_part), len, self.options.durable)?;
        }
        Ok(WriteSummary {
            path: self.path,
            file_len: data.end().unwrap_or(u64::MAX),
            addressed_tiles: self.addressed,
            tile_entries: self.spilled,
            tile_contents: self.contents,
            data_bytes: self.data_len,
            directory_bytes: root_dir.len + leaf_dirs.len,
            metadata_bytes: metadata.len,
            leaf_count: directories.leaf_count,
        })
    }
}

/// Writes into every layer of `metadata` where its tiles are (FORMAT.md §3.7), from the
/// tiles counted in `extents` (one per layer).
pub fn record_extents(metadata: &mut Metadata, extents: &[ExtentBuilder]) {
    let georeference = metadata.georeference.clone();
    for (layer, builder) in metadata.layers.iter_mut().zip(extents) {
        layer.extent = builder.record(layer, georeference.as_ref());
    }
}

/// Bytes of one bootstrap slot (metadata and root) in an archive with room for updates:
/// two fit in the first [`BOOTSTRAP_READ`] bytes after the header.
pub const BOOTSTRAP_SLOT: u64 = (BOOTSTRAP_READ - HEADER_LEN as u64) / 2;

/// Alignment of the data section in an archive with room for updates (a filesystem
/// block: copies of the archive can share the data's blocks).
const DATA_ALIGN: u64 = 4096;

/// The leaf-directory area of an archive with room for updates whose directories (root
/// and leaves) take `len` bytes: room for its leaves, and for the next version's three
/// times as large, plus 16 KiB (an update's blobs, appended out of key order, cost bytes
/// of offset: a 1 % update of a 5 m DEM took its leaves from 13.7 to 22.3 KiB; and a
/// root-only directory may move into leaves). Directories are a few bytes per tile, so
/// this is a small part of any archive worth updating.
pub(crate) fn leaf_area(len: u64) -> u64 {
    len.saturating_mul(4) + 16 * 1024
}

/// Where the sections go: back to back, or with `reserve` (a bootstrap that fits its slot,
/// and an archive larger than one bootstrap read) the layout of FORMAT.md §7.1: metadata and root in the first slot, the leaves at
/// [`BOOTSTRAP_READ`] in an area of [`leaf_area`] of the directories, the data after it,
/// block-aligned.
fn layout(metadata: u64, root: u64, leaves: u64, data: u64, reserve: bool) -> [Section; 4] {
    let metadata = Section { offset: HEADER_LEN as u64, len: metadata };
    let root = Section { offset: metadata.offset + metadata.len, len: root };
    let fits = root.offset + root.len <= HEADER_LEN as u64 + BOOTSTRAP_SLOT;
    // An archive that one bootstrap read holds whole stays so: cheaper to rewrite than to
    // read twice.
    let whole = root.offset + root.len + leaves + data <= BOOTSTRAP_READ;
    let (leaves, data_offset) = if reserve && fits && !whole {
        let leaves = Section { offset: BOOTSTRAP_READ, len: leaves };
        (leaves, (BOOTSTRAP_READ + leaf_area(root.len + leaves.len)).div_ceil(DATA_ALIGN) * DATA_ALIGN)
    } else {
        let leaves = Section { offset: root.offset + root.len, len: leaves };
        (leaves, leaves.offset + leaves.len)
    };
    [metadata, root, leaves, Section { offset: data_offset, len: data }]
}

/// The root directory and the leaves of an archive being finished.
pub(crate) struct Directories {
    /// The root, compressed.
    pub(crate) root: Vec<u8>,
    /// The leaves, compressed and concatenated, at the start of a temporary file.
    pub(crate) leaves: File,
    pub(crate) leaves_len: u64,
    pub(crate) leaf_count: u64,
}

/// Reads the `count` spilled entries back and builds the directories: every entry in the
/// root when it fits the bootstrap `budget` (a cold tile then costs 2 reads), else leaves
/// of `leaf_entries` entries, doubled until the root of leaf pointers fits.
pub(crate) fn build_directories(
    spill: &mut File,
    count: u64,
    options: &WriterOptions,
    budget: u64,
    folder: &Path,
) -> std::io::Result<Directories> {
    let level = options.directory_zstd_level;
    let mut leaves = tempfile::tempfile_in(folder)?;
    // Every entry costs at least one compressed byte: only then can the root hold them all.
    if count <= budget.max(options.leaf_entries as u64) {
        spill.seek(SeekFrom::Start(0))?;
        let entries = read_entries(&mut BufReader::new(&mut *spill), count)?;
        let root = zstd_compress(&Directory::Tiles(entries).encode_raw(), level)?;
        if root.len() as u64 <= budget || count <= 1 {
            return Ok(Directories { root, leaves, leaves_len: 0, leaf_count: 0 });
        }
    }
    let mut leaf_entries = options.leaf_entries.max(1);
    loop {
        spill.seek(SeekFrom::Start(0))?;
        leaves.set_len(0)?;
        leaves.seek(SeekFrom::Start(0))?;
        let pointers = write_leaves(spill, count, leaf_entries, level, &mut leaves)?;
        let root = zstd_compress(&Directory::Leaves(pointers.clone()).encode_raw(), level)?;
        if root.len() as u64 <= budget || pointers.len() <= 1 {
            let leaves_len = pointers.last().map_or(0, |p| p.offset + u64::from(p.length));
            return Ok(Directories { root, leaves, leaves_len, leaf_count: pointers.len() as u64 });
        }
        leaf_entries *= 2;
    }
}

fn read_entries(reader: &mut impl Read, count: u64) -> std::io::Result<Vec<Entry>> {
    let mut entries = Vec::new();
    let mut record = [0u8; SPILL_RECORD];
    for _ in 0..count {
        reader.read_exact(&mut record)?;
        let u64_at = |at: usize| {
            let mut b = [0u8; 8];
            b.copy_from_slice(&record[at..at + 8]);
            u64::from_le_bytes(b)
        };
        let u32_at = |at: usize| u32::from_le_bytes([record[at], record[at + 1], record[at + 2], record[at + 3]]);
        entries.push(Entry { key: u64_at(0), run_length: u32_at(8), offset: u64_at(12), length: u32_at(20) });
    }
    Ok(entries)
}

/// Streams the spilled entries into leaves of `per_leaf` entries; returns their pointers.
fn write_leaves(
    spill: &mut File,
    count: u64,
    per_leaf: usize,
    level: i32,
    out: &mut File,
) -> std::io::Result<Vec<LeafPointer>> {
    let mut reader = BufReader::with_capacity(1 << 16, spill);
    let mut out = BufWriter::new(out);
    let mut pointers = Vec::new();
    let mut offset = 0u64;
    let mut remaining = count;
    while remaining > 0 {
        let n = remaining.min(per_leaf as u64);
        remaining -= n;
        let entries = read_entries(&mut reader, n)?;
        let first_key = entries.first().map_or(0, |e| e.key);
        let stored = zstd_compress(&Directory::Tiles(entries).encode_raw(), level)?;
        let length = u32::try_from(stored.len()).map_err(|_| std::io::Error::other("a leaf directory over 4 GiB"))?;
        out.write_all(&stored)?;
        pointers.push(LeafPointer { first_key, offset, length, crc: crc32c(&stored) });
        offset += u64::from(length);
    }
    out.flush()?;
    Ok(pointers)
}

#[cfg(test)]
mod tests {
    #![allow(clippy::unwrap_used, clippy::cast_possible_truncation)]

    use terrastream_format::{Layer, LayerKind, Metadata, PayloadCompression, TileFormat, TileKey};

    use super::{Writer, WriterOptions};

    /// A 40 x 40 pyramid of tiles of varied lengths (leaves, several batches, 8 MiB of data
    /// so that it is synced on the way, by the syncer's thread), written with the data
    /// moved into place and with it copied.
    fn archive(dir: &std::path::Path, name: &str, insert_range: bool) -> Vec<u8> {
        let layer = Layer {
            name: "texture".into(),
            kind: LayerKind::Texture,
            format: TileFormat::Png,
            compression: PayloadCompression::None,
            tile_resolution: 256,
            border: 0,
            num_x_tiles: 40,
            num_y_tiles: 40,
            num_lods: 6,
            tile_world_size: 100.0,
            elevation: None,
            extent: None,
        };
        let metadata = Metadata::new("t", vec![layer.clone()]);
        let mut tiles: Vec<(u64, TileKey)> = (0..6u8)
            .flat_map(|lod| layer.tiles_at(0, lod).collect::<Vec<_>>())
            .map(|t| (Writer::order_key(&metadata, t).unwrap(), t))
            .collect();
        tiles.sort_unstable();
        let path = dir.join(name);
        let mut writer = Writer::create(&path, metadata, WriterOptions::default()).unwrap();
        writer.insert_range = insert_range;
        for (k, (_, tile)) in tiles.into_iter().enumerate() {
            let len = (k * 7919) % 9000 + 10;
            let payload: Vec<u8> = (0..len).map(|i| (i * 31 + k) as u8).collect();
            writer.add(tile, payload).unwrap();
        }
        writer.finish().unwrap();
        std::fs::read(path).unwrap()
    }

    #[test]
    fn moving_the_data_into_place_writes_the_bytes_a_copy_does() {
        let dir = tempfile::tempdir().unwrap();
        let (moved, copied) = (archive(dir.path(), "a.tspack", true), archive(dir.path(), "b.tspack", false));
        assert!(moved.len() > 8 << 20, "{} bytes", moved.len());
        assert!(moved == copied, "the archives differ");
        // Nothing but the two archives is left in the folder.
        let mut names: Vec<_> = std::fs::read_dir(dir.path()).unwrap().map(|e| e.unwrap().file_name()).collect();
        names.sort();
        assert_eq!(names, ["a.tspack", "b.tspack"]);
        let reader = terrastream_format::Reader::open_mmap(dir.path().join("a.tspack")).unwrap();
        terrastream_format::verify(&reader, |_| {}).unwrap();
    }
}
