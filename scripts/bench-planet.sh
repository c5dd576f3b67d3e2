#!/usr/bin/env bash
# A planet's tile run, projected from one measured on this machine, as the cluster Jobs run
# it (deploy/k8s/tile-job.yaml), their steps one after another:
#
#   bash scripts/bench-planet.sh
#
# - a generated mosaic of FILES GeoTIFFs of SIDE² float32 heights (default 256 of 2048²:
#   1.07e9 samples), tiled 512², in two UTM zones (32N and 33N, half each), with GDAL's
#   exact statistics in their headers, as `gdal_translate -stats` writes them (written by
#   this script, kept in $PLANET_DIR for the next run; not committed);
# - the plan: the height range from the statistics (`--require-statistics`) and the shard
#   plan (`--shards N --shard-plan-out`), from the headers;
# - N shards one after another, each given only the inputs its list names (hard links in
#   a folder of its own, as a pod fetches them), timed, with its peak memory;
# - the publish step: `merge --manifest` (the coarse levels + a manifest naming the
#   shards where they lie), and the single-archive `merge` for comparison.
# Prints samples per second, peak memory per shard, bytes each shard reads against all
# inputs, and the projection to a GLO-30-sized planet (1.7e11 land samples) on 2, 32 and
# 256 cores (see docs/BENCHMARKS.md for the assumptions). Needs GDAL's Python bindings
# (python3-gdal) and GNU time.
set -euo pipefail
cd "$(dirname "$0")/.."
FILES=${FILES:-256}
SIDE=${SIDE:-2048}
N=${N:-4}
PLANET_DIR=${PLANET_DIR:-$HOME/.cache/terrastream-planet}
command -v /usr/bin/time >/dev/null || { echo "GNU time not found (apt-get install time)"; exit 1; }
cargo build --release --quiet --bin terrastream
bin=$PWD/target/release/terrastream
work=$(mktemp -d)
trap 'rm -rf "$work"' EXIT INT TERM

inputs="$PLANET_DIR/in-$FILES-$SIDE"
if ! [ -f "$inputs/done" ]; then
  echo "writing $FILES GeoTIFFs of $SIDE² into $inputs ..."
  mkdir -p "$inputs"
  /usr/bin/python3 - "$inputs" "$FILES" "$SIDE" <<'PY'
import math, os, sys
import numpy as np
from osgeo import gdal, osr
out, files, side = sys.argv[1], int(sys.argv[2]), int(sys.argv[3])
spacing = 30.0
per_zone = files // 2
cols = 6
y, x = np.mgrid[0:side, 0:side].astype(np.float32)
driver = gdal.GetDriverByName("GTiff")
for k in range(files):
    zone = 32 if k < per_zone else 33
    i = k % per_zone
    col, row = i % cols, i // cols
    # Zone 32N's block west of 12 E (easting about 720 km at 48 N), 33N's east of it
    # (about 280 km): the two meet along the zones' boundary.
    span = side * spacing
    east = (720_000.0 - (col + 1) * span) if zone == 32 else (280_000.0 + col * span)
    north = 5_400_000.0 - row * side * spacing
    gx, gy = east + x * spacing, north - y * spacing
    h = (800 + 600 * np.sin(gx / 37_000.0) * np.cos(gy / 23_000.0) + 40 * np.sin(gx / 900.0 + gy / 1300.0)
         + (k % 7)).astype(np.float32)
    path = os.path.join(out, f"z{zone}", f"t{i:04d}.tif")
    os.makedirs(os.path.dirname(path), exist_ok=True)
    ds = driver.Create(path, side, side, 1, gdal.GDT_Float32, ["TILED=YES", "BLOCKXSIZE=512", "BLOCKYSIZE=512"])
    ds.SetGeoTransform((east, spacing, 0, north, 0, -spacing))
    srs = osr.SpatialReference()
    srs.ImportFromEPSG(32600 + zone)
    ds.SetProjection(srs.ExportToWkt())
    band = ds.GetRasterBand(1)
    band.WriteArray(h)
    band.SetStatistics(float(h.min()), float(h.max()), float(h.mean()), float(h.std()))
    ds = None
PY
  touch "$inputs/done"
fi
samples=$((FILES * SIDE * SIDE))
all_bytes=$(du -sb --exclude=done "$inputs" | awk '{print $1}')
echo "inputs: $FILES files, $samples samples, $all_bytes bytes; $N shards; $(nproc) cores"

# timed NAME CMD...: seconds and peak RSS (KiB) into $work/NAME.time.
timed() {
  local name=$1; shift
  /usr/bin/time -f "%e %M" -o "$work/$name.time" "$@" > "$work/$name.out"
}
opts=(--tile-size 256)
timed range "$bin" -q tile --elevation "$inputs" "${opts[@]}" --dry-run --height-range-out "$work/height-range" \
  --require-statistics
timed plan "$bin" -q tile --elevation "$inputs" "${opts[@]}" --shards "$N" --shard-plan-out "$work/plan" \
  --relative-to "$inputs"
echo "height range $(cat "$work/height-range") (from the statistics)"
printf '%-10s %10s %12s %16s %12s\n' step seconds "peak MiB" "bytes read" "of all"
for step in range plan; do
  read -r s m < "$work/$step.time"
  printf '%-10s %10s %12d %16s %12s\n' "$step" "$s" $((m / 1024)) "headers" ""
done
total=0
read_sum=0
for i in $(seq 0 $((N - 1))); do
  pod="$work/pod$i"
  bytes=0
  while read -r rel; do
    mkdir -p "$(dirname "$pod/in/$rel")"
    ln "$inputs/$rel" "$pod/in/$rel"
    bytes=$((bytes + $(stat -c %s "$inputs/$rel")))
  done < "$work/plan/shard-$i.txt"
  (cd "$pod" && timed "shard$i" "$bin" -q tile --elevation in "${opts[@]}" --shard "$i/$N" \
    --shard-plan "$work/plan/plan.json" --height-range "@$work/height-range" -o "$work/shards/shard-$i.tspack")
  read -r s m < "$work/shard$i.time"
  total=$(awk -v a="$total" -v b="$s" 'BEGIN { print a + b }')
  read_sum=$((read_sum + bytes))
  printf '%-10s %10s %12d %16d %11.0f%%\n' "shard $i" "$s" $((m / 1024)) "$bytes" \
    "$(awk -v a="$bytes" -v b="$all_bytes" 'BEGIN { print 100 * a / b }')"
done
timed publish "$bin" -q merge "$work/shards" -o "$work/coarse.tspack" --manifest "$work/shards/terrain.json"
timed merge "$bin" -q merge "$work/shards" -o "$work/one.tspack"
for step in publish merge; do
  read -r s m < "$work/$step.time"
  printf '%-10s %10s %12d\n' "$step" "$s" $((m / 1024))
done
read -r publish _ < "$work/publish.time"
rate=$(awk -v n="$samples" -v t="$total" 'BEGIN { printf "%.0f", n / t }')
echo
echo "shards: $samples samples in $total s of shard time: $rate samples/s on $(nproc) cores"
echo "coarse levels + manifest: $publish s ($(du -b "$work/coarse.tspack" | cut -f1) bytes)"
read_factor=$(awk -v a="$read_sum" -v b="$all_bytes" 'BEGIN { printf "%.3f", a / b }')
echo "the shards read $read_factor x the inputs' bytes (files their bands' edges cut are read by both)"
# The planet: 1.7e11 samples of 4 bytes (as these inputs), on pods of this machine's cores,
# each computing at the rate measured here and fetching its share (this run's read
# overhead included) at FETCH_MBPS MB/s, fetch and tiling not overlapped.
awk -v r="$rate" -v c="$(nproc)" -v f="${FETCH_MBPS:-100}" -v over="$read_factor" 'BEGIN {
  per_core = r / c
  for (i = 1; i <= 3; i++) {
    cores = (i == 1 ? 2 : (i == 2 ? 32 : 256))
    tile = 1.7e11 / (per_core * cores)
    fetch = 1.7e11 * 4 * over / (f * 1e6 * cores / c)
    printf "GLO-30-sized planet (1.7e11 samples) on %3d cores: tiling %6.1f min, + fetching %6.1f min = %6.1f min\n",
      cores, tile / 60, fetch / 60, (tile + fetch) / 60
  }
}'
