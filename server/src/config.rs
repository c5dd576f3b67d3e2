//! Server settings: from flags and an optional TOML file.

use std::net::SocketAddr;
use std::path::PathBuf;
use std::time::Duration;

use serde::{Deserialize, Serialize};

/// Everything `terrastream serve` can be told.
#[derive(Clone, Debug, PartialEq, Eq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct ServerConfig {
    /// Address to listen on.
    pub addr: SocketAddr,
    /// Archive files and folders of archives to serve.
    pub paths: Vec<PathBuf>,
    /// `Cache-Control` of archive bytes and tiles.
    pub cache_control: String,
    /// Most ranges honoured in one request; more are answered with the whole file (as
    /// nginx's `max_ranges`).
    pub max_ranges: usize,
    /// Seconds a request may take before it is answered 408.
    pub request_timeout_secs: u64,
    /// Connections served at once; more wait in the listen backlog.
    pub max_connections: usize,
    /// Bytes of request head (request line + headers) accepted.
    pub max_header_bytes: usize,
    /// How often served folders are rescanned for replaced, added or removed archives.
    pub reload_interval_ms: u64,
    /// Seconds in-flight requests get to finish on shutdown.
    pub shutdown_grace_secs: u64,
    /// Threads serving connections, each with its own runtime and listening socket
    /// (0: one per core).
    pub workers: usize,
    /// PEM certificate chain: with `tls_key`, serve HTTPS (HTTP/2 and HTTP/1.1 by ALPN).
    pub tls_cert: Option<PathBuf>,
    /// PEM private key of `tls_cert`.
    pub tls_key: Option<PathBuf>,
    /// Answer plain `GET`/`HEAD` requests of archive bytes and tiles over HTTP/1.1 on the
    /// lean path (see the `h1` module) rather than through hyper and the router. The
    /// answers are the same; `false` routes everything through hyper.
    pub lean_http1: bool,
    /// Leaf directories of each archive kept decoded (an archive of more than a few
    /// thousand tiles keeps its entries in leaves of 4 096 or more; about 100 KiB each
    /// decoded). A tile whose leaf is not kept costs a leaf decode (0.1 - 0.2 ms); 1 024
    /// leaves cover 4 million tiles in at most about 100 MiB per archive, grown as tiles
    /// are asked for.
    pub leaf_cache: usize,
    /// Threads making web tiles and answering the elevation API (0: one per core), at a
    /// lower priority than the threads answering requests.
    pub web_threads: usize,
    /// Web tiles and elevation requests waiting for those threads; more are answered 503
    /// with `Retry-After`.
    pub web_queue: usize,
    /// Bytes of made web tiles kept (least recently used dropped first).
    pub web_cache_bytes: usize,
    /// Bytes of archive tiles kept decoded for web tiles and the elevation API
    /// (neighbouring web tiles and zooms read the same archive tiles).
    pub web_decoded_bytes: usize,
    /// Locations one elevation request may ask for (Open Topo Data's default: 100).
    pub max_locations: usize,
    /// The colour table of `color-relief` tiles, in `gdaldem color-relief`'s text format
    /// (default: built-in hypsometric tints).
    pub color_relief_table: Option<PathBuf>,
    /// Every archive needs a key or a signed token (`serve --private`).
    pub private_all: bool,
    /// Names (globs: `*`, `?`) of the archives that need a key or a signed token; the
    /// others are public.
    pub private: Vec<String>,
    /// The keys file (`terrastream key new` writes it; hashes only), reread when it
    /// changes.
    pub keys: Option<PathBuf>,
    /// The file holding the secret that signs tokens (`terrastream sign`).
    pub signing_secret_file: Option<PathBuf>,
    /// Seconds past a key's or token's expiry still accepted (clocks differ).
    pub clock_skew_secs: u64,
    /// Refusals (401, 403, 429) a second, all clients together, answered at once; beyond
    /// it each is held for its turn (up to a second), so a flood of bad credentials costs
    /// the server this rate and no more. 0: no pace.
    pub refusal_rate: u32,
    /// Refusals answered at once before the pace applies.
    pub refusal_burst: u32,
    /// A folder of TrueType/OpenType fonts (searched four folders deep) whose glyphs
    /// `/fonts/{fontstack}/{range}.pbf` serves for map labels (none: that route answers
    /// 404).
    pub fonts: Option<PathBuf>,
}

impl Default for ServerConfig {
    fn default() -> Self {
        Self {
            addr: SocketAddr::from(([127, 0, 0, 1], 8080)),
            paths: Vec::new(),
            cache_control: "public, max-age=3600".into(),
            max_ranges: 256,
            request_timeout_secs: 30,
            max_connections: 4096,
            max_header_bytes: 16 * 1024,
            reload_interval_ms: 1000,
            shutdown_grace_secs: 10,
            workers: 0,
            tls_cert: None,
            tls_key: None,
            lean_http1: true,
            leaf_cache: 1024,
            web_threads: 0,
            web_queue: 64,
            web_cache_bytes: 256 << 20,
            web_decoded_bytes: terrastream_views::resample::DECODED_BYTES,
            max_locations: 100,
            color_relief_table: None,
            private_all: false,
            private: Vec::new(),
            keys: None,
            signing_secret_file: None,
            clock_skew_secs: 60,
            refusal_rate: 200,
            refusal_burst: 400,
            fonts: None,
        }
    }
}

impl ServerConfig {
    /// Parses a TOML document.
    ///
    /// # Errors
    /// The TOML parser's message, naming the line and field.
    pub fn from_toml(text: &str) -> Result<Self, String> {
        toml::from_str(text).map_err(|e| e.to_string())
    }

    /// The request timeout.
    pub fn request_timeout(&self) -> Duration {
        Duration::from_secs(self.request_timeout_secs.max(1))
    }

    /// The access rules of these settings.
    pub fn access_rules(&self) -> crate::access::Rules {
        crate::access::Rules {
            private_all: self.private_all,
            private: self.private.clone(),
            keys: self.keys.clone(),
            secret: self.signing_secret_file.clone(),
            clock_skew_secs: self.clock_skew_secs,
            refusal_rate: self.refusal_rate,
            refusal_burst: self.refusal_burst,
        }
    }

    /// The rescan interval.
    pub fn reload_interval(&self) -> Duration {
        Duration::from_millis(self.reload_interval_ms.max(10))
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn toml_overrides_defaults_and_rejects_unknown_fields() {
        let c =
            ServerConfig::from_toml("addr = \"0.0.0.0:9000\"\npaths = [\"/data\"]\nmax_ranges = 8\nleaf_cache = 16\n")
                .unwrap();
        assert_eq!(c.addr.port(), 9000);
        assert_eq!(c.max_ranges, 8);
        assert_eq!((c.leaf_cache, ServerConfig::default().leaf_cache), (16, 1024));
        assert_eq!(c.cache_control, ServerConfig::default().cache_control);
        assert!(ServerConfig::from_toml("max_rangez = 8").unwrap_err().contains("max_rangez"));
    }
}
