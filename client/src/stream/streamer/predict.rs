//! Prefetch: the view ahead along the camera's motion.

use super::*;

impl Streamer {
    /// The tiles of the view `prefetch_ahead` from now, at the camera's speed and turn
    /// since the last update, that the current view does not want: fetched with the
    /// requests it leaves free, cancelled when the camera stops wanting them.
    pub(super) fn predict(&mut self, camera: &Camera, now: Instant) {
        self.prefetch.clear();
        self.prefetch_keys.clear();
        let last = self.last_camera.replace((*camera, now));
        let ahead = self.options.prefetch_ahead.as_secs_f64();
        let Some(surface) = self.surface() else { return };
        let (Some((before, at)), Some(metadata)) = (last, self.metadata()) else { return };
        let dt = now.saturating_duration_since(at).as_secs_f64();
        if ahead <= 0.0 || dt <= 0.0 || dt > 1.0 {
            return;
        }
        let velocity = (camera.position - before.position) / dt;
        let turn = (camera.forward.normalize_or_zero() - before.forward.normalize_or_zero()) / dt;
        if velocity.length_squared() == 0.0 && turn.length_squared() == 0.0 {
            return;
        }
        let predicted = Camera {
            position: camera.position + velocity * ahead,
            forward: camera.forward.normalize_or_zero() + turn * ahead,
            ..*camera
        };
        let states = &self.states;
        let soon = select(metadata, &surface, &predicted, &self.options.select, |k| {
            !matches!(states.get(&k), Some(TileState::Missing))
        });
        for w in soon {
            if !self.wanted_keys.contains(&w.key) && self.prefetch_keys.insert(w.key) {
                self.prefetch.push(w.key);
            }
        }
    }
}
