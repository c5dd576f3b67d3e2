//! `info` and `verify` of a manifest (FORMAT.md §9): the manifest, then each archive.

use std::process::ExitCode;

use anyhow::{Context, Result};
use terrastream_client::ManifestSource;
use terrastream_format::{ArchiveStats, MAX_LAYERS, Manifest, verify};

use super::CliProgress;

/// Reads and validates the manifest at `location` (a path or URL).
pub fn read(location: &str) -> Result<Manifest> {
    let source = ManifestSource::new(location)?;
    let runtime = tokio::runtime::Builder::new_current_thread().enable_all().build()?;
    runtime.block_on(source.manifest()).with_context(|| format!("cannot read manifest {location}"))
}

/// `terrastream info MANIFEST`.
pub fn info(location: &str, json: bool) -> Result<ExitCode> {
    let manifest = read(location)?;
    let mut parts = Vec::new();
    for (i, part) in manifest.archives.iter().enumerate() {
        let at = manifest.resolve(location, i).context("archive location")?;
        let reader = super::open(&at)?;
        manifest.check_part(i, &reader.header().encode(), reader.metadata())?;
        parts.push((at, ArchiveStats::collect(&reader)?, part));
    }
    if json {
        let archives: Vec<_> = parts
            .iter()
            .map(|(at, stats, part)| serde_json::json!({ "location": at, "part": part, "stats": stats }))
            .collect();
        let doc = serde_json::json!({ "manifest": location, "metadata": manifest.metadata, "archives": archives });
        println!("{}", serde_json::to_string_pretty(&doc)?);
        return Ok(ExitCode::SUCCESS);
    }
    let total: u64 = parts.iter().map(|p| p.1.file_bytes).sum();
    let tiles: u64 = parts.iter().map(|p| p.1.addressed_tiles).sum();
    println!(
        "manifest    {location} — {} archives, {} in all, {tiles} tiles; terrain \"{}\"",
        parts.len(),
        super::info::human(total),
        manifest.metadata.name
    );
    for (at, stats, part) in &parts {
        let layers: Vec<String> = part
            .layers
            .iter()
            .map(|l| {
                let cover = l.coverage.as_ref().map_or("all".to_owned(), |c| {
                    let rects: Vec<String> =
                        c.rects.iter().map(|[x0, y0, x1, y1]| format!("x {x0}..{x1} y {y0}..{y1}")).collect();
                    format!("tiles {} at LOD {}", rects.join(", "), c.lod)
                });
                format!("{} LOD {}..={} {cover}", l.name, l.lods[0], l.lods[1])
            })
            .collect();
        println!(
            "archive     {at} — {}, {} tiles, tag {}: {}",
            super::info::human(stats.file_bytes),
            stats.addressed_tiles,
            part.etag,
            layers.join("; ")
        );
    }
    Ok(ExitCode::SUCCESS)
}

/// `terrastream verify MANIFEST`: the manifest, every archive as `verify` checks one, that
/// each is the archive named, and that each tile it holds is one the manifest routes to it.
pub fn verify_all(location: &str, progress: &CliProgress) -> Result<ExitCode> {
    let manifest = read(location)?;
    let mut problems = Vec::new();
    let mut tiles = 0u64;
    for i in 0..manifest.archives.len() {
        let at = manifest.resolve(location, i).context("archive location")?;
        let reader = match super::open(&at) {
            Ok(r) => r,
            Err(e) => {
                problems.push(format!("{at}: {e:#}"));
                continue;
            }
        };
        if let Err(e) = manifest.check_part(i, &reader.header().encode(), reader.metadata()) {
            problems.push(e.to_string());
        }
        progress.start_bytes(&format!("verify {}", manifest.archives[i].url), reader.header().data.len);
        let report = verify(&reader, |bytes| progress.set_position(bytes))?;
        problems.extend(report.problems.iter().map(|p| format!("{at}: {p}")));
        tiles += report.addressed_tiles;
        // Every tile it holds is reachable: the manifest routes its key here.
        let names: Vec<&str> = reader.metadata().layers.iter().map(|l| l.name.as_str()).collect();
        let mut stray = 0u64;
        reader.for_each_entry(|e| -> Result<()> {
            for k in 0..u64::from(e.run_length) {
                let key = reader.archive().tile_of(e.key + k * MAX_LAYERS as u64)?;
                let name = names[usize::from(key.layer())];
                let reachable = manifest.metadata.layer_index(name).is_some_and(|layer| {
                    terrastream_format::TileKey::new(layer, key.lod(), key.x(), key.y())
                        .ok()
                        .and_then(|k| manifest.route(k))
                        .is_some_and(|r| r.part == i && r.key == key)
                });
                if !reachable {
                    if stray < 5 {
                        problems.push(format!("{at}: tile {key} ({name}) is not routed here by the manifest"));
                    }
                    stray += 1;
                }
            }
            Ok(())
        })?;
        if stray > 5 {
            problems.push(format!("{at}: {} more tiles not routed here", stray - 5));
        }
    }
    progress.finish();
    if problems.is_empty() {
        println!(
            "{location}: OK — {} archives, {tiles} tiles, each where the manifest routes it",
            manifest.archives.len()
        );
        Ok(ExitCode::SUCCESS)
    } else {
        for p in &problems {
            eprintln!("{location}: {p}");
        }
        eprintln!("{location}: DAMAGED — {} problem(s)", problems.len());
        Ok(ExitCode::from(2))
    }
}
