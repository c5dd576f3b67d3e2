//! Byte-range backends. A reader needs nothing but "give me bytes [offset, offset+len)".

use std::future::Future;

use bytes::Bytes;

use crate::error::{Error, Result};

/// `Send` on native targets, nothing on wasm32 (browser futures are not `Send`).
#[cfg(not(target_arch = "wasm32"))]
pub trait MaybeSend: Send {}
#[cfg(not(target_arch = "wasm32"))]
impl<T: Send + ?Sized> MaybeSend for T {}
/// `Send` on native targets, nothing on wasm32 (browser futures are not `Send`).
#[cfg(target_arch = "wasm32")]
pub trait MaybeSend {}
#[cfg(target_arch = "wasm32")]
impl<T: ?Sized> MaybeSend for T {}

/// `Sync` on native targets, nothing on wasm32.
#[cfg(not(target_arch = "wasm32"))]
pub trait MaybeSync: Sync {}
#[cfg(not(target_arch = "wasm32"))]
impl<T: Sync + ?Sized> MaybeSync for T {}
/// `Sync` on native targets, nothing on wasm32.
#[cfg(target_arch = "wasm32")]
pub trait MaybeSync {}
#[cfg(target_arch = "wasm32")]
impl<T: ?Sized> MaybeSync for T {}

/// A blocking byte-range backend (memory, file, mmap).
pub trait RangeSource {
    /// Total length of the archive in bytes.
    fn len(&self) -> u64;

    /// True for an empty source.
    fn is_empty(&self) -> bool {
        self.len() == 0
    }

    /// Exactly the bytes `[offset, offset + len)`.
    ///
    /// # Errors
    /// [`Error::OutOfBounds`] past the end, [`Error::Source`] on I/O failure.
    fn read_range(&self, offset: u64, len: u64) -> Result<Bytes>;
}

/// A non-blocking byte-range backend (HTTP, browser fetch, or any [`RangeSource`]).
pub trait AsyncRangeSource: MaybeSend + MaybeSync {
    /// Total length of the archive in bytes (may cost a request the first time).
    fn size(&self) -> impl Future<Output = Result<u64>> + MaybeSend;

    /// Exactly the bytes `[offset, offset + len)`.
    fn fetch(&self, offset: u64, len: u64) -> impl Future<Output = Result<Bytes>> + MaybeSend;

    /// Forgets what the source remembers of the archive's identity (length, ETag, cached
    /// bytes) after [`crate::Error::Changed`], so that the next read opens the new version.
    fn forget(&self) {}
}

/// Checks `[offset, offset + len)` against `total` and returns it as `usize` bounds.
pub(crate) fn checked_range(offset: u64, len: u64, total: u64) -> Result<(usize, usize)> {
    let out_of_bounds = || Error::OutOfBounds { what: "read".into(), offset, len, limit_name: "archive", limit: total };
    let end = offset.checked_add(len).filter(|&e| e <= total).ok_or_else(out_of_bounds)?;
    let start = usize::try_from(offset).map_err(|_| out_of_bounds())?;
    let end = usize::try_from(end).map_err(|_| out_of_bounds())?;
    Ok((start, end))
}

/// An archive held in memory (tests, archives handed in by a host application, wasm).
#[derive(Clone, Debug)]
pub struct MemorySource {
    bytes: Bytes,
}

impl MemorySource {
    /// Wraps the whole archive.
    pub fn new(bytes: impl Into<Bytes>) -> Self {
        Self { bytes: bytes.into() }
    }
}

impl RangeSource for MemorySource {
    fn len(&self) -> u64 {
        self.bytes.len() as u64
    }

    fn read_range(&self, offset: u64, len: u64) -> Result<Bytes> {
        let (start, end) = checked_range(offset, len, RangeSource::len(self))?;
        Ok(self.bytes.slice(start..end))
    }
}

impl<T: RangeSource + Sync + Send> AsyncRangeSource for T {
    fn size(&self) -> impl Future<Output = Result<u64>> + MaybeSend {
        std::future::ready(Ok(RangeSource::len(self)))
    }

    fn fetch(&self, offset: u64, len: u64) -> impl Future<Output = Result<Bytes>> + MaybeSend {
        std::future::ready(RangeSource::read_range(self, offset, len))
    }
}

#[cfg(not(target_arch = "wasm32"))]
mod native {
    use std::fs::File;
    use std::path::{Path, PathBuf};

    use bytes::Bytes;

    use super::{RangeSource, checked_range};
    use crate::error::{Error, Result};

    /// Positioned reads on an open file: one `pread` per range, no shared cursor.
    #[derive(Debug)]
    pub struct FileSource {
        file: File,
        len: u64,
        path: PathBuf,
    }

    impl FileSource {
        /// Opens `path` for reading.
        ///
        /// # Errors
        /// [`Error::File`] if it cannot be opened.
        pub fn open(path: impl AsRef<Path>) -> Result<Self> {
            let path = path.as_ref().to_path_buf();
            let file = File::open(&path).map_err(|e| Error::file(&path, e))?;
            let len = file.metadata().map_err(|e| Error::file(&path, e))?.len();
            Ok(Self { file, len, path })
        }
    }

    impl RangeSource for FileSource {
        fn len(&self) -> u64 {
            self.len
        }

        fn read_range(&self, offset: u64, len: u64) -> Result<Bytes> {
            let (start, end) = checked_range(offset, len, self.len)?;
            let mut buf = vec![0u8; end - start];
            read_exact_at(&self.file, &mut buf, offset).map_err(|e| Error::Source {
                offset,
                len,
                reason: format!("{}: {e}", self.path.display()),
            })?;
            Ok(Bytes::from(buf))
        }
    }

    #[cfg(unix)]
    fn read_exact_at(file: &File, buf: &mut [u8], offset: u64) -> std::io::Result<()> {
        std::os::unix::fs::FileExt::read_exact_at(file, buf, offset)
    }

    #[cfg(windows)]
    fn read_exact_at(file: &File, mut buf: &mut [u8], mut offset: u64) -> std::io::Result<()> {
        while !buf.is_empty() {
            match std::os::windows::fs::FileExt::seek_read(file, buf, offset)? {
                0 => return Err(std::io::ErrorKind::UnexpectedEof.into()),
                n => {
                    buf = &mut buf[n..];
                    offset += n as u64;
                }
            }
        }
        Ok(())
    }

    /// A memory-mapped archive: ranges are zero-copy slices of the mapping.
    #[derive(Clone, Debug)]
    pub struct MmapSource {
        bytes: Bytes,
        /// The file mapped (kept open: a server can `sendfile` from it what the mapping
        /// shows, the same inode even after the path was replaced).
        file: Option<std::sync::Arc<File>>,
    }

    impl MmapSource {
        /// Maps `path` read-only.
        ///
        /// # Errors
        /// [`Error::File`] if it cannot be opened or mapped.
        pub fn open(path: impl AsRef<Path>) -> Result<Self> {
            let path = path.as_ref();
            let file = File::open(path).map_err(|e| Error::file(path, e))?;
            if file.metadata().map_err(|e| Error::file(path, e))?.len() == 0 {
                // Mapping an empty file fails on some systems; an empty archive is just invalid.
                return Ok(Self { bytes: Bytes::new(), file: None });
            }
            #[expect(
                unsafe_code,
                reason = "memory-mapping a file (with the tiler's prefetch and its call into AVX2 code: all the unsafe code)"
            )]
            // SAFETY: archives are immutable once written: the writer publishes a new archive by
            // atomic rename and never modifies a file in place, so the mapped pages do not change
            // under us. A file truncated by a third party would raise SIGBUS; that is the
            // documented contract of serving archives by mmap (FORMAT.md §7).
            let map = unsafe { memmap2::Mmap::map(&file) }.map_err(|e| Error::file(path, e))?;
            Ok(Self { bytes: Bytes::from_owner(map), file: Some(std::sync::Arc::new(file)) })
        }

        /// The file the mapping is of (none for an empty file, which is not mapped).
        pub fn file(&self) -> Option<&std::sync::Arc<File>> {
            self.file.as_ref()
        }

        /// The whole mapping.
        pub fn bytes(&self) -> &Bytes {
            &self.bytes
        }
    }

    impl RangeSource for MmapSource {
        fn len(&self) -> u64 {
            self.bytes.len() as u64
        }

        fn read_range(&self, offset: u64, len: u64) -> Result<Bytes> {
            let (start, end) = checked_range(offset, len, RangeSource::len(self))?;
            Ok(self.bytes.slice(start..end))
        }
    }
}

#[cfg(not(target_arch = "wasm32"))]
pub use native::{FileSource, MmapSource};

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn memory_source_checks_bounds() {
        let s = MemorySource::new(vec![1u8, 2, 3, 4]);
        assert_eq!(&s.read_range(1, 2).unwrap()[..], &[2, 3]);
        assert!(s.read_range(3, 2).is_err());
        assert!(s.read_range(u64::MAX, 2).is_err());
        assert_eq!(s.read_range(4, 0).unwrap().len(), 0);
    }

    #[test]
    fn file_and_mmap_sources_agree() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("f");
        std::fs::write(&path, b"hello archive").unwrap();
        let f = FileSource::open(&path).unwrap();
        let m = MmapSource::open(&path).unwrap();
        assert_eq!(f.read_range(6, 7).unwrap(), m.read_range(6, 7).unwrap());
        assert!(f.read_range(10, 7).is_err());
        assert!(m.read_range(10, 7).is_err());
    }
}
