"""The node's force inputs: ``~/vertex_forces``, ``~/point_forces``, ``~/force_field`` and
``~/wind``, their limits (``max_force``, ``max_acceleration``, ``max_wind``) and their
lapse after ``force_timeout`` seconds of simulation time.

A message is parsed and checked by :mod:`.commands`; what it leaves standing is kept here
with the simulation time it arrived at, and handed to the simulator. A refused message
goes to the node's rejections (:class:`.status.Rejections`) and changes nothing.
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Dict, Optional, Tuple

import numpy as np
from geometry_msgs.msg import Vector3Stamped
from std_msgs.msg import Float64MultiArray

from . import commands

__all__ = ['Inputs']


@dataclass
class _Force:
    indices: np.ndarray
    forces: np.ndarray
    received: float                     # [s] sim time


def _vector_values(v) -> Dict[str, object]:
    """A Vector3's components as the offending values of a rejection."""
    return {'x': float(v.x), 'y': float(v.y), 'z': float(v.z)}


class Inputs:
    """The standing commanded forces, force field and streamed wind of a node.

    ``node`` gives ``sim``, ``mesh``, ``frame_id``, ``get_logger`` and ``reject``;
    ``p`` is the node's parameter values at start-up; ``steady_wind`` is ``air.wind``."""

    def __init__(self, node, p: dict, steady_wind: np.ndarray):
        self.node = node
        self.sim = node.sim
        self.force_timeout = p['force_timeout']      # [s] sim time; 0: hold
        self.max_force = p['max_force']              # [N] per vertex
        self.max_acceleration = p['max_acceleration']   # [m/s^2]
        self.max_wind = p['max_wind']                # [m/s]
        self._steady_wind = steady_wind              # air.wind [m/s]
        self.forces: Dict[str, Optional[_Force]] = {'vertex': None, 'point': None}
        self.field: Optional[Tuple[np.ndarray, float]] = None    # (a [m/s^2], received)
        self.wind: Optional[Tuple[np.ndarray, float]] = None     # (v [m/s], received)

    def subscribe(self, sized):
        """The four input topics; ``sized(topic, type, limit, handler)`` wraps a raw
        subscription's callback with a size limit (:meth:`.node.ClothNode._sized`)."""
        node = self.node
        node.create_subscription(
            Float64MultiArray, '~/vertex_forces',
            sized('vertex_forces', Float64MultiArray, commands.MAX_FORCE_BYTES,
                  self.on_vertex_forces), 10, raw=True)
        node.create_subscription(
            Float64MultiArray, '~/point_forces',
            sized('point_forces', Float64MultiArray, commands.MAX_FORCE_BYTES,
                  self.on_point_forces), 10, raw=True)
        node.create_subscription(Vector3Stamped, '~/force_field', self.on_force_field, 10)
        node.create_subscription(Vector3Stamped, '~/wind', self.on_wind, 10)

    # ------------------------------------------------------------------ messages
    def on_vertex_forces(self, msg: Float64MultiArray):
        """Rows [index, fx, fy, fz] [N]; replaces the previous set (empty: clear)."""
        try:
            rows = commands.force_rows(msg, 4, self.max_force)
            idx, f = commands.vertex_forces(rows, self.node.mesh.n_vertices)
            self._check_totals('point', idx, f)
        except commands.CommandError as exc:
            self.node._reject('vertex_forces', str(exc))
            return
        self.forces['vertex'] = _Force(idx, f, self.sim.time)
        self._push_forces()

    def on_point_forces(self, msg: Float64MultiArray):
        """Rows [px, py, pz, fx, fy, fz] in frame_id: each force goes to the closest point
        of the cloth (shared by its triangle's vertices, barycentrically) and stays with
        that material point until replaced."""
        try:
            rows = commands.force_rows(msg, 6, self.max_force)
            idx, f = commands.point_forces(rows, self.sim.positions, self.node.mesh.faces)
            self._check_totals('vertex', idx, f)
        except commands.CommandError as exc:
            self.node._reject('point_forces', str(exc))
            return
        self.forces['point'] = _Force(idx, f, self.sim.time)
        self._push_forces()

    def on_force_field(self, msg: Vector3Stamped):
        """Uniform force per unit mass [m/s^2] in frame_id ('' is taken as frame_id)."""
        try:
            v = commands.force_field(msg, self.node.frame_id, self.max_acceleration)
        except commands.CommandError as exc:
            self.node._reject('force_field', str(exc), values=_vector_values(msg.vector))
            return
        self.field = (v, self.sim.time)
        self.sim.force_field = v

    def on_wind(self, msg: Vector3Stamped):
        """Wind velocity [m/s] in frame_id, until it lapses (force_timeout; then back to
        air.wind); refused while air.enabled is false, since it would move nothing."""
        try:
            if self.sim.air is None:
                raise commands.CommandError('air.enabled is false: wind acts only on a cloth '
                                            'in air')
            v = commands.wind(msg, self.node.frame_id, self.max_wind)
        except commands.CommandError as exc:
            self.node._reject('wind', str(exc), values=_vector_values(msg.vector))
            return
        self.wind = (v, self.sim.time)
        self.sim.wind = v

    def _check_totals(self, other: str, idx: np.ndarray, f: np.ndarray):
        """``max_force`` bounds the total on each vertex: this message's rows with the
        standing forces of the ``other`` topic."""
        o = self.forces[other]
        if o is not None:
            idx, f = np.concatenate([idx, o.indices]), np.concatenate([f, o.forces])
        commands.check_totals(idx, f, self.node.mesh.n_vertices, self.max_force)

    # ------------------------------------------------------------------ what stands
    def _push_forces(self):
        parts = [f for f in self.forces.values() if f is not None]
        if parts:
            self.sim.set_vertex_forces(np.concatenate([p.indices for p in parts]),
                                       np.concatenate([p.forces for p in parts]))
        else:
            self.sim.clear_vertex_forces()

    def drop_field(self):
        """The commanded force field ends (lapsed or above a lowered limit)."""
        self.field = None
        self.sim.force_field = (0.0, 0.0, 0.0)

    def drop_wind(self):
        """The streamed wind ends (lapsed, above a lowered limit, air off): back to the
        steady ``air.wind``."""
        self.wind = None
        self.sim.wind = self.steady_wind

    @property
    def steady_wind(self) -> np.ndarray:
        """``air.wind`` [m/s]; set, it blows unless a streamed wind stands."""
        return self._steady_wind

    @steady_wind.setter
    def steady_wind(self, value):
        self._steady_wind = np.array(value, dtype=np.float64)
        if self.wind is None:
            self.sim.wind = self._steady_wind

    def enforce_limits(self):
        """A lowered ``max_force``, ``max_acceleration`` or ``max_wind`` also bounds what
        stands (a command is checked when it arrives, and with ``force_timeout`` 0 it
        stands until replaced): the commanded forces, the force field or the streamed
        wind above it are dropped, and the log says so."""
        log = self.node.get_logger()
        parts = [f for f in self.forces.values() if f is not None]
        if parts:
            try:
                commands.check_totals(np.concatenate([f.indices for f in parts]),
                                      np.concatenate([f.forces for f in parts]),
                                      self.node.mesh.n_vertices, self.max_force)
            except commands.CommandError as exc:
                self.forces = {key: None for key in self.forces}
                self._push_forces()
                log.warning(f'commanded forces dropped: {exc}')
        if (self.field is not None
                and float(np.linalg.norm(self.field[0])) > self.max_acceleration):
            self.drop_field()
            log.warning('force field dropped: above the new max_acceleration')
        if self.wind is not None and float(np.linalg.norm(self.wind[0])) > self.max_wind:
            self.drop_wind()
            log.warning('streamed wind dropped: above the new max_wind; back to air.wind')

    def expire(self, now: float):
        """At sim time ``now`` [s]: the commands not renewed for ``force_timeout`` s of
        sim time lapse (a node slower than real time gives a client that paces on /clock
        the same time to renew them as one at full speed)."""
        if self.force_timeout <= 0:
            return
        log = self.node.get_logger()
        changed = False
        for key, f in self.forces.items():
            if f is not None and now - f.received > self.force_timeout:
                self.forces[key] = None
                changed = True
                log.info(f'{key} forces lapsed after {self.force_timeout} s of sim time '
                         'without a new message')
        if changed:
            self._push_forces()
        if self.field is not None and now - self.field[1] > self.force_timeout:
            self.drop_field()
            log.info('force field lapsed')
        if self.wind is not None and now - self.wind[1] > self.force_timeout:
            self.drop_wind()
            log.info('wind lapsed: back to air.wind')

    def restart(self):
        """After a reset to t = 0: the standing commands lapse ``force_timeout`` of sim
        time from now on."""
        self.forces = {k: f if f is None else _Force(f.indices, f.forces, 0.0)
                       for k, f in self.forces.items()}
        if self.field is not None:
            self.field = (self.field[0], 0.0)
        if self.wind is not None:
            self.wind = (self.wind[0], 0.0)
