//! `terrastream pack x.mbtiles`: an MBTiles raster tileset (SQLite; PNG, JPEG or WebP
//! tiles, e.g. a Terrain-RGB DEM) into one layer of a tspack archive, tiles stored
//! unchanged.
//!
//! The file is opened read-only. Rows are checked as they are read: zoom within the
//! archive's LOD limit, column and row inside the zoom's grid (MBTiles rows count from the
//! south, TMS; they are flipped to XYZ), a non-empty blob in the tileset's format.

use std::path::Path;

use rusqlite::{Connection, OpenFlags, OptionalExtension};
use terrastream_format::{MAX_LODS, TileFormat};

use super::layers::{Opened, write_layers};
use super::xyz::{TilesetInput, WebTile, open_web_tiles};
use crate::error::{Error, Result};
use crate::progress::Progress;
use crate::writer::{WriteSummary, WriterOptions};

/// Packs an MBTiles raster tileset at `input` into a one-layer archive at `out`.
///
/// Zoom `z` becomes LOD `max_zoom - z` on the Web Mercator grid. The tile format is the
/// `metadata` table's `format` (png, jpg, webp) when there is one, else the first tile's.
///
/// # Errors
/// [`Error::Input`] naming the file and the table or tile at fault (not SQLite, no
/// `tiles` table, vector tiles, a tile outside its zoom's grid or in another format);
/// writer and I/O errors; [`Error::Interrupted`]. Nothing is written under `out` on error.
pub fn pack_mbtiles(
    input: &Path,
    options: TilesetInput,
    out: &Path,
    writer_options: WriterOptions,
    progress: &dyn Progress,
) -> Result<WriteSummary> {
    write_layers(vec![open_mbtiles(input, options, progress)?], out, writer_options, progress)
}

/// Opens an MBTiles raster tileset as one layer (see [`pack_mbtiles`]).
///
/// # Errors
/// As [`pack_mbtiles`], before any tile is read.
pub(crate) fn open_mbtiles(input: &Path, options: TilesetInput, progress: &dyn Progress) -> Result<Opened<'static>> {
    let sql = |e: rusqlite::Error| Error::input(input, format!("not a readable MBTiles file: {e}"));
    if !input.is_file() {
        return Err(Error::input(input, "no such file"));
    }
    let db = Connection::open_with_flags(input, OpenFlags::SQLITE_OPEN_READ_ONLY | OpenFlags::SQLITE_OPEN_NO_MUTEX)
        .map_err(sql)?;
    let format = format_of(&db).map_err(sql)?;
    let format = match format.as_deref().map(str::to_ascii_lowercase).as_deref() {
        None => None,
        Some("png") => Some(TileFormat::Png),
        Some("jpg" | "jpeg") => Some(TileFormat::Jpeg),
        Some("webp") => Some(TileFormat::Webp),
        Some("pbf" | "mvt") => {
            return Err(Error::input(input, "vector tiles (metadata format pbf): only raster MBTiles are packed"));
        }
        Some(other) => {
            return Err(Error::input(input, format!("metadata format {other:?}: only png, jpg or webp tiles")));
        }
    };
    let mut tiles = Vec::new();
    {
        let mut rows = db
            .prepare("SELECT zoom_level, tile_column, tile_row FROM tiles")
            .map_err(|e| Error::input(input, format!("no tiles table ({e}): not an MBTiles file")))?;
        let mut rows = rows.query([]).map_err(sql)?;
        while let Some(row) = rows.next().map_err(sql)? {
            if tiles.len() % 4096 == 0 {
                progress.check()?;
            }
            let (z, x, row_tms): (i64, i64, i64) =
                (row.get(0).map_err(sql)?, row.get(1).map_err(sql)?, row.get(2).map_err(sql)?);
            let z8 = u8::try_from(z).ok().filter(|&z| z < MAX_LODS).ok_or_else(|| {
                Error::input(input, format!("tile z{z} x{x} row {row_tms}: zoom outside 0..{MAX_LODS}"))
            })?;
            let side = 1i64 << z8;
            if !(0..side).contains(&x) || !(0..side).contains(&row_tms) {
                return Err(Error::input(
                    input,
                    format!("tile z{z} x{x} row {row_tms}: outside the {side}x{side} grid of zoom {z}"),
                ));
            }
            let (x, y) = (u32::try_from(x).unwrap_or(0), u32::try_from(side - 1 - row_tms).unwrap_or(0));
            tiles.push(WebTile { z: z8, x, y, at: (z, i64::from(x), row_tms) });
        }
    }
    let path = input.to_path_buf();
    let read = move |&(z, x, row): &(i64, i64, i64), what: &str| -> Result<bytes::Bytes> {
        let input = &path;
        let mut query = db
            .prepare_cached("SELECT tile_data FROM tiles WHERE zoom_level = ?1 AND tile_column = ?2 AND tile_row = ?3")
            .map_err(|e| Error::input(input, format!("not a readable MBTiles file: {e}")))?;
        let blob: Option<Vec<u8>> = query
            .query_row([z, x, row], |r| r.get::<_, Option<Vec<u8>>>(0))
            .optional()
            .map_err(|e| Error::input(input, format!("{what}: {e}")))?
            .flatten();
        match blob {
            Some(b) if !b.is_empty() => Ok(b.into()),
            _ => Err(Error::input(input, format!("{what}: empty tile_data"))),
        }
    };
    open_web_tiles(input, options, format, tiles, read)
}

/// The `metadata` table's `format`, when the table and the row exist.
fn format_of(db: &Connection) -> rusqlite::Result<Option<String>> {
    let has_table: bool = db.query_row(
        "SELECT EXISTS (SELECT 1 FROM sqlite_master WHERE name = 'metadata' AND type IN ('table', 'view'))",
        [],
        |r| r.get(0),
    )?;
    if !has_table {
        return Ok(None);
    }
    db.query_row("SELECT value FROM metadata WHERE name = 'format'", [], |r| r.get(0)).optional()
}

#[cfg(test)]
mod tests {
    #![allow(clippy::unwrap_used)]
    use super::*;
    use crate::progress::Silent;
    use terrastream_format::{ElevationScheme, LayerKind};
    use terrastream_format::{Reader, TileKey};

    fn png(v: u8) -> Vec<u8> {
        let mut out = Vec::new();
        let mut e = png::Encoder::new(&mut out, 4, 4);
        e.set_color(png::ColorType::Rgb);
        e.set_depth(png::BitDepth::Eight);
        e.write_header().unwrap().write_image_data(&[v; 48]).unwrap();
        out
    }

    /// An MBTiles file as tools write it: the normalized schema (`map` + `images`, `tiles`
    /// a view), TMS rows.
    fn write_mbtiles(path: &Path, format: Option<&str>, tiles: &[(i64, i64, i64, Vec<u8>)]) {
        let db = Connection::open(path).unwrap();
        db.execute_batch(
            "CREATE TABLE metadata (name TEXT, value TEXT);
             CREATE TABLE map (zoom_level INTEGER, tile_column INTEGER, tile_row INTEGER, tile_id TEXT);
             CREATE TABLE images (tile_data BLOB, tile_id TEXT);
             CREATE UNIQUE INDEX map_index ON map (zoom_level, tile_column, tile_row);
             CREATE VIEW tiles AS SELECT map.zoom_level AS zoom_level, map.tile_column AS tile_column,
               map.tile_row AS tile_row, images.tile_data AS tile_data
               FROM map JOIN images ON images.tile_id = map.tile_id;",
        )
        .unwrap();
        if let Some(f) = format {
            db.execute("INSERT INTO metadata VALUES ('format', ?1)", [f]).unwrap();
        }
        for (i, (z, x, row, data)) in tiles.iter().enumerate() {
            let id = format!("t{i}");
            db.execute("INSERT INTO map VALUES (?1, ?2, ?3, ?4)", rusqlite::params![z, x, row, id]).unwrap();
            db.execute("INSERT INTO images VALUES (?1, ?2)", rusqlite::params![data, id]).unwrap();
        }
    }

    #[test]
    fn tiles_land_on_the_web_mercator_grid_with_rows_flipped() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("dem.mbtiles");
        // z1: TMS row 1 is the north row = XYZ y 0.
        let tiles = vec![(0, 0, 0, png(9)), (1, 0, 1, png(1)), (1, 1, 0, png(2)), (1, 1, 1, png(3))];
        write_mbtiles(&path, Some("png"), &tiles);
        let out = dir.path().join("dem.tspack");
        let input = TilesetInput { kind: LayerKind::Elevation, elevation: Some(ElevationScheme::TerrainRgb) };
        let summary = pack_mbtiles(&path, input, &out, WriterOptions::default(), &Silent::default()).unwrap();
        assert_eq!(summary.addressed_tiles, 4);
        let reader = Reader::open_mmap(&out).unwrap();
        let layer = &reader.metadata().layers[0];
        assert_eq!((layer.num_lods, layer.num_x_tiles, layer.tile_resolution), (2, 2, 4));
        assert_eq!(layer.elevation.as_ref().unwrap().scheme, ElevationScheme::TerrainRgb);
        for (lod, x, y, want) in [(1u8, 0u32, 0u32, png(9)), (0, 0, 0, png(1)), (0, 1, 1, png(2)), (0, 1, 0, png(3))] {
            let got = reader.tile(TileKey::new(0, lod, x, y).unwrap()).unwrap().unwrap();
            assert_eq!(&got[..], &want[..], "lod {lod} ({x}, {y})");
        }
        assert!(reader.tile(TileKey::new(0, 0, 0, 1).unwrap()).unwrap().is_none());
    }

    #[test]
    fn bad_tilesets_are_named_and_nothing_is_written() {
        let dir = tempfile::tempdir().unwrap();
        let out = dir.path().join("out.tspack");
        let input = TilesetInput { kind: LayerKind::Texture, elevation: None };
        let fails = |path: &Path, needle: &str| {
            let err =
                pack_mbtiles(path, input, &out, WriterOptions::default(), &Silent::default()).unwrap_err().to_string();
            assert!(err.contains(&path.display().to_string()) && err.contains(needle), "{err}");
            assert!(!out.exists());
        };
        let not_sqlite = dir.path().join("text.mbtiles");
        std::fs::write(&not_sqlite, b"this is not a database, just some words long enough").unwrap();
        fails(&not_sqlite, "MBTiles");
        let no_tiles = dir.path().join("empty.mbtiles");
        Connection::open(&no_tiles).unwrap().execute_batch("CREATE TABLE other (a INTEGER);").unwrap();
        fails(&no_tiles, "no tiles table");
        let vector = dir.path().join("vector.mbtiles");
        write_mbtiles(&vector, Some("pbf"), &[(0, 0, 0, vec![1, 2, 3])]);
        fails(&vector, "vector tiles");
        let outside = dir.path().join("outside.mbtiles");
        write_mbtiles(&outside, Some("png"), &[(1, 2, 0, png(1))]);
        fails(&outside, "z1 x2 row 0: outside the 2x2 grid");
        let mixed = dir.path().join("mixed.mbtiles");
        write_mbtiles(&mixed, None, &[(1, 0, 0, png(1)), (1, 1, 0, b"GIF89a not a png".to_vec())]);
        fails(&mixed, "in a Png tileset");
        let none = dir.path().join("none.mbtiles");
        write_mbtiles(&none, Some("png"), &[]);
        fails(&none, "no tiles");
        fails(&dir.path().join("missing.mbtiles"), "no such file");
    }
}
