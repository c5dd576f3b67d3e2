//! Non-blocking reader over any [`AsyncRangeSource`] (HTTP range requests, browser fetch).

use bytes::Bytes;

use crate::archive::{Archive, Bootstrap, Locate, TileLocation};
use crate::error::{Error, Result};
use crate::key::TileKey;
use crate::metadata::Metadata;
use crate::ranges::AsyncRangeSource;

/// The async twin of [`crate::Reader`]: the same [`Archive`] core, awaited reads.
#[derive(Debug)]
pub struct AsyncReader<S> {
    source: S,
    archive: Archive,
}

impl<S: AsyncRangeSource> AsyncReader<S> {
    /// Opens an archive with one read (two if metadata + root exceed 16 KiB).
    ///
    /// # Errors
    /// Any [`Error`] describing why the bytes are not a valid archive.
    pub async fn new(source: S) -> Result<Self> {
        let file_len = source.size().await?;
        let first = source.fetch(0, Archive::first_read_len(file_len)).await?;
        let archive = match Archive::open(&first, file_len)? {
            Bootstrap::Ready(a) => *a,
            Bootstrap::NeedBytes(n) => match Archive::open(&source.fetch(0, n).await?, file_len)? {
                Bootstrap::Ready(a) => *a,
                Bootstrap::NeedBytes(_) => {
                    return Err(Error::corrupt("header", "bootstrap length is unstable"));
                }
            },
        };
        let mut archive = archive;
        // Older archives with leaf directories: their extents from every leaf, in one
        // request for the leaf section.
        if let Some(section) = archive.leaves_for_extents() {
            archive.derive_extents_from_leaves(&source.fetch(section.offset, section.len).await?)?;
        }
        Ok(Self { source, archive })
    }

    /// The parsed archive core.
    pub fn archive(&self) -> &Archive {
        &self.archive
    }
    /// The metadata.
    pub fn metadata(&self) -> &Metadata {
        self.archive.metadata()
    }
    /// The byte source.
    pub fn source(&self) -> &S {
        &self.source
    }

    /// Where a tile is stored, fetching its leaf directory if needed.
    ///
    /// # Errors
    /// Source errors, a damaged leaf, or a tile outside its layer's grid.
    pub async fn locate(&self, tile: TileKey) -> Result<Option<TileLocation>> {
        loop {
            match self.archive.locate(tile)? {
                Locate::Found(location) => return Ok(Some(location)),
                Locate::Missing => return Ok(None),
                Locate::NeedLeaf { offset, len } => {
                    let bytes = self.source.fetch(offset, len).await?;
                    self.archive.add_leaf(offset, &bytes)?;
                }
            }
        }
    }

    /// A tile's checked payload; `None` if the tile is missing.
    ///
    /// # Errors
    /// Source errors, [`Error::TileChecksum`], [`Error::InvalidTile`].
    pub async fn tile(&self, tile: TileKey) -> Result<Option<Bytes>> {
        let Some(location) = self.locate(tile).await? else {
            return Ok(None);
        };
        let blob = self.source.fetch(location.offset, location.blob_len()).await?;
        self.archive.payload(&location, blob).map(Some)
    }
}
