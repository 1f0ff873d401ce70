"""Triangle meshes for the cloth: validation, adjacency in CSR form, factories and loading.

A :class:`ClothMesh` is the rest shape of the Cosserat surface. It never changes after
construction; everything the kernels need from the topology is precomputed here as flat
arrays (struct of arrays), with adjacency in compressed-sparse-row form:

==================  =====================  ===============================================
attribute           shape / dtype          meaning
==================  =====================  ===============================================
vertices            (n, 3) float64         rest positions R [m]
faces               (m, 3) int64           counter-clockwise vertex indices
ring1_ptr, ring1    (n+1,), (k1,) int64    1-ring neighbours of vertex i:
                                           ``ring1[ring1_ptr[i]:ring1_ptr[i+1]]``
ring2_ptr, ring2    (n+1,), (k2,) int64    vertices at graph distance 1 or 2 (i excluded)
vf_ptr, vf_face,    (n+1,), (3m,) int64    faces incident to vertex i and the corner
vf_corner                                  (0, 1, 2) that i occupies in each
edges               (e, 2) int64           undirected edges, ``edges[:, 0] < edges[:, 1]``
boundary_edges      (b, 2) int64           edges with one incident face, oriented as in it
boundary_vertices   (n,) bool              vertex lies on a boundary edge
face_areas          (m,) float64           rest triangle areas [m^2]
dual_areas          (n,) float64           barycentric dual areas, sum of area/3 [m^2]
==================  =====================  ===============================================
"""
from __future__ import annotations

import logging
from pathlib import Path
from typing import Union
import warnings

import numpy as np

from .constants import DEGENERATE_AREA_RTOL

__all__ = ['ClothMesh', 'MeshError', 'grid_mesh', 'load_mesh', 'csr_from_pairs', 'k_ring']

_log = logging.getLogger(__name__)

GRID_PATTERNS = ('regular', 'alternating', 'irregular')


class MeshError(ValueError):
    """A mesh the Cosserat model cannot use; the message names the problem."""


def csr_from_pairs(rows: np.ndarray, cols: np.ndarray, n: int):
    """CSR (ptr, idx) of the relation ``rows -> cols``; within a row, columns ascend."""
    order = np.lexsort((cols, rows))
    rows = rows[order]
    cols = cols[order]
    ptr = np.zeros(n + 1, dtype=np.int64)
    np.add.at(ptr, rows + 1, 1)
    np.cumsum(ptr, out=ptr)
    return ptr, cols.astype(np.int64), order


def k_ring(ptr: np.ndarray, idx: np.ndarray, vertex: int, k: int) -> np.ndarray:
    """Vertices within graph distance ``k`` of ``vertex`` (itself excluded), sorted."""
    seen = {vertex}
    frontier = [vertex]
    for _ in range(k):
        nxt = []
        for v in frontier:
            for w in idx[ptr[v]:ptr[v + 1]]:
                w = int(w)
                if w not in seen:
                    seen.add(w)
                    nxt.append(w)
        frontier = nxt
    seen.discard(vertex)
    return np.array(sorted(seen), dtype=np.int64)


class ClothMesh:
    """A validated, consistently oriented triangle mesh with precomputed adjacency.

    Parameters
    ----------
    vertices : (n, 3) array_like of float
        Rest positions [m]; must be finite.
    faces : (m, 3) array_like of int
        Vertex indices of each triangle, consistently oriented (every interior edge is
        traversed once in each direction).

    Raises
    ------
    MeshError
        (a ``ValueError``) naming the first problem found: wrong shape or dtype,
        non-finite coordinates, no triangle, index out of range, degenerate or duplicate
        faces, non-manifold edges, inconsistent orientation, unreferenced vertices.
    """

    def __init__(self, vertices, faces):
        v = np.asarray(vertices)
        f = np.asarray(faces)
        if v.ndim != 2 or v.shape[1] != 3:
            raise MeshError(f'vertices must have shape (n, 3), got {v.shape}')
        if f.ndim != 2 or f.shape[1] != 3:
            raise MeshError(f'faces must have shape (m, 3), got {f.shape}')
        if not np.issubdtype(v.dtype, np.number) or np.iscomplexobj(v):
            raise MeshError(f'vertices must be real numbers, got dtype {v.dtype}')
        if f.size and not np.issubdtype(f.dtype, np.integer):
            if np.issubdtype(f.dtype, np.floating) and np.all(np.isfinite(f)) \
                    and np.all(f == np.round(f)):
                f = f.astype(np.int64)
            else:
                raise MeshError(f'faces must hold integer vertex indices, got dtype {f.dtype}')
        v = np.ascontiguousarray(v, dtype=np.float64)
        f = np.ascontiguousarray(f, dtype=np.int64)
        if len(f) < 1:
            raise MeshError('a mesh needs at least one triangle, got 0 faces')
        if not np.all(np.isfinite(v)):
            bad = np.flatnonzero(~np.all(np.isfinite(v), axis=1))
            raise MeshError(f'{len(bad)} vertices have non-finite coordinates '
                            f'(first: vertex {bad[0]})')
        n = len(v)
        if f.min() < 0 or f.max() >= n:
            raise MeshError(f'face indices must lie in [0, {n - 1}], '
                            f'got range [{f.min()}, {f.max()}]')
        rep = (f[:, 0] == f[:, 1]) | (f[:, 1] == f[:, 2]) | (f[:, 0] == f[:, 2])
        if rep.any():
            raise MeshError(f'{rep.sum()} degenerate faces repeat a vertex '
                            f'(first: face {np.flatnonzero(rep)[0]} = {f[rep][0].tolist()})')
        used = np.zeros(n, dtype=bool)
        used[f.ravel()] = True
        if not used.all():
            raise MeshError(f'{(~used).sum()} vertices are not referenced by any face '
                            f'(first: vertex {np.flatnonzero(~used)[0]}); '
                            'load_mesh drops them, ClothMesh refuses them')
        key = np.sort(f, axis=1)
        _, first, counts = np.unique(key, axis=0, return_index=True, return_counts=True)
        if (counts > 1).any():
            dup = key[first[counts > 1][0]]
            raise MeshError(f'{(counts > 1).sum()} duplicate faces '
                            f'(first: vertices {dup.tolist()})')
        p0, p1, p2 = v[f[:, 0]], v[f[:, 1]], v[f[:, 2]]
        cross = np.cross(p1 - p0, p2 - p0)
        areas = 0.5 * np.linalg.norm(cross, axis=1)
        elen = np.concatenate([np.linalg.norm(p1 - p0, axis=1), np.linalg.norm(p2 - p1, axis=1),
                               np.linalg.norm(p0 - p2, axis=1)])
        h = float(elen.mean())
        if h <= 0.0:
            raise MeshError('all vertices coincide: the mesh has zero size')
        degenerate = areas <= DEGENERATE_AREA_RTOL * h * h
        if degenerate.any():
            raise MeshError(f'{degenerate.sum()} degenerate faces have (near) zero area '
                            f'(first: face {np.flatnonzero(degenerate)[0]})')

        # Directed half-edges a->b of every face; undirected key a<b.
        he_a = f.ravel()
        he_b = f[:, [1, 2, 0]].ravel()
        lo = np.minimum(he_a, he_b)
        hi = np.maximum(he_a, he_b)
        ukey = lo * n + hi
        uniq, inverse, ucount = np.unique(ukey, return_inverse=True, return_counts=True)
        if (ucount > 2).any():
            k = uniq[ucount > 2][0]
            raise MeshError(f'{(ucount > 2).sum()} non-manifold edges are shared by more '
                            f'than two faces (first: edge {k // n}-{k % n}, '
                            f'{ucount[ucount > 2][0]} faces)')
        dkey = he_a * n + he_b
        _, dcount = np.unique(dkey, return_counts=True)
        if (dcount > 1).any():
            raise MeshError('faces are not consistently oriented: some edge is traversed '
                            'twice in the same direction (flip the winding of one side)')

        self.vertices = v
        self.faces = f
        self.face_areas = areas
        self.mean_edge_length = h
        self.edges = np.stack([uniq // n, uniq % n], axis=1).astype(np.int64)
        on_boundary = ucount[inverse] == 1
        self.boundary_edges = np.stack([he_a[on_boundary], he_b[on_boundary]], axis=1)
        bmask = np.zeros(n, dtype=bool)
        bmask[self.boundary_edges.ravel()] = True
        self.boundary_vertices = bmask

        dual = np.zeros(n)
        np.add.at(dual, f.ravel(), np.repeat(areas / 3.0, 3))
        self.dual_areas = dual

        e = self.edges
        rows = np.concatenate([e[:, 0], e[:, 1]])
        cols = np.concatenate([e[:, 1], e[:, 0]])
        self.ring1_ptr, self.ring1, _ = csr_from_pairs(rows, cols, n)
        self.ring2_ptr, self.ring2 = self._two_ring()

        corner = np.tile(np.arange(3, dtype=np.int64), len(f))
        face_id = np.repeat(np.arange(len(f), dtype=np.int64), 3)
        self.vf_ptr, self.vf_face, order = csr_from_pairs(f.ravel(), face_id, n)
        self.vf_corner = corner[order]

        fn = cross / (2.0 * areas[:, None])
        self.face_normals = fn
        vn = np.zeros((n, 3))
        np.add.at(vn, f.ravel(), np.repeat(cross, 3, axis=0))
        self.vertex_normals = vn / np.linalg.norm(vn, axis=1)[:, None].clip(1e-300)

    @property
    def n_vertices(self) -> int:
        """Number of vertices n."""
        return len(self.vertices)

    @property
    def n_faces(self) -> int:
        """Number of triangles m."""
        return len(self.faces)

    @property
    def is_closed(self) -> bool:
        """True when the surface has no boundary edge (a sphere, a torus...)."""
        return len(self.boundary_edges) == 0

    @property
    def total_area(self) -> float:
        """Rest area of the whole surface [m^2]."""
        return float(self.face_areas.sum())

    def ring(self, vertex: int, k: int) -> np.ndarray:
        """Vertices within graph distance ``k`` of ``vertex``, itself excluded."""
        return k_ring(self.ring1_ptr, self.ring1, vertex, k)

    def _two_ring(self):
        n = self.n_vertices
        ptr, idx = self.ring1_ptr, self.ring1
        deg = np.diff(ptr)
        # pairs (i, j) for j in N(i), then (i, k) for k in N(j): vectorised
        i1 = np.repeat(np.arange(n), deg)
        j1 = idx
        cnt = deg[j1]
        i2 = np.repeat(i1, cnt)
        starts = np.repeat(ptr[j1], cnt)
        offs = np.arange(len(i2)) - np.repeat(np.cumsum(cnt) - cnt, cnt)
        k2 = idx[starts + offs]
        rows = np.concatenate([i1, i2])
        cols = np.concatenate([j1, k2])
        keep = rows != cols
        key = np.sort(rows[keep] * n + cols[keep])
        key = key[np.concatenate([[True], key[1:] != key[:-1]])]
        ptr2, idx2, _ = csr_from_pairs(key // n, key % n, n)
        return ptr2, idx2

    def __repr__(self) -> str:
        kind = 'closed' if self.is_closed else f'{len(self.boundary_edges)} boundary edges'
        return f'ClothMesh({self.n_vertices} vertices, {self.n_faces} faces, {kind})'


# --------------------------------------------------------------------------- factories

def grid_mesh(nx: int, ny: int, width: float = 1.0, height: float = 1.0,
              pattern: str = 'regular', seed: int = 0) -> ClothMesh:
    """A flat ``width`` x ``height`` sheet in the z = 0 plane, centred on the origin.

    Vertex (i, j), ``i = 0..nx`` along X and ``j = 0..ny`` along Y, has index
    ``j*(nx+1) + i`` for every pattern; faces are counter-clockwise seen from +z.

    Patterns
    --------
    ``"regular"``
        every quad split along its (i, j)-(i+1, j+1) diagonal (interior valence 6).
    ``"alternating"``
        criss-cross splits, the diagonal alternating with (i + j) parity, so interior
        valences are 4 and 8 as in the seed's experiments.
    ``"irregular"``
        interior vertices moved by up to 30% of the spacing (uniform in a disc, ``seed``
        makes it reproducible), each quad split along its Delaunay diagonal, then Lawson
        edge flips to the Delaunay triangulation: mixed valences. Boundary vertices stay on
        the straight edges.
    """
    for name, val in (('nx', nx), ('ny', ny)):
        if int(val) != val or val < 1:
            raise ValueError(f'{name} must be a positive integer, got {val!r}')
    nx, ny = int(nx), int(ny)
    for name, val in (('width', width), ('height', height)):
        if not np.isfinite(val) or val <= 0:
            raise ValueError(f'{name} must be a positive finite length [m], got {val!r}')
    if pattern not in GRID_PATTERNS:
        raise ValueError(f'pattern must be one of {GRID_PATTERNS}, got {pattern!r}')
    dx, dy = width / nx, height / ny
    jj, ii = np.meshgrid(np.arange(ny + 1), np.arange(nx + 1), indexing='ij')
    x = -0.5 * width + ii.ravel() * dx
    y = -0.5 * height + jj.ravel() * dy
    pts = np.stack([x, y, np.zeros_like(x)], axis=1)

    qi, qj = np.meshgrid(np.arange(nx), np.arange(ny), indexing='xy')
    qi, qj = qi.ravel(), qj.ravel()
    v00 = qj * (nx + 1) + qi
    v10 = v00 + 1
    v01 = v00 + nx + 1
    v11 = v01 + 1
    if pattern == 'regular':
        main = np.ones(len(v00), dtype=bool)
    elif pattern == 'alternating':
        main = (qi + qj) % 2 == 0
    else:
        rng = np.random.default_rng(seed)
        interior = (ii.ravel() > 0) & (ii.ravel() < nx) & (jj.ravel() > 0) & (jj.ravel() < ny)
        k = int(interior.sum())
        r = 0.3 * min(dx, dy) * np.sqrt(rng.random(k))
        t = 2.0 * np.pi * rng.random(k)
        pts[interior, 0] += r * np.cos(t)
        pts[interior, 1] += r * np.sin(t)
        # Delaunay split of each (convex) quad: keep diagonal 00-11 unless v01 lies inside
        # the circumcircle of (v00, v10, v11).
        main = ~_in_circle(pts[v00], pts[v10], pts[v11], pts[v01])
    faces = np.concatenate([
        np.stack([v00[main], v10[main], v11[main]], axis=1),
        np.stack([v00[main], v11[main], v01[main]], axis=1),
        np.stack([v00[~main], v10[~main], v01[~main]], axis=1),
        np.stack([v10[~main], v11[~main], v01[~main]], axis=1),
    ])
    if pattern == 'irregular':
        faces = _lawson_flip(pts[:, :2], faces)
    faces = faces[np.lexsort((faces[:, 0], faces.min(axis=1)))]
    return ClothMesh(pts, faces)


def disc_mesh(radius: float = 0.15, rings: int = 20) -> ClothMesh:
    """A flat disc of ``radius`` [m] in the z = 0 plane, centred on the origin: the centre
    and ``rings`` concentric rings of 6 k vertices (k = 1..rings) at radius ``k radius /
    rings``, consecutive rings zipped into triangles by angle (interior valence 6 on the
    ring's six spokes, 5-7 in between); counter-clockwise seen from +z. The specimen of
    the Cusick drape test (``core/scenarios.py``)."""
    if int(rings) != rings or rings < 1:
        raise ValueError(f'rings must be a positive integer, got {rings!r}')
    if not np.isfinite(radius) or radius <= 0:
        raise ValueError(f'radius must be a positive finite length [m], got {radius!r}')
    rings = int(rings)
    pts = [np.zeros(3)]
    start = [0]
    for k in range(1, rings + 1):
        a = 2.0 * np.pi * np.arange(6 * k) / (6 * k)
        r = radius * k / rings
        start.append(len(pts))
        pts += list(np.stack([r * np.cos(a), r * np.sin(a), np.zeros_like(a)], axis=1))
    faces = [[0, 1 + j, 1 + (j + 1) % 6] for j in range(6)]
    for k in range(1, rings):
        na, nb = 6 * k, 6 * (k + 1)
        a0, b0 = start[k], start[k + 1]
        i = j = 0
        while i < na or j < nb:
            # advance on the ring whose next vertex comes first by angle
            if j >= nb or (i < na and (i + 1) / na < (j + 1) / nb):
                faces.append([a0 + i % na, b0 + j % nb, a0 + (i + 1) % na])
                i += 1
            else:
                faces.append([a0 + i % na, b0 + j % nb, b0 + (j + 1) % nb])
                j += 1
    pts = np.array(pts)
    faces = np.array(faces, dtype=np.int64)
    e1 = pts[faces[:, 1]] - pts[faces[:, 0]]
    e2 = pts[faces[:, 2]] - pts[faces[:, 0]]
    flip = (e1[:, 0] * e2[:, 1] - e1[:, 1] * e2[:, 0]) < 0
    faces[flip] = faces[flip][:, [0, 2, 1]]
    return ClothMesh(pts, faces)


def _in_circle(a, b, c, d):
    """True where d lies strictly inside the circumcircle of the CCW triangle (a, b, c)."""
    ad, bd, cd = a[:, :2] - d[:, :2], b[:, :2] - d[:, :2], c[:, :2] - d[:, :2]
    det = ((ad[:, 0] ** 2 + ad[:, 1] ** 2) * (bd[:, 0] * cd[:, 1] - cd[:, 0] * bd[:, 1])
           - (bd[:, 0] ** 2 + bd[:, 1] ** 2) * (ad[:, 0] * cd[:, 1] - cd[:, 0] * ad[:, 1])
           + (cd[:, 0] ** 2 + cd[:, 1] ** 2) * (ad[:, 0] * bd[:, 1] - bd[:, 0] * ad[:, 1]))
    scale = np.abs(ad).max() ** 4 + 1e-300
    return det > 1e-12 * scale


def _lawson_flip(p: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """Flip interior edges of a valid planar triangulation until it is Delaunay."""
    faces = [list(map(int, t)) for t in faces]
    edge_faces: dict = {}
    for fi, t in enumerate(faces):
        for c in range(3):
            a, b = t[c], t[(c + 1) % 3]
            edge_faces.setdefault((min(a, b), max(a, b)), []).append(fi)
    stack = [e for e, fs in edge_faces.items() if len(fs) == 2]
    guard = 0
    while stack:
        guard += 1
        if guard > 50 * len(faces) + 1000:
            raise RuntimeError('Delaunay edge flipping did not converge')
        e = stack.pop()
        fs = edge_faces.get(e)
        if fs is None or len(fs) != 2:
            continue
        f0, f1 = fs
        t0, t1 = faces[f0], faces[f1]
        c = [v for v in t0 if v not in e][0]
        d = [v for v in t1 if v not in e][0]
        # orient so that (a, b, c) is t0 in CCW order
        k = t0.index(c)
        a, b = t0[(k + 1) % 3], t0[(k + 2) % 3]
        if not _in_circle(p[[a]], p[[b]], p[[c]], p[[d]])[0]:
            continue
        # flip edge a-b to c-d: new CCW triangles (c, a, d) and (c, d, b)
        faces[f0] = [c, a, d]
        faces[f1] = [c, d, b]
        del edge_faces[e]
        edge_faces[(min(c, d), max(c, d))] = [f0, f1]
        for (u, w), old, new in (((a, d), f1, f0), ((d, b), f1, f1),
                                 ((b, c), f0, f1), ((c, a), f0, f0)):
            key = (min(u, w), max(u, w))
            lst = edge_faces[key]
            lst[lst.index(old)] = new
            if len(lst) == 2:
                stack.append(key)
    return np.array(faces, dtype=np.int64)


def load_mesh(path: Union[str, Path]) -> ClothMesh:
    """Load a rest shape from any format trimesh reads (OBJ, PLY, STL, OFF, GLB, ...).

    Coincident vertices are merged (STL stores none shared), scenes are flattened into one
    mesh, and unreferenced vertices are dropped with a warning. Everything else the model
    cannot handle is refused with a :class:`MeshError` naming the problem: non-manifold
    edges, degenerate or duplicate faces, inconsistent winding, non-finite coordinates,
    no triangle.
    """
    import trimesh  # deferred: only file loading needs it

    path = Path(path)
    if not path.is_file():
        raise MeshError(f'mesh file not found: {path}')
    try:
        loaded = trimesh.load(str(path), force='mesh', process=False)
    except Exception as exc:  # trimesh raises many types for unreadable files
        raise MeshError(f'cannot read mesh file {path}: {exc}') from exc
    if not isinstance(loaded, trimesh.Trimesh) or len(loaded.faces) == 0:
        raise MeshError(f'{path} holds no triangles')
    verts = np.asarray(loaded.vertices, dtype=np.float64)
    faces = np.asarray(loaded.faces, dtype=np.int64)
    if not np.all(np.isfinite(verts)):
        raise MeshError(f'{path}: {int((~np.isfinite(verts).all(axis=1)).sum())} vertices '
                        'have non-finite coordinates')
    # merge exactly coincident vertices (no tolerance beyond round-off of the file format)
    scale = float(np.ptp(verts, axis=0).max()) or 1.0
    q = np.round(verts / (scale * 1e-9)).astype(np.int64)
    _, first, inv = np.unique(q, axis=0, return_index=True, return_inverse=True)
    inv = inv.ravel()
    if len(first) < len(verts):
        verts = verts[first]
        faces = inv[faces]
    used = np.zeros(len(verts), dtype=bool)
    used[faces.ravel()] = True
    if not used.all():
        msg = f'{path}: dropped {(~used).sum()} unreferenced vertices'
        warnings.warn(msg, stacklevel=2)
        _log.warning(msg)
        remap = np.cumsum(used) - 1
        verts = verts[used]
        faces = remap[faces]
    try:
        return ClothMesh(verts, faces)
    except MeshError as exc:
        raise MeshError(f'{path}: {exc}') from None
