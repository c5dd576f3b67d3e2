//! A heads-up display: lines of text rasterized on the CPU with an 8x8 bitmap font
//! (public domain) and drawn over the frame in one small pass.

use std::collections::VecDeque;

use bytemuck::{Pod, Zeroable};
use glam::DVec3;

use super::gpu::{
    PipelineDesc, bind_group, pipeline, texture, texture_entry, uniform_buffer, uniform_entry, write_layer,
};

use super::renderer::FrameStats;
use crate::stream::streamer::{StreamStats, UploadBudget};

/// The last second or so of frame times: fps and frame time as a HUD shows them.
#[derive(Clone, Debug, Default)]
pub struct FrameTimes(VecDeque<f64>);

impl FrameTimes {
    /// Records a frame that took `seconds`.
    pub fn push(&mut self, seconds: f64) {
        self.0.push_back(seconds);
        if self.0.len() > 60 {
            self.0.pop_front();
        }
    }

    /// Mean frame time in seconds over the last 60 frames.
    pub fn mean(&self) -> f64 {
        self.0.iter().sum::<f64>() / self.0.len().max(1) as f64
    }

    /// Frames per second over the last 60 frames.
    pub fn fps(&self) -> f64 {
        1.0 / self.mean().max(1e-6)
    }
}

/// What the status lines of a viewer's HUD report.
#[derive(Clone, Copy, Debug)]
pub struct Status<'a> {
    /// Frame times.
    pub times: &'a FrameTimes,
    /// The graphics API / adapter.
    pub api: &'a str,
    /// Streaming counters.
    pub stream: &'a StreamStats,
    /// Wanted tiles not on the GPU yet.
    pub pending: usize,
    /// What the last frame drew.
    pub frame: &'a FrameStats,
    /// Tiles uploaded this frame.
    pub uploads: u64,
    /// The upload budget.
    pub budget: UploadBudget,
    /// Bytes received and the requests that brought them.
    pub received: (u64, u64),
    /// The eye (scene coordinates).
    pub eye: DVec3,
    /// The eye is in ECEF over the globe: shown as longitude, latitude and height.
    pub globe: bool,
    /// The fly camera's speed factor.
    pub speed: f64,
}

/// "eye ..." in world units on the plate, in degrees and metres on the globe.
fn eye_line(s: &Status<'_>) -> String {
    if s.globe {
        let (lon, lat, height) = crate::globe::geodetic(s.eye);
        let (lon, lat) = (lon.to_degrees(), lat.to_degrees());
        let (ew, ns) = (if lon < 0.0 { 'W' } else { 'E' }, if lat < 0.0 { 'S' } else { 'N' });
        return format!("eye {:.5} {ew} {:.5} {ns} {height:.0} m   speed x{:.2}", lon.abs(), lat.abs(), s.speed);
    }
    format!("eye {:.0} {:.0} {:.0}   speed x{:.2}", s.eye.x, s.eye.y, s.eye.z, s.speed)
}

/// The HUD's status lines (ASCII, at most 96 columns), the same in every front end.
pub fn status_lines(s: &Status<'_>) -> Vec<String> {
    let mib = |b: u64| b as f64 / (1024.0 * 1024.0);
    let (stream, frame) = (s.stream, s.frame);
    let mut lines = vec![
        format!("fps {:5.1}   frame {:6.2} ms   {}", s.times.fps(), s.times.mean() * 1e3, s.api),
        format!(
            "tiles in flight {:3}   wanted {:5}   pending {:5}   fetched {:6}   missing {}   failures {}",
            stream.in_flight, stream.wanted, s.pending, stream.tiles_fetched, stream.missing, stream.failures
        ),
        format!(
            "cache {:7.1} MiB ({} tiles)   GPU {:7.1} MiB (resident: {} elevation, {} texture)",
            mib(stream.cache_bytes),
            stream.cache_tiles,
            mib(frame.gpu_bytes),
            frame.resident.0,
            frame.resident.1
        ),
        format!(
            "uploads this frame {:2} (budget {} tiles, {:.1} MiB)   received {:6.1} MiB in {} requests",
            s.uploads,
            s.budget.max_tiles,
            mib(s.budget.max_bytes as u64),
            mib(s.received.0),
            s.received.1
        ),
        format!(
            "mesh levels in view {}..{}   patches {}   triangles {}   draw calls {}",
            frame.levels.0, frame.levels.1, frame.patches, frame.triangles, frame.draw_calls
        ),
        eye_line(s),
    ];
    if frame.drew_nothing_in_view() {
        lines.push(format!("WARNING: {} tiles in view are resident but no terrain is drawn", frame.in_view_resident));
    }
    if let Some(layer) = frame.unreached_layer {
        lines.push(format!("WARNING: layer {layer}'s data is in view but none of its tiles could be fetched"));
    }
    lines
}

/// The shader source.
pub const HUD_WGSL: &str = include_str!("../../../shaders/hud.wgsl");

const COLUMNS: u32 = 96;
const LINES: u32 = 10;
const LINE_HEIGHT: u32 = 10;
const PAD: u32 = 4;

#[repr(C)]
#[derive(Clone, Copy, Pod, Zeroable)]
struct Uniforms {
    rect: [f32; 4],
    screen: [f32; 4],
}

/// Text over the frame.
#[derive(Debug)]
pub struct Hud {
    pipeline: wgpu::RenderPipeline,
    uniforms: wgpu::Buffer,
    texture: wgpu::Texture,
    bind_group: wgpu::BindGroup,
    pixels: Vec<u8>,
    size: (u32, u32),
    used: (u32, u32),
}

impl Hud {
    /// Width and height of the text image.
    fn image_size() -> (u32, u32) {
        (COLUMNS * 8 + 2 * PAD, LINES * LINE_HEIGHT + 2 * PAD)
    }

    /// A HUD drawing into targets of `format`.
    pub fn new(device: &wgpu::Device, format: wgpu::TextureFormat) -> Self {
        let size = Self::image_size();
        let texture = texture(
            device,
            "texture.hud",
            (size.0, size.1, 1),
            wgpu::TextureFormat::Rgba8UnormSrgb,
            wgpu::TextureUsages::TEXTURE_BINDING | wgpu::TextureUsages::COPY_DST,
        );
        let uniforms = uniform_buffer(device, "buffer.hud.uniforms", size_of::<Uniforms>());
        let layout = device.create_bind_group_layout(&wgpu::BindGroupLayoutDescriptor {
            label: Some("layout.hud"),
            entries: &[
                uniform_entry(0),
                texture_entry(1, wgpu::TextureSampleType::Float { filterable: false }, wgpu::TextureViewDimension::D2),
            ],
        });
        let view = texture.create_view(&wgpu::TextureViewDescriptor::default());
        let bind_group = bind_group(
            device,
            "bind_group.hud",
            &layout,
            &[uniforms.as_entire_binding(), wgpu::BindingResource::TextureView(&view)],
        );
        let pipeline = pipeline(
            device,
            &PipelineDesc {
                name: "hud",
                wgsl: HUD_WGSL,
                layout: &layout,
                buffers: &[],
                topology: wgpu::PrimitiveTopology::TriangleStrip,
                depth: (false, wgpu::CompareFunction::Always),
                target: (format, Some(wgpu::BlendState::ALPHA_BLENDING)),
            },
        );
        Self {
            pipeline,
            uniforms,
            texture,
            bind_group,
            pixels: vec![0; (size.0 * size.1 * 4) as usize],
            size,
            used: (0, 0),
        }
    }

    /// Rasterizes `lines` (ASCII; at most 96 columns, 10 lines) for a target of
    /// `target` pixels, drawn at `scale` x.
    pub fn set_text(&mut self, queue: &wgpu::Queue, lines: &[String], target: (u32, u32), scale: u32) {
        let (w, h) = self.size;
        self.pixels.fill(0);
        let columns = lines.iter().map(|l| l.len()).max().unwrap_or(0).min(COLUMNS as usize);
        let rows = lines.len().min(LINES as usize);
        let used = (
            u32::try_from(columns).unwrap_or(COLUMNS) * 8 + 2 * PAD,
            u32::try_from(rows).unwrap_or(LINES) * LINE_HEIGHT + 2 * PAD,
        );
        // Translucent backdrop, then white glyphs with a dark shadow.
        for y in 0..used.1 {
            for x in 0..used.0 {
                let i = ((y * w + x) * 4) as usize;
                self.pixels[i..i + 4].copy_from_slice(&[0, 0, 0, 150]);
            }
        }
        for (row, line) in lines.iter().take(rows).enumerate() {
            for (col, ch) in line.bytes().take(columns).enumerate() {
                let glyph = font8x8::legacy::BASIC_LEGACY[usize::from(ch.min(127))];
                for (gy, bits) in glyph.iter().enumerate() {
                    for gx in 0..8 {
                        if bits & (1 << gx) == 0 {
                            continue;
                        }
                        let x = PAD as usize + col * 8 + gx;
                        let y = PAD as usize + row * LINE_HEIGHT as usize + gy;
                        for (dx, dy, value) in [(1, 1, 0u8), (0, 0, 255u8)] {
                            let (px, py) = (x + dx, y + dy);
                            if px < w as usize && py < h as usize {
                                let i = (py * w as usize + px) * 4;
                                self.pixels[i..i + 4].copy_from_slice(&[value, value, value, 255]);
                            }
                        }
                    }
                }
            }
        }
        write_layer(queue, &self.texture, 0, &self.pixels, (w * 4, h), (w, h));
        self.used = used;
        #[allow(clippy::cast_precision_loss)]
        let uniforms = Uniforms {
            rect: [8.0, 8.0, used.0 as f32, used.1 as f32],
            screen: [target.0.max(1) as f32, target.1.max(1) as f32, scale.max(1) as f32, 0.0],
        };
        queue.write_buffer(&self.uniforms, 0, bytemuck::bytes_of(&uniforms));
    }

    /// Records the HUD into `pass` (after [`Self::set_text`]).
    pub fn draw(&self, pass: &mut wgpu::RenderPass<'_>) {
        if self.used.0 == 0 {
            return;
        }
        pass.set_pipeline(&self.pipeline);
        pass.set_bind_group(0, &self.bind_group, &[]);
        pass.draw(0..4, 0..1);
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_eye_reads_in_degrees_and_metres_on_the_globe() {
        let (times, stream, frame) = (FrameTimes::default(), StreamStats::default(), FrameStats::default());
        let status = |eye: DVec3, globe: bool| Status {
            times: &times,
            api: "test",
            stream: &stream,
            pending: 0,
            frame: &frame,
            uploads: 0,
            budget: UploadBudget::default(),
            received: (0, 0),
            eye,
            globe,
            speed: 1.0,
        };
        let everest = crate::globe::ecef(86.925_f64.to_radians(), 27.9881_f64.to_radians(), 8850.0);
        let line = eye_line(&status(everest, true));
        assert!(line.starts_with("eye 86.92500 E 27.98810 N 8850 m"), "{line}");
        let west = crate::globe::ecef(-122.6_f64.to_radians(), -37.9_f64.to_radians(), 10.0);
        assert!(eye_line(&status(west, true)).starts_with("eye 122.60000 W 37.90000 S 10 m"));
        assert!(eye_line(&status(DVec3::new(1.0, 2.0, 3.0), false)).starts_with("eye 1 2 3"));
    }
}
