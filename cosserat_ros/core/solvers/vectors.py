"""Compiled vector work of the implicit solver's conjugate gradients (:mod:`.implicit`).

Each CG iteration of :meth:`.implicit.ImplicitSolver._cg` does, beside its one internal
force and one preconditioner solve, about twenty passes over (n, 3) arrays: the finite
difference's product, the updates of the iterate and residual, their dot products and
norms, and the split preconditioner's change to each vertex's frame and back. In numpy
each is a separate pass with its own temporary; at 160 x 160 they took ~2.5 ms a CG
iteration (~16 ms of a 191 ms step; all of numpy's vector work between the kernels was
~25% of it, docs/performance.md). Here they are fused, a few passes an iteration.

One thread each: these passes are bound by memory, and on two cores the parallel
versions were no faster (160 x 160: 130-138 ms a step either way) while they took 7.9 s
to compile cold against 3.0 (docs/performance.md). Their sums are in vertex order.
"""
from __future__ import annotations

import numpy as np

from ..compiled import kernel

__all__ = ['dot', 'fd_product', 'cg_update', 'direction', 'inertia_residual',
           'inertia_energy', 'residual_measure', 'to_frames', 'from_frames', 'vertex_frames',
           'warm']


@kernel()
def dot(a, b):
    """sum(a * b) over two (n, 3) arrays."""
    s = 0.0
    for i in range(a.shape[0]):
        s += a[i, 0] * b[i, 0] + a[i, 1] * b[i, 1] + a[i, 2] * b[i, 2]
    return s


@kernel()
def fd_product(diag, d, fq, f, eps, out):
    """out = diag d - (fq - f) / eps: ``(m / dt^2 + c / dt) d`` plus the elastic
    Hessian's product by the forward difference of the internal force (``fq`` at
    ``x + eps d``, ``f`` at x); diag (n,)."""
    for i in range(d.shape[0]):
        for k in range(3):
            out[i, k] = diag[i] * d[i, k] - (fq[i, k] - f[i, k]) / eps


@kernel()
def cg_update(p, zr, d, ad, a):
    """p += a d, zr -= a ad; returns |zr|^2 (the step of CG along d)."""
    s = 0.0
    for i in range(p.shape[0]):
        for k in range(3):
            p[i, k] += a * d[i, k]
            r = zr[i, k] - a * ad[i, k]
            zr[i, k] = r
            s += r * r
    return s


@kernel()
def direction(d, z, beta):
    """d = z + beta d (the next conjugate direction); returns max |d| (the finite
    difference's scale; inf where d holds a NaN)."""
    m = 0.0
    for i in range(d.shape[0]):
        for k in range(3):
            v = z[i, k] + beta * d[i, k]
            d[i, k] = v
            if v != v:
                m = np.inf
            m = max(m, abs(v))
    return m


@kernel()
def inertia_residual(mass, damp, x, y, xn, f, dt, out):
    """out = m (x - y) / dt^2 + c (x - xn) / dt - f: the residual of the incremental
    potential without the drag (:mod:`.implicit`); mass, damp (n,)."""
    for i in range(x.shape[0]):
        a = mass[i] / (dt * dt)
        b = damp[i] / dt
        for k in range(3):
            out[i, k] = a * (x[i, k] - y[i, k]) + b * (x[i, k] - xn[i, k]) - f[i, k]


@kernel()
def inertia_energy(mass, damp, x, y, xn, dt):
    """sum_i m_i |x_i - y_i|^2 / (2 dt^2) + c_i |x_i - xn_i|^2 / (2 dt): the incremental
    potential's inertia and damping (:mod:`.implicit`)."""
    s = 0.0
    for i in range(x.shape[0]):
        d0 = x[i, 0] - y[i, 0]
        d1 = x[i, 1] - y[i, 1]
        d2 = x[i, 2] - y[i, 2]
        e0 = x[i, 0] - xn[i, 0]
        e1 = x[i, 1] - xn[i, 1]
        e2 = x[i, 2] - xn[i, 2]
        s += (0.5 * mass[i] / (dt * dt) * (d0 * d0 + d1 * d1 + d2 * d2)
              + 0.5 * damp[i] / dt * (e0 * e0 + e1 * e1 + e2 * e2))
    return s


@kernel()
def residual_measure(r, denom):
    """(max_i |r_i|, max_i |r_i| / denom_i) of a residual r (n,3), NaN where numpy's
    max would give NaN (a NaN residual; the ratio also for inf / inf)."""
    m = 0.0
    q = 0.0
    for i in range(r.shape[0]):
        a = np.sqrt(r[i, 0] * r[i, 0] + r[i, 1] * r[i, 1] + r[i, 2] * r[i, 2])
        b = a / denom[i]
        # a NaN is not a residual, as in numpy's max (numba's max would skip it): the
        # caller stops; inf / inf is an infinite start residual's
        if a != a:
            return np.nan, np.nan
        if b != b:
            q = np.nan
        m = max(m, a)
        if q == q:
            q = max(q, b)
    return m, q


@kernel()
def to_frames(frame, r, zt, zn):
    """r (n, 3) in each vertex's frame (n, 3, 3; columns two tangent axes and the
    normal): zt (2n,) its two tangential components, zn (n,) its normal one, both
    float32 (what the split preconditioner's factors solve in)."""
    for i in range(r.shape[0]):
        t0 = frame[i, 0, 0] * r[i, 0] + frame[i, 1, 0] * r[i, 1] + frame[i, 2, 0] * r[i, 2]
        t1 = frame[i, 0, 1] * r[i, 0] + frame[i, 1, 1] * r[i, 1] + frame[i, 2, 1] * r[i, 2]
        nn = frame[i, 0, 2] * r[i, 0] + frame[i, 1, 2] * r[i, 1] + frame[i, 2, 2] * r[i, 2]
        zt[2 * i] = t0
        zt[2 * i + 1] = t1
        zn[i] = nn


@kernel()
def from_frames(frame, zt, zn, pinned, out):
    """The inverse of :func:`to_frames` into out (n, 3) float64, 0 on the ``pinned``
    vertices."""
    for i in range(out.shape[0]):
        if pinned[i]:
            out[i, 0] = 0.0
            out[i, 1] = 0.0
            out[i, 2] = 0.0
            continue
        t0 = np.float64(zt[2 * i])
        t1 = np.float64(zt[2 * i + 1])
        nn = np.float64(zn[i])
        for k in range(3):
            out[i, k] = frame[i, k, 0] * t0 + frame[i, k, 1] * t1 + frame[i, k, 2] * nn


def warm() -> None:
    """Compile every kernel here on tiny arrays (the cold start's warm-up,
    ``core/warmup.py``), so that a node's first implicit step does not."""
    a = np.zeros((2, 3))
    b = np.ones((2, 3))
    frame = np.tile(np.eye(3), (2, 1, 1))
    dot(a, b)
    fd_product(np.ones(2), a, b, a, 1.0, b)
    cg_update(a, b.copy(), a, b, 0.5)
    direction(a, b, 0.5)
    inertia_residual(np.ones(2), np.ones(2), a, b, a, b, 0.1, a.copy())
    inertia_energy(np.ones(2), np.ones(2), a, b, a, 0.1)
    residual_measure(b, np.ones(2))
    # the implicit solver's kernels in the terms (the bending energy's sum of the line
    # search, the compression product of projected Newton)
    from ..terms.bending import _energy_sum
    from ..terms.membrane import _compression_scatter
    _energy_sum(np.ones(2), b, a, np.ones(2), 1.0)
    _compression_scatter(np.array([[0, 1, 0]]), np.zeros((1, 2, 2)), b, np.zeros(1, np.int64),
                         a, b.copy())
    zt, zn = np.zeros(4, np.float32), np.zeros(2, np.float32)
    to_frames(frame, b, zt, zn)
    from_frames(frame, zt, zn, np.zeros(2, np.bool_), a)


def vertex_frames(x: np.ndarray, corners: np.ndarray) -> np.ndarray:
    """(n, 3, 3): each vertex's frame at positions x, its columns two tangent axes and the
    unit normal, the normal the area-weighted mean of its faces' (+z where they cancel to
    round-off or it has none; ``.implicit.ImplicitSolver._preconditioner``)."""
    n = len(x)
    fn = np.cross(x[corners[:, 1]] - x[corners[:, 0]], x[corners[:, 2]] - x[corners[:, 0]])
    at = corners.ravel()
    nrm = np.stack([np.bincount(at, weights=np.repeat(fn[:, k], 3), minlength=n)
                    for k in range(3)], axis=1)
    size = np.linalg.norm(nrm, axis=1)
    # where the faces' normals (nearly) cancel, as on the crease of a cloth folded flat,
    # their sum is round-off: +z then, as for a vertex without faces
    total = np.bincount(at, weights=np.repeat(np.linalg.norm(fn, axis=1), 3), minlength=n)
    flat = ~(size > 1e-9 * total) | ~(size > 1e-300)
    nrm[flat] = (0.0, 0.0, 1.0)
    size[flat] = 1.0
    nrm /= size[:, None]
    # the first tangent: the coordinate axis least along the normal, made normal to it
    e = np.eye(3)[np.argmin(np.abs(nrm), axis=1)]
    t1 = e - np.sum(e * nrm, axis=1)[:, None] * nrm
    t1 /= np.linalg.norm(t1, axis=1)[:, None]
    return np.stack([t1, np.cross(nrm, t1), nrm], axis=2)
