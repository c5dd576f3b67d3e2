//! The same Range requests to this server and to nginx serving the same file give the same
//! status codes, `Content-Range` and bodies: nginx is the reference behaviour.
#![allow(clippy::unwrap_used, clippy::expect_used, clippy::cast_possible_truncation, missing_docs)]

use terrastream_server::{AppState, ServerConfig, serve};
use terrastream_testkit::archives::archives;
use terrastream_testkit::http::split_multipart;
use terrastream_testkit::nginx::start_nginx;

/// (status, Content-Range, body parts as (Content-Range, bytes)).
type Answer = (u16, String, Vec<(String, Vec<u8>)>);

async fn ask(client: &reqwest::Client, url: &str, range: &str) -> Answer {
    let r = client.get(url).header("range", range).send().await.unwrap();
    let status = r.status().as_u16();
    let content_range = r.headers().get("content-range").map(|v| v.to_str().unwrap().to_owned()).unwrap_or_default();
    let content_type = r.headers().get("content-type").map(|v| v.to_str().unwrap().to_owned()).unwrap_or_default();
    let body = r.bytes().await.unwrap().to_vec();
    let parts = if let Some(boundary) = content_type.split("boundary=").nth(1) {
        split_multipart(&body, boundary)
    } else if status == 416 {
        Vec::new() // nginx sends an HTML page, we send nothing: bodies of errors are not compared
    } else {
        vec![(String::new(), body)]
    };
    (status, content_range, parts)
}

#[tokio::test]
async fn range_answers_match_nginx() {
    let (dir, path) = archives();
    let len = std::fs::metadata(&path).unwrap().len();
    let Some(nginx) = start_nginx(dir.path(), "server { listen 127.0.0.1:{port}; root {root}; max_ranges 256; }")
    else {
        return;
    };
    let config = ServerConfig { paths: vec![dir.path().to_path_buf()], max_ranges: 256, ..ServerConfig::default() };
    let state = AppState::new(config);
    state.catalog.reload();
    let listener = tokio::net::TcpListener::bind("127.0.0.1:0").await.unwrap();
    let addr = listener.local_addr().unwrap();
    let (stop, stopped) = tokio::sync::oneshot::channel::<()>();
    let server = tokio::spawn(serve(listener, state, async {
        let _ = stopped.await;
    }));

    let hundreds: Vec<String> = (0..256).map(|i| format!("{}-{}", i * 100, i * 100 + 9)).collect();
    let too_many: Vec<String> = (0..257).map(|i| format!("{}-{}", i * 100, i * 100 + 9)).collect();
    let mut cases: Vec<String> = [
        "bytes=0-0",
        "bytes=0-127",
        "bytes=128-",
        "bytes=-1",
        "bytes=-128",
        "bytes=-99999999",
        "bytes=100-99999999",
        "bytes=0-9,20-29",
        "bytes=0-9,5-14",
        "bytes=0-9,0-9",
        "bytes=50-59,0-9",
        "bytes= 1 - 2 , 4 - 5",
        "bytes=5-1",
        "bytes=5-1,0-1",
        "bytes=-0",
        "bytes=0-",
        "bytes=abc",
        "bytes=1-2;",
        "bytes=--1",
        "bytes=1--2",
        "bytes=,0-1",
        "bytes=0-1,",
        "bytes=",
        "bytes=18446744073709551615-",
        "bytes=99999999999999999999-",
        "pages=0-1",
        "BYTES=0-3",
    ]
    .iter()
    .map(|s| s.to_string())
    .collect();
    cases.extend([
        format!("bytes={len}-"),
        format!("bytes={}-", len - 1),
        format!("bytes={}-{}", len - 10, len + 10),
        format!("bytes={}-{},{}-{}", len + 1, len + 2, len + 3, len + 4),
        format!("bytes=0-{}", len - 1),
        format!("bytes=0-{},0-1", len - 1),
        format!("bytes={}", hundreds.join(",")),
        format!("bytes={}", too_many.join(",")),
    ]);
    let client = reqwest::Client::new();
    let ours_url = format!("http://{addr}/sample.tspack");
    let nginx_url = format!("http://127.0.0.1:{}/sample.tspack", nginx.port);
    let mut mismatches = Vec::new();
    for range in &cases {
        let ours = ask(&client, &ours_url, range).await;
        let theirs = ask(&client, &nginx_url, range).await;
        if ours != theirs {
            let show = |a: &Answer| format!("{} {:?} {} part(s)", a.0, a.1, a.2.len());
            mismatches.push(format!("{range:.60}: ours {} / nginx {}", show(&ours), show(&theirs)));
        }
    }
    // The whole-file and open ranges above went out through sendfile (on Linux), and their
    // bytes matched nginx's.
    let metrics = client.get(format!("http://{addr}/metrics")).send().await.unwrap().text().await.unwrap();
    let sent: u64 = metrics
        .lines()
        .find_map(|l| l.strip_prefix("terrastream_sendfile_bytes_total "))
        .expect("the sendfile counter in /metrics")
        .parse()
        .unwrap();
    let _ = stop.send(());
    server.await.unwrap().unwrap();
    assert!(mismatches.is_empty(), "differences from nginx:\n{}", mismatches.join("\n"));
    assert!(len > 8192, "the sample archive is large enough for sendfile ({len} bytes)");
    if cfg!(target_os = "linux") {
        assert!(sent >= 2 * len, "{sent} bytes through sendfile, {len} in the file");
    }
}
