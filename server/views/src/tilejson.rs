//! TileJSON 3.0.0 documents for an archive's layers, as Web Mercator XYZ sources.

use terrastream_crs::{Crs, Transform};
use terrastream_format::{Layer, LayerKind, Metadata};

use crate::encode::{HeightEncoding, ImageFormat};
use crate::mercator::{HALF_WORLD, MAX_LATITUDE};

/// Where a layer lies and which zooms show it.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Coverage {
    /// West, south, east, north (degrees).
    pub bounds: [f64; 4],
    /// The zoom whose pixels are no larger than the finest samples (at the data's centre).
    pub maxzoom: u8,
}

/// The coverage of layer `layer` of `metadata` for tiles of `size` pixels: its data's
/// box in degrees and the zoom that shows its finest samples; None when the archive does
/// not say where it lies.
pub fn coverage(metadata: &Metadata, layer: &Layer, size: u32) -> Option<Coverage> {
    let g = metadata.georeference.as_ref()?;
    let crs = Crs::parse(g.definition.as_deref().or(g.crs.as_deref())?).ok()?;
    let (origin, scale) = (g.origin?, g.scale?);
    let to_degrees = Transform::new(&crs, &Crs::wgs84());
    let world_to_degrees = |x: f64, z: f64| to_degrees.apply(origin[0] + x * scale[0], origin[1] - z * scale[1]);
    let detail = layer.data_detail();
    // A collection's finest levels cover only its finer inputs: its data is the whole
    // box, which its coarser levels cover.
    let partial = layer.extent.as_ref().is_some_and(|e| !e.partial.is_empty());
    let framed = if partial { layer.data_world() } else { detail };
    let bounds = match layer.extent.as_ref().and_then(|e| e.lon_lat).filter(|_| !partial) {
        Some(b) => b,
        None => {
            // The box's edges, sampled (a projected box is curved in degrees).
            let detail = framed;
            let mut b = [f64::INFINITY, f64::INFINITY, f64::NEG_INFINITY, f64::NEG_INFINITY];
            for k in 0..=16 {
                let t = f64::from(k) / 16.0;
                let (x, z) = (detail[0] + (detail[2] - detail[0]) * t, detail[1] + (detail[3] - detail[1]) * t);
                for (px, pz) in [(x, detail[1]), (x, detail[3]), (detail[0], z), (detail[2], z)] {
                    let (lon, lat) = world_to_degrees(px, pz)?;
                    b = [b[0].min(lon), b[1].min(lat), b[2].max(lon), b[3].max(lat)];
                }
            }
            b
        }
    };
    // The finest samples' size in metres, measured between two samples at the centre.
    let spacing = layer.sample_spacing(0);
    let (cx, cz) = ((detail[0] + detail[2]) / 2.0, (detail[1] + detail[3]) / 2.0);
    let (a, b) = (world_to_degrees(cx, cz)?, world_to_degrees(cx + spacing, cz)?);
    let metres = haversine(a, b).max(1e-6);
    let lat = a.1.clamp(-MAX_LATITUDE, MAX_LATITUDE).to_radians();
    // (A hundredth of a zoom allowed: a pyramid made on the Web Mercator grid has samples
    // of exactly a zoom's pixels, which the sphere's radius measures a little smaller.)
    let zoom = ((2.0 * HALF_WORLD * lat.cos() / (f64::from(size) * metres)).log2() - 0.01).ceil();
    #[expect(clippy::cast_possible_truncation, clippy::cast_sign_loss, reason = "clamped to 0..=24")]
    let maxzoom = zoom.clamp(0.0, 24.0) as u8;
    Some(Coverage { bounds, maxzoom })
}

/// Great-circle distance in metres between two (lon, lat) points in degrees.
pub fn haversine((lon1, lat1): (f64, f64), (lon2, lat2): (f64, f64)) -> f64 {
    const R: f64 = 6_371_008.8;
    let (p1, p2) = (lat1.to_radians(), lat2.to_radians());
    let (dp, dl) = (p2 - p1, (lon2 - lon1).to_radians());
    let h = (dp / 2.0).sin().powi(2) + p1.cos() * p2.cos() * (dl / 2.0).sin().powi(2);
    2.0 * R * h.sqrt().asin()
}

/// What a TileJSON document describes.
#[derive(Clone, Debug)]
pub struct TileJsonRequest<'a> {
    /// The archive's URL name.
    pub name: &'a str,
    /// The layer's name.
    pub layer: &'a str,
    /// The tile URL template, absolute or relative.
    pub tiles: String,
    /// Heights' encoding (elevation layers).
    pub encoding: Option<HeightEncoding>,
    /// Image format of the tiles.
    pub format: ImageFormat,
    /// Pixels a side.
    pub size: u32,
}

/// The TileJSON 3.0.0 document of `layer` (a `raster-dem` source for elevation: MapLibre
/// reads `encoding` beside the standard keys).
pub fn tilejson(
    metadata: &Metadata,
    layer: &Layer,
    request: &TileJsonRequest<'_>,
    coverage: Coverage,
) -> serde_json::Value {
    let [w, s, e, n] = coverage.bounds;
    let centre_zoom = coverage.maxzoom.saturating_sub(3);
    let mut doc = serde_json::json!({
        "tilejson": "3.0.0",
        "name": format!("{} {}", request.name, request.layer),
        "description": metadata.name,
        "version": "1.0.0",
        "scheme": "xyz",
        "tiles": [request.tiles],
        "minzoom": 0,
        "maxzoom": coverage.maxzoom,
        "bounds": [w, s, e, n],
        "center": [(w + e) / 2.0, (s + n) / 2.0, centre_zoom],
        "tileSize": request.size,
        "format": request.format.extension(),
    });
    // Heights as heights: a `raster-dem`; a map made from them (no encoding): a `raster`.
    if layer.kind == LayerKind::Elevation && request.encoding.is_some() {
        doc["type"] = "raster-dem".into();
        doc["encoding"] = request.encoding.unwrap_or(HeightEncoding::Terrarium).name().into();
        // Heights as stored: above sea level for an archive above a geoid (what maps
        // want), else what the archive says.
        let d = &metadata.vertical_datum;
        doc["vertical_datum"] =
            serde_json::json!({ "heights": d.reference.name(), "epsg": d.epsg, "describe": d.describe() });
    } else {
        doc["type"] = "raster".into();
    }
    doc
}
