//! What the streamer knows of each tile and request, and what its tasks hand back.

use super::*;

#[derive(Clone, Copy, Debug)]
pub(super) enum TileState {
    Requested(u64),
    Missing,
    Failed {
        failures: u32,
        retry_at: Instant,
    },
    /// Fetched, but the payload does not decode: asking again would give the same bytes.
    Undecodable,
}

impl TileState {
    /// Nothing more will come for the tile in this generation of the archive: the view
    /// neither waits for it nor asks again, and coverage falls back to a coarser tile.
    pub(super) fn is_settled_without_data(self) -> bool {
        matches!(self, Self::Missing | Self::Undecodable)
    }
}

pub(in crate::stream) enum Outcome {
    Ready(Arc<DecodedTile>),
    Missing,
    /// The fetch failed (worth a retry).
    Failed(String),
    /// The bytes arrived but are not a tile of their layer (a retry gives the same bytes).
    Undecodable(String),
}

pub(in crate::stream) enum Completion {
    /// `took`: the fetch's round trip (the request until its bytes are in, decoding aside).
    Tiles {
        request: u64,
        generation: u64,
        results: Vec<(TileKey, Outcome)>,
        bytes: u64,
        needed: u64,
        took: Duration,
    },
    /// A leaf directory of archive `part` (0 unless a manifest's), or (offset
    /// [`OPEN_PART`]) the archive itself, opened.
    Leaf {
        request: u64,
        generation: u64,
        part: usize,
        offset: u64,
        failure: Option<String>,
        bytes: u64,
        took: Duration,
    },
    Opened {
        generation: u64,
        result: Result<Backend>,
    },
    Changed {
        generation: u64,
        what: String,
    },
    /// A manifest was asked whether it was republished, and was not (or the question
    /// failed: asked again later).
    Rechecked,
}

/// The "leaf offset" of a manifest's archive being opened: its header and root directory.
pub(super) const OPEN_PART: u64 = u64::MAX;

/// A tile's bytes: in which archive (0 unless a manifest's), where.
pub(in crate::stream) type Located = (usize, TileLocation);

pub(super) struct InFlight {
    pub(super) tiles: Vec<TileKey>,
    pub(super) leaf: Option<(usize, u64)>,
    pub(super) abort: AbortHandle,
}

#[derive(Default)]
pub(super) struct Queue(Mutex<Vec<Completion>>);

impl Queue {
    pub(super) fn push(&self, c: Completion) {
        self.0.lock().unwrap_or_else(PoisonError::into_inner).push(c);
    }
    pub(super) fn take(&self) -> Vec<Completion> {
        std::mem::take(&mut *self.0.lock().unwrap_or_else(PoisonError::into_inner))
    }
}
