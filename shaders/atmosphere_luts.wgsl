// The atmosphere's tables (appended to atmosphere.wgsl): transmittance to the top of the
// atmosphere (256 x 64) and the multiple-scattering contribution (32 x 32), made once;
// the sky view and the aerial perspective, made per frame from inside the atmosphere.
// Each is a fullscreen triangle into its texture.

@group(0) @binding(0) var<uniform> ATMO: AtmosphereUniform;
@group(0) @binding(1) var transmittance_lut: texture_2d<f32>;
@group(0) @binding(2) var multiscattering_lut: texture_2d<f32>;
@group(0) @binding(3) var lut_sampler: sampler;

struct Fullscreen {
    @builtin(position) clip: vec4<f32>,
    @location(0) uv: vec2<f32>,
}

@vertex
fn vs_main(@builtin(vertex_index) i: u32) -> Fullscreen {
    let xy = vec2<f32>(f32((i << 1u) & 2u), f32(i & 2u));
    return Fullscreen(vec4<f32>(xy * 2.0 - 1.0, 0.0, 1.0), vec2<f32>(xy.x, 1.0 - xy.y));
}

@fragment
fn fs_transmittance(in: Fullscreen) -> @location(0) vec4<f32> {
    let rm = lut_r_mu(in.uv);
    let p = vec3<f32>(0.0, rm.x, 0.0);
    let d = vec3<f32>(sqrt(max(1.0 - rm.y * rm.y, 0.0)), rm.y, 0.0);
    let length_to_top = ray_sphere(p, d, TOP);
    let steps = 40.0;
    let dt = length_to_top / steps;
    var depth = vec3<f32>(0.0);
    for (var i = 0.0; i < steps; i += 1.0) {
        let q = p + d * ((i + 0.5) * dt);
        depth += medium(length(q) - BOTTOM).extinction * dt;
    }
    return vec4<f32>(exp(-depth), 1.0);
}

// Hillaire 2020, section 5.5: second-order light over the sphere of directions with an
// isotropic phase, and the transfer factor f_ms; their infinite series is L2 / (1 - f_ms).
@fragment
fn fs_multiscattering(in: Fullscreen) -> @location(0) vec4<f32> {
    let rm = lut_r_mu(in.uv);
    let p = vec3<f32>(0.0, rm.x, 0.0);
    let sun = vec3<f32>(sqrt(max(1.0 - rm.y * rm.y, 0.0)), rm.y, 0.0);
    let isotropic = 1.0 / (4.0 * PI);
    var l2 = vec3<f32>(0.0);
    var fms = vec3<f32>(0.0);
    let n = 8.0;
    for (var i = 0.0; i < n; i += 1.0) {
        for (var j = 0.0; j < n; j += 1.0) {
            let theta = (i + 0.5) / n * 2.0 * PI;
            let cos_phi = 1.0 - 2.0 * (j + 0.5) / n;
            let sin_phi = sqrt(max(1.0 - cos_phi * cos_phi, 0.0));
            let d = vec3<f32>(cos(theta) * sin_phi, cos_phi, sin(theta) * sin_phi);
            var end = ray_sphere(p, d, TOP);
            let ground = ray_sphere(p, d, BOTTOM);
            if ground > 0.0 {
                end = ground;
            }
            let steps = 20.0;
            let dt = end / steps;
            var light = vec3<f32>(0.0);
            var f = vec3<f32>(0.0);
            var transmittance = vec3<f32>(1.0);
            for (var k = 0.0; k < steps; k += 1.0) {
                let q = p + d * ((k + 0.5) * dt);
                let m = medium(length(q) - BOTTOM);
                let step = exp(-m.extinction * dt);
                let scattering = m.rayleigh + vec3<f32>(m.mie);
                let ext = max(m.extinction, vec3<f32>(1.0e-12));
                f += transmittance * (scattering - scattering * step) / ext;
                var sun_t = transmittance_to_top(q, sun);
                if ray_sphere(q, sun, BOTTOM) > 0.0 {
                    sun_t = vec3<f32>(0.0);
                }
                let s = sun_t * scattering * isotropic;
                light += transmittance * (s - s * step) / ext;
                transmittance *= step;
            }
            if ground > 0.0 {
                // Light the ground sends back up (Lambertian).
                let g = p + d * ground;
                let up = normalize(g);
                light += transmittance * transmittance_to_top(g, sun) * max(dot(up, sun), 0.0) * GROUND_ALBEDO / PI;
            }
            l2 += light / (n * n);
            fms += f / (n * n);
        }
    }
    return vec4<f32>(l2 / (vec3<f32>(1.0) - fms), 1.0);
}

@fragment
fn fs_skyview(in: Fullscreen) -> @location(0) vec4<f32> {
    let sun = ATMO.sun.xyz;
    let f = view_frame(ATMO.eye.xyz, sun);
    let d = sky_view_direction(f, in.uv);
    return vec4<f32>(integrate(ATMO.eye.xyz, d, 1.0e9, sun, 20.0).light, 1.0);
}

// One froxel: the light scattered towards the eye along its screen ray out to its slice's
// distance (rgb), and the mean transmittance over that stretch (a), both as the ground is
// seen through them (GROUND_HAZE: the table serves only the ground). The slices' distances
// grow as the square of their number, so the near ones are short: 2 steps for the first
// eight, one more for every four after, 8 for the last four (148 steps a ray, not 256).
@fragment
fn fs_aerial(in: Fullscreen) -> @location(0) vec4<f32> {
    let texel = in.uv * vec2<f32>(AERIAL_SLICES * 32.0, 32.0);
    let slice = floor(texel.x / 32.0);
    let xy = (vec2<f32>(texel.x - slice * 32.0, texel.y)) / 32.0;
    // Screen rays: x right, y up in clip space, row 0 at the top.
    let ndc = vec2<f32>(xy.x * 2.0 - 1.0, 1.0 - xy.y * 2.0);
    let far = ATMO.inv_view_proj * vec4<f32>(ndc, 1.0, 1.0);
    let d = normalize(far.xyz / far.w);
    let distance = aerial_distance(slice + 1.0);
    let steps = clamp(ceil((slice + 1.0) / 4.0), 2.0, 8.0);
    let s = integrate(ATMO.eye.xyz, d, distance, ATMO.sun.xyz, steps);
    return vec4<f32>(s.light * GROUND_HAZE, pow(dot(s.transmittance, vec3<f32>(1.0 / 3.0)), GROUND_HAZE));
}
