//! Any bytes as a manifest (FORMAT.md §9): parsed and validated; an accepted one routes
//! keys and checks archives without panicking, and never routes a tile to two archives
//! or outside the one it names.
#![no_main]

use libfuzzer_sys::fuzz_target;
use terrastream_format::{Manifest, TileKey};

fuzz_target!(|data: &[u8]| {
    let Ok(manifest) = Manifest::from_json(data) else { return };
    for (i, layer) in manifest.metadata.layers.iter().enumerate() {
        let index = u8::try_from(i).unwrap_or(0);
        for lod in 0..layer.num_lods.min(6) {
            let (nx, ny) = layer.grid_at(lod);
            for (x, y) in [(0, 0), (nx - 1, ny - 1), (nx / 2, ny / 3)] {
                let Ok(key) = TileKey::new(index, lod, x, y) else { continue };
                if let Some(route) = manifest.route(key) {
                    let part = &manifest.archives[route.part];
                    assert!(part.layers.iter().any(|l| l.index == route.key.layer() && l.name == layer.name));
                    assert_eq!((route.key.lod(), route.key.x(), route.key.y()), (lod, x, y));
                }
            }
        }
    }
    let header = [0u8; 128];
    for i in 0..manifest.archives.len().min(4) {
        let _ = manifest.check_part(i, &header, &manifest.metadata);
        let _ = manifest.resolve("http://h/m.json", i);
    }
    let _ = Manifest::from_json(&manifest.to_json()).expect("a manifest written back reads back");
});
