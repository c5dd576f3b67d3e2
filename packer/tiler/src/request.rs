//! A tiling request as a user states it (inputs, CRS, resolution, encodings), and the
//! decisions that turn it into sources: one elevation file or a mosaic of several (or of
//! one geographic file, onto a transverse Mercator centred on it), imagery as one file,
//! a window of it over the elevation, a warp of it onto the elevation, or a mosaic.
//! `terrastream tile` and any library caller go through [`Sources::open`] and
//! [`Sources::inputs`], then [`crate::plan()`] or [`crate::tile_shard`].

use std::path::{Path, PathBuf};

use terrastream_format::ElevationEncoding;

use crate::crs::Crs;
use crate::error::{Error, Result};
use crate::options::{TextureFormat, TextureInput};
use crate::raster::{DatumName, datum_of_input};
use crate::raster::{
    ElevationFile, ElevationSource, GridSpec, Heights, ImageFile, ImageSource, ImageWindow, KnownRange, Mosaic,
    MosaicOptions, Pixels, Warped, image_pixel_metres, is_vrt, open_elevation, open_image,
};

/// What to tile.
#[derive(Clone, Debug, Default)]
pub struct TileRequest {
    /// Elevation rasters (files, expanded: see [`crate::expand_inputs`]).
    pub elevation: Vec<PathBuf>,
    /// Imagery (files, expanded).
    pub texture: Vec<PathBuf>,
    /// How the elevation's pixels map to heights (`None`: samples are heights).
    pub encoding: Option<ElevationEncoding>,
    /// Output CRS of a mosaic (`EPSG:xxxx` or a PROJ string); asking for one makes a mosaic.
    pub crs: Option<String>,
    /// Output spacing of a mosaic in metres; asking for one makes a mosaic.
    pub resolution: Option<f64>,
    /// Output extent of a mosaic in its CRS (min x, min y, max x, max y): a grid given
    /// whole, as an archive's own that `update` tiles onto (default: the inputs' union).
    pub extent: Option<[f64; 4]>,
    /// Keep one geographic input on its own grid instead of a transverse Mercator.
    pub keep_geographic: bool,
    /// Metres between samples of an input that does not say.
    pub sample_spacing: Option<f64>,
    /// The height range, known beforehand (a shard of a run): no range pass.
    pub height_range: Option<(f32, f32)>,
    /// Leave out mosaic inputs, or parts of them, that cannot be used.
    pub skip_bad_inputs: bool,
    /// Texture pixels per tile edge.
    pub texture_tile_size: u32,
    /// Texture tile encoding.
    pub texture_format: TextureFormat,
    /// Metres per texture pixel without elevation (default: the georeference's, else 1).
    pub pixel_size: Option<f64>,
    /// The elevation mosaic's grid, given whole (with `crs`): a shard of a planned run,
    /// given only the inputs its band reads, makes the grid all of them make.
    pub elevation_grid: Option<GridSpec>,
    /// The imagery mosaic's grid, given whole, as `elevation_grid`.
    pub texture_grid: Option<GridSpec>,
    /// What the elevation's heights are measured from, named by the person: overrides
    /// what the inputs say (`--vertical-datum`).
    pub vertical_datum: Option<DatumName>,
    /// The datum the output's heights must be in (an update's archive's): inputs that name
    /// another are converted to it (default: the first one named).
    pub target_datum: Option<DatumName>,
}

impl TileRequest {
    /// Each VRT whose sources are of different resolutions, each a whole file read as it
    /// is, replaced by its files (in its order), so that each is tiled as deep as its own
    /// resolution reaches (a collection) where the VRT would be one input at its finest
    /// source's spacing. Other VRTs stay as they are.
    ///
    /// # Errors
    /// A VRT that cannot be read.
    pub fn vrts_as_their_files(&mut self) -> Result<()> {
        for (inputs, heights) in [(&mut self.elevation, true), (&mut self.texture, false)] {
            let mut out = Vec::with_capacity(inputs.len());
            for path in inputs.drain(..) {
                let files = if !is_vrt(&path) {
                    None
                } else if heights {
                    crate::raster::vrt_files_by_resolution::<Heights>(&path)?
                } else {
                    crate::raster::vrt_files_by_resolution::<Pixels>(&path)?
                };
                match files {
                    Some(files) => {
                        tracing::info!(
                            vrt = %path.display(),
                            files = files.len(),
                            "a VRT of sources of different resolutions: each of its files tiled as deep as it reaches"
                        );
                        out.extend(files);
                    }
                    None => out.push(path),
                }
            }
            *inputs = out;
        }
        Ok(())
    }
}

/// The opened inputs of a [`TileRequest`].
pub struct Sources {
    heights: Option<Mosaic<Heights>>,
    file: Option<ElevationFile>,
    images: Option<Mosaic<Pixels>>,
    image: Option<ImageFile>,
    height_range: Option<(f32, f32)>,
    texture_tile_size: u32,
    texture_format: TextureFormat,
    pixel_size: Option<f64>,
}

impl std::fmt::Debug for Sources {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("Sources")
            .field("height_mosaic", &self.heights.is_some())
            .field("image_mosaic", &self.images.is_some())
            .finish_non_exhaustive()
    }
}

impl Sources {
    /// Opens the request's inputs (headers; a mosaic's footprints), deciding how each is read.
    ///
    /// # Errors
    /// Raster errors naming an input that cannot be used, [`Error::InvalidOption`] for a
    /// bad spacing, CRS errors.
    pub fn open(request: &TileRequest) -> Result<Self> {
        let crs = request.crs.as_deref().map(Crs::parse).transpose()?;
        let mut heights = height_mosaic(request, crs.as_ref())?;
        let datum = vertical_datum(request, heights.as_mut())?;
        let file = match request.elevation.first().filter(|_| heights.is_none()) {
            Some(path) => Some(elevation_file(path, request)?.with_datum(datum.clone())),
            None => None,
        };
        if let Some(m) = &mut heights {
            m.set_datum(datum);
        }
        let elevation: Option<&dyn ElevationSource> = match (&heights, &file) {
            (Some(m), _) => Some(m),
            (None, Some(f)) => Some(f),
            (None, None) => None,
        };
        let images = image_mosaic(request, elevation, crs)?;
        let image = match request.texture.first() {
            Some(path) if images.is_none() => Some(open_image(path)?),
            _ => None,
        };
        Ok(Self {
            heights,
            file,
            images,
            image,
            height_range: request.height_range,
            texture_tile_size: request.texture_tile_size,
            texture_format: request.texture_format,
            pixel_size: request.pixel_size,
        })
    }

    /// Gives the elevation's height range (found without reading a height, e.g. from its
    /// statistics): as `TileRequest::height_range` would, without opening the inputs again.
    pub fn set_height_range(&mut self, range: (f32, f32)) {
        self.height_range = Some(range);
    }

    /// The imagery's mosaic, where the inputs make one.
    pub fn image_mosaic(&self) -> Option<&Mosaic<Pixels>> {
        self.images.as_ref()
    }

    /// The heights' mosaic, where the inputs make one.
    pub fn height_mosaic(&self) -> Option<&Mosaic<Heights>> {
        self.heights.as_ref()
    }

    /// The mosaics opened, of heights and of imagery: what a caller that reads them itself
    /// (`update`, which crops them to what they touch) takes.
    pub fn into_mosaics(self) -> (Option<Mosaic<Heights>>, Option<Mosaic<Pixels>>) {
        (self.heights, self.images)
    }

    /// The sources to plan and tile: the elevation (with its known range) and the imagery
    /// placed over it (a window of it in the elevation's CRS, a warp of it from another).
    ///
    /// # Errors
    /// [`Error::Input`] for imagery whose georeference cannot be placed over the elevation.
    pub fn inputs(&self) -> Result<Inputs<'_>> {
        let base: Option<&dyn ElevationSource> = match (&self.heights, &self.file) {
            (Some(m), _) => Some(m),
            (None, Some(f)) => Some(f),
            (None, None) => None,
        };
        let known = base.zip(self.height_range).map(|(e, range)| KnownRange::new(e, range));
        let image = self.image.as_ref().map(|i| i as &dyn ImageSource);
        // Both georeferenced in one CRS: only the part of the image over the elevation is used.
        let window = match (base, image) {
            (Some(e), Some(i)) => ImageWindow::over(e, i)?,
            _ => None,
        };
        if let Some(w) = &window {
            let (x, y, width, height) = w.bounds();
            tracing::info!(
                "texture: pixels {x}..{}, {y}..{} of the image lie over the elevation",
                x + width,
                y + height
            );
        }
        // Georeferenced in another CRS: resampled onto the elevation by both georeferences.
        let warped = match (base, image) {
            (Some(e), Some(i)) => Warped::over(e, i)?,
            _ => None,
        };
        if let Some(w) = &warped {
            let (width, height) = w.size();
            tracing::info!("texture: reprojected onto the elevation's extent, {width}x{height} texels");
        }
        Ok(Inputs { sources: self, base, known, window, warped })
    }

    /// Inputs left out with `skip_bad_inputs`, wholly or in part, and why.
    pub fn skipped(&self) -> Vec<(PathBuf, String)> {
        self.heights.iter().flat_map(Mosaic::skipped).chain(self.images.iter().flat_map(Mosaic::skipped)).collect()
    }
}

/// The sources of a request, placed: see [`Sources::inputs`].
pub struct Inputs<'a> {
    sources: &'a Sources,
    base: Option<&'a dyn ElevationSource>,
    known: Option<KnownRange<'a>>,
    window: Option<ImageWindow<'a>>,
    warped: Option<Warped<'a>>,
}

impl Inputs<'_> {
    /// The elevation, if any.
    pub fn elevation(&self) -> Option<&dyn ElevationSource> {
        match &self.known {
            Some(k) => Some(k),
            None => self.base,
        }
    }

    /// The imagery as the tiler takes it, if any.
    pub fn texture(&self) -> Option<TextureInput<'_>> {
        let s = self.sources;
        let source: &dyn ImageSource = match (&s.images, &self.warped, &self.window, &s.image) {
            (Some(m), ..) => m,
            (None, Some(w), ..) => w,
            (None, None, Some(w), _) => w,
            (None, None, None, Some(i)) => i,
            (None, None, None, None) => return None,
        };
        Some(TextureInput {
            source,
            tile_size: s.texture_tile_size,
            format: s.texture_format,
            pixel_size: texture_pixel_size(s.pixel_size, source),
        })
    }
}

/// Whether a CRS, spacing or extent was asked for: the inputs go onto that grid.
fn grid_asked(request: &TileRequest) -> bool {
    request.crs.is_some()
        || request.resolution.is_some()
        || request.extent.is_some()
        || request.elevation_grid.is_some()
}

/// The elevation inputs as one mosaic on one output grid, when they need one: several
/// inputs, a VRT (a mosaic of its sources, even alone), a grid asked for, or one
/// geographic GeoTIFF of a region (onto a transverse Mercator centred on it, as a
/// mosaic's geographic inputs go: a metre is a metre everywhere, not only at the centre
/// latitude; one spanning more than [`crate::crs::REGION_DEGREES`] keeps its grid).
fn height_mosaic(request: &TileRequest, crs: Option<&Crs>) -> Result<Option<Mosaic<Heights>>> {
    let inputs = &request.elevation;
    let vrt = inputs.iter().any(|p| is_vrt(p));
    let geographic = match inputs.as_slice() {
        [one] if !vrt && !request.keep_geographic && request.sample_spacing.is_none() => {
            let file = open_elevation(one, request.encoding)?;
            // More than a region keeps its own grid (the globe draws it undistorted).
            let region = file
                .georeference()
                .and_then(|g| g.lat_lon_bounds)
                .is_none_or(|[w, s, e, n]| !crate::crs::spans_more_than_region(w, s, e, n));
            file.is_geographic_tiff() && region
        }
        _ => false,
    };
    if inputs.is_empty() || !(inputs.len() > 1 || vrt || geographic || grid_asked(request)) {
        return Ok(None);
    }
    let options = MosaicOptions {
        crs: crs.cloned(),
        resolution: request.resolution,
        cache_bytes: None,
        extent: request.extent,
        skip_bad_inputs: request.skip_bad_inputs,
        grid: request.elevation_grid,
    };
    let mosaic = Mosaic::<Heights>::open(inputs, &options)?;
    let (w, h) = mosaic.size();
    tracing::info!("mosaic of {} inputs in {}: {w} x {h} samples", inputs.len(), mosaic.crs().name());
    Ok(Some(mosaic))
}

/// The imagery as one mosaic, when it needs one: several images (or a VRT of them), over
/// the elevation's extent in its CRS; with no elevation, on the grid asked for, if any
/// (then even one image is reprojected).
fn image_mosaic(
    request: &TileRequest,
    elevation: Option<&dyn ElevationSource>,
    crs: Option<Crs>,
) -> Result<Option<Mosaic<Pixels>>> {
    let textures = &request.texture;
    let alone = elevation.is_none() && grid_asked(request);
    if !(textures.len() > 1 || textures.iter().any(|p| is_vrt(p)) || alone || request.texture_grid.is_some()) {
        return Ok(None);
    }
    let (crs, extent, resolution) = match elevation {
        Some(e) => {
            let (crs, extent) = elevation_extent(e)?;
            (crs, extent, None)
        }
        None => (crs, request.extent, request.resolution),
    };
    let grid = request.texture_grid;
    let options = MosaicOptions {
        crs,
        extent,
        resolution,
        skip_bad_inputs: request.skip_bad_inputs,
        grid,
        ..MosaicOptions::default()
    };
    let mosaic = Mosaic::<Pixels>::open(textures, &options)?;
    let (w, h) = ImageSource::size(&mosaic);
    tracing::info!("texture: a mosaic of {} images in {}, {w} x {h} pixels", textures.len(), mosaic.crs().name());
    Ok(Some(mosaic))
}

/// What the elevation's heights are measured from: the datum named in the request (for
/// every input), else the one the inputs name (GeoTIFF `VerticalCSTypeGeoKey`, a compound
/// CRS's WKT beside them or in a VRT), else unknown with a warning. Inputs of a mosaic
/// that name different datums are converted to the request's target datum, else to the
/// first one named; inputs that name none are taken to be in it.
///
/// # Errors
/// An input naming a vertical CRS with no model here; a geoid grid that is missing.
fn vertical_datum(request: &TileRequest, mosaic: Option<&mut Mosaic<Heights>>) -> Result<Option<DatumName>> {
    if let Some(d) = &request.vertical_datum {
        return Ok(Some(d.clone()));
    }
    let Some(first) = request.elevation.first() else { return Ok(None) };
    // Each file's datum: a VRT's sources take the VRT's.
    let mut named: Vec<(PathBuf, DatumName)> = vec![];
    for path in &request.elevation {
        let Some(datum) = datum_of_input(path)? else { continue };
        if is_vrt(path) {
            for source in crate::raster::read_vrt(path)?.sources {
                named.push((source.path, datum.clone()));
            }
        }
        named.push((path.clone(), datum));
    }
    let target = request.target_datum.clone().or_else(|| named.first().map(|(_, d)| d.clone()));
    let Some(target) = target.filter(|_| !named.is_empty()) else {
        if let Some(t) = &request.target_datum {
            return Ok(Some(t.clone()));
        }
        tracing::warn!(
            "{}: the heights name no vertical datum: recorded as unknown (name it with --vertical-datum: 5773 for EGM96, as SRTM's; 3855 for EGM2008, as Copernicus'; 4979 for ellipsoidal)",
            first.display()
        );
        return Ok(None);
    };
    if named.iter().all(|(_, d)| *d == target) {
        return Ok(Some(target));
    }
    let Some(mosaic) = mosaic else { return Ok(Some(target)) };
    // Each distinct datum's grid read once.
    let mut loaded: Vec<crate::raster::LoadedDatum> = vec![];
    for d in named.iter().map(|(_, d)| d).chain(std::iter::once(&target)) {
        if !loaded.iter().any(|l| l.name() == d) {
            loaded.push(d.load()?);
        }
    }
    let to = loaded.iter().find(|l| *l.name() == target).cloned().ok_or(Error::NothingToTile)?;
    let datum_of = |path: &Path| {
        let d = named.iter().find(|(p, _)| p == path).map(|(_, d)| d)?;
        loaded.iter().find(|l| l.name() == d).cloned()
    };
    let converted = mosaic.convert_datums(&datum_of, &to);
    tracing::info!("{converted} inputs converted to heights above the {}", target.describe());
    Ok(Some(target))
}

/// One elevation file, with the spacing asked for where it says none.
fn elevation_file(path: &Path, request: &TileRequest) -> Result<ElevationFile> {
    let mut file = open_elevation(path, request.encoding)?;
    match request.sample_spacing {
        Some(s) if s.is_finite() && s > 0.0 => file = file.with_spacing(s),
        Some(s) => return Err(Error::option("--sample-spacing", s, "positive metres")),
        None if !file.is_georeferenced() => {
            tracing::warn!("{} does not say where it lies: 1 m between samples (set --sample-spacing)", path.display())
        }
        None => {}
    }
    Ok(file)
}

/// The elevation's CRS and extent (min x, min y, max x, max y there), for imagery that
/// must cover it; `None`s when the elevation does not say where it lies.
fn elevation_extent(e: &dyn ElevationSource) -> Result<(Option<Crs>, Option<[f64; 4]>)> {
    let g = e.georeference();
    let (Some(crs), Some(origin), Some((px, py))) =
        (g.and_then(|g| g.crs.as_deref()), g.and_then(|g| g.origin), e.crs_pixel_size())
    else {
        return Ok((None, None));
    };
    let (w, h) = e.size();
    let extent = [origin[0], origin[1] - f64::from(h) * py, origin[0] + f64::from(w) * px, origin[1]];
    Ok((Some(Crs::parse(crs)?), Some(extent)))
}

/// Metres per pixel of a texture tiled without elevation: the size given, else the pixel
/// its georeference gives, else 1.
fn texture_pixel_size(given: Option<f64>, source: &dyn ImageSource) -> f64 {
    if let Some(metres) = given {
        return metres;
    }
    let Some(metres) = image_pixel_metres(source) else { return 1.0 };
    tracing::info!("texture: {metres:.3} m per pixel, from {}'s georeference", source.path().display());
    metres
}
