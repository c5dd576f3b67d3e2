// An elevation tile's shade texels, made on the GPU as the tile is uploaded (one
// fullscreen pass into its layer of the shade array). For each sample: x and z of the
// terrain's normal there (y is the rest of a unit vector), from the four neighbours,
// normalize(h west - h east, 2 spacing, h north - h south); 1 where the sample and its
// four neighbours are one height within half a metre of 0 (a flat sea, as SRTM and
// Copernicus store it); and 1 where the sample has data (the normal is there), else 0.
// Beside the tile's outermost samples and the data's edge the differences are one-sided.
// Normals are stored as n * 0.5 + 0.5 (unorm: renderable on WebGL2 too). Filtered
// bilinearly, one sample gives the terrain's fragment shader what twelve height loads
// gave it.

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
    let h = height(p);
    if h <= NODATA * 0.5 {
        return NONE;
    }
    let w = height(p - vec2<i32>(1, 0));
    let e = height(p + vec2<i32>(1, 0));
    let n = height(p - vec2<i32>(0, 1));
    let s = height(p + vec2<i32>(0, 1));
    let normal = normalize(vec3<f32>(difference(w, h, e), 2.0 * job.spacing, difference(n, h, s)));
    // Neighbours past the tile's edge (or the data's) are left out of the sea's test too:
    // otherwise every tile's rim would draw a line of land across the sea.
    let around = vec4<f32>(w, e, n, s);
    let level = (around == vec4<f32>(h)) | (around <= vec4<f32>(NODATA * 0.5));
    let sea = (abs(h) < 0.5) & all(level);
    return vec4<f32>(normal.x * 0.5 + 0.5, normal.z * 0.5 + 0.5, select(0.0, 1.0, sea), 1.0);
}

// The central difference `before - after` across a sample `h`. Where one of them has no
// data (past the tile's outermost sample, whose neighbour lies in the next tile, or past
// the data's edge) it is the one-sided difference, doubled; where neither has, 0.
fn difference(before: f32, h: f32, after: f32) -> f32 {
    let has_before = before > NODATA * 0.5;
    let has_after = after > NODATA * 0.5;
    if has_before && has_after {
        return before - after;
    }
    if has_before {
        return 2.0 * (before - h);
    }
    if has_after {
        return 2.0 * (h - after);
    }
    return 0.0;
}

// The height at sample `p` of the job's tile (NODATA where none, or outside it).
fn height(p: vec2<i32>) -> f32 {
    if any(p < vec2<i32>(0)) || any(p >= vec2<i32>(job.edge)) {
        return NODATA;
    }
    return textureLoad(heights, p, job.slot, 0).r;
}
