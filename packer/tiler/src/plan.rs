//! Planning a tiling run: grids, LOD counts and encodings, decided before any tile.

use terrastream_format::{
    ElevationEncoding, ElevationScheme, Georeference, Layer, LayerExtent, LayerKind, Metadata, PayloadCompression,
    TileFormat, TileKey, levels_to_one,
};
use terrastream_pack::progress::Progress;

use crate::crs::Crs;
use crate::error::{Error, Result};
use crate::options::{ElevationStorage, TextureFormat, TextureInput, TileOptions};
use crate::raster::{ElevationSource, ImageSource, crs_placement};

/// Decides grids, LOD counts and encodings: everything but the tiles. Reads the elevation
/// once for its height range.
///
/// # Errors
/// Bad options; neither elevation nor texture; a texture whose extent differs from the
/// elevation's ([`Error::Input`] naming it); unreadable input.
pub fn plan(
    elevation: Option<&dyn ElevationSource>,
    texture: Option<&TextureInput<'_>>,
    name: &str,
    options: TileOptions,
    progress: &dyn Progress,
) -> Result<Plan> {
    plan_with(elevation, texture, name, options, Some(progress))
}

/// [`plan`]'s grids and LOD counts without reading any height: the heights' encoding is a
/// placeholder. What a shard plan needs (the bands and the inputs they read).
///
/// # Errors
/// As [`plan`], less unreadable heights.
pub fn plan_layout(
    elevation: Option<&dyn ElevationSource>,
    texture: Option<&TextureInput<'_>>,
    name: &str,
    options: TileOptions,
) -> Result<Plan> {
    plan_with(elevation, texture, name, options, None)
}

/// A plan; the heights' range read with `progress`, or not read at all without.
fn plan_with(
    elevation: Option<&dyn ElevationSource>,
    texture: Option<&TextureInput<'_>>,
    name: &str,
    options: TileOptions,
    progress: Option<&dyn Progress>,
) -> Result<Plan> {
    if options.border > 16 {
        return Err(Error::option("--border", options.border, "0..=16"));
    }
    if !(16..=4096).contains(&options.tile_size) {
        return Err(Error::option("--tile-size", options.tile_size, "16..=4096"));
    }
    let mut layers = Vec::new();
    let mut plans = Vec::new();
    let mut metadata = Metadata::new(name, Vec::new());
    // The data's extent in metres, when the elevation gives it.
    let mut extent = None;
    if let Some(e) = elevation {
        let planned = plan_elevation(e, options, progress)?;
        extent = Some(planned.extent);
        metadata.terrain = planned.terrain;
        metadata.terrain.data_extent = Some([planned.extent.0, planned.extent.1]);
        metadata.georeference = placed(e.georeference(), e.crs_pixel_size(), e.size(), planned.extent);
        layers.push(planned.layer);
        plans.push(planned.plan);
    }
    if let Some(t) = texture {
        let (layer, plan) = plan_texture(t, elevation, extent, options.border)?;
        if elevation.is_none() {
            let texel = layer.tile_world_size / f64::from(t.tile_size);
            let extent = (f64::from(plan.size.0) * texel, f64::from(plan.size.1) * texel, 0.0);
            metadata.georeference = placed(t.source.georeference(), t.source.crs_pixel_size(), t.source.size(), extent);
            metadata.terrain.base_tile_size = layer.tile_world_size / f64::from(t.tile_size);
            metadata.terrain.data_extent = Some([extent.0, extent.1]);
        }
        layers.push(layer);
        plans.push(plan);
    }
    if layers.is_empty() {
        return Err(Error::NothingToTile);
    }
    // Each elevation tile's height range, on the elevation's grid.
    if let Some(e) = layers.first().filter(|l| l.kind == LayerKind::Elevation) {
        let range = Layer {
            name: "elevation-range".into(),
            kind: LayerKind::HeightRange,
            format: TileFormat::MinMaxF32,
            compression: PayloadCompression::None,
            elevation: None,
            ..e.clone()
        };
        let tiles = plans[0].tiles;
        plans.push(LayerPlan { size: plans[0].size, offset: plans[0].offset, tiles, estimated_bytes: tiles * 8 });
        layers.push(range);
    }
    // Where each layer's samples end inside its grid (the writer adds the LODs).
    for (layer, plan) in layers.iter_mut().zip(&plans) {
        let texel = layer.sample_spacing(0);
        let (x0, z0) =
            (f64::from(plan.offset.0) * layer.tile_world_size, f64::from(plan.offset.1) * layer.tile_world_size);
        let (w, h) = match (layer.kind, metadata.terrain.data_extent) {
            (LayerKind::Elevation | LayerKind::HeightRange, Some([w, h])) => (w, h),
            _ => (f64::from(plan.size.0) * texel, f64::from(plan.size.1) * texel),
        };
        let world = [x0, z0, x0 + w, z0 + h];
        let lon_lat = metadata.georeference.as_ref().and_then(|g| lon_lat_box(g, world));
        layer.extent = Some(LayerExtent {
            coarsest_lod: 0,
            finest_lod: 0,
            world,
            detail: world,
            crs: None,
            lon_lat,
            partial: Vec::new(),
        });
    }
    // What the heights are measured from, with a geoid's undulation over the footprint.
    if let Some(datum) = elevation.and_then(ElevationSource::vertical_datum) {
        let lon_lat = layers.first().and_then(|l| l.extent.as_ref()).and_then(|x| x.lon_lat);
        metadata.vertical_datum = datum.resolve(lon_lat)?;
    }
    metadata.layers = layers;
    metadata.validate()?;
    Ok(Plan { metadata, layers: plans })
}

/// A source's georeference as the archive records it: with its CRS's PROJ definition
/// (when the tiler knows the CRS) and the scale from world metres to CRS units, for a
/// source of `size` pixels of `crs_pixel` CRS units drawn over `extent` (world width and
/// height in metres).
fn placed(
    georeference: Option<&Georeference>,
    crs_pixel: Option<(f64, f64)>,
    (w, h): (u32, u32),
    extent: (f64, f64, f64),
) -> Option<Georeference> {
    let mut g = georeference?.clone();
    if g.definition.is_none() {
        g.definition = g.crs.as_deref().and_then(|c| Crs::parse(c).ok()).map(|c| c.definition().to_owned());
    }
    if let Some((px, py)) = crs_pixel.filter(|_| extent.0 > 0.0 && extent.1 > 0.0) {
        g.scale = Some([f64::from(w) * px / extent.0, f64::from(h) * py / extent.1]);
    }
    Some(g)
}

/// Narrows each layer's given finest-level box (`extent.detail`) of `metadata` to the one
/// the tiles `keys` make, with its degrees, before a writer records them: the writer
/// keeps a given box's degrees only where its tiles make that box, and it cannot
/// transform boxes itself. A collection's plan gives the whole grid's box, which its
/// finest level covers only where the surveys are; so its run, and the merge of its
/// shards (whose boxes are each their own), record the same box with the same degrees.
pub(crate) fn settle_details(metadata: &mut Metadata, keys: impl Iterator<Item = TileKey>) {
    let mut found = vec![terrastream_format::ExtentBuilder::default(); metadata.layers.len()];
    for key in keys {
        if let Some(builder) = found.get_mut(usize::from(key.layer())) {
            builder.add(key);
        }
    }
    let georeference = metadata.georeference.clone();
    for (layer, builder) in metadata.layers.iter_mut().zip(&found) {
        let Some(made) = builder.finish(layer) else { continue };
        let Some(given) = layer.extent.as_mut() else { continue };
        let detail = terrastream_format::intersect(made.detail, given.detail).unwrap_or(made.detail);
        if detail != given.detail {
            given.detail = detail;
            given.lon_lat = georeference.as_ref().and_then(|g| lon_lat_box(g, detail));
        }
    }
}

/// West, south, east, north in degrees of a world box, through the georeference's CRS:
/// its edges sampled, so that a projection's curved meridians and parallels are bounded.
pub(crate) fn lon_lat_box(g: &Georeference, [x0, z0, x1, z1]: [f64; 4]) -> Option<[f64; 4]> {
    let crs = Crs::parse(g.definition.as_deref().or(g.crs.as_deref())?).ok()?;
    let to_degrees = crate::crs::Transform::new(&crs, &Crs::wgs84());
    const STEPS: u32 = 16;
    let mut out: Option<[f64; 4]> = None;
    for i in 0..=STEPS {
        let t = f64::from(i) / f64::from(STEPS);
        let (x, z) = (x0 + (x1 - x0) * t, z0 + (z1 - z0) * t);
        for (wx, wz) in [(x, z0), (x, z1), (x0, z), (x1, z)] {
            let (cx, cy) = g.world_to_crs(wx, wz)?;
            let (lon, lat) = to_degrees.apply(cx, cy)?;
            out = Some(
                out.map_or([lon, lat, lon, lat], |b| [b[0].min(lon), b[1].min(lat), b[2].max(lon), b[3].max(lat)]),
            );
        }
    }
    out
}

/// The elevation's part of a plan.
struct ElevationPlan {
    layer: Layer,
    plan: LayerPlan,
    terrain: terrastream_format::Terrain,
    /// Width and height in metres, and the grid's aspect (samples across / down).
    extent: (f64, f64, f64),
}

/// Samples across that make samples of spacing `(sx, sy)` square (metres), where `w` of
/// them are more than 1 % from square (a geographic grid's are narrower than they are
/// tall); None where they are square enough.
fn square_width(w: u32, (sx, sy): (f64, f64)) -> Option<u32> {
    let ratio = sx / sy;
    #[expect(clippy::cast_possible_truncation, clippy::cast_sign_loss, reason = "a sane sample count")]
    ((ratio - 1.0).abs() >= 0.01).then(|| ((f64::from(w) * ratio).round() as u32).max(1))
}

/// The grid `grid` of heights `e` is tiled on where their samples are not square: as
/// many columns over the same area as [`plan`] resamples their rows to (None: square
/// already). A collection opens its inputs onto it, as `update` opens them onto an
/// archive's grid, instead of resampling rows.
#[must_use]
pub fn squared_grid(e: &dyn ElevationSource, grid: crate::raster::GridSpec) -> Option<crate::raster::GridSpec> {
    let width = square_width(grid.size.0, e.spacing())?;
    let pixel = (grid.pixel.0 * f64::from(grid.size.0) / f64::from(width), grid.pixel.1);
    Some(crate::raster::GridSpec { origin: grid.origin, pixel, size: (width, grid.size.1) })
}

/// The grid imagery on `grid`, over the area of heights `e`, is tiled on where its pixels
/// are not square in metres as the heights' plan makes them: as many columns as [`plan`]
/// gives its texture layer (None: within 1 % of them already). An imagery collection
/// opens its pictures onto it, as a collection of heights opens them onto
/// [`squared_grid`]'s.
#[must_use]
pub fn squared_texture_grid(e: &dyn ElevationSource, grid: crate::raster::GridSpec) -> Option<crate::raster::GridSpec> {
    let width = texture_width(grid.size.1, elevation_extent(e));
    let (now, wanted) = (f64::from(grid.size.0), f64::from(width));
    ((wanted / now - 1.0).abs() >= 0.01).then(|| crate::raster::GridSpec {
        origin: grid.origin,
        pixel: (grid.pixel.0 * now / wanted, grid.pixel.1),
        size: (width, grid.size.1),
    })
}

/// The columns and spacing (metres) heights `e` are tiled at: square samples, their rows
/// resampled along x where the source's are more than 1 % from square.
fn square_samples(e: &dyn ElevationSource) -> (u32, f64) {
    let (w, _) = e.size();
    let (sx, sy) = e.spacing();
    match square_width(w, (sx, sy)) {
        None => (w, (sx * sy).sqrt()),
        Some(width) => (width, sy),
    }
}

/// The width and height in metres of heights `e` as [`plan`] tiles them.
fn elevation_extent(e: &dyn ElevationSource) -> (f64, f64) {
    let (width, spacing) = square_samples(e);
    (f64::from(width) * spacing, f64::from(e.size().1) * spacing)
}

/// Texels across a texture `rows` tall over heights of extent `(ex, ez)` (metres): square
/// in metres, as tiles are.
fn texture_width(rows: u32, (ex, ez): (f64, f64)) -> u32 {
    #[expect(clippy::cast_possible_truncation, clippy::cast_sign_loss, reason = "a pixel count")]
    let width = ((f64::from(rows) * ex / ez).round() as u32).max(1);
    width
}

/// The elevation layer: square samples (rows resampled along x when the source's are more
/// than 1 % from square), an encoding that keeps the height range exact enough, the
/// terrain's settings.
fn plan_elevation(
    e: &dyn ElevationSource,
    options: TileOptions,
    progress: Option<&dyn Progress>,
) -> Result<ElevationPlan> {
    let res = options.tile_size;
    let (w, h) = e.size();
    if w == 0 || h == 0 {
        return Err(Error::input(e.path(), format!("the raster is empty ({w}x{h})")));
    }
    let (width, spacing) = square_samples(e);
    let extent = (f64::from(width) * spacing, f64::from(h) * spacing, f64::from(w) / f64::from(h));
    let (min, max, estimated) = match progress {
        Some(progress) => {
            let (min, max) = height_range(e, progress)?;
            (min, max, e.height_range_estimate()?.map(|(lo, hi)| (f64::from(lo), f64::from(hi))))
        }
        None => (0.0, 0.0, None),
    };
    let encoding = chosen_encoding(options.storage, (min, max), estimated);
    let (nx, ny) = (width.div_ceil(res), h.div_ceil(res));
    let float = encoding.scheme == ElevationScheme::Float32;
    let layer = Layer {
        name: "elevation".into(),
        kind: LayerKind::Elevation,
        format: if float { TileFormat::RawF32 } else { TileFormat::RawU16 },
        compression: if float { PayloadCompression::Zstd } else { PayloadCompression::ZstdGradient },
        tile_resolution: res,
        border: options.border,
        num_x_tiles: nx,
        num_y_tiles: ny,
        num_lods: levels_to_one(nx.max(ny)),
        tile_world_size: f64::from(res) * spacing,
        elevation: Some(encoding),
        extent: None,
    };
    let tiles = tiles_over((width, h), res, layer.num_lods);
    let plan = LayerPlan {
        size: (width, h),
        offset: (0, 0),
        tiles,
        // u16: gradient-coded, 0.23-0.31 bytes a sample on the bench DEMs; rough terrain more.
        estimated_bytes: estimate(tiles, res, options.border, if float { 2.4 } else { 0.5 }),
    };
    let mut terrain = terrastream_format::Terrain {
        base_tile_size: spacing,
        high_detail_range: spacing * 64.0,
        num_detail_levels: u32::from(layer.num_lods) + 6,
        ..terrastream_format::Terrain::default()
    };
    set_height_range(&mut terrain, (min, max));
    Ok(ElevationPlan { layer, plan, terrain, extent })
}

/// Records the heights' range `min..=max` in `terrain`.
pub(crate) fn set_height_range(terrain: &mut terrastream_format::Terrain, (min, max): (f64, f64)) {
    let span = max - min;
    (terrain.min_elevation, terrain.max_elevation) = (min, max);
    (terrain.displacement, terrain.elevation_range) = (span, span);
}

/// How heights are stored, given their range `exact` and, where the source has one, an
/// estimate of it from part of the heights: the estimate's encoding if it holds the whole
/// range, else the range's own. A whole run finds this without the range: it tiles with
/// the estimate's encoding, tracking the range, and only if a height falls outside what
/// that encoding holds does it scan the range and tile again. Shards given the range
/// (`--height-range`) make the same choice from it, so they encode as a whole run does.
pub(crate) fn chosen_encoding(
    storage: ElevationStorage,
    exact: (f64, f64),
    estimate: Option<(f64, f64)>,
) -> ElevationEncoding {
    if let Some(estimate) = estimate {
        let speculative = estimated_encoding(storage, estimate);
        let (lo, hi) = holds(&speculative);
        #[expect(clippy::cast_possible_truncation, reason = "heights are f32, compared as rows compare them")]
        if lo <= exact.0 as f32 && exact.1 as f32 <= hi {
            return speculative;
        }
    }
    height_encoding(storage, exact.0, exact.1 - exact.0)
}

/// The encoding for heights estimated to lie in `min..=max`: the step for twice the
/// estimated span (the powers of two a step is made of leave it the same as the span's
/// own below 2 km of span, at most twice as coarse above), and the estimate in the
/// middle of the codes, with at least half its span to spare on each side.
pub(crate) fn estimated_encoding(storage: ElevationStorage, (min, max): (f64, f64)) -> ElevationEncoding {
    let span = max - min;
    let encoding = height_encoding(storage, min, 2.0 * span);
    if encoding.scheme != ElevationScheme::QuantizedU16 {
        return encoding;
    }
    let step = encoding.scale;
    let spare = ((65_534.0 - (span / step).ceil()) / 2.0).floor().max(0.0);
    ElevationEncoding { offset: ((min / step).floor() - 1.0 - spare) * step, ..encoding }
}

/// The heights `encoding` holds: those whose code lands in 1..=65534 (a step inside the
/// u16 codes, whatever the rounding), all for f32.
pub(crate) fn holds(encoding: &ElevationEncoding) -> (f32, f32) {
    if encoding.scheme != ElevationScheme::QuantizedU16 {
        return (f32::NEG_INFINITY, f32::INFINITY);
    }
    let height = |code: f64| {
        #[expect(clippy::cast_possible_truncation, reason = "heights are f32")]
        let h = encoding.height(code) as f32;
        h
    };
    (height(1.0), height(65_534.0))
}

/// How heights are stored: quantized u16 with a power-of-two step of at most 1/16 that
/// fits the span, else f32 (or as `storage` says).
fn height_encoding(storage: ElevationStorage, min: f64, span: f64) -> ElevationEncoding {
    let step = (0..=8).map(|k| f64::from(1u32 << k) / 16.0).find(|s| span / s < 65_000.0);
    match (storage, step) {
        (ElevationStorage::F32, _) | (ElevationStorage::Auto, None) => {
            ElevationEncoding { scheme: ElevationScheme::Float32, scale: 1.0, offset: 0.0, nodata: None }
        }
        (_, step) => {
            let step = step.unwrap_or(span / 65_000.0);
            // 0 is nodata; heights start at 1.
            let offset = (min / step).floor() * step - step;
            ElevationEncoding { scheme: ElevationScheme::QuantizedU16, scale: step, offset, nodata: Some(0.0) }
        }
    }
}

/// Whether the texture can be tiled as given: not empty, its options in range, and
/// placed in the elevation's CRS when both say where they lie.
fn check_texture(t: &TextureInput<'_>, elevation: Option<&dyn ElevationSource>) -> Result<()> {
    let path = t.source.path();
    let (w, h) = t.source.size();
    if w == 0 || h == 0 {
        return Err(Error::input(path, format!("the image is empty ({w}x{h})")));
    }
    if !(16..=4096).contains(&t.tile_size) {
        return Err(Error::option("--texture-tile-size", t.tile_size, "16..=4096"));
    }
    if let TextureFormat::Jpeg(q) = t.format
        && !(1..=100).contains(&q)
    {
        return Err(Error::option("--jpeg-quality", q, "1..=100"));
    }
    // An image that says where it lies is placed by it, never by a guess: in another CRS
    // than the elevation it must come warped onto the elevation's extent (`Warped`).
    if let (Some(e), Some(image_crs)) = (elevation, t.source.georeference().and_then(|g| g.crs.as_deref()))
        && let Some(dem_crs) = e.georeference().and_then(|g| g.crs.as_deref()).filter(|c| *c != image_crs)
    {
        return Err(Error::input(
            path,
            format!(
                "the image lies in {image_crs}, the elevation in {dem_crs}: warp it onto the elevation (Warped::over)"
            ),
        ));
    }
    Ok(())
}

/// The texture layer: over the elevation's extent (checked to be the same area), or alone
/// at `pixel_size` metres a pixel.
fn plan_texture(
    t: &TextureInput<'_>,
    elevation: Option<&dyn ElevationSource>,
    extent: Option<(f64, f64, f64)>,
    border: u8,
) -> Result<(Layer, LayerPlan)> {
    let path = t.source.path();
    let (w, h) = t.source.size();
    check_texture(t, elevation)?;
    let (fw, fh) = (f64::from(w), f64::from(h));
    let (width, world_width) = match extent {
        Some((ex, ez, grid_aspect)) => {
            // The texture covers the elevation's area on the same grid (both geographic,
            // say: its pixels have the DEM's pixel shape) or in metres (square pixels).
            let near = |a: f64, b: f64| (a / b - 1.0).abs() <= 0.02;
            // Or both say where they lie, in one CRS, and cover the same area there
            // (pixels of any shape: degrees square in the image, not in the DEM).
            let same_place = elevation.is_some_and(|e| same_crs_extent(e, t.source));
            if !same_place && !near(fw / fh, grid_aspect) && !near(fw / fh, ex / ez) {
                return Err(Error::input(
                    path,
                    format!(
                        "mismatched extents: the elevation covers {ex:.0} x {ez:.0} m (aspect {:.3}; its grid \
                         {grid_aspect:.3}), the texture is {w} x {h} px (aspect {:.3}); both must cover the same area",
                        ex / ez,
                        fw / fh
                    ),
                ));
            }
            // Texels square in metres, as tiles are: resample along x where they are not.
            let width = texture_width(h, (ex, ez));
            (width, ex)
        }
        None => {
            if !(t.pixel_size.is_finite() && t.pixel_size > 0.0) {
                return Err(Error::option("--pixel-size", t.pixel_size, "a positive number of metres"));
            }
            (w, fw * t.pixel_size)
        }
    };
    let (nx, ny) = (width.div_ceil(t.tile_size), h.div_ceil(t.tile_size));
    let layer = Layer {
        name: "texture".into(),
        kind: LayerKind::Texture,
        format: t.format.tile_format(),
        compression: t.format.compression(),
        tile_resolution: t.tile_size,
        border,
        num_x_tiles: nx,
        num_y_tiles: ny,
        num_lods: levels_to_one(nx.max(ny)),
        tile_world_size: f64::from(t.tile_size) * world_width / f64::from(width),
        elevation: None,
        extent: None,
    };
    let tiles = tiles_over((width, h), t.tile_size, layer.num_lods);
    let estimated_bytes = estimate(tiles, t.tile_size, border, t.format.typical_bytes_per_texel());
    Ok((layer, LayerPlan { size: (width, h), offset: (0, 0), tiles, estimated_bytes }))
}

/// Typical stored bytes of `tiles` tiles of `res` texels plus `border`.
#[expect(clippy::cast_possible_truncation, clippy::cast_sign_loss, clippy::cast_precision_loss, reason = "an estimate")]
fn estimate(tiles: u64, res: u32, border: u8, bytes_per_texel: f64) -> u64 {
    let edge = u64::from(res + 2 * u32::from(border));
    (tiles as f64 * (edge * edge) as f64 * bytes_per_texel) as u64
}

/// Do the elevation and the image both lie, by their georeference, over the same area of
/// one CRS (each edge within 2% of the extent)?
fn same_crs_extent(elevation: &dyn ElevationSource, image: &dyn ImageSource) -> bool {
    // The CRS, and west, north, width and height in its units.
    fn extent(placed: Option<(&str, [f64; 2], (f64, f64))>, (w, h): (u32, u32)) -> Option<(&str, [f64; 4])> {
        placed.map(|(crs, origin, pixel)| (crs, [origin[0], origin[1], f64::from(w) * pixel.0, f64::from(h) * pixel.1]))
    }
    let (Some((a_crs, a)), Some((b_crs, b))) = (
        extent(crs_placement(elevation.georeference(), elevation.crs_pixel_size()), elevation.size()),
        extent(crs_placement(image.georeference(), image.crs_pixel_size()), image.size()),
    ) else {
        return false;
    };
    let close = |x: f64, y: f64, span: f64| (x - y).abs() <= 0.02 * span;
    a_crs == b_crs
        && close(a[0], b[0], a[2])
        && close(a[0] + a[2], b[0] + b[2], a[2])
        && close(a[1], b[1], a[3])
        && close(a[1] - a[3], b[1] - b[3], a[3])
}

/// What [`plan`] decides: the metadata (grids, LOD counts, encodings) and the work.
#[derive(Clone, Debug)]
pub struct Plan {
    /// The archive's metadata.
    pub metadata: Metadata,
    /// Per layer, in the metadata's order: LOD-0 size in samples after squaring (rows are
    /// resampled to its width), tiles to cut (an upper bound: those with no data are left
    /// out) and typical stored bytes.
    pub layers: Vec<LayerPlan>,
}

/// One layer of a [`Plan`].
#[derive(Clone, Debug, PartialEq)]
pub struct LayerPlan {
    /// Samples across and down at LOD 0.
    pub size: (u32, u32),
    /// The layer's LOD-0 tile where these samples start: (0, 0), or for the crop of an
    /// update, where the crop lies (its tiles' keys are shifted by it; LOD 0 only).
    pub offset: (u32, u32),
    /// Tiles with data or not, every LOD.
    pub tiles: u64,
    /// A rough size of the stored tiles (typical compression ratios; within about 2x).
    pub estimated_bytes: u64,
}

impl Plan {
    /// Typical archive size: the layers' estimates.
    pub fn estimated_bytes(&self) -> u64 {
        self.layers.iter().map(|l| l.estimated_bytes).sum()
    }

    /// Tiles to cut, all layers.
    pub fn tiles(&self) -> u64 {
        self.layers.iter().map(|l| l.tiles).sum()
    }
}

/// Tiles over `size` samples at every LOD of a layer.
fn tiles_over(size: (u32, u32), res: u32, lods: u8) -> u64 {
    (0..lods)
        .map(|lod| {
            let side = |n: u32| u64::from(n.div_ceil(1 << lod).max(1).div_ceil(res));
            side(size.0) * side(size.1)
        })
        .sum()
}

/// The elevation's height range (a pass over the raster, making no rows where the source can).
fn height_range(elevation: &dyn ElevationSource, progress: &dyn Progress) -> Result<(f64, f64)> {
    progress.start("scan", u64::from(elevation.size().1));
    let mut told = 0u32;
    let (min, max) = elevation.height_range(&mut |rows| {
        if rows / 64 != told / 64 {
            progress.check().map_err(Error::from)?;
        }
        progress.advance(u64::from(rows.saturating_sub(told)));
        told = rows;
        Ok(())
    })?;
    let (min, max) = (f64::from(min), f64::from(max));
    if !min.is_finite() {
        return Err(Error::input(elevation.path(), "the raster holds no data (every sample is nodata)"));
    }
    Ok((min, max))
}
