"""The implicit solver: backward Euler of the discrete Cosserat surface, by Newton-CG.

Backward Euler (the same forces as Eq. 1 of the explicit update, taken at the end of the
step) for a free vertex i with lumped mass ``m_i`` and damping ``c_i``::

    m_i (v' - v) / dt = f_int(x') + f_applied + m_i g - c_i v',     x' = x + dt v'

is the stationarity condition of the incremental potential (Martin et al. 2011, "Example-
based elastic materials"; Liu, Bouaziz & Kavan 2017, Eq. 2), with ``y = x + dt v + dt^2
(f_applied / m + g)``::

    Phi(x') = sum_i m_i / (2 dt^2) |x'_i - y_i|^2 + c_i / (2 dt) |x'_i - x_i|^2 + E(x')

E the discrete energy of :mod:`..terms` (membrane + bending + coupling, and any registered
term: :mod:`..terms.registry`, whose blocks join the preconditioner). Its gradient is
the residual ``r(x') = m (x' - y) / dt^2 + c (x' - x) / dt - f_int(x')`` and its Hessian
``A = (m / dt^2 + c / dt) I + H_E``. Each step minimises Phi over the free vertices (a
pinned or held vertex moves with its prescribed velocity, as in the explicit update) by
Newton's method:

* the Newton system ``A+ p = -r`` by preconditioned conjugate gradients, matrix-free:
  ``H_E q = -(f_int(x' + eps q) - f_int(x')) / eps`` from the compiled internal force of
  the explicit solver (one evaluation per CG iteration), plus what makes the membrane's
  part of it positive semi-definite, ``G(S+ - S) (x) I_3 q`` (``membrane.
  add_compression_product``: the stress part of a compressed triangle's Hessian with S's
  negative eigenvalue clamped, the projected Newton of Teran et al. 2005, "Robust
  quasistatic finite elements"; the solution is the same, only the path to it: a cloth
  swinging under compression otherwise meets negative curvature in most Newton
  iterations and the line search cuts the truncated step to 1/16-1/1000);
  preconditioned by a sparse factorization of P = the mass and damping + the membrane's
  whole Hessian (its positive part) + the bending's and coupling's per-vertex 3x3 blocks
  (``hessian_blocks``, positive semi-definite; where the bending dominates the inertia
  at the mesh's scale, its whole plate operator instead of its blocks, and where it
  dominates by more, P factored in each vertex's frame as an in-plane and a normal
  part), kept across iterations and steps until CG needs more than twice what it took
  with it fresh and more than ``refresh`` (8) iterations
  (``ImplicitSolver._preconditioner``);
  stopped at the inexact-Newton forcing tolerance ``|r + A+ p| <= eta |r|``, or where
  ``q^T A+ q <= 0`` (negative curvature, which the bending can still have: Steihaug
  truncation, Nocedal & Wright 2006, Alg. 7.1) with the iterate so far, or the steepest
  descent if there is none. The forcing is Eisenstat & Walker's (1996) choice 1: 0.5
  (:data:`FIRST_FORCING`) at a step's first iteration (and after one whose direction
  was not CG's iterate: steepest descent, or negative curvature at once), then how far
  the last iteration's linear model missed,
  ``eta_k = | |r_k| - |r_{k-1} + alpha A+ p_{k-1}| | / |r_{k-1}|``,
  kept above ``eta_{k-1}^1.618`` while that is above 0.1 (their safeguard) and above
  half the reduction the tolerance still asks for (no solve past it), at most 0.5.
  Where the forces are near linear over the step (a sheet settling) the model is good,
  eta falls and Newton converges superlinearly; where they are not (a fall from flat, a
  swing through compression) it stays loose and no CG iterations are spent on a model
  that misses (against ``min(0.5, sqrt(|r| / |r_0|))``: docs/performance.md);
* a backtracking (Armijo) line search on Phi, so that every iteration lowers the
  potential (no overshoot, no divergence from a too-long Newton step at large dt); a
  full step whose change of Phi is below Phi's round-off (1e-11 of it, near the
  solution) is taken if it lowers the largest residual;
* converged when every vertex's residual ``|r_i|`` has fallen below ``tolerance`` times
  the larger of the residual's largest vertex force at the start, ``R_0 = max_j |r_j|``
  (the step's whole unbalanced force: the applied forces, gravity, the elastic forces
  out of balance, the inertia), and the vertex's own load ``F_i = m_i |g| +
  |f_applied,i|`` (and a contact round's friction): the velocity change of the step is
  right to that fraction of the step's own change whatever the forces' size, or, where
  that change is smaller than the load's in a step (a cloth at or near rest), to that
  fraction of ``F_i dt / m_i`` (``g dt`` for a vertex that only weighs), a static error
  of that fraction of the load's deflection (relative to R_0 alone, a settling sheet kept
  cutting an imbalance already below 1e-3 of its weight: docs/performance.md). Or
  after ``iterations`` Newton iterations; a residual below 1e-8 of the largest force on
  a vertex (elastic, applied or weight) is round-off: a cloth at rest takes none. The
  start is ``x + dt v``, where the vertices coast to (R_0 is the residual there), or,
  without obstacles, that plus ``dt^2`` times the last step's acceleration where Phi is
  lower: a steady fall or swing then starts at or near its solution
  (docs/performance.md).

What backward Euler does to energy: it dissipates, strongly for the modes of period
below ~dt (the stiff membrane modes) and weakly for slow ones (a mode of frequency omega
loses a fraction ~omega^2 dt^2 of its amplitude per step, Hairer, Lubich & Wanner 2006);
statics are exact to the tolerance: at rest the residual is the static balance, which a
step leaves below the tolerance times each vertex's load, a static error of that
fraction of the load's deflection (the linearised solver, which takes its Newton step
every step, to round-off). The tests compare them with the explicit solver's. The
numerical dissipation is not in ``State.acc``'s ``dissipated`` (which counts the damping
force only), so the energy report's total drops by it.

Air (``Control.air``): its force at the start of the step, plus the drag's velocity
derivative (``air.drag_blocks``: ``f_air(v') ~ f_air(v) - D (v' - v)``, D per vertex,
symmetric positive semi-definite), so that the drag is implicit too: its term
``(x' - x - dt v)^T D (x' - x - dt v) / (2 dt)`` joins Phi and ``D / dt`` joins A, and a
strong wind does not force a small step (the explicit drag is unstable above ``dt ~ 2 mu
/ (rho C_D |u|)``: 7.9 ms for polyester, 0.113 kg/m^2, at 20 m/s, half a 1/60 s frame).
The lift stays explicit.

Contact with obstacles is part of the solve (:mod:`.implicit_contact`): a vertex that
reaches an obstacle's contact layer in the step is constrained in it, sticking (all three
coordinates fixed, like a pin) or sliding (the normal one fixed, kinetic friction as an
applied force); the conjugate gradients run on the free coordinates only (the filter of
Baraff & Witkin 1998, Sec. 5.3: the residual, the matrix products and the preconditioner's
output projected), the residual at the fixed ones is the contact force, and the Signorini
and Coulomb conditions on it change the set and solve the step again (at most
``ROUNDS + ADDS`` solves, :mod:`.implicit_contact`). What the last solve leaves inside a
layer is answered afterwards by the explicit update's contact
(:func:`.update.contact_list`).

With ``iterations = 1`` the solver is the linearised backward Euler of Baraff & Witkin
1998 ("Large steps in cloth simulation"): one Newton step a step, from the same start,
its linear system solved to ``LINEARIZED_FORCING``, the tolerance not asked for. Statics
are unchanged (at rest the residual is the static balance, and each step's Newton step
continues from the last); the dynamics lose accuracy where the forces are far from
linear over a step (11 oz denim swinging down from flat at 40 x 40: its mean height
within 2.5% of the converged solve's over the first 0.8 s, 6% at 1 s, and 3x faster;
docs/performance.md). The report still gives the residual it leaves.

``ImplicitSolver.step`` has the explicit solver's signature; ``last`` holds what the last
step's solve did (Newton iterations, CG iterations, residual, converged).
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..air import air_pass, drag_blocks
from ..constants import VERTEX_CHUNK
from ..energy import elastic_energy
from ..terms import TERMS
from ..terms.registry import acting
from ..terms.jet import model_scratch
from ..terms.membrane import add_compression_product, compressed_faces, compression_stress
from .implicit_contact import ADDS, FREE, ROUNDS, STICK, ObstacleConstraints, push_list
from .ldl import LDLFactor, solve_pair, symmetric_lu
from ..update import contact_list
from .vectors import (cg_update, direction, dot, fd_product, from_frames, inertia_energy,
                      inertia_residual, residual_measure, to_frames, vertex_frames)

__all__ = ['ImplicitSolver', 'SolveReport']


#: the CG forcing of the one Newton iteration of ``iterations = 1`` (linearised backward
#: Euler, module docstring): the step is then only as right as this linear solve (0.5
#: let the swinging denim of docs/performance.md fall at half its speed; 0.1 follows the
#: converged solve's mean height within 2.5% over its first 0.8 s, at a third of its cost)
LINEARIZED_FORCING = 0.1

#: the forcing of a step's first Newton iteration, and the largest of the later ones
#: (module docstring)
FIRST_FORCING = 0.5

#: (1 + sqrt 5) / 2: the safeguard's exponent in Eisenstat & Walker's choice 1
GOLDEN = 0.5 * (1.0 + 5.0 ** 0.5)

#: the preconditioner holds the bending's whole plate operator where it dominates the
#: inertia by more than this (:meth:`ImplicitSolver._preconditioner`; the bench's square sheet at
#: N = 40, beta 14, gained from it, the hanging denim at N = 80, beta 7, lost)
PLATE_RATIO = 10.0

#: and above this ratio, the preconditioner is split in each vertex's frame into a
#: tangential and a normal part (:meth:`ImplicitSolver._preconditioner`; the bench's square sheet
#: at beta 14 / 20 / 29 took 1.45x / 1.06x / 0.64x the time a step whole)
SPLIT_RATIO = 25.0


def _norm(a: np.ndarray) -> float:
    """|a| without BLAS: ``np.linalg.norm`` of a whole array calls OpenBLAS's dot, whose
    worker threads then spin and take the cores from the compiled kernels (the bench's
    square sheet at 80 x 80: 0.6 -> 5.8 ms an internal force inside the solve); a compiled sum, no
    temporary (:func:`.vectors.dot`)."""
    return float(np.sqrt(dot(a, a)))


@dataclass
class SolveReport:
    """What the last step's Newton solve did."""

    #: Newton iterations of the last step
    iterations: int = 0
    #: conjugate-gradient iterations summed over them (= internal force evaluations)
    cg_iterations: int = 0
    #: factorizations of the preconditioner in the last step (it is kept across steps)
    factorizations: int = 0
    #: conjugate-gradient solves of the last step stopped at negative curvature
    negative_curvature: int = 0
    #: the final residual, ``max_i (|r_i| / max(R_0, F_i))`` (module docstring; R_0 the
    #: largest at the step's start, F_i vertex i's load), dimensionless
    residual: float = 0.0
    #: whether it fell below the tolerance
    converged: bool = True
    #: whether the step was the linearised backward Euler (``iterations`` 1, module
    #: docstring): unconverged by design, not a failure
    linearized: bool = False
    #: steps whose solve ended unconverged (at the iteration limit, or a line search that
    #: could not lower Phi), since construction; the linearised solver's steps, which
    #: are not asked to converge, are not counted
    unconverged_steps: int = 0


class ImplicitSolver:
    """Backward Euler by Newton-CG (module docstring).

    Parameters
    ----------
    model : :class:`..model.Model`
    explicit : :class:`.explicit.ExplicitSolver`
        Whose compiled internal force this solver evaluates.
    iterations : int
        Most Newton iterations per step (default 20); 1: linearised backward Euler
        (module docstring).
    tolerance : float
        Convergence: every vertex's residual relative to the larger of the step's
        start residual and the vertex's load (default 1e-3; module docstring).
    cg_iterations : int
        Most conjugate-gradient iterations per Newton iteration (default 200).
    """

    def __init__(self, model, explicit, iterations: int = 20, tolerance: float = 1e-3,
                 cg_iterations: int = 200):
        if explicit.discretisation != 'variational':
            raise ValueError("the implicit solver needs discretisation='variational' (the "
                             "seed's covariant route has no energy to minimise)")
        self.model = model
        self.explicit = explicit
        self.iterations = iterations
        self.tolerance = tolerance
        self.cg_iterations = cg_iterations
        n = model.n_vertices
        self.last = SolveReport()
        self._part = np.zeros((-(-n // VERTEX_CHUNK), 3))
        self._f = np.zeros((n, 3))
        self._fq = np.zeros((n, 3))
        self._xe = np.zeros((n, 3))         # CG's buffers (``_cg``)
        self._ad = np.zeros((n, 3))
        self._csc = {}
        self._plate_coo = None
        self._plate_diag = None
        self._pinv = None
        self._pinv_key = None
        self._pinv_of = (None, None)
        #: CG iterations above which the factored preconditioner is rebuilt, when they
        #: are also more than twice what it took when fresh (``_fresh_cg``). It is
        #: rebuilt where the next solves run: at the next Newton iterate of the step;
        #: after a step's last one, at the step's solution, the linearised solver at the
        #: next step's start, its one iterate. A stiff cloth swinging (11 oz denim, 24 x
        #: 24) needs ~10x the CG iterations with P from one step of motion before (the
        #: membrane's stiff directions turned); a P kept for many steps (a sheet
        #: settling) is better taken at a solution than at a start, which carries the
        #: fall's transient (docs/performance.md)
        self.refresh = 8
        self._stale = False
        self._fresh_cg = None
        self._face_blk = np.empty((model.mesh.n_faces, 3, 3, 3, 3))
        self._tens = np.empty((model.mesh.n_faces, 3))
        self._contacts = ObstacleConstraints(n)
        self._scratch = model_scratch(model)
        #: the last step's acceleration (v' - v) / dt, for the next step's predictor
        #: (:meth:`forget` clears it)
        self._accel = np.zeros((n, 3))

    def forget(self) -> None:
        """Drop what the solver carries from the last step to the next, the predictor's
        acceleration: the state was set from outside (a reset, ``set_positions``,
        ``set_velocities``, a divergence's restore), so the next step starts as from a
        fresh simulator (the linearised solver's step depends on its start), and the
        contacts' modes and normal forces (a vertex that slid would slide on with the
        last step's friction)."""
        self._accel[:] = 0.0
        self._contacts.clear()

    @property
    def linearized(self) -> bool:
        """Whether a step is the linearised backward Euler: one Newton step, its linear
        system solved to :data:`LINEARIZED_FORCING` (``iterations`` 1)."""
        return self.iterations == 1

    # ------------------------------------------------------------------ pieces
    def internal_forces(self, x: np.ndarray, coeff, out: np.ndarray) -> None:
        """The internal force at positions x (n,3) into out (n,3) [N] (the explicit
        solver's compiled one)."""
        self.explicit.internal_forces(np.ascontiguousarray(x), coeff, out)

    def _energy(self, coeff, x: np.ndarray) -> float:
        """The elastic energy E(x) [J] (the terms' sum, from one pass over their fields:
        ``energy.elastic_energy``)."""
        e = elastic_energy(self.model, coeff, np.ascontiguousarray(x), self._scratch)
        for term, c in acting(self.explicit.extra):   # the registered terms (:mod:`..terms`)
            e += term.energy(self.model, x, c)
        return e

    def _plate(self):
        """The plate operator ``bending.plate_matrix`` (COO, for D = 1 N m); built once,
        with its diagonal."""
        if self._plate_coo is None:
            from ..terms.bending import plate_matrix
            k = plate_matrix(self.model)
            self._plate_diag = k.diagonal()
            self._plate_coo = k.tocoo()
        return self._plate_coo

    def plate_ratio(self, coeff, dt: float) -> float:
        """beta: the median over the vertices of the bending's plate operator's diagonal,
        ``6 xi K_ii``, over the inertia's ``m_i / dt^2``: how far the bending dominates at
        the mesh's own scale (``_preconditioner``)."""
        self._plate()
        return float(np.median(6.0 * coeff.xi * self._plate_diag / (coeff.mass / dt ** 2)))

    def _pattern(self, form: str):
        """The fixed sparsity of P in ``form`` (``_preconditioner``), built once for each: a
        list of ``(size, inv, nnz, indices, indptr)`` per factored matrix (the CSC arrays
        and the map from the assembled entries to them: the 3n x 3n P, or its tangential
        2n x 2n and normal n x n parts), and each entry's row and column vertex (for the
        pins). The entries come in the order :meth:`_preconditioner` assembles them: the
        membrane's face blocks, the per-vertex blocks, the plate operator (on each
        coordinate, or on the normal part)."""
        if form not in self._csc:
            c = self.model.faces.corners
            n = self.model.n_vertices
            nf = len(c)
            vert = np.arange(n)
            mats, rv, cv = [], [], []
            # (coordinates per vertex in the matrix, whether the plate is on them)
            parts = {'blocks': ((3, False),), 'plate': ((3, True),),
                     'split': ((2, False), (1, True))}[form]
            for k, plate in parts:
                a = np.arange(k)
                fr = np.broadcast_to(c[:, :, None, None, None], (nf, 3, 3, k, k))
                fc = np.broadcast_to(c[:, None, :, None, None], (nf, 3, 3, k, k))
                vr = np.broadcast_to(vert[:, None, None], (n, k, k))
                rows = [(k * fr + a[:, None]).ravel(), (k * vr + a[:, None]).ravel()]
                cols = [(k * fc + a[None, :]).ravel(), (k * vr + a[None, :]).ravel()]
                if plate:
                    pl = self._plate()
                    rows.append((k * pl.row[:, None] + a).ravel())
                    cols.append((k * pl.col[:, None] + a).ravel())
                rows, cols = np.concatenate(rows), np.concatenate(cols)
                size = k * n
                key = cols.astype(np.int64) * size + rows           # column-major: CSC order
                uniq, inv = np.unique(key, return_inverse=True)
                indices = (uniq % size).astype(np.int32)
                indptr = np.searchsorted(uniq // size, np.arange(size + 1)).astype(np.int32)
                mats.append((size, inv, len(uniq), indices, indptr))
                rv.append(rows // k)                # each entry's row and column vertex
                cv.append(cols // k)
            self._csc[form] = (mats, rv, cv)
        return self._csc[form]

    def _preconditioner(self, coeff, x: np.ndarray, diag: np.ndarray, drag_dt,
                        pinned: np.ndarray, dt: float):
        """``z = P^-1 r`` (0 on the pinned vertices) as a function of r (n,3), P = (m / dt^2
        + c / dt) I (``diag``) + the drag's D / dt (``drag_dt``, or None) + the membrane's
        whole Hessian (positive part, ``membrane.face_hessians``) + the coupling's diagonal
        blocks + the bending's, with the rows and columns of ``pinned`` (the pins and the
        vertices that stick to an obstacle) replaced by the identity. Three forms, by
        beta, how far the bending dominates the inertia at the mesh's scale
        (:meth:`plate_ratio`):

        * beta up to :data:`PLATE_RATIO`: P on the 3n coordinates, the bending's diagonal
          3 x 3 blocks (``hessian_blocks``, positive semi-definite);
        * up to :data:`SPLIT_RATIO`: P on the 3n coordinates, the bending's whole plate
          operator ``6 xi K`` (``bending.plate_matrix``) on each coordinate;
        * above: the plate operator on the displacement normal to the sheet only, and P
          taken in each vertex's frame (two tangent axes and the normal,
          :func:`.vectors.vertex_frames`) and split there into a tangential 2n x 2n part and a
          normal n x n part, factored apart: the blocks between a tangential and a
          normal coordinate are left out.

        Why the plate operator: the diagonal blocks alone leave CG a condition number of
        about 1 + beta in the bending's band of modes (beta grows as N^4 at a fixed dt:
        0.9 / 14 / 230 on the bench's square sheet at N = 20 / 40 / 80 and 1/60 s), so ~sqrt(beta)
        iterations (~18 per Newton iteration at N = 80). Why the split: on each of the
        three coordinates the operator's two-ring stencil meets the membrane's 3 x 3
        blocks and the factor fills in; split, the plate meets one coordinate a vertex
        and the membrane's one-ring stencil two (at 160 x 160 a quarter of the entries
        and a third of the solve's time: docs/performance.md). What it leaves out is
        small where the bending dominates the inertia at the mesh's scale: it keeps the
        surface smooth there, so that neighbouring frames turn little, and the
        membrane's in-plane stiffness reaches a normal coordinate only through that
        turn (flat and without the coupling's blocks, phi = 0, the two parts are exactly
        P's; the coupling's blocks join the tangential and the normal coordinates of a
        vertex, and their link is left out too); nearer the ratio it is not small
        (SPLIT_RATIO). And why not the
        operator below PLATE_RATIO: its fill makes each factorization ~2.5x dearer,
        which a cloth that swings and so refactors P often (11 oz denim: beta 0.4 at
        N = 40) does not win back.

        Factored by SuperLU in single precision: a preconditioner needs no more (the CG
        iterations stay the same), and its solves, the solver's largest cost, take less
        time (docs/performance.md). Solved as ``L D L^T`` from SuperLU's factor by a
        compiled supernodal solve (:mod:`.ldl`: half the entries read, free of the GIL,
        the split's two parts at once on two threads): at 160 x 160 a pair of solves
        inside a step 4.4 ms against SuperLU's own 10.4."""
        import scipy.sparse as sp
        from ..terms.membrane import face_hessians
        mdl = self.model
        f = mdl.faces
        n = len(x)
        beta = self.plate_ratio(coeff, dt)
        form = ('blocks' if beta <= PLATE_RATIO else 'plate' if beta <= SPLIT_RATIO
                else 'split')
        blocks = (TERMS['bending'].hessian_blocks(mdl, coeff, x) if form == 'blocks'
                  else np.zeros((n, 3, 3)))
        if coeff.phi != 0.0:
            blocks += TERMS['coupling'].hessian_blocks(mdl, coeff, x)
        for term, c in acting(self.explicit.extra):   # the registered terms' own blocks
            blocks += term.hessian_blocks(mdl, x, c)
        blocks[:, [0, 1, 2], [0, 1, 2]] += diag
        if drag_dt is not None:
            blocks += drag_dt
        blocks[pinned] = np.eye(3)
        blk = self._face_blk
        face_hessians(x, f.corners, f.dinv, f.area, coeff.zeta, True, blk)
        plate = 6.0 * coeff.xi * self._plate().data if form != 'blocks' else None
        if form == 'split':
            frame = vertex_frames(x, f.corners)
            rf = frame[f.corners]
            blk = np.einsum('tcra,tcdrq,tdqb->tcdab', rf, blk, rf, optimize=True)
            blocks = np.einsum('nra,nrq,nqb->nab', frame, blocks, frame, optimize=True)
            vals = [np.concatenate([blk[..., :2, :2].ravel(), blocks[:, :2, :2].ravel()]),
                    np.concatenate([blk[..., 2, 2].ravel(), blocks[:, 2, 2], plate])]
        else:
            vals = [blk.ravel(), blocks.ravel()]
            if plate is not None:
                vals.append(np.repeat(plate, 3))
            vals = [np.concatenate(vals)]
        mats, rv, cv = self._pattern(form)
        facs = []
        for (size, inv, nnz, indices, indptr), v, r_v, c_v in zip(mats, vals, rv, cv):
            if pinned.any():
                k = size // n
                off = pinned[r_v] | pinned[c_v]
                nface = len(f.corners) * 9 * k * k
                off[nface:nface + n * k * k] = False        # the identity's blocks stay
                v = np.where(off, 0.0, v)
            data = np.bincount(inv, weights=v, minlength=nnz)
            facs.append(LDLFactor(symmetric_lu(sp.csc_matrix(
                (data.astype(np.float32), indices, indptr), shape=(size, size)))))

        if form != 'split':
            fac = facs[0]
            rf = np.empty(3 * n, np.float32)

            def solve(r):
                rf[:] = r.reshape(-1)
                z = fac.solve(rf).reshape(n, 3).astype(np.float64)
                z[pinned] = 0.0
                return z
            return solve
        lt, ln = facs
        frame = np.ascontiguousarray(frame)
        rt, rn = np.empty(2 * n, np.float32), np.empty(n, np.float32)
        zt, zn = np.empty(2 * n, np.float32), np.empty(n, np.float32)

        def solve_split(r):
            to_frames(frame, np.ascontiguousarray(r), rt, rn)
            solve_pair(lt, rt, zt, ln, rn, zn)      # the two parts at once
            z = np.empty((n, 3))
            from_frames(frame, zt, zn, pinned, z)
            return z
        return solve_split

    # ------------------------------------------------------------------ step
    def step(self, nsteps: int, state, control, coeff, dt: float, vmax2: float) -> int:
        """Advance ``nsteps`` backward-Euler steps in place; returns the steps completed
        (fewer: the next one produced a non-finite value or a speed above sqrt(vmax2),
        ``state`` is then invalid and the caller restores it)."""
        for s in range(nsteps):
            if not self._one_step(state, control, coeff, dt, vmax2):
                return s
        return nsteps

    def _one_step(self, state, control, coeff, dt, vmax2) -> bool:
        m = self.model
        x, v = state.x, state.v
        if control.air[0] != 0.0:
            air_pass(x, v, m.faces.corners, m.vertex_faces.ptr, m.vertex_faces.face, control,
                     self._part.shape[0])
        pinned = control.pinned
        free = ~pinned
        mass = coeff.mass[:, None]
        damp = coeff.damp[:, None]
        g = control.gravity[None, :]
        fa = control.f_applied
        xn = x.copy()
        vn = v.copy()
        u = control.pin_velocity
        diag = mass / dt ** 2 + damp / dt                           # (n,1)
        # the drag linearised about the step's start: f_air(v') ~ f_air(v) - D (v' - v)
        drag = drag_blocks(m, xn, vn, control.air) if control.air[0] != 0.0 else None
        drag_dt = None if drag is None else drag / dt
        y = xn + dt * vn + dt ** 2 * (fa / mass + g)
        rep = self.last
        rep.iterations = rep.cg_iterations = rep.factorizations = rep.negative_curvature = 0
        rep.residual, rep.converged = float('nan'), False    # until a solve ends
        # the start: where the vertices would coast to (x + dt v), not y: y carries the
        # whole applied force as if nothing resisted it, and a 10 N pull on one light
        # vertex puts y metres away and the first residuals at 1e11 N
        xk = np.where(free[:, None], xn + dt * vn, xn + dt * u)
        con = None
        if control.obstacles.shape[0] > 0:
            con = self._contacts
            con.begin(xn, vn, y, free, control, dt)
        th = control.contact_params[0]
        f = self._f
        # the forces on each vertex other than the elastic one, for the round-off floor
        outer = np.linalg.norm(fa, axis=1) + mass[:, 0] * np.linalg.norm(g)
        scale = [0.0]        # the residual at the step's start: every round's tolerance
        for round_ in range(ROUNDS + ADDS if con is not None else 1):
            yr, out = y, outer
            if con is not None:
                if con.active:
                    yr = y + dt ** 2 * con.friction / mass
                    out = outer + np.linalg.norm(con.friction, axis=1)
                con.project(xn, xk, dt, th)
            # without obstacles a second start, the last step's acceleration carried on
            guess = (np.where(free[:, None], xk + dt ** 2 * self._accel, xk)
                     if con is None else None)
            r = self._newton(xk, yr, xn, vn, f, pinned, con, coeff, diag, drag, drag_dt,
                             dt, out, scale, guess)
            if r is None:
                return False
            # the last solve's set is final: a vertex it took inside a layer stays free, for
            # the explicit contact's correction after the solve (``contact_list``)
            if (con is None or round_ == ROUNDS + ADDS - 1
                    or not con.update(xn, xk, r, free, control, dt,
                                      adds_only=round_ >= ROUNDS - 1)):
                break
        if not rep.converged and not rep.linearized:
            rep.unconverged_steps += 1
        # the end of the step: velocities, the pins' reactions, the balance (``f`` is the
        # internal force at xk, where the last solve left it; the pinned vertices are at
        # x + dt u since the start)
        vk = (xk - xn) / dt
        vk[pinned] = u[pinned]
        # a speed the elastic waves cannot carry, on the free vertices (a pin or a
        # handle moves as prescribed, as in the explicit update)
        if np.any(np.sum(vk[free] * vk[free], axis=1) > vmax2):
            return False
        self._accel[:] = (vk - vn) / dt
        if drag is not None:                     # the applied force the step used
            fa = fa - np.einsum('nij,nj->ni', drag, vk - vn)
        # the force the step's own forces leave unbalanced: a pin's reaction, an
        # obstacle's contact force (friction included)
        react = mass * (vk - vn) / dt - (f + fa + mass * g - damp * vk)
        control.reaction[pinned] = react[pinned]
        dx = dt * vk
        # a held vertex: the applied force's work and the damping's loss as on a free one,
        # and the reaction's work (a pin, dx = 0, does none)
        work = float(np.sum(fa * dx) + np.sum((react * dx)[pinned]))
        diss = float(np.sum(damp * vk * dx))
        x[:] = xk
        v[:] = vk
        if con is not None:
            held, w, d = con.finish(xn, xk, react, control, dt)
            rest = np.flatnonzero(con.mode == FREE)
            # the internal force with which the explicit update (Eq. 29) would take vn to
            # vk: the correction's ledger takes the step's force from it
            # (``update.contact_vertex``)
            feq = (mass * (vk - vn * (1.0 - dt * damp / mass)) / dt - control.f_applied
                   - mass * g)
            w2, d2 = contact_list(rest, 0, len(rest), x, v, feq, control, coeff, dt, True)
            push_list(held, x, control.obstacles, control.sdf_meta, control.sdf_data, th,
                      control.contact)
            work += w + w2
            diss += d + d2
        state.acc[0] += work
        state.acc[1] += diss
        return True

    def _newton(self, xk, y, xn, vn, f, pinned, con, coeff, diag, drag, drag_dt, dt,
                outer, scale, guess=None):
        """Minimise Phi (module docstring; ``y`` with the applied forces and friction)
        from ``xk`` in place over the free coordinates; ``f`` ends as the internal force
        at ``xk``; ``outer`` (n,) the size of each vertex's other forces [N]; ``scale``
        a one-element list, the largest residual at the step's start (set by the
        step's first solve; a contact round after it starts near a solution, and its
        tolerance stays relative to the step's forces, not to that small start);
        ``guess``: another start, taken instead of ``xk`` when Phi is lower there (after
        the scale is set at ``xk``). Returns
        the residual there before the filter (at a fixed coordinate: the force its
        constraint exerts), or None if it is not finite."""
        rep = self.last
        held = pinned if con is None or not con.active else pinned | (con.mode == STICK)

        def filt(a):
            a[pinned] = 0.0
            if con is not None:
                con.filter(a)
            return a

        m1, c1 = coeff.mass, coeff.damp

        def raw(xx, ff):
            r = np.empty_like(xx)
            inertia_residual(m1, c1, xx, y, xn, ff, dt, r)
            if drag is not None:
                r += np.einsum('nij,nj->ni', drag, (xx - xn) / dt - vn)
            return r

        def residual(xx, out_f):
            self.internal_forces(xx, coeff, out_f)
            return filt(raw(xx, out_f))

        def potential(xx):
            phi_ = inertia_energy(m1, c1, xx, y, xn, dt) + self._energy(coeff, xx)
            if drag is not None:
                q = xx - xn - dt * vn
                phi_ += 0.5 / dt * float(np.einsum('ni,nij,nj->', q, drag, q))
            return float(phi_)

        r = residual(xk, f)
        norms = np.linalg.norm(r, axis=1)
        if scale[0] == 0.0:
            scale[0] = float(norms.max())
        # the tolerance's scale per vertex: R_0, or the vertex's own load (docstring)
        denom = np.maximum(np.maximum(max(float(norms.max()), scale[0]), outer), 1e-300)

        def measure(rr):
            """(max_i |r_i|, the residual in the tolerance's units) of residual rr."""
            a, b = residual_measure(rr, denom)
            return float(a), float(b)

        def unmet(res_):
            # the linearised solver takes its one step whatever the residual (the
            # tolerance is not asked for): statics are then reached to round-off
            return self.linearized or res_ > self.tolerance
        rmax, res = measure(r)
        # below this the residual is round-off (and the finite-difference products'
        # error): 1e-8 of the largest force on a vertex, elastic, applied or weight
        floor = 1e-8 * float(np.max(np.linalg.norm(f, axis=1) + outer))
        floor = max(floor, 1e-300)
        phi = None
        if guess is not None and rmax > floor and unmet(res):
            phi = potential(xk)
            pg = potential(guess)
            if pg < phi:
                xk[:] = guess
                phi = pg
                r = residual(xk, f)
                rmax, res = measure(r)
        if not np.isfinite(res):
            return None                          # a non-finite force at the start
        it = 0
        key = (dt, coeff.zeta, coeff.xi, coeff.phi, held.tobytes(), drag is None,
               tuple((t.name, tuple(c.values())) for t, c in acting(self.explicit.extra)))

        def current():
            # the mass and damping by identity, held: a material change makes new arrays
            # (an id alone can be reused by the next allocation)
            return (self._pinv_key == key and self._pinv_of[0] is coeff.mass
                    and self._pinv_of[1] is coeff.damp)

        def factor():
            self._pinv = self._preconditioner(coeff, xk, diag, drag_dt, held, dt)
            self._pinv_key = key
            self._pinv_of = (coeff.mass, coeff.damp)
            self._fresh_cg = None
            self._stale = False
            rep.factorizations += 1
        eta_next = None
        while unmet(res) and rmax > floor and it < self.iterations:
            if self._pinv is None or not current() or self._stale:
                factor()
            pinv = self._pinv
            if con is not None and con.active:
                base = pinv

                def pinv(q, base=base):
                    return filt(base(filt(q.copy())))
            eta = (LINEARIZED_FORCING if self.linearized
                   else FIRST_FORCING if eta_next is None else eta_next)
            p, used, zr = self._cg(xk, f, r, diag, drag_dt, pinv, filt, coeff, eta)
            if self._fresh_cg is None:
                self._fresh_cg = used
            elif used > max(self.refresh, 2 * self._fresh_cg):
                # P has drifted from A: factor it again (``_stale``, ``refresh``). Not
                # merely because CG needs many iterations: with the bending's diagonal
                # blocks only (beta below PLATE_RATIO) even a fresh P needs many (~17 a
                # solve on the bench's square sheet at 80 x 80 without the plate
                # operator), and a factorization costs ~30 solves (~60 and ~2 ms there)
                self._stale = True
            rep.cg_iterations += used
            if phi is None:
                phi = potential(xk)
            slope = float(np.sum(r * p))
            if not slope < 0.0:                  # not a descent direction: steepest descent
                p = -pinv(r)
                slope = float(np.sum(r * p))
                zr = None
            alpha = 1.0
            rt = None
            for _ in range(30):
                xt = xk + alpha * p
                pt = potential(xt)
                if np.isfinite(pt) and pt <= phi + 1e-4 * alpha * slope:
                    break
                if alpha == 1.0 and abs(pt - phi) <= 1e-11 * abs(phi):
                    # the change is below Phi's round-off: judge the step by the residual
                    rt = residual(xt, self._fq)
                    if np.max(np.linalg.norm(rt, axis=1)) < rmax:
                        f[:] = self._fq
                        break
                    rt = None
                alpha *= 0.5
            else:
                break                            # no decrease even at 2^-30: stalled
            xk[:] = xt
            phi = pt
            r_old = r
            r = rt if rt is not None else residual(xk, f)
            rmax, res = measure(r)
            it += 1
            if zr is not None:
                # the next forcing (module docstring): how far the residual the linear
                # model predicted, r + alpha A+ p = (1 - alpha) r - alpha zr, missed the
                # one reached, relative to |r|; not shrinking faster than eta^golden,
                # nor below what the tolerance still asks for
                lin = _norm((1.0 - alpha) * r_old - alpha * zr)
                e = abs(_norm(r) - lin) / max(_norm(r_old), 1e-300)
                g = eta ** GOLDEN
                if g > 0.1:
                    e = max(e, g)
                e = max(e, 0.5 * self.tolerance / max(res, 1e-300))
                eta_next = min(FIRST_FORCING, e)
            else:
                eta_next = None
        if self._stale and not self.linearized and current():
            factor()                             # at the step's solution (``refresh``)
        rep.iterations += it
        rep.residual = res
        rep.converged = bool(res <= self.tolerance or rmax <= floor)
        rep.linearized = self.linearized
        # a non-finite force or position where the solve ended (a NaN residual meets
        # neither test of the loop, and the line search asks Phi only to be finite)
        if not (np.isfinite(res) and np.all(np.isfinite(xk))):
            return None
        return raw(xk, f)

    def _cg(self, xk, f, r, diag, drag_dt, pinv, filt, coeff, eta):
        """Truncated PCG for ``A+ p = -r`` on the free coordinates (``filt`` zeroes the
        others; A+ = A with the membrane's compressed stress clamped, module docstring);
        returns (p, iterations, zr): zr = -(r + A+ p), the linear model's residual at p
        (the next forcing's measure), or None where p is not CG's iterate (negative
        curvature at the first iteration: p is the preconditioned residual)."""
        fq, xe, ad = self._fq, self._xe, self._ad
        b = -r
        p = np.zeros_like(r)
        z_r = b.copy()
        z = pinv(z_r)
        d = z.copy()
        rz = dot(z_r, z)
        bnorm = _norm(b)
        xscale = max(1.0, float(np.abs(xk).max()))
        diag1 = np.ascontiguousarray(diag[:, 0])
        fc = self.model.faces
        tens = self._tens
        compression_stress(np.ascontiguousarray(xk), fc.corners, fc.dinv, fc.area,
                           coeff.zeta, tens)
        squeezed = compressed_faces(tens)
        dn = float(np.abs(d).max())
        for k in range(self.cg_iterations):
            if dn == 0.0:
                return p, k, z_r
            eps = 1e-7 * xscale / dn
            np.multiply(d, eps, out=xe)
            xe += xk
            self.internal_forces(xe, coeff, fq)
            fd_product(diag1, d, fq, f, eps, ad)
            if drag_dt is not None:
                ad += np.einsum('nij,nj->ni', drag_dt, d)
            add_compression_product(self.model, tens, squeezed, d, ad)
            filt(ad)
            curv = dot(d, ad)
            if not curv > 0.0:                   # negative curvature (or NaN): stop here
                self.last.negative_curvature += 1
                return (p, k + 1, z_r) if k > 0 else (d, 1, None)
            a = rz / curv
            if np.sqrt(cg_update(p, z_r, d, ad, a)) <= eta * bnorm:
                return p, k + 1, z_r
            z = pinv(z_r)
            rz_new = dot(z_r, z)
            dn = direction(d, z, rz_new / rz)
            rz = rz_new
        return p, self.cg_iterations, z_r
