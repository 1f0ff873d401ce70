"""The scene around the cloth, as :class:`.simulator.ClothSimulator`'s methods: grasp
handles (:mod:`.handles`), rigid obstacles (:mod:`.obstacles`, :mod:`.contact`,
:mod:`.features`) and self-collision (:mod:`.self_contact`).

:class:`SceneMethods` is a base class of ``ClothSimulator`` and of nothing else: it holds
no state of its own and works on the simulator's (``state``, ``control``, ``_handles``,
``_obstacles``, ``_features``, ``_self``), so that the simulator's module stays the
model, the state and the step. This module imports no ROS package.
"""
from __future__ import annotations

import math
from typing import Dict, Optional

import numpy as np

from . import contact as C
from .self_contact import SelfCollision

__all__ = ['SceneMethods']


class SceneMethods:
    """Handles, obstacles and self-collision of a :class:`.simulator.ClothSimulator`."""

    # ------------------------------------------------------------------ handles
    def grasp(self, point=None, radius=None, vertices=None, name=None,
              break_force=None, orientation=(0.0, 0.0, 0.0, 1.0)) -> int:
        """Grab the cloth: the vertices within ``radius`` [m] of ``point``, or the
        ``vertices`` given (the handle's origin then ``point``, or their centroid), as
        they are now. Returns the handle id; from now on they move rigidly with the
        handle's pose (:meth:`move_handle`) and :meth:`handle_wrench` is what the handle
        exerts on them. ``break_force`` [N]: each vertex holds at most its share of it
        and slips out above. ``orientation``: the handle frame's at the grasp (later
        poses turn the offsets from it). ``ValueError`` if nothing is within the radius,
        or a vertex is held by another handle. Physics: :mod:`cosserat_ros.core.handles`."""
        if vertices is not None:
            vertices = self._indices(vertices, 'vertices')
        hid = self._handles.grasp(self.state.x, point, radius, vertices, name, break_force,
                                  orientation)
        self._sync_pins()
        return hid

    def move_handle(self, id, position, orientation=(0.0, 0.0, 0.0, 1.0),
                    duration=None, at=None) -> None:
        """Move handle ``id`` to ``position`` [m], ``orientation`` (quaternion x, y, z, w),
        reached linearly (slerp for the orientation) over ``duration`` seconds of sim
        time (default: over the next step), starting from wherever the handle is and
        replacing what it was doing; or, with ``at``, a sim time [s] after :attr:`time`,
        arriving there at ``at`` (within one step) after the waypoints already given
        before ``at`` (those after it are dropped): a trajectory streamed ahead of
        simulation time, at most :data:`.handles.MAX_WAYPOINTS` waypoints. ``ValueError``
        for a time not ahead or too many waypoints."""
        self._handles.move(id, self._time, self._dt, position, orientation, duration, at)

    def handle_waypoints(self, id) -> list:
        """[(time [s], position (3,), orientation (x, y, z, w))]: handle ``id``'s pose now,
        then the waypoints it has ahead (:meth:`move_handle`)."""
        return self._handles.waypoints(id, self._time)

    def handle_wrench(self, id):
        """(force (3) [N], torque (3) [N m]) the handle exerted on the cloth over the last
        step, world frame, torque about the handle's position (hanging at rest: the
        weight it carries, upwards). A handle whose every vertex slipped out (its
        ``break_force``) is gone: ``ValueError``, and it is no longer in :attr:`handles`."""
        return self._handles.wrench(id, self.state.x, self.control.reaction)

    @property
    def handles(self) -> Dict[int, dict]:
        """{id: description}: name, vertices, pose, whether it is moving, break force."""
        return self._handles.describe(self._time)

    def release(self, id) -> None:
        """Let go: the vertices go back to the dynamics with the velocity they had."""
        self._handles.release(id)
        self._sync_pins()

    # ------------------------------------------------------------------ obstacles
    def add_obstacle(self, shape: str, friction=0.5, name: Optional[str] = None,
                     **geometry) -> int:
        """Add a rigid obstacle; returns its id. Shapes and their geometry [m]:

        * ``'plane'``: ``point``, ``normal`` (the solid side is opposite the normal; the
          ground by default: point (0, 0, 0), normal (0, 0, 1));
        * ``'sphere'``: ``center``, ``radius``;
        * ``'box'``: ``center``, ``half_extents``, ``orientation`` (quaternion x, y, z, w);
        * ``'capsule'``, ``'cylinder'``: ``center``, ``radius``, ``half_length``,
          ``orientation`` (axis = local z);
        * ``'mesh'``: ``vertices`` and ``faces``, or ``file`` (OBJ / STL / PLY, loaded by
          trimesh), a closed mesh; ``center``, ``orientation`` place it, ``spacing`` is
          its distance field's grid step (default 1 cm).

        ``friction``: mu, or (mu_static, mu_kinetic) with kinetic <= static (default 0.5
        both). ``name``: unique, default ``<shape>_<id>``. Raises ``ValueError`` with the
        reason for a bad shape or geometry. Physics: :mod:`cosserat_ros.core.contact`.
        An obstacle added through the cloth is released from the vertices inside it
        until they are out of its contact layer (:mod:`.contact`, "Obstacles placed
        through the cloth").
        """
        oid = self._obstacles.add(shape, friction=friction, name=name, **geometry)
        self._sync_obstacles(changed_set=True)
        self._release(oid)
        return oid

    def set_obstacle_pose(self, id, position, orientation=(0.0, 0.0, 0.0, 1.0),
                          linear_velocity=(0.0, 0.0, 0.0),
                          angular_velocity=(0.0, 0.0, 0.0)) -> None:
        """Place obstacle ``id`` at ``position`` [m] with ``orientation`` (quaternion x, y,
        z, w; for a plane, the rotation of its normal from +z) and let it move on with
        the given velocities [m/s, rad/s, world frame] until the next call. The new pose
        carries the vertices that were within 2 contact thicknesses of it; the others
        it is placed through are released from it until they are out of its contact
        layer (:mod:`.contact`, "Obstacles placed through the cloth")."""
        before = self._obstacles.distances(id, self.state.x)
        self._obstacles.set_pose(id, position, orientation, linear_velocity,
                                 angular_velocity)
        self._sync_obstacles()
        self._release(id, before)

    def remove_obstacle(self, id) -> None:
        """Remove obstacle ``id`` (``ValueError`` if there is none)."""
        self._obstacles.remove(id)
        self._sync_obstacles(changed_set=True)

    @property
    def obstacles(self) -> Dict[int, dict]:
        """{id: description} of the obstacles: name, shape, geometry, pose, velocities,
        friction (a copy; change them through the methods)."""
        return self._obstacles.describe()

    def find_obstacle(self, name: str) -> Optional[int]:
        """The id of the obstacle called ``name``, or None."""
        return self._obstacles.find(name)

    def obstacle_snapshot(self):
        """An opaque copy of the obstacle set: :meth:`restore_obstacles` undoes every
        change made after it (a batch of changes applied all or not at all)."""
        return self._obstacles.snapshot()

    def restore_obstacles(self, snapshot) -> None:
        self._obstacles.restore_snapshot(snapshot)
        self._sync_obstacles(changed_set=True)

    def obstacle_mesh(self, id):
        """(vertices, faces) of a mesh obstacle in its own frame, else None."""
        return self._obstacles.mesh_of(id)

    def contact_forces(self) -> Dict[int, tuple]:
        """{id: (force (3) [N], torque (3) [N m] about the obstacle's position)}: what the
        cloth exerted on each obstacle over the last step (at rest on the ground: its
        weight). The corners and edges of boxes, cylinders and meshes (:mod:`.features`)
        add the mean of what they took over the steps of the last :meth:`step` call:
        their projection acts in the steps where the cloth has sunk beyond its slack,
        not in every one."""
        return self._obstacles.forces(self.state.x, self.control.contact,
                                      self._features.forces)

    def contact_state(self) -> Dict[str, float]:
        """Contact counts and depth of the last step: ``contacts`` (vertices in contact),
        ``deepest`` [m] (how far the deepest vertex was inside the contact layer at the
        start of its step, >= 0), ``feature_pairs`` (candidate pairs of the corners and
        edges of boxes and cylinders with the cloth's triangles and edges,
        :mod:`.features`),
        ``feature_active`` (those the last step's response moved) and ``released``
        (vertices an obstacle placed through them does not act on yet, :mod:`.contact`)."""
        c = self.control.contact
        active = c[:, C.C_ID] >= 0
        gap = c[:, C.C_GAP]
        deepest = float(max(0.0, -gap.min())) if len(self._obstacles) and len(gap) else 0.0
        return {'contacts': int(active.sum()), 'deepest': deepest,
                'feature_pairs': int(self._features.pairs),
                'feature_active': int(self._features.acted),
                'released': int(np.count_nonzero(C.released_rows(c)))}

    @property
    def contact_thickness(self) -> float:
        """Distance [m] the cloth keeps from every obstacle surface (default 2 mm)."""
        return float(self.control.contact_params[0])

    @contact_thickness.setter
    def contact_thickness(self, value: float):
        self.control.contact_params[0] = self._check_positive(value, 'contact_thickness')

    # ------------------------------------------------------------------ self-collision
    @property
    def self_collision(self) -> bool:
        """Whether the cloth collides with itself (:mod:`.self_contact`; default False):
        vertex-triangle and edge-edge pairs kept :attr:`contact_thickness` apart, with
        friction :attr:`self_friction` between the layers. It costs a response after
        every step while pairs are near, and little while none is (docs/performance.md)."""
        return self._self_on

    @self_collision.setter
    def self_collision(self, on):
        if not isinstance(on, (bool, np.bool_)):
            raise ValueError(f'self_collision must be True or False, got {on!r}')
        if on and self._self is None:
            self._self = SelfCollision(self.mesh)
            self._self.friction = self._self_friction
        self._self_on = bool(on)

    @property
    def self_friction(self) -> float:
        """Coulomb friction coefficient between two layers of the cloth (default 0.5)."""
        return self._self_friction

    @self_friction.setter
    def self_friction(self, mu: float):
        try:
            mu = float(mu)
        except (TypeError, ValueError):
            raise ValueError(f'self_friction must be a number, got {mu!r}') from None
        if not (math.isfinite(mu) and mu >= 0):
            raise ValueError(f'self_friction must be finite and >= 0, got {mu!r}')
        self._self_friction = mu
        if self._self is not None:
            self._self.friction = mu

    def self_contact_state(self) -> Dict[str, float]:
        """The last step's self-contact (:meth:`.self_contact.SelfCollision.report`):
        ``candidates``, ``live``, ``active`` (pairs the response moved), ``left_short``,
        ``closest_gap`` [m], ``builds``; zeros while self-collision is off."""
        if self._self is None or not self._self_on:
            return {'candidates': 0, 'live': 0, 'active': 0, 'rounds': 0, 'sweeps': 0,
                    'left_short': 0, 'closest_gap': math.inf, 'builds': 0}
        return self._self.report()

    def _sync_obstacles(self, changed_set: bool = False) -> None:
        """The obstacles' table into the control; ``changed_set``: obstacles were added or
        removed, so the last step's contact rows (which name obstacles by table row) and
        the corners' forces name rows that may now be other obstacles: cleared."""
        o = self._obstacles
        self.control = self.control.with_obstacles(o.table, o.meta, o.data)
        self._features.set_shapes(*o.shapes)
        # the release masks follow their obstacles' rows (:mod:`.obstacles`)
        masks = o.remap_released(C.released_rows(self.control.contact))
        if changed_set or not len(o):
            self._clear_contacts()
        C.store_released_rows(self.control.contact, masks)

    def _release(self, oid, before=None) -> None:
        """Obstacle ``oid``'s release of the vertices it was just placed through
        (:meth:`.obstacles.ObstacleSet.release`; ``before``: their distances from it at
        its old pose)."""
        c = self.control.contact
        C.store_released_rows(c, self._obstacles.release(
            oid, self.state.x, C.released_rows(c), self.contact_thickness, before,
            self.control.pinned))

    def _clear_contacts(self) -> None:
        """Forget the last step's contact output: each vertex's contact row (force, none)
        and the corners' and edges' forces (:mod:`.features`)."""
        self.control.contact[:] = C.NO_CONTACT
        self._features.start()
