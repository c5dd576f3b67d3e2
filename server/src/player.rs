//! The webplayer, embedded in the binary: `GET /view/{name}` is the player page for the
//! archive `name`, and `/view/terrastream_web.js` and `/view/terrastream_web_bg.wasm`
//! (the names the page asks for, relative to itself) are its code.
//!
//! The files come from `client/web/dist` at build time (see `build.rs`). Text and wasm
//! are gzipped once, on first request, for clients that accept it.

use std::io::Write;
use std::sync::{LazyLock, OnceLock};

use bytes::Bytes;

include!(concat!(env!("OUT_DIR"), "/player_files.rs"));

/// The placeholder in `player.html` that the page for an archive fills in.
const ARCHIVE_META: &str = r#"<meta name="terrastream-archive" content="">"#;

/// One embedded file.
#[derive(Debug)]
pub struct Asset {
    /// File name.
    pub name: &'static str,
    /// MIME type.
    pub content_type: &'static str,
    /// The bytes.
    pub bytes: Bytes,
    /// Strong ETag (a hash of the bytes).
    pub etag: String,
    gzip: OnceLock<Option<Bytes>>,
}

impl Asset {
    fn new(name: &'static str, bytes: Bytes) -> Self {
        let content_type = match name.rsplit_once('.').map(|(_, ext)| ext) {
            Some("html") => "text/html; charset=utf-8",
            Some("js") => "text/javascript; charset=utf-8",
            Some("wasm") => "application/wasm",
            _ => "application/octet-stream",
        };
        let etag = format!("\"{:016x}\"", xxhash_rust::xxh3::xxh3_64(&bytes));
        Self { name, content_type, bytes, etag, gzip: OnceLock::new() }
    }

    /// The bytes gzipped, or `None` where that does not make them smaller. Compressed
    /// once, on first use, on a blocking thread (the wasm takes a good part of a second
    /// at the best level): never on the runtime's workers.
    pub async fn gzipped(&'static self) -> Option<Bytes> {
        if let Some(done) = self.gzip.get() {
            return done.clone();
        }
        tokio::task::spawn_blocking(move || self.gzip.get_or_init(|| gzip(&self.bytes)).clone()).await.ok().flatten()
    }
}

fn gzip(bytes: &[u8]) -> Option<Bytes> {
    let mut encoder = flate2::write::GzEncoder::new(Vec::new(), flate2::Compression::best());
    encoder.write_all(bytes).ok()?;
    let out = encoder.finish().ok()?;
    (out.len() < bytes.len()).then(|| Bytes::from(out))
}

static ASSETS: LazyLock<Vec<Asset>> =
    LazyLock::new(|| FILES.iter().map(|(name, bytes)| Asset::new(name, Bytes::from_static(bytes))).collect());

/// Was the player built into this binary?
pub fn available() -> bool {
    !ASSETS.is_empty()
}

/// All the player's files as built (the page with its archive left blank): what a
/// static host serves.
pub fn files() -> impl Iterator<Item = (&'static str, &'static [u8])> {
    FILES.iter().copied()
}

/// The player's code files by name (not the page itself: that is [`page`]).
pub fn asset(name: &str) -> Option<&'static Asset> {
    ASSETS.iter().find(|a| a.name == name && a.name != "player.html")
}

/// The player page for the archive at `archive_url` (relative to the page), or `None`
/// when the player is not built in.
pub fn page(archive_url: &str) -> Option<String> {
    let html = ASSETS.iter().find(|a| a.name == "player.html")?;
    let html = std::str::from_utf8(&html.bytes).ok()?;
    let filled = format!(r#"<meta name="terrastream-archive" content="{}">"#, crate::app::escape(archive_url));
    Some(html.replacen(ARCHIVE_META, &filled, 1))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[tokio::test]
    async fn assets_have_types_and_compress() {
        let a: &'static Asset = Box::leak(Box::new(Asset::new("x.js", Bytes::from(vec![b'a'; 10_000]))));
        assert_eq!(a.content_type, "text/javascript; charset=utf-8");
        assert!(a.gzipped().await.is_some_and(|g| g.len() < 1000));
        let b: &'static Asset = Box::leak(Box::new(Asset::new("y.wasm", Bytes::from_static(&[0, 97, 115, 109]))));
        assert_eq!(b.content_type, "application/wasm");
        assert!(b.gzipped().await.is_none(), "gzip of 4 bytes is larger: served plain");
    }

    #[test]
    fn the_page_is_filled_in_when_built_in() {
        match page(r#"../a"b<c>&.tspack"#) {
            Some(html) => assert!(html.contains(r#"content="../a&quot;b&lt;c&gt;&amp;.tspack""#), "{html}"),
            None => assert!(!available()),
        }
        assert!(asset("player.html").is_none());
    }
}
