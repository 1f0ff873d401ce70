"""The node's virtual cameras: their parameters, checks and topics.

Parameters: ``cameras.names`` and per camera ``cameras.<name>.<key>`` (:data:`CAMERA_KEYS`):
``width``, ``height`` [px], ``fov`` (vertical, degrees), ``position`` [m] and
``orientation`` (x, y, z, w) of the optical frame (z forward, x right, y down) in
``frame_id``, ``rate`` [Hz of simulation time, at most ``publish_rate``], ``points``
(publish the organised cloud), ``near`` and ``far`` [m].

Topics, under ``~/cameras/<name>/``, all stamped with the simulation time of the state
they show and in frame ``<name>_optical_frame``:

* ``depth/image_raw`` ``sensor_msgs/Image`` ``32FC1`` [m along the optical axis], NaN
  where nothing is seen; ``color/image_raw`` ``rgb8``; ``camera_info``
  ``sensor_msgs/CameraInfo`` (K, R = I, P = [K | 0], ``plumb_bob`` with zero D);
* with ``points``: ``points`` ``sensor_msgs/PointCloud2`` organised (height x width),
  x y z float32 in the optical frame, NaN where nothing is seen;
* ``pose_out`` ``geometry_msgs/PoseStamped``: the optical frame's pose in ``frame_id``
  (the transform ``frame_id`` -> ``<name>_optical_frame``), published with every image.
  No tf2 wheels exist on PyPI; on a ROS install a ``tf2_ros.TransformBroadcaster`` (or
  a static one for a fixed camera) relays it to ``/tf`` so that RViz places the images
  and clouds (doc/viewing.md);
* in: ``pose`` ``geometry_msgs/PoseStamped`` in ``frame_id`` (finite, unit quaternion:
  the checks of a handle's target) moves the camera, e.g. one on a robot's wrist.

Bounded work: at most :data:`MAX_CAMERAS` cameras, each image at most
:data:`~cosserat_ros.camera.MAX_PIXELS`, and all cameras together at most
:data:`PIXEL_BUDGET` pixels per second of simulation time (``width * height * rate``
summed); a camera renders at most once per tick.
"""
from __future__ import annotations

import math
import time
from typing import Dict, List

import numpy as np

from ..camera import Camera
from .params import CAMERA_KEYS, ConfigError

__all__ = ['CAMERA_KEYS', 'MAX_CAMERAS', 'PIXEL_BUDGET', 'camera_specs', 'declared_cameras',
           'optical_frame', 'CameraStreams']

#: the most cameras one node serves
MAX_CAMERAS = 4
#: the most pixels per second of simulation time all cameras render together (640 x 480
#: at 15 Hz is 4.6e6; 1280 x 960 at 15 Hz 1.8e7)
PIXEL_BUDGET = 2.0e7


def optical_frame(name: str) -> str:
    return f'{name}_optical_frame'


def camera_specs(p: dict) -> Dict[str, dict]:
    """{name: {'camera': Camera, 'rate': Hz, 'points': bool}} of checked parameters ``p``
    (flat, with ``cameras.<name>.<key>`` for every declared camera), else ConfigError
    with the reason."""
    names = [n for n in p['cameras.names'] if n]
    if len(set(names)) != len(names):
        raise ConfigError(f'cameras.names has duplicates: {names}')
    if len(names) > MAX_CAMERAS:
        raise ConfigError(f'cameras.names: {len(names)} cameras, at most {MAX_CAMERAS}')
    out, pixels = {}, 0.0
    for name in names:
        c = {k: p[f'cameras.{name}.{k}'] for k in CAMERA_KEYS}
        rate = c['rate']
        if not (isinstance(rate, float) and math.isfinite(rate)
                and 0.0 < rate <= p['publish_rate']):
            raise ConfigError(f'cameras.{name}.rate must be in (0, publish_rate = '
                              f'{p["publish_rate"]:g}] Hz, got {rate!r}')
        if not isinstance(c['points'], bool):
            raise ConfigError(f'cameras.{name}.points must be true or false, got '
                              f'{c["points"]!r}')
        try:
            cam = Camera(c['width'], c['height'], c['fov'], c['position'], c['orientation'],
                         near=c['near'], far=c['far'])
        except ValueError as exc:
            raise ConfigError(f'cameras.{name}: {exc}') from None
        pixels += cam.width * cam.height * rate
        out[name] = {'camera': cam, 'rate': rate, 'points': c['points']}
    if pixels > PIXEL_BUDGET:
        raise ConfigError(f'cameras: {pixels:.3g} pixels per second (width x height x rate '
                          f'summed), at most {PIXEL_BUDGET:.3g}: lower a size or a rate')
    return out


def declared_cameras(node, p: dict) -> Dict[str, dict]:
    """The cameras of ``cameras.names`` of ``node``: their parameters declared (read-only)
    and checked (:func:`camera_specs`); ``p``: the node's values of the declarations."""
    from .params import CAMERA_KEYS, group_names
    values = {'cameras.names': group_names('cameras', p['cameras.names']),
              'publish_rate': p['publish_rate']}
    for name in values['cameras.names']:
        for key, value in node._declare_group('cameras', name, CAMERA_KEYS, 'camera').items():
            values[f'cameras.{name}.{key}'] = value
    return camera_specs(values)


class CameraStreams:
    """The publishers, pose subscriptions and schedule of the node's cameras."""

    def __init__(self, node, specs: Dict[str, dict], qos):
        from geometry_msgs.msg import PoseStamped
        from sensor_msgs.msg import CameraInfo, Image, PointCloud2
        self.node = node
        self.streams: Dict[str, dict] = {}
        for name, spec in specs.items():
            base = f'~/cameras/{name}'
            s = dict(spec)
            s['depth'] = node.create_publisher(Image, f'{base}/depth/image_raw', qos)
            s['color'] = node.create_publisher(Image, f'{base}/color/image_raw', qos)
            s['info'] = node.create_publisher(CameraInfo, f'{base}/camera_info', qos)
            s['cloud'] = (node.create_publisher(PointCloud2, f'{base}/points', qos)
                          if spec['points'] else None)
            s['pose_out'] = node.create_publisher(PoseStamped, f'{base}/pose_out', qos)
            node.create_subscription(PoseStamped, f'{base}/pose',
                                     lambda msg, n=name: self.on_pose(n, msg), 10)
            s['last'] = -math.inf          # sim time of the last image
            s['wall'] = -math.inf          # monotonic time of the last image
            s['moved'] = False
            self.streams[name] = s

    def __len__(self):
        return len(self.streams)

    def on_pose(self, name: str, msg) -> None:
        from . import commands
        try:
            p, q = commands.handle_target(msg, self.node.frame_id)
        except commands.CommandError as exc:
            self.node._reject('cameras', f'cameras/{name}/pose: {exc}', f'cameras/{name}/pose')
            return
        s = self.streams[name]
        s['camera'].set_pose(p, q)
        s['moved'] = True
        self.node._dirty = True

    def due(self, running: bool, now_sim: float, now_wall: float, repeat: float) -> List[str]:
        """The cameras to render now: a period of ``rate`` of simulation time has passed
        since the last image, or the camera moved; while the cloth stands still, once
        every ``repeat`` seconds of wall time (a late subscriber still gets an image)."""
        out = []
        for name, s in self.streams.items():
            if s['moved'] or s['last'] == -math.inf:
                out.append(name)
            elif running:
                # a tick's quantum of simulation time: 1e-9 s of slack for the rounding
                if now_sim - s['last'] >= 1.0 / s['rate'] - 1e-9:
                    out.append(name)
            elif now_wall - s['wall'] >= repeat:
                out.append(name)
        return out

    def publish(self, sim, stamp: int, colors: np.ndarray, running: bool,
                repeat: float, live=None) -> None:
        """Render and publish the cameras that are due (:meth:`due`), on the live view too
        when there is one (:meth:`.live_view.LiveView.publish_camera`)."""
        from .conversions import camera_info, image, organised_cloud
        from . import messages
        now_wall = time.monotonic()
        for name in self.due(running, sim.time, now_wall, repeat):
            s = self.streams[name]
            cam: Camera = s['camera']
            depth, rgb = cam.render(sim, colors)
            frame = optical_frame(name)
            s['depth'].publish(image(depth, stamp, frame))
            s['color'].publish(image(rgb, stamp, frame))
            s['info'].publish(camera_info(cam.intrinsics, cam.width, cam.height, stamp,
                                          frame))
            if s['cloud'] is not None:
                s['cloud'].publish(organised_cloud(cam.points(depth), stamp, frame))
            s['pose_out'].publish(messages.pose(stamp, self.node.frame_id, cam.position,
                                                cam.orientation))
            if live is not None:
                live.publish_camera(name, stamp, frame, depth, rgb, cam.intrinsics)
            s['last'], s['wall'], s['moved'] = sim.time, now_wall, False
