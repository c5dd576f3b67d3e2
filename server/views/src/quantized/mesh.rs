//! Irregular meshes of height grids with a bound on their vertical error.
//!
//! Greedy insertion into a Delaunay triangulation (Garland and Heckbert, "Fast polygonal
//! approximation of terrains and height fields", 1995; the method of Delatin): start from
//! the grid's corners, and while some grid point lies further than the bound from the
//! mesh above or below it, insert the worst point of the worst triangle and restore the
//! Delaunay condition by edge flips. Every triangle's error is found by visiting every
//! grid point inside it (edges included), so the bound holds exactly, not at sampled
//! points.
//!
//! The border is simplified first, on its own: each of the four edges keeps the points a
//! one-dimensional split (Douglas and Peucker's, in height) needs to stay within the
//! bound, and the interior never adds a point on the border. A point's neighbours across
//! an edge see the same heights along it, so two tiles sharing an edge keep the same
//! vertices on it: no T-junction, no crack, before any skirt.

use std::collections::BinaryHeap;

/// A mesh of a square grid of heights.
#[derive(Clone, Debug, Default, PartialEq)]
pub struct Mesh {
    /// Vertices as grid points: column (from the west) and row (from the north).
    pub vertices: Vec<[u32; 2]>,
    /// Triangles: three vertex indices each, counter-clockwise as seen from above (with
    /// north up).
    pub triangles: Vec<[u32; 3]>,
}

/// Meshes a `size` x `size` grid of heights (row by row from the north) so that no grid
/// point lies further than `max_error` from the mesh. Heights must be finite (see
/// [`fill_nodata`]); a grid smaller than 2 x 2 or of the wrong length gives an empty mesh.
pub fn mesh(heights: &[f32], size: usize, max_error: f32) -> Mesh {
    let Ok(n) = i32::try_from(size) else { return Mesh::default() };
    if size < 2 || heights.len() != size * size || n > 1 << 15 {
        return Mesh::default();
    }
    let mut t = Triangulation::new(heights, n, max_error.max(0.0));
    for p in border_points(heights, size, max_error) {
        t.insert_on_border(p);
    }
    t.flush();
    while let Some(tri) = t.worst() {
        t.insert(tri);
        t.flush();
    }
    t.finish()
}

/// Replaces the heights that are not finite: on the grid's border by 0 (the ellipsoid, as
/// beyond the data: what a neighbour sees on the same edge), inside by the mean of their
/// finite neighbours, grown inwards from the holes' rims.
pub fn fill_nodata(heights: &mut [f32], size: usize) {
    if size == 0 || heights.len() != size * size {
        return;
    }
    for i in 0..size {
        for at in [i, (size - 1) * size + i, i * size, i * size + size - 1] {
            if !heights[at].is_finite() {
                heights[at] = 0.0;
            }
        }
    }
    let mut holes: Vec<usize> = (0..heights.len()).filter(|&i| !heights[i].is_finite()).collect();
    while !holes.is_empty() {
        let mut filled = vec![];
        for &at in &holes {
            let (x, y) = (at % size, at / size);
            let neighbours = [(x > 0).then(|| at - 1), (x + 1 < size).then(|| at + 1), (y > 0).then(|| at - size)];
            let below = (y + 1 < size).then(|| at + size);
            let (sum, count) = neighbours
                .into_iter()
                .chain([below])
                .flatten()
                .map(|i| heights[i])
                .filter(|h| h.is_finite())
                .fold((0.0f64, 0u32), |(s, c), h| (s + f64::from(h), c + 1));
            if count > 0 {
                #[expect(clippy::cast_possible_truncation, reason = "a mean of f32 heights")]
                filled.push((at, (sum / f64::from(count)) as f32));
            }
        }
        if filled.is_empty() {
            // Unreachable: the border is finite and every hole touches a filled point.
            for &at in &holes {
                heights[at] = 0.0;
            }
            return;
        }
        for &(at, h) in &filled {
            heights[at] = h;
        }
        holes.retain(|&at| !heights[at].is_finite());
    }
}

/// The border points (other than the corners) that the four edges keep.
fn border_points(heights: &[f32], size: usize, max_error: f32) -> Vec<[i32; 2]> {
    let last = size - 1;
    let mut out = vec![];
    let edges: [(usize, usize, bool); 4] =
        [(0, 1, true), (last * size, 1, true), (0, size, false), (last, size, false)];
    for (start, step, horizontal) in edges {
        let line: Vec<f64> = (0..size).map(|i| f64::from(heights[start + i * step])).collect();
        let mut kept = vec![];
        split(&line, 0, last, f64::from(max_error), &mut kept);
        for k in kept {
            let fixed = if horizontal { start / size } else { start % size };
            #[expect(clippy::cast_possible_truncation, clippy::cast_possible_wrap, reason = "size <= 2^15")]
            let point = if horizontal { [k as i32, fixed as i32] } else { [fixed as i32, k as i32] };
            out.push(point);
        }
    }
    out
}

/// Douglas-Peucker in height along a line of samples: the points between `i` and `j`
/// that keep every sample within `bound` of the polyline through the kept points.
fn split(line: &[f64], i: usize, j: usize, bound: f64, kept: &mut Vec<usize>) {
    if j <= i + 1 {
        return;
    }
    let (hi, hj) = (line[i], line[j]);
    let span = (j - i) as f64;
    let mut worst = (0.0, i);
    for (k, &h) in line.iter().enumerate().take(j).skip(i + 1) {
        let e = (h - (hi + (hj - hi) * (k - i) as f64 / span)).abs();
        if e > worst.0 {
            worst = (e, k);
        }
    }
    if worst.0 > bound {
        kept.push(worst.1);
        split(line, i, worst.1, bound, kept);
        split(line, worst.1, j, bound, kept);
    }
}

/// Twice the signed area of triangle (a, b, c): positive when counter-clockwise in grid
/// coordinates (column right, row down), which is clockwise as seen with north up.
fn orient(a: [i32; 2], b: [i32; 2], c: [i32; 2]) -> i64 {
    i64::from(b[0] - a[0]) * i64::from(c[1] - a[1]) - i64::from(b[1] - a[1]) * i64::from(c[0] - a[0])
}

/// Whether `d` lies strictly inside the circle through (a, b, c), `orient(a, b, c) > 0`.
/// Exact: grid coordinates below 2^15 keep every product within i128.
fn in_circle(a: [i32; 2], b: [i32; 2], c: [i32; 2], d: [i32; 2]) -> bool {
    let row = |p: [i32; 2]| {
        let (x, y) = (i128::from(p[0] - d[0]), i128::from(p[1] - d[1]));
        (x, y, x * x + y * y)
    };
    let (ax, ay, a2) = row(a);
    let (bx, by, b2) = row(b);
    let (cx, cy, c2) = row(c);
    ax * (by * c2 - b2 * cy) - ay * (bx * c2 - b2 * cx) + a2 * (bx * cy - by * cx) > 0
}

/// A triangulation in progress: triangles with their half-edges' twins, each with its
/// worst grid point, in a queue by error (dead triangles are skipped when popped).
struct Triangulation<'a> {
    heights: &'a [f32],
    n: i32,
    bound: f32,
    points: Vec<[i32; 2]>,
    /// Vertex index of each grid point (u32::MAX: none).
    vertex_at: Vec<u32>,
    triangles: Vec<[u32; 3]>,
    /// The twin of half-edge `3t + k` (from corner k to corner k + 1 of triangle t), or -1
    /// on the border.
    twins: Vec<i64>,
    alive: Vec<bool>,
    candidates: Vec<([i32; 2], f32)>,
    queue: BinaryHeap<(u32, u32)>,
    pending: Vec<u32>,
}

impl<'a> Triangulation<'a> {
    fn new(heights: &'a [f32], n: i32, bound: f32) -> Self {
        let size = usize::try_from(n).unwrap_or(0);
        let mut t = Self {
            heights,
            n,
            bound,
            points: vec![],
            vertex_at: vec![u32::MAX; size * size],
            triangles: vec![],
            twins: vec![],
            alive: vec![],
            candidates: vec![],
            queue: BinaryHeap::new(),
            pending: vec![],
        };
        let m = n - 1;
        let [p0, p1, p2, p3] = [[0, 0], [m, 0], [0, m], [m, m]].map(|p| t.add_point(p));
        let first = t.add_triangle([p0, p1, p3], [-1, -1, -1]);
        t.add_triangle([p0, p3, p2], [first + 2, -1, -1]);
        t
    }

    fn at(&self, [x, y]: [i32; 2]) -> usize {
        #[expect(clippy::cast_sign_loss, reason = "grid coordinates are non-negative")]
        let at = (y * self.n + x) as usize;
        at
    }

    fn height(&self, p: [i32; 2]) -> f64 {
        f64::from(self.heights[self.at(p)])
    }

    fn add_point(&mut self, p: [i32; 2]) -> u32 {
        let index = u32::try_from(self.points.len()).unwrap_or(u32::MAX);
        let at = self.at(p);
        self.vertex_at[at] = index;
        self.points.push(p);
        index
    }

    /// Adds triangle `corners` whose edges' twins are `twins` (linked both ways); its first
    /// half-edge.
    fn add_triangle(&mut self, corners: [u32; 3], twins: [i64; 3]) -> i64 {
        let t = u32::try_from(self.triangles.len()).unwrap_or(u32::MAX);
        let e = i64::from(t) * 3;
        self.triangles.push(corners);
        for (k, twin) in twins.into_iter().enumerate() {
            self.twins.push(twin);
            if let Ok(twin) = usize::try_from(twin) {
                self.twins[twin] = e + k as i64;
            }
        }
        self.alive.push(true);
        self.candidates.push(([0, 0], 0.0));
        self.pending.push(t);
        e
    }

    fn corner(&self, e: i64) -> u32 {
        let (t, k) = split_edge(e);
        self.triangles[t][k]
    }

    fn twin(&self, e: i64) -> i64 {
        usize::try_from(e).map_or(-1, |e| self.twins[e])
    }

    fn kill(&mut self, e: i64) {
        self.alive[split_edge(e).0] = false;
    }

    /// Finds the worst grid point of every new triangle.
    fn flush(&mut self) {
        while let Some(t) = self.pending.pop() {
            let t = t as usize;
            if !self.alive[t] {
                continue;
            }
            let [a, b, c] = self.triangles[t].map(|v| self.points[v as usize]);
            let candidate = self.worst_point(a, b, c);
            self.candidates[t] = candidate;
            if candidate.1 > self.bound {
                #[expect(clippy::cast_possible_truncation, reason = "triangle counts fit u32")]
                self.queue.push((candidate.1.to_bits(), t as u32));
            }
        }
    }

    /// The grid point of triangle (a, b, c) furthest from its plane, and how far; points
    /// on the grid's border and the corners themselves are never candidates.
    ///
    /// Row by row: the columns inside the triangle (edges included) from the three edge
    /// functions, exactly, in integers; along them the plane's height by a step per column.
    fn worst_point(&self, a: [i32; 2], b: [i32; 2], c: [i32; 2]) -> ([i32; 2], f32) {
        let area = orient(a, b, c);
        if area <= 0 {
            return (a, 0.0);
        }
        let (ha, hb, hc) = (self.height(a), self.height(b), self.height(c));
        let area = area as f64;
        // The plane: z = ha + dx (x - ax) + dy (y - ay).
        let [(ea, fa), (eb, fb), (ec, fc)] =
            [(b, c), (c, a), (a, b)].map(|(p, q)| (f64::from(p[1] - q[1]), f64::from(q[0] - p[0])));
        let dx = (ea * ha + eb * hb + ec * hc) / area;
        let dy = (fa * ha + fb * hb + fc * hc) / area;
        let last = self.n - 1;
        let (x0, x1) = (a[0].min(b[0]).min(c[0]).max(1), a[0].max(b[0]).max(c[0]).min(last - 1));
        let (y0, y1) = (a[1].min(b[1]).min(c[1]).max(1), a[1].max(b[1]).max(c[1]).min(last - 1));
        let width = usize::try_from(self.n).unwrap_or(0);
        let mut worst = (a, 0.0f64);
        for y in y0..=y1 {
            // Columns where every edge function is >= 0.
            let (mut from, mut to) = (x0, x1);
            for (p, q) in [(b, c), (c, a), (a, b)] {
                // orient(p, q, (x, y)) = (qx - px)(y - py) - (qy - py)(x - px) = k - s x.
                let s = i64::from(q[1] - p[1]);
                let k = i64::from(q[0] - p[0]) * i64::from(y - p[1]) + s * i64::from(p[0]);
                match s.cmp(&0) {
                    // x <= k / s
                    std::cmp::Ordering::Greater => to = to.min(i32::try_from(k.div_euclid(s)).unwrap_or(i32::MIN)),
                    // x >= k / s, rounded up
                    std::cmp::Ordering::Less => {
                        from = from.max(i32::try_from(-(k.div_euclid(-s))).unwrap_or(i32::MAX));
                    }
                    std::cmp::Ordering::Equal if k < 0 => to = from - 1,
                    std::cmp::Ordering::Equal => {}
                }
            }
            if from > to {
                continue;
            }
            let row = &self.heights[y as usize * width..][from as usize..=to as usize];
            let z0 = ha + dx * f64::from(from - a[0]) + dy * f64::from(y - a[1]);
            let (mut best, mut at) = (worst.1, usize::MAX);
            for (i, &h) in row.iter().enumerate() {
                let e = (z0 + dx * i as f64 - f64::from(h)).abs();
                if e > best {
                    (best, at) = (e, i);
                }
            }
            if at != usize::MAX {
                #[expect(clippy::cast_possible_truncation, clippy::cast_possible_wrap, reason = "a column of the grid")]
                let x = from + at as i32;
                worst = ([x, y], best);
            }
        }
        // The corners lie on the plane (up to rounding): never a candidate.
        if worst.0 == a || worst.0 == b || worst.0 == c {
            return (a, 0.0);
        }
        #[expect(clippy::cast_possible_truncation, reason = "an error in metres")]
        let e = worst.1 as f32;
        (worst.0, e)
    }

    /// The live triangle with the largest error above the bound.
    fn worst(&mut self) -> Option<usize> {
        while let Some((_, t)) = self.queue.pop() {
            if self.alive[t as usize] {
                return Some(t as usize);
            }
        }
        None
    }

    /// Inserts triangle `t`'s candidate point (inside it: its border points are never
    /// candidates, but it may lie on an edge shared with a neighbour).
    fn insert(&mut self, t: usize) {
        let (p, _) = self.candidates[t];
        let e0 = t as i64 * 3;
        self.split_at(e0, p);
    }

    /// Inserts border point `p`: into the triangle whose border edge holds it.
    fn insert_on_border(&mut self, p: [i32; 2]) {
        if self.vertex_at[self.at(p)] != u32::MAX {
            return;
        }
        let found = (0..self.triangles.len()).find(|&t| {
            self.alive[t] && {
                let [a, b, c] = self.triangles[t].map(|v| self.points[v as usize]);
                orient(a, b, p) >= 0 && orient(b, c, p) >= 0 && orient(c, a, p) >= 0
            }
        });
        if let Some(t) = found {
            self.split_at(t as i64 * 3, p);
        }
    }

    /// Splits the triangle of half-edge `e0` (its first) at point `p`, inside it or on one
    /// of its edges, then restores the Delaunay condition around `p`.
    fn split_at(&mut self, e0: i64, p: [i32; 2]) {
        let pts = [0, 1, 2].map(|k| self.points[self.corner(e0 + k) as usize]);
        let on_edge = (0..3).find(|&k| orient(pts[k], pts[(k + 1) % 3], p) == 0);
        let pn = self.add_point(p);
        match on_edge {
            Some(k) => self.split_edge_at(e0 + k as i64, pn),
            None => {
                let [a, b, c] = [0, 1, 2].map(|k| self.corner(e0 + k));
                let [hab, hbc, hca] = [0, 1, 2].map(|k| self.twin(e0 + k));
                self.kill(e0);
                let t0 = self.add_triangle([a, b, pn], [hab, -1, -1]);
                let t1 = self.add_triangle([b, c, pn], [hbc, -1, t0 + 1]);
                let t2 = self.add_triangle([c, a, pn], [hca, t0 + 2, t1 + 1]);
                for e in [t0, t1, t2] {
                    self.legalize(e);
                }
            }
        }
    }

    /// Splits edge `e` (a to b, in triangle a, b, c) and its twin's triangle (b, a, d) at
    /// new vertex `pn` on it.
    fn split_edge_at(&mut self, e: i64, pn: u32) {
        let (t, k) = split_edge(e);
        let base = t as i64 * 3;
        let next = |k: usize| base + ((k + 1) % 3) as i64;
        let prev = |k: usize| base + ((k + 2) % 3) as i64;
        let (a, b, c) = (self.corner(e), self.corner(next(k)), self.corner(prev(k)));
        let (hbc, hca) = (self.twin(next(k)), self.twin(prev(k)));
        let twin = self.twin(e);
        self.kill(e);
        if twin < 0 {
            let t0 = self.add_triangle([a, pn, c], [-1, -1, hca]);
            let t1 = self.add_triangle([pn, b, c], [-1, hbc, t0 + 1]);
            self.legalize(t0 + 2);
            self.legalize(t1 + 1);
            return;
        }
        let (t2, k2) = split_edge(twin);
        let base2 = t2 as i64 * 3;
        let (e_ad, e_db) = (base2 + ((k2 + 1) % 3) as i64, base2 + ((k2 + 2) % 3) as i64);
        let d = self.corner(e_db);
        let (had, hdb) = (self.twin(e_ad), self.twin(e_db));
        self.kill(twin);
        let t0 = self.add_triangle([a, pn, c], [-1, -1, hca]);
        let t1 = self.add_triangle([pn, b, c], [-1, hbc, t0 + 1]);
        let t2 = self.add_triangle([b, pn, d], [t1, -1, hdb]);
        let t3 = self.add_triangle([pn, a, d], [t0, had, t2 + 1]);
        for e in [t0 + 2, t1 + 1, t2 + 2, t3 + 1] {
            self.legalize(e);
        }
    }

    /// Flips edge `e` (a to b in triangle a, b, p, opposite the new point p) when the
    /// twin's far corner d lies inside the circle through a, b, p; then the two edges the
    /// flip puts opposite p.
    fn legalize(&mut self, e: i64) {
        let twin = self.twin(e);
        if twin < 0 {
            return;
        }
        let (t, k) = split_edge(e);
        let base = t as i64 * 3;
        let (e_bp, e_pa) = (base + ((k + 1) % 3) as i64, base + ((k + 2) % 3) as i64);
        let (a, b, p) = (self.corner(e), self.corner(e_bp), self.corner(e_pa));
        let (t2, k2) = split_edge(twin);
        let base2 = t2 as i64 * 3;
        let (e_ad, e_db) = (base2 + ((k2 + 1) % 3) as i64, base2 + ((k2 + 2) % 3) as i64);
        let d = self.corner(e_db);
        let [pa, pb, pp, pd] = [a, b, p, d].map(|v| self.points[v as usize]);
        if !in_circle(pa, pb, pp, pd) || orient(pa, pd, pp) <= 0 || orient(pd, pb, pp) <= 0 {
            return;
        }
        let (hbp, hpa, had, hdb) = (self.twin(e_bp), self.twin(e_pa), self.twin(e_ad), self.twin(e_db));
        self.kill(e);
        self.kill(twin);
        let t0 = self.add_triangle([a, d, p], [had, -1, hpa]);
        let t1 = self.add_triangle([d, b, p], [hdb, hbp, t0 + 1]);
        self.legalize(t0);
        self.legalize(t1);
    }

    fn finish(self) -> Mesh {
        let triangles = (0..self.triangles.len())
            .filter(|&t| self.alive[t])
            // Counter-clockwise with north up: the grid's rows go down, so reverse.
            .map(|t| {
                let [a, b, c] = self.triangles[t];
                [a, c, b]
            })
            .collect();
        #[expect(clippy::cast_sign_loss, reason = "grid coordinates are non-negative")]
        let vertices = self.points.iter().map(|p| [p[0] as u32, p[1] as u32]).collect();
        Mesh { vertices, triangles }
    }
}

fn split_edge(e: i64) -> (usize, usize) {
    #[expect(clippy::cast_sign_loss, clippy::cast_possible_truncation, reason = "a live half-edge")]
    let e = e as usize;
    (e / 3, e % 3)
}

#[cfg(test)]
#[allow(clippy::cast_possible_truncation, clippy::cast_possible_wrap, clippy::cast_sign_loss, clippy::unwrap_used)]
mod tests {
    use super::*;
    use proptest::prelude::*;

    /// Checks that `m` covers the grid exactly once with counter-clockwise (north up)
    /// triangles and that no grid point is further than `bound` from it; the largest error.
    fn check(m: &Mesh, heights: &[f32], n: usize, bound: f32) -> f64 {
        let p = |v: u32| m.vertices[v as usize].map(|c| i32::try_from(c).unwrap());
        let mut area = 0i64;
        let mut covered = vec![0u32; n * n];
        let mut worst = 0.0f64;
        for &[a, b, c] in &m.triangles {
            let (a, b, c) = (p(a), p(b), p(c));
            // North up is grid rows reversed: counter-clockwise there is negative here.
            let twice = orient(a, b, c);
            assert!(twice < 0, "triangle {a:?} {b:?} {c:?} is not counter-clockwise");
            area -= twice;
            let h = |q: [i32; 2]| f64::from(heights[q[1] as usize * n + q[0] as usize]);
            for y in 0..n as i32 {
                for x in 0..n as i32 {
                    let q = [x, y];
                    let (wa, wb, wc) = (orient(c, b, q), orient(a, c, q), orient(b, a, q));
                    if wa < 0 || wb < 0 || wc < 0 {
                        continue;
                    }
                    covered[y as usize * n + x as usize] += 1;
                    let z = (wa as f64 * h(a) + wb as f64 * h(b) + wc as f64 * h(c)) / (-twice) as f64;
                    worst = worst.max((z - h(q)).abs());
                }
            }
        }
        let side = i64::try_from(n - 1).unwrap();
        assert_eq!(area, 2 * side * side, "the triangles' area is not the grid's");
        assert!(covered.iter().all(|&c| c >= 1), "a grid point lies in no triangle");
        assert!(worst <= f64::from(bound) + 1e-3, "error {worst} over the bound {bound}");
        let mut seen = std::collections::HashSet::new();
        assert!(m.vertices.iter().all(|v| seen.insert(*v)), "a vertex twice");
        worst
    }

    fn border(m: &Mesh, n: u32) -> Vec<[u32; 2]> {
        let mut b: Vec<[u32; 2]> =
            m.vertices.iter().copied().filter(|v| v[0] == 0 || v[1] == 0 || v[0] == n - 1 || v[1] == n - 1).collect();
        b.sort_unstable();
        b
    }

    #[test]
    fn a_flat_grid_is_two_triangles() {
        let m = mesh(&[7.0; 65 * 65], 65, 0.0);
        assert_eq!((m.vertices.len(), m.triangles.len()), (4, 2));
        check(&m, &[7.0; 65 * 65], 65, 0.0);
        // A tilted plane too: bilinear grids of a plane need no more.
        let plane: Vec<f32> = (0..65 * 65).map(|i| (i % 65) as f32 * 2.0 - (i / 65) as f32).collect();
        let m = mesh(&plane, 65, 0.01);
        assert_eq!(m.triangles.len(), 2);
        check(&m, &plane, 65, 0.01);
    }

    #[test]
    fn a_zero_bound_keeps_every_point_that_is_off_the_plane() {
        let heights: Vec<f32> = (0..17 * 17).map(|i| ((i * 7919) % 13) as f32).collect();
        let m = mesh(&heights, 17, 0.0);
        let worst = check(&m, &heights, 17, 0.0);
        assert!(worst < 1e-3);
    }

    #[test]
    fn spikes_and_steps_stay_within_the_bound() {
        let n = 65;
        let mut heights = vec![100.0f32; n * n];
        heights[20 * n + 30] = 900.0;
        heights[50 * n + 10] = -300.0;
        for y in 0..n {
            for x in 40..n {
                heights[y * n + x] = 250.0;
            }
        }
        let m = mesh(&heights, n, 1.0);
        check(&m, &heights, n, 1.0);
        assert!(m.vertices.contains(&[30, 20]) && m.vertices.contains(&[10, 50]));
        assert!(m.vertices.len() < 400, "{} vertices for two spikes and a step", m.vertices.len());
    }

    #[test]
    fn tiles_sharing_an_edge_keep_the_same_points_on_it() {
        let n = 33;
        let field = |x: usize, y: usize| ((x as f32 * 0.37).sin() * 40.0 + (y as f32 * 0.21).cos() * 25.0).round();
        // Two tiles side by side over one field: the left's east column is the right's west.
        let left: Vec<f32> = (0..n * n).map(|i| field(i % n, i / n)).collect();
        let right: Vec<f32> = (0..n * n).map(|i| field(i % n + n - 1, i / n)).collect();
        let (a, b) = (mesh(&left, n, 2.0), mesh(&right, n, 2.0));
        check(&a, &left, n, 2.0);
        check(&b, &right, n, 2.0);
        let last = u32::try_from(n - 1).unwrap();
        let mut east: Vec<u32> = border(&a, last + 1).iter().filter(|v| v[0] == last).map(|v| v[1]).collect();
        let mut west: Vec<u32> = border(&b, last + 1).iter().filter(|v| v[0] == 0).map(|v| v[1]).collect();
        east.sort_unstable();
        west.sort_unstable();
        assert_eq!(east, west);
        assert!(east.len() > 2, "the shared edge is not flat: it needs points");
    }

    #[test]
    fn nodata_is_filled_from_the_rim_and_zero_on_the_border() {
        let n = 9;
        let mut h = vec![10.0f32; n * n];
        for y in 2..7 {
            for x in 2..7 {
                h[y * n + x] = f32::NAN;
            }
        }
        h[0] = f32::NAN;
        h[4] = f32::INFINITY;
        fill_nodata(&mut h, n);
        assert!(h.iter().all(|v| v.is_finite()));
        assert_eq!((h[0], h[4]), (0.0, 0.0));
        assert!((h[4 * n + 4] - 10.0).abs() < 1e-4, "the hole's middle {}", h[4 * n + 4]);
        let mut all = vec![f32::NAN; n * n];
        fill_nodata(&mut all, n);
        assert!(all.iter().all(|&v| v == 0.0));
    }

    #[test]
    fn degenerate_input_gives_an_empty_mesh_not_a_panic() {
        assert_eq!(mesh(&[], 0, 1.0), Mesh::default());
        assert_eq!(mesh(&[1.0], 1, 1.0), Mesh::default());
        assert_eq!(mesh(&[1.0; 5], 3, 1.0), Mesh::default());
        let m = mesh(&[1.0, 2.0, 3.0, f32::NAN], 2, 0.0);
        assert_eq!(m.triangles.len(), 2);
    }

    fn grid() -> impl Strategy<Value = (usize, Vec<f32>, f32)> {
        (prop_oneof![Just(2usize), Just(3), Just(5), Just(9), Just(17), Just(33)], 0u8..4, any::<u64>(), 0.0f32..30.0)
            .prop_map(|(n, kind, seed, bound)| {
                let mut s = seed | 1;
                let mut next = move || {
                    s ^= s << 13;
                    s ^= s >> 7;
                    s ^= s << 17;
                    s
                };
                let heights = (0..n * n)
                    .map(|i| {
                        let (x, y) = ((i % n) as f32, (i / n) as f32);
                        #[expect(clippy::cast_precision_loss)]
                        let r = (next() % 1000) as f32;
                        match kind {
                            0 => r, // noise
                            1 => {
                                if r > 990.0 {
                                    r * 5.0
                                } else {
                                    0.0
                                }
                            } // spikes
                            2 => {
                                if x + y * 0.5 > n as f32 * 0.6 {
                                    300.0
                                } else {
                                    0.0
                                }
                            } // a step
                            _ => {
                                if r > 700.0 {
                                    f32::NAN
                                } else {
                                    x * 3.0 - y + r * 0.01
                                }
                            } // holes
                        }
                    })
                    .collect();
                (n, heights, bound)
            })
    }

    proptest! {
        /// The scanline finds what a scan of every point of the triangle's box finds.
        #[test]
        fn a_triangles_worst_point_is_the_one_a_full_scan_finds(
            heights in proptest::collection::vec(-50.0f32..50.0, 17 * 17),
            corners in proptest::array::uniform3(proptest::array::uniform2(0i32..17)),
        ) {
            let [a, b, c] = corners;
            let t = Triangulation::new(&heights, 17, 0.0);
            let (found, error) = t.worst_point(a, b, c);
            let area = orient(a, b, c);
            let h = |q: [i32; 2]| f64::from(heights[q[1] as usize * 17 + q[0] as usize]);
            let mut worst = 0.0f64;
            for y in 1..16 {
                for x in 1..16 {
                    let q = [x, y];
                    let (wa, wb, wc) = (orient(b, c, q), orient(c, a, q), orient(a, b, q));
                    if area <= 0 || wa < 0 || wb < 0 || wc < 0 || q == a || q == b || q == c {
                        continue;
                    }
                    let z = (wa as f64 * h(a) + wb as f64 * h(b) + wc as f64 * h(c)) / area as f64;
                    worst = worst.max((z - h(q)).abs());
                }
            }
            prop_assert!((f64::from(error) - worst).abs() <= 1e-4 * (1.0 + worst), "{error} against {worst}");
            if error > 0.0 {
                let q = found;
                let (wa, wb, wc) = (orient(b, c, q), orient(c, a, q), orient(a, b, q));
                prop_assert!(wa >= 0 && wb >= 0 && wc >= 0, "{q:?} outside the triangle");
                let z = (wa as f64 * h(a) + wb as f64 * h(b) + wc as f64 * h(c)) / area as f64;
                prop_assert!(((z - h(q)).abs() - f64::from(error)).abs() <= 1e-4 * (1.0 + worst));
            }
        }

        #[test]
        fn any_grid_meshes_within_its_bound((n, mut heights, bound) in grid()) {
            fill_nodata(&mut heights, n);
            let m = mesh(&heights, n, bound);
            check(&m, &heights, n, bound);
        }
    }
}
