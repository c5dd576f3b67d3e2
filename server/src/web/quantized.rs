//! Quantized-mesh terrain over HTTP (CesiumJS, Cesium for Unreal and Unity, iTowns); the
//! tiles themselves are made by [`terrastream_views::quantized`].
//!
//! Routes (CORS as for the others):
//! - `GET /{name}/layer.json`: the layer document (`format` "quantized-mesh-1.0", `scheme`
//!   "tms", tiles `{z}/{x}/{y}.terrain` relative to it, true `available` ranges, the
//!   extensions offered and `metadataAvailability`).
//! - `GET /{name}/{z}/{x}/{y}.terrain`: a tile, with the extensions the `Accept` header
//!   asks for (`application/vnd.quantized-mesh;extensions=octvertexnormals-metadata`, as
//!   Cesium sends it; or `?extensions=`), gzipped when accepted. 404 outside `available`.

use terrastream_views::quantized::encode::Extensions;
use terrastream_views::quantized::geodetic::GeoTile;
use terrastream_views::quantized::{MEDIA_TYPE, Terrain, gzip};

/// The query of a terrain tile: `extensions=octvertexnormals-metadata` (as Cesium ion's
/// clients ask), instead of the `Accept` header's.
#[derive(Clone, Debug, Default, serde::Deserialize)]
pub struct TerrainQuery {
    /// Extensions, joined by `-`.
    pub extensions: Option<String>,
}

/// `GET /{name}/layer.json`.
pub async fn layer_json(
    axum::extract::State(state): axum::extract::State<crate::app::AppState>,
    axum::extract::Path(name): axum::extract::Path<String>,
    grant: Option<axum::extract::Extension<crate::access::Grant>>,
) -> Result<axum::response::Response, super::WebError> {
    use axum::http::header::CACHE_CONTROL;
    use axum::response::IntoResponse as _;
    let served = state.catalog.get(&name).ok_or_else(|| super::not_found(format!("no archive named {name:?}")))?;
    let terrain = Terrain::new(&served.reader, None).ok_or_else(|| {
        super::not_found(format!("archive {name:?} has no terrain: no elevation layer that says where it lies"))
    })?;
    let description = served.reader.metadata().name.clone();
    // The tile template carries the request's credential when it came in the query
    // (Cesium's template requests send no header of ours).
    let template = grant.map(|g| g.0).unwrap_or_default().carry("{z}/{x}/{y}.terrain");
    let doc = terrain.layer_json(&name, &description, &template);
    let mut response = axum::Json(doc).into_response();
    let h = response.headers_mut();
    h.insert(CACHE_CONTROL, state.cache_control.clone());
    h.insert(crate::app::ARCHIVE_ETAG, served.etag_header.clone());
    Ok(response)
}

/// `GET /{name}/{z}/{x}/{y}.terrain`.
pub async fn terrain_tile(
    axum::extract::State(state): axum::extract::State<crate::app::AppState>,
    axum::extract::Path((name, z, x, file)): axum::extract::Path<(String, String, String, String)>,
    axum::extract::Query(query): axum::extract::Query<TerrainQuery>,
    headers: axum::http::HeaderMap,
) -> axum::response::Response {
    use axum::response::IntoResponse as _;
    match terrain_answer(&state, [&name, &z, &x, &file], &query, &headers).await {
        Ok(response) => response,
        Err(e) => e.into_response(),
    }
}

async fn terrain_answer(
    state: &crate::app::AppState,
    [name, z, x, file]: [&str; 4],
    query: &TerrainQuery,
    headers: &axum::http::HeaderMap,
) -> Result<axum::response::Response, super::WebError> {
    use axum::http::header::{ACCEPT, CACHE_CONTROL, CONTENT_ENCODING, CONTENT_LENGTH, CONTENT_TYPE, ETAG, VARY};
    use axum::http::{HeaderValue, StatusCode};
    use axum::response::IntoResponse as _;
    let served = state.catalog.get(name).ok_or_else(|| super::not_found(format!("no archive named {name:?}")))?;
    let tile = parse_tile(z, x, file)?;
    let extensions = match &query.extensions {
        Some(names) => Extensions::from_accept(&format!("x;extensions={names}")),
        None => Extensions::from_accept(headers.get(ACCEPT).and_then(|v| v.to_str().ok()).unwrap_or("")),
    };
    let gzipped = crate::app::accepts(headers, "gzip");
    let version = xxhash_rust::xxh3::xxh3_64(served.etag.as_bytes());
    let key = super::MadeKey { archive: version, request: super::Made::Terrain(tile, extensions) };
    let etag = format!(
        "\"{}-qm-{}-{}-{}-{}{}\"",
        served.etag.trim_matches('"'),
        tile.z,
        tile.x,
        tile.y,
        extensions.names(),
        if gzipped { "-gz" } else { "" }
    );
    let mut h = axum::http::HeaderMap::with_capacity(10);
    h.insert(ETAG, HeaderValue::from_str(&etag).unwrap_or_else(|_| HeaderValue::from_static("\"\"")));
    h.insert(crate::app::ARCHIVE_ETAG, served.etag_header.clone());
    h.insert(CACHE_CONTROL, state.cache_control.clone());
    h.insert(VARY, HeaderValue::from_static("Accept, Accept-Encoding"));
    if crate::range::preconditions(headers, &etag, served.modified, true) == crate::range::Precondition::NotModified {
        return Ok((StatusCode::NOT_MODIFIED, h).into_response());
    }
    let what = format!("{name}: terrain tile {}/{}/{}", tile.z, tile.x, tile.y);
    let bytes = super::made_bytes(state, served, key, &what, move |served, web| {
        let terrain = Terrain::new(&served.reader, Some((&web.decoded, version)));
        terrain.map_or(Ok(None), |t| t.tile(tile, extensions)).map(|b| b.map(|b| gzip(&b))).map_err(|e| e.to_string())
    })
    .await?;
    if bytes.is_empty() {
        return Ok((StatusCode::NOT_FOUND, h, "no such tile: see the available ranges of layer.json\n").into_response());
    }
    let body = if gzipped {
        h.insert(CONTENT_ENCODING, HeaderValue::from_static("gzip"));
        bytes
    } else {
        let mut raw = vec![];
        std::io::Read::read_to_end(&mut flate2::read::GzDecoder::new(&bytes[..]), &mut raw)
            .map_err(|e| super::WebError(StatusCode::INTERNAL_SERVER_ERROR, format!("internal server error: {e}")))?;
        bytes::Bytes::from(raw)
    };
    let names = extensions.names();
    let media = if names.is_empty() { MEDIA_TYPE.to_owned() } else { format!("{MEDIA_TYPE};extensions={names}") };
    h.insert(CONTENT_TYPE, HeaderValue::from_str(&media).unwrap_or_else(|_| HeaderValue::from_static(MEDIA_TYPE)));
    h.insert(CONTENT_LENGTH, HeaderValue::from(body.len()));
    Ok((StatusCode::OK, h, body).into_response())
}

/// The tile a path names: level, column, `{row}.terrain`.
fn parse_tile(z: &str, x: &str, file: &str) -> Result<GeoTile, super::WebError> {
    let y = file
        .strip_suffix(".terrain")
        .ok_or_else(|| super::not_found(format!("{file:?}: name a tile as {{y}}.terrain")))?;
    let (Ok(z), Ok(x), Ok(y)) = (z.parse::<u8>(), x.parse::<u32>(), y.parse::<u32>()) else {
        return Err(super::bad(format!("{z}/{x}/{file}: level, column and row are numbers")));
    };
    GeoTile::new(z, x, y).ok_or_else(|| super::bad(format!("tile {z}/{x}/{y} is outside the grid of level {z}")))
}
