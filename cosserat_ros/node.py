"""``cloth_node``: a ROS 2 node that owns a :class:`ClothSimulator` and serves the cloth.

Topics (relative, so namespaces and remapping work):

=======================  =====================================  ============================
name                     type                                   direction
=======================  =====================================  ============================
``~/mesh``               visualization_msgs/MarkerArray         out, every tick
``~/energy``             diagnostic_msgs/DiagnosticArray        out, every tick
``/diagnostics``         diagnostic_msgs/DiagnosticArray        out, ~1 Hz
``/clock``               rosgraph_msgs/Clock                    out (``publish_clock``)
``~/vertex_forces``      std_msgs/Float64MultiArray             in: rows [index, fx, fy, fz]
``~/point_forces``       std_msgs/Float64MultiArray             in: rows [px,py,pz, fx,fy,fz]
``~/force_field``        geometry_msgs/Vector3Stamped           in: uniform [m/s^2]
``~/reset``              std_srvs/Trigger                       service
``~/pause``              std_srvs/SetBool                       service
=======================  =====================================  ============================

Every header is stamped with simulation time; the node itself keeps ``use_sim_time``
false and publishes ``/clock`` so that consumers with ``use_sim_time:=true`` agree.
"""
from __future__ import annotations

from dataclasses import dataclass
import math
import os
import sys
import time
from typing import Dict, List, Optional, Tuple

import numpy as np
import rclpy
from rclpy.executors import ExternalShutdownException
from rclpy.node import Node
from rclpy.parameter import Parameter
from rclpy.qos import DurabilityPolicy, QoSProfile, ReliabilityPolicy
from rcl_interfaces.msg import (FloatingPointRange, IntegerRange, ParameterDescriptor,
                                SetParametersResult)
from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus, KeyValue
from geometry_msgs.msg import Vector3Stamped
from rosgraph_msgs.msg import Clock
from std_msgs.msg import Float64MultiArray
from std_srvs.srv import SetBool, Trigger
from visualization_msgs.msg import MarkerArray

from . import warmup
from .forces import DIVERGENCE_METHODS
from .mesh import grid_mesh, GRID_PATTERNS, load_mesh, MeshError
from .messages import colormap, mesh_marker_array
from .simulator import ClothSimulator, Material, SimulationDiverged, steps_tiled
from .surface_query import closest_points

COLORINGS = ('energy', 'stretch', 'speed', 'none')
PIN_SETS = ('none', 'corners', 'top_corners', 'top_edge', 'bottom_edge', 'left_edge',
            'right_edge', 'boundary')
MATERIAL_KEYS = ('zeta', 'xi', 'phi', 'density', 'damping')
#: [s] what each tick leaves free before the next is due, beyond its publishing: the
#: executor's latency and the scatter of the publish cost (ClothNode._advance)
TICK_MARGIN = 0.5e-3


class ConfigError(ValueError):
    """A parameter value the node cannot start with; the message is the reason."""


@dataclass
class _Force:
    indices: np.ndarray
    forces: np.ndarray
    received: float


def _fp(lo: float, hi: float) -> List[FloatingPointRange]:
    return [FloatingPointRange(from_value=lo, to_value=hi, step=0.0)]


def _desc(text: str, read_only: bool = False, fp=None, ip=None) -> ParameterDescriptor:
    d = ParameterDescriptor(description=text, read_only=read_only)
    if fp is not None:
        d.floating_point_range = fp
    if ip is not None:
        d.integer_range = ip
    return d


#: name -> (default, descriptor). One source of truth for defaults, ranges and docs.
PARAMETERS: Dict[str, Tuple[object, ParameterDescriptor]] = {
    'mesh.file': ('', _desc('Mesh file (any format trimesh reads); empty for a grid. '
                            'Relative paths resolve against the working directory.', True)),
    'mesh.nx': (40, _desc('Grid segments along X', True,
                          ip=[IntegerRange(from_value=1, to_value=2000, step=1)])),
    'mesh.ny': (40, _desc('Grid segments along Y', True,
                          ip=[IntegerRange(from_value=1, to_value=2000, step=1)])),
    'mesh.width': (1.0, _desc('Grid size along X [m]', True, fp=_fp(1e-6, 1e4))),
    'mesh.height': (1.0, _desc('Grid size along Y [m]', True, fp=_fp(1e-6, 1e4))),
    'mesh.pattern': ('regular', _desc('Grid triangulation: ' + ', '.join(GRID_PATTERNS),
                                      True)),
    'mesh.seed': (0, _desc('Random seed of the irregular pattern', True)),
    'material.zeta': (50.0, _desc('Stretching coefficient zeta [N/m] (E h = 16 zeta/3)',
                                  fp=_fp(0.0, 1e9))),
    'material.xi': (2e-5, _desc('Bending coefficient xi [N m] (D = 6 xi)', fp=_fp(0.0, 1e6))),
    'material.phi': (1e-6, _desc('Stretch-bend coupling phi [N]; phi^2 < 4 zeta xi',
                                 fp=_fp(0.0, 1e6))),
    'material.density': (0.2, _desc('Mass per unit area mu [kg/m^2]', fp=_fp(0.0, 1e6))),
    'material.damping': (0.1, _desc('Damping rho [kg/(m^2 s)] (Eq. 1)', fp=_fp(0.0, 1e6))),
    'dt': (2e-4, _desc('Time step [s]; must not exceed the critical step of the mesh and '
                       'material', fp=_fp(0.0, 1.0))),
    'publish_rate': (30.0, _desc('Ticks per second: mesh, energy and /clock are published '
                                 'every tick', True, fp=_fp(0.1, 1000.0))),
    'gravity': ([0.0, 0.0, -9.81], _desc('Gravitational acceleration [m/s^2], 3 values')),
    'pinned.indices': ([-1], _desc('Pinned vertex indices ([-1]: none)', True)),
    'pinned.sets': (['top_corners'], _desc('Named pinned sets: ' + ', '.join(PIN_SETS),
                                           True)),
    'divergence': ('variational', _desc('Internal force discretisation: '
                                        + ', '.join(DIVERGENCE_METHODS), True)),
    'frame_id': ('world', _desc('Frame of the published mesh and accepted commands', True)),
    'publish_clock': (True, _desc('Publish simulation time on /clock', True)),
    'force_timeout': (1.0, _desc('Forces lapse after this many seconds without a new '
                                 'message (0 = hold) [s]', fp=_fp(0.0, 1e6))),
    'max_force': (10.0, _desc('Largest accepted force per row [N]', fp=_fp(0.0, 1e9))),
    'max_acceleration': (100.0, _desc('Largest accepted force field [m/s^2]',
                                      fp=_fp(0.0, 1e9))),
    'coloring': ('energy', _desc('Mesh colouring: ' + ', '.join(COLORINGS))),
    'wireframe': (False, _desc('Publish a LINE_LIST wireframe too')),
    'status_period': (1.0, _desc('Seconds between one-line status logs (0 = off)',
                                 fp=_fp(0.0, 3600.0))),
}


def pin_set(mesh, name: str) -> np.ndarray:
    """Vertex indices of a named pinned set, from the rest shape's bounding box."""
    X = mesh.vertices
    b = mesh.boundary_vertices
    lo, hi = X.min(axis=0), X.max(axis=0)
    tol = 1e-6 * max(float(np.ptp(X, axis=0).max()), 1e-12)
    bidx = np.flatnonzero(b)
    if name == 'none':
        return np.zeros(0, dtype=np.int64)
    if name == 'boundary':
        return bidx
    if len(bidx) == 0:
        raise ConfigError(f'pinned set {name!r} needs a mesh with a boundary')
    if name in ('corners', 'top_corners'):
        targets = [(lo[0], hi[1]), (hi[0], hi[1])]
        if name == 'corners':
            targets += [(lo[0], lo[1]), (hi[0], lo[1])]
        pts = X[bidx, :2]
        return np.unique([bidx[np.argmin(np.linalg.norm(pts - t, axis=1))] for t in targets])
    axis, side = {'top_edge': (1, hi), 'bottom_edge': (1, lo), 'left_edge': (0, lo),
                  'right_edge': (0, hi)}[name]
    return bidx[np.abs(X[bidx, axis] - side[axis]) <= tol]


def percentile(v: np.ndarray, q: float) -> float:
    """``np.percentile(v, q)`` (linear interpolation between the two nearest ranks) from a
    partial sort of those two ranks: ~10x cheaper on a mesh's densities, each publish."""
    k = q / 100.0 * (len(v) - 1)
    lo = int(k)
    hi = min(lo + 1, len(v) - 1)
    p = np.partition(v, (lo, hi))
    return float(p[lo] + (k - lo) * (p[hi] - p[lo]))


class ClothNode(Node):
    """Owns the simulator; steps it in real time on a timer and publishes it."""

    def __init__(self, name: str = 'cloth_node', **kwargs):
        super().__init__(name, **kwargs)
        self._declare()
        p = self._values()
        self.mesh = self._build_mesh(p)
        try:
            material = Material(**{k: p['material.' + k] for k in MATERIAL_KEYS})
        except ValueError as exc:
            raise ConfigError(str(exc)) from None
        if p['divergence'] not in DIVERGENCE_METHODS:
            raise ConfigError(f'divergence must be one of {DIVERGENCE_METHODS}, '
                              f'got {p["divergence"]!r}')
        t0 = time.perf_counter()
        # with a cold compile cache, a second process compiles on the other core what the
        # start-up below needs after its step's big vertex pass (cosserat_ros.warmup)
        warmup.start(steps_tiled(self.mesh.n_vertices, material.phi, p['divergence']))
        self.sim = ClothSimulator(self.mesh, material, dt=max(p['dt'], 1e-12),
                                  divergence=p['divergence'], check_dt=False)
        # compile (or load from cache) every kernel of the step and of the energy report
        # before any topic exists: a recorder that starts when the topics appear must not
        # wait through a first tick that compiles
        self.sim.step(1)
        self.sim.energy_and_densities()
        self.sim.reset()
        self._check_dt(p['dt'], self.sim.critical_dt())
        self.sim.dt = p['dt']
        self.get_logger().info(
            f'{self.mesh}: kernels ready and critical dt {self.sim.critical_dt():.3g} s '
            f'found in {time.perf_counter() - t0:.2f} s')
        self.sim.gravity = self._vec3(p['gravity'], 'gravity')
        self._apply_pins(p)
        self.frame_id = p['frame_id']
        self._coloring = p['coloring']
        self._check_choice(self._coloring, COLORINGS, 'coloring')
        self._wireframe = bool(p['wireframe'])
        self._force_timeout = p['force_timeout']
        self._max_force = p['max_force']
        self._max_acc = p['max_acceleration']
        self._status_period = p['status_period']
        self._forces: Dict[str, Optional[_Force]] = {'vertex': None, 'point': None}
        self._field: Optional[Tuple[np.ndarray, float]] = None
        self.rejected = {'vertex_forces': 0, 'point_forces': 0, 'force_field': 0}
        self.paused = False
        self.diverged: Optional[str] = None
        self._step_cost = 0.0
        self._publish_cost = 0.0
        self._rtf = 1.0
        self._lagging = False
        self._window = [time.monotonic(), 0.0]   # wall start, sim advanced since
        self._last_tick = None
        self._owed = 0.0      # sim seconds the ticks so far fell short of wall time
        self._last_status = time.monotonic()
        self._last_diag = 0.0
        self._energy_scale = 1e-300

        reliable = QoSProfile(depth=5, reliability=ReliabilityPolicy.RELIABLE,
                              durability=DurabilityPolicy.VOLATILE)
        self.mesh_pub = self.create_publisher(MarkerArray, '~/mesh', reliable)
        self.energy_pub = self.create_publisher(DiagnosticArray, '~/energy', reliable)
        self.diag_pub = self.create_publisher(DiagnosticArray, '/diagnostics', reliable)
        self.clock_pub = None
        if p['publish_clock']:
            latched = QoSProfile(depth=1, reliability=ReliabilityPolicy.RELIABLE,
                                 durability=DurabilityPolicy.TRANSIENT_LOCAL)
            self.clock_pub = self.create_publisher(Clock, '/clock', latched)
        self.create_subscription(Float64MultiArray, '~/vertex_forces', self.on_vertex_forces,
                                 10)
        self.create_subscription(Float64MultiArray, '~/point_forces', self.on_point_forces, 10)
        self.create_subscription(Vector3Stamped, '~/force_field', self.on_force_field, 10)
        self.create_service(Trigger, '~/reset', self.on_reset)
        self.create_service(SetBool, '~/pause', self.on_pause)
        self.add_on_set_parameters_callback(self.validate_parameters)
        self.add_post_set_parameters_callback(self.apply_parameters)
        self.period = 1.0 / p['publish_rate']
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

    @staticmethod
    def _check_choice(value, choices, name):
        if value not in choices:
            raise ConfigError(f'{name} must be one of {", ".join(choices)}, got {value!r}')

    @staticmethod
    def _vec3(value, name) -> np.ndarray:
        arr = np.asarray(list(value), dtype=np.float64)
        if arr.shape != (3,) or not np.all(np.isfinite(arr)):
            raise ConfigError(f'{name} must be 3 finite numbers, got {list(value)!r}')
        return arr

    @staticmethod
    def _check_dt(dt: float, critical: float):
        if not (dt > 0 and math.isfinite(dt)):
            raise ConfigError(f'dt must be positive, got {dt!r}')
        if dt > critical:
            raise ConfigError(f'dt = {dt:.3g} s exceeds the critical step {critical:.3g} s '
                              'of this mesh and material (the membrane wave speed over the '
                              'shortest edge limits it): lower dt, zeta or the resolution')

    @staticmethod
    def _mesh_path(path: str) -> str:
        """A relative path resolves against the working directory, then against the
        package's installed share directory (so configs can name config/meshes/...)."""
        if os.path.isabs(path) or os.path.exists(path):
            return path
        try:
            from ament_index_python.packages import get_package_share_directory
            shared = os.path.join(get_package_share_directory('cosserat_ros'), path)
        except Exception:       # package not installed through an ament index
            return path
        return shared if os.path.exists(shared) else path

    def _build_mesh(self, p):
        try:
            if p['mesh.file']:
                return load_mesh(self._mesh_path(p['mesh.file']))
            self._check_choice(p['mesh.pattern'], GRID_PATTERNS, 'mesh.pattern')
            return grid_mesh(p['mesh.nx'], p['mesh.ny'], p['mesh.width'], p['mesh.height'],
                             p['mesh.pattern'], p['mesh.seed'])
        except (MeshError, ValueError) as exc:
            raise ConfigError(f'mesh: {exc}') from None

    def _apply_pins(self, p):
        idx = [int(i) for i in p['pinned.indices'] if i != -1]
        n = self.mesh.n_vertices
        bad = [i for i in idx if not 0 <= i < n]
        if bad:
            raise ConfigError(f'pinned.indices must lie in [0, {n - 1}] (or be [-1] for '
                              f'none), got {bad}')
        sets = [s for s in p['pinned.sets'] if s]
        for s in sets:
            self._check_choice(s, PIN_SETS, 'pinned.sets entries')
            idx.extend(pin_set(self.mesh, s).tolist())
        if idx:
            self.sim.pin(np.unique(idx))

    # ------------------------------------------------------------------ commands
    def _reject(self, topic: str, reason: str):
        self.rejected[topic] += 1
        self.get_logger().warning(f'rejected ~/{topic}: {reason} '
                                  f'({self.rejected[topic]} rejected so far)',
                                  throttle_duration_sec=1.0)

    def _rows(self, msg: Float64MultiArray, width: int, topic: str) -> Optional[np.ndarray]:
        data = np.asarray(msg.data, dtype=np.float64)
        off = msg.layout.data_offset
        if off > len(data):
            self._reject(topic, f'layout.data_offset {off} beyond {len(data)} values')
            return None
        data = data[off:]
        dims = msg.layout.dim
        if len(dims) >= 2 and (dims[1].size != width or dims[0].size * width != len(data)):
            self._reject(topic, f'layout {dims[0].size}x{dims[1].size} does not describe '
                                f'{len(data)} values in rows of {width}')
            return None
        if len(data) % width:
            self._reject(topic, f'{len(data)} values are not rows of {width}')
            return None
        if not np.all(np.isfinite(data)):
            self._reject(topic, 'non-finite value')
            return None
        rows = data.reshape(-1, width)
        mag = np.linalg.norm(rows[:, -3:], axis=1)
        if len(rows) and mag.max() > self._max_force:
            self._reject(topic, f'force {mag.max():.4g} N above max_force '
                                f'{self._max_force:.4g} N')
            return None
        return rows

    def on_vertex_forces(self, msg: Float64MultiArray):
        """Rows [index, fx, fy, fz] [N]; replaces the previous set (empty: clear)."""
        rows = self._rows(msg, 4, 'vertex_forces')
        if rows is None:
            return
        idx = rows[:, 0]
        n = self.mesh.n_vertices
        if len(idx) and (np.any(idx != np.round(idx)) or idx.min() < 0 or idx.max() >= n):
            self._reject('vertex_forces', f'indices must be integers in [0, {n - 1}]')
            return
        self._forces['vertex'] = _Force(idx.astype(np.int64), rows[:, 1:].copy(),
                                        time.monotonic())
        self._push_forces()

    def on_point_forces(self, msg: Float64MultiArray):
        """Rows [px, py, pz, fx, fy, fz] in frame_id: each force goes to the closest point
        of the cloth (shared by its triangle's vertices, barycentrically) and stays with
        that material point until replaced."""
        rows = self._rows(msg, 6, 'point_forces')
        if rows is None:
            return
        if len(rows):
            x = self.sim.positions
            tri, bary = closest_points(x, self.mesh.faces, rows[:, :3])
            idx = self.mesh.faces[tri].reshape(-1)
            f = (bary[:, :, None] * rows[:, None, 3:]).reshape(-1, 3)
        else:
            idx, f = np.zeros(0, dtype=np.int64), np.zeros((0, 3))
        self._forces['point'] = _Force(idx, f, time.monotonic())
        self._push_forces()

    def on_force_field(self, msg: Vector3Stamped):
        """Uniform force per unit mass [m/s^2] in frame_id ('' is taken as frame_id)."""
        if msg.header.frame_id not in ('', self.frame_id):
            self._reject('force_field', f'frame {msg.header.frame_id!r} is not '
                                        f'{self.frame_id!r} (no tf here)')
            return
        v = np.array([msg.vector.x, msg.vector.y, msg.vector.z])
        if not np.all(np.isfinite(v)):
            self._reject('force_field', 'non-finite value')
            return
        if np.linalg.norm(v) > self._max_acc:
            self._reject('force_field', f'|F| = {np.linalg.norm(v):.4g} m/s^2 above '
                                        f'max_acceleration {self._max_acc:.4g}')
            return
        self._field = (v, time.monotonic())
        self.sim.force_field = v

    def _push_forces(self):
        parts = [f for f in self._forces.values() if f is not None]
        if parts:
            self.sim.set_vertex_forces(np.concatenate([p.indices for p in parts]),
                                       np.concatenate([p.forces for p in parts]))
        else:
            self.sim.clear_vertex_forces()

    def _expire_forces(self, now: float):
        if self._force_timeout <= 0:
            return
        changed = False
        for key, f in self._forces.items():
            if f is not None and now - f.received > self._force_timeout:
                self._forces[key] = None
                changed = True
                self.get_logger().info(f'{key} forces lapsed after {self._force_timeout} s '
                                       'without a new message')
        if changed:
            self._push_forces()
        if self._field is not None and now - self._field[1] > self._force_timeout:
            self._field = None
            self.sim.force_field = (0.0, 0.0, 0.0)
            self.get_logger().info('force field lapsed')

    # ------------------------------------------------------------------ services
    def on_reset(self, request, response):
        self.sim.reset()
        self.diverged = None
        self.paused = False
        self._window = [time.monotonic(), 0.0]
        self._last_tick = None
        response.success = True
        response.message = 'cloth back to its rest shape at t = 0'
        self.publish_state()
        return response

    def on_pause(self, request, response):
        if not request.data and self.diverged:
            response.success = False
            response.message = f'simulation diverged ({self.diverged}); call ~/reset first'
            return response
        self.paused = bool(request.data)
        self._last_tick = None
        response.success = True
        response.message = 'paused' if self.paused else 'running'
        return response

    # ------------------------------------------------------------------ parameters
    def validate_parameters(self, params: List[Parameter]) -> SetParametersResult:
        """Only validates; :meth:`apply_parameters` applies accepted values."""
        mat = {k: getattr(self.sim.material, k) for k in MATERIAL_KEYS}
        dt = self.sim.dt
        for prm in params:
            name, val = prm.name, prm.value
            if name.startswith('material.'):
                if not isinstance(val, float) or not math.isfinite(val):
                    return SetParametersResult(successful=False,
                                               reason=f'{name} must be a finite float')
                mat[name.split('.', 1)[1]] = val
            elif name == 'dt':
                if not isinstance(val, float) or not (val > 0 and math.isfinite(val)):
                    return SetParametersResult(successful=False,
                                               reason='dt must be a positive float')
                dt = val
            elif name == 'gravity':
                try:
                    self._vec3(val, 'gravity')
                except (ConfigError, TypeError, ValueError) as exc:
                    return SetParametersResult(successful=False, reason=str(exc))
            elif name == 'coloring' and val not in COLORINGS:
                return SetParametersResult(successful=False,
                                           reason=f'coloring must be one of {COLORINGS}')
            elif name in ('force_timeout', 'max_force', 'max_acceleration', 'status_period'):
                if not isinstance(val, float) or not (val >= 0 and math.isfinite(val)):
                    return SetParametersResult(successful=False,
                                               reason=f'{name} must be a non-negative float')
        try:
            material = Material(**mat)
        except ValueError as exc:
            return SetParametersResult(successful=False, reason=str(exc))
        if material != self.sim.material or dt != self.sim.dt:
            probe = self.sim if material == self.sim.material else ClothSimulator(
                self.mesh, material, dt=dt, check_dt=False)
            crit = probe.critical_dt()
            if dt > crit:
                return SetParametersResult(
                    successful=False, reason=f'dt = {dt:.3g} s would exceed the critical step '
                                             f'{crit:.3g} s of this mesh and material')
        return SetParametersResult(successful=True)

    def apply_parameters(self, params: List[Parameter]):
        mat = {k: getattr(self.sim.material, k) for k in MATERIAL_KEYS}
        changed_material = False
        for prm in params:
            name, val = prm.name, prm.value
            if name.startswith('material.'):
                mat[name.split('.', 1)[1]] = val
                changed_material = True
            elif name == 'dt':
                self.sim.dt = val
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
        if changed_material:
            self.sim.material = Material(**mat)
            self._energy_scale = 1e-300

    # ------------------------------------------------------------------ the loop
    def tick(self):
        """Advance as many steps as keep sim time with wall time, then publish: the wall
        time since the last tick (at most 4 periods) plus what earlier ticks fell short by,
        in whole steps."""
        now = time.monotonic()
        self._expire_forces(now)
        if not self.paused and self.diverged is None:
            if self._last_tick is None:
                elapsed, owed = self.period, 0.0
            else:
                elapsed, owed = now - self._last_tick, self._owed
            owed += min(elapsed, 4 * self.period)
            wanted = max(1, int(round(owed / self.sim.dt)))
            done = self._advance(wanted)
            self._lagging = done < wanted
            # carry what the rounding to whole steps left, so that sim time keeps wall
            # time over many ticks (a period of 199.6 steps, rounded alone, gains 0.2%);
            # a tick that could not keep up drops its debt instead of piling it up
            self._owed = 0.0 if self._lagging else owed - done * self.sim.dt
            self._window[1] += done * self.sim.dt
        self._last_tick = now
        wall = now - self._window[0]
        if wall >= 1.0:
            self._rtf = self._window[1] / wall if not self.paused else 0.0
            self._window = [now, 0.0]
        t1 = time.perf_counter()
        self.publish_state()
        cost = time.perf_counter() - t1
        self._publish_cost = cost if self._publish_cost == 0 else (
            0.8 * self._publish_cost + 0.2 * cost)
        if now - self._last_diag >= 1.0:
            self._last_diag = now
            self.diag_pub.publish(self.diagnostics())
        if self._status_period > 0 and now - self._last_status >= self._status_period:
            self._last_status = now
            e = self._energy
            state = 'DIVERGED' if self.diverged else ('paused' if self.paused else 'running')
            self.get_logger().info(
                f'{state} t={self.sim.time:.3f} s  RTF {self._rtf:.2f}  step '
                f'{self._step_cost * 1e3:.3f} ms  E_total {e["total"]:.6g} J  '
                f'(kin {e["kinetic"]:.3g}, elastic {e["elastic"]:.3g})')

    def _advance(self, wanted: int) -> int:
        """Take up to ``wanted`` steps, as many as fit before the next tick is due; return
        how many were taken.

        The steps end where the timer's next call is due, less the publishing that follows
        them (its cost smoothed over ticks) and TICK_MARGIN; never less than a third of
        the period. The timer keeps its own schedule (rcl's next call is a whole number of
        periods from its start), so a tick that starts late, or one before it that ran
        over, shortens this tick's stepping instead of shifting the next tick. The first
        batch takes at most 3/4 of what the smoothed step cost says fits; the rest is
        sized on that batch's own cost, measured in this tick, so a host that slows
        down between ticks does not push the tick past its period."""
        due = self.timer.time_until_next_call()
        left = self.period if due is None else due * 1e-9
        end = time.perf_counter() + max(self.period / 3,
                                        left - self._publish_cost - TICK_MARGIN)
        done, cost = 0, self._step_cost
        while done < wanted:
            if cost <= 0:
                n = 1                                    # no estimate yet: one step
            else:
                fit = (end - time.perf_counter()) / cost
                n = min(wanted - done, int(0.75 * fit if done == 0 else fit))
                if n <= 0:
                    if done:
                        break
                    n = 1                                # every tick takes a step
            t0 = time.perf_counter()
            try:
                self.sim.step(n)
            except SimulationDiverged as exc:
                self.diverged = str(exc)
                self.paused = True
                self.get_logger().error(f'{exc}; paused, call ~/reset to recover')
                break
            cost = (time.perf_counter() - t0) / n
            self._step_cost = cost if self._step_cost == 0 else (
                0.8 * self._step_cost + 0.2 * cost)
            done += n
        return done

    def stamp_ns(self) -> int:
        return int(round(self.sim.time * 1e9))

    def vertex_colors(self) -> np.ndarray:
        n = self.mesh.n_vertices
        if self._coloring == 'none':
            out = np.empty((n, 4), dtype=np.float32)
            out[:] = (0.55, 0.65, 0.85, 1.0)
            return out
        if self._coloring == 'energy':       # 98th percentile: pins would saturate a max
            v = self._densities['total']
            return colormap(v, 0.0, max(percentile(v, 98.0), 1e-12))
        if self._coloring == 'speed':
            v = np.linalg.norm(self.sim.velocities, axis=1)
            return colormap(v, 0.0, max(float(v.max()), 1e-9))
        g = self.sim.geometry()                          # stretch: area ratio - 1
        v = np.sqrt(np.linalg.det(g.metric) / np.linalg.det(g.rest_metric)) - 1.0
        return colormap(v, -0.05, 0.05)

    def publish_state(self):
        """Publish ~/mesh, ~/energy and /clock for the current state."""
        self._energy, self._densities = self.sim.energy_and_densities()
        x = self.sim.positions
        if not np.all(np.isfinite(x)):       # never publish a NaN (step() restores state)
            return
        stamp = self.stamp_ns()
        pinned = np.flatnonzero(self.sim.pinned)
        self.mesh_pub.publish(mesh_marker_array(
            x, self.mesh.faces, self.vertex_colors(), stamp, self.frame_id,
            edges=self.mesh.edges if self._wireframe else None, pinned=pinned,
            pin_size=0.3 * self.mesh.mean_edge_length))
        self.energy_pub.publish(self.energy_message(stamp))
        if self.clock_pub is not None:
            c = Clock()
            c.clock.sec, c.clock.nanosec = divmod(stamp, 1_000_000_000)
            self.clock_pub.publish(c)

    def _status(self, name: str, level: bytes, message: str, values: Dict[str, object],
                stamp: Optional[int] = None) -> DiagnosticArray:
        arr = DiagnosticArray()
        sec, nsec = divmod(self.stamp_ns() if stamp is None else stamp, 1_000_000_000)
        arr.header.stamp.sec, arr.header.stamp.nanosec = sec, nsec
        arr.header.frame_id = self.frame_id
        st = DiagnosticStatus(level=level, name=name, message=message,
                              hardware_id=self.get_fully_qualified_name())
        st.values = [KeyValue(key=k, value=repr(v) if isinstance(v, float) else str(v))
                     for k, v in values.items()]
        arr.status = [st]
        return arr

    def energy_message(self, stamp: int) -> DiagnosticArray:
        e = dict(self._energy)
        vals = {k: float(v) for k, v in e.items()}
        vals['sim_time'] = float(self.sim.time)
        vals['step'] = int(self.sim.step_count)
        if self.diverged:
            level, msg = DiagnosticStatus.ERROR, 'diverged: ' + self.diverged
        elif self.paused:
            level, msg = DiagnosticStatus.WARN, 'paused'
        else:
            level, msg = DiagnosticStatus.OK, 'running'
        return self._status('energy', level, msg, vals, stamp)

    def diagnostics(self) -> DiagnosticArray:
        crit = self.sim.critical_dt()
        rej = sum(self.rejected.values())
        if self.diverged:
            level, msg = DiagnosticStatus.ERROR, 'diverged: ' + self.diverged
        elif self._lagging or (not self.paused and self._rtf < 0.9):
            level, msg = DiagnosticStatus.WARN, (f'cannot keep real time (RTF '
                                                 f'{self._rtf:.2f})')
        elif self.paused:
            level, msg = DiagnosticStatus.WARN, 'paused'
        else:
            level, msg = DiagnosticStatus.OK, 'running'
        vals = {'real_time_factor': float(self._rtf),
                'step_cost_ms': float(self._step_cost * 1e3),
                'publish_cost_ms': float(self._publish_cost * 1e3),
                'dt': float(self.sim.dt), 'critical_dt': float(crit),
                'dt_over_critical': float(self.sim.dt / crit),
                'vertices': self.mesh.n_vertices, 'faces': self.mesh.n_faces,
                'sim_time': float(self.sim.time), 'paused': self.paused,
                'rejected_total': rej}
        vals.update({f'rejected_{k}': v for k, v in self.rejected.items()})
        return self._status(f'{self.get_name()}: simulation', level, msg, vals)


def main(args=None) -> int:
    """Entry point of the ``cloth_node`` executable (``ros2 run cosserat_ros cloth_node``)."""
    try:
        rclpy.init(args=args)
    except Exception as exc:       # e.g. an unreadable --params-file
        print(f'cloth_node: error: {str(exc).strip().splitlines()[0]}', file=sys.stderr)
        return 2
    node = None
    code = 0
    try:
        node = ClothNode()
        rclpy.spin(node)
    except ConfigError as exc:
        print(f'cloth_node: error: {exc}', file=sys.stderr)
        code = 2
    except (KeyboardInterrupt, ExternalShutdownException):
        pass
    except Exception:
        # SIGINT/SIGTERM shut the context down while a tick was publishing: the publish
        # fails with an RCLError. That is a shutdown, not a failure; anything else is.
        if rclpy.ok():
            raise
    finally:
        if node is not None:
            node.destroy_node()
        rclpy.try_shutdown()
    return code


if __name__ == '__main__':
    sys.exit(main())
