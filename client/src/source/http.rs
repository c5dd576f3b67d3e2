//! HTTP Range source: any server or CDN that honours `Range` (ours, nginx, object
//! storage). One connection pool (HTTP/2 when the server offers it), the first 16 KiB
//! fetched once so that opening an archive costs one request, every later request
//! conditional on the first response's ETag (`If-Match`): a replaced archive is detected
//! ([`Error::Changed`]) instead of mixing bytes of two versions. Transient failures
//! (connection errors, timeouts, 5xx, 429, truncated bodies) are retried with backoff.

use std::sync::atomic::{AtomicU64, Ordering::Relaxed};
use std::sync::{Arc, Mutex};
use std::time::Duration;

use bytes::Bytes;
use reqwest::StatusCode;
use reqwest::header::{CONTENT_RANGE, ETAG, IF_MATCH, RANGE};
use terrastream_format::{AsyncRangeSource, BOOTSTRAP_READ, Error, Result};

use crate::error::Error as ClientError;

/// How often and how patiently to retry a failed request.
#[derive(Clone, Copy, Debug)]
pub struct RetryPolicy {
    /// Attempts in all (>= 1).
    pub attempts: u32,
    /// Wait before the first retry; doubled each time.
    pub first_backoff: Duration,
    /// Time limit of one request.
    pub timeout: Duration,
}

impl Default for RetryPolicy {
    fn default() -> Self {
        Self { attempts: 4, first_backoff: Duration::from_millis(100), timeout: Duration::from_secs(20) }
    }
}

/// Counters of an [`HttpSource`].
#[derive(Debug, Default)]
pub struct HttpStats {
    /// Requests sent (retries included).
    pub requests: AtomicU64,
    /// Body bytes received.
    pub bytes: AtomicU64,
    /// Retries after transient failures.
    pub retries: AtomicU64,
}

#[derive(Debug, Default)]
struct Known {
    len: Option<u64>,
    etag: Option<String>,
    head: Option<Bytes>,
}

/// An archive at an `http(s)://` URL.
#[derive(Debug)]
pub struct HttpSource {
    client: reqwest::Client,
    url: reqwest::Url,
    retry: RetryPolicy,
    known: Mutex<Known>,
    stats: Arc<HttpStats>,
}

enum Attempt {
    Done(Bytes),
    Retry(String),
}

impl HttpSource {
    /// A source for `url` with a new connection pool.
    ///
    /// # Errors
    /// [`ClientError::BadUrl`] if the URL is not http(s), [`ClientError::HttpClient`] if
    /// the client cannot be built.
    pub fn new(url: &str) -> crate::Result<Self> {
        let builder = reqwest::Client::builder();
        #[cfg(not(target_arch = "wasm32"))]
        let builder = builder.pool_max_idle_per_host(64).tcp_nodelay(true);
        let client = builder.build().map_err(|e| ClientError::HttpClient { reason: e.to_string() })?;
        Self::with_client(client, url, RetryPolicy::default())
    }

    /// A source for `url` over HTTP/2 without TLS (h2c, prior knowledge): one multiplexed
    /// connection instead of several, for a server known to speak it (`terrastream serve`
    /// does; HTTP/1-only servers refuse it). Over `https://`, [`HttpSource::new`]
    /// negotiates HTTP/2 by itself where the server offers it.
    ///
    /// # Errors
    /// As [`HttpSource::new`].
    #[cfg(not(target_arch = "wasm32"))]
    pub fn new_http2(url: &str) -> crate::Result<Self> {
        let client = reqwest::Client::builder()
            .http2_prior_knowledge()
            .tcp_nodelay(true)
            .build()
            .map_err(|e| ClientError::HttpClient { reason: e.to_string() })?;
        Self::with_client(client, url, RetryPolicy::default())
    }

    /// A source sharing an existing client (and its pool).
    ///
    /// # Errors
    /// [`ClientError::BadUrl`] if the URL is not http(s).
    pub fn with_client(client: reqwest::Client, url: &str, retry: RetryPolicy) -> crate::Result<Self> {
        let bad = |reason: String| ClientError::BadUrl { url: url.to_owned(), reason };
        let url = reqwest::Url::parse(url).map_err(|e| bad(e.to_string()))?;
        if !matches!(url.scheme(), "http" | "https") {
            return Err(bad("only http and https URLs".into()));
        }
        Ok(Self {
            client,
            url,
            retry: RetryPolicy { attempts: retry.attempts.max(1), ..retry },
            known: Mutex::default(),
            stats: Arc::default(),
        })
    }

    /// The URL.
    pub fn url(&self) -> &reqwest::Url {
        &self.url
    }

    /// Request and byte counters.
    pub fn stats(&self) -> &HttpStats {
        &self.stats
    }

    /// The counters, shared: they stay readable after the source is handed to a streamer.
    pub fn shared_stats(&self) -> Arc<HttpStats> {
        self.stats.clone()
    }

    /// Counts into `stats` (shared by several sources, e.g. a manifest's archives).
    #[must_use]
    pub fn with_stats(mut self, stats: Arc<HttpStats>) -> Self {
        self.stats = stats;
        self
    }

    /// The ETag the archive had when first read.
    pub fn etag(&self) -> Option<String> {
        self.known().etag.clone()
    }

    fn known(&self) -> std::sync::MutexGuard<'_, Known> {
        self.known.lock().unwrap_or_else(std::sync::PoisonError::into_inner)
    }

    /// Fetches `[offset, offset + len)`, retrying transient failures.
    async fn get(&self, offset: u64, len: u64) -> Result<Bytes> {
        if len == 0 {
            return Ok(Bytes::new());
        }
        let mut backoff = self.retry.first_backoff;
        let mut last = String::new();
        for attempt in 0..self.retry.attempts {
            if attempt > 0 {
                self.stats.retries.fetch_add(1, Relaxed);
                tracing::debug!(url = %self.url, offset, len, "retrying after: {last}");
                sleep(backoff).await;
                backoff *= 2;
            }
            match self.attempt(offset, len).await? {
                Attempt::Done(bytes) => return Ok(bytes),
                Attempt::Retry(why) => last = why,
            }
        }
        Err(source_error(offset, len, format!("{}: {last} (after {} attempts)", self.url, self.retry.attempts)))
    }

    async fn attempt(&self, offset: u64, len: u64) -> Result<Attempt> {
        let last_byte =
            offset.checked_add(len - 1).ok_or_else(|| source_error(offset, len, "range overflows".into()))?;
        let etag = self.known().etag.clone();
        let mut request = self.client.get(self.url.clone()).header(RANGE, format!("bytes={offset}-{last_byte}"));
        #[cfg(not(target_arch = "wasm32"))]
        {
            request = request.timeout(self.retry.timeout);
        }
        if let Some(etag) = &etag {
            request = request.header(IF_MATCH, etag);
        }
        self.stats.requests.fetch_add(1, Relaxed);
        let response = match request.send().await {
            Ok(r) => r,
            Err(e) => return Ok(Attempt::Retry(e.to_string())),
        };
        if let Some(retry) = self.check_status(response.status(), etag, offset, len)? {
            return Ok(retry);
        }
        let (start, end) = self.check_range(response.headers(), offset, len)?;
        let body = match response.bytes().await {
            Ok(b) => b,
            Err(e) => return Ok(Attempt::Retry(format!("body: {e}"))),
        };
        self.stats.bytes.fetch_add(body.len() as u64, Relaxed);
        if body.len() as u64 != end - start + 1 {
            return Ok(Attempt::Retry(format!("truncated body: {} of {} bytes", body.len(), end - start + 1)));
        }
        Ok(Attempt::Done(body))
    }

    /// What a response's status means: go on (206), retry (5xx, 429, 408), or an error
    /// (the archive changed, the range is outside it, no Range support).
    fn check_status(&self, status: StatusCode, etag: Option<String>, offset: u64, len: u64) -> Result<Option<Attempt>> {
        if status == StatusCode::PRECONDITION_FAILED {
            return Err(Error::Changed {
                what: format!("{}: ETag {} no longer matches", self.url, etag.unwrap_or_default()),
            });
        }
        if status.is_server_error() || status == StatusCode::TOO_MANY_REQUESTS || status == StatusCode::REQUEST_TIMEOUT
        {
            return Ok(Some(Attempt::Retry(format!("HTTP {status}"))));
        }
        if status == StatusCode::RANGE_NOT_SATISFIABLE {
            return Err(Error::OutOfBounds {
                what: format!("{} range", self.url),
                offset,
                len,
                limit_name: "remote archive",
                limit: self.known().len.unwrap_or(0),
            });
        }
        if status != StatusCode::PARTIAL_CONTENT {
            let why = if status == StatusCode::OK {
                "the server ignores Range requests".into()
            } else {
                format!("HTTP {status}")
            };
            return Err(source_error(offset, len, format!("{}: {why}", self.url)));
        }
        Ok(None)
    }

    /// Checks a 206's Content-Range (the range asked for, clamped to the file) and ETag
    /// against what is known of the archive, learning its length and ETag on the first
    /// answer. Returns the first and last byte sent.
    fn check_range(&self, headers: &reqwest::header::HeaderMap, offset: u64, len: u64) -> Result<(u64, u64)> {
        let header =
            |name| headers.get(name).and_then(|v: &reqwest::header::HeaderValue| v.to_str().ok()).map(str::to_owned);
        let new_etag = header(ETAG);
        let content_range = header(CONTENT_RANGE).unwrap_or_default();
        let (start, end, total) = parse_content_range(&content_range)
            .ok_or_else(|| source_error(offset, len, format!("{}: bad Content-Range {content_range:?}", self.url)))?;
        {
            let mut known = self.known();
            if let (Some(old), Some(new)) = (&known.etag, &new_etag)
                && old != new
            {
                return Err(Error::Changed { what: format!("{}: ETag {old} -> {new}", self.url) });
            }
            if known.len.is_some_and(|l| l != total) {
                return Err(Error::Changed {
                    what: format!("{}: length {} -> {total}", self.url, known.len.unwrap_or(0)),
                });
            }
            known.len = Some(total);
            if known.etag.is_none() {
                known.etag = new_etag;
            }
        }
        let last_byte = offset + (len - 1);
        let expected_end = last_byte.min(total.saturating_sub(1));
        if start != offset || end != expected_end {
            return Err(source_error(
                offset,
                len,
                format!("{}: asked {offset}-{last_byte}, got {content_range}", self.url),
            ));
        }
        Ok((start, end))
    }

    /// Opens the archive: fetches the first 16 KiB (header, metadata, root) and learns the
    /// length and ETag. Later reads inside these bytes cost no request.
    async fn head(&self) -> Result<(u64, Bytes)> {
        {
            let known = self.known();
            if let (Some(len), Some(head)) = (known.len, &known.head) {
                return Ok((len, head.clone()));
            }
        }
        // A file shorter than 16 KiB comes back whole (the server clamps the range).
        let head = self.get(0, BOOTSTRAP_READ).await?;
        let len = self.known().len.unwrap_or(head.len() as u64);
        self.known().head = Some(head.clone());
        Ok((len, head))
    }
}

impl AsyncRangeSource for HttpSource {
    async fn size(&self) -> Result<u64> {
        self.head().await.map(|(len, _)| len)
    }

    async fn fetch(&self, offset: u64, len: u64) -> Result<Bytes> {
        let cached = self.known().head.clone();
        if let Some(head) = cached
            && let Some(end) = offset.checked_add(len).filter(|&e| e <= head.len() as u64)
        {
            // Inside the bootstrap bytes: no request.
            return Ok(head.slice(usize::try_from(offset).unwrap_or(0)..usize::try_from(end).unwrap_or(0)));
        }
        self.get(offset, len).await
    }

    fn forget(&self) {
        *self.known() = Known::default();
    }
}

/// `bytes START-END/TOTAL`.
fn parse_content_range(v: &str) -> Option<(u64, u64, u64)> {
    let rest = v.trim().strip_prefix("bytes ")?;
    let (range, total) = rest.split_once('/')?;
    let (start, end) = range.split_once('-')?;
    let (start, end, total) = (start.trim().parse().ok()?, end.trim().parse().ok()?, total.trim().parse().ok()?);
    (start <= end && end < total).then_some((start, end, total))
}

fn source_error(offset: u64, len: u64, reason: String) -> Error {
    Error::Source { offset, len, reason }
}

#[cfg(not(target_arch = "wasm32"))]
async fn sleep(d: Duration) {
    tokio::time::sleep(d).await;
}

#[cfg(target_arch = "wasm32")]
async fn sleep(d: Duration) {
    // A promise resolved by the browser's timer.
    let ms = i32::try_from(d.as_millis()).unwrap_or(i32::MAX);
    let promise = js_sys::Promise::new(&mut |resolve, _reject| {
        let scheduled = web_sys::window()
            .is_some_and(|w| w.set_timeout_with_callback_and_timeout_and_arguments_0(&resolve, ms).is_ok());
        if !scheduled {
            // No window (a worker without timers): retry at once.
            let _ = resolve.call0(&wasm_bindgen::JsValue::NULL);
        }
    });
    let _ = wasm_bindgen_futures::JsFuture::from(promise).await;
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn content_range_is_parsed_strictly() {
        assert_eq!(parse_content_range("bytes 0-9/100"), Some((0, 9, 100)));
        assert_eq!(parse_content_range("bytes 10-9/100"), None);
        assert_eq!(parse_content_range("bytes 0-100/100"), None);
        assert_eq!(parse_content_range("bytes */100"), None);
        assert_eq!(parse_content_range("0-9/100"), None);
    }
}
