"""Clients on simulation time: stamped handle targets, ``~/rejections``, the node's
``real_time_factor``, and the demos giving the same result at any real-time factor.

The busy host is forced with the node's own ``real_time_factor`` parameter (the node then
advances that many simulation seconds per wall second), which reproduces what a client
meets on a loaded machine: a node slower than real time."""
import math
import os
import subprocess
import time

import numpy as np
import pytest
from ament_index_python.packages import get_package_share_directory
from diagnostic_msgs.msg import DiagnosticStatus
from geometry_msgs.msg import PoseStamped, Vector3Stamped
from std_srvs.srv import SetBool

from test_node import Harness
from test_node_process import ros2_run


def _pose(p, q=(0.0, 0.0, 0.0, 1.0), at=0.0):
    m = PoseStamped()
    m.header.frame_id = 'world'
    ns = int(round(at * 1e9))
    m.header.stamp.sec, m.header.stamp.nanosec = ns // 10 ** 9, ns % 10 ** 9
    m.pose.position.x, m.pose.position.y, m.pose.position.z = (float(c) for c in p)
    (m.pose.orientation.x, m.pose.orientation.y, m.pose.orientation.z,
     m.pose.orientation.w) = (float(c) for c in q)
    return m


@pytest.fixture
def held():
    """A node with handle ``left`` holding a corner of the cloth, a peer publishing its
    targets and following ~/rejections; yields (harness, target publisher, rejections,
    the handle's id, its position at the grasp)."""
    h = Harness(**{'handles.names': ['left'], 'handles.left.radius': 0.08,
                   'pinned.sets': ['none'], 'pinned.indices': [-1], 'gravity': [0.0, 0.0, 0.0]})
    target = h.peer.create_publisher(PoseStamped, '/cloth_node/handles/left/target', 50)
    grasp = h.peer.create_client(SetBool, '/cloth_node/handles/left/grasp')
    rejections = []
    h.peer.create_subscription(DiagnosticStatus, '/cloth_node/rejections',
                               rejections.append, 50)
    try:
        assert h.spin_until(lambda: len(h.meshes) > 0, 30)
        assert grasp.wait_for_service(timeout_sec=10)
        corner = h.node.mesh.vertices[np.argmax(h.node.mesh.vertices @ [-1, 1, 0])]
        target.publish(_pose(corner))
        assert h.spin_until(lambda: h.node._handles['left']['target'] is not None, 5)
        fut = grasp.call_async(SetBool.Request(data=True))
        assert h.spin_until(fut.done, 10) and fut.result().success
        yield h, target, rejections, h.node._handles['left']['id'], corner
    finally:
        h.close()


def test_stamped_targets_streamed_ahead_are_reached_each_on_time(held):
    """Twelve targets on a circle (0.2 m/s), stamped 0.5-1.6 s of sim time ahead and sent
    at once (all kept: none lost to a shallow reader queue): the handle is at each when sim
    time first reaches its stamp, within one
    step's motion, and nothing is refused. Logged after every compiled call (the
    handles' settle)."""
    h, target, rejections, hid, corner = held
    handles = h.node.sim._handles
    log = []
    settle = handles.settle

    def logged(t):
        settle(t)
        log.append((t, handles._item(hid).position.copy()))
    handles.settle = logged
    t0 = h.node.sim.time + 0.5
    period = 0.1
    radius = 0.2 * period / (2 * math.sin(math.pi / 12))        # chord 2 cm per 0.1 s
    centre = corner + [radius, 0.0, 0.0]
    way = [(t0 + k * period,
            centre + radius * np.array([-math.cos(2 * math.pi * k / 12),
                                        math.sin(2 * math.pi * k / 12), 0.0]))
           for k in range(12)]
    for t, p in way:
        target.publish(_pose(p, at=t))
    assert h.spin_until(lambda: len(h.node.sim.handle_waypoints(hid)) == 13, 10), \
        h.node.sim.handle_waypoints(hid)
    last = way[-1][0]
    assert h.spin_until(lambda: h.node.sim.time > last + 0.05, 120)
    assert not rejections, [(r.name, r.message) for r in rejections]
    dt = h.node.sim.dt
    for t, p in way:
        first = next(i for i, (tl, _) in enumerate(log) if tl >= t - 1e-12)
        tl, got = log[first]
        assert tl < t + dt, (t, tl)
        assert np.linalg.norm(got - p) <= 0.2 * dt * 1.0001 + 1e-12, (t, got, p)


def test_late_and_too_fast_stamped_targets_are_refused_on_the_rejections_topic(held):
    """A stamp behind sim time and a target too far for its stamp's interval are refused,
    counted, and each published on ~/rejections: the target's topic, the reason and, as
    values, the sim time and the offending stamp, position and speed."""
    h, target, rejections, hid, corner = held
    before = h.node.rejected['handles']
    h.spin_until(lambda: h.node.sim.time > 0.1, 10)
    target.publish(_pose(corner, at=0.05))                     # behind: late
    assert h.spin_until(lambda: len(rejections) == 1, 10)
    r = rejections[0]
    vals = {kv.key: kv.value for kv in r.values}
    assert r.name == '/cloth_node/handles/left/target'
    assert 'late' in r.message and 'not ahead of the simulation time' in r.message
    assert float(vals['stamp']) == pytest.approx(0.05)
    assert float(vals['sim_time']) > 0.05
    now = h.node.sim.time
    far = corner + [0.5, 0.0, 0.0]                             # 0.5 m in 0.1 s: 5 m/s
    target.publish(_pose(far, at=now + 0.1))
    assert h.spin_until(lambda: len(rejections) == 2, 10)
    r = rejections[1]
    vals = {kv.key: kv.value for kv in r.values}
    assert 'handles.max_speed' in r.message
    assert float(vals['speed']) > h.node._max_handle_speed
    assert float(vals['x']) == pytest.approx(far[0])
    assert h.node.rejected['handles'] == before + 2
    # the same target with a stamp far enough ahead is taken (0.5 m in 1 s: 0.5 m/s)
    target.publish(_pose(far, at=h.node.sim.time + 1.0))
    assert h.spin_until(lambda: len(h.node.sim.handle_waypoints(hid)) == 2, 10)
    assert len(rejections) == 2


def test_refused_wind_is_on_the_rejections_topic():
    h = Harness()                                       # air.enabled false: wind refused
    rejections = []
    h.peer.create_subscription(DiagnosticStatus, '/cloth_node/rejections',
                               rejections.append, 10)
    try:
        msg = Vector3Stamped()
        msg.vector.x = 3.0
        h.send('wind', msg)
        assert h.spin_until(lambda: rejections, 10)
        vals = {kv.key: kv.value for kv in rejections[0].values}
        assert rejections[0].name == '/cloth_node/wind'
        assert 'air.enabled' in rejections[0].message
        assert float(vals['x']) == 3.0
    finally:
        h.close()


@pytest.mark.slow
def test_the_node_never_runs_ahead_of_the_real_time_factor_asked_for():
    """real_time_factor 0.25: over 2 s of wall time the sim advances at most a quarter of
    it (and a tick's share more); an upper bound, which a busy host cannot break."""
    h = Harness(real_time_factor=0.25)
    try:
        assert h.spin_until(lambda: len(h.meshes) > 0, 30)
        t0, w0 = h.node.sim.time, time.monotonic()
        h.spin(2.0)
        sim, wall = h.node.sim.time - t0, time.monotonic() - w0
        assert 0 < sim <= 0.25 * wall + 0.25 * h.node.period + h.node.sim.dt, (sim, wall)
        h.node.set_parameters([rclpy_parameter('real_time_factor', 2.0)])
        assert h.node.pacer.factor == 2.0
    finally:
        h.close()


def rclpy_parameter(name, value):
    from rclpy.parameter import Parameter
    return Parameter(name, value=value)


def _node(config, factor, log):
    """The installed cloth_node with the shipped ``config`` at ``real_time_factor``
    ``factor``, its output to the file ``log`` (a pipe nobody reads would fill, and the
    node would block writing its log)."""
    share = get_package_share_directory('cosserat_ros')
    out = open(log, 'w')
    proc = subprocess.Popen(
        ros2_run('cosserat_ros', 'cloth_node', '--ros-args', '--params-file',
                 os.path.join(share, 'config', config), '-p', f'real_time_factor:={factor}'),
        stdout=out, stderr=subprocess.STDOUT, text=True, cwd=share)
    out.close()
    proc.log = log
    return proc


def _stop(proc):
    """SIGINT the node; its (exit code, output), after checking it ended cleanly."""
    import signal
    proc.send_signal(signal.SIGINT)
    try:
        proc.wait(timeout=30)
    except subprocess.TimeoutExpired:
        proc.kill()
        proc.wait()
    with open(proc.log) as fh:
        out = fh.read()
    assert 'Traceback' not in out, out
    return proc.returncode, out


@pytest.mark.parametrize('factor', [1.0, 0.2])
@pytest.mark.process
def test_fold_demo_folds_the_cloth_at_any_real_time_factor(factor, tmp_path):
    """The shipped demo end to end (config/fold.yaml in one process, fold_demo in
    another: grasp, a stamped pose stream, release, its own check of the fold from
    ~/points), with the node at full speed and forced to a fifth of real time, where the
    wall-clock stream of the demo's first version was refused as too fast."""
    proc = _node('fold.yaml', factor, tmp_path / 'node.log')
    try:
        # --wait: the node's start-up compiles on a cold cache (minutes on a busy host)
        demo = subprocess.run(ros2_run('cosserat_ros', 'fold_demo', '--wait', '600'),
                              capture_output=True, text=True, timeout=1500)
    finally:
        code, err = _stop(proc)
    assert demo.returncode == 0, demo.stdout + demo.stderr
    assert '100% of the grasped edge' in demo.stdout and 'folded' in demo.stdout
    assert demo.stdout.count('holds') == 2
    assert code == 0, err
    assert 'rejected' not in err                  # every target was taken


def _flag_gusts(factor, duration, log):
    """flag_demo against config/flag.yaml at ``factor``: (exit code, output, the wind
    messages as rows [stamp - first stamp, vx, vy, vz])."""
    import rclpy
    from rclpy.context import Context
    from rclpy.executors import SingleThreadedExecutor
    ctx = Context()
    rclpy.init(context=ctx)
    peer = rclpy.create_node('gust_listener', context=ctx)
    got = []
    peer.create_subscription(Vector3Stamped, '/cloth_node/wind', got.append, 1000)
    ex = SingleThreadedExecutor(context=ctx)
    ex.add_node(peer)
    proc = _node('flag.yaml', factor, log)
    try:
        demo = subprocess.Popen(ros2_run('cosserat_ros', 'flag_demo', '--duration',
                                         str(duration), '--wait', '600'),
                                stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
        while demo.poll() is None:
            ex.spin_once(timeout_sec=0.05)
        end = time.monotonic() + 2.0
        while time.monotonic() < end:                 # the last messages in flight
            ex.spin_once(timeout_sec=0.05)
        out, err = demo.communicate()
    finally:
        code, node_err = _stop(proc)
        assert code == 0, node_err
        assert 'rejected' not in node_err           # every gust was taken
        ex.shutdown()
        peer.destroy_node()
        rclpy.shutdown(context=ctx)
    rows = np.array([[m.header.stamp.sec + 1e-9 * m.header.stamp.nanosec,
                      m.vector.x, m.vector.y, m.vector.z] for m in got])
    rows[:, 0] -= rows[0, 0]
    return demo.returncode, out + err, rows


@pytest.mark.process
def test_flag_demo_flies_the_same_gusts_in_sim_time_at_any_real_time_factor(tmp_path):
    """The wind messages flag_demo sends (recorded by a third process) have the same
    stamps, relative to the first, and values at full speed and at a fifth of real time:
    one per 1/30 s of simulation time, gust(t) at each; the flag flies (the demo's own
    check: its free edge out downwind and swinging across it) in both."""
    duration = 3.0
    runs = [_flag_gusts(f, duration, tmp_path / f'node-{f}.log') for f in (1.0, 0.2)]
    for code, out, rows in runs:
        assert code == 0, out
        assert 'flew' in out and 'NOT' not in out, out
        assert len(rows) == round(30 * duration), len(rows)
    (_, _, fast), (_, _, slow) = runs
    np.testing.assert_allclose(fast[:, 0], np.arange(len(fast)) / 30.0, atol=2e-9)
    np.testing.assert_allclose(slow, fast, rtol=0, atol=2e-9)
    assert np.ptp(fast[:, 1]) > 1.0                     # gusts, not a steady wind
