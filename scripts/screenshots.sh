#!/usr/bin/env bash
# Regenerates the README's viewer screenshots: the real `terrastream view` window under
# Xvfb (software Vulkan), streaming the built-in SRTM crop over HTTP from `terrastream serve`.
set -euo pipefail
cd "$(dirname "$0")/.."

as_root() { if [ "$(id -u)" = 0 ]; then "$@"; else sudo "$@"; fi; }
need=()
for pkg in xvfb imagemagick mesa-vulkan-drivers libvulkan1; do
  dpkg -s "$pkg" >/dev/null 2>&1 || need+=("$pkg")
done
if [ ${#need[@]} -gt 0 ]; then
  as_root apt-get update -qq
  as_root env DEBIAN_FRONTEND=noninteractive apt-get install -y -qq "${need[@]}"
fi

cargo build --release --locked
bin=target/release/terrastream
work=$(mktemp -d)
export XDG_RUNTIME_DIR="$work/xdg"
mkdir -m 700 "$XDG_RUNTIME_DIR"
pids=()
cleanup() { for p in "${pids[@]}"; do kill "$p" 2>/dev/null || true; done; rm -rf "$work"; }
trap cleanup EXIT

"$bin" -q demo --dir "$work/demo" --no-window >/dev/null
port=$(python3 -c 'import socket; s=socket.socket(); s.bind(("127.0.0.1", 0)); print(s.getsockname()[1])')
"$bin" -q serve "$work/demo/tamalpais.tspack" --addr "127.0.0.1:$port" &
pids+=($!)
display=:$((90 + RANDOM % 100))
Xvfb "$display" -screen 0 1280x720x24 -nolisten tcp &
pids+=($!)
sleep 2
out=docs/screenshots
mkdir -p "$out"

shot() { # name, seconds to stream, view arguments...
  local name=$1 wait=$2
  shift 2
  DISPLAY=$display "$bin" view "http://127.0.0.1:$port/tamalpais.tspack" --size 1280x720 --exit-after $((wait + 5)) "$@" &
  local viewer=$!
  sleep "$wait"
  DISPLAY=$display import -window root "$out/$name.png"
  wait "$viewer" || true
  echo "wrote $out/$name.png"
}

shot viewer-whole 12
shot viewer-grazing 12 --camera 2200,650,9200,5000,350,2500
shot viewer-lods 12 --camera 2200,650,9200,5000,350,2500 --lod-colours --wireframe
