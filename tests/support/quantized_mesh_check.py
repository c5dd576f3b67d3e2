"""Checks every tile of a quantized-mesh export with an independent decoder (PyPI
`quantized-mesh-tile`): header bounds, bounding sphere, horizon-occlusion point, edge
lists, triangles covering the tile once, the vertical error against the heights the
server meant, and equal heights on the edges neighbours share.

Usage: quantized_mesh_check.py EXPORT_DIR HEIGHTS_DIR GRID
HEIGHTS_DIR holds `{z}/{x}/{y}.f32` (GRID x GRID little-endian heights, rows from the
north) and `bounds.json` ({level: largest vertical error allowed}). Prints a JSON summary;
exits 1 with the failures listed.
"""

import gzip
import io
import json
import math
import os
import sys
import warnings

import numpy as np
from quantized_mesh_tile import horizon_occlusion_point as hop
from quantized_mesh_tile.bbsphere import BoundingSphere
from quantized_mesh_tile.llh_ecef import LLH2ECEF
from quantized_mesh_tile.terrain import TerrainTile

Q = 32767


def bounds(z, x, y):
    d = 180.0 / 2**z
    return x * d - 180.0, y * d - 90.0, (x + 1) * d - 180.0, (y + 1) * d - 90.0


def main():
    export, heights_dir, grid = sys.argv[1], sys.argv[2], int(sys.argv[3])
    limits = {int(k): v for k, v in json.load(open(os.path.join(heights_dir, "bounds.json"))).items()}
    failures, tiles, worst_ratio, vertices, triangles = [], {}, 0.0, 0, 0
    for z in sorted(int(d) for d in os.listdir(export) if d.isdigit()):
        for x in sorted(int(d) for d in os.listdir(os.path.join(export, str(z)))):
            for name in sorted(os.listdir(os.path.join(export, str(z), str(x)))):
                y = int(name.split(".")[0])
                raw = gzip.decompress(open(os.path.join(export, str(z), str(x), name), "rb").read())
                w, s, e, n = bounds(z, x, y)
                tile = TerrainTile(west=w, south=s, east=e, north=n)
                with warnings.catch_warnings():
                    warnings.simplefilter("ignore")  # the metadata extension is skipped
                    tile.fromBytesIO(io.BytesIO(raw), hasLighting=True, hasWatermask=True)
                where = f"{z}/{x}/{y}"
                fail = lambda why: failures.append(f"{where}: {why}")
                # The water mask: one value, or 256 rows of 256.
                mask = tile.watermask
                if not (len(mask) == 1 and len(mask[0]) == 1) and not (len(mask) == 256 and all(len(r) == 256 for r in mask)):
                    fail(f"a water mask of {len(mask)} rows")
                u, v = np.array(tile.u, float), np.array(tile.v, float)
                h = np.array([p[2] for p in tile.getVerticesCoordinates()])
                idx = np.array(tile.indices).reshape(-1, 3)
                vertices += len(u)
                triangles += len(idx)
                hd = tile.header
                # Header bounds hold every vertex.
                if h.min() < hd["minimumHeight"] - 1e-3 or h.max() > hd["maximumHeight"] + 1e-3:
                    fail(f"heights {h.min()}..{h.max()} outside the header's range")
                lon, lat = w + (e - w) * u / Q, s + (n - s) * v / Q
                ecef = np.array([LLH2ECEF(a, b, c) for a, b, c in zip(lon, lat, h)])
                centre = np.array([hd["boundingSphereCenterX"], hd["boundingSphereCenterY"], hd["boundingSphereCenterZ"]])
                far = np.linalg.norm(ecef - centre, axis=1).max()
                if far > hd["boundingSphereRadius"] + 1e-3:
                    fail(f"a vertex {far} m from the sphere's centre, radius {hd['boundingSphereRadius']}")
                # The horizon-occlusion point, computed here from the vertices (level 0
                # spans a hemisphere, where no such point exists: not checked).
                if z > 0:
                    mine = np.array(hop.fromPoints(ecef.tolist(), BoundingSphere(center=centre.tolist())))
                    theirs = np.array([hd["horizonOcclusionPointX"], hd["horizonOcclusionPointY"], hd["horizonOcclusionPointZ"]])
                    if np.linalg.norm(mine - theirs) > 1e-6 * np.linalg.norm(mine):
                        fail(f"horizon-occlusion point {theirs} but the vertices give {mine}")
                # Edge lists hold exactly the vertices on each edge.
                for label, listed, on in (
                    ("west", tile.westI, u == 0), ("south", tile.southI, v == 0),
                    ("east", tile.eastI, u == Q), ("north", tile.northI, v == Q),
                ):
                    if sorted(listed) != sorted(np.nonzero(on)[0].tolist()):
                        fail(f"the {label} list is not the vertices on that edge")
                # Triangles: counter-clockwise, covering the tile's area once.
                a, b, c = idx[:, 0], idx[:, 1], idx[:, 2]
                twice = (u[b] - u[a]) * (v[c] - v[a]) - (v[b] - v[a]) * (u[c] - u[a])
                if (twice <= 0).any():
                    fail(f"{(twice <= 0).sum()} triangles not counter-clockwise")
                if abs(twice.sum() / 2 - Q * Q) > 1e-6 * Q * Q:
                    fail(f"triangles cover {twice.sum() / 2} of {Q * Q}")
                # The vertical error at every grid point, against the heights meant.
                meant = np.fromfile(os.path.join(heights_dir, str(z), str(x), f"{y}.f32"), "<f4").reshape(grid, grid)
                gi, gj = np.meshgrid(np.arange(grid), np.arange(grid))
                gu = np.rint(gi * Q / (grid - 1)).ravel()
                gv = np.rint((grid - 1 - gj) * Q / (grid - 1)).ravel()
                gh = meant.ravel().astype(float)
                err = np.full(gu.shape, np.nan)
                covered = np.zeros(gu.shape, int)
                for t in range(len(idx)):
                    ia, ib, ic = idx[t]
                    l0 = ((u[ib] - gu) * (v[ic] - gv) - (v[ib] - gv) * (u[ic] - gu)) / twice[t]
                    l1 = ((u[ic] - gu) * (v[ia] - gv) - (v[ic] - gv) * (u[ia] - gu)) / twice[t]
                    l2 = 1 - l0 - l1
                    inside = (l0 >= -1e-9) & (l1 >= -1e-9) & (l2 >= -1e-9)
                    covered += inside
                    zi = l0 * h[ia] + l1 * h[ib] + l2 * h[ic]
                    err = np.where(inside, np.fmax(err, np.abs(zi - gh)), err)
                if (covered == 0).any():
                    fail(f"{(covered == 0).sum()} grid points in no triangle")
                largest = np.nanmax(err)
                limit = limits[z]
                worst_ratio = max(worst_ratio, largest / limit)
                if largest > limit + 1e-3:
                    fail(f"vertical error {largest:.3f} m over the bound {limit:.3f} m")
                tiles[(z, x, y)] = (u, v, h, tile)
    # Shared edges: the same vertices, the same heights (to both tiles' quantization).
    edges = 0
    for (z, x, y), (u, v, h, t) in tiles.items():
        quantum = lambda tt: (tt.header["maximumHeight"] - tt.header["minimumHeight"]) / Q
        for (dx, dy, mine, theirs, along) in ((1, 0, u == Q, "west", v), (0, 1, v == Q, "south", u)):
            other = tiles.get((z, x + dx, y + dy))
            if other is None:
                continue
            ou, ov, oh, ot = other
            there = ou == 0 if theirs == "west" else ov == 0
            oalong = ov if theirs == "west" else ou
            here = dict(zip(along[mine].tolist(), h[mine].tolist()))
            away = dict(zip(oalong[there].tolist(), oh[there].tolist()))
            edges += 1
            if sorted(here) != sorted(away):
                failures.append(f"{z}/{x}/{y} and its {theirs} neighbour keep different vertices on their edge")
                continue
            allowed = (quantum(t) + quantum(ot)) / 2 + 1e-6
            worst = max(abs(here[k] - away[k]) for k in here)
            if worst > allowed:
                failures.append(f"{z}/{x}/{y}: shared edge heights differ by {worst} m")
    print(json.dumps({"tiles": len(tiles), "vertices": vertices, "triangles": triangles,
                      "shared_edges": edges, "worst_error_over_bound": worst_ratio, "failures": failures[:20]}))
    sys.exit(1 if failures else 0)


main()
