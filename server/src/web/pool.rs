//! The threads that make tiles: CPU work kept off the async workers and bounded, so that
//! Range reads, cached tiles and `/healthz` stay fast while cold tiles are flooded.
//!
//! A fixed number of threads (the cores) at a lower scheduling priority (nice 10 on
//! Linux: the async workers win the CPU whenever they have work) take jobs from a bounded
//! queue; a job that finds the queue full is refused at once (the handler answers 503 with
//! `Retry-After`) rather than waiting behind a backlog it cannot see the end of.

use std::sync::mpsc::{Receiver, SyncSender, TrySendError, sync_channel};
use std::sync::{Arc, Mutex};

type Job = Box<dyn FnOnce() + Send>;

/// The pool.
#[derive(Debug)]
pub struct Pool {
    jobs: SyncSender<Job>,
    threads: usize,
}

/// The queue is full.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct Busy;

impl Pool {
    /// `threads` threads (0: one per core) behind a queue of `queue` jobs.
    pub fn new(threads: usize, queue: usize) -> Self {
        let threads = if threads == 0 { std::thread::available_parallelism().map_or(2, usize::from) } else { threads };
        let (jobs, receiver) = sync_channel::<Job>(queue);
        let receiver = Arc::new(Mutex::new(receiver));
        for i in 0..threads {
            let receiver = Arc::clone(&receiver);
            let spawned = std::thread::Builder::new().name(format!("tile-maker-{i}")).spawn(move || work(&receiver));
            if let Err(e) = spawned {
                tracing::error!("cannot start a tile-making thread: {e}");
            }
        }
        Self { jobs, threads }
    }

    /// Threads making tiles.
    pub fn threads(&self) -> usize {
        self.threads
    }

    /// Runs `job` on the pool and waits for its result without blocking the caller's
    /// thread; [`Busy`] at once when the queue is full.
    pub async fn run<T: Send + 'static>(&self, job: impl FnOnce() -> T + Send + 'static) -> Result<T, Busy> {
        let (tx, rx) = tokio::sync::oneshot::channel();
        let job: Job = Box::new(move || {
            let _ = tx.send(job());
        });
        match self.jobs.try_send(job) {
            Ok(()) => rx.await.map_err(|_| Busy),
            Err(TrySendError::Full(_) | TrySendError::Disconnected(_)) => Err(Busy),
        }
    }
}

fn work(receiver: &Mutex<Receiver<Job>>) {
    lower_priority();
    loop {
        let job = {
            let receiver = receiver.lock().unwrap_or_else(std::sync::PoisonError::into_inner);
            receiver.recv()
        };
        let Ok(job) = job else { return };
        // A panicking job (a bug) loses its answer, not the thread.
        if std::panic::catch_unwind(std::panic::AssertUnwindSafe(job)).is_err() {
            tracing::error!("a tile-making job panicked");
        }
    }
}

/// Nice 10 for this thread (Linux sets priorities per thread).
fn lower_priority() {
    #[cfg(target_os = "linux")]
    {
        let tid = rustix::thread::gettid();
        if let Err(e) = rustix::process::setpriority_process(Some(tid), 10) {
            tracing::debug!("tile-making thread keeps its priority: {e}");
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[tokio::test]
    async fn jobs_run_and_a_full_queue_refuses_at_once() {
        let pool = Pool::new(1, 1);
        assert_eq!(pool.run(|| 6 * 7).await, Ok(42));
        // One job holds the thread, one waits in the queue: a third is refused.
        let (hold, release) = std::sync::mpsc::channel::<()>();
        let pool = Arc::new(pool);
        let p = Arc::clone(&pool);
        let first = tokio::spawn(async move { p.run(move || release.recv().is_ok()).await });
        tokio::time::sleep(std::time::Duration::from_millis(50)).await;
        let p = Arc::clone(&pool);
        let second = tokio::spawn(async move { p.run(|| 2).await });
        tokio::time::sleep(std::time::Duration::from_millis(50)).await;
        assert_eq!(pool.run(|| 3).await, Err(Busy));
        hold.send(()).unwrap();
        assert_eq!(first.await.unwrap(), Ok(true));
        assert_eq!(second.await.unwrap(), Ok(2));
    }
}
