//! Prometheus metrics: requests, bytes, errors and a latency histogram per route.

use std::collections::BTreeMap;
use std::fmt::Write;
use std::sync::Mutex;
use std::time::Duration;

/// Upper bounds of the latency buckets, in seconds.
const BUCKETS: [f64; 12] = [0.0001, 0.00025, 0.0005, 0.001, 0.0025, 0.005, 0.01, 0.025, 0.05, 0.1, 0.5, 2.5];

#[derive(Debug, Default, Clone)]
struct RouteStats {
    by_status: BTreeMap<u16, u64>,
    bytes: u64,
    buckets: [u64; BUCKETS.len()],
    count: u64,
    sum_secs: f64,
}

/// Counters shared by all requests. One short lock per request: cheap next to the I/O.
#[derive(Debug, Default)]
pub struct Metrics {
    routes: Mutex<BTreeMap<String, RouteStats>>,
}

impl Metrics {
    /// Records one answered request.
    pub fn record(&self, route: &str, status: u16, bytes: u64, latency: Duration) {
        let mut routes = self.routes.lock().unwrap_or_else(std::sync::PoisonError::into_inner);
        let s = routes.entry(route.to_owned()).or_default();
        *s.by_status.entry(status).or_default() += 1;
        s.bytes += bytes;
        let secs = latency.as_secs_f64();
        for (bucket, bound) in s.buckets.iter_mut().zip(BUCKETS) {
            if secs <= bound {
                *bucket += 1;
            }
        }
        s.count += 1;
        s.sum_secs += secs;
    }

    /// Requests answered on a route (all statuses); tests and caches use it.
    pub fn requests(&self, route: &str) -> u64 {
        self.routes.lock().unwrap_or_else(std::sync::PoisonError::into_inner).get(route).map_or(0, |s| s.count)
    }

    /// The Prometheus text exposition.
    pub fn render(&self, archives: usize) -> String {
        let routes = self.routes.lock().unwrap_or_else(std::sync::PoisonError::into_inner).clone();
        let mut out = String::new();
        let _ = writeln!(out, "# HELP terrastream_archives Archives being served.\n# TYPE terrastream_archives gauge");
        let _ = writeln!(out, "terrastream_archives {archives}");
        let _ = writeln!(
            out,
            "# HELP terrastream_requests_total Requests answered.\n# TYPE terrastream_requests_total counter"
        );
        for (route, s) in &routes {
            for (status, n) in &s.by_status {
                let _ = writeln!(out, "terrastream_requests_total{{route=\"{route}\",status=\"{status}\"}} {n}");
            }
        }
        let _ = writeln!(
            out,
            "# HELP terrastream_errors_total Requests answered 5xx.\n# TYPE terrastream_errors_total counter"
        );
        for (route, s) in &routes {
            let errors: u64 = s.by_status.iter().filter(|(st, _)| **st >= 500).map(|(_, n)| n).sum();
            let _ = writeln!(out, "terrastream_errors_total{{route=\"{route}\"}} {errors}");
        }
        let _ = writeln!(
            out,
            "# HELP terrastream_response_bytes_total Body bytes sent.\n# TYPE terrastream_response_bytes_total counter"
        );
        for (route, s) in &routes {
            let _ = writeln!(out, "terrastream_response_bytes_total{{route=\"{route}\"}} {}", s.bytes);
        }
        let _ = writeln!(
            out,
            "# HELP terrastream_request_duration_seconds Time to answer.\n# TYPE terrastream_request_duration_seconds histogram"
        );
        for (route, s) in &routes {
            for (bound, n) in BUCKETS.iter().zip(s.buckets) {
                let _ = writeln!(
                    out,
                    "terrastream_request_duration_seconds_bucket{{route=\"{route}\",le=\"{bound}\"}} {n}"
                );
            }
            let _ = writeln!(
                out,
                "terrastream_request_duration_seconds_bucket{{route=\"{route}\",le=\"+Inf\"}} {}",
                s.count
            );
            let _ = writeln!(out, "terrastream_request_duration_seconds_sum{{route=\"{route}\"}} {}", s.sum_secs);
            let _ = writeln!(out, "terrastream_request_duration_seconds_count{{route=\"{route}\"}} {}", s.count);
        }
        out
    }
}
