#!/usr/bin/env bash
# A collection against its parts, in two cases. The patch is a 1" crop of the SRTM tile
# (PATCH samples a side from pixel 600, 600; default 2400) in both.
# - small: the base is the SRTM tile averaged to 30" and raised 3 m (as an older survey
#   disagrees): one degree, mostly under the patch. Also tiled together at one resolution
#   (--priority order: the base at the patch's spacing everywhere).
# - wide: a 26 x 15 degree base at 30" around it (the shaded-relief world picture's grey
#   as heights, the small base laid over it): a planet or national base and one survey.
#   Also tiled with --lod0 finest (LOD 0 at the patch's 1", the base upsampled to 16").
# Prints tiles, bytes and the median time of RUNS runs of each, and the collection's
# ratios to the parts' sums, in wall time and in CPU time (user + system: the steadier
# of the two on a shared machine). CASES="small wide" picks the cases.
# Needs: gdal-bin. SRTM=path picks the DEM (default: ../shared/data/srtm/n37_w123_1arc_v3.tif),
# WORLD=path the world picture (default: ../shared/data/imagery/shadedrelief.jpg).
set -euo pipefail
cd "$(dirname "$0")/.."
SRTM=${SRTM:-../shared/data/srtm/n37_w123_1arc_v3.tif}
WORLD=${WORLD:-../shared/data/imagery/shadedrelief.jpg}
RUNS=${RUNS:-3}
PATCH=${PATCH:-2400}
CASES=${CASES:-small wide}
cargo build --release --quiet --bin terrastream
t=target/release/terrastream
work=$(mktemp -d)
trap 'rm -rf "$work"' EXIT INT TERM
arc30=$(echo '30/3600' | bc -l)
gdalwarp -q -tr "$arc30" "$arc30" -r average -ot Float32 "$SRTM" "$work/base0.tif"
gdal_calc.py --quiet -A "$work/base0.tif" --outfile="$work/small.tif" --calc="A+3" --type=Float32 --overwrite
gdal_translate -q -srcwin 600 600 "$PATCH" "$PATCH" "$SRTM" "$work/patch.tif"
if [[ " $CASES " == *" wide "* ]]; then
  gdal_translate -q -b 1 -ot Float32 -scale 0 255 0 2550 -a_srs EPSG:4326 -a_ullr -180 90 180 -90 \
    "$WORLD" "$work/world.tif"
  gdalwarp -q -te -126 30 -100 45 -tr "$arc30" "$arc30" -r bilinear -co COMPRESS=DEFLATE -co TILED=YES \
    "$work/world.tif" "$work/small.tif" "$work/wide.tif"
fi
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
ratio() { echo "$1 / ($2 + $3)" | bc -l; }
for case in $CASES; do
  base="$work/$case.tif"
  case $case in
    small) names="collection base patch one" ;;
    wide) names="collection base patch finest" ;;
    *) echo "unknown case $case" >&2; exit 2 ;;
  esac
  declare -A secs=() tiles=() bytes=() cpu=()
  for name in $names; do secs[$name]=""; cpu[$name]=""; done
  for _ in $(seq "$RUNS"); do
    for name in $names; do
      case $name in
        collection) r=$(run collection "$base" "$work/patch.tif") ;;
        base) r=$(run base "$base") ;;
        patch) r=$(run patch "$work/patch.tif") ;;
        one) r=$(run one "$base" "$work/patch.tif" --priority order) ;;
        finest) r=$(run finest "$base" "$work/patch.tif" --lod0 finest) ;;
      esac
      read -r s n b c <<<"$r"
      secs[$name]="${secs[$name]} $s"
      cpu[$name]="${cpu[$name]} $c"
      tiles[$name]=$n
      bytes[$name]=$b
    done
  done
  echo "== $case base: $(gdalinfo "$base" | sed -n 's/^Size is //p') samples"
  for name in $names; do
    # shellcheck disable=SC2086
    secs[$name]=$(median ${secs[$name]})
    # shellcheck disable=SC2086
    cpu[$name]=$(median ${cpu[$name]})
    printf '%-11s %8d tiles %12d bytes %8.3f s %8.3f s CPU\n' "$name" "${tiles[$name]}" "${bytes[$name]}" \
      "${secs[$name]}" "${cpu[$name]}"
  done
  printf 'collection / (base + patch alone): tiles %.3fx, bytes %.3fx, time %.3fx (median of %d)\n' \
    "$(ratio "${tiles[collection]}" "${tiles[base]}" "${tiles[patch]}")" \
    "$(ratio "${bytes[collection]}" "${bytes[base]}" "${bytes[patch]}")" \
    "$(ratio "${secs[collection]}" "${secs[base]}" "${secs[patch]}")" "$RUNS"
  printf 'collection / (base + patch alone): CPU time %.3fx (user + system, median of %d)\n' \
    "$(ratio "${cpu[collection]}" "${cpu[base]}" "${cpu[patch]}")" "$RUNS"
  other=one
  [[ $case == wide ]] && other=finest
  printf '%s / collection: tiles %.2fx, bytes %.2fx, time %.2fx\n' "$other" \
    "$(echo "${tiles[$other]} / ${tiles[collection]}" | bc -l)" \
    "$(echo "${bytes[$other]} / ${bytes[collection]}" | bc -l)" \
    "$(echo "${secs[$other]} / ${secs[collection]}" | bc -l)"
  "$t" info "$work/collection.tspack" | sed -n '/^inputs/,/only where/p'
  unset secs tiles bytes cpu
done
