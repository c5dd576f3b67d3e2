//! A response body made of `Bytes` chunks that are slices of the archive's mapping: the
//! payload is never copied on its way to the socket. The handlers of the archive and tile
//! routes answer with it; both hyper (as an `http_body::Body`) and the lean HTTP/1.1 path
//! ([`crate::h1`], which takes the chunks out) send it.

use std::collections::VecDeque;
use std::convert::Infallible;
use std::pin::Pin;
use std::task::{Context, Poll};

use bytes::Bytes;
use http_body::{Body, Frame, SizeHint};

/// Chunks sent in order, with an exact length. One chunk (the common answer) needs no
/// allocation beyond the `Bytes` itself.
#[derive(Debug, Default)]
pub struct Payload {
    first: Option<Bytes>,
    rest: VecDeque<Bytes>,
    remaining: u64,
}

impl Payload {
    /// No bytes.
    pub fn empty() -> Self {
        Self::default()
    }

    /// A body of these chunks.
    pub fn chunks(chunks: Vec<Bytes>) -> Self {
        let remaining = chunks.iter().map(|c| c.len() as u64).sum();
        Self { first: None, rest: chunks.into(), remaining }
    }

    /// Bytes left to send.
    pub fn len(&self) -> u64 {
        self.remaining
    }

    /// The chunks, in order.
    pub fn iter(&self) -> impl Iterator<Item = &Bytes> {
        self.first.iter().chain(self.rest.iter())
    }
}

impl From<Bytes> for Payload {
    fn from(bytes: Bytes) -> Self {
        Self { remaining: bytes.len() as u64, first: (!bytes.is_empty()).then_some(bytes), rest: VecDeque::new() }
    }
}

impl From<&'static str> for Payload {
    fn from(text: &'static str) -> Self {
        Bytes::from_static(text.as_bytes()).into()
    }
}

impl From<String> for Payload {
    fn from(text: String) -> Self {
        Bytes::from(text).into()
    }
}

impl Body for Payload {
    type Data = Bytes;
    type Error = Infallible;

    fn poll_frame(mut self: Pin<&mut Self>, _: &mut Context<'_>) -> Poll<Option<Result<Frame<Bytes>, Infallible>>> {
        let next = match self.first.take() {
            Some(first) => Some(first),
            None => self.rest.pop_front(),
        };
        Poll::Ready(next.map(|c| {
            self.remaining -= c.len() as u64;
            Ok(Frame::data(c))
        }))
    }

    fn is_end_stream(&self) -> bool {
        self.first.is_none() && self.rest.is_empty()
    }

    fn size_hint(&self) -> SizeHint {
        SizeHint::with_exact(self.remaining)
    }
}
