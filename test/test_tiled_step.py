"""The tiled step (integrator.run_tiled): each thread runs the vertex pass over its part of
the mesh tile by tile and gathers and updates the vertices a tile completes right away.
It must give the very same trajectory as the two-pass step, and its work plan must never
update a vertex before everything that reads or feeds it is done."""
import numba as nb
import numpy as np
import pytest
import trimesh

from cosserat_ros import integrator, workshare
from cosserat_ros.constants import FUSE_MIN_VERTICES
from cosserat_ros.forces import chunk_of_vertex
from cosserat_ros.mesh import ClothMesh, grid_mesh
from cosserat_ros.simulator import ClothSimulator, Material, steps_tiled


def _mesh(name):
    if name == 'icosphere':
        m = trimesh.creation.icosphere(subdivisions=3, radius=0.5)
        return ClothMesh(m.vertices, m.faces)
    return grid_mesh(41, 37, pattern=name, seed=3)


def _sim(mesh, tile_vertices, parts, tiled):
    sim = ClothSimulator(mesh, Material(zeta=20.0, xi=1e-3, phi=0.0, density=0.2,
                                        damping=3.0), dt=1e-4, check_dt=False)
    nch = len(sim._ops[28]) - 1
    sim._ops = sim._ops[:27] + sim._schedule(nch, tile_vertices, parts, tiled)
    sim._tiled = tiled
    return sim


def _contributors(sim):
    """(vertex, chunk) pairs: every chunk whose work reads x_j or feeds the force on j."""
    tile_ch, fc_ptr, fc_face, gl_ptr, gl_vert, part_tile = sim._ops[27:33]
    nch = tile_ch[-1]
    chunk = chunk_of_vertex(sim.mesh.n_vertices, nch, sim._ops[19], sim._ops[22])
    face_chunk = np.repeat(np.arange(nch), np.diff(fc_ptr))[np.argsort(fc_face)]
    st_ptr, st_idx = sim._jet.st_ptr, sim._jet.st_idx
    pairs = [(st_idx, np.repeat(chunk, np.diff(st_ptr))),
             (sim.mesh.faces.ravel(), np.repeat(face_chunk, 3))]
    return np.concatenate([p[0] for p in pairs]), np.concatenate([p[1] for p in pairs])


@pytest.mark.parametrize('name', ['irregular', 'icosphere'])
@pytest.mark.parametrize('parts', [2, 3])
def test_tiled_step_gives_the_same_trajectory_to_the_bit(name, parts):
    mesh = _mesh(name)
    rng = np.random.default_rng(7)
    x0 = mesh.vertices + 0.01 * rng.standard_normal(mesh.vertices.shape)
    v0 = 0.05 * rng.standard_normal(mesh.vertices.shape)
    runs = []
    for tile, tiled in ((10 ** 9, False), (64, True), (16, True)):
        sim = _sim(mesh, tile, parts, tiled)
        assert (len(sim._ops[27]) - 1 > 2 * parts) == tiled     # several tiles per part
        sim.gravity = (0.0, 0.0, -9.81)
        sim.pin(np.arange(0, mesh.n_vertices, 97))
        sim.set_vertex_forces([5, 40], [[0.0, 0.0, 1e-3], [1e-3, 0.0, 0.0]])
        sim.set_positions(x0)
        sim.set_velocities(v0)
        sim.step(40)
        runs.append((sim.positions.copy(), sim.velocities.copy(), sim._acc.copy()))
    for x, v, acc in runs[1:]:
        assert np.array_equal(x, runs[0][0]) and np.array_equal(v, runs[0][1])
        # the work and dissipation sums only add up in another order
        assert acc == pytest.approx(runs[0][2], rel=1e-12, abs=1e-300)


@pytest.mark.parametrize('name', ['irregular', 'icosphere'])
def test_tiled_plan_updates_each_vertex_once_after_everything_that_touches_it(name):
    sim = _sim(_mesh(name), 32, 3, True)
    tile_ch, fc_ptr, fc_face, gl_ptr, gl_vert, part_tile = sim._ops[27:33]
    n, ntile = sim.mesh.n_vertices, len(tile_ch) - 1
    assert np.array_equal(np.sort(gl_vert), np.arange(n))
    assert np.array_equal(np.sort(fc_face), np.arange(sim.mesh.n_faces))
    assert len(gl_ptr) == ntile + 2 and gl_ptr[-1] == n
    part_ch = tile_ch[part_tile]
    assert np.all(np.diff(part_ch) >= 0) and part_ch[0] == 0 and part_ch[-1] == tile_ch[-1]
    vertex, chunk = _contributors(sim)
    tile_of = np.full(n, -1)
    for t in range(ntile + 1):
        tile_of[gl_vert[gl_ptr[t]:gl_ptr[t + 1]]] = t
    inner = tile_of[vertex] < ntile
    t = tile_of[vertex[inner]]
    part_of_tile = np.searchsorted(part_tile, np.arange(ntile), 'right') - 1
    p = part_of_tile[t]
    # every contributor of a vertex updated inside a part is that part's and comes no
    # later than the end of the tile that updates it
    assert np.all(chunk[inner] >= part_ch[p]) and np.all(chunk[inner] < part_ch[p + 1])
    assert np.all(chunk[inner] < tile_ch[t + 1])
    # the seam: a minority when the vertex numbering is local (a generated sheet); nearly
    # all of trimesh's icosphere, whose subdivision numbers new vertices apart from their
    # neighbours (correct, just no cache gain)
    seam = gl_ptr[-1] - gl_ptr[-2]
    assert seam < (0.5 * n if name == 'irregular' else n)


@pytest.mark.parametrize('name', ['regular', 'irregular'])
@pytest.mark.parametrize('tile', [16, 64])
def test_ring_slots_hold_every_gradient_until_its_last_reader(name, tile):
    # replay the tiled step's writes and reads, tile by tile: every slot a gather reads
    # must still hold the group that wrote that entry, and the rings must really recycle
    sim = _sim(grid_mesh(41, 37, pattern=name, seed=3), tile, 2, True)
    g_ptr, tile_ch, gl_ptr, gl_vert = sim._ops[20], sim._ops[27], sim._ops[30], sim._ops[31]
    base, slot_of, pos_of = sim._ops[33][:, 2], sim._ops[34].astype(np.int64), sim._ops[14]
    tr_ptr, nch, ng = sim._jet.tr_ptr, tile_ch[-1], len(g_ptr) - 1
    size = np.diff(g_ptr)
    g_tile = np.searchsorted(tile_ch, np.arange(ng) // -(-ng // nch), 'right') - 1
    owner = np.full(len(sim._jet.st_idx), -1)
    group_of = np.searchsorted(g_ptr, pos_of, 'right') - 1   # -1: a single vertex's entry
    assert np.all(owner[:g_ptr[0]] == -1) and np.all(base >= g_ptr[0])
    # the faces' corner gradients: rows fc_slot of fgrad, read as row 3 slot + corner
    fc_ptr, fc_face, fc_slot, vf_row = (sim._ops[28], sim._ops[29], sim._ops[35],
                                        sim._ops[36].astype(np.int64))
    assert np.array_equal(vf_row % 3, sim.mesh.vf_corner)
    f_tile = np.searchsorted(tile_ch, np.repeat(np.arange(nch), np.diff(fc_ptr)), 'right') - 1
    face_owner = np.full(sim.mesh.n_faces, -1)
    vf_ptr, vf_face = sim.mesh.vf_ptr, sim.mesh.vf_face
    for t in range(len(tile_ch)):                          # the last one: the seam
        for g in np.nonzero(g_tile == t)[0]:
            owner[base[g]:base[g] + size[g]] = g
        face_owner[fc_slot[f_tile == t]] = fc_face[f_tile == t]
        for j in gl_vert[gl_ptr[t]:gl_ptr[t + 1]]:
            e = np.arange(tr_ptr[j], tr_ptr[j + 1])
            g = group_of[e]
            assert np.array_equal(owner[slot_of[e][g >= 0]], g[g >= 0])
            assert np.array_equal(slot_of[e][g < 0], pos_of[e][g < 0])
            q = np.arange(vf_ptr[j], vf_ptr[j + 1])
            assert np.array_equal(face_owner[vf_row[q] // 3], vf_face[q])
    # slots are reused (without the rings: 1.0; an irregular sheet's lane groups mix
    # vertices farther apart, so more of them keep slots of their own)
    assert (base + size).max() < (0.7 if name == 'regular' else 0.9) * g_ptr[-1]
    assert fc_slot.max() < 0.7 * sim.mesh.n_faces


def test_large_meshes_step_tiled_and_coupled_ones_do_not(monkeypatch):
    calls = []
    for name in ('run_tiled', 'run_variational', 'run_fused'):
        real = getattr(integrator, name)
        monkeypatch.setattr('cosserat_ros.simulator.' + name,
                            lambda *a, _real=real, _name=name: calls.append(_name) or _real(*a))
    side = int(np.ceil(np.sqrt(FUSE_MIN_VERTICES)))
    # small meshes without coupling: all steps of a call in one parallel region where the
    # threading layer runs every iteration at once, each thread on a CPU of its own
    # (test_compiled has the other cases)
    small = ('run_fused' if workshare.start_threads() in ('omp', 'workqueue')
             and nb.get_num_threads() <= workshare.usable_cpus() else 'run_variational')
    for phi, side_n, expect in ((0.0, side, 'run_tiled'), (0.0, 20, small),
                                (1e-3, side, 'run_variational')):
        sim = ClothSimulator(grid_mesh(side_n, side_n), Material(zeta=20.0, xi=1e-3, phi=phi,
                                                                 density=0.2),
                             dt=1e-5, check_dt=False)
        sim.step(1)
        assert calls[-1] == expect
        assert steps_tiled(sim.mesh.n_vertices, phi) == (expect == 'run_tiled')


@pytest.mark.parametrize('name', ['regular', 'alternating', 'irregular', 'icosphere'])
def test_the_vertex_pass_reads_each_face_rest_shape_from_a_table_of_the_distinct_ones(name):
    # ops[37:41]: the faces' corners in chunk order (uint32) and a row per face in a table
    # of the distinct (Dinv, area) pairs, with the very bits of the face's own: the same
    # forces, from a few dozen rows on a structured sheet
    sim = _sim(_mesh(name), 32, 2, True)
    fc_face = sim._ops[29].astype(np.int64)
    fc_vert, fc_tpl, t_dinv, t_area = sim._ops[37:41]
    assert fc_vert.dtype == fc_tpl.dtype == np.uint32
    assert np.array_equal(fc_vert, sim.mesh.faces[fc_face])
    assert np.array_equal(t_dinv[fc_tpl].view(np.int64), sim._dinv[fc_face].view(np.int64))
    assert np.array_equal(t_area[fc_tpl].view(np.int64),
                          sim.mesh.face_areas[fc_face].view(np.int64))
    rows = np.concatenate([t_dinv.reshape(-1, 4), t_area[:, None]], axis=1).view(np.int64)
    assert len(np.unique(rows, axis=0)) == len(rows)
    # rows in order of first use: the stream reads the table front to back
    assert np.all(np.diff(np.maximum.accumulate(fc_tpl.astype(np.int64))) <= 1)
    if name in ('regular', 'alternating'):
        assert len(rows) <= 64


@pytest.mark.parametrize('name', ['irregular', 'icosphere'])
def test_a_tiled_simulator_computes_the_same_internal_force_as_an_untiled_one(name):
    # its force outside the step (critical dt, internal_forces) runs the two-pass vertex
    # pass, whose corner gradients must go to each face's own row, not to the tiled step's
    # ring slots
    mesh = _mesh(name)
    x = mesh.vertices + 0.01 * np.random.default_rng(5).standard_normal(mesh.vertices.shape)
    forces = []
    for tiled in (False, True):
        sim = _sim(mesh, 32, 2, tiled)
        sim.set_positions(x)
        forces.append(sim.internal_forces())
    assert np.abs(forces[0]).max() > 0
    assert np.array_equal(forces[0], forces[1])
