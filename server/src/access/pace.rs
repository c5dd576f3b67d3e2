//! The pace of refusals: every refusal (401, 403, 429) the server makes shares one
//! budget, `refusal_rate` a second with a burst of `refusal_burst`; a refusal beyond it is
//! held until its turn comes (at most [`MAX_HOLD`]) before it is answered.
//!
//! A flood of bad credentials then costs the server what that rate costs, however fast
//! its clients send: each of the flood's connections waits for its answer before it can
//! send the next request (a closed refusal's client waits before it reconnects), so
//! requests with valid credentials keep the cores. Valid requests never wait on it.
//!
//! A GCRA (the token bucket as one "theoretical arrival time"), lock-free: one atomic
//! per refusal, none per allowed request.

use std::sync::atomic::{AtomicU64, Ordering};
use std::time::{Duration, Instant};

/// Longest a refusal is held. Beyond it a refusal is answered after this long without
/// taking a turn (so a queue of attackers cannot push turns past any bound).
pub const MAX_HOLD: Duration = Duration::from_secs(1);

/// Refusals' shared pace.
#[derive(Debug)]
pub(super) struct Pace {
    /// Nanoseconds between turns.
    interval: u64,
    /// Nanoseconds of turns that may be taken at once (the burst).
    tolerance: u64,
    /// Origin of the clock below.
    start: Instant,
    /// When the next turn is free, in nanoseconds from `start`.
    next: AtomicU64,
}

impl Pace {
    /// `rate` refusals a second, `burst` at once; None where `rate` is not positive (no
    /// pace: refusals answered at once).
    pub(super) fn new(rate: u32, burst: u32) -> Option<Self> {
        if rate == 0 {
            return None;
        }
        let interval = 1_000_000_000 / u64::from(rate);
        let tolerance = interval.saturating_mul(u64::from(burst.max(1)) - 1);
        Some(Self { interval, tolerance, start: Instant::now(), next: AtomicU64::new(0) })
    }

    /// How long to hold a refusal made at `now` before answering it (zero within the
    /// burst).
    pub(super) fn hold(&self, now: Instant) -> Duration {
        #[expect(clippy::cast_possible_truncation, reason = "u64 nanoseconds: 584 years of uptime")]
        let t = now.saturating_duration_since(self.start).as_nanos() as u64;
        let mut next = self.next.load(Ordering::Relaxed);
        loop {
            let turn = next.max(t);
            let wait = turn.saturating_sub(t.saturating_add(self.tolerance));
            if u128::from(wait) > MAX_HOLD.as_nanos() {
                return MAX_HOLD;
            }
            match self.next.compare_exchange_weak(next, turn + self.interval, Ordering::Relaxed, Ordering::Relaxed) {
                Ok(_) => return Duration::from_nanos(wait),
                Err(seen) => next = seen,
            }
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_burst_then_one_turn_per_interval_then_the_cap() {
        let pace = Pace::new(100, 5).unwrap();
        let t0 = pace.start + Duration::from_secs(10);
        for _ in 0..5 {
            assert_eq!(pace.hold(t0), Duration::ZERO, "within the burst");
        }
        // The sixth waits one interval (10 ms), the seventh two.
        assert_eq!(pace.hold(t0), Duration::from_millis(10));
        assert_eq!(pace.hold(t0), Duration::from_millis(20));
        // Later, the turns have come back.
        assert_eq!(pace.hold(t0 + Duration::from_secs(1)), Duration::ZERO);
        // A crowd: holds grow to the cap and stay there.
        let holds: Vec<Duration> = (0..300).map(|_| pace.hold(t0 + Duration::from_secs(1))).collect();
        assert!(holds.windows(2).all(|w| w[0] <= w[1]), "holds grow");
        assert_eq!(*holds.last().unwrap(), MAX_HOLD);
        assert!(Pace::new(0, 10).is_none(), "rate 0: no pace");
    }
}
