//! Sequential JPEGs (baseline and extended, Huffman-coded, 8-bit) decoded a row of MCUs at a
//! time: how a JPEG too large to decode whole is read, in the memory of one row of MCUs
//! whatever its height. Progressive, lossless, arithmetic-coded and CMYK JPEGs are not
//! read here (their error says so). Chroma is upsampled by replication and converted as
//! libjpeg converts it; the IDCT is a separable float one, so pixels may differ from
//! another decoder's by a level or two (tested against zune-jpeg).

use std::io::Read;
use std::path::Path;

use super::image::ycbcr_to_rgb;
use crate::error::{Error, Result};

/// What is wrong with a JPEG that is not read by rows: damaged data, or a kind of JPEG
/// (progressive, lossless, arithmetic-coded, 12-bit, CMYK) this decoder does not read.
#[derive(Debug, thiserror::Error)]
#[non_exhaustive]
pub enum JpegError {
    /// Reading the file failed.
    #[error("{0}")]
    Io(#[from] std::io::Error),
    /// The data contradicts the format (what was found, in words).
    #[error("{0}")]
    Damaged(&'static str),
    /// The entropy-coded data ends before the image does.
    #[error("the data ends early, at marker {0:#04x}")]
    EndsEarly(u8),
    /// A marker other than RST where a restart interval ends.
    #[error("marker {0:#04x} where a restart was due")]
    NoRestart(u8),
    /// Samples of another precision than 8 bits.
    #[error("{0}-bit samples (8 are read)")]
    Precision(u8),
    /// A frame of other than one or three components, or of no pixels.
    #[error("{components} components in a {width}x{height} frame (1 or 3 are read)")]
    Frame {
        /// Components in the frame.
        components: usize,
        /// Pixels across.
        width: usize,
        /// Pixels down.
        height: usize,
    },
    /// A coding this decoder does not read (what, in words).
    #[error("{0}")]
    Unsupported(&'static str),
    /// The row consumer stopped the decoding (its own error is what is returned).
    #[error("stopped by the consumer of rows")]
    Stopped,
}

type Decoded<T = ()> = std::result::Result<T, JpegError>;

/// Coefficient order in the stream: ZIGZAG[k] is the k-th coefficient's index (row-major).
const ZIGZAG: [u8; 64] = [
    0, 1, 8, 16, 9, 2, 3, 10, 17, 24, 32, 25, 18, 11, 4, 5, 12, 19, 26, 33, 40, 48, 41, 34, 27, 20, 13, 6, 7, 14, 21,
    28, 35, 42, 49, 56, 57, 50, 43, 36, 29, 22, 15, 23, 30, 37, 44, 51, 58, 59, 52, 45, 38, 31, 39, 46, 53, 60, 61, 54,
    47, 55, 62, 63,
];

/// Bits a code may take through the lookup table at once.
const FAST_BITS: u32 = 9;

/// A Huffman table: a lookup of the first [`FAST_BITS`] bits, and the canonical code's
/// bounds per length for longer codes (JPEG F.2.2.3).
struct Huffman {
    /// (code length, value) for each `FAST_BITS`-bit prefix; length 0: a longer code.
    fast: Vec<(u8, u8)>,
    /// Largest code of each length (-1: none), lengths 1..=16.
    max_code: [i32; 17],
    /// Index into `values` of each length's first code, less that code.
    offset: [i32; 17],
    values: Vec<u8>,
}

impl Huffman {
    fn new(counts: &[u8; 16], values: Vec<u8>) -> Decoded<Self> {
        let total: usize = counts.iter().map(|&c| usize::from(c)).sum();
        if total > values.len() || total > 256 {
            return Err(JpegError::Damaged("a Huffman table lists more codes than values"));
        }
        let (mut fast, mut max_code, mut offset) = (vec![(0u8, 0u8); 1 << FAST_BITS], [-1i32; 17], [0i32; 17]);
        let (mut code, mut k) = (0i32, 0usize);
        for (len, &count) in (1u8..=16).zip(counts) {
            let slot = usize::from(len);
            offset[slot] = i32::try_from(k).map_err(|_| JpegError::Damaged("too many codes"))? - code;
            for _ in 0..count {
                if u32::from(len) <= FAST_BITS {
                    let shift = FAST_BITS - u32::from(len);
                    let first = usize::try_from(code).map_err(|_| JpegError::Damaged("a negative code"))? << shift;
                    for entry in fast.iter_mut().skip(first).take(1 << shift) {
                        *entry = (len, values[k]);
                    }
                }
                code += 1;
                k += 1;
            }
            if count > 0 {
                max_code[slot] = code - 1;
            }
            if code > 1 << len {
                return Err(JpegError::Damaged("a Huffman table's codes do not fit their lengths"));
            }
            code <<= 1;
        }
        Ok(Self { fast, max_code, offset, values })
    }
}

/// The entropy-coded bits of a scan, read from a file through a buffer; a marker ends them
/// (zeros are read past it) until a restart takes it.
struct Bits<R: Read> {
    src: R,
    buffer: Vec<u8>,
    at: usize,
    len: usize,
    acc: u64,
    count: u32,
    marker: Option<u8>,
    /// Zero bytes read past `marker`: a scan that runs on past its data is damaged.
    past: usize,
}

impl<R: Read> Bits<R> {
    fn new(src: R) -> Self {
        Self { src, buffer: vec![0; 1 << 16], at: 0, len: 0, acc: 0, count: 0, marker: None, past: 0 }
    }

    fn byte(&mut self) -> Decoded<u8> {
        if self.at == self.len {
            self.len = self.src.read(&mut self.buffer)?;
            self.at = 0;
            if self.len == 0 {
                return Err(JpegError::Damaged("the file ends inside the image"));
            }
        }
        self.at += 1;
        Ok(self.buffer[self.at - 1])
    }

    fn u16(&mut self) -> Decoded<u16> {
        Ok(u16::from_be_bytes([self.byte()?, self.byte()?]))
    }

    /// A marker segment's payload (its length read first).
    fn segment(&mut self) -> Decoded<Vec<u8>> {
        let len =
            usize::from(self.u16()?).checked_sub(2).ok_or(JpegError::Damaged("a segment shorter than its length"))?;
        let mut segment = vec![0u8; len];
        for b in &mut segment {
            *b = self.byte()?;
        }
        Ok(segment)
    }

    /// The next marker (after any fill bytes), outside entropy-coded data.
    fn next_marker(&mut self) -> Decoded<u8> {
        if let Some(m) = self.marker.take() {
            return Ok(m);
        }
        loop {
            if self.byte()? != 0xFF {
                continue;
            }
            let mut m = self.byte()?;
            while m == 0xFF {
                m = self.byte()?;
            }
            if m != 0 {
                return Ok(m);
            }
        }
    }

    fn fill(&mut self) -> Decoded<()> {
        while self.count <= 56 {
            let mut b = 0u8;
            if self.marker.is_some() {
                // A few bytes of look-ahead past a restart marker are normal; more: the
                // data ends before the image does.
                self.past += 1;
                if self.past > 512 {
                    return Err(JpegError::EndsEarly(self.marker.unwrap_or(0)));
                }
            } else {
                b = self.byte()?;
                if b == 0xFF {
                    let mut next = self.byte()?;
                    while next == 0xFF {
                        next = self.byte()?;
                    }
                    if next != 0 {
                        self.marker = Some(next);
                        b = 0;
                    }
                }
            }
            self.acc |= u64::from(b) << (56 - self.count);
            self.count += 8;
        }
        Ok(())
    }

    fn bits(&mut self, n: u32) -> Decoded<u32> {
        if n == 0 {
            return Ok(0);
        }
        if self.count < n {
            self.fill()?;
        }
        #[expect(clippy::cast_possible_truncation, reason = "n is at most 16 bits")]
        let v = (self.acc >> (64 - n)) as u32;
        self.acc <<= n;
        self.count -= n;
        Ok(v)
    }

    fn decode(&mut self, table: &Huffman) -> Decoded<u8> {
        if self.count < 16 {
            self.fill()?;
        }
        let (len, value) = table.fast[(self.acc >> (64 - FAST_BITS)) as usize];
        if len > 0 {
            self.acc <<= len;
            self.count -= u32::from(len);
            return Ok(value);
        }
        let mut code = self.bits(FAST_BITS)? as i32;
        for len in FAST_BITS as usize + 1..=16 {
            code = (code << 1) | self.bits(1)? as i32;
            if code <= table.max_code[len] {
                let i =
                    usize::try_from(table.offset[len] + code).map_err(|_| JpegError::Damaged("bad Huffman code"))?;
                return table.values.get(i).copied().ok_or(JpegError::Damaged("bad Huffman code"));
            }
        }
        Err(JpegError::Damaged("a Huffman code no table holds"))
    }

    /// `s` bits as a signed value (JPEG's EXTEND).
    fn signed(&mut self, s: u8) -> Decoded<i32> {
        if s == 0 {
            return Ok(0);
        }
        if s > 16 {
            return Err(JpegError::Damaged("a coefficient of more than 16 bits"));
        }
        let v = self.bits(u32::from(s))? as i32;
        Ok(if v < 1 << (s - 1) { v - (1 << s) + 1 } else { v })
    }

    /// At a restart interval's end: the bits left dropped, the RST marker taken.
    fn restart(&mut self) -> Decoded<()> {
        (self.acc, self.count, self.past) = (0, 0, 0);
        match self.next_marker()? {
            0xD0..=0xD7 => Ok(()),
            m => Err(JpegError::NoRestart(m)),
        }
    }
}

struct Component {
    id: u8,
    h: usize,
    v: usize,
    quant: usize,
    dc: usize,
    ac: usize,
    predictor: i32,
    /// One row of MCUs of this component's samples.
    plane: Vec<u8>,
    stride: usize,
}

/// Calls `row` with each row of RGB pixels (3 bytes a pixel) of the sequential JPEG at
/// `path`, top to bottom, decoding a row of MCUs at a time: what the tiler reads a JPEG too
/// large to decode whole with.
///
/// # Errors
/// [`Error::Jpeg`] naming the file: not a JPEG this reads (progressive, lossless,
/// arithmetic-coded, 12-bit, CMYK), damaged data; `row`'s errors.
pub fn jpeg_rows(path: &Path, row: &mut dyn FnMut(&[u8]) -> Result<()>) -> Result<()> {
    let file = std::fs::File::open(path).map_err(|e| Error::file(path, e))?;
    let mut failed = None;
    let result = decode(file, &mut |r| {
        row(r).map_err(|e| {
            failed = Some(e);
            JpegError::Stopped
        })
    });
    match (result, failed) {
        (_, Some(e)) => Err(e),
        (Err(error), None) => Err(Error::Jpeg { path: path.to_owned(), error }),
        (Ok(()), None) => Ok(()),
    }
}

/// Whether [`jpeg_rows`] reads the JPEG at `path`: a sequential Huffman frame of 8-bit
/// samples, one or three components.
///
/// # Errors
/// [`Error::Jpeg`] naming the file if its headers cannot be read.
pub(super) fn reads_by_rows(path: &Path) -> Result<bool> {
    let file = std::fs::File::open(path).map_err(|e| Error::file(path, e))?;
    let mut bits = Bits::new(std::io::BufReader::with_capacity(1 << 12, file));
    let mut frame = || -> Decoded<bool> {
        start_of_image(&mut bits)?;
        loop {
            match bits.next_marker()? {
                0x01 | 0xD0..=0xD7 => {}
                0xD9 | 0xDA => return Ok(false),
                marker => {
                    let segment = bits.segment()?;
                    match marker {
                        0xC0 | 0xC1 => return Ok(segment.first() == Some(&8) && matches!(segment.get(5), Some(1 | 3))),
                        m if unread_frame(m) => return Ok(false),
                        _ => {}
                    }
                }
            }
        }
    };
    frame().map_err(|error| Error::Jpeg { path: path.to_owned(), error })
}

/// A frame marker of a kind this does not read: progressive, lossless, hierarchical or
/// arithmetic-coded.
fn unread_frame(marker: u8) -> bool {
    matches!(marker, 0xC2 | 0xC3 | 0xC5..=0xC7 | 0xC9..=0xCB | 0xCD..=0xCF)
}

fn start_of_image(bits: &mut Bits<impl Read>) -> Decoded {
    if bits.byte()? != 0xFF || bits.byte()? != 0xD8 {
        return Err(JpegError::Damaged("no start-of-image marker"));
    }
    Ok(())
}

fn decode(file: impl Read, row: &mut dyn FnMut(&[u8]) -> Decoded) -> Decoded {
    let mut bits = Bits::new(file);
    start_of_image(&mut bits)?;
    let mut frame = Frame::read(&mut bits)?;
    frame.decode(&mut bits, row)
}

/// Byte `i` of a marker segment.
fn at(segment: &[u8], i: usize) -> Decoded<u8> {
    segment.get(i).copied().ok_or(JpegError::Damaged("a segment cut short"))
}

/// What the headers up to the scan say: the frame, its tables, the restart interval.
struct Frame {
    width: usize,
    height: usize,
    components: Vec<Component>,
    quant: [[f32; 64]; 4],
    dc: [Option<Huffman>; 4],
    ac: [Option<Huffman>; 4],
    /// MCUs between restart markers (0: none).
    interval: usize,
    /// Three components stored as RGB (Adobe's transform 0), not YCbCr.
    rgb: bool,
}

impl Frame {
    /// Reads the markers up to and with the (one) scan's header.
    fn read(bits: &mut Bits<impl Read>) -> Decoded<Self> {
        let mut frame = Self {
            width: 0,
            height: 0,
            components: Vec::new(),
            quant: [[0f32; 64]; 4],
            dc: [None, None, None, None],
            ac: [None, None, None, None],
            interval: 0,
            rgb: false,
        };
        loop {
            let marker = bits.next_marker()?;
            if matches!(marker, 0x01 | 0xD0..=0xD7) {
                continue;
            }
            if marker == 0xD9 {
                return Err(JpegError::Damaged("the image ends before its scan"));
            }
            let segment = bits.segment()?;
            match marker {
                0xC0 | 0xC1 => frame.start_of_frame(&segment)?,
                m if unread_frame(m) => {
                    return Err(JpegError::Unsupported(
                        "progressive, lossless or arithmetic-coded (only sequential Huffman JPEGs are read by rows)",
                    ));
                }
                0xC4 => frame.huffman_tables(&segment)?,
                0xDB => frame.quantization_tables(&segment)?,
                0xDD => frame.interval = usize::from(u16::from_be_bytes([at(&segment, 0)?, at(&segment, 1)?])),
                // Adobe's segment: transform 0 with three components is RGB, not YCbCr.
                0xEE if segment.starts_with(b"Adobe") => frame.rgb = at(&segment, 11)? == 0,
                0xDA => {
                    frame.start_of_scan(&segment)?;
                    return Ok(frame);
                }
                _ => {}
            }
        }
    }

    fn start_of_frame(&mut self, segment: &[u8]) -> Decoded {
        let at = |i| at(segment, i);
        if at(0)? != 8 {
            return Err(JpegError::Precision(at(0)?));
        }
        self.height = usize::from(u16::from_be_bytes([at(1)?, at(2)?]));
        self.width = usize::from(u16::from_be_bytes([at(3)?, at(4)?]));
        let n = usize::from(at(5)?);
        if !matches!(n, 1 | 3) || self.width == 0 || self.height == 0 {
            return Err(JpegError::Frame { components: n, width: self.width, height: self.height });
        }
        for c in 0..n {
            let (h, v) = (usize::from(at(7 + 3 * c)? >> 4), usize::from(at(7 + 3 * c)? & 15));
            if !(1..=4).contains(&h) || !(1..=4).contains(&v) {
                return Err(JpegError::Damaged("a sampling factor outside 1..4"));
            }
            let quant = usize::from(at(8 + 3 * c)? & 3);
            self.components.push(Component {
                id: at(6 + 3 * c)?,
                h,
                v,
                quant,
                dc: 0,
                ac: 0,
                predictor: 0,
                plane: Vec::new(),
                stride: 0,
            });
        }
        Ok(())
    }

    fn huffman_tables(&mut self, segment: &[u8]) -> Decoded {
        let mut i = 0;
        while i < segment.len() {
            let class = at(segment, i)?;
            let mut counts = [0u8; 16];
            for (k, c) in counts.iter_mut().enumerate() {
                *c = at(segment, i + 1 + k)?;
            }
            let total: usize = counts.iter().map(|&c| usize::from(c)).sum();
            let values = segment.get(i + 17..i + 17 + total).ok_or(JpegError::Damaged("a Huffman table cut short"))?;
            let table = Some(Huffman::new(&counts, values.to_vec())?);
            let slot = usize::from(class & 3);
            if class >> 4 == 0 {
                self.dc[slot] = table
            } else {
                self.ac[slot] = table
            }
            i += 17 + total;
        }
        Ok(())
    }

    fn quantization_tables(&mut self, segment: &[u8]) -> Decoded {
        let mut i = 0;
        while i < segment.len() {
            let (precision, slot) = (at(segment, i)? >> 4, usize::from(at(segment, i)? & 3));
            for (k, &z) in ZIGZAG.iter().enumerate() {
                let q = if precision == 0 {
                    u16::from(at(segment, i + 1 + k)?)
                } else {
                    u16::from_be_bytes([at(segment, i + 1 + 2 * k)?, at(segment, i + 2 + 2 * k)?])
                };
                self.quant[slot][usize::from(z)] = f32::from(q);
            }
            i += 1 + 64 * (1 + usize::from(precision != 0));
        }
        Ok(())
    }

    fn start_of_scan(&mut self, segment: &[u8]) -> Decoded {
        if self.components.is_empty() {
            return Err(JpegError::Damaged("a scan before the frame"));
        }
        let n = usize::from(at(segment, 0)?);
        if n != self.components.len() {
            return Err(JpegError::Unsupported("a scan of some components only (one scan of all is read by rows)"));
        }
        for k in 0..n {
            let (id, tables) = (at(segment, 1 + 2 * k)?, at(segment, 2 + 2 * k)?);
            let c = self
                .components
                .iter_mut()
                .find(|c| c.id == id)
                .ok_or(JpegError::Damaged("a scan of an unknown component"))?;
            (c.dc, c.ac) = (usize::from(tables >> 4 & 3), usize::from(tables & 3));
        }
        // One component alone is not interleaved: its blocks are its MCUs.
        if let [only] = self.components.as_mut_slice() {
            (only.h, only.v) = (1, 1);
        }
        Ok(())
    }

    /// Largest sampling factors across and down: an MCU is 8 times these in pixels.
    fn max_sampling(&self) -> (usize, usize) {
        (self.components.iter().map(|c| c.h).max().unwrap_or(1), self.components.iter().map(|c| c.v).max().unwrap_or(1))
    }

    /// Decodes the scan a row of MCUs at a time, calling `row` with each row of pixels.
    fn decode(&mut self, bits: &mut Bits<impl Read>, row: &mut dyn FnMut(&[u8]) -> Decoded) -> Decoded {
        let (hmax, vmax) = self.max_sampling();
        let (mcu_w, mcu_h) = (8 * hmax, 8 * vmax);
        let (mcus_x, mcus_y) = (self.width.div_ceil(mcu_w), self.height.div_ceil(mcu_h));
        for c in &mut self.components {
            c.stride = mcus_x * c.h * 8;
            c.plane = vec![0; c.stride * c.v * 8];
        }
        let mut out = vec![0u8; self.width * 3];
        // Per component, the column of its plane under each pixel (replicated chroma).
        let columns: Vec<Vec<usize>> =
            self.components.iter().map(|c| (0..self.width).map(|x| x * c.h / hmax).collect()).collect();
        let mut done = 0usize;
        for my in 0..mcus_y {
            for mx in 0..mcus_x {
                if self.interval > 0 && done > 0 && done.is_multiple_of(self.interval) {
                    bits.restart()?;
                    self.components.iter_mut().for_each(|c| c.predictor = 0);
                }
                done += 1;
                self.decode_mcu(bits, mx)?;
            }
            for ly in 0..mcu_h.min(self.height - my * mcu_h) {
                self.pixels(ly, vmax, &columns, &mut out);
                row(&out)?;
            }
        }
        Ok(())
    }

    /// The blocks of MCU `mx` of the current row, each component's into its plane.
    fn decode_mcu(&mut self, bits: &mut Bits<impl Read>, mx: usize) -> Decoded {
        for c in &mut self.components {
            let (dc_table, ac_table) = (
                self.dc[c.dc].as_ref().ok_or(JpegError::Damaged("a scan's DC table is missing"))?,
                self.ac[c.ac].as_ref().ok_or(JpegError::Damaged("a scan's AC table is missing"))?,
            );
            let q = &self.quant[c.quant];
            for by in 0..c.v {
                for bx in 0..c.h {
                    let coefficients = block(bits, c, dc_table, ac_table, q)?;
                    let x0 = (mx * c.h + bx) * 8;
                    let y0 = by * 8;
                    idct(&coefficients, &mut c.plane[y0 * c.stride + x0..], c.stride);
                }
            }
        }
        Ok(())
    }

    /// Line `ly` of the MCU row as RGB pixels: each component's sample under each pixel
    /// (replicated).
    fn pixels(&self, ly: usize, vmax: usize, columns: &[Vec<usize>], out: &mut [u8]) {
        // Each component's line under this row of pixels.
        let line = |k: usize| {
            let c = &self.components[k];
            let at = (ly * c.v / vmax) * c.stride;
            (&c.plane[at..at + c.stride], &columns[k][..])
        };
        match self.components.len() {
            1 => {
                let (plane, cols) = line(0);
                for (px, &col) in out.chunks_exact_mut(3).zip(cols) {
                    px.fill(plane[col]);
                }
            }
            3 => {
                let [(p0, c0), (p1, c1), (p2, c2)] = [line(0), line(1), line(2)];
                for (x, px) in out.chunks_exact_mut(3).enumerate() {
                    let samples = [p0[c0[x]], p1[c1[x]], p2[c2[x]]];
                    px.copy_from_slice(&if self.rgb { samples } else { ycbcr_to_rgb(samples) });
                }
            }
            _ => out.fill(0),
        }
    }
}

/// One 8x8 block of component `c`, dequantized, in row-major order.
fn block(
    bits: &mut Bits<impl Read>,
    c: &mut Component,
    dc: &Huffman,
    ac: &Huffman,
    q: &[f32; 64],
) -> Decoded<[f32; 64]> {
    let mut coefficients = [0f32; 64];
    let s = bits.decode(dc)?;
    c.predictor += bits.signed(s)?;
    #[expect(clippy::cast_precision_loss, reason = "DC values fit 16 bits")]
    let dc_value = c.predictor as f32;
    coefficients[0] = dc_value * q[0];
    let mut k = 1;
    while k < 64 {
        let rs = bits.decode(ac)?;
        let (run, size) = (usize::from(rs >> 4), rs & 15);
        if size == 0 {
            if run != 15 {
                break;
            }
            k += 16;
            continue;
        }
        k += run;
        let Some(&z) = ZIGZAG.get(k) else { return Err(JpegError::Damaged("a coefficient past the 64th")) };
        #[expect(clippy::cast_precision_loss, reason = "coefficients fit 16 bits")]
        let v = bits.signed(size)? as f32;
        coefficients[usize::from(z)] = v * q[usize::from(z)];
        k += 1;
    }
    Ok(coefficients)
}

/// The 8x8 inverse DCT of `f` (row-major, dequantized) into `out` (rows `stride` apart),
/// level-shifted, rounded (half up: truncating a value clamped to be positive, where
/// `round` would call the C library for every sample) and clamped to 0..=255.
fn idct(f: &[f32; 64], out: &mut [u8], stride: usize) {
    use std::sync::OnceLock;
    static TABLE: OnceLock<[[f32; 8]; 8]> = OnceLock::new();
    let cos = TABLE.get_or_init(|| {
        let mut t = [[0f32; 8]; 8];
        for (x, row) in t.iter_mut().enumerate() {
            for (u, v) in row.iter_mut().enumerate() {
                let c = if u == 0 { std::f64::consts::FRAC_1_SQRT_2 } else { 1.0 };
                #[expect(clippy::cast_precision_loss, clippy::cast_possible_truncation, reason = "small indices; f32")]
                let value = (c * 0.5 * ((2 * x + 1) as f64 * u as f64 * std::f64::consts::PI / 16.0).cos()) as f32;
                *v = value;
            }
        }
        t
    });
    // Rows first (skipped where all but the DC term are zero), then columns.
    let mut tmp = [0f32; 64];
    for v in 0..8 {
        let r = &f[v * 8..v * 8 + 8];
        if r[1..].iter().all(|&a| a == 0.0) {
            let dc = r[0] * cos[0][0];
            tmp[v * 8..v * 8 + 8].fill(dc);
            continue;
        }
        for x in 0..8 {
            tmp[v * 8 + x] = (0..8).map(|u| cos[x][u] * r[u]).sum();
        }
    }
    for (y, cos_y) in cos.iter().enumerate() {
        let Some(line) = out.get_mut(y * stride..y * stride + 8) else { return };
        for (x, o) in line.iter_mut().enumerate() {
            let s: f32 = (0..8).map(|v| cos_y[v] * tmp[v * 8 + x]).sum();
            #[expect(clippy::cast_possible_truncation, clippy::cast_sign_loss, reason = "clamped to 0..=255")]
            let value = (s + 128.5).clamp(0.0, 255.0) as u8;
            *o = value;
        }
    }
}

#[cfg(test)]
mod tests {
    #![allow(clippy::unwrap_used, clippy::cast_possible_truncation, clippy::cast_precision_loss)]
    use std::path::Path;

    use jpeg_encoder::{ColorType, Encoder, SamplingFactor};

    use super::jpeg_rows;
    use crate::jpeg::decode_jpeg;

    /// A smooth gradient with a sharp-edged square and some texture: what orthophotos hold.
    fn picture(w: u16, h: u16) -> Vec<u8> {
        let (w, h) = (usize::from(w), usize::from(h));
        let mut rgb = Vec::with_capacity(w * h * 3);
        for y in 0..h {
            for x in 0..w {
                let edge = (w / 4..w / 2).contains(&x) && (h / 3..h / 2).contains(&y);
                let t = ((x * 13 + y * 7) % 23) as u8;
                rgb.extend([(x * 255 / w) as u8 / 2 + t, (y * 255 / h) as u8, if edge { 230 } else { 40 + t }]);
            }
        }
        rgb
    }

    /// `pixels` as a JPEG at `path`, the encoder set up by `setup`.
    fn write(
        path: &Path,
        pixels: &[u8],
        (w, h): (u16, u16),
        colour: ColorType,
        setup: impl FnOnce(&mut Encoder<&mut Vec<u8>>),
    ) {
        let mut bytes = Vec::new();
        let mut encoder = Encoder::new(&mut bytes, 90);
        setup(&mut encoder);
        encoder.encode(pixels, w, h, colour).unwrap();
        std::fs::write(path, bytes).unwrap();
    }

    fn ours(path: &Path) -> Vec<u8> {
        let mut all = Vec::new();
        jpeg_rows(path, &mut |row| {
            all.extend_from_slice(row);
            Ok(())
        })
        .unwrap();
        all
    }

    #[test]
    fn sequential_jpegs_read_by_rows_match_a_whole_decoder() {
        let dir = tempfile::tempdir().unwrap();
        // Odd sizes (MCUs cut off at the right and bottom), every usual subsampling, with
        // and without restart intervals, gray, and Adobe RGB.
        let cases = [
            (203, 77, SamplingFactor::F_2_2, 0, ColorType::Rgb),
            (203, 77, SamplingFactor::F_2_1, 3, ColorType::Rgb),
            (96, 131, SamplingFactor::F_1_1, 0, ColorType::Rgb),
            (96, 131, SamplingFactor::F_1_2, 7, ColorType::Rgb),
            (150, 45, SamplingFactor::F_2_2, 1, ColorType::Rgb),
            (131, 70, SamplingFactor::F_1_1, 2, ColorType::Luma),
        ];
        for (k, (w, h, sampling, restart, colour)) in cases.into_iter().enumerate() {
            let path = dir.path().join(format!("case{k}.jpg"));
            let rgb = picture(w, h);
            let pixels: Vec<u8> =
                if colour == ColorType::Luma { rgb.chunks_exact(3).map(|p| p[1]).collect() } else { rgb };
            write(&path, &pixels, (w, h), colour, |e| {
                e.set_sampling_factor(sampling);
                e.set_restart_interval(restart);
            });
            let (_, _, theirs) = decode_jpeg(&path).unwrap();
            let ours = ours(&path);
            assert_eq!(ours.len(), theirs.len(), "case {k}");
            let diffs: Vec<u32> = ours.iter().zip(&theirs).map(|(&a, &b)| u32::from(a.abs_diff(b))).collect();
            let mean = diffs.iter().sum::<u32>() as f64 / diffs.len() as f64;
            let max = diffs.iter().copied().max().unwrap();
            // Luma is decoded at full resolution by both: within rounding.
            let luma = |p: &[u8]| 0.299 * f64::from(p[0]) + 0.587 * f64::from(p[1]) + 0.114 * f64::from(p[2]);
            let luma_max = ours.chunks_exact(3).zip(theirs.chunks_exact(3)).map(|(a, b)| (luma(a) - luma(b)).abs());
            let luma_max = luma_max.fold(0.0, f64::max);
            if sampling == SamplingFactor::F_1_1 {
                assert!(mean < 0.1 && max <= 3, "case {k}: mean {mean:.3}, max {max}");
            } else {
                // Chroma replicated here, interpolated there: apart at sharp colour edges.
                assert!(
                    mean < 2.5 && max <= 90 && luma_max < 3.0,
                    "case {k}: mean {mean:.3}, max {max}, luma {luma_max:.1}"
                );
            }
        }
    }

    #[test]
    fn unread_kinds_and_damage_are_errors_naming_the_file() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("progressive.jpg");
        write(&path, &picture(64, 64), (64, 64), ColorType::Rgb, |e| e.set_progressive(true));
        let err = jpeg_rows(&path, &mut |_| Ok(())).unwrap_err().to_string();
        assert!(err.contains("progressive.jpg") && err.contains("progressive"), "{err}");
        assert!(!super::reads_by_rows(&path).unwrap(), "a progressive JPEG is not read by rows");

        let good = dir.path().join("good.jpg");
        write(&good, &picture(64, 64), (64, 64), ColorType::Rgb, |_| {});
        assert!(super::reads_by_rows(&good).unwrap(), "a baseline JPEG is read by rows");
        let bytes = std::fs::read(&good).unwrap();
        // Cut short, and every prefix: an error or rows, never a panic.
        let cut = dir.path().join("cut.jpg");
        for len in (0..bytes.len()).step_by(97) {
            std::fs::write(&cut, &bytes[..len]).unwrap();
            let err = jpeg_rows(&cut, &mut |_| Ok(())).unwrap_err().to_string();
            assert!(err.contains("cut.jpg"), "{err}");
        }
        // A row's own error comes back as it was.
        let err = jpeg_rows(&good, &mut |_| Err(crate::error::Error::damaged("elsewhere", "stop"))).unwrap_err();
        assert!(err.to_string().starts_with("elsewhere"), "{err}");
    }
}
