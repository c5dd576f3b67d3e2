#!/usr/bin/env bash
# Contour tiles a second, one at a time (one core each), in one headless Chromium run:
# terrastream's contour tiles made on each request by a server that keeps nothing,
# against maplibre-contour (npm) making the same tiles from our Terrarium tiles on the
# page's thread (its DEM tiles fetched and decoded first, its isolines measured alone).
# The data's five finest zooms at 256 px, every INTERVAL metres (default 20).
# Needs: chromium, chromium-driver, nginx, npm. SRTM=path picks the DEM (default:
# ../shared/data/srtm/n37_w123_1arc_v3.tif).
set -euo pipefail
cd "$(dirname "$0")/.."
SRTM=${SRTM:-../shared/data/srtm/n37_w123_1arc_v3.tif}
npm_cache=${TERRASTREAM_NPM:-$HOME/.cache/terrastream-npm}
if ! [ -f "$npm_cache/maplibre-contour-0.1.1/package/dist/index.js" ]; then
  mkdir -p "$npm_cache/maplibre-contour-0.1.1"
  (cd "$npm_cache" && npm pack --silent maplibre-contour@0.1.1 >/dev/null \
    && tar xzf maplibre-contour-0.1.1.tgz -C maplibre-contour-0.1.1 && rm maplibre-contour-0.1.1.tgz)
fi
export TERRASTREAM_NPM=$npm_cache
cargo build --release --quiet --bin terrastream
work=$(mktemp -d)
trap 'rm -rf "$work"' EXIT INT TERM
target/release/terrastream -q tile --elevation "$SRTM" -o "$work/srtm.tspack"
BENCH_ARCHIVE=$work/srtm.tspack cargo test --release --quiet --test contour_bench -- --ignored --nocapture \
  bench_contours_against_maplibre_contour 2>&1 | grep -v '^$' | grep -v '^running\|^test \|^test result'
