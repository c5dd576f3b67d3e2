//! The deployment files in `deploy/`: nginx as a caching proxy in front of a really started
//! `terrastream serve` (a second pass served from the cache, a replaced archive picked up
//! without mixing versions), and offline validation of the Dockerfile, compose file,
//! Kubernetes manifests and systemd unit.
//! (nginx as a static host of archives is exercised by `client/tests/stream.rs`.)
#![allow(clippy::unwrap_used, clippy::expect_used, clippy::cast_possible_truncation, missing_docs)]

use std::collections::HashMap;
use std::path::{Path, PathBuf};
use std::process::{Command, Stdio};
use std::sync::Arc;
use std::time::{Duration, Instant};

use terrastream_client::{Camera, DecodedTile, Origin, SelectOptions, StreamOptions, Streamer, TileData, UploadBudget};
use terrastream_format::TileKey;
use terrastream_testkit::browser::Process;
use terrastream_testkit::labelled::{LabelledSpec, label_colour, write_labelled_archive};

fn deploy(path: &str) -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR")).join("deploy").join(path)
}

/// `terrastream serve` as a child process, killed on drop.
struct Server {
    _child: Process,
    port: u16,
}

fn start_server(dir: &Path) -> Server {
    let port = terrastream_testkit::nginx::free_port();
    let config = dir.join("server.toml");
    // The shipped config, with this test's address, folder and a quick rescan.
    let shipped = std::fs::read_to_string(deploy("k8s/server.toml")).unwrap();
    let text = shipped
        .replace("addr = \"0.0.0.0:8080\"", &format!("addr = \"127.0.0.1:{port}\""))
        .replace("paths = [\"/srv/terrastream\"]", &format!("paths = [{:?}]", dir.join("archives")))
        .replace("reload_interval_ms = 2000", "reload_interval_ms = 100");
    assert_ne!(text, shipped);
    std::fs::write(&config, text).unwrap();
    let child = Command::new(env!("CARGO_BIN_EXE_terrastream"))
        .args(["-q", "serve", "--config"])
        .arg(&config)
        .stdout(Stdio::null())
        .spawn()
        .unwrap();
    let server = Server { _child: Process(child), port };
    let health = format!("http://127.0.0.1:{port}/healthz");
    for _ in 0..200 {
        let ok = Command::new(env!("CARGO_BIN_EXE_terrastream")).args(["health", &health]).output().unwrap();
        if ok.status.success() {
            return server;
        }
        std::thread::sleep(Duration::from_millis(25));
    }
    panic!("the server did not become healthy");
}

fn camera(x: f64, z: f64) -> Camera {
    Camera::look_at(glam::DVec3::new(x, 220.0, z), glam::DVec3::new(x + 150.0, 150.0, z + 150.0), 800, 600)
}

/// Streams three views to completion; every tile shown is checked against `version`.
fn stream(s: &mut Streamer, shown: &mut HashMap<TileKey, Arc<DecodedTile>>, version: u8) {
    let mut generation = s.generation();
    for (x, z) in [(100.0, 100.0), (900.0, 400.0), (300.0, 1200.0)] {
        let start = Instant::now();
        loop {
            s.update(&camera(x, z));
            if s.generation() != generation {
                shown.clear();
                generation = s.generation();
            }
            for u in s.drain_uploads(UploadBudget { max_tiles: 16, max_bytes: 1 << 20 }) {
                let k = u.tile.key;
                if let TileData::Rgba8(p) = &u.tile.data {
                    let [r, g, b] = label_colour(k.lod(), k.x(), k.y(), version);
                    assert_eq!(&p[..4], &[r, g, b, 255], "tile {k}: wrong tile or version");
                }
                shown.insert(k, u.tile.clone());
            }
            if s.metadata().is_some() && s.pending() == 0 {
                break;
            }
            assert!(start.elapsed() < Duration::from_secs(30), "{:?} {:?}", s.stats(), s.last_error());
            std::thread::sleep(Duration::from_millis(2));
        }
    }
}

fn options() -> StreamOptions {
    StreamOptions {
        select: SelectOptions { pixel_error: 8.0, ..SelectOptions::default() },
        retry_backoff: Duration::from_millis(5),
        max_retry_backoff: Duration::from_millis(100),
        ..StreamOptions::default()
    }
}

#[test]
fn nginx_caching_proxy_serves_the_second_pass_and_picks_up_a_replaced_archive() {
    let dir = tempfile::tempdir().unwrap();
    let archives = dir.path().join("archives");
    std::fs::create_dir(&archives).unwrap();
    let path = archives.join("terrain.tspack");
    write_labelled_archive(&path, &LabelledSpec::default()).unwrap();
    let server = start_server(dir.path());

    // The shipped proxy config, pointed at this server, a private cache and a 1 s validity.
    let shipped = std::fs::read_to_string(deploy("nginx/cache-proxy.conf")).unwrap();
    let cache = dir.path().join("cache");
    let config = shipped
        .replace("/var/cache/nginx/terrastream", &cache.display().to_string())
        .replace("server server:8080;", &format!("server 127.0.0.1:{};", server.port))
        .replace("listen 8080;", "listen 127.0.0.1:{port};")
        .replace(" 10s;", " 1s;");
    assert_eq!(config.matches(" 1s;").count(), 2, "both validities replaced");
    let Some(nginx) = terrastream_testkit::nginx::start_nginx(dir.path(), &config) else { return };
    let url = format!("http://127.0.0.1:{}/terrain.tspack", nginx.port);

    // Pass 1 fills the cache; what is shown equals what the server itself streams.
    let mut first = HashMap::new();
    let mut s = Streamer::open(Origin::parse(&url).unwrap(), options()).unwrap();
    stream(&mut s, &mut first, 1);
    let direct_url = format!("http://127.0.0.1:{}/terrain.tspack", server.port);
    let mut direct = HashMap::new();
    stream(&mut Streamer::open(Origin::parse(&direct_url).unwrap(), options()).unwrap(), &mut direct, 1);
    assert_eq!(first.len(), direct.len());
    for (k, t) in &direct {
        assert_eq!(first.get(k), Some(t), "tile {k} through the proxy");
    }

    // Pass 2, a new client right away: served from the cache, the server sees nothing.
    let before = terrastream_testkit::http::archive_requests(server.port);
    let mut second = HashMap::new();
    stream(&mut Streamer::open(Origin::parse(&url).unwrap(), options()).unwrap(), &mut second, 1);
    assert_eq!(second.len(), first.len());
    assert_eq!(terrastream_testkit::http::archive_requests(server.port), before, "the second pass came from the cache");
    let hit = Command::new("curl").args(["-s", "-o", "/dev/null", "-D", "-", "-r", "0-99", &url]).output();
    if let Ok(hit) = hit {
        let head = String::from_utf8_lossy(&hit.stdout).to_lowercase();
        assert!(head.contains("x-cache-status: hit"), "{head}");
    }

    // A new version is published by rename. Once the server serves it, and after the
    // cache validity, the proxy revalidates; the streaming client notices the new ETag,
    // drops everything, and shows only version 2. (Waiting for the server first: a
    // revalidation before it sees the rename renews the old version for another validity,
    // and a client with every tile it needs asks nothing more.)
    let etag = || {
        let head = Command::new("curl").args(["-s", "-o", "/dev/null", "-D", "-", "-r", "0-99", &direct_url]).output();
        let head = String::from_utf8_lossy(&head.map(|o| o.stdout).unwrap_or_default()).to_lowercase();
        head.lines().find_map(|l| l.strip_prefix("etag:").map(|v| v.trim().to_owned()))
    };
    let old = etag();
    let next = archives.join("next.tmp");
    write_labelled_archive(&next, &LabelledSpec { version: 2, ..LabelledSpec::default() }).unwrap();
    std::fs::rename(&next, &path).unwrap();
    let start = Instant::now();
    while etag() == old {
        assert!(start.elapsed() < Duration::from_secs(20), "the server still serves {old:?}");
        std::thread::sleep(Duration::from_millis(50));
    }
    std::thread::sleep(Duration::from_millis(1500));
    let generation = s.generation();
    let mut after = HashMap::new();
    let start = Instant::now();
    // A corner none of the earlier views looked at, so that tiles must be fetched.
    let corner =
        Camera::look_at(glam::DVec3::new(1450.0, 200.0, 150.0), glam::DVec3::new(1550.0, 170.0, 50.0), 800, 600);
    while s.generation() == generation {
        s.update(&corner);
        s.drain_uploads(UploadBudget { max_tiles: 16, max_bytes: 1 << 20 });
        assert!(start.elapsed() < Duration::from_secs(20), "the replacement was not noticed: {:?}", s.stats());
        std::thread::sleep(Duration::from_millis(5));
    }
    stream(&mut s, &mut after, 2);
    assert!(!after.is_empty());
    assert_eq!(s.stats().reloads, 1);
    drop(nginx);
}

fn yaml_docs(path: &Path) -> Vec<serde_json::Value> {
    let text = std::fs::read_to_string(path).unwrap();
    text.split("\n---")
        .filter(|d| d.lines().any(|l| !l.trim().is_empty() && !l.trim_start().starts_with('#')))
        .map(|d| serde_yaml::from_str::<serde_json::Value>(d).unwrap_or_else(|e| panic!("{}: {e}", path.display())))
        .collect()
}

#[test]
fn kubernetes_manifests_are_complete_and_locked_down() {
    let dir = deploy("k8s");
    let mut kinds = HashMap::new();
    for entry in std::fs::read_dir(&dir).unwrap() {
        let path = entry.unwrap().path();
        if path.extension().is_none_or(|e| e != "yaml") {
            continue;
        }
        for doc in yaml_docs(&path) {
            let kind = doc["kind"].as_str().unwrap_or_else(|| panic!("{}: no kind", path.display())).to_owned();
            assert!(doc["apiVersion"].is_string(), "{}: no apiVersion", path.display());
            if kind != "Kustomization" {
                assert!(doc["metadata"]["name"].is_string(), "{}: no metadata.name", path.display());
            }
            kinds.entry(kind.clone()).or_insert_with(Vec::new).push((path.clone(), doc));
        }
    }
    for k in ["Deployment", "Service", "HorizontalPodAutoscaler", "PodDisruptionBudget", "ConfigMap"] {
        assert!(kinds.contains_key(k), "no {k}");
    }
    assert!(kinds.contains_key("PersistentVolumeClaim"));
    // Every resource the kustomization lists exists.
    let (kpath, kustomization) = &kinds["Kustomization"][0];
    for r in kustomization["resources"].as_array().unwrap() {
        assert!(dir.join(r.as_str().unwrap()).exists(), "{}: {r} missing", kpath.display());
    }
    let selector = |doc: &serde_json::Value| doc["spec"]["selector"]["matchLabels"].clone();
    for (path, d) in &kinds["Deployment"] {
        let at = path.display();
        let spec = &d["spec"]["template"]["spec"];
        assert_eq!(selector(d), d["spec"]["template"]["metadata"]["labels"], "{at}: selector matches the pods");
        assert_eq!(spec["securityContext"]["runAsNonRoot"], true, "{at}");
        let containers = spec["containers"].as_array().unwrap();
        let server = containers.iter().find(|c| c["args"][0] == "serve").unwrap_or_else(|| panic!("{at}"));
        for probe in ["readinessProbe", "livenessProbe"] {
            assert_eq!(server[probe]["httpGet"]["path"], "/healthz", "{at}: {probe}");
        }
        for c in containers.iter().chain(spec["initContainers"].as_array().into_iter().flatten()) {
            let name = &c["name"];
            assert!(c["resources"]["limits"]["memory"].is_string(), "{at}: {name} has no memory limit");
            assert!(c["resources"]["limits"]["cpu"].is_string(), "{at}: {name} has no cpu limit");
            assert!(c["resources"]["requests"].is_object(), "{at}: {name} has no requests");
            assert_eq!(c["securityContext"]["allowPrivilegeEscalation"], false, "{at}: {name}");
            assert_eq!(c["securityContext"]["readOnlyRootFilesystem"], true, "{at}: {name}");
            assert!(!c["image"].as_str().unwrap().ends_with(":latest"), "{at}: {name} pins its image");
        }
        let archives = server["volumeMounts"].as_array().unwrap().iter().find(|m| m["mountPath"] == "/srv/terrastream");
        assert_eq!(archives.unwrap()["readOnly"], true, "{at}: archives are mounted read-only");
        // The config the server is told to read comes from the ConfigMap.
        let volumes = spec["volumes"].as_array().unwrap();
        assert!(volumes.iter().any(|v| v["configMap"]["name"] == "terrastream-config"), "{at}");
        assert_eq!(server["args"], serde_json::json!(["serve", "--config", "/etc/terrastream/server.toml"]));
    }
    let (_, main) = kinds["Deployment"].iter().find(|(_, d)| d["metadata"]["name"] == "terrastream").unwrap();
    let labels = selector(main);
    for kind in ["Service", "PodDisruptionBudget"] {
        let doc = &kinds[kind][0].1;
        let sel = if kind == "Service" { doc["spec"]["selector"].clone() } else { selector(doc) };
        assert_eq!(sel, labels, "{kind} selects the deployment's pods");
    }
    let hpa = &kinds["HorizontalPodAutoscaler"][0].1;
    assert_eq!(hpa["spec"]["scaleTargetRef"]["name"], "terrastream");
    assert!(hpa["spec"]["minReplicas"].as_u64().unwrap() >= 2, "one pod may be disrupted");
    // The ConfigMap's TOML is a valid server config, the same as the one shipped for compose/systemd.
    let toml = kinds["ConfigMap"][0].1["data"]["server.toml"].as_str().unwrap().to_owned();
    let parsed = terrastream_server::ServerConfig::from_toml(&toml).unwrap();
    let shipped = std::fs::read_to_string(deploy("k8s/server.toml")).unwrap();
    assert_eq!(parsed, terrastream_server::ServerConfig::from_toml(&shipped).unwrap());
}

#[test]
fn compose_dockerfile_and_systemd_unit_hold_together() {
    let compose = &yaml_docs(&deploy("compose.yaml"))[0];
    let services = compose["services"].as_object().unwrap();
    let server = &services["server"];
    assert_eq!(server["build"]["dockerfile"], "deploy/Dockerfile");
    assert!(server["volumes"].as_array().unwrap().iter().any(|v| v.as_str().unwrap().ends_with("/srv/terrastream:ro")));
    assert_eq!(server["read_only"], true);
    assert!(server["healthcheck"]["test"].as_array().unwrap().iter().any(|a| a == "health"));
    let cache = &services["cache"];
    let mounted: Vec<&str> = cache["volumes"].as_array().unwrap().iter().map(|v| v.as_str().unwrap()).collect();
    assert!(mounted.iter().any(|v| v.starts_with("./nginx/cache-proxy.conf:")), "{mounted:?}");
    for v in mounted
        .iter()
        .chain(server["volumes"].as_array().unwrap().iter().map(|v| v.as_str().unwrap()).collect::<Vec<_>>().iter())
    {
        if let Some(local) = v.strip_prefix("./") {
            let file = local.split(':').next().unwrap();
            assert!(deploy(file).exists(), "compose mounts {file}, which is not in deploy/");
        }
    }
    assert!(cache["image"].as_str().unwrap().starts_with("nginx:1."), "a pinned nginx");

    // The Dockerfile: multi-stage, locked build, non-root runtime, health check through
    // the binary itself (the runtime image has no shell or curl).
    let docker = std::fs::read_to_string(deploy("Dockerfile")).unwrap();
    let froms: Vec<&str> = docker.lines().filter(|l| l.starts_with("FROM ")).collect();
    assert!(froms.len() >= 2, "multi-stage");
    assert!(froms.iter().all(|f| !f.contains(":latest") && f.contains(':')), "pinned base images: {froms:?}");
    assert!(docker.contains("cargo build --release --locked"));
    let last_user = docker.lines().rev().find(|l| l.starts_with("USER ")).unwrap();
    assert!(!last_user.contains("root") && !last_user.contains(" 0"), "{last_user}");
    assert!(docker.contains("HEALTHCHECK") && docker.contains("\"health\""));
    // Every path the build copies exists.
    for line in docker.lines().filter(|l| l.starts_with("COPY ") && !l.contains("--from")) {
        let parts: Vec<&str> = line.split_whitespace().collect();
        for src in &parts[1..parts.len() - 1] {
            assert!(Path::new(env!("CARGO_MANIFEST_DIR")).join(src).exists(), "Dockerfile copies missing {src}");
        }
    }
    // The dependency stage sees the whole workspace: every member's manifest is copied.
    let manifest = std::fs::read_to_string(Path::new(env!("CARGO_MANIFEST_DIR")).join("Cargo.toml")).unwrap();
    let members = manifest.lines().find(|l| l.starts_with("members")).unwrap();
    for member in members.split('"').skip(1).step_by(2) {
        assert!(docker.contains(&format!("COPY {member}/Cargo.toml {member}/Cargo.toml")), "Dockerfile lacks {member}");
    }
    assert!(docker.contains("scripts/build-player.sh"), "the image embeds the webplayer");
    // The health subcommand the image relies on works against a real server.
    let dir = tempfile::tempdir().unwrap();
    std::fs::create_dir(dir.path().join("archives")).unwrap();
    let server = start_server(dir.path());
    let bad = Command::new(env!("CARGO_BIN_EXE_terrastream"))
        .args(["health", &format!("http://127.0.0.1:{}/nothing-here", server.port)])
        .output()
        .unwrap();
    assert!(!bad.status.success(), "a 404 is unhealthy");
    drop(server);

    // The systemd unit: sandboxing present; `systemd-analyze verify` where available.
    let unit = std::fs::read_to_string(deploy("systemd/terrastream.service")).unwrap();
    for option in ["NoNewPrivileges=yes", "ProtectSystem=strict", "ReadOnlyPaths=/srv/terrastream", "DynamicUser=yes"] {
        assert!(unit.contains(option), "unit lacks {option}");
    }
    let analyze = Path::new("/usr/bin/systemd-analyze");
    if analyze.exists() {
        let local = dir.path().join("terrastream.service");
        std::fs::write(&local, unit.replace("/usr/local/bin/terrastream", env!("CARGO_BIN_EXE_terrastream"))).unwrap();
        let out = Command::new(analyze).arg("verify").arg(&local).output().unwrap();
        let text = format!("{}{}", String::from_utf8_lossy(&out.stdout), String::from_utf8_lossy(&out.stderr));
        let problems: Vec<&str> = text
            .lines()
            .filter(|l| l.contains("terrastream.service"))
            .filter(|l| !l.contains("Unit configured to use KillMode=none") && !l.trim().is_empty())
            .collect();
        assert!(out.status.success() && problems.is_empty(), "systemd-analyze verify: {text}");
    } else {
        eprintln!("\n*** systemd-analyze not installed: the unit file was checked for its options only ***\n");
    }
}

/// `kubernetes-validate` (PyPI; the test command installs it) on every manifest in
/// `deploy/k8s`, against the Kubernetes API schemas, strictly (no unknown fields); and on a
/// broken copy, which must fail, so that a validator that checks nothing is noticed.
#[test]
fn kubernetes_manifests_pass_the_api_schemas() {
    let validate = |files: &[PathBuf]| {
        Command::new("kubernetes-validate").args(["-k", "1.30.0", "--strict", "--quiet"]).args(files).output()
    };
    let files: Vec<PathBuf> = std::fs::read_dir(deploy("k8s"))
        .unwrap()
        .map(|e| e.unwrap().path())
        .filter(|p| p.extension().is_some_and(|e| e == "yaml") && !p.ends_with("kustomization.yaml"))
        .collect();
    assert!(files.iter().any(|p| p.ends_with("tile-job.yaml")));
    let out = match validate(&files) {
        Ok(out) => out,
        Err(e) => {
            assert!(std::env::var_os("CI").is_none(), "kubernetes-validate: {e} (pip install kubernetes-validate)");
            eprintln!("\n*** SKIPPING: kubernetes-validate is not installed (pip install kubernetes-validate) ***\n");
            return;
        }
    };
    let text = format!("{}{}", String::from_utf8_lossy(&out.stdout), String::from_utf8_lossy(&out.stderr));
    assert!(out.status.success() && !text.contains("ERROR"), "{text}");
    let dir = tempfile::tempdir().unwrap();
    let broken = dir.path().join("broken.yaml");
    let job = std::fs::read_to_string(deploy("k8s/tile-job.yaml")).unwrap();
    std::fs::write(&broken, job.replacen("completionMode: Indexed", "completionMode: Indexed\n  completionz: 3", 1))
        .unwrap();
    let out = validate(&[broken]).unwrap();
    assert!(!out.status.success(), "an unknown field passed: {}", String::from_utf8_lossy(&out.stdout));
}

/// A projected (UTM 33N) GeoTIFF: `(w, h)` samples of `spacing` metres, the north-west
/// corner at (east, north); `sample(x, y)` in metres gives the values (8-bit RGB if
/// `rgb`, else f32 heights).
fn utm_geotiff(path: &Path, (w, h): (u32, u32), (east, north): (f64, f64), spacing: f64, rgb: bool) {
    use tiff::encoder::{TiffEncoder, colortype};
    use tiff::tags::Tag;
    let mut encoder = TiffEncoder::new(std::fs::File::create(path).unwrap()).unwrap();
    let at = |i: u32, j: u32| (east + (f64::from(i) + 0.5) * spacing, north - (f64::from(j) + 0.5) * spacing);
    let tags = |e: &mut tiff::encoder::DirectoryEncoder<'_, std::fs::File, tiff::encoder::TiffKindStandard>| {
        e.write_tag(Tag::Unknown(33550), &[spacing, spacing, 0.0][..]).unwrap();
        e.write_tag(Tag::Unknown(33922), &[0.0, 0.0, 0.0, east, north, 0.0][..]).unwrap();
        e.write_tag(Tag::Unknown(34735), &[1u16, 1, 0, 2, 1024, 0, 1, 1, 3072, 0, 1, 32633][..]).unwrap();
    };
    if rgb {
        let mut image = encoder.new_image::<colortype::RGB8>(w, h).unwrap();
        tags(image.encoder());
        let data: Vec<u8> = (0..h)
            .flat_map(|j| (0..w).map(move |i| (i, j)))
            .flat_map(|(i, j)| {
                let (x, y) = at(i, j);
                [(x / 7.0 % 256.0) as u8, (y / 5.0 % 256.0) as u8, ((x + y) / 3.0 % 256.0) as u8]
            })
            .collect();
        image.write_data(&data).unwrap();
    } else {
        let mut image = encoder.new_image::<colortype::Gray32Float>(w, h).unwrap();
        tags(image.encoder());
        let data: Vec<f32> = (0..h)
            .flat_map(|j| (0..w).map(move |i| (i, j)))
            .map(|(i, j)| {
                let (x, y) = at(i, j);
                (400.0 + 90.0 * (x / 900.0).sin() * (y / 700.0).cos() + (x - east) * 0.01) as f32
            })
            .collect();
        // GDAL's exact statistics, as `gdal_translate -stats` writes them: what the plan Job
        // takes the height range from.
        let (min, max) = data.iter().fold((f32::INFINITY, f32::NEG_INFINITY), |(a, b), &v| (a.min(v), b.max(v)));
        let stats = format!(
            r#"<GDALMetadata><Item name="STATISTICS_MAXIMUM" sample="0">{max}</Item><Item name="STATISTICS_MINIMUM" sample="0">{min}</Item></GDALMetadata>"#
        );
        image.encoder().write_tag(Tag::Unknown(42112), &*stats).unwrap();
        image.write_data(&data).unwrap();
    }
}

/// Bytes on disk (blocks: a sparse file's holes take none) of the files in `dir` whose
/// names start with `prefix`, and their lengths.
fn on_disk(dir: &Path, prefix: &str) -> (u64, u64) {
    std::fs::read_dir(dir)
        .unwrap()
        .map(|e| e.unwrap())
        .filter(|e| e.file_name().to_string_lossy().starts_with(prefix))
        .map(|e| {
            let m = e.metadata().unwrap();
            (std::os::unix::fs::MetadataExt::blocks(&m) * 512, m.len())
        })
        .fold((0, 0), |(a, b), (c, d)| (a + c, b + d))
}

/// An S3 API server on loopback (PyPI `moto[server]`'s `moto_server`), stopped on drop.
struct ObjectStore {
    _child: Process,
    port: u16,
}

impl ObjectStore {
    /// Started, or None (saying why) where `moto_server` or `rclone` is missing; in CI
    /// their absence fails (scripts/test.sh installs them).
    fn start() -> Option<Self> {
        let missing: Vec<&str> = ["moto_server", "rclone"]
            .into_iter()
            .filter(|tool| {
                Command::new(tool).arg("--help").stdout(Stdio::null()).stderr(Stdio::null()).status().is_err()
            })
            .collect();
        if !missing.is_empty() {
            assert!(std::env::var_os("CI").is_none(), "{missing:?} not installed (scripts/test.sh installs them)");
            eprintln!("\n*** SKIPPING: {missing:?} not installed (rclone: apt; moto[server]: PyPI) ***\n");
            return None;
        }
        let port = std::net::TcpListener::bind("127.0.0.1:0").unwrap().local_addr().unwrap().port();
        let child = Command::new("moto_server")
            .args(["-H", "127.0.0.1", "-p", &port.to_string()])
            .stdout(Stdio::null())
            .stderr(Stdio::null())
            .spawn()
            .unwrap();
        let store = Self { _child: Process(child), port };
        terrastream_testkit::browser::wait_for_port(port, "moto_server");
        Some(store)
    }
}

/// The Jobs of `deploy/k8s/tile-job.yaml` run here as their pods would run them, every
/// container's exact command line in order, against real object storage (an S3 API server
/// on loopback, rclone with the environment the Job sets, pointed at it): the plan Job's
/// pod, then the tile Job's N indexed pods (`$(JOB_COMPLETION_INDEX)` set as Kubernetes
/// sets it; each pod's `/work` a folder of its own, its `/.cache` rclone's cache), then the
/// merge Job's. What it publishes to the bucket (a manifest, the coarse archive, the
/// shards) verifies, the shards merged into one file are the archive a single `tile` run
/// over the same inputs writes, byte for byte, and no tile pod fetched every input. (The plan
/// pod fetches each input's first MiB, here the whole of each; `tests/cli.rs` plans from
/// 16 KiB heads of COGs.)
#[test]
fn the_sharded_tile_jobs_run_against_object_storage_and_make_the_single_runs_archive() {
    let Some(store) = ObjectStore::start() else { return };
    let docs = yaml_docs(&deploy("k8s/tile-job.yaml"));
    let job =
        |name: &str| docs.iter().find(|d| d["metadata"]["name"] == name).unwrap_or_else(|| panic!("no Job {name}"));
    let (plan_job, tile_job, merge_job) = (job("terrastream-plan"), job("terrastream-tile"), job("terrastream-merge"));
    assert_eq!(tile_job["spec"]["completionMode"], "Indexed");
    let n = tile_job["spec"]["completions"].as_u64().unwrap();
    assert_eq!(tile_job["spec"]["parallelism"].as_u64(), Some(n), "all shards at once");

    let dir = tempfile::tempdir().unwrap();
    let work = dir.path();
    // DEM tiles, two across (overlapping) and four down, and images over them two down, in
    // UTM 33N: tall enough for five rows of 256-sample tiles, so that most of the N shards
    // hold a band, and each band reads some of the files only.
    let inputs = work.join("inputs");
    for d in ["elevation", "texture"] {
        std::fs::create_dir_all(inputs.join(d)).unwrap();
    }
    for row in 0..4u32 {
        let north = 5_100_000.0 - f64::from(row) * 275.0 * 20.0;
        for (name, w, east) in [("a", 150, 500_000.0), ("b", 140, 502_800.0)] {
            let path = inputs.join(format!("elevation/{name}{row}.tif"));
            utm_geotiff(&path, (w, 275), (east, north), 20.0, false);
        }
    }
    for row in 0..2u32 {
        let north = 5_100_000.0 - f64::from(row) * 550.0 * 20.0;
        utm_geotiff(&inputs.join(format!("texture/ortho{row}.tif")), (290, 550), (500_000.0, north), 20.0, true);
    }
    let bucket_bytes: u64 = ["elevation", "texture"]
        .iter()
        .flat_map(|d| std::fs::read_dir(inputs.join(d)).unwrap())
        .map(|e| e.unwrap().metadata().unwrap().len())
        .sum();

    // rclone as the Job's containers run it: their environment, the credentials and the
    // endpoint a cluster's service account and region would give.
    let rclone_env: Vec<(String, String)> = plan_job["spec"]["template"]["spec"]["initContainers"][0]["env"]
        .as_array()
        .unwrap()
        .iter()
        .map(|e| (e["name"].as_str().unwrap().to_owned(), e["value"].as_str().unwrap().to_owned()))
        .chain([
            ("RCLONE_CONFIG_REMOTE_ENDPOINT".to_owned(), format!("http://127.0.0.1:{}", store.port)),
            // A loopback endpoint has no bucket host names: path-style requests, which
            // rclone makes for any provider but AWS (the Job's, whose endpoint has them).
            ("RCLONE_CONFIG_REMOTE_PROVIDER".to_owned(), "Other".to_owned()),
            ("RCLONE_CONFIG_REMOTE_FORCE_PATH_STYLE".to_owned(), "true".to_owned()),
            ("RCLONE_RETRIES".to_owned(), "1".to_owned()),
            ("AWS_ACCESS_KEY_ID".to_owned(), "test".to_owned()),
            ("AWS_SECRET_ACCESS_KEY".to_owned(), "test".to_owned()),
            ("AWS_REGION".to_owned(), "us-east-1".to_owned()),
            ("RCLONE_CONFIG".to_owned(), work.join("no-rclone.conf").to_str().unwrap().to_owned()),
        ])
        .collect();
    let rclone = |args: &[&str]| {
        let out = Command::new("rclone")
            .args(args)
            .envs(rclone_env.iter().cloned())
            .env_remove("AWS_CA_BUNDLE")
            .output()
            .unwrap();
        assert!(out.status.success(), "rclone {args:?}: {}", String::from_utf8_lossy(&out.stderr));
    };
    rclone(&["copy", inputs.to_str().unwrap(), "remote:terrain-inputs/current"]);

    // A pod: its init containers, then its containers, each to completion (an upload's
    // only dependency is the last init container's output).
    let pod = |job: &serde_json::Value, index: u64, root: &Path| {
        std::fs::create_dir_all(root.join(".cache")).unwrap();
        let spec = &job["spec"]["template"]["spec"];
        let containers =
            spec["initContainers"].as_array().into_iter().flatten().chain(spec["containers"].as_array().unwrap());
        for c in containers {
            let expand = |a: &str| {
                a.replace("$(JOB_COMPLETION_INDEX)", &index.to_string()).replace("/work", root.to_str().unwrap())
            };
            let args: Vec<String> = c["args"].as_array().unwrap().iter().map(|a| expand(a.as_str().unwrap())).collect();
            let image = c["image"].as_str().unwrap();
            let program = match c["command"].as_array() {
                Some(command) => command.iter().map(|a| a.as_str().unwrap().to_owned()).collect::<Vec<_>>(),
                None if image.starts_with("rclone/") => vec!["rclone".to_owned()],
                None => vec![env!("CARGO_BIN_EXE_terrastream").to_owned(), "-q".to_owned()],
            };
            let out = Command::new(&program[0])
                .args(&program[1..])
                .args(&args)
                .envs(rclone_env.iter().cloned())
                .env_remove("AWS_CA_BUNDLE")
                .env("XDG_CACHE_HOME", root.join(".cache"))
                .output()
                .unwrap();
            let name = c["name"].as_str().unwrap();
            assert!(
                out.status.success(),
                "{} pod {index}, container {name}: {}{}",
                job["metadata"]["name"],
                String::from_utf8_lossy(&out.stdout),
                String::from_utf8_lossy(&out.stderr)
            );
        }
    };
    let in_bytes = |root: &Path| -> u64 {
        ["in/elevation", "in/texture"]
            .iter()
            .filter_map(|d| std::fs::read_dir(root.join(d)).ok())
            .flatten()
            .map(|e| {
                let e = e.unwrap();
                // Blocks on disk: a sparse copy's hole takes none.
                std::os::unix::fs::MetadataExt::blocks(&e.metadata().unwrap()) * 512
            })
            .sum()
    };
    let planner = work.join("plan-pod");
    pod(plan_job, 0, &planner);
    let plan_bytes = in_bytes(&planner);
    let mut fetched = vec![];
    for i in 0..n {
        let root = work.join(format!("tile-pod-{i}"));
        pod(tile_job, i, &root);
        fetched.push(in_bytes(&root));
    }
    let merger = work.join("merge-pod");
    pod(merge_job, 0, &merger);
    let shard_bytes: u64 =
        (0..n).map(|i| std::fs::metadata(work.join(format!("tile-pod-{i}/out/shard-{i}.tspack"))).unwrap().len()).sum();
    let (tops, _) = on_disk(&merger.join("shards"), "shard-");
    eprintln!(
        "on disk: plan pod {plan_bytes} bytes, tile pods {fetched:?}, of {bucket_bytes} in the bucket; \
         merge pod {tops} of the shards' {shard_bytes}"
    );
    assert!(fetched.iter().all(|&b| b < bucket_bytes), "a pod fetched every input: {fetched:?} of {bucket_bytes}");
    // (Here the split LOD is the shards' only one, so their tops are the whole of them;
    // tests/cli.rs publishes from the tops of shards with more.)
    assert!(tops > 0);
    // What the object-storage deployment serves: the manifest, the coarse archive and the
    // shards, together.
    let served = work.join("served");
    rclone(&["copy", "remote:terrain-archives", served.to_str().unwrap()]);
    let manifest = served.join("terrain.json");
    let out = Command::new(env!("CARGO_BIN_EXE_terrastream")).arg("verify").arg(&manifest).output().unwrap();
    let said = format!("{}{}", String::from_utf8_lossy(&out.stdout), String::from_utf8_lossy(&out.stderr));
    // The coarse archive and every shard that holds tiles.
    assert!(out.status.success() && said.contains("OK — ") && said.contains("where the manifest routes it"), "{said}");
    // One file, for those who want one: the shards merged whole.
    let published = work.join("published.tspack");
    let shards: Vec<PathBuf> = (0..n).map(|i| served.join(format!("shard-{i}.tspack"))).collect();
    let status = Command::new(env!("CARGO_BIN_EXE_terrastream"))
        .args(["-q", "merge"])
        .args(&shards)
        .arg("-o")
        .arg(&published)
        .status()
        .unwrap();
    assert!(status.success());

    // One run over the same inputs: the tile Job's command line, the shard, plan and
    // height-range options left out (it finds the range itself).
    let tile_args: Vec<String> = tile_job["spec"]["template"]["spec"]["initContainers"]
        .as_array()
        .unwrap()
        .iter()
        .find(|c| c["name"] == "tile")
        .unwrap()["args"]
        .as_array()
        .unwrap()
        .iter()
        .map(|a| a.as_str().unwrap().replace("/work/in", inputs.to_str().unwrap()))
        .collect();
    let mut single = tile_args;
    for option in ["--shard", "--shard-plan", "--height-range"] {
        let at = single.iter().position(|a| a == option).unwrap_or_else(|| panic!("the shards take {option}"));
        single.drain(at..at + 2);
    }
    let out = single.iter().position(|a| a == "-o").unwrap();
    single[out + 1] = work.join("single.tspack").to_str().unwrap().to_owned();
    let status =
        Command::new(env!("CARGO_BIN_EXE_terrastream")).arg("-q").args(&single).stdout(Stdio::null()).status().unwrap();
    assert!(status.success(), "single run {single:?}");
    let (a, b) = (std::fs::read(work.join("single.tspack")).unwrap(), std::fs::read(&published).unwrap());
    assert!(a.len() > 10_000, "a real archive");
    assert!(a == b, "the merged shards ({} bytes) differ from the single run ({} bytes)", b.len(), a.len());
}
