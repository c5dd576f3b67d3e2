//! Private terrain: who may read what. One function, [`Access::decide`], rules on every
//! request before it is routed, on hyper's path (`crate::edge`) and on the lean
//! HTTP/1.1 path (`crate::h1`) alike.
//!
//! - Archives are public unless a rule makes them private: `private` globs in the
//!   configuration, or `private_all` (`serve --private`).
//! - A private archive is opened by an API key whose scope names it ([`keys`]), or by a
//!   signed token for it or for a path prefix above the request ([`token`]), presented as
//!   `Authorization: Bearer …`, `?access_token=…` (Cesium ion's name) or `?key=…`
//!   (MapTiler's).
//! - Without a credential: 401. With one that is not valid, expired, used from an origin
//!   it does not allow, or that does not open the archive: 403. Over its rate: 429 with
//!   `Retry-After`. Each with a JSON body naming the reason, never the tile.
//! - The answer depends on the archive's *name* and the credential only, never on whether
//!   the archive exists: a private name the credential does not open is refused the same
//!   way whether or not an archive has it, so nothing can be enumerated.
//! - A credential given in the query is carried into the URLs the server hands out
//!   (TileJSON, `layer.json`, the player, manifests, the listing) so that clients that
//!   cannot set headers work from the first URL; one given in a header is not (headers
//!   stay out of URLs, logs and caches), and its answers are marked `private` for caches.

pub mod keys;
mod limiter;
mod pace;
pub mod token;

use std::borrow::Cow;
use std::cell::RefCell;
use std::path::PathBuf;
use std::sync::atomic::{AtomicU64, Ordering};
use std::sync::{Arc, Mutex, RwLock};
use std::time::SystemTime;

use axum::http::header::{CACHE_CONTROL, CONTENT_LENGTH, CONTENT_TYPE, RETRY_AFTER, WWW_AUTHENTICATE};
use axum::http::{HeaderValue, StatusCode};

use crate::app::Answer;
use crate::body::Payload;
use crate::route::Route;
use keys::{KeyFile, KeyRecord, KeyStore, KeysError};
use limiter::Limiter;
use pace::Pace;
use token::Scope;

/// The query parameters a credential may be given in, in the order they are looked for.
pub const QUERY_PARAMETERS: [&str; 2] = ["access_token", "key"];

/// Longest credential read (longer ones are refused unread).
const MAX_CREDENTIAL: usize = 1024;

/// What a request presents, borrowed from it.
#[derive(Clone, Copy, Debug, Default)]
pub struct Presented<'a> {
    /// The request target's path, as received (percent-encoded).
    pub path: &'a str,
    /// The query, without its `?`.
    pub query: Option<&'a str>,
    /// The `Authorization` header's value.
    pub authorization: Option<&'a [u8]>,
    /// The `Origin` header's value.
    pub origin: Option<&'a [u8]>,
    /// The `Referer` header's value (the origin of pages that send no `Origin`).
    pub referer: Option<&'a [u8]>,
}

/// What a request may see, once allowed.
#[derive(Clone, Debug, Default)]
pub struct Grant {
    /// What opened it: nothing (public), a key, or a signed token.
    by: By,
    /// The request names a private archive.
    pub private: bool,
    /// The credential came in a header (its answers are marked private for caches).
    pub by_header: bool,
    /// The query parameter and credential to carry into handed-out URLs.
    carry: Carried,
}

#[derive(Clone, Debug, Default)]
enum By {
    #[default]
    Nothing,
    Key(Arc<KeyRecord>),
    Token(Scope),
}

impl Grant {
    /// `?param=credential` (or `&…` when `url` has a query) appended to `url`, when the
    /// request's credential came in the query; `url` as it is otherwise.
    pub fn carry(&self, url: &str) -> String {
        match &self.carry {
            Some((param, value)) => {
                let join = if url.contains('?') { '&' } else { '?' };
                format!("{url}{join}{param}={value}")
            }
            None => url.to_owned(),
        }
    }

    /// The query text (`param=credential`) carried into URLs, if any.
    pub fn carried(&self) -> Option<String> {
        self.carry.as_ref().map(|(p, v)| format!("{p}={v}"))
    }

    /// Whether it opens archive `name` (listing: which archives to show), given whether
    /// that archive is private.
    pub fn opens(&self, name: &str, private: bool) -> bool {
        !private
            || match &self.by {
                By::Nothing => false,
                By::Key(k) => k.archives.iter().any(|g| glob(g, name)),
                By::Token(Scope::Archive(a)) => a == name,
                By::Token(Scope::Prefix(p)) => p == "/",
            }
    }
}

/// Why a request was refused.
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct Denied {
    /// 401, 403 or 429.
    pub status: StatusCode,
    /// The reason, for the body.
    pub reason: &'static str,
    /// Seconds to wait (429).
    pub retry_after: Option<u64>,
}

impl Denied {
    fn new(status: StatusCode, reason: &'static str) -> Self {
        Self { status, reason, retry_after: None }
    }

    /// The answer: the status, a JSON body naming the reason, `WWW-Authenticate` (401) or
    /// `Retry-After` (429); never cached.
    pub fn answer(&self) -> Answer {
        let code = match self.status {
            StatusCode::UNAUTHORIZED => "UNAUTHORIZED",
            StatusCode::TOO_MANY_REQUESTS => "RATE_LIMITED",
            _ => "FORBIDDEN",
        };
        let body = serde_json::json!({ "error": self.reason, "status": code }).to_string();
        let mut answer = Answer::new(Payload::from(body.clone()));
        *answer.status_mut() = self.status;
        let h = answer.headers_mut();
        h.insert(CONTENT_TYPE, HeaderValue::from_static("application/json"));
        h.insert(CONTENT_LENGTH, HeaderValue::from(body.len()));
        h.insert(CACHE_CONTROL, HeaderValue::from_static("no-store"));
        if self.status == StatusCode::UNAUTHORIZED {
            h.insert(WWW_AUTHENTICATE, HeaderValue::from_static("Bearer realm=\"terrastream\""));
        }
        if let Some(secs) = self.retry_after {
            h.insert(RETRY_AFTER, HeaderValue::from(secs.max(1)));
        }
        answer
    }
}

/// The access rules of a server (from its configuration).
#[derive(Clone, Debug, Default, PartialEq, Eq)]
pub struct Rules {
    /// Every archive needs a credential.
    pub private_all: bool,
    /// Names (globs) of the archives that need one.
    pub private: Vec<String>,
    /// The keys file.
    pub keys: Option<PathBuf>,
    /// The file holding the secret that signs tokens.
    pub secret: Option<PathBuf>,
    /// Seconds past an expiry still accepted (clocks differ).
    pub clock_skew_secs: u64,
    /// Refusals a second, all clients together, answered without delay (0: no pace);
    /// beyond it each is held for its turn (`pace`).
    pub refusal_rate: u32,
    /// Refusals answered at once before the pace applies.
    pub refusal_burst: u32,
}

/// Why the access rules cannot be used.
#[derive(Debug, thiserror::Error)]
pub enum AccessError {
    /// The keys file.
    #[error(transparent)]
    Keys(#[from] KeysError),
    /// The secret file cannot be read, or is too short.
    #[error("{path}: {reason}")]
    Secret {
        /// The file.
        path: PathBuf,
        /// Why.
        reason: String,
    },
}

/// Numbers told apart [`Access`] values (for the per-thread copies of their keys).
static ACCESS_IDS: AtomicU64 = AtomicU64::new(1);

thread_local! {
    /// This thread's copy of the key store it last used: which [`Access`] it is of, the
    /// store's generation, the store ([`KeyStore::private_copy`]). A decision reads the
    /// keys without touching a lock or a reference count shared with the other threads:
    /// on 2 cores their cache lines going back and forth doubled a decision's time.
    static KEYS: RefCell<Option<(u64, u64, KeyStore)>> = const { RefCell::new(None) };
}

/// The rules, the keys and the rate limits, shared by every connection.
#[derive(Debug, Default)]
pub struct Access {
    rules: Rules,
    /// This value's number among others (0: none yet, for `Default`).
    id: u64,
    keys: RwLock<Arc<KeyStore>>,
    /// Bumped when `keys` is replaced: threads' copies of an older one are renewed.
    generation: AtomicU64,
    keys_stamp: Mutex<Option<SystemTime>>,
    secret: Option<Vec<u8>>,
    limiter: Limiter,
    pace: Option<Pace>,
    enabled: bool,
}

/// Fewest bytes of a signing secret.
pub const MIN_SECRET_BYTES: usize = 16;

/// Reads a signing secret: the file's bytes, surrounding whitespace trimmed.
///
/// # Errors
/// [`AccessError::Secret`] naming the file.
pub fn read_secret(path: &std::path::Path) -> Result<Vec<u8>, AccessError> {
    let bad = |reason: String| AccessError::Secret { path: path.to_owned(), reason };
    let bytes = std::fs::read(path).map_err(|e| bad(e.to_string()))?;
    let trimmed = bytes.trim_ascii().to_vec();
    if trimmed.len() < MIN_SECRET_BYTES {
        return Err(bad(format!("a signing secret has at least {MIN_SECRET_BYTES} bytes")));
    }
    Ok(trimmed)
}

impl Access {
    /// The rules, with their keys file and secret read.
    ///
    /// # Errors
    /// [`AccessError`] naming the file at fault.
    pub fn new(rules: Rules) -> Result<Self, AccessError> {
        let secret = rules.secret.as_deref().map(read_secret).transpose()?;
        let (store, stamp) = match &rules.keys {
            Some(path) => (KeyStore::new(KeyFile::read(path)?), modified(path)),
            None => (KeyStore::default(), None),
        };
        let enabled = rules.private_all || !rules.private.is_empty() || rules.keys.is_some() || secret.is_some();
        Ok(Self {
            pace: Pace::new(rules.refusal_rate, rules.refusal_burst),
            rules,
            id: ACCESS_IDS.fetch_add(1, Ordering::Relaxed),
            keys: RwLock::new(Arc::new(store)),
            generation: AtomicU64::new(0),
            keys_stamp: Mutex::new(stamp),
            secret,
            limiter: Limiter::default(),
            enabled,
        })
    }

    /// Waits the turn of a refusal made now before it is answered: refusals share one pace
    /// (`pace`), so a flood of bad credentials leaves the cores to valid requests. Both
    /// HTTP paths await it on every refusal.
    pub async fn wait_turn(&self) {
        let hold = self.pace.as_ref().map_or(std::time::Duration::ZERO, |p| p.hold(std::time::Instant::now()));
        if !hold.is_zero() {
            tokio::time::sleep(hold).await;
        }
    }

    /// Whether refusals are paced (`refusal_rate` above 0).
    pub fn paced(&self) -> bool {
        self.pace.is_some()
    }

    /// Whether any rule is set (else every request is allowed without a look).
    pub fn enabled(&self) -> bool {
        self.enabled
    }

    /// Rereads the keys file if it changed (keys added or revoked take effect without a
    /// restart). A file that cannot be read keeps the keys as they were.
    pub fn reload(&self) {
        let Some(path) = &self.rules.keys else { return };
        let stamp = modified(path);
        let mut seen = self.keys_stamp.lock().unwrap_or_else(std::sync::PoisonError::into_inner);
        if stamp == *seen {
            return;
        }
        match KeyFile::read(path) {
            Ok(file) => {
                let store = KeyStore::new(file);
                tracing::info!(keys = store.len(), "{}: keys reloaded", path.display());
                *self.keys.write().unwrap_or_else(std::sync::PoisonError::into_inner) = Arc::new(store);
                self.generation.fetch_add(1, Ordering::Release);
                *seen = stamp;
            }
            Err(e) => tracing::warn!("keys not reloaded: {e}"),
        }
    }

    /// `f` of the keys, from this thread's copy while it is current.
    fn with_keys<R>(&self, f: impl FnOnce(&KeyStore) -> R) -> R {
        let generation = self.generation.load(Ordering::Acquire);
        KEYS.with(|slot| {
            let mut slot = slot.borrow_mut();
            match slot.as_ref() {
                Some((id, g, store)) if *id == self.id && *g == generation && self.id != 0 => f(store),
                _ => {
                    let store = self.keys.read().unwrap_or_else(std::sync::PoisonError::into_inner).private_copy();
                    let answer = f(&store);
                    *slot = Some((self.id, generation, store));
                    answer
                }
            }
        })
    }

    /// Whether archive `name` needs a credential.
    pub fn is_private(&self, name: &str) -> bool {
        self.rules.private_all || self.rules.private.iter().any(|g| glob(g, name))
    }

    /// Rules on one request: what it may see, or why it is refused.
    ///
    /// # Errors
    /// [`Denied`]: 401 without a credential where one is needed, 403 for a credential
    /// that does not open what is asked, 429 over a key's rate.
    pub fn decide(&self, req: &Presented<'_>, now: SystemTime) -> Result<Grant, Denied> {
        self.rule(req, &mut || now)
    }

    /// [`Access::decide`] at the present time (read only where a credential's expiry
    /// needs it).
    ///
    /// # Errors
    /// As [`Access::decide`].
    pub fn decide_now(&self, req: &Presented<'_>) -> Result<Grant, Denied> {
        self.rule(req, &mut SystemTime::now)
    }

    /// The rules themselves, for [`Access::decide`] and [`Access::decide_now`].
    fn rule(&self, req: &Presented<'_>, now: &mut dyn FnMut() -> SystemTime) -> Result<Grant, Denied> {
        if !self.enabled {
            return Ok(Grant::default());
        }
        let target = target(req.path);
        if matches!(target, Target::Open) {
            return Ok(Grant::default());
        }
        let private = match &target {
            Target::Archive(name) => self.is_private(name),
            Target::Metrics => true,
            Target::Listing | Target::Open => false,
        };
        let (credential, carry) = credential(req)?;
        let Some(credential) = credential else {
            return if private {
                Err(Denied::new(StatusCode::UNAUTHORIZED, "a key is needed"))
            } else {
                Ok(Grant::default())
            };
        };
        let mut unix = || now().duration_since(SystemTime::UNIX_EPOCH).map_or(0, |d| d.as_secs());
        let by = self.credential_opens(&credential, req, &mut unix)?;
        let grant = Grant { by, private, by_header: carry.is_none(), carry };
        let allowed = match &target {
            Target::Archive(name) => grant.opens(name, private) || prefix_opens(&grant.by, req.path),
            Target::Metrics => matches!(&grant.by, By::Key(k) if k.admin),
            Target::Listing | Target::Open => true,
        };
        if !allowed {
            return Err(Denied::new(StatusCode::FORBIDDEN, "the key does not open this"));
        }
        if let By::Key(k) = &grant.by
            && k.rate.is_some()
            && let Err(wait) = self.limiter.take(k, std::time::Instant::now())
        {
            return Err(Denied {
                retry_after: Some(wait),
                ..Denied::new(StatusCode::TOO_MANY_REQUESTS, "over the key's rate")
            });
        }
        Ok(grant)
    }

    /// What a presented credential is, if it is valid here and now.
    fn credential_opens(
        &self,
        credential: &str,
        req: &Presented<'_>,
        unix: &mut dyn FnMut() -> u64,
    ) -> Result<By, Denied> {
        let refused = |reason| Err(Denied::new(StatusCode::FORBIDDEN, reason));
        if credential.starts_with("ts1~") {
            let Some(secret) = &self.secret else { return refused("the key is not valid") };
            return match token::verify(secret, credential, unix(), self.rules.clock_skew_secs) {
                Ok(scope) => Ok(By::Token(scope)),
                Err(token::Refused::Expired) => refused("the key has expired"),
                Err(_) => refused("the key is not valid"),
            };
        }
        let found = self.with_keys(|keys| keys.find(credential));
        let Some(record) = found else { return refused("the key is not valid") };
        if record.expires.is_some_and(|e| unix() > e.saturating_add(self.rules.clock_skew_secs)) {
            return refused("the key has expired");
        }
        if !record.origins.is_empty() {
            let origin = req.origin.or(req.referer).and_then(|o| origin_of(o));
            if !origin.is_some_and(|o| record.origins.iter().any(|allowed| allowed.trim_end_matches('/') == o)) {
                return refused("the key is not allowed from this origin");
            }
        }
        Ok(By::Key(record))
    }
}

/// A signed token for a path prefix opens the paths under it.
fn prefix_opens(by: &By, path: &str) -> bool {
    match by {
        By::Token(Scope::Prefix(prefix)) => {
            percent_decoded(path).is_some_and(|p| p.starts_with(prefix.as_str()) && !p.contains("/../"))
        }
        _ => false,
    }
}

/// A query parameter's name and value, carried into handed-out URLs.
type Carried = Option<(&'static str, String)>;

/// The credential a request presents (and what to carry into URLs: the query's
/// parameter and value), if any.
fn credential<'a>(req: &Presented<'a>) -> Result<(Option<Cow<'a, str>>, Carried), Denied> {
    let bad = || Denied::new(StatusCode::FORBIDDEN, "the key is not valid");
    if let Some(header) = req.authorization {
        let header = header.trim_ascii();
        let scheme = b"bearer ";
        let value = match header.get(..scheme.len()) {
            Some(s) if s.eq_ignore_ascii_case(scheme) => header[scheme.len()..].trim_ascii(),
            _ => return Err(bad()),
        };
        if value.len() > MAX_CREDENTIAL {
            return Err(bad());
        }
        let value = std::str::from_utf8(value).map_err(|_| bad())?;
        return Ok((Some(Cow::Borrowed(value)), None));
    }
    let Some(query) = req.query else { return Ok((None, None)) };
    for param in QUERY_PARAMETERS {
        for pair in query.split('&') {
            let Some((name, value)) = pair.split_once('=') else { continue };
            if name != param || value.is_empty() {
                continue;
            }
            if value.len() > MAX_CREDENTIAL {
                return Err(bad());
            }
            let decoded = percent_decoded(value).ok_or_else(bad)?;
            let carried = value.to_owned();
            return Ok((Some(Cow::Owned(decoded.into_owned())), Some((param, carried))));
        }
    }
    Ok((None, None))
}

/// A query with the value of every credential parameter replaced by `…`: what logs show.
pub fn redacted(query: &str) -> String {
    query
        .split('&')
        .map(|pair| match pair.split_once('=') {
            Some((name, _)) if QUERY_PARAMETERS.contains(&name) => format!("{name}=…"),
            _ => pair.to_owned(),
        })
        .collect::<Vec<_>>()
        .join("&")
}

/// What a request path asks for, as far as access goes.
#[derive(Clone, Debug, PartialEq, Eq)]
enum Target<'a> {
    /// An archive or manifest, by name (every route of it).
    Archive(Cow<'a, str>),
    /// The list of archives (filtered by what the credential opens).
    Listing,
    /// `/metrics`: an admin key's.
    Metrics,
    /// Open to all: health, the player's own files, paths that name no archive.
    Open,
}

/// The target of a request path, with the archive's name as the router's handlers see it
/// (the path segment the route names it by, percent-decoded).
fn target(path: &str) -> Target<'_> {
    let route = Route::of(path);
    let mut segments = path.strip_prefix('/').unwrap_or(path).split('/');
    let first = segments.next().unwrap_or("");
    let second = segments.next().unwrap_or("");
    let name = match route {
        Route::Index => return Target::Listing,
        Route::Metrics => return Target::Metrics,
        // `/auth` rules on the URI it is given, in its handler.
        Route::Health | Route::Auth | Route::Fonts | Route::Other => return Target::Open,
        Route::View if crate::player::asset(second).is_some() => return Target::Open,
        Route::View | Route::Elevation => second,
        Route::Archive => {
            let Some(decoded) = percent_decoded(first) else { return Target::Open };
            // Archives and manifests; and the exports a proxy's `auth_request` asks about.
            let stem = [".tspack", ".json", ".pmtiles", ".mbtiles"].iter().find_map(|s| decoded.strip_suffix(s));
            // A file that is none of these is answered 404 by every server.
            return stem.map_or(Target::Open, |s| Target::Archive(Cow::Owned(s.to_owned())));
        }
        Route::Metadata
        | Route::Tile
        | Route::TileJson
        | Route::LayerTileJson
        | Route::WebTile
        | Route::LayerJson
        | Route::TerrainTile
        | Route::Contours => first,
    };
    // Undecodable: the router answers 400 without reaching a handler.
    percent_decoded(name).map_or(Target::Open, Target::Archive)
}

/// `text` with its `%XX` escapes decoded, as the router decodes a path's parameters; None
/// when an escape is malformed or the result is not UTF-8.
pub(crate) fn percent_decoded(text: &str) -> Option<Cow<'_, str>> {
    if !text.contains('%') {
        return Some(Cow::Borrowed(text));
    }
    let bytes = text.as_bytes();
    let mut out = Vec::with_capacity(bytes.len());
    let mut i = 0;
    while i < bytes.len() {
        if bytes[i] == b'%' {
            let hex = bytes.get(i + 1..i + 3)?;
            out.push(u8::from_str_radix(std::str::from_utf8(hex).ok()?, 16).ok()?);
            i += 3;
        } else {
            out.push(bytes[i]);
            i += 1;
        }
    }
    String::from_utf8(out).ok().map(Cow::Owned)
}

/// The origin (`scheme://host[:port]`) of an `Origin` or `Referer` value.
fn origin_of(value: &[u8]) -> Option<&str> {
    let text = std::str::from_utf8(value).ok()?.trim();
    let (scheme, rest) = text.split_once("://")?;
    let host_end = rest.find(['/', '?', '#']).unwrap_or(rest.len());
    Some(&text[..scheme.len() + 3 + host_end])
}

/// Whether `name` matches `pattern`: `*` any run of characters, `?` any one (byte-wise:
/// names are of a safe ASCII alphabet). No allocation: it runs on every request.
pub fn glob(pattern: &str, name: &str) -> bool {
    let (p, n) = (pattern.as_bytes(), name.as_bytes());
    if !p.contains(&b'*') && !p.contains(&b'?') {
        return p == n;
    }
    // Iterative matching with one backtrack point (the last `*`).
    let (mut i, mut j, mut star, mut mark) = (0, 0, None, 0);
    while j < n.len() {
        if i < p.len() && (p[i] == b'?' || p[i] == n[j]) {
            i += 1;
            j += 1;
        } else if i < p.len() && p[i] == b'*' {
            star = Some(i);
            mark = j;
            i += 1;
        } else if let Some(s) = star {
            i = s + 1;
            mark += 1;
            j = mark;
        } else {
            return false;
        }
    }
    p[i..].iter().all(|&c| c == b'*')
}

fn modified(path: &std::path::Path) -> Option<SystemTime> {
    std::fs::metadata(path).and_then(|m| m.modified()).ok()
}

#[cfg(test)]
mod tests;
