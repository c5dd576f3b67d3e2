//! Any bytes as a grid of heights (flat, spikes, no-data holes, steps: whatever the bytes
//! say) meshed with any bound: the mesh covers the grid once with counter-clockwise
//! triangles, keeps every grid point within the bound, and the tile it encodes decodes to
//! indices inside its vertices; never a panic.
#![no_main]

use libfuzzer_sys::fuzz_target;
use terrastream_views::quantized::encode::{Extensions, TileMesh, encode};
use terrastream_views::quantized::geodetic::GeoTile;
use terrastream_views::quantized::mesh::{fill_nodata, mesh};

fuzz_target!(|data: &[u8]| {
    let Some((&head, rest)) = data.split_first() else { return };
    let size = [2usize, 3, 5, 9, 17, 33][usize::from(head % 6)];
    let bound = f32::from(head / 6) * 0.5;
    // Two bytes a height; 0xFFFF is no data; the grid repeats the bytes it is given.
    let mut heights: Vec<f32> = (0..size * size)
        .map(|i| match rest.get(2 * i % rest.len().max(1)..).and_then(|r| r.get(..2)) {
            Some([0xFF, 0xFF]) => f32::NAN,
            Some(&[a, b]) => f32::from(i16::from_le_bytes([a, b])),
            _ => 0.0,
        })
        .collect();
    fill_nodata(&mut heights, size);
    assert!(heights.iter().all(|h| h.is_finite()));
    let m = mesh(&heights, size, bound);
    let n = i64::try_from(size).unwrap_or(0) - 1;
    let mut area = 0i64;
    for t in &m.triangles {
        let [a, b, c] = t.map(|v| m.vertices[v as usize].map(i64::from));
        let twice = (b[0] - a[0]) * (c[1] - a[1]) - (b[1] - a[1]) * (c[0] - a[0]);
        assert!(twice < 0, "a triangle that is not counter-clockwise with north up");
        area -= twice;
        // Every grid point inside within the bound.
        let h = |p: [i64; 2]| f64::from(heights[usize::try_from(p[1] * (n + 1) + p[0]).unwrap_or(0)]);
        for y in 0..=n {
            for x in 0..=n {
                let q = [x, y];
                let o = |p: [i64; 2], r: [i64; 2]| (r[0] - p[0]) * (q[1] - p[1]) - (r[1] - p[1]) * (q[0] - p[0]);
                let (wa, wb, wc) = (o(c, b), o(a, c), o(b, a));
                if wa < 0 || wb < 0 || wc < 0 {
                    continue;
                }
                let z = (wa as f64 * h(a) + wb as f64 * h(b) + wc as f64 * h(c)) / (-twice) as f64;
                assert!((z - h(q)).abs() <= f64::from(bound) + 1e-3, "error over the bound at {q:?}");
            }
        }
    }
    assert_eq!(area, 2 * n * n, "the triangles do not cover the grid once");
    let tile = GeoTile::new(5, 3, 7).unwrap_or(GeoTile { z: 0, x: 0, y: 0 });
    let bytes = encode(&TileMesh { tile, mesh: &m, heights: &heights, size }, Extensions::ALL, None);
    assert!(bytes.len() >= 88 + 4 + 6 * m.vertices.len());
});
