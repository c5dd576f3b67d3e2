#!/usr/bin/env bash
# What converting heights between vertical datums costs:
# - a tile run: the SRTM tile cut in two halves by GDAL, the east half made ellipsoidal
#   (gdalwarp to EPSG:4979); the two tiled as they are (the east half converted to EGM96)
#   and with --vertical-datum naming one datum for both (nothing converted): the same
#   files onto the same grid, RUNS times each, alternating; the medians' ratio;
# - a quantized-mesh tile: `bench mesh` on the SRTM tile above EGM96 (the share of a
#   tile's sampling, meshing and encoding that lifting its heights by N takes).
# Needs: gdal-bin, proj-data. SRTM=path picks the DEM (default:
# ../shared/data/srtm/n37_w123_1arc_v3.tif).
set -euo pipefail
cd "$(dirname "$0")/.."
SRTM=${SRTM:-../shared/data/srtm/n37_w123_1arc_v3.tif}
RUNS=${RUNS:-5}
cargo build --release --quiet --bin terrastream
t=target/release/terrastream
work=$(mktemp -d)
trap 'rm -rf "$work"' EXIT INT TERM
read -r w h < <(gdalinfo "$SRTM" | sed -n 's/^Size is \([0-9]*\), \([0-9]*\)/\1 \2/p')
half=$((w / 2))
gdal_translate -q -srcwin 0 0 $((half + 8)) "$h" -a_srs EPSG:4326+5773 -ot Float32 "$SRTM" "$work/west.tif"
gdal_translate -q -srcwin "$half" 0 $((w - half)) "$h" -a_srs EPSG:4326+5773 -ot Float32 "$SRTM" "$work/east-h.tif"
gdalwarp -q -s_srs EPSG:4326+5773 -t_srs EPSG:4979 "$work/east-h.tif" "$work/east.tif"
run() { # inputs... -> seconds
  local start end
  start=$(date +%s.%N)
  "$t" -q tile -o "$work/out.tspack" --storage f32 --elevation "$@" >/dev/null
  end=$(date +%s.%N)
  echo "$end - $start" | bc -l
}
same=() converted=()
for _ in $(seq "$RUNS"); do
  same+=("$(run "$work/west.tif" "$work/east.tif" --vertical-datum 5773)")
  converted+=("$(run "$work/west.tif" "$work/east.tif")")
done
median() { printf '%s\n' "$@" | sort -g | awk '{a[NR]=$1} END {print a[int((NR + 1) / 2)]}'; }
ms=$(median "${same[@]}")
mc=$(median "${converted[@]}")
printf 'tile run, %s: one datum %.3f s, half converted %.3f s: %.3fx (median of %d)\n' \
  "$(basename "$SRTM")" "$ms" "$mc" "$(echo "$mc / $ms" | bc -l)" "$RUNS"
"$t" -q tile --elevation "$SRTM" -o "$work/srtm.tspack" --vertical-datum 5773
"$t" bench mesh "$work/srtm.tspack" | tail -1
