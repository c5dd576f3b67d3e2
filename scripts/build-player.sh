#!/usr/bin/env bash
# Builds the webplayer into client/web/dist: the client crate compiled to wasm32, its
# wasm-bindgen glue and the page. `terrastream serve` embeds that folder when it is
# built afterwards (server/build.rs); any static host can serve it as it is.
#
# Installs what it needs: the wasm32 target (rustup) and the wasm-bindgen CLI of the
# version Cargo.lock pins (cargo install, once).
set -euo pipefail
cd "$(dirname "$0")/.."

version=$(awk '/^name = "wasm-bindgen"$/ { getline; gsub(/version = |"/, ""); print; exit }' Cargo.lock)
if [ -z "$version" ]; then
    echo "build-player: no wasm-bindgen in Cargo.lock" >&2
    exit 1
fi
if ! rustup target list --installed 2>/dev/null | grep -qx wasm32-unknown-unknown; then
    rustup target add wasm32-unknown-unknown
fi
if ! wasm-bindgen --version 2>/dev/null | grep -q " $version\$"; then
    echo "build-player: installing wasm-bindgen-cli $version"
    # Not --locked: its lock file pins crates newer than some registry mirrors carry.
    cargo install wasm-bindgen-cli --version "$version"
fi

cargo build -p terrastream-web --target wasm32-unknown-unknown --profile web --locked
target_dir=$(cargo metadata --format-version 1 --no-deps | python3 -c 'import json,sys; print(json.load(sys.stdin)["target_directory"])')

out=client/web/dist
rm -rf "$out.new"
mkdir -p "$out.new"
wasm-bindgen --target web --no-typescript --remove-name-section --remove-producers-section --out-dir "$out.new" \
    "$target_dir/wasm32-unknown-unknown/web/terrastream_web.wasm"
cp client/web/static/* "$out.new/"
# Replace the old build in one step: a server build never sees half of one.
rm -rf "$out.old"
if [ -d "$out" ]; then mv "$out" "$out.old"; fi
mv "$out.new" "$out"
rm -rf "$out.old"

wasm="$out/terrastream_web_bg.wasm"
printf 'build-player: %s: %d KiB, %d KiB gzipped\n' "$wasm" \
    $(( $(stat -c %s "$wasm") / 1024 )) $(( $(gzip -9c "$wasm" | wc -c) / 1024 ))
