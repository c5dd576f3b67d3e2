//! Heights between samples: which tile of which LOD holds a ground point, and the height
//! there by nearest, bilinear or bicubic interpolation over decoded tiles, no-data aware.

use terrastream_format::{Layer, TileKey};

use crate::decode::DecodedTile;

/// How a height between samples is made from the samples around it.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub enum Interpolation {
    /// The nearest sample's.
    Nearest,
    /// Bilinear over the four around it (no-data corners drop out and the others are
    /// re-weighted): what the renderer draws.
    #[default]
    Bilinear,
    /// Bicubic (Keys, a = -0.5) over the sixteen around it; bilinear where one of them
    /// has no data.
    Cubic,
}

/// The height at ground position `(x, z)` (world units) on `lod` of elevation layer
/// `info` (index `layer`), sample `i` of the LOD at `(i + 0.5)` spacings, as the renderer
/// samples; `tile` gives the decoded tiles (a neighbour it does not give is clamped to
/// the tile under the point). `None` where that tile is not given or the data has no
/// value. The one height query of the client (`Streamer::height_at`) and the server's
/// elevation API.
pub fn height_on_lod<T: std::ops::Deref<Target = DecodedTile>>(
    info: &Layer,
    layer: u8,
    lod: u8,
    x: f64,
    z: f64,
    interpolation: Interpolation,
    tile: impl Fn(TileKey) -> Option<T>,
) -> Option<f64> {
    let res = info.tile_resolution;
    let spacing = info.sample_spacing(lod);
    let (nx, ny) = info.grid_at(lod);
    let home = tile_of(info, layer, lod, x, z)?;
    let (gx, gz) = (x / spacing - 0.5, z / spacing - 0.5);
    let (i0, j0) = (gx.floor(), gz.floor());
    let (fx, fz) = (gx - i0, gz - j0);
    let max_i = f64::from(nx) * f64::from(res) - 1.0;
    let max_j = f64::from(ny) * f64::from(res) - 1.0;
    let sample = |i: f64, j: f64| -> Option<f64> {
        #[expect(clippy::cast_possible_truncation, reason = "clamped into the grid's u32 range")]
        let (i, j) = (i.clamp(0.0, max_i) as u32, j.clamp(0.0, max_j) as u32);
        let key = TileKey::new(layer, lod, i / res, j / res).ok()?;
        let (t, li, lj) = match tile(key) {
            Some(t) => (t, i % res, j % res),
            // Neighbour not given: clamp to the home tile's edge.
            None => {
                let t = tile(home)?;
                let clamp = |g: u32, t0: u32| g.clamp(t0 * res, t0 * res + res - 1) - t0 * res;
                (t, clamp(i, home.x()), clamp(j, home.y()))
            }
        };
        let v = t.height(li + t.border, lj + t.border)?;
        v.is_finite().then_some(f64::from(v))
    };
    match interpolation {
        Interpolation::Nearest => sample((gx + 0.5).floor(), (gz + 0.5).floor()),
        Interpolation::Cubic => cubic(&sample, (i0, j0), (fx, fz)).or_else(|| bilinear(&sample, (i0, j0), (fx, fz))),
        Interpolation::Bilinear => bilinear(&sample, (i0, j0), (fx, fz)),
    }
}

/// Bilinear over the four samples from `(i0, j0)`: no-data corners drop out and the
/// others are re-weighted.
fn bilinear(sample: &dyn Fn(f64, f64) -> Option<f64>, (i0, j0): (f64, f64), (fx, fz): (f64, f64)) -> Option<f64> {
    let corners = [
        (sample(i0, j0), (1.0 - fx) * (1.0 - fz)),
        (sample(i0 + 1.0, j0), fx * (1.0 - fz)),
        (sample(i0, j0 + 1.0), (1.0 - fx) * fz),
        (sample(i0 + 1.0, j0 + 1.0), fx * fz),
    ];
    let (sum, weight) =
        corners.iter().filter_map(|(v, w)| v.map(|v| (v * w, *w))).fold((0.0, 0.0), |(s, ws), (v, w)| (s + v, ws + w));
    (weight > 1e-12).then(|| sum / weight)
}

/// Bicubic (Keys' kernel, a = -0.5) over the sixteen samples around `(i0, j0)`; None when
/// one of them has no data.
fn cubic(sample: &dyn Fn(f64, f64) -> Option<f64>, (i0, j0): (f64, f64), (fx, fz): (f64, f64)) -> Option<f64> {
    let weights = |t: f64| {
        let k = |d: f64| {
            let d = d.abs();
            if d <= 1.0 {
                1.5 * d * d * d - 2.5 * d * d + 1.0
            } else if d < 2.0 {
                -0.5 * d * d * d + 2.5 * d * d - 4.0 * d + 2.0
            } else {
                0.0
            }
        };
        [k(1.0 + t), k(t), k(1.0 - t), k(2.0 - t)]
    };
    let (wx, wz) = (weights(fx), weights(fz));
    let mut sum = 0.0;
    for (dj, wj) in (-1..=2).zip(wz) {
        for (di, wi) in (-1..=2).zip(wx) {
            sum += sample(i0 + f64::from(di), j0 + f64::from(dj))? * wi * wj;
        }
    }
    Some(sum)
}

/// The tile of layer `info` (index `layer`) at `lod` holding ground point `(x, z)`.
pub fn tile_of(info: &Layer, layer: u8, lod: u8, x: f64, z: f64) -> Option<TileKey> {
    let size = info.world_size_at(lod);
    let (tx, tz) = ((x / size).floor(), (z / size).floor());
    let (nx, ny) = info.grid_at(lod);
    if !(tx >= 0.0 && tz >= 0.0 && tx < f64::from(nx) && tz < f64::from(ny)) {
        return None;
    }
    #[expect(clippy::cast_possible_truncation, reason = "checked against the grid above")]
    TileKey::new(layer, lod, tx as u32, tz as u32).ok()
}
