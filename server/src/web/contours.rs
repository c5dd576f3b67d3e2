//! Contour vector tiles over HTTP: `GET /{name}/contours/{z}/{x}/{y}.pbf` (Mapbox Vector
//! Tile 2.1, layer `contours`, properties `ele` and `major`) and
//! `GET /{name}/contours/tiles.json` (with `vector_layers`), made by
//! [`terrastream_views::contours`] on the tile-making pool and kept with the other made
//! tiles. Query: `interval` (default: the zoom's), `major` (every how many lines, 5),
//! `units` (`m` or `ft`).

use std::sync::Arc;

use axum::extract::{Path, Query, State};
use axum::http::header::{CACHE_CONTROL, HOST};
use axum::http::{HeaderMap, StatusCode};
use axum::response::{IntoResponse, Response};
use terrastream_format::LayerKind;
use terrastream_views::contours::{ContourOptions, contour_tile};
use terrastream_views::mercator::WebTile;

use super::{Made, Made2, MadeKey, TileQuery, WebError, bad, made_answer, not_found};
use crate::access::Grant;
use crate::app::{ARCHIVE_ETAG, AppState};
use crate::catalog::Served;

/// The finest interval asked for (a line a decimetre apart is already a fill).
const MIN_INTERVAL: f64 = 0.1;
/// The coarsest (beyond Everest's height, a tile would hold no line at all).
const MAX_INTERVAL: f64 = 10_000.0;

/// The media type of a vector tile.
const MVT: &str = "application/vnd.mapbox-vector-tile";

/// The options a query asks for, checked.
fn options(query: &TileQuery) -> Result<ContourOptions, WebError> {
    let feet = match query.units.as_deref() {
        None | Some("m") => false,
        Some("ft") => true,
        Some(other) => return Err(bad(format!("units {other:?}: use m or ft"))),
    };
    if let Some(i) = query.interval.filter(|i| !(i.is_finite() && (MIN_INTERVAL..=MAX_INTERVAL).contains(i))) {
        return Err(bad(format!("interval {i}: a height from {MIN_INTERVAL} to {MAX_INTERVAL}")));
    }
    if query.major == Some(0) {
        return Err(bad("major 0: every how many lines a major one is, at least 1"));
    }
    Ok(ContourOptions { interval: query.interval, major: query.major.unwrap_or(5), feet })
}

/// `GET /{name}/contours/{z}/{x}/{y}.pbf`.
pub async fn tile(
    State(state): State<AppState>,
    Path((name, z, x, file)): Path<(String, u8, u32, String)>,
    Query(query): Query<TileQuery>,
    headers: HeaderMap,
) -> Response {
    match answer(&state, (&name, z, x, &file), &query, &headers).await {
        Ok(answer) => answer.map(axum::body::Body::new),
        Err(e) => e.into_response(),
    }
}

async fn answer(
    state: &AppState,
    (name, z, x, file): (&str, u8, u32, &str),
    query: &TileQuery,
    headers: &HeaderMap,
) -> Result<crate::app::Answer, WebError> {
    let served = state.catalog.get(name).ok_or_else(|| not_found(format!("no archive named {name:?}")))?;
    let y = file.strip_suffix(".pbf").or_else(|| file.strip_suffix(".mvt"));
    let y: u32 = y.and_then(|y| y.parse().ok()).ok_or_else(|| bad(format!("{file:?}: name a tile as {{y}}.pbf")))?;
    let tile = WebTile::new(z, x, y).ok_or_else(|| bad(format!("tile {z}/{x}/{y} is outside the grid of zoom {z}")))?;
    let options = options(query)?;
    placed(&served)?;
    let version = xxhash_rust::xxh3::xxh3_64(served.etag.as_bytes());
    let what = format!(
        "contours-{z}-{x}-{y}-i{}-m{}-{}",
        options.interval.map_or_else(|| "auto".to_owned(), |i| i.to_string()),
        options.major,
        if options.feet { "ft" } else { "m" }
    );
    let etag = format!("\"{}-{what}\"", served.etag.trim_matches('"'));
    let key = MadeKey { archive: version, request: Made::Relief(what.clone()) };
    let make = move |served: Arc<Served>, web: Arc<super::WebState>| {
        contour_tile(&served.reader, tile, options, Some((&web.decoded, version))).map_err(|e| e.to_string())
    };
    let made = Made2 { key, etag, media: MVT, what: format!("{name}: {what}") };
    made_answer(state, served, made, headers, make).await
}

/// The archive's elevation, when it says where it lies.
fn placed(served: &Served) -> Result<u8, WebError> {
    let layers = &served.reader.metadata().layers;
    let index = layers.iter().position(|l| l.kind == LayerKind::Elevation).and_then(|i| u8::try_from(i).ok());
    index.filter(|&i| terrastream_views::resample::Placed::new(&served.reader, i).is_some()).ok_or_else(|| {
        WebError(StatusCode::NOT_FOUND, format!("archive {:?} has no elevation that says where it lies", served.name))
    })
}

/// `GET /{name}/contours/tiles.json`: the contours as a vector source.
pub(crate) fn tilejson(
    state: &AppState,
    served: &Served,
    query: &TileQuery,
    grant: &Grant,
    headers: &HeaderMap,
) -> Result<Response, WebError> {
    let options = options(query)?;
    let metadata = served.reader.metadata();
    let index = placed(served)?;
    let coverage = terrastream_views::tilejson::coverage(metadata, &metadata.layers[usize::from(index)], 256)
        .ok_or_else(|| not_found(format!("archive {:?} does not say where it lies", served.name)))?;
    let host = headers.get(HOST).and_then(|h| h.to_str().ok()).unwrap_or("localhost");
    let scheme = if state.config.tls_cert.is_some() { "https" } else { "http" };
    let mut params = vec![];
    if let Some(i) = options.interval {
        params.push(format!("interval={i}"));
    }
    if options.major != 5 {
        params.push(format!("major={}", options.major));
    }
    if options.feet {
        params.push("units=ft".to_owned());
    }
    params.extend(grant.carried());
    let query_text = if params.is_empty() { String::new() } else { format!("?{}", params.join("&")) };
    let tiles = format!("{scheme}://{host}/{}/contours/{{z}}/{{x}}/{{y}}.pbf{query_text}", served.name);
    let doc = terrastream_views::contours::tilejson(&served.name, &metadata.name, tiles, coverage);
    let mut response = axum::Json(doc).into_response();
    response.headers_mut().insert(CACHE_CONTROL, state.cache_control.clone());
    response.headers_mut().insert(ARCHIVE_ETAG, served.etag_header.clone());
    Ok(response)
}

/// The answer to a contour TileJSON of an archive `name` (from the layer TileJSON route).
pub(crate) fn tilejson_of(
    state: &AppState,
    name: &str,
    query: &TileQuery,
    grant: &Grant,
    headers: &HeaderMap,
) -> Result<Response, WebError> {
    let served = state.catalog.get(name).ok_or_else(|| not_found(format!("no archive named {name:?}")))?;
    tilejson(state, &served, query, grant, headers)
}
