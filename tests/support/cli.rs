//! Running the `terrastream` binary from end-to-end tests.
#![allow(dead_code)] // each test binary uses part of it

use std::process::{Child, Command};

/// The binary, with a private `XDG_RUNTIME_DIR` where none is set (lavapipe warns on
/// every start without one).
pub fn terrastream() -> Command {
    let mut command = Command::new(env!("CARGO_BIN_EXE_terrastream"));
    if std::env::var_os("XDG_RUNTIME_DIR").is_none() {
        let dir = std::env::temp_dir().join(format!("terrastream-xdg-{}", std::process::id()));
        std::fs::create_dir_all(&dir).unwrap();
        command.env("XDG_RUNTIME_DIR", dir);
    }
    command
}

/// A child process killed (and reaped) when dropped.
pub struct Killed(pub Child);

impl Drop for Killed {
    fn drop(&mut self) {
        let _ = self.0.kill();
        let _ = self.0.wait();
    }
}
