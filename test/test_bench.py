"""The benchmark's own pieces: our row, the peer scene (MuJoCo, when installed)."""
import math
import time
import xml.etree.ElementTree as ET

import numpy as np
import pytest

from cosserat_ros.tools import bench, peer_mujoco as peer

# the bench tier: MuJoCo and the benchmark's parts (make test, not test-fast)
pytestmark = pytest.mark.bench


def test_our_row_is_measured():
    r = bench.bench(8, batch_s=0.02, repeats=3)
    assert r['vertices'] == 81 and r['ms'] > 0 and r['steps_s'] == pytest.approx(1e3 / r['ms'])
    assert r['dt'] == pytest.approx(bench.DT_FRACTION * r['crit_dt'])
    assert 1000 < r['bytes_per_vertex'] < 20000


def test_step_alone_rtf_is_dt_over_the_measured_step():
    sim = bench.scene_simulator(8)
    steps = sim.step_count
    rtf, ms = bench.step_rtf(sim, batch_s=0.01, repeats=3, warmup_s=0.02)
    assert ms > 0 and rtf == pytest.approx(sim.dt / (ms * 1e-3))
    assert sim.step_count > steps + 3        # it really stepped: warm-up and 3 batches


def test_sustained_rtf_steps_in_calls_of_one_frame_for_the_time_asked(monkeypatch):
    """The node's 'alone' reference steps as the node's ticks do: calls of one frame's
    steps, for as long as the node is watched; RTF = sim time over wall time."""
    sim = bench.scene_simulator(8)
    calls = []
    step = sim.step
    monkeypatch.setattr(sim, 'step', lambda k: (calls.append(k), step(k)))
    t = time.perf_counter()
    rtf = bench.sustained_rtf(sim, 0.05)
    wall = time.perf_counter() - t
    k = round(1.0 / 30.0 / sim.dt)
    assert set(calls) == {k} and len(calls) >= 2 and wall >= 0.05
    # the warm-up call is left out of the rate, so the rate is at least the whole call's
    assert rtf >= (len(calls) - 1) * k * sim.dt / wall


def test_peer_scene_has_the_issue_material():
    root = ET.fromstring(peer.scene_xml(10, 'Euler', 2e-4))
    fc = root.find('./worldbody/flexcomp')
    el = fc.find('elasticity')
    young, h = float(el.get('young')), float(el.get('thickness'))
    nu = float(el.get('poisson'))
    assert young * h == pytest.approx(peer.YOUNGS_2D)
    assert young * h ** 3 / (12 * (1 - nu ** 2)) == pytest.approx(peer.BENDING)
    assert fc.get('count') == '11 11 1' and fc.get('dim') == '2'
    # every vertex carries density * spacing^2, like our interior vertices
    assert float(fc.get('mass')) / 11 ** 2 == pytest.approx(peer.DENSITY / 10 ** 2)
    assert len(fc.findall('pin')) == 4
    assert root.find('option').get('integrator') == 'Euler'


def test_both_engines_sag_alike():
    pytest.importorskip('mujoco')
    ours = bench.settled_sag(10)
    theirs = peer.settled_sag(10, 'Euler', 2e-4, bench.SETTLE_TIME, bench.SETTLE_RATE)
    assert math.isfinite(theirs)
    assert abs(ours - theirs) < 0.01 * theirs
    assert 0.03 < ours < 0.04
    # the implicit solver, converged and linearised, at 1/60 s: the same statics
    for iterations in (20, 1):
        assert bench.settled_sag(10, 'implicit', iterations) == pytest.approx(ours, rel=1e-3)


def test_paired_ratio_is_measured():
    pytest.importorskip('mujoco')
    r = bench.paired_ratio(6, pairs=3, batch_s=0.01)
    assert math.isfinite(r) and r > 0


def test_shared_peer_model_takes_each_runs_settings():
    mujoco = pytest.importorskip('mujoco')
    fresh = mujoco.MjModel.from_xml_string(peer.scene_xml(6, 'discrete', 3e-4))
    peer.build(6, 'Euler', 1e-4, damping_rate=5.0)          # a run with other settings
    model, data = peer.build(6, 'discrete', 3e-4)
    assert model.opt.timestep == fresh.opt.timestep == 3e-4
    assert model.opt.integrator == fresh.opt.integrator == mujoco.mjtIntegrator.mjINT_DISCRETE
    assert (model.dof_damping == fresh.dof_damping).all() and not model.dof_damping.any()
    assert not data.qvel.any() and data.time == 0.0


def test_peer_contact_scene_is_ours():
    # the MuJoCo side of the contact benchmark: the same cloth on the ground, the same
    # six obstacles (plane, five primitives, the 5,120-triangle icosphere); contact off
    # without them
    root = ET.fromstring(peer.contact_xml(10, 3e-4, True))
    geoms = root.findall('./worldbody/geom')
    assert sorted(g.get('type') for g in geoms) == ['box', 'box', 'capsule', 'cylinder',
                                                    'mesh', 'plane', 'sphere']
    fc = root.find('./worldbody/flexcomp')
    assert fc.get('radius') == repr(0.002) and fc.get('pos') == f'0 0 {0.002!r}'
    assert fc.find('contact').get('selfcollide') == 'none'
    assert len(root.find('./asset/mesh').get('face').split()) == 3 * 5120
    assert not fc.findall('pin')
    off = ET.fromstring(peer.contact_xml(10, 3e-4, False))
    assert not off.findall('./worldbody/geom')
    assert off.find('./worldbody/flexcomp/contact').get('contype') == '0'


def test_peer_contact_scene_lies_on_the_ground():
    pytest.importorskip('mujoco')
    run = peer.contact_stepper(10, 3e-4, True)
    run(20)
    assert not run.bad() and run.contacts() > 0


def test_air_scene_is_the_flag_with_and_without_air():
    from cosserat_ros.tools.bench import air_scene
    on, off = air_scene(6, True), air_scene(6, False)
    for sim in (on, off):
        assert np.ptp(sim.mesh.vertices[:, 1]) == 0.0          # upright, in the xz plane
        assert sim.pinned.sum() == 7 and sim.material.density == 0.113
    assert on.air is not None and off.air is None
    c = on.control
    assert (c.f_applied - c.f_external)[:, 0].sum() > 0        # the wind pushes downwind
    assert np.array_equal(off.control.f_applied, off.control.f_external)


def test_implicit_part_runs_both_solvers_on_the_issue6_and_stiff_scenes(capsys):
    from cosserat_ros.tools.bench import ISSUE6, part_implicit, scene_simulator, STIFF
    im = scene_simulator(6, scene=STIFF, solver='implicit')
    ex = scene_simulator(6, scene=STIFF)
    assert im.solver_kind == 'implicit' and im.dt == 1.0 / 60.0
    assert ex.solver_kind == 'explicit' and ex.dt == pytest.approx(0.9 * ex.critical_dt())
    assert STIFF.youngs_2d == 2e3 and ISSUE6.youngs_2d == 500.0
    assert np.array_equal(im.pinned, ex.pinned) and im.pinned.sum() == 24
    # the linearised column's runs are linearised: one Newton iteration a step at most
    lin, its, _, times = bench._implicit_window(6, STIFF, 0.25, iterations=1)
    assert lin.solver_iterations == 1 and lin.solve_report['linearized']
    assert 0 < its <= len(times)
    part_implicit([6], window_s=0.25)
    rows = [l for l in capsys.readouterr().out.splitlines() if l.startswith('| issue6')
            or l.startswith('| stiff')]
    assert len(rows) == 2 and all(float(r.split('|')[6]) > 0 for r in rows)   # RTF
    for r in rows:                       # MuJoCo discrete beside it, and the RTF ratio
        cells = [c.strip() for c in r.split('|')[1:-1]]
        assert len(cells) == 16
        ours_fall, theirs_fall = (c.strip() for c in cells[12].split('/'))
        assert float(ours_fall) > 0 and float(cells[14]) > 0     # the linearised solver
        if peer.available() is None:
            assert cells[9:12] == ['-', '-', '-'] and theirs_fall == '-' and cells[13] == '-'
            assert cells[15] == '-'
        else:
            theirs_ms = 1e3 / 60.0 / float(cells[10])           # from MuJoCo's RTF
            assert float(cells[15]) == pytest.approx(theirs_ms / float(cells[14]), rel=0.02)
            ms, rtf, ratio = (float(c) for c in cells[9:12])
            assert ms > 0 and rtf > 0
            assert ratio == pytest.approx(float(cells[5]) / rtf, rel=0.02)
            assert float(cells[13]) == pytest.approx(float(theirs_fall) / float(ours_fall),
                                                     rel=0.05)


def test_self_part_folds_the_cloth_into_touching_layers_without_stretching_it(capsys):
    mesh = bench.grid_mesh(40, 40)
    th = 2e-3
    x = bench.pleated_positions(mesh, th)
    e = mesh.edges
    rest = np.linalg.norm(np.diff(mesh.vertices[e], axis=1)[:, 0], axis=1)
    now = np.linalg.norm(np.diff(x[e], axis=1)[:, 0], axis=1)
    assert np.all(now <= rest * (1 + 1e-12))                 # chords: never stretched
    assert np.median(now / rest) == pytest.approx(1.0)       # flat away from the folds
    layers = np.unique(np.round((x[:, 2] - th) / (1.5 * th), 6))
    assert x[:, 2].min() == pytest.approx(th) and len(layers) > bench.PLEATS
    assert np.ptp(x[:, 0]) < 1.0 / bench.PLEATS + 2 * th      # one pleat wide
    # a short warm-up: at 12 x 12 the 0.3 s of the bench's is thousands of steps, and
    # the crumpled cloth without self-collision, its layers passed through each other,
    # diverged 0.8 s after the drop in one such run (its kinetic energy leapt from 0.014
    # to 50 J in one step: not self-collision, which that cloth did not have)
    bench.part_self([24], crumpled=[12], pairs=1, batch_s=0.01, warmup_s=0.02)
    out = capsys.readouterr().out.splitlines()
    row = [l for l in out if l.startswith('| 24 |')][0]
    cells = [c.strip() for c in row.split('|')[1:-1]]
    assert float(cells[3]) > 0 and int(cells[6]) > 0         # it stepped; layers touch
    # the crumpled cloth: it stepped, and lies folded on itself (live pairs)
    row = [l for l in out if l.startswith('| 12 |')][0]
    cells = [c.strip() for c in row.split('|')[1:-1]]
    assert float(cells[3]) > 0 and int(cells[7]) > 0


def test_the_crumpled_scene_lies_on_the_ground_folded_onto_itself():
    off, on = bench.crumpled_scenes(12)
    np.testing.assert_array_equal(off.state.x, on.state.x)
    assert not off.self_collision and on.self_collision
    x = on.state.x
    # down on the ground (its centre fell from ~1 m, its lower edge from 0.5 m), above it;
    # a flap may still stand or settle (22 cm up and moving at 1.3 m/s, at 12 x 12)
    assert x[:, 2].mean() < 0.1 and x[:, 2].max() < 0.5 and x[:, 2].min() > 0.0
    assert np.ptp(x[:, 1]) < 0.9                             # the 1 m sheet is folded
    assert on.self_contact_state()['candidates'] > 0
