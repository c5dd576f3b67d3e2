//! Embeds the webplayer: the files `scripts/build-player.sh` writes to `client/web/dist`
//! (or `$TERRASTREAM_PLAYER_DIR`). Without them the server builds all the same and
//! `/view/{name}` says how to add the player.

use std::path::PathBuf;
use std::{env, fs};

/// The player's files, all needed.
const FILES: [&str; 4] = ["player.html", "terrastream_web.js", "terrastream_web_bg.wasm", "decoder.js"];

fn main() {
    println!("cargo:rerun-if-env-changed=TERRASTREAM_PLAYER_DIR");
    let manifest = PathBuf::from(env::var_os("CARGO_MANIFEST_DIR").unwrap_or_default());
    let dir = env::var_os("TERRASTREAM_PLAYER_DIR").map_or_else(|| manifest.join("../client/web/dist"), PathBuf::from);
    let found = FILES.iter().all(|f| dir.join(f).is_file());
    if found {
        for f in FILES {
            println!("cargo:rerun-if-changed={}", dir.join(f).display());
        }
    } else {
        // Watch the folder it would appear in, so that a later player build is picked up.
        let watch = if dir.is_dir() { dir.clone() } else { dir.parent().map_or(dir.clone(), PathBuf::from) };
        println!("cargo:rerun-if-changed={}", watch.display());
    }
    let mut code = String::from(
        "/// The embedded player's files: (name, bytes).\npub(crate) static FILES: &[(&str, &[u8])] = &[\n",
    );
    if found {
        for f in FILES {
            let path = fs::canonicalize(dir.join(f)).unwrap_or_else(|_| dir.join(f));
            code.push_str(&format!("    ({f:?}, include_bytes!({:?})),\n", path.display().to_string()));
        }
    }
    code.push_str("];\n");
    let out = PathBuf::from(env::var_os("OUT_DIR").unwrap_or_default()).join("player_files.rs");
    if let Err(e) = fs::write(&out, code) {
        panic!("writing {}: {e}", out.display());
    }
}
