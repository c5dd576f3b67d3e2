//! The deployment files in `deploy/` in front of private terrain: the shipped caching
//! proxy (signed links cached under their own URLs, answers to header keys never stored)
//! and the shipped `auth_request` config serving static exports as the server allows.
#![allow(clippy::unwrap_used, clippy::expect_used, clippy::cast_possible_truncation, missing_docs)]

use std::path::{Path, PathBuf};
use std::process::Command;
use std::time::Duration;

use terrastream_testkit::browser::Process;
use terrastream_testkit::labelled::{LabelledSpec, write_labelled_archive};

fn deploy(path: &str) -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR")).join("deploy").join(path)
}

/// The shipped caching proxy in front of a server of private terrain: a signed link is
/// served and then cached under its own URL, and neither that entry nor an answer to a
/// header key is ever handed to a request without a credential.
#[test]
fn a_caching_proxy_keeps_private_terrain_private() {
    let dir = tempfile::tempdir().unwrap();
    let archives = dir.path().join("archives");
    std::fs::create_dir(&archives).unwrap();
    write_labelled_archive(&archives.join("terrain.tspack"), &LabelledSpec::default()).unwrap();
    let run = |args: &[&str]| {
        let out = Command::new(env!("CARGO_BIN_EXE_terrastream")).args(args).current_dir(dir.path()).output().unwrap();
        assert!(out.status.success(), "{args:?}: {}", String::from_utf8_lossy(&out.stderr));
        String::from_utf8(out.stdout).unwrap().trim().to_owned()
    };
    std::fs::write(dir.path().join("secret"), "the operator's secret, shared with no one").unwrap();
    let key = run(&["key", "new", "--archives", "terrain", "--keys", "keys.toml"]);
    let token = run(&["sign", "--secret-file", "secret", "--archive", "terrain", "--expires", "1h"]);
    let port = terrastream_testkit::nginx::free_port();
    let addr = format!("127.0.0.1:{port}");
    let args =
        ["-q", "serve", "archives", "--private", "--keys", "keys.toml", "--secret-file", "secret", "--addr", &addr];
    let child = Command::new(env!("CARGO_BIN_EXE_terrastream")).args(args).current_dir(dir.path()).spawn().unwrap();
    let _server = Process(child);
    let health = format!("http://{addr}/healthz");
    let healthy = (0..200).any(|_| {
        std::thread::sleep(Duration::from_millis(25));
        Command::new(env!("CARGO_BIN_EXE_terrastream")).args(["health", &health]).output().unwrap().status.success()
    });
    assert!(healthy, "the server did not become healthy");
    let shipped = std::fs::read_to_string(deploy("nginx/cache-proxy.conf")).unwrap();
    let config = shipped
        .replace("/var/cache/nginx/terrastream", &dir.path().join("cache").display().to_string())
        .replace("server server:8080;", &format!("server {addr};"))
        .replace("listen 8080;", "listen 127.0.0.1:{port};");
    let Some(nginx) = terrastream_testkit::nginx::start_nginx(dir.path(), &config) else { return };
    // Status and cache status of a GET through the proxy.
    let curl = |path: &str, header: Option<&str>| {
        let url = format!("http://127.0.0.1:{}{path}", nginx.port);
        let mut args = vec!["-s", "-o", "/dev/null", "-D", "-", "-r", "0-99"];
        if let Some(h) = header {
            args.extend(["-H", h]);
        }
        args.push(&url);
        let out = Command::new("curl").args(&args).output().unwrap();
        let head = String::from_utf8_lossy(&out.stdout).to_lowercase();
        let status: u16 = head.split(' ').nth(1).and_then(|s| s.parse().ok()).unwrap_or(0);
        let cache = head.lines().find_map(|l| l.strip_prefix("x-cache-status:").map(|v| v.trim().to_owned()));
        (status, cache.unwrap_or_default())
    };
    for path in ["/terrain.tspack", "/terrain/metadata"] {
        let signed = format!("{path}?access_token={token}");
        assert_eq!(curl(&signed, None).0, if path.ends_with("tspack") { 206 } else { 200 }, "{path}");
        let (status, cache) = curl(&signed, None);
        assert!(status < 300 && cache == "hit", "{path}: the signed link is cached ({status} {cache})");
        let bearer = format!("Authorization: Bearer {key}");
        assert!(curl(path, Some(&bearer)).0 < 300, "{path} with a header key");
        assert!(curl(path, Some(&bearer)).1 != "hit", "{path}: a header key's answer is never stored");
        for _ in 0..2 {
            assert_eq!(curl(path, None).0, 401, "{path}: nothing cached reaches a request without a credential");
        }
        assert_eq!(curl(&format!("{path}?access_token=ts1~1~terrain~{}", "0".repeat(64)), None).0, 403);
    }
}

/// Static exports of private terrain behind nginx, each request ruled on by the server's
/// `/auth` (the shipped `auth_request` config): the signed link or key opens its export,
/// nothing opens another's, and no file goes out without a credential.
#[test]
fn nginx_serves_private_exports_only_as_the_server_allows() {
    let dir = tempfile::tempdir().unwrap();
    let work = dir.path();
    let run = |args: &[&str]| {
        let out = Command::new(env!("CARGO_BIN_EXE_terrastream")).args(args).current_dir(work).output().unwrap();
        assert!(out.status.success(), "{args:?}: {}", String::from_utf8_lossy(&out.stderr));
        String::from_utf8(out.stdout).unwrap().trim().to_owned()
    };
    let dem =
        Path::new(env!("CARGO_MANIFEST_DIR")).join("tests/data/srtm-tamalpais-150x100-strips-int16-public-domain.tif");
    std::fs::create_dir(work.join("archives")).unwrap();
    run(&["-q", "tile", "--elevation", dem.to_str().unwrap(), "-o", "archives/valley.tspack"]);
    let www = work.join("www");
    run(&[
        "-q",
        "export",
        "archives/valley.tspack",
        "--to",
        "xyz",
        "--maxzoom",
        "12",
        "--base-url",
        "https://t/valley",
        "-o",
        "www/valley",
    ]);
    run(&["-q", "export", "archives/valley.tspack", "--to", "quantized-mesh", "-o", "www/valley-terrain"]);
    run(&[
        "-q",
        "export",
        "archives/valley.tspack",
        "--to",
        "pmtiles",
        "--encoding",
        "terrarium",
        "-o",
        "www/valley.pmtiles",
    ]);
    std::fs::write(work.join("secret"), "the operator's secret, shared with no one").unwrap();
    let key = run(&["key", "new", "--archives", "valley*", "--keys", "keys.toml"]);
    let sign = |scope: &[&str]| {
        let mut args = vec!["sign", "--secret-file", "secret", "--expires", "1h"];
        args.extend(scope);
        run(&args)
    };
    let (valley, terrain) = (sign(&["--archive", "valley"]), sign(&["--prefix", "/valley-terrain/"]));
    let port = terrastream_testkit::nginx::free_port();
    let addr = format!("127.0.0.1:{port}");
    let args =
        ["-q", "serve", "archives", "--private", "--keys", "keys.toml", "--secret-file", "secret", "--addr", &addr];
    let _server =
        Process(Command::new(env!("CARGO_BIN_EXE_terrastream")).args(args).current_dir(work).spawn().unwrap());
    let health = format!("http://{addr}/healthz");
    let healthy = (0..200).any(|_| {
        std::thread::sleep(Duration::from_millis(25));
        Command::new(env!("CARGO_BIN_EXE_terrastream")).args(["health", &health]).output().unwrap().status.success()
    });
    assert!(healthy, "the server did not become healthy");
    let shipped = std::fs::read_to_string(deploy("nginx/auth-request.conf")).unwrap();
    let config = shipped
        .replace("server terrastream:8080;", &format!("server {addr};"))
        .replace("listen 8080;", "listen 127.0.0.1:{port};")
        .replace("root /srv/terrain-exports;", &format!("root {};", www.display()));
    let Some(nginx) = terrastream_testkit::nginx::start_nginx(&www, &config) else { return };
    let status = |path: &str, header: Option<&str>| {
        let url = format!("http://127.0.0.1:{}{path}", nginx.port);
        let mut args = vec!["-s", "-o", "/dev/null", "-w", "%{http_code}", "-r", "0-99"];
        if let Some(h) = header {
            args.extend(["-H", h]);
        }
        args.push(&url);
        let out = Command::new("curl").args(&args).output().unwrap();
        String::from_utf8_lossy(&out.stdout).parse::<u16>().unwrap_or(0)
    };
    let tile = walk_one(&www.join("valley"), "webp");
    let terrain_tile = walk_one(&www.join("valley-terrain"), "terrain");
    let bearer = format!("Authorization: Bearer {key}");
    for (path, token) in [
        ("/valley/tiles.json".to_owned(), &valley),
        (format!("/valley/{tile}"), &valley),
        ("/valley.pmtiles".to_owned(), &valley),
        ("/valley-terrain/layer.json".to_owned(), &terrain),
        (format!("/valley-terrain/{terrain_tile}"), &terrain),
    ] {
        assert_eq!(status(&path, None), 401, "{path} without a credential");
        assert!(matches!(status(&format!("{path}?access_token={token}"), None), 200 | 206), "{path} signed");
        assert!(matches!(status(&path, Some(&bearer)), 200 | 206), "{path} with a key in a header");
        assert!(matches!(status(&format!("{path}?key={key}"), None), 200 | 206), "{path} with a key in the URL");
    }
    assert_eq!(status("/valley/tiles.json?access_token=".to_owned().as_str(), None), 401);
    assert_eq!(status(&format!("/valley-terrain/layer.json?access_token={valley}"), None), 403, "another export");
    assert_eq!(status(&format!("/valley/tiles.json?access_token={terrain}"), None), 403, "outside the prefix");
}

/// A file with `extension` somewhere under `root`, as a path relative to it.
fn walk_one(root: &Path, extension: &str) -> String {
    let mut folders = vec![root.to_path_buf()];
    while let Some(folder) = folders.pop() {
        for entry in std::fs::read_dir(&folder).unwrap().map(Result::unwrap) {
            let path = entry.path();
            if path.is_dir() {
                folders.push(path);
            } else if path.extension().is_some_and(|e| e == extension) {
                return path.strip_prefix(root).unwrap().display().to_string();
            }
        }
    }
    panic!("no .{extension} file under {}", root.display());
}
