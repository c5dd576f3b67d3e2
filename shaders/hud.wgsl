// Heads-up display: a text image (rasterized on the CPU) drawn in the top-left corner
// at an integer scale, alpha-blended over the frame.

struct Hud {
    // xy: top-left corner in pixels, zw: size of the text image in pixels.
    rect: vec4<f32>,
    // xy: target size in pixels, z: scale.
    screen: vec4<f32>,
}

@group(0) @binding(0) var<uniform> H: Hud;
@group(0) @binding(1) var text: texture_2d<f32>;

struct VertexOut {
    @builtin(position) clip: vec4<f32>,
    @location(0) pixel: vec2<f32>,
}

@vertex
fn vs_main(@builtin(vertex_index) i: u32) -> VertexOut {
    let corner = vec2<f32>(f32(i & 1u), f32((i >> 1u) & 1u));
    let size = H.rect.zw * H.screen.z;
    let p = H.rect.xy + corner * size;
    var out: VertexOut;
    out.clip = vec4<f32>(p.x / H.screen.x * 2.0 - 1.0, 1.0 - p.y / H.screen.y * 2.0, 0.0, 1.0);
    out.pixel = corner * H.rect.zw;
    return out;
}

@fragment
fn fs_main(in: VertexOut) -> @location(0) vec4<f32> {
    let texel = vec2<i32>(clamp(in.pixel, vec2<f32>(0.0), H.rect.zw - 1.0));
    return textureLoad(text, texel, 0);
}
