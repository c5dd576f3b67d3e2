//! Where a [`super::streamer::Streamer`] gets its tiles: an archive behind any byte-range source
//! (mmap, HTTP Range, memory), our server's tile endpoint, or tiles handed in by the host
//! application.

use std::collections::HashMap;
use std::future::Future;
use std::pin::Pin;
use std::sync::atomic::{AtomicU64, Ordering::Relaxed};
use std::sync::{Arc, Mutex, PoisonError};

use bytes::Bytes;
use reqwest::StatusCode;
use terrastream_format::{AsyncRangeSource, AsyncReader, Manifest, MaybeSend, MaybeSync, Metadata, TileKey, protocol};

use crate::error::{Error, Result};
use crate::source::http::HttpSource;
use crate::source::is_http_url;

/// A boxed future, `Send` on native targets.
#[cfg(not(target_arch = "wasm32"))]
pub type BoxFuture<'a, T> = Pin<Box<dyn Future<Output = T> + Send + 'a>>;
/// A boxed future (browser futures are not `Send`).
#[cfg(target_arch = "wasm32")]
pub type BoxFuture<'a, T> = Pin<Box<dyn Future<Output = T> + 'a>>;

/// [`AsyncRangeSource`] made object-safe.
pub trait ErasedSource: MaybeSend + MaybeSync {
    /// See [`AsyncRangeSource::size`].
    fn size_boxed(&self) -> BoxFuture<'_, terrastream_format::Result<u64>>;
    /// See [`AsyncRangeSource::fetch`].
    fn fetch_boxed(&self, offset: u64, len: u64) -> BoxFuture<'_, terrastream_format::Result<Bytes>>;
    /// See [`AsyncRangeSource::forget`].
    fn forget_erased(&self);
}

impl<S: AsyncRangeSource> ErasedSource for S {
    fn size_boxed(&self) -> BoxFuture<'_, terrastream_format::Result<u64>> {
        Box::pin(self.size())
    }
    fn fetch_boxed(&self, offset: u64, len: u64) -> BoxFuture<'_, terrastream_format::Result<Bytes>> {
        Box::pin(self.fetch(offset, len))
    }
    fn forget_erased(&self) {
        self.forget();
    }
}

/// Any byte-range source behind one type.
#[derive(Clone)]
pub struct DynSource(Arc<dyn ErasedSource>);

impl std::fmt::Debug for DynSource {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str("DynSource")
    }
}

impl DynSource {
    /// Wraps a source.
    pub fn new(source: impl AsyncRangeSource + 'static) -> Self {
        Self(Arc::new(source))
    }
}

impl AsyncRangeSource for DynSource {
    fn size(&self) -> impl Future<Output = terrastream_format::Result<u64>> + MaybeSend {
        self.0.size_boxed()
    }
    fn fetch(&self, offset: u64, len: u64) -> impl Future<Output = terrastream_format::Result<Bytes>> + MaybeSend {
        self.0.fetch_boxed(offset, len)
    }
    fn forget(&self) {
        self.0.forget_erased();
    }
}

/// Our server's tile endpoint: `{base}/metadata` and `{base}/{layer}/{lod}/{x}/{y}`, one
/// request per tile (the server decodes zstd payloads; a missing tile is a 404). Every
/// response names the archive's ETag; a different one means the archive was replaced.
#[derive(Debug)]
pub struct EndpointSource {
    client: reqwest::Client,
    base: String,
    archive_etag: Mutex<Option<String>>,
    requests: AtomicU64,
}

impl EndpointSource {
    /// The archive served at `base` (e.g. `http://host:8080/alps`).
    ///
    /// # Errors
    /// [`Error::BadUrl`] for a URL that is not http(s), [`Error::HttpClient`] if the
    /// client cannot be built.
    pub fn new(base: &str) -> Result<Self> {
        if !is_http_url(base) {
            return Err(Error::BadUrl { url: base.to_owned(), reason: "only http and https URLs".into() });
        }
        let client = reqwest::Client::builder().build().map_err(|e| Error::HttpClient { reason: e.to_string() })?;
        Ok(Self {
            client,
            base: base.trim_end_matches('/').to_owned(),
            archive_etag: Mutex::new(None),
            requests: AtomicU64::new(0),
        })
    }

    /// Requests sent.
    pub fn requests(&self) -> u64 {
        self.requests.load(Relaxed)
    }

    async fn get(&self, path: &str) -> Result<Option<Bytes>> {
        let url = format!("{}/{path}", self.base);
        let fail = |reason: String| Error::Request { url: url.clone(), reason };
        self.requests.fetch_add(1, Relaxed);
        let response = self.client.get(&url).send().await.map_err(|e| fail(e.to_string()))?;
        let etag =
            response.headers().get(protocol::ARCHIVE_ETAG_HEADER).and_then(|v| v.to_str().ok()).map(str::to_owned);
        {
            let mut known = self.archive_etag.lock().unwrap_or_else(PoisonError::into_inner);
            match (&*known, etag) {
                (Some(old), Some(new)) if *old != new => {
                    return Err(Error::Changed { what: format!("{url}: archive ETag {old} -> {new}") });
                }
                (None, Some(new)) => *known = Some(new),
                _ => {}
            }
        }
        match response.status() {
            StatusCode::OK => response.bytes().await.map(Some).map_err(|e| fail(format!("body: {e}"))),
            StatusCode::NOT_FOUND if path != protocol::METADATA_PATH => Ok(None),
            status => Err(Error::Status { url, status: status.as_u16() }),
        }
    }

    /// The archive's metadata.
    ///
    /// # Errors
    /// Request errors; a metadata error for a bad document.
    pub async fn metadata(&self) -> Result<Metadata> {
        let bytes = self.get(protocol::METADATA_PATH).await?.unwrap_or_default();
        Ok(Metadata::from_json(&bytes)?)
    }

    /// One tile's payload (zstd already removed), `None` if the archive has no such tile.
    ///
    /// # Errors
    /// Request errors; [`Error::Changed`] when the archive was replaced.
    pub async fn tile(&self, key: TileKey) -> Result<Option<Bytes>> {
        self.get(&protocol::tile_path(key)).await
    }

    fn forget(&self) {
        *self.archive_etag.lock().unwrap_or_else(PoisonError::into_inner) = None;
    }
}

/// Tiles handed in by the host application (a simulator generating or receiving them):
/// the metadata up front, payloads as they become available. A tile not handed in yet
/// counts as missing; handing it in later makes the streamer look again.
#[derive(Debug)]
pub struct HostTiles {
    metadata: Metadata,
    tiles: Mutex<HashMap<TileKey, Bytes>>,
    version: AtomicU64,
}

impl HostTiles {
    /// An empty set of tiles for a terrain described by `metadata`.
    ///
    /// # Errors
    /// A metadata error if the metadata is invalid.
    pub fn new(metadata: Metadata) -> Result<Self> {
        metadata.validate()?;
        Ok(Self { metadata, tiles: Mutex::default(), version: AtomicU64::new(0) })
    }

    /// The metadata.
    pub fn metadata(&self) -> &Metadata {
        &self.metadata
    }

    /// Hands in a tile's payload, encoded as its layer says (format and compression).
    ///
    /// # Errors
    /// A tile error for a tile outside its layer's grid.
    pub fn insert(&self, key: TileKey, payload: Bytes) -> Result<()> {
        self.metadata.directory_key(key)?;
        self.tiles.lock().unwrap_or_else(PoisonError::into_inner).insert(key, payload);
        self.version.fetch_add(1, Relaxed);
        Ok(())
    }

    /// Takes a tile back.
    pub fn remove(&self, key: TileKey) {
        self.tiles.lock().unwrap_or_else(PoisonError::into_inner).remove(&key);
        self.version.fetch_add(1, Relaxed);
    }

    /// The tile's payload, if handed in.
    pub fn get(&self, key: TileKey) -> Option<Bytes> {
        self.tiles.lock().unwrap_or_else(PoisonError::into_inner).get(&key).cloned()
    }

    /// Changes with every insert or remove.
    pub fn version(&self) -> u64 {
        self.version.load(Relaxed)
    }
}

/// A terrain published as several archives: a manifest (FORMAT.md §9) at a path or URL.
/// Its archives are opened when a tile of theirs is first wanted, over one shared HTTP
/// client (one pool, one HTTP/2 connection per host).
#[derive(Debug)]
pub struct ManifestSource {
    location: String,
    client: Option<reqwest::Client>,
    stats: Arc<crate::HttpStats>,
    /// The version last read: its HTTP ETag (if any) and a hash of its bytes.
    seen: Mutex<Option<(Option<String>, String)>>,
}

impl ManifestSource {
    /// The manifest at `location`: a path (native) or an `http(s)://` URL.
    ///
    /// # Errors
    /// [`Error::HttpClient`] if the HTTP client cannot be built.
    pub fn new(location: &str) -> Result<Self> {
        let client = if is_http_url(location) {
            let builder = reqwest::Client::builder();
            #[cfg(not(target_arch = "wasm32"))]
            let builder = builder.pool_max_idle_per_host(64).tcp_nodelay(true);
            Some(builder.build().map_err(|e| Error::HttpClient { reason: e.to_string() })?)
        } else {
            None
        };
        Ok(Self { location: location.to_owned(), client, stats: Arc::default(), seen: Mutex::default() })
    }

    /// Request and byte counters of all its archives (HTTP only).
    pub fn shared_stats(&self) -> Arc<crate::HttpStats> {
        self.stats.clone()
    }

    /// Where the manifest is.
    pub fn location(&self) -> &str {
        &self.location
    }

    /// Reads and validates the manifest.
    ///
    /// # Errors
    /// A request or file error naming the manifest; a manifest error.
    pub async fn manifest(&self) -> Result<Manifest> {
        let (bytes, etag) = self.fetch(None).await?.unwrap_or_default();
        let manifest = Manifest::from_json(&bytes)
            .map_err(|e| Error::Request { url: self.location.clone(), reason: e.to_string() })?;
        *self.seen.lock().unwrap_or_else(PoisonError::into_inner) =
            Some((etag, terrastream_format::content_tag(&bytes)));
        Ok(manifest)
    }

    /// Was the manifest republished since it was last read? One conditional request
    /// (`If-None-Match`) over HTTP; a read of the file otherwise.
    ///
    /// # Errors
    /// A request or file error naming the manifest.
    pub async fn republished(&self) -> Result<bool> {
        let seen = self.seen.lock().unwrap_or_else(PoisonError::into_inner).clone();
        let Some((etag, hash)) = seen else { return Ok(false) };
        Ok(match self.fetch(etag.as_deref()).await? {
            None => false,
            Some((bytes, _)) => terrastream_format::content_tag(&bytes) != hash,
        })
    }

    /// The manifest's bytes and HTTP ETag; None when `if_none_match` still matches.
    async fn fetch(&self, if_none_match: Option<&str>) -> Result<Option<(Bytes, Option<String>)>> {
        let Some(client) = &self.client else { return Ok(Some((read_file(&self.location)?, None))) };
        let fail = |reason: String| Error::Request { url: self.location.clone(), reason };
        let mut request = client.get(&self.location);
        if let Some(etag) = if_none_match {
            request = request.header(reqwest::header::IF_NONE_MATCH, etag);
        }
        let response = request.send().await.map_err(|e| fail(e.to_string()))?;
        match response.status() {
            StatusCode::NOT_MODIFIED if if_none_match.is_some() => Ok(None),
            StatusCode::OK => {
                let etag =
                    response.headers().get(reqwest::header::ETAG).and_then(|v| v.to_str().ok()).map(str::to_owned);
                let bytes = response.bytes().await.map_err(|e| fail(format!("body: {e}")))?;
                Ok(Some((bytes, etag)))
            }
            status => Err(Error::Status { url: self.location.clone(), status: status.as_u16() }),
        }
    }

    /// Opens archive `part` of `manifest` and checks it is the one named.
    // In the browser nothing is Send (one thread); the Arc is shared, not sent.
    #[cfg_attr(target_arch = "wasm32", allow(clippy::arc_with_non_send_sync))]
    pub(crate) async fn open_part(&self, manifest: &Manifest, part: usize) -> Result<Arc<AsyncReader<DynSource>>> {
        let location = manifest.resolve(&self.location, part).ok_or(Error::NotOpen { why: None })?;
        let source = match &self.client {
            Some(client) => {
                let source = HttpSource::with_client(client.clone(), &location, crate::RetryPolicy::default())?;
                DynSource::new(source.with_stats(self.stats.clone()))
            }
            None => open_file(&location)?,
        };
        let reader = AsyncReader::new(source).await?;
        let header = reader.archive().header().encode();
        manifest.check_part(part, &header, reader.metadata())?;
        Ok(Arc::new(reader))
    }
}

#[cfg(not(target_arch = "wasm32"))]
fn read_file(path: &str) -> Result<Bytes> {
    let file =
        std::fs::File::open(path).map_err(|e| terrastream_format::Error::File { path: path.into(), error: e })?;
    let mut bytes = Vec::new();
    std::io::Read::read_to_end(&mut std::io::Read::take(file, terrastream_format::MAX_MANIFEST_BYTES + 1), &mut bytes)
        .map_err(|e| terrastream_format::Error::File { path: path.into(), error: e })?;
    Ok(bytes.into())
}

#[cfg(target_arch = "wasm32")]
fn read_file(path: &str) -> Result<Bytes> {
    Err(Error::NotAUrl { location: path.to_owned() })
}

#[cfg(not(target_arch = "wasm32"))]
fn open_file(path: &str) -> Result<DynSource> {
    Ok(DynSource::new(terrastream_format::MmapSource::open(path)?))
}

#[cfg(target_arch = "wasm32")]
fn open_file(path: &str) -> Result<DynSource> {
    Err(Error::NotAUrl { location: path.to_owned() })
}

/// An opened manifest: its archives, each opened once, when first needed.
#[derive(Debug)]
pub(crate) struct Parts {
    pub(crate) source: Arc<ManifestSource>,
    pub(crate) manifest: Manifest,
    readers: Vec<std::sync::OnceLock<Arc<AsyncReader<DynSource>>>>,
}

impl Parts {
    /// Archive `part`, if opened.
    pub(crate) fn reader(&self, part: usize) -> Option<&Arc<AsyncReader<DynSource>>> {
        self.readers.get(part)?.get()
    }

    /// Keeps an opened archive (the first one opened wins).
    pub(crate) fn set(&self, part: usize, reader: Arc<AsyncReader<DynSource>>) {
        if let Some(slot) = self.readers.get(part) {
            let _ = slot.set(reader);
        }
    }

    /// Archive `part`, opened now if it is not yet.
    pub(crate) async fn open(&self, part: usize) -> Result<Arc<AsyncReader<DynSource>>> {
        if let Some(reader) = self.reader(part) {
            return Ok(reader.clone());
        }
        let reader = self.source.open_part(&self.manifest, part).await?;
        self.set(part, reader.clone());
        Ok(reader)
    }
}

/// What a streamer streams from.
#[derive(Clone, Debug)]
pub enum Origin {
    /// A `.tspack` archive behind a byte-range source.
    Archive(DynSource),
    /// Our server's tile endpoint for one archive.
    Endpoint(Arc<EndpointSource>),
    /// Tiles handed in by the host application.
    Host(Arc<HostTiles>),
    /// Several archives named by a manifest, streamed as one.
    Manifest(Arc<ManifestSource>),
}

impl Origin {
    /// An archive behind any byte-range source.
    pub fn archive(source: impl AsyncRangeSource + 'static) -> Self {
        Self::Archive(DynSource::new(source))
    }

    /// A location as the command line takes it: a file path (memory-mapped), an
    /// `http(s)://…/name.tspack` URL (Range requests against any server or CDN), an
    /// `http(s)://…/name` URL of our server's tile endpoint, or a manifest's path or URL
    /// (`….json`).
    ///
    /// # Errors
    /// A file error naming a file that cannot be mapped; [`Error::BadUrl`] for a bad URL;
    /// [`Error::NotAUrl`] for a path in the browser.
    pub fn parse(location: &str) -> Result<Self> {
        if terrastream_format::is_manifest_location(location) {
            return Ok(Self::Manifest(Arc::new(ManifestSource::new(location)?)));
        }
        if is_http_url(location) {
            let path = location.split(['?', '#']).next().unwrap_or(location);
            return if path.ends_with(".tspack") {
                Ok(Self::archive(HttpSource::new(location)?))
            } else {
                Ok(Self::Endpoint(Arc::new(EndpointSource::new(location)?)))
            };
        }
        #[cfg(not(target_arch = "wasm32"))]
        {
            Ok(Self::archive(terrastream_format::MmapSource::open(location)?))
        }
        #[cfg(target_arch = "wasm32")]
        {
            Err(Error::NotAUrl { location: location.to_owned() })
        }
    }

    // In the browser nothing is Send (one thread); the Arc is shared, not sent.
    #[cfg_attr(target_arch = "wasm32", allow(clippy::arc_with_non_send_sync))]
    pub(crate) async fn open(&self) -> Result<Backend> {
        match self {
            Self::Archive(source) => Ok(Backend::Archive(Arc::new(AsyncReader::new(source.clone()).await?))),
            Self::Endpoint(endpoint) => {
                let metadata = endpoint.metadata().await?;
                Ok(Backend::Endpoint(endpoint.clone(), Arc::new(metadata)))
            }
            Self::Host(host) => Ok(Backend::Host(host.clone())),
            Self::Manifest(source) => {
                let manifest = source.manifest().await?;
                let readers = manifest.archives.iter().map(|_| std::sync::OnceLock::new()).collect();
                Ok(Backend::Manifest(Arc::new(Parts { source: source.clone(), manifest, readers })))
            }
        }
    }

    pub(crate) fn forget(&self) {
        match self {
            Self::Archive(source) => source.forget(),
            Self::Endpoint(endpoint) => endpoint.forget(),
            Self::Host(_) | Self::Manifest(_) => {}
        }
    }
}

/// An opened origin.
#[derive(Clone)]
pub(crate) enum Backend {
    Archive(Arc<AsyncReader<DynSource>>),
    Endpoint(Arc<EndpointSource>, Arc<Metadata>),
    Host(Arc<HostTiles>),
    Manifest(Arc<Parts>),
}

impl Backend {
    pub(crate) fn metadata(&self) -> &Metadata {
        match self {
            Self::Archive(reader) => reader.metadata(),
            Self::Endpoint(_, metadata) => metadata,
            Self::Host(host) => host.metadata(),
            Self::Manifest(parts) => &parts.manifest.metadata,
        }
    }

    /// The archive reader of part `part` (0 for a single archive), if open.
    pub(crate) fn part_reader(&self, part: usize) -> Option<&Arc<AsyncReader<DynSource>>> {
        match self {
            Self::Archive(reader) => (part == 0).then_some(reader),
            Self::Manifest(parts) => parts.reader(part),
            Self::Endpoint(..) | Self::Host(_) => None,
        }
    }
}
