"""Independent checks of a cloth's self-intersection for the tests (numpy only, written
apart from the collision code it checks): triangle-triangle intersection of every pair of
triangles that share no vertex, and the closest distance of every vertex to the triangles
that do not hold it."""
import numpy as np


def _aabb_pairs(lo, hi, pad=0.0):
    """Index pairs (i < j) whose boxes overlap (grown by pad)."""
    order = np.argsort(lo[:, 0])
    lo_s, hi_s = lo[order], hi[order]
    pairs = []
    n = len(lo)
    # sweep and prune along x
    start = np.searchsorted(lo_s[:, 0], hi_s[:, 0] + pad, side='right')
    for a in range(n):
        b = np.arange(a + 1, start[a])
        if len(b) == 0:
            continue
        ok = np.all((lo_s[b] - pad <= hi_s[a]) & (hi_s[b] + pad >= lo_s[a]), axis=1)
        b = b[ok]
        pairs.append(np.stack([np.full(len(b), order[a]), order[b]], 1))
    if not pairs:
        return np.zeros((0, 2), int)
    return np.concatenate(pairs)


def _segment_hits_triangle(p, q, a, b, c):
    """Vectorised: does segment p-q cross triangle abc (Moller-Trumbore, parameter in
    [0, 1], barycentrics in [0, 1])?"""
    d = q - p
    e1 = b - a
    e2 = c - a
    h = np.cross(d, e2)
    det = np.einsum('ij,ij->i', e1, h)
    ok = np.abs(det) > 1e-18
    inv = np.where(ok, 1.0 / np.where(ok, det, 1.0), 0.0)
    s = p - a
    u = inv * np.einsum('ij,ij->i', s, h)
    qv = np.cross(s, e1)
    v = inv * np.einsum('ij,ij->i', d, qv)
    t = inv * np.einsum('ij,ij->i', e2, qv)
    return ok & (u >= 0) & (v >= 0) & (u + v <= 1) & (t >= 0) & (t <= 1)


def intersecting_pairs(x, faces):
    """Pairs of triangles sharing no vertex that intersect (an edge of one crosses the
    other)."""
    tri = x[faces]
    pairs = _aabb_pairs(tri.min(1), tri.max(1))
    if len(pairs) == 0:
        return pairs
    fa, fb = faces[pairs[:, 0]], faces[pairs[:, 1]]
    share = (fa[:, :, None] == fb[:, None, :]).any(axis=(1, 2))
    pairs = pairs[~share]
    A, B = tri[pairs[:, 0]], tri[pairs[:, 1]]
    hit = np.zeros(len(pairs), bool)
    for (S, T) in ((A, B), (B, A)):
        for k in range(3):
            hit |= _segment_hits_triangle(S[:, k], S[:, (k + 1) % 3], T[:, 0], T[:, 1],
                                          T[:, 2])
    return pairs[hit]


def _point_segment(p, a, b):
    ab = b - a
    t = np.clip(np.einsum('ij,ij->i', p - a, ab) / np.maximum(
        np.einsum('ij,ij->i', ab, ab), 1e-300), 0, 1)
    return np.linalg.norm(p - (a + t[:, None] * ab), axis=1)


def point_triangle_distance(p, a, b, c):
    """Vectorised distance from points to triangles: the plane when the projection is
    inside, else the nearest edge."""
    n = np.cross(b - a, c - a)
    nn = np.linalg.norm(n, axis=1)
    n = n / np.maximum(nn, 1e-300)[:, None]
    h = np.einsum('ij,ij->i', p - a, n)
    f = p - h[:, None] * n
    # inside test by signs of the sub-triangle normals
    s1 = np.einsum('ij,ij->i', np.cross(b - a, f - a), n)
    s2 = np.einsum('ij,ij->i', np.cross(c - b, f - b), n)
    s3 = np.einsum('ij,ij->i', np.cross(a - c, f - c), n)
    inside = (s1 >= 0) & (s2 >= 0) & (s3 >= 0) & (nn > 0)
    edge = np.minimum(np.minimum(_point_segment(p, a, b), _point_segment(p, b, c)),
                      _point_segment(p, c, a))
    return np.where(inside, np.abs(h), edge)


def closest_vertex_triangle(x, faces, limit):
    """The smallest distance of any vertex to a triangle that does not hold it, among
    those closer than ``limit`` (inf if none)."""
    tri = x[faces]
    lo, hi = tri.min(1) - limit, tri.max(1) + limit
    best = np.inf
    order = np.argsort(x[:, 0])
    xs = x[order, 0]
    for t in range(len(faces)):
        i0, i1 = np.searchsorted(xs, [lo[t, 0], hi[t, 0]])
        cand = order[i0:i1]
        inb = np.all((x[cand] >= lo[t]) & (x[cand] <= hi[t]), axis=1)
        cand = cand[inb & ~np.isin(cand, faces[t])]
        if len(cand) == 0:
            continue
        d = point_triangle_distance(x[cand], np.repeat(tri[t, :1], len(cand), 0),
                                    np.repeat(tri[t, 1:2], len(cand), 0),
                                    np.repeat(tri[t, 2:], len(cand), 0))
        best = min(best, float(d.min()))
    return best
