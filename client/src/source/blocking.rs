//! Blocking access to async sources, for command-line tools (`info`, `verify`, `extract`
//! on a URL). Never used on a frame loop or inside an async runtime.

use bytes::Bytes;
use terrastream_format::{AsyncRangeSource, MmapSource, RangeSource, Result};

use super::http::HttpSource;

/// An async source driven by its own single-threaded runtime.
#[derive(Debug)]
pub struct BlockingSource<S> {
    inner: S,
    runtime: tokio::runtime::Runtime,
    len: u64,
}

impl<S: AsyncRangeSource> BlockingSource<S> {
    /// Wraps `inner`, learning its length (one request for HTTP).
    ///
    /// # Errors
    /// The source's error; [`crate::Error::Threads`] if its runtime cannot start.
    pub fn new(inner: S) -> crate::Result<Self> {
        let runtime =
            tokio::runtime::Builder::new_current_thread().enable_all().build().map_err(crate::Error::Threads)?;
        let len = runtime.block_on(inner.size())?;
        Ok(Self { inner, runtime, len })
    }

    /// The wrapped source.
    pub fn inner(&self) -> &S {
        &self.inner
    }
}

impl<S: AsyncRangeSource> RangeSource for BlockingSource<S> {
    fn len(&self) -> u64 {
        self.len
    }

    fn read_range(&self, offset: u64, len: u64) -> Result<Bytes> {
        self.runtime.block_on(self.inner.fetch(offset, len))
    }
}

/// A local file (memory-mapped) or an `http(s)://` URL.
#[derive(Debug)]
pub enum AnySource {
    /// A memory-mapped file.
    Mmap(MmapSource),
    /// A remote archive.
    Http(Box<BlockingSource<HttpSource>>),
}

impl RangeSource for AnySource {
    fn len(&self) -> u64 {
        match self {
            Self::Mmap(s) => s.len(),
            Self::Http(s) => s.len(),
        }
    }

    fn read_range(&self, offset: u64, len: u64) -> Result<Bytes> {
        match self {
            Self::Mmap(s) => s.read_range(offset, len),
            Self::Http(s) => s.read_range(offset, len),
        }
    }
}

/// Opens a path or an `http(s)://` URL.
///
/// # Errors
/// A file error naming the path that cannot be mapped; a URL that is not http(s) or
/// cannot be read.
pub fn open_source(location: &str) -> crate::Result<AnySource> {
    if super::is_http_url(location) {
        return Ok(AnySource::Http(Box::new(BlockingSource::new(HttpSource::new(location)?)?)));
    }
    Ok(MmapSource::open(location).map(AnySource::Mmap)?)
}
