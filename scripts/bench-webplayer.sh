#!/usr/bin/env bash
# The webplayer over emulated links, in headless Chromium (the shaper of `bench stream`
# in front of the server, for the archive's requests): first frame, first complete frame,
# and frame time p50/p99 while streaming against the same with every tile resident, in
# the same browser run.
#
#   bash scripts/bench-webplayer.sh            # WebGPU (SwiftShader's Vulkan)
#   BACKEND=webgl2 bash scripts/bench-webplayer.sh
#   WORKERS=0 bash scripts/bench-webplayer.sh   # decode on the page's thread
#
# Needs chromium and chromium-driver (apt-get install chromium chromium-driver).
set -euo pipefail
cd "$(dirname "$0")/.."
bash scripts/build-player.sh >/dev/null
cargo build --release --quiet
cargo test --release --quiet --test webplayer -- --ignored --nocapture --test-threads 1 \
  bench_webplayer_over_emulated_links 2>&1 | grep -v '^$' | grep -v '^running\|^test \|^test result'
