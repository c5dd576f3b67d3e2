//! Any bytes as a `zstd_gradient` tile: as a zstd frame (`payload_bytes`, which must return
//! the samples or an error, never panic or inflate past a tile), and as the planes
//! themselves, which must decode to samples that code back to the same planes.
#![no_main]

use libfuzzer_sys::fuzz_target;
use terrastream_format::{
    Layer, LayerKind, PayloadCompression, TileFormat, gradient_decode, gradient_encode, payload_bytes,
};

fuzz_target!(|data: &[u8]| {
    // The first byte picks the tile's edge (1..=64 samples, border included).
    let [size, payload @ ..] = data else { return };
    let layer = Layer {
        name: "fuzz".into(),
        kind: LayerKind::Elevation,
        format: TileFormat::RawU16,
        compression: PayloadCompression::ZstdGradient,
        tile_resolution: u32::from(size % 64) + 1,
        border: 0,
        num_x_tiles: 1,
        num_y_tiles: 1,
        num_lods: 1,
        tile_world_size: 1.0,
        elevation: None,
        extent: None,
    };
    let edge = layer.stored_edge();
    if let Ok(samples) = payload_bytes(&layer, payload, "fuzz") {
        assert_eq!(samples.len(), 2 * edge * edge);
    }
    // Planes of any content are some grid's coding: decoding and coding again is exact.
    let planes: Vec<u8> = payload.iter().copied().cycle().take(2 * edge * edge).collect();
    if planes.len() == 2 * edge * edge {
        let samples = gradient_decode(&planes, edge, "fuzz").expect("planes of the right size decode");
        assert_eq!(gradient_encode(&samples, edge), planes);
    }
});
