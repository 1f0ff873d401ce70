"""cosserat_ros.ros.messages: the node's small messages built without a node.

A tool that writes bags without ROS (no rclpy.init, no DDS) builds its messages with this
module, so it must import no node or simulator and its messages must serialise without a
context. CDR leaves the padding between fields as it finds it (not always zeros), so
round trips compare messages, not bytes.
"""
import math
import os
import subprocess
import sys

import numpy as np
import pytest
from rclpy.serialization import deserialize_message, serialize_message
from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus
from geometry_msgs.msg import WrenchStamped
from rosgraph_msgs.msg import Clock
from visualization_msgs.msg import Marker, MarkerArray

from cosserat_ros.ros import messages

STAMP = 3_250_000_001                   # 3 s + 250000001 ns

#: run in a fresh interpreter: no rclpy.init anywhere, and what importing the module loads
_NO_INIT = r'''
import sys
from cosserat_ros.ros import messages
loaded = sorted(k for k in sys.modules
                if k.split('.')[0] in ('rclpy', 'numba', 'scipy', 'trimesh')
                or k.startswith(('cosserat_ros.core', 'cosserat_ros.ros.node',
                                 'cosserat_ros.simulator')))
assert not loaded, loaded
import rclpy
from rclpy.serialization import serialize_message
obstacles = {0: {'name': 'ball', 'shape': 'sphere', 'position': (0.0, 0.0, 1.0),
                 'orientation': (0.0, 0.0, 0.0, 1.0), 'radius': 0.1}}
built = [messages.clock(7), messages.wrench(7, 'world', (1, 2, 3), (4, 5, 6)),
         messages.obstacle_markers(obstacles, None, 7, 'world'),
         messages.status(7, 'world', 'x', b'\x00', 'ok', {'a': 1.0}, '/n'),
         messages.energy_status(7, 'world', {'total': 1.0}, 0.5, 3, None, False, '/n')]
sizes = [len(serialize_message(m)) for m in built]
assert not rclpy.ok()
print(sizes)
'''


@pytest.mark.process
def test_the_module_loads_no_node_and_serialises_without_init():
    # the interpreter finds cosserat_ros where this one did (the installed copy, or the
    # working tree if it comes first on sys.path)
    env = dict(os.environ, PYTHONPATH=os.pathsep.join(p for p in sys.path if p))
    out = subprocess.run([sys.executable, '-c', _NO_INIT], env=env, capture_output=True,
                         text=True, timeout=120, cwd=os.path.dirname(__file__))
    assert out.returncode == 0, out.stderr
    sizes = eval(out.stdout.strip())
    assert len(sizes) == 5 and all(s > 4 for s in sizes)


def _round_trip(msg):
    """msg through CDR and back: the same message (float32 fields, such as a marker's
    colour, come back rounded to float32: compared after one more trip)."""
    wire = serialize_message(msg)
    back = deserialize_message(wire, type(msg))
    again = serialize_message(back)
    assert len(again) == len(wire)
    assert deserialize_message(again, type(msg)) == back
    if not isinstance(msg, MarkerArray):
        assert back == msg
    return back


def test_clock_and_wrench():
    c = _round_trip(messages.clock(STAMP))
    assert isinstance(c, Clock) and (c.clock.sec, c.clock.nanosec) == (3, 250_000_001)
    w = _round_trip(messages.wrench(STAMP, 'world', np.array([1.5, -2, 3]),
                                    (np.float32(0.25), 0, -1)))
    assert isinstance(w, WrenchStamped)
    assert (w.header.stamp.sec, w.header.stamp.nanosec) == (3, 250_000_001)
    assert w.header.frame_id == 'world'
    assert (w.wrench.force.x, w.wrench.force.y, w.wrench.force.z) == (1.5, -2.0, 3.0)
    assert (w.wrench.torque.x, w.wrench.torque.y, w.wrench.torque.z) == (0.25, 0.0, -1.0)


def _obstacle(name, shape, **geometry):
    d = {'name': name, 'shape': shape, 'position': (0.1, 0.2, 0.3),
         'orientation': (0.0, 0.0, math.sin(0.1), math.cos(0.1)),
         'linear_velocity': (0.0, 0.0, 0.0), 'angular_velocity': (0.0, 0.0, 0.0),
         'friction': {'static': 0.5, 'kinetic': 0.5}}
    d.update(geometry)
    return d


def test_obstacle_markers_types_and_scales():
    verts = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0], [0, 0, 1]], float)
    faces = np.array([[0, 2, 1], [0, 1, 3], [0, 3, 2], [1, 2, 3]])
    obstacles = {
        0: _obstacle('ball', 'sphere', radius=0.15),
        1: _obstacle('table', 'box', half_extents=(0.5, 0.4, 0.05)),
        2: _obstacle('ground', 'plane', normal=(0.0, 0.0, 1.0)),
        3: _obstacle('pole', 'cylinder', radius=0.05, half_length=0.3),
        4: _obstacle('pill', 'capsule', radius=0.07, half_length=0.2),
        7: _obstacle('tet', 'mesh', spacing=0.01)}
    asked = []

    def mesh_points(oid):
        asked.append(oid)
        return messages.mesh_triangle_points(verts, faces)

    arr = _round_trip(messages.obstacle_markers(obstacles, mesh_points, STAMP, 'map'))
    assert isinstance(arr, MarkerArray) and asked == [7]
    clear, *ms = arr.markers
    assert clear.action == Marker.DELETEALL
    assert [m.ns for m in ms] == ['ball', 'table', 'ground', 'pole', 'pill', 'tet']
    for m in ms:
        assert m.action == Marker.ADD and m.id == 0 and m.header.frame_id == 'map'
        assert (m.header.stamp.sec, m.header.stamp.nanosec) == (3, 250_000_001)
        assert (m.pose.position.x, m.pose.position.y, m.pose.position.z) == (0.1, 0.2, 0.3)
        assert m.pose.orientation.z == math.sin(0.1) and m.pose.orientation.w == math.cos(0.1)
        assert (m.color.r, m.color.g, m.color.b, m.color.a) == pytest.approx(
            messages.OBSTACLE_COLOR)
    scale = {m.ns: (m.type, (m.scale.x, m.scale.y, m.scale.z)) for m in ms}
    assert scale['ball'] == (Marker.SPHERE, (0.3, 0.3, 0.3))
    assert scale['table'] == (Marker.CUBE, (1.0, 0.8, 0.1))
    assert scale['ground'] == (Marker.CUBE, (10.0, 10.0, 1e-3))
    assert scale['pole'][0] == Marker.CYLINDER
    assert scale['pole'][1] == pytest.approx((0.1, 0.1, 0.6))
    assert scale['pill'][0] == Marker.CYLINDER
    assert scale['pill'][1] == pytest.approx((0.14, 0.14, 0.4 + 0.14))
    assert scale['tet'] == (Marker.TRIANGLE_LIST, (1.0, 1.0, 1.0))
    tet = ms[-1]
    pts = np.array([[p.x, p.y, p.z] for p in tet.points])
    np.testing.assert_array_equal(pts, verts[faces.reshape(-1)])
    # no obstacle: the DELETEALL alone (it clears the last one from a display)
    empty = messages.obstacle_markers({}, mesh_points, STAMP, 'map')
    assert [m.action for m in empty.markers] == [Marker.DELETEALL]


def test_status_values_floats_as_repr():
    arr = _round_trip(messages.status(STAMP, 'world', 'sim', DiagnosticStatus.WARN, 'slow',
                                      {'a': 0.1 + 0.2, 'n': 3, 'flag': True, 's': 'x'},
                                      '/ns/cloth_node'))
    assert isinstance(arr, DiagnosticArray)
    assert (arr.header.stamp.sec, arr.header.stamp.nanosec, arr.header.frame_id) == (
        3, 250_000_001, 'world')
    (st,) = arr.status
    assert (st.name, st.level, st.message, st.hardware_id) == (
        'sim', DiagnosticStatus.WARN, 'slow', '/ns/cloth_node')
    assert [(kv.key, kv.value) for kv in st.values] == [
        ('a', '0.30000000000000004'), ('n', '3'), ('flag', 'True'), ('s', 'x')]


@pytest.mark.parametrize('diverged, paused, level, message', [
    (None, False, DiagnosticStatus.OK, 'running'),
    (None, True, DiagnosticStatus.WARN, 'paused'),
    ('NaN in positions', False, DiagnosticStatus.ERROR, 'diverged: NaN in positions'),
    ('NaN in positions', True, DiagnosticStatus.ERROR, 'diverged: NaN in positions'),
])
def test_energy_status_levels(diverged, paused, level, message):
    arr = messages.energy_status(STAMP, 'world', {'total': 1.0}, 3.25, 7, diverged, paused,
                                 '/cloth_node')
    (st,) = arr.status
    assert (st.name, st.level, st.message) == ('energy', level, message)


def test_energy_status_round_trips():
    energy = {'kinetic': np.float64(0.0001554773459379232), 'stretching': 2.9e-13,
              'gravity': np.float32(-0.5), 'external_work': 0, 'total': 1 / 3}
    arr = messages.energy_status(STAMP, 'world', energy, np.float64(3.250000001), 16250,
                                 None, False, '/cloth_node')
    back = deserialize_message(serialize_message(arr), DiagnosticArray)
    assert back == arr
    (st,) = back.status
    values = {kv.key: kv.value for kv in st.values}
    assert list(values) == list(energy) + ['sim_time', 'step']
    for k, v in energy.items():
        assert float(values[k]) == float(v)          # repr of a float: exact
    assert values['external_work'] == '0.0'
    assert values['sim_time'] == '3.250000001' and values['step'] == '16250'
    assert st.hardware_id == '/cloth_node' and st.level == DiagnosticStatus.OK
