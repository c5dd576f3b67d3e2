//! Any bytes as an archive: open, look every tile up, verify. Must never panic.
#![no_main]

use libfuzzer_sys::fuzz_target;
use terrastream_packer::{MemorySource, Reader, TileKey, verify};

fuzz_target!(|data: &[u8]| {
    let Ok(reader) = Reader::new(MemorySource::new(data.to_vec())) else { return };
    let _ = verify(&reader, |_| {});
    for (layer, l) in reader.metadata().layers.clone().iter().enumerate().take(4) {
        for lod in 0..l.num_lods.min(6) {
            let (nx, ny) = l.grid_at(lod);
            for y in 0..ny.min(8) {
                for x in 0..nx.min(8) {
                    if let Ok(key) = TileKey::new(layer as u8, lod, x, y) {
                        let _ = reader.tile_or_coarser(key);
                    }
                }
            }
        }
    }
});
