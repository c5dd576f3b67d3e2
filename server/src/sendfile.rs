//! Bodies that are slices of an archive's mapping go to the socket with `sendfile(2)` from
//! the archive's file, as nginx sends files: the kernel hands page-cache pages to the
//! socket instead of copying the bytes from the mapping into socket buffers (that copy was
//! the largest single cost of a Range or tile answer).
//!
//! Hyper (HTTP/1.1) and h2 write a response as a vectored write of buffers: the head, then
//! the body's `Bytes`, which for archives are slices of the mapping. [`Stream`] wraps a
//! plain TCP connection and looks each buffer up among the mapped archives
//! ([`register`]): the buffers before a mapped one go out with `sendmsg(MSG_MORE)` (the
//! kernel holds them for the body, one segment as with `writev`), the mapped one with
//! `sendfile` at its offset in the file. Anything else, and every other platform, is
//! written as before. The bytes on the wire are the same either way: a mapping shows its
//! file, and the registered file is the one mapped (kept open: the same inode even after
//! the path was replaced).

use std::fs::File;
use std::io::IoSlice;
use std::pin::Pin;
use std::sync::atomic::{AtomicU64, Ordering};
use std::sync::{Arc, PoisonError, RwLock};
use std::task::{Context, Poll, ready};

use bytes::Bytes;
use tokio::io::{AsyncRead, AsyncWrite, Interest, ReadBuf};
use tokio::net::TcpStream;

/// Below this, a copy costs less than the page references and the extra system call.
const MIN_SENDFILE: usize = 4096;

/// Body bytes sent with `sendfile` since start (for `/metrics`).
static SENT: AtomicU64 = AtomicU64::new(0);

/// Body bytes sent with `sendfile` so far, by every connection.
pub fn sent_bytes() -> u64 {
    SENT.load(Ordering::Relaxed)
}

/// A mapped file's address range.
struct Region {
    start: usize,
    len: usize,
    file: Arc<File>,
}

/// Every registered mapping. A handful of archives, read on each large write: a short list
/// behind a read-mostly lock.
static REGIONS: RwLock<Vec<Region>> = RwLock::new(Vec::new());

/// A mapping registered for `sendfile` until this is dropped.
#[derive(Debug)]
pub struct Registration {
    start: usize,
}

impl Drop for Registration {
    fn drop(&mut self) {
        REGIONS.write().unwrap_or_else(PoisonError::into_inner).retain(|r| r.start != self.start);
    }
}

/// Registers `mapping`, the whole of `file` mapped, so that writes of its slices go out
/// with `sendfile`. None for an empty mapping.
pub fn register(mapping: &Bytes, file: Arc<File>) -> Option<Registration> {
    if mapping.is_empty() {
        return None;
    }
    let start = mapping.as_ptr() as usize;
    REGIONS.write().unwrap_or_else(PoisonError::into_inner).push(Region { start, len: mapping.len(), file });
    Some(Registration { start })
}

/// The file a buffer lies in, and the buffer's offset in it.
fn find(buf: &[u8]) -> Option<(Arc<File>, u64)> {
    let at = buf.as_ptr() as usize;
    let regions = REGIONS.read().unwrap_or_else(PoisonError::into_inner);
    regions
        .iter()
        .find(|r| at >= r.start && at + buf.len() <= r.start + r.len)
        .map(|r| (Arc::clone(&r.file), (at - r.start) as u64))
}

/// A plain TCP connection that sends mapped archive bytes with `sendfile`.
#[derive(Debug)]
pub struct Stream {
    inner: TcpStream,
}

impl Stream {
    /// Wraps an accepted connection.
    pub fn new(inner: TcpStream) -> Self {
        Self { inner }
    }
}

/// The first buffer worth sending from its file, with the file and offset.
fn first_mapped(bufs: &[IoSlice<'_>]) -> Option<(usize, Arc<File>, u64)> {
    bufs.iter().enumerate().filter(|(_, b)| b.len() >= MIN_SENDFILE).find_map(|(i, b)| find(b).map(|(f, o)| (i, f, o)))
}

#[cfg(target_os = "linux")]
fn write_mapped(
    socket: &TcpStream,
    bufs: &[IoSlice<'_>],
    at: usize,
    file: &File,
    offset: u64,
) -> std::io::Result<usize> {
    use rustix::net::{SendAncillaryBuffer, SendFlags};
    let mut written = 0;
    if at > 0 {
        let head: usize = bufs[..at].iter().map(|b| b.len()).sum();
        let flags = SendFlags::MORE | SendFlags::NOSIGNAL;
        written = rustix::net::sendmsg(socket, &bufs[..at], &mut SendAncillaryBuffer::default(), flags)?;
        if written < head {
            return Ok(written);
        }
    }
    let mut offset = offset;
    match rustix::fs::sendfile(socket, file, Some(&mut offset), bufs[at].len()) {
        Ok(n) => {
            SENT.fetch_add(n as u64, Ordering::Relaxed);
            Ok(written + n)
        }
        // The head went out: report it; the body follows on the next write.
        Err(_) if written > 0 => Ok(written),
        Err(e) => Err(e.into()),
    }
}

#[cfg(not(target_os = "linux"))]
fn write_mapped(socket: &TcpStream, bufs: &[IoSlice<'_>], _: usize, _: &File, _: u64) -> std::io::Result<usize> {
    socket.try_write_vectored(bufs)
}

impl AsyncWrite for Stream {
    fn poll_write(self: Pin<&mut Self>, cx: &mut Context<'_>, buf: &[u8]) -> Poll<std::io::Result<usize>> {
        self.poll_write_vectored(cx, &[IoSlice::new(buf)])
    }

    fn poll_write_vectored(
        mut self: Pin<&mut Self>,
        cx: &mut Context<'_>,
        bufs: &[IoSlice<'_>],
    ) -> Poll<std::io::Result<usize>> {
        let Some((at, file, offset)) = first_mapped(bufs) else {
            return Pin::new(&mut self.inner).poll_write_vectored(cx, bufs);
        };
        loop {
            ready!(self.inner.poll_write_ready(cx))?;
            // `try_io` clears the readiness when the writes would block, so the next
            // `poll_write_ready` waits for the socket again.
            match self.inner.try_io(Interest::WRITABLE, || write_mapped(&self.inner, bufs, at, &file, offset)) {
                Err(e) if e.kind() == std::io::ErrorKind::WouldBlock => {}
                result => return Poll::Ready(result),
            }
        }
    }

    fn is_write_vectored(&self) -> bool {
        true
    }

    fn poll_flush(mut self: Pin<&mut Self>, cx: &mut Context<'_>) -> Poll<std::io::Result<()>> {
        Pin::new(&mut self.inner).poll_flush(cx)
    }

    fn poll_shutdown(mut self: Pin<&mut Self>, cx: &mut Context<'_>) -> Poll<std::io::Result<()>> {
        Pin::new(&mut self.inner).poll_shutdown(cx)
    }
}

impl AsyncRead for Stream {
    fn poll_read(mut self: Pin<&mut Self>, cx: &mut Context<'_>, buf: &mut ReadBuf<'_>) -> Poll<std::io::Result<()>> {
        Pin::new(&mut self.inner).poll_read(cx, buf)
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use tokio::io::{AsyncReadExt, AsyncWriteExt};

    #[tokio::test]
    async fn mapped_slices_arrive_as_in_the_file_and_are_counted() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("blob");
        let data: Vec<u8> = (0..600_000u32).map(|i| (i * 7 % 251) as u8).collect();
        std::fs::write(&path, &data).unwrap();
        let source = terrastream_format::MmapSource::open(&path).unwrap();
        let mapping = source.bytes().clone();
        let registration = register(&mapping, Arc::clone(source.file().unwrap())).unwrap();

        let listener = tokio::net::TcpListener::bind("127.0.0.1:0").await.unwrap();
        let addr = listener.local_addr().unwrap();
        let reader = tokio::spawn(async move {
            let (mut s, _) = listener.accept().await.unwrap();
            let mut got = Vec::new();
            s.read_to_end(&mut got).await.unwrap();
            got
        });
        let mut stream = Stream::new(TcpStream::connect(addr).await.unwrap());
        let before = sent_bytes();
        // A head, a big mapped slice at an odd offset (more than a socket buffer: partial
        // sends), a small mapped slice (copied), a heap buffer.
        let (big, small) = (mapping.slice(1234..501_234), mapping.slice(10..100));
        let parts: [&[u8]; 4] = [b"HEAD\r\n", &big, &small, b"tail"];
        let mut expected = Vec::new();
        for p in parts {
            expected.extend_from_slice(p);
        }
        let mut sent = 0;
        while sent < expected.len() {
            // Rebuild the slices past what went out, as hyper does.
            let mut skip = sent;
            let mut bufs = Vec::new();
            for p in parts {
                if skip >= p.len() {
                    skip -= p.len();
                    continue;
                }
                bufs.push(IoSlice::new(&p[skip..]));
                skip = 0;
            }
            sent += std::future::poll_fn(|cx| Pin::new(&mut stream).poll_write_vectored(cx, &bufs)).await.unwrap();
        }
        stream.shutdown().await.unwrap();
        drop(stream);
        assert_eq!(reader.await.unwrap(), expected);
        let through_sendfile = sent_bytes() - before;
        if cfg!(target_os = "linux") {
            // Other tests may send concurrently: at least the big slice went this way.
            assert!(through_sendfile >= big.len() as u64, "{through_sendfile} bytes through sendfile");
        }
        drop(registration);
        assert!(find(&big).is_none(), "unregistered with its registration");
    }
}
