//! The terrain's shaders, bind group layout and pipelines, made once per colour format
//! and shared by every renderer of that format; the patch mesh's buffers.

use wgpu::util::DeviceExt;

use super::atmosphere::{ATMOSPHERE_WGSL, AtmospherePipelines};
use super::gpu::{self, sampler_entry, texture_entry, uniform_entry};
use super::mesh::PatchMesh;

/// The shader source.
pub const TERRAIN_WGSL: &str = include_str!("../../../shaders/terrain.wgsl");

/// Depth buffer format (reversed depth: 1 near, 0 at infinity).
pub const DEPTH_FORMAT: wgpu::TextureFormat = wgpu::TextureFormat::Depth32Float;

/// Bilinear, clamped: the colour tiles' sampler.
pub(super) fn colour_sampler(device: &wgpu::Device) -> wgpu::Sampler {
    device.create_sampler(&wgpu::SamplerDescriptor {
        label: Some("sampler.tiles.colour"),
        address_mode_u: wgpu::AddressMode::ClampToEdge,
        address_mode_v: wgpu::AddressMode::ClampToEdge,
        mag_filter: wgpu::FilterMode::Linear,
        min_filter: wgpu::FilterMode::Linear,
        ..Default::default()
    })
}

/// The terrain's bind group layout and pipeline for one colour format: its shaders are
/// compiled when it is made. Renderers of that format share one; a front end may make it
/// before any archive is open, so that the first frame with terrain does not wait for
/// the shaders (wgpu handles are reference-counted: clones share the pipeline).
#[derive(Clone, Debug)]
pub struct TerrainPipeline {
    pub(super) layout: wgpu::BindGroupLayout,
    pub(super) pipeline: wgpu::RenderPipeline,
    pub(super) atmosphere: AtmospherePipelines,
    format: wgpu::TextureFormat,
}

impl TerrainPipeline {
    /// Makes (compiles) the pipelines for `colour_format`: the terrain's, the sky's and
    /// the atmosphere tables'.
    pub fn new(device: &wgpu::Device, colour_format: wgpu::TextureFormat) -> Self {
        let layout = bind_group_layout(device);
        let source = format!("{TERRAIN_WGSL}\n{ATMOSPHERE_WGSL}");
        let module = gpu::shader(device, "terrain", &source);
        let pipeline = terrain_pipeline(device, &module, &layout, colour_format);
        let atmosphere = AtmospherePipelines::new(device, &module, &layout, colour_format);
        Self { layout, pipeline, atmosphere, format: colour_format }
    }

    /// The colour format it draws into.
    pub fn format(&self) -> wgpu::TextureFormat {
        self.format
    }
}

/// Globals, page table, elevation tiles, colour tiles, colour sampler.
fn bind_group_layout(device: &wgpu::Device) -> wgpu::BindGroupLayout {
    device.create_bind_group_layout(&wgpu::BindGroupLayoutDescriptor {
        label: Some("layout.terrain"),
        entries: &[
            uniform_entry(0),
            texture_entry(1, wgpu::TextureSampleType::Uint, wgpu::TextureViewDimension::D2),
            texture_entry(2, wgpu::TextureSampleType::Float { filterable: false }, wgpu::TextureViewDimension::D2Array),
            texture_entry(3, wgpu::TextureSampleType::Float { filterable: true }, wgpu::TextureViewDimension::D2Array),
            sampler_entry(4),
            texture_entry(5, wgpu::TextureSampleType::Float { filterable: false }, wgpu::TextureViewDimension::D2),
            uniform_entry(6),
            texture_entry(7, wgpu::TextureSampleType::Float { filterable: true }, wgpu::TextureViewDimension::D2),
            texture_entry(8, wgpu::TextureSampleType::Float { filterable: true }, wgpu::TextureViewDimension::D2),
            sampler_entry(9),
            texture_entry(10, wgpu::TextureSampleType::Float { filterable: true }, wgpu::TextureViewDimension::D2),
            texture_entry(11, wgpu::TextureSampleType::Float { filterable: true }, wgpu::TextureViewDimension::D2),
            texture_entry(12, wgpu::TextureSampleType::Float { filterable: true }, wgpu::TextureViewDimension::D2),
            texture_entry(13, wgpu::TextureSampleType::Float { filterable: true }, wgpu::TextureViewDimension::D2Array),
        ],
    })
}

/// The terrain pipeline: patch vertices and per-instance patch placement, reversed depth.
fn terrain_pipeline(
    device: &wgpu::Device,
    module: &wgpu::ShaderModule,
    layout: &wgpu::BindGroupLayout,
    colour_format: wgpu::TextureFormat,
) -> wgpu::RenderPipeline {
    gpu::pipeline_in(
        device,
        module,
        &gpu::PipelineDesc {
            name: "terrain",
            wgsl: TERRAIN_WGSL,
            layout,
            buffers: &[
                Some(wgpu::VertexBufferLayout {
                    array_stride: 8,
                    step_mode: wgpu::VertexStepMode::Vertex,
                    attributes: &wgpu::vertex_attr_array![0 => Float32x2],
                }),
                Some(wgpu::VertexBufferLayout {
                    array_stride: 16,
                    step_mode: wgpu::VertexStepMode::Instance,
                    attributes: &wgpu::vertex_attr_array![1 => Float32x4],
                }),
            ],
            topology: wgpu::PrimitiveTopology::TriangleList,
            depth: (true, wgpu::CompareFunction::Greater),
            target: (colour_format, None),
        },
    )
}

/// The patch mesh's vertex and index buffers.
pub(super) fn patch_buffers(device: &wgpu::Device, mesh: &PatchMesh) -> (wgpu::Buffer, wgpu::Buffer) {
    let vertices = device.create_buffer_init(&wgpu::util::BufferInitDescriptor {
        label: Some("buffer.terrain.patch_vertices"),
        contents: bytemuck::cast_slice(&mesh.vertices),
        usage: wgpu::BufferUsages::VERTEX,
    });
    let indices = device.create_buffer_init(&wgpu::util::BufferInitDescriptor {
        label: Some("buffer.terrain.patch_indices"),
        contents: bytemuck::cast_slice(&mesh.indices),
        usage: wgpu::BufferUsages::INDEX,
    });
    (vertices, indices)
}
