#!/usr/bin/env bash
# Web tiles and the elevation API against TiTiler, in one run, side by side (run by
# scripts/bench-server.sh, or alone):
#   (e) Terrain-RGB tiles made on the fly by `terrastream serve` from a transverse-Mercator
#       archive of the SRTM tile (every tile reprojected), random tiles of the data's five
#       finest zooms (z10-z14 for the SRTM tile) inside its bounds, 256 px PNG: cold
#       (nothing kept: web_cache_bytes = 0) and warm;
#   (f) TiTiler 2.4 (two uvicorn workers) on a Cloud-Optimized GeoTIFF of the same DEM
#       (gdal_translate -of COG), algorithm=terrainrgb, the same tiles;
#   (g) nginx serving `terrastream export --to xyz` of the same tiles (static files);
#   (h) single-point elevation requests: ours (/v1) against TiTiler's /cog/point; and
#       points per second with 100 locations a request;
#   (i) quantized-mesh tiles (both extensions, gzipped, as CesiumJS asks) made on each
#       request, random tiles of the five deepest levels inside the bounds, against (e) cold;
#   (j) the same tiles warm (kept), against nginx serving `terrastream export --to
#       quantized-mesh` of them (gzipped files sent with `Content-Encoding: gzip`).
# Needs: wrk, nginx, gdal-bin, python3 (TiTiler is installed from PyPI into a cache venv).
# SRTM=path picks the DEM (default: ../shared/data/srtm/n37_w123_1arc_v3.tif). The work is
# sized from it: the zooms are the data's own five finest (fewer, from the finest down,
# where more would export over MAX_TILES = 200000 static tiles), up to 2 000 distinct
# tiles drawn from them; a DEM with fewer than 100 tiles there is refused, with the reason.
set -euo pipefail
cd "$(dirname "$0")/.."
CONNS=${CONNS:-64}
SECS=${SECS:-10}
SRTM=${SRTM:-../shared/data/srtm/n37_w123_1arc_v3.tif}
command -v wrk >/dev/null || { echo "wrk is not installed (apt-get install wrk)"; exit 1; }
NGINX=$(command -v nginx || echo /usr/sbin/nginx)
venv=${TITILER_VENV:-$HOME/.cache/terrastream-titiler}
if ! [ -x "$venv/bin/uvicorn" ]; then
  python3 -m venv "$venv"
  "$venv/bin/pip" install -q "titiler.application==2.4.0" "uvicorn[standard]"
fi

cargo build --release --quiet --bin terrastream
bin=$PWD/target/release/terrastream
work=$(mktemp -d)
pids=()
cleanup() { for p in "${pids[@]}"; do kill "$p" 2>/dev/null || true; done; rm -rf "$work"; }
trap cleanup EXIT INT TERM

echo "tiling $SRTM (transverse Mercator), making its COG..."
"$bin" -q tile --elevation "$SRTM" -o "$work/srtm.tspack"
gdal_translate -q -of COG "$SRTM" "$work/srtm-cog.tif"
mkdir -p "$work/www"
printf 'web_cache_bytes = 0\n' > "$work/cold.toml"

port() { python3 -c 'import socket; s=socket.socket(); s.bind(("127.0.0.1",0)); print(s.getsockname()[1])'; }
cold=$(port); warm=$(port); titiler=$(port); static=$(port)
"$bin" -q serve "$work/srtm.tspack" --addr "127.0.0.1:$cold" --config "$work/cold.toml" & pids+=($!)
"$bin" -q serve "$work/srtm.tspack" --addr "127.0.0.1:$warm" & pids+=($!)
(cd "$work" && exec "$venv/bin/uvicorn" titiler.application.main:app --workers 2 --host 127.0.0.1 --port "$titiler" \
  --log-level warning) & pids+=($!)
for p in $cold $warm $titiler; do
  for _ in $(seq 100); do (exec 3<>/dev/tcp/127.0.0.1/$p) 2>/dev/null && break; sleep 0.2; done
done

# Random tiles of the data's finest zooms inside its bounds, and random points inside them:
# the zooms sized from the DEM (zooms.txt: web min and max, terrain min and max).
python3 - "$work" "http://127.0.0.1:$warm/srtm/tiles.json?size=256" "${MAX_TILES:-200000}" <<'PY'
import json, math, random, sys, urllib.request
work, url, max_tiles = sys.argv[1], sys.argv[2], int(sys.argv[3])
doc = json.load(urllib.request.urlopen(url))
w, s, e, n = doc["bounds"]
random.seed(7)
def tile(z, lon, lat):
    k = 2 ** z
    y = (1 - math.log(math.tan(math.radians(lat)) + 1 / math.cos(math.radians(lat))) / math.pi) / 2 * k
    return min(int((lon + 180) / 360 * k), k - 1), min(max(int(y), 0), k - 1)
def web_ranges(z):
    (x0, y0), (x1, y1) = tile(z, w, n), tile(z, e, s)
    return range(x0, x1 + 1), range(y0, y1 + 1)
def geo_ranges(z):
    d = 180 / 2 ** z
    xs = range(int((w + 180) // d), int((min(e, 179.999999) + 180) // d) + 1)
    ys = range(int((s + 90) // d), int((min(n, 89.999999) + 90) // d) + 1)
    return xs, ys
def zooms(finest, ranges, what):
    """The five finest zooms (fewer where they would hold over max_tiles), and their tiles."""
    chosen, total = [], 0
    for z in range(finest, max(finest - 5, -1), -1):
        xs, ys = ranges(z)
        if total + len(xs) * len(ys) > max_tiles:
            break
        chosen.append(z)
        total += len(xs) * len(ys)
    if not chosen:
        sys.exit(f"{what}: zoom {finest} alone holds over {max_tiles} tiles: pick a smaller DEM or raise MAX_TILES")
    every = [(z, x, y) for z in chosen for x in ranges(z)[0] for y in ranges(z)[1]]
    if len(every) < 100:
        sys.exit(f"{what}: only {len(every)} tiles at zooms {min(chosen)}-{max(chosen)} over the data: "
                 "too few to measure (pick a DEM of more than a few tiles)")
    return min(chosen), max(chosen), sorted(random.sample(every, min(2000, len(every))))
maxzoom = json.load(urllib.request.urlopen(url.replace("tiles.json?size=256", "layer.json")))["maxzoom"]
zmin, zmax, tiles = zooms(doc["maxzoom"], web_ranges, "web tiles")
tmin, tmax, terrain = zooms(maxzoom, geo_ranges, "quantized-mesh")
with open(f"{work}/zooms.txt", "w") as f:
    f.write(f"{zmin} {zmax} {tmin} {tmax}\n")
print(f"web tiles: {len(tiles)} of zooms {zmin}-{zmax}; quantized-mesh: {len(terrain)} of levels {tmin}-{tmax}")
cog = f"file://{work}/srtm-cog.tif"
with open(f"{work}/ours.txt", "w") as f:
    f.writelines(f"/srtm/xyz/elevation/{z}/{x}/{y}.png?size=256&encoding=mapbox\n" for z, x, y in tiles)
with open(f"{work}/titiler.txt", "w") as f:
    f.writelines(f"/cog/tiles/WebMercatorQuad/{z}/{x}/{y}.png?url={cog}&algorithm=terrainrgb\n" for z, x, y in tiles)
with open(f"{work}/static.txt", "w") as f:
    f.writelines(f"/xyz/{z}/{x}/{y}.png\n" for z, x, y in tiles)
points = [(random.uniform(s + (n - s) * 0.05, n - (n - s) * 0.05), random.uniform(w + (e - w) * 0.05, e - (e - w) * 0.05))
          for _ in range(2000)]
with open(f"{work}/point.txt", "w") as f:
    f.writelines(f"/v1/srtm?locations={lat:.6f},{lon:.6f}\n" for lat, lon in points)
with open(f"{work}/titiler-point.txt", "w") as f:
    f.writelines(f"/cog/point/{lon:.6f},{lat:.6f}?url={cog}\n" for lat, lon in points)
with open(f"{work}/hundred.txt", "w") as f:
    for i in range(0, 2000, 100):
        f.write("/v1/srtm?locations=" + "|".join(f"{lat:.6f},{lon:.6f}" for lat, lon in points[i:i + 100]) + "\n")
with open(f"{work}/terrain.txt", "w") as f:
    f.writelines(f"/srtm/{z}/{x}/{y}.terrain\n" for z, x, y in terrain)
with open(f"{work}/terrain-static.txt", "w") as f:
    f.writelines(f"/terrain/{z}/{x}/{y}.terrain\n" for z, x, y in terrain)
PY
read -r zmin zmax tmin tmax < "$work/zooms.txt"
echo "exporting the same tiles for nginx..."
"$bin" -q export "$work/srtm.tspack" --to xyz --encoding mapbox --format png --size 256 --minzoom "$zmin" \
  --maxzoom "$zmax" --base-url "http://127.0.0.1:$static/xyz/" -o "$work/www/xyz"
"$bin" -q export "$work/srtm.tspack" --to quantized-mesh --minzoom "$tmin" --maxzoom "$tmax" -o "$work/www/terrain"
chmod -R a+rX "$work"
mkdir -p "$work/nginx"
cat > "$work/nginx/nginx.conf" <<CONF
daemon off; master_process on; worker_processes 2; pid $work/nginx/pid; error_log $work/nginx/error.log warn;
events { worker_connections 4096; }
http { access_log off; sendfile on; keepalive_requests 100000; types { image/png png; }
  client_body_temp_path $work/nginx/b; proxy_temp_path $work/nginx/p; fastcgi_temp_path $work/nginx/f;
  uwsgi_temp_path $work/nginx/u; scgi_temp_path $work/nginx/s;
  server { listen 127.0.0.1:$static; root $work/www;
    location /terrain/ { types { application/vnd.quantized-mesh terrain; application/json json; }
      location ~ [.]terrain\$ { add_header Content-Encoding gzip; } } } }
CONF
"$NGINX" -p "$work/nginx" -c "$work/nginx/nginx.conf" -e "$work/nginx/error.log" & pids+=($!)
for _ in $(seq 100); do (exec 3<>/dev/tcp/127.0.0.1/$static) 2>/dev/null && break; sleep 0.2; done
cat > "$work/paths.lua" <<'LUA'
local paths = {}
for line in io.lines(os.getenv("PATHS")) do paths[#paths + 1] = line end
math.randomseed(os.time())
local headers = nil
if os.getenv("CESIUM") then
  headers = { ["Accept"] = "application/vnd.quantized-mesh;extensions=octvertexnormals-metadata",
              ["Accept-Encoding"] = "gzip" }
end
request = function() return wrk.format("GET", paths[math.random(#paths)], headers) end
LUA

run() { # port paths -> "requests/s p50 p99 errors"
  local out
  out=$(PATHS="$work/$2" wrk -t2 -c"$CONNS" -d"${SECS}s" --latency -s "$work/paths.lua" "http://127.0.0.1:$1")
  local rps p50 p99 errs
  rps=$(awk '/Requests\/sec/ { print $2 }' <<<"$out")
  p50=$(awk '$1 == "50%" { print $2 }' <<<"$out")
  p99=$(awk '$1 == "99%" { print $2 }' <<<"$out")
  errs=$(awk '/Non-2xx|Socket errors/ { $1 = $1; print }' <<<"$out" | paste -sd' ' -)
  [ -n "$errs" ] && echo "WARNING: $2 on $1: $errs" >&2
  echo "$rps $p50 $p99"
}
# Warm: every tile asked once first.
while read -r p; do curl -s -o /dev/null "http://127.0.0.1:$warm$p"; done < "$work/ours.txt"
while read -r p; do
  curl -s -o /dev/null -H 'Accept: application/vnd.quantized-mesh;extensions=octvertexnormals-metadata' \
    -H 'Accept-Encoding: gzip' "http://127.0.0.1:$warm$p"
done < "$work/terrain.txt"

echo
echo "wrk, $CONNS connections, ${SECS}s each, 2 threads, loopback, $(nproc) cores"
printf '%-58s %12s %10s %10s\n' "target" "requests/s" "p50" "p99"
declare -A r
for row in "e-cold|$cold|ours.txt|(e) terrastream web tiles, cold (made on each request)" \
           "e-warm|$warm|ours.txt|(e) terrastream web tiles, warm (kept)" \
           "f|$titiler|titiler.txt|(f) TiTiler 2.4 on the COG, terrainrgb" \
           "g|$static|static.txt|(g) nginx, the exported tiles" \
           "h-ours|$warm|point.txt|(h) terrastream /v1, one point a request" \
           "h-titiler|$titiler|titiler-point.txt|(h) TiTiler /cog/point" \
           "h-100|$warm|hundred.txt|(h) terrastream /v1, 100 points a request" \
           "i|$cold|terrain.txt|(i) terrastream quantized-mesh tiles, cold" \
           "j-warm|$warm|terrain.txt|(j) terrastream quantized-mesh tiles, warm (kept)" \
           "j-nginx|$static|terrain-static.txt|(j) nginx, the exported quantized-mesh tiles"; do
  IFS='|' read -r key p file name <<<"$row"
  if [ "${key:0:1}" = i ] || [ "${key:0:1}" = j ]; then r[$key]=$(CESIUM=1 run "$p" "$file"); else r[$key]=$(run "$p" "$file"); fi
  read -r rps p50 p99 <<<"${r[$key]}"
  printf '%-58s %12s %10s %10s\n' "$name" "$rps" "$p50" "$p99"
done
ratio() { awk -v a="${r[$1]%% *}" -v b="${r[$2]%% *}" 'BEGIN { printf "%.1f", a / b }'; }
echo
echo "cold web tiles / TiTiler: $(ratio e-cold f)x; warm web tiles / nginx static: $(ratio e-warm g)x"
echo "cold quantized-mesh tiles / cold web tiles: $(ratio i e-cold)x;" \
  "warm quantized-mesh tiles / nginx static: $(ratio j-warm j-nginx)x"
echo "single-point elevation / TiTiler /cog/point: $(ratio h-ours h-titiler)x;" \
  "points/s at 100 a request: $(awk -v a="${r[h-100]%% *}" 'BEGIN { printf "%.0f", a * 100 }')"
