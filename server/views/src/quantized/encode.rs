//! The quantized-mesh-1.0 binary (github.com/CesiumGS/quantized-mesh), little-endian:
//! header (tile centre, height range, bounding sphere, horizon-occlusion point), vertices
//! as zig-zag delta-coded u, v and height, triangles as high-water-mark coded indices (16
//! bits up to 65 536 vertices, 32 beyond), the four edges' vertex lists, then extensions.

use super::geodetic::{self, GeoTile};
use super::mesh::Mesh;

/// Quantized coordinates span 0..=32767.
const QUANTA: f64 = 32767.0;

/// Extension identifiers.
const OCT_NORMALS: u8 = 1;
const WATER_MASK: u8 = 2;
const METADATA: u8 = 4;

/// The extensions a tile carries.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Hash)]
pub struct Extensions {
    /// `octvertexnormals`: a unit normal a vertex, oct-encoded in two bytes.
    pub normals: bool,
    /// `watermask`: where the tile is sea (one byte, 0 all land or 255 all sea, or 256 x
    /// 256 from the north-west corner, rows north to south).
    pub water: bool,
    /// `metadata`: JSON with the availability of the levels below (tiles whose level is a
    /// multiple of [`geodetic::METADATA_LEVELS`] only).
    pub metadata: bool,
}

impl Extensions {
    /// The extensions a client's `Accept` header asks for
    /// (`application/vnd.quantized-mesh;extensions=octvertexnormals-metadata`).
    pub fn from_accept(accept: &str) -> Self {
        let mut out = Self::default();
        for part in accept.split(',') {
            for param in part.split(';').skip(1) {
                let Some((key, value)) = param.split_once('=') else { continue };
                if key.trim() != "extensions" {
                    continue;
                }
                for name in value.trim().trim_matches('"').split('-') {
                    match name {
                        "octvertexnormals" | "vertexnormals" => out.normals = true,
                        "watermask" => out.water = true,
                        "metadata" => out.metadata = true,
                        _ => {}
                    }
                }
            }
        }
        out
    }

    /// All the extensions this server offers (what `export` writes).
    pub const ALL: Self = Self { normals: true, water: true, metadata: true };

    /// The `extensions=` value naming these (empty for none).
    pub fn names(self) -> String {
        let mut names = vec![];
        if self.normals {
            names.push("octvertexnormals");
        }
        if self.water {
            names.push("watermask");
        }
        if self.metadata {
            names.push("metadata");
        }
        names.join("-")
    }
}

/// What a tile's binary is made of: its mesh over its grid of heights.
pub struct TileMesh<'a> {
    /// The tile.
    pub tile: GeoTile,
    /// The mesh, on grid points of `heights`.
    pub mesh: &'a Mesh,
    /// The heights, `size` x `size`, row by row from the north.
    pub heights: &'a [f32],
    /// Grid points a side.
    pub size: usize,
    /// The water mask (one byte or 256 x 256), where the tile's sea is known.
    pub water: Option<&'a [u8]>,
}

/// A vertex as the tile stores it and as a client decodes it.
#[derive(Clone, Copy, Debug)]
struct Vertex {
    u: u16,
    v: u16,
    h: u16,
    /// Earth-centred, Earth-fixed position of the decoded vertex.
    ecef: [f64; 3],
}

/// Encodes a tile, with `metadata` JSON when the metadata extension is asked and given.
pub fn encode(t: &TileMesh<'_>, extensions: Extensions, metadata: Option<&serde_json::Value>) -> Vec<u8> {
    let (order, triangles) = first_use_order(t.mesh);
    let (vertices, range) = quantized_vertices(t, &order);
    let mut out = Vec::with_capacity(88 + vertices.len() * 10 + triangles.len() * 6);
    header(&mut out, t.tile, &vertices, range);
    let count = u32::try_from(vertices.len()).unwrap_or(u32::MAX);
    out.extend_from_slice(&count.to_le_bytes());
    for get in [|v: &Vertex| v.u, |v: &Vertex| v.v, |v: &Vertex| v.h] {
        let mut previous = 0i32;
        for v in &vertices {
            let value = i32::from(get(v));
            out.extend_from_slice(&zigzag(value - previous).to_le_bytes());
            previous = value;
        }
    }
    let indices = Indices { wide: vertices.len() > 65_536 };
    if indices.wide {
        while out.len() % 4 != 0 {
            out.push(0);
        }
    }
    let triangle_count = u32::try_from(triangles.len()).unwrap_or(u32::MAX);
    out.extend_from_slice(&triangle_count.to_le_bytes());
    let mut highest = 0u32;
    for &index in triangles.iter().flatten() {
        indices.put(&mut out, highest - index);
        if index == highest {
            highest += 1;
        }
    }
    for edge in edges(&vertices) {
        out.extend_from_slice(&u32::try_from(edge.len()).unwrap_or(u32::MAX).to_le_bytes());
        for i in edge {
            indices.put(&mut out, i);
        }
    }
    if extensions.normals {
        let normals = vertex_normals(&vertices, &triangles);
        extension(&mut out, OCT_NORMALS, &normals.iter().flat_map(|&n| oct_encode(n)).collect::<Vec<u8>>());
    }
    if extensions.water {
        extension(&mut out, WATER_MASK, t.water.unwrap_or(&[0]));
    }
    if let (true, Some(json)) = (extensions.metadata, metadata) {
        let text = json.to_string();
        let mut data = u32::try_from(text.len()).unwrap_or(u32::MAX).to_le_bytes().to_vec();
        data.extend_from_slice(text.as_bytes());
        extension(&mut out, METADATA, &data);
    }
    out
}

/// The vertices in `order`, quantized (u, v over the tile, heights over their range),
/// with their ECEF positions as a decoder finds them; and the height range.
fn quantized_vertices(t: &TileMesh<'_>, order: &[usize]) -> (Vec<Vertex>, [f64; 2]) {
    let last = (t.size.max(2) - 1) as f64;
    let point = |i: usize| t.mesh.vertices[i];
    let height = |[c, r]: [u32; 2]| f64::from(t.heights[r as usize * t.size + c as usize]);
    let (mut min, mut max) = (f64::INFINITY, f64::NEG_INFINITY);
    for &i in order {
        let h = height(point(i));
        min = min.min(h);
        max = max.max(h);
    }
    if !min.is_finite() {
        (min, max) = (0.0, 0.0);
    }
    // (Heights are f32: the header's f32 range holds these exactly.)
    let [west, south, east, north] = t.tile.bounds();
    let vertices = order
        .iter()
        .map(|&i| {
            let [c, r] = point(i);
            let u = quantize(f64::from(c) / last);
            let v = quantize((last - f64::from(r)) / last);
            let h = if max > min { quantize((height([c, r]) - min) / (max - min)) } else { 0 };
            let lon = west + (east - west) * f64::from(u) / QUANTA;
            let lat = south + (north - south) * f64::from(v) / QUANTA;
            let hd = min + (max - min) * f64::from(h) / QUANTA;
            Vertex { u, v, h, ecef: geodetic::ecef(lon, lat, hd) }
        })
        .collect();
    (vertices, [min, max])
}

/// Vertex indices as written: 16 bits, or 32 beyond 65 536 vertices.
struct Indices {
    wide: bool,
}

impl Indices {
    fn put(&self, out: &mut Vec<u8>, index: u32) {
        if self.wide {
            out.extend_from_slice(&index.to_le_bytes());
        } else {
            #[expect(clippy::cast_possible_truncation, reason = "16-bit indices below 65 536 vertices")]
            out.extend_from_slice(&(index as u16).to_le_bytes());
        }
    }
}

/// The vertices on the west, south, east and north edges, each list along its edge.
fn edges(vertices: &[Vertex]) -> [Vec<u32>; 4] {
    let count = u32::try_from(vertices.len()).unwrap_or(u32::MAX);
    let edge_of = |keep: &dyn Fn(u16, u16) -> bool, by_u: bool| {
        let mut edge: Vec<u32> = (0..count).filter(|&i| keep(vertices[i as usize].u, vertices[i as usize].v)).collect();
        edge.sort_by_key(|&i| if by_u { vertices[i as usize].u } else { vertices[i as usize].v });
        edge
    };
    let top = 32767;
    [
        edge_of(&|u, _| u == 0, false),
        edge_of(&|_, v| v == 0, true),
        edge_of(&|u, _| u == top, false),
        edge_of(&|_, v| v == top, true),
    ]
}

/// The mesh's vertices in the order the triangles first use them (so that each index is
/// at most one above the highest before it: high-water-mark coding), and the triangles
/// renumbered to that order.
fn first_use_order(mesh: &Mesh) -> (Vec<usize>, Vec<[u32; 3]>) {
    let mut new_index = vec![u32::MAX; mesh.vertices.len()];
    let mut order = Vec::with_capacity(mesh.vertices.len());
    let triangles = mesh
        .triangles
        .iter()
        .map(|tri| {
            tri.map(|v| {
                let v = v as usize;
                if new_index[v] == u32::MAX {
                    new_index[v] = u32::try_from(order.len()).unwrap_or(u32::MAX);
                    order.push(v);
                }
                new_index[v]
            })
        })
        .collect();
    (order, triangles)
}

#[expect(clippy::cast_possible_truncation, clippy::cast_sign_loss, reason = "clamped to 0..=32767")]
fn quantize(t: f64) -> u16 {
    (t * QUANTA).round().clamp(0.0, QUANTA) as u16
}

fn zigzag(v: i32) -> u16 {
    #[expect(clippy::cast_possible_truncation, clippy::cast_sign_loss, reason = "deltas of 15-bit values")]
    let z = ((v << 1) ^ (v >> 31)) as u16;
    z
}

fn header(out: &mut Vec<u8>, tile: GeoTile, vertices: &[Vertex], [min, max]: [f64; 2]) {
    let [west, south, east, north] = tile.bounds();
    let centre = geodetic::ecef((west + east) / 2.0, (south + north) / 2.0, (min + max) / 2.0);
    let (sphere_centre, radius) = bounding_sphere(vertices.iter().map(|v| v.ecef));
    let horizon = geodetic::horizon_occlusion_point(vertices.iter().map(|v| v.ecef), sphere_centre);
    for v in centre {
        out.extend_from_slice(&v.to_le_bytes());
    }
    #[expect(clippy::cast_possible_truncation, reason = "heights in f32, as the format stores them")]
    for v in [min as f32, max as f32] {
        out.extend_from_slice(&v.to_le_bytes());
    }
    for v in sphere_centre.into_iter().chain([radius]).chain(horizon) {
        out.extend_from_slice(&v.to_le_bytes());
    }
}

/// A sphere holding every point: the centre of their box, the distance to the furthest.
fn bounding_sphere(points: impl Iterator<Item = [f64; 3]> + Clone) -> ([f64; 3], f64) {
    let (mut lo, mut hi) = ([f64::INFINITY; 3], [f64::NEG_INFINITY; 3]);
    for p in points.clone() {
        for k in 0..3 {
            lo[k] = lo[k].min(p[k]);
            hi[k] = hi[k].max(p[k]);
        }
    }
    if !lo[0].is_finite() {
        return ([0.0; 3], 0.0);
    }
    let centre = [0, 1, 2].map(|k| (lo[k] + hi[k]) / 2.0);
    let radius = points.map(|p| distance(p, centre)).fold(0.0, f64::max);
    // A hair more, so that rounding never leaves a vertex outside.
    (centre, radius * (1.0 + 1e-9) + 1e-6)
}

fn distance(a: [f64; 3], b: [f64; 3]) -> f64 {
    ((a[0] - b[0]).powi(2) + (a[1] - b[1]).powi(2) + (a[2] - b[2]).powi(2)).sqrt()
}

/// Unit normals a vertex: the area-weighted mean of its triangles' normals (in ECEF).
fn vertex_normals(vertices: &[Vertex], triangles: &[[u32; 3]]) -> Vec<[f64; 3]> {
    let mut sums = vec![[0.0f64; 3]; vertices.len()];
    for tri in triangles {
        let [a, b, c] = tri.map(|i| vertices[i as usize].ecef);
        let (ab, ac) = ([0, 1, 2].map(|k| b[k] - a[k]), [0, 1, 2].map(|k| c[k] - a[k]));
        let n = [ab[1] * ac[2] - ab[2] * ac[1], ab[2] * ac[0] - ab[0] * ac[2], ab[0] * ac[1] - ab[1] * ac[0]];
        for &i in tri {
            for k in 0..3 {
                sums[i as usize][k] += n[k];
            }
        }
    }
    sums.iter()
        .zip(vertices)
        .map(|(n, v)| {
            let len = (n[0] * n[0] + n[1] * n[1] + n[2] * n[2]).sqrt();
            if len > 0.0 {
                n.map(|c| c / len)
            } else {
                // No area (a degenerate vertex): the ellipsoid's normal.
                geodetic::surface_normal(v.ecef)
            }
        })
        .collect()
}

/// Oct-encodes a unit vector in two bytes (as Cesium's `AttributeCompression.octEncode`).
pub fn oct_encode(n: [f64; 3]) -> [u8; 2] {
    let sum = n[0].abs() + n[1].abs() + n[2].abs();
    if sum == 0.0 {
        return [128, 128];
    }
    let (mut x, mut y) = (n[0] / sum, n[1] / sum);
    if n[2] < 0.0 {
        let sign = |v: f64| if v < 0.0 { -1.0 } else { 1.0 };
        (x, y) = ((1.0 - y.abs()) * sign(x), (1.0 - x.abs()) * sign(y));
    }
    #[expect(clippy::cast_possible_truncation, clippy::cast_sign_loss, reason = "clamped to 0..=255")]
    let snorm = |v: f64| ((v.clamp(-1.0, 1.0) * 0.5 + 0.5) * 255.0).round() as u8;
    [snorm(x), snorm(y)]
}

fn extension(out: &mut Vec<u8>, id: u8, data: &[u8]) {
    out.push(id);
    out.extend_from_slice(&u32::try_from(data.len()).unwrap_or(u32::MAX).to_le_bytes());
    out.extend_from_slice(data);
}

#[cfg(test)]
#[allow(clippy::cast_possible_truncation, clippy::unwrap_used)]
mod tests {
    use super::*;

    /// A decoded tile: header values, vertices (u, v, h), triangles, edges, extensions.
    struct Decoded {
        header: Vec<f64>,
        vertices: Vec<[u16; 3]>,
        triangles: Vec<[u32; 3]>,
        edges: [Vec<u32>; 4],
        extensions: Vec<(u8, Vec<u8>)>,
    }

    struct Cursor<'a>(&'a [u8], usize);

    impl Cursor<'_> {
        fn take(&mut self, n: usize) -> &[u8] {
            let s = &self.0[self.1..self.1 + n];
            self.1 += n;
            s
        }
        fn u32(&mut self) -> u32 {
            u32::from_le_bytes(self.take(4).try_into().unwrap())
        }
        fn u16(&mut self) -> u16 {
            u16::from_le_bytes(self.take(2).try_into().unwrap())
        }
        fn index(&mut self, wide: bool) -> u32 {
            if wide { self.u32() } else { u32::from(self.u16()) }
        }
    }

    fn decode(b: &[u8]) -> Decoded {
        let mut c = Cursor(b, 0);
        let mut header = vec![];
        for i in 0..12 {
            if i == 3 || i == 4 {
                header.push(f64::from(f32::from_le_bytes(c.take(4).try_into().unwrap())));
            } else {
                header.push(f64::from_le_bytes(c.take(8).try_into().unwrap()));
            }
        }
        let n = c.u32() as usize;
        let mut columns = [vec![], vec![], vec![]];
        for column in &mut columns {
            let mut value = 0i32;
            for _ in 0..n {
                let z = i32::from(c.u16());
                value += (z >> 1) ^ -(z & 1);
                column.push(u16::try_from(value).unwrap());
            }
        }
        let vertices = (0..n).map(|i| [columns[0][i], columns[1][i], columns[2][i]]).collect();
        let wide = n > 65_536;
        if wide {
            c.1 = c.1.div_ceil(4) * 4;
        }
        let count = c.u32() as usize;
        let mut highest = 0;
        let mut flat = vec![];
        for _ in 0..count * 3 {
            let code = c.index(wide);
            flat.push(highest - code);
            if code == 0 {
                highest += 1;
            }
        }
        let triangles = flat.chunks(3).map(|t| [t[0], t[1], t[2]]).collect();
        let mut edges: [Vec<u32>; 4] = Default::default();
        for edge in &mut edges {
            let k = c.u32();
            *edge = (0..k).map(|_| c.index(wide)).collect();
        }
        let mut extensions = vec![];
        while c.1 < b.len() {
            let id = c.take(1)[0];
            let len = c.u32() as usize;
            extensions.push((id, c.take(len).to_vec()));
        }
        Decoded { header, vertices, triangles, edges, extensions }
    }

    fn grid_mesh(n: u32) -> Mesh {
        let vertices = (0..n * n).map(|i| [i % n, i / n]).collect();
        let mut triangles = vec![];
        for y in 0..n - 1 {
            for x in 0..n - 1 {
                let (a, b, c, d) = (y * n + x, y * n + x + 1, (y + 1) * n + x, (y + 1) * n + x + 1);
                triangles.push([a, c, b]);
                triangles.push([b, c, d]);
            }
        }
        Mesh { vertices, triangles }
    }

    #[test]
    fn a_tile_decodes_to_its_mesh() {
        let n = 5;
        let heights: Vec<f32> = (0..25).map(|i| 100.0 + (i * 37 % 11) as f32).collect();
        let mesh = grid_mesh(n);
        let tile = GeoTile::new(3, 9, 5).unwrap();
        let t = TileMesh { tile, mesh: &mesh, heights: &heights, size: 5, water: None };
        let json = serde_json::json!({"available": [[]]});
        let d = decode(&encode(&t, Extensions::ALL, Some(&json)));
        assert_eq!(d.vertices.len(), 25);
        assert_eq!(d.triangles.len(), mesh.triangles.len());
        assert_eq!((d.header[3], d.header[4]), (100.0, 110.0));
        // Every vertex back where it was, in quanta, and its height to a quantum.
        for tri in &d.triangles {
            for &i in tri {
                let [u, v, h] = d.vertices[i as usize];
                assert!(u <= 32767 && v <= 32767 && h <= 32767);
            }
        }
        let corner = d.vertices.iter().find(|v| v[0] == 0 && v[1] == 32767).unwrap();
        assert_eq!(f64::from(corner[2]) / 32767.0 * 10.0 + 100.0, f64::from(heights[0]));
        // Edges: west and east south to north, south and north west to east, 5 each.
        for (k, edge) in d.edges.iter().enumerate() {
            assert_eq!(edge.len(), 5);
            let key = |i: &u32| d.vertices[*i as usize][if k % 2 == 0 { 1 } else { 0 }];
            assert!(edge.windows(2).all(|w| key(&w[0]) < key(&w[1])));
        }
        assert_eq!(d.extensions.iter().map(|e| e.0).collect::<Vec<_>>(), vec![1, 2, 4]);
        assert_eq!(d.extensions[0].1.len(), 50);
        assert_eq!(d.extensions[1].1, vec![0], "no mask known: all land");
        let meta = &d.extensions[2].1;
        assert_eq!(&meta[4..], json.to_string().as_bytes());
        // Without extensions: none.
        let d = decode(&encode(&t, Extensions::default(), Some(&json)));
        assert!(d.extensions.is_empty());
        // Sphere holds the vertices.
        let (centre, radius) = ([d.header[5], d.header[6], d.header[7]], d.header[8]);
        let [w, s, e, n_] = tile.bounds();
        for v in &d.vertices {
            let lon = w + (e - w) * f64::from(v[0]) / 32767.0;
            let lat = s + (n_ - s) * f64::from(v[1]) / 32767.0;
            let p = geodetic::ecef(lon, lat, 100.0 + 10.0 * f64::from(v[2]) / 32767.0);
            assert!(distance(p, centre) <= radius);
        }
    }

    #[test]
    fn more_than_65536_vertices_take_32_bit_indices() {
        let n = 257;
        let mesh = grid_mesh(n);
        let heights = vec![5.0f32; (n * n) as usize];
        let t = TileMesh {
            tile: GeoTile::new(12, 100, 200).unwrap(),
            mesh: &mesh,
            heights: &heights,
            size: n as usize,
            water: None,
        };
        let bytes = encode(&t, Extensions::default(), None);
        let d = decode(&bytes);
        assert_eq!(d.vertices.len(), 66_049);
        assert_eq!(d.triangles.len(), mesh.triangles.len());
        assert!(d.triangles.iter().flatten().all(|&i| (i as usize) < d.vertices.len()));
        assert!(d.edges.iter().all(|e| e.len() == 257));
        // Indices past 65 535 survive.
        assert!(d.triangles.iter().flatten().any(|&i| i > 65_535));
    }

    #[test]
    fn oct_encoding_matches_cesium() {
        // Values from Cesium's AttributeCompression.octEncode (range 255).
        assert_eq!(oct_encode([0.0, 0.0, 1.0]), [128, 128]);
        assert_eq!(oct_encode([1.0, 0.0, 0.0]), [255, 128]);
        assert_eq!(oct_encode([0.0, 0.0, -1.0]), [255, 255]);
        assert_eq!(oct_encode([0.0, -1.0, 0.0]), [128, 0]);
    }

    #[test]
    fn accept_headers_name_the_extensions() {
        let cesium = "application/vnd.quantized-mesh;extensions=octvertexnormals-watermask-metadata,application/octet-stream;q=0.9,*/*;q=0.01";
        assert_eq!(Extensions::from_accept(cesium), Extensions::ALL);
        assert_eq!(Extensions::from_accept("application/vnd.quantized-mesh,*/*;q=0.01"), Extensions::default());
        let only = Extensions::from_accept("application/vnd.quantized-mesh;extensions=metadata");
        assert_eq!(only, Extensions { normals: false, water: false, metadata: true });
        assert_eq!(Extensions::ALL.names(), "octvertexnormals-watermask-metadata");
    }

    #[test]
    fn the_water_mask_is_the_flat_zero_from_the_north_west() {
        use super::super::water_mask;
        let n = 9;
        // West of column 4 a flat 0; east of it land; one land point inside the sea.
        let mut h: Vec<f32> = (0..n * n).map(|i| if i % n < 4 { 0.0 } else { 3.0 + (i % n) as f32 }).collect();
        assert_eq!(water_mask(&vec![0.0; n * n], n, None), vec![255]);
        assert_eq!(water_mask(&h.iter().map(|v| v + 10.0).collect::<Vec<_>>(), n, None), vec![0]);
        h[n + 1] = 0.3;
        let m = water_mask(&h, n, None);
        assert_eq!(m.len(), 65_536);
        assert_eq!(m[200 * 256 + 2], 255, "west: sea");
        assert_eq!(m[200 * 256 + 253], 0, "east: land");
        assert!(m[20 * 256 + 20] < 255, "the point at 0.3 m breaks the flat 0 near the north-west");
        // A basin below sea level (not flat at 0) is land.
        assert_eq!(water_mask(&vec![-30.0; n * n], n, None), vec![0]);
        // Beside missing data the sea stays sea, as the renderer draws it (its shade
        // texels' rule): a flat 0 whose northern rows have no data.
        let mut coast = vec![0.0f32; n * n];
        coast[..2 * n].fill(f32::NAN);
        let m = water_mask(&coast, n, None);
        assert_eq!(m[255 * 256 + 128], 255, "south: sea");
        assert_eq!(m[70 * 256 + 128], 255, "between the row beside the missing data and the next: sea");
        assert!(terrastream_tiles::flat_sea(0.0, [f32::NAN, 0.0, f32::NAN, 0.0]));
        assert!(!terrastream_tiles::flat_sea(0.0, [0.2, 0.0, 0.0, 0.0]));
    }

    #[test]
    fn a_water_layer_overrides_the_flat_zero_where_it_has_data() {
        use super::super::water_mask;
        let n = 9;
        // Land at 300 m with a lake in the middle columns; the layer says nothing in the
        // last three rows, which are a flat 0 (the sea, by the heights' rule).
        let mut h = vec![300.0f32; n * n];
        h[6 * n..].fill(0.0);
        let mut w: Vec<f32> = (0..n * n).map(|i| if (3..6).contains(&(i % n)) { 1.0 } else { 0.0 }).collect();
        w[6 * n..].fill(f32::NAN);
        let m = water_mask(&h, n, Some(&w));
        assert_eq!(m.len(), 65_536);
        assert_eq!(m[64 * 256 + 128], 255, "the lake, from the layer");
        assert_eq!(m[64 * 256 + 10], 0, "land beside it");
        assert_eq!(m[255 * 256 + 10], 255, "the sea where the layer says nothing");
        // The layer's land wins over a flat 0: a polder stored at 0 m.
        assert_eq!(water_mask(&vec![0.0; n * n], n, Some(&vec![0.0; n * n])), vec![0]);
        assert_eq!(water_mask(&h, n, Some(&vec![1.0; n * n])), vec![255]);
    }
}
