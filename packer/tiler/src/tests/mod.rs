//! Unit tests of the tiler, by concept; the fixtures they share are here.

#![allow(clippy::unwrap_used, clippy::cast_possible_truncation, clippy::cast_sign_loss, clippy::cast_precision_loss)]

use std::path::{Path, PathBuf};

use terrastream_format::{ElevationEncoding, ElevationScheme, LayerKind, Reader, TileFormat, TileKey};
use terrastream_pack::progress::Silent;

use super::*;
use crate::pyramid::*;
use terrastream_raster::min_max;

mod encodings;
mod inputs;
mod pyramid;
mod ranges;
mod textures;

fn raster(width: u32, height: u32, f: impl Fn(u32, u32) -> f32) -> Raster {
    let data = (0..height).flat_map(|y| (0..width).map(move |x| (x, y))).map(|(x, y)| f(x, y)).collect();
    Raster { width, height, data, spacing: (30.0, 30.0), georeference: None }
}

fn repo_data(name: &str) -> PathBuf {
    // The 320-sample crop is the built-in demo DEM, kept beside the built-in sample.
    let folder = if name == "srtm-tamalpais-320-public-domain.tif" { "../pack/data" } else { "../../tests/data" };
    Path::new(env!("CARGO_MANIFEST_DIR")).join(folder).join(name)
}

fn png_file(path: &Path, width: u32, height: u32, rgba: &[u8]) {
    png_with(path, width, height, png::ColorType::Rgba, png::BitDepth::Eight, rgba);
}

fn png_with(path: &Path, width: u32, height: u32, colour: png::ColorType, depth: png::BitDepth, data: &[u8]) {
    let file = std::io::BufWriter::new(std::fs::File::create(path).unwrap());
    let mut encoder = png::Encoder::new(file, width, height);
    encoder.set_color(colour);
    encoder.set_depth(depth);
    encoder.write_header().unwrap().write_image_data(data).unwrap();
}

fn decode_png(bytes: &[u8]) -> (u32, Vec<u8>) {
    let mut decoder = png::Decoder::new(std::io::Cursor::new(bytes));
    decoder.set_transformations(png::Transformations::EXPAND | png::Transformations::ALPHA);
    let mut reader = decoder.read_info().unwrap();
    let mut buf = vec![0; reader.output_buffer_size().unwrap()];
    let info = reader.next_frame(&mut buf).unwrap();
    buf.truncate(info.buffer_size());
    (info.width, buf)
}

/// A 64x64 texture: (x*4, y*4, x+y, 255), transparent where x, y >= 48.
fn texture_pixels() -> Vec<u8> {
    (0..64u32)
        .flat_map(|y| (0..64u32).map(move |x| (x, y)))
        .flat_map(|(x, y)| if x >= 48 && y >= 48 { [0; 4] } else { [(x * 4) as u8, (y * 4) as u8, (x + y) as u8, 255] })
        .collect()
}

fn texture(source: &dyn ImageSource, tile_size: u32, format: TextureFormat) -> TextureInput<'_> {
    TextureInput { source, tile_size, format, pixel_size: 1.0 }
}

/// Heights of an elevation tile (NaN for nodata), decoded as a client would.
fn heights(reader: &Reader<terrastream_format::MmapSource>, key: TileKey) -> Option<Vec<f64>> {
    let layer = &reader.metadata().layers[usize::from(key.layer())];
    let enc = layer.elevation.unwrap();
    let stored = reader.tile(key).unwrap()?;
    let raw = terrastream_format::payload_bytes(layer, &stored, "tile").unwrap();
    Some(if layer.format == TileFormat::RawF32 {
        raw.chunks_exact(4).map(|c| f64::from(f32::from_le_bytes([c[0], c[1], c[2], c[3]]))).collect()
    } else {
        raw.chunks_exact(2)
            .map(|c| u16::from_le_bytes([c[0], c[1]]))
            .map(|q| if q == 0 { f64::NAN } else { enc.height(f64::from(q)) })
            .collect()
    })
}

/// A GeoTIFF in EPSG:4326 with the north-west corner at `origin` and `pixel` degrees per
/// pixel: f32 heights (`rgb` = None) or RGB pixels.
fn geotiff(path: &Path, (width, height): (u32, u32), origin: [f64; 2], pixel: f64, rgb: Option<&[u8]>) {
    use tiff::encoder::{TiffEncoder, colortype};
    use tiff::tags::Tag;
    let file = std::fs::File::create(path).unwrap();
    let mut encoder = TiffEncoder::new(file).unwrap();
    let tag = |image: &mut tiff::encoder::DirectoryEncoder<'_, _, _>| {
        image.write_tag(Tag::Unknown(33550), &[pixel, pixel, 0.0][..]).unwrap();
        image.write_tag(Tag::Unknown(33922), &[0.0, 0.0, 0.0, origin[0], origin[1], 0.0][..]).unwrap();
        image.write_tag(Tag::Unknown(34735), &[1u16, 1, 0, 2, 1024, 0, 1, 2, 2048, 0, 1, 4326][..]).unwrap();
    };
    match rgb {
        Some(pixels) => {
            let mut image = encoder.new_image::<colortype::RGB8>(width, height).unwrap();
            tag(image.encoder());
            image.write_data(pixels).unwrap();
        }
        None => {
            let mut image = encoder.new_image::<colortype::Gray32Float>(width, height).unwrap();
            tag(image.encoder());
            let heights: Vec<f32> = (0..width * height).map(|i| (i % 97) as f32).collect();
            image.write_data(&heights).unwrap();
        }
    }
}

/// The committed SRTM crops: Deflate strips with ocean nodata, LZW float32 tiles (clipped
/// at the edges), Deflate int16 strips.
const SRTM_FIXTURES: [&str; 3] = [
    "srtm-tamalpais-320-public-domain.tif",
    "srtm-tamalpais-150x100-tiled-float32-public-domain.tif",
    "srtm-tamalpais-150x100-strips-int16-public-domain.tif",
];
