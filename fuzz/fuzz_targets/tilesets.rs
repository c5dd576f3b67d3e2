//! Any bytes as a PMTiles tileset packed into an archive: header sections, directories,
//! leaves and tile ranges are all untrusted. Must never panic, and must leave no archive
//! behind when it fails.
#![no_main]

use libfuzzer_sys::fuzz_target;
use terrastream_format::LayerKind;
use terrastream_pack::WriterOptions;
use terrastream_pack::import::{TilesetInput, pack_pmtiles};
use terrastream_pack::progress::Silent;

fuzz_target!(|data: &[u8]| {
    let dir = std::env::temp_dir().join(format!("terrastream-fuzz-tilesets-{}", std::process::id()));
    let _ = std::fs::create_dir_all(&dir);
    let (input, out) = (dir.join("input.pmtiles"), dir.join("out.tspack"));
    let _ = std::fs::remove_file(&out);
    if std::fs::write(&input, data).is_err() {
        return;
    }
    let options = TilesetInput { kind: LayerKind::Texture, elevation: None };
    if pack_pmtiles(&input, options, &out, WriterOptions::default(), &Silent::default()).is_err() {
        assert!(!out.exists(), "a failed pack left {}", out.display());
    }
});
