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
