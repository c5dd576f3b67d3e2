//! The streamer's settings, budgets and counters.

use super::*;

/// Settings of a [`Streamer`].
#[derive(Clone, Debug, PartialEq)]
pub struct StreamOptions {
    /// Tile selection.
    pub select: SelectOptions,
    /// Most requests in flight at once.
    pub max_in_flight: usize,
    /// Adapt the in-flight limit to the link (see `InFlightLimit`), between 2 and
    /// `max_in_flight`, starting at 8; else `max_in_flight` is the limit.
    pub adaptive_in_flight: bool,
    /// Merge neighbouring tiles of an archive into one range request.
    pub coalesce: bool,
    /// Largest gap between two tiles' bytes that still merges them.
    pub coalesce_gap: u64,
    /// Largest coalesced request.
    pub max_request_bytes: u64,
    /// Decoded-tile cache budget in bytes (what the current view needs is kept even above it).
    pub cache_bytes: usize,
    /// Wait before retrying a failed tile; doubled per failure.
    pub retry_backoff: Duration,
    /// Longest wait between retries.
    pub max_retry_backoff: Duration,
    /// Worker threads for fetching and decoding (native only).
    pub worker_threads: usize,
    /// Prefetch what the camera will see this far ahead, at its current speed and turn,
    /// with the requests the current view leaves free (zero: no prefetch).
    pub prefetch_ahead: Duration,
    /// How often a manifest is asked whether it was republished (one conditional
    /// request); when it was, everything is re-read from the new one (zero: never).
    pub manifest_recheck: Duration,
    /// Make elevation tiles' shade texels as they are decoded, for the renderer (see
    /// [`crate::DecodedTile::shade`]): off the frame's thread, at 4 more bytes a sample. A
    /// program that only reads heights can leave them out.
    pub shade: bool,
}

impl Default for StreamOptions {
    fn default() -> Self {
        Self {
            select: SelectOptions::default(),
            max_in_flight: 32,
            adaptive_in_flight: true,
            coalesce: true,
            coalesce_gap: 4 * 1024,
            max_request_bytes: 512 * 1024,
            cache_bytes: 512 * 1024 * 1024,
            retry_backoff: Duration::from_millis(250),
            max_retry_backoff: Duration::from_secs(10),
            worker_threads: 2,
            prefetch_ahead: Duration::from_millis(500),
            manifest_recheck: Duration::from_secs(30),
            shade: true,
        }
    }
}

/// Why a [`Decoder`] handed back no tile.
#[derive(Clone, Debug, PartialEq, Eq)]
pub enum DecodeFailure {
    /// The payload is not a tile of its layer (what [`decode`] says of it).
    Undecodable(String),
    /// The decoder could not run (a worker that did not start): the tile is decoded
    /// where it was fetched instead.
    Unavailable,
}

/// What a [`Decoder`] returns.
pub type DecodeResult = BoxFuture<'static, std::result::Result<DecodedTile, DecodeFailure>>;

/// Decodes payloads somewhere else than the fetching task: in a browser, Web Workers,
/// so that decoding does not take the page's thread. Given the layer, the tile, its
/// payload and whether the layer's compression is still on it.
#[cfg(target_arch = "wasm32")]
pub type Decoder = std::rc::Rc<dyn Fn(&Layer, TileKey, Bytes, bool) -> DecodeResult>;
/// Decodes payloads somewhere else than the fetching task (see the wasm32 definition).
#[cfg(not(target_arch = "wasm32"))]
pub type Decoder = Arc<dyn Fn(&Layer, TileKey, Bytes, bool) -> DecodeResult + Send + Sync>;

/// How much one frame may upload.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct UploadBudget {
    /// Most tiles.
    pub max_tiles: usize,
    /// Most bytes (decoded size). Must be at least one tile's size, or nothing is uploaded.
    pub max_bytes: usize,
}

impl Default for UploadBudget {
    fn default() -> Self {
        Self { max_tiles: 8, max_bytes: 4 * 1024 * 1024 }
    }
}

/// A tile ready for the GPU.
#[derive(Clone, Debug)]
pub struct Upload {
    /// The decoded tile.
    pub tile: Arc<DecodedTile>,
    /// The archive version it belongs to (see [`Streamer::generation`]).
    pub generation: u64,
    /// Its urgency rank this frame (0 = most urgent).
    pub rank: usize,
}

/// Counters since the streamer was made.
#[derive(Clone, Debug, Default, PartialEq, Eq)]
pub struct StreamStats {
    /// Requests sent (tile fetches, coalesced or not, and directory leaves).
    pub requests: u64,
    /// Tiles fetched and decoded.
    pub tiles_fetched: u64,
    /// Bytes received.
    pub bytes_fetched: u64,
    /// Bytes of the tiles themselves among them (the rest is gaps of coalesced requests
    /// and directory leaves).
    pub bytes_needed: u64,
    /// Requests in flight now.
    pub in_flight: u64,
    /// The in-flight limit now (adaptive: follows the link).
    pub in_flight_limit: u64,
    /// Tiles the camera's motion predicts it will want, not wanted yet (fetched with the
    /// requests the view leaves free).
    pub prefetch: u64,
    /// Bytes in the decoded-tile cache now.
    pub cache_bytes: u64,
    /// Tiles in the decoded-tile cache now.
    pub cache_tiles: u64,
    /// Wanted tiles found in the cache, summed over updates.
    pub hits: u64,
    /// Tiles whose request was cancelled because the camera no longer needed them.
    pub cancelled: u64,
    /// Tiles that rode in a request with others (tiles - requests, for tile fetches).
    pub coalesced: u64,
    /// Failed tile fetches (each is retried after a backoff).
    pub failures: u64,
    /// Tiles the origin does not have.
    pub missing: u64,
    /// Tiles fetched whole whose bytes could not be decoded (not retried; coverage falls
    /// back to the parent there). Also counted in `failures`.
    pub undecodable: u64,
    /// Tiles handed to the renderer.
    pub uploads: u64,
    /// Bytes handed to the renderer.
    pub upload_bytes: u64,
    /// Times the archive was found replaced and everything re-read.
    pub reloads: u64,
    /// Tiles wanted by the last update.
    pub wanted: u64,
}
