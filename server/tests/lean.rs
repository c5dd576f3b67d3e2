//! The lean HTTP/1.1 path answers exactly as hyper and the router do: the same requests,
//! on real sockets, to a server with it and one without, give the same status lines,
//! headers (but `date`) and bodies; pipelined requests are answered in order; whatever the
//! lean path does not take still works on the same connection; shutdown closes its idle
//! connections at once.
#![allow(clippy::unwrap_used, clippy::expect_used, missing_docs)]

use std::path::Path;
use std::time::{Duration, Instant};

use terrastream_testkit::archives::archives;
use terrastream_testkit::server::Running;
use tokio::io::{AsyncReadExt, AsyncWriteExt};
use tokio::net::TcpStream;

async fn start(dir: &Path, lean: bool) -> Running {
    terrastream_testkit::server::start(dir, |c| c.lean_http1 = lean).await
}

/// One answer: status line, headers (lowercase, sorted, without `date`), body.
#[derive(Debug, PartialEq)]
struct Answer {
    status: String,
    headers: Vec<String>,
    body: Vec<u8>,
}

/// Reads one answer from `stream`, buffering past it in `buf`.
async fn read_answer(stream: &mut TcpStream, buf: &mut Vec<u8>, head_request: bool) -> Answer {
    let end = loop {
        if let Some(at) = buf.windows(4).position(|w| w == b"\r\n\r\n") {
            break at + 4;
        }
        read_more(stream, buf, "a whole head").await;
    };
    let head = String::from_utf8(buf[..end].to_vec()).unwrap();
    let mut lines = head.trim_end().split("\r\n");
    let status = lines.next().unwrap().to_string();
    let mut headers: Vec<String> = lines
        .map(|l| {
            let (name, value) = l.split_once(':').unwrap();
            format!("{}: {}", name.to_ascii_lowercase(), value.trim())
        })
        .filter(|l| !l.starts_with("date: "))
        .collect();
    headers.sort();
    let length =
        headers.iter().find_map(|h| h.strip_prefix("content-length: ")).map_or(0, |v| v.parse::<usize>().unwrap());
    let length = if head_request || status.contains(" 304 ") { 0 } else { length };
    while buf.len() < end + length {
        read_more(stream, buf, "the whole body").await;
    }
    let body = buf[end..end + length].to_vec();
    buf.drain(..end + length);
    Answer { status, headers, body }
}

/// Appends what the server sends next to `buf`; it must send something before closing.
async fn read_more(stream: &mut TcpStream, buf: &mut Vec<u8>, wanted: &str) {
    let mut chunk = [0u8; 65536];
    let n = tokio::time::timeout(Duration::from_secs(10), stream.read(&mut chunk)).await.unwrap().unwrap();
    assert!(n > 0, "closed before {wanted}: {:?}", String::from_utf8_lossy(buf));
    buf.extend_from_slice(&chunk[..n]);
}

fn request(method: &str, path: &str, headers: &[&str]) -> String {
    let mut r = format!("{method} {path} HTTP/1.1\r\nHost: test\r\n");
    for h in headers {
        r.push_str(h);
        r.push_str("\r\n");
    }
    r.push_str("\r\n");
    r
}

/// The requests compared: every case of the two lean routes, and some that go to hyper.
fn requests() -> Vec<(String, bool)> {
    let cases: &[(&str, &str, &[&str])] = &[
        ("GET", "/sample.tspack", &[]),
        ("GET", "/sample.tspack", &["Range: bytes=0-99"]),
        ("GET", "/sample.tspack", &["Range: bytes=-10", "Connection: keep-alive"]),
        ("GET", "/sample.tspack", &["Range: bytes=5-"]),
        ("GET", "/sample.tspack", &["Range: bytes=0-0,5-9,3-4"]),
        ("GET", "/sample.tspack", &["Range: bytes=999999999-"]),
        ("GET", "/sample.tspack", &["Range: bytes=x"]),
        ("GET", "/sample.tspack", &["If-None-Match: *"]),
        ("GET", "/sample.tspack", &["If-Match: \"nope\""]),
        ("GET", "/sample.tspack", &["If-Range: \"old\"", "Range: bytes=0-9"]),
        ("GET", "/sample.tspack", &["If-Modified-Since: Sun, 06 Nov 2095 08:49:37 GMT"]),
        ("HEAD", "/sample.tspack", &[]),
        ("HEAD", "/sample.tspack", &["Range: bytes=1-2"]),
        ("GET", "/missing.tspack", &[]),
        ("HEAD", "/missing.tspack", &[]),
        ("GET", "/elev/elevation/0/0/0", &[]),
        ("GET", "/elev/elevation/0/0/0", &["Accept-Encoding: gzip, zstd"]),
        ("GET", "/elev/elevation/0/0/0", &["Accept-Encoding: zstd;q=0"]),
        ("HEAD", "/elev/0/1/1", &["Accept-Encoding: zstd"]),
        ("GET", "/elev/elevation/0/0/1", &[]),
        ("GET", "/elev/elevation/1/0/0", &["If-None-Match: *"]),
        ("GET", "/elev/elevation/0/9/9", &[]),
        ("GET", "/elev/elevation/9/0/0", &[]),
        ("GET", "/elev/nope/0/0/0", &[]),
        ("GET", "/nope/elevation/0/0/0", &[]),
        ("GET", "/sample/0/0/0/0", &[]),
        // Not lean: answered by hyper on both servers, on the same connection.
        ("GET", "/elev/metadata", &[]),
        ("GET", "/healthz", &[]),
        ("GET", "/sample.tspack?x=1", &["Range: bytes=0-3"]),
        ("GET", "/elev/elevation/0/%30/0", &[]),
        ("OPTIONS", "/sample.tspack", &["Origin: http://a", "Access-Control-Request-Method: GET"]),
        ("GET", "/sample.tspack", &["Range: bytes=0-3", "Connection: close"]),
        // Web tiles: lean with their plain query, to the router with any other.
        ("GET", "/elev/xyz/elevation/3/1/2.png", &[]),
        ("GET", "/elev/xyz/elevation/3/1/2.webp?size=256&encoding=mapbox", &[]),
        ("GET", "/elev/xyz/elevation/3/1/x.webp", &[]),
        ("GET", "/elev/xyz/elevation/3/1/2.webp?size=300", &[]),
        ("GET", "/elev/xyz/elevation/3/1/2.webp?other=1", &[]),
        ("GET", "/nope/xyz/elevation/3/1/2.png", &[]),
    ];
    cases.iter().map(|(m, p, h)| (request(m, p, h), *m == "HEAD")).collect()
}

#[tokio::test]
async fn lean_answers_equal_hypers() {
    let (dir, _) = archives();
    let (lean, plain) = (start(dir.path(), true).await, start(dir.path(), false).await);
    let cases = requests();
    let mut answers = Vec::new();
    for server in [&lean, &plain] {
        let mut got = Vec::new();
        let (mut stream, mut buf) = (TcpStream::connect(server.addr).await.unwrap(), Vec::new());
        for (request, head) in &cases {
            // A fresh connection after hyper took one, so that every case meets the lean path.
            if !buf.is_empty() || got.len() >= 26 {
                stream = TcpStream::connect(server.addr).await.unwrap();
                buf.clear();
            }
            stream.write_all(request.as_bytes()).await.unwrap();
            got.push(read_answer(&mut stream, &mut buf, *head).await);
        }
        answers.push(got);
    }
    for (i, ((request, _), (a, b))) in cases.iter().zip(answers[0].iter().zip(&answers[1])).enumerate() {
        assert_eq!(a, b, "case {i}: {request:?}");
    }
    // Sanity: the cases cover what they mean to.
    let statuses: Vec<&str> = answers[0].iter().map(|a| &a.status[9..12]).collect();
    for code in ["200", "206", "304", "400", "404", "412", "416", "204"] {
        assert!(statuses.contains(&code), "no {code} among {statuses:?}");
    }
    assert!(answers[0][4].headers.iter().any(|h| h.starts_with("content-type: multipart/byteranges")));
    assert!(answers[0][16].headers.contains(&"content-encoding: zstd".to_string()));
    assert!(answers[0][19].headers.iter().any(|h| h.starts_with("x-terrastream-fallback-lod: ")));
    // The lean server counted its answers as the router's routes.
    assert_eq!(lean.state.metrics.requests("/{file}"), plain.state.metrics.requests("/{file}"));
    assert_eq!(
        lean.state.metrics.requests("/{name}/{layer}/{lod}/{x}/{y}"),
        plain.state.metrics.requests("/{name}/{layer}/{lod}/{x}/{y}")
    );
    assert!(lean.state.metrics.requests("/{file}") >= 15);
    lean.stop().await;
    plain.stop().await;
}

#[tokio::test]
async fn pipelined_requests_are_answered_in_order_then_hyper_takes_over() {
    let (dir, _) = archives();
    let server = start(dir.path(), true).await;
    let mut stream = TcpStream::connect(server.addr).await.unwrap();
    let batch = [
        request("GET", "/sample.tspack", &["Range: bytes=0-3"]),
        request("HEAD", "/elev/elevation/0/1/1", &[]),
        request("GET", "/sample.tspack", &["Range: bytes=4-7"]),
        request("GET", "/healthz", &[]),
        request("GET", "/sample.tspack", &["Range: bytes=8-11"]),
    ]
    .concat();
    let file = std::fs::read(dir.path().join("sample.tspack")).unwrap();
    // In one write, then byte by byte: heads split anywhere are put together.
    for split in [false, true] {
        if split {
            for b in batch.as_bytes() {
                stream.write_all(&[*b]).await.unwrap();
            }
        } else {
            stream.write_all(batch.as_bytes()).await.unwrap();
        }
        let mut buf = Vec::new();
        let first = read_answer(&mut stream, &mut buf, false).await;
        assert_eq!((first.status.as_str(), first.body.as_slice()), ("HTTP/1.1 206 Partial Content", &file[0..4]));
        let second = read_answer(&mut stream, &mut buf, true).await;
        assert_eq!(second.status, "HTTP/1.1 200 OK");
        let third = read_answer(&mut stream, &mut buf, false).await;
        assert_eq!(third.body, &file[4..8]);
        let fourth = read_answer(&mut stream, &mut buf, false).await;
        assert_eq!(fourth.body, b"ok\n");
        let fifth = read_answer(&mut stream, &mut buf, false).await;
        assert_eq!(fifth.body, &file[8..12], "hyper answers the lean routes too once it has the connection");
        assert!(buf.is_empty());
        stream = TcpStream::connect(server.addr).await.unwrap();
    }
    server.stop().await;
}

#[tokio::test]
async fn shutdown_closes_idle_lean_connections_at_once() {
    let (dir, _) = archives();
    let server = start(dir.path(), true).await;
    let mut idle = TcpStream::connect(server.addr).await.unwrap();
    idle.write_all(request("GET", "/sample.tspack", &["Range: bytes=0-0"]).as_bytes()).await.unwrap();
    let mut buf = Vec::new();
    assert_eq!(read_answer(&mut idle, &mut buf, false).await.body.len(), 1);
    let started = Instant::now();
    server.stop().await;
    assert!(
        started.elapsed() < Duration::from_secs(5),
        "shutdown waited {:?} for an idle connection",
        started.elapsed()
    );
    let mut rest = Vec::new();
    let n = tokio::time::timeout(Duration::from_secs(5), idle.read_to_end(&mut rest)).await.unwrap().unwrap_or(0);
    assert_eq!(n, 0, "closed without another answer");
}

#[tokio::test]
async fn slow_and_oversized_lean_heads_are_cut_off_or_refused() {
    let (dir, _) = archives();
    let server = terrastream_testkit::server::start(dir.path(), |c| {
        c.request_timeout_secs = 1;
        c.max_header_bytes = 8192;
    })
    .await;
    let addr = server.addr;
    // A head never finished: closed after the timeout.
    let mut slow = TcpStream::connect(addr).await.unwrap();
    slow.write_all(b"GET /sample.tspack HTTP/1.1\r\nHost: x\r\n").await.unwrap();
    let mut rest = Vec::new();
    let closed = tokio::time::timeout(Duration::from_secs(10), slow.read_to_end(&mut rest)).await;
    assert!(closed.is_ok(), "the connection was not closed");
    // An idle connection too.
    let mut idle = TcpStream::connect(addr).await.unwrap();
    let closed = tokio::time::timeout(Duration::from_secs(10), idle.read_to_end(&mut rest)).await;
    assert!(closed.is_ok(), "the idle connection was not closed");
    // A head over the limit: hyper's 431.
    let mut big = TcpStream::connect(addr).await.unwrap();
    let request = format!("GET /sample.tspack HTTP/1.1\r\nHost: x\r\nX-Big: {}\r\n\r\n", "a".repeat(64 * 1024));
    let _ = big.write_all(request.as_bytes()).await;
    let mut answer = Vec::new();
    let _ = tokio::time::timeout(Duration::from_secs(5), big.read_to_end(&mut answer)).await;
    let text = String::from_utf8_lossy(&answer);
    assert!(text.starts_with("HTTP/1.1 431"), "{text}");
    server.stop().await;
}
