//! What every request goes through, outside the router, in one cheap step: CORS, the
//! access rules ([`crate::access`]), the metrics, and a debug span when debug logging is
//! on.
//!
//! One hand-written service instead of a stack of general layers (tower-http's CORS and
//! trace layers, a `from_fn` middleware reading the matched path): they cost more per
//! request than the archive handler itself (a third of the server's CPU time under load,
//! measured with `scripts/bench-server.sh`). Here a simple request costs a clock read, a
//! path split and a few relaxed atomic increments on the thread's own metrics shard.

use std::convert::Infallible;
use std::future::Future;
use std::pin::Pin;
use std::task::{Context, Poll};
use std::time::Instant;

use axum::body::Body;
use axum::http::header::{
    ACCESS_CONTROL_ALLOW_HEADERS, ACCESS_CONTROL_ALLOW_METHODS, ACCESS_CONTROL_ALLOW_ORIGIN,
    ACCESS_CONTROL_EXPOSE_HEADERS, ACCESS_CONTROL_MAX_AGE, ACCESS_CONTROL_REQUEST_METHOD, AUTHORIZATION, CACHE_CONTROL,
    CONNECTION, CONTENT_LENGTH, HeaderValue, ORIGIN, REFERER,
};
use axum::http::{Method, Request, StatusCode};
use axum::response::Response;
use tower::Service;
use tracing::Instrument;

use crate::access::{Denied, Grant, Presented};
use crate::app::AppState;
use crate::route::{READ_HEADERS, Route};

/// Methods a browser may use (preflight answer).
const ALLOW_METHODS: HeaderValue = HeaderValue::from_static("GET, HEAD, POST, OPTIONS");
/// Response headers a page may read.
const EXPOSE_HEADERS: HeaderValue = HeaderValue::from_static(
    "etag, content-range, content-length, content-encoding, accept-ranges, last-modified, \
     x-terrastream-fallback-lod, x-terrastream-archive-etag",
);
/// How long a browser may cache a preflight answer (seconds).
const MAX_AGE: HeaderValue = HeaderValue::from_static("86400");

/// Rules on a request's access ([`crate::access::Access::decide`]), for both HTTP paths:
/// what it may see, or the answer refusing it.
pub(crate) fn admit(state: &AppState, presented: &Presented<'_>) -> Result<Grant, Denied> {
    state.access.decide_now(presented)
}

/// What an allowed request's answer gets from its grant: a private archive's answers to a
/// key sent in a header are kept out of shared caches (they key by URL, which holds no
/// credential); a credential in the URL keys the cache itself.
pub(crate) fn mark_private<B>(state: &AppState, grant: &Grant, response: &mut axum::http::Response<B>) {
    if grant.private && grant.by_header && response.headers().contains_key(CACHE_CONTROL) {
        response.headers_mut().insert(CACHE_CONTROL, state.private_cache_control.clone());
    }
}

/// What every answer gets on its way out, whichever path served it: the CORS headers, and
/// its line in the metrics under `route`.
pub(crate) fn finish<B>(state: &AppState, route: Route, started: Instant, response: &mut axum::http::Response<B>) {
    // On every response, not only to requests with an `Origin`: a shared cache may hand
    // one answer to both kinds of client (no `Vary: Origin` needed).
    let h = response.headers_mut();
    h.insert(ACCESS_CONTROL_ALLOW_ORIGIN, HeaderValue::from_static("*"));
    h.insert(ACCESS_CONTROL_EXPOSE_HEADERS, EXPOSE_HEADERS);
    let bytes = h.get(CONTENT_LENGTH).and_then(|v| v.to_str().ok()).and_then(|v| v.parse().ok()).unwrap_or(0);
    state.metrics.record(route, response.status().as_u16(), bytes, started.elapsed());
}

/// Wraps the router: see the module's documentation.
#[derive(Clone)]
pub struct Edge<S> {
    inner: S,
    state: AppState,
}

impl<S> Edge<S> {
    /// `inner` with CORS, metrics and spans around it.
    pub fn new(inner: S, state: AppState) -> Self {
        Self { inner, state }
    }

    /// The application state it answers with.
    pub(crate) fn state(&self) -> &AppState {
        &self.state
    }
}

impl<S, B> Service<Request<B>> for Edge<S>
where
    S: Service<Request<B>, Response = Response, Error = Infallible> + Send + 'static,
    S::Future: Send + 'static,
{
    type Response = Response;
    type Error = Infallible;
    type Future = Pin<Box<dyn Future<Output = Result<Response, Infallible>> + Send>>;

    fn poll_ready(&mut self, cx: &mut Context<'_>) -> Poll<Result<(), Infallible>> {
        self.inner.poll_ready(cx)
    }

    fn call(&mut self, mut req: Request<B>) -> Self::Future {
        let started = Instant::now();
        let route = Route::of(req.uri().path());
        let state = self.state.clone();
        // A CORS preflight is answered here, for any path: it carries no credential and
        // reveals nothing.
        let preflight = req.method() == Method::OPTIONS
            && req.headers().contains_key(ORIGIN)
            && req.headers().contains_key(ACCESS_CONTROL_REQUEST_METHOD);
        if preflight {
            let mut response = preflight_answer();
            finish(&state, route, started, &mut response);
            return Box::pin(std::future::ready(Ok(response)));
        }
        let grant = if state.access.enabled() {
            let h = req.headers();
            let presented = Presented {
                path: req.uri().path(),
                query: req.uri().query(),
                authorization: h.get(AUTHORIZATION).map(HeaderValue::as_bytes),
                origin: h.get(ORIGIN).map(HeaderValue::as_bytes),
                referer: h.get(REFERER).map(HeaderValue::as_bytes),
            };
            match admit(&state, &presented) {
                Ok(grant) => grant,
                Err(refused) => {
                    let mut response = refused.answer().map(Body::new);
                    // HTTP/1.1 without a pace: the refused request ends its connection, as
                    // on the lean path.
                    if req.version() <= axum::http::Version::HTTP_11 && !state.access.paced() {
                        response.headers_mut().insert(CONNECTION, HeaderValue::from_static("close"));
                    }
                    // Held for its turn among refusals (a flood's connections wait here).
                    return Box::pin(async move {
                        state.access.wait_turn().await;
                        finish(&state, route, started, &mut response);
                        Ok(response)
                    });
                }
            }
        } else {
            Grant::default()
        };
        let finish = {
            let grant = grant.clone();
            move |mut response: Response| {
                mark_private(&state, &grant, &mut response);
                finish(&state, route, started, &mut response);
                Ok(response)
            }
        };
        req.extensions_mut().insert(grant);
        if tracing::enabled!(tracing::Level::DEBUG) {
            // The path and the query with any credential's value hidden: keys never reach
            // the logs.
            let query = req.uri().query().map(crate::access::redacted).unwrap_or_default();
            let span = tracing::debug_span!(
                "request",
                method = %req.method(),
                path = %req.uri().path(),
                query = %query,
                version = ?req.version()
            );
            let answer = self.inner.call(req);
            return Box::pin(
                async move {
                    let response = answer.await?;
                    tracing::debug!(status = response.status().as_u16(), latency = ?started.elapsed(), "answered");
                    finish(response)
                }
                .instrument(span),
            );
        }
        let answer = self.inner.call(req);
        Box::pin(async move { finish(answer.await?) })
    }
}

/// The answer to a CORS preflight: the methods and request headers a page may use (those
/// the handlers read, and `Authorization` for keys).
fn preflight_answer() -> Response {
    let mut response = Response::new(Body::empty());
    *response.status_mut() = StatusCode::NO_CONTENT;
    let h = response.headers_mut();
    h.insert(ACCESS_CONTROL_ALLOW_METHODS, ALLOW_METHODS);
    let allowed = READ_HEADERS
        .iter()
        .map(axum::http::HeaderName::as_str)
        .chain(["content-type", "authorization"])
        .collect::<Vec<_>>()
        .join(", ");
    if let Ok(allowed) = HeaderValue::from_str(&allowed) {
        h.insert(ACCESS_CONTROL_ALLOW_HEADERS, allowed);
    }
    h.insert(ACCESS_CONTROL_MAX_AGE, MAX_AGE);
    response
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn pages_may_read_the_protocol_headers() {
        let exposed = EXPOSE_HEADERS;
        let exposed = exposed.to_str().unwrap();
        for name in
            [terrastream_format::protocol::ARCHIVE_ETAG_HEADER, terrastream_format::protocol::FALLBACK_LOD_HEADER]
        {
            assert!(exposed.contains(name), "{exposed}");
        }
    }
}
