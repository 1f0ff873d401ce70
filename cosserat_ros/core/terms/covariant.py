"""The seed's covariant route (Sec. 5.3-5.5): the internal force from the balance law itself.

Per vertex, from the jet geometry (:mod:`..geometry`) and vertex strains ``eps = (a - A)/2``,
``kap = -(b - B)``:

* ``N* = 2 Phi eps + Theta kap``, ``M = 2 Psi kap + Theta eps`` (Eq. 27 with the factor 2,
  doc/theory.md section 2);
* ``N^ab = N*^ab - M^bg a^ad b_dg`` and ``N^3b = M^ba|_a`` (Eq. 28, the covariant derivative
  of Eq. 15 with least-squares partial derivatives);
* force vectors ``N^b = N^ab a_a + N^3b a_3`` (Eq. 26);
* nodal force ``A_i N^a|_a = A_i (d_a N^a + Gamma^a_al N^l)`` (Eq. 14, 24).

It discretises the same balance law as the variational terms (interior force densities
converge to theirs) but is not the gradient of an energy: it has no energy and no Hessian
block, its operator is non-symmetric with growing modes (pinned plates diverge at any dt,
``docs/validation.md``), and it needs every boundary vertex pinned (seed Sec. 6.4, 7). It is
kept for comparison (``ClothSimulator(discretisation='covariant')``), and replaces the three
variational terms when selected.
"""
from __future__ import annotations

from typing import NamedTuple

import numba as nb
import numpy as np

from ..compiled import kernel
from ..material import contract
from .jet import cross as _cross

__all__ = ['forces', 'resultants']


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



class Work(NamedTuple):
    """Scratch of the covariant force (n vertices)."""

    basis: np.ndarray     # (n, 3, 3) rows a_1, a_2, a_3
    chris: np.ndarray     # (n, 2, 2, 2) Gamma^g_ab
    mres: np.ndarray      # (n, 2, 2) M^ab
    nres: np.ndarray      # (n, 2, 2) N^ab
    nvec: np.ndarray      # (n, 2, 3) force vectors N^b

    @classmethod
    def zeros(cls, n: int) -> 'Work':
        return cls(np.zeros((n, 3, 3)), np.zeros((n, 2, 2, 2)), np.zeros((n, 2, 2)),
                   np.zeros((n, 2, 2)), np.zeros((n, 2, 3)))


@kernel()
def covariant_forces(x, jets, vertices, st_T, zeta, xi, phi, cw, force):
    """Seed-route internal force (n,3) [N] at positions x, into ``force``."""
    st_ptr, st_idx, st_w = jets.ptr, jets.idx, jets.w
    covariant_resultants(x, st_ptr, st_idx, st_w, vertices.rest_a, vertices.ainv,
                         vertices.rest_b, zeta, xi, phi, cw.basis, cw.chris, cw.mres, cw.nres)
    covariant_force_vectors(st_ptr, st_idx, st_w, st_T, cw.basis, cw.chris, cw.mres, cw.nres,
                            cw.nvec)
    covariant_divergence(st_ptr, st_idx, st_w, st_T, cw.chris, cw.nvec, vertices.dual_area,
                         force)


def forces(model, coeff, x: np.ndarray) -> np.ndarray:
    """The seed route's internal force N^a|_a per dual cell (n,3) [N] at positions x."""
    out = np.zeros_like(x)
    covariant_forces(np.ascontiguousarray(x, dtype=np.float64), model.jets, model.vertices,
                     model.st_T, coeff.zeta, coeff.xi, coeff.phi, Work.zeros(len(x)), out)
    return out


def resultants(model, coeff, x: np.ndarray):
    """Per-vertex basis, Christoffel symbols, M^ab, N^ab and force vectors N^b (n,2,3)."""
    cw = Work.zeros(len(x))
    j, v = model.jets, model.vertices
    x = np.ascontiguousarray(x, dtype=np.float64)
    covariant_resultants(x, j.ptr, j.idx, j.w, v.rest_a, v.ainv, v.rest_b, coeff.zeta,
                         coeff.xi, coeff.phi, cw.basis, cw.chris, cw.mres, cw.nres)
    covariant_force_vectors(j.ptr, j.idx, j.w, model.st_T, cw.basis, cw.chris, cw.mres,
                            cw.nres, cw.nvec)
    return cw
