#!/usr/bin/env bash
# Server benchmark: wrk against (a) the tile endpoint with random tiles, (b) random-tile
# Range requests on the archive, (c) nginx serving the same file with the same Range
# requests — in one run, side by side. Optional memory soak: SOAK_SECS=300. LARGE=1 adds
# (d): the tile endpoint on a 349 525-tile archive whose entries are in 85 leaf
# directories (about 2 minutes more to build), as large archives are laid out. Then
# (e)-(j), web tiles, the elevation API and quantized-mesh terrain against TiTiler and
# nginx: scripts/bench-web.sh, then meshing against pydelatin: scripts/bench-mesh.sh (WEB=0
# leaves both out).
# Needs: nginx, wrk (apt-get install nginx wrk). Loopback only.
set -euo pipefail
cd "$(dirname "$0")/.."
CONNS=${CONNS:-64}
SECS=${SECS:-10}
SOAK_SECS=${SOAK_SECS:-0}
LARGE=${LARGE:-0}
command -v wrk >/dev/null || { echo "wrk is not installed (apt-get install wrk)"; exit 1; }
NGINX=$(command -v nginx || echo /usr/sbin/nginx)
[ -x "$NGINX" ] || { echo "nginx is not installed (apt-get install nginx)"; exit 1; }

cargo build --release --quiet
bin=target/release/terrastream
work=$(mktemp -d)
pids=()
cleanup() { for p in "${pids[@]}"; do kill "$p" 2>/dev/null || true; done; rm -rf "$work"; }
trap cleanup EXIT INT TERM

echo "building a 5461-tile, 80 MB archive..."
"$bin" -q bench archive --dir "$work" --lookups 1 >/dev/null
archive="$work/bench.tspack"
# nginx workers run as an unprivileged user: let them read the archive.
chmod 755 "$work"; chmod 644 "$archive"
"$bin" info "$archive" --tiles > "$work/tiles.tsv"
awk -F'\t' '{ print "/bench/" $1 "/" $2 "/" $3 "/" $4 }' "$work/tiles.tsv" > "$work/tile-paths.txt"
awk -F'\t' '{ print $5 "-" ($5 + $6 - 1) }' "$work/tiles.tsv" > "$work/ranges.txt"
served=("$archive")
if [ "$LARGE" = 1 ]; then
  echo "building a 349 525-tile archive with leaf directories..."
  mkdir -p "$work/large"
  "$bin" -q bench archive --dir "$work/large" --grid 512 --tile-bytes 512 --lookups 1 --no-copies >/dev/null
  mv "$work/large/bench.tspack" "$work/large.tspack"
  rm -rf "$work/large"
  "$bin" info "$work/large.tspack" | grep -E '^(sections|tiles)'
  # Every 50th tile: spread over every leaf, and a path list small enough that wrk's Lua
  # garbage collection does not show in its latencies (all 350 000 paths did, 25 ms+).
  "$bin" info "$work/large.tspack" --tiles |
    awk -F'\t' 'NR % 50 == 0 { print "/large/" $1 "/" $2 "/" $3 "/" $4 }' > "$work/large-paths.txt"
  served+=("$work/large.tspack")
fi

port() { python3 -c 'import socket; s=socket.socket(); s.bind(("127.0.0.1",0)); print(s.getsockname()[1])'; }
ours=$(port); theirs=$(port)
"$bin" -q serve "${served[@]}" --addr "127.0.0.1:$ours" & pids+=($!)
mkdir -p "$work/nginx"
cat > "$work/nginx/nginx.conf" <<CONF
daemon off; master_process on; worker_processes 2; pid $work/nginx/pid; error_log $work/nginx/error.log warn;
events { worker_connections 4096; }
http { access_log off; sendfile on; tcp_nopush on; keepalive_requests 100000;
  client_body_temp_path $work/nginx/b; proxy_temp_path $work/nginx/p; fastcgi_temp_path $work/nginx/f;
  uwsgi_temp_path $work/nginx/u; scgi_temp_path $work/nginx/s;
  types { application/octet-stream tspack; }
  server { listen 127.0.0.1:$theirs; root $work; } }
CONF
"$NGINX" -p "$work/nginx" -c "$work/nginx/nginx.conf" -e "$work/nginx/error.log" & pids+=($!)
for p in $ours $theirs; do
  for _ in $(seq 50); do (exec 3<>/dev/tcp/127.0.0.1/$p) 2>/dev/null && break; sleep 0.1; done
done

cat > "$work/tiles.lua" <<'LUA'
local paths = {}
for line in io.lines(os.getenv("TILE_PATHS")) do paths[#paths + 1] = line end
math.randomseed(os.time())
request = function() return wrk.format("GET", paths[math.random(#paths)]) end
LUA
cat > "$work/ranges.lua" <<'LUA'
local ranges = {}
for line in io.lines(os.getenv("RANGES")) do ranges[#ranges + 1] = line end
math.randomseed(os.time())
request = function()
  return wrk.format("GET", "/bench.tspack", { ["Range"] = "bytes=" .. ranges[math.random(#ranges)] })
end
LUA
export TILE_PATHS="$work/tile-paths.txt" RANGES="$work/ranges.txt"

# CPU time (clock ticks, user + system) of processes, all their threads.
ticks() { local t=0 p; for p in "$@"; do t=$((t + $(awk '{ print $14 + $15 }' "/proc/$p/stat" 2>/dev/null || echo 0))); done; echo "$t"; }
hz=$(getconf CLK_TCK)

run() { # url script pids... -> "requests/s p50 p99 cpu-us-per-answer errors"
  local out rps p50 p99 errs url=$1 script=$2 before after requests; shift 2
  before=$(ticks "$@")
  out=$(wrk -t2 -c"$CONNS" -d"${SECS}s" --latency -s "$script" "$url")
  after=$(ticks "$@")
  rps=$(awk '/Requests\/sec/ { print $2 }' <<<"$out")
  p50=$(awk '$1 == "50%" { print $2 }' <<<"$out")
  p99=$(awk '$1 == "99%" { print $2 }' <<<"$out")
  requests=$(awk '/requests in/ { print $1 }' <<<"$out")
  errs=$(awk '/Non-2xx|Socket errors/ { $1 = $1; print }' <<<"$out" | paste -sd' ' -)
  # A benchmark of error answers measures nothing: say so loudly.
  [ -n "$errs" ] && echo "WARNING: errors answered: $errs" >&2
  # The server's CPU per answer: on 2 cores wrk takes the rest, so this sets the rate.
  local cpu
  cpu=$(awk -v t=$((after - before)) -v hz="$hz" -v n="$requests" 'BEGIN { printf "%.1f", (n > 0 ? t / hz * 1e6 / n : 0) }')
  echo "$rps $p50 $p99 $cpu ${errs:+errors}"
}

# This machine is shared and noisy: the three targets take turns, ROUNDS times, and each
# round's ratio against nginx is computed from runs a few seconds apart.
ROUNDS=${ROUNDS:-3}
echo
echo "wrk, $CONNS connections, ${SECS}s each, 2 threads, loopback, $(nproc) cores, $ROUNDS rounds"
printf '%-6s %-44s %12s %10s %10s %8s %12s\n' "round" "target" "requests/s" "p50" "p99" "x nginx" "CPU us/ans"
: > "$work/results.txt"
for round in $(seq "$ROUNDS"); do
  a=$(run "http://127.0.0.1:$ours" "$work/tiles.lua" "${pids[0]}")
  b=$(run "http://127.0.0.1:$ours" "$work/ranges.lua" "${pids[0]}")
  c=$(run "http://127.0.0.1:$theirs" "$work/ranges.lua" $(pgrep -P "${pids[1]}" | tr '\n' ' '))
  nginx_rps=${c%% *}
  rows=("(a) terrastream tile endpoint, random tiles|$a" "(b) terrastream archive, random tile Ranges|$b"
    "(c) nginx archive, same Ranges|$c")
  if [ "$LARGE" = 1 ]; then
    d=$(export TILE_PATHS="$work/large-paths.txt"; run "http://127.0.0.1:$ours" "$work/tiles.lua" "${pids[0]}")
    rows+=("(d) tile endpoint, 350k tiles in 85 leaves|$d")
  fi
  for row in "${rows[@]}"; do
    name=${row%%|*}; read -r rps p50 p99 cpu errs <<<"${row#*|}"
    ratio=$(awk -v x="$rps" -v y="$nginx_rps" 'BEGIN { printf "%.2f", x / y }')
    printf '%-6s %-44s %12s %10s %10s %8s %12s %s\n' "$round" "$name" "$rps" "$p50" "$p99" "$ratio" "$cpu" "$errs"
    echo "${name:1:1} $ratio $p99" >> "$work/results.txt"
  done
done
echo
echo "median over the rounds:"
for t in a b $([ "$LARGE" = 1 ] && echo d); do
  sort -k2 -n <(grep "^$t " "$work/results.txt") | awk -v t="$t" '{ r[NR] = $2 } END {
    printf "  (%s) %.2fx nginx\n", t, (NR % 2) ? r[(NR + 1) / 2] : (r[NR / 2] + r[NR / 2 + 1]) / 2 }'
done

if [ "$SOAK_SECS" -gt 0 ]; then
  echo; echo "soak: (b) for ${SOAK_SECS}s, server RSS every 10 s (KiB):"
  server_pid=${pids[0]}
  wrk -t2 -c"$CONNS" -d"${SOAK_SECS}s" -s "$work/ranges.lua" "http://127.0.0.1:$ours" > "$work/soak.txt" &
  soak=$!
  while kill -0 $soak 2>/dev/null; do
    awk '/VmRSS/ { printf "%s ", $2 }' "/proc/$server_pid/status"; sleep 10
  done; echo
  awk '/Requests\/sec|Non-2xx|Socket errors/' "$work/soak.txt"
  grep -q -E 'Non-2xx|Socket errors' "$work/soak.txt" || echo "zero errors"
fi

if [ "${WEB:-1}" = 1 ]; then
  echo
  bash scripts/bench-web.sh
  echo
  bash scripts/bench-mesh.sh
fi
