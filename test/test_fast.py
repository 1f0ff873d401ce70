"""The compiled step (``cosserat_ros/fast``) against the scalar terms of ``core/terms``, and
its machinery: the SIMD vectors, the lane layout, the work sharing, the tiled plan. Each
fast path must compute what the reference computes; only who computes it may change."""
import os

import numba as nb
import numpy as np
import pytest
import trimesh

from cosserat_ros.core.constants import FUSE_MIN_VERTICES, VERTEX_CHUNK
from cosserat_ros.core.solvers import explicit
from cosserat_ros.core.state import State
from cosserat_ros.fast import step as fast_step, workshare
from cosserat_ros.fast.lanes import chunk_of_vertex, FAN_WINDOW, lane_layout
from cosserat_ros.fast.plan import build_plan
from cosserat_ros.fast.simd import lane, splat, vfma, vload, vload3, vset, vsqrt, vstore
from cosserat_ros.fast.workshare import split, take
from cosserat_ros.mesh import ClothMesh, grid_mesh
from cosserat_ros.simulator import (Air, ClothSimulator, Material, SimulationDiverged,
                                    steps_tiled)


def _mesh(name, n=13):
    if name == 'icosphere':
        m = trimesh.creation.icosphere(subdivisions=2 if n < 20 else 3, radius=0.5)
        return ClothMesh(m.vertices, m.faces)
    return grid_mesh(n, n - 2, pattern=name, seed=2)


def _shaken(sim, seed=4, amp=0.02):
    rng = np.random.default_rng(seed)
    sim.set_positions(sim.mesh.vertices + amp * rng.standard_normal(sim.mesh.vertices.shape))
    return sim


# ------------------------------------------------------------------ against the terms

@pytest.mark.parametrize('name', ['regular', 'alternating', 'irregular', 'icosphere'])
@pytest.mark.parametrize('phi', [0.0, 2e-3])
@pytest.mark.parametrize('simd', [True, False])
def test_the_step_force_is_minus_the_sum_of_the_term_gradients(name, phi, simd):
    """The fast force (lanes or one vertex at a time, the coupling's strain side folded
    into the vertex's own entries) against the terms' own kernels, summed."""
    mesh = _mesh(name)
    mat = Material(zeta=20.0, xi=1e-3, phi=phi, density=0.2)
    sim = _shaken(ClothSimulator(mesh, mat, dt=1e-4, check_dt=False, simd=simd))
    assert (len(sim.solver.lanes.g_vert) > 0) == simd
    ref = explicit.internal_force_reference(sim.model, sim.coefficients, sim.state.x)
    got = sim.internal_forces()
    assert np.abs(ref).max() > 0
    assert np.abs(got - ref).max() <= 1e-12 * np.abs(ref).max()


@pytest.mark.parametrize('simd', [True, False])
def test_the_step_force_follows_the_terms_below_the_jet_area_floor(simd):
    """The same on a sheet pressed to 0.05 of its width (test_terms.squeezed): |a_1 x a_2|
    below constants.JET_AREA_FLOOR at every vertex, where the jet's normal shortens (the
    SIMD lanes take the branch-free min of simd.py)."""
    from cosserat_ros.core.constants import JET_AREA_FLOOR
    from test_terms import _area_ratios, squeezed
    mesh = _mesh('irregular')
    mat = Material(zeta=20.0, xi=1e-3, phi=2e-3, density=0.2)
    sim = ClothSimulator(mesh, mat, dt=1e-4, check_dt=False, simd=simd)
    sim.set_positions(squeezed(mesh.vertices))
    assert _area_ratios(sim.model, sim.state.x).max() < JET_AREA_FLOOR
    ref = explicit.internal_force_reference(sim.model, sim.coefficients, sim.state.x)
    got = sim.internal_forces()
    assert np.abs(ref).max() > 0
    assert np.abs(got - ref).max() <= 1e-12 * np.abs(ref).max()


@pytest.mark.parametrize('name', ['irregular', 'icosphere'])
def test_the_fast_step_follows_the_reference_step(name):
    """300 steps of the compiled step against the update with the terms' forces summed
    (``solvers.explicit.reference_step``), with pins, forces, a field, air and damping."""
    mesh = _mesh(name)
    mat = Material(zeta=20.0, xi=1e-3, phi=2e-3, density=0.2, damping=0.3)
    sims = []
    for _ in range(2):
        sim = _shaken(ClothSimulator(mesh, mat, dt=1e-4), amp=0.005)
        sim.pin([0, 5])
        sim.gravity = (0.0, 0.0, -9.81)
        sim.force_field = (0.3, 0.0, 0.1)
        sim.set_vertex_forces([3, 3, 9], [[0, 0, 1e-3], [1e-3, 0, 0], [0, -1e-3, 0]])
        sim.air = Air(density=5.0, lift=0.8)
        sim.wind = (2.0, 0.5, -1.0)
        sims.append(sim)
    sims[0].step(300)
    s = sims[1]
    assert explicit.reference_step(s.model, s.coefficients, s.state, s.control, s.dt,
                                   300) == 300
    x0, x1 = sims[0].state.x, s.state.x
    assert np.abs(x1 - s.mesh.vertices).max() > 1e-3           # it moved
    assert np.abs(x0 - x1).max() <= 1e-10 * np.abs(x1).max()
    assert np.abs(sims[0].state.v - s.state.v).max() <= 1e-8 * np.abs(s.state.v).max()
    assert sims[0].state.acc == pytest.approx(s.state.acc, rel=1e-9)


# ------------------------------------------------------------------ SIMD and the layout

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
        for ln, i in enumerate(verts):                        # entry s of lane ln
            s = np.arange(sizes[i])
            assert list(pos[st_ptr[i] + s]) == list(g_ptr[g] + lanes * s + ln)
            e = g_wptr[g, 1] + lanes * s + ln                 # its entry block: offsets
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


def test_a_flat_sheet_shares_its_entry_blocks():
    # numbered row by row and flat at rest, the lane groups' neighbour offsets and rest
    # residuals repeat: the vertex pass then reads a few shared blocks, not one per group,
    # and their number does not grow with the sheet
    sizes = []
    for n in (16, 32):
        sim = ClothSimulator(grid_mesh(n, n), Material(zeta=20.0, xi=1e-3, density=0.2),
                             dt=1e-4, check_dt=False)
        lanes = sim.solver.lanes
        assert lanes.sigma.shape == lanes.idx.shape
        sizes.append(lanes.idx.shape[0])
    assert sizes[0] == sizes[1] < len(sim.model.jets.idx) // 10


# ------------------------------------------------------------------ work sharing

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


def _run(sim, one_region, nsteps, nr=None):
    s, m = sim.solver, sim.model
    args = (nsteps, sim.state, sim.control, sim.coefficients, m.faces, m.vertex_faces,
            m.vertices, m.jets.tr_ptr, s.lanes, s.plan, s.work, sim.dt, sim._vmax ** 2)
    coupled = sim.coefficients.phi != 0.0
    s.work.share[0] = s.work.ushare[0] = nr or nb.get_num_threads()
    if one_region:
        run = fast_step.run_region_coupled if coupled else fast_step.run_region
        return run(*args, nb.get_num_threads())
    return (fast_step.run_two_pass_coupled if coupled else fast_step.run_two_pass)(*args)


@pytest.mark.slow
@pytest.mark.parametrize('phi', [0.0, 1e-3])
def test_the_step_is_the_same_to_the_bit_however_the_threads_share_it(phi):
    # the vertex pass and the update in 1, 2, 3 or 7 ranges (more than the threads: the
    # ranges a thread does not own it takes from their back), each step in its parallel
    # regions or all steps in one region with barriers: the same trajectory and the same
    # work and dissipation sums, to the bit
    mesh = grid_mesh(23, 19, pattern='irregular', seed=1)
    mat = Material(zeta=50.0, xi=1e-3, phi=phi, density=0.2, damping=0.3)
    runs = []
    for nr in (1, 2, 3, 7):
        for one_region in (False, True):
            sim = ClothSimulator(mesh, mat, dt=1e-4)
            sim.pin([0, 5])
            sim.gravity = (0, 0, -9.81)
            sim.force_field = (0.3, 0.0, 0.1)
            sim.air = Air(density=5.0, lift=0.8)
            sim.wind = (2.0, 0.5, -1.0)
            assert _run(sim, one_region, 300, nr) == 300
            runs.append(sim.state.copy())
    assert runs[0].acc[0] != 0 and runs[0].acc[1] > 0           # work and dissipation
    for run in runs[1:]:
        assert all(np.array_equal(a, b) for a, b in zip(runs[0], run))


@pytest.mark.parametrize('phi', [0.0, 1e-3])
def test_the_internal_force_through_the_one_region_step_is_the_two_pass_one(phi):
    # the critical dt's force, one step of dt = 0 through run_region (so that a process
    # compiles the vertex code once), is the two-pass vertex pass's force to the bit; the
    # state is left as it was
    sim = _shaken(ClothSimulator(grid_mesh(17, 13, pattern='irregular', seed=2),
                                 Material(zeta=50.0, xi=1e-3, phi=phi, density=0.2),
                                 dt=1e-4), amp=0.005)
    sim.pin([0, 5])
    x, v = sim.positions, sim.velocities
    got = sim.internal_forces()
    s, m = sim.solver, sim.model
    ref = np.zeros_like(got)
    run = fast_step.elastic_forces_coupled if phi else fast_step.elastic_forces
    run(sim.state.x, sim.coefficients, m.faces, m.vertex_faces, m.vertices, m.jets.tr_ptr,
        s.lanes, s.plan, s.work, ref)
    assert np.abs(ref).max() > 0 and np.array_equal(got, ref)
    assert np.array_equal(sim.positions, x) and np.array_equal(sim.velocities, v)


def test_steps_in_one_parallel_region_stop_at_the_step_that_went_bad():
    # one region for all steps: every thread must leave it at the same step, as with a
    # region per pass
    ends = []
    for one_region in (False, True):
        sim = ClothSimulator(grid_mesh(15, 15), Material(zeta=50.0, xi=1e-4, phi=1e-5,
                                                         density=0.2), dt=1e-4)
        sim.pin([0, 15])
        sim.gravity = (0, 0, -9.81)
        sim.step(20)
        sim.dt = 10 * sim.critical_dt()
        done = _run(sim, one_region, 400)
        assert 0 < done < 400
        ends.append((done, sim.state.x.copy()))
    assert ends[0][0] == ends[1][0]
    assert np.array_equal(ends[0][1], ends[1][1], equal_nan=True)


_BARRIER_SCRIPT = """
import sys
import numba as nb
import numpy as np
from cosserat_ros.fast.workshare import arrive, _SYS_FUTEX

@nb.njit(parallel=True)
def rounds(sync, board, slow, out):
    nthr = board.shape[0]
    for t in nb.prange(nthr):
        errors = 0
        slept = 0
        acc = 0.0
        for r in range(1, out.shape[1] + 1):
            if t == nthr - 1:                  # the late thread: the others wait for it
                for i in range(slow):
                    acc += i * 1e-12
            board[t] = r
            slept += arrive(sync, r, nthr)
            for u in range(nthr):              # all have written round r before any left
                if board[u] < r:
                    errors += 1
        out[t, 0] = errors
        out[t, 1] = slept
        out[t, 2] = acc > -1.0

nb.set_num_threads(2)
sync = np.zeros(4, dtype=np.int64)             # count, -, sleepers, spin: sleep at once
out = np.zeros((2, 20000), dtype=np.int64)
rounds(sync, np.zeros(2, dtype=np.int64), 2000, out)
print(int(out[:, 0].sum()), int(out[0, 1]), int(out[1, 1]), int(sync[0]), _SYS_FUTEX)
"""


@pytest.mark.process
def test_the_barrier_sleeps_and_loses_no_wake_up():
    # 20000 rounds of two threads, the second late by a short loop each round, the waiter
    # sent to sleep at once (no spin): every round, each thread leaves only after both
    # arrived, the early one slept (Linux: futex) and was woken every time; a lost wake-up
    # hangs, so the rounds run in a process of their own with a time limit
    if workshare.usable_cpus() < 2 or nb.config.NUMBA_NUM_THREADS < 2:
        pytest.skip('the barrier needs two threads, each on a CPU of its own')
    import subprocess
    import sys
    out = subprocess.run([sys.executable, '-c', _BARRIER_SCRIPT], capture_output=True,
                         text=True, timeout=600)
    assert out.returncode == 0, out.stderr[-2000:]
    errors, slept0, slept1, count, futex = (int(v) for v in out.stdout.split())
    assert errors == 0 and count == 2 * 20000
    if futex:
        assert slept0 > 1000, f'the early thread slept {slept0} times in 20000 rounds'
    else:
        assert slept0 == slept1 == 0


def test_the_step_through_sleeping_barriers_is_the_same_to_the_bit():
    # the one-region step with its waiters sent to sleep at once (no spin) and with the
    # default spin: the same trajectory, to the bit
    mesh = grid_mesh(19, 17, pattern='irregular', seed=3)
    runs = []
    for spin in (workshare.SPIN, 0):
        sim = ClothSimulator(mesh, Material(zeta=50.0, xi=1e-3, phi=1e-3, density=0.2,
                                            damping=0.3), dt=1e-4)
        sim.pin([0, 5])
        sim.gravity = (0, 0, -9.81)
        assert sim.solver.work.sync[3] == workshare.SPIN
        sim.solver.work.sync[3] = spin
        assert _run(sim, True, 300) == 300
        runs.append(sim.state.copy())
    assert np.abs(runs[0].x - mesh.vertices).max() > 1e-4
    assert all(np.array_equal(a, b) for a, b in zip(runs[0], runs[1]))


def test_one_region_only_where_every_iteration_gets_a_cpu(monkeypatch):
    # the barrier of the one-region step waits for every iteration of its prange: it is
    # used only with numba's static schedule on a layer that runs them all at once, and
    # with no more threads than CPUs (spinning threads would take the CPU of those they
    # wait for), and never for the tiled step
    sim = ClothSimulator(grid_mesh(6, 5), Material(zeta=50.0, xi=1e-4, phi=0.0, density=0.2),
                         dt=1e-5, check_dt=False)
    sim.step(1)
    nthr = nb.get_num_threads()
    ok = nb.threading_layer() in ('omp', 'workqueue') and nthr <= workshare.usable_cpus()
    assert sim.solver._share_threads() == (nthr if ok else 0)
    nb.set_parallel_chunksize(2)
    try:
        assert sim.solver._share_threads() == 0
        sim.step(3)                                 # the passes per region still step
    finally:
        nb.set_parallel_chunksize(0)
    monkeypatch.setattr(explicit, 'usable_cpus', lambda: nthr - 1)
    assert sim.solver._share_threads() == 0
    sim.step(2)
    assert sim.step_count == 6
    assert 1 <= workshare.usable_cpus() <= (os.cpu_count() or 1)


def test_a_diverging_step_stops_there_and_the_state_is_restored():
    sim = ClothSimulator(grid_mesh(15, 15), Material(zeta=50.0, xi=1e-4, phi=1e-5,
                                                     density=0.2), dt=1e-4)
    sim.pin([0, 15])
    sim.gravity = (0, 0, -9.81)
    sim.step(20)
    x = sim.positions
    sim.dt = 10 * sim.critical_dt()
    with pytest.raises(SimulationDiverged) as err:
        sim.step(400)
    assert 20 < err.value.step < 420 and 'above the stable limit' in err.value.hint
    assert np.array_equal(sim.positions, x) and sim.step_count == 20


# ------------------------------------------------------------------ the tiled step

def _replanned(mesh, tile_vertices, parts, tiled, phi=0.0):
    sim = ClothSimulator(mesh, Material(zeta=20.0, xi=1e-3, phi=phi, density=0.2,
                                        damping=3.0), dt=1e-4, check_dt=False)
    s = sim.solver
    nch = -(-mesh.n_vertices // VERTEX_CHUNK)
    s.plan = build_plan(sim.model, s.lanes, nch, tile_vertices, parts, tiled)
    s.tiled = tiled
    return sim


def _contributors(sim):
    """(vertex, chunk) pairs: every chunk whose work reads x_j or feeds the force on j."""
    p, lanes, jet = sim.solver.plan, sim.solver.lanes, sim.model.jet
    nch = p.tile_ch[-1]
    chunk = chunk_of_vertex(sim.mesh.n_vertices, nch, lanes.g_vert, lanes.s_vert)
    face_chunk = np.repeat(np.arange(nch), np.diff(p.fc_ptr))[np.argsort(p.fc_face)]
    pairs = [(jet.st_idx, np.repeat(chunk, np.diff(jet.st_ptr))),
             (sim.mesh.faces.ravel(), np.repeat(face_chunk, 3))]
    return np.concatenate([q[0] for q in pairs]), np.concatenate([q[1] for q in pairs])


@pytest.mark.slow
@pytest.mark.parametrize('name', ['irregular', 'icosphere'])
@pytest.mark.parametrize('parts, phi', [(2, 0.0), (3, 0.0), (2, 1e-3)])
def test_tiled_step_gives_the_same_trajectory_to_the_bit(name, parts, phi):
    mesh = _mesh(name, 41)
    rng = np.random.default_rng(7)
    x0 = mesh.vertices + 0.01 * rng.standard_normal(mesh.vertices.shape)
    v0 = 0.05 * rng.standard_normal(mesh.vertices.shape)
    runs = []
    for tile, tiled in ((10 ** 9, False), (64, True), (16, True)):
        sim = _replanned(mesh, tile, parts, tiled, phi)
        assert (len(sim.solver.plan.tile_ch) - 1 > 2 * parts) == tiled   # tiles per part
        sim.gravity = (0.0, 0.0, -9.81)
        sim.pin(np.arange(0, mesh.n_vertices, 97))
        sim.set_vertex_forces([5, 40], [[0.0, 0.0, 1e-3], [1e-3, 0.0, 0.0]])
        sim.air = Air(density=5.0, lift=0.8)
        sim.wind = (2.0, 0.5, -1.0)
        sim.set_positions(x0)
        sim.set_velocities(v0)
        sim.step(40)
        runs.append(sim.state.copy())
    for run in runs[1:]:
        assert np.array_equal(run.x, runs[0].x) and np.array_equal(run.v, runs[0].v)
        # the work and dissipation sums only add up in another order
        assert run.acc == pytest.approx(runs[0].acc, rel=1e-12, abs=1e-300)


@pytest.mark.parametrize('name', ['irregular', 'icosphere'])
def test_tiled_plan_updates_each_vertex_once_after_everything_that_touches_it(name):
    sim = _replanned(_mesh(name, 41), 32, 3, True)
    p = sim.solver.plan
    n, ntile = sim.mesh.n_vertices, len(p.tile_ch) - 1
    assert np.array_equal(np.sort(p.gl_vert), np.arange(n))
    assert np.array_equal(np.sort(p.fc_face), np.arange(sim.mesh.n_faces))
    assert len(p.gl_ptr) == ntile + 2 and p.gl_ptr[-1] == n
    part_ch = p.tile_ch[p.part_tile]
    assert np.all(np.diff(part_ch) >= 0) and part_ch[0] == 0 and part_ch[-1] == p.tile_ch[-1]
    vertex, chunk = _contributors(sim)
    tile_of = np.full(n, -1)
    for t in range(ntile + 1):
        tile_of[p.gl_vert[p.gl_ptr[t]:p.gl_ptr[t + 1]]] = t
    inner = tile_of[vertex] < ntile
    t = tile_of[vertex[inner]]
    part_of_tile = np.searchsorted(p.part_tile, np.arange(ntile), 'right') - 1
    q = part_of_tile[t]
    # every contributor of a vertex updated inside a part is that part's and comes no
    # later than the end of the tile that updates it
    assert np.all(chunk[inner] >= part_ch[q]) and np.all(chunk[inner] < part_ch[q + 1])
    assert np.all(chunk[inner] < p.tile_ch[t + 1])


@pytest.mark.slow
@pytest.mark.parametrize('pattern, most', [('regular', 0.1), ('irregular', 0.2)])
def test_the_tiled_step_leaves_a_small_seam_on_a_locally_numbered_sheet(pattern, most):
    # with the default tiles and a part per thread, on a sheet numbered row by row: the
    # seam gathered after the parts (from memory, not from the cache) is a minority. An
    # irregular sheet's lane groups gather vertices of one fan shape from windows of
    # lanes.FAN_WINDOW vertices, so its seam is wider. (trimesh's icosphere numbers new
    # vertices apart from their neighbours: nearly all of it is seam, correct, no gain.)
    sim = ClothSimulator(grid_mesh(80, 80, pattern=pattern, seed=3),
                         Material(zeta=20.0, xi=1e-3, phi=1e-3, density=0.2), dt=1e-5,
                         check_dt=False)
    p = sim.solver.plan
    assert sim.solver.tiled and len(p.part_tile) - 1 == nb.get_num_threads()
    assert (p.gl_ptr[-1] - p.gl_ptr[-2]) < most * sim.n_vertices


@pytest.mark.slow
@pytest.mark.parametrize('name', ['regular', 'irregular'])
@pytest.mark.parametrize('tile, side', [(16, 41), (256, 81)])
def test_ring_slots_hold_every_gradient_until_its_last_reader(name, tile, side):
    # replay the tiled step's writes and reads, tile by tile: every slot a gather reads
    # must still hold the group that wrote that entry, and the rings must really recycle
    sim = _replanned(grid_mesh(side, side - 4, pattern=name, seed=3), tile, 2, True)
    p, lanes, jet = sim.solver.plan, sim.solver.lanes, sim.model.jet
    g_ptr, tile_ch, gl_ptr, gl_vert = lanes.g_ptr, p.tile_ch, p.gl_ptr, p.gl_vert
    base, slot_of = p.g_wptr[:, 2], p.tr_slot.astype(np.int64)
    pos_of = lanes.pos[jet.tr_slot]
    tr_ptr, nch, ng = jet.tr_ptr, tile_ch[-1], len(g_ptr) - 1
    size = np.diff(g_ptr)
    g_tile = np.searchsorted(tile_ch, np.arange(ng) // -(-ng // nch), 'right') - 1
    owner = np.full(len(jet.st_idx), -1)
    group_of = np.searchsorted(g_ptr, pos_of, 'right') - 1   # -1: a single vertex's entry
    assert np.all(owner[:g_ptr[0]] == -1) and np.all(base >= g_ptr[0])
    # the faces' corner gradients: rows fc_slot of fgrad, read as row 3 slot + corner
    vf_row = p.vf_row.astype(np.int64)
    assert np.array_equal(vf_row % 3, sim.model.vertex_faces.corner)
    f_tile = np.searchsorted(tile_ch, np.repeat(np.arange(nch), np.diff(p.fc_ptr)),
                             'right') - 1
    face_owner = np.full(sim.mesh.n_faces, -1)
    vf_ptr, vf_face = sim.model.vertex_faces.ptr, sim.model.vertex_faces.face
    for t in range(len(tile_ch)):                          # the last one: the seam
        for g in np.nonzero(g_tile == t)[0]:
            owner[base[g]:base[g] + size[g]] = g
        face_owner[p.fc_slot[f_tile == t]] = p.fc_face[f_tile == t]
        for j in gl_vert[gl_ptr[t]:gl_ptr[t + 1]]:
            e = np.arange(tr_ptr[j], tr_ptr[j + 1])
            g = group_of[e]
            assert np.array_equal(owner[slot_of[e][g >= 0]], g[g >= 0])
            assert np.array_equal(slot_of[e][g < 0], pos_of[e][g < 0])
            q = np.arange(vf_ptr[j], vf_ptr[j + 1])
            assert np.array_equal(face_owner[vf_row[q] // 3], vf_face[q])
    # slots are reused (without the rings: 1.0; an irregular sheet's lane groups gather
    # vertices of one fan shape from windows of lanes.FAN_WINDOW vertices, so tiles
    # smaller than that recycle none of their slots, and larger ones fewer)
    if name == 'regular' or tile >= FAN_WINDOW:
        assert (base + size).max() < (0.7 if name == 'regular' else 0.9) * g_ptr[-1]
        assert p.fc_slot.max() < 0.7 * sim.mesh.n_faces


@pytest.mark.slow
@pytest.mark.parametrize('phi', [0.0, 1e-3])
def test_large_meshes_step_tiled_whatever_the_material(monkeypatch, phi):
    calls = []
    for name in ('run_tiled', 'run_tiled_coupled', 'run_two_pass', 'run_two_pass_coupled',
                 'run_region', 'run_region_coupled'):
        real = getattr(fast_step, name)
        monkeypatch.setattr(fast_step, name,
                            lambda *a, _real=real, _name=name: calls.append(_name) or _real(*a))
    side = int(np.ceil(np.sqrt(FUSE_MIN_VERTICES)))
    suffix = '_coupled' if phi else ''
    # small meshes: all steps of a call in one parallel region where every iteration gets
    # a thread and a CPU of its own (test_one_region_only_where_every_iteration_gets_a_cpu)
    small = ('run_region' if workshare.start_threads() in ('omp', 'workqueue')
             and nb.get_num_threads() <= workshare.usable_cpus() else 'run_two_pass')
    for side_n, expect in ((side, 'run_tiled'), (20, small)):
        sim = ClothSimulator(grid_mesh(side_n, side_n), Material(zeta=20.0, xi=1e-3, phi=phi,
                                                                 density=0.2),
                             dt=1e-5, check_dt=False)
        sim.step(1)
        assert calls[-1] == expect + suffix
        assert steps_tiled(sim.mesh.n_vertices) == (expect == 'run_tiled')


@pytest.mark.slow
@pytest.mark.parametrize('name', ['regular', 'alternating', 'irregular', 'icosphere'])
def test_the_vertex_pass_reads_each_face_rest_shape_from_a_table_of_the_distinct_ones(name):
    # the faces' corners in chunk order (uint32) and a row per face in a table of the
    # distinct (Dinv, area) pairs, with the very bits of the face's own: the same forces,
    # from a few dozen rows on a structured sheet
    sim = _replanned(_mesh(name, 41), 32, 2, True)
    p, f = sim.solver.plan, sim.model.faces
    fc_face = p.fc_face.astype(np.int64)
    assert p.fc_vert.dtype == p.fc_tpl.dtype == np.uint32
    assert np.array_equal(p.fc_vert, sim.mesh.faces[fc_face])
    assert np.array_equal(p.t_dinv[p.fc_tpl].view(np.int64), f.dinv[fc_face].view(np.int64))
    assert np.array_equal(p.t_area[p.fc_tpl].view(np.int64), f.area[fc_face].view(np.int64))
    rows = np.concatenate([p.t_dinv.reshape(-1, 4), p.t_area[:, None]], axis=1).view(np.int64)
    assert len(np.unique(rows, axis=0)) == len(rows)
    # rows in order of first use: the stream reads the table front to back
    assert np.all(np.diff(np.maximum.accumulate(p.fc_tpl.astype(np.int64))) <= 1)
    if name in ('regular', 'alternating'):
        assert len(rows) <= 64


@pytest.mark.slow
@pytest.mark.parametrize('phi', [0.0, 1e-3])
def test_a_tiled_simulator_computes_its_force_outside_the_step_from_its_own_slots(phi):
    # its force outside the step (critical dt, internal_forces) runs the two-pass vertex
    # pass, whose corner gradients must go to each face's own row, not to the tiled step's
    # ring slots
    side = int(np.ceil(np.sqrt(FUSE_MIN_VERTICES)))
    sim = _shaken(ClothSimulator(grid_mesh(side, side, pattern='irregular', seed=1),
                                 Material(zeta=20.0, xi=1e-3, phi=phi, density=0.2), dt=1e-4,
                                 check_dt=False), amp=0.002)
    assert sim.solver.tiled and sim.solver.force_plan is not sim.solver.plan
    ref = explicit.internal_force_reference(sim.model, sim.coefficients, sim.state.x)
    assert np.abs(sim.internal_forces() - ref).max() <= 1e-12 * np.abs(ref).max()


def test_state_tuples_copy_and_assign():
    s = State.at_rest(np.ones((3, 3)))
    c = s.copy()
    c.x[0, 0] = 5.0
    assert s.x[0, 0] == 1.0
    s.assign(c)
    assert s.x[0, 0] == 5.0 and s.x is not c.x


def test_the_fast_passes_import_no_solver():
    # layering: core/solvers/explicit.py drives fast/, which calls the update of
    # core/update.py; fast/ imports nothing from core/solvers, so the two never import
    # each other
    import ast
    here = os.path.dirname(fast_step.__file__)
    for name in sorted(os.listdir(here)):
        if name.endswith('.py'):
            tree = ast.parse(open(os.path.join(here, name)).read())
            for node in ast.walk(tree):
                if isinstance(node, ast.ImportFrom):
                    assert 'solvers' not in (node.module or ''), (name, node.module)
