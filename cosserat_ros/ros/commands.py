"""Command messages -> arrays for the simulator, with their limits: pure functions.

Each parser takes a received message (and the limits in force) and returns what the
simulator needs, or raises :class:`CommandError` whose message is the one-line reason the
node logs (throttled) and counts in ``/diagnostics``. A refused message changes nothing.
"""
from __future__ import annotations

from typing import Tuple

import numpy as np

from ..core.surface_query import closest_points

__all__ = ['CommandError', 'force_rows', 'vertex_forces', 'point_forces', 'force_field']


class CommandError(ValueError):
    """A command message refused whole; the message is the reason."""


def force_rows(msg, width: int, max_force: float) -> np.ndarray:
    """The rows (k, width) of a ``std_msgs/Float64MultiArray`` whose last three columns
    are a force [N]: ``layout.data_offset`` honoured, a 2-D layout must describe the data
    in rows of ``width``, every value finite, every force at most ``max_force``."""
    data = np.asarray(msg.data, dtype=np.float64)
    off = msg.layout.data_offset
    if off > len(data):
        raise CommandError(f'layout.data_offset {off} beyond {len(data)} values')
    data = data[off:]
    dims = msg.layout.dim
    if len(dims) >= 2 and (dims[1].size != width or dims[0].size * width != len(data)):
        raise CommandError(f'layout {dims[0].size}x{dims[1].size} does not describe '
                           f'{len(data)} values in rows of {width}')
    if len(data) % width:
        raise CommandError(f'{len(data)} values are not rows of {width}')
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
    (3k,3))."""
    if not len(rows):
        return np.zeros(0, dtype=np.int64), np.zeros((0, 3))
    tri, bary = closest_points(x, faces, rows[:, :3])
    idx = faces[tri].reshape(-1)
    f = (bary[:, :, None] * rows[:, None, 3:]).reshape(-1, 3)
    return idx.astype(np.int64), f


def force_field(msg, frame_id: str, max_acceleration: float) -> np.ndarray:
    """A ``geometry_msgs/Vector3Stamped`` force per unit mass [m/s^2] in ``frame_id`` (an
    empty frame is taken as ``frame_id``) -> (3,)."""
    if msg.header.frame_id not in ('', frame_id):
        raise CommandError(f'frame {msg.header.frame_id!r} is not {frame_id!r} (no tf here)')
    v = np.array([msg.vector.x, msg.vector.y, msg.vector.z])
    if not np.all(np.isfinite(v)):
        raise CommandError('non-finite value')
    if np.linalg.norm(v) > max_acceleration:
        raise CommandError(f'|F| = {np.linalg.norm(v):.4g} m/s^2 above max_acceleration '
                           f'{max_acceleration:.4g}')
    return v
