"""The explicit solver: symplectic Euler (Eq. 29) of the discrete Cosserat surface.

``ExplicitSolver.step(n, state, control, coeff, dt, vmax2)`` advances a
:class:`..state.State` n steps inside compiled code. The internal force is that of the
three variational terms (``core/terms``), computed by the compiled step of ``fast/``
(two passes, or tiles for large meshes), or, with ``discretisation='covariant'``, the seed's
covariant route; either way each vertex is updated by ``update.advance_vertex``.

:func:`reference_step` is the same update with the internal force summed from the term
modules themselves, one parallel pass per term: slow and simple, the truth that the fast
step is tested against (``test/test_fast.py``).
"""
from __future__ import annotations

from typing import Optional

import numba as nb
import numpy as np

from ...fast.lanes import build_lanes
from ...fast.plan import build_plan
from ...fast.simd import LANES
from ...fast.workshare import SPIN, start_threads, usable_cpus
from ...fast import step as _fast
from ..air import air_pass
from ..compiled import kernel
from ..constants import FUSE_MIN_VERTICES, TILE_VERTICES, VERTEX_CHUNK
from ..terms import covariant, TERMS
from ..terms.registry import acting
from ..state import Control, State
from ..update import advance_vertex, contact_range

__all__ = ['ExplicitSolver', 'reference_step', 'DISCRETISATIONS', 'DIVERGENCE_METHODS',
           'steps_tiled']

#: the discretisations of N^a|_a: the variational terms (default) or the seed's route
DISCRETISATIONS = ('variational', 'covariant')
#: their name before 0.2 (deprecated: DISCRETISATIONS)
DIVERGENCE_METHODS = DISCRETISATIONS


def steps_tiled(n_vertices: int, discretisation: str = 'variational') -> bool:
    """Whether the step of a mesh of ``n_vertices`` runs tile by tile
    (``fast.step.run_tiled``): the variational route from ``FUSE_MIN_VERTICES`` on."""
    return discretisation == 'variational' and n_vertices >= FUSE_MIN_VERTICES


@kernel(parallel=True)
def advance_all(x, v, force, control, coeff, dt, vmax2, part, acc):
    """The update (``update.advance_vertex``) of every vertex with a given internal force
    (n,3), in the chunks of ``part`` (nch, 3) whose sums are added in chunk order (the
    same numbers on any thread count); returns the number of vertices that went bad."""
    n = x.shape[0]
    nch = part.shape[0]
    size = (n + nch - 1) // nch
    for c in nb.prange(nch):
        w = 0.0
        d = 0.0
        b = 0
        for i in range(c * size, min(n, (c + 1) * size)):
            dw, dd, db = advance_vertex(i, force[i, 0], force[i, 1], force[i, 2], x, v,
                                        control, coeff, dt, vmax2)
            w += dw
            d += dd
            b += db
        if control.obstacles.shape[0] > 0:
            dw, dd = contact_range(nb.int64(c * size), nb.int64(min(n, (c + 1) * size)), x,
                                   v, force, control, coeff, dt)
            w += dw
            d += dd
        part[c, 0] = w
        part[c, 1] = d
        part[c, 2] = b
    bad = 0
    for c in range(nch):
        acc[0] += part[c, 0]
        acc[1] += part[c, 1]
        bad += int(part[c, 2])
    return bad


@kernel()
def run_covariant(nsteps, state, control, coeff, faces, vf, jets, vertices, st_T, cw, part,
                  force, dt, vmax2):
    """``nsteps`` steps with the seed route's force (``terms.covariant``); returns the
    steps done (fewer: that step diverged). A kernel of its own, so that a process that
    never selects the route never compiles it."""
    x, v, acc = state.x, state.v, state.acc
    for s in range(nsteps):
        if control.air[0] != 0.0:
            air_pass(x, v, faces.corners, vf.ptr, vf.face, control, part.shape[0])
        covariant.covariant_forces(x, jets, vertices, st_T, coeff.zeta, coeff.xi, coeff.phi,
                                   cw, force)
        if advance_all(x, v, force, control, coeff, dt, vmax2, part, acc) > 0:
            return s
    return nsteps


class ExplicitSolver:
    """Steps a model's state with the explicit update (module docstring).

    Parameters
    ----------
    model : :class:`..model.Model`
    discretisation : {"variational", "covariant"}
    simd : bool
        The vertex pass four vertices per SIMD vector (default), or one at a time (the
        same formulas; for tests and comparison).
    """

    def __init__(self, model, discretisation: str = 'variational', simd: bool = True):
        if discretisation not in DISCRETISATIONS:
            raise ValueError(f'discretisation must be one of {DISCRETISATIONS}, '
                             f'got {discretisation!r}')
        self.model = model
        self.discretisation = discretisation
        n, m = model.n_vertices, model.mesh.n_faces
        self.lanes = build_lanes(model, LANES if simd else 1)
        nch = -(-n // VERTEX_CHUNK)
        self.tiled = steps_tiled(n, discretisation)
        parts = max(1, nb.get_num_threads())
        self.plan = build_plan(model, self.lanes, nch, TILE_VERTICES, parts, self.tiled)
        # the internal force alone runs the two-pass layout (every gradient in its slot)
        self.force_plan = (build_plan(model, self.lanes, nch, TILE_VERTICES, parts, False)
                           if self.tiled else self.plan)
        # scratch rows per work item (fast/lanes.py: five of the jet, three of the
        # coupling), their length the largest lane group's stencil, padded by a cache line
        # so that rows in use by two threads never share one (false sharing)
        lanes = LANES if simd else 1
        smax = -(-lanes * int(np.diff(model.jets.ptr).max()) // 8) * 8 + 8
        threads = nb.config.NUMBA_NUM_THREADS + 1
        self.work = _fast.Work(np.zeros((m, 3, 3)), np.zeros((3, len(model.jets.idx))),
                               np.zeros((nch, 8, smax)), np.zeros(threads, dtype=np.int64),
                               np.zeros((nch, 3)), np.zeros((n, 3)),
                               np.zeros(threads, dtype=np.int64),
                               np.array([0, 0, 0, SPIN], dtype=np.int64))
        # the internal force through the one-region step: x and v of its own, never read
        self._force_state = State(np.zeros((n, 3)), np.zeros((n, 3)), np.zeros(2))
        self._force_control = Control.empty(n)
        self.cov_work: Optional[covariant.Work] = (covariant.Work.zeros(n)
                                                   if discretisation == 'covariant' else None)
        #: the registered terms besides the built-ins, (term, its coefficient values)
        #: pairs (:mod:`..terms.registry`; the simulator's list, shared)
        self.extra: list = []

    def _share_threads(self) -> int:
        """Set the work-sharing states' range count (``fast/workshare.py``) to the threads
        numba runs now, from Python: ``numba.get_num_threads()`` in compiled code makes
        numba refuse to cache the kernel. A stale count gives the same numbers, only
        slower. Returns the thread count for the one-region step (``fast.step.run_region``)
        or 0 where it does not apply: a tiled step, or where its barrier could wait for
        ever or spin away the time of the threads it waits for: each of its iterations
        must run on a thread of its own, at once, which numba's static schedule (no
        ``set_parallel_chunksize``) on the OpenMP or workqueue layer does, and each thread
        needs a CPU of its own (``workshare.usable_cpus``). numba picks its layer at the
        first parallel call (``workshare.start_threads``)."""
        nthr = nb.get_num_threads()
        self.work.share[0] = nthr
        self.work.ushare[0] = nthr
        ok = (not self.tiled and nb.get_parallel_chunksize() == 0
              and nthr <= usable_cpus() and start_threads() in ('omp', 'workqueue'))
        return nthr if ok else 0

    def step(self, nsteps: int, state, control, coeff, dt: float, vmax2: float) -> int:
        """Advance ``nsteps`` steps in place; returns the steps completed (fewer means the
        next one diverged and ``state`` is invalid: the caller restores it)."""
        if acting(self.extra):
            return self._step_with_terms(nsteps, state, control, coeff, dt, vmax2)
        return self._step(nsteps, state, control, coeff, dt, vmax2)

    def extra_force(self, x: np.ndarray) -> np.ndarray:
        """-sum of the registered terms' gradients at x (n,3) [N] (:attr:`extra`)."""
        f = np.zeros_like(x)
        for term, c in acting(self.extra):
            f -= term.gradient(self.model, x, c)
        return f

    def _step_with_terms(self, nsteps, state, control, coeff, dt, vmax2) -> int:
        """The steps with the registered terms (:attr:`extra`): one compiled step at a
        time, each with the terms' force at its start positions added to the applied force
        (symplectic Euler: every force of the update at x_n), and its work ``f . (x_{n+1}
        - x_n)``, which the update books as external work (a held vertex's included: its
        reaction takes the term's force off), taken back out: it is the change of the
        term's own energy, which the report counts (:mod:`..energy`)."""
        fe, fa = control.f_external, control.f_applied
        base_e, base_a = fe.copy(), fa.copy()
        f = np.zeros_like(state.x)
        try:
            for s in range(nsteps):
                f[:] = self.extra_force(state.x)
                x0 = state.x.copy()
                fe[:] = base_e + f          # with air the step's air pass adds to this one
                fa[:] = base_a + f
                done = self._step(1, state, control, coeff, dt, vmax2)
                state.acc[0] -= float(np.sum(f * (state.x - x0)))
                if done < 1:
                    return s
            return nsteps
        finally:
            fe[:] = base_e
            if control.air[0] != 0.0:
                fa -= f                     # the last step's air force stays
            else:
                fa[:] = base_a

    def _step(self, nsteps: int, state, control, coeff, dt: float, vmax2: float) -> int:
        m = self.model
        if self.discretisation == 'covariant':
            return run_covariant(nsteps, state, control, coeff, m.faces, m.vertex_faces,
                                 m.jets, m.vertices, m.st_T, self.cov_work, self.work.part,
                                 self.work.force, dt, vmax2)
        nthr = self._share_threads()
        coupled = coeff.phi != 0.0
        if nthr:
            run = _fast.run_region_coupled if coupled else _fast.run_region
            return run(nsteps, state, control, coeff, m.faces, m.vertex_faces, m.vertices,
                       m.jets.tr_ptr, self.lanes, self.plan, self.work, dt, vmax2, nthr)
        if self.tiled:
            run = _fast.run_tiled_coupled if coupled else _fast.run_tiled
        else:
            run = _fast.run_two_pass_coupled if coupled else _fast.run_two_pass
        return run(nsteps, state, control, coeff, m.faces, m.vertex_faces, m.vertices,
                   m.jets.tr_ptr, self.lanes, self.plan, self.work, dt, vmax2)

    def forget(self) -> None:
        """Nothing to drop when the state is set from outside: the explicit update
        carries nothing from one step to the next but the state (the implicit solver's
        predictor: :meth:`.implicit.ImplicitSolver.forget`)."""

    def internal_forces(self, x: np.ndarray, coeff, out: np.ndarray) -> None:
        """The internal force at positions x (n,3) into out (n,3) [N]: the built-in
        terms' and the registered ones' (:attr:`extra`)."""
        m = self.model
        if self.discretisation == 'covariant':
            covariant.covariant_forces(x, m.jets, m.vertices, m.st_T, coeff.zeta, coeff.xi,
                                       coeff.phi, self.cov_work, out)
            if acting(self.extra):
                out += self.extra_force(x)
            return
        nthr = self._share_threads()
        coupled = coeff.phi != 0.0
        if nthr:
            # the step's own kernel, one step of dt = 0 (x and v stay; the force is the
            # same to the bit), so that a process compiles the vertex code once
            fs = self._force_state
            fs.x[:] = x
            fs.v[:] = 0.0
            run = _fast.run_region_coupled if coupled else _fast.run_region
            run(1, fs, self._force_control, coeff, m.faces, m.vertex_faces, m.vertices,
                m.jets.tr_ptr,
                self.lanes, self.plan, self.work, 0.0, np.inf, nthr)
            out[:] = self.work.force
            if acting(self.extra):
                out += self.extra_force(x)
            return
        run = _fast.elastic_forces_coupled if coupled else _fast.elastic_forces
        run(x, coeff, m.faces, m.vertex_faces, m.vertices, m.jets.tr_ptr,
                       self.lanes, self.force_plan, self.work, out)
        if acting(self.extra):
            out += self.extra_force(x)


def internal_force_reference(model, coeff, x: np.ndarray) -> np.ndarray:
    """-sum of the variational terms' gradients (n,3) [N], term by term."""
    return -sum(term.gradient(model, coeff, x) for term in TERMS.values())


def reference_step(model, coeff, state, control, dt: float, nsteps: int = 1,
                   vmax2: float = np.inf) -> int:
    """``nsteps`` steps of the update with the internal force summed from the term modules
    (:data:`..terms.TERMS`); returns the steps completed."""
    part = np.zeros((-(-model.n_vertices // VERTEX_CHUNK), 3))
    for s in range(nsteps):
        air_pass(state.x, state.v, model.faces.corners, model.vertex_faces.ptr,
                 model.vertex_faces.face, control, part.shape[0])
        f = internal_force_reference(model, coeff, state.x)
        if advance_all(state.x, state.v, f, control, coeff, dt, vmax2, part, state.acc) > 0:
            return s
    return nsteps
