//! The common DEM layouts decoded without the `tiff` crate's per-row machinery: strips or
//! tiles of one 8- or 16-bit integer sample (or 8-bit pixels of up to four), or of one
//! 32-bit float, uncompressed or Deflate, with or without the horizontal predictor (and
//! for floats, the floating-point one). That is what GDAL writes for `COMPRESS=DEFLATE
//! PREDICTOR=2` (integers) and `PREDICTOR=3` (floats), the usual ways DEMs are published.
//!
//! Why: undoing a predictor is a running sum. The `tiff` crate adds each sample (each byte,
//! for the floating-point predictor: four a sample) to the one before it in memory (a
//! load, add and store, each waiting for the last store), about 2 ns a sample for
//! integers and more for floats: more than inflating them. Here the sums run in registers
//! as the samples are converted, and the chunk is inflated by one call into its buffer.
//! Anything else (LZW, 32-bit integers, 64-bit, planar ...) goes through the `tiff` crate
//! as before; the two are compared in tests.

use tiff::decoder::DecodingResult;
use tiff::tags::Tag;

use super::tiff::TiffDecoder;

/// Why a strip or tile read directly from the file cannot be decoded.
#[derive(Debug, thiserror::Error)]
#[non_exhaustive]
pub enum ChunkError {
    /// The chunk's index is past the file's offset table.
    #[error("missing from the offset table")]
    NotListed,
    /// Asked for more pixels across than the file stores per row.
    #[error("{width} pixels wide, in rows of {stored}")]
    Wider {
        /// Pixels asked for.
        width: usize,
        /// Pixels per stored row.
        stored: usize,
    },
    /// Larger than a chunk may be.
    #[error("too large")]
    TooLarge,
    /// Reading the chunk's bytes failed.
    #[error("reading {count} bytes at {offset}: {error}")]
    Read {
        /// Bytes asked for.
        count: usize,
        /// Where in the file.
        offset: u64,
        /// The OS error.
        error: std::io::Error,
    },
    /// Fewer bytes stored (or inflated) than the chunk's pixels need.
    #[error("{}{got} bytes, {needed} expected", if *.inflated { "inflates to " } else { "" })]
    Short {
        /// Bytes there are.
        got: usize,
        /// Bytes needed.
        needed: usize,
        /// Whether `got` counts inflated bytes.
        inflated: bool,
    },
    /// The Deflate stream is damaged.
    #[error("Deflate: {0}")]
    Deflate(#[from] flate2::DecompressError),
}

/// Where a chunk's bytes are and how they are coded, read once from the TIFF's tags.
pub(super) struct RawLayout {
    file: std::fs::File,
    offsets: Vec<u64>,
    counts: Vec<u64>,
    deflate: bool,
    /// The horizontal predictor (2): a running sum of samples.
    predictor: bool,
    /// The floating-point predictor (3): a running sum of a row's bytes, laid out most
    /// significant byte of every sample first.
    float_predictor: bool,
    big_endian: bool,
    /// 8 or 16 (integers), 32 (floats).
    bits: u8,
    signed: bool,
    /// Samples a pixel.
    channels: usize,
    /// Samples a row of the chunk as stored (tiles: the padded width).
    stored_width: usize,
}

/// Chunks larger than this (compressed or not) are left to the `tiff` crate's limits.
const MAX_CHUNK_BYTES: u64 = 1 << 30;

impl RawLayout {
    /// The layout of the decoder's image if this module decodes it (read from `file`, a
    /// duplicate of the decoder's file, by positional reads), else None.
    pub(super) fn of(
        file: std::fs::File,
        decoder: &mut TiffDecoder,
        channels: usize,
        tiled: bool,
        chunk_w: usize,
    ) -> Option<Self> {
        if !cfg!(unix) {
            return None;
        }
        let one = |d: &mut TiffDecoder, tag: Tag| d.find_tag_unsigned_vec::<u64>(tag).ok().flatten();
        let all_equal = |v: &[u64]| v.first().filter(|&&f| v.iter().all(|&x| x == f)).copied();
        let scalar = |d: &mut TiffDecoder, tag: Tag, default: u64| match one(d, tag) {
            None => Some(default),
            Some(v) => all_equal(&v),
        };
        let compression = scalar(decoder, Tag::Compression, 1)?;
        let predictor = scalar(decoder, Tag::Predictor, 1)?;
        let bits = scalar(decoder, Tag::BitsPerSample, 1)?;
        let format = scalar(decoder, Tag::SampleFormat, 1)?;
        let spp = scalar(decoder, Tag::SamplesPerPixel, 1)?;
        let planar = scalar(decoder, Tag::PlanarConfiguration, 1)?;
        let photometric = scalar(decoder, Tag::PhotometricInterpretation, 1)?;
        let (offsets, counts) = if tiled {
            (one(decoder, Tag::TileOffsets)?, one(decoder, Tag::TileByteCounts)?)
        } else {
            (one(decoder, Tag::StripOffsets)?, one(decoder, Tag::StripByteCounts)?)
        };
        let deflate = match compression {
            1 => false,
            8 | 32946 => true,
            _ => return None,
        };
        let big_endian = decoder.byte_order() == tiff::tags::ByteOrder::BigEndian;
        let float = format == 3;
        let ok = (if float { matches!(predictor, 1..=3) && bits == 32 } else { matches!(predictor, 1 | 2) })
            && matches!(format, 1..=3)
            && usize::try_from(spp).ok() == Some(channels)
            && (planar == 1 || channels == 1)
            // Gray or RGB(A): no palette, no inverted gray, no YCbCr or CMYK.
            && matches!(photometric, 1 | 2)
            && match bits {
                8 => channels <= 4 && !float,
                16 => channels == 1 && !float,
                32 => channels == 1 && float,
                _ => false,
            }
            && offsets.len() == counts.len();
        if !ok {
            return None;
        }
        // Every chunk inside the file: no buffer is sized by a claim the file cannot back.
        let len = file.metadata().ok()?.len();
        let inside = |(&o, &c): (&u64, &u64)| c <= MAX_CHUNK_BYTES && o.checked_add(c).is_some_and(|end| end <= len);
        if !offsets.iter().zip(&counts).all(inside) {
            return None;
        }
        Some(Self {
            file,
            offsets,
            counts,
            deflate,
            predictor: predictor == 2,
            float_predictor: predictor == 3,
            big_endian,
            bits: u8::try_from(bits).ok()?,
            signed: format == 2,
            channels,
            stored_width: chunk_w,
        })
    }

    /// Chunk `index` of `w` x `h` pixels of data (rows of `stored_width` in the file:
    /// tiles are padded, strips not), decoded as the `tiff` crate decodes it.
    pub(super) fn read(&self, index: usize, w: usize, h: usize) -> Result<DecodingResult, ChunkError> {
        self.with_bytes(index, w, h, |coded, row_bytes| {
            let samples = w * self.channels;
            let rows = coded.chunks(row_bytes).take(h);
            match (self.bits, self.signed) {
                (32, _) => DecodingResult::F32(self.rows32(rows, samples, h)),
                (8, false) => DecodingResult::U8(self.rows8(rows, samples, h)),
                #[expect(clippy::cast_possible_wrap, reason = "two's complement, as stored")]
                (8, true) => DecodingResult::I8(self.rows8(rows, samples, h).into_iter().map(|v| v as i8).collect()),
                (_, false) => DecodingResult::U16(self.rows16(rows, samples, h, |v| v)),
                #[expect(clippy::cast_possible_wrap, reason = "two's complement, as stored")]
                (_, true) => DecodingResult::I16(self.rows16(rows, samples, h, |v| v as i16)),
            }
        })
    }

    /// The same chunk as f32 samples, converted in the predictor's loop (no second pass).
    pub(super) fn read_f32(&self, index: usize, w: usize, h: usize) -> Result<Vec<f32>, ChunkError> {
        self.with_bytes(index, w, h, |coded, row_bytes| {
            let samples = w * self.channels;
            let rows = coded.chunks(row_bytes).take(h);
            match (self.bits, self.signed) {
                (32, _) => self.rows32(rows, samples, h),
                (8, false) => self.rows8(rows, samples, h).into_iter().map(f32::from).collect(),
                #[expect(clippy::cast_possible_wrap, reason = "two's complement, as stored")]
                (8, true) => self.rows8(rows, samples, h).into_iter().map(|v| f32::from(v as i8)).collect(),
                (_, false) => self.rows16(rows, samples, h, f32::from),
                #[expect(clippy::cast_possible_wrap, reason = "two's complement, as stored")]
                (_, true) => self.rows16(rows, samples, h, |v| f32::from(v as i16)),
            }
        })
    }

    /// The same chunk converted into `rows`: the first `w` pixels of each, as many rows as
    /// there are (at most `h`). What a row of tiles is decoded into, in place.
    pub(super) fn read_f32_into(
        &self,
        index: usize,
        w: usize,
        h: usize,
        rows: &mut [&mut [f32]],
    ) -> Result<(), ChunkError> {
        self.with_bytes(index, w, h, |coded, row_bytes| {
            let samples = w * self.channels;
            for (src, dst) in coded.chunks(row_bytes).take(h).zip(rows.iter_mut()) {
                let n = samples.min(dst.len());
                let dst = &mut dst[..n];
                match (self.bits, self.signed) {
                    (32, _) => self.row32(src, samples, dst),
                    (8, signed) => {
                        let bytes = self.rows8(std::iter::once(src), samples, 1);
                        for (d, &v) in dst.iter_mut().zip(&bytes) {
                            #[expect(clippy::cast_possible_wrap, reason = "two's complement, as stored")]
                            let v = if signed { f32::from(v as i8) } else { f32::from(v) };
                            *d = v;
                        }
                    }
                    (_, false) => self.row16(src, dst, &f32::from),
                    #[expect(clippy::cast_possible_wrap, reason = "two's complement, as stored")]
                    (_, true) => self.row16(src, dst, &|v| f32::from(v as i16)),
                }
            }
        })
    }

    /// One row of 16-bit samples as `T`, put into `out`: a loop per byte order and
    /// predictor, so that each compiles to straight-line code.
    fn row16<T>(&self, row: &[u8], out: impl Sink<T>, from_bits: &impl Fn(u16) -> T) {
        match (self.big_endian, self.predictor) {
            (false, true) => out.put(samples16::<false, true>(row).map(from_bits)),
            (false, false) => out.put(samples16::<false, false>(row).map(from_bits)),
            (true, true) => out.put(samples16::<true, true>(row).map(from_bits)),
            (true, false) => out.put(samples16::<true, false>(row).map(from_bits)),
        }
    }

    /// One stored row of 32-bit floats (`row`: all its bytes; a tile's padding included,
    /// which the floating-point predictor's byte planes span), its first `samples` put
    /// into `out`.
    fn row32(&self, row: &[u8], samples: usize, out: impl Sink<f32>) {
        if self.float_predictor {
            return out.put(float_planes(row).take(samples));
        }
        let row = &row[..(4 * samples).min(row.len())];
        match (self.big_endian, self.predictor) {
            (false, true) => out.put(samples32::<false, true>(row)),
            (false, false) => out.put(samples32::<false, false>(row)),
            (true, true) => out.put(samples32::<true, true>(row)),
            (true, false) => out.put(samples32::<true, false>(row)),
        }
    }

    /// 32-bit floats of `h` rows, `samples` a row (rows short of them padded with 0).
    fn rows32<'a>(&self, rows: impl Iterator<Item = &'a [u8]>, samples: usize, h: usize) -> Vec<f32> {
        let mut out = Vec::with_capacity(samples * h);
        for row in rows {
            let before = out.len();
            self.row32(row, samples, &mut out);
            out.resize(before + samples, 0.0);
        }
        out.resize(samples * h, 0.0);
        out
    }

    /// `convert` of the chunk's bytes, inflated: `h` rows of `row_bytes` (its second
    /// argument). The bytes are read and inflated into this thread's buffers, kept from
    /// chunk to chunk: a fresh zeroed buffer for each chunk (the inflater writes into
    /// initialized memory) cost more than the conversion itself.
    fn with_bytes<T>(
        &self,
        index: usize,
        w: usize,
        h: usize,
        convert: impl FnOnce(&[u8], usize) -> T,
    ) -> Result<T, ChunkError> {
        let (offset, count) = match (self.offsets.get(index), self.counts.get(index)) {
            (Some(&o), Some(&c)) => (o, c),
            _ => return Err(ChunkError::NotListed),
        };
        if w > self.stored_width {
            return Err(ChunkError::Wider { width: w, stored: self.stored_width });
        }
        let row_bytes = self.stored_width * self.channels * usize::from(self.bits / 8);
        let needed = row_bytes.checked_mul(h).filter(|&n| n as u64 <= MAX_CHUNK_BYTES).ok_or(ChunkError::TooLarge)?;
        let count = usize::try_from(count).map_err(|_| ChunkError::TooLarge)?;
        SCRATCH.with_borrow_mut(|(raw, out)| {
            let result = (|| {
                let raw = grown(raw, count);
                read_at(&self.file, raw, offset).map_err(|error| ChunkError::Read { count, offset, error })?;
                if !self.deflate {
                    if raw.len() < needed {
                        return Err(ChunkError::Short { got: raw.len(), needed, inflated: false });
                    }
                    return Ok(convert(raw, row_bytes));
                }
                let out = grown(out, needed);
                let mut inflate = flate2::Decompress::new(true);
                inflate.decompress(raw, out, flate2::FlushDecompress::Finish)?;
                let got = usize::try_from(inflate.total_out()).unwrap_or(usize::MAX);
                if got < needed {
                    return Err(ChunkError::Short { got, needed, inflated: true });
                }
                Ok(convert(out, row_bytes))
            })();
            // A huge strip's buffers are not kept past it.
            for buffer in [raw, out] {
                if buffer.len() > SCRATCH_KEPT {
                    *buffer = Vec::new();
                }
            }
            result
        })
    }

    fn rows8<'a>(&self, rows: impl Iterator<Item = &'a [u8]>, samples: usize, h: usize) -> Vec<u8> {
        let mut out = Vec::with_capacity(samples * h);
        for row in rows {
            let row = &row[..samples.min(row.len())];
            if !self.predictor {
                out.extend_from_slice(row);
                continue;
            }
            // One running sum a channel, in registers.
            let mut sum = [0u8; 4];
            let n = self.channels;
            for pixel in row.chunks_exact(n) {
                for (s, &v) in sum.iter_mut().zip(pixel) {
                    *s = s.wrapping_add(v);
                }
                out.extend_from_slice(&sum[..n]);
            }
        }
        out
    }

    /// 16-bit samples as `T` (u16 or i16, from the same bits), the predictor's running sum
    /// in a register: appended by loops of known length (no capacity checks), into a
    /// buffer that is not zeroed first.
    fn rows16<'a, T: Copy + Default>(
        &self,
        rows: impl Iterator<Item = &'a [u8]>,
        samples: usize,
        h: usize,
        from_bits: impl Fn(u16) -> T,
    ) -> Vec<T> {
        let mut out = Vec::with_capacity(samples * h);
        for row in rows {
            self.row16(&row[..(2 * samples).min(row.len())], &mut out, &from_bits);
        }
        out.resize(samples * h, T::default());
        out
    }
}

/// A row's 16-bit samples in one byte order, the predictor's running sum undone in a
/// register.
#[inline(always)]
fn samples16<const BIG: bool, const PREDICT: bool>(row: &[u8]) -> impl Iterator<Item = u16> + '_ {
    let mut sum = 0u16;
    row.chunks_exact(2).map(move |b| {
        let v = if BIG { u16::from_be_bytes([b[0], b[1]]) } else { u16::from_le_bytes([b[0], b[1]]) };
        sum = if PREDICT { sum.wrapping_add(v) } else { v };
        sum
    })
}

/// A row's 32-bit samples (as floats) in one byte order, the horizontal predictor's
/// running sum (of their bits as integers) undone in a register.
#[inline(always)]
fn samples32<const BIG: bool, const PREDICT: bool>(row: &[u8]) -> impl Iterator<Item = f32> + '_ {
    let mut sum = 0u32;
    row.chunks_exact(4).map(move |b| {
        let b = [b[0], b[1], b[2], b[3]];
        let v = if BIG { u32::from_be_bytes(b) } else { u32::from_le_bytes(b) };
        sum = if PREDICT { sum.wrapping_add(v) } else { v };
        f32::from_bits(sum)
    })
}

/// A row coded with the floating-point predictor (TIFF Technical Note 3): its samples'
/// bytes as four planes, most significant first whatever the file's byte order, the whole
/// row then differenced byte by byte. The running sum over the row is four sums at once,
/// one a plane, each started from the total of the planes before it (a sum the compiler
/// vectorizes): four independent chains in registers where one ran through memory.
#[inline(always)]
fn float_planes(row: &[u8]) -> impl Iterator<Item = f32> + '_ {
    let n = row.len() / 4;
    let (p0, rest) = row.split_at(n);
    let (p1, rest) = rest.split_at(n);
    let (p2, p3) = rest.split_at(n);
    let total = |p: &[u8]| p.iter().fold(0u8, |a, &v| a.wrapping_add(v));
    let (t0, t1, t2) = (total(p0), total(p1), total(p2));
    let mut sum = [0, t0, t0.wrapping_add(t1), t0.wrapping_add(t1).wrapping_add(t2)];
    p0.iter().zip(p1).zip(p2).zip(&p3[..n]).map(move |(((&a, &b), &c), &d)| {
        sum = [sum[0].wrapping_add(a), sum[1].wrapping_add(b), sum[2].wrapping_add(c), sum[3].wrapping_add(d)];
        f32::from_bits(u32::from_be_bytes(sum))
    })
}

/// Where a row of converted samples goes: appended to a buffer (not zeroed first), or
/// written over a row of a band.
trait Sink<T> {
    fn put(self, values: impl Iterator<Item = T>);
}

impl<T> Sink<T> for &mut Vec<T> {
    #[inline(always)]
    fn put(self, values: impl Iterator<Item = T>) {
        self.extend(values);
    }
}

impl<T> Sink<T> for &mut [T] {
    #[inline(always)]
    fn put(self, values: impl Iterator<Item = T>) {
        for (d, v) in self.iter_mut().zip(values) {
            *d = v;
        }
    }
}

/// Bytes of scratch a thread keeps between chunks (the compressed and the inflated chunk).
const SCRATCH_KEPT: usize = 8 << 20;

thread_local! {
    static SCRATCH: std::cell::RefCell<(Vec<u8>, Vec<u8>)> = const { std::cell::RefCell::new((Vec::new(), Vec::new())) };
}

/// The first `n` bytes of `buffer`, grown (zeroed) only where it is shorter.
fn grown(buffer: &mut Vec<u8>, n: usize) -> &mut [u8] {
    if buffer.len() < n {
        buffer.resize(n, 0);
    }
    &mut buffer[..n]
}

#[cfg(unix)]
fn read_at(file: &std::fs::File, buf: &mut [u8], offset: u64) -> std::io::Result<()> {
    std::os::unix::fs::FileExt::read_exact_at(file, buf, offset)
}

#[cfg(not(unix))]
fn read_at(_: &std::fs::File, _: &mut [u8], _: u64) -> std::io::Result<()> {
    Err(std::io::Error::other("positioned reads need a unix system"))
}

#[cfg(test)]
mod tests {
    #![allow(clippy::unwrap_used, clippy::cast_possible_truncation)]
    use std::path::Path;
    use std::process::Command;

    use tiff::encoder::{TiffEncoder, colortype};

    use super::super::tiff::{TiffChunks, open_tiff, samples_f32, tiff_rows, tiff_rows_in, tiff_rows_mapped};

    fn gdal_translate(args: &[&str], from: &Path, to: &Path) -> bool {
        match Command::new("gdal_translate").arg("-q").args(args).arg(from).arg(to).status() {
            Ok(s) => {
                assert!(s.success(), "gdal_translate {args:?} failed");
                true
            }
            Err(_) => {
                assert!(std::env::var_os("CI").is_none(), "gdal_translate is not installed (apt-get install gdal-bin)");
                eprintln!("\n*** SKIPPING: gdal_translate is not installed (apt-get install gdal-bin) ***\n");
                false
            }
        }
    }

    /// Every chunk of `path`, decoded here and by the `tiff` crate: the same samples.
    fn same_as_tiff_crate(path: &Path, channels: usize) {
        let chunks = TiffChunks::open(path, channels).unwrap();
        assert!(chunks.raw.is_some(), "{} is not decoded here", path.display());
        let mut decoder = open_tiff(path).unwrap();
        for i in 0..chunks.needed() {
            let (ours, w, h) = chunks.read(i).unwrap();
            let theirs = decoder.read_chunk(i as u32).unwrap();
            assert_eq!((w as u32, h as u32), decoder.chunk_data_dimensions(i as u32), "chunk {i}");
            let theirs = samples_f32(theirs).unwrap();
            assert_eq!(samples_f32(ours).unwrap(), theirs, "{} chunk {i}", path.display());
            assert_eq!(chunks.read_f32(i).unwrap().0, theirs, "{} chunk {i} as f32", path.display());
        }
    }

    /// Every row of `path` as `tiff_rows` reads it (tiles decoded in place, in parallel).
    fn rows_of(path: &Path, channels: usize) -> Vec<f32> {
        let mut all = Vec::new();
        tiff_rows(path, channels, &|_: &mut [f32]| {}, &mut |row| {
            all.extend_from_slice(row);
            Ok(())
        })
        .unwrap();
        all
    }

    #[test]
    fn deflate_and_predictor_chunks_decode_as_the_tiff_crate_decodes_them() {
        let dir = tempfile::tempdir().unwrap();
        // 101 x 77: tiles of 32 x 16 leave cut-off tiles at the right and the bottom.
        let (w, h) = (101u32, 77u32);
        let base = dir.path().join("base.tif");
        let mut encoder = TiffEncoder::new(std::fs::File::create(&base).unwrap()).unwrap();
        let heights: Vec<i16> =
            (0..w * h).map(|i| ((i % w) as i16 * 37 - (i / w) as i16 * 91) ^ (i as i16).wrapping_mul(7)).collect();
        encoder.write_image::<colortype::GrayI16>(w, h, &heights).unwrap();
        let rgb_base = dir.path().join("rgb.tif");
        let mut encoder = TiffEncoder::new(std::fs::File::create(&rgb_base).unwrap()).unwrap();
        let pixels: Vec<u8> = (0..w * h * 3).map(|i| (i.wrapping_mul(2_654_435_761) >> 13) as u8).collect();
        encoder.write_image::<colortype::RGB8>(w, h, &pixels).unwrap();
        // 32 x 16 tiles, Deflate with the horizontal predictor: what DEMs are published as.
        const TILED_DEFLATE: &[&str] = &[
            "-co",
            "TILED=YES",
            "-co",
            "BLOCKXSIZE=32",
            "-co",
            "BLOCKYSIZE=16",
            "-co",
            "COMPRESS=DEFLATE",
            "-co",
            "PREDICTOR=2",
        ];
        let cases: [(&Path, &[&str], usize); 9] = [
            (&base, TILED_DEFLATE, 1),
            (&base, &["-co", "TILED=YES", "-co", "BLOCKXSIZE=32", "-co", "BLOCKYSIZE=16"], 1),
            (&base, &["-co", "BLOCKYSIZE=7", "-co", "COMPRESS=DEFLATE", "-co", "PREDICTOR=2"], 1),
            (
                &base,
                &["-co", "BLOCKYSIZE=7", "-co", "COMPRESS=DEFLATE", "-co", "PREDICTOR=2", "-co", "ENDIANNESS=BIG"],
                1,
            ),
            (&base, &["-ot", "UInt16", "-co", "COMPRESS=DEFLATE", "-co", "ZLEVEL=1"], 1),
            (&base, &["-ot", "Byte", "-scale", "-co", "TILED=YES", "-co", "COMPRESS=DEFLATE", "-co", "PREDICTOR=2"], 1),
            (&rgb_base, TILED_DEFLATE, 3),
            (&rgb_base, &["-co", "BLOCKYSIZE=5", "-co", "PREDICTOR=2", "-co", "COMPRESS=DEFLATE"], 3),
            // Tiled LZW: left to the `tiff` crate, its rows assembled the same way.
            (&base, &["-co", "TILED=YES", "-co", "BLOCKXSIZE=32", "-co", "BLOCKYSIZE=16", "-co", "COMPRESS=LZW"], 1),
        ];
        // 32-bit floats with fractions (every fourth a multiple of 5, which the ranges'
        // check makes no data), GDAL's floating-point predictor among them.
        let float_base = dir.path().join("float.tif");
        let mut encoder = TiffEncoder::new(std::fs::File::create(&float_base).unwrap()).unwrap();
        let floats: Vec<f32> = (0..w * h)
            .map(|i| {
                let (x, y) = ((i % w) as f32, (i / w) as f32);
                if i % 4 == 0 { 5.0 * (x - y) } else { x * 1.37 - y * 3.11 + 1e-3 * (i as f32).sin() - 8848.86 }
            })
            .collect();
        encoder.write_image::<colortype::Gray32Float>(w, h, &floats).unwrap();
        // Creation options, each after a `-co`.
        let co = |options: &[&'static str]| -> Vec<&'static str> { options.iter().flat_map(|o| ["-co", *o]).collect() };
        let float_cases = [
            co(&["TILED=YES", "BLOCKXSIZE=32", "BLOCKYSIZE=16", "COMPRESS=DEFLATE", "PREDICTOR=3"]),
            // (Big-endian with the floating-point predictor is left out: the libtiff of
            // Debian's GDAL 3.6 writes it swapped, and reads back other numbers than it
            // was given; every decoder agrees on those.)
            co(&["BLOCKYSIZE=7", "COMPRESS=DEFLATE", "PREDICTOR=3"]),
            co(&["BLOCKYSIZE=7", "COMPRESS=DEFLATE", "PREDICTOR=2"]),
            co(&["BLOCKYSIZE=7", "COMPRESS=DEFLATE", "PREDICTOR=2", "ENDIANNESS=BIG"]),
            co(&["TILED=YES", "BLOCKXSIZE=32", "BLOCKYSIZE=16", "COMPRESS=DEFLATE"]),
            co(&["TILED=YES", "BLOCKXSIZE=32", "BLOCKYSIZE=16", "ENDIANNESS=BIG"]),
        ];
        let cases = cases.into_iter().chain(float_cases.iter().map(|args| (float_base.as_path(), args.as_slice(), 1)));
        for (k, (from, args, channels)) in cases.enumerate() {
            let to = dir.path().join(format!("case{k}.tif"));
            if !gdal_translate(args, from, &to) {
                return;
            }
            if !args.contains(&"COMPRESS=LZW") {
                same_as_tiff_crate(&to, channels);
            }
            // Its rows, against those of the same samples in plain strips.
            let plain = dir.path().join(format!("plain{k}.tif"));
            assert!(gdal_translate(&["-co", "TILED=NO", "-co", "COMPRESS=NONE"], &to, &plain));
            let rows = rows_of(&to, channels);
            assert_eq!(rows.len(), (w * h) as usize * channels, "case {k}");
            assert!(rows == rows_of(&plain, channels), "case {k}: rows differ from the plain file's");
            if channels == 1 {
                rows_come_with_their_ranges(&to, k);
            }
        }
    }

    /// `tiff_rows_mapped` of `path` (some samples made no data where they are decoded, a
    /// window of rows): without a map, the rows `tiff_rows_in` gives, each with its own
    /// lowest and highest height; with one, each row as it maps it.
    fn rows_come_with_their_ranges(path: &Path, case: usize) {
        let prepare = |s: &mut [f32]| s.iter_mut().filter(|v| v.rem_euclid(5.0) == 0.0).for_each(|v| *v = f32::NAN);
        for wanted in [0..usize::MAX, 3..40] {
            let (mut rows, mut ranged) = (Vec::new(), Vec::new());
            tiff_rows_in(path, 1, wanted.clone(), &prepare, &mut |row| {
                rows.push(row.to_vec());
                Ok(())
            })
            .unwrap();
            tiff_rows_mapped(path, wanted.clone(), &prepare, None, &mut |row, range| {
                ranged.push((row, range));
                Ok(())
            })
            .unwrap();
            // Mapped where decoded (a resampling: here, every other sample), handed over.
            let map = |r: &[f32]| r.iter().step_by(2).copied().collect::<Vec<f32>>();
            let mut mapped = Vec::new();
            tiff_rows_mapped(path, wanted.clone(), &prepare, Some(&map), &mut |row, range| {
                mapped.push((row, range));
                Ok(())
            })
            .unwrap();
            assert_eq!(mapped.len(), rows.len(), "case {case}, rows {wanted:?} mapped");
            for (j, (row, (m, range))) in rows.iter().zip(&mapped).enumerate() {
                assert!(map(row).iter().zip(m).all(|(a, b)| a.to_bits() == b.to_bits()), "case {case}, row {j} mapped");
                assert_eq!(*range, crate::min_max(row), "case {case}, row {j}: the source row's range");
            }
            assert_eq!(rows.len(), ranged.len(), "case {case}, rows {wanted:?}");
            for (j, (row, (same, range))) in rows.iter().zip(&ranged).enumerate() {
                assert!(row.iter().zip(same).all(|(a, b)| a.to_bits() == b.to_bits()), "case {case}, row {j}");
                assert!(row.iter().any(|v| v.is_nan()), "case {case}, row {j}: the test wants no data in it");
                assert_eq!(*range, crate::min_max(row), "case {case}, row {j}");
            }
        }
    }

    #[test]
    fn a_damaged_chunk_is_an_error_naming_it() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("dem.tif");
        let mut encoder = TiffEncoder::new(std::fs::File::create(&path).unwrap())
            .unwrap()
            .with_compression(tiff::encoder::Compression::Deflate(tiff::encoder::DeflateLevel::Balanced))
            .with_predictor(tiff::tags::Predictor::Horizontal);
        let mut image = encoder.new_image::<colortype::GrayI16>(64, 64).unwrap();
        image.rows_per_strip(16).unwrap();
        image.write_data(&(0..64 * 64).map(|i| (i % 300) as i16).collect::<Vec<_>>()).unwrap();
        let good = TiffChunks::open(&path, 1).unwrap();
        assert!(good.raw.is_some());
        assert_eq!(good.read_f32(1).unwrap().0.len(), 64 * 16);
        // Overwrite the middle of the file (the strips' compressed bytes) with junk.
        let mut bytes = std::fs::read(&path).unwrap();
        let n = bytes.len();
        for b in &mut bytes[n / 4..n / 2] {
            *b = 0x5a;
        }
        std::fs::write(&path, &bytes).unwrap();
        let chunks = TiffChunks::open(&path, 1).unwrap();
        let failed =
            (0..chunks.needed()).filter_map(|i| chunks.read_f32(i).err()).map(|e| e.to_string()).collect::<Vec<_>>();
        assert!(!failed.is_empty(), "junk decoded without an error");
        assert!(failed.iter().all(|e| e.contains("dem.tif") && e.contains("reading strip")), "{failed:?}");
    }
}
