//! `terrastream demo`: the README's first command.

use std::path::PathBuf;
use std::process::ExitCode;

use anyhow::{Context, Result};
use clap::Args;
use terrastream_packer::import::{OriginalLayout, pack, scan_original};
use terrastream_packer::sample::write_sample_pyramid;
use terrastream_packer::{ArchiveStats, WriterOptions, verify};

use super::CliProgress;

#[derive(Debug, Args)]
pub struct DemoArgs {
    /// Working folder for the sample pyramid and its archive.
    #[arg(long, default_value = "target/terrastream-demo")]
    dir: PathBuf,
    /// Where to serve the sample (port 0: any free port).
    #[arg(long, default_value = "127.0.0.1:0")]
    addr: std::net::SocketAddr,
    /// Keep serving after the demo requests, until Ctrl-C.
    #[arg(long)]
    keep_serving: bool,
}

/// One HTTP/1.1 GET over a plain socket: (status line, headers, body).
fn fetch(addr: std::net::SocketAddr, path: &str, extra: &str) -> Result<(String, String, Vec<u8>)> {
    use std::io::{Read, Write};
    let mut s = std::net::TcpStream::connect(addr)?;
    write!(s, "GET {path} HTTP/1.1\r\nHost: {addr}\r\n{extra}Connection: close\r\n\r\n")?;
    let mut answer = Vec::new();
    s.read_to_end(&mut answer)?;
    let end = answer.windows(4).position(|w| w == b"\r\n\r\n").context("malformed HTTP answer")?;
    let head = String::from_utf8_lossy(&answer[..end]).into_owned();
    let (status, headers) = head.split_once("\r\n").unwrap_or((&head, ""));
    Ok((status.to_owned(), headers.to_owned(), answer[end + 4..].to_vec()))
}

/// Serves the archive on a loopback port and shows a client's first requests.
fn serve_and_show(args: &DemoArgs) -> Result<()> {
    use terrastream_server::{AppState, ServerConfig, serve};
    let runtime = tokio::runtime::Builder::new_multi_thread().worker_threads(2).enable_all().build()?;
    runtime.block_on(async {
        let config = ServerConfig { paths: vec![args.dir.join("sample.tspack")], ..ServerConfig::default() };
        let state = AppState::new(config);
        state.catalog.reload();
        let listener =
            tokio::net::TcpListener::bind(args.addr).await.with_context(|| format!("binding {}", args.addr))?;
        let addr = listener.local_addr()?;
        let (stop, stopped) = tokio::sync::oneshot::channel::<()>();
        let server = tokio::spawn(serve(listener, state, async {
            let _ = stopped.await;
        }));
        println!("\nserving http://{addr}/sample.tspack");
        let shown = tokio::task::spawn_blocking(move || -> Result<()> {
            for (what, path, extra) in [
                ("bootstrap (first 16 KiB)", "/sample.tspack", "Range: bytes=0-16383\r\n"),
                ("metadata", "/sample/metadata", ""),
                ("coarsest texture tile", "/sample/texture/3/0/0", ""),
                ("missing lake tile", "/sample/texture/0/1/4", ""),
            ] {
                let (status, headers, body) = fetch(addr, path, extra)?;
                let pick = |name: &str| {
                    headers.lines().find_map(|l| {
                        l.split_once(':')
                            .filter(|(k, _)| k.eq_ignore_ascii_case(name))
                            .map(|(_, v)| v.trim().to_owned())
                    })
                };
                let detail = [
                    pick("content-range"),
                    pick("content-type"),
                    pick("x-terrastream-fallback-lod").map(|l| format!("use LOD {l}")),
                ]
                .into_iter()
                .flatten()
                .collect::<Vec<_>>()
                .join(", ");
                println!("  GET {path:<28} {status:<28} {:>7} bytes  {detail}   ({what})", body.len());
            }
            Ok(())
        })
        .await?;
        shown?;
        if args.keep_serving {
            println!("serving until Ctrl-C: http://{addr}/");
            let _ = tokio::signal::ctrl_c().await;
        }
        let _ = stop.send(());
        server.await??;
        anyhow::Ok(())
    })
}

pub fn run(args: DemoArgs, progress: &CliProgress) -> Result<ExitCode> {
    let input = args.dir.join("sample");
    let archive = args.dir.join("sample.tspack");
    if !input.join("metadata.txt").exists() {
        write_sample_pyramid(&input).with_context(|| format!("writing the sample pyramid to {}", input.display()))?;
        println!("wrote the built-in sample pyramid (original LOD-folder layout) to {}", input.display());
    }
    let scanned = scan_original(&input, &OriginalLayout::default())?;
    let summary = pack(scanned, &archive, WriterOptions::default(), progress)?;
    progress.finish();
    println!("packed {} tiles into {} ({} bytes)\n", summary.addressed_tiles, archive.display(), summary.file_len);
    let location = archive.display().to_string();
    let reader = super::open(&location)?;
    print!("{}", super::info::render(&location, &ArchiveStats::collect(&reader)?, reader.metadata()));
    let report = verify(&reader, |_| {})?;
    println!(
        "\nverify: {} ({} tiles, {} blobs checked)",
        if report.is_ok() { "OK" } else { "DAMAGED" },
        report.addressed_tiles,
        report.blobs_checked
    );
    if !report.is_ok() {
        return Ok(ExitCode::FAILURE);
    }
    serve_and_show(&args)?;
    println!(
        "\nnext: terrastream serve {} (or --keep-serving), terrastream extract {} -o <dir>",
        archive.display(),
        archive.display()
    );
    Ok(ExitCode::SUCCESS)
}
