"""``cloth_node``: a ROS 2 node that owns a :class:`ClothSimulator` and serves the cloth.

Topics (relative, so namespaces and remapping work):

=======================  =====================================  ============================
name                     type                                   direction
=======================  =====================================  ============================
``~/mesh``               visualization_msgs/MarkerArray         out, every tick
``~/energy``             diagnostic_msgs/DiagnosticArray        out, every tick
``~/points``             sensor_msgs/PointCloud2                out, every tick
                                                                (``publish.points``)
``~/shape``              shape_msgs/Mesh                        out, every tick
                                                                (``publish.shape``)
``/diagnostics``         diagnostic_msgs/DiagnosticArray        out, ~1 Hz
``/clock``               rosgraph_msgs/Clock                    out (``publish_clock``)
``~/vertex_forces``      std_msgs/Float64MultiArray             in: rows [index, fx, fy, fz]
``~/point_forces``       std_msgs/Float64MultiArray             in: rows [px,py,pz, fx,fy,fz]
``~/force_field``        geometry_msgs/Vector3Stamped           in: uniform [m/s^2]
``~/wind``               geometry_msgs/Vector3Stamped           in: wind velocity [m/s]
                                                                (``air.enabled``)
``~/obstacles``          visualization_msgs/MarkerArray         in: add / move / delete
``~/obstacle_markers``   visualization_msgs/MarkerArray         out: the obstacles, ~1 Hz
``~/contact/<name>``     geometry_msgs/WrenchStamped            out, every tick: what the
                                                                cloth exerts on obstacle
                                                                <name> (torque about its
                                                                origin)
``~/handles/<n>/target`` geometry_msgs/PoseStamped              in: handle <n>'s pose
``~/handles/<n>/grasp``  std_srvs/SetBool                       service: grab / release
``~/handles/<n>/wrench`` geometry_msgs/WrenchStamped            out, every tick
``~/rejections``         diagnostic_msgs/DiagnosticStatus       out: each refused input,
                                                                its topic and reason
``~/reset``              std_srvs/Trigger                       service
``~/pause``              std_srvs/SetBool                       service
=======================  =====================================  ============================

Every header is stamped with simulation time; the node itself keeps ``use_sim_time``
false and publishes ``/clock`` so that consumers with ``use_sim_time:=true`` agree.

The node only wires things together: parameters and their validation are in
:mod:`.params`, command parsing in :mod:`.commands`, the tick's pacing in :mod:`.pacing`,
the messages in :mod:`.conversions` (the cloth's, as CDR bytes) and :mod:`.messages` (the
others: clock, wrenches, obstacle markers, status).
"""
from __future__ import annotations

from dataclasses import dataclass
import math
import os
import sys
import time
import traceback
from typing import Dict, List, Optional, Tuple

import numba
import numpy as np
import rclpy
from rclpy.executors import ExternalShutdownException
from rclpy.node import Node
from rclpy.parameter import Parameter
from rclpy.qos import DurabilityPolicy, QoSProfile, ReliabilityPolicy
from rclpy.serialization import deserialize_message
from rcl_interfaces.msg import ParameterDescriptor, SetParametersResult
from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus
from geometry_msgs.msg import PoseStamped, Vector3Stamped, WrenchStamped
from sensor_msgs.msg import PointCloud2
from shape_msgs.msg import Mesh
from rosgraph_msgs.msg import Clock
from std_msgs.msg import Float64MultiArray
from std_srvs.srv import SetBool, Trigger
from visualization_msgs.msg import MarkerArray

from ..core import warmup
from ..core.air import Air
from ..core.contact import mesh_distance_field
from ..core.handles import MAX_WAYPOINTS, turn_angle
from ..core.simulator import ClothSimulator, Material, SimulationDiverged, steps_tiled
from . import commands, messages, scene
from .conversions import (mesh_marker_array, OPTIONAL_MARKERS, optional_markers,
                          percentile, point_cloud, shape_mesh, vertex_colors)
from .cameras import CameraStreams, camera_specs
from .pacing import Pacer
from .params import (AIR_KEYS, CAMERA_KEYS, check_choice, check_dt, COLORINGS, ConfigError,
                     HANDLE_KEYS, MATERIAL_KEYS, MIN_DT, node_sections, OBSERVER_RUNTIME,
                     OBSTACLE_KEYS,
                     PARAMETERS, params_files, pin_set,
                     RUNTIME_FLOATS, unknown_parameters, vec3, wind as checked_wind)

__all__ = ['ClothNode', 'ConfigError', 'main', 'pin_set', 'percentile']


#: the largest serialised ~/obstacles message [bytes]: commands.MAX_MESH_POINTS points
#: (24 bytes each) and commands.MAX_MARKERS markers' headers, with room to spare
MAX_OBSTACLE_BYTES = 24 * 30_000 + 64 * 512

#: [s] while paused (or diverged) the state is published when it changes and at least
#: this often, not every tick, and the timer ticks every PAUSED_TICK: a paused node idles
PAUSED_PUBLISH_PERIOD = 1.0
PAUSED_TICK = 0.2

#: the most refusals published on ~/rejections between two ticks (the rest are counted
#: in /diagnostics and logged, throttled): a flood of bad input costs bounded work
MAX_REJECTIONS_PER_TICK = 20

#: [s] wall time between two distance-field builds for mesh markers on ~/obstacles (each
#: costs up to ~1 s of the callback thread: commands.MAX_MESH_POINTS, obstacles.py)
MESH_BUILD_PERIOD = 2.0


def solver_warning(report: Dict[str, object], tolerance: float) -> Optional[str]:
    """The WARN message of an implicit step's solve (``ClothSimulator.solve_report``), or
    None: an unconverged solve warns, the linearised solver (``linearized``: one Newton
    step a step by design) does not; both report their residual."""
    if report['converged'] or report['linearized']:
        return None
    return (f"implicit solve not converged (residual {report['residual']:.2g} > "
            f'solver.tolerance {tolerance:g})')


def _marker_key(shape, geometry):
    return (shape, {k: np.asarray(v).tobytes() for k, v in geometry.items()})


def _angular_velocity(q0, q1, dt: float) -> np.ndarray:
    """The constant angular velocity [rad/s, world frame] turning unit quaternion q0
    (x, y, z, w) into q1 in dt seconds: the axis-angle of q1 q0^-1 over dt."""
    x0, y0, z0, w0 = -q0[0], -q0[1], -q0[2], q0[3]          # q0^-1
    x1, y1, z1, w1 = q1
    d = np.array([w1 * x0 + x1 * w0 + y1 * z0 - z1 * y0,
                  w1 * y0 - x1 * z0 + y1 * w0 + z1 * x0,
                  w1 * z0 + x1 * y0 - y1 * x0 + z1 * w0,
                  w1 * w0 - x1 * x0 - y1 * y0 - z1 * z0])
    if d[3] < 0:
        d = -d
    s = float(np.linalg.norm(d[:3]))
    if s < 1e-12:
        return np.zeros(3)
    angle = 2.0 * math.atan2(s, d[3])
    return d[:3] / s * angle / dt


#: why the node refuses ``use_sim_time`` true: its timer would then wait for the /clock
#: that only its own ticks publish, and the cloth would never move again
SIM_TIME_REASON = ('use_sim_time must stay false: this node is the source of /clock (its '
                   'ticks run on wall time and publish it); set use_sim_time on the nodes '
                   'that consume it')

@dataclass
class _Force:
    indices: np.ndarray
    forces: np.ndarray
    received: float


def _vector_values(v) -> Dict[str, object]:
    """A Vector3's components as the offending values of a rejection."""
    return {'x': float(v.x), 'y': float(v.y), 'z': float(v.z)}


class ClothNode(Node):
    """Owns the simulator; steps it in real time on a timer and publishes it."""

    def __init__(self, name: str = 'cloth_node', argv=None, **kwargs):
        super().__init__(name, **kwargs)
        self._declare()
        p = self._values()
        # everything that needs no compiled kernel is checked first: a bad file fails fast
        self._check_parameter_names(p, sys.argv if argv is None else argv)
        if self.get_parameter('use_sim_time').value:
            raise ConfigError(SIM_TIME_REASON)
        self.observe_only = bool(p['observe_only'])
        self.mesh = scene.build_mesh(p)
        material = self._initial_material(p)
        scene.check_solver(p)
        self.implicit = p['solver'] == 'implicit'
        settings = scene.checked_settings(p, self.mesh)
        self._max_wind = p['max_wind']
        self._steady_wind = settings.wind
        check_dt(p['dt'])
        t0 = time.perf_counter()
        # with a cold compile cache, a second process compiles on the other core what the
        # start-up below needs after its step (cosserat_ros.core.warmup)
        warmup.start(steps_tiled(self.mesh.n_vertices, p['divergence']), material.phi != 0.0)
        self.sim = ClothSimulator(self.mesh, material, dt=max(p['dt'], 1e-12),
                                  divergence=p['divergence'], check_dt=False,
                                  solver=p['solver'])
        if self.implicit:
            self.sim.solver_iterations = p['solver.iterations']
            self.sim.solver_tolerance = p['solver.tolerance']
        else:
            unused = [k for k in ('solver.iterations', 'solver.tolerance')
                      if k in self._parameter_overrides]
            if unused:
                self.get_logger().warning(f'{", ".join(unused)}: controls of the implicit '
                                          'solver, unused with solver: explicit')
        # compile (or load from cache) every kernel of the step and of the energy report
        # before any topic exists: a recorder that starts when the topics appear must not
        # wait through a first tick that compiles
        self.sim.step(1)
        self.sim.energy_and_densities()
        self.sim.reset()
        check_dt(p['dt'], math.inf if self.implicit else self.sim.critical_dt())
        self.sim.dt = p['dt']
        self.get_logger().info(
            f'{self.mesh}: kernels ready and critical dt {self.sim.critical_dt():.3g} s '
            f'found in {time.perf_counter() - t0:.2f} s')
        # what the commands call, compiled (or loaded) before any topic: the closest-point
        # query of ~/point_forces, the distance field of a mesh marker on ~/obstacles
        commands.point_forces(np.zeros((1, 6)), self.sim.positions, self.mesh.faces)
        if not self.observe_only:
            mesh_distance_field(*warmup.TETRAHEDRON, 0.25, 0.1)
        scene.apply_settings(self.sim, settings, p)
        self.frame_id = p['frame_id']
        self._wrench_pubs: Dict[int, object] = {}
        self._marker_seen: Dict[int, Tuple[float, np.ndarray, np.ndarray]] = {}
        self._declared_obstacles(p['obstacles.names'])
        self._coloring = check_choice(p['coloring'], COLORINGS, 'coloring')
        self._wireframe = bool(p['wireframe'])
        self._force_timeout = p['force_timeout']
        self._max_force = p['max_force']
        self._max_acc = p['max_acceleration']
        self._status_period = p['status_period']
        self._forces: Dict[str, Optional[_Force]] = {'vertex': None, 'point': None}
        self._field: Optional[Tuple[np.ndarray, float]] = None
        self._wind: Optional[Tuple[np.ndarray, float]] = None     # ~/wind: (v, received)
        self.rejected = {'vertex_forces': 0, 'point_forces': 0, 'force_field': 0,
                         'wind': 0, 'obstacles': 0, 'handles': 0, 'cameras': 0}
        self.paused = False
        self.diverged: Optional[str] = None
        self.period = 1.0 / p['publish_rate']
        self.pacer = Pacer(self.period, p['real_time_factor'])
        self._dirty = True                 # something to publish while paused
        self._last_publish = -math.inf
        self._rtf = 1.0
        self._window = [time.monotonic(), 0.0]   # wall start, sim advanced since
        self._last_status = time.monotonic()
        self._last_diag = 0.0

        reliable = QoSProfile(depth=5, reliability=ReliabilityPolicy.RELIABLE,
                              durability=DurabilityPolicy.VOLATILE)
        self.mesh_pub = self.create_publisher(MarkerArray, '~/mesh', reliable)
        self.energy_pub = self.create_publisher(DiagnosticArray, '~/energy', reliable)
        self.diag_pub = self.create_publisher(DiagnosticArray, '/diagnostics', reliable)
        self.rejections_pub = self.create_publisher(DiagnosticStatus, '~/rejections',
                                                    QoSProfile(depth=50))
        self._rejections_sent = 0            # since the last tick
        self.points_pub = (self.create_publisher(PointCloud2, '~/points', reliable)
                           if p['publish.points'] else None)
        self.shape_pub = (self.create_publisher(Mesh, '~/shape', reliable)
                          if p['publish.shape'] else None)
        self.clock_pub = None
        if p['publish_clock']:
            latched = QoSProfile(depth=1, reliability=ReliabilityPolicy.RELIABLE,
                                 durability=DurabilityPolicy.TRANSIENT_LOCAL)
            self.clock_pub = self.create_publisher(Clock, '/clock', latched)
        if not self.observe_only:
            # raw: a message's size is checked before rclpy builds its Python object
            self.create_subscription(
                Float64MultiArray, '~/vertex_forces',
                self._sized('vertex_forces', Float64MultiArray, commands.MAX_FORCE_BYTES,
                            self.on_vertex_forces), 10, raw=True)
            self.create_subscription(
                Float64MultiArray, '~/point_forces',
                self._sized('point_forces', Float64MultiArray, commands.MAX_FORCE_BYTES,
                            self.on_point_forces), 10, raw=True)
            self.create_subscription(Vector3Stamped, '~/force_field', self.on_force_field, 10)
            self.create_subscription(Vector3Stamped, '~/wind', self.on_wind, 10)
            self.create_subscription(
                MarkerArray, '~/obstacles',
                self._sized('obstacles', MarkerArray, MAX_OBSTACLE_BYTES, self.on_obstacles),
                10, raw=True)
        self.obstacle_pub = self.create_publisher(MarkerArray, '~/obstacle_markers',
                                                  reliable)
        self._last_obstacle_pub = -1.0
        self._marker_points: Dict[int, list] = {}
        self._last_field_build = -math.inf
        for oid in self.sim.obstacles:
            self._add_wrench_pub(oid)
        self._max_handle_speed = p['handles.max_speed']
        self._handles = self._declared_handles(p['handles.names'], reliable)
        cameras = self._declared_cameras(p)
        if cameras:                    # the renderer compiled (or loaded) before any topic
            next(iter(cameras.values()))['camera'].render(self.sim)
        self.cameras = CameraStreams(self, cameras, reliable)
        if not self.observe_only:
            self.create_service(Trigger, '~/reset', self.on_reset)
            self.create_service(SetBool, '~/pause', self.on_pause)
        self.live = None
        if p['foxglove.port']:
            self.live = self._live_view(p['foxglove.port'], p['foxglove.host'])
        self.add_on_set_parameters_callback(self.validate_parameters)
        self.add_post_set_parameters_callback(self.apply_parameters)
        self.timer = self.create_timer(self.period, self.tick)

    # ------------------------------------------------------------------ set-up
    def _declare(self):
        for name, (default, desc) in PARAMETERS.items():
            try:
                self.declare_parameter(name, default, desc)
            except Exception as exc:   # rclpy's InvalidParameter*Exception family
                raise ConfigError(f'parameter {name}: {exc}') from None

    def _values(self) -> dict:
        return {name: self.get_parameter(name).value for name in PARAMETERS}

    def _check_parameter_names(self, p: dict, argv):
        """Refuse names the node does not know (a typo would otherwise start a default
        cloth) and a params file that has no section for this node."""
        known = set(PARAMETERS) | set(self._parameters)        # rclpy's own: use_sim_time
        for group, keys in (('obstacles', OBSTACLE_KEYS), ('handles', HANDLE_KEYS),
                            ('cameras', CAMERA_KEYS)):
            known |= {f'{group}.{n}.{k}' for n in p[f'{group}.names'] if n for k in keys}
        bad = unknown_parameters(self._parameter_overrides, known)
        if bad:
            raise ConfigError(f'unknown parameter{"s" if len(bad) > 1 else ""} '
                              f'{", ".join(bad)} for {self.get_fully_qualified_name()} '
                              '(doc/node.md lists them all)')
        files = params_files(argv)
        if files and not any(node_sections(path, self.get_fully_qualified_name())[0]
                             for path in files):
            raise ConfigError(f'{", ".join(files)}: no section for node '
                              f'{self.get_fully_qualified_name()} (a file for this node '
                              f'starts with "{self.get_name()}:" or "/**:", then '
                              '"ros__parameters:")')

    def _live_pause(self, args: dict) -> Tuple[bool, str]:
        """The live view's pause, a std_srvs/SetBool: ``{"data": true}`` pauses,
        ``false`` resumes; anything else (no ``data``, ``"false"``, which is a true
        string) is refused, not read as a truth value."""
        data = args.get('data')
        if not isinstance(data, bool):
            return False, f'data must be true or false, got {data!r}'
        return self.pause(data)

    def _live_view(self, port: int, host: str):
        """The Foxglove server (:mod:`.live_view`), or ConfigError with the reason."""
        from .live_view import LiveView
        if not 0 < port < 65536:
            raise ConfigError(f'foxglove.port must be in [1, 65535] (0: off), got {port}')
        handlers = {} if self.observe_only else {
            'reset': lambda args: self.reset(),
            'pause': self._live_pause}
        try:
            live = LiveView(port, host, self.get_fully_qualified_name(), handlers)
        except ImportError as exc:
            raise ConfigError(str(exc)) from None
        except Exception as exc:                     # e.g. the port is taken
            raise ConfigError(f'foxglove.port {port}: {exc}') from None
        self.get_logger().info(f'live view: open ws://{host}:{live.port} in the Foxglove app')
        return live

    def destroy_node(self):
        if getattr(self, 'live', None) is not None:
            self.live.close()
            self.live = None
        return super().destroy_node()

    def _sized(self, topic: str, msg_type, limit: int, handler):
        """A raw-subscription callback: a serialised message above ``limit`` bytes is
        refused unread (bounded work per message: rclpy would otherwise build its Python
        object first), else it is deserialised and handed to ``handler``."""
        def callback(data: bytes):
            if len(data) > limit:
                self._reject(topic, f'message of {len(data)} bytes, at most {limit}')
                return
            try:
                msg = deserialize_message(data, msg_type)
            except Exception as exc:                  # a malformed serialisation
                self._reject(topic, f'undecodable message: {exc}')
                return
            handler(msg)
        return callback

    @staticmethod
    def _group_names(group: str, names) -> list:
        """The non-empty names of ``<group>.names``, refused if one repeats."""
        names = [n for n in names if n]
        if len(set(names)) != len(names):
            raise ConfigError(f'{group}.names has duplicates: {names}')
        return names

    def _declare_group(self, group: str, name: str, keys: dict, what: str) -> dict:
        """Declare ``<group>.<name>.<key>`` (read-only, default ``keys[key]``) for every
        key and return their values."""
        values = {}
        for key, default in keys.items():
            full = f'{group}.{name}.{key}'
            try:
                self.declare_parameter(full, default, ParameterDescriptor(
                    description=f'{what} {name}: {key}', read_only=True))
            except Exception as exc:   # rclpy's InvalidParameter*Exception family
                raise ConfigError(f'parameter {full}: {exc}') from None
            values[key] = self.get_parameter(full).value
        return values

    def _declared_obstacles(self, names):
        """The obstacles of the parameters (``obstacles.names`` and, for each,
        ``obstacles.<name>.<key>``, :data:`.params.OBSTACLE_KEYS`), added as
        :func:`.scene.add_declared_obstacles` adds them."""
        values = {'obstacles.names': self._group_names('obstacles', names)}
        for name in values['obstacles.names']:
            for key, value in self._declare_group('obstacles', name, OBSTACLE_KEYS,
                                                  'obstacle').items():
                values[f'obstacles.{name}.{key}'] = value
        scene.add_declared_obstacles(self.sim, values)

    def _declared_cameras(self, p: dict) -> dict:
        """The cameras of ``cameras.names``, checked (:func:`.cameras.camera_specs`)."""
        values = {'cameras.names': self._group_names('cameras', p['cameras.names']),
                  'publish_rate': p['publish_rate']}
        for name in values['cameras.names']:
            for key, value in self._declare_group('cameras', name, CAMERA_KEYS,
                                                  'camera').items():
                values[f'cameras.{name}.{key}'] = value
        return camera_specs(values)

    def _declared_handles(self, names, qos):
        """The handles of ``handles.names``: their parameters, topics and service."""
        out = {}
        for name in self._group_names('handles', names):
            cfg = self._declare_group('handles', name, HANDLE_KEYS, 'handle')
            if not (isinstance(cfg['radius'], float) and cfg['radius'] > 0):
                raise ConfigError(f'handles.{name}.radius must be a positive float, got '
                                  f'{cfg["radius"]!r}')
            if not (isinstance(cfg['break_force'], float) and cfg['break_force'] >= 0):
                raise ConfigError(f'handles.{name}.break_force must be a float >= 0 (0: '
                                  f'none), got {cfg["break_force"]!r}')
            h = {'radius': cfg['radius'], 'break_force': cfg['break_force'] or None,
                 'id': None, 'target': None, 'received': None,
                 'wrench': self.create_publisher(WrenchStamped, f'~/handles/{name}/wrench',
                                                 qos)}
            if not self.observe_only:
                # deep: a controller may stream a whole trajectory of stamped targets
                # at once (MAX_WAYPOINTS ahead), which a last-10 reader would cut
                self.create_subscription(PoseStamped, f'~/handles/{name}/target',
                                         lambda msg, n=name: self.on_handle_target(n, msg),
                                         MAX_WAYPOINTS)
                self.create_service(SetBool, f'~/handles/{name}/grasp',
                                    lambda req, res, n=name: self.on_grasp(n, req, res))
            out[name] = h
        return out

    def on_handle_target(self, name: str, msg: PoseStamped):
        """A pose for handle ``name``: places it if it holds nothing; if it holds the
        cloth, moves it there: with a header stamp of zero over the sim time since the
        previous target (at least a tick, at most 1 s), starting from where the handle is;
        with a stamp T, a sim time ahead of the node's, arriving at T after the targets
        already given before T (a trajectory streamed ahead; a stamp not ahead is
        refused as late).

        The speed is checked from where the motion starts (the handle now, or the
        waypoint before T), its turn counted at the grasp radius: ``(|p - p_from| + theta
        r) / (t - t_from)`` must not exceed ``handles.max_speed``. From where the handle
        is, not from the last target: many targets in one tick, or while paused, would
        each be one short hop and add up to a jump."""
        h = self._handles[name]
        topic = f'handles/{name}/target'
        stamp = msg.header.stamp.sec + 1e-9 * msg.header.stamp.nanosec
        now = self.sim.time
        offending: Dict[str, object] = {'stamp': float(stamp)}
        try:
            p, q = commands.handle_target(msg, self.frame_id)
            offending.update(x=float(p[0]), y=float(p[1]), z=float(p[2]))
            held = h['id'] is not None and h['id'] in self.sim.handles
            duration = self.period
            if h['target'] is not None:
                duration = min(max(now - h['received'], self.period), 1.0)
            if held and stamp > 0:
                if stamp <= now:
                    raise commands.CommandError(
                        f'stamped {stamp:.4f} s, not ahead of the simulation time '
                        f'{now:.4f} s ({now - stamp:.4f} s late): a stamped target says '
                        'when to be there')
                after = [w for w in self.sim.handle_waypoints(h['id']) if w[0] < stamp]
                t_from, p_from, q_from = after[-1]
                interval = stamp - t_from
            elif held:
                d = self.sim.handles[h['id']]
                t_from, p_from, q_from = now, np.asarray(d['position']), d['orientation']
                interval = duration
            if held:
                theta = turn_angle(np.asarray(q_from), q)
                speed = (float(np.linalg.norm(p - np.asarray(p_from)))
                         + theta * h['radius']) / interval
                offending['speed'] = speed
                if speed > self._max_handle_speed:
                    raise commands.CommandError(
                        f'target {speed:.3g} m/s from where the handle is '
                        f'{"at " + format(t_from, ".4f") + " s " if stamp > 0 else ""}'
                        f'(its turn at the grasp radius included), above '
                        f'handles.max_speed {self._max_handle_speed:.3g}')
                if stamp > 0:
                    try:
                        self.sim.move_handle(h['id'], p, q, at=stamp)
                    except ValueError as exc:             # too many waypoints ahead
                        raise commands.CommandError(str(exc)) from None
                else:
                    self.sim.move_handle(h['id'], p, q, duration=duration)
        except commands.CommandError as exc:
            self._reject('handles', f'{name}: {exc}', topic, offending)
            return
        h['target'], h['received'] = (p, q), now
        self._dirty = True

    def on_grasp(self, name: str, request, response):
        h = self._handles[name]
        self._dirty = True
        if request.data:
            if h['id'] is not None:
                response.success, response.message = True, f'{name} holds the cloth already'
                return response
            if h['target'] is None:
                response.success = False
                response.message = (f'no target for {name} yet: publish '
                                    f'~/handles/{name}/target first')
                return response
            p, q = h['target']
            try:
                h['id'] = self.sim.grasp(point=p, radius=h['radius'], name=name,
                                         break_force=h['break_force'], orientation=q)
            except ValueError as exc:
                response.success, response.message = False, str(exc)
                return response
            response.success = True
            response.message = (f'{name} holds {len(self.sim.handles[h["id"]]["vertices"])} '
                                'vertices')
        else:
            if h['id'] is not None and h['id'] in self.sim.handles:
                self.sim.release(h['id'])
            h['id'] = None
            response.success, response.message = True, f'{name} released'
        return response

    def publish_handles(self, stamp: int):
        held = self.sim.handles
        for name, h in self._handles.items():
            if h['id'] is not None and h['id'] not in held:
                h['id'] = None                       # it broke loose
            f = t = np.zeros(3)
            if h['id'] is not None:
                f, t = self.sim.handle_wrench(h['id'])
                if not (np.all(np.isfinite(f)) and np.all(np.isfinite(t))):
                    continue
            h['wrench'].publish(messages.wrench(stamp, self.frame_id, f, t))

    def _add_wrench_pub(self, oid: int):
        name = self.sim.obstacles[oid]['name']
        self._wrench_pubs[oid] = self.create_publisher(WrenchStamped, f'~/contact/{name}', 5)

    def on_obstacles(self, msg: MarkerArray):
        """Markers -> obstacles (:func:`.commands.obstacle_markers`), all or none: ADD
        creates or moves obstacle ``<ns>_<id>`` (its velocity from its last pose), DELETE
        removes it, DELETEALL removes every obstacle made from markers."""
        try:
            ops = commands.obstacle_markers(msg, self.frame_id)
        except commands.CommandError as exc:
            self._reject('obstacles', str(exc))
            return
        builds = sum(1 for op in ops if op[0] == 'add' and op[2] == 'mesh'
                     and not self._same_marker(op))
        wall = time.monotonic()
        if builds and wall - self._last_field_build < MESH_BUILD_PERIOD:
            self._reject('obstacles', f'a new mesh obstacle {wall - self._last_field_build:.2f}'
                                      f' s after the last one (at most one per '
                                      f'{MESH_BUILD_PERIOD} s: each builds a distance field)')
            return
        if builds > 1:
            self._reject('obstacles', f'{builds} new mesh obstacles in one message (one at '
                                      'a time: each builds a distance field)')
            return
        snap = self.sim.obstacle_snapshot()
        seen = dict(self._marker_seen)
        now = self.sim.time
        try:
            for op in ops:
                self._apply_obstacle_op(op, seen, now)
            if sum(1 for oid in seen if oid in self.sim.obstacles) > commands.MAX_MARKERS:
                raise ValueError(f'more than {commands.MAX_MARKERS} obstacles from markers')
            meshes = sum(1 for oid in seen if oid in self.sim.obstacles
                         and self.sim.obstacles[oid]['shape'] == 'mesh')
            if meshes > commands.MAX_MESH_MARKERS:
                raise ValueError(f'more than {commands.MAX_MESH_MARKERS} mesh obstacles from '
                                 'markers (each holds a distance field)')
        except ValueError as exc:
            self.sim.restore_obstacles(snap)
            self._reject('obstacles', str(exc))
            return
        if builds:                 # a refused mesh stops before its field: cheap
            self._last_field_build = wall
        self._marker_seen = {oid: v for oid, v in seen.items() if oid in self.sim.obstacles}
        for oid in list(self._wrench_pubs):
            if oid not in self.sim.obstacles:
                self.destroy_publisher(self._wrench_pubs.pop(oid))
        for oid in self.sim.obstacles:
            if oid not in self._wrench_pubs:
                self._add_wrench_pub(oid)
        self._last_obstacle_pub = -1.0               # republish at the next tick
        self._dirty = True

    def _same_marker(self, op) -> bool:
        """An ADD for a marker obstacle that exists with this very shape and geometry (a
        move, no new distance field)."""
        oid = self.sim.find_obstacle(op[1])
        if oid is None or oid not in self._marker_seen:
            return False
        return self._marker_seen[oid][3] == _marker_key(op[2], op[3])

    def _apply_obstacle_op(self, op, seen, now):
        if op[0] == 'deleteall':
            for oid in list(seen):
                if oid in self.sim.obstacles:
                    self.sim.remove_obstacle(oid)
                del seen[oid]
            return
        oid = self.sim.find_obstacle(op[1])
        if op[0] == 'delete':
            if oid is not None and oid in seen:
                self.sim.remove_obstacle(oid)
                del seen[oid]
            return
        _, name, shape, geometry, (p, q) = op
        if oid is not None and oid not in seen:
            raise ValueError(f'{name} is a declared obstacle, not a marker\'s')
        key = _marker_key(shape, geometry)
        if oid is not None and seen[oid][3] == key:
            t0, p0, q0, _ = seen[oid]
            dt = now - t0
            v = (p - p0) / dt if 0 < dt < 1.0 else np.zeros(3)
            w = _angular_velocity(q0, q, dt) if 0 < dt < 1.0 else np.zeros(3)
            self.sim.set_obstacle_pose(oid, p, q, v, w)
        else:
            if oid is not None:
                self.sim.remove_obstacle(oid)
            place = dict(center=p)
            if shape != 'sphere':
                place['orientation'] = q
            oid = self.sim.add_obstacle(shape, name=name, **geometry, **place)
        seen[oid] = (now, p, q, key)

    def publish_obstacles(self, stamp: int):
        """The obstacles as markers in ``frame_id`` (ns = their name):
        :func:`.messages.obstacle_markers`."""
        arr = messages.obstacle_markers(self.sim.obstacles, self._mesh_points, stamp,
                                        self.frame_id)
        for oid in set(self._marker_points) - set(self.sim.obstacles):
            del self._marker_points[oid]
        self.obstacle_pub.publish(arr)

    def _mesh_points(self, oid: int) -> list:
        """A mesh obstacle's triangles as the points of a TRIANGLE_LIST, in its own frame;
        built once per obstacle (an id's mesh never changes: a new shape is a new id)."""
        if oid not in self._marker_points:
            self._marker_points[oid] = messages.mesh_triangle_points(
                *self.sim.obstacle_mesh(oid))
        return self._marker_points[oid]

    def publish_contact(self, stamp: int):
        for oid, (f, t) in self.sim.contact_forces().items():
            pub = self._wrench_pubs.get(oid)
            if pub is None or not (np.all(np.isfinite(f)) and np.all(np.isfinite(t))):
                continue
            pub.publish(messages.wrench(stamp, self.frame_id, f, t))

    # ------------------------------------------------------------------ commands
    def _reject(self, counter: str, reason: str, topic: Optional[str] = None,
                values: Optional[Dict[str, object]] = None):
        """Refuse an input: count it under ``counter`` (/diagnostics), log it (throttled)
        and publish it on ``~/rejections`` (:func:`.messages.rejection`; at most
        :data:`MAX_REJECTIONS_PER_TICK` between two ticks) named ``<node>/<topic>``
        (default: the counter's topic) with ``values``, the offending values."""
        self.rejected[counter] += 1
        topic = counter if topic is None else topic
        self.get_logger().warning(f'rejected ~/{topic}: {reason} '
                                  f'({self.rejected[counter]} rejected so far)',
                                  throttle_duration_sec=1.0)
        if self._rejections_sent < MAX_REJECTIONS_PER_TICK:
            self._rejections_sent += 1
            self.rejections_pub.publish(messages.rejection(
                f'{self.get_fully_qualified_name()}/{topic}', reason, self.sim.time,
                values or {}, self.get_fully_qualified_name()))

    def on_vertex_forces(self, msg: Float64MultiArray):
        """Rows [index, fx, fy, fz] [N]; replaces the previous set (empty: clear)."""
        try:
            rows = commands.force_rows(msg, 4, self._max_force)
            idx, f = commands.vertex_forces(rows, self.mesh.n_vertices)
            self._check_totals('point', idx, f)
        except commands.CommandError as exc:
            self._reject('vertex_forces', str(exc))
            return
        self._forces['vertex'] = _Force(idx, f, self.sim.time)
        self._push_forces()

    def _check_totals(self, other: str, idx: np.ndarray, f: np.ndarray):
        """``max_force`` bounds the total on each vertex: this message's rows with the
        standing forces of the ``other`` topic."""
        o = self._forces[other]
        if o is not None:
            idx, f = np.concatenate([idx, o.indices]), np.concatenate([f, o.forces])
        commands.check_totals(idx, f, self.mesh.n_vertices, self._max_force)

    def on_point_forces(self, msg: Float64MultiArray):
        """Rows [px, py, pz, fx, fy, fz] in frame_id: each force goes to the closest point
        of the cloth (shared by its triangle's vertices, barycentrically) and stays with
        that material point until replaced."""
        try:
            rows = commands.force_rows(msg, 6, self._max_force)
            idx, f = commands.point_forces(rows, self.sim.positions, self.mesh.faces)
            self._check_totals('vertex', idx, f)
        except commands.CommandError as exc:
            self._reject('point_forces', str(exc))
            return
        self._forces['point'] = _Force(idx, f, self.sim.time)
        self._push_forces()

    def on_force_field(self, msg: Vector3Stamped):
        """Uniform force per unit mass [m/s^2] in frame_id ('' is taken as frame_id)."""
        try:
            v = commands.force_field(msg, self.frame_id, self._max_acc)
        except commands.CommandError as exc:
            self._reject('force_field', str(exc), values=_vector_values(msg.vector))
            return
        self._field = (v, self.sim.time)
        self.sim.force_field = v

    def on_wind(self, msg: Vector3Stamped):
        """Wind velocity [m/s] in frame_id, until it lapses (force_timeout; then back to
        air.wind); refused while air.enabled is false, since it would move nothing."""
        try:
            if self.sim.air is None:
                raise commands.CommandError('air.enabled is false: wind acts only on a cloth '
                                            'in air')
            v = commands.wind(msg, self.frame_id, self._max_wind)
        except commands.CommandError as exc:
            self._reject('wind', str(exc), values=_vector_values(msg.vector))
            return
        self._wind = (v, self.sim.time)
        self.sim.wind = v

    def _initial_material(self, p: dict) -> Material:
        """The material of the material.* parameters (:func:`.scene.initial_material`:
        a preset's constants, overridden by the material.* given explicitly); the
        parameters are then set to what the cloth gets. ConfigError if bad."""
        material = scene.initial_material(p, self._parameter_overrides)
        if p['material.preset']:
            self.set_parameters([Parameter('material.' + k, value=float(getattr(material, k)))
                                 for k in MATERIAL_KEYS])
        return material

    def _enforce_limits(self):
        """A lowered ``max_force``, ``max_acceleration`` or ``max_wind`` also bounds what
        stands (a command is checked when it arrives, and with ``force_timeout`` 0 it
        stands until replaced): the commanded forces, the force field or the streamed
        wind above it are dropped, and the log says so."""
        parts = [f for f in self._forces.values() if f is not None]
        if parts:
            try:
                commands.check_totals(np.concatenate([f.indices for f in parts]),
                                      np.concatenate([f.forces for f in parts]),
                                      self.mesh.n_vertices, self._max_force)
            except commands.CommandError as exc:
                self._forces = {key: None for key in self._forces}
                self._push_forces()
                self.get_logger().warning(f'commanded forces dropped: {exc}')
        if self._field is not None and float(np.linalg.norm(self._field[0])) > self._max_acc:
            self._drop_field()
            self.get_logger().warning('force field dropped: above the new max_acceleration')
        if self._wind is not None and float(np.linalg.norm(self._wind[0])) > self._max_wind:
            self._drop_wind()
            self.get_logger().warning('streamed wind dropped: above the new max_wind; back '
                                      'to air.wind')

    def _drop_field(self):
        """The commanded force field ends (lapsed or above a lowered limit)."""
        self._field = None
        self.sim.force_field = (0.0, 0.0, 0.0)

    def _drop_wind(self):
        """The streamed wind ends (lapsed, above a lowered limit, air off): back to the
        steady ``air.wind``."""
        self._wind = None
        self.sim.wind = self._steady_wind

    def _push_forces(self):
        parts = [f for f in self._forces.values() if f is not None]
        if parts:
            self.sim.set_vertex_forces(np.concatenate([p.indices for p in parts]),
                                       np.concatenate([p.forces for p in parts]))
        else:
            self.sim.clear_vertex_forces()

    def _expire_forces(self, now: float):
        """At sim time ``now`` [s]: the commands not renewed for ``force_timeout`` s of
        sim time lapse (a node slower than real time gives a client that paces on /clock
        the same time to renew them as one at full speed)."""
        if self._force_timeout <= 0:
            return
        described = self.sim.obstacles if self._marker_seen else {}
        for oid, (t0, p0, q0, key) in self._marker_seen.items():
            d = described.get(oid)
            if (d is not None and now - t0 > self._force_timeout
                    and any(d['linear_velocity'] + d['angular_velocity'])):
                self.sim.set_obstacle_pose(oid, d['position'], d['orientation'])
        changed = False
        for key, f in self._forces.items():
            if f is not None and now - f.received > self._force_timeout:
                self._forces[key] = None
                changed = True
                self.get_logger().info(f'{key} forces lapsed after {self._force_timeout} s '
                                       'of sim time without a new message')
        if changed:
            self._push_forces()
        if self._field is not None and now - self._field[1] > self._force_timeout:
            self._drop_field()
            self.get_logger().info('force field lapsed')
        if self._wind is not None and now - self._wind[1] > self._force_timeout:
            self._drop_wind()
            self.get_logger().info('wind lapsed: back to air.wind')

    # ------------------------------------------------------------------ services
    def on_reset(self, request, response):
        response.success, response.message = self.reset()
        return response

    def on_pause(self, request, response):
        response.success, response.message = self.pause(bool(request.data))
        return response

    def reset(self) -> Tuple[bool, str]:
        """Back to the rest shape at t = 0 (``~/reset``, and the live view's service)."""
        self.sim.reset()
        for h in self._handles.values():
            h['id'] = None
            h['received'] = 0.0
        # standing commands lapse force_timeout of sim time from now on
        self._forces = {k: f if f is None else _Force(f.indices, f.forces, 0.0)
                        for k, f in self._forces.items()}
        if self._field is not None:
            self._field = (self._field[0], 0.0)
        if self._wind is not None:
            self._wind = (self._wind[0], 0.0)
        # the markers' obstacles stop where they are, their streams restart at t = 0
        # (their velocity came from poses stamped before the reset, and their lapse
        # after force_timeout compares sim times)
        described = self.sim.obstacles
        for oid, (_, _, _, key) in list(self._marker_seen.items()):
            d = described.get(oid)
            if d is not None:
                self.sim.set_obstacle_pose(oid, d['position'], d['orientation'])
                self._marker_seen[oid] = (0.0, np.array(d['position']),
                                          np.array(d['orientation']), key)
        self.diverged = None
        self.paused = False
        self._retime(True)
        self._window = [time.monotonic(), 0.0]
        self.pacer.restart()
        self.publish_state()
        return True, 'cloth back to its rest shape at t = 0'

    def pause(self, paused: bool) -> Tuple[bool, str]:
        """Pause or resume (``~/pause``, and the live view's service)."""
        if not paused and self.diverged:
            return False, f'simulation diverged ({self.diverged}); call ~/reset first'
        self.paused = paused
        self._dirty = True
        self._retime(not self.paused)
        self.pacer.restart()
        return True, 'paused' if self.paused else 'running'

    # ------------------------------------------------------------------ parameters
    def validate_parameters(self, params: List[Parameter]) -> SetParametersResult:
        """Only validates; :meth:`apply_parameters` applies accepted values."""
        mat = {k: getattr(self.sim.material, k) for k in MATERIAL_KEYS}
        air = {k: getattr(self.sim.air or Air(), k) for k in AIR_KEYS}
        dt = self.sim.dt
        max_wind = next((prm.value for prm in params if prm.name == 'max_wind'),
                        self._max_wind)
        for prm in params:
            name, val = prm.name, prm.value
            if name == 'use_sim_time' and val:
                return SetParametersResult(successful=False, reason=SIM_TIME_REASON)
            if name in ('solver.iterations', 'solver.tolerance') and not self.implicit:
                return SetParametersResult(
                    successful=False, reason=f'{name} is a control of the implicit solver; '
                                             'this node runs solver: explicit (chosen at '
                                             'start-up)')
            if self.observe_only and name not in OBSERVER_RUNTIME:
                return SetParametersResult(
                    successful=False, reason=f'observe_only: {name} cannot change (only '
                                             f'{", ".join(OBSERVER_RUNTIME)} can)')
            if name.startswith('material.'):
                if not isinstance(val, float) or not math.isfinite(val):
                    return SetParametersResult(successful=False,
                                               reason=f'{name} must be a finite float')
                mat[name.split('.', 1)[1]] = val
            elif name == 'dt':
                if not isinstance(val, float) or not (val >= MIN_DT and math.isfinite(val)):
                    return SetParametersResult(successful=False,
                                               reason=f'dt must be a float of at least '
                                                      f'{MIN_DT:g} s')
                dt = val
            elif name == 'gravity':
                try:
                    vec3(val, 'gravity')
                except ConfigError as exc:
                    return SetParametersResult(successful=False, reason=str(exc))
            elif name in ('air.' + k for k in AIR_KEYS):
                if not isinstance(val, float):
                    return SetParametersResult(successful=False,
                                               reason=f'{name} must be a float')
                air[name.split('.', 1)[1]] = val
            elif name == 'air.wind':
                try:
                    checked_wind(val, max_wind if isinstance(max_wind, float) else math.inf)
                except ConfigError as exc:
                    return SetParametersResult(successful=False, reason=str(exc))
            elif name == 'coloring' and val not in COLORINGS:
                return SetParametersResult(successful=False,
                                           reason=f'coloring must be one of {COLORINGS}')
            elif name == 'handles.max_speed':
                if not isinstance(val, float) or not (val > 0 and math.isfinite(val)):
                    return SetParametersResult(successful=False,
                                               reason='handles.max_speed must be a '
                                                      'positive float')
            elif name == 'contact.thickness':
                if not isinstance(val, float) or not (1e-5 <= val <= 0.1):
                    return SetParametersResult(
                        successful=False, reason='contact.thickness must be a float in '
                                                 '[1e-5, 0.1] m')
            elif name in RUNTIME_FLOATS:
                if not isinstance(val, float) or not (val >= 0 and math.isfinite(val)):
                    return SetParametersResult(successful=False,
                                               reason=f'{name} must be a non-negative float')
        names = {prm.name for prm in params}
        if ('max_wind' in names and 'air.wind' not in names and isinstance(max_wind, float)
                and float(np.linalg.norm(self._steady_wind)) > max_wind):
            return SetParametersResult(
                successful=False, reason=f'max_wind {max_wind:g} m/s is below the standing '
                                         f'air.wind ({np.linalg.norm(self._steady_wind):.3g} '
                                         'm/s): lower air.wind first, or both together')
        try:
            material = Material(**mat)
            Air(**air)
        except ValueError as exc:
            return SetParametersResult(successful=False, reason=str(exc))
        if not self.implicit and (material != self.sim.material or dt != self.sim.dt):
            try:
                crit = self.sim.critical_dt(material)
            except (ArithmeticError, ValueError, np.linalg.LinAlgError) as exc:
                return SetParametersResult(
                    successful=False, reason=f'no stable step found for this material '
                                             f'({type(exc).__name__}: {exc})')
            if not dt <= crit:                   # (a NaN limit refuses too)
                return SetParametersResult(
                    successful=False, reason=f'dt = {dt:.3g} s would exceed the critical step '
                                             f'{crit:.3g} s of this mesh and material')
        return SetParametersResult(successful=True)

    def apply_parameters(self, params: List[Parameter]):
        names = {prm.name for prm in params}
        mat = {k: getattr(self.sim.material, k) for k in MATERIAL_KEYS}
        changed_material = False
        changed_air = False
        for prm in params:
            name, val = prm.name, prm.value
            if name.startswith('material.'):
                mat[name.split('.', 1)[1]] = val
                changed_material = True
            elif name.startswith('air.') and name != 'air.wind':
                changed_air = True
            elif name == 'air.wind':
                self._steady_wind = np.array(val, dtype=np.float64)
                if self._wind is None:
                    self.sim.wind = self._steady_wind
            elif name == 'max_wind':
                self._max_wind = val
            elif name == 'dt':
                self.sim.dt = val
            elif name == 'solver.iterations' and self.implicit:
                self.sim.solver_iterations = val
            elif name == 'solver.tolerance' and self.implicit:
                self.sim.solver_tolerance = val
            elif name == 'gravity':
                self.sim.gravity = list(val)
            elif name == 'coloring':
                self._coloring = val
            elif name == 'wireframe':
                self._wireframe = bool(val)
            elif name == 'force_timeout':
                self._force_timeout = val
            elif name == 'max_force':
                self._max_force = val
            elif name == 'max_acceleration':
                self._max_acc = val
            elif name == 'status_period':
                self._status_period = val
            elif name == 'real_time_factor':
                self.pacer.factor = val
            elif name == 'contact.thickness':
                self.sim.contact_thickness = val
            elif name == 'contact.self':
                self.sim.self_collision = bool(val)
            elif name == 'contact.self_friction':
                self.sim.self_friction = val
            elif name == 'handles.max_speed':
                self._max_handle_speed = val
        if names & {'max_force', 'max_acceleration', 'max_wind'}:
            self._enforce_limits()
        if changed_material:
            self.sim.material = Material(**mat)
        if changed_air:
            self.sim.air = scene.build_air(self.get_parameter('air.enabled').value,
                                     {k: self.get_parameter('air.' + k).value
                                      for k in AIR_KEYS})
            if self.sim.air is None and self._wind is not None:
                self._drop_wind()
        self._dirty = True

    # ------------------------------------------------------------------ the loop
    def tick(self):
        """Advance as many steps as keep sim time with wall time (:mod:`.pacing`), then
        publish."""
        now = time.monotonic()
        self._rejections_sent = 0
        if self.live is not None:
            self.live.serve()
        self._expire_forces(self.sim.time)
        if not self.paused and self.diverged is None:
            wanted = self.pacer.wanted(now, self.sim.dt)
            due = self.timer.time_until_next_call()
            done = self.pacer.advance(self._step, wanted, None if due is None else due * 1e-9)
            self.pacer.carry(done, wanted, self.sim.dt, now)
            self._window[1] += done * self.sim.dt
        else:
            self.pacer.last_tick = now
        wall = now - self._window[0]
        if wall >= 1.0:
            self._rtf = self._window[1] / wall if not self.paused else 0.0
            self._window = [now, 0.0]
        running = not self.paused and self.diverged is None
        # paused, nothing moves: the state goes out when it changes and once a second
        if running or self._dirty or now - self._last_publish >= PAUSED_PUBLISH_PERIOD:
            t1 = time.perf_counter()
            # the publishing's parallel kernels (energy densities, cameras) on the count
            # the step measured fastest: beside a busy process, one (core/threads.py)
            was = numba.get_num_threads()
            numba.set_num_threads(self.sim.best_threads)
            try:
                self.publish_state()
            finally:
                numba.set_num_threads(was)
            if running:
                self.pacer.note_publish(time.perf_counter() - t1)
        self._retime(running)
        if now - self._last_diag >= 1.0:
            self._last_diag = now
            self.diag_pub.publish(self.diagnostics())
        if self._status_period > 0 and now - self._last_status >= self._status_period:
            self._last_status = now
            e = self._energy
            state = 'DIVERGED' if self.diverged else ('paused' if self.paused else 'running')
            self.get_logger().info(
                f'{state} t={self.sim.time:.3f} s  RTF {self._rtf:.2f}  step '
                f'{self.pacer.step_cost * 1e3:.3f} ms  E_total {e["total"]:.6g} J  '
                f'(kin {e["kinetic"]:.3g}, elastic {e["elastic"]:.3g})')

    def _retime(self, running: bool):
        """The timer ticks every period while the cloth runs, every
        :data:`PAUSED_TICK` s while it is paused or diverged (an idle node)."""
        ns = int(round((self.period if running else PAUSED_TICK) * 1e9))
        if self.timer.timer_period_ns != ns:
            self.timer.timer_period_ns = ns
            if running:
                self.timer.reset()

    def _step(self, n: int) -> bool:
        """n steps; on a divergence, pause and report, and return False. Any other error
        of the step (the simulator restores its state from before the call) is reported
        the same way, with its traceback in the log: the node stays up."""
        try:
            self.sim.step(n)
        except SimulationDiverged as exc:
            reason = str(exc)
        except Exception as exc:                 # noqa: BLE001 (reported, not hidden)
            reason = f'the step failed: {type(exc).__name__}: {exc}'
            self.get_logger().error(traceback.format_exc())
        else:
            return True
        self.diverged = reason
        self.paused = True
        self._dirty = True
        self.get_logger().error(f'{reason}; paused, call ~/reset to recover')
        return False

    def stamp_ns(self) -> int:
        return int(round(self.sim.time * 1e9))

    def vertex_colors(self) -> np.ndarray:
        return vertex_colors(self._coloring, self.sim, self._densities)

    def publish_state(self):
        """Publish ~/mesh, ~/energy and /clock for the current state."""
        self._dirty = False
        self._last_publish = time.monotonic()
        self._energy, self._densities = self.sim.energy_and_densities()
        x = self.sim.positions
        if not np.all(np.isfinite(x)):       # never publish a NaN (step() restores state)
            return
        stamp = self.stamp_ns()
        if self.clock_pub is not None:     # first: a recorder on sim time logs what follows
            self.clock_pub.publish(messages.clock(stamp))    # at this very instant
        pinned = np.flatnonzero(self.sim.pinned)
        colors = self.vertex_colors()
        handles = np.array([d['position'] for d in self.sim.handles.values()])
        edges = self.mesh.edges if self._wireframe else None
        # an optional marker this message does not draw (the wireframe off, no pin or
        # grasp) is deleted, in every message: a marker stays on screen until deleted,
        # and one lost message must not leave it there
        drawn = optional_markers(edges, pinned, handles)
        self.mesh_pub.publish(mesh_marker_array(
            x, self.mesh.faces, colors, stamp, self.frame_id, edges=edges, pinned=pinned,
            pin_size=0.3 * self.mesh.mean_edge_length, handles=handles,
            delete=sorted(OPTIONAL_MARKERS - drawn)))
        if self.live is not None:
            self.live.publish(stamp, self.frame_id, x, self.mesh.faces, colors, self._energy,
                              lambda: [(d['shape'], d, self.sim.obstacle_mesh(oid)
                                        if d['shape'] == 'mesh' else None)
                                       for oid, d in self.sim.obstacles.items()], handles)
        self.energy_pub.publish(self.energy_message(stamp))
        if self.points_pub is not None:
            self.points_pub.publish(point_cloud(x, self.sim.velocities, stamp, self.frame_id))
        if self.shape_pub is not None:
            self.shape_pub.publish(shape_mesh(x, self.mesh.faces))
        if self._wrench_pubs:
            self.publish_contact(stamp)
        if self._handles:
            self.publish_handles(stamp)
        if self.cameras:
            self.cameras.publish(self.sim, stamp, colors, not self.paused and self.diverged
                                 is None, PAUSED_PUBLISH_PERIOD, self.live)
        mono = time.monotonic()
        # ~1 Hz while there are obstacles, and once after every change: the last
        # obstacle's removal too (the array is then its DELETEALL alone, which clears it
        # from RViz / Foxglove)
        if self._last_obstacle_pub < 0 or (self.sim.obstacles
                                           and mono - self._last_obstacle_pub >= 1.0):
            self._last_obstacle_pub = mono
            self.publish_obstacles(stamp)

    def _status(self, name: str, level: bytes, message: str, values: Dict[str, object],
                stamp: Optional[int] = None) -> DiagnosticArray:
        """:func:`.messages.status` in ``frame_id``, stamped ``stamp`` [ns] (default: now
        in sim time), hardware_id this node's fully qualified name."""
        return messages.status(self.stamp_ns() if stamp is None else stamp, self.frame_id,
                               name, level, message, values,
                               self.get_fully_qualified_name())

    def energy_message(self, stamp: int) -> DiagnosticArray:
        """~/energy: :func:`.messages.energy_status` of the last published energies."""
        return messages.energy_status(stamp, self.frame_id, self._energy, self.sim.time,
                                      self.sim.step_count, self.diverged, self.paused,
                                      self.get_fully_qualified_name())

    def diagnostics(self) -> DiagnosticArray:
        crit = self.sim.critical_dt()
        rej = sum(self.rejected.values())
        if self.diverged:
            level, msg = DiagnosticStatus.ERROR, 'diverged: ' + self.diverged
        elif self.pacer.lagging or (not self.paused
                                    and self._rtf < 0.9 * self.pacer.factor):
            level, msg = DiagnosticStatus.WARN, (
                f'cannot keep the real-time factor asked for (RTF {self._rtf:.2f} of '
                f'{self.pacer.factor:g})')
        elif self.paused:
            level, msg = DiagnosticStatus.WARN, 'paused'
        else:
            level, msg = DiagnosticStatus.OK, 'running'
        vals = {'real_time_factor': float(self._rtf),
                'real_time_factor_asked': float(self.pacer.factor),
                'step_cost_ms': float(self.pacer.step_cost * 1e3),
                'publish_cost_ms': float(self.pacer.publish_cost * 1e3),
                'dt': float(self.sim.dt), 'critical_dt': float(crit),
                'dt_over_critical': float(self.sim.dt / crit),
                'vertices': self.mesh.n_vertices, 'faces': self.mesh.n_faces,
                'sim_time': float(self.sim.time), 'paused': self.paused,
                'rejected_total': rej, 'obstacles': len(self.sim.obstacles),
                'air': self.sim.air is not None,
                'wind_speed': float(np.linalg.norm(self.sim.wind)),
                'solver': self.sim.solver_kind}
        if self.implicit:
            r = self.sim.solve_report
            vals.update({'solver_iterations': r['iterations'],
                         'solver_cg_iterations': r['cg_iterations'],
                         'solver_residual': float(r['residual']),
                         'solver_converged': r['converged'],
                         'solver_unconverged_steps': r['unconverged_steps']})
            warning = solver_warning(r, self.sim.solver_tolerance)
            if warning is not None and level == DiagnosticStatus.OK:
                level, msg = DiagnosticStatus.WARN, warning
        if self.sim.obstacles:
            cs = self.sim.contact_state()
            vals['contacts'] = cs['contacts']
            vals['deepest_penetration_m'] = float(cs['deepest'])
            vals['feature_pairs'] = cs['feature_pairs']
            vals['feature_active'] = cs['feature_active']
        if self.sim.self_collision:
            sc = self.sim.self_contact_state()
            vals['self_pairs_active'] = sc['active']
            vals['self_pairs_live'] = sc['live']
            vals['self_pairs_short'] = sc['left_short']
            vals['self_closest_gap_m'] = float(sc['closest_gap'])
        vals.update({f'rejected_{k}': v for k, v in self.rejected.items()})
        return self._status(f'{self.get_name()}: simulation', level, msg, vals)


def _security_requested() -> bool:
    return os.environ.get('ROS_SECURITY_ENABLE', '').lower() == 'true'


def _security_reason(exc: Exception) -> Optional[str]:
    """The one-line reason to give when ROS security was requested and rcl failed: the
    middleware's own first line, what was asked for, and where to look (README)."""
    if not _security_requested():
        return None
    text = str(exc).strip().splitlines()
    first = text[0] if text else type(exc).__name__
    if 'security libraries' in str(exc):
        first = 'this middleware (the PyPI Fast DDS) has no security libraries'
    keystore = os.environ.get('ROS_SECURITY_KEYSTORE', '')
    return (f'ROS security requested (ROS_SECURITY_ENABLE=true, strategy '
            f'{os.environ.get("ROS_SECURITY_STRATEGY", "Permissive")}, keystore '
            f'{keystore or "unset"}) but it cannot be provided: {first}; see doc/node.md, '
            '"Security"')


def main(args=None) -> int:
    """Entry point of the ``cloth_node`` executable (``ros2 run cosserat_ros cloth_node``)."""
    try:
        rclpy.init(args=args)
    except Exception as exc:       # e.g. an unreadable --params-file
        reason = _security_reason(exc) or str(exc).strip().splitlines()[0]
        print(f'cloth_node: error: {reason}', file=sys.stderr)
        return 2
    node = None
    code = 0
    if _security_requested():
        # rclpy's own note while it undoes a node that security kept from starting
        import warnings
        warnings.filterwarnings('ignore', message='Failed to fini rosout publisher')
    # A Ctrl-C that lands while a C library runs a callback into Python (llvmlite's, as
    # numba loads a cached kernel) cannot propagate: Python prints it as "Exception
    # ignored" with a traceback and goes on. Note it instead, and end once out of it.
    interrupts = []
    default_hook = sys.unraisablehook

    def quiet(unraisable):
        if isinstance(unraisable.exc_value, KeyboardInterrupt):
            interrupts.append(unraisable.exc_value)
        else:
            default_hook(unraisable)
    sys.unraisablehook = quiet
    try:
        node = ClothNode(argv=args)                  # None: sys.argv, as rclpy.init
        if interrupts:
            raise KeyboardInterrupt
        rclpy.spin(node)
    except ConfigError as exc:
        print(f'cloth_node: error: {exc}', file=sys.stderr)
        code = 2
    except (KeyboardInterrupt, ExternalShutdownException):
        pass
    except Exception as exc:
        reason = _security_reason(exc) if node is None else None
        if reason is not None:                   # the node could not even be created
            print(f'cloth_node: error: {reason}', file=sys.stderr)
            code = 2
        # SIGINT/SIGTERM shut the context down while a tick was publishing: the publish
        # fails with an RCLError. That is a shutdown, not a failure; anything else is.
        elif rclpy.ok():
            raise
    finally:
        sys.unraisablehook = default_hook
        if node is not None:
            node.destroy_node()
        rclpy.try_shutdown()
    return code


if __name__ == '__main__':
    sys.exit(main())
