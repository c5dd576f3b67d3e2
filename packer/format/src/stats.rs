//! What `terrastream info` reports: sizes, counts per layer and LOD, dedup ratio.

use serde::Serialize;

use crate::directory::{Directory, Entry};
use crate::error::Result;
use crate::key::{MAX_LAYERS, level_base, tile_id_to_zxy};
use crate::metadata::{LayerKind, PayloadCompression, TileFormat};
use crate::ranges::RangeSource;
use crate::reader::Reader;

/// Counts for one layer.
#[derive(Clone, Debug, Serialize)]
pub struct LayerStats {
    /// Layer name.
    pub name: String,
    /// Layer kind.
    pub kind: LayerKind,
    /// Payload format.
    pub format: TileFormat,
    /// Compression around the payload.
    pub compression: PayloadCompression,
    /// Pixels per tile edge.
    pub tile_resolution: u32,
    /// Border pixels.
    pub border: u8,
    /// LOD-0 tiles across and down.
    pub grid: [u32; 2],
    /// LODs that may hold tiles.
    pub num_lods: u8,
    /// World units per LOD-0 tile edge.
    pub tile_world_size: f64,
    /// Present tiles at each LOD (index = LOD, 0 = finest).
    pub tiles_per_lod: Vec<u64>,
    /// Grid cells at each LOD (present + missing).
    pub grid_tiles_per_lod: Vec<u64>,
    /// Payload bytes of the distinct blobs first referenced by this layer.
    pub data_bytes: u64,
}

/// Whole-archive counts.
#[derive(Clone, Debug, Serialize)]
pub struct ArchiveStats {
    /// Format version.
    pub version: String,
    /// File size.
    pub file_bytes: u64,
    /// Stored metadata bytes.
    pub metadata_bytes: u64,
    /// Root directory bytes.
    pub root_directory_bytes: u64,
    /// Leaf directories bytes.
    pub leaf_directory_bytes: u64,
    /// Number of leaf directories.
    pub leaf_directories: u64,
    /// Data section bytes (payloads + checksums).
    pub data_bytes: u64,
    /// Tiles addressed.
    pub addressed_tiles: u64,
    /// Directory entries.
    pub tile_entries: u64,
    /// Distinct blobs.
    pub tile_contents: u64,
    /// addressed tiles / distinct blobs.
    pub dedup_ratio: f64,
    /// (root + leaves) / addressed tiles.
    pub directory_bytes_per_tile: f64,
    /// Bytes a reader fetches to open the archive.
    pub bootstrap_bytes: u64,
    /// Per layer.
    pub layers: Vec<LayerStats>,
}

impl ArchiveStats {
    /// Walks every directory of the archive (not the tile data).
    ///
    /// # Errors
    /// Read or decode errors of a leaf directory.
    pub fn collect<S: RangeSource>(reader: &Reader<S>) -> Result<Self> {
        let header = reader.header().clone();
        let meta = reader.metadata();
        let depths = meta.depths();
        let mut layers: Vec<LayerStats> = meta
            .layers
            .iter()
            .map(|l| LayerStats {
                name: l.name.clone(),
                kind: l.kind,
                format: l.format,
                compression: l.compression,
                tile_resolution: l.tile_resolution,
                border: l.border,
                grid: [l.num_x_tiles, l.num_y_tiles],
                num_lods: l.num_lods,
                tile_world_size: l.tile_world_size,
                tiles_per_lod: vec![0; usize::from(l.num_lods)],
                grid_tiles_per_lod: (0..l.num_lods)
                    .map(|lod| {
                        let (x, y) = l.grid_at(lod);
                        u64::from(x) * u64::from(y)
                    })
                    .collect(),
                data_bytes: 0,
            })
            .collect();
        // Each distinct blob once, where it is first referenced. (Not by offsets rising:
        // an archive updated in place has its new blobs after the old ones, so entries in
        // key order jump back.)
        let mut seen = std::collections::HashSet::new();
        reader.for_each_entry(|e: &Entry| -> Result<()> {
            let layer = usize::from(crate::key::layer_of(e.key));
            if let Some(stats) = layers.get_mut(layer) {
                count_run(stats, e, depths[layer]);
                if seen.insert(e.offset) {
                    stats.data_bytes += u64::from(e.length);
                }
            }
            Ok(())
        })?;
        let leaf_directories = match reader.archive().root() {
            Directory::Leaves(l) => l.len() as u64,
            Directory::Tiles(_) => 0,
        };
        let directory_bytes = header.root_dir.len + header.leaf_dirs.len;
        Ok(Self {
            version: format!("{}.{}", header.version_major, header.version_minor),
            file_bytes: reader.archive().file_len(),
            metadata_bytes: header.metadata.len,
            root_directory_bytes: header.root_dir.len,
            leaf_directory_bytes: header.leaf_dirs.len,
            leaf_directories,
            data_bytes: header.data.len,
            addressed_tiles: header.addressed_tiles,
            tile_entries: header.tile_entries,
            tile_contents: header.tile_contents,
            dedup_ratio: ratio(header.addressed_tiles, header.tile_contents),
            directory_bytes_per_tile: ratio(directory_bytes, header.addressed_tiles),
            bootstrap_bytes: header.bootstrap_len(),
            layers,
        })
    }
}

fn ratio(a: u64, b: u64) -> f64 {
    if b == 0 { 0.0 } else { a as f64 / b as f64 }
}

/// Adds the tiles of a run to the per-LOD counts; a run may cross quadtree levels.
fn count_run(stats: &mut LayerStats, e: &Entry, depth: u8) {
    let first = e.key / MAX_LAYERS as u64;
    let last = first + u64::from(e.run_length) - 1;
    let mut id = first;
    while id <= last {
        let (z, ..) = tile_id_to_zxy(id);
        let n = last.min(level_base(z + 1) - 1) - id + 1;
        if let Some(lod) = depth.checked_sub(1 + z)
            && let Some(count) = stats.tiles_per_lod.get_mut(usize::from(lod))
        {
            *count += n;
        }
        id += n;
    }
}
