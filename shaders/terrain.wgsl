// Terrain: a CDLOD patch mesh whose vertices morph between levels, heights read in the
// vertex shader from GPU-resident elevation tiles, every texture LOD blended per pixel.
//
// Coordinates: x east, y up, z south. Everything horizontal is relative to an anchor
// near the camera (camera-relative rendering keeps f32 exact enough on a 1000 km
// terrain); tile addresses are integer tile indices of the anchor plus a fraction.
// On the globe the grid stays the archive's; each vertex is placed on the WGS 84
// ellipsoid, in the frame east-up-south at the anchor (client/src/globe.rs).

struct LodInfo {
    // xy: the anchor's tile index at this LOD.
    tile: vec4<i32>,
    // xy: the anchor's position inside that tile (0..1), z: 1 / tile world size.
    frac: vec4<f32>,
}

struct GlobeInfo {
    // x: 0 flat plate, 1 geographic grid, 2 Web Mercator, 3 lattice; y, z: lattice size.
    kind: vec4<u32>,
    // Geographic, Web Mercator: radians per world unit along x (longitude) and z
    // (latitude, or the Mercator ordinate over the radius), z: that ordinate at the anchor.
    // Lattice: the anchor's lattice coordinates, z: lattice points per world unit.
    // w: the anchor's latitude (radians; Web Mercator, for its polar caps).
    map: vec4<f32>,
    // x, y: sine and cosine of the anchor's latitude, z: the prime vertical radius there,
    // w: the column height (the eye's height clamped to the terrain's range).
    anchor: vec4<f32>,
    // The geoid's undulation (the lattice texture's b): the anchor's lattice coordinates,
    // z: lattice points per world unit, w: 1 where heights are above a geoid (else 0).
    geoid: vec4<f32>,
    // xyz: the Earth's centre in the anchor's frame, w: the radius of a ball inside the
    // Earth and below the terrain (what hides the far side).
    earth: vec4<f32>,
}

struct Globals {
    // Rotation + projection (reversed depth); applied to camera-relative positions.
    view_proj: mat4x4<f32>,
    // xyz: camera relative to the anchor (y absolute), w: mesh base spacing (world units).
    camera: vec4<f32>,
    // xyz: direction to the sun, w: ambient light.
    sun: vec4<f32>,
    // rgb: haze colour (linear), w: fog density per world unit.
    fog: vec4<f32>,
    // x: lowest height, y: highest height, z: column height offset for LOD distances
    // (clamp(camera y, lowest, highest) - camera y), w: detail texture strength.
    terrain: vec4<f32>,
    // Elevation layer: x: samples per tile edge, y: border, z: stored edge, w: sample spacing at LOD 0.
    elev: vec4<f32>,
    // Texture layer: the same for texels.
    tex: vec4<f32>,
    // x: elevation LODs (0 = no layer), y: texture LODs, z: page table mask, w: page table width.
    counts: vec4<u32>,
    // x: shading (0 lit, 1 flat white, 2 baseline: one texel), y: wireframe, z: LOD colours,
    // w: page table probes.
    mode: vec4<u32>,
    // x: elevation LOD offset (log2 of base spacing / elevation spacing), y: first morph
    // range radius, z: log2 of the page table's width (a power of two); w unused.
    lod: vec4<f32>,
    // The data's extent relative to the anchor: min x, min z, max x, max z. The mesh
    // ends on patch boundaries, which can lie beyond it.
    bounds: vec4<f32>,
    globe: GlobeInfo,
    // Per mesh level: morph start, morph end (= the level's range), quad size in base units.
    ranges: array<vec4<f32>, 32>,
    elev_lods: array<LodInfo, 32>,
    tex_lods: array<LodInfo, 32>,
}

@group(0) @binding(0) var<uniform> G: Globals;
@group(0) @binding(1) var page_table: texture_2d<u32>;
@group(0) @binding(2) var elevation: texture_2d_array<f32>;
@group(0) @binding(3) var colour: texture_2d_array<f32>;
@group(0) @binding(4) var colour_sampler: sampler;
// Longitude and latitude (radians, from the lattice's centre) at lattice points (rg), and
// the geoid's undulation there (b, metres).
@group(0) @binding(5) var lattice: texture_2d<f32>;
// The atmosphere (atmosphere.wgsl, appended to this source).
@group(0) @binding(6) var<uniform> ATMO: AtmosphereUniform;
@group(0) @binding(7) var transmittance_lut: texture_2d<f32>;
@group(0) @binding(8) var multiscattering_lut: texture_2d<f32>;
@group(0) @binding(9) var lut_sampler: sampler;
@group(0) @binding(10) var sky_view_lut: texture_2d<f32>;
@group(0) @binding(11) var aerial_lut: texture_2d<f32>;
// The whole Earth, equirectangular (longitude -180..180, latitude 90..-90), sRGB, mipmapped:
// the ground beyond the archive's data.
@group(0) @binding(12) var earth_map: texture_2d<f32>;
// Per elevation sample, made where the tile was decoded (terrastream-tiles' shade.rs): x and z of the
// normal (as n * 0.5 + 0.5), the fraction of water (the water layer's, else 1 in a flat
// sea), 1 where the sample has data. The same slots as `elevation`; filtered.
@group(0) @binding(13) var elevation_shade: texture_2d_array<f32>;

const NODATA: f32 = -1.0e30;
const KIND_ELEVATION: u32 = 0u;
const KIND_TEXTURE: u32 = 1u;

// Must match `residency::hash_key` in Rust.
fn hash_key(x: u32, y: u32, k: u32) -> u32 {
    var h = (x * 0x9E3779B1u) ^ (y * 0x85EBCA77u) ^ (k * 0xC2B2AE3Du);
    h = h ^ (h >> 15u);
    h = h * 0x2C1B3C6Du;
    h = h ^ (h >> 12u);
    return h;
}

// The array slot holding tile (lod, t) of a layer kind (x), and the slot of its parent
// (y); -1 where not resident.
fn find_slots(kind: u32, lod: u32, t: vec2<i32>) -> vec2<i32> {
    if t.x < 0 || t.y < 0 {
        return vec2<i32>(-1);
    }
    let x = u32(t.x);
    let y = u32(t.y);
    let k = lod | (kind << 8u);
    var h = hash_key(x, y, k) & G.counts.z;
    // The table's width is a power of two: a mask and a shift, where the modulo and the
    // division of a width the compiler does not know cost dozens of instructions a probe.
    let column = G.counts.w - 1u;
    let row = u32(G.lod.z);
    for (var i = 0u; i < G.mode.w; i++) {
        let e = textureLoad(page_table, vec2<i32>(i32(h & column), i32(h >> row)), 0);
        if e.w == 0u {
            return vec2<i32>(-1);
        }
        // z: the key's LOD and kind, and the parent's slot + 1 above them.
        if e.x == x && e.y == y && (e.z & 0xFFFFu) == k {
            return vec2<i32>(i32(e.w) - 1, i32(e.z >> 16u) - 1);
        }
        h = (h + 1u) & G.counts.z;
    }
    return vec2<i32>(-1);
}

// The array slot holding tile (lod, t) of a layer kind, or -1 when it is not resident.
fn find_slot(kind: u32, lod: u32, t: vec2<i32>) -> i32 {
    return find_slots(kind, lod, t).x;
}

struct TilePos {
    tile: vec2<i32>,
    within: vec2<f32>,
}

fn tile_pos(info: LodInfo, p: vec2<f32>) -> TilePos {
    let q = info.frac.xy + p * info.frac.z;
    let f = floor(q);
    return TilePos(info.tile.xy + vec2<i32>(f), q - f);
}

// Bilinear height inside one resident elevation tile; nodata samples are left out.
fn sample_height(slot: i32, within: vec2<f32>) -> f32 {
    return sample_height_cover(slot, within).x;
}

// The same, with the bilinear weight of the samples that have data (1 inside the data,
// less along its rim).
fn sample_height_cover(slot: i32, within: vec2<f32>) -> vec2<f32> {
    let s = G.elev.y + within * G.elev.x - 0.5;
    let i0 = floor(s);
    let t = s - i0;
    let last = i32(G.elev.z) - 1;
    let a = clamp(vec2<i32>(i0), vec2<i32>(0), vec2<i32>(last));
    let b = clamp(vec2<i32>(i0) + 1, vec2<i32>(0), vec2<i32>(last));
    let h00 = textureLoad(elevation, vec2<i32>(a.x, a.y), slot, 0).r;
    let h10 = textureLoad(elevation, vec2<i32>(b.x, a.y), slot, 0).r;
    let h01 = textureLoad(elevation, vec2<i32>(a.x, b.y), slot, 0).r;
    let h11 = textureLoad(elevation, vec2<i32>(b.x, b.y), slot, 0).r;
    return bilinear(vec4<f32>(h00, h10, h01, h11), t);
}

// Four samples (x0y0, x1y0, x0y1, x1y1) at fraction t between them, nodata left out:
// the height and the weight of the samples with data.
fn bilinear(hs: vec4<f32>, t: vec2<f32>) -> vec2<f32> {
    let w = vec4<f32>((1.0 - t.x) * (1.0 - t.y), t.x * (1.0 - t.y), (1.0 - t.x) * t.y, t.x * t.y);
    let valid = select(vec4<f32>(0.0), vec4<f32>(1.0), hs > vec4<f32>(NODATA * 0.5));
    let weight = dot(w, valid);
    if weight <= 1.0e-6 {
        return vec2<f32>(NODATA, 0.0);
    }
    return vec2<f32>(dot(w * valid, hs) / weight, weight);
}

struct HeightSample {
    h: f32,
    lod: f32,
    // The bilinear weight of the samples with data.
    cover: f32,
    // The resident tile it came from, and where in it.
    slot: i32,
    within: vec2<f32>,
}

// Height at p from the finest resident elevation tile at `start` or coarser.
fn height_from(start: u32, p: vec2<f32>) -> HeightSample {
    for (var lod = start; lod < G.counts.x; lod++) {
        let tp = tile_pos(G.elev_lods[lod], p);
        let slot = find_slot(KIND_ELEVATION, lod, tp.tile);
        if slot >= 0 {
            let hc = sample_height_cover(slot, tp.within);
            return HeightSample(hc.x, f32(lod), hc.y, slot, tp.within);
        }
    }
    return HeightSample(0.0, -1.0, 0.0, -1, vec2<f32>(0.0));
}

// The first height with data at p from LOD `start` up: coarser samples are nodata-aware
// averages, so they reach further out than a finer LOD's last ones. NODATA if none has.
fn coarser_height(start: u32, p: vec2<f32>) -> f32 {
    for (var lod = start; lod < G.counts.x; lod++) {
        let tp = tile_pos(G.elev_lods[lod], p);
        let slot = find_slot(KIND_ELEVATION, lod, tp.tile);
        if slot >= 0 {
            let h = sample_height(slot, tp.within);
            if h > NODATA * 0.5 {
                return h;
            }
        }
    }
    return NODATA;
}

const WGS84_A: f32 = 6378137.0;
// Web Mercator's ordinate (over the radius) at the edge of its world, less a margin.
const MERCATOR_EDGE: f32 = 3.14159;
const WGS84_E2: f32 = 0.0066943799901413165;

// Bilinear between lattice points.
fn lattice_at(q: vec2<f32>) -> vec4<f32> {
    let last = vec2<f32>(G.globe.kind.yz) - 1.0;
    let c = clamp(q, vec2<f32>(0.0), last);
    let i = min(floor(c), max(last - 1.0, vec2<f32>(0.0)));
    let t = c - i;
    let a = vec2<i32>(i);
    let b = min(a + 1, vec2<i32>(last));
    let v00 = textureLoad(lattice, a, 0);
    let v10 = textureLoad(lattice, vec2<i32>(b.x, a.y), 0);
    let v01 = textureLoad(lattice, vec2<i32>(a.x, b.y), 0);
    let v11 = textureLoad(lattice, b, 0);
    return mix(mix(v00, v10, t.x), mix(v01, v11, t.x), t.y);
}

// Longitude and latitude of grid point p (from the anchor), less the anchor's.
fn geo_offset(p: vec2<f32>) -> vec2<f32> {
    let m = G.globe.map;
    switch G.globe.kind.x {
        case 2u: {
            // gd(v + dv) - gd(v) = 2 atan(sinh(dv / 2) / cosh(v + dv / 2)): no cancellation.
            let dv = p.y * m.y;
            var dlat = 2.0 * atan(sinh(0.5 * dv) / cosh(m.z + 0.5 * dv));
            // The grid's edge at 85.05 degrees goes to the pole: the last row of
            // triangles closes the cap (a world grid covers the whole Earth).
            let v = m.z + dv;
            if abs(v) >= MERCATOR_EDGE {
                dlat = sign(v) * PI / 2.0 - G.globe.map.w;
            }
            return vec2<f32>(p.x * m.x, dlat);
        }
        case 3u: {
            return lattice_at(m.xy + p * m.z).xy - lattice_at(m.xy).xy;
        }
        default: {
            return vec2<f32>(p.x * m.x, p.y * m.y);
        }
    }
}

// The point d = (longitude, latitude) from the anchor's, h metres above the ellipsoid,
// in the frame at the anchor (x east, y up, z south; metres from the anchor). Every term
// is a difference formed from half-angle sines, never of two radii, so f32 keeps its
// precision relative to the distance from the anchor, not to the Earth's radius.
fn globe_local(d: vec2<f32>, h: f32) -> vec3<f32> {
    let sa = G.globe.anchor.x;
    let ca = G.globe.anchor.y;
    let na = G.globe.anchor.z;
    let half = sin(0.5 * d.y);
    let cos_half = cos(0.5 * d.y);
    // cos and sin of the latitude less the anchor's: -2 sin(d/2) sin(mid), 2 sin(d/2) cos(mid).
    let dc = -2.0 * half * (sa * cos_half + ca * half);
    let ds = 2.0 * half * (ca * cos_half - sa * half);
    let s = sa + ds;
    let c = ca + dc;
    let w = sqrt(1.0 - WGS84_E2 * s * s);
    let wa = WGS84_A / na;
    let n = WGS84_A / w;
    // The prime vertical radius less the anchor's.
    let dn = n * WGS84_E2 * ds * (s + sa) / (wa * (w + wa));
    let sl = sin(0.5 * d.x);
    // ECEF turned so that the anchor's meridian is x = 0, less the anchor's position.
    let x = (n + h) * c * (-2.0 * sl * sl) + (dn + h) * c + na * dc;
    let y = (n + h) * c * sin(d.x);
    let z = (dn * (1.0 - WGS84_E2) + h) * s + na * (1.0 - WGS84_E2) * ds;
    return vec3<f32>(y, ca * x + sa * z, sa * x - ca * z);
}

// The geoid's undulation at grid point p (from the anchor): what lifts heights above
// the archive's geoid onto the ellipsoid (0 where they are not above one).
fn undulation(p: vec2<f32>) -> f32 {
    let g = G.globe.geoid;
    if g.w == 0.0 {
        return 0.0;
    }
    return lattice_at(g.xy + p * g.z).z;
}

// Where grid point p (from the anchor) at height h (the archive's) is drawn, in the
// anchor's frame.
fn place(p: vec2<f32>, h: f32) -> vec3<f32> {
    if G.globe.kind.x == 0u {
        return vec3<f32>(p.x, h, p.y);
    }
    return globe_local(geo_offset(p), h + undulation(p));
}

// Distance from the camera to the vertical column at p over the terrain's height range:
// a function of (x, z) only, the same the CPU selection measures node boxes with, which
// is what makes the morph reach 1 exactly where a coarser neighbour begins.
// On the globe: to the point at p at the column height, which lies in the node's box.
fn column_distance(p: vec2<f32>) -> f32 {
    if G.globe.kind.x != 0u {
        return length(place(p, G.globe.anchor.w) - G.camera.xyz);
    }
    return length(vec3<f32>(p - G.camera.xz, G.terrain.z));
}

// The height drawn at p: a continuous mix of two elevation LODs chosen by distance (a
// function of position only, so neighbouring patches agree on every shared vertex).
fn terrain_height(p: vec2<f32>) -> vec2<f32> {
    // No elevation layer: flat, at the height the renderer chose (terrain.x = terrain.y).
    if G.counts.x == 0u {
        return vec2<f32>(G.terrain.x, 0.0);
    }
    let d = column_distance(p);
    let top = f32(G.counts.x - 1u);
    let t = clamp(log2(max(d, 1.0e-3) / G.lod.y) + G.lod.x, 0.0, top);
    let l0 = floor(t);
    let f = t - l0;
    let sa = height_from(u32(l0), p);
    // y: 1 where an elevation tile covers p (at this LOD or a coarser one).
    let covered = select(0.0, 1.0, sa.lod >= 0.0);
    if sa.lod < 0.0 {
        return vec2<f32>(G.terrain.x, 0.0);
    }
    // A vertex just past the data's edge (its samples all nodata) takes the height of the
    // coarser LODs there, so that the triangles reaching into the data do not ramp down to
    // the lowest height; the fragments past the edge are discarded at pixel resolution.
    var a = sa.h;
    if a <= NODATA * 0.5 {
        a = coarser_height(u32(sa.lod) + 1u, p);
    }
    if f <= 0.0 || l0 >= top {
        return vec2<f32>(a, covered);
    }
    var b = height_from(u32(l0) + 1u, p).h;
    if b <= NODATA * 0.5 {
        b = a;
    }
    if a <= NODATA * 0.5 {
        return vec2<f32>(b, covered);
    }
    if b <= NODATA * 0.5 {
        return vec2<f32>(a, covered);
    }
    return vec2<f32>(mix(a, b, f), covered);
}

struct VertexOut {
    @builtin(position) clip: vec4<f32>,
    // Position relative to the anchor (xz) and height.
    @location(0) world: vec3<f32>,
    // Patch grid coordinates before the morph (for the wireframe overlay).
    @location(1) grid: vec2<f32>,
    @location(2) @interpolate(flat) level: u32,
    // 1 where a corner had no data.
    @location(3) nodata: f32,
    // 1 where an elevation tile covers the vertex (0 beyond the elevation's tiles, and
    // without an elevation layer): there, only imagery with texels is drawn.
    @location(4) covered: f32,
    // Position relative to the eye, in the anchor's frame.
    @location(5) rel: vec3<f32>,
    // 1 where the Earth hides the vertex from the eye (the far side, past the limb).
    @location(6) behind: f32,
    // On the globe with the atmosphere's tables, the air at the vertex (see `air_at`):
    // the up direction, the sunlight that reaches it, the air between it and the eye.
    @location(7) up: vec3<f32>,
    @location(8) sunlight: vec3<f32>,
    @location(9) air: vec4<f32>,
}

// Is the point q (in the anchor's frame) hidden from the eye by the ball inside the Earth?
fn behind_the_earth(q: vec3<f32>) -> bool {
    let e = G.camera.xyz;
    let c = G.globe.earth.xyz;
    let d = q - e;
    let t = clamp(dot(c - e, d) / max(dot(d, d), 1.0e-6), 0.0, 1.0);
    let closest = e + d * t - c;
    return dot(closest, closest) < G.globe.earth.w * G.globe.earth.w;
}

@vertex
fn vs_main(@location(0) local: vec2<f32>, @location(1) instance: vec4<f32>) -> VertexOut {
    let level = u32(instance.z);
    let range = G.ranges[level];
    let quad = range.z;
    let base = G.camera.w;
    let g0 = instance.xy + local * quad;
    // On the globe, points are placed within the data's box (the lattice ends there).
    var m0 = g0 * base;
    if G.globe.kind.x != 0u {
        m0 = clamp(m0, G.bounds.xy, G.bounds.zw);
    }
    let morph = clamp((column_distance(m0) - range.x) / (range.y - range.x), 0.0, 1.0);
    let odd = fract(local * 0.5) * 2.0;
    let g = instance.xy + (local - odd * morph) * quad;
    // The mesh ends where the data does, at every level: vertices beyond the data's box
    // move onto its edge (the triangles out there collapse to nothing), so a coarse
    // patch's edge follows the data's instead of stepping by whole quads.
    let p = clamp(g * base, G.bounds.xy, G.bounds.zw);
    let found = terrain_height(p);
    var h = found.x;
    var out: VertexOut;
    out.covered = found.y;
    out.nodata = 0.0;
    if h <= NODATA * 0.5 {
        out.nodata = 1.0;
        h = G.terrain.x;
    }
    out.world = vec3<f32>(p.x, h, p.y);
    let placed = place(p, h);
    out.rel = placed - G.camera.xyz;
    out.behind = 0.0;
    if G.globe.kind.x != 0u && behind_the_earth(placed) {
        out.behind = 1.0;
    }
    out.clip = G.view_proj * vec4<f32>(out.rel, 1.0);
    out.grid = local;
    out.level = level;
    out.up = vec3<f32>(0.0, 1.0, 0.0);
    out.sunlight = vec3<f32>(1.0);
    out.air = vec4<f32>(0.0, 0.0, 0.0, 1.0);
    if ATMO.look.y > 0.5 && ATMO.tables.x > 0.5 {
        let air = air_at(out.rel, h, out.clip);
        out.up = air.up;
        out.sunlight = air.sunlight;
        out.air = air.air;
    }
    return out;
}

struct AirAt {
    up: vec3<f32>,
    sunlight: vec3<f32>,
    air: vec4<f32>,
}

// The air at a vertex `rel` from the eye, `height` above the model's sphere, at `clip`:
// its up direction, the sunlight through the air above it (none in the planet's shadow),
// and the aerial perspective between it and the eye. They change over kilometres, not
// pixels: computed a vertex, they cost a pixel an interpolation (three table reads and
// two square roots fewer), and the mesh's vertices lie about eight pixels apart.
fn air_at(rel: vec3<f32>, height: f32, clip: vec4<f32>) -> AirAt {
    let up = normalize(ATMO.eye.xyz + rel * ATMO.eye.w);
    let p = ground_point(up, height);
    // Its place on the screen (0..1, row 0 at the top), as a fragment's pixel over the
    // target's size. (A vertex behind the eye is near it, where the air is thin.)
    let ndc = clip.xy / max(clip.w, 1.0e-6);
    let uv = vec2<f32>(0.5 + 0.5 * ndc.x, 0.5 - 0.5 * ndc.y);
    return AirAt(up, sunlight_at(p), aerial(uv, length(p - ATMO.eye.xyz)));
}

// The point `height` above the model's sphere under `up` (the ellipsoid's radius varies
// by 21 km; the air's density follows the height, not the radius).
fn ground_point(up: vec3<f32>, height: f32) -> vec3<f32> {
    return up * (BOTTOM + max(height, 0.0));
}

// The sunlight that reaches ground point `p` through the air above it; none in the
// planet's shadow.
fn sunlight_at(p: vec3<f32>) -> vec3<f32> {
    let sun = ATMO.sun.xyz;
    if ray_sphere(p, sun, BOTTOM - 100.0) > 0.0 {
        return vec3<f32>(0.0);
    }
    return transmittance_to_top(p, sun);
}

// The colour of texture tile `slot` at `within` (0..1 across the tile proper).
fn texel_in(slot: i32, within: vec2<f32>) -> vec4<f32> {
    let uv = (G.tex.y + within * G.tex.x) / G.tex.z;
    return textureSampleLevel(colour, colour_sampler, uv, slot, 0.0);
}

struct TwoTexels {
    fine: vec4<f32>,
    coarse: vec4<f32>,
}

// The colours of p at texture LODs l0 and l0 + 1 (the last LOD at most), each from the
// finest resident tile at that LOD or coarser, as `texel_from` gives them: the coarser
// tile is the finer one's parent, whose slot its page-table entry names, so one probe
// serves both where both are resident.
fn texels_at(l0: u32, p: vec2<f32>) -> TwoTexels {
    let l1 = min(l0 + 1u, G.counts.y - 1u);
    let tp = tile_pos(G.tex_lods[l0], p);
    let slots = find_slots(KIND_TEXTURE, l0, tp.tile);
    if slots.x < 0 {
        // The walk from l0 continues at l0 + 1, which is where l1's starts.
        let c = texel_from(l0 + 1u, p);
        return TwoTexels(c, c);
    }
    let c0 = texel_in(slots.x, tp.within);
    if l1 == l0 {
        return TwoTexels(c0, c0);
    }
    if slots.y >= 0 {
        return TwoTexels(c0, texel_in(slots.y, tile_pos(G.tex_lods[l1], p).within));
    }
    return TwoTexels(c0, texel_from(l1, p));
}

// Colour of p from the finest resident texture tile at `start` or coarser.
fn texel_from(start: u32, p: vec2<f32>) -> vec4<f32> {
    for (var lod = start; lod < G.counts.y; lod++) {
        let tp = tile_pos(G.tex_lods[lod], p);
        let slot = find_slot(KIND_TEXTURE, lod, tp.tile);
        if slot >= 0 {
            return texel_in(slot, tp.within);
        }
    }
    return vec4<f32>(0.5, 0.5, 0.5, 0.0);
}

// Colour ramp by height when the archive has no texture layer.
// The sea's albedo in linear light: the whole-Earth picture's sea (client/data/earth.webp).
const SEA_ALBEDO: vec3<f32> = vec3<f32>(0.015, 0.045, 0.09);

fn hypsometric(h: f32) -> vec3<f32> {
    let t = clamp((h - G.terrain.x) / max(G.terrain.y - G.terrain.x, 1.0), 0.0, 1.0);
    let low = vec3<f32>(0.09, 0.21, 0.07);
    let mid = vec3<f32>(0.36, 0.30, 0.16);
    let high = vec3<f32>(0.55, 0.52, 0.50);
    if t < 0.5 {
        return mix(low, mid, t * 2.0);
    }
    return mix(mid, high, t * 2.0 - 1.0);
}

fn lod_colour(level: u32) -> vec3<f32> {
    let palette = array<vec3<f32>, 6>(
        vec3<f32>(0.9, 0.2, 0.2), vec3<f32>(0.9, 0.7, 0.1), vec3<f32>(0.2, 0.8, 0.2),
        vec3<f32>(0.1, 0.7, 0.9), vec3<f32>(0.3, 0.3, 0.95), vec3<f32>(0.8, 0.3, 0.9),
    );
    return palette[level % 6u];
}

// Value noise for the optional detail texture.
fn noise(p: vec2<f32>) -> f32 {
    let i = floor(p);
    let f = p - i;
    let u = f * f * (3.0 - 2.0 * f);
    let c = vec2<u32>(vec2<i32>(i) + vec2<i32>(1 << 20));
    let a = f32(hash_key(c.x, c.y, 7u) & 0xFFFFu) / 65535.0;
    let b = f32(hash_key(c.x + 1u, c.y, 7u) & 0xFFFFu) / 65535.0;
    let d = f32(hash_key(c.x, c.y + 1u, 7u) & 0xFFFFu) / 65535.0;
    let e = f32(hash_key(c.x + 1u, c.y + 1u, 7u) & 0xFFFFu) / 65535.0;
    return mix(mix(a, b, u.x), mix(d, e, u.x), u.y);
}

@fragment
fn fs_main(in: VertexOut) -> @location(0) vec4<f32> {
    // Derivatives first, in uniform control flow.
    let footprint = max(length(dpdx(in.world.xz)), length(dpdy(in.world.xz)));
    let grid_width = fwidth(in.grid);
    // Vertices lie on or inside the box; the slack keeps rounding from cutting its rim.
    let slack = G.camera.w * 0.01;
    let outside = any(in.world.xz < G.bounds.xy - slack) || any(in.world.xz > G.bounds.zw + slack);
    if in.nodata > 0.999 || outside || in.behind > 0.5 {
        discard;
    }
    // The baseline: one texel a pixel, nothing else.
    if G.mode.x == 2u {
        return textureSampleLevel(colour, colour_sampler, fract(in.world.xz / 256.0), 0, 0.0);
    }
    let p = in.world.xz;
    // The elevation at the pixel's own resolution: where it has no data the terrain ends,
    // at every mesh level (a coarse triangle over the data's edge is cut at the pixel, not
    // dropped whole, which drew the edge as stair steps).
    var found = HeightSample(0.0, -1.0, 0.0, -1, vec2<f32>(0.0));
    if G.counts.x > 0u {
        let le = u32(clamp(floor(log2(max(footprint, 1.0e-6) / G.elev.w)), 0.0, f32(G.counts.x - 1u)));
        found = height_from(le, p);
        if found.lod >= 0.0 && found.h <= NODATA * 0.5 {
            discard;
        }
    }
    if G.mode.x == 1u {
        return vec4<f32>(1.0, 1.0, 1.0, 1.0);
    }
    // Normal from the elevation data at the pixel's own resolution.
    var normal = vec3<f32>(0.0, 1.0, 0.0);
    // Water, from the shade texels' water byte: the archive's water layer's fraction where
    // it has one, else the sea as DEMs that store it as a flat 0 have it (SRTM,
    // Copernicus): where the pixel's samples and their four neighbours are one height
    // within half a metre of sea level. Filtered, it ramps across a shore over a sample:
    // water from half of it up, fully water from 0.95, so the shore is anti-aliased.
    var water = 0.0;
    if G.counts.x > 0u {
        if found.lod >= 0.0 {
            // One filtered sample of the tile's shade texels (terrastream-tiles): the
            // normal, and the flat sea, from the pixel's four samples with data. One
            // sample, where
            // the neighbours' four bilinear heights took twelve loads and, across a
            // tile's edge, four page-table probes (a slower path kept for those made
            // lavapipe's globe frame 2.5x slower, though few pixels took it).
            let uv = (G.elev.y + found.within * G.elev.x) / G.elev.z;
            let shade = textureSampleLevel(elevation_shade, colour_sampler, uv, found.slot, 0.0);
            if shade.w > 0.01 {
                // Samples without data hold a zero normal: dividing by the weight of
                // those with data leaves their weighted mean (the data's rim included).
                let xz = (shade.xy * 2.0 - 1.0) / shade.w;
                normal = normalize(vec3<f32>(xz.x, sqrt(max(1.0 - dot(xz, xz), 0.0)), xz.y));
                water = smoothstep(0.5, 0.95, shade.z);
            }
        }
    }
    var albedo = mix(hypsometric(in.world.y), SEA_ALBEDO, water);
    if G.counts.y > 0u {
        let t = clamp(log2(max(footprint, 1.0e-6) / G.tex.w), 0.0, f32(G.counts.y - 1u));
        let l0 = floor(t);
        let two = texels_at(u32(l0), p);
        let c0 = two.fine;
        let c1 = two.coarse;
        // Alpha is coverage (LODs are alpha-weighted averages): the two LODs' colours are
        // mixed by their coverage, so the partly covered texels along the data's edge at a
        // coarse LOD do not let the height tint show through as a fringe.
        let w0 = c0.a * (1.0 - (t - l0));
        let w1 = c1.a * (t - l0);
        let colour = (c0.rgb * w0 + c1.rgb * w1) / max(w0 + w1, 1.0e-6);
        // Data edges (docs/rendering.md): imagery is there where a texel is at least half
        // covered; the terrain is drawn where either layer has data, so beyond the
        // elevation's tiles only where the imagery is, and along the elevation's rim
        // (where some of its samples have no data) the imagery draws the edge.
        let imagery = max(c0.a, c1.a) >= 0.5;
        let elevation_inside = in.covered >= 0.5 && (G.counts.x == 0u || found.cover > 0.999);
        if !imagery && !elevation_inside {
            discard;
        }
        if imagery {
            albedo = colour;
        }
    }
    if G.terrain.w > 0.0 {
        // Detail texture: fine noise that fades out once its features get below a pixel.
        let scale = 0.25 / G.elev.w;
        let fade = clamp(1.0 - footprint * scale * 2.0, 0.0, 1.0);
        let n = noise(p * scale) * 0.6 + noise(p * scale * 4.0) * 0.4;
        albedo = albedo * (1.0 + G.terrain.w * fade * (n - 0.5));
    }
    if G.mode.z == 1u {
        albedo = mix(albedo, lod_colour(in.level), 0.6);
    }
    let sun = normalize(G.sun.xyz);
    let direct = max(dot(normal, sun), 0.0);
    let sky = 0.5 + 0.5 * normal.y;
    var rgb = albedo * (direct * (1.0 - G.sun.w) + sky * G.sun.w) * vec3<f32>(1.0, 0.97, 0.92);
    // Water mirrors: the sky (here the haze's colour) and the sun's glint. The light's
    // scale here has no 1/pi: the glint's lobe is taken times pi to match.
    if water > 0.0 {
        let sunlight = vec3<f32>(1.0, 0.97, 0.92) * (1.0 - G.sun.w) * PI;
        rgb += water * water_specular(normal, normalize(-in.rel), sun, G.fog.rgb, sunlight);
    }
    if G.mode.y == 1u {
        let e = fract(in.grid);
        let dist = min(e, 1.0 - e) / max(grid_width, vec2<f32>(1.0e-6));
        let diagonal = abs(e.x - e.y) / max(grid_width.x + grid_width.y, 1.0e-6);
        let line = 1.0 - clamp(min(min(dist.x, dist.y), diagonal), 0.0, 1.0);
        rgb = mix(rgb, vec3<f32>(0.02, 0.02, 0.02), line * 0.8);
    }
    if ATMO.look.y > 0.5 {
        if ATMO.tables.x > 0.5 {
            let air = AirAt(in.up, in.sunlight, in.air);
            return vec4<f32>(seen_through_air(albedo, normal, air, in.rel, water), 1.0);
        }
        return vec4<f32>(through_atmosphere(albedo, normal, in.rel, in.world.y, water), 1.0);
    }
    let distance = length(in.rel);
    let haze = 1.0 - exp(-G.fog.w * distance);
    return vec4<f32>(mix(rgb, G.fog.rgb, haze), 1.0);
}

// On the globe with an atmosphere: the ground lit by the sun through the air above it,
// seen through the air between it and the eye (the aerial perspective), exposed; the air
// as `air_at` found it at the vertices.
fn seen_through_air(albedo: vec3<f32>, grid_normal: vec3<f32>, at: AirAt, rel: vec3<f32>, water: f32) -> vec3<f32> {
    let up = normalize(at.up);
    var radiance = ground_radiance(albedo, grid_normal, up, at.sunlight);
    if water > 0.0 {
        radiance += water * water_light(up, normalize(-rel), at.sunlight);
    }
    // The table holds the air as the ground is seen through it (GROUND_HAZE applied).
    return expose(radiance * at.air.a + at.air.rgb);
}

// A grid normal (east, up, south) where the up is `up`, in the anchor's frame.
fn frame_normal(grid_normal: vec3<f32>, up: vec3<f32>) -> vec3<f32> {
    let east = normalize(cross(ATMO.pole.xyz, up));
    let north = cross(up, east);
    return normalize(east * grid_normal.x + up * grid_normal.y - north * grid_normal.z);
}

// Water's reflection toward the eye (`view`, from the point) under the atmosphere, its
// surface level (its normal the up): the sky mirrored (its radiance taken as its light
// from above over pi, as from a uniform sky) and the sun's glint.
fn water_light(up: vec3<f32>, view: vec3<f32>, sunlight: vec3<f32>) -> vec3<f32> {
    let sun = ATMO.sun.xyz;
    return water_specular(up, view, sun, sky_light(up, sun) / PI, sunlight);
}

// What still water reflects toward `view` (unit, from the point) with normal `n`: the sky
// of radiance `sky` mirrored, weighted by Schlick's Fresnel term for water (2 % head on,
// all of it at grazing), and the glint of a sun of light `sunlight` from `sun`, a
// normalized Blinn-Phong lobe (a calm surface: the glint a few degrees across).
fn water_specular(n: vec3<f32>, view: vec3<f32>, sun: vec3<f32>, sky: vec3<f32>, sunlight: vec3<f32>) -> vec3<f32> {
    let h = normalize(view + sun);
    let lobe = (WATER_SHININESS + 8.0) / (8.0 * PI) * pow(clamp(dot(n, h), 0.0, 1.0), WATER_SHININESS);
    return schlick(dot(n, view)) * sky + schlick(dot(h, view)) * lobe * max(dot(n, sun), 0.0) * sunlight;
}

// Schlick's Fresnel term for water (2 % head on) at the cosine `c` of the angle.
fn schlick(c: f32) -> f32 {
    let m = 1.0 - clamp(c, 0.0, 1.0);
    let m2 = m * m;
    return 0.02 + 0.98 * m2 * m2 * m;
}

// The glint's sharpness (a Blinn-Phong exponent): about the spread of the sea's wave slopes
// in a light breeze (Cox and Munk: some 8 degrees), so the glint is a blurred patch, not a
// mirror image of the sun.
const WATER_SHININESS: f32 = 100.0;

// The light ground of `albedo` sends back where its up is `up`, its grid normal (east, up,
// south) `grid_normal` and `sunlight` reaches it: the sun's and the sky's.
fn ground_radiance(albedo: vec3<f32>, grid_normal: vec3<f32>, up: vec3<f32>, sunlight: vec3<f32>) -> vec3<f32> {
    let n = frame_normal(grid_normal, up);
    let sun = ATMO.sun.xyz;
    // Sky light from above, growing with the sun's height, less on slopes facing away.
    let sky = sky_light(up, sun) * (0.5 + 0.5 * dot(n, up));
    return albedo / PI * (sunlight * max(dot(n, sun), 0.0) + sky);
}

// The same without the tables: the air integrated along the ray, a pixel at a time.
fn through_atmosphere(albedo: vec3<f32>, grid_normal: vec3<f32>, rel: vec3<f32>, height: f32, water: f32) -> vec3<f32> {
    let up = normalize(ATMO.eye.xyz + rel * ATMO.eye.w);
    let p = ground_point(up, height);
    let sunlight = sunlight_at(p);
    var radiance = ground_radiance(albedo, grid_normal, up, sunlight);
    if water > 0.0 {
        radiance += water * water_light(up, normalize(-rel), sunlight);
    }
    let to = p - ATMO.eye.xyz;
    let air = integrate(ATMO.eye.xyz, normalize(to), length(to), ATMO.sun.xyz, ATMO.look.w);
    return expose(ground_seen(radiance, air.light, air.transmittance));
}

// The aerial-perspective table at screen position `uv` (0..1, row 0 at the top) and
// distance `t`: light (rgb) and mean transmittance (a), between its slices.
fn aerial(uv: vec2<f32>, t: f32) -> vec4<f32> {
    let w = sqrt(max(t, 0.0) / ATMO.tables.y) * AERIAL_SLICES - 1.0;
    let inside = clamp(uv, vec2<f32>(0.5 / 32.0), vec2<f32>(1.0 - 0.5 / 32.0));
    let k0 = clamp(floor(w), -1.0, AERIAL_SLICES - 1.0);
    let f = clamp(w - k0, 0.0, 1.0);
    var a = vec4<f32>(0.0, 0.0, 0.0, 1.0);
    if k0 >= 0.0 {
        a = textureSampleLevel(aerial_lut, lut_sampler, vec2<f32>((k0 + inside.x) / AERIAL_SLICES, inside.y), 0.0);
    }
    let k1 = min(k0 + 1.0, AERIAL_SLICES - 1.0);
    let b = textureSampleLevel(aerial_lut, lut_sampler, vec2<f32>((k1 + inside.x) / AERIAL_SLICES, inside.y), 0.0);
    return mix(a, b, f);
}

// Whether an albedo of the whole-Earth picture is its sea: blue well above its red and
// green (the picture's oceans, shallow seas included; not its land, ice or lakes' rims).
fn picture_sea(albedo: vec3<f32>) -> bool {
    return albedo.b > 1.15 * albedo.g && albedo.b > 1.6 * albedo.r;
}

// The plain Earth drawn beyond an archive's data: a dark, slightly blue-green ground.
const EARTH_ALBEDO: vec3<f32> = vec3<f32>(0.07, 0.09, 0.11);

struct SkyOut {
    @builtin(position) clip: vec4<f32>,
    @location(0) ndc: vec2<f32>,
}

// The sky: a fullscreen triangle at the far plane, drawn after the terrain where it left
// the far depth.
@vertex
fn vs_sky(@builtin(vertex_index) i: u32) -> SkyOut {
    let xy = vec2<f32>(f32((i << 1u) & 2u), f32(i & 2u)) * 2.0 - 1.0;
    return SkyOut(vec4<f32>(xy, 0.0, 1.0), xy);
}

// Where the whole-Earth picture is sampled at `up` (the unit direction from the planet's
// centre): its longitude and latitude as texture coordinates.
fn earth_uv(up: vec3<f32>) -> vec2<f32> {
    let pole = ATMO.pole.xyz;
    let x = ATMO.meridian.xyz;
    let y = cross(pole, x);
    let lat = asin(clamp(dot(up, pole), -1.0, 1.0));
    let lon = atan2(dot(up, y), dot(up, x));
    return vec2<f32>(lon / (2.0 * PI) + 0.5, 0.5 - lat / PI);
}

// The picture's texel gradients at `uv`: those of whichever of u and u + 1/2 does not jump
// at its seam here (taken in uniform control flow).
struct EarthGrad {
    x: vec2<f32>,
    y: vec2<f32>,
}

fn earth_grad(uv: vec2<f32>) -> EarthGrad {
    let u2 = fract(uv.x + 0.5);
    let gx = select(dpdx(uv), vec2<f32>(dpdx(u2), dpdx(uv.y)), abs(dpdx(u2)) < abs(dpdx(uv.x)));
    let gy = select(dpdy(uv), vec2<f32>(dpdy(u2), dpdy(uv.y)), abs(dpdy(u2)) < abs(dpdy(uv.x)));
    return EarthGrad(gx, gy);
}

// The highest ground the picture's heights hold (its alpha's 1 + 254 * sqrt(h / 9000 m):
// scripts/make-earth.sh). Must match `earth::HIGHEST` and `earth::height_of` in Rust.
const EARTH_HIGHEST: f32 = 9000.0;

// The ground's height above the sea at `up`, from the picture's alpha at mip `level`.
fn earth_height(up: vec3<f32>, level: f32) -> f32 {
    let a = textureSampleLevel(earth_map, colour_sampler, earth_uv(up), level).a;
    let s = max(a * 255.0 - 1.0, 0.0) / 254.0;
    return EARTH_HIGHEST * s * s;
}

// The heights' spacing at the equator, in metres (2048 samples around).
const EARTH_TEXEL: f32 = 19568.0;

// Where the ray from `eye` (direction `d`) passes the sphere of the highest ground in
// its view (ATMO.pole.w, the highest within the eye's horizon: `earth::highest_near`):
// the distances in and out (in from 0 where the eye is inside), or -1 out where it misses.
fn highest_span(eye: vec3<f32>, d: vec3<f32>) -> vec2<f32> {
    let top = BOTTOM + ATMO.pole.w;
    let b = dot(eye, d);
    let lo = length(eye);
    let disc = b * b - (lo - top) * (lo + top);
    if disc < 0.0 || ATMO.pole.w <= 0.0 {
        return vec2<f32>(-1.0);
    }
    let s = sqrt(disc);
    return vec2<f32>(max(-b - s, 0.0), -b + s);
}

// How far around an eye below the heights' ground the ground is lowered to pass below it
// (`raised_ground`): two of the heights' spacings.
const EARTH_SINK_REACH: f32 = 39136.0;

// How far point `p`, `t` from the eye along a ray, is above the heights' ground read at mip
// `level`, that ground lowered by `sink` at the eye and by less out to EARTH_SINK_REACH.
fn above_ground(p: vec3<f32>, t: f32, level: f32, sink: f32) -> f32 {
    let sunk = sink * max(1.0 - t / EARTH_SINK_REACH, 0.0);
    return length(p) - BOTTOM - earth_height(normalize(p), level) + sunk;
}

// Along the ray from `eye` (direction `d`) where it first meets the ground's heights,
// marched from where it enters the sphere of the highest ground in view to where it meets
// the sea's sphere (`sea`) or leaves the highest's (`span`). Each step is a quarter of the
// distance from the eye, at least the heights' spacing, at most what is left: a stretch
// shorter than the spacing takes one step, 700 km from an eye below the highest ground
// about 14. The heights are read at the mip of the step; the crossing is interpolated
// between the two samples around it. `sea` where it meets none. An eye lower than the
// heights' ground at its own place (a valley of the data below the 20 km cells' mean)
// would start every ray below the ground: there the ground is lowered to pass a metre
// below the eye, by less with the distance, its own heights from EARTH_SINK_REACH on, so
// that the eye sees it rise around it (else it saw no ground beyond the data at all).
fn raised_ground(eye: vec3<f32>, d: vec3<f32>, sea: f32, span: vec2<f32>) -> f32 {
    if span.y <= 0.0 {
        return sea;
    }
    let sink = max(earth_height(normalize(eye), 0.0) - (length(eye) - BOTTOM) + 1.0, 0.0);
    let start = span.x;
    let end = select(span.y, sea, sea > 0.0);
    var t_prev = start;
    var above_prev = above_ground(eye + d * start, start, 0.0, sink);
    for (var i = 0u; i < 24u && t_prev < end; i++) {
        let step = max(EARTH_TEXEL, 0.25 * t_prev);
        let t = min(t_prev + step, end);
        let above = above_ground(eye + d * t, t, log2(step / EARTH_TEXEL), sink);
        if above <= 0.0 && above_prev > 0.0 {
            return mix(t_prev, t, above_prev / (above_prev - above));
        }
        t_prev = t;
        above_prev = above;
    }
    return sea;
}

@fragment
fn fs_sky(in: SkyOut) -> @location(0) vec4<f32> {
    let far = ATMO.inv_view_proj * vec4<f32>(in.ndc, 1.0, 1.0);
    let d = normalize(far.xyz / far.w);
    let sun = ATMO.sun.xyz;
    let eye = ATMO.eye.xyz;
    var light = vec3<f32>(0.0);
    if ATMO.tables.x > 0.5 {
        light = textureSampleLevel(sky_view_lut, lut_sampler, sky_view_uv(view_frame(eye, sun), d), 0.0).rgb;
    } else {
        light = integrate(eye, d, 1.0e9, sun, ATMO.look.z).light;
    }
    // The Earth beyond the archive's data: the whole-Earth picture on its heights above
    // the model's sphere (or a plain ground on the sphere), lit by the sun through the air
    // above it, seen through the air in front of it (the terrain, drawn before, covers it
    // where there is data).
    let sea = ray_sphere(eye, d, BOTTOM);
    let span = highest_span(eye, d);
    // The picture's gradients where the ray meets the sea's sphere, or else where it
    // comes nearest to it, which is the same point at the sea's horizon: a point that
    // jumped there between neighbouring pixels drew the horizon's row from the picture's
    // coarsest mip, a bright line (taken here, in uniform control flow).
    let grad = earth_grad(earth_uv(normalize(eye + d * select(max(-dot(eye, d), 0.0), sea, sea > 0.0))));
    let earth = ATMO.meridian.w > 0.5;
    var ground = sea;
    // The ground raised to its heights, where they show: from further than 10 000 km they
    // move it by less than a pixel.
    if earth && length(eye) < BOTTOM + 1.0e7 {
        ground = raised_ground(eye, d, sea, span);
    }
    if ground > 0.0 {
        let g = eye + d * ground;
        var albedo = EARTH_ALBEDO;
        if earth {
            albedo = textureSampleGrad(earth_map, colour_sampler, earth_uv(normalize(g)), grad.x, grad.y).rgb;
        }
        let up = normalize(g);
        let sunlight = sunlight_at(g);
        var radiance = albedo / PI * (sunlight * max(dot(up, sun), 0.0) + sky_light(up, sun));
        // The picture's sea mirrors the sky and the sun, as the data's water does.
        if picture_sea(albedo) {
            radiance += water_light(up, -d, sunlight);
        }
        if ATMO.tables.x > 0.5 {
            // From inside the air, the air in front is the terrain's: the aerial table
            // at the ground's distance (the sky's table holds the light of whole rays,
            // which, where raised ground stops a ray that misses the sea, is the sky's).
            let air = aerial(vec2<f32>(0.5 + 0.5 * in.ndc.x, 0.5 - 0.5 * in.ndc.y), ground);
            light = radiance * air.a + air.rgb;
        } else {
            // Along a ray that meets the ground, the air between is the ratio of the two
            // stretches up to the top (the way back up passes the eye).
            let through = transmittance_to_top(g, -d) / max(transmittance_to_top(eye, -d), vec3<f32>(1.0e-6));
            light = ground_seen(radiance, light, clamp(through, vec3<f32>(0.0), vec3<f32>(1.0)));
        }
    }
    // The sun's disc, dimmed by the air in front of it, where the planet does not hide it.
    if dot(d, sun) > cos(ATMO.sun.w) && ground < 0.0 {
        var through = vec3<f32>(1.0);
        if dot(eye, eye) <= TOP * TOP {
            through = transmittance_to_top(eye, d);
        }
        light += through * (1.0 / (PI * ATMO.sun.w * ATMO.sun.w)) * 0.02;
    }
    return vec4<f32>(expose(light), 1.0);
}
