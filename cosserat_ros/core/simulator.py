"""The cloth simulator: a thin facade over the model, state, controls, terms and solver.

This module imports no ROS package: scripts, tests and benchmarks use it directly, and
the node (``cosserat_ros.ros.node``) is a thin layer over it.

Example::

    from cosserat_ros.mesh import grid_mesh
    from cosserat_ros.simulator import ClothSimulator, Material
    sim = ClothSimulator(grid_mesh(40, 40), Material(zeta=100.0, xi=1e-5, phi=0.0,
                                                     density=0.2, damping=0.05), dt=2e-4)
    sim.gravity = (0.0, 0.0, -9.81)
    sim.pin([0, 40])
    sim.step(1000)
    print(sim.energy()['total'])

What it holds: ``sim.model`` (:class:`.model.Model`, frozen rest data), ``sim.state``
(:class:`.state.State`: x, v and the energy balance), ``sim.control``
(:class:`.state.Control`: applied forces, gravity, pins), ``sim.coefficients`` (the
material on the mesh) and ``sim.solver`` (:class:`.solvers.explicit.ExplicitSolver` by
default; :class:`.solvers.implicit.ImplicitSolver` with ``solver='implicit'``).

Units are SI throughout: positions [m], velocities [m/s], forces [N], energies [J],
accelerations [m/s^2], time [s].
"""
from __future__ import annotations

import math
from typing import Dict, Optional
import warnings

import numba
import numpy as np

from . import contact as C
from .air import Air, air_pass, air_row
from .constants import DIVERGENCE_SPEED_FACTOR, VERTEX_CHUNK
from .material import Material
from .mesh import ClothMesh
from .model import Model
from .handles import HandleSet
from .threads import ThreadTuner, run_tuned
from .obstacles import ObstacleSet
from .passes import run_calls, step_passes
from .features import FeatureContact
from .self_contact import DEFAULT_FRICTION, SelfCollision
from .simulator_analysis import AnalysisMethods
from .simulator_scene import SceneMethods
from .solvers.explicit import DISCRETISATIONS, DIVERGENCE_METHODS, ExplicitSolver, steps_tiled
from .solvers.implicit import ImplicitSolver
from .state import Control, State
from .terms import registry
from .terms.jet import model_scratch

__all__ = ['ClothSimulator', 'Material', 'Air', 'SimulationDiverged', 'steps_tiled',
           'DISCRETISATIONS', 'DIVERGENCE_METHODS']


class SimulationDiverged(RuntimeError):
    """A step produced a non-finite value or a physically impossible speed.

    The simulator has been put back to the state it had before the failing ``step`` call.
    Attributes: ``step`` (the global step index that diverged), ``time`` [s] and ``hint``.
    """

    def __init__(self, step: int, time: float, hint: str):
        self.step = step
        self.time = time
        self.hint = hint
        super().__init__(f'simulation diverged at step {step} (t = {time:.6g} s): {hint}')


def _as_vec3(value, name: str) -> np.ndarray:
    arr = np.asarray(value, dtype=np.float64) if not isinstance(value, str) else None
    if arr is None or arr.shape != (3,):
        raise ValueError(f'{name} must be 3 numbers, got {value!r}')
    if not np.all(np.isfinite(arr)):
        raise ValueError(f'{name} must be finite, got {value!r}')
    return arr


def _extra_terms(given) -> list:
    """(term, coefficient values) of every registered term that is not built in, the
    values from ``given`` (term name -> {coefficient: value}) over the defaults;
    ValueError for a name no registered term has."""
    given = dict(given or {})
    extras = registry.extra_terms()
    unknown = sorted(set(given) - {t.name for t in extras})
    if unknown:
        raise ValueError(f'terms: no registered term {", ".join(map(repr, unknown))} '
                         f'(registered: {", ".join(t.name for t in extras) or "none"}; '
                         'cosserat_ros.core.terms.register adds one)')
    return [(t, registry.values_of(t, given.get(t.name))) for t in extras]


class ClothSimulator(SceneMethods, AnalysisMethods):
    """Elastic Cosserat surface on a triangle mesh, integrated explicitly (Eq. 29, the
    default) or by backward Euler (``solver='implicit'``).

    Parameters
    ----------
    mesh : ClothMesh
        The rest shape (flat or curved, open or closed).
    material : Material
        Constants zeta, xi, phi, density, damping (SI units).
    dt : float
        Time step [s]; a warning is issued when it exceeds :meth:`critical_dt`.
    discretisation : {"variational", "covariant"}
        Discretisation of the internal force N^a|_a: the exact negative gradient of the
        discrete energy (default; any boundary), or the seed's covariant derivatives
        (comparison only; needs every boundary vertex pinned). ``divergence``, its name
        before 0.2, is still taken, with a DeprecationWarning.
    check_dt : bool
        Compare ``dt`` with :meth:`critical_dt` on construction (costs ~100 force
        evaluations) and warn when it is too large.
    simd : bool
        Run the vertex pass four vertices per SIMD vector (default). False runs it one
        vertex at a time, the same formulas; kept for tests and comparison.
    solver : {"explicit", "implicit"}
        The time integrator: symplectic Euler (default; stable below :meth:`critical_dt`)
        or backward Euler by Newton-CG (:mod:`.solvers.implicit`; any dt, dissipative,
        its controls :attr:`solver_iterations` and :attr:`solver_tolerance`, its last
        solve in :attr:`solve_report`).
    terms : dict, optional
        Coefficient values of registered energy terms (:mod:`.terms.registry`), by term
        name: ``{'tether': {'k': 50.0}}``. Every term registered when the simulator is
        built acts, with its coefficients' defaults where none is given; :meth:`set_term`
        changes them later.
    """

    SOLVERS = ('explicit', 'implicit')

    def __init__(self, mesh: ClothMesh, material: Material, dt: float = 2e-4,
                 discretisation: str = 'variational', check_dt: bool = True,
                 simd: bool = True, solver: str = 'explicit',
                 terms: Optional[Dict[str, dict]] = None, *, divergence: Optional[str] = None):
        if not isinstance(mesh, ClothMesh):
            raise ValueError(f'mesh must be a ClothMesh, got {type(mesh).__name__}')
        if not isinstance(material, Material):
            raise ValueError(f'material must be a Material, got {type(material).__name__}')
        if divergence is not None:                  # the name before 0.2
            warnings.warn("ClothSimulator(divergence=...) is deprecated: it is "
                          "discretisation=... now", DeprecationWarning, stacklevel=2)
            if discretisation != 'variational' and discretisation != divergence:
                raise ValueError(f'discretisation={discretisation!r} and its deprecated '
                                 f'name divergence={divergence!r} disagree')
            discretisation = divergence
        if discretisation not in DISCRETISATIONS:
            raise ValueError(f'discretisation must be one of {DISCRETISATIONS}, '
                             f'got {discretisation!r}')
        if solver not in self.SOLVERS:
            raise ValueError(f'solver must be one of {self.SOLVERS}, got {solver!r}')
        if solver == 'implicit' and discretisation != 'variational':
            raise ValueError("solver='implicit' needs discretisation='variational': the "
                             "seed's covariant route has no energy to minimise")
        self.mesh = mesh
        self._discretisation = discretisation
        self.model = Model.from_mesh(mesh)
        self.solver = ExplicitSolver(self.model, discretisation, simd)
        self._terms = _extra_terms(terms)
        self.solver.extra = self._terms              # (the implicit solver reads its own)
        if solver == 'implicit':
            self.solver = ImplicitSolver(self.model, self.solver)
        self._solver_kind = solver
        self._threads = 'auto'
        self._tuner: Optional[ThreadTuner] = None
        n = mesh.n_vertices
        self.state = State.at_rest(mesh.vertices)
        self.control = Control.empty(n, faces=mesh.n_faces)
        self._obstacles = ObstacleSet()
        self._handles = HandleSet()
        self._self: Optional[SelfCollision] = None     # built when first switched on
        self._features = FeatureContact(mesh)           # boxes' and cylinders' edges
        self._self_on = False
        self._self_friction = DEFAULT_FRICTION
        self._passes = step_passes(self)                # around the solver: core/passes.py
        self._user_pins = np.zeros(n, dtype=bool)
        self._f_vertex = np.zeros((n, 3))
        self._force_field = np.zeros(3)
        self._air: Optional[Air] = None
        self._wind = np.zeros(3)
        self._scratch = model_scratch(self.model)
        self._time = 0.0
        self._steps = 0
        self._critical_dt: Optional[float] = None
        # omega_max^2 of the first full estimate: (material, omega^2, Ritz vector)
        self._omega2_base = None
        self._omega2_known: Dict[tuple, float] = {}
        self.material = material
        self._dt = self._check_positive(dt, 'dt')
        if check_dt and solver == 'explicit':
            self._warn_if_unstable(self._dt)

    # ------------------------------------------------------------------ state
    @property
    def n_vertices(self) -> int:
        """Number of vertices."""
        return self.mesh.n_vertices

    @property
    def positions(self) -> np.ndarray:
        """Current positions (n, 3) [m] (a copy)."""
        return self.state.x.copy()

    def set_positions(self, x) -> None:
        """Set positions (n, 3) [m]; pinned vertices move too (to script a grasp), and a
        handle holds its vertices where they are now (their offsets from it taken again).
        A vertex moved is released from no obstacle any more (placed anew: inside one,
        it is pushed out; :mod:`.contact`, "Obstacles placed through the cloth")."""
        x = self._checked_state(x, 'positions')
        self.control.contact[np.any(x != self.state.x, axis=1), C.C_FREE:C.C_FREE + 2] = 0.0
        self.state.x[:] = x
        self._handles.rebase(self.state.x)      # held vertices: their new offsets
        self.solver.forget()

    @property
    def velocities(self) -> np.ndarray:
        """Current velocities (n, 3) [m/s] (a copy; the explicit solver's at the half step
        of the leapfrog, the implicit solver's at the positions' time)."""
        return self.state.v.copy()

    def set_velocities(self, v) -> None:
        """Set velocities (n, 3) [m/s]; pinned vertices keep zero velocity."""
        arr = self._checked_state(v, 'velocities')
        arr[self.control.pinned] = 0.0
        self.state.v[:] = arr
        self.solver.forget()

    def _checked_state(self, value, name: str) -> np.ndarray:
        arr = np.array(value, dtype=np.float64)
        if arr.shape != (self.mesh.n_vertices, 3):
            raise ValueError(f'{name} must have shape ({self.mesh.n_vertices}, 3), '
                             f'got {arr.shape}')
        if not np.all(np.isfinite(arr)):
            raise ValueError(f'{name} must be finite')
        return arr

    @property
    def time(self) -> float:
        """Simulated time [s]."""
        return self._time

    @property
    def step_count(self) -> int:
        """Number of steps taken since construction or :meth:`reset`."""
        return self._steps

    @property
    def dt(self) -> float:
        """Time step [s]."""
        return self._dt

    @dt.setter
    def dt(self, value: float):
        self._dt = self._check_positive(value, 'dt')

    @property
    def discretisation(self) -> str:
        """The discretisation of N^a|_a in use: 'variational' or 'covariant'."""
        return self._discretisation

    @property
    def divergence(self) -> str:
        """Deprecated (before 0.2): :attr:`discretisation`."""
        warnings.warn('ClothSimulator.divergence is deprecated: it is .discretisation now',
                      DeprecationWarning, stacklevel=2)
        return self._discretisation

    @property
    def material(self) -> Material:
        """Material constants; assigning a new :class:`Material` takes effect at once."""
        return self._material

    @material.setter
    def material(self, material: Material):
        if not isinstance(material, Material):
            raise ValueError(f'material must be a Material, got {type(material).__name__}')
        self._material = material
        self._critical_dt = None
        self.coefficients = self.model.coefficients(material)
        self._vmax = DIVERGENCE_SPEED_FACTOR * material.wave_speed + 100.0
        self._update_applied()

    @property
    def gravity(self) -> np.ndarray:
        """Gravitational acceleration g (3,) [m/s^2]; (0, 0, 0) by default."""
        return self.control.gravity.copy()

    @gravity.setter
    def gravity(self, g):
        self.control.gravity[:] = _as_vec3(g, 'gravity')

    @property
    def force_field(self) -> np.ndarray:
        """Uniform external force per unit mass F (3,) [m/s^2], e.g. wind."""
        return self._force_field.copy()

    @force_field.setter
    def force_field(self, f):
        self._force_field = _as_vec3(f, 'force_field')
        self._update_applied()

    @property
    def pinned(self) -> np.ndarray:
        """Boolean mask (n,) of pinned vertices (a copy)."""
        return self.control.pinned.copy()

    def pin(self, indices) -> None:
        """Pin vertices (indices or a boolean mask): they keep their position (a pin is a
        handle that never moves)."""
        idx = self._indices(indices)
        self._user_pins[idx] = True
        self._sync_pins()
        self.state.v[idx] = 0.0

    def unpin(self, indices) -> None:
        """Release pinned vertices (indices or a boolean mask); a vertex a handle holds
        stays held until the handle releases it."""
        self._user_pins[self._indices(indices)] = False
        self._sync_pins()

    def _sync_pins(self) -> None:
        held = np.zeros(self.n_vertices, dtype=bool)
        held[self._handles.held()] = True
        self.control.pinned[:] = self._user_pins | held
        # a vertex no handle holds has no prescribed motion: a pin a handle let go of
        # stays where it is
        self.control.pin_velocity[~held] = 0.0

    def set_vertex_forces(self, indices, forces) -> None:
        """Replace the external nodal forces [N]: ``forces`` (k, 3) on vertices ``indices``
        (k,). Repeated indices add up. Previous nodal forces are removed."""
        idx = self._indices(indices)
        f = np.asarray(forces, dtype=np.float64)
        if f.shape != (len(idx), 3):
            raise ValueError(f'forces must have shape ({len(idx)}, 3) for {len(idx)} '
                             f'indices, got {f.shape}')
        if not np.all(np.isfinite(f)):
            raise ValueError('forces must be finite')
        fv = np.zeros_like(self._f_vertex)
        np.add.at(fv, idx, f)
        self._f_vertex = fv
        self._update_applied()

    def clear_vertex_forces(self) -> None:
        """Remove all external nodal forces."""
        self._f_vertex = np.zeros_like(self._f_vertex)
        self._update_applied()

    @property
    def vertex_forces(self) -> np.ndarray:
        """External nodal forces currently applied (n, 3) [N] (a copy)."""
        return self._f_vertex.copy()

    def _update_applied(self):
        c = self.control
        c.f_external[:] = self._f_vertex + self.coefficients.mass[:, None] * self._force_field
        c.air[:] = air_row(self._air, self._wind)
        if self._air is None:
            c.f_applied[:] = c.f_external
        else:
            vf = self.model.vertex_faces
            air_pass(self.state.x, self.state.v, self.model.faces.corners, vf.ptr, vf.face,
                     c, max(1, -(-self.n_vertices // VERTEX_CHUNK)))

    # ------------------------------------------------------------------ air
    @property
    def air(self) -> Optional[Air]:
        """The air around the cloth (:class:`Air`: density, drag and lift coefficients),
        or None (default): no aerodynamic force. Each triangle then feels pressure drag and
        lift from its velocity relative to :attr:`wind` (:mod:`cosserat_ros.core.air`)."""
        return self._air

    @air.setter
    def air(self, air: Optional[Air]):
        if air is not None and not isinstance(air, Air):
            raise ValueError(f'air must be an Air or None, got {type(air).__name__}')
        self._air = air
        self._update_applied()

    @property
    def wind(self) -> np.ndarray:
        """Velocity of the air (3,) [m/s], world frame; (0, 0, 0) by default. Acts only
        when :attr:`air` is set."""
        return self._wind.copy()

    @wind.setter
    def wind(self, w):
        self._wind = _as_vec3(w, 'wind')
        self._update_applied()

    def reset(self) -> None:
        """Back to the rest shape at rest: positions, velocities, time, step count and the
        energy-balance integrals; the last step's contact and reaction forces are
        cleared. Pins, forces, gravity, material and obstacles (where they are, with
        their velocities) are kept; grasp handles let go (their offsets belong to the
        cloth before the reset)."""
        for hid in list(self._handles.describe(self._time)):
            self._handles.release(hid)
        self._sync_pins()
        self.control.pin_velocity[:] = 0.0
        self.state.assign(State.at_rest(self.mesh.vertices))
        self.solver.forget()
        # what the last step wrote (contact rows, reactions) belongs to the old state
        self._clear_contacts()
        self.control.reaction[:] = 0.0
        self._time = 0.0
        self._steps = 0

    # ------------------------------------------------------------------ solver
    @property
    def solver_kind(self) -> str:
        """``'explicit'`` or ``'implicit'`` (the constructor's ``solver``)."""
        return self._solver_kind

    def _implicit(self, what: str) -> ImplicitSolver:
        if self._solver_kind != 'implicit':
            raise ValueError(f'{what} is a control of the implicit solver; this simulator '
                             "runs the explicit one (ClothSimulator(..., solver='implicit'))")
        return self.solver

    @property
    def solver_iterations(self) -> int:
        """Most Newton iterations per implicit step (default 20). 1 is the linearised
        backward Euler (one Newton step a step, as Baraff & Witkin 1998): ~3x faster on a
        swinging stiff cloth, exact statics, less accurate dynamics, and
        :attr:`solver_tolerance` is not asked for (``core/solvers/implicit.py``)."""
        return self._implicit('solver_iterations').iterations

    @solver_iterations.setter
    def solver_iterations(self, value: int):
        s = self._implicit('solver_iterations')
        if isinstance(value, bool) or int(value) != value or not 1 <= value <= 1000:
            raise ValueError(f'solver_iterations must be an integer in [1, 1000], got {value!r}')
        s.iterations = int(value)

    @property
    def solver_tolerance(self) -> float:
        """Convergence of an implicit step: every vertex's residual force relative to the
        larger of the step's start residual (its whole unbalanced force) and the vertex's
        own load (weight, applied force), default 1e-3 (``core/solvers/implicit.py``)."""
        return self._implicit('solver_tolerance').tolerance

    @solver_tolerance.setter
    def solver_tolerance(self, value: float):
        s = self._implicit('solver_tolerance')
        value = self._check_positive(value, 'solver_tolerance')
        if value >= 1.0:
            raise ValueError(f'solver_tolerance must be below 1 (a fraction of the step\'s '
                             f'forces), got {value!r}')
        s.tolerance = value

    @property
    def solve_report(self) -> Dict[str, float]:
        """What the last implicit step's solve did: ``iterations`` (Newton),
        ``cg_iterations``, ``factorizations`` (of its preconditioner, which is kept
        across steps until CG needs too many iterations), ``negative_curvature`` (CG
        solves stopped where the bending's Hessian is not positive), ``residual`` (in
        :attr:`solver_tolerance`'s units),
        ``converged``, ``linearized`` (the step was the linearised backward Euler of
        :attr:`solver_iterations` 1, unconverged by design) and ``unconverged_steps``
        since construction."""
        r = self._implicit('solve_report').last
        return {'iterations': r.iterations, 'cg_iterations': r.cg_iterations,
                'factorizations': r.factorizations,
                'negative_curvature': r.negative_curvature, 'residual': r.residual,
                'converged': r.converged, 'linearized': r.linearized,
                'unconverged_steps': r.unconverged_steps}

    # ------------------------------------------------------------------ dynamics
    def step(self, n: int = 1) -> None:
        """Advance ``n`` steps of size :attr:`dt` inside compiled code.

        Raises :class:`SimulationDiverged` (and restores the state from before this call)
        when a step produces a non-finite value or an impossible speed.
        """
        if isinstance(n, bool) or int(n) != n or n < 0:
            raise ValueError(f'n must be a non-negative integer, got {n!r}')
        n = int(n)
        if n == 0:
            return
        backup = self.state.copy()
        passes = [p for p in self._passes if p.active()]
        saved = [(p, p.snapshot()) for p in passes]
        for p in self._passes:
            p.start()
        try:
            done = run_calls(self, passes, n) if passes else self._solve(n)
        except BaseException:
            # any other failure (or a Ctrl-C) inside a step: all as before the call
            self._roll_back(backup, saved)
            raise
        if done < n:
            self._roll_back(backup, saved)
            crit = self.critical_dt() if self._solver_kind == 'explicit' else math.inf
            if self._dt > crit:
                hint = (f'dt = {self._dt:.3g} s is above the stable limit {crit:.3g} s; '
                        'reduce dt or soften the material')
            else:
                hint = ('a speed exceeded the elastic limit or a value became non-finite; '
                        'check the applied forces and the material, then reset')
            raise SimulationDiverged(self._steps + done + 1, self._time + (done + 1) * self._dt,
                                     hint)
        self._steps += n
        self._time += n * self._dt

    def _roll_back(self, backup, saved) -> None:
        """Back to the start of a :meth:`step` that failed: the state, and every pass
        (:mod:`.passes`) where the calls that succeeded had moved it."""
        self.state.assign(backup)
        self.solver.forget()
        for p, snap in saved:
            p.restore(snap)

    @property
    def threads(self):
        """The threads the compiled step runs on: ``'auto'`` (default) all of numba's
        (``numba.get_num_threads()`` of the calling thread) or one, whichever it measures
        faster, measured again as the machine's load changes (:mod:`.threads`: on a busy
        machine the parallel step's threads wait for each other); or an int, that many
        (at most numba's). The trajectory is the same to the bit either way."""
        return self._threads

    @threads.setter
    def threads(self, value):
        if value != 'auto' and (isinstance(value, bool) or not isinstance(value, int)
                                or not 1 <= value <= numba.config.NUMBA_NUM_THREADS):
            raise ValueError(f"threads must be 'auto' or an int in [1, "
                             f"{numba.config.NUMBA_NUM_THREADS}], got {value!r}")
        self._threads = value

    @property
    def best_threads(self) -> int:
        """The thread count the step runs fastest on now, by its own measurement
        (:attr:`threads`): the caller's other parallel work (the node's publishing: the
        energy densities, the cameras) is best run on it too."""
        if self._threads != 'auto':
            return self._threads
        return self._tuner.best if self._tuner is not None else numba.get_num_threads()

    def _solve(self, k: int) -> int:
        """The solver's ``k`` steps on the thread count :attr:`threads` says; the steps
        done (fewer: the next one went bad)."""
        def run(m):
            return self.solver.step(m, self.state, self.control, self.coefficients,
                                    self._dt, self._vmax ** 2)
        if self._threads == 'auto':
            most = numba.get_num_threads()
            if self._tuner is None or self._tuner.most != most:
                self._tuner = ThreadTuner(most)
            return run_tuned(self._tuner, run, k)
        was = numba.get_num_threads()
        numba.set_num_threads(self._threads)
        try:
            return run(k)
        finally:
            numba.set_num_threads(was)

    # ------------------------------------------------------------------ terms
    @property
    def terms(self) -> Dict[str, Dict[str, float]]:
        """The registered terms this simulator carries besides the built-in ones, with
        their coefficient values: ``{name: {coefficient: value}}`` (a copy)."""
        return {t.name: dict(c) for t, c in self._terms}

    def set_term(self, name: str, **values) -> None:
        """Set coefficients of the registered term ``name`` (``set_term('tether',
        k=80.0)``); takes effect at the next step. ValueError for an unknown term or
        coefficient or a value out of its range (nothing changes then)."""
        for term, c in self._terms:
            if term.name == name:
                c.update(registry.values_of(term, {**c, **values}))
                # the stability estimate and its material shortcut included the old values
                self._critical_dt = None
                self._omega2_base = None
                self._omega2_known.clear()
                return
        raise ValueError(f'no term {name!r} in this simulator (it carries '
                         f'{", ".join(t.name for t, _ in self._terms) or "none"})')

    def internal_forces(self) -> np.ndarray:
        """Internal force N^a|_a integrated over each dual cell, (n, 3) [N], now (with
        the registered terms' forces, :attr:`terms`)."""
        out = np.zeros((self.n_vertices, 3))
        self.solver.internal_forces(self.state.x, self.coefficients, out)
        return out

    # ------------------------------------------------------------------ helpers
    @staticmethod
    def _check_positive(value, name: str) -> float:
        if isinstance(value, bool) or not isinstance(value, (int, float, np.floating,
                                                             np.integer)):
            raise ValueError(f'{name} must be a number, got {value!r}')
        value = float(value)
        if not math.isfinite(value) or value <= 0:
            raise ValueError(f'{name} must be positive and finite, got {value!r}')
        return value

    def _indices(self, indices, name: str = 'indices') -> np.ndarray:
        arr = np.asarray(indices)
        n = self.mesh.n_vertices
        if arr.dtype == bool:
            if arr.shape != (n,):
                raise ValueError(f'a boolean {name} mask must have shape ({n},), '
                                 f'got {arr.shape}')
            return np.flatnonzero(arr)
        arr = np.atleast_1d(arr)
        if arr.ndim != 1:
            raise ValueError(f'{name} must be a 1-D list of vertex indices, got shape '
                             f'{arr.shape}')
        if arr.size == 0:
            return arr.astype(np.int64)
        if not np.issubdtype(arr.dtype, np.integer):
            if (np.issubdtype(arr.dtype, np.floating) and np.all(np.isfinite(arr))
                    and np.all(arr == np.round(arr))):
                arr = arr.astype(np.int64)
            else:
                raise ValueError(f'{name} must be integers, got {indices!r}')
        if arr.min() < 0 or arr.max() >= n:
            raise ValueError(f'{name} must lie in [0, {n - 1}], got range '
                             f'[{arr.min()}, {arr.max()}]')
        return arr.astype(np.int64)

    def _warn_if_unstable(self, dt: float):
        crit = self.critical_dt()
        if dt > crit:
            warnings.warn(f'dt = {dt:.3g} s exceeds the stable limit {crit:.3g} s of this '
                          'mesh and material: the explicit update will diverge',
                          RuntimeWarning, stacklevel=3)

    def __repr__(self) -> str:
        return (f'ClothSimulator({self.mesh!r}, {self._material}, dt={self._dt:g}, '
                f'discretisation={self._discretisation!r})')
