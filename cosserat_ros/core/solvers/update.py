"""The explicit update of one vertex (Eq. 29): the one place where forces accumulate.

For a free vertex i with lumped mass ``m_i = mu A_i`` and damping ``c_i = rho A_i``::

    f   = f_int + f_applied + m_i g - c_i v          (internal, users' forces and field,
                                                      gravity, damping: Eq. 1)
    v  <- v + dt / m_i f                              (Eq. 29, velocity first)
    x  <- x + dt v                                    (then position)

This is symplectic Euler (leapfrog with velocities at half steps): undamped runs keep a
shadow energy, so the total energy oscillates by O(dt^2) instead of drifting. A pinned
vertex keeps its position and zero velocity.

Bookkeeping (``State.acc``): external work ``(f_applied . dx)`` and damping dissipation
``c v_old . dx`` with ``dx = dt v_new``, so that ``total(t) - total(0) = external_work -
dissipated`` up to the O(dt^2) integration error.

Every step kernel (``fast/step.py``, and the reference and seed-route steps of
:mod:`.explicit`) calls :func:`advance_vertex`; a new force or constraint on the vertices
(contact, grasp handles) enters here, once, not in each driver.
"""
from __future__ import annotations

import numba as nb

from ..compiled import kernel

__all__ = ['advance_vertex']


@kernel(inline='always')
def advance_vertex(i, f0, f1, f2, x, v, control, coeff, dt, vmax2):
    """Eq. 29 for vertex i with internal force f = (f0, f1, f2) [N], the users' controls
    (:class:`..state.Control`) and the material's masses and damping
    (:class:`..model.Coefficients`). Returns (external work [J], dissipation [J], 1 if the
    vertex went bad (non-finite or faster than sqrt(vmax2)) else 0); a pinned vertex
    stays put: (0, 0, 0)."""
    i = nb.uint64(i)        # no negative-index wrap-around on the ~15 loads and stores
    if control.pinned[i]:
        return 0.0, 0.0, 0
    f_applied = control.f_applied
    m = coeff.mass[i]
    c = coeff.damp[i]
    g = control.gravity
    vo0 = v[i, 0]
    vo1 = v[i, 1]
    vo2 = v[i, 2]
    vn0 = vo0 + dt / m * (f0 + f_applied[i, 0] + m * g[0] - c * vo0)
    vn1 = vo1 + dt / m * (f1 + f_applied[i, 1] + m * g[1] - c * vo1)
    vn2 = vo2 + dt / m * (f2 + f_applied[i, 2] + m * g[2] - c * vo2)
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
