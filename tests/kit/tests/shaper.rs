//! The emulated link delivers every byte, in order, and never faster than its delay and
//! rate allow (lower bounds only: how much slower depends on the machine).
#![allow(clippy::unwrap_used, missing_docs)]

use std::time::{Duration, Instant};

use terrastream_testkit::shaper::{Link, Shaper};
use tokio::io::{AsyncReadExt, AsyncWriteExt};
use tokio::net::TcpListener;

/// An echo server on a loopback port.
async fn echo() -> std::net::SocketAddr {
    let listener = TcpListener::bind("127.0.0.1:0").await.unwrap();
    let addr = listener.local_addr().unwrap();
    tokio::spawn(async move {
        while let Ok((mut s, _)) = listener.accept().await {
            tokio::spawn(async move {
                let (mut r, mut w) = s.split();
                let _ = tokio::io::copy(&mut r, &mut w).await;
            });
        }
    });
    addr
}

async fn round_trip(addr: std::net::SocketAddr, data: &[u8]) -> (Vec<u8>, Duration) {
    let started = Instant::now();
    let mut s = tokio::net::TcpStream::connect(addr).await.unwrap();
    let (mut r, mut w) = s.split();
    let (_, back) = tokio::join!(
        async {
            w.write_all(data).await.unwrap();
            w.shutdown().await.unwrap();
        },
        async {
            let mut back = Vec::new();
            r.read_to_end(&mut back).await.unwrap();
            back
        }
    );
    (back, started.elapsed())
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_link_delays_and_limits_but_delivers_everything_in_order() {
    let upstream = echo().await;
    let data: Vec<u8> = (0..400_000u32).map(|i| (i.wrapping_mul(2_654_435_761) >> 24) as u8).collect();
    let link = Link { rtt: Duration::from_millis(60), rate: 8_000_000, loss: 0.0 };
    let shaper = Shaper::start(upstream, link).await.unwrap();
    let (back, took) = round_trip(shaper.addr, &data).await;
    assert_eq!(back.len(), data.len());
    assert!(back == data, "bytes changed or reordered on the link");
    // Both directions share the 8 Mbit/s bucket: 2 x 400 kB take at least 0.8 s to leave
    // it, and the last segment half an RTT to arrive.
    let floor = Duration::from_secs_f64(2.0 * data.len() as f64 * 8.0 / 8e6) + link.rtt / 2;
    assert!(took >= floor, "{took:?} through the link, faster than its floor {floor:?}");

    // A small exchange costs at least one round trip; loss adds stalls, never loses data.
    let lossy =
        Shaper::start(upstream, Link { rtt: Duration::from_millis(40), rate: 100_000_000, loss: 0.5 }).await.unwrap();
    let (back, took) = round_trip(lossy.addr, &data).await;
    assert!(back == data, "a lossy link lost or reordered bytes");
    assert!(took >= Duration::from_millis(240), "{took:?}: a 50 % lossy link stalled less than one timeout");
}
