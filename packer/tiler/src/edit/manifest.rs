//! Publishing a sharded run as several archives (`merge --manifest`, `tile
//! --manifest-out`): the shards stay as they are, the levels above their split LOD go into
//! one coarse archive, and a manifest (FORMAT.md §9) tells readers which archive holds
//! which tile. Nothing is copied: for a planet, the merge only makes the coarse levels.

use std::collections::BTreeMap;
use std::path::{Component, Path, PathBuf};

use terrastream_format::{Coverage, LayerKind, Manifest, Metadata, Part, PartLayer, Reader, content_tag};
use terrastream_pack::progress::Progress;
use terrastream_pack::{WriteSummary, Writer, WriterOptions};

use crate::edit::merge::{prepare, warn_water_above_split, write};
use crate::error::{Error, Result};
use crate::pyramid::Spool;

/// What [`merge_to_manifest`] did.
#[derive(Clone, Debug)]
pub struct ManifestSummary {
    /// The coarse archive written.
    pub coarse: WriteSummary,
    /// The manifest.
    pub manifest: Manifest,
}

/// Makes the levels above the split LOD of a complete set of shards into `coarse` and
/// writes `manifest_path`, listing the coarse archive and every shard that holds tiles
/// (URLs relative to the manifest). The manifest is written last, beside, then renamed.
///
/// # Errors
/// [`Error::Input`] if the inputs are not all the shards of one run, or an archive's path
/// cannot be written relative to the manifest's folder (another drive, characters a URL
/// path may not hold); as [`crate::merge`] otherwise.
///
/// With `water` (a mask, shards that hold a water layer: `terrastream water` of each), the
/// coarse archive's water tiles are made from it, as [`crate::add_water`] makes them:
/// shards without a water layer are refused, naming the first.
pub fn merge_to_manifest(
    inputs: &[PathBuf],
    coarse: &Path,
    manifest_path: &Path,
    water: Option<&Path>,
    run: crate::RunInputs<'_>,
    progress: &dyn Progress,
) -> Result<ManifestSummary> {
    if let Some(mask) = water {
        crate::water::check_mask(mask)?;
    }
    let prepared = prepare(inputs, progress)?;
    let Some(split_lods) = prepared.shards.clone() else {
        return Err(Error::input(&inputs[0], "a manifest is made from the complete set of shards of one run"));
    };
    let has_water = prepared.metadata.layers.iter().any(|l| l.kind == LayerKind::Water);
    match water {
        Some(_) if !has_water => {
            return Err(Error::input(
                &inputs[0],
                "the shards hold no water layer, so the manifest would route water tiles to none: add it to each \
                 shard first (`terrastream water SHARD --mask MASK`), then publish them with the same mask",
            ));
        }
        Some(_) => {}
        None => warn_water_above_split(&prepared.metadata, &split_lods),
    }
    let folder = terrastream_pack::output_folder(manifest_path);
    let spools = terrastream_pack::output_folder(coarse);
    let mut spool = Spool::new(&spools)?;
    prepared.make_above(&split_lods, run, &inputs[0], &mut spool, progress)?;
    let options = WriterOptions { batch_bytes: 4 << 20, ..WriterOptions::default() };
    let mut writer = Writer::create(coarse, prepared.metadata.clone(), options)?;
    write(&mut writer, &prepared.readers, &BTreeMap::new(), spool.into_sorted()?, progress)?;
    let mut summary = writer.finish()?;
    // The water above the split, from the mask (the shards' own stand below it).
    if let Some(mask) = water {
        summary = crate::add_water(coarse, mask, coarse, progress)?.write;
    }

    let coarse_reader =
        Reader::open_mmap(coarse).map_err(|e| Error::input(coarse, format!("cannot read back: {e}")))?;
    // The terrain's data: the shards' and the coarse levels' above them.
    let mut metadata = prepared.metadata.clone();
    for (layer, coarse_layer) in metadata.layers.iter_mut().zip(&coarse_reader.metadata().layers) {
        layer.extent = match (&layer.extent, &coarse_layer.extent) {
            (Some(a), Some(b)) => Some(a.union(b)),
            (a, b) => a.clone().or_else(|| b.clone()),
        };
    }
    let mut archives = vec![Part {
        url: relative_url(&folder, coarse)?,
        etag: content_tag(&coarse_reader.header().encode()),
        layers: coarse_layers(&metadata, &split_lods),
    }];
    for (path, reader) in inputs.iter().zip(&prepared.readers) {
        let Some(shard) = &reader.metadata().shard else { continue };
        if reader.header().addressed_tiles == 0 {
            continue;
        }
        let layers = shard_layers(&metadata, &split_lods, &shard.tile_rows);
        if layers.is_empty() {
            continue;
        }
        archives.push(Part { url: relative_url(&folder, path)?, etag: content_tag(&reader.header().encode()), layers });
    }
    let manifest = Manifest { archives, ..Manifest::single(metadata, String::new(), String::new()) };
    manifest.validate()?;
    write_manifest(&manifest, manifest_path)?;
    Ok(ManifestSummary { coarse: summary, manifest })
}

/// The coarse archive holds, of every layer, the levels above its split LOD.
fn coarse_layers(metadata: &Metadata, split_lods: &[u8]) -> Vec<PartLayer> {
    metadata
        .layers
        .iter()
        .zip(0u8..)
        .filter_map(|(layer, index)| {
            let k = split_lods.get(usize::from(index)).copied().unwrap_or(0);
            (k + 1 < layer.num_lods).then(|| PartLayer {
                name: layer.name.clone(),
                index,
                lods: [k + 1, layer.num_lods - 1],
                coverage: None,
            })
        })
        .collect()
}

/// A shard holds, of every layer, LODs 0 to K in its band of LOD-0 tile rows (a multiple
/// of 2^K, or the grid's edge: whole rows at K).
fn shard_layers(metadata: &Metadata, split_lods: &[u8], tile_rows: &[[u32; 2]]) -> Vec<PartLayer> {
    metadata
        .layers
        .iter()
        .zip(0u8..)
        .filter_map(|(layer, index)| {
            let k = split_lods.get(usize::from(index)).copied()?.min(layer.num_lods - 1);
            let [start, end] = *tile_rows.get(usize::from(index))?;
            let (y0, y1) = (start >> k, end.div_ceil(1 << k));
            (y0 < y1).then(|| PartLayer {
                name: layer.name.clone(),
                index,
                lods: [0, k],
                coverage: Some(Coverage { lod: k, rects: vec![[0, y0, layer.grid_at(k).0, y1]] }),
            })
        })
        .collect()
}

/// `target`'s path from `folder`, as a URL path: `/`-separated, `..` where needed.
fn relative_url(folder: &Path, target: &Path) -> Result<String> {
    let canonical = |p: &Path| std::fs::canonicalize(p).map_err(|e| Error::file(p, e));
    let (from, to) = (canonical(folder)?, canonical(target)?);
    let (from, to): (Vec<Component>, Vec<Component>) = (from.components().collect(), to.components().collect());
    let common = from.iter().zip(&to).take_while(|(a, b)| a == b).count();
    if common == 0 {
        return Err(Error::input(target, "not reachable by a relative URL from the manifest's folder"));
    }
    let mut parts: Vec<String> = vec!["..".to_owned(); from.len() - common];
    for c in &to[common..] {
        let name = c.as_os_str().to_str().filter(|s| s.chars().all(|c| c.is_ascii_alphanumeric() || "-_.".contains(c)));
        let Some(name) = name else {
            return Err(Error::input(target, "a manifest names archives by URL: use letters, digits, '-', '_', '.'"));
        };
        parts.push(name.to_owned());
    }
    Ok(parts.join("/"))
}

/// Writes a manifest beside `path`, then renames it into place.
pub fn write_manifest(manifest: &Manifest, path: &Path) -> Result<()> {
    let folder = terrastream_pack::output_folder(path);
    let name = path.file_name().and_then(|n| n.to_str()).unwrap_or("manifest.json");
    let partial = folder.join(format!(".{name}.partial"));
    std::fs::write(&partial, manifest.to_json()).map_err(|e| Error::file(&partial, e))?;
    std::fs::rename(&partial, path).map_err(|e| {
        let _ = std::fs::remove_file(&partial);
        Error::file(path, e)
    })
}

/// A manifest of one finished archive (`tile --manifest-out`).
///
/// # Errors
/// The archive cannot be read back, or not named relative to the manifest.
pub fn single_manifest(archive: &Path, manifest_path: &Path) -> Result<Manifest> {
    let reader = Reader::open_mmap(archive).map_err(|e| Error::input(archive, format!("cannot read back: {e}")))?;
    let folder = terrastream_pack::output_folder(manifest_path);
    let mut metadata = reader.metadata().clone();
    metadata.shard = None;
    let mut manifest =
        Manifest::single(metadata, relative_url(&folder, archive)?, content_tag(&reader.header().encode()));
    // A shard holds only its band up to its split LOD.
    if let Some(shard) = &reader.metadata().shard {
        manifest.archives[0].layers = shard_layers(&manifest.metadata, &shard.split_lods, &shard.tile_rows);
    }
    manifest.validate()?;
    write_manifest(&manifest, manifest_path)?;
    Ok(manifest)
}
