"""``flag_demo``: blow a gusty 6 m/s wind on the flag of ``config/flag.yaml`` through the
node's ``~/wind`` topic, and measure how it flies.

    flag_demo [--node cloth_node] [--speed 6.0] [--duration 10.0] [--wait 120] [--timeout 1800]

Streams :func:`gust` on ``~/wind`` for ``--duration`` seconds of simulation time, one
message per 1/30 s of simulation time, each stamped with the simulation time it is for
and sent when the node's ``/clock`` reaches it (its node has ``use_sim_time``), so the
sequence is the same at any real-time factor; then checks the flag: its free edge (the
vertices furthest from the pole) must have flown out downwind (mean distance from the pole
above half the flag's length) and fluttered (the free edge's sideways position varying by
more than 2 cm over the last half of the run). Prints what it measured; exit 0 if it flew, 1
if not or if the node refused a message (its reason printed), 2 if the node is not there.
Needs ``air.enabled: true``, ``publish.points: true`` and ``publish_clock: true`` (flag.yaml
has them). On a terminal, a progress line on stderr counts the simulation seconds done.

Why gusts: the air model (``core/air.py``) is local, each triangle pushed by its own
relative velocity, with no wake, so in a steady wind a flag settles into a steady shape,
streaming out and drooping; the flapping of a real flag comes from the vortices it sheds.
The gusts here stand in for them (and for a real wind's turbulence, as in Wilson et al.
2014): the speed varies by +-30% and the direction swings by up to +-20 degrees across the
flag, at 0.5-2.1 Hz.
"""
from __future__ import annotations

import math
import sys

import numpy as np

__all__ = ['main', 'gust']

RATE = 30.0           # wind messages per second of simulation time


def gust(t: float, speed: float) -> np.ndarray:
    """The demo's wind at time t [s]: mean ``speed`` [m/s] along +x, its speed varying by
    up to +-30% and its direction swinging in the horizontal plane by up to +-20 degrees,
    each the sum of two incommensurate sines (0.5/1.3 Hz and 0.8/2.1 Hz)."""
    psi = (0.22 * math.sin(2 * math.pi * 0.5 * t)
           + 0.13 * math.sin(2 * math.pi * 1.3 * t + 0.7))
    mag = speed * (1.0 + 0.18 * math.sin(2 * math.pi * 0.8 * t)
                   + 0.12 * math.sin(2 * math.pi * 2.1 * t + 2.0))
    return np.array([mag * math.cos(psi), mag * math.sin(psi), 0.0])


def main(argv=None) -> int:
    from geometry_msgs.msg import Vector3Stamped
    from rclpy.executors import ExternalShutdownException
    from .demo_peer import DemoPeer, Refused, parse, parser
    ap = parser('flag_demo', __doc__)
    ap.add_argument('--speed', type=float, default=6.0, help='mean wind speed [m/s]')
    ap.add_argument('--duration', type=float, default=10.0,
                    help='seconds of simulation time of wind')
    a = parse(ap, argv)
    peer = DemoPeer('flag_demo', a.node, argv, a.timeout)
    wind = peer.node.create_publisher(Vector3Stamped, f'{peer.base}/wind', 10)
    try:
        if not peer.wait_for(wind.get_subscription_count, a.wait):
            print(f'flag_demo: error: no {peer.base}/points (publish.points) or /clock '
                  f'(publish_clock) after {a.wait:g} s: start the node with '
                  'config/flag.yaml', file=sys.stderr)
            return 2
        x0 = peer.points()
        pole = x0[:, 0].min()
        length = x0[:, 0].max() - pole
        free = x0[:, 0] > pole + 0.97 * length
        t0 = peer.sim_now()
        peer.plan(a.duration)
        side, out = [], []
        steps = int(round(a.duration * RATE))
        k = 0
        while k < steps:
            # every gust whose time has come, in order (several if the node ran ahead)
            while k < steps and t0 + k / RATE <= peer.sim_now():
                msg = Vector3Stamped()
                msg.header.frame_id = 'world'
                peer.stamp(msg.header, t0 + k / RATE)
                msg.vector.x, msg.vector.y, msg.vector.z = map(float, gust(k / RATE, a.speed))
                wind.publish(msg)
                k += 1
            if peer.spin_once(0.01) and peer.sim_now() > t0 + 0.5 * a.duration:
                p = peer.points()[free]
                side.append(p[:, 1].mean())
                out.append(p[:, 0].mean() - pole)
            peer.check()
        peer.finish()
        if not out:
            print('flag_demo: error: the node published no points during the run',
                  file=sys.stderr)
            return 1
        reach, sway = float(np.mean(out)), float(np.ptp(side))
        flew = reach > 0.5 * length and sway > 0.02
        print(f'flag_demo: the free edge flew {reach:.2f} m out from the pole (flag length '
              f'{length:.2f} m) and swung {100 * sway:.1f} cm across the wind over the last '
              f'{a.duration / 2:g} s: {"flew" if flew else "did NOT fly"}')
        return 0 if flew else 1
    except (Refused, TimeoutError) as exc:
        peer.finish()
        print(f'flag_demo: error: {exc}', file=sys.stderr)
        return 1
    except (KeyboardInterrupt, ExternalShutdownException):    # Ctrl-C, SIGTERM
        return 130
    finally:
        peer.close()


if __name__ == '__main__':
    sys.exit(main())
