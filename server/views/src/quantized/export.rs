//! Quantized-mesh terrain written for static hosting (`terrastream export --to
//! quantized-mesh`): `layer.json` and the `{z}/{x}/{y}.terrain` tree, gzipped, with every
//! extension offered: bit for bit what the server sends a client that asks for them all.

use std::path::Path;
use std::sync::atomic::{AtomicUsize, Ordering};

use terrastream_format::{Interrupted, MmapSource, Reader};

use super::encode::Extensions;
use super::geodetic::GeoTile;
use super::{Terrain, gzip};
use crate::export::{ExportError, WebExportSummary, file_err, in_order, publish, stage};
use crate::resample::{DECODED_BYTES, DecodedCache};

/// Writes the archive's terrain in `dir`, levels `minzoom` to `maxzoom` (default: the
/// terrain's deepest); `tick(done, total)` after each tile. Written into a temporary
/// folder beside `dir` and renamed once complete.
///
/// # Errors
/// [`ExportError::NotPlaced`] for an archive without placed elevation; a tile that cannot
/// be made; [`ExportError::File`] naming a file that cannot be written.
pub fn export_quantized_mesh(
    reader: &Reader<MmapSource>,
    dir: &Path,
    minzoom: u8,
    maxzoom: Option<u8>,
    tick: &(dyn Fn(u64, u64) -> Result<(), Interrupted> + Sync),
) -> Result<WebExportSummary, ExportError> {
    let decoded = DecodedCache::new(DECODED_BYTES);
    let terrain = Terrain::new(reader, Some((&decoded, 0))).ok_or(ExportError::NotPlaced)?;
    let maxzoom = maxzoom.unwrap_or(terrain.maxzoom()).min(terrain.maxzoom());
    let minzoom = minzoom.min(maxzoom);
    let mut tiles = vec![];
    for z in minzoom..=maxzoom {
        let Some(ranges) = terrain.available(z) else { continue };
        let mut level: Vec<GeoTile> = vec![];
        for ([x0, x1], [y0, y1]) in ranges {
            for y in y0..=y1 {
                level.extend((x0..=x1).filter_map(|x| GeoTile::new(z, x, y)));
            }
        }
        // Rectangles of one level may overlap: each tile once.
        level.sort_by_key(|t| (t.y, t.x));
        level.dedup();
        tiles.extend(level);
    }
    let temp = stage(dir)?;
    let mut summary = WebExportSummary { zooms: (minzoom, maxzoom), ..WebExportSummary::default() };
    let done = AtomicUsize::new(0);
    let total = tiles.len() as u64;
    let count = || tick(done.fetch_add(1, Ordering::Relaxed) as u64 + 1, total);
    let make = |&tile: &GeoTile| {
        let made = terrain.tile(tile, Extensions::ALL).map_err(|error| ExportError::Terrain { tile, error })?;
        Ok(made.map(|bytes| gzip(&bytes)))
    };
    in_order::<GeoTile, ExportError>(&tiles, 0, &make, &count, &mut |tile, bytes| {
        let folder = temp.path().join(tile.z.to_string()).join(tile.x.to_string());
        std::fs::create_dir_all(&folder).map_err(file_err(&folder))?;
        let path = folder.join(format!("{}.terrain", tile.y));
        std::fs::write(&path, &bytes).map_err(file_err(&path))?;
        summary.tiles += 1;
        summary.bytes += bytes.len() as u64;
        Ok(())
    })?;
    let name = reader.metadata().name.clone();
    let mut doc = terrain.layer_json(&name, &name, "{z}/{x}/{y}.terrain");
    doc["minzoom"] = minzoom.into();
    doc["maxzoom"] = maxzoom.into();
    if let Some(levels) = doc["available"].as_array_mut() {
        levels.truncate(usize::from(maxzoom) + 1);
    }
    let path = temp.path().join("layer.json");
    std::fs::write(&path, serde_json::to_vec_pretty(&doc).unwrap_or_default()).map_err(file_err(&path))?;
    publish(temp, dir)?;
    Ok(summary)
}
