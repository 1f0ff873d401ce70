"""``fold_demo``: fold the cloth of ``config/fold.yaml`` in half with its two handles, as a
robot would, through the node's ROS interfaces only.

    fold_demo [--node cloth_node] [--duration 4.0] [--settle 2.0] [--wait 120] [--timeout 1800]

Places handles ``left`` and ``right`` on the cloth's corners at x = min (``~/handles/<n>/
target``), grasps (``~/handles/<n>/grasp``), streams targets at 30 per simulated second
along an arc that lifts the corners 0.25 m while carrying them to the far edge, turning the
grip about y by 180 degrees, releases them just above the far corners and lets the cloth
settle. Then it reads ``~/points`` and checks the fold: the vertices that started within
0.1 width of the grasped edge must end on the far half, and the cloth must lie on the
ground (every vertex below 5 cm). Prints what it measured; exit 0 if folded, 1 if not or
if the node refused a command (its reason printed), 2 if the node is not there. Needs
``publish.points: true`` and ``publish_clock: true`` (fold.yaml has them). On a terminal, a
progress line on stderr counts the simulation seconds done.

It runs on simulation time (its node has ``use_sim_time``; the clock is the node's
``/clock``): every target is stamped with the simulation time at which the handle must be
there, sent up to :data:`LEAD` s of simulation time ahead, and every wait counts
simulation seconds, so the fold is the same at any real-time factor. ``--duration`` and
``--settle`` are simulation seconds.
"""
from __future__ import annotations

import math
import sys
import time

import numpy as np

__all__ = ['main', 'fold_path']

RATE = 30.0           # targets per second of simulation time
LIFT = 0.25           # [m] highest point of the arc
LEAD = 0.2            # [s] of simulation time: how far ahead targets are sent


def fold_path(s: float, start: np.ndarray, end_x: float):
    """Handle pose at progress s in [0, 1]: (position (3,), quaternion (x, y, z, w)). The
    corner rises on a half sine while x goes from start to end_x (cosine-eased), the grip
    turns about +y by pi s (the inward direction of the cloth at the edge, +x, turns
    through -z to -x)."""
    e = 0.5 * (1.0 - math.cos(math.pi * s))
    p = np.array([start[0] + (end_x - start[0]) * e, start[1],
                  start[2] + LIFT * math.sin(math.pi * s) + 0.01 * e])
    q = np.array([0.0, math.sin(math.pi * s / 2), 0.0, math.cos(math.pi * s / 2)])
    return p, q


def main(argv=None) -> int:
    from geometry_msgs.msg import PoseStamped
    from std_srvs.srv import SetBool
    from rclpy.executors import ExternalShutdownException
    from .demo_peer import DemoPeer, Refused, parse, parser
    ap = parser('fold_demo', __doc__)
    ap.add_argument('--duration', type=float, default=4.0,
                    help='seconds of simulation time the carry takes')
    ap.add_argument('--settle', type=float, default=2.0,
                    help='seconds of simulation time after the release')
    a = parse(ap, argv)
    peer = DemoPeer('fold_demo', a.node, argv, a.timeout)
    node, base = peer.node, peer.base
    targets = {n: node.create_publisher(PoseStamped, f'{base}/handles/{n}/target', 10)
               for n in ('left', 'right')}
    grasp = {n: node.create_client(SetBool, f'{base}/handles/{n}/grasp')
             for n in ('left', 'right')}
    points = peer.points

    def send(name, p, q, at=0.0):
        """Target ``p, q`` for handle ``name``, to be reached at simulation time ``at``
        (0: over the time since the last target, or placed if not grasped)."""
        msg = PoseStamped()
        msg.header.frame_id = 'world'
        peer.stamp(msg.header, at)
        msg.pose.position.x, msg.pose.position.y, msg.pose.position.z = map(float, p)
        (msg.pose.orientation.x, msg.pose.orientation.y, msg.pose.orientation.z,
         msg.pose.orientation.w) = map(float, q)
        targets[name].publish(msg)

    def call(name, data):
        fut = grasp[name].call_async(SetBool.Request(data=data))
        end = time.monotonic() + 10
        while not fut.done() and time.monotonic() < end:
            peer.spin_once(0.05)
        return fut.result()

    try:
        if not peer.wait_for(lambda: all(c.wait_for_service(timeout_sec=0.01)
                                         for c in grasp.values()), a.wait):
            print(f'fold_demo: error: no {base}/points (publish.points), /clock '
                  f'(publish_clock) or handle services after {a.wait:g} s: start the node '
                  'with config/fold.yaml', file=sys.stderr)
            return 2
        # settle 1, place 0.3, carry LEAD + duration, hold 0.3, settle (the grasps'
        # service calls add a few ticks)
        peer.plan(1.0 + 0.3 + LEAD + a.duration + 0.3 + a.settle)
        peer.wait_sim(1.0)                               # let the cloth settle on the ground
        x0 = points()
        lo, hi = x0.min(axis=0), x0.max(axis=0)
        corners = {'left': np.array([lo[0], lo[1], x0[:, 2].mean()]),
                   'right': np.array([lo[0], hi[1], x0[:, 2].mean()])}
        end_x = hi[0] - 0.03 * (hi[0] - lo[0])
        for name, p in corners.items():
            send(name, p, (0.0, 0.0, 0.0, 1.0))
        peer.wait_sim(0.3)
        for name in corners:
            res = call(name, True)
            if res is None or not res.success:
                peer.finish()
                print(f'fold_demo: error: grasp {name}: '
                      f'{res.message if res else "no answer"}', file=sys.stderr)
                return 1
            peer.say(f'fold_demo: {res.message}')
        steps = int(round(a.duration * RATE))
        t0 = peer.sim_now() + LEAD
        k = 1
        while k <= steps:                       # stream the arc, LEAD ahead of sim time
            while k <= steps and t0 + k / RATE <= peer.sim_now() + LEAD:
                for name, p in corners.items():
                    send(name, *fold_path(k / steps, p, end_x), at=t0 + k / RATE)
                k += 1
            peer.spin_once(0.01)
            peer.check()
        peer.wait_until(t0 + steps / RATE + 0.3)
        for name in corners:
            call(name, False)
        peer.wait_sim(a.settle)
        x1 = points()
        edge = x0[:, 0] < lo[0] + 0.1 * (hi[0] - lo[0])
        mid = 0.5 * (lo[0] + hi[0])
        over = float(np.mean(x1[edge, 0] > mid))
        top = float(x1[:, 2].max())
        folded = over == 1.0 and top < 0.05
        peer.finish()
        print(f'fold_demo: {over:.0%} of the grasped edge\'s vertices ended on the far half '
              f'(x > {mid:.3f} m), highest vertex at z = {top:.3f} m: '
              f'{"folded" if folded else "NOT folded"}')
        return 0 if folded else 1
    except (Refused, TimeoutError) as exc:
        peer.finish()
        print(f'fold_demo: error: {exc}', file=sys.stderr)
        return 1
    except (KeyboardInterrupt, ExternalShutdownException):    # Ctrl-C, SIGTERM
        return 130
    finally:
        peer.close()


if __name__ == '__main__':
    sys.exit(main())
