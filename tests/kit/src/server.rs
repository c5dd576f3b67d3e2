//! The server on a loopback port, or its router alone, for tests.

use std::path::Path;

use terrastream_server::{AppState, ServerConfig, serve};
use tokio::sync::oneshot;

/// The server's state over the archives in `dir`, loaded.
pub fn state(dir: &Path) -> AppState {
    let config = ServerConfig { paths: vec![dir.to_path_buf()], ..ServerConfig::default() };
    let state = AppState::new(config);
    state.catalog.reload();
    state
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

/// Serves `router` on `addr` (`"127.0.0.1:0"` for any free port) until the task is aborted.
pub async fn serve_router(router: axum::Router, addr: &str) -> (std::net::SocketAddr, tokio::task::JoinHandle<()>) {
    let listener = tokio::net::TcpListener::bind(addr).await.unwrap();
    let addr = listener.local_addr().unwrap();
    (addr, tokio::spawn(async move { axum::serve(listener, router).await.unwrap() }))
}

/// A `terrastream serve` process on a loopback port it picked itself, killed when dropped
/// (a failed test leaves no server behind).
pub struct Spawned {
    /// The port, once every serving thread listens.
    pub port: u16,
    /// The process.
    pub child: std::process::Child,
    /// Its output, kept open: the server may still print.
    _stdout: std::io::BufReader<std::process::ChildStdout>,
}

/// Runs the `terrastream` binary `exe` as `serve ARGS --addr 127.0.0.1:0` in `dir` and
/// waits for its "listening on" line. Port 0, not a port found free first, which another
/// process may take before the server binds it; and that line, not the first connection
/// it accepts, since it comes once every serving socket listens (a connection to a socket
/// of the port's group that is bound but not listening yet is refused).
pub fn spawn_serve(exe: &Path, args: &[&str], dir: &Path) -> Spawned {
    use std::io::{BufRead, Read};
    let mut child = std::process::Command::new(exe)
        .arg("serve")
        .args(args)
        .args(["--addr", "127.0.0.1:0"])
        .current_dir(dir)
        .stdout(std::process::Stdio::piped())
        .stderr(std::process::Stdio::null())
        .spawn()
        .unwrap();
    let mut stdout = std::io::BufReader::new(child.stdout.take().unwrap());
    let line = stdout.by_ref().lines().map_while(Result::ok).find(|l| l.starts_with("listening on http://"));
    let port = line.and_then(|l| {
        let addr = l.trim_start_matches("listening on http://").split('/').next()?.to_owned();
        addr.rsplit(':').next()?.parse::<u16>().ok()
    });
    let Some(port) = port else {
        let _ = child.kill();
        panic!("terrastream serve {args:?} did not say where it listens: {:?}", child.wait());
    };
    Spawned { port, child, _stdout: stdout }
}

impl Drop for Spawned {
    fn drop(&mut self) {
        let _ = self.child.kill();
        let _ = self.child.wait();
    }
}
