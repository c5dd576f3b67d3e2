//! A network link emulated in user space, in front of a server on a loopback port: a delay
//! each way, one token bucket for the link's rate shared by every connection, and loss
//! emulated as the stall a TCP retransmission costs. The kernel here has no netem; this
//! proxy needs none, binds loopback only and touches no other address.

use std::net::SocketAddr;
use std::sync::{Arc, Mutex, PoisonError};
use std::time::Duration;

use tokio::io::{AsyncReadExt, AsyncWriteExt};
use tokio::net::{TcpListener, TcpStream};
use tokio::sync::mpsc;
use tokio::time::Instant;

/// The link to emulate.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Link {
    /// Round-trip time (half each way).
    pub rtt: Duration,
    /// Bits per second, both directions sharing one bucket.
    pub rate: u64,
    /// Share of segments lost: each costs a stall of one retransmission timeout.
    pub loss: f64,
}

impl Link {
    /// (a) 20 ms RTT, 100 Mbit/s.
    pub const NEAR: Self = Self { rtt: Duration::from_millis(20), rate: 100_000_000, loss: 0.0 };
    /// (b) 80 ms RTT, 20 Mbit/s.
    pub const FAR: Self = Self { rtt: Duration::from_millis(80), rate: 20_000_000, loss: 0.0 };
    /// (c) 150 ms RTT, 5 Mbit/s, 1 % loss.
    pub const POOR: Self = Self { rtt: Duration::from_millis(150), rate: 5_000_000, loss: 0.01 };

    /// The stall of a lost segment: TCP's minimum retransmission timeout or two RTTs.
    fn stall(&self) -> Duration {
        (self.rtt * 2).max(Duration::from_millis(200))
    }
}

/// Bytes a segment carries (one read), as TCP would send them.
const SEGMENT: usize = 16 * 1024;

/// The link's shared state: when its bucket is next free, and a small random source.
struct Wire {
    link: Link,
    free_at: Mutex<Instant>,
    seed: Mutex<u64>,
}

impl Wire {
    /// When `bytes` sent now finish leaving the shared bucket.
    fn departure(&self, bytes: usize) -> Instant {
        let mut free = self.free_at.lock().unwrap_or_else(PoisonError::into_inner);
        let start = (*free).max(Instant::now());
        #[expect(clippy::cast_precision_loss, reason = "a rate in bits per second")]
        let time = Duration::from_secs_f64(bytes as f64 * 8.0 / self.link.rate.max(1) as f64);
        *free = start + time;
        *free
    }

    /// Is the next segment lost? (xorshift: reproducible, no dependency)
    fn lost(&self) -> bool {
        if self.link.loss <= 0.0 {
            return false;
        }
        let mut s = self.seed.lock().unwrap_or_else(PoisonError::into_inner);
        *s ^= *s << 13;
        *s ^= *s >> 7;
        *s ^= *s << 17;
        #[expect(clippy::cast_precision_loss, reason = "a uniform draw in [0, 1)")]
        let draw = (*s >> 11) as f64 / (1u64 << 53) as f64;
        draw < self.link.loss
    }
}

/// The proxy: connect to `addr` instead of the upstream server. Stops when dropped.
pub struct Shaper {
    /// Where clients connect.
    pub addr: SocketAddr,
    task: tokio::task::JoinHandle<()>,
}

impl Drop for Shaper {
    fn drop(&mut self) {
        self.task.abort();
    }
}

impl Shaper {
    /// Starts a proxy for `upstream` on a free loopback port, on the current runtime.
    ///
    /// # Errors
    /// The loopback listener cannot be bound.
    pub async fn start(upstream: SocketAddr, link: Link) -> std::io::Result<Self> {
        let listener = TcpListener::bind("127.0.0.1:0").await?;
        let addr = listener.local_addr()?;
        let wire =
            Arc::new(Wire { link, free_at: Mutex::new(Instant::now()), seed: Mutex::new(0x9e37_79b9_7f4a_7c15) });
        let task = tokio::spawn(async move {
            while let Ok((client, _)) = listener.accept().await {
                let wire = wire.clone();
                tokio::spawn(async move {
                    let Ok(server) = TcpStream::connect(upstream).await else { return };
                    let _ = client.set_nodelay(true);
                    let _ = server.set_nodelay(true);
                    let (client_read, client_write) = client.into_split();
                    let (server_read, server_write) = server.into_split();
                    let up = tokio::spawn(pump(client_read, server_write, wire.clone()));
                    let down = tokio::spawn(pump(server_read, client_write, wire));
                    let _ = tokio::join!(up, down);
                });
            }
        });
        Ok(Self { addr, task })
    }
}

/// Carries one direction of a connection over the link: each segment leaves when the
/// shared bucket lets it, arrives half an RTT later (plus a stall if lost), in order.
async fn pump(mut from: tokio::net::tcp::OwnedReadHalf, mut to: tokio::net::tcp::OwnedWriteHalf, wire: Arc<Wire>) {
    let (send, mut arrivals) = mpsc::unbounded_channel::<(Instant, Vec<u8>)>();
    let writer = tokio::spawn(async move {
        while let Some((at, bytes)) = arrivals.recv().await {
            tokio::time::sleep_until(at).await;
            if to.write_all(&bytes).await.is_err() {
                return;
            }
        }
        let _ = to.shutdown().await;
    });
    let mut buf = vec![0u8; SEGMENT];
    let mut last = Instant::now();
    loop {
        let n = match from.read(&mut buf).await {
            Ok(0) | Err(_) => break,
            Ok(n) => n,
        };
        let mut at = wire.departure(n) + wire.link.rtt / 2;
        if wire.lost() {
            at += wire.link.stall();
        }
        // In order, as TCP delivers: a stalled segment holds back those behind it.
        at = at.max(last);
        last = at;
        if send.send((at, buf[..n].to_vec())).is_err() {
            break;
        }
    }
    drop(send);
    let _ = writer.await;
}
