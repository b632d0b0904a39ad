#!/usr/bin/env python3
"""Write a small RLINES1 test file for bench/embree/trace.

Scene: a closed cube [-0.5, 0.5]^3 (12 triangles) plus, unless --cube-only,
a few hundred small random triangles.  Lines: --bundles bundles of random unit
directions; each bundle is a --grid x --grid grid of parallel lines laid on the
plane through the world origin perpendicular to the direction, spanning
[-1, 1]^2 on that plane, with each line's origin moved back by 2 * direction.
Every line is traced for t in (0, 4).

The script also counts, by brute force in double precision on the exact f32
values it wrote, how many crossings a correct all-hits tracer must find, and
prints that as JSON on stdout (pass "expected_crossings" to trace --expect).
With --cube-only every line crosses the cube 0 or 2 times.

Format (little-endian):
  8 bytes "RLINES1\\0", u32 T, T x 9 f32 (a.xyz b.xyz c.xyz),
  u32 B, per bundle: 3 f32 direction, u32 N, N x 3 f32 origins.
"""

import argparse
import json
import math
import random
import struct

TFAR = 4.0


def f32(x):
    """Round a Python float to the nearest f32, as stored in the file."""
    return struct.unpack("<f", struct.pack("<f", x))[0]


def cube_triangles():
    """12 triangles of the closed cube [-0.5, 0.5]^3 (two per face)."""
    tris = []
    for axis in range(3):
        u, v = (axis + 1) % 3, (axis + 2) % 3
        for side in (-0.5, 0.5):
            quad = []
            for a, b in ((-0.5, -0.5), (0.5, -0.5), (0.5, 0.5), (-0.5, 0.5)):
                p = [0.0, 0.0, 0.0]
                p[axis], p[u], p[v] = side, a, b
                quad.append(p)
            tris.append((quad[0], quad[1], quad[2]))
            tris.append((quad[0], quad[2], quad[3]))
    return tris


def random_unit(rng):
    while True:
        d = [rng.gauss(0.0, 1.0) for _ in range(3)]
        n = math.sqrt(sum(c * c for c in d))
        if n > 1e-6:
            return [c / n for c in d]


def random_small_triangle(rng, size):
    c = [rng.uniform(-1.0, 1.0) for _ in range(3)]
    return tuple([c[k] + rng.uniform(-size, size) for k in range(3)] for _ in range(3))


def basis(d):
    """Two unit vectors u, v with (u, v, d) orthonormal."""
    helper = [1.0, 0.0, 0.0] if abs(d[0]) < 0.9 else [0.0, 1.0, 0.0]
    u = cross(helper, d)
    n = math.sqrt(dot(u, u))
    u = [c / n for c in u]
    return u, cross(d, u)


def dot(a, b):
    return a[0] * b[0] + a[1] * b[1] + a[2] * b[2]


def cross(a, b):
    return [a[1] * b[2] - a[2] * b[1], a[2] * b[0] - a[0] * b[2], a[0] * b[1] - a[1] * b[0]]


def sub(a, b):
    return [a[0] - b[0], a[1] - b[1], a[2] - b[2]]


def crossing_t(org, d, tri):
    """Moller-Trumbore in double precision; t of the crossing or None."""
    a, b, c = tri
    e1, e2 = sub(b, a), sub(c, a)
    p = cross(d, e2)
    det = dot(e1, p)
    if abs(det) < 1e-15:
        return None
    s = sub(org, a)
    bu = dot(s, p) / det
    if bu < 0.0 or bu > 1.0:
        return None
    q = cross(s, e1)
    bv = dot(d, q) / det
    if bv < 0.0 or bu + bv > 1.0:
        return None
    t = dot(e2, q) / det
    return t if 0.0 < t < TFAR else None


def count_crossings(tris, bundles, grid):
    """Brute-force reference: crossings per line, using a 2D pre-filter.

    Each triangle is projected on the bundle's (u, v) plane; only the grid
    lines inside its projected bounding box (plus a margin) are tested.
    """
    step = 2.0 / (grid - 1)
    per_line = []
    for d, _u, _v, origins in bundles:
        u, v = _u, _v
        counts = [0] * len(origins)
        for tri in tris:
            us = [dot(p, u) for p in tri]
            vs = [dot(p, v) for p in tri]
            i0 = max(0, math.floor((min(us) + 1.0) / step - 1))
            i1 = min(grid - 1, math.ceil((max(us) + 1.0) / step + 1))
            j0 = max(0, math.floor((min(vs) + 1.0) / step - 1))
            j1 = min(grid - 1, math.ceil((max(vs) + 1.0) / step + 1))
            for i in range(i0, i1 + 1):
                for j in range(j0, j1 + 1):
                    k = i * grid + j
                    if crossing_t(origins[k], d, tri) is not None:
                        counts[k] += 1
        per_line.extend(counts)
    return per_line


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("out", help="output file")
    ap.add_argument("--cube-only", action="store_true", help="only the 12 cube triangles")
    ap.add_argument("--extra", type=int, default=300, help="random small triangles (default 300)")
    ap.add_argument("--size", type=float, default=0.08, help="half-size of random triangles")
    ap.add_argument("--bundles", type=int, default=64)
    ap.add_argument("--grid", type=int, default=32, help="lines per bundle = grid^2")
    ap.add_argument("--seed", type=int, default=1)
    ap.add_argument("--no-reference", action="store_true",
                    help="skip the brute-force crossing count (slow for big files)")
    args = ap.parse_args()
    if args.grid < 2:
        ap.error("--grid must be at least 2")

    rng = random.Random(args.seed)
    tris = cube_triangles()
    if not args.cube_only:
        tris += [random_small_triangle(rng, args.size) for _ in range(args.extra)]
    tris = [tuple([f32(c) for c in p] for p in tri) for tri in tris]

    step = 2.0 / (args.grid - 1)
    bundles = []
    for _ in range(args.bundles):
        d = random_unit(rng)
        u, v = basis(d)
        origins = []
        for i in range(args.grid):
            for j in range(args.grid):
                s, r = -1.0 + i * step, -1.0 + j * step
                origins.append([f32(s * u[k] + r * v[k] - 2.0 * d[k]) for k in range(3)])
        bundles.append(([f32(c) for c in d], u, v, origins))

    with open(args.out, "wb") as f:
        f.write(b"RLINES1\0")
        f.write(struct.pack("<I", len(tris)))
        for tri in tris:
            f.write(struct.pack("<9f", *(c for p in tri for c in p)))
        f.write(struct.pack("<I", len(bundles)))
        for d, _u, _v, origins in bundles:
            f.write(struct.pack("<3fI", *d, len(origins)))
            for o in origins:
                f.write(struct.pack("<3f", *o))

    summary = {"file": args.out, "triangles": len(tris), "lines": args.bundles * args.grid ** 2}
    if not args.no_reference:
        per_line = count_crossings(tris, bundles, args.grid)
        hist = [0] * 9
        for n in per_line:
            hist[min(n, 8)] += 1
        summary["expected_crossings"] = sum(per_line)
        summary["hist"] = hist
    print(json.dumps(summary))


if __name__ == "__main__":
    main()
