"""Sharp obstacle features: the corners and edges of boxes, cylinders and meshes
against the cloth's triangles and edges.

Why
---
Vertex contact (:mod:`.contact`) keeps every *vertex* of the cloth off every obstacle.
On a smooth obstacle whose radius of curvature is well above the cloth's edge length,
that keeps the triangles off it too. A box is not smooth. With cloth edges longer than
the box (a 25 cm triangle on a 12 cm box) the box passes through a triangle between its
vertices and the cloth falls around it; and a table edge under a hanging cloth cuts into
every triangle that crosses it. A cylinder's rims do the same (a round table's rim went
7 mm into the triangles hanging over it), and a side bent tighter than the triangles (a
3 cm post under a cloth of 12.5 cm triangles) passes between their vertices. What is
missing are the pairs of a mesh against a mesh,
those of self-collision (:mod:`.self_contact`), with one side rigid and moved by the
user:

* corner-triangle: obstacle corner ``p`` and cloth triangle (a, b, c), closest point
  ``q = u x_a + v x_b + w x_c`` (Ericson 5.1.5);
* edge-edge: obstacle edge (p0, p1) and cloth edge (a0, a1), closest points
  ``p = (1 - t) p0 + t p1`` and ``q = (1 - s) x_a0 + s x_a1`` (Ericson 5.1.9).

A box's faces against the cloth's vertices are vertex contact; the three kinds together
are every closest-feature pair of two triangle meshes. A cylinder of radius r is taken
as a prism of K sides with its corners on its rims (2 K corners; 2 K rim sides and K
edges along its side), K the least for which the sides' sagitta ``r (1 - cos(pi / K))``
is at most :data:`RIM_SAG` th (:func:`rim_sides`): the prism lies inside the cylinder,
whose surface stays within 0.1 th of it; its faces against the cloth's vertices are
the cylinder's vertex contact. A mesh obstacle's features are its sharp convex edges
and their end points (:func:`sharp_features`); vertex contact reads its distance
field, which rounds every edge over a cell, so without them a box given as a mesh
went 8.8 mm into the triangles of a cloth over its edge, as the box primitive did.

Constraint and response
-----------------------
Each pair is one constraint on the cloth's vertices k with weights ``w_k`` (u, v, w or
1 - s, s), unit normal ``n = (q - p) / |q - p|`` from the obstacle to the cloth and
distance ``d = |q - p|``, both where the step began, and the obstacle point's
displacement over the step ``o = dt (v_lin + omega x (p - c))`` (the pose of its row is
the pose at the step's start, as for vertex contact)::

    g = d + n . (sum_k w_k (x_k - x0_k) - o)

This is self-collision's gap with side B rigid, so the response is self-collision's
(:func:`.self_contact.respond`). Every pair must end the step at ``g >= th``; a pair that
began inside the layer moves back out at most at :data:`.self_contact.SEP_SPEED`. The
correction is inelastic, a Gauss-Seidel projection; the obstacle has zero inverse mass,
so the cloth takes all of it. Coulomb friction acts on the slip relative to the obstacle,
with mu the obstacle's kinetic coefficient. A pair that acted is projected once more from the
exact geometry at the step's end. A step whose motion exceeds ``STAGE th`` (the implicit
solver's) is answered in stages, as in self-collision. A pair that ends every step at
``g >= th`` along its own normal cannot cross within a step whose relative motion is
below th. A box placed through the cloth is not pulled back out: that pair's normal
already points the wrong way.

The cloth's momentum change over the response is the force on the obstacle. It is reported
with vertex contact's, in :meth:`.simulator.ClothSimulator.contact_forces`. The energy
the response removes (:func:`.self_contact._ledger`) counts as dissipation.

Candidates: for each box or cylinder, the cloth's vertices are taken into its frame. A
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
list, :class:`FeatureContact`). The cost is a few comparisons per element and obstacle,
and only with a box, a cylinder or a mesh with sharp edges present.

This module imports no ROS package.
"""
from __future__ import annotations

import math
from typing import NamedTuple

import numpy as np

from .compiled import kernel
from .contact import (MU_K, PARAM, POS, ROT, SHAPE, SHAPES, SPEED, _point_velocity,
                      distance)
from .self_contact import (SEP_SPEED, STAGE, _deficit, _inverse_mass, _ledger, in_stages,
                           overrun_speed, respond, segment_segment, set_normal)
from .surface_query import point_triangle_sq
from .terms.jet import cross

__all__ = ['FeatureContact', 'box_corners', 'feature_corners', 'BOX_EDGES', 'FEATURED',
           'rim_sides', 'warm']

BOX = SHAPES['box']
CYLINDER = SHAPES['cylinder']
#: a cylinder's rim is taken as a regular polygon of K sides with its corners on the
#: circle, K the least for which the polygon's sides come no further inside the circle
#: (the sagitta r (1 - cos(pi / K))) than this fraction of th, within [8, RIM_SIDES_MAX]
RIM_SAG = 0.1
#: the most sides of a rim polygon (beyond r ~ 3.3 m at th = 2 mm the sagitta grows
#: above RIM_SAG th: 0.1 th per 3.3 m of radius)
RIM_SIDES_MAX = 256
MESH = SHAPES['mesh']
#: the shapes with sharp features: box and cylinder (and a mesh with sharp edges:
#: :func:`sharp_features`)
FEATURED = (BOX, CYLINDER)
#: [degrees] a mesh obstacle's edge is sharp where its two faces' normals differ by
#: more than this and the edge is convex (it bulges towards the cloth)
SHARP_ANGLE = 30.0
#: the columns of :attr:`Shapes.fmeta`, per obstacle row: first corner, corners, first
#: edge, edges, then the corners' bounding box in the obstacle's frame (lo, hi)
FM_CORNER, FM_NCORNER, FM_EDGE, FM_NEDGE, FM_LO, FM_HI = 0, 1, 2, 3, 4, 7
FM_WIDTH = 10


class Shapes(NamedTuple):
    """The features of the obstacle rows beyond their table row: the box's edges
    (:data:`BOX_EDGES`), and the sharp corners and edges of the mesh obstacles
    (:func:`sharp_features`): ``fmeta`` (rows, :data:`FM_WIDTH`), their corners
    ``fcorner`` (C, 3) in each obstacle's frame, their edges ``fedge`` (E, 2) as corner
    indices of their row."""
    box_edges: np.ndarray
    fmeta: np.ndarray
    fcorner: np.ndarray
    fedge: np.ndarray


def sharp_features(verts: np.ndarray, faces: np.ndarray, angle: float = SHARP_ANGLE):
    """The sharp convex edges of a closed triangle mesh (two faces whose normals differ
    by more than ``angle`` degrees, the edge bulging out: each face's far vertex below
    the other's plane) and their end points: (corners (C, 3), edges (E, 2) indices into
    corners). A smooth mesh (a sphere's) has none; a box's twelve edges and eight
    corners."""
    verts = np.asarray(verts, dtype=np.float64)
    faces = np.asarray(faces, dtype=np.int64)
    n = np.cross(verts[faces[:, 1]] - verts[faces[:, 0]],
                 verts[faces[:, 2]] - verts[faces[:, 0]])
    n /= np.maximum(np.linalg.norm(n, axis=1), 1e-300)[:, None]
    half = np.concatenate([faces[:, [0, 1]], faces[:, [1, 2]], faces[:, [2, 0]]])
    owner = np.tile(np.arange(len(faces)), 3)
    far = np.concatenate([faces[:, 2], faces[:, 0], faces[:, 1]])
    key = np.sort(half, axis=1)
    order = np.lexsort((key[:, 1], key[:, 0]))
    key, owner, far = key[order], owner[order], far[order]
    # a closed mesh: every edge twice, once each way, in consecutive rows once sorted
    same = np.all(key[0::2] == key[1::2], axis=1)
    if not same.all():
        raise ValueError('sharp_features needs a closed mesh (each edge in two faces)')
    f1, f2 = owner[0::2], owner[1::2]
    cosine = np.einsum('ij,ij->i', n[f1], n[f2])
    convex = np.einsum('ij,ij->i', verts[far[1::2]] - verts[key[0::2, 0]], n[f1]) < 0.0
    sharp = (cosine < math.cos(math.radians(angle))) & convex
    edges = key[0::2][sharp]
    used, inverse = np.unique(edges, return_inverse=True)
    return verts[used].copy(), inverse.reshape(-1, 2).astype(np.int64)


def no_shapes() -> Shapes:
    """The :class:`Shapes` of no obstacle rows (until :meth:`FeatureContact.set_shapes`)."""
    return Shapes(BOX_EDGES, np.zeros((0, FM_WIDTH)), np.zeros((0, 3)),
                  np.zeros((0, 2), np.int64))

#: a pair short of its target by less than this fraction of th counts as satisfied. Ten
#: times below self-collision's: a cloth resting on an edge sinks by g dt^2 per step
#: (5e-4 th at the explicit step of config/table.yaml) and the edge takes its share of
#: the weight in the steps where that adds up to the slack, so the force over one step
#: flickers; :attr:`FeatureContact.forces` is therefore the mean over a call's steps
SLACK = 1e-3
#: [m/s] the least speed a cloth is assumed to reach when the steps it may take without
#: the response are counted (:meth:`FeatureContact.free_steps`)
FREE_SPEED = 1.0
#: the candidate list's skin: at least this many thicknesses (and 2.5 times the motion
#: of the step that builds it); rebuilt when a vertex has moved half of it, or a box
SKIN = 2.0

#: the 12 edges of a box as pairs of corner indices; corner c has the local coordinates
#: (+-h_0, +-h_1, +-h_2) with the signs of bits 0, 1, 2 of c (set: +)
BOX_EDGES = np.array([(c, c | (1 << b)) for b in range(3) for c in range(8)
                      if not c & (1 << b)], dtype=np.int64)


@kernel()
def box_corners(ob, k, out):
    """The world positions (8, 3) of box row k's corners into ``out``."""
    for c in range(8):
        l0 = ob[k, PARAM] if c & 1 else -ob[k, PARAM]
        l1 = ob[k, PARAM + 1] if c & 2 else -ob[k, PARAM + 1]
        l2 = ob[k, PARAM + 2] if c & 4 else -ob[k, PARAM + 2]
        for r in range(3):
            out[c, r] = (ob[k, POS + r] + ob[k, ROT + 3 * r] * l0
                         + ob[k, ROT + 3 * r + 1] * l1 + ob[k, ROT + 3 * r + 2] * l2)


@kernel()
def rim_sides(r, th):
    """K, the sides of the polygon taken for a rim of radius ``r`` (:data:`RIM_SAG`)."""
    c = 1.0 - RIM_SAG * th / r
    if c <= 0.0:
        return 8
    return max(8, min(RIM_SIDES_MAX, int(math.ceil(math.pi / math.acos(c)))))


@kernel()
def n_features(ob, k, th, sh):
    """(corners, edges) of obstacle row k: a box 8 and 12; a cylinder, as a prism of K
    sides (:func:`rim_sides`), 2 K and 3 K (its two rims' sides, then the K edges along
    its side: a side bent tighter than the cloth's triangles would pass between their
    vertices as a box's edge would); a mesh, its sharp corners and edges (``sh``,
    :func:`sharp_features`); any other shape 0 and 0 (smooth)."""
    shape = ob[k, SHAPE]
    if shape == BOX:
        return 8, 12
    if shape == CYLINDER:
        nr = rim_sides(ob[k, PARAM], th)
        return 2 * nr, 3 * nr
    if shape == MESH and k < sh.fmeta.shape[0]:
        return int(sh.fmeta[k, FM_NCORNER]), int(sh.fmeta[k, FM_NEDGE])
    return 0, 0


@kernel()
def feature_corners(ob, k, th, sh, out):
    """The world positions of row k's corners into ``out`` (n_features(...)[0] rows): a
    box's 8 (:func:`box_corners`); a cylinder's rim corners, corner ``c K + j`` at angle
    2 pi j / K on the rim at local z = -h (c = 0) or +h (c = 1); a mesh's sharp
    corners (``sh``)."""
    if ob[k, SHAPE] == BOX:
        box_corners(ob, k, out)
        return
    if ob[k, SHAPE] == MESH:
        c0 = int(sh.fmeta[k, FM_CORNER])
        for c in range(int(sh.fmeta[k, FM_NCORNER])):
            l0 = sh.fcorner[c0 + c, 0]
            l1 = sh.fcorner[c0 + c, 1]
            l2 = sh.fcorner[c0 + c, 2]
            for q in range(3):
                out[c, q] = (ob[k, POS + q] + ob[k, ROT + 3 * q] * l0
                             + ob[k, ROT + 3 * q + 1] * l1 + ob[k, ROT + 3 * q + 2] * l2)
        return
    r = ob[k, PARAM]
    h = ob[k, PARAM + 1]
    nr = rim_sides(r, th)
    for c in range(2):
        l2 = h if c else -h
        for j in range(nr):
            a = 2.0 * math.pi * j / nr
            l0 = r * math.cos(a)
            l1 = r * math.sin(a)
            for q in range(3):
                out[c * nr + j, q] = (ob[k, POS + q] + ob[k, ROT + 3 * q] * l0
                                      + ob[k, ROT + 3 * q + 1] * l1
                                      + ob[k, ROT + 3 * q + 2] * l2)


@kernel()
def edge_ends(ob, k, f, ncorner, sh):
    """The corners (c0, c1) at the ends of row k's edge f: a box's :data:`BOX_EDGES`;
    a cylinder's rim sides (f < 2 K: corner j to j + 1 round each rim), then its side
    edges (corner j of one rim to corner j of the other); a mesh's sharp edges."""
    if ob[k, SHAPE] == BOX:
        return sh.box_edges[f, 0], sh.box_edges[f, 1]
    if ob[k, SHAPE] == MESH:
        e = int(sh.fmeta[k, FM_EDGE]) + f
        return sh.fedge[e, 0], sh.fedge[e, 1]
    nr = ncorner // 2
    if f >= 2 * nr:
        return f - 2 * nr, f - nr
    c = f // nr
    j = f - c * nr
    return c * nr + j, c * nr + (j + 1) % nr


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
def geometry(cand, nc, xs, x, ob, faces, edges, sh, dt, shift, part, corners, gi,
             gw, gn, gd, go, g0, first, th, sep, slack, flag):
    """The constraint of each pair ``cand[:nc]`` (module docstring) linearised at the
    cloth's positions ``xs``, with the box moved on by ``shift`` of its step's
    displacement and moving ``part`` of it in what is left to answer (the whole step: 0
    and 1; its end: 1 and 0; a stage j of m: j / m and 1 / m): vertices gi (P,4), weights
    gw (P,4), normal gn (P,3) from the box to the cloth, distance gd (P,), the box's
    displacement go (P,3). A pair at zero distance takes the triangle's normal (or the
    edges' cross product) turned away from the obstacle's centre. ``first``: g0 takes gd
    (the distance that sets each pair's target). flag[p]: 1 if short at x by more
    than ``slack`` [m]."""
    last = -1
    ncorner = 0
    for p in range(nc):
        k = cand[p, 0]
        f = cand[p, 1]
        e = cand[p, 2]
        if k != last:
            feature_corners(ob, k, th, sh, corners)
            ncorner = n_features(ob, k, th, sh)[0]
            last = k
        if f < ncorner:
            a = faces[e, 0]
            b = faces[e, 1]
            c = faces[e, 2]
            dd, u, v, w = point_triangle_sq(corners[f, 0], corners[f, 1], corners[f, 2],
                                            xs[a], xs[b], xs[c])
            p0 = corners[f, 0]
            p1 = corners[f, 1]
            p2 = corners[f, 2]
            gi[p, 0] = a
            gi[p, 1] = b
            gi[p, 2] = c
            gi[p, 3] = a
            gw[p, 0] = u
            gw[p, 1] = v
            gw[p, 2] = w
            gw[p, 3] = 0.0
            f0, f1, f2 = cross(xs[b, 0] - xs[a, 0], xs[b, 1] - xs[a, 1], xs[b, 2] - xs[a, 2],
                               xs[c, 0] - xs[a, 0], xs[c, 1] - xs[a, 1], xs[c, 2] - xs[a, 2])
        else:
            a = edges[e, 0]
            b = edges[e, 1]
            c0, c1 = edge_ends(ob, k, f - ncorner, ncorner, sh)
            dd, s, t = segment_segment(xs[a], xs[b], corners[c0], corners[c1])
            p0 = corners[c0, 0] + t * (corners[c1, 0] - corners[c0, 0])
            p1 = corners[c0, 1] + t * (corners[c1, 1] - corners[c0, 1])
            p2 = corners[c0, 2] + t * (corners[c1, 2] - corners[c0, 2])
            gi[p, 0] = a
            gi[p, 1] = b
            gi[p, 2] = a
            gi[p, 3] = b
            gw[p, 0] = 1.0 - s
            gw[p, 1] = s
            gw[p, 2] = 0.0
            gw[p, 3] = 0.0
            f0, f1, f2 = cross(xs[b, 0] - xs[a, 0], xs[b, 1] - xs[a, 1], xs[b, 2] - xs[a, 2],
                               corners[c1, 0] - corners[c0, 0], corners[c1, 1] - corners[c0, 1],
                               corners[c1, 2] - corners[c0, 2])
        o0, o1, o2 = _point_velocity(ob, k, p0, p1, p2)
        p0 += shift * dt * o0
        p1 += shift * dt * o1
        p2 += shift * dt * o2
        go[p, 0] = part * dt * o0
        go[p, 1] = part * dt * o1
        go[p, 2] = part * dt * o2
        # the cloth's point q less the box's point (moved on by shift, with dd at the
        # unmoved box: recomputed here)
        r0 = -p0
        r1 = -p1
        r2 = -p2
        for j in range(4):
            r0 += gw[p, j] * xs[gi[p, j], 0]
            r1 += gw[p, j] * xs[gi[p, j], 1]
            r2 += gw[p, j] * xs[gi[p, j], 2]
        # the fallback direction turned away from the box's centre
        sg = 1.0 if ((p0 - ob[k, POS]) * f0 + (p1 - ob[k, POS + 1]) * f1
                     + (p2 - ob[k, POS + 2]) * f2) >= 0.0 else -1.0
        set_normal(p, r0, r1, r2, sg * f0, sg * f1, sg * f2, gw, gn, gd, g0, first)
        flag[p] = 1 if _deficit(p, x, xs, gi, gw, gn, gd, go, g0, th, sep) > slack else 0


@kernel()
def _impulse(x, v, v_before, c_before, contact, mass, dt, ob, k, out):
    """The force and torque (about its position) that the cloth exerted on box row k
    through the response that took the velocities from ``v_before`` to ``v``: minus the
    cloth's momentum change over dt, less what vertex contact recorded meanwhile in
    ``contact`` (the response's pushes back onto obstacle layers; ``c_before`` before
    it); added to ``out`` (6,)."""
    for i in range(x.shape[0]):
        if v[i, 0] == v_before[i, 0] and v[i, 1] == v_before[i, 1] and v[i, 2] == v_before[i, 2]:
            continue
        f0 = (contact[i, 0] - c_before[i, 0]) - mass[i] * (v[i, 0] - v_before[i, 0]) / dt
        f1 = (contact[i, 1] - c_before[i, 1]) - mass[i] * (v[i, 1] - v_before[i, 1]) / dt
        f2 = (contact[i, 2] - c_before[i, 2]) - mass[i] * (v[i, 2] - v_before[i, 2]) / dt
        out[0] += f0
        out[1] += f1
        out[2] += f2
        t0, t1, t2 = cross(x[i, 0] - ob[k, POS], x[i, 1] - ob[k, POS + 1],
                           x[i, 2] - ob[k, POS + 2], f0, f1, f2)
        out[3] += t0
        out[4] += t1
        out[5] += t2


@kernel()
def clearance(x, v, edges, ob, meta, data, th, sh):
    """(how far every obstacle with corners and edges is from the cloth beyond its
    longest edge plus ``th`` [m], the fastest any such obstacle's surface moves [m/s],
    the fastest vertex [m/s]):
    :meth:`FeatureContact.free_steps`."""
    fastest = 0.0
    for i in range(x.shape[0]):
        fastest = max(fastest, v[i, 0] * v[i, 0] + v[i, 1] * v[i, 1] + v[i, 2] * v[i, 2])
    longest = 0.0
    for e in range(edges.shape[0]):
        a = edges[e, 0]
        b = edges[e, 1]
        d0 = x[a, 0] - x[b, 0]
        d1 = x[a, 1] - x[b, 1]
        d2 = x[a, 2] - x[b, 2]
        longest = max(longest, d0 * d0 + d1 * d1 + d2 * d2)
    near = np.inf
    speed = 0.0
    for k in range(ob.shape[0]):
        if n_features(ob, k, th, sh)[0] == 0:
            continue
        speed = max(speed, ob[k, SPEED])
        for i in range(x.shape[0]):
            d, n0, n1, n2 = distance(ob, meta, data, k, x[i, 0], x[i, 1], x[i, 2])
            near = min(near, d)
    return near - math.sqrt(longest) - th, speed, math.sqrt(fastest)


@kernel()
def _largest_motion(x, ref):
    """max_i |x_i - ref_i| [m]."""
    out = 0.0
    for i in range(x.shape[0]):
        d0 = x[i, 0] - ref[i, 0]
        d1 = x[i, 1] - ref[i, 1]
        d2 = x[i, 2] - ref[i, 2]
        out = max(out, d0 * d0 + d1 * d1 + d2 * d2)
    return math.sqrt(out)


class Pairs(NamedTuple):
    """Candidate pairs (rows p) and each one's constraint (module docstring): ``cand``
    (box row, feature, cloth element), then what :func:`geometry` writes: vertices
    ``gi``, weights ``gw``, normal ``gn``, distance ``gd``, the box's displacement
    ``go``, the distance that sets the target ``g0``, short ``flag``; ``active``: the
    projection's list of short pairs."""
    cand: np.ndarray
    gi: np.ndarray
    gw: np.ndarray
    gn: np.ndarray
    gd: np.ndarray
    go: np.ndarray
    g0: np.ndarray
    flag: np.ndarray
    active: np.ndarray

    @staticmethod
    def zeros(p: int) -> 'Pairs':
        return Pairs(np.zeros((p, 3), np.int64), np.zeros((p, 4), np.int64),
                     np.zeros((p, 4)), np.zeros((p, 3)), np.zeros(p), np.zeros((p, 3)),
                     np.zeros(p), np.zeros(p, np.int64), np.zeros(p, np.int64))


class Scratch(NamedTuple):
    """Per-vertex (n, 3) arrays of a step's response: where the step began ``x0``, ``v0``;
    where the response began ``xs``, ``vs``; the base of its last pass ``xe``; the
    velocities and contact forces before a box's projection ``vb``, ``cb``; inverse masses
    ``inv`` (n,); an obstacle's ``corners`` (at most 2 :data:`RIM_SIDES_MAX`, 3); the
    projection's ``stats`` (5,)."""
    x0: np.ndarray
    v0: np.ndarray
    xs: np.ndarray
    vs: np.ndarray
    xe: np.ndarray
    vb: np.ndarray
    cb: np.ndarray
    inv: np.ndarray
    corners: np.ndarray
    stats: np.ndarray

    @staticmethod
    def zeros(n: int) -> 'Scratch':
        z = [np.zeros((n, 3)) for _ in range(7)]
        return Scratch(*z, np.zeros(n), np.zeros((2 * RIM_SIDES_MAX, 3)),
                       np.zeros(5))


@kernel()
def respond_boxes(pairs, nc, base, x, v, ob, meta, data, contact, faces, edges, sh,
                  dt, shift, part, first, friction, s, mass, th, sep, slack, forces):
    """One pass of the response (module docstring): the constraints of ``pairs[:nc]``
    linearised at ``base`` (:func:`geometry`), then self-collision's projection box by
    box, each with its own kinetic mu (none if not ``friction``), and each box's force
    and torque added to ``forces[k]`` (:func:`_impulse`). Returns how many pairs
    acted."""
    P = pairs
    geometry(P.cand, nc, base, x, ob, faces, edges, sh, dt, shift, part, s.corners,
             P.gi, P.gw, P.gn, P.gd, P.go, P.g0, first, th, sep, slack, P.flag)
    acted = 0
    a = 0
    while a < nc:
        k = P.cand[a, 0]
        b = a
        while b < nc and P.cand[b, 0] == k:
            b += 1
        mu = ob[k, MU_K] if friction else 0.0
        s.vb[:] = v
        s.cb[:] = contact[:, :3]
        respond(x, base, v, s.inv, mass, P.gi[a:b], P.gw[a:b], P.gn[a:b], P.gd[a:b],
                P.go[a:b], P.g0[a:b], b - a, th, mu, dt, sep, slack, P.flag[a:b],
                P.active[a:b], ob, meta, data, contact, s.stats)
        if s.stats[0] > 0:
            acted += int(s.stats[0])
            _impulse(x, v, s.vb, s.cb, contact, mass, dt, ob, k, forces[k])
        a = b
    return acted


@kernel()
def _within(pairs, nc, ob, dt, reach, late):
    """The pairs of ``pairs[:nc]`` (their distance ``gd`` where the first pass
    linearised them, at the step's start with the box unmoved) that may still be short
    of their target once the cloth has moved up to ``reach`` [m] and each box its
    step's travel ``dt SPEED``: into ``late`` (cand and g0), in order; returns how many.
    A point's distance to a triangle or a segment changes by no more than its vertices
    move, and no target exceeds th, so a pair left out is not short."""
    m = 0
    for p in range(nc):
        k = pairs.cand[p, 0]
        if pairs.gd[p] < reach + dt * ob[k, SPEED]:
            for j in range(3):
                late.cand[m, j] = pairs.cand[p, j]
            late.g0[m] = pairs.g0[p]
            m += 1
    return m


@kernel()
def respond_step(pairs, late, nc, s, x, v, ob, meta, data, contact, faces, edges,
                 sh, mass, pinned, dt, th, sep, slack, forces, out):
    """The response to one step from ``s.x0, s.v0`` to (x, v), in place and in one
    stage: a pass from the step's start with friction, and if a pair acted or began
    inside the layer, a pass from the geometry at its end over the pairs that can still
    be short (:func:`_within`). Returns how many pairs acted; ``out[0]``: the energy the
    response removed [J] (:func:`_ledger`)."""
    _inverse_mass(mass, pinned, s.inv)
    s.xs[:] = x
    s.vs[:] = v
    # the passes' shift, part and flags as values, not literals: numba compiles a callee
    # once per distinct literal argument (respond_boxes three times: docs/performance.md),
    # and once for all values of the same type
    zero = 0.0 * dt
    one = zero + 1.0
    yes = nc >= 0
    acted = respond_boxes(pairs, nc, s.x0, x, v, ob, meta, data, contact, faces, edges,
                          sh, dt, zero, one, yes, yes, s, mass, th, sep, slack,
                          forces)
    inside = False
    for p in range(nc):
        if pairs.g0[p] < th:
            inside = True
            break
    if acted > 0 or inside:
        s.xe[:] = x
        m = _within(pairs, nc, ob, dt, th + slack + _largest_motion(x, s.x0), late)
        acted += respond_boxes(late, m, s.xe, x, v, ob, meta, data, contact, faces, edges,
                               sh, dt, one, zero, not yes, not yes, s, mass, th, sep,
                               slack, forces)
    out[0] = _ledger(x, s.xs, v, s.vs, s.v0, mass, dt) if acted > 0 else 0.0
    return acted


@kernel()
def fresh(x, x0, xb, skin, ob, built, move):
    """Whether the candidate list built at ``xb`` for the obstacle rows ``built`` (same
    shape as ``ob``) still holds: no vertex has moved half the skin since and no box
    has moved or changed. ``move[0]``: the step's largest motion of a vertex (from x0)."""
    move[0] = _largest_motion(x, x0)
    for k in range(ob.shape[0]):
        for j in range(PARAM + 3):
            if ob[k, j] != built[k, j]:
                return False
    return _largest_motion(x, xb) <= 0.5 * skin


class FeatureContact:
    """The corners and edges of the boxes, cylinders and meshes with sharp edges among
    a simulator's obstacles against its cloth (module docstring); the meshes' features
    come through :meth:`set_shapes`.

    ``start()`` before a call's steps, ``begin(x, v)`` before each step,
    ``after_step(state, control, coeff, dt)`` after it, while one is present
    (:meth:`present`): the response, in place; returns the energy it removed [J].
    :attr:`forces` (obstacle rows, 6): the force and torque each obstacle took through its
    features, the mean over the steps since ``start()``.

    The candidate pairs are a Verlet list: found within ``th + skin`` where a step
    began, kept while no vertex has moved more than half the skin since and no box has
    moved or changed (module docstring)."""

    def __init__(self, mesh):
        n = mesh.n_vertices
        self.faces = np.ascontiguousarray(mesh.faces, dtype=np.int64)
        self.edges = np.ascontiguousarray(mesh.edges, dtype=np.int64)
        self.s = Scratch.zeros(n)
        self.sh = no_shapes()
        self.xt = np.zeros((n, 3))
        self.xb = np.zeros((n, 3))
        self.loc = np.zeros((n, 3))
        self.move = np.zeros(1)
        self.scratch = np.zeros(2)
        self.out = np.zeros(1)
        self.sums = np.zeros((0, 6))
        self.steps = 0
        self.built = None                  # the obstacle rows of the last build
        self.built_th = 0.0                # and its contact thickness
        self.skin = 0.0
        self.builds = 0
        self.pairs = 0
        self.acted = 0
        self.gap = 0.0
        self.overrun_speed = 0.0           # [m/s] (overran)
        self._alloc(64)

    def _alloc(self, p):
        self.p = Pairs.zeros(p)
        self.late = Pairs.zeros(p)         # the second pass's (:func:`_within`)

    def present(self, control) -> bool:
        """Whether any obstacle is a box, a cylinder or a mesh with sharp edges (else
        nothing to do)."""
        return bool(self._featured(control.obstacles).any())

    def _featured(self, ob: np.ndarray) -> np.ndarray:
        """Which obstacle rows have corners and edges (:func:`n_features` > 0): boxes,
        cylinders, meshes with sharp edges."""
        shape = ob[:, SHAPE]
        rows = shape == FEATURED[0]
        for k in FEATURED[1:]:                 # (np.isin sorts: 40 us on every step call)
            rows |= shape == k
        fm = self.sh.fmeta
        if fm.shape[0] == ob.shape[0]:
            rows |= (ob[:, SHAPE] == MESH) & (fm[:, FM_NCORNER] > 0)
        return rows

    def set_shapes(self, fmeta: np.ndarray, fcorner: np.ndarray, fedge: np.ndarray) -> None:
        """The mesh obstacles' sharp features, per obstacle row (:class:`Shapes`): after
        any change of the obstacles (the candidate list is built again)."""
        self.sh = Shapes(BOX_EDGES, np.ascontiguousarray(fmeta, dtype=np.float64),
                         np.ascontiguousarray(fcorner, dtype=np.float64).reshape(-1, 3),
                         np.ascontiguousarray(fedge, dtype=np.int64).reshape(-1, 2))
        most = int(fmeta[:, FM_NCORNER].max()) if len(fmeta) else 0
        if most > self.s.corners.shape[0]:
            self.s = self.s._replace(corners=np.zeros((most, 3)))
        self.built = None

    def start(self) -> None:
        self.sums[:] = 0.0
        self.steps = 0

    @property
    def forces(self) -> np.ndarray:
        """(obstacle rows, 6): force and torque on each box, the mean over the steps
        since :meth:`start`."""
        return self.sums / max(1, self.steps)

    def begin(self, x: np.ndarray, v: np.ndarray) -> None:
        self.s.x0[:] = x
        self.s.v0[:] = v

    def free_steps(self, x: np.ndarray, v: np.ndarray, control, dt: float) -> int:
        """How many steps the cloth can probably take from (x, v) before any of its
        triangles could come within the thickness of a box, so that no response is
        needed after them (fewer than 2: answer each step). A triangle that near has a
        vertex within its longest edge plus th of the box; the steps are those in which
        the fastest vertex, at its present speed but at least :data:`FREE_SPEED`, and the
        box's surface together cover half that gap. :meth:`overran` then checks the call
        (a cloth can speed up). While the last step had candidate pairs: 0 without
        looking."""
        if self.pairs:
            return 0
        gap, speed, fastest = clearance(x, v, self.edges, control.obstacles,
                                        control.sdf_meta, control.sdf_data,
                                        float(control.contact_params[0]), self.sh)
        self.gap = gap
        if gap <= 0.0:
            return 0
        return int(min(0.5 * gap / ((max(fastest, FREE_SPEED, self.overrun_speed) + speed)
                                    * dt), 2.0 ** 62))

    def overran(self, x_start: np.ndarray, x: np.ndarray, control, dt: float,
                steps: int) -> bool:
        """Whether a call of ``steps`` steps allowed by :meth:`free_steps` moved some
        vertex, together with the surface of an obstacle with features, further than the
        gap it was given (then it must be stepped again one step per call, with the
        response), and the speed the next calls assume
        (:func:`.self_contact.overrun_speed`)."""
        ob = control.obstacles
        speed = float(ob[self._featured(ob), SPEED].max(initial=0.0))
        moved = _largest_motion(x, x_start)
        over = moved + speed * steps * dt >= self.gap
        self.overrun_speed = overrun_speed(self.overrun_speed, over, moved, steps, dt)
        return over

    def _candidates(self, x, ob, th, dt) -> None:
        """The Verlet list (class docstring), built again where this step began if it
        is stale; then ``self.pairs`` = its length and ``self.move[0]`` the step's
        largest motion of a vertex."""
        s = self.s
        if (self.built is not None and self.built.shape == ob.shape and self.built_th == th
                and fresh(x, s.x0, self.xb, self.skin, ob, self.built, self.move)):
            return
        move = _largest_motion(x, s.x0)
        self.move[0] = move
        self.skin = max(SKIN * th, 2.5 * move)
        self.scratch[1] = th                 # the features' own thickness (rim polygons)
        while True:
            nc = candidates(s.x0, s.x0, self.faces, self.edges, ob, th + self.skin, dt,
                            self.sh, self.loc, s.corners, self.p.cand, self.scratch)
            if nc <= len(self.p.cand):
                break
            self._alloc(2 * nc)
        self.pairs = nc
        self.xb[:] = s.x0
        self.built = ob.copy()
        self.built_th = th
        self.builds += 1

    def _pass(self, base, x, v, control, mass, th, dt, shift, part, first, friction):
        """:func:`respond_boxes` at ``base`` over every pair (its arguments from this
        object)."""
        return respond_boxes(self.p, self.pairs, base, x, v, control.obstacles,
                             control.sdf_meta, control.sdf_data, control.contact,
                             self.faces, self.edges, self.sh, dt, shift, part, first,
                             friction, self.s, mass, th, SEP_SPEED * dt, SLACK * th,
                             self.sums)

    def after_step(self, state, control, coeff, dt: float) -> float:
        ob = control.obstacles
        if self.sums.shape[0] != ob.shape[0]:
            self.sums = np.zeros((ob.shape[0], 6))
        self.steps += 1
        self.acted = 0
        th = float(control.contact_params[0])
        x, v = state.x, state.v
        s = self.s
        self._candidates(x, ob, th, dt)
        nc = self.pairs
        if nc == 0:
            return 0.0
        stages = max(1, int(math.ceil(float(self.move[0]) / (STAGE * th))))
        if stages == 1:
            self.acted = respond_step(self.p, self.late, nc, s, x, v, ob, control.sdf_meta,
                                      control.sdf_data, control.contact, self.faces,
                                      self.edges, self.sh, coeff.mass, control.pinned,
                                      dt, th, SEP_SPEED * dt, SLACK * th, self.sums,
                                      self.out)
            return float(self.out[0])
        # a step longer than STAGE th (the implicit solver's): the solver's displacement
        # in equal parts, each linearised where the last one ended (self-collision's
        # stages), then once more from the exact geometry at the step's end
        _inverse_mass(coeff.mass, control.pinned, s.inv)
        s.xs[:] = x
        s.vs[:] = v
        acted = in_stages(x, v, s.x0, s.xe, self.xt, stages,
                          lambda start, j: self._pass(start, x, v, control, coeff.mass, th,
                                                      dt, j / stages, 1.0 / stages,
                                                      j == 0, True),
                          s.inv, coeff.mass, control, th, dt)
        if acted > 0 or self.p.g0[:nc].min() < th:
            s.xe[:] = x
            acted += self._pass(s.xe, x, v, control, coeff.mass, th, dt, 1.0, 0.0, False,
                                False)
        self.acted = acted
        if acted == 0:
            return 0.0
        return _ledger(x, s.xs, v, s.vs, s.v0, coeff.mass, dt)


def warm() -> None:
    """Compile this module's kernels (into numba's cache): a triangle falling onto a box
    corner, in one step and in stages."""
    from types import SimpleNamespace
    from .contact import WIDTH
    from .mesh import ClothMesh
    from .state import Control, State
    rest = np.array([[-1.0, -1.0, 0.0], [1.0, -1.0, 0.0], [0.0, 1.0, 0.0]])
    fc = FeatureContact(ClothMesh(rest, np.array([[0, 1, 2]])))
    box = np.zeros((1, WIDTH))
    box[0, SHAPE] = BOX
    box[0, ROT:ROT + 9] = np.eye(3).reshape(-1)
    box[0, POS + 2] = -0.2
    box[0, PARAM:PARAM + 3] = 0.1
    box[0, MU_K] = 0.5
    control = Control.empty(3).with_obstacles(box, np.zeros((0, 8)), np.zeros(0))
    coeff = SimpleNamespace(mass=np.full(3, 0.01))
    for fall in (0.0005, 0.004):                 # one step; a staged one
        x = rest.copy()
        x[:, 2] = -0.097
        v = np.zeros((3, 3))
        v[:, 2] = -1.0
        fc.begin(x, v)
        x += fall * v
        fc.after_step(State(x, v, np.zeros(2)), control, coeff, fall)
