//! Any bytes as a tile payload of every format of every layer kind the client decodes
//! (PNG, JPEG, WebP, raw u16/f32, BC1/BC7; texture and elevation in every encoding;
//! as stored: plain, zstd-wrapped, gradient-coded in zstd). `decode` must return a tile or
//! an error, never panic.
#![no_main]

use libfuzzer_sys::fuzz_target;
use terrastream_tiles::decode;
use terrastream_format::{ElevationEncoding, ElevationScheme, Layer, LayerKind, PayloadCompression, TileFormat, TileKey};

const FORMATS: [TileFormat; 7] = [
    TileFormat::Png,
    TileFormat::Jpeg,
    TileFormat::Webp,
    TileFormat::RawU16,
    TileFormat::RawF32,
    TileFormat::Bc1,
    TileFormat::Bc7,
];
const SCHEMES: [ElevationScheme; 6] = [
    ElevationScheme::Gray8,
    ElevationScheme::RgbThirds,
    ElevationScheme::TerrainRgb,
    ElevationScheme::Terrarium,
    ElevationScheme::QuantizedU16,
    ElevationScheme::Float32,
];

fuzz_target!(|data: &[u8]| {
    // The first byte picks the layer, the second the tile size, the third the payload
    // compression; the rest is the payload.
    let [pick, size, how, payload @ ..] = data else { return };
    let format = FORMATS[usize::from(pick % 7)];
    // A water layer's samples decode as heights do (the fraction of water).
    let kind = match (pick & 8 == 0, how & 4 == 0) {
        (true, _) => LayerKind::Texture,
        (false, true) => LayerKind::Elevation,
        (false, false) => LayerKind::Water,
    };
    let scheme = SCHEMES[usize::from((pick >> 4) % 6)];
    let compression = [PayloadCompression::None, PayloadCompression::Zstd, PayloadCompression::ZstdGradient]
        [usize::from(how % 3)];
    let layer = Layer {
        name: "fuzz".into(),
        kind,
        format,
        compression,
        tile_resolution: u32::from(size % 64) + 1,
        border: size >> 6,
        num_x_tiles: 1,
        num_y_tiles: 1,
        num_lods: 1,
        tile_world_size: 1.0,
        elevation: (kind != LayerKind::Texture).then_some(ElevationEncoding {
            scheme,
            scale: 1.0,
            offset: 0.0,
            nodata: Some(0.0),
        }),
        extent: None,
    };
    let key = TileKey::new(0, 0, 0, 0).expect("tile (0, 0) of LOD 0 exists");
    let _ = decode(&layer, key, payload, true);
    let _ = decode(&layer, key, payload, false);
});
