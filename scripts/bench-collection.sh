#!/usr/bin/env bash
# A collection against its parts: the SRTM tile averaged to 30" and raised 3 m (the base,
# as an older survey disagrees) and a 1" crop of it (the patch: PATCH samples a side from
# pixel 600, 600; default 2400), tiled together (each as deep as it reaches), each alone,
# and together at one resolution (--priority order: the base at the patch's spacing
# everywhere). Prints tiles, bytes and the median time of RUNS runs of each, and the
# collection's ratios to the parts' sums, in wall time and in CPU time (user + system: the
# steadier of the two on a shared machine).
# Needs: gdal-bin. SRTM=path picks the DEM (default: ../shared/data/srtm/n37_w123_1arc_v3.tif).
set -euo pipefail
cd "$(dirname "$0")/.."
SRTM=${SRTM:-../shared/data/srtm/n37_w123_1arc_v3.tif}
RUNS=${RUNS:-3}
PATCH=${PATCH:-2400}
cargo build --release --quiet --bin terrastream
t=target/release/terrastream
work=$(mktemp -d)
trap 'rm -rf "$work"' EXIT INT TERM
gdalwarp -q -tr "$(echo '30/3600' | bc -l)" "$(echo '30/3600' | bc -l)" -r average -ot Float32 "$SRTM" "$work/base0.tif"
gdal_calc.py --quiet -A "$work/base0.tif" --outfile="$work/base.tif" --calc="A+3" --type=Float32 --overwrite
gdal_translate -q -srcwin 600 600 "$PATCH" "$PATCH" "$SRTM" "$work/patch.tif"
run() { # name inputs... -> "seconds tiles bytes cpu-seconds"
  local name=$1
  shift
  local TIMEFORMAT='%3R %3U %3S' tiles wall user sys
  { time "$t" -q tile -o "$work/$name.tspack" --elevation "$@" >/dev/null; } 2>"$work/time"
  read -r wall user sys <"$work/time"
  tiles=$("$t" info "$work/$name.tspack" | sed -n 's/^tiles *\([0-9]*\) addressed.*/\1/p')
  echo "$wall $tiles $(stat -c %s "$work/$name.tspack") $(echo "$user + $sys" | bc -l)"
}
median() { printf '%s\n' "$@" | sort -g | awk '{a[NR]=$1} END {print a[int((NR + 1) / 2)]}'; }
declare -A secs tiles bytes cpu
for name in collection base patch one; do secs[$name]=""; cpu[$name]=""; done
for _ in $(seq "$RUNS"); do
  for name in collection base patch one; do
    case $name in
      collection) r=$(run collection "$work/base.tif" "$work/patch.tif") ;;
      base) r=$(run base "$work/base.tif") ;;
      patch) r=$(run patch "$work/patch.tif") ;;
      one) r=$(run one "$work/base.tif" "$work/patch.tif" --priority order) ;;
    esac
    read -r s n b c <<<"$r"
    secs[$name]="${secs[$name]} $s"
    cpu[$name]="${cpu[$name]} $c"
    tiles[$name]=$n
    bytes[$name]=$b
  done
done
for name in collection base patch one; do
  # shellcheck disable=SC2086
  m=$(median ${secs[$name]})
  secs[$name]=$m
  # shellcheck disable=SC2086
  cpu[$name]=$(median ${cpu[$name]})
  printf '%-11s %8d tiles %12d bytes %8.3f s %8.3f s CPU\n' "$name" "${tiles[$name]}" "${bytes[$name]}" "$m" \
    "${cpu[$name]}"
done
ratio() { echo "$1 / ($2 + $3)" | bc -l; }
printf 'collection / (base + patch alone): tiles %.3fx, bytes %.3fx, time %.3fx (median of %d)\n' \
  "$(ratio "${tiles[collection]}" "${tiles[base]}" "${tiles[patch]}")" \
  "$(ratio "${bytes[collection]}" "${bytes[base]}" "${bytes[patch]}")" \
  "$(ratio "${secs[collection]}" "${secs[base]}" "${secs[patch]}")" "$RUNS"
printf 'collection / (base + patch alone): CPU time %.3fx (user + system, median of %d)\n' \
  "$(ratio "${cpu[collection]}" "${cpu[base]}" "${cpu[patch]}")" "$RUNS"
printf 'one resolution / collection: tiles %.1fx, bytes %.1fx, time %.1fx\n' \
  "$(echo "${tiles[one]} / ${tiles[collection]}" | bc -l)" \
  "$(echo "${bytes[one]} / ${bytes[collection]}" | bc -l)" \
  "$(echo "${secs[one]} / ${secs[collection]}" | bc -l)"
"$t" info "$work/collection.tspack" | sed -n '/^inputs/,/only where/p'
