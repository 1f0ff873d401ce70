"""A virtual RGB-D camera: depth and colour images of a :class:`~cosserat_ros.ClothSimulator`
(the cloth, both of its sides, and every obstacle), ray-cast on the CPU.

::

    from cosserat_ros.camera import Camera
    cam = Camera.looking_at(640, 480, fov=60.0, position=(0, 0, 1.5), target=(0, 0, 0))
    depth, rgb = cam.render(sim)       # (480, 640) float32 [m], (480, 640, 3) uint8
    points = cam.points(depth)         # (480, 640, 3) float32 in the optical frame

Conventions (those of ROS cameras, REP 103 and ``sensor_msgs/CameraInfo``):

* The pose is the camera's **optical frame** in the world: z forward, x right, y down;
  ``orientation`` a unit quaternion (x, y, z, w) rotating optical-frame vectors into
  the world. A camera looking straight down with image x along world x has
  orientation (1, 0, 0, 0).
* ``fov`` is the vertical field of view [degrees]; pixels are square, so
  ``fy = fx = (height / 2) / tan(fov / 2)``, and the principal point is the image's
  centre with pixel centres at integer coordinates (OpenCV, ROS):
  ``cx = (width - 1) / 2``, ``cy = (height - 1) / 2``. Pixel (u, v) sees along the ray
  ``K^-1 (u, v, 1)``.
* ``depth[v, u]`` is the z (along the optical axis, not along the ray) of the nearest
  surface the pixel's ray meets between ``near`` and ``far`` [m], NaN where none is.
  The cloth is its mid-surface (the contact layer keeps it ``contact_thickness`` above a
  support, so it is seen above the table it lies on).
* ``rgb``: the cloth in the given per-vertex colours (default :data:`FABRIC`; the node
  passes its ``coloring``), planes in light grey, other obstacles in grey, lit by a light
  at the camera on both sides of every surface; :data:`BACKGROUND` where nothing is hit.

The kernels and their formulas are in :mod:`cosserat_ros.core.raster`: exact float64
ray-triangle and ray-shape intersections, binned by image rows so that the cost grows with
pixels plus triangles. This module imports no ROS package.
"""
from __future__ import annotations

import math
from typing import Optional, Sequence

import numpy as np

from .core import raster
from .core.contact import rotation_matrix

__all__ = ['Camera', 'FABRIC', 'BACKGROUND', 'MAX_SIDE', 'MAX_PIXELS', 'quaternion_looking_at']

#: the cloth's flat colour (RGB in [0, 1]; the node's ``coloring: none``)
FABRIC = (0.55, 0.65, 0.85)
#: the colour where nothing is hit
BACKGROUND = (0.96, 0.96, 0.96)
#: grey levels of planes and of the other obstacles
PLANE_GRAY, OBSTACLE_GRAY = 0.8, 0.55
#: the part of the light that does not depend on the surface's angle
AMBIENT = 0.35
#: the largest image side [px] and the most pixels of one image (its scratch is ~80 bytes
#: a pixel: 2048 x 2048 needs ~330 MB)
MAX_SIDE = 4096
MAX_PIXELS = 2048 * 2048


def _int(value, name, low, high) -> int:
    if isinstance(value, (bool, np.bool_)) or not isinstance(value, (int, np.integer)):
        raise ValueError(f'{name} must be an integer, got {value!r}')
    if not low <= int(value) <= high:
        raise ValueError(f'{name} must be in [{low}, {high}], got {value}')
    return int(value)


def _float(value, name) -> float:
    try:
        x = float(value)
    except (TypeError, ValueError):
        raise ValueError(f'{name} must be a number, got {value!r}') from None
    if not math.isfinite(x):
        raise ValueError(f'{name} must be finite, got {value!r}')
    return x


def _vector(value, name, n) -> np.ndarray:
    try:
        arr = np.asarray(value, dtype=np.float64).reshape(-1)
    except (TypeError, ValueError):
        raise ValueError(f'{name} must be {n} numbers, got {value!r}') from None
    if arr.shape != (n,) or not np.all(np.isfinite(arr)):
        raise ValueError(f'{name} must be {n} finite numbers, got {value!r}')
    return arr


def check_orientation(value, name='orientation') -> np.ndarray:
    """A unit quaternion (x, y, z, w) within 1e-3 of norm 1 (renormalised), else
    ValueError."""
    q = _vector(value, name, 4)
    norm = float(np.linalg.norm(q))
    if abs(norm - 1.0) > 1e-3:
        raise ValueError(f'{name} must be a unit quaternion (x, y, z, w), got '
                         f'{list(q)} (norm {norm:.4g})')
    return q / norm


def quaternion_looking_at(position, target, up=(0.0, 0.0, 1.0)) -> np.ndarray:
    """The optical-frame orientation (x, y, z, w) of a camera at ``position`` looking at
    ``target``, its image's up (-y) as close to ``up`` as the view allows (any up
    perpendicular to the view when ``up`` is parallel to it)."""
    p, t, w_up = (_vector(v, n, 3) for v, n in ((position, 'position'), (target, 'target'),
                                                 (up, 'up')))
    z = t - p
    if np.linalg.norm(z) == 0.0:
        raise ValueError('target must differ from position')
    z /= np.linalg.norm(z)
    x = np.cross(z, w_up)                 # right = forward x up (y down = -up)
    if np.linalg.norm(x) < 1e-9 * max(np.linalg.norm(w_up), 1e-300):
        x = np.cross(z, [1.0, 0.0, 0.0] if abs(z[0]) < 0.9 else [0.0, 1.0, 0.0])
    x /= np.linalg.norm(x)
    y = np.cross(z, x)
    return _quaternion_of(np.column_stack([x, y, z]))


def _quaternion_of(R: np.ndarray) -> np.ndarray:
    """(x, y, z, w) of a rotation matrix (Shepperd's method: the largest diagonal term)."""
    tr = np.trace(R)
    k = int(np.argmax([R[0, 0], R[1, 1], R[2, 2], tr]))
    if k == 3:
        w = 0.5 * math.sqrt(1.0 + tr)
        q = [(R[2, 1] - R[1, 2]) / (4 * w), (R[0, 2] - R[2, 0]) / (4 * w),
             (R[1, 0] - R[0, 1]) / (4 * w), w]
    else:
        i, j, m = k, (k + 1) % 3, (k + 2) % 3
        s = 2.0 * math.sqrt(1.0 + R[i, i] - R[j, j] - R[m, m])
        q = [0.0, 0.0, 0.0, (R[m, j] - R[j, m]) / s]
        q[i] = 0.25 * s
        q[j] = (R[j, i] + R[i, j]) / s
        q[m] = (R[m, i] + R[i, m]) / s
    q = np.array(q)
    return q / np.linalg.norm(q)


class Camera:
    """A pinhole RGB-D camera (module docstring for the conventions).

    Parameters
    ----------
    width, height : int
        Image size [px], each in [1, :data:`MAX_SIDE`], at most :data:`MAX_PIXELS` pixels.
    fov : float
        Vertical field of view [degrees], in (0, 180).
    position : 3 floats
        The optical centre in the world [m].
    orientation : 4 floats
        Unit quaternion (x, y, z, w) of the optical frame in the world.
    near, far : float
        The depth range [m] that is seen, 0 < near < far.
    """

    def __init__(self, width: int, height: int, fov: float, position, orientation,
                 near: float = 0.01, far: float = 10.0):
        self.width = _int(width, 'width', 1, MAX_SIDE)
        self.height = _int(height, 'height', 1, MAX_SIDE)
        if self.width * self.height > MAX_PIXELS:
            raise ValueError(f'{self.width} x {self.height} = {self.width * self.height} '
                             f'pixels, at most {MAX_PIXELS}')
        self.fov = _float(fov, 'fov')
        if not 0.0 < self.fov < 180.0:
            raise ValueError(f'fov must be in (0, 180) degrees, got {self.fov}')
        self.near = _float(near, 'near')
        self.far = _float(far, 'far')
        if not 0.0 < self.near < self.far:
            raise ValueError(f'need 0 < near < far, got near {self.near}, far {self.far}')
        f = 0.5 * self.height / math.tan(math.radians(0.5 * self.fov))
        self._f = f
        self._c = (0.5 * (self.width - 1), 0.5 * (self.height - 1))
        self.set_pose(position, orientation)
        self._scratch = None              # (depth, hit, bary), allocated at the first render

    @classmethod
    def looking_at(cls, width: int, height: int, fov: float, position, target,
                   up=(0.0, 0.0, 1.0), **kwargs) -> 'Camera':
        """A camera at ``position`` looking at ``target`` (:func:`quaternion_looking_at`)."""
        return cls(width, height, fov, position, quaternion_looking_at(position, target, up),
                   **kwargs)

    # ------------------------------------------------------------------ pose
    def set_pose(self, position, orientation) -> None:
        """Move the camera: ``position`` [m] and the unit quaternion ``orientation``
        (x, y, z, w) of its optical frame in the world."""
        p = _vector(position, 'position', 3)
        q = check_orientation(orientation)
        self.position, self.orientation = p, q
        self.rotation = rotation_matrix(q)          # optical frame -> world

    @property
    def intrinsics(self) -> np.ndarray:
        """The 3x3 camera matrix K = [[fx, 0, cx], [0, fy, cy], [0, 0, 1]] [px]."""
        cx, cy = self._c
        return np.array([[self._f, 0.0, cx], [0.0, self._f, cy], [0.0, 0.0, 1.0]])

    def to_camera(self, points) -> np.ndarray:
        """World points (..., 3) in the optical frame: ``R^T (p - position)``."""
        return (np.asarray(points, dtype=np.float64) - self.position) @ self.rotation

    def rays(self) -> np.ndarray:
        """(height, width, 3) the direction ``K^-1 (u, v, 1)`` of every pixel's ray in the
        optical frame (z = 1)."""
        cx, cy = self._c
        u = (np.arange(self.width) - cx) / self._f
        v = (np.arange(self.height) - cy) / self._f
        out = np.ones((self.height, self.width, 3))
        out[:, :, 0] = u[None, :]
        out[:, :, 1] = v[:, None]
        return out

    # ------------------------------------------------------------------ images
    def render(self, sim, colors: Optional[Sequence] = None):
        """``(depth, rgb)`` of ``sim`` now: depth (height, width) float32 [m], NaN where
        nothing is hit; rgb (height, width, 3) uint8. ``colors``: (n, 3) or (n, 4) per
        vertex RGB(A) in [0, 1] (the alpha is ignored), default :data:`FABRIC`.
        Fresh arrays every call."""
        n = sim.n_vertices
        if colors is None:
            cols = np.empty((n, 3))
            cols[:] = FABRIC
        else:
            cols = np.asarray(colors, dtype=np.float64)
            if cols.ndim != 2 or cols.shape[0] != n or cols.shape[1] not in (3, 4):
                raise ValueError(f'colors must be ({n}, 3) or ({n}, 4), got {cols.shape}')
            cols = np.ascontiguousarray(cols[:, :3])
        verts, tris, gray, ob, ob_gray = self._scene(sim)
        n_cloth = sim.mesh.n_faces
        fx = fy = self._f
        cx, cy = self._c
        if self._scratch is None:
            h, w = self.height, self.width
            self._scratch = (np.empty((h, w)), np.empty((h, w), np.int64),
                             np.empty((h, w, 2)))
        dep, hit, bary = self._scratch
        raster.cast(verts, tris, ob, fx, fy, cx, cy, self.near, self.far, dep, hit, bary)
        vn = np.zeros((len(verts), 3))
        raster.vertex_normals(verts, tris, n_cloth, vn)
        rgb = np.empty((self.height, self.width, 3), np.uint8)
        padded = np.zeros((len(verts), 3))
        padded[:n] = cols
        raster.shade(verts, tris, n_cloth, vn, padded, ob_gray, gray, fx, fy, cx, cy,
                     ob, dep, hit, bary, np.asarray(BACKGROUND), AMBIENT, rgb)
        depth = dep.astype(np.float32)
        depth[hit == raster.NO_HIT] = np.nan
        return depth, rgb

    def points(self, depth) -> np.ndarray:
        """The organised point cloud (height, width, 3) float32 of a depth image in the
        optical frame: ``depth * K^-1 (u, v, 1)``, NaN where the depth is NaN."""
        d = np.asarray(depth, dtype=np.float64)
        if d.shape != (self.height, self.width):
            raise ValueError(f'depth must be ({self.height}, {self.width}), got {d.shape}')
        return (self.rays() * d[:, :, None]).astype(np.float32)

    def _scene(self, sim):
        """Triangles (cloth first, then mesh obstacles) in the optical frame, each mesh
        triangle's grey, and the analytic obstacles' rows (:mod:`.core.raster`)."""
        Rt = self.rotation.T
        parts = [self.to_camera(sim.state.x)]
        tris = [np.asarray(sim.mesh.faces, dtype=np.int64)]
        offset = len(parts[0])
        rows, ob_gray = [], []
        for oid, d in sim.obstacles.items():
            R = rotation_matrix(d['orientation'])
            c = np.asarray(d['position'], dtype=np.float64)
            if d['shape'] == 'mesh':
                v, f = sim.obstacle_mesh(oid)
                parts.append(self.to_camera(c + v @ R.T))
                tris.append(f.astype(np.int64) + offset)
                offset += len(v)
                continue
            row = np.zeros(raster.OB_WIDTH)
            row[raster.OB_KIND] = {'plane': raster.KIND_PLANE, 'sphere': raster.KIND_SPHERE,
                                   'box': raster.KIND_BOX, 'capsule': raster.KIND_CAPSULE,
                                   'cylinder': raster.KIND_CYLINDER}[d['shape']]
            row[raster.OB_O:raster.OB_O + 3] = R.T @ (self.position - c)
            row[raster.OB_R:raster.OB_R + 9] = (R.T @ self.rotation).reshape(-1)
            reach = 0.0
            if d['shape'] == 'sphere':
                row[raster.OB_P] = reach = d['radius']
            elif d['shape'] == 'box':
                row[raster.OB_P:raster.OB_P + 3] = d['half_extents']
                reach = float(np.linalg.norm(d['half_extents']))
            elif d['shape'] in ('capsule', 'cylinder'):
                row[raster.OB_P:raster.OB_P + 2] = d['radius'], d['half_length']
                reach = d['radius'] + d['half_length']
            row[raster.OB_BOX:raster.OB_BOX + 4] = self._pixel_box(Rt @ (c - self.position),
                                                                   reach)
            rows.append(row)
            ob_gray.append(PLANE_GRAY if d['shape'] == 'plane' else OBSTACLE_GRAY)
        verts = np.ascontiguousarray(np.concatenate(parts))
        all_tris = np.ascontiguousarray(np.concatenate(tris))
        gray = np.full(len(all_tris), OBSTACLE_GRAY)
        ob = np.array(rows).reshape(-1, raster.OB_WIDTH)
        return verts, all_tris, gray, ob, np.array(ob_gray, dtype=np.float64)

    def _pixel_box(self, center, reach: float):
        """(u0, u1, v0, v1) inclusive: the pixels whose rays may meet a solid within
        ``reach`` of ``center`` (optical frame): the projection of the cube around that
        ball (convex, so its image lies within the hull of the corners' images) when
        the cube is in front of the camera, the whole image otherwise or when
        ``reach`` is 0 (a plane)."""
        full = (0.0, self.width - 1.0, 0.0, self.height - 1.0)
        if reach == 0.0:
            return full
        corners = center + reach * np.array([[i, j, k] for i in (-1, 1) for j in (-1, 1)
                                              for k in (-1, 1)], dtype=np.float64)
        z = corners[:, 2]
        if z.max() < self.near or z.min() > self.far:
            return (1.0, 0.0, 1.0, 0.0)                  # unseen
        if z.min() <= 0.0:
            return full
        cx, cy = self._c
        u = self._f * corners[:, 0] / z + cx
        v = self._f * corners[:, 1] / z + cy
        u0, u1 = max(0.0, math.floor(u.min())), min(self.width - 1.0, math.ceil(u.max()))
        v0, v1 = max(0.0, math.floor(v.min())), min(self.height - 1.0, math.ceil(v.max()))
        if u0 > u1 or v0 > v1:
            return (1.0, 0.0, 1.0, 0.0)
        return (u0, u1, v0, v1)

    def __repr__(self):
        return (f'Camera({self.width} x {self.height}, fov {self.fov:g} deg, at '
                f'{tuple(np.round(self.position, 4))})')
