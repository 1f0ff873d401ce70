"""Command messages -> arrays for the simulator, with their limits: pure functions.

Each parser takes a received message (and the limits in force) and returns what the
simulator needs, or raises :class:`CommandError` whose message is the one-line reason the
node logs (throttled) and counts in ``/diagnostics``. A refused message changes nothing.
"""
from __future__ import annotations

from typing import Tuple

import numpy as np

from ..core.surface_query import closest_points

__all__ = ['CommandError', 'force_rows', 'vertex_forces', 'point_forces', 'force_field', 'wind',
           'check_totals', 'obstacle_markers', 'obstacle_name', 'MAX_MARKERS',
           'MAX_MESH_POINTS', 'MAX_MESH_MARKERS', 'MAX_ROWS', 'MAX_FORCE_BYTES', 'handle_target']

#: rows per ``~/vertex_forces`` or ``~/point_forces`` message
MAX_ROWS = 4096
#: the largest serialised force message [bytes]: MAX_ROWS rows of 6 doubles and a layout
#: (a larger one is refused unread)
MAX_FORCE_BYTES = 8 * 6 * MAX_ROWS + 2048


class CommandError(ValueError):
    """A command message refused whole; the message is the reason."""


def force_rows(msg, width: int, max_force: float) -> np.ndarray:
    """The rows (k, width) of a ``std_msgs/Float64MultiArray`` whose last three columns
    are a force [N]: ``layout.data_offset`` honoured; a layout, if given, describes the
    data exactly (one dimension: ``size`` = the number of values; two: ``size`` rows of
    ``width``; strides 0, i.e. unset, or those of packed rows); at most :data:`MAX_ROWS`
    rows, every value finite, every row's force at most ``max_force`` (their totals per
    vertex: :func:`check_totals`)."""
    data = np.asarray(msg.data, dtype=np.float64)
    off = msg.layout.data_offset
    if off > len(data):
        raise CommandError(f'layout.data_offset {off} beyond {len(data)} values')
    data = data[off:]
    n = len(data)
    dims = list(msg.layout.dim)
    if len(dims) > 2:
        raise CommandError(f'a layout of {len(dims)} dimensions (rows of {width}: 1 or 2)')
    if len(dims) == 1 and (dims[0].size != n or dims[0].stride not in (0, n)):
        raise CommandError(f'layout size {dims[0].size} stride {dims[0].stride} does not '
                           f'describe {n} values')
    if len(dims) == 2 and (dims[1].size != width or dims[0].size * width != n
                           or dims[0].stride not in (0, n)
                           or dims[1].stride not in (0, width)):
        raise CommandError(f'layout {dims[0].size}x{dims[1].size} (strides {dims[0].stride}, '
                           f'{dims[1].stride}) does not describe {n} values in packed rows '
                           f'of {width}')
    if n % width:
        raise CommandError(f'{n} values are not rows of {width}')
    if n // width > MAX_ROWS:
        raise CommandError(f'{n // width} rows, at most {MAX_ROWS} per message')
    if not np.all(np.isfinite(data)):
        raise CommandError('non-finite value')
    rows = data.reshape(-1, width)
    mag = np.linalg.norm(rows[:, -3:], axis=1)
    if len(rows) and mag.max() > max_force:
        raise CommandError(f'force {mag.max():.4g} N above max_force {max_force:.4g} N')
    return rows


def vertex_forces(rows: np.ndarray, n_vertices: int) -> Tuple[np.ndarray, np.ndarray]:
    """Rows ``[index, fx, fy, fz]`` -> (indices (k,) int64, forces (k,3) [N])."""
    idx = rows[:, 0]
    if len(idx) and (np.any(idx != np.round(idx)) or idx.min() < 0
                     or idx.max() >= n_vertices):
        raise CommandError(f'indices must be integers in [0, {n_vertices - 1}]')
    return idx.astype(np.int64), rows[:, 1:].copy()


def point_forces(rows: np.ndarray, x: np.ndarray,
                 faces: np.ndarray) -> Tuple[np.ndarray, np.ndarray]:
    """Rows ``[px, py, pz, fx, fy, fz]`` -> the force of each row shared by the vertices of
    the cloth's closest triangle to its point, barycentrically: (indices (3k,), forces
    (3k,3)). A point further from the cloth's bounding box than the box's diagonal (at
    least 1 m) is refused: it names no place on the cloth."""
    if not len(rows):
        return np.zeros(0, dtype=np.int64), np.zeros((0, 3))
    lo, hi = x.min(axis=0), x.max(axis=0)
    reach = max(float(np.linalg.norm(hi - lo)), 1.0)
    # the gap along the worst axis (no square to overflow for a point 1e200 m away)
    away = np.maximum(np.maximum(lo - rows[:, :3], rows[:, :3] - hi), 0.0).max(axis=1)
    if away.max() > reach:
        k = int(np.argmax(away))
        raise CommandError(f'row {k}: point {away[k]:.3g} m from the cloth\'s bounding box, '
                           f'more than {reach:.3g} m')
    tri, bary = closest_points(x, faces, rows[:, :3])
    idx = faces[tri].reshape(-1)
    f = (bary[:, :, None] * rows[:, None, 3:]).reshape(-1, 3)
    return idx.astype(np.int64), f


def check_totals(indices: np.ndarray, forces: np.ndarray, n_vertices: int,
                 max_force: float) -> None:
    """CommandError unless the force summed on each vertex (rows repeating a vertex, point
    forces sharing it, both topics together) is at most ``max_force`` [N]."""
    if not len(indices):
        return
    total = np.zeros((n_vertices, 3))
    np.add.at(total, indices, forces)
    mag = np.linalg.norm(total, axis=1)
    v = int(np.argmax(mag))
    if mag[v] > max_force * (1.0 + 1e-12):
        raise CommandError(f'the forces on vertex {v} add up to {mag[v]:.4g} N, above '
                           f'max_force {max_force:.4g} N')


def _stamped_vector(msg, frame_id: str) -> np.ndarray:
    if msg.header.frame_id not in ('', frame_id):
        raise CommandError(f'frame {msg.header.frame_id!r} is not {frame_id!r} (no tf here)')
    v = np.array([msg.vector.x, msg.vector.y, msg.vector.z])
    if not np.all(np.isfinite(v)):
        raise CommandError('non-finite value')
    return v


def force_field(msg, frame_id: str, max_acceleration: float) -> np.ndarray:
    """A ``geometry_msgs/Vector3Stamped`` force per unit mass [m/s^2] in ``frame_id`` (an
    empty frame is taken as ``frame_id``) -> (3,)."""
    v = _stamped_vector(msg, frame_id)
    if np.linalg.norm(v) > max_acceleration:
        raise CommandError(f'|F| = {np.linalg.norm(v):.4g} m/s^2 above max_acceleration '
                           f'{max_acceleration:.4g}')
    return v


def wind(msg, frame_id: str, max_wind: float) -> np.ndarray:
    """A ``geometry_msgs/Vector3Stamped`` wind velocity [m/s] in ``frame_id`` (an empty
    frame is taken as ``frame_id``) no faster than ``max_wind`` -> (3,)."""
    v = _stamped_vector(msg, frame_id)
    if np.linalg.norm(v) > max_wind:
        raise CommandError(f'|wind| = {np.linalg.norm(v):.4g} m/s above max_wind '
                           f'{max_wind:.4g}')
    return v


#: limits of ``~/obstacles``: markers per message, points of one TRIANGLE_LIST
MAX_MARKERS = 64
MAX_MESH_POINTS = 30_000
#: the most mesh obstacles made from markers at once: each holds a distance field (up to
#: 16 MB) and goes out on ~/obstacle_markers each second with its triangles
MAX_MESH_MARKERS = 4

# visualization_msgs/Marker constants (kept here so the parser needs no ROS import)
_CUBE, _SPHERE, _CYLINDER, _TRIANGLE_LIST = 1, 2, 3, 11
_ADD, _DELETE, _DELETEALL = 0, 2, 3
_SHAPES = {_CUBE: 'box', _SPHERE: 'sphere', _CYLINDER: 'cylinder',
           _TRIANGLE_LIST: 'mesh'}


def obstacle_name(ns: str, mid: int) -> str:
    """The obstacle name of marker (ns, id): ``<ns>_<id>`` in the characters a ROS topic
    name token allows (its wrench goes to ``~/contact/<name>``)."""
    base = ''.join(ch if ch.isalnum() or ch == '_' else '_' for ch in (ns or 'marker'))
    name = f'{base}_{int(mid)}'
    return name if name[0].isalpha() else 'o_' + name


def obstacle_markers(msg, frame_id: str):
    """A ``visualization_msgs/MarkerArray`` -> a list of operations, each
    ``('add', name, shape, geometry, pose)``, ``('delete', name)`` or ``('deleteall',)``;
    ``pose`` is (position (3,), quaternion (4,)). SPHERE (diameter = scale, equal in x,
    y, z), CUBE (full extents = scale), CYLINDER (diameter scale.x = scale.y, height
    scale.z), TRIANGLE_LIST (points in the marker's frame, a closed mesh); every marker
    in ``frame_id`` (or an empty frame); at most :data:`MAX_MARKERS` markers and
    :data:`MAX_MESH_POINTS` points in all. Any bad marker refuses the whole message."""
    markers = list(msg.markers)
    if len(markers) > MAX_MARKERS:
        raise CommandError(f'{len(markers)} markers, at most {MAX_MARKERS} per message')
    points = sum(len(m.points) for m in markers)
    if points > MAX_MESH_POINTS:
        raise CommandError(f'{points} points in all, at most {MAX_MESH_POINTS} per message')
    ops = []
    for m in markers:
        where = f'marker {m.ns!r}/{m.id}'
        if m.action == _DELETEALL:
            ops.append(('deleteall',))
            continue
        name = obstacle_name(m.ns, m.id)
        if m.action == _DELETE:
            ops.append(('delete', name))
            continue
        if m.action != _ADD:
            raise CommandError(f'{where}: action {m.action} is not ADD, DELETE or DELETEALL')
        if m.header.frame_id not in ('', frame_id):
            raise CommandError(f'{where}: frame {m.header.frame_id!r} is not {frame_id!r} '
                               '(no tf here)')
        if m.type not in _SHAPES:
            raise CommandError(f'{where}: marker type {m.type} is not SPHERE, CUBE, CYLINDER '
                               'or TRIANGLE_LIST')
        p = np.array([m.pose.position.x, m.pose.position.y, m.pose.position.z])
        q = np.array([m.pose.orientation.x, m.pose.orientation.y, m.pose.orientation.z,
                      m.pose.orientation.w])
        s = np.array([m.scale.x, m.scale.y, m.scale.z])
        if not (np.all(np.isfinite(p)) and np.all(np.isfinite(q)) and np.all(np.isfinite(s))):
            raise CommandError(f'{where}: non-finite pose or scale')
        nq = float(np.linalg.norm(q))
        if abs(nq - 1.0) > 1e-3:
            raise CommandError(f'{where}: orientation is not a unit quaternion '
                               f'(norm {nq:.4g})')
        q = q / nq
        shape = _SHAPES[m.type]
        ops.append(('add', name, shape, _marker_geometry(m, shape, s, where), (p, q)))
    return ops


def _marker_geometry(m, shape: str, s: np.ndarray, where: str) -> dict:
    """The ``add_obstacle`` geometry of marker ``m`` of ``shape`` with scale ``s``
    (:func:`obstacle_markers`); CommandError naming the marker (``where``) if bad."""
    if shape == 'mesh':
        if len(m.points) > MAX_MESH_POINTS:
            raise CommandError(f'{where}: {len(m.points)} points, at most '
                               f'{MAX_MESH_POINTS}')
        if len(m.points) < 12 or len(m.points) % 3:
            raise CommandError(f'{where}: a TRIANGLE_LIST needs 3 points per triangle '
                               f'and at least 4 triangles, got {len(m.points)} points')
        pts = np.array([[pt.x, pt.y, pt.z] for pt in m.points])
        if not np.all(np.isfinite(pts)):
            raise CommandError(f'{where}: non-finite point')
        # merge the corners shared by triangles (bit-equal points), as RViz draws them
        verts, inverse = np.unique(pts, axis=0, return_inverse=True)
        geometry = {'vertices': verts, 'faces': inverse.reshape(-1, 3)}
    else:
        if np.any(s <= 0):
            raise CommandError(f'{where}: scale must be positive, got {tuple(s)}')
        if shape == 'sphere':
            if np.ptp(s) > 1e-9 * s.max():
                raise CommandError(f'{where}: a SPHERE needs equal scales (an ellipsoid '
                                   f'is not supported), got {tuple(s)}')
            geometry = {'radius': s[0] / 2}
        elif shape == 'box':
            geometry = {'half_extents': s / 2}
        else:
            if abs(s[0] - s[1]) > 1e-9 * s.max():
                raise CommandError(f'{where}: a CYLINDER needs scale.x = scale.y, got '
                                   f'{tuple(s)}')
            geometry = {'radius': s[0] / 2, 'half_length': s[2] / 2}
    return geometry


def handle_target(msg, frame_id: str):
    """A ``geometry_msgs/PoseStamped`` in ``frame_id`` (or an empty frame) -> (position
    (3,), unit quaternion (4,)): finite, the quaternion of norm 1 within 1e-3."""
    if msg.header.frame_id not in ('', frame_id):
        raise CommandError(f'frame {msg.header.frame_id!r} is not {frame_id!r} (no tf here)')
    p = np.array([msg.pose.position.x, msg.pose.position.y, msg.pose.position.z])
    q = np.array([msg.pose.orientation.x, msg.pose.orientation.y, msg.pose.orientation.z,
                  msg.pose.orientation.w])
    if not (np.all(np.isfinite(p)) and np.all(np.isfinite(q))):
        raise CommandError('non-finite pose')
    n = float(np.linalg.norm(q))
    if abs(n - 1.0) > 1e-3:
        raise CommandError(f'orientation is not a unit quaternion (norm {n:.4g})')
    return p, q / n
