"""The explicit update of one vertex (Eq. 29): the one place where forces accumulate.

For a free vertex i with lumped mass ``m_i = mu A_i`` and damping ``c_i = rho A_i``::

    f   = f_int + f_applied + m_i g - c_i v          (internal, users' forces and field,
                                                      gravity, damping: Eq. 1)
    v  <- v + dt / m_i f                              (Eq. 29, velocity first)
    x  <- x + dt v                                    (then position)

This is symplectic Euler (leapfrog with velocities at half steps): undamped runs keep a
shadow energy, so the total energy oscillates by O(dt^2) instead of drifting. A pinned
vertex keeps its position and zero velocity; a vertex a grasp handle holds moves with
the velocity the handle prescribes, and both report the force that took
(:func:`_prescribed`).

Contact (:mod:`..contact`) is part of the same update: with obstacles, every loop that
calls :func:`advance_vertex` runs :func:`contact_range` over the same vertices right
after it, which takes each vertex's new velocity through the contact response (from its
old position ``x - dt v``), moves it with the velocity it ends with and puts it back on
the contact layer. The two are separate loops because the contact code, inside the
update loop, slowed the step without obstacles by 10-40% (paired runs): LLVM then has to
assume that the calls touch the step's arrays. Each such loop first bounds its vertices
(a box and a speed) and keeps only the obstacles that can reach one of them
(:func:`..contact.near_mask`, exact), so an obstacle away from that part of the cloth
costs its vertices nothing.

Bookkeeping (``State.acc``): external work ``(f_applied . dx)`` and damping dissipation
``c v_old . dx`` with ``dx = dt v_new``, so that ``total(t) - total(0) = external_work -
dissipated`` up to the O(dt^2) integration error.

Every step kernel (``fast/step.py``, and the reference and seed-route steps of
:mod:`.explicit`) calls :func:`advance_vertex`; a new force or constraint on the vertices
(contact, grasp handles) enters here, once, not in each driver.
"""
from __future__ import annotations

import math

import numba as nb

from .compiled import kernel
from .contact import ALL, C_WIDTH, NO_CONTACT, near_mask, push_out, released, resolve

__all__ = ['advance_vertex', 'contact_vertex', 'contact_range', 'contact_list']


@kernel(inline='always')
def _prescribed(i, f0, f1, f2, x, v, control, m, c, dt):
    """A pinned or held vertex: it moves with its prescribed velocity u
    (``Control.pin_velocity``), and the force that takes, beyond the step's own forces f
    (internal, applied, gravity, damping), is its reaction ``r = m (u - v) / dt - f``
    (``Control.reaction``; :mod:`..handles`). Returns (the work of r and of the applied
    force over the step [J], the damping's dissipation [J], 0): the ledger of a free
    vertex (the applied force's work, the damping's loss) plus what the handle does, so
    that with the held vertices' kinetic energy (:mod:`..energy`) the balance closes
    for a moving handle too; a pin (u = 0) does no work."""
    u = control.pin_velocity
    r = control.reaction
    fa = control.f_applied
    g = control.gravity
    u0 = u[i, 0]
    u1 = u[i, 1]
    u2 = u[i, 2]
    if dt > 0.0:
        r[i, 0] = m * (u0 - v[i, 0]) / dt - (f0 + fa[i, 0] + m * g[0] - c * v[i, 0])
        r[i, 1] = m * (u1 - v[i, 1]) / dt - (f1 + fa[i, 1] + m * g[1] - c * v[i, 1])
        r[i, 2] = m * (u2 - v[i, 2]) / dt - (f2 + fa[i, 2] + m * g[2] - c * v[i, 2])
    work = dt * ((r[i, 0] + fa[i, 0]) * u0 + (r[i, 1] + fa[i, 1]) * u1
                 + (r[i, 2] + fa[i, 2]) * u2)
    diss = dt * c * (v[i, 0] * u0 + v[i, 1] * u1 + v[i, 2] * u2)
    v[i, 0] = u0
    v[i, 1] = u1
    v[i, 2] = u2
    x[i, 0] += dt * u0
    x[i, 1] += dt * u1
    x[i, 2] += dt * u2
    return work, diss, 0


@kernel(inline='always')
def advance_vertex(i, f0, f1, f2, x, v, control, coeff, dt, vmax2):
    """Eq. 29 for vertex i with internal force f = (f0, f1, f2) [N], the users' controls
    (:class:`..state.Control`) and the material's masses and damping
    (:class:`..model.Coefficients`). Returns (external work [J], dissipation [J], 1 if the
    vertex went bad (non-finite or faster than sqrt(vmax2)) else 0); a pinned vertex
    stays put: (0, 0, 0)."""
    i = nb.uint64(i)        # no negative-index wrap-around on the ~15 loads and stores
    f_applied = control.f_applied
    m = coeff.mass[i]
    c = coeff.damp[i]
    g = control.gravity
    if control.pinned[i]:
        return _prescribed(i, f0, f1, f2, x, v, control, m, c, dt)
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


@kernel(inline='always')
def contact_vertex(i, x, v, force, control, coeff, dt, mask, vmax2, backward):
    """The contact response of vertex i after :func:`advance_vertex` moved it with internal
    force ``force[i]`` (see the module docstring), against the obstacles ``mask`` keeps
    (:func:`..contact.near_mask`, valid while the vertex ends slower than sqrt(vmax2));
    returns (external work [J], dissipation [J]) of the contact: the response's
    (:func:`..contact.resolve`), and what the update's ledger counted of the applied
    force's work and the damping over the displacement before contact, ``dt v``, that
    belongs to the one after it, ``dt w``: ``dt f_a . (w - v)`` and ``dt c v_d . (w -
    v)``, ``v_d`` the velocity the damping acted at (the start velocity; ``backward``:
    the end one, the implicit step's)."""
    i = nb.uint64(i)
    if control.pinned[i]:
        # a pinned or held vertex moves as prescribed, in no contact: its row is cleared
        # (a vertex pinned while resting on an obstacle kept reporting its weight there)
        for j in range(C_WIDTH):
            control.contact[i, j] = NO_CONTACT[j]
        return 0.0, 0.0
    ob = control.obstacles
    th = control.contact_params[0]
    v0 = v[i, 0]
    v1 = v[i, 1]
    v2 = v[i, 2]
    x0 = x[i, 0] - dt * v0
    x1 = x[i, 1] - dt * v1
    x2 = x[i, 2] - dt * v2
    # the step's force m (v - v_start) / dt, with v_start from Eq. 29 (advance_vertex)
    # solved for it: (v - dt F / m) / (1 - c dt / m), F = internal + applied + weight
    m = coeff.mass[i]
    c = coeff.damp[i]
    fa = control.f_applied
    g = control.gravity
    den = 1.0 - c * dt / m
    if abs(den) < 1e-12:             # the update forgot v_start: F - c v stands for it
        den = 1.0
    u0 = (v0 - dt / m * (force[i, 0] + fa[i, 0] + m * g[0])) / den
    u1 = (v1 - dt / m * (force[i, 1] + fa[i, 1] + m * g[1])) / den
    u2 = (v2 - dt / m * (force[i, 2] + fa[i, 2] + m * g[2])) / den
    p0 = v0
    p1 = v1
    p2 = v2
    v0, v1, v2, w, d = resolve(i, x0, x1, x2, v0, v1, v2, m * (p0 - u0) / dt,
                               m * (p1 - u1) / dt, m * (p2 - u2) / dt, m, dt, ob,
                               control.sdf_meta, control.sdf_data, th, control.contact, mask)
    if backward:
        u0 = p0
        u1 = p1
        u2 = p2
    w += dt * (fa[i, 0] * (v0 - p0) + fa[i, 1] * (v1 - p1) + fa[i, 2] * (v2 - p2))
    d += dt * c * (u0 * (v0 - p0) + u1 * (v1 - p1) + u2 * (v2 - p2))
    if v0 * v0 + v1 * v1 + v2 * v2 > vmax2:
        mask = ALL
    # not out of the obstacles it is released from (``resolve`` kept their mask)
    x0, x1, x2 = push_out(x0 + dt * v0, x1 + dt * v1, x2 + dt * v2, ob, control.sdf_meta,
                          control.sdf_data, th, mask, released(control.contact, i))
    v[i, 0] = v0
    v[i, 1] = v1
    v[i, 2] = v2
    x[i, 0] = x0
    x[i, 1] = x1
    x[i, 2] = x2
    return w, d


@kernel(inline='always')
def _box(lo0, lo1, lo2, hi0, hi1, hi2, s2, i, x, v, dt):
    """(lo, hi, largest squared speed) grown by vertex i's old position x - dt v."""
    a0 = x[i, 0] - dt * v[i, 0]
    a1 = x[i, 1] - dt * v[i, 1]
    a2 = x[i, 2] - dt * v[i, 2]
    return (min(lo0, a0), min(lo1, a1), min(lo2, a2), max(hi0, a0), max(hi1, a1),
            max(hi2, a2), max(s2, v[i, 0] * v[i, 0] + v[i, 1] * v[i, 1] + v[i, 2] * v[i, 2]))


@kernel(refcount=False)
def contact_range(i0, i1, x, v, force, control, coeff, dt):
    """:func:`contact_vertex` for vertices i0..i1-1 (internal forces ``force``) after the
    explicit update, the obstacles first narrowed to those that may reach them
    (:func:`..contact.near_mask`); returns (work, dissipation)."""
    inf = math.inf
    lo0, lo1, lo2, hi0, hi1, hi2, s2 = inf, inf, inf, -inf, -inf, -inf, 0.0
    for i in range(i0, i1):
        lo0, lo1, lo2, hi0, hi1, hi2, s2 = _box(lo0, lo1, lo2, hi0, hi1, hi2, s2, i, x, v, dt)
    mask, vmax2 = near_mask(lo0, lo1, lo2, hi0, hi1, hi2, math.sqrt(s2), control.obstacles,
                            control.contact_params[0], dt)
    w = 0.0
    d = 0.0
    for i in range(i0, i1):
        dw, dd = contact_vertex(i, x, v, force, control, coeff, dt, mask, vmax2, False)
        w += dw
        d += dd
    return w, d


@kernel(refcount=False)
def contact_list(verts, q0, q1, x, v, force, control, coeff, dt, backward):
    """:func:`contact_range` for vertices ``verts[q0:q1]`` (``backward``: after the
    implicit step, :func:`contact_vertex`)."""
    inf = math.inf
    lo0, lo1, lo2, hi0, hi1, hi2, s2 = inf, inf, inf, -inf, -inf, -inf, 0.0
    for q in range(q0, q1):
        lo0, lo1, lo2, hi0, hi1, hi2, s2 = _box(lo0, lo1, lo2, hi0, hi1, hi2, s2, verts[q],
                                                x, v, dt)
    mask, vmax2 = near_mask(lo0, lo1, lo2, hi0, hi1, hi2, math.sqrt(s2), control.obstacles,
                            control.contact_params[0], dt)
    w = 0.0
    d = 0.0
    for q in range(q0, q1):
        dw, dd = contact_vertex(verts[q], x, v, force, control, coeff, dt, mask, vmax2,
                                backward)
        w += dw
        d += dd
    return w, d
