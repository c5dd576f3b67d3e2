//! Which tiles of each layer the camera wants, at which LOD, in which order.
//!
//! Each layer's quadtree is walked from its coarsest LOD down. A tile is refined while one
//! of its texels (or elevation samples) would cover more than `pixel_error` pixels at the
//! tile's distance from the eye — the screen-space error rule — and only where the tile
//! is in view (or the eye is within one tile width of it, so looking around near the
//! ground stays sharp). Every ancestor of a wanted tile is wanted too: coverage can always
//! fall back to a coarser LOD. The walk is breadth-first, so a cap on the number of wanted
//! tiles drops the finest ones first.

use std::cmp::Ordering;

use terrastream_format::{Layer, LayerKind, Metadata, TileKey};

use super::camera::{Camera, SceneBox};
use crate::globe::Surface;

/// Knobs of the selection.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct SelectOptions {
    /// Largest on-screen size of one texel, in pixels, before the tile is refined.
    pub pixel_error: f64,
    /// Most tiles wanted at once, all layers together (the finest are dropped first).
    pub max_wanted: usize,
    /// Place a georeferenced archive on the globe (cameras in ECEF); else the flat plate.
    pub globe: bool,
}

impl Default for SelectOptions {
    fn default() -> Self {
        Self { pixel_error: 1.5, max_wanted: 4096, globe: false }
    }
}

/// One wanted tile.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Want {
    /// The tile.
    pub key: TileKey,
    /// Its box intersects the view frustum.
    pub in_view: bool,
    /// Distance from the eye to its box.
    pub distance: f64,
    /// A tile of the layer's coarsest LOD: always wanted, fetched before anything else,
    /// never evicted, so that coverage never has a hole.
    pub top: bool,
    /// Not refined further this frame (the finest wanted tile of its area).
    pub leaf: bool,
}

impl Want {
    /// Request and upload order: coarsest-LOD tiles first, then tiles in view, then
    /// coarse before fine, then near before far.
    pub fn urgency(&self, other: &Self) -> Ordering {
        other
            .top
            .cmp(&self.top)
            .then(other.in_view.cmp(&self.in_view))
            .then(other.key.lod().cmp(&self.key.lod()))
            .then(self.distance.total_cmp(&other.distance))
            .then(self.key.cmp(&other.key))
    }
}

/// The heights the terrain is drawn between: the metadata's range where an elevation
/// layer gives heights, else the flat height a texture-only archive is drawn at (the
/// metadata's minimum elevation, else 0) for both.
pub fn drawn_heights(metadata: &Metadata) -> (f64, f64) {
    let (lo, hi) = metadata.terrain.height_range();
    if metadata.layers.iter().any(|l| l.kind == LayerKind::Elevation) {
        (lo, hi)
    } else {
        let flat = if lo.is_finite() { lo } else { 0.0 };
        (flat, flat)
    }
}

/// Scene box of a tile: its grid square between the given heights, on the plate or the
/// globe.
pub fn tile_box(surface: &Surface, layer: &Layer, key: TileKey, heights: (f64, f64)) -> SceneBox {
    let size = layer.world_size_at(key.lod());
    let (x0, z0) = (f64::from(key.x()) * size, f64::from(key.y()) * size);
    surface.bounds([x0, z0, x0 + size, z0 + size], heights)
}

/// The wanted tiles of every layer, most urgent first.
///
/// `descend(key)` says whether the quadtree may go below `key` (false for a tile the
/// archive is known not to have: a sparse pyramid has no children under a missing tile).
pub fn select(
    metadata: &Metadata,
    surface: &Surface,
    camera: &Camera,
    options: &SelectOptions,
    descend: impl Fn(TileKey) -> bool,
) -> Vec<Want> {
    let frustum = camera.frustum();
    let pixels_per_radian = camera.pixels_per_radian();
    let heights = drawn_heights(metadata);
    let mut wants = Vec::new();
    // Breadth-first over the drawn layers at once, level by level from the top.
    let mut level: Vec<TileKey> = Vec::new();
    for (index, layer) in metadata.layers.iter().enumerate() {
        let Ok(index) = u8::try_from(index) else { continue };
        if !matches!(layer.kind, LayerKind::Elevation | LayerKind::Texture) {
            continue;
        }
        // From the coarsest LOD holding tiles, over the data: a regional pyramid has no
        // ancestors up to one tile.
        let start = layer.start_lod();
        let (x0, y0, x1, y1) = layer.data_tiles_at(start);
        level.extend((y0..=y1).flat_map(|y| (x0..=x1).filter_map(move |x| TileKey::new(index, start, x, y).ok())));
    }
    // Tiles already wanted or queued: refinement stops when four more would pass the cap.
    let mut accounted = level.len();
    while !level.is_empty() {
        let mut next = Vec::new();
        for key in level {
            let layer = &metadata.layers[usize::from(key.layer())];
            let bounds = tile_box(surface, layer, key, heights);
            let top = key.lod() == layer.start_lod();
            // Behind the horizon: never wanted (but for the coarsest tiles, which always are).
            let hidden = surface.hidden(camera.position, &bounds);
            if hidden && !top {
                continue;
            }
            let distance = bounds.distance(camera.position);
            let in_view = !hidden && frustum.intersects_box(&bounds);
            let size = layer.world_size_at(key.lod());
            let texel = size / f64::from(layer.tile_resolution);
            let projected = texel * pixels_per_radian / distance.max(1e-9);
            let mut refine = key.lod() > 0
                && projected > options.pixel_error
                && (in_view || (distance < size && !hidden))
                && descend(key)
                && accounted + 4 <= options.max_wanted;
            if refine {
                let lod = key.lod() - 1;
                let (x0, y0, x1, y1) = layer.data_tiles_at(lod);
                let before = next.len();
                for (dx, dy) in [(0, 0), (1, 0), (0, 1), (1, 1)] {
                    let (x, y) = (key.x() * 2 + dx, key.y() * 2 + dy);
                    // A partial level (a collection's finer one) holds nothing outside its
                    // rectangles: the coarser tile stands there.
                    if (x0..=x1).contains(&x)
                        && (y0..=y1).contains(&y)
                        && layer.extent.as_ref().is_none_or(|e| e.may_hold(lod, x, y))
                        && let Ok(child) = TileKey::new(key.layer(), lod, x, y)
                    {
                        accounted += 1;
                        next.push(child);
                    }
                }
                refine = next.len() > before;
            }
            wants.push(Want { key, in_view, distance, top, leaf: !refine });
        }
        level = next;
    }
    wants.sort_by(Want::urgency);
    wants
}

#[cfg(test)]
mod tests {
    use terrastream_format::{LayerKind, PayloadCompression, TileFormat};

    use glam::DVec3;

    use super::*;

    fn metadata() -> Metadata {
        let layer = Layer {
            name: "texture".into(),
            kind: LayerKind::Texture,
            format: TileFormat::Png,
            compression: PayloadCompression::None,
            tile_resolution: 256,
            border: 0,
            num_x_tiles: 64,
            num_y_tiles: 64,
            num_lods: 7,
            tile_world_size: 256.0,
            elevation: None,
            extent: None,
        };
        Metadata::new("t", vec![layer])
    }

    #[test]
    fn near_tiles_are_fine_far_tiles_coarse_and_ancestors_come_first() {
        let m = metadata();
        let cam = Camera::look_at(DVec3::new(1000.0, 200.0, 1000.0), DVec3::new(4000.0, 0.0, 4000.0), 1024, 768);
        let wants = select(&m, &Surface::Flat, &cam, &SelectOptions::default(), |_| true);
        let finest = wants.iter().map(|w| w.key.lod()).min().unwrap();
        assert_eq!(finest, 0, "the ground under the eye is at full detail");
        // Every wanted tile's parent is wanted and more urgent.
        let position = |k: TileKey| wants.iter().position(|w| w.key == k);
        for (i, w) in wants.iter().enumerate() {
            if let Some(parent) = w.key.parent().filter(|p| p.lod() < m.layers[0].num_lods) {
                let p = position(parent).unwrap_or_else(|| panic!("{} wanted without its parent", w.key));
                assert!(p < i, "{} before its parent", w.key);
            }
        }
        // Tiles behind the camera are not refined.
        assert!(
            wants.iter().filter(|w| !w.in_view).all(|w| w.leaf || w.distance < m.layers[0].world_size_at(w.key.lod()))
        );
    }

    #[test]
    fn the_cap_drops_the_finest_tiles() {
        let m = metadata();
        let cam = Camera::look_at(DVec3::new(1000.0, 50.0, 1000.0), DVec3::new(9000.0, 0.0, 9000.0), 1920, 1080);
        let all = select(&m, &Surface::Flat, &cam, &SelectOptions::default(), |_| true);
        let capped =
            select(&m, &Surface::Flat, &cam, &SelectOptions { max_wanted: 40, ..SelectOptions::default() }, |_| true);
        assert!(all.len() > 40 && capped.len() <= 40, "{} / {}", all.len(), capped.len());
        let top = m.layers[0].num_lods - 1;
        assert_eq!(capped.iter().filter(|w| w.key.lod() == top).count(), 1);
        assert!(capped.iter().map(|w| w.key.lod()).min() > all.iter().map(|w| w.key.lod()).min());
    }

    #[test]
    fn a_regional_pyramid_is_selected_from_its_coarsest_level_inside_its_box() {
        let mut m = metadata();
        // Tiles at LODs 0..=3 only, over LOD-0 tiles 16..24 (the grid is 64 x 64).
        m.layers[0].extent = Some(terrastream_format::LayerExtent {
            coarsest_lod: 3,
            finest_lod: 0,
            world: [4096.0, 4096.0, 6144.0, 6144.0],
            detail: [4096.0, 4096.0, 6144.0, 6144.0],
            crs: None,
            lon_lat: None,
            partial: Vec::new(),
        });
        let cam = Camera::look_at(DVec3::new(5000.0, 600.0, 6500.0), DVec3::new(5100.0, 0.0, 5100.0), 1024, 768);
        let wants = select(&m, &Surface::Flat, &cam, &SelectOptions::default(), |_| true);
        let tops: Vec<TileKey> = wants.iter().filter(|w| w.top).map(|w| w.key).collect();
        assert_eq!(tops, [TileKey::new(0, 3, 2, 2).unwrap()], "the one LOD-3 tile over the box");
        assert!(wants.iter().all(|w| w.key.lod() <= 3), "nothing above the coarsest populated LOD");
        let inside = |k: TileKey| {
            let s = 256u32 << k.lod();
            (4096..6144).contains(&(k.x() * s)) && (4096..6144).contains(&(k.y() * s))
        };
        assert!(wants.iter().all(|w| inside(w.key)), "nothing outside the data's box");
        assert_eq!(wants.iter().map(|w| w.key.lod()).min(), Some(0), "refined down to the finest LOD");
    }

    #[test]
    fn no_descent_below_a_missing_tile() {
        let m = metadata();
        let cam = Camera::look_at(DVec3::new(1000.0, 200.0, 1000.0), DVec3::new(4000.0, 0.0, 4000.0), 1024, 768);
        let wants = select(&m, &Surface::Flat, &cam, &SelectOptions::default(), |k| k.lod() > 3);
        assert_eq!(wants.iter().map(|w| w.key.lod()).min(), Some(3));
    }

    #[test]
    fn on_the_globe_nothing_behind_the_horizon_is_wanted() {
        // A geographic world: 64 x 32 tiles of 5.6 degrees at LOD 0, 7 LODs.
        let mut m = metadata();
        let degree = 6_378_137.0 * std::f64::consts::PI / 180.0;
        m.layers[0].num_x_tiles = 64;
        m.layers[0].num_y_tiles = 32;
        m.layers[0].tile_world_size = 5.625 * degree;
        m.georeference = Some(terrastream_format::Georeference {
            crs: Some("EPSG:4326".into()),
            origin: Some([-180.0, 90.0]),
            lat_lon_bounds: Some([-180.0, -90.0, 180.0, 90.0]),
            definition: Some("+proj=longlat +datum=WGS84 +no_defs".into()),
            scale: Some([1.0 / degree; 2]),
        });
        let surface = Surface::new(&m, true);
        assert!(surface.globe().is_some());
        // 10 km above (0, 0), looking east along the horizon: it is 357 km away.
        let eye = crate::globe::ecef(0.0, 0.0, 10_000.0);
        let east = crate::globe::enu(0.0, 0.0).x_axis;
        let mut camera = Camera::look_at(eye, eye + east * 1000.0, 1024, 768);
        camera.zenith = surface.up(eye);
        camera.far = 4.0e7;
        let wants = select(&m, &surface, &camera, &SelectOptions::default(), |_| true);
        assert!(wants.iter().any(|w| w.in_view && w.key.lod() == 0), "the ground ahead is refined");
        let top = m.layers[0].start_lod();
        for w in wants.iter().filter(|w| w.key.lod() < top) {
            let size = m.layers[0].world_size_at(w.key.lod());
            assert!(
                w.distance < 357_000.0 + size,
                "{} wanted {:.0} km away, beyond the horizon",
                w.key,
                w.distance / 1000.0
            );
        }
    }
}
