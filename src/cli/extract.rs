//! `terrastream extract`.

use std::path::PathBuf;
use std::process::ExitCode;

use anyhow::Result;
use clap::{Args, ValueEnum};
use terrastream_pack::extract::{Layout, extract};

use super::CliProgress;

#[derive(Debug, Args)]
pub struct ExtractArgs {
    /// The archive: a path or an http(s):// URL.
    archive: String,
    /// Output folder.
    #[arg(short, long)]
    output: PathBuf,
    /// Folder layout to write.
    #[arg(long, value_enum, default_value_t = LayoutArg::Original)]
    layout: LayoutArg,
}

#[derive(Clone, Copy, Debug, ValueEnum)]
enum LayoutArg {
    /// LOD0, LOD1, ... folders per layer plus the metadata text.
    Original,
    /// {z}/{x}/{y} tree (web zoom: z = 0 coarsest).
    Xyz,
}

pub fn run(args: ExtractArgs, progress: &CliProgress) -> Result<ExitCode> {
    let reader = super::open(&args.archive)?;
    let layout = match args.layout {
        LayoutArg::Original => Layout::Original,
        LayoutArg::Xyz => Layout::Xyz,
    };
    let summary = extract(&reader, &args.output, layout, progress)?;
    progress.finish();
    println!("wrote {} tiles ({} bytes) under {}", summary.files, summary.bytes, args.output.display());
    Ok(ExitCode::SUCCESS)
}
