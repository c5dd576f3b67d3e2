//! TIFF strips and tiles, read and decoded in parallel, as rows of samples.

use std::path::Path;

use super::rawchunk::RawLayout;
use crate::error::{Error, Result};

pub(super) const PLANAR_CONFIGURATION: u16 = 284;

pub(super) type TiffDecoder = tiff::decoder::Decoder<std::io::BufReader<std::fs::File>>;

pub(super) fn open_tiff(path: &Path) -> Result<TiffDecoder> {
    let file = std::fs::File::open(path).map_err(|e| Error::file(path, e))?;
    tiff_decoder(path, file)
}

/// A decoder of `file`, opened from `path`.
fn tiff_decoder(path: &Path, file: std::fs::File) -> Result<TiffDecoder> {
    use tiff::decoder::{Decoder, Limits};
    let mut limits = Limits::default();
    // One chunk (a strip or a tile) is decoded at a time: allow big ones, not the image.
    limits.decoding_buffer_size = 1 << 30;
    limits.intermediate_buffer_size = 1 << 30;
    Ok(Decoder::new(std::io::BufReader::new(file))
        .map_err(|e| Error::tiff(path, "not a readable TIFF: ", e))?
        .with_limits(limits))
}

/// [`open_tiff`] of a raster given as input, once its strips or tiles are checked to lie
/// inside the file: a truncated file (a download or copy cut short) is then an error
/// naming it when it is opened, which `--skip-bad-inputs` can leave out, not a failed
/// read when the run reaches its end, perhaps an hour in.
pub(super) fn open_input_tiff(path: &Path) -> Result<TiffDecoder> {
    use tiff::decoder::ChunkType;
    use tiff::tags::Tag;
    let mut decoder = open_tiff(path)?;
    let len = std::fs::metadata(path).map_err(|e| Error::file(path, e))?.len();
    let (what, offsets, counts) = match decoder.get_chunk_type() {
        ChunkType::Tile => ("tile", Tag::TileOffsets, Tag::TileByteCounts),
        ChunkType::Strip => ("strip", Tag::StripOffsets, Tag::StripByteCounts),
    };
    let mut table = |tag: Tag| decoder.find_tag_unsigned_vec::<u64>(tag).ok().flatten().unwrap_or_default();
    let (offsets, counts) = (table(offsets), table(counts));
    let outside = offsets.iter().zip(&counts).position(|(&o, &c)| o.checked_add(c).is_none_or(|end| end > len));
    if let Some(i) = outside {
        return Err(Error::damaged(
            path,
            format!(
                "{what} {i} lies past the end of the file ({} bytes at {}, the file has {len}): is it truncated?",
                counts[i], offsets[i]
            ),
        ));
    }
    Ok(decoder)
}

/// Bytes of samples decoded per batch of strips (at least two strips a thread).
const STRIP_BATCH_BYTES: usize = 1 << 20;

/// A TIFF's strips or tiles, read and decoded by any thread: each read takes a spare
/// decoder (or opens one) and gives it back, so that chunks decode in parallel.
pub(super) struct TiffChunks<'p> {
    path: &'p Path,
    /// Decoders not in use.
    spare: std::sync::Mutex<Vec<TiffDecoder>>,
    pub(super) kind: tiff::decoder::ChunkType,
    count: usize,
    /// Samples per pixel.
    channels: usize,
    pub(super) width: usize,
    pub(super) height: usize,
    pub(super) chunk_w: usize,
    pub(super) chunk_h: usize,
    /// Set where [`RawLayout`] decodes the chunks instead of the `tiff` crate.
    pub(super) raw: Option<RawLayout>,
}

impl<'p> TiffChunks<'p> {
    pub(super) fn open(path: &'p Path, channels: usize) -> Result<Self> {
        use tiff::decoder::ChunkType;
        let bad = |why: String| Error::damaged(path, why);
        // One open file for the decoder and the raw reader (positional reads): thousands
        // of inputs are opened again and again as bands read them.
        let file = std::fs::File::open(path).map_err(|e| Error::file(path, e))?;
        let mut decoder = tiff_decoder(path, file.try_clone().map_err(|e| Error::file(path, e))?)?;
        let (width, height) = decoder.dimensions().map_err(|e| Error::tiff(path, "", e))?;
        let (chunk_w, chunk_h) = decoder.chunk_dimensions();
        if chunk_w == 0 || chunk_h == 0 {
            return Err(bad("zero-size strips or tiles".into()));
        }
        let kind = decoder.get_chunk_type();
        let count = match kind {
            ChunkType::Strip => decoder.strip_count(),
            ChunkType::Tile => decoder.tile_count(),
        }
        .map_err(|e| Error::tiff(path, format!("{}s: ", Self::name(kind)), e))? as usize;
        let raw = RawLayout::of(file, &mut decoder, channels, kind == ChunkType::Tile, chunk_w as usize);
        Ok(Self {
            raw,
            path,
            spare: std::sync::Mutex::new(vec![decoder]),
            kind,
            count,
            channels,
            width: width as usize,
            height: height as usize,
            chunk_w: chunk_w as usize,
            chunk_h: chunk_h as usize,
        })
    }

    fn name(kind: tiff::decoder::ChunkType) -> &'static str {
        if kind == tiff::decoder::ChunkType::Strip { "strip" } else { "tile" }
    }

    /// Strips decoded at a time: about [`STRIP_BATCH_BYTES`] of samples, at least two a
    /// thread.
    pub(super) fn batch(&self) -> usize {
        let strip_bytes = (self.width * self.channels * self.chunk_h * 4).max(1);
        (STRIP_BATCH_BYTES / strip_bytes).max(2 * rayon::current_num_threads())
    }

    /// Chunks across the raster: one strip, or a row of tiles.
    pub(super) fn across(&self) -> usize {
        if self.kind == tiff::decoder::ChunkType::Strip { 1 } else { self.width.div_ceil(self.chunk_w) }
    }

    /// The chunks the raster needs.
    pub(super) fn needed(&self) -> usize {
        self.height.div_ceil(self.chunk_h) * self.across()
    }

    /// Rows of the raster read once chunks `..end` (in file order) are.
    pub(super) fn rows_before(&self, end: usize) -> u32 {
        u32::try_from((end / self.across().max(1) * self.chunk_h).min(self.height)).unwrap_or(u32::MAX)
    }

    /// Chunk `index` as f32 samples, and the pixels across and down it holds.
    pub(super) fn read_f32(&self, index: usize) -> Result<(Vec<f32>, usize, usize)> {
        if let Some(raw) = self.raw.as_ref().filter(|_| index < self.count) {
            let (w, h) = self.data_size(index);
            let what = Self::name(self.kind);
            let values = raw.read_f32(index, w, h).map_err(|error| Error::Chunk {
                path: self.path.to_owned(),
                what,
                index,
                error,
            })?;
            return Ok((values, w, h));
        }
        let (data, w, h) = self.read(index)?;
        let values = samples_f32(data).ok_or_else(|| Error::unsupported(self.path, "unsupported sample type"))?;
        Ok((values, w, h))
    }

    /// Chunk `index` converted into `rows` (each at least the chunk's width in samples, as
    /// the raster cuts it off), as many rows as there are; the rows the chunk holds.
    pub(super) fn read_f32_into(&self, index: usize, rows: &mut [&mut [f32]]) -> Result<usize> {
        if let Some(raw) = self.raw.as_ref().filter(|_| index < self.count) {
            let (w, h) = self.data_size(index);
            let what = Self::name(self.kind);
            raw.read_f32_into(index, w, h, rows).map_err(|error| Error::Chunk {
                path: self.path.to_owned(),
                what,
                index,
                error,
            })?;
            return Ok(h);
        }
        let (values, w, h) = self.read_f32(index)?;
        for (dst, src) in rows.iter_mut().zip(values.chunks_exact((w * self.channels).max(1))).take(h) {
            let n = dst.len().min(src.len());
            dst[..n].copy_from_slice(&src[..n]);
        }
        Ok(h)
    }

    /// The pixels across and down chunk `index` holds (the raster's, where it is cut off).
    fn data_size(&self, index: usize) -> (usize, usize) {
        let across = self.across().max(1);
        let (cx, cy) = (index % across, index / across);
        let w = self.chunk_w.min(self.width.saturating_sub(cx * self.chunk_w));
        (
            if self.kind == tiff::decoder::ChunkType::Strip { self.width } else { w },
            self.chunk_h.min(self.height.saturating_sub(cy * self.chunk_h)),
        )
    }

    /// Chunk `index` decoded, and the pixels across and down it holds.
    pub(super) fn read(&self, index: usize) -> Result<(tiff::decoder::DecodingResult, usize, usize)> {
        let what = Self::name(self.kind);
        let bad = |why: String| Error::damaged(self.path, why);
        let i = u32::try_from(index).map_err(|_| bad("too many chunks".into()))?;
        if index >= self.count {
            return Err(bad(format!("{what} {index} is missing (the file lists {})", self.count)));
        }
        if let Some(raw) = &self.raw {
            let (w, h) = self.data_size(index);
            let data = raw.read(index, w, h).map_err(|error| Error::Chunk {
                path: self.path.to_owned(),
                what,
                index,
                error,
            })?;
            return Ok((data, w, h));
        }
        let spare = self.spare.lock().unwrap_or_else(std::sync::PoisonError::into_inner).pop();
        let mut decoder = match spare {
            Some(d) => d,
            None => open_tiff(self.path)?,
        };
        let (w, h) = decoder.chunk_data_dimensions(i);
        let data = decoder.read_chunk(i).map_err(|e| Error::tiff(self.path, format!("reading {what} {index}: "), e));
        self.spare.lock().unwrap_or_else(std::sync::PoisonError::into_inner).push(decoder);
        let data = data?;
        let (w, h) = (w as usize, h as usize);
        let (held, expected) = (samples_in(&data), w * h * self.channels);
        if held < expected {
            return Err(bad(format!("{what} {index}: {held} samples, {expected} expected")));
        }
        Ok((data, w, h))
    }
}

/// How many samples a decoded chunk holds.
fn samples_in(data: &tiff::decoder::DecodingResult) -> usize {
    use tiff::decoder::DecodingResult as D;
    match data {
        D::U8(v) => v.len(),
        D::I8(v) => v.len(),
        D::U16(v) => v.len(),
        D::I16(v) => v.len(),
        D::U32(v) => v.len(),
        D::I32(v) => v.len(),
        D::U64(v) => v.len(),
        D::I64(v) => v.len(),
        D::F32(v) => v.len(),
        D::F64(v) => v.len(),
        _ => 0,
    }
}

/// Calls `row` with each row of a TIFF's samples (`channels` per pixel), in order, after
/// `prepare` has seen them (in the decoding threads: a conversion in place). Strips
/// (a batch of about [`STRIP_BATCH_BYTES`]) or tiles (a row of them, each straight into
/// its columns of the rows) are read and decoded in parallel, each thread with a decoder
/// of its own, so decompression (LZW, Deflate) and conversion use every core; memory is
/// one batch of strips, or a row of tiles (and a tile per thread where the `tiff` crate
/// decodes them). Samples are f32: exact for 8- and 16-bit values, and heights are kept
/// as f32 anyway.
pub(super) fn tiff_rows(
    path: &Path,
    channels: usize,
    prepare: &(dyn Fn(&mut [f32]) + Sync),
    row: &mut dyn FnMut(&[f32]) -> Result<()>,
) -> Result<()> {
    tiff_rows_in(path, channels, 0..usize::MAX, prepare, row)
}

/// [`tiff_rows`] for rows `wanted` only: the strips or tiles above are not read.
pub(super) fn tiff_rows_in(
    path: &Path,
    channels: usize,
    wanted: std::ops::Range<usize>,
    prepare: &(dyn Fn(&mut [f32]) + Sync),
    row: &mut dyn FnMut(&[f32]) -> Result<()>,
) -> Result<()> {
    rows_of_chunks(path, channels, wanted, prepare, false, None, &mut |r, _, _| row(r))
}

/// [`tiff_rows_in`] of heights, each row handed over as `map` makes it from the row (as it
/// is, without one), with the row's lowest and highest height (infinities reversed for
/// none): both found where the rows are decoded, in parallel, so the thread that hands
/// the rows on does not read them again.
pub(super) fn tiff_rows_mapped(
    path: &Path,
    wanted: std::ops::Range<usize>,
    prepare: &(dyn Fn(&mut [f32]) + Sync),
    map: Option<&crate::RowMap<'_>>,
    row: &mut crate::MappedRow<'_>,
) -> Result<()> {
    rows_of_chunks(path, 1, wanted, prepare, true, map, &mut |r, mapped, range| {
        row(mapped.unwrap_or_else(|| r.to_vec()), range.unwrap_or_else(|| crate::min_max(r)))
    })
}

/// A row of [`rows_of_chunks`], as `map` made it where asked, with its range where asked.
type ChunkRow<'a> = dyn FnMut(&[f32], Option<Vec<f32>>, Option<(f32, f32)>) -> Result<()> + 'a;

/// [`tiff_rows_in`], with each row's range (`ranged`; else None) and `map` of it (where
/// given; else None), both found on the pool.
fn rows_of_chunks(
    path: &Path,
    channels: usize,
    wanted: std::ops::Range<usize>,
    prepare: &(dyn Fn(&mut [f32]) + Sync),
    ranged: bool,
    map: Option<&crate::RowMap<'_>>,
    row: &mut ChunkRow<'_>,
) -> Result<()> {
    use rayon::prelude::*;
    use tiff::decoder::ChunkType;
    let bad = |why: String| Error::damaged(path, why);
    let chunks = TiffChunks::open(path, channels)?;
    let (width, height, kind) = (chunks.width, chunks.height, chunks.kind);
    let stride = width * channels;
    let (chunk_w, chunk_h) = (chunks.chunk_w, chunks.chunk_h);
    // A strip's samples, its rows' ranges (where `ranged`) and maps (where `map`), width
    // and rows.
    type Strip = (Vec<f32>, Vec<(f32, f32)>, Vec<Vec<f32>>, usize, usize);
    let chunk = |index: usize| -> Result<Strip> {
        let (mut values, w, h) = chunks.read_f32(index)?;
        prepare(&mut values);
        let ranges = if ranged { values.chunks_exact(stride).map(crate::min_max).collect() } else { Vec::new() };
        let mapped = map.map_or_else(Vec::new, |m| values.chunks_exact(stride).take(h).map(m).collect());
        Ok((values, ranges, mapped, w, h))
    };
    // Chunks `range`, decoded in parallel; the first failure in file order is the error.
    let decode = |range: std::ops::Range<usize>| -> Result<Vec<Strip>> {
        range.into_par_iter().map(chunk).collect::<Vec<_>>().into_iter().collect()
    };
    match kind {
        ChunkType::Strip => {
            let strips = height.div_ceil(chunk_h).min(wanted.end.div_ceil(chunk_h));
            let batch = chunks.batch();
            let start = (wanted.start / chunk_h).min(strips);
            let mut y = start * chunk_h;
            for first in (start..strips).step_by(batch) {
                for (values, ranges, mapped, _, h) in decode(first..strips.min(first + batch))? {
                    let mut mapped = mapped.into_iter();
                    for (k, r) in values.chunks_exact(stride).take(h.min(height - y)).enumerate() {
                        let m = mapped.next();
                        if wanted.contains(&(y + k)) {
                            row(r, m, ranges.get(k).copied())?;
                        }
                    }
                    y += h;
                }
            }
            if y < height.min(wanted.end) {
                return Err(bad(format!("strips hold {y} of {height} rows")));
            }
        }
        ChunkType::Tile => {
            let across = chunks.across();
            let tile_rows = height.div_ceil(chunk_h).min(wanted.end.div_ceil(chunk_h));
            // Row of tiles `ty`, every tile decoded in parallel straight into its columns
            // of `band`'s rows (no tile is held apart and copied): the rows it holds. The
            // first failure in file order is the error.
            // (With each row's range where `ranged`: its tiles' parts', joined.) A column
            // of tiles gives the rows it holds and, where asked, their parts' ranges.
            type ColumnRows = (usize, Vec<(f32, f32)>);
            let decode_band = |ty: usize,
                               band: &mut [f32],
                               ranges: &mut Vec<(f32, f32)>,
                               mapped: &mut Vec<Vec<f32>>|
             -> Result<usize> {
                let mut rows_here = chunk_h.min(height - ty * chunk_h);
                let mut columns: Vec<Vec<&mut [f32]>> = (0..across).map(|_| Vec::with_capacity(rows_here)).collect();
                for band_row in band.chunks_exact_mut(stride).take(rows_here) {
                    for (column, part) in columns.iter_mut().zip(band_row.chunks_mut(chunk_w * channels)) {
                        column.push(part);
                    }
                }
                let held: Vec<Result<ColumnRows>> = columns
                    .into_par_iter()
                    .enumerate()
                    .map(|(tx, mut rows)| {
                        let h = chunks.read_f32_into(ty * across + tx, &mut rows)?;
                        rows.iter_mut().take(h).for_each(|r| prepare(r));
                        let parts =
                            if ranged { rows.iter().take(h).map(|r| crate::min_max(r)).collect() } else { Vec::new() };
                        Ok((h, parts))
                    })
                    .collect();
                ranges.clear();
                if ranged {
                    ranges.resize(rows_here, (f32::INFINITY, f32::NEG_INFINITY));
                }
                for column in held {
                    let (h, parts) = column?;
                    rows_here = rows_here.min(h);
                    for (range, part) in ranges.iter_mut().zip(parts) {
                        *range = (range.0.min(part.0), range.1.max(part.1));
                    }
                }
                // Each whole row mapped, once all its tiles are in.
                *mapped =
                    map.map_or_else(Vec::new, |m| band[..rows_here * stride].par_chunks_exact(stride).map(m).collect());
                Ok(rows_here)
            };
            let first = (wanted.start / chunk_h).min(tile_rows);
            let (mut band, mut ahead) = (vec![0f32; stride * chunk_h], vec![0f32; stride * chunk_h]);
            let (mut ranges, mut ranges_ahead) = (Vec::new(), Vec::new());
            let (mut mapped, mut mapped_ahead) = (Vec::new(), Vec::new());
            let mut decoded = (first < tile_rows).then(|| decode_band(first, &mut band, &mut ranges, &mut mapped));
            for ty in first..tile_rows {
                let rows_here = decoded.take().unwrap_or(Ok(0))?;
                // The next row of tiles is decoded on the pool while this one's rows are
                // handed on: the pool does not wait for the hand-over, nor the hand-over
                // for the decoding (rows came in bursts, with the pool idle between).
                let mut next = None;
                let mut handed = Ok(());
                rayon::in_place_scope(|s| {
                    if ty + 1 < tile_rows {
                        let (ahead, ranges_ahead, mapped_ahead, next) =
                            (&mut ahead, &mut ranges_ahead, &mut mapped_ahead, &mut next);
                        s.spawn(move |_| *next = Some(decode_band(ty + 1, ahead, ranges_ahead, mapped_ahead)));
                    }
                    let mut made = std::mem::take(&mut mapped).into_iter();
                    handed = band.chunks_exact(stride).take(rows_here).enumerate().try_for_each(|(k, r)| {
                        let m = made.next();
                        if wanted.contains(&(ty * chunk_h + k)) { row(r, m, ranges.get(k).copied()) } else { Ok(()) }
                    });
                });
                handed?;
                std::mem::swap(&mut band, &mut ahead);
                std::mem::swap(&mut ranges, &mut ranges_ahead);
                std::mem::swap(&mut mapped, &mut mapped_ahead);
                decoded = next;
            }
        }
    }
    Ok(())
}

#[expect(
    clippy::cast_precision_loss,
    clippy::cast_possible_truncation,
    reason = "samples are kept as f32: exact up to 24 bits, heights need no more"
)]
pub(super) fn samples_f32(data: tiff::decoder::DecodingResult) -> Option<Vec<f32>> {
    use tiff::decoder::DecodingResult as D;
    Some(match data {
        D::U8(v) => v.into_iter().map(f32::from).collect(),
        D::I8(v) => v.into_iter().map(f32::from).collect(),
        D::U16(v) => v.into_iter().map(f32::from).collect(),
        D::I16(v) => v.into_iter().map(f32::from).collect(),
        D::U32(v) => v.into_iter().map(|x| x as f32).collect(),
        D::I32(v) => v.into_iter().map(|x| x as f32).collect(),
        D::U64(v) => v.into_iter().map(|x| x as f32).collect(),
        D::I64(v) => v.into_iter().map(|x| x as f32).collect(),
        D::F32(v) => v,
        D::F64(v) => v.into_iter().map(|x| x as f32).collect(),
        _ => return None,
    })
}
