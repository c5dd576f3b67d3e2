//! `terrastream info`.

use std::process::ExitCode;

use anyhow::{Context, Result};
use clap::Args;
use terrastream_format::ArchiveStats;

use super::people;

#[derive(Debug, Args)]
pub struct InfoArgs {
    /// The archive or manifest (`.json`): a path or an http(s):// URL.
    archive: String,
    /// Print JSON instead of text.
    #[arg(long)]
    json: bool,
    /// List every tile: layer, lod, x, y, absolute byte offset and length of its blob
    /// (payload + 4-byte checksum), tab-separated.
    #[arg(long, conflicts_with = "json")]
    tiles: bool,
    /// A shard: write to this file the length of the prefix of the archive that holds its
    /// header, directories and every tile at its layers' split LODs (coarsest first: what
    /// `merge --manifest` reads of a shard), so that a publish step fetches only that.
    #[arg(long, conflicts_with_all = ["json", "tiles"])]
    shard_top_out: Option<std::path::PathBuf>,
}

pub fn run(args: InfoArgs) -> Result<ExitCode> {
    let InfoArgs { archive, json, tiles, shard_top_out } = args;
    if let Some(out) = shard_top_out {
        let reader = super::open(&archive)?;
        let top = shard_top(&reader).with_context(|| format!("{archive}: the prefix of its top tiles"))?;
        super::make_parent(&out)?;
        std::fs::write(&out, format!("{top}\n")).with_context(|| format!("{}: cannot write", out.display()))?;
        return Ok(ExitCode::SUCCESS);
    }
    if !tiles && terrastream_format::is_manifest_location(&archive) {
        return super::manifest::info(&archive, json);
    }
    let path = archive.as_str();
    let reader = super::open(path)?;
    if tiles {
        use std::io::Write;
        let mut out = std::io::BufWriter::new(std::io::stdout().lock());
        let data = reader.header().data.offset;
        reader.for_each_entry(|e| -> Result<()> {
            for i in 0..u64::from(e.run_length) {
                let t = reader.archive().tile_of(e.key + i * terrastream_format::MAX_LAYERS as u64)?;
                let line = format!(
                    "{}\t{}\t{}\t{}\t{}\t{}",
                    t.layer(),
                    t.lod(),
                    t.x(),
                    t.y(),
                    data + e.offset,
                    e.stored_len()
                );
                writeln!(out, "{line}")?;
            }
            Ok(())
        })?;
        out.flush()?;
        return Ok(ExitCode::SUCCESS);
    }
    let stats = ArchiveStats::collect(&reader)?;
    if json {
        let doc = serde_json::json!({ "stats": stats, "metadata": reader.metadata() });
        println!("{}", serde_json::to_string_pretty(&doc)?);
        return Ok(ExitCode::SUCCESS);
    }
    print!("{}", render(path, &stats, reader.metadata()));
    Ok(ExitCode::SUCCESS)
}

/// The bytes of a shard from its start to the end of its last blob at or above its layers'
/// split LODs (at least the header and directories: up to the data section).
fn shard_top<S: terrastream_format::RangeSource>(reader: &terrastream_format::Reader<S>) -> Result<u64> {
    let Some(shard) = reader.metadata().shard.as_ref() else {
        anyhow::bail!("not a shard (its metadata names no shard of a run)");
    };
    let data = reader.header().data.offset;
    let mut end = data;
    reader.for_each_entry(|e| -> Result<()> {
        for i in 0..u64::from(e.run_length) {
            let t = reader.archive().tile_of(e.key + i * terrastream_format::MAX_LAYERS as u64)?;
            if shard.split_lods.get(usize::from(t.layer())).is_some_and(|&k| t.lod() >= k) {
                end = end.max(data + e.offset + e.stored_len());
            }
        }
        Ok(())
    })?;
    Ok(end)
}

pub use super::people::bytes as human;

pub fn render(path: &str, s: &ArchiveStats, m: &terrastream_format::Metadata) -> String {
    use std::fmt::Write;
    let mut out = String::new();
    let _ = writeln!(out, "archive     {path} — {}, format {}", human(s.file_bytes), s.version);
    let _ = writeln!(out, "name        {}", m.name);
    let _ = writeln!(
        out,
        "sections    metadata {} · root directory {} · leaf directories {} ({} leaves) · data {}",
        human(s.metadata_bytes),
        human(s.root_directory_bytes),
        human(s.leaf_directory_bytes),
        s.leaf_directories,
        human(s.data_bytes)
    );
    let _ = writeln!(out, "bootstrap   {} (first read of a client)", human(s.bootstrap_bytes));
    let _ = writeln!(
        out,
        "tiles       {} addressed · {} entries · {} distinct · dedup {:.2}x · {:.2} directory bytes/tile",
        s.addressed_tiles, s.tile_entries, s.tile_contents, s.dedup_ratio, s.directory_bytes_per_tile
    );
    if let Some(sh) = &m.shard {
        out.push_str(&shard(sh, m));
    }
    let t = &m.terrain;
    let _ = writeln!(
        out,
        "terrain     elevation {} to {} · mesh base {}, high-detail range {}, {} detail levels",
        people::height(t.min_elevation),
        people::height(t.max_elevation),
        people::length(t.base_tile_size),
        people::length(t.high_detail_range),
        t.num_detail_levels
    );
    if let Some(g) = &m.georeference {
        out.push_str(&georeference(g));
    }
    out.push_str(&vertical(&m.vertical_datum));
    for (k, source) in m.sources.iter().enumerate() {
        let _ = writeln!(
            out,
            "{:<12}{} · {} between samples · from LOD{}{}",
            if k == 0 { "inputs" } else { "" },
            source.name,
            people::length(source.spacing),
            source.lod,
            source.layer.as_deref().map_or_else(String::new, |l| format!(" ({l})"))
        );
    }
    for (i, l) in s.layers.iter().enumerate() {
        out.push_str(&layer(i, l, m.layers.get(i).and_then(|l| l.extent.as_ref())));
    }
    out
}

/// Which shard of a run this is, what it holds, and what its merge needs: the run's
/// inputs too where a collection's layer is split finer than its base.
fn shard(sh: &terrastream_format::Shard, m: &terrastream_format::Metadata) -> String {
    let k = sh.split_lods.first().copied().unwrap_or(0);
    let [a, b] = sh.tile_rows.first().copied().unwrap_or([0, 0]);
    let mut line = format!(
        "shard       {}/{} of a run (`--shard`) · LOD 0 to {k} · LOD-0 tile rows {a} to {}",
        sh.index,
        sh.count,
        b.saturating_sub(1)
    );
    let finer: Vec<String> = (m.layers.iter().zip(&sh.split_lods))
        .filter(|(l, _)| {
            matches!(l.kind, terrastream_format::LayerKind::Elevation | terrastream_format::LayerKind::Texture)
        })
        .filter_map(|(l, &k)| {
            let base = l.extent.as_ref()?.whole_from()?;
            (k < base).then(|| format!("{} (base LOD {base})", l.name))
        })
        .collect();
    if !finer.is_empty() {
        line.push_str(&format!(
            " · split finer than the base of {}: `merge` needs the run's inputs too (`--elevation`/`--texture`, or \
             `--shard-plan`)",
            finer.join(", ")
        ));
    }
    line + "\n"
}

/// What the heights are measured from, and the geoid's undulation over the footprint.
fn vertical(d: &terrastream_format::VerticalDatum) -> String {
    let mut line = format!("heights     above the {}", d.describe());
    if d.is_unknown() {
        line = "heights     vertical datum unknown (served as stored; `tile --vertical-datum` names it)".to_owned();
    }
    if let Some(u) = &d.undulation {
        let (lo, hi) = u.range();
        line.push_str(&format!(
            " · geoid {} to {} above the ellipsoid here ({}x{} nodes{})",
            people::height(lo),
            people::height(hi),
            u.columns,
            u.rows,
            d.grid.as_deref().map(|g| format!(" of {g}")).unwrap_or_default()
        ));
    }
    line + "\n"
}

/// Where the archive lies: its CRS by name and code, the grid's origin, the bounds.
fn georeference(g: &terrastream_format::Georeference) -> String {
    let mut out = String::new();
    let crs = g.crs.as_deref().or(g.definition.as_deref());
    let geographic = crs.is_some_and(|c| terrastream_crs::Crs::parse(c).is_ok_and(|c| c.is_geographic()));
    let mut line = format!("crs         {}", crs.map_or_else(|| "not recorded".to_owned(), people::crs));
    if let Some([x, y]) = g.origin {
        // Degrees to five decimals (about a metre); CRS units to the centimetre.
        let (x, y) = if geographic {
            (people::fixed(x, 5), people::fixed(y, 5))
        } else {
            (people::fixed(x, 2), people::fixed(y, 2))
        };
        line.push_str(&format!(" · origin {x}, {y}"));
    }
    out.push_str(&line);
    out.push('\n');
    if let Some(b) = g.lat_lon_bounds {
        out.push_str(&format!("bounds      {}\n", people::lon_lat_box(b)));
    }
    out
}

/// One layer: what it stores, its grid, LODs and bytes, then where its data lies.
fn layer(i: usize, l: &terrastream_format::LayerStats, extent: Option<&terrastream_format::LayerExtent>) -> String {
    use std::fmt::Write;
    let mut out = String::new();
    let compression = match l.compression {
        terrastream_format::PayloadCompression::None => String::new(),
        other => format!("+{}", other.name()),
    };
    let _ = writeln!(
        out,
        "layer {i}     {} ({}, {}{compression}, {} px + border {}) grid {}x{} · {} LODs · {}/tile · {}",
        l.name,
        people::name(&l.kind),
        people::name(&l.format),
        l.tile_resolution,
        l.border,
        l.grid[0],
        l.grid[1],
        l.num_lods,
        people::length(l.tile_world_size),
        human(l.data_bytes)
    );
    let per_lod: Vec<String> = l
        .tiles_per_lod
        .iter()
        .zip(&l.grid_tiles_per_lod)
        .enumerate()
        .map(|(lod, (n, of))| format!("LOD{lod} {n}/{of}"))
        .collect();
    let _ = writeln!(out, "            {}", per_lod.join(" · "));
    if let Some(e) = extent {
        let [x0, z0, x1, z1] = e.world.map(|v| people::fixed(v, 1));
        let [dx0, dz0, dx1, dz1] = e.detail.map(|v| people::fixed(v, 1));
        let mut line = format!(
            "            data LOD{}..=LOD{} · world {x0},{z0}..{x1},{z1} · detail {dx0},{dz0}..{dx1},{dz1}",
            e.finest_lod, e.coarsest_lod
        );
        if let Some(c) = e.crs {
            let [a, b, c, d] = c.map(|v| people::fixed(v, 3));
            line.push_str(&format!(" · crs {a},{b}..{c},{d}"));
        }
        if let Some(b) = e.lon_lat {
            line.push_str(&format!(" · {}", people::lon_lat_box(b)));
        }
        let _ = writeln!(out, "{line}");
        if !e.partial.is_empty() {
            let levels: Vec<String> = (e.partial.iter())
                .map(|c| {
                    format!("LOD{} in {} rectangle{}", c.lod, c.tiles.len(), if c.tiles.len() == 1 { "" } else { "s" })
                })
                .collect();
            let _ = writeln!(out, "            only where fine inputs lie: {}", levels.join(" · "));
        }
    }
    out
}
