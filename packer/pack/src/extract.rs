//! `terrastream extract`: writes an archive's tiles back as files, in the original
//! engine's folder layout or as an XYZ tree. Tiles packed from files come back
//! byte-for-byte under the names they were found with.

use std::path::{Path, PathBuf};

use terrastream_format::{MAX_LAYERS, Metadata, RangeSource, Reader, TileKey, payload_bytes};

use crate::error::{Error, Result};
use crate::import::original::metadata;
use crate::import::{LayerNaming, LayoutRecord, XyzRecord};
use crate::progress::Progress;

/// Folder layout written by [`extract`].
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Layout {
    /// `LOD0`, `LOD1`, ... per layer, plus the metadata text.
    Original,
    /// `{z}/{x}/{y}.ext` (the template recorded at import, else per layer folder).
    Xyz,
}

/// What [`extract`] wrote.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub struct ExtractSummary {
    /// Tile files written.
    pub files: u64,
    /// Bytes of tile files written.
    pub bytes: u64,
}

/// Computes the file path of each tile for a layout.
struct Namer {
    layout: Layout,
    record: Option<LayoutRecord>,
    original: Vec<LayerNaming>,
    xyz: Option<XyzRecord>,
    single_layer: bool,
}

impl Namer {
    fn new(metadata: &Metadata, layout: Layout) -> Self {
        let record: Option<LayoutRecord> =
            metadata.extra.get(crate::import::LAYOUT_KEY).and_then(|v| serde_json::from_value(v.clone()).ok());
        let xyz = metadata.extra.get(crate::import::XYZ_KEY).and_then(|v| serde_json::from_value(v.clone()).ok());
        let single_layer = metadata.layers.len() == 1;
        let original = metadata
            .layers
            .iter()
            .map(|l| {
                record.as_ref().and_then(|r| r.layers.iter().find(|n| n.layer == l.name).cloned()).unwrap_or_else(
                    || LayerNaming {
                        layer: l.name.clone(),
                        folder: if single_layer { String::new() } else { l.name.clone() },
                        prefix: String::new(),
                        separator: "_".into(),
                        suffix: String::new(),
                        extension: l.format.extension().into(),
                        swap_xy: false,
                    },
                )
            })
            .collect();
        Self { layout, record, original, xyz, single_layer }
    }

    fn path(&self, metadata: &Metadata, tile: TileKey) -> PathBuf {
        let layer = &metadata.layers[usize::from(tile.layer())];
        match self.layout {
            Layout::Original => {
                let n = &self.original[usize::from(tile.layer())];
                let (a, b) = if n.swap_xy { (tile.y(), tile.x()) } else { (tile.x(), tile.y()) };
                let mut name = format!("{}{a}{}{b}{}", n.prefix, n.separator, n.suffix);
                if !n.extension.is_empty() {
                    name = format!("{name}.{}", n.extension);
                }
                let mut p = PathBuf::new();
                if !n.folder.is_empty() {
                    p.push(&n.folder);
                }
                p.push(format!("LOD{}", tile.lod()));
                p.push(name);
                p
            }
            Layout::Xyz => {
                let z = u32::from(layer.depth() - 1 - tile.lod());
                // The tree's own names, where it was packed from one (zooms counted from its
                // finest, rows flipped against its own grid: a geodetic tree is 2x1 at zoom 0).
                let original = self.xyz.as_ref().filter(|_| self.single_layer).and_then(|record| {
                    let z = u32::from(record.max_zoom.checked_sub(tile.lod())?);
                    let y = match record.scheme {
                        crate::import::Scheme::Xyz => tile.y(),
                        crate::import::Scheme::Tms => layer.grid_at(tile.lod()).1.checked_sub(tile.y() + 1)?,
                    };
                    crate::import::fill_template(&record.template, z, tile.x(), y).ok()
                });
                match original {
                    Some(name) => PathBuf::from(name),
                    None => PathBuf::from(format!(
                        "{}/{z}/{}/{}.{}",
                        layer.name,
                        tile.x(),
                        tile.y(),
                        layer.format.extension()
                    )),
                }
            }
        }
    }
}

/// Writes every tile of the archive under `out`.
///
/// # Errors
/// [`Error::File`] naming a file that cannot be written, archive read errors,
/// [`Error::Interrupted`] on cancel.
pub fn extract<S: RangeSource>(
    reader: &Reader<S>,
    out: &Path,
    layout: Layout,
    progress: &dyn Progress,
) -> Result<ExtractSummary> {
    let metadata = reader.metadata();
    let namer = Namer::new(metadata, layout);
    let mut summary = ExtractSummary::default();
    let mut made_dirs: Option<PathBuf> = None;
    progress.start("extract", reader.header().addressed_tiles);
    reader.for_each_entry(|entry| -> Result<()> {
        progress.check()?;
        let first = reader.archive().tile_of(entry.key)?;
        let layer = &metadata.layers[usize::from(first.layer())];
        let stored = reader.entry_payload(entry)?;
        let payload = payload_bytes(layer, &stored, &format!("tile {first}"))?.into_owned();
        for i in 0..u64::from(entry.run_length) {
            let tile = reader.archive().tile_of(entry.key + i * MAX_LAYERS as u64)?;
            let path = out.join(namer.path(metadata, tile));
            if let Some(parent) = path.parent()
                && made_dirs.as_deref() != Some(parent)
            {
                std::fs::create_dir_all(parent).map_err(|e| Error::file(parent, e))?;
                made_dirs = Some(parent.to_path_buf());
            }
            std::fs::write(&path, &payload).map_err(|e| Error::file(&path, e))?;
            summary.files += 1;
            summary.bytes += payload.len() as u64;
        }
        progress.advance(u64::from(entry.run_length));
        Ok(())
    })?;
    if layout == Layout::Original {
        write_metadata_text(metadata, namer.record.as_ref(), out)?;
    }
    Ok(summary)
}

/// The metadata text: verbatim when the archive was packed from one, generated otherwise.
fn write_metadata_text(metadata: &Metadata, record: Option<&LayoutRecord>, out: &Path) -> Result<()> {
    let (name, text) = match record {
        Some(LayoutRecord { metadata_file: Some(name), metadata_text: Some(text), .. }) => (name.clone(), text.clone()),
        _ => ("metadata.txt".to_owned(), metadata::render(&metadata::fields_for(metadata))),
    };
    let path = out.join(name);
    std::fs::create_dir_all(out).map_err(|e| Error::file(out, e))?;
    std::fs::write(&path, text).map_err(|e| Error::file(&path, e))
}
