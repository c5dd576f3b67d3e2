//! The camera as the streaming core sees it: a position, a view frustum and the screen
//! it projects onto.
//!
//! World axes (right-handed, y up, as in wgpu and glTF): x east, y up (height), z south,
//! so that the ground plane (x, z) runs like a tile grid — tile (tx, ty) of a layer at
//! a LOD whose tiles are `s` world units wide covers x in `[tx s, (tx+1) s]` and z in
//! `[ty s, (ty+1) s]`. Units are the archive's world units (metres).

use glam::{DMat3, DMat4, DVec3, DVec4};

/// A perspective camera.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Camera {
    /// Eye position in world units.
    pub position: DVec3,
    /// View direction (need not be normalized).
    pub forward: DVec3,
    /// Vertical field of view in radians.
    pub fov_y: f64,
    /// Width / height of the viewport.
    pub aspect: f64,
    /// Viewport height in pixels: turns a world size at a distance into pixels.
    pub viewport_height: u32,
    /// Near plane distance.
    pub near: f64,
    /// Far plane distance.
    pub far: f64,
    /// The scene's up at the eye: world +y on the plate, the ellipsoid's normal on the
    /// globe ([`crate::globe`]).
    pub zenith: DVec3,
}

impl Camera {
    /// A camera at `position` looking at `target`, 60 degrees vertical field of view.
    pub fn look_at(position: DVec3, target: DVec3, width: u32, height: u32) -> Self {
        let aspect = f64::from(width.max(1)) / f64::from(height.max(1));
        let distance = (target - position).length().max(1.0);
        Self {
            position,
            forward: target - position,
            fov_y: 60f64.to_radians(),
            aspect,
            viewport_height: height.max(1),
            near: (distance * 1e-4).max(0.1),
            far: distance * 100.0 + 1e5,
            zenith: DVec3::Y,
        }
    }

    /// The view direction, normalized (straight down if `forward` is zero).
    pub fn direction(&self) -> DVec3 {
        self.forward.try_normalize().unwrap_or(DVec3::NEG_Y)
    }

    /// An up vector for the view matrix: the zenith, unless looking straight up or down
    /// (then the way north: -z on the plate).
    pub fn up(&self) -> DVec3 {
        let d = self.direction();
        let zenith = self.zenith.try_normalize().unwrap_or(DVec3::Y);
        if d.cross(zenith).length_squared() >= 1e-12 {
            return zenith;
        }
        if zenith == DVec3::Y {
            return DVec3::NEG_Z;
        }
        // On the globe: towards the pole axis, projected onto the view plane.
        (DVec3::Z - zenith * zenith.z).try_normalize().unwrap_or(DVec3::X)
    }

    /// World-to-view matrix (right-handed, looking down -z in view space).
    pub fn view(&self) -> DMat4 {
        DMat4::look_to_rh(self.position, self.direction(), self.up())
    }

    /// View-to-clip matrix with a 0..1 depth range.
    pub fn projection(&self) -> DMat4 {
        DMat4::perspective_rh(self.fov_y, self.aspect, self.near, self.far)
    }

    /// The view frustum's planes.
    pub fn frustum(&self) -> Frustum {
        Frustum::from_matrix(self.projection() * self.view())
    }

    /// Pixels per world unit at distance 1: `viewport_height / (2 tan(fov_y / 2))`.
    pub fn pixels_per_radian(&self) -> f64 {
        f64::from(self.viewport_height) / (2.0 * (self.fov_y * 0.5).tan())
    }
}

/// An axis-aligned box.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Aabb {
    /// Smallest corner.
    pub min: DVec3,
    /// Largest corner.
    pub max: DVec3,
}

impl Aabb {
    /// The eight corners.
    pub fn corners(&self) -> [DVec3; 8] {
        let (lo, hi) = (self.min, self.max);
        [0, 1, 2, 3, 4, 5, 6, 7].map(|i| {
            DVec3::new(
                if i & 1 == 0 { lo.x } else { hi.x },
                if i & 2 == 0 { lo.y } else { hi.y },
                if i & 4 == 0 { lo.z } else { hi.z },
            )
        })
    }

    /// Distance from `p` to the box (0 inside).
    pub fn distance(&self, p: DVec3) -> f64 {
        (self.min - p).max(p - self.max).max(DVec3::ZERO).length()
    }
}

/// A box turned by an orthonormal frame: scene boxes on the globe follow the ground's
/// tangent plane (an axis-aligned box in ECEF of a tilted patch is up to 1.7 times its
/// size, and a distance to it too short). On the plate the frame is the identity.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct SceneBox {
    /// The box's centre.
    pub centre: DVec3,
    /// Its axes (orthonormal columns).
    pub axes: DMat3,
    /// Half its size along each axis.
    pub half: DVec3,
}

impl SceneBox {
    /// Distance from `p` to the box (0 inside).
    pub fn distance(&self, p: DVec3) -> f64 {
        let q = self.axes.transpose() * (p - self.centre);
        (q.abs() - self.half).max(DVec3::ZERO).length()
    }

    /// The eight corners.
    pub fn corners(&self) -> [DVec3; 8] {
        let local = Aabb { min: -self.half, max: self.half }.corners();
        local.map(|c| self.centre + self.axes * c)
    }
}

impl From<Aabb> for SceneBox {
    fn from(b: Aabb) -> Self {
        Self { centre: (b.min + b.max) * 0.5, axes: DMat3::IDENTITY, half: (b.max - b.min) * 0.5 }
    }
}

/// Six planes `(n, d)` with `n . p + d >= 0` inside.
#[derive(Clone, Copy, Debug)]
pub struct Frustum {
    planes: [DVec4; 6],
}

impl Frustum {
    /// Planes of a clip-space cube (x, y in -1..1, z in 0..1) pulled back through `m`.
    pub fn from_matrix(m: DMat4) -> Self {
        let (r0, r1, r2, r3) = (m.row(0), m.row(1), m.row(2), m.row(3));
        let planes = [r3 + r0, r3 - r0, r3 + r1, r3 - r1, r2, r3 - r2].map(|p| {
            let len = p.truncate().length();
            if len > 0.0 { p / len } else { p }
        });
        Self { planes }
    }

    /// False only when the turned box lies entirely outside one plane (conservative).
    pub fn intersects_box(&self, b: &SceneBox) -> bool {
        self.planes.iter().all(|p| {
            let n = p.truncate();
            let reach = (b.axes.transpose() * n).abs().dot(b.half);
            n.dot(b.centre) + p.w + reach >= 0.0
        })
    }

    /// False only when the box lies entirely outside one plane (conservative).
    pub fn intersects(&self, b: &Aabb) -> bool {
        self.planes.iter().all(|p| {
            let n = p.truncate();
            // The box corner furthest along the plane normal.
            let corner = DVec3::new(
                if n.x >= 0.0 { b.max.x } else { b.min.x },
                if n.y >= 0.0 { b.max.y } else { b.min.y },
                if n.z >= 0.0 { b.max.z } else { b.min.z },
            );
            n.dot(corner) + p.w >= 0.0
        })
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn frustum_keeps_what_is_ahead_and_drops_what_is_behind() {
        // 100 m up, looking east and down at a point 100 m away.
        let cam = Camera::look_at(DVec3::new(0.0, 100.0, 0.0), DVec3::new(100.0, 0.0, 0.0), 800, 600);
        let f = cam.frustum();
        let ahead = Aabb { min: DVec3::new(90.0, -5.0, -10.0), max: DVec3::new(110.0, 5.0, 10.0) };
        let behind = Aabb { min: DVec3::new(-300.0, -5.0, -10.0), max: DVec3::new(-200.0, 5.0, 10.0) };
        let far_left = Aabb { min: DVec3::new(90.0, -5.0, -5000.0), max: DVec3::new(110.0, 5.0, -4000.0) };
        assert!(f.intersects(&ahead));
        assert!(!f.intersects(&behind));
        assert!(!f.intersects(&far_left));
    }

    #[test]
    fn box_distance() {
        let b = Aabb { min: DVec3::ZERO, max: DVec3::splat(10.0) };
        assert!((b.distance(DVec3::new(13.0, 14.0, 5.0)) - 5.0).abs() < 1e-12);
        assert!(b.distance(DVec3::splat(5.0)).abs() < 1e-12);
    }
}
