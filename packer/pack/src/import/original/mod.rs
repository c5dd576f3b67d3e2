//! The original engine's folder layout: `LOD0`, `LOD1`, ... (LOD0 finest), optionally
//! split into sub-folders, one folder set per layer, and a metadata text.

pub(crate) mod metadata;

use std::collections::BTreeMap;
use std::path::{Path, PathBuf};

use metadata::number;
use serde::{Deserialize, Serialize};
use terrastream_format::{
    ElevationEncoding, ElevationScheme, Layer, LayerKind, Metadata, PayloadCompression, TileFormat, TileKey,
};

use super::{ScannedPyramid, image_size, split_stem, walk_files};
use crate::error::{Error, Result};

/// Options of the original-layout importer.
#[derive(Clone, Debug)]
pub struct OriginalLayout {
    /// Kind of the layer when the LOD folders sit directly in the input folder.
    pub kind: LayerKind,
    /// File names give y before x.
    pub swap_xy: bool,
}

impl Default for OriginalLayout {
    fn default() -> Self {
        Self { kind: LayerKind::Texture, swap_xy: false }
    }
}

/// How the files of one layer were named, so that `extract` writes them back the same way.
#[derive(Clone, Debug, PartialEq, Eq, Serialize, Deserialize)]
pub struct LayerNaming {
    /// Layer name in the archive.
    pub layer: String,
    /// Folder holding the LOD folders, relative to the input ("" = the input itself).
    pub folder: String,
    /// Text before x in the file stem.
    pub prefix: String,
    /// Text between x and y.
    pub separator: String,
    /// Text after y.
    pub suffix: String,
    /// File extension as found.
    pub extension: String,
    /// y came first in the names.
    pub swap_xy: bool,
}

/// What the importer records in `metadata.extra["original_layout"]`.
#[derive(Clone, Debug, Default, PartialEq, Eq, Serialize, Deserialize)]
pub struct LayoutRecord {
    /// Name of the metadata text file.
    pub metadata_file: Option<String>,
    /// The metadata text, verbatim.
    pub metadata_text: Option<String>,
    /// Naming per layer.
    pub layers: Vec<LayerNaming>,
}

/// Key under which [`LayoutRecord`] is stored in the metadata.
pub const LAYOUT_KEY: &str = "original_layout";

fn lod_folder(path: &Path) -> Option<u8> {
    let name = path.file_name()?.to_str()?;
    let digits = name.strip_prefix("LOD").or_else(|| name.strip_prefix("lod"))?;
    if digits.is_empty() || !digits.bytes().all(|b| b.is_ascii_digit()) {
        return None;
    }
    digits.parse().ok()
}

fn lod_folders(dir: &Path) -> Result<Vec<(u8, PathBuf)>> {
    let mut out = Vec::new();
    for entry in std::fs::read_dir(dir).map_err(|e| Error::file(dir, e))? {
        let path = entry.map_err(|e| Error::file(dir, e))?.path();
        if path.is_dir()
            && let Some(lod) = lod_folder(&path)
        {
            out.push((lod, path));
        }
    }
    out.sort();
    Ok(out)
}

fn kind_of_folder(name: &str) -> Option<LayerKind> {
    let n = name.to_ascii_lowercase();
    if ["elev", "height", "dem"].iter().any(|k| n.contains(k)) {
        Some(LayerKind::Elevation)
    } else if ["tex", "image", "ortho", "color", "colour"].iter().any(|k| n.contains(k)) {
        Some(LayerKind::Texture)
    } else {
        None
    }
}

fn find_metadata_text(root: &Path) -> Result<Option<(PathBuf, String)>> {
    let mut candidates = Vec::new();
    for entry in std::fs::read_dir(root).map_err(|e| Error::file(root, e))? {
        let path = entry.map_err(|e| Error::file(root, e))?.path();
        if path.is_file() && path.extension().is_some_and(|e| e.eq_ignore_ascii_case("txt")) {
            candidates.push(path);
        }
    }
    candidates.sort();
    for path in candidates {
        let text = std::fs::read_to_string(&path).map_err(|e| Error::file(&path, e))?;
        if text.contains("public ") {
            return Ok(Some((path, text)));
        }
    }
    Ok(None)
}

/// Scans an original-layout folder.
///
/// # Errors
/// [`Error::Input`] naming the folder or file at fault, [`Error::OriginalMetadata`] for a
/// malformed metadata line.
pub fn scan_original(root: &Path, options: &OriginalLayout) -> Result<ScannedPyramid> {
    let meta_text = find_metadata_text(root)?;
    let fields = match &meta_text {
        Some((path, text)) => metadata::parse(text, path)?,
        None => Vec::new(),
    };
    // Layer folders: LOD folders right here, or one sub-folder per layer.
    let mut layer_dirs: Vec<(LayerKind, String, PathBuf)> = Vec::new();
    if !lod_folders(root)?.is_empty() {
        layer_dirs.push((options.kind, String::new(), root.to_path_buf()));
    } else {
        let mut subs: Vec<PathBuf> = std::fs::read_dir(root)
            .map_err(|e| Error::file(root, e))?
            .filter_map(|e| e.ok().map(|e| e.path()))
            .filter(|p| p.is_dir())
            .collect();
        subs.sort();
        for sub in subs {
            if lod_folders(&sub)?.is_empty() {
                continue;
            }
            let name = sub.file_name().and_then(|n| n.to_str()).unwrap_or_default().to_owned();
            let kind = kind_of_folder(&name).ok_or_else(|| {
                Error::input(
                    &sub,
                    "cannot tell the layer kind from the folder name (use e.g. `textures`, `elevations`)",
                )
            })?;
            if layer_dirs.iter().any(|(k, ..)| *k == kind) {
                return Err(Error::input(&sub, format!("a second {kind:?} folder")));
            }
            layer_dirs.push((kind, name, sub));
        }
    }
    if layer_dirs.is_empty() {
        return Err(Error::input(root, "no LOD0, LOD1, ... folders found (here or one level down)"));
    }
    // Elevation after texture: a stable layer order.
    layer_dirs.sort_by_key(|(k, ..)| *k != LayerKind::Texture);

    let mut metadata = Metadata::new(root.file_name().and_then(|n| n.to_str()).unwrap_or("terrain"), Vec::new());
    metadata::apply_terrain(&fields, &mut metadata);
    metadata.original_fields = fields.clone();
    let mut record = LayoutRecord {
        metadata_file: meta_text.as_ref().and_then(|(p, _)| p.file_name()?.to_str().map(str::to_owned)),
        metadata_text: meta_text.map(|(_, t)| t),
        layers: Vec::new(),
    };
    let mut all_tiles: Vec<(u8, u8, u32, u32, PathBuf)> = Vec::new();
    for (index, (kind, folder, dir)) in layer_dirs.iter().enumerate() {
        let layer_index = u8::try_from(index).map_err(|_| Error::input(root, "too many layers"))?;
        let (layer, naming, tiles) = scan_layer(*kind, folder, dir, &fields, options)?;
        all_tiles.extend(tiles.into_iter().map(|(lod, x, y, p)| (layer_index, lod, x, y, p)));
        metadata.layers.push(layer);
        record.layers.push(naming);
    }
    let record = serde_json::to_value(&record).map_err(|e| Error::metadata(&e))?;
    metadata.extra.insert(LAYOUT_KEY.into(), record);
    let tiles = all_tiles
        .into_iter()
        .map(|(layer, lod, x, y, path)| {
            let tile = TileKey::new(layer, lod, x, y).map_err(|e| Error::input(&path, e.to_string()))?;
            Ok((tile, path))
        })
        .collect::<Result<Vec<_>>>()?;
    ScannedPyramid::new(metadata, tiles)
}

/// Tile files found: `(lod, x, y, path)`.
type FoundTiles = Vec<(u8, u32, u32, PathBuf)>;
type LayerScan = (Layer, LayerNaming, FoundTiles);

fn scan_layer(
    kind: LayerKind,
    folder: &str,
    dir: &Path,
    fields: &[terrastream_format::OriginalField],
    options: &OriginalLayout,
) -> Result<LayerScan> {
    let layer_name = match kind {
        LayerKind::Elevation => "elevation",
        LayerKind::Normals => "normals",
        LayerKind::Material => "material",
        LayerKind::HeightRange => "elevation-range",
        LayerKind::Water => "water",
        LayerKind::Texture => "texture",
    };
    let (tiles, naming) = find_tiles(dir, layer_name, folder, options.swap_xy)?;
    let first = &tiles[0].3;
    let head = read_head(first)?;
    let format = TileFormat::sniff(&head).ok_or_else(|| Error::input(first, "not a PNG, JPEG or WebP image"))?;
    let (width, _) = image_size(&head).ok_or_else(|| Error::input(first, "cannot read the image size"))?;
    let field =
        |texture: &str, elevation: &str| number(fields, if kind == LayerKind::Elevation { elevation } else { texture });
    let as_u32 = |v: Option<f64>| v.and_then(metadata::to_u32).filter(|&v| v >= 1);

    // Grid: the metadata's, else what the finest tiles found imply.
    let (found_x, found_y, found_lods) = implied_grid(&tiles);
    let num_x_tiles = as_u32(field("TEXTURES_texturesNumXTiles", "ELEVATIONS_elevationsNumXTiles")).unwrap_or(found_x);
    let num_y_tiles = as_u32(field("TEXTURES_texturesNumYTiles", "ELEVATIONS_elevationsNumYTiles")).unwrap_or(found_y);
    let meta_lods =
        as_u32(field("TEXTURES_numTextureLODS", "ELEVATIONS_numElevationLODS")).map_or(0, |n| n.min(255) as u8);
    let declared = as_u32(field("TEXTURES_textureTileResolution", "ELEVATIONS_elevationTileResolution"));
    // Files wider than the declared resolution carry a border (written by `extract` from an
    // archive with borders): its own field says how wide, else the difference does.
    let border = match number(
        fields,
        if kind == LayerKind::Elevation { metadata::ELEVATION_BORDER } else { metadata::TEXTURE_BORDER },
    )
    .and_then(metadata::to_u32)
    {
        Some(b) => b,
        None => declared
            .filter(|&r| width > r && (width - r) % 2 == 0 && (width - r) / 2 <= 16)
            .map_or(0, |r| (width - r) / 2),
    };
    let border = u8::try_from(border)
        .ok()
        .filter(|&b| b <= 16)
        .ok_or_else(|| Error::input(first, format!("a tile border of {border} pixels (at most 16)")))?;
    let tile_resolution = declared.unwrap_or(width.saturating_sub(2 * u32::from(border)).max(1));
    let tile_world_size = field("TEXTURES_textureTileSize", "ELEVATIONS_elevationTileSize")
        .filter(|v| v.is_finite() && *v > 0.0)
        .unwrap_or(f64::from(tile_resolution));
    let mut layer = Layer {
        name: layer_name.into(),
        kind,
        format,
        compression: PayloadCompression::None,
        tile_resolution,
        border,
        num_x_tiles,
        num_y_tiles,
        num_lods: found_lods.max(meta_lods),
        tile_world_size,
        elevation: None,
        extent: None,
    };
    layer.num_lods = layer.num_lods.min(layer.depth());
    if kind == LayerKind::Elevation {
        let gray = format == TileFormat::Png && head.get(25).is_some_and(|&t| t == 0 || t == 4);
        let min = number(fields, "ELEVATIONS_minElevation").unwrap_or(0.0);
        let displacement = number(fields, "ELEVATIONS_displacement").unwrap_or(255.0);
        layer.elevation = Some(ElevationEncoding {
            scheme: if gray { ElevationScheme::Gray8 } else { ElevationScheme::RgbThirds },
            scale: displacement,
            offset: min,
            nodata: None,
        });
    }
    Ok((layer, naming, tiles))
}

/// The tile files under a layer's LOD folders, `(lod, x, y, path)`, and how they are named
/// (from the first one).
fn find_tiles(dir: &Path, layer_name: &str, folder: &str, swap_xy: bool) -> Result<(FoundTiles, LayerNaming)> {
    let mut tiles = Vec::new();
    let mut naming: Option<LayerNaming> = None;
    for (lod, lod_dir) in lod_folders(dir)? {
        for path in walk_files(&lod_dir)? {
            let name = path.file_name().and_then(|n| n.to_str()).unwrap_or_default();
            if name.starts_with('.') || name.eq_ignore_ascii_case("thumbs.db") {
                continue;
            }
            let (stem, ext) = name.rsplit_once('.').unwrap_or((name, ""));
            let Some((prefix, a, separator, b, suffix)) = split_stem(stem) else {
                return Err(Error::input(&path, "file name has no x and y numbers"));
            };
            let (x, y) = if swap_xy { (b, a) } else { (a, b) };
            if naming.is_none() {
                naming = Some(LayerNaming {
                    layer: layer_name.into(),
                    folder: folder.into(),
                    prefix,
                    separator,
                    suffix,
                    extension: ext.into(),
                    swap_xy,
                });
            }
            tiles.push((lod, x, y, path));
        }
    }
    let naming = naming.ok_or_else(|| Error::input(dir, "LOD folders hold no tile files"))?;
    Ok((tiles, naming))
}

/// The LOD-0 grid (tiles across and down) and LOD count that the tiles found imply.
fn implied_grid(tiles: &FoundTiles) -> (u32, u32, u8) {
    let mut implied = BTreeMap::<u8, (u32, u32)>::new();
    for (lod, x, y, _) in tiles {
        let e = implied.entry(*lod).or_insert((0, 0));
        let scale = 1u32.checked_shl(u32::from(*lod)).unwrap_or(u32::MAX);
        e.0 = e.0.max(x.saturating_add(1).saturating_mul(scale));
        e.1 = e.1.max(y.saturating_add(1).saturating_mul(scale));
    }
    let (found_x, found_y) = implied.values().fold((1, 1), |a, b| (a.0.max(b.0), a.1.max(b.1)));
    (found_x, found_y, implied.keys().max().map_or(1, |m| m + 1))
}

/// The first bytes of a file: enough for format and size sniffing.
fn read_head(path: &Path) -> Result<Vec<u8>> {
    use std::io::Read;
    let mut head = Vec::with_capacity(64 << 10);
    std::fs::File::open(path)
        .and_then(|f| f.take(64 << 10).read_to_end(&mut head))
        .map_err(|e| Error::file(path, e))?;
    Ok(head)
}
