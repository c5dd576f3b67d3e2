//! Any bytes as an archive, with the header, metadata and root checksums recomputed after
//! mutation, so that the fuzzer gets past them into metadata, directory and leaf parsing.
#![no_main]

mod common;

use libfuzzer_sys::fuzz_target;
use terrastream_format::crc32c;

fn u64_at(b: &[u8], at: usize) -> u64 {
    u64::from_le_bytes(b[at..at + 8].try_into().unwrap_or([0; 8]))
}

fn section(b: &[u8], at: usize) -> Option<std::ops::Range<usize>> {
    let start = usize::try_from(u64_at(b, at)).ok()?;
    let end = start.checked_add(usize::try_from(u64_at(b, at + 8)).ok()?)?;
    (end <= b.len()).then_some(start..end)
}

fuzz_target!(|data: &[u8]| {
    let mut bytes = data.to_vec();
    if bytes.len() >= 128 {
        if let Some(r) = section(&bytes, 24) {
            let crc = crc32c(&bytes[r]);
            bytes[112..116].copy_from_slice(&crc.to_le_bytes());
        }
        if let Some(r) = section(&bytes, 40) {
            let crc = crc32c(&bytes[r]);
            bytes[116..120].copy_from_slice(&crc.to_le_bytes());
        }
        let crc = crc32c(&bytes[..124]);
        bytes[124..128].copy_from_slice(&crc.to_le_bytes());
    }
    common::exercise(bytes);
});
