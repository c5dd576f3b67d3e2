//! Tile payload -> pixels ready for the GPU or heights ready for queries. Runs on worker
//! threads (a blocking pool on native, inside the fetch task in the browser), never on the
//! frame thread.

use bytes::Bytes;
use terrastream_format::{ElevationEncoding, ElevationScheme, Layer, LayerKind, TileFormat, TileKey, payload_bytes};

use crate::error::{Error, Result};
use crate::image::Image;

/// A decoded tile.
#[derive(Clone, Debug, PartialEq)]
pub struct DecodedTile {
    /// Which tile.
    pub key: TileKey,
    /// Pixels per edge, borders included.
    pub size: u32,
    /// Border pixels on each side (copies of the neighbours' edge pixels).
    pub border: u32,
    /// The pixels.
    pub data: TileData,
}

/// Decoded pixels.
#[derive(Clone, Debug, PartialEq)]
pub enum TileData {
    /// 8-bit RGBA, row-major.
    Rgba8(Vec<u8>),
    /// Heights in world units, row-major; NaN where the source had no data.
    Heights {
        /// The samples.
        heights: Vec<f32>,
        /// Lowest valid height (`+inf` if none).
        min: f32,
        /// Highest valid height (`-inf` if none).
        max: f32,
        /// The renderer's shade texels, four bytes a sample, where they were made
        /// ([`DecodedTile::shade`]).
        shade: Option<Vec<u8>>,
    },
    /// GPU block-compressed texels, uploaded as they are.
    Compressed {
        /// [`TileFormat::Bc1`] or [`TileFormat::Bc7`].
        format: TileFormat,
        /// The blocks, row-major, 4x4 texels each.
        blocks: Bytes,
    },
}

impl DecodedTile {
    /// Bytes the tile occupies in memory (and in a GPU upload).
    pub fn byte_len(&self) -> usize {
        match &self.data {
            TileData::Rgba8(p) => p.len(),
            TileData::Heights { heights, shade, .. } => heights.len() * 4 + shade.as_ref().map_or(0, Vec::len),
            TileData::Compressed { blocks, .. } => blocks.len(),
        }
    }

    /// The tile as flat bytes, for a thread that shares no memory with this one (a
    /// browser's Web Worker decodes, the page's thread uploads): key, size, border, then
    /// the pixels (little-endian). [`DecodedTile::from_wire`] reads it back.
    pub fn to_wire(&self) -> Vec<u8> {
        let mut out = Vec::with_capacity(32 + self.byte_len());
        out.extend_from_slice(&[self.key.layer(), self.key.lod()]);
        for v in [self.key.x(), self.key.y(), self.size, self.border] {
            out.extend_from_slice(&v.to_le_bytes());
        }
        match &self.data {
            TileData::Rgba8(p) => {
                out.push(0);
                out.extend_from_slice(p);
            }
            TileData::Heights { heights, min, max, shade } => {
                out.push(if shade.is_some() { 4 } else { 1 });
                out.extend_from_slice(&min.to_le_bytes());
                out.extend_from_slice(&max.to_le_bytes());
                out.extend(heights.iter().flat_map(|h| h.to_le_bytes()));
                out.extend(shade.iter().flatten());
            }
            TileData::Compressed { format, blocks } => {
                out.push(if *format == TileFormat::Bc7 { 3 } else { 2 });
                out.extend_from_slice(blocks);
            }
        }
        out
    }

    /// A tile from [`DecodedTile::to_wire`]'s bytes.
    ///
    /// # Errors
    /// [`Error::BadTile`] when the bytes are not such a tile.
    pub fn from_wire(bytes: &[u8]) -> Result<Self> {
        let bad = |reason: &str| Error::Wire { reason: reason.to_owned() };
        let (head, rest) = bytes.split_at_checked(19).ok_or_else(|| bad("too short"))?;
        let word = |i: usize| u32::from_le_bytes([head[i], head[i + 1], head[i + 2], head[i + 3]]);
        let key = TileKey::new(head[0], head[1], word(2), word(6)).map_err(|_| bad("bad key"))?;
        let (size, border) = (word(10), word(14));
        let pixels = usize::try_from(u64::from(size) * u64::from(size)).map_err(|_| bad("size"))?;
        let data = match head[18] {
            0 if rest.len() == pixels * 4 => TileData::Rgba8(rest.to_vec()),
            kind @ (1 | 4) if rest.len() == 8 + pixels * (if kind == 4 { 8 } else { 4 }) => {
                let f = |c: &[u8]| f32::from_le_bytes([c[0], c[1], c[2], c[3]]);
                let (samples, shade) = rest[8..].split_at(pixels * 4);
                TileData::Heights {
                    min: f(&rest[0..4]),
                    max: f(&rest[4..8]),
                    heights: samples.chunks_exact(4).map(f).collect(),
                    shade: (kind == 4).then(|| shade.to_vec()),
                }
            }
            2 => TileData::Compressed { format: TileFormat::Bc1, blocks: Bytes::copy_from_slice(rest) },
            3 => TileData::Compressed { format: TileFormat::Bc7, blocks: Bytes::copy_from_slice(rest) },
            _ => return Err(bad("unknown kind or length")),
        };
        Ok(Self { key, size, border, data })
    }

    /// A tile of GPU blocks (BC1, BC7) as RGBA pixels, as a GPU would sample them; other
    /// tiles as they are.
    ///
    /// # Errors
    /// The block decoder's message, for blocks that do not fill the tile.
    #[cfg(feature = "blocks")]
    pub fn unblocked(self) -> std::result::Result<Self, &'static str> {
        let TileData::Compressed { format, blocks } = &self.data else { return Ok(self) };
        let size = self.size as usize;
        let mut pixels = vec![0u32; size * size];
        match format {
            TileFormat::Bc7 => texture2ddecoder::decode_bc7(blocks, size, size, &mut pixels)?,
            _ => texture2ddecoder::decode_bc1(blocks, size, size, &mut pixels)?,
        }
        // The decoder's pixels are B, G, R, A in memory order.
        let rgba = pixels.iter().flat_map(|p| {
            let [b, g, r, a] = p.to_le_bytes();
            [r, g, b, a]
        });
        Ok(Self { data: TileData::Rgba8(rgba.collect()), ..self })
    }

    /// Height sample at pixel `(i, j)` of the stored grid (borders included).
    pub fn height(&self, i: u32, j: u32) -> Option<f32> {
        match &self.data {
            TileData::Heights { heights, .. } => {
                heights.get(usize::try_from(u64::from(j) * u64::from(self.size) + u64::from(i)).ok()?).copied()
            }
            _ => None,
        }
    }
}

/// Decodes one tile's payload as stored in the archive (`compressed` = the layer's
/// payload compression is still applied; the tile endpoint may already have removed it).
///
/// # Errors
/// [`Error::BadTile`] naming the tile when the payload is not what the layer says.
pub fn decode(layer: &Layer, key: TileKey, payload: &[u8], compressed: bool) -> Result<DecodedTile> {
    let bad = |reason: String| Error::BadTile { key, layer: layer.name.clone(), reason };
    let inflated;
    let bytes = if compressed {
        inflated = payload_bytes(layer, payload, &format!("tile {key}"))?;
        &inflated[..]
    } else {
        payload
    };
    let border = u32::from(layer.border);
    let size = layer.tile_resolution + 2 * border;
    let samples = usize::try_from(u64::from(size) * u64::from(size)).map_err(|_| bad("too large".into()))?;
    let tile = |data| Ok(DecodedTile { key, size, border, data });
    match layer.format {
        TileFormat::Bc1 | TileFormat::Bc7 => {
            let block_bytes = if layer.format == TileFormat::Bc1 { 8 } else { 16 };
            let blocks_per_edge = usize::try_from(size.div_ceil(4)).unwrap_or(usize::MAX);
            let expected = blocks_per_edge * blocks_per_edge * block_bytes;
            if bytes.len() != expected {
                return Err(bad(format!("{} bytes of {:?} blocks, {expected} expected", bytes.len(), layer.format)));
            }
            tile(TileData::Compressed { format: layer.format, blocks: Bytes::copy_from_slice(bytes) })
        }
        TileFormat::MinMaxF32 => Err(bad("a height-range tile is not drawn".into())),
        TileFormat::RawU16 | TileFormat::RawF32 => {
            let width = if layer.format == TileFormat::RawU16 { 2 } else { 4 };
            if bytes.len() != samples * width {
                return Err(bad(format!(
                    "{} bytes, {} expected for {size}x{size} samples",
                    bytes.len(),
                    samples * width
                )));
            }
            let encoding = layer.elevation.unwrap_or(ElevationEncoding {
                scheme: if width == 2 { ElevationScheme::QuantizedU16 } else { ElevationScheme::Float32 },
                scale: 1.0,
                offset: 0.0,
                nodata: None,
            });
            // Samples straight from the payload, no intermediate copy.
            let chunks = bytes.chunks_exact(width);
            tile(if width == 2 {
                heights(&encoding, chunks.map(|c| f64::from(u16::from_le_bytes([c[0], c[1]]))))
            } else {
                heights(&encoding, chunks.map(|c| f64::from(f32::from_le_bytes([c[0], c[1], c[2], c[3]]))))
            })
        }
        TileFormat::Png | TileFormat::Jpeg | TileFormat::Webp => {
            let image = Image::decode(layer.format, bytes).map_err(bad)?;
            if image.width() != size || image.height() != size {
                return Err(bad(format!(
                    "image is {}x{}, the layer's tiles are {size}x{size}",
                    image.width(),
                    image.height()
                )));
            }
            match (layer.kind, layer.elevation) {
                (LayerKind::Elevation | LayerKind::Water, Some(encoding)) => {
                    let values = image.values(encoding.scheme).map_err(bad)?;
                    tile(heights(&encoding, values.into_iter()))
                }
                (LayerKind::Elevation, None) => Err(bad("elevation layer without an encoding".into())),
                _ => tile(TileData::Rgba8(image.rgba8())),
            }
        }
    }
}

/// Raw sample values -> heights (NaN for nodata) with their range.
fn heights(encoding: &ElevationEncoding, values: impl Iterator<Item = f64>) -> TileData {
    let (mut min, mut max) = (f32::INFINITY, f32::NEG_INFINITY);
    let heights = values
        .map(|v| {
            if encoding.nodata == Some(v) || !v.is_finite() {
                return f32::NAN;
            }
            #[expect(clippy::cast_possible_truncation, reason = "heights are stored as f32 on the GPU")]
            let h = encoding.height(v) as f32;
            min = min.min(h);
            max = max.max(h);
            h
        })
        .collect();
    TileData::Heights { heights, min, max, shade: None }
}

#[cfg(test)]
mod tests {
    use terrastream_format::PayloadCompression;

    use super::*;

    fn png(width: u32, colour: png::ColorType, depth: png::BitDepth, data: &[u8]) -> Vec<u8> {
        let mut out = Vec::new();
        let mut encoder = png::Encoder::new(&mut out, width, width);
        encoder.set_color(colour);
        encoder.set_depth(depth);
        encoder.write_header().unwrap().write_image_data(data).unwrap();
        out
    }

    fn layer(kind: LayerKind, format: TileFormat, elevation: Option<ElevationEncoding>) -> Layer {
        Layer {
            name: "l".into(),
            kind,
            format,
            compression: PayloadCompression::None,
            tile_resolution: 2,
            border: 0,
            num_x_tiles: 1,
            num_y_tiles: 1,
            num_lods: 1,
            tile_world_size: 1.0,
            elevation,
            extent: None,
        }
    }

    #[test]
    fn every_elevation_encoding_decodes_to_its_height() {
        let key = TileKey::new(0, 0, 0, 0).unwrap();
        let enc = |scheme, scale, offset| Some(ElevationEncoding { scheme, scale, offset, nodata: None });
        // RGB thirds: 300 of 765 over a 510 m span from 100 m -> 300.0 m.
        let l = layer(LayerKind::Elevation, TileFormat::Png, enc(ElevationScheme::RgbThirds, 510.0, 100.0));
        let t = decode(&l, key, &png(2, png::ColorType::Rgb, png::BitDepth::Eight, &[255, 45, 0].repeat(4)), false);
        assert_eq!(t.unwrap().height(1, 1), Some(300.0));
        // Terrain-RGB: (1, 134, 160) -> -10000 + 100000 * 0.1 = 0 ... 1*65536+134*256+160 = 100000.
        let l = layer(LayerKind::Elevation, TileFormat::Png, enc(ElevationScheme::TerrainRgb, 1.0, 0.0));
        let t = decode(&l, key, &png(2, png::ColorType::Rgb, png::BitDepth::Eight, &[1, 134, 160].repeat(4)), false);
        assert_eq!(t.unwrap().height(0, 0), Some(0.0));
        // Terrarium: (128, 100, 128) -> 32768 + 100 + 0.5 - 32768.
        let l = layer(LayerKind::Elevation, TileFormat::Png, enc(ElevationScheme::Terrarium, 1.0, 0.0));
        let t = decode(&l, key, &png(2, png::ColorType::Rgb, png::BitDepth::Eight, &[128, 100, 128].repeat(4)), false);
        assert_eq!(t.unwrap().height(0, 1), Some(100.5));
        // 16-bit gray PNG, quantized: 1000 * 0.5 - 20.
        let l = layer(LayerKind::Elevation, TileFormat::Png, enc(ElevationScheme::QuantizedU16, 0.5, -20.0));
        let t = decode(&l, key, &png(2, png::ColorType::Grayscale, png::BitDepth::Sixteen, &[3, 232].repeat(4)), false);
        assert_eq!(t.unwrap().height(1, 0), Some(480.0));
        // Raw f32 with nodata, zstd-wrapped.
        let mut l = layer(LayerKind::Elevation, TileFormat::RawF32, enc(ElevationScheme::Float32, 1.0, 0.0));
        l.elevation.as_mut().unwrap().nodata = Some(-9999.0);
        l.compression = PayloadCompression::Zstd;
        let raw: Vec<u8> = [1.5f32, -9999.0, 7.0, 2.0].iter().flat_map(|v| v.to_le_bytes()).collect();
        let t = decode(&l, key, &terrastream_pack::zstd_compress(&raw, 3).unwrap(), true).unwrap();
        assert!(t.height(1, 0).unwrap().is_nan());
        assert!(matches!(t.data, TileData::Heights { min: 1.5, max: 7.0, .. }), "{:?}", t.data);
        assert_eq!((t.height(0, 0), t.height(0, 1)), (Some(1.5), Some(7.0)));
        // Raw u16, gradient-coded (the tiler's default): as stored, and as the tile endpoint
        // sends it (decoded); a frame of the wrong size names the tile.
        let mut l = layer(LayerKind::Elevation, TileFormat::RawU16, enc(ElevationScheme::QuantizedU16, 0.5, -20.0));
        l.compression = PayloadCompression::ZstdGradient;
        let raw: Vec<u8> = [1000u16, 1002, 999, 65_535].iter().flat_map(|v| v.to_le_bytes()).collect();
        let stored = terrastream_pack::zstd_compress_gradient(&raw, 2).unwrap();
        for t in [decode(&l, key, &stored, true).unwrap(), decode(&l, key, &raw, false).unwrap()] {
            assert_eq!((t.height(0, 0), t.height(1, 0), t.height(0, 1)), (Some(480.0), Some(481.0), Some(479.5)));
            assert_eq!(t.height(1, 1), Some(32_747.5));
        }
        let e = decode(&l, key, &terrastream_pack::zstd_compress(&raw[..6], 3).unwrap(), true).unwrap_err();
        assert!(e.to_string().contains("tile layer 0 lod 0 x 0 y 0") && e.to_string().contains("6 bytes"), "{e}");
    }

    #[test]
    fn bad_payloads_name_the_tile() {
        let key = TileKey::new(0, 0, 0, 0).unwrap();
        let l = layer(LayerKind::Texture, TileFormat::Png, None);
        let e = decode(&l, key, b"not a png", false).unwrap_err().to_string();
        assert!(e.contains("tile") && e.contains("PNG"), "{e}");
        let e = decode(&l, key, &png(4, png::ColorType::Rgb, png::BitDepth::Eight, &[0; 48]), false).unwrap_err();
        assert!(e.to_string().contains("4x4"), "{e}");
        let l = layer(LayerKind::Texture, TileFormat::Bc1, None);
        assert!(decode(&l, key, &[0; 7], false).is_err());
        assert!(decode(&l, key, &[0; 8], false).is_ok());
    }

    #[test]
    fn webp_textures_and_terrain_rgb_webp_decode() {
        let key = TileKey::new(0, 0, 0, 0).unwrap();
        let webp = |pixels: &[u8]| {
            let mut out = Vec::new();
            image_webp::WebPEncoder::new(&mut out).encode(pixels, 2, 2, image_webp::ColorType::Rgb8).unwrap();
            out
        };
        let l = layer(LayerKind::Texture, TileFormat::Webp, None);
        let t = decode(&l, key, &webp(&[10, 20, 30].repeat(4)), false).unwrap();
        assert_eq!(t.data, TileData::Rgba8([10, 20, 30, 255].repeat(4)));
        let enc =
            Some(ElevationEncoding { scheme: ElevationScheme::TerrainRgb, scale: 1.0, offset: 0.0, nodata: None });
        let l = layer(LayerKind::Elevation, TileFormat::Webp, enc);
        let t = decode(&l, key, &webp(&[1, 134, 170].repeat(4)), false).unwrap();
        assert_eq!(t.height(1, 1), Some(1.0));
        let e = decode(&l, key, b"RIFF\0\0\0\0WEBPjunk", false).unwrap_err().to_string();
        assert!(e.contains("WebP"), "{e}");
    }

    fn jpeg(width: u16, colour: jpeg_encoder::ColorType, data: &[u8]) -> Vec<u8> {
        let mut out = Vec::new();
        jpeg_encoder::Encoder::new(&mut out, 100).encode(data, width, width, colour).unwrap();
        out
    }

    fn rgba(tile: Result<DecodedTile>) -> Vec<u8> {
        match tile.unwrap().data {
            TileData::Rgba8(p) => p,
            other => panic!("not RGBA: {other:?}"),
        }
    }

    fn close(a: &[u8], b: &[u8]) -> bool {
        a.len() == b.len() && a.iter().zip(b).all(|(x, y)| x.abs_diff(*y) <= 3)
    }

    /// Every colour type the packer accepts decodes, for texture and elevation layers,
    /// and a colour type a scheme cannot read is an error naming the tile, not a panic.
    #[test]
    fn every_colour_type_decodes() {
        use jpeg_encoder::ColorType as J;
        let key = TileKey::new(0, 3, 1, 2).unwrap();
        let mut l = layer(LayerKind::Texture, TileFormat::Jpeg, None);
        l.tile_resolution = 8;
        // One-component (gray) JPEG: once an index out of bounds in the decoder task.
        let t = rgba(decode(&l, key, &jpeg(8, J::Luma, &[100; 64]), false));
        assert!(close(&t, &[100, 100, 100, 255].repeat(64)), "{t:?}");
        // RGB and CMYK JPEGs come out as RGB (CMYK 0,0,0,0 is white; jpeg-encoder writes
        // Adobe's inverted CMYK, as Photoshop does).
        let t = rgba(decode(&l, key, &jpeg(8, J::Rgb, &[200, 40, 10].repeat(64)), false));
        assert!(close(&t, &[200, 40, 10, 255].repeat(64)), "{t:?}");
        let t = rgba(decode(&l, key, &jpeg(8, J::Cmyk, &[0, 0, 0, 0].repeat(64)), false));
        assert!(t.chunks(4).all(|p| p[..3].iter().all(|&c| c > 240) || p[..3].iter().all(|&c| c < 15)), "{t:?}");
        assert!(t.chunks(4).all(|p| p == &t[..4]), "{t:?}");
        // Gray JPEG elevation (gray8): every sample the same height.
        let gray = Some(ElevationEncoding { scheme: ElevationScheme::Gray8, scale: 255.0, offset: 10.0, nodata: None });
        let mut e = layer(LayerKind::Elevation, TileFormat::Jpeg, gray);
        e.tile_resolution = 8;
        let t = decode(&e, key, &jpeg(8, J::Luma, &[100; 64]), false).unwrap();
        let h = t.height(7, 7).unwrap();
        assert!((h - 110.0).abs() <= 2.0, "{h}");
        // A gray JPEG where RGB is needed: an error naming the tile.
        let rgb =
            Some(ElevationEncoding { scheme: ElevationScheme::TerrainRgb, scale: 1.0, offset: 0.0, nodata: None });
        let mut e = layer(LayerKind::Elevation, TileFormat::Jpeg, rgb);
        e.tile_resolution = 8;
        let err = decode(&e, key, &jpeg(8, J::Luma, &[100; 64]), false).unwrap_err().to_string();
        assert!(err.contains("lod 3 x 1 y 2") && err.contains("RGB"), "{err}");
        // PNG: gray + alpha, 16-bit RGBA, 16-bit gray as gray8 elevation (refused: 8-bit only).
        let l = layer(LayerKind::Texture, TileFormat::Png, None);
        let t = rgba(decode(
            &l,
            key,
            &png(2, png::ColorType::GrayscaleAlpha, png::BitDepth::Eight, &[90, 30].repeat(4)),
            false,
        ));
        assert_eq!(t, [90, 90, 90, 30].repeat(4));
        let sixteen = [0x12, 0x34, 0x56, 0x78, 0x9a, 0xbc, 0xff, 0xff].repeat(4);
        let t = rgba(decode(&l, key, &png(2, png::ColorType::Rgba, png::BitDepth::Sixteen, &sixteen), false));
        assert_eq!(t, [0x12, 0x56, 0x9a, 0xff].repeat(4));
        let mut e = layer(LayerKind::Elevation, TileFormat::Png, gray);
        e.tile_resolution = 2;
        let err = decode(&e, key, &png(2, png::ColorType::Grayscale, png::BitDepth::Sixteen, &[1; 8]), false);
        assert!(err.unwrap_err().to_string().contains("8-bit"));
    }

    /// Truncated and bit-flipped payloads of every image format are errors, never panics
    /// (the fuzz target `tiles` does this at scale).
    #[test]
    fn damaged_images_are_errors() {
        use jpeg_encoder::ColorType as J;
        let key = TileKey::new(0, 0, 0, 0).unwrap();
        let mut l = layer(LayerKind::Texture, TileFormat::Jpeg, None);
        l.tile_resolution = 8;
        let good = jpeg(8, J::Luma, &(0..64).collect::<Vec<u8>>());
        for cut in (0..good.len()).step_by(7) {
            let _ = decode(&l, key, &good[..cut], false);
            let mut flipped = good.clone();
            flipped[cut] ^= 0x5a;
            let _ = decode(&l, key, &flipped, false);
        }
        assert!(decode(&l, key, &good[..good.len() / 2], false).is_err());
    }

    #[test]
    fn texture_becomes_rgba() {
        let key = TileKey::new(0, 0, 0, 0).unwrap();
        let l = layer(LayerKind::Texture, TileFormat::Png, None);
        let t = decode(&l, key, &png(2, png::ColorType::Rgb, png::BitDepth::Eight, &[10, 20, 30].repeat(4)), false);
        assert_eq!(t.unwrap().data, TileData::Rgba8([10, 20, 30, 255].repeat(4)));
    }

    #[test]
    fn decoded_tiles_cross_to_another_thread_as_flat_bytes() {
        let key = TileKey::new(2, 3, 5, 7).unwrap();
        let tiles = [
            TileData::Rgba8((0..16u8).collect()),
            TileData::Heights { heights: vec![1.5, f32::NAN, -2.0, 9.25], min: -2.0, max: 9.25, shade: None },
            TileData::Heights {
                heights: vec![1.5, f32::NAN, -2.0, 9.25],
                min: -2.0,
                max: 9.25,
                shade: Some((0..16).collect()),
            },
            TileData::Compressed { format: TileFormat::Bc7, blocks: Bytes::from_static(&[9; 16]) },
            TileData::Compressed { format: TileFormat::Bc1, blocks: Bytes::from_static(&[3; 8]) },
        ];
        for data in tiles {
            let tile = DecodedTile { key, size: 2, border: 1, data };
            let back = DecodedTile::from_wire(&tile.to_wire()).unwrap();
            assert_eq!((back.key, back.size, back.border), (key, 2, 1));
            match (&back.data, &tile.data) {
                (
                    TileData::Heights { heights: a, shade: shade_a, .. },
                    TileData::Heights { heights: b, shade: shade_b, .. },
                ) => {
                    assert!(a.iter().zip(b).all(|(x, y)| x.to_bits() == y.to_bits()));
                    assert_eq!(shade_a, shade_b);
                }
                (a, b) => assert_eq!(a, b),
            }
        }
        let wire = DecodedTile { key, size: 2, border: 0, data: TileData::Rgba8(vec![0; 16]) }.to_wire();
        assert!(DecodedTile::from_wire(&wire[..wire.len() - 1]).is_err(), "a short tile");
        assert!(DecodedTile::from_wire(&wire[..10]).is_err(), "a short head");
    }
}
