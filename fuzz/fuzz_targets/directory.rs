//! Any bytes as a directory, compressed or not. Must never panic or over-allocate.
#![no_main]

use libfuzzer_sys::fuzz_target;
use terrastream_format::{Compression, Directory};

fuzz_target!(|data: &[u8]| {
    let _ = Directory::decode_raw(data, "fuzz", 1 << 40, 1 << 40);
    let _ = Directory::decode(data, Compression::Zstd, "fuzz", 1 << 40, 1 << 40);
});
