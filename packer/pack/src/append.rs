//! In-place updates (FORMAT.md §7.1): an archive written with room for them takes new
//! tiles without being copied.
//!
//! Nothing the current header points at is ever overwritten. New blobs go after the data
//! section; the new leaf directories into the free part of the leaf area, the new metadata
//! and root into the free bootstrap slot; each of those is synced before the 128-byte
//! header is rewritten, the one write that switches readers to the new version. A crash
//! or an error before it leaves the archive as it was, the bytes appended lying unused
//! after the data section (never cut off: a reader that mapped the longer file would
//! fault; the next update writes over them). A reader that opened the archive before
//! keeps reading the old version's bytes, which stay in place until the update after
//! next reuses its slots.

use std::collections::{HashMap, HashSet};
use std::fs::File;
use std::io::{BufWriter, Read, Seek, SeekFrom, Write};
use std::os::unix::fs::FileExt;
use std::path::{Path, PathBuf};

use terrastream_format::{
    BOOTSTRAP_READ, Compression, Entry, ExtentBuilder, HEADER_LEN, Header, MAX_LAYERS, Metadata, Section,
    TILE_TRAILER_LEN, TileKey, VERSION_MINOR, crc32c,
};

use crate::compress::zstd_compress;
use crate::error::{Error, Result};
use crate::publish::output_folder;
use crate::writer::{Directories, SPILL_RECORD, WriteSummary, WriterOptions, build_directories, record_extents};

/// Appends a new version of an archive's tiles to it, in place.
///
/// Give every tile of the new version in archive order ([`crate::Writer::order_key`]):
/// [`Appender::keep`] for one whose blob the archive already holds, [`Appender::add`]
/// for new bytes; tiles not given are gone from the new version. [`Appender::finish`]
/// publishes it; dropping the appender before leaves the archive's version as it was.
pub struct Appender {
    path: PathBuf,
    file: File,
    header: Header,
    options: WriterOptions,
    /// New blobs, buffered; `None` once dropped.
    blobs: Option<BufWriter<File>>,
    /// Offset in the data section of the next new blob.
    data_len: u64,
    spill: BufWriter<File>,
    spilled: u64,
    open: Option<Entry>,
    dedup: HashMap<u128, u64>,
    kept: HashSet<u64>,
    added: u64,
    addressed: u64,
    last_key: Option<u64>,
    /// Where each layer's tiles are in the new version.
    extents: Vec<ExtentBuilder>,
}

impl std::fmt::Debug for Appender {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("Appender").field("path", &self.path).field("addressed", &self.addressed).finish_non_exhaustive()
    }
}

impl Appender {
    /// Opens `path` for an in-place update, locking it against other updates.
    ///
    /// # Errors
    /// [`Error::NoRoom`] for an archive written without room for updates (rewrite it
    /// instead); [`Error::File`] if it cannot be opened for writing or another update
    /// holds it; a format error for a damaged header.
    pub fn open(path: impl AsRef<Path>, options: WriterOptions) -> Result<Self> {
        let path = path.as_ref().to_path_buf();
        let io = |e| Error::file(&path, e);
        let file = File::options().read(true).write(true).open(&path).map_err(io)?;
        file.try_lock().map_err(|e| match e {
            std::fs::TryLockError::WouldBlock => {
                Error::file(&path, std::io::Error::other("another update of this archive is running"))
            }
            std::fs::TryLockError::Error(e) => Error::file(&path, e),
        })?;
        let len = file.metadata().map_err(io)?.len();
        let mut bytes = [0u8; HEADER_LEN];
        file.read_exact_at(&mut bytes, 0).map_err(io)?;
        let header = Header::decode(&bytes, len)?;
        let no_room = |why: &str| Error::NoRoom { path: path.clone(), why: why.to_owned() };
        if header.bootstrap_len() > BOOTSTRAP_READ
            || header.data.offset < BOOTSTRAP_READ
            || (header.leaf_dirs.len > 0 && header.leaf_dirs.offset < BOOTSTRAP_READ)
        {
            return Err(no_room("it was written without room for updates"));
        }
        let data_end = header.data.end().unwrap_or(u64::MAX);
        let mut blobs = BufWriter::with_capacity(1 << 20, file.try_clone().map_err(io)?);
        blobs.seek(SeekFrom::Start(data_end)).map_err(io)?;
        let folder = output_folder(&path);
        let spill =
            tempfile::tempfile_in(&folder).map_err(|e| Error::Temporary { folder: folder.clone(), error: e })?;
        Ok(Self {
            data_len: header.data.len,
            path,
            file,
            header,
            options,
            blobs: Some(blobs),
            spill: BufWriter::with_capacity(1 << 16, spill),
            spilled: 0,
            open: None,
            dedup: HashMap::new(),
            kept: HashSet::new(),
            added: 0,
            addressed: 0,
            last_key: None,
            extents: Vec::new(),
        })
    }

    /// The archive's header as opened (the version being updated).
    pub fn header(&self) -> &Header {
        &self.header
    }

    /// Keeps the tile with archive key `key` at a blob the archive holds: `offset` in the
    /// data section and `length` payload bytes, as a directory entry says.
    ///
    /// # Errors
    /// [`Error::OutOfOrder`], [`Error::Input`] for a blob outside the data section.
    pub fn keep(&mut self, tile: TileKey, key: u64, offset: u64, length: u32) -> Result<()> {
        let end = offset.checked_add(u64::from(length) + TILE_TRAILER_LEN);
        if length == 0 || end.is_none_or(|end| end > self.header.data.len) {
            return Err(Error::input(&self.path, format!("{tile}: no blob at {offset} (+{length}) to keep")));
        }
        self.kept.insert(offset);
        self.entry(tile, key, offset, length)
    }

    /// Adds the tile with archive key `key` with new stored bytes (compressed as its layer
    /// says), appended after the data section unless an added tile had the same bytes.
    ///
    /// # Errors
    /// [`Error::OutOfOrder`], an empty or oversized tile, I/O errors.
    pub fn add(&mut self, tile: TileKey, key: u64, stored: &[u8]) -> Result<()> {
        let length = u32::try_from(stored.len()).map_err(|_| Error::too_large(format!("tile {tile}"), stored.len()))?;
        if length == 0 {
            return Err(Error::EmptyTile { tile });
        }
        let hash = xxhash_rust::xxh3::xxh3_128(stored);
        let offset = match self.dedup.get(&hash) {
            Some(&offset) => offset,
            None => {
                let offset = self.data_len;
                let io = |e| Error::file(&self.path, e);
                let blobs = self.blobs.as_mut().ok_or_else(|| io(std::io::Error::other("finished")))?;
                blobs.write_all(stored).map_err(io)?;
                blobs.write_all(&crc32c(stored).to_le_bytes()).map_err(io)?;
                self.data_len += u64::from(length) + TILE_TRAILER_LEN;
                self.added += 1;
                self.dedup.insert(hash, offset);
                offset
            }
        };
        self.entry(tile, key, offset, length)
    }

    fn entry(&mut self, tile: TileKey, key: u64, offset: u64, length: u32) -> Result<()> {
        if self.last_key.is_some_and(|last| key <= last) {
            return Err(Error::OutOfOrder { tile });
        }
        self.last_key = Some(key);
        let layer = usize::from(tile.layer());
        if self.extents.len() <= layer {
            self.extents.resize_with(layer + 1, ExtentBuilder::default);
        }
        self.extents[layer].add(tile);
        self.addressed += 1;
        if let Some(open) = &mut self.open
            && open.offset == offset
            && open.length == length
            && open.last_key().checked_add(MAX_LAYERS as u64) == Some(key)
            && open.run_length < u32::MAX
        {
            open.run_length += 1;
            return Ok(());
        }
        self.close_run()?;
        self.open = Some(Entry { key, run_length: 1, offset, length });
        Ok(())
    }

    fn close_run(&mut self) -> Result<()> {
        if let Some(e) = self.open.take() {
            let mut record = [0u8; SPILL_RECORD];
            record[0..8].copy_from_slice(&e.key.to_le_bytes());
            record[8..12].copy_from_slice(&e.run_length.to_le_bytes());
            record[12..20].copy_from_slice(&e.offset.to_le_bytes());
            record[20..24].copy_from_slice(&e.length.to_le_bytes());
            let folder = output_folder(&self.path);
            self.spill.write_all(&record).map_err(|error| Error::Temporary { folder, error })?;
            self.spilled += 1;
        }
        Ok(())
    }

    /// Writes the new version's directories and `metadata` into the free slots and
    /// switches the header to them.
    ///
    /// # Errors
    /// [`Error::NoRoom`] when the new directories do not fit the free slots (the archive
    /// is left as it was: rewrite it instead); I/O errors.
    pub fn finish(mut self, metadata: &Metadata) -> Result<WriteSummary> {
        metadata.validate()?;
        // The new version's tiles say where its data is, within the box the metadata
        // gives (an update tiles onto the archive's own grid and data extent).
        let mut metadata = metadata.clone();
        self.extents.resize_with(metadata.layers.len(), ExtentBuilder::default);
        record_extents(&mut metadata, &self.extents);
        let metadata = &metadata;
        self.close_run()?;
        let path = self.path.clone();
        let io = |e| Error::file(&path, e);
        if let Some(blobs) = self.blobs.as_mut() {
            blobs.flush().map_err(io)?;
        }
        let folder = output_folder(&self.path);
        let temp = |error| Error::Temporary { folder: folder.clone(), error };
        let level = self.options.directory_zstd_level;
        let metadata_bytes = zstd_compress(&metadata.to_json(), level)
            .map_err(|error| Error::Compress { what: "the metadata", error })?;

        // The bootstrap slot: before the current metadata, or after the current root.
        let old = &self.header;
        let free = free_bootstrap(old);
        let target = self.options.bootstrap_target.saturating_sub(HEADER_LEN as u64);
        let budget = free.0.max(free.1).min(target).saturating_sub(metadata_bytes.len() as u64);
        self.spill.flush().map_err(temp)?;
        let mut spill = self.spill.get_ref().try_clone().map_err(temp)?;
        let mut directories =
            build_directories(&mut spill, self.spilled, &self.options, budget, &folder).map_err(temp)?;
        let slot = (metadata_bytes.len() + directories.root.len()) as u64;
        let metadata_offset = place(free, HEADER_LEN as u64, BOOTSTRAP_READ, slot).ok_or_else(|| {
            self.no_room(format!(
                "the new metadata and root directory take {slot} bytes; the free bootstrap slot has {}",
                free.0.max(free.1)
            ))
        })?;
        let new_metadata = Section { offset: metadata_offset, len: metadata_bytes.len() as u64 };
        let root_dir = Section { offset: new_metadata.offset + new_metadata.len, len: directories.root.len() as u64 };

        // The leaves: before the current ones, or after them, in the leaf area.
        let free = free_leaf_area(old);
        let leaves_len = directories.leaves_len;
        let leaves_offset = place(free, BOOTSTRAP_READ, old.data.offset, leaves_len).ok_or_else(|| {
            self.no_room(format!(
                "the new leaf directories take {leaves_len} bytes; the free part of the leaf area has {}",
                free.0.max(free.1)
            ))
        })?;
        let leaf_dirs = Section { offset: leaves_offset, len: leaves_len };
        let data = Section { offset: old.data.offset, len: self.data_len };
        let header = Header {
            version_major: metadata.format_major(),
            version_minor: VERSION_MINOR,
            metadata: new_metadata,
            root_dir,
            leaf_dirs,
            data,
            addressed_tiles: self.addressed,
            tile_entries: self.spilled,
            tile_contents: self.kept.len() as u64 + self.added,
            metadata_crc: crc32c(&metadata_bytes),
            root_dir_crc: crc32c(&directories.root),
            metadata_compression: Compression::Zstd,
            directory_compression: Compression::Zstd,
        };
        let file_len = self.write_version(&header, &metadata_bytes, &mut directories)?;
        Ok(WriteSummary {
            path: self.path.clone(),
            file_len,
            addressed_tiles: self.addressed,
            tile_entries: self.spilled,
            tile_contents: header.tile_contents,
            data_bytes: data.len,
            directory_bytes: root_dir.len + leaf_dirs.len,
            metadata_bytes: new_metadata.len,
            leaf_count: directories.leaf_count,
        })
    }

    fn no_room(&self, why: String) -> Error {
        Error::NoRoom { path: self.path.clone(), why }
    }

    /// Writes the new version where `header` says: everything but the header, synced,
    /// then the header, synced. Returns the file's length.
    fn write_version(&mut self, header: &Header, metadata_bytes: &[u8], directories: &mut Directories) -> Result<u64> {
        let path = self.path.clone();
        let io = |e| Error::file(&path, e);
        let folder = output_folder(&self.path);
        let temp = |error| Error::Temporary { folder: folder.clone(), error };
        let leaves_len = header.leaf_dirs.len;
        let mut out = self.file.try_clone().map_err(io)?;
        out.seek(SeekFrom::Start(header.leaf_dirs.offset)).map_err(io)?;
        directories.leaves.seek(SeekFrom::Start(0)).map_err(temp)?;
        let copied = std::io::copy(&mut Read::take(&mut directories.leaves, leaves_len), &mut out).map_err(io)?;
        if copied != leaves_len {
            return Err(temp(std::io::Error::new(std::io::ErrorKind::UnexpectedEof, "leaves shorter than written")));
        }
        self.file.write_all_at(metadata_bytes, header.metadata.offset).map_err(io)?;
        self.file.write_all_at(&directories.root, header.root_dir.offset).map_err(io)?;
        let end = header.data.end().unwrap_or(u64::MAX);
        self.file.sync_data().map_err(io)?;
        self.file.write_all_at(&header.encode(), 0).map_err(io)?;
        self.file.sync_data().map_err(io)?;
        // Bytes an unfinished update left after a longer data section stay.
        Ok(self.file.metadata().map_or(end, |m| m.len().max(end)))
    }
}

/// The free bytes of the bootstrap read before the current metadata and after the
/// current root directory.
fn free_bootstrap(old: &Header) -> (u64, u64) {
    (old.metadata.offset.saturating_sub(HEADER_LEN as u64), BOOTSTRAP_READ.saturating_sub(old.bootstrap_len()))
}

/// The free bytes of the leaf area (between the bootstrap read and the data) before and
/// after the current leaf directories.
fn free_leaf_area(old: &Header) -> (u64, u64) {
    let area = BOOTSTRAP_READ..old.data.offset;
    if old.leaf_dirs.len == 0 {
        (area.end - area.start, 0)
    } else {
        let end = old.leaf_dirs.end().unwrap_or(u64::MAX);
        (old.leaf_dirs.offset - area.start, area.end.saturating_sub(end))
    }
}

/// Where `len` bytes go in an area from `start` to `end` whose free bytes are `free`
/// (before and after what it holds now): at its start, else ending at its end; None when
/// neither has room.
fn place(free: (u64, u64), start: u64, end: u64, len: u64) -> Option<u64> {
    if len <= free.0 {
        Some(start)
    } else if len <= free.1 {
        Some(end - len)
    } else {
        None
    }
}

impl Drop for Appender {
    /// Not finished: blobs still buffered are dropped; those written and the free slots
    /// hold bytes nothing points at.
    fn drop(&mut self) {
        if let Some(blobs) = self.blobs.take() {
            let _ = blobs.into_parts();
        }
    }
}
