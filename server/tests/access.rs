//! Private terrain on a real socket, on both HTTP paths (the lean HTTP/1.1 path and
//! hyper's): keys and signed tokens open what they name and nothing else, refusals carry
//! no byte of a private archive, credentials are carried into handed-out URLs, and a
//! flood of bad keys serves nothing private.
#![allow(clippy::unwrap_used, clippy::expect_used, clippy::cast_possible_truncation, missing_docs)]

use std::net::SocketAddr;
use std::path::Path;

use proptest::prelude::*;
use terrastream_server::access::keys::{KeyFile, KeyRecord};
use terrastream_server::access::token::{self, Scope};
use terrastream_testkit::archives::archives;
use terrastream_testkit::server::{Running, start};
use tokio::io::{AsyncReadExt, AsyncWriteExt};

const SECRET: &str = "a signing secret of the operator, long enough";

fn rule(archives: &[&str]) -> KeyRecord {
    KeyRecord::opening(archives.iter().copied())
}

/// Keys: one for `sample` (the private archive), one for another name, one admin.
struct Keys {
    sample: String,
    other: String,
    admin: String,
}

fn write_rules(dir: &Path) -> Keys {
    let mut file = KeyFile::default();
    let sample = file.add(rule(&["sample"])).unwrap();
    let other = file.add(rule(&["elsewhere-*"])).unwrap();
    let admin = file.add(KeyRecord { admin: true, ..rule(&["*"]) }).unwrap();
    file.write(&dir.join("keys.toml")).unwrap();
    std::fs::write(dir.join("secret"), SECRET).unwrap();
    Keys { sample, other, admin }
}

/// The server over `sample.tspack` (private, with every name matching `secret-*`) and
/// `elev.tspack` (public), its rules in `rules` (a folder of its own: not served).
async fn private_server(dir: &Path, rules: &Path, lean: bool) -> Running {
    let (keys, secret) = (rules.join("keys.toml"), rules.join("secret"));
    start(dir, |c| {
        c.lean_http1 = lean;
        c.private = vec!["sample".into(), "secret-*".into()];
        c.keys = Some(keys);
        c.signing_secret_file = Some(secret);
        // Thousands of refusals a test: paced, but not at the default's 200 a second.
        c.refusal_rate = 5000;
    })
    .await
}

/// One HTTP/1.1 request on a fresh keep-alive connection (as browsers send them: the
/// lean path answers those): status, head (lowercase), body (by its `Content-Length`).
async fn get(addr: SocketAddr, method: &str, target: &str, headers: &[(&str, &str)]) -> (u16, String, Vec<u8>) {
    let mut s = tokio::net::TcpStream::connect(addr).await.unwrap();
    let extra: String = headers.iter().map(|(k, v)| format!("{k}: {v}\r\n")).collect();
    let request = format!("{method} {target} HTTP/1.1\r\nHost: t\r\n{extra}\r\n");
    s.write_all(request.as_bytes()).await.unwrap();
    let mut answer = Vec::new();
    let mut chunk = vec![0u8; 65_536];
    let end = loop {
        if let Some(e) = answer.windows(4).position(|w| w == b"\r\n\r\n") {
            break e + 4;
        }
        let n = s.read(&mut chunk).await.unwrap();
        assert!(n > 0, "closed before a whole head: {:?}", String::from_utf8_lossy(&answer));
        answer.extend_from_slice(&chunk[..n]);
    };
    let head = String::from_utf8_lossy(&answer[..end]).to_lowercase();
    let status = head.split(' ').nth(1).and_then(|s| s.parse().ok()).unwrap_or(0);
    let length = head
        .lines()
        .find_map(|l| l.strip_prefix("content-length: "))
        .and_then(|v| v.trim().parse::<usize>().ok())
        .unwrap_or(0);
    let length = if method == "HEAD" || status == 304 || status == 204 { 0 } else { length };
    while answer.len() < end + length {
        let n = s.read(&mut chunk).await.unwrap();
        assert!(n > 0, "closed before the whole body");
        answer.extend_from_slice(&chunk[..n]);
    }
    (status, head, answer[end..end + length].to_vec())
}

#[tokio::test]
async fn keys_and_tokens_open_what_they_name_on_both_paths() {
    let (dir, path) = archives();
    let rules = tempfile::tempdir().unwrap();
    let keys = write_rules(rules.path());
    let file = std::fs::read(&path).unwrap();
    for lean in [true, false] {
        let server = private_server(dir.path(), rules.path(), lean).await;
        let a = server.addr;
        let bearer = |k: &str| format!("Bearer {k}");
        // No key: 401 with a JSON reason and nothing of the archive; public archives open.
        let (status, head, body) = get(a, "GET", "/sample.tspack", &[]).await;
        assert_eq!(status, 401, "lean {lean}: {head}");
        assert!(head.contains("www-authenticate: bearer") && head.contains("application/json"), "{head}");
        assert!(String::from_utf8_lossy(&body).contains("\"a key is needed\""), "{body:?}");
        assert_eq!(get(a, "GET", "/elev/elevation/0/0/0", &[]).await.0, 200);
        // The key for it, in a header: the same bytes as the file; a refusal for others.
        let (status, head, body) =
            get(a, "GET", "/sample.tspack", &[("authorization", &bearer(&keys.sample)), ("range", "bytes=0-99")]).await;
        assert_eq!((status, &body[..]), (206, &file[..100]), "lean {lean}");
        assert!(head.contains("cache-control: private"), "a header key's answer stays out of shared caches: {head}");
        for (target, key, expected) in [
            ("/sample/texture/3/0/0", &keys.sample, 200),
            ("/sample/texture/3/0/0", &keys.other, 403),
            ("/sample.tspack", &keys.other, 403),
            ("/secret-never-made.tspack", &keys.sample, 403),
            ("/sample.tspack", &format!("{}0", keys.sample), 403),
        ] {
            let (status, _, body) = get(a, "GET", target, &[("authorization", &bearer(key))]).await;
            assert_eq!(status, expected, "lean {lean}: {target}");
            if expected != 200 {
                assert!(body.len() < 200 && body.starts_with(b"{\"error\""), "{body:?}");
            }
        }
        // A private name that does not exist answers as one that does, to anyone without
        // a key that opens it (no enumeration).
        for key in [None, Some(&keys.other)] {
            let h: Vec<(&str, String)> = key.map(|k| ("authorization", bearer(k))).into_iter().collect();
            let h: Vec<(&str, &str)> = h.iter().map(|(k, v)| (*k, v.as_str())).collect();
            let real = get(a, "GET", "/sample/metadata", &h).await;
            let made_up = get(a, "GET", "/secret-x/metadata", &h).await;
            assert_eq!((real.0, real.2), (made_up.0, made_up.2), "lean {lean}");
        }
        // In the query (hyper's path): opens, and is carried into the URLs handed out.
        let (status, _, body) = get(a, "GET", &format!("/sample/metadata?access_token={}", keys.sample), &[]).await;
        assert_eq!(status, 200, "{body:?}");
        let (_, _, listing) = get(a, "GET", &format!("/?key={}", keys.sample), &[("accept", "application/json")]).await;
        let listing: serde_json::Value = serde_json::from_slice(&listing).unwrap();
        let names: Vec<&str> =
            listing["archives"].as_array().unwrap().iter().map(|x| x["name"].as_str().unwrap()).collect();
        assert_eq!(names, ["elev", "sample"]);
        assert_eq!(listing["archives"][1]["url"], format!("/sample.tspack?key={}", keys.sample));
        let (_, _, listing) = get(a, "GET", "/", &[("accept", "application/json")]).await;
        assert!(!String::from_utf8_lossy(&listing).contains("sample"), "the listing shows only what may be seen");
        let (_, _, page) = get(a, "GET", &format!("/view/sample?access_token={}", keys.sample), &[]).await;
        let page = String::from_utf8_lossy(&page);
        if !page.contains("built without the webplayer") {
            assert!(page.contains(&format!("../sample.tspack?access_token={}", keys.sample)), "{page}");
        }
        // Signed tokens: their archive only, until they expire.
        let secret = SECRET.as_bytes();
        let now = std::time::SystemTime::now().duration_since(std::time::UNIX_EPOCH).unwrap().as_secs();
        let good = token::sign(secret, &Scope::parse("sample").unwrap(), now + 600);
        let expired = token::sign(secret, &Scope::parse("sample").unwrap(), now - 3600);
        assert_eq!(get(a, "GET", &format!("/sample.tspack?access_token={good}"), &[]).await.0, 200);
        assert_eq!(get(a, "GET", &format!("/secret-b.tspack?access_token={good}"), &[]).await.0, 403);
        let (status, _, body) = get(a, "GET", &format!("/sample.tspack?access_token={expired}"), &[]).await;
        assert_eq!(status, 403);
        assert!(String::from_utf8_lossy(&body).contains("expired"));
        // Metrics: an admin key's; health: anyone's; a preflight may send Authorization.
        assert_eq!(get(a, "GET", "/metrics", &[]).await.0, 401);
        assert_eq!(get(a, "GET", "/metrics", &[("authorization", &bearer(&keys.sample))]).await.0, 403);
        assert_eq!(get(a, "GET", "/metrics", &[("authorization", &bearer(&keys.admin))]).await.0, 200);
        assert_eq!(get(a, "GET", "/healthz", &[]).await.0, 200);
        let preflight = [("origin", "https://maps.example.com"), ("access-control-request-method", "GET")];
        let (status, head, _) = get(a, "OPTIONS", "/sample.tspack", &preflight).await;
        assert!(status == 204 && head.contains("authorization"), "{head}");
        server.stop().await;
    }
}

/// What a request is made of, for the property below.
#[derive(Clone, Debug)]
struct Probe {
    method: &'static str,
    path: String,
    query: &'static str,
    headers: Vec<(&'static str, String)>,
    lean: bool,
}

fn probes(bad_keys: Vec<String>) -> impl Strategy<Value = Probe> {
    // Route shapes with the archive's name in its slot (spelt in several ways), and any
    // run of segments; mostly GETs without a query, as the lean path takes them.
    let name = prop::sample::select(vec!["sample", "%73ample", "sampl%65", "secret-a", "elev", "SAMPLE", "sample."]);
    let shape = prop::sample::select(vec![
        "/{n}.tspack",
        "/{n}/metadata",
        "/{n}/texture/{l}/{x}/{y}",
        "/{n}/0/{l}/{x}/{y}",
        "/{n}/tiles.json",
        "/{n}/texture/tiles.json",
        "/{n}/xyz/texture/{l}/{x}/{y}.png",
        "/{n}/layer.json",
        "/{n}/{l}/{x}/{y}.terrain",
        "/v1/{n}",
        "/view/{n}",
        "/{n}.json",
        "/{n}//{l}/{x}/{y}",
        "/{n}/../{n}.tspack",
        "/{n}.tspack/{l}",
    ]);
    let junk = prop::collection::vec(
        prop::sample::select(vec![
            "sample",
            "sample.tspack",
            "view",
            "v1",
            "xyz",
            "texture",
            "metadata",
            "0",
            "..",
            "",
        ]),
        1..6,
    )
    .prop_map(|s| format!("/{}", s.join("/")));
    let path = prop_oneof![
        4 => (shape, name, 0u8..4, 0u8..2, 0u8..2).prop_map(|(shape, n, l, x, y)| shape
            .replace("{n}", n)
            .replace("{l}", &l.to_string())
            .replace("{x}", &x.to_string())
            .replace("{y}", &y.to_string())),
        1 => junk,
    ];
    let method = prop::sample::select(vec!["GET", "GET", "GET", "HEAD", "POST", "OPTIONS", "PUT"]);
    let query = prop::sample::select(vec![
        "",
        "",
        "",
        "?access_token=",
        "?key=nothing",
        "?size=256",
        "?access_token=ts1~99999999999~sample~00",
    ]);
    let header = prop::sample::select(vec![
        ("range", "bytes=0-100".to_owned()),
        ("range", "bytes=5-9,20-30".to_owned()),
        ("accept-encoding", "zstd, gzip".to_owned()),
        ("origin", "https://evil.example".to_owned()),
        ("authorization", "Basic c2FtcGxlOnNhbXBsZQ==".to_owned()),
        ("authorization", format!("Bearer {}", bad_keys[0])),
        ("authorization", format!("Bearer {}", bad_keys[1])),
        ("authorization", "Bearer".to_owned()),
        ("if-none-match", "*".to_owned()),
        ("accept", "application/json".to_owned()),
    ]);
    (method, path, query, prop::collection::vec(header, 0..3), any::<bool>())
        .prop_map(|(method, path, query, headers, lean)| Probe { method, path, query, headers, lean })
}

/// No request without a key that opens the private archive gets any of its bytes: not a
/// slice of its file, not any answer a key that opens it gets, on either path.
#[test]
fn no_request_without_a_valid_key_gets_private_bytes() {
    let runtime = tokio::runtime::Builder::new_multi_thread().worker_threads(2).enable_all().build().unwrap();
    let (dir, path) = archives();
    let rules = tempfile::tempdir().unwrap();
    let keys = write_rules(rules.path());
    let file = std::fs::read(&path).unwrap();
    let (lean, hyper) = runtime.block_on(async {
        (private_server(dir.path(), rules.path(), true).await, private_server(dir.path(), rules.path(), false).await)
    });
    // Every answer a key that opens `sample` gets for the paths the probes build.
    let granted = |probe: &Probe| {
        let target = format!("{}?key={}", probe.path, keys.sample);
        runtime.block_on(get(lean.addr, "GET", &target, &[])).2
    };
    let bad = vec![keys.other.clone(), format!("{}f", keys.sample)];
    let mut runner = proptest::test_runner::TestRunner::new(ProptestConfig { cases: 600, ..ProptestConfig::default() });
    runner
        .run(&probes(bad), |probe| {
            let addr = if probe.lean { lean.addr } else { hyper.addr };
            let headers: Vec<(&str, &str)> = probe.headers.iter().map(|(k, v)| (*k, v.as_str())).collect();
            let target = format!("{}{}", probe.path, probe.query);
            let (status, head, body) = runtime.block_on(get(addr, probe.method, &target, &headers));
            let private_slice = body.len() >= 32 && file.windows(body.len()).any(|w| w == body);
            prop_assert!(!private_slice, "{probe:?}: {status} {head} carries bytes of the private archive");
            let reference = granted(&probe);
            let names_private = probe.path.to_lowercase().contains("ample") || probe.path.contains("secret");
            if names_private && reference.len() > 64 && status < 300 {
                prop_assert!(body != reference, "{probe:?}: {status} {head} is the private answer");
            }
            Ok(())
        })
        .unwrap();
    runtime.block_on(async {
        lean.stop().await;
        hyper.stop().await;
    });
}

/// 2 000 requests with bad keys, many at once, on both paths, while a good key keeps
/// reading: no byte of the private archive goes out, every good request is answered.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_flood_of_bad_keys_serves_nothing_private() {
    let (dir, path) = archives();
    let rules = tempfile::tempdir().unwrap();
    let keys = write_rules(rules.path());
    let file = std::fs::read(&path).unwrap();
    let server = private_server(dir.path(), rules.path(), true).await;
    let addr = server.addr;
    let mut tasks = Vec::new();
    for worker in 0..16 {
        let other = keys.other.clone();
        tasks.push(tokio::spawn(async move {
            let mut leaked = 0usize;
            for i in 0..125 {
                let bearer = format!("Bearer tk_{worker:04}{i:04}_{}", "0".repeat(64));
                let target =
                    if i % 2 == 0 { "/sample.tspack".to_owned() } else { format!("/sample/metadata?key={other}") };
                let (status, _, body) = get(addr, "GET", &target, &[("authorization", &bearer)]).await;
                assert!(status == 403, "{status}");
                leaked += body.len().saturating_sub(64);
            }
            leaked
        }));
    }
    let good = tokio::spawn(async move {
        let bearer = format!("Bearer {}", keys.sample);
        let mut ok = 0;
        for _ in 0..100 {
            let (status, _, body) = get(addr, "GET", "/sample.tspack", &[("authorization", &bearer)]).await;
            ok += usize::from(status == 200 && body == file);
        }
        ok
    });
    let mut leaked = 0;
    for t in tasks {
        leaked += t.await.unwrap();
    }
    assert_eq!(leaked, 0, "bytes beyond the refusals' JSON");
    assert_eq!(good.await.unwrap(), 100, "every good request answered whole during the flood");
    server.stop().await;
}

/// Refusals share a pace (`refusal_rate`, `refusal_burst`): beyond the burst each waits
/// its turn before it is answered, and keeps its connection; a valid key never waits. On
/// both paths.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn refusals_beyond_the_pace_wait_their_turn_and_valid_keys_do_not() {
    let (dir, _) = archives();
    let rules = tempfile::tempdir().unwrap();
    let keys = write_rules(rules.path());
    for lean in [true, false] {
        let (keys_file, secret) = (rules.path().join("keys.toml"), rules.path().join("secret"));
        let server = start(dir.path(), |c| {
            c.lean_http1 = lean;
            c.private = vec!["sample".into()];
            c.keys = Some(keys_file);
            c.signing_secret_file = Some(secret);
            c.refusal_rate = 20;
            c.refusal_burst = 2;
        })
        .await;
        let addr = server.addr;
        let started = std::time::Instant::now();
        // Eight refusals at once: two in the burst, then one every 50 ms (the last about
        // 300 ms after the first).
        let refused: Vec<_> = (0..8)
            .map(|_| {
                tokio::spawn(async move {
                    let (status, head, _) = get(addr, "GET", "/sample.tspack", &[]).await;
                    (status, head, started.elapsed())
                })
            })
            .collect();
        tokio::time::sleep(std::time::Duration::from_millis(20)).await;
        let bearer = format!("Bearer {}", keys.sample);
        let (status, _, _) = get(addr, "GET", "/sample.tspack", &[("authorization", &bearer)]).await;
        let good_at = started.elapsed();
        assert_eq!(status, 200);
        let mut last = std::time::Duration::ZERO;
        for r in refused {
            let (status, head, at) = r.await.unwrap();
            assert_eq!(status, 401, "lean {lean}");
            assert!(!head.contains("connection: close"), "a paced refusal keeps its connection: {head}");
            last = last.max(at);
        }
        assert!(last >= std::time::Duration::from_millis(250), "lean {lean}: the last refusal after {last:?}");
        assert!(good_at < last, "lean {lean}: the valid key ({good_at:?}) waited for the refusals ({last:?})");
        server.stop().await;
    }
}
