//! `terrastream pack x.pmtiles`: a PMTiles v3 raster archive (PNG, JPEG or WebP tiles, e.g.
//! a Terrain-RGB DEM tileset) into one layer of a tspack archive, tiles stored unchanged.
//!
//! Everything read from the file is untrusted: the header's sections must lie inside the
//! file, directories are decompressed with a size cap, entry counts are bounded by the
//! directory's bytes, leaf pointers must lie in the leaf section and may nest at most
//! [`MAX_DEPTH`] deep, and every tile's range must lie in the tile-data section.

use std::io::Read;
use std::path::Path;

use terrastream_format::{Cursor, FileSource, MAX_LODS, RangeSource, TileFormat, tile_id_to_zxy};

use super::layers::{Opened, write_layers};
use super::xyz::{TilesetInput, WebTile, open_web_tiles};
use crate::error::{Error, Result};
use crate::progress::Progress;
use crate::writer::{WriteSummary, WriterOptions};

/// Leaf directories nest at most this deep (the reference writer uses one level).
pub const MAX_DEPTH: usize = 4;
/// Largest decompressed directory accepted.
const MAX_DIRECTORY: u64 = 64 << 20;

struct Header {
    root: (u64, u64),
    leaves: (u64, u64),
    data: (u64, u64),
    internal_compression: u8,
    tile_compression: u8,
    tile_type: u8,
}

/// `[offset, offset + len)` of the input; out of the file is an error naming `what`.
fn read_at(file: &FileSource, path: &Path, (offset, len): (u64, u64), what: &str) -> Result<bytes::Bytes> {
    file.read_range(offset, len).map_err(|e| Error::input(path, format!("{what}: {e}")))
}

fn header(file: &FileSource, path: &Path) -> Result<Header> {
    let bad = |why: &str| Error::input(path, format!("PMTiles header: {why}"));
    let h = read_at(file, path, (0, 127), "the header").map_err(|_| bad("shorter than 127 bytes"))?;
    if &h[..7] != b"PMTiles" {
        return Err(bad("not a PMTiles file (bad magic)"));
    }
    if h[7] != 3 {
        return Err(bad(&format!("version {} (only v3 is read)", h[7])));
    }
    let u64_at = |i: usize| u64::from_le_bytes(h[i..i + 8].try_into().unwrap_or([0; 8]));
    let header = Header {
        root: (u64_at(8), u64_at(16)),
        leaves: (u64_at(40), u64_at(48)),
        data: (u64_at(56), u64_at(64)),
        internal_compression: h[97],
        tile_compression: h[98],
        tile_type: h[99],
    };
    // Every section inside the file: offsets within a section then never overflow.
    let size = file.len();
    for (name, (offset, len)) in
        [("root directory", header.root), ("leaf section", header.leaves), ("tile data", header.data)]
    {
        if offset.checked_add(len).is_none_or(|end| end > size) {
            return Err(bad(&format!("{name} [{offset}, +{len}) outside the {size}-byte file")));
        }
    }
    Ok(header)
}

fn decompress(bytes: &[u8], compression: u8, path: &Path, what: &str) -> Result<Vec<u8>> {
    let bad = |why: String| Error::input(path, format!("{what}: {why}"));
    match compression {
        0 | 1 => Ok(bytes.to_vec()),
        2 => {
            let mut out = Vec::new();
            flate2::read::GzDecoder::new(bytes)
                .take(MAX_DIRECTORY + 1)
                .read_to_end(&mut out)
                .map_err(|e| bad(format!("gzip: {e}")))?;
            if out.len() as u64 > MAX_DIRECTORY {
                return Err(bad(format!("over {MAX_DIRECTORY} bytes decompressed")));
            }
            Ok(out)
        }
        4 => terrastream_format::zstd_decompress(bytes, MAX_DIRECTORY, what).map_err(|e| bad(e.to_string())),
        3 => Err(bad("brotli compression is not supported (recompress with gzip or zstd)".into())),
        other => Err(bad(format!("unknown compression {other}"))),
    }
}

/// (tile id, run length, offset, length); run length 0 points at a leaf directory.
fn directory(bytes: &[u8], path: &Path, what: &str) -> Result<Vec<(u64, u64, u64, u64)>> {
    let mut c = Cursor::new(bytes, what);
    let bad = |why: String| Error::input(path, format!("{what}: {why}"));
    let n = c.varint().map_err(|e| bad(e.to_string()))?;
    // Each entry takes at least 4 bytes of varints.
    if n > bytes.len() as u64 / 4 + 1 {
        return Err(bad(format!("{n} entries in {} bytes", bytes.len())));
    }
    let n = usize::try_from(n).map_err(|_| bad("too many entries".into()))?;
    let v = |c: &mut Cursor| c.varint().map_err(|e| bad(e.to_string()));
    let mut ids = Vec::with_capacity(n);
    let mut last = 0u64;
    for _ in 0..n {
        last = last.checked_add(v(&mut c)?).ok_or_else(|| bad("tile id overflows".into()))?;
        ids.push(last);
    }
    let runs = (0..n).map(|_| v(&mut c)).collect::<Result<Vec<_>>>()?;
    let lengths = (0..n).map(|_| v(&mut c)).collect::<Result<Vec<_>>>()?;
    let mut out: Vec<(u64, u64, u64, u64)> = Vec::with_capacity(n);
    for i in 0..n {
        let raw = v(&mut c)?;
        let offset = if raw == 0 {
            let Some(prev) = out.last() else { return Err(bad("first entry has offset 0 (contiguous)".into())) };
            prev.2.checked_add(prev.3).ok_or_else(|| bad("offset overflows".into()))?
        } else {
            raw - 1
        };
        out.push((ids[i], runs[i], offset, lengths[i]));
    }
    Ok(out)
}

/// Packs a PMTiles v3 raster archive at `input` into a one-layer archive at `out`: zoom
/// `z` becomes LOD `max_zoom - z` on the Web Mercator grid, tiles stored unchanged, runs
/// of one tile expanded (the writer stores the content once).
///
/// # Errors
/// [`Error::Input`] naming the file and the header, directory or tile at fault; writer
/// and I/O errors; [`Error::Interrupted`]. Nothing is written under `out` on error.
pub fn pack_pmtiles(
    input: &Path,
    options: TilesetInput,
    out: &Path,
    writer_options: WriterOptions,
    progress: &dyn Progress,
) -> Result<WriteSummary> {
    write_layers(vec![open_pmtiles(input, options, progress)?], out, writer_options, progress)
}

/// Opens a PMTiles v3 raster archive as one layer (see [`pack_pmtiles`]).
///
/// # Errors
/// As [`pack_pmtiles`], before any tile is read.
pub(crate) fn open_pmtiles(input: &Path, options: TilesetInput, progress: &dyn Progress) -> Result<Opened<'static>> {
    let file = FileSource::open(input)?;
    let h = header(&file, input)?;
    let format = match h.tile_type {
        2 => TileFormat::Png,
        3 => TileFormat::Jpeg,
        4 => TileFormat::Webp,
        1 => return Err(Error::input(input, "vector tiles (MVT): only raster PMTiles are packed")),
        other => return Err(Error::input(input, format!("tile type {other}: only PNG, JPEG or WebP tiles"))),
    };
    if !matches!(h.tile_compression, 0 | 1) {
        return Err(Error::input(
            input,
            format!("tile compression {}: raster tiles must be stored as they are", h.tile_compression),
        ));
    }
    // Every tile entry, leaves followed (bounded depth, each leaf inside the leaf section).
    let mut tiles: Vec<(u64, u64, u64, u64)> = Vec::new();
    let mut pending = vec![(h.root, 0usize, "root directory".to_owned())];
    while let Some((range, depth, what)) = pending.pop() {
        progress.check()?;
        let stored = read_at(&file, input, range, &what)?;
        let bytes = decompress(&stored, h.internal_compression, input, &what)?;
        for e in directory(&bytes, input, &what)? {
            if e.1 > 0 {
                tiles.push(e);
                continue;
            }
            if depth + 1 > MAX_DEPTH {
                return Err(Error::input(input, format!("{what}: leaf directories nest deeper than {MAX_DEPTH}")));
            }
            if e.2.checked_add(e.3).is_none_or(|end| end > h.leaves.1) {
                return Err(Error::input(input, format!("{what}: leaf [{}, +{}) outside the leaf section", e.2, e.3)));
            }
            pending.push(((h.leaves.0 + e.2, e.3), depth + 1, format!("leaf directory at {}", e.2)));
        }
    }
    // Tiles by key; zooms and coordinates checked.
    let mut keyed: Vec<WebTile<(u64, u64)>> = Vec::new();
    for &(id, run, offset, len) in &tiles {
        if offset.checked_add(len).is_none_or(|end| end > h.data.1) || len == 0 || len > u64::from(u32::MAX) {
            return Err(Error::input(input, format!("tile {id}: data [{offset}, +{len}) outside the tile data")));
        }
        let last = id.checked_add(run - 1).ok_or_else(|| Error::input(input, format!("tile {id}: run overflows")))?;
        if run > 1 << 24 || tile_id_to_zxy(last).0 >= MAX_LODS {
            return Err(Error::input(input, format!("tile {id}: run of {run} or zoom beyond {MAX_LODS} levels")));
        }
        for t in id..=last {
            let (z, x, y) = tile_id_to_zxy(t);
            keyed.push(WebTile { z, x, y, at: (h.data.0 + offset, len) });
        }
    }
    let path = input.to_path_buf();
    let read = move |&(offset, len): &(u64, u64), what: &str| read_at(&file, &path, (offset, len), what);
    open_web_tiles(input, options, Some(format), keyed, read)
}

#[cfg(test)]
mod tests {
    #![allow(clippy::unwrap_used)]
    use super::*;
    use crate::export::pmtiles::export_pmtiles;
    use crate::progress::Silent;
    use terrastream_format::LayerKind;
    use terrastream_format::{Reader, TileKey};

    #[test]
    fn an_exported_pmtiles_packs_back_to_the_same_tiles_and_bad_files_are_named() {
        let dir = tempfile::tempdir().unwrap();
        let archive = dir.path().join("a.tspack");
        std::fs::write(&archive, terrastream_testkit::archives::tiny_archive()).unwrap();
        let reader = Reader::open_mmap(&archive).unwrap();
        let texture = reader.metadata().layer_index("texture").unwrap();
        let pm = dir.path().join("a.pmtiles");
        export_pmtiles(&reader, texture, &pm, &Silent::default()).unwrap();
        let out = dir.path().join("b.tspack");
        let options = TilesetInput { kind: LayerKind::Texture, elevation: None };
        pack_pmtiles(&pm, options, &out, WriterOptions::default(), &Silent::default()).unwrap();
        let back = Reader::open_mmap(&out).unwrap();
        let (a, b) = (&reader.metadata().layers[usize::from(texture)], &back.metadata().layers[0]);
        assert_eq!((b.format, b.tile_resolution), (a.format, a.tile_resolution));
        let mut n = 0;
        for lod in 0..a.num_lods {
            for key in a.tiles_at(texture, lod) {
                let Some(want) = reader.tile(key).unwrap() else { continue };
                // The PMTiles grid is the Web Mercator one: same LOD, same x and y.
                let got = back.tile(TileKey::new(0, lod, key.x(), key.y()).unwrap()).unwrap().unwrap();
                assert_eq!(got, want, "{key}");
                n += 1;
            }
        }
        assert!(n > 3, "{n} tiles compared");

        // Damage: bad magic, a root directory past the end, a truncated file.
        let bytes = std::fs::read(&pm).unwrap();
        let cases: [(&str, Vec<u8>, &str); 4] = [
            ("magic.pmtiles", [b"PMTilez".as_slice(), &bytes[7..]].concat(), "bad magic"),
            (
                "root.pmtiles",
                {
                    let mut b = bytes.clone();
                    b[8..16].copy_from_slice(&u64::MAX.to_le_bytes());
                    b
                },
                "root directory",
            ),
            ("cut.pmtiles", bytes[..bytes.len() - 10].to_vec(), "outside"),
            // Found by fuzzing: a leaf section offset near u64::MAX overflowed offset + entry.
            (
                "leaves.pmtiles",
                {
                    let mut b = bytes.clone();
                    b[40..48].copy_from_slice(&(u64::MAX - 7).to_le_bytes());
                    b
                },
                "leaf section",
            ),
        ];
        for (name, damaged, expect) in cases {
            let path = dir.path().join(name);
            std::fs::write(&path, damaged).unwrap();
            let out = dir.path().join(format!("{name}.tspack"));
            let e = pack_pmtiles(&path, options, &out, WriterOptions::default(), &Silent::default()).unwrap_err();
            let e = e.to_string();
            assert!(e.contains(name) && e.contains(expect), "{name}: {e}");
            assert!(!out.exists());
        }
    }
}
