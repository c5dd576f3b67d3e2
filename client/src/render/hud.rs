//! A heads-up display: lines of text rasterized on the CPU with an 8x8 bitmap font
//! (public domain) and drawn over the frame in one small pass.

use bytemuck::{Pod, Zeroable};

use super::gpu::{texture, texture_entry, uniform_entry, write_layer};

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
        let uniforms = device.create_buffer(&wgpu::BufferDescriptor {
            label: Some("buffer.hud.uniforms"),
            size: size_of::<Uniforms>() as u64,
            usage: wgpu::BufferUsages::UNIFORM | wgpu::BufferUsages::COPY_DST,
            mapped_at_creation: false,
        });
        let layout = device.create_bind_group_layout(&wgpu::BindGroupLayoutDescriptor {
            label: Some("layout.hud"),
            entries: &[
                uniform_entry(0),
                texture_entry(1, wgpu::TextureSampleType::Float { filterable: false }, wgpu::TextureViewDimension::D2),
            ],
        });
        let view = texture.create_view(&wgpu::TextureViewDescriptor::default());
        let bind_group = device.create_bind_group(&wgpu::BindGroupDescriptor {
            label: Some("bind_group.hud"),
            layout: &layout,
            entries: &[
                wgpu::BindGroupEntry { binding: 0, resource: uniforms.as_entire_binding() },
                wgpu::BindGroupEntry { binding: 1, resource: wgpu::BindingResource::TextureView(&view) },
            ],
        });
        let shader = device.create_shader_module(wgpu::ShaderModuleDescriptor {
            label: Some("shader.hud"),
            source: wgpu::ShaderSource::Wgsl(HUD_WGSL.into()),
        });
        let pipeline_layout = device.create_pipeline_layout(&wgpu::PipelineLayoutDescriptor {
            label: Some("pipeline_layout.hud"),
            bind_group_layouts: &[Some(&layout)],
            immediate_size: 0,
        });
        let pipeline = device.create_render_pipeline(&wgpu::RenderPipelineDescriptor {
            label: Some("pipeline.hud"),
            layout: Some(&pipeline_layout),
            vertex: wgpu::VertexState {
                module: &shader,
                entry_point: Some("vs_main"),
                compilation_options: wgpu::PipelineCompilationOptions::default(),
                buffers: &[],
            },
            primitive: wgpu::PrimitiveState { topology: wgpu::PrimitiveTopology::TriangleStrip, ..Default::default() },
            depth_stencil: Some(wgpu::DepthStencilState {
                format: super::renderer::DEPTH_FORMAT,
                depth_write_enabled: Some(false),
                depth_compare: Some(wgpu::CompareFunction::Always),
                stencil: wgpu::StencilState::default(),
                bias: wgpu::DepthBiasState::default(),
            }),
            multisample: wgpu::MultisampleState::default(),
            fragment: Some(wgpu::FragmentState {
                module: &shader,
                entry_point: Some("fs_main"),
                compilation_options: wgpu::PipelineCompilationOptions::default(),
                targets: &[Some(wgpu::ColorTargetState {
                    format,
                    blend: Some(wgpu::BlendState::ALPHA_BLENDING),
                    write_mask: wgpu::ColorWrites::ALL,
                })],
            }),
            multiview_mask: None,
            cache: None,
        });
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
