//! The ecosystem's protocols over HTTP, so that the clients people already use read any
//! archive: TileJSON and Web Mercator XYZ tiles (MapLibre GL JS, deck.gl, OpenLayers), an
//! elevation API shaped like Open Topo Data's, quantized-mesh ([`quantized`]). The
//! products are made by `terrastream-views`; this module routes, caches and pools them.
//!
//! Routes (CORS as for the others):
//! - `GET /{name}/tiles.json`: the elevation as a `raster-dem` source;
//!   `GET /{name}/{layer}/tiles.json`: any layer (imagery as a `raster` source). Query:
//!   `encoding=terrarium|mapbox`, `format=webp|png`, `size=512|256`.
//! - `GET /{name}/xyz/{layer}/{z}/{x}/{y}.{webp|png}`: a tile (same query). Lossless
//!   WebP and 512 pixels by default: WebP is about two thirds of the PNG's bytes for
//!   terrain, and 512 is MapLibre's own `raster-dem` default, a quarter of the requests
//!   of 256 for the same screen. 404 outside the data.
//! - `GET|POST /v1/{name}`: heights at points (see [`elevation`]).

pub mod contours;
pub mod fonts;
pub mod pool;
pub mod quantized;
mod relief;

use axum::body::Body;
use axum::extract::{Extension, Path, Query, State};
use axum::http::header::{CACHE_CONTROL, CONTENT_LENGTH, CONTENT_TYPE, ETAG, HOST, RETRY_AFTER};
use axum::http::{HeaderMap, HeaderValue, StatusCode};
use axum::response::{IntoResponse, Response};
use bytes::Bytes;
use terrastream_format::LayerKind;
use terrastream_views::cache::Lru;
use terrastream_views::encode::{HeightEncoding, ImageFormat};
use terrastream_views::mercator::WebTile;
use terrastream_views::relief::Product;
use terrastream_views::resample::{self, Placed};
use terrastream_views::{WebTileRequest, elevation, make_tile_cached, tilejson};

use crate::access::Grant;
use crate::app::{ARCHIVE_ETAG, Answer, AppState};
use crate::body::Payload;
use crate::range::{Precondition, preconditions};
use pool::Pool;

/// What the web routes keep: the tile-making threads and the tiles made.
#[derive(Debug)]
pub struct WebState {
    /// The colour table of `color-relief` tiles.
    pub color_table: terrastream_views::relief::ColorTable,
    /// The threads that make tiles.
    pub pool: Pool,
    /// Tiles made, by what they are.
    pub made: Lru<MadeKey>,
    /// Archive tiles decoded for them.
    pub decoded: resample::DecodedCache,
    /// The fonts of map labels' glyphs (`serve --fonts`), if any.
    pub fonts: Option<std::sync::Arc<fonts::Fonts>>,
}

impl WebState {
    /// `threads` tile-making threads (0: the cores) behind `queue` waiting jobs, up to
    /// `cache_bytes` of made tiles and `decoded_bytes` of decoded archive tiles kept.
    pub fn new(threads: usize, queue: usize, cache_bytes: usize, decoded_bytes: usize) -> Self {
        Self {
            pool: Pool::new(threads, queue),
            made: Lru::new(cache_bytes),
            decoded: Lru::new(decoded_bytes),
            color_table: terrastream_views::relief::ColorTable::default(),
            fonts: None,
        }
    }
}

/// A made tile's identity: the archive's version (its strong ETag: a replaced archive
/// never serves its predecessor's tiles) and the tile.
#[derive(Clone, Debug, PartialEq, Eq, Hash)]
pub struct MadeKey {
    /// The archive's version: a hash of its strong ETag.
    archive: u64,
    request: Made,
}

/// What a made tile is.
#[derive(Clone, Debug, PartialEq, Eq, Hash)]
enum Made {
    /// A Web Mercator tile.
    Web(WebTileRequest),
    /// A relief tile: what it is, as its ETag names it.
    Relief(String),
    /// A quantized-mesh tile with these extensions (gzipped).
    Terrain(terrastream_views::quantized::geodetic::GeoTile, terrastream_views::quantized::encode::Extensions),
}

impl MadeKey {
    /// The strong ETag of the made web tile `r`, from the archive's.
    fn etag(r: &WebTileRequest, archive_etag: &str) -> String {
        let encoding = r.encoding.map_or("rgba", HeightEncoding::name);
        format!(
            "\"{}-w{}-{}-{}-{}-{encoding}-{}.{}\"",
            archive_etag.trim_matches('"'),
            r.layer,
            r.tile.z,
            r.tile.x,
            r.tile.y,
            r.size,
            r.format.extension()
        )
    }
}

/// The query of the web tile and TileJSON routes.
#[derive(Clone, Debug, Default, serde::Deserialize)]
pub struct TileQuery {
    /// `terrarium` (default) or `mapbox`, for heights.
    pub encoding: Option<String>,
    /// `webp` (default) or `png`, for TileJSON (a tile's extension says its own).
    pub format: Option<String>,
    /// 512 (default) or 256.
    pub size: Option<u32>,
    /// Relief tiles: `gdaldem`'s `-z` (vertical exaggeration).
    pub z_factor: Option<f64>,
    /// Relief tiles: the light's azimuth, degrees (`-az`).
    pub azimuth: Option<f64>,
    /// Relief tiles: the light's altitude, degrees (`-alt`).
    pub altitude: Option<f64>,
    /// Relief tiles: `true` for four lights (`-multidirectional`).
    pub multidirectional: Option<bool>,
    /// Slope tiles: `degrees` (default) or `percent`; contours: `m` (default) or `ft`.
    pub units: Option<String>,
    /// Contours: the height between lines (default: the zoom's).
    pub interval: Option<f64>,
    /// Contours: every how many lines a major one is (default 5).
    pub major: Option<u32>,
}

/// A web route's error: status and a one-line reason.
#[derive(Debug)]
pub struct WebError(StatusCode, String);

impl IntoResponse for WebError {
    fn into_response(self) -> Response {
        let mut response = (self.0, format!("{}\n", self.1)).into_response();
        if self.0 == StatusCode::SERVICE_UNAVAILABLE {
            response.headers_mut().insert(RETRY_AFTER, HeaderValue::from_static("1"));
        }
        response
    }
}

fn bad(why: impl Into<String>) -> WebError {
    WebError(StatusCode::BAD_REQUEST, why.into())
}

fn not_found(why: impl Into<String>) -> WebError {
    WebError(StatusCode::NOT_FOUND, why.into())
}

/// A web tile's path names neither a layer of the archive nor a map made from the
/// heights: 400, naming the word and what it may be.
fn unknown_layer(metadata: &terrastream_format::Metadata, name: &str, word: &str) -> WebError {
    let layers: Vec<&str> = metadata.layers.iter().map(|l| l.name.as_str()).collect();
    let products: Vec<&str> = Product::ALL.iter().map(|p| p.name()).collect();
    bad(format!(
        "{word:?} is neither a layer of archive {name:?} ({}) nor a product ({})",
        layers.join(", "),
        products.join(", ")
    ))
}

/// The options of a query, checked; `format` when the path already names it (a tile's
/// extension), else the query's.
fn options(
    query: &TileQuery,
    kind: LayerKind,
    format: Option<ImageFormat>,
) -> Result<(Option<HeightEncoding>, ImageFormat, u32), WebError> {
    let encoding = match (kind, query.encoding.as_deref()) {
        (LayerKind::Elevation, None) => Some(HeightEncoding::Terrarium),
        (LayerKind::Elevation, Some(e)) => {
            Some(HeightEncoding::parse(e).ok_or_else(|| bad(format!("encoding {e:?}: use terrarium or mapbox")))?)
        }
        (_, None) => None,
        (_, Some(e)) => return Err(bad(format!("encoding {e:?}: only elevation layers are encoded"))),
    };
    let format = match (format, query.format.as_deref()) {
        (Some(format), _) => format,
        (None, None) => ImageFormat::Webp,
        (None, Some(f)) => ImageFormat::parse(f).ok_or_else(|| bad(format!("format {f:?}: use webp or png")))?,
    };
    let size = match query.size {
        None => 512,
        Some(s @ (256 | 512)) => s,
        Some(s) => return Err(bad(format!("size {s}: use 256 or 512"))),
    };
    Ok((encoding, format, size))
}

/// `GET /{name}/tiles.json`: the elevation's TileJSON.
pub async fn elevation_tilejson(
    State(state): State<AppState>,
    Path(name): Path<String>,
    Query(query): Query<TileQuery>,
    grant: Option<Extension<Grant>>,
    headers: HeaderMap,
) -> Result<Response, WebError> {
    let grant = grant.map(|g| g.0).unwrap_or_default();
    layer_tilejson_of(&state, (&name, None), &query, &grant, &headers)
}

/// `GET /{name}/{layer}/tiles.json`: a layer's TileJSON.
pub async fn layer_tilejson(
    State(state): State<AppState>,
    Path((name, layer)): Path<(String, String)>,
    Query(query): Query<TileQuery>,
    grant: Option<Extension<Grant>>,
    headers: HeaderMap,
) -> Result<Response, WebError> {
    let grant = grant.map(|g| g.0).unwrap_or_default();
    layer_tilejson_of(&state, (&name, Some(&layer)), &query, &grant, &headers)
}

/// The TileJSON of archive `name`'s `layer` (the elevation when None); its tile URLs carry
/// the request's credential when it came in the query.
fn layer_tilejson_of(
    state: &AppState,
    (name, layer): (&str, Option<&str>),
    query: &TileQuery,
    grant: &Grant,
    headers: &HeaderMap,
) -> Result<Response, WebError> {
    let served = state.catalog.get(name).ok_or_else(|| not_found(format!("no archive named {name:?}")))?;
    let metadata = served.reader.metadata();
    if layer == Some("contours") && metadata.resolve_layer("contours").is_none() {
        return contours::tilejson_of(state, name, query, grant, headers);
    }
    let elevation = || {
        let i = metadata.layers.iter().position(|l| l.kind == LayerKind::Elevation);
        i.and_then(|i| u8::try_from(i).ok())
            .ok_or_else(|| not_found(format!("archive {name:?} has no elevation layer")))
    };
    // A layer by name; else a map made from the heights (`hillshade`, …); else none.
    let (index, product) = match layer {
        Some(l) => match (metadata.resolve_layer(l), Product::parse(l)) {
            (Some(i), _) => (i, None),
            (None, Some(product)) => (elevation()?, Some(product)),
            (None, None) => return Err(unknown_layer(metadata, name, l)),
        },
        None => (elevation()?, None),
    };
    let info = &metadata.layers[usize::from(index)];
    if Placed::new(&served.reader, index).is_none() {
        return Err(not_found(format!(
            "layer {:?} of {name:?} has no web tiles: it does not say where it lies, or its tiles are not heights or images",
            info.name
        )));
    }
    let (encoding, format, size) = match product {
        Some(_) => {
            let (_, size) = relief::options(query, &state.web.color_table)?;
            (None, options(query, LayerKind::Texture, None)?.1, size)
        }
        None => options(query, info.kind, None)?,
    };
    let coverage = tilejson::coverage(metadata, info, size)
        .ok_or_else(|| not_found(format!("archive {name:?} does not say where it lies")))?;
    let host = headers.get(HOST).and_then(|h| h.to_str().ok()).unwrap_or("localhost");
    let scheme = if state.config.tls_cert.is_some() { "https" } else { "http" };
    let mut params = vec![];
    if let Some(e) = encoding.filter(|&e| e != HeightEncoding::Terrarium) {
        params.push(format!("encoding={}", e.name()));
    }
    if size != 512 {
        params.push(format!("size={size}"));
    }
    if product.is_some() {
        params.extend(relief::query_text(query));
    }
    params.extend(grant.carried());
    let query_text = if params.is_empty() { String::new() } else { format!("?{}", params.join("&")) };
    let shown: &str = product.map_or(info.name.as_str(), |p| p.name());
    let tiles = format!("{scheme}://{host}/{name}/xyz/{shown}/{{z}}/{{x}}/{{y}}.{}{query_text}", format.extension());
    let request = tilejson::TileJsonRequest { name, layer: shown, tiles, encoding, format, size };
    let doc = tilejson::tilejson(metadata, info, &request, coverage);
    let mut response = axum::Json(doc).into_response();
    let h = response.headers_mut();
    h.insert(CACHE_CONTROL, state.cache_control.clone());
    h.insert(ARCHIVE_ETAG, served.etag_header.clone());
    Ok(response)
}

/// `GET /{name}/xyz/{layer}/{z}/{x}/{y}.{ext}`: a Web Mercator tile.
pub async fn web_tile(
    State(state): State<AppState>,
    Path((name, layer, z, x, file)): Path<(String, String, u8, u32, String)>,
    Query(query): Query<TileQuery>,
    headers: HeaderMap,
) -> Response {
    let at = WebTileAt { name: &name, layer: &layer, z, x, file: &file };
    web_tile_answer(&state, at, &query, &headers).await.map(Body::new)
}

/// A web tile as a request's path names it.
#[derive(Clone, Copy, Debug)]
pub(crate) struct WebTileAt<'a> {
    pub(crate) name: &'a str,
    pub(crate) layer: &'a str,
    pub(crate) z: u8,
    pub(crate) x: u32,
    /// `{y}.webp` or `{y}.png`.
    pub(crate) file: &'a str,
}

/// The answer of a web tile, for the router and for the lean HTTP/1.1 path (which passes
/// only the headers in `route::READ_HEADERS`).
pub(crate) async fn web_tile_answer(
    state: &AppState,
    at: WebTileAt<'_>,
    query: &TileQuery,
    headers: &HeaderMap,
) -> Answer {
    match web_tile_made(state, at, query, headers).await {
        Ok(answer) => answer,
        Err(WebError(status, why)) => {
            let mut answer = Answer::new(Payload::from(format!("{why}\n")));
            *answer.status_mut() = status;
            answer.headers_mut().insert(CONTENT_TYPE, HeaderValue::from_static("text/plain; charset=utf-8"));
            if status == StatusCode::SERVICE_UNAVAILABLE {
                answer.headers_mut().insert(RETRY_AFTER, HeaderValue::from_static("1"));
            }
            answer
        }
    }
}

async fn web_tile_made(
    state: &AppState,
    WebTileAt { name, layer, z, x, file }: WebTileAt<'_>,
    query: &TileQuery,
    headers: &HeaderMap,
) -> Result<Answer, WebError> {
    let served = state.catalog.get(name).ok_or_else(|| not_found(format!("no archive named {name:?}")))?;
    let metadata = served.reader.metadata();
    let (y, extension) =
        file.split_once('.').ok_or_else(|| bad(format!("{file:?}: name a tile as {{y}}.webp or {{y}}.png")))?;
    let y: u32 = y.parse().map_err(|_| bad(format!("{file:?}: the row is not a number")))?;
    let format = ImageFormat::parse(extension).ok_or_else(|| bad(format!("{file:?}: use .webp or .png")))?;
    let tile = WebTile::new(z, x, y).ok_or_else(|| bad(format!("tile {z}/{x}/{y} is outside the grid of zoom {z}")))?;
    let Some(index) = metadata.resolve_layer(layer) else {
        // A map made from the heights, where no layer has that name.
        let product = Product::parse(layer).ok_or_else(|| unknown_layer(metadata, name, layer))?;
        return relief::answer(state, served, relief::At { product, tile, format }, query, headers).await;
    };
    let info = &metadata.layers[usize::from(index)];
    let (encoding, _, size) = options(query, info.kind, Some(format))?;
    let request = WebTileRequest { layer: index, tile, encoding, format, size };
    let version = xxhash_rust::xxh3::xxh3_64(served.etag.as_bytes());
    let key = MadeKey { archive: version, request: Made::Web(request) };
    let etag = MadeKey::etag(&request, &served.etag);
    let what = format!("{name}: web tile {z}/{x}/{y}");
    let make = move |served: std::sync::Arc<crate::catalog::Served>, web: std::sync::Arc<WebState>| {
        make_tile_cached(&served.reader, &request, Some((&web.decoded, version))).map_err(|e| e.to_string())
    };
    made_answer(state, served, Made2 { key, etag, media: format.media_type(), what }, headers, make).await
}

/// A made tile's identity, ETag, media type and name for the logs.
pub(crate) struct Made2 {
    pub(crate) key: MadeKey,
    pub(crate) etag: String,
    pub(crate) media: &'static str,
    pub(crate) what: String,
}

/// The answer of a made tile: 304 for its ETag, else from the made tiles kept, else made
/// on the pool by `make` (and kept); 404 when it holds no data.
pub(crate) async fn made_answer(
    state: &AppState,
    served: std::sync::Arc<crate::catalog::Served>,
    made: Made2,
    headers: &HeaderMap,
    make: impl FnOnce(std::sync::Arc<crate::catalog::Served>, std::sync::Arc<WebState>) -> Result<Option<Vec<u8>>, String>
    + Send
    + 'static,
) -> Result<Answer, WebError> {
    let Made2 { key, etag, media, what } = made;
    let mut h = HeaderMap::with_capacity(8);
    h.insert(ETAG, HeaderValue::from_str(&etag).unwrap_or_else(|_| HeaderValue::from_static("\"\"")));
    h.insert(ARCHIVE_ETAG, served.etag_header.clone());
    h.insert(CACHE_CONTROL, state.cache_control.clone());
    let with = |status: StatusCode, h: HeaderMap, body: Payload| {
        let mut answer = Answer::new(body);
        *answer.status_mut() = status;
        *answer.headers_mut() = h;
        answer
    };
    if preconditions(headers, &etag, served.modified, true) == Precondition::NotModified {
        return Ok(with(StatusCode::NOT_MODIFIED, h, Payload::empty()));
    }
    let bytes = made_bytes(state, served, key, &what, make).await?;
    if bytes.is_empty() {
        return Ok(with(StatusCode::NOT_FOUND, h, Payload::from("no data in this tile\n")));
    }
    h.insert(CONTENT_TYPE, HeaderValue::from_static(media));
    h.insert(CONTENT_LENGTH, HeaderValue::from(bytes.len()));
    Ok(with(StatusCode::OK, h, Payload::from(bytes)))
}

/// The bytes of the made tile `key` (empty where it holds no data): from the made tiles
/// kept, else made on the pool by `make` and kept. 503 when the pool is full; a failure
/// is logged with `what` and answered 500.
pub(crate) async fn made_bytes(
    state: &AppState,
    served: std::sync::Arc<crate::catalog::Served>,
    key: MadeKey,
    what: &str,
    make: impl FnOnce(std::sync::Arc<crate::catalog::Served>, std::sync::Arc<WebState>) -> Result<Option<Vec<u8>>, String>
    + Send
    + 'static,
) -> Result<Bytes, WebError> {
    if let Some(bytes) = state.web.made.get(&key) {
        return Ok(bytes);
    }
    let web = std::sync::Arc::clone(&state.web);
    let made = state
        .web
        .pool
        .run(move || make(served, web))
        .await
        .map_err(|_| WebError(StatusCode::SERVICE_UNAVAILABLE, "busy making tiles: try again".into()))?
        .map_err(|e| {
            tracing::error!("{what}: {e}");
            WebError(StatusCode::INTERNAL_SERVER_ERROR, "internal server error".into())
        })?;
    let made = Bytes::from(made.unwrap_or_default());
    state.web.made.put(key, made.clone());
    Ok(made)
}

impl TileQuery {
    /// The query of a request target's `?...` part as the lean path takes it: only
    /// `encoding`, `format` and `size` with plain values (anything else: None, and the
    /// router answers).
    pub(crate) fn plain(query: &str) -> Option<Self> {
        let mut out = Self::default();
        for pair in query.split('&').filter(|p| !p.is_empty()) {
            let (key, value) = pair.split_once('=')?;
            if !value.bytes().all(|b| b.is_ascii_alphanumeric() || b == b'-') {
                return None;
            }
            match key {
                "encoding" => out.encoding = Some(value.to_owned()),
                "format" => out.format = Some(value.to_owned()),
                "size" => out.size = Some(value.parse().ok()?),
                _ => return None,
            }
        }
        Some(out)
    }
}

/// The JSON error of the elevation API.
fn api_error(status: StatusCode, error: &str) -> Response {
    let code = if status == StatusCode::NOT_FOUND {
        "NOT_FOUND"
    } else if status.is_client_error() {
        "INVALID_REQUEST"
    } else {
        "SERVER_ERROR"
    };
    (status, axum::Json(serde_json::json!({ "error": error, "status": code }))).into_response()
}

/// `GET /v1/{name}?locations=...`.
pub async fn elevation_get(
    State(state): State<AppState>,
    Path(name): Path<String>,
    query: Result<Query<elevation::Query>, axum::extract::rejection::QueryRejection>,
) -> Response {
    match query {
        Ok(Query(query)) => elevation_answer(&state, &name, &query).await,
        Err(e) => api_error(StatusCode::BAD_REQUEST, &format!("Invalid query: {}", e.body_text())),
    }
}

/// `POST /v1/{name}` with `{"locations": ..., "interpolation": ..., "samples": ...}`.
pub async fn elevation_post(State(state): State<AppState>, Path(name): Path<String>, body: Bytes) -> Response {
    match serde_json::from_slice::<elevation::Query>(&body) {
        Ok(query) => elevation_answer(&state, &name, &query).await,
        Err(e) => api_error(StatusCode::BAD_REQUEST, &format!("Invalid JSON body: {e}")),
    }
}

async fn elevation_answer(state: &AppState, name: &str, query: &elevation::Query) -> Response {
    let Some(served) = state.catalog.get(name) else {
        return api_error(StatusCode::NOT_FOUND, &format!("No archive named '{name}'."));
    };
    let points = match query.points(state.config.max_locations) {
        Ok(p) => p,
        Err(elevation::Invalid(why)) => return api_error(StatusCode::BAD_REQUEST, &why),
    };
    let job_points = points.clone();
    let dataset = name.to_owned();
    let web = std::sync::Arc::clone(&state.web);
    let heights = state
        .web
        .pool
        .run(move || {
            let version = xxhash_rust::xxh3::xxh3_64(served.etag.as_bytes());
            let heights = elevation::Heights::new(&served.reader)
                .ok_or("the archive has no placed elevation")?
                .with_cache(&web.decoded, version);
            let found = heights.found(&job_points.points, job_points.interpolation).map_err(|e| {
                tracing::error!("elevation of {dataset:?}: {e}");
                "an archive tile could not be read"
            })?;
            let spacing: Vec<Option<f64>> = found.iter().map(|f| f.map(|(_, s)| s)).collect();
            let mut found: Vec<Option<f64>> = found.into_iter().map(|f| f.map(|(h, _)| h)).collect();
            let datum = &served.reader.metadata().vertical_datum;
            let above = elevation::answer_datum(datum, job_points.datum, &job_points.points, &mut found);
            Ok::<_, &str>((found, spacing, above, datum.describe()))
        })
        .await;
    let (heights, spacing, above, datum) = match heights {
        Ok(Ok(h)) => h,
        Ok(Err(why)) => return api_error(StatusCode::BAD_REQUEST, &format!("Archive '{name}': {why}.")),
        Err(_) => {
            let mut r = api_error(StatusCode::SERVICE_UNAVAILABLE, "Busy: try again.");
            r.headers_mut().insert(RETRY_AFTER, HeaderValue::from_static("1"));
            return r;
        }
    };
    let results: Vec<serde_json::Value> = points
        .points
        .iter()
        .zip(heights)
        .zip(spacing)
        .map(|((&(lat, lng), h), spacing)| {
            // The spacing of the level the height came from, to the centimetre: the
            // finest data there (a collection's finer survey where one lies).
            let resolution = spacing.map(|s| (s * 100.0).round() / 100.0);
            serde_json::json!({
                "dataset": name,
                "elevation": h,
                "resolution": resolution,
                "datum": above,
                "location": { "lat": lat, "lng": lng }
            })
        })
        .collect();
    axum::Json(serde_json::json!({ "results": results, "datum": above, "vertical_datum": datum, "status": "OK" }))
        .into_response()
}
