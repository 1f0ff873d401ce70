"""Membrane term: constant-strain triangles (seed Eq. 17-19, 22 in each triangle's chart).

Energy
------
``E_m = sum_t area_t W_m(eps_t)``, with, in the orthonormal rest chart of triangle t
(``A = I`` there, so the form ``B`` of :mod:`..material` is the plain one):

    F_t   = [x_1 - x_0, x_2 - x_0] Dinv_t            (3x2 deformation gradient)
    eps_t = (F_t^T F_t - I) / 2                        (Green strain, Eq. 17)
    W_m   = zeta B(eps, eps) = zeta [tr(eps)^2 + 2 eps:eps]

A per-triangle strain sees every in-plane mode (doc/theory.md section 7: collocated vertex
gradients are blind to the checkerboard), so the membrane has no hourglass mode.

Gradient
--------
With the stress times area ``S_t = area_t N*_t``, ``N* = dW/deps = 2 zeta (tr(eps) I +
2 eps)`` (Eq. 22, the factor 2 kept: doc/theory.md section 2), the corner gradients are

    [g_1 g_2] = F_t S_t Dinv_t^T,   g_0 = -g_1 - g_2            (dE_m/dx at the corners)

Hessian block
-------------
For corner c, ``dF = dx (x) G_c`` (``G_1, G_2`` the rows of Dinv, ``G_0 = -G_1 - G_2``) and
``deps = sym(F^T dF)``, linear in dx: ``deps_11 = a F_:1 . dx``, ``deps_22 = b F_:2 . dx``,
``deps_12 = (b F_:1 + a F_:2) . dx / 2`` with ``G_c = (a, b)``. Then

    d2E_m/dx_c2 = (G_c S G_c^T) I_3  +  area 2 zeta L^T Q L

with ``L`` those three rows and ``Q = [[3, 0, 1], [0, 4, 0], [1, 0, 3]]`` on (11, 12, 22)
(``d2W = 2 zeta Q``). The stress part ``G_c S G_c^T`` is the only one that can be
negative (a compressed triangle); :func:`hessian_blocks` with ``psd=True`` (default)
replaces S by its positive part, which leaves a stretched triangle's block exact and
makes every block positive semi-definite (as implicit cloth solvers do, e.g. Teran et al.
2005, "Robust quasistatic finite elements").

Between two corners c, d of a face the same rows give the off-diagonal block,

    d2E_m/dx_c dx_d = (G_c S G_d^T) I_3  +  area 2 zeta L_c^T Q L_d,

which :func:`hessian_matrix` assembles, with S's positive part, into the whole sparse
(3n x 3n) matrix: positive semi-definite (a sum over faces of ``J^T Q J`` and ``S+ (x)
G^T G``), exact for stretched triangles; the implicit solver factors it.

The per-vertex kernels below gather over the vertex's incident faces (``VertexFaces``),
recomputing each face's strain, so they never scatter; the step (``fast/step.py``) runs
:func:`face_membrane` once per face instead and gathers the corner gradients.
"""
from __future__ import annotations

import numba as nb
import numpy as np

from ..compiled import kernel

__all__ = ['energy', 'gradient', 'hessian_blocks', 'hessian_matrix', 'compression_stress',
           'add_compression_product', 'compressed_faces', 'face_membrane',
           'deformation_gradient', 'corner_gradient_row']


@kernel(inline='always')
def deformation_gradient(x, faces, dinv, t, td):
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
def green_strain(f00, f01, f10, f11, f20, f21):
    """eps = (F^T F - I) / 2 as (11, 12, 22) (Eq. 17)."""
    return (0.5 * (f00 * f00 + f10 * f10 + f20 * f20 - 1.0),
            0.5 * (f00 * f01 + f10 * f11 + f20 * f21),
            0.5 * (f01 * f01 + f11 * f11 + f21 * f21 - 1.0))


@kernel(inline='always')
def strain_energy_density(zeta, e11, e12, e22):
    """W_m = zeta B(eps, eps) = zeta [tr(eps)^2 + 2 eps:eps] [J/m^2] (A = I)."""
    tr = e11 + e22
    return zeta * (tr * tr + 2.0 * (e11 * e11 + 2.0 * e12 * e12 + e22 * e22))


@kernel(inline='always')
def stress_times_area(c, e11, e12, e22):
    """S = area N* with ``c = 2 zeta area``: ``c (tr(eps) I + 2 eps)`` as (11, 12, 22)."""
    tr = e11 + e22
    return c * (tr + 2.0 * e11), c * (2.0 * e12), c * (tr + 2.0 * e22)


@kernel(inline='always')
def corner_gradient_row(td, ts, k, fa, fb, s11, s12, s22, dinv, fgrad, add):
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
def face_membrane(t, td, ts, x, faces, dinv, face_area, zeta, fgrad):
    """Face t: the membrane's corner gradients fgrad[ts] (3,3) = d(area W_m)/dx_corner
    (ts = t, or the face's ring slot in the tiled step); returns the strain (11, 12, 22).
    The corners are faces[t], the rest shape dinv[td] and face_area[td] (td = t, or in
    the step's vertex pass the face's row in the table of distinct rest shapes)."""
    f00, f01, f10, f11, f20, f21 = deformation_gradient(x, faces, dinv, t, td)
    e11, e12, e22 = green_strain(f00, f01, f10, f11, f20, f21)
    s11, s12, s22 = stress_times_area(face_area[td] * 2.0 * zeta, e11, e12, e22)
    corner_gradient_row(td, ts, 0, f00, f01, s11, s12, s22, dinv, fgrad, False)
    corner_gradient_row(td, ts, 1, f10, f11, s11, s12, s22, dinv, fgrad, False)
    corner_gradient_row(td, ts, 2, f20, f21, s11, s12, s22, dinv, fgrad, False)
    return e11, e12, e22


@kernel(inline='always')
def _corner_weights(dinv, t, c):
    """Row G_c of the corner's gradient operator: dF = dx_c (x) G_c (G_0 = -G_1 - G_2)."""
    if c == 1:
        return dinv[t, 0, 0], dinv[t, 0, 1]
    if c == 2:
        return dinv[t, 1, 0], dinv[t, 1, 1]
    return -dinv[t, 0, 0] - dinv[t, 1, 0], -dinv[t, 0, 1] - dinv[t, 1, 1]


@kernel(parallel=True)
def face_energies(x, faces, dinv, face_area, zeta, eps, out):
    """Per face: strain eps (m,3) and energy area W_m (m,) [J]."""
    for t in nb.prange(faces.shape[0]):
        f00, f01, f10, f11, f20, f21 = deformation_gradient(x, faces, dinv, t, t)
        e11, e12, e22 = green_strain(f00, f01, f10, f11, f20, f21)
        eps[t, 0] = e11
        eps[t, 1] = e12
        eps[t, 2] = e22
        out[t] = face_area[t] * strain_energy_density(zeta, e11, e12, e22)


@kernel(parallel=True)
def add_gradient(x, faces, dinv, face_area, vf_ptr, vf_face, vf_corner, zeta, grad):
    """grad[j] += dE_m/dx_j (n,3): over j's incident faces, each face's strain recomputed."""
    for j in nb.prange(grad.shape[0]):
        g0 = 0.0
        g1 = 0.0
        g2 = 0.0
        for q in range(vf_ptr[j], vf_ptr[j + 1]):
            t = vf_face[q]
            a, b = _corner_weights(dinv, t, vf_corner[q])
            f00, f01, f10, f11, f20, f21 = deformation_gradient(x, faces, dinv, t, t)
            e11, e12, e22 = green_strain(f00, f01, f10, f11, f20, f21)
            s11, s12, s22 = stress_times_area(face_area[t] * 2.0 * zeta, e11, e12, e22)
            # F S G_c for the corner's row G_c = (a, b)
            sa = s11 * a + s12 * b
            sb = s12 * a + s22 * b
            g0 += f00 * sa + f01 * sb
            g1 += f10 * sa + f11 * sb
            g2 += f20 * sa + f21 * sb
        grad[j, 0] += g0
        grad[j, 1] += g1
        grad[j, 2] += g2


@kernel(inline='always')
def _positive_stress(s11, s12, s22):
    """The positive part of the symmetric 2x2 S = (s11, s12, s22)."""
    tr = 0.5 * (s11 + s22)
    rad = np.sqrt(0.25 * (s11 - s22) ** 2 + s12 * s12)
    l1 = tr + rad
    l2 = tr - rad
    if l2 >= 0.0:
        return s11, s12, s22
    if l1 <= 0.0:
        return 0.0, 0.0, 0.0
    if s12 != 0.0:              # l1 v v^T with v the eigenvector of l1
        v0 = l1 - s22
        v1 = s12
    elif s11 >= s22:
        v0 = 1.0
        v1 = 0.0
    else:
        v0 = 0.0
        v1 = 1.0
    nv = v0 * v0 + v1 * v1
    return l1 * v0 * v0 / nv, l1 * v0 * v1 / nv, l1 * v1 * v1 / nv


@kernel(parallel=True)
def add_hessian_blocks(x, faces, dinv, face_area, vf_ptr, vf_face, vf_corner, zeta, psd, out):
    """out[j] += d2E_m/dx_j2 (n,3,3) over j's incident faces (module docstring, *Hessian
    block*); ``psd``: the stress part from the positive part of S."""
    for j in nb.prange(out.shape[0]):
        h = np.zeros((3, 3))
        for q in range(vf_ptr[j], vf_ptr[j + 1]):
            t = vf_face[q]
            a, b = _corner_weights(dinv, t, vf_corner[q])
            f00, f01, f10, f11, f20, f21 = deformation_gradient(x, faces, dinv, t, t)
            e11, e12, e22 = green_strain(f00, f01, f10, f11, f20, f21)
            area = face_area[t]
            s11, s12, s22 = stress_times_area(area * 2.0 * zeta, e11, e12, e22)
            if psd:     # positive part of the symmetric 2x2 S
                s11, s12, s22 = _positive_stress(s11, s12, s22)
            geo = a * (s11 * a + s12 * b) + b * (s12 * a + s22 * b)
            for k in range(3):
                h[k, k] += geo
            # d eps_11 = a (F_:0 . dx), d eps_22 = b (F_:1 . dx),
            # d eps_12 = (b F_:0 + a F_:1) . dx / 2
            c0 = (a * f00, a * f10, a * f20)
            c2 = (b * f01, b * f11, b * f21)
            c1 = (0.5 * (b * f00 + a * f01), 0.5 * (b * f10 + a * f11),
                  0.5 * (b * f20 + a * f21))
            w = area * 2.0 * zeta
            for r in range(3):
                for s in range(3):
                    # Q: tr^2 + 2 (e11^2 + 2 e12^2 + e22^2) -> d2/de2 / 2:
                    # [[3, 0, 1], [0, 4, 0], [1, 0, 3]] on (e11, e12, e22)
                    h[r, s] += w * (3.0 * c0[r] * c0[s] + 3.0 * c2[r] * c2[s]
                                    + c0[r] * c2[s] + c2[r] * c0[s]
                                    + 4.0 * c1[r] * c1[s])
        for r in range(3):
            for s in range(3):
                out[j, r, s] += h[r, s]


# ------------------------------------------------------------------------- term API

def energy(model, coeff, x: np.ndarray) -> float:
    """E_m [J] at positions x (n,3)."""
    f = model.faces
    out = np.empty(len(f.corners))
    face_energies(x, f.corners, f.dinv, f.area, coeff.zeta, np.empty((len(f.corners), 3)),
                  out)
    return float(out.sum())


def gradient(model, coeff, x: np.ndarray) -> np.ndarray:
    """dE_m/dx (n,3) [N] at positions x."""
    f, vf = model.faces, model.vertex_faces
    g = np.zeros_like(x)
    add_gradient(x, f.corners, f.dinv, f.area, vf.ptr, vf.face, vf.corner, coeff.zeta, g)
    return g


def hessian_blocks(model, coeff, x: np.ndarray, psd: bool = True) -> np.ndarray:
    """Per-vertex blocks d2E_m/dx_j2 (n,3,3) [N/m]; ``psd`` clamps the stress part
    (exact for stretched triangles, positive semi-definite always)."""
    f, vf = model.faces, model.vertex_faces
    h = np.zeros((len(x), 3, 3))
    add_hessian_blocks(x, f.corners, f.dinv, f.area, vf.ptr, vf.face, vf.corner, coeff.zeta,
                       psd, h)
    return h



@kernel(parallel=True)
def face_hessians(x, faces, dinv, face_area, zeta, psd, out):
    """out[t, c, d] (m,3,3,3,3) = d2(area_t W_m)/dx_c dx_d of face t (module docstring)."""
    for t in nb.prange(faces.shape[0]):
        f00, f01, f10, f11, f20, f21 = deformation_gradient(x, faces, dinv, t, t)
        e11, e12, e22 = green_strain(f00, f01, f10, f11, f20, f21)
        w = face_area[t] * 2.0 * zeta
        s11, s12, s22 = stress_times_area(w, e11, e12, e22)
        if psd:
            s11, s12, s22 = _positive_stress(s11, s12, s22)
        ga = np.empty(3)
        gb = np.empty(3)
        L = np.empty((3, 3, 3))          # corner, strain row (11, 12, 22), coordinate
        for c in range(3):
            a, b = _corner_weights(dinv, t, c)
            ga[c] = a
            gb[c] = b
            L[c, 0, 0] = a * f00
            L[c, 0, 1] = a * f10
            L[c, 0, 2] = a * f20
            L[c, 2, 0] = b * f01
            L[c, 2, 1] = b * f11
            L[c, 2, 2] = b * f21
            L[c, 1, 0] = 0.5 * (b * f00 + a * f01)
            L[c, 1, 1] = 0.5 * (b * f10 + a * f11)
            L[c, 1, 2] = 0.5 * (b * f20 + a * f21)
        for c in range(3):
            for d in range(3):
                geo = (ga[c] * (s11 * ga[d] + s12 * gb[d])
                       + gb[c] * (s12 * ga[d] + s22 * gb[d]))
                for r in range(3):
                    for q in range(3):
                        h = w * (3.0 * L[c, 0, r] * L[d, 0, q] + 3.0 * L[c, 2, r] * L[d, 2, q]
                                 + L[c, 0, r] * L[d, 2, q] + L[c, 2, r] * L[d, 0, q]
                                 + 4.0 * L[c, 1, r] * L[d, 1, q])
                        if r == q:
                            h += geo
                        out[t, c, d, r, q] = h


@kernel(parallel=True)
def compression_stress(x, faces, dinv, face_area, zeta, out):
    """out[t] (m,3) = ``S+_t - S_t`` as (11, 12, 22): minus the negative part of face t's
    stress times area (zero for a triangle stretched in both directions; positive
    semi-definite always). What the clamp of ``psd=True`` adds to the exact Hessian:
    ``d2E_m+ - d2E_m = G(S+ - S) (x) I_3`` with ``G(T)_cd = G_c T G_d^T`` (module
    docstring); :func:`add_compression_product` applies it."""
    for t in nb.prange(faces.shape[0]):
        f00, f01, f10, f11, f20, f21 = deformation_gradient(x, faces, dinv, t, t)
        e11, e12, e22 = green_strain(f00, f01, f10, f11, f20, f21)
        s11, s12, s22 = stress_times_area(face_area[t] * 2.0 * zeta, e11, e12, e22)
        p11, p12, p22 = _positive_stress(s11, s12, s22)
        out[t, 0] = p11 - s11
        out[t, 1] = p12 - s12
        out[t, 2] = p22 - s22


def compressed_faces(tens: np.ndarray) -> np.ndarray:
    """The faces (int64 indices) with a compressed stress in ``tens`` (m,3, from
    :func:`compression_stress`): those whose row is not zero."""
    return np.flatnonzero(np.any(tens != 0.0, axis=1))


@kernel()
def _compression_scatter(faces, dinv, tens, which, q, out):
    for i in range(which.shape[0]):
        t = which[i]
        t11 = tens[t, 0]
        t12 = tens[t, 1]
        t22 = tens[t, 2]
        for k in range(3):
            ua = 0.0
            ub = 0.0
            for c in range(3):
                a, b = _corner_weights(dinv, t, c)
                qc = q[faces[t, c], k]
                ua += a * qc
                ub += b * qc
            s0 = t11 * ua + t12 * ub
            s1 = t12 * ua + t22 * ub
            for c in range(3):
                a, b = _corner_weights(dinv, t, c)
                out[faces[t, c], k] += a * s0 + b * s1


def add_compression_product(model, tens: np.ndarray, which: np.ndarray, q: np.ndarray,
                            out: np.ndarray) -> None:
    """out (n,3) += ``(G(T) (x) I_3) q``: the geometric stiffness of ``tens`` (m,3, from
    :func:`compression_stress`) times q (n,3), over the faces ``which`` (from
    :func:`compressed_faces`; the others' rows are zero). One serial pass over those
    faces, scattering to their corners: a cloth in tension has few (the bench's square sheet
    settling: 1-2% of its faces), and a pass over all faces and a gather over every
    vertex took 0.8 ms a CG iteration at 160 x 160 for them."""
    f = model.faces
    _compression_scatter(f.corners, f.dinv, tens, which, q, out)


def hessian_matrix(model, coeff, x: np.ndarray, psd: bool = True):
    """d2E_m/dx2 as a scipy.sparse CSR matrix (3n, 3n) [N/m], row 3 j + k for coordinate k
    of vertex j (module docstring: every corner pair of every face; ``psd``: the stress
    part from S's positive part). Its diagonal blocks are :func:`hessian_blocks`."""
    import scipy.sparse as sp
    f = model.faces
    c = f.corners
    n = len(x)
    blk = np.empty((len(c), 3, 3, 3, 3))
    face_hessians(np.ascontiguousarray(x, dtype=np.float64), c, f.dinv, f.area, coeff.zeta,
                  psd, blk)
    rows, cols = hessian_pattern(c)
    return sp.csr_matrix((blk.ravel(), (rows, cols)), shape=(3 * n, 3 * n))


def hessian_pattern(corners: np.ndarray):
    """(rows, cols) of :func:`face_hessians`' entries, raveled, in the 3n x 3n matrix."""
    c = corners
    rows = (3 * c[:, :, None, None, None] + np.arange(3)[None, None, None, :, None])
    cols = (3 * c[:, None, :, None, None] + np.arange(3)[None, None, None, None, :])
    shape = (len(c), 3, 3, 3, 3)
    return (np.broadcast_to(rows, shape).ravel(), np.broadcast_to(cols, shape).ravel())
