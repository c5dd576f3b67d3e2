//! The streaming core and the renderer, stepped together once per frame.

use terrastream_format::{LayerKind, Metadata};

use super::renderer::{FrameStats, RenderSettings, TerrainPipeline, TerrainRenderer};
use crate::stream::camera::Camera;
use crate::stream::select::drawn_heights;
use crate::stream::streamer::{StreamStats, Streamer, UploadBudget};

/// A streamer feeding a renderer.
#[derive(Debug)]
pub struct Session {
    /// The streaming core.
    pub streamer: Streamer,
    /// The renderer.
    pub renderer: TerrainRenderer,
    /// Upload budget per frame.
    pub budget: UploadBudget,
    generation: u64,
    metadata: Metadata,
    pipeline: TerrainPipeline,
    /// The last frame drew no terrain although tiles in view were resident (warned once
    /// per such spell, not once per frame).
    blank: bool,
    /// The layer the last frame could not reach (warned once per such spell).
    unreached: Option<u8>,
}

impl Session {
    /// Joins an opened `streamer` (its metadata known) with a new renderer. The streaming
    /// selection is capped to what the GPU arrays hold.
    ///
    /// # Errors
    /// When the streamer has no metadata yet.
    pub fn new(
        streamer: Streamer,
        device: &wgpu::Device,
        settings: RenderSettings,
        format: wgpu::TextureFormat,
        budget: UploadBudget,
    ) -> crate::Result<Self> {
        Self::with_pipeline(streamer, device, settings, &TerrainPipeline::new(device, format), budget)
    }

    /// [`Session::new`] drawing with a pipeline made before (e.g. while the archive
    /// opened, so that its shaders are compiled by the first frame with terrain).
    ///
    /// # Errors
    /// When the streamer has no metadata yet.
    pub fn with_pipeline(
        mut streamer: Streamer,
        device: &wgpu::Device,
        settings: RenderSettings,
        pipeline: &TerrainPipeline,
        budget: UploadBudget,
    ) -> crate::Result<Self> {
        let why = streamer.last_error().map(str::to_owned);
        let metadata = streamer.metadata().cloned().ok_or(crate::Error::NotOpen { why })?;
        let renderer = TerrainRenderer::with_pipeline(device, &metadata, settings, pipeline);
        let mut options = streamer.options().clone();
        options.select.max_wanted = options.select.max_wanted.min(renderer.max_resident_tiles());
        options.select.globe = !settings.flat;
        streamer.set_options(options);
        streamer.set_surface(renderer.surface().clone());
        let generation = streamer.generation();
        Ok(Self {
            streamer,
            renderer,
            budget,
            generation,
            metadata,
            pipeline: pipeline.clone(),
            blank: false,
            unreached: None,
        })
    }

    /// One frame: stream for `camera`, upload within the budget, prepare the draw. The
    /// camera's clip planes are fitted to the terrain first ([`Camera::enclosing`]), the
    /// same for every front end.
    pub fn frame(&mut self, device: &wgpu::Device, queue: &wgpu::Queue, camera: &Camera) -> (StreamStats, FrameStats) {
        let camera = &camera.enclosing(&self.renderer.scene_box());
        self.streamer.update(camera);
        if self.streamer.generation() != self.generation {
            self.generation = self.streamer.generation();
            match self.streamer.metadata() {
                Some(m) if *m != self.metadata => {
                    self.metadata = m.clone();
                    let settings = *self.renderer.settings();
                    self.renderer = TerrainRenderer::with_pipeline(device, &self.metadata, settings, &self.pipeline);
                    self.streamer.set_surface(self.renderer.surface().clone());
                }
                _ => self.renderer.clear(),
            }
        }
        let uploads = self.streamer.drain_uploads(self.budget);
        for key in self.renderer.upload(queue, &uploads) {
            self.streamer.release(key);
        }
        let mut stats = self.renderer.prepare(device, queue, camera, self.streamer.wanted().iter().map(|w| w.key));
        let in_view = self.streamer.wanted().iter().filter(|w| w.in_view && self.renderer.is_resident(w.key));
        stats.in_view_resident = u32::try_from(in_view.count()).unwrap_or(u32::MAX);
        let blank = stats.drew_nothing_in_view();
        if blank && !self.blank {
            tracing::warn!(
                resident_in_view = stats.in_view_resident,
                eye = ?camera.position,
                "tiles in view are resident but the frame draws no terrain"
            );
        }
        self.blank = blank;
        stats.unreached_layer = self.unreached_layer(camera);
        if let Some(index) = stats.unreached_layer
            && self.unreached != stats.unreached_layer
        {
            tracing::warn!(
                layer = self.metadata.layers[usize::from(index)].name,
                eye = ?camera.position,
                "the layer's data is in view but none of its tiles in view could be fetched"
            );
        }
        self.unreached = stats.unreached_layer;
        (self.streamer.stats(), stats)
    }

    /// The first drawn layer whose data box is in view while, with nothing left to fetch,
    /// none of its tiles in view is on the GPU. In view as the selection sees it: inside
    /// the frustum and, on the globe, not wholly behind the Earth (the far side, past the
    /// limb).
    fn unreached_layer(&self, camera: &Camera) -> Option<u8> {
        if !self.settled() {
            return None;
        }
        let frustum = camera.frustum();
        let (lo, hi) = drawn_heights(&self.metadata);
        let wanted = self.streamer.wanted();
        self.metadata.layers.iter().enumerate().find_map(|(index, layer)| {
            let index = u8::try_from(index).ok()?;
            let extent =
                layer.extent.as_ref().filter(|_| matches!(layer.kind, LayerKind::Elevation | LayerKind::Texture))?;
            let data = self.renderer.surface().bounds(extent.world, (lo, hi));
            let reached =
                wanted.iter().any(|w| w.key.layer() == index && w.in_view && self.renderer.is_resident(w.key));
            let surface = self.renderer.surface();
            let in_view = frustum.intersects_box(&data) && !surface.hidden(camera.position, &data);
            (in_view && !reached).then_some(index)
        })
    }

    /// The name of the layer [`FrameStats::unreached_layer`] names.
    pub fn layer_name(&self, index: u8) -> &str {
        self.metadata.layers.get(usize::from(index)).map_or("?", |l| l.name.as_str())
    }

    /// Steps frames for a fixed `camera` until `done(self)` holds, flushing the GPU's
    /// queue each frame: the last frame's counters and the frames stepped, or `None` when
    /// `timeout` passes first. Waits 1 ms between frames: for stills and benchmarks, not for
    /// interactive loops.
    #[cfg(not(target_arch = "wasm32"))]
    pub fn run_until(
        &mut self,
        device: &wgpu::Device,
        queue: &wgpu::Queue,
        camera: &Camera,
        timeout: std::time::Duration,
        done: impl Fn(&Self) -> bool,
    ) -> Option<(StreamStats, FrameStats, u32)> {
        let start = web_time::Instant::now();
        let mut frames = 0;
        loop {
            let (stream, frame) = self.frame(device, queue, camera);
            queue.submit([]);
            frames += 1;
            if done(self) {
                return Some((stream, frame, frames));
            }
            if start.elapsed() > timeout {
                return None;
            }
            std::thread::sleep(std::time::Duration::from_millis(1));
        }
    }

    /// The terrain's height under a scene point, from the elevation tiles in the cache
    /// (`None` where none is loaded): the ground a flyer stays above.
    pub fn ground(&self, p: glam::DVec3) -> Option<f64> {
        let surface = self.renderer.surface();
        let w = surface.world_at(p)?;
        // On the globe, above the ellipsoid as the eye's height is.
        Some(self.streamer.height_at(w.x, w.y)? + surface.lift(p))
    }

    /// Is everything the view wants on the GPU (and nothing in flight), the whole-Earth
    /// picture included?
    pub fn settled(&self) -> bool {
        self.streamer.metadata().is_some()
            && self.streamer.pending() == 0
            && self.streamer.stats().in_flight == 0
            && !self.renderer.earth_pending()
    }
}
