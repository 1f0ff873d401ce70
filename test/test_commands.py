"""The node's pure functions for commands and parameters, and its pacing helpers: the
limits a peer cannot walk around (rows, totals per vertex, layouts, far points), the
closest-point grid against its brute-force reference, strict parameter files."""
import numpy as np
import pytest
from std_msgs.msg import Float64MultiArray, MultiArrayDimension

from cosserat_ros.core.mesh import grid_mesh
from cosserat_ros.core.surface_query import closest_points, closest_points_brute
from cosserat_ros.ros import commands
from cosserat_ros.ros.commands import CommandError
from cosserat_ros.ros.pacing import ThreadTuner
from cosserat_ros.ros.params import (check_dt, ConfigError, MIN_DT, node_sections,
                                     params_files, unknown_parameters)


def msg(values, dims=()):
    m = Float64MultiArray()
    m.data = [float(v) for v in np.ravel(values)]
    m.layout.dim = [MultiArrayDimension(label=str(i), size=s, stride=st)
                    for i, (s, st) in enumerate(dims)]
    return m


def test_force_rows_take_packed_layouts_only():
    data = np.arange(8.0) * 0.1
    assert commands.force_rows(msg(data), 4, 10.0).shape == (2, 4)
    assert commands.force_rows(msg(data, [(2, 8), (4, 4)]), 4, 10.0).shape == (2, 4)
    assert commands.force_rows(msg(data, [(2, 0), (4, 0)]), 4, 10.0).shape == (2, 4)
    assert commands.force_rows(msg(data, [(8, 8)]), 4, 10.0).shape == (2, 4)
    for dims, why in (([(7, 7)], 'does not describe'),             # 1-D size != data
                      ([(8, 3)], 'does not describe'),             # 1-D odd stride
                      ([(2, 8), (4, 5)], 'packed'),                # arbitrary stride
                      ([(2, 9), (4, 4)], 'packed'),
                      ([(1, 8), (8, 8)], 'packed'),
                      ([(2, 8), (2, 4), (2, 2)], 'dimensions')):
        with pytest.raises(CommandError, match=why):
            commands.force_rows(msg(data, dims), 4, 10.0)


def test_rows_per_message_are_bounded():
    ok = np.zeros((commands.MAX_ROWS, 4))
    assert len(commands.force_rows(msg(ok), 4, 10.0)) == commands.MAX_ROWS
    with pytest.raises(CommandError, match='at most'):
        commands.force_rows(msg(np.zeros((commands.MAX_ROWS + 1, 4))), 4, 10.0)
    # the serialised size limit of the node's raw subscription admits the largest message
    from rclpy.serialization import serialize_message
    full = msg(np.zeros((commands.MAX_ROWS, 6)), [(commands.MAX_ROWS, 0), (6, 0)])
    assert len(serialize_message(full)) <= commands.MAX_FORCE_BYTES
    over = msg(np.zeros((commands.MAX_ROWS + 50, 6)))
    assert len(serialize_message(over)) > commands.MAX_FORCE_BYTES


def test_max_force_bounds_the_total_on_a_vertex():
    n = 100
    # 1,000 rows of 10 N on one vertex: each row is within max_force, their sum is not
    rows = np.tile([7.0, 0.0, 0.0, 10.0], (1000, 1))
    idx, f = commands.vertex_forces(commands.force_rows(msg(rows), 4, 10.0), n)
    with pytest.raises(CommandError, match='vertex 7 add up to 1e\\+04 N'):
        commands.check_totals(idx, f, n, 10.0)
    # opposite rows cancel; rows on different vertices do not add
    commands.check_totals(np.array([3, 3]), np.array([[0, 0, 9.0], [0, 0, -9.0]]), n, 10.0)
    commands.check_totals(np.arange(50), np.tile([0, 0, 10.0], (50, 1)), n, 10.0)
    with pytest.raises(CommandError):
        commands.check_totals(np.array([3, 3]), np.array([[0, 0, 6.0], [0, 0, 6.0]]), n,
                              10.0)


def test_point_forces_refuse_points_far_from_the_cloth():
    m = grid_mesh(6, 6)
    x = m.vertices
    rows = np.array([[0.5, 0.5, 0.1, 0, 0, 1.0]])
    idx, f = commands.point_forces(rows, x, m.faces)
    assert f.sum(axis=0) == pytest.approx([0, 0, 1.0])
    for far in (1e200, -3.0, 5.0):
        with pytest.raises(CommandError, match='row 1: point'):
            commands.point_forces(np.array([rows[0], [far, 0.5, 0, 0, 0, 1.0]]), x, m.faces)


@pytest.mark.parametrize('pattern', ['regular', 'alternating', 'irregular'])
def test_closest_point_grid_agrees_with_brute_force(pattern):
    rng = np.random.default_rng(1)
    m = grid_mesh(30, 20, 1.5, 1.0, pattern, 4)
    x = m.vertices.copy()
    x[:, 2] = 0.3 * np.sin(4 * x[:, 0]) * np.cos(3 * x[:, 1])
    crumpled = x + 0.01 * rng.standard_normal(x.shape)       # stretched, uneven triangles
    for cloth in (x, crumpled):
        pts = np.concatenate([cloth[rng.integers(0, len(cloth), 300)]
                              + 0.01 * rng.standard_normal((300, 3)),
                              rng.uniform(-1.0, 2.5, (300, 3)),
                              [[40.0, -30.0, 7.0], [0.75, 0.5, 0.0]]])
        got = closest_points(cloth, m.faces, pts)
        ref = closest_points_brute(cloth, m.faces, pts)

        def dist(tri, bary):
            q = np.einsum('kj,kjc->kc', bary, cloth[m.faces[tri]])
            return np.linalg.norm(q - pts, axis=1)
        assert np.allclose(got[1].sum(axis=1), 1.0) and np.all(got[1] >= 0)
        np.testing.assert_allclose(dist(*got), dist(*ref), rtol=0, atol=1e-12)


def test_dt_has_a_floor():
    assert check_dt(2e-4, 1e-3) == 2e-4
    with pytest.raises(ConfigError, match='below'):
        check_dt(1e-9, 1e-3)
    assert MIN_DT <= 1e-6


def test_parameter_files_are_strict(tmp_path):
    assert unknown_parameters({'dt': 1, 'materal.zeta': 2, 'dtt': 3}, {'dt'}) == [
        'dtt', 'materal.zeta']
    assert params_files(['x', '--ros-args', '--params-file', 'a.yaml', '-p', 'dt:=1',
                         '--params-file', 'b.yaml']) == ['a.yaml', 'b.yaml']
    assert params_files(['--params-file', 'not_ros.yaml']) == []
    f = tmp_path / 'p.yaml'
    f.write_text('cloth_node:\n  ros__parameters:\n    dt: 1.0e-4\n'
                 '/sim/other:\n  ros__parameters: {}\n'
                 'ns:\n  deeper:\n    ros__parameters: {}\n')
    mine, every = node_sections(str(f), '/cloth_node')
    assert mine == ['/cloth_node'] and set(every) == {'/cloth_node', '/sim/other',
                                                     '/ns/deeper'}
    assert node_sections(str(f), '/robot/cloth_node')[0] == []
    assert node_sections(str(f), '/ns/deeper')[0] == ['/ns/deeper']
    f.write_text('/**:\n  ros__parameters:\n    dt: 1.0e-4\n')
    assert node_sections(str(f), '/a/b/cloth_node')[0] == ['/**']
    f.write_text('/**/cloth_node:\n  ros__parameters: {}\n')
    assert node_sections(str(f), '/a/cloth_node')[0] and not node_sections(str(f),
                                                                            '/a/x')[0]


def test_thread_tuner_follows_the_faster_count():
    tuner = ThreadTuner(2, period=2.0)
    t = 0.0
    seen = []

    def tick(cost):                          # cost: thread count -> seconds per step
        nonlocal t
        k = tuner.threads(t)
        tuner.record(k, 100, 100 * cost[k])
        seen.append(k)
        t += 1 / 30
    alone = {2: 0.3e-3, 1: 0.5e-3}
    for _ in range(90):
        tick(alone)
    assert seen[:2] == [2, 1] and tuner.best == 2
    assert seen[2:].count(1) <= 2            # one probe of the other count per 2 s
    shared = {2: 3e-3, 1: 0.6e-3}            # one busy process beside the node
    seen.clear()
    for _ in range(150):
        tick(shared)
    assert tuner.best == 1 and seen[-30:].count(1) >= 29
    seen.clear()
    for _ in range(150):                      # the load goes away: back to all threads
        tick(alone)
    assert tuner.best == 2 and seen[-30:].count(2) >= 29
    assert ThreadTuner(1).threads(0.0) == 1
