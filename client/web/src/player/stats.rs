//! The counters the page and the tests read (`Player::stats`).

use super::*;

impl State {
    pub(super) fn stats(&self) -> String {
        let still = FlyCamera { eye: DVec3::ZERO, yaw: 0.0, pitch: 0.0, speed: 1.0, globe: false };
        let (pending, settled, error, fly) = match &self.phase {
            Phase::Running { session, fly } => {
                (session.streamer.pending(), session.settled(), session.streamer.last_error().map(str::to_owned), *fly)
            }
            Phase::Opening(o) => (0, false, o.last_error().map(str::to_owned), still),
            Phase::Failed => (0, false, None, still),
        };
        let (stream, frame) = self.last.clone().unwrap_or_default();
        let since_start = |at: Option<f64>| at.map(|t| t - self.started_ms);
        serde_json::json!({
            "archive": self.params.archive,
            "backend": if self.gpu.info.backend == wgpu::Backend::Gl { "webgl2" } else { "webgpu" },
            "adapter": self.gpu.info.name,
            "frames": self.timings.frames,
            "fps": self.frame_times.fps(),
            "first_frame_ms": since_start(self.timings.first_frame_at),
            "page_first_frame_ms": self.timings.first_frame_at,
            "settled_ms": since_start(self.timings.settled_at),
            "settled": settled,
            "pending": pending,
            "http_requests": self.http.requests.load(Relaxed),
            "http_bytes": self.http.bytes.load(Relaxed),
            "http_retries": self.http.retries.load(Relaxed),
            "requests": stream.requests,
            "tiles_fetched": stream.tiles_fetched,
            "bytes_fetched": stream.bytes_fetched,
            "in_flight": stream.in_flight,
            "wanted": stream.wanted,
            "missing": stream.missing,
            "failures": stream.failures,
            "uploads": stream.uploads,
            "max_uploads_per_frame": self.timings.max_uploads_per_frame,
            "upload_budget": match &self.phase {
                Phase::Running { session, .. } => session.budget.max_tiles,
                Phase::Opening(_) | Phase::Failed => 0,
            },
            "max_frame_ms_streaming": self.timings.max_frame_ms_streaming,
            "session_ms": self.timings.session_ms,
            "first_draw_prepare_ms": self.timings.first_draw.map(|t| t.0),
            "first_draw_submit_ms": self.timings.first_draw.map(|t| t.1),
            "workers": self.workers.as_ref().map_or(0, |w| w.len()),
            "decoded_in_workers": self.workers.as_ref().map_or(0, |w| w.decoded()),
            "earth_decoded_in_worker": self.workers.as_ref().is_some_and(|w| w.decoded_earth()),
            "frames_streaming": self.timings.streaming_ms.len(),
            "frames_resident": self.timings.resident_ms.len(),
            "frame_p50_streaming_ms": quantile(&self.timings.streaming_ms, 0.5),
            "frame_p99_streaming_ms": quantile(&self.timings.streaming_ms, 0.99),
            "frame_p50_resident_ms": quantile(&self.timings.resident_ms, 0.5),
            "frame_p99_resident_ms": quantile(&self.timings.resident_ms, 0.99),
            "flight_done": self.flight.as_ref().is_some_and(Flight::done),
            "flight_frames_streaming": self.flight.as_ref().map_or(0, |f| f.streaming_ms.len()),
            "flight_frames_resident": self.flight.as_ref().map_or(0, |f| f.resident_ms.len()),
            "flight_p50_streaming_ms": self.flight.as_ref().and_then(|f| quantile(&f.streaming_ms, 0.5)),
            "flight_p99_streaming_ms": self.flight.as_ref().and_then(|f| quantile(&f.streaming_ms, 0.99)),
            "flight_max_streaming_ms": self.flight.as_ref().and_then(|f| quantile(&f.streaming_ms, 1.0)),
            "flight_p50_resident_ms": self.flight.as_ref().and_then(|f| quantile(&f.resident_ms, 0.5)),
            "flight_p99_resident_ms": self.flight.as_ref().and_then(|f| quantile(&f.resident_ms, 0.99)),
            "resident": [frame.resident.0, frame.resident.1],
            "triangles": frame.triangles,
            "patches": frame.patches,
            "drew_nothing_in_view": frame.drew_nothing_in_view(),
            "unreached_layer": frame.unreached_layer,
            "hud": self.show_hud,
            "eye": [fly.eye.x, fly.eye.y, fly.eye.z],
            "yaw": fly.yaw,
            "pitch": fly.pitch,
            "speed": fly.speed,
            "error": error,
        })
        .to_string()
    }
}
