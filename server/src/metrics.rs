//! Prometheus metrics: requests by status, bytes, errors and a latency histogram per route.
//! Lock-free: every counter is an atomic in a table fixed at compile time, so recording
//! costs a few relaxed increments per request.

use std::fmt::Write;
use std::sync::atomic::{AtomicU64, Ordering::Relaxed};
use std::time::Duration;

/// Routes of the application, as axum's matched-path templates; "other" for the rest.
pub const ROUTES: [&str; 8] = [
    "/",
    "/healthz",
    "/metrics",
    "/{file}",
    "/{name}/metadata",
    "/{name}/{layer}/{lod}/{x}/{y}",
    "/view/{name}",
    "other",
];
/// Status codes counted one by one; any other lands in "other".
const STATUSES: [u16; 20] =
    [200, 204, 206, 301, 302, 304, 400, 403, 404, 405, 408, 412, 413, 416, 429, 431, 500, 502, 503, 504];
/// Upper bounds of the latency buckets, in seconds.
const BUCKETS: [f64; 12] = [0.0001, 0.00025, 0.0005, 0.001, 0.0025, 0.005, 0.01, 0.025, 0.05, 0.1, 0.5, 2.5];

#[derive(Debug, Default)]
struct RouteStats {
    by_status: [AtomicU64; STATUSES.len() + 1],
    bytes: AtomicU64,
    buckets: [AtomicU64; BUCKETS.len()],
    count: AtomicU64,
    sum_nanos: AtomicU64,
}

/// Counters shared by all requests.
#[derive(Debug, Default)]
pub struct Metrics {
    routes: [RouteStats; ROUTES.len()],
}

/// Index of a route template in [`ROUTES`] ("other" for anything else).
pub fn route_index(route: &str) -> usize {
    ROUTES.iter().position(|r| *r == route).unwrap_or(ROUTES.len() - 1)
}

impl Metrics {
    /// Records one answered request.
    pub fn record(&self, route: &str, status: u16, bytes: u64, latency: Duration) {
        self.record_at(route_index(route), status, bytes, latency);
    }

    /// Records one answered request on the route at `index` (see [`route_index`]).
    pub fn record_at(&self, index: usize, status: u16, bytes: u64, latency: Duration) {
        let s = &self.routes[index.min(ROUTES.len() - 1)];
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

    /// Requests answered on a route (all statuses); tests and caches use it.
    pub fn requests(&self, route: &str) -> u64 {
        self.routes[route_index(route)].count.load(Relaxed)
    }

    /// The Prometheus text exposition.
    pub fn render(&self, archives: usize) -> String {
        let mut out = String::new();
        let _ = writeln!(out, "# HELP terrastream_archives Archives being served.\n# TYPE terrastream_archives gauge");
        let _ = writeln!(out, "terrastream_archives {archives}");
        let used: Vec<(&str, &RouteStats)> =
            ROUTES.iter().copied().zip(&self.routes).filter(|(_, s)| s.count.load(Relaxed) > 0).collect();
        let _ = writeln!(
            out,
            "# HELP terrastream_requests_total Requests answered.\n# TYPE terrastream_requests_total counter"
        );
        for (route, s) in &used {
            for (i, n) in s.by_status.iter().enumerate() {
                let n = n.load(Relaxed);
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
            let errors: u64 =
                STATUSES.iter().zip(&s.by_status).filter(|(code, _)| **code >= 500).map(|(_, n)| n.load(Relaxed)).sum();
            let _ = writeln!(out, "terrastream_errors_total{{route=\"{route}\"}} {errors}");
        }
        let _ = writeln!(
            out,
            "# HELP terrastream_response_bytes_total Body bytes sent.\n# TYPE terrastream_response_bytes_total counter"
        );
        for (route, s) in &used {
            let _ = writeln!(out, "terrastream_response_bytes_total{{route=\"{route}\"}} {}", s.bytes.load(Relaxed));
        }
        let _ = writeln!(
            out,
            "# HELP terrastream_request_duration_seconds Time to answer.\n# TYPE terrastream_request_duration_seconds histogram"
        );
        for (route, s) in &used {
            let mut cumulative = 0;
            for (bound, n) in BUCKETS.iter().zip(&s.buckets) {
                cumulative += n.load(Relaxed);
                let _ = writeln!(
                    out,
                    "terrastream_request_duration_seconds_bucket{{route=\"{route}\",le=\"{bound}\"}} {cumulative}"
                );
            }
            let count = s.count.load(Relaxed);
            let sum = s.sum_nanos.load(Relaxed) as f64 / 1e9;
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
        m.record("/{file}", 206, 10, Duration::from_micros(50));
        m.record("/{file}", 206, 5, Duration::from_millis(3));
        m.record("/{file}", 599, 0, Duration::from_secs(9));
        m.record("/nope", 404, 0, Duration::from_micros(1));
        let text = m.render(1);
        assert!(text.contains("terrastream_requests_total{route=\"/{file}\",status=\"206\"} 2"), "{text}");
        assert!(text.contains("terrastream_requests_total{route=\"/{file}\",status=\"other\"} 1"), "{text}");
        assert!(text.contains("route=\"/{file}\",le=\"0.0001\"} 1"), "{text}");
        assert!(text.contains("route=\"/{file}\",le=\"0.005\"} 2"), "{text}");
        assert!(text.contains("route=\"/{file}\",le=\"+Inf\"} 3"), "{text}");
        assert!(text.contains("terrastream_response_bytes_total{route=\"/{file}\"} 15"), "{text}");
        assert_eq!(m.requests("other"), 1);
    }
}
