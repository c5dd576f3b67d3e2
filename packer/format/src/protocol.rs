//! The tile endpoint's wire protocol, spelled once for the server that speaks it and the
//! clients that read it: paths under an archive's base URL and the headers it adds.

use crate::key::TileKey;

/// Response header on metadata and tile answers: the strong ETag of the archive file they
/// come from, so a client of the tile endpoint never mixes tiles of two versions.
pub const ARCHIVE_ETAG_HEADER: &str = "x-terrastream-archive-etag";
/// Response header of a missing tile's 404: the nearest coarser LOD that exists there.
pub const FALLBACK_LOD_HEADER: &str = "x-terrastream-fallback-lod";
/// Path of the metadata document under an archive's base URL.
pub const METADATA_PATH: &str = "metadata";

/// Path of a tile under an archive's base URL: `{layer}/{lod}/{x}/{y}` (the layer by its
/// index; the server also takes its name).
pub fn tile_path(key: TileKey) -> String {
    format!("{}/{}/{}/{}", key.layer(), key.lod(), key.x(), key.y())
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_tile_path_is_layer_lod_x_y() {
        assert_eq!(tile_path(TileKey::new(1, 3, 5, 7).unwrap()), "1/3/5/7");
    }
}
