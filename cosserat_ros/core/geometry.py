"""Differential geometry of the Cosserat surface at every vertex (seed Sec. 2, 5.1, 5.2).

Charts
------
Each vertex ``i`` carries a chart fixed at rest: the rest tangent plane with orthonormal
axes ``E1, E2`` and normal ``N`` (``frames[i]`` rows). ``E1`` is the global X axis projected
onto the tangent plane (Y when X is nearly normal), ``E2 = N x E1``. A neighbour ``j`` has
chart coordinates ``x^1 = (R_j - R_i) . E1``, ``x^2 = (R_j - R_i) . E2``. For a flat rest
sheet in the XY plane with counter-clockwise faces the chart is exactly ``x^1 = X``,
``x^2 = Y`` at every vertex, so components compare directly with analytic values. The
coordinates are convected: they belong to the material point and never change.

Cubic jet (the default, convergent estimator)
---------------------------------------------
Over the stencil of vertex ``i`` (its 2-ring; the 3-ring for boundary vertices, whose
one-sided 2-ring is too thin; grown further where a fit is ill-conditioned) we fit, by least
squares in chart coordinates and through ``r_i``,

    r(x) ~ r_i + a_1 x^1 + a_2 x^2 + 1/2 r_11 (x^1)^2 + r_12 x^1 x^2 + 1/2 r_22 (x^2)^2
           + (cubic terms r_111 ... r_222)

The fit is linear in the positions, so its coefficients are fixed weighted sums

    [a_1, a_2, r_11, r_12, r_22, r_111, ...] = sum_k W[k, :] x[stencil[k]]   (i included)

with the weights ``W`` precomputed once from the rest mesh (9 rows; the geometry uses the
first five). From them (Eq. 8, 10, 11, 13):

    a_3 = n = a_1 x a_2 / |a_1 x a_2|           a_ab = a_a . a_b
    b_ab = n . r_ab                               Gamma^g_ab = a^gd a_d . r_ab   (Sec. 2.6)

Exact for quadratic surfaces (the seed's saddle); with the cubic terms the second
derivatives are O(h^2) on any stencil, boundary included (a quadratic jet is only O(h) on
one-sided or irregular stencils). See ``docs/validation.md`` section 1.

Seed estimator (``curvature="seed"``, for comparison only)
-----------------------------------------------------------
Seed Sec. 5.2 (Batagelo & Wu): area-weighted vertex normals, a local frame
``{t, b, n}`` with ``t`` along the first incident edge, and least squares of the normal
differences along every incident edge, ``-(dn . t) = S_tt t_j + S_tb b_j``,
``-(dn . b) = S_tb t_j + S_bb b_j`` (the Weingarten relation, Eq. 12 with the sign of
doc/theory.md section 1), then ``b_ab = (a_a . e_k)(a_b . e_l) S_kl``. Its error does not
fall with refinement: the O(h) error of the vertex normals becomes an O(1) curvature error.

Sign convention: ``b_ab = n . r_ab`` with ``n`` along ``a_1 x a_2`` (Eq. 10, 11); a sphere
with outward normals has ``b_ab = -a_ab / R``, i.e. mean curvature ``H = a^ab b_ab / 2 = -1/R``
and Gaussian curvature ``K = det b / det a = 1/R^2``.
"""
from __future__ import annotations

from dataclasses import dataclass
import warnings

import numba as nb
import numpy as np

from . import compiled  # noqa: F401  (drops stale kernel caches before these load)
from .constants import JET_MAX_RINGS, JET_RCOND_MIN, JET_TEMPLATE_TOL
from .mesh import ClothMesh, csr_from_pairs, k_ring

__all__ = ['JetOperator', 'Geometry', 'build_jet_operator', 'compute_geometry',
           'CURVATURE_ESTIMATORS']

CURVATURE_ESTIMATORS = ('jet', 'seed')

#: Index order of the five jet coefficients.
JET_A1, JET_A2, JET_R11, JET_R12, JET_R22 = range(5)
#: rows of the (cubic) jet operator: a_1, a_2, r_11, r_12, r_22, r_111, r_112, r_122, r_222
NJET = 9


@dataclass(frozen=True)
class JetOperator:
    """Precomputed least-squares derivative weights (the discrete operators of the jet).

    ``coeff[i, c] = sum_{k in st_ptr[i]:st_ptr[i+1]} st_w[c, k] * x[st_idx[k]]``, with
    ``c`` = a_1, a_2, r_11, r_12, r_22, r_111, r_112, r_122, r_222. The weights are stored
    coefficient-major, so one coefficient's weights over a stencil are contiguous (the
    vertex kernel reads them as vectors). The fit weights are uniform over a stencil. The
    transposed CSR (``tr_ptr``, ``tr_slot``) lists, for every vertex ``j``, the stencil
    entries ``k`` (of any vertex) whose fit uses ``x[j]``: the adjoint (a discrete
    divergence) is a gather.

    Entry order: the centre, then the 1-ring in fan order (:func:`fan_order`), then the
    rest of the stencil ascending; ``vf_order`` lists each vertex's faces in the same fan
    order, face f having the 1-ring entries f and f + 1 as its other corners. Two vertices
    with the same fan (valence, open or closed) then have each face's corners at the same
    entries, which the step's coupling uses (``fast/lanes.py``).

    Stencil templates: vertices whose stencils have the same shape (chart coordinates equal
    to ``JET_TEMPLATE_TOL`` of the stencil radius, in the same order) share the weights and
    chart coordinates of the first such vertex, ``template[i]``. On a structured sheet that
    is nearly every vertex, and the shared weights differ from a vertex's own by round-off
    (~1e-13 relative); everything downstream (rest curvature, rest residuals, forces) uses
    the shared ones, so the rest state stays exactly stress-free. The vertex pass then
    reads one copy of the weights for many vertices (less memory traffic).
    """

    frames: np.ndarray    # (n, 3, 3) rest chart axes E1, E2, N (rows)
    st_ptr: np.ndarray    # (n+1,) int64
    st_idx: np.ndarray    # (K,) int64, stencil vertices, centre included
    st_w: np.ndarray      # (NJET, K) float64 weights, coefficient-major
    st_x: np.ndarray      # (K, 2) float64 chart coordinates of the stencil vertex
    radius: np.ndarray    # (n,) float64 rms stencil radius h_i [m]
    tr_ptr: np.ndarray    # (n+1,) int64
    tr_slot: np.ndarray   # (K,) int64 index k of the entry in st_*
    rings: np.ndarray     # (n,) int64 ring depth used per vertex
    template: np.ndarray  # (n,) int64 vertex whose weights this vertex shares (itself if none)
    vf_order: np.ndarray  # (V,) int64 the mesh's vertex-face pairs in fan order (fan_order)


def rest_frames(mesh: ClothMesh) -> np.ndarray:
    """Rest chart axes (E1, E2, N) per vertex, (n, 3, 3): see the module docstring."""
    nrm = mesh.vertex_normals
    ex = np.array([1.0, 0.0, 0.0])
    ey = np.array([0.0, 1.0, 0.0])
    e1 = ex[None, :] - nrm[:, :1] * nrm
    bad = np.linalg.norm(e1, axis=1) < 0.3
    e1[bad] = ey[None, :] - nrm[bad, 1:2] * nrm[bad]
    e1 /= np.linalg.norm(e1, axis=1)[:, None]
    e2 = np.cross(nrm, e1)
    return np.stack([e1, e2, nrm], axis=1)


#: the direction [rad] from which a closed fan's first neighbour is counted: off every
#: direction of a regular grid, so that round-off cannot change which one comes first
FAN_START = 0.123


def fan_order(mesh: ClothMesh, frames: np.ndarray):
    """Every vertex's 1-ring and faces in fan order: counter-clockwise (the faces' own
    orientation), face f with corners (i, n_f, n_{f+1}); an open fan (a boundary vertex)
    from its boundary edge, a closed one from the neighbour first counter-clockwise from
    :data:`FAN_START` in the vertex's rest chart. A vertex whose faces form no single fan
    (two fans meeting at a point) keeps the sorted 1-ring and the mesh's face order.

    Returns (ring (list of n arrays), vf_order (V,) int64: a permutation of the mesh's
    vertex-face pairs, each vertex's range in fan order)."""
    X, f = mesh.vertices, mesh.faces
    ring = []
    vf_order = np.arange(len(mesh.vf_face), dtype=np.int64)
    for i in range(mesh.n_vertices):
        q0, q1 = mesh.vf_ptr[i], mesh.vf_ptr[i + 1]
        faces, corners = mesh.vf_face[q0:q1], mesh.vf_corner[q0:q1]
        nxt = {int(f[t, (c + 1) % 3]): (int(f[t, (c + 2) % 3]), q)
               for t, c, q in zip(faces, corners, range(q0, q1))}
        nbrs = mesh.ring1[mesh.ring1_ptr[i]:mesh.ring1_ptr[i + 1]]
        heads = set(nxt) - {k for k, _ in nxt.values()}
        if len(nxt) != q1 - q0 or len(heads) > 1:
            ring.append(nbrs.copy())
            continue
        if heads:
            start = heads.pop()
        else:
            d = X[list(nxt)] - X[i]
            ang = np.arctan2(d @ frames[i, 1], d @ frames[i, 0])
            start = list(nxt)[int(np.argmin((ang - FAN_START) % (2 * np.pi)))]
        order, qs, j = [start], [], start
        while j in nxt and len(qs) < q1 - q0:
            j, q = nxt[j]
            qs.append(q)
            if j != start:
                order.append(j)
        if len(qs) != q1 - q0 or len(order) != len(nbrs):
            ring.append(nbrs.copy())
            continue
        ring.append(np.array(order, dtype=np.int64))
        vf_order[q0:q1] = qs
    return ring, vf_order


def design_matrix(u: np.ndarray, v: np.ndarray) -> np.ndarray:
    """Columns of the cubic jet fit at chart coordinates (u, v), shape (..., NJET): u, v,
    u^2/2, uv, v^2/2, u^3/6, u^2 v/2, u v^2/2, v^3/6."""
    cols = [u, v, 0.5 * u * u, u * v, 0.5 * v * v,
            u ** 3 / 6, 0.5 * u * u * v, 0.5 * u * v * v, v ** 3 / 6]
    return np.stack(cols, axis=-1)


def _fit_weights(d: np.ndarray, frame: np.ndarray, mask: np.ndarray):
    """Batched LS weights. d (b, S, 3) offsets R_j - R_i; mask (b, S) valid entries.

    Returns weights (b, S, NJET) in physical units, chart coords (b, S, 2), rcond (b,)
    and the stencil radius s (b,) [m].
    """
    u = np.einsum('bsk,bk->bs', d, frame[:, 0])
    v = np.einsum('bsk,bk->bs', d, frame[:, 1])
    w = mask.astype(np.float64)
    cnt = np.maximum(w.sum(axis=1), 1.0)
    s = np.sqrt(((u * u + v * v) * w).sum(axis=1) / cnt)
    s = np.where(s > 0, s, 1.0)
    sw = np.sqrt(w)
    phi = design_matrix(u / s[:, None], v / s[:, None]) * sw[..., None]
    m = np.einsum('bsa,bsc->bac', phi, phi)
    ev = np.linalg.eigvalsh(m)
    rcond = ev[:, 0] / np.maximum(ev[:, -1], 1e-300)
    ok = rcond > JET_RCOND_MIN
    nc = phi.shape[-1]
    coef = np.zeros((len(d), nc, d.shape[1]))
    if ok.any():
        coef[ok] = np.linalg.solve(m[ok], np.transpose(phi[ok], (0, 2, 1)))
    for b in np.flatnonzero(~ok):
        coef[b] = np.linalg.pinv(m[b], rcond=1e-10) @ phi[b].T
    coef = coef * sw[:, None, :]
    scale = np.stack([1 / s, 1 / s] + [1 / s ** 2] * 3 + [1 / s ** 3] * (nc - 5), axis=1)
    wts = np.transpose(coef * scale[:, :, None], (0, 2, 1))
    return wts, np.stack([u, v], axis=-1), rcond, s


def build_jet_operator(mesh: ClothMesh) -> JetOperator:
    """Cubic-jet weights over the 2-ring of every vertex (grown where needed)."""
    n = mesh.n_vertices
    X = mesh.vertices
    frames = rest_frames(mesh)
    stencils = [None] * n
    ptr, idx = mesh.ring2_ptr, mesh.ring2
    sizes = np.diff(ptr)
    smax = int(sizes.max())
    pad = np.full((n, smax), -1, dtype=np.int64)
    pos = np.arange(smax)[None, :] < sizes[:, None]
    pad[pos] = idx
    mask = pad >= 0
    d = X[np.where(mask, pad, 0)] - X[:, None, :]
    wts, chart, rcond, radius = _fit_weights(d, frames, mask)
    rings = np.full(n, 2, dtype=np.int64)
    # one-sided stencils: boundary vertices fit over their 3-ring (a cubic jet needs the
    # points spread over more than the thin one-sided 2-ring); ill-conditioned fits grow
    bad = np.flatnonzero((rcond <= JET_RCOND_MIN) | mesh.boundary_vertices)
    for i in range(n):
        sel = mask[i]
        stencils[i] = (pad[i, sel], wts[i, sel], chart[i, sel])
    for i in bad:
        for k in range(3, JET_MAX_RINGS + 1):
            nb_ = k_ring(mesh.ring1_ptr, mesh.ring1, int(i), k)
            w_i, c_i, rc, rad_i = _fit_weights((X[nb_] - X[i])[None], frames[i:i + 1],
                                               np.ones((1, len(nb_)), dtype=bool))
            stencils[i] = (nb_, w_i[0], c_i[0])
            radius[i] = rad_i[0]
            rings[i] = k
            if rc[0] > JET_RCOND_MIN and (k >= 3 or not mesh.boundary_vertices[i]):
                break
        else:
            warnings.warn(f'vertex {i}: even its {JET_MAX_RINGS}-ring cannot determine a '
                          'quadratic (a strip one triangle wide?); its curvature across the '
                          'degenerate direction is taken as zero', stacklevel=3)
    # the 1-ring first, in fan order, then the rest ascending (the weights of a
    # least-squares fit follow their points)
    ring, vf_order = fan_order(mesh, frames)
    for i, (nbr, w, c) in enumerate(stencils):
        first = ring[i]
        rest = np.setdiff1d(nbr, first, assume_unique=True)
        where = {int(v): k for k, v in enumerate(nbr)}
        perm = np.array([where[int(v)] for v in np.concatenate([first, rest])], dtype=np.int64)
        stencils[i] = (nbr[perm], w[perm], c[perm])
    template = _stencil_templates([s[2] for s in stencils], radius)
    stencils = [(nbr, stencils[t][1], stencils[t][2])
                for (nbr, _, _), t in zip(stencils, template)]
    lens = np.array([len(s[0]) + 1 for s in stencils], dtype=np.int64)
    st_ptr = np.zeros(n + 1, dtype=np.int64)
    np.cumsum(lens, out=st_ptr[1:])
    st_idx = np.empty(st_ptr[-1], dtype=np.int64)
    st_w = np.empty((NJET, st_ptr[-1]))
    st_x = np.zeros((st_ptr[-1], 2))
    for i, (nbr, w, c) in enumerate(stencils):
        a, b = st_ptr[i], st_ptr[i + 1]
        st_idx[a] = i
        st_w[:, a] = -w.sum(axis=0)
        st_idx[a + 1:b] = nbr
        st_w[:, a + 1:b] = w.T
        st_x[a + 1:b] = c
    src = np.repeat(np.arange(n, dtype=np.int64), lens)
    tr_ptr, _, order = csr_from_pairs(st_idx, src, n)
    return JetOperator(frames=frames, st_ptr=st_ptr, st_idx=st_idx, st_w=st_w, st_x=st_x,
                       radius=radius, tr_ptr=tr_ptr, tr_slot=order.astype(np.int64),
                       rings=rings, template=template, vf_order=vf_order)


def _stencil_templates(charts, radius) -> np.ndarray:
    """template[i]: the first vertex whose stencil chart coordinates equal those of i (same
    count and order) to JET_TEMPLATE_TOL of i's stencil radius; i itself if none."""
    first = {}
    template = np.empty(len(charts), dtype=np.int64)
    for i, c in enumerate(charts):
        key = np.round(c / (JET_TEMPLATE_TOL * radius[i])).astype(np.int64).tobytes()
        template[i] = first.setdefault(key, i)
    return template


# --------------------------------------------------------------------------- kernels

@nb.njit(cache=True, inline='always')
def _cross(a0, a1, a2, b0, b1, b2):
    return a1 * b2 - a2 * b1, a2 * b0 - a0 * b2, a0 * b1 - a1 * b0


@nb.njit(cache=True, parallel=True)
def jet_coefficients(x, st_ptr, st_idx, st_w, out):
    """out[i, c, :] = sum_k st_w[c, k] x[st_idx[k]]: a_1, a_2, r_11, r_12, r_22 (n, 5, 3)."""
    n = x.shape[0]
    for i in nb.prange(n):
        for c in range(5):
            s0 = 0.0
            s1 = 0.0
            s2 = 0.0
            for k in range(st_ptr[i], st_ptr[i + 1]):
                w = st_w[c, k]
                j = st_idx[k]
                s0 += w * x[j, 0]
                s1 += w * x[j, 1]
                s2 += w * x[j, 2]
            out[i, c, 0] = s0
            out[i, c, 1] = s1
            out[i, c, 2] = s2


@nb.njit(cache=True, parallel=True)
def jet_geometry(jet, basis, metric, curvature, christoffel):
    """Basis, metric, curvature and Christoffel symbols from jet coefficients (Eq. 8-13).

    basis (n,3,3) rows a_1, a_2, a_3; metric a_ab (n,2,2); curvature b_ab = n . r_ab
    (n,2,2); christoffel[i, g, a, b] = a^gd a_d . r_ab (n,2,2,2).
    """
    n = jet.shape[0]
    for i in nb.prange(n):
        a1 = jet[i, 0]
        a2 = jet[i, 1]
        c0, c1, c2 = _cross(a1[0], a1[1], a1[2], a2[0], a2[1], a2[2])
        cn = np.sqrt(c0 * c0 + c1 * c1 + c2 * c2)
        if cn > 0.0:
            c0 /= cn
            c1 /= cn
            c2 /= cn
        for k in range(3):
            basis[i, 0, k] = a1[k]
            basis[i, 1, k] = a2[k]
        basis[i, 2, 0] = c0
        basis[i, 2, 1] = c1
        basis[i, 2, 2] = c2
        g11 = a1[0] * a1[0] + a1[1] * a1[1] + a1[2] * a1[2]
        g12 = a1[0] * a2[0] + a1[1] * a2[1] + a1[2] * a2[2]
        g22 = a2[0] * a2[0] + a2[1] * a2[1] + a2[2] * a2[2]
        metric[i, 0, 0] = g11
        metric[i, 0, 1] = g12
        metric[i, 1, 0] = g12
        metric[i, 1, 1] = g22
        det = g11 * g22 - g12 * g12
        inv11 = g22 / det
        inv12 = -g12 / det
        inv22 = g11 / det
        for ab in range(3):
            r = jet[i, 2 + ab]
            al = 0 if ab < 2 else 1
            be = 0 if ab == 0 else 1
            bval = c0 * r[0] + c1 * r[1] + c2 * r[2]
            curvature[i, al, be] = bval
            curvature[i, be, al] = bval
            p1 = a1[0] * r[0] + a1[1] * r[1] + a1[2] * r[2]
            p2 = a2[0] * r[0] + a2[1] * r[1] + a2[2] * r[2]
            g1 = inv11 * p1 + inv12 * p2
            g2 = inv12 * p1 + inv22 * p2
            christoffel[i, 0, al, be] = g1
            christoffel[i, 0, be, al] = g1
            christoffel[i, 1, al, be] = g2
            christoffel[i, 1, be, al] = g2


@nb.njit(cache=True, parallel=True)
def seed_curvature(x, faces, vf_ptr, vf_face, ring1_ptr, ring1, basis, out):
    """Seed Sec. 5.2 curvature: normal differences along the 1-ring, least squares.

    Vertex normals are area-weighted face normals; the local frame is t along the first
    1-ring edge (projected), b = n x t. Result in the convected basis (basis rows a_1,
    a_2), out (n, 2, 2).
    """
    n = x.shape[0]
    vn = np.zeros((n, 3))
    for i in nb.prange(n):
        s0 = 0.0
        s1 = 0.0
        s2 = 0.0
        for k in range(vf_ptr[i], vf_ptr[i + 1]):
            f = vf_face[k]
            p = x[faces[f, 0]]
            q = x[faces[f, 1]]
            r = x[faces[f, 2]]
            c0, c1, c2 = _cross(q[0] - p[0], q[1] - p[1], q[2] - p[2],
                                r[0] - p[0], r[1] - p[1], r[2] - p[2])
            s0 += c0
            s1 += c1
            s2 += c2
        nn = np.sqrt(s0 * s0 + s1 * s1 + s2 * s2)
        vn[i, 0] = s0 / nn
        vn[i, 1] = s1 / nn
        vn[i, 2] = s2 / nn
    for i in nb.prange(n):
        nx_, ny_, nz_ = vn[i, 0], vn[i, 1], vn[i, 2]
        j0 = ring1[ring1_ptr[i]]
        e0 = x[j0, 0] - x[i, 0]
        e1 = x[j0, 1] - x[i, 1]
        e2 = x[j0, 2] - x[i, 2]
        dp = e0 * nx_ + e1 * ny_ + e2 * nz_
        t0 = e0 - dp * nx_
        t1 = e1 - dp * ny_
        t2 = e2 - dp * nz_
        tn = np.sqrt(t0 * t0 + t1 * t1 + t2 * t2)
        t0 /= tn
        t1 /= tn
        t2 /= tn
        b0, b1, b2 = _cross(nx_, ny_, nz_, t0, t1, t2)
        # normal equations for (S_tt, S_tb, S_bb)
        m00 = 0.0
        m01 = 0.0
        m02 = 0.0
        m11 = 0.0
        m12 = 0.0
        m22 = 0.0
        r0 = 0.0
        r1 = 0.0
        r2 = 0.0
        for k in range(ring1_ptr[i], ring1_ptr[i + 1]):
            j = ring1[k]
            d0 = x[j, 0] - x[i, 0]
            d1 = x[j, 1] - x[i, 1]
            d2 = x[j, 2] - x[i, 2]
            tj = d0 * t0 + d1 * t1 + d2 * t2
            bj = d0 * b0 + d1 * b1 + d2 * b2
            dn0 = vn[j, 0] - nx_
            dn1 = vn[j, 1] - ny_
            dn2 = vn[j, 2] - nz_
            yt = -(dn0 * t0 + dn1 * t1 + dn2 * t2)
            yb = -(dn0 * b0 + dn1 * b1 + dn2 * b2)
            # row (tj, bj, 0) . S = yt ; row (0, tj, bj) . S = yb
            m00 += tj * tj
            m01 += tj * bj
            m11 += bj * bj + tj * tj
            m12 += tj * bj
            m22 += bj * bj
            r0 += tj * yt
            r1 += bj * yt + tj * yb
            r2 += bj * yb
        # solve symmetric 3x3 [[m00,m01,m02],[m01,m11,m12],[m02,m12,m22]] s = r
        det = (m00 * (m11 * m22 - m12 * m12) - m01 * (m01 * m22 - m12 * m02)
               + m02 * (m01 * m12 - m11 * m02))
        i00 = (m11 * m22 - m12 * m12) / det
        i01 = -(m01 * m22 - m02 * m12) / det
        i02 = (m01 * m12 - m02 * m11) / det
        i11 = (m00 * m22 - m02 * m02) / det
        i12 = -(m00 * m12 - m01 * m02) / det
        i22 = (m00 * m11 - m01 * m01) / det
        stt = i00 * r0 + i01 * r1 + i02 * r2
        stb = i01 * r0 + i11 * r1 + i12 * r2
        sbb = i02 * r0 + i12 * r1 + i22 * r2
        for al in range(2):
            pa_t = basis[i, al, 0] * t0 + basis[i, al, 1] * t1 + basis[i, al, 2] * t2
            pa_b = basis[i, al, 0] * b0 + basis[i, al, 1] * b1 + basis[i, al, 2] * b2
            for be in range(2):
                pb_t = basis[i, be, 0] * t0 + basis[i, be, 1] * t1 + basis[i, be, 2] * t2
                pb_b = basis[i, be, 0] * b0 + basis[i, be, 1] * b1 + basis[i, be, 2] * b2
                out[i, al, be] = (pa_t * pb_t * stt + (pa_t * pb_b + pa_b * pb_t) * stb
                                  + pa_b * pb_b * sbb)


@dataclass(frozen=True)
class Geometry:
    """Per-vertex geometry of the current configuration, all in the rest charts.

    Every array is indexed by vertex first. ``christoffel[i, g, a, b]`` is
    Gamma^g_ab. ``strain`` is eps_ab = (a_ab - A_ab)/2 and ``bending_strain`` is
    kappa_ab = -(b_ab - B_ab) (Eq. 17).
    """

    basis: np.ndarray            # (n, 3, 3) rows a_1, a_2, a_3
    metric: np.ndarray           # (n, 2, 2) a_ab
    curvature: np.ndarray        # (n, 2, 2) b_ab
    christoffel: np.ndarray      # (n, 2, 2, 2) Gamma^g_ab
    second_derivatives: np.ndarray  # (n, 3, 3) r_11, r_12, r_22
    rest_metric: np.ndarray      # (n, 2, 2) A_ab
    rest_curvature: np.ndarray   # (n, 2, 2) B_ab
    strain: np.ndarray           # (n, 2, 2) eps_ab
    bending_strain: np.ndarray   # (n, 2, 2) kappa_ab
    estimator: str

    @property
    def normal(self) -> np.ndarray:
        """Unit normals a_3, (n, 3)."""
        return self.basis[:, 2]

    @property
    def inverse_metric(self) -> np.ndarray:
        """a^ab, (n, 2, 2)."""
        return np.linalg.inv(self.metric)

    @property
    def mean_curvature(self) -> np.ndarray:
        """H = a^ab b_ab / 2, (n,) [1/m]; negative on a sphere with outward normals."""
        return 0.5 * np.einsum('nab,nab->n', self.inverse_metric, self.curvature)

    @property
    def gaussian_curvature(self) -> np.ndarray:
        """K = det(b_ab) / det(a_ab), (n,) [1/m^2]."""
        return np.linalg.det(self.curvature) / np.linalg.det(self.metric)


def compute_geometry(x: np.ndarray, mesh: ClothMesh, jet: JetOperator,
                     curvature: str = 'jet', rest: 'Geometry | None' = None) -> Geometry:
    """Evaluate the geometry of configuration ``x`` (n, 3) in the rest charts of ``jet``."""
    if curvature not in CURVATURE_ESTIMATORS:
        raise ValueError(f'curvature estimator must be one of {CURVATURE_ESTIMATORS}, '
                         f'got {curvature!r}')
    n = x.shape[0]
    coeff = np.empty((n, 5, 3))
    jet_coefficients(x, jet.st_ptr, jet.st_idx, jet.st_w[:5], coeff)
    basis = np.empty((n, 3, 3))
    metric = np.empty((n, 2, 2))
    curv = np.empty((n, 2, 2))
    chris = np.empty((n, 2, 2, 2))
    jet_geometry(coeff, basis, metric, curv, chris)
    if curvature == 'seed':
        seed_curvature(x, mesh.faces, mesh.vf_ptr, mesh.vf_face, mesh.ring1_ptr, mesh.ring1,
                       basis, curv)
    if rest is None:
        rest_metric, rest_curv = metric, curv
    else:
        rest_metric, rest_curv = rest.metric, rest.curvature
    return Geometry(basis=basis, metric=metric, curvature=curv, christoffel=chris,
                    second_derivatives=coeff[:, 2:].copy(), rest_metric=rest_metric,
                    rest_curvature=rest_curv, strain=0.5 * (metric - rest_metric),
                    bending_strain=-(curv - rest_curv), estimator=curvature)
