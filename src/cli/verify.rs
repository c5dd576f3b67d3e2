//! `terrastream verify`.

use std::process::ExitCode;

use anyhow::Result;
use clap::Args;
use terrastream_format::verify;

use super::CliProgress;

#[derive(Debug, Args)]
pub struct VerifyArgs {
    /// The archive or manifest (`.json`): a path or an http(s):// URL.
    archive: String,
}

pub fn run(args: VerifyArgs, progress: &CliProgress) -> Result<ExitCode> {
    let archive = args.archive;
    if terrastream_format::is_manifest_location(&archive) {
        return super::manifest::verify_all(&archive, progress);
    }
    let reader = super::open(&archive)?;
    progress.start_bytes("verify", reader.header().data.len);
    let report = verify(&reader, |bytes| progress.set_position(bytes))?;
    progress.finish();
    if report.is_ok() {
        println!(
            "{archive}: OK — {} tiles, {} blobs, {} leaves, {} payload bytes checked",
            report.addressed_tiles, report.blobs_checked, report.leaves_checked, report.bytes_checked
        );
        if report.unreferenced_bytes > 0 {
            println!(
                "{archive}: {} bytes of replaced tiles left by updates in place (`terrastream merge {archive} -o …` writes a compact copy)",
                report.unreferenced_bytes
            );
        }
        Ok(ExitCode::SUCCESS)
    } else {
        for p in &report.problems {
            eprintln!("{archive}: {p}");
        }
        eprintln!("{archive}: DAMAGED — {} problem(s)", report.problems.len());
        Ok(ExitCode::from(2))
    }
}
