#!/usr/bin/env bash
# Private terrain's cost, in one run, side by side:
#   (a) the tile endpoint of a public archive (no access rules), random tiles;
#   (k) the same archive private, each request with a valid key in its Authorization
#       header (the lean HTTP/1.1 path checks it), the same tiles; its ratio to (a) is
#       what checking a key costs;
#   (f) a flood of requests with bad keys (at least FLOOD = 100 000) while good-key
#       requests run beside it: the good requests' p99 against (k)'s, and what the flood
#       got (every answer a refusal: non-2xx, and the bytes read per answer those of a
#       refusal's JSON, so no byte of the archive).
# Rounds take turns (ROUNDS, SECS each). Needs: wrk. Loopback only.
set -euo pipefail
cd "$(dirname "$0")/.."
CONNS=${CONNS:-64}
SECS=${SECS:-8}
ROUNDS=${ROUNDS:-5}
FLOOD=${FLOOD:-100000}
command -v wrk >/dev/null || { echo "wrk is not installed (apt-get install wrk)"; exit 1; }

cargo build --release --quiet --bin terrastream
bin=$PWD/target/release/terrastream
work=$(mktemp -d)
pids=()
cleanup() { for p in "${pids[@]}"; do kill "$p" 2>/dev/null || true; done; rm -rf "$work"; }
trap cleanup EXIT INT TERM

echo "building a 5461-tile, 80 MB archive..."
"$bin" -q bench archive --dir "$work" --lookups 1 >/dev/null
mkdir -p "$work/public" "$work/private"
cp "$work/bench.tspack" "$work/public/bench.tspack"
mv "$work/bench.tspack" "$work/private/bench.tspack"
"$bin" info "$work/public/bench.tspack" --tiles |
  awk -F'\t' '{ print "/bench/" $1 "/" $2 "/" $3 "/" $4 }' > "$work/tile-paths.txt"
key=$("$bin" key new --archives bench --keys "$work/keys.toml")
port() { python3 -c 'import socket; s=socket.socket(); s.bind(("127.0.0.1",0)); print(s.getsockname()[1])'; }
public=$(port); private=$(port)
"$bin" -q serve "$work/public" --addr "127.0.0.1:$public" & pids+=($!)
# REFUSAL_RATE / REFUSAL_BURST: the private server's pace of refusals (its defaults if unset).
: > "$work/private.toml"
[ -n "${REFUSAL_RATE:-}" ] && echo "refusal_rate = $REFUSAL_RATE" >> "$work/private.toml"
[ -n "${REFUSAL_BURST:-}" ] && echo "refusal_burst = $REFUSAL_BURST" >> "$work/private.toml"
"$bin" -q serve "$work/private" --config "$work/private.toml" --private --keys "$work/keys.toml" \
  --addr "127.0.0.1:$private" & pids+=($!)
for p in $public $private; do
  for _ in $(seq 50); do (exec 3<>/dev/tcp/127.0.0.1/$p) 2>/dev/null && break; sleep 0.1; done
done

cat > "$work/tiles.lua" <<'LUA'
local paths = {}
for line in io.lines(os.getenv("TILE_PATHS")) do paths[#paths + 1] = line end
math.randomseed(os.time())
local headers = nil
if os.getenv("KEY") then headers = { ["Authorization"] = "Bearer " .. os.getenv("KEY") } end
request = function() return wrk.format("GET", paths[math.random(#paths)], headers) end
LUA
export TILE_PATHS="$work/tile-paths.txt"

# CPU time (clock ticks, user + system) of a process, all its threads.
ticks() { awk '{ print $14 + $15 }' "/proc/$1/stat" 2>/dev/null || echo 0; }
hz=$(getconf CLK_TCK)

run() { # url [KEY [SECS [PID]]] -> "requests/s p50 p99 non2xx requests bytes cpu-us-per-answer"
  local out url=$1 key=${2:-} secs=${3:-$SECS} pid=${4:-} before=0 after=0
  [ -n "$pid" ] && before=$(ticks "$pid")
  if [ -n "$key" ]; then
    out=$(KEY=$key wrk -t2 -c"$CONNS" -d"${secs}s" --latency -s "$work/tiles.lua" "$url")
  else
    out=$(env -u KEY wrk -t2 -c"$CONNS" -d"${secs}s" --latency -s "$work/tiles.lua" "$url")
  fi
  [ -n "$pid" ] && after=$(ticks "$pid")
  awk -v t=$((after - before)) -v hz="$hz" '/Requests\/sec/ { rps = $2 } $1 == "50%" { p50 = $2 } $1 == "99%" { p99 = $2 }
       /Non-2xx/ { bad = $5 } /requests in/ { n = $1; bytes = $5 }
       END { printf "%s %s %s %s %s %s %.2f\n", rps, p50, p99, bad + 0, n, bytes, (n > 0 ? t / hz * 1e6 / n : 0) }' <<<"$out"
}

echo
echo "wrk, $CONNS connections, ${SECS}s each, 2 threads, loopback, $(nproc) cores, $ROUNDS rounds"
printf '%-6s %-40s %12s %10s %10s %8s %12s %8s\n' round target requests/s p50 p99 "x (a)" "CPU us/ans" "x (a)"
: > "$work/ratios.txt"
for round in $(seq "${CHECK_ROUNDS:-$ROUNDS}"); do
  read -r a_rps a_p50 a_p99 a_bad _ _ a_cpu <<<"$(run "http://127.0.0.1:$public" "" "$SECS" "${pids[0]}")"
  read -r k_rps k_p50 k_p99 k_bad _ _ k_cpu <<<"$(run "http://127.0.0.1:$private" "$key" "$SECS" "${pids[1]}")"
  [ "$a_bad$k_bad" = 00 ] || echo "WARNING: non-2xx answers: (a) $a_bad, (k) $k_bad" >&2
  ratio=$(awk -v x="$k_rps" -v y="$a_rps" 'BEGIN { printf "%.3f", x / y }')
  cpu=$(awk -v x="$k_cpu" -v y="$a_cpu" 'BEGIN { printf "%.3f", x / y }')
  printf '%-6s %-40s %12s %10s %10s %8s %12s %8s\n' "$round" "(a) public tile endpoint" "$a_rps" "$a_p50" "$a_p99" 1 "$a_cpu" 1
  printf '%-6s %-40s %12s %10s %10s %8s %12s %8s\n' "$round" "(k) private, a valid key in a header" "$k_rps" "$k_p50" "$k_p99" "$ratio" "$k_cpu" "$cpu"
  echo "$ratio $cpu" >> "$work/ratios.txt"
done
for column in 1 2; do
  sort -n -k"$column" "$work/ratios.txt" | awk -v c="$column" '{ r[NR] = $c } END {
    m = (NR % 2) ? r[(NR + 1) / 2] : (r[NR / 2] + r[NR / 2 + 1]) / 2;
    if (c == 1) printf "median (k) / (a) requests/s: %.3f\n", m;
    else printf "median (k) / (a) server CPU per answer: %.3f: checking a key costs %.1f %%\n", m, (m - 1) * 100 }'
done

# The flood: a saturating wrk (all but 4 connections) sending bad keys for FLOOD_SECS,
# while 4 connections of good keys read tiles beside it, ROUNDS rounds of SECS; their
# p99 against the same rounds before the flood (medians of the rounds: single rounds of a
# closed loop on 2 cores shared with both load generators vary by 2x). The server paces
# its refusals (`refusal_rate`, default 200/s), so the flood needs about 500 s to send
# 100 000 requests.
echo
to_ms() { awk -v v="$1" 'BEGIN { u = v; sub(/[0-9.]+/, "", u); x = v + 0; if (u == "us") x /= 1000; if (u == "s") x *= 1000; print x }'; }
median() { sort -n | awk '{ r[NR] = $1 } END { print (NR % 2) ? r[(NR + 1) / 2] : (r[NR / 2] + r[NR / 2 + 1]) / 2 }'; }
good_rounds() { # -> lines "p99-ms requests/s non-2xx"
  for _ in $(seq "$ROUNDS"); do
    read -r rps _ p99 bad _ <<<"$(CONNS=4 run "http://127.0.0.1:$private" "$key" "$SECS")"
    echo "$(to_ms "$p99") $rps $bad"
  done
}
good_rounds > "$work/alone.txt"
bad_key="tk_00000000_$(printf '0%.0s' $(seq 64))"
# Long enough for FLOOD requests at the pace (the server's default: 200 refusals a second).
FLOOD_SECS=${FLOOD_SECS:-$((FLOOD / ${REFUSAL_RATE:-200} + 5))}
CONNS=$((CONNS - 4)) run "http://127.0.0.1:$private" "$bad_key" "$FLOOD_SECS" > "$work/flood.txt" &
flood=$!
sleep 2
good_rounds > "$work/during.txt"
wait $flood
read -r f_rps _ _ f_bad f_n f_bytes _ <<<"$(cat "$work/flood.txt")"
echo "flood: $f_n requests with a bad key in ${FLOOD_SECS}s ($f_rps/s), $f_bad answered non-2xx, $f_bytes read in all"
[ "$f_n" -ge "$FLOOD" ] || echo "WARNING: fewer than $FLOOD flood requests: raise FLOOD_SECS" >&2
if [ "$f_bad" = "$f_n" ]; then echo "  every flood answer a refusal: no byte of the archive"; else echo "WARNING: a flood request was answered 2xx" >&2; fi
g_p99=$(awk '{ print $1 }' "$work/alone.txt" | median); d_p99=$(awk '{ print $1 }' "$work/during.txt" | median)
g_rps=$(awk '{ print $2 }' "$work/alone.txt" | median); d_rps=$(awk '{ print $2 }' "$work/during.txt" | median)
bad=$(awk '{ n += $3 } END { print n + 0 }' "$work/alone.txt" "$work/during.txt")
echo "good keys (4 connections), rounds' p99 in ms: alone $(awk '{ printf "%s ", $1 }' "$work/alone.txt")| during $(awk '{ printf "%s ", $1 }' "$work/during.txt")"
ratio=$(awk -v a="$d_p99" -v b="$g_p99" 'BEGIN { printf "%.2f", a / b }')
echo "good keys: median p99 ${g_p99} ms alone ($g_rps/s), ${d_p99} ms during the flood ($d_rps/s): ${ratio}x; non-2xx $bad"
