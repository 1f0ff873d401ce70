"""Mesh construction, adjacency and the refusal of meshes the model cannot use."""
import warnings

import numpy as np
import pytest
import trimesh

from cosserat_ros.mesh import ClothMesh, grid_mesh, load_mesh, MeshError

SQUARE_V = np.array([[0, 0, 0], [1, 0, 0], [1, 1, 0], [0, 1, 0]], dtype=float)
SQUARE_F = np.array([[0, 1, 2], [0, 2, 3]])


@pytest.mark.parametrize('pattern', ['regular', 'alternating', 'irregular'])
def test_grid_index_convention_and_area(pattern):
    nx, ny, w, h = 6, 4, 2.0, 1.0
    m = grid_mesh(nx, ny, width=w, height=h, pattern=pattern, seed=3)
    assert m.n_vertices == (nx + 1) * (ny + 1)
    assert m.n_faces == 2 * nx * ny
    assert m.total_area == pytest.approx(w * h, rel=1e-12)
    assert m.dual_areas.sum() == pytest.approx(w * h, rel=1e-12)
    # boundary vertices sit exactly on the grid (only interior ones are jittered)
    for i, j in [(0, 0), (nx, 0), (3, 0), (0, 2), (nx, ny)]:
        v = m.vertices[j * (nx + 1) + i]
        assert v == pytest.approx([-w / 2 + i * w / nx, -h / 2 + j * h / ny, 0.0])
    assert np.all(m.face_normals[:, 2] > 0), 'faces must be counter-clockwise from +z'
    assert m.boundary_vertices.sum() == 2 * (nx + ny)
    assert len(m.boundary_edges) == 2 * (nx + ny)


def test_grid_valences():
    inter = ~grid_mesh(8, 8).boundary_vertices
    assert set(np.diff(grid_mesh(8, 8).ring1_ptr)[inter]) == {6}
    m = grid_mesh(8, 8, pattern='alternating')
    assert set(np.diff(m.ring1_ptr)[~m.boundary_vertices]) == {4, 8}
    m = grid_mesh(16, 16, pattern='irregular', seed=5)
    assert len(set(np.diff(m.ring1_ptr)[~m.boundary_vertices])) >= 3
    # reproducible with the seed, different across seeds
    assert np.array_equal(m.vertices, grid_mesh(16, 16, pattern='irregular', seed=5).vertices)
    assert not np.array_equal(m.vertices,
                              grid_mesh(16, 16, pattern='irregular', seed=6).vertices)


def test_irregular_is_delaunay():
    m = grid_mesh(12, 12, pattern='irregular', seed=1)
    p = m.vertices[:, :2]
    for f in m.faces:
        a, b, c = p[f]
        # circumcentre o solves 2 (b - a) . o = |b|^2 - |a|^2, 2 (c - a) . o = |c|^2 - |a|^2
        o = np.linalg.solve(2 * np.array([b - a, c - a]), [b @ b - a @ a, c @ c - a @ a])
        r = np.linalg.norm(a - o)
        d = np.linalg.norm(p - o, axis=1)
        d[f] = np.inf
        assert d.min() > r * (1 - 1e-9), 'a vertex lies inside a circumcircle'


def test_rings_and_vertex_faces():
    m = grid_mesh(5, 5)
    i = 2 * 6 + 2  # interior vertex (2, 2)
    ring1 = set(m.ring1[m.ring1_ptr[i]:m.ring1_ptr[i + 1]].tolist())
    assert ring1 == {i - 1, i + 1, i - 6, i + 6, i - 7, i + 7}
    ring2 = set(m.ring2[m.ring2_ptr[i]:m.ring2_ptr[i + 1]].tolist())
    assert ring1 < ring2 and i not in ring2 and len(ring2) == 18
    assert set(m.ring(i, 2).tolist()) == ring2
    for k in range(m.vf_ptr[i], m.vf_ptr[i + 1]):
        assert m.faces[m.vf_face[k], m.vf_corner[k]] == i
    assert m.vf_ptr[-1] == 3 * m.n_faces


@pytest.mark.parametrize('verts, faces, match', [
    (SQUARE_V[:, :2], SQUARE_F, r'shape \(n, 3\)'),
    (SQUARE_V, SQUARE_F[:, :2], r'shape \(m, 3\)'),
    (SQUARE_V, np.zeros((0, 3), dtype=int), 'at least one triangle'),
    (np.where(np.arange(12).reshape(4, 3) == 4, np.nan, SQUARE_V), SQUARE_F, 'non-finite'),
    (SQUARE_V, [[0, 1, 2], [0, 2, 4]], 'indices must lie'),
    (SQUARE_V, [[0, 1, 2], [0, -1, 3]], 'indices must lie'),
    (SQUARE_V, [[0, 1, 1], [0, 2, 3]], 'repeat a vertex'),
    (SQUARE_V, [[0, 1, 2], [0, 2, 3], [2, 0, 1]], 'duplicate faces'),
    (SQUARE_V, [[0, 1, 2]], 'not referenced'),
    (SQUARE_V, [[0, 1, 2], [0, 3, 2]], 'consistently oriented'),
    (np.array([[0, 0, 0], [1, 0, 0], [2, 0, 0], [0, 1, 0.]]), [[0, 1, 2], [0, 1, 3]],
     'zero area'),
    (np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0], [0, -1, 0], [0, 0, 1.]]),
     [[0, 1, 2], [1, 0, 3], [0, 1, 4]], 'non-manifold'),
    (SQUARE_V, [[0, 1.5, 2], [0, 2, 3]], 'integer vertex indices'),
])
def test_bad_meshes_are_refused(verts, faces, match):
    with pytest.raises(MeshError, match=match):
        ClothMesh(verts, faces)


@pytest.mark.parametrize('kwargs, match', [
    (dict(nx=0, ny=3), 'nx must be a positive integer'),
    (dict(nx=3, ny=2.5), 'ny must be a positive integer'),
    (dict(nx=3, ny=3, width=-1.0), 'width must be a positive'),
    (dict(nx=3, ny=3, height=float('nan')), 'height must be a positive'),
    (dict(nx=3, ny=3, pattern='hexagonal'), 'pattern must be one of'),
])
def test_bad_grid_arguments(kwargs, match):
    with pytest.raises(ValueError, match=match):
        grid_mesh(**kwargs)


def test_load_mesh_formats_and_topologies(tmp_path):
    sphere = trimesh.creation.icosphere(subdivisions=2, radius=0.3)
    for ext in ('obj', 'ply', 'stl', 'off', 'glb'):
        path = tmp_path / f'sphere.{ext}'
        sphere.export(path)
        m = load_mesh(path)
        assert m.n_vertices == len(sphere.vertices), ext   # STL vertices merged again
        assert m.is_closed
        assert m.total_area == pytest.approx(sphere.area, rel=1e-6)
    annulus = trimesh.creation.annulus(r_min=0.2, r_max=0.5, height=0.1, sections=24)
    annulus.export(tmp_path / 'annulus.obj')   # a closed surface of genus 1 (a hole)
    m = load_mesh(tmp_path / 'annulus.obj')
    assert m.is_closed and m.n_vertices - len(m.edges) + m.n_faces == 0  # Euler: torus
    sheet = grid_mesh(6, 3)
    trimesh.Trimesh(sheet.vertices, sheet.faces, process=False).export(tmp_path / 's.ply')
    assert load_mesh(tmp_path / 's.ply').n_vertices == sheet.n_vertices


def test_load_mesh_refusals(tmp_path):
    with pytest.raises(MeshError, match='not found'):
        load_mesh(tmp_path / 'missing.obj')
    bad = tmp_path / 'garbage.stl'
    bad.write_bytes(b'\x00\x01garbage' * 3)
    with pytest.raises(MeshError):
        load_mesh(bad)
    nm = tmp_path / 'nonmanifold.obj'
    nm.write_text('v 0 0 0\nv 1 0 0\nv 0 1 0\nv 0 -1 0\nv 0 0 1\n'
                  'f 1 2 3\nf 2 1 4\nf 1 2 5\n')
    with pytest.raises(MeshError, match='non-manifold'):
        load_mesh(nm)
    nan = tmp_path / 'nan.obj'
    nan.write_text('v 0 0 0\nv 1 0 nan\nv 0 1 0\nf 1 2 3\n')
    with pytest.raises(MeshError, match='non-finite'):
        load_mesh(nan)
    extra = tmp_path / 'extra.ply'   # PLY keeps vertices no face uses (OBJ readers drop them)
    trimesh.Trimesh([[0, 0, 0], [1, 0, 0], [0, 1, 0], [5, 5, 5]], [[0, 1, 2]],
                    process=False).export(extra)
    with pytest.warns(UserWarning, match='dropped 1 unreferenced'):
        m = load_mesh(extra)
    assert m.n_vertices == 3
    dup = tmp_path / 'dup.obj'
    dup.write_text('v 0 0 0\nv 1 0 0\nv 0 1 0\nf 1 2 3\nf 2 3 1\n')
    with warnings.catch_warnings():
        warnings.simplefilter('ignore')
        with pytest.raises(MeshError, match='duplicate'):
            load_mesh(dup)
