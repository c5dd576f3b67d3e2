//! What `pack` reads from a pyramid's tiles as they pass, each tile decoded at most once
//! and the tiles of a batch on every core: the height range of elevation layers
//! (Terrain-RGB, Terrarium, gray), and where the tiles on each level's rim of image
//! layers have opaque pixels.

use rayon::prelude::*;
use terrastream_format::{ElevationEncoding, LayerKind, Metadata, TileKey};

use super::heights::{HeightRange, pixel_heights};
use super::opaque::OpaqueBox;
use super::pixels::{self, Pixels};
use crate::error::Result;
use crate::writer::Writer;

/// The scan of one archive's tiles.
#[derive(Debug)]
pub(crate) struct TileScan {
    /// Per layer: the height encoding of an elevation layer of images.
    encodings: Vec<Option<ElevationEncoding>>,
    heights: HeightRange,
    /// Per layer with images that can be transparent.
    opaque: Vec<Option<OpaqueBox>>,
}

impl TileScan {
    /// For an archive of `metadata` whose tiles are `keys` (any order).
    pub(crate) fn new(metadata: &Metadata, keys: impl Iterator<Item = TileKey> + Clone) -> Self {
        let encodings =
            metadata.layers.iter().map(|l| l.elevation.filter(|_| l.kind == LayerKind::Elevation)).collect();
        let opaque = (0u8..).zip(&metadata.layers).map(|(i, l)| OpaqueBox::new(i, l, keys.clone())).collect();
        Self { encodings, heights: HeightRange::default(), opaque }
    }

    /// Reads a batch of tiles (stored bytes, in the layers' formats).
    ///
    /// # Errors
    /// The index in `batch` of an elevation tile that is not an image of its encoding,
    /// and why.
    pub(crate) fn scan(&mut self, metadata: &Metadata, batch: &[(TileKey, &[u8])]) -> Result<(), (usize, String)> {
        let found: Vec<(HeightRange, Option<Option<Pixels>>)> = batch
            .par_iter()
            .enumerate()
            .map(|(i, &(key, bytes))| {
                let layer = usize::from(key.layer());
                let encoding = self.encodings.get(layer).copied().flatten();
                let rim = self.opaque.get(layer).and_then(Option::as_ref).is_some_and(|o| o.on_rim(key));
                if encoding.is_none() && !rim {
                    return Ok((HeightRange::default(), None));
                }
                let pixels = pixels::decode(metadata.layers[layer].format, bytes);
                let heights = match (&pixels, encoding) {
                    (Ok(Some(p)), Some(e)) => pixel_heights(p, &e).map_err(|e| (i, e))?,
                    (Err(e), Some(_)) => return Err((i, e.clone())),
                    _ => HeightRange::default(),
                };
                // A rim tile that does not decode counts whole.
                Ok((heights, rim.then(|| pixels.ok().flatten())))
            })
            .collect::<Result<_, _>>()?;
        for ((key, _), (heights, rim)) in batch.iter().zip(found) {
            self.heights = self.heights.merge(heights);
            if let (Some(pixels), Some(Some(o))) = (rim, self.opaque.get_mut(usize::from(key.layer()))) {
                o.add_pixels(*key, pixels.as_ref());
            }
        }
        Ok(())
    }

    /// Writes what was read into the writer's metadata: the height range; for image
    /// layers, the boxes narrowed to their opaque pixels (every LOD's for the data's box,
    /// the finest LOD's for the detail box; the writer takes them as bounds on what the
    /// tiles say).
    ///
    /// # Errors
    /// A metadata error (none for a range of finite heights and boxes inside the grid).
    pub(crate) fn record(self, writer: &mut Writer) -> Result<()> {
        let found: Vec<(u8, [f64; 4], [f64; 4])> = self.opaque.iter().flatten().filter_map(OpaqueBox::finish).collect();
        if self.heights.range.is_none() && found.is_empty() {
            return Ok(());
        }
        let mut metadata = writer.metadata().clone();
        self.heights.record(&mut metadata);
        for (index, world, detail) in found {
            if let Some(layer) = metadata.layers.get_mut(usize::from(index)) {
                layer.extent = Some(terrastream_format::LayerExtent {
                    coarsest_lod: 0,
                    finest_lod: 0,
                    world,
                    detail,
                    crs: None,
                    lon_lat: None,
                    partial: Vec::new(),
                });
            }
        }
        writer.set_metadata(metadata)
    }
}
