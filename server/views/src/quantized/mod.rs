//! Quantized-mesh terrain (CesiumJS, Cesium for Unreal and Unity, iTowns) made from any
//! archive's heights, in the geographic TMS grid.
//! The server serves them (`/{name}/layer.json`, `/{name}/{z}/{x}/{y}.terrain`) and
//! `export --to quantized-mesh` writes them.
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

use terrastream_format::{LayerKind, MmapSource, Reader, VerticalDatum};

use crate::resample::{DecodedCache, MakeError, Placed};
use crate::tilejson::{self, Coverage};
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
    /// The archive's water layer, when it has one: the water mask where it has data.
    water: Option<Placed<'a>>,
    /// What the archive's heights are measured from: tiles hold heights above the WGS 84
    /// ellipsoid where it says how to make them.
    datum: &'a VerticalDatum,
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
        let placed_layer = |index: usize| {
            let placed = Placed::new(reader, u8::try_from(index).ok()?)?;
            Some(match cache {
                Some((cache, version)) => placed.with_cache(cache, version),
                None => placed,
            })
        };
        let placed = placed_layer(index)?;
        let water = metadata.layers.iter().position(|l| l.kind == LayerKind::Water).and_then(placed_layer);
        // A level's grid spans what a Web Mercator tile of 64 pixels spans a zoom deeper.
        let mut coverage = tilejson::coverage(metadata, layer, 64)?;
        coverage.maxzoom = coverage.maxzoom.saturating_sub(1);
        let [w, s, e, n] = coverage.bounds;
        let centre = placed.world((w + e) / 2.0, (s + n) / 2.0)?;
        Some(Self { placed, water, coverage, centre, datum: &metadata.vertical_datum })
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
    /// tiles (a client starts from them); where the level samples a partial LOD of the
    /// archive (a collection's finer levels, made only where a fine input lies), those
    /// its rectangles touch. None beyond [`Terrain::maxzoom`].
    pub fn available(&self, z: u8) -> Option<Vec<Range>> {
        match z {
            0 => Some(vec![([0, 1], [0, 0])]),
            z if z <= self.maxzoom() => {
                let partial = self.placed.layer().extent.as_ref().and_then(|e| {
                    let lod = self.lod(z);
                    e.partial.iter().find(|c| c.lod == lod && !c.lon_lat.is_empty())
                });
                Some(match partial {
                    Some(cover) => cover.lon_lat.iter().map(|b| GeoTile::range(z, *b)).collect(),
                    None => vec![GeoTile::range(z, self.coverage.bounds)],
                })
            }
            _ => None,
        }
    }

    /// Whether `tile` exists.
    pub fn exists(&self, tile: GeoTile) -> bool {
        self.available(tile.z).is_some_and(|ranges| {
            ranges.iter().any(|&([x0, x1], [y0, y1])| (x0..=x1).contains(&tile.x) && (y0..=y1).contains(&tile.y))
        })
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
    /// no data filled as [`mesh::fill_nodata`] does, above the WGS 84 ellipsoid where
    /// the archive's datum says how ([`Terrain::to_ellipsoid`]).
    ///
    /// # Errors
    /// [`MakeError::Tile`] for an archive tile that cannot be read.
    pub fn heights(&self, tile: GeoTile) -> Result<Vec<f32>, MakeError> {
        Ok(self.grid(tile, false)?.0)
    }

    /// [`Terrain::heights`], and where `water` is asked the tile's water mask
    /// ([`water_mask`]): from the archive's water layer where it has data, else from the
    /// heights as stored.
    fn grid(&self, tile: GeoTile, water: bool) -> Result<(Vec<f32>, Option<Vec<u8>>), MakeError> {
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
        let lod = self.lod(tile.z);
        let mut heights = self.placed.sample(&positions, lod)?.unwrap_or_else(|| vec![f32::NAN; GRID * GRID]);
        let mask = match (water, &self.water) {
            (false, _) => None,
            (true, None) => Some(water_mask(&heights, GRID, None)),
            (true, Some(layer)) => Some(water_mask(&heights, GRID, layer.sample(&positions, lod)?.as_deref())),
        };
        mesh::fill_nodata(&mut heights, GRID);
        self.to_ellipsoid(tile, &mut heights);
        Ok((heights, mask))
    }

    /// Makes `tile`'s grid of heights above a geoid heights above the WGS 84 ellipsoid,
    /// as CesiumJS places them (`h = H + N`, N the geoid's undulation at each grid
    /// point); heights already ellipsoidal, or of an unknown datum, stay as they are.
    pub fn to_ellipsoid(&self, tile: GeoTile, heights: &mut [f32]) {
        if !self.datum.converts() || heights.len() != GRID * GRID {
            return;
        }
        // N changes over tens of kilometres: exact at every 8th point (and the last),
        // linear between; knots on the edges, so neighbours lift a shared edge alike.
        const STEP: usize = 8;
        let knots: Vec<usize> =
            (0..GRID).step_by(STEP).chain((!(GRID - 1).is_multiple_of(STEP)).then_some(GRID - 1)).collect();
        // Where each column falls between knots: the knot before it and the fraction.
        let spans: Vec<(usize, f64)> = (0..GRID)
            .map(|v| {
                let k = knots.partition_point(|&k| k <= v).clamp(1, knots.len() - 1) - 1;
                #[expect(clippy::cast_precision_loss, reason = "grid indices")]
                let f = (v - knots[k]) as f64 / (knots[k + 1] - knots[k]) as f64;
                (k, f)
            })
            .collect();
        // N along each knot row, at every column.
        let rows: Vec<Vec<f64>> = knots
            .iter()
            .map(|&row| {
                #[expect(clippy::cast_precision_loss, reason = "grid indices")]
                let at: Vec<f64> = knots
                    .iter()
                    .map(|&column| {
                        let (lon, lat) = tile.grid_point_at(column as f64, row as f64, GRID);
                        self.datum.to_ellipsoid(lon, lat)
                    })
                    .collect();
                spans.iter().map(|&(k, f)| at[k] + (at[k + 1] - at[k]) * f).collect()
            })
            .collect();
        for (row, &(k, f)) in spans.iter().enumerate() {
            let (a, b) = (&rows[k], &rows[k + 1]);
            for (column, h) in heights[row * GRID..(row + 1) * GRID].iter_mut().enumerate() {
                #[expect(clippy::cast_possible_truncation, reason = "heights are kept as f32")]
                let shift = (a[column] + (b[column] - a[column]) * f) as f32;
                *h += shift;
            }
        }
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
        let (heights, water) = self.grid(tile, extensions.water)?;
        let mesh = mesh::mesh(&heights, GRID, Self::bound(tile, &heights));
        let metadata = self.metadata(tile);
        let t = TileMesh { tile, mesh: &mesh, heights: &heights, size: GRID, water: water.as_deref() };
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
                let first = |v: u32| v << k;
                let last = |v: u32| ((v + 1) << k) - 1;
                let ranges = (self.available(z)?.into_iter())
                    .filter_map(|([x0, x1], [y0, y1])| {
                        let (cx, cy) = (
                            [x0.max(first(tile.x)), x1.min(last(tile.x))],
                            [y0.max(first(tile.y)), y1.min(last(tile.y))],
                        );
                        (cx[0] <= cx[1] && cy[0] <= cy[1]).then(|| range_json((cx, cy)))
                    })
                    .collect();
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
            .map(|ranges| serde_json::Value::Array(ranges.into_iter().map(range_json).collect()))
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
            "extensions": ["octvertexnormals", "watermask", "metadata"],
            "metadataAvailability": METADATA_LEVELS,
            "verticalDatum": self.vertical_datum_json(),
        })
    }
}

impl Terrain<'_> {
    /// What the tiles' heights are measured from, for `layer.json`: above the WGS 84
    /// ellipsoid when converted (and from what), else the archive's datum as it is.
    fn vertical_datum_json(&self) -> serde_json::Value {
        let d = self.datum;
        if d.converts() {
            serde_json::json!({ "heights": "ellipsoid", "epsg": 4979, "convertedFrom": d.describe() })
        } else {
            serde_json::json!({ "heights": d.reference.name(), "epsg": d.epsg, "describe": d.describe() })
        }
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

/// Where a grid of heights (`size` a side, rows from the north, as stored: before any
/// datum shift) is water: the fraction of the archive's water layer at a point (`water`,
/// the same grid) where it has data; elsewhere the sea as DEMs store it, a flat 0 (SRTM,
/// Copernicus): a point and its neighbours in the grid at one height within half a metre
/// of 0, a neighbour without data left out ([`terrastream_tiles::flat_sea`], the
/// renderer's rule). As the quantized-mesh water mask: one byte (0 all land, 255 all
/// water), else 256 x 256 from the north-west corner, rows north to south, bilinear between
/// the grid's points (the coast anti-aliased, as the format allows).
#[must_use]
pub fn water_mask(h: &[f32], size: usize, water: Option<&[f32]>) -> Vec<u8> {
    let at = |c: usize, r: usize| h[r * size + c];
    let sea: Vec<f32> = (0..size * size)
        .map(|i| {
            if let Some(w) = water.and_then(|w| w.get(i)).filter(|w| w.is_finite()) {
                return w.clamp(0.0, 1.0);
            }
            let (c, r) = (i % size, i / size);
            // Past the grid's rim: no neighbour (NaN), as the renderer's shade texels take it.
            let near = |cc: Option<usize>, rr: Option<usize>| match (cc, rr) {
                (Some(cc), Some(rr)) if cc < size && rr < size => at(cc, rr),
                _ => f32::NAN,
            };
            let neighbours = [
                near(c.checked_sub(1), Some(r)),
                near(Some(c + 1), Some(r)),
                near(Some(c), r.checked_sub(1)),
                near(Some(c), Some(r + 1)),
            ];
            if terrastream_tiles::flat_sea(h[i], neighbours) { 1.0 } else { 0.0 }
        })
        .collect();
    if sea.iter().all(|&s| s == 0.0) {
        return vec![0];
    }
    if sea.iter().all(|&s| s == 1.0) {
        return vec![255];
    }
    #[expect(clippy::cast_precision_loss, reason = "grid indices")]
    let last = (size - 1) as f32;
    let mut out = Vec::with_capacity(256 * 256);
    for j in 0..256u16 {
        for i in 0..256u16 {
            let (u, v) = ((f32::from(i) + 0.5) / 256.0 * last, (f32::from(j) + 0.5) / 256.0 * last);
            #[expect(clippy::cast_possible_truncation, clippy::cast_sign_loss, reason = "within the grid")]
            let (c0, r0) = (u.floor() as usize, v.floor() as usize);
            let (c1, r1) = ((c0 + 1).min(size - 1), (r0 + 1).min(size - 1));
            #[expect(clippy::cast_precision_loss, reason = "grid indices")]
            let (fu, fv) = (u - c0 as f32, v - r0 as f32);
            let top = sea[r0 * size + c0] * (1.0 - fu) + sea[r0 * size + c1] * fu;
            let bottom = sea[r1 * size + c0] * (1.0 - fu) + sea[r1 * size + c1] * fu;
            #[expect(clippy::cast_possible_truncation, clippy::cast_sign_loss, reason = "0..=255")]
            out.push(((top * (1.0 - fv) + bottom * fv) * 255.0).round() as u8);
        }
    }
    out
}
