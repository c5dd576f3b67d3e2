//! Opening the origin, backing off, reloading a replaced archive, and asking a manifest
//! whether it was republished.

use super::*;

impl Streamer {
    /// Starts opening the origin (in the background), after `failures` failed attempts.
    pub(super) fn start_open(&mut self, failures: u32) {
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
    pub(super) fn spawn(&self, task: impl Future<Output = ()> + Send + 'static) {
        self.runtime.spawn(task);
    }

    #[cfg(target_arch = "wasm32")]
    pub(super) fn spawn(&self, task: impl Future<Output = ()> + 'static) {
        wasm_bindgen_futures::spawn_local(task);
    }

    pub(super) fn take_completions(&mut self, now: Instant) {
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
    pub(super) fn finished(&mut self, id: u64, took: Duration) {
        let full = self.requests.len() >= self.in_flight.limit(&self.options);
        if self.requests.remove(&id).is_some() {
            self.in_flight.sample(took, full, self.options.max_in_flight);
        }
    }

    /// The origin opened, or failed to (retried with a growing backoff).
    pub(super) fn opened(&mut self, generation: u64, result: Result<Backend>, now: Instant) {
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
    pub(in crate::stream) fn absorb(
        &mut self,
        results: Vec<(TileKey, Outcome)>,
        now: Instant,
    ) -> Option<(TileKey, String)> {
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
    pub(super) fn leaf_done(&mut self, offset: (usize, u64), failure: Option<String>, now: Instant) {
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
    pub(in crate::stream) fn backend(&self) -> Option<&Backend> {
        match &self.link {
            Link::Open(backend) => Some(backend),
            Link::Opening { .. } | Link::Closed { .. } => None,
        }
    }

    pub(super) fn backoff(&self, failures: u32) -> Duration {
        let factor = 1u32 << failures.saturating_sub(1).min(16);
        (self.options.retry_backoff * factor).min(self.options.max_retry_backoff)
    }

    /// The archive was replaced: drop every request, tile and state of the old version
    /// and open the new one.
    pub(super) fn reload(&mut self, what: &str) {
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

    /// Asks a manifest, every `manifest_recheck`, whether it was republished; a new one
    /// makes the streamer re-read everything from it ([`Completion::Changed`]).
    pub(super) fn recheck_manifest(&mut self, now: Instant) {
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
}
