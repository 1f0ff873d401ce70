"""The vertex pass of the step: the jet terms four vertices at a time, and its layout.

:func:`vertex_lanes` is the SIMD twin of :func:`..core.terms.jet.jet_adjoint` (plus the
coupling's strain side, :func:`..core.terms.coupling.add_face_side`): the same formulas,
each operation on the same quantity of four vertices in one AVX vector (:mod:`.simd`).
Vertices whose stencil size does not fill a group of four go one at a time through the
scalar functions themselves. ``test/test_fast.py`` checks both against the terms.

Why: the vertex pass works on short stencils (about 18 entries); vectorised along the
stencil (what LLVM does by itself) each vertex pays for loop remainders, horizontal sums
and its per-vertex arithmetic on one lane. Across vertices the step ran 0.75x the time
(0.20 -> 0.15 ms at N = 40; docs/performance.md).

Layout (:func:`lane_layout`): the groups' stencil entries are interleaved (entry s of lane
l at ``g_ptr[g] + 4 s + l``), so the four vertices' weights, residuals and gradients move
as one vector load or store; equal-shape stencils share one block of weights, and groups
with equal neighbour offsets and rest residuals one block of those, so a structured sheet
streams almost no weights.
"""
from __future__ import annotations

from typing import NamedTuple

import numba as nb
import numpy as np

from ..core.compiled import kernel
from ..core.material import contract
from ..core.terms.coupling import add_face_side, epsbar
from ..core.terms.jet import cross, jet_adjoint, phi_dot
from ..core.terms.membrane import face_membrane
from .simd import LANES, lane, splat, vfma, vload, vload3, vset, vsqrt, vstore

__all__ = ['Lanes', 'lane_layout', 'chunk_of_vertex', 'vertex_chunk', 'vertex_chunk_coupled',
           'build_lanes']


class Lanes(NamedTuple):
    """The vertex pass's stencils in lane order (:func:`lane_layout`)."""

    g_vert: np.ndarray      # (G, 4) int64 the vertices of each lane group
    g_ptr: np.ndarray       # (G+1,) int64 its entries
    g_wptr: np.ndarray      # (G, 4) int64 weight block, entry block, gradient slot, rows?
    s_vert: np.ndarray      # (S,) int64 single vertices
    s_ptr: np.ndarray       # (S+1,) int64 their entries
    s_wptr: np.ndarray      # (S,) int64 their weight blocks
    idx: np.ndarray         # (KE,) neighbours: absolute (singles), offsets (groups)
    w: np.ndarray           # (9, KW) weight blocks
    uv: np.ndarray          # (2, KW) chart coordinates of the weight blocks
    sigma: np.ndarray       # (KE,) rest residuals
    pos: np.ndarray         # (K,) position of each CSR entry in lane order


def build_lanes(model, lanes: int = LANES) -> Lanes:
    """The lane layout of ``model``'s jets (``lanes = 1``: every vertex a single one)."""
    j = model.jets
    (g_vert, g_ptr, g_wptr, s_vert, s_ptr, s_wptr, pos, wsrc, ln_idx,
     ln_sigma) = lane_layout(j.ptr, model.jet.template, j.idx, j.sigma, lanes)
    return Lanes(g_vert, g_ptr, g_wptr, s_vert, s_ptr, s_wptr, ln_idx,
                 np.ascontiguousarray(j.w[:, wsrc]), np.ascontiguousarray(j.uv[:, wsrc]),
                 ln_sigma, pos)


@kernel(inline='always')
def _gather_lanes(a, c, i0, i1, i2, i3):
    """(a[i0, c], a[i1, c], a[i2, c], a[i3, c]) as one vector."""
    return vset(a[i0, c], a[i1, c], a[i2, c], a[i3, c])


@kernel(inline='always')
def vertex_lanes(g, x, g_vert, g_ptr, g_wptr, st_idx, st_w, st_uv, st_sigma, stab, dual_area,
                 ainv, rest_b, xi, phi, sc, ch, contrib, faces, dinv, face_area, K_face,
                 vf_ptr, vf_face, vf_corner, vf_entry, vf_K, coupled):
    """:func:`..core.terms.jet.jet_adjoint` for the four vertices of lane group g at once,
    one per SIMD lane (:mod:`.simd`), with the coupling: the same formulas, each operation
    on the four vertices in one vector; the coupling's strain average and strain side go
    lane by lane through the scalar functions of ``core/terms/coupling.py``. ``coupled``
    (a literal at every call: ``fast/step.py`` compiles a step for phi = 0 and one for
    phi != 0) keeps the coupling's code out of the step without it, which otherwise ran
    the vertex pass 1.2-1.7x slower even with the coupling skipped at run time.

    The group's stencils have the same size, and their entries are interleaved (lane
    order, :func:`lane_layout`): entry s of lane l sits at ``g_ptr[g] + 4 s + l``, s = 0
    the centre, its weights and chart coordinates at ``g_wptr[g, 0] + 4 s + l`` (a block
    that groups with the same stencil templates share) and its neighbour's offset
    ``j - i`` and rest residual at ``g_wptr[g, 1] + 4 s + l`` (a block that groups with
    the same offsets and residuals share); its gradients go to ``contrib`` from
    ``g_wptr[g, 2]`` on, in the same order (its entries' own positions, or in the tiled
    step a slot of its part's ring, ``fast/plan.py``). So the weights, chart coordinates
    and rest residuals of one entry of the four vertices load as one vector, and the
    gradients store as one. The positions x[j] are gathered lane by lane, except in a
    group whose four neighbours of each entry are four consecutive rows of x
    (``g_wptr[g, 3]``; 83% of the vertices of a 40 x 40 sheet): those load as one block
    (``simd.vload3``). The stencil loops have no remainder and no horizontal sums, and
    the per-vertex work (normal, resultants, adjoint) is shared four ways."""
    K = contrib.shape[1]     # entries (ln_idx and ln_sigma hold blocks, maybe fewer)
    KW = st_w.shape[1]
    W = sc.shape[2]
    r0 = ch * 5 * W          # scratch rows d_0, d_1, d_2, dn, h of this chunk (flat offsets)
    ns = (g_ptr[g + 1] - g_ptr[g]) // 4 - 1
    b = g_wptr[g, 2]        # its gradients: its entries' positions, or its slot of a ring
    p0 = b + 4
    bw = g_wptr[g, 0]       # weights and chart coordinates: the group's (shared) block
    q0 = bw + 4
    e0 = g_wptr[g, 1] + 4   # neighbour offsets and rest residuals: its (shared) block
    # the lanes' vertices, unsigned (no negative-index wrap-around per load or store);
    # the coupling's functions take them signed (they add 1 to them)
    i0 = nb.uint64(g_vert[g, 0])
    i1 = nb.uint64(g_vert[g, 1])
    i2 = nb.uint64(g_vert[g, 2])
    i3 = nb.uint64(g_vert[g, 3])
    rows = g_wptr[g, 3] != 0     # the lanes' neighbours are four consecutive rows of x
    if rows:
        xi0, xi1, xi2 = vload3(x, 3 * i0)
    else:
        xi0 = _gather_lanes(x, 0, i0, i1, i2, i3)
        xi1 = _gather_lanes(x, 1, i0, i1, i2, i3)
        xi2 = _gather_lanes(x, 2, i0, i1, i2, i3)
    # pass 1: offsets d_k and the tangent vectors a_1, a_2 (Eq. 8)
    a10 = splat(0.0)
    a11 = splat(0.0)
    a12 = splat(0.0)
    a20 = splat(0.0)
    a21 = splat(0.0)
    a22 = splat(0.0)
    for s in range(ns):
        kw = q0 + 4 * s
        ke = nb.uint64(e0 + 4 * s)      # unsigned: no negative-index wrap-around per load
        # j = i + (j - i) in unsigned arithmetic: modulo 2^64, so a negative offset (a
        # two's complement) wraps to the right index
        j0 = i0 + nb.uint64(st_idx[ke])
        if rows:
            y0, y1, y2 = vload3(x, 3 * j0)
        else:
            j1 = i1 + nb.uint64(st_idx[ke + nb.uint64(1)])
            j2 = i2 + nb.uint64(st_idx[ke + nb.uint64(2)])
            j3 = i3 + nb.uint64(st_idx[ke + nb.uint64(3)])
            y0 = _gather_lanes(x, 0, j0, j1, j2, j3)
            y1 = _gather_lanes(x, 1, j0, j1, j2, j3)
            y2 = _gather_lanes(x, 2, j0, j1, j2, j3)
        d0 = y0 - xi0
        d1 = y1 - xi1
        d2 = y2 - xi2
        vstore(sc, r0 + 4 * s, d0)
        vstore(sc, r0 + W + 4 * s, d1)
        vstore(sc, r0 + 2 * W + 4 * s, d2)
        w0 = vload(st_w, kw)
        w1 = vload(st_w, KW + kw)
        a10 = vfma(w0, d0, a10)
        a11 = vfma(w0, d1, a11)
        a12 = vfma(w0, d2, a12)
        a20 = vfma(w1, d0, a20)
        a21 = vfma(w1, d1, a21)
        a22 = vfma(w1, d2, a22)
    c0, c1, c2 = cross(a10, a11, a12, a20, a21, a22)
    cn = vsqrt(c0 * c0 + c1 * c1 + c2 * c2)
    icn = 1.0 / cn
    n0 = c0 * icn
    n1 = c1 * icn
    n2 = c2 * icn
    # pass 2: dn_k and the jet along the normal q_c = coef_c . n (Eq. 11)
    q2 = splat(0.0)
    q3 = splat(0.0)
    q4 = splat(0.0)
    q5 = splat(0.0)
    q6 = splat(0.0)
    q7 = splat(0.0)
    q8 = splat(0.0)
    for s in range(ns):
        kw = q0 + 4 * s
        dn = (vload(sc, r0 + 4 * s) * n0 + vload(sc, r0 + W + 4 * s) * n1
              + vload(sc, r0 + 2 * W + 4 * s) * n2)
        vstore(sc, r0 + 3 * W + 4 * s, dn)
        q2 = vfma(vload(st_w, 2 * KW + kw), dn, q2)
        q3 = vfma(vload(st_w, 3 * KW + kw), dn, q3)
        q4 = vfma(vload(st_w, 4 * KW + kw), dn, q4)
        q5 = vfma(vload(st_w, 5 * KW + kw), dn, q5)
        q6 = vfma(vload(st_w, 6 * KW + kw), dn, q6)
        q7 = vfma(vload(st_w, 7 * KW + kw), dn, q7)
        q8 = vfma(vload(st_w, 8 * KW + kw), dn, q8)
    k11 = -(q2 - _gather_lanes(rest_b, 0, i0, i1, i2, i3))
    k12 = -(q3 - _gather_lanes(rest_b, 1, i0, i1, i2, i3))
    k22 = -(q4 - _gather_lanes(rest_b, 2, i0, i1, i2, i3))
    i11 = _gather_lanes(ainv, 0, i0, i1, i2, i3)
    i12 = _gather_lanes(ainv, 1, i0, i1, i2, i3)
    i22 = _gather_lanes(ainv, 2, i0, i1, i2, i3)
    m11, m12, m22 = contract(2.0 * xi, i11, i12, i22, k11, k12, k22)
    if coupled:     # M += Theta epsbar
        a0, b0, c0_ = epsbar(g_vert[g, 0], x, faces, dinv, vf_ptr, vf_face, vf_K, phi)
        a1, b1, c1_ = epsbar(g_vert[g, 1], x, faces, dinv, vf_ptr, vf_face, vf_K, phi)
        a2, b2, c2_ = epsbar(g_vert[g, 2], x, faces, dinv, vf_ptr, vf_face, vf_K, phi)
        a3, b3, c3_ = epsbar(g_vert[g, 3], x, faces, dinv, vf_ptr, vf_face, vf_K, phi)
        s11, s12, s22 = contract(phi, i11, i12, i22, vset(a0, a1, a2, a3),
                                 vset(b0, b1, b2, b3), vset(c0_, c1_, c2_, c3_))
        m11 = m11 + s11
        m12 = m12 + s12
        m22 = m22 + s22
    A = vset(dual_area[i0], dual_area[i1], dual_area[i2], dual_area[i3])
    g11 = -A * m11
    g12 = -2.0 * A * m12
    g22 = -A * m22
    # pass 3: residuals along the normal and h_k = dE_i/d(dn_k)
    om = vset(stab[i0], stab[i1], stab[i2], stab[i3])
    # e, the residual's sum of squares, is not stored here (the energy report takes it
    # from core/terms/jet.py), and LLVM drops it in the end. It stays because with it in the loop
    # LLVM compiles the loop into code that ran the step 0.87-0.91x the time of the loop
    # without it (paired, N = 20 / 40).
    e = splat(0.0)
    for s in range(ns):
        kw = q0 + 4 * s
        dd = (vload(sc, r0 + 3 * W + 4 * s) - vload(st_sigma, e0 + 4 * s)
              - phi_dot(vload(st_uv, kw), vload(st_uv, KW + kw), 0.0, 0.0, q2, q3, q4, q5, q6,
                         q7, q8))
        vstore(sc, r0 + 4 * W + 4 * s,
               2.0 * om * dd + vload(st_w, 2 * KW + kw) * g11 + vload(st_w, 3 * KW + kw) * g12
               + vload(st_w, 4 * KW + kw) * g22)
        e = vfma(dd, dd, e)
    e = om * e
    # V = sum_k h_k d_k and sum_k h_k
    v0 = splat(0.0)
    v1 = splat(0.0)
    v2 = splat(0.0)
    hs = splat(0.0)
    for s in range(ns):
        h = vload(sc, r0 + 4 * W + 4 * s)
        v0 = vfma(h, vload(sc, r0 + 4 * s), v0)
        v1 = vfma(h, vload(sc, r0 + W + 4 * s), v1)
        v2 = vfma(h, vload(sc, r0 + 2 * W + 4 * s), v2)
        hs = hs + h
    vn = v0 * n0 + v1 * n1 + v2 * n2
    t0 = (v0 - vn * n0) * icn
    t1 = (v1 - vn * n1) * icn
    t2 = (v2 - vn * n2) * icn
    j10, j11, j12 = cross(a20, a21, a22, t0, t1, t2)
    j20, j21, j22 = cross(t0, t1, t2, a10, a11, a12)
    # pass 4: dE_i/dx_j per stencil entry; the centre takes minus their sum
    for s in range(ns):
        k = p0 + 4 * s
        kw = q0 + 4 * s
        h = vload(sc, r0 + 4 * W + 4 * s)
        w0 = vload(st_w, kw)
        w1 = vload(st_w, KW + kw)
        vstore(contrib, k, w0 * j10 + w1 * j20 + h * n0)
        vstore(contrib, K + k, w0 * j11 + w1 * j21 + h * n1)
        vstore(contrib, 2 * K + k, w0 * j12 + w1 * j22 + h * n2)
    c0w = vload(st_w, bw)
    c1w = vload(st_w, KW + bw)
    vstore(contrib, b, c0w * j10 + c1w * j20 - hs * n0)
    vstore(contrib, K + b, c0w * j11 + c1w * j21 - hs * n1)
    vstore(contrib, 2 * K + b, c0w * j12 + c1w * j22 - hs * n2)
    # the coupling's strain side, into each lane's own entries
    for ln in range(4 if coupled else 0):
        add_face_side(g_vert[g, ln], x, faces, dinv, face_area, K_face, vf_ptr, vf_face,
                      vf_corner, vf_entry, phi, ainv, lane(k11, ln), lane(k12, ln),
                      lane(k22, ln), contrib, b + ln, 4)


@kernel(inline='always')
def _vertex_chunk(ch, nch, row, x, lanes, plan, faces, vf, vertices, coeff, work, coupled):
    """Work item (chunk) ``ch`` of the vertex pass (``fast/step.py``): the membrane of the
    chunk's faces, then the jet terms of its lane groups (:func:`vertex_lanes`) and of its
    single vertices (stencil sizes that do not fill a group: the scalar
    ``jet_adjoint`` and ``add_face_side``), writing the stencil gradients ``contrib``
    (3,K) in the lane layout of :func:`lane_layout`; ``nch`` chunks split the mesh
    (:func:`chunk_of_vertex`); ``scratch[row]`` (5, S) is this work item's alone while it
    runs (no allocation, no shared writes).

    The faces q = ``fc_ptr[ch]:fc_ptr[ch + 1]`` (``core.terms.membrane.face_membrane``)
    come in chunk order, streamed front to back: their corners ``fc_vert[q]`` (uint32),
    their rest shapes as rows ``fc_tpl[q]`` of a table of the distinct (Dinv, area) pairs
    (``t_dinv``, ``t_area``; a structured sheet has a few dozen) and the rows
    ``fc_slot[q]`` of fgrad their corner gradients go to (the face itself, or a ring slot
    in the tiled step). The coupling (``coupled``, a literal: :func:`vertex_lanes`) reads
    the faces of its vertices from ``faces``, ``dinv`` and ``face_area`` directly.

    Called through :func:`vertex_chunk` and :func:`vertex_chunk_coupled`, ``forceinline``
    (LLVM ``alwaysinline``) functions of their own, one for each value of the literal
    ``coupled``: inlined into the parallel loop's body, they get that body's ``noalias``
    arrays (a plain call was 5-10% slower), and each is optimised without the other's
    code (one function with a run-time flag ran the vertex pass 1.07x slower at phi = 0).
    The arrays come in the named tuples of ``core/model.py``, ``.plan`` and ``fast/step.py``
    (numba inlines no function of more than ~30 arguments).
    """
    g_vert, g_ptr, s_vert, s_ptr, s_wptr = (lanes.g_vert, lanes.g_ptr, lanes.s_vert,
                                            lanes.s_ptr, lanes.s_wptr)
    st_idx, st_w, st_uv, st_sigma = lanes.idx, lanes.w, lanes.uv, lanes.sigma
    g_wptr, fc_ptr, fc_slot = plan.g_wptr, plan.fc_ptr, plan.fc_slot
    fc_vert, fc_tpl, t_dinv, t_area = plan.fc_vert, plan.fc_tpl, plan.t_dinv, plan.t_area
    corners, dinv, face_area, K_face = faces.corners, faces.dinv, faces.area, faces.K
    vf_ptr, vf_face, vf_corner, vf_entry, vf_K = vf.ptr, vf.face, vf.corner, vf.entry, vf.K
    dual_area, ainv, rest_b = vertices.dual_area, vertices.ainv, vertices.rest_b
    zeta, xi, phi, stab = coeff.zeta, coeff.xi, coeff.phi, coeff.stab
    fgrad, contrib, scratch = work.fgrad, work.contrib, work.scratch
    # the chunk sizes follow from the caller's nch (not from a module constant, which
    # numba's cache would freeze into the compiled code); chunk_of_vertex is this split in
    # numpy. (Spreading the groups and singles evenly over the chunks ran the pass
    # 3-9% slower at N = 20 / 40: the few singles then leave the first chunks, i.e. the
    # calling thread, which starts before the woken worker.)
    ng = g_vert.shape[0]
    nsv = s_vert.shape[0]
    for q in range(nb.uint64(fc_ptr[ch]), nb.uint64(fc_ptr[ch + 1])):
        face_membrane(q, nb.uint64(fc_tpl[q]), nb.uint64(fc_slot[q]), x, fc_vert, t_dinv,
                      t_area, zeta, fgrad)
    gchunk = (ng + nch - 1) // nch
    for g in range(ch * gchunk, min(ng, (ch + 1) * gchunk)):
        vertex_lanes(g, x, g_vert, g_ptr, g_wptr, st_idx, st_w, st_uv, st_sigma, stab,
                     dual_area, ainv, rest_b, xi, phi, scratch, row, contrib, corners, dinv,
                     face_area, K_face, vf_ptr, vf_face, vf_corner, vf_entry, vf_K, coupled)
    schunk = (nsv + nch - 1) // nch
    for u in range(ch * schunk, min(nsv, (ch + 1) * schunk)):
        i = s_vert[u]
        e11 = 0.0
        e12 = 0.0
        e22 = 0.0
        if coupled:
            e11, e12, e22 = epsbar(i, x, corners, dinv, vf_ptr, vf_face, vf_K, phi)
        k11, k12, k22, _ = jet_adjoint(i, s_ptr[u], s_ptr[u + 1], s_wptr[u], x, st_idx, st_w,
                                       st_uv, st_sigma, stab, dual_area, ainv, rest_b, xi,
                                       phi, e11, e12, e22, scratch, row, contrib)
        if coupled:
            add_face_side(i, x, corners, dinv, face_area, K_face, vf_ptr, vf_face, vf_corner,
                          vf_entry, phi, ainv, k11, k12, k22, contrib, s_ptr[u], 1)


@kernel(forceinline=True)
def vertex_chunk(ch, nch, row, x, lanes, plan, faces, vf, vertices, coeff, work):
    """:func:`_vertex_chunk` without coupling (phi = 0)."""
    _vertex_chunk(ch, nch, row, x, lanes, plan, faces, vf, vertices, coeff, work, False)


@kernel(forceinline=True)
def vertex_chunk_coupled(ch, nch, row, x, lanes, plan, faces, vf, vertices, coeff, work):
    """:func:`_vertex_chunk` with the coupling (phi != 0)."""
    _vertex_chunk(ch, nch, row, x, lanes, plan, faces, vf, vertices, coeff, work, True)


def chunk_of_vertex(n: int, nch: int, g_vert: np.ndarray, s_vert: np.ndarray) -> np.ndarray:
    """The work item (chunk) of every vertex, (n,) int64: the split of
    :func:`vertex_chunk`, lane groups in equal runs, then single vertices in equal runs."""
    chunk = np.empty(n, dtype=np.int64)
    if len(g_vert):
        chunk[g_vert] = (np.arange(len(g_vert)) // -(-len(g_vert) // nch))[:, None]
    if len(s_vert):
        chunk[s_vert] = np.arange(len(s_vert)) // -(-len(s_vert) // nch)
    return chunk


def lane_layout(st_ptr: np.ndarray, template: np.ndarray, st_idx: np.ndarray,
                st_sigma: np.ndarray, lanes: int = LANES):
    """Order of the stencil entries, and blocks of the weights and of the entries' own
    data, for the vertex pass (:func:`vertex_chunk`).

    Entries (the gradients the pass writes, contrib): the vertices left over from the
    groups below (fewer than ``lanes`` of a stencil size; ``lanes = 1`` puts every vertex
    here) come first, as plain CSR blocks ``s_ptr[u] : s_ptr[u + 1]``. Then the vertices
    with the same stencil size form groups of ``lanes`` (sorted by stencil template, then
    vertex, within a size; groups in the order of their first vertex); a group's entries
    are interleaved, entry s of lane l at ``g_ptr[g] + lanes s + l`` (s = 0 the centre).

    Weights (and chart coordinates): a group reads the block at ``g_wptr[g, 0]``, in the
    same interleaved order; groups whose lanes have the same templates (geometry.py,
    ``JetOperator.template``) share one block, so a structured sheet streams almost no
    weights. A single vertex reads its block at ``s_wptr[u]``.

    The entries' neighbour and rest residual (``ln_idx``, ``ln_sigma``): a single vertex
    reads them at its entries' own positions (the neighbour's index); a group reads them
    in the block at ``g_wptr[g, 1]``, interleaved, with the neighbour as an offset from
    the lane's vertex (``j = i + ln_idx``). Groups whose offsets and rest residuals are
    the same to the bit share one block: on a sheet numbered row by row and flat at rest
    the pass then streams neither indices nor residuals, only its gradients.

    A group whose lanes are consecutive vertices i, i+1, i+2, i+3 with the same offsets
    at every entry (most of a sheet numbered row by row) finds the four neighbours of an
    entry in four consecutive rows of x, and loads them as one block (``simd.vload3``);
    ``g_wptr[g, 3]`` says so.

    Returns ``g_vert`` (G, lanes), ``g_ptr`` (G+1,), ``g_wptr`` (G, 4: weight block, entry
    block, where its gradients go: here ``g_ptr[g]``, its entry positions; 1 if its lanes'
    neighbours are rows, else 0), ``s_vert`` (S,),
    ``s_ptr`` (S+1,), ``s_wptr`` (S,), all int64; ``pos`` (K,): the position of CSR entry
    k in the entry order (a permutation); ``wsrc`` (KW,): the CSR entry whose weights fill
    each slot of the weight blocks; ``ln_idx`` (KE,) int64 and ``ln_sigma`` (KE,)."""
    n = len(st_ptr) - 1
    sizes = np.diff(st_ptr)
    order = np.lexsort((np.arange(n), template, sizes))
    _, first, counts = np.unique(sizes[order], return_index=True, return_counts=True)
    rank = np.arange(n) - np.repeat(first, counts)
    grouped = rank < np.repeat(counts // lanes * lanes, counts)
    if lanes == 1:
        grouped[:] = False
    g_vert = order[grouped].reshape(-1, lanes).astype(np.int64)
    g_vert = g_vert[np.argsort(g_vert[:, 0], kind='stable')]
    s_vert = np.sort(order[~grouped]).astype(np.int64)
    g_size = sizes[g_vert[:, 0]]
    s_ptr = np.zeros(len(s_vert) + 1, dtype=np.int64)
    np.cumsum(sizes[s_vert], out=s_ptr[1:])
    g_ptr = np.full(len(g_vert) + 1, s_ptr[-1], dtype=np.int64)
    np.cumsum(lanes * g_size, out=g_ptr[1:])
    g_ptr[1:] += s_ptr[-1]
    pos = np.empty(st_ptr[-1], dtype=np.int64)
    # grouped entries: vertex g_vert[g, l], its entry s -> g_ptr[g] + lanes s + l
    gv = g_vert.ravel()
    sz = sizes[gv]
    s_in = np.arange(sz.sum()) - np.repeat(np.cumsum(sz) - sz, sz)
    lane_of = np.tile(np.arange(lanes), len(g_vert))
    pos[np.repeat(st_ptr[gv], sz) + s_in] = (
        np.repeat(np.repeat(g_ptr[:-1], lanes) + lane_of, sz) + lanes * s_in)
    sz = sizes[s_vert]
    s_in = np.arange(sz.sum()) - np.repeat(np.cumsum(sz) - sz, sz)
    pos[np.repeat(st_ptr[s_vert], sz) + s_in] = np.repeat(s_ptr[:-1], sz) + s_in
    owner = np.repeat(np.arange(n, dtype=np.int64), sizes)
    offset = st_idx - owner
    # weight blocks (one per distinct tuple of lane templates, then one per single vertex)
    # and entry blocks (after the single vertices' entries: one per distinct pair of the
    # group's offsets and rest residuals)
    wblocks, eblocks = {}, {}
    g_wptr = np.zeros((len(g_vert), 4), dtype=np.int64)
    s_src = [np.arange(st_ptr[i], st_ptr[i + 1]) for i in s_vert]    # their CSR entries
    wsrc, esrc = [], list(s_src)
    nw, ne = 0, int(s_ptr[-1])
    for g, verts in enumerate(g_vert):
        m = int(g_size[g])
        # slot lanes s + l holds entry s of lane l
        src = (st_ptr[verts][None, :] + np.arange(m)[:, None]).ravel()
        wkey = tuple(template[verts])
        if wkey not in wblocks:
            wblocks[wkey] = nw
            wsrc.append(src)        # each lane's own CSR entry: same weights as the template
            nw += lanes * m
        ekey = offset[src].tobytes() + st_sigma[src].tobytes()
        if ekey not in eblocks:
            eblocks[ekey] = ne
            esrc.append(src)
            ne += lanes * m
        g_wptr[g, :2] = wblocks[wkey], eblocks[ekey]
        # rows: lane l's neighbour at every entry is lane 0's plus l
        off = offset[src].reshape(m, lanes)
        g_wptr[g, 3] = (lanes == LANES and np.all(verts == verts[0] + np.arange(lanes))
                        and np.all(off == off[:, :1]))
    s_wptr = nw + s_ptr[:-1]
    wsrc += s_src
    wsrc = np.concatenate(wsrc).astype(np.int64) if wsrc else np.zeros(0, np.int64)
    esrc = np.concatenate(esrc).astype(np.int64) if esrc else np.zeros(0, np.int64)
    ln_idx = np.where(np.arange(len(esrc)) < s_ptr[-1], st_idx[esrc], offset[esrc])
    ln_sigma = st_sigma[esrc].copy()
    g_wptr[:, 2] = g_ptr[:-1]
    return g_vert, g_ptr, g_wptr, s_vert, s_ptr, s_wptr, pos, wsrc, ln_idx, ln_sigma


