//! The axum application: routes, handlers, errors. `app(state)` is kept apart from
//! binding and serving so tests drive it with `oneshot`.

use std::sync::Arc;

use axum::Router;
use axum::body::Body;
use axum::extract::{Extension, Path, Request, State};
use axum::http::header::{
    ACCEPT, ACCEPT_ENCODING, ACCEPT_RANGES, CACHE_CONTROL, CONTENT_ENCODING, CONTENT_LENGTH, CONTENT_RANGE,
    CONTENT_TYPE, ETAG, HeaderName, HeaderValue, LAST_MODIFIED, RANGE, VARY,
};
use axum::http::{HeaderMap, Method, StatusCode};
use axum::response::{Html, IntoResponse, Response};
use axum::routing::get;
use bytes::Bytes;
use terrastream_format::{Error as PackError, PayloadCompression, TileKey, protocol};
use tower_http::timeout::TimeoutLayer;

use crate::access::{Access, AccessError, Grant};
use crate::body::Payload;
use crate::catalog::{Catalog, Served};
use crate::config::ServerConfig;
use crate::edge::Edge;
use crate::metrics::Metrics;
use crate::range::{Precondition, RangeOutcome, if_none_match, if_range_allows, parse_range, preconditions};
use crate::route::Route;

/// A response whose body is slices of the archive (or small texts): what the archive and
/// tile routes answer, sent by hyper (as a boxed body) or by the lean HTTP/1.1 path.
pub(crate) type Answer = axum::http::Response<Payload>;

const OCTET_STREAM: HeaderValue = HeaderValue::from_static("application/octet-stream");

/// Response header naming the nearest coarser LOD that exists for a missing tile.
pub const FALLBACK_LOD: HeaderName = HeaderName::from_static(protocol::FALLBACK_LOD_HEADER);
/// Header on metadata and tile responses: the strong ETag of the archive file they come
/// from ([`protocol::ARCHIVE_ETAG_HEADER`]).
pub const ARCHIVE_ETAG: HeaderName = HeaderName::from_static(protocol::ARCHIVE_ETAG_HEADER);

/// Shared state of all handlers: one `Arc`, so the per-request clone (by each extractor)
/// is one atomic increment rather than one per field.
#[derive(Clone, Debug)]
pub struct AppState(Arc<AppInner>);

impl std::ops::Deref for AppState {
    type Target = AppInner;
    fn deref(&self) -> &AppInner {
        &self.0
    }
}

/// What [`AppState`] holds.
#[derive(Debug)]
pub struct AppInner {
    /// Served archives.
    pub catalog: Arc<Catalog>,
    /// Request counters.
    pub metrics: Arc<Metrics>,
    /// Settings.
    pub config: Arc<ServerConfig>,
    /// `Cache-Control` value, validated once.
    pub cache_control: HeaderValue,
    /// The same for a private archive's answers to a key sent in a header (`private`:
    /// no shared cache keeps them).
    pub private_cache_control: HeaderValue,
    /// The web routes' tile-making threads and made tiles.
    pub web: Arc<crate::web::WebState>,
    /// Who may read what ([`crate::access`]).
    pub access: Arc<Access>,
}

impl AppState {
    /// State for a configuration; call `catalog.reload()` to load the archives. Access
    /// rules that cannot be read (a damaged keys file, a missing secret) fail closed:
    /// every request is refused, and the reason logged; [`AppState::try_new`] says it.
    pub fn new(config: ServerConfig) -> Self {
        Self::try_new(config.clone()).unwrap_or_else(|e| {
            tracing::error!("settings: {e}: every request is refused");
            let shut = crate::access::Rules { private_all: true, ..crate::access::Rules::default() };
            let access = Access::new(shut).unwrap_or_default();
            Self::with_access(config, access, terrastream_views::relief::ColorTable::default(), None)
        })
    }

    /// State for a configuration, its files read (keys file, signing secret, colour table).
    ///
    /// # Errors
    /// [`StartError`] naming the file at fault.
    pub fn try_new(config: ServerConfig) -> Result<Self, StartError> {
        let table = match &config.color_relief_table {
            // Read once, at the start: a table that cannot be read is the operator's to fix.
            Some(path) => {
                let bad = |reason: String| StartError::ColorTable { path: path.clone(), reason };
                let text = std::fs::read_to_string(path).map_err(|e| bad(e.to_string()))?;
                terrastream_views::relief::ColorTable::parse(&text).map_err(bad)?
            }
            None => terrastream_views::relief::ColorTable::default(),
        };
        let access = Access::new(config.access_rules())?;
        let fonts = match &config.fonts {
            Some(dir) => {
                let set = terrastream_views::glyphs::FontSet::load(dir)?;
                for (file, why) in set.skipped() {
                    tracing::warn!("{}: not a font ({why}): skipped", file.display());
                }
                tracing::info!(fonts = set.names().count(), "{}: fonts for labels", dir.display());
                Some(Arc::new(crate::web::fonts::Fonts::new(set)))
            }
            None => None,
        };
        Ok(Self::with_access(config, access, table, fonts))
    }

    fn with_access(
        config: ServerConfig,
        access: Access,
        table: terrastream_views::relief::ColorTable,
        fonts: Option<Arc<crate::web::fonts::Fonts>>,
    ) -> Self {
        Self(Arc::new(AppInner {
            access: Arc::new(access),
            catalog: Arc::new(Catalog::new(config.paths.clone()).with_leaf_cache(config.leaf_cache)),
            metrics: Arc::new(Metrics::default()),
            cache_control: HeaderValue::from_str(&config.cache_control)
                .unwrap_or_else(|_| HeaderValue::from_static("no-cache")),
            private_cache_control: HeaderValue::from_str(&private_cache_control(&config.cache_control))
                .unwrap_or_else(|_| HeaderValue::from_static("private, no-cache")),
            web: Arc::new(crate::web::WebState {
                color_table: table,
                fonts,
                ..crate::web::WebState::new(
                    config.web_threads,
                    config.web_queue,
                    config.web_cache_bytes,
                    config.web_decoded_bytes,
                )
            }),
            config: Arc::new(config),
        }))
    }
}

/// Why a server's state cannot be made from its settings.
#[derive(Debug, thiserror::Error)]
pub enum StartError {
    /// The access rules' files.
    #[error(transparent)]
    Access(#[from] AccessError),
    /// The fonts folder of labels' glyphs.
    #[error(transparent)]
    Fonts(#[from] terrastream_views::glyphs::GlyphError),
    /// The colour table of `color-relief` tiles.
    #[error("{path}: {reason}")]
    ColorTable {
        /// The file.
        path: std::path::PathBuf,
        /// Why it is not a table.
        reason: String,
    },
}

/// `Cache-Control` for answers only the asker may keep: `public` becomes `private`.
fn private_cache_control(value: &str) -> String {
    let kept: Vec<&str> =
        value.split(',').map(str::trim).filter(|d| !d.eq_ignore_ascii_case("public") && !d.is_empty()).collect();
    std::iter::once("private").chain(kept).collect::<Vec<_>>().join(", ")
}

/// Errors of the handlers, each with its status. 5xx bodies stay generic.
#[derive(Debug, thiserror::Error)]
pub enum AppError {
    /// 404 with a reason.
    #[error("{0}")]
    NotFound(String),
    /// 400 with a reason.
    #[error("{0}")]
    BadRequest(String),
    /// 500; the detail is logged, never sent.
    #[error("{0}")]
    Internal(String),
}

impl AppError {
    /// The error as an answer: its status and a plain-text reason.
    pub(crate) fn into_answer(self) -> Answer {
        let (status, text) = match self {
            Self::NotFound(m) => (StatusCode::NOT_FOUND, Payload::from(m)),
            Self::BadRequest(m) => (StatusCode::BAD_REQUEST, Payload::from(m)),
            Self::Internal(m) => {
                tracing::error!("internal error: {m}");
                (StatusCode::INTERNAL_SERVER_ERROR, Payload::from("internal server error"))
            }
        };
        let mut answer = Answer::new(text);
        *answer.status_mut() = status;
        answer.headers_mut().insert(CONTENT_TYPE, HeaderValue::from_static("text/plain; charset=utf-8"));
        answer
    }
}

impl IntoResponse for AppError {
    fn into_response(self) -> Response {
        self.into_answer().map(Body::new)
    }
}

/// The application as an axum [`Router`] (for `oneshot` tests, extra layers, or nesting
/// in another application): [`service`] behind a fallback.
pub fn app(state: AppState) -> Router {
    Router::new().fallback_service(service(state))
}

/// The application as `serve` runs it: the routes wrapped in CORS, metrics and request
/// spans ([`Edge`]).
///
/// Only `/view` waits on anything (the player's gzip, on a blocking thread): it alone
/// carries a timeout. Every other handler answers from memory without waiting; slow
/// clients are cut off by the connection's header-read timeout (see `serve`).
pub fn service(state: AppState) -> Edge<Router> {
    let timeout = TimeoutLayer::with_status_code(StatusCode::REQUEST_TIMEOUT, state.config.request_timeout());
    // One handler per route, mounted on the route's template (the match makes a new
    // route without a handler a compile error).
    let router = Route::ALL.into_iter().fold(Router::new(), |router, route| {
        let handler = match route {
            Route::Index => get(index),
            Route::Health => get(|| async { "ok\n" }),
            Route::Metrics => get(metrics),
            Route::Auth => get(auth),
            Route::Archive => get(archive_bytes),
            Route::Metadata => get(metadata),
            Route::Tile => get(tile),
            Route::View => get(view).layer(timeout),
            Route::TileJson => get(crate::web::elevation_tilejson),
            Route::LayerTileJson => get(crate::web::layer_tilejson),
            Route::WebTile => get(crate::web::web_tile),
            Route::Elevation => get(crate::web::elevation_get).post(crate::web::elevation_post),
            Route::LayerJson => get(crate::web::quantized::layer_json),
            Route::TerrainTile => get(crate::web::quantized::terrain_tile),
            Route::Contours => get(crate::web::contours::tile),
            Route::Fonts => get(crate::web::fonts::glyphs),
            Route::Other => return router,
        };
        router.route(route.template(), handler)
    });
    let router = router.with_state(state.clone());
    Edge::new(router, state)
}

fn archive(state: &AppState, name: &str) -> Result<Arc<Served>, AppError> {
    state.catalog.get(name).ok_or_else(|| AppError::NotFound(format!("no archive named {name:?}\n")))
}

fn header(v: &str) -> HeaderValue {
    HeaderValue::from_str(v).unwrap_or_else(|_| HeaderValue::from_static(""))
}

/// `GET|HEAD /{name}.tspack`: the archive's bytes with Range and conditional requests;
/// `/{name}.json` a manifest.
async fn archive_bytes(State(state): State<AppState>, Path(file): Path<String>, req: Request) -> Response {
    // The request by value, not a `HeaderMap` extractor: that one clones every header.
    if let Some(name) = file.strip_suffix(".json") {
        let grant = req.extensions().get::<Grant>();
        return manifest_answer(&state, name, req.headers(), grant)
            .unwrap_or_else(AppError::into_answer)
            .map(Body::new);
    }
    archive_answer(&state, &file, req.method(), req.headers()).map(Body::new)
}

/// The answer of `GET|HEAD /{file}`, for the router and for the lean HTTP/1.1 path. Reads
/// no request header but those in `route::READ_HEADERS`: the lean path passes no others.
#[tracing::instrument(level = "debug", skip_all, fields(file = %file))]
pub(crate) fn archive_answer(state: &AppState, file: &str, method: &Method, headers: &HeaderMap) -> Answer {
    archive_range(state, file, method, headers).unwrap_or_else(AppError::into_answer)
}

fn archive_range(state: &AppState, file: &str, method: &Method, headers: &HeaderMap) -> Result<Answer, AppError> {
    let name = file.strip_suffix(".tspack").ok_or_else(|| AppError::NotFound("not found\n".into()))?;
    let served = archive(state, name)?;
    let bytes = served.bytes();
    let len = bytes.len() as u64;
    // Headers inserted into a map sized once (CORS adds two): a builder chain re-checks and
    // grows the map header by header, on the hottest route.
    let mut h = HeaderMap::with_capacity(12);
    h.insert(ETAG, served.etag_header.clone());
    h.insert(LAST_MODIFIED, served.last_modified_header.clone());
    h.insert(ACCEPT_RANGES, HeaderValue::from_static("bytes"));
    h.insert(CACHE_CONTROL, state.cache_control.clone());
    let safe = method == Method::GET || method == Method::HEAD;
    match preconditions(headers, &served.etag, served.modified, safe) {
        Precondition::NotModified => return Ok(answer(StatusCode::NOT_MODIFIED, h, Payload::empty())),
        Precondition::Failed => return Ok(answer(StatusCode::PRECONDITION_FAILED, h, Payload::empty())),
        Precondition::Proceed => {}
    }
    let outcome = match headers.get(RANGE) {
        Some(range) if if_range_allows(headers, &served.etag, served.modified) => {
            parse_range(range.as_bytes(), len, state.config.max_ranges)
        }
        _ => RangeOutcome::Full,
    };
    let to_usize = |r: &std::ops::Range<u64>| {
        // Ranges are clamped to the file's length, which is a usize (it is mapped).
        usize::try_from(r.start).unwrap_or(usize::MAX)..usize::try_from(r.end).unwrap_or(usize::MAX)
    };
    let (status, body) = match outcome {
        RangeOutcome::Full => {
            h.insert(CONTENT_TYPE, OCTET_STREAM);
            (StatusCode::OK, Payload::from(bytes.clone()))
        }
        RangeOutcome::Unsatisfiable => {
            h.insert(CONTENT_RANGE, header(&format!("bytes */{len}")));
            (StatusCode::RANGE_NOT_SATISFIABLE, Payload::empty())
        }
        RangeOutcome::Partial(ranges) if ranges.len() == 1 => {
            let r = &ranges[0];
            h.insert(CONTENT_TYPE, OCTET_STREAM);
            h.insert(CONTENT_RANGE, header(&format!("bytes {}-{}/{len}", r.start, r.end - 1)));
            (StatusCode::PARTIAL_CONTENT, Payload::from(bytes.slice(to_usize(r))))
        }
        RangeOutcome::Partial(ranges) => {
            let boundary = format!("tspack{}", served.etag.trim_matches('"'));
            let mut chunks = Vec::with_capacity(ranges.len() * 2 + 1);
            for r in &ranges {
                chunks.push(Bytes::from(format!(
                    "\r\n--{boundary}\r\nContent-Type: application/octet-stream\r\nContent-Range: bytes {}-{}/{len}\r\n\r\n",
                    r.start,
                    r.end - 1
                )));
                chunks.push(bytes.slice(to_usize(r)));
            }
            chunks.push(Bytes::from(format!("\r\n--{boundary}--\r\n")));
            h.insert(CONTENT_TYPE, header(&format!("multipart/byteranges; boundary={boundary}")));
            (StatusCode::PARTIAL_CONTENT, Payload::chunks(chunks))
        }
    };
    h.insert(CONTENT_LENGTH, HeaderValue::from(body.len()));
    Ok(answer(status, h, body))
}

/// `GET|HEAD /{name}.json`: a manifest, as found on disk (its archives are served beside
/// it by name; clients read them with Range requests), its archives' URLs carrying the
/// request's credential when it came in the query.
fn manifest_answer(
    state: &AppState,
    name: &str,
    headers: &HeaderMap,
    grant: Option<&Grant>,
) -> Result<Answer, AppError> {
    let served =
        state.catalog.manifest(name).ok_or_else(|| AppError::NotFound(format!("no manifest named {name:?}\n")))?;
    let (bytes, etag) = match grant.filter(|g| g.carried().is_some()) {
        Some(grant) => {
            let mut doc: serde_json::Value =
                serde_json::from_slice(&served.bytes).map_err(|e| AppError::Internal(e.to_string()))?;
            for part in doc["archives"].as_array_mut().into_iter().flatten() {
                if let Some(url) = part["url"].as_str() {
                    part["url"] = grant.carry(url).into();
                }
            }
            let bytes = Bytes::from(serde_json::to_vec(&doc).map_err(|e| AppError::Internal(e.to_string()))?);
            let etag = format!("\"{:016x}\"", xxhash_rust::xxh3::xxh3_64(&bytes));
            (bytes, etag)
        }
        None => (served.bytes.clone(), served.etag.clone()),
    };
    let mut h = HeaderMap::with_capacity(6);
    h.insert(ETAG, header(&etag));
    // Revalidated on every use: a republished manifest must be seen at once.
    h.insert(CACHE_CONTROL, HeaderValue::from_static("no-cache"));
    if if_none_match(headers, &etag) {
        return Ok(answer(StatusCode::NOT_MODIFIED, h, Payload::empty()));
    }
    h.insert(CONTENT_TYPE, HeaderValue::from_static("application/json"));
    h.insert(CONTENT_LENGTH, HeaderValue::from(bytes.len()));
    Ok(answer(StatusCode::OK, h, Payload::from(bytes)))
}

/// An answer of these parts.
fn answer(status: StatusCode, headers: HeaderMap, body: Payload) -> Answer {
    let mut answer = Answer::new(body);
    *answer.status_mut() = status;
    *answer.headers_mut() = headers;
    answer
}

fn empty(builder: axum::http::response::Builder) -> Response {
    builder.body(Body::empty()).unwrap_or_default()
}

/// `GET /{name}/metadata`.
#[tracing::instrument(level = "debug", skip_all, fields(name = %name))]
async fn metadata(
    State(state): State<AppState>,
    Path(name): Path<String>,
    headers: HeaderMap,
) -> Result<Response, AppError> {
    let served = archive(&state, &name)?;
    let etag = format!("\"{}-m\"", served.etag.trim_matches('"'));
    let builder = Response::builder()
        .header(ETAG, header(&etag))
        .header(ARCHIVE_ETAG, served.etag_header.clone())
        .header(CACHE_CONTROL, state.cache_control.clone());
    if preconditions(&headers, &etag, served.modified, true) == Precondition::NotModified {
        return Ok(empty(builder.status(StatusCode::NOT_MODIFIED)));
    }
    let json = serde_json::to_vec(served.reader.metadata()).map_err(|e| AppError::Internal(e.to_string()))?;
    builder
        .header(CONTENT_TYPE, "application/json")
        .body(Body::from(json))
        .map_err(|e| AppError::Internal(e.to_string()))
}

/// `GET /{name}/{layer}/{lod}/{x}/{y}`: one tile; the layer by name or index.
async fn tile(
    State(state): State<AppState>,
    Path((name, layer, lod, x, y)): Path<(String, String, u8, u32, u32)>,
    req: Request,
) -> Response {
    tile_answer(&state, &name, &layer, TileAt { lod, x, y }, req.headers()).map(Body::new)
}

/// A tile as a request's path names it, beside its layer's name: the layer is resolved
/// against the archive's metadata before the tile becomes a [`TileKey`].
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub(crate) struct TileAt {
    /// LOD, 0 the finest.
    pub(crate) lod: u8,
    /// Column.
    pub(crate) x: u32,
    /// Row.
    pub(crate) y: u32,
}

/// The answer of `GET|HEAD /{name}/{layer}/{lod}/{x}/{y}`, for the router and for the lean
/// HTTP/1.1 path. Reads no request header but those in `route::READ_HEADERS`.
#[tracing::instrument(level = "debug", skip_all, fields(name = %name, layer = %layer, lod = at.lod, x = at.x, y = at.y))]
pub(crate) fn tile_answer(state: &AppState, name: &str, layer: &str, at: TileAt, headers: &HeaderMap) -> Answer {
    tile_located(state, name, layer, at, headers).unwrap_or_else(AppError::into_answer)
}

fn tile_located(
    state: &AppState,
    name: &str,
    layer: &str,
    TileAt { lod, x, y }: TileAt,
    headers: &HeaderMap,
) -> Result<Answer, AppError> {
    let served = archive(state, name)?;
    let meta = served.reader.metadata();
    let index = meta
        .resolve_layer(layer)
        .ok_or_else(|| AppError::NotFound(format!("archive {name:?} has no layer {layer:?}\n")))?;
    let info = &meta.layers[usize::from(index)];
    let key = TileKey::new(index, lod, x, y).map_err(|e| AppError::BadRequest(format!("{e}\n")))?;
    if !info.contains(key) {
        let (nx, ny) = info.grid_at(lod);
        return Err(AppError::BadRequest(format!(
            "tile ({lod}, {x}, {y}) is outside layer {:?}: {} LODs, {nx}x{ny} tiles at LOD {lod}\n",
            info.name, info.num_lods
        )));
    }
    let zstd_ok = info.compression == PayloadCompression::Zstd && accepts(headers, "zstd");
    let etag = format!("\"{}-{index}-{lod}-{x}-{y}{}\"", served.etag.trim_matches('"'), if zstd_ok { "z" } else { "" });
    let mut h = HeaderMap::with_capacity(12);
    h.insert(ETAG, header(&etag));
    h.insert(ARCHIVE_ETAG, served.etag_header.clone());
    h.insert(CACHE_CONTROL, state.cache_control.clone());
    h.insert(VARY, HeaderValue::from_static("Accept-Encoding"));
    // Locate first: a revalidation (304) costs no read and no checksum of the tile.
    match served.reader.locate(key) {
        Ok(Some(location)) => {
            if preconditions(headers, &etag, served.modified, true) == Precondition::NotModified {
                return Ok(answer(StatusCode::NOT_MODIFIED, h, Payload::empty()));
            }
            let stored =
                served.tile_payload(&location).map_err(|e| AppError::Internal(format!("archive {name:?}: {e}")))?;
            let body = match info.compression {
                PayloadCompression::None => stored,
                PayloadCompression::Zstd if zstd_ok => {
                    h.insert(CONTENT_ENCODING, HeaderValue::from_static("zstd"));
                    stored
                }
                // Zstd not accepted, or gradient-coded samples (which only this project
                // reads): the format's own bytes, as its media type says.
                PayloadCompression::Zstd | PayloadCompression::ZstdGradient => {
                    let raw = terrastream_format::payload_bytes(info, &stored, &format!("tile {key}"))
                        .map_err(|e| AppError::Internal(e.to_string()))?;
                    Bytes::from(raw.into_owned())
                }
            };
            h.insert(CONTENT_TYPE, HeaderValue::from_static(info.format.media_type()));
            h.insert(CONTENT_LENGTH, HeaderValue::from(body.len()));
            Ok(answer(StatusCode::OK, h, Payload::from(body)))
        }
        Ok(None) => {
            let fallback = key.parent().map(|p| served.reader.tile_or_coarser(p)).transpose();
            let fallback = fallback.map_err(|e| AppError::Internal(e.to_string()))?.flatten();
            if let Some((coarser, _)) = fallback {
                h.insert(FALLBACK_LOD, HeaderValue::from(u16::from(coarser.lod())));
            }
            Ok(answer(StatusCode::NOT_FOUND, h, Payload::from("tile missing\n")))
        }
        Err(err @ PackError::InvalidTile { .. }) => Err(AppError::BadRequest(format!("{err}\n"))),
        Err(err) => Err(AppError::Internal(format!("archive {name:?}: {err}"))),
    }
}

/// Does `Accept-Encoding` accept `coding` (named, and not with `q=0`)?
pub(crate) fn accepts(headers: &HeaderMap, coding: &str) -> bool {
    headers.get_all(ACCEPT_ENCODING).iter().filter_map(|v| v.to_str().ok()).flat_map(|v| v.split(',')).any(|c| {
        let mut parts = c.split(';');
        let name = parts.next().unwrap_or("").trim();
        let refused = parts.any(|p| p.trim().replace(' ', "") == "q=0");
        name.eq_ignore_ascii_case(coding) && !refused
    })
}

/// `GET /auth`: the access rules as the authority of a proxy in front of other files
/// (nginx's `auth_request` on static exports, a CDN's edge function): 204 when the
/// request's credential opens the URI in `X-Original-URI`, else the refusal (401, 403 or
/// 429 with its reason), exactly as this server would answer that URI itself.
async fn auth(State(state): State<AppState>, headers: HeaderMap) -> Response {
    use axum::http::header::{AUTHORIZATION, ORIGIN, REFERER};
    let Some(uri) = headers.get("x-original-uri").and_then(|v| v.to_str().ok()) else {
        return AppError::BadRequest("X-Original-URI: the URI to rule on is missing\n".into()).into_response();
    };
    let (path, query) = uri.split_once('?').map_or((uri, None), |(p, q)| (p, Some(q)));
    let presented = crate::access::Presented {
        path,
        query,
        authorization: headers.get(AUTHORIZATION).map(HeaderValue::as_bytes),
        origin: headers.get(ORIGIN).map(HeaderValue::as_bytes),
        referer: headers.get(REFERER).map(HeaderValue::as_bytes),
    };
    match crate::edge::admit(&state, &presented) {
        Ok(_) => StatusCode::NO_CONTENT.into_response(),
        Err(refused) => refused.answer().map(Body::new),
    }
}

/// `GET /metrics`.
async fn metrics(State(state): State<AppState>) -> Response {
    let text = state.metrics.render(state.catalog.list().len());
    ([(CONTENT_TYPE, "text/plain; version=0.0.4")], text).into_response()
}

/// `GET /`: the archives the request may see (its credential's, and the public ones), as
/// HTML for people or JSON for `Accept: application/json`; their URLs carry a credential
/// given in the query.
async fn index(State(state): State<AppState>, grant: Option<Extension<Grant>>, headers: HeaderMap) -> Response {
    let grant = grant.map(|g| g.0).unwrap_or_default();
    let visible = |name: &str| !state.access.enabled() || grant.opens(name, state.access.is_private(name));
    let archives: Vec<serde_json::Value> = state
        .catalog
        .list()
        .iter()
        .filter(|a| visible(&a.name))
        .map(|a| {
            let m = a.reader.metadata();
            serde_json::json!({
                "name": a.name,
                "url": grant.carry(&format!("/{}.tspack", a.name)),
                "metadata": grant.carry(&format!("/{}/metadata", a.name)),
                "view": grant.carry(&format!("/view/{}", a.name)),
                "bytes": a.bytes().len(),
                "etag": a.etag,
                "layers": m.layers.iter().map(|l| serde_json::json!({
                    "name": l.name, "kind": l.kind, "format": l.format,
                    "grid": [l.num_x_tiles, l.num_y_tiles], "num_lods": l.num_lods,
                })).collect::<Vec<_>>(),
            })
        })
        .collect();
    let wants_json = headers.get(ACCEPT).and_then(|v| v.to_str().ok()).is_some_and(|v| v.contains("application/json"));
    let manifests: Vec<serde_json::Value> = state
        .catalog
        .manifests()
        .iter()
        .filter(|m| visible(&m.name))
        .map(|m| {
            serde_json::json!({
                "name": m.name,
                "url": grant.carry(&format!("/{}.json", m.name)),
                "archives": m.manifest.archives.iter().map(|p| p.url.as_str()).collect::<Vec<_>>(),
            })
        })
        .collect();
    if wants_json {
        return axum::Json(serde_json::json!({ "archives": archives, "manifests": manifests })).into_response();
    }
    let mut html = String::from(
        "<!doctype html><meta charset=utf-8><title>terrastream</title><h1>terrastream archives</h1><table>\
         <tr><th>archive</th><th>size</th><th>layers</th><th>metadata</th><th>view</th></tr>",
    );
    for a in &archives {
        let name = escape(a["name"].as_str().unwrap_or(""));
        let link = |key: &str| escape(a[key].as_str().unwrap_or(""));
        let layers: Vec<String> = a["layers"]
            .as_array()
            .map(|ls| ls.iter().map(|l| escape(l["name"].as_str().unwrap_or(""))).collect())
            .unwrap_or_default();
        html.push_str(&format!(
            "<tr><td><a href=\"{}\">{name}.tspack</a></td><td>{}</td><td>{}</td><td><a href=\"{}\">json</a></td><td><a href=\"{}\">fly over it</a></td></tr>",
            link("url"),
            a["bytes"],
            layers.join(", "),
            link("metadata"),
            link("view")
        ));
    }
    html.push_str("</table>");
    Html(html).into_response()
}

/// `GET /view/{name}`: the webplayer's page for archive `name`, or one of the player's
/// own files (`/view/terrastream_web.js`, `/view/terrastream_web_bg.wasm`: the page
/// asks for them relative to itself).
#[tracing::instrument(level = "debug", skip_all, fields(name = %name))]
async fn view(
    State(state): State<AppState>,
    Path(name): Path<String>,
    grant: Option<Extension<Grant>>,
    headers: HeaderMap,
) -> Result<Response, AppError> {
    if let Some(asset) = crate::player::asset(&name) {
        let builder = Response::builder()
            .header(ETAG, header(&asset.etag))
            // Revalidated each time: a new binary serves a new player at once.
            .header(CACHE_CONTROL, HeaderValue::from_static("no-cache"))
            .header(VARY, HeaderValue::from_static("accept-encoding"));
        if if_none_match(&headers, &asset.etag) {
            return Ok(empty(builder.status(StatusCode::NOT_MODIFIED)));
        }
        let gzipped = if accepts(&headers, "gzip") { asset.gzipped().await } else { None };
        let builder = builder.status(StatusCode::OK).header(CONTENT_TYPE, asset.content_type);
        let response = match gzipped {
            Some(gz) => builder
                .header(CONTENT_ENCODING, HeaderValue::from_static("gzip"))
                .header(CONTENT_LENGTH, gz.len())
                .body(Body::from(gz.clone())),
            None => builder.header(CONTENT_LENGTH, asset.bytes.len()).body(Body::from(asset.bytes.clone())),
        };
        return response.map_err(|e| AppError::Internal(e.to_string()));
    }
    // An archive, or else a manifest of that name.
    let target = match (state.catalog.get(&name), state.catalog.manifest(&name)) {
        (Some(served), _) => format!("../{}.tspack", served.name),
        (None, Some(manifest)) => format!("../{}.json", manifest.name),
        (None, None) => return Err(AppError::NotFound(format!("no archive or manifest named {name:?}\n"))),
    };
    // The player fetches the archive with the page's credential, when it came in the query.
    let target = grant.map(|g| g.0).unwrap_or_default().carry(&target);
    let Some(page) = crate::player::page(&target) else {
        return Ok((
            StatusCode::NOT_IMPLEMENTED,
            "This terrastream binary was built without the webplayer: run scripts/build-player.sh, \
             then rebuild terrastream.\n",
        )
            .into_response());
    };
    Ok(([(CACHE_CONTROL, HeaderValue::from_static("no-cache"))], Html(page)).into_response())
}

/// Escapes text for HTML (content and double-quoted attributes).
pub(crate) fn escape(s: &str) -> String {
    s.replace('&', "&amp;").replace('<', "&lt;").replace('>', "&gt;").replace('"', "&quot;")
}
