//! Each key's rate: a token bucket of `burst` requests refilled at `rate` a second.

use std::collections::HashMap;
use std::sync::Mutex;
use std::time::Instant;

use super::keys::KeyRecord;

/// The buckets, by key id.
#[derive(Debug, Default)]
pub(super) struct Limiter {
    buckets: Mutex<HashMap<String, Bucket>>,
}

#[derive(Clone, Copy, Debug)]
struct Bucket {
    tokens: f64,
    at: Instant,
}

impl Limiter {
    /// Takes one request from `key`'s bucket at `now`; Err: the whole seconds until one is
    /// there again. A key without a rate is never limited.
    pub(super) fn take(&self, key: &KeyRecord, now: Instant) -> Result<(), u64> {
        let Some(rate) = key.rate else { return Ok(()) };
        let burst = key.burst.unwrap_or(rate).max(1.0);
        let mut buckets = self.buckets.lock().unwrap_or_else(std::sync::PoisonError::into_inner);
        let bucket = buckets.entry(key.id.clone()).or_insert(Bucket { tokens: burst, at: now });
        let refilled = now.saturating_duration_since(bucket.at).as_secs_f64() * rate;
        bucket.tokens = (bucket.tokens + refilled).min(burst);
        bucket.at = now;
        if bucket.tokens >= 1.0 {
            bucket.tokens -= 1.0;
            Ok(())
        } else {
            #[expect(clippy::cast_possible_truncation, clippy::cast_sign_loss, reason = "a few seconds, rounded up")]
            let wait = ((1.0 - bucket.tokens) / rate).ceil().max(1.0) as u64;
            Err(wait)
        }
    }
}

#[cfg(test)]
mod tests {
    use std::time::Duration;

    use super::*;

    #[test]
    fn a_burst_then_the_rate() {
        let key = KeyRecord {
            id: "00000001".into(),
            rate: Some(2.0),
            burst: Some(3.0),
            ..KeyRecord::opening(Vec::<String>::new())
        };
        let limiter = Limiter::default();
        let t0 = Instant::now();
        for _ in 0..3 {
            assert_eq!(limiter.take(&key, t0), Ok(()));
        }
        assert_eq!(limiter.take(&key, t0), Err(1));
        assert_eq!(limiter.take(&key, t0 + Duration::from_millis(500)), Ok(()), "half a second: one more");
        assert!(limiter.take(&key, t0 + Duration::from_millis(500)).is_err());
        let free = KeyRecord { rate: None, ..key };
        assert!((0..100).all(|_| limiter.take(&free, t0).is_ok()));
    }
}
