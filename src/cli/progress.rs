//! Progress bars (indicatif) and Ctrl-C: the first Ctrl-C asks the running command to stop
//! cleanly, a second one exits at once.

use std::sync::Arc;
use std::sync::atomic::{AtomicBool, Ordering};
use std::time::Duration;

use indicatif::{ProgressBar, ProgressDrawTarget, ProgressStyle};
use terrastream_pack::progress::Progress;

/// A progress bar on stderr that also carries the Ctrl-C flag.
pub struct CliProgress {
    bar: ProgressBar,
    stop: Arc<AtomicBool>,
    quiet: bool,
}

impl CliProgress {
    /// Installs the Ctrl-C / SIGTERM handler and returns a hidden bar.
    pub fn install(quiet: bool) -> Self {
        let stop = Arc::new(AtomicBool::new(false));
        let flag = Arc::clone(&stop);
        let installed = ctrlc::set_handler(move || {
            if flag.swap(true, Ordering::SeqCst) {
                std::process::exit(130);
            }
            eprintln!("\nstopping… (Ctrl-C again to quit at once)");
        });
        if let Err(err) = installed {
            tracing::warn!("cannot install the Ctrl-C handler: {err}");
        }
        // Drawn once a phase starts: before that, its default style is an empty bar.
        Self { bar: ProgressBar::hidden(), stop, quiet }
    }

    fn style(&self, template: &str) {
        if let Ok(style) = ProgressStyle::with_template(template) {
            // A whole number of tiles a second: `{per_sec}` prints four decimals.
            let rate = |state: &indicatif::ProgressState, w: &mut dyn std::fmt::Write| {
                let _ = write!(w, "{:.0}/s", state.per_sec());
            };
            self.bar.set_style(style.progress_chars("=> ").with_key("rate", rate));
        }
        if !self.quiet && self.bar.is_hidden() {
            self.bar.set_draw_target(ProgressDrawTarget::stderr());
        }
        self.bar.enable_steady_tick(Duration::from_millis(200));
    }

    /// Starts a phase counted in bytes.
    pub fn start_bytes(&self, phase: &str, total: u64) {
        self.bar.reset();
        self.bar.set_length(total);
        self.bar.set_message(phase.to_owned());
        self.style("{msg:>8} [{bar:40}] {bytes}/{total_bytes} {bytes_per_sec} ETA {eta}");
    }

    /// Moves the bar to `pos`.
    pub fn set_position(&self, pos: u64) {
        self.bar.set_position(pos);
    }

    /// Clears the bar.
    pub fn finish(&self) {
        self.bar.finish_and_clear();
    }
}

impl Progress for CliProgress {
    fn start(&self, phase: &str, total: u64) {
        self.bar.reset();
        self.bar.set_length(total);
        self.bar.set_message(phase.to_owned());
        // The height scan counts the output's rows; every other phase, tiles.
        let unit = if phase == "scan" { "rows" } else { "tiles" };
        self.style(&format!("{{msg:>8}} [{{bar:40}}] {{pos}}/{{len}} {unit} {{rate}} ETA {{eta}}"));
    }

    fn advance(&self, n: u64) {
        self.bar.inc(n);
    }

    fn cancelled(&self) -> bool {
        self.stop.load(Ordering::Relaxed)
    }
}
