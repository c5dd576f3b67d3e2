//! Framing a dataset and flying over it: the one camera model of every front end. The
//! headless `render`, the native viewer and the webplayer all start from
//! [`start_camera`]; the viewers fly on with [`FlyCamera`]; and every frame's camera gets
//! clip planes that enclose the whole terrain ([`Camera::enclosing`], applied by the
//! render session), so that none of them can cull what another draws (a continent is
//! 10^7 m across: a fixed far plane of a hundred kilometres once left the viewers with
//! nothing to draw).

use glam::{DMat4, DVec2, DVec3};
use terrastream_format::{Layer, LayerKind, Metadata, intersect, union};

use crate::globe::Surface;
use crate::stream::camera::{Aabb, Camera, SceneBox};
pub use crate::stream::select::drawn_heights;

/// The box `[min x, min z, max x, max z]` in world units where the terrain is drawn, and
/// the heights it is drawn between.
///
/// The one rule of every front end (docs/rendering.md, "Data edges"): the terrain covers
/// the union of the drawn layers' data boxes (elevation and texture, FORMAT.md §3.7),
/// within the source's extent where the archive gives it (`terrain.data_extent`). Inside
/// it, heights come from the elevation where it has data (elsewhere the ground lies flat
/// at the lowest height) and colour from the imagery where it has texels (elsewhere the
/// height tint).
pub fn terrain_bounds(metadata: &Metadata) -> ([f64; 4], (f64, f64)) {
    let drawn = metadata.layers.iter().filter(|l| matches!(l.kind, LayerKind::Elevation | LayerKind::Texture));
    let mut area = drawn.map(Layer::data_world).reduce(union).unwrap_or([0.0, 0.0, 1.0, 1.0]);
    if let Some([dx, dz]) = metadata.terrain.data_extent.filter(|[dx, dz]| *dx > 0.0 && *dz > 0.0) {
        area = intersect(area, [0.0, 0.0, dx, dz]).unwrap_or(area);
    }
    (area, drawn_heights(metadata))
}

/// The box the terrain is drawn in.
pub fn terrain_box(metadata: &Metadata) -> Aabb {
    let ([x0, z0, x1, z1], (lo, hi)) = terrain_bounds(metadata);
    Aabb { min: DVec3::new(x0, lo, z0), max: DVec3::new(x1, hi, z1) }
}

/// The box views frame: where the drawn layers' detail is (their finest LOD's tiles,
/// FORMAT.md §3.7), inside [`terrain_bounds`]. A regional tree's coarse tiles reach far
/// beyond its data; its finest tiles do not.
pub fn framed_box(metadata: &Metadata) -> Aabb {
    let (area, (lo, hi)) = terrain_bounds(metadata);
    let drawn = metadata.layers.iter().filter(|l| matches!(l.kind, LayerKind::Elevation | LayerKind::Texture));
    let detail = drawn.map(Layer::data_detail).reduce(union).and_then(|d| intersect(d, area)).unwrap_or(area);
    let [x0, z0, x1, z1] = detail;
    Aabb { min: DVec3::new(x0, lo, z0), max: DVec3::new(x1, hi, z1) }
}

/// Pitch of the default view, below the horizon.
const DEFAULT_PITCH_DEGREES: f64 = 50.0;
/// Share of the frame's half-width and half-height the default view may fill.
const FRAME_FILL: f64 = 0.92;

/// An oblique view from the south framing the whole dataset: looking down at
/// `DEFAULT_PITCH_DEGREES`, the terrain's box centred in the frame and as close as it
/// can be while every corner stays inside `FRAME_FILL` of the frame. On the globe the
/// same over the data's box on the ellipsoid, and a data set spanning a hemisphere or
/// more (a world archive) is seen whole, straight down from above its centre.
pub fn default_camera(metadata: &Metadata, surface: &Surface, width: u32, height: u32) -> Camera {
    let Some(globe) = surface.globe() else {
        let terrain = framed_box(metadata);
        let drawn = SceneBox::from(terrain_box(metadata));
        let centre = (terrain.min + terrain.max) * 0.5;
        let pitch = DEFAULT_PITCH_DEGREES.to_radians();
        let back = DVec3::new(0.0, pitch.sin(), pitch.cos());
        // The camera's up: moving the eye along it moves the picture down, direction kept.
        let up = DVec3::new(0.0, pitch.cos(), -pitch.sin());
        let framing = Framing { centre, back, up, points: terrain.corners().to_vec() };
        return framing.fit(surface, &drawn, width, height);
    };
    let framed = framed_box(metadata);
    let (lo, hi) = (framed.min.y, framed.max.y);
    let rect = [framed.min.x, framed.min.z, framed.max.x, framed.max.z];
    let centre_world = DVec2::new((rect[0] + rect[2]) * 0.5, (rect[1] + rect[3]) * 0.5);
    let centre_geo = globe.lon_lat(centre_world.x, centre_world.y);
    let frame = crate::globe::enu(centre_geo.x, centre_geo.y);
    let (north, up) = (frame.y_axis, frame.z_axis);
    let drawn = scene_box(metadata, surface);
    // The data's points on the ellipsoid, and how far apart they lie.
    let mut points = Vec::new();
    for j in 0..=8 {
        for i in 0..=8 {
            let (u, v) = (f64::from(i) / 8.0, f64::from(j) / 8.0);
            let (x, z) = (rect[0] + (rect[2] - rect[0]) * u, rect[1] + (rect[3] - rect[1]) * v);
            points.push(globe.ecef(x, z, lo));
            points.push(globe.ecef(x, z, hi));
        }
    }
    let centre = globe.ecef(centre_world.x, centre_world.y, (lo + hi) * 0.5);
    let widest = points.iter().map(|p| p.normalize().dot(centre.normalize())).fold(1.0, f64::min);
    if widest < 0.3 {
        // More than about 70 degrees from the centre: the whole Earth, straight down.
        let camera = Camera::look_at(centre, DVec3::ZERO, width, height);
        let half = (camera.fov_y * 0.5).min(((camera.fov_y * 0.5).tan() * camera.aspect).atan());
        let distance = crate::globe::A / (half * FRAME_FILL).sin();
        let eye = centre.normalize() * distance;
        let mut camera = Camera::look_at(eye, DVec3::ZERO, width, height);
        camera.zenith = north;
        return camera.enclosing(&drawn);
    }
    let pitch = DEFAULT_PITCH_DEGREES.to_radians();
    let back = up * pitch.sin() - north * pitch.cos();
    let camera_up = up * pitch.cos() + north * pitch.sin();
    Framing { centre, back, up: camera_up, points }.fit(surface, &drawn, width, height)
}

/// A view to fit: looking along `-back` at `centre`, moved along `up` to centre the
/// points vertically, as close as the fill allows.
struct Framing {
    centre: DVec3,
    back: DVec3,
    up: DVec3,
    points: Vec<DVec3>,
}

impl Framing {
    fn fit(&self, surface: &Surface, drawn: &SceneBox, width: u32, height: u32) -> Camera {
        let Self { centre, back, up, points } = self;
        let at = |distance: f64, lift: f64| {
            let eye = *centre + *back * distance + *up * lift;
            let mut camera = Camera::look_at(eye, eye - *back, width, height);
            camera.zenith = surface.up(eye);
            camera.enclosing(drawn)
        };
        // The points' extent on screen (normalized device coordinates), None if behind the eye.
        let extent = |camera: &Camera| {
            let clip = camera.view_projection();
            let (mut lo, mut hi) = (DVec2::splat(f64::MAX), DVec2::splat(f64::MIN));
            for p in points {
                let p = clip * p.extend(1.0);
                if p.w <= 0.0 {
                    return None;
                }
                let ndc = DVec2::new(p.x / p.w, p.y / p.w);
                (lo, hi) = (lo.min(ndc), hi.max(ndc));
            }
            Some((lo, hi))
        };
        let fits = |camera: &Camera| {
            extent(camera).is_some_and(|(lo, hi)| {
                lo.cmpge(DVec2::splat(-FRAME_FILL)).all() && hi.cmple(DVec2::splat(FRAME_FILL)).all()
            })
        };
        let (lo, hi) = points.iter().fold((DVec3::MAX, DVec3::MIN), |(lo, hi), p| (lo.min(*p), hi.max(*p)));
        let size = (hi - lo).length().max(1.0);
        let (mut distance, mut lift) = (size * 4.0, 0.0);
        // Alternately: centre the points vertically, then come as close as the fill allows.
        for round in 0..4 {
            let (mut near, mut far) = (size * 1e-3, distance);
            while !fits(&at(far, lift)) && far < size * 1e4 {
                far *= 2.0;
            }
            for _ in 0..48 {
                let mid = (near + far) * 0.5;
                if fits(&at(mid, lift)) { far = mid } else { near = mid }
            }
            distance = far;
            let Some((lo, hi)) = extent(&at(distance, lift)).filter(|_| round < 3) else { break };
            // One unit of NDC is distance * tan(fov / 2) world units across the view's centre.
            let camera = at(distance, lift);
            lift += (lo.y + hi.y) * 0.5 * distance * (camera.fov_y * 0.5).tan();
        }
        let camera = at(distance, lift);
        if fits(&camera) { camera } else { at(size * 4.0, 0.0) }
    }
}

/// The terrain's box in scene coordinates (world on the plate, ECEF on the globe).
pub fn scene_box(metadata: &Metadata, surface: &Surface) -> SceneBox {
    match surface {
        Surface::Flat => terrain_box(metadata).into(),
        Surface::Globe(globe) => {
            let (rect, heights) = terrain_bounds(metadata);
            globe.bounds(rect, heights)
        }
    }
}

/// The benchmarks' flight, `frames` eye and target positions: from the south-west corner
/// to the north-east one, low over the terrain, looking ahead and down. `bench render`
/// flies it natively, the webplayer with `flight=<frames>`.
pub fn bench_flight(metadata: &Metadata, frames: usize) -> Vec<(DVec3, DVec3)> {
    let ([x0, z0, x1, z1], (_, hi)) = terrain_bounds(metadata);
    let (ex, ez) = (x1 - x0, z1 - z0);
    let altitude = hi + 0.04 * ex.max(ez);
    #[expect(clippy::cast_precision_loss, reason = "frame numbers")]
    let at = |i: usize| i as f64 / (frames.max(2) - 1) as f64;
    (0..frames)
        .map(|i| {
            let t = at(i);
            let eye = DVec3::new(x0 + ex * (0.1 + 0.8 * t), altitude, z0 + ez * (0.9 - 0.8 * t));
            (eye, eye + DVec3::new(ex * 0.1, -altitude * 0.6, -ez * 0.1))
        })
        .collect()
}

/// Where every front end starts: the eye and target asked for (scene coordinates of
/// `surface`), else [`default_camera`].
pub fn start_camera(
    metadata: &Metadata,
    surface: &Surface,
    start: Option<(DVec3, DVec3)>,
    width: u32,
    height: u32,
) -> Camera {
    match start {
        Some((eye, target)) => {
            let mut camera = Camera::look_at(eye, target, width, height);
            camera.zenith = surface.up(eye);
            camera.enclosing(&scene_box(metadata, surface))
        }
        None => default_camera(metadata, surface, width, height),
    }
}

impl Camera {
    /// This camera with near and far planes that enclose `terrain` wherever the eye is:
    /// far beyond its farthest corner, near a tenth of the way to its closest point.
    #[must_use]
    pub fn enclosing(mut self, terrain: &SceneBox) -> Self {
        let farthest = terrain.corners().iter().map(|c| c.distance(self.position)).fold(0.0, f64::max);
        self.near = (terrain.distance(self.position) * 0.1).max(0.05);
        self.far = (farthest * 1.05 + 1.0).max(self.near * 2.0);
        self
    }

    /// World-to-clip matrix.
    pub fn view_projection(&self) -> DMat4 {
        self.projection() * self.view()
    }
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

/// A fly camera: position, yaw (0 = north), pitch, and a speed factor. On the plate
/// north is -z and up +y; on the globe (`globe`: the eye in ECEF) they are those of the
/// ellipsoid under the eye, so level flight follows the Earth's curve.
/// Speed scales with the height above the ground: at factor 1, a second covers about
/// the altitude, so the same controls work at 50 m, at 50 km and from orbit.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct FlyCamera {
    /// Eye position in scene units (world units on the plate, ECEF metres on the globe).
    pub eye: DVec3,
    /// Heading in radians, 0 = north, positive turns east.
    pub yaw: f64,
    /// Pitch in radians, positive up.
    pub pitch: f64,
    /// Speed factor (the mouse wheel scales it).
    pub speed: f64,
    /// The eye is in ECEF over the ellipsoid.
    pub globe: bool,
}

/// Lowest the eye goes above the ground.
const CLEARANCE: f64 = 2.0;
/// Height above which a drag orbits the globe rather than turning the view, metres.
pub const ORBIT_ABOVE: f64 = 200_000.0;

impl FlyCamera {
    /// The flyer at `camera`'s position and direction: on the globe when the camera's
    /// zenith is not the plate's +y.
    pub fn from_camera(camera: &Camera) -> Self {
        let globe = camera.zenith != DVec3::Y;
        let at = Self { eye: camera.position, yaw: 0.0, pitch: 0.0, speed: 1.0, globe };
        let (east, north, up) = at.frame();
        let d = camera.direction();
        Self { yaw: d.dot(east).atan2(d.dot(north)), pitch: d.dot(up).clamp(-1.0, 1.0).asin(), ..at }
    }

    /// East, north and up at the eye.
    pub fn frame(&self) -> (DVec3, DVec3, DVec3) {
        if !self.globe {
            return (DVec3::X, DVec3::NEG_Z, DVec3::Y);
        }
        let (lon, lat, _) = crate::globe::geodetic(self.eye);
        let m = crate::globe::enu(lon, lat);
        (m.x_axis, m.y_axis, m.z_axis)
    }

    /// The eye's height above the datum (the plate's y, the ellipsoid's height).
    pub fn height(&self) -> f64 {
        if self.globe { crate::globe::geodetic(self.eye).2 } else { self.eye.y }
    }

    /// The unit view direction.
    pub fn forward(&self) -> DVec3 {
        let (east, north, up) = self.frame();
        (east * self.yaw.sin() + north * self.yaw.cos()) * self.pitch.cos() + up * self.pitch.sin()
    }

    /// The camera for a `width` x `height` viewport (a render session fits its clip
    /// planes to the terrain: [`Camera::enclosing`]).
    pub fn camera(&self, width: u32, height: u32) -> Camera {
        let mut camera = Camera::look_at(self.eye, self.eye + self.forward() * 100.0, width, height);
        camera.zenith = self.frame().2;
        camera
    }

    /// Turns the view by a pointer drag of (`dx`, `dy`) pixels; on the globe above
    /// [`ORBIT_ABOVE`], orbits instead: the Earth turns under the eye (dragging right
    /// brings the land to the east into view), at the same height, heading and pitch.
    pub fn look(&mut self, dx: f64, dy: f64) {
        let height = self.height();
        if self.globe && height > ORBIT_ABOVE {
            let (lon, lat, _) = crate::globe::geodetic(self.eye);
            // A drag across the screen covers about the view's width on the ground.
            let step = 0.004 * height / crate::globe::A;
            let lat = (lat + dy * step).clamp(-1.55, 1.55);
            self.eye = crate::globe::ecef(lon + dx * step / lat.cos().max(0.05), lat, height);
            return;
        }
        self.yaw += dx * 0.004;
        self.pitch = (self.pitch - dy * 0.004).clamp(-1.5, 1.5);
    }

    /// Scales the speed by 1.25 per wheel notch (`notches` > 0: faster).
    pub fn scale_speed(&mut self, notches: f64) {
        self.speed = (self.speed * 1.25f64.powf(notches)).clamp(0.01, 100.0);
    }

    /// Moves for `dt` seconds as `input` asks, never below `ground(eye)` (the terrain's
    /// height under a scene point, where it is known).
    pub fn step(&mut self, dt: f64, input: FlyInput, ground: impl Fn(DVec3) -> Option<f64>) {
        let altitude = (self.height() - ground(self.eye).unwrap_or(0.0)).max(1.0);
        let speed = altitude.max(20.0) * self.speed * dt;
        let (_, _, up) = self.frame();
        let forward = self.forward();
        let right = (forward - up * forward.dot(up)).normalize_or_zero().cross(up);
        let step = forward * input.forward + right * input.right + up * input.up;
        self.eye += step.normalize_or_zero() * speed;
        // On the globe, the ellipsoid is the ground where no height is known yet.
        let known = ground(self.eye);
        if let Some(g) = known.or(self.globe.then_some(0.0)) {
            let below = g + CLEARANCE - self.height();
            if below > 0.0 {
                self.eye += self.frame().2 * below;
            }
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A transverse Mercator centred at 122.6 W, 37.9 N, one metre a world unit, its
    /// north-west corner at CRS (-5000, 5000).
    fn placed() -> Metadata {
        let mut m = Metadata::new("placed", vec![]);
        m.georeference = Some(terrastream_format::Georeference {
            definition: Some(
                "+proj=tmerc +lat_0=37.9 +lon_0=-122.6 +k=1 +x_0=0 +y_0=0 +datum=WGS84 +units=m +no_defs".into(),
            ),
            origin: Some([-5000.0, 5000.0]),
            scale: Some([1.0, 1.0]),
            ..Default::default()
        });
        m
    }

    #[test]
    fn poses_follow_cesiums_conventions() {
        let m = placed();
        let look = |heading: f64, pitch: f64| {
            let (eye, target) =
                Pose::parse("-122.6,37.9,500", heading, pitch).unwrap().eye_target(&m, &Surface::Flat).unwrap();
            (eye, (target - eye).normalize())
        };
        let (eye, north) = look(0.0, 0.0);
        // The projection's centre is the CRS origin: world (5000, 5000); heights as given.
        assert!((eye - DVec3::new(5000.0, 500.0, 5000.0)).length() < 1e-3, "{eye}");
        // x east, y up, z south.
        assert!((north - DVec3::NEG_Z).length() < 1e-6, "heading 0 looks north: {north}");
        assert!((look(90.0, 0.0).1 - DVec3::X).length() < 1e-6, "heading 90 looks east");
        assert!((look(180.0, 0.0).1 - DVec3::Z).length() < 1e-6, "heading 180 looks south");
        assert!((look(0.0, -90.0).1 - DVec3::NEG_Y).length() < 1e-6, "pitch -90 looks down");
        let down = look(0.0, -30.0).1;
        assert!((down.y - (-30f64).to_radians().sin()).abs() < 1e-9);
    }

    #[test]
    fn north_is_true_north_off_the_central_meridian() {
        // One degree east of the central meridian at 37.9 N the grid's north is turned
        // by the meridian convergence, about 1 degree * sin(37.9) = 0.61 degrees.
        let (eye, target) =
            Pose::parse("-121.6,37.9,0", 0.0, 0.0).unwrap().eye_target(&placed(), &Surface::Flat).unwrap();
        let d = target - eye;
        let turned = d.x.atan2(-d.z).to_degrees();
        assert!((turned.abs() - 0.614).abs() < 0.01, "north is turned {turned} degrees from grid north");
    }

    #[test]
    fn bad_poses_are_named() {
        assert!(Pose::parse("200,0,0", 0.0, 0.0).unwrap_err().contains("longitude"));
        assert!(Pose::parse("1,2", 0.0, 0.0).unwrap_err().contains("three numbers"));
        assert!(Pose::parse("1,2,x", 0.0, 0.0).unwrap_err().contains("LON,LAT,HEIGHT"));
        assert!(Pose::parse("1,2,3", 0.0, -100.0).unwrap_err().contains("pitch"));
        let unplaced = Pose::parse("1,2,3", 0.0, 0.0)
            .unwrap()
            .eye_target(&Metadata::new("unplaced", vec![]), &Surface::Flat)
            .unwrap_err();
        assert!(unplaced.contains("says where it lies"), "{unplaced}");
    }

    #[test]
    fn round_trips_a_camera_direction() {
        let c = Camera::look_at(DVec3::new(0.0, 100.0, 0.0), DVec3::new(100.0, 0.0, -100.0), 64, 64);
        let fly = FlyCamera::from_camera(&c);
        assert!((fly.forward() - c.direction()).length() < 1e-9);
        assert!((fly.camera(64, 64).direction() - c.direction()).length() < 1e-9);
    }

    fn continent() -> Metadata {
        let layer = Layer {
            name: "elevation".into(),
            kind: LayerKind::Elevation,
            format: terrastream_format::TileFormat::RawU16,
            compression: terrastream_format::PayloadCompression::Zstd,
            tile_resolution: 256,
            border: 1,
            num_x_tiles: 40,
            num_y_tiles: 24,
            num_lods: 7,
            tile_world_size: 250_000.0, // 10 000 km x 6 000 km
            elevation: None,
            extent: None,
        };
        let mut m = Metadata::new("continent", vec![layer]);
        m.terrain.min_elevation = -100.0;
        m.terrain.max_elevation = 5000.0;
        m
    }

    #[test]
    fn every_front_end_camera_sees_the_whole_continent() {
        let m = continent();
        let terrain = terrain_box(&m);
        let start = start_camera(&m, &Surface::Flat, None, 1280, 720);
        // The flyer's camera (view, webplayer) and the still's (render) are one camera.
        let flown = FlyCamera::from_camera(&start).camera(1280, 720).enclosing(&terrain.into());
        assert!((flown.position - start.position).length() < 1e-6 && (flown.far - start.far).abs() < 1e-3);
        for camera in [start, flown] {
            let farthest = terrain.corners().iter().map(|c| c.distance(camera.position)).fold(0.0, f64::max);
            assert!(camera.far > farthest, "far {} < farthest corner {farthest}", camera.far);
            assert!(camera.frustum().intersects(&terrain));
        }
        // Low over one corner, looking across: the far side is still inside the far plane.
        let low = FlyCamera { eye: DVec3::new(10.0, 300.0, 10.0), yaw: 2.3, pitch: -0.05, speed: 1.0, globe: false };
        let camera = low.camera(1280, 720).enclosing(&terrain.into());
        assert!(camera.far > DVec3::new(1.0e7, 0.0, 6.0e6).length());
        assert!(camera.near <= 0.1 * 300.0 + 1e-9);
    }

    #[test]
    fn the_default_view_fills_most_of_the_frame() {
        for (width, height) in [(1280, 720), (800, 600), (600, 900)] {
            let m = continent();
            let camera = default_camera(&m, &Surface::Flat, width, height);
            let clip = camera.view_projection();
            let (mut lo, mut hi) = (DVec2::splat(f64::MAX), DVec2::splat(f64::MIN));
            for c in terrain_box(&m).corners() {
                let p = clip * c.extend(1.0);
                let ndc = DVec2::new(p.x / p.w, p.y / p.w);
                lo = lo.min(ndc);
                hi = hi.max(ndc);
            }
            let filled = ((hi.x - lo.x) / 2.0).max((hi.y - lo.y) / 2.0);
            assert!(lo.x >= -FRAME_FILL - 1e-6 && hi.x <= FRAME_FILL + 1e-6, "{lo} {hi}");
            assert!(filled > 0.85, "{width}x{height}: the terrain spans {filled:.2} of the frame");
        }
    }

    #[test]
    fn the_default_view_frames_the_data_not_the_grid_around_it() {
        // 4 x 3 tiles of 2 500 km; the data ends 8 000 km east and 5 000 km south.
        let mut m = continent();
        m.layers[0].num_x_tiles = 4;
        m.layers[0].num_y_tiles = 3;
        m.layers[0].tile_world_size = 2.5e6;
        m.terrain.data_extent = Some([8.0e6, 5.0e6]);
        assert_eq!(terrain_bounds(&m).0, [0.0, 0.0, 8.0e6, 5.0e6]);
        let camera = default_camera(&m, &Surface::Flat, 1280, 720);
        // Looking at the data's middle: the ray from the eye meets its ground there.
        let (eye, dir) = (camera.position, camera.direction());
        let t = (drawn_heights(&m).0 - eye.y) / dir.y;
        let ground = eye + dir * t;
        assert!((ground.x - 4.0e6).abs() < 2.0e5, "{ground}");
        // A grid without the field is framed whole.
        m.terrain.data_extent = None;
        assert_eq!(terrain_bounds(&m).0, [0.0, 0.0, 1.0e7, 7.5e6]);
    }

    #[test]
    fn a_texture_only_archive_is_drawn_flat_at_its_minimum_elevation() {
        let mut m = continent();
        m.layers[0].kind = LayerKind::Texture;
        assert_eq!(drawn_heights(&m), (-100.0, -100.0));
        m.terrain.min_elevation = 0.0;
        m.terrain.max_elevation = 0.0;
        assert_eq!(drawn_heights(&m), (0.0, 0.0));
    }

    #[test]
    fn on_the_globe_the_flyer_keeps_north_up_and_the_ground_below() {
        let eye = crate::globe::ecef(86.9_f64.to_radians(), 27.9_f64.to_radians(), 9000.0);
        let pose = Pose::parse("86.9,27.9,9000", 90.0, -10.0).unwrap();
        let (lon, lat) = (86.9_f64.to_radians(), 27.9_f64.to_radians());
        let frame = crate::globe::enu(lon, lat);
        let direction = (frame.x_axis * 10f64.to_radians().cos()) - frame.z_axis * 10f64.to_radians().sin();
        let mut camera = Camera::look_at(eye, eye + direction * 1000.0, 64, 64);
        camera.zenith = frame.z_axis;
        let mut fly = FlyCamera::from_camera(&camera);
        assert!(fly.globe);
        assert!(
            (fly.yaw.to_degrees() - pose.heading).abs() < 1e-9 && (fly.pitch.to_degrees() - pose.pitch).abs() < 1e-9
        );
        assert!((fly.camera(64, 64).direction() - direction).length() < 1e-9);
        // A second's flight 1 000 m above the ground: 1 000 m along the view.
        let before = fly.eye;
        fly.step(1.0, FlyInput { forward: 1.0, ..FlyInput::default() }, |_| Some(8000.0));
        assert!(((fly.eye - before).length() - 1000.0).abs() < 1e-6, "{}", (fly.eye - before).length());
        // Straight down for a long time: on the ground, never under it.
        fly.step(100.0, FlyInput { up: -1.0, ..FlyInput::default() }, |_| Some(8000.0));
        assert!((fly.height() - (8000.0 + CLEARANCE)).abs() < 1e-3, "{}", fly.height());
    }

    #[test]
    fn high_above_the_globe_a_drag_orbits_and_low_it_turns() {
        let eye = crate::globe::ecef(0.0, 0.0, 1.0e7);
        let frame = crate::globe::enu(0.0, 0.0);
        let mut camera = Camera::look_at(eye, DVec3::ZERO, 64, 64);
        camera.zenith = frame.z_axis;
        let mut fly = FlyCamera::from_camera(&camera);
        fly.look(100.0, 0.0);
        let (lon, lat, h) = crate::globe::geodetic(fly.eye);
        assert!(lon > 0.05 && lat.abs() < 1e-9 && (h - 1.0e7).abs() < 1e-3, "{lon} {lat} {h}");
        assert!((fly.forward() + fly.eye.normalize()).length() < 1e-6, "still looking straight down");
        // Low, the same drag turns the view in place.
        let low = crate::globe::ecef(0.0, 0.0, 1000.0);
        let mut fly = FlyCamera { eye: low, yaw: 0.0, pitch: 0.0, speed: 1.0, globe: true };
        fly.look(100.0, 0.0);
        assert!(fly.eye == low && (fly.yaw - 0.4).abs() < 1e-12);
    }

    #[test]
    fn speed_follows_altitude_and_ground_stops_descent() {
        let mut fly = FlyCamera { eye: DVec3::new(0.0, 1000.0, 0.0), yaw: 0.0, pitch: 0.0, speed: 1.0, globe: false };
        fly.step(0.5, FlyInput { forward: 1.0, ..FlyInput::default() }, |_| Some(0.0));
        // Half a second at 1000 m: 500 m north (-z).
        assert!((fly.eye.z + 500.0).abs() < 1e-6, "{:?}", fly.eye);
        fly.step(10.0, FlyInput { up: -1.0, ..FlyInput::default() }, |_| Some(990.0));
        assert!((fly.eye.y - (990.0 + CLEARANCE)).abs() < 1e-9, "{:?}", fly.eye);
        fly.look(0.0, 1e6);
        assert!(fly.pitch >= -1.5);
        fly.scale_speed(1e3);
        assert!(fly.speed <= 100.0);
    }
}

/// A camera pose in geographic terms, with CesiumJS's conventions: the eye at a longitude
/// and latitude (degrees, WGS 84) and a height (metres), heading clockwise from north and
/// pitch from the horizontal (negative: looking down), both in degrees.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Pose {
    /// Longitude of the eye.
    pub lon: f64,
    /// Latitude of the eye.
    pub lat: f64,
    /// Height of the eye (metres; the archive's height datum).
    pub height: f64,
    /// Degrees clockwise from north.
    pub heading: f64,
    /// Degrees above the horizontal (negative: down).
    pub pitch: f64,
}

impl Pose {
    /// The pose of `at` ("LON,LAT,HEIGHT"), `heading` and `pitch`.
    ///
    /// # Errors
    /// A message naming the bad value.
    pub fn parse(at: &str, heading: f64, pitch: f64) -> Result<Self, String> {
        let v: Vec<f64> = at
            .split(',')
            .map(|p| p.trim().parse::<f64>())
            .collect::<Result<_, _>>()
            .map_err(|_| format!("at {at:?}: expected LON,LAT,HEIGHT (degrees, degrees, metres)"))?;
        let [lon, lat, height] = v[..] else {
            return Err(format!("at {at:?}: expected three numbers LON,LAT,HEIGHT"));
        };
        if !(-180.0..=180.0).contains(&lon) || !(-90.0..=90.0).contains(&lat) || !height.is_finite() {
            return Err(format!("at {at:?}: longitude -180..180, latitude -90..90, a finite height"));
        }
        if !heading.is_finite() || !(-90.0..=90.0).contains(&pitch) {
            return Err(format!("heading {heading}, pitch {pitch}: a finite heading, pitch -90..90"));
        }
        Ok(Self { lon, lat, height, heading, pitch })
    }

    /// The eye and a target one kilometre along the view, in `metadata`'s world: north
    /// and east are measured on the archive's grid at the eye (a projected grid's north
    /// is not its -z axis away from the central meridian).
    ///
    /// # Errors
    /// A message when the archive does not say where it lies, or the eye has no place in
    /// its CRS.
    pub fn eye_target(&self, metadata: &Metadata, surface: &Surface) -> Result<(DVec3, DVec3), String> {
        if surface.globe().is_some() {
            let (lon, lat) = (self.lon.to_radians(), self.lat.to_radians());
            let eye = crate::globe::ecef(lon, lat, self.height);
            let frame = crate::globe::enu(lon, lat);
            let (heading, pitch) = (self.heading.to_radians(), self.pitch.to_radians());
            let flat = frame.y_axis * heading.cos() + frame.x_axis * heading.sin();
            let direction = flat * pitch.cos() + frame.z_axis * pitch.sin();
            return Ok((eye, eye + direction * 1000.0));
        }
        let geo = crate::geo::Geo::new(metadata)
            .ok_or("a camera in longitude and latitude needs an archive that says where it lies (a georeference)")?;
        let world = |lon: f64, lat: f64| {
            geo.lon_lat_to_world(lon, lat)
                .ok_or_else(|| format!("{lon},{lat} has no place in the archive's CRS"))
                .map(|(x, z)| DVec2::new(x, z))
        };
        let eye = world(self.lon, self.lat)?;
        // A step of about a metre north and east, as the grid draws them.
        let step = 1e-5;
        let north = (world(self.lon, (self.lat + step).min(90.0))? - eye).try_normalize().unwrap_or(DVec2::NEG_Y);
        let east = (world(self.lon + step, self.lat)? - eye).try_normalize().unwrap_or(DVec2::X);
        let (heading, pitch) = (self.heading.to_radians(), self.pitch.to_radians());
        let flat = north * heading.cos() + east * heading.sin();
        let direction = DVec3::new(flat.x * pitch.cos(), pitch.sin(), flat.y * pitch.cos());
        let position = DVec3::new(eye.x, self.height, eye.y);
        Ok((position, position + direction * 1000.0))
    }
}
