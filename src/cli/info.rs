//! `terrastream info`.

use std::process::ExitCode;

use anyhow::{Context, Result};
use clap::Args;
use terrastream_format::ArchiveStats;

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

pub fn human(bytes: u64) -> String {
    let units = ["B", "KiB", "MiB", "GiB", "TiB"];
    let mut v = bytes as f64;
    let mut unit = 0;
    while v >= 1024.0 && unit + 1 < units.len() {
        v /= 1024.0;
        unit += 1;
    }
    if unit == 0 { format!("{bytes} B") } else { format!("{v:.1} {}", units[unit]) }
}

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
    let t = &m.terrain;
    let _ = writeln!(
        out,
        "terrain     elevation {}..{} m · mesh base {} m, high-detail range {} m, {} detail levels",
        t.min_elevation, t.max_elevation, t.base_tile_size, t.high_detail_range, t.num_detail_levels
    );
    if let Some(g) = &m.georeference {
        let _ = writeln!(out, "georef      {:?} origin {:?} bounds {:?}", g.crs, g.origin, g.lat_lon_bounds);
    }
    for (i, l) in s.layers.iter().enumerate() {
        let _ = writeln!(
            out,
            "layer {i}     {} ({:?}, {:?}{}, {} px + border {}) grid {}x{} · {} LODs · {} m/tile · {}",
            l.name,
            l.kind,
            l.format,
            match l.compression {
                terrastream_format::PayloadCompression::None => String::new(),
                other => format!("+{}", other.name()),
            },
            l.tile_resolution,
            l.border,
            l.grid[0],
            l.grid[1],
            l.num_lods,
            l.tile_world_size,
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
        if let Some(e) = m.layers.get(i).and_then(|l| l.extent.as_ref()) {
            let [x0, z0, x1, z1] = e.world;
            let [dx0, dz0, dx1, dz1] = e.detail;
            let mut line = format!(
                "            data LOD{}..=LOD{} · world {x0:.1},{z0:.1}..{x1:.1},{z1:.1} · detail \
                 {dx0:.1},{dz0:.1}..{dx1:.1},{dz1:.1}",
                e.finest_lod, e.coarsest_lod
            );
            if let Some([a, b, c, d]) = e.crs {
                line.push_str(&format!(" · crs {a:.3},{b:.3}..{c:.3},{d:.3}"));
            }
            if let Some([w, so, ea, n]) = e.lon_lat {
                line.push_str(&format!(" · lon/lat {w:.5},{so:.5}..{ea:.5},{n:.5}"));
            }
            let _ = writeln!(out, "{line}");
        }
    }
    out
}
