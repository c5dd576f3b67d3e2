//! A terrain published as several archives (FORMAT.md §9): the manifest names each
//! archive (by URL relative to the manifest), the layers and LODs it holds, the part of
//! the grid it covers at a split LOD, and its content tag; readers route every tile to
//! the one archive that holds it and stream across them as if they were one.

use serde::{Deserialize, Serialize};

use crate::error::{Error, Result};
use crate::key::TileKey;
use crate::metadata::{Layer, Metadata};

/// The value of a manifest's `format` member.
pub const MANIFEST_FORMAT: &str = "terrastream-manifest";

/// Largest manifest document read, in bytes (a planet in 100 000 archives fits).
pub const MAX_MANIFEST_BYTES: u64 = 64 << 20;

/// The manifest document.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct Manifest {
    /// Always [`MANIFEST_FORMAT`].
    pub format: String,
    /// Version of the manifest format: 1.
    pub version: u32,
    /// The terrain the archives make together: what one archive holding every tile
    /// would carry.
    pub metadata: Metadata,
    /// The archives; no two hold the same tile.
    pub archives: Vec<Part>,
}

/// One archive of a manifest.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct Part {
    /// Where it is, relative to the manifest's own location (or an absolute URL).
    pub url: String,
    /// Its content tag ([`content_tag`] of its header): a reader that finds another
    /// archive there knows the manifest and the archive were not published together.
    pub etag: String,
    /// The layers it holds tiles of (it may define more).
    pub layers: Vec<PartLayer>,
}

/// What one archive holds of one layer.
#[derive(Clone, Debug, PartialEq, Eq, Serialize, Deserialize)]
pub struct PartLayer {
    /// The layer's name (the manifest's metadata defines it).
    pub name: String,
    /// The layer's index in the archive's own metadata (tile keys there use it).
    pub index: u8,
    /// The finest and the coarsest LOD it holds, inclusive.
    pub lods: [u8; 2],
    /// The part of the grid it holds; absent: all of it.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub coverage: Option<Coverage>,
}

/// Tiles of a layer at one LOD (at least as coarse as every LOD the archive holds): the
/// archive holds a tile when its ancestor at `lod` lies in one of the rectangles.
#[derive(Clone, Debug, PartialEq, Eq, Serialize, Deserialize)]
pub struct Coverage {
    /// The split LOD the rectangles are given at.
    pub lod: u8,
    /// Tile rectangles `[x0, y0, x1, y1)` at `lod`.
    pub rects: Vec<[u32; 4]>,
}

/// Where a tile of a manifest's terrain is.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct Route {
    /// Index of the archive in [`Manifest::archives`].
    pub part: usize,
    /// The tile's key in that archive (its layer index is the archive's own).
    pub key: TileKey,
}

/// The content tag of an archive: 16 hex digits of the XXH3 hash of its 128-byte header
/// (as [`crate::Header::encode`] writes it), which holds the sections' offsets, lengths
/// and checksums. Unlike an HTTP ETag it does
/// not depend on the host (a CDN or nginx derives ETags from file times), so a manifest
/// can name it before the archives are published.
pub fn content_tag(header: &[u8]) -> String {
    format!("{:016x}", xxhash_rust::xxh3::xxh3_64(header))
}

impl Manifest {
    /// A manifest of one archive holding all of `metadata`'s terrain.
    pub fn single(metadata: Metadata, url: impl Into<String>, etag: impl Into<String>) -> Self {
        let layers = metadata
            .layers
            .iter()
            .zip(0u8..)
            .map(|(l, index)| PartLayer { name: l.name.clone(), index, lods: [0, l.num_lods - 1], coverage: None })
            .collect();
        Self {
            format: MANIFEST_FORMAT.to_owned(),
            version: 1,
            metadata,
            archives: vec![Part { url: url.into(), etag: etag.into(), layers }],
        }
    }

    /// Parses and validates a document.
    ///
    /// # Errors
    /// [`Error::Manifest`] on invalid JSON or a document that breaks a rule of FORMAT.md
    /// §9, naming the archive and layer at fault.
    pub fn from_json(bytes: &[u8]) -> Result<Self> {
        if bytes.len() as u64 > MAX_MANIFEST_BYTES {
            return Err(Error::Manifest(format!("{} bytes, over the {MAX_MANIFEST_BYTES}-byte limit", bytes.len())));
        }
        let m: Self = serde_json::from_slice(bytes).map_err(|e| Error::Manifest(e.to_string()))?;
        m.validate()?;
        Ok(m)
    }

    /// Serializes to indented JSON.
    pub fn to_json(&self) -> Vec<u8> {
        // Plain data with string keys: cannot fail.
        let mut out = serde_json::to_vec_pretty(self).unwrap_or_default();
        out.push(b'\n');
        out
    }

    /// Checks the rules of FORMAT.md §9.
    ///
    /// # Errors
    /// [`Error::Manifest`] naming the archive and layer at fault.
    pub fn validate(&self) -> Result<()> {
        let bad = |msg: String| Err(Error::Manifest(msg));
        if self.format != MANIFEST_FORMAT {
            return bad(format!("format {:?}, not {MANIFEST_FORMAT:?}", self.format));
        }
        if self.version != 1 {
            return bad(format!("version {} (this reader reads 1)", self.version));
        }
        self.metadata.validate().map_err(|e| Error::Manifest(format!("metadata: {e}")))?;
        if self.archives.is_empty() {
            return bad("no archives".into());
        }
        for (i, part) in self.archives.iter().enumerate() {
            let at = format!("archive {i} ({:?})", part.url);
            if part.url.is_empty() || part.url.starts_with('/') || part.url.contains(['\\', '\0']) {
                return bad(format!("{at}: url must be relative to the manifest, or http(s)"));
            }
            if part.layers.is_empty() || part.layers.len() > crate::MAX_LAYERS {
                return bad(format!("{at}: {} layers", part.layers.len()));
            }
            for (j, pl) in part.layers.iter().enumerate() {
                let at = format!("{at}, layer {:?}", pl.name);
                if part.layers[..j].iter().any(|o| o.name == pl.name || o.index == pl.index) {
                    return bad(format!("{at}: its name or index listed twice"));
                }
                let Some(layer) = self.layer(&pl.name) else {
                    return bad(format!("{at}: the manifest's metadata has no such layer"));
                };
                let [finest, coarsest] = pl.lods;
                if finest > coarsest || coarsest >= layer.num_lods {
                    return bad(format!("{at}: lods {finest}..={coarsest} outside 0..{}", layer.num_lods));
                }
                if let Some(c) = &pl.coverage {
                    if c.lod < coarsest || c.lod >= layer.num_lods {
                        return bad(format!("{at}: coverage at LOD {}, must be {coarsest}..{}", c.lod, layer.num_lods));
                    }
                    let (nx, ny) = layer.grid_at(c.lod);
                    if let Some(r) = c.rects.iter().find(|r| r[0] >= r[2] || r[1] >= r[3] || r[2] > nx || r[3] > ny) {
                        return bad(format!(
                            "{at}: rectangle {r:?} empty or outside the {nx}x{ny} grid at LOD {}",
                            c.lod
                        ));
                    }
                }
            }
        }
        self.check_disjoint()
    }

    fn layer(&self, name: &str) -> Option<&Layer> {
        self.metadata.layers.iter().find(|l| l.name == name)
    }

    /// No two archives hold the same tile.
    fn check_disjoint(&self) -> Result<()> {
        for layer in &self.metadata.layers {
            let holders: Vec<(usize, &PartLayer)> = self
                .archives
                .iter()
                .enumerate()
                .filter_map(|(i, p)| p.layers.iter().find(|l| l.name == layer.name).map(|l| (i, l)))
                .collect();
            for (n, &(i, a)) in holders.iter().enumerate() {
                for &(j, b) in &holders[..n] {
                    if a.lods[0] > b.lods[1]
                        || b.lods[0] > a.lods[1]
                        || !overlap(a.coverage.as_ref(), b.coverage.as_ref())
                    {
                        continue;
                    }
                    return Err(Error::Manifest(format!(
                        "archives {j} ({:?}) and {i} ({:?}) both hold tiles of layer {:?}",
                        self.archives[j].url, self.archives[i].url, layer.name
                    )));
                }
            }
        }
        Ok(())
    }

    /// The archive that holds `key` (a key of the manifest's terrain), and the tile's key
    /// there; None if no archive does (the tile is missing).
    pub fn route(&self, key: TileKey) -> Option<Route> {
        let name = &self.metadata.layers.get(usize::from(key.layer()))?.name;
        self.archives.iter().enumerate().find_map(|(part, p)| {
            let pl = p.layers.iter().find(|l| l.name == *name)?;
            if key.lod() < pl.lods[0] || key.lod() > pl.lods[1] {
                return None;
            }
            if let Some(c) = &pl.coverage {
                let shift = u32::from(c.lod - key.lod());
                let (x, y) = (key.x().checked_shr(shift).unwrap_or(0), key.y().checked_shr(shift).unwrap_or(0));
                if !c.rects.iter().any(|r| (r[0]..r[2]).contains(&x) && (r[1]..r[3]).contains(&y)) {
                    return None;
                }
            }
            let key = TileKey::new(pl.index, key.lod(), key.x(), key.y()).ok()?;
            Some(Route { part, key })
        })
    }

    /// Checks that the archive found at part `index` is the one the manifest names: its
    /// content tag, and its layers (where the manifest says, defined as the manifest's)
    /// and CRS.
    ///
    /// # Errors
    /// [`Error::Manifest`] naming the archive and what differs.
    pub fn check_part(&self, index: usize, header: &[u8], metadata: &Metadata) -> Result<()> {
        let part = self.archives.get(index).ok_or_else(|| Error::Manifest(format!("no archive {index}")))?;
        let bad = |why: String| Err(Error::Manifest(format!("archive {:?}: {why}", part.url)));
        let tag = content_tag(header);
        if tag != part.etag {
            return bad(format!("content tag {tag}, the manifest names {} (published apart?)", part.etag));
        }
        for listed in &part.layers {
            let Some(have) = metadata.layers.get(usize::from(listed.index)) else {
                return bad(format!("no layer {} ({:?} in the manifest)", listed.index, listed.name));
            };
            if have.name != listed.name {
                return bad(format!("layer {} is {:?}, the manifest lists {:?}", listed.index, have.name, listed.name));
            }
            if self.layer(&have.name).is_none_or(|l| !l.same_grid(have)) {
                return bad(format!("layer {:?} is not defined as in the manifest", have.name));
            }
        }
        let crs = |m: &Metadata| m.georeference.as_ref().map(|g| (g.crs.clone(), g.origin));
        if crs(metadata) != crs(&self.metadata) {
            return bad("another CRS or origin than the manifest's".into());
        }
        Ok(())
    }

    /// Resolves a part's URL against the manifest's own location (a path or an http(s)
    /// URL): the location of the archive.
    pub fn resolve(&self, manifest_location: &str, index: usize) -> Option<String> {
        let url = &self.archives.get(index)?.url;
        if url.starts_with("http://") || url.starts_with("https://") {
            return Some(url.clone());
        }
        let base = manifest_location.split(['?', '#']).next().unwrap_or(manifest_location);
        let dir = base.rfind('/').map_or("", |i| &base[..=i]);
        Some(format!("{dir}{url}"))
    }
}

/// Do two coverages share a tile? (None is the whole grid.) Compared at the finer of
/// their LODs, where the coarser one's rectangles scale exactly.
fn overlap(a: Option<&Coverage>, b: Option<&Coverage>) -> bool {
    let (Some(a), Some(b)) = (a, b) else { return true };
    let lod = a.lod.min(b.lod);
    let scaled = |c: &Coverage| -> Vec<[u64; 4]> {
        let s = u32::from(c.lod - lod);
        c.rects.iter().map(|r| r.map(|v| u64::from(v) << s)).collect()
    };
    let (ra, rb) = (scaled(a), scaled(b));
    ra.iter().any(|p| rb.iter().any(|q| p[0] < q[2] && q[0] < p[2] && p[1] < q[3] && q[1] < p[3]))
}

/// Is `location` (a path or URL) a manifest rather than an archive? By its name: `.json`.
pub fn is_manifest_location(location: &str) -> bool {
    let path = location.split(['?', '#']).next().unwrap_or(location);
    path.ends_with(".json")
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::metadata::{LayerKind, TileFormat};

    fn layer(name: &str) -> Layer {
        Layer {
            name: name.into(),
            kind: LayerKind::Texture,
            format: TileFormat::Png,
            compression: crate::PayloadCompression::None,
            tile_resolution: 256,
            border: 0,
            num_x_tiles: 8,
            num_y_tiles: 6,
            num_lods: 4,
            tile_world_size: 100.0,
            elevation: None,
            extent: None,
        }
    }

    /// A coarse archive (LODs 2..=3 of both layers) plus two bands of LOD-1 rows.
    fn sample() -> Manifest {
        let metadata = Metadata::new("t", vec![layer("texture"), layer("other")]);
        let band = |rows: [u32; 2]| Some(Coverage { lod: 1, rects: vec![[0, rows[0], 4, rows[1]]] });
        let regional = |url: &str, rows| Part {
            url: url.into(),
            etag: "0".into(),
            layers: vec![
                PartLayer { name: "other".into(), index: 0, lods: [0, 1], coverage: band(rows) },
                PartLayer { name: "texture".into(), index: 1, lods: [0, 1], coverage: band(rows) },
            ],
        };
        let mut m = Manifest::single(metadata, "coarse.tspack", "0");
        for l in &mut m.archives[0].layers {
            l.lods = [2, 3];
        }
        m.archives.push(regional("a.tspack", [0, 2]));
        m.archives.push(regional("sub/b.tspack", [2, 3]));
        m
    }

    #[test]
    fn every_tile_goes_to_the_one_archive_that_holds_it() {
        let m = sample();
        m.validate().unwrap();
        let key = |layer, lod, x, y| TileKey::new(layer, lod, x, y).unwrap();
        let route = |k| m.route(k).map(|r| (r.part, r.key));
        assert_eq!(route(key(0, 3, 0, 0)), Some((0, key(0, 3, 0, 0))));
        assert_eq!(route(key(1, 2, 1, 1)), Some((0, key(1, 2, 1, 1))));
        // LOD-0 row 3 is LOD-1 row 1: band a; the layer's index there is a's own.
        assert_eq!(route(key(0, 0, 7, 3)), Some((1, key(1, 0, 7, 3))));
        assert_eq!(route(key(1, 0, 7, 3)), Some((1, key(0, 0, 7, 3))));
        assert_eq!(route(key(0, 1, 3, 2)), Some((2, key(1, 1, 3, 2))));
        assert_eq!(route(key(0, 0, 0, 5)), Some((2, key(1, 0, 0, 5))));
        // LOD-1 rows from 3 on: no archive holds them.
        assert_eq!(route(key(0, 0, 0, 6)), None);
        assert_eq!(route(key(2, 0, 0, 0)), None);
        assert_eq!(m.resolve("http://h/x/planet.json?v=2", 2).as_deref(), Some("http://h/x/sub/b.tspack"));
        assert_eq!(m.resolve("planet.json", 1).as_deref(), Some("a.tspack"));
        assert_eq!(m.resolve("/d/planet.json", 0).as_deref(), Some("/d/coarse.tspack"));
        let back = Manifest::from_json(&m.to_json()).unwrap();
        assert_eq!(back, m);
    }

    #[test]
    fn a_tile_held_twice_or_outside_the_grid_is_refused_naming_the_archives() {
        let mut m = sample();
        m.archives[2].layers[1].coverage = Some(Coverage { lod: 2, rects: vec![[0, 0, 1, 1]] });
        let e = m.validate().unwrap_err().to_string();
        assert!(e.contains("archives 1 (\"a.tspack\") and 2 (\"sub/b.tspack\")") && e.contains("texture"), "{e}");
        // Bands that touch without sharing a row are fine, whatever LOD they are given at.
        m.archives[2].layers[1].coverage = Some(Coverage { lod: 2, rects: vec![[0, 1, 2, 2]] });
        m.validate().unwrap();
        let mut m = sample();
        m.archives[0].layers[0].lods = [1, 3];
        assert!(m.validate().unwrap_err().to_string().contains("both hold"));
        let mut m = sample();
        m.archives[1].layers[0].coverage = Some(Coverage { lod: 1, rects: vec![[0, 0, 5, 1]] });
        assert!(m.validate().unwrap_err().to_string().contains("outside the 4x3 grid"));
        let mut m = sample();
        m.archives[1].layers[0].coverage = Some(Coverage { lod: 0, rects: vec![[0, 0, 1, 1]] });
        assert!(m.validate().unwrap_err().to_string().contains("coverage at LOD 0, must be 1..4"));
        let mut m = sample();
        m.archives[1].layers[0].name = "nope".into();
        assert!(m.validate().unwrap_err().to_string().contains("no such layer"));
        let mut m = sample();
        m.archives[1].url = "/etc/passwd".into();
        assert!(m.validate().unwrap_err().to_string().contains("relative"));
        assert!(Manifest::from_json(b"{\"format\":\"x\"}").is_err());
    }

    #[test]
    fn an_archive_that_is_not_the_one_named_is_refused() {
        let mut m = sample();
        let header = [7u8; 128];
        m.archives[1].etag = content_tag(&header);
        let mut metadata = m.metadata.clone();
        metadata.layers.reverse();
        m.check_part(1, &header, &metadata).unwrap();
        let e = m.check_part(1, &[8u8; 128], &metadata).unwrap_err().to_string();
        assert!(e.contains("a.tspack") && e.contains("content tag"), "{e}");
        metadata.layers[0].tile_resolution = 128;
        let e = m.check_part(1, &header, &metadata).unwrap_err().to_string();
        assert!(e.contains("not defined as in the manifest"), "{e}");
        metadata.layers.reverse();
        let e = m.check_part(1, &header, &metadata).unwrap_err().to_string();
        assert!(e.contains("layer 0 is \"texture\", the manifest lists \"other\""), "{e}");
        metadata.layers.reverse();
        metadata.layers[0].tile_resolution = 256;
        metadata.layers.truncate(1);
        let e = m.check_part(1, &header, &metadata).unwrap_err().to_string();
        assert!(e.contains("no layer 1 (\"texture\" in the manifest)"), "{e}");
    }
}
