//! CDLOD node selection (Strugar 2010, "Continuous Distance-Dependent Level of Detail").
//!
//! The terrain is covered by square patches of `patch` x `patch` quads. A patch at mesh
//! level `L` has quads `base * 2^L` wide; level `L` is drawn out to `range(L) =
//! high_detail_range * 2^L` from the eye (the original engine's `baseTileSize`,
//! `highDetailRange`, `numDetailLevels`). In the last third of its range a patch's odd
//! vertices slide onto the next level's grid (the morph), so where a coarser patch
//! begins the finer one already has the coarser one's vertices: no cracks, no popping.
//!
//! Distances are measured to the vertical column over `(x, z)` spanning the terrain's
//! height range — the same function the vertex shader evaluates — which makes the proof
//! exact: a coarser neighbour was not refined because its whole box lies beyond
//! `range(L)`, so every shared vertex is at least that far and has morph 1.

use glam::DVec3;

use crate::globe::Surface;
use crate::stream::camera::Frustum;

/// Mesh parameters.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct MeshParams {
    /// Finest quad size in world units (= the elevation sample spacing).
    pub base: f64,
    /// Quads per patch edge (a power of two, at least 2).
    pub patch: u32,
    /// Radius of the finest ring in world units.
    pub high_detail_range: f64,
    /// Mesh levels.
    pub levels: u32,
}

/// Morph starts at this fraction of the way from the previous range to a level's range.
pub const MORPH_START: f64 = 2.0 / 3.0;
/// Most mesh levels (the shaders' uniform arrays).
pub const MAX_LEVELS: u32 = 32;

impl MeshParams {
    /// Parameters for a terrain, with the finest ring widened to at least three patches
    /// (narrower rings let neighbours differ by more than one level, and crack).
    pub fn new(base: f64, patch: u32, high_detail_range: f64, levels: u32) -> Self {
        let patch = patch.clamp(2, 256).next_power_of_two();
        let base = if base.is_finite() && base > 0.0 { base } else { 1.0 };
        let high_detail_range = high_detail_range.max(3.0 * f64::from(patch) * base);
        Self { base, patch, high_detail_range, levels: levels.clamp(1, MAX_LEVELS) }
    }

    /// The levels needed so that the coarsest range reaches `distance`.
    pub fn levels_to_cover(&self, distance: f64) -> u32 {
        let mut levels = 1;
        while levels < MAX_LEVELS && self.range(levels - 1) < distance {
            levels += 1;
        }
        levels
    }

    /// Patch edge at `level` in base units.
    pub fn node_units(&self, level: u32) -> i64 {
        i64::from(self.patch) << level
    }

    /// How far `level` is drawn.
    pub fn range(&self, level: u32) -> f64 {
        self.high_detail_range * f64::from(level).exp2()
    }

    /// Distances where `level`'s morph starts and ends.
    pub fn morph(&self, level: u32) -> (f64, f64) {
        let end = self.range(level);
        let previous = if level == 0 { 0.0 } else { self.range(level - 1) };
        (previous + (end - previous) * MORPH_START, end)
    }
}

/// One patch to draw.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct Node {
    /// Corner with the smallest x and z, in base units from the world origin.
    pub origin: (i64, i64),
    /// Mesh level.
    pub level: u32,
    /// A quarter patch (`patch / 2` quads per edge): the part of a level-`level` node
    /// whose child was out of range.
    pub quarter: bool,
}

impl Node {
    /// Edge in base units.
    pub fn units(&self, params: &MeshParams) -> i64 {
        params.node_units(self.level) >> u32::from(self.quarter)
    }
}

/// What the selection needs to know of the scene.
pub struct Scene<'a> {
    /// Where the terrain starts, in base units (x, z).
    pub start: (i64, i64),
    /// Where the terrain ends, in base units (x, z).
    pub extent: (i64, i64),
    /// Eye position in world units.
    pub eye: DVec3,
    /// View frustum, for culling.
    pub frustum: &'a Frustum,
    /// The terrain's height range (the columns LOD distances are measured to).
    pub column: (f64, f64),
    /// Height range of the data under a box `[x0, x1] x [z0, z1]` (world units), for culling.
    pub heights: &'a dyn Fn(f64, f64, f64, f64) -> (f64, f64),
    /// The plate or the globe: boxes and the eye are in its scene coordinates.
    pub surface: &'a Surface,
}

/// The patches covering the terrain for `scene`.
pub fn select_nodes(params: &MeshParams, scene: &Scene<'_>) -> Vec<Node> {
    let mut out = Vec::new();
    let top = params.levels - 1;
    let root = params.node_units(top);
    // Root nodes on the root grid from the one holding the start to the one holding the end.
    let (i0, j0) = (scene.start.0.div_euclid(root), scene.start.1.div_euclid(root));
    let nx = scene.extent.0.div_euclid(root) + i64::from(scene.extent.0.rem_euclid(root) != 0);
    let nz = scene.extent.1.div_euclid(root) + i64::from(scene.extent.1.rem_euclid(root) != 0);
    for j in j0..nz {
        for i in i0..nx {
            select(params, scene, (i * root, j * root), top, &mut out);
        }
    }
    out
}

/// The node's square in world units.
fn node_rect(params: &MeshParams, origin: (i64, i64), units: i64) -> [f64; 4] {
    let b = params.base;
    #[allow(clippy::cast_precision_loss)]
    [origin.0 as f64 * b, origin.1 as f64 * b, (origin.0 + units) as f64 * b, (origin.1 + units) as f64 * b]
}

/// Strugar's recursion: false when the node is beyond its level's range (the parent
/// then draws that area itself).
fn select(params: &MeshParams, scene: &Scene<'_>, origin: (i64, i64), level: u32, out: &mut Vec<Node>) -> bool {
    let units = params.node_units(level);
    let rect = node_rect(params, origin, units);
    let column = scene.surface.bounds(rect, scene.column);
    let distance = column.distance(scene.eye);
    if distance > params.range(level) {
        return false;
    }
    let [x0, z0, x1, z1] = rect;
    let visible = scene.surface.bounds(rect, (scene.heights)(x0, z0, x1, z1));
    if !scene.frustum.intersects_box(&visible) || scene.surface.hidden(scene.eye, &visible) {
        return true;
    }
    if level == 0 || distance > params.range(level - 1) {
        out.push(Node { origin, level, quarter: false });
        return true;
    }
    let half = units / 2;
    for (dx, dz) in [(0, 0), (1, 0), (0, 1), (1, 1)] {
        let child = (origin.0 + dx * half, origin.1 + dz * half);
        if child.0 >= scene.extent.0
            || child.1 >= scene.extent.1
            || child.0 + half <= scene.start.0
            || child.1 + half <= scene.start.1
        {
            continue;
        }
        if !select(params, scene, child, level - 1, out) {
            out.push(Node { origin: child, level, quarter: true });
        }
    }
    true
}

/// Vertices (patch grid coordinates) and triangle indices of one patch; the first
/// `quarter_indices` indices draw its `patch / 2` quarter.
pub struct PatchMesh {
    /// `(patch + 1)^2` grid points.
    pub vertices: Vec<[f32; 2]>,
    /// Full patch triangles, then the quarter's.
    pub indices: Vec<u32>,
    /// Indices of the full patch.
    pub full_indices: u32,
}

impl PatchMesh {
    /// The patch of `params`.
    pub fn new(patch: u32) -> Self {
        let n = patch + 1;
        let mut vertices = Vec::with_capacity((n * n) as usize);
        for j in 0..n {
            for i in 0..n {
                #[allow(clippy::cast_precision_loss)]
                vertices.push([i as f32, j as f32]);
            }
        }
        let quads = |size: u32, indices: &mut Vec<u32>| {
            for j in 0..size {
                for i in 0..size {
                    let (a, b, c, d) = (j * n + i, j * n + i + 1, (j + 1) * n + i, (j + 1) * n + i + 1);
                    // Diagonal a-d, as the wireframe overlay draws it.
                    indices.extend_from_slice(&[a, d, b, a, c, d]);
                }
            }
        };
        let mut indices = Vec::new();
        quads(patch, &mut indices);
        let full_indices = u32::try_from(indices.len()).unwrap_or(u32::MAX);
        quads(patch / 2, &mut indices);
        Self { vertices, indices, full_indices }
    }
}

#[cfg(test)]
mod tests {
    #![allow(clippy::unwrap_used, clippy::cast_precision_loss)]
    use std::collections::HashMap;

    use super::*;
    use crate::stream::camera::Camera;

    fn nodes(eye: DVec3, target: DVec3) -> (MeshParams, Vec<Node>, (i64, i64)) {
        let params = MeshParams::new(30.0, 16, 100.0, 1);
        let params = MeshParams { levels: params.levels_to_cover(400_000.0), ..params };
        let extent = (4096, 2048);
        let cam = Camera::look_at(eye, target, 800, 600);
        let frustum = cam.frustum();
        let scene = Scene {
            start: (0, 0),
            extent,
            eye,
            frustum: &frustum,
            column: (0.0, 500.0),
            heights: &|_, _, _, _| (0.0, 500.0),
            surface: &Surface::Flat,
        };
        (params, select_nodes(&params, &scene), extent)
    }

    /// Per base-unit cell: the level drawn there (for cells in view).
    fn raster(params: &MeshParams, nodes: &[Node]) -> HashMap<(i64, i64), u32> {
        let mut cells = HashMap::new();
        for n in nodes {
            let u = n.units(params);
            let step = 8;
            for z in (n.origin.1..n.origin.1 + u).step_by(step) {
                for x in (n.origin.0..n.origin.0 + u).step_by(step) {
                    assert!(cells.insert((x / 8, z / 8), n.level).is_none(), "two patches over ({x}, {z})");
                }
            }
        }
        cells
    }

    #[test]
    fn patches_never_overlap_and_neighbours_differ_by_at_most_one_level() {
        let (params, nodes, _) = nodes(DVec3::new(60_000.0, 800.0, 30_000.0), DVec3::new(90_000.0, 0.0, 40_000.0));
        assert!(nodes.iter().any(|n| n.level == 0) && nodes.iter().any(|n| n.level >= 4), "several rings");
        assert!(nodes.iter().any(|n| n.quarter));
        let cells = raster(&params, &nodes);
        for (&(x, z), &level) in &cells {
            for (dx, dz) in [(1, 0), (0, 1)] {
                if let Some(&other) = cells.get(&(x + dx, z + dz)) {
                    assert!(level.abs_diff(other) <= 1, "levels {level} and {other} meet at cell ({x}, {z})");
                }
            }
        }
    }

    #[test]
    fn vertices_on_an_edge_with_a_coarser_patch_are_fully_morphed() {
        let eye = DVec3::new(60_000.0, 800.0, 30_000.0);
        let (params, nodes, _) = nodes(eye, DVec3::new(90_000.0, 0.0, 40_000.0));
        let cells = raster(&params, &nodes);
        let column = |x: f64, z: f64| {
            let y = eye.y.clamp(0.0, 500.0);
            DVec3::new(x, y, z).distance(eye)
        };
        let mut checked = 0;
        for n in &nodes {
            let u = n.units(&params);
            // Walk the node's four edges; where the cell across belongs to a coarser level,
            // the morph factor of every vertex on the edge must be 1.
            for t in 0..=u {
                for (x, z, across) in [
                    (n.origin.0 + t, n.origin.1, (n.origin.0 + t, n.origin.1 - 1)),
                    (n.origin.0 + t, n.origin.1 + u, (n.origin.0 + t, n.origin.1 + u)),
                    (n.origin.0, n.origin.1 + t, (n.origin.0 - 1, n.origin.1 + t)),
                    (n.origin.0 + u, n.origin.1 + t, (n.origin.0 + u, n.origin.1 + t)),
                ] {
                    let Some(&other) = cells.get(&(across.0.div_euclid(8), across.1.div_euclid(8))) else { continue };
                    if other <= n.level || t % (1 << n.level) != 0 || t == u {
                        continue;
                    }
                    let (start, end) = params.morph(n.level);
                    let d = column(x as f64 * params.base, z as f64 * params.base);
                    let morph = ((d - start) / (end - start)).clamp(0.0, 1.0);
                    assert!(morph >= 1.0, "level {} vertex ({x}, {z}) beside level {other}: morph {morph}", n.level);
                    checked += 1;
                }
            }
        }
        assert!(checked > 100, "{checked} edge vertices checked");
    }

    #[test]
    fn ranges_double_and_cover_what_is_asked() {
        let p = MeshParams::new(2.0, 32, 50.0, 4);
        assert!(p.high_detail_range >= 3.0 * 32.0 * 2.0);
        assert!((p.range(3) / p.range(2) - 2.0).abs() < 1e-12);
        let levels = p.levels_to_cover(1.0e6);
        assert!(p.range(levels - 1) >= 1.0e6 && p.range(levels - 2) < 1.0e6);
        let mesh = PatchMesh::new(4);
        assert_eq!(mesh.vertices.len(), 25);
        assert_eq!(mesh.full_indices, 4 * 4 * 6);
        assert_eq!(mesh.indices.len(), 4 * 4 * 6 + 2 * 2 * 6);
    }
}
