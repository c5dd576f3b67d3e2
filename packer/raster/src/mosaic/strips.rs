//! PNG and JPEG inputs, which cannot be read by parts: decoded by strips of rows from
//! their top, on a thread of their own.

use super::*;

/// Rows of a PNG or JPEG input a strip holds.
pub(super) const STRIP_ROWS: usize = 64;

/// Strips skipped to reach a later one that are still kept: other threads may be about to
/// ask for them (the strips of one window are asked for at once).
pub(super) const KEPT_BEHIND: usize = 8;

/// A PNG or JPEG input decoded from the top, [`STRIP_ROWS`] rows at a time, on a thread of
/// its own that runs a strip ahead: memory follows the image's width, not its size. A
/// strip above the next one, asked for again once dropped from the cache, starts the
/// decoding over.
pub(super) struct RowStrips {
    pub(super) path: PathBuf,
    pub(super) width: usize,
    pub(super) decoder: Mutex<Decoding>,
}

/// Where a [`RowStrips`]' decoding stands.
#[derive(Default)]
pub(super) struct Decoding {
    /// The next strip the decoder hands over, and the decoder.
    pub(super) next: usize,
    pub(super) strips: Option<Strips>,
    /// The strip at which decoding failed: it and those below are not asked of a new
    /// decoder (which would decode from the top again only to fail there).
    pub(super) failed: Option<usize>,
}

/// The strips a decoder thread hands over, top down.
pub(super) type Strips = mpsc::Receiver<Result<Vec<u8>>>;

impl RowStrips {
    /// Starts decoding `path`, opened as kind `K`, from its first row.
    pub(super) fn start<K: MosaicKind>(path: &Path) -> Strips {
        let (sender, receiver) = mpsc::sync_channel(1);
        let spawned = std::thread::Builder::new().name("mosaic rows".into()).spawn({
            let (sender, path) = (sender.clone(), path.to_path_buf());
            move || {
                let mut strip = Vec::new();
                let mut rows = 0;
                let decoded = K::open(&path).and_then(|file| {
                    K::file_rows(&file, &mut |row| {
                        strip.extend_from_slice(row);
                        rows += 1;
                        if rows == STRIP_ROWS {
                            rows = 0;
                            // Nobody waits for it any more: stop decoding.
                            sender
                                .send(Ok(std::mem::take(&mut strip)))
                                .map_err(|_| Error::Interrupted(crate::Interrupted))?;
                        }
                        Ok(())
                    })
                });
                let last = match decoded {
                    Ok(()) if strip.is_empty() => return,
                    Ok(()) => Ok(strip),
                    Err(e) => Err(e),
                };
                let _ = sender.send(last);
            }
        });
        if let Err(e) = spawned {
            let _ = sender.send(Err(Error::file(path, e)));
        }
        receiver
    }

    /// Strip `id`, made by `keep` from its bytes, as are the strips decoded on the way to
    /// it [`KEPT_BEHIND`] or fewer above it (`keep` takes a strip's number); or what
    /// `cached` finds once the decoder is this thread's (another thread that held it may
    /// have made the strip meanwhile). Strips are kept while the decoder is held, so a
    /// thread waiting for it finds them.
    pub(super) fn strip<K: MosaicKind, C>(
        &self,
        id: usize,
        cached: impl FnOnce() -> Option<C>,
        mut keep: impl FnMut(usize, Vec<u8>) -> Result<C>,
    ) -> Result<C> {
        let mut decoder = self.decoder.lock().unwrap_or_else(PoisonError::into_inner);
        if let Some(chunk) = cached() {
            return Ok(chunk);
        }
        let Decoding { next, strips: receiver, failed } = &mut *decoder;
        if let Some(at) = failed.filter(|&at| at <= id) {
            return Err(Error::damaged(
                &self.path,
                format!("strip {id}: the image could not be decoded past strip {at}"),
            ));
        }
        if *next > id || receiver.is_none() {
            if *next > 0 {
                tracing::debug!(path = %self.path.display(), strip = id, "decoding again from the top");
            }
            (*next, *receiver) = (0, Some(Self::start::<K>(&self.path)));
        }
        loop {
            let received = receiver.as_ref().and_then(|r| r.recv().ok());
            let Some(strip) = received else {
                *receiver = None;
                *failed = Some(*next);
                let why = format!("strip {id} of {STRIP_ROWS} rows: the image ended (or its decoder stopped) first");
                return Err(Error::damaged(&self.path, why));
            };
            let strip = strip.inspect_err(|e| {
                *receiver = None;
                if e.is_bad_input() {
                    *failed = Some(*next);
                }
            })?;
            let n = *next;
            *next += 1;
            if n == id {
                return keep(n, strip);
            }
            if n + KEPT_BEHIND >= id {
                keep(n, strip)?;
            }
        }
    }
}
