"""``make bench``'s node parts: the installed ``cloth_node`` started as ``ros2 run`` does
(time to its first mesh, cold and warm; mesh rate and real-time factor alone and beside
busy processes; the CPU it uses while paused) and the library's step on a shared machine
(:func:`part_busy_step`). :mod:`.bench` runs them after its step parts; the camera part
(:mod:`.bench_camera`) starts the node through :func:`run_node`."""
from __future__ import annotations

import os
import subprocess
import sys
import tempfile
import time

import numba
import numpy as np

from . import peer_mujoco as peer
from ..core.mesh import grid_mesh
from ..core.simulator import ClothSimulator, Material
from .bench import DT_FRACTION, SCENE, _table, step_rtf, sustained_rtf

__all__ = ['run_node', 'part_node', 'part_busy_step', 'busy_processes', 'stop']


def _node_params(path: str, n: int, material: Material, dt: float, pinned,
                 solver: str = 'explicit'):
    with open(path, 'w') as fh:
        fh.write(f"""cloth_node:
  ros__parameters:
    mesh: {{nx: {n}, ny: {n}}}
    material: {{zeta: {material.zeta!r}, xi: {material.xi!r}, phi: {material.phi!r},
                density: {material.density!r}, damping: {material.damping!r}}}
    dt: {float(dt)!r}
    solver: {solver}
    publish_rate: 30.0
    pinned: {{sets: [{', '.join(pinned)}]}}
    status_period: 0.0
""")


def _cpu_seconds(pid: int) -> float:
    """User + system CPU time of process ``pid`` so far [s] (/proc/<pid>/stat)."""
    with open(f'/proc/{pid}/stat') as fh:
        fields = fh.read().rsplit(')', 1)[1].split()
    return (int(fields[11]) + int(fields[12])) / os.sysconf('SC_CLK_TCK')


def busy_processes(k: int) -> list:
    """``k`` processes that each spin on a core until killed (a shared machine)."""
    return [subprocess.Popen([sys.executable, '-c', 'while True: pass']) for _ in range(k)]


def stop(procs) -> None:
    for p in procs:
        p.kill()
        p.wait()


def run_node(params: str, watch_s: float, env=None, busy: int = 0,
             paused_s: float = 0.0):
    """Start the installed cloth_node as ``ros2 run`` does; return (seconds from process
    start to the first mesh message, mesh messages per second, real-time factor from the
    energy topic's sim_time over ``watch_s`` s after the first message, and the share of
    one core the node used over ``paused_s`` s paused, or nan). ``busy``: that many other
    processes spin on a core each during the watch (a shared machine)."""
    import rclpy
    from ament_index_python.packages import get_package_prefix
    from diagnostic_msgs.msg import DiagnosticArray
    from rclpy.context import Context
    from rclpy.executors import SingleThreadedExecutor
    from visualization_msgs.msg import MarkerArray

    exe = os.path.join(get_package_prefix('cosserat_ros'), 'lib', 'cosserat_ros', 'cloth_node')
    ctx = Context()
    rclpy.init(context=ctx)
    node = rclpy.create_node('bench_client', context=ctx)
    ex = SingleThreadedExecutor(context=ctx)
    ex.add_node(node)
    meshes, energies = [], []
    # raw: counting the meshes must not cost the machine a Python deserialisation each
    node.create_subscription(MarkerArray, '/cloth_node/mesh',
                             lambda m: meshes.append(time.monotonic()), 10, raw=True)

    def on_energy(msg):
        vals = {kv.key: kv.value for kv in msg.status[0].values}
        energies.append((time.monotonic(), float(vals['sim_time'])))
    node.create_subscription(DiagnosticArray, '/cloth_node/energy', on_energy, 10)
    t0 = time.monotonic()
    proc = subprocess.Popen([exe, '--ros-args', '--params-file', params], env=env,
                            stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True)
    try:
        while not meshes and proc.poll() is None and time.monotonic() - t0 < 300:
            ex.spin_once(timeout_sec=0.01)
        if not meshes:
            raise RuntimeError('cloth_node published no mesh: ' + (proc.stderr.read()
                                                                   if proc.poll() else ''))
        first = meshes[0] - t0
        hogs = busy_processes(busy)
        try:
            end = time.monotonic() + watch_s
            while time.monotonic() < end:
                ex.spin_once(timeout_sec=0.01)
        finally:
            stop(hogs)
        # the first second warms the executor and the step-cost estimate: skip it
        win = [e for e in energies if e[0] >= meshes[0] + 1.0]
        rtf = ((win[-1][1] - win[0][1]) / (win[-1][0] - win[0][0])
               if len(win) > 2 else float('nan'))
        rate = (sum(1 for m in meshes if m >= meshes[0] + 1.0) / (watch_s - 1.0)
                if watch_s > 1 else float('nan'))
        paused = float('nan')
        if paused_s > 0:
            from std_srvs.srv import SetBool
            cli = node.create_client(SetBool, '/cloth_node/pause')
            cli.wait_for_service(timeout_sec=10.0)
            fut = cli.call_async(SetBool.Request(data=True))
            ex.spin_until_future_complete(fut, timeout_sec=10.0)
            ex.spin_once(timeout_sec=0.5)
            c0, w0 = _cpu_seconds(proc.pid), time.monotonic()
            while time.monotonic() < w0 + paused_s:
                ex.spin_once(timeout_sec=0.05)
            paused = (_cpu_seconds(proc.pid) - c0) / (time.monotonic() - w0)
    finally:
        proc.terminate()
        try:
            proc.wait(10)
        except subprocess.TimeoutExpired:
            proc.kill()
        ex.shutdown()
        node.destroy_node()
        rclpy.shutdown(context=ctx)
    return first, rate, rtf, paused


def part_node(watch_s: float):
    os.environ.setdefault('ROS_DOMAIN_ID', str(100 + os.getpid() % 100))
    os.environ.setdefault('ROS_AUTOMATIC_DISCOVERY_RANGE', 'LOCALHOST')
    print('\n## node: the installed cloth_node, 40 x 40, publishing at 30 Hz\n')
    import yaml
    from ament_index_python.packages import get_package_share_directory
    from ..ros.params import pin_set
    # the demo as shipped (the installed config/cloth.yaml), and the square sheet
    with open(os.path.join(get_package_share_directory('cosserat_ros'), 'config',
                           'cloth.yaml')) as fh:
        shipped = yaml.safe_load(fh)['cloth_node']['ros__parameters']
    demo = Material(**shipped['material'])
    demo_pins = shipped['pinned']['sets']
    cases = []
    for name, mat, pinned in (('config/cloth.yaml material and pins', demo, demo_pins),
                              ('square sheet, all edges pinned', SCENE, ['boundary'])):
        mesh = grid_mesh(40, 40)
        # the node's cloth: its critical dt, and stepped alone beside each node run
        probe = ClothSimulator(mesh, mat, dt=1e-5, check_dt=False)
        probe.pin(np.concatenate([pin_set(mesh, p) for p in pinned]))
        probe.gravity = (0.0, 0.0, -peer.GRAVITY)
        crit = probe.critical_dt()
        for dt in sorted({2e-4, round(DT_FRACTION * crit, 7)}):
            if dt <= crit:
                cases.append((name, mat, pinned, dt, crit, probe, 'explicit'))
    # the implicit solver at 1/60 s on the square sheet (its target: RTF >= 1 at N = 40
    # while the node publishes at 30 Hz); its sheet falls from flat, then hangs settled
    probe = ClothSimulator(grid_mesh(40, 40), SCENE, dt=1 / 60, check_dt=False,
                           solver='implicit')
    probe.pin(pin_set(probe.mesh, 'boundary'))
    probe.gravity = (0.0, 0.0, -peer.GRAVITY)
    cases.append(('square sheet, all edges pinned, implicit solver', SCENE, ['boundary'],
                  1 / 60, crit, probe, 'implicit'))
    with tempfile.TemporaryDirectory() as tmp:
        params = os.path.join(tmp, 'p.yaml')
        _node_params(params, 40, demo, 2e-4, demo_pins)
        cold_env = dict(os.environ, NUMBA_CACHE_DIR=os.path.join(tmp, 'numba-cache'))
        cold = run_node(params, 0.0, cold_env)[0]
        warm = run_node(params, 0.0, cold_env)[0]
        print(f'Start-up, process start to first mesh message: {cold:.1f} s with an empty '
              f'compile cache (NUMBA_CACHE_DIR pointed at a new directory), {warm:.1f} s '
              'warm (second start, same cache).\n')
        print('"alone before / after": the same cloth stepped in this process for as long '
              'as the node is watched, in calls of one frame\'s steps as the node\'s ticks '
              'step it, right before the node starts and right after it ends: what the '
              'node\'s step allows in the same minute. The node also publishes and waits '
              'for its timer, and keeps real time at most: "node / alone" is its RTF over '
              'the smaller of 1 and the mean of the two (target >= 0.9). "short batches": '
              'the median of five 0.1 s batches before the node, the host\'s best '
              'moments.\n')
        _table(('material / pins', 'dt [s]', 'dt / critical', 'mesh msgs/s', 'RTF',
                'alone before', 'alone after', 'node / alone', 'short batches: RTF',
                'short batches: ms'))
        for name, mat, pinned, dt, crit, probe, solver in cases:
            probe.reset()
            probe.dt = dt
            short_rtf, short_ms = step_rtf(probe)
            before = sustained_rtf(probe, watch_s)
            _node_params(params, 40, mat, dt, pinned, solver)
            _, rate, rtf, _ = run_node(params, watch_s)
            after = sustained_rtf(probe, watch_s)
            print(f'| {name} | {dt:.3g} | {dt / crit:.2f} | {rate:.1f} | {rtf:.3f} | '
                  f'{before:.2f} | {after:.2f} | '
                  f'{rtf / min(1.0, 0.5 * (before + after)):.2f} | '
                  f'{short_rtf:.2f} | {short_ms:.3f} |', flush=True)
        shipped_file = os.path.join(get_package_share_directory('cosserat_ros'), 'config',
                                    'cloth.yaml')
        print('\nThe shipped config/cloth.yaml on a shared machine: the node alone, then '
              'with one and with two other processes spinning on a core each all the time '
              '(targets: at least 60% and 40% of the RTF alone), and the CPU it uses '
              'paused (target: under 5% of a core).\n')
        _table(('case', 'mesh msgs/s', 'RTF', 'RTF / alone', 'paused: share of a core'))
        _, rate0, rtf0, paused = run_node(shipped_file, watch_s, paused_s=5.0)
        print(f'| alone | {rate0:.1f} | {rtf0:.3f} | 1 | {paused:.3f} |', flush=True)
        for k, label in ((1, 'one busy process'), (2, 'two busy processes')):
            _, rate1, rtf1, _ = run_node(shipped_file, watch_s, busy=k)
            print(f'| {label} beside it | {rate1:.1f} | {rtf1:.3f} | {rtf1 / rtf0:.2f} '
                  '| |', flush=True)
        part_busy_step(watch_s)
        # the implicit solver's demo: real fabric with the implicit solver at frame-rate steps
        denim = os.path.join(get_package_share_directory('cosserat_ros'), 'config',
                             'denim.yaml')
        with open(denim) as fh:
            p = yaml.safe_load(fh)['cloth_node']['ros__parameters']
        _, rate, rtf, _ = run_node(denim, watch_s)
        print(f"\nThe shipped config/denim.yaml ({p['material']['preset']}, "
              f"{p['mesh']['nx']} x {p['mesh']['ny']}, solver {p['solver']} with "
              f"{p['solver.iterations']} Newton iteration(s) a step at dt = {p['dt']:.4g} s; "
              f'the watch holds its swing down from flat): {rate:.1f} mesh messages a second, '
              f'RTF {rtf:.3f}.', flush=True)


def part_busy_step(seconds: float, n: int = 40):
    """The library's step on a shared machine: ``ClothSimulator.step`` of the shipped
    cloth (config/cloth.yaml's material, n x n) in calls of one 30 Hz frame's steps for
    ``seconds`` s, alone and beside one and two busy processes, with ``threads='auto'``
    (the default: core/threads.py) and with all of numba's threads fixed; each as its
    speed over the speed alone (auto alone). Targets: 0.6 beside one, 0.4
    beside two."""
    import yaml
    from ament_index_python.packages import get_package_share_directory
    from ..ros.params import pin_set
    with open(os.path.join(get_package_share_directory('cosserat_ros'), 'config',
                           'cloth.yaml')) as fh:
        shipped = yaml.safe_load(fh)['cloth_node']['ros__parameters']
    sim = ClothSimulator(grid_mesh(n, n), Material(**shipped['material']),
                         dt=shipped['dt'], check_dt=False)
    sim.pin(np.concatenate([pin_set(sim.mesh, p) for p in shipped['pinned']['sets']]))
    sim.gravity = (0.0, 0.0, -peer.GRAVITY)
    most = numba.get_num_threads()
    print(f'\nThe library\'s step on a shared machine: ClothSimulator.step, {n} x {n}, '
          f'config/cloth.yaml\'s material, in calls of one 30 Hz frame\'s steps for '
          f'{seconds:g} s per case; speed over the speed alone with threads=\'auto\' '
          '(targets: 0.6 beside one busy process, 0.4 beside two).\n')
    _table(('threads', 'busy processes', 'ms per step', 'speed / alone (auto)'))
    base = None
    for busy in (0, 1, 2):
        for threads in ('auto', most):
            sim.reset()
            sim.threads = threads
            sim._tuner = None                       # measured afresh in each case
            hogs = busy_processes(busy)
            try:
                time.sleep(0.2)
                rtf = sustained_rtf(sim, seconds)
            finally:
                stop(hogs)
            ms = 1e3 * sim.dt / rtf
            if base is None:
                base = ms
            print(f'| {threads} | {busy} | {ms:.3f} | {base / ms:.2f} |', flush=True)
    sim.threads = 'auto'

