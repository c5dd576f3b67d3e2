//! A device without a window, an offscreen target, and reading pixels back.

use std::fmt;

use super::renderer::DEPTH_FORMAT;

/// Colour format of offscreen targets (sRGB, so shaders work in linear light).
pub const OFFSCREEN_FORMAT: wgpu::TextureFormat = wgpu::TextureFormat::Rgba8UnormSrgb;

/// Why no GPU could be used.
#[derive(Debug)]
pub struct GpuError(pub String);

impl fmt::Display for GpuError {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.write_str(&self.0)
    }
}

impl std::error::Error for GpuError {}

/// An adapter's device and queue.
#[derive(Debug)]
pub struct Gpu {
    /// The device.
    pub device: wgpu::Device,
    /// Its queue.
    pub queue: wgpu::Queue,
    /// Which adapter and backend (a software rasterizer counts: device type `Cpu`).
    pub info: wgpu::AdapterInfo,
    /// The adapter.
    pub adapter: wgpu::Adapter,
}

impl Gpu {
    /// A device on the first adapter `WGPU_BACKEND` allows (Vulkan first, then GL),
    /// software rasterizers included.
    ///
    /// # Errors
    /// When no adapter or device is available.
    pub async fn new(instance: &wgpu::Instance, surface: Option<&wgpu::Surface<'_>>) -> Result<Self, GpuError> {
        let adapter = instance
            .request_adapter(&wgpu::RequestAdapterOptions {
                power_preference: wgpu::PowerPreference::HighPerformance,
                force_fallback_adapter: false,
                compatible_surface: surface,
                ..Default::default()
            })
            .await
            .map_err(|e| GpuError(format!("no graphics adapter: {e}")))?;
        let info = adapter.get_info();
        let features = adapter.features() & wgpu::Features::TEXTURE_COMPRESSION_BC;
        let (device, queue) = adapter
            .request_device(&wgpu::DeviceDescriptor {
                label: Some("device.terrastream"),
                required_features: features,
                required_limits: adapter.limits(),
                ..Default::default()
            })
            .await
            .map_err(|e| GpuError(format!("adapter {} ({:?}) refused a device: {e}", info.name, info.backend)))?;
        Ok(Self { device, queue, info, adapter })
    }

    /// A device without a window (blocking).
    ///
    /// # Errors
    /// When no adapter or device is available.
    #[cfg(not(target_arch = "wasm32"))]
    pub fn headless() -> Result<Self, GpuError> {
        let instance = wgpu::Instance::new(wgpu::InstanceDescriptor::new_without_display_handle_from_env());
        pollster::block_on(Self::new(&instance, None))
    }

    /// "name (backend, device type)".
    pub fn describe(&self) -> String {
        format!("{} ({:?}, {:?})", self.info.name, self.info.backend, self.info.device_type)
    }
}

/// The surface's next frame to draw into. An outdated or lost surface is configured
/// again with `config` and gives `None` this time (the next frame will have one).
pub fn next_frame(
    surface: &wgpu::Surface<'_>,
    device: &wgpu::Device,
    config: &wgpu::SurfaceConfiguration,
) -> Option<wgpu::SurfaceTexture> {
    match surface.get_current_texture() {
        wgpu::CurrentSurfaceTexture::Success(t) | wgpu::CurrentSurfaceTexture::Suboptimal(t) => Some(t),
        wgpu::CurrentSurfaceTexture::Outdated | wgpu::CurrentSurfaceTexture::Lost => {
            surface.configure(device, config);
            None
        }
        other => {
            tracing::warn!("no frame to draw into: {other:?}");
            None
        }
    }
}

/// A 2D texture (`layers` > 1: an array) with one mip level.
pub fn texture(
    device: &wgpu::Device,
    label: &str,
    (width, height, layers): (u32, u32, u32),
    format: wgpu::TextureFormat,
    usage: wgpu::TextureUsages,
) -> wgpu::Texture {
    device.create_texture(&wgpu::TextureDescriptor {
        label: Some(label),
        size: wgpu::Extent3d { width, height, depth_or_array_layers: layers },
        mip_level_count: 1,
        sample_count: 1,
        dimension: wgpu::TextureDimension::D2,
        format,
        usage,
        view_formats: &[],
    })
}

/// A depth target of [`DEPTH_FORMAT`].
pub fn depth_target(device: &wgpu::Device, label: &str, width: u32, height: u32) -> wgpu::Texture {
    texture(device, label, (width.max(1), height.max(1), 1), DEPTH_FORMAT, wgpu::TextureUsages::RENDER_ATTACHMENT)
}

/// Writes a whole `width` x `height` image (`rows` rows of `bytes_per_row`: texels, or
/// 4x4 blocks for compressed formats) into array layer `layer` of `texture`.
pub fn write_layer(
    queue: &wgpu::Queue,
    texture: &wgpu::Texture,
    layer: u32,
    data: &[u8],
    (bytes_per_row, rows): (u32, u32),
    (width, height): (u32, u32),
) {
    queue.write_texture(
        wgpu::TexelCopyTextureInfo {
            texture,
            mip_level: 0,
            origin: wgpu::Origin3d { x: 0, y: 0, z: layer },
            aspect: wgpu::TextureAspect::All,
        },
        data,
        wgpu::TexelCopyBufferLayout { offset: 0, bytes_per_row: Some(bytes_per_row), rows_per_image: Some(rows) },
        wgpu::Extent3d { width, height, depth_or_array_layers: 1 },
    );
}

/// What tells this crate's render pipelines apart; they all have one bind group, entry
/// points `vs_main` and `fs_main`, one colour target and a [`DEPTH_FORMAT`] depth test.
pub struct PipelineDesc<'a> {
    /// Names the shader, layout and pipeline (`shader.{name}`, ...).
    pub name: &'a str,
    /// WGSL source.
    pub wgsl: &'a str,
    /// The bind group's layout.
    pub layout: &'a wgpu::BindGroupLayout,
    /// Vertex buffers.
    pub buffers: &'a [Option<wgpu::VertexBufferLayout<'a>>],
    /// Primitive topology.
    pub topology: wgpu::PrimitiveTopology,
    /// Write depth, and the depth test.
    pub depth: (bool, wgpu::CompareFunction),
    /// Colour target format and blending.
    pub target: (wgpu::TextureFormat, Option<wgpu::BlendState>),
}

/// A render pipeline from `desc`.
pub fn pipeline(device: &wgpu::Device, desc: &PipelineDesc<'_>) -> wgpu::RenderPipeline {
    pipeline_in(device, &shader(device, desc.name, desc.wgsl), desc)
}

/// A shader module of WGSL source, named `shader.{name}`.
pub fn shader(device: &wgpu::Device, name: &str, wgsl: &str) -> wgpu::ShaderModule {
    device.create_shader_module(wgpu::ShaderModuleDescriptor {
        label: Some(&format!("shader.{name}")),
        source: wgpu::ShaderSource::Wgsl(wgsl.into()),
    })
}

/// A render pipeline from `desc` with a module already made (`desc.wgsl` unused): its
/// other entry points serve other pipelines.
pub fn pipeline_in(
    device: &wgpu::Device,
    shader: &wgpu::ShaderModule,
    desc: &PipelineDesc<'_>,
) -> wgpu::RenderPipeline {
    let layout = device.create_pipeline_layout(&wgpu::PipelineLayoutDescriptor {
        label: Some(&format!("pipeline_layout.{}", desc.name)),
        bind_group_layouts: &[Some(desc.layout)],
        immediate_size: 0,
    });
    device.create_render_pipeline(&wgpu::RenderPipelineDescriptor {
        label: Some(&format!("pipeline.{}", desc.name)),
        layout: Some(&layout),
        vertex: wgpu::VertexState {
            module: shader,
            entry_point: Some("vs_main"),
            compilation_options: wgpu::PipelineCompilationOptions::default(),
            buffers: desc.buffers,
        },
        primitive: wgpu::PrimitiveState { topology: desc.topology, cull_mode: None, ..Default::default() },
        depth_stencil: Some(wgpu::DepthStencilState {
            format: DEPTH_FORMAT,
            depth_write_enabled: Some(desc.depth.0),
            depth_compare: Some(desc.depth.1),
            stencil: wgpu::StencilState::default(),
            bias: wgpu::DepthBiasState::default(),
        }),
        multisample: wgpu::MultisampleState::default(),
        fragment: Some(wgpu::FragmentState {
            module: shader,
            entry_point: Some("fs_main"),
            compilation_options: wgpu::PipelineCompilationOptions::default(),
            targets: &[Some(wgpu::ColorTargetState {
                format: desc.target.0,
                blend: desc.target.1,
                write_mask: wgpu::ColorWrites::ALL,
            })],
        }),
        multiview_mask: None,
        cache: None,
    })
}

/// A uniform buffer of `size` bytes, written with `queue.write_buffer`.
pub fn uniform_buffer(device: &wgpu::Device, label: &str, size: usize) -> wgpu::Buffer {
    device.create_buffer(&wgpu::BufferDescriptor {
        label: Some(label),
        size: size as u64,
        usage: wgpu::BufferUsages::UNIFORM | wgpu::BufferUsages::COPY_DST,
        mapped_at_creation: false,
    })
}

/// A bind group whose entries are `resources` at bindings 0, 1, ...
pub fn bind_group(
    device: &wgpu::Device,
    label: &str,
    layout: &wgpu::BindGroupLayout,
    resources: &[wgpu::BindingResource<'_>],
) -> wgpu::BindGroup {
    let entries: Vec<wgpu::BindGroupEntry<'_>> = (0u32..)
        .zip(resources)
        .map(|(binding, resource)| wgpu::BindGroupEntry { binding, resource: resource.clone() })
        .collect();
    device.create_bind_group(&wgpu::BindGroupDescriptor { label: Some(label), layout, entries: &entries })
}

/// A bind-group layout entry for a uniform buffer seen by both stages.
pub fn uniform_entry(binding: u32) -> wgpu::BindGroupLayoutEntry {
    wgpu::BindGroupLayoutEntry {
        binding,
        visibility: wgpu::ShaderStages::VERTEX_FRAGMENT,
        ty: wgpu::BindingType::Buffer {
            ty: wgpu::BufferBindingType::Uniform,
            has_dynamic_offset: false,
            min_binding_size: None,
        },
        count: None,
    }
}

/// A bind-group layout entry for a texture seen by both stages.
pub fn texture_entry(
    binding: u32,
    sample_type: wgpu::TextureSampleType,
    view_dimension: wgpu::TextureViewDimension,
) -> wgpu::BindGroupLayoutEntry {
    wgpu::BindGroupLayoutEntry {
        binding,
        visibility: wgpu::ShaderStages::VERTEX_FRAGMENT,
        ty: wgpu::BindingType::Texture { sample_type, view_dimension, multisampled: false },
        count: None,
    }
}

/// A bind-group layout entry for a filtering sampler seen by both stages.
pub fn sampler_entry(binding: u32) -> wgpu::BindGroupLayoutEntry {
    wgpu::BindGroupLayoutEntry {
        binding,
        visibility: wgpu::ShaderStages::VERTEX_FRAGMENT,
        ty: wgpu::BindingType::Sampler(wgpu::SamplerBindingType::Filtering),
        count: None,
    }
}

/// A colour and depth target that can be read back.
#[derive(Debug)]
pub struct Offscreen {
    colour: wgpu::Texture,
    depth: wgpu::Texture,
    /// Width in pixels.
    pub width: u32,
    /// Height in pixels.
    pub height: u32,
}

impl Offscreen {
    /// A `width` x `height` target.
    pub fn new(device: &wgpu::Device, width: u32, height: u32) -> Self {
        let colour = texture(
            device,
            "texture.offscreen.colour",
            (width, height, 1),
            OFFSCREEN_FORMAT,
            wgpu::TextureUsages::RENDER_ATTACHMENT | wgpu::TextureUsages::COPY_SRC,
        );
        let depth = depth_target(device, "texture.offscreen.depth", width, height);
        Self { colour, depth, width, height }
    }

    /// View of the colour target.
    pub fn colour_view(&self) -> wgpu::TextureView {
        self.colour.create_view(&wgpu::TextureViewDescriptor::default())
    }

    /// View of the depth target.
    pub fn depth_view(&self) -> wgpu::TextureView {
        self.depth.create_view(&wgpu::TextureViewDescriptor::default())
    }

    /// The colour target's pixels, RGBA8 rows top to bottom (blocks until the GPU is done).
    ///
    /// # Errors
    /// When the GPU cannot map the read-back buffer.
    pub fn read_rgba(&self, device: &wgpu::Device, queue: &wgpu::Queue) -> Result<Vec<u8>, GpuError> {
        let row = self.width * 4;
        let padded = row.div_ceil(wgpu::COPY_BYTES_PER_ROW_ALIGNMENT) * wgpu::COPY_BYTES_PER_ROW_ALIGNMENT;
        let buffer = device.create_buffer(&wgpu::BufferDescriptor {
            label: Some("buffer.offscreen.readback"),
            size: u64::from(padded) * u64::from(self.height),
            usage: wgpu::BufferUsages::COPY_DST | wgpu::BufferUsages::MAP_READ,
            mapped_at_creation: false,
        });
        let mut encoder = device
            .create_command_encoder(&wgpu::CommandEncoderDescriptor { label: Some("encoder.offscreen.readback") });
        encoder.copy_texture_to_buffer(
            wgpu::TexelCopyTextureInfo {
                texture: &self.colour,
                mip_level: 0,
                origin: wgpu::Origin3d::ZERO,
                aspect: wgpu::TextureAspect::All,
            },
            wgpu::TexelCopyBufferInfo {
                buffer: &buffer,
                layout: wgpu::TexelCopyBufferLayout {
                    offset: 0,
                    bytes_per_row: Some(padded),
                    rows_per_image: Some(self.height),
                },
            },
            wgpu::Extent3d { width: self.width, height: self.height, depth_or_array_layers: 1 },
        );
        queue.submit([encoder.finish()]);
        let slice = buffer.slice(..);
        slice.map_async(wgpu::MapMode::Read, |_| {});
        device.poll(wgpu::PollType::wait_indefinitely()).map_err(|e| GpuError(format!("waiting for the GPU: {e}")))?;
        let mapped = slice.get_mapped_range().map_err(|e| GpuError(format!("reading the frame back: {e}")))?;
        let mut out = Vec::with_capacity((row * self.height) as usize);
        for r in 0..self.height as usize {
            let start = r * padded as usize;
            out.extend_from_slice(&mapped[start..start + row as usize]);
        }
        Ok(out)
    }
}

/// Records one pass drawing `draw` into `colour` and `depth`, cleared to `clear`.
pub fn render_pass(
    device: &wgpu::Device,
    queue: &wgpu::Queue,
    colour: &wgpu::TextureView,
    depth: &wgpu::TextureView,
    clear: wgpu::Color,
    draw: impl FnOnce(&mut wgpu::RenderPass<'_>),
) {
    let mut encoder = device.create_command_encoder(&wgpu::CommandEncoderDescriptor { label: Some("encoder.frame") });
    {
        let mut pass = encoder.begin_render_pass(&wgpu::RenderPassDescriptor {
            label: Some("pass.terrain"),
            color_attachments: &[Some(wgpu::RenderPassColorAttachment {
                view: colour,
                depth_slice: None,
                resolve_target: None,
                ops: wgpu::Operations { load: wgpu::LoadOp::Clear(clear), store: wgpu::StoreOp::Store },
            })],
            depth_stencil_attachment: Some(wgpu::RenderPassDepthStencilAttachment {
                view: depth,
                depth_ops: Some(wgpu::Operations { load: wgpu::LoadOp::Clear(0.0), store: wgpu::StoreOp::Store }),
                stencil_ops: None,
            }),
            timestamp_writes: None,
            occlusion_query_set: None,
            multiview_mask: None,
        });
        draw(&mut pass);
    }
    queue.submit([encoder.finish()]);
}
