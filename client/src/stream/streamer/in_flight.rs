//! The adaptive in-flight limit.

use super::*;

/// The in-flight limit, adapted to the link as a delay-based congestion control does: a
/// request that comes back about as fast as the fastest so far, while the limit was all
/// used, means the link has room (one more request in flight); one that takes three times
/// as long means requests queue at the bottleneck (15 % fewer). Over a long, fast link this
/// fills the bandwidth-delay product with requests; over a slow one it keeps few enough in
/// flight that the most urgent tiles are not stuck behind less urgent ones.
#[derive(Clone, Debug)]
pub(super) struct InFlightLimit {
    pub(super) limit: f64,
    /// The fastest round trip seen, slowly forgotten (a route may change).
    pub(super) base: Option<Duration>,
    /// The last fetch took well over the base: requests queue at the bottleneck, and
    /// bandwidth spent on prefetch is taken from the view.
    pub(super) queueing: bool,
}

impl InFlightLimit {
    const START: f64 = 8.0;
    const LOWEST: f64 = 2.0;

    pub(super) fn new(max: usize) -> Self {
        Self { limit: Self::START.min(max as f64), base: None, queueing: false }
    }

    #[expect(clippy::cast_possible_truncation, clippy::cast_sign_loss, reason = "between 2 and a usize cap")]
    pub(super) fn limit(&self, options: &StreamOptions) -> usize {
        if options.adaptive_in_flight {
            (self.limit as usize).clamp(1, options.max_in_flight)
        } else {
            options.max_in_flight
        }
    }

    /// A request came back after `rtt`; `full`: the limit was all in use when it did.
    pub(super) fn sample(&mut self, rtt: Duration, full: bool, max: usize) {
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

#[cfg(test)]
mod tests {
    use std::time::Duration;

    use super::InFlightLimit;

    const MS: Duration = Duration::from_millis(1);

    #[expect(clippy::cast_possible_truncation, clippy::cast_sign_loss, reason = "a small positive limit")]
    fn limit(flow: &InFlightLimit) -> usize {
        flow.limit as usize
    }

    #[test]
    fn the_in_flight_limit_grows_on_a_free_link_and_backs_off_when_requests_queue() {
        let mut flow = InFlightLimit::new(32);
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
        assert_eq!(limit(&InFlightLimit::new(4)), 4);
    }
}
