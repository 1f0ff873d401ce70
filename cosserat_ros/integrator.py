"""Explicit time integration of Eq. 1 / 24 with the update of Eq. 29.

Per step, for every free vertex with lumped mass ``m_i = mu A_i`` and damping
``c_i = rho A_i``::

    v <- v + dt/m_i (f_int(x) + f_ext + m_i (g + F) - c_i v)      (Eq. 29, velocity first)
    x <- x + dt v                                                   (then position)

This is symplectic Euler (leapfrog with velocities at half steps): undamped runs keep a
shadow energy, so the total energy oscillates by O(dt^2) instead of drifting. Pinned
vertices keep their position and zero velocity.

Bookkeeping per step (accumulated in ``acc``): external work ``sum (f_ext + m F) . dx`` and
damping dissipation ``sum c_i v_old . dx`` with ``dx = dt v_new``, so that
``total(t) - total(0) = external_work - dissipated`` up to the O(dt^2) integration error.
"""
from __future__ import annotations

import numba as nb
import numpy as np

from .compiled import kernel
from .forces import _gather, covariant_forces, variational_stages

METHOD_VARIATIONAL = 0
METHOD_COVARIANT = 1


@kernel(inline='always')
def _update(i, x, v, f0, f1, f2, f_applied, mass, damp, dt, g0, g1, g2, vmax2):
    """Eq. 29 for vertex i with internal force f: returns (external work, dissipation,
    1 if the vertex went bad (non-finite or faster than sqrt(vmax2)) else 0)."""
    m = mass[i]
    c = damp[i]
    vo0 = v[i, 0]
    vo1 = v[i, 1]
    vo2 = v[i, 2]
    vn0 = vo0 + dt / m * (f0 + f_applied[i, 0] + m * g0 - c * vo0)
    vn1 = vo1 + dt / m * (f1 + f_applied[i, 1] + m * g1 - c * vo1)
    vn2 = vo2 + dt / m * (f2 + f_applied[i, 2] + m * g2 - c * vo2)
    s2 = vn0 * vn0 + vn1 * vn1 + vn2 * vn2
    bad = 0 if s2 <= vmax2 else 1  # also catches NaN
    v[i, 0] = vn0
    v[i, 1] = vn1
    v[i, 2] = vn2
    x[i, 0] += dt * vn0
    x[i, 1] += dt * vn1
    x[i, 2] += dt * vn2
    work = dt * (f_applied[i, 0] * vn0 + f_applied[i, 1] * vn1 + f_applied[i, 2] * vn2)
    diss = dt * c * (vo0 * vn0 + vo1 * vn1 + vo2 * vn2)
    return work, diss, bad


@kernel(parallel=True)
def integrate(ops, work_arrays, gather, x, v, force, f_applied, mass, damp, pinned, gravity,
              dt, vmax2, acc):
    """One symplectic Euler update in place, one pass over the vertices; returns the number
    of vertices that went bad (non-finite or faster than sqrt(vmax2)). With ``gather`` the
    last stage of the variational force (the gather of corner and stencil gradients) runs
    in the same pass and fills ``force``; otherwise ``force`` is read as given."""
    tr_ptr, tr_slot, vf_ptr, vf_face, vf_corner = ops[13], ops[14], ops[15], ops[16], ops[17]
    fgrad, contrib = work_arrays[5], work_arrays[6]
    work = 0.0
    diss = 0.0
    bad = 0
    for i in nb.prange(x.shape[0]):
        if gather:
            f0, f1, f2 = _gather(i, vf_ptr, vf_face, vf_corner, fgrad, tr_ptr, tr_slot,
                                 contrib)
            force[i, 0] = f0
            force[i, 1] = f1
            force[i, 2] = f2
        else:
            f0 = force[i, 0]
            f1 = force[i, 1]
            f2 = force[i, 2]
        if not pinned[i]:
            w, d, b = _update(i, x, v, f0, f1, f2, f_applied, mass, damp, dt, gravity[0],
                              gravity[1], gravity[2], vmax2)
            work += w
            diss += d
            bad += b
    acc[0] += work
    acc[1] += diss
    return bad


@kernel()
def run_variational(nsteps, x, v, f_applied, mass, damp, pinned, gravity, dt, vmax2, acc,
                    ops, mat, work, force):
    """Advance ``nsteps`` steps with the variational force (the default) in compiled code.
    Returns the number of completed steps; fewer than ``nsteps`` means step ``returned
    value`` diverged (state then invalid). A step is two parallel passes: faces (strains,
    membrane gradients) and vertices (jets, bending, stencil gradients) in one, then
    gather + update. With a coupling (phi != 0) the vertex terms read the face strains and
    the face coupling gradients read the vertex terms: four passes (faces, vertices,
    faces, gather + update)."""
    for s in range(nsteps):
        variational_stages(x, ops, mat, work)
        if integrate(ops, work, True, x, v, force, f_applied, mass, damp, pinned, gravity, dt,
                     vmax2, acc) > 0:
            return s
    return nsteps


@kernel()
def run_covariant(nsteps, x, v, f_applied, mass, damp, pinned, gravity, dt, vmax2, acc, ops,
                  cov, mat, cwork, work, force):
    """:func:`run_variational` with the seed's covariant-divergence force. A kernel of its
    own (not a branch of one stepping kernel), so that a process that never selects it
    never compiles it."""
    for s in range(nsteps):
        covariant_forces(x, ops, cov, mat, cwork, force)
        if integrate(ops, work, False, x, v, force, f_applied, mass, damp, pinned, gravity,
                     dt, vmax2, acc) > 0:
            return s
    return nsteps


def stability_limit(omega_max: float, gamma_max: float) -> float:
    """Largest stable dt of the damped symplectic Euler update for a mode of angular
    frequency omega with damping rate gamma = rho/mu: the Jury conditions of
    ``x'' = -omega^2 x - gamma x'`` give ``omega^2 dt^2 + 2 gamma dt < 4`` and
    ``gamma dt < 2``, i.e. ``dt < (sqrt(gamma^2 + 4 omega^2) - gamma) / omega^2``."""
    if omega_max <= 0:
        return np.inf if gamma_max <= 0 else 2.0 / gamma_max
    return (np.sqrt(gamma_max ** 2 + 4.0 * omega_max ** 2) - gamma_max) / omega_max ** 2
