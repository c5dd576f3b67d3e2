//! The original engine's metadata text: a block of C# field declarations such as
//! `public int TEXTURES_numTextureLODS = 6;`. Read verbatim (unknown fields kept, values as
//! written), mapped onto [`Metadata`], and written back for consumers of that format.

use std::path::Path;

use terrastream_format::{Metadata, OriginalField};

use crate::error::{Error, Result};

const MODIFIERS: [&str; 8] = ["public", "private", "protected", "internal", "static", "readonly", "const", "volatile"];

/// Parses the text; `path` names the file in errors.
///
/// Blank lines and `//` comments are skipped. Every other line must be one declaration
/// `[modifiers] type name = value;` optionally followed by a `//` comment.
///
/// # Errors
/// [`Error::OriginalMetadata`] with the 1-based line number of the first malformed line.
pub fn parse(text: &str, path: &Path) -> Result<Vec<OriginalField>> {
    let mut fields = Vec::new();
    for (i, line) in text.lines().enumerate() {
        let fail =
            |reason: &str| Error::OriginalMetadata { path: path.to_path_buf(), line: i + 1, reason: reason.to_owned() };
        let line = line.trim().trim_start_matches('\u{feff}');
        if line.is_empty() || line.starts_with("//") {
            continue;
        }
        let Some((decl, value_part)) = line.split_once('=') else {
            return Err(fail("expected `type name = value;`"));
        };
        let words: Vec<&str> = decl.split_whitespace().filter(|w| !MODIFIERS.contains(w)).collect();
        let [ty, name] = words[..] else {
            return Err(fail("expected a type and a field name before `=`"));
        };
        if !is_identifier(name) || !ty.chars().all(|c| c.is_alphanumeric() || "_.<>[]?".contains(c)) {
            return Err(fail("field name or type is not a C# identifier"));
        }
        let value = split_value(value_part.trim()).ok_or_else(|| fail("value must end with `;`"))?;
        if value.is_empty() {
            return Err(fail("missing value"));
        }
        fields.push(OriginalField { ty: ty.to_owned(), name: name.to_owned(), value: value.to_owned() });
    }
    Ok(fields)
}

fn is_identifier(s: &str) -> bool {
    let mut chars = s.chars();
    chars.next().is_some_and(|c| c.is_alphabetic() || c == '_') && chars.all(|c| c.is_alphanumeric() || c == '_')
}

/// The literal before the terminating `;` (a `;` inside a string literal does not count),
/// if only whitespace or a `//` comment follows it.
fn split_value(rest: &str) -> Option<&str> {
    let mut in_string = false;
    let mut escaped = false;
    for (i, c) in rest.char_indices() {
        match c {
            _ if escaped => escaped = false,
            '\\' if in_string => escaped = true,
            '"' => in_string = !in_string,
            ';' if !in_string => {
                let tail = rest[i + 1..].trim();
                return (tail.is_empty() || tail.starts_with("//")).then(|| rest[..i].trim());
            }
            _ => {}
        }
    }
    None
}

/// The numeric value of a field, C# suffixes (`f`, `d`, `m`, `L`) ignored.
pub fn number(fields: &[OriginalField], name: &str) -> Option<f64> {
    let f = fields.iter().find(|f| f.name == name)?;
    f.value.trim_end_matches(['f', 'F', 'd', 'D', 'm', 'M', 'l', 'L', 'u', 'U']).parse().ok()
}

/// A whole number in u32 range, else `None`.
#[expect(clippy::cast_possible_truncation, reason = "range and integrality checked first")]
pub fn to_u32(v: f64) -> Option<u32> {
    (v.fract() == 0.0 && (0.0..=f64::from(u32::MAX)).contains(&v)).then_some(v as u32)
}

/// Fills the terrain and mesh parameters of `metadata` from the fields it knows.
/// Layer grids are the importer's business (they depend on the folders found).
pub fn apply_terrain(fields: &[OriginalField], metadata: &mut Metadata) {
    let t = &mut metadata.terrain;
    let set = |v: &mut f64, name: &str| {
        if let Some(x) = number(fields, name) {
            *v = x;
        }
    };
    set(&mut t.min_elevation, "ELEVATIONS_minElevation");
    set(&mut t.max_elevation, "ELEVATIONS_maxElevation");
    set(&mut t.displacement, "ELEVATIONS_displacement");
    set(&mut t.elevation_range, "ELEVATIONS_elevationRange");
    set(&mut t.smoothing_range, "ELEVATIONS_smoothingRange");
    set(&mut t.base_tile_size, "baseTileSize");
    set(&mut t.high_detail_range, "highDetailRange");
    let as_u32 = |name: &str| number(fields, name).and_then(to_u32);
    if let Some(n) = as_u32("numDetailLevels") {
        t.num_detail_levels = n;
    }
    if let Some(n) = as_u32("TEXTURES_maxConsolidatedTextureResolution") {
        t.max_consolidated_texture_resolution = n;
    }
}

/// Pixels duplicated from the neighbours around each texture tile (this format's field;
/// the original engine's tiles had none): the files are `textureTileResolution` plus twice
/// this wide.
pub const TEXTURE_BORDER: &str = "TEXTURES_textureTileBorder";
/// The same for elevation tiles.
pub const ELEVATION_BORDER: &str = "ELEVATIONS_elevationTileBorder";

/// The fields describing `metadata` in the original engine's names: the original fields in
/// their order with values updated where the archive says otherwise, then the known fields
/// the original did not have.
pub fn fields_for(metadata: &Metadata) -> Vec<OriginalField> {
    let mut known: Vec<(&str, &str, f64)> = Vec::new();
    let t = &metadata.terrain;
    for layer in &metadata.layers {
        let (prefix, res, lods, nx, ny, size) = match layer.kind {
            terrastream_format::LayerKind::Texture => (
                "TEXTURES_",
                "TEXTURES_textureTileResolution",
                "TEXTURES_numTextureLODS",
                "TEXTURES_texturesNumXTiles",
                "TEXTURES_texturesNumYTiles",
                "TEXTURES_textureTileSize",
            ),
            terrastream_format::LayerKind::Elevation => (
                "ELEVATIONS_",
                "ELEVATIONS_elevationTileResolution",
                "ELEVATIONS_numElevationLODS",
                "ELEVATIONS_elevationsNumXTiles",
                "ELEVATIONS_elevationsNumYTiles",
                "ELEVATIONS_elevationTileSize",
            ),
            _ => continue,
        };
        if known.iter().any(|(_, n, _)| n.starts_with(prefix)) {
            continue; // the original format has one layer of each kind
        }
        // Tiles with borders are written as stored (resolution + 2 x border pixels): the
        // border has a field of its own, so that packing them again gives the same layer.
        if layer.border > 0 {
            let border =
                if layer.kind == terrastream_format::LayerKind::Texture { TEXTURE_BORDER } else { ELEVATION_BORDER };
            known.push(("int", border, f64::from(layer.border)));
        }
        known.extend([
            ("int", res, f64::from(layer.tile_resolution)),
            ("int", lods, f64::from(layer.num_lods)),
            ("int", nx, f64::from(layer.num_x_tiles)),
            ("int", ny, f64::from(layer.num_y_tiles)),
            ("float", size, layer.tile_world_size),
        ]);
    }
    known.extend([
        ("int", "TEXTURES_maxConsolidatedTextureResolution", f64::from(t.max_consolidated_texture_resolution)),
        ("double", "ELEVATIONS_displacement", t.displacement),
        ("double", "ELEVATIONS_smoothingRange", t.smoothing_range),
        ("double", "ELEVATIONS_minElevation", t.min_elevation),
        ("double", "ELEVATIONS_maxElevation", t.max_elevation),
        ("double", "ELEVATIONS_elevationRange", t.elevation_range),
        ("float", "baseTileSize", t.base_tile_size),
        ("float", "highDetailRange", t.high_detail_range),
        ("int", "numDetailLevels", f64::from(t.num_detail_levels)),
    ]);
    let mut fields = metadata.original_fields.clone();
    for (ty, name, value) in known {
        match fields.iter_mut().find(|f| f.name == name) {
            Some(f) => {
                if number(std::slice::from_ref(f), name) != Some(value) {
                    f.value = literal(&f.ty, value);
                }
            }
            None => fields.push(OriginalField { ty: ty.to_owned(), name: name.to_owned(), value: literal(ty, value) }),
        }
    }
    fields
}

fn literal(ty: &str, value: f64) -> String {
    match ty {
        "float" => format!("{value}f"),
        "int" | "long" | "uint" | "short" => format!("{value:.0}"),
        _ => format!("{value}"),
    }
}

/// Renders fields as the original text, one `public type name = value;` per line.
pub fn render(fields: &[OriginalField]) -> String {
    fields.iter().map(|f| format!("public {} {} = {};\n", f.ty, f.name, f.value)).collect()
}

#[cfg(test)]
mod tests {
    use super::*;

    const SAMPLE: &str = "public int TEXTURES_textureTileResolution = 256;
public int TEXTURES_numTextureLODS = 6;
public float TEXTURES_textureTileSize = 76.963814f;

// a comment
public double ELEVATIONS_smoothingRange = 1.0f;
public double ELEVATIONS_minElevation = 714.794678; // trailing comment
public string tilePath = \"C:/data;x/LOD\";
public static bool MyCustomFlag = true;
";

    #[test]
    fn reads_fields_verbatim_and_keeps_unknown_ones() {
        let fields = parse(SAMPLE, Path::new("meta.txt")).unwrap();
        assert_eq!(fields.len(), 7);
        assert_eq!(fields[2].value, "76.963814f");
        assert_eq!(fields[5].value, "\"C:/data;x/LOD\"");
        assert_eq!(fields[6].name, "MyCustomFlag");
        assert_eq!(number(&fields, "TEXTURES_textureTileSize"), Some(76.963814));
        assert_eq!(number(&fields, "ELEVATIONS_smoothingRange"), Some(1.0));
    }

    #[test]
    fn names_the_malformed_line() {
        let text = "public int a = 1;\n\npublic int b 2;\n";
        let err = parse(text, Path::new("m.txt")).unwrap_err();
        assert!(matches!(err, Error::OriginalMetadata { line: 3, .. }), "{err}");
        assert!(err.to_string().starts_with("m.txt:3:"), "{err}");
        for bad in ["public int a = 1", "public int = 1;", "int a = ;", "public int a = 1; junk"] {
            assert!(parse(bad, Path::new("m")).is_err(), "{bad}");
        }
    }

    #[test]
    fn unchanged_values_are_written_back_verbatim() {
        let fields = parse(SAMPLE, Path::new("m")).unwrap();
        let mut m = Metadata::new("t", vec![]);
        m.original_fields = fields.clone();
        apply_terrain(&fields, &mut m);
        let back = fields_for(&m);
        let min = back.iter().find(|f| f.name == "ELEVATIONS_minElevation").unwrap();
        assert_eq!(min.value, "714.794678");
        assert!(back.iter().any(|f| f.name == "MyCustomFlag"));
        assert!(render(&back).contains("public float baseTileSize = 1f;\n"));
    }
}
