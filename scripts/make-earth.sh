#!/usr/bin/env bash
# Makes client/data/earth.webp, the whole-Earth picture the globe draws beyond an
# archive's data: Natural Earth II (Tom Patterson; land cover, shaded relief, water and
# drainages; public domain, naturalearthdata.com) as CesiumJS redistributes it for its own
# globe (npm cesium, Assets/Textures/NaturalEarthII: a geodetic TMS of 256-px JPEG
# tiles), its level 2 (8 x 4 tiles) joined into one 2048 x 1024 equirectangular picture,
# north up. Needs: ImageMagick, and the npm package (CESIUM=its folder; default: the one
# the tests install, cesium 1.145.0).
set -euo pipefail
cd "$(dirname "$0")/.."
npm_cache=${TERRASTREAM_NPM:-$HOME/.cache/terrastream-npm}
CESIUM=${CESIUM:-$npm_cache/cesium-1.145.0}
tiles=$CESIUM/Assets/Textures/NaturalEarthII/2
[ -f "$tiles/0/0.jpg" ] || { echo "no NaturalEarthII tiles in $tiles (npm pack cesium@1.145.0)"; exit 1; }
work=$(mktemp -d)
trap 'rm -rf "$work"' EXIT
# TMS rows count from the south: row 3 is the northernmost.
for y in 3 2 1 0; do
  convert "$tiles"/{0,1,2,3,4,5,6,7}/"$y".jpg +append "$work/row$y.png"
done
# The water darkened to about water's albedo (its pixels, blue above red and green,
# times 0.62 in sRGB: 0.35 in linear light; the picture's sea is a map's light blue),
# then WebP at quality 80 (about 200 KiB, which the webplayer carries in its wasm).
convert "$work/row3.png" "$work/row2.png" "$work/row1.png" "$work/row0.png" -append \
  -fx "(b > r + 0.15 && b > g + 0.08 && r < 0.6) ? u * 0.62 : u" \
  -strip -quality 80 client/data/earth.webp
identify client/data/earth.webp
