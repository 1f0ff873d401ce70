"""The candidate pairs of obstacle features (:mod:`.feature_shapes`) and the cloth's
triangles and edges, which :mod:`.features` answers.

For each box or cylinder, the cloth's vertices are taken into its frame. A
triangle or edge is tested against a box's 8 corners or 12 edges only if its bounding
box, grown by ``th + m``, meets the box's and reaches a face plane ``+-h_a`` on at least
two axes. Here m is the step's largest motion of a vertex plus the obstacle surface's
travel. A point within that distance of an edge is that close to two face planes, so a
cloth lying inside a face (a table top) is not tested at all. Against a cylinder the
grown bounding box must meet the curved side (z range meeting [-h, h], its x-y
rectangle's distances from the axis spanning r), and only the corners and edges within
the rectangle's angular window are tested (:func:`_window`); against a mesh, the grown
bounding box must meet the box round its sharp corners, and each corner and edge is
then tested after a bounding-box check. A pair is kept if its
distance at the start is below ``th + m``, and the list is kept over steps (a Verlet
list, :class:`.features.FeatureContact`). The cost is a few comparisons per element and obstacle,
and only with a box, a cylinder or a mesh with sharp edges present.

This module imports no ROS package.
"""
from __future__ import annotations

import math

import numpy as np

from .compiled import kernel
from .contact import PARAM, POS, ROT, SHAPE, SPEED
from .feature_shapes import (CYLINDER, FM_HI, FM_LO, MESH, edge_ends, feature_corners,
                             n_features)
from .surface_query import point_triangle_sq, segment_segment

__all__ = ['candidates', 'fresh', 'largest_motion', 'SKIN']


#: the candidate list's skin: at least this many thicknesses (and 2.5 times the motion
#: of the step that builds it); rebuilt when a vertex has moved half of it, or a box
SKIN = 2.0


@kernel(inline='always')
def _near_rim(loc, ob, k, m, i0, i1, i2):
    """Whether the element with vertices i0, i1, i2 (cylinder-frame coordinates
    ``loc``) may come within ``m`` of cylinder k's corners and edges, all on its curved
    side (rims included): its bounding box grown by m holds a point of that side, so
    its z range meets [-h, h] and the distances from the axis of its x-y rectangle span
    r."""
    h = ob[k, PARAM + 1]
    r = ob[k, PARAM]
    lo = min(loc[i0, 2], min(loc[i1, 2], loc[i2, 2])) - m
    hi = max(loc[i0, 2], max(loc[i1, 2], loc[i2, 2])) + m
    if lo > h or hi < -h:
        return False
    near = 0.0
    far = 0.0
    for a in range(2):
        lo = min(loc[i0, a], min(loc[i1, a], loc[i2, a])) - m
        hi = max(loc[i0, a], max(loc[i1, a], loc[i2, a])) + m
        if lo > 0.0:
            near += lo * lo
        elif hi < 0.0:
            near += hi * hi
        far += max(lo * lo, hi * hi)
    return near <= r * r <= far


@kernel(inline='always')
def _near_mesh(loc, sh, k, m, i0, i1, i2):
    """Whether the element with vertices i0, i1, i2 (obstacle-frame coordinates
    ``loc``), its bounding box grown by m, meets the box round mesh k's sharp corners."""
    for a in range(3):
        lo = min(loc[i0, a], min(loc[i1, a], loc[i2, a])) - m
        hi = max(loc[i0, a], max(loc[i1, a], loc[i2, a])) + m
        if lo > sh.fmeta[k, FM_HI + a] or hi < sh.fmeta[k, FM_LO + a]:
            return False
    return True


@kernel(inline='always')
def _near(loc, ob, sh, k, m, i0, i1, i2, lo, hi, x):
    """Whether the element with vertices i0, i1, i2 (an edge repeats one; ``loc`` in row
    k's frame) may come within ``m`` of row k's corners and edges (:func:`_near_rim`,
    :func:`_near_mesh`, :func:`_near_features`); if so, its bounding box in the world
    (positions ``x``) grown by m into ``lo``, ``hi``."""
    shape = ob[k, SHAPE]
    if shape == CYLINDER:
        near = _near_rim(loc, ob, k, m, i0, i1, i2)
    elif shape == MESH:
        near = _near_mesh(loc, sh, k, m, i0, i1, i2)
    else:
        near = _near_features(loc, ob, k, m, i0, i1, i2)
    if near:
        for q in range(3):
            lo[q] = min(x[i0, q], min(x[i1, q], x[i2, q])) - m
            hi[q] = max(x[i0, q], max(x[i1, q], x[i2, q])) + m
    return near


@kernel(inline='always')
def _window(loc, m, i0, i1, i2, nr):
    """The corners j0 .. j0 + count - 1 (mod K = ``nr``) of a rim whose angle may lie
    within the x-y rectangle of the element's vertices (cylinder-frame coordinates
    ``loc``) grown by m, one more on each side (the rim sides that end there): the
    least and largest angle of the rectangle's corners; all K if it holds the axis."""
    x0 = min(loc[i0, 0], min(loc[i1, 0], loc[i2, 0])) - m
    x1 = max(loc[i0, 0], max(loc[i1, 0], loc[i2, 0])) + m
    y0 = min(loc[i0, 1], min(loc[i1, 1], loc[i2, 1])) - m
    y1 = max(loc[i0, 1], max(loc[i1, 1], loc[i2, 1])) + m
    if x0 <= 0.0 <= x1 and y0 <= 0.0 <= y1:
        return 0, nr
    mid = math.atan2(0.5 * (y0 + y1), 0.5 * (x0 + x1))
    lo = 0.0
    hi = 0.0
    for c in range(4):
        a = math.atan2(y1 if c & 2 else y0, x1 if c & 1 else x0) - mid
        if a > math.pi:                  # unwrapped about the rectangle's middle: the
            a -= 2.0 * math.pi           # rectangle misses the axis, so it subtends
        elif a < -math.pi:               # less than pi
            a += 2.0 * math.pi
        lo = min(lo, a)
        hi = max(hi, a)
    step = 2.0 * math.pi / nr
    j0 = int(math.floor((mid + lo) / step)) - 1
    count = min(nr, int(math.ceil((mid + hi) / step)) + 1 - j0 + 1)
    return j0 % nr, count


@kernel(inline='always')
def _outside(lo, hi, p, q):
    """Whether the box [lo, hi] misses the bounding box of points p and q."""
    for a in range(3):
        if min(p[a], q[a]) > hi[a] or max(p[a], q[a]) < lo[a]:
            return True
    return False


@kernel(inline='always')
def _near_features(loc, ob, k, m, i0, i1, i2):
    """Whether the element with vertices i0, i1, i2 (box-frame coordinates ``loc``; an
    edge repeats one) may come within ``m`` of box k's corners or edges: its bounding box
    grown by m meets the box's, and on at least two axes it reaches a face plane +-h_a
    (a point within m of an edge is within m of two face planes)."""
    planes = 0
    for a in range(3):
        h = ob[k, PARAM + a]
        lo = min(loc[i0, a], min(loc[i1, a], loc[i2, a])) - m
        hi = max(loc[i0, a], max(loc[i1, a], loc[i2, a])) + m
        if lo > h or hi < -h:
            return False
        if (lo <= h <= hi) or (lo <= -h <= hi):
            planes += 1
    return planes >= 2


@kernel()
def candidates(x0, x, faces, edges, ob, th, dt, sh, loc, corners, cand, out):
    """The pairs that may come within ``th`` of a box's or a cylinder's features in this
    step (module docstring), rows (obstacle row k, feature f, cloth element e) of
    ``cand``: f below the row's corner count C corner f against face e, else edge f - C
    against cloth edge e; rows in order, so each obstacle's pairs are contiguous.
    Returns how many (more than ``len(cand)``: only counted, call again with room).
    ``loc`` (n, 3): room for the vertices in an obstacle's frame; ``corners``: room for
    its corners; ``out[0]``: the step's largest motion of a vertex [m]. The features
    are those at the contact thickness ``out[1]`` (a cylinder's rim polygon depends on
    it, :func:`rim_sides`)."""
    n = x0.shape[0]
    move = 0.0
    for i in range(n):
        d0 = x[i, 0] - x0[i, 0]
        d1 = x[i, 1] - x0[i, 1]
        d2 = x[i, 2] - x0[i, 2]
        move = max(move, d0 * d0 + d1 * d1 + d2 * d2)
    move = math.sqrt(move)
    out[0] = move
    lay = out[1]
    cap = cand.shape[0]
    lo = np.empty(3)
    hi = np.empty(3)
    nc = 0
    for k in range(ob.shape[0]):
        ncorner, nedge = n_features(ob, k, lay, sh)
        if ncorner == 0:
            continue
        rim = ob[k, SHAPE] == CYLINDER
        nr = ncorner // 2
        margin = th + move + dt * ob[k, SPEED]
        lim2 = margin * margin
        for i in range(n):
            d0 = x0[i, 0] - ob[k, POS]
            d1 = x0[i, 1] - ob[k, POS + 1]
            d2 = x0[i, 2] - ob[k, POS + 2]
            for a in range(3):
                loc[i, a] = (ob[k, ROT + a] * d0 + ob[k, ROT + 3 + a] * d1
                             + ob[k, ROT + 6 + a] * d2)
        feature_corners(ob, k, lay, sh, corners)
        for t in range(faces.shape[0]):
            a = faces[t, 0]
            b = faces[t, 1]
            c = faces[t, 2]
            if not _near(loc, ob, sh, k, margin, a, b, c, lo, hi, x0):
                continue
            # a box: its 8 corners; a cylinder: the window's on both rims
            j0, count = _window(loc, margin, a, b, c, nr) if rim else (0, ncorner)
            for q in range(2 * count if rim else ncorner):
                f = (q % 2) * nr + (j0 + q // 2) % nr if rim else q
                if _outside(lo, hi, corners[f], corners[f]):
                    continue
                dd, u, v, w = point_triangle_sq(corners[f, 0], corners[f, 1], corners[f, 2],
                                                x0[a], x0[b], x0[c])
                if dd < lim2:
                    if nc < cap:
                        cand[nc, 0] = k
                        cand[nc, 1] = f
                        cand[nc, 2] = t
                    nc += 1
        for e in range(edges.shape[0]):
            a = edges[e, 0]
            b = edges[e, 1]
            if not _near(loc, ob, sh, k, margin, a, b, b, lo, hi, x0):
                continue
            # a box: its 12 edges; a cylinder: the window's rim sides and side edges
            j0, count = _window(loc, margin, a, b, b, nr) if rim else (0, nedge)
            for q in range(3 * count if rim else nedge):
                f = (q % 3) * nr + (j0 + q // 3) % nr if rim else q
                c0, c1 = edge_ends(ob, k, f, ncorner, sh)
                if _outside(lo, hi, corners[c0], corners[c1]):
                    continue
                dd, s, t = segment_segment(x0[a], x0[b], corners[c0], corners[c1])
                if dd < lim2:
                    if nc < cap:
                        cand[nc, 0] = k
                        cand[nc, 1] = ncorner + f
                        cand[nc, 2] = e
                    nc += 1
    return nc


@kernel()
def largest_motion(x, ref):
    """max_i |x_i - ref_i| [m]."""
    out = 0.0
    for i in range(x.shape[0]):
        d0 = x[i, 0] - ref[i, 0]
        d1 = x[i, 1] - ref[i, 1]
        d2 = x[i, 2] - ref[i, 2]
        out = max(out, d0 * d0 + d1 * d1 + d2 * d2)
    return math.sqrt(out)


@kernel()
def fresh(x, x0, xb, skin, ob, built, move):
    """Whether the candidate list built at ``xb`` for the obstacle rows ``built`` (same
    shape as ``ob``) still holds: no vertex has moved half the skin since and no box
    has moved or changed. ``move[0]``: the step's largest motion of a vertex (from x0)."""
    move[0] = largest_motion(x, x0)
    for k in range(ob.shape[0]):
        for j in range(PARAM + 3):
            if ob[k, j] != built[k, j]:
                return False
    return largest_motion(x, xb) <= 0.5 * skin
