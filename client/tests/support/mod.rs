//! Helpers shared by the client's integration tests.
#![allow(dead_code, clippy::unwrap_used)]

/// Serves `router` on `addr` (`"127.0.0.1:0"` for any free port) until the task is aborted.
pub async fn serve(router: axum::Router, addr: &str) -> (std::net::SocketAddr, tokio::task::JoinHandle<()>) {
    let listener = tokio::net::TcpListener::bind(addr).await.unwrap();
    let addr = listener.local_addr().unwrap();
    (addr, tokio::spawn(async move { axum::serve(listener, router).await.unwrap() }))
}
