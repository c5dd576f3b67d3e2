//! Private terrain from the command line: `key new`, `key list`, `key revoke` and `sign`
//! against a `terrastream serve --private`, as an operator runs them; keys and tokens
//! never appear in the server's logs (debug logging on) or its metrics.
#![allow(clippy::unwrap_used, clippy::expect_used, clippy::cast_possible_truncation, missing_docs)]

use std::io::{BufRead, Read, Write};
use std::path::Path;
use std::process::{Command, Stdio};
use std::time::{Duration, Instant};

fn exe() -> &'static Path {
    Path::new(env!("CARGO_BIN_EXE_terrastream"))
}

/// `terrastream ARGS` in `cwd`: its standard output; fails the test on failure.
fn run(args: &[&str], cwd: &Path) -> String {
    let out = Command::new(exe()).args(args).current_dir(cwd).output().unwrap();
    assert!(out.status.success(), "terrastream {args:?}: {}", String::from_utf8_lossy(&out.stderr));
    String::from_utf8(out.stdout).unwrap()
}

/// One GET over HTTP/1.1 (keep-alive, as browsers send it): status and body.
fn get(port: u16, target: &str, headers: &[(&str, &str)]) -> (u16, Vec<u8>) {
    let mut s = std::net::TcpStream::connect(("127.0.0.1", port)).unwrap();
    s.set_read_timeout(Some(Duration::from_secs(30))).unwrap();
    let extra: String = headers.iter().map(|(k, v)| format!("{k}: {v}\r\n")).collect();
    write!(s, "GET {target} HTTP/1.1\r\nHost: 127.0.0.1\r\n{extra}\r\n").unwrap();
    let mut reader = std::io::BufReader::new(s);
    let mut status_line = String::new();
    reader.read_line(&mut status_line).unwrap();
    let status = status_line.split(' ').nth(1).and_then(|s| s.parse().ok()).unwrap_or(0);
    let mut length = 0;
    loop {
        let mut line = String::new();
        reader.read_line(&mut line).unwrap();
        if line.trim().is_empty() {
            break;
        }
        if let Some(v) = line.to_lowercase().strip_prefix("content-length:") {
            length = v.trim().parse().unwrap();
        }
    }
    let mut body = vec![0; length];
    reader.read_exact(&mut body).unwrap();
    (status, body)
}

#[test]
fn keys_and_signed_links_from_the_command_line_and_nothing_in_the_logs() {
    let dir = tempfile::tempdir().unwrap();
    let work = dir.path();
    std::fs::create_dir(work.join("served")).unwrap();
    let dem =
        terrastream_testkit::golden::repo().join("tests/data/srtm-tamalpais-150x100-strips-int16-public-domain.tif");
    run(&["-q", "tile", "--elevation", dem.to_str().unwrap(), "-o", "served/valley.tspack"], work);
    std::fs::copy(work.join("served/valley.tspack"), work.join("served/other.tspack")).unwrap();
    std::fs::write(work.join("secret"), "a secret of the operator, 40 bytes long\n").unwrap();
    // Keys: shown once, stored as hashes; listed by id; bad rules refused.
    let key =
        run(&["key", "new", "--archives", "valley", "--keys", "keys.toml", "--note", "the survey's client"], work);
    let key = key.trim().to_owned();
    let admin = run(&["key", "new", "--archives", "*", "--admin", "--keys", "keys.toml"], work).trim().to_owned();
    assert!(key.starts_with("tk_") && key.len() == 76, "{key}");
    let stored = std::fs::read_to_string(work.join("keys.toml")).unwrap();
    assert!(!stored.contains(&key[12..]) && !stored.contains(&admin[12..]), "{stored}");
    let listed = run(&["key", "list", "--keys", "keys.toml"], work);
    assert!(
        listed.contains(&key[..11]) && listed.contains("archives valley") && listed.contains("the survey's client")
    );
    let refused = Command::new(exe()).args(["key", "new", "--archives", "a", "--rate", "0"]).current_dir(work).output();
    assert!(!refused.unwrap().status.success());
    let token = run(&["sign", "--secret-file", "secret", "--archive", "valley", "--expires", "1h"], work);
    let token = token.trim().to_owned();
    let link =
        run(&["sign", "--secret-file", "secret", "--prefix", "/valley/", "--url", "http://h/valley/tiles.json"], work);
    assert!(link.starts_with("http://h/valley/tiles.json?access_token=ts1~"), "{link}");

    // The server, every archive private, logging at debug level into a file.
    let log = std::fs::File::create(work.join("server.log")).unwrap();
    let args =
        ["serve", "served", "--private", "--keys", "keys.toml", "--secret-file", "secret", "--addr", "127.0.0.1:0"];
    let mut child = Command::new(exe())
        .args(args)
        .env("RUST_LOG", "debug")
        .current_dir(work)
        .stdout(Stdio::piped())
        .stderr(log)
        .spawn()
        .unwrap();
    let stdout = std::io::BufReader::new(child.stdout.take().unwrap());
    let line = stdout.lines().map_while(Result::ok).find(|l| l.starts_with("listening on http://")).unwrap();
    let port: u16 = line
        .trim_start_matches("listening on http://")
        .split('/')
        .next()
        .unwrap()
        .rsplit(':')
        .next()
        .unwrap()
        .parse()
        .unwrap();
    let bearer = format!("Bearer {key}");
    assert_eq!(get(port, "/valley.tspack", &[]).0, 401);
    assert_eq!(get(port, "/valley.tspack", &[("authorization", &bearer)]).0, 200, "a header key, lean path");
    assert_eq!(get(port, &format!("/valley/metadata?access_token={key}"), &[]).0, 200, "a query key");
    assert_eq!(get(port, &format!("/other/metadata?access_token={key}"), &[]).0, 403, "another archive");
    assert_eq!(get(port, &format!("/valley.tspack?access_token={token}"), &[]).0, 200, "a signed token");
    assert_eq!(get(port, &format!("/other.tspack?access_token={token}"), &[]).0, 403);
    let (status, tilejson) = get(port, &format!("/valley/tiles.json?key={key}"), &[]);
    assert_eq!(status, 200);
    let tilejson: serde_json::Value = serde_json::from_slice(&tilejson).unwrap();
    let template = tilejson["tiles"][0].as_str().unwrap().to_owned();
    assert!(template.ends_with(&format!("?key={key}")), "{template}");
    // The template, filled in, opens a tile with nothing but its own URL.
    let tile = template.split_once("127.0.0.1").map(|(_, rest)| rest.split_once('/').unwrap().1).unwrap();
    let tile = format!("/{}", tile.replace("{z}", "12").replace("{x}", "654").replace("{y}", "1582"));
    assert!(matches!(get(port, &tile, &[]).0, 200 | 404), "{tile}");
    let (status, metrics) = get(port, "/metrics", &[("authorization", &format!("Bearer {admin}"))]);
    assert_eq!(status, 200);
    // Revoked: refused within a reload.
    run(&["key", "revoke", &key[..11], "--keys", "keys.toml"], work);
    let deadline = Instant::now() + Duration::from_secs(10);
    while get(port, "/valley.tspack", &[("authorization", &bearer)]).0 != 403 {
        assert!(Instant::now() < deadline, "the revoked key still opens the archive");
        std::thread::sleep(Duration::from_millis(100));
    }
    let _ = child.kill();
    let _ = child.wait();
    let logs = std::fs::read_to_string(work.join("server.log")).unwrap();
    assert!(logs.contains("valley/metadata") && logs.contains("access_token=…"), "debug logs of the requests: {logs}");
    let metrics = String::from_utf8(metrics).unwrap();
    for secret in [&key[3..], &admin[3..], &token[4..]] {
        assert!(!logs.contains(secret), "a credential in the logs");
        assert!(!metrics.contains(secret), "a credential in the metrics");
    }
}
