//! Prometheus metrics: requests by status, bytes, errors and a latency histogram per route.
//! Lock-free: every counter is an atomic in a table fixed at compile time, so recording
//! costs a few relaxed increments per request. The table is sharded: each thread counts in
//! its own cache-line-aligned copy (summed when rendered), so serving threads never write
//! to the same cache line.
//!
//! Also the open connections of each serving thread ([`Connections`]): counted when a
//! connection is accepted and when it closes, and used to keep the threads even.

use std::fmt::Write;
use std::sync::atomic::{AtomicU64, AtomicUsize, Ordering::Relaxed};
use std::sync::{Arc, Mutex, PoisonError};
use std::time::Duration;

use crate::route::Route;

/// Status codes counted one by one; any other lands in "other".
const STATUSES: [u16; 20] =
    [200, 204, 206, 301, 302, 304, 400, 403, 404, 405, 408, 412, 413, 416, 429, 431, 500, 502, 503, 504];
/// Upper bounds of the latency buckets, in seconds.
const BUCKETS: [f64; 12] = [0.0001, 0.00025, 0.0005, 0.001, 0.0025, 0.005, 0.01, 0.025, 0.05, 0.1, 0.5, 2.5];

#[derive(Debug, Default)]
struct RouteStats<T = AtomicU64> {
    by_status: [T; STATUSES.len() + 1],
    bytes: T,
    buckets: [T; BUCKETS.len()],
    count: T,
    sum_nanos: T,
}

impl RouteStats {
    /// Adds this shard's counts to `total`.
    fn add_to(&self, total: &mut RouteStats<u64>) {
        let add = |t: &mut u64, a: &AtomicU64| *t += a.load(Relaxed);
        total.by_status.iter_mut().zip(&self.by_status).for_each(|(t, a)| add(t, a));
        total.buckets.iter_mut().zip(&self.buckets).for_each(|(t, a)| add(t, a));
        add(&mut total.bytes, &self.bytes);
        add(&mut total.count, &self.count);
        add(&mut total.sum_nanos, &self.sum_nanos);
    }
}

/// Shards of the counters: threads are spread over them round-robin.
const SHARDS: usize = 16;

/// One thread's copy of the table, on its own cache lines.
#[derive(Debug, Default)]
#[repr(align(128))]
struct Shard([RouteStats; Route::ALL.len()]);

/// Counters shared by all requests.
#[derive(Debug)]
pub struct Metrics {
    shards: Box<[Shard]>,
    /// The serving threads' connections, once a server runs.
    connections: Mutex<Option<Arc<Connections>>>,
}

impl Default for Metrics {
    fn default() -> Self {
        Self { shards: (0..SHARDS).map(|_| Shard::default()).collect(), connections: Mutex::new(None) }
    }
}

/// A counter on its own cache line.
#[derive(Debug, Default)]
#[repr(align(128))]
struct Padded(AtomicUsize);

/// Open connections of each serving thread, and the rule that keeps them even.
///
/// The kernel picks the thread of a new connection (see `serve_workers`); a thread that
/// accepts one while it serves [`Connections::SLACK`] more than the least busy thread
/// hands it to that thread instead — unless that thread has connections of its own
/// waiting to be accepted (then the counts lag behind the kernel's choices, as when many
/// clients connect at once). No choice of the kernel's can load one thread with every
/// connection.
#[derive(Debug)]
pub(crate) struct Connections {
    open: Box<[Padded]>,
    handed: AtomicU64,
}

impl Connections {
    /// How many more connections than the least busy thread a thread keeps for itself.
    ///
    /// Counts lag behind the kernel's choices: when one client thread opens its
    /// connections a moment before another, the first serving thread has accepted them all
    /// before any of the second one's arrive. A small slack would hand those away and split
    /// each client thread's connections over the serving threads again; a large one leaves
    /// more of an imbalance the kernel makes. 32: a browser opens 6 connections to a host,
    /// a load generator or prefetching client a few dozen per thread.
    pub const SLACK: usize = 32;

    /// No connections yet, on `threads` threads.
    pub fn new(threads: usize) -> Self {
        Self { open: (0..threads.max(1)).map(|_| Padded::default()).collect(), handed: AtomicU64::new(0) }
    }

    /// The thread that serves a connection `thread` accepted, counted as open there until
    /// the returned seat is dropped. `accepting(t)`: whether connections wait for thread `t`
    /// to accept them.
    pub fn seat(self: &Arc<Self>, thread: usize, accepting: impl Fn(usize) -> bool) -> Seat {
        let mine = self.open[thread].0.load(Relaxed);
        let (least, fewest) =
            self.open.iter().map(|c| c.0.load(Relaxed)).enumerate().min_by_key(|&(_, n)| n).unwrap_or((thread, mine));
        let thread = if mine >= fewest + Self::SLACK && !accepting(least) {
            self.handed.fetch_add(1, Relaxed);
            least
        } else {
            thread
        };
        self.open[thread].0.fetch_add(1, Relaxed);
        Seat { connections: Arc::clone(self), thread }
    }

    /// Open connections, by thread.
    pub fn open(&self) -> Vec<usize> {
        self.open.iter().map(|c| c.0.load(Relaxed)).collect()
    }

    /// Connections handed from the thread that accepted them to another.
    pub fn handed(&self) -> u64 {
        self.handed.load(Relaxed)
    }
}

/// One open connection, counted on its thread until dropped.
#[derive(Debug)]
pub(crate) struct Seat {
    connections: Arc<Connections>,
    thread: usize,
}

impl Seat {
    /// The thread that serves the connection.
    pub fn thread(&self) -> usize {
        self.thread
    }
}

impl Drop for Seat {
    fn drop(&mut self) {
        self.connections.open[self.thread].0.fetch_sub(1, Relaxed);
    }
}

/// The shard of the calling thread.
fn shard_index() -> usize {
    use std::sync::atomic::AtomicUsize;
    static NEXT: AtomicUsize = AtomicUsize::new(0);
    thread_local! {
        static SHARD: usize = NEXT.fetch_add(1, Relaxed) % SHARDS;
    }
    SHARD.with(|s| *s)
}

impl Metrics {
    /// Records one answered request.
    pub fn record(&self, route: Route, status: u16, bytes: u64, latency: Duration) {
        let s = &self.shards[shard_index()].0[route.index()];
        let status_slot = STATUSES.iter().position(|&c| c == status).unwrap_or(STATUSES.len());
        s.by_status[status_slot].fetch_add(1, Relaxed);
        s.bytes.fetch_add(bytes, Relaxed);
        let secs = latency.as_secs_f64();
        // Cumulative buckets are summed at render time: one increment here.
        if let Some(b) = BUCKETS.iter().position(|&bound| secs <= bound) {
            s.buckets[b].fetch_add(1, Relaxed);
        }
        s.count.fetch_add(1, Relaxed);
        s.sum_nanos.fetch_add(u64::try_from(latency.as_nanos()).unwrap_or(u64::MAX), Relaxed);
    }

    /// Requests answered on the route of a template (all statuses); tests and caches use it.
    pub fn requests(&self, template: &str) -> u64 {
        self.totals()[Route::from_template(template).index()].count
    }

    /// Every route's counts, summed over the shards.
    fn totals(&self) -> [RouteStats<u64>; Route::ALL.len()] {
        let mut totals: [RouteStats<u64>; Route::ALL.len()] = Default::default();
        for shard in &self.shards {
            shard.0.iter().zip(&mut totals).for_each(|(s, t)| s.add_to(t));
        }
        totals
    }

    /// Reports the open connections of `connections` from now on.
    pub(crate) fn watch_connections(&self, connections: Arc<Connections>) {
        *self.connections.lock().unwrap_or_else(PoisonError::into_inner) = Some(connections);
    }

    /// The Prometheus text exposition.
    pub fn render(&self, archives: usize) -> String {
        let mut out = String::new();
        let _ = writeln!(out, "# HELP terrastream_archives Archives being served.\n# TYPE terrastream_archives gauge");
        let _ = writeln!(out, "terrastream_archives {archives}");
        if let Some(connections) = self.connections.lock().unwrap_or_else(PoisonError::into_inner).as_ref() {
            let _ = writeln!(
                out,
                "# HELP terrastream_connections Open connections, by serving thread.\n# TYPE terrastream_connections gauge"
            );
            for (thread, n) in connections.open().iter().enumerate() {
                let _ = writeln!(out, "terrastream_connections{{thread=\"{thread}\"}} {n}");
            }
            let _ = writeln!(
                out,
                "# HELP terrastream_connections_handed_total Connections handed by the thread that accepted them to a less busy one.\n# TYPE terrastream_connections_handed_total counter"
            );
            let _ = writeln!(out, "terrastream_connections_handed_total {}", connections.handed());
        }
        let totals = self.totals();
        let used: Vec<(&str, &RouteStats<u64>)> =
            Route::ALL.iter().map(|r| r.template()).zip(&totals).filter(|(_, s)| s.count > 0).collect();
        let _ = writeln!(
            out,
            "# HELP terrastream_requests_total Requests answered.\n# TYPE terrastream_requests_total counter"
        );
        for (route, s) in &used {
            for (i, &n) in s.by_status.iter().enumerate() {
                if n > 0 {
                    let status = STATUSES.get(i).map_or_else(|| "other".to_owned(), u16::to_string);
                    let _ = writeln!(out, "terrastream_requests_total{{route=\"{route}\",status=\"{status}\"}} {n}");
                }
            }
        }
        let _ = writeln!(
            out,
            "# HELP terrastream_errors_total Requests answered 5xx.\n# TYPE terrastream_errors_total counter"
        );
        for (route, s) in &used {
            let errors: u64 = STATUSES.iter().zip(&s.by_status).filter(|(code, _)| **code >= 500).map(|(_, n)| n).sum();
            let _ = writeln!(out, "terrastream_errors_total{{route=\"{route}\"}} {errors}");
        }
        let _ = writeln!(
            out,
            "# HELP terrastream_response_bytes_total Body bytes sent.\n# TYPE terrastream_response_bytes_total counter"
        );
        for (route, s) in &used {
            let _ = writeln!(out, "terrastream_response_bytes_total{{route=\"{route}\"}} {}", s.bytes);
        }
        let _ = writeln!(
            out,
            "# HELP terrastream_sendfile_bytes_total Body bytes sent from the archive file by sendfile (no copy).\n# TYPE terrastream_sendfile_bytes_total counter"
        );
        let _ = writeln!(out, "terrastream_sendfile_bytes_total {}", crate::sendfile::sent_bytes());
        let _ = writeln!(
            out,
            "# HELP terrastream_request_duration_seconds Time to answer.\n# TYPE terrastream_request_duration_seconds histogram"
        );
        for (route, s) in &used {
            let mut cumulative = 0;
            for (bound, n) in BUCKETS.iter().zip(&s.buckets) {
                cumulative += n;
                let _ = writeln!(
                    out,
                    "terrastream_request_duration_seconds_bucket{{route=\"{route}\",le=\"{bound}\"}} {cumulative}"
                );
            }
            let count = s.count;
            let sum = s.sum_nanos as f64 / 1e9;
            let _ =
                writeln!(out, "terrastream_request_duration_seconds_bucket{{route=\"{route}\",le=\"+Inf\"}} {count}");
            let _ = writeln!(out, "terrastream_request_duration_seconds_sum{{route=\"{route}\"}} {sum}");
            let _ = writeln!(out, "terrastream_request_duration_seconds_count{{route=\"{route}\"}} {count}");
        }
        out
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn buckets_are_cumulative_and_statuses_counted() {
        let m = Metrics::default();
        m.record(Route::Archive, 206, 10, Duration::from_micros(50));
        m.record(Route::Archive, 206, 5, Duration::from_millis(3));
        m.record(Route::Archive, 599, 0, Duration::from_secs(9));
        m.record(Route::Other, 404, 0, Duration::from_micros(1));
        let text = m.render(1);
        assert!(text.contains("terrastream_requests_total{route=\"/{file}\",status=\"206\"} 2"), "{text}");
        assert!(text.contains("terrastream_requests_total{route=\"/{file}\",status=\"other\"} 1"), "{text}");
        assert!(text.contains("route=\"/{file}\",le=\"0.0001\"} 1"), "{text}");
        assert!(text.contains("route=\"/{file}\",le=\"0.005\"} 2"), "{text}");
        assert!(text.contains("route=\"/{file}\",le=\"+Inf\"} 3"), "{text}");
        assert!(text.contains("terrastream_response_bytes_total{route=\"/{file}\"} 15"), "{text}");
        assert_eq!(m.requests("other"), 1);
    }

    #[test]
    fn counts_from_many_threads_are_summed_over_the_shards() {
        let m = Metrics::default();
        std::thread::scope(|scope| {
            for _ in 0..2 * SHARDS + 3 {
                scope.spawn(|| {
                    for _ in 0..100 {
                        m.record(Route::Archive, 206, 2, Duration::from_micros(50));
                    }
                });
            }
        });
        let n = (2 * SHARDS + 3) as u64 * 100;
        assert_eq!(m.requests("/{file}"), n);
        let text = m.render(1);
        assert!(text.contains(&format!("terrastream_response_bytes_total{{route=\"/{{file}}\"}} {}", 2 * n)), "{text}");
    }

    #[test]
    fn connections_stay_within_the_slack_of_the_least_busy_thread() {
        let connections = Arc::new(Connections::new(3));
        // Every connection accepted by thread 0, as when the kernel picks one thread.
        let seats: Vec<Seat> = (0..200).map(|_| connections.seat(0, |_| false)).collect();
        let open = connections.open();
        assert_eq!(open.iter().sum::<usize>(), 200);
        let (most, fewest) = (open.iter().max().unwrap(), open.iter().min().unwrap());
        assert!(most - fewest <= Connections::SLACK, "{open:?}");
        assert_eq!(connections.handed(), 200 - open[0] as u64);
        assert!(seats.iter().all(|s| s.thread() < 3));
        drop(seats);
        assert_eq!(connections.open(), [0, 0, 0]);
        // A thread that has connections of its own waiting to be accepted is given none.
        let seats: Vec<Seat> = (0..100).map(|_| connections.seat(1, |t| t != 1)).collect();
        assert_eq!(connections.open(), [0, 100, 0]);
        assert_eq!(connections.handed(), 200 - open[0] as u64);
        drop(seats);
        let m = Metrics::default();
        assert!(!m.render(0).contains("terrastream_connections"));
        m.watch_connections(Arc::clone(&connections));
        let _seat = connections.seat(2, |_| false);
        let text = m.render(0);
        assert!(text.contains("terrastream_connections{thread=\"2\"} 1\n"), "{text}");
        assert!(text.contains("terrastream_connections{thread=\"0\"} 0\n"), "{text}");
        assert!(text.contains(&format!("terrastream_connections_handed_total {}\n", connections.handed())), "{text}");
    }
}
