"""Internal forces N^a|_a of the Cosserat surface (Eq. 20, 24-28) and the discrete energy.

Discrete energy (``"variational"``)
----------------------------------
``E = sum_t area_t W_m(eps_t) + sum_i A_i [xi B(kap_i, kap_i) + phi B(epsbar_i, kap_i)]``

* membrane, per triangle (constant-strain triangle, so no hourglass mode): the deformation
  gradient ``F_t = [x1 - x0, x2 - x0] Dinv_t`` in the triangle's orthonormal rest chart,
  ``eps_t = (F_t^T F_t - I) / 2`` (Eq. 17), ``W_m = zeta B(eps_t, eps_t)`` with A = I;
* bending, per vertex from the quadratic jet of :mod:`.geometry`: ``kap_i = -(b_i - B_i)``;
* coupling, per vertex: ``epsbar_i`` is the dual-area average of the incident triangles'
  strain carried to the vertex chart, ``epsbar_i = sum_t (area_t / 3 A_i) K_it^T eps_t K_it``
  where ``K_it = D_t U_it^-1`` maps the vertex chart onto the triangle chart (``U_it`` are
  the triangle's rest edges projected on the vertex's rest tangent plane).

The force is ``-dE/dx`` exactly. Every estimator is linear in the positions, so the chain
rule through them is the adjoint (transpose) of the discrete derivative operators: a
discrete divergence, gathered per vertex through the transposed stencils. With
``N*_t = 2 Phi eps_t`` (Eq. 22) and ``M_i = 2 Psi kap_i + Theta epsbar_i``:

    dE/dx_j = sum_{t ni j} [F_t S_t Dinv_t^T]_corner
            + sum_{i: j in stencil(i)} sum_c W_i[j, c] J_i[c]

with the triangle "stress times area" ``S_t = area_t N*_t + sum_{i in t} area_t/3 K Theta kap_i K^T``
and the vertex jet stresses ``J = dE_i/d(a_1, a_2, r_11, r_12, r_22)``:
``dE_i/dr_ab = g_ab n``, ``dE_i/da_1 = sum g_ab a_2 x t_ab``, ``dE_i/da_2 = sum g_ab t_ab x a_1``,
``g_ab = -A_i (M^ab + M^ba)/(1 + [a == b])``, ``t_ab = (I - n n^T) r_ab / |a_1 x a_2|``.
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

from .geometry import _cross
from .material import bilinear, contract

__all__ = ['DIVERGENCE_METHODS']

DIVERGENCE_METHODS = ('variational', 'covariant')


@nb.njit(cache=True, parallel=True)
def face_strain(x, faces, dinv, F, eps):
    """Deformation gradient F (m,3,2) and Green strain eps (m,3) = (11, 12, 22) per face."""
    m = faces.shape[0]
    for t in nb.prange(m):
        i0 = faces[t, 0]
        i1 = faces[t, 1]
        i2 = faces[t, 2]
        d00 = dinv[t, 0, 0]
        d01 = dinv[t, 0, 1]
        d10 = dinv[t, 1, 0]
        d11 = dinv[t, 1, 1]
        for k in range(3):
            e1 = x[i1, k] - x[i0, k]
            e2 = x[i2, k] - x[i0, k]
            F[t, k, 0] = e1 * d00 + e2 * d10
            F[t, k, 1] = e1 * d01 + e2 * d11
        f11 = F[t, 0, 0] ** 2 + F[t, 1, 0] ** 2 + F[t, 2, 0] ** 2
        f12 = F[t, 0, 0] * F[t, 0, 1] + F[t, 1, 0] * F[t, 1, 1] + F[t, 2, 0] * F[t, 2, 1]
        f22 = F[t, 0, 1] ** 2 + F[t, 1, 1] ** 2 + F[t, 2, 1] ** 2
        eps[t, 0] = 0.5 * (f11 - 1.0)
        eps[t, 1] = 0.5 * f12
        eps[t, 2] = 0.5 * (f22 - 1.0)


@nb.njit(cache=True, inline='always')
def _to_vertex_chart(K, t, c, e11, e12, e22):
    """K^T e K for the corner (t, c): a face-chart tensor in the vertex chart."""
    k00 = K[t, c, 0, 0]
    k01 = K[t, c, 0, 1]
    k10 = K[t, c, 1, 0]
    k11 = K[t, c, 1, 1]
    # e K
    p00 = e11 * k00 + e12 * k10
    p01 = e11 * k01 + e12 * k11
    p10 = e12 * k00 + e22 * k10
    p11 = e12 * k01 + e22 * k11
    return (k00 * p00 + k10 * p10, k00 * p01 + k10 * p11, k01 * p01 + k11 * p11)


@nb.njit(cache=True, inline='always')
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


@nb.njit(cache=True, inline='always')
def _jet(x, st_ptr, st_idx, st_w, i, out):
    """out (nc, 3): a_1, a_2, r_11, r_12, r_22 (and the cubic terms) of vertex i."""
    nc = st_w.shape[1]
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
            w = st_w[k, c]
            out[c, 0] += w * x0
            out[c, 1] += w * x1
            out[c, 2] += w * x2


@nb.njit(cache=True, parallel=True)
def vertex_bending(x, st_ptr, st_idx, st_w, st_ph, st_omega, st_sigma, stab, vf_ptr, vf_face,
                   vf_corner, eps, face_area, K, dual_area, ainv, rest_b, xi, phi, jstress,
                   cstress, kap, epsbar, sgrad, estab, jets):
    """Per-vertex bending and coupling: kap, epsbar (n,3), jet stresses J (n,5,3), the
    coupling stress Theta kap (n,3) that the faces take up, and the jet-residual
    stabilisation: its energy estab (n,) and direct gradient per stencil entry sgrad (K,3).
    See the module docstring."""
    n = x.shape[0]
    nc = st_w.shape[1]
    for i in nb.prange(n):
        jt = jets[i]                 # per-vertex scratch: no allocation in the parallel loop
        jx = jstress[i]
        _jet(x, st_ptr, st_idx, st_w, i, jt)
        for c in range(nc):
            jx[c, 0] = 0.0
            jx[c, 1] = 0.0
            jx[c, 2] = 0.0
        c0, c1, c2 = _cross(jt[0, 0], jt[0, 1], jt[0, 2], jt[1, 0], jt[1, 1], jt[1, 2])
        cn = np.sqrt(c0 * c0 + c1 * c1 + c2 * c2)
        n0 = c0 / cn
        n1 = c1 / cn
        n2 = c2 / cn
        _jet_residual(x, st_ptr, st_idx, st_ph, st_omega, st_sigma, stab[i], i, jt, n0, n1, n2,
                      cn, jx, sgrad, estab)
        b11 = n0 * jt[2, 0] + n1 * jt[2, 1] + n2 * jt[2, 2]
        b12 = n0 * jt[3, 0] + n1 * jt[3, 1] + n2 * jt[3, 2]
        b22 = n0 * jt[4, 0] + n1 * jt[4, 1] + n2 * jt[4, 2]
        k11 = -(b11 - rest_b[i, 0])
        k12 = -(b12 - rest_b[i, 1])
        k22 = -(b22 - rest_b[i, 2])
        e11 = 0.0
        e12 = 0.0
        e22 = 0.0
        for q in range(vf_ptr[i], vf_ptr[i + 1]):
            t = vf_face[q]
            c = vf_corner[q]
            w = face_area[t] / (3.0 * dual_area[i])
            v11, v12, v22 = _to_vertex_chart(K, t, c, eps[t, 0], eps[t, 1], eps[t, 2])
            e11 += w * v11
            e12 += w * v12
            e22 += w * v22
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
        g = (-A * m11, -2.0 * A * m12, -A * m22)
        for c in range(3):
            jx[2 + c, 0] += g[c] * n0
            jx[2 + c, 1] += g[c] * n1
            jx[2 + c, 2] += g[c] * n2
        da10 = 0.0
        da11 = 0.0
        da12 = 0.0
        da20 = 0.0
        da21 = 0.0
        da22 = 0.0
        for c in range(3):
            r0 = jt[2 + c, 0]
            r1 = jt[2 + c, 1]
            r2 = jt[2 + c, 2]
            rn = r0 * n0 + r1 * n1 + r2 * n2
            t0 = g[c] * (r0 - rn * n0) / cn
            t1 = g[c] * (r1 - rn * n1) / cn
            t2 = g[c] * (r2 - rn * n2) / cn
            u0, u1, u2 = _cross(jt[1, 0], jt[1, 1], jt[1, 2], t0, t1, t2)
            da10 += u0
            da11 += u1
            da12 += u2
            w0, w1, w2 = _cross(t0, t1, t2, jt[0, 0], jt[0, 1], jt[0, 2])
            da20 += w0
            da21 += w1
            da22 += w2
        jx[0, 0] += da10
        jx[0, 1] += da11
        jx[0, 2] += da12
        jx[1, 0] += da20
        jx[1, 1] += da21
        jx[1, 2] += da22


@nb.njit(cache=True, inline='always')
def _coef_dot_n(jt, n0, n1, n2, out):
    """out[c] = coef_c . n for every jet coefficient."""
    for c in range(jt.shape[0]):
        out[c] = jt[c, 0] * n0 + jt[c, 1] * n1 + jt[c, 2] * n2


@nb.njit(cache=True, inline='always')
def _residual_n(x, i, j, ph, cn_, n0, n1, n2):
    """Offset d = x_j - x_i and the fit residual along the normal,
    rho . n = d . n - sum_c phi_c (coef_c . n): returns (d0, d1, d2, rho . n)."""
    d0 = x[j, 0] - x[i, 0]
    d1 = x[j, 1] - x[i, 1]
    d2 = x[j, 2] - x[i, 2]
    s = 0.0
    for c in range(ph.shape[0]):
        s += ph[c] * cn_[c]
    return d0, d1, d2, d0 * n0 + d1 * n1 + d2 * n2 - s


@nb.njit(cache=True, inline='always')
def _jet_residual(x, st_ptr, st_idx, st_ph, st_omega, st_sigma, cst, i, jt, n0, n1, n2, cn,
                  jx, sgrad, estab):
    """Hourglass control of the jet: E_s,i = c_i sum_k omega_k (rho_k . n - sigma_k)^2,
    rho_k = x_j - x_i - sum_c phi_c(u_k, v_k) coef_c the least-squares residual, sigma_k its
    rest value along the rest normal (zero on a flat sheet). Rotation invariant, zero at
    rest, O(h^4) for smooth fields. Writes estab[i] and the direct gradient g_k n at each
    stencil entry (the centre takes minus their sum) and adds dE_s/dcoef_c to jx (the
    normal's dependence on a_1, a_2 included)."""
    p0 = st_ptr[i]
    nc = jt.shape[0]
    # rho_k . n = d_k . n - sum_c phi_kc (coef_c . n): scalar products per entry; the
    # adjoint needs only G = sum_k g_k d_k and P_c = sum_k g_k phi_kc
    cn_ = np.zeros(9)
    _coef_dot_n(jt, n0, n1, n2, cn_)
    pc = np.zeros(9)
    e = 0.0
    gs = 0.0
    G0 = 0.0
    G1 = 0.0
    G2 = 0.0
    for k in range(p0 + 1, st_ptr[i + 1]):
        ph = st_ph[k]
        d0, d1, d2, rn = _residual_n(x, i, st_idx[k], ph, cn_, n0, n1, n2)
        d = rn - st_sigma[k]
        om = cst * st_omega[k]
        e += om * d * d
        g = 2.0 * om * d
        sgrad[k, 0] = g * n0
        sgrad[k, 1] = g * n1
        sgrad[k, 2] = g * n2
        gs += g
        G0 += g * d0
        G1 += g * d1
        G2 += g * d2
        for c in range(nc):
            pc[c] += g * ph[c]
    v0 = G0
    v1 = G1
    v2 = G2
    for c in range(nc):
        jx[c, 0] -= pc[c] * n0
        jx[c, 1] -= pc[c] * n1
        jx[c, 2] -= pc[c] * n2
        v0 -= pc[c] * jt[c, 0]
        v1 -= pc[c] * jt[c, 1]
        v2 -= pc[c] * jt[c, 2]
    sgrad[p0, 0] = -gs * n0
    sgrad[p0, 1] = -gs * n1
    sgrad[p0, 2] = -gs * n2
    estab[i] = e
    # v . dn with dn = (I - n n^T) dc / |c|, dc = da_1 x a_2 + a_1 x da_2
    vn = v0 * n0 + v1 * n1 + v2 * n2
    t0 = (v0 - vn * n0) / cn
    t1 = (v1 - vn * n1) / cn
    t2 = (v2 - vn * n2) / cn
    u0, u1, u2 = _cross(jt[1, 0], jt[1, 1], jt[1, 2], t0, t1, t2)
    jx[0, 0] += u0
    jx[0, 1] += u1
    jx[0, 2] += u2
    w0, w1, w2 = _cross(t0, t1, t2, jt[0, 0], jt[0, 1], jt[0, 2])
    jx[1, 0] += w0
    jx[1, 1] += w1
    jx[1, 2] += w2


@nb.njit(cache=True, parallel=True)
def jet_normal_residuals(x, st_ptr, st_idx, st_w, st_ph, out):
    """out[k] = rho_k . n_i for every stencil entry (the sigma_k of the rest state)."""
    n = x.shape[0]
    nc = st_w.shape[1]
    for i in nb.prange(n):
        jt = np.zeros((nc, 3))
        _jet(x, st_ptr, st_idx, st_w, i, jt)
        c0, c1, c2 = _cross(jt[0, 0], jt[0, 1], jt[0, 2], jt[1, 0], jt[1, 1], jt[1, 2])
        cn = np.sqrt(c0 * c0 + c1 * c1 + c2 * c2)
        cn_ = np.zeros(nc)
        _coef_dot_n(jt, c0 / cn, c1 / cn, c2 / cn, cn_)
        out[st_ptr[i]] = 0.0
        for k in range(st_ptr[i] + 1, st_ptr[i + 1]):
            out[k] = _residual_n(x, i, st_idx[k], st_ph[k], cn_, c0 / cn, c1 / cn,
                                 c2 / cn)[3]


@nb.njit(cache=True, parallel=True)
def face_forces(faces, F, eps, dinv, face_area, K, cstress, zeta, fgrad):
    """Energy gradient at the three corners of each face, fgrad (m,3,3) = dE_t/dx_corner."""
    m = faces.shape[0]
    for t in nb.prange(m):
        e11 = eps[t, 0]
        e12 = eps[t, 1]
        e22 = eps[t, 2]
        a = face_area[t]
        tr = e11 + e22
        s11 = a * 2.0 * zeta * (tr + 2.0 * e11)
        s12 = a * 2.0 * zeta * (2.0 * e12)
        s22 = a * 2.0 * zeta * (tr + 2.0 * e22)
        for c in range(3):
            i = faces[t, c]
            q11, q12, q22 = _to_face_chart(K, t, c, cstress[i, 0], cstress[i, 1],
                                           cstress[i, 2])
            s11 += a / 3.0 * q11
            s12 += a / 3.0 * q12
            s22 += a / 3.0 * q22
        d00 = dinv[t, 0, 0]
        d01 = dinv[t, 0, 1]
        d10 = dinv[t, 1, 0]
        d11 = dinv[t, 1, 1]
        for k in range(3):
            p0 = F[t, k, 0] * s11 + F[t, k, 1] * s12
            p1 = F[t, k, 0] * s12 + F[t, k, 1] * s22
            g1 = p0 * d00 + p1 * d01
            g2 = p0 * d10 + p1 * d11
            fgrad[t, 1, k] = g1
            fgrad[t, 2, k] = g2
            fgrad[t, 0, k] = -g1 - g2


@nb.njit(cache=True, parallel=True)
def gather_forces(vf_ptr, vf_face, vf_corner, fgrad, tr_ptr, tr_src, tr_slot, st_w,
                  jstress, sgrad, force):
    """force[j] = -dE/dx_j: corner gradients of incident faces plus the jet adjoint."""
    n = force.shape[0]
    for j in nb.prange(n):
        g0 = 0.0
        g1 = 0.0
        g2 = 0.0
        for q in range(vf_ptr[j], vf_ptr[j + 1]):
            t = vf_face[q]
            c = vf_corner[q]
            g0 += fgrad[t, c, 0]
            g1 += fgrad[t, c, 1]
            g2 += fgrad[t, c, 2]
        for q in range(tr_ptr[j], tr_ptr[j + 1]):
            i = tr_src[q]
            k = tr_slot[q]
            g0 += sgrad[k, 0]
            g1 += sgrad[k, 1]
            g2 += sgrad[k, 2]
            for c in range(st_w.shape[1]):
                w = st_w[k, c]
                g0 += w * jstress[i, c, 0]
                g1 += w * jstress[i, c, 1]
                g2 += w * jstress[i, c, 2]
        force[j, 0] = -g0
        force[j, 1] = -g1
        force[j, 2] = -g2


@nb.njit(cache=True)
def variational_forces(x, ops, mat, work, force):
    """Internal force -dE/dx (n,3) [N] of the discrete Cosserat energy at positions x."""
    (faces, dinv, face_area, K, dual_area, ainv, rest_b, st_ptr, st_idx, st_w, st_ph,
     st_omega, st_sigma, stab, tr_ptr, tr_src, tr_slot, vf_ptr, vf_face, vf_corner) = ops
    zeta, xi, phi = mat[0], mat[1], mat[2]
    F, eps, jstress, cstress, kap, epsbar, fgrad, sgrad, estab, jets = work
    face_strain(x, faces, dinv, F, eps)
    vertex_bending(x, st_ptr, st_idx, st_w, st_ph, st_omega, st_sigma, stab, vf_ptr, vf_face,
                   vf_corner, eps, face_area, K, dual_area, ainv, rest_b, xi, phi, jstress,
                   cstress, kap, epsbar, sgrad, estab, jets)
    face_forces(faces, F, eps, dinv, face_area, K, cstress, zeta, fgrad)
    gather_forces(vf_ptr, vf_face, vf_corner, fgrad, tr_ptr, tr_src, tr_slot, st_w, jstress,
                  sgrad, force)


@nb.njit(cache=True, parallel=True)
def energy_densities(eps, kap, epsbar, estab, faces, face_area, vf_ptr, vf_face, dual_area,
                     ainv, zeta, xi, phi, out):
    """Per-vertex energy densities [J/m^2] out (n,3): stretching (dual-area average of the
    incident triangles' W_m), bending xi B(kap, kap), coupling phi B(epsbar, kap)."""
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


# --------------------------------------------------------------------------- seed route

@nb.njit(cache=True, parallel=True)
def covariant_resultants(x, st_ptr, st_idx, st_w, rest_a, ainv, rest_b, zeta, xi, phi,
                         basis, chris, mres, nres):
    """Vertex resultants for the seed route: basis (n,3,3), Christoffel (n,2,2,2),
    M^ab (n,2,2) and N^ab = N*^ab - M^bg a^ad b_dg (n,2,2) (Eq. 27, 28)."""
    n = x.shape[0]
    for i in nb.prange(n):
        jt = np.zeros((st_w.shape[1], 3))
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


@nb.njit(cache=True, parallel=True)
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
                    dM[0, b, a] += st_w[k, 0] * v
                    dM[1, b, a] += st_w[k, 1] * v
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


@nb.njit(cache=True, parallel=True)
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
                w = st_w[k, a]
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


@nb.njit(cache=True)
def covariant_forces(x, ops, cov, mat, cwork, force):
    """Seed-route internal force (n,3) [N] at positions x."""
    (faces, dinv, face_area, K, dual_area, ainv, rest_b, st_ptr, st_idx, st_w, st_ph,
     st_omega, st_sigma, stab, tr_ptr, tr_src, tr_slot, vf_ptr, vf_face, vf_corner) = ops
    rest_a, st_T = cov
    basis, chris, mres, nres, nvec = cwork
    covariant_resultants(x, st_ptr, st_idx, st_w, rest_a, ainv, rest_b, mat[0], mat[1],
                         mat[2], basis, chris, mres, nres)
    covariant_force_vectors(st_ptr, st_idx, st_w, st_T, basis, chris, mres, nres, nvec)
    covariant_divergence(st_ptr, st_idx, st_w, st_T, chris, nvec, dual_area, force)
