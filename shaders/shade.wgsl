// An elevation tile's shade texels, made on the GPU as the tile is uploaded (one
// fullscreen pass into its layer of the shade array): for each sample, x and z of the
// terrain's normal there (y is the rest of a unit vector), made as the lit shader made it
// from the four neighbours, normalize(h west - h east, 2 spacing, h north - h south); 1
// where the sample and its four neighbours are one height within half a metre of 0 (a
// flat sea, as SRTM and Copernicus store it); and 1 where the sample and its four
// neighbours have data (the normal is there), else 0: along the tile's outermost samples,
// whose neighbours lie in other tiles, and beside no data. Normals are stored as
// n * 0.5 + 0.5 (unorm: renderable on WebGL2 too). Filtered bilinearly, one sample gives
// the terrain's fragment shader what twelve height loads gave it.

struct Job {
    // The tile's array layer, its samples' spacing (metres), samples per edge.
    slot: i32,
    spacing: f32,
    edge: i32,
    unused: i32,
}

@group(0) @binding(0) var heights: texture_2d_array<f32>;
@group(0) @binding(1) var<uniform> job: Job;

const NODATA: f32 = -1.0e30;
const NONE: vec4<f32> = vec4<f32>(0.5, 0.5, 0.0, 0.0);

@vertex
fn vs_main(@builtin(vertex_index) i: u32) -> @builtin(position) vec4<f32> {
    let uv = vec2<f32>(f32((i << 1u) & 2u), f32(i & 2u));
    return vec4<f32>(uv * 2.0 - 1.0, 0.0, 1.0);
}

@fragment
fn fs_shade(@builtin(position) at: vec4<f32>) -> @location(0) vec4<f32> {
    let p = vec2<i32>(at.xy);
    if any(p < vec2<i32>(1)) || any(p > vec2<i32>(job.edge - 2)) {
        return NONE;
    }
    let h = textureLoad(heights, p, job.slot, 0).r;
    let w = textureLoad(heights, p - vec2<i32>(1, 0), job.slot, 0).r;
    let e = textureLoad(heights, p + vec2<i32>(1, 0), job.slot, 0).r;
    let n = textureLoad(heights, p - vec2<i32>(0, 1), job.slot, 0).r;
    let s = textureLoad(heights, p + vec2<i32>(0, 1), job.slot, 0).r;
    if min(min(h, w), min(min(e, n), s)) <= NODATA * 0.5 {
        return NONE;
    }
    let normal = normalize(vec3<f32>(w - e, 2.0 * job.spacing, n - s));
    let sea = (abs(h) < 0.5) & (w == h) & (e == h) & (n == h) & (s == h);
    return vec4<f32>(normal.x * 0.5 + 0.5, normal.z * 0.5 + 0.5, select(0.0, 1.0, sea), 1.0);
}
