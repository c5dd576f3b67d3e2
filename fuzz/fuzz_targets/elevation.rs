//! Any bytes as an elevation API request: a query string (`?locations=...&samples=...`)
//! and a JSON body, through the checks the API applies. Every request is either points
//! within the limit, each a valid latitude and longitude, or an error naming what is
//! wrong; never a panic.
#![no_main]

use libfuzzer_sys::fuzz_target;
use terrastream_views::elevation::{Locations, Query, decode_polyline};

fn check(query: &Query) {
    match query.points(100) {
        Ok(p) => {
            assert!(!p.points.is_empty() && p.points.len() <= 100);
            for (lat, lng) in p.points {
                assert!((-90.0..=90.0).contains(&lat) && (-180.0..=180.0).contains(&lng), "{lat},{lng}");
            }
        }
        Err(invalid) => assert!(!invalid.0.is_empty()),
    }
}

fuzz_target!(|data: &[u8]| {
    let text = String::from_utf8_lossy(data);
    if let Ok(points) = decode_polyline(&text) {
        assert!(!points.is_empty());
    }
    // As a query string's value, and with samples and an interpolation beside it.
    let (locations, rest) = text.split_once('&').unwrap_or((&text, ""));
    let mut query = Query { locations: Some(Locations::Text(locations.to_owned())), ..Query::default() };
    check(&query);
    query.samples = Some(serde_json::Value::String(rest.chars().take(8).collect()));
    query.interpolation = Some(rest.chars().skip(8).collect());
    check(&query);
    // As a JSON body.
    if let Ok(query) = serde_json::from_slice::<Query>(data) {
        check(&query);
    }
});
