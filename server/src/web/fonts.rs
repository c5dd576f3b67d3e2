//! Glyphs for map labels: `GET /fonts/{fontstack}/{range}.pbf`, the URL a MapLibre style's
//! `glyphs` names (`http://host/fonts/{fontstack}/{range}.pbf`), made by
//! [`terrastream_views::glyphs`] from the fonts of the folder `serve --fonts` (or the
//! config's `fonts`) names, on a blocking thread, and kept (by font and range: a stack's
//! name only labels the answer).

use std::collections::HashMap;
use std::sync::{Arc, Mutex};

use axum::extract::{Path, State};
use axum::http::header::{CACHE_CONTROL, CONTENT_ENCODING, CONTENT_TYPE, VARY};
use axum::http::{HeaderMap, HeaderName, HeaderValue, StatusCode};
use axum::response::{IntoResponse, Response};
use bytes::Bytes;
use terrastream_views::glyphs::{FontSet, parse_range, range_message};

use super::{WebError, bad, not_found};
use crate::app::AppState;

/// Header naming the font a stack was answered with (a fallback's name where none of the
/// stack's names is served).
pub const FONT_HEADER: HeaderName = HeaderName::from_static("x-terrastream-font");

/// The fonts served, and the ranges made from them.
#[derive(Debug)]
pub struct Fonts {
    /// The fonts.
    pub set: FontSet,
    /// Glyphs made, by font and first code point (not by the stack's name: any number of
    /// names map to one font, and memory stays bounded by the fonts' glyphs).
    made: Mutex<HashMap<(usize, u32), Bytes>>,
}

impl Fonts {
    /// The fonts of `set`, nothing made yet.
    pub fn new(set: FontSet) -> Self {
        Self { set, made: Mutex::new(HashMap::new()) }
    }
}

/// `GET /fonts/{fontstack}/{range}.pbf` (gzipped when the client accepts it: a Latin
/// range is about 100 KiB, a third of that gzipped).
pub async fn glyphs(
    State(state): State<AppState>,
    Path((stack, range)): Path<(String, String)>,
    headers: HeaderMap,
) -> Response {
    match answer(&state, stack, &range, crate::app::accepts(&headers, "gzip")).await {
        Ok(response) => response,
        Err(e) => e.into_response(),
    }
}

async fn answer(state: &AppState, stack: String, range: &str, gzipped: bool) -> Result<Response, WebError> {
    let Some(fonts) = state.web.fonts.clone() else {
        return Err(not_found("no fonts are served here (serve --fonts DIR)"));
    };
    let start = parse_range(range).ok_or_else(|| {
        bad(format!("range {range:?}: START-END.pbf, START a multiple of 256 below 65536, END START + 255"))
    })?;
    if stack.is_empty() || stack.len() > 512 {
        return Err(bad("fontstack: one to 512 characters of comma-separated font names"));
    }
    let (font, name) = fonts.set.pick(&stack);
    let name = name.to_owned();
    let key = (font, start);
    let kept = fonts.made.lock().unwrap_or_else(std::sync::PoisonError::into_inner).get(&key).cloned();
    let glyphs = match kept {
        Some(bytes) => bytes,
        None => {
            let made = Arc::clone(&fonts);
            let failed = || WebError(StatusCode::INTERNAL_SERVER_ERROR, "glyphs could not be made".into());
            let made = tokio::task::spawn_blocking(move || made.set.glyphs(font, start)).await.map_err(|_| failed())?;
            let bytes = Bytes::from(made.map_err(|why| {
                tracing::error!("glyphs of {name}: {why}");
                failed()
            })?);
            fonts.made.lock().unwrap_or_else(std::sync::PoisonError::into_inner).insert(key, bytes.clone());
            bytes
        }
    };
    let message = range_message(&stack, start, &glyphs);
    let body = if gzipped { terrastream_views::quantized::gzip(&message) } else { message };
    let mut response = Bytes::from(body).into_response();
    let h = response.headers_mut();
    if gzipped {
        h.insert(CONTENT_ENCODING, HeaderValue::from_static("gzip"));
    }
    h.insert(VARY, HeaderValue::from_static("accept-encoding"));
    h.insert(CONTENT_TYPE, HeaderValue::from_static("application/x-protobuf"));
    h.insert(CACHE_CONTROL, state.cache_control.clone());
    if let Ok(v) = HeaderValue::from_str(&name) {
        h.insert(FONT_HEADER, v);
    }
    Ok(response)
}
