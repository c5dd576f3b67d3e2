// The atmosphere: Hillaire 2020, "A Scalable and Production Ready Sky and Atmosphere
// Rendering Technique" — Rayleigh, Mie and ozone over a spherical planet, a transmittance
// table and a multiple-scattering table computed once (render passes, so WebGL2 runs
// them too), then the sky and the aerial perspective ray-marched through them.
//
// Shared functions. The module that includes this declares:
//   var<uniform> ATMO: AtmosphereUniform;
//   var transmittance_lut: texture_2d<f32>;   (256 x 64)
//   var multiscattering_lut: texture_2d<f32>; (32 x 32)
//   var lut_sampler: sampler;                 (linear, clamped)
//
// Units: metres, radiance for a sun of illuminance 1. Positions are relative to the
// planet's centre on a sphere of BOTTOM radius (the caller scales its ellipsoid radius
// at the anchor to it).

const BOTTOM: f32 = 6360000.0;
const TOP: f32 = 6460000.0;
const PI: f32 = 3.14159265358979;
const RAYLEIGH_SCATTERING: vec3<f32> = vec3<f32>(5.802e-6, 13.558e-6, 33.1e-6);
const RAYLEIGH_HEIGHT: f32 = 8000.0;
const MIE_SCATTERING: f32 = 3.996e-6;
const MIE_EXTINCTION: f32 = 4.440e-6;
const MIE_HEIGHT: f32 = 1200.0;
const MIE_G: f32 = 0.8;
const OZONE_ABSORPTION: vec3<f32> = vec3<f32>(0.650e-6, 1.881e-6, 0.085e-6);
const GROUND_ALBEDO: f32 = 0.3;
// The share of the air between the eye and the ground that the ground is seen through:
// its in-scattered light and its optical depth are scaled by it (the sky's rays are not).
// Measured against CesiumJS's ground atmosphere (tests/cesium.rs,
// the_sky_and_the_haze_look_like_cesiums): with the whole column (1.0), desert 40 to
// 70 km away from 3 km up was a white bank, CIE76 25.7 from Cesium's; at 0.5, 18.
const GROUND_HAZE: f32 = 0.5;

// Ground of `radiance` seen through air that scatters `light` towards the eye and lets
// `transmittance` through, as GROUND_HAZE has it.
fn ground_seen(radiance: vec3<f32>, light: vec3<f32>, transmittance: vec3<f32>) -> vec3<f32> {
    return radiance * pow(transmittance, vec3<f32>(GROUND_HAZE)) + light * GROUND_HAZE;
}

// The sky's light on ground whose up is `up` and the sun `sun` (a share of a sun of
// illuminance 1): about a fifth of the direct light when the sun is high, bluish.
fn sky_light(up: vec3<f32>, sun: vec3<f32>) -> vec3<f32> {
    return (0.05 + 0.1 * max(dot(up, sun), 0.0)) * vec3<f32>(0.6, 0.75, 1.0);
}

struct AtmosphereUniform {
    // Camera-relative rotation and projection, inverted: view rays from clip space.
    inv_view_proj: mat4x4<f32>,
    // xyz: the eye relative to the planet's centre, at its height above the BOTTOM sphere,
    // w: the scale from frame metres to metres about that sphere.
    eye: vec4<f32>,
    // xyz: direction to the sun (frame axes), w: the sun's angular radius.
    sun: vec4<f32>,
    // x: exposure, y: 1 to draw the atmosphere, z: steps of the sky, w: steps of the
    // aerial perspective.
    look: vec4<f32>,
    // xyz: the planet's axis towards the north pole (frame axes); w: the highest ground
    // beyond the data the eye can see, metres (0 without the whole-Earth picture).
    pole: vec4<f32>,
    // x: 1 when the eye is inside the atmosphere and the per-frame tables serve the sky
    // and the aerial perspective (else both are ray-marched per pixel), y: the aerial
    // perspective's farthest distance, zw: the viewport in pixels.
    tables: vec4<f32>,
    // xyz: the prime meridian at the equator (frame axes), w: 1 to draw the whole-Earth
    // picture on the ground beyond the data (else plain ground).
    meridian: vec4<f32>,
}

struct Medium {
    rayleigh: vec3<f32>,
    mie: f32,
    extinction: vec3<f32>,
}

fn medium(height: f32) -> Medium {
    let h = max(height, 0.0);
    let r = exp(-h / RAYLEIGH_HEIGHT);
    let m = exp(-h / MIE_HEIGHT);
    let ozone = max(0.0, 1.0 - abs(h - 25000.0) / 15000.0);
    let rayleigh = RAYLEIGH_SCATTERING * r;
    let mie = MIE_SCATTERING * m;
    return Medium(rayleigh, mie, rayleigh + vec3<f32>(MIE_EXTINCTION * m) + OZONE_ABSORPTION * ozone);
}

// Distance along a unit ray from `o` to the sphere of radius `r` at the origin: the far
// intersection when inside, the near one when outside; -1 when it misses.
fn ray_sphere(o: vec3<f32>, d: vec3<f32>, r: f32) -> f32 {
    let b = dot(o, d);
    // As a product: |o|^2 - r^2 cancels in f32 6 400 km from the centre.
    let lo = length(o);
    let c = (lo - r) * (lo + r);
    let disc = b * b - c;
    if disc < 0.0 {
        return -1.0;
    }
    let s = sqrt(disc);
    if c > 0.0 {
        // Outside: the near hit, if ahead.
        let t = -b - s;
        return select(-1.0, t, t >= 0.0);
    }
    return -b + s;
}

fn rayleigh_phase(c: f32) -> f32 {
    return 3.0 / (16.0 * PI) * (1.0 + c * c);
}

// Cornette-Shanks.
fn mie_phase(c: f32) -> f32 {
    let g = MIE_G;
    let k = 3.0 / (8.0 * PI) * (1.0 - g * g) / (2.0 + g * g);
    return k * (1.0 + c * c) / pow(max(1.0 + g * g - 2.0 * g * c, 1.0e-4), 1.5);
}

// Table coordinates: u the cosine of the zenith angle, v the height (square-rooted, more
// rows near the ground).
fn lut_uv(r: f32, mu: f32) -> vec2<f32> {
    let h = clamp((r - BOTTOM) / (TOP - BOTTOM), 0.0, 1.0);
    return vec2<f32>(clamp(0.5 + 0.5 * mu, 0.0, 1.0), sqrt(h));
}

fn lut_r_mu(uv: vec2<f32>) -> vec2<f32> {
    return vec2<f32>(BOTTOM + uv.y * uv.y * (TOP - BOTTOM), uv.x * 2.0 - 1.0);
}

fn transmittance_to_top(p: vec3<f32>, d: vec3<f32>) -> vec3<f32> {
    let r = length(p);
    return textureSampleLevel(transmittance_lut, lut_sampler, lut_uv(r, dot(p, d) / r), 0.0).rgb;
}

fn multiscattering(p: vec3<f32>, sun: vec3<f32>) -> vec3<f32> {
    let r = length(p);
    return textureSampleLevel(multiscattering_lut, lut_sampler, lut_uv(r, dot(p, sun) / r), 0.0).rgb;
}

struct Scattered {
    light: vec3<f32>,
    transmittance: vec3<f32>,
}

// In-scattered light and transmittance along a ray from `o` (inside or outside the
// atmosphere) for `t_max` metres (or to the ground or the atmosphere's top), `steps`
// samples, single scattering through the transmittance table plus the multiple-scattering
// table's share.
fn integrate(o: vec3<f32>, d: vec3<f32>, t_max: f32, sun: vec3<f32>, steps: f32) -> Scattered {
    // The stretch of the ray inside the atmosphere's sphere, the ground's hit, t_max.
    let b = dot(o, d);
    let lo = length(o);
    let disc = b * b - (lo - TOP) * (lo + TOP);
    if disc < 0.0 {
        return Scattered(vec3<f32>(0.0), vec3<f32>(1.0));
    }
    let s = sqrt(disc);
    let start = max(0.0, -b - s);
    var end = min(t_max, -b + s);
    let ground = ray_sphere(o, d, BOTTOM);
    if ground > 0.0 {
        end = min(end, ground);
    }
    if end <= start {
        return Scattered(vec3<f32>(0.0), vec3<f32>(1.0));
    }
    let c = dot(d, sun);
    let phase_r = rayleigh_phase(c);
    let phase_m = mie_phase(c);
    var light = vec3<f32>(0.0);
    var transmittance = vec3<f32>(1.0);
    let dt = (end - start) / steps;
    for (var i = 0.0; i < steps; i += 1.0) {
        let t = start + (i + 0.5) * dt;
        let p = o + d * t;
        let r = length(p);
        let m = medium(r - BOTTOM);
        let step = exp(-m.extinction * dt);
        // The sun, unless the planet is in the way.
        var sun_t = transmittance_to_top(p, sun);
        if ray_sphere(p, sun, min(BOTTOM, r) - 100.0) > 0.0 {
            sun_t = vec3<f32>(0.0);
        }
        let ms = multiscattering(p, sun);
        let scattered = (m.rayleigh * phase_r + vec3<f32>(m.mie * phase_m)) * sun_t + (m.rayleigh + vec3<f32>(m.mie)) * ms;
        // Integrated analytically over the step (Hillaire 2015).
        let through = (scattered - scattered * step) / max(m.extinction, vec3<f32>(1.0e-12));
        light += transmittance * through;
        transmittance *= step;
    }
    return Scattered(light, transmittance);
}

// The sky-view table (192 x 108, made per frame from inside the atmosphere): u the
// azimuth from the sun's (0..pi, the sky is symmetric about the sun's vertical), v the
// elevation, square-rooted about the horizon so that its rows crowd there.
const SKY_VIEW_SIZE: vec2<f32> = vec2<f32>(192.0, 108.0);
// The aerial-perspective table: 32 x 32 rays over the screen, 32 distances (squared
// spacing out to tables.y), laid side by side in a 1024 x 32 texture.
const AERIAL_SLICES: f32 = 32.0;

struct ViewFrame {
    up: vec3<f32>,
    sun_h: vec3<f32>,
    side: vec3<f32>,
    horizon: f32,
}

fn view_frame(eye: vec3<f32>, sun: vec3<f32>) -> ViewFrame {
    let up = normalize(eye);
    var sun_h = sun - up * dot(sun, up);
    if dot(sun_h, sun_h) < 1.0e-8 {
        sun_h = cross(up, select(vec3<f32>(1.0, 0.0, 0.0), vec3<f32>(0.0, 0.0, 1.0), abs(up.x) > 0.9));
    }
    sun_h = normalize(sun_h);
    let r = length(eye);
    let horizon = -acos(clamp(sqrt(max(r * r - BOTTOM * BOTTOM, 0.0)) / r, 0.0, 1.0));
    return ViewFrame(up, sun_h, cross(up, sun_h), horizon);
}

fn sky_view_uv(f: ViewFrame, d: vec3<f32>) -> vec2<f32> {
    let elevation = asin(clamp(dot(d, f.up), -1.0, 1.0));
    var h = d - f.up * dot(d, f.up);
    var azimuth = 0.0;
    if dot(h, h) > 1.0e-12 {
        h = normalize(h);
        azimuth = acos(clamp(dot(h, f.sun_h), -1.0, 1.0));
    }
    var v = 0.0;
    if elevation >= f.horizon {
        v = 0.5 - 0.5 * sqrt((elevation - f.horizon) / (PI / 2.0 - f.horizon));
    } else {
        v = 0.5 + 0.5 * sqrt((f.horizon - elevation) / (f.horizon + PI / 2.0));
    }
    // Half a texel in from each edge, so the rows at the horizon are sampled, not blended.
    let texel = 1.0 / SKY_VIEW_SIZE;
    return vec2<f32>(azimuth / PI, v) * (1.0 - texel) + texel * 0.5;
}

fn sky_view_direction(f: ViewFrame, uv: vec2<f32>) -> vec3<f32> {
    let texel = 1.0 / SKY_VIEW_SIZE;
    let q = clamp((uv - texel * 0.5) / (1.0 - texel), vec2<f32>(0.0), vec2<f32>(1.0));
    var elevation = 0.0;
    if q.y < 0.5 {
        let t = (1.0 - 2.0 * q.y) * (1.0 - 2.0 * q.y);
        elevation = f.horizon + t * (PI / 2.0 - f.horizon);
    } else {
        let t = (2.0 * q.y - 1.0) * (2.0 * q.y - 1.0);
        elevation = f.horizon - t * (f.horizon + PI / 2.0);
    }
    let azimuth = q.x * PI;
    let horizontal = f.sun_h * cos(azimuth) + f.side * sin(azimuth);
    return normalize(horizontal * cos(elevation) + f.up * sin(elevation));
}

// Distance of aerial-perspective slice `k` (0..32), squared spacing.
fn aerial_distance(k: f32) -> f32 {
    let s = k / AERIAL_SLICES;
    return s * s * ATMO.tables.y;
}

// Display: an exposure and a soft shoulder, so the sun-lit sky and ground fit in.
fn expose(radiance: vec3<f32>) -> vec3<f32> {
    return vec3<f32>(1.0) - exp(-radiance * ATMO.look.x);
}
