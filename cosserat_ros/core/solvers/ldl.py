"""The preconditioner's triangular solves as ``L D L^T``, compiled and free of the GIL.

The implicit solver factors its preconditioner P (symmetric positive definite: the
inertia plus positive semi-definite stiffness blocks) with SuperLU in symmetric mode,
with a symmetric fill-reducing ordering and no pivoting (``diag_pivot_thresh=0``). Then
SuperLU's ``Pr P Pc = L U`` has ``Pr = Pc^T`` (the same permutation on the rows and the
columns) and ``U = D L^T`` with ``D = diag(U)`` (Golub & Van Loan 2013, Sec. 4.1: the LU
factors of a symmetric matrix without pivoting), so ``L`` and ``D`` are the whole
factor and a solve reads half the entries of SuperLU's own (which reads L and U)::

    P z = r:   y = Pc^T r,   L w = y,   w <- D^-1 w,   L^T u = w,   z = Pc u

``L`` is kept by supernodes: runs of consecutive columns whose rows below the diagonal
are the same (each column's structure is the next one's plus its own diagonal row),
stored as one dense row-major block each (the columns' rows, the triangle's upper part
zero), so that the forward solve is one dot product per row of a block and the backward
one an axpy per row, with one row index per row and not per entry.

Why not SuperLU's own solve (docs/performance.md, tenth session; the bench's square sheet at
160 x 160, the split preconditioner's two parts): a pair of solves inside a step took
10.4 ms through SuperLU (the normal part in a worker thread) and takes 4.4 ms here. The
tangential part alone, back to back: 5.1-7.4 ms through SuperLU, 3.0 here; after an
80 MB stream through the cache, as inside a step: 6.8-9.0 against 5.0. SuperLU's solve
reads L and U, twice the entries, with a row index per entry of U, and it takes the GIL
back to allocate its result, so its two parts in two threads did not overlap whole.
Here both parts run at once in one parallel kernel (:func:`solve_pair`).
"""
from __future__ import annotations

import numba as nb
import numpy as np

from ..compiled import REDUCTION, kernel

U64 = nb.uint64

__all__ = ['LDLFactor', 'symmetric_lu', 'solve_pair', 'warm']


@kernel()
def _supernodes(indptr, indices):
    """The first column of each supernode of the lower triangular CSC ``L`` (the
    diagonal first in each column), and the number of columns at the end: column j + 1
    joins j's supernode where its rows are exactly j's without j, in the same order."""
    n = len(indptr) - 1
    start = np.empty(n + 1, np.int64)
    ns = 0
    start[0] = 0
    for j in range(n - 1):
        a0, a1 = indptr[j], indptr[j + 1]
        b0, b1 = indptr[j + 1], indptr[j + 2]
        same = b1 - b0 == a1 - a0 - 1 and indices[a0] == j and indices[b0] == j + 1
        if same:
            for q in range(b1 - b0):
                if indices[a0 + 1 + q] != indices[b0 + q]:
                    same = False
                    break
        if not same:
            ns += 1
            start[ns] = j + 1
    ns += 1
    start[ns] = n
    return start[:ns + 1].copy()


@kernel()
def _pack(indptr, indices, data, start):
    """Each supernode as a dense row-major block: returns its rows (all of them, the
    diagonal ones first), their offsets by supernode, the blocks (float32) and their
    offsets. Column k of a supernode holds the rows from its diagonal on; the entries
    above the diagonal are 0 and never read."""
    ns = len(start) - 1
    rptr = np.zeros(ns + 1, np.int64)
    vptr = np.zeros(ns + 1, np.int64)
    for s in range(ns):
        c0 = start[s]
        m = indptr[c0 + 1] - indptr[c0]
        rptr[s + 1] = rptr[s] + m
        vptr[s + 1] = vptr[s] + m * (start[s + 1] - c0)
    rows = np.empty(rptr[ns], np.int32)
    blk = np.zeros(vptr[ns], np.float32)
    for s in range(ns):
        c0 = start[s]
        w = start[s + 1] - c0
        a0 = indptr[c0]
        for i in range(indptr[c0 + 1] - a0):
            rows[rptr[s] + i] = indices[a0 + i]
        for k in range(w):
            p0 = indptr[c0 + k]
            for q in range(indptr[c0 + k + 1] - p0):
                blk[vptr[s] + (q + k) * w + k] = data[p0 + q]
    return rows, rptr, blk, vptr


@kernel(nogil=True, fastmath=REDUCTION)
def _solve(perm, start, rows, rptr, blk, vptr, dinv, acc, y, b, out):
    """out = P^-1 b by the factor's arrays (module docstring); y (n,) float64 and acc
    (widest supernode,) are scratch. Each block is read row by row, in the order it is
    stored: the forward solve a dot product a row (triangle and rows below), the
    backward one an axpy a row; the dot products may be summed in SIMD lanes
    (``REDUCTION``: a preconditioner's solve needs no fixed summation order). Every
    index is unsigned (``compiled.py``). Against signed indices, the triangles solved by
    columns and the sums in order: 160 x 160, the square sheet's tangential part, 3.0 ms a solve
    against 7.4 (docs/performance.md)."""
    n = U64(len(b))
    for j in range(n):
        y[U64(perm[j])] = b[j]
    ns = U64(len(start) - 1)
    one = U64(1)
    for s in range(ns):                         # L w = y
        c0 = U64(start[s])
        w = U64(start[s + one]) - c0
        v0 = U64(vptr[s])
        for i in range(one, w):                 # the dense triangle
            t = 0.0
            base = v0 + i * w
            for k in range(i):
                t += blk[base + k] * y[c0 + k]
            y[c0 + i] -= t
        base = v0 + w * w
        for i in range(U64(rptr[s]) + w, U64(rptr[s + one])):   # the rows below
            t = 0.0
            for k in range(w):
                t += blk[base + k] * y[c0 + k]
            y[U64(rows[i])] -= t
            base += w
    for j in range(n):
        y[j] *= dinv[j]
    for s1 in range(ns):                        # L^T u = D^-1 w, the last supernode first
        s = ns - one - s1
        c0 = U64(start[s])
        w = U64(start[s + one]) - c0
        v0 = U64(vptr[s])
        for k in range(w):
            acc[k] = 0.0
        base = v0 + w * w
        for i in range(U64(rptr[s]) + w, U64(rptr[s + one])):   # the rows below
            yi = y[U64(rows[i])]
            for k in range(w):
                acc[k] += blk[base + k] * yi
            base += w
        for i1 in range(w):                     # the triangle, its last row first
            i = w - one - i1
            yi = y[c0 + i] - acc[i]
            y[c0 + i] = yi
            base = v0 + i * w
            for k in range(i):
                acc[k] += blk[base + k] * yi
    for j in range(n):
        out[j] = y[U64(perm[j])]


def symmetric_lu(a):
    """SuperLU's factor of the symmetric positive definite CSC matrix ``a`` in the form
    :class:`LDLFactor` reads (module docstring): a symmetric minimum-degree ordering
    (MMD on A^T + A), symmetric mode, and no pivoting."""
    from scipy.sparse.linalg import splu
    return splu(a, permc_spec='MMD_AT_PLUS_A', diag_pivot_thresh=0.0,
                options={'SymmetricMode': True})


class LDLFactor:
    """``P = Pc L D L^T Pc^T`` from SuperLU's factor ``lu`` (``scipy.sparse.linalg.
    splu`` of a symmetric positive definite P in symmetric mode without pivoting,
    :func:`symmetric_lu`; the module docstring). Raises ``ValueError`` where the factor is not
    of that form (rows and columns permuted apart: SuperLU pivoted, on a zero diagonal)."""

    def __init__(self, lu):
        if not np.array_equal(lu.perm_r, lu.perm_c):
            raise ValueError('SuperLU pivoted: its L and U are not an L D L^T factor')
        low = lu.L
        self.n = low.shape[0]
        # SuperLU gives each column its diagonal first and the rows of a supernode in
        # one order (unsorted below): all the packing needs. Sorted only if not
        if not np.array_equal(low.indices[low.indptr[:-1]], np.arange(self.n)):
            low = low.tocsc()
            low.sort_indices()
        indptr = low.indptr.astype(np.int64)
        self.perm = np.ascontiguousarray(lu.perm_c, dtype=np.int64)
        self.start = _supernodes(indptr, low.indices)
        self.rows, self.rptr, self.blk, self.vptr = _pack(indptr, low.indices, low.data,
                                                          self.start)
        self.dinv = 1.0 / lu.U.diagonal().astype(np.float64)
        self.acc = np.empty(int(np.diff(self.start).max()) if self.n else 1)
        self.y = np.empty(self.n)

    def arrays(self):
        """The factor's arrays in :func:`_solve`'s order (``perm`` to ``y``)."""
        return (self.perm, self.start, self.rows, self.rptr, self.blk, self.vptr,
                self.dinv, self.acc, self.y)

    def solve(self, b: np.ndarray, out: np.ndarray | None = None) -> np.ndarray:
        """P^-1 b (n,), into out (float32 unless given)."""
        if out is None:
            out = np.empty(self.n, np.float32)
        _solve(*self.arrays(), b, out)
        return out


@kernel(parallel=True)
def _pair(ta, tb, tc, td, te, tf, tg, th, ti, bt, ot,
          na, nb_, nc, nd, ne, nf, ng, nh, ni, bn, on):
    for p in nb.prange(2):
        if p == 0:
            _solve(ta, tb, tc, td, te, tf, tg, th, ti, bt, ot)
        else:
            _solve(na, nb_, nc, nd, ne, nf, ng, nh, ni, bn, on)


def solve_pair(ft: LDLFactor, bt, ot, fn: LDLFactor, bn, on) -> None:
    """``ot = Pt^-1 bt`` and ``on = Pn^-1 bn`` at once, one on each of two threads (the
    split preconditioner's tangential and normal parts)."""
    _pair(*ft.arrays(), bt, ot, *fn.arrays(), bn, on)


def warm() -> None:
    """Compile the kernels here on a 2 x 2 factor (``core/warmup.py``)."""
    import scipy.sparse as sp
    a = sp.csc_matrix(np.array([[2.0, 1.0], [1.0, 2.0]], np.float32))
    f, g = (LDLFactor(symmetric_lu(a)) for _ in range(2))
    b = np.ones(2, np.float32)
    f.solve(b)
    solve_pair(f, b, np.empty(2, np.float32), g, b.copy(), np.empty(2, np.float32))
