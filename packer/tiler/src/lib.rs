//! Source rasters -> a LOD pyramid in an archive (`terrastream tile`).
//!
//! Inputs are read a band of rows at a time ([`raster`]): an elevation raster (GeoTIFF of
//! numbers, or a PNG whose pixels encode heights), an optional texture image, or a texture
//! alone. Each is resampled along x to square samples in metres when its pixels are more
//! than 1 % from square (a geographic raster is converted to metres at its centre
//! latitude), then streamed through a [`pyramid::Pyramid`]: LOD 0 keeps the source's
//! spacing; each coarser LOD averages 2x2 of the previous one (ignoring nodata for heights,
//! weighted by alpha for imagery); odd edges are padded with no data; tiles that hold only
//! no data are left missing. Only a band of rows per level is held, so memory does not grow
//! with the raster's height; it grows with its width (about `2 x width x (tile + 2 x
//! border + 1)` samples for all levels together) and with the tile count (the spool's index,
//! 24 bytes a tile).
//!
//! Elevation is stored losslessly (quantized u16 with a power-of-two step that keeps integer
//! sources exact at LOD 0, or f32; zstd) beside a height-range layer: each elevation tile's
//! lowest and highest height, for culling before the tile is loaded. Imagery is stored as
//! PNG, JPEG, lossless WebP, or GPU-ready BC1/BC7 blocks (zstd).

mod bc;
mod collection;
mod edit;
mod encode;
mod error;
mod options;
mod phases;
mod plan;
pub mod pyramid;
mod request;
mod shard;
mod tile;
mod water;

pub use collection::{
    Blend, Collection, CollectionInput, Collections, DEFAULT_BLEND, PlannedCollection, RunInputs, SparseLevel,
    aligned_grid, collection_shard_plan, depth_of, tile_collection,
};
pub use edit::manifest::{ManifestSummary, merge_to_manifest, single_manifest, write_manifest};
pub use edit::merge::{MergeSummary, Prefer, merge, merge_with, merge_with_water};
pub use edit::update::{UpdateSummary, update};
pub use error::{Error, Result};
pub use options::{ElevationStorage, ShardSpec, TextureFormat, TextureInput, TileOptions};
pub use plan::{LayerPlan, Plan, plan, plan_layout, squared_grid, squared_texture_grid};
pub use request::{Inputs, Sources, TileRequest};
pub use shard::{PlannedGrid, ShardInputs, ShardPlan, shard_plan};
pub use terrastream_format::Interrupted;
/// The raster reading this crate tiles from, re-exported so that a caller needs one crate.
pub use terrastream_raster::{
    self as raster, Crs, ElevationFile, ElevationSource, GridSpec, Heights, Image, ImageFile, ImageSource, ImageWindow,
    InputLayout, KnownRange, Mosaic, MosaicKind, MosaicOptions, OPEN_FILES, Pixels, Raster, Transform, Vrt, VrtSource,
    Warped, crs, expand_inputs, image_pixel_metres, is_vrt, jpeg_rows, open_elevation, open_image, read_geotiff,
    read_image, read_vrt, vrt_files_by_resolution,
};
pub use tile::{tile_elevation, tile_shard, tile_terrain};
pub use water::{ALL_WATER, KNOT, NO_WATER_DATA, WATER_LAYER, WaterSummary, add_water, water_encoding};

#[cfg(test)]
mod tests;
