#!/usr/bin/env bash
# Makes client/data/earth.webp, the whole-Earth picture the globe draws beyond an
# archive's data: Natural Earth II (Tom Patterson; land cover, shaded relief, water and
# drainages; public domain, naturalearthdata.com) as CesiumJS redistributes it for its own
# globe (npm cesium, Assets/Textures/NaturalEarthII: a geodetic TMS of 256-px JPEG
# tiles), its level 2 (8 x 4 tiles) joined into one 2048 x 1024 equirectangular picture,
# north up. Its alpha holds the ground's heights: KDE Marble's "Atlas" theme (Debian
# marble-qt-data: maps/earth/srtm, SRTM30 relief and bathymetry as 8-bit grey, public
# domain), its level 3 (16 x 8 tiles of 675 px, 2') read through the theme's legend (grey
# 0.38 is sea level, 0.59 500 m, 0.77 2000 m, 0.95 7000 m, in between linear), the sea
# (below 0) at 0, averaged to the picture's grid and stored as 1 + 254 * sqrt(height / 9000 m)
# (from 1: WebP's encoder smears the colours where the alpha is 0).
# Needs: ImageMagick, GDAL's Python (python3-gdal, numpy), the npm package (CESIUM=its
# folder; default: the one the tests install, cesium 1.145.0) and marble-qt-data (MARBLE=
# its data/maps/earth/srtm folder; default: the Debian package, fetched by apt-get).
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
if [ -z "${MARBLE:-}" ]; then
  (cd "$work" && apt-get download -q marble-qt-data >/dev/null && dpkg -x marble-qt-data_*.deb marble)
  MARBLE=$work/marble/usr/share/marble/data/maps/earth/srtm
fi
[ -f "$MARBLE/3/000000/000000_000000.jpg" ] || { echo "no Atlas relief tiles in $MARBLE/3"; exit 1; }
/usr/bin/python3 - "$MARBLE/3" "$work/relief.tif" <<'PY'
import glob, os, sys
import numpy as np
from osgeo import gdal
src, out = sys.argv[1], sys.argv[2]
side = 675
grey = np.zeros((8 * side, 16 * side), np.float32)
for path in glob.glob(f"{src}/*/*.jpg"):
    row, col = (int(v) for v in os.path.basename(path)[:-4].split("_"))
    grey[row * side:(row + 1) * side, col * side:(col + 1) * side] = gdal.Open(path).ReadAsArray()
# The theme's legend: palette position (grey / 255) -> metres; 1.0 continues 5000-7000's slope.
at = [0.00, 0.07, 0.14, 0.21, 0.28, 0.31, 0.38, 0.45, 0.52, 0.59, 0.70, 0.77, 0.83, 0.90, 0.95, 1.00]
metres = [-11000, -6500, -4000, -2000, -200, -50, 0, 50, 200, 500, 1000, 2000, 3500, 5000, 7000, 9000]
heights = np.maximum(np.interp(grey / 255.0, at, metres), 0.0).astype(np.float32)
tif = gdal.GetDriverByName("GTiff").Create(out, heights.shape[1], heights.shape[0], 1, gdal.GDT_Float32)
tif.SetGeoTransform((-180.0, 1.0 / 30.0, 0.0, 90.0, 0.0, -1.0 / 30.0))
tif.SetProjection("EPSG:4326")
tif.GetRasterBand(1).WriteArray(heights)
PY
gdalwarp -q -r average -ts 2048 1024 -te -180 -90 180 90 "$work/relief.tif" "$work/heights.tif"
gdal_calc.py --quiet -A "$work/heights.tif" --calc="1 + round(254 * sqrt(clip(A, 0, 9000) / 9000))" \
  --type=Byte --outfile="$work/alpha.tif"
gdal_translate -q -of PNG "$work/alpha.tif" "$work/alpha.png"
# The water darkened to about water's albedo (its pixels, blue above red and green,
# times 0.62 in sRGB: 0.35 in linear light; the picture's sea is a map's light blue),
# then WebP at quality 80 with the heights as its lossless alpha (about 500 KiB, which the
# webplayer carries in its wasm).
convert "$work/row3.png" "$work/row2.png" "$work/row1.png" "$work/row0.png" -append \
  -fx "(b > r + 0.15 && b > g + 0.08 && r < 0.6) ? u * 0.62 : u" \
  \( "$work/alpha.png" -alpha off \) -compose CopyOpacity -composite \
  -strip -quality 80 -define webp:alpha-quality=100 client/data/earth.webp
identify client/data/earth.webp
