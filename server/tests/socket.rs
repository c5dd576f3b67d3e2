//! The server on a real loopback socket: HTTP/1.1 and h2c, hot reload under load,
//! graceful shutdown, header limits.
#![allow(clippy::unwrap_used, clippy::expect_used, clippy::cast_possible_truncation, missing_docs)]

use std::net::SocketAddr;
use std::sync::Arc;
use std::sync::atomic::{AtomicBool, AtomicU64, Ordering};
use std::time::Duration;

use terrastream_format::TileKey;
use terrastream_server::{AppState, ServerConfig};
use terrastream_testkit::archives::{archives, raw_tile, write_zstd_archive};
use terrastream_testkit::server::start;
use tokio::io::{AsyncReadExt, AsyncWriteExt};
use tokio::sync::oneshot;

#[tokio::test]
async fn ranges_over_http1_and_h2c() {
    let (dir, path) = archives();
    let file = std::fs::read(&path).unwrap();
    let server = start(dir.path(), |_| {}).await;
    let url = format!("http://{}/sample.tspack", server.addr);
    let h1 = reqwest::Client::new();
    let h2 = reqwest::Client::builder().http2_prior_knowledge().build().unwrap();
    for (client, version) in [(&h1, reqwest::Version::HTTP_11), (&h2, reqwest::Version::HTTP_2)] {
        let r = client.get(&url).header("range", "bytes=128-1151").send().await.unwrap();
        assert_eq!(r.status(), 206);
        assert_eq!(r.version(), version);
        assert_eq!(r.headers()["content-range"], format!("bytes 128-1151/{}", file.len()).as_str());
        assert_eq!(r.bytes().await.unwrap(), &file[128..1152]);
        // Bodies of 4 KiB and more leave through sendfile (Linux), in h2 DATA frames too:
        // the whole file, and from an odd offset.
        assert!(file.len() > 8192);
        let r = client.get(&url).send().await.unwrap();
        assert_eq!(r.status(), 200);
        assert_eq!(r.bytes().await.unwrap(), &file[..], "{version:?}");
        let r = client.get(&url).header("range", "bytes=3-").send().await.unwrap();
        assert_eq!(r.status(), 206);
        assert_eq!(r.bytes().await.unwrap(), &file[3..], "{version:?}");
        let r = client.get(format!("http://{}/sample/texture/3/0/0", server.addr)).send().await.unwrap();
        assert_eq!(r.status(), 200);
        assert_eq!(r.headers()["content-type"], "image/png");
    }
    server.stop().await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn hot_reload_under_load_fails_no_request() {
    let (dir, _) = archives();
    let server = start(dir.path(), |_| {}).await;
    let base = format!("http://{}", server.addr);
    let client = reqwest::Client::new();
    let key = TileKey::new(0, 0, 1, 1).unwrap();
    let (v1, v2) = (raw_tile(key, 1), raw_tile(key, 2));
    let failures = Arc::new(AtomicU64::new(0));
    let (seen_v1, seen_v2) = (Arc::new(AtomicU64::new(0)), Arc::new(AtomicU64::new(0)));
    let done = Arc::new(AtomicBool::new(false));
    let mut workers = Vec::new();
    for _ in 0..8 {
        let (client, base) = (client.clone(), base.clone());
        let (failures, seen_v1, seen_v2, done) = (failures.clone(), seen_v1.clone(), seen_v2.clone(), done.clone());
        let (v1, v2) = (v1.clone(), v2.clone());
        workers.push(tokio::spawn(async move {
            let mut n = 0u32;
            // Bounded: stops when told, or after 20 000 requests.
            while !done.load(Ordering::SeqCst) && n < 20_000 {
                n += 1;
                let ok = match client.get(format!("{base}/elev/elevation/0/1/1")).send().await {
                    Ok(r) if r.status() == 200 => match r.bytes().await {
                        Ok(b) if b == v1 => {
                            seen_v1.fetch_add(1, Ordering::SeqCst);
                            true
                        }
                        Ok(b) if b == v2 => {
                            seen_v2.fetch_add(1, Ordering::SeqCst);
                            true
                        }
                        _ => false,
                    },
                    _ => false,
                };
                let range = client.get(format!("{base}/elev.tspack")).header("range", "bytes=0-127").send().await;
                let range_ok = match range {
                    Ok(r) if r.status() == 206 => r.bytes().await.is_ok_and(|b| b.len() == 128),
                    _ => false,
                };
                if !ok || !range_ok {
                    failures.fetch_add(1, Ordering::SeqCst);
                }
            }
        }));
    }
    let etag_before = server.state.catalog.get("elev").unwrap().etag.clone();
    tokio::time::sleep(Duration::from_millis(300)).await;
    // Replace the archive the way the writer always does: temporary file + rename.
    let path = dir.path().join("elev.tspack");
    tokio::task::spawn_blocking(move || write_zstd_archive(&path, 2)).await.unwrap();
    for _ in 0..100 {
        if seen_v2.load(Ordering::SeqCst) > 100 {
            break;
        }
        tokio::time::sleep(Duration::from_millis(50)).await;
    }
    done.store(true, Ordering::SeqCst);
    for w in workers {
        w.await.unwrap();
    }
    assert_eq!(failures.load(Ordering::SeqCst), 0, "requests failed during the replacement");
    assert!(seen_v1.load(Ordering::SeqCst) > 0 && seen_v2.load(Ordering::SeqCst) > 0, "both versions were served");
    assert_ne!(server.state.catalog.get("elev").unwrap().etag, etag_before, "the ETag changed");
    server.stop().await;
}

#[tokio::test]
async fn shutdown_lets_requests_in_flight_finish() {
    let (dir, path) = archives();
    let len = std::fs::metadata(&path).unwrap().len() as usize;
    let server = start(dir.path(), |_| {}).await;
    let addr = server.addr;
    let mut stream = tokio::net::TcpStream::connect(addr).await.unwrap();
    stream.write_all(b"GET /sample.tspack HTTP/1.1\r\nHost: x\r\n\r\n").await.unwrap();
    let mut first = vec![0u8; 1024];
    let n = stream.read(&mut first).await.unwrap();
    assert!(n > 0);
    // Shut down while most of the body is still to be read.
    let stopping = tokio::spawn(server.stop());
    let mut rest = Vec::new();
    stream.read_to_end(&mut rest).await.unwrap();
    let mut all = first[..n].to_vec();
    all.extend(rest);
    let head_end = all.windows(4).position(|w| w == b"\r\n\r\n").unwrap() + 4;
    assert_eq!(all.len() - head_end, len, "the whole body arrived");
    stopping.await.unwrap();
    assert!(tokio::net::TcpStream::connect(addr).await.is_err(), "no longer accepting");
}

#[tokio::test]
async fn oversized_headers_are_refused() {
    let (dir, _) = archives();
    let server = start(dir.path(), |c| c.max_header_bytes = 8192).await;
    let mut stream = tokio::net::TcpStream::connect(server.addr).await.unwrap();
    let big = "a".repeat(64 * 1024);
    let request = format!("GET /healthz HTTP/1.1\r\nHost: x\r\nX-Big: {big}\r\n\r\n");
    let _ = stream.write_all(request.as_bytes()).await;
    let mut answer = Vec::new();
    let _ = tokio::time::timeout(Duration::from_secs(5), stream.read_to_end(&mut answer)).await;
    let text = String::from_utf8_lossy(&answer);
    assert!(text.is_empty() || text.starts_with("HTTP/1.1 431"), "{text}");
    // The server is still fine.
    let r = reqwest::get(format!("http://{}/healthz", server.addr)).await.unwrap();
    assert_eq!(r.status(), 200);
    server.stop().await;
}

/// A system tool, or `None` with a loud message outside CI (the test command installs it).
fn tool(name: &str) -> Option<()> {
    let found = std::process::Command::new("sh").arg("-c").arg(format!("command -v {name}")).output().unwrap();
    if found.status.success() {
        return Some(());
    }
    assert!(std::env::var_os("CI").is_none(), "{name} is not installed; required on CI");
    eprintln!("\n*** SKIPPING: {name} is not installed ***\n");
    None
}

#[tokio::test]
async fn https_offers_h2_and_http1_by_alpn() {
    if tool("openssl").is_none() || tool("curl").is_none() {
        return;
    }
    let (dir, _) = archives();
    let certs = tempfile::tempdir().unwrap();
    let (cert, key) = (certs.path().join("cert.pem"), certs.path().join("key.pem"));
    let made = std::process::Command::new("openssl")
        .args(["req", "-x509", "-newkey", "ec", "-pkeyopt", "ec_paramgen_curve:prime256v1", "-nodes", "-days", "1"])
        .args(["-subj", "/CN=localhost", "-addext", "subjectAltName=DNS:localhost", "-keyout"])
        .arg(&key)
        .arg("-out")
        .arg(&cert)
        .output()
        .unwrap();
    assert!(made.status.success(), "{}", String::from_utf8_lossy(&made.stderr));
    let (c, k) = (cert.clone(), key.clone());
    let server = start(dir.path(), move |config| {
        config.tls_cert = Some(c);
        config.tls_key = Some(k);
    })
    .await;
    let port = server.addr.port();
    for (flag, want) in [("--http2", "206 2"), ("--http1.1", "206 1.1")] {
        let out = tokio::process::Command::new("curl")
            .args(["-sS", "-o", "/dev/null", "-w", "%{http_code} %{http_version}", flag, "-r", "0-127", "--cacert"])
            .arg(&cert)
            .args([
                "--resolve",
                &format!("localhost:{port}:127.0.0.1"),
                &format!("https://localhost:{port}/sample.tspack"),
            ])
            .output()
            .await
            .unwrap();
        assert_eq!(String::from_utf8_lossy(&out.stdout), want, "{}", String::from_utf8_lossy(&out.stderr));
    }
    // Plain HTTP on the TLS port is refused without harming the server.
    let plain = reqwest::get(format!("http://127.0.0.1:{port}/healthz")).await;
    assert!(plain.is_err() || !plain.unwrap().status().is_success());
    server.stop().await;
}

#[tokio::test]
async fn connections_beyond_the_cap_wait_for_a_free_slot() {
    let (dir, _) = archives();
    let server = start(dir.path(), |c| c.max_connections = 1).await;
    // A holds the only slot (connected, idle).
    let mut a = tokio::net::TcpStream::connect(server.addr).await.unwrap();
    a.write_all(b"GET /healthz HTTP/1.1\r\nHost: x\r\n\r\n").await.unwrap();
    let mut buf = [0u8; 256];
    let n = a.read(&mut buf).await.unwrap();
    assert!(String::from_utf8_lossy(&buf[..n]).starts_with("HTTP/1.1 200"));
    // B is accepted by the kernel but not served while A is open.
    let mut b = tokio::net::TcpStream::connect(server.addr).await.unwrap();
    b.write_all(b"GET /healthz HTTP/1.1\r\nHost: x\r\nConnection: close\r\n\r\n").await.unwrap();
    let early = tokio::time::timeout(Duration::from_millis(300), b.read(&mut buf)).await;
    assert!(early.is_err(), "served beyond max_connections");
    drop(a);
    let mut answer = Vec::new();
    tokio::time::timeout(Duration::from_secs(5), b.read_to_end(&mut answer)).await.unwrap().unwrap();
    assert!(String::from_utf8_lossy(&answer).starts_with("HTTP/1.1 200"), "served once a slot is free");
    server.stop().await;
}

#[tokio::test]
async fn a_client_that_never_finishes_its_headers_is_cut_off() {
    let (dir, _) = archives();
    let server = start(dir.path(), |c| c.request_timeout_secs = 1).await;
    let mut slow = tokio::net::TcpStream::connect(server.addr).await.unwrap();
    slow.write_all(b"GET /healthz HTTP/1.1\r\nHost: x\r\n").await.unwrap(); // no blank line, ever
    let mut rest = Vec::new();
    let closed = tokio::time::timeout(Duration::from_secs(10), slow.read_to_end(&mut rest)).await;
    assert!(closed.is_ok(), "the connection was not closed");
    let text = String::from_utf8_lossy(&rest);
    assert!(text.is_empty() || text.starts_with("HTTP/1.1 408"), "{text}");
    server.stop().await;
}

#[tokio::test]
async fn archives_added_and_removed_are_picked_up() {
    let (dir, _) = archives();
    let server = start(dir.path(), |_| {}).await;
    let client = reqwest::Client::new();
    let url = |name: &str| format!("http://{}/{name}.tspack", server.addr);
    assert_eq!(client.get(url("late")).send().await.unwrap().status(), 404);
    write_zstd_archive(&dir.path().join("late.tspack"), 3);
    std::fs::remove_file(dir.path().join("elev.tspack")).unwrap();
    let mut status = (0, 0);
    for _ in 0..100 {
        tokio::time::sleep(Duration::from_millis(50)).await;
        status = (
            client.get(url("late")).send().await.unwrap().status().as_u16(),
            client.get(url("elev")).send().await.unwrap().status().as_u16(),
        );
        if status == (200, 404) {
            break;
        }
    }
    assert_eq!(status, (200, 404), "new archive served, removed one gone");
    server.stop().await;
}

/// `serve_workers`, as `terrastream serve` runs it: several threads, each with its own
/// socket on one port. Every connection is served whichever thread the kernel gives it to;
/// hot reload (run on the calling thread) reaches all of them; shutdown stops them all and
/// closes the port.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn worker_threads_share_one_port_reload_and_stop_together() {
    let (dir, path) = archives();
    let file = std::fs::read(&path).unwrap();
    let config =
        ServerConfig { paths: vec![dir.path().to_path_buf()], reload_interval_ms: 50, ..ServerConfig::default() };
    let state = AppState::new(config);
    state.catalog.reload();
    let (stop, stopped) = oneshot::channel::<()>();
    let (bound_tx, bound_rx) = std::sync::mpsc::channel();
    let thread = std::thread::spawn(move || {
        let addr = SocketAddr::from(([127, 0, 0, 1], 0));
        terrastream_server::serve_workers(
            addr,
            3,
            state,
            async {
                let _ = stopped.await;
            },
            move |a| bound_tx.send(a).unwrap(),
        )
    });
    let addr = tokio::task::spawn_blocking(move || bound_rx.recv().unwrap()).await.unwrap();
    // A second server on the same port is refused, not handed half of the connections.
    let again = terrastream_server::serve_workers(addr, 2, AppState::new(ServerConfig::default()), async {}, |_| {
        panic!("bound a port in use")
    });
    assert_eq!(again.unwrap_err().kind(), std::io::ErrorKind::AddrInUse);
    // 48 separate connections (a client each: no pooling), 4 requests on each.
    let mut tasks = Vec::new();
    for i in 0..48u64 {
        let want = file.clone();
        tasks.push(tokio::spawn(async move {
            let client = reqwest::Client::new();
            for j in 0..4u64 {
                let start = (i * 97 + j * 13) % (want.len() as u64 - 64);
                let r = client
                    .get(format!("http://{addr}/sample.tspack"))
                    .header("range", format!("bytes={start}-{}", start + 63))
                    .send()
                    .await
                    .unwrap();
                assert_eq!(r.status(), 206);
                assert_eq!(r.bytes().await.unwrap(), &want[start as usize..start as usize + 64]);
            }
        }));
    }
    for t in tasks {
        t.await.unwrap();
    }
    // Every thread's connections are counted, and the 48 closed ones no longer.
    let client = reqwest::Client::new();
    let (mut metrics, mut open) = (String::new(), 0);
    // Up to 5 s for the clients' pools to close their sockets.
    for _ in 0..250 {
        metrics = client.get(format!("http://{addr}/metrics")).send().await.unwrap().text().await.unwrap();
        open = metrics
            .lines()
            .filter(|l| l.starts_with("terrastream_connections{"))
            .map(|l| l.rsplit(' ').next().unwrap().parse::<usize>().unwrap())
            .sum::<usize>();
        if open == 1 {
            break;
        }
        tokio::time::sleep(Duration::from_millis(20)).await;
    }
    assert_eq!(open, 1, "only the connection asking is open: {metrics}");
    for thread in 0..3 {
        assert!(metrics.contains(&format!("terrastream_connections{{thread=\"{thread}\"}} ")), "{metrics}");
    }
    assert!(metrics.contains("terrastream_connections_handed_total "), "{metrics}");
    drop(client);
    // A removed archive disappears for every worker.
    std::fs::remove_file(&path).unwrap();
    let mut statuses = Vec::new();
    for _ in 0..100 {
        tokio::time::sleep(Duration::from_millis(50)).await;
        statuses.clear();
        for _ in 0..6 {
            // A fresh connection each time: the kernel spreads them over the workers.
            let r = reqwest::Client::new().get(format!("http://{addr}/sample.tspack")).send().await.unwrap();
            statuses.push(r.status().as_u16());
        }
        if statuses.iter().all(|&s| s == 404) {
            break;
        }
    }
    assert!(statuses.iter().all(|&s| s == 404), "removed archive still served: {statuses:?}");
    stop.send(()).unwrap();
    let result = tokio::task::spawn_blocking(move || thread.join().unwrap()).await.unwrap();
    result.unwrap();
    assert!(tokio::net::TcpStream::connect(addr).await.is_err(), "port still open after shutdown");
}
