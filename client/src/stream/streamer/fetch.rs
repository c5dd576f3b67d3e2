//! Requests: cancelling what the view no longer wants, issuing the most urgent, grouping
//! neighbouring tiles into one range request, fetching leaves and tiles, decoding them on
//! the worker tasks.

use super::*;

impl Streamer {
    pub(super) fn cancel_unwanted(&mut self) {
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

    pub(super) fn issue(&mut self, now: Instant) {
        let Some(backend) = self.backend().cloned() else { return };
        let mut free = self.in_flight.limit(&self.options).saturating_sub(self.requests.len());
        if free == 0 {
            return;
        }
        // Candidates, most urgent first; located (for archives) so they can be coalesced.
        let mut candidates: Vec<(usize, TileKey, Option<Located>)> = Vec::new();
        let limit = free * 64;
        // What the view wants, then what it will want soon, unless the link is queueing.
        let soon = if self.in_flight.queueing { &[][..] } else { &self.prefetch[..] };
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
    pub(super) fn may_fetch_leaf(&self, leaf: (usize, u64), now: Instant) -> bool {
        let waiting = self.leaf_failures.get(&leaf).is_some_and(|f| f.1 > now);
        !waiting && !self.requests.values().any(|r| r.leaf == Some(leaf))
    }

    /// Splits candidates into requests: runs of tiles of one archive whose bytes are at
    /// most `coalesce_gap` apart, ordered by their most urgent tile.
    pub(super) fn group(&self, mut candidates: Vec<(usize, TileKey, Option<Located>)>) -> Vec<Group> {
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

    pub(super) fn next_id(&mut self) -> u64 {
        self.next_request += 1;
        self.next_request
    }

    pub(super) fn fetch_leaf(
        &mut self,
        reader: Arc<terrastream_format::AsyncReader<crate::stream::origin::DynSource>>,
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
    pub(super) fn open_part(&mut self, parts: Arc<crate::stream::origin::Parts>, part: usize) {
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
    pub(super) fn spawn_leaf(
        &mut self,
        part: usize,
        offset: u64,
        work: impl Future<Output = std::result::Result<(Option<String>, u64), String>> + MaybeSend + 'static,
    ) {
        let task = self.leaf_task(part, offset, work);
        self.spawn(task);
    }

    /// Registers a leaf request and wraps `work` into the task that reports it.
    pub(super) fn leaf_task<W>(&mut self, part: usize, offset: u64, work: W) -> impl Future<Output = ()> + use<W>
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

    pub(super) fn fetch_group(&mut self, backend: &Backend, group: Group) {
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
        let (decoder, shade) = (self.decoder.clone(), self.options.shade);
        self.spawn(async move {
            let work = fetch_and_decode(backend, group, id, generation, decoder, shade);
            if let Ok(c) = Abortable::new(work, registration).await {
                queue.push(c);
            }
        });
    }
}

pub(in crate::stream) struct Group {
    pub(in crate::stream) rank: usize,
    /// Tiles of one archive (located) or of an endpoint or host (not located).
    pub(in crate::stream) tiles: Vec<(TileKey, Option<Located>)>,
}

impl Group {
    /// The archive the tiles are in (0 unless a manifest's).
    pub(in crate::stream) fn part(&self) -> Option<usize> {
        self.tiles.first().and_then(|t| t.1).map(|l| l.0)
    }

    pub(super) fn span(&self) -> (u64, u64) {
        let locations = self.tiles.iter().filter_map(|t| t.1.map(|l| l.1));
        let start = locations.clone().map(|l| l.offset).min().unwrap_or(0);
        let end = locations.map(|l| l.offset + l.blob_len()).max().unwrap_or(0);
        (start, end)
    }
}

/// Decodes one payload. A decoder that panics on some input (a bug: the decoders are
/// fuzzed so as not to) costs that tile, never the worker thread or the page.
/// With `shade`, an elevation tile's shade texels are made too, here, off the frame's
/// thread ([`DecodedTile::shade`]).
pub(super) fn decode_guarded(layer: &Layer, key: TileKey, payload: &[u8], compressed: bool, shade: bool) -> Outcome {
    let attempt = std::panic::catch_unwind(|| {
        let mut tile = decode(layer, key, payload, compressed)?;
        if shade {
            tile.shade(layer);
        }
        Ok::<_, terrastream_tiles::Error>(tile)
    });
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
pub(super) async fn fetch_located(
    reader: &terrastream_format::AsyncReader<crate::stream::origin::DynSource>,
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
pub(super) async fn decode_with(
    decoder: &Decoder,
    metadata: &Metadata,
    raw: Fetched,
    (compressed, shade): (bool, bool),
) -> Vec<(TileKey, Outcome)> {
    let jobs = raw.into_iter().map(|(key, fetched)| {
        let layer = metadata.layers.get(usize::from(key.layer())).cloned();
        let decoder = decoder.clone();
        async move {
            let outcome = match (fetched, layer) {
                (Ok(None), _) => Outcome::Missing,
                (Ok(Some(payload)), Some(layer)) => match decoder(&layer, key, payload.clone(), compressed).await {
                    // A browser's workers make the shade texels as they decode; a decoder
                    // that did not leaves them to the upload.
                    Ok(tile) => Outcome::Ready(Arc::new(tile)),
                    Err(DecodeFailure::Undecodable(why)) => Outcome::Undecodable(why),
                    Err(DecodeFailure::Unavailable) => decode_guarded(&layer, key, &payload, compressed, shade),
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
pub(in crate::stream) async fn fetch_and_decode(
    backend: Backend,
    group: Group,
    request: u64,
    generation: u64,
    decoder: Option<Decoder>,
    shade: bool,
) -> Completion {
    let changed = |what| Completion::Changed { generation, what };
    let started = Instant::now();
    let mut raw: Fetched = Vec::new();
    let (mut bytes, mut needed) = (0, 0);
    let compressed;
    let water = water_layers(backend.metadata());
    match &backend {
        Backend::Archive(_) | Backend::Manifest(_) => {
            compressed = true;
            match group.part().and_then(|part| backend.part_reader(part)) {
                Some(reader) => {
                    match fetch_located(reader, with_water(reader, &group, water.as_ref()).as_ref().unwrap_or(&group))
                        .await
                    {
                        Ok(fetched) => (raw, bytes, needed) = fetched,
                        Err(what) => return changed(what),
                    }
                }
                None => {
                    let why = || Err("the archive holding it is not open".to_owned());
                    raw.extend(group.tiles.iter().map(|(k, _)| (*k, why())));
                }
            }
        }
        Backend::Endpoint(endpoint, _) => {
            compressed = false;
            for key in with_companions(&group, water.as_ref()) {
                match endpoint.tile(key).await {
                    Ok(body) => {
                        let n = body.as_ref().map_or(0, |b| b.len() as u64);
                        bytes += n;
                        needed += n;
                        raw.push((key, Ok(body)));
                    }
                    Err(Error::Changed { what }) => return changed(what),
                    Err(e) => raw.push((key, Err(e.to_string()))),
                }
            }
        }
        Backend::Host(host) => {
            compressed = true;
            for key in with_companions(&group, water.as_ref()) {
                raw.push((key, Ok(host.get(key))));
            }
        }
    }
    let took = started.elapsed();
    let metadata = backend.metadata().clone();
    if let Some(decoder) = decoder {
        let results = decode_with(&decoder, &metadata, raw, (compressed, shade)).await;
        let results = apply_water(water.as_ref(), results);
        return Completion::Tiles { request, generation, results, bytes, needed, took };
    }
    let decode_all = move || -> Vec<(TileKey, Outcome)> {
        raw.into_iter()
            .map(|(key, r)| {
                let outcome = match r {
                    Ok(None) => Outcome::Missing,
                    Ok(Some(payload)) => match metadata.layers.get(usize::from(key.layer())) {
                        Some(layer) => decode_guarded(layer, key, &payload, compressed, shade),
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
    let results = apply_water(water.as_ref(), results);
    Completion::Tiles { request, generation, results, bytes, needed, took }
}

/// An archive's elevation layer and its water layer.
struct Water {
    elevation: u8,
    water: u8,
    layer: Layer,
}

/// The elevation layer and the water layer, where the archive has both.
fn water_layers(metadata: &Metadata) -> Option<Water> {
    use terrastream_format::LayerKind;
    let find = |kind| metadata.layers.iter().position(|l| l.kind == kind).and_then(|i| u8::try_from(i).ok());
    let (elevation, water) = (find(LayerKind::Elevation)?, find(LayerKind::Water)?);
    Some(Water { elevation, water, layer: metadata.layers[usize::from(elevation)].clone() })
}

/// `group` with the water tile of each of its elevation tiles (None where it gains none),
/// where the archive has one and its directory is at hand: the tile right after the
/// elevation tile in the archive's order (FORMAT.md §6), so the range grows by its bytes
/// alone. One whose leaf directory is not loaded is left out (its elevation tile then
/// takes the sea from its heights).
fn with_water(
    reader: &terrastream_format::AsyncReader<crate::stream::origin::DynSource>,
    group: &Group,
    water: Option<&Water>,
) -> Option<Group> {
    let &Water { elevation, water, .. } = water?;
    let mut tiles = group.tiles.clone();
    for (key, located) in &group.tiles {
        let Some((part, _)) = located else { continue };
        if key.layer() != elevation {
            continue;
        }
        let Ok(companion) = TileKey::new(water, key.lod(), key.x(), key.y()) else { continue };
        if tiles.iter().any(|t| t.0 == companion) {
            continue;
        }
        if let Ok(Locate::Found(location)) = reader.archive().locate(companion) {
            tiles.push((companion, Some((*part, location))));
        }
    }
    (tiles.len() > group.tiles.len()).then_some(Group { rank: group.rank, tiles })
}

/// The keys of `group`, each elevation tile's water tile after it (tiles fetched one by
/// one: a tile endpoint, a host's tiles).
fn with_companions(group: &Group, water: Option<&Water>) -> Vec<TileKey> {
    let mut keys = Vec::with_capacity(group.tiles.len() * 2);
    for (key, _) in &group.tiles {
        keys.push(*key);
        if let Some(w) = water.filter(|w| key.layer() == w.elevation)
            && let Ok(companion) = TileKey::new(w.water, key.lod(), key.x(), key.y())
        {
            keys.push(companion);
        }
    }
    keys
}

/// Puts each water tile's fractions into the shade texels of the elevation tile with the
/// same LOD, x and y ([`terrastream_tiles::DecodedTile::set_water`]) and leaves the water
/// tiles out of the results: they are not tiles the streamer asked for.
fn apply_water(water: Option<&Water>, results: Vec<(TileKey, Outcome)>) -> Vec<(TileKey, Outcome)> {
    let Some(&Water { elevation, water, ref layer }) = water else { return results };
    let (fractions, mut results): (Vec<_>, Vec<_>) = results.into_iter().partition(|(k, _)| k.layer() == water);
    let fractions: HashMap<(u8, u32, u32), Arc<DecodedTile>> = fractions
        .into_iter()
        .filter_map(|(k, o)| match o {
            Outcome::Ready(tile) => Some(((k.lod(), k.x(), k.y()), tile)),
            _ => None,
        })
        .collect();
    for (key, outcome) in &mut results {
        let Outcome::Ready(tile) = outcome else { continue };
        if key.layer() != elevation {
            continue;
        }
        if let Some(w) = fractions.get(&(key.lod(), key.x(), key.y())) {
            // Just decoded, the tile has no other owner: changed where it is.
            Arc::make_mut(tile).set_water(layer, w);
        }
    }
    results
}
