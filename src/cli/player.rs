//! `terrastream player`.

use std::path::PathBuf;
use std::process::ExitCode;

use anyhow::{Context, Result};
use clap::Args;

#[derive(Debug, Args)]
pub struct PlayerArgs {
    /// Output folder (created if missing).
    #[arg(short, long)]
    output: PathBuf,
}

/// `terrastream player -o DIR`.
pub fn run(args: PlayerArgs) -> Result<ExitCode> {
    let output = args.output.as_path();
    use terrastream_server::player;
    anyhow::ensure!(
        player::available(),
        "this terrastream binary was built without the webplayer: run scripts/build-player.sh, then rebuild"
    );
    std::fs::create_dir_all(output).with_context(|| format!("creating {}", output.display()))?;
    for (name, bytes) in player::files() {
        let path = output.join(name);
        // Written beside, then renamed: a host never serves half a file.
        let partial = output.join(format!(".{name}.partial"));
        std::fs::write(&partial, bytes).with_context(|| format!("writing {}", partial.display()))?;
        std::fs::rename(&partial, &path).with_context(|| format!("writing {}", path.display()))?;
        println!("{}  {} bytes", path.display(), bytes.len());
    }
    println!("open <host>/player.html?archive=<URL of a .tspack> (CORS needed when the archive is on another host)");
    Ok(ExitCode::SUCCESS)
}
