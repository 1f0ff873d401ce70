"""What the demos (``fold_demo``, ``flag_demo``) share: a peer node that parses its command
line past the ROS arguments, follows the cloth through ``~/points`` and keeps simulation
time from their stamps.

A demo is a separate process that talks to ``cloth_node`` through its topics and services
only, as a user's robot code would; nothing here imports the simulator.
"""
from __future__ import annotations

import argparse
import sys
import time

import numpy as np

__all__ = ['DemoPeer', 'parser', 'parse']


def parser(prog: str, doc: str) -> argparse.ArgumentParser:
    """The demos' command line: ``--node`` (whose topics, default cloth_node) and
    ``--wait`` (seconds to wait for it); the demo adds its own."""
    ap = argparse.ArgumentParser(prog=prog, description=doc.split('\n')[0])
    ap.add_argument('--node', default='cloth_node')
    ap.add_argument('--wait', type=float, default=120.0, help='seconds to wait for the node')
    return ap


def parse(ap: argparse.ArgumentParser, argv=None) -> argparse.Namespace:
    """``ap``'s arguments from ``argv`` (default ``sys.argv[1:]``), ROS arguments
    (``--ros-args ...``) left out for rclpy."""
    import rclpy
    args = ['demo'] + list(sys.argv[1:] if argv is None else argv)
    return ap.parse_args(rclpy.utilities.remove_ros_args(args)[1:])


class DemoPeer:
    """An rclpy node subscribed to ``/<node>/points`` (sensor_msgs/PointCloud2): :meth:`points` is the latest cloud's xyz (n, 3), :meth:`sim_now` its
    stamp in seconds (the node stamps with simulation time)."""

    def __init__(self, name: str, node: str, argv=None):
        import rclpy
        from sensor_msgs.msg import PointCloud2
        rclpy.init(args=argv)
        self.node = rclpy.create_node(name)
        self.base = f'/{node}'
        self.clouds = []
        self.node.create_subscription(PointCloud2, f'{self.base}/points',
                                      self.clouds.append, 5)

    def spin_once(self, timeout: float = 0.01) -> bool:
        """Handle what has arrived (waiting at most ``timeout`` s); True if a new cloud
        came in."""
        import rclpy
        n = len(self.clouds)
        rclpy.spin_once(self.node, timeout_sec=timeout)
        return len(self.clouds) > n

    def spin(self, seconds: float) -> None:
        """Handle callbacks for ``seconds`` of wall time."""
        end = time.monotonic() + seconds
        while time.monotonic() < end:
            self.spin_once(min(0.01, max(end - time.monotonic(), 0.0)))

    def wait_for(self, ready, seconds: float) -> bool:
        """Spin until a cloud has arrived and ``ready()`` holds, or ``seconds`` of wall time
        have passed; True if a cloud came."""
        end = time.monotonic() + seconds
        while time.monotonic() < end and not (self.clouds and ready()):
            self.spin_once(0.1)
        return bool(self.clouds)

    def sim_now(self) -> float:
        """Simulation time [s] of the latest cloud."""
        stamp = self.clouds[-1].header.stamp
        return stamp.sec + 1e-9 * stamp.nanosec

    def points(self) -> np.ndarray:
        """The latest cloud's vertex positions (n, 3) [m]; the node publishes x, y, z,
        vx, vy, vz as six float32 per point (``ros/conversions.py``, POINT_FIELDS)."""
        c = self.clouds[-1]
        return np.frombuffer(bytes(c.data), dtype='<f4').reshape(-1, 6)[:, :3].astype(float)

    def wait_sim(self, seconds: float) -> None:
        """Spin until the simulation time has moved on ``seconds`` (a node slower than real
        time takes longer; at most 20 s of wall time per second asked)."""
        target = self.sim_now() + seconds
        end = time.monotonic() + 20.0 * seconds + 1.0
        while self.sim_now() < target and time.monotonic() < end:
            self.spin_once(0.01)

    def close(self) -> None:
        import rclpy
        self.node.destroy_node()
        rclpy.try_shutdown()
