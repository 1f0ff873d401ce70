"""One episode: build the scene, place the cloth, act, record a bag, measure.

:func:`run_episode` is pure: no Ray, no ROS graph (the messages are serialised by the same
builders the node publishes with and written by :class:`..tools.bagfile.BagWriter`), and
its bag is a function of the episode alone: the same episode gives the same bytes on any
worker, attempt or thread count (the step is deterministic; nothing of the wall clock
enters the bag).

What a run writes, under ``OUT/episodes/<id>/``:

* ``bag/`` -- a rosbag2 directory (``metadata.yaml``, ``bag.mcap``), log times =
  simulation time, with ``/clock``, ``/cloth_node/mesh`` and ``/cloth_node/energy`` at
  ``record.mesh_hz``, ``/cloth_node/points`` at ``record.points_hz`` (if > 0), every
  obstacle's ``/cloth_node/contact/<name>`` and every handle's
  ``/cloth_node/handles/<name>/wrench`` with each mesh, and ``/cloth_node/obstacle_markers``
  at the start, once a simulated second and after every change of the obstacle set;
* ``params.yaml`` -- the episode's node parameters, a file ``cloth_node --params-file``
  takes (it reproduces the scene; the initial placement and the policy are in
  ``result.json``);
* ``env.yaml`` instead, for an environment's episode (``env`` in the spec:
  :mod:`.env_episode`): the id, options, agent and seed that reproduce it;
* ``result.json`` -- the manifest line of the episode (:func:`run_episode`'s result).

The directory is written under ``OUT/.tmp/`` and renamed into ``episodes/`` whole (a rename
is atomic on one file system): a reader sees an episode completely or not at all, and a
second attempt that finishes after the first finds its place taken and leaves it.
"""
from __future__ import annotations

import hashlib
import json
import math
import os
from pathlib import Path
import platform
import shutil
import socket
import time
from typing import Callable, Dict, List, Optional
import uuid

import numpy as np

from .spec import Episode, resolve_script

__all__ = ['run_episode', 'EpisodeFailed', 'NODE', 'cpu_model', 'coverage',
           'commit_directory', 'package_version', 'result_line']

#: the node name the bag's topics are under (as a node of that name publishes them)
NODE = 'cloth_node'
#: [m] the raster step of the coverage
COVERAGE_PIXEL = 5e-3
#: [m/s] the crumpling lifts' speed, and [s] the time given to each before the policy
CRUMPLE_SPEED = 1.0
CRUMPLE_TIME = 1.5


class EpisodeFailed(RuntimeError):
    """The episode cannot run, for a reason that would recur on any attempt."""


def package_version() -> str:
    try:
        from importlib.metadata import version
        return version('cosserat_ros')
    except Exception:                               # not installed as a distribution
        return 'unknown'


def cpu_model() -> str:
    """The CPU's model name (reproducibility holds on the same build and CPU type)."""
    try:
        with open('/proc/cpuinfo') as fh:
            for line in fh:
                if line.startswith('model name'):
                    return line.split(':', 1)[1].strip()
    except OSError:
        pass
    return platform.processor() or platform.machine()


def coverage(x: np.ndarray, faces: np.ndarray, pixel: float = COVERAGE_PIXEL) -> float:
    """The area [m^2] of the cloth's projection on the ground plane (x, y), on a raster
    of ``pixel`` [m] (:func:`..core.scenarios.shadow`)."""
    from ..core.scenarios import shadow
    return shadow(np.ascontiguousarray(x[:, :2]), faces, pixel)[0]


# ---------------------------------------------------------------- placing the cloth
def _rotation(axis, angle: float) -> np.ndarray:
    """Rodrigues: the rotation by ``angle`` [rad] about unit ``axis``."""
    k = np.asarray(axis, dtype=float)
    k = k / np.linalg.norm(k)
    K = np.array([[0, -k[2], k[1]], [k[2], 0, -k[0]], [-k[1], k[0], 0]])
    return np.eye(3) + math.sin(angle) * K + (1 - math.cos(angle)) * K @ K


def support_height(sim, lo_xy, hi_xy) -> float:
    """The highest point [m] of the obstacles over the rectangle [lo_xy, hi_xy] (their
    bounding boxes; a plane at the rectangle's corners); -inf if none is under it."""
    from ..core.contact import rotation_matrix
    top = -math.inf
    corners = np.array([[lo_xy[0], lo_xy[1]], [lo_xy[0], hi_xy[1]], [hi_xy[0], lo_xy[1]],
                        [hi_xy[0], hi_xy[1]]])
    for oid, d in sim.obstacles.items():
        c = np.asarray(d['position'], dtype=float)
        R = rotation_matrix(d['orientation'])
        shape = d['shape']
        if shape == 'plane':                        # through c, normal R e_z
            n = R[:, 2]
            if abs(n[2]) < 1e-6:
                continue                            # a wall: nothing under the cloth
            zs = c[2] - (n[0] * (corners[:, 0] - c[0]) + n[1] * (corners[:, 1] - c[1])) / n[2]
            top = max(top, float(zs.max()))
            continue
        if shape == 'sphere':
            half = np.full(3, d['radius'])
        elif shape == 'box':
            half = np.abs(R) @ np.asarray(d['half_extents'])
        elif shape in ('capsule', 'cylinder'):
            extra = d['radius'] if shape == 'capsule' else 0.0
            half = np.abs(R[:, 2]) * (d['half_length'] + extra) + d['radius']
        else:                                       # mesh: its vertices, posed
            verts, _ = sim.obstacle_mesh(oid)
            half = np.abs(verts @ R.T).max(axis=0)
        if np.all(c[:2] + half[:2] >= lo_xy) and np.all(c[:2] - half[:2] <= hi_xy):
            top = max(top, float(c[2] + half[2]))
    return top


def place(sim, init: dict) -> None:
    """Put the cloth where ``init`` says (module :mod:`.spec`): tilted about its centre
    for a drop, its lowest point ``height`` above the highest obstacle under it (above
    z = 0 with none), at rest."""
    kind = init['kind']
    x = sim.positions.copy()
    if kind in ('drop', 'crumple'):
        tilt = math.radians(float(init.get('tilt_deg', 0.0) or 0.0))
        az = math.radians(float(init.get('azimuth_deg', 0.0) or 0.0))
        c = x.mean(axis=0)
        R = _rotation((math.cos(az), math.sin(az), 0.0), tilt)
        x = (x - c) @ R.T + c
        lo, hi = x[:, :2].min(axis=0), x[:, :2].max(axis=0)
        top = support_height(sim, lo, hi)
        base = top if math.isfinite(top) else 0.0
        x[:, 2] += base + float(init['height']) - x[:, 2].min()
    elif float(init.get('height', 0.0)):
        x[:, 2] += float(init['height'])
    sim.set_positions(x)
    sim.set_velocities(np.zeros_like(x))


def top_vertex(x: np.ndarray, xy, radius: float) -> int:
    """The highest vertex within ``radius`` [m] of ``xy`` seen from above, else the one
    nearest to it."""
    d = np.linalg.norm(x[:, :2] - np.asarray(xy, dtype=float), axis=1)
    near = np.flatnonzero(d <= radius)
    if len(near) == 0:
        return int(np.argmin(d))
    return int(near[np.argmax(x[near, 2])])


# ---------------------------------------------------------------- actions
class Timeline:
    """Actions at simulation steps: ``at(step, fn)``; :meth:`due` pops those whose step
    has come, in the order they were added for the same step."""

    def __init__(self):
        self._items: List[tuple] = []

    def at(self, step: int, fn: Callable[[], None]) -> None:
        self._items.append((int(step), len(self._items), fn))
        self._items.sort(key=lambda a: a[:2])

    def next_step(self) -> Optional[int]:
        return self._items[0][0] if self._items else None

    def due(self, step: int) -> List[Callable[[], None]]:
        out = []
        while self._items and self._items[0][0] <= step:
            out.append(self._items.pop(0)[2])
        return out


def pick_place(sim, tl: Timeline, start: int, moves, radius: float, lift: float,
               speed: float, settle: float, centre0, size0,
               handles: Dict[str, Optional[int]], names: List[str]) -> None:
    """Schedule ``moves`` (per move: per handle a pick (u, v) and a place (u, v)) from
    step ``start``, one after the other: grasp the top-most vertex within ``radius``
    under each pick point ((u, v) in [-1, 1]^2 of the cloth's footprint then), lift by
    ``lift`` [m], carry to the place point ((u, v) times the cloth's half size about
    ``centre0``, where it started), lower by half the lift, release, and let it settle
    ``settle`` [s] before the next. Every leg at ``speed`` [m/s] (the farthest handle's
    distance over the speed); each phase is scheduled when the previous one ends, so
    the moves run as far as the episode lasts."""
    dt = sim.dt
    todo = list(moves)

    def steps_for(distance: float) -> int:
        return max(1, int(math.ceil(distance / speed / dt)))

    def held():
        return [(name, handles[name]) for name in names
                if handles.get(name) is not None and handles[name] in sim.handles]

    def go_to(targets, then):
        """Move each held handle to its target; ``then`` when the farthest arrives."""
        far = 0.0
        for name, hid in held():
            p = np.array(sim.handles[hid]['position'], dtype=float)
            q = targets(name, p)
            far = max(far, float(np.linalg.norm(q - p)))
        k = steps_for(max(far, 1e-9))
        for name, hid in held():
            p = np.array(sim.handles[hid]['position'], dtype=float)
            sim.move_handle(hid, targets(name, p), duration=k * dt)
        tl.at(sim.step_count + k, then)

    def begin():
        if not todo:
            return
        picks, places = todo.pop(0)
        x = sim.positions
        lo, hi = x[:, :2].min(axis=0), x[:, :2].max(axis=0)
        centre, half = 0.5 * (lo + hi), 0.5 * (hi - lo)
        for name, uv in zip(names, picks):
            v = top_vertex(x, centre + np.asarray(uv) * half, radius)
            try:
                handles[name] = sim.grasp(point=x[v], radius=radius, name=name)
            except ValueError:                 # its vertices are another handle's
                handles[name] = None
        place = {name: np.asarray(centre0) + np.asarray(uv) * size0
                 for name, uv in zip(names, places)}

        def up(name, p):
            return p + (0.0, 0.0, lift)

        def over(name, p):
            return np.array([place[name][0], place[name][1], p[2]])

        def down(name, p):
            return p - (0.0, 0.0, 0.5 * lift)

        def release():
            for name, hid in held():
                sim.release(hid)
            for name in names:
                handles[name] = None
            tl.at(sim.step_count + max(1, int(round(settle / dt))), begin)

        go_to(up, lambda: go_to(over, lambda: go_to(down, release)))

    tl.at(start, begin)


# ---------------------------------------------------------------- the run
class _Recorder:
    """The bag of one episode and the running metrics."""

    def __init__(self, path: Path, sim, params: dict, handle_names: List[str],
                 points: bool, cameras: Dict[str, dict]):
        from ..ros import messages
        from ..ros.conversions import OPTIONAL_MARKERS, mesh_marker_array, optional_markers
        from ..tools.bagfile import BagWriter, qos_yaml
        from rclpy.serialization import serialize_message
        self.m, self.ser = messages, serialize_message
        self.mesh_msg, self.optional, self.all_optional = (mesh_marker_array,
                                                           optional_markers,
                                                           OPTIONAL_MARKERS)
        self.sim, self.frame = sim, params['frame_id']
        self.coloring = params['coloring']
        self.bag = BagWriter(path)
        self.topics = {'clock': '/clock', 'mesh': f'/{NODE}/mesh',
                       'energy': f'/{NODE}/energy', 'points': f'/{NODE}/points',
                       'obstacles': f'/{NODE}/obstacle_markers'}
        self.bag.add('/clock', 'rosgraph_msgs/msg/Clock', qos_yaml(latched=True, depth=1))
        self.bag.add(self.topics['mesh'], 'visualization_msgs/msg/MarkerArray')
        self.bag.add(self.topics['energy'], 'diagnostic_msgs/msg/DiagnosticArray')
        if points:
            self.bag.add(self.topics['points'], 'sensor_msgs/msg/PointCloud2')
        self.bag.add(self.topics['obstacles'], 'visualization_msgs/msg/MarkerArray')
        self.contact_topics = {}
        for oid, d in sim.obstacles.items():
            t = f'/{NODE}/contact/{d["name"]}'
            self.contact_topics[oid] = t
            self.bag.add(t, 'geometry_msgs/msg/WrenchStamped')
        self.handle_topics = {}
        for name in handle_names:
            t = f'/{NODE}/handles/{name}/wrench'
            self.handle_topics[name] = t
            self.bag.add(t, 'geometry_msgs/msg/WrenchStamped')
        self.cameras = cameras
        for name, spec in cameras.items():
            base = f'/{NODE}/cameras/{name}'
            self.bag.add(f'{base}/depth/image_raw', 'sensor_msgs/msg/Image')
            self.bag.add(f'{base}/color/image_raw', 'sensor_msgs/msg/Image')
            self.bag.add(f'{base}/camera_info', 'sensor_msgs/msg/CameraInfo')
            if spec['points']:
                self.bag.add(f'{base}/points', 'sensor_msgs/msg/PointCloud2')
            self.bag.add(f'{base}/pose_out', 'geometry_msgs/msg/PoseStamped')
        self.mesh_points: Dict[int, list] = {}
        e = sim.mesh.edges
        self.edges = e
        self.rest = np.linalg.norm(sim.mesh.vertices[e[:, 1]] - sim.mesh.vertices[e[:, 0]],
                                   axis=1)
        self.max_strain = 0.0
        self.peak_handle = 0.0
        self.peak_contact = 0.0
        self.energy: Dict[str, float] = {}
        self.last_obstacles = (None, None)

    def _write(self, topic: str, stamp: int, msg) -> None:
        """``msg`` (serialised bytes, or an rclpy message) into the bag. rclpy's CDR
        leaves its alignment padding uninitialised (the same message serialises to
        different bytes), so its output is written again by rosbags' serialiser, which
        pads with zeros: the bag is then a function of the episode alone."""
        if not isinstance(msg, bytes):
            kind = self.bag.topics[topic].type_name
            ts = self.bag.typestore
            msg = ts.serialize_cdr(ts.deserialize_cdr(self.ser(msg), kind), kind)
        self.bag.write(topic, stamp, msg)

    def _points_of(self, oid):
        if oid not in self.mesh_points:
            verts, faces = self.sim.obstacle_mesh(oid)
            self.mesh_points[oid] = self.m.mesh_triangle_points(verts, faces)
        return self.mesh_points[oid]

    def obstacles(self, stamp: int, force: bool = False) -> None:
        sim = self.sim
        key = tuple(sorted(sim.obstacles))
        if not force and key == self.last_obstacles[0] and stamp < self.last_obstacles[1]:
            return
        self.last_obstacles = (key, stamp + 1_000_000_000)
        self._write(self.topics['obstacles'], stamp,
                    self.m.obstacle_markers(sim.obstacles, self._points_of, stamp,
                                            self.frame))

    def state(self, stamp: int, handles: Dict[str, Optional[int]]) -> None:
        from ..ros.conversions import vertex_colors
        sim = self.sim
        energy, densities = sim.energy_and_densities()
        self.energy = {k: float(v) for k, v in energy.items()}
        x = sim.positions
        self._write('/clock', stamp, self.m.clock(stamp))
        pinned = np.flatnonzero(sim.pinned)
        held_ids = sim.handles
        held = np.array([d['position'] for d in held_ids.values()])
        drawn = self.optional(None, pinned, held)
        self._write(self.topics['mesh'], stamp, self.mesh_msg(
            x, sim.mesh.faces, vertex_colors(self.coloring, sim, densities), stamp,
            self.frame, pinned=pinned, pin_size=0.3 * sim.mesh.mean_edge_length,
            handles=held, delete=sorted(self.all_optional - drawn)))
        self._write(self.topics['energy'], stamp, self.m.energy_status(
            stamp, self.frame, energy, sim.time, sim.step_count, None, False, f'/{NODE}'))
        for oid, (f, t) in sim.contact_forces().items():
            if oid in self.contact_topics:
                self._write(self.contact_topics[oid], stamp,
                            self.m.wrench(stamp, self.frame, f, t))
                self.peak_contact = max(self.peak_contact, float(np.linalg.norm(f)))
        for name, topic in self.handle_topics.items():
            hid = handles.get(name)
            f = t = np.zeros(3)
            if hid is not None and hid in held_ids:
                f, t = sim.handle_wrench(hid)
            self._write(topic, stamp, self.m.wrench(stamp, self.frame, f, t))
            self.peak_handle = max(self.peak_handle, float(np.linalg.norm(f)))
        e = self.edges
        length = np.linalg.norm(x[e[:, 1]] - x[e[:, 0]], axis=1)
        self.max_strain = max(self.max_strain, float(np.max(np.abs(length / self.rest - 1))))

    def points(self, stamp: int) -> None:
        from ..ros.conversions import point_cloud
        self._write(self.topics['points'], stamp,
                    point_cloud(self.sim.positions, self.sim.velocities, stamp, self.frame))

    def camera(self, name: str, stamp: int) -> None:
        """Camera ``name``'s topics, as the node publishes them (:mod:`..ros.cameras`)."""
        from ..ros.cameras import optical_frame
        from ..ros.conversions import camera_info, image, organised_cloud, vertex_colors
        sim, spec = self.sim, self.cameras[name]
        cam = spec['camera']
        densities = sim.energy_and_densities()[1] if self.coloring == 'energy' else None
        depth, rgb = cam.render(sim, vertex_colors(self.coloring, sim, densities))
        base, frame = f'/{NODE}/cameras/{name}', optical_frame(name)
        self._write(f'{base}/depth/image_raw', stamp, image(depth, stamp, frame))
        self._write(f'{base}/color/image_raw', stamp, image(rgb, stamp, frame))
        self._write(f'{base}/camera_info', stamp,
                    camera_info(cam.intrinsics, cam.width, cam.height, stamp, frame))
        if spec['points']:
            self._write(f'{base}/points', stamp, organised_cloud(cam.points(depth), stamp,
                                                                 frame))
        self._write(f'{base}/pose_out', stamp,
                    self.m.pose(stamp, self.frame, cam.position, cam.orientation))


def _simulate(episode: Episode, bag_dir: Path) -> dict:
    """Build, place, act and record; the metrics. Raises EpisodeFailed (or the
    simulator's SimulationDiverged) for what any attempt would meet."""
    from ..core.simulator import SimulationDiverged
    from ..ros.params import ConfigError
    from ..ros.scene import build_simulator, check_parameters
    if episode.policy['kind'] == 'env':
        from .env_episode import simulate_env
        p = check_parameters({})        # the node's defaults: the frame and the colouring
        return simulate_env(episode, bag_dir,
                            lambda path, sim, names: _Recorder(path, sim, p, names, False, {}))
    try:
        p = check_parameters(episode.params)
        sim = build_simulator(p, given=episode.params)
    except ConfigError as exc:
        raise EpisodeFailed(f'refused: {exc}') from None
    dt = sim.dt
    place(sim, episode.init)
    end = int(round(episode.duration / dt))
    tl = Timeline()
    handles: Dict[str, Optional[int]] = {}
    policy = episode.policy
    names: List[str] = []
    x0 = sim.positions
    centre0 = 0.5 * (x0[:, :2].min(axis=0) + x0[:, :2].max(axis=0))
    size0 = 0.5 * (x0[:, :2].max(axis=0) - x0[:, :2].min(axis=0))
    if episode.init['kind'] == 'crumple':
        # picked at random points, lifted and dropped; then the episode's policy
        names = ['crumple']
        pick_place(sim, tl, 0, [([uv], [[0.0, 0.0]]) for uv in episode.init['picks']],
                   0.03, float(episode.init['height']), CRUMPLE_SPEED, 0.5, centre0,
                   np.zeros(2), handles, ['crumple'])
    if policy['kind'] == 'pick_place':
        pnames = [f'h{i}' for i in range(int(policy['handles']))]
        names += pnames
        start = int(round(float(policy['start']) / dt))
        if episode.init['kind'] == 'crumple':
            start += int(round(len(episode.init['picks']) * CRUMPLE_TIME / dt))
        pick_place(sim, tl, start, list(zip(policy['picks'], policy['places'])),
                   float(policy['radius']), float(policy['lift']), float(policy['speed']),
                   float(policy['settle']), centre0, size0, handles, pnames)
    script = None
    if policy['kind'] == 'script':
        try:
            script = resolve_script(policy['target'])
        except ValueError as exc:
            raise EpisodeFailed(str(exc)) from None
    from ..ros.cameras import camera_specs
    cameras = camera_specs(p)
    rec = _Recorder(bag_dir, sim, p, names, episode.record['points_hz'] > 0, cameras)
    # a rate's k-th sample is at step round(k / (hz dt)): on time, not drifting; what is
    # recorded at each rate, in order: the state (with the obstacles), the points, the
    # cameras (at cameras.<name>.rate)
    actions = [(episode.record['mesh_hz'],
                lambda stamp: (rec.obstacles(stamp), rec.state(stamp, handles)))]
    if episode.record['points_hz'] > 0:
        actions.append((episode.record['points_hz'], rec.points))
    for cname, cspec in cameras.items():
        actions.append((cspec['rate'], lambda stamp, n=cname: rec.camera(n, stamp)))
    rates = [hz for hz, _ in actions]

    def due(hz: float, step: int) -> bool:
        k = round(step * hz * dt)
        return step == end or int(round(k / (hz * dt))) == step

    def after(hz: float, step: int) -> int:
        k = max(0, int(step * hz * dt) - 1)
        while int(round(k / (hz * dt))) <= step:
            k += 1
        return int(round(k / (hz * dt)))

    def boundary(step: int) -> int:
        """The next step after ``step`` at which something is recorded (or the end)."""
        return min([end] + [after(hz, step) for hz in rates])

    def record(step: int) -> None:
        stamp = int(round(step * dt * 1e9))
        for hz, action in actions:
            if due(hz, step):
                action(stamp)

    try:
        if script is not None:
            script_driver = _ScriptStepper(sim, record, boundary, end)
            try:
                script(script_driver, np.random.default_rng(episode.seed), episode)
            except (SimulationDiverged, OSError, MemoryError):
                raise
            except Exception as exc:            # the user's code: the same every attempt
                raise EpisodeFailed(f'policy {policy["target"]} raised '
                                    f'{type(exc).__name__}: {exc}') from None
            script_driver.finish()
        else:
            step = 0
            record(0)
            while step < end:
                for fn in tl.due(step):
                    fn()
                target = boundary(step)
                if tl.next_step() is not None:
                    target = min(target, max(tl.next_step(), step + 1))
                sim.step(target - step)
                step = target
                record(step)
    finally:
        rec.bag.close()
    x = sim.positions
    return {'kinetic_energy': rec.energy.get('kinetic', 0.0),
            'elastic_energy': rec.energy.get('elastic', 0.0),
            'max_edge_strain': rec.max_strain,
            'peak_handle_force': rec.peak_handle,
            'peak_contact_force': rec.peak_contact,
            'coverage': coverage(x, sim.mesh.faces),
            'final_height': float(x[:, 2].mean())}, sim.time


class _ScriptStepper:
    """What a ``policy: {script: ...}`` function is handed as ``sim``: the simulator
    itself (every method and property), whose :meth:`step` also records at the episode's
    rates and stops at the episode's end (a call past it steps only up to it)."""

    def __init__(self, sim, record, boundary, end: int):
        object.__setattr__(self, '_sim', sim)
        object.__setattr__(self, '_record', record)
        object.__setattr__(self, '_boundary', boundary)
        object.__setattr__(self, '_end', end)
        record(0)

    def __getattr__(self, name):
        return getattr(self._sim, name)

    def __setattr__(self, name, value):
        setattr(self._sim, name, value)

    @property
    def remaining_steps(self) -> int:
        return self._end - self._sim.step_count

    def step(self, n: int = 1) -> None:
        left = min(int(n), self.remaining_steps)
        while left > 0:
            step = self._sim.step_count
            k = min(left, self._boundary(step) - step)
            self._sim.step(k)
            left -= k
            self._record(self._sim.step_count)

    def finish(self) -> None:
        """Step what the script left of the episode (no action)."""
        self.step(self.remaining_steps)


def result_line(episode: Episode, **fields) -> dict:
    """An episode's manifest line (``status`` 'ok' until ``fields`` say otherwise): what
    it is, where it ran, and room for its results."""
    line = {'id': episode.id, 'index': episode.index, 'seed': episode.seed,
            'params': episode.params, 'init': episode.init, 'policy': episode.policy,
            'status': 'ok', 'error': None, 'deterministic': True, 'metrics': None,
            'sim_time': 0.0, 'wall_time': 0.0, 'host': socket.gethostname(),
            'cpu': cpu_model(), 'bag_sha256': None, 'version': package_version(),
            'spec_digest': episode.spec_digest}
    line.update(fields)
    return line


def commit_directory(staged: Path, final: Path) -> bool:
    """Rename the finished ``staged`` directory to ``final``; False (and ``staged``
    removed) if ``final`` exists: another attempt put its episode there first."""
    final.parent.mkdir(parents=True, exist_ok=True)
    try:
        os.rename(staged, final)
        return True
    except OSError:
        if final.exists():
            shutil.rmtree(staged, ignore_errors=True)
            return False
        raise


def file_sha256(path: Path) -> str:
    h = hashlib.sha256()
    with open(path, 'rb') as fh:
        for block in iter(lambda: fh.read(1 << 20), b''):
            h.update(block)
    return h.hexdigest()


def run_episode(episode, out_dir) -> dict:
    """Run ``episode`` (an :class:`.spec.Episode` or its dict) and write it under
    ``out_dir/episodes/<id>/`` (module docstring); returns its result, the manifest line
    (``status`` 'ok' or 'failed' with ``error``; ``metrics``, ``bag_sha256``, ...).

    A failure any attempt would meet (a refused parameter, a diverged simulation) is a
    'failed' result with the reason; anything else (a full disk, a killed process)
    propagates, for the caller to retry. Pure: no Ray, no ROS graph."""
    import yaml
    from ..core.simulator import SimulationDiverged
    from ..ros.scene import params_file_tree
    if isinstance(episode, dict):
        episode = Episode(**{k: v for k, v in episode.items() if k != 'extra'})
    out = Path(out_dir)
    staged = out / '.tmp' / f'{episode.id}.{uuid.uuid4().hex}'
    staged.mkdir(parents=True)
    t0 = time.perf_counter()
    result = result_line(episode)
    try:
        if episode.policy['kind'] == 'env':     # what reproduces it: make, reset, agent
            with open(staged / 'env.yaml', 'w') as fh:
                yaml.safe_dump({k: v for k, v in episode.policy.items() if k != 'kind'}
                               | {'seed': episode.seed}, fh, sort_keys=True)
        else:
            with open(staged / 'params.yaml', 'w') as fh:
                yaml.safe_dump(params_file_tree(episode.params), fh, sort_keys=True)
        try:
            metrics, sim_time = _simulate(episode, staged / 'bag')
        except (EpisodeFailed, SimulationDiverged) as exc:
            result.update(status='failed', error=str(exc).splitlines()[0])
            shutil.rmtree(staged / 'bag', ignore_errors=True)    # no partial bag
        else:
            result.update(metrics=metrics, sim_time=sim_time,
                          bag_sha256=file_sha256(staged / 'bag' / 'bag.mcap'))
        result['wall_time'] = time.perf_counter() - t0
        (staged / 'result.json').write_text(json.dumps(result, sort_keys=True) + '\n')
        final = out / 'episodes' / episode.id
        if not commit_directory(staged, final):
            return json.loads((final / 'result.json').read_text())
        return result
    except BaseException:
        shutil.rmtree(staged, ignore_errors=True)
        raise
