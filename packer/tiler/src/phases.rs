//! A run's phases as `tile -v` reports them: how long each took and how many cores it
//! kept busy, which shows the part of a run that more cores do not shorten.

use std::sync::{Mutex, PoisonError};
use std::time::{Duration, Instant};

/// The clock of one run: marks the end of each phase.
pub(crate) struct Phases {
    started: Instant,
    /// The process's CPU time when the run started.
    cpu: Option<Duration>,
    /// When the last phase ended, and the process's CPU time then.
    last: Mutex<(Instant, Option<Duration>)>,
}

impl Phases {
    /// A run starting now.
    pub(crate) fn start() -> Self {
        let (now, cpu) = (Instant::now(), process_cpu());
        Self { started: now, cpu, last: Mutex::new((now, cpu)) }
    }

    /// Logs the whole run (at debug level: `-v`): its wall time, the cores it kept busy
    /// and its busy share, those over the cores the machine has (what more cores would
    /// not shorten shows as a share below 1).
    pub(crate) fn finish(&self) {
        let wall = self.started.elapsed();
        let available = std::thread::available_parallelism().map_or(1, std::num::NonZero::get);
        if let Some(busy) = cores(process_cpu(), self.cpu, wall) {
            #[expect(clippy::cast_precision_loss, reason = "a count of cores")]
            let share = busy / available as f64;
            tracing::debug!(
                took = ?wall,
                cores = %format!("{busy:.2} of {available}"),
                busy_share = %format!("{share:.2}"),
                "the run"
            );
        }
    }

    /// Logs the end of phase `what` (at debug level: `-v`): its wall time, the run's
    /// time so far, and the cores it kept busy (the process's CPU time over the phase's
    /// wall time, where the platform tells it).
    pub(crate) fn mark(&self, what: &str) {
        let (now, cpu) = (Instant::now(), process_cpu());
        let mut last = self.last.lock().unwrap_or_else(PoisonError::into_inner);
        let took = now.duration_since(last.0);
        let busy = cores(cpu, last.1, took);
        *last = (now, cpu);
        drop(last);
        match busy {
            Some(busy) => {
                tracing::debug!(took = ?took, cores = %format!("{busy:.2}"), elapsed = ?self.started.elapsed(), "{what}")
            }
            None => tracing::debug!(took = ?took, elapsed = ?self.started.elapsed(), "{what}"),
        }
    }
}

/// CPU time over wall time between two readings of the process's CPU time.
fn cores(now: Option<Duration>, before: Option<Duration>, wall: Duration) -> Option<f64> {
    let used = now?.checked_sub(before?)?;
    (wall.as_secs_f64() > 0.0).then(|| used.as_secs_f64() / wall.as_secs_f64())
}

/// The process's CPU time so far (user and system, all threads): Linux's
/// `/proc/self/stat`, in its clock ticks of 1/100 s (a fixed part of its interface); None
/// elsewhere.
fn process_cpu() -> Option<Duration> {
    let stat = std::fs::read_to_string("/proc/self/stat").ok()?;
    // Fields after the command's name (which may hold spaces, in parentheses): state is
    // the third field of the line, user time the 14th and system time the 15th.
    let after = stat.get(stat.rfind(')')? + 1..)?;
    let mut fields = after.split_whitespace().skip(11);
    let user: u64 = fields.next()?.parse().ok()?;
    let system: u64 = fields.next()?.parse().ok()?;
    Some(Duration::from_millis((user + system) * 10))
}

#[cfg(test)]
mod tests {
    #![allow(clippy::unwrap_used)]
    use super::*;

    #[test]
    #[cfg(target_os = "linux")]
    fn the_process_cpu_time_grows_with_work_on_several_threads() {
        // A thread's own CPU time: the same fields of `/proc/thread-self/stat`.
        let thread_cpu = || {
            let stat = std::fs::read_to_string("/proc/thread-self/stat").unwrap();
            let after = &stat[stat.rfind(')').unwrap() + 1..];
            let mut fields = after.split_whitespace().skip(11);
            let ticks: u64 =
                fields.next().unwrap().parse::<u64>().unwrap() + fields.next().unwrap().parse::<u64>().unwrap();
            Duration::from_millis(ticks * 10)
        };
        let before = process_cpu().unwrap();
        // Two threads, each spinning until it has run 0.2 s of its own CPU time (however
        // busy the machine is: other tests run beside this one): 0.4 s of the process's.
        std::thread::scope(|s| {
            for _ in 0..2 {
                s.spawn(|| {
                    let start = thread_cpu();
                    let mut x = 0u64;
                    while thread_cpu() - start < Duration::from_millis(200) {
                        for _ in 0..100_000 {
                            x = std::hint::black_box(x.wrapping_mul(6_364_136_223_846_793_005).wrapping_add(1));
                        }
                    }
                });
            }
        });
        let used = process_cpu().unwrap() - before;
        // Both threads' time, not one's (a tick of 10 ms either way).
        assert!(used >= Duration::from_millis(380), "the process's CPU time grew by {used:?}, not both threads' 0.4 s");
    }

    #[test]
    fn cores_are_cpu_time_over_wall_time() {
        let s = Duration::from_secs;
        assert_eq!(cores(Some(s(5)), Some(s(1)), s(2)), Some(2.0));
        assert_eq!(cores(None, Some(s(1)), s(2)), None);
        assert_eq!(cores(Some(s(5)), Some(s(1)), Duration::ZERO), None);
    }
}
