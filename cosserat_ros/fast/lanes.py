"""The vertex pass of the step: the jet terms four vertices at a time, and its layout.

:func:`vertex_lanes` is the SIMD twin of :func:`..core.terms.jet.jet_adjoint` (plus the
coupling's strain side, :func:`..core.terms.coupling.add_face_side`): the same formulas,
each operation on the same quantity of four vertices in one AVX vector (:mod:`.simd`).
Vertices whose stencil size does not fill a group of four go one at a time through the
scalar functions themselves. ``test/test_fast.py`` checks both against the terms.

Why: the vertex pass works on short stencils (about 18 entries); vectorised along the
stencil (what LLVM does by itself) each vertex pays for loop remainders, horizontal sums
and its per-vertex arithmetic on one lane; across vertices none of that is paid
(docs/performance.md).

Layout (:func:`lane_layout`): the groups' stencil entries are interleaved (entry s of lane
l at ``g_ptr[g] + 4 s + l``), so the four vertices' weights, residuals and gradients move
as one vector load or store; equal-shape stencils share one block of weights, and groups
with equal neighbour offsets and rest residuals one block of those, so a structured sheet
streams almost no weights.
"""
from __future__ import annotations

from typing import NamedTuple

import numba as nb
from numba import literally
import numpy as np

from ..core.compiled import kernel
from ..core.material import contract
from ..core.terms.coupling import add_face_side, epsbar
from ..core.terms.jet import cross, floored_normal, jet_adjoint, phi_dot
from ..core.terms.membrane import face_membrane
from .simd import LANES, lane, splat, vfma, vload, vload3, vset, vsqrt, vstore

__all__ = ['Lanes', 'lane_layout', 'chunk_of_vertex', 'vertex_chunk', 'build_lanes']


class Lanes(NamedTuple):
    """The vertex pass's stencils in lane order (:func:`lane_layout`)."""

    g_vert: np.ndarray      # (G, 4) int64 the vertices of each lane group
    g_ptr: np.ndarray       # (G+1,) int64 its entries
    g_wptr: np.ndarray      # (G, 5) int64 weight, entry block, gradient slot, rows, coupling
    s_vert: np.ndarray      # (S,) int64 single vertices
    s_ptr: np.ndarray       # (S+1,) int64 their entries
    s_wptr: np.ndarray      # (S,) int64 their weight blocks
    idx: np.ndarray         # (KE,) neighbours: absolute (singles), offsets (groups)
    w: np.ndarray           # (9, KW) weight blocks
    uv: np.ndarray          # (2, KW) chart coordinates of the weight blocks
    sigma: np.ndarray       # (KE,) rest residuals
    pos: np.ndarray         # (K,) position of each CSR entry in lane order
    sp_P: np.ndarray        # (V, 4) the coupling's spoke maps P_q (:func:`spokes`)
    sp_entry: np.ndarray    # (V, 2) the stencil entries of the face's two spokes
    sp_ebar0: np.ndarray    # (n, 3) the rest term of epsbar in that form


def build_lanes(model, lanes: int = LANES) -> Lanes:
    """The lane layout of ``model``'s jets (``lanes = 1``: every vertex a single one), with
    each group's coupling mode in ``g_wptr[:, 4]`` (:func:`coupling_modes`)."""
    j = model.jets
    # vertices of one fan shape (face count, open or closed) in a group: their faces'
    # corners are the same entries of their stencils (geometry.fan_order)
    fan = 2 * np.diff(model.vertex_faces.ptr) + model.mesh.boundary_vertices
    (g_vert, g_ptr, g_wptr, s_vert, s_ptr, s_wptr, pos, wsrc, ln_idx,
     ln_sigma) = lane_layout(j.ptr, model.jet.template, j.idx, j.sigma, lanes, fan)
    sp_P, sp_entry, sp_ebar0 = spokes(model)
    g_wptr = np.ascontiguousarray(np.concatenate(
        [g_wptr, coupling_modes(model, g_vert, sp_P, sp_entry)[:, None]], axis=1))
    return Lanes(g_vert, g_ptr, g_wptr, s_vert, s_ptr, s_wptr, ln_idx,
                 np.ascontiguousarray(j.w[:, wsrc]), np.ascontiguousarray(j.uv[:, wsrc]),
                 ln_sigma, pos, sp_P, sp_entry, sp_ebar0)


def spokes(model):
    """The coupling's strain average in the form the lane kernel computes it.

    A face t of vertex i, with corners (i, j, k) counter-clockwise from i, has its strain
    through the Gram matrix ``G`` of its two spokes ``s_j = x_j - x_i``, ``s_k = x_k - x_i``
    (both stencil offsets of i, which the jet's pass 1 holds): ``F^T F = D'^T G D'`` with
    ``D'`` the inverse of the rest spokes in the face chart, so with ``P = D' K_w``
    (``K_w`` the weighted corner map ``vf_K``)

        epsbar_i = sum_t K_w^T eps_t K_w = 1/2 sum_t P^T G P - ebar0_i,
        ebar0_i  = 1/2 sum_t P^T G_rest P.

    The strain side of the gradient follows: with ``H = A_i/2 P cs P^T`` (cs = Theta kap),
    ``dE/ds_j = 2 (H_11 s_j + H_12 s_k)``, ``dE/ds_k = 2 (H_22 s_k + H_12 s_j)``, and the
    centre takes minus their sum. The same numbers as ``core.terms.coupling`` to
    round-off (``test/test_fast.py``), with no gather of x and no face strain.

    Returns ``P`` (V,4) row by row, the spokes' stencil entries (V,2) and ebar0 (n,3).
    Maps equal to 1e-12 of the largest are made equal to the bit (the first one's), so
    that lane groups of a structured sheet read one (``COUPLING_SHARED``)."""
    vf, f = model.vertex_faces, model.faces
    D = np.linalg.inv(f.dinv)                       # columns: corners 1, 2 from corner 0
    pts = np.zeros((len(D), 3, 2))
    pts[:, 1] = D[:, :, 0]
    pts[:, 2] = D[:, :, 1]
    t, c = vf.face, vf.corner
    pc, pj, pk = pts[t, c], pts[t, (c + 1) % 3], pts[t, (c + 2) % 3]
    E = np.stack([pj - pc, pk - pc], axis=-1)       # the rest spokes, as columns
    P = np.linalg.inv(E) @ vf.K.reshape(-1, 2, 2)
    flat = P.reshape(-1, 4)
    key = np.round(flat / (1e-12 * max(np.abs(flat).max(), 1e-300))).astype(np.int64)
    _, first, inv = np.unique(key, axis=0, return_index=True, return_inverse=True)
    flat = np.ascontiguousarray(flat[first[inv.ravel()]])
    P = flat.reshape(-1, 2, 2)
    rest = np.einsum('qba,qbc,qcd->qad', P, np.einsum('qba,qbc->qac', E, E), P)
    n = model.n_vertices
    owner = np.repeat(np.arange(n), np.diff(vf.ptr))
    ebar0 = np.zeros((n, 3))
    for col, (a, b) in enumerate(((0, 0), (0, 1), (1, 1))):
        np.add.at(ebar0[:, col], owner, 0.5 * rest[:, a, b])
    entry = np.stack([vf.entry[np.arange(len(c)), (c + 1) % 3],
                      vf.entry[np.arange(len(c)), (c + 2) % 3]], axis=1)
    return flat, np.ascontiguousarray(entry), ebar0


#: vertices of one stencil size and no shared template are grouped by fan shape within
#: windows of this many consecutive vertices (:func:`lane_layout`): local enough for the
#: step's tiles (constants.TILE_VERTICES), wide enough that most groups have one fan shape
FAN_WINDOW = 256

#: coupling mode bits of a lane group (:func:`coupling_modes`)
COUPLING_ENTRIES, COUPLING_SHARED = 1, 2


def coupling_modes(model, g_vert: np.ndarray, sp_P: np.ndarray,
                   sp_entry: np.ndarray) -> np.ndarray:
    """How each lane group runs the coupling (G,) int64, a sum of bits (the group's four
    vertices always go as one vector, :func:`_coupling_group`): ``COUPLING_ENTRIES`` if
    they have the same number of faces and each face's spokes at the same stencil entries
    (spokes loaded and their gradients stored as one vector each, not lane by lane), plus
    ``COUPLING_SHARED`` if the four faces' spoke maps ``P`` are equal to the bit (read
    once, not gathered). 97% of the groups of a regular or alternating 40 x 40 sheet have
    ``COUPLING_ENTRIES``."""
    vf = model.vertex_faces
    out = np.zeros(len(g_vert), dtype=np.int64)
    count = np.diff(vf.ptr)
    for g, verts in enumerate(g_vert):
        if len(verts) != LANES or len(set(count[verts])) != 1:
            continue
        nf = count[verts[0]]
        rng = [slice(vf.ptr[i], vf.ptr[i] + nf) for i in verts]
        entries = np.stack([sp_entry[r] for r in rng])
        if not (entries == entries[0]).all():
            continue
        out[g] = COUPLING_ENTRIES
        maps = np.stack([sp_P[r] for r in rng]).view(np.int64)
        if (maps == maps[0]).all():
            out[g] += COUPLING_SHARED
    return out


@kernel(inline='always')
def _gather_lanes(a, c, i0, i1, i2, i3):
    """(a[i0, c], a[i1, c], a[i2, c], a[i3, c]) as one vector."""
    return vset(a[i0, c], a[i1, c], a[i2, c], a[i3, c])


@kernel(inline='always')
def _vadd(sc, o, v):
    vstore(sc, o, vload(sc, o) + v)


@kernel(inline='always')
def _spoke_face(sj0, sj1, sj2, sk0, sk1, sk2, p00, p01, p10, p11, h, cs11, cs12, cs22):
    """One face of each of the four lanes, as vectors (:func:`spokes`): the face's term
    ``P^T G P`` of ``2 epsbar`` (11, 12, 22) and the spokes' gradients ``dE/ds_j``,
    ``dE/ds_k`` (three coordinates each), with ``h = A_i`` (zero: a masked lane)."""
    g11 = sj0 * sj0 + sj1 * sj1 + sj2 * sj2
    g12 = sj0 * sk0 + sj1 * sk1 + sj2 * sk2
    g22 = sk0 * sk0 + sk1 * sk1 + sk2 * sk2
    a00 = g11 * p00 + g12 * p10
    a01 = g11 * p01 + g12 * p11
    a10 = g12 * p00 + g22 * p10
    a11 = g12 * p01 + g22 * p11
    b00 = p00 * cs11 + p01 * cs12
    b01 = p00 * cs12 + p01 * cs22
    b10 = p10 * cs11 + p11 * cs12
    b11 = p10 * cs12 + p11 * cs22
    # 2 H = A P cs P^T
    h11 = h * (b00 * p00 + b01 * p01)
    h12 = h * (b00 * p10 + b01 * p11)
    h22 = h * (b10 * p10 + b11 * p11)
    return (p00 * a00 + p10 * a10, p00 * a01 + p10 * a11, p01 * a01 + p11 * a11,
            h11 * sj0 + h12 * sk0, h11 * sj1 + h12 * sk1, h11 * sj2 + h12 * sk2,
            h22 * sk0 + h12 * sj0, h22 * sk1 + h12 * sj1, h22 * sk2 + h12 * sj2)


@kernel(inline='always')
def _spoke_lanes(sc, d, ea, eb, ec, ed):
    """Stencil offsets d_e of entry e_l (>= 1) of each lane, from the scratch rows at
    flat offset d (entry e of lane l at ``d + 4 (e - 1) + l``): three vectors."""
    W = sc.shape[2]
    scf = sc.reshape(sc.size)
    oa = nb.uint64(d + 4 * (ea - 1))
    ob = nb.uint64(d + 4 * (eb - 1) + 1)
    oc = nb.uint64(d + 4 * (ec - 1) + 2)
    od = nb.uint64(d + 4 * (ed - 1) + 3)
    return (vset(scf[oa], scf[ob], scf[oc], scf[od]),
            vset(scf[oa + W], scf[ob + W], scf[oc + W], scf[od + W]),
            vset(scf[oa + 2 * W], scf[ob + 2 * W], scf[oc + 2 * W], scf[od + 2 * W]))


@kernel(refcount=False)
def _coupling_group(i0, i1, i2, i3, mode, vf_ptr, sp_P, sp_entry, sp_ebar0, A, cs11, cs12, cs22,
                    sc, r0, W):
    """The coupling of the four lanes at once (:func:`spokes`): epsbar (three vectors)
    from the spokes the jet's pass 1 left in the scratch rows 0-2 of flat offset ``r0``,
    and the strain side added to the scratch rows 5-7 (the centre at entry 0). With
    ``COUPLING_ENTRIES`` in ``mode`` face f's spokes sit at the same entries in every lane
    (one vector load and store each; with ``COUPLING_SHARED`` the spoke map read once);
    otherwise a lane with fewer faces repeats its last one under a zero mask and the
    spokes go lane by lane. A function of its own, not inlined: inlined, its code slowed
    the jet's passes around it."""
    t0 = r0 + 5 * W
    e11 = splat(0.0)
    e12 = splat(0.0)
    e22 = splat(0.0)
    qa = nb.uint64(vf_ptr[i0])
    qb = nb.uint64(vf_ptr[i1])
    qc = nb.uint64(vf_ptr[i2])
    qd = nb.uint64(vf_ptr[i3])
    na = nb.uint64(vf_ptr[i0 + nb.uint64(1)]) - qa
    if (mode & COUPLING_ENTRIES) != 0:
        shared = (mode & COUPLING_SHARED) != 0
        for f in range(na):
            ka, kb, kc, kd = qa + f, qb + f, qc + f, qd + f
            oj = 4 * (sp_entry[ka, 0] - 1)
            ok = 4 * (sp_entry[ka, 1] - 1)
            if shared:
                p00 = splat(sp_P[ka, 0])
                p01 = splat(sp_P[ka, 1])
                p10 = splat(sp_P[ka, 2])
                p11 = splat(sp_P[ka, 3])
            else:
                p00 = vset(sp_P[ka, 0], sp_P[kb, 0], sp_P[kc, 0], sp_P[kd, 0])
                p01 = vset(sp_P[ka, 1], sp_P[kb, 1], sp_P[kc, 1], sp_P[kd, 1])
                p10 = vset(sp_P[ka, 2], sp_P[kb, 2], sp_P[kc, 2], sp_P[kd, 2])
                p11 = vset(sp_P[ka, 3], sp_P[kb, 3], sp_P[kc, 3], sp_P[kd, 3])
            v11, v12, v22, gj0, gj1, gj2, gk0, gk1, gk2 = _spoke_face(
                vload(sc, r0 + oj), vload(sc, r0 + W + oj), vload(sc, r0 + 2 * W + oj),
                vload(sc, r0 + ok), vload(sc, r0 + W + ok), vload(sc, r0 + 2 * W + ok),
                p00, p01, p10, p11, A, cs11, cs12, cs22)
            e11 = e11 + v11
            e12 = e12 + v12
            e22 = e22 + v22
            oj += t0 + 4
            ok += t0 + 4
            _vadd(sc, oj, gj0)
            _vadd(sc, oj + W, gj1)
            _vadd(sc, oj + 2 * W, gj2)
            _vadd(sc, ok, gk0)
            _vadd(sc, ok + W, gk1)
            _vadd(sc, ok + 2 * W, gk2)
            _vadd(sc, t0, -(gj0 + gk0))
            _vadd(sc, t0 + W, -(gj1 + gk1))
            _vadd(sc, t0 + 2 * W, -(gj2 + gk2))
    else:
        scf = sc.reshape(sc.size)
        nb_ = nb.uint64(vf_ptr[i1 + nb.uint64(1)]) - qb
        nc = nb.uint64(vf_ptr[i2 + nb.uint64(1)]) - qc
        nd = nb.uint64(vf_ptr[i3 + nb.uint64(1)]) - qd
        for f in range(max(max(na, nb_), max(nc, nd))):
            ka = qa + min(f, na - nb.uint64(1))
            kb = qb + min(f, nb_ - nb.uint64(1))
            kc = qc + min(f, nc - nb.uint64(1))
            kd = qd + min(f, nd - nb.uint64(1))
            mask = vset(1.0 if f < na else 0.0, 1.0 if f < nb_ else 0.0,
                        1.0 if f < nc else 0.0, 1.0 if f < nd else 0.0)
            sj0, sj1, sj2 = _spoke_lanes(sc, r0, sp_entry[ka, 0], sp_entry[kb, 0],
                                         sp_entry[kc, 0], sp_entry[kd, 0])
            sk0, sk1, sk2 = _spoke_lanes(sc, r0, sp_entry[ka, 1], sp_entry[kb, 1],
                                         sp_entry[kc, 1], sp_entry[kd, 1])
            v11, v12, v22, gj0, gj1, gj2, gk0, gk1, gk2 = _spoke_face(
                sj0, sj1, sj2, sk0, sk1, sk2,
                vset(sp_P[ka, 0], sp_P[kb, 0], sp_P[kc, 0], sp_P[kd, 0]),
                vset(sp_P[ka, 1], sp_P[kb, 1], sp_P[kc, 1], sp_P[kd, 1]),
                vset(sp_P[ka, 2], sp_P[kb, 2], sp_P[kc, 2], sp_P[kd, 2]),
                vset(sp_P[ka, 3], sp_P[kb, 3], sp_P[kc, 3], sp_P[kd, 3]),
                A * mask, cs11, cs12, cs22)
            e11 = e11 + mask * v11
            e12 = e12 + mask * v12
            e22 = e22 + mask * v22
            _vadd(sc, t0, -(gj0 + gk0))
            _vadd(sc, t0 + W, -(gj1 + gk1))
            _vadd(sc, t0 + 2 * W, -(gj2 + gk2))
            for ln in range(4):
                k = ka if ln == 0 else (kb if ln == 1 else (kc if ln == 2 else kd))
                oj = nb.uint64(t0 + 4 * sp_entry[k, 0] + ln)
                ok = nb.uint64(t0 + 4 * sp_entry[k, 1] + ln)
                scf[oj] += lane(gj0, ln)
                scf[oj + W] += lane(gj1, ln)
                scf[oj + 2 * W] += lane(gj2, ln)
                scf[ok] += lane(gk0, ln)
                scf[ok + W] += lane(gk1, ln)
                scf[ok + 2 * W] += lane(gk2, ln)
    return (0.5 * e11 - vset(sp_ebar0[i0, 0], sp_ebar0[i1, 0], sp_ebar0[i2, 0],
                             sp_ebar0[i3, 0]),
            0.5 * e12 - vset(sp_ebar0[i0, 1], sp_ebar0[i1, 1], sp_ebar0[i2, 1],
                             sp_ebar0[i3, 1]),
            0.5 * e22 - vset(sp_ebar0[i0, 2], sp_ebar0[i1, 2], sp_ebar0[i2, 2],
                             sp_ebar0[i3, 2]))


@kernel(inline='always')
def vertex_lanes(g, x, g_vert, g_ptr, g_wptr, st_idx, st_w, st_uv, st_sigma, stab, dual_area,
                 ainv, rest_b, xi, phi, sc, ch, contrib, vf_ptr, sp_P, sp_entry, sp_ebar0,
                 coupled):
    """:func:`..core.terms.jet.jet_adjoint` for the four vertices of lane group g at once,
    one per SIMD lane (:mod:`.simd`), with the coupling: the same formulas, each operation
    on the four vertices in one vector; the coupling's strain average and strain side from
    the stencil offsets of pass 1 (:func:`spokes`, :func:`_coupling_group`). ``coupled``
    (a literal at every call: ``fast/step.py`` compiles a step for phi = 0 and one for
    phi != 0) keeps the coupling's code out of the step without it, which otherwise
    slows the vertex pass even with the coupling skipped at run time.

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
    # scratch rows d_0, d_1, d_2, dn, h of this chunk (flat offsets), then (coupled) the
    # three coordinates of the coupling's strain side per entry (the centre first)
    r0 = ch * sc.shape[1] * W
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
    n0, n1, n2, isn, gam = floored_normal(c0, c1, c2, vsqrt(c0 * c0 + c1 * c1 + c2 * c2))
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
    if coupled:     # M += Theta epsbar, and the strain side into scratch rows 5-7
        zero = splat(0.0)
        for s in range(ns + 1):
            vstore(sc, r0 + 5 * W + 4 * s, zero)
            vstore(sc, r0 + 6 * W + 4 * s, zero)
            vstore(sc, r0 + 7 * W + 4 * s, zero)
        cs11, cs12, cs22 = contract(phi, i11, i12, i22, k11, k12, k22)
        ev11, ev12, ev22 = _coupling_group(
            i0, i1, i2, i3, g_wptr[g, 4], vf_ptr, sp_P, sp_entry, sp_ebar0,
            vset(dual_area[i0], dual_area[i1], dual_area[i2], dual_area[i3]), cs11, cs12,
            cs22, sc, r0, W)
        s11, s12, s22 = contract(phi, i11, i12, i22, ev11, ev12, ev22)
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
    # from core/terms/jet.py), and LLVM drops it in the end. It stays because with it in
    # the loop LLVM schedules the loop into faster code than without it (paired A/B,
    # docs/performance.md).
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
    vn = (v0 * n0 + v1 * n1 + v2 * n2) * gam
    t0 = (v0 - vn * n0) * isn
    t1 = (v1 - vn * n1) * isn
    t2 = (v2 - vn * n2) * isn
    j10, j11, j12 = cross(a20, a21, a22, t0, t1, t2)
    j20, j21, j22 = cross(t0, t1, t2, a10, a11, a12)
    # pass 4: dE_i/dx_j per stencil entry; the centre takes minus their sum (coupled:
    # plus the strain side of scratch rows 5-7)
    for s in range(ns):
        k = p0 + 4 * s
        kw = q0 + 4 * s
        h = vload(sc, r0 + 4 * W + 4 * s)
        w0 = vload(st_w, kw)
        w1 = vload(st_w, KW + kw)
        if coupled:
            e = r0 + 5 * W + 4 * (s + 1)
            vstore(contrib, k, w0 * j10 + w1 * j20 + h * n0 + vload(sc, e))
            vstore(contrib, K + k, w0 * j11 + w1 * j21 + h * n1 + vload(sc, e + W))
            vstore(contrib, 2 * K + k, w0 * j12 + w1 * j22 + h * n2 + vload(sc, e + 2 * W))
        else:
            vstore(contrib, k, w0 * j10 + w1 * j20 + h * n0)
            vstore(contrib, K + k, w0 * j11 + w1 * j21 + h * n1)
            vstore(contrib, 2 * K + k, w0 * j12 + w1 * j22 + h * n2)
    c0w = vload(st_w, bw)
    c1w = vload(st_w, KW + bw)
    if coupled:
        e = r0 + 5 * W
        vstore(contrib, b, c0w * j10 + c1w * j20 - hs * n0 + vload(sc, e))
        vstore(contrib, K + b, c0w * j11 + c1w * j21 - hs * n1 + vload(sc, e + W))
        vstore(contrib, 2 * K + b, c0w * j12 + c1w * j22 - hs * n2 + vload(sc, e + 2 * W))
    else:
        vstore(contrib, b, c0w * j10 + c1w * j20 - hs * n0)
        vstore(contrib, K + b, c0w * j11 + c1w * j21 - hs * n1)
        vstore(contrib, 2 * K + b, c0w * j12 + c1w * j22 - hs * n2)


@kernel(refcount=False, forceinline=True)
def vertex_chunk(ch, nch, row, x, g_vert, g_ptr, g_wptr, s_vert, s_ptr, s_wptr, st_idx, st_w,
                 st_uv, st_sigma, sp_P, sp_entry, sp_ebar0, stab, dual_area, ainv, rest_b, xi,
                 phi, scratch, contrib, corners, dinv, face_area, K_face, vf_ptr, vf_face,
                 vf_corner, vf_entry, vf_K, fc_vert, t_dinv, t_area, zeta, fc_ptr, fc_tpl,
                 fc_slot, fgrad, coupled):
    """Work item (chunk) ``ch`` of the vertex pass (``fast/step.py``): the membrane of the
    chunk's faces, then the jet terms of its lane groups (:func:`vertex_lanes`) and of its
    single vertices (stencil sizes that do not fill a group: the scalar
    ``jet_adjoint`` and ``add_face_side``), writing the stencil gradients ``contrib``
    (3,K) in the lane layout of :func:`lane_layout`; ``nch`` chunks split the mesh
    (:func:`chunk_of_vertex`); ``scratch[row]`` (8, S) is this work item's alone while it
    runs (no allocation, no shared writes).

    The faces q = ``fc_ptr[ch]:fc_ptr[ch + 1]`` (``core.terms.membrane.face_membrane``)
    come in chunk order, streamed front to back: their corners ``fc_vert[q]`` (uint32),
    their rest shapes as rows ``fc_tpl[q]`` of a table of the distinct (Dinv, area) pairs
    (``t_dinv``, ``t_area``; a structured sheet has a few dozen) and the rows
    ``fc_slot[q]`` of fgrad their corner gradients go to (the face itself, or a ring slot
    in the tiled step). With ``coupled`` the lane groups run the coupling from their
    spokes (:func:`vertex_lanes`), the single vertices from their faces (``corners``,
    ``dinv``, ``face_area``, ``K_face`` and the vertex-face arrays).

    ``forceinline`` (LLVM ``alwaysinline``): inlined into the parallel loop's body, it
    gets that body's ``noalias`` arrays (a plain call is slower). ``coupled`` is
    made a literal (``numba.literally``): each value compiles a function of its own,
    optimised without the other's code (one function with a run-time flag is slower at
    phi = 0). The arrays come one by one, not in their named tuples: tuples carried into
    the parallel loop's body add a fixed cost to every pass (docs/performance.md).
    """
    literally(coupled)
    # the chunk sizes follow from the caller's nch (not from a module constant, which
    # numba's cache would freeze into the compiled code); chunk_of_vertex is this split in
    # numpy. (Spreading the groups and singles evenly over the chunks was slower: the few
    # singles then leave the first chunks, i.e. the calling thread, which starts before
    # the woken worker.)
    ng = g_vert.shape[0]
    nsv = s_vert.shape[0]
    for q in range(nb.uint64(fc_ptr[ch]), nb.uint64(fc_ptr[ch + 1])):
        face_membrane(q, nb.uint64(fc_tpl[q]), nb.uint64(fc_slot[q]), x, fc_vert, t_dinv,
                      t_area, zeta, fgrad)
    gchunk = (ng + nch - 1) // nch
    for g in range(ch * gchunk, min(ng, (ch + 1) * gchunk)):
        vertex_lanes(g, x, g_vert, g_ptr, g_wptr, st_idx, st_w, st_uv, st_sigma, stab,
                     dual_area, ainv, rest_b, xi, phi, scratch, row, contrib, vf_ptr, sp_P,
                     sp_entry, sp_ebar0, coupled)
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
                st_sigma: np.ndarray, lanes: int = LANES, fan: np.ndarray = None):
    """Order of the stencil entries, and blocks of the weights and of the entries' own
    data, for the vertex pass (:func:`vertex_chunk`).

    Entries (the gradients the pass writes, contrib): the vertices left over from the
    groups below (fewer than ``lanes`` of a stencil size; ``lanes = 1`` puts every vertex
    here) come first, as plain CSR blocks ``s_ptr[u] : s_ptr[u + 1]``. Then the vertices
    with the same stencil size form groups of ``lanes`` (sorted, within a size, by windows
    of :data:`FAN_WINDOW` vertices for those whose stencil template is their own, then
    ``fan``, the 1-ring's shape if given, then stencil template, then vertex; groups in
    the order of their first vertex); a group's entries
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
    # within a size: vertices with a stencil template of their own (an irregular mesh) in
    # windows of FAN_WINDOW consecutive vertices, so that the groups stay local (their
    # chunks, tiles and gathers touch nearby vertices); then fan, template, vertex
    alone = np.bincount(template, minlength=n)[template] == 1
    window = np.where(alone, np.arange(n) // FAN_WINDOW, -1)
    order = np.lexsort((np.arange(n), template, np.zeros(n, np.int64) if fan is None else fan,
                        window, sizes))
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


