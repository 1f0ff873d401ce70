"""The per-vertex jet energy and its exact adjoint, shared by bending and coupling.

Both vertex terms depend on the positions through the cubic least-squares jet of
:mod:`..geometry` (weights ``W`` over the stencil of vertex i, its 2-ring or more):

    a_a  = sum_k W_k,a d_k,          n = a_1 x a_2 / s(|a_1 x a_2|)     (Eq. 8, 13)
    b_ab = sum_k W_k,ab dn_k,        dn_k = d_k . n                      (Eq. 10, 11)
    kap  = -(b - B)                                                      (Eq. 17)

with the offsets ``d_k = x_j - x_i`` of the stencil entries. A vertex energy
``E_i(kap, ...)`` with moment ``M = dW/dkap`` (Eq. 22: ``M = 2 Psi kap + Theta epsbar``;
bending gives the first part, coupling the second) has, with ``h_k = dE_i/d(dn_k)`` and
``g_ab = dE_i/db_ab = -A_i (M^ab + M^ba)/(1 + [a == b])``,

    dE_i/dd_k = h_k n + W_k,1 (a_2 x t) + W_k,2 (t x a_1),
    t = (I - gam n n^T) sum_k h_k d_k / s

since ``n`` depends on the positions through ``a_1, a_2`` only (``c = a_1 x a_2``,
``r = |c|``: ``dn = (I - gam n n^T) dc / s``). The centre takes minus the
sum of the others. Four passes over the stencil per vertex (:func:`jet_adjoint`); the
adjoint is the transpose of the discrete derivative operators, a discrete divergence,
gathered per vertex through the transposed stencil (:func:`gather`).

The normal's length (:func:`floored_normal`): ``s(r) = r`` (a unit normal, Eq. 13, and
``gam = 1``) while the area ratio ``r`` is at least ``f = constants.JET_AREA_FLOOR`` (at rest
r = 1: the chart is orthonormal), and ``s(r) = (r^2 + f^2) / (2 f)`` below it, C1 at f. With
``u = min(r, f)``: ``s = r + (f - u)^2 / (2 f)``, ``s' = u / f`` and ``gam = r s' s / r^2 =
u s / (f r)``. A stencil crumpled inside itself (a pinch, a fold across it) can make the
fitted tangents parallel while every edge keeps its length; a unit normal's derivative
grows as 1/r there and the explicit step blows up. Below the floor the normal shortens
instead, so the curvature ``b = n . r_ab`` the jet reports fades where the fit no longer
sees a surface, and ``1/s <= 2/f``.

Hourglass control (part of the bending term, ``constants.JET_STABILIZATION``): a
least-squares fit cannot see some oscillating patterns, so the energy adds
``om_i sum_k (rho_k . n - sigma_k)^2`` with ``rho_k . n = dn_k - phi_k . q`` the fit's
residual along the normal at entry k (``q_c = sum_k W_k,c dn_k``, ``phi_k`` the design row)
and ``sigma_k`` its rest value; ``om_i = s xi A_i / h_i^4 / S_i``. It is rotation
invariant, zero at rest and O(h^4) on smooth fields. The residual is orthogonal to the
design columns (uniform fit weights), so it needs no jet adjoint of its own: its
gradient joins ``h_k``.

Stencil layout: entry k of a vertex reads its neighbour ``st_idx[k]`` and rest residual
``st_sigma[k]`` at its entry position and its weights ``st_w[:, kw]`` and chart
coordinates ``st_uv[:, kw]`` at its weight position; the centre comes first. The CSR
order of :class:`..geometry.JetOperator` is one such layout; the step's lane layout
(``fast/lanes.py``) is another.
"""
from __future__ import annotations

import numba as nb
import numpy as np

from numba import literally

from ..compiled import REDUCTION, kernel
from ..constants import JET_AREA_FLOOR
from ..material import contract

__all__ = ['jet_adjoint', 'vertex_pass', 'vertex_energies', 'gather', 'normal_residuals',
           'cross', 'floored_normal', 'phi_dot', 'jet_fields', 'jet_energies']


@kernel(inline='always')
def cross(a0, a1, a2, b0, b1, b2):
    """a x b for vectors given by components (scalars or SIMD vectors)."""
    return a1 * b2 - a2 * b1, a2 * b0 - a0 * b2, a0 * b1 - a1 * b0


@kernel(inline='always')
def floored_normal(c0, c1, c2, cn):
    """The jet's normal ``c / s(r)`` from ``c = a_1 x a_2`` and ``r = |c|`` = ``cn`` (scalars
    or SIMD vectors; module docstring): (n0, n1, n2, 1/s, gam). Where ``r >= f`` this is
    ``c / r`` with ``gam = 1``, bit for bit. ``gam = r s / (f r) = s / max(r, f)``, written
    so: ``r / r`` would be 0 / 0 at ``r = 0`` (tangents parallel, a stencil pinched to a
    line), where the limit is 1/2 (``max`` from ``min``: the SIMD vectors have only that)."""
    f = JET_AREA_FLOOR
    u = min(cn, f)
    s = cn + (f - u) * (f - u) * (0.5 / f)
    isn = 1.0 / s
    gam = s / (cn + (f - u))
    return c0 * isn, c1 * isn, c2 * isn, isn, gam


@kernel(inline='always')
def stencil_normal(x, st_idx, st_w, p0, p1):
    """Vertex i's floored normal (:func:`floored_normal`) from its stencil entries p0..p1
    (``st_idx``, the weights ``st_w`` of its jet's first derivatives): the tangents
    ``a_alpha = sum_k w_alpha,k x_k`` (Eq. 8) and ``c = a_1 x a_2``. For the Hessian
    blocks' kernels (``bending``, ``coupling``); the vertex pass has its own, written for
    the vectoriser."""
    a10 = 0.0
    a11 = 0.0
    a12 = 0.0
    a20 = 0.0
    a21 = 0.0
    a22 = 0.0
    for k in range(p0, p1):
        j = st_idx[k]
        a10 += st_w[0, k] * x[j, 0]
        a11 += st_w[0, k] * x[j, 1]
        a12 += st_w[0, k] * x[j, 2]
        a20 += st_w[1, k] * x[j, 0]
        a21 += st_w[1, k] * x[j, 1]
        a22 += st_w[1, k] * x[j, 2]
    c0, c1, c2 = cross(a10, a11, a12, a20, a21, a22)
    n0, n1, n2, _, _ = floored_normal(c0, c1, c2, np.sqrt(c0 * c0 + c1 * c1 + c2 * c2))
    return n0, n1, n2


@kernel(inline='always')
def phi_dot(u, v, q0, q1, q2, q3, q4, q5, q6, q7, q8):
    """phi(u, v) . q for the cubic design row phi = (u, v, u^2/2, uv, v^2/2, u^3/6, u^2 v/2,
    u v^2/2, v^3/6) (geometry.design_matrix), in Horner form."""
    return (u * (q0 + u * (0.5 * q2 + u * (q5 / 6.0) + v * (0.5 * q6)) + v * (q3 + v * (0.5 * q7)))
            + v * (q1 + v * (0.5 * q4 + v * (q8 / 6.0))))


# Two stencil sums of the vertex pass. They are functions of their own, compiled with
# ``reassoc`` (compiled.REDUCTION) and not inlined by numba, so that their sums over the
# stencil run as SIMD vectors while the rest of the step keeps the strict order.

@kernel(refcount=False, fastmath=REDUCTION)
def normal_jet(ns, p0, st_w, scratch, ch, n0, n1, n2):
    """DN_k = d_k . n and q_c = sum_k W_kc DN_k for c = r_11 ... r_222 (Eq. 11)."""
    p0 = max(p0, 0)
    q2 = 0.0
    q3 = 0.0
    q4 = 0.0
    q5 = 0.0
    q6 = 0.0
    q7 = 0.0
    q8 = 0.0
    for s in range(ns):
        dn = scratch[ch, 0, s] * n0 + scratch[ch, 1, s] * n1 + scratch[ch, 2, s] * n2
        scratch[ch, 3, s] = dn
        k = p0 + s
        q2 += st_w[2, k] * dn
        q3 += st_w[3, k] * dn
        q4 += st_w[4, k] * dn
        q5 += st_w[5, k] * dn
        q6 += st_w[6, k] * dn
        q7 += st_w[7, k] * dn
        q8 += st_w[8, k] * dn
    return q2, q3, q4, q5, q6, q7, q8


@kernel(refcount=False, fastmath=REDUCTION)
def weighted_offsets(ns, scratch, ch):
    """V = sum_k h_k d_k and sum_k h_k."""
    v0 = 0.0
    v1 = 0.0
    v2 = 0.0
    hs = 0.0
    for s in range(ns):
        h = scratch[ch, 4, s]
        v0 += h * scratch[ch, 0, s]
        v1 += h * scratch[ch, 1, s]
        v2 += h * scratch[ch, 2, s]
        hs += h
    return v0, v1, v2, hs


@kernel(inline='always')
def jet_adjoint(i, pc, p1, pw, x, st_idx, st_w, st_uv, st_sigma, stab, dual_area, ainv, rest_b,
                xi, phi, e11, e12, e22, sc, ch, contrib, adjoint=True):
    """Vertex i's jet energy and its adjoint (module docstring): bending
    ``A_i xi B(kap, kap)`` with its hourglass control ``stab[i] sum_k (rho_k . n - sigma_k)^2``,
    and the curvature side of the coupling ``A_i phi B(epsbar, kap)`` for the strain average
    ``(e11, e12, e22)`` given by the caller (coupling.py; zero and phi = 0 without it).

    Entries: the centre at ``pc`` (its weights at ``pw``), the others at ``pc+1 .. p1-1``
    (weights from ``pw+1``). Writes ``contrib[:, k] = dE_i/dx_j`` for every entry (3, K);
    ``sc[ch]`` (5, S) is the caller's scratch row. Returns the curvature change
    ``(k11, k12, k22)`` and the hourglass energy ``estab``; ``adjoint`` False (a
    constant at the call) stops after them, for the energy alone.

    Written for the vectoriser: no array views inside the parallel loop (numba then marks
    the kernel's arrays ``noalias`` and LLVM vectorises the contiguous loops without
    run-time overlap checks), the stencil offset clamped to ``p0 >= 0`` and the gathered
    index unsigned (so no negative-index wrap-around turns contiguous loads into gathers),
    and the two stencil sums in :data:`compiled.REDUCTION` helpers. The gather of x
    stays scalar (vector gathers are slower here)."""
    p0 = max(pc + 1, 0)
    ns = p1 - p0
    q0 = max(pw + 1, 0)     # the weights and chart coordinates of entry p0 + s: q0 + s
    xi0 = x[i, 0]
    xi1 = x[i, 1]
    xi2 = x[i, 2]
    # pass 1: offsets d_k (an indexed gather, kept scalar) and the tangents a_1, a_2 (Eq. 8)
    a10 = 0.0
    a11 = 0.0
    a12 = 0.0
    a20 = 0.0
    a21 = 0.0
    a22 = 0.0
    for s in range(ns):
        k = p0 + s
        j = nb.uint64(st_idx[k])
        d0 = x[j, 0] - xi0
        d1 = x[j, 1] - xi1
        d2 = x[j, 2] - xi2
        sc[ch, 0, s] = d0
        sc[ch, 1, s] = d1
        sc[ch, 2, s] = d2
        a10 += st_w[0, q0 + s] * d0
        a11 += st_w[0, q0 + s] * d1
        a12 += st_w[0, q0 + s] * d2
        a20 += st_w[1, q0 + s] * d0
        a21 += st_w[1, q0 + s] * d1
        a22 += st_w[1, q0 + s] * d2
    c0, c1, c2 = cross(a10, a11, a12, a20, a21, a22)
    n0, n1, n2, isn, gam = floored_normal(c0, c1, c2, np.sqrt(c0 * c0 + c1 * c1 + c2 * c2))
    # pass 2: dn_k and the jet along the normal, q_c = coef_c . n; b_ab = q for r_ab
    # (Eq. 11). q_1 = a_1 . n and q_2 = a_2 . n vanish.
    q2, q3, q4, q5, q6, q7, q8 = normal_jet(ns, q0, st_w, sc, ch, n0, n1, n2)
    k11 = -(q2 - rest_b[i, 0])
    k12 = -(q3 - rest_b[i, 1])
    k22 = -(q4 - rest_b[i, 2])
    i11 = ainv[i, 0]
    i12 = ainv[i, 1]
    i22 = ainv[i, 2]
    # M = 2 Psi kap + Theta epsbar (Eq. 22)
    m11, m12, m22 = contract(2.0 * xi, i11, i12, i22, k11, k12, k22)
    s11, s12, s22 = contract(phi, i11, i12, i22, e11, e12, e22)
    m11 += s11
    m12 += s12
    m22 += s22
    A = dual_area[i]
    # g_ab = dE_i/db_ab (r_12 enters twice)
    g11 = -A * m11
    g12 = -2.0 * A * m12
    g22 = -A * m22
    # pass 3: residuals along the normal rho_k . n = dn_k - phi_k . q (the design row from
    # the chart coordinates) and h_k = dE_i/d(dn_k)
    om = stab[i]            # c_i omega, omega = 1 / (stencil size)
    e = 0.0
    for s in range(ns):
        kw = q0 + s
        dd = (sc[ch, 3, s] - st_sigma[p0 + s]
              - phi_dot(st_uv[0, kw], st_uv[1, kw], 0.0, 0.0, q2, q3, q4, q5, q6, q7, q8))
        sc[ch, 4, s] = (2.0 * om * dd + st_w[2, kw] * g11 + st_w[3, kw] * g12
                        + st_w[4, kw] * g22)
        e += dd * dd
    if not adjoint:
        return k11, k12, k22, om * e
    v0, v1, v2, hs = weighted_offsets(ns, sc, ch)
    # V = sum_k h_k d_k, and V . dn with dn = (I - gam n n^T) (da_1 x a_2 + a_1 x da_2) / s
    vn = (v0 * n0 + v1 * n1 + v2 * n2) * gam
    t0 = (v0 - vn * n0) * isn
    t1 = (v1 - vn * n1) * isn
    t2 = (v2 - vn * n2) * isn
    j10, j11, j12 = cross(a20, a21, a22, t0, t1, t2)
    j20, j21, j22 = cross(t0, t1, t2, a10, a11, a12)
    # pass 4: dE_i/dx_j per stencil entry (elementwise: it vectorises). The centre takes
    # minus their sum; the weights of a_1, a_2 sum to minus the centre's weight.
    for s in range(ns):
        k = p0 + s
        h = sc[ch, 4, s]
        w0 = st_w[0, q0 + s]
        w1 = st_w[1, q0 + s]
        contrib[0, k] = w0 * j10 + w1 * j20 + h * n0
        contrib[1, k] = w0 * j11 + w1 * j21 + h * n1
        contrib[2, k] = w0 * j12 + w1 * j22 + h * n2
    c0w = st_w[0, q0 - 1]
    c1w = st_w[1, q0 - 1]
    contrib[0, p0 - 1] = c0w * j10 + c1w * j20 - hs * n0
    contrib[1, p0 - 1] = c0w * j11 + c1w * j21 - hs * n1
    contrib[2, p0 - 1] = c0w * j12 + c1w * j22 - hs * n2
    return k11, k12, k22, om * e


@kernel(refcount=False)
def vertex_range(i0, i1, st_ptr, st_wptr, x, st_idx, st_w, st_uv, st_sigma, stab, dual_area,
                 ainv, rest_b, xi, phi, epsbar, sc, ch, contrib, kap, estab, adjoint):
    """:func:`jet_adjoint` for the vertices i0:i1 with scratch row ``ch`` (CSR layout,
    weights per stencil template at ``st_wptr[i]``), storing kap (n,3) and estab (n,). A
    function of its own, called once per work item of :func:`vertex_pass`: numba's
    parallel passes then see a call instead of the inlined vertex term (a shorter cold
    compile). ``adjoint`` (a literal: one function each) False computes kap and estab
    alone."""
    literally(adjoint)
    for i in range(i0, i1):
        k11, k12, k22, es = jet_adjoint(
            i, st_ptr[i], st_ptr[i + 1], st_wptr[i], x, st_idx, st_w, st_uv, st_sigma, stab,
            dual_area, ainv, rest_b, xi, phi, epsbar[i, 0], epsbar[i, 1], epsbar[i, 2], sc, ch,
            contrib, adjoint)
        kap[i, 0] = k11
        kap[i, 1] = k12
        kap[i, 2] = k22
        estab[i] = es


@kernel(inline='always')
def _vertex_pass(x, jets, vertices, stab, xi, phi, epsbar, scratch, contrib, kap, estab,
                 adjoint):
    """:func:`vertex_range` over the work items of ``scratch`` in parallel (``adjoint``: a
    literal; :func:`vertex_pass`, :func:`vertex_energies`)."""
    st_ptr, st_wptr, st_idx, st_w, st_uv, st_sigma = (jets.ptr, jets.wptr, jets.idx, jets.tw,
                                                      jets.tuv, jets.sigma)
    dual_area, ainv, rest_b = vertices.dual_area, vertices.ainv, vertices.rest_b
    n = x.shape[0]
    nch = scratch.shape[0]
    chunk = (n + nch - 1) // nch
    for c in nb.prange(nch):
        vertex_range(np.int64(c) * chunk, min(n, (np.int64(c) + 1) * chunk), st_ptr, st_wptr, x,
                     st_idx, st_w, st_uv, st_sigma, stab, dual_area, ainv, rest_b, xi, phi,
                     epsbar, scratch, np.int64(c), contrib, kap, estab, adjoint)


@kernel(parallel=True)
def vertex_pass(x, jets, vertices, stab, xi, phi, epsbar, scratch, contrib, kap, estab):
    """:func:`jet_adjoint` for every vertex on the CSR stencils of ``jets``
    (:class:`..model.Jets`), in work items of its ``scratch`` (R, 5, S) rows: contrib (3,K)
    in CSR order, kap (n,3), estab (n,). ``epsbar`` (n,3) is read only when phi != 0."""
    _vertex_pass(x, jets, vertices, stab, xi, phi, epsbar, scratch, contrib, kap, estab, True)


@kernel(parallel=True)
def vertex_energies(x, jets, vertices, stab, xi, phi, epsbar, scratch, kap, estab):
    """:func:`vertex_pass` without the adjoint: kap (n,3) and estab (n,) alone, for the
    energy (``contrib`` is not written: scratch stands in for it)."""
    _vertex_pass(x, jets, vertices, stab, xi, phi, epsbar, scratch, scratch[0], kap, estab,
                 False)


@kernel(parallel=True)
def gather(tr_ptr, tr_slot, contrib, grad):
    """grad[j] += sum of the stencil gradients ``contrib[:, tr_slot[q]]`` of every entry
    q of j's transposed stencil (every vertex whose jet uses x_j)."""
    for j in nb.prange(grad.shape[0]):
        g0 = 0.0
        g1 = 0.0
        g2 = 0.0
        for q in range(tr_ptr[j], tr_ptr[j + 1]):
            k = tr_slot[q]
            g0 += contrib[0, k]
            g1 += contrib[1, k]
            g2 += contrib[2, k]
        grad[j, 0] += g0
        grad[j, 1] += g1
        grad[j, 2] += g2


@kernel(parallel=True)
def normal_residuals(x, st_ptr, st_idx, st_w, st_uv, out):
    """out[k] = rho_k . n_i for every stencil entry (the sigma_k of the rest state), with
    the arithmetic of the vertex pass."""
    n = x.shape[0]
    nc = st_w.shape[0]
    for i in nb.prange(n):
        jt = np.zeros((nc, 3))
        for k in range(st_ptr[i], st_ptr[i + 1]):
            j = st_idx[k]
            for c in range(nc):
                jt[c, 0] += st_w[c, k] * x[j, 0]
                jt[c, 1] += st_w[c, k] * x[j, 1]
                jt[c, 2] += st_w[c, k] * x[j, 2]
        c0, c1, c2 = cross(jt[0, 0], jt[0, 1], jt[0, 2], jt[1, 0], jt[1, 1], jt[1, 2])
        n0, n1, n2, _, _ = floored_normal(c0, c1, c2, np.sqrt(c0 * c0 + c1 * c1 + c2 * c2))
        q = np.zeros(nc)
        for c in range(nc):
            q[c] = jt[c, 0] * n0 + jt[c, 1] * n1 + jt[c, 2] * n2
        out[st_ptr[i]] = 0.0
        for k in range(st_ptr[i] + 1, st_ptr[i + 1]):
            j = st_idx[k]
            dn = (x[j, 0] - x[i, 0]) * n0 + (x[j, 1] - x[i, 1]) * n1 + (x[j, 2] - x[i, 2]) * n2
            out[k] = dn - phi_dot(st_uv[0, k], st_uv[1, k], q[0], q[1], q[2], q[3], q[4],
                                  q[5], q[6], q[7], q[8])


def jet_fields(model, x: np.ndarray, xi: float, phi: float, stab: np.ndarray,
               epsbar: np.ndarray):
    """Run :func:`vertex_pass` on fresh arrays: (contrib (3,K), kap (n,3), estab (n,))."""
    j = model.jets
    n = len(x)
    contrib = np.zeros((3, len(j.idx)))
    kap = np.zeros((n, 3))
    estab = np.zeros(n)
    vertex_pass(np.ascontiguousarray(x, dtype=np.float64), j, model.vertices, stab, xi, phi,
                epsbar, model_scratch(model), contrib, kap, estab)
    return contrib, kap, estab


def jet_energies(model, x: np.ndarray, xi: float, phi: float, stab: np.ndarray,
                 epsbar: np.ndarray):
    """Run :func:`vertex_energies` on fresh arrays: (kap (n,3), estab (n,))."""
    n = len(x)
    kap = np.zeros((n, 3))
    estab = np.zeros(n)
    vertex_energies(np.ascontiguousarray(x, dtype=np.float64), model.jets, model.vertices,
                    stab, xi, phi, epsbar, model_scratch(model), kap, estab)
    return kap, estab


def model_scratch(model, rows: int = 0) -> np.ndarray:
    """Scratch rows (R, 5, S) for :func:`vertex_pass`: S the largest stencil, padded by a
    cache line so that rows in use by two threads never share one."""
    smax = -(-int(np.diff(model.jets.ptr).max()) // 8) * 8 + 8
    nch = rows or max(1, -(-len(model.jets.ptr) // 16))
    return np.zeros((nch, 5, smax))
