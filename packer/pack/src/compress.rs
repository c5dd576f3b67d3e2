//! The writer's zstd compression.

/// Compresses with zstd at `level`.
///
/// # Errors
/// I/O errors from the compressor (allocation failure).
pub fn zstd_compress(bytes: &[u8], level: i32) -> std::io::Result<Vec<u8>> {
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
        compressor.compress(bytes)
    })
}

/// Compresses a grid of raw samples (an elevation tile: u16 or f32 heights, little-endian)
/// with the parameters measured best for them: zstd's fast strategy, a 2^16-entry hash
/// table and 4-byte matches. On 133 KB SRTM u16 tiles that is 1.43x the speed of level 3
/// for 0.7 % more bytes (level 1: 1.9x the speed, 6.5 % more bytes); see
/// docs/BENCHMARKS.md. Standard zstd frames: any decoder reads them.
///
/// # Errors
/// I/O errors from the compressor (allocation failure).
pub fn zstd_compress_samples(bytes: &[u8]) -> std::io::Result<Vec<u8>> {
    use std::cell::RefCell;
    use zstd::zstd_safe::{CParameter, Strategy};
    thread_local! {
        static CONTEXT: RefCell<Option<zstd::bulk::Compressor<'static>>> = const { RefCell::new(None) };
    }
    CONTEXT.with(|context| {
        let mut context = context.borrow_mut();
        let compressor = match &mut *context {
            Some(c) => c,
            slot => {
                let mut c = zstd::bulk::Compressor::new(3)?;
                c.set_parameter(CParameter::Strategy(Strategy::ZSTD_fast))?;
                c.set_parameter(CParameter::HashLog(16))?;
                c.set_parameter(CParameter::MinMatch(4))?;
                slot.insert(c)
            }
        };
        compressor.compress(bytes)
    })
}

/// Compresses an elevation tile's u16 samples (little-endian, `edge` x `edge`) as a
/// `zstd_gradient` layer stores them: gradient-coded byte planes
/// ([`terrastream_format::gradient_encode`]), zstd level 1. On the 8100² bench DEM's
/// tiles: 2.1x fewer bytes than [`zstd_compress_samples`] (1.9x on SRTM) in 0.8x its time;
/// see docs/BENCHMARKS.md.
///
/// # Errors
/// I/O errors from the compressor (allocation failure); `InvalidInput` if `samples` is
/// not `2 * edge^2` bytes.
pub fn zstd_compress_gradient(samples: &[u8], edge: usize) -> std::io::Result<Vec<u8>> {
    use std::cell::RefCell;
    if samples.len() != 2 * edge * edge {
        return Err(std::io::Error::new(
            std::io::ErrorKind::InvalidInput,
            format!("{} bytes are not {edge}x{edge} u16 samples", samples.len()),
        ));
    }
    thread_local! {
        static CONTEXT: RefCell<Option<zstd::bulk::Compressor<'static>>> = const { RefCell::new(None) };
        static PLANES: RefCell<Vec<u8>> = const { RefCell::new(Vec::new()) };
    }
    PLANES.with_borrow_mut(|planes| {
        terrastream_format::gradient_encode_into(samples, edge, planes);
        CONTEXT.with_borrow_mut(|context| {
            let compressor = match context {
                Some(c) => c,
                slot => slot.insert(zstd::bulk::Compressor::new(1)?),
            };
            compressor.compress(planes)
        })
    })
}

/// An elevation tile's samples (u16 or f32, little-endian, `edge` x `edge`) -> what a
/// layer compressed as `compression` stores: the samples, [`zstd_compress_samples`], or
/// [`zstd_compress_gradient`] (u16 only).
///
/// # Errors
/// As those two.
pub fn compress_heights(
    compression: terrastream_format::PayloadCompression,
    samples: &[u8],
    edge: usize,
) -> std::io::Result<Vec<u8>> {
    use terrastream_format::PayloadCompression;
    match compression {
        PayloadCompression::None => Ok(samples.to_vec()),
        PayloadCompression::Zstd => zstd_compress_samples(samples),
        PayloadCompression::ZstdGradient => zstd_compress_gradient(samples, edge),
    }
}
