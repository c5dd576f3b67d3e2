//! Progress reporting and cancellation for long operations (pack, extract, verify).

use std::sync::atomic::{AtomicBool, Ordering};

use crate::error::{Error, Result};

/// Receives progress of a long operation and tells it when to stop.
pub trait Progress: Sync {
    /// A phase starts with `total` units of work (tiles, bytes).
    fn start(&self, phase: &str, total: u64);
    /// `n` more units are done.
    fn advance(&self, n: u64);
    /// True once the user asked to stop (Ctrl-C).
    fn cancelled(&self) -> bool {
        false
    }
    /// Returns [`Error::Interrupted`] once cancelled.
    ///
    /// # Errors
    /// [`Error::Interrupted`].
    fn check(&self) -> Result<()> {
        if self.cancelled() { Err(Error::Interrupted(terrastream_format::Interrupted)) } else { Ok(()) }
    }
}

/// Reports nothing; stops when its flag is set.
#[derive(Debug, Default)]
pub struct Silent {
    /// Set to stop the operation.
    pub stop: AtomicBool,
}

impl Progress for Silent {
    fn start(&self, _: &str, _: u64) {}
    fn advance(&self, _: u64) {}
    fn cancelled(&self) -> bool {
        self.stop.load(Ordering::Relaxed)
    }
}
