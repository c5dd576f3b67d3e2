//! Comparing a rendered image with a committed reference in `tests/golden/`.
//! `TERRASTREAM_BLESS=1` (re)writes the reference; a missing one fails.

use std::path::{Path, PathBuf};

/// How far an image may be from its reference.
#[derive(Clone, Copy, Debug)]
pub struct Tolerance {
    /// Largest mean absolute channel difference (of 255).
    pub mean: f64,
    /// A pixel is "off" when a channel differs by more than this (of 255).
    pub pixel: u8,
    /// Largest share of pixels off.
    pub off_share: f64,
}

/// The repository's root (this crate lives in `tests/kit`).
pub fn repo() -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR")).join("../..").canonicalize().unwrap()
}

pub fn write_png(path: &Path, width: u32, height: u32, rgba: &[u8]) {
    let file = std::io::BufWriter::new(std::fs::File::create(path).unwrap());
    let mut encoder = png::Encoder::new(file, width, height);
    encoder.set_color(png::ColorType::Rgba);
    encoder.set_depth(png::BitDepth::Eight);
    let mut writer = encoder.write_header().unwrap();
    writer.write_image_data(rgba).unwrap();
    writer.finish().unwrap();
}

/// Decodes a PNG to RGBA8: (width, height, pixels).
pub fn decode_png(bytes: &[u8]) -> (u32, u32, Vec<u8>) {
    let mut decoder = png::Decoder::new(std::io::Cursor::new(bytes));
    decoder.set_transformations(png::Transformations::EXPAND | png::Transformations::ALPHA);
    let mut reader = decoder.read_info().unwrap();
    let mut buf = vec![0; reader.output_buffer_size().unwrap()];
    let info = reader.next_frame(&mut buf).unwrap();
    buf.truncate(info.buffer_size());
    let rgba = match info.color_type {
        png::ColorType::Rgba => buf,
        png::ColorType::GrayscaleAlpha => buf.chunks_exact(2).flat_map(|p| [p[0], p[0], p[0], p[1]]).collect(),
        other => panic!("unexpected PNG colour type {other:?}"),
    };
    (info.width, info.height, rgba)
}

/// Compares `rgba` with `tests/golden/{name}.png`; the image is also written to
/// `target/render-tests/{name}.png` to look at.
pub fn assert_golden(name: &str, width: u32, height: u32, rgba: &[u8], tolerance: Tolerance) {
    let out = repo().join("target/render-tests");
    std::fs::create_dir_all(&out).unwrap();
    write_png(&out.join(format!("{name}.png")), width, height, rgba);
    let golden = repo().join(format!("tests/golden/{name}.png"));
    if std::env::var_os("TERRASTREAM_BLESS").is_some() {
        write_png(&golden, width, height, rgba);
        eprintln!("blessed {}", golden.display());
        return;
    }
    assert!(golden.exists(), "no reference image {} (TERRASTREAM_BLESS=1 writes it)", golden.display());
    let (w, h, reference) = decode_png(&std::fs::read(&golden).unwrap());
    assert_eq!((w, h), (width, height), "{name}: size differs from the reference");
    let (mean, off) = difference(rgba, &reference, tolerance.pixel);
    let pixels = (w * h) as usize;
    assert!(
        mean <= tolerance.mean && off as f64 <= tolerance.off_share * pixels as f64,
        "{name}: mean difference {mean:.3}/255, {off} of {pixels} pixels off by > {}/255 \
         (allowed: mean {}, {:.2} % off); see target/render-tests/{name}.png",
        tolerance.pixel,
        tolerance.mean,
        tolerance.off_share * 100.0
    );
}

/// Mean absolute channel difference of two RGBA8 images of one size (of 255), and how
/// many pixels differ by more than `pixel` in a channel.
pub fn difference(a: &[u8], b: &[u8], pixel: u8) -> (f64, usize) {
    assert_eq!(a.len(), b.len(), "images of different sizes");
    let mut sum = 0u64;
    let mut off = 0usize;
    for (a, b) in a.chunks_exact(4).zip(b.chunks_exact(4)) {
        let d = [0, 1, 2].map(|c| a[c].abs_diff(b[c]));
        sum += d.iter().map(|&x| u64::from(x)).sum::<u64>();
        if d.iter().any(|&x| x > pixel) {
            off += 1;
        }
    }
    (sum as f64 / (a.len() / 4 * 3).max(1) as f64, off)
}
