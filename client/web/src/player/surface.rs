//! The canvas's surface and its depth buffer.

use super::*;

pub(super) struct Surface {
    pub(super) surface: wgpu::Surface<'static>,
    pub(super) config: wgpu::SurfaceConfiguration,
    /// The sRGB view of the surface's format (the renderer writes linear light).
    pub(super) view_format: wgpu::TextureFormat,
    pub(super) depth: wgpu::TextureView,
}

impl Surface {
    pub(super) fn configure(&mut self, device: &wgpu::Device, (width, height): (u32, u32)) {
        self.config.width = width;
        self.config.height = height;
        self.surface.configure(device, &self.config);
        self.depth = depth_view(device, (width, height));
    }
}

pub(super) fn depth_view(device: &wgpu::Device, (width, height): (u32, u32)) -> wgpu::TextureView {
    depth_target(device, "texture.canvas.depth", width, height).create_view(&wgpu::TextureViewDescriptor::default())
}
