//! Binding and serving: HTTP/1.1 and HTTP/2 (h2c) on one port, a cap on connections,
//! header limits, graceful shutdown that lets requests in flight finish, and the
//! hot-reload loop.
//!
//! [`serve_workers`] is what `terrastream serve` runs: one thread per core, each with its
//! own single-threaded runtime and its own listening socket on the same port
//! (`SO_REUSEPORT`), as nginx runs one worker process per core. A connection lives on one
//! thread from accept to close: no work stealing, no wake-ups across threads, no shared
//! run queue. [`serve`] runs the same accept loop on whatever runtime calls it (tests,
//! embedding).
//!
//! Which thread gets a connection: on Linux, socket *i* asks for the connections whose
//! handshake the kernel processes on CPU *i* (`SO_INCOMING_CPU`), so a connection is
//! served where its packets arrive — on a network, the CPU of the card's receive queue;
//! on one machine, the CPU of the client thread that connected. The connections of one
//! client thread then stay together on one serving thread, and the scheduler can keep the
//! pair on one core; spread by a hash instead, every client thread talks to every serving
//! thread, and under load each core's pair keeps feeding the other core's, which is where
//! the latency tail came from (`scripts/bench-server.sh`: p99 about 4.5 ms against 0.9 ms
//! with this, at 64 connections on 2 cores). The kernel's choice alone could put every
//! connection on one thread (a card with one receive queue, clients that all connected
//! from one CPU): a thread that serves [`Connections::SLACK`] more connections than the
//! least busy one hands each new connection to it, unless that thread has connections
//! waiting in its own accept queue.

use std::future::Future;
use std::net::SocketAddr;
use std::sync::Arc;
use std::time::Duration;

use axum::Router;
use hyper_util::rt::{TokioExecutor, TokioIo, TokioTimer};
use hyper_util::server::conn::auto::Builder;
use hyper_util::server::graceful::GracefulShutdown;
use hyper_util::service::TowerToHyperService;
use tokio::net::{TcpListener, TcpSocket, TcpStream};
use tokio::sync::{OwnedSemaphorePermit, Semaphore, mpsc, watch};

use crate::app::{AppState, service};
use crate::edge::Edge;
use crate::h1::{self, Rewind};
use crate::metrics::{Connections, Seat};
use crate::sendfile::Stream;

/// Serves `state` on `listener` until `shutdown` resolves, then stops accepting and waits up
/// to the configured grace period for requests in flight.
///
/// # Errors
/// Only if the listener itself fails, or the TLS settings are wrong.
pub async fn serve(listener: TcpListener, state: AppState, shutdown: impl Future<Output = ()>) -> std::io::Result<()> {
    let shared = Shared::new(&state)?;
    let connections = Arc::new(Connections::new(1));
    state.metrics.watch_connections(Arc::clone(&connections));
    let place = Place { thread: 0, connections, inboxes: Arc::new([]), inbox: None, listeners: Arc::new([]) };
    let reload = tokio::spawn(reload_loop(state));
    let result = accept_loop(listener, shared, place, shutdown).await;
    reload.abort();
    result
}

/// Serves `state` on `workers` threads (0: one per core), each accepting on its own socket
/// bound to `addr`, until `shutdown` resolves; then every worker stops accepting and waits
/// up to the grace period for its requests in flight. `bound` is told the address once
/// every socket is bound (the port, when `addr` asked for port 0). Blocks until all workers
/// are done; `shutdown` and the hot-reload loop run on the calling thread.
///
/// # Errors
/// Binding, or a listener failing, or wrong TLS settings.
pub fn serve_workers(
    addr: SocketAddr,
    workers: usize,
    state: AppState,
    shutdown: impl Future<Output = ()>,
    bound: impl FnOnce(SocketAddr),
) -> std::io::Result<()> {
    let workers = if workers == 0 { std::thread::available_parallelism().map_or(1, usize::from) } else { workers };
    let shared = Shared::new(&state)?;
    let (sockets, local) = bind_sockets(addr, workers)?;
    let connections = Arc::new(Connections::new(sockets.len()));
    state.metrics.watch_connections(Arc::clone(&connections));
    let (inboxes, mut receivers): (Vec<_>, Vec<_>) = sockets.iter().map(|_| mpsc::unbounded_channel()).unzip();
    let inboxes: Arc<[Inbox]> = inboxes.into();
    let listeners = sockets.iter().map(Probe::new).collect::<std::io::Result<Arc<[_]>>>()?;
    let (stop, stopped) = watch::channel(false);
    let (listening, listened) = std::sync::mpsc::channel::<std::io::Result<()>>();
    let threads = sockets
        .into_iter()
        .zip(receivers.drain(..))
        .enumerate()
        .map(|(i, (socket, inbox))| {
            let (shared, mut stopped, listening) = (shared.clone(), stopped.clone(), listening.clone());
            let place = Place {
                thread: i,
                connections: Arc::clone(&connections),
                inboxes: Arc::clone(&inboxes),
                inbox: Some(inbox),
                listeners: Arc::clone(&listeners),
            };
            std::thread::Builder::new().name(format!("serve-{i}")).spawn(move || {
                let runtime = tokio::runtime::Builder::new_current_thread().enable_all().build()?;
                runtime.block_on(async move {
                    let listener = match socket.listen(1024) {
                        Ok(l) => l,
                        Err(err) => {
                            // Reported once, through the channel: `serve_workers` returns it.
                            let _ = listening.send(Err(err));
                            return Ok(());
                        }
                    };
                    let _ = listening.send(Ok(()));
                    accept_loop(listener, shared, place, async move {
                        let _ = stopped.wait_for(|stop| *stop).await;
                    })
                    .await
                })
            })
        })
        .collect::<std::io::Result<Vec<_>>>()?;
    drop(listening);
    // Told once every socket listens: a client may connect at once, and a second server on
    // this port is refused from then on.
    let failed = (0..threads.len()).find_map(|_| match listened.recv() {
        Ok(Ok(())) => None,
        Ok(Err(err)) => Some(err),
        Err(_) => Some(std::io::Error::other("a server thread ended before listening")),
    });
    drop(stopped);
    if failed.is_none() {
        bound(local);
        let control = tokio::runtime::Builder::new_current_thread().enable_all().build()?;
        control.block_on(async {
            let reload = tokio::spawn(reload_loop(state));
            shutdown.await;
            reload.abort();
        });
    }
    let _ = stop.send(true);
    let mut result = failed.map_or(Ok(()), Err);
    for thread in threads {
        match thread.join() {
            Ok(Ok(())) => {}
            Ok(Err(err)) => result = Err(err),
            Err(_) => result = Err(std::io::Error::other("a server thread panicked")),
        }
    }
    result
}

/// `workers` sockets bound to one address. With `SO_REUSEPORT` each gets its own accept
/// queue and the kernel balances connections over them; elsewhere they would all share the
/// first socket's queue, so only one is made.
///
/// On Linux, socket *i* prefers the connections the kernel receives on the *i*-th CPU this
/// process may run on (see the module's documentation).
///
/// `SO_REUSEPORT` would also let a second server started on the same port silently take
/// half of its connections: the address is first bound without it, which fails if anything
/// listens there (and picks the port when `addr` asks for port 0).
fn bind_sockets(addr: SocketAddr, workers: usize) -> std::io::Result<(Vec<TcpSocket>, SocketAddr)> {
    let named = |e: std::io::Error| std::io::Error::new(e.kind(), format!("binding {addr}: {e}"));
    let new_socket = |at: SocketAddr| if at.is_ipv4() { TcpSocket::new_v4() } else { TcpSocket::new_v6() };
    let probe = new_socket(addr)?;
    probe.set_reuseaddr(true)?;
    probe.bind(addr).map_err(named)?;
    let local = probe.local_addr()?;
    drop(probe);
    let reuse_port = cfg!(all(unix, not(any(target_os = "solaris", target_os = "illumos", target_os = "cygwin"))));
    let count = if reuse_port { workers.max(1) } else { 1 };
    let sockets = (0..count)
        .map(|_| {
            let s = new_socket(local)?;
            s.set_reuseaddr(true)?;
            #[cfg(all(unix, not(any(target_os = "solaris", target_os = "illumos", target_os = "cygwin"))))]
            s.set_reuseport(true)?;
            Ok(s)
        })
        .collect::<std::io::Result<Vec<_>>>()
        .map_err(named)?;
    #[cfg(target_os = "linux")]
    if count > 1 {
        prefer_cpus(&sockets);
    }
    for s in &sockets {
        s.bind(local).map_err(named)?;
    }
    Ok((sockets, local))
}

/// Socket *i* asks for the connections received on the *i*-th CPU this process may run on
/// (`SO_INCOMING_CPU`). A preference only: without it (older kernels, an unknown CPU set)
/// the kernel spreads connections by hash.
#[cfg(target_os = "linux")]
fn prefer_cpus(sockets: &[TcpSocket]) {
    let Ok(set) = rustix::thread::sched_getaffinity(None) else { return };
    let cpus = (0..rustix::thread::CpuSet::MAX_CPU).filter(|&c| set.is_set(c)).filter_map(|c| u32::try_from(c).ok());
    for (socket, cpu) in sockets.iter().zip(cpus.cycle()) {
        if let Err(err) = rustix::net::sockopt::set_socket_incoming_cpu(socket, cpu) {
            tracing::debug!("SO_INCOMING_CPU: {err}");
        }
    }
}

/// What a connection holds until it closes: its slot under the connection cap and its
/// place in its thread's count.
struct Held {
    _permit: OwnedSemaphorePermit,
    _seat: Seat,
}

/// A connection one thread accepted and hands to another.
struct Handed {
    stream: std::net::TcpStream,
    peer: SocketAddr,
    held: Held,
}

/// Where a thread sends the connections it hands to another.
type Inbox = mpsc::UnboundedSender<Handed>;

/// An accept loop's thread among the others: its number, every thread's connections, the
/// way connections are handed between threads, and every thread's listening socket (to
/// see whether connections wait there).
struct Place {
    thread: usize,
    connections: Arc<Connections>,
    inboxes: Arc<[Inbox]>,
    inbox: Option<mpsc::UnboundedReceiver<Handed>>,
    listeners: Arc<[Probe]>,
}

/// A listening socket, seen from another thread: whether connections wait in its accept
/// queue (Linux; elsewhere never).
struct Probe(#[cfg(target_os = "linux")] std::os::fd::OwnedFd);

impl Probe {
    fn new(socket: &TcpSocket) -> std::io::Result<Self> {
        #[cfg(target_os = "linux")]
        return Ok(Self(std::os::fd::AsFd::as_fd(socket).try_clone_to_owned()?));
        #[cfg(not(target_os = "linux"))]
        {
            let _ = socket;
            Ok(Self())
        }
    }

    fn waiting(&self) -> bool {
        #[cfg(target_os = "linux")]
        {
            use rustix::event::{PollFd, PollFlags, Timespec, poll};
            let mut fds = [PollFd::new(&self.0, PollFlags::IN)];
            matches!(poll(&mut fds, Some(&Timespec { tv_sec: 0, tv_nsec: 0 })), Ok(n) if n > 0)
        }
        #[cfg(not(target_os = "linux"))]
        false
    }
}

/// What every accept loop shares: the router, the HTTP settings, the connection cap, TLS.
#[derive(Clone)]
struct Shared {
    service: Edge<Router>,
    lean: Option<h1::Limits>,
    builder: Builder<TokioExecutor>,
    slots: Arc<Semaphore>,
    tls: Option<tokio_rustls::TlsAcceptor>,
    request_timeout: Duration,
    grace: Duration,
}

impl Shared {
    fn new(state: &AppState) -> std::io::Result<Self> {
        let config = &state.config;
        let tls = match (&config.tls_cert, &config.tls_key) {
            (Some(cert), Some(key)) => Some(tls_acceptor(cert, key)?),
            (None, None) => None,
            _ => return Err(std::io::Error::other("TLS needs both a certificate and a key")),
        };
        let mut builder = Builder::new(TokioExecutor::new());
        builder
            .http1()
            .timer(TokioTimer::new())
            .header_read_timeout(config.request_timeout())
            .max_buf_size(config.max_header_bytes.max(8192))
            .keep_alive(true);
        builder
            .http2()
            .timer(TokioTimer::new())
            .max_header_list_size(u32::try_from(config.max_header_bytes).unwrap_or(u32::MAX));
        let lean = config
            .lean_http1
            .then_some(h1::Limits { timeout: config.request_timeout(), max_head: config.max_header_bytes.max(8192) });
        Ok(Self {
            service: service(state.clone()),
            lean,
            builder,
            slots: Arc::new(Semaphore::new(config.max_connections.max(1))),
            tls,
            request_timeout: config.request_timeout(),
            grace: Duration::from_secs(config.shutdown_grace_secs),
        })
    }
}

/// Accepts and serves connections on the current runtime until `shutdown` resolves, then
/// drains them for up to the grace period. Connections handed over by other threads are
/// served too.
async fn accept_loop(
    listener: TcpListener,
    shared: Shared,
    place: Place,
    shutdown: impl Future<Output = ()>,
) -> std::io::Result<()> {
    let Place { thread, connections, inboxes, mut inbox, listeners } = place;
    let graceful = GracefulShutdown::new();
    // Tells connections on the lean path to close once idle (hyper's learn it from `graceful`).
    let (closing, closed) = watch::channel(false);
    let mut shutdown = std::pin::pin!(shutdown);
    loop {
        let handed = async {
            match inbox.as_mut() {
                Some(inbox) => inbox.recv().await,
                None => std::future::pending().await,
            }
        };
        tokio::select! {
            biased;
            () = &mut shutdown => break,
            Some(handed) = handed => match TcpStream::from_std(handed.stream) {
                Ok(stream) => spawn_connection(&shared, &graceful, &closed, stream, handed.peer, handed.held),
                Err(err) => tracing::debug!(peer = %handed.peer, "handed connection lost: {err}"),
            },
            accepted = accept(&listener, &shared.slots) => {
                let (stream, peer, permit) = match accepted {
                    Ok(a) => a,
                    Err(err) => {
                        // Out of file descriptors and the like: back off instead of spinning.
                        tracing::warn!("accept failed: {err}");
                        tokio::time::sleep(Duration::from_millis(50)).await;
                        continue;
                    }
                };
                let _ = stream.set_nodelay(true);
                let seat = connections.seat(thread, |t| listeners.get(t).is_some_and(Probe::waiting));
                let to = seat.thread();
                let held = Held { _permit: permit, _seat: seat };
                if to == thread {
                    spawn_connection(&shared, &graceful, &closed, stream, peer, held);
                } else if let Ok(stream) = stream.into_std() {
                    // A thread that has stopped drops it: the server is shutting down.
                    let _ = inboxes[to].send(Handed { stream, peer, held });
                }
            }
        }
    }
    drop(listener);
    drop(inbox);
    let _ = closing.send(true);
    tracing::info!("shutting down: waiting for requests in flight");
    if tokio::time::timeout(shared.grace, graceful.shutdown()).await.is_err() {
        tracing::warn!("grace period over: closing the remaining connections");
    }
    Ok(())
}

/// The next connection, once a connection slot is free: excess clients wait in the
/// backlog.
async fn accept(
    listener: &TcpListener,
    slots: &Arc<Semaphore>,
) -> std::io::Result<(TcpStream, SocketAddr, OwnedSemaphorePermit)> {
    let permit = Arc::clone(slots).acquire_owned().await.map_err(std::io::Error::other)?;
    let (stream, peer) = listener.accept().await?;
    Ok((stream, peer, permit))
}

/// Serves one connection on the current runtime, holding its slot and seat until it closes.
fn spawn_connection(
    shared: &Shared,
    graceful: &GracefulShutdown,
    closed: &watch::Receiver<bool>,
    stream: TcpStream,
    peer: SocketAddr,
    held: Held,
) {
    let (watcher, closed) = (graceful.watcher(), closed.clone());
    let (service, builder, tls) = (shared.service.clone(), shared.builder.clone(), shared.tls.clone());
    let (lean, handshake_timeout) = (shared.lean, shared.request_timeout);
    tokio::spawn(async move {
        let result = match tls {
            None => {
                let stream = Stream::new(stream);
                // The watcher lives as long as the task: shutdown waits for the lean path too.
                let handed = match lean {
                    Some(limits) => h1::serve(stream, service.state(), closed, limits).await,
                    None => Ok(h1::Ended::Hyper(Rewind::new(bytes::Bytes::new(), stream))),
                };
                match handed {
                    Ok(h1::Ended::Hyper(io)) => {
                        let connection =
                            builder.serve_connection_with_upgrades(TokioIo::new(io), TowerToHyperService::new(service));
                        watcher.watch(connection.into_owned()).await
                    }
                    Ok(h1::Ended::Closed) => Ok(()),
                    Err(err) => Err(err.into()),
                }
            }
            Some(acceptor) => match tokio::time::timeout(handshake_timeout, acceptor.accept(stream)).await {
                Ok(Ok(tls_stream)) => {
                    let io = TokioIo::new(tls_stream);
                    let service = TowerToHyperService::new(service);
                    watcher.watch(builder.serve_connection_with_upgrades(io, service).into_owned()).await
                }
                Ok(Err(err)) => Err(err.into()),
                Err(_) => Err("TLS handshake timed out".into()),
            },
        };
        if let Err(err) = result {
            tracing::debug!(%peer, "connection ended: {err}");
        }
        drop(held);
    });
}

/// A TLS acceptor for a PEM certificate chain and key, offering h2 and http/1.1.
fn tls_acceptor(cert: &std::path::Path, key: &std::path::Path) -> std::io::Result<tokio_rustls::TlsAcceptor> {
    use rustls_pki_types::pem::PemObject;
    use rustls_pki_types::{CertificateDer, PrivateKeyDer};
    use tokio_rustls::rustls;
    let named =
        |path: &std::path::Path, e: &dyn std::fmt::Display| std::io::Error::other(format!("{}: {e}", path.display()));
    let chain = CertificateDer::pem_file_iter(cert)
        .and_then(Iterator::collect::<Result<Vec<_>, _>>)
        .map_err(|e| named(cert, &e))?;
    let key_der = PrivateKeyDer::from_pem_file(key).map_err(|e| named(key, &e))?;
    let provider = Arc::new(rustls::crypto::ring::default_provider());
    let mut tls = rustls::ServerConfig::builder_with_provider(provider)
        .with_safe_default_protocol_versions()
        .map_err(|e| named(cert, &e))?
        .with_no_client_auth()
        .with_single_cert(chain, key_der)
        .map_err(|e| named(cert, &e))?;
    tls.alpn_protocols = vec![b"h2".to_vec(), b"http/1.1".to_vec()];
    Ok(tokio_rustls::TlsAcceptor::from(Arc::new(tls)))
}

/// Rescans the served paths periodically (hot reload of replaced, added, removed archives)
/// and the keys file.
async fn reload_loop(state: AppState) {
    let mut tick = tokio::time::interval(state.config.reload_interval());
    tick.set_missed_tick_behavior(tokio::time::MissedTickBehavior::Delay);
    loop {
        tick.tick().await;
        let (catalog, access) = (Arc::clone(&state.catalog), Arc::clone(&state.access));
        match tokio::task::spawn_blocking(move || {
            access.reload();
            catalog.reload()
        })
        .await
        {
            Ok(changed) if changed > 0 => tracing::info!(changed, "archives reloaded"),
            Ok(_) => {}
            Err(err) => tracing::error!("reload task failed: {err}"),
        }
    }
}

/// Resolves on Ctrl-C or SIGTERM.
pub async fn shutdown_signal() {
    let ctrl_c = async {
        if let Err(err) = tokio::signal::ctrl_c().await {
            tracing::error!("cannot listen for Ctrl-C: {err}");
            std::future::pending::<()>().await;
        }
    };
    #[cfg(unix)]
    let terminate = async {
        match tokio::signal::unix::signal(tokio::signal::unix::SignalKind::terminate()) {
            Ok(mut s) => {
                s.recv().await;
            }
            Err(err) => {
                tracing::error!("cannot listen for SIGTERM: {err}");
                std::future::pending::<()>().await;
            }
        }
    };
    #[cfg(not(unix))]
    let terminate = std::future::pending::<()>();
    tokio::select! {
        () = ctrl_c => {},
        () = terminate => {},
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::config::ServerConfig;
    use tokio::io::{AsyncReadExt, AsyncWriteExt};

    /// A thread that accepts a connection while it serves `SLACK` more than another hands
    /// it over: the other thread answers it, and the counts follow the connection.
    #[test]
    fn a_busy_thread_hands_new_connections_to_the_least_busy_one() {
        let state = AppState::new(ServerConfig::default());
        let shared = Shared::new(&state).unwrap();
        let connections = Arc::new(Connections::new(2));
        // Thread 0 already serves SLACK connections; thread 1 none.
        let held: Vec<Seat> = (0..Connections::SLACK).map(|_| connections.seat(0, |_| false)).collect();
        assert_eq!(connections.open(), [Connections::SLACK, 0]);
        let sockets: Vec<TcpSocket> = (0..2)
            .map(|_| {
                let s = TcpSocket::new_v4().unwrap();
                s.bind(SocketAddr::from(([127, 0, 0, 1], 0))).unwrap();
                s
            })
            .collect();
        let addr = sockets[0].local_addr().unwrap();
        let listeners: Arc<[Probe]> = sockets.iter().map(Probe::new).collect::<std::io::Result<_>>().unwrap();
        let (inboxes, receivers): (Vec<_>, Vec<_>) = (0..2).map(|_| mpsc::unbounded_channel()).unzip();
        let inboxes: Arc<[Inbox]> = inboxes.into();
        let (stop, stopped) = watch::channel(false);
        let (listening, listened) = std::sync::mpsc::channel();
        let threads: Vec<_> = sockets
            .into_iter()
            .zip(receivers)
            .enumerate()
            .map(|(thread, (socket, inbox))| {
                let place = Place {
                    thread,
                    connections: Arc::clone(&connections),
                    inboxes: Arc::clone(&inboxes),
                    inbox: Some(inbox),
                    listeners: Arc::clone(&listeners),
                };
                let (shared, mut stopped, listening) = (shared.clone(), stopped.clone(), listening.clone());
                std::thread::spawn(move || {
                    let runtime = tokio::runtime::Builder::new_current_thread().enable_all().build().unwrap();
                    runtime.block_on(async move {
                        let listener = socket.listen(16).unwrap();
                        listening.send(()).unwrap();
                        accept_loop(listener, shared, place, async move {
                            let _ = stopped.wait_for(|stop| *stop).await;
                        })
                        .await
                    })
                })
            })
            .collect();
        listened.recv().unwrap();
        listened.recv().unwrap();
        let runtime = tokio::runtime::Builder::new_current_thread().enable_all().build().unwrap();
        let answer = runtime.block_on(async {
            let mut client = TcpStream::connect(addr).await.unwrap();
            client.write_all(b"GET /healthz HTTP/1.1\r\nhost: x\r\nconnection: close\r\n\r\n").await.unwrap();
            let mut answer = String::new();
            client.read_to_string(&mut answer).await.unwrap();
            answer
        });
        assert!(answer.starts_with("HTTP/1.1 200"), "{answer}");
        assert!(answer.ends_with("ok\n"), "{answer}");
        assert_eq!(connections.handed(), 1);
        // Counted on thread 1 while open, and no longer once closed.
        let _ = stop.send(true);
        for thread in threads {
            thread.join().unwrap().unwrap();
        }
        assert_eq!(connections.open(), [Connections::SLACK, 0]);
        drop(held);
        assert_eq!(connections.open(), [0, 0]);
    }
}
