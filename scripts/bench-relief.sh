#!/usr/bin/env bash
# Maps from the heights, cold, in one run: hillshade tiles made on each request by
# `terrastream serve` (nothing kept: web_cache_bytes = 0) against TiTiler 2.4's
# `algorithm=hillshade` on a COG of the same DEM, and contour vector tiles; both against
# our terrain tiles of the same zooms as the baseline. wrk, CONNS connections, SECS s a
# target; tiles of the data's five finest zooms at 256 px (as scripts/bench-web.sh).
# Needs: wrk, gdal-bin, python3 (TiTiler is installed from PyPI into a cache venv).
# SRTM=path picks the DEM (default: ../shared/data/srtm/n37_w123_1arc_v3.tif).
set -euo pipefail
cd "$(dirname "$0")/.."
CONNS=${CONNS:-32}
SECS=${SECS:-8}
SRTM=${SRTM:-../shared/data/srtm/n37_w123_1arc_v3.tif}
command -v wrk >/dev/null || { echo "wrk is not installed (apt-get install wrk)"; exit 1; }
venv=${TITILER_VENV:-$HOME/.cache/terrastream-titiler}
if ! [ -x "$venv/bin/uvicorn" ]; then
  python3 -m venv "$venv"
  "$venv/bin/pip" install -q "titiler.application==2.4.0" "uvicorn[standard]"
fi
cargo build --release --quiet --bin terrastream
bin=$PWD/target/release/terrastream
work=$(mktemp -d)
pids=()
# The servers stopped, and waited for (TiTiler's workers finish the requests still queued,
# which read the COG), before their files go.
cleanup() {
  for p in "${pids[@]}"; do kill "$p" 2>/dev/null || true; done
  for p in "${pids[@]}"; do wait "$p" 2>/dev/null || true; done
  rm -rf "$work"
}
trap cleanup EXIT INT TERM

"$bin" -q tile --elevation "$SRTM" -o "$work/srtm.tspack"
gdal_translate -q -of COG "$SRTM" "$work/srtm-cog.tif"
printf 'web_cache_bytes = 0\n' > "$work/cold.toml"
port() { python3 -c 'import socket; s=socket.socket(); s.bind(("127.0.0.1",0)); print(s.getsockname()[1])'; }
ours=$(port); titiler=$(port)
"$bin" -q serve "$work/srtm.tspack" --addr "127.0.0.1:$ours" --config "$work/cold.toml" & pids+=($!)
# (TiTiler's hillshade warns of the sea's no data in numpy at every such tile: not shown.)
(cd "$work" && PYTHONWARNINGS=ignore::RuntimeWarning exec "$venv/bin/uvicorn" titiler.application.main:app --workers 2 --host 127.0.0.1 --port "$titiler" \
  --log-level warning) & pids+=($!)
for p in $ours $titiler; do
  for _ in $(seq 100); do (exec 3<>/dev/tcp/127.0.0.1/$p) 2>/dev/null && break; sleep 0.2; done
done

# The data's five finest zooms at 256 px, every tile over the data (at most 2 000).
python3 - "$work" "http://127.0.0.1:$ours/srtm/tiles.json?size=256" <<'PY'
import json, math, random, sys, urllib.request
work, url = sys.argv[1], sys.argv[2]
doc = json.load(urllib.request.urlopen(url))
w, s, e, n = doc["bounds"]
def tile(z, lon, lat):
    k = 2 ** z
    y = (1 - math.log(math.tan(math.radians(lat)) + 1 / math.cos(math.radians(lat))) / math.pi) / 2 * k
    return min(int((lon + 180) / 360 * k), k - 1), min(max(int(y), 0), k - 1)
tiles = []
for z in range(doc["maxzoom"], max(doc["maxzoom"] - 5, -1), -1):
    (x0, y0), (x1, y1) = tile(z, w, n), tile(z, e, s)
    tiles += [(z, x, y) for x in range(x0, x1 + 1) for y in range(y0, y1 + 1)]
random.seed(7)
tiles = random.sample(tiles, min(2000, len(tiles)))
cog = f"file://{work}/srtm-cog.tif"
lists = {
    "terrain": "/srtm/xyz/elevation/{z}/{x}/{y}.png?size=256",
    "hillshade": "/srtm/xyz/hillshade/{z}/{x}/{y}.png?size=256",
    "contours": "/srtm/contours/{z}/{x}/{y}.pbf",
    "titiler": "/cog/tiles/WebMercatorQuad/{z}/{x}/{y}.png?url=" + cog + "&algorithm=hillshade",
}
for name, template in lists.items():
    with open(f"{work}/{name}.txt", "w") as f:
        f.writelines(template.format(z=z, x=x, y=y) + "\n" for z, x, y in tiles)
print(f"{len(tiles)} tiles of zooms {doc['maxzoom'] - 4}-{doc['maxzoom']}")
PY
cat > "$work/paths.lua" <<'LUA'
local paths = {}
for line in io.lines(os.getenv("PATHS")) do paths[#paths + 1] = line end
math.randomseed(os.time())
request = function() return wrk.format("GET", paths[math.random(#paths)]) end
LUA
# Tiles answered 200 a second (a 503 "busy" answer is no tile: when the tile-making queue
# is full, refusals are fast and would count as throughput), p99, and the others.
run() { # port paths -> "tiles/s p99 non2xx"
  PATHS="$work/$2.txt" wrk -t2 -c"$CONNS" -d"${SECS}s" --latency -s "$work/paths.lua" "http://127.0.0.1:$1" |
    awk -v secs="$SECS" '$1 == "99%" { p = $2 } /Non-2xx/ { b = $5 } /requests in/ { n = $1 }
      END { printf "%.1f %s %d\n", (n - b) / secs, p, b }'
}
printf '%-44s %12s %10s %8s\n' target "tiles/s (200)" p99 non2xx
read -r t_rps t_p99 t_bad <<<"$(run "$ours" terrain)"
read -r h_rps h_p99 h_bad <<<"$(run "$ours" hillshade)"
read -r c_rps c_p99 c_bad <<<"$(run "$ours" contours)"
read -r ti_rps ti_p99 ti_bad <<<"$(run "$titiler" titiler)"
printf '%-44s %12s %10s %8s\n' "terrain tiles, cold (baseline)" "$t_rps" "$t_p99" "$t_bad"
printf '%-44s %12s %10s %8s\n' "hillshade tiles, cold" "$h_rps" "$h_p99" "$h_bad"
printf '%-44s %12s %10s %8s\n' "contour tiles, cold" "$c_rps" "$c_p99" "$c_bad"
printf '%-44s %12s %10s %8s\n' "TiTiler 2.4 algorithm=hillshade" "$ti_rps" "$ti_p99" "$ti_bad"
awk -v h="$h_rps" -v t="$t_rps" -v c="$c_rps" -v ti="$ti_rps" 'BEGIN {
  printf "hillshade: %.2fx our terrain tiles, %.1fx TiTiler; contours: %.2fx our terrain tiles\n", h / t, h / ti, c / t }'
