//! Any bytes as an archive: open, look every tile up, verify. Must never panic.
#![no_main]

mod common;

use libfuzzer_sys::fuzz_target;

fuzz_target!(|data: &[u8]| common::exercise(data.to_vec()));
