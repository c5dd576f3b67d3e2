//! `terrastream pack`: existing tile pyramids into one archive.
//!
//! PMTiles v3 ([`pack_pmtiles`]) and MBTiles ([`pack_mbtiles`]) raster tilesets are read
//! directly. Two folder layouts:
//! the original engine's folders (`LOD0`, `LOD1`, ... with a metadata
//! text of C# field declarations) and XYZ / TMS trees addressed by a path template such as
//! `{z}/{x}/{y}.png`. Both importers first scan the tree (names only), then stream the
//! files in archive order into a [`Writer`]; tile bytes are stored unchanged so that
//! `extract` gives back the same files.

mod heights;
mod layers;
mod mbtiles;
mod opaque;
pub(crate) mod original;
mod pixels;
mod pmtiles;
mod scan;
mod xyz;

use std::path::{Path, PathBuf};

use rayon::prelude::*;

pub use layers::{LayerInput, PyramidSource, pack_layers};
pub use mbtiles::pack_mbtiles;
pub use original::{LAYOUT_KEY, LayerNaming, LayoutRecord, OriginalLayout, scan_original};
pub use pmtiles::pack_pmtiles;
pub use xyz::{Scheme, TilesetInput, XYZ_KEY, XyzOptions, XyzRecord, fill_template, scan_xyz};

use crate::error::{Error, Result};
use crate::progress::Progress;
use crate::writer::{WriteSummary, Writer, WriterOptions};
use scan::TileScan;
use terrastream_format::TileKey;
use terrastream_format::{Metadata, TileFormat};

/// A scanned input: the metadata to write and every tile file, in archive order.
#[derive(Debug)]
pub struct ScannedPyramid {
    /// Metadata of the archive to write.
    pub metadata: Metadata,
    /// (tile, file) in archive order.
    pub tiles: Vec<(TileKey, PathBuf)>,
}

impl ScannedPyramid {
    /// Sorts `tiles` into archive order; rejects tiles outside their layer's grid and
    /// two files for one tile.
    pub(crate) fn new(metadata: Metadata, tiles: Vec<(TileKey, PathBuf)>) -> Result<Self> {
        metadata.validate()?;
        let mut keyed = Vec::with_capacity(tiles.len());
        for (tile, path) in tiles {
            let key = Writer::order_key(&metadata, tile).map_err(|e| Error::input(&path, e.to_string()))?;
            keyed.push((key, tile, path));
        }
        keyed.sort_unstable_by_key(|(key, ..)| *key);
        if let Some(pair) = keyed.windows(2).find(|w| w[0].0 == w[1].0) {
            return Err(Error::input(&pair[1].2, format!("same tile ({}) as {}", pair[1].1, pair[0].2.display())));
        }
        Ok(Self { metadata, tiles: keyed.into_iter().map(|(_, t, p)| (t, p)).collect() })
    }
}

/// Files read in parallel per step (bounded memory: one chunk of tiles at a time).
const READ_CHUNK: usize = 256;

/// Streams the scanned tiles into an archive at `out`.
///
/// Every file is sniffed: all tiles of a layer must be in the layer's format.
///
/// # Errors
/// [`Error::Input`] naming a bad file, [`Error::Interrupted`] on cancel (nothing is written
/// under `out`), I/O errors.
pub fn pack(
    scanned: ScannedPyramid,
    out: &Path,
    options: WriterOptions,
    progress: &dyn Progress,
) -> Result<WriteSummary> {
    let mut scan = TileScan::new(&scanned.metadata, scanned.tiles.iter().map(|t| t.0));
    let mut writer = Writer::create(out, scanned.metadata, options)?;
    progress.start("pack", scanned.tiles.len() as u64);
    for chunk in scanned.tiles.chunks(READ_CHUNK) {
        progress.check()?;
        let formats: Vec<TileFormat> =
            chunk.iter().map(|(t, _)| writer.metadata().layers[usize::from(t.layer())].format).collect();
        let read = chunk
            .par_iter()
            .zip(formats.par_iter())
            .map(|((_, path), &format)| read_tile(path, format))
            .collect::<Result<Vec<Vec<u8>>>>()?;
        let batch: Vec<(TileKey, &[u8])> = chunk.iter().zip(&read).map(|((t, _), b)| (*t, b.as_slice())).collect();
        scan.scan(writer.metadata(), &batch).map_err(|(i, why)| Error::input(&chunk[i].1, why))?;
        for ((tile, _), bytes) in chunk.iter().zip(read) {
            writer.add_stored(*tile, bytes)?;
        }
        progress.advance(chunk.len() as u64);
    }
    progress.check()?;
    scan.record(&mut writer)?;
    writer.finish()
}

pub(crate) fn read_tile(path: &Path, format: TileFormat) -> Result<Vec<u8>> {
    let bytes = std::fs::read(path).map_err(|e| Error::file(path, e))?;
    match TileFormat::sniff(&bytes) {
        Some(found) if found == format => Ok(bytes),
        Some(found) => Err(Error::input(path, format!("{found:?} tile in a layer of {format:?} tiles"))),
        None => Err(Error::input(path, "not a PNG, JPEG or WebP image")),
    }
}

/// The two integers at the end of a file stem, and the text around them:
/// `tile_12_7` gives (`tile_`, 12, `_`, 7, ``).
pub(crate) fn split_stem(stem: &str) -> Option<(String, u32, String, u32, String)> {
    let groups: Vec<(usize, usize)> = {
        let mut out = Vec::new();
        let mut start = None;
        for (i, c) in stem.char_indices() {
            match (c.is_ascii_digit(), start) {
                (true, None) => start = Some(i),
                (false, Some(s)) => {
                    out.push((s, i));
                    start = None;
                }
                _ => {}
            }
        }
        if let Some(s) = start {
            out.push((s, stem.len()));
        }
        out
    };
    let [.., (a0, a1), (b0, b1)] = groups[..] else {
        return None;
    };
    Some((
        stem[..a0].to_owned(),
        stem[a0..a1].parse().ok()?,
        stem[a1..b0].to_owned(),
        stem[b0..b1].parse().ok()?,
        stem[b1..].to_owned(),
    ))
}

/// Width and height from a PNG or JPEG header.
pub(crate) fn image_size(bytes: &[u8]) -> Option<(u32, u32)> {
    match TileFormat::sniff(bytes)? {
        TileFormat::Png if bytes.len() >= 24 => {
            let w = u32::from_be_bytes(bytes[16..20].try_into().ok()?);
            let h = u32::from_be_bytes(bytes[20..24].try_into().ok()?);
            Some((w, h))
        }
        TileFormat::Jpeg => {
            // Walk the markers to the first start-of-frame.
            let mut i = 2usize;
            while i + 9 < bytes.len() {
                if bytes[i] != 0xff {
                    return None;
                }
                let marker = bytes[i + 1];
                let len = usize::from(u16::from_be_bytes([bytes[i + 2], bytes[i + 3]]));
                if matches!(marker, 0xc0..=0xc3 | 0xc5..=0xc7 | 0xc9..=0xcb | 0xcd..=0xcf) {
                    let h = u16::from_be_bytes([bytes[i + 5], bytes[i + 6]]);
                    let w = u16::from_be_bytes([bytes[i + 7], bytes[i + 8]]);
                    return Some((u32::from(w), u32::from(h)));
                }
                i = i.checked_add(2 + len)?;
            }
            None
        }
        _ => None,
    }
}

/// Every regular file under `dir`, recursively, sorted (deterministic scans).
pub(crate) fn walk_files(dir: &Path) -> Result<Vec<PathBuf>> {
    let mut out = Vec::new();
    let mut stack = vec![dir.to_path_buf()];
    while let Some(d) = stack.pop() {
        for entry in std::fs::read_dir(&d).map_err(|e| Error::file(&d, e))? {
            let entry = entry.map_err(|e| Error::file(&d, e))?;
            let path = entry.path();
            let ty = entry.file_type().map_err(|e| Error::file(&path, e))?;
            if ty.is_dir() {
                stack.push(path);
            } else if ty.is_file() {
                out.push(path);
            }
        }
    }
    out.sort();
    Ok(out)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn splits_common_tile_names() {
        assert_eq!(split_stem("12_7"), Some((String::new(), 12, "_".into(), 7, String::new())));
        assert_eq!(split_stem("tile_x3-y4_tex"), Some(("tile_x".into(), 3, "-y".into(), 4, "_tex".into())));
        assert_eq!(split_stem("lod2_10_11"), Some(("lod2_".into(), 10, "_".into(), 11, String::new())));
        assert_eq!(split_stem("tile7"), None);
    }
}
