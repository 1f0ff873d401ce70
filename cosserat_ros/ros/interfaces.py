"""The node's topics and services, declared once: the manual's table (doc/node.md) is
generated from :data:`INTERFACES`, and a test starts a node with every optional interface
on and compares its graph with it.

Names are relative to the node (``~/``), so namespaces and remapping work; ``<name>`` is
an obstacle's, a handle's or a camera's name. ``when`` says which parameters make the
interface exist (space-separated; ``commands``: unless ``observe_only``).
"""
from __future__ import annotations

from typing import NamedTuple, Tuple

__all__ = ['Interface', 'INTERFACES']


class Interface(NamedTuple):
    name: str
    type: str             # package/Type
    kind: str             # 'publisher', 'subscription' or 'service'
    when: str             # the parameters it depends on; '' for always
    text: str             # what it carries (Markdown)


#: every topic and service of the node, in the manual's order
INTERFACES: Tuple[Interface, ...] = (
    Interface('~/mesh', 'visualization_msgs/MarkerArray', 'publisher', '',
              'every tick: TRIANGLE_LIST (id 0, per-vertex colours), LINE_LIST wireframe (id 1,'
              " optional), pinned and held vertices as SPHERE_LIST (id 2), the handles' origins"
              ' as SPHERE_LIST (id 3); namespace `cloth`'),
    Interface('~/energy', 'diagnostic_msgs/DiagnosticArray', 'publisher', '',
              'every tick: status `energy` with `kinetic`, `stretching`, `bending`, `coupling`,'
              ' `elastic`, `gravity`, `external_work`, `dissipated`, `total` [J], `sim_time`, '
              '`step`; level OK / WARN (paused) / ERROR (diverged)'),
    Interface('/diagnostics', 'diagnostic_msgs/DiagnosticArray', 'publisher', '',
              '~1 Hz: real-time factor, step and publishing cost, dt vs critical dt, vertex '
              'count, rejected-message counts; with obstacles `contacts`, '
              '`deepest_penetration_m`, `feature_pairs`, `feature_active`, `released_vertices`'
              ' (those an obstacle placed through them does not act on yet); with '
              'self-collision its pair counts; with the implicit solver its convergence'),
    Interface('/clock', 'rosgraph_msgs/Clock', 'publisher', 'publish_clock',
              'simulation time (reliable, transient local), when `publish_clock`'),
    Interface('~/points', 'sensor_msgs/PointCloud2', 'publisher', 'publish.points',
              'every tick when `publish.points`: one point per vertex, in vertex order, float32'
              ' fields `x y z vx vy vz`'),
    Interface('~/shape', 'shape_msgs/Mesh', 'publisher', 'publish.shape',
              "every tick when `publish.shape`: the cloth's triangles and vertices in "
              '`frame_id` (what MoveIt collision objects take)'),
    Interface('~/vertex_forces', 'std_msgs/Float64MultiArray', 'subscription', 'commands',
              'rows `[index, fx, fy, fz]` [N]; replaces the previous set; empty clears'),
    Interface('~/point_forces', 'std_msgs/Float64MultiArray', 'subscription', 'commands',
              'rows `[px, py, pz, fx, fy, fz]` in `frame_id`: each force goes to the closest '
              "point of the cloth (its triangle's vertices, barycentric)"),
    Interface('~/force_field', 'geometry_msgs/Vector3Stamped', 'subscription', 'commands',
              'uniform force per unit mass [m/s^2]; frame must be `frame_id` (or empty)'),
    Interface('~/wind', 'geometry_msgs/Vector3Stamped', 'subscription', 'commands',
              'wind velocity [m/s] in `frame_id` (or empty), acting through the air model '
              '(`air.enabled`); lapses after `force_timeout` back to `air.wind`; refused while '
              'air is off, non-finite, in another frame or faster than `max_wind`'),
    Interface('~/obstacles', 'visualization_msgs/MarkerArray', 'subscription', 'commands',
              'SPHERE, CUBE, CYLINDER, TRIANGLE_LIST (closed) markers in `frame_id` become '
              'obstacles named `<ns>_<id>`; ADD again moves one (velocity from its last pose), '
              "DELETE, DELETEALL (the markers' obstacles); at most 64 markers and 30,000 mesh "
              'points per message, applied all or not at all'),
    Interface('~/obstacle_markers', 'visualization_msgs/MarkerArray', 'publisher', '',
              '~1 Hz while there are obstacles and once on every change (a DELETEALL first, so '
              "the last one's removal clears it): every obstacle, for RViz / Foxglove"),
    Interface('~/contact/<name>', 'geometry_msgs/WrenchStamped', 'publisher', 'obstacles.names',
              'every tick, per obstacle: the force the cloth exerts on it over the last step '
              'and the torque about its origin (at rest on it: its weight)'),
    Interface('~/handles/<name>/target', 'geometry_msgs/PoseStamped',
              'subscription', 'handles.names commands',
              'pose of handle `<name>` in `frame_id`; before a grasp it places the handle; '
              'after it, with a header stamp of zero, moves it there over the sim time since '
              'the previous target, and with a stamp T ahead of sim time arrives there at T, '
              'after the targets already given before T (a trajectory streamed ahead, up to 256'
              ' targets; linear, slerp); refused: NaN, other frames, unnormalised quaternions, '
              'a stamp not ahead of sim time, and while grasped faster than `handles.max_speed`'),
    Interface('~/handles/<name>/grasp', 'std_srvs/SetBool', 'service', 'handles.names commands',
              'true: grab the vertices within `handles.<name>.radius` of the target; false: '
              'release (with their velocity)'),
    Interface('~/handles/<name>/wrench', 'geometry_msgs/WrenchStamped',
              'publisher', 'handles.names',
              'every tick: force and torque (about the handle) the handle exerts on the cloth; '
              'zero when free'),
    Interface('~/cameras/<name>/depth/image_raw', 'sensor_msgs/Image',
              'publisher', 'cameras.names',
              'per camera at `cameras.<name>.rate` [Hz of sim time]: `32FC1` depth [m along the'
              ' optical axis, NaN where nothing is seen], `rgb8` colour; frame '
              '`<name>_optical_frame` (see *Cameras*)'),
    Interface('~/cameras/<name>/color/image_raw', 'sensor_msgs/Image',
              'publisher', 'cameras.names',
              'with every depth image: the `rgb8` colour image of the same view'),
    Interface('~/cameras/<name>/camera_info', 'sensor_msgs/CameraInfo',
              'publisher', 'cameras.names',
              'with every image: K, R = I, P = [K | 0], `plumb_bob` with zero D'),
    Interface('~/cameras/<name>/points', 'sensor_msgs/PointCloud2',
              'publisher', 'cameras.names cameras.<name>.points',
              'with `cameras.<name>.points`: organised (height x width), `x y z` float32 in the'
              ' optical frame, NaN where nothing is seen'),
    Interface('~/cameras/<name>/pose_out', 'geometry_msgs/PoseStamped',
              'publisher', 'cameras.names',
              "with every image: the optical frame's pose in `frame_id` (what a tf broadcaster "
              'relays)'),
    Interface('~/cameras/<name>/pose', 'geometry_msgs/PoseStamped',
              'subscription', 'cameras.names',
              'moves the camera (finite, unit quaternion, `frame_id` or empty; refused and '
              'counted otherwise)'),
    Interface('~/rejections', 'diagnostic_msgs/DiagnosticStatus', 'publisher', '',
              'every refused input (at most 20 per tick; all are counted in `/diagnostics`): '
              '`name` its topic (`/cloth_node/handles/left/target`), `message` the reason, '
              '`values` the sim time and the offending values'),
    Interface('~/reset', 'std_srvs/Trigger', 'service', 'commands',
              'back to the rest shape at t = 0 (also recovers from a divergence; handles let '
              'go)'),
    Interface('~/pause', 'std_srvs/SetBool', 'service', 'commands',
              'pause (true) or resume (false)'),
)
