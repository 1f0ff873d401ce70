"""Self-collision's candidates: the pairs of the cloth that can come within the contact
thickness, kept in a Verlet list (:mod:`.self_contact` answers the live ones).

Finding the pairs within ``th`` costs a spatial hash over all triangles and edges
(:func:`build_candidates`: cells of about one mean edge plus the radius; vertices and
edge midpoints sorted by the hash of their cell). The hash is built for a radius ``th +
skin`` at positions ``x_b``; a pair missing from the list was further than ``th + skin``
apart then, so it cannot come within ``th`` before some vertex has moved more than
``skin / 2`` relative to the others (relative: the displacement since ``x_b`` less its
mean, since a rigid translation moves no pair). After each step the largest such
displacement decides whether the list is built again, at the positions the step began
from, with a skin of at least :data:`SKIN` thicknesses and :data:`SKIN_EDGE` of the mean
edge, grown with the step's own relative motion (so that a fast or large step, the
implicit solver's, is covered too). Each step then looks only at the live pairs
(:func:`_select`): those whose distance at the build, less how far their vertices have
moved since, can still be within ``th``. A cloth at rest or falling rigidly builds its
list once and has no live pair until it touches itself.

Partial refresh (:meth:`.self_contact.SelfCollision._refresh`): the references ``x_b``
need not be one snapshot. A pair missing from the list was further than ``th + skin`` apart at its
vertices' own references, so it cannot come within ``th`` before one of them has moved
more than ``skin / 2`` from its reference relative to the others (the distance changes
by at most the two sides' displacements, less any common translation: the mean is still
taken out). So when some vertex runs out of room, only the vertices that moved more than
:data:`REFRESH` of the skin, or that at this step's speed would run out of room before
the fastest of them could again (:func:`_renew`), take new references where the step
began, and the candidates that hold one of them are found again there
(:func:`scan_candidates`: the triangles and edges that hold one against everything, and
those vertices against the other triangles); the rest of the list stands. A crumpled
cloth with a part still moving renews a few percent of its vertices at a time (80 x 80:
~3%, 1-3 ms instead of a build's ~9). When more than :data:`REFRESH_MOST` of the
vertices moved, the thickness changed, or the step needs a skin larger than the list's
or under :data:`REFRESH_SKIN` of it, the list is built anew.

Distances taken again (:meth:`.self_contact.SelfCollision._rebase`): which candidates are live is
decided from their distances where they were last taken, ``x_d``, less how far their
vertices have moved since (relative, as above). The bound holds for any per-vertex
``x_d`` at which the distances were taken, so ``x_d`` need not be the list's references
``x_b``, which only decide when the list runs out of room. A cloth in motion moves
every vertex, so the bound loosens for every pair though few come closer: ~40 steps
after a build of the crumpled 80 x 80 cloth, 2,200 of its 8,600 candidates were live
against ~450 on the build's first step (and refreshed references drift alike). So the
distances of all the candidates are taken again where the step began, one pass over
the list (~0.1 ms at 80 x 80, a build ~9 ms), after every partial refresh and whenever
the live pairs added since the last time, over the steps since, outnumber the
candidates (:meth:`.self_contact.SelfCollision._swollen`, :data:`REBASE_LIVE`).

This module imports no ROS package.
"""
from __future__ import annotations

import math

import numba as nb
import numpy as np

from .compiled import kernel
from .surface_query import point_triangle_sq, segment_segment

__all__ = ['build_candidates', 'scan_candidates', 'first_vertex_lists', 'SKIN', 'SKIN_EDGE',
           'STEPS_PER_BUILD', 'REFRESH', 'REFRESH_MOST', 'REFRESH_SKIN', 'REBASE_LIVE',
           'PAIR_CHUNK']


#: the skin of the candidate list: at least this many contact thicknesses and this
#: fraction of the mean edge (module docstring)
SKIN = 2.0


SKIN_EDGE = 0.25


#: the skin grows with the relative motion of the step that builds the list, to allow
#: half this many such steps before the next build (at most a mean edge long, or 2.5
#: steps' motion)
STEPS_PER_BUILD = 16.0


#: when the list runs out of room, the vertices that moved more than this fraction of the
#: skin renew their candidates (a partial refresh: module docstring) ...
REFRESH = 0.25


#: ... unless they are more than this fraction of all vertices, or the skin the step
#: needs is below this fraction of the list's (a larger skin than needed: more
#: candidates, more of them live): then it is built anew
REFRESH_MOST = 0.25


REFRESH_SKIN = 0.8


#: so many live pair-steps cost what taking every candidate's distance again costs per
#: candidate (:meth:`.self_contact.SelfCollision._swollen`)
REBASE_LIVE = 1.0


@kernel(inline='always')
def _hash(ix, iy, iz, mask):
    return ((ix * 73856093) ^ (iy * 19349663) ^ (iz * 83492791)) & mask


@kernel()
def _bucket_sort(p, cell):
    """Points p (k,3) sorted by the hash of their cell into a table of :data:`HASH_LOAD`
    buckets per point (a power of two): (order, start (mask+2,), cells (k,3), mask)."""
    k = p.shape[0]
    size = 64
    while size < HASH_LOAD * k:
        size *= 2
    mask = size - 1
    cells = np.empty((k, 3), np.int64)
    count = np.zeros(mask + 2, np.int64)
    for i in range(k):
        cx = int(math.floor(p[i, 0] / cell))
        cy = int(math.floor(p[i, 1] / cell))
        cz = int(math.floor(p[i, 2] / cell))
        cells[i, 0] = cx
        cells[i, 1] = cy
        cells[i, 2] = cz
        count[_hash(cx, cy, cz, mask) + 1] += 1
    for b in range(mask + 1):
        count[b + 1] += count[b]
    fill = count[:-1].copy()
    order = np.empty(k, np.int64)
    for i in range(k):
        h = _hash(cells[i, 0], cells[i, 1], cells[i, 2], mask)
        order[fill[h]] = i
        fill[h] += 1
    return order, count, cells, mask


#: buckets of the spatial hash per point hashed (:func:`_bucket_sort`): a cell holds
#: several points, so most buckets hold one cell or none, and a small table stays in cache
HASH_LOAD = 1.0


#: the candidate build's parallel loops: blocks of this many triangles or edges ...
BUILD_BLOCK = 64


#: ... dealt in turn to this many slabs (block b to slab b % BUILD_SLABS), so that every
#: slab gets a like share of a dense region (a fold); the threads share the slabs
BUILD_SLABS = 8


@kernel(inline='always')
def _vt_pair(i, t, a, b, c, x, rest, r2, th2, out, outd, pos, end):
    """Vertex i and triangle t = (a, b, c) as a candidate when they are within the radius
    at x but not within th at rest; returns the next row."""
    dd = point_triangle_sq(x[i, 0], x[i, 1], x[i, 2], x[a], x[b], x[c])[0]
    if dd >= r2:
        return pos
    if point_triangle_sq(rest[i, 0], rest[i, 1], rest[i, 2], rest[a], rest[b],
                         rest[c])[0] < th2:
        return pos
    if pos < end:
        out[pos, 0] = i
        out[pos, 1] = t
        outd[pos] = math.sqrt(dd)
    return pos + 1


@kernel()
def _vt_block(s0, s1, tris, x, rest, faces, radius, th, cell, mask, order, start, cells,
              out, outd, pos, end):
    """The vertex-triangle candidates of triangles ``tris[s0:s1]`` with every vertex
    (:func:`scan_candidates`), written from row ``pos`` of ``out`` / ``outd`` while below
    row ``end``; returns the row after the last (counted on beyond ``end``: the slab was
    too short)."""
    r2 = radius * radius
    th2 = th * th
    for s in range(s0, s1):
        t = tris[s]
        a = faces[t, 0]
        b = faces[t, 1]
        c = faces[t, 2]
        lo0 = min(x[a, 0], x[b, 0], x[c, 0]) - radius
        lo1 = min(x[a, 1], x[b, 1], x[c, 1]) - radius
        lo2 = min(x[a, 2], x[b, 2], x[c, 2]) - radius
        hi0 = max(x[a, 0], x[b, 0], x[c, 0]) + radius
        hi1 = max(x[a, 1], x[b, 1], x[c, 1]) + radius
        hi2 = max(x[a, 2], x[b, 2], x[c, 2]) + radius
        for cx in range(int(math.floor(lo0 / cell)), int(math.floor(hi0 / cell)) + 1):
            for cy in range(int(math.floor(lo1 / cell)), int(math.floor(hi1 / cell)) + 1):
                for cz in range(int(math.floor(lo2 / cell)), int(math.floor(hi2 / cell)) + 1):
                    h = _hash(cx, cy, cz, mask)
                    for q in range(start[h], start[h + 1]):
                        i = order[q]
                        if cells[i, 0] != cx or cells[i, 1] != cy or cells[i, 2] != cz:
                            continue
                        if i == a or i == b or i == c:
                            continue
                        if (x[i, 0] < lo0 or x[i, 0] > hi0 or x[i, 1] < lo1
                                or x[i, 1] > hi1 or x[i, 2] < lo2 or x[i, 2] > hi2):
                            continue
                        pos = _vt_pair(i, t, a, b, c, x, rest, r2, th2, out, outd, pos, end)
    return pos


@kernel()
def _tv_block(s0, s1, verts, x, rest, faces, tfresh, first, fstart, reach, radius, th, cell,
              mask, order, start, cells, out, outd, pos, end):
    """The vertex-triangle candidates of vertices ``verts[s0:s1]`` with the triangles not
    marked in ``tfresh`` (:func:`scan_candidates`), as :func:`_vt_block`: a triangle
    within ``radius`` of vertex i has every vertex within ``reach`` (radius and its
    longest edge) of it, so it is found once, through its first vertex
    (``first[fstart[j]:fstart[j + 1]]``: the triangles whose first vertex is j) among the
    vertices in the cells of i's box grown by ``reach``."""
    r2 = radius * radius
    th2 = th * th
    for s in range(s0, s1):
        i = verts[s]
        for cx in range(int(math.floor((x[i, 0] - reach) / cell)),
                        int(math.floor((x[i, 0] + reach) / cell)) + 1):
            for cy in range(int(math.floor((x[i, 1] - reach) / cell)),
                            int(math.floor((x[i, 1] + reach) / cell)) + 1):
                for cz in range(int(math.floor((x[i, 2] - reach) / cell)),
                                int(math.floor((x[i, 2] + reach) / cell)) + 1):
                    h = _hash(cx, cy, cz, mask)
                    for q in range(start[h], start[h + 1]):
                        j = order[q]
                        if fstart[j] == fstart[j + 1]:
                            continue
                        if cells[j, 0] != cx or cells[j, 1] != cy or cells[j, 2] != cz:
                            continue
                        if (abs(x[i, 0] - x[j, 0]) > reach or abs(x[i, 1] - x[j, 1]) > reach
                                or abs(x[i, 2] - x[j, 2]) > reach):
                            continue
                        for u in range(fstart[j], fstart[j + 1]):
                            t = first[u]
                            if tfresh[t]:
                                continue
                            a = faces[t, 0]
                            b = faces[t, 1]
                            c = faces[t, 2]
                            if i == a or i == b or i == c:
                                continue
                            pos = _vt_pair(i, t, a, b, c, x, rest, r2, th2, out, outd, pos,
                                           end)
    return pos


@kernel()
def _ee_block(s0, s1, eds, efresh, x, rest, edges, mid, half, hmax, radius, th, cell, mask,
              order, start, cells, out, outd, pos, end):
    """The edge-edge candidates of edges ``eds[s0:s1]`` with every other edge, a pair of
    two edges marked in ``efresh`` once (:func:`scan_candidates`), written as (lower,
    higher) index, as :func:`_vt_block`."""
    r2 = radius * radius
    th2 = th * th
    for s in range(s0, s1):
        e = eds[s]
        a0 = edges[e, 0]
        a1 = edges[e, 1]
        # the edge's box grown by radius (b_lo, b_hi), and by the longest half edge too
        b_lo0 = min(x[a0, 0], x[a1, 0]) - radius
        b_lo1 = min(x[a0, 1], x[a1, 1]) - radius
        b_lo2 = min(x[a0, 2], x[a1, 2]) - radius
        b_hi0 = max(x[a0, 0], x[a1, 0]) + radius
        b_hi1 = max(x[a0, 1], x[a1, 1]) + radius
        b_hi2 = max(x[a0, 2], x[a1, 2]) + radius
        for cx in range(int(math.floor((b_lo0 - hmax) / cell)),
                        int(math.floor((b_hi0 + hmax) / cell)) + 1):
            for cy in range(int(math.floor((b_lo1 - hmax) / cell)),
                            int(math.floor((b_hi1 + hmax) / cell)) + 1):
                for cz in range(int(math.floor((b_lo2 - hmax) / cell)),
                                int(math.floor((b_hi2 + hmax) / cell)) + 1):
                    h = _hash(cx, cy, cz, mask)
                    for q in range(start[h], start[h + 1]):
                        f = order[q]
                        if f == e or (f < e and efresh[f]):
                            continue
                        if cells[f, 0] != cx or cells[f, 1] != cy or cells[f, 2] != cz:
                            continue
                        lim = half[e] + half[f] + radius
                        dm = ((mid[e, 0] - mid[f, 0]) ** 2 + (mid[e, 1] - mid[f, 1]) ** 2
                              + (mid[e, 2] - mid[f, 2]) ** 2)
                        if dm > lim * lim:
                            continue
                        c0 = edges[f, 0]
                        c1 = edges[f, 1]
                        if c0 == a0 or c0 == a1 or c1 == a0 or c1 == a1:
                            continue
                        # apart along an axis by more than radius: the segments too
                        if (min(x[c0, 0], x[c1, 0]) > b_hi0 or max(x[c0, 0], x[c1, 0]) < b_lo0
                                or min(x[c0, 1], x[c1, 1]) > b_hi1
                                or max(x[c0, 1], x[c1, 1]) < b_lo1
                                or min(x[c0, 2], x[c1, 2]) > b_hi2
                                or max(x[c0, 2], x[c1, 2]) < b_lo2):
                            continue
                        # the lower edge first: the same bits as the full build's
                        if e < f:
                            dd = segment_segment(x[a0], x[a1], x[c0], x[c1])[0]
                        else:
                            dd = segment_segment(x[c0], x[c1], x[a0], x[a1])[0]
                        if dd >= r2:
                            continue
                        if segment_segment(rest[a0], rest[a1], rest[c0], rest[c1])[0] < th2:
                            continue
                        if pos < end:
                            out[pos, 0] = min(e, f)
                            out[pos, 1] = max(e, f)
                            outd[pos] = math.sqrt(dd)
                        pos += 1
    return pos


@kernel(inline='always')
def _slabs(items, out):
    """For a parallel loop over ``items`` in blocks into ``out``: (blocks, rows per block
    (zeros), rows per slab, the slabs' rows and distances)."""
    cap = out.shape[0] // BUILD_SLABS
    nbl = (items + BUILD_BLOCK - 1) // BUILD_BLOCK
    return (nbl, np.zeros(nbl, np.int64), cap, np.empty((BUILD_SLABS * cap, 2), np.int64),
            np.empty(BUILD_SLABS * cap))


@kernel(inline='always')
def _in_order(nblocks, count, tmp, tmpd, cap, out, outd):
    """The slabs' rows (:data:`BUILD_SLABS` slabs of ``cap`` rows in ``tmp``, ``tmpd``)
    into ``out``, ``outd`` in block order, so in the order of a serial loop; ``count``:
    the rows of each block. Returns the total, or when a slab overflowed the length the
    output must have for the slabs to fit (above ``len(out)``)."""
    used = np.zeros(BUILD_SLABS, np.int64)
    total = 0
    for b in range(nblocks):
        used[b % BUILD_SLABS] += count[b]
        total += count[b]
    if used.max() > cap:
        return max(total, BUILD_SLABS * used.max(), out.shape[0] + 1)
    used[:] = 0
    k = 0
    for b in range(nblocks):
        sl = b % BUILD_SLABS
        src = sl * cap + used[sl]
        for r in range(count[b]):
            out[k, 0] = tmp[src + r, 0]
            out[k, 1] = tmp[src + r, 1]
            outd[k] = tmpd[src + r]
            k += 1
        used[sl] += count[b]
    return total


@kernel(parallel=True)
def scan_candidates(x, rest, faces, edges, radius, th, tris, verts, tfresh, first, fstart,
                    eds, efresh, vt, ee, vtd, eed):
    """The candidate pairs within ``radius`` of each other at x (module docstring: no
    pair incident at a vertex, none within ``th`` in the rest shape) that involve the
    triangles ``tris``, the vertices ``verts`` or the edges ``eds``, into ``vt`` and
    ``ee`` (their distances at x into ``vtd`` and ``eed``); returns their counts (a count
    above an array's length: make it at least that long and call again).

    * vertex-triangle: every vertex against the triangles ``tris`` (the vertices in the
      cells of each triangle's box grown by radius), then the vertices ``verts`` against
      the triangles not marked in ``tfresh`` (those are in ``tris``; through the
      triangles' first vertices, ``first[fstart[j]:fstart[j + 1]]`` those of vertex j:
      :func:`first_vertex_lists`);
    * edge-edge (e, f), e < f: the edges ``eds`` against every other edge (the midpoints
      in the cells of each edge's box grown by radius and the longest half edge, within
      the two half lengths + radius of its own midpoint), a pair of two edges marked in
      ``efresh`` found once.

    All of them (``tris`` and ``eds`` every triangle and edge, ``verts`` empty) is the
    full build (:func:`build_candidates`); those of the vertices that moved, a partial
    one (:meth:`.self_contact.SelfCollision._refresh`). Each loop runs on the threads in blocks of
    :data:`BUILD_BLOCK` triangles, vertices or edges, dealt to :data:`BUILD_SLABS` slabs
    (each a share of the output's length), and is then put in block order: the same
    lists, in the same order, as one loop over all."""
    ne = edges.shape[0]
    # edge midpoints and half lengths; cells about one mean edge long
    hmax = 0.0
    hsum = 0.0
    mid = np.empty((ne, 3))
    half = np.empty(ne)
    for e in range(ne):
        a = edges[e, 0]
        b = edges[e, 1]
        l2 = 0.0
        for k in range(3):
            mid[e, k] = 0.5 * (x[a, k] + x[b, k])
            l2 += (x[a, k] - x[b, k]) ** 2
        half[e] = 0.5 * math.sqrt(l2)
        hmax = max(hmax, half[e])
        hsum += half[e]
    cell = 2.0 * hsum / max(ne, 1) + radius
    # vertex-triangle, 1: every vertex against the triangles tris
    order, start, cells, mask = _bucket_sort(x, cell)
    nt = tris.shape[0]
    nbl, count, cap, tmp, tmpd = _slabs(nt, vt)
    for sl in nb.prange(BUILD_SLABS):
        pos = sl * cap
        for b in range(sl, nbl, BUILD_SLABS):
            end = _vt_block(b * BUILD_BLOCK, min(nt, (b + 1) * BUILD_BLOCK), tris, x, rest,
                            faces, radius, th, cell, mask, order, start, cells, tmp, tmpd,
                            pos, (sl + 1) * cap)
            count[b] = end - pos
            pos = end
    nvt = _in_order(nbl, count, tmp, tmpd, cap, vt, vtd)
    # vertex-triangle, 2: the vertices verts against the triangles not in tris
    nv = verts.shape[0]
    if nv > 0 and nvt <= vt.shape[0]:
        rest_vt = vt[nvt:]
        rest_vtd = vtd[nvt:]
        nbl, count, cap, tmp, tmpd = _slabs(nv, rest_vt)
        for sl in nb.prange(BUILD_SLABS):
            pos = sl * cap
            for b in range(sl, nbl, BUILD_SLABS):
                end = _tv_block(b * BUILD_BLOCK, min(nv, (b + 1) * BUILD_BLOCK), verts, x,
                                rest, faces, tfresh, first, fstart, radius + 2.0 * hmax,
                                radius, th, cell, mask, order, start, cells, tmp, tmpd, pos,
                                (sl + 1) * cap)
                count[b] = end - pos
                pos = end
        nvt += _in_order(nbl, count, tmp, tmpd, cap, rest_vt, rest_vtd)
    # edge-edge: the edges eds against every other edge
    order, start, cells, mask = _bucket_sort(mid, cell)
    nd = eds.shape[0]
    nbl, count, cap, tmp, tmpd = _slabs(nd, ee)
    for sl in nb.prange(BUILD_SLABS):
        pos = sl * cap
        for b in range(sl, nbl, BUILD_SLABS):
            end = _ee_block(b * BUILD_BLOCK, min(nd, (b + 1) * BUILD_BLOCK), eds, efresh, x,
                            rest, edges, mid, half, hmax, radius, th, cell, mask, order,
                            start, cells, tmp, tmpd, pos, (sl + 1) * cap)
            count[b] = end - pos
            pos = end
    nee = _in_order(nbl, count, tmp, tmpd, cap, ee, eed)
    return nvt, nee


def build_candidates(x, rest, faces, edges, radius, th, vt, ee, vtd, eed):
    """Every vertex-triangle pair (i, t) and edge-edge pair (e, f), e < f, within
    ``radius`` of each other at x (module docstring: no pair incident at a vertex, none
    within ``th`` in the rest shape), into ``vt`` and ``ee``, their distances at x into
    ``vtd`` and ``eed``; returns their counts (a count above an array's length: make it
    at least that long and call again). :func:`scan_candidates` over all triangles and
    edges."""
    none = np.zeros(0, np.int64)
    return scan_candidates(x, rest, faces, edges, radius, th,
                           np.arange(len(faces), dtype=np.int64), none,
                           np.ones(len(faces), np.bool_), none, np.zeros(len(x) + 1, np.int64),
                           np.arange(len(edges), dtype=np.int64), np.ones(len(edges), np.bool_),
                           vt, ee, vtd, eed)


def first_vertex_lists(faces, n):
    """(first, fstart): the triangles whose first vertex is j are
    ``first[fstart[j]:fstart[j + 1]]`` (:func:`scan_candidates`), for n vertices."""
    first = np.argsort(faces[:, 0], kind='stable').astype(np.int64)
    fstart = np.zeros(n + 1, np.int64)
    np.cumsum(np.bincount(faces[:, 0], minlength=n), out=fstart[1:])
    return first, fstart


#: pairs per task of :func:`_pair_geometry`'s parallel loop
PAIR_CHUNK = 256


@kernel(inline='always')
def _mean_shift(x, ref):
    """mean_j (x_j - ref_j), as three floats."""
    n = x.shape[0]
    c0 = 0.0
    c1 = 0.0
    c2 = 0.0
    for i in range(n):
        c0 += x[i, 0] - ref[i, 0]
        c1 += x[i, 1] - ref[i, 1]
        c2 += x[i, 2] - ref[i, 2]
    return c0 / n, c1 / n, c2 / n


@kernel()
def _displacement(x, ref, out):
    """out[i] = |(x_i - ref_i) - mean_j (x_j - ref_j)|: how far vertex i moved from ref
    relative to the others (a rigid translation moves no pair; module docstring);
    returns the largest."""
    c0, c1, c2 = _mean_shift(x, ref)
    best = 0.0
    for i in range(x.shape[0]):
        out[i] = math.sqrt((x[i, 0] - ref[i, 0] - c0) ** 2 + (x[i, 1] - ref[i, 1] - c1) ** 2
                           + (x[i, 2] - ref[i, 2] - c2) ** 2)
        best = max(best, out[i])
    return best


@kernel()
def _displacements(x, x0, xb, xd, step, dmoved):
    """:func:`_displacement` of x from the step's start ``x0`` and from where the
    candidates' distances were taken, ``xd``, into ``step`` and ``dmoved``; returns the
    largest of the first and the largest from the list's references ``xb`` (whose own
    array only a refresh needs)."""
    c = np.zeros(9)
    n = x.shape[0]
    for i in range(n):
        for k in range(3):
            c[k] += x[i, k] - x0[i, k]
            c[3 + k] += x[i, k] - xb[i, k]
            c[6 + k] += x[i, k] - xd[i, k]
    c /= n
    b0 = 0.0
    b1 = 0.0
    for i in range(n):
        step[i] = math.sqrt((x[i, 0] - x0[i, 0] - c[0]) ** 2 + (x[i, 1] - x0[i, 1] - c[1]) ** 2
                            + (x[i, 2] - x0[i, 2] - c[2]) ** 2)
        moved = ((x[i, 0] - xb[i, 0] - c[3]) ** 2 + (x[i, 1] - xb[i, 1] - c[4]) ** 2
                 + (x[i, 2] - xb[i, 2] - c[5]) ** 2)
        dmoved[i] = math.sqrt((x[i, 0] - xd[i, 0] - c[6]) ** 2
                              + (x[i, 1] - xd[i, 1] - c[7]) ** 2
                              + (x[i, 2] - xd[i, 2] - c[8]) ** 2)
        b0 = max(b0, step[i])
        b1 = max(b1, moved)
    return b0, math.sqrt(b1)


@kernel()
def _select(vt, vtd, nvt, edges, ee, eed, nee, faces, th, moved, step, reach, live):
    """The candidates that may come within ``th`` this step, into ``live``; returns
    their count. Vertex i moved ``moved[i]`` relative to the others since the
    candidates' distances were taken (at ``x_d``: module docstring) and ``step[i]`` in
    this step (:func:`_displacement`); ``reach[i] = moved[i] + 2 step[i]`` bounds how far
    it got, at any time in the step and after a response (which moves a vertex by no
    more than the step's own approach), relative to ``x_d``. A pair whose distance there
    exceeds ``th`` plus its vertices' reaches is left out."""
    for i in range(reach.shape[0]):
        reach[i] = moved[i] + 2.0 * step[i]
    k = 0
    for p in range(nvt):
        t = vt[p, 1]
        r = (reach[vt[p, 0]] + max(reach[faces[t, 0]], reach[faces[t, 1]],
                                  reach[faces[t, 2]]))
        if vtd[p] < th + r:
            live[k] = p
            k += 1
    for q in range(nee):
        e = ee[q, 0]
        f = ee[q, 1]
        r = (max(reach[edges[e, 0]], reach[edges[e, 1]])
             + max(reach[edges[f, 0]], reach[edges[f, 1]]))
        if eed[q] < th + r:
            live[k] = nvt + q
            k += 1
    return k


@kernel(parallel=True)
def _distances(x, faces, edges, vt, nvt, ee, nee, vtd, eed):
    """Every candidate's distance at x, into ``vtd`` and ``eed`` (the same arithmetic as
    the build's: :func:`_vt_pair`, :func:`_ee_block`), in chunks of :data:`PAIR_CHUNK`."""
    for c in nb.prange((nvt + PAIR_CHUNK - 1) // PAIR_CHUNK):
        for p in range(c * PAIR_CHUNK, min(nvt, (c + 1) * PAIR_CHUNK)):
            i = vt[p, 0]
            t = vt[p, 1]
            vtd[p] = math.sqrt(point_triangle_sq(x[i, 0], x[i, 1], x[i, 2], x[faces[t, 0]],
                                                 x[faces[t, 1]], x[faces[t, 2]])[0])
    for c in nb.prange((nee + PAIR_CHUNK - 1) // PAIR_CHUNK):
        for q in range(c * PAIR_CHUNK, min(nee, (c + 1) * PAIR_CHUNK)):
            e = ee[q, 0]
            f = ee[q, 1]
            eed[q] = math.sqrt(segment_segment(x[edges[e, 0]], x[edges[e, 1]],
                                               x[edges[f, 0]], x[edges[f, 1]])[0])


@kernel()
def _room(vt, vtd, nvt, edges, ee, eed, nee, faces, th, moved, dmoved, half_skin):
    """How far every vertex may still move relative to the others [m] before some
    candidate pair could come within ``th`` or the list could miss a pair: the least of
    ``half_skin`` less the largest ``moved`` (since the list's references: its own bound,
    module docstring) and, over the candidates, half of their distance less ``th`` and
    less how far each side's vertices have moved since it was taken (``dmoved``)."""
    out = half_skin
    for i in range(moved.shape[0]):
        out = min(out, half_skin - moved[i])
    for p in range(nvt):
        t = vt[p, 1]
        r = dmoved[vt[p, 0]] + max(dmoved[faces[t, 0]], dmoved[faces[t, 1]],
                                   dmoved[faces[t, 2]])
        out = min(out, 0.5 * (vtd[p] - th - r))
    for q in range(nee):
        e = ee[q, 0]
        f = ee[q, 1]
        r = (max(dmoved[edges[e, 0]], dmoved[edges[e, 1]])
             + max(dmoved[edges[f, 0]], dmoved[edges[f, 1]]))
        out = min(out, 0.5 * (eed[q] - th - r))
    return out


@kernel()
def _renew(x0, xb, moved, step, skin, most, fresh):
    """The vertices of a partial refresh (:meth:`.self_contact.SelfCollision._refresh`), marked in
    ``fresh``: those that moved more than :data:`REFRESH` of the skin since their
    reference ``xb`` (``moved``: relative to the others, :func:`_displacement`), and those
    that at the speed of this step (``step``: its relative displacement) run out of room
    (half the skin) before the fastest renewed vertex would again at its own. When they
    are at most ``most``, their reference moves to where the step began, ``x0``, less the
    mean displacement since the references (so that there they have moved none relative
    to the others). Returns how many they are."""
    n = x0.shape[0]
    fast = 0.0
    for i in range(n):
        fast = max(fast, step[i])
    horizon = 0.5 * skin / max(fast, 1e-300)     # [steps]
    k = 0
    for i in range(n):
        fresh[i] = (moved[i] > REFRESH * skin
                    or moved[i] + horizon * step[i] > 0.5 * skin)
        k += fresh[i]
    if k > most:
        return k
    c0, c1, c2 = _mean_shift(x0, xb)
    for i in range(n):
        if fresh[i]:
            xb[i, 0] = x0[i, 0] - c0
            xb[i, 1] = x0[i, 1] - c1
            xb[i, 2] = x0[i, 2] - c2
    return k


@kernel(inline='always')
def _compact(pairs, d, count, drop0, drop1):
    """Keeps, in order at the front, the first ``count`` pairs (rows of ``pairs``, with
    ``d``) whose first member is not marked in ``drop0`` nor second in ``drop1``;
    returns how many."""
    k = 0
    for p in range(count):
        if drop0[pairs[p, 0]] or drop1[pairs[p, 1]]:
            continue
        pairs[k, 0] = pairs[p, 0]
        pairs[k, 1] = pairs[p, 1]
        d[k] = d[p]
        k += 1
    return k


@kernel()
def _keep_untouched(fresh, faces, edges, vt, vtd, nvt, ee, eed, nee, tfresh, efresh):
    """Of the candidates, keeps (in order, at the front) those with no vertex marked in
    ``fresh``, marks the triangles and edges that hold one in ``tfresh`` and ``efresh``;
    returns (candidates kept: vertex-triangle, edge-edge; the marked triangles, vertices
    and edges)."""
    for t in range(faces.shape[0]):
        tfresh[t] = fresh[faces[t, 0]] or fresh[faces[t, 1]] or fresh[faces[t, 2]]
    for e in range(edges.shape[0]):
        efresh[e] = fresh[edges[e, 0]] or fresh[edges[e, 1]]
    k = _compact(vt, vtd, nvt, fresh, tfresh)
    j = _compact(ee, eed, nee, efresh, efresh)
    return k, j, np.nonzero(tfresh)[0], np.nonzero(fresh)[0], np.nonzero(efresh)[0]
