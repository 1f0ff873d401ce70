"""The hostile peer of test_node_process.py, a process of its own: it floods cloth_node's
command topics (and calls its set_parameters) while the test process only watches the
node's ~/mesh. The test's clock then times the mesh as it arrives, not as the test's own
publishing (rclpy builds a Python object per point of a 2.9 MB marker array: seconds on a
busy host) lets it read it; and the flood goes on while the test waits for the node to end.

``python hostile_peer.py obstacles|forces`` prints ``ready`` once the node's subscriptions
(and, for ``forces``, its set_parameters service) are there, then takes commands, one a
line on stdin, and answers each with one line on stdout:

* ``flood N``: floods, prints ``started`` after the first round, and goes on until the
  line ``stop`` has come and at least N set_parameters calls were answered (at most
  :data:`FLOOD_LIMIT` s); then waits for the answers to the calls that must be refused
  and prints a JSON summary: ``rounds``, ``answered``, ``refused`` (the successful flag
  of each call that must be refused);
* ``tail`` (forces): publishes the largest accepted point forces 5 times, prints
  ``tailing`` and goes on publishing them every 10 ms until ``stop`` or end of input.
"""
import json
import os
import select
import sys
import time

import numpy as np
import rclpy
from geometry_msgs.msg import Point, PoseStamped
from rcl_interfaces.srv import SetParameters
from rclpy.executors import SingleThreadedExecutor
from rclpy.parameter import Parameter
from std_msgs.msg import Float64MultiArray
from visualization_msgs.msg import Marker, MarkerArray

#: [s] the longest a flood lasts, whatever it waits for
FLOOD_LIMIT = 120.0


def say(line):
    print(line, flush=True)


_read = b''


def stdin_line(timeout=0.0):
    """The next line on stdin if one comes within ``timeout`` [s] (None: it did not),
    '' at its end. Read unbuffered, so that select sees every line not yet taken."""
    global _read
    end = time.monotonic() + timeout
    while b'\n' not in _read:
        if not select.select([sys.stdin], [], [], max(0.0, end - time.monotonic()))[0]:
            return None
        chunk = os.read(sys.stdin.fileno(), 4096)
        if not chunk:
            return ''
        _read += chunk
    line, _read = _read.split(b'\n', 1)
    return line.decode() + '\n'


class Obstacles:
    """~/obstacles: 2.9 MB marker arrays (refused unread, by their size) and 200 NaN
    markers; ~/handles/left/target: bad quaternions. One round each 50 ms at most."""

    def __init__(self, node):
        self.node = node
        self.obstacles = node.create_publisher(MarkerArray, '/cloth_node/obstacles', 10)
        self.target = node.create_publisher(PoseStamped, '/cloth_node/handles/left/target',
                                            10)
        big = Marker()
        big.header.frame_id = 'world'
        big.ns, big.id, big.type = 'big', 1, Marker.TRIANGLE_LIST
        big.pose.orientation.w = 1.0
        big.scale.x = big.scale.y = big.scale.z = 1.0
        big.points = [Point(x=float(i), y=0.0, z=0.0) for i in range(120_000)]
        self.huge = MarkerArray(markers=[big])
        nan = Marker()
        nan.header.frame_id = 'world'
        nan.type, nan.pose.position.x = Marker.SPHERE, float('nan')
        self.many = MarkerArray(markers=[nan] * 200)
        self.bad_pose = PoseStamped()
        self.bad_pose.header.frame_id = 'world'
        self.bad_pose.pose.orientation.w = 3.0
        self.publishers = (self.obstacles, self.target)
        self.answered, self.refused = 0, []

    def ready(self):
        return True

    def round(self, ex):
        self.obstacles.publish(self.huge)
        self.obstacles.publish(self.many)
        for _ in range(20):
            self.target.publish(self.bad_pose)
        ex.spin_once(timeout_sec=0.05)

    def settle(self, ex, timeout):
        pass


class Forces:
    """~/point_forces: 10,000-row messages (refused unread, by their size) and the largest
    accepted ones (4,096 rows near the cloth); ~/vertex_forces: 1,000 rows of 10 N on one
    vertex (each row within max_force, their sum not); set_parameters: a new material
    each call, four calls in flight, every fifth call a value that must be refused (a
    density whose rates overflow a float, use_sim_time true)."""

    def __init__(self, node):
        self.node = node
        self.points = node.create_publisher(Float64MultiArray, '/cloth_node/point_forces', 10)
        self.vertex = node.create_publisher(Float64MultiArray, '/cloth_node/vertex_forces',
                                            10)
        rng = np.random.default_rng(0)
        self.huge = Float64MultiArray()
        self.huge.data = rng.uniform(0.0, 1.0, 60_000).tolist()           # 10,000 rows of 6
        full = np.zeros((4096, 6))
        full[:, :2] = rng.uniform(0.0, 1.0, (4096, 2))                    # over the cloth
        full[:, 2] = rng.uniform(-0.8, 0.2, 4096)
        full[:, 5] = 1e-3                                                 # 4 N in all
        self.largest = Float64MultiArray()
        self.largest.data = full.ravel().tolist()
        self.summed = Float64MultiArray()
        self.summed.data = np.tile([20.0 * 41 + 20.0, 0.0, 0.0, 10.0], 1000).tolist()
        self.setp = node.create_client(SetParameters, '/cloth_node/set_parameters')
        self.publishers = (self.points, self.vertex)
        self.pending, self.bad, self.k, self.answered = [], [], 0, 0

    def ready(self):
        return self.setp.service_is_ready()

    def round(self, ex):
        self.points.publish(self.huge)
        self.points.publish(self.largest)
        self.vertex.publish(self.summed)
        self.answered += sum(1 for f in self.pending if f.done())
        self.pending = [f for f in self.pending if not f.done()]
        while len(self.pending) < 4:                    # a new material every call
            self.k += 1
            req = SetParameters.Request()
            req.parameters = [Parameter('material.zeta',
                                        value=50.0 + 0.01 * self.k).to_parameter_msg()]
            if self.k % 5 == 0:                         # and values that must be refused:
                # a density whose rates overflow a float; a clock the node would wait on
                req.parameters = [(Parameter('material.density', value=1e-160)
                                   if self.k % 10 else Parameter('use_sim_time', value=True)
                                   ).to_parameter_msg()]
                self.bad.append(self.setp.call_async(req))
                continue
            self.pending.append(self.setp.call_async(req))
        ex.spin_once(timeout_sec=0.01)

    def settle(self, ex, timeout):
        end = time.monotonic() + timeout
        while time.monotonic() < end and not all(f.done() for f in self.bad):
            ex.spin_once(timeout_sec=0.05)
        self.answered += sum(1 for f in self.bad if f.done())
        self.refused = [r.successful for f in self.bad if f.done()
                        for r in f.result().results]


def main(kind):
    rclpy.init()
    node = rclpy.create_node('hostile_peer')
    ex = SingleThreadedExecutor()
    ex.add_node(node)
    peer = {'obstacles': Obstacles, 'forces': Forces}[kind](node)
    end = time.monotonic() + 60.0
    while time.monotonic() < end and not (
            all(p.get_subscription_count() > 0 for p in peer.publishers) and peer.ready()):
        ex.spin_once(timeout_sec=0.05)
    say('ready')
    try:
        while True:
            line = stdin_line(FLOOD_LIMIT)
            if not line:                                 # end of input, or none for long
                return
            cmd = line.split()
            if cmd[:1] == ['flood']:
                need, stopped = int(cmd[1]), False
                limit = time.monotonic() + FLOOD_LIMIT
                rounds = 0
                while time.monotonic() < limit and not (stopped and peer.answered >= need):
                    peer.round(ex)
                    rounds += 1
                    if rounds == 1:
                        say('started')
                    got = stdin_line()
                    if got == '':                        # the test has gone: so does this
                        return
                    stopped = stopped or got is not None
                peer.settle(ex, 10.0)
                say(json.dumps({'rounds': rounds, 'answered': peer.answered,
                                'refused': peer.refused}))
            elif cmd[:1] == ['tail']:
                for _ in range(5):
                    peer.points.publish(peer.largest)
                say('tailing')
                limit = time.monotonic() + FLOOD_LIMIT
                while time.monotonic() < limit and stdin_line() is None:
                    peer.points.publish(peer.largest)
                    time.sleep(0.01)
                say('done')
                return
    finally:
        ex.shutdown()
        node.destroy_node()
        rclpy.try_shutdown()


if __name__ == '__main__':
    main(sys.argv[1])
