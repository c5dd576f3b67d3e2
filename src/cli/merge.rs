//! `terrastream merge`.

use std::path::PathBuf;
use std::process::ExitCode;

use anyhow::{Context, Result};
use clap::{Args, ValueEnum};

use super::CliProgress;

#[derive(Debug, Args)]
pub struct MergeArgs {
    /// Archives, in order: a later one's tile replaces an earlier one's. A folder stands
    /// for the `*.tspack` files in it, by name.
    #[arg(required = true)]
    inputs: Vec<PathBuf>,
    /// Output archive (written to a temporary name, then renamed).
    #[arg(short, long)]
    output: PathBuf,
    /// Tiles several archives hold: `last` (a later archive's tile replaces the
    /// tile), or `pixels` (a later archive's samples with data replace, its nodata
    /// and transparent samples keep the earlier ones).
    #[arg(long, value_enum, default_value_t = PreferArg::Last)]
    prefer: PreferArg,
    /// Publish the shards of a run as they are instead of one archive: the output
    /// gets only the levels above their split LOD, and this manifest names it and
    /// every shard (URLs relative to the manifest; FORMAT.md §9).
    #[arg(long, conflicts_with = "prefer")]
    manifest: Option<PathBuf>,
    /// A water mask (as `terrastream water` takes): the output's water layer made from
    /// it. Shards that hold a water layer (`terrastream water` of each) need it for the
    /// levels above their split LOD: a water tile is the mask's, not its children's
    /// means. With `--manifest`, the coarse archive's water tiles.
    #[arg(long)]
    water: Option<PathBuf>,
    /// The run's elevation inputs, as `tile` took them: needed by the shards of a
    /// collection split finer than its base (the merge makes the levels from the split up
    /// to the base from their tiles and the inputs as deep).
    #[arg(long, num_args = 1..)]
    elevation: Vec<PathBuf>,
    /// The run's imagery, as `--elevation` (a collection of images split finer than its
    /// base).
    #[arg(long, num_args = 1..)]
    texture: Vec<PathBuf>,
    /// The run's shard plan (`plan.json` of `tile --shard-plan-out`): instead of every
    /// input, the merge then opens only those it reads (its `merge.txt` lists them), at
    /// the paths the plan records, under `--inputs`.
    #[arg(long, conflicts_with_all = ["elevation", "texture"])]
    shard_plan: Option<PathBuf>,
    /// With `--shard-plan`: the folder its input paths are under (its `--relative-to`).
    #[arg(long = "inputs", requires = "shard_plan")]
    inputs_root: Option<PathBuf>,
}

#[derive(Clone, Copy, Debug, PartialEq, Eq, ValueEnum)]
enum PreferArg {
    /// A later archive's tile replaces the tile.
    Last,
    /// A later archive's samples with data replace, per sample (LOD 0).
    Pixels,
}

pub fn run(args: MergeArgs, progress: &CliProgress) -> Result<ExitCode> {
    let MergeArgs { inputs, output, prefer, manifest, water, elevation, texture, shard_plan, inputs_root: root } = args;
    super::make_parent(&output)?;
    let (elevation, texture) =
        (terrastream_tiler::expand_inputs(&elevation)?, terrastream_tiler::expand_inputs(&texture)?);
    let planned = match &shard_plan {
        Some(path) => super::tile::read_shard_plan(path)?.collections,
        None => Vec::new(),
    };
    let run = terrastream_tiler::RunInputs {
        elevation: &elevation,
        texture: &texture,
        planned: &planned,
        root: root.as_deref(),
    };
    if let Some(manifest) = manifest {
        // The coarse archive of an earlier run in the shards' folder is not an input.
        let earlier = std::fs::canonicalize(&output).ok();
        let mut inputs = archives_in(&inputs)?;
        inputs.retain(|p| earlier.is_none() || std::fs::canonicalize(p).ok() != earlier);
        let summary =
            terrastream_tiler::merge_to_manifest(&inputs, &output, &manifest, water.as_deref(), run, progress)?;
        progress.finish();
        println!(
            "{}: {} archives ({} tiles above the split LOD made into {}, {} bytes)",
            manifest.display(),
            summary.manifest.archives.len(),
            summary.coarse.addressed_tiles,
            output.display(),
            summary.coarse.file_len
        );
        return Ok(ExitCode::SUCCESS);
    }
    let inputs = archives_in(&inputs)?;
    let prefer = match prefer {
        PreferArg::Last => terrastream_tiler::Prefer::Last,
        PreferArg::Pixels => terrastream_tiler::Prefer::Pixels,
    };
    let (summary, water_made) =
        terrastream_tiler::merge_with_water(&inputs, &output, prefer, water.as_deref(), run, progress)?;
    progress.finish();
    if let (Some(mask), Some(w)) = (&water, water_made) {
        println!(
            "{}: water layer from {}: {} tiles ({} with water), {} elevation tiles outside the mask",
            output.display(),
            mask.display(),
            w.tiles,
            w.wet,
            w.uncovered
        );
    }
    println!(
        "{}: {} tiles copied from {} archives ({} replaced by a later one), {} made, {} bytes",
        output.display(),
        summary.copied,
        inputs.len(),
        summary.replaced,
        summary.made,
        summary.write.file_len
    );
    Ok(ExitCode::SUCCESS)
}

/// Paths with each folder replaced by the `*.tspack` files in it, sorted by name.
fn archives_in(paths: &[PathBuf]) -> Result<Vec<PathBuf>> {
    let mut out = Vec::new();
    for path in paths {
        if !path.is_dir() {
            out.push(path.clone());
            continue;
        }
        let mut found: Vec<PathBuf> = std::fs::read_dir(path)
            .with_context(|| format!("cannot list {}", path.display()))?
            .filter_map(|e| e.ok().map(|e| e.path()))
            .filter(|p| p.extension().is_some_and(|e| e == "tspack") && p.is_file())
            .collect();
        anyhow::ensure!(!found.is_empty(), "{}: no .tspack archives in this folder", path.display());
        found.sort();
        out.extend(found);
    }
    Ok(out)
}
