//! Height queries on what a [`Streamer`] has loaded: bilinear heights and normals from the
//! finest elevation in the cache, and exact LOD-0 heights fetched on demand.

use terrastream_format::{LayerKind, Metadata, TileKey};

use terrastream_tiles::{Interpolation, height_on_lod, tile_of};
#[cfg(not(target_arch = "wasm32"))]
use web_time::Instant;

#[cfg(not(target_arch = "wasm32"))]
use super::origin::Backend;
use super::streamer::Streamer;
#[cfg(not(target_arch = "wasm32"))]
use super::streamer::{Completion, Group, fetch_and_decode};
#[cfg(not(target_arch = "wasm32"))]
use crate::error::{Error, Result};

impl Streamer {
    /// [`Self::height_at`] at a longitude and latitude (degrees, WGS 84), for archives
    /// that record where they lie (see [`crate::Geo`]).
    pub fn height_at_lon_lat(&self, lon: f64, lat: f64) -> Option<f64> {
        let (x, z) = crate::Geo::new(self.metadata()?)?.lon_lat_to_world(lon, lat)?;
        self.height_at(x, z)
    }

    /// Height in world units at ground position `(x, z)`, bilinear over the finest
    /// elevation LOD in the cache (sample `i` of a LOD at `(i + 0.5)` spacings, as the
    /// renderer samples); `None` where nothing is loaded or the data has no value.
    pub fn height_at(&self, x: f64, z: f64) -> Option<f64> {
        let (layer, lod) = self.best_elevation(x, z)?;
        self.sample_height(layer, lod, x, z)
    }

    /// Unit surface normal at `(x, z)` from the same data as [`Self::height_at`].
    pub fn normal_at(&self, x: f64, z: f64) -> Option<[f64; 3]> {
        let (layer, lod) = self.best_elevation(x, z)?;
        let info = &self.metadata()?.layers[usize::from(layer)];
        let h = info.sample_spacing(lod);
        let at = |dx: f64, dz: f64| self.sample_height(layer, lod, x + dx, z + dz);
        let (l, r, u, d) = (at(-h, 0.0)?, at(h, 0.0)?, at(0.0, -h)?, at(0.0, h)?);
        let n = glam::DVec3::new(-(r - l) / (2.0 * h), 1.0, -(d - u) / (2.0 * h)).normalize();
        Some(n.to_array())
    }

    /// Like [`Self::height_at`] but from LOD 0, fetching the tiles around `(x, z)` now if
    /// they are not loaded (blocks; not for a frame loop).
    ///
    /// # Errors
    /// The origin's error, [`Error::NotOpen`], [`Error::NoLayer`] when there is no elevation
    /// layer, [`Error::Outside`] when the point is outside it, [`Error::TileLoad`].
    #[cfg(not(target_arch = "wasm32"))]
    pub fn height_at_exact(&mut self, x: f64, z: f64) -> Result<Option<f64>> {
        let backend = self.backend().cloned().ok_or_else(|| Error::NotOpen { why: self.last_error.clone() })?;
        let metadata = backend.metadata();
        let layer = elevation_layer(metadata).ok_or(Error::NoLayer { kind: "elevation" })?;
        let info = &metadata.layers[usize::from(layer)];
        let spacing = info.sample_spacing(0);
        // The (up to) four tiles holding the bilinear footprint.
        let mut keys = Vec::new();
        for (dx, dz) in [(-1.0, -1.0), (1.0, -1.0), (-1.0, 1.0), (1.0, 1.0)] {
            if let Some(key) = tile_at(metadata, layer, 0, x + dx * spacing, z + dz * spacing)
                && !keys.contains(&key)
                && !self.cache.contains(key)
            {
                keys.push(key);
            }
        }
        if tile_at(metadata, layer, 0, x, z).is_none() {
            return Err(Error::Outside { layer: info.name.clone(), x, z });
        }
        for key in keys {
            let location = match &backend {
                Backend::Archive(reader) => match self.runtime.block_on(reader.locate(key))? {
                    Some(location) => Some((0, location)),
                    None => continue,
                },
                Backend::Manifest(parts) => {
                    let Some(route) = parts.manifest.route(key) else { continue };
                    let reader = self.runtime.block_on(parts.open(route.part))?;
                    match self.runtime.block_on(reader.locate(route.key))? {
                        Some(location) => Some((route.part, location)),
                        None => continue,
                    }
                }
                Backend::Endpoint(..) | Backend::Host(_) => None,
            };
            let group = Group { rank: 0, tiles: vec![(key, location)] };
            // Fetched and taken in as the frame loop's requests are.
            match self.runtime.block_on(fetch_and_decode(backend.clone(), group, 0, self.generation, None, false)) {
                Completion::Tiles { results, .. } => {
                    if let Some((key, reason)) = self.absorb(results, Instant::now()) {
                        return Err(Error::TileLoad { key, reason });
                    }
                }
                Completion::Changed { what, .. } => return Err(Error::Changed { what }),
                Completion::Opened { .. } | Completion::Leaf { .. } | Completion::Rechecked => {}
            }
        }
        Ok(self.sample_height(layer, 0, x, z))
    }

    fn best_elevation(&self, x: f64, z: f64) -> Option<(u8, u8)> {
        let metadata = self.metadata()?;
        let layer = elevation_layer(metadata)?;
        let num_lods = metadata.layers[usize::from(layer)].num_lods;
        (0..num_lods).find_map(|lod| {
            let key = tile_at(metadata, layer, lod, x, z)?;
            self.cache.contains(key).then_some((layer, lod))
        })
    }

    fn sample_height(&self, layer: u8, lod: u8, x: f64, z: f64) -> Option<f64> {
        let info = self.metadata()?.layers.get(usize::from(layer))?;
        height_on_lod(info, layer, lod, x, z, Interpolation::Bilinear, |key| {
            self.cache.peek(key).map(std::sync::Arc::as_ref)
        })
    }
}

fn elevation_layer(metadata: &Metadata) -> Option<u8> {
    let i = metadata.layers.iter().position(|l| l.kind == LayerKind::Elevation)?;
    u8::try_from(i).ok()
}

/// The tile of `layer` at `lod` holding ground point `(x, z)`.
fn tile_at(metadata: &Metadata, layer: u8, lod: u8, x: f64, z: f64) -> Option<TileKey> {
    tile_of(metadata.layers.get(usize::from(layer))?, layer, lod, x, z)
}
