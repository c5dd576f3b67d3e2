//! Every route and case through the router with `oneshot`.
#![allow(clippy::unwrap_used, clippy::expect_used, clippy::cast_possible_truncation, missing_docs)]

use axum::body::{Body, to_bytes};
use axum::http::{Request, StatusCode};
use axum::response::Response;
use terrastream_format::{MmapSource, Reader, TileKey};
use terrastream_server::{FALLBACK_LOD, app};
use terrastream_testkit::archives::{archives, raw_tile};
use terrastream_testkit::http::split_multipart;
use terrastream_testkit::server::state;
use tower::ServiceExt;

async fn send(state: &terrastream_server::AppState, req: Request<Body>) -> (Response, Vec<u8>) {
    let response = app(state.clone()).oneshot(req).await.unwrap();
    let (parts, body) = response.into_parts();
    let bytes = to_bytes(body, usize::MAX).await.unwrap().to_vec();
    (Response::from_parts(parts, Body::empty()), bytes)
}

fn get(uri: &str, headers: &[(&str, &str)]) -> Request<Body> {
    let mut b = Request::get(uri);
    for (k, v) in headers {
        b = b.header(*k, *v);
    }
    b.body(Body::empty()).unwrap()
}

fn h(r: &Response, name: &str) -> String {
    r.headers().get(name).map(|v| v.to_str().unwrap().to_owned()).unwrap_or_default()
}

/// Splits a multipart/byteranges answer into (Content-Range, data) parts.
fn parts(content_type: &str, body: &[u8]) -> Vec<(String, Vec<u8>)> {
    split_multipart(body, content_type.split("boundary=").nth(1).unwrap())
}

#[tokio::test]
async fn whole_archive_with_validators() {
    let (dir, path) = archives();
    let s = state(dir.path());
    let file = std::fs::read(&path).unwrap();
    let (r, body) = send(&s, get("/sample.tspack", &[])).await;
    assert_eq!(r.status(), StatusCode::OK);
    assert_eq!(body, file);
    assert_eq!(h(&r, "content-length"), file.len().to_string());
    assert_eq!(h(&r, "accept-ranges"), "bytes");
    assert!(h(&r, "etag").starts_with('"'), "strong etag");
    assert!(!h(&r, "last-modified").is_empty());
    assert_eq!(h(&r, "cache-control"), "public, max-age=3600");

    let head = Request::head("/sample.tspack").body(Body::empty()).unwrap();
    let (r, body) = send(&s, head).await;
    assert_eq!(r.status(), StatusCode::OK);
    assert!(body.is_empty());
    assert_eq!(h(&r, "content-length"), file.len().to_string());
}

#[tokio::test]
async fn ranges_single_open_suffix_multi_and_unsatisfiable() {
    let (dir, path) = archives();
    let s = state(dir.path());
    let file = std::fs::read(&path).unwrap();
    let len = file.len();
    for (range, start, end) in [
        ("bytes=0-127", 0, 128),
        ("bytes=100-", 100, len),
        ("bytes=-50", len - 50, len),
        ("bytes=10-99999999", 10, len),
    ] {
        let (r, body) = send(&s, get("/sample.tspack", &[("range", range)])).await;
        assert_eq!(r.status(), StatusCode::PARTIAL_CONTENT, "{range}");
        assert_eq!(h(&r, "content-range"), format!("bytes {start}-{}/{len}", end - 1));
        assert_eq!(body, &file[start..end]);
    }
    for range in
        [format!("bytes={len}-"), format!("bytes={}-{}", len + 5, len + 10), "bytes=x-1".into(), "bytes=1-2;3".into()]
    {
        let (r, body) = send(&s, get("/sample.tspack", &[("range", &range)])).await;
        assert_eq!(r.status(), StatusCode::RANGE_NOT_SATISFIABLE, "{range}");
        assert_eq!(h(&r, "content-range"), format!("bytes */{len}"));
        assert!(body.is_empty());
    }
    // Multiple and overlapping ranges: multipart/byteranges, parts in request order.
    let (r, body) = send(&s, get("/sample.tspack", &[("range", "bytes=0-9, 5-14, -4")])).await;
    assert_eq!(r.status(), StatusCode::PARTIAL_CONTENT);
    let ct = h(&r, "content-type");
    assert!(ct.starts_with("multipart/byteranges; boundary="), "{ct}");
    assert_eq!(h(&r, "content-length"), body.len().to_string());
    let got = parts(&ct, &body);
    assert_eq!(got.len(), 3);
    assert_eq!(got[0], (format!("bytes 0-9/{len}"), file[0..10].to_vec()));
    assert_eq!(got[1], (format!("bytes 5-14/{len}"), file[5..15].to_vec()));
    assert_eq!(got[2], (format!("bytes {}-{}/{len}", len - 4, len - 1), file[len - 4..].to_vec()));
    // Hundreds of ranges: past max_ranges (256) the whole file, as nginx does.
    let many: Vec<String> = (0..300).map(|i| format!("{}-{}", i * 10, i * 10 + 1)).collect();
    let (r, body) = send(&s, get("/sample.tspack", &[("range", &format!("bytes={}", many.join(",")))])).await;
    assert_eq!(r.status(), StatusCode::OK);
    assert_eq!(body.len(), len);
    let (r, body) = send(&s, get("/sample.tspack", &[("range", &format!("bytes={}", many[..200].join(",")))])).await;
    assert_eq!(r.status(), StatusCode::PARTIAL_CONTENT);
    assert_eq!(parts(&h(&r, "content-type"), &body).len(), 200);
    // Not a bytes range: ignored.
    let (r, _) = send(&s, get("/sample.tspack", &[("range", "pages=1-2")])).await;
    assert_eq!(r.status(), StatusCode::OK);
}

#[tokio::test]
async fn conditional_requests() {
    let (dir, _) = archives();
    let s = state(dir.path());
    let (r, _) = send(&s, get("/sample.tspack", &[])).await;
    let etag = h(&r, "etag");
    let modified = h(&r, "last-modified");
    let (r, body) = send(&s, get("/sample.tspack", &[("if-none-match", &etag)])).await;
    assert_eq!(r.status(), StatusCode::NOT_MODIFIED);
    assert!(body.is_empty());
    assert_eq!(h(&r, "etag"), etag);
    let (r, _) = send(&s, get("/sample.tspack", &[("if-match", "\"some-other-version\"")])).await;
    assert_eq!(r.status(), StatusCode::PRECONDITION_FAILED);
    let (r, _) = send(&s, get("/sample.tspack", &[("if-match", &etag), ("range", "bytes=0-3")])).await;
    assert_eq!(r.status(), StatusCode::PARTIAL_CONTENT);
    let (r, _) = send(&s, get("/sample.tspack", &[("if-range", &etag), ("range", "bytes=0-3")])).await;
    assert_eq!(r.status(), StatusCode::PARTIAL_CONTENT);
    let (r, _) = send(&s, get("/sample.tspack", &[("if-range", "\"stale\""), ("range", "bytes=0-3")])).await;
    assert_eq!(r.status(), StatusCode::OK, "a stale If-Range gets the whole new file");
    let (r, _) = send(&s, get("/sample.tspack", &[("if-range", &modified), ("range", "bytes=0-3")])).await;
    assert_eq!(r.status(), StatusCode::PARTIAL_CONTENT);
    let (r, _) = send(&s, get("/sample.tspack", &[("if-modified-since", &modified)])).await;
    assert_eq!(r.status(), StatusCode::NOT_MODIFIED);
}

#[tokio::test]
async fn nothing_outside_the_served_files() {
    let (dir, _) = archives();
    std::fs::write(dir.path().join("secret.txt"), "secret").unwrap();
    std::os::unix::fs::symlink("/etc/hostname", dir.path().join("escape.tspack")).unwrap();
    let s = state(dir.path());
    for uri in [
        "/secret.txt",
        "/..%2Fsecret.txt",
        "/..%2F..%2Fetc%2Fpasswd",
        "/%2e%2e/secret.txt",
        "/escape.tspack",
        "/sample.tspack%00",
        "/nope.tspack",
        "/sample",
    ] {
        let (r, body) = send(&s, get(uri, &[])).await;
        assert!(r.status() == StatusCode::NOT_FOUND || r.status() == StatusCode::BAD_REQUEST, "{uri}: {}", r.status());
        assert!(!String::from_utf8_lossy(&body).contains("secret"), "{uri}");
    }
    assert!(s.catalog.get("escape").is_none(), "symlinks are not served");
}

#[tokio::test]
async fn metadata_and_tiles() {
    let (dir, path) = archives();
    let s = state(dir.path());
    let reader = Reader::new(MmapSource::open(&path).unwrap()).unwrap();
    let (r, body) = send(&s, get("/sample/metadata", &[])).await;
    assert_eq!(r.status(), StatusCode::OK);
    assert_eq!(h(&r, "content-type"), "application/json");
    let meta: terrastream_format::Metadata = serde_json::from_slice(&body).unwrap();
    assert_eq!(&meta, reader.metadata());

    let want = reader.tile(TileKey::new(0, 1, 2, 1).unwrap()).unwrap().unwrap();
    for uri in ["/sample/texture/1/2/1", "/sample/0/1/2/1"] {
        let (r, body) = send(&s, get(uri, &[])).await;
        assert_eq!(r.status(), StatusCode::OK, "{uri}");
        assert_eq!(h(&r, "content-type"), "image/png");
        assert_eq!(body, want.to_vec());
        let etag = h(&r, "etag");
        let (r, _) = send(&s, get(uri, &[("if-none-match", &etag)])).await;
        assert_eq!(r.status(), StatusCode::NOT_MODIFIED);
    }
    // The sample's lake tile is missing at LOD 0: 404 naming the LOD to use instead.
    let (r, _) = send(&s, get("/sample/texture/0/1/4", &[])).await;
    assert_eq!(r.status(), StatusCode::NOT_FOUND);
    assert_eq!(h(&r, FALLBACK_LOD.as_str()), "1");
    // Outside the grid, malformed numbers: 400. Unknown layer or archive: 404.
    for (uri, status) in [
        ("/sample/texture/0/8/0", StatusCode::BAD_REQUEST),
        ("/sample/texture/9/0/0", StatusCode::BAD_REQUEST),
        ("/sample/texture/0/-1/0", StatusCode::BAD_REQUEST),
        ("/sample/texture/zero/0/0", StatusCode::BAD_REQUEST),
        ("/sample/texture/0/99999999999/0", StatusCode::BAD_REQUEST),
        ("/sample/normals/0/0/0", StatusCode::NOT_FOUND),
        ("/sample/7/0/0/0", StatusCode::NOT_FOUND),
        ("/other/texture/0/0/0", StatusCode::NOT_FOUND),
    ] {
        let (r, _) = send(&s, get(uri, &[])).await;
        assert_eq!(r.status(), status, "{uri}");
    }
}

#[tokio::test]
async fn zstd_tiles_pass_through_only_when_accepted() {
    let (dir, _) = archives();
    let s = state(dir.path());
    let key = TileKey::new(0, 0, 1, 1).unwrap();
    let (r, body) = send(&s, get("/elev/elevation/0/1/1", &[("accept-encoding", "gzip, zstd")])).await;
    assert_eq!(r.status(), StatusCode::OK);
    assert_eq!(h(&r, "content-encoding"), "zstd");
    assert_eq!(h(&r, "vary"), "Accept-Encoding");
    assert_eq!(terrastream_format::zstd_decompress(&body, 1 << 20, "t").unwrap(), raw_tile(key, 1));
    let zstd_etag = h(&r, "etag");
    for accept in [None, Some("gzip"), Some("zstd;q=0")] {
        let headers: Vec<(&str, &str)> = accept.map(|a| vec![("accept-encoding", a)]).unwrap_or_default();
        let (r, body) = send(&s, get("/elev/elevation/0/1/1", &headers)).await;
        assert_eq!(r.status(), StatusCode::OK);
        assert_eq!(h(&r, "content-encoding"), "", "{accept:?}");
        assert_eq!(body, raw_tile(key, 1));
        assert_ne!(h(&r, "etag"), zstd_etag, "each representation has its own tag");
    }
}

/// Gradient-coded tiles are sent decoded, whatever the client accepts: the media type
/// (raw u16) is what the body is, for any HTTP client.
#[tokio::test]
async fn gradient_coded_tiles_are_sent_as_their_samples() {
    let dir = tempfile::tempdir().unwrap();
    terrastream_testkit::archives::write_u16_archive(
        &dir.path().join("g.tspack"),
        2,
        terrastream_format::PayloadCompression::ZstdGradient,
    );
    let s = state(dir.path());
    let key = TileKey::new(0, 0, 1, 1).unwrap();
    for accept in [None, Some("gzip, zstd")] {
        let headers: Vec<(&str, &str)> = accept.map(|a| vec![("accept-encoding", a)]).unwrap_or_default();
        let (r, body) = send(&s, get("/g/elevation/0/1/1", &headers)).await;
        assert_eq!(r.status(), StatusCode::OK);
        assert_eq!(h(&r, "content-encoding"), "", "{accept:?}");
        assert_eq!(h(&r, "content-type"), "application/octet-stream");
        assert_eq!(body, raw_tile(key, 2));
    }
}

#[tokio::test]
async fn listing_health_metrics_and_cors() {
    let (dir, _) = archives();
    let s = state(dir.path());
    let (r, body) = send(&s, get("/", &[("accept", "application/json")])).await;
    assert_eq!(r.status(), StatusCode::OK);
    let doc: serde_json::Value = serde_json::from_slice(&body).unwrap();
    let names: Vec<&str> = doc["archives"].as_array().unwrap().iter().map(|a| a["name"].as_str().unwrap()).collect();
    assert_eq!(names, ["elev", "sample"]);
    let (r, body) = send(&s, get("/", &[])).await;
    assert!(h(&r, "content-type").starts_with("text/html"));
    assert!(String::from_utf8_lossy(&body).contains("href=\"/sample.tspack\""));
    let (r, body) = send(&s, get("/healthz", &[])).await;
    assert_eq!((r.status(), body), (StatusCode::OK, b"ok\n".to_vec()));

    send(&s, get("/sample.tspack", &[("range", "bytes=0-9")])).await;
    send(&s, get("/sample/texture/0/8/0", &[])).await;
    let (_, body) = send(&s, get("/metrics", &[])).await;
    let text = String::from_utf8(body).unwrap();
    assert!(text.contains("terrastream_requests_total{route=\"/{file}\",status=\"206\"} 1"), "{text}");
    assert!(
        text.contains("terrastream_requests_total{route=\"/{name}/{layer}/{lod}/{x}/{y}\",status=\"400\"} 1"),
        "{text}"
    );
    assert!(text.contains("terrastream_response_bytes_total{route=\"/{file}\"} 10"), "{text}");
    assert!(text.contains("terrastream_request_duration_seconds_count{route=\"/{file}\"} 1"), "{text}");
    assert!(text.contains("terrastream_archives 2"));

    let preflight = Request::options("/sample.tspack")
        .header("origin", "https://viewer.example")
        .header("access-control-request-method", "GET")
        .header("access-control-request-headers", "range, if-none-match")
        .body(Body::empty())
        .unwrap();
    let (r, _) = send(&s, preflight).await;
    assert!(r.status().is_success());
    assert_eq!(h(&r, "access-control-allow-origin"), "*");
    let allowed = h(&r, "access-control-allow-headers").to_lowercase();
    assert!(
        allowed.contains("range") && allowed.contains("if-none-match") && allowed.contains("if-match"),
        "{allowed}"
    );
    let (r, _) = send(&s, get("/sample.tspack", &[("origin", "https://viewer.example"), ("range", "bytes=0-1")])).await;
    let exposed = h(&r, "access-control-expose-headers").to_lowercase();
    for name in ["etag", "content-range", "content-length", "content-encoding"] {
        assert!(exposed.contains(name), "{exposed}");
    }
}

/// A tile's checksum is verified the first time it is served (then remembered: the
/// mapping is immutable); a damaged tile is refused with a 500 every time, never
/// remembered as good, and the archive's other tiles are still served.
#[tokio::test]
async fn damaged_tiles_are_refused_every_time_and_good_ones_checked_once() {
    let (dir, path) = archives();
    let reader = Reader::new(MmapSource::open(&path).unwrap()).unwrap();
    let good = reader.locate(TileKey::new(0, 1, 2, 1).unwrap()).unwrap().unwrap();
    let bad = reader.locate(TileKey::new(0, 1, 0, 0).unwrap()).unwrap().unwrap();
    assert_ne!(good.offset, bad.offset);
    let want = reader.read(&good).unwrap().to_vec();
    drop(reader);
    let mut bytes = std::fs::read(&path).unwrap();
    bytes[bad.offset as usize + 20] ^= 0x55;
    std::fs::write(&path, &bytes).unwrap();
    let s = state(dir.path());
    let served = s.catalog.get("sample").unwrap();
    assert!(!served.is_verified(good.offset));
    for _ in 0..2 {
        let (r, body) = send(&s, get("/sample/texture/1/2/1", &[])).await;
        assert_eq!(r.status(), StatusCode::OK);
        assert_eq!(body, want);
        assert!(served.is_verified(good.offset));
        let (r, body) = send(&s, get("/sample/texture/1/0/0", &[])).await;
        assert_eq!(r.status(), StatusCode::INTERNAL_SERVER_ERROR);
        assert_eq!(body, b"internal server error");
        assert!(!served.is_verified(bad.offset));
    }
}

/// A manifest in a served folder is served at `/{name}.json` as found (validated first),
/// revalidated by its ETag, replaced when the file is (hot reload), and kept when the
/// new file does not validate; `/view/{name}` points the player at it.
#[tokio::test]
async fn manifests_are_served_beside_the_archives_and_hot_reloaded() {
    let (dir, path) = archives();
    let reader = Reader::new(MmapSource::open(&path).unwrap()).unwrap();
    let tag = terrastream_format::content_tag(&reader.header().encode());
    let manifest = terrastream_format::Manifest::single(reader.metadata().clone(), "sample.tspack", tag);
    let file = dir.path().join("planet.json");
    std::fs::write(&file, manifest.to_json()).unwrap();
    let s = state(dir.path());
    let (r, body) = send(&s, get("/planet.json", &[])).await;
    assert_eq!(r.status(), StatusCode::OK);
    assert_eq!(body, manifest.to_json());
    assert_eq!(h(&r, "content-type"), "application/json");
    assert_eq!(h(&r, "cache-control"), "no-cache");
    let etag = h(&r, "etag");
    let (r, _) = send(&s, get("/planet.json", &[("if-none-match", &etag)])).await;
    assert_eq!(r.status(), StatusCode::NOT_MODIFIED);
    let (r, _) = send(&s, get("/other.json", &[])).await;
    assert_eq!(r.status(), StatusCode::NOT_FOUND);
    // Listed in the index.
    let (_, body) = send(&s, get("/", &[("accept", "application/json")])).await;
    let index: serde_json::Value = serde_json::from_slice(&body).unwrap();
    assert_eq!(index["manifests"][0]["url"], "/planet.json", "{index}");

    // Replaced (written beside, renamed): the new one after a reload.
    let mut second = manifest.clone();
    second.metadata.name = "second".into();
    let partial = dir.path().join(".planet.json.partial");
    std::fs::write(&partial, second.to_json()).unwrap();
    std::fs::rename(&partial, &file).unwrap();
    assert!(s.catalog.reload() >= 1);
    let (r, body) = send(&s, get("/planet.json", &[])).await;
    assert_eq!(body, second.to_json());
    assert_ne!(h(&r, "etag"), etag);
    // A broken one is refused; the last good one stays served.
    std::fs::write(dir.path().join(".broken"), b"{\"format\": \"terrastream-manifest\"").unwrap();
    std::fs::rename(dir.path().join(".broken"), &file).unwrap();
    s.catalog.reload();
    let (r, body) = send(&s, get("/planet.json", &[])).await;
    assert_eq!(r.status(), StatusCode::OK);
    assert_eq!(body, second.to_json());
    // Removed: gone.
    std::fs::remove_file(&file).unwrap();
    s.catalog.reload();
    let (r, _) = send(&s, get("/planet.json", &[])).await;
    assert_eq!(r.status(), StatusCode::NOT_FOUND);
}

/// Labels' glyphs: a range of the fonts folder's font (a stack it does not hold answered
/// with the fallback, named in a header), the range checked, no folder a 404; and a
/// folder that holds no font refuses to start naming it.
#[tokio::test]
async fn glyph_ranges_for_map_labels() {
    let (dir, _) = archives();
    let fonts = std::path::Path::new("/usr/share/fonts/truetype/dejavu");
    assert!(fonts.join("DejaVuSans.ttf").exists(), "DejaVu's fonts (apt-get install fonts-dejavu-core)");
    let config = |fonts: Option<&std::path::Path>| terrastream_server::ServerConfig {
        paths: vec![dir.path().to_path_buf()],
        fonts: fonts.map(std::path::Path::to_path_buf),
        ..terrastream_server::ServerConfig::default()
    };
    let served = terrastream_server::AppState::try_new(config(Some(fonts))).unwrap();
    let (r, body) = send(&served, get("/fonts/DejaVu%20Sans%20Bold/0-255.pbf", &[])).await;
    assert_eq!(r.status(), StatusCode::OK);
    assert_eq!(h(&r, "content-type"), "application/x-protobuf");
    assert_eq!(h(&r, "x-terrastream-font"), "DejaVu Sans Bold");
    assert!(body.len() > 20_000, "{} bytes for the Latin range", body.len());
    // Gzipped when accepted: the same message.
    let (r, gz) = send(&served, get("/fonts/DejaVu%20Sans%20Bold/0-255.pbf", &[("accept-encoding", "gzip, br")])).await;
    assert_eq!(h(&r, "content-encoding"), "gzip");
    let mut plain = Vec::new();
    std::io::Read::read_to_end(&mut flate2::read::GzDecoder::new(&gz[..]), &mut plain).unwrap();
    assert!(plain == body && gz.len() * 2 < body.len(), "{} gzipped bytes of {}", gz.len(), body.len());
    let (r, body) =
        send(&served, get("/fonts/Open%20Sans%20Regular,Arial%20Unicode%20MS%20Regular/256-511.pbf", &[])).await;
    assert_eq!((r.status(), h(&r, "x-terrastream-font").as_str()), (StatusCode::OK, "DejaVu Sans"));
    // The answer names the stack asked for and its range (the glyphs are the fallback's).
    for label in ["Open Sans Regular,Arial Unicode MS Regular", "256-511"] {
        assert!(body.windows(label.len()).any(|w| w == label.as_bytes()), "{label} not in the answer");
    }
    for bad in
        ["/fonts/DejaVu%20Sans/1-256.pbf", "/fonts/DejaVu%20Sans/0-100.pbf", "/fonts/DejaVu%20Sans/65536-65791.pbf"]
    {
        let (r, body) = send(&served, get(bad, &[])).await;
        assert_eq!(r.status(), StatusCode::BAD_REQUEST, "{bad}");
        assert!(String::from_utf8_lossy(&body).contains("range"), "{bad}");
    }
    let without = terrastream_server::AppState::try_new(config(None)).unwrap();
    let (r, body) = send(&without, get("/fonts/DejaVu%20Sans/0-255.pbf", &[])).await;
    assert_eq!(r.status(), StatusCode::NOT_FOUND);
    assert!(String::from_utf8_lossy(&body).contains("--fonts"));
    let empty = tempfile::tempdir().unwrap();
    let refused = terrastream_server::AppState::try_new(config(Some(empty.path()))).unwrap_err().to_string();
    assert!(refused.contains(&empty.path().display().to_string()) && refused.contains("no TrueType"), "{refused}");
}
