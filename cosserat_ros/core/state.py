"""What moves and what users command: :class:`State` and :class:`Control`.

The solvers advance a :class:`State` in place under a :class:`Control`; both are named
tuples of arrays that the compiled step reads by name. :class:`..simulator.ClothSimulator`
owns one of each and keeps them consistent with its Python API (``set_vertex_forces``,
``force_field``, ``gravity``, ``pin``).

================  ================  ========================================================
field             shape / unit      meaning
================  ================  ========================================================
``State.x``       (n,3) [m]         positions
``State.v``       (n,3) [m/s]       velocities (at the half step of the leapfrog)
``State.acc``     (2,) [J]          running balance since the last reset: external work of
                                    the applied forces, energy dissipated by damping
``Control.f_external`` (n,3) [N]    what users command: nodal forces plus the force
                                    field ``m_i F``
``Control.f_applied`` (n,3) [N]     the applied force of the step: ``f_external``, plus
                                    the air force when air is on (:mod:`.air` writes it
                                    before each update)
``Control.air`` (6,)                air on/off, its coefficients and the wind (:mod:`.air`)
``Control.air_face`` (m,3) [N]      scratch of the step: each face's air force
``Control.gravity`` (3,) [m/s^2]    gravitational acceleration g
``Control.pinned`` (n,) bool        vertices whose motion is prescribed: pins and the
                                    vertices grasp handles hold (:mod:`.handles`)
``Control.pin_velocity`` (n,3)      their prescribed velocity [m/s] (zero for a pin)
``Control.reaction`` (n,3) [N]      written by the step: the force the pin or handle
                                    exerts on each of them
``Control.obstacles`` (k, W)        rigid obstacles, one row each (:mod:`.contact`)
``Control.sdf_meta`` (m, 8)         the mesh obstacles' distance grids: offset, shape,
                                    origin, spacing (:mod:`.contact`)
``Control.sdf_data`` (s,) [m]       their samples
``Control.contact_params`` (1,)     contact thickness [m]
``Control.contact`` (n, 11)         written by the step: each vertex's contact force [N]
                                    (3), obstacle row (-1: none), gap to the layer [m],
                                    a second obstacle's part of the force (3) and its row
                                    (a corner), the rows of the obstacles placed through
                                    it that it is released from (2; :mod:`.contact`)
================  ================  ========================================================
"""
from __future__ import annotations

from typing import NamedTuple

import numpy as np

__all__ = ['State', 'Control']


class State(NamedTuple):
    """Positions, velocities and the energy balance integrals (module table)."""

    x: np.ndarray
    v: np.ndarray
    acc: np.ndarray

    @classmethod
    def at_rest(cls, x0: np.ndarray) -> 'State':
        return cls(np.array(x0, dtype=np.float64), np.zeros((len(x0), 3)), np.zeros(2))

    def copy(self) -> 'State':
        return State(self.x.copy(), self.v.copy(), self.acc.copy())

    def assign(self, other: 'State') -> None:
        """Copy ``other`` into this state's arrays (in place)."""
        self.x[:] = other.x
        self.v[:] = other.v
        self.acc[:] = other.acc


class Control(NamedTuple):
    """What users command (module table)."""

    f_external: np.ndarray
    f_applied: np.ndarray
    air: np.ndarray
    air_face: np.ndarray
    gravity: np.ndarray
    pinned: np.ndarray
    pin_velocity: np.ndarray
    reaction: np.ndarray
    obstacles: np.ndarray
    sdf_meta: np.ndarray
    sdf_data: np.ndarray
    contact_params: np.ndarray
    contact: np.ndarray

    @classmethod
    def empty(cls, n: int, thickness: float = 2e-3, faces: int = 0) -> 'Control':
        """No force, pin or obstacle on n vertices; room for the air force of ``faces``
        faces (0: the controls of a step without air)."""
        from .air import AIR_WIDTH
        from .contact import NO_CONTACT, WIDTH
        contact = np.tile(NO_CONTACT, (n, 1))
        return cls(np.zeros((n, 3)), np.zeros((n, 3)), np.zeros(AIR_WIDTH),
                   np.zeros((faces, 3)), np.zeros(3), np.zeros(n, dtype=bool),
                   np.zeros((n, 3)), np.zeros((n, 3)), np.zeros((0, WIDTH)), np.zeros((0, 8)),
                   np.zeros(0),
                   np.array([float(thickness)]), contact)

    def with_obstacles(self, obstacles: np.ndarray, sdf_meta: np.ndarray,
                       sdf_data: np.ndarray) -> 'Control':
        """The same controls with another obstacle table (the arrays of the rest are
        shared)."""
        return self._replace(obstacles=obstacles, sdf_meta=sdf_meta, sdf_data=sdf_data)
