//! Input lists as users give them: files, folders (every GeoTIFF under them, and every
//! PNG or JPEG with a world file), and patterns with `*` and `?` in the file name.

use std::path::{Path, PathBuf};

use crate::error::{Error, Result};

/// The raster files that `inputs` name, in order: a file as given, a folder's GeoTIFFs
/// (`.tif`, `.tiff`) and PNGs and JPEGs with a world file (recursively, sorted by path),
/// a pattern's matches (sorted).
///
/// # Errors
/// [`Error::NotFound`] naming an input that does not exist, a folder without GeoTIFFs, or a
/// pattern that matches nothing.
pub fn expand_inputs(inputs: &[PathBuf]) -> Result<Vec<PathBuf>> {
    let mut out = Vec::new();
    for input in inputs {
        let name = input.file_name().and_then(|n| n.to_str()).unwrap_or_default();
        if name.contains(['*', '?']) {
            let folder = input.parent().filter(|p| !p.as_os_str().is_empty()).unwrap_or(Path::new("."));
            let entries = std::fs::read_dir(folder).map_err(|e| Error::file(folder, e))?;
            let mut found: Vec<PathBuf> = entries
                .filter_map(|e| e.ok().map(|e| e.path()))
                .filter(|p| p.is_file() && p.file_name().and_then(|n| n.to_str()).is_some_and(|n| matches(name, n)))
                .collect();
            if found.is_empty() {
                return Err(Error::NotFound { path: input.clone(), reason: "the pattern matches no file" });
            }
            found.sort();
            out.extend(found);
        } else if input.is_dir() {
            let mut found = Vec::new();
            walk(input, &mut found)?;
            if found.is_empty() {
                return Err(Error::NotFound {
                    path: input.clone(),
                    reason: "the folder holds no GeoTIFF (.tif, .tiff), nor a PNG or JPEG with a world file",
                });
            }
            found.sort();
            out.extend(found);
        } else if input.is_file() {
            out.push(input.clone());
        } else {
            return Err(Error::NotFound { path: input.clone(), reason: "no such file or folder" });
        }
    }
    Ok(out)
}

fn walk(folder: &Path, out: &mut Vec<PathBuf>) -> Result<()> {
    for entry in std::fs::read_dir(folder).map_err(|e| Error::file(folder, e))? {
        let entry = entry.map_err(|e| Error::file(folder, e))?;
        let path = entry.path();
        // The kind the listing gives, with no call per entry (thousands of files); a
        // link is followed.
        let kind = entry.file_type().map_err(|e| Error::file(&path, e))?;
        if kind.is_dir() || (kind.is_symlink() && path.is_dir()) {
            walk(&path, out)?;
        } else if is_raster(&path) {
            out.push(path);
        }
    }
    Ok(())
}

/// A GeoTIFF (`.tif`, `.tiff`), or a PNG or JPEG with a world file beside it (the
/// others in a folder of orthophotos are previews, legends and the like).
fn is_raster(path: &Path) -> bool {
    let ext = path.extension().and_then(|e| e.to_str()).unwrap_or_default().to_ascii_lowercase();
    match ext.as_str() {
        "tif" | "tiff" => true,
        "png" | "jpg" | "jpeg" => super::worldfile::world_file(path).is_some(),
        _ => false,
    }
}

/// Does `name` match `pattern` (`*`: any run of characters, `?`: any one)?
fn matches(pattern: &str, name: &str) -> bool {
    let (p, n): (Vec<char>, Vec<char>) = (pattern.chars().collect(), name.chars().collect());
    // Classic wildcard matching with backtracking to the last `*`.
    let (mut i, mut j, mut star, mut mark) = (0, 0, None, 0);
    while j < n.len() {
        if i < p.len() && (p[i] == '?' || p[i] == n[j]) {
            i += 1;
            j += 1;
        } else if i < p.len() && p[i] == '*' {
            star = Some(i);
            mark = j;
            i += 1;
        } else if let Some(s) = star {
            i = s + 1;
            mark += 1;
            j = mark;
        } else {
            return false;
        }
    }
    while i < p.len() && p[i] == '*' {
        i += 1;
    }
    i == p.len()
}

#[cfg(test)]
mod tests {
    #![allow(clippy::unwrap_used)]

    use super::{expand_inputs, matches};

    #[test]
    fn a_folder_gives_its_geotiffs_and_the_images_a_world_file_places() {
        let dir = tempfile::tempdir().unwrap();
        let sub = dir.path().join("z");
        std::fs::create_dir(&sub).unwrap();
        for name in ["a.tif", "b.JPG", "b.JGW", "c.png", "d.txt", "z/e.png", "z/e.wld", "z/f.TIFF"] {
            std::fs::write(dir.path().join(name), b"").unwrap();
        }
        let found = expand_inputs(&[dir.path().to_path_buf()]).unwrap();
        let names: Vec<_> = found.iter().map(|p| p.strip_prefix(dir.path()).unwrap().to_str().unwrap()).collect();
        // c.png has no world file: a preview or a legend, left out.
        assert_eq!(names, ["a.tif", "b.JPG", "z/e.png", "z/f.TIFF"]);
    }

    #[test]
    fn patterns_match_as_shells_do() {
        assert!(matches("*.tif", "a.tif"));
        assert!(matches("dem_??.tif", "dem_01.tif"));
        assert!(!matches("dem_??.tif", "dem_1.tif"));
        assert!(matches("*_*.tif", "n45_e012.tif"));
        assert!(!matches("*.tif", "a.tiff"));
        assert!(matches("*", ""));
    }
}
