"""What a :class:`.simulator.ClothSimulator` reports about its cloth, as its methods:
the energy and its densities (:mod:`.energy`), the discrete geometry (:mod:`.geometry`),
the stress resultants, and the explicit step's stability limit
(:mod:`.solvers.stability`).

:class:`AnalysisMethods` is a base class of ``ClothSimulator`` and of nothing else: it
holds no state of its own and reads the simulator's. This module imports no ROS package.
"""
from __future__ import annotations

from typing import Dict, Optional

import numpy as np

from . import energy as _energy
from .geometry import CURVATURE_ESTIMATORS, Geometry
from .material import Material, material_tensor
from .solvers.stability import critical_dt as _critical_dt, max_eigenpair as _max_eigenpair
from .terms import covariant, registry

__all__ = ['AnalysisMethods']


class AnalysisMethods:
    """Energy, geometry, resultants and stability of a :class:`.simulator.ClothSimulator`."""

    # ------------------------------------------------------------------ energy
    def energy_and_densities(self):
        """:meth:`energy` and :meth:`energy_densities` from one evaluation of the fields
        and of the internal force."""
        # the explicit solver's velocity is half a step behind x (leapfrog), the implicit
        # one's at x's time: the report carries it by dt / 2 for the first only
        lag = self._dt if self._solver_kind == 'explicit' else 0.0
        energy, dens = _energy.report(self.model, self.coefficients, self.state, self.control,
                                      lag, self._scratch, self.internal_forces())
        if self._terms:
            # each registered term under its name, in the total (not in ``elastic``, the
            # Cosserat surface's own), at the positions (the report's x)
            extra = {t.name: float(t.energy(self.model, self.state.x, c))
                     for t, c in self._terms}
            total = energy['total'] + sum(extra.values())
            energy = {k: v for k, v in energy.items() if k != 'total'}
            energy.update(extra)
            energy['total'] = total
        return energy, dens

    def energy_densities(self) -> Dict[str, np.ndarray]:
        """Per-vertex energy densities [J/m^2] (seed Fig. 4): ``stretching``, ``bending``,
        ``coupling`` and ``total``, each (n,)."""
        return self.energy_and_densities()[1]

    def energy(self) -> Dict[str, float]:
        """Energies [J] of the current state and the running balance terms.

        ``kinetic`` uses the velocity synchronised with the positions (for the explicit
        solver the leapfrog half-step correction v + dt/2 a; the implicit solver's
        velocity is at the positions' time), ``stretching``, ``bending``, ``coupling`` are the
        discrete elastic energy terms (``elastic`` their sum), ``gravity`` is
        -sum m g . x, each registered term's energy under its name (:attr:`terms`),
        ``total`` = kinetic + elastic + gravity + those. ``external_work`` (nodal
        forces, force field, air, and what pins, handles and obstacles do) and
        ``dissipated`` (damping, friction) accumulate since the last
        reset, so ``total - total(0) ~ external_work - dissipated``.
        """
        return self.energy_and_densities()[0]

    # ------------------------------------------------------------------ inspection
    def geometry(self, curvature: str = 'jet') -> Geometry:
        """Per-vertex geometry of the current state (see :class:`Geometry`).

        ``curvature`` selects the curvature estimator: ``"jet"`` (cubic least-squares
        jet, convergent, default) or ``"seed"`` (normal differences along the 1-ring, the
        seed's Sec. 5.2; does not converge, kept for comparison).
        """
        if curvature not in CURVATURE_ESTIMATORS:
            raise ValueError(f'curvature must be one of {CURVATURE_ESTIMATORS}, '
                             f'got {curvature!r}')
        return self.model.geometry(self.state.x, curvature)

    def resultants(self) -> Dict[str, np.ndarray]:
        """Per-vertex contact quantities from the vertex strains, for inspection:
        ``M`` = M^ab (n,2,2), ``N`` = N^ab (n,2,2) (Eq. 28), ``N3`` = N^3b = M^ba|_a (n,2),
        ``force_vectors`` N^b (n,2,3) (Eq. 26), and the material tensors ``Phi``, ``Psi``,
        ``Theta`` (n,2,2,2,2) of Eq. 19."""
        cw = covariant.resultants(self.model, self.coefficients, self.state.x)
        n3 = np.einsum('nbk,nk->nb', cw.nvec, cw.basis[:, 2])
        A = self.model.rest.metric
        mat = self._material
        return {'M': cw.mres, 'N': cw.nres, 'N3': n3, 'force_vectors': cw.nvec,
                'Phi': material_tensor(mat.zeta, A), 'Psi': material_tensor(mat.xi, A),
                'Theta': material_tensor(mat.phi, A)}

    # ------------------------------------------------------------------ stability
    def critical_dt(self, material: Optional[Material] = None) -> float:
        """Largest stable time step [s] for this mesh and material, or for another
        ``material`` on the same mesh: 0.8 of the damped symplectic Euler limit for the
        highest frequency of the system linearised at rest (:mod:`.solvers.stability`).

        The first call runs the full estimate (60 Lanczos iterations); later materials
        update it (:meth:`_material_omega2`), so that a run-time material change costs
        milliseconds, not a new estimate."""
        if material is not None and material != self._material:
            if not isinstance(material, Material):
                raise ValueError(f'material must be a Material, got {type(material).__name__}')
            return _critical_dt(self._material_omega2(material), material.density,
                                material.damping)
        if self._critical_dt is None:
            self._critical_dt = _critical_dt(self._material_omega2(self._material),
                                             self._material.density, self._material.damping)
        return self._critical_dt

    #: Lanczos iterations of an update from the first estimate's Ritz vector
    UPDATE_ITERATIONS = 12

    def _material_omega2(self, material: Material) -> float:
        """omega_max^2 at rest for ``material``. The internal force is linear in the
        stiffness coefficients (zeta, xi, phi) and the mass in the density, so for
        coefficients c = s c0 and density mu, omega^2 = s (mu0 / mu) omega0^2 exactly
        (damping does not enter). Any other change runs :data:`UPDATE_ITERATIONS` Lanczos
        iterations from the first estimate's top Ritz vector (an upper estimate still:
        Ritz value plus residual). Results are kept per material."""
        stiff = np.array([material.zeta, material.xi, material.phi])
        key = (*stiff.tolist(), material.density)
        if key in self._omega2_known:
            return self._omega2_known[key]
        coeff = self.model.coefficients(material)
        if self._omega2_base is None:
            w2, vec = self._omega2(coeff, self.mesh.vertices)
            self._omega2_base = (material, w2, vec)
        else:
            m0, w0, vec0 = self._omega2_base
            stiff0 = np.array([m0.zeta, m0.xi, m0.phi])
            k = int(np.argmax(np.abs(stiff0)))
            scale = stiff[k] / stiff0[k] if stiff0[k] else 0.0
            # (not with registered terms: their stiffness does not scale with the material)
            if (scale > 0 and not registry.acting(self._terms)
                    and np.allclose(stiff, scale * stiff0, rtol=1e-12, atol=0.0)):
                w2 = w0 * scale * m0.density / material.density
            else:
                w2, _ = self._omega2(coeff, self.mesh.vertices, self.UPDATE_ITERATIONS,
                                     start=vec0)
        if len(self._omega2_known) > 64:
            self._omega2_known.clear()
        self._omega2_known[key] = w2
        return w2

    def max_eigenvalue(self, iterations: int = 60, seed: int = 0,
                       at: Optional[np.ndarray] = None) -> float:
        """omega_max^2 [1/s^2] of the free system linearised at rest, or at positions
        ``at`` (Lanczos, an upper estimate: largest Ritz value plus its residual)."""
        X = self.mesh.vertices if at is None else np.asarray(at, dtype=np.float64)
        return self._omega2(self.coefficients, X, iterations, seed)[0]

    def _omega2(self, coeff, X, iterations: int = 60, seed: int = 0, start=None):
        def force(x, out):
            self.solver.internal_forces(np.ascontiguousarray(x), coeff, out)
        return _max_eigenpair(force, coeff.mass, X, self.mesh.mean_edge_length, iterations,
                              seed, start)
