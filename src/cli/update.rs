//! `terrastream update`.

use std::path::PathBuf;
use std::process::ExitCode;

use anyhow::Result;
use clap::Args;

use super::CliProgress;

#[derive(Debug, Args)]
#[command(group = clap::ArgGroup::new("target").required(true))]
pub struct UpdateArgs {
    /// The archive to update (a projected CRS: tiled from a mosaic or with --crs).
    base: PathBuf,
    /// New elevation rasters (files, folders, patterns; any CRS).
    #[arg(long, num_args = 1..)]
    elevation: Vec<PathBuf>,
    /// New imagery (GeoTIFFs; any CRS).
    #[arg(long, num_args = 1..)]
    texture: Vec<PathBuf>,
    /// Output archive: a copy of the base, updated.
    #[arg(short, long, group = "target")]
    output: Option<PathBuf>,
    /// Update the base itself: only the changed tiles and the new directories are
    /// written (FORMAT.md §7.1); readers of the old version keep reading it.
    #[arg(long, group = "target")]
    in_place: bool,
    /// Also write a manifest (FORMAT.md §9) naming the updated archive: a manifest names
    /// an archive by its content tag, which every update changes, so publish it again.
    #[arg(long)]
    manifest_out: Option<PathBuf>,
}

pub fn run(args: UpdateArgs, progress: &CliProgress) -> Result<ExitCode> {
    let UpdateArgs { base, elevation, texture, output, manifest_out, .. } = args;
    anyhow::ensure!(!elevation.is_empty() || !texture.is_empty(), "nothing to update: give --elevation or --texture");
    let output = output.unwrap_or_else(|| base.clone());
    let elevation = terrastream_tiler::expand_inputs(&elevation)?;
    let texture = terrastream_tiler::expand_inputs(&texture)?;
    let summary = terrastream_tiler::update(&base, &elevation, &texture, &output, progress)?;
    progress.finish();
    println!(
        "{}: {} tiles from the new rasters, {} base tiles replaced, {} made again around and above them, {} bytes",
        output.display(),
        summary.tiled,
        summary.merge.replaced,
        summary.merge.made,
        summary.merge.write.file_len
    );
    if let Some(manifest) = &manifest_out {
        terrastream_tiler::single_manifest(&output, manifest)?;
        println!("{}: manifest of {}", manifest.display(), output.display());
    }
    Ok(ExitCode::SUCCESS)
}
