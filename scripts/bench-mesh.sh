#!/usr/bin/env bash
# Quantized-mesh meshing against Python's pydelatin + quantized-mesh-encoder (PyPI), on the
# same height grids with the same error bound, one core each, in one run:
#   ours: `terrastream bench mesh` (greedy Delaunay insertion + encoder, no extensions);
#   peer: pydelatin's Delatin(grid, max_error=bound) + quantized_mesh_encoder.encode.
# The grids are what the server samples for CesiumJS: 65 x 65, levels 8-13 of the SRTM tile
# tiled with the defaults (a transverse Mercator, reprojected to the geographic grid).
# SRTM=path picks the DEM (default: ../shared/data/srtm/n37_w123_1arc_v3.tif); PER_LEVEL=n
# tiles a level (default 150).
set -euo pipefail
cd "$(dirname "$0")/.."
SRTM=${SRTM:-../shared/data/srtm/n37_w123_1arc_v3.tif}
venv=${MESH_VENV:-$HOME/.cache/terrastream-mesh}
if ! [ -x "$venv/bin/python" ] || ! "$venv/bin/python" -c "import pydelatin, quantized_mesh_encoder" 2>/dev/null; then
  python3 -m venv "$venv"
  "$venv/bin/pip" install -q pydelatin==0.4.0 quantized-mesh-encoder==0.5.0
fi
cargo build --release --quiet --bin terrastream
bin=$PWD/target/release/terrastream
work=$(mktemp -d)
trap 'rm -rf "$work"' EXIT INT TERM

"$bin" -q tile --elevation "$SRTM" -o "$work/srtm.tspack"
echo "== ours: terrastream bench mesh (one core)"
taskset -c 0 "$bin" -q bench mesh "$work/srtm.tspack" --min-level 8 --max-level 13 \
  --per-level "${PER_LEVEL:-150}" --grids-out "$work/grids.bin" | tee "$work/ours.txt"
echo "== peer: pydelatin $("$venv/bin/pip" show pydelatin | awk '/^Version/ {print $2}')" \
  "+ quantized-mesh-encoder $("$venv/bin/pip" show quantized-mesh-encoder | awk '/^Version/ {print $2}') (one core)"
taskset -c 0 "$venv/bin/python" - "$work/grids.bin" <<'PY' | tee "$work/peer.txt"
import io, struct, sys, time
from collections import defaultdict
import numpy as np
from pydelatin import Delatin
from quantized_mesh_encoder import encode

data = open(sys.argv[1], "rb").read()
assert data[:8] == b"TSGRIDS1", "not a grid file"
count, side = struct.unpack_from("<II", data, 8)
at = 16
levels = defaultdict(lambda: [0, 0, 0, 0.0])
for _ in range(count):
    z, x, y, west, south, east, north, bound = struct.unpack_from("<BIIddddf", data, at)
    at += struct.calcsize("<BIIddddf")
    heights = np.frombuffer(data, dtype="<f4", count=side * side, offset=at).reshape(side, side)
    at += 4 * side * side
    best = float("inf")
    for _ in range(3):
        start = time.perf_counter()
        tin = Delatin(heights, max_error=bound)
        v = tin.vertices.astype(np.float64)
        positions = np.empty_like(v)
        positions[:, 0] = west + v[:, 0] / (side - 1) * (east - west)
        positions[:, 1] = north - v[:, 1] / (side - 1) * (north - south)
        positions[:, 2] = v[:, 2]
        f = io.BytesIO()
        encode(f, positions.astype(np.float32), tin.triangles.astype(np.uint32), bounds=[west, south, east, north])
        best = min(best, time.perf_counter() - start)
    level = levels[z]
    level[0] += 1
    level[1] += len(tin.triangles)
    level[2] += len(tin.vertices)
    level[3] += best
print("level  tiles  triangles/tile  vertices/tile  mesh+encode µs/tile")
n = tris = secs = 0
for z in sorted(levels):
    k, t, v, s = levels[z]
    print(f"{z:>5}  {k:>5}  {t / k:>14.1f}  {v / k:>13.1f}  {s / k * 1e6:>19.1f}")
    n, tris, secs = n + k, tris + t, secs + s
print(f"all    {n:>5}  {tris / n:>14.1f}  meshes/s on one core: {n / secs:.0f}")
PY
ours=$(awk '/meshes\/s/ { print $NF }' "$work/ours.txt")
peer=$(awk '/meshes\/s/ { print $NF }' "$work/peer.txt")
ot=$(awk '/meshes\/s/ { print $3 }' "$work/ours.txt")
pt=$(awk '/meshes\/s/ { print $3 }' "$work/peer.txt")
echo
echo "meshes/s, ours / pydelatin: $(awk -v a="$ours" -v b="$peer" 'BEGIN { printf "%.1f", a / b }')x;" \
  "triangles per tile, ours / pydelatin: $(awk -v a="$ot" -v b="$pt" 'BEGIN { printf "%.2f", a / b }')x"
