//! `terrastream export`.

use std::path::PathBuf;
use std::process::ExitCode;

use anyhow::{Context, Result};
use clap::{Args, ValueEnum};

use super::CliProgress;

#[derive(Debug, Args)]
pub struct ExportArgs {
    /// The archive: a path or an http(s):// URL.
    archive: String,
    /// Layer name (or index).
    #[arg(long)]
    layer: String,
    /// Target format.
    #[arg(long, value_enum)]
    to: ExportFormat,
    /// Output file (written to a temporary name, then renamed).
    #[arg(short, long)]
    output: PathBuf,
}

#[derive(Clone, Copy, Debug, ValueEnum)]
enum ExportFormat {
    /// PMTiles v3 (web zoom z = coarsest 0), readable by any PMTiles reader.
    Pmtiles,
}

pub fn run(args: ExportArgs, progress: &CliProgress) -> Result<ExitCode> {
    let ExportArgs { archive, layer, to: ExportFormat::Pmtiles, output } = args;
    let reader = super::open(&archive)?;
    let meta = reader.metadata();
    let index = meta.resolve_layer(&layer).with_context(|| {
        let names: Vec<&str> = meta.layers.iter().map(|l| l.name.as_str()).collect();
        format!("{archive} has no layer {layer:?} (layers: {})", names.join(", "))
    })?;
    let summary = terrastream_pack::export::pmtiles::export_pmtiles(&reader, index, &output, progress)?;
    progress.finish();
    println!(
        "{}: PMTiles v3, {} tiles ({} distinct), {} bytes",
        output.display(),
        summary.addressed_tiles,
        summary.tile_contents,
        summary.file_len
    );
    Ok(ExitCode::SUCCESS)
}
