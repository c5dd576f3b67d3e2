//! The archives being served, and their hot reload.
//!
//! Each archive is memory-mapped once; requests take an `Arc` of the current version, so a
//! replaced file (atomic rename) is picked up by new requests while requests in flight
//! finish on the old mapping.

use std::collections::BTreeMap;
use std::path::{Path, PathBuf};
use std::sync::atomic::{AtomicU64, Ordering};
use std::sync::{Arc, RwLock};
use std::time::SystemTime;

use bytes::Bytes;
use terrastream_format::{MmapSource, Reader};

/// One archive as served.
#[derive(Debug)]
pub struct Served {
    /// URL name: the file name without `.tspack`.
    pub name: String,
    /// File it was mapped from.
    pub path: PathBuf,
    /// Reader over the mapping.
    pub reader: Reader<MmapSource>,
    /// Strong entity tag, quoted.
    pub etag: String,
    /// Modification time.
    pub modified: SystemTime,
    /// `ETag` header value, formatted once.
    pub etag_header: axum::http::HeaderValue,
    /// `Last-Modified` header value, formatted once.
    pub last_modified_header: axum::http::HeaderValue,
    identity: FileIdentity,
    /// Blobs whose checksum was verified: a hit skips the CRC of a tile served before.
    verified: Verified,
    /// The mapping, registered for `sendfile` while this version is served.
    _sendfile: Option<crate::sendfile::Registration>,
}

/// Slots of the verified-blob table (128 KiB per archive).
const VERIFIED_SLOTS: usize = 16 * 1024;
/// Slots a blob may take in the table: its bucket. Direct-mapped (one slot), a quarter of
/// the 4 902 distinct blobs of `scripts/bench-server.sh`'s archive shared a slot with
/// another and were checked again and again (3% of the server's time on random tiles);
/// with buckets of 4, under 1% of buckets overflow.
const VERIFIED_WAYS: usize = 4;

impl Served {
    /// The whole file, zero-copy.
    pub fn bytes(&self) -> &Bytes {
        self.reader.source().bytes()
    }

    /// A located tile's payload, zero-copy. Its CRC32C is checked the first time the blob
    /// is served (and again whenever another blob took its slot in the table since): the
    /// mapping is immutable (a changed file is a new `Served`), so a blob that checked out
    /// once stays good.
    ///
    /// # Errors
    /// As [`Reader::read`].
    pub fn tile_payload(&self, location: &terrastream_format::TileLocation) -> terrastream_format::Result<Bytes> {
        if self.verified.contains(location.offset) {
            return self.reader.read_unchecked(location);
        }
        let payload = self.reader.read(location)?;
        self.verified.insert(location.offset);
        Ok(payload)
    }

    /// Whether the blob at `offset` is in the verified table.
    pub fn is_verified(&self, offset: u64) -> bool {
        self.verified.contains(offset)
    }
}

/// Offsets of verified blobs: a 4-way set-associative table of offsets (+1; 0 is empty),
/// fixed in size, lock-free.
#[derive(Debug)]
struct Verified(Box<[AtomicU64]>);

impl Verified {
    fn new() -> Self {
        Self((0..VERIFIED_SLOTS).map(|_| AtomicU64::new(0)).collect())
    }

    fn contains(&self, offset: u64) -> bool {
        self.bucket(offset).0.iter().any(|s| s.load(Ordering::Relaxed) == offset + 1)
    }

    fn insert(&self, offset: u64) {
        let (bucket, victim) = self.bucket(offset);
        // An empty slot of the bucket, or else the blob's own choice among the four.
        let slot = bucket.iter().find(|s| s.load(Ordering::Relaxed) == 0).unwrap_or(&bucket[victim]);
        slot.store(offset + 1, Ordering::Relaxed);
    }

    /// The slots the blob at `offset` may take, and the one it replaces when all are taken.
    fn bucket(&self, offset: u64) -> (&[AtomicU64], usize) {
        // Fibonacci hashing: neighbouring blobs land far apart.
        let hash = offset.wrapping_mul(0x9E37_79B9_7F4A_7C15);
        let bucket = usize::try_from(hash >> 32).unwrap_or(0) % (VERIFIED_SLOTS / VERIFIED_WAYS);
        let victim = usize::try_from(hash >> 24).unwrap_or(0) % VERIFIED_WAYS;
        (&self.0[bucket * VERIFIED_WAYS..][..VERIFIED_WAYS], victim)
    }
}

/// What tells two versions of a file apart without reading it.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
struct FileIdentity {
    len: u64,
    modified_ns: u128,
    inode: u64,
}

fn identity(meta: &std::fs::Metadata) -> FileIdentity {
    #[cfg(unix)]
    let inode = std::os::unix::fs::MetadataExt::ino(meta);
    #[cfg(not(unix))]
    let inode = 0;
    let modified_ns =
        meta.modified().ok().and_then(|m| m.duration_since(SystemTime::UNIX_EPOCH).ok()).map_or(0, |d| d.as_nanos());
    FileIdentity { len: meta.len(), modified_ns, inode }
}

/// A manifest as served (FORMAT.md §9): its bytes as found, once they validated.
#[derive(Debug)]
pub struct ServedManifest {
    /// URL name: the file name without `.json`.
    pub name: String,
    /// File it was read from.
    pub path: PathBuf,
    /// The document as found.
    pub bytes: Bytes,
    /// It, parsed.
    pub manifest: terrastream_format::Manifest,
    /// Strong entity tag of the bytes, quoted.
    pub etag: String,
    identity: FileIdentity,
}

/// The served archives and manifests by name.
#[derive(Debug)]
pub struct Catalog {
    roots: Vec<PathBuf>,
    archives: RwLock<BTreeMap<String, Arc<Served>>>,
    manifests: RwLock<BTreeMap<String, Arc<ServedManifest>>>,
    leaf_cache: usize,
}

impl Catalog {
    /// A catalog of the given files and folders (scanned by [`Catalog::reload`]).
    pub fn new(roots: Vec<PathBuf>) -> Self {
        Self {
            roots,
            archives: RwLock::new(BTreeMap::new()),
            manifests: RwLock::new(BTreeMap::new()),
            leaf_cache: terrastream_format::DEFAULT_LEAF_CACHE,
        }
    }

    /// Keeps up to `leaves` decoded leaf directories per archive opened from now on.
    #[must_use]
    pub fn with_leaf_cache(mut self, leaves: usize) -> Self {
        self.leaf_cache = leaves;
        self
    }

    /// The current version of an archive.
    pub fn get(&self, name: &str) -> Option<Arc<Served>> {
        self.archives.read().unwrap_or_else(std::sync::PoisonError::into_inner).get(name).cloned()
    }

    /// The current version of a manifest.
    pub fn manifest(&self, name: &str) -> Option<Arc<ServedManifest>> {
        self.manifests.read().unwrap_or_else(std::sync::PoisonError::into_inner).get(name).cloned()
    }

    /// All manifests, by name.
    pub fn manifests(&self) -> Vec<Arc<ServedManifest>> {
        self.manifests.read().unwrap_or_else(std::sync::PoisonError::into_inner).values().cloned().collect()
    }

    /// All archives, by name.
    pub fn list(&self) -> Vec<Arc<Served>> {
        self.archives.read().unwrap_or_else(std::sync::PoisonError::into_inner).values().cloned().collect()
    }

    fn candidates(&self, extension: &str) -> Vec<PathBuf> {
        let mut out = Vec::new();
        for root in &self.roots {
            if root.is_dir() {
                match std::fs::read_dir(root) {
                    Ok(entries) => out.extend(
                        entries
                            .filter_map(Result::ok)
                            .map(|e| e.path())
                            .filter(|p| p.extension().is_some_and(|e| e == extension)),
                    ),
                    Err(err) => tracing::warn!("cannot list {}: {err}", root.display()),
                }
            } else if root.extension().is_some_and(|e| e == extension) {
                out.push(root.clone());
            }
        }
        out
    }

    /// Rescans: maps new and replaced archives, reads new and replaced manifests, forgets
    /// removed ones. A file that fails to open (or a manifest that does not validate) is
    /// logged and skipped (its previous version, if any, stays served). Returns how many
    /// archives and manifests changed.
    pub fn reload(&self) -> usize {
        self.reload_archives() + self.reload_manifests()
    }

    fn reload_manifests(&self) -> usize {
        rescan(
            &self.manifests,
            self.candidates("json"),
            ".json",
            |m| (m.identity, &m.path),
            |name, path, _, id| {
                let served = read_manifest(name, path, id)?;
                tracing::info!(manifest = %name, archives = served.manifest.archives.len(), "serving {}", path.display());
                Ok(served)
            },
        )
    }

    fn reload_archives(&self) -> usize {
        let leaf_cache = self.leaf_cache;
        rescan(
            &self.archives,
            self.candidates("tspack"),
            ".tspack",
            |a| (a.identity, &a.path),
            |name, path, meta, id| {
                let served = open(name, path, meta, id, leaf_cache)?;
                tracing::info!(archive = %name, etag = %served.etag, "serving {}", path.display());
                Ok(served)
            },
        )
    }
}

/// Rescans one kind of served file: `open`s new and replaced ones (regular files only:
/// a symlink could point anywhere on the machine), keeps unchanged ones, forgets removed
/// ones; a file that fails to open is logged and its previous version kept. Returns how
/// many changed.
fn rescan<T>(
    served: &RwLock<BTreeMap<String, Arc<T>>>,
    paths: Vec<PathBuf>,
    suffix: &str,
    version: impl Fn(&T) -> (FileIdentity, &PathBuf),
    open: impl Fn(&str, &Path, &std::fs::Metadata, FileIdentity) -> Result<T, terrastream_format::Error>,
) -> usize {
    let current = served.read().unwrap_or_else(std::sync::PoisonError::into_inner).clone();
    let mut next = BTreeMap::new();
    let mut changed = 0;
    for path in paths {
        let Some(name) = file_name(&path, suffix) else { continue };
        let meta = match std::fs::symlink_metadata(&path) {
            Ok(m) if m.file_type().is_file() => m,
            Ok(_) => {
                tracing::warn!("{}: not a regular file, not served", path.display());
                continue;
            }
            Err(err) => {
                tracing::warn!("{}: {err}", path.display());
                continue;
            }
        };
        let id = identity(&meta);
        if let Some(old) = current.get(&name).filter(|o| version(o) == (id, &path)) {
            next.insert(name, Arc::clone(old));
            continue;
        }
        match open(&name, &path, &meta, id) {
            Ok(fresh) => {
                next.insert(name, Arc::new(fresh));
                changed += 1;
            }
            Err(err) => {
                tracing::error!("{}: {err}", path.display());
                if let Some(old) = current.get(&name) {
                    next.insert(name, Arc::clone(old));
                }
            }
        }
    }
    changed += current.keys().filter(|k| !next.contains_key(*k)).count();
    *served.write().unwrap_or_else(std::sync::PoisonError::into_inner) = next;
    changed
}

/// The URL name of an archive file: its stem, restricted to a safe alphabet.
pub fn archive_name(path: &Path) -> Option<String> {
    file_name(path, ".tspack")
}

fn read_manifest(name: &str, path: &Path, id: FileIdentity) -> Result<ServedManifest, terrastream_format::Error> {
    let file = |error| terrastream_format::Error::File { path: path.to_path_buf(), error };
    let mut bytes = Vec::new();
    let reader = std::fs::File::open(path).map_err(file)?;
    std::io::Read::read_to_end(
        &mut std::io::Read::take(reader, terrastream_format::MAX_MANIFEST_BYTES + 1),
        &mut bytes,
    )
    .map_err(file)?;
    let manifest = terrastream_format::Manifest::from_json(&bytes)?;
    let etag = format!("\"{:016x}\"", xxhash_rust::xxh3::xxh3_64(&bytes));
    Ok(ServedManifest {
        name: name.to_owned(),
        path: path.to_path_buf(),
        bytes: bytes.into(),
        manifest,
        etag,
        identity: id,
    })
}

/// A file's URL name: its name without `suffix`, restricted to a safe alphabet.
fn file_name(path: &Path, suffix: &str) -> Option<String> {
    let stem = path.file_name()?.to_str()?.strip_suffix(suffix)?;
    let ok = !stem.is_empty()
        && stem.chars().all(|c| c.is_ascii_alphanumeric() || "-_.".contains(c))
        && !stem.starts_with('.');
    ok.then(|| stem.to_owned())
}

fn open(
    name: &str,
    path: &Path,
    meta: &std::fs::Metadata,
    id: FileIdentity,
    leaf_cache: usize,
) -> Result<Served, terrastream_format::Error> {
    let mut reader = Reader::new(MmapSource::open(path)?)?;
    reader.set_leaf_cache_capacity(leaf_cache);
    let registration =
        reader.source().file().and_then(|file| crate::sendfile::register(reader.source().bytes(), Arc::clone(file)));
    let mut tag = Vec::with_capacity(160);
    tag.extend_from_slice(&reader.source().bytes()[..terrastream_format::HEADER_LEN]);
    tag.extend_from_slice(&id.len.to_le_bytes());
    tag.extend_from_slice(&id.modified_ns.to_le_bytes());
    tag.extend_from_slice(&id.inode.to_le_bytes());
    let etag = format!("\"{:016x}\"", xxhash_rust::xxh3::xxh3_64(&tag));
    let modified = meta.modified().unwrap_or(SystemTime::UNIX_EPOCH);
    let value =
        |s: &str| axum::http::HeaderValue::from_str(s).unwrap_or_else(|_| axum::http::HeaderValue::from_static(""));
    Ok(Served {
        name: name.to_owned(),
        path: path.to_path_buf(),
        reader,
        etag_header: value(&etag),
        last_modified_header: value(&httpdate::fmt_http_date(modified)),
        etag,
        modified,
        identity: id,
        verified: Verified::new(),
        _sendfile: registration,
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Blobs that share a bucket all stay verified up to its four slots; a fifth replaces
    /// one of them, never more, and blobs of other buckets are untouched.
    #[test]
    fn verified_blobs_share_a_bucket_four_at_a_time() {
        let table = Verified::new();
        let first = |offset: u64| table.bucket(offset).0.as_ptr();
        let bucket = first(1000);
        let same: Vec<u64> = (1000..).step_by(8).filter(|&o| first(o) == bucket).take(5).collect();
        let other = (1000..).step_by(8).find(|&o| first(o) != bucket).unwrap();
        table.insert(other);
        for (i, &o) in same[..4].iter().enumerate() {
            assert!(!table.contains(o));
            table.insert(o);
            assert!(same[..=i].iter().all(|&o| table.contains(o)), "{i}");
        }
        table.insert(same[4]);
        assert!(table.contains(same[4]));
        assert_eq!(same[..4].iter().filter(|&&o| table.contains(o)).count(), 3);
        assert!(table.contains(other));
        // Offset 0 is a blob like any other (slots hold offset + 1).
        table.insert(0);
        assert!(table.contains(0));
    }
}
