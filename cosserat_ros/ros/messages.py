"""The cloth node's small ROS messages, built from plain values: one place for each.

``cloth_node`` (:mod:`.node`) publishes these, and a tool that writes the same topics to
a bag without a node (no ``rclpy.init``, no DDS) builds them here too, so both produce the
same messages: ``rclpy.serialization.serialize_message`` of any of them needs no context.

Every header is stamped with simulation time, ``stamp_ns`` [ns] (an int, split into the
stamp's ``sec`` and ``nanosec``). Lengths are in metres, forces in newtons, torques in
newton metres, energies in joules, as the simulator reports them.

The large per-tick messages (the cloth's mesh, point cloud and shape) are written as CDR
bytes straight from numpy instead: :mod:`.conversions`.

This module imports message packages, numpy and the standard library only (no rclpy node,
no simulator).
"""
from __future__ import annotations

from typing import Callable, Dict, List, Optional

import numpy as np
from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus, KeyValue
from geometry_msgs.msg import Point, PoseStamped, WrenchStamped
from rosgraph_msgs.msg import Clock
from visualization_msgs.msg import Marker, MarkerArray

__all__ = ['clock', 'wrench', 'pose', 'obstacle_markers', 'mesh_triangle_points', 'status',
           'rejection', 'energy_status', 'OBSTACLE_COLOR', 'PLANE_SIZE', 'PLANE_THICKNESS']

#: RGBA of every obstacle marker
OBSTACLE_COLOR = (0.6, 0.6, 0.6, 0.8)
#: [m] a plane obstacle is drawn as a PLANE_SIZE square, PLANE_THICKNESS thick
PLANE_SIZE = 10.0
PLANE_THICKNESS = 1e-3


def _stamp(header, stamp_ns: int):
    """Set ``header.stamp`` to ``stamp_ns`` [ns]."""
    header.stamp.sec, header.stamp.nanosec = divmod(stamp_ns, 1_000_000_000)


def clock(stamp_ns: int) -> Clock:
    """``rosgraph_msgs/Clock`` at simulation time ``stamp_ns`` [ns] (the node's /clock)."""
    c = Clock()
    c.clock.sec, c.clock.nanosec = divmod(stamp_ns, 1_000_000_000)
    return c


def wrench(stamp_ns: int, frame_id: str, force, torque) -> WrenchStamped:
    """``geometry_msgs/WrenchStamped`` in ``frame_id`` at ``stamp_ns`` [ns]: ``force``
    [N] and ``torque`` [N m], three numbers each (stored as floats). The node's
    ``~/contact/<name>`` (what the cloth exerts on an obstacle, torque about the obstacle's
    origin) and ``~/handles/<n>/wrench`` (what a handle exerts on the cloth, torque about
    the handle's position), both in world axes."""
    w = WrenchStamped()
    _stamp(w.header, stamp_ns)
    w.header.frame_id = frame_id
    w.wrench.force.x, w.wrench.force.y, w.wrench.force.z = (float(c) for c in force)
    w.wrench.torque.x, w.wrench.torque.y, w.wrench.torque.z = (float(c) for c in torque)
    return w


def pose(stamp_ns: int, frame_id: str, position, orientation) -> PoseStamped:
    """``geometry_msgs/PoseStamped`` in ``frame_id`` at ``stamp_ns`` [ns]: ``position``
    [m] and the unit quaternion ``orientation`` (x, y, z, w). A camera's ``pose_out``."""
    m = PoseStamped()
    _stamp(m.header, stamp_ns)
    m.header.frame_id = frame_id
    m.pose.position.x, m.pose.position.y, m.pose.position.z = (float(c) for c in position)
    o = m.pose.orientation
    o.x, o.y, o.z, o.w = (float(c) for c in orientation)
    return m


def mesh_triangle_points(verts, faces) -> List[Point]:
    """A triangle mesh as the points of a ``Marker.TRIANGLE_LIST``: three corners per
    face, in order; ``verts`` (V, 3) [m], ``faces`` (F, 3) vertex indices. The points are
    in whatever frame ``verts`` are (for a mesh obstacle, its own)."""
    verts = np.asarray(verts)
    return [Point(x=float(a), y=float(b), z=float(c))
            for a, b, c in verts[np.asarray(faces).reshape(-1)]]


def obstacle_markers(obstacles: Dict[int, dict], mesh_points: Callable[[int], list],
                     stamp_ns: int, frame_id: str) -> MarkerArray:
    """The obstacles as ``visualization_msgs/MarkerArray`` (the node's
    ``~/obstacle_markers``): first a DELETEALL (so that a removed obstacle disappears; with
    no obstacle the array is that alone), then one ADD marker per obstacle, ns = its name,
    id 0, in ``frame_id`` at ``stamp_ns`` [ns], posed at its position [m] and orientation
    (quaternion x, y, z, w), colour :data:`OBSTACLE_COLOR`. Scales [m]:

    * sphere: SPHERE, its diameter;
    * box: CUBE, twice its half extents;
    * cylinder: CYLINDER, diameter x diameter x length; a capsule the same with its caps'
      length added (2 half_length + 2 radius);
    * plane: a thin CUBE, PLANE_SIZE x PLANE_SIZE x PLANE_THICKNESS, along the plane;
    * mesh (any other shape): TRIANGLE_LIST of ``mesh_points(id)`` (points in the
      obstacle's own frame, e.g. :func:`mesh_triangle_points`), scale 1.

    ``obstacles``: {id: description} as ``ClothSimulator.obstacles`` gives (name, shape,
    position, orientation and the shape's geometry)."""
    arr = MarkerArray()
    clear = Marker()
    clear.action = Marker.DELETEALL
    arr.markers.append(clear)
    for oid, d in obstacles.items():
        m = Marker()
        m.header.frame_id = frame_id
        _stamp(m.header, stamp_ns)
        m.ns, m.id, m.action = d['name'], 0, Marker.ADD
        (m.pose.position.x, m.pose.position.y, m.pose.position.z) = d['position']
        (m.pose.orientation.x, m.pose.orientation.y, m.pose.orientation.z,
         m.pose.orientation.w) = d['orientation']
        m.color.r, m.color.g, m.color.b, m.color.a = OBSTACLE_COLOR
        shape = d['shape']
        if shape == 'sphere':
            m.type = Marker.SPHERE
            m.scale.x = m.scale.y = m.scale.z = 2 * d['radius']
        elif shape == 'box':
            m.type = Marker.CUBE
            m.scale.x, m.scale.y, m.scale.z = (2 * h for h in d['half_extents'])
        elif shape in ('cylinder', 'capsule'):
            m.type = Marker.CYLINDER
            m.scale.x = m.scale.y = 2 * d['radius']
            m.scale.z = 2 * d['half_length'] + (2 * d['radius'] if shape == 'capsule'
                                                else 0.0)
        elif shape == 'plane':
            m.type = Marker.CUBE          # a thin square along the plane
            m.scale.x = m.scale.y = PLANE_SIZE
            m.scale.z = PLANE_THICKNESS
        else:
            m.type = Marker.TRIANGLE_LIST
            m.scale.x = m.scale.y = m.scale.z = 1.0
            m.points = mesh_points(oid)
        arr.markers.append(m)
    return arr


def status(stamp_ns: int, frame_id: str, name: str, level: bytes, message: str,
           values: Dict[str, object], hardware_id: str) -> DiagnosticArray:
    """``diagnostic_msgs/DiagnosticArray`` of one ``DiagnosticStatus`` (``name``,
    ``level`` such as ``DiagnosticStatus.OK``, ``message``, ``hardware_id``; the node
    gives its fully qualified name), header in ``frame_id`` at ``stamp_ns`` [ns]. Each
    ``values`` item becomes a KeyValue in order: a float as its ``repr`` (round-trips
    exactly), anything else as ``str``."""
    arr = DiagnosticArray()
    _stamp(arr.header, stamp_ns)
    arr.header.frame_id = frame_id
    st = DiagnosticStatus(level=level, name=name, message=message, hardware_id=hardware_id)
    st.values = [KeyValue(key=k, value=repr(v) if isinstance(v, float) else str(v))
                 for k, v in values.items()]
    arr.status = [st]
    return arr


def rejection(topic: str, reason: str, sim_time: float, values: Dict[str, object],
              hardware_id: str) -> DiagnosticStatus:
    """A refused input, as the node's ``~/rejections`` carries it: a WARN
    ``DiagnosticStatus`` named after the input's topic or service (``topic``), the
    ``reason`` as its message, and as values ``sim_time`` [s] (when it was refused) then
    the offending ``values`` (floats as their ``repr``, the rest as ``str``)."""
    st = DiagnosticStatus(level=DiagnosticStatus.WARN, name=topic, message=reason,
                          hardware_id=hardware_id)
    vals: Dict[str, object] = {'sim_time': float(sim_time)}
    vals.update(values)
    st.values = [KeyValue(key=k, value=repr(v) if isinstance(v, float) else str(v))
                 for k, v in vals.items()]
    return st


def energy_status(stamp_ns: int, frame_id: str, energy: Dict[str, float], sim_time: float,
                  step: int, diverged: Optional[str], paused: bool,
                  hardware_id: str) -> DiagnosticArray:
    """The node's ``~/energy``: a :func:`status` named ``energy`` whose values are each
    ``energy`` item [J] as a float (the simulator's order), then ``sim_time`` [s] and
    ``step`` (steps taken). Level and message: ERROR ``diverged: <diverged>`` when
    ``diverged`` is a reason (non-empty), else WARN ``paused`` when ``paused``, else OK
    ``running``."""
    vals: Dict[str, object] = {k: float(v) for k, v in energy.items()}
    vals['sim_time'] = float(sim_time)
    vals['step'] = int(step)
    if diverged:
        level, msg = DiagnosticStatus.ERROR, 'diverged: ' + diverged
    elif paused:
        level, msg = DiagnosticStatus.WARN, 'paused'
    else:
        level, msg = DiagnosticStatus.OK, 'running'
    return status(stamp_ns, frame_id, 'energy', level, msg, vals, hardware_id)
