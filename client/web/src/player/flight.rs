//! The benchmark flight (`flight=N`) and the frame timings the page reports.

use super::*;

/// Counters the page (and tests) read through [`Player::stats`].
#[derive(Default)]
pub(super) struct Timings {
    /// Page time (ms since navigation start) of the first frame with terrain drawn.
    pub(super) first_frame_at: Option<f64>,
    /// ... of the first frame with everything the view wants on the GPU.
    pub(super) settled_at: Option<f64>,
    pub(super) frames: u64,
    pub(super) max_uploads_per_frame: u64,
    /// Longest time between two frames while tiles were still coming: how responsive the
    /// page stayed while streaming.
    pub(super) max_frame_ms_streaming: f64,
    /// Times between frames while tiles were coming (the first [`MAX_FRAME_SAMPLES`]).
    pub(super) streaming_ms: Vec<f64>,
    /// ... and while everything the view wants was resident.
    pub(super) resident_ms: Vec<f64>,
    /// Making the session (renderer, pipelines, GPU arrays) once the metadata was in.
    pub(super) session_ms: Option<f64>,
    /// The first frame that drew terrain: streaming and preparing it (uploads included),
    /// then encoding and submitting its draw (ms on the page's thread).
    pub(super) first_draw: Option<(f64, f64)>,
}

/// The benchmark flight (`flight=N`): its path, where it is, and the frame times of its
/// frames while tiles were coming and while everything was resident.
pub(super) struct Flight {
    pub(super) path: Vec<(DVec3, DVec3)>,
    /// Pass (0, 1) and frame along the path.
    pub(super) pass: usize,
    pub(super) at: usize,
    pub(super) streaming_ms: Vec<f64>,
    pub(super) resident_ms: Vec<f64>,
}

impl Flight {
    const PASSES: usize = 2;

    pub(super) fn done(&self) -> bool {
        self.pass >= Self::PASSES
    }

    /// The next camera along the path, None once both passes are flown.
    pub(super) fn next(&mut self) -> Option<(DVec3, DVec3)> {
        if self.done() {
            return None;
        }
        let camera = self.path[self.at];
        self.at += 1;
        if self.at == self.path.len() {
            (self.pass, self.at) = (self.pass + 1, 0);
        }
        Some(camera)
    }
}

/// Time between the first complete view and the start of the benchmark flight (its
/// resident frames are measured meanwhile).
pub(super) const FLIGHT_AFTER_MS: f64 = 4000.0;

/// Frame intervals kept per kind, for the percentiles of [`Player::stats`].
pub(super) const MAX_FRAME_SAMPLES: usize = 20_000;

/// The `p` quantile (0..=1) of `samples`, None if there are none.
pub(super) fn quantile(samples: &[f64], p: f64) -> Option<f64> {
    let mut sorted = samples.to_vec();
    sorted.sort_by(f64::total_cmp);
    #[expect(
        clippy::cast_possible_truncation,
        clippy::cast_sign_loss,
        clippy::cast_precision_loss,
        reason = "an index"
    )]
    let at = ((p * sorted.len() as f64).ceil() as usize).clamp(1, sorted.len().max(1)) - 1;
    sorted.get(at).copied()
}
