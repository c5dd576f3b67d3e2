//! The lean HTTP/1.1 path: the two routes that carry the load (Range requests on an
//! archive, and tiles), answered straight from the connection's read buffer.
//!
//! Under load nearly every request is a small `GET` of one of these, and hyper and the
//! router cost more user-space time per request than the kernel spends sending the bytes
//! (request and header map building, routing, path extraction, a boxed future per layer,
//! the dispatcher's state machine). A plain TCP connection therefore starts here: a request
//! is parsed in place (`httparse`, headers borrowed from the buffer), and when it is a
//! well-formed `GET` or `HEAD` of `/{name}.tspack` or `/{name}/{layer}/{lod}/{x}/{y}`
//! over HTTP/1.1, with no body, no upgrade and no `Connection` option but `keep-alive`, it
//! is answered by the same handler functions the router calls ([`archive_answer`],
//! [`tile_answer`]), with the same CORS headers and metrics ([`finish`]); the head is
//! written into one reused buffer and the body goes out with `sendfile`.
//!
//! Anything else — another route or method, HTTP/1.0, h2c's preface, a body, `Expect`,
//! a percent-encoded or query-carrying path, a malformed or oversized head, more than
//! [`MAX_HEADERS`] headers — hands the connection to hyper for the rest of its life, with
//! the bytes read so far ([`Rewind`]): every answer the lean path does not give, hyper and
//! the router give exactly as without it. Pipelined requests are answered in order.
//!
//! Waiting for a request (idle, or part of a head read) is bounded by the request timeout,
//! as hyper's header-read timeout bounds it. The timer is re-armed lazily: it fires at the
//! oldest deadline and is moved on then, instead of being reset on every request.

use std::io::IoSlice;
use std::pin::Pin;
use std::task::{Context, Poll};
use std::time::{Duration, Instant, SystemTime};

use axum::http::header::{CONTENT_LENGTH, DATE};
use axum::http::{HeaderMap, HeaderValue, Method, StatusCode};
use bytes::{Buf, Bytes};
use tokio::io::{AsyncRead, AsyncReadExt, AsyncWrite, ReadBuf};
use tokio::sync::watch;

use crate::access::{Grant, Presented};
use crate::app::{Answer, AppState, TileAt, archive_answer, tile_answer};
use crate::edge::{admit, finish, mark_private};
use crate::route::{READ_HEADERS, Route};
use crate::sendfile::Stream;
use crate::web::{TileQuery, WebTileAt, web_tile_answer};

/// Most request headers the lean path parses; a request with more goes to hyper.
pub(crate) const MAX_HEADERS: usize = 32;

/// Request headers that change how a request is framed or answered beyond what the lean
/// path does: a request with one goes to hyper (`connection: keep-alive` excepted).
const HYPER_HEADERS: [&str; 6] = ["content-length", "transfer-encoding", "connection", "upgrade", "expect", "te"];

/// How a connection left the lean path.
pub(crate) enum Ended {
    /// Closed: by the client, the timeout, or shutdown.
    Closed,
    /// For hyper to serve from here, with the bytes already read.
    Hyper(Rewind),
}

/// Limits of the lean path, the same as hyper's.
#[derive(Clone, Copy, Debug)]
pub(crate) struct Limits {
    /// Longest wait for a request's head (idle connections included).
    pub timeout: Duration,
    /// Longest request head; a longer one goes to hyper, which answers 431.
    pub max_head: usize,
}

/// A recognised request, borrowing from the read buffer.
struct Request<'a> {
    /// Bytes of the head.
    len: usize,
    method: Method,
    path: &'a str,
    route: Lean<'a>,
    headers: HeaderMap,
    /// What the access rules read: `Authorization`, `Origin`, `Referer` (never copied).
    credentials: [Option<&'a [u8]>; 3],
}

/// A request the lean path answers itself, its path's segments captured.
enum Lean<'a> {
    Archive(&'a str),
    Tile {
        name: &'a str,
        layer: &'a str,
        at: TileAt,
    },
    /// A web tile and its query (boxed: the rest of the lean requests stay small).
    WebTile(Box<(WebTileAt<'a>, TileQuery)>),
}

impl Lean<'_> {
    /// The router's route for this request.
    fn route(&self) -> Route {
        match self {
            Lean::Archive(_) => Route::Archive,
            Lean::Tile { .. } => Route::Tile,
            Lean::WebTile(_) => Route::WebTile,
        }
    }
}

#[expect(clippy::large_enum_variant, reason = "on the stack for one request: a box would allocate on the hot path")]
enum Parsed<'a> {
    /// More bytes needed.
    Partial,
    /// Not for the lean path.
    Hyper,
    Request(Request<'a>),
}

/// Serves `stream` until it closes or needs hyper. `closing` turns true at shutdown: the
/// connection is closed once no request is in progress.
///
/// # Errors
/// Reading or writing the socket.
pub(crate) async fn serve(
    mut stream: Stream,
    state: &AppState,
    closing: watch::Receiver<bool>,
    limits: Limits,
) -> std::io::Result<Ended> {
    let mut buf: Vec<u8> = Vec::with_capacity(4096);
    let mut at = 0;
    let mut head = Vec::with_capacity(1024);
    let mut deadline = Instant::now() + limits.timeout;
    let timer = tokio::time::sleep_until(deadline.into());
    tokio::pin!(timer);
    // Waits for shutdown, registered once for the connection's life rather than once per
    // request (`closing` itself is read between requests).
    let mut watch = closing.clone();
    let shutdown = watch.changed();
    tokio::pin!(shutdown);
    loop {
        // Every complete request buffered, in order.
        while at < buf.len() {
            let request = match parse(&buf[at..], limits.max_head) {
                Parsed::Partial => break,
                Parsed::Hyper => return Ok(Ended::Hyper(Rewind::new(Bytes::copy_from_slice(&buf[at..]), stream))),
                Parsed::Request(request) => request,
            };
            // From the request's start: a clock read less per request, a few µs shorter.
            let (started, refused) = answer(&mut stream, state, &request, &mut head).await?;
            // A refusal held for its turn keeps its connection (the hold is what slows a
            // flood; reconnecting would cost both sides more). Without a pace, a refused
            // request ends its connection: a flood of bad credentials pays a new
            // connection for each try, and the rest of the server keeps its share.
            if refused && !state.access.paced() {
                return Ok(Ended::Closed);
            }
            deadline = started + limits.timeout;
            at += request.len;
        }
        if at == buf.len() {
            buf.clear();
            at = 0;
            if *closing.borrow() {
                return Ok(Ended::Closed);
            }
        } else if at > 0 {
            buf.drain(..at);
            at = 0;
        }
        if buf.capacity() - buf.len() < 1024 {
            buf.reserve(4096);
        }
        loop {
            tokio::select! {
                biased;
                read = stream.read_buf(&mut buf) => {
                    if read? == 0 {
                        return Ok(Ended::Closed);
                    }
                    break;
                }
                () = &mut timer => {
                    if Instant::now() >= deadline {
                        return Ok(Ended::Closed);
                    }
                    timer.as_mut().reset(deadline.into());
                }
                // Closed at shutdown when idle; a request in progress is read and answered.
                // (Polled only until it fires: then the connection closes.)
                _ = &mut shutdown, if buf.is_empty() => return Ok(Ended::Closed),
            }
        }
    }
}

/// Answers one request: the handler's answer, its CORS headers and metrics, the head into
/// `head`, then head and body in one vectored write. Returns when it started, and whether
/// the access rules refused it (the connection is then closed, unless refusals are paced).
async fn answer(
    stream: &mut Stream,
    state: &AppState,
    request: &Request<'_>,
    head: &mut Vec<u8>,
) -> std::io::Result<(Instant, bool)> {
    let started = Instant::now();
    let grant = if state.access.enabled() {
        let (path, query) = request.path.split_once('?').map_or((request.path, None), |(p, q)| (p, Some(q)));
        let [authorization, origin, referer] = request.credentials;
        admit(state, &Presented { path, query, authorization, origin, referer })
    } else {
        Ok(Grant::default())
    };
    let refused = grant.is_err();
    let mut answer = match grant {
        Err(refused) => {
            // Held for its turn among refusals (a flood's connections wait here).
            state.access.wait_turn().await;
            let mut answer = refused.answer();
            if !state.access.paced() {
                answer.headers_mut().insert(axum::http::header::CONNECTION, HeaderValue::from_static("close"));
            }
            answer
        }
        Ok(grant) => {
            let mut answer = match &request.route {
                Lean::Archive(file) => archive_answer(state, file, &request.method, &request.headers),
                Lean::Tile { name, layer, at } => tile_answer(state, name, layer, *at, &request.headers),
                Lean::WebTile(tile) => web_tile_answer(state, tile.0, &tile.1, &request.headers).await,
            };
            mark_private(state, &grant, &mut answer);
            answer
        }
    };
    finish(state, request.route.route(), started, &mut answer);
    if tracing::enabled!(tracing::Level::DEBUG) {
        let (method, status) = (&request.method, answer.status().as_u16());
        // The path, and the query with any credential hidden: keys never reach the logs.
        let (path, query) = request.path.split_once('?').map_or((request.path, None), |(p, q)| (p, Some(q)));
        let query = query.map(crate::access::redacted).unwrap_or_default();
        tracing::debug!(%method, path, query, status, latency = ?started.elapsed(), "answered");
    }
    write_head(head, &answer);
    let body = answer.body();
    let mut chunks = body.iter();
    match (chunks.next(), chunks.next()) {
        _ if request.method == Method::HEAD => write_all(stream, &mut [IoSlice::new(head)]).await?,
        (None, _) => write_all(stream, &mut [IoSlice::new(head)]).await?,
        (Some(one), None) => write_all(stream, &mut [IoSlice::new(head), IoSlice::new(one)]).await?,
        _ => {
            let mut slices: Vec<IoSlice<'_>> =
                std::iter::once(IoSlice::new(head)).chain(body.iter().map(|c| IoSlice::new(c))).collect();
            write_all(stream, &mut slices).await?;
        }
    }
    Ok((started, refused))
}

/// Writes all of `bufs`.
async fn write_all(stream: &mut Stream, mut bufs: &mut [IoSlice<'_>]) -> std::io::Result<()> {
    while !bufs.is_empty() {
        let n = std::future::poll_fn(|cx| Pin::new(&mut *stream).poll_write_vectored(cx, bufs)).await?;
        if n == 0 {
            return Err(std::io::ErrorKind::WriteZero.into());
        }
        IoSlice::advance_slices(&mut bufs, n);
    }
    Ok(())
}

/// Parses the request at the start of `buf`.
fn parse(buf: &[u8], max_head: usize) -> Parsed<'_> {
    let mut raw = [httparse::EMPTY_HEADER; MAX_HEADERS];
    let mut req = httparse::Request::new(&mut raw);
    let len = match req.parse(buf) {
        Ok(httparse::Status::Complete(len)) if len <= max_head => len,
        Ok(httparse::Status::Partial) if buf.len() < max_head => return Parsed::Partial,
        _ => return Parsed::Hyper,
    };
    let method = match req.method {
        Some("GET") => Method::GET,
        Some("HEAD") => Method::HEAD,
        _ => return Parsed::Hyper,
    };
    let (Some(1), Some(path)) = (req.version, req.path) else { return Parsed::Hyper };
    let Some(route) = route(path) else { return Parsed::Hyper };
    let mut headers = HeaderMap::new();
    let mut credentials = [None; 3];
    for h in req.headers.iter() {
        if let Some(i) = ["authorization", "origin", "referer"].iter().position(|n| h.name.eq_ignore_ascii_case(n)) {
            credentials[i] = Some(h.value);
        }
        if HYPER_HEADERS.iter().any(|n| h.name.eq_ignore_ascii_case(n))
            && !(h.name.eq_ignore_ascii_case("connection") && h.value.eq_ignore_ascii_case(b"keep-alive"))
        {
            return Parsed::Hyper;
        }
        // `httparse` allows only token characters in names, as `HeaderName` does; values are
        // checked as `HeaderValue` checks them, without copying the ones no handler reads.
        match READ_HEADERS.iter().find(|n| h.name.eq_ignore_ascii_case(n.as_str())) {
            Some(name) => match HeaderValue::from_bytes(h.value) {
                Ok(value) => {
                    headers.append(name.clone(), value);
                }
                Err(_) => return Parsed::Hyper,
            },
            None if !h.value.iter().all(|&b| (b >= b' ' && b != 0x7f) || b == b'\t') => return Parsed::Hyper,
            None => {}
        }
    }
    Parsed::Request(Request { len, method, path, route, headers, credentials })
}

/// Parses `bytes` as the lean path does, for fuzzing and tests: the head's length and the
/// route template (as the metrics name it) of a request it would answer, checking that the
/// two routers agree.
///
/// # Panics
/// When the lean path's route and the router's differ, or the head overruns `bytes`.
#[doc(hidden)]
pub fn inspect_head(bytes: &[u8], max_head: usize) -> Option<(usize, &'static str)> {
    let Parsed::Request(request) = parse(bytes, max_head) else { return None };
    assert!(request.len <= bytes.len() && request.len <= max_head, "head of {} bytes", request.len);
    match &request.route {
        Lean::Archive(file) => assert!(file.ends_with(".tspack") && !file.contains('/')),
        Lean::Tile { name, layer, .. } => assert!(!name.is_empty() && !layer.is_empty()),
        Lean::WebTile(tile) => assert!(!tile.0.name.is_empty() && !tile.0.layer.is_empty() && !tile.0.file.is_empty()),
    }
    let route = request.route.route();
    assert_eq!(Route::of(request.path), route, "{:?}", request.path);
    Some((request.len, route.template()))
}

/// The lean route a path names, if any: only paths that the router would match the same
/// way and whose segments need no decoding.
fn route(target: &str) -> Option<Lean<'_>> {
    // Only a web tile's query is read here (its plain parameters); any other target with
    // a query goes to the router.
    let (path, query) = match target.split_once('?') {
        Some((path, query)) => (path, Some(query)),
        None => (target, None),
    };
    if !target.is_ascii() || path.contains(['%', '#']) || query.is_some_and(|q| q.contains(['%', '#', '?'])) {
        return None;
    }
    let mut segments = path.strip_prefix('/')?.split('/');
    let s: [Option<&str>; 6] = std::array::from_fn(|_| segments.next());
    match s {
        [Some(name), Some("xyz"), Some(layer), Some(z), Some(x), Some(file)]
            if ![name, layer, z, x, file].contains(&"") && segments.next().is_none() =>
        {
            let at = WebTileAt { name, layer, z: z.parse().ok()?, x: x.parse().ok()?, file };
            Some(Lean::WebTile(Box::new((at, TileQuery::plain(query.unwrap_or(""))?))))
        }
        _ if query.is_some() => None,
        [Some(file), None, ..] if file.len() > ".tspack".len() && file.ends_with(".tspack") => {
            Some(Lean::Archive(file))
        }
        [Some(name), Some(layer), Some(lod), Some(x), Some(y), None] if !name.is_empty() && !layer.is_empty() => {
            Some(Lean::Tile {
                name,
                layer,
                at: TileAt { lod: lod.parse().ok()?, x: x.parse().ok()?, y: y.parse().ok()? },
            })
        }
        _ => None,
    }
}

/// The response head as hyper writes it: status line, the headers, `content-length` where
/// the handler left it out and the status has a body, `date`.
fn write_head(out: &mut Vec<u8>, answer: &Answer) {
    out.clear();
    let status = answer.status();
    out.extend_from_slice(b"HTTP/1.1 ");
    out.extend_from_slice(status.as_str().as_bytes());
    out.push(b' ');
    out.extend_from_slice(status.canonical_reason().unwrap_or("").as_bytes());
    out.extend_from_slice(b"\r\n");
    let headers = answer.headers();
    for (name, value) in headers {
        out.extend_from_slice(name.as_str().as_bytes());
        out.extend_from_slice(b": ");
        out.extend_from_slice(value.as_bytes());
        out.extend_from_slice(b"\r\n");
    }
    let bodiless = status == StatusCode::NOT_MODIFIED || status == StatusCode::NO_CONTENT || status.is_informational();
    if !bodiless && !headers.contains_key(CONTENT_LENGTH) {
        out.extend_from_slice(b"content-length: ");
        out.extend_from_slice(answer.body().len().to_string().as_bytes());
        out.extend_from_slice(b"\r\n");
    }
    if !headers.contains_key(DATE) {
        out.extend_from_slice(b"date: ");
        http_date(out);
        out.extend_from_slice(b"\r\n");
    }
    out.extend_from_slice(b"\r\n");
}

/// Appends the current time as an HTTP date, formatted once a second per thread.
fn http_date(out: &mut Vec<u8>) {
    use std::cell::RefCell;
    thread_local! {
        static CACHED: RefCell<(u64, String)> = const { RefCell::new((u64::MAX, String::new())) };
    }
    let now = SystemTime::now();
    let second = now.duration_since(SystemTime::UNIX_EPOCH).map_or(0, |d| d.as_secs());
    CACHED.with(|cached| {
        let mut cached = cached.borrow_mut();
        if cached.0 != second {
            *cached = (second, httpdate::fmt_http_date(now));
        }
        out.extend_from_slice(cached.1.as_bytes());
    });
}

/// A connection handed to hyper: the bytes the lean path read first, then the socket.
#[derive(Debug)]
pub(crate) struct Rewind {
    prefix: Bytes,
    inner: Stream,
}

impl Rewind {
    /// `inner`, whose next bytes are `prefix`.
    pub(crate) fn new(prefix: Bytes, inner: Stream) -> Self {
        Self { prefix, inner }
    }
}

impl AsyncRead for Rewind {
    fn poll_read(mut self: Pin<&mut Self>, cx: &mut Context<'_>, buf: &mut ReadBuf<'_>) -> Poll<std::io::Result<()>> {
        if self.prefix.is_empty() {
            return Pin::new(&mut self.inner).poll_read(cx, buf);
        }
        let n = self.prefix.len().min(buf.remaining());
        buf.put_slice(&self.prefix[..n]);
        self.prefix.advance(n);
        Poll::Ready(Ok(()))
    }
}

impl AsyncWrite for Rewind {
    fn poll_write(mut self: Pin<&mut Self>, cx: &mut Context<'_>, buf: &[u8]) -> Poll<std::io::Result<usize>> {
        Pin::new(&mut self.inner).poll_write(cx, buf)
    }

    fn poll_write_vectored(
        mut self: Pin<&mut Self>,
        cx: &mut Context<'_>,
        bufs: &[IoSlice<'_>],
    ) -> Poll<std::io::Result<usize>> {
        Pin::new(&mut self.inner).poll_write_vectored(cx, bufs)
    }

    fn is_write_vectored(&self) -> bool {
        self.inner.is_write_vectored()
    }

    fn poll_flush(mut self: Pin<&mut Self>, cx: &mut Context<'_>) -> Poll<std::io::Result<()>> {
        Pin::new(&mut self.inner).poll_flush(cx)
    }

    fn poll_shutdown(mut self: Pin<&mut Self>, cx: &mut Context<'_>) -> Poll<std::io::Result<()>> {
        Pin::new(&mut self.inner).poll_shutdown(cx)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn lean(request: &str) -> bool {
        matches!(parse(request.as_bytes(), 16 * 1024), Parsed::Request(_))
    }

    #[test]
    fn only_plain_requests_of_the_hot_routes_take_the_lean_path() {
        for ok in [
            "GET /a.tspack HTTP/1.1\r\nHost: x\r\nRange: bytes=0-9\r\n\r\n",
            "HEAD /a.tspack HTTP/1.1\r\n\r\n",
            "GET /a/elevation/3/1/2 HTTP/1.1\r\nConnection: Keep-Alive\r\n\r\n",
            "GET /a/0/0/0/0 HTTP/1.1\r\nAccept-Encoding: zstd\r\n\r\n",
        ] {
            assert!(lean(ok), "{ok:?} should be lean");
        }
        for hyper in [
            "POST /a.tspack HTTP/1.1\r\n\r\n",
            "OPTIONS /a.tspack HTTP/1.1\r\n\r\n",
            "GET /a.tspack HTTP/1.0\r\n\r\n",
            "PRI * HTTP/2.0\r\n\r\nSM\r\n\r\n",
            "GET /a.tspack HTTP/1.1\r\nConnection: close\r\n\r\n",
            "GET /a.tspack HTTP/1.1\r\nContent-Length: 3\r\n\r\nabc",
            "GET /a.tspack HTTP/1.1\r\nTransfer-Encoding: chunked\r\n\r\n",
            "GET /a.tspack HTTP/1.1\r\nExpect: 100-continue\r\n\r\n",
            "GET /a.tspack HTTP/1.1\r\nUpgrade: h2c\r\n\r\n",
            "GET /a%2Eb.tspack HTTP/1.1\r\n\r\n",
            "GET /a.tspack?x=1 HTTP/1.1\r\n\r\n",
            "GET /.tspack HTTP/1.1\r\n\r\n",
            "GET /a.tspack/ HTTP/1.1\r\n\r\n",
            "GET /a HTTP/1.1\r\n\r\n",
            "GET / HTTP/1.1\r\n\r\n",
            "GET /metrics HTTP/1.1\r\n\r\n",
            "GET /a/metadata HTTP/1.1\r\n\r\n",
            "GET /view/a HTTP/1.1\r\n\r\n",
            "GET /a/e/256/0/0 HTTP/1.1\r\n\r\n",
            "GET /a/e/1/-1/0 HTTP/1.1\r\n\r\n",
            "GET /a/e/1/0/0/ HTTP/1.1\r\n\r\n",
            "GET //e/1/0/0 HTTP/1.1\r\n\r\n",
            "GET http://x/a.tspack HTTP/1.1\r\n\r\n",
            "GET /a.tspack HTTP/1.1\r\nBad Header: x\r\n\r\n",
            "garbage\r\n\r\n",
        ] {
            assert!(!lean(hyper), "{hyper:?} should go to hyper");
        }
        let many: String = (0..=MAX_HEADERS).map(|i| format!("x-{i}: 1\r\n")).collect();
        assert!(!lean(&format!("GET /a.tspack HTTP/1.1\r\n{many}\r\n")));
    }

    /// Mutated requests (bytes changed, dropped, duplicated, truncated), deterministic: the
    /// parser never panics, and what it takes, it routes as the router does.
    #[test]
    #[allow(clippy::cast_possible_truncation)]
    fn mutated_heads_never_panic_and_route_as_the_router() {
        let seeds: [&[u8]; 4] = [
            b"GET /a.tspack HTTP/1.1\r\nHost: x\r\nRange: bytes=0-9\r\n\r\n",
            b"HEAD /a/elevation/3/1/2 HTTP/1.1\r\nConnection: keep-alive\r\n\r\n",
            b"GET /n/0/0/0/0 HTTP/1.1\r\nAccept-Encoding: zstd\r\nIf-None-Match: \"x\"\r\n\r\n",
            b"GET /b.tspack HTTP/1.1\r\n\r\nGET /c.tspack HTTP/1.1\r\n\r\n",
        ];
        let mut state = 0x9E37_79B9_7F4A_7C15_u64;
        let mut next = move || {
            state ^= state << 13;
            state ^= state >> 7;
            state ^= state << 17;
            state
        };
        let (mut taken, mut refused) = (0, 0);
        for round in 0..100_000 {
            let mut bytes = seeds[round % seeds.len()].to_vec();
            const PICKS: &[u8] = b"/%.?:\r\n 0aZ-+";
            for _ in 0..1 + next() % 4 {
                if bytes.is_empty() {
                    bytes.push(b'G');
                }
                let at = (next() as usize) % bytes.len();
                match next() % 5 {
                    0 => bytes[at] = next() as u8,
                    1 => bytes[at] = PICKS[(next() as usize) % PICKS.len()],
                    2 if bytes.len() > 1 => {
                        bytes.remove(at);
                    }
                    3 => bytes.insert(at, bytes[at]),
                    _ => bytes.truncate(at),
                }
            }
            match inspect_head(&bytes, 1024) {
                Some(_) => taken += 1,
                None => refused += 1,
            }
        }
        assert!(taken > 1000 && refused > 1000, "{taken} taken, {refused} refused");
    }

    #[test]
    fn only_the_headers_handlers_read_are_kept_and_every_value_is_checked() {
        let request = b"GET /a.tspack HTTP/1.1\r\nHost: x\r\nUser-Agent: y\r\nRANGE: bytes=0-9\r\nX-Custom: \xff z\r\n\
                        If-None-Match: \"e\"\r\nAccept-Encoding: zstd\r\nAccept-Encoding: gzip\r\n\r\n";
        let Parsed::Request(r) = parse(request, 1024) else { panic!("not lean") };
        let kept: Vec<(&str, &[u8])> = r.headers.iter().map(|(n, v)| (n.as_str(), v.as_bytes())).collect();
        assert_eq!(
            kept,
            [
                ("range", &b"bytes=0-9"[..]),
                ("if-none-match", b"\"e\""),
                ("accept-encoding", b"zstd"),
                ("accept-encoding", b"gzip")
            ]
        );
        // A control character in a header no handler reads still sends the request to hyper.
        let mut bad = b"GET /a.tspack HTTP/1.1\r\nX-Custom: a".to_vec();
        bad.extend_from_slice(b"\x01b\r\n\r\n");
        assert!(!matches!(parse(&bad, 1024), Parsed::Request(_)));
    }

    #[test]
    fn partial_heads_wait_until_they_are_too_long() {
        assert!(matches!(parse(b"GET /a.tspack HTTP/1.1\r\nRange: by", 1024), Parsed::Partial));
        let long = format!("GET /a.tspack HTTP/1.1\r\nx-pad: {}", "y".repeat(2000));
        assert!(matches!(parse(long.as_bytes(), 1024), Parsed::Hyper));
        let complete = format!("{long}\r\n\r\n");
        assert!(matches!(parse(complete.as_bytes(), 1024), Parsed::Hyper), "a complete head over the limit");
    }

    #[test]
    fn heads_have_length_and_date_unless_bodiless() {
        let mut out = Vec::new();
        let mut answer = Answer::new(crate::body::Payload::from("hi"));
        answer.headers_mut().insert("x-a", HeaderValue::from_static("1"));
        write_head(&mut out, &answer);
        let text = String::from_utf8(out.clone()).unwrap();
        assert!(text.starts_with("HTTP/1.1 200 OK\r\nx-a: 1\r\ncontent-length: 2\r\ndate: "), "{text}");
        assert!(text.ends_with(" GMT\r\n\r\n"), "{text}");
        *answer.status_mut() = StatusCode::NOT_MODIFIED;
        write_head(&mut out, &answer);
        let text = String::from_utf8(out).unwrap();
        assert!(text.starts_with("HTTP/1.1 304 Not Modified\r\nx-a: 1\r\ndate: "), "{text}");
    }
}
