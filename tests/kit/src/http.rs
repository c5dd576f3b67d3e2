//! A plain HTTP/1.1 client for tests (one request per connection), the server's
//! archive-request counter, and a multipart/byteranges splitter.

use std::io::{Read, Write};
use std::time::Duration;

use serde_json::Value;

/// One HTTP/1.1 exchange on a fresh connection: (status, body).
pub fn request(port: u16, method: &str, path: &str, body: Option<&Value>) -> (u16, Vec<u8>) {
    let mut s = std::net::TcpStream::connect(("127.0.0.1", port)).unwrap();
    s.set_read_timeout(Some(Duration::from_secs(180))).unwrap();
    let body = body.map(Value::to_string).unwrap_or_default();
    write!(
        s,
        "{method} {path} HTTP/1.1\r\nHost: 127.0.0.1:{port}\r\nContent-Type: application/json\r\n\
         Content-Length: {}\r\nConnection: close\r\n\r\n{body}",
        body.len()
    )
    .unwrap();
    // Read by Content-Length: chromedriver keeps the connection open after answering.
    let mut answer = Vec::new();
    let mut buf = [0u8; 64 * 1024];
    let end = loop {
        if let Some(end) = answer.windows(4).position(|w| w == b"\r\n\r\n") {
            break end;
        }
        let n = s.read(&mut buf).unwrap();
        assert!(n > 0, "connection closed before an HTTP answer");
        answer.extend_from_slice(&buf[..n]);
    };
    let head = String::from_utf8_lossy(&answer[..end]).to_lowercase();
    let status = head.split(' ').nth(1).and_then(|s| s.parse().ok()).unwrap_or(0);
    let length =
        head.lines().find_map(|l| l.strip_prefix("content-length:")).and_then(|v| v.trim().parse::<usize>().ok());
    let mut payload = answer[end + 4..].to_vec();
    match length {
        Some(length) => {
            while payload.len() < length {
                let n = s.read(&mut buf).unwrap();
                assert!(n > 0, "connection closed mid-body");
                payload.extend_from_slice(&buf[..n]);
            }
        }
        None => {
            s.read_to_end(&mut payload).unwrap();
        }
    }
    (status, payload)
}

/// Archive GETs the server answered, from its `/metrics` (route `/{file}`).
pub fn archive_requests(port: u16) -> u64 {
    let (_, body) = request(port, "GET", "/metrics", None);
    String::from_utf8(body)
        .unwrap()
        .lines()
        .filter(|l| l.starts_with("terrastream_requests_total{route=\"/{file}\""))
        .filter_map(|l| l.rsplit(' ').next()?.parse::<u64>().ok())
        .sum()
}

/// Splits a multipart/byteranges body into (Content-Range, data) parts.
pub fn split_multipart(body: &[u8], boundary: &str) -> Vec<(String, Vec<u8>)> {
    let delimiter = format!("--{boundary}");
    let find = |hay: &[u8], n: &[u8]| hay.windows(n.len()).position(|w| w == n);
    let mut out = Vec::new();
    let mut rest = body;
    while let Some(at) = find(rest, delimiter.as_bytes()) {
        rest = &rest[at + delimiter.len()..];
        if rest.starts_with(b"--") {
            break;
        }
        let head_end = find(rest, b"\r\n\r\n").unwrap();
        let head = String::from_utf8_lossy(&rest[..head_end]).to_lowercase();
        let range = head.lines().find_map(|l| l.strip_prefix("content-range: ")).unwrap().to_owned();
        let start = head_end + 4;
        let len = find(&rest[start..], format!("\r\n{delimiter}").as_bytes()).unwrap();
        out.push((range, rest[start..start + len].to_vec()));
        rest = &rest[start + len..];
    }
    out
}
