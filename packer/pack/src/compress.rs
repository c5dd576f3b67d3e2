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
