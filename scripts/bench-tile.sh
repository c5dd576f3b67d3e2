#!/usr/bin/env bash
# Tiler benchmark: `terrastream tile` against gdal2tiles.py on the same inputs, same cores,
# in one run; wall time, peak memory (max RSS) and output size side by side, with ratios.
# Compared jobs run in turn, round after round (REPEAT rounds, default 3): the table has
# each job's fastest run, and the ratios are also given round by round, with their median.
#
#   bash scripts/bench-tile.sh [DEM.tif] [IMAGE.jpg]
#
# Defaults: the full SRTM 1" tile N37 W123 (3601 x 3601 int16) and the 10800 x 5400 global
# shaded relief from the shared data folder beside the repository. Needs gdal-bin and
# python3-gdal (apt-get install gdal-bin python3-gdal); GNU time (apt-get install time).
#
# MOSAIC=1 (the default) adds the mosaic case: the DEM cut into GRID x GRID windows of
# SIDE samples (default 8 x 8 of 448, the most a 3601-sample tile holds; 16-sample
# overlaps), the western half warped to UTM 10N and the eastern half to UTM 11N, tiled
# end to end by `terrastream tile --elevation dir/` against gdalwarp (the inputs onto one
# grid) + gdal_translate -ot Byte + gdal2tiles.py; then our peak memory for the first
# quarter of the rows against the whole (4x the area, the same width: memory follows the
# output's width by design, so that a mosaic may grow south without bound). SCALE=441
# upsamples each window 4.41x (464 -> 2048 samples, at 6.8 m) for 64 files of 2048^2. MOSAIC=only runs that case alone.
# MANY=1 (the default) adds the many-files case: the DEM's first 3584^2 samples cut into
# 64 x 64 = 4096 GeoTIFFs of 56^2 (gdal_retile.py), as a state's DEM is published in
# thousands of files, tiled from the folder against the same samples in one file (both
# onto the default transverse Mercator): the cost of many files over one; and against
# gdalwarp (onto UTM 10N at 25 m, about our spacing) + gdal_translate + gdal2tiles.
# MANY=only runs that case alone.
# GEO=1 (the default) adds the geographic-to-projected case: a GLOBE-sized geographic DEM
# (the SRTM tile stretched to 10800 x 6000 over 0-90E, 0-50N, as GLOBE tile G lies), tiled
# onto Web Mercator (--crs EPSG:3857) and on its own grid (our default for a region this
# wide), against gdal2tiles' Web Mercator profile (reprojecting) and raster profile (not):
# what reprojection costs each. GEO=only runs that case alone.
# TAP=1 warps the windows onto one lattice per zone (gdalwarp -tap), as tiles cut from one
# source usually are: inputs on the output's lattice are then copied, not resampled.
#
# gdal2tiles only tiles 8-bit rasters: its DEM job is `gdal_translate -ot Byte -scale`
# (timed with it) then gdal2tiles, so its tiles hold 256 levels where ours are lossless u16.
# Both use the raster profile (no reprojection: ours with --keep-geographic) and area
# averaging for coarser levels; the DEM is also tiled the default way, reprojected onto a
# transverse Mercator centred on it, for the cost of that.
set -euo pipefail
cd "$(dirname "$0")/.."
DEM=${1:-../shared/data/srtm/n37_w123_1arc_v3.tif}
IMAGE=${2:-../shared/data/imagery/shadedrelief.jpg}
CORES=$(nproc)
for tool in gdal2tiles.py gdal_translate /usr/bin/time; do
  command -v "$tool" >/dev/null || { echo "$tool not found (apt-get install gdal-bin python3-gdal time)"; exit 1; }
done
[ -f "$DEM" ] && [ -f "$IMAGE" ] || { echo "inputs not found: $DEM $IMAGE"; exit 1; }

cargo build --release --quiet
bin=$PWD/target/release/terrastream
work=$(mktemp -d)
trap 'rm -rf "$work"' EXIT INT TERM

# measure NAME OUTPUT CMD...: runs CMD under GNU time REPEAT times (default 3) and keeps
# the fastest run's seconds and the largest peak KiB (this machine is shared and noisy: one
# run can take twice as long as the next), and the output's bytes.
REPEAT=${REPEAT:-3}
declare -A secs peak size runs
measure_once() {
  local name=$1 out=$2; shift 2
  rm -rf "$out"
  # Every run starts with nothing left to write: the inputs just made, or the last
  # run's output, would otherwise be written back to disk during it (and wait in
  # front of a tool that syncs its output).
  sync
  # GNU time for the peak memory; the wall time from the clock in ms (time's %e has
  # 10 ms steps, 6% of the DEM job).
  local t0 t1 m s
  t0=$(date +%s%N)
  /usr/bin/time -f '%M' -o "$work/time" "$@" >"$work/log" 2>&1 || { cat "$work/log"; exit 1; }
  t1=$(date +%s%N)
  read -r m <"$work/time"
  s=$(awk -v a="$t0" -v b="$t1" 'BEGIN { printf "%.3f", (b - a) / 1e9 }')
  runs[$name]="${runs[$name]:-} $s"
  if [ -z "${secs[$name]:-}" ] || awk -v a="$s" -v b="${secs[$name]}" 'BEGIN { exit !(a < b) }'; then
    secs[$name]=$s
  fi
  [ "$m" -gt "${peak[$name]:-0}" ] && peak[$name]=$m
  size[$name]=$(du -sb "$out" | cut -f1)
}
measure() {
  for _ in $(seq "$REPEAT"); do measure_once "$@"; done
}
# rounds SLOW FAST: the ratio of two jobs measured together, round by round (each pair of
# runs minutes apart at most), and their median: steadier than the fastest runs' ratio.
rounds() {
  awk -v a="${runs[$1]}" -v b="${runs[$2]}" 'BEGIN {
    n = split(a, x, " "); split(b, y, " ")
    for (i = 1; i <= n; i++) { r[i] = x[i] / y[i]; out = out sprintf("%s%.1f", i > 1 ? ", " : "", r[i]) }
    for (i = 1; i <= n; i++) for (j = i + 1; j <= n; j++) if (r[j] < r[i]) { t = r[i]; r[i] = r[j]; r[j] = t }
    m = n % 2 ? r[(n + 1) / 2] : (r[n / 2] + r[n / 2 + 1]) / 2
    printf "%s (median %.1fx)", out, m
  }'
}
# measure_together NAME OUTPUT ARRAY [NAME OUTPUT ARRAY ...]: the jobs (each command in the
# array named) run in turn, round after round, so that a slow minute on this shared
# machine falls on all of them: their ratios are what this bench reports.
measure_together() {
  local args=("$@") i
  for _ in $(seq "$REPEAT"); do
    for ((i = 0; i < ${#args[@]}; i += 3)); do
      local -n job=${args[i + 2]}
      measure_once "${args[i]}" "${args[i + 1]}" "${job[@]}"
    done
  done
}
# Two-step jobs (translate + tile) are timed as one shell.
gdal_dem() {
  gdal_translate -q -ot Byte -scale "$DEM" "$work/dem8.tif"
  gdal2tiles.py -q -p raster -r average --processes="$CORES" "$work/dem8.tif" "$1"
}
export -f gdal_dem; export DEM work CORES

echo "inputs: $DEM ($(gdalinfo "$DEM" | awk '/^Size is/ { print $3 $4 }')), $IMAGE ($(gdalinfo "$IMAGE" | awk '/^Size is/ { print $3 $4 }')); $CORES cores"
MOSAIC=${MOSAIC:-1}
mosaic_case() {
  local grid=${GRID:-8} side=${SIDE:-448} dir="$work/mosaic" x y k zone
  local spacing; spacing=$(awk -v s="${SCALE:-100}" 'BEGIN { printf "%.4f", 30 * 100 / s }')
  mkdir -p "$dir/all" "$dir/quarter"
  for ((y = 0; y < grid; y++)); do
    for ((x = 0; x < grid; x++)); do
      k=$(printf '%02d_%02d' "$y" "$x")
      gdal_translate -q -srcwin $((x * side)) $((y * side)) $((side + 16)) $((side + 16)) \
        -outsize "${SCALE:-100}%" "${SCALE:-100}%" -r bilinear "$DEM" "$dir/w$k.tif"
      zone=$((x < grid / 2 ? 32610 : 32611))
      gdalwarp -q -t_srs "EPSG:$zone" -r bilinear -tr "$spacing" "$spacing" ${TAP:+-tap} -dstnodata -32768 -co TILED=YES \
        "$dir/w$k.tif" "$dir/all/$k.tif"
      rm "$dir/w$k.tif"
      if ((y < grid / 4)); then cp "$dir/all/$k.tif" "$dir/quarter/"; fi
    done
  done
  echo "mosaic: $(ls "$dir/all" | wc -l) GeoTIFFs in two UTM zones at $spacing m, $(du -sh "$dir/all" | cut -f1)"
  export MOSAIC_SPACING=$spacing
  local ours=("$bin" -q tile --elevation "$dir/all" -o "$work/m.tspack")
  local quarter=("$bin" -q tile --elevation "$dir/quarter" -o "$work/mq.tspack")
  local theirs=(bash -c 'gdal_mosaic "$0" "$1"' "$dir/all" "$work/m-g2t")
  measure_together ours-mosaic "$work/m.tspack" ours ours-mosaic-quarter "$work/mq.tspack" quarter \
    gdal-mosaic "$work/m-g2t" theirs
}
gdal_mosaic() {
  gdalwarp -q -t_srs EPSG:32610 -tr "$MOSAIC_SPACING" "$MOSAIC_SPACING" -r bilinear -dstnodata -32768 -multi \
    -wo NUM_THREADS=ALL_CPUS "$1"/*.tif "$work/mosaic.tif"
  gdal_translate -q -ot Byte -scale "$work/mosaic.tif" "$work/mosaic8.tif"
  gdal2tiles.py -q -p raster -r average --processes="$CORES" "$work/mosaic8.tif" "$2"
  rm -f "$work/mosaic.tif" "$work/mosaic8.tif"
}
export -f gdal_mosaic
GEO=${GEO:-1}
geo_case() {
  gdal_translate -q -outsize 10800 6000 -r bilinear -a_ullr 0 50 90 0 -a_srs EPSG:4326 -co TILED=YES \
    -co COMPRESS=DEFLATE -co PREDICTOR=2 "$DEM" "$work/globe.tif"
  gdal_translate -q -ot Byte -scale "$work/globe.tif" "$work/globe8.tif"
  local tm=("$bin" -q tile --elevation "$work/globe.tif" --crs EPSG:3857 -o "$work/g-tm.tspack")
  local geographic=("$bin" -q tile --elevation "$work/globe.tif" --keep-geographic -o "$work/g-geo.tspack")
  local mercator=(gdal2tiles.py -q -p mercator -r average --processes="$CORES" "$work/globe8.tif" "$work/g-merc")
  local raster=(gdal2tiles.py -q -p raster -r average --processes="$CORES" "$work/globe8.tif" "$work/g-raster")
  measure_together ours-geo-tm "$work/g-tm.tspack" tm ours-geo-geo "$work/g-geo.tspack" geographic \
    gdal-geo-merc "$work/g-merc" mercator gdal-geo-raster "$work/g-raster" raster
}
geo_report() {
  printf '%-40s %9s s %9s MiB
' "10800x6000 geographic: ours, onto 3857" "${secs[ours-geo-tm]}" "$((peak[ours-geo-tm] / 1024))"
  printf '%-40s %9s s %9s MiB
' "the same kept geographic: ours" "${secs[ours-geo-geo]}" "$((peak[ours-geo-geo] / 1024))"
  printf '%-40s %9s s %9s MiB
' "gdal2tiles, Web Mercator profile" "${secs[gdal-geo-merc]}" "$((peak[gdal-geo-merc] / 1024))"
  printf '%-40s %9s s %9s MiB
' "gdal2tiles, raster profile" "${secs[gdal-geo-raster]}" "$((peak[gdal-geo-raster] / 1024))"
  echo "reprojection costs ours $(awk -v a="${secs[ours-geo-tm]}" -v b="${secs[ours-geo-geo]}" 'BEGIN { printf "%.2fx", a / b }') (by round $(rounds ours-geo-tm ours-geo-geo)), gdal2tiles $(awk -v a="${secs[gdal-geo-merc]}" -v b="${secs[gdal-geo-raster]}" 'BEGIN { printf "%.2fx", a / b }'); reprojecting, ours is $(awk -v a="${secs[gdal-geo-merc]}" -v b="${secs[ours-geo-tm]}" 'BEGIN { printf "%.1fx", a / b }') gdal2tiles (by round $(rounds gdal-geo-merc ours-geo-tm)), without $(awk -v a="${secs[gdal-geo-raster]}" -v b="${secs[ours-geo-geo]}" 'BEGIN { printf "%.1fx", a / b }')"
}
if [ "$GEO" = only ]; then
  geo_case
  echo
  geo_report
  exit 0
fi
MANY=${MANY:-1}
many_case() {
  local dir="$work/many"
  mkdir -p "$dir/tiles"
  gdal_translate -q -srcwin 0 0 3584 3584 "$DEM" "$dir/one.tif"
  gdal_retile.py -q -ps 56 56 -targetDir "$dir/tiles" "$dir/one.tif"
  echo "many files: $(ls "$dir/tiles" | wc -l) GeoTIFFs of 56^2 samples, $(du -sh "$dir/tiles" | cut -f1)"
  local ours=("$bin" -q tile --elevation "$dir/tiles" -o "$work/many.tspack")
  local one=("$bin" -q tile --elevation "$dir/one.tif" -o "$work/one.tspack")
  local theirs=(bash -c 'MOSAIC_SPACING=25 gdal_mosaic "$0" "$1"' "$dir/tiles" "$work/many-g2t")
  measure_together ours-many "$work/many.tspack" ours ours-one "$work/one.tspack" one gdal-many "$work/many-g2t" theirs
}
many_report() {
  printf '%-40s %9s s %9s MiB\n' "4096 files: terrastream tile" "${secs[ours-many]}" "$((peak[ours-many] / 1024))"
  printf '%-40s %9s s %9s MiB\n' "the same samples in one file: ours" "${secs[ours-one]}" "$((peak[ours-one] / 1024))"
  printf '%-40s %9s s %9s MiB\n' "4096 files: gdalwarp + translate + g2t" "${secs[gdal-many]}" "$((peak[gdal-many] / 1024))"
  echo "4096 files against one: $(awk -v a="${secs[ours-many]}" -v b="${secs[ours-one]}" 'BEGIN { printf "%.1fx", a / b }') the time, by round $(rounds ours-many ours-one); speed-up over GDAL: $(awk -v a="${secs[gdal-many]}" -v b="${secs[ours-many]}" 'BEGIN { printf "%.1fx", a / b }'), by round $(rounds gdal-many ours-many)"
}
if [ "$MANY" = only ]; then
  many_case
  echo
  many_report
  exit 0
fi
if [ "$MOSAIC" = only ]; then
  mosaic_case
  echo
  printf '%-40s %11s %13s %14s\n' job "wall" "peak RSS" "output"
  printf '%-40s %9s s %9s MiB\n' "mosaic: terrastream tile" "${secs[ours-mosaic]}" "$((peak[ours-mosaic] / 1024))"
  printf '%-40s %9s s %9s MiB\n' "mosaic: gdalwarp + translate + gdal2tiles" "${secs[gdal-mosaic]}" "$((peak[gdal-mosaic] / 1024))"
  printf '%-40s %9s s %9s MiB\n' "mosaic, its first quarter of rows: ours" "${secs[ours-mosaic-quarter]}" "$((peak[ours-mosaic-quarter] / 1024))"
  echo "mosaic speed-up over GDAL: $(awk -v a="${secs[gdal-mosaic]}" -v b="${secs[ours-mosaic]}" 'BEGIN { printf "%.1fx", a / b }'); by round: $(rounds gdal-mosaic ours-mosaic)"
  echo "mosaic peak memory, 4x the area: $(awk -v a="${peak[ours-mosaic]}" -v b="${peak[ours-mosaic-quarter]}" 'BEGIN { printf "%.2fx", a / b }')"
  exit 0
fi
# One large DEM: the DEM upsampled to LARGE^2 (default 8100^2 = 65.6 M samples), written as
# DEMs are published (tiled, Deflate + horizontal predictor, int16).
LARGE=${LARGE:-8100}
gdal_translate -q -outsize "$LARGE" "$LARGE" -r bilinear -co TILED=YES -co COMPRESS=DEFLATE -co PREDICTOR=2 \
  "$DEM" "$work/large.tif"
# The DEMs, ours and GDAL's, in turn (their ratios, and the samples/s across the sizes).
ours_dem=("$bin" -q tile --elevation "$DEM" --keep-geographic -o "$work/dem.tspack")
gdal_dem=(bash -c 'gdal_dem "$0"' "$work/dem-g2t")
ours_large=("$bin" -q tile --elevation "$work/large.tif" --keep-geographic -o "$work/l.tspack")
gdal_large=(bash -c 'DEM=$1 gdal_dem "$0"' "$work/l-g2t" "$work/large.tif")
measure_together ours-dem "$work/dem.tspack" ours_dem gdal-dem "$work/dem-g2t" gdal_dem \
  ours-dem-large "$work/l.tspack" ours_large gdal-dem-large "$work/l-g2t" gdal_large
measure ours-dem-tm "$work/dem-tm.tspack" "$bin" -q tile --elevation "$DEM" -o "$work/dem-tm.tspack"
ours_png=("$bin" -q tile --texture "$IMAGE" --texture-format png -o "$work/img.tspack")
gdal_png=(gdal2tiles.py -q -p raster -r average --processes="$CORES" "$IMAGE" "$work/img-g2t")
measure_together ours-img-png "$work/img.tspack" ours_png gdal-img-png "$work/img-g2t" gdal_png
measure ours-img-jpeg "$work/imgj.tspack" "$bin" -q tile --texture "$IMAGE" --texture-format jpeg -o "$work/imgj.tspack"

# Memory against input size: the same DEM a quarter as tall, and twice as tall (mirrored).
gdal_translate -q -srcwin 0 0 3601 900 "$DEM" "$work/quarter.tif"
gdal_translate -q -outsize 100% 200% -r near "$DEM" "$work/double.tif"
gdal_translate -q -co TILED=YES -co COMPRESS=DEFLATE "$IMAGE" "$work/image-tiled.tif"
measure ours-dem-quarter "$work/q.tspack" "$bin" -q tile --elevation "$work/quarter.tif" --keep-geographic -o "$work/q.tspack"
measure ours-dem-double "$work/d.tspack" "$bin" -q tile --elevation "$work/double.tif" --keep-geographic -o "$work/d.tspack"
measure ours-img-tiff "$work/it.tspack" "$bin" -q tile --texture "$work/image-tiled.tif" -o "$work/it.tspack"

row() { printf '%-40s %9s s %9s MiB %10s MiB\n' "$1" "${secs[$2]}" "$((peak[$2] / 1024))" "$(awk -v b="${size[$2]}" 'BEGIN { printf "%.1f", b / 1048576 }')"; }
ratio() { awk -v a="${secs[$1]}" -v b="${secs[$2]}" 'BEGIN { printf "%.1fx", a / b }'; }
echo
printf '%-40s %11s %13s %14s\n' job "wall" "peak RSS" "output"
row "DEM: terrastream tile (u16, lossless)" ours-dem
row "DEM onto a transverse Mercator (default)" ours-dem-tm
row "DEM: gdal_translate -ot Byte + gdal2tiles" gdal-dem
row "image: terrastream tile (PNG)" ours-img-png
row "image: terrastream tile (JPEG)" ours-img-jpeg
row "image: gdal2tiles (PNG)" gdal-img-png
row "DEM 3601x900 (quarter height)" ours-dem-quarter
row "DEM 3601x7202 (double height)" ours-dem-double
row "image as a tiled GeoTIFF (streamed)" ours-img-tiff
row "DEM ${LARGE}^2 Deflate+predictor: ours" ours-dem-large
row "DEM ${LARGE}^2: translate + gdal2tiles" gdal-dem-large
echo
echo "speed-up over gdal2tiles: DEM $(ratio gdal-dem ours-dem), large DEM $(ratio gdal-dem-large ours-dem-large), image (PNG) $(ratio gdal-img-png ours-img-png)"
echo "  by round: DEM $(rounds gdal-dem ours-dem); large DEM $(rounds gdal-dem-large ours-dem-large); image $(rounds gdal-img-png ours-img-png)"
echo "DEM reprojected onto its transverse Mercator (the default; gdal2tiles does not reproject here): $(ratio ours-dem-tm ours-dem) the time kept geographic, $(ratio gdal-dem ours-dem-tm) faster than gdal2tiles"
dem_samples=$(gdalinfo "$DEM" | awk '/^Size is/ { gsub(",", ""); print $3 * $4 }')
echo "samples/s: DEM $(awk -v n="$dem_samples" -v s="${secs[ours-dem]}" 'BEGIN { printf "%.0f M", n / s / 1e6 }'), large DEM $(awk -v n="$LARGE" -v s="${secs[ours-dem-large]}" 'BEGIN { printf "%.0f M", n * n / s / 1e6 }'); DEM / large DEM: $(awk -v n="$dem_samples" -v m="$LARGE" -v a="${secs[ours-dem]}" -v b="${secs[ours-dem-large]}" 'BEGIN { printf "%.2fx", (n / a) / (m * m / b) }')"
echo "peak memory, DEM double / quarter height (8x the samples): $(awk -v a="${peak[ours-dem-double]}" -v b="${peak[ours-dem-quarter]}" 'BEGIN { printf "%.2fx", a / b }')"
if [ "$MOSAIC" != 0 ]; then
  mosaic_case
  row "mosaic: terrastream tile" ours-mosaic
  row "mosaic: gdalwarp + translate + gdal2tiles" gdal-mosaic
  row "mosaic, its first quarter of rows: ours" ours-mosaic-quarter
  echo "mosaic speed-up over GDAL: $(ratio gdal-mosaic ours-mosaic), by round $(rounds gdal-mosaic ours-mosaic); peak memory for 4x the area: $(awk -v a="${peak[ours-mosaic]}" -v b="${peak[ours-mosaic-quarter]}" 'BEGIN { printf "%.2fx", a / b }')"
fi
if [ "$MANY" != 0 ]; then
  many_case
  many_report
fi
if [ "$GEO" != 0 ]; then
  geo_case
  geo_report
fi
echo "peak memory, image streamed from TIFF / decoded JPEG: $(awk -v a="${peak[ours-img-tiff]}" -v b="${peak[ours-img-png]}" 'BEGIN { printf "%.2fx", a / b }')"
