//! An elevation API shaped like Open Topo Data's (itself shaped like the Google Maps
//! Elevation API): `GET /v1/{name}?locations=lat,lng|lat,lng` or a Google encoded
//! polyline, `POST /v1/{name}` with the same parameters as JSON; `interpolation=nearest|
//! bilinear|cubic`; `samples=N` for N points evenly spaced along the path; `datum=geoid|
//! ellipsoid` for heights above sea level (the default) or above the WGS 84 ellipsoid.
//!
//! Heights come from the finest LOD that holds a tile at the point, through the client's
//! [`height_on_lod`] (the same code as its `height_at`).

use std::collections::HashMap;
use std::sync::Arc;

use terrastream_crs::{Crs, Transform};
use terrastream_format::{HeightReference, LayerKind, MmapSource, Reader, TileKey, VerticalDatum};
use terrastream_tiles::DecodedTile;
use terrastream_tiles::{Interpolation, height_on_lod};

use crate::tilejson::haversine;

/// A request as its parameters state it.
#[derive(Clone, Debug, Default, serde::Deserialize)]
pub struct Query {
    /// `lat,lng|lat,lng...` or an encoded polyline (in a POST also a list of strings or
    /// of `[lat, lng]` pairs).
    pub locations: Option<Locations>,
    /// `nearest`, `bilinear` (the default) or `cubic`.
    pub interpolation: Option<String>,
    /// Points evenly spaced along the path through the locations.
    pub samples: Option<serde_json::Value>,
    /// `geoid` (the default: heights above sea level, as maps show them) or `ellipsoid`
    /// (above the WGS 84 ellipsoid, as GPS and CesiumJS place them).
    pub datum: Option<String>,
}

/// The surface a request wants heights above.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub enum Wanted {
    /// Above the geoid: orthometric, "above sea level".
    #[default]
    Geoid,
    /// Above the WGS 84 ellipsoid.
    Ellipsoid,
}

/// Makes `heights` (at `points`, (lat, lng)) heights above what `wanted` names where the
/// archive's `datum` says how, and says what they are above: `geoid`, `ellipsoid`, or
/// `unknown` (an archive that does not say: heights as stored). An archive of
/// ellipsoidal heights answers ellipsoidal heights (it carries no geoid to subtract).
pub fn answer_datum(
    datum: &VerticalDatum,
    wanted: Wanted,
    points: &[(f64, f64)],
    heights: &mut [Option<f64>],
) -> &'static str {
    match (datum.reference, wanted) {
        (HeightReference::Geoid, Wanted::Ellipsoid) if datum.converts() => {
            for (h, &(lat, lng)) in heights.iter_mut().zip(points) {
                if let Some(h) = h {
                    *h += datum.to_ellipsoid(lng, lat);
                }
            }
            "ellipsoid"
        }
        (reference, _) => reference.name(),
    }
}

/// Locations as given.
#[derive(Clone, Debug, serde::Deserialize)]
#[serde(untagged)]
pub enum Locations {
    /// `lat,lng|lat,lng` or a polyline.
    Text(String),
    /// `["lat,lng", ...]` or `[[lat, lng], ...]`.
    List(Vec<serde_json::Value>),
}

/// A bad request, named.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct Invalid(pub String);

/// The points and options of a valid request.
#[derive(Debug, Clone, PartialEq)]
pub struct Points {
    /// (lat, lng) in degrees.
    pub points: Vec<(f64, f64)>,
    /// How heights are made between samples.
    pub interpolation: Interpolation,
    /// The surface the heights are wanted above.
    pub datum: Wanted,
}

impl Query {
    /// The points asked for, checked: at most `limit` of them (locations given, or samples
    /// along them).
    ///
    /// # Errors
    /// [`Invalid`] naming the parameter at fault.
    pub fn points(&self, limit: usize) -> Result<Points, Invalid> {
        let interpolation = match self.interpolation.as_deref().map(str::trim) {
            None | Some("" | "bilinear") => Interpolation::Bilinear,
            Some("nearest") => Interpolation::Nearest,
            Some("cubic") => Interpolation::Cubic,
            Some(other) => {
                return Err(Invalid(format!("Invalid interpolation '{other}': use 'nearest', 'bilinear' or 'cubic'.")));
            }
        };
        let datum = match self.datum.as_deref().map(str::trim) {
            None | Some("" | "geoid") => Wanted::Geoid,
            Some("ellipsoid") => Wanted::Ellipsoid,
            Some(other) => return Err(Invalid(format!("Invalid datum '{other}': use 'geoid' or 'ellipsoid'."))),
        };
        let locations = match &self.locations {
            None => return Err(Invalid("No locations provided: give locations=lat,lng|lat,lng or a polyline.".into())),
            Some(Locations::Text(t)) => parse_text(t)?,
            Some(Locations::List(items)) => items.iter().map(parse_item).collect::<Result<_, _>>()?,
        };
        if locations.is_empty() {
            return Err(Invalid("No locations provided.".into()));
        }
        let samples = match &self.samples {
            None => None,
            Some(serde_json::Value::Number(n)) => Some(n.as_u64().ok_or_else(|| bad_samples(&n.to_string()))?),
            Some(serde_json::Value::String(s)) if s.trim().is_empty() => None,
            Some(serde_json::Value::String(s)) => Some(s.trim().parse::<u64>().map_err(|_| bad_samples(s))?),
            Some(other) => return Err(bad_samples(&other.to_string())),
        };
        let points = match samples {
            None => locations,
            Some(n) if n < 2 || n > limit as u64 => {
                return Err(Invalid(format!("Invalid samples '{n}': between 2 and {limit} points along the path.")));
            }
            #[expect(clippy::cast_possible_truncation, reason = "at most the limit")]
            Some(n) => along(&locations, n as usize),
        };
        if points.len() > limit {
            return Err(Invalid(format!("Too many locations provided ({}), the limit is {limit}.", points.len())));
        }
        Ok(Points { points, interpolation, datum })
    }
}

fn bad_samples(given: &str) -> Invalid {
    Invalid(format!("Invalid samples '{given}': a whole number of points."))
}

/// `lat,lng|lat,lng`, or else an encoded polyline.
fn parse_text(text: &str) -> Result<Vec<(f64, f64)>, Invalid> {
    let text = text.trim();
    if text.is_empty() {
        return Err(Invalid("No locations provided: give locations=lat,lng|lat,lng or a polyline.".into()));
    }
    let looks_numeric =
        text.chars().all(|c| c.is_ascii_digit() || matches!(c, ',' | '|' | '.' | '-' | '+' | ' ' | 'e' | 'E'));
    if looks_numeric && text.contains(',') {
        return text.split('|').map(parse_pair).collect();
    }
    decode_polyline(text)
}

/// One `lat,lng`.
fn parse_pair(pair: &str) -> Result<(f64, f64), Invalid> {
    let bad = || Invalid(format!("Unable to parse location '{pair}': give lat,lng in decimal degrees."));
    let (lat, lng) = pair.split_once(',').ok_or_else(bad)?;
    let (lat, lng) = (lat.trim().parse::<f64>().map_err(|_| bad())?, lng.trim().parse::<f64>().map_err(|_| bad())?);
    check(lat, lng).map_err(|why| Invalid(format!("Invalid location '{pair}': {why}.")))?;
    Ok((lat, lng))
}

fn parse_item(item: &serde_json::Value) -> Result<(f64, f64), Invalid> {
    match item {
        serde_json::Value::String(s) => parse_pair(s),
        serde_json::Value::Array(a) if a.len() == 2 => {
            let (Some(lat), Some(lng)) = (a[0].as_f64(), a[1].as_f64()) else {
                return Err(Invalid(format!("Unable to parse location {item}: give [lat, lng] numbers.")));
            };
            check(lat, lng).map_err(|why| Invalid(format!("Invalid location {item}: {why}.")))?;
            Ok((lat, lng))
        }
        other => Err(Invalid(format!("Unable to parse location {other}: give \"lat,lng\" or [lat, lng]."))),
    }
}

fn check(lat: f64, lng: f64) -> Result<(), String> {
    if !(lat.is_finite() && (-90.0..=90.0).contains(&lat)) {
        return Err(format!("latitude {lat} outside -90..90"));
    }
    if !(lng.is_finite() && (-180.0..=180.0).contains(&lng)) {
        return Err(format!("longitude {lng} outside -180..180"));
    }
    Ok(())
}

/// A Google encoded polyline (precision 5) as (lat, lng) points.
///
/// # Errors
/// [`Invalid`] for a string that is not one.
pub fn decode_polyline(text: &str) -> Result<Vec<(f64, f64)>, Invalid> {
    let bad = |why: &str| Invalid(format!("Unable to parse locations as a polyline: {why}."));
    let bytes = text.as_bytes();
    let (mut i, mut lat, mut lng) = (0usize, 0i64, 0i64);
    let mut out = Vec::new();
    let next = |i: &mut usize| -> Result<i64, Invalid> {
        let (mut shift, mut result) = (0u32, 0i64);
        loop {
            let &b = bytes.get(*i).ok_or_else(|| bad("it ends inside a number"))?;
            if !(63..=126).contains(&b) {
                return Err(bad(&format!("character {:?} at {} is not in a polyline", b as char, *i)));
            }
            *i += 1;
            let chunk = i64::from(b - 63);
            if shift > 60 {
                return Err(bad("a number too long"));
            }
            result |= (chunk & 0x1f) << shift;
            shift += 5;
            if chunk < 0x20 {
                break;
            }
        }
        Ok(if result & 1 == 1 { !(result >> 1) } else { result >> 1 })
    };
    while i < bytes.len() {
        lat += next(&mut i)?;
        lng += next(&mut i)?;
        #[expect(clippy::cast_precision_loss, reason = "degrees times 1e5")]
        let point = (lat as f64 / 1e5, lng as f64 / 1e5);
        check(point.0, point.1).map_err(|why| bad(&why))?;
        out.push(point);
    }
    if out.is_empty() {
        return Err(bad("it is empty"));
    }
    Ok(out)
}

/// `n` points evenly spaced (by distance on the sphere) along the path through `points`,
/// the first and last included; each between two locations linearly in degrees.
pub fn along(points: &[(f64, f64)], n: usize) -> Vec<(f64, f64)> {
    let legs: Vec<f64> = points.windows(2).map(|w| haversine((w[0].1, w[0].0), (w[1].1, w[1].0))).collect();
    let total: f64 = legs.iter().sum();
    if points.len() == 1 || total <= 0.0 {
        return vec![points[0]; n];
    }
    (0..n)
        .map(|k| {
            #[expect(clippy::cast_precision_loss, reason = "a count of points")]
            let mut d = total * k as f64 / (n - 1) as f64;
            for (w, &len) in points.windows(2).zip(&legs) {
                if d <= len || std::ptr::eq(w, points.windows(2).last().unwrap_or(w)) {
                    let t = if len > 0.0 { (d / len).min(1.0) } else { 0.0 };
                    return (w[0].0 + (w[1].0 - w[0].0) * t, w[0].1 + (w[1].1 - w[0].1) * t);
                }
                d -= len;
            }
            points[points.len() - 1]
        })
        .collect()
}

/// The elevation layer of an archive, placed on the Earth: what the API reads.
pub struct Heights<'a> {
    reader: &'a Reader<MmapSource>,
    /// Decoded tiles kept between requests, and this archive version's number in it.
    cache: Option<(&'a crate::resample::DecodedCache, u64)>,
    layer: u8,
    to_archive: Transform,
    origin: [f64; 2],
    scale: [f64; 2],
}

impl<'a> Heights<'a> {
    /// The archive's elevation; None without one, or without a georeference.
    pub fn new(reader: &'a Reader<MmapSource>) -> Option<Self> {
        let metadata = reader.metadata();
        let layer = u8::try_from(metadata.layers.iter().position(|l| l.kind == LayerKind::Elevation)?).ok()?;
        let g = metadata.georeference.as_ref()?;
        let crs = Crs::parse(g.definition.as_deref().or(g.crs.as_deref())?).ok()?;
        Some(Self {
            reader,
            cache: None,
            layer,
            to_archive: Transform::new(&Crs::wgs84(), &crs),
            origin: g.origin?,
            scale: g.scale?,
        })
    }

    /// Keeps decoded tiles in `cache` under `version` (the archive's content tag), shared
    /// with the web tiles.
    #[must_use]
    pub fn with_cache(mut self, cache: &'a crate::resample::DecodedCache, version: u64) -> Self {
        self.cache = Some((cache, version));
        self
    }

    /// The height at each point (None: no data there).
    ///
    /// # Errors
    /// A tile of the archive that cannot be read or decoded, named.
    pub fn at(&self, points: &[(f64, f64)], interpolation: Interpolation) -> Result<Vec<Option<f64>>, String> {
        Ok(self.found(points, interpolation)?.into_iter().map(|h| h.map(|(h, _)| h)).collect())
    }

    /// The height at each point, from the finest level with data there, and that level's
    /// sample spacing in metres (None: no data there). In a collection of inputs of
    /// different resolutions (docs/tiling.md, "Collections"), that is the finest input's
    /// there.
    ///
    /// # Errors
    /// As [`Heights::at`].
    pub fn found(
        &self,
        points: &[(f64, f64)],
        interpolation: Interpolation,
    ) -> Result<Vec<Option<(f64, f64)>>, String> {
        let info = &self.reader.metadata().layers[usize::from(self.layer)];
        let finest = info.extent.as_ref().map_or(0, |e| e.finest_lod);
        let mut tiles: HashMap<TileKey, Option<Arc<DecodedTile>>> = HashMap::new();
        let mut out = Vec::with_capacity(points.len());
        for &(lat, lng) in points {
            let Some((cx, cy)) = self.to_archive.apply(lng, lat) else {
                out.push(None);
                continue;
            };
            let (x, z) = ((cx - self.origin[0]) / self.scale[0], (self.origin[1] - cy) / self.scale[1]);
            let [x0, z0, x1, z1] = info.data_world();
            if !(x >= x0 && x <= x1 && z >= z0 && z <= z1) {
                out.push(None);
                continue;
            }
            // The finest LOD with a tile under the point.
            let mut height = None;
            for lod in finest..info.num_lods {
                let Some(home) = terrastream_tiles::tile_of(info, self.layer, lod, x, z) else {
                    break;
                };
                if self.load(&mut tiles, home)?.is_none() {
                    continue;
                }
                // The neighbours a bilinear or cubic footprint reaches.
                let spacing = info.sample_spacing(lod);
                for (dx, dz) in [
                    (-2.0, -2.0),
                    (2.0, -2.0),
                    (-2.0, 2.0),
                    (2.0, 2.0),
                    (-2.0, 0.0),
                    (2.0, 0.0),
                    (0.0, -2.0),
                    (0.0, 2.0),
                ] {
                    if let Some(key) =
                        terrastream_tiles::tile_of(info, self.layer, lod, x + dx * spacing, z + dz * spacing)
                    {
                        self.load(&mut tiles, key)?;
                    }
                }
                // The finest input's spacing there, where a collection's level is
                // filled from coarser data beneath its finer inputs' footprints.
                let surveyed = self.reader.metadata().source_spacing_at(x, z).unwrap_or(0.0);
                let metres = spacing.max(surveyed);
                height =
                    height_on_lod(info, self.layer, lod, x, z, interpolation, |key| tiles.get(&key).cloned().flatten())
                        .map(|h| (h, metres));
                break;
            }
            out.push(height);
        }
        Ok(out)
    }

    fn load(
        &self,
        tiles: &mut HashMap<TileKey, Option<Arc<DecodedTile>>>,
        key: TileKey,
    ) -> Result<Option<Arc<DecodedTile>>, String> {
        if let Some(t) = tiles.get(&key) {
            return Ok(t.clone());
        }
        let info = &self.reader.metadata().layers[usize::from(self.layer)];
        let tile = crate::resample::load_tile(self.reader, info, key, self.cache).map_err(|e| e.to_string())?;
        tiles.insert(key, tile.clone());
        Ok(tile)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn locations_polylines_and_samples_parse_or_are_named() {
        let q = |locations: &str| Query { locations: Some(Locations::Text(locations.into())), ..Query::default() };
        assert_eq!(q("37.9,-122.6|38,-122.5").points(100).unwrap().points, vec![(37.9, -122.6), (38.0, -122.5)]);
        // Google's documented example: "_p~iF~ps|U_ulLnnqC_mqNvxq`@".
        let line = q("_p~iF~ps|U_ulLnnqC_mqNvxq`@").points(100).unwrap().points;
        assert_eq!(line, vec![(38.5, -120.2), (40.7, -120.95), (43.252, -126.453)]);
        for (bad, says) in [
            ("91,0", "latitude 91"),
            ("10,181", "longitude 181"),
            ("1,2|3", "'3'"),
            ("abc", "polyline"),
            ("", "No locations"),
        ] {
            let e = q(bad).points(100).unwrap_err().0;
            assert!(e.contains(says), "{bad}: {e}");
        }
        let too_many = vec!["1,1"; 101].join("|");
        assert!(q(&too_many).points(100).unwrap_err().0.contains("Too many locations provided (101)"));
        let mut sampled = q("0,0|0,1");
        sampled.samples = Some(serde_json::json!(5));
        let points = sampled.points(100).unwrap().points;
        assert_eq!(points.len(), 5);
        assert!((points[2].1 - 0.5).abs() < 1e-9 && points[4] == (0.0, 1.0));
        sampled.samples = Some(serde_json::json!("1"));
        assert!(sampled.points(100).unwrap_err().0.contains("samples"));
        let mut interpolated = q("0,0");
        interpolated.interpolation = Some("spline".into());
        assert!(interpolated.points(100).unwrap_err().0.contains("interpolation 'spline'"));
    }
}
