"""Internal forces N^a|_a of the Cosserat surface (Eq. 20, 24-28) and the discrete energy.

Discrete energy (``"variational"``)
----------------------------------
``E = sum_t area_t W_m(eps_t) + sum_i A_i [xi B(kap_i, kap_i) + phi B(epsbar_i, kap_i)]``

* membrane, per triangle (constant-strain triangle, so no hourglass mode): the deformation
  gradient ``F_t = [x1 - x0, x2 - x0] Dinv_t`` in the triangle's orthonormal rest chart,
  ``eps_t = (F_t^T F_t - I) / 2`` (Eq. 17), ``W_m = zeta B(eps_t, eps_t)`` with A = I;
* bending, per vertex from the cubic jet of :mod:`.geometry`: ``kap_i = -(b_i - B_i)``;
* coupling, per vertex: ``epsbar_i`` is the dual-area average of the incident triangles'
  strain carried to the vertex chart, ``epsbar_i = sum_t (area_t / 3 A_i) K_it^T eps_t K_it``
  where ``K_it = D_t U_it^-1`` maps the vertex chart onto the triangle chart (``U_it`` are
  the triangle's rest edges projected on the vertex's rest tangent plane).

The force is ``-dE/dx`` exactly. Every estimator is linear in the positions, so the chain
rule through them is the adjoint (transpose) of the discrete derivative operators: a
discrete divergence, gathered per vertex through the transposed stencils. With
``N*_t = 2 Phi eps_t`` (Eq. 22) and ``M_i = 2 Psi kap_i + Theta epsbar_i``:

    dE/dx_j = sum_{t ni j} [F_t S_t Dinv_t^T]_corner + sum_{i: j in stencil(i)} dE_i/dx_j

with the triangle "stress times area"
``S_t = area_t N*_t + sum_{i in t} area_t/3 K Theta kap_i K^T``.
The vertex term depends on the stencil offsets ``d_k = x_j - x_i`` only through the normal
components ``dn_k = d_k . n`` (``b_ab = sum_k W_k,ab dn_k``) and the normal
``n = a_1 x a_2 / |a_1 x a_2|`` (``a_a = sum_k W_k,a d_k``), so with
``h_k = dE_i/d(dn_k)`` and ``g_ab = dE_i/db_ab = -A_i (M^ab + M^ba)/(1 + [a == b])``:

    dE_i/dd_k = h_k n + W_k,1 (a_2 x t) + W_k,2 (t x a_1),
    t = (I - n n^T) sum_k h_k d_k / |a_1 x a_2|

(see :func:`_vertex`). Four passes over the stencil per vertex and one gather per vertex;
no scatter, no per-coefficient jet stress.
These are the Euler-Lagrange equations Eq. 24-28 in weak form; free edges carry their
natural conditions without special code.

Hourglass control of the jets: a least-squares fit cannot see some oscillating patterns
(they leave the fitted derivatives nearly unchanged), and on irregular meshes the static
plate exploited them (+3% that did not fall with refinement). The energy therefore adds
``s xi A_i / h_i^4 sum_k omega_k (rho_k . n - sigma_k)^2`` per vertex, with ``rho_k`` the fit
residual at stencil entry k and ``sigma_k`` its rest value (constants.JET_STABILIZATION).
It is rotation invariant, zero at rest and O(h^4) for smooth fields, so it vanishes with
refinement; its gradient joins the same adjoint gather.

Seed route (``"covariant"``)
----------------------------
Per vertex, from the jet geometry and vertex strains: ``N*``, ``M`` (Eq. 27 with the factor
2), ``N^ab = N*^ab - M^bg a^ad b_dg`` and ``N^3b = M^ba|_a`` (Eq. 28, covariant derivative
Eq. 15 with least-squares partial derivatives), force vectors ``N^b = N^ab a_a + N^3b a_3``
(Eq. 26), and the nodal force ``A_i N^a|_a = A_i (d_a N^a + Gamma^a_al N^l)`` (Eq. 14).
It needs every boundary vertex pinned (seed Sec. 6.4, 7).
"""
from __future__ import annotations

import numba as nb
import numpy as np

from .compiled import REDUCTION, kernel
from .geometry import _cross
from .material import bilinear, contract
from .simd import LANES, lane, splat, vfma, vload, vload3, vset, vsqrt, vstore

__all__ = ['DIVERGENCE_METHODS']

DIVERGENCE_METHODS = ('variational', 'covariant')


@kernel(inline='always')
def _deformation_gradient(x, faces, dinv, t, td):
    """F_t = [x1 - x0, x2 - x0] Dinv_t (3x2) of face t (corners faces[t], Dinv = dinv[td]:
    td = t, or the face's rest shape in a table of the distinct ones), returned row by
    row (F_00, F_01, F_10, F_11, F_20, F_21). Recomputed where needed rather than stored
    (memory traffic)."""
    i0 = nb.uint64(faces[t, 0])     # unsigned: no negative-index wrap-around per load
    i1 = nb.uint64(faces[t, 1])
    i2 = nb.uint64(faces[t, 2])
    d00 = dinv[td, 0, 0]
    d01 = dinv[td, 0, 1]
    d10 = dinv[td, 1, 0]
    d11 = dinv[td, 1, 1]
    e10 = x[i1, 0] - x[i0, 0]
    e20 = x[i2, 0] - x[i0, 0]
    e11 = x[i1, 1] - x[i0, 1]
    e21 = x[i2, 1] - x[i0, 1]
    e12 = x[i1, 2] - x[i0, 2]
    e22 = x[i2, 2] - x[i0, 2]
    return (e10 * d00 + e20 * d10, e10 * d01 + e20 * d11,
            e11 * d00 + e21 * d10, e11 * d01 + e21 * d11,
            e12 * d00 + e22 * d10, e12 * d01 + e22 * d11)


@kernel(inline='always')
def _corner_gradient_row(td, ts, k, fa, fb, s11, s12, s22, dinv, fgrad, add):
    """Coordinate k (row (fa, fb) of F) of the corner gradients ``[g_1 g_2] = F S Dinv^T``
    of a face with Dinv = dinv[td], into fgrad[ts] (ts = the face, or its ring slot in the
    tiled step); corner 0 takes ``-g_1 - g_2``; written, or added (add)."""
    p0 = fa * s11 + fb * s12
    p1 = fa * s12 + fb * s22
    g1 = p0 * dinv[td, 0, 0] + p1 * dinv[td, 0, 1]
    g2 = p0 * dinv[td, 1, 0] + p1 * dinv[td, 1, 1]
    if add:
        fgrad[ts, 1, k] += g1
        fgrad[ts, 2, k] += g2
        fgrad[ts, 0, k] -= g1 + g2
    else:
        fgrad[ts, 1, k] = g1
        fgrad[ts, 2, k] = g2
        fgrad[ts, 0, k] = -g1 - g2


@kernel(inline='always')
def _corner_gradients(x, faces, dinv, t, s11, s12, s22, fgrad, add):
    """dE/dx at the three corners of face t for the stress-times-area S (face chart):
    ``[g_1 g_2] = F S Dinv^T``, corner 0 takes ``-g_1 - g_2``; written, or added (add)."""
    f00, f01, f10, f11, f20, f21 = _deformation_gradient(x, faces, dinv, t, t)
    _corner_gradient_row(t, t, 0, f00, f01, s11, s12, s22, dinv, fgrad, add)
    _corner_gradient_row(t, t, 1, f10, f11, s11, s12, s22, dinv, fgrad, add)
    _corner_gradient_row(t, t, 2, f20, f21, s11, s12, s22, dinv, fgrad, add)


@kernel(inline='always')
def _face_membrane(t, td, ts, x, faces, dinv, face_area, zeta, eps, fgrad, store_eps):
    """Face t: Green strain eps[t] = (11, 12, 22) of the deformation gradient F (Eq. 17),
    stored if ``store_eps`` (a constant at every call: the step's vertex pass does not
    need it), and the membrane's corner gradients fgrad[ts] (3,3) = d(area W_m)/dx_corner
    (ts = t, or the face's ring slot in the tiled step), with
    ``N* = 2 zeta (tr(eps) I + 2 eps)`` (Eq. 22, A = I in the face chart). The corners are
    faces[t], the rest shape dinv[td] and face_area[td] (td = t, or in the step's vertex
    pass the face's row in the table of distinct rest shapes)."""
    f00, f01, f10, f11, f20, f21 = _deformation_gradient(x, faces, dinv, t, td)
    e11 = 0.5 * (f00 * f00 + f10 * f10 + f20 * f20 - 1.0)
    e12 = 0.5 * (f00 * f01 + f10 * f11 + f20 * f21)
    e22 = 0.5 * (f01 * f01 + f11 * f11 + f21 * f21 - 1.0)
    if store_eps:
        eps[t, 0] = e11
        eps[t, 1] = e12
        eps[t, 2] = e22
    c = face_area[td] * 2.0 * zeta
    tr = e11 + e22
    s11 = c * (tr + 2.0 * e11)
    s12 = c * (2.0 * e12)
    s22 = c * (tr + 2.0 * e22)
    _corner_gradient_row(td, ts, 0, f00, f01, s11, s12, s22, dinv, fgrad, False)
    _corner_gradient_row(td, ts, 1, f10, f11, s11, s12, s22, dinv, fgrad, False)
    _corner_gradient_row(td, ts, 2, f20, f21, s11, s12, s22, dinv, fgrad, False)


@kernel(parallel=True)
def face_membrane(x, faces, dinv, face_area, zeta, eps, fgrad):
    """Per face: strain eps (m,3) and membrane corner gradients fgrad (m,3,3)
    (:func:`_face_membrane`). The step runs this in the vertex pass when phi = 0; with a
    coupling, the vertex pass reads eps, so the faces go first in a pass of their own."""
    for t in nb.prange(faces.shape[0]):
        _face_membrane(t, t, t, x, faces, dinv, face_area, zeta, eps, fgrad, True)


@kernel(inline='always')
def _to_vertex_chart(vf_K, q, e11, e12, e22):
    """K^T e K for the vertex-face entry q (vf_K (nvf,4) holds the 2x2 K row by row)."""
    k00 = vf_K[q, 0]
    k01 = vf_K[q, 1]
    k10 = vf_K[q, 2]
    k11 = vf_K[q, 3]
    # e K
    p00 = e11 * k00 + e12 * k10
    p01 = e11 * k01 + e12 * k11
    p10 = e12 * k00 + e22 * k10
    p11 = e12 * k01 + e22 * k11
    return (k00 * p00 + k10 * p10, k00 * p01 + k10 * p11, k01 * p01 + k11 * p11)


@kernel(inline='always')
def _to_face_chart(K, t, c, s11, s12, s22):
    """K s K^T for the corner (t, c): a vertex-chart stress in the face chart."""
    k00 = K[t, c, 0, 0]
    k01 = K[t, c, 0, 1]
    k10 = K[t, c, 1, 0]
    k11 = K[t, c, 1, 1]
    p00 = k00 * s11 + k01 * s12
    p01 = k00 * s12 + k01 * s22
    p10 = k10 * s11 + k11 * s12
    p11 = k10 * s12 + k11 * s22
    return (p00 * k00 + p01 * k01, p00 * k10 + p01 * k11, p10 * k10 + p11 * k11)


@kernel(inline='always')
def _jet(x, st_ptr, st_idx, st_w, i, out):
    """out (nc, 3): a_1, a_2, r_11, r_12, r_22 (and the cubic terms) of vertex i."""
    nc = st_w.shape[0]
    for c in range(nc):
        out[c, 0] = 0.0
        out[c, 1] = 0.0
        out[c, 2] = 0.0
    for k in range(st_ptr[i], st_ptr[i + 1]):
        j = st_idx[k]
        x0 = x[j, 0]
        x1 = x[j, 1]
        x2 = x[j, 2]
        for c in range(nc):
            w = st_w[c, k]
            out[c, 0] += w * x0
            out[c, 1] += w * x1
            out[c, 2] += w * x2


# Two stencil sums of the vertex pass. They are functions of their own, compiled with
# ``reassoc`` (compiled.REDUCTION) and not inlined by numba, so that their sums over the
# stencil run as SIMD vectors while the rest of the step keeps the strict order.

@kernel(fastmath=REDUCTION)
def _normal_jet(ns, p0, st_w, scratch, ch, n0, n1, n2):
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


@kernel(fastmath=REDUCTION)
def _weighted_offsets(ns, scratch, ch):
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
def _residual(sc, ch, s, k, kw, st_uv, st_sigma, q2, q3, q4, q5, q6, q7, q8):
    """rho_k . n - sigma_k = DN_k - phi_k . q - sigma_k for stencil entry k (scratch slot
    s, its chart coordinates at kw), q_1 = q_2 = 0."""
    return (sc[ch, 3, s] - st_sigma[k]
            - _phi_dot(st_uv[0, kw], st_uv[1, kw], 0.0, 0.0, q2, q3, q4, q5, q6, q7, q8))


@kernel(inline='always')
def _epsbar(i, vf_ptr, vf_face, eps, vf_K, phi):
    """epsbar_i = sum_t area_t / (3 A_i) K_it^T eps_t K_it, with the weight folded into vf_K
    (the corner matrices stored in vertex-face order); only the coupling uses it, so it is
    zero (not computed) when phi = 0."""
    e11 = 0.0
    e12 = 0.0
    e22 = 0.0
    for q in range(vf_ptr[i], vf_ptr[i + 1] if phi != 0.0 else vf_ptr[i]):
        t = vf_face[q]
        v11, v12, v22 = _to_vertex_chart(vf_K, q, eps[t, 0], eps[t, 1], eps[t, 2])
        e11 += v11
        e12 += v12
        e22 += v22
    return e11, e12, e22


@kernel(inline='always')
def _vertex(i, pc, p1, pw, x, st_idx, st_w, st_uv, st_sigma, stab, vf_ptr, vf_face, eps, vf_K,
            dual_area, ainv, rest_b, xi, phi, sc, ch, contrib, cstress, kap, epsbar, estab):
    """Bending, coupling and jet hourglass control of vertex i, and their adjoint.

    Energy ``E_i(dn, n)`` with ``dn_k = d_k . n`` (``d_k = x_j - x_i`` over the stencil):
    ``b_ab = sum_k W_k,ab dn_k``, ``cn_c = coef_c . n = sum_k W_kc dn_k``, residual along
    the normal ``rho_k . n = dn_k - phi_k . cn``. Then

        h_k = dE_i/d(dn_k) = 2 c_i omega (rho_k . n - sigma_k) + sum_ab W_k,ab g_ab
        dE_i/dd_k = h_k n + W_k1 J_1 + W_k2 J_2,   J_1 = a_2 x t, J_2 = t x a_1,
        t = (I - n n^T) V / |a_1 x a_2|,            V = sum_k h_k d_k

    (the normal depends on the positions through a_1, a_2 only). The least-squares fit
    residual is orthogonal to the design columns (sum_k phi_k (rho_k . n - sigma_k) = 0
    for the uniform fit weights), so the residual term needs no jet adjoint of its own.
    Writes ``contrib[k] = dE_i/dx_j`` for every stencil entry, coordinate-major (3, K);
    the centre's (minus the sum of the others) comes from the centre weights and
    ``sum_k h_k``. ``sc[ch]`` (5, S) is the chunk's scratch. Also writes kap, epsbar, the
    coupling stress and the residual energy estab[i]: this scalar form serves the step's
    single vertices and :func:`vertex_fields` (the energy); the lane form
    (:func:`_vertex_lanes`) stores only what the step reads.

    Written for the vectoriser: no array views inside the parallel loop (numba then marks
    the kernel's arrays ``noalias`` and LLVM vectorises the contiguous loops without
    run-time overlap checks), the stencil offset clamped to ``p0 >= 0`` and the gathered
    index unsigned (so no negative-index wrap-around turns contiguous loads into gathers),
    and the two stencil sums in :data:`compiled.REDUCTION` helpers. The gather of x
    stays scalar (vector gathers are slower here)."""
    p0 = max(pc + 1, 0)
    ns = p1 - p0
    q0 = max(pw + 1, 0)     # the weights and chart coordinates of entry p0 + s: q0 + s
    # one coefficient's weights over the stencil are contiguous: the loops below run over
    # the stencil entries k = p0 + s as vectors
    xi0 = x[i, 0]
    xi1 = x[i, 1]
    xi2 = x[i, 2]
    # pass 1: offsets d_k (an indexed gather, kept scalar) and the tangent vectors
    # a_1, a_2 (Eq. 8)
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
    c0, c1, c2 = _cross(a10, a11, a12, a20, a21, a22)
    cn = np.sqrt(c0 * c0 + c1 * c1 + c2 * c2)
    icn = 1.0 / cn
    n0 = c0 * icn
    n1 = c1 * icn
    n2 = c2 * icn
    # pass 2: dn_k and the jet along the normal, q_c = coef_c . n; b_ab = q for r_ab
    # (Eq. 11). q_1 = a_1 . n and q_2 = a_2 . n vanish.
    q2, q3, q4, q5, q6, q7, q8 = _normal_jet(ns, q0, st_w, sc, ch, n0, n1, n2)
    k11 = -(q2 - rest_b[i, 0])
    k12 = -(q3 - rest_b[i, 1])
    k22 = -(q4 - rest_b[i, 2])
    e11, e12, e22 = _epsbar(i, vf_ptr, vf_face, eps, vf_K, phi)
    i11 = ainv[i, 0]
    i12 = ainv[i, 1]
    i22 = ainv[i, 2]
    m11, m12, m22 = contract(2.0 * xi, i11, i12, i22, k11, k12, k22)
    s11, s12, s22 = contract(phi, i11, i12, i22, e11, e12, e22)
    m11 += s11
    m12 += s12
    m22 += s22
    cs11, cs12, cs22 = contract(phi, i11, i12, i22, k11, k12, k22)
    cstress[i, 0] = cs11
    cstress[i, 1] = cs12
    cstress[i, 2] = cs22
    kap[i, 0] = k11
    kap[i, 1] = k12
    kap[i, 2] = k22
    epsbar[i, 0] = e11
    epsbar[i, 1] = e12
    epsbar[i, 2] = e22
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
        dd = _residual(sc, ch, s, p0 + s, kw, st_uv, st_sigma, q2, q3, q4, q5, q6, q7, q8)
        sc[ch, 4, s] = (2.0 * om * dd + st_w[2, kw] * g11 + st_w[3, kw] * g12
                        + st_w[4, kw] * g22)
        e += dd * dd
    estab[i] = om * e
    v0, v1, v2, hs = _weighted_offsets(ns, sc, ch)
    # V = sum_k h_k d_k, and V . dn with dn = (I - n n^T) (da_1 x a_2 + a_1 x da_2) / |c|
    vn = v0 * n0 + v1 * n1 + v2 * n2
    t0 = (v0 - vn * n0) * icn
    t1 = (v1 - vn * n1) * icn
    t2 = (v2 - vn * n2) * icn
    j10, j11, j12 = _cross(a20, a21, a22, t0, t1, t2)
    j20, j21, j22 = _cross(t0, t1, t2, a10, a11, a12)
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


@kernel(inline='always')
def _gather_lanes(a, c, i0, i1, i2, i3):
    """(a[i0, c], a[i1, c], a[i2, c], a[i3, c]) as one vector."""
    return vset(a[i0, c], a[i1, c], a[i2, c], a[i3, c])


@kernel(inline='always')
def _store_lanes(a, c, i0, i1, i2, i3, v):
    """a[i_l, c] = lane l of v."""
    a[i0, c] = lane(v, 0)
    a[i1, c] = lane(v, 1)
    a[i2, c] = lane(v, 2)
    a[i3, c] = lane(v, 3)


@kernel(inline='always')
def _vertex_lanes(g, x, g_vert, g_ptr, g_wptr, st_idx, st_w, st_uv, st_sigma, stab, vf_ptr,
                  vf_face, eps, vf_K, dual_area, ainv, rest_b, xi, phi, sc, ch, contrib, cstress,
                  store_cs):
    """:func:`_vertex` for the four vertices of lane group g at once, one per SIMD lane
    (:mod:`.simd`): the same formulas, each operation on the four vertices in one vector.

    The group's stencils have the same size, and their entries are interleaved (lane
    order, :func:`lane_layout`): entry s of lane l sits at ``g_ptr[g] + 4 s + l``, s = 0
    the centre, its weights and chart coordinates at ``g_wptr[g, 0] + 4 s + l`` (a block
    that groups with the same stencil templates share) and its neighbour's offset
    ``j - i`` and rest residual at ``g_wptr[g, 1] + 4 s + l`` (a block that groups with
    the same offsets and residuals share); its gradients go to ``contrib`` from
    ``g_wptr[g, 2]`` on, in the same order (its entries' own positions, or in the tiled
    step a slot of its part's ring, integrator.vertex_parts). So the weights, chart
    coordinates and rest residuals of one entry of the four vertices load as one vector,
    and the gradients store as one. The positions x[j] are gathered lane by lane, except
    in a group whose four neighbours of each entry are four consecutive rows of x
    (``g_wptr[g, 3]``; 83% of the vertices of a 40 x 40 sheet): those load as one block
    (``simd.vload3``: step 0.93 / 0.96 / 0.97 / 0.90x at N = 20 / 40 / 80 / 160, paired,
    same bits).
    The stencil loops have no remainder and no horizontal sums, and the per-vertex work
    (normal, resultants, adjoint) is shared four ways."""
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
    # _epsbar takes them signed (it adds 1 to them)
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
    c0, c1, c2 = _cross(a10, a11, a12, a20, a21, a22)
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
    a0, b0, c0_ = _epsbar(g_vert[g, 0], vf_ptr, vf_face, eps, vf_K, phi)
    a1, b1, c1_ = _epsbar(g_vert[g, 1], vf_ptr, vf_face, eps, vf_K, phi)
    a2, b2, c2_ = _epsbar(g_vert[g, 2], vf_ptr, vf_face, eps, vf_K, phi)
    a3, b3, c3_ = _epsbar(g_vert[g, 3], vf_ptr, vf_face, eps, vf_K, phi)
    e11 = vset(a0, a1, a2, a3)
    e12 = vset(b0, b1, b2, b3)
    e22 = vset(c0_, c1_, c2_, c3_)
    i11 = _gather_lanes(ainv, 0, i0, i1, i2, i3)
    i12 = _gather_lanes(ainv, 1, i0, i1, i2, i3)
    i22 = _gather_lanes(ainv, 2, i0, i1, i2, i3)
    m11, m12, m22 = contract(2.0 * xi, i11, i12, i22, k11, k12, k22)
    s11, s12, s22 = contract(phi, i11, i12, i22, e11, e12, e22)
    m11 = m11 + s11
    m12 = m12 + s12
    m22 = m22 + s22
    cs11, cs12, cs22 = contract(phi, i11, i12, i22, k11, k12, k22)
    # the step stores the coupling stress (the faces read it when phi != 0), not kap,
    # epsbar or the residual energy: only the energy reads those, and it takes them from
    # vertex_fields (storing them here cost the step 3-13%, paired). The tiled step
    # (phi = 0: nothing reads it) passes a literal False and the stores compile away
    # (0.93-0.98x at N = 80 / 160, 1.00x at 320); the same as a run-time flag on the
    # two-pass step had made N = 20 / 40 8-14% slower
    if store_cs:
        _store_lanes(cstress, 0, i0, i1, i2, i3, cs11)
        _store_lanes(cstress, 1, i0, i1, i2, i3, cs12)
        _store_lanes(cstress, 2, i0, i1, i2, i3, cs22)
    A = vset(dual_area[i0], dual_area[i1], dual_area[i2], dual_area[i3])
    g11 = -A * m11
    g12 = -2.0 * A * m12
    g22 = -A * m22
    # pass 3: residuals along the normal and h_k = dE_i/d(dn_k)
    om = vset(stab[i0], stab[i1], stab[i2], stab[i3])
    # e, the residual's sum of squares, is not stored here (vertex_fields computes it for
    # the energy), and LLVM drops it in the end. It stays because with it in the loop
    # LLVM compiles the loop into code that ran the step 0.87-0.91x the time of the loop
    # without it (paired, N = 20 / 40).
    e = splat(0.0)
    for s in range(ns):
        kw = q0 + 4 * s
        dd = (vload(sc, r0 + 3 * W + 4 * s) - vload(st_sigma, e0 + 4 * s)
              - _phi_dot(vload(st_uv, kw), vload(st_uv, KW + kw), 0.0, 0.0, q2, q3, q4, q5, q6,
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
    j10, j11, j12 = _cross(a20, a21, a22, t0, t1, t2)
    j20, j21, j22 = _cross(t0, t1, t2, a10, a11, a12)
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


@kernel(forceinline=True)
def _vertex_chunk(ch, nch, row, x, g_vert, g_ptr, g_wptr, s_vert, s_ptr, s_wptr, st_idx, st_w,
                  st_uv, st_sigma, stab, vf_ptr, vf_face, eps, vf_K, dual_area, ainv, rest_b, xi,
                  phi, scratch, contrib, cstress, kap, epsbar, estab, faces, dinv, face_area,
                  zeta, fc_ptr, fc_tpl, fc_slot, with_faces, fgrad, store_cs):
    """Work item (chunk) ``ch`` of the vertex pass (integrator.vertex_pass, and tile by
    tile integrator.vertex_parts): the vertex term for its lane groups (four vertices at
    a time, :func:`_vertex_lanes`) and its single vertices (stencil sizes that do not fill
    a group, :func:`_vertex`): the coupling stress Theta kap (n,3) that the faces take up
    and the stencil gradients contrib (3,K) (the single vertices also store kap, epsbar
    and estab; the energy takes all of them from :func:`vertex_fields`) in the lane
    layout of :func:`lane_layout` (st_idx, st_sigma, contrib: entries; st_w, st_uv:
    weight blocks); ``nch`` chunks split the mesh (:func:`chunk_of_vertex`);
    ``scratch[row]`` (5, S) is this work item's alone while it runs (no allocation, no
    shared writes).

    With ``with_faces`` the membrane terms (:func:`_face_membrane`) of the chunk's faces
    q = ``fc_ptr[ch]:fc_ptr[ch + 1]`` run here too: one parallel region fewer per step.
    The caller passes them in chunk order, streamed front to back: their corners
    ``faces[q]`` (uint32), their rest shapes as rows ``fc_tpl[q]`` of a table of the
    distinct (Dinv, area) pairs (``dinv``, ``face_area``; a structured sheet has a few
    dozen) and the rows ``fc_slot[q]`` of fgrad their corner gradients go to (the face
    itself, or a ring slot in the tiled step). Only valid when the vertex terms do not read
    eps (phi = 0); the strains are then not stored. ``store_cs`` (a literal at each call)
    stores the lane groups' coupling stress; the tiled step, where nothing reads it,
    passes False.

    ``forceinline`` (LLVM ``alwaysinline``): inlined into the parallel loop's body, it
    gets that body's ``noalias`` arrays; a plain call was 5-10% slower."""
    # the chunk sizes follow from the caller's nch (not from a module constant, which
    # numba's cache would freeze into the compiled code); chunk_of_vertex is this split in
    # numpy. (Spreading the groups and singles evenly over the chunks ran the pass
    # 3-9% slower at N = 20 / 40: the few singles then leave the first chunks, i.e. the
    # calling thread, which starts before the woken worker.)
    ng = g_vert.shape[0]
    nsv = s_vert.shape[0]
    for q in range(nb.uint64(fc_ptr[ch]), nb.uint64(fc_ptr[ch + 1] if with_faces else
                                                  fc_ptr[ch])):
        _face_membrane(q, nb.uint64(fc_tpl[q]), nb.uint64(fc_slot[q]), x, faces, dinv,
                       face_area, zeta, eps, fgrad, False)
    gchunk = (ng + nch - 1) // nch
    for g in range(ch * gchunk, min(ng, (ch + 1) * gchunk)):
        _vertex_lanes(g, x, g_vert, g_ptr, g_wptr, st_idx, st_w, st_uv, st_sigma, stab,
                      vf_ptr, vf_face, eps, vf_K, dual_area, ainv, rest_b, xi, phi, scratch,
                      row, contrib, cstress, store_cs)
    schunk = (nsv + nch - 1) // nch
    for u in range(ch * schunk, min(nsv, (ch + 1) * schunk)):
        _vertex(s_vert[u], s_ptr[u], s_ptr[u + 1], s_wptr[u], x, st_idx, st_w, st_uv,
                st_sigma, stab, vf_ptr, vf_face, eps, vf_K, dual_area, ainv, rest_b, xi,
                phi, scratch, row, contrib, cstress, kap, epsbar, estab)


@kernel()
def _vertex_range(i0, i1, st_ptr, st_wptr, x, st_idx, st_w, st_uv, st_sigma, stab, vf_ptr,
                  vf_face, eps, vf_K, dual_area, ainv, rest_b, xi, phi, sc, ch, contrib,
                  cstress, kap, epsbar, estab):
    """:func:`_vertex` for the vertices i0:i1 with scratch row ``ch``: a function of its own
    for the parallel loop of :func:`vertex_fields`, called once per work item. numba's
    parallel passes then see a call instead of the inlined vertex term, which took them
    ~12 s more to compile (cold start); a call per vertex (26 array arguments each) made
    the energy report 1.15-1.2x slower than this."""
    for i in range(i0, i1):
        _vertex(i, st_ptr[i], st_ptr[i + 1], st_wptr[i], x, st_idx, st_w, st_uv, st_sigma,
                stab, vf_ptr, vf_face, eps, vf_K, dual_area, ainv, rest_b, xi, phi, sc, ch,
                contrib, cstress, kap, epsbar, estab)


@kernel(parallel=True)
def vertex_fields(x, faces, dinv, face_area, zeta, st_ptr, st_wptr, st_idx, st_w, st_uv,
                  st_sigma, stab, vf_ptr, vf_face, vf_K, dual_area, ainv, rest_b, xi, phi,
                  scratch, csr_contrib, fgrad, eps, cstress, kap, epsbar, estab):
    """The per-element fields of the energy at positions x: face strains eps (m,3) (Eq. 17),
    curvature change kap, strain average epsbar and coupling stress (n,3), and the jet
    residual energy estab (n,), from the same formulas as the step (:func:`_face_membrane`,
    :func:`_vertex`) on the stencils in plain CSR order (``st_sigma`` in that order too;
    vertex i's weights ``st_w`` and chart coordinates ``st_uv`` from ``st_wptr[i]`` on,
    a block per stencil template, which vertices with the same stencil share: a
    structured sheet then streams almost no weights; a weight per entry made this pass
    1.5x slower at N = 80). The step does not store these fields (the stores cost it
    3-13%); the energy report calls this instead of the step's force. It also writes the
    membrane corner gradients ``fgrad`` and the stencil gradients ``csr_contrib`` (3,K) in
    CSR order, so that the report gathers its force from them (with the transposed
    stencil's CSR slots) rather than run the force a second time; ``scratch`` (R, 5, S)
    gives each of its R work items a row."""
    for t in nb.prange(faces.shape[0]):
        _face_membrane(t, t, t, x, faces, dinv, face_area, zeta, eps, fgrad, True)
    n = x.shape[0]
    nch = scratch.shape[0]
    chunk = (n + nch - 1) // nch
    for c in nb.prange(nch):
        _vertex_range(np.int64(c) * chunk, min(n, (np.int64(c) + 1) * chunk), st_ptr,
                      st_wptr, x, st_idx, st_w, st_uv, st_sigma, stab, vf_ptr, vf_face, eps,
                      vf_K, dual_area, ainv, rest_b, xi, phi, scratch, np.int64(c),
                      csr_contrib, cstress, kap, epsbar, estab)


def chunk_of_vertex(n: int, nch: int, g_vert: np.ndarray, s_vert: np.ndarray) -> np.ndarray:
    """The work item (chunk) of every vertex, (n,) int64: the split of
    :func:`_vertex_chunk`, lane groups in equal runs, then single vertices in equal runs."""
    chunk = np.empty(n, dtype=np.int64)
    if len(g_vert):
        chunk[g_vert] = (np.arange(len(g_vert)) // -(-len(g_vert) // nch))[:, None]
    if len(s_vert):
        chunk[s_vert] = np.arange(len(s_vert)) // -(-len(s_vert) // nch)
    return chunk


def lane_layout(st_ptr: np.ndarray, template: np.ndarray, st_idx: np.ndarray,
                st_sigma: np.ndarray, lanes: int = LANES):
    """Order of the stencil entries, and blocks of the weights and of the entries' own
    data, for the vertex pass (:func:`_vertex_chunk`).

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


@kernel(inline='always')
def _phi_dot(u, v, q0, q1, q2, q3, q4, q5, q6, q7, q8):
    """phi(u, v) . q for the cubic design row phi = (u, v, u^2/2, uv, v^2/2, u^3/6, u^2 v/2,
    u v^2/2, v^3/6) (geometry.design_matrix), in Horner form."""
    return (u * (q0 + u * (0.5 * q2 + u * (q5 / 6.0) + v * (0.5 * q6)) + v * (q3 + v * (0.5 * q7)))
            + v * (q1 + v * (0.5 * q4 + v * (q8 / 6.0))))


@kernel(parallel=True)
def jet_normal_residuals(x, st_ptr, st_idx, st_w, st_uv, out):
    """out[k] = rho_k . n_i for every stencil entry (the sigma_k of the rest state), with
    the arithmetic of the vertex pass."""
    n = x.shape[0]
    nc = st_w.shape[0]
    for i in nb.prange(n):
        jt = np.zeros((nc, 3))
        _jet(x, st_ptr, st_idx, st_w, i, jt)
        c0, c1, c2 = _cross(jt[0, 0], jt[0, 1], jt[0, 2], jt[1, 0], jt[1, 1], jt[1, 2])
        cn = np.sqrt(c0 * c0 + c1 * c1 + c2 * c2)
        n0 = c0 / cn
        n1 = c1 / cn
        n2 = c2 / cn
        q = np.zeros(nc)
        for c in range(nc):
            q[c] = jt[c, 0] * n0 + jt[c, 1] * n1 + jt[c, 2] * n2
        out[st_ptr[i]] = 0.0
        for k in range(st_ptr[i] + 1, st_ptr[i + 1]):
            j = st_idx[k]
            dn = (x[j, 0] - x[i, 0]) * n0 + (x[j, 1] - x[i, 1]) * n1 + (x[j, 2] - x[i, 2]) * n2
            out[k] = dn - _phi_dot(st_uv[0, k], st_uv[1, k], q[0], q[1], q[2], q[3], q[4],
                                   q[5], q[6], q[7], q[8])


@kernel(parallel=True)
def face_coupling(x, faces, dinv, face_area, K, cstress, fgrad):
    """Adds the coupling's corner gradients: the stress-times-area
    ``S_t = sum_{i in t} area_t / 3 K_it Theta kap_i K_it^T`` of the vertex strain average
    (module docstring). Only run when phi != 0."""
    m = faces.shape[0]
    for t in nb.prange(m):
        a = face_area[t] / 3.0
        s11 = 0.0
        s12 = 0.0
        s22 = 0.0
        for c in range(3):
            i = faces[t, c]
            q11, q12, q22 = _to_face_chart(K, t, c, cstress[i, 0], cstress[i, 1],
                                           cstress[i, 2])
            s11 += a * q11
            s12 += a * q12
            s22 += a * q22
        _corner_gradients(x, faces, dinv, t, s11, s12, s22, fgrad, True)


@kernel(inline='always')
def _gather(j, vf_ptr, vf_row, frow, tr_ptr, tr_slot, contrib):
    """-dE/dx_j: corner gradients of the incident faces plus the stencil gradients of every
    vertex whose jet uses x_j (the transposed stencil).

    The corner gradients are rows ``frow`` (3 m, 3) of fgrad: ``vf_row`` holds 3 face +
    corner (or 3 slot + corner, where the tiled step puts them) per vertex-face pair, and
    ``tr_slot`` the stencil gradients' positions in ``contrib``. Both are uint32: the gather
    streams 4 bytes per index instead of 8, and one index per face instead of two. All
    indices are read as unsigned: a signed index makes numba add its negative-index
    wrap-around (four integer instructions per load), which cost the gather ~25% at
    N = 40 (one thread, 42 -> 31 ns per vertex)."""
    j1 = nb.uint64(j + 1)
    j = nb.uint64(j)
    g0 = 0.0
    g1 = 0.0
    g2 = 0.0
    for q in range(nb.uint64(vf_ptr[j]), nb.uint64(vf_ptr[j1])):
        r = nb.uint64(vf_row[q])
        g0 += frow[r, 0]
        g1 += frow[r, 1]
        g2 += frow[r, 2]
    for q in range(nb.uint64(tr_ptr[j]), nb.uint64(tr_ptr[j1])):
        k = nb.uint64(tr_slot[q])
        g0 += contrib[0, k]
        g1 += contrib[1, k]
        g2 += contrib[2, k]
    return -g0, -g1, -g2


@kernel(parallel=True)
def gather_forces(vf_ptr, vf_row, fgrad, tr_ptr, tr_slot, contrib, force):
    """force[j] = -dE/dx_j (n,3) [N] (:func:`_gather`; fgrad (m, 3, 3) read as rows)."""
    n = force.shape[0]
    frow = fgrad.reshape((fgrad.shape[0] * 3, 3))
    for j in nb.prange(n):
        force[j, 0], force[j, 1], force[j, 2] = _gather(j, vf_ptr, vf_row, frow, tr_ptr,
                                                        tr_slot, contrib)


@kernel(parallel=True)
def energy_densities(eps, kap, epsbar, estab, faces, face_area, vf_ptr, vf_face, dual_area,
                     ainv, zeta, xi, phi, out):
    """Per-vertex energy densities [J/m^2] in out[:, 0:3] (out (n,3) or wider): stretching
    (dual-area average of the incident triangles' W_m), bending xi B(kap, kap), coupling
    phi B(epsbar, kap)."""
    n = out.shape[0]
    for i in nb.prange(n):
        s = 0.0
        for q in range(vf_ptr[i], vf_ptr[i + 1]):
            t = vf_face[q]
            e11 = eps[t, 0]
            e12 = eps[t, 1]
            e22 = eps[t, 2]
            tr = e11 + e22
            s += face_area[t] / 3.0 * zeta * (tr * tr + 2.0 * (e11 * e11 + 2.0 * e12 * e12
                                                                 + e22 * e22))
        out[i, 0] = s / dual_area[i]
        i11 = ainv[i, 0]
        i12 = ainv[i, 1]
        i22 = ainv[i, 2]
        out[i, 1] = xi * bilinear(i11, i12, i22, kap[i, 0], kap[i, 1], kap[i, 2],
                                  kap[i, 0], kap[i, 1], kap[i, 2]) + estab[i] / dual_area[i]
        out[i, 2] = phi * bilinear(i11, i12, i22, epsbar[i, 0], epsbar[i, 1], epsbar[i, 2],
                                   kap[i, 0], kap[i, 1], kap[i, 2])


@kernel()
def energy_totals(dens, dual_area, force, f_applied, mass, damp, v, x, pinned, gravity, dt,
                  out):
    """The sums of the energy report (simulator ``energy_and_densities``) in one pass, from
    the densities ``dens`` (n,4) of :func:`energy_densities` in its first three columns:

    * ``dens[:, 3]`` = their sum per vertex (the total density);
    * ``out[0:3]`` = sum_i A_i dens_i: the stretching, bending and coupling energy [J];
    * ``out[3]`` = kinetic energy 1/2 sum_i m_i |v_i + dt/2 a_i|^2 of the leapfrog velocity
      carried to the positions' time, with ``m_i a_i = f_i + f_applied_i + m_i g - c_i v_i``
      (the step's acceleration, :func:`.integrator._update`) and 0 at pinned vertices;
    * ``out[4]`` = -sum_i m_i g . x_i, the gravity potential [J].

    Serial, in vertex order: the sums are the same numbers on any thread count."""
    n = dens.shape[0]
    s0 = 0.0
    s1 = 0.0
    s2 = 0.0
    kin = 0.0
    pot = 0.0
    g0 = gravity[0]
    g1 = gravity[1]
    g2 = gravity[2]
    h = 0.5 * dt
    for i in range(n):
        a = dual_area[i]
        d0 = dens[i, 0]
        d1 = dens[i, 1]
        d2 = dens[i, 2]
        dens[i, 3] = d0 + d1 + d2
        s0 += a * d0
        s1 += a * d1
        s2 += a * d2
        m = mass[i]
        pot -= m * (x[i, 0] * g0 + x[i, 1] * g1 + x[i, 2] * g2)
        if not pinned[i]:
            c = damp[i]
            w0 = v[i, 0] + h * (force[i, 0] + f_applied[i, 0] + m * g0 - c * v[i, 0]) / m
            w1 = v[i, 1] + h * (force[i, 1] + f_applied[i, 1] + m * g1 - c * v[i, 1]) / m
            w2 = v[i, 2] + h * (force[i, 2] + f_applied[i, 2] + m * g2 - c * v[i, 2]) / m
            kin += m * (w0 * w0 + w1 * w1 + w2 * w2)
    out[0] = s0
    out[1] = s1
    out[2] = s2
    out[3] = 0.5 * kin
    out[4] = pot


# --------------------------------------------------------------------------- seed route

@kernel(parallel=True)
def covariant_resultants(x, st_ptr, st_idx, st_w, rest_a, ainv, rest_b, zeta, xi, phi,
                         basis, chris, mres, nres):
    """Vertex resultants for the seed route: basis (n,3,3), Christoffel (n,2,2,2),
    M^ab (n,2,2) and N^ab = N*^ab - M^bg a^ad b_dg (n,2,2) (Eq. 27, 28)."""
    n = x.shape[0]
    for i in nb.prange(n):
        jt = np.zeros((st_w.shape[0], 3))
        _jet(x, st_ptr, st_idx, st_w, i, jt)
        c0, c1, c2 = _cross(jt[0, 0], jt[0, 1], jt[0, 2], jt[1, 0], jt[1, 1], jt[1, 2])
        cn = np.sqrt(c0 * c0 + c1 * c1 + c2 * c2)
        nv = (c0 / cn, c1 / cn, c2 / cn)
        for k in range(3):
            basis[i, 0, k] = jt[0, k]
            basis[i, 1, k] = jt[1, k]
            basis[i, 2, k] = nv[k]
        g11 = jt[0, 0] ** 2 + jt[0, 1] ** 2 + jt[0, 2] ** 2
        g12 = jt[0, 0] * jt[1, 0] + jt[0, 1] * jt[1, 1] + jt[0, 2] * jt[1, 2]
        g22 = jt[1, 0] ** 2 + jt[1, 1] ** 2 + jt[1, 2] ** 2
        det = g11 * g22 - g12 * g12
        a11 = g22 / det
        a12 = -g12 / det
        a22 = g11 / det
        bb = np.zeros(3)
        for c in range(3):
            bb[c] = nv[0] * jt[2 + c, 0] + nv[1] * jt[2 + c, 1] + nv[2] * jt[2 + c, 2]
            al = 0 if c < 2 else 1
            be = 0 if c == 0 else 1
            p1 = jt[0, 0] * jt[2 + c, 0] + jt[0, 1] * jt[2 + c, 1] + jt[0, 2] * jt[2 + c, 2]
            p2 = jt[1, 0] * jt[2 + c, 0] + jt[1, 1] * jt[2 + c, 1] + jt[1, 2] * jt[2 + c, 2]
            chris[i, 0, al, be] = a11 * p1 + a12 * p2
            chris[i, 0, be, al] = a11 * p1 + a12 * p2
            chris[i, 1, al, be] = a12 * p1 + a22 * p2
            chris[i, 1, be, al] = a12 * p1 + a22 * p2
        e11 = 0.5 * (g11 - rest_a[i, 0])
        e12 = 0.5 * (g12 - rest_a[i, 1])
        e22 = 0.5 * (g22 - rest_a[i, 2])
        k11 = -(bb[0] - rest_b[i, 0])
        k12 = -(bb[1] - rest_b[i, 1])
        k22 = -(bb[2] - rest_b[i, 2])
        i11 = ainv[i, 0]
        i12 = ainv[i, 1]
        i22 = ainv[i, 2]
        n11, n12, n22 = contract(2.0 * zeta, i11, i12, i22, e11, e12, e22)
        t11, t12, t22 = contract(phi, i11, i12, i22, k11, k12, k22)
        m11, m12, m22 = contract(2.0 * xi, i11, i12, i22, k11, k12, k22)
        u11, u12, u22 = contract(phi, i11, i12, i22, e11, e12, e22)
        M = ((m11 + u11, m12 + u12), (m12 + u12, m22 + u22))
        Ns = ((n11 + t11, n12 + t12), (n12 + t12, n22 + t22))
        ainvc = ((a11, a12), (a12, a22))
        bm = ((bb[0], bb[1]), (bb[1], bb[2]))
        for al in range(2):
            for be in range(2):
                mres[i, al, be] = M[al][be]
                s = 0.0
                for g in range(2):
                    for d in range(2):
                        s += M[be][g] * ainvc[al][d] * bm[d][g]
                nres[i, al, be] = Ns[al][be] - s


@kernel(parallel=True)
def covariant_force_vectors(st_ptr, st_idx, st_w, st_T, basis, chris, mres, nres, nvec):
    """N^3b = M^ba|_a (Eq. 15, 28) and the force vectors N^b = N^ab a_a + N^3b a_3
    (Eq. 26), nvec (n,2,3). Neighbour components are carried into the vertex chart by
    st_T (the identity on a flat sheet)."""
    n = basis.shape[0]
    for i in nb.prange(n):
        # partial derivatives d_g M^ba (g, b, a)
        dM = np.zeros((2, 2, 2))
        for k in range(st_ptr[i], st_ptr[i + 1]):
            j = st_idx[k]
            for b in range(2):
                for a in range(2):
                    v = 0.0
                    for p in range(2):
                        for q in range(2):
                            v += st_T[k, b, p] * st_T[k, a, q] * mres[j, p, q]
                    dM[0, b, a] += st_w[0, k] * v
                    dM[1, b, a] += st_w[1, k] * v
        for b in range(2):
            s = 0.0
            for a in range(2):
                s += dM[a, b, a]
                for lam in range(2):
                    s += chris[i, b, a, lam] * mres[i, lam, a]
                    s += chris[i, a, a, lam] * mres[i, b, lam]
            for k in range(3):
                nvec[i, b, k] = (nres[i, 0, b] * basis[i, 0, k] + nres[i, 1, b] * basis[i, 1, k]
                                 + s * basis[i, 2, k])


@kernel(parallel=True)
def covariant_divergence(st_ptr, st_idx, st_w, st_T, chris, nvec, dual_area, force):
    """Nodal force A_i N^a|_a = A_i (d_a N^a + Gamma^a_al N^l) (Eq. 14, 24)."""
    n = nvec.shape[0]
    for i in nb.prange(n):
        f0 = 0.0
        f1 = 0.0
        f2 = 0.0
        for k in range(st_ptr[i], st_ptr[i + 1]):
            j = st_idx[k]
            for a in range(2):
                w = st_w[a, k]
                for b in range(2):
                    tw = w * st_T[k, a, b]
                    f0 += tw * nvec[j, b, 0]
                    f1 += tw * nvec[j, b, 1]
                    f2 += tw * nvec[j, b, 2]
        for a in range(2):
            for lam in range(2):
                gm = chris[i, a, a, lam]
                f0 += gm * nvec[i, lam, 0]
                f1 += gm * nvec[i, lam, 1]
                f2 += gm * nvec[i, lam, 2]
        A = dual_area[i]
        force[i, 0] = A * f0
        force[i, 1] = A * f1
        force[i, 2] = A * f2


@kernel()
def covariant_forces(x, ops, cov, mat, cwork, force):
    """Seed-route internal force (n,3) [N] at positions x."""
    dual_area, st_ptr, st_idx, st_w = ops[4], ops[7], ops[8], ops[9]
    rest_a, st_T = cov
    basis, chris, mres, nres, nvec = cwork
    covariant_resultants(x, st_ptr, st_idx, st_w, rest_a, ops[5], ops[6], mat[0], mat[1],
                         mat[2], basis, chris, mres, nres)
    covariant_force_vectors(st_ptr, st_idx, st_w, st_T, basis, chris, mres, nres, nvec)
    covariant_divergence(st_ptr, st_idx, st_w, st_T, chris, nvec, dual_area, force)
