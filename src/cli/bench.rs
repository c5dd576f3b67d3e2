//! `terrastream bench archive`: pack throughput against a plain recursive copy of the same
//! folder (same run, same cache state), warm tile-lookup latency through mmap, and
//! directory bytes per tile against a PMTiles v3 directory of the same tiles.

use std::collections::HashMap;
use std::path::{Path, PathBuf};
use std::process::ExitCode;
use std::time::{Duration, Instant};

use anyhow::Result;
use clap::{Args, Subcommand};
use terrastream_format::{Directory, Entry, MmapSource, Reader, TileKey};
use terrastream_pack::import::{OriginalLayout, pack, scan_original};
use terrastream_pack::progress::Silent;
use terrastream_pack::{WriteSummary, WriterOptions};

#[derive(Debug, Subcommand)]
pub enum BenchCommand {
    /// Archive writer and reader: pack vs copy, lookup latency, directory size.
    Archive(ArchiveBench),
    /// Streaming core: time to full detail, requests per tile, upload budget (mmap vs HTTP).
    Stream(super::bench_stream::StreamBench),
    /// Renderer: frame times along a scripted flight, streaming vs all resident; vertices, draw calls.
    Render(super::bench_render::RenderBench),
    /// Quantized-mesh tiles: meshes per second per core, triangles per tile; height grids
    /// for a peer mesher.
    Mesh(super::bench_mesh::MeshBench),
}

#[derive(Debug, Args)]
pub struct ArchiveBench {
    /// LOD-0 tiles per side of the synthetic pyramid.
    #[arg(long, default_value_t = 64)]
    grid: u32,
    /// Mean tile size in bytes.
    #[arg(long, default_value_t = 16 * 1024)]
    tile_bytes: usize,
    /// Random lookups to time.
    #[arg(long, default_value_t = 200_000)]
    lookups: usize,
    /// Working folder (a temporary one by default).
    #[arg(long)]
    dir: Option<PathBuf>,
    /// Only pack (no copy baselines): to make a large archive for other benchmarks.
    #[arg(long)]
    no_copies: bool,
}

pub fn run(cmd: BenchCommand, progress: &super::CliProgress) -> Result<ExitCode> {
    match cmd {
        BenchCommand::Render(args) => super::bench_render::run(args, progress).map(|()| ExitCode::SUCCESS),
        BenchCommand::Archive(args) => archive(args),
        BenchCommand::Mesh(args) => super::bench_mesh::run(&args).map(|()| ExitCode::SUCCESS),
        BenchCommand::Stream(args) => super::bench_stream::run(args).map(|()| ExitCode::SUCCESS),
    }
}

/// xorshift64*: deterministic data without a dependency.
struct Rng(u64);
impl Rng {
    fn next(&mut self) -> u64 {
        self.0 ^= self.0 >> 12;
        self.0 ^= self.0 << 25;
        self.0 ^= self.0 >> 27;
        self.0.wrapping_mul(0x2545_f491_4f6c_dd1d)
    }
}

/// A pyramid in the original layout: PNG-signed payloads of varied size (not decodable
/// images: packing never decodes), one in ten tiles identical (dedup).
fn write_pyramid(dir: &Path, grid: u32, tile_bytes: usize) -> Result<(u64, u64)> {
    let mut rng = Rng(0x9e37_79b9_7f4a_7c15);
    // PNG signature + IHDR of a 256x256 RGB image: what the importer sniffs.
    let head: &[u8] = b"\x89PNG\r\n\x1a\n\0\0\0\rIHDR\0\0\x01\0\0\0\x01\0\x08\x02\0\0\0";
    let blank: Vec<u8> = head.iter().copied().chain(std::iter::repeat_n(0u8, 120)).collect();
    let (mut files, mut bytes) = (0u64, 0u64);
    let mut lod = 0u32;
    let mut n = grid;
    loop {
        let folder = dir.join(format!("LOD{lod}"));
        std::fs::create_dir_all(&folder)?;
        for y in 0..n {
            for x in 0..n {
                let payload = if rng.next().is_multiple_of(10) {
                    blank.clone()
                } else {
                    let len = tile_bytes / 2 + usize::try_from(rng.next() % tile_bytes as u64)?;
                    let mut p = head.to_vec();
                    p.extend((0..len / 8).flat_map(|_| rng.next().to_le_bytes()));
                    p
                };
                bytes += payload.len() as u64;
                files += 1;
                std::fs::write(folder.join(format!("{x}_{y}.png")), payload)?;
            }
        }
        if n == 1 {
            break;
        }
        n = n.div_ceil(2);
        lod += 1;
    }
    Ok((files, bytes))
}

fn files_under(dir: &Path) -> Result<Vec<PathBuf>> {
    let mut out = Vec::new();
    let mut stack = vec![dir.to_path_buf()];
    while let Some(d) = stack.pop() {
        for e in std::fs::read_dir(&d)? {
            let p = e?.path();
            if p.is_dir() { stack.push(p) } else { out.push(p) }
        }
    }
    Ok(out)
}

/// Copies every file; with `durable`, fsyncs each copy as the packer fsyncs its output.
/// (Not a system-wide `sync`: that would also time whatever else the machine has dirty.)
fn copy_tree(from: &Path, to: &Path, durable: bool) -> Result<()> {
    for file in files_under(from)? {
        let target = to.join(file.strip_prefix(from)?);
        if let Some(parent) = target.parent() {
            std::fs::create_dir_all(parent)?;
        }
        std::fs::copy(&file, &target)?;
        if durable {
            std::fs::File::open(&target)?.sync_all()?;
        }
    }
    Ok(())
}

/// PMTiles v3 directory bytes (root + leaves) for the same entries, encoded exactly as
/// `export --to pmtiles` writes them (gzip, the reference writer's leaf sizing).
fn pmtiles_directory_bytes(entries: &[Entry]) -> Result<usize> {
    // PMTiles stores no checksum trailer: re-lay the blobs back to back.
    let mut remap: HashMap<u64, u64> = HashMap::new();
    let mut next = 0u64;
    let rows: Vec<terrastream_pack::export::pmtiles::Row> = entries
        .iter()
        .map(|e| {
            let offset = *remap.entry(e.offset).or_insert_with(|| {
                let o = next;
                next += u64::from(e.length);
                o
            });
            (e.key >> 4, e.run_length, offset, e.length)
        })
        .collect();
    let (root, leaves) = terrastream_pack::export::pmtiles::directories(&rows)?;
    Ok(root.len() + leaves.len())
}

fn nanos(since: Instant) -> u64 {
    u64::try_from(since.elapsed().as_nanos()).unwrap_or(u64::MAX)
}

fn per_sec(n: f64, d: Duration) -> f64 {
    n / d.as_secs_f64().max(1e-9)
}

fn archive(args: ArchiveBench) -> Result<ExitCode> {
    let temp = tempfile::tempdir()?;
    let root = args.dir.clone().unwrap_or_else(|| temp.path().to_path_buf());
    let input = root.join("pyramid");
    let (files, bytes) = write_pyramid(&input, args.grid, args.tile_bytes)?;
    // Flush the input to disk so neither contender pays for writing it back.
    std::process::Command::new("sync").status().ok();
    let mb = bytes as f64 / 1e6;
    println!(
        "input: {files} tiles, {mb:.1} MB in the original LOD-folder layout ({}x{} at LOD 0)",
        args.grid, args.grid
    );

    // The baselines: plain copies, timed after warming the page cache once so both
    // contenders read from memory.
    let copies = if args.no_copies {
        None
    } else {
        for f in files_under(&input)? {
            std::fs::read(f)?;
        }
        let t = Instant::now();
        copy_tree(&input, &root.join("copy"), false)?;
        let copy = t.elapsed();
        let t = Instant::now();
        copy_tree(&input, &root.join("copy-durable"), true)?;
        Some((copy, t.elapsed()))
    };

    let t = Instant::now();
    let scanned = scan_original(&input, &OriginalLayout::default())?;
    let out = root.join("bench.tspack");
    let summary = pack(scanned, &out, WriterOptions::default(), &Silent::default())?;
    let packed = t.elapsed();

    println!("\n== pack throughput (same input, same run) ==");
    let line = |name: &str, d: Duration| {
        println!(
            "  {name:<34}: {:>9.0} tiles/s {:>8.1} MB/s  ({:.2} s)",
            per_sec(files as f64, d),
            per_sec(mb, d),
            d.as_secs_f64()
        );
    };
    if let Some((copy, durable_copy)) = copies {
        line("recursive copy (page cache only)", copy);
        line("recursive copy, each file fsynced", durable_copy);
    }
    line("terrastream pack (output fsynced)", packed);
    if let Some((copy, durable_copy)) = copies {
        let ratio = |d: Duration| packed.as_secs_f64() / d.as_secs_f64().max(1e-9);
        println!(
            "  pack / copy time                  : {:.2}x (cache only), {:.2}x (durable)",
            ratio(copy),
            ratio(durable_copy)
        );
    }
    let reader = Reader::new(MmapSource::open(&out)?)?;
    let entries = lookups(&reader, args.lookups, summary.leaf_count)?;
    directory_sizes(&reader, &summary, &entries)?;
    Ok(ExitCode::SUCCESS)
}

/// Times warm lookups of `count` random tiles of the archive; returns its entries.
fn lookups(reader: &Reader<MmapSource>, count: usize, leaf_count: u64) -> Result<Vec<Entry>> {
    let mut keys = Vec::new();
    let mut entries = Vec::new();
    reader.for_each_entry(|e| -> Result<()> {
        entries.push(*e);
        for i in 0..u64::from(e.run_length) {
            keys.push(reader.archive().tile_of(e.key + i * 16)?);
        }
        Ok(())
    })?;
    let mut rng = Rng(42);
    let picks: Vec<TileKey> =
        (0..count).map(|_| keys[usize::try_from(rng.next() % keys.len() as u64).unwrap_or(0)]).collect();
    for k in &picks {
        reader.tile(*k)?; // warm: leaves cached, pages mapped
    }
    let mut locate_ns = Vec::with_capacity(picks.len());
    let mut tile_ns = Vec::with_capacity(picks.len());
    for k in &picks {
        let t = Instant::now();
        std::hint::black_box(reader.locate(*k)?);
        locate_ns.push(nanos(t));
        let t = Instant::now();
        std::hint::black_box(reader.tile(*k)?);
        tile_ns.push(nanos(t));
    }
    let pct = |v: &mut Vec<u64>, p: usize| {
        v.sort_unstable();
        v[(v.len() - 1) * p / 100]
    };
    println!("\n== warm tile lookup, mmap ({} random tiles, {leaf_count} leaf directories) ==", picks.len());
    println!(
        "  locate (directory only)     : p50 {:>6} ns  p99 {:>6} ns",
        pct(&mut locate_ns, 50),
        pct(&mut locate_ns, 99)
    );
    println!(
        "  tile (locate + CRC32C check): p50 {:>6} ns  p99 {:>6} ns",
        pct(&mut tile_ns, 50),
        pct(&mut tile_ns, 99)
    );
    Ok(entries)
}

/// The archive's directory bytes per tile against PMTiles v3's for the same tiles.
fn directory_sizes(reader: &Reader<MmapSource>, summary: &WriteSummary, entries: &[Entry]) -> Result<()> {
    let ours = summary.directory_bytes as f64 / summary.addressed_tiles as f64;
    let pm = pmtiles_directory_bytes(entries)? as f64 / summary.addressed_tiles as f64;
    let root_entries = match reader.archive().root() {
        Directory::Tiles(e) => e.len(),
        Directory::Leaves(l) => l.len(),
    };
    println!(
        "\n== directory size ({} tiles, {} entries, {} distinct) ==",
        summary.addressed_tiles, summary.tile_entries, summary.tile_contents
    );
    println!("  tspack (zstd, root {root_entries} entries) : {ours:.3} bytes/tile");
    println!("  PMTiles v3 (gzip), same tiles     : {pm:.3} bytes/tile");
    println!("  tspack / PMTiles                  : {:.2}x", ours / pm);
    println!("  bootstrap read                    : {} bytes", reader.header().bootstrap_len());
    Ok(())
}
