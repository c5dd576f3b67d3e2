//! `terrastream water`.

use std::path::PathBuf;
use std::process::ExitCode;

use anyhow::Result;
use clap::Args;

use super::CliProgress;

#[derive(Debug, Args)]
pub struct WaterArgs {
    /// The archive to add the water layer to (one with an elevation layer and a
    /// georeference).
    archive: PathBuf,
    /// The water mask: a single-band raster in any CRS (a GeoTIFF), 0 land, 1 water
    /// (larger values count as 1, fractions between as partial cover), no data where it
    /// says nothing (the sea is then taken from the heights, a flat 0).
    #[arg(long)]
    mask: PathBuf,
    /// Output archive; by default the archive itself: the water tiles appended in place
    /// where it has room for updates, else written anew beside it and renamed over it.
    #[arg(short, long)]
    output: Option<PathBuf>,
}

pub fn run(args: WaterArgs, progress: &CliProgress) -> Result<ExitCode> {
    let WaterArgs { archive, mask, output } = args;
    let output = output.unwrap_or_else(|| archive.clone());
    let summary = terrastream_tiler::add_water(&archive, &mask, &output, progress)?;
    progress.finish();
    println!(
        "{}: water layer from {}: {} tiles ({} with water, {} bytes), {} elevation tiles outside the mask; {} bytes",
        output.display(),
        mask.display(),
        summary.tiles,
        summary.wet,
        summary.bytes,
        summary.uncovered,
        summary.write.file_len
    );
    Ok(ExitCode::SUCCESS)
}
