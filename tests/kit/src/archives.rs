//! Small archives written on the spot: the built-in sample, and a raw-u16 + zstd layer
//! whose every sample is known.

use std::path::{Path, PathBuf};

use terrastream_format::{Layer, LayerKind, Metadata, PayloadCompression, TileFormat, TileKey};
use terrastream_pack::import::{OriginalLayout, pack, scan_original};
use terrastream_pack::progress::Silent;
use terrastream_pack::sample::write_sample_pyramid;
use terrastream_pack::{Writer, WriterOptions};

/// The built-in sample terrain packed into an archive, in memory.
pub fn tiny_archive() -> Vec<u8> {
    let dir = tempfile::tempdir().unwrap();
    let input = dir.path().join("sample");
    write_sample_pyramid(&input).unwrap();
    let scanned = scan_original(&input, &OriginalLayout::default()).unwrap();
    let out = dir.path().join("sample.tspack");
    pack(scanned, &out, WriterOptions::default(), &Silent::default()).unwrap();
    std::fs::read(&out).unwrap()
}

/// A folder holding `sample.tspack` (the built-in sample) and `elev.tspack` (a zstd layer).
pub fn archives() -> (tempfile::TempDir, PathBuf) {
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("sample.tspack");
    std::fs::write(&path, tiny_archive()).unwrap();
    write_zstd_archive(&dir.path().join("elev.tspack"), 1);
    (dir, path)
}

/// A one-layer raw-u16 + zstd archive whose samples depend on `version`.
pub fn write_zstd_archive(path: &Path, version: u16) {
    write_u16_archive(path, version, PayloadCompression::Zstd);
}

/// [`write_zstd_archive`] with its tiles stored as `compression` says.
pub fn write_u16_archive(path: &Path, version: u16, compression: PayloadCompression) {
    let layer = Layer {
        name: "elevation".into(),
        kind: LayerKind::Elevation,
        format: TileFormat::RawU16,
        compression,
        tile_resolution: 16,
        border: 0,
        num_x_tiles: 2,
        num_y_tiles: 2,
        num_lods: 2,
        tile_world_size: 100.0,
        elevation: None,
        extent: None,
    };
    let meta = Metadata::new("elev", vec![layer]);
    let mut tiles: Vec<(u64, TileKey)> = [(1u8, 0u32, 0u32), (0, 0, 0), (0, 1, 0), (0, 1, 1)]
        .iter()
        .map(|&(lod, x, y)| {
            let t = TileKey::new(0, lod, x, y).unwrap();
            (Writer::order_key(&meta, t).unwrap(), t)
        })
        .collect();
    tiles.sort();
    let mut w = Writer::create(path, meta, WriterOptions::default()).unwrap();
    for (_, t) in tiles {
        w.add(t, raw_tile(t, version)).unwrap();
    }
    w.finish().unwrap();
}

/// The raw samples of a tile of [`write_zstd_archive`].
pub fn raw_tile(t: TileKey, version: u16) -> Vec<u8> {
    (0..256u16).flat_map(|i| (i + u16::from(t.lod()) * 7 + version * 1000).to_le_bytes()).collect()
}

/// A texture layer of `tiles` (across, down) LOD-0 PNG tiles of 64 pixels, no border,
/// `num_lods` levels, each LOD-0 tile `tile_world_size` world units a side.
pub fn png_texture_layer(tiles: (u32, u32), num_lods: u8, tile_world_size: f64) -> Layer {
    Layer {
        name: "texture".into(),
        kind: LayerKind::Texture,
        format: TileFormat::Png,
        compression: PayloadCompression::None,
        tile_resolution: 64,
        border: 0,
        num_x_tiles: tiles.0,
        num_y_tiles: tiles.1,
        num_lods,
        tile_world_size,
        elevation: None,
        extent: None,
    }
}

/// A `size` x `size` RGB PNG checkered in 8-pixel squares of `rgb` and `dark`, starting
/// with `rgb` at the top left: a tile whose placement and LOD show in a render.
pub fn checkered_png(size: u32, rgb: [u8; 3], dark: [u8; 3]) -> Vec<u8> {
    let mut out = Vec::new();
    let mut encoder = png::Encoder::new(&mut out, size, size);
    encoder.set_color(png::ColorType::Rgb);
    let pixels: Vec<u8> = (0..size * size)
        .flat_map(|i| if (i % size / 8 + i / size / 8).is_multiple_of(2) { rgb } else { dark })
        .collect();
    encoder.write_header().unwrap().write_image_data(&pixels).unwrap();
    out
}

/// Every tile's stored payload of the archive at `path`, by key (for comparing two
/// archives' tiles whatever their layout).
///
/// # Panics
/// When the archive cannot be read.
pub fn stored_tiles(path: &Path) -> std::collections::BTreeMap<TileKey, Vec<u8>> {
    let mut out = std::collections::BTreeMap::new();
    terrastream_format::Reader::open_mmap(path)
        .unwrap_or_else(|e| panic!("{}: {e}", path.display()))
        .for_each_tile(|key, payload| -> terrastream_format::Result<()> {
            out.insert(key, payload.to_vec());
            Ok(())
        })
        .unwrap_or_else(|e| panic!("{}: {e}", path.display()));
    out
}
