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
