"""Contact with obstacles inside the implicit solve: each vertex that reaches an obstacle's
contact layer in the step is a constraint of the backward-Euler solve, not a correction
after it.

Why not after it
----------------
The explicit update answers contact after each small step (:mod:`..contact`): the impulse
that stops a vertex is ``m du / dt`` and the elastic forces hardly change within one step.
Backward Euler at dt = 1/30 s moves a stiff cloth to its relaxed shape in one step, so a
correction after the solve fights it:

* friction judged on the solved velocity sticks far too easily: a vertex whose strain
  would relax by ``delta`` in the step moves at ``delta / dt``, and the per-step friction
  test ``delta / dt <= mu g dt`` holds for a force ``k delta`` that is ``k dt^2 / m``
  times the friction limit, so the cloth lands with strain locked in;
* the vertices put back on the layer strain the cloth the solve just relaxed; measured on
  a 16x16 cloth dropped tilted onto the ground at dt = 1/30 s: the total energy rose from
  0.13 J to 0.45 J after impact and 0.11 J of strain stayed at rest (the explicit solver:
  no rise, no strain left).

The constraints (an active set, as Baraff & Witkin 1998, "Large steps in cloth
simulation", Sec. 5.3, filter the conjugate gradients of their implicit step)
-------------------------------------------------------------------------------------
For a free vertex i with start position ``x``, end position ``x'``, an obstacle k with
distance ``d`` and outward normal ``n`` at ``x`` and velocity ``v_o`` there, the end
position's gap, linearised at ``x`` as the explicit contact does (so that a step that
would carry the vertex through a thin obstacle is caught by the tangent plane)::

    g(x') = d - th + n . (x' - x - v_o dt)

Where ``g(x') < 0`` for the solve's ``x'``, the vertex is constrained:

* STICK: ``x' = x + v_o dt - max(d - th, 0) n`` (it ends on the layer, or stays where it
  is in it, and moves with the obstacle): its three coordinates leave the solve like a
  pin's;
* SLIDE: only its normal coordinate is fixed, ``n . (x' - x) = n . v_o dt - max(d - th,
  0)``; the tangential ones stay free, and the kinetic friction force ``-mu_k f_n s /
  |s|`` (``s`` the tangential slip) enters the step as an applied force.

The solve's residual at a constrained coordinate is the constraint force on the vertex
(``f_c = m (x' - y) / dt^2 + c (x' - x) / dt - f_int(x')``, the force the rest of the
step leaves unbalanced); its normal part ``f_n = f_c . n`` and tangential part ``f_t``
decide the set, the Signorini and Coulomb conditions:

* ``f_n <= 0``: the obstacle would pull: the vertex is released;
* STICK with ``|f_t| > mu_s f_n``: static friction cannot hold it: SLIDE, its friction
  ``mu_k f_n f_t / |f_t|`` (the direction that would have held it);
* SLIDE whose slip turned against its friction force: friction stopped it: STICK;
* a free vertex whose solved position is inside the layer: STICK.

and the step is solved again from where it ended (the friction of a sliding vertex is
lagged: its normal force and direction from the last solve). A vertex changes between
stick and slide once per step at most; after :data:`ROUNDS` solves only vertices a solve
took inside a layer join the set (at most :data:`ADDS` more solves), so that none is
left to a correction after the solve, which would move it without its neighbours (a
vertex the last of them takes inside a layer is: it stays free, and the explicit
contact's correction answers it, :func:`..update.contact_list`). A
vertex inside the layer at the step's start is held where it is, not pushed out by the
solve: :func:`..contact.push_out` puts it back on the layer afterwards, a position
change without velocity as in the explicit update. Each vertex takes the obstacle whose
linearised gap is the most negative; a sliding vertex that a solve takes into a second
obstacle's layer (a corner, its normal at least :data:`SIN_CORNER` from parallel to the
first's) sticks where it is moved onto the second's layer without entering the first's
(``ObstacleConstraints._corner``; this step: sliding along the corner's line is the next
step's). Its contact force is reported as both obstacles': each takes its normal push,
and the friction along the corner's line is shared in proportion to them
(``ObstacleConstraints._second_part``).

The contact force on a constrained vertex is written into ``Control.contact`` as the
explicit update writes it, and its work is split as there: ``f_c . v_o dt`` is the
obstacle's work on the cloth, ``-f_c . (x' - x - v_o dt) >= 0`` is dissipated (an
inelastic approach, sliding friction; zero when sticking).
"""
from __future__ import annotations

import math

import numpy as np

from ..compiled import kernel
from ..contact import (ALL, C_FORCE, C_FORCE2, C_GAP, C_ID, C_ID2, MU_K, MU_S, SPEED, _bit,
                       _far, _point_velocity, _store_released, distance, push_out, released)

__all__ = ['ObstacleConstraints', 'FREE', 'STICK', 'SLIDE', 'ROUNDS', 'ADDS', 'SIN_CORNER',
           'frames', 'push_list', 'warm']

FREE, STICK, SLIDE = 0, 1, 2
#: solves per step that may change the set any way (the first plus re-solves after the
#: set changed), then at most :data:`ADDS` more that only add vertices to it
ROUNDS = 4
ADDS = 4
#: the sine of the least angle between two obstacles' normals that makes a corner of them
#: (:meth:`ObstacleConstraints._corner`): about 11.5 degrees
SIN_CORNER = 0.2


@kernel()
def frames(x, pred, free, dt, ob, meta, data, th, skip, k_out, d_out, n_out, vo_out,
           contact):
    """For every free vertex i: of the obstacles whose linearised gap at ``pred[i]``
    (module docstring) is negative, the one where it is the most negative, obstacle
    ``skip[i]`` left out: its row (``k_out``, -1 for none), distance ``d`` [m], normal
    and velocity at ``x[i]``. An obstacle vertex i is released from (its
    :func:`..contact.released` mask in ``contact``) is left out while ``x[i]`` is
    inside its layer, and found outside it, releases it no more (as
    :func:`..contact.resolve` does)."""
    for i in range(x.shape[0]):
        k_out[i] = -1
        if not free[i]:
            continue
        x0 = x[i, 0]
        x1 = x[i, 1]
        x2 = x[i, 2]
        e0 = pred[i, 0] - x0
        e1 = pred[i, 1] - x1
        e2 = pred[i, 2] - x2
        reach = math.sqrt(e0 * e0 + e1 * e1 + e2 * e2)
        best = 0.0
        rel = released(contact, i)
        for k in range(ob.shape[0]):
            if k == skip[i]:
                continue
            bit = _bit(k)
            if _far(ob, k, x0, x1, x2, th + reach + dt * ob[k, SPEED]):
                rel &= ~bit
                continue
            d, n0, n1, n2 = distance(ob, meta, data, k, x0, x1, x2)
            if rel & bit:
                if d < th:
                    continue
                rel &= ~bit
            o0, o1, o2 = _point_velocity(ob, k, x0, x1, x2)
            g = d - th + n0 * (e0 - dt * o0) + n1 * (e1 - dt * o1) + n2 * (e2 - dt * o2)
            if g < best:
                best = g
                k_out[i] = k
                d_out[i] = d
                n_out[i, 0] = n0
                n_out[i, 1] = n1
                n_out[i, 2] = n2
                vo_out[i, 0] = o0
                vo_out[i, 1] = o1
                vo_out[i, 2] = o2
        _store_released(contact, i, rel)


@kernel()
def push_list(verts, x, ob, meta, data, th, contact):
    """:func:`..contact.push_out` for vertices ``verts`` (positions only; not out of
    the obstacles each is released from, its mask in ``contact``)."""
    for q in range(verts.shape[0]):
        i = verts[q]
        x[i, 0], x[i, 1], x[i, 2] = push_out(x[i, 0], x[i, 1], x[i, 2], ob, meta, data, th,
                                            ALL, released(contact, i))


class ObstacleConstraints:
    """The active set of one implicit step (module docstring); per-vertex arrays of
    ``n`` vertices. The mode and normal force of the last step carry over to the next
    (a vertex that slid starts sliding)."""

    def __init__(self, n: int):
        self.mode = np.zeros(n, np.int8)
        self.row = np.full(n, -1, np.int64)
        self.d = np.zeros(n)
        self.normal = np.zeros((n, 3))
        self.vo = np.zeros((n, 3))
        self.friction = np.zeros((n, 3))
        self.target = np.zeros((n, 3))       # where a sticking vertex ends the step
        self.fn = np.zeros(n)                # the last normal force [N], carried over
        self.switched = np.zeros(n, bool)    # changed between stick and slide this step
        self.row2 = np.full(n, -1, np.int64)  # a corner's second obstacle (``_corner``)
        self.normal2 = np.zeros((n, 3))       # and its normal
        self._k = np.full(n, -1, np.int64)
        self._d = np.zeros(n)
        self._n = np.zeros((n, 3))
        self._vo = np.zeros((n, 3))
        self._none = np.full(n, -1, np.int64)

    def clear(self) -> None:
        """Forget what carries over from the last step (the modes, the normal forces):
        the next step starts as without a last one."""
        self.mode[:] = FREE
        self.fn[:] = 0.0
        self.friction[:] = 0.0

    # ------------------------------------------------------------------ the set
    def _find(self, xn, pred, free, control, dt, skip=None):
        """Rows etc. of the vertices whose linearised gap at ``pred`` is negative (for
        an obstacle other than ``skip``'s, per vertex): a boolean mask; the frames in the
        ``_k.._vo`` scratch arrays."""
        frames(xn, pred, free, dt, control.obstacles, control.sdf_meta, control.sdf_data,
               control.contact_params[0], self._none if skip is None else skip, self._k,
               self._d, self._n, self._vo, control.contact)
        return self._k >= 0

    def _take(self, sel):
        self.row[sel] = self._k[sel]
        self.row2[sel] = -1
        self.d[sel] = self._d[sel]
        self.normal[sel] = self._n[sel]
        self.vo[sel] = self._vo[sel]

    def begin(self, xn, vn, pred, free, control, dt) -> None:
        """The set at the step's start: the vertices whose predicted position ``pred``
        (no internal forces) reaches a layer; those that slid in the last step slide on
        with friction against their relative velocity and the last normal force."""
        hit = self._find(xn, pred, free, control, dt)
        slid = self.mode == SLIDE
        self.mode[:] = FREE
        self.switched[:] = False
        self.friction[:] = 0.0
        self._take(hit)
        self.mode[hit] = STICK
        th = control.contact_params[0]
        self.target[hit] = (xn + dt * self.vo
                            - np.maximum(self.d - th, 0.0)[:, None] * self.normal)[hit]
        sl = np.flatnonzero(hit & slid & (self.fn > 0.0))
        if len(sl):
            nrm = self.normal[sl]
            u = vn[sl] - self.vo[sl]
            ut = u - np.sum(u * nrm, 1)[:, None] * nrm
            s = np.linalg.norm(ut, axis=1)
            go = s > 0.0
            sl, ut, s = sl[go], ut[go], s[go]
            mu_k = control.obstacles[self.row[sl], MU_K]
            self.mode[sl] = SLIDE
            self.friction[sl] = -(mu_k * self.fn[sl] / s)[:, None] * ut

    @property
    def active(self) -> bool:
        return bool(np.any(self.mode != FREE))

    def project(self, xn, xk, dt, th) -> None:
        """Put the constrained vertices of ``xk`` where their constraints hold."""
        st = self.mode == STICK
        xk[st] = self.target[st]
        sl = self.mode == SLIDE
        if sl.any():
            xk[sl] = self._onto_plane(xn, xk, dt, th, sl)

    def _onto_plane(self, xn, xk, dt, th, sel):
        """``xk`` of vertices ``sel`` moved along their normal onto their constraint's
        plane ``n . (x' - x) = n . v_o dt - max(d - th, 0)``."""
        nrm = self.normal[sel]
        c = np.sum(dt * self.vo[sel] * nrm, 1) - np.maximum(self.d[sel] - th, 0.0)
        return xk[sel] + (c - np.sum((xk - xn)[sel] * nrm, 1))[:, None] * nrm

    def filter(self, a) -> None:
        """Remove the constrained components of a per-vertex field (n,3), in place."""
        a[self.mode == STICK] = 0.0
        sl = self.mode == SLIDE
        if sl.any():
            nrm = self.normal[sl]
            a[sl] -= np.sum(a[sl] * nrm, 1)[:, None] * nrm

    def update(self, xn, xk, r, free, control, dt, adds_only=False) -> bool:
        """The Signorini and Coulomb checks (module docstring) on the solve that ended at
        ``xk`` with raw residual ``r`` (the constraint forces); True if the set changed
        (then the step is solved again). A vertex changes between stick and slide once
        per step at most (so the set settles: sticking and sliding neighbours otherwise
        trade places from solve to solve). ``adds_only``: after :data:`ROUNDS` solves
        only vertices the solve took inside a layer join (the set grows, so this ends),
        so that none is left to the correction after the solve, which moves a vertex
        without its neighbours (5 mm, straining the cloth, in a crumpling drop)."""
        ob = control.obstacles
        nrm = self.normal
        fn = np.sum(r * nrm, 1)
        con = self.mode != FREE
        self.fn[con] = fn[con]
        # released in every round, adds-only included: a sliding vertex the obstacle
        # pulls would otherwise keep a friction that pushes it along its slip, and a
        # sticking one a negative contact force; an adds-only round does not solve
        # again for it (it leaves the layer in the next step)
        release = con & ~(fn > 0.0)
        changed = bool(release.any()) and not adds_only
        self.mode[release] = FREE
        self.friction[release] = 0.0
        self.row2[release] = -1
        st = np.flatnonzero((self.mode == STICK) & ~self.switched & (not adds_only))
        if len(st):
            ft = r[st] - fn[st, None] * nrm[st]
            a = np.linalg.norm(ft, axis=1)
            out = a > ob[self.row[st], MU_S] * fn[st]
            if out.any():
                changed = True
                q = st[out]
                self.mode[q] = SLIDE
                self.switched[q] = True
                self.friction[q] = (ob[self.row[q], MU_K] * fn[q] / a[out])[:, None] * ft[out]
        sl = np.flatnonzero(self.mode == SLIDE)
        if len(sl):
            s = xk[sl] - xn[sl] - dt * self.vo[sl]
            s -= np.sum(s * nrm[sl], 1)[:, None] * nrm[sl]
            back = (np.sum(s * self.friction[sl], 1) > 0.0) & ~self.switched[sl] & (
                not adds_only)
            if back.any():                        # friction stopped it
                changed = True
                q = sl[back]
                self.mode[q] = STICK
                self.switched[q] = True
                self.friction[q] = 0.0
                self.target[q] = xk[q]               # where friction stopped it
            go = ~back
            q, s = sl[go], s[go]
            a = np.linalg.norm(s, axis=1)
            moving = a > 0.0
            q, s, a = q[moving], s[moving], a[moving]
            self.friction[q] = -(ob[self.row[q], MU_K] * fn[q] / a)[:, None] * s
        # a sliding vertex the solve took into a second obstacle's layer (a corner: the
        # floor and a wall) sticks on the second's layer, out of the first's (``_corner``):
        # its one constraint held it on the first only, and a push onto the second after
        # the solve moved it without its neighbours (a frictionless corner's cloth
        # rebounded, its strain energy rising by 4e-3 J in a step)
        sl = self.mode == SLIDE
        if sl.any():
            two = self._find(xn, xk, sl, control, dt, skip=self.row)
            q = np.flatnonzero(two)
            q = q[self._corner(q, xn, xk, dt, control)]
            if len(q):
                changed = True
                self.mode[q] = STICK
                self.switched[q] = True
                self.friction[q] = 0.0
        new = self._find(xn, xk, free & (self.mode == FREE) & ~release, control, dt)
        if new.any():
            # held where the solve took it, on the layer: the solve that follows starts
            # near where this one ended
            changed = True
            self._take(new)
            self.mode[new] = STICK
            self.target[new] = self._onto_plane(xn, xk, dt, control.contact_params[0], new)
        return changed

    def _corner(self, q, xn, xk, dt, control) -> np.ndarray:
        """Of the sliding vertices ``q`` that the solve took into a second obstacle's
        layer (its distance, normal and velocity in the ``_d, _n, _vo`` scratch,
        :meth:`_find`), those that stick in a corner (a mask over q), and where: the
        nearest place that closes the second's gap as a STICK constraint closes it
        (module docstring), ``g2 = max(d2 - th, 0) + n2 . (xk - x - v2 dt) < 0`` made 0,
        and does not enter the first's layer (whose constraint only pushes: the vertex
        may leave it). With ``c = n1 . n2``:

        * ``c >= 0`` (a right angle, or an obtuse crease, a floor meeting a ramp): straight
          out of the second's layer, ``x' = xk - g2 n2``; the first's gap grows by
          ``-c g2 >= 0`` (the vertex rides up the ramp);
        * ``c < 0`` (a wedge narrower than a right angle): along the part of n2 in the
          first's plane, ``t = n2 - c n1``, ``x' = xk - g2 t / |t|^2``, a move of
          ``|g2| / sin``; straight out would enter the first's layer.

        Either way a vertex the first held inside its layer stays at its depth (a push
        onto that layer would become velocity: 0.06 m/s from half a 2 mm layer at 1/60
        s; the correction after the solve puts it back without velocity), the second is
        met where it is at the step's end (a wall moving at v2 pushes the vertex with it),
        and a vertex inside the second's layer stays at its depth there. Its obstacle
        velocity for the ledger (:meth:`finish`) becomes ``v1 + (n2 . (v2 - v1)) u / (n2
        . u)`` with u the move's direction, whose part along n2 is the second's.

        No corner where the normals are within :data:`SIN_CORNER` of parallel: nearly the
        same (a seam between two flush obstacles: the first's plane keeps the vertex near
        the second's layer, and sticking there would catch a frictionless cloth) or
        nearly opposite (a pinch: no place outside both layers is near; the move along t
        would be the gap over the sine); the vertex slides on, and the correction after
        the solve answers the second. Where the corner's place is inside a third
        obstacle's layer (the inside corner of a box), the vertex sticks where
        :func:`..contact.push_out` puts it out of every layer (at the step's start
        poses), as before this rule."""
        th = control.contact_params[0]
        n1, n2, v2 = self.normal[q], self._n[q], self._vo[q]
        second = self._k[q]
        c = np.sum(n1 * n2, 1)
        s2 = 1.0 - c * c                          # sin^2 of the angle
        g2 = (np.maximum(self._d[q] - th, 0.0)
              + np.sum(n2 * (xk[q] - xn[q] - dt * v2), 1))
        # one moving out of the second is no corner, nor one between near-parallel normals
        ok = (g2 < 0.0) & (s2 >= SIN_CORNER ** 2)
        q, n1, n2, v2, second, c, s2, g2 = (a[ok] for a in (q, n1, n2, v2, second, c, s2, g2))
        wedge = c < 0.0
        u = np.where(wedge[:, None], n2 - c[:, None] * n1, n2)     # the move's direction
        nu = np.where(wedge, s2, 1.0)                              # n2 . u
        self.target[q] = xk[q] - (g2 / nu)[:, None] * u          # nu >= SIN_CORNER^2
        self.row2[q] = second
        self.normal2[q] = n2
        v1 = self.vo[q]
        self.vo[q] = v1 + (np.sum(n2 * (v2 - v1), 1) / nu)[:, None] * u
        if len(q):
            # a corner's place inside a third obstacle's layer: out of every layer
            mask = np.zeros(len(xk), bool)
            mask[q] = True
            self._find(xn, self.target, mask, control, dt, skip=self.row)
            third = (self._k[q] >= 0) & (self._k[q] != second)
            if third.any():
                rest = q[third]
                t = xk.copy()
                push_list(rest, t, control.obstacles, control.sdf_meta, control.sdf_data, th,
                          control.contact)
                self.target[rest] = t[rest]
                self.vo[rest] = v1[third]
                self.row2[rest] = -1
        return ok

    # ------------------------------------------------------------------ the end
    def _second_part(self, q, force):
        """The second obstacle's part of the contact force ``force[q]`` on corner
        vertices q (``_corner``), the rest being the first's: the force's part in the
        plane of the two normals, ``a n1 + b n2``, gives each obstacle its normal push
        (a negative one, a pull, is the other's), and the rest, along the corner's line
        (friction), is shared in proportion to the pushes."""
        f = force[q]
        n1, n2 = self.normal[q], self.normal2[q]
        c = np.sum(n1 * n2, 1)
        f1, f2 = np.sum(f * n1, 1), np.sum(f * n2, 1)
        det = 1.0 - c * c                         # >= SIN_CORNER^2 (``_corner``)
        a = (f1 - c * f2) / det
        b = (f2 - c * f1) / det
        a, b = np.maximum(a, 0.0), np.maximum(b, 0.0)
        line = f - a[:, None] * n1 - b[:, None] * n2
        share = np.where(a + b > 0.0, b / np.maximum(a + b, 1e-300), 0.5)
        return b[:, None] * n2 + share[:, None] * line

    def finish(self, xn, xk, force, control, dt):
        """Write the constrained vertices' contact rows (``force`` (n,3): the contact
        force on each vertex over the step) and return (their indices, obstacle work
        [J], dissipation [J])."""
        q = np.flatnonzero(self.mode != FREE)
        th = control.contact_params[0]
        c = control.contact
        c[q, C_FORCE:C_FORCE + 3] = force[q]
        c[q, C_ID] = self.row[q]
        c[q, C_GAP] = self.d[q] - th
        c[q, C_FORCE2:C_FORCE2 + 3] = 0.0
        c[q, C_ID2] = -1.0
        corner = q[(self.mode[q] == STICK) & (self.row2[q] >= 0)]
        if len(corner):
            c[corner, C_FORCE2:C_FORCE2 + 3] = self._second_part(corner, force)
            c[corner, C_ID2] = self.row2[corner]
        self.fn[self.mode == FREE] = 0.0
        move = dt * self.vo[q]
        work = float(np.sum(force[q] * move))
        diss = -float(np.sum(force[q] * (xk[q] - xn[q] - move)))
        return q, work, diss


def warm(x, control) -> None:
    """Compile :func:`frames` and :func:`push_list` (for the node's warm-up)."""
    n = x.shape[0]
    c = ObstacleConstraints(n)
    c._find(x, x, np.zeros(n, np.bool_), control, 1e-3)
    push_list(np.zeros(0, np.int64), x, control.obstacles, control.sdf_meta,
              control.sdf_data, control.contact_params[0], control.contact)
