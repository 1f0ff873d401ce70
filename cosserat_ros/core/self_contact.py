"""Self-collision: the cloth folds onto itself without passing through.

Contacts
--------
Two kinds of pair, each within the contact thickness ``th`` (the same as obstacle
contact's, ``Control.contact_params[0]``):

* vertex-triangle: vertex i and a triangle (a, b, c) that does not hold i, closest point
  ``q = u x_a + v x_b + w x_c`` (Ericson 5.1.5, :func:`.surface_query.point_triangle_sq`);
* edge-edge: edges (a0, a1) and (b0, b1) that share no vertex, closest points
  ``p = (1 - s) x_a0 + s x_a1`` and ``q = (1 - t) x_b0 + t x_b1`` (Ericson 5.1.9,
  :func:`segment_segment`).

Pairs that lie within ``th`` of each other in the rest shape (a sliver triangle's vertex
next to its neighbour) are topology, not contact, and are left out.

Both are one constraint on up to four vertices k with weights ``w_k`` (side A positive,
side B negative: (1, -u, -v, -w) and (1 - s, s, -(1 - t), -t)), the unit normal ``n``
from B to A and the distance d, all taken at the positions ``x0`` where the step began::

    g = d + n . sum_k w_k (x_k - x0_k)          the gap at the step's end, to first order

Response: inelastic, on positions and velocities together (Bridson, Fedkiw and Anderson
2002, Sec. 7.1-7.2, as a Gauss-Seidel projection)
-----------------------------------------------------------------------------------
After every step (explicit or implicit) each pair must end with ``g >= target`` where
``target = th`` for a pair that began outside the layer and ``d + min(th - d, S dt)``
for one that began inside it (back to the layer at most at the speed :data:`SEP_SPEED`;
drift of second order, never a kick). A pair short of its target gets the impulse that
closes the gap exactly, shared by inverse mass (a pinned or held vertex has none)::

    lam  = (target - g) / W,     W = sum_k w_k^2 / m_k
    dx_k = w_k lam n / m_k                      (x_k += dx_k,  v_k += dx_k / dt)

which conserves momentum (sum_k m_k dx_k = lam n sum_k w_k = 0 since the weights of
each side sum to one) and removes the pair's approach velocity (inelastic). Coulomb
friction between the layers follows on the pair's relative tangential motion of the
step ``r_t = (I - n n^T) sum_k w_k (x_k - x0_k)``: it stops if ``|r_t| <= mu (target -
g)`` (static: the tangential correction bounded by mu times the normal one, in the same
units) and is otherwise reduced by that much. Pairs share vertices, so the corrections
are swept (Gauss-Seidel) over the pairs that were short until none moves, at most
:data:`SWEEPS` sweeps, then every live pair is checked again and the rounds repeat (at
most :data:`ROUNDS`; what is still short by more than :data:`SLACK` of th is reported
and kept from approaching further by the next step). A vertex the response pushes into
an obstacle's contact layer is put back on it at once (position and velocity, the
obstacle's impulse added to its contact force), so a layer pressed onto the ground stays
on it and the ground carries the weight of both.

Sliding contacts: the gap above is linear in the step's displacement, so a vertex sliding
over a curved or kinked layer sees it drift by about ``|slip|^2 / d``. Whenever a pair
acted or began the step within ``th``, the response therefore runs once more from the
exact geometry at the step's end (closest points and normals there; friction already
applied), against the same targets, which every pass takes from the pair's distance
where the step began: a pair that began outside the layer ends on it, not inside by the
drift, and one that began inside ends no closer than it began. Only when that drift can
exceed the slack (:func:`drifts`: (2 step)^2 / d > SLACK th, with step the step's
relative motion and d the closest live pair's distance where it began); a layer at rest
on another or sliding slowly over it, whose gap the first pass then holds to within
twice the slack (its own tolerance and the drift), skips it (half the cost of a folded
cloth's response).

Energy: the response removes the energy :func:`_ledger` measures (kinetic, and the
potential change over its displacement), counted as dissipation in ``State.acc``.

Why no crossing: a pair that ends every step at ``g >= th`` along its own normal cannot
change sides within a step whose relative motion is below ``th`` (the explicit step
moves a vertex far less: a 5 m/s fall at dt = 3e-4 s is 1.5 mm). A larger step (the
implicit solver's: 1 m/s relative at 1/60 s is 17 mm) is answered in stages: the
solver's displacement is split into the fewest equal parts that each move a vertex at
most :data:`STAGE` th relative to the others, and each part's constraints are linearised
where the previous part ended (the response so far included); velocities change by the
positions' change over the whole step (backward Euler's x1 = x0 + dt v1 still holds).

Candidates: a Verlet list
-------------------------
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

Partial refresh (:meth:`SelfCollision._refresh`): the references ``x_b`` need not be one
snapshot. A pair missing from the list was further than ``th + skin`` apart at its
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

Distances taken again (:meth:`SelfCollision._rebase`): which candidates are live is
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
candidates (:meth:`SelfCollision._swollen`, :data:`REBASE_LIVE`).

This module imports no ROS package.
"""
from __future__ import annotations

import math
from typing import Dict

import numba as nb
import numpy as np

from .compiled import kernel
from .contact import C_FORCE, C_FORCE2, C_ID, C_ID2, _bit, distance, released
from .surface_query import point_triangle_sq
from .terms.jet import cross

__all__ = ['SelfCollision', 'segment_segment', 'build_candidates', 'warm', 'SWEEPS',
           'ROUNDS', 'SEP_SPEED', 'DEFAULT_FRICTION']

#: Gauss-Seidel sweeps over the pairs short of their target, per round
SWEEPS = 16
#: rounds of (check every live pair, sweep the short ones)
ROUNDS = 4
#: [m/s] the fastest a pair that began inside the layer is moved back out to it
SEP_SPEED = 0.05
#: a step whose relative motion exceeds this many thicknesses is answered in stages
#: (module docstring: the implicit solver's large steps)
STAGE = 0.5
#: a pair short of its target by less than this fraction of th counts as satisfied
SLACK = 1e-2
#: friction coefficient between two layers of the cloth (static = kinetic)
DEFAULT_FRICTION = 0.5
#: the skin of the candidate list: at least this many contact thicknesses and this
#: fraction of the mean edge (module docstring)
SKIN = 2.0
SKIN_EDGE = 0.25
#: the skin grows with the relative motion of the step that builds the list, to allow
#: half this many such steps before the next build (at most a mean edge long, or 2.5
#: steps' motion)
STEPS_PER_BUILD = 16.0
#: [m/s] the relative speed a cloth is assumed to have at least when the steps it can
#: take without a response are counted (:meth:`SelfCollision.free_steps`)
FREE_SPEED = 0.25
#: when the list runs out of room, the vertices that moved more than this fraction of the
#: skin renew their candidates (a partial refresh: module docstring) ...
REFRESH = 0.25
#: ... unless they are more than this fraction of all vertices, or the skin the step
#: needs is below this fraction of the list's (a larger skin than needed: more
#: candidates, more of them live): then it is built anew
REFRESH_MOST = 0.25
REFRESH_SKIN = 0.8
#: so many live pair-steps cost what taking every candidate's distance again costs per
#: candidate (:meth:`SelfCollision._swollen`)
REBASE_LIVE = 1.0


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
    one (:meth:`SelfCollision._refresh`). Each loop runs on the threads in blocks of
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


@kernel(inline='always')
def _gap(p, x, x0, gi, gw, gn, gd, go):
    """Gap of pair p at the step's end, along its normal at the start; ``go[p]``: side
    B's own displacement over the step when it is not the cloth (a moving obstacle's
    point, :mod:`.features`; zero here)."""
    g = gd[p] - (gn[p, 0] * go[p, 0] + gn[p, 1] * go[p, 1] + gn[p, 2] * go[p, 2])
    for k in range(4):
        j = gi[p, k]
        g += gw[p, k] * (gn[p, 0] * (x[j, 0] - x0[j, 0]) + gn[p, 1] * (x[j, 1] - x0[j, 1])
                         + gn[p, 2] * (x[j, 2] - x0[j, 2]))
    return g


@kernel(inline='always')
def _deficit(p, x, x0, gi, gw, gn, gd, go, g0, th, sep):
    """How far pair p falls short of its target at the step's end [m]: the target from
    its distance ``g0[p]`` where the whole step began, the gap linearised at x0; the pair
    is short when this exceeds the slack ``SLACK th``."""
    return _target(g0[p], th, sep) - _gap(p, x, x0, gi, gw, gn, gd, go)


@kernel(inline='always')
def _target(d, th, sep):
    """The gap a pair must end the step with (module docstring)."""
    # inside the layer: back out by sep beyond the slack that counts as satisfied, so a
    # pair inside does climb back (a slack larger than sep would let it stay and drift)
    return th if d >= th else d + min(th - d, sep + SLACK * th)


#: pairs per task of :func:`_pair_geometry`'s parallel loop
PAIR_CHUNK = 256


@kernel(parallel=True)
def _pair_geometry(x0, x, faces, edges, vt, nvt, ee, live, nlive, gi, gw, gn, gd, go, g0,
                   first, th, sep, flag):
    """The constraint of each live candidate ``live[:nlive]`` (an index into the
    vertex-triangle pairs, then the edge-edge pairs) at the step's start x0 (module
    docstring), in slot p of: vertices
    gi (P,4), weights gw (P,4), normal gn (P,3) from side B to side A, distance gd (P,).
    A pair at zero distance takes the triangle's normal (or the edges' cross product)
    turned towards A's side; if that too is undefined it gets weight 0 (skipped).
    ``first``: x0 is where the step began, and g0 (each pair's distance there, which
    sets its target: :func:`_deficit`) takes gd. flag[p]: 1 if the pair is short of its
    target at the step's end x (:func:`_short`). In chunks of :data:`PAIR_CHUNK` pairs
    (:func:`_pair_range`: the arrays' reference counts change once a chunk)."""
    for c in nb.prange((nlive + PAIR_CHUNK - 1) // PAIR_CHUNK):
        _pair_range(c * PAIR_CHUNK, min(nlive, (c + 1) * PAIR_CHUNK), x0, x, faces, edges,
                    vt, nvt, ee, live, gi, gw, gn, gd, go, g0, first, th, sep, flag)


@kernel(refcount=False)
def _pair_range(lo, hi, x0, x, faces, edges, vt, nvt, ee, live, gi, gw, gn, gd, go, g0,
                first, th, sep, flag):
    """:func:`_pair_geometry` for the live pairs lo..hi-1, without reference counting
    (:func:`.compiled.kernel`: the rows of x0 it passes on are views)."""
    for p in range(lo, hi):
        cand = live[p]
        if cand < nvt:
            i = vt[cand, 0]
            t = vt[cand, 1]
            a = faces[t, 0]
            b = faces[t, 1]
            c = faces[t, 2]
            dd, u, v, w = point_triangle_sq(x0[i, 0], x0[i, 1], x0[i, 2], x0[a], x0[b],
                                            x0[c])
            gi[p, 0] = i
            gi[p, 1] = a
            gi[p, 2] = b
            gi[p, 3] = c
            gw[p, 0] = 1.0
            gw[p, 1] = -u
            gw[p, 2] = -v
            gw[p, 3] = -w
            # the fallback direction: the triangle's normal, (b - a) x (c - a)
            p1, q1, p2, q2 = a, b, a, c
        else:
            q = cand - nvt
            e = ee[q, 0]
            f = ee[q, 1]
            a0 = edges[e, 0]
            a1 = edges[e, 1]
            b0 = edges[f, 0]
            b1 = edges[f, 1]
            dd, s, t = segment_segment(x0[a0], x0[a1], x0[b0], x0[b1])
            gi[p, 0] = a0
            gi[p, 1] = a1
            gi[p, 2] = b0
            gi[p, 3] = b1
            gw[p, 0] = 1.0 - s
            gw[p, 1] = s
            gw[p, 2] = t - 1.0
            gw[p, 3] = -t
            # the fallback direction: the edges' cross product
            p1, q1, p2, q2 = a0, a1, b0, b1
        f0, f1, f2 = cross(x0[q1, 0] - x0[p1, 0], x0[q1, 1] - x0[p1, 1], x0[q1, 2] - x0[p1, 2],
                           x0[q2, 0] - x0[p2, 0], x0[q2, 1] - x0[p2, 1], x0[q2, 2] - x0[p2, 2])
        # the vector from side B's point to side A's: sum_k w_k x0_k
        r0 = 0.0
        r1 = 0.0
        r2 = 0.0
        for k in range(4):
            j = gi[p, k]
            r0 += gw[p, k] * x0[j, 0]
            r1 += gw[p, k] * x0[j, 1]
            r2 += gw[p, k] * x0[j, 2]
        set_normal(p, r0, r1, r2, f0, f1, f2, gw, gn, gd, g0, first)
        flag[p] = 1 if _deficit(p, x, x0, gi, gw, gn, gd, go, g0, th, sep) > SLACK * th else 0


@kernel(inline='always')
def set_normal(p, r0, r1, r2, f0, f1, f2, gw, gn, gd, g0, first):
    """Pair p's normal gn[p] = r / |r| (r: from side B's point to side A's) and distance
    gd[p] = |r|; at zero distance the fallback direction f normalised, and if that too is
    zero the pair gets weight 0 (skipped). ``first``: g0[p] (the distance that sets the
    pair's target) takes gd[p] too."""
    d = math.sqrt(r0 * r0 + r1 * r1 + r2 * r2)
    if d > 1e-12:
        gn[p, 0] = r0 / d
        gn[p, 1] = r1 / d
        gn[p, 2] = r2 / d
    else:
        fn = math.sqrt(f0 * f0 + f1 * f1 + f2 * f2)
        if fn > 0.0:
            gn[p, 0] = f0 / fn
            gn[p, 1] = f1 / fn
            gn[p, 2] = f2 / fn
        else:
            for k in range(gw.shape[1]):
                gw[p, k] = 0.0
            gn[p, 0] = 0.0
            gn[p, 1] = 0.0
            gn[p, 2] = 1.0
    gd[p] = d
    if first:
        g0[p] = d


@kernel(refcount=False)
def _short(x, x0, gi, gw, gn, gd, go, g0, npair, th, sep, slack, flag):
    """flag[p] = 1 for every pair short of its target by more than ``slack`` [m];
    returns how many."""
    k = 0
    for p in range(npair):
        f = 1 if _deficit(p, x, x0, gi, gw, gn, gd, go, g0, th, sep) > slack else 0
        flag[p] = f
        k += f
    return k


@kernel(inline='always')
def _kick(j, x, v, dt, c0, c1, c2):
    """Move vertex j by c (c0, c1, c2) [m] and its velocity by c / dt."""
    x[j, 0] += c0
    x[j, 1] += c1
    x[j, 2] += c2
    v[j, 0] += c0 / dt
    v[j, 1] += c1 / dt
    v[j, 2] += c2 / dt


@kernel(refcount=False)
def _onto_obstacles(j, x, v, dt, mass, ob, meta, data, th, contact):
    """Vertex j, just moved by the response, back onto the contact layer of every
    obstacle it entered (position and velocity, as an impulse of the obstacle: its force
    is added to ``Control.contact``), but those it is released from (placed through it:
    :func:`.contact.released`)."""
    free = released(contact, j)
    for k in range(ob.shape[0]):
        if free & _bit(k):
            continue
        d, n0, n1, n2 = distance(ob, meta, data, k, x[j, 0], x[j, 1], x[j, 2])
        if d >= th:
            continue
        c = th - d
        _kick(j, x, v, dt, c * n0, c * n1, c * n2)
        f = mass[j] * c / (dt * dt)
        contact[j, C_FORCE] += f * n0
        contact[j, C_FORCE + 1] += f * n1
        contact[j, C_FORCE + 2] += f * n2
        if contact[j, C_ID] < 0.0 or contact[j, C_ID] == k:
            contact[j, C_ID] = k
        else:                                   # the step's second obstacle: its share
            contact[j, C_FORCE2] += f * n0
            contact[j, C_FORCE2 + 1] += f * n1
            contact[j, C_FORCE2 + 2] += f * n2
            contact[j, C_ID2] = k


@kernel()
def _all_onto_obstacles(x, v, dt, inv, mass, ob, meta, data, th, contact):
    """:func:`_onto_obstacles` for every free vertex."""
    for j in range(x.shape[0]):
        if inv[j] > 0.0:
            _onto_obstacles(j, x, v, dt, mass, ob, meta, data, th, contact)


@kernel(refcount=False)
def _project(p, x, x0, v, inv, mass, gi, gw, gn, gd, go, g0, th, sep, slack, mu, dt, ob,
             meta, data, contact):
    """The impulse of pair p (module docstring) if it is short of its target; returns 1
    if it acted, else 0 (also for a pair without weight: degenerate, or all pinned)."""
    short = _deficit(p, x, x0, gi, gw, gn, gd, go, g0, th, sep)
    if short <= slack:
        return 0
    W = 0.0
    for k in range(4):
        W += gw[p, k] * gw[p, k] * inv[gi[p, k]]
    if W <= 0.0:
        return 0
    lam = short / W
    n0 = gn[p, 0]
    n1 = gn[p, 1]
    n2 = gn[p, 2]
    # relative tangential motion of the step (before this normal correction)
    r0 = -go[p, 0]
    r1 = -go[p, 1]
    r2 = -go[p, 2]
    for k in range(4):
        j = gi[p, k]
        r0 += gw[p, k] * (x[j, 0] - x0[j, 0])
        r1 += gw[p, k] * (x[j, 1] - x0[j, 1])
        r2 += gw[p, k] * (x[j, 2] - x0[j, 2])
    rn = r0 * n0 + r1 * n1 + r2 * n2
    t0 = r0 - rn * n0
    t1 = r1 - rn * n1
    t2 = r2 - rn * n2
    rt = math.sqrt(t0 * t0 + t1 * t1 + t2 * t2)
    # friction: remove up to mu (target - g) of the tangential slip, in the same units
    fl = 0.0
    if rt > 0.0 and mu > 0.0:
        fl = min(rt, mu * short) / (W * rt)
    for k in range(4):
        j = gi[p, k]
        s = gw[p, k] * inv[j]
        if s == 0.0:
            continue
        _kick(j, x, v, dt, s * (lam * n0 - fl * t0), s * (lam * n1 - fl * t1),
              s * (lam * n2 - fl * t2))
        if ob.shape[0] > 0:
            _onto_obstacles(j, x, v, dt, mass, ob, meta, data, th, contact)
    return 1


@kernel()
def _inverse_mass(mass, pinned, inv):
    """inv[i] = 1 / m_i, 0 for a pinned or held vertex."""
    for i in range(mass.shape[0]):
        inv[i] = 0.0 if pinned[i] else 1.0 / mass[i]


@kernel(refcount=False)
def respond(x, x0, v, inv, mass, gi, gw, gn, gd, go, g0, npair, th, mu, dt, sep, slack,
            flag, active, ob, meta, data, contact, stats):
    """The response of the module docstring over the live pairs' constraints (from
    :func:`_pair_geometry`, which also flagged the short ones); x and v in place; inverse
    masses ``inv`` (:func:`_inverse_mass`). ``stats``: (pairs that acted, rounds, sweeps,
    pairs still short at the end, the closest gap at the end [m]); ``sep``: how far a
    pair inside the layer moves back out (:func:`_target`)."""
    acted = 0
    sweeps = 0
    rounds = 0
    na = 0
    for rnd in range(ROUNDS):
        # the first round's flags come with the geometry (:func:`_pair_geometry`)
        if rnd > 0 and _short(x, x0, gi, gw, gn, gd, go, g0, npair, th, sep, slack, flag) == 0:
            break
        na = 0
        for p in range(npair):
            if flag[p]:
                active[na] = p
                na += 1
        if na == 0:
            break
        rounds += 1
        for sw in range(SWEEPS):
            sweeps += 1
            moved = 0
            for q in range(na):
                moved += _project(active[q], x, x0, v, inv, mass, gi, gw, gn, gd, go, g0,
                                  th, sep, slack, mu, dt, ob, meta, data, contact)
            if sw == 0:
                acted += moved
            if moved == 0:
                break
    # the last check found every pair satisfied, or the rounds ran out: count what is
    # short and the closest gap among the pairs of the last round
    left = 0
    closest = np.inf
    if rounds > 0:
        for q in range(na):
            p = active[q]
            closest = min(closest, _gap(p, x, x0, gi, gw, gn, gd, go))
            left += 1 if _deficit(p, x, x0, gi, gw, gn, gd, go, g0, th, sep) > slack else 0
    stats[0] = acted
    stats[1] = rounds
    stats[2] = sweeps
    stats[3] = left
    stats[4] = closest


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
    """The vertices of a partial refresh (:meth:`SelfCollision._refresh`), marked in
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


@kernel()
def _ledger(x, xs, v, vs, v0, mass, dt):
    """The energy the response removed [J]: minus the change of kinetic energy and of
    potential energy, the latter as minus the work of the step's force ``f_i = m_i (vs_i
    - v0_i) / dt`` over the response's displacement ``x_i - xs_i`` by the trapezoid rule
    (the force falls from f to what the contact balances; xs, vs: position and velocity
    before the response, v0: velocity before the step). In a resting contact, where a
    force pushes a vertex into the layer each step and the response takes it back, this
    reads zero; a collision without force reads its lost kinetic energy."""
    out = 0.0
    for i in range(x.shape[0]):
        m = mass[i]
        for k in range(3):
            c = x[i, k] - xs[i, k]
            if c == 0.0 and v[i, k] == vs[i, k]:
                continue
            out -= 0.5 * m * (v[i, k] * v[i, k] - vs[i, k] * vs[i, k])
            out += 0.5 * m * (vs[i, k] - v0[i, k]) / dt * c
    return out


def overrun_speed(speed: float, overran: bool, moved: float, steps: int,
                  dt: float) -> float:
    """The least speed [m/s] the next calls of several steps assume, after a call of
    ``steps`` steps that moved the cloth ``moved`` [m] and ``overran`` (or not) the room
    it was given, where they assumed at least ``speed`` before: a cloth that speeds up
    within calls would overrun each, so an overrun's speed, doubled, becomes the floor,
    halved after each call that did not overrun (here and in :mod:`.features`)."""
    return max(speed, 2.0 * moved / (steps * dt)) if overran else 0.5 * speed


def drifts(step: float, th: float, d: float) -> bool:
    """Whether a step whose relative motion is ``step`` [m] (the most any vertex moved
    relative to the others) can make the gap of a pair at distance ``d`` (the least
    among the live pairs where the step began), linearised there, drift by more than the
    slack: two vertices of a pair moving apart tangentially by up to 2 step drift by
    about (2 step)^2 / d (module docstring). A layer resting on another (d about th) or
    sliding slowly over it (on fold.yaml's 2 mm layer at dt = 2e-4 s: below ~0.5 m/s)
    skips the second pass; a pair deep inside the layer makes every moving step take it."""
    return (2.0 * step) ** 2 > SLACK * th * max(d, 0.0)


def in_stages(x, v, x0, xe, xt, stages, answer, inv, mass, control, th, dt):
    """The response to a step from ``x0`` to ``x`` whose relative motion exceeds
    :data:`STAGE` th, in ``stages`` equal parts of the solver's displacement, each
    answered by ``answer(start, j)`` linearised where the last one ended (``start``:
    ``x0`` for the first, then ``xe``; ``xt``: room for where the solver took the
    cloth); x and v in place. Returns the sum of what the answers returned (the pairs
    that acted). A vertex pushed towards an obstacle in an early stage went on along
    the solver's path, which ended on the contact layer: it is put back onto it. Used
    by self-collision and by the obstacles' corners and edges (:mod:`.features`)."""
    xt[:] = x
    x[:] = x0
    acted = 0
    for j in range(stages):
        start = x0 if j == 0 else xe
        xe[:] = x
        x += (xt - x0) / stages
        acted += answer(start, j)
    if control.obstacles.shape[0] > 0:
        _all_onto_obstacles(x, v, dt, inv, mass, control.obstacles, control.sdf_meta,
                            control.sdf_data, th, control.contact)
    return acted


class SelfCollision:
    """The self-collision of one simulator's cloth (module docstring).

    ``begin(x, v)`` before a run of steps (the state the first step starts from),
    ``after_step(state, control, coeff, dt)`` after each step: the response, in place;
    returns the energy it removed [J] (:func:`_ledger`; the balance's dissipation). While
    no pair is near, a call of several steps (:meth:`free_steps`, checked by
    :meth:`overran`) takes no response and ends with ``begin`` instead."""

    def __init__(self, mesh):
        n = mesh.n_vertices
        self.rest = np.ascontiguousarray(mesh.vertices, dtype=np.float64)
        self.faces = np.ascontiguousarray(mesh.faces, dtype=np.int64)
        self.edges = np.ascontiguousarray(mesh.edges, dtype=np.int64)
        # the mean rest edge: the skin grows to it at most, unless one step moves further
        self.edge = float(mesh.mean_edge_length)
        self.friction = DEFAULT_FRICTION
        self.x0 = np.zeros((n, 3))
        self.v0 = np.zeros((n, 3))               # velocities where the step began
        self.xs = np.zeros((n, 3))               # before the response
        self.vs = np.zeros((n, 3))
        self.xe = np.zeros((n, 3))               # after the first response
        self.xt = np.zeros((n, 3))               # where a staged step's solver ended
        self.xb = np.zeros((n, 3))              # the list's references (module docstring)
        self.skin = 0.0
        self.vt = np.zeros((max(64, n), 2), np.int64)
        self.ee = np.zeros((max(64, 2 * n), 2), np.int64)
        self.vtd = np.zeros(len(self.vt))
        self.eed = np.zeros(len(self.ee))
        self.nvt = 0
        self.nee = 0
        self.nlive = 0
        self._alloc(len(self.vt) + len(self.ee))
        self.moved = np.zeros(n)                # relative displacement since xb
        self.step_moved = np.zeros(n)           # ... and in this step
        self.xd = np.zeros((n, 3))              # where the candidates' distances were taken
        self.dmoved = np.zeros(n)               # relative displacement since then
        self.rebases = 0                        # their distances taken again (_rebase)
        self.live_based = -1                    # live pairs on the first step after that
        self.since_based = 0                    # steps since
        self.reach = np.zeros(n)
        self.inv = np.zeros(n)
        self.stats = np.zeros(5)
        self.stats[4] = np.inf
        self.builds = 0
        self.room = 0.0                          # what free_steps allowed the last call
        self.still = np.zeros((n, 3))            # zero velocities (free_steps)
        self.speeds = np.zeros(n)
        self.overrun_speed = 0.0                 # [m/s] (overran)
        self.built_th = 0.0                      # the thickness of the last build
        self.refreshes = 0                       # partial refreshes (_refresh)
        self.fresh = np.zeros(n, np.bool_)
        self.tfresh = np.zeros(len(self.faces), np.bool_)
        self.efresh = np.zeros(len(self.edges), np.bool_)
        self.first, self.fstart = first_vertex_lists(self.faces, n)

    def _alloc(self, p):
        self.live = np.zeros(p, np.int64)
        self.gi = np.zeros((p, 4), np.int64)
        self.gw = np.zeros((p, 4))
        self.gn = np.zeros((p, 3))
        self.gd = np.zeros(p)
        self.go = np.zeros((p, 3))            # side B is the cloth: it moves itself
        self.g0 = np.zeros(p)
        self.flag = np.zeros(p, np.int64)
        self.active = np.zeros(p, np.int64)

    def begin(self, x: np.ndarray, v: np.ndarray) -> None:
        self.x0[:] = x
        self.v0[:] = v

    def free_steps(self, x: np.ndarray, v: np.ndarray, th: float, dt: float) -> int:
        """How many steps the cloth can probably take from (x, v) with no pair coming
        within ``th`` (so without a response after each; fewer than 2: answer each
        step): none while the last step had live pairs or before the first list; else
        the steps in which the fastest vertex relative to the others, at its present
        speed but at least :data:`FREE_SPEED`, covers half the room the list leaves
        (:func:`_room`). :meth:`overran` then checks the call (a cloth can speed up)."""
        self.room = 0.0
        if self.builds == 0 or self.nlive or th != self.built_th:
            return 0
        _displacement(x, self.xb, self.moved)
        _displacement(x, self.xd, self.dmoved)
        room = _room(self.vt, self.vtd, self.nvt, self.edges, self.ee, self.eed, self.nee,
                     self.faces, th, self.moved, self.dmoved, 0.5 * self.skin)
        if room <= 0.0:
            return 0
        self.room = room
        # the fastest vertex relative to the cloth's mean motion (a rigid translation
        # brings no pair closer): v's displacement from rest, the mean taken out
        speed = max(_displacement(v, self.still, self.speeds), FREE_SPEED,
                    self.overrun_speed)
        return int(min(0.5 * room / (speed * dt), 2.0 ** 62))

    def overran(self, x_start: np.ndarray, x: np.ndarray, steps: int, dt: float) -> bool:
        """Whether a call of ``steps`` steps allowed by :meth:`free_steps` moved some
        vertex, relative to the others, as far as the room it was given (then it is
        stepped again, one step per call with the response), and the speed the next
        calls assume (:func:`overrun_speed`)."""
        moved = _displacement(x, x_start, self.step_moved)
        over = moved >= self.room
        self.overrun_speed = overrun_speed(self.overrun_speed, over, moved, steps, dt)
        return over

    def _build(self, x: np.ndarray, th: float, skin: float) -> None:
        while True:
            nvt, nee = build_candidates(x, self.rest, self.faces, self.edges, th + skin, th,
                                        self.vt, self.ee, self.vtd, self.eed)
            if nvt <= len(self.vt) and nee <= len(self.ee):
                break
            if nvt > len(self.vt):
                self.vt = np.zeros((2 * nvt, 2), np.int64)
                self.vtd = np.zeros(2 * nvt)
            if nee > len(self.ee):
                self.ee = np.zeros((2 * nee, 2), np.int64)
                self.eed = np.zeros(2 * nee)
        self.nvt, self.nee = nvt, nee
        if len(self.gd) < nvt + nee:
            self._alloc(2 * (nvt + nee))
        self.xb[:] = x
        self.xd[:] = x
        self.skin = skin
        self.built_th = th
        self.builds += 1
        self.live_based = -1
        self.since_based = 0

    def _swollen(self) -> bool:
        """Whether taking every candidate's distance again now costs less than what the
        live pairs added since the distances were last taken cost over those steps
        (:data:`REBASE_LIVE`): each step checks every pair whose vertices' displacement
        since then may have brought it within th, and a cloth in motion moves every
        vertex, so the live pairs grow though few pairs come closer."""
        extra = (self.nlive - self.live_based) * self.since_based
        return extra > REBASE_LIVE * (self.nvt + self.nee)

    def _rebase(self, x0: np.ndarray) -> None:
        """Every candidate's distance taken again at ``x0`` (where the step began): the
        live pairs are then those that can come within th from there."""
        self.xd[:] = x0
        _distances(x0, self.faces, self.edges, self.vt, self.nvt, self.ee, self.nee,
                   self.vtd, self.eed)
        self.rebases += 1
        self.live_based = -1
        self.since_based = 0

    def _refresh(self, x0: np.ndarray, x: np.ndarray, th: float) -> bool:
        """A partial refresh of the list (module docstring), where the step began (``x0``;
        ``x``: where it ended): the vertices that moved more than :data:`REFRESH` of the
        skin since their references or would soon run out of room (:func:`_renew`) take
        ``x0`` as their reference, and every candidate that holds one of them is found
        again there.
        Returns False, and the list must be built anew, when they are more than
        :data:`REFRESH_MOST` of the vertices or some vertex is still more than half the
        skin from its reference."""
        _displacement(x, self.xb, self.moved)
        if _renew(x0, self.xb, self.moved, self.step_moved, self.skin,
                  REFRESH_MOST * len(x0), self.fresh) > REFRESH_MOST * len(x0):
            return False
        kv, ke, tris, verts, eds = _keep_untouched(
            self.fresh, self.faces, self.edges, self.vt, self.vtd, self.nvt, self.ee,
            self.eed, self.nee, self.tfresh, self.efresh)
        while True:
            nv, ne = scan_candidates(self.xb, self.rest, self.faces, self.edges,
                                     th + self.skin, th, tris, verts, self.tfresh,
                                     self.first, self.fstart, eds, self.efresh, self.vt[kv:],
                                     self.ee[ke:], self.vtd[kv:], self.eed[ke:])
            if kv + nv <= len(self.vt) and ke + ne <= len(self.ee):
                break
            if kv + nv > len(self.vt):
                self.vt = np.concatenate([self.vt[:kv], np.zeros((2 * (kv + nv), 2), np.int64)])
                self.vtd = np.concatenate([self.vtd[:kv], np.zeros(2 * (kv + nv))])
            if ke + ne > len(self.ee):
                self.ee = np.concatenate([self.ee[:ke], np.zeros((2 * (ke + ne), 2), np.int64)])
                self.eed = np.concatenate([self.eed[:ke], np.zeros(2 * (ke + ne))])
        self.nvt, self.nee = kv + nv, ke + ne
        if len(self.gd) < self.nvt + self.nee:
            self._alloc(2 * (self.nvt + self.nee))
        self.refreshes += 1
        return _displacement(x, self.xb, self.moved) <= 0.5 * self.skin

    def _respond(self, start, x, v, control, mass, th, mu, dt) -> None:
        """The live pairs' constraints linearised at ``start`` (the step's start x0 the
        first time, which sets each pair's target), and the response to them."""
        sep = SEP_SPEED * dt
        _pair_geometry(start, x, self.faces, self.edges, self.vt, self.nvt, self.ee,
                       self.live, self.nlive, self.gi, self.gw, self.gn, self.gd, self.go,
                       self.g0, start is self.x0, th, sep, self.flag)
        respond(x, start, v, self.inv, mass, self.gi, self.gw, self.gn, self.gd, self.go,
                self.g0, self.nlive, th, mu, dt, sep, SLACK * th, self.flag, self.active,
                control.obstacles, control.sdf_meta, control.sdf_data, control.contact,
                self.stats)

    def _staged(self, x, v, control, mass, th, dt, stages) -> None:
        """The response to a step whose relative motion exceeds :data:`STAGE` th
        (:func:`in_stages`)."""
        def answer(start, j):
            self._respond(start, x, v, control, mass, th, self.friction, dt)
            return self.stats[0]
        self.stats[0] = in_stages(x, v, self.x0, self.xe, self.xt, stages, answer,
                                  self.inv, mass, control, th, dt)

    def after_step(self, state, control, coeff, dt: float) -> float:
        th = float(control.contact_params[0])
        x = state.x
        step, far = _displacements(x, self.x0, self.xb, self.xd, self.step_moved,
                                   self.dmoved)
        skin = max(SKIN * th, SKIN_EDGE * self.edge, 2.5 * step,
                   min(STEPS_PER_BUILD * step, self.edge))
        out = self.builds == 0 or th != self.built_th or far > 0.5 * self.skin
        if out and not (self.builds and th == self.built_th
                        and REFRESH_SKIN * self.skin <= skin <= self.skin
                        and self._refresh(self.x0, x, th)):
            self._build(self.x0, th, skin)
            self.dmoved[:] = self.step_moved        # built where this step began
        elif out or self._swollen():
            # refreshed (the new candidates' distances are at their references) or
            # swollen: every distance taken again where this step began
            self._rebase(self.x0)
            self.dmoved[:] = self.step_moved
        self.nlive = _select(self.vt, self.vtd, self.nvt, self.edges, self.ee, self.eed,
                             self.nee, self.faces, th, self.dmoved, self.step_moved,
                             self.reach, self.live)
        self.since_based += 1
        if self.live_based < 0:
            self.live_based = self.nlive          # the first step after a rebase
        diss = 0.0
        if self.nlive:
            _inverse_mass(coeff.mass, control.pinned, self.inv)
            self.xs[:] = x
            self.vs[:] = state.v
            stages = int(math.ceil(step / (STAGE * th)))
            if stages > 1:
                self._staged(x, state.v, control, coeff.mass, th, dt, stages)
            else:
                self._respond(self.x0, x, state.v, control, coeff.mass, th, self.friction,
                              dt)
            closest = self.g0[:self.nlive].min()
            if (self.stats[0] > 0 or closest < th) and drifts(step, th, closest):
                # pairs in contact: once more from the exact geometry at the step's end
                # (the linearised gap drifts by |slip|^2 / d under a sliding contact;
                # module docstring), friction already applied
                acted = self.stats[0]
                self.xe[:] = x
                self._respond(self.xe, x, state.v, control, coeff.mass, th, 0.0, dt)
                self.stats[0] += acted
            if self.stats[0] > 0:
                diss = _ledger(x, self.xs, state.v, self.vs, self.v0, coeff.mass, dt)
        else:
            self.stats[:4] = 0.0
            self.stats[4] = np.inf
        self.x0[:] = x
        self.v0[:] = state.v
        return diss

    def report(self) -> Dict[str, float]:
        """The last step's self-contact: candidates (vertex-triangle, edge-edge), the
        live ones (that could touch this step), pairs that acted, rounds and sweeps of
        the projection, pairs left short, the closest gap [m] along the live pairs'
        normals, and the candidate builds and partial refreshes so far."""
        s = self.stats
        return {'candidates': int(self.nvt + self.nee), 'live': int(self.nlive),
                'active': int(s[0]), 'rounds': int(s[1]), 'sweeps': int(s[2]),
                'left_short': int(s[3]), 'closest_gap': float(s[4]),
                'builds': int(self.builds), 'refreshes': int(self.refreshes),
                'rebases': int(self.rebases)}


def warm() -> None:
    """Compile every kernel of this module (into numba's cache) on two triangles, one
    falling onto the other just above a plane: the candidates, the live pairs, the staged
    response with an obstacle, the ledger and a partial refresh."""
    from types import SimpleNamespace
    from .contact import WIDTH
    from .mesh import ClothMesh
    from .state import Control, State
    rest = np.array([[0.0, 0.0, 0.0], [1.0, 0.0, 0.0], [0.0, 1.0, 0.0],
                     [0.2, 0.2, 5.0], [0.6, 0.2, 5.0], [0.2, 0.6, 5.0]])
    sc = SelfCollision(ClothMesh(rest, np.array([[0, 1, 2], [3, 4, 5]])))
    x = rest.copy()
    x[3:, 2] = 0.003
    v = np.zeros((6, 3))
    v[3:, 2] = -1.0
    plane = np.zeros((1, WIDTH))
    plane[0, 4:13] = np.eye(3).reshape(-1)
    plane[0, 2] = -1.0
    control = Control.empty(6).with_obstacles(plane, np.zeros((0, 8)), np.zeros(0))
    sc.begin(x, v)
    x += 0.004 * v                      # 2 mm relative: a staged response (STAGE)
    sc.after_step(State(x, v, np.zeros(2)), control, SimpleNamespace(mass=np.full(6, 0.01)),
                  0.002)
    sc.moved[:] = 0.0
    sc.moved[3] = sc.skin                 # one vertex ran out of room: a partial refresh
    sc._refresh(x, x, sc.built_th)
