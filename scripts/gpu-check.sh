#!/usr/bin/env bash
# The checks that need a GPU machine, prepared here and run there in one go (the lent
# machine's time is short: about 15 minutes a session, starts included).
#
#   scripts/gpu-check.sh prepare   here: fills .gpu/ (git-ignored, under 64 MiB) with the
#                                  stripped release binary (xz), the Vulkan loaders
#                                  (Debian's, unpacked there), the renderer's archive and
#                                  the tiler's input
#   scripts/gpu-check.sh run       there (carry .gpu): the renderer's frame times and
#                                  ratios at 1920x1080 and 3840x2160, and the tiler's time
#                                  at 1, 2, 4, 8 and 16 threads (same bytes at each), into
#                                  $OUT (or .gpu/out here); ends well inside 10 minutes
#
# The device call: command "bash scripts/gpu-check.sh run", carry [".gpu"], timeout_s
# 540. There it needs only bash, coreutils, awk and xz. Run here (`run` without a GPU), it measures lavapipe with smaller sizes
# (SMALL=1 forces that), which checks the script itself.
#
# What it measures (docs/BENCHMARKS.md says what each number is):
# - `bench render` over the SRTM tile with a colour-relief imagery layer at twice its
#   resolution: lit / baseline, globe / plate, the atmosphere's share, streaming /
#   resident, at both sizes;
# - `tile` of a 12288 x 12288 DEM (151 M samples, 7 m, UTM 10N, Deflate + predictor):
#   T(n) and T(1) / T(n), two rounds, and whether every thread count wrote the same bytes.
#
# Needs here: gdal-bin, xz-utils, apt-get (for the loaders). SRTM=path picks the DEM
# (default: ../shared/data/srtm/n37_w123_1arc_v3.tif).
set -euo pipefail
cd "$(dirname "$0")/.."
dir=.gpu

prepare() {
  local srtm=${SRTM:-../shared/data/srtm/n37_w123_1arc_v3.tif}
  mkdir -p "$dir/debs"
  cargo build --release --quiet --locked --bin terrastream
  strip -o "$dir/terrastream" target/release/terrastream
  xz -T0 -6 -f "$dir/terrastream"
  local t=target/release/terrastream work
  work=$(mktemp -d)
  trap 'rm -rf "$work"' RETURN
  # The renderer's archive: heights above EGM96 and a colour relief at twice their
  # resolution (so that the texture's LODs are deeper than the heights').
  printf '%s\n' "-50 40 70 140" "0 60 110 60" "300 150 160 80" "600 190 170 120" "800 240 240 240" >"$work/ramp.txt"
  gdaldem color-relief -q "$srtm" "$work/ramp.txt" "$work/relief.tif"
  gdal_translate -q -outsize 200% 200% -r bilinear -co TILED=YES "$work/relief.tif" "$work/relief2x.tif"
  "$t" -q tile --elevation "$srtm" --vertical-datum 5773 --texture "$work/relief2x.tif" --texture-format jpeg \
    -o "$dir/render.tspack"
  # The tiler's input: the tile in UTM 10N at 7 m, its middle 12288 x 12288.
  gdalwarp -q -t_srs EPSG:32610 -tr 7 7 -r bilinear -ot Int16 "$srtm" "$work/utm.tif"
  local size
  size=$(gdalinfo "$work/utm.tif" | sed -n 's/^Size is \([0-9]*\), \([0-9]*\)/\1 \2/p')
  read -r w h <<<"$size"
  gdal_translate -q -srcwin $(((w - 12288) / 2)) $(((h - 12288) / 2)) 12288 12288 -co TILED=YES \
    -co COMPRESS=DEFLATE -co PREDICTOR=2 -co BIGTIFF=NO "$work/utm.tif" "$dir/dem.tif"
  # Debian's Vulkan and EGL loaders, for a machine that has the driver but not them.
  local o=(-oAPT::Architecture=amd64 -oAPT::Architectures=amd64 -oDir::State::Lists="$work/lists")
  mkdir -p "$work/lists/partial"
  apt-get "${o[@]}" update >/dev/null
  (cd "$dir/debs" && apt-get "${o[@]}" download libvulkan1 libegl1 libglvnd0 >/dev/null)
  du -sh "$dir"/* | sed 's/^/prepared: /'
  echo "prepared: $(du -sm "$dir" | cut -f1) MiB in $dir (the device takes 64 MiB with the checkout)"
}

run() {
  local out=${OUT:-$dir/out} t=/tmp/terrastream-gpu
  mkdir -p "$out"
  # A GPU machine: its driver's Vulkan, through the carried loaders where it has none.
  local gpu=0
  if [[ -e /dev/nvidia0 || -d /usr/local/nvidia ]]; then
    gpu=1
    if ! ldconfig -p | grep -q libvulkan.so.1; then
      for f in "$dir"/debs/*.deb; do dpkg -x "$f" /; done
      ldconfig
    fi
    [[ -f /usr/local/nvidia/share/vulkan/icd.d/nvidia_icd.json ]] &&
      export VK_DRIVER_FILES=/usr/local/nvidia/share/vulkan/icd.d/nvidia_icd.json
  fi
  export WGPU_BACKEND=vulkan
  xz -dc "$dir/terrastream.xz" >"$t"
  chmod +x "$t"
  local small=${SMALL:-$((1 - gpu))}
  local sizes=("1920x1080 60" "3840x2160 30") threads=(1 2 4 8 16)
  if [[ $small == 1 ]]; then
    sizes=("640x360 20")
    threads=(1 2)
  fi
  {
    echo "== $(date -u +%FT%TZ) on $(nproc) cores; gpu=$gpu"
    command -v nvidia-smi >/dev/null && nvidia-smi --query-gpu=name,driver_version --format=csv,noheader
    for s in "${sizes[@]}"; do
      read -r size frames <<<"$s"
      echo "== bench render $size, $frames frames"
      "$t" bench render --archive "$dir/render.tspack" --size "$size" --frames "$frames" 2>&1
    done
    echo "== tile: T(n) of $(basename "$dir/dem.tif"), two rounds"
    local first="" base
    for round in 1 2; do
      for n in "${threads[@]}"; do
        local start end secs sum
        start=$(date +%s.%N)
        RAYON_NUM_THREADS=$n "$t" -q tile --elevation "$dir/dem.tif" -o "/tmp/gpu-check-$n.tspack" >/dev/null
        end=$(date +%s.%N)
        secs=$(awk -v a="$start" -v b="$end" 'BEGIN { printf "%.3f", b - a }')
        sum=$(sha256sum "/tmp/gpu-check-$n.tspack" | cut -c1-16)
        [[ -z $first ]] && first=$sum
        [[ $n == 1 ]] && base=$secs
        printf 'round %d: %2d threads %6.3f s  T(1)/T(n) %5.2f  %s\n' "$round" "$n" "$secs" \
          "$(awk -v a="$base" -v b="$secs" 'BEGIN { print a / b }')" \
          "$([[ $sum == "$first" ]] && echo "same bytes" || echo "DIFFERENT BYTES $sum")"
        rm -f "/tmp/gpu-check-$n.tspack"
      done
    done
  } 2>&1 | tee "$out/gpu-check.txt"
}

case ${1:-} in
  prepare) prepare ;;
  run) run ;;
  *)
    sed -n '2,16p' "$0"
    exit 2
    ;;
esac
