//! Relief tiles over HTTP: `GET /{name}/xyz/{hillshade|slope|aspect|color-relief}/{z}/{x}/{y}.webp|png`
//! (where the archive has no layer of that name), made by [`terrastream_views::relief`]
//! on the tile-making pool and kept with the other made tiles. Query: `size`, and
//! `gdaldem`'s parameters `z_factor`, `azimuth`, `altitude`, `multidirectional`, `units`
//! (`degrees` or `percent`, for slope).

use std::sync::Arc;

use axum::http::{HeaderMap, StatusCode};
use terrastream_views::encode::ImageFormat;
use terrastream_views::mercator::WebTile;
use terrastream_views::relief::{Product, ReliefOptions, ReliefRequest, relief_tile};

use super::{Made, Made2, MadeKey, TileQuery, WebError, bad, made_answer};
use crate::app::{Answer, AppState};
use crate::catalog::Served;

/// A relief tile as a request's path names it.
pub(crate) struct At {
    pub(crate) product: Product,
    pub(crate) tile: WebTile,
    pub(crate) format: ImageFormat,
}

/// The options a query asks for, checked.
///
/// # Errors
/// A 400 naming the parameter at fault.
pub(crate) fn options(
    query: &TileQuery,
    table: &terrastream_views::relief::ColorTable,
) -> Result<(ReliefOptions, u32), WebError> {
    let defaults = ReliefOptions::default();
    let finite = |name: &str, v: Option<f64>, default: f64| match v {
        None => Ok(default),
        Some(v) if v.is_finite() => Ok(v),
        Some(v) => Err(bad(format!("{name} {v}: a finite number"))),
    };
    let altitude = finite("altitude", query.altitude, defaults.altitude)?;
    if !(0.0..=90.0).contains(&altitude) {
        return Err(bad(format!("altitude {altitude}: degrees from 0 to 90")));
    }
    let slope_percent = match query.units.as_deref() {
        None | Some("degrees") => false,
        Some("percent") => true,
        Some(other) => return Err(bad(format!("units {other:?}: use degrees or percent"))),
    };
    let size = match query.size {
        None => 512,
        Some(s @ (256 | 512)) => s,
        Some(s) => return Err(bad(format!("size {s}: use 256 or 512"))),
    };
    if query.encoding.is_some() {
        return Err(bad("encoding: relief tiles are images, not heights"));
    }
    let options = ReliefOptions {
        z_factor: finite("z_factor", query.z_factor, defaults.z_factor)?,
        azimuth: finite("azimuth", query.azimuth, defaults.azimuth)?,
        altitude,
        multidirectional: query.multidirectional.unwrap_or(false),
        slope_percent,
        table: table.clone(),
    };
    Ok((options, size))
}

/// The relief parameters of a query, as a TileJSON's tile URLs repeat them.
pub(crate) fn query_text(query: &TileQuery) -> Vec<String> {
    let mut out = vec![];
    let numbers = [("z_factor", query.z_factor), ("azimuth", query.azimuth), ("altitude", query.altitude)];
    out.extend(numbers.into_iter().filter_map(|(name, v)| v.map(|v| format!("{name}={v}"))));
    if query.multidirectional == Some(true) {
        out.push("multidirectional=true".to_owned());
    }
    if let Some(units) = &query.units {
        out.push(format!("units={units}"));
    }
    out
}

/// The answer of a relief tile of `served`.
pub(crate) async fn answer(
    state: &AppState,
    served: Arc<Served>,
    At { product, tile, format }: At,
    query: &TileQuery,
    headers: &HeaderMap,
) -> Result<Answer, WebError> {
    let (options, size) = options(query, &state.web.color_table)?;
    let version = xxhash_rust::xxh3::xxh3_64(served.etag.as_bytes());
    // Everything that makes the tile, in its identity and ETag.
    let what = format!(
        "{}-{}-{}-{}-{size}-z{}-a{}-h{}-m{}-p{}.{}",
        product.name(),
        tile.z,
        tile.x,
        tile.y,
        options.z_factor,
        options.azimuth,
        options.altitude,
        u8::from(options.multidirectional),
        u8::from(options.slope_percent),
        format.extension()
    );
    let etag = format!("\"{}-r{}\"", served.etag.trim_matches('"'), what);
    let key = MadeKey { archive: version, request: Made::Relief(what.clone()) };
    let request = ReliefRequest { product, tile, format, size, options };
    let make = move |served: Arc<Served>, web: Arc<super::WebState>| {
        relief_tile(&served.reader, &request, Some((&web.decoded, version))).map_err(|e| match e {
            terrastream_views::MakeError::NotPlaced => "the archive has no placed elevation".to_owned(),
            other => other.to_string(),
        })
    };
    let made = Made2 { key, etag, media: format.media_type(), what: format!("{}: relief tile {what}", served.name) };
    if terrastream_views::resample::Placed::new(&served.reader, elevation(&served).unwrap_or(u8::MAX)).is_none() {
        return Err(WebError(StatusCode::NOT_FOUND, format!("archive {:?} has no placed elevation", served.name)));
    }
    made_answer(state, served, made, headers, make).await
}

/// The archive's first elevation layer.
fn elevation(served: &Served) -> Option<u8> {
    let layers = &served.reader.metadata().layers;
    layers.iter().position(|l| l.kind == terrastream_format::LayerKind::Elevation).and_then(|i| u8::try_from(i).ok())
}
