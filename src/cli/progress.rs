//! Progress bars (indicatif) and Ctrl-C: the first Ctrl-C asks the running command to stop
//! cleanly, a second one exits at once.

use std::io::IsTerminal as _;
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::{Arc, Mutex};
use std::time::{Duration, Instant};

use indicatif::{ProgressBar, ProgressDrawTarget, ProgressStyle};
use terrastream_pack::progress::Progress;

/// A progress bar on stderr that also carries the Ctrl-C flag; where stderr is not a
/// terminal, a log line now and then instead.
pub struct CliProgress {
    bar: ProgressBar,
    stop: Arc<AtomicBool>,
    quiet: bool,
    /// Lines instead of a bar: at most one this often.
    lines: Option<Duration>,
    /// When the phase started and when its last line was written.
    clock: Mutex<(Instant, Instant)>,
}

impl CliProgress {
    /// Installs the Ctrl-C / SIGTERM handler and returns a hidden bar.
    pub fn install(quiet: bool, log_every: f64) -> Self {
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
        let lines = (!quiet && !std::io::stderr().is_terminal())
            .then(|| Duration::try_from_secs_f64(log_every.max(0.0)).unwrap_or(Duration::from_secs(30)));
        let now = Instant::now();
        Self { bar: ProgressBar::hidden(), stop, quiet, lines, clock: Mutex::new((now, now)) }
    }

    /// A progress line (where there is no bar), at most one per interval, and always at
    /// the phase's end.
    fn line(&self) {
        let Some(every) = self.lines else { return };
        let (pos, len) = (self.bar.position(), self.bar.length().unwrap_or(0));
        let mut clock = self.clock.lock().unwrap_or_else(std::sync::PoisonError::into_inner);
        let now = Instant::now();
        if now.duration_since(clock.1) < every && pos < len {
            return;
        }
        clock.1 = now;
        let secs = now.duration_since(clock.0).as_secs_f64();
        let rate = if secs > 0.0 { pos as f64 / secs } else { 0.0 };
        let left = if rate > 0.0 { (len.saturating_sub(pos)) as f64 / rate } else { 0.0 };
        let percent = if len > 0 { 100.0 * pos as f64 / len as f64 } else { 100.0 };
        tracing::info!(
            "{}: {pos}/{len} ({percent:.1} %), {rate:.0}/s, {secs:.0} s so far, about {left:.0} s left",
            self.bar.message()
        );
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
        self.line();
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
        if self.lines.is_some() {
            let now = Instant::now();
            *self.clock.lock().unwrap_or_else(std::sync::PoisonError::into_inner) = (now, now);
            tracing::info!("{phase}: {total} to do");
        }
        // The height scan counts the output's rows; every other phase, tiles.
        let unit = if phase == "scan" { "rows" } else { "tiles" };
        self.style(&format!("{{msg:>8}} [{{bar:40}}] {{pos}}/{{len}} {unit} {{rate}} ETA {{eta}}"));
    }

    fn advance(&self, n: u64) {
        self.bar.inc(n);
        self.line();
    }

    fn cancelled(&self) -> bool {
        self.stop.load(Ordering::Relaxed)
    }
}
