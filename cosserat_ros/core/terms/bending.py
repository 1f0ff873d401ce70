"""Bending term: per-vertex curvature change from the cubic jet, with hourglass control.

Energy (seed Eq. 18-19 with Psi = C(xi); doc/theory.md section 2)
--------------------------------------------------------------
``E_b = sum_i A_i xi B(kap_i, kap_i) + sum_i om_i sum_k (rho_k . n_i - sigma_k)^2``

* ``kap_i = -(b_i - B_i)`` (Eq. 17) from the jet of :mod:`.jet`, ``B`` the form of
  :mod:`..material` with the vertex's rest metric, ``A_i`` its dual area; for a flat sheet
  ``xi B(kap, kap) = D/2 [tr(kap)^2 - 2 (1 - nu) det kap]`` with ``D = 6 xi``, nu = 1/3;
* the second sum is the jet's hourglass control (:mod:`.jet`), ``om_i = s xi A_i / h_i^4 /
  S_i`` (``s = constants.JET_STABILIZATION``, ``h_i`` the stencil radius, ``S_i`` its entries
  besides the centre): it vanishes as O(h^4) on smooth fields and stiffens the oscillating
  patterns a least-squares fit cannot see.

Gradient: the exact adjoint of :func:`.jet.jet_adjoint` with ``M = 2 Psi kap``.

Hessian blocks (Gauss-Newton, positive semi-definite)
-----------------------------------------------------
With the normal held fixed, ``db_ab/dx_j = W_k,ab n`` for the stencil entry k of x_j (the
centre included, with its weight) and the residuals' derivative along the normal is the
projection ``R = I - P``, ``P = Phi W`` (the fit's hat matrix over the stencil, Phi the
design rows): ``d rho_s/dx_j = R_sk n``. So vertex i adds to the block of x_j

    ( 2 A_i xi B(w_k, w_k) + 2 om_i R_kk ) n n^T,   R_kk = 1 - phi_k . W_k

(``w_k = (W_k,11, W_k,12, W_k,22)``; the centre's residual coefficient is
``1^T R 1 = S - (sum phi) . (sum W)``). Both coefficients are >= 0, so each block is
positive semi-definite. At a flat rest state (kap = 0, residuals 0, ``r_ab = 0``) this is the
exact diagonal block of the Hessian; elsewhere it drops the terms that rotate the normal
(second order in the curvature change).

Plate operator (the implicit solver's preconditioner)
-----------------------------------------------------
The blocks above are the diagonal of a fourth-order operator; a preconditioner that keeps
only them leaves the conjugate gradients a condition number growing as N^4 in the
bending-dominated band of modes. :func:`plate_matrix` gives the whole operator of the
continuum limit instead: on a flat sheet with the normal deflection w, ``E_b -> D/2 int
((Delta w)^2 - 2 (1 - nu) det grad grad w) dA``, whose second term integrates to the
boundary (Kirchhoff plate; Timoshenko & Woinowsky-Krieger 1959, Eq. 118), so the bulk of
E_b is ``D/2 w^T L^T M^-1 L w`` with L the cotangent Laplacian (Pinkall & Polthier 1993;
positive semi-definite, ``(L w)_i = sum_j (cot a_ij + cot b_ij) / 2 (w_i - w_j)``) and M
the dual areas, over the vertices off the boundary (a boundary vertex's row of L is not
a Laplacian): ``D L^T M^-1 L`` per coordinate, built once from the rest mesh.
"""
from __future__ import annotations

import numba as nb
import numpy as np

from ..compiled import kernel
from ..material import bilinear
from .jet import gather, jet_energies, jet_fields, stencil_normal

__all__ = ['energy', 'gradient', 'hessian_blocks', 'energy_from_fields', 'plate_matrix']


def energy_from_fields(model, coeff, kap: np.ndarray, estab: np.ndarray) -> float:
    """E_b [J] from the curvature changes kap (n,3) and hourglass energies estab (n,):
    sum_i A_i xi B(kap_i, kap_i) + estab_i."""
    v = model.vertices
    return float(_energy_sum(v.dual_area, v.ainv, kap, estab, coeff.xi))


@kernel()
def _energy_sum(dual_area, ainv, kap, estab, xi):
    s = 0.0
    for i in range(kap.shape[0]):
        k11 = kap[i, 0]
        k12 = kap[i, 1]
        k22 = kap[i, 2]
        s += (dual_area[i] * xi * bilinear(ainv[i, 0], ainv[i, 1], ainv[i, 2], k11, k12, k22,
                                           k11, k12, k22) + estab[i])
    return s


def energy(model, coeff, x: np.ndarray) -> float:
    """E_b [J] at positions x (n,3)."""
    kap, estab = jet_energies(model, x, coeff.xi, 0.0, coeff.stab, np.zeros((len(x), 3)))
    return energy_from_fields(model, coeff, kap, estab)


def gradient(model, coeff, x: np.ndarray) -> np.ndarray:
    """dE_b/dx (n,3) [N] at positions x."""
    contrib, _, _ = jet_fields(model, x, coeff.xi, 0.0, coeff.stab, np.zeros((len(x), 3)))
    g = np.zeros_like(x)
    gather(model.jets.tr_ptr, model.jets.tr_slot, contrib, g)
    return g


@kernel(parallel=True)
def gn_coefficients(x, st_ptr, st_idx, st_w, st_uv, dual_area, ainv, stab, xi, coef, normals):
    """Per CSR stencil entry k of vertex i: the Gauss-Newton coefficient ``coef[k]`` of
    ``n_i n_i^T`` in the block of x_{st_idx[k]} (module docstring), and n_i (n,3)."""
    for i in nb.prange(x.shape[0]):
        p0 = st_ptr[i]
        p1 = st_ptr[i + 1]
        n0, n1, n2 = stencil_normal(x, st_idx, st_w, p0, p1)
        normals[i, 0] = n0
        normals[i, 1] = n1
        normals[i, 2] = n2
        b = 2.0 * dual_area[i] * xi
        om2 = 2.0 * stab[i]
        i11 = ainv[i, 0]
        i12 = ainv[i, 1]
        i22 = ainv[i, 2]
        ssum = np.zeros(9)      # sum of the design rows (physical units)
        wsum = np.zeros(9)      # sum of the weights over the entries besides the centre
        for k in range(p0 + 1, p1):
            u = st_uv[0, k]
            v = st_uv[1, k]
            phi = (u, v, 0.5 * u * u, u * v, 0.5 * v * v, u ** 3 / 6.0, 0.5 * u * u * v,
                   0.5 * u * v * v, v ** 3 / 6.0)
            pw = 0.0
            for c in range(9):
                pw += phi[c] * st_w[c, k]
                ssum[c] += phi[c]
                wsum[c] += st_w[c, k]
            w11 = st_w[2, k]
            w12 = st_w[3, k]
            w22 = st_w[4, k]
            coef[k] = (b * bilinear(i11, i12, i22, w11, w12, w22, w11, w12, w22)
                       + om2 * (1.0 - pw))
        w11 = st_w[2, p0]
        w12 = st_w[3, p0]
        w22 = st_w[4, p0]
        sp = 0.0
        for c in range(9):
            sp += ssum[c] * wsum[c]
        coef[p0] = (b * bilinear(i11, i12, i22, w11, w12, w22, w11, w12, w22)
                    + om2 * ((p1 - p0 - 1) - sp))


@kernel(parallel=True)
def gather_nn_blocks(tr_ptr, tr_slot, owner, coef, normals, out):
    """out[j] += sum over j's transposed stencil entries q of coef * n n^T (n the entry
    owner's normal)."""
    for j in nb.prange(out.shape[0]):
        for q in range(tr_ptr[j], tr_ptr[j + 1]):
            k = tr_slot[q]
            i = owner[k]
            c = coef[k]
            for r in range(3):
                for s in range(3):
                    out[j, r, s] += c * normals[i, r] * normals[i, s]


def hessian_blocks(model, coeff, x: np.ndarray) -> np.ndarray:
    """Gauss-Newton blocks of E_b per vertex (n,3,3) [N/m], positive semi-definite."""
    j = model.jets
    x = np.ascontiguousarray(x, dtype=np.float64)
    coef = np.zeros(len(j.idx))
    normals = np.zeros_like(x)
    gn_coefficients(x, j.ptr, j.idx, j.w, j.uv, model.vertices.dual_area, model.vertices.ainv,
                    coeff.stab, coeff.xi, coef, normals)
    out = np.zeros((len(x), 3, 3))
    gather_nn_blocks(j.tr_ptr, j.tr_slot, j.owner, coef, normals, out)
    return out


def cotangent_laplacian(points: np.ndarray, corners: np.ndarray):
    """The cotangent Laplacian L (n, n) of a triangle mesh, scipy.sparse CSR,
    dimensionless, positive semi-definite (module docstring)."""
    import scipy.sparse as sp
    n = len(points)
    rows, cols, vals = [], [], []
    for a in range(3):
        b, c = corners[:, (a + 1) % 3], corners[:, (a + 2) % 3]
        u = points[b] - points[corners[:, a]]
        v = points[c] - points[corners[:, a]]
        # half the cotangent of the angle at corner a, on the edge (b, c) opposite it
        w = 0.5 * np.einsum('ij,ij->i', u, v) / np.linalg.norm(np.cross(u, v), axis=1)
        rows += [b, c, b, c]
        cols += [c, b, b, c]
        vals += [-w, -w, w, w]
    return sp.csr_matrix((np.concatenate(vals), (np.concatenate(rows), np.concatenate(cols))),
                         shape=(n, n))


def plate_matrix(model):
    """``L^T M^-1 L`` (n, n) [1/m^2], scipy.sparse CSR, from the rest mesh (module
    docstring): ``6 xi`` times it, on each coordinate, is the Kirchhoff plate's Hessian."""
    import scipy.sparse as sp
    lap = cotangent_laplacian(np.asarray(model.mesh.vertices, dtype=np.float64),
                              np.asarray(model.faces.corners))
    # a boundary vertex's row is not a Laplacian (it sums the normal slope across the
    # edge): with it, w^T K w of a deflection vanishing on the edge grew as N
    inner = ~model.mesh.boundary_vertices
    lap = lap[inner]
    return (lap.T @ sp.diags(1.0 / model.vertices.dual_area[inner]) @ lap).tocsr()
