#!/usr/bin/env bash
# Tiles and packs the committed inputs through every writer path (the built-in sample,
# `tile` with each texture format, `pack` of original, XYZ, PMTiles and MBTiles-free
# round trips, `export`) and prints the sha256 of each output, sorted by name. Two builds
# that write the same bytes print the same list: run it before and after a refactor.
#
#   scripts/archive-hashes.sh [OUT_DIR]        (TERRASTREAM=path/to/binary to pick a build)
set -euo pipefail
cd "$(dirname "$0")/.."
bin=${TERRASTREAM:-target/debug/terrastream}
out=${1:-target/archive-hashes}
[ -x "$bin" ] || cargo build --locked -q --bin terrastream
rm -rf "$out" && mkdir -p "$out"
ts() { "$bin" -q "$@" >/dev/null; }

ts demo --dir "$out/demo" --no-window >/dev/null 2>&1
cp "$out/demo/sample.tspack" "$out/demo/tamalpais.tspack" "$out/"
dem=packer/pack/data/srtm-tamalpais-320-public-domain.tif
texture=$out/demo/sample/textures/LOD0/0_0.png
ts tile --elevation tests/data/srtm-tamalpais-150x100-strips-int16-public-domain.tif -o "$out/strips.tspack"
ts tile --elevation tests/data/srtm-tamalpais-150x100-tiled-float32-public-domain.tif -o "$out/tiled.tspack"
ts tile --elevation "$dem" -o "$out/tile-dem.tspack"
# The sample's square tile cannot drape the DEM (its transverse Mercator grid is not
# square): each texture format is written from it alone.
for f in png jpeg webp bc1 bc7; do
    ts tile --texture "$texture" --pixel-size 10 --texture-format "$f" --texture-tile-size 32 -o "$out/tile-$f.tspack"
done
ts extract "$out/sample.tspack" --layout original -o "$out/original"
ts pack "$out/original" -o "$out/repack-original.tspack"
ts extract "$out/tile-png.tspack" --layout xyz -o "$out/xyz"
ts pack "$out/xyz/texture" --template '{z}/{x}/{y}.png' -o "$out/repack-xyz.tspack"
ts export "$out/tile-png.tspack" --layer texture --to pmtiles -o "$out/texture.pmtiles"
ts pack "$out/texture.pmtiles" -o "$out/repack-pmtiles.tspack"
(cd "$out" && sha256sum ./*.tspack ./*.pmtiles | sort -k2)
