"""Closest point of a triangle mesh to query points (for point forces), compiled.

For each query point the closest point over all triangles is found with the region tests
of Ericson, *Real-Time Collision Detection*, Sec. 5.1.5; the result is the triangle index
and the barycentric weights (which sum to 1 and are all >= 0). Brute force over the
triangles: O(m) per query, which is what a handful of force commands per tick needs.
"""
from __future__ import annotations

import numba as nb
import numpy as np

__all__ = ['closest_points']


@nb.njit(cache=True, inline='always')
def _closest_on_triangle(p, a, b, c):
    ab = b - a
    ac = c - a
    ap = p - a
    d1 = ab @ ap
    d2 = ac @ ap
    if d1 <= 0.0 and d2 <= 0.0:
        return 1.0, 0.0, 0.0
    bp = p - b
    d3 = ab @ bp
    d4 = ac @ bp
    if d3 >= 0.0 and d4 <= d3:
        return 0.0, 1.0, 0.0
    vc = d1 * d4 - d3 * d2
    if vc <= 0.0 and d1 >= 0.0 and d3 <= 0.0:
        v = d1 / (d1 - d3)
        return 1.0 - v, v, 0.0
    cp = p - c
    d5 = ab @ cp
    d6 = ac @ cp
    if d6 >= 0.0 and d5 <= d6:
        return 0.0, 0.0, 1.0
    vb = d5 * d2 - d1 * d6
    if vb <= 0.0 and d2 >= 0.0 and d6 <= 0.0:
        w = d2 / (d2 - d6)
        return 1.0 - w, 0.0, w
    va = d3 * d6 - d5 * d4
    if va <= 0.0 and (d4 - d3) >= 0.0 and (d5 - d6) >= 0.0:
        w = (d4 - d3) / ((d4 - d3) + (d5 - d6))
        return 0.0, 1.0 - w, w
    denom = 1.0 / (va + vb + vc)
    v = vb * denom
    w = vc * denom
    return 1.0 - v - w, v, w


@nb.njit(cache=True, parallel=True)
def _closest(x, faces, points, tri, bary):
    for q in nb.prange(points.shape[0]):
        p = points[q]
        best = np.inf
        for t in range(faces.shape[0]):
            a = x[faces[t, 0]]
            b = x[faces[t, 1]]
            c = x[faces[t, 2]]
            u, v, w = _closest_on_triangle(p, a, b, c)
            d = p - (u * a + v * b + w * c)
            dd = d @ d
            if dd < best:
                best = dd
                tri[q] = t
                bary[q, 0] = u
                bary[q, 1] = v
                bary[q, 2] = w


def closest_points(x: np.ndarray, faces: np.ndarray, points: np.ndarray):
    """Closest triangle (k,) int64 and barycentric weights (k, 3) for points (k, 3)."""
    points = np.ascontiguousarray(points, dtype=np.float64).reshape(-1, 3)
    tri = np.zeros(len(points), dtype=np.int64)
    bary = np.zeros((len(points), 3))
    _closest(np.ascontiguousarray(x, dtype=np.float64), faces, points, tri, bary)
    return tri, bary
