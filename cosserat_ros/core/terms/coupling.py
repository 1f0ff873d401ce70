"""Stretch-bend coupling term (the seed's "wrinkle" constant phi, Theta = C(phi) of Eq. 19).

Energy
------
``E_c = sum_i A_i phi B(epsbar_i, kap_i)``

* ``kap_i`` the vertex's curvature change (:mod:`.jet`);
* ``epsbar_i`` the dual-area average of the incident triangles' strain carried to the vertex
  chart: ``epsbar_i = sum_t (area_t / 3 A_i) K_it^T eps_t K_it``, ``K_it = D_t U_it^-1`` mapping
  the vertex chart onto the triangle chart (``U_it`` the triangle's rest edges projected on
  the vertex's rest tangent plane); the weight is folded into ``vf_K`` (:mod:`..model`).

The energy is positive definite together with membrane and bending iff
``phi^2 < 4 zeta xi`` (:class:`..material.Material` refuses more).

Gradient
--------
* curvature side: the jet adjoint (:func:`.jet.jet_adjoint`) with ``M = Theta epsbar``;
* strain side: ``dE_c/deps_t = sum_{i in t} area_t/3 K_it cs_i K_it^T`` (face chart) with
  ``cs_i = Theta kap_i = contract(phi, kap_i)``, whose corner gradients are those of the
  membrane, ``F_t S Dinv_t^T``. The reference (:func:`add_face_gradient`) gathers them per
  vertex over its faces; the step folds vertex i's part into i's own stencil entries
  (:func:`add_face_side`: the corners of i's faces are in its stencil), so that the step
  needs no face pass after the vertex pass.

Hessian blocks
--------------
``E_c`` is a cross term: its Hessian in the strains ``(epsbar, kap)`` is
``A_i phi [[0, Q], [Q, 0]]`` (``B(e, k) = e^T Q k``, evaluated as
:func:`..material.bilinear`), indefinite, with positive part
``A_i phi / 2 [[Q, Q], [Q, Q]]``. With ``J_e, J_k`` the Jacobians of ``epsbar_i`` and
``kap_i`` in x_j (Gauss-Newton: the normal held fixed, ``dkap = -W_k,ab n . dx``), the block
is ``A_i phi / 2 (J_e + J_k)^T Q (J_e + J_k)``, positive semi-definite (``psd=True``); with
``psd=False`` it is the Gauss-Newton block ``A_i phi (J_e^T Q J_k + J_k^T Q J_e)``, exact at
a flat rest state.
"""
from __future__ import annotations

import numba as nb
import numpy as np

from ..compiled import kernel
from ..material import bilinear, bilinear_forms, contract
from .jet import gather, jet_energies, jet_fields, stencil_normal
from .membrane import deformation_gradient, green_strain

__all__ = ['energy', 'gradient', 'hessian_blocks', 'epsbar', 'add_face_side', 'corner_rows',
           'strain_average', 'energy_from_fields']


@kernel(inline='always')
def to_vertex_chart(vf_K, q, e11, e12, e22):
    """K^T e K for the vertex-face entry q (vf_K (nvf,4) holds the 2x2 K row by row, with
    the weight sqrt(area_t / 3 A_i) folded in)."""
    k00 = vf_K[q, 0]
    k01 = vf_K[q, 1]
    k10 = vf_K[q, 2]
    k11 = vf_K[q, 3]
    p00 = e11 * k00 + e12 * k10
    p01 = e11 * k01 + e12 * k11
    p10 = e12 * k00 + e22 * k10
    p11 = e12 * k01 + e22 * k11
    return (k00 * p00 + k10 * p10, k00 * p01 + k10 * p11, k01 * p01 + k11 * p11)


@kernel(inline='always')
def to_face_chart(K, t, c, s11, s12, s22):
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
def epsbar(i, x, faces, dinv, vf_ptr, vf_face, vf_K, phi):
    """epsbar_i (11, 12, 22) from the incident faces' strains, recomputed from x; zero
    (not computed) when phi = 0, where nothing reads it."""
    e11 = 0.0
    e12 = 0.0
    e22 = 0.0
    for q in range(vf_ptr[i], vf_ptr[i + 1] if phi != 0.0 else vf_ptr[i]):
        t = vf_face[q]
        f00, f01, f10, f11, f20, f21 = deformation_gradient(x, faces, dinv, t, t)
        a11, a12, a22 = green_strain(f00, f01, f10, f11, f20, f21)
        v11, v12, v22 = to_vertex_chart(vf_K, q, a11, a12, a22)
        e11 += v11
        e12 += v12
        e22 += v22
    return e11, e12, e22


@kernel(inline='always')
def corner_rows(fa, fb, s11, s12, s22, d00, d01, d10, d11):
    """One coordinate (row (fa, fb) of F) of the corner gradients ``F S Dinv^T``:
    (g_1, g_2); corner 0 takes ``-g_1 - g_2``."""
    u0 = fa * s11 + fb * s12
    u1 = fa * s12 + fb * s22
    return u0 * d00 + u1 * d01, u0 * d10 + u1 * d11


@kernel(inline='always')
def add_face_side(i, x, faces, dinv, face_area, K, vf_ptr, vf_face, vf_corner, vf_entry, phi,
                  ainv, k11, k12, k22, contrib, base, stride):
    """The strain side of vertex i's coupling gradient, added to i's own stencil entries:
    for each incident face t, ``S = area_t/3 K cs K^T`` (cs = Theta kap_i) and the corner
    gradients ``F_t S Dinv_t^T`` go to the entries of t's corners (``vf_entry[q, c]``: the
    corner's entry in i's stencil, 0 = the centre), at ``base + stride * entry`` of contrib
    (3, K). Nothing when phi = 0."""
    if phi == 0.0:
        return
    cs11, cs12, cs22 = contract(phi, ainv[i, 0], ainv[i, 1], ainv[i, 2], k11, k12, k22)
    for q in range(nb.uint64(vf_ptr[i]), nb.uint64(vf_ptr[i + 1])):
        t = nb.uint64(vf_face[q])
        a = face_area[t] / 3.0
        s11, s12, s22 = to_face_chart(K, t, vf_corner[q], cs11, cs12, cs22)
        s11 *= a
        s12 *= a
        s22 *= a
        f00, f01, f10, f11, f20, f21 = deformation_gradient(x, faces, dinv, t, t)
        d00 = dinv[t, 0, 0]
        d01 = dinv[t, 0, 1]
        d10 = dinv[t, 1, 0]
        d11 = dinv[t, 1, 1]
        p0 = nb.uint64(base + stride * vf_entry[q, 0])
        p1 = nb.uint64(base + stride * vf_entry[q, 1])
        p2 = nb.uint64(base + stride * vf_entry[q, 2])
        g1, g2 = corner_rows(f00, f01, s11, s12, s22, d00, d01, d10, d11)
        contrib[0, p1] += g1
        contrib[0, p2] += g2
        contrib[0, p0] -= g1 + g2
        g1, g2 = corner_rows(f10, f11, s11, s12, s22, d00, d01, d10, d11)
        contrib[1, p1] += g1
        contrib[1, p2] += g2
        contrib[1, p0] -= g1 + g2
        g1, g2 = corner_rows(f20, f21, s11, s12, s22, d00, d01, d10, d11)
        contrib[2, p1] += g1
        contrib[2, p2] += g2
        contrib[2, p0] -= g1 + g2


@kernel(parallel=True)
def strain_average(x, faces, dinv, vf_ptr, vf_face, vf_K, out):
    """epsbar (n,3) at positions x (every vertex, whatever phi)."""
    for i in nb.prange(out.shape[0]):
        out[i, 0], out[i, 1], out[i, 2] = epsbar(i, x, faces, dinv, vf_ptr, vf_face, vf_K, 1.0)


@kernel(parallel=True)
def add_face_gradient(x, faces, dinv, face_area, K, vf_ptr, vf_face, vf_corner, ainv, kap, phi,
                      grad):
    """grad[j] += the strain side of dE_c/dx_j, gathered over j's incident faces: per face
    ``S_t = sum_{i in t} area_t/3 K_it (Theta kap_i) K_it^T`` and j's corner row of
    ``F_t S_t Dinv_t^T``."""
    for j in nb.prange(grad.shape[0]):
        g0 = 0.0
        g1 = 0.0
        g2 = 0.0
        for q in range(vf_ptr[j], vf_ptr[j + 1]):
            t = vf_face[q]
            c = vf_corner[q]
            a3 = face_area[t] / 3.0
            s11 = 0.0
            s12 = 0.0
            s22 = 0.0
            for cc in range(3):
                i = faces[t, cc]
                cs11, cs12, cs22 = contract(phi, ainv[i, 0], ainv[i, 1], ainv[i, 2],
                                            kap[i, 0], kap[i, 1], kap[i, 2])
                u11, u12, u22 = to_face_chart(K, t, cc, cs11, cs12, cs22)
                s11 += a3 * u11
                s12 += a3 * u12
                s22 += a3 * u22
            if c == 1:
                ga, gb = dinv[t, 0, 0], dinv[t, 0, 1]
            elif c == 2:
                ga, gb = dinv[t, 1, 0], dinv[t, 1, 1]
            else:
                ga = -dinv[t, 0, 0] - dinv[t, 1, 0]
                gb = -dinv[t, 0, 1] - dinv[t, 1, 1]
            f00, f01, f10, f11, f20, f21 = deformation_gradient(x, faces, dinv, t, t)
            sa = s11 * ga + s12 * gb
            sb = s12 * ga + s22 * gb
            g0 += f00 * sa + f01 * sb
            g1 += f10 * sa + f11 * sb
            g2 += f20 * sa + f21 * sb
        grad[j, 0] += g0
        grad[j, 1] += g1
        grad[j, 2] += g2


def _fields(model, coeff, x):
    x = np.ascontiguousarray(x, dtype=np.float64)
    f, vf = model.faces, model.vertex_faces
    eb = np.zeros((len(x), 3))
    strain_average(x, f.corners, f.dinv, vf.ptr, vf.face, vf.K, eb)
    return x, eb


def energy_from_fields(model, coeff, epsbar_: np.ndarray, kap: np.ndarray) -> float:
    """E_c [J] from epsbar (n,3) and kap (n,3)."""
    v = model.vertices
    return float(np.sum(v.dual_area * coeff.phi * bilinear_forms(v.ainv, epsbar_, kap)))


def energy(model, coeff, x: np.ndarray) -> float:
    """E_c [J] at positions x (n,3)."""
    x, eb = _fields(model, coeff, x)
    kap, _ = jet_energies(model, x, 0.0, 0.0, np.zeros(len(x)), eb)
    return energy_from_fields(model, coeff, eb, kap)


def gradient(model, coeff, x: np.ndarray) -> np.ndarray:
    """dE_c/dx (n,3) [N] at positions x: curvature side (jet adjoint) + strain side."""
    x, eb = _fields(model, coeff, x)
    contrib, kap, _ = jet_fields(model, x, 0.0, coeff.phi, np.zeros(len(x)), eb)
    g = np.zeros_like(x)
    gather(model.jets.tr_ptr, model.jets.tr_slot, contrib, g)
    f, vf = model.faces, model.vertex_faces
    add_face_gradient(x, f.corners, f.dinv, f.area, f.K, vf.ptr, vf.face, vf.corner,
                      model.vertices.ainv, kap, coeff.phi, g)
    return g


@kernel(parallel=True)
def entry_blocks(x, st_ptr, st_idx, st_w, faces, dinv, vf_ptr, vf_face, vf_K, vf_entry,
                 dual_area, ainv, phi, psd, blk):
    """Vertex i's Hessian block for each of its stencil entries, blk (K,3,3) (module
    docstring)."""
    for i in nb.prange(x.shape[0]):
        p0 = st_ptr[i]
        p1 = st_ptr[i + 1]
        n0, n1, n2 = stencil_normal(x, st_idx, st_w, p0, p1)
        nrm = (n0, n1, n2)
        i11 = ainv[i, 0]
        i12 = ainv[i, 1]
        i22 = ainv[i, 2]
        # J_e per entry: (entries, 3 strain components, 3 coordinates)
        je = np.zeros((p1 - p0, 3, 3))
        for q in range(vf_ptr[i], vf_ptr[i + 1]):
            t = vf_face[q]
            f = deformation_gradient(x, faces, dinv, t, t)
            for cc in range(3):
                if cc == 1:
                    ga, gb = dinv[t, 0, 0], dinv[t, 0, 1]
                elif cc == 2:
                    ga, gb = dinv[t, 1, 0], dinv[t, 1, 1]
                else:
                    ga = -dinv[t, 0, 0] - dinv[t, 1, 0]
                    gb = -dinv[t, 0, 1] - dinv[t, 1, 1]
                s = vf_entry[q, cc]
                for r in range(3):      # coordinate r of dx
                    fa = f[2 * r]
                    fb = f[2 * r + 1]
                    # face-chart strain of a unit dx_r: (ga fa, (gb fa + ga fb)/2, gb fb)
                    v11, v12, v22 = to_vertex_chart(vf_K, q, ga * fa, 0.5 * (gb * fa + ga * fb),
                                                    gb * fb)
                    je[s, 0, r] += v11
                    je[s, 1, r] += v12
                    je[s, 2, r] += v22
        c = dual_area[i] * phi
        for s in range(p1 - p0):
            k = p0 + s
            # J_k column r: -W_k,ab n_r; (J^T Q J)_rs = B(J[:, r], J[:, s])
            w11 = -st_w[2, k]
            w12 = -st_w[3, k]
            w22 = -st_w[4, k]
            for r in range(3):
                for q in range(3):
                    if psd:
                        blk[k, r, q] = 0.5 * c * bilinear(
                            i11, i12, i22, je[s, 0, r] + w11 * nrm[r], je[s, 1, r] + w12 * nrm[r],
                            je[s, 2, r] + w22 * nrm[r], je[s, 0, q] + w11 * nrm[q],
                            je[s, 1, q] + w12 * nrm[q], je[s, 2, q] + w22 * nrm[q])
                    else:
                        blk[k, r, q] = c * (
                            bilinear(i11, i12, i22, je[s, 0, r], je[s, 1, r], je[s, 2, r],
                                     w11 * nrm[q], w12 * nrm[q], w22 * nrm[q])
                            + bilinear(i11, i12, i22, je[s, 0, q], je[s, 1, q], je[s, 2, q],
                                       w11 * nrm[r], w12 * nrm[r], w22 * nrm[r]))


@kernel(parallel=True)
def gather_blocks(tr_ptr, tr_slot, blk, out):
    """out[j] += sum of the entry blocks of j's transposed stencil."""
    for j in nb.prange(out.shape[0]):
        for q in range(tr_ptr[j], tr_ptr[j + 1]):
            out[j] += blk[tr_slot[q]]


def hessian_blocks(model, coeff, x: np.ndarray, psd: bool = True) -> np.ndarray:
    """Per-vertex blocks of E_c (n,3,3) [N/m]: the positive part of its Gauss-Newton
    Hessian (``psd``, default) or the Gauss-Newton block itself (module docstring)."""
    j, f, vf, v = model.jets, model.faces, model.vertex_faces, model.vertices
    x = np.ascontiguousarray(x, dtype=np.float64)
    blk = np.zeros((len(j.idx), 3, 3))
    entry_blocks(x, j.ptr, j.idx, j.w, f.corners, f.dinv, vf.ptr, vf.face, vf.K, vf.entry,
                 v.dual_area, v.ainv, coeff.phi, psd, blk)
    out = np.zeros((len(x), 3, 3))
    gather_blocks(j.tr_ptr, j.tr_slot, blk, out)
    return out
