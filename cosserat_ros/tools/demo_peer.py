"""What the demos (``fold_demo``, ``flag_demo``) share: a peer node on simulation time
that parses its command line past the ROS arguments, follows the cloth through
``~/points`` and watches the node's ``~/rejections``.

A demo is a separate process that talks to ``cloth_node`` through its topics and services
only, as a user's robot code would; nothing here imports the simulator. It paces on
simulation time: its node has ``use_sim_time`` true, so its clock is the node's ``/clock``,
and every wait and every stamp is in simulation seconds, which gives the same motion at
any real-time factor (a busy host, or the node's ``real_time_factor``). Wall-clock limits
are safety nets only: ``--wait`` for the node to appear, ``--timeout`` for the whole run.

On a terminal, a progress line on stderr says how long the demo has waited for the node
and then how many of its simulation seconds are done (:meth:`DemoPeer.plan`); a pipe or a
file gets none of it (:mod:`.progress`).
"""
from __future__ import annotations

import argparse
import sys
import time

import numpy as np

__all__ = ['DemoPeer', 'Refused', 'parser', 'parse', 'FLUSH_TIMEOUT']

#: [s] wall time a demo waits at its end for its subscribers to acknowledge what it sent
FLUSH_TIMEOUT = 10.0


class Refused(RuntimeError):
    """The node refused one of the demo's commands (its ``~/rejections``), or its
    simulation diverged (its ``~/energy``); the message names the input and the node's
    reason."""


def parser(prog: str, doc: str) -> argparse.ArgumentParser:
    """The demos' command line: ``--node`` (whose topics, default cloth_node), ``--wait``
    (wall seconds to wait for it) and ``--timeout`` (wall seconds for the whole run); the
    demo adds its own."""
    ap = argparse.ArgumentParser(prog=prog, description=doc.split('\n')[0])
    ap.add_argument('--node', default='cloth_node')
    ap.add_argument('--wait', type=float, default=120.0,
                    help='wall-clock seconds to wait for the node to appear')
    ap.add_argument('--timeout', type=float, default=1800.0,
                    help='wall-clock seconds the run may take at most, a safety net (the '
                         'demo itself runs on simulation time)')
    return ap


def parse(ap: argparse.ArgumentParser, argv=None) -> argparse.Namespace:
    """``ap``'s arguments from ``argv`` (default ``sys.argv[1:]``), ROS arguments
    (``--ros-args ...``) left out for rclpy."""
    import rclpy
    args = ['demo'] + list(sys.argv[1:] if argv is None else argv)
    return ap.parse_args(rclpy.utilities.remove_ros_args(args)[1:])


class DemoPeer:
    """An rclpy node with ``use_sim_time``: :meth:`sim_now` is the node's ``/clock``;
    subscribed to ``/<node>/points`` (sensor_msgs/PointCloud2, :meth:`points` the latest
    cloud's xyz), ``/<node>/rejections`` (diagnostic_msgs/DiagnosticStatus, kept in
    :attr:`rejections`) and ``/<node>/energy`` (an ERROR status: diverged);
    :meth:`check` raises :class:`Refused` on the first rejection or a divergence.
    :attr:`progress` is the demo's progress line (:meth:`plan`, :meth:`say`)."""

    def __init__(self, name: str, node: str, argv=None, timeout: float = 1800.0):
        import rclpy
        from rclpy.parameter import Parameter
        from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus
        from sensor_msgs.msg import PointCloud2
        from .progress import Progress
        self.progress = Progress(name)           # on a terminal only
        self._plan = None                        # (start, total) [s of simulation time]
        rclpy.init(args=argv)
        self.node = rclpy.create_node(
            name, parameter_overrides=[Parameter('use_sim_time', value=True)])
        self.base = f'/{node}'
        self.clouds = []
        self.rejections = []
        self.deadline = time.monotonic() + timeout
        self.node.create_subscription(PointCloud2, f'{self.base}/points',
                                      self.clouds.append, 5)
        self.node.create_subscription(DiagnosticStatus, f'{self.base}/rejections',
                                      self.rejections.append, 50)
        self.diverged = None                 # the node's reason, once it has diverged
        self.node.create_subscription(DiagnosticArray, f'{self.base}/energy',
                                      self._on_energy, 5)

    def _on_energy(self, msg) -> None:
        st = msg.status[0] if msg.status else None
        if st is not None and st.level == st.ERROR and self.diverged is None:
            self.diverged = st.message

    def spin_once(self, timeout: float = 0.01) -> bool:
        """Handle what has arrived (waiting at most ``timeout`` wall s); True if a new
        cloud came in. Updates the progress line of :meth:`plan`."""
        import rclpy
        n = len(self.clouds)
        rclpy.spin_once(self.node, timeout_sec=timeout)
        if self._plan is not None:
            start, total = self._plan
            done = min(max(self.sim_now() - start, 0.0), total)
            self.progress.update(f'{done:.1f} of {total:.1f} s of simulation time')
        return len(self.clouds) > n

    def plan(self, total: float) -> None:
        """From now on the progress line counts the simulation seconds done of ``total``."""
        self._plan = (self.sim_now(), float(total))

    def say(self, text: str) -> None:
        """Print ``text`` (a line of the demo's output) without mixing it into the
        progress line."""
        self.progress.clear()
        print(text, flush=True)

    def wait_for(self, ready, seconds: float) -> bool:
        """Spin until a cloud and the clock have arrived and ``ready()`` holds, or
        ``seconds`` of wall time have passed; True if they came."""
        start = time.monotonic()
        end = start + seconds
        while time.monotonic() < end and not (self.clouds and self.sim_now() > 0
                                              and ready()):
            self.progress.update(f'waiting for {self.base} ({time.monotonic() - start:.0f} '
                                 f's of --wait {seconds:g})')
            self.spin_once(0.1)
        self.progress.clear()
        return bool(self.clouds) and self.sim_now() > 0

    def sim_now(self) -> float:
        """Simulation time [s]: the node's /clock (0 before the first)."""
        return self.node.get_clock().now().nanoseconds * 1e-9

    def points(self) -> np.ndarray:
        """The latest cloud's vertex positions (n, 3) [m]; the node publishes x, y, z,
        vx, vy, vz as six float32 per point (``ros/conversions.py``, POINT_FIELDS)."""
        c = self.clouds[-1]
        return np.frombuffer(bytes(c.data), dtype='<f4').reshape(-1, 6)[:, :3].astype(float)

    def check(self) -> None:
        """:class:`Refused` if the node has refused a command of this demo; a wall-clock
        ``TimeoutError`` past ``--timeout``."""
        if self.diverged is not None:
            raise Refused(f'the node stopped: {self.diverged}')
        if self.rejections:
            r = self.rejections[0]
            vals = ', '.join(f'{kv.key}={kv.value}' for kv in r.values)
            raise Refused(f'the node refused {r.name}: {r.message} ({vals})')
        if time.monotonic() > self.deadline:
            raise TimeoutError('the run took longer than --timeout (wall clock): is the '
                               'node still running?')

    def wait_until(self, t: float) -> None:
        """Spin until the simulation time reaches ``t`` [s] (checking as it goes)."""
        while self.sim_now() < t:
            self.spin_once(0.01)
            self.check()

    def wait_sim(self, seconds: float) -> None:
        """Spin for ``seconds`` of simulation time (a node slower than real time takes
        longer in wall time)."""
        self.wait_until(self.sim_now() + seconds)

    def stamp(self, header, t: float) -> None:
        """Stamp ``header`` with simulation time ``t`` [s]."""
        ns = int(round(t * 1e9))
        header.stamp.sec, header.stamp.nanosec = ns // 10 ** 9, ns % 10 ** 9

    def finish(self) -> None:
        """End the progress line with the simulation seconds the demo took, before its
        result."""
        if self._plan is not None and self.progress.enabled:
            self.progress.done(f'{self.sim_now() - self._plan[0]:.1f} s of simulation '
                               'time, done')
        self.progress.done()
        self._plan = None

    def close(self) -> None:
        """Leave the graph once every reliable subscriber has what the demo sent (at most
        :data:`FLUSH_TIMEOUT` s): a publish only queues its message, and a process that
        exits right after its last one can take it along undelivered (seen beside two
        busy processes: a listener got 89 of flag_demo's 90 gusts, the last missing)."""
        import rclpy
        from rclpy.duration import Duration
        self.progress.done()
        for pub in self.node.publishers:
            try:
                pub.wait_for_all_acked(Duration(seconds=FLUSH_TIMEOUT))
            except Exception:           # a publisher the context has already let go of
                pass
        self.node.destroy_node()
        rclpy.try_shutdown()
