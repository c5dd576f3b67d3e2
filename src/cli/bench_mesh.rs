//! `terrastream bench mesh`: quantized-mesh tiles made per second and per core from an
//! archive's terrain (mesh + encode, the heights sampled beforehand), the sampling's and
//! the vertical datum conversion's share of a whole tile, triangles per tile,
//! and the same height grids and bounds written for a peer to mesh (`scripts/bench-mesh.sh`
//! runs Python's pydelatin + quantized-mesh-encoder on them).
//!
//! Grid file (little-endian): `TSGRIDS1`, tile count (u32), grid side (u32), then per tile
//! level (u8), column and row (u32, TMS), west, south, east, north (f64 degrees), the bound
//! (f32 metres) and the heights (f32, row by row from the north).

use std::io::Write as _;
use std::path::PathBuf;
use std::time::{Duration, Instant};

use anyhow::{Context, Result, bail};
use clap::Args;
use terrastream_format::{MmapSource, Reader};
use terrastream_views::quantized::encode::{self, Extensions, TileMesh};
use terrastream_views::quantized::geodetic::GeoTile;
use terrastream_views::quantized::{GRID, Terrain, geometric_error, mesh};

#[derive(Debug, Args)]
pub struct MeshBench {
    /// The archive (with a placed elevation layer).
    archive: PathBuf,
    /// Coarsest level.
    #[arg(long, default_value_t = 8)]
    min_level: u8,
    /// Finest level (default: the terrain's deepest).
    #[arg(long)]
    max_level: Option<u8>,
    /// At most this many tiles a level, spread over the level's available tiles.
    #[arg(long, default_value_t = 150)]
    per_level: usize,
    /// Times each tile is meshed (the best time is kept).
    #[arg(long, default_value_t = 3)]
    repeat: usize,
    /// Write the height grids and bounds here, for a peer to mesh.
    #[arg(long)]
    grids_out: Option<PathBuf>,
}

struct Grid {
    tile: GeoTile,
    heights: Vec<f32>,
    bound: f32,
}

pub fn run(args: &MeshBench) -> Result<()> {
    let reader =
        Reader::<MmapSource>::open_mmap(&args.archive).with_context(|| format!("{}", args.archive.display()))?;
    let Some(terrain) = Terrain::new(&reader, None) else {
        bail!("{}: no elevation layer that says where it lies", args.archive.display());
    };
    let max_level = args.max_level.unwrap_or(terrain.maxzoom()).min(terrain.maxzoom());
    let mut grids = vec![];
    // Sampling (its datum conversion included), and the conversion alone: the best of
    // `repeat` each.
    let (mut sampling, mut converting) = (Duration::ZERO, Duration::ZERO);
    for z in args.min_level..=max_level {
        let Some(ranges) = terrain.available(z) else { continue };
        let all: Vec<GeoTile> = (ranges.into_iter())
            .flat_map(|([x0, x1], [y0, y1])| {
                (y0..=y1).flat_map(move |y| (x0..=x1).filter_map(move |x| GeoTile::new(z, x, y)))
            })
            .collect();
        let step = all.len().div_ceil(args.per_level.max(1)).max(1);
        for &tile in all.iter().step_by(step) {
            let (mut best, mut best_datum) = (Duration::MAX, Duration::MAX);
            let mut heights = vec![];
            for _ in 0..args.repeat.max(1) {
                let start = Instant::now();
                heights = terrain.heights(tile).with_context(|| format!("tile {}/{}/{}", tile.z, tile.x, tile.y))?;
                best = best.min(start.elapsed());
                let mut copy = heights.clone();
                let start = Instant::now();
                terrain.to_ellipsoid(tile, &mut copy);
                best_datum = best_datum.min(start.elapsed());
                std::hint::black_box(copy);
            }
            (sampling, converting) = (sampling + best, converting + best_datum);
            let bound = Terrain::bound(tile, &heights);
            grids.push(Grid { tile, heights, bound });
        }
    }
    if grids.is_empty() {
        bail!("no tiles between levels {} and {max_level}", args.min_level);
    }
    if let Some(path) = &args.grids_out {
        write_grids(path, &grids).with_context(|| format!("{}", path.display()))?;
    }
    println!("level  tiles  triangles/tile  vertices/tile  bound (m)  mesh+encode µs/tile  of it mesh");
    let mut total = Duration::ZERO;
    let mut triangles = 0usize;
    for z in args.min_level..=max_level {
        let level: Vec<&Grid> = grids.iter().filter(|g| g.tile.z == z).collect();
        if level.is_empty() {
            continue;
        }
        let (mut time, mut meshing, mut tris, mut verts) = (Duration::ZERO, Duration::ZERO, 0usize, 0usize);
        for g in &level {
            let (mut best, mut best_mesh) = (Duration::MAX, Duration::MAX);
            for _ in 0..args.repeat.max(1) {
                let start = Instant::now();
                let m = mesh::mesh(&g.heights, GRID, g.bound);
                let meshed = start.elapsed();
                let t = TileMesh { tile: g.tile, mesh: &m, heights: &g.heights, size: GRID, water: None };
                std::hint::black_box(encode::encode(&t, Extensions::default(), None));
                (best, best_mesh) = (best.min(start.elapsed()), best_mesh.min(meshed));
                (tris, verts) = (tris + m.triangles.len(), verts + m.vertices.len());
            }
            time += best;
            meshing += best_mesh;
        }
        total += time;
        let per_tile = (level.len() * args.repeat.max(1)) as f64;
        triangles += tris / args.repeat.max(1);
        println!(
            "{z:>5}  {:>5}  {:>14.1}  {:>13.1}  {:>9.2}  {:>19.1}  {:>10.1}",
            level.len(),
            tris as f64 / per_tile,
            verts as f64 / per_tile,
            geometric_error(z),
            time.as_secs_f64() * 1e6 / level.len() as f64,
            meshing.as_secs_f64() * 1e6 / level.len() as f64
        );
    }
    let n = grids.len() as f64;
    println!(
        "all    {:>5}  {:>14.1}  meshes/s on one core: {:.0}",
        grids.len(),
        triangles as f64 / n,
        n / total.as_secs_f64()
    );
    let whole = sampling + total;
    println!(
        "a tile: sampling {:.1} µs + mesh and encode {:.1} µs; of it the vertical datum's conversion {:.1} µs ({:.2} % of the tile{})",
        sampling.as_secs_f64() * 1e6 / n,
        total.as_secs_f64() * 1e6 / n,
        converting.as_secs_f64() * 1e6 / n,
        100.0 * converting.as_secs_f64() / whole.as_secs_f64().max(1e-12),
        if reader.metadata().vertical_datum.converts() { "" } else { "; this archive's heights are not converted" }
    );
    Ok(())
}

fn write_grids(path: &std::path::Path, grids: &[Grid]) -> std::io::Result<()> {
    let mut out = std::io::BufWriter::new(std::fs::File::create(path)?);
    out.write_all(b"TSGRIDS1")?;
    out.write_all(&u32::try_from(grids.len()).unwrap_or(u32::MAX).to_le_bytes())?;
    out.write_all(&u32::try_from(GRID).unwrap_or(u32::MAX).to_le_bytes())?;
    for g in grids {
        out.write_all(&[g.tile.z])?;
        out.write_all(&g.tile.x.to_le_bytes())?;
        out.write_all(&g.tile.y.to_le_bytes())?;
        for v in g.tile.bounds() {
            out.write_all(&v.to_le_bytes())?;
        }
        out.write_all(&g.bound.to_le_bytes())?;
        for h in &g.heights {
            out.write_all(&h.to_le_bytes())?;
        }
    }
    out.flush()
}
