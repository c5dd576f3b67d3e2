//! `terrastream health`.

use std::process::ExitCode;

use anyhow::{Context, Result};
use clap::Args;

#[derive(Debug, Args)]
pub struct HealthArgs {
    /// The URL to ask (plain http).
    #[arg(default_value = "http://127.0.0.1:8080/healthz")]
    url: String,
    /// Seconds to wait for the answer.
    #[arg(long, default_value_t = 3)]
    timeout: u64,
}

pub fn run(args: HealthArgs) -> Result<ExitCode> {
    health(&args.url, std::time::Duration::from_secs(args.timeout))
}

/// `GET url` over plain HTTP/1.1 with std only; success on a 200 status line.
fn health(url: &str, timeout: std::time::Duration) -> Result<ExitCode> {
    use std::io::{Read, Write};
    let rest = url.strip_prefix("http://").with_context(|| format!("{url}: only http:// URLs"))?;
    let (authority, path) = rest.split_once('/').map_or((rest, "/".to_owned()), |(a, p)| (a, format!("/{p}")));
    let addr = std::net::ToSocketAddrs::to_socket_addrs(authority)
        .with_context(|| format!("{url}: bad address"))?
        .next()
        .with_context(|| format!("{url}: no address"))?;
    let mut stream =
        std::net::TcpStream::connect_timeout(&addr, timeout).with_context(|| format!("{url}: cannot connect"))?;
    stream.set_read_timeout(Some(timeout))?;
    stream.set_write_timeout(Some(timeout))?;
    write!(stream, "GET {path} HTTP/1.1\r\nHost: {authority}\r\nConnection: close\r\n\r\n")?;
    let mut head = [0u8; 64];
    let n = stream.read(&mut head).with_context(|| format!("{url}: no answer"))?;
    let status = String::from_utf8_lossy(&head[..n]);
    let ok = status.starts_with("HTTP/1.1 200") || status.starts_with("HTTP/1.0 200");
    let line = status.lines().next().unwrap_or("").to_owned();
    if ok {
        println!("{url}: {line}");
        Ok(ExitCode::SUCCESS)
    } else {
        eprintln!("{url}: unhealthy: {line}");
        Ok(ExitCode::FAILURE)
    }
}
