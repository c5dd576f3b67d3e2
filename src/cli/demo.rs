//! `terrastream demo`: the README's first command.

use std::path::PathBuf;
use std::process::ExitCode;

use anyhow::{Context, Result};
use clap::Args;
use terrastream_packer::import::{OriginalLayout, pack, scan_original};
use terrastream_packer::sample::write_sample_pyramid;
use terrastream_packer::{ArchiveStats, WriterOptions, verify};

use super::CliProgress;

#[derive(Debug, Args)]
pub struct DemoArgs {
    /// Working folder for the sample pyramid and its archive.
    #[arg(long, default_value = "target/terrastream-demo")]
    dir: PathBuf,
}

pub fn run(args: DemoArgs, progress: &CliProgress) -> Result<ExitCode> {
    let input = args.dir.join("sample");
    let archive = args.dir.join("sample.tspack");
    if !input.join("metadata.txt").exists() {
        write_sample_pyramid(&input).with_context(|| format!("writing the sample pyramid to {}", input.display()))?;
        println!("wrote the built-in sample pyramid (original LOD-folder layout) to {}", input.display());
    }
    let scanned = scan_original(&input, &OriginalLayout::default())?;
    let summary = pack(scanned, &archive, WriterOptions::default(), progress)?;
    progress.finish();
    println!("packed {} tiles into {} ({} bytes)\n", summary.addressed_tiles, archive.display(), summary.file_len);
    let reader = super::open(&archive)?;
    print!("{}", super::info::render(&archive, &ArchiveStats::collect(&reader)?, reader.metadata()));
    let report = verify(&reader, |_| {})?;
    println!(
        "\nverify: {} ({} tiles, {} blobs checked)",
        if report.is_ok() { "OK" } else { "DAMAGED" },
        report.addressed_tiles,
        report.blobs_checked
    );
    println!("next: terrastream extract {} -o {}/extracted", archive.display(), args.dir.display());
    Ok(if report.is_ok() { ExitCode::SUCCESS } else { ExitCode::FAILURE })
}
