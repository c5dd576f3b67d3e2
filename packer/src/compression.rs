//! Decompression with a size cap (pure Rust, so the reader builds for wasm32), and the
//! writer's zstd compression.

use std::io::Read;

use crate::error::{Error, Result};
use crate::header::Compression;

/// Decompresses `bytes`, refusing to produce more than `limit` bytes.
///
/// # Errors
/// [`Error::Decompress`] if the frame is invalid or inflates past `limit`.
pub fn decompress(bytes: &[u8], compression: Compression, limit: u64, section: &str) -> Result<Vec<u8>> {
    match compression {
        Compression::None => {
            if bytes.len() as u64 > limit {
                return Err(Error::Decompress {
                    section: section.into(),
                    reason: format!("larger than {limit} bytes"),
                });
            }
            Ok(bytes.to_vec())
        }
        Compression::Zstd => zstd_decompress(bytes, limit, section),
    }
}

/// Decompresses one zstd frame, refusing to produce more than `limit` bytes.
///
/// # Errors
/// [`Error::Decompress`] if the frame is invalid, truncated or inflates past `limit`.
pub fn zstd_decompress(bytes: &[u8], limit: u64, section: &str) -> Result<Vec<u8>> {
    let fail = |reason: String| Error::Decompress { section: section.into(), reason };
    let mut source = bytes;
    let decoder = ruzstd::decoding::StreamingDecoder::new(&mut source).map_err(|e| fail(e.to_string()))?;
    let mut out = Vec::new();
    // Read one byte past the limit to tell "exactly at the limit" from "over it".
    decoder.take(limit.saturating_add(1)).read_to_end(&mut out).map_err(|e| fail(e.to_string()))?;
    if out.len() as u64 > limit {
        return Err(fail(format!("inflates past {limit} bytes")));
    }
    Ok(out)
}

/// Compresses with zstd at `level`.
///
/// # Errors
/// I/O errors from the compressor (allocation failure).
#[cfg(feature = "write")]
pub fn zstd_compress(bytes: &[u8], level: i32) -> Result<Vec<u8>> {
    use std::cell::RefCell;
    // One compression context per thread and level, kept: making one allocates and
    // clears its tables, which for tile-sized inputs costs as much as compressing them.
    // The output is the same as a fresh context's.
    thread_local! {
        static CONTEXT: RefCell<Option<(i32, zstd::bulk::Compressor<'static>)>> = const { RefCell::new(None) };
    }
    CONTEXT.with(|context| {
        let mut context = context.borrow_mut();
        let compressor = match &mut *context {
            Some((l, c)) if *l == level => c,
            slot => &mut slot.insert((level, zstd::bulk::Compressor::new(level)?)).1,
        };
        Ok(compressor.compress(bytes)?)
    })
}

#[cfg(all(test, feature = "write"))]
mod tests {
    use super::*;

    #[test]
    fn round_trip_and_limit() {
        let data = vec![7u8; 100_000];
        let packed = zstd_compress(&data, 3).unwrap();
        assert_eq!(zstd_decompress(&packed, 100_000, "t").unwrap(), data);
        assert!(zstd_decompress(&packed, 99_999, "t").is_err());
        assert!(zstd_decompress(&packed[..packed.len() / 2], 1 << 20, "t").is_err());
        assert!(zstd_decompress(b"not zstd", 1 << 20, "t").is_err());
    }
}
