#!/usr/bin/env bash
# Sharding, merging and updating, measured in one run on one machine:
#
#   bash scripts/bench-merge.sh [DEM.tif]
#
# - merge throughput: `merge` of the N shards of a run (tiles/s, MB/s) against `cp` of the
#   same bytes;
# - shard + merge against one run: N shards at once (each uses every core), then the merge,
#   against a single `tile` (about 1x on 2 cores: the point is the overhead);
# - update cost: `update` of a window of UPDATE_PERCENT % of the area (a square) against
#   the full tile run of the base, in place and into a copy (`-o`).
#
# Default input: the SRTM 1" tile from the shared data folder beside the repository,
# warped to UTM 10N (gdalwarp) so that updates have a projected grid. Needs gdal-bin.
set -euo pipefail
cd "$(dirname "$0")/.."
DEM=${1:-../shared/data/srtm/n37_w123_1arc_v3.tif}
N=${N:-4}
UPDATE_PERCENT=${UPDATE_PERCENT:-1}
REPEAT=${REPEAT:-3}
# Output spacing of the warped DEM: 10 m makes about 110 M samples of the 1" tile.
RES=${RES:-10}
command -v gdalwarp >/dev/null || { echo "gdalwarp not found (apt-get install gdal-bin)"; exit 1; }
[ -f "$DEM" ] || { echo "input not found: $DEM"; exit 1; }
cargo build --release --quiet
bin=$PWD/target/release/terrastream
work=$(mktemp -d)
trap 'rm -rf "$work"' EXIT INT TERM

gdalwarp -q -t_srs EPSG:32610 -tr "$RES" "$RES" -r bilinear -dstnodata -32768 -co TILED=YES "$DEM" "$work/dem.tif"
read -r W H < <(gdalinfo "$work/dem.tif" | awk '/^Size is/ { gsub(",", ""); print $3, $4 }')
# The update: a square of UPDATE_PERCENT % of the area, in the middle, heights raised 5 %.
side=$(awk -v w="$W" -v h="$H" -v p="$UPDATE_PERCENT" 'BEGIN { printf "%d", sqrt(w * h * p / 100) }')
gdal_translate -q -srcwin $(((W - side) / 2)) $(((H - side) / 2)) "$side" "$side" -scale 0 1000 0 1050 \
  -ot Float32 "$work/dem.tif" "$work/patch.tif"
echo "input: $W x $H samples at $RES m (UTM 10N); update: $side x $side samples ($UPDATE_PERCENT % of the area); $N shards; $(nproc) cores"

# best NAME CMD...: the fastest of REPEAT runs, in seconds; a function NAME_setup, if
# there is one, runs untimed before each.
declare -A secs
best() {
  local name=$1 b="" t0 t1 s; shift
  for _ in $(seq "$REPEAT"); do
    if declare -F "${name}_setup" >/dev/null; then "${name}_setup"; fi
    t0=$(date +%s%N)
    "$@" >/dev/null 2>&1 || { "$@"; exit 1; }
    t1=$(date +%s%N)
    s=$(awk -v a="$t0" -v b="$t1" 'BEGIN { printf "%.3f", (b - a) / 1e9 }')
    if [ -z "$b" ] || awk -v a="$s" -v b="$b" 'BEGIN { exit !(a < b) }'; then b=$s; fi
  done
  secs[$name]=$b
}
single() { rm -f "$work/single.tspack"; "$bin" -q tile --elevation "$work/dem.tif" -o "$work/single.tspack"; }
# The shards of one run: a plan step finds the height range once (`--dry-run`), then the N
# shards start together, each given it (`--height-range`: no pass of its own).
shards() {
  rm -rf "$work/shards"; mkdir -p "$work/shards"
  local pids=() i range
  range=$("$bin" -q tile --elevation "$work/dem.tif" --dry-run | awk '/^heights/ { sub(",", "", $4); print $2 "," $4 }')
  for ((i = 0; i < N; i++)); do
    "$bin" -q tile --elevation "$work/dem.tif" --shard "$i/$N" --height-range="$range" \
      -o "$work/shards/shard-$i.tspack" & pids+=($!)
  done
  for p in "${pids[@]}"; do wait "$p"; done
}
merge() { rm -f "$work/merged.tspack"; "$bin" -q merge "$work/shards" -o "$work/merged.tspack"; }
# Published as they are: the levels above the split LOD into a coarse archive + a manifest.
publish() { rm -rf "$work/pub"; mkdir -p "$work/pub"; "$bin" -q merge "$work/shards" -o "$work/pub/coarse.tspack" --manifest "$work/pub/t.json"; }
copy() { rm -f "$work/copy.bin"; cat "$work"/shards/*.tspack > "$work/copy.bin"; sync -f "$work/copy.bin"; }
update() { rm -f "$work/updated.tspack"; "$bin" -q update "$work/single.tspack" --elevation "$work/patch.tif" -o "$work/updated.tspack"; }
# In place (FORMAT.md §7.1): each run updates a fresh copy of the base, copied untimed.
inplace_setup() { cp "$work/single.tspack" "$work/inplace.tspack"; sync -f "$work/inplace.tspack"; }
inplace() { "$bin" -q update "$work/inplace.tspack" --elevation "$work/patch.tif" --in-place; }
export -f single shards merge publish copy update inplace_setup inplace; export bin work N

best single single
best shards shards
best merge merge
best publish publish
best copy copy
best update update
best inplace inplace
cmp -s "$work/single.tspack" "$work/merged.tspack" && same="byte-identical" || same="DIFFERENT"
bytes=$(cat "$work"/shards/*.tspack | wc -c)
tiles=$("$bin" info "$work/merged.tspack" --json | awk -F: '/"tile_entries"/ { gsub(/[ ,]/, "", $2); print $2; exit }')
printf '\n%-44s %9s\n' job wall
printf '%-44s %7s s\n' "one tile run" "${secs[single]}" "plan + $N shards at once" "${secs[shards]}" \
  "merge of the $N shards" "${secs[merge]}" "merge --manifest (coarse archive + manifest)" "${secs[publish]}" \
  "cp of the shards' bytes" "${secs[copy]}" \
  "update of $UPDATE_PERCENT % of the area, -o a copy" "${secs[update]}" \
  "update of $UPDATE_PERCENT % of the area, --in-place" "${secs[inplace]}"
echo
echo "merged archive: $same to the single run's; $tiles tiles, $((bytes / 1048576)) MiB of shards"
awk -v m="${secs[merge]}" -v c="${secs[copy]}" -v t="$tiles" -v b="$bytes" 'BEGIN {
  printf "merge throughput: %.0f tiles/s, %.0f MB/s; against cp: %.2fx\n", t / m, b / m / 1e6, c / m }'
awk -v s="${secs[shards]}" -v m="${secs[merge]}" -v o="${secs[single]}" 'BEGIN {
  printf "shards + merge against one run: %.2fx the time (the merge alone: %.0f %% of one run)\n", (s + m) / o, 100 * m / o }'
awk -v p="${secs[publish]}" -v m="${secs[merge]}" -v s="${secs[shards]}" -v o="${secs[single]}" 'BEGIN {
  printf "merge --manifest: %.2fx the merge; shards + merge --manifest against one run: %.2fx\n", p / m, (s + p) / o }'
awk -v u="${secs[update]}" -v i="${secs[inplace]}" -v o="${secs[single]}" -v p="$UPDATE_PERCENT" 'BEGIN {
  printf "update of %s %% of the area: in place %.1f %% of a full tile run; into a copy %.1f %%\n", p, 100 * i / o, 100 * u / o }'
base_len=$(stat -c %s "$work/single.tspack")
grown=$(($(stat -c %s "$work/inplace.tspack") - base_len))
awk -v g="$grown" -v b="$base_len" 'BEGIN { printf "in place, the archive grew by %d bytes (%.2f %%)\n", g, 100 * g / b }'
"$bin" verify "$work/inplace.tspack" >/dev/null && echo "updated in place: verify ok"
