//! Framing a dataset and flying over it: the camera model shared by the native viewer
//! and the webplayer, so both fly the same way.

use glam::DVec3;
use terrastream_packer::{Layer, LayerKind, Metadata};

use crate::stream::camera::Camera;

/// The terrain's extent (x, z) in world units and its height range.
pub fn terrain_bounds(metadata: &Metadata) -> ((f64, f64), (f64, f64)) {
    let layer = metadata
        .layers
        .iter()
        .find(|l| l.kind == LayerKind::Elevation)
        .or_else(|| metadata.layers.iter().find(|l| l.kind == LayerKind::Texture))
        .or(metadata.layers.first());
    (layer.map_or((1.0, 1.0), Layer::world_extent), metadata.terrain.height_range())
}

/// An oblique view from the south framing the whole dataset.
pub fn default_camera(metadata: &Metadata, width: u32, height: u32) -> Camera {
    let ((ex, ez), (lo, hi)) = terrain_bounds(metadata);
    let centre = DVec3::new(ex / 2.0, (lo + hi) / 2.0, ez / 2.0);
    let distance = ex.max(ez) * 1.1;
    let pitch = 40f64.to_radians();
    let eye = centre + DVec3::new(0.0, distance * pitch.sin(), distance * pitch.cos());
    Camera::look_at(eye, centre, width, height)
}

/// Which way the flyer is asked to move this frame: each component in -1..=1
/// (several keys at once add up; the sum is normalized).
#[derive(Clone, Copy, Debug, Default, PartialEq)]
pub struct FlyInput {
    /// Along the view direction (+ forward).
    pub forward: f64,
    /// Sideways on the ground plane (+ right).
    pub right: f64,
    /// Straight up (+) or down.
    pub up: f64,
}

/// A fly camera: position, yaw (0 = north, towards -z), pitch, and a speed factor.
/// Speed scales with the height above the ground: at factor 1, a second covers about
/// the altitude, so the same controls work at 50 m and at 50 km.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct FlyCamera {
    /// Eye position in world units.
    pub eye: DVec3,
    /// Heading in radians, 0 = north (-z), positive turns east.
    pub yaw: f64,
    /// Pitch in radians, positive up.
    pub pitch: f64,
    /// Speed factor (the mouse wheel scales it).
    pub speed: f64,
}

/// Lowest the eye goes above the ground.
const CLEARANCE: f64 = 2.0;

impl FlyCamera {
    /// The flyer at `camera`'s position and direction.
    pub fn from_camera(camera: &Camera) -> Self {
        let d = camera.direction();
        Self { eye: camera.position, yaw: d.x.atan2(-d.z), pitch: d.y.clamp(-1.0, 1.0).asin(), speed: 1.0 }
    }

    /// The unit view direction.
    pub fn forward(&self) -> DVec3 {
        DVec3::new(self.pitch.cos() * self.yaw.sin(), self.pitch.sin(), -self.pitch.cos() * self.yaw.cos())
    }

    /// The camera for a `width` x `height` viewport. The near plane follows the eye's
    /// height, which keeps depth precise low and high.
    pub fn camera(&self, width: u32, height: u32) -> Camera {
        let mut c = Camera::look_at(self.eye, self.eye + self.forward() * 100.0, width, height);
        c.near = (self.eye.y.abs() * 1e-3).clamp(0.05, 50.0);
        c
    }

    /// Turns the view by a pointer drag of (`dx`, `dy`) pixels.
    pub fn look(&mut self, dx: f64, dy: f64) {
        self.yaw += dx * 0.004;
        self.pitch = (self.pitch - dy * 0.004).clamp(-1.5, 1.5);
    }

    /// Scales the speed by 1.25 per wheel notch (`notches` > 0: faster).
    pub fn scale_speed(&mut self, notches: f64) {
        self.speed = (self.speed * 1.25f64.powf(notches)).clamp(0.01, 100.0);
    }

    /// Moves for `dt` seconds as `input` asks, never below `ground(x, z)` (the terrain's
    /// height where it is known).
    pub fn step(&mut self, dt: f64, input: FlyInput, ground: impl Fn(f64, f64) -> Option<f64>) {
        let altitude = (self.eye.y - ground(self.eye.x, self.eye.z).unwrap_or(0.0)).max(1.0);
        let speed = altitude.max(20.0) * self.speed * dt;
        let forward = self.forward();
        let right = DVec3::new(forward.x, 0.0, forward.z).normalize_or_zero().cross(DVec3::Y);
        let step = forward * input.forward + right * input.right + DVec3::Y * input.up;
        self.eye += step.normalize_or_zero() * speed;
        if let Some(g) = ground(self.eye.x, self.eye.z) {
            self.eye.y = self.eye.y.max(g + CLEARANCE);
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn round_trips_a_camera_direction() {
        let c = Camera::look_at(DVec3::new(0.0, 100.0, 0.0), DVec3::new(100.0, 0.0, -100.0), 64, 64);
        let fly = FlyCamera::from_camera(&c);
        assert!((fly.forward() - c.direction()).length() < 1e-9);
        assert!((fly.camera(64, 64).direction() - c.direction()).length() < 1e-9);
    }

    #[test]
    fn speed_follows_altitude_and_ground_stops_descent() {
        let mut fly = FlyCamera { eye: DVec3::new(0.0, 1000.0, 0.0), yaw: 0.0, pitch: 0.0, speed: 1.0 };
        fly.step(0.5, FlyInput { forward: 1.0, ..FlyInput::default() }, |_, _| Some(0.0));
        // Half a second at 1000 m: 500 m north (-z).
        assert!((fly.eye.z + 500.0).abs() < 1e-6, "{:?}", fly.eye);
        fly.step(10.0, FlyInput { up: -1.0, ..FlyInput::default() }, |_, _| Some(990.0));
        assert!((fly.eye.y - (990.0 + CLEARANCE)).abs() < 1e-9, "{:?}", fly.eye);
        fly.look(0.0, 1e6);
        assert!(fly.pitch >= -1.5);
        fly.scale_speed(1e3);
        assert!(fly.speed <= 100.0);
    }
}
