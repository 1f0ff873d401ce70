"""The obstacle set of a simulator: shapes and their checks, poses, velocities and the
table the compiled step reads (:mod:`.contact` has the physics).

:class:`ObstacleSet` is what ``ClothSimulator.add_obstacle`` and friends work on. Every
geometry argument is checked here (finite, positive sizes, unit quaternions) and refused
with a ``ValueError`` that says why; the table (``Control.obstacles``) is rebuilt on
every change, so the step never sees a half-made obstacle.

Moving obstacles: between two poses the user sets, an obstacle moves with its linear and
angular velocity. The step reads a pose per call of the compiled step, so
:meth:`ObstacleSet.max_steps` bounds the steps of one call by the obstacle's travel:
at most a quarter of the contact thickness per call (a displacement cap; a vertex in the
way is pushed back onto the layer by at most that much, and the obstacle's velocity
already enters every contact's friction and normal response).

Placed through the cloth: an obstacle added, or given a new pose, where vertices of the
cloth are inside its solid is released from them until they are out of its layer
(:meth:`ObstacleSet.release`; the physics and why: :mod:`.contact`, "Obstacles placed
through the cloth"). The masks live in ``Control.contact``, one bit per table row, so
a change of the set moves them onto the rows the obstacles have after it
(:meth:`ObstacleSet.remap_released`).
"""
from __future__ import annotations

import copy
import math
import os
from typing import Dict, Optional, Tuple

import numpy as np

from . import contact as C
from .feature_shapes import FEATURE_META, FM_WIDTH, sharp_features

__all__ = ['ObstacleSet', 'SHAPE_ARGS']

#: the geometry arguments of each shape (besides friction and name)
SHAPE_ARGS = {
    'plane': ('point', 'normal'),
    'sphere': ('center', 'radius'),
    'box': ('center', 'half_extents', 'orientation'),
    'capsule': ('center', 'radius', 'half_length', 'orientation'),
    'cylinder': ('center', 'radius', 'half_length', 'orientation'),
    'mesh': ('vertices', 'faces', 'file', 'center', 'orientation', 'spacing'),
}

#: the mesh field's default grid spacing [m] and its margin around the mesh, in cells
FIELD_SPACING = 0.01
FIELD_MARGIN_CELLS = 4
#: the most samples a mesh field may have (bounded memory per obstacle)
FIELD_MAX_SAMPLES = 2_000_000
#: the most triangle-sample distance tests its construction may make (bounded work: about
#: a second; a 5,120-triangle sphere of radius 0.2 m at 1 cm makes ~4e6)
FIELD_MAX_VISITS = 5e7
#: a vertex within this many contact thicknesses of an obstacle's surface before a new
#: pose is on it (resting, or about to): the pose carries it (:meth:`ObstacleSet.release`)
CARRY_THICKNESS = 2.0


def _vec(value, name, n=3) -> np.ndarray:
    try:
        arr = np.asarray(value, dtype=np.float64).reshape(-1)
    except (TypeError, ValueError):
        raise ValueError(f'{name} must be {n} numbers, got {value!r}') from None
    if arr.shape != (n,):
        raise ValueError(f'{name} must be {n} numbers, got {value!r}')
    if not np.all(np.isfinite(arr)):
        raise ValueError(f'{name} must be finite, got {value!r}')
    return arr


def _positive(value, name) -> float:
    try:
        x = float(value)
    except (TypeError, ValueError):
        raise ValueError(f'{name} must be a number, got {value!r}') from None
    if not (math.isfinite(x) and x > 0):
        raise ValueError(f'{name} must be positive and finite, got {value!r}')
    return x


def _quaternion(value, name='orientation') -> np.ndarray:
    q = _vec(value, name, 4)
    norm = float(np.linalg.norm(q))
    if abs(norm - 1.0) > 1e-3:
        raise ValueError(f'{name} must be a unit quaternion (x, y, z, w), got {value!r} '
                         f'(norm {norm:.4g})')
    return q / norm


def _friction(value) -> Tuple[float, float]:
    """mu, or (mu_static, mu_kinetic), each >= 0, kinetic <= static."""
    if np.ndim(value) == 0:
        value = (value, value)
    try:
        ms, mk = (float(v) for v in value)
    except (TypeError, ValueError):
        raise ValueError(f'friction must be mu or (mu_static, mu_kinetic), got {value!r}') \
            from None
    if not (math.isfinite(ms) and math.isfinite(mk) and ms >= 0 and mk >= 0):
        raise ValueError(f'friction must be finite and >= 0, got {value!r}')
    if mk > ms:
        raise ValueError(f'kinetic friction {mk} must not exceed static friction {ms}')
    return ms, mk


def _plane_quaternion(normal: np.ndarray) -> np.ndarray:
    """A quaternion turning local z onto ``normal`` (unit)."""
    z = np.array([0.0, 0.0, 1.0])
    c = float(np.dot(z, normal))
    if c < -1 + 1e-12:
        return np.array([1.0, 0.0, 0.0, 0.0])
    axis = np.cross(z, normal)
    q = np.array([axis[0], axis[1], axis[2], 1.0 + c])
    return q / np.linalg.norm(q)


class _Obstacle:
    __slots__ = ('name', 'shape', 'params', 'position', 'orientation', 'velocity',
                 'omega', 'friction', 'field', 'mesh', 'sharp')

    def describe(self) -> dict:
        d = {'name': self.name, 'shape': self.shape,
             'position': tuple(self.position), 'orientation': tuple(self.orientation),
             'linear_velocity': tuple(self.velocity),
             'angular_velocity': tuple(self.omega),
             'friction': {'static': self.friction[0], 'kinetic': self.friction[1]}}
        d.update(self.params)
        return d


def id_key(items: dict, key, what: str) -> int:
    """``key`` as the int an item of ``items`` is stored under; ValueError naming ``what``
    for anything else (a float or a string is not truncated into another item's id).
    The obstacles' and the handles' ids (:mod:`.handles`)."""
    if (isinstance(key, (bool, np.bool_)) or not isinstance(key, (int, np.integer))
            or int(key) not in items):
        raise ValueError(f'no {what} with id {key!r}')
    return int(key)


class ObstacleSet:
    """The obstacles of one simulator (module docstring)."""

    def __init__(self):
        self._items: Dict[int, _Obstacle] = {}
        self._next = 0
        self._fields: Dict[int, Tuple[np.ndarray, np.ndarray, np.ndarray]] = {}
        self.table = np.zeros((0, C.WIDTH))
        self.meta = np.zeros((0, 8))
        self.data = np.zeros(0)
        self.shapes = (np.zeros((0, FM_WIDTH)), np.zeros((0, 3)), np.zeros((0, 2), np.int64))
        self.ids: list = []              # table row -> obstacle id
        self._released_ids: list = []    # the rows the release masks were set for

    def __len__(self):
        return len(self._items)

    # ------------------------------------------------------------------ building
    def add(self, shape: str, friction=0.5, name: Optional[str] = None, **geometry) -> int:
        if shape not in SHAPE_ARGS:
            raise ValueError(f'unknown obstacle shape {shape!r}; one of '
                             f'{", ".join(SHAPE_ARGS)}')
        unknown = set(geometry) - set(SHAPE_ARGS[shape])
        if unknown:
            raise ValueError(f'{shape} takes {", ".join(SHAPE_ARGS[shape])}; got '
                             f'{", ".join(sorted(unknown))}')
        if name is not None:
            name = str(name)
            if any(o.name == name for o in self._items.values()):
                raise ValueError(f'an obstacle named {name!r} exists already')
        o = _Obstacle()
        o.shape = shape
        o.friction = _friction(friction)
        o.velocity = np.zeros(3)
        o.omega = np.zeros(3)
        o.field = None
        o.mesh = None
        o.sharp = None
        o.orientation = np.array([0.0, 0.0, 0.0, 1.0])
        g = geometry
        if shape == 'plane':
            o.position = _vec(g.get('point', (0.0, 0.0, 0.0)), 'point')
            normal = _vec(g.get('normal', (0.0, 0.0, 1.0)), 'normal')
            norm = float(np.linalg.norm(normal))
            if norm < 1e-12:
                raise ValueError('normal must not be zero')
            o.orientation = _plane_quaternion(normal / norm)
            o.params = {}
        elif shape == 'sphere':
            o.position = _vec(self._required(g, 'center', shape), 'center')
            o.params = {'radius': _positive(self._required(g, 'radius', shape), 'radius')}
        elif shape == 'box':
            o.position = _vec(self._required(g, 'center', shape), 'center')
            h = _vec(self._required(g, 'half_extents', shape), 'half_extents')
            if np.any(h <= 0):
                raise ValueError(f'half_extents must be positive, got {tuple(h)}')
            o.params = {'half_extents': tuple(h)}
            o.orientation = _quaternion(g.get('orientation', (0, 0, 0, 1)))
        elif shape in ('capsule', 'cylinder'):
            o.position = _vec(self._required(g, 'center', shape), 'center')
            o.params = {'radius': _positive(self._required(g, 'radius', shape), 'radius'),
                        'half_length': _positive(self._required(g, 'half_length', shape),
                                                 'half_length')}
            o.orientation = _quaternion(g.get('orientation', (0, 0, 0, 1)))
        else:
            self._mesh(o, g)
        o.name = name if name is not None else f'{shape}_{self._next}'
        oid = self._next
        self._next += 1
        self._items[oid] = o
        self._rebuild()
        return oid

    @staticmethod
    def _required(g, key, shape):
        if key not in g:
            raise ValueError(f'{shape} needs {key}')
        return g[key]

    def _mesh(self, o, g):
        if 'file' in g:
            if 'vertices' in g or 'faces' in g:
                raise ValueError('mesh takes a file or vertices and faces, not both')
            path = str(g['file'])
            if not os.path.isfile(path):
                raise ValueError(f'mesh file {path!r} does not exist')
            import trimesh
            try:
                loaded = trimesh.load(path, force='mesh', process=True)
            except Exception as exc:  # trimesh raises many types on bad files
                raise ValueError(f'mesh file {path!r} does not load: {exc}') from None
            verts, faces = np.asarray(loaded.vertices), np.asarray(loaded.faces)
        else:
            verts = np.asarray(self._required(g, 'vertices', 'mesh'), dtype=np.float64)
            faces = np.asarray(self._required(g, 'faces', 'mesh'))
        if verts.ndim != 2 or verts.shape[1] != 3 or len(verts) < 4:
            raise ValueError(f'mesh vertices must be (n >= 4, 3), got {verts.shape}')
        if not np.all(np.isfinite(verts)):
            raise ValueError('mesh vertices must be finite')
        if faces.ndim != 2 or faces.shape[1] != 3 or len(faces) < 4:
            raise ValueError(f'mesh faces must be (m >= 4, 3), got {faces.shape}')
        if faces.min() < 0 or faces.max() >= len(verts):
            raise ValueError('mesh faces index vertices that do not exist')
        spacing = _positive(g.get('spacing', FIELD_SPACING), 'spacing')
        extent = verts.max(0) - verts.min(0) + 2 * FIELD_MARGIN_CELLS * spacing
        samples = float(np.prod(np.ceil(extent / spacing) + 1))
        if samples > FIELD_MAX_SAMPLES:
            raise ValueError(f'mesh distance field of {samples:.3g} samples at spacing '
                             f'{spacing} m exceeds {FIELD_MAX_SAMPLES}: use a larger '
                             'spacing')
        band = FIELD_MARGIN_CELLS * spacing
        ext = (verts[faces].max(1) - verts[faces].min(1) + 2 * band) / spacing + 2
        visits = float(np.prod(ext, axis=1).sum())
        if visits > FIELD_MAX_VISITS:
            raise ValueError(f'mesh distance field would test {visits:.3g} triangle-sample '
                             f'pairs at spacing {spacing} m, more than {FIELD_MAX_VISITS:.3g}'
                             ': use fewer or smaller triangles, or a larger spacing')
        import trimesh
        if not trimesh.Trimesh(verts, faces, process=False).is_watertight:
            raise ValueError('mesh obstacle must be closed (watertight): its inside '
                             'must be defined')
        origin, shape, values = C.mesh_distance_field(verts, faces, spacing,
                                                      FIELD_MARGIN_CELLS * spacing)
        o.field = (origin, shape, values, spacing)
        o.mesh = (verts, faces.astype(np.int64))
        o.sharp = sharp_features(verts, faces)     # corners and edges (:mod:`.features`)
        o.position = _vec(g.get('center', (0.0, 0.0, 0.0)), 'center')
        o.orientation = _quaternion(g.get('orientation', (0, 0, 0, 1)))
        o.params = {'triangles': len(faces), 'spacing': spacing}

    def snapshot(self):
        """Everything :meth:`restore_snapshot` needs to undo later changes."""
        return ({oid: copy.copy(o) for oid, o in self._items.items()}, self._next)

    def restore_snapshot(self, snap) -> None:
        """Back to the snapshot (copied again: later changes do not reach it, so it can be
        restored more than once)."""
        self._items = {oid: copy.copy(o) for oid, o in snap[0].items()}
        self._next = snap[1]
        self._rebuild()

    def remove(self, oid: int) -> None:
        del self._items[self._key(oid)]
        self._rebuild()

    def clear(self) -> None:
        self._items.clear()
        self._rebuild()

    def _key(self, oid) -> int:
        return id_key(self._items, oid, 'obstacle')

    def _item(self, oid) -> _Obstacle:
        return self._items[self._key(oid)]

    def find(self, name: str) -> Optional[int]:
        for oid, o in self._items.items():
            if o.name == name:
                return oid
        return None

    def set_pose(self, oid, position, orientation, linear_velocity=(0, 0, 0),
                 angular_velocity=(0, 0, 0)) -> None:
        o = self._item(oid)
        p = _vec(position, 'position')
        q = _quaternion(orientation)
        v = _vec(linear_velocity, 'linear_velocity')
        w = _vec(angular_velocity, 'angular_velocity')
        o.position, o.orientation, o.velocity, o.omega = p, q, v, w
        self._rebuild(fields=False)

    def describe(self) -> Dict[int, dict]:
        return {oid: o.describe() for oid, o in self._items.items()}

    def mesh_of(self, oid) -> Optional[Tuple[np.ndarray, np.ndarray]]:
        return self._item(oid).mesh

    # ------------------------------------------------------------------ the table
    def _rebuild(self, fields: bool = True) -> None:
        """The table the step reads, one row per obstacle; with ``fields`` also the mesh
        obstacles' distance grids and sharp features, concatenated. A pose change
        (``fields`` False) keeps those: they are in each obstacle's own frame, and the
        set and its order are unchanged, so a moving mesh does not copy every mesh's
        field again (up to 16 MB each)."""
        table = np.zeros((len(self._items), C.WIDTH))
        rec = C.records(table)
        metas, datas, ids = [], [], []
        offset = 0
        for row, (oid, o) in zip(rec, self._items.items()):
            row['shape'] = C.SHAPES[o.shape]
            row['position'] = o.position
            row['rotation'] = C.rotation_matrix(o.orientation)
            row['velocity'] = o.velocity
            row['omega'] = o.omega
            if o.shape in ('sphere',):
                row['params'][0] = o.params['radius']
            elif o.shape == 'box':
                row['params'] = o.params['half_extents']
            elif o.shape in ('capsule', 'cylinder'):
                row['params'][:2] = o.params['radius'], o.params['half_length']
            elif o.shape == 'mesh':
                origin, shape, values, spacing = o.field
                row['field'] = len(metas)
                metas.append([offset, shape[0], shape[1], shape[2], origin[0], origin[1],
                              origin[2], spacing])
                datas.append(values)
                offset += len(values)
            row['mu_s'], row['mu_k'] = o.friction
            reach = 0.0 if o.shape == 'plane' else self._reach(o)
            if o.shape == 'mesh':
                reach += FIELD_MARGIN_CELLS * o.field[3]
            row['reach'] = reach
            row['speed'] = (float(np.linalg.norm(o.velocity))
                            + float(np.linalg.norm(o.omega)) * reach)
            ids.append(oid)
        self.table = table
        self.ids = ids
        if not fields:
            return
        self.meta = np.array(metas, dtype=np.float64).reshape(-1, 8)
        # the mesh obstacles' sharp corners and edges, per row (features.Shapes)
        fmeta = np.zeros((len(table), FM_WIDTH))
        frec = fmeta.view(FEATURE_META).reshape(-1)
        corners, edges = [np.zeros((0, 3))], [np.zeros((0, 2), np.int64)]
        nc = ne = 0
        for r, o in enumerate(self._items.values()):
            if o.shape == 'mesh' and len(o.sharp[0]):
                c, e = o.sharp
                frec[r] = nc, len(c), ne, len(e), c.min(0), c.max(0)
                corners.append(c)
                edges.append(e)
                nc += len(c)
                ne += len(e)
        self.shapes = (fmeta, np.concatenate(corners), np.concatenate(edges))
        self.data = np.concatenate(datas) if datas else np.zeros(0)

    # ------------------------------------------------------------------ release
    def row(self, oid) -> int:
        """The table row of obstacle ``oid`` (``ValueError`` if there is none)."""
        return self.ids.index(self._key(oid))

    def distances(self, oid, x) -> np.ndarray:
        """Signed distances [m] of points ``x`` (m, 3) from obstacle ``oid``'s surface at
        its pose now (:func:`.contact.distance`; negative inside)."""
        pts = np.ascontiguousarray(x, dtype=np.float64).reshape(-1, 3)
        return C.distances(self.table, self.meta, self.data, self.row(oid), pts)[:, 0]

    def release(self, oid, x, masks, th, before=None, held=None) -> np.ndarray:
        """The vertices' release masks (n,) uint64 with obstacle ``oid``'s bit set anew
        for the cloth at ``x`` (:mod:`.contact`, "Obstacles placed through the cloth"),
        after the obstacle was added (``before`` None) or given a new pose (``before``:
        each vertex's distance from it at its old pose). Set for the vertices inside its
        solid (d < 0), except those ``held`` (pinned or held: no contact) and, after a
        new pose, those that were within :data:`CARRY_THICKNESS` th of its surface
        before (on it or about to be: the pose carries them, the next step puts them
        back on its layer as a moving obstacle's push would); kept for the vertices
        released before that are still inside its layer (d < th); cleared for the rest.
        An obstacle from the 65th table row on has no bit (:data:`.contact.MASK_BITS`):
        ``masks`` come back unchanged, and every vertex inside it is pushed out."""
        masks = np.asarray(masks, dtype=np.uint64)
        row = self.row(oid)
        if row >= C.MASK_BITS:
            return masks
        d = self.distances(oid, x)
        bit = np.uint64(1) << np.uint64(row)
        had = (masks & bit) != 0
        new = d < 0.0
        if before is not None:
            new &= ~(np.asarray(before) < CARRY_THICKNESS * th)
        new |= had & (d < th)
        if held is not None:
            new &= ~np.asarray(held, dtype=bool)
        return np.where(new, masks | bit, masks & ~bit)

    def remap_released(self, masks) -> np.ndarray:
        """Release masks (n,) uint64 set for the rows of the table of the last call (of
        the set's start) moved onto the rows of the table now: an obstacle keeps its
        vertices' bits wherever its row went, a removed one's are dropped."""
        old, self._released_ids = self._released_ids, list(self.ids)
        masks = np.asarray(masks, dtype=np.uint64)
        if old == self.ids or not masks.any():
            return masks
        out = np.zeros_like(masks)
        for r, oid in enumerate(old[:C.MASK_BITS]):
            if oid in self.ids and self.ids.index(oid) < C.MASK_BITS:
                has = (masks >> np.uint64(r)) & np.uint64(1)
                out |= has << np.uint64(self.ids.index(oid))
        return out

    # ------------------------------------------------------------------ motion
    def moving(self) -> bool:
        return any(np.any(o.velocity) or np.any(o.omega) for o in self._items.values())

    def max_steps(self, dt: float, thickness: float) -> int:
        """The most steps one compiled call may take so that no obstacle moves more than a
        quarter of the contact thickness in it (module docstring); 0: no limit."""
        speed = 0.0
        for o in self._items.values():
            reach = self._reach(o)
            speed = max(speed, float(np.linalg.norm(o.velocity))
                        + float(np.linalg.norm(o.omega)) * reach)
        if speed == 0.0:
            return 0
        return max(1, int(0.25 * thickness / (speed * dt)))

    @staticmethod
    def _reach(o) -> float:
        """An upper bound on the distance of the obstacle's surface points near the cloth
        from its origin (for the travel of a rotating obstacle)."""
        if o.shape == 'plane':
            return 10.0                       # a rotating ground: any reasonable cloth
        if o.shape == 'sphere':
            return o.params['radius']
        if o.shape == 'box':
            return float(np.linalg.norm(o.params['half_extents']))
        if o.shape in ('capsule', 'cylinder'):
            return o.params['radius'] + o.params['half_length']
        verts = o.mesh[0]
        return float(np.linalg.norm(verts, axis=1).max())

    def poses(self):
        """The obstacles' poses, for :meth:`restore`."""
        return {oid: (o.position.copy(), o.orientation.copy())
                for oid, o in self._items.items()}

    def restore(self, poses) -> None:
        for oid, (p, q) in poses.items():
            if oid in self._items:
                self._items[oid].position, self._items[oid].orientation = p, q
        self._rebuild(fields=False)

    def advance(self, t: float) -> None:
        """Move every obstacle by its velocities over ``t`` seconds."""
        if not self.moving():
            return
        for o in self._items.values():
            o.position = o.position + o.velocity * t
            w = float(np.linalg.norm(o.omega))
            if w > 0:
                axis = o.omega / w
                half = 0.5 * w * t
                dq = np.array([*(axis * math.sin(half)), math.cos(half)])
                o.orientation = _qmul(dq, o.orientation)
                o.orientation /= np.linalg.norm(o.orientation)
        self._rebuild(fields=False)

    # ------------------------------------------------------------------ forces
    def forces(self, x: np.ndarray, contact: np.ndarray,
               extra: Optional[np.ndarray] = None) -> Dict[int, tuple]:
        """{id: (force (3), torque (3) about the obstacle's position)} that the cloth
        exerts on each obstacle over the last step: minus the contact forces on the
        vertices whose contact was with it, plus ``extra[row]`` (force, torque) where
        given (a box's corners and edges, :mod:`.features`)."""
        out = {}
        rows = contact[:, C.C_ID].astype(np.int64)
        rows2 = contact[:, C.C_ID2].astype(np.int64)
        second = contact[:, C.C_FORCE2:C.C_FORCE2 + 3]
        first = contact[:, C.C_FORCE:C.C_FORCE + 3] - second
        for r, oid in enumerate(self.ids):
            sel, sel2 = rows == r, rows2 == r
            # a vertex that touched two obstacles in its step: each takes its own part
            f = -np.concatenate([first[sel], second[sel2]])
            arm = np.concatenate([x[sel], x[sel2]]) - self._items[oid].position
            force, torque = f.sum(0), np.cross(arm, f).sum(0)
            if extra is not None and r < len(extra):
                force = force + extra[r, :3]
                torque = torque + extra[r, 3:]
            out[oid] = (force, torque)
        return out


def _qmul(a, b):
    ax, ay, az, aw = a
    bx, by, bz, bw = b
    return np.array([aw * bx + ax * bw + ay * bz - az * by,
                     aw * by - ax * bz + ay * bw + az * bx,
                     aw * bz + ax * by - ay * bx + az * bw,
                     aw * bw - ax * bx - ay * by - az * bz])
