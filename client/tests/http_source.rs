//! The HTTP Range source against our server and nginx: same tiles as mmap, one request to
//! open, replaced archives detected, transient failures retried.
#![allow(clippy::unwrap_used, clippy::expect_used, clippy::cast_possible_truncation, missing_docs)]

use std::sync::Arc;
use std::sync::atomic::{AtomicU64, Ordering};
use std::time::Duration;

use axum::body::Body;
use axum::http::{Request, StatusCode};
use axum::middleware::Next;
use axum::response::{IntoResponse, Response};
use terrastream_client::{HttpSource, RetryPolicy};
use terrastream_format::{AsyncReader, Error, MmapSource, Reader, TileKey};
use terrastream_server::app;
use terrastream_testkit::archives::{archives, write_zstd_archive};
use terrastream_testkit::nginx::start_nginx;
use terrastream_testkit::server::{serve_router as serve, state};

/// Every tile of every layer and LOD, read through `reader`, equals the mmap reader's.
async fn same_tiles(reader: &AsyncReader<HttpSource>, local: &Reader<MmapSource>) -> usize {
    let mut n = 0;
    for (li, l) in local.metadata().layers.iter().enumerate() {
        for lod in 0..l.num_lods {
            let (nx, ny) = l.grid_at(lod);
            for y in 0..ny {
                for x in 0..nx {
                    let key = TileKey::new(li as u8, lod, x, y).unwrap();
                    assert_eq!(reader.tile(key).await.unwrap(), local.tile(key).unwrap(), "{key}");
                    n += 1;
                }
            }
        }
    }
    n
}

#[tokio::test]
async fn same_tiles_from_our_server_and_nginx_with_one_request_to_open() {
    let (dir, path) = archives();
    let local = Reader::new(MmapSource::open(&path).unwrap()).unwrap();
    let (addr, _task) = serve(app(state(dir.path())), "127.0.0.1:0").await;
    let mut urls = vec![format!("http://{addr}/sample.tspack")];
    // nginx with the shipped static-hosting config (deploy/nginx), on a test port and root.
    let shipped =
        std::fs::read_to_string(concat!(env!("CARGO_MANIFEST_DIR"), "/../deploy/nginx/tspack-static.conf")).unwrap();
    let config =
        shipped.replace("listen 8080;", "listen 127.0.0.1:{port};").replace("root /srv/terrastream;", "root {root};");
    let nginx = start_nginx(dir.path(), &config);
    if let Some(n) = &nginx {
        let url = format!("http://127.0.0.1:{}/sample.tspack", n.port);
        let client = reqwest::Client::new();
        let r =
            client.get(&url).header("range", "bytes=0-9").header("origin", "https://x.example").send().await.unwrap();
        assert_eq!(r.status(), 206);
        assert_eq!(r.headers()["access-control-allow-origin"], "*");
        let exposed = r.headers()["access-control-expose-headers"].to_str().unwrap().to_lowercase();
        assert!(exposed.contains("etag") && exposed.contains("content-range"), "{exposed}");
        assert_eq!(r.headers()["cache-control"], "public, max-age=3600");
        let preflight = client
            .request(reqwest::Method::OPTIONS, &url)
            .header("origin", "https://x.example")
            .header("access-control-request-method", "GET")
            .header("access-control-request-headers", "range, if-match")
            .send()
            .await
            .unwrap();
        assert_eq!(preflight.status(), 204);
        assert!(preflight.headers()["access-control-allow-headers"].to_str().unwrap().contains("If-Match"));
        urls.push(url);
    }
    for url in urls {
        let reader = AsyncReader::new(HttpSource::new(&url).unwrap()).await.unwrap();
        assert_eq!(reader.source().stats().requests.load(Ordering::SeqCst), 1, "{url}: opening costs one request");
        let tiles = same_tiles(&reader, &local).await;
        let requests = reader.source().stats().requests.load(Ordering::SeqCst);
        // The sample's root holds every entry: one request per present tile beyond the first
        // 16 KiB (those came with the bootstrap), none for missing ones.
        let mut beyond_head = 0;
        local
            .for_each_entry(|e| -> terrastream_format::Result<()> {
                if local.header().data.offset + e.offset + e.stored_len() > 16 * 1024 {
                    beyond_head += u64::from(e.run_length);
                }
                Ok(())
            })
            .unwrap();
        assert_eq!(requests, 1 + beyond_head, "{url}: {tiles} tiles asked");
    }
}

#[tokio::test]
async fn a_replaced_archive_is_detected_not_mixed() {
    let (dir, _) = archives();
    let s = state(dir.path());
    let (addr, _task) = serve(app(s.clone()), "127.0.0.1:0").await;
    let reader = AsyncReader::new(HttpSource::new(&format!("http://{addr}/sample.tspack")).unwrap()).await.unwrap();
    assert!(reader.tile(TileKey::new(0, 0, 7, 5).unwrap()).await.unwrap().is_some());
    // A new version published by rename (here: same bytes, a new file: a new ETag).
    let path = dir.path().join("sample.tspack");
    let bytes = std::fs::read(&path).unwrap();
    std::fs::write(dir.path().join("next.partial"), &bytes).unwrap();
    std::fs::rename(dir.path().join("next.partial"), &path).unwrap();
    s.catalog.reload();
    let err = reader.tile(TileKey::new(0, 0, 6, 5).unwrap()).await.unwrap_err();
    assert!(matches!(err, Error::Changed { .. }), "{err}");
    // A small archive lies entirely in the first 16 KiB: the reader keeps its consistent snapshot.
    let small = AsyncReader::new(HttpSource::new(&format!("http://{addr}/elev.tspack")).unwrap()).await.unwrap();
    write_zstd_archive(&dir.path().join("elev.tspack"), 2);
    s.catalog.reload();
    let key = TileKey::new(0, 0, 1, 1).unwrap();
    let tile = small.tile(key).await.unwrap().unwrap();
    assert_eq!(
        terrastream_format::zstd_decompress(&tile, 1 << 20, "t").unwrap(),
        terrastream_testkit::archives::raw_tile(key, 1)
    );
}

#[tokio::test]
async fn failures_are_retried_with_backoff() {
    let (dir, path) = archives();
    let local = Reader::new(MmapSource::open(&path).unwrap()).unwrap();
    // Every third request fails with 500; every fifth that gets through is cut short.
    let counter = Arc::new(AtomicU64::new(0));
    let c = counter.clone();
    let flaky = app(state(dir.path())).layer(axum::middleware::from_fn(move |req: Request<Body>, next: Next| {
        let n = c.fetch_add(1, Ordering::SeqCst);
        async move {
            if n % 3 == 2 {
                return StatusCode::INTERNAL_SERVER_ERROR.into_response();
            }
            let response: Response = next.run(req).await;
            if n % 5 == 4 && response.status() == StatusCode::PARTIAL_CONTENT {
                let (mut parts, body) = response.into_parts();
                let bytes = axum::body::to_bytes(body, usize::MAX).await.unwrap();
                parts.headers.remove("content-length");
                return Response::from_parts(parts, Body::from(bytes.slice(..bytes.len() / 2)));
            }
            response
        }
    }));
    let (addr, _task) = serve(flaky, "127.0.0.1:0").await;
    let policy = RetryPolicy { attempts: 6, first_backoff: Duration::from_millis(1), ..RetryPolicy::default() };
    let source =
        HttpSource::with_client(reqwest::Client::new(), &format!("http://{addr}/sample.tspack"), policy).unwrap();
    let reader = AsyncReader::new(source).await.unwrap();
    same_tiles(&reader, &local).await;
    assert!(reader.source().stats().retries.load(Ordering::SeqCst) > 10, "failures happened and were retried");
}

#[tokio::test]
async fn a_stopped_server_is_an_error_then_recovery_when_it_is_back() {
    let (dir, path) = archives();
    let local = Reader::new(MmapSource::open(&path).unwrap()).unwrap();
    let s = state(dir.path());
    let listener = tokio::net::TcpListener::bind("127.0.0.1:0").await.unwrap();
    let addr = listener.local_addr().unwrap();
    let task = tokio::spawn(axum::serve(listener, app(s.clone())).into_future());
    let policy = RetryPolicy { attempts: 2, first_backoff: Duration::from_millis(1), ..RetryPolicy::default() };
    let source =
        HttpSource::with_client(reqwest::Client::new(), &format!("http://{addr}/sample.tspack"), policy).unwrap();
    let reader = AsyncReader::new(source).await.unwrap();
    let key = TileKey::new(0, 3, 0, 0).unwrap();
    assert_eq!(reader.tile(key).await.unwrap(), local.tile(key).unwrap());
    task.abort();
    let _ = task.await;
    let other = TileKey::new(0, 2, 1, 1).unwrap();
    let err = reader.tile(other).await.unwrap_err();
    assert!(matches!(err, Error::Source { .. }), "{err}");
    // Back on the same port: the same reader recovers.
    let listener = tokio::net::TcpListener::bind(addr).await.unwrap();
    let _task = tokio::spawn(axum::serve(listener, app(s)).into_future());
    assert_eq!(reader.tile(other).await.unwrap(), local.tile(other).unwrap());
}

/// `HttpSource::new_http2`: HTTP/2 without TLS (prior knowledge) against our server, which
/// answers it on the same port as HTTP/1.1: the same tiles, over one multiplexed connection.
#[tokio::test]
async fn http2_without_tls_reads_the_same_tiles() {
    let (dir, path) = archives();
    let local = Reader::new(MmapSource::open(&path).unwrap()).unwrap();
    let (addr, _task) = serve(app(state(dir.path())), "127.0.0.1:0").await;
    let url = format!("http://{addr}/sample.tspack");
    let h2 = reqwest::Client::builder().http2_prior_knowledge().build().unwrap();
    let r = h2.get(&url).header("range", "bytes=0-9").send().await.unwrap();
    assert_eq!((r.status().as_u16(), r.version()), (206, reqwest::Version::HTTP_2));
    let reader = AsyncReader::new(HttpSource::new_http2(&url).unwrap()).await.unwrap();
    assert!(same_tiles(&reader, &local).await > 10);
}
