"""Numpy -> serialised ROS 2 messages for the cloth, without one Python object per point.

Building an 80x80 ``visualization_msgs/MarkerArray`` TRIANGLE_LIST the obvious way (one
``Point`` and one ``ColorRGBA`` object per triangle corner) costs tens of milliseconds, and
serialising it as much again. The CDR layout is simple enough to write straight from numpy
arrays; rclpy publishers accept the bytes (``Publisher.publish(bytes)``).

CDR here is the XCDR1 little-endian encoding every ROS 2 RMW uses on the wire: a 4-byte
encapsulation header ``00 01 00 00``, then the fields in order, each primitive aligned to
its own size (at most 8) relative to the start of the body; strings are a uint32 length
(including the terminating NUL), the bytes and a NUL; sequences a uint32 count then the
elements. The tests check these bytes against rclpy's own serialiser.

This module imports no ROS package.
"""
from __future__ import annotations

import struct
from typing import Optional

import numpy as np

__all__ = ['CdrWriter', 'mesh_marker_array', 'point_cloud', 'shape_mesh', 'POINT_FIELDS',
           'colormap', 'percentile', 'TRIANGLE_LIST',
           'LINE_LIST', 'SPHERE_LIST', 'MARKER_NAMESPACE', 'MESH_ID', 'WIREFRAME_ID',
           'PINS_ID', 'HANDLES_ID', 'optional_markers', 'OPTIONAL_MARKERS', 'image',
           'camera_info', 'organised_cloud']

TRIANGLE_LIST = 11
LINE_LIST = 5
SPHERE_LIST = 7
#: visualization_msgs/Marker action DELETE
DELETE = 2
MARKER_NAMESPACE = 'cloth'
MESH_ID, WIREFRAME_ID, PINS_ID, HANDLES_ID = 0, 1, 2, 3


class CdrWriter:
    """Append-only little-endian CDR (XCDR1) body with alignment bookkeeping."""

    def __init__(self):
        self._parts = [b'\x00\x01\x00\x00']
        self._size = 0          # body size (alignment is relative to the body start)

    def _align(self, n: int):
        pad = (-self._size) % n
        if pad:
            self._parts.append(b'\x00' * pad)
            self._size += pad

    def _raw(self, data: bytes):
        self._parts.append(data)
        self._size += len(data)

    def prim(self, fmt: str, *values):
        """Primitive(s) of one struct format char ('i', 'I', 'd', 'f', '?', 'B')."""
        size = struct.calcsize('<' + fmt)
        self._align(size)
        self._raw(struct.pack('<' + fmt * len(values), *values))

    def string(self, s: str):
        data = s.encode('utf-8') + b'\x00'
        self.prim('I', len(data))
        self._raw(data)

    def array(self, arr: np.ndarray, dtype: str, count: Optional[int] = None):
        """A sequence of structs of one primitive type: count, then the packed values."""
        a = np.ascontiguousarray(arr, dtype=dtype)
        self.prim('I', len(a) if count is None else count)
        if a.size:
            self._align(a.dtype.itemsize)
            self._raw(a.tobytes())

    def bytes(self) -> bytes:
        return b''.join(self._parts)


def _header(w: CdrWriter, sec: int, nanosec: int, frame_id: str):
    w.prim('i', sec)
    w.prim('I', nanosec)
    w.string(frame_id)


def _marker(w: CdrWriter, sec: int, nanosec: int, frame_id: str, mid: int, mtype: int,
            scale: float, color, points: np.ndarray, colors: Optional[np.ndarray],
            action: int = 0):
    _header(w, sec, nanosec, frame_id)
    w.string(MARKER_NAMESPACE)
    w.prim('i', mid)
    w.prim('i', mtype)
    w.prim('i', action)                              # ADD (0) or DELETE (2)
    w.prim('d', 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 1.0)    # pose: origin, identity
    w.prim('d', scale, scale, scale)
    w.prim('f', *color)
    w.prim('i', 0)                                   # lifetime: forever
    w.prim('I', 0)
    w.prim('?', False)                               # frame_locked
    w.array(points, '<f8', count=len(points))
    if colors is None:
        w.prim('I', 0)
    else:
        w.array(colors, '<f4', count=len(colors))
    w.string('')                                     # texture_resource
    _header(w, 0, 0, '')                             # texture: CompressedImage
    w.string('')
    w.prim('I', 0)
    w.prim('I', 0)                                   # uv_coordinates
    w.string('')                                     # text
    w.string('')                                     # mesh_resource
    w.string('')                                     # mesh_file.filename
    w.prim('I', 0)                                   # mesh_file.data
    w.prim('?', False)                               # mesh_use_embedded_materials


def mesh_marker_array(positions: np.ndarray, faces: np.ndarray, vertex_colors: np.ndarray,
                      stamp_ns: int, frame_id: str, edges: Optional[np.ndarray] = None,
                      pinned: Optional[np.ndarray] = None, pin_size: float = 0.02,
                      wire_color=(0.1, 0.1, 0.1, 1.0),
                      pin_color=(0.9, 0.2, 0.1, 1.0),
                      handles: Optional[np.ndarray] = None,
                      handle_color=(0.1, 0.8, 0.3, 1.0), delete=()) -> bytes:
    """Serialised ``visualization_msgs/MarkerArray`` of the cloth.

    Parameters
    ----------
    positions : (n, 3) float64 vertex positions [m] in ``frame_id``.
    faces : (m, 3) int64 triangles.
    vertex_colors : (n, 4) float32 RGBA in [0, 1] per vertex.
    stamp_ns : header stamp [ns] (simulation time).
    edges : (e, 2) int64 or None; a LINE_LIST wireframe (id 1) when given.
    pinned : (k,) int64 or None; a SPHERE_LIST of pinned vertices (id 2) when non-empty
        (the vertices grasp handles hold are pinned too).
    handles : (h, 3) float64 or None; the grasp handles' origins as a SPHERE_LIST (id 3,
        three times the pin size) when non-empty.
    delete : marker ids (of 1, 2, 3) to remove, each as a DELETE marker after the others:
        the node sends one for each optional marker a message does not draw, in every
        message (markers live until replaced or deleted, so a released grasp's spheres
        would otherwise stay on screen, and one lost message must not leave them there;
        :func:`optional_markers` says which a message draws).

    Marker 0 is a TRIANGLE_LIST with one point and one colour per triangle corner, unit
    scale and an opaque base colour (RViz needs a non-zero ``color.a`` even with per-vertex
    colours); markers are in namespace ``"cloth"``.
    """
    sec, nanosec = divmod(int(stamp_ns), 1_000_000_000)
    corners = faces.reshape(-1)
    # np.take, not positions[corners]: numpy's fancy indexing of rows is much slower
    drawn = optional_markers(edges, pinned, handles)
    w = CdrWriter()
    w.prim('I', 1 + len(drawn) + len(delete))
    _marker(w, sec, nanosec, frame_id, MESH_ID, TRIANGLE_LIST, 1.0, (1.0, 1.0, 1.0, 1.0),
            np.take(positions, corners, axis=0), np.take(vertex_colors, corners, axis=0))
    if WIREFRAME_ID in drawn:
        _marker(w, sec, nanosec, frame_id, WIREFRAME_ID, LINE_LIST, 0.002, wire_color,
                np.take(positions, edges.reshape(-1), axis=0), None)
    if PINS_ID in drawn:
        _marker(w, sec, nanosec, frame_id, PINS_ID, SPHERE_LIST, pin_size, pin_color,
                positions[pinned], None)
    if HANDLES_ID in drawn:
        _marker(w, sec, nanosec, frame_id, HANDLES_ID, SPHERE_LIST, 3 * pin_size,
                handle_color, np.ascontiguousarray(handles, dtype=np.float64), None)
    for mid in delete:
        _marker(w, sec, nanosec, frame_id, int(mid), SPHERE_LIST, 1.0, (0.0, 0.0, 0.0, 0.0),
                np.zeros((0, 3)), None, action=DELETE)
    return w.bytes()


#: the ids of the optional markers of ~/mesh: wireframe, pins, handles
OPTIONAL_MARKERS = frozenset((WIREFRAME_ID, PINS_ID, HANDLES_ID))


def optional_markers(edges=None, pinned=None, handles=None) -> frozenset:
    """The ids of the optional markers :func:`mesh_marker_array` draws with these
    arguments (1 wireframe, 2 pins, 3 handles)."""
    return frozenset(k for k, a in ((WIREFRAME_ID, edges), (PINS_ID, pinned),
                                    (HANDLES_ID, handles))
                     if a is not None and (k == WIREFRAME_ID or len(a) > 0))


#: sensor_msgs/PointField datatype FLOAT32
_FLOAT32 = 7
#: the fields of ``~/points``, float32 each, in this order
POINT_FIELDS = ('x', 'y', 'z', 'vx', 'vy', 'vz')


def point_cloud(positions: np.ndarray, velocities: np.ndarray, stamp_ns: int,
                frame_id: str) -> bytes:
    """Serialised ``sensor_msgs/PointCloud2``: one point per vertex in vertex order, float32
    fields x y z [m] and vx vy vz [m/s] (:data:`POINT_FIELDS`), little-endian, dense, one
    row."""
    n = len(positions)
    data = np.empty((n, 6), dtype='<f4')
    data[:, :3] = positions
    data[:, 3:] = velocities
    sec, nanosec = divmod(int(stamp_ns), 1_000_000_000)
    w = CdrWriter()
    _header(w, sec, nanosec, frame_id)
    w.prim('I', 1)                                   # height
    w.prim('I', n)                                   # width
    w.prim('I', len(POINT_FIELDS))
    for k, name in enumerate(POINT_FIELDS):
        w.string(name)
        w.prim('I', 4 * k)                           # offset
        w.prim('B', _FLOAT32)
        w.prim('I', 1)                               # count
    w.prim('?', False)                               # is_bigendian
    w.prim('I', 24)                                  # point_step
    w.prim('I', 24 * n)                              # row_step
    w.array(data.reshape(-1).view(np.uint8), '<u1')
    w.prim('?', True)                                # is_dense
    return w.bytes()


def image(pixels: np.ndarray, stamp_ns: int, frame_id: str) -> bytes:
    """Serialised ``sensor_msgs/Image`` of ``pixels``: (h, w) float32 as ``32FC1`` (a
    depth image in metres, REP 118) or (h, w, 3) uint8 as ``rgb8``; little-endian, rows
    packed (``step`` = w times the pixel's bytes)."""
    if pixels.ndim == 2 and pixels.dtype == np.float32:
        encoding, data = '32FC1', pixels.astype('<f4', copy=False)
    elif pixels.ndim == 3 and pixels.shape[2] == 3 and pixels.dtype == np.uint8:
        encoding, data = 'rgb8', pixels
    else:
        raise ValueError(f'an image is (h, w) float32 or (h, w, 3) uint8, got '
                         f'{pixels.shape} {pixels.dtype}')
    h, w = pixels.shape[:2]
    sec, nanosec = divmod(int(stamp_ns), 1_000_000_000)
    out = CdrWriter()
    _header(out, sec, nanosec, frame_id)
    out.prim('I', h)
    out.prim('I', w)
    out.string(encoding)
    out.prim('B', 0)                                 # is_bigendian
    out.prim('I', data.nbytes // max(h, 1))          # step [bytes]
    out.array(np.ascontiguousarray(data).reshape(-1).view(np.uint8), '<u1')
    return out.bytes()


def camera_info(K: np.ndarray, width: int, height: int, stamp_ns: int,
                frame_id: str) -> bytes:
    """Serialised ``sensor_msgs/CameraInfo`` of an ideal pinhole camera: ``K`` (3x3), no
    distortion (``plumb_bob``, D = 0 (5)), R = I, P = [K | 0], no binning, full ROI."""
    sec, nanosec = divmod(int(stamp_ns), 1_000_000_000)
    out = CdrWriter()
    _header(out, sec, nanosec, frame_id)
    out.prim('I', height)
    out.prim('I', width)
    out.string('plumb_bob')
    out.array(np.zeros(5), '<f8')
    out.prim('d', *np.asarray(K, dtype=np.float64).reshape(-1))
    out.prim('d', *np.eye(3).reshape(-1))
    out.prim('d', *np.hstack([K, np.zeros((3, 1))]).reshape(-1))
    out.prim('I', 0, 0)                              # binning
    out.prim('I', 0, 0, 0, 0)                        # roi: offsets, size (0: full)
    out.prim('?', False)                             # roi.do_rectify
    return out.bytes()


def organised_cloud(points: np.ndarray, stamp_ns: int, frame_id: str) -> bytes:
    """Serialised organised ``sensor_msgs/PointCloud2`` of (h, w, 3) float32 points: one
    per pixel, row-major, fields x y z float32, NaN where nothing was hit (not dense)."""
    h, w = points.shape[:2]
    sec, nanosec = divmod(int(stamp_ns), 1_000_000_000)
    out = CdrWriter()
    _header(out, sec, nanosec, frame_id)
    out.prim('I', h)
    out.prim('I', w)
    out.prim('I', 3)
    for k, name in enumerate('xyz'):
        out.string(name)
        out.prim('I', 4 * k)
        out.prim('B', _FLOAT32)
        out.prim('I', 1)
    out.prim('?', False)                             # is_bigendian
    out.prim('I', 12)                                # point_step
    out.prim('I', 12 * w)                            # row_step
    data = np.ascontiguousarray(points, dtype='<f4')
    out.array(data.reshape(-1).view(np.uint8), '<u1')
    out.prim('?', False)                             # is_dense: NaN where no hit
    return out.bytes()


def shape_mesh(positions: np.ndarray, faces: np.ndarray) -> bytes:
    """Serialised ``shape_msgs/Mesh`` (what MoveIt collision objects take): the triangles
    as vertex indices, the vertices [m]. It has no header: it is in the node's frame_id at
    the time of the ``~/mesh`` message of the same tick."""
    w = CdrWriter()
    w.array(faces, '<u4', count=len(faces))          # MeshTriangle: uint32[3], no count
    w.array(positions, '<f8', count=len(positions))
    return w.bytes()


# viridis-like, 8 evenly spaced control points
_VIRIDIS = np.array([
    [0.267004, 0.004874, 0.329415], [0.275191, 0.194905, 0.496005],
    [0.212395, 0.359683, 0.551710], [0.153364, 0.497000, 0.557724],
    [0.122312, 0.633153, 0.530398], [0.288921, 0.758394, 0.428426],
    [0.626579, 0.854645, 0.223353], [0.993248, 0.906157, 0.143936]])
_VIRIDIS_T = np.linspace(0.0, 1.0, len(_VIRIDIS))


def colormap(values: np.ndarray, vmin: float, vmax: float, alpha: float = 1.0) -> np.ndarray:
    """Viridis-like RGBA (n, 4) float32 for ``values`` scaled from [vmin, vmax]: piecewise
    linear through the 8 control points (one ``np.interp`` per channel, cheaper than
    indexing the table per value). NaN maps to vmin."""
    v = np.asarray(values, dtype=np.float64)
    span = vmax - vmin
    t = np.clip((v - vmin) / span, 0.0, 1.0) if span > 0 else np.zeros_like(v)
    t = np.nan_to_num(t)
    out = np.empty((len(v), 4), dtype=np.float32)
    for c in range(3):
        out[:, c] = np.interp(t, _VIRIDIS_T, _VIRIDIS[:, c])
    out[:, 3] = alpha
    return out


def percentile(v: np.ndarray, q: float) -> float:
    """``np.percentile(v, q)`` (linear interpolation between the two nearest ranks) from a
    partial sort of those two ranks: much cheaper than a full sort, each publish."""
    k = q / 100.0 * (len(v) - 1)
    lo = int(k)
    hi = min(lo + 1, len(v) - 1)
    p = np.partition(v, (lo, hi))
    return float(p[lo] + (k - lo) * (p[hi] - p[lo]))


#: the colour of every vertex with ``coloring: none`` (RGBA)
PLAIN_COLOR = (0.55, 0.65, 0.85, 1.0)


def vertex_colors(coloring: str, sim, densities) -> np.ndarray:
    """(n, 4) float32 RGBA per vertex of ``sim``'s cloth as the node's ``coloring`` draws
    it: ``energy`` (the total energy density, scaled to its 98th percentile: pins would
    saturate a max), ``stretch`` (area ratio - 1 over [-5%, 5%]), ``speed`` (|v| over its
    max) or ``none`` (:data:`PLAIN_COLOR`). ``densities``: the simulator's energy
    densities ({'total': (n,) J/m^2, ...})."""
    n = sim.n_vertices
    if coloring == 'none':
        out = np.empty((n, 4), dtype=np.float32)
        out[:] = PLAIN_COLOR
        return out
    if coloring == 'energy':
        v = densities['total']
        return colormap(v, 0.0, max(percentile(v, 98.0), 1e-12))
    if coloring == 'speed':
        v = np.linalg.norm(sim.velocities, axis=1)
        return colormap(v, 0.0, max(float(v.max()), 1e-9))
    g = sim.geometry()                                   # stretch: area ratio - 1
    v = np.sqrt(np.linalg.det(g.metric) / np.linalg.det(g.rest_metric)) - 1.0
    return colormap(v, -0.05, 0.05)
