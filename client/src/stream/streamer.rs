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
use terrastream_format::{AsyncRangeSource, Layer, LayerKind, Locate, Metadata, TileKey, TileLocation};

use crate::error::{Error, Result};
use web_time::Instant;

use super::cache::TileCache;
use super::camera::Camera;
use super::decode::{DecodedTile, decode};
use super::origin::{Backend, Origin};
use super::select::{SelectOptions, Want, select};

/// Settings of a [`Streamer`].
#[derive(Clone, Debug, PartialEq)]
pub struct StreamOptions {
    /// Tile selection.
    pub select: SelectOptions,
    /// Most requests in flight at once.
    pub max_in_flight: usize,
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
}

impl Default for StreamOptions {
    fn default() -> Self {
        Self {
            select: SelectOptions::default(),
            max_in_flight: 8,
            coalesce: true,
            coalesce_gap: 4 * 1024,
            max_request_bytes: 512 * 1024,
            cache_bytes: 512 * 1024 * 1024,
            retry_backoff: Duration::from_millis(250),
            max_retry_backoff: Duration::from_secs(10),
            worker_threads: 2,
        }
    }
}

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

enum Outcome {
    Ready(Arc<DecodedTile>),
    Missing,
    /// The fetch failed (worth a retry).
    Failed(String),
    /// The bytes arrived but are not a tile of their layer (a retry gives the same bytes).
    Undecodable(String),
}

enum Completion {
    Tiles { request: u64, generation: u64, results: Vec<(TileKey, Outcome)>, bytes: u64, needed: u64 },
    Leaf { request: u64, generation: u64, offset: u64, failure: Option<String>, bytes: u64 },
    Opened { generation: u64, result: Result<Backend> },
    Changed { generation: u64, what: String },
}

struct InFlight {
    tiles: Vec<TileKey>,
    leaf: Option<u64>,
    abort: AbortHandle,
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
    backend: Option<Backend>,
    opening: bool,
    open_failures: u32,
    open_retry_at: Option<Instant>,
    generation: u64,
    queue: Arc<Queue>,
    #[cfg(not(target_arch = "wasm32"))]
    runtime: tokio::runtime::Runtime,
    states: HashMap<TileKey, TileState>,
    requests: HashMap<u64, InFlight>,
    leaf_failures: HashMap<u64, (u32, Instant)>,
    next_request: u64,
    cache: TileCache,
    delivered: HashSet<TileKey>,
    wanted: Vec<Want>,
    /// The keys of `wanted`: what the cache keeps and what requests are still for.
    wanted_keys: HashSet<TileKey>,
    host_version: u64,
    stats: StreamStats,
    last_error: Option<String>,
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
        streamer.start_open();
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
        Ok(Self {
            origin,
            cache: TileCache::new(options.cache_bytes),
            options,
            backend: None,
            opening: false,
            open_failures: 0,
            open_retry_at: None,
            generation: 0,
            queue: Arc::default(),
            #[cfg(not(target_arch = "wasm32"))]
            runtime,
            states: HashMap::new(),
            requests: HashMap::new(),
            leaf_failures: HashMap::new(),
            next_request: 0,
            delivered: HashSet::new(),
            wanted: Vec::new(),
            wanted_keys: HashSet::new(),
            host_version: 0,
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
        streamer.backend = Some(backend);
        streamer.generation += 1;
        Ok(streamer)
    }

    /// The metadata, once the origin is open.
    pub fn metadata(&self) -> Option<&Metadata> {
        self.backend.as_ref().map(Backend::metadata)
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
            cache_bytes: self.cache.bytes() as u64,
            cache_tiles: self.cache.len() as u64,
            wanted: self.wanted.len() as u64,
            ..self.stats.clone()
        }
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
        if self.backend.is_none() {
            if !self.opening && self.open_retry_at.is_none_or(|t| now >= t) {
                self.start_open();
            }
            return;
        }
        if let Some(Backend::Host(host)) = &self.backend {
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
        self.cancel_unwanted();
        self.issue(now);
        self.cache.trim(&self.wanted_keys);
    }

    /// Ready tiles for this frame, most urgent first, within `budget`; a tile is never
    /// handed over before its parent (unless the parent is unavailable).
    pub fn drain_uploads(&mut self, budget: UploadBudget) -> Vec<Upload> {
        let mut out = Vec::new();
        let mut bytes = 0;
        let Some(metadata) = self.backend.as_ref().map(Backend::metadata) else { return out };
        for (rank, w) in self.wanted.iter().enumerate() {
            if out.len() >= budget.max_tiles {
                break;
            }
            if self.delivered.contains(&w.key) {
                continue;
            }
            let Some(tile) = self.cache.peek(w.key) else { continue };
            let num_lods = metadata.layers[usize::from(w.key.layer())].num_lods;
            if let Some(parent) = w.key.parent().filter(|p| p.lod() < num_lods) {
                if !self.delivered.contains(&parent) && !self.is_unavailable(parent) {
                    continue;
                }
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

    fn start_open(&mut self) {
        self.opening = true;
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
                    if generation != self.generation + 1 {
                        continue;
                    }
                    self.opening = false;
                    match result {
                        Ok(backend) => {
                            self.generation = generation;
                            self.backend = Some(backend);
                            self.open_failures = 0;
                            self.open_retry_at = None;
                        }
                        Err(e) => {
                            tracing::warn!("cannot open the archive: {e}");
                            self.last_error = Some(e.to_string());
                            self.open_failures += 1;
                            self.open_retry_at = Some(now + self.backoff(self.open_failures));
                        }
                    }
                }
                Completion::Changed { generation, what } => {
                    if generation == self.generation {
                        self.reload(&what);
                    }
                }
                Completion::Tiles { request, generation, results, bytes, needed } => {
                    if generation != self.generation {
                        continue;
                    }
                    self.requests.remove(&request);
                    self.stats.bytes_fetched += bytes;
                    self.stats.bytes_needed += needed;
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
                                self.last_error = Some(why);
                                self.states.insert(key, TileState::Undecodable);
                            }
                            Outcome::Failed(why) => {
                                self.stats.failures += 1;
                                tracing::debug!("tile {key}: {why}");
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
                }
                Completion::Leaf { request, generation, offset, failure, bytes } => {
                    if generation != self.generation {
                        continue;
                    }
                    self.requests.remove(&request);
                    self.stats.bytes_fetched += bytes;
                    if let Some(why) = failure {
                        self.stats.failures += 1;
                        self.last_error = Some(why);
                        let failures = self.leaf_failures.get(&offset).map_or(1, |f| f.0 + 1);
                        self.leaf_failures.insert(offset, (failures, now + self.backoff(failures)));
                    } else {
                        self.leaf_failures.remove(&offset);
                    }
                }
            }
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
        self.backend = None;
        self.stats.reloads += 1;
        self.last_error = Some(format!("archive replaced: {what}"));
        self.generation += 1;
        self.origin.forget();
        self.start_open();
    }

    fn cancel_unwanted(&mut self) {
        let wanted = &self.wanted_keys;
        let stale: Vec<u64> = self
            .requests
            .iter()
            .filter(|(_, r)| r.leaf.is_none() && !r.tiles.iter().any(|k| wanted.contains(k)))
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
        let Some(backend) = self.backend.clone() else { return };
        let mut free = self.options.max_in_flight.saturating_sub(self.requests.len());
        if free == 0 {
            return;
        }
        // Candidates, most urgent first; located (for archives) so they can be coalesced.
        let mut candidates: Vec<(usize, TileKey, Option<TileLocation>)> = Vec::new();
        let limit = free * 64;
        for rank in 0..self.wanted.len() {
            let key = self.wanted[rank].key;
            if self.cache.contains(key) {
                continue;
            }
            match self.states.get(&key) {
                Some(TileState::Requested(_)) => continue,
                Some(state) if state.is_settled_without_data() => continue,
                Some(TileState::Failed { retry_at, .. }) if *retry_at > now => continue,
                _ => {}
            }
            match &backend {
                Backend::Archive(reader) => match reader.archive().locate(key) {
                    Ok(Locate::Found(location)) => candidates.push((rank, key, Some(location))),
                    Ok(Locate::Missing) => {
                        self.stats.missing += 1;
                        self.states.insert(key, TileState::Missing);
                    }
                    Ok(Locate::NeedLeaf { offset, len }) => {
                        let waiting = self.leaf_failures.get(&offset).is_some_and(|f| f.1 > now);
                        let fetching = self.requests.values().any(|r| r.leaf == Some(offset));
                        if free > 0 && !waiting && !fetching {
                            free -= 1;
                            self.fetch_leaf(reader.clone(), offset, len);
                        }
                    }
                    Err(e) => {
                        self.stats.failures += 1;
                        self.last_error = Some(e.to_string());
                        let retry_at = now + self.options.max_retry_backoff;
                        self.states.insert(key, TileState::Failed { failures: 16, retry_at });
                    }
                },
                Backend::Endpoint(..) | Backend::Host(_) => candidates.push((rank, key, None)),
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

    /// Splits candidates into requests: runs of tiles whose bytes are at most
    /// `coalesce_gap` apart (archives only), ordered by their most urgent tile.
    fn group(&self, mut candidates: Vec<(usize, TileKey, Option<TileLocation>)>) -> Vec<Group> {
        let mut groups: Vec<Group> = Vec::new();
        let located = candidates.iter().all(|c| c.2.is_some());
        if !located {
            return candidates.into_iter().map(|(rank, key, loc)| Group { rank, tiles: vec![(key, loc)] }).collect();
        }
        candidates.sort_by_key(|c| c.2.map(|l| l.offset));
        for (rank, key, location) in candidates {
            let Some(loc) = location else { continue };
            let end = loc.offset + loc.blob_len();
            if let Some(g) = groups.last_mut() {
                let (start, g_end) = g.span();
                let same_blob = g.tiles.iter().any(|t| t.1.is_some_and(|l| l.offset == loc.offset));
                let close = loc.offset <= g_end + self.options.coalesce_gap
                    && end.max(g_end) - start <= self.options.max_request_bytes;
                if same_blob || (self.options.coalesce && close) {
                    g.rank = g.rank.min(rank);
                    g.tiles.push((key, Some(loc)));
                    continue;
                }
            }
            groups.push(Group { rank, tiles: vec![(key, Some(loc))] });
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
        offset: u64,
        len: u64,
    ) {
        let id = self.next_id();
        let (abort, registration) = AbortHandle::new_pair();
        self.requests.insert(id, InFlight { tiles: Vec::new(), leaf: Some(offset), abort });
        self.stats.requests += 1;
        let (queue, generation) = (self.queue.clone(), self.generation);
        self.spawn(async move {
            let work = async {
                let (failure, bytes) = match reader.source().fetch(offset, len).await {
                    Ok(bytes) => (reader.archive().add_leaf(offset, &bytes).err().map(|e| e.to_string()), bytes.len()),
                    Err(terrastream_format::Error::Changed { what }) => {
                        return Completion::Changed { generation, what };
                    }
                    Err(e) => (Some(e.to_string()), 0),
                };
                Completion::Leaf { request: id, generation, offset, failure, bytes: bytes as u64 }
            };
            if let Ok(c) = Abortable::new(work, registration).await {
                queue.push(c);
            }
        });
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
        self.spawn(async move {
            let work = fetch_and_decode(backend, group, id, generation);
            if let Ok(c) = Abortable::new(work, registration).await {
                queue.push(c);
            }
        });
    }

    /// Height in world units at ground position `(x, z)`, bilinear over the finest
    /// elevation LOD in the cache (sample `i` of a LOD at `(i + 0.5)` spacings, as the
    /// renderer samples); `None` where nothing is loaded or the data has no value.
    pub fn height_at(&self, x: f64, z: f64) -> Option<f64> {
        let (layer, lod) = self.best_elevation(x, z)?;
        self.sample_height(layer, lod, x, z)
    }

    /// Unit surface normal at `(x, z)` from the same data as [`Self::height_at`].
    pub fn normal_at(&self, x: f64, z: f64) -> Option<[f64; 3]> {
        let (layer, lod) = self.best_elevation(x, z)?;
        let info = &self.metadata()?.layers[usize::from(layer)];
        let h = info.world_size_at(lod) / f64::from(info.tile_resolution);
        let at = |dx: f64, dz: f64| self.sample_height(layer, lod, x + dx, z + dz);
        let (l, r, u, d) = (at(-h, 0.0)?, at(h, 0.0)?, at(0.0, -h)?, at(0.0, h)?);
        let n = glam::DVec3::new(-(r - l) / (2.0 * h), 1.0, -(d - u) / (2.0 * h)).normalize();
        Some(n.to_array())
    }

    /// Like [`Self::height_at`] but from LOD 0, fetching the tiles around `(x, z)` now if
    /// they are not loaded (blocks; not for a frame loop).
    ///
    /// # Errors
    /// The origin's error, [`Error::NotOpen`], [`Error::NoLayer`] when there is no elevation
    /// layer, [`Error::Outside`] when the point is outside it, [`Error::TileLoad`].
    #[cfg(not(target_arch = "wasm32"))]
    pub fn height_at_exact(&mut self, x: f64, z: f64) -> Result<Option<f64>> {
        let backend = self.backend.clone().ok_or_else(|| Error::NotOpen { why: self.last_error.clone() })?;
        let metadata = backend.metadata();
        let layer = elevation_layer(metadata).ok_or(Error::NoLayer { kind: "elevation" })?;
        let info = &metadata.layers[usize::from(layer)];
        let spacing = info.tile_world_size / f64::from(info.tile_resolution);
        // The (up to) four tiles holding the bilinear footprint.
        let mut keys = Vec::new();
        for (dx, dz) in [(-1.0, -1.0), (1.0, -1.0), (-1.0, 1.0), (1.0, 1.0)] {
            if let Some(key) = tile_at(metadata, layer, 0, x + dx * spacing, z + dz * spacing) {
                if !keys.contains(&key) && !self.cache.contains(key) {
                    keys.push(key);
                }
            }
        }
        if tile_at(metadata, layer, 0, x, z).is_none() {
            return Err(Error::Outside { layer: info.name.clone(), x, z });
        }
        for key in keys {
            let location = match &backend {
                Backend::Archive(reader) => match self.runtime.block_on(reader.locate(key))? {
                    Some(location) => Some(location),
                    None => continue,
                },
                Backend::Endpoint(..) | Backend::Host(_) => None,
            };
            let group = Group { rank: 0, tiles: vec![(key, location)] };
            let completion = self.runtime.block_on(fetch_and_decode(backend.clone(), group, 0, self.generation));
            match completion {
                Completion::Tiles { results, .. } => {
                    for (key, outcome) in results {
                        match outcome {
                            Outcome::Ready(tile) => self.cache.insert(tile),
                            Outcome::Missing => {}
                            Outcome::Failed(why) | Outcome::Undecodable(why) => {
                                return Err(Error::TileLoad { key, reason: why });
                            }
                        }
                    }
                }
                Completion::Changed { what, .. } => return Err(Error::Changed { what }),
                _ => {}
            }
        }
        Ok(self.sample_height(layer, 0, x, z))
    }

    fn best_elevation(&self, x: f64, z: f64) -> Option<(u8, u8)> {
        let metadata = self.metadata()?;
        let layer = elevation_layer(metadata)?;
        let num_lods = metadata.layers[usize::from(layer)].num_lods;
        (0..num_lods).find_map(|lod| {
            let key = tile_at(metadata, layer, lod, x, z)?;
            self.cache.contains(key).then_some((layer, lod))
        })
    }

    fn sample_height(&self, layer: u8, lod: u8, x: f64, z: f64) -> Option<f64> {
        let metadata = self.metadata()?;
        let info = &metadata.layers[usize::from(layer)];
        let res = info.tile_resolution;
        let spacing = info.world_size_at(lod) / f64::from(res);
        let (nx, ny) = info.grid_at(lod);
        let home = tile_at(metadata, layer, lod, x, z)?;
        let (gx, gz) = (x / spacing - 0.5, z / spacing - 0.5);
        let (i0, j0) = (gx.floor(), gz.floor());
        let (fx, fz) = (gx - i0, gz - j0);
        let max_i = f64::from(nx) * f64::from(res) - 1.0;
        let max_j = f64::from(ny) * f64::from(res) - 1.0;
        let sample = |i: f64, j: f64| -> Option<f64> {
            #[expect(clippy::cast_possible_truncation, reason = "clamped into the grid's u32 range")]
            let (i, j) = (i.clamp(0.0, max_i) as u32, j.clamp(0.0, max_j) as u32);
            let key = TileKey::new(layer, lod, i / res, j / res).ok()?;
            let (tile, li, lj) = match self.cache.peek(key) {
                Some(t) => (t, i % res, j % res),
                // Neighbour not loaded: clamp to the home tile's edge.
                None => {
                    let t = self.cache.peek(home)?;
                    let clamp = |g: u32, t0: u32| g.clamp(t0 * res, t0 * res + res - 1) - t0 * res;
                    (t, clamp(i, home.x()), clamp(j, home.y()))
                }
            };
            let v = tile.height(li + tile.border, lj + tile.border)?;
            v.is_finite().then_some(f64::from(v))
        };
        let corners = [
            (sample(i0, j0), (1.0 - fx) * (1.0 - fz)),
            (sample(i0 + 1.0, j0), fx * (1.0 - fz)),
            (sample(i0, j0 + 1.0), (1.0 - fx) * fz),
            (sample(i0 + 1.0, j0 + 1.0), fx * fz),
        ];
        // Nodata corners drop out and the others are re-weighted.
        let (sum, weight) = corners
            .iter()
            .filter_map(|(v, w)| v.map(|v| (v * w, *w)))
            .fold((0.0, 0.0), |(s, ws), (v, w)| (s + v, ws + w));
        (weight > 1e-12).then(|| sum / weight)
    }
}

impl Drop for Streamer {
    fn drop(&mut self) {
        for (_, r) in self.requests.drain() {
            r.abort.abort();
        }
    }
}

struct Group {
    rank: usize,
    tiles: Vec<(TileKey, Option<TileLocation>)>,
}

impl Group {
    fn span(&self) -> (u64, u64) {
        let locations = self.tiles.iter().filter_map(|t| t.1);
        let start = locations.clone().map(|l| l.offset).min().unwrap_or(0);
        let end = locations.map(|l| l.offset + l.blob_len()).max().unwrap_or(0);
        (start, end)
    }
}

fn elevation_layer(metadata: &Metadata) -> Option<u8> {
    let i = metadata.layers.iter().position(|l| l.kind == LayerKind::Elevation)?;
    u8::try_from(i).ok()
}

/// The tile of `layer` at `lod` holding ground point `(x, z)`.
fn tile_at(metadata: &Metadata, layer: u8, lod: u8, x: f64, z: f64) -> Option<TileKey> {
    let info = metadata.layers.get(usize::from(layer))?;
    let size = info.world_size_at(lod);
    let (tx, tz) = ((x / size).floor(), (z / size).floor());
    let (nx, ny) = info.grid_at(lod);
    if !(tx >= 0.0 && tz >= 0.0 && tx < f64::from(nx) && tz < f64::from(ny)) {
        return None;
    }
    #[expect(clippy::cast_possible_truncation, reason = "checked against the grid above")]
    TileKey::new(layer, lod, tx as u32, tz as u32).ok()
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

/// Fetches a group of tiles (one request) and decodes them off the calling thread.
async fn fetch_and_decode(backend: Backend, group: Group, request: u64, generation: u64) -> Completion {
    let changed = |what| Completion::Changed { generation, what };
    let mut raw: Vec<(TileKey, std::result::Result<Option<Bytes>, String>)> = Vec::new();
    let (mut bytes, mut needed) = (0, 0);
    let compressed;
    match &backend {
        Backend::Archive(reader) => {
            compressed = true;
            let (start, end) = group.span();
            match reader.source().fetch(start, end - start).await {
                Ok(body) => {
                    bytes = body.len() as u64;
                    let mut blobs = HashSet::new();
                    for (key, location) in &group.tiles {
                        let Some(loc) = location else { continue };
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
                }
                Err(terrastream_format::Error::Changed { what }) => return changed(what),
                Err(e) => raw.extend(group.tiles.iter().map(|(k, _)| (*k, Err(e.to_string())))),
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
    let metadata = backend.metadata().clone();
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
    Completion::Tiles { request, generation, results, bytes, needed }
}
