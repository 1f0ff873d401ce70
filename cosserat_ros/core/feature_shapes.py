"""The corners and edges of the obstacles' shapes, which :mod:`.features` keeps the cloth's
triangles and edges off: a box's 8 corners and 12 edges, a cylinder's rims as a prism, a
mesh obstacle's sharp convex edges.

A cylinder of radius r is taken as a prism of K sides with its corners on its rims (2 K
corners; 2 K rim sides and K edges along its side), K the least for which the sides'
sagitta ``r (1 - cos(pi / K))`` is at most :data:`RIM_SAG` th (:func:`rim_sides`): the
prism lies inside the cylinder, whose surface stays within 0.1 th of it; its faces
against the cloth's vertices are the cylinder's vertex contact. A mesh obstacle's
features are its sharp convex edges and their end points (:func:`sharp_features`): vertex
contact reads its distance field, which rounds every edge over a cell.

This module imports no ROS package.
"""
from __future__ import annotations

import math
from typing import NamedTuple

import numpy as np

from .compiled import kernel
from .contact import PARAM, POS, ROT, SHAPE, SHAPES

__all__ = ['Shapes', 'sharp_features', 'no_shapes', 'box_corners', 'rim_sides', 'n_features',
           'feature_corners', 'edge_ends', 'BOX_EDGES', 'FEATURED', 'FEATURE_META',
           'FM_CORNER', 'FM_NCORNER', 'FM_EDGE', 'FM_NEDGE', 'FM_LO', 'FM_HI', 'FM_WIDTH']


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
#: a row of :attr:`Shapes.fmeta` (one per obstacle row), by name: the layout whose float64
#: columns the compiled code reads by the offsets ``FM_*`` below
#: (``fmeta.view(FEATURE_META)`` gives the fields by name)
FEATURE_META = np.dtype([
    ('corner', 'f8'),              # its first corner in Shapes' corners
    ('ncorner', 'f8'),             # its corners
    ('edge', 'f8'),                # its first edge in Shapes' edges
    ('nedge', 'f8'),               # its edges
    ('lo', 'f8', 3),               # the corners' bounding box in the obstacle's frame [m]
    ('hi', 'f8', 3),
])
FM_CORNER, FM_NCORNER, FM_EDGE, FM_NEDGE, FM_LO, FM_HI = (
    FEATURE_META.fields[f][1] // 8 for f in ('corner', 'ncorner', 'edge', 'nedge', 'lo', 'hi'))
FM_WIDTH = FEATURE_META.itemsize // 8


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
