"""The node's obstacles: those declared in the parameters (``obstacles.names``), those
made from ``~/obstacles`` markers, ``~/obstacle_markers`` (out, ~1 Hz and after every
change) and ``~/contact/<name>`` (each obstacle's wrench from the cloth, every tick).

A marker message is applied all or none (the simulator's obstacles are snapshotted and
restored on a refusal). A mesh marker builds a distance field (up to ~1 s of the
callback thread), so at most one per message and one per :data:`MESH_BUILD_PERIOD`.
"""
from __future__ import annotations

import math
import time
from typing import Dict, Tuple

import numpy as np
from geometry_msgs.msg import WrenchStamped
from visualization_msgs.msg import MarkerArray

from . import commands, messages, scene
from .params import group_names, OBSTACLE_KEYS

__all__ = ['ObstacleStreams', 'MAX_OBSTACLE_BYTES', 'MESH_BUILD_PERIOD']

#: the largest serialised ~/obstacles message [bytes]: commands.MAX_MESH_POINTS points
#: (24 bytes each) and commands.MAX_MARKERS markers' headers, with room to spare
MAX_OBSTACLE_BYTES = 24 * 30_000 + 64 * 512

#: [s] wall time between two distance-field builds for mesh markers on ~/obstacles (each
#: costs up to ~1 s of the callback thread: commands.MAX_MESH_POINTS, obstacles.py)
MESH_BUILD_PERIOD = 2.0


def _marker_key(shape, geometry):
    return (shape, {k: np.asarray(v).tobytes() for k, v in geometry.items()})


def _angular_velocity(q0, q1, dt: float) -> np.ndarray:
    """The constant angular velocity [rad/s, world frame] turning unit quaternion q0
    (x, y, z, w) into q1 in dt seconds: the axis-angle of q1 q0^-1 over dt."""
    x0, y0, z0, w0 = -q0[0], -q0[1], -q0[2], q0[3]          # q0^-1
    x1, y1, z1, w1 = q1
    d = np.array([w1 * x0 + x1 * w0 + y1 * z0 - z1 * y0,
                  w1 * y0 - x1 * z0 + y1 * w0 + z1 * x0,
                  w1 * z0 + x1 * y0 - y1 * x0 + z1 * w0,
                  w1 * w0 - x1 * x0 - y1 * y0 - z1 * z0])
    if d[3] < 0:
        d = -d
    s = float(np.linalg.norm(d[:3]))
    if s < 1e-12:
        return np.zeros(3)
    angle = 2.0 * math.atan2(s, d[3])
    return d[:3] / s * angle / dt


class ObstacleStreams:
    """The obstacles' topics of a node. ``seen[oid]`` = (sim time, position,
    orientation, shape key) of the last pose of each obstacle made from markers."""

    def __init__(self, node, names, qos, build_period: float = MESH_BUILD_PERIOD):
        self.node = node
        self.build_period = build_period             # [s] between two distance fields
        self.sim = node.sim
        values = {'obstacles.names': group_names('obstacles', names)}
        for name in values['obstacles.names']:
            for key, value in node._declare_group('obstacles', name, OBSTACLE_KEYS,
                                                  'obstacle').items():
                values[f'obstacles.{name}.{key}'] = value
        scene.add_declared_obstacles(self.sim, values)
        self.seen: Dict[int, Tuple[float, np.ndarray, np.ndarray, object]] = {}
        self.wrench_pubs: Dict[int, object] = {}
        self.marker_points: Dict[int, list] = {}
        self.last_field_build = -math.inf            # [s] monotonic
        self.last_publish = -1.0                     # [s] monotonic; < 0: at the next tick
        self.markers_pub = node.create_publisher(MarkerArray, '~/obstacle_markers', qos)
        for oid in self.sim.obstacles:
            self._add_wrench_pub(oid)

    def subscribe(self, sized):
        """``~/obstacles``, a raw subscription refused above :data:`MAX_OBSTACLE_BYTES`."""
        self.node.create_subscription(
            MarkerArray, '~/obstacles',
            sized('obstacles', MarkerArray, MAX_OBSTACLE_BYTES, self.on_markers), 10, raw=True)

    def _add_wrench_pub(self, oid: int):
        name = self.sim.obstacles[oid]['name']
        self.wrench_pubs[oid] = self.node.create_publisher(WrenchStamped, f'~/contact/{name}', 5)

    # ------------------------------------------------------------------ markers in
    def on_markers(self, msg: MarkerArray):
        """Markers -> obstacles (:func:`.commands.obstacle_markers`), all or none: ADD
        creates or moves obstacle ``<ns>_<id>`` (its velocity from its last pose), DELETE
        removes it, DELETEALL removes every obstacle made from markers."""
        try:
            ops = commands.obstacle_markers(msg, self.node.frame_id)
            builds, wall = self._builds(ops)
        except commands.CommandError as exc:
            self.node._reject('obstacles', str(exc))
            return
        snap = self.sim.obstacle_snapshot()
        seen = dict(self.seen)
        try:
            for op in ops:
                self._apply(op, seen, self.sim.time)
            self._check_counts(seen)
        except ValueError as exc:
            self.sim.restore_obstacles(snap)
            self.node._reject('obstacles', str(exc))
            return
        if builds:                 # a refused mesh stops before its field: cheap
            self.last_field_build = wall
        self.seen = {oid: v for oid, v in seen.items() if oid in self.sim.obstacles}
        for oid in list(self.wrench_pubs):
            if oid not in self.sim.obstacles:
                self.node.destroy_publisher(self.wrench_pubs.pop(oid))
        for oid in self.sim.obstacles:
            if oid not in self.wrench_pubs:
                self._add_wrench_pub(oid)
        self.last_publish = -1.0               # republish at the next tick
        self.node._dirty = True

    def _builds(self, ops) -> Tuple[int, float]:
        """(how many distance fields ``ops`` would build, the wall time now); CommandError
        if more than one, or one sooner than ``build_period`` after the last."""
        builds = sum(1 for op in ops if op[0] == 'add' and op[2] == 'mesh'
                     and not self._same_marker(op))
        wall = time.monotonic()
        since = wall - self.last_field_build
        if builds and since < self.build_period:
            raise commands.CommandError(
                f'a new mesh obstacle {since:.2f} s after the last one (at most one per '
                f'{self.build_period} s: each builds a distance field)')
        if builds > 1:
            raise commands.CommandError(f'{builds} new mesh obstacles in one message (one at '
                                        'a time: each builds a distance field)')
        return builds, wall

    def _check_counts(self, seen):
        """ValueError if the markers' obstacles exceed :data:`.commands.MAX_MARKERS` or
        their meshes :data:`.commands.MAX_MESH_MARKERS`."""
        live = [oid for oid in seen if oid in self.sim.obstacles]
        if len(live) > commands.MAX_MARKERS:
            raise ValueError(f'more than {commands.MAX_MARKERS} obstacles from markers')
        meshes = sum(1 for oid in live if self.sim.obstacles[oid]['shape'] == 'mesh')
        if meshes > commands.MAX_MESH_MARKERS:
            raise ValueError(f'more than {commands.MAX_MESH_MARKERS} mesh obstacles from '
                             'markers (each holds a distance field)')

    def _same_marker(self, op) -> bool:
        """An ADD for a marker obstacle that exists with this very shape and geometry (a
        move, no new distance field)."""
        oid = self.sim.find_obstacle(op[1])
        if oid is None or oid not in self.seen:
            return False
        return self.seen[oid][3] == _marker_key(op[2], op[3])

    def _apply(self, op, seen, now):
        if op[0] == 'deleteall':
            for oid in list(seen):
                if oid in self.sim.obstacles:
                    self.sim.remove_obstacle(oid)
                del seen[oid]
            return
        oid = self.sim.find_obstacle(op[1])
        if op[0] == 'delete':
            if oid is not None and oid in seen:
                self.sim.remove_obstacle(oid)
                del seen[oid]
            return
        _, name, shape, geometry, (p, q) = op
        if oid is not None and oid not in seen:
            raise ValueError(f'{name} is a declared obstacle, not a marker\'s')
        key = _marker_key(shape, geometry)
        if oid is not None and seen[oid][3] == key:
            t0, p0, q0, _ = seen[oid]
            dt = now - t0
            v = (p - p0) / dt if 0 < dt < 1.0 else np.zeros(3)
            w = _angular_velocity(q0, q, dt) if 0 < dt < 1.0 else np.zeros(3)
            self.sim.set_obstacle_pose(oid, p, q, v, w)
        else:
            if oid is not None:
                self.sim.remove_obstacle(oid)
            place = dict(center=p)
            if shape != 'sphere':
                place['orientation'] = q
            oid = self.sim.add_obstacle(shape, name=name, **geometry, **place)
        seen[oid] = (now, p, q, key)

    def expire(self, now: float, timeout: float):
        """A marker obstacle whose pose was not renewed for ``timeout`` s of sim time stops
        where it is (its velocity, from its last two poses, is dropped)."""
        described = self.sim.obstacles if self.seen else {}
        for oid, (t0, _, _, _) in self.seen.items():
            d = described.get(oid)
            if (d is not None and now - t0 > timeout
                    and any(d['linear_velocity'] + d['angular_velocity'])):
                self.sim.set_obstacle_pose(oid, d['position'], d['orientation'])

    def restart(self):
        """After a reset to t = 0: the markers' obstacles stop where they are and their
        streams restart at t = 0 (their velocity came from poses stamped before the reset,
        and their lapse after force_timeout compares sim times)."""
        described = self.sim.obstacles
        for oid, (_, _, _, key) in list(self.seen.items()):
            d = described.get(oid)
            if d is not None:
                self.sim.set_obstacle_pose(oid, d['position'], d['orientation'])
                self.seen[oid] = (0.0, np.array(d['position']), np.array(d['orientation']),
                                  key)

    # ------------------------------------------------------------------ out
    def publish(self, stamp: int):
        """Every tick: each obstacle's wrench from the cloth; ~1 Hz while there are
        obstacles, and once after every change, the markers (the last obstacle's removal
        too: the array is then its DELETEALL alone, which clears it from RViz /
        Foxglove)."""
        if self.wrench_pubs:
            for oid, (f, t) in self.sim.contact_forces().items():
                pub = self.wrench_pubs.get(oid)
                if pub is None or not (np.all(np.isfinite(f)) and np.all(np.isfinite(t))):
                    continue
                pub.publish(messages.wrench(stamp, self.node.frame_id, f, t))
        mono = time.monotonic()
        if self.last_publish < 0 or (self.sim.obstacles and mono - self.last_publish >= 1.0):
            self.last_publish = mono
            self.publish_markers(stamp)

    def publish_markers(self, stamp: int):
        """The obstacles as markers in ``frame_id`` (ns = their name):
        :func:`.messages.obstacle_markers`."""
        arr = messages.obstacle_markers(self.sim.obstacles, self._mesh_points, stamp,
                                        self.node.frame_id)
        for oid in set(self.marker_points) - set(self.sim.obstacles):
            del self.marker_points[oid]
        self.markers_pub.publish(arr)

    def _mesh_points(self, oid: int) -> list:
        """A mesh obstacle's triangles as the points of a TRIANGLE_LIST, in its own frame;
        built once per obstacle (an id's mesh never changes: a new shape is a new id)."""
        if oid not in self.marker_points:
            self.marker_points[oid] = messages.mesh_triangle_points(
                *self.sim.obstacle_mesh(oid))
        return self.marker_points[oid]
