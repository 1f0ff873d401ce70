"""cloth_node's virtual cameras through real rclpy subscribers: the sensor_msgs conventions
(encodings, steps, sizes, CameraInfo against the images), image_geometry-style
back-projection with K, frames and stamps, the pose topic, the schedule in simulation
time, and the refusal of bad parameters."""
import math

import numpy as np
import pytest
import rclpy
from geometry_msgs.msg import PoseStamped
from rclpy.context import Context
from rclpy.parameter import Parameter
from sensor_msgs.msg import CameraInfo, Image, PointCloud2

from cosserat_ros.camera import Camera
from cosserat_ros.ros.cameras import MAX_CAMERAS, PIXEL_BUDGET
from cosserat_ros.ros.node import ClothNode, ConfigError
from test_node import Harness, OVERRIDES, _pose

TOP = {'cameras.names': ['top'], 'cameras.top.width': 64, 'cameras.top.height': 48,
       'cameras.top.fov': 70.0, 'cameras.top.position': [0.05, -0.02, 1.0],
       'cameras.top.orientation': [1.0, 0.0, 0.0, 0.0], 'cameras.top.rate': 10.0,
       'cameras.top.points': True}
BASE = '/cloth_node/cameras/top'


class Recorder:
    def __init__(self, harness):
        self.msgs = {k: [] for k in ('depth', 'color', 'info', 'points', 'pose_out')}
        peer = harness.peer
        for key, mtype, topic in (('depth', Image, 'depth/image_raw'),
                                  ('color', Image, 'color/image_raw'),
                                  ('info', CameraInfo, 'camera_info'),
                                  ('points', PointCloud2, 'points'),
                                  ('pose_out', PoseStamped, 'pose_out')):
            peer.create_subscription(mtype, f'{BASE}/{topic}', self.msgs[key].append, 10)

    def complete(self, n=1):
        return all(len(v) >= n for v in self.msgs.values())


def _stamp(msg):
    return msg.header.stamp.sec + 1e-9 * msg.header.stamp.nanosec


@pytest.fixture
def cam():
    harness = Harness(**TOP)
    rec = Recorder(harness)
    assert harness.spin_until(lambda: rec.complete(3), 30), \
        {k: len(v) for k, v in rec.msgs.items()}
    yield harness, rec
    harness.close()


def test_images_info_and_cloud_follow_the_ros_conventions(cam):
    harness, rec = cam
    depth, color, info = rec.msgs['depth'][-1], rec.msgs['color'][-1], rec.msgs['info'][-1]
    w, h = 64, 48
    assert (depth.width, depth.height, depth.encoding, depth.step) == (w, h, '32FC1', 4 * w)
    assert (color.width, color.height, color.encoding, color.step) == (w, h, 'rgb8', 3 * w)
    assert len(depth.data) == 4 * w * h and len(color.data) == 3 * w * h
    assert depth.is_bigendian == 0 and color.is_bigendian == 0
    assert (info.width, info.height) == (w, h)
    assert info.distortion_model == 'plumb_bob' and list(info.d) == [0.0] * 5
    K = np.array(info.k).reshape(3, 3)
    ref = Camera(w, h, 70.0, (0, 0, 1), (1, 0, 0, 0)).intrinsics
    np.testing.assert_allclose(K, ref)
    np.testing.assert_allclose(np.array(info.r).reshape(3, 3), np.eye(3))
    np.testing.assert_allclose(np.array(info.p).reshape(3, 4), np.hstack([ref, np.zeros((3, 1))]))
    # one frame: every topic in the camera's optical frame, at one simulation time
    for key in ('depth', 'color', 'info', 'points'):
        assert rec.msgs[key][-1].header.frame_id == 'top_optical_frame'
    pose = rec.msgs['pose_out'][-1]
    assert pose.header.frame_id == 'world'
    assert (pose.pose.position.x, pose.pose.position.y, pose.pose.position.z) == \
        (0.05, -0.02, 1.0)
    stamps = {key: [_stamp(m) for m in v] for key, v in rec.msgs.items()}
    common = set(stamps['depth']) & set(stamps['color']) & set(stamps['info']) & \
        set(stamps['points']) & set(stamps['pose_out'])
    assert len(common) >= 2
    # the depth: the cloth (about 1 m below) is seen at the centre, the sky at a corner
    z = np.frombuffer(bytes(depth.data), dtype='<f4').reshape(h, w)
    assert 0.5 < z[h // 2, w // 2] < 1.5
    # image_geometry: projectPixelTo3dRay(u, v) * depth = the cloud's point
    cloud = next(m for m in reversed(rec.msgs['points']) if _stamp(m) == _stamp(depth))
    assert (cloud.height, cloud.width, cloud.point_step, cloud.row_step) == (h, w, 12, 12 * w)
    assert [f.name for f in cloud.fields] == ['x', 'y', 'z'] and not cloud.is_dense
    pts = np.frombuffer(bytes(cloud.data), dtype='<f4').reshape(h, w, 3)
    u, v = np.meshgrid(np.arange(w), np.arange(h))
    ray = np.stack([(u - K[0, 2]) / K[0, 0], (v - K[1, 2]) / K[1, 1], np.ones((h, w))], -1)
    assert np.array_equal(np.isnan(pts[..., 2]), np.isnan(z))
    ok = np.isfinite(z)
    assert ok.sum() > 100
    np.testing.assert_allclose(pts[ok], ray[ok] * z[ok][:, None], rtol=1e-6, atol=1e-6)
    rgb = np.frombuffer(bytes(color.data), dtype=np.uint8).reshape(h, w, 3)
    assert np.all(rgb[~ok] == rgb[~ok][0])          # one plain background


def test_images_come_at_the_rate_in_simulation_time(cam):
    harness, rec = cam
    n = len(rec.msgs['depth'])
    assert harness.spin_until(lambda: len(rec.msgs['depth']) >= n + 4, 30)
    t = np.array([_stamp(m) for m in rec.msgs['depth']])
    period = 1.0 / 10.0
    assert np.all(np.diff(t) >= period - 1e-6), np.diff(t)
    # ... and at the first published state after a period has passed: no ~/mesh between
    # a frame's due time and the next frame
    states = np.array([_stamp(m.markers[0]) for m in harness.meshes])
    for t0, t1 in zip(t[:-1], t[1:]):
        skipped = states[(states >= t0 + period - 1e-6) & (states < t1)]
        assert skipped.size == 0, (t0, t1, skipped)


def test_the_pose_topic_moves_the_camera_and_bad_poses_are_refused(cam):
    harness, rec = cam
    pub = harness.peer.create_publisher(PoseStamped, f'{BASE}/pose', 10)
    q = (0.0, math.sin(math.pi / 2 * 0.9), 0.0, math.cos(math.pi / 2 * 0.9))
    sub = harness.node.cameras.streams['top']
    before = harness.node.rejected['cameras']
    for bad in (_pose((0.0, 0.0, 1.0), (0.0, 0.0, 0.0, 2.0)),
                _pose((0.0, float('nan'), 1.0)),
                _pose((0.0, 0.0, 1.0), frame='map')):
        pub.publish(bad)
        assert harness.spin_until(lambda: harness.node.rejected['cameras'] > before, 10)
        before = harness.node.rejected['cameras']
    np.testing.assert_allclose(sub['camera'].position, (0.05, -0.02, 1.0))
    pub.publish(_pose((0.3, 0.1, -0.8), q))
    assert harness.spin_until(
        lambda: rec.msgs['pose_out'][-1].pose.position.z == pytest.approx(-0.8), 10)
    o = rec.msgs['pose_out'][-1].pose.orientation
    np.testing.assert_allclose((o.x, o.y, o.z, o.w), q, atol=1e-12)
    assert harness.node.rejected['cameras'] == 3
    assert harness.node.diverged is None and not harness.node.paused


@pytest.mark.parametrize('params, match', [
    ({'cameras.top.width': 0}, 'cameras.top: width must be in'),
    ({'cameras.top.height': 100_000}, 'height must be in'),
    ({'cameras.top.fov': 180.0}, 'fov must be in'),
    ({'cameras.top.orientation': [0.0, 0.0, 0.0, 0.5]}, 'unit quaternion'),
    ({'cameras.top.rate': 60.0}, r'rate must be in \(0, publish_rate = 50\]'),
    ({'cameras.top.rate': 0.0}, 'rate must be in'),
    ({'cameras.top.near': 2.0, 'cameras.top.far': 1.0}, 'near < far'),
    ({'cameras.top.width': 2048, 'cameras.top.height': 2048, 'cameras.top.rate': 15.0},
     'at most ' + f'{PIXEL_BUDGET:.3g}'.replace('+', r'\+')),
    ({'cameras.names': ['top'] + [f'c{i}' for i in range(MAX_CAMERAS)]},
     f'at most {MAX_CAMERAS}'),
    ({'cameras.names': ['top', 'top']}, 'duplicates'),
    ({'cameras.top.size': 3}, 'unknown parameter cameras.top.size'),
])
def test_bad_camera_parameters_are_refused_with_the_reason(params, match):
    ctx = Context()
    rclpy.init(context=ctx)
    try:
        with pytest.raises(ConfigError, match=match):
            ClothNode(context=ctx, parameter_overrides=[
                Parameter(k, value=v) for k, v in {**OVERRIDES, **TOP, **params}.items()])
    finally:
        rclpy.shutdown(context=ctx)
