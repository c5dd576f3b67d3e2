//! GDAL virtual rasters (`.vrt`), the common subset: a `VRTRasterBand` (or, for imagery,
//! one a band, each reading that band of the same sources) of
//! `SimpleSource` / `ComplexSource` elements, each a window (`SrcRect`) of a file placed at
//! `DstRect` on the VRT's grid (`GeoTransform`, `SRS`), with `SourceFilename` relative to
//! the VRT or absolute, an optional `NODATA` and, for a `ComplexSource`, `ScaleOffset` and
//! `ScaleRatio` (value = sample x ratio + offset, after the NODATA test, as GDAL applies
//! them). A mosaic reads each source as an input.

use std::path::{Path, PathBuf};

use crate::crs::crs_of_srs;
use crate::error::{Error, Result};

/// One source of a VRT, placed on the VRT's grid.
#[derive(Clone, Debug, PartialEq)]
pub struct VrtSource {
    /// The file.
    pub path: PathBuf,
    /// The window of the file used: first column and row, width and height.
    pub window: [u32; 4],
    /// Where the window lies: CRS coordinates of its north-west corner.
    pub origin: [f64; 2],
    /// CRS units per window pixel (x, y).
    pub pixel: (f64, f64),
    /// Samples equal to this are nodata (on top of the file's own nodata).
    pub nodata: Option<f64>,
    /// `ScaleRatio` and `ScaleOffset`: a sample's value is `sample * ratio + offset`.
    pub scale: Option<(f64, f64)>,
}

/// A VRT's CRS (`EPSG:xxxx` or a PROJ string), its bands and its sources, in order.
#[derive(Clone, Debug, PartialEq)]
pub struct Vrt {
    /// The CRS as the tiler names it.
    pub crs: String,
    /// Bands: 1 for heights; imagery may have 3 or 4 (RGB, RGBA), band k reading band k of
    /// the same sources.
    pub bands: usize,
    /// The sources.
    pub sources: Vec<VrtSource>,
}

/// Whether `path` names a GDAL virtual raster (by its `.vrt` extension): read as a
/// mosaic of its sources, never as an image.
pub fn is_vrt(path: &Path) -> bool {
    path.extension().and_then(|e| e.to_str()).is_some_and(|e| e.eq_ignore_ascii_case("vrt"))
}

/// Reads the VRT at `path`.
///
/// # Errors
/// [`Error::Damaged`] (or [`Error::Xml`]) naming the VRT for anything it cannot use: not XML, no
/// `GeoTransform` or `SRS`, a rotated grid, bands that do not read the same sources
/// band for band, a source without a file or with a broken rectangle, a source file that
/// does not exist (named).
pub fn read_vrt(path: &Path) -> Result<Vrt> {
    let bad = |why: String| Error::damaged(path, why);
    let text = std::fs::read_to_string(path).map_err(|e| Error::file(path, e))?;
    let doc = roxmltree::Document::parse(&text).map_err(|error| Error::Xml {
        path: path.to_owned(),
        what: "not a VRT",
        error,
    })?;
    let root = doc.root_element();
    if !root.has_tag_name("VRTDataset") {
        return Err(bad(format!("not a VRT: the root is <{}>", root.tag_name().name())));
    }
    let text = child(root, "GeoTransform")
        .and_then(|n| n.text())
        .ok_or_else(|| bad("no <GeoTransform>: the VRT does not say where it lies".into()))?;
    let [ox, px, rx, oy, ry, py] = super::worldfile::parse_geotransform(path, text)?;
    if rx != 0.0 || ry != 0.0 || px <= 0.0 || py >= 0.0 {
        return Err(bad("a rotated or flipped <GeoTransform>: only north-up grids are read".into()));
    }
    let srs = child(root, "SRS").and_then(|n| n.text()).ok_or_else(|| bad("no <SRS>".into()))?;
    let crs = crs_of_srs(srs).ok_or_else(|| bad(format!("<SRS> names no EPSG code the tiler can use: {srs:.80}")))?;
    let bands: Vec<_> = root.children().filter(|c| c.has_tag_name("VRTRasterBand")).collect();
    let Some(&first) = bands.first() else { return Err(bad("no <VRTRasterBand>".into())) };
    let sources = band_sources(path, first, 1, [ox, px, oy, py])?;
    // Several bands (imagery): band k must read band k of band 1's sources, source for
    // source, as gdalbuildvrt writes them.
    for (k, &band) in bands.iter().enumerate().skip(1) {
        if band_sources(path, band, k + 1, [ox, px, oy, py])? != sources {
            return Err(bad(format!(
                "band {} does not read band {} of band 1's sources, source for source: only such VRTs of \
                 several bands are read",
                k + 1,
                k + 1
            )));
        }
    }
    Ok(Vrt { crs, bands: bands.len(), sources })
}

/// The sources of `band` (band number `number`), each checked to read band `number` of
/// its file; `grid`: the VRT's west, x pixel size, north and y pixel size.
fn band_sources(path: &Path, band: roxmltree::Node<'_, '_>, number: usize, grid: [f64; 4]) -> Result<Vec<VrtSource>> {
    let bad = |why: String| Error::damaged(path, why);
    let [ox, px, oy, py] = grid;
    let folder = path.parent().unwrap_or(Path::new("."));
    let mut sources = Vec::new();
    for source in band.children().filter(|c| c.has_tag_name("SimpleSource") || c.has_tag_name("ComplexSource")) {
        let file = child(source, "SourceFilename").ok_or_else(|| bad("a source without <SourceFilename>".into()))?;
        let name = file.text().unwrap_or_default().trim();
        let relative = file.attribute("relativeToVRT").is_some_and(|v| v.trim() == "1");
        let source_path = if relative { folder.join(name) } else { PathBuf::from(name) };
        if !source_path.is_file() {
            return Err(Error::NamedButMissing { path: source_path, named_by: path.to_owned() });
        }
        let read = child(source, "SourceBand").and_then(|n| n.text()).map_or("1", str::trim);
        if read.parse::<usize>().ok() != Some(number) {
            return Err(bad(format!(
                "band {number} reads band {read:?} of {}: each band must read the same band of its sources",
                source_path.display()
            )));
        }
        let rect = |name: &str| -> Result<Option<[f64; 4]>> {
            let Some(r) = child(source, name) else { return Ok(None) };
            let get = |a: &str| {
                r.attribute(a)
                    .and_then(|v| v.trim().parse::<f64>().ok())
                    .ok_or_else(|| bad(format!("<{name}> of {} has no number {a}", source_path.display())))
            };
            Ok(Some([get("xOff")?, get("yOff")?, get("xSize")?, get("ySize")?]))
        };
        let (src, dst) = (rect("SrcRect")?, rect("DstRect")?);
        let (Some(src), Some(dst)) = (src, dst) else {
            return Err(bad(format!("the source {} has no <SrcRect> and <DstRect>", source_path.display())));
        };
        if src.iter().chain(&dst).any(|v| !v.is_finite())
            || src[2] <= 0.0
            || src[3] <= 0.0
            || dst[2] <= 0.0
            || dst[3] <= 0.0
        {
            return Err(bad(format!("the source {} has an empty or broken rectangle", source_path.display())));
        }
        #[expect(
            clippy::cast_possible_truncation,
            clippy::cast_sign_loss,
            reason = "pixel rectangles, checked positive"
        )]
        let window = src.map(|v| v.max(0.0).round() as u32);
        let nodata = child(source, "NODATA").and_then(|n| n.text()).and_then(|t| t.trim().parse::<f64>().ok());
        let number = |name: &str| -> Result<Option<f64>> {
            let Some(n) = child(source, name) else { return Ok(None) };
            let text = n.text().unwrap_or_default().trim();
            match text.parse::<f64>() {
                Ok(v) if v.is_finite() => Ok(Some(v)),
                _ => Err(bad(format!("<{name}> of {} is not a number: {text:?}", source_path.display()))),
            }
        };
        let (ratio, offset) = (number("ScaleRatio")?, number("ScaleOffset")?);
        let scale = (ratio.is_some() || offset.is_some()).then(|| (ratio.unwrap_or(1.0), offset.unwrap_or(0.0)));
        sources.push(VrtSource {
            path: source_path,
            window,
            origin: [ox + dst[0] * px, oy + dst[1] * py],
            pixel: (px * dst[2] / src[2], -py * dst[3] / src[3]),
            nodata,
            scale,
        });
    }
    if sources.is_empty() {
        return Err(bad(format!("band {number} has no <SimpleSource> or <ComplexSource>")));
    }
    Ok(sources)
}

/// The first child of `node` named `name`.
fn child<'a, 'input>(node: roxmltree::Node<'a, 'input>, name: &str) -> Option<roxmltree::Node<'a, 'input>> {
    node.children().find(|c| c.has_tag_name(name))
}
