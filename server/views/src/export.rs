//! The web tiles of a layer written for static hosting: an XYZ tree and its TileJSON
//! (`terrastream export --to xyz`), bit for bit the tiles the server makes.

use std::path::{Path, PathBuf};

use std::sync::atomic::{AtomicBool, AtomicUsize, Ordering};

use terrastream_format::{Interrupted, MmapSource, Reader};

use crate::encode::{HeightEncoding, ImageFormat};
use crate::mercator::{WebTile, tiles_over};
use crate::relief::{Product, ReliefOptions, ReliefRequest, relief_tile};
use crate::resample::MakeError;
use crate::resample::{DECODED_BYTES, DecodedCache};
use crate::tilejson::{TileJsonRequest, coverage, tilejson};
use crate::xyz::{WebTileRequest, make_tile_cached};

/// What to export.
#[derive(Clone, Debug)]
pub struct WebExport {
    /// The layer.
    pub layer: u8,
    /// Heights' encoding (elevation layers).
    pub encoding: Option<HeightEncoding>,
    /// The tiles' format.
    pub format: ImageFormat,
    /// Pixels a side.
    pub size: u32,
    /// The coarsest zoom written.
    pub minzoom: u8,
    /// The finest zoom written (default: the layer's, as its TileJSON says).
    pub maxzoom: Option<u8>,
    /// A map made from the elevation instead of the layer's own samples, with its
    /// `gdaldem` parameters.
    pub relief: Option<(Product, ReliefOptions)>,
}

/// Why an export failed.
#[derive(Debug, thiserror::Error)]
pub enum ExportError {
    /// A tile could not be made.
    #[error("tile {z}/{x}/{y}: {error}", z = .tile.z, x = .tile.x, y = .tile.y)]
    Make {
        /// The tile.
        tile: WebTile,
        /// Why.
        error: MakeError,
    },
    /// A terrain tile could not be made.
    #[error("terrain tile {z}/{x}/{y}: {error}", z = .tile.z, x = .tile.x, y = .tile.y)]
    Terrain {
        /// The tile.
        tile: crate::quantized::geodetic::GeoTile,
        /// Why.
        error: MakeError,
    },
    /// A base URL that is not an absolute http(s) URL.
    #[error(
        "--base-url {base_url:?}: the absolute URL the folder will be served at (https://host/path/): TileJSON \
         needs absolute tile URLs, and MapLibre resolves relative ones against the page, not tiles.json"
    )]
    BaseUrl {
        /// What was given.
        base_url: String,
    },
    /// The layer does not say where it lies (or is not heights or images).
    #[error(
        "the layer has no web tiles: the archive does not say where it lies, or its tiles are not heights or images"
    )]
    NotPlaced,
    /// Writing a file failed.
    #[error("{path}: {error}")]
    File {
        /// The file.
        path: PathBuf,
        /// The error.
        error: std::io::Error,
    },
    /// Stopped on request.
    #[error(transparent)]
    Interrupted(#[from] Interrupted),
    /// The PMTiles file could not be written (the writer's error names it).
    #[error(transparent)]
    Pmtiles(Box<dyn std::error::Error + Send + Sync>),
}

/// What an export wrote.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub struct WebExportSummary {
    /// Tiles with data, written.
    pub tiles: u64,
    /// Tiles without data, left out.
    pub empty: u64,
    /// Bytes of the tiles.
    pub bytes: u64,
    /// The zooms written.
    pub zooms: (u8, u8),
}

/// The tiles an export makes, zoom by zoom: those over the layer's bounds.
///
/// # Errors
/// [`ExportError::NotPlaced`] for a layer without web tiles.
pub fn planned_tiles(reader: &Reader<MmapSource>, export: &WebExport) -> Result<(Vec<WebTile>, (u8, u8)), ExportError> {
    let metadata = reader.metadata();
    let info = metadata.layers.get(usize::from(export.layer)).ok_or(ExportError::NotPlaced)?;
    let cover = coverage(metadata, info, export.size).ok_or(ExportError::NotPlaced)?;
    let maxzoom = export.maxzoom.unwrap_or(cover.maxzoom);
    let minzoom = export.minzoom.min(maxzoom);
    let mut tiles = Vec::new();
    for z in minzoom..=maxzoom {
        let (columns, rows) = tiles_over(z, cover.bounds);
        for y in rows {
            for x in columns.clone() {
                tiles.extend(WebTile::new(z, x, y));
            }
        }
    }
    Ok((tiles, (minzoom, maxzoom)))
}

/// Makes `tiles` on `threads` threads (0: the cores) and hands each with data to `each`
/// in the order given; `tick` is called after each tile (its error stops the export).
///
/// # Errors
/// The first tile that cannot be made, `each`'s or `tick`'s error.
pub fn make_tiles(
    reader: &Reader<MmapSource>,
    export: &WebExport,
    tiles: &[WebTile],
    threads: usize,
    tick: &(dyn Fn() -> Result<(), Interrupted> + Sync),
    each: &mut dyn FnMut(WebTile, Vec<u8>) -> Result<(), ExportError>,
) -> Result<(), ExportError> {
    // Neighbouring web tiles sample the same archive tiles: decode each once, as the
    // server does.
    let decoded = DecodedCache::new(DECODED_BYTES);
    let make = |&tile: &WebTile| {
        if let Some((product, options)) = &export.relief {
            let (format, size, options) = (export.format, export.size, options.clone());
            let request = ReliefRequest { product: *product, tile, format, size, options };
            return relief_tile(reader, &request, Some((&decoded, 0)))
                .map_err(|error| ExportError::Make { tile, error });
        }
        let request = WebTileRequest {
            layer: export.layer,
            tile,
            encoding: export.encoding,
            format: export.format,
            size: export.size,
        };
        make_tile_cached(reader, &request, Some((&decoded, 0))).map_err(|error| ExportError::Make { tile, error })
    };
    in_order(tiles, threads, &make, tick, each)
}

/// A made file's bytes, None when it holds no data.
pub type Made<E> = Result<Option<Vec<u8>>, E>;

/// Makes each of `items` on `threads` threads (0: the cores) and hands those with data to
/// `each` in the order given; `tick` is called after each (its error stops the work).
///
/// # Errors
/// The first item that cannot be made, `each`'s or `tick`'s error.
pub fn in_order<T: Copy + Sync, E: From<Interrupted> + Send>(
    items: &[T],
    threads: usize,
    make: &(dyn Fn(&T) -> Made<E> + Sync),
    tick: &(dyn Fn() -> Result<(), Interrupted> + Sync),
    each: &mut dyn FnMut(T, Vec<u8>) -> Result<(), E>,
) -> Result<(), E> {
    let threads = if threads == 0 { std::thread::available_parallelism().map_or(2, usize::from) } else { threads };
    let next = AtomicUsize::new(0);
    let (sender, receiver) = std::sync::mpsc::sync_channel::<(usize, Made<E>)>(4 * threads);
    let failed = AtomicBool::new(false);
    std::thread::scope(|scope| -> Result<(), E> {
        for _ in 0..threads {
            let (sender, next, failed) = (sender.clone(), &next, &failed);
            scope.spawn(move || {
                loop {
                    let i = next.fetch_add(1, Ordering::Relaxed);
                    if i >= items.len() || failed.load(Ordering::Relaxed) {
                        return;
                    }
                    if sender.send((i, make(&items[i]))).is_err() {
                        return;
                    }
                }
            });
        }
        drop(sender);
        // Taken in order: a reorder buffer of what arrived early.
        let mut early = std::collections::BTreeMap::new();
        let mut want = 0;
        let result = (|| {
            for (i, made) in receiver.iter() {
                early.insert(i, made);
                while let Some(made) = early.remove(&want) {
                    if let Some(bytes) = made? {
                        each(items[want], bytes)?;
                    }
                    tick()?;
                    want += 1;
                }
            }
            Ok(())
        })();
        if result.is_err() {
            failed.store(true, Ordering::Relaxed);
            // Let the threads finish their item and see the flag.
            for _ in receiver.iter() {}
        }
        result
    })
}

/// Writes layer `export.layer` as an XYZ tree in `dir` (`{z}/{x}/{y}.{ext}`, tiles
/// without data left out, as the server answers 404 for them) and `dir/tiles.json`,
/// whose tile URLs are absolute, under `base_url` (the URL the folder will be served at:
/// TileJSON 3.0.0 asks for absolute URLs, and MapLibre resolves relative ones against the
/// page, not the document). Written into a temporary folder beside `dir` and renamed once
/// complete.
///
/// # Errors
/// [`ExportError::BaseUrl`] for a base URL that is not absolute; as [`make_tiles`];
/// [`ExportError::File`] naming a file that cannot be written.
pub fn export_xyz(
    reader: &Reader<MmapSource>,
    export: &WebExport,
    dir: &Path,
    base_url: &str,
    tick: &(dyn Fn(u64, u64) -> Result<(), Interrupted> + Sync),
) -> Result<WebExportSummary, ExportError> {
    if !(base_url.starts_with("https://") || base_url.starts_with("http://")) || base_url.contains(['?', '#', ' ']) {
        return Err(ExportError::BaseUrl { base_url: base_url.to_owned() });
    }
    let (tiles, zooms) = planned_tiles(reader, export)?;
    let temp = stage(dir)?;
    let mut summary = WebExportSummary { zooms, ..WebExportSummary::default() };
    let extension = export.format.extension();
    let done = AtomicUsize::new(0);
    let total = tiles.len() as u64;
    let count = || {
        let n = done.fetch_add(1, Ordering::Relaxed) as u64 + 1;
        tick(n, total)
    };
    make_tiles(reader, export, &tiles, 0, &count, &mut |tile, bytes| {
        let folder = temp.path().join(tile.z.to_string()).join(tile.x.to_string());
        std::fs::create_dir_all(&folder).map_err(file_err(&folder))?;
        let path = folder.join(format!("{}.{extension}", tile.y));
        std::fs::write(&path, &bytes).map_err(file_err(&path))?;
        summary.tiles += 1;
        summary.bytes += bytes.len() as u64;
        Ok(())
    })?;
    summary.empty = total - summary.tiles;
    let metadata = reader.metadata();
    let info = &metadata.layers[usize::from(export.layer)];
    let mut cover = coverage(metadata, info, export.size).ok_or(ExportError::NotPlaced)?;
    cover.maxzoom = zooms.1;
    let base = format!("{}/", base_url.trim_end_matches('/'));
    let shown = export.relief.as_ref().map_or(info.name.as_str(), |(p, _)| p.name());
    let request = TileJsonRequest {
        name: &metadata.name,
        layer: shown,
        tiles: format!("{base}{{z}}/{{x}}/{{y}}.{extension}"),
        encoding: export.encoding,
        format: export.format,
        size: export.size,
    };
    let mut doc = tilejson(metadata, info, &request, cover);
    doc["minzoom"] = zooms.0.into();
    let json_path = temp.path().join("tiles.json");
    let text = serde_json::to_vec_pretty(&doc).unwrap_or_default();
    std::fs::write(&json_path, text).map_err(file_err(&json_path))?;
    publish(temp, dir)?;
    Ok(summary)
}

/// The error of a file that could not be written.
pub(crate) fn file_err(path: &Path) -> impl FnOnce(std::io::Error) -> ExportError + use<> {
    let path = path.to_path_buf();
    move |error| ExportError::File { path, error }
}

/// A temporary folder beside `dir` to write an export into.
///
/// # Errors
/// [`ExportError::File`] when it cannot be made.
pub(crate) fn stage(dir: &Path) -> Result<tempfile::TempDir, ExportError> {
    let parent = dir.parent().filter(|p| !p.as_os_str().is_empty()).unwrap_or(Path::new("."));
    std::fs::create_dir_all(parent).map_err(file_err(parent))?;
    tempfile::Builder::new().prefix(".export-").suffix(".partial").tempdir_in(parent).map_err(file_err(parent))
}

/// Puts a complete export in `dir`'s place.
///
/// # Errors
/// [`ExportError::File`] when the old folder cannot be removed or the new renamed.
pub(crate) fn publish(temp: tempfile::TempDir, dir: &Path) -> Result<(), ExportError> {
    if dir.exists() {
        std::fs::remove_dir_all(dir).map_err(file_err(dir))?;
    }
    let kept = temp.keep();
    std::fs::rename(&kept, dir).map_err(file_err(dir))
}
