//! Fixtures shared by the server tests.
#![allow(dead_code, clippy::unwrap_used, clippy::expect_used)]

use std::path::{Path, PathBuf};

use terrastream_packer::{Layer, LayerKind, Metadata, PayloadCompression, TileFormat, TileKey, Writer, WriterOptions};
use terrastream_server::{AppState, ServerConfig, serve};
use tokio::sync::oneshot;

/// A folder holding `sample.tspack` (the built-in sample) and `elev.tspack` (a zstd layer).
pub fn archives() -> (tempfile::TempDir, PathBuf) {
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("sample.tspack");
    std::fs::write(&path, terrastream_packer::sample::tiny_archive().unwrap()).unwrap();
    write_zstd_archive(&dir.path().join("elev.tspack"), 1);
    (dir, path)
}

/// A one-layer raw-u16 + zstd archive whose samples depend on `version`.
pub fn write_zstd_archive(path: &Path, version: u16) {
    let layer = Layer {
        name: "elevation".into(),
        kind: LayerKind::Elevation,
        format: TileFormat::RawU16,
        compression: PayloadCompression::Zstd,
        tile_resolution: 16,
        border: 0,
        num_x_tiles: 2,
        num_y_tiles: 2,
        num_lods: 2,
        tile_world_size: 100.0,
        elevation: None,
    };
    let meta = Metadata::new("elev", vec![layer]);
    let mut tiles: Vec<(u64, TileKey)> = [(1u8, 0u32, 0u32), (0, 0, 0), (0, 1, 0), (0, 1, 1)]
        .iter()
        .map(|&(lod, x, y)| {
            let t = TileKey::new(0, lod, x, y).unwrap();
            (Writer::order_key(&meta, t).unwrap(), t)
        })
        .collect();
    tiles.sort();
    let mut w = Writer::create(path, meta, WriterOptions::default()).unwrap();
    for (_, t) in tiles {
        w.add(t, raw_tile(t, version)).unwrap();
    }
    w.finish().unwrap();
}

/// The raw samples of a tile of [`write_zstd_archive`].
pub fn raw_tile(t: TileKey, version: u16) -> Vec<u8> {
    (0..256u16).flat_map(|i| (i + u16::from(t.lod()) * 7 + version * 1000).to_le_bytes()).collect()
}

pub fn state(dir: &Path) -> AppState {
    let config = ServerConfig { paths: vec![dir.to_path_buf()], ..ServerConfig::default() };
    let state = AppState::new(config);
    state.catalog.reload();
    state
}

/// nginx serving `root` as static files on a loopback port, stopped on drop.
pub struct Nginx {
    pub port: u16,
    child: std::process::Child,
    _dir: tempfile::TempDir,
}

impl Drop for Nginx {
    fn drop(&mut self) {
        let _ = self.child.kill();
        let _ = self.child.wait();
    }
}

/// The nginx binary, or `None` (with a loud message) when it is missing outside CI.
/// On CI a missing nginx is a failure: the test command installs it.
pub fn nginx_binary() -> Option<PathBuf> {
    for p in ["/usr/sbin/nginx", "/usr/local/sbin/nginx", "/usr/bin/nginx"] {
        if Path::new(p).exists() {
            return Some(PathBuf::from(p));
        }
    }
    assert!(std::env::var_os("CI").is_none(), "nginx is not installed (apt-get install nginx); required on CI");
    eprintln!("\n*** SKIPPING: nginx is not installed (apt-get install nginx) ***\n");
    None
}

pub fn free_port() -> u16 {
    std::net::TcpListener::bind("127.0.0.1:0").unwrap().local_addr().unwrap().port()
}

/// Starts nginx with `server_block` (inside `http {}`; `{port}` and `{root}` are filled in).
pub fn start_nginx(root: &Path, server_block: &str) -> Option<Nginx> {
    let binary = nginx_binary()?;
    let dir = tempfile::tempdir().unwrap();
    let port = free_port();
    let d = dir.path().display();
    let server = server_block.replace("{port}", &port.to_string()).replace("{root}", &root.display().to_string());
    let conf = format!(
        "daemon off;\nmaster_process off;\nworker_processes 1;\npid {d}/nginx.pid;\nerror_log {d}/error.log warn;\n\
         events {{ worker_connections 512; }}\nhttp {{\n  access_log off;\n  client_body_temp_path {d}/body;\n  \
         proxy_temp_path {d}/proxy;\n  fastcgi_temp_path {d}/fcgi;\n  uwsgi_temp_path {d}/uwsgi;\n  scgi_temp_path {d}/scgi;\n  \
         types {{ application/octet-stream tspack; }}\n  default_type application/octet-stream;\n{server}\n}}\n"
    );
    std::fs::write(dir.path().join("nginx.conf"), conf).unwrap();
    let child = std::process::Command::new(binary)
        .arg("-p")
        .arg(dir.path())
        .arg("-c")
        .arg(dir.path().join("nginx.conf"))
        .arg("-e")
        .arg(dir.path().join("error.log"))
        .stdout(std::process::Stdio::null())
        .spawn()
        .unwrap();
    let nginx = Nginx { port, child, _dir: dir };
    for _ in 0..100 {
        if std::net::TcpStream::connect(("127.0.0.1", port)).is_ok() {
            return Some(nginx);
        }
        std::thread::sleep(std::time::Duration::from_millis(50));
    }
    panic!("nginx did not start: {}", std::fs::read_to_string(nginx._dir.path().join("error.log")).unwrap_or_default());
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

/// A server on a loopback port, serving `dir`, until [`Running::stop`].
pub struct Running {
    pub addr: std::net::SocketAddr,
    stop: Option<oneshot::Sender<()>>,
    task: tokio::task::JoinHandle<std::io::Result<()>>,
    pub state: AppState,
}

/// Starts [`serve`] on a free loopback port with `dir` and the settings `tweak` makes.
pub async fn start(dir: &Path, tweak: impl FnOnce(&mut ServerConfig)) -> Running {
    let mut config = ServerConfig { paths: vec![dir.to_path_buf()], reload_interval_ms: 50, ..ServerConfig::default() };
    tweak(&mut config);
    let state = AppState::new(config);
    state.catalog.reload();
    let listener = tokio::net::TcpListener::bind("127.0.0.1:0").await.unwrap();
    let addr = listener.local_addr().unwrap();
    let (stop, stopped) = oneshot::channel::<()>();
    let task = tokio::spawn(serve(listener, state.clone(), async {
        let _ = stopped.await;
    }));
    Running { addr, stop: Some(stop), task, state }
}

impl Running {
    /// Shuts the server down gracefully and waits for it.
    pub async fn stop(mut self) {
        let _ = self.stop.take().unwrap().send(());
        self.task.await.unwrap().unwrap();
    }
}
