//! Any bytes as what a client sends the server: a request head as the lean HTTP/1.1 path
//! parses and routes it (it must agree with the router on what it takes), and a `Range`
//! header value against files of a few lengths. Must never panic.
#![no_main]

use libfuzzer_sys::fuzz_target;
use terrastream_server::{RangeOutcome, inspect_head, parse_range};

fuzz_target!(|data: &[u8]| {
    for max_head in [64, 16 * 1024] {
        if let Some((len, _)) = inspect_head(data, max_head) {
            assert!(len <= data.len());
        }
    }
    for file_len in [0u64, 1, 1000, u64::MAX / 2] {
        if let RangeOutcome::Partial(ranges) = parse_range(data, file_len, 256) {
            assert!(!ranges.is_empty() && ranges.len() <= 256);
            for r in ranges {
                assert!(r.start < r.end && r.end <= file_len, "{r:?} of {file_len}");
            }
        }
    }
});
