//! Web Mercator tiles written as one PMTiles v3 file (`export --to pmtiles --encoding`): a
//! `raster-dem` (or raster) source for MapLibre's pmtiles protocol, with no server.

use std::path::Path;

use terrastream_format::{Interrupted, MmapSource, Reader, zxy_to_tile_id};
pub use terrastream_pack::export::pmtiles::PmtilesSummary;

use crate::encode::{HeightEncoding, ImageFormat};
use crate::export::{ExportError, WebExport, make_tiles, planned_tiles};
use crate::tilejson::coverage;

/// Makes the web tiles `export` asks for and writes them, with their TileJSON-like
/// metadata, as a PMTiles file at `out` (temporary name, renamed when complete); `tick`
/// once before the tiles with their number, then after each tile with None.
///
/// # Errors
/// [`ExportError::NotPlaced`] for a layer without web tiles, a tile that cannot be made,
/// [`ExportError::Pmtiles`] when the file cannot be written.
pub fn export_web_pmtiles(
    reader: &Reader<MmapSource>,
    export: &WebExport,
    out: &Path,
    tick: &(dyn Fn(Option<u64>) -> Result<(), Interrupted> + Sync),
) -> Result<(PmtilesSummary, (u8, u8)), ExportError> {
    let (tiles, zooms) = planned_tiles(reader, export)?;
    tick(Some(tiles.len() as u64))?;
    let mut made = Vec::with_capacity(tiles.len());
    make_tiles(reader, export, &tiles, 0, &|| tick(None), &mut |tile, bytes| {
        made.push((zxy_to_tile_id(tile.z, tile.x, tile.y), bytes));
        Ok(())
    })?;
    made.sort_by_key(|(id, _)| *id);
    let meta = reader.metadata();
    let info = meta.layers.get(usize::from(export.layer)).ok_or(ExportError::NotPlaced)?;
    let cover = coverage(meta, info, export.size).ok_or(ExportError::NotPlaced)?;
    let metadata = serde_json::json!({
        "name": meta.name,
        "type": "baselayer",
        "format": export.format.extension(),
        "encoding": export.encoding.map(HeightEncoding::name),
        "tileSize": export.size,
        "minzoom": zooms.0,
        "maxzoom": zooms.1,
        "bounds": cover.bounds,
    });
    let tile_type = match export.format {
        ImageFormat::Png => 2,
        ImageFormat::Webp => 4,
    };
    let summary = terrastream_pack::export::pmtiles::write_pmtiles(out, &made, tile_type, cover.bounds, &metadata)
        .map_err(|e| ExportError::Pmtiles(Box::new(e)))?;
    Ok((summary, zooms))
}

/// Contour vector tiles (`export --to contours`) written as a PMTiles file of Mapbox
/// Vector Tiles (MapLibre's pmtiles protocol reads it as a vector source): zooms
/// `minzoom` to `maxzoom` (default: the elevation's finest) over the data; `tick` once
/// before the tiles with their number, then after each tile with None.
///
/// # Errors
/// [`ExportError::NotPlaced`] without placed elevation, a tile that cannot be made,
/// [`ExportError::Pmtiles`] when the file cannot be written.
pub fn export_contours_pmtiles(
    reader: &Reader<MmapSource>,
    options: crate::contours::ContourOptions,
    (minzoom, maxzoom): (u8, Option<u8>),
    out: &Path,
    tick: &(dyn Fn(Option<u64>) -> Result<(), Interrupted> + Sync),
) -> Result<(PmtilesSummary, (u8, u8)), ExportError> {
    let meta = reader.metadata();
    let index = meta
        .layers
        .iter()
        .position(|l| l.kind == terrastream_format::LayerKind::Elevation)
        .ok_or(ExportError::NotPlaced)?;
    let cover = coverage(meta, &meta.layers[index], 256).ok_or(ExportError::NotPlaced)?;
    let maxzoom = maxzoom.unwrap_or(cover.maxzoom);
    let minzoom = minzoom.min(maxzoom);
    let mut tiles = vec![];
    for z in minzoom..=maxzoom {
        let (columns, rows) = crate::mercator::tiles_over(z, cover.bounds);
        for y in rows {
            tiles.extend(columns.clone().filter_map(|x| crate::mercator::WebTile::new(z, x, y)));
        }
    }
    tick(Some(tiles.len() as u64))?;
    let decoded = crate::resample::DecodedCache::new(crate::resample::DECODED_BYTES);
    let make = |&tile: &crate::mercator::WebTile| {
        crate::contours::contour_tile(reader, tile, options, Some((&decoded, 0)))
            .map_err(|error| ExportError::Make { tile, error })
    };
    let mut made = Vec::with_capacity(tiles.len());
    crate::export::in_order(&tiles, 0, &make, &|| tick(None), &mut |tile, bytes| {
        made.push((zxy_to_tile_id(tile.z, tile.x, tile.y), bytes));
        Ok(())
    })?;
    made.sort_by_key(|(id, _)| *id);
    let mut metadata = crate::contours::tilejson(&meta.name, &meta.name, String::new(), cover);
    metadata["minzoom"] = minzoom.into();
    metadata["maxzoom"] = maxzoom.into();
    let summary = terrastream_pack::export::pmtiles::write_pmtiles(out, &made, 1, cover.bounds, &metadata)
        .map_err(|e| ExportError::Pmtiles(Box::new(e)))?;
    Ok((summary, (minzoom, maxzoom)))
}
