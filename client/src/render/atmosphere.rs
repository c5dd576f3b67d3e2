//! The atmosphere over the globe (Hillaire 2020; `shaders/atmosphere.wgsl`): its two
//! tables made once by render passes (which WebGL2 runs too), the per-frame uniform, and
//! the sky's pipeline. The terrain's fragment shader reads the same tables for the aerial
//! perspective.

use bytemuck::{Pod, Zeroable};
use glam::{DMat4, DVec3, Mat4};

use super::gpu::{self, sampler_entry, texture_entry, uniform_entry};

/// Shared functions of the atmosphere (appended to the shaders that use them).
pub const ATMOSPHERE_WGSL: &str = include_str!("../../../shaders/atmosphere.wgsl");
/// The tables' passes (appended to [`ATMOSPHERE_WGSL`]).
const LUTS_WGSL: &str = include_str!("../../../shaders/atmosphere_luts.wgsl");

/// Radius of the atmosphere model's ground sphere (the shader's `BOTTOM`), metres.
pub const BOTTOM: f64 = 6_360_000.0;
/// Sample format of the tables: linear light, filterable, renderable on WebGL2.
const LUT_FORMAT: wgpu::TextureFormat = wgpu::TextureFormat::Rgba16Float;
const TRANSMITTANCE_SIZE: (u32, u32) = (256, 64);
const MULTISCATTERING_SIZE: (u32, u32) = (32, 32);
const SKY_VIEW_SIZE: (u32, u32) = (192, 108);
/// 32 x 32 screen rays, 32 distances side by side.
const AERIAL_SIZE: (u32, u32) = (32 * 32, 32);
/// The top of the model's atmosphere above its sphere, metres (the shader's TOP - BOTTOM).
const THICKNESS: f64 = 100_000.0;
/// Exposure of the displayed radiance (for a sun of illuminance 1).
const EXPOSURE: f32 = 10.0;
/// Ray-march samples of the sky and of the aerial perspective.
const SKY_STEPS: f32 = 16.0;
const AERIAL_STEPS: f32 = 8.0;
/// The sun's angular radius, radians.
const SUN_RADIUS: f32 = 0.004_65;

/// `AtmosphereUniform` of the shaders.
#[repr(C)]
#[derive(Clone, Copy, Pod, Zeroable, Debug, PartialEq)]
pub struct AtmosphereUniform {
    inv_view_proj: [[f32; 4]; 4],
    eye: [f32; 4],
    sun: [f32; 4],
    look: [f32; 4],
    pole: [f32; 4],
    tables: [f32; 4],
    meridian: [f32; 4],
}

/// How far an eye `height` above the sphere sees what stands `top` above it: to the
/// eye's horizon on the sphere and on from there to where that height meets it.
fn horizon_reach(height: f64, top: f64) -> f64 {
    let r = BOTTOM + height.max(0.0);
    (r * r - BOTTOM * BOTTOM).max(0.0).sqrt() + ((BOTTOM + top).powi(2) - BOTTOM * BOTTOM).sqrt()
}

impl AtmosphereUniform {
    /// Off: the terrain keeps its plain haze and no sky is drawn.
    pub fn off() -> Self {
        Self::zeroed()
    }

    /// On, for a view from `eye` (frame metres from the planet's centre, `height` above
    /// the ellipsoid, whose radius under the anchor is `radius`), looking through the
    /// camera-relative `rotation_projection` onto a `viewport` (pixels), the sun towards
    /// `sun`, the pole towards `pole` and the prime meridian at the equator towards
    /// `meridian` (all in the frame's axes); the whole-Earth picture on the ground beyond
    /// the data where `earth` gives the eye's longitude and latitude (degrees). From
    /// inside the atmosphere the sky and the aerial perspective come from per-frame tables.
    pub fn on(
        eye: DVec3,
        height: f64,
        radius: f64,
        (rotation_projection, viewport): (DMat4, (f64, f64)),
        sun: DVec3,
        (pole, meridian, earth): (DVec3, DVec3, Option<(f64, f64)>),
    ) -> Self {
        let scale = BOTTOM / radius.max(1.0);
        let inverse: Mat4 = rotation_projection.inverse().as_mat4();
        let e = (eye.normalize_or(DVec3::Y) * (BOTTOM + height)).as_vec3();
        let s = sun.try_normalize().unwrap_or(DVec3::Y).as_vec3();
        let p = pole.try_normalize().unwrap_or(DVec3::Y).as_vec3();
        let m = meridian.try_normalize().unwrap_or(DVec3::X).as_vec3();
        // The highest ground beyond the data that the eye can see: within its horizon's
        // reach of the highest the whole-Earth heights hold (the sky pass marches below it).
        let highest = earth.map_or(0.0, |(lon, lat)| {
            super::earth::highest_near(lon, lat, horizon_reach(height, f64::from(super::earth::HIGHEST)))
        });
        #[allow(clippy::cast_possible_truncation)]
        Self {
            inv_view_proj: inverse.to_cols_array_2d(),
            eye: [e.x, e.y, e.z, scale as f32],
            sun: [s.x, s.y, s.z, SUN_RADIUS],
            look: [EXPOSURE, 1.0, SKY_STEPS, AERIAL_STEPS],
            pole: [p.x, p.y, p.z, highest],
            meridian: [m.x, m.y, m.z, f32::from(u8::from(earth.is_some()))],
            tables: {
                // Out to where the ground and the air's top meet the horizon.
                let far = horizon_reach(height, THICKNESS);
                let inside = height < THICKNESS * 0.95;
                #[allow(clippy::cast_possible_truncation)]
                [f32::from(u8::from(inside)), far as f32, viewport.0 as f32, viewport.1 as f32]
            },
        }
    }

    /// Are the sky and the aerial perspective read from the per-frame tables?
    pub fn uses_tables(&self) -> bool {
        self.is_on() && self.tables[0] > 0.5
    }

    /// Is the atmosphere drawn?
    pub fn is_on(&self) -> bool {
        self.look[1] > 0.5
    }
}

/// The tables, their views and the uniform, shared by the sky and the terrain.
pub struct AtmosphereTables {
    /// The per-frame uniform.
    pub uniform: wgpu::Buffer,
    transmittance: wgpu::Texture,
    multiscattering: wgpu::Texture,
    /// Views the terrain's and the sky's bind group take.
    pub transmittance_view: wgpu::TextureView,
    /// The same of the multiple-scattering table.
    pub multiscattering_view: wgpu::TextureView,
    /// The same of the per-frame sky-view table.
    pub sky_view_view: wgpu::TextureView,
    /// The same of the per-frame aerial-perspective table.
    pub aerial_view: wgpu::TextureView,
    /// The per-frame passes' bind group (made with the tables).
    frame_group: Option<wgpu::BindGroup>,
    /// Linear, clamped.
    pub sampler: wgpu::Sampler,
    made: bool,
}

impl std::fmt::Debug for AtmosphereTables {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("AtmosphereTables").field("made", &self.made).finish_non_exhaustive()
    }
}

fn lut(device: &wgpu::Device, label: &str, (w, h): (u32, u32)) -> wgpu::Texture {
    gpu::texture(
        device,
        label,
        (w, h, 1),
        LUT_FORMAT,
        wgpu::TextureUsages::TEXTURE_BINDING | wgpu::TextureUsages::RENDER_ATTACHMENT,
    )
}

impl AtmosphereTables {
    /// Empty tables (made by [`Self::make`] before the first frame that draws them).
    pub fn new(device: &wgpu::Device) -> Self {
        let transmittance = lut(device, "texture.atmosphere.transmittance", TRANSMITTANCE_SIZE);
        let multiscattering = lut(device, "texture.atmosphere.multiscattering", MULTISCATTERING_SIZE);
        let view = |t: &wgpu::Texture| t.create_view(&wgpu::TextureViewDescriptor::default());
        let sky_view = lut(device, "texture.atmosphere.sky_view", SKY_VIEW_SIZE);
        let aerial = lut(device, "texture.atmosphere.aerial", AERIAL_SIZE);
        Self {
            sky_view_view: view(&sky_view),
            aerial_view: view(&aerial),
            frame_group: None,
            uniform: gpu::uniform_buffer(device, "buffer.atmosphere", size_of::<AtmosphereUniform>()),
            transmittance_view: view(&transmittance),
            multiscattering_view: view(&multiscattering),
            transmittance,
            multiscattering,
            sampler: device.create_sampler(&wgpu::SamplerDescriptor {
                label: Some("sampler.atmosphere"),
                mag_filter: wgpu::FilterMode::Linear,
                min_filter: wgpu::FilterMode::Linear,
                ..Default::default()
            }),
            made: false,
        }
    }

    /// This frame's tables (after its uniform is written): the sky view and the aerial
    /// perspective, from the transmittance and multiple-scattering tables.
    pub fn make_frame(&mut self, device: &wgpu::Device, queue: &wgpu::Queue, pipelines: &AtmospherePipelines) {
        let group = self.frame_group.get_or_insert_with(|| {
            gpu::bind_group(
                device,
                "bind_group.atmosphere.frame",
                &pipelines.lut_layout,
                &[
                    self.uniform.as_entire_binding(),
                    wgpu::BindingResource::TextureView(&self.transmittance_view),
                    wgpu::BindingResource::TextureView(&self.multiscattering_view),
                    wgpu::BindingResource::Sampler(&self.sampler),
                ],
            )
        });
        let mut encoder =
            device.create_command_encoder(&wgpu::CommandEncoderDescriptor { label: Some("encoder.atmosphere.frame") });
        for (target, pipeline) in [(&self.sky_view_view, &pipelines.sky_view), (&self.aerial_view, &pipelines.aerial)] {
            fill(&mut encoder, target, pipeline, group);
        }
        queue.submit([encoder.finish()]);
    }

    /// Computes the tables once: transmittance, then multiple scattering from it.
    pub fn make(&mut self, device: &wgpu::Device, queue: &wgpu::Queue, pipelines: &AtmospherePipelines) {
        if self.made {
            return;
        }
        self.made = true;
        // The multiple-scattering pass reads the transmittance table; the transmittance
        // pass reads nothing, but its layout has a texture there: a 1 x 1 stand-in.
        let stand_in = lut(device, "texture.atmosphere.none", (1, 1));
        let stand_in_view = stand_in.create_view(&wgpu::TextureViewDescriptor::default());
        let mut encoder =
            device.create_command_encoder(&wgpu::CommandEncoderDescriptor { label: Some("encoder.atmosphere") });
        for (target, pipeline, input) in [
            (&self.transmittance, &pipelines.transmittance, &stand_in_view),
            (&self.multiscattering, &pipelines.multiscattering, &self.transmittance_view),
        ] {
            let group = gpu::bind_group(
                device,
                "bind_group.atmosphere.lut",
                &pipelines.lut_layout,
                &[
                    self.uniform.as_entire_binding(),
                    wgpu::BindingResource::TextureView(input),
                    wgpu::BindingResource::TextureView(&stand_in_view),
                    wgpu::BindingResource::Sampler(&self.sampler),
                ],
            );
            let view = target.create_view(&wgpu::TextureViewDescriptor::default());
            fill(&mut encoder, &view, pipeline, &group);
        }
        queue.submit([encoder.finish()]);
    }
}

/// One fullscreen pass of `pipeline` into `target`.
fn fill(
    encoder: &mut wgpu::CommandEncoder,
    target: &wgpu::TextureView,
    pipeline: &wgpu::RenderPipeline,
    group: &wgpu::BindGroup,
) {
    let mut pass = encoder.begin_render_pass(&wgpu::RenderPassDescriptor {
        label: Some("pass.atmosphere.table"),
        color_attachments: &[Some(wgpu::RenderPassColorAttachment {
            view: target,
            depth_slice: None,
            resolve_target: None,
            ops: wgpu::Operations { load: wgpu::LoadOp::Clear(wgpu::Color::BLACK), store: wgpu::StoreOp::Store },
        })],
        depth_stencil_attachment: None,
        timestamp_writes: None,
        occlusion_query_set: None,
        multiview_mask: None,
    });
    pass.set_pipeline(pipeline);
    pass.set_bind_group(0, group, &[]);
    pass.draw(0..3, 0..1);
}

/// The tables' pipelines and the sky's, compiled with the terrain's (a front end makes
/// them before an archive opens).
#[derive(Clone, Debug)]
pub struct AtmospherePipelines {
    lut_layout: wgpu::BindGroupLayout,
    transmittance: wgpu::RenderPipeline,
    multiscattering: wgpu::RenderPipeline,
    sky_view: wgpu::RenderPipeline,
    aerial: wgpu::RenderPipeline,
    /// The sky, drawn with the terrain's bind group before the terrain.
    pub sky: wgpu::RenderPipeline,
}

fn fullscreen(
    device: &wgpu::Device,
    name: &str,
    module: &wgpu::ShaderModule,
    layout: &wgpu::BindGroupLayout,
    (vertex, fragment): (&str, &str),
    format: wgpu::TextureFormat,
    depth: bool,
) -> wgpu::RenderPipeline {
    let layout = device.create_pipeline_layout(&wgpu::PipelineLayoutDescriptor {
        label: Some(&format!("pipeline_layout.{name}")),
        bind_group_layouts: &[Some(layout)],
        immediate_size: 0,
    });
    device.create_render_pipeline(&wgpu::RenderPipelineDescriptor {
        label: Some(&format!("pipeline.{name}")),
        layout: Some(&layout),
        vertex: wgpu::VertexState {
            module,
            entry_point: Some(vertex),
            compilation_options: wgpu::PipelineCompilationOptions::default(),
            buffers: &[],
        },
        primitive: wgpu::PrimitiveState::default(),
        depth_stencil: depth.then(|| wgpu::DepthStencilState {
            format: super::renderer::DEPTH_FORMAT,
            depth_write_enabled: Some(false),
            // Drawn after the terrain: only where the depth is still the far plane's
            // (reversed depth: 0), so covered pixels are never shaded.
            depth_compare: Some(wgpu::CompareFunction::GreaterEqual),
            stencil: wgpu::StencilState::default(),
            bias: wgpu::DepthBiasState::default(),
        }),
        multisample: wgpu::MultisampleState::default(),
        fragment: Some(wgpu::FragmentState {
            module,
            entry_point: Some(fragment),
            compilation_options: wgpu::PipelineCompilationOptions::default(),
            targets: &[Some(wgpu::ColorTargetState { format, blend: None, write_mask: wgpu::ColorWrites::ALL })],
        }),
        multiview_mask: None,
        cache: None,
    })
}

impl AtmospherePipelines {
    /// The pipelines; the sky's draws into `format` with the terrain's `layout` and
    /// `terrain` shader module (which has the sky's entry points).
    pub fn new(
        device: &wgpu::Device,
        terrain: &wgpu::ShaderModule,
        layout: &wgpu::BindGroupLayout,
        format: wgpu::TextureFormat,
    ) -> Self {
        let lut_layout = device.create_bind_group_layout(&wgpu::BindGroupLayoutDescriptor {
            label: Some("layout.atmosphere.lut"),
            entries: &[
                uniform_entry(0),
                texture_entry(1, wgpu::TextureSampleType::Float { filterable: true }, wgpu::TextureViewDimension::D2),
                texture_entry(2, wgpu::TextureSampleType::Float { filterable: true }, wgpu::TextureViewDimension::D2),
                sampler_entry(3),
            ],
        });
        let source = format!("{ATMOSPHERE_WGSL}\n{LUTS_WGSL}");
        let module = device.create_shader_module(wgpu::ShaderModuleDescriptor {
            label: Some("shader.atmosphere.lut"),
            source: wgpu::ShaderSource::Wgsl(source.into()),
        });
        let transmittance = fullscreen(
            device,
            "atmosphere.transmittance",
            &module,
            &lut_layout,
            ("vs_main", "fs_transmittance"),
            LUT_FORMAT,
            false,
        );
        let multiscattering = fullscreen(
            device,
            "atmosphere.multiscattering",
            &module,
            &lut_layout,
            ("vs_main", "fs_multiscattering"),
            LUT_FORMAT,
            false,
        );
        let sky_view = fullscreen(
            device,
            "atmosphere.sky_view",
            &module,
            &lut_layout,
            ("vs_main", "fs_skyview"),
            LUT_FORMAT,
            false,
        );
        let aerial =
            fullscreen(device, "atmosphere.aerial", &module, &lut_layout, ("vs_main", "fs_aerial"), LUT_FORMAT, false);
        let sky = fullscreen(device, "atmosphere.sky", terrain, layout, ("vs_sky", "fs_sky"), format, true);
        Self { lut_layout, transmittance, multiscattering, sky_view, aerial, sky }
    }
}
