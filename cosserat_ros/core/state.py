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
``Control.f_applied`` (n,3) [N]     nodal forces plus the force field ``m_i F``
``Control.gravity`` (3,) [m/s^2]    gravitational acceleration g
``Control.pinned`` (n,) bool        vertices held at their position with zero velocity
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

    f_applied: np.ndarray
    gravity: np.ndarray
    pinned: np.ndarray

    @classmethod
    def empty(cls, n: int) -> 'Control':
        return cls(np.zeros((n, 3)), np.zeros(3), np.zeros(n, dtype=bool))
