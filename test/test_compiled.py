"""The numba set-up: one option set, stale caches of cross-file kernels are dropped, the
explicit SIMD vectors of the vertex pass compute what the one-vertex-at-a-time code does, and
the threads' sharing of work changes who computes what, not what is computed."""
import os
import pathlib
import re
import subprocess
import sys
import time

import numba as nb
import numpy as np
import pytest
import trimesh

import cosserat_ros
from cosserat_ros import compiled, workshare
from cosserat_ros.forces import lane_layout
from cosserat_ros.integrator import run_fused, run_variational, variational_forces
from cosserat_ros.mesh import ClothMesh, grid_mesh
from cosserat_ros.simd import lane, splat, vfma, vload, vload3, vset, vsqrt, vstore
from cosserat_ros.simulator import ClothSimulator, Material, SimulationDiverged
from cosserat_ros.workshare import split, take


def test_every_kernel_module_is_hashed():
    pkg = pathlib.Path(cosserat_ros.__file__).parent
    with_kernels = {p.name for p in pkg.glob('*.py')
                    if re.search(r'@(nb\.njit|kernel)\(|@intrinsic\b', p.read_text())}
    # compiled.py holds the options every kernel is compiled with
    assert with_kernels | {'compiled.py'} == set(compiled.KERNEL_MODULES)


_STARTS = """
import os, sys
from cosserat_ros import warmup
assert not warmup.kernels_cached()
first, second = warmup.start(sys.argv[1] == 'tiled'), warmup.start()
assert first is not None and second is None
assert first.wait(600) == 0
assert warmup.kernels_cached() and not os.path.exists(warmup._index_path() + '.warmup')
print('ok')
"""

_LOADS = """
import sys
import numba as nb
from cosserat_ros import warmup
from cosserat_ros.forces import vertex_fields
from cosserat_ros.integrator import integrate, variational_forces
from cosserat_ros.mesh import grid_mesh
from cosserat_ros.simulator import ClothSimulator, Material
assert warmup.kernels_cached()
s = ClothSimulator(grid_mesh(6, 5), Material(zeta=93.75, xi=1e-4 / 6, phi=0.0, density=0.1),
                   dt=1e-5, check_dt=False)
s.energy_and_densities()
if sys.argv[1] == 'tiled':
    variational_forces(s._x, s._ops, s._mat, s._work, s._force.copy())
    loaded = (vertex_fields, variational_forces)
else:
    @nb.njit
    def step_update(ops, work, x, v, force, fa, mass, damp, pinned, g, dt, vmax2, acc):
        # as run_variational calls it: a literal True
        return integrate(ops, work, True, x, v, force, fa, mass, damp, pinned, g, dt, vmax2,
                         acc)

    step_update(s._ops, s._work, s._x, s._v, s._force, s._f_applied, s._mass, s._damp,
                s._pinned, s._gravity, s._dt, 1e6, s._acc)
    loaded = (vertex_fields, integrate)
for k in loaded:
    assert sum(k.stats.cache_hits.values()) == 1 and not k.stats.cache_misses, k
print('loaded')
"""


@pytest.mark.parametrize('plan', ['two-pass', 'tiled'])
def test_warmup_process_compiles_what_the_node_then_loads(tmp_path, plan):
    # cosserat_ros.warmup, the node's second process on a cold start: into an empty cache
    # it compiles what the node needs after its step's vertex pass (two-pass step: the
    # energy kernels and the update; tiled step: the energy kernels and the critical dt's
    # force) with the signatures the node asks for, so that a later process (another
    # mesh, another material) loads them. A second start while the first warm-up runs
    # does not start another.
    env = dict(os.environ, NUMBA_CACHE_DIR=str(tmp_path / 'cache'))
    run = dict(env=env, cwd=tmp_path, capture_output=True, text=True, timeout=600)
    cold = subprocess.run([sys.executable, '-c', _STARTS, plan], **run)
    assert cold.stdout.strip() == 'ok', cold.stderr
    warm = subprocess.run([sys.executable, '-c', _LOADS, plan], **run)
    assert warm.stdout.strip() == 'loaded', warm.stderr


def test_warmup_lock_is_taken_once_and_a_stale_one_replaced(tmp_path):
    from cosserat_ros import warmup
    lock = str(tmp_path / 'x.nbi.warmup')
    assert warmup._take_lock(lock) and not warmup._take_lock(lock)
    old = time.time() - warmup.LOCK_SECONDS - 1          # its warm-up died long ago
    os.utime(lock, (old, old))
    assert warmup._take_lock(lock) and not warmup._take_lock(lock)
    assert not warmup._take_lock(str(tmp_path / 'missing' / 'x.warmup'))


def test_stale_cache_is_removed_when_a_kernel_source_changes(tmp_path):
    for name in compiled.KERNEL_MODULES:
        (tmp_path / name).write_text(f'# {name}\n')
    cache = tmp_path / '__pycache__'
    assert compiled.invalidate_stale_cache(str(tmp_path))       # first sight: wiped
    cached = [cache / 'integrator.run_variational-1.py311.nbi',
              cache / 'integrator.run_variational-1.py311.1.nbc']
    for f in cached:
        f.write_bytes(b'x')
    (cache / 'other.pyc').write_bytes(b'x')
    assert not compiled.invalidate_stale_cache(str(tmp_path))   # unchanged: kept
    assert all(f.exists() for f in cached)
    # only the callee's file changes (the case numba's own check misses)
    (tmp_path / 'forces.py').write_text('# changed\n')
    assert compiled.invalidate_stale_cache(str(tmp_path))
    assert not any(f.exists() for f in cached)
    assert (cache / 'other.pyc').exists()


def test_unwritable_cache_is_left_alone(tmp_path):
    for name in compiled.KERNEL_MODULES:
        (tmp_path / name).write_text('\n')
    (tmp_path / '__pycache__').write_text('not a directory')   # cannot hold a cache
    assert not compiled.invalidate_stale_cache(str(tmp_path))
    assert (tmp_path / '__pycache__').read_text() == 'not a directory'


@nb.njit
def _vector_ops(a, b, c, out):
    for k in range(0, a.size, 4):
        va = vload(a, k)
        vb = vload(b, k)
        vc = vload(c, k)
        r = vfma(va, vb, vc) - va / vb + 2.0 * vsqrt(vc) - (-va) * 0.5 + splat(1.0)
        vstore(out, k, r)
    return lane(vset(out[0], out[1], 3.0, out[3]), 2)


def test_simd_vectors_compute_lane_by_lane_like_numpy():
    rng = np.random.default_rng(0)
    a, b, c = (rng.uniform(0.5, 2.0, 16) for _ in range(3))
    out = np.zeros(16)
    assert _vector_ops(a, b, c, out) == 3.0
    ref = a * b + c - a / b + 2.0 * np.sqrt(c) + a * 0.5 + 1.0
    assert np.allclose(out, ref, rtol=1e-15, atol=0)


@nb.njit
def _columns(a, k, out):
    c0, c1, c2 = vload3(a, k)
    vstore(out, 0, c0)
    vstore(out, 4, c1)
    vstore(out, 8, c2)


def test_vload3_splits_four_rows_into_their_columns():
    a = np.arange(30.0).reshape(10, 3) * 1.5 - 7.0
    out = np.zeros(12)
    for row in (0, 3, 6):
        _columns(a, 3 * row, out)
        assert np.array_equal(out.reshape(3, 4), a[row:row + 4].T)


@pytest.mark.parametrize('lanes', [1, 4])
def test_lane_layout_is_a_permutation_of_whole_stencils(lanes):
    st_ptr = np.cumsum([0] + [3, 5, 3, 3, 5, 3, 4, 3, 5, 5, 5, 3])
    rng = np.random.default_rng(3)
    st_idx = rng.integers(0, len(st_ptr) - 1, st_ptr[-1])
    st_sigma = rng.standard_normal(st_ptr[-1])
    g_vert, g_ptr, g_wptr, s_vert, s_ptr, s_wptr, pos, wsrc, ln_idx, ln_sigma = lane_layout(
        st_ptr, np.arange(len(st_ptr) - 1), st_idx, st_sigma, lanes)
    assert sorted(pos) == list(range(st_ptr[-1]))
    assert sorted(np.concatenate([g_vert.ravel(), s_vert])) == list(range(len(st_ptr) - 1))
    sizes = np.diff(st_ptr)
    for g, verts in enumerate(g_vert):
        assert len(set(sizes[verts])) == 1                    # one stencil size per group
        for l, i in enumerate(verts):                         # entry s of lane l
            s = np.arange(sizes[i])
            assert list(pos[st_ptr[i] + s]) == list(g_ptr[g] + lanes * s + l)
            e = g_wptr[g, 1] + lanes * s + l                  # its entry block: offsets
            assert list(i + ln_idx[e]) == list(st_idx[st_ptr[i] + s])
            assert list(ln_sigma[e]) == list(st_sigma[st_ptr[i] + s])
        rows = (np.array_equal(verts, verts[0] + np.arange(lanes))    # g_wptr[g, 3]
                and len({tuple(st_idx[st_ptr[i]:st_ptr[i + 1]] - i) for i in verts}) == 1)
        assert g_wptr[g, 3] == (lanes == 4 and rows)
    for u, i in enumerate(s_vert):                            # leftovers: plain CSR blocks
        assert list(pos[st_ptr[i]:st_ptr[i + 1]]) == list(range(s_ptr[u], s_ptr[u + 1]))
        assert list(ln_idx[s_ptr[u]:s_ptr[u + 1]]) == list(st_idx[st_ptr[i]:st_ptr[i + 1]])
    if lanes == 4:      # sizes 3 (x6), 5 (x5), 4 (x1): one group of each of 3 and 5
        assert len(g_vert) == 2 and len(s_vert) == 4


def test_lane_layout_flags_groups_whose_neighbours_are_rows():
    """g_wptr[g, 3]: the lanes are four consecutive vertices, with the same offsets."""
    n = 10
    st_idx = np.array([[i, i + 1, i + 2] for i in range(8)] + [[8, 7, 6], [9, 8, 7]])
    st_idx[6] = (6, 5, 7)            # the second group: consecutive, other offsets
    st_ptr = np.arange(0, 3 * n + 1, 3)
    g_vert, _, g_wptr, s_vert, *_ = lane_layout(st_ptr, np.zeros(n, dtype=np.int64),
                                                st_idx.ravel(), np.zeros(3 * n))
    assert g_vert.tolist() == [[0, 1, 2, 3], [4, 5, 6, 7]] and s_vert.tolist() == [8, 9]
    assert g_wptr[:, 3].tolist() == [1, 0]


@pytest.mark.parametrize('name', ['regular', 'irregular', 'icosphere'])
def test_simd_vertex_pass_matches_one_vertex_at_a_time(name):
    mesh = (ClothMesh(*(lambda m: (m.vertices, m.faces))(
        trimesh.creation.icosphere(subdivisions=2, radius=0.5))) if name == 'icosphere'
        else grid_mesh(13, 11, pattern=name, seed=2))
    mat = Material(zeta=20.0, xi=1e-3, phi=1e-3, density=0.2)
    sims = [ClothSimulator(mesh, mat, dt=1e-4, check_dt=False, simd=f) for f in (True, False)]
    assert sims[0]._ops[19].shape[0] > 0 and sims[1]._ops[19].shape[0] == 0
    # the regular sheet has groups whose neighbours are rows of x (simd.vload3)
    assert sims[0]._ops[21][:, 3].any() == (name == 'regular')
    x = mesh.vertices + 0.02 * np.random.default_rng(4).standard_normal(mesh.vertices.shape)
    f, e = [], []
    for sim in sims:
        sim.set_positions(x)
        f.append(sim.internal_forces())
        e.append(sim.energy())
    assert np.abs(f[0] - f[1]).max() <= 1e-13 * np.abs(f[1]).max()
    for key in ('stretching', 'bending', 'coupling'):
        assert e[0][key] == pytest.approx(e[1][key], rel=1e-13, abs=1e-300)


def test_a_flat_sheet_shares_its_entry_blocks():
    # numbered row by row and flat at rest, the lane groups' neighbour offsets and rest
    # residuals repeat: the vertex pass then reads a few shared blocks, not one per group,
    # and their number does not grow with the sheet
    sizes = []
    for n in (16, 32):
        sim = ClothSimulator(grid_mesh(n, n), Material(zeta=20.0, xi=1e-3, density=0.2),
                             dt=1e-4, check_dt=False)
        assert sim._ops[11].shape == sim._ops[25].shape      # residuals, offsets
        sizes.append(sim._ops[25].shape[0])
    assert sizes[0] == sizes[1] < sim._ops[8].shape[0] // 10  # of the stencil entries


@pytest.mark.parametrize('name', ['irregular', 'icosphere'])
def test_faces_in_the_vertex_pass_match_their_own_pass(name):
    # phi = 0 runs the membrane faces inside the vertex pass's chunks; any phi != 0 runs
    # them in a pass of their own first. phi = 1e-300 changes the force by ~1e-300 only.
    mesh = (ClothMesh(*(lambda m: (m.vertices, m.faces))(
        trimesh.creation.icosphere(subdivisions=3, radius=0.5))) if name == 'icosphere'
        else grid_mesh(41, 37, pattern=name, seed=3))
    x = mesh.vertices + 0.02 * np.random.default_rng(5).standard_normal(mesh.vertices.shape)
    f, eps = [], []
    for phi in (0.0, 1e-300):
        sim = ClothSimulator(mesh, Material(zeta=20.0, xi=1e-3, phi=phi, density=0.2),
                             dt=1e-4, check_dt=False)
        assert len(sim._ops[28]) - 1 > 2                # several chunks share the faces
        sim.set_positions(x)
        f.append(sim.internal_forces())
        eps.append(sim.energy()['stretching'])      # strains from forces.vertex_fields
    assert eps[0] == eps[1] > 0
    assert np.abs(f[0] - f[1]).max() <= 1e-14 * np.abs(f[1]).max()


@nb.njit
def _take_moves(state, n, ranges, fronts, out):
    nr = split(state, n)
    for q in range(ranges.shape[0]):
        out[q] = take(state, ranges[q] % nr, fronts[q])
    return nr


@pytest.mark.parametrize('n, nr', [(0, 1), (1, 3), (7, 2), (100, 1), (100, 2), (101, 5)])
def test_work_sharing_hands_out_every_item_once(n, nr):
    # owners (front) and thieves (back) in a random interleaving, serially: every item once,
    # each range's front in increasing and back in decreasing order, then nothing
    rng = np.random.default_rng(n + nr)
    state = np.zeros(9, dtype=np.int64)
    state[0] = nr
    moves = 3 * n + 10
    ranges = rng.integers(0, nr, moves)
    fronts = rng.random(moves) < 0.6
    out = np.empty(moves, dtype=np.int64)
    assert _take_moves(state, n, ranges, fronts, out) == nr
    got = out[out >= 0]
    assert sorted(got.tolist()) == list(range(n))
    bounds = [n * r // nr for r in range(nr + 1)]
    for r in range(nr):
        mine = (ranges == r) & (out >= 0)
        assert np.all((out[mine] >= bounds[r]) & (out[mine] < bounds[r + 1]))
        assert np.all(np.diff(out[mine & fronts]) > 0)
        assert np.all(np.diff(out[mine & ~fronts]) < 0)
    rest = np.empty(2 * nr, dtype=np.int64)
    _take_moves(state, 0, np.arange(2 * nr), np.arange(2 * nr) % 2 == 0, rest)
    assert (rest == -1).all()
    state[0] = 0                                    # no count set: one range
    assert _take_moves(state, 5, ranges[:0], fronts[:0], out) == 1 and state[1] == 5 << 32


@pytest.mark.parametrize('phi', [0.0, 1e-3])
def test_the_step_is_the_same_to_the_bit_however_the_threads_share_it(phi):
    # the vertex pass and the update in 1, 2, 3 or 7 ranges (more than the threads: the
    # ranges a thread does not own it takes from their back), each step in its parallel
    # regions or (phi = 0) all steps in one region with barriers: the same trajectory and
    # the same work and dissipation sums, to the bit
    mesh = grid_mesh(23, 19, pattern='irregular', seed=1)
    mat = Material(zeta=50.0, xi=1e-3, phi=phi, density=0.2, damping=0.3)
    runs = []
    for nr in (1, 2, 3, 7):
        for one_region in ((False, True) if phi == 0.0 else (False,)):
            sim = ClothSimulator(mesh, mat, dt=1e-4)
            sim.pin([0, 5])
            sim.gravity = (0, 0, -9.81)
            sim.force_field = (0.3, 0.0, 0.1)
            share, ushare = np.zeros(9, dtype=np.int64), np.zeros(9, dtype=np.int64)
            share[0] = ushare[0] = nr
            work = sim._work[:8] + (share,) + sim._work[9:10] + (ushare,) + sim._work[11:]
            args = (300, sim._x, sim._v, sim._f_applied, sim._mass, sim._damp, sim._pinned,
                    sim._gravity, sim.dt, 1e6, sim._acc, sim._ops, sim._mat, work, sim._force)
            done = run_fused(*args, nb.get_num_threads()) if one_region \
                else run_variational(*args)
            assert done == 300
            runs.append((sim._x.copy(), sim._v.copy(), sim._acc.copy()))
    assert runs[0][2][0] != 0 and runs[0][2][1] > 0           # work and dissipation
    for run in runs[1:]:
        assert all(np.array_equal(a, b) for a, b in zip(runs[0], run))


def test_the_internal_force_through_the_one_region_step_is_the_same_to_the_bit(monkeypatch):
    # the critical dt's force, one step of dt = 0 through run_fused (so that a process
    # compiles the vertex code once), is the variational force; the state is left as it was
    sim = ClothSimulator(grid_mesh(17, 13, pattern='irregular', seed=2),
                         Material(zeta=50.0, xi=1e-3, phi=0.0, density=0.2, damping=0.3),
                         dt=1e-4)
    sim.pin([0, 5])
    sim.gravity = (0, 0, -9.81)
    sim.step(50)
    x, v = sim.positions.copy(), sim.velocities.copy()
    bent = x + 1e-3 * np.sin(np.arange(x.size)).reshape(x.shape)
    ref, ref_bent, got_bent = np.empty_like(x), np.empty_like(x), np.empty_like(x)
    variational_forces(x, sim._ops, sim._mat, sim._work, ref)
    variational_forces(bent, sim._ops, sim._mat, sim._work, ref_bent)
    steps = []
    monkeypatch.setattr('cosserat_ros.simulator.run_fused',
                        lambda *a: steps.append(a[0]) or run_fused(*a))
    got = sim.internal_forces()
    sim._internal(bent, got_bent)
    assert steps == ([1, 1] if sim._share_threads() > 0 else [])
    assert np.array_equal(got, ref)
    assert np.array_equal(got_bent, ref_bent) and not np.array_equal(ref_bent, ref)
    assert np.array_equal(sim.positions, x) and np.array_equal(sim.velocities, v)


def test_steps_in_one_parallel_region_stop_at_the_step_that_went_bad():
    # one region for all steps: every thread must leave it at the same step, and step()
    # restores the state from before the call, as with a region per pass
    ends = []
    for one_region in (False, True):
        sim = ClothSimulator(grid_mesh(15, 15), Material(zeta=50.0, xi=1e-4, phi=0.0,
                                                         density=0.2), dt=1e-4)
        sim.pin([0, 15])
        sim.gravity = (0, 0, -9.81)
        sim.step(20)
        x = sim.positions.copy()
        sim._dt = 10 * sim.critical_dt()
        work = sim._work
        work[8][0] = work[10][0] = nb.get_num_threads()
        args = (400, sim._x, sim._v, sim._f_applied, sim._mass, sim._damp, sim._pinned,
                sim._gravity, sim.dt, sim._vmax ** 2, sim._acc, sim._ops, sim._mat, work,
                sim._force)
        done = run_fused(*args, nb.get_num_threads()) if one_region else run_variational(*args)
        assert 0 < done < 400
        ends.append((done, sim._x.copy()))
        sim.set_positions(x)
        with pytest.raises(SimulationDiverged):
            sim.step(400)
        assert np.array_equal(sim.positions, x)
    assert ends[0][0] == ends[1][0]
    assert np.array_equal(ends[0][1], ends[1][1], equal_nan=True)


def test_one_region_per_call_only_where_every_iteration_gets_a_thread(monkeypatch):
    # the barrier of the one-region step waits for every iteration of its prange: it is
    # used only with numba's static schedule on a layer that runs them all at once, and
    # with no more threads than CPUs (spinning threads would take the CPU of those they
    # wait for)
    sim = ClothSimulator(grid_mesh(6, 5), Material(zeta=50.0, xi=1e-4, phi=0.0, density=0.2),
                         dt=1e-5, check_dt=False)
    sim.step(1)
    nthr = nb.get_num_threads()
    ok = nb.threading_layer() in ('omp', 'workqueue') and nthr <= workshare.usable_cpus()
    assert sim._share_threads() == (nthr if ok else 0)
    nb.set_parallel_chunksize(2)
    try:
        assert sim._share_threads() == 0
        sim.step(3)                                 # the passes per region still step
    finally:
        nb.set_parallel_chunksize(0)
    monkeypatch.setattr('cosserat_ros.simulator.usable_cpus', lambda: nthr - 1)
    assert sim._share_threads() == 0
    sim.step(2)
    assert sim.step_count == 6
    assert 1 <= workshare.usable_cpus() <= (os.cpu_count() or 1)
