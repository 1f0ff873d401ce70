"""``cloth_node``: a ROS 2 node that owns a :class:`ClothSimulator` and serves the cloth.

Its topics, services and parameters are listed in the manual (doc/node.md), generated
from their declarations: :data:`.interfaces.INTERFACES` and :data:`.params.DECLARATIONS`.
Every header is stamped with simulation time; the node itself keeps ``use_sim_time``
false and publishes ``/clock`` so that consumers with ``use_sim_time:=true`` agree.

This module is the wiring: the parameters are declared, validated and applied by loops
over their declarations (:mod:`.params`); the force inputs live in :mod:`.inputs`, the
handles in :mod:`.handles`, the obstacles in :mod:`.obstacles`, the cameras in
:mod:`.cameras`, the refusals and ``/diagnostics`` in :mod:`.status`; command parsing is
:mod:`.commands`, the tick's pacing :mod:`.pacing`, the messages :mod:`.conversions` (the
cloth's, as CDR bytes) and :mod:`.messages` (the others).
"""
from __future__ import annotations

import math
import sys
import time
import traceback
from typing import List, Optional, Tuple

import numba
import numpy as np
from rclpy.node import Node
from rclpy.parameter import Parameter
from rclpy.qos import DurabilityPolicy, QoSProfile, ReliabilityPolicy
from rclpy.serialization import deserialize_message
from rcl_interfaces.msg import ParameterDescriptor, SetParametersResult
from diagnostic_msgs.msg import DiagnosticArray
from sensor_msgs.msg import PointCloud2
from shape_msgs.msg import Mesh
from rosgraph_msgs.msg import Clock
from std_srvs.srv import SetBool, Trigger
from visualization_msgs.msg import MarkerArray

from ..core import warmup
from ..core.contact import mesh_distance_field
from ..core.simulator import ClothSimulator, Material, SimulationDiverged, steps_tiled
from . import commands, messages, runtime, scene, status
from .conversions import (mesh_marker_array, OPTIONAL_MARKERS, optional_markers,
                          percentile, point_cloud, shape_mesh, vertex_colors)
from .cameras import CameraStreams, declared_cameras
from .handles import HandleStreams
from .inputs import Inputs
from .obstacles import ObstacleStreams
from .pacing import Pacer
from .obstacles import MESH_BUILD_PERIOD
from .serve import main
from .params import (carry_renamed, check_choice, check_dt, check_names, check_value,
                     COLORINGS, ConfigError, DECLARATIONS, MATERIAL_KEYS, OBSERVER_RUNTIME,
                     pin_set, term_declarations, wind as checked_wind)
from .status import solver_warning

__all__ = ['ClothNode', 'ConfigError', 'main', 'pin_set', 'percentile', 'solver_warning']

#: [s] while paused (or diverged) the state is published when it changes and at least
#: this often, not every tick, and the timer ticks every PAUSED_TICK: a paused node idles
PAUSED_PUBLISH_PERIOD = 1.0
PAUSED_TICK = 0.2

#: why the node refuses ``use_sim_time`` true: its timer would then wait for the /clock
#: that only its own ticks publish, and the cloth would never move again
SIM_TIME_REASON = ('use_sim_time must stay false: this node is the source of /clock (its '
                   'ticks run on wall time and publish it); set use_sim_time on the nodes '
                   'that consume it')


def _refused(reason: str) -> SetParametersResult:
    return SetParametersResult(successful=False, reason=reason)


class ClothNode(Node):
    """Owns the simulator; steps it in real time on a timer and publishes it."""

    def __init__(self, name: str = 'cloth_node', argv=None, **kwargs):
        super().__init__(name, **kwargs)
        #: the node's own parameters and the registered terms' (terms.<name>.<coefficient>)
        self.declarations = {**DECLARATIONS, **term_declarations()}
        for pname, d in self.declarations.items():
            self._declare(pname, d.default, d.descriptor)
        p = {pname: self.get_parameter(pname).value for pname in self.declarations}
        # everything that needs no compiled kernel is checked first: a bad file fails fast
        check_names(p, self._parameter_overrides,
                    set(self.declarations) | set(self._parameters),
                    sys.argv if argv is None else argv, self.get_fully_qualified_name())
        carry_renamed(p, self.get_logger().warning)        # a deprecated name, warned
        if self.get_parameter('use_sim_time').value:
            raise ConfigError(SIM_TIME_REASON)
        self.observe_only = bool(p['observe_only'])
        self.mesh = scene.build_mesh(p)
        material = scene.initial_material(p, self._parameter_overrides)
        if p['material.preset']:         # the parameters say what the cloth gets
            self.set_parameters([Parameter('material.' + k, value=float(getattr(material, k)))
                                 for k in MATERIAL_KEYS])
        scene.check_solver(p)
        self.implicit = p['solver'] == 'implicit'
        settings = scene.checked_settings(p, self.mesh)
        check_dt(p['dt'])
        self.sim = self._simulator(p, material)
        scene.apply_settings(self.sim, settings, p)
        self.frame_id = p['frame_id']
        self.coloring = check_choice(p['coloring'], COLORINGS, 'coloring')
        self.wireframe = bool(p['wireframe'])
        self.status_period = p['status_period']
        self.paused = False
        self.diverged: Optional[str] = None
        self.period = 1.0 / p['publish_rate']
        self.pacer = Pacer(self.period, p['real_time_factor'])
        self._dirty = True                 # something to publish while paused
        self._last_publish = -math.inf
        self.rtf = 1.0
        self._window = [time.monotonic(), 0.0]   # wall start, sim advanced since
        self._last_status = time.monotonic()
        self._last_diag = 0.0
        self._create_interfaces(p)
        self.add_on_set_parameters_callback(self.validate_parameters)
        self.add_post_set_parameters_callback(self.apply_parameters)
        self.timer = self.create_timer(self.period, self.tick)

    # ------------------------------------------------------------------ set-up
    def _declare(self, name: str, default, descriptor: ParameterDescriptor):
        try:
            self.declare_parameter(name, default, descriptor)
        except Exception as exc:   # rclpy's InvalidParameter*Exception family
            raise ConfigError(f'parameter {name}: {exc}') from None

    def _simulator(self, p: dict, material: Material) -> ClothSimulator:
        """The simulator with every kernel of the step, the energy report and the
        commands compiled (or loaded from the cache) before any topic exists: a recorder
        that starts when the topics appear must not wait through a first tick that
        compiles. ConfigError if dt exceeds the critical step."""
        t0 = time.perf_counter()
        if not warmup.kernels_cached():
            with status.Progress(self.get_logger(), 'first start: compiling the kernels (1-3 '
                                 'minutes on 2 cores, cached for the next starts)'):
                return self._simulator_built(p, material, t0)
        return self._simulator_built(p, material, t0)

    def _simulator_built(self, p: dict, material: Material, t0: float) -> ClothSimulator:
        # with a cold compile cache, a second process compiles on the other core what the
        # start-up below needs after its step (cosserat_ros.core.warmup)
        warmup.start(steps_tiled(self.mesh.n_vertices, p['discretisation']),
                     material.phi != 0.0)
        terms = {}
        for pname in self.declarations:
            if pname.startswith('terms.'):
                _, term, coef = pname.split('.')
                terms.setdefault(term, {})[coef] = p[pname]
        sim = ClothSimulator(self.mesh, material, dt=max(p['dt'], 1e-12),
                             discretisation=p['discretisation'], check_dt=False,
                             solver=p['solver'],
                             terms=terms)
        if self.implicit:
            sim.solver_iterations = p['solver.iterations']
            sim.solver_tolerance = p['solver.tolerance']
        else:
            unused = [k for k in ('solver.iterations', 'solver.tolerance')
                      if k in self._parameter_overrides]
            if unused:
                self.get_logger().warning(f'{", ".join(unused)}: controls of the implicit '
                                          'solver, unused with solver: explicit')
        sim.step(1)
        sim.energy_and_densities()
        sim.reset()
        check_dt(p['dt'], math.inf if self.implicit else sim.critical_dt())
        sim.dt = p['dt']
        self.get_logger().info(
            f'{self.mesh}: kernels ready and critical dt {sim.critical_dt():.3g} s '
            f'found in {time.perf_counter() - t0:.2f} s')
        # the closest-point query of ~/point_forces, the distance field of a mesh marker
        commands.point_forces(np.zeros((1, 6)), sim.positions, self.mesh.faces)
        if not self.observe_only:
            mesh_distance_field(*warmup.TETRAHEDRON, 0.25, 0.1)
        return sim

    def _create_interfaces(self, p: dict):
        """The publishers, subscriptions and services of doc/node.md, each with the
        module that serves it."""
        reliable = QoSProfile(depth=5, reliability=ReliabilityPolicy.RELIABLE,
                              durability=DurabilityPolicy.VOLATILE)
        self.mesh_pub = self.create_publisher(MarkerArray, '~/mesh', reliable)
        self.energy_pub = self.create_publisher(DiagnosticArray, '~/energy', reliable)
        self.diag_pub = self.create_publisher(DiagnosticArray, '/diagnostics', reliable)
        self._reject = status.Rejections(self)
        self.rejected = self._reject.counts
        self.points_pub = (self.create_publisher(PointCloud2, '~/points', reliable)
                           if p['publish.points'] else None)
        self.shape_pub = (self.create_publisher(Mesh, '~/shape', reliable)
                          if p['publish.shape'] else None)
        self.clock_pub = None
        if p['publish_clock']:
            latched = QoSProfile(depth=1, reliability=ReliabilityPolicy.RELIABLE,
                                 durability=DurabilityPolicy.TRANSIENT_LOCAL)
            self.clock_pub = self.create_publisher(Clock, '/clock', latched)
        self.inputs = Inputs(self, p, checked_wind(p['air.wind'], p['max_wind']))
        self.obstacles = ObstacleStreams(self, p['obstacles.names'], reliable,
                                         MESH_BUILD_PERIOD)
        if not self.observe_only:
            self.inputs.subscribe(self._sized)
            self.obstacles.subscribe(self._sized)
        self.handles = HandleStreams(self, p['handles.names'], p['handles.max_speed'],
                                     reliable)
        cameras = declared_cameras(self, p)
        if cameras:                    # the renderer compiled (or loaded) before any topic
            next(iter(cameras.values()))['camera'].render(self.sim)
        self.cameras = CameraStreams(self, cameras, reliable)
        if not self.observe_only:
            self.create_service(Trigger, '~/reset', self.on_reset)
            self.create_service(SetBool, '~/pause', self.on_pause)
        self.live = None
        if p['foxglove.port']:
            from .live_view import open_live_view
            self.live = open_live_view(self, p['foxglove.port'], p['foxglove.host'])

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

    def _declare_group(self, group: str, name: str, keys: dict, what: str) -> dict:
        """Declare ``<group>.<name>.<key>`` (read-only, default ``keys[key]``) for every
        key and return their values."""
        values = {}
        for key, default in keys.items():
            full = f'{group}.{name}.{key}'
            self._declare(full, default, ParameterDescriptor(
                description=f'{what} {name}: {key}', read_only=True))
            values[key] = self.get_parameter(full).value
        return values

    @property
    def _handles(self) -> dict:
        """The handles' state by name (:class:`.handles.HandleStreams`)."""
        return self.handles.streams

    @property
    def _max_handle_speed(self) -> float:
        return self.handles.max_speed

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
        self.handles.restart()
        self.inputs.restart()
        self.obstacles.restart()
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
        """Each value against its declaration (:func:`.params.check_value`), then what
        they must satisfy together (:func:`.runtime.check_together`); only validates:
        :meth:`apply_parameters` applies accepted values."""
        for prm in params:
            name, val = prm.name, prm.value
            d = self.declarations.get(name)
            if name == 'use_sim_time' and val:
                return _refused(SIM_TIME_REASON)
            if d is not None and d.implicit and not self.implicit:
                return _refused(f'{name} is a control of the implicit solver; this node runs '
                                'solver: explicit (chosen at start-up)')
            if self.observe_only and not (d is not None and d.observer):
                return _refused(f'observe_only: {name} cannot change (only '
                                f'{", ".join(OBSERVER_RUNTIME)} can)')
            if d is not None and d.runtime:
                try:
                    check_value(name, val, d)
                except ConfigError as exc:
                    return _refused(str(exc))
        try:
            runtime.check_together(self, {prm.name: prm.value for prm in params})
        except ConfigError as exc:
            return _refused(str(exc))
        return SetParametersResult(successful=True)

    def apply_parameters(self, params: List[Parameter]):
        """Each accepted value to where its declaration says (``Param.apply``), then the
        groups that change together: the material, the air, the lowered limits."""
        new = {prm.name: prm.value for prm in params}
        groups = set()
        for name, val in new.items():
            d = self.declarations.get(name)
            if d is None or not d.runtime:
                continue
            if d.apply is not None:
                path, attr = d.apply.rpartition('.')[::2]
                target = self
                for part in filter(None, path.split('.')):
                    target = getattr(target, part)
                setattr(target, attr, val)
            if d.group is not None:
                groups.add(d.group)
        if groups & {'material', 'air'}:
            material, air = runtime.material_and_air(self, new)
            if 'material' in groups:
                self.sim.material = material
            if 'air' in groups:
                self.sim.air = air
                if air is None and self.inputs.wind is not None:
                    self.inputs.drop_wind()
        if 'limits' in groups:
            self.inputs.enforce_limits()
        if 'terms' in groups:
            for name, val in new.items():
                if name.startswith('terms.'):
                    _, term, coef = name.split('.')
                    self.sim.set_term(term, **{coef: val})
        self._dirty = True

    # ------------------------------------------------------------------ the loop
    def tick(self):
        """Advance as many steps as keep sim time with wall time (:mod:`.pacing`), then
        publish."""
        now = time.monotonic()
        self._reject.sent = 0
        if self.live is not None:
            self.live.serve()
        if self.inputs.force_timeout > 0:
            self.obstacles.expire(self.sim.time, self.inputs.force_timeout)
        self.inputs.expire(self.sim.time)
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
            self.rtf = self._window[1] / wall if not self.paused else 0.0
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
        if self.status_period > 0 and now - self._last_status >= self.status_period:
            self._last_status = now
            e = self._energy
            state = 'DIVERGED' if self.diverged else ('paused' if self.paused else 'running')
            self.get_logger().info(
                f'{state} t={self.sim.time:.3f} s  RTF {self.rtf:.2f}  step '
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
        return vertex_colors(self.coloring, self.sim, self._densities)

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
        edges = self.mesh.edges if self.wireframe else None
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
        self.energy_pub.publish(messages.energy_status(
            stamp, self.frame_id, self._energy, self.sim.time, self.sim.step_count,
            self.diverged, self.paused, self.get_fully_qualified_name()))
        if self.points_pub is not None:
            self.points_pub.publish(point_cloud(x, self.sim.velocities, stamp, self.frame_id))
        if self.shape_pub is not None:
            self.shape_pub.publish(shape_mesh(x, self.mesh.faces))
        self.obstacles.publish(stamp)
        if self.handles:
            self.handles.publish(stamp)
        if self.cameras:
            self.cameras.publish(self.sim, stamp, colors, not self.paused and self.diverged
                                 is None, PAUSED_PUBLISH_PERIOD, self.live)

    def diagnostics(self) -> DiagnosticArray:
        """``/diagnostics`` (:func:`.status.diagnostics`)."""
        return status.diagnostics(self)
