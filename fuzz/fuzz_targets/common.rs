//! What both reader targets do with bytes that open as an archive.

use terrastream_format::{MemorySource, Reader, TileKey, verify};

/// Opens, verifies, and looks tiles up (with coarser fallback); must never panic.
pub fn exercise(bytes: Vec<u8>) {
    let Ok(reader) = Reader::new(MemorySource::new(bytes)) else { return };
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
}
