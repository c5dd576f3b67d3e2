//! The built-in sample terrain: a small procedural valley written as an original-engine
//! pyramid (texture + RGB-thirds elevation, metadata text), so that `terrastream demo` and
//! the tests need no downloaded data.

use std::f64::consts::PI;
use std::io::BufWriter;
use std::path::Path;

use terrastream_format::levels_to_one;

use crate::error::{Error, Result};

/// The built-in real DEM: 320 x 320 samples of SRTM 1 arc-second around Mt Tamalpais
/// (public domain; `data/README.md` beside this crate says how it was cut).
pub const TAMALPAIS_TIF: &[u8] = include_bytes!("../data/srtm-tamalpais-320-public-domain.tif");

/// Texture tiles across and down at LOD 0.
pub const TEXTURE_GRID: (u32, u32) = (8, 6);
/// Texture pixels per tile edge.
pub const TEXTURE_RES: u32 = 64;
/// World metres per LOD-0 texture tile.
pub const TEXTURE_TILE_SIZE: f64 = 100.0;
/// Elevation tiles across and down at LOD 0.
pub const ELEVATION_GRID: (u32, u32) = (2, 2);
/// Elevation pixels per tile edge.
pub const ELEVATION_RES: u32 = 128;
/// World metres per LOD-0 elevation tile.
pub const ELEVATION_TILE_SIZE: f64 = 400.0;
/// Height span of the RGB-thirds encoding.
pub const DISPLACEMENT: f64 = 500.0;
const LAKE_LEVEL: f64 = 120.0;

/// Height in metres at world (x, y); x east, y south, inside 800 x 600 m.
pub fn height(x: f64, y: f64) -> f64 {
    let ridge = 0.5 + 0.25 * (x * 0.008).sin() * (y * 0.011).cos();
    let hills = 0.15 * (x * 0.021 + y * 0.017).sin() + 0.1 * (x * 0.05).sin() * (y * 0.043).sin();
    // A basin in the south-west holds a lake.
    let d = ((x - 170.0).powi(2) + (y - 430.0).powi(2)).sqrt();
    let basin = if d < 160.0 { -0.9 * (0.5 + 0.5 * (d / 160.0 * PI).cos()) } else { 0.0 };
    (DISPLACEMENT * (ridge + hills + basin)).clamp(0.0, DISPLACEMENT)
}

fn world_size() -> (f64, f64) {
    (f64::from(TEXTURE_GRID.0) * TEXTURE_TILE_SIZE, f64::from(TEXTURE_GRID.1) * TEXTURE_TILE_SIZE)
}

#[expect(clippy::cast_possible_truncation, reason = "clamped to 0..=255 first")]
fn colour(x: f64, y: f64) -> [u8; 3] {
    let (w, h) = world_size();
    if x < 0.0 || y < 0.0 || x >= w || y >= h {
        return [0, 0, 0]; // padding beyond the dataset's extent
    }
    let z = height(x, y);
    if z < LAKE_LEVEL {
        return [38, 84, 140];
    }
    let e = 2.0;
    let (dx, dy) = (height(x + e, y) - height(x - e, y), height(x, y + e) - height(x, y - e));
    // Lambert shading with a sun from the north-west.
    let n = [-dx / (2.0 * e), -dy / (2.0 * e), 1.0];
    let len = (n[0] * n[0] + n[1] * n[1] + 1.0).sqrt();
    let light = ((-0.5 * n[0] - 0.5 * n[1] + 0.7 * n[2]) / len / 0.99).clamp(0.2, 1.0);
    let t = ((z - LAKE_LEVEL) / (DISPLACEMENT - LAKE_LEVEL)).clamp(0.0, 1.0);
    let base = if t < 0.45 {
        [70.0 + 60.0 * t, 120.0 + 40.0 * t, 50.0]
    } else if t < 0.8 {
        [130.0, 110.0, 80.0]
    } else {
        [235.0, 235.0, 240.0]
    };
    base.map(|c| (c * light).clamp(0.0, 255.0) as u8)
}

#[expect(clippy::cast_possible_truncation, reason = "clamped to 0..=765 first")]
fn rgb_thirds(h: f64) -> [u8; 3] {
    let v = (h / DISPLACEMENT * 765.0).round().clamp(0.0, 765.0) as u32;
    let third = |lo: u32| (v.saturating_sub(lo)).min(255) as u8;
    [third(0), third(255), third(510)]
}

fn write_png(path: &Path, size: u32, pixels: &[u8]) -> Result<()> {
    let file = std::fs::File::create(path).map_err(|e| Error::file(path, e))?;
    let mut encoder = png::Encoder::new(BufWriter::new(file), size, size);
    encoder.set_color(png::ColorType::Rgb);
    encoder.set_depth(png::BitDepth::Eight);
    let fail = |e: png::EncodingError| Error::input(path, e.to_string());
    let mut writer = encoder.write_header().map_err(fail)?;
    writer.write_image_data(pixels).map_err(fail)?;
    writer.finish().map_err(fail)
}

/// Writes one layer's pyramid: every LOD down to 1x1, tiles sampled from `pixel(x, y)`.
/// LOD-0 tiles for which `skip` says so are left missing (a sparse area).
fn write_layer(
    dir: &Path,
    grid: (u32, u32),
    res: u32,
    tile_size: f64,
    pixel: &dyn Fn(f64, f64) -> [u8; 3],
    skip: &dyn Fn(f64, f64, f64) -> bool,
) -> Result<u8> {
    let lods = levels_to_one(grid.0.max(grid.1));
    for lod in 0..lods {
        let scale = f64::from(1u32 << lod);
        let (nx, ny) = (grid.0.div_ceil(1 << lod), grid.1.div_ceil(1 << lod));
        let folder = dir.join(format!("LOD{lod}"));
        std::fs::create_dir_all(&folder).map_err(|e| Error::file(&folder, e))?;
        for ty in 0..ny {
            for tx in 0..nx {
                let size = tile_size * scale;
                let (x0, y0) = (f64::from(tx) * size, f64::from(ty) * size);
                if lod == 0 && skip(x0, y0, size) {
                    continue;
                }
                let step = size / f64::from(res);
                let mut pixels = Vec::with_capacity((res * res * 3) as usize);
                for py in 0..res {
                    for px in 0..res {
                        pixels.extend(pixel(x0 + (f64::from(px) + 0.5) * step, y0 + (f64::from(py) + 0.5) * step));
                    }
                }
                write_png(&folder.join(format!("{tx}_{ty}.png")), res, &pixels)?;
            }
        }
    }
    Ok(lods)
}

/// True when a square of world space lies entirely in the lake (sampled on a 9x9 grid).
fn all_lake(x0: f64, y0: f64, size: f64) -> bool {
    (0..=8)
        .all(|i| (0..=8).all(|j| height(x0 + size * f64::from(i) / 8.0, y0 + size * f64::from(j) / 8.0) < LAKE_LEVEL))
}

/// Writes the sample pyramid under `dir` (`textures/`, `elevations/`, `metadata.txt`).
///
/// # Errors
/// [`Error::File`] if `dir` is not writable.
pub fn write_sample_pyramid(dir: &Path) -> Result<()> {
    let texture_lods =
        write_layer(&dir.join("textures"), TEXTURE_GRID, TEXTURE_RES, TEXTURE_TILE_SIZE, &colour, &all_lake)?;
    let elevation_lods = write_layer(
        &dir.join("elevations"),
        ELEVATION_GRID,
        ELEVATION_RES,
        ELEVATION_TILE_SIZE,
        &|x, y| rgb_thirds(height(x, y)),
        &|_, _, _| false,
    )?;
    let spacing = ELEVATION_TILE_SIZE / f64::from(ELEVATION_RES);
    let text = format!(
        "public int TEXTURES_textureTileResolution = {TEXTURE_RES};
public int TEXTURES_numTextureLODS = {texture_lods};
public int TEXTURES_texturesNumXTiles = {};
public int TEXTURES_texturesNumYTiles = {};
public float TEXTURES_textureTileSize = {TEXTURE_TILE_SIZE}f;
public int TEXTURES_maxConsolidatedTextureResolution = 256;
public int ELEVATIONS_elevationTileResolution = {ELEVATION_RES};
public int ELEVATIONS_numElevationLODS = {elevation_lods};
public int ELEVATIONS_elevationsNumXTiles = {};
public int ELEVATIONS_elevationsNumYTiles = {};
public float ELEVATIONS_elevationTileSize = {ELEVATION_TILE_SIZE}f;
public double ELEVATIONS_displacement = {DISPLACEMENT};
public double ELEVATIONS_smoothingRange = 1.0f;
public double ELEVATIONS_minElevation = 0.0;
public double ELEVATIONS_maxElevation = {DISPLACEMENT};
public double ELEVATIONS_elevationRange = {DISPLACEMENT};
public float baseTileSize = {spacing}f;
public float highDetailRange = 50;
public int numDetailLevels = 8;
public string sampleName = \"terrastream procedural valley\";
",
        TEXTURE_GRID.0, TEXTURE_GRID.1, ELEVATION_GRID.0, ELEVATION_GRID.1,
    );
    let path = dir.join("metadata.txt");
    std::fs::write(&path, text).map_err(|e| Error::file(&path, e))
}
