//! Any bytes as a JPEG read by rows (`jpeg_rows`, what reads a JPEG too large to decode
//! whole): must never panic, every row as wide as the frame says, and no allocation from a
//! size the file claims beyond one row of MCUs.
#![no_main]

use libfuzzer_sys::fuzz_target;

fuzz_target!(|data: &[u8]| {
    let dir = std::env::temp_dir().join(format!("terrastream-fuzz-jpeg-{}", std::process::id()));
    let _ = std::fs::create_dir_all(&dir);
    let path = dir.join("input.jpg");
    if std::fs::write(&path, data).is_err() {
        return;
    }
    let mut width = None;
    let mut rows = 0usize;
    let _ = terrastream_raster::jpeg_rows(&path, &mut |row| {
        assert_eq!(row.len() % 3, 0);
        assert_eq!(*width.get_or_insert(row.len()), row.len());
        rows += 1;
        if rows >= 4096 { Err(terrastream_raster::Error::Interrupted(terrastream_format::Interrupted)) } else { Ok(()) }
    });
});
