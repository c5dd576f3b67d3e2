//! XYZ / TMS tile trees addressed by a path template such as `{z}/{x}/{y}.png`.
//! Web zoom z = 0 is the coarsest level; it maps to LOD `max_zoom - z`.

use std::path::{Path, PathBuf};

use serde::{Deserialize, Serialize};

use super::{ScannedPyramid, image_size, walk_files};
use crate::error::{Error, Result};
use crate::key::{MAX_LODS, TileKey};
use crate::metadata::{
    ElevationEncoding, ElevationScheme, Georeference, Layer, LayerKind, Metadata, PayloadCompression, TileFormat,
};
use crate::progress::Progress;
use crate::writer::{WriteSummary, Writer, WriterOptions};

/// Row order of the tree.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum Scheme {
    /// y = 0 at the north (slippy maps).
    Xyz,
    /// y = 0 at the south.
    Tms,
}

/// Options of the XYZ importer.
#[derive(Clone, Debug)]
pub struct XyzOptions {
    /// Path template relative to the input folder, with `{z}`, `{x}` and `{y}`.
    pub template: String,
    /// Row order.
    pub scheme: Scheme,
    /// Layer kind.
    pub kind: LayerKind,
    /// Height encoding of an elevation layer (Terrain-RGB or Terrarium tiles).
    pub elevation: Option<ElevationScheme>,
}

/// What the importer records in `metadata.extra["xyz"]`, for `extract --layout xyz`.
#[derive(Clone, Debug, PartialEq, Eq, Serialize, Deserialize)]
pub struct XyzRecord {
    /// The template the tiles were found with.
    pub template: String,
    /// Row order of the source.
    pub scheme: Scheme,
    /// Coarsest zoom present.
    pub min_zoom: u8,
    /// Finest zoom present (LOD 0).
    pub max_zoom: u8,
}

/// Key under which [`XyzRecord`] is stored in the metadata.
pub const XYZ_KEY: &str = "xyz";

#[derive(Debug, PartialEq)]
enum Part {
    Literal(String),
    Z,
    X,
    Y,
}

fn parse_template(template: &str) -> Result<Vec<Part>> {
    let mut parts = Vec::new();
    let mut rest = template;
    while let Some(open) = rest.find('{') {
        if open > 0 {
            parts.push(Part::Literal(rest[..open].to_owned()));
        }
        let close = rest[open..].find('}').ok_or_else(|| Error::input(template, "unclosed `{` in template"))?;
        parts.push(match &rest[open + 1..open + close] {
            "z" => Part::Z,
            "x" => Part::X,
            "y" => Part::Y,
            other => {
                return Err(Error::input(template, format!("unknown placeholder {{{other}}} (use {{z}} {{x}} {{y}})")));
            }
        });
        rest = &rest[open + close + 1..];
    }
    if !rest.is_empty() {
        parts.push(Part::Literal(rest.to_owned()));
    }
    for p in [Part::Z, Part::X, Part::Y] {
        if parts.iter().filter(|q| **q == p).count() != 1 {
            return Err(Error::input(template, "template needs each of {z}, {x}, {y} exactly once"));
        }
    }
    Ok(parts)
}

/// Matches a relative path (with `/` separators) against the template.
fn match_template(parts: &[Part], path: &str) -> Option<(u32, u32, u32)> {
    let (mut z, mut x, mut y) = (None, None, None);
    let mut rest = path;
    for (i, part) in parts.iter().enumerate() {
        match part {
            Part::Literal(lit) => rest = rest.strip_prefix(lit.as_str())?,
            number => {
                let end = rest.find(|c: char| !c.is_ascii_digit()).unwrap_or(rest.len());
                if end == 0 || (i + 1 == parts.len() && end != rest.len()) {
                    return None;
                }
                let v: u32 = rest[..end].parse().ok()?;
                rest = &rest[end..];
                match number {
                    Part::Z => z = Some(v),
                    Part::X => x = Some(v),
                    _ => y = Some(v),
                }
            }
        }
    }
    rest.is_empty().then_some((z?, x?, y?))
}

/// Scans an XYZ / TMS tree.
///
/// # Errors
/// [`Error::Input`] naming the template or a file at fault.
pub fn scan_xyz(root: &Path, options: &XyzOptions) -> Result<ScannedPyramid> {
    let parts = parse_template(&options.template)?;
    let mut found: Vec<(u32, u32, u32, PathBuf)> = Vec::new();
    for path in walk_files(root)? {
        let Ok(relative) = path.strip_prefix(root) else {
            continue;
        };
        let relative: Vec<&str> = relative.iter().filter_map(|c| c.to_str()).collect();
        if let Some((z, x, y)) = match_template(&parts, &relative.join("/")) {
            if z >= u32::from(MAX_LODS) {
                return Err(Error::input(&path, format!("zoom {z} is beyond the format's {} levels", MAX_LODS)));
            }
            if x >= 1 << z || y >= 1 << z {
                return Err(Error::input(&path, format!("tile ({x}, {y}) outside zoom {z}'s {0}x{0} grid", 1u64 << z)));
            }
            found.push((z, x, y, path));
        }
    }
    let Some(max_zoom) = found.iter().map(|t| t.0).max() else {
        return Err(Error::input(root, format!("no file matches the template {:?}", options.template)));
    };
    let min_zoom = found.iter().map(|t| t.0).min().unwrap_or(0);
    let max_zoom = u8::try_from(max_zoom).map_err(|_| Error::input(root, "zoom out of range"))?;
    let first = &found[0].3;
    let head = std::fs::read(first).map_err(|e| Error::file(first, e))?;
    let format = TileFormat::sniff(&head).ok_or_else(|| Error::input(first, "not a PNG, JPEG or WebP image"))?;
    let (width, _) = image_size(&head).unwrap_or((256, 256));
    let name = root.file_name().and_then(|n| n.to_str()).unwrap_or("terrain");
    let mut metadata = web_mercator_metadata(name, options.kind, options.elevation, format, width, max_zoom);
    let record = XyzRecord {
        template: options.template.clone(),
        scheme: options.scheme,
        min_zoom: u8::try_from(min_zoom).unwrap_or(0),
        max_zoom,
    };
    metadata.extra.insert(XYZ_KEY.into(), serde_json::to_value(record).map_err(|e| Error::Metadata(e.to_string()))?);
    let tiles = found
        .into_iter()
        .map(|(z, x, y, path)| {
            let y = if options.scheme == Scheme::Tms { (1 << z) - 1 - y } else { y };
            let lod = max_zoom - u8::try_from(z).unwrap_or(max_zoom);
            let tile = TileKey::new(0, lod, x, y).map_err(|e| Error::input(&path, e.to_string()))?;
            Ok((tile, path))
        })
        .collect::<Result<Vec<_>>>()?;
    ScannedPyramid::new(metadata, tiles)
}

/// What a tileset is, beyond what its file says (PMTiles, MBTiles).
#[derive(Clone, Copy, Debug)]
pub struct TilesetInput {
    /// Layer kind.
    pub kind: LayerKind,
    /// Height encoding of an elevation layer (Terrain-RGB, Terrarium, gray).
    pub elevation: Option<ElevationScheme>,
}

/// One tile of a Web Mercator tileset (XYZ numbering: row 0 at the north) and where its
/// bytes are in the input.
#[derive(Clone, Copy, Debug)]
pub(crate) struct WebTile<T> {
    pub z: u8,
    pub x: u32,
    pub y: u32,
    pub at: T,
}

/// Packs the tiles of a Web Mercator tileset into a one-layer archive at `out`: zoom `z`
/// becomes LOD `max_zoom - z`, tile bytes are stored unchanged (identical tiles once), each
/// checked to be an image of the tileset's `format` (`None`: the first tile's). `read`
/// fetches a tile's bytes; its second argument names the tile for errors.
#[allow(clippy::too_many_arguments)]
pub(crate) fn pack_web_tiles<T>(
    input: &Path,
    options: TilesetInput,
    format: Option<TileFormat>,
    tiles: Vec<WebTile<T>>,
    mut read: impl FnMut(&T, &str) -> Result<bytes::Bytes>,
    out: &Path,
    writer_options: WriterOptions,
    progress: &dyn Progress,
) -> Result<WriteSummary> {
    let Some(first) = tiles.first() else {
        return Err(Error::input(input, "no tiles"));
    };
    let what = |t: &WebTile<T>| format!("tile z{} x{} y{}", t.z, t.x, t.y);
    let head = read(&first.at, &what(first))?;
    let format = match format.or_else(|| TileFormat::sniff(&head)) {
        Some(f @ (TileFormat::Png | TileFormat::Jpeg | TileFormat::Webp)) => f,
        _ => return Err(Error::input(input, format!("{}: not a PNG, JPEG or WebP image", what(first)))),
    };
    let (width, _) = image_size(&head).unwrap_or((256, 256));
    let max_zoom = tiles.iter().map(|t| t.z).max().unwrap_or(0);
    let min_zoom = tiles.iter().map(|t| t.z).min().unwrap_or(0);
    if max_zoom >= MAX_LODS {
        return Err(Error::input(input, format!("zoom {max_zoom}: at most {} levels", MAX_LODS)));
    }
    let name = input.file_stem().and_then(|n| n.to_str()).unwrap_or("terrain");
    let mut metadata = web_mercator_metadata(name, options.kind, options.elevation, format, width, max_zoom);
    let record = XyzRecord { template: "{z}/{x}/{y}".into(), scheme: Scheme::Xyz, min_zoom, max_zoom };
    metadata.extra.insert(XYZ_KEY.into(), serde_json::to_value(record).map_err(|e| Error::Metadata(e.to_string()))?);
    let mut ordered = tiles
        .into_iter()
        .map(|t| {
            let key = TileKey::new(0, max_zoom - t.z, t.x, t.y)
                .map_err(|e| Error::input(input, format!("{}: {e}", what(&t))))?;
            let order =
                Writer::order_key(&metadata, key).map_err(|e| Error::input(input, format!("{}: {e}", what(&t))))?;
            Ok((order, key, t))
        })
        .collect::<Result<Vec<_>>>()?;
    ordered.sort_unstable_by_key(|t| t.0);
    if let Some(pair) = ordered.windows(2).find(|w| w[0].0 == w[1].0) {
        return Err(Error::input(input, format!("{} appears twice", what(&pair[1].2))));
    }
    let mut writer = Writer::create(out, metadata, writer_options)?;
    progress.start("pack", ordered.len() as u64);
    for (n, (_, key, t)) in ordered.into_iter().enumerate() {
        if n.is_multiple_of(256) {
            progress.check()?;
        }
        let bytes = read(&t.at, &what(&t))?;
        match TileFormat::sniff(&bytes) {
            Some(found) if found == format => {}
            found => {
                return Err(Error::input(input, format!("{}: {found:?} bytes in a {format:?} tileset", what(&t))));
            }
        }
        writer.add_stored(key, bytes.into())?;
        progress.advance(1);
    }
    writer.finish()
}

/// One layer on the Web Mercator tile grid of zoom `max_zoom` (LOD 0), `width`-pixel tiles.
pub(crate) fn web_mercator_metadata(
    name: &str,
    kind: LayerKind,
    elevation: Option<ElevationScheme>,
    format: TileFormat,
    width: u32,
    max_zoom: u8,
) -> Metadata {
    let side = 1u32 << max_zoom.min(27);
    // Web Mercator: the world is 2 * pi * 6378137 m across at the equator.
    let world = 40_075_016.685_578_49;
    let layer = Layer {
        name: if kind == LayerKind::Elevation { "elevation".into() } else { "texture".into() },
        kind,
        format,
        compression: PayloadCompression::None,
        tile_resolution: width,
        border: 0,
        num_x_tiles: side,
        num_y_tiles: side,
        num_lods: max_zoom.min(27) + 1,
        tile_world_size: world / f64::from(side),
        elevation: elevation.map(|scheme| ElevationEncoding { scheme, scale: 1.0, offset: 0.0, nodata: None }),
    };
    let mut metadata = Metadata::new(name, vec![layer]);
    metadata.georeference = Some(Georeference {
        crs: Some("EPSG:3857".into()),
        origin: Some([-world / 2.0, world / 2.0]),
        lat_lon_bounds: Some([-180.0, -85.051_128_779_806_59, 180.0, 85.051_128_779_806_59]),
    });
    metadata
}

/// Fills a template for one tile.
pub fn fill_template(template: &str, z: u32, x: u32, y: u32) -> String {
    template.replace("{z}", &z.to_string()).replace("{x}", &x.to_string()).replace("{y}", &y.to_string())
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn templates_match_only_their_paths() {
        let parts = parse_template("{z}/{x}/{y}.png").unwrap();
        assert_eq!(match_template(&parts, "3/5/7.png"), Some((3, 5, 7)));
        assert_eq!(match_template(&parts, "3/5/7.jpg"), None);
        assert_eq!(match_template(&parts, "3/5/x.png"), None);
        assert_eq!(match_template(&parts, "3/5/7.png.bak"), None);
        let parts = parse_template("tiles_{z}_{y}_{x}").unwrap();
        assert_eq!(match_template(&parts, "tiles_2_1_3"), Some((2, 3, 1)));
        assert!(parse_template("{z}/{x}.png").is_err());
        assert!(parse_template("{z}/{x}/{y}/{q}").is_err());
        assert_eq!(fill_template("{z}/{x}/{y}.png", 1, 2, 3), "1/2/3.png");
    }
}
