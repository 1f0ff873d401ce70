"""Grasp handles: sets of vertices moved as a rigid body along a pose the user commands,
and the exact wrench the handle exerts to move them.

A handle grabs vertices (those within a radius of a point, or a list), keeps their offsets
``o_i = R^T (x_i - p)`` in its frame (pose p, R at the grasp) and from then on prescribes
their motion ``x_i(t) = p(t) + R(t) o_i``. The pose follows a path of waypoints (t_k, p_k,
q_k) in sim time, linearly in position and along the shortest arc in orientation (slerp)
between two of them. A command with a duration replaces the path by one segment from
where the handle is; a command with an arrival time ``at`` keeps the waypoints before
``at``, drops those after it and ends the path there, so a controller can stream a
trajectory ahead of simulation time (at most :data:`MAX_WAYPOINTS` waypoints ahead). The
compiled step sees a prescribed velocity per vertex, constant
over one call (``Control.pin_velocity``), chosen so that each call ends exactly on the
path: the simulator splits a step(n) into calls that each turn a handle by at most
:data:`MAX_TURN` and end at the first step that reaches a waypoint (a handle is at a
waypoint on time within one step).

Reaction (``core/update.py``): a held vertex of mass m, with internal, applied,
gravity and damping forces f and velocity v_old, gets the prescribed velocity u; the
force the handle exerts on it over the step is what the update needs beyond f::

    r = m (u - v_old) / dt - f

(the balance of Eq. 29 solved for the missing force; every force of the step, contact
included once it acts on the vertex, is in f). The handle's wrench is the sum of r over
its vertices and its torque ``sum (x_i - p) x r_i`` about the handle origin. At rest it
carries the weight of what hangs from it. A break force F_b shares the grip equally:
a vertex whose |r| exceeds ``F_b / k`` (k vertices grasped) at the end of a call of the
compiled step slips out. The grip is sampled, not watched: while a handle has a break
force a call lasts at most :data:`BREAK_CHECK` (every step of the implicit solver at
1/60 s), and a pull that rises above the share and falls back within one call holds.
"""
from __future__ import annotations

import copy
import math
from typing import Dict

import numpy as np

from .contact import rotation_matrix
from .obstacles import _quaternion, _vec, id_key

__all__ = ['HandleSet', 'MAX_TURN', 'MAX_WAYPOINTS', 'turn_angle']

#: the most a handle turns within one compiled call [rad] (the chord of a turning offset
#: stays within MAX_TURN^2 / 8 of the arc, relative)
MAX_TURN = 0.02
#: [s] the longest call of the compiled step between two checks of the break forces
BREAK_CHECK = 0.005
#: the most waypoints a handle keeps ahead of simulation time (bounded work per command)
MAX_WAYPOINTS = 256


def _slerp(q0, q1, s):
    d = float(np.dot(q0, q1))
    if d < 0:
        q1, d = -q1, -d
    if d > 0.9995:
        q = q0 + s * (q1 - q0)
        return q / np.linalg.norm(q)
    a = math.acos(min(1.0, d))
    return (math.sin((1 - s) * a) * q0 + math.sin(s * a) * q1) / math.sin(a)


def turn_angle(q0, q1) -> float:
    """The angle [rad] of the turn between unit quaternions q0 and q1 (x, y, z, w), in
    [0, pi] (q and -q are the same turn)."""
    return 2.0 * math.acos(min(1.0, abs(float(np.dot(q0, q1)))))


class _Handle:
    __slots__ = ('name', 'idx', 'offsets', 'position', 'orientation', 'path',
                 'break_force')

    def pose_at(self, t):
        """The handle's pose at sim time t on its path [(t_k, p_k, q_k), ...] (before the
        first waypoint: the first; after the last: the last)."""
        path = self.path
        if not path:
            return self.position, self.orientation
        if t <= path[0][0]:
            return path[0][1], path[0][2]
        for (ta, pa, qa), (tb, pb, qb) in zip(path, path[1:]):
            if t < tb:
                s = (t - ta) / (tb - ta)
                return pa + s * (pb - pa), _slerp(qa, qb, s)
        return path[-1][1], path[-1][2]

    def segment(self, t):
        """The waypoints (a, b) of the segment under way at t, or None if not moving."""
        for a, b in zip(self.path, self.path[1:]):
            if t < b[0] - 1e-12:
                return a, b
        return None


class HandleSet:
    """The handles of one simulator (module docstring)."""

    def __init__(self):
        self._items: Dict[int, _Handle] = {}
        self._next = 0

    def __len__(self):
        return len(self._items)

    def _item(self, hid) -> _Handle:
        return self._items[id_key(self._items, hid, 'handle')]

    def snapshot(self):
        """Everything :meth:`restore_snapshot` needs to undo later changes: a copy of each
        handle's slots (they are only ever assigned anew, never changed in place)."""
        return {hid: copy.copy(h) for hid, h in self._items.items()}, self._next

    def restore_snapshot(self, snap) -> None:
        """Back to the snapshot (copied again, so it can be restored more than once)."""
        self._items = {hid: copy.copy(h) for hid, h in snap[0].items()}
        self._next = snap[1]

    def held(self) -> np.ndarray:
        """Indices of every vertex some handle holds."""
        if not self._items:
            return np.zeros(0, dtype=np.int64)
        return np.concatenate([h.idx for h in self._items.values()])

    def grasp(self, x, point, radius, vertices, name, break_force,
              orientation=(0.0, 0.0, 0.0, 1.0)) -> int:
        n = len(x)
        if vertices is not None:
            idx = np.unique(np.asarray(vertices, dtype=np.int64).reshape(-1))
            if len(idx) == 0 or idx.min() < 0 or idx.max() >= n:
                raise ValueError(f'vertices must be indices in [0, {n - 1}]')
            p = (_vec(point, 'point') if point is not None else x[idx].mean(0))
        else:
            if point is None or radius is None:
                raise ValueError('grasp needs point and radius, or vertices')
            p = _vec(point, 'point')
            r = float(radius)
            if not (math.isfinite(r) and r > 0):
                raise ValueError(f'radius must be positive and finite, got {radius!r}')
            idx = np.flatnonzero(np.linalg.norm(x - p, axis=1) <= r)
            if len(idx) == 0:
                raise ValueError(f'no vertex within {r} m of {tuple(p)}')
        if break_force is not None:
            break_force = float(break_force)
            if not (math.isfinite(break_force) and break_force > 0):
                raise ValueError(f'break_force must be positive, got {break_force!r}')
        taken = np.intersect1d(idx, self.held())
        if len(taken):
            raise ValueError(f'vertices {taken[:5].tolist()} are held by another handle')
        if name is None:
            name = f'handle_{self._next}'
        name = str(name)
        if any(h.name == name for h in self._items.values()):
            raise ValueError(f'a handle named {name!r} exists already')
        h = _Handle()
        h.name, h.idx, h.break_force = name, idx, break_force
        q = _quaternion(orientation)
        h.position, h.orientation = p.copy(), q
        h.offsets = (x[idx] - p) @ rotation_matrix(q)          # R^T (x - p), row-wise
        h.path = []
        hid = self._next
        self._next += 1
        self._items[hid] = h
        return hid

    def move(self, hid, t, dt, position, orientation, duration=None, at=None) -> None:
        """Head for (position, orientation) from sim time t: over ``duration`` [s] (at
        least a step; None: one step), replacing the path; or arriving at sim time ``at``
        (> t), after the waypoints before ``at`` (those after it are dropped)."""
        h = self._item(hid)
        p1 = _vec(position, 'position')
        q1 = _quaternion(orientation)
        p0, q0 = h.pose_at(t)
        if at is None:
            if duration is None:
                duration = dt
            duration = float(duration)
            if not (math.isfinite(duration) and duration >= 0):
                raise ValueError(f'duration must be >= 0, got {duration!r}')
            kept = []
            at = t + max(duration, dt)
        else:
            if duration is not None:
                raise ValueError('give duration or at, not both')
            at = float(at)
            if not (math.isfinite(at) and at > t):
                raise ValueError(f'at must be a sim time after the present {t!r} s, '
                                 f'got {at!r}')
            kept = [w for w in h.path if t < w[0] < at]
            if len(kept) >= MAX_WAYPOINTS:
                raise ValueError(f'{len(kept)} waypoints ahead already, at most '
                                 f'{MAX_WAYPOINTS}')
        h.position, h.orientation = p0, q0
        h.path = [(t, p0.copy(), q0.copy())] + kept + [(at, p1, q1)]

    def waypoints(self, hid, t) -> list:
        """[(t_k, position, orientation)]: the pose at t, then the waypoints ahead."""
        h = self._item(hid)
        p, q = h.pose_at(t)
        return [(t, p.copy(), q.copy())] + [(w[0], w[1].copy(), w[2].copy())
                                            for w in h.path if w[0] > t]

    def release(self, hid) -> np.ndarray:
        return self._items.pop(id_key(self._items, hid, 'handle')).idx

    def describe(self, t) -> Dict[int, dict]:
        out = {}
        for hid, h in self._items.items():
            p, q = h.pose_at(t)
            out[hid] = {'name': h.name, 'vertices': h.idx.copy(), 'position': tuple(p),
                        'orientation': tuple(q), 'moving': self._moving(h, t),
                        'break_force': h.break_force}
        return out

    @staticmethod
    def _moving(h, t) -> bool:
        return bool(h.path) and t < h.path[-1][0] - 1e-12

    def moving(self, t) -> bool:
        return any(self._moving(h, t) for h in self._items.values())

    def plan(self, t, dt, n) -> int:
        """Steps of the next call (at most n): to the first step that reaches the nearest
        waypoint, no more than a turn of :data:`MAX_TURN` for any handle, and with a
        break force at most :data:`BREAK_CHECK` seconds between two checks of it."""
        k = n
        if any(h.break_force is not None for h in self._items.values()):
            k = min(k, max(1, int(BREAK_CHECK / dt)))
        for h in self._items.values():
            seg = h.segment(t)
            if seg is None:
                continue
            (ta, _, qa), (tb, _, qb) = seg
            left = max(1, int(math.ceil((tb - t) / dt - 1e-9)))
            k = min(k, left)
            turn = turn_angle(qa, qb) / (tb - ta) * dt                   # per step
            if turn > 0:
                k = min(k, max(1, int(MAX_TURN / turn)))
        return max(1, k)

    def rebase(self, x) -> None:
        """Positions were set from outside: each handle holds its vertices where they
        are now, their offsets ``R^T (x - p)`` taken again at its pose."""
        for h in self._items.values():
            h.offsets = (x[h.idx] - h.position) @ rotation_matrix(h.orientation)

    def prescribe(self, x, t, dt, k, pin_velocity) -> None:
        """The velocity of every held vertex over the next k steps from t: to its place on
        the path at t + k dt (zero for a handle at rest)."""
        for h in self._items.values():
            if not self._moving(h, t):
                pin_velocity[h.idx] = 0.0
                continue
            p, q = h.pose_at(t + k * dt)
            target = p + h.offsets @ rotation_matrix(q).T
            pin_velocity[h.idx] = (target - x[h.idx]) / (k * dt)

    def settle(self, t) -> None:
        """After a call: the handles' poses at t (motions done are dropped)."""
        for h in self._items.values():
            h.position, h.orientation = h.pose_at(t)
            if h.path:
                ahead = [w for w in h.path if w[0] > t + 1e-12]
                h.path = ([(t, h.position.copy(), h.orientation.copy())] + ahead
                          if ahead else [])

    def wrench(self, hid, x, reaction):
        h = self._item(hid)
        r = reaction[h.idx]
        return r.sum(0), np.cross(x[h.idx] - h.position, r).sum(0)

    def broken(self, reaction) -> np.ndarray:
        """Vertices pulled harder than their share of their handle's break force; they
        leave their handle."""
        out = []
        for hid, h in list(self._items.items()):
            if h.break_force is None:
                continue
            pull = np.linalg.norm(reaction[h.idx], axis=1)
            slip = pull > h.break_force / len(h.idx)
            if not slip.any():
                continue
            out.append(h.idx[slip])
            keep = ~slip
            h.idx, h.offsets = h.idx[keep], h.offsets[keep]
            if not len(h.idx):
                del self._items[hid]
        return np.concatenate(out) if out else np.zeros(0, dtype=np.int64)
