//! `terrastream serve`.

use std::net::SocketAddr;
use std::path::PathBuf;
use std::process::ExitCode;

use anyhow::{Context, Result, bail};
use clap::Args;
use terrastream_server::{AppState, ServerConfig, serve_workers, shutdown_signal};

#[derive(Debug, Args)]
pub struct ServeArgs {
    /// Archive files and folders of `*.tspack` to serve (added to the config file's).
    paths: Vec<PathBuf>,
    /// Address to listen on [default: 127.0.0.1:8080].
    #[arg(long)]
    addr: Option<SocketAddr>,
    /// TOML settings (see `ServerConfig`); flags override it.
    #[arg(long)]
    config: Option<PathBuf>,
    /// Most ranges honoured per request.
    #[arg(long)]
    max_ranges: Option<usize>,
    /// `Cache-Control` of archive bytes and tiles.
    #[arg(long)]
    cache_control: Option<String>,
    /// Most connections served at once.
    #[arg(long)]
    max_connections: Option<usize>,
    /// Serving threads, each with its own listening socket [default: one per core].
    #[arg(long)]
    workers: Option<usize>,
    /// PEM certificate chain: serve HTTPS (HTTP/2 and HTTP/1.1 by ALPN).
    #[arg(long, requires = "tls_key")]
    tls_cert: Option<PathBuf>,
    /// PEM private key of --tls-cert.
    #[arg(long, requires = "tls_cert")]
    tls_key: Option<PathBuf>,
    /// Every archive needs a key or a signed token (else only those the config's
    /// `private` globs name).
    #[arg(long)]
    private: bool,
    /// The keys file (`terrastream key new` writes it), reread when it changes.
    #[arg(long)]
    keys: Option<PathBuf>,
    /// The file of the secret that signs tokens (`terrastream sign`).
    #[arg(long)]
    secret_file: Option<PathBuf>,
    /// A folder of TrueType/OpenType fonts: `/fonts/{fontstack}/{range}.pbf` serves their
    /// glyphs, for map styles' labels (e.g. /usr/share/fonts/truetype/dejavu).
    #[arg(long)]
    fonts: Option<PathBuf>,
}

pub fn run(args: ServeArgs) -> Result<ExitCode> {
    let mut config = match &args.config {
        Some(path) => {
            let text = std::fs::read_to_string(path).with_context(|| format!("reading {}", path.display()))?;
            ServerConfig::from_toml(&text).map_err(|e| anyhow::anyhow!("{}: {e}", path.display()))?
        }
        None => ServerConfig::default(),
    };
    config.paths.extend(args.paths);
    if let Some(addr) = args.addr {
        config.addr = addr;
    }
    if let Some(n) = args.max_ranges {
        config.max_ranges = n;
    }
    if let Some(c) = args.cache_control {
        config.cache_control = c;
    }
    if let Some(n) = args.max_connections {
        config.max_connections = n;
    }
    if let Some(n) = args.workers {
        config.workers = n;
    }
    if args.tls_cert.is_some() {
        config.tls_cert = args.tls_cert;
        config.tls_key = args.tls_key;
    }
    config.private_all |= args.private;
    if args.keys.is_some() {
        config.keys = args.keys;
    }
    if args.secret_file.is_some() {
        config.signing_secret_file = args.secret_file;
    }
    if args.fonts.is_some() {
        config.fonts = args.fonts;
    }
    if config.paths.is_empty() {
        bail!("nothing to serve: give archive files or folders");
    }
    for p in &config.paths {
        if !p.exists() {
            bail!("{}: no such file or folder", p.display());
        }
    }
    let state = AppState::try_new(config.clone()).context("reading the access rules")?;
    if state.access.enabled() {
        let private = if config.private_all { "every archive".to_owned() } else { format!("{:?}", config.private) };
        tracing::info!("private terrain: {private} needs a key or a signed token");
    }
    state.catalog.reload();
    let scheme = if config.tls_cert.is_some() { "https" } else { "http" };
    serve_workers(config.addr, config.workers, state.clone(), shutdown_signal(), |addr| {
        for a in state.catalog.list() {
            println!("serving http://{addr}/{}.tspack  ({})", a.name, a.path.display());
        }
        println!("listening on {scheme}://{addr}/ (Ctrl-C to stop)");
    })
    .with_context(|| format!("serving on {}", config.addr))?;
    Ok(ExitCode::SUCCESS)
}
