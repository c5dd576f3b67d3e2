//! Web Mercator XYZ tiles of any archive's layer (MapLibre GL JS, deck.gl, OpenLayers,
//! Leaflet): heights as Terrarium or Terrain-RGB, imagery as it is, in WebP or PNG, made
//! from the archive's own tiles in whatever CRS it is (or passed through when the archive
//! is already such a pyramid).

use terrastream_format::{MmapSource, Reader};

use crate::encode::{HeightEncoding, ImageFormat, Layout};
use crate::mercator::{self, WebTile};
use crate::resample::{self, MakeError, Placed, Samples};
use crate::tilejson;

/// A web tile of a layer, as it is encoded.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash)]
pub struct WebTileRequest {
    /// The archive's layer.
    pub layer: u8,
    /// The tile.
    pub tile: WebTile,
    /// Heights' encoding (None for imagery).
    pub encoding: Option<HeightEncoding>,
    /// The file's format.
    pub format: ImageFormat,
    /// Pixels a side.
    pub size: u32,
}

/// Makes a web tile of an archive: the file's bytes; None when the tile holds no data
/// (the server answers 404, and keeps the empty answer, so that the empty tiles around a
/// region cost one check each). What the server sends and `export --to xyz` writes.
///
/// # Errors
/// [`MakeError`] for a layer without web tiles or an archive tile that cannot be read.
pub fn make_tile(reader: &Reader<MmapSource>, request: &WebTileRequest) -> Result<Option<Vec<u8>>, MakeError> {
    make_tile_cached(reader, request, None)
}

/// [`make_tile`], keeping the archive tiles it decodes in `cache` (with the archive's
/// version number).
///
/// # Errors
/// As [`make_tile`].
pub fn make_tile_cached(
    reader: &Reader<MmapSource>,
    request: &WebTileRequest,
    cache: Option<(&resample::DecodedCache, u64)>,
) -> Result<Option<Vec<u8>>, MakeError> {
    if let Some(stored) = stored_as_asked(reader, request)? {
        return Ok(Some(stored));
    }
    let Some((samples, kind)) = samples_cached(reader, request, cache)? else { return Ok(None) };
    let rgba = match kind {
        Samples::Heights => {
            let encoding = request.encoding.unwrap_or(HeightEncoding::Terrarium);
            // Every pixel with data (most tiles): RGB straight away.
            if let Some(rgb) = encoding.rgb_pixels(&samples) {
                return request.format.encode_raw(&rgb, request.size, Layout::Rgb).map(Some).map_err(MakeError::Encode);
            }
            encoding.pixels(&samples)
        }
        #[expect(clippy::cast_possible_truncation, clippy::cast_sign_loss, reason = "rounded and clamped to 0..=255")]
        Samples::Rgba => samples.iter().map(|v| v.round().clamp(0.0, 255.0) as u8).collect(),
    };
    request.format.encode(&rgba, request.size).map(Some).map_err(MakeError::Encode)
}

/// The archive's own tile, when the archive's grid is the Web Mercator XYZ grid (an
/// archive packed from such a pyramid) and the tile is stored as asked: same size, no
/// border, the same image format, heights in the encoding asked. None otherwise (the
/// tile is made, as from any grid).
///
/// # Errors
/// [`MakeError::Tile`] for a stored tile that cannot be read.
fn stored_as_asked(reader: &Reader<MmapSource>, request: &WebTileRequest) -> Result<Option<Vec<u8>>, MakeError> {
    use terrastream_format::{ElevationScheme, PayloadCompression, TileFormat, TileKey};
    let metadata = reader.metadata();
    let Some(info) = metadata.layers.get(usize::from(request.layer)) else { return Ok(None) };
    let Some(g) = metadata.georeference.as_ref() else { return Ok(None) };
    let (Some(origin), Some(scale)) = (g.origin, g.scale) else { return Ok(None) };
    let mercator = g.crs.as_deref() == Some("EPSG:3857")
        && (origin[0] + mercator::HALF_WORLD).abs() < 1e-3
        && (origin[1] - mercator::HALF_WORLD).abs() < 1e-3;
    let format_matches = matches!(
        (info.format, request.format),
        (TileFormat::Png, ImageFormat::Png) | (TileFormat::Webp, ImageFormat::Webp)
    );
    let encoding_matches = matches!(
        (info.elevation.map(|e| e.scheme), request.encoding),
        (None, None)
            | (Some(ElevationScheme::Terrarium), Some(HeightEncoding::Terrarium))
            | (Some(ElevationScheme::TerrainRgb), Some(HeightEncoding::Mapbox))
    );
    if !mercator
        || !format_matches
        || !encoding_matches
        || info.border != 0
        || info.tile_resolution != request.size
        || info.compression != PayloadCompression::None
    {
        return Ok(None);
    }
    // The zoom of LOD 0: its tiles span 2 * HALF_WORLD / 2^z metres.
    let zooms = (2.0 * mercator::HALF_WORLD / (info.tile_world_size * scale[0])).log2();
    if (zooms - zooms.round()).abs() > 1e-9 || zooms < 0.0 {
        return Ok(None);
    }
    #[expect(clippy::cast_possible_truncation, clippy::cast_sign_loss, reason = "a whole, non-negative zoom")]
    let finest = zooms.round() as u8;
    let Some(lod) = finest.checked_sub(request.tile.z).filter(|&l| l < info.num_lods) else { return Ok(None) };
    let Ok(key) = TileKey::new(request.layer, lod, request.tile.x, request.tile.y) else { return Ok(None) };
    let bad = |e: terrastream_format::Error| MakeError::Tile { key, reason: e.to_string() };
    Ok(reader.tile(key).map_err(bad)?.map(|bytes| bytes.to_vec()))
}

/// The samples of a web tile before they are encoded: a height a pixel (NaN: no data) or
/// RGBA values (0 to 255, alpha 0: no data), row by row; None outside the bounds the
/// TileJSON gives (inside them, a tile without data is all no data: a client asks for
/// every tile there).
///
/// # Errors
/// As [`make_tile`].
pub fn tile_samples(
    reader: &Reader<MmapSource>,
    request: &WebTileRequest,
) -> Result<Option<(Vec<f32>, Samples)>, MakeError> {
    samples_cached(reader, request, None)
}

fn samples_cached(
    reader: &Reader<MmapSource>,
    request: &WebTileRequest,
    cache: Option<(&resample::DecodedCache, u64)>,
) -> Result<Option<(Vec<f32>, Samples)>, MakeError> {
    let mut placed = Placed::new(reader, request.layer).ok_or(MakeError::NotPlaced)?;
    if let Some((cache, version)) = cache {
        placed = placed.with_cache(cache, version);
    }
    let size = request.size as usize;
    let positions = placed.positions(request.tile, size);
    // World units per output pixel, at the tile's centre.
    let centre = size / 2 * size + size / 2;
    let per_pixel = match (positions.point(centre), positions.point(centre + 1)) {
        (Some(a), Some(b)) => (b.0 - a.0).hypot(b.1 - a.1),
        _ => f64::INFINITY,
    };
    let lod = placed.lod_for(per_pixel);
    if let Some(samples) = placed.sample(&positions, lod)? {
        return Ok(Some((samples, placed.samples())));
    }
    let metadata = reader.metadata();
    let info = &metadata.layers[usize::from(request.layer)];
    let inside = tilejson::coverage(metadata, info, request.size).is_some_and(|c| {
        let [w, s, e, n] = request.tile.bounds();
        w < c.bounds[2] && c.bounds[0] < e && s < c.bounds[3] && c.bounds[1] < n
    });
    Ok(inside.then(|| match placed.samples() {
        Samples::Heights => (vec![f32::NAN; size * size], Samples::Heights),
        Samples::Rgba => (vec![0.0; size * size * 4], Samples::Rgba),
    }))
}
