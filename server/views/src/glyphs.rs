//! Glyphs for map labels: ranges of 256 code points as signed distance fields, in the
//! protocol-buffer form MapLibre GL JS (and Mapbox GL) load from a style's `glyphs` URL
//! (`…/{fontstack}/{range}.pbf`), made from TrueType or OpenType files at 24 px with a
//! 3-pixel border, radius 8 and cutoff 0.25 (what those clients expect: the edge at 192 of
//! 255).
//!
//! A font stack names fonts by family and style ("DejaVu Sans Book", "Open Sans Regular");
//! the first name that matches a font here (case, spaces and a "Regular"/"Book"/"Roman"
//! style ignored) is used, else the fallback (the first of [`FontSet::fallback_order`]
//! present), so a style written for another glyph server still gets its labels.

use std::path::{Path, PathBuf};

use crate::mvt::{bytes_field, varint, varint_field, zigzag};

/// Glyphs' size in pixels (the em), border and the distance field's radius and cutoff.
const SIZE: f32 = 24.0;
const BORDER: usize = 3;
const RADIUS: f64 = 8.0;
const CUTOFF: f64 = 0.25;
/// Infinity, for the distance transform: large, finite (TinySDF's 1e20).
const FAR: f64 = 1e20;

/// Why fonts cannot be served.
#[derive(Debug, thiserror::Error)]
pub enum GlyphError {
    /// The folder cannot be read.
    #[error("{}: {reason}", path.display())]
    Folder {
        /// The folder.
        path: PathBuf,
        /// Why.
        reason: String,
    },
    /// No font file in it could be read.
    #[error("{}: no TrueType or OpenType font found", path.display())]
    Empty {
        /// The folder.
        path: PathBuf,
    },
}

/// The fonts of a folder.
pub struct FontSet {
    fonts: Vec<Face>,
    /// Files that did not parse, and why.
    skipped: Vec<(PathBuf, String)>,
}

struct Face {
    name: String,
    key: String,
    file: PathBuf,
    bytes: Vec<u8>,
    /// The font, parsed for glyphs at its first use (not at start-up: a folder of 22
    /// DejaVu faces took a third of a second to parse whole).
    font: std::sync::OnceLock<Result<fontdue::Font, String>>,
}

impl Face {
    /// The font parsed for glyphs, or why it cannot be.
    fn font(&self) -> Result<&fontdue::Font, String> {
        let parsed = self.font.get_or_init(|| {
            fontdue::Font::from_bytes(self.bytes.as_slice(), fontdue::FontSettings::default())
                .map_err(|e| format!("{}: {e}", self.file.display()))
        });
        parsed.as_ref().map_err(Clone::clone)
    }
}

/// A font file's full name (name ID 4), if it parses as one.
fn full_name(bytes: &[u8]) -> Result<Option<String>, String> {
    let face = ttf_parser::Face::parse(bytes, 0).map_err(|e| e.to_string())?;
    Ok(face.names().into_iter().filter(|n| n.name_id == ttf_parser::name_id::FULL_NAME).find_map(|n| n.to_string()))
}

impl std::fmt::Debug for FontSet {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_list().entries(self.fonts.iter().map(|face| &face.name)).finish()
    }
}

/// A name as compared: lower case, without spaces, dashes or a regular style's word.
fn key(name: &str) -> String {
    let lower: String = name.chars().filter(|c| !c.is_whitespace() && *c != '-').flat_map(char::to_lowercase).collect();
    ["regular", "book", "roman", "normal"]
        .iter()
        .find_map(|s| lower.strip_suffix(s).filter(|rest| !rest.is_empty()))
        .unwrap_or(&lower)
        .to_owned()
}

impl FontSet {
    /// Fonts used for a stack none of whose names is here, in order of preference.
    pub fn fallback_order() -> [&'static str; 4] {
        ["Open Sans Regular", "Noto Sans Regular", "DejaVu Sans Book", "Liberation Sans Regular"]
    }

    /// Every `.ttf` and `.otf` file under `dir` (files that do not parse are skipped:
    /// [`FontSet::skipped`]).
    ///
    /// # Errors
    /// [`GlyphError`] naming the folder.
    pub fn load(dir: &Path) -> Result<Self, GlyphError> {
        let mut files = Vec::new();
        collect(dir, &mut files, 0).map_err(|e| GlyphError::Folder { path: dir.to_owned(), reason: e.to_string() })?;
        files.sort();
        let (mut fonts, mut skipped) = (Vec::new(), Vec::new());
        for file in files {
            // Only the name table is read here; the glyphs' tables at first use.
            let read = std::fs::read(&file).map_err(|e| e.to_string());
            match read.and_then(|bytes| full_name(&bytes).map(|name| (bytes, name))) {
                Ok((bytes, name)) => {
                    let name = name.unwrap_or_else(|| stem(&file));
                    if fonts.iter().all(|f: &Face| f.name != name) {
                        fonts.push(Face { key: key(&name), name, file, bytes, font: std::sync::OnceLock::new() });
                    }
                }
                Err(reason) => skipped.push((file, reason)),
            }
        }
        if fonts.is_empty() {
            return Err(GlyphError::Empty { path: dir.to_owned() });
        }
        Ok(Self { fonts, skipped })
    }

    /// The files under the folder that are not fonts this reads, and why.
    pub fn skipped(&self) -> &[(PathBuf, String)] {
        &self.skipped
    }

    /// The fonts' names.
    pub fn names(&self) -> impl Iterator<Item = &str> {
        self.fonts.iter().map(|f| f.name.as_str())
    }

    /// The font for a stack (comma-separated names): its index and name; the fallback's
    /// where no name of the stack is here.
    pub fn pick(&self, stack: &str) -> (usize, &str) {
        let find = |name: &str| {
            let k = key(name);
            self.fonts.iter().position(|f| f.key == k)
        };
        let i = (stack.split(',').find_map(|n| find(n.trim())))
            .or_else(|| Self::fallback_order().iter().find_map(|n| find(n)))
            .unwrap_or(0);
        (i, &self.fonts[i].name)
    }

    /// The glyph fields of code points `start..start + 256` of font `font`, as
    /// [`range_message`] wraps them: what depends on the font alone (a server keeps these,
    /// whatever stack names asked for them).
    ///
    /// # Errors
    /// The font's file, where its glyphs cannot be read.
    pub fn glyphs(&self, font: usize, start: u32) -> Result<Vec<u8>, String> {
        let font = self.fonts[font.min(self.fonts.len() - 1)].font()?;
        let mut out = Vec::new();
        for code in start..start.saturating_add(256) {
            let Some(c) = char::from_u32(code) else { continue };
            if font.chars().contains_key(&c) {
                bytes_field(&mut out, 3, &glyph(font, c));
            }
        }
        Ok(out)
    }
}

/// A `glyphs` message: one font stack named `stack`, range `start`-`start + 255`, of the
/// glyph fields `glyphs` ([`FontSet::glyphs`]).
pub fn range_message(stack: &str, start: u32, glyphs: &[u8]) -> Vec<u8> {
    let mut stack_message = Vec::with_capacity(glyphs.len() + stack.len() + 16);
    bytes_field(&mut stack_message, 1, stack.as_bytes());
    bytes_field(&mut stack_message, 2, format!("{start}-{}", start + 255).as_bytes());
    stack_message.extend_from_slice(glyphs);
    let mut out = Vec::with_capacity(stack_message.len() + 8);
    bytes_field(&mut out, 1, &stack_message);
    out
}

fn stem(path: &Path) -> String {
    path.file_stem().map_or_else(String::new, |s| s.to_string_lossy().into_owned())
}

/// Font files under `dir`, four folders deep at most.
fn collect(dir: &Path, files: &mut Vec<PathBuf>, depth: u32) -> std::io::Result<()> {
    for entry in std::fs::read_dir(dir)? {
        let path = entry?.path();
        if path.is_dir() {
            if depth < 4 {
                collect(&path, files, depth + 1)?;
            }
        } else if path
            .extension()
            .and_then(|e| e.to_str())
            .is_some_and(|e| e.eq_ignore_ascii_case("ttf") || e.eq_ignore_ascii_case("otf"))
        {
            files.push(path);
        }
    }
    Ok(())
}

/// The range a request names: `START-END.pbf`'s START, a multiple of 256 with END
/// 255 more, below 65 536.
pub fn parse_range(text: &str) -> Option<u32> {
    let (a, b) = text.strip_suffix(".pbf").unwrap_or(text).split_once('-')?;
    let (a, b): (u32, u32) = (a.parse().ok()?, b.parse().ok()?);
    (a % 256 == 0 && b == a + 255 && a < 65_536).then_some(a)
}

/// One glyph message: id, the distance field (border included), the bitmap's size,
/// bearing and advance.
fn glyph(font: &fontdue::Font, c: char) -> Vec<u8> {
    let (m, coverage) = font.rasterize(c, SIZE);
    let mut out = Vec::new();
    varint_field(&mut out, 1, u64::from(u32::from(c)));
    if m.width > 0 && m.height > 0 {
        bytes_field(&mut out, 2, &distance_field(&coverage, m.width, m.height));
    }
    varint_field(&mut out, 3, m.width as u64);
    varint_field(&mut out, 4, m.height as u64);
    // Left bearing; top from the clients' origin above the em box (its baseline 24 px
    // down, less the border: what the clients' own glyphs are shifted by).
    let top = i64::from(m.ymin) + i64::try_from(m.height).unwrap_or(0) - 27;
    varint(&mut out, 5 << 3);
    varint(&mut out, zigzag(i64::from(m.xmin)));
    varint(&mut out, 6 << 3);
    varint(&mut out, zigzag(top));
    #[expect(clippy::cast_possible_truncation, clippy::cast_sign_loss, reason = "an advance in pixels")]
    let advance = m.advance_width.round().max(0.0) as u64;
    varint_field(&mut out, 7, advance);
    out
}

/// The signed distance field of a coverage bitmap, `BORDER` pixels wider each way: 255 at
/// most inside, 192 on the edge, falling by 255 / 8 a pixel outward (the sub-pixel edge
/// from the coverage, as TinySDF sets it up, then exact Euclidean distances).
fn distance_field(coverage: &[u8], width: usize, height: usize) -> Vec<u8> {
    let (w, h) = (width + 2 * BORDER, height + 2 * BORDER);
    let mut outer = vec![FAR; w * h];
    let mut inner = vec![0.0; w * h];
    for y in 0..height {
        for x in 0..width {
            let a = f64::from(coverage[y * width + x]) / 255.0;
            let i = (y + BORDER) * w + x + BORDER;
            if a >= 1.0 {
                outer[i] = 0.0;
                inner[i] = FAR;
            } else if a > 0.0 {
                let d = 0.5 - a;
                outer[i] = if d > 0.0 { d * d } else { 0.0 };
                inner[i] = if d < 0.0 { d * d } else { 0.0 };
            }
        }
    }
    edt(&mut outer, w, h);
    edt(&mut inner, w, h);
    outer
        .iter()
        .zip(&inner)
        .map(|(o, i)| {
            let d = o.sqrt() - i.sqrt();
            #[expect(clippy::cast_possible_truncation, clippy::cast_sign_loss, reason = "clamped to a byte")]
            let v = (255.0 - 255.0 * (d / RADIUS + CUTOFF)).round().clamp(0.0, 255.0) as u8;
            v
        })
        .collect()
}

/// Squared Euclidean distance transform in place (Felzenszwalb and Huttenlocher): each
/// cell becomes the least `grid[q] + |p - q|²` over the grid.
fn edt(grid: &mut [f64], w: usize, h: usize) {
    let n = w.max(h);
    let (mut f, mut d, mut v, mut z) = (vec![0.0; n], vec![0.0; n], vec![0usize; n], vec![0.0; n + 1]);
    for x in 0..w {
        for y in 0..h {
            f[y] = grid[y * w + x];
        }
        edt_1d(&f[..h], &mut d[..h], &mut v, &mut z);
        for y in 0..h {
            grid[y * w + x] = d[y];
        }
    }
    for y in 0..h {
        f[..w].copy_from_slice(&grid[y * w..(y + 1) * w]);
        edt_1d(&f[..w], &mut d[..w], &mut v, &mut z);
        grid[y * w..(y + 1) * w].copy_from_slice(&d[..w]);
    }
}

/// One row or column of [`edt`] (TinySDF's, with its large finite stand-in for
/// infinity, so that differences of two stay numbers).
#[expect(clippy::cast_precision_loss, reason = "small indices")]
fn edt_1d(f: &[f64], d: &mut [f64], v: &mut [usize], z: &mut [f64]) {
    let n = f.len();
    v[0] = 0;
    z[0] = -FAR;
    z[1] = FAR;
    let mut k = 0usize;
    for q in 1..n {
        let mut s;
        loop {
            let r = v[k];
            s = (f[q] - f[r] + (q * q) as f64 - (r * r) as f64) / (q as f64 - r as f64) / 2.0;
            if s <= z[k] && k > 0 {
                k -= 1;
            } else {
                break;
            }
        }
        if s <= z[k] {
            // Even the first parabola lies above: this one replaces it.
            v[0] = q;
            z[0] = -FAR;
            z[1] = FAR;
            continue;
        }
        k += 1;
        v[k] = q;
        z[k] = s;
        z[k + 1] = FAR;
    }
    let mut k = 0usize;
    for (q, out) in d.iter_mut().enumerate() {
        while z[k + 1] < q as f64 {
            k += 1;
        }
        let r = v[k];
        let dq = q as f64 - r as f64;
        *out = dq * dq + f[r];
    }
}

#[cfg(test)]
#[allow(clippy::cast_precision_loss, clippy::unwrap_used, reason = "tests")]
mod tests {
    use super::*;

    #[test]
    fn the_distance_transform_is_the_brute_force_one() {
        let (w, h) = (13, 9);
        let grid: Vec<f64> = (0..w * h)
            .map(|i| match i % 17 {
                0 => 0.0,
                5 => 0.16,
                _ => FAR,
            })
            .collect();
        let mut fast = grid.clone();
        edt(&mut fast, w, h);
        for (p, got) in fast.iter().enumerate() {
            let (px, py) = ((p % w) as f64, (p / w) as f64);
            let brute = (0..w * h)
                .map(|q| {
                    let (qx, qy) = ((q % w) as f64, (q / w) as f64);
                    grid[q] + (px - qx).powi(2) + (py - qy).powi(2)
                })
                .fold(FAR * 4.0, f64::min);
            assert!((got - brute).abs() < 1e-6 * brute.max(1.0), "cell {p}: {got} against {brute}");
        }
    }

    #[test]
    fn a_filled_square_has_its_edge_at_192() {
        // 10 x 10 inside, covered whole: inside rises above 192, outside falls below.
        let sdf = distance_field(&[255; 100], 10, 10);
        let w = 16;
        let at = |x: usize, y: usize| sdf[y * w + x];
        assert!(at(8, 8) > 230, "centre {}", at(8, 8));
        assert!(at(0, 8) < 150, "border {}", at(0, 8));
        // Across the edge (between columns 2 and 3): from below to above the cutoff.
        assert!(at(2, 8) < 192 && at(3, 8) > 192, "{} {}", at(2, 8), at(3, 8));
    }

    #[test]
    fn names_match_without_case_spaces_or_a_regular_style() {
        assert_eq!(key("DejaVu Sans Book"), key("dejavu sans"));
        assert_eq!(key("Open Sans Regular"), key("OpenSans"));
        assert_ne!(key("DejaVu Sans Bold"), key("DejaVu Sans"));
        assert_eq!(parse_range("256-511.pbf"), Some(256));
        assert_eq!(parse_range("0-255"), Some(0));
        for bad in ["1-256.pbf", "0-254.pbf", "65536-65791.pbf", "x-y.pbf", "0255.pbf"] {
            assert_eq!(parse_range(bad), None, "{bad}");
        }
    }
}
