//! Quantized-mesh terrain (CesiumJS, Cesium for Unreal and Unity, iTowns) made from any
//! archive's heights, in the geographic TMS grid.
//!
//! Routes (CORS as for the others):
//! - `GET /{name}/layer.json`: the layer document (`format` "quantized-mesh-1.0", `scheme`
//!   "tms", tiles `{z}/{x}/{y}.terrain` relative to it, true `available` ranges, the
//!   extensions offered and `metadataAvailability`).
//! - `GET /{name}/{z}/{x}/{y}.terrain`: a tile, with the extensions the `Accept` header
//!   asks for (`application/vnd.quantized-mesh;extensions=octvertexnormals-metadata`, as
//!   Cesium sends it; or `?extensions=`), gzipped when accepted. 404 outside `available`.
//!
//! A tile samples the archive's heights on a 65 x 65 grid of its own (Cesium's heightmap
//! size; edges shared with the neighbours, corners included) from the LOD whose samples
//! are no larger than the grid's at the data's centre (one LOD a level, so that neighbours
//! read the same heights on their shared edge; the grid through the web tiles' approximate
//! transform, its outermost points exact), then meshes them with a vertical error of
//! at most Cesium's geometric error for the level, [`geometric_error`] (the height
//! quantization's half step included).

pub mod encode;
pub mod export;
pub mod geodetic;
pub mod mesh;

use std::io::Write as _;

use terrastream_format::{LayerKind, MmapSource, Reader};

use super::resample::{DecodedCache, MakeError, Placed};
use super::tilejson::{self, Coverage};
use encode::{Extensions, TileMesh};
use geodetic::{GeoTile, METADATA_LEVELS};

/// Grid points a tile side.
pub const GRID: usize = 65;

/// The media type of a tile.
pub const MEDIA_TYPE: &str = "application/vnd.quantized-mesh";

/// Cesium's geometric error of a level for heightmap terrain of 65 samples a side and two
/// root tiles (`TerrainProvider.getEstimatedLevelZeroGeometricErrorForAHeightmap` with
/// its terrain quality of 0.25): 77 067 m at level 0, halved a level. The bound of every
/// tile's vertical error.
pub fn geometric_error(z: u8) -> f64 {
    6_378_137.0 * std::f64::consts::TAU * 0.25 / (65.0 * 2.0) / f64::from(1u32 << z.min(31))
}

/// An archive's elevation as quantized-mesh terrain.
pub struct Terrain<'a> {
    placed: Placed<'a>,
    coverage: Coverage,
    /// World point at the data's centre: where a level's LOD is chosen.
    centre: (f64, f64),
}

/// The available tiles of a level: columns and rows, inclusive.
pub type Range = ([u32; 2], [u32; 2]);

impl<'a> Terrain<'a> {
    /// The archive's elevation layer, when it has one that says where it lies; decoded
    /// archive tiles kept in `cache` (with the archive's version) when given.
    pub fn new(reader: &'a Reader<MmapSource>, cache: Option<(&'a DecodedCache, u64)>) -> Option<Self> {
        let metadata = reader.metadata();
        let index = metadata.layers.iter().position(|l| l.kind == LayerKind::Elevation)?;
        let layer = &metadata.layers[index];
        let mut placed = Placed::new(reader, u8::try_from(index).ok()?)?;
        if let Some((cache, version)) = cache {
            placed = placed.with_cache(cache, version);
        }
        // A level's grid spans what a Web Mercator tile of 64 pixels spans a zoom deeper.
        let mut coverage = tilejson::coverage(metadata, layer, 64)?;
        coverage.maxzoom = coverage.maxzoom.saturating_sub(1);
        let [w, s, e, n] = coverage.bounds;
        let centre = placed.world((w + e) / 2.0, (s + n) / 2.0)?;
        Some(Self { placed, coverage, centre })
    }

    /// West, south, east, north of the data (degrees).
    pub fn bounds(&self) -> [f64; 4] {
        self.coverage.bounds
    }

    /// The deepest level: its grid's points are no further apart than the finest samples.
    pub fn maxzoom(&self) -> u8 {
        self.coverage.maxzoom
    }

    /// The tiles of level `z` that exist: those the data's box touches, and both root
    /// tiles (a client starts from them); None beyond [`Terrain::maxzoom`].
    pub fn available(&self, z: u8) -> Option<Range> {
        match z {
            0 => Some(([0, 1], [0, 0])),
            z if z <= self.maxzoom() => Some(GeoTile::range(z, self.coverage.bounds)),
            _ => None,
        }
    }

    /// Whether `tile` exists.
    pub fn exists(&self, tile: GeoTile) -> bool {
        self.available(tile.z)
            .is_some_and(|([x0, x1], [y0, y1])| (x0..=x1).contains(&tile.x) && (y0..=y1).contains(&tile.y))
    }

    /// The LOD a level samples: the coarsest whose samples are no larger than the level's
    /// grid spacing at the data's centre (the smaller of its two directions).
    fn lod(&self, z: u8) -> u8 {
        let step = 180.0 / f64::from(1u32 << z.min(31)) / (GRID - 1) as f64;
        let [w, s, e, n] = self.coverage.bounds;
        let (lon, lat) = ((w + e) / 2.0, (s + n) / 2.0);
        let far = |dlon: f64, dlat: f64| {
            self.placed.world(lon + dlon, lat + dlat).map(|(x, z)| (x - self.centre.0).hypot(z - self.centre.1))
        };
        let spacing = match (far(step, 0.0), far(0.0, step.copysign(-lat))) {
            (Some(a), Some(b)) => a.min(b),
            (a, b) => a.or(b).unwrap_or(f64::INFINITY),
        };
        self.placed.lod_for(spacing)
    }

    /// The heights of `tile`'s grid ([`GRID`] a side, row by row from the north), with
    /// no data filled as [`mesh::fill_nodata`] does.
    ///
    /// # Errors
    /// [`MakeError::Tile`] for an archive tile that cannot be read.
    pub fn heights(&self, tile: GeoTile) -> Result<Vec<f32>, MakeError> {
        let at = |column: f64, row: f64| {
            let (lon, lat) = tile.grid_point_at(column, row, GRID);
            self.placed.world(lon, lat)
        };
        // The approximate transform, as for web tiles (point (i, j) is the centre of
        // "pixel" (i, j)); the grid's outermost points exact, as its neighbours compute
        // them, so that tiles sharing an edge sample the same heights on it.
        #[expect(clippy::cast_precision_loss, reason = "grid indices")]
        let positions = (self.placed.lattice(GRID, &|u, v| at(u - 0.5, v - 0.5)))
            .with_exact_border(GRID, |column, row| at(column as f64, row as f64));
        let mut heights =
            self.placed.sample(&positions, self.lod(tile.z))?.unwrap_or_else(|| vec![f32::NAN; GRID * GRID]);
        mesh::fill_nodata(&mut heights, GRID);
        Ok(heights)
    }

    /// The mesher's bound for `tile` over `heights`: the level's geometric error less the
    /// height quantization's step (so that the decoded mesh keeps the level's bound).
    pub fn bound(tile: GeoTile, heights: &[f32]) -> f32 {
        let (lo, hi) = heights.iter().fold((f32::INFINITY, f32::NEG_INFINITY), |(lo, hi), &h| (lo.min(h), hi.max(h)));
        let quantum = if hi > lo { f64::from(hi - lo) / 32767.0 } else { 0.0 };
        #[expect(clippy::cast_possible_truncation, reason = "an error in metres")]
        let bound = (geometric_error(tile.z) - quantum).max(0.0) as f32;
        bound
    }

    /// The binary of `tile` with `extensions` (not compressed); None where it does not
    /// exist.
    ///
    /// # Errors
    /// [`MakeError::Tile`] for an archive tile that cannot be read.
    pub fn tile(&self, tile: GeoTile, extensions: Extensions) -> Result<Option<Vec<u8>>, MakeError> {
        if !self.exists(tile) {
            return Ok(None);
        }
        let heights = self.heights(tile)?;
        let mesh = mesh::mesh(&heights, GRID, Self::bound(tile, &heights));
        let metadata = self.metadata(tile);
        let t = TileMesh { tile, mesh: &mesh, heights: &heights, size: GRID };
        Ok(Some(encode::encode(&t, extensions, metadata.as_ref())))
    }

    /// The `metadata` extension's JSON of `tile`: for a tile of a level that is a multiple
    /// of [`METADATA_LEVELS`], the available tiles of its subtree on the levels below,
    /// down to the next such level.
    pub fn metadata(&self, tile: GeoTile) -> Option<serde_json::Value> {
        if !tile.z.is_multiple_of(METADATA_LEVELS) {
            return None;
        }
        let levels: Vec<serde_json::Value> = (1..=METADATA_LEVELS)
            .map_while(|k| {
                let z = tile.z.checked_add(k)?;
                let ([x0, x1], [y0, y1]) = self.available(z)?;
                let first = |v: u32| v << k;
                let last = |v: u32| ((v + 1) << k) - 1;
                let (cx, cy) =
                    ([x0.max(first(tile.x)), x1.min(last(tile.x))], [y0.max(first(tile.y)), y1.min(last(tile.y))]);
                let ranges = if cx[0] <= cx[1] && cy[0] <= cy[1] { vec![range_json((cx, cy))] } else { vec![] };
                Some(serde_json::Value::Array(ranges))
            })
            .collect();
        Some(serde_json::json!({ "available": levels }))
    }

    /// The `layer.json` of the terrain: `tiles` the URL template (relative to the
    /// document, or absolute), `name` and `description` for people.
    pub fn layer_json(&self, name: &str, description: &str, tiles: &str) -> serde_json::Value {
        let available: Vec<serde_json::Value> = (0..=self.maxzoom())
            .filter_map(|z| self.available(z))
            .map(|r| serde_json::json!([range_json(r)]))
            .collect();
        serde_json::json!({
            "tilejson": "2.1.0",
            "name": name,
            "description": description,
            "version": "1.2.0",
            "format": "quantized-mesh-1.0",
            "attribution": "",
            "scheme": "tms",
            "projection": "EPSG:4326",
            "tiles": [tiles],
            "minzoom": 0,
            "maxzoom": self.maxzoom(),
            "bounds": self.bounds(),
            "available": available,
            "extensions": ["octvertexnormals", "metadata"],
            "metadataAvailability": METADATA_LEVELS,
        })
    }
}

fn range_json(([x0, x1], [y0, y1]): Range) -> serde_json::Value {
    serde_json::json!({ "startX": x0, "startY": y0, "endX": x1, "endY": y1 })
}

/// Gzips a tile, the same bytes every time (no timestamp, no name): what the server sends
/// and `export` writes.
pub fn gzip(bytes: &[u8]) -> Vec<u8> {
    let mut encoder = flate2::GzBuilder::new().mtime(0).write(Vec::new(), flate2::Compression::new(6));
    // Writing into a Vec cannot fail.
    let _ = encoder.write_all(bytes);
    encoder.finish().unwrap_or_default()
}

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
) -> Result<axum::response::Response, super::WebError> {
    use axum::http::header::CACHE_CONTROL;
    use axum::response::IntoResponse as _;
    let served = state.catalog.get(&name).ok_or_else(|| super::not_found(format!("no archive named {name:?}")))?;
    let terrain = Terrain::new(&served.reader, None).ok_or_else(|| {
        super::not_found(format!("archive {name:?} has no terrain: no elevation layer that says where it lies"))
    })?;
    let description = served.reader.metadata().name.clone();
    let doc = terrain.layer_json(&name, &description, "{z}/{x}/{y}.terrain");
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
    let bytes = match state.web.made.get(&key) {
        Some(bytes) => bytes,
        None => {
            let web = std::sync::Arc::clone(&state.web);
            let made = state
                .web
                .pool
                .run(move || {
                    let terrain = Terrain::new(&served.reader, Some((&web.decoded, version)));
                    terrain.map_or(Ok(None), |t| t.tile(tile, extensions)).map(|b| b.map(|b| gzip(&b)))
                })
                .await
                .map_err(|_| super::WebError(StatusCode::SERVICE_UNAVAILABLE, "busy making tiles: try again".into()))?
                .map_err(|e| {
                    tracing::error!("{name}: terrain tile {}/{}/{}: {e}", tile.z, tile.x, tile.y);
                    super::WebError(StatusCode::INTERNAL_SERVER_ERROR, "internal server error".into())
                })?;
            let made = bytes::Bytes::from(made.unwrap_or_default());
            state.web.made.put(key, made.clone());
            made
        }
    };
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
