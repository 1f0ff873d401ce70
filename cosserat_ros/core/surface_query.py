"""Closest point of a triangle mesh to query points (for point forces), compiled.

For each query point the closest point of one triangle is found with the region tests of
Ericson, *Real-Time Collision Detection*, Sec. 5.1.5; the result is the triangle index and
the barycentric weights (which sum to 1 and are all >= 0).

:func:`closest_points` looks only at the triangles near each point, through a uniform grid
built over the current triangles at every call (O(m) to build; cells twice a triangle's
mean bounding-box side, each triangle listed in every cell its box meets). A query
visits the rings of cells around its point, projected onto the grid's box, until no
unvisited cell can hold a closer triangle: with p' the projection of p onto the box (a
convex set) and q any point of it, |p - q|^2 >= |p - p'|^2 + |p' - q|^2, and every point
of the cells beyond ring r lies at least r h from p'. So the answer is the brute force's
(:func:`closest_points_brute`, the reference it is tested against) at a cost of the
triangles near the point: a few dozen for a point near the cloth. A cell whose distance to
p is no less than the best found so far is skipped. The worst case (a point in mid-air
inside a crumpled cloth's box) stays the brute force's O(m).
"""
from __future__ import annotations

import numba as nb
import numpy as np

from .compiled import kernel

__all__ = ['segment_segment', 'closest_points', 'closest_points_brute', 'triangle_barycentric',
           'point_triangle_sq']


@kernel(inline='always')
def _segment(p0, p1, p2, a, b):
    """(squared distance, t) from point p to segment a + t (b - a), t in [0, 1] (0 for
    a segment of length 0)."""
    e0 = b[0] - a[0]
    e1 = b[1] - a[1]
    e2 = b[2] - a[2]
    ee = e0 * e0 + e1 * e1 + e2 * e2
    t = 0.0
    if ee > 0.0:
        t = min(1.0, max(0.0, ((p0 - a[0]) * e0 + (p1 - a[1]) * e1 + (p2 - a[2]) * e2) / ee))
    q0 = p0 - a[0] - t * e0
    q1 = p1 - a[1] - t * e1
    q2 = p2 - a[2] - t * e2
    return q0 * q0 + q1 * q1 + q2 * q2, t


@kernel(inline='always')
def _degenerate(p0, p1, p2, a, b, c):
    """:func:`triangle_barycentric` of a triangle with no area: the closest point of its
    three edges."""
    dab, tab = _segment(p0, p1, p2, a, b)
    dbc, tbc = _segment(p0, p1, p2, b, c)
    dca, tca = _segment(p0, p1, p2, c, a)
    if dab <= dbc and dab <= dca:
        return 1.0 - tab, tab, 0.0
    if dbc <= dca:
        return 0.0, 1.0 - tbc, tbc
    return tca, 0.0, 1.0 - tca


@kernel(inline='always')
def triangle_barycentric(p0, p1, p2, a, b, c):
    """Barycentric weights (u, v, w) of the point of triangle (a, b, c) closest to point
    (p0, p1, p2): Ericson, Real-Time Collision Detection, 5.1.5 (the Voronoi regions of
    the vertices, then of the edges, then the face), in scalars (no temporary arrays)."""
    ab0 = b[0] - a[0]
    ab1 = b[1] - a[1]
    ab2 = b[2] - a[2]
    ac0 = c[0] - a[0]
    ac1 = c[1] - a[1]
    ac2 = c[2] - a[2]
    ap0 = p0 - a[0]
    ap1 = p1 - a[1]
    ap2 = p2 - a[2]
    d1 = ab0 * ap0 + ab1 * ap1 + ab2 * ap2
    d2 = ac0 * ap0 + ac1 * ap1 + ac2 * ap2
    if d1 <= 0.0 and d2 <= 0.0:
        return 1.0, 0.0, 0.0
    bp0 = p0 - b[0]
    bp1 = p1 - b[1]
    bp2 = p2 - b[2]
    d3 = ab0 * bp0 + ab1 * bp1 + ab2 * bp2
    d4 = ac0 * bp0 + ac1 * bp1 + ac2 * bp2
    if d3 >= 0.0 and d4 <= d3:
        return 0.0, 1.0, 0.0
    vc = d1 * d4 - d3 * d2
    if vc <= 0.0 and d1 >= 0.0 and d3 <= 0.0 and d1 - d3 > 0.0:
        v = d1 / (d1 - d3)
        return 1.0 - v, v, 0.0
    cp0 = p0 - c[0]
    cp1 = p1 - c[1]
    cp2 = p2 - c[2]
    d5 = ab0 * cp0 + ab1 * cp1 + ab2 * cp2
    d6 = ac0 * cp0 + ac1 * cp1 + ac2 * cp2
    if d6 >= 0.0 and d5 <= d6:
        return 0.0, 0.0, 1.0
    vb = d5 * d2 - d1 * d6
    if vb <= 0.0 and d2 >= 0.0 and d6 <= 0.0 and d2 - d6 > 0.0:
        w = d2 / (d2 - d6)
        return 1.0 - w, 0.0, w
    va = d3 * d6 - d5 * d4
    if va <= 0.0 and (d4 - d3) >= 0.0 and (d5 - d6) >= 0.0 and (d4 - d3) + (d5 - d6) > 0.0:
        w = (d4 - d3) / ((d4 - d3) + (d5 - d6))
        return 0.0, 1.0 - w, w
    if not va + vb + vc > 0.0:
        # no area (two corners at one point: an edge of length 0 met the tests above
        # with 0 / 0): the nearer end of the segment the corners span
        return _degenerate(p0, p1, p2, a, b, c)
    den = 1.0 / (va + vb + vc)
    v = vb * den
    w = vc * den
    return 1.0 - v - w, v, w


@kernel(inline='always')
def point_triangle_sq(p0, p1, p2, a, b, c):
    """(squared distance, u, v, w) from point (p0, p1, p2) to triangle (a, b, c): the
    closest point of :func:`triangle_barycentric`."""
    u, v, w = triangle_barycentric(p0, p1, p2, a, b, c)
    e0 = p0 - (u * a[0] + v * b[0] + w * c[0])
    e1 = p1 - (u * a[1] + v * b[1] + w * c[1])
    e2 = p2 - (u * a[2] + v * b[2] + w * c[2])
    return e0 * e0 + e1 * e1 + e2 * e2, u, v, w


@kernel(inline='always')
def _consider(p, x, faces, t, q, best, tri, bary):
    """Triangle t for point q: if closer than ``best`` (a squared distance), it becomes
    the answer (tri, bary); returns the new best."""
    dd, u, v, w = point_triangle_sq(p[0], p[1], p[2], x[faces[t, 0]], x[faces[t, 1]],
                                    x[faces[t, 2]])
    if dd < best:
        tri[q] = t
        bary[q, 0] = u
        bary[q, 1] = v
        bary[q, 2] = w
        return dd
    return best


@kernel(parallel=True)
def _closest(x, faces, points, tri, bary):
    for q in nb.prange(points.shape[0]):
        p = points[q]
        best = np.inf
        for t in range(faces.shape[0]):
            best = _consider(p, x, faces, t, q, best, tri, bary)


def closest_points_brute(x: np.ndarray, faces: np.ndarray, points: np.ndarray):
    """:func:`closest_points` over all triangles for every point (the reference)."""
    points = np.ascontiguousarray(points, dtype=np.float64).reshape(-1, 3)
    tri = np.zeros(len(points), dtype=np.int64)
    bary = np.zeros((len(points), 3))
    _closest(np.ascontiguousarray(x, dtype=np.float64), faces, points, tri, bary)
    return tri, bary


@kernel()
def _span(x, faces, t, k, lo, h, n):
    """The first and last cell along axis k of triangle t's bounding box."""
    a = x[faces[t, 0], k]
    b = x[faces[t, 1], k]
    c = x[faces[t, 2], k]
    return (min(int((min(a, b, c) - lo) / h), n - 1),
            min(int((max(a, b, c) - lo) / h), n - 1))


@kernel()
def _grid(x, faces):
    """The uniform grid over the triangles: (lo (3,), h, dims (3,), start (cells+1,),
    items); the triangles of cell c are items[start[c]:start[c+1]]. Cells twice the mean
    bounding-box side of a triangle, larger if there would be more than 8 m + 64 cells or
    more than 32 m entries (a few stretched triangles only add entries)."""
    m = faces.shape[0]
    lo = np.full(3, np.inf)
    hi = np.full(3, -np.inf)
    h = 0.0
    for t in range(m):
        side = 0.0
        for k in range(3):
            a = x[faces[t, 0], k]
            b = x[faces[t, 1], k]
            c = x[faces[t, 2], k]
            side = max(side, max(a, b, c) - min(a, b, c))
            lo[k] = min(lo[k], min(a, b, c))
            hi[k] = max(hi[k], max(a, b, c))
        h += side
    h = max(2.0 * h / m, 1e-12 * max(1.0, np.max(hi - lo)))
    dims = np.empty(3, dtype=np.int64)
    while True:
        for k in range(3):
            dims[k] = int((hi[k] - lo[k]) / h) + 1
        if dims[0] * dims[1] * dims[2] <= 8 * m + 64:
            entries = 0
            for t in range(m):
                i0, i1 = _span(x, faces, t, 0, lo[0], h, dims[0])
                j0, j1 = _span(x, faces, t, 1, lo[1], h, dims[1])
                l0, l1 = _span(x, faces, t, 2, lo[2], h, dims[2])
                entries += (i1 - i0 + 1) * (j1 - j0 + 1) * (l1 - l0 + 1)
            if entries <= 32 * m:
                break
        h *= 2.0
    start = np.zeros(dims[0] * dims[1] * dims[2] + 1, dtype=np.int64)
    items = np.empty(entries, dtype=np.int64)
    for sweep in range(2):
        if sweep == 1:
            for c in range(1, start.shape[0]):
                start[c] += start[c - 1]
            fill = start.copy()
        for t in range(m):
            i0, i1 = _span(x, faces, t, 0, lo[0], h, dims[0])
            j0, j1 = _span(x, faces, t, 1, lo[1], h, dims[1])
            l0, l1 = _span(x, faces, t, 2, lo[2], h, dims[2])
            for i in range(i0, i1 + 1):
                for j in range(j0, j1 + 1):
                    for l in range(l0, l1 + 1):
                        cell = (i * dims[1] + j) * dims[2] + l
                        if sweep == 0:
                            start[cell + 1] += 1
                        else:
                            items[fill[cell]] = t
                            fill[cell] += 1
    return lo, h, dims, start, items


@kernel(inline='always')
def _cell_of(p, lo, h, n):
    """(the coordinate of p projected onto [lo, lo + n h], its cell, the squared distance
    the projection moved it)."""
    q = min(max(p, lo), lo + n * h)
    return min(int((q - lo) / h), n - 1), (p - q) * (p - q)


@kernel(parallel=True)
def _closest_grid(x, faces, points, lo, h, dims, start, items, tri, bary):
    n0, n1, n2 = dims[0], dims[1], dims[2]
    rmax = max(n0, n1, n2)
    for q in nb.prange(points.shape[0]):
        p = points[q]
        c0, o0 = _cell_of(p[0], lo[0], h, n0)
        c1, o1 = _cell_of(p[1], lo[1], h, n1)
        c2, o2 = _cell_of(p[2], lo[2], h, n2)
        out2 = o0 + o1 + o2                        # |p - p'|^2
        best = np.inf
        r = 0
        while r <= rmax:
            for i in range(max(c0 - r, 0), min(c0 + r, n0 - 1) + 1):
                for j in range(max(c1 - r, 0), min(c1 + r, n1 - 1) + 1):
                    edge = abs(i - c0) == r or abs(j - c1) == r
                    for l in range(max(c2 - r, 0), min(c2 + r, n2 - 1) + 1):
                        if not (edge or abs(l - c2) == r):
                            continue                 # the shell of ring r only
                        # skip a cell that cannot hold anything closer than the best
                        g = 0.0
                        for k, idx in ((0, i), (1, j), (2, l)):
                            below = lo[k] + idx * h - p[k]
                            above = p[k] - (lo[k] + (idx + 1) * h)
                            g += max(below, above, 0.0) ** 2
                        if g >= best:
                            continue
                        c = (i * n1 + j) * n2 + l
                        for e in range(start[c], start[c + 1]):
                            best = _consider(p, x, faces, items[e], q, best, tri, bary)
            if best <= out2 + (r * h) ** 2:
                break
            r += 1


def closest_points(x: np.ndarray, faces: np.ndarray, points: np.ndarray):
    """Closest triangle (k,) int64 and barycentric weights (k, 3) for points (k, 3) (finite,
    and not so far that their squared distances overflow)."""
    x = np.ascontiguousarray(x, dtype=np.float64)
    points = np.ascontiguousarray(points, dtype=np.float64).reshape(-1, 3)
    tri = np.zeros(len(points), dtype=np.int64)
    bary = np.zeros((len(points), 3))
    if len(points):
        lo, h, dims, start, items = _grid(x, faces)
        _closest_grid(x, faces, points, lo, h, dims, start, items, tri, bary)
    return tri, bary


@kernel(inline='always')
def _clamp01(a):
    return min(max(a, 0.0), 1.0)


@kernel(refcount=False)
def segment_segment(p0, p1, q0, q1):
    """Parameters (s, t) of the closest points ``p0 + s (p1 - p0)`` and ``q0 + t (q1 -
    q0)`` of two segments (Ericson, Real-Time Collision Detection, 5.1.9), and their
    squared distance: (dd, s, t)."""
    d10 = p1[0] - p0[0]
    d11 = p1[1] - p0[1]
    d12 = p1[2] - p0[2]
    d20 = q1[0] - q0[0]
    d21 = q1[1] - q0[1]
    d22 = q1[2] - q0[2]
    r0 = p0[0] - q0[0]
    r1 = p0[1] - q0[1]
    r2 = p0[2] - q0[2]
    a = d10 * d10 + d11 * d11 + d12 * d12
    e = d20 * d20 + d21 * d21 + d22 * d22
    f = d20 * r0 + d21 * r1 + d22 * r2
    eps = 1e-30
    if a <= eps and e <= eps:
        s = 0.0
        t = 0.0
    elif a <= eps:
        s = 0.0
        t = _clamp01(f / e)
    else:
        c = d10 * r0 + d11 * r1 + d12 * r2
        if e <= eps:
            t = 0.0
            s = _clamp01(-c / a)
        else:
            b = d10 * d20 + d11 * d21 + d12 * d22
            den = a * e - b * b
            s = _clamp01((b * f - c * e) / den) if den > 0.0 else 0.0
            t = (b * s + f) / e
            if t < 0.0:
                t = 0.0
                s = _clamp01(-c / a)
            elif t > 1.0:
                t = 1.0
                s = _clamp01((b - c) / a)
    e0 = r0 + s * d10 - t * d20
    e1 = r1 + s * d11 - t * d21
    e2 = r2 + s * d12 - t * d22
    return e0 * e0 + e1 * e1 + e2 * e2, s, t
