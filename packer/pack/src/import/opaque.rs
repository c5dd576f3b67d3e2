//! Where a pyramid's imagery has pixels: the opaque box of its finest tiles. Tile trees
//! cut from a raster (gdal2tiles, MapTiler) fill the tiles on the data's rim with
//! transparent pixels; the finest LOD's tile box alone frames the data loosely.

use terrastream_format::{Layer, LayerKind, TileFormat, TileKey};

use super::pixels::Pixels;

/// Accumulates, per LOD, the box of the opaque pixels of the tiles on the rim of that
/// LOD's tile box (tiles inside it are taken as opaque: they do not reach its edge).
#[derive(Clone, Debug)]
pub struct OpaqueBox {
    layer: u8,
    /// Per LOD: its tile box (inclusive), its tile size in world units, and the opaque
    /// pixels' box in world units so far.
    lods: Vec<Option<LodBox>>,
}

#[derive(Clone, Copy, Debug)]
struct LodBox {
    tiles: [u32; 4],
    size: f64,
    found: Option<[f64; 4]>,
}

impl LodBox {
    /// The box of what was found, with the inner tiles (opaque by assumption) included.
    fn finish(&self) -> Option<[f64; 4]> {
        let f = self.found?;
        let [x0, y0, x1, y1] = self.tiles;
        let s = self.size;
        let inner = (x1 > x0 + 1 && y1 > y0 + 1)
            .then(|| [f64::from(x0 + 1) * s, f64::from(y0 + 1) * s, f64::from(x1) * s, f64::from(y1) * s]);
        Some(inner.map_or(f, |i| terrastream_format::union(f, i)))
    }
}

impl OpaqueBox {
    /// For layer `index`, whose tiles are among `keys`; `None` for layers whose tiles are
    /// not images with alpha (PNG, WebP), or without tiles.
    pub fn new(index: u8, layer: &Layer, keys: impl Iterator<Item = TileKey>) -> Option<Self> {
        let image = matches!(layer.kind, LayerKind::Texture | LayerKind::Elevation);
        if !image || !matches!(layer.format, TileFormat::Png | TileFormat::Webp) {
            return None;
        }
        let mut lods: Vec<Option<LodBox>> = Vec::new();
        for k in keys.filter(|k| k.layer() == index) {
            let lod = usize::from(k.lod());
            if lods.len() <= lod {
                lods.resize(lod + 1, None);
            }
            let (x, y) = (k.x(), k.y());
            let tiles = match lods[lod] {
                Some(b) => [b.tiles[0].min(x), b.tiles[1].min(y), b.tiles[2].max(x), b.tiles[3].max(y)],
                None => [x, y, x, y],
            };
            lods[lod] = Some(LodBox { tiles, size: layer.world_size_at(k.lod()), found: None });
        }
        lods.iter().any(Option::is_some).then_some(Self { layer: index, lods })
    }

    /// Is `key` a tile of this layer on the rim of its LOD's box (whose pixels count)?
    pub fn on_rim(&self, key: TileKey) -> bool {
        let Some(Some(lod)) = self.lods.get(usize::from(key.lod())).filter(|_| key.layer() == self.layer) else {
            return false;
        };
        let [x0, y0, x1, y1] = lod.tiles;
        key.x() == x0 || key.x() == x1 || key.y() == y0 || key.y() == y1
    }

    /// Counts a tile's pixels, if it is on the rim of its LOD's box (else nothing).
    #[cfg(test)]
    pub fn add(&mut self, key: TileKey, bytes: &[u8]) {
        let pixels = TileFormat::sniff(bytes).and_then(|f| super::pixels::decode(f, bytes).ok().flatten());
        self.add_pixels(key, pixels.as_ref());
    }

    /// Counts a rim tile's decoded pixels (`None`: it did not decode, and counts whole:
    /// the pack stores it as it is).
    pub(crate) fn add_pixels(&mut self, key: TileKey, pixels: Option<&Pixels>) {
        if !self.on_rim(key) {
            return;
        }
        let Some(Some(lod)) = self.lods.get_mut(usize::from(key.lod())) else { return };
        let (w, h, opaque) = pixels.map_or((1, 1, Some([0, 0, 0, 0])), |p| (p.width(), p.height(), opaque_pixels(p)));
        let Some([px0, py0, px1, py1]) = opaque else { return };
        let size = lod.size;
        let (tx, ty) = (f64::from(key.x()) * size, f64::from(key.y()) * size);
        let (sx, sy) = (size / f64::from(w), size / f64::from(h));
        let b = [
            tx + f64::from(px0) * sx,
            ty + f64::from(py0) * sy,
            tx + f64::from(px1 + 1) * sx,
            ty + f64::from(py1 + 1) * sy,
        ];
        lod.found = Some(lod.found.map_or(b, |f| terrastream_format::union(f, b)));
    }

    /// The layer index, the box of every LOD's opaque pixels and that of the finest LOD's,
    /// in world units; `None` when no rim tile had an opaque pixel.
    pub fn finish(&self) -> Option<(u8, [f64; 4], [f64; 4])> {
        let boxes: Vec<[f64; 4]> = self.lods.iter().flatten().filter_map(LodBox::finish).collect();
        let detail = self.lods.iter().flatten().next()?.finish()?;
        let world = boxes.into_iter().reduce(terrastream_format::union)?;
        Some((self.layer, world, detail))
    }
}

/// The box (inclusive pixel columns and rows) of the pixels with alpha above zero; every
/// pixel without an alpha channel; `None` when every pixel is transparent.
fn opaque_pixels(p: &Pixels) -> Option<[u32; 4]> {
    let (w, h) = (p.width(), p.height());
    let Some(alpha) = p.alpha() else { return Some([0, 0, w.saturating_sub(1), h.saturating_sub(1)]) };
    let mut found: Option<[u32; 4]> = None;
    for (i, px) in p.data().chunks_exact(p.channels()).enumerate() {
        if px[alpha] == 0 {
            continue;
        }
        let i = u32::try_from(i).ok()?;
        let (x, y) = (i % w.max(1), i / w.max(1));
        found = Some(found.map_or([x, y, x, y], |r| [r[0].min(x), r[1].min(y), r[2].max(x), r[3].max(y)]));
    }
    found
}

#[cfg(test)]
mod tests {
    use terrastream_format::PayloadCompression;

    use super::*;

    #[test]
    fn the_box_ends_where_the_rim_tiles_turn_transparent() {
        let layer = Layer {
            name: "texture".into(),
            kind: LayerKind::Texture,
            format: TileFormat::Png,
            compression: PayloadCompression::None,
            tile_resolution: 4,
            border: 0,
            num_x_tiles: 8,
            num_y_tiles: 8,
            num_lods: 4,
            tile_world_size: 4.0,
            elevation: None,
            extent: None,
        };
        // Tiles (2..=3, 2..=2) at LOD 0: the west one opaque from column 1, the east one
        // up to column 2; rows 1..=3 opaque in both.
        let png = |first: u32, last: u32| {
            let data: Vec<u8> = (0..16u32)
                .flat_map(|i| {
                    let (x, y) = (i % 4, i / 4);
                    let a = if (first..=last).contains(&x) && y >= 1 { 255 } else { 0 };
                    [9, 9, 9, a]
                })
                .collect();
            let mut out = Vec::new();
            let mut e = png::Encoder::new(&mut out, 4, 4);
            e.set_color(png::ColorType::Rgba);
            e.write_header().unwrap().write_image_data(&data).unwrap();
            out
        };
        let keys =
            [TileKey::new(0, 0, 2, 2).unwrap(), TileKey::new(0, 0, 3, 2).unwrap(), TileKey::new(0, 1, 1, 1).unwrap()];
        let mut b = OpaqueBox::new(0, &layer, keys.iter().copied()).unwrap();
        b.add(keys[0], &png(1, 3));
        b.add(keys[1], &png(0, 2));
        b.add(keys[2], &png(0, 3));
        // LOD 1's one tile (8 m) is opaque from row 1 (2 m) down.
        assert_eq!(b.finish(), Some((0, [8.0, 9.0, 16.0, 16.0], [9.0, 9.0, 15.0, 12.0])));
    }
}
