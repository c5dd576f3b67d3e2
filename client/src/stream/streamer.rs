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
use super::decode::{DecodedTile, decode};
use super::origin::{Backend, BoxFuture, Origin};
use super::select::{SelectOptions, Want, select};
use crate::error::{Error, Result};

/// Settings of a [`Streamer`].
#[derive(Clone, Debug, PartialEq)]
pub struct StreamOptions {
    /// Tile selection.
    pub select: SelectOptions,
    /// Most requests in flight at once.
    pub max_in_flight: usize,
    /// Adapt the in-flight limit to the link (see [`Flow`]), between 2 and
    /// `max_in_flight`, starting at 8; else `max_in_flight` is the limit.
    pub adaptive_in_flight: bool,
    /// Merge neighbouring tiles of an archive into one range request.
    pub coalesce: bool,
    /// Largest gap between two tiles' bytes that still merges them.
    pub coalesce_gap: u64,
    /// Largest coalesced request.
    pub max_request_bytes: u64,
    /// Decoded-tile cache budget in bytes (what the current view needs is kept even above it).
    pub cache_bytes: usize,
    /// Wait before retrying a failed tile; doubled per failure.
    pub retry_backoff: Duration,
    /// Longest wait between retries.
    pub max_retry_backoff: Duration,
    /// Worker threads for fetching and decoding (native only).
    pub worker_threads: usize,
    /// Prefetch what the camera will see this far ahead, at its current speed and turn,
    /// with the requests the current view leaves free (zero: no prefetch).
    pub prefetch_ahead: Duration,
    /// How often a manifest is asked whether it was republished (one conditional
    /// request); when it was, everything is re-read from the new one (zero: never).
    pub manifest_recheck: Duration,
}

impl Default for StreamOptions {
    fn default() -> Self {
        Self {
            select: SelectOptions::default(),
            max_in_flight: 32,
            adaptive_in_flight: true,
            coalesce: true,
            coalesce_gap: 4 * 1024,
            max_request_bytes: 512 * 1024,
            cache_bytes: 512 * 1024 * 1024,
            retry_backoff: Duration::from_millis(250),
            max_retry_backoff: Duration::from_secs(10),
            worker_threads: 2,
            prefetch_ahead: Duration::from_millis(500),
            manifest_recheck: Duration::from_secs(30),
        }
    }
}

/// Why a [`Decoder`] handed back no tile.
#[derive(Clone, Debug, PartialEq, Eq)]
pub enum DecodeFailure {
    /// The payload is not a tile of its layer (what [`decode`] says of it).
    Undecodable(String),
    /// The decoder could not run (a worker that did not start): the tile is decoded
    /// where it was fetched instead.
    Unavailable,
}

/// What a [`Decoder`] returns.
pub type DecodeResult = BoxFuture<'static, std::result::Result<DecodedTile, DecodeFailure>>;

/// Decodes payloads somewhere else than the fetching task: in a browser, Web Workers,
/// so that decoding does not take the page's thread. Given the layer, the tile, its
/// payload and whether the layer's compression is still on it.
#[cfg(target_arch = "wasm32")]
pub type Decoder = std::rc::Rc<dyn Fn(&Layer, TileKey, Bytes, bool) -> DecodeResult>;
/// Decodes payloads somewhere else than the fetching task (see the wasm32 definition).
#[cfg(not(target_arch = "wasm32"))]
pub type Decoder = Arc<dyn Fn(&Layer, TileKey, Bytes, bool) -> DecodeResult + Send + Sync>;

/// How much one frame may upload.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct UploadBudget {
    /// Most tiles.
    pub max_tiles: usize,
    /// Most bytes (decoded size). Must be at least one tile's size, or nothing is uploaded.
    pub max_bytes: usize,
}

impl Default for UploadBudget {
    fn default() -> Self {
        Self { max_tiles: 8, max_bytes: 4 * 1024 * 1024 }
    }
}

/// A tile ready for the GPU.
#[derive(Clone, Debug)]
pub struct Upload {
    /// The decoded tile.
    pub tile: Arc<DecodedTile>,
    /// The archive version it belongs to (see [`Streamer::generation`]).
    pub generation: u64,
    /// Its urgency rank this frame (0 = most urgent).
    pub rank: usize,
}

/// Counters since the streamer was made.
#[derive(Clone, Debug, Default, PartialEq, Eq)]
pub struct StreamStats {
    /// Requests sent (tile fetches, coalesced or not, and directory leaves).
    pub requests: u64,
    /// Tiles fetched and decoded.
    pub tiles_fetched: u64,
    /// Bytes received.
    pub bytes_fetched: u64,
    /// Bytes of the tiles themselves among them (the rest is gaps of coalesced requests
    /// and directory leaves).
    pub bytes_needed: u64,
    /// Requests in flight now.
    pub in_flight: u64,
    /// The in-flight limit now (adaptive: follows the link).
    pub in_flight_limit: u64,
    /// Tiles the camera's motion predicts it will want, not wanted yet (fetched with the
    /// requests the view leaves free).
    pub prefetch: u64,
    /// Bytes in the decoded-tile cache now.
    pub cache_bytes: u64,
    /// Tiles in the decoded-tile cache now.
    pub cache_tiles: u64,
    /// Wanted tiles found in the cache, summed over updates.
    pub hits: u64,
    /// Tiles whose request was cancelled because the camera no longer needed them.
    pub cancelled: u64,
    /// Tiles that rode in a request with others (tiles - requests, for tile fetches).
    pub coalesced: u64,
    /// Failed tile fetches (each is retried after a backoff).
    pub failures: u64,
    /// Tiles the origin does not have.
    pub missing: u64,
    /// Tiles fetched whole whose bytes could not be decoded (not retried; coverage falls
    /// back to the parent there). Also counted in `failures`.
    pub undecodable: u64,
    /// Tiles handed to the renderer.
    pub uploads: u64,
    /// Bytes handed to the renderer.
    pub upload_bytes: u64,
    /// Times the archive was found replaced and everything re-read.
    pub reloads: u64,
    /// Tiles wanted by the last update.
    pub wanted: u64,
}

#[derive(Clone, Copy, Debug)]
enum TileState {
    Requested(u64),
    Missing,
    Failed {
        failures: u32,
        retry_at: Instant,
    },
    /// Fetched, but the payload does not decode: asking again would give the same bytes.
    Undecodable,
}

impl TileState {
    /// Nothing more will come for the tile in this generation of the archive: the view
    /// neither waits for it nor asks again, and coverage falls back to a coarser tile.
    fn is_settled_without_data(self) -> bool {
        matches!(self, Self::Missing | Self::Undecodable)
    }
}

pub(super) enum Outcome {
    Ready(Arc<DecodedTile>),
    Missing,
    /// The fetch failed (worth a retry).
    Failed(String),
    /// The bytes arrived but are not a tile of their layer (a retry gives the same bytes).
    Undecodable(String),
}

pub(super) enum Completion {
    /// `took`: the fetch's round trip (the request until its bytes are in, decoding aside).
    Tiles {
        request: u64,
        generation: u64,
        results: Vec<(TileKey, Outcome)>,
        bytes: u64,
        needed: u64,
        took: Duration,
    },
    /// A leaf directory of archive `part` (0 unless a manifest's), or (offset
    /// [`OPEN_PART`]) the archive itself, opened.
    Leaf {
        request: u64,
        generation: u64,
        part: usize,
        offset: u64,
        failure: Option<String>,
        bytes: u64,
        took: Duration,
    },
    Opened {
        generation: u64,
        result: Result<Backend>,
    },
    Changed {
        generation: u64,
        what: String,
    },
    /// A manifest was asked whether it was republished, and was not (or the question
    /// failed: asked again later).
    Rechecked,
}

/// The "leaf offset" of a manifest's archive being opened: its header and root directory.
const OPEN_PART: u64 = u64::MAX;

/// A tile's bytes: in which archive (0 unless a manifest's), where.
pub(super) type Located = (usize, TileLocation);

struct InFlight {
    tiles: Vec<TileKey>,
    leaf: Option<(usize, u64)>,
    abort: AbortHandle,
}

/// The in-flight limit, adapted to the link as a delay-based congestion control does: a
/// request that comes back about as fast as the fastest so far, while the limit was all
/// used, means the link has room (one more request in flight); one that takes three times
/// as long means requests queue at the bottleneck (15 % fewer). Over a long, fast link this
/// fills the bandwidth-delay product with requests; over a slow one it keeps few enough in
/// flight that the most urgent tiles are not stuck behind less urgent ones.
#[derive(Clone, Debug)]
struct Flow {
    limit: f64,
    /// The fastest round trip seen, slowly forgotten (a route may change).
    base: Option<Duration>,
    /// The last fetch took well over the base: requests queue at the bottleneck, and
    /// bandwidth spent on prefetch is taken from the view.
    queueing: bool,
}

impl Flow {
    const START: f64 = 8.0;
    const LOWEST: f64 = 2.0;

    fn new(max: usize) -> Self {
        Self { limit: Self::START.min(max as f64), base: None, queueing: false }
    }

    #[expect(clippy::cast_possible_truncation, clippy::cast_sign_loss, reason = "between 2 and a usize cap")]
    fn limit(&self, options: &StreamOptions) -> usize {
        if options.adaptive_in_flight {
            (self.limit as usize).clamp(1, options.max_in_flight)
        } else {
            options.max_in_flight
        }
    }

    /// A request came back after `rtt`; `full`: the limit was all in use when it did.
    fn sample(&mut self, rtt: Duration, full: bool, max: usize) {
        let base = match self.base {
            Some(b) if rtt >= b => b + (rtt - b) / 128,
            _ => rtt,
        };
        self.base = Some(base);
        let slack = Duration::from_millis(2);
        self.queueing = rtt > base.mul_f64(1.5) + slack;
        if rtt <= base.mul_f64(1.5) + slack {
            if full {
                self.limit = (self.limit + 1.0).min(max as f64);
            }
        } else if rtt > base * 3 + slack {
            self.limit = (self.limit * 0.85).max(Self::LOWEST.min(max as f64));
        }
    }
}

#[derive(Default)]
struct Queue(Mutex<Vec<Completion>>);

impl Queue {
    fn push(&self, c: Completion) {
        self.0.lock().unwrap_or_else(PoisonError::into_inner).push(c);
    }
    fn take(&self) -> Vec<Completion> {
        std::mem::take(&mut *self.0.lock().unwrap_or_else(PoisonError::into_inner))
    }
}

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
    flow: Flow,
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
        let flow = Flow::new(options.max_in_flight);
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
            flow,
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

    /// Changes whenever the archive was found replaced: everything uploaded before
    /// belongs to the old version and must be dropped.
    pub fn generation(&self) -> u64 {
        self.generation
    }

    /// Counters.
    pub fn stats(&self) -> StreamStats {
        StreamStats {
            in_flight: self.requests.len() as u64,
            in_flight_limit: self.flow.limit(&self.options) as u64,
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
        let Some(metadata) = self.metadata() else { return };
        let states = &self.states;
        self.wanted =
            select(metadata, camera, &self.options.select, |k| !matches!(states.get(&k), Some(TileState::Missing)));
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

    /// Asks a manifest, every `manifest_recheck`, whether it was republished; a new one
    /// makes the streamer re-read everything from it ([`Completion::Changed`]).
    fn recheck_manifest(&mut self, now: Instant) {
        let source = match self.backend() {
            Some(Backend::Manifest(parts)) => parts.source.clone(),
            _ => return,
        };
        let interval = self.options.manifest_recheck;
        if interval.is_zero() || self.rechecking {
            return;
        }
        match self.recheck_at {
            // The first question is an interval after it opened.
            None => {
                self.recheck_at = Some(now + interval);
                return;
            }
            Some(at) if now < at => return,
            Some(_) => {}
        }
        self.rechecking = true;
        let (queue, generation) = (self.queue.clone(), self.generation);
        self.spawn(async move {
            let answer = match source.republished().await {
                Ok(true) => Completion::Changed { generation, what: format!("{}: republished", source.location()) },
                Ok(false) => Completion::Rechecked,
                Err(e) => {
                    tracing::debug!("asking whether the manifest changed: {e}");
                    Completion::Rechecked
                }
            };
            queue.push(answer);
        });
    }

    /// The tiles of the view `prefetch_ahead` from now, at the camera's speed and turn
    /// since the last update, that the current view does not want: fetched with the
    /// requests it leaves free, cancelled when the camera stops wanting them.
    fn predict(&mut self, camera: &Camera, now: Instant) {
        self.prefetch.clear();
        self.prefetch_keys.clear();
        let last = self.last_camera.replace((*camera, now));
        let ahead = self.options.prefetch_ahead.as_secs_f64();
        let (Some((before, at)), Some(metadata)) = (last, self.metadata()) else { return };
        let dt = now.saturating_duration_since(at).as_secs_f64();
        if ahead <= 0.0 || dt <= 0.0 || dt > 1.0 {
            return;
        }
        let velocity = (camera.position - before.position) / dt;
        let turn = (camera.forward.normalize_or_zero() - before.forward.normalize_or_zero()) / dt;
        if velocity.length_squared() == 0.0 && turn.length_squared() == 0.0 {
            return;
        }
        let predicted = Camera {
            position: camera.position + velocity * ahead,
            forward: camera.forward.normalize_or_zero() + turn * ahead,
            ..*camera
        };
        let states = &self.states;
        let soon =
            select(metadata, &predicted, &self.options.select, |k| !matches!(states.get(&k), Some(TileState::Missing)));
        for w in soon {
            if !self.wanted_keys.contains(&w.key) && self.prefetch_keys.insert(w.key) {
                self.prefetch.push(w.key);
            }
        }
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

    /// Starts opening the origin (in the background), after `failures` failed attempts.
    fn start_open(&mut self, failures: u32) {
        self.link = Link::Opening { failures };
        let origin = self.origin.clone();
        let queue = self.queue.clone();
        let generation = self.generation + 1;
        self.spawn(async move {
            let result = origin.open().await;
            queue.push(Completion::Opened { generation, result });
        });
    }

    #[cfg(not(target_arch = "wasm32"))]
    fn spawn(&self, task: impl Future<Output = ()> + Send + 'static) {
        self.runtime.spawn(task);
    }

    #[cfg(target_arch = "wasm32")]
    fn spawn(&self, task: impl Future<Output = ()> + 'static) {
        wasm_bindgen_futures::spawn_local(task);
    }

    fn take_completions(&mut self, now: Instant) {
        for completion in self.queue.take() {
            match completion {
                Completion::Opened { generation, result } => {
                    if generation == self.generation + 1 {
                        self.opened(generation, result, now);
                    }
                }
                Completion::Changed { generation, what } => {
                    if generation == self.generation {
                        self.reload(&what);
                    }
                }
                Completion::Rechecked => {
                    self.rechecking = false;
                    self.recheck_at = Some(now + self.options.manifest_recheck);
                }
                Completion::Tiles { request, generation, results, bytes, needed, took } => {
                    if generation == self.generation {
                        self.finished(request, took);
                        self.stats.bytes_fetched += bytes;
                        self.stats.bytes_needed += needed;
                        self.absorb(results, now);
                    }
                }
                Completion::Leaf { request, generation, part, offset, failure, bytes, took } => {
                    if generation == self.generation {
                        self.finished(request, took);
                        self.stats.bytes_fetched += bytes;
                        self.leaf_done((part, offset), failure, now);
                    }
                }
            }
        }
    }

    /// Request `id` came back after `took`: no longer in flight; its round trip tells the
    /// flow control.
    fn finished(&mut self, id: u64, took: Duration) {
        let full = self.requests.len() >= self.flow.limit(&self.options);
        if self.requests.remove(&id).is_some() {
            self.flow.sample(took, full, self.options.max_in_flight);
        }
    }

    /// The origin opened, or failed to (retried with a growing backoff).
    fn opened(&mut self, generation: u64, result: Result<Backend>, now: Instant) {
        match result {
            Ok(backend) => {
                self.generation = generation;
                self.link = Link::Open(backend);
            }
            Err(e) => {
                tracing::warn!("cannot open the archive: {e}");
                self.last_error = Some(e.to_string());
                let failures = match self.link {
                    Link::Opening { failures } | Link::Closed { failures, .. } => failures + 1,
                    Link::Open(_) => 1,
                };
                self.link = Link::Closed { failures, retry_at: now + self.backoff(failures) };
            }
        }
    }

    /// Takes in fetched tiles: ready ones into the cache, missing and undecodable ones
    /// settled, failed ones retried later. Returns the first failure, if any.
    pub(super) fn absorb(&mut self, results: Vec<(TileKey, Outcome)>, now: Instant) -> Option<(TileKey, String)> {
        let mut first_failure = None;
        for (key, outcome) in results {
            match outcome {
                Outcome::Ready(tile) => {
                    self.stats.tiles_fetched += 1;
                    self.states.remove(&key);
                    self.cache.insert(tile);
                }
                Outcome::Missing => {
                    self.stats.missing += 1;
                    self.states.insert(key, TileState::Missing);
                }
                Outcome::Undecodable(why) => {
                    self.stats.failures += 1;
                    self.stats.undecodable += 1;
                    tracing::warn!("{why}: drawn from a coarser tile");
                    first_failure.get_or_insert((key, why.clone()));
                    self.last_error = Some(why);
                    self.states.insert(key, TileState::Undecodable);
                }
                Outcome::Failed(why) => {
                    self.stats.failures += 1;
                    tracing::debug!("tile {key}: {why}");
                    first_failure.get_or_insert((key, why.clone()));
                    self.last_error = Some(why);
                    let failures = match self.states.get(&key) {
                        Some(TileState::Failed { failures, .. }) => failures + 1,
                        _ => 1,
                    };
                    let retry_at = now + self.backoff(failures);
                    self.states.insert(key, TileState::Failed { failures, retry_at });
                }
            }
        }
        first_failure
    }

    /// A leaf directory arrived (or failed: retried later with a growing backoff).
    fn leaf_done(&mut self, offset: (usize, u64), failure: Option<String>, now: Instant) {
        if let Some(why) = failure {
            self.stats.failures += 1;
            self.last_error = Some(why);
            let failures = self.leaf_failures.get(&offset).map_or(1, |f| f.0 + 1);
            self.leaf_failures.insert(offset, (failures, now + self.backoff(failures)));
        } else {
            self.leaf_failures.remove(&offset);
        }
    }

    /// The origin's reader, once open.
    pub(super) fn backend(&self) -> Option<&Backend> {
        match &self.link {
            Link::Open(backend) => Some(backend),
            Link::Opening { .. } | Link::Closed { .. } => None,
        }
    }

    fn backoff(&self, failures: u32) -> Duration {
        let factor = 1u32 << failures.saturating_sub(1).min(16);
        (self.options.retry_backoff * factor).min(self.options.max_retry_backoff)
    }

    /// The archive was replaced: drop every request, tile and state of the old version
    /// and open the new one.
    fn reload(&mut self, what: &str) {
        tracing::info!("archive replaced ({what}); dropping cached tiles and re-reading");
        for (_, r) in self.requests.drain() {
            r.abort.abort();
        }
        self.leaf_failures.clear();
        self.states.clear();
        self.cache.clear();
        self.delivered.clear();
        self.wanted.clear();
        self.wanted_keys.clear();
        self.prefetch.clear();
        self.prefetch_keys.clear();
        self.stats.reloads += 1;
        (self.recheck_at, self.rechecking) = (None, false);
        self.last_error = Some(format!("archive replaced: {what}"));
        self.generation += 1;
        self.origin.forget();
        self.start_open(0);
    }

    fn cancel_unwanted(&mut self) {
        let (wanted, soon) = (&self.wanted_keys, &self.prefetch_keys);
        let stale: Vec<u64> = self
            .requests
            .iter()
            .filter(|(_, r)| r.leaf.is_none() && !r.tiles.iter().any(|k| wanted.contains(k) || soon.contains(k)))
            .map(|(&id, _)| id)
            .collect();
        for id in stale {
            if let Some(r) = self.requests.remove(&id) {
                r.abort.abort();
                self.stats.cancelled += r.tiles.len() as u64;
                for key in r.tiles {
                    if matches!(self.states.get(&key), Some(TileState::Requested(x)) if *x == id) {
                        self.states.remove(&key);
                    }
                }
            }
        }
    }

    fn issue(&mut self, now: Instant) {
        let Some(backend) = self.backend().cloned() else { return };
        let mut free = self.flow.limit(&self.options).saturating_sub(self.requests.len());
        if free == 0 {
            return;
        }
        // Candidates, most urgent first; located (for archives) so they can be coalesced.
        let mut candidates: Vec<(usize, TileKey, Option<Located>)> = Vec::new();
        let limit = free * 64;
        // What the view wants, then what it will want soon, unless the link is queueing.
        let soon = if self.flow.queueing { &[][..] } else { &self.prefetch[..] };
        let keys: Vec<TileKey> = self.wanted.iter().map(|w| w.key).chain(soon.iter().copied()).collect();
        for (rank, &key) in keys.iter().enumerate() {
            if self.cache.contains(key) {
                continue;
            }
            match self.states.get(&key) {
                Some(TileState::Requested(_)) => continue,
                Some(state) if state.is_settled_without_data() => continue,
                Some(TileState::Failed { retry_at, .. }) if *retry_at > now => continue,
                _ => {}
            }
            let (part, part_key) = match &backend {
                Backend::Archive(_) => (0, key),
                Backend::Manifest(parts) => match parts.manifest.route(key) {
                    Some(route) => (route.part, route.key),
                    None => {
                        self.stats.missing += 1;
                        self.states.insert(key, TileState::Missing);
                        continue;
                    }
                },
                Backend::Endpoint(..) | Backend::Host(_) => {
                    candidates.push((rank, key, None));
                    if candidates.len() >= limit {
                        break;
                    }
                    continue;
                }
            };
            let Some(reader) = backend.part_reader(part) else {
                // A manifest's archive not opened yet: open it (one request, like a leaf).
                if let Backend::Manifest(parts) = &backend
                    && free > 0
                    && self.may_fetch_leaf((part, OPEN_PART), now)
                {
                    free -= 1;
                    self.open_part(parts.clone(), part);
                }
                continue;
            };
            match reader.archive().locate(part_key) {
                Ok(Locate::Found(location)) => candidates.push((rank, key, Some((part, location)))),
                Ok(Locate::Missing) => {
                    self.stats.missing += 1;
                    self.states.insert(key, TileState::Missing);
                }
                Ok(Locate::NeedLeaf { offset, len }) => {
                    if free > 0 && self.may_fetch_leaf((part, offset), now) {
                        free -= 1;
                        self.fetch_leaf(reader.clone(), part, offset, len);
                    }
                }
                Err(e) => {
                    self.stats.failures += 1;
                    self.last_error = Some(e.to_string());
                    let retry_at = now + self.options.max_retry_backoff;
                    self.states.insert(key, TileState::Failed { failures: 16, retry_at });
                }
            }
            if candidates.len() >= limit {
                break;
            }
        }
        let groups = self.group(candidates);
        for group in groups.into_iter().take(free) {
            self.fetch_group(&backend, group);
        }
    }

    /// Is a leaf (or a manifest's archive) neither being fetched nor waiting to be
    /// retried?
    fn may_fetch_leaf(&self, leaf: (usize, u64), now: Instant) -> bool {
        let waiting = self.leaf_failures.get(&leaf).is_some_and(|f| f.1 > now);
        !waiting && !self.requests.values().any(|r| r.leaf == Some(leaf))
    }

    /// Splits candidates into requests: runs of tiles of one archive whose bytes are at
    /// most `coalesce_gap` apart, ordered by their most urgent tile.
    fn group(&self, mut candidates: Vec<(usize, TileKey, Option<Located>)>) -> Vec<Group> {
        let mut groups: Vec<Group> = Vec::new();
        let located = candidates.iter().all(|c| c.2.is_some());
        if !located {
            return candidates.into_iter().map(|(rank, key, loc)| Group { rank, tiles: vec![(key, loc)] }).collect();
        }
        candidates.sort_by_key(|c| c.2.map(|(part, l)| (part, l.offset)));
        for (rank, key, location) in candidates {
            let Some((part, loc)) = location else { continue };
            let end = loc.offset + loc.blob_len();
            if let Some(g) = groups.last_mut().filter(|g| g.part() == Some(part)) {
                let (start, g_end) = g.span();
                let same_blob = g.tiles.iter().any(|t| t.1.is_some_and(|l| l.1.offset == loc.offset));
                let close = loc.offset <= g_end + self.options.coalesce_gap
                    && end.max(g_end) - start <= self.options.max_request_bytes;
                if same_blob || (self.options.coalesce && close) {
                    g.rank = g.rank.min(rank);
                    g.tiles.push((key, Some((part, loc))));
                    continue;
                }
            }
            groups.push(Group { rank, tiles: vec![(key, Some((part, loc)))] });
        }
        groups.sort_by_key(|g| g.rank);
        groups
    }

    fn next_id(&mut self) -> u64 {
        self.next_request += 1;
        self.next_request
    }

    fn fetch_leaf(
        &mut self,
        reader: Arc<terrastream_format::AsyncReader<super::origin::DynSource>>,
        part: usize,
        offset: u64,
        len: u64,
    ) {
        self.spawn_leaf(part, offset, async move {
            match reader.source().fetch(offset, len).await {
                Ok(bytes) => {
                    Ok((reader.archive().add_leaf(offset, &bytes).err().map(|e| e.to_string()), bytes.len() as u64))
                }
                Err(terrastream_format::Error::Changed { what }) => Err(what),
                Err(e) => Ok((Some(e.to_string()), 0)),
            }
        });
    }

    /// Opens archive `part` of a manifest (its header, metadata and root directory).
    fn open_part(&mut self, parts: Arc<super::origin::Parts>, part: usize) {
        self.spawn_leaf(part, OPEN_PART, async move {
            match parts.open(part).await {
                Ok(reader) => Ok((None, reader.archive().header().bootstrap_len())),
                Err(Error::Changed { what } | Error::Format(terrastream_format::Error::Changed { what })) => Err(what),
                Err(e) => Ok((Some(e.to_string()), 0)),
            }
        });
    }

    /// Starts a request for a leaf directory of archive `part` (or, at [`OPEN_PART`], the
    /// archive itself): `work` gives why it failed (if it did) and the bytes received, or
    /// `Err` with what changed when the archive was found replaced.
    fn spawn_leaf(
        &mut self,
        part: usize,
        offset: u64,
        work: impl Future<Output = std::result::Result<(Option<String>, u64), String>> + MaybeSend + 'static,
    ) {
        let task = self.leaf_task(part, offset, work);
        self.spawn(task);
    }

    /// Registers a leaf request and wraps `work` into the task that reports it.
    fn leaf_task<W>(&mut self, part: usize, offset: u64, work: W) -> impl Future<Output = ()> + use<W>
    where
        W: Future<Output = std::result::Result<(Option<String>, u64), String>>,
    {
        let id = self.next_id();
        let (abort, registration) = AbortHandle::new_pair();
        self.requests.insert(id, InFlight { tiles: Vec::new(), leaf: Some((part, offset)), abort });
        self.stats.requests += 1;
        let (queue, generation) = (self.queue.clone(), self.generation);
        async move {
            let timed = async {
                let started = Instant::now();
                match work.await {
                    Ok((failure, bytes)) => {
                        let took = started.elapsed();
                        Completion::Leaf { request: id, generation, part, offset, failure, bytes, took }
                    }
                    Err(what) => Completion::Changed { generation, what },
                }
            };
            if let Ok(c) = Abortable::new(timed, registration).await {
                queue.push(c);
            }
        }
    }

    fn fetch_group(&mut self, backend: &Backend, group: Group) {
        let id = self.next_id();
        let (abort, registration) = AbortHandle::new_pair();
        let keys: Vec<TileKey> = group.tiles.iter().map(|t| t.0).collect();
        for &key in &keys {
            self.states.insert(key, TileState::Requested(id));
        }
        self.stats.requests += 1;
        self.stats.coalesced += keys.len() as u64 - 1;
        self.requests.insert(id, InFlight { tiles: keys, leaf: None, abort });
        let (queue, generation, backend) = (self.queue.clone(), self.generation, backend.clone());
        let decoder = self.decoder.clone();
        self.spawn(async move {
            let work = fetch_and_decode(backend, group, id, generation, decoder);
            if let Ok(c) = Abortable::new(work, registration).await {
                queue.push(c);
            }
        });
    }
}

impl Drop for Streamer {
    fn drop(&mut self) {
        for (_, r) in self.requests.drain() {
            r.abort.abort();
        }
    }
}

pub(super) struct Group {
    pub(super) rank: usize,
    /// Tiles of one archive (located) or of an endpoint or host (not located).
    pub(super) tiles: Vec<(TileKey, Option<Located>)>,
}

impl Group {
    /// The archive the tiles are in (0 unless a manifest's).
    pub(super) fn part(&self) -> Option<usize> {
        self.tiles.first().and_then(|t| t.1).map(|l| l.0)
    }

    fn span(&self) -> (u64, u64) {
        let locations = self.tiles.iter().filter_map(|t| t.1.map(|l| l.1));
        let start = locations.clone().map(|l| l.offset).min().unwrap_or(0);
        let end = locations.map(|l| l.offset + l.blob_len()).max().unwrap_or(0);
        (start, end)
    }
}

/// Decodes one payload. A decoder that panics on some input (a bug: the decoders are
/// fuzzed so as not to) costs that tile, never the worker thread or the page.
fn decode_guarded(layer: &Layer, key: TileKey, payload: &[u8], compressed: bool) -> Outcome {
    let attempt = std::panic::catch_unwind(|| decode(layer, key, payload, compressed));
    match attempt {
        Ok(Ok(tile)) => Outcome::Ready(Arc::new(tile)),
        Ok(Err(e)) => Outcome::Undecodable(e.to_string()),
        Err(_) => Outcome::Undecodable(format!("tile {key} of layer {:?}: the decoder failed", layer.name)),
    }
}

type Fetched = Vec<(TileKey, std::result::Result<Option<Bytes>, String>)>;

/// Fetches a group of located tiles of one archive in one range request: each tile's
/// payload (or why not), bytes received, bytes of the tiles themselves. Err: the archive
/// was replaced (what changed).
async fn fetch_located(
    reader: &terrastream_format::AsyncReader<super::origin::DynSource>,
    group: &Group,
) -> std::result::Result<(Fetched, u64, u64), String> {
    let mut raw = Vec::new();
    let (start, end) = group.span();
    match reader.source().fetch(start, end - start).await {
        Ok(body) => {
            let mut blobs = HashSet::new();
            let mut needed = 0;
            for (key, location) in &group.tiles {
                let Some((_, loc)) = location else { continue };
                if blobs.insert(loc.offset) {
                    needed += loc.blob_len();
                }
                let from = usize::try_from(loc.offset - start).unwrap_or(usize::MAX);
                let to = from.saturating_add(usize::try_from(loc.blob_len()).unwrap_or(usize::MAX));
                let result = if to <= body.len() {
                    reader.archive().payload(loc, body.slice(from..to)).map(Some).map_err(|e| e.to_string())
                } else {
                    Err(format!("tile {key}: short read"))
                };
                raw.push((*key, result));
            }
            Ok((raw, body.len() as u64, needed))
        }
        Err(terrastream_format::Error::Changed { what }) => Err(what),
        Err(e) => {
            raw.extend(group.tiles.iter().map(|(k, _)| (*k, Err(e.to_string()))));
            Ok((raw, 0, 0))
        }
    }
}

/// Decodes fetched payloads with `decoder`, all at once; where it cannot run, here.
async fn decode_with(
    decoder: &Decoder,
    metadata: &Metadata,
    raw: Fetched,
    compressed: bool,
) -> Vec<(TileKey, Outcome)> {
    let jobs = raw.into_iter().map(|(key, fetched)| {
        let layer = metadata.layers.get(usize::from(key.layer())).cloned();
        let decoder = decoder.clone();
        async move {
            let outcome = match (fetched, layer) {
                (Ok(None), _) => Outcome::Missing,
                (Ok(Some(payload)), Some(layer)) => match decoder(&layer, key, payload.clone(), compressed).await {
                    Ok(tile) => Outcome::Ready(Arc::new(tile)),
                    Err(DecodeFailure::Undecodable(why)) => Outcome::Undecodable(why),
                    Err(DecodeFailure::Unavailable) => decode_guarded(&layer, key, &payload, compressed),
                },
                (Ok(Some(_)), None) => Outcome::Failed(format!("tile {key}: no such layer")),
                (Err(why), _) => Outcome::Failed(why),
            };
            (key, outcome)
        }
    });
    futures_util::future::join_all(jobs).await
}

/// Fetches a group of tiles (one request) and decodes them off the calling thread.
pub(super) async fn fetch_and_decode(
    backend: Backend,
    group: Group,
    request: u64,
    generation: u64,
    decoder: Option<Decoder>,
) -> Completion {
    let changed = |what| Completion::Changed { generation, what };
    let started = Instant::now();
    let mut raw: Fetched = Vec::new();
    let (mut bytes, mut needed) = (0, 0);
    let compressed;
    match &backend {
        Backend::Archive(_) | Backend::Manifest(_) => {
            compressed = true;
            match group.part().and_then(|part| backend.part_reader(part)) {
                Some(reader) => match fetch_located(reader, &group).await {
                    Ok(fetched) => (raw, bytes, needed) = fetched,
                    Err(what) => return changed(what),
                },
                None => {
                    let why = || Err("the archive holding it is not open".to_owned());
                    raw.extend(group.tiles.iter().map(|(k, _)| (*k, why())));
                }
            }
        }
        Backend::Endpoint(endpoint, _) => {
            compressed = false;
            for (key, _) in &group.tiles {
                match endpoint.tile(*key).await {
                    Ok(body) => {
                        let n = body.as_ref().map_or(0, |b| b.len() as u64);
                        bytes += n;
                        needed += n;
                        raw.push((*key, Ok(body)));
                    }
                    Err(Error::Changed { what }) => return changed(what),
                    Err(e) => raw.push((*key, Err(e.to_string()))),
                }
            }
        }
        Backend::Host(host) => {
            compressed = true;
            for (key, _) in &group.tiles {
                raw.push((*key, Ok(host.get(*key))));
            }
        }
    }
    let took = started.elapsed();
    let metadata = backend.metadata().clone();
    if let Some(decoder) = decoder {
        let results = decode_with(&decoder, &metadata, raw, compressed).await;
        return Completion::Tiles { request, generation, results, bytes, needed, took };
    }
    let decode_all = move || -> Vec<(TileKey, Outcome)> {
        raw.into_iter()
            .map(|(key, r)| {
                let outcome = match r {
                    Ok(None) => Outcome::Missing,
                    Ok(Some(payload)) => match metadata.layers.get(usize::from(key.layer())) {
                        Some(layer) => decode_guarded(layer, key, &payload, compressed),
                        None => Outcome::Failed(format!("tile {key}: no such layer")),
                    },
                    Err(why) => Outcome::Failed(why),
                };
                (key, outcome)
            })
            .collect()
    };
    #[cfg(not(target_arch = "wasm32"))]
    let results = match tokio::task::spawn_blocking(decode_all).await {
        Ok(r) => r,
        Err(e) => group.tiles.iter().map(|(k, _)| (*k, Outcome::Failed(format!("decoder: {e}")))).collect(),
    };
    #[cfg(target_arch = "wasm32")]
    let results = decode_all();
    Completion::Tiles { request, generation, results, bytes, needed, took }
}

#[cfg(test)]
mod tests {
    use std::time::Duration;

    use super::Flow;

    const MS: Duration = Duration::from_millis(1);

    #[expect(clippy::cast_possible_truncation, clippy::cast_sign_loss, reason = "a small positive limit")]
    fn limit(flow: &Flow) -> usize {
        flow.limit as usize
    }

    #[test]
    fn the_in_flight_limit_grows_on_a_free_link_and_backs_off_when_requests_queue() {
        let mut flow = Flow::new(32);
        assert_eq!(limit(&flow), 8);
        // Round trips at the base while the limit is all used: one more each.
        for _ in 0..10 {
            flow.sample(80 * MS, true, 32);
        }
        assert_eq!(limit(&flow), 18);
        // Not all used: no evidence the link has room.
        flow.sample(80 * MS, false, 32);
        assert_eq!(limit(&flow), 18);
        // Never above the cap.
        for _ in 0..40 {
            flow.sample(80 * MS, true, 32);
        }
        assert_eq!(limit(&flow), 32);
        // Requests now queue (25 times the base): 15 % fewer each, down to 2.
        flow.sample(2000 * MS, true, 32);
        assert_eq!(limit(&flow), 27);
        for _ in 0..40 {
            flow.sample(2000 * MS, true, 32);
        }
        assert_eq!(limit(&flow), 2);
        // The cap below the start.
        assert_eq!(limit(&Flow::new(4)), 4);
    }
}
