//! The frame API: `update(camera)` then `drain_uploads(budget)`, never blocking on I/O.
//!
//! Each update selects the wanted tiles ([`super::select`]), cancels requests for tiles
//! no longer wanted, and issues new ones — most urgent first, at most `max_in_flight` at
//! once, neighbouring tiles of an archive coalesced into one range request when their
//! bytes are close. Fetches and decodes run on worker tasks; their results wait in a
//! queue the next update takes in. `drain_uploads` hands over ready tiles within the
//! frame's budget, never a tile before its parent (coarse first), so what the renderer
//! has always covers the view at some LOD.

use std::collections::{HashMap, HashSet};
use std::sync::{Arc, Mutex, PoisonError};
use std::time::Duration;

use bytes::Bytes;
use futures_util::future::{AbortHandle, Abortable};
use terrastream_format::{AsyncRangeSource, Layer, Locate, MaybeSend, Metadata, TileKey, TileLocation};
use web_time::Instant;

use super::cache::TileCache;
use super::camera::Camera;
use crate::error::{Error, Result};
use crate::globe::Surface;
use crate::stream::origin::{Backend, BoxFuture, Origin};
use crate::stream::select::{SelectOptions, Want, select};
use terrastream_tiles::{DecodedTile, decode};

mod fetch;
mod in_flight;
mod lifecycle;
mod options;
mod predict;
mod state;

use in_flight::*;
pub use options::*;
use state::*;

// For the exact height queries (heights.rs), which fetch tiles themselves.
#[cfg(not(target_arch = "wasm32"))]
pub(super) use fetch::{Group, fetch_and_decode};
pub(super) use state::{Completion, Located, Outcome};

/// Streams the tiles a camera needs from an [`Origin`].
pub struct Streamer {
    origin: Origin,
    options: StreamOptions,
    link: Link,
    pub(super) generation: u64,
    queue: Arc<Queue>,
    #[cfg(not(target_arch = "wasm32"))]
    pub(super) runtime: tokio::runtime::Runtime,
    states: HashMap<TileKey, TileState>,
    requests: HashMap<u64, InFlight>,
    leaf_failures: HashMap<(usize, u64), (u32, Instant)>,
    in_flight: InFlightLimit,
    next_request: u64,
    pub(super) cache: TileCache,
    delivered: HashSet<TileKey>,
    wanted: Vec<Want>,
    /// The keys of `wanted`: what the cache keeps and what requests are still for.
    wanted_keys: HashSet<TileKey>,
    /// Tiles the camera will want soon (not in `wanted`), most urgent first.
    prefetch: Vec<TileKey>,
    prefetch_keys: HashSet<TileKey>,
    /// The camera of the last update, and when: its motion predicts the next views.
    last_camera: Option<(Camera, Instant)>,
    host_version: u64,
    /// When to ask a manifest again whether it was republished (None: not set since it
    /// opened), and whether a question is out.
    recheck_at: Option<Instant>,
    rechecking: bool,
    decoder: Option<Decoder>,
    /// The shape the selection sees, for (generation, globe asked).
    surface: Option<((u64, bool), Surface)>,
    pub(super) stats: StreamStats,
    pub(super) last_error: Option<String>,
}

/// Where a streamer stands with its origin.
enum Link {
    /// Opening, in the background, after `failures` failed attempts.
    Opening { failures: u32 },
    /// Not open: `failures` attempts failed; the next one at `retry_at`.
    Closed { failures: u32, retry_at: Instant },
    /// Open: tiles are read through it.
    Open(Backend),
}

impl std::fmt::Debug for Streamer {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("Streamer").field("origin", &self.origin).field("stats", &self.stats).finish_non_exhaustive()
    }
}

impl Streamer {
    /// A streamer that starts opening `origin` at once (in the background).
    ///
    /// # Errors
    /// [`Error::Threads`] if the worker threads cannot be started.
    pub fn new(origin: Origin, options: StreamOptions) -> Result<Self> {
        let mut streamer = Self::build(origin, options)?;
        streamer.start_open(0);
        Ok(streamer)
    }

    fn build(origin: Origin, options: StreamOptions) -> Result<Self> {
        #[cfg(not(target_arch = "wasm32"))]
        let runtime = tokio::runtime::Builder::new_multi_thread()
            .worker_threads(options.worker_threads.max(1))
            .thread_name("terrastream-stream")
            .enable_all()
            .build()
            .map_err(Error::Threads)?;
        let in_flight = InFlightLimit::new(options.max_in_flight);
        Ok(Self {
            origin,
            cache: TileCache::new(options.cache_bytes),
            options,
            link: Link::Opening { failures: 0 },
            generation: 0,
            queue: Arc::default(),
            #[cfg(not(target_arch = "wasm32"))]
            runtime,
            states: HashMap::new(),
            requests: HashMap::new(),
            leaf_failures: HashMap::new(),
            in_flight,
            next_request: 0,
            delivered: HashSet::new(),
            wanted: Vec::new(),
            wanted_keys: HashSet::new(),
            prefetch: Vec::new(),
            prefetch_keys: HashSet::new(),
            last_camera: None,
            host_version: 0,
            recheck_at: None,
            rechecking: false,
            decoder: None,
            surface: None,
            stats: StreamStats::default(),
            last_error: None,
        })
    }

    /// A streamer whose origin is already open (native): waits for the first read.
    ///
    /// # Errors
    /// Why the origin could not be opened.
    #[cfg(not(target_arch = "wasm32"))]
    pub fn open(origin: Origin, options: StreamOptions) -> Result<Self> {
        let mut streamer = Self::build(origin, options)?;
        let backend = streamer.runtime.block_on(streamer.origin.open())?;
        streamer.link = Link::Open(backend);
        streamer.generation += 1;
        Ok(streamer)
    }

    /// The metadata, once the origin is open.
    pub fn metadata(&self) -> Option<&Metadata> {
        self.backend().map(Backend::metadata)
    }

    /// The terrain's shape as the selection sees it (the globe for a georeferenced archive
    /// when [`SelectOptions::globe`] asks for it): cameras must be in its scene
    /// coordinates. `None` before the archive is open.
    pub fn surface(&mut self) -> Option<Surface> {
        let key = (self.generation, self.options.select.globe);
        if let Some((k, surface)) = &self.surface
            && *k == key
        {
            return Some(surface.clone());
        }
        let surface = Surface::new(self.metadata()?, key.1);
        self.surface = Some((key, surface.clone()));
        Some(surface)
    }

    /// Hands in the surface made for the current archive elsewhere (a renderer makes the
    /// same one), so that a lattice of transforms is made once.
    pub fn set_surface(&mut self, surface: Surface) {
        self.surface = Some(((self.generation, self.options.select.globe), surface));
    }

    /// Changes whenever the archive was found replaced: everything uploaded before
    /// belongs to the old version and must be dropped.
    pub fn generation(&self) -> u64 {
        self.generation
    }

    /// Counters.
    pub fn stats(&self) -> StreamStats {
        StreamStats {
            in_flight: self.requests.len() as u64,
            in_flight_limit: self.in_flight.limit(&self.options) as u64,
            prefetch: self.prefetch.len() as u64,
            cache_bytes: self.cache.bytes() as u64,
            cache_tiles: self.cache.len() as u64,
            wanted: self.wanted.len() as u64,
            ..self.stats.clone()
        }
    }

    /// For a manifest, which of its archives are open (opened when a tile of theirs is
    /// first wanted); for a single archive, `[true]` once open; empty before.
    pub fn opened_parts(&self) -> Vec<bool> {
        match self.backend() {
            Some(Backend::Manifest(parts)) => {
                (0..parts.manifest.archives.len()).map(|i| parts.reader(i).is_some()).collect()
            }
            Some(_) => vec![true],
            None => Vec::new(),
        }
    }

    /// Decodes fetched tiles with `decoder` from now on (None: where they are fetched).
    pub fn set_decoder(&mut self, decoder: Option<Decoder>) {
        self.decoder = decoder;
    }

    /// The settings.
    pub fn options(&self) -> &StreamOptions {
        &self.options
    }

    /// Changes the settings that can change while streaming (in-flight cap, coalescing,
    /// selection, cache budget).
    pub fn set_options(&mut self, options: StreamOptions) {
        self.cache.set_budget(options.cache_bytes);
        self.cache.trim(&self.wanted_keys);
        self.options = options;
    }

    /// The last error met (a failed fetch, an archive that could not be opened).
    pub fn last_error(&self) -> Option<&str> {
        self.last_error.as_deref()
    }

    /// The tiles wanted by the last update, most urgent first.
    pub fn wanted(&self) -> &[Want] {
        &self.wanted
    }

    /// Is the tile handed to the renderer (and not released)?
    pub fn is_delivered(&self, key: TileKey) -> bool {
        self.delivered.contains(&key)
    }

    /// Does the origin lack this tile (or keep failing to give it)? Coverage falls back
    /// to the nearest coarser LOD there.
    pub fn is_unavailable(&self, key: TileKey) -> bool {
        matches!(self.states.get(&key), Some(TileState::Missing | TileState::Failed { .. } | TileState::Undecodable))
    }

    /// Is the tile known to be absent from the origin?
    pub fn is_missing(&self, key: TileKey) -> bool {
        matches!(self.states.get(&key), Some(TileState::Missing))
    }

    /// The renderer dropped a tile it was given: it will be handed over again if wanted.
    pub fn release(&mut self, key: TileKey) {
        self.delivered.remove(&key);
    }

    /// Wanted tiles not delivered yet (excluding those the origin lacks and those that
    /// arrived undecodable): 0 means the view is fully streamed.
    pub fn pending(&self) -> usize {
        self.wanted
            .iter()
            .filter(|w| {
                !self.delivered.contains(&w.key)
                    && !self.states.get(&w.key).is_some_and(|s| s.is_settled_without_data())
            })
            .count()
    }

    /// A decoded tile from the cache.
    pub fn cached(&self, key: TileKey) -> Option<&Arc<DecodedTile>> {
        self.cache.peek(key)
    }

    /// One frame's bookkeeping: takes in finished work, selects what `camera` needs,
    /// cancels what it no longer needs and issues new requests. Never blocks on I/O.
    pub fn update(&mut self, camera: &Camera) {
        let now = Instant::now();
        self.take_completions(now);
        match self.link {
            Link::Open(_) => {}
            Link::Opening { .. } => return,
            Link::Closed { failures, retry_at } => {
                if now >= retry_at {
                    self.start_open(failures);
                }
                return;
            }
        }
        self.recheck_manifest(now);
        if let Some(Backend::Host(host)) = self.backend() {
            let version = host.version();
            if version != self.host_version {
                self.host_version = version;
                self.states.retain(|_, s| !s.is_settled_without_data());
            }
        }
        let Some(surface) = self.surface() else { return };
        let Some(metadata) = self.metadata() else { return };
        let states = &self.states;
        self.wanted = select(metadata, &surface, camera, &self.options.select, |k| {
            !matches!(states.get(&k), Some(TileState::Missing))
        });
        self.wanted_keys = self.wanted.iter().map(|w| w.key).collect();
        for w in &self.wanted {
            if self.cache.touch(w.key) {
                self.stats.hits += 1;
            }
        }
        self.predict(camera, now);
        self.cancel_unwanted();
        self.issue(now);
        self.cache.trim(&self.wanted_keys);
    }

    /// Ready tiles for this frame, most urgent first, within `budget`; a tile is never
    /// handed over before its parent (unless the parent is unavailable).
    pub fn drain_uploads(&mut self, budget: UploadBudget) -> Vec<Upload> {
        let mut out = Vec::new();
        let mut bytes = 0;
        let Link::Open(backend) = &self.link else { return out };
        let metadata = backend.metadata();
        for (rank, w) in self.wanted.iter().enumerate() {
            if out.len() >= budget.max_tiles {
                break;
            }
            if self.delivered.contains(&w.key) {
                continue;
            }
            let Some(tile) = self.cache.peek(w.key) else { continue };
            let start = metadata.layers[usize::from(w.key.layer())].start_lod();
            if let Some(parent) = w.key.parent().filter(|p| p.lod() <= start)
                && !self.delivered.contains(&parent)
                && !self.is_unavailable(parent)
            {
                continue;
            }
            if bytes + tile.byte_len() > budget.max_bytes {
                break;
            }
            bytes += tile.byte_len();
            self.delivered.insert(w.key);
            out.push(Upload { tile: tile.clone(), generation: self.generation, rank });
        }
        self.stats.uploads += out.len() as u64;
        self.stats.upload_bytes += bytes as u64;
        out
    }
}

impl Drop for Streamer {
    fn drop(&mut self) {
        for (_, r) in self.requests.drain() {
            r.abort.abort();
        }
    }
}
