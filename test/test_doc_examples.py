"""The manual's rclpy examples, extracted from the pages and run as written against the
installed node (a process of its own, as `make run` starts it)."""
import os
import re
import subprocess
import sys

import pytest

from test_sim_time import _node, _stop

# the examples run against a node process (make test, not test-fast)
pytestmark = pytest.mark.process

HERE = os.path.dirname(os.path.abspath(__file__))
DOC = os.path.join(os.path.dirname(HERE), 'doc')


def _block(page: str, marker: str) -> str:
    """The one ```python block of doc/``page`` that contains ``marker``."""
    text = open(os.path.join(DOC, page)).read()
    blocks = [b for b in re.findall(r'```python\n(.*?)```', text, flags=re.S) if marker in b]
    assert len(blocks) == 1, (page, marker, len(blocks))
    return blocks[0]


def test_the_grasp_example_of_the_handles_page_grasps_lifts_and_lets_go(tmp_path):
    """doc/handles.md, "Grasp from your own node", against config/fold.yaml: the handle
    takes the vertices within its radius of the corner, holds the lifted corner up (a
    positive vertical force, less than the whole cloth's weight, 0.6 x 0.6 m at 0.2
    kg/m^2: 0.71 N) and releases it."""
    script = _block('handles.md', "create_node('grasper'")
    proc = _node('fold.yaml', 1.0, tmp_path / 'node.log')
    try:
        out = subprocess.run([sys.executable, '-c', script], capture_output=True, text=True,
                             timeout=900)
    finally:
        code, log = _stop(proc)
    assert out.returncode == 0, out.stdout + out.stderr
    lines = out.stdout.strip().splitlines()
    assert re.fullmatch(r'left holds \d+ vertices', lines[0]), lines
    force = float(re.search(r'with (-?[\d.]+) N', lines[1]).group(1))
    assert 0.0 < force < 0.6 * 0.6 * 0.2 * 9.81, lines
    assert lines[2] == 'left released', lines
    assert code == 0 and 'rejected' not in log, log


def test_the_readme_push_example_pushes_the_cloth(tmp_path):
    """README.md, "Push it from your own node", against config/cloth.yaml (the 40 x 40
    cloth of `make run`): the forces and the field it streams are taken (no refusal in
    the node's log) and do work on the cloth (``external_work`` in ~/energy grows). The
    example spins until stopped; the test stops it once the work is seen."""
    import signal
    import rclpy
    from rclpy.context import Context
    from rclpy.executors import SingleThreadedExecutor
    from diagnostic_msgs.msg import DiagnosticArray
    from test_node_process import spin_until
    readme = open(os.path.join(os.path.dirname(HERE), 'README.md')).read()
    blocks = [b for b in re.findall(r'```python\n(.*?)```', readme, flags=re.S)
              if "create_node('pusher')" in b]
    assert len(blocks) == 1
    proc = _node('cloth.yaml', 1.0, tmp_path / 'node.log')
    ctx = Context()
    rclpy.init(context=ctx)
    node = rclpy.create_node('watcher', context=ctx)
    ex = SingleThreadedExecutor(context=ctx)
    ex.add_node(node)
    work = []
    node.create_subscription(DiagnosticArray, '/cloth_node/energy', lambda m: work.append(
        float(next(kv.value for kv in m.status[0].values if kv.key == 'external_work'))), 10)
    example = subprocess.Popen([sys.executable, '-c', blocks[0]], stdout=subprocess.PIPE,
                               stderr=subprocess.STDOUT, text=True)
    try:
        assert spin_until(ex, lambda: work and work[-1] > 0.01, 900), work[-3:]
    finally:
        example.send_signal(signal.SIGINT)
        try:
            example.wait(timeout=30)
        except subprocess.TimeoutExpired:
            example.kill()
        ex.shutdown()
        node.destroy_node()
        rclpy.shutdown(context=ctx)
        code, log = _stop(proc)
    assert code == 0 and 'rejected' not in log, log
