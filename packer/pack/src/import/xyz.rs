//! XYZ / TMS tile trees addressed by a path template such as `{z}/{x}/{y}.png`.
//! Web zoom z = 0 is the coarsest level; it maps to LOD `max_zoom - z`.

use std::path::{Path, PathBuf};

use serde::{Deserialize, Serialize};
use terrastream_format::{
    ElevationEncoding, ElevationScheme, Georeference, Layer, LayerKind, MAX_LODS, Metadata, PayloadCompression,
    TileFormat, TileKey,
};

use super::layers::Opened;
use super::{ScannedPyramid, image_size, walk_files};
use crate::error::{Error, Result};
use crate::writer::Writer;

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

/// Which tile coordinate a placeholder stands for.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
enum Coord {
    Z,
    X,
    Y,
}

#[derive(Debug, PartialEq)]
enum Part {
    Literal(String),
    /// `{x}` (width 0: any number of digits) or `{x:06}` (zero-padded to `width` digits).
    Field {
        coord: Coord,
        width: usize,
    },
}

/// How to write a template, for errors and `--help`.
pub const TEMPLATE_HELP: &str = "placeholders {z}, {x} and {y}, each at least once; {y:06} writes y zero-padded \
     to 6 digits; a placeholder may appear twice (it must then agree), e.g. {z}/{y:06}/{y:06}_{x:06}.jpg";

fn parse_template(template: &str) -> Result<Vec<Part>> {
    let mut parts = Vec::new();
    let mut rest = template;
    while let Some(open) = rest.find('{') {
        if open > 0 {
            parts.push(Part::Literal(rest[..open].to_owned()));
        }
        let close = rest[open..].find('}').ok_or_else(|| Error::input(template, "unclosed `{` in template"))?;
        let inner = &rest[open + 1..open + close];
        let (name, width) = match inner.split_once(':') {
            None => (inner, 0),
            Some((name, pad)) => {
                let width = pad
                    .strip_prefix('0')
                    .and_then(|w| w.parse::<usize>().ok())
                    .filter(|w| (1..=10).contains(w))
                    .ok_or_else(|| {
                        Error::input(template, format!("{{{inner}}}: a width is written :0N, N in 1..=10"))
                    })?;
                (name, width)
            }
        };
        let coord = match name {
            "z" => Coord::Z,
            "x" => Coord::X,
            "y" => Coord::Y,
            other => {
                return Err(Error::input(template, format!("unknown placeholder {{{other}}}: {TEMPLATE_HELP}")));
            }
        };
        if let Some(Part::Field { width: 0, .. }) = parts.last() {
            return Err(Error::input(
                template,
                "two placeholders in a row need a fixed width ({x:03}) or text between",
            ));
        }
        parts.push(Part::Field { coord, width });
        rest = &rest[open + close + 1..];
    }
    if !rest.is_empty() {
        parts.push(Part::Literal(rest.to_owned()));
    }
    for c in [Coord::Z, Coord::X, Coord::Y] {
        if !parts.iter().any(|q| matches!(q, Part::Field { coord, .. } if *coord == c)) {
            return Err(Error::input(template, format!("the template lacks a placeholder: {TEMPLATE_HELP}")));
        }
    }
    Ok(parts)
}

/// Matches a relative path (with `/` separators) against the template: (z, x, y).
fn match_template(parts: &[Part], path: &str) -> Option<(u32, u32, u32)> {
    let mut values: [Option<u32>; 3] = [None; 3];
    let mut rest = path;
    for (i, part) in parts.iter().enumerate() {
        match part {
            Part::Literal(lit) => rest = rest.strip_prefix(lit.as_str())?,
            Part::Field { coord, width } => {
                let digits = rest.find(|c: char| !c.is_ascii_digit()).unwrap_or(rest.len());
                // A padded field right before another field takes exactly its width.
                let followed_by_field = matches!(parts.get(i + 1), Some(Part::Field { .. }));
                let end = if *width > 0 && followed_by_field { (*width).min(digits) } else { digits };
                if end == 0 || (i + 1 == parts.len() && end != rest.len()) {
                    return None;
                }
                let v: u32 = rest[..end].parse().ok()?;
                // Padded names are matched only as they are written (so extract gives them back).
                if *width > 0 && rest[..end] != format!("{v:0width$}") {
                    return None;
                }
                rest = &rest[end..];
                let slot = &mut values[*coord as usize];
                if slot.is_some_and(|seen| seen != v) {
                    return None;
                }
                *slot = Some(v);
            }
        }
    }
    let [z, x, y] = values;
    rest.is_empty().then_some((z?, x?, y?))
}

/// The tiles across and down of a tree's zoom 0: what its coarsest zoom's tiles imply
/// (1x1 for Web Mercator trees, 2x1 for the geodetic profile), widened to 2x1 where a
/// `tilemapresource.xml` (gdal2tiles, TMS) says `profile="geodetic"`.
fn top_grid(root: &Path, found: &[(u32, u32, u32, PathBuf)]) -> (u32, u32) {
    let zmin = found.iter().map(|t| t.0).min().unwrap_or(0);
    let mut grid = (1u32, 1u32);
    for &(z, x, y, _) in found.iter().filter(|t| t.0 == zmin) {
        let zoom_0 = |v: u32| u32::try_from((u64::from(v) + 1).div_ceil(1u64 << z)).unwrap_or(u32::MAX);
        grid = (grid.0.max(zoom_0(x)), grid.1.max(zoom_0(y)));
    }
    let geodetic = std::fs::read_to_string(root.join("tilemapresource.xml"))
        .is_ok_and(|xml| xml.contains("profile=\"geodetic\"") || xml.contains("profile=\"global-geodetic\""));
    if geodetic {
        grid = (grid.0.max(2), grid.1);
    }
    grid
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
            found.push((z, x, y, path));
        }
    }
    let Some(max_zoom) = found.iter().map(|t| t.0).max() else {
        return Err(Error::input(root, format!("no file matches the template {:?}", options.template)));
    };
    let min_zoom = found.iter().map(|t| t.0).min().unwrap_or(0);
    let max_zoom = u8::try_from(max_zoom).map_err(|_| Error::input(root, "zoom out of range"))?;
    // Every finer zoom must fit the grid the coarsest one implies, doubled per zoom.
    let top = top_grid(root, &found);
    let at_zoom = |z: u32| (u64::from(top.0) << z, u64::from(top.1) << z);
    for (z, x, y, path) in &found {
        let (w, h) = at_zoom(*z);
        if u64::from(*x) >= w || u64::from(*y) >= h {
            return Err(Error::input(
                path,
                format!(
                    "tile ({x}, {y}) outside zoom {z}'s {w}x{h} grid (zoom {min_zoom}, the coarsest, implies {}x{} \
                     tiles at zoom 0, doubled at each finer zoom)",
                    top.0, top.1
                ),
            ));
        }
    }
    let first = &found[0].3;
    let head = std::fs::read(first).map_err(|e| Error::file(first, e))?;
    let format = TileFormat::sniff(&head).ok_or_else(|| Error::input(first, "not a PNG, JPEG or WebP image"))?;
    let (width, _) = image_size(&head).unwrap_or((256, 256));
    let name = root.file_name().and_then(|n| n.to_str()).unwrap_or("terrain");
    let mut metadata = grid_metadata(name, options.kind, options.elevation, format, width, max_zoom, top)?;
    let record = XyzRecord {
        template: options.template.clone(),
        scheme: options.scheme,
        min_zoom: u8::try_from(min_zoom).unwrap_or(0),
        max_zoom,
    };
    metadata.extra.insert(XYZ_KEY.into(), serde_json::to_value(record).map_err(|e| Error::metadata(&e))?);
    let tiles = found
        .into_iter()
        .map(|(z, x, y, path)| {
            let y = if options.scheme == Scheme::Tms { (top.1 << z) - 1 - y } else { y };
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

/// Opens the tiles of a Web Mercator tileset as one layer: zoom `z` becomes LOD
/// `max_zoom - z`, each tile checked, when read, to be an image of the tileset's `format`
/// (`None`: the first tile's). `read` fetches a tile's bytes; its second argument names
/// the tile for errors.
///
/// # Errors
/// [`Error::Input`] naming the input and the tile at fault.
pub(crate) fn open_web_tiles<'a, T: 'a>(
    input: &Path,
    options: TilesetInput,
    format: Option<TileFormat>,
    tiles: Vec<WebTile<T>>,
    mut read: impl FnMut(&T, &str) -> Result<bytes::Bytes> + 'a,
) -> Result<Opened<'a>> {
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
    let mut metadata = grid_metadata(name, options.kind, options.elevation, format, width, max_zoom, (1, 1))?;
    let record = XyzRecord { template: "{z}/{x}/{y}".into(), scheme: Scheme::Xyz, min_zoom, max_zoom };
    metadata.extra.insert(XYZ_KEY.into(), serde_json::to_value(record).map_err(|e| Error::metadata(&e))?);
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
    let (keys, sources): (Vec<(TileKey, String)>, Vec<T>) =
        ordered.into_iter().map(|(_, key, t)| ((key, what(&t)), t.at)).unzip();
    let path = input.to_path_buf();
    let read = move |index: usize, what: &str| -> Result<bytes::Bytes> {
        let at = sources.get(index).ok_or_else(|| Error::input(&path, format!("{what}: no such tile")))?;
        let bytes = read(at, what)?;
        match TileFormat::sniff(&bytes) {
            Some(found) if found == format => Ok(bytes),
            found => Err(Error::input(&path, format!("{what}: {found:?} bytes in a {format:?} tileset"))),
        }
    };
    Ok(Opened { input: input.to_path_buf(), metadata, tiles: keys, read: Box::new(read) })
}

/// The equator's length on the WGS 84 ellipsoid, metres: Web Mercator's world width.
const EQUATOR: f64 = 40_075_016.685_578_49;

/// One layer of `top.0` x `top.1` tiles at zoom 0, doubled per zoom down to `max_zoom`
/// (LOD 0), `width`-pixel tiles, the grid spanning the equator's length. 1x1 is Web
/// Mercator (EPSG:3857); 2x1 the geodetic profile (EPSG:4326, 180 degrees per zoom-0
/// tile); other shapes carry no georeference.
#[allow(clippy::too_many_arguments)]
pub(crate) fn grid_metadata(
    name: &str,
    kind: LayerKind,
    elevation: Option<ElevationScheme>,
    format: TileFormat,
    width: u32,
    max_zoom: u8,
    top: (u32, u32),
) -> Result<Metadata> {
    let grid = |n: u32| n.checked_shl(u32::from(max_zoom)).filter(|g| g >> max_zoom == n);
    let (Some(nx), Some(ny)) = (grid(top.0), grid(top.1)) else {
        let grid = format!("{}x{} tiles at zoom 0 over {max_zoom} zooms: too many", top.0, top.1);
        return Err(terrastream_format::Error::Metadata(grid).into());
    };
    let mut metadata = Metadata::new(name, vec![web_layer(kind, elevation, format, width, (nx, ny), max_zoom)]);
    metadata.georeference = match top {
        (1, 1) => Some(Georeference {
            crs: Some("EPSG:3857".into()),
            origin: Some([-EQUATOR / 2.0, EQUATOR / 2.0]),
            // World units are Web Mercator metres.
            scale: Some([1.0, 1.0]),
            lat_lon_bounds: Some([-180.0, -85.051_128_779_806_59, 180.0, 85.051_128_779_806_59]),
            ..Georeference::default()
        }),
        (2, 1) => Some(Georeference {
            crs: Some("EPSG:4326".into()),
            origin: Some([-180.0, 90.0]),
            // The equator's length in world units spans 360 degrees.
            scale: Some([360.0 / EQUATOR, 360.0 / EQUATOR]),
            lat_lon_bounds: Some([-180.0, -90.0, 180.0, 90.0]),
            ..Georeference::default()
        }),
        _ => None,
    };
    Ok(metadata)
}

fn web_layer(
    kind: LayerKind,
    elevation: Option<ElevationScheme>,
    format: TileFormat,
    width: u32,
    (nx, ny): (u32, u32),
    max_zoom: u8,
) -> Layer {
    Layer {
        name: if kind == LayerKind::Elevation { "elevation".into() } else { "texture".into() },
        kind,
        format,
        compression: PayloadCompression::None,
        tile_resolution: width,
        border: 0,
        num_x_tiles: nx,
        num_y_tiles: ny,
        num_lods: max_zoom + 1,
        tile_world_size: EQUATOR / f64::from(nx),
        elevation: elevation.map(|scheme| ElevationEncoding { scheme, scale: 1.0, offset: 0.0, nodata: None }),
        extent: None,
    }
}

/// Fills a template for one tile (zero-padded where it says `{x:0N}`).
///
/// # Errors
/// [`Error::Input`] when the template is not one [`scan_xyz`] accepts.
pub fn fill_template(template: &str, z: u32, x: u32, y: u32) -> Result<String> {
    let mut out = String::new();
    for part in parse_template(template)? {
        match part {
            Part::Literal(text) => out.push_str(&text),
            Part::Field { coord, width } => {
                let v = match coord {
                    Coord::Z => z,
                    Coord::X => x,
                    Coord::Y => y,
                };
                out.push_str(&format!("{v:0width$}"));
            }
        }
    }
    Ok(out)
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
        assert_eq!(fill_template("{z}/{x}/{y}.png", 1, 2, 3).unwrap(), "1/2/3.png");
    }

    #[test]
    fn placeholders_repeat_and_pad() {
        let template = "{z}/{y:06}/{y:06}_{x:06}.jpg";
        let parts = parse_template(template).unwrap();
        assert_eq!(match_template(&parts, "4/000012/000012_000003.jpg"), Some((4, 3, 12)));
        // The two y's disagree, or a padded field is not written padded: not a tile.
        assert_eq!(match_template(&parts, "4/000012/000013_000003.jpg"), None);
        assert_eq!(match_template(&parts, "4/12/12_3.jpg"), None);
        // Wider than the padding is the number itself.
        assert_eq!(match_template(&parts, "4/1234567/1234567_000003.jpg"), Some((4, 3, 1_234_567)));
        assert_eq!(fill_template(template, 4, 3, 12).unwrap(), "4/000012/000012_000003.jpg");
        // Fixed widths can sit side by side; plain ones cannot.
        let parts = parse_template("{z}/{y:03}{x:03}.png").unwrap();
        assert_eq!(match_template(&parts, "2/001002.png"), Some((2, 2, 1)));
        assert!(parse_template("{z}/{y}{x}.png").is_err());
        for bad in ["{z}/{x:6}/{y}", "{z}/{x:0}/{y}", "{z}/{x:0a}/{y}"] {
            let e = parse_template(bad).unwrap_err().to_string();
            assert!(e.contains(":0N"), "{bad}: {e}");
        }
    }

    #[test]
    fn the_coarsest_zoom_sets_the_grid_and_finer_zooms_must_fit_it() {
        let dir = tempfile::tempdir().unwrap();
        let tile = |z: u32, x: u32, y: u32| (z, x, y, dir.path().join(format!("{z}/{x}/{y}.png")));
        // Geodetic: 2x1 at zoom 0.
        assert_eq!(top_grid(dir.path(), &[tile(0, 0, 0), tile(0, 1, 0), tile(1, 3, 1)]), (2, 1));
        // A regional Web Mercator tree starting at zoom 5.
        assert_eq!(top_grid(dir.path(), &[tile(5, 10, 12), tile(6, 21, 25)]), (1, 1));
        // A geodetic tree whose coarsest tiles all lie in the west: the TMS resource says so.
        std::fs::write(dir.path().join("tilemapresource.xml"), r#"<TileSets profile="geodetic">"#).unwrap();
        assert_eq!(top_grid(dir.path(), &[tile(3, 1, 2)]), (2, 1));
    }
}
