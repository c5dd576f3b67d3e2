//! Decompression with a size cap: pure Rust, so the reader builds for wasm32, and libzstd
//! on native targets for frames that state their size.

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
    #[cfg(not(target_arch = "wasm32"))]
    if let Some(out) = zstd_native(bytes, limit) {
        return Ok(out);
    }
    zstd_pure(bytes, limit, section)
}

/// [`zstd_decompress`] in pure Rust.
fn zstd_pure(bytes: &[u8], limit: u64, section: &str) -> Result<Vec<u8>> {
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

/// Decodes a frame that states its size (every frame the writer makes), within `limit`,
/// with libzstd, about twice as fast as the pure-Rust decoder, with a context kept per
/// thread. `None`: left to the pure-Rust decoder, which then decides (a frame without a
/// size or over the limit, several frames, bytes libzstd refuses), so what is accepted,
/// and every error, does not depend on the build.
#[cfg(not(target_arch = "wasm32"))]
fn zstd_native(bytes: &[u8], limit: u64) -> Option<Vec<u8>> {
    use std::cell::RefCell;
    thread_local! {
        static CONTEXT: RefCell<Option<zstd::bulk::Decompressor<'static>>> = const { RefCell::new(None) };
    }
    let size = zstd::zstd_safe::get_frame_content_size(bytes).ok()??;
    let capacity = usize::try_from(size).ok().filter(|_| size <= limit)?;
    CONTEXT.with(|context| {
        let mut context = context.borrow_mut();
        let decompressor = match &mut *context {
            Some(d) => d,
            slot => slot.insert(zstd::bulk::Decompressor::new().ok()?),
        };
        // Exactly the stated size, or the pure-Rust decoder has its say.
        decompressor.decompress(bytes, capacity).ok().filter(|out| out.len() == capacity)
    })
}

#[cfg(all(test, not(target_arch = "wasm32")))]
mod tests {
    use super::*;

    fn zstd_compress(bytes: &[u8], level: i32) -> std::io::Result<Vec<u8>> {
        zstd::bulk::compress(bytes, level)
    }

    #[test]
    fn round_trip_and_limit() {
        let data = vec![7u8; 100_000];
        let packed = zstd_compress(&data, 3).unwrap();
        assert_eq!(zstd_decompress(&packed, 100_000, "t").unwrap(), data);
        assert!(zstd_decompress(&packed, 99_999, "t").is_err());
        assert!(zstd_decompress(&packed[..packed.len() / 2], 1 << 20, "t").is_err());
        assert!(zstd_decompress(b"not zstd", 1 << 20, "t").is_err());
    }

    /// libzstd and the pure-Rust decoder accept the same frames and give the same bytes:
    /// frames with and without a stated size, at and over the limit, with trailing bytes,
    /// two frames, truncated, damaged.
    #[test]
    fn both_decoders_agree() {
        let data: Vec<u8> =
            (0..50_000u32).map(|i| u8::try_from((i.wrapping_mul(2_654_435_761) >> 20) % 17).unwrap()).collect();
        let sized = zstd_compress(&data, 3).unwrap();
        let mut sizeless = Vec::new();
        {
            let mut encoder = zstd::stream::Encoder::new(&mut sizeless, 3).unwrap();
            std::io::Write::write_all(&mut encoder, &data).unwrap();
            encoder.finish().unwrap();
        }
        assert!(zstd::zstd_safe::get_frame_content_size(&sizeless).unwrap().is_none());
        // The writer's frames go to libzstd, the others to the pure-Rust decoder.
        assert_eq!(zstd_native(&sized, 50_000), Some(data.clone()));
        assert_eq!(zstd_native(&sizeless, 50_000), None);
        let mut trailing = sized.clone();
        trailing.extend_from_slice(b"junk");
        let two = [sized.clone(), sized.clone()].concat();
        let mut damaged = sized.clone();
        let middle = damaged.len() / 2;
        damaged[middle] ^= 0x5a;
        let cases: [(&[u8], u64); 8] = [
            (&sized, 50_000),
            (&sized, 49_999),
            (&sizeless, 50_000),
            (&sizeless, 49_999),
            (&trailing, 1 << 20),
            (&two, 1 << 20),
            (&sized[..sized.len() - 3], 1 << 20),
            (&damaged, 1 << 20),
        ];
        for (i, (bytes, limit)) in cases.into_iter().enumerate() {
            let native = zstd_decompress(bytes, limit, "t").ok();
            assert_eq!(native, zstd_pure(bytes, limit, "t").ok(), "case {i}");
            if i == 0 || i == 2 {
                assert_eq!(native.as_deref(), Some(&data[..]), "case {i}");
            }
        }
    }
}
