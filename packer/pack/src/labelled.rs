//! Labelled archives: every texture tile is one colour that says which tile it is, and
//! every elevation sample lies on a known plane, so a client can check each tile it shows.
//! `terrastream bench stream` streams them; the tests check what clients show against them.

use std::path::Path;

use crate::error::Error;
use crate::writer::{WriteSummary, Writer, WriterOptions};
use terrastream_format::{
    ElevationEncoding, ElevationScheme, Layer, LayerKind, Metadata, PayloadCompression, TileFormat, TileKey,
    levels_to_one,
};

/// A synthetic archive whose every tile says what it is: texture tiles are one solid
/// colour encoding `(x, y, lod, version)` ([`label_colour`]) and elevation tiles sample a
/// tilted plane ([`label_height`]), so a client can check that each tile it shows is the
/// right one, from the right version, and that bilinear height queries are exact.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct LabelledSpec {
    /// Texture tiles across and down at LOD 0 (at most 256).
    pub texture_grid: u32,
    /// Texture pixels per tile edge.
    pub texture_res: u32,
    /// World metres per LOD-0 texture tile.
    pub texture_tile_size: f64,
    /// Elevation tiles across and down at LOD 0.
    pub elevation_grid: u32,
    /// Elevation samples per tile edge.
    pub elevation_res: u32,
    /// Written into every tile, so two versions of the archive differ everywhere.
    pub version: u8,
    /// LOD-0 texture tiles at `x >= sparse_from` (and coarser tiles over only those) are
    /// left missing, but for the last column's LOD-0 tiles: the data's box spans the grid,
    /// so readers look for the missing tiles inside it.
    pub sparse_from: Option<u32>,
}

impl Default for LabelledSpec {
    fn default() -> Self {
        Self {
            texture_grid: 32,
            texture_res: 16,
            texture_tile_size: 50.0,
            elevation_grid: 8,
            elevation_res: 16,
            version: 1,
            sparse_from: None,
        }
    }
}

/// Colour of every pixel of texture tile `(lod, x, y)` in a [`LabelledSpec`] archive.
#[expect(clippy::cast_possible_truncation, reason = "grids are at most 256 tiles across; lod < 16")]
pub fn label_colour(lod: u8, x: u32, y: u32, version: u8) -> [u8; 3] {
    [x as u8, y as u8, lod * 16 + (version & 15)]
}

/// Height at ground point `(x, z)` (x east, z south) of a [`LabelledSpec`] archive.
pub fn label_height(x: f64, z: f64, version: u8) -> f64 {
    100.0 * f64::from(version) + 0.05 * x + 0.02 * z
}

/// Writes a [`LabelledSpec`] archive to `path`.
///
/// # Errors
/// Writer and I/O errors.
pub fn write_labelled_archive(path: &Path, spec: &LabelledSpec) -> Result<WriteSummary, Error> {
    let metadata = labelled_metadata(spec);
    let mut tiles = Vec::new();
    for (index, layer) in (0u8..).zip(&metadata.layers) {
        for key in (0..layer.num_lods).flat_map(|lod| layer.tiles_at(index, lod)) {
            let last_column = key.lod() == 0 && key.x() + 1 == layer.num_x_tiles;
            if index == 0
                && !last_column
                && spec.sparse_from.is_some_and(|s| u64::from(key.x()) << key.lod() >= u64::from(s))
            {
                continue;
            }
            tiles.push((Writer::order_key(&metadata, key)?, key));
        }
    }
    tiles.sort_unstable();
    let mut writer = Writer::create(path, metadata.clone(), WriterOptions::default())?;
    for (_, key) in tiles {
        let layer = &metadata.layers[usize::from(key.layer())];
        let payload = if key.layer() == 0 {
            label_png(path, key, layer.tile_resolution, spec.version)?
        } else {
            label_heights(key, layer, spec.version)
        };
        writer.add(key, payload)?;
    }
    writer.finish()
}

/// The labelled archive's metadata: a texture layer and an elevation layer over one square.
fn labelled_metadata(spec: &LabelledSpec) -> Metadata {
    let world = f64::from(spec.texture_grid) * spec.texture_tile_size;
    let texture = Layer {
        name: "texture".into(),
        kind: LayerKind::Texture,
        format: TileFormat::Png,
        compression: PayloadCompression::None,
        tile_resolution: spec.texture_res,
        border: 0,
        num_x_tiles: spec.texture_grid,
        num_y_tiles: spec.texture_grid,
        num_lods: levels_to_one(spec.texture_grid),
        tile_world_size: spec.texture_tile_size,
        elevation: None,
        extent: None,
    };
    let elevation = Layer {
        name: "elevation".into(),
        kind: LayerKind::Elevation,
        format: TileFormat::RawF32,
        compression: PayloadCompression::Zstd,
        tile_resolution: spec.elevation_res,
        border: 0,
        num_x_tiles: spec.elevation_grid,
        num_y_tiles: spec.elevation_grid,
        num_lods: levels_to_one(spec.elevation_grid),
        tile_world_size: world / f64::from(spec.elevation_grid),
        elevation: Some(ElevationEncoding { scheme: ElevationScheme::Float32, scale: 1.0, offset: 0.0, nodata: None }),
        extent: None,
    };
    let mut metadata = Metadata::new(format!("labelled v{}", spec.version), vec![texture, elevation]);
    let (lo, hi) = (label_height(0.0, 0.0, spec.version), label_height(world, world, spec.version));
    metadata.terrain.min_elevation = lo;
    metadata.terrain.max_elevation = hi;
    metadata.terrain.displacement = hi - lo;
    metadata.terrain.elevation_range = hi - lo;
    metadata.terrain.base_tile_size = metadata.layers[1].tile_world_size / f64::from(spec.elevation_res);
    metadata
}

/// A texture tile of one colour, the label of its key.
fn label_png(path: &Path, key: TileKey, res: u32, version: u8) -> Result<Vec<u8>, Error> {
    let pixels = label_colour(key.lod(), key.x(), key.y(), version).repeat((res * res) as usize);
    let mut png_bytes = Vec::new();
    let mut encoder = png::Encoder::new(&mut png_bytes, res, res);
    encoder.set_color(png::ColorType::Rgb);
    encoder.set_depth(png::BitDepth::Eight);
    let fail = |e: png::EncodingError| Error::input(path, format!("{key}: {e}"));
    let mut png_writer = encoder.write_header().map_err(fail)?;
    png_writer.write_image_data(&pixels).map_err(fail)?;
    drop(png_writer);
    Ok(png_bytes)
}

/// An elevation tile of the label heights, as f32 samples.
fn label_heights(key: TileKey, layer: &Layer, version: u8) -> Vec<u8> {
    let res = layer.tile_resolution;
    let size = layer.world_size_at(key.lod());
    let step = size / f64::from(res);
    let (x0, z0) = (f64::from(key.x()) * size, f64::from(key.y()) * size);
    let mut raw = Vec::with_capacity((res * res * 4) as usize);
    for j in 0..res {
        for i in 0..res {
            let h = label_height(x0 + (f64::from(i) + 0.5) * step, z0 + (f64::from(j) + 0.5) * step, version);
            #[expect(clippy::cast_possible_truncation, reason = "stored as f32 by design")]
            raw.extend_from_slice(&(h as f32).to_le_bytes());
        }
    }
    raw
}
