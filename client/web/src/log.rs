//! `tracing` output to the browser's console: one console call per event, at the
//! console level of the event's level.

use std::io;

use tracing::{Level, Metadata};
use tracing_subscriber::fmt::MakeWriter;

/// Writes one event; sends it to the console when dropped.
pub struct ConsoleLine {
    level: Level,
    buf: Vec<u8>,
}

impl io::Write for ConsoleLine {
    fn write(&mut self, bytes: &[u8]) -> io::Result<usize> {
        self.buf.extend_from_slice(bytes);
        Ok(bytes.len())
    }

    fn flush(&mut self) -> io::Result<()> {
        Ok(())
    }
}

impl Drop for ConsoleLine {
    fn drop(&mut self) {
        let text = String::from_utf8_lossy(&self.buf);
        let text = text.trim_end();
        if text.is_empty() {
            return;
        }
        let value = wasm_bindgen::JsValue::from_str(text);
        match self.level {
            Level::ERROR => web_sys::console::error_1(&value),
            Level::WARN => web_sys::console::warn_1(&value),
            Level::INFO => web_sys::console::info_1(&value),
            _ => web_sys::console::debug_1(&value),
        }
    }
}

/// Makes [`ConsoleLine`]s.
pub struct Console;

impl<'a> MakeWriter<'a> for Console {
    type Writer = ConsoleLine;

    fn make_writer(&'a self) -> ConsoleLine {
        ConsoleLine { level: Level::INFO, buf: Vec::new() }
    }

    fn make_writer_for(&'a self, meta: &Metadata<'_>) -> ConsoleLine {
        ConsoleLine { level: *meta.level(), buf: Vec::new() }
    }
}

/// Installs the console subscriber (info and above) and a panic hook that reports to
/// the console; a second call does nothing.
pub fn init() {
    let _ = tracing_subscriber::fmt()
        .with_writer(Console)
        .with_max_level(Level::INFO)
        .without_time()
        .with_ansi(false)
        .with_target(false)
        .try_init();
}
