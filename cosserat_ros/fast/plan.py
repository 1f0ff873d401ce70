"""The step's work plan: which thread runs which work items, where gradients go.

Built once per simulator (``build_plan``) from the model and the lane layout; the step
kernels of :mod:`.step` read it by name (:class:`Plan`).

Work items (chunks) of ``VERTEX_CHUNK`` vertices each own a scratch row. Two steps use it:

* the two-pass step (meshes below ``FUSE_MIN_VERTICES``): the vertex pass (faces and
  vertices together) over all chunks, then the gather and update over all vertices;
* the tiled step (larger meshes): the chunks split into one part per thread, each part
  run in tiles of ``TILE_VERTICES``; after the last chunk of a tile the thread gathers and
  updates every vertex whose contributors (the vertices whose stencils hold it, and its
  faces) all lie in its part and are now done, while their gradients are still in its
  cache. Updating x_j there is safe: the vertices and faces that read x_j are exactly
  those that contribute to j (the coupling's strain side reads and writes only a vertex's
  own faces, whose corners are in its stencil). A second pass gathers and updates the
  seam between the parts. Since a gradient is dead once its last reader's tile has
  gathered it, each part writes its stencil and corner gradients round rings
  (:func:`_rings`), so they never leave the cache. The forces and the update are the same
  as the two-pass step's, vertex for vertex and in the same order: the same trajectory to
  the bit (``test/test_fast.py``).
"""
from __future__ import annotations

from typing import NamedTuple

import numpy as np

from ..core.constants import VERTEX_CHUNK
from .lanes import chunk_of_vertex

__all__ = ['Plan', 'build_plan']


class Plan(NamedTuple):
    """The step's schedule (module docstring); T tiles, P parts, nch chunks."""

    tile_ch: np.ndarray     # (T+1,) int64 chunk boundaries of the tiles
    fc_ptr: np.ndarray      # (nch+1,) int64 the faces of each chunk ...
    fc_face: np.ndarray     # (m,) uint32 ... in chunk order
    gl_ptr: np.ndarray      # (T+2,) int64 the vertices each tile completes, then the seam
    gl_vert: np.ndarray     # (n,) int64
    part_tile: np.ndarray   # (P+1,) int64 the tiles of each part
    g_wptr: np.ndarray      # (G,4) int64 the lanes' g_wptr, column 2 = gradient slots
    tr_slot: np.ndarray     # (K,) uint32 where the gather reads each transposed entry
    fc_slot: np.ndarray     # (m,) uint32 the fgrad row of each face in chunk order
    vf_row: np.ndarray      # (V,) uint32 3 slot + corner per vertex-face pair
    fc_vert: np.ndarray     # (m,3) uint32 the faces' corners in chunk order
    fc_tpl: np.ndarray      # (m,) uint32 their rows in the table of rest shapes
    t_dinv: np.ndarray      # (R,2,2) the distinct rest shapes: Dinv ...
    t_area: np.ndarray      # (R,) ... and area


def build_plan(model, lanes, nch: int, tile_vertices: int, parts: int, tiled: bool) -> Plan:
    """The plan for ``nch`` chunks, tiles of ``tile_vertices``, ``parts`` parts
    (``tiled``; otherwise the two-pass step's: equal runs of faces per chunk, faster on
    small meshes, and every gradient in its own slot)."""
    mesh, jet = model.mesh, model.jet
    n, faces = mesh.n_vertices, mesh.faces
    chunk = chunk_of_vertex(n, nch, lanes.g_vert, lanes.s_vert)
    face_chunk = (chunk[faces].max(axis=1) if tiled
                  else np.arange(len(faces)) // -(-len(faces) // nch))
    fc_face = np.argsort(face_chunk, kind='stable').astype(np.uint32)
    fc_ptr = np.zeros(nch + 1, dtype=np.int64)
    np.cumsum(np.bincount(face_chunk, minlength=nch), out=fc_ptr[1:])
    # first and last contributing chunk of every vertex
    src = np.repeat(chunk, np.diff(jet.st_ptr))
    first, last = chunk.copy(), chunk.copy()
    for idx, c in ((jet.st_idx, src), (faces.ravel(), np.repeat(face_chunk, 3))):
        np.minimum.at(first, idx, c)
        np.maximum.at(last, idx, c)
    part_ch = np.linspace(0, nch, parts + 1).round().astype(np.int64)
    per_tile = max(1, tile_vertices // VERTEX_CHUNK)
    starts = [np.arange(part_ch[p], part_ch[p + 1], per_tile) for p in range(parts)]
    part_tile = np.zeros(parts + 1, dtype=np.int64)
    np.cumsum([len(t) for t in starts], out=part_tile[1:])
    tile_ch = np.append(np.concatenate(starts), nch).astype(np.int64)
    ntile = len(tile_ch) - 1
    inner = (np.searchsorted(part_ch, first, 'right')
             == np.searchsorted(part_ch, last, 'right'))
    key = np.where(inner, np.searchsorted(tile_ch, last, 'right') - 1, ntile)
    gl_vert = np.argsort(key, kind='stable').astype(np.int64)
    gl_ptr = np.zeros(ntile + 2, dtype=np.int64)
    np.cumsum(np.bincount(key, minlength=ntile + 1), out=gl_ptr[1:])
    if tiled:
        g_wptr, tr_slot, fc_slot, vf_row = _rings(model, lanes, nch, tile_ch, part_tile, key,
                                                  fc_ptr, fc_face)
    else:
        g_wptr = lanes.g_wptr
        tr_slot = lanes.pos[jet.tr_slot].astype(np.uint32)
        fc_slot = fc_face
        vf_row = model.vertex_faces.row
    return Plan(tile_ch, fc_ptr, fc_face, gl_ptr, gl_vert, part_tile, g_wptr, tr_slot, fc_slot,
                vf_row, *_face_stream(model, fc_face))


def _rings(model, lanes, nch, tile_ch, part_tile, key, fc_ptr, fc_face):
    """Where the tiled step writes its gradients, and where its gathers read them:
    the lane groups' stencil gradients (``contrib``: ``g_wptr`` with column 2
    replaced, the transposed stencil's slots to match) and the faces' corner
    gradients (rows of ``fgrad``: ``fc_slot`` per face in chunk order, ``vf_row`` =
    3 slot + corner per vertex-face pair). The gathers' two index arrays are uint32.

    A group (a face) whose gradients are all gathered inside its part (every target
    vertex's contributors lie in that part, ``key`` < T) is dead once the last of
    those targets' tiles has gathered them; its slot is reused after that. Each part's
    such groups (faces) go, in the order the part writes them, round a ring
    (:func:`_ring_slots`). So the step writes its gradients into a few hundred kB that
    stay in the core's cache, instead of streaming ~600 B per vertex out to memory and
    back (each store's line is read first). Those with a target on the seam (gathered
    after every part is done), the 5% read the latest after they are written, and the
    single vertices keep slots of their own. The forces are the same numbers,
    gathered in the same order."""
    g_vert, g_ptr, g_wptr = lanes.g_vert, lanes.g_ptr, lanes.g_wptr
    jet, mesh = model.jet, model.mesh
    st_ptr, st_idx = jet.st_ptr, jet.st_idx
    faces, vf_face = mesh.faces, model.vertex_faces.face
    K, m = len(st_idx), len(faces)
    tile_of_chunk = np.searchsorted(tile_ch, np.arange(nch), 'right') - 1
    pos_of_tr = lanes.pos[jet.tr_slot]
    w, tr = g_wptr, pos_of_tr
    if len(g_vert):
        size = np.diff(g_ptr)
        # the tile each group is written in and the last tile reading it
        g_tile = tile_of_chunk[np.arange(len(g_vert)) // -(-len(g_vert) // nch)]
        g_last = np.maximum.reduceat(key[st_idx], st_ptr[:-1])[g_vert].max(axis=1)
        # after the single vertices' entries, which keep their slots
        base, end = _place(size, g_tile, g_last, part_tile, int(g_ptr[0]))
        if end <= K:        # else no room to spare (a tiny mesh): entry positions
            w = g_wptr.copy()
            w[:, 2] = base
            # position -> slot, for the transposed stencil: a group's entry at
            # g_ptr[g] + r goes to base[g] + r
            slot = np.arange(K, dtype=np.int64)
            slot[g_ptr[0]:] += np.repeat(base - g_ptr[:-1], size)
            tr = slot[pos_of_tr]
    f_tile = tile_of_chunk[np.repeat(np.arange(nch), np.diff(fc_ptr))]
    base, end = _place(np.ones(m, dtype=np.int64), f_tile,
                       key[faces[fc_face]].max(axis=1), part_tile, 0)
    if end > m:
        base = fc_face.copy()      # each face its own row
    slot_of_face = np.empty(m, dtype=np.int64)
    slot_of_face[fc_face] = base
    # 32-bit: the gathers stream 4 bytes per index, and one index per face
    vf_row = 3 * slot_of_face[vf_face] + model.vertex_faces.corner
    return w, tr.astype(np.uint32), base.astype(np.uint32), vf_row.astype(np.uint32)


def _face_stream(model, fc_face):
    """What the step's vertex pass reads of the faces, in its order (``fc_face``):
    their corners (m,3) uint32, and for each its row (m,) uint32 in a table of the
    distinct rest shapes (Dinv (R,2,2), area (R,)), in order of first use. Rows are
    equal when their bits are: the step computes the same numbers as from ``dinv`` and
    ``area`` themselves. A structured sheet has a few dozen shapes (18 on the scene's
    grids), so the step streams 20 bytes per face (corners, row and ring slot) where it
    streamed 80 (int64 corners, Dinv, area, face and slot indices); an irregular mesh,
    whose table has a row per face, streams 60."""
    m = len(fc_face)
    f = model.faces
    shape = np.concatenate([f.dinv[fc_face].reshape(m, 4), f.area[fc_face, None]], axis=1)
    _, first, row = np.unique(shape.view(np.int64), axis=0, return_index=True,
                              return_inverse=True)
    order = np.argsort(first)
    rank = np.empty(len(order), dtype=np.int64)
    rank[order] = np.arange(len(order))
    table = shape[first[order]]
    return (f.corners[fc_face].astype(np.uint32), rank[row.ravel()].astype(np.uint32),
            np.ascontiguousarray(table[:, :4].reshape(-1, 2, 2)),
            np.ascontiguousarray(table[:, 4]))


def _place(size, tile, last, part_tile, start):
    """Slots for items (lane groups, faces) of ``size`` entries, written in order, in
    tiles ``tile``, last read at the end of tile ``last`` (T: the seam): those read
    inside their part, but for the 5% read the latest, go round a ring per part; the
    others get slots of their own from ``start`` on. Returns (slots, end)."""
    ntile = int(part_tile[-1])
    part = np.searchsorted(part_tile, tile, 'right') - 1
    ring = last < ntile
    # the few read much later than most (lanes far apart, e.g. along a boundary)
    # would set the ring's length alone
    if ring.any():
        ring &= last - tile <= int(np.quantile((last - tile)[ring], 0.95))
    base = np.empty(len(size), dtype=np.int64)
    own = np.nonzero(~ring)[0]
    base[own] = start + np.cumsum(size[own]) - size[own]
    end = start + int(size[own].sum())
    for p in range(len(part_tile) - 1):
        end = -(-end // 8) * 8          # each ring starts on a cache line of its own
        q = np.nonzero(ring & (part == p))[0]
        if len(q):
            lin, R = _ring_slots(size[q], tile[q], last[q])
            base[q] = end + lin
            end += R
    return base, end


def _ring_slots(size, tile, last):
    """Ring slots for groups of ``size`` entries written in order in tiles ``tile`` and
    read up to the end of tile ``last``: (slot of each group, ring length R). A
    group's slot is its place in the written sequence modulo R, moved to the ring's
    start if it would wrap; R is the smallest multiple of the largest group that
    keeps every group's entries until its last reader is done."""
    step = int(size.max())
    total = int(size.sum())
    R = step
    while True:
        if R >= total:
            return np.cumsum(size) - size, total
        if size.min() == step:      # equal sizes (faces): R is a multiple, no gaps
            lin = np.cumsum(size) - size
        else:
            lin = np.empty(len(size), dtype=np.int64)
            at = 0
            for q, m in enumerate(size.tolist()):
                if at % R + m > R:
                    at += R - at % R
                lin[q] = at
                at += m
        # entries written up to the end of each tile, and the span each group needs
        done = np.maximum.accumulate(lin + size)
        upto = done[np.searchsorted(tile, last, 'right') - 1]
        need = int((upto - lin).max())
        if need <= R:
            return lin % R, R
        R = -(-need // step) * step
