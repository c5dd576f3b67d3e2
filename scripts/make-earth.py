#!/usr/bin/env python3
"""Makes client/data/earth.png, the whole-Earth base the globe draws beyond an archive's
data: Natural Earth's 1:50m land polygons (public domain; version 4.1.0 as TopoJSON in npm
`world-atlas@2.0.2`, ISC) filled onto an equirectangular grid (longitude -180..180 west to
east, latitude 90..-90 north to south, pixel centres), sea and land in flat colours, land
south of 60 S, north of 78 N and Greenland as ice. Standard library only.

    npm pack world-atlas@2.0.2 && tar xzf world-atlas-2.0.2.tgz
    python3 scripts/make-earth.py package/land-50m.json client/data/earth.png
"""
import json
import struct
import sys
import zlib

WIDTH, HEIGHT = 2048, 1024
SEA, LAND, ICE = 0, 1, 2
# sRGB colours: deep sea, vegetated land, ice.
PALETTE = [(12, 36, 78), (86, 104, 62), (236, 240, 244)]


def rings(topology):
    """Every ring of every polygon, as lists of (lon, lat)."""
    sx, sy = topology["transform"]["scale"]
    tx, ty = topology["transform"]["translate"]
    arcs = []
    for arc in topology["arcs"]:
        x = y = 0
        points = []
        for dx, dy in arc:
            x += dx
            y += dy
            points.append((x * sx + tx, y * sy + ty))
        arcs.append(points)

    def ring(indices):
        out = []
        for i in indices:
            points = arcs[i] if i >= 0 else arcs[~i][::-1]
            out.extend(points if not out else points[1:])
        return out

    for geometry in topology["objects"]["land"]["geometries"]:
        polygons = geometry["arcs"] if geometry["type"] == "MultiPolygon" else [geometry["arcs"]]
        for polygon in polygons:
            for r in polygon:
                yield ring(r)


def fill(all_rings):
    """Even-odd scanline fill at pixel centres: 1 inside land."""
    edges = []

    def edge(x0, y0, x1, y1):
        a = ((x0 + 180.0) / 360.0 * WIDTH, (90.0 - y0) / 180.0 * HEIGHT)
        b = ((x1 + 180.0) / 360.0 * WIDTH, (90.0 - y1) / 180.0 * HEIGHT)
        if a[1] != b[1]:
            edges.append((a, b) if a[1] < b[1] else (b, a))

    for r in all_rings:
        # Longitudes made continuous across the antimeridian.
        unwrapped, offset = [r[0]], 0.0
        for (x0, _), (x1, y1) in zip(r, r[1:]):
            if x1 - x0 > 180.0:
                offset -= 360.0
            elif x1 - x0 < -180.0:
                offset += 360.0
            unwrapped.append((x1 + offset, y1))
        closed = abs(unwrapped[-1][0] - unwrapped[0][0]) < 180.0
        if closed:
            # A ring across the antimeridian: drawn where it lies and a turn either way.
            for shift in (-360.0, 0.0, 360.0):
                ring = [(x + shift, y) for x, y in unwrapped]
                if max(x for x, _ in ring) < -180.0 or min(x for x, _ in ring) > 180.0:
                    continue
                for (x0, y0), (x1, y1) in zip(ring, ring[1:] + ring[:1]):
                    edge(x0, y0, x1, y1)
        else:
            # A ring round a pole (Antarctica): as it is, its step across the
            # antimeridian left out (the pole closes it).
            for (x0, y0), (x1, y1) in zip(r, r[1:] + r[:1]):
                if abs(x1 - x0) <= 180.0:
                    edge(x0, y0, x1, y1)
    rows = [[] for _ in range(HEIGHT)]
    for (ax, ay), (bx, by) in edges:
        for j in range(max(0, int(ay + 0.5) - 1), min(HEIGHT, int(by + 0.5) + 1)):
            y = j + 0.5
            if ay <= y < by:
                rows[j].append(ax + (y - ay) / (by - ay) * (bx - ax))
    grid = []
    for j, xs in enumerate(rows):
        xs.sort()
        row = bytearray(WIDTH)
        for k in range(0, len(xs) - 1, 2):
            start, end = int(xs[k] + 0.5), int(xs[k + 1] + 0.5)
            for i in range(max(0, start), min(WIDTH, end)):
                row[i] = LAND
        grid.append(row)
    return grid


def ice(grid):
    for j, row in enumerate(grid):
        lat = 90.0 - (j + 0.5) / HEIGHT * 180.0
        for i in range(WIDTH):
            lon = (i + 0.5) / WIDTH * 360.0 - 180.0
            greenland = lat > 59.5 and -74.0 < lon < -11.0
            if row[i] == LAND and (lat < -60.0 or lat > 78.0 or greenland):
                row[i] = ICE


def png(path, grid):
    def chunk(kind, data):
        body = kind + data
        return struct.pack(">I", len(data)) + body + struct.pack(">I", zlib.crc32(body) & 0xFFFFFFFF)

    raw = b"".join(b"\x00" + bytes(row) for row in grid)
    with open(path, "wb") as f:
        f.write(b"\x89PNG\r\n\x1a\n")
        f.write(chunk(b"IHDR", struct.pack(">IIBBBBB", WIDTH, HEIGHT, 8, 3, 0, 0, 0)))
        f.write(chunk(b"PLTE", b"".join(bytes(c) for c in PALETTE)))
        f.write(chunk(b"IDAT", zlib.compress(raw, 9)))
        f.write(chunk(b"IEND", b""))


def main():
    source, out = sys.argv[1], sys.argv[2]
    with open(source) as f:
        topology = json.load(f)
    grid = fill(list(rings(topology)))
    ice(grid)
    png(out, grid)


if __name__ == "__main__":
    main()
