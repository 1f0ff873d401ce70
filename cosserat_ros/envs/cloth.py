"""The cloth tasks as Gymnasium environments (SoftGym's ClothFlatten, ClothFold and
ClothDrop on this package's physics): one base class, :class:`ClothEnv`, and a task class
each, which sets the start, the reward and the success.

The scene
---------
A square sheet of ``cloth_size`` [m] and ``resolution`` x ``resolution`` segments (vertex
(i, j) at index ``j (resolution + 1) + i``, i along x: the grid's row-major order, as the
node's ``~/points``), centred at the origin on a ground plane at z = 0 (friction 1.0,
contact thickness 2 mm), gravity -9.81 m/s^2, self-collision on (``self_collision``),
the explicit solver at 0.9 of its critical step. ``material``: a preset name
(``'denim'``, ...), a dict of :class:`~cosserat_ros.Material` arguments, a Material, or
None for
:data:`DEFAULT_MATERIAL`; checked as the node checks its ``material.*`` parameters.
``randomize``: node ``material.*`` parameters drawn at every reset from the episode's
generator, in the batch spec's vocabulary and by its code (``{'material.damping':
{'uniform': [0.1, 0.3]}, 'material.preset': {'choice': ['denim', 'jersey']}}``; a
drawn preset brings its own constants unless they are drawn too); the step is then 0.9
of the drawn material's critical step.

Pickers
-------
``num_pickers`` (1 or 2) grasp handles. A picker holds the layer it pinches: the
vertices within ``picker_radius`` of the point it grasps that are joined to the nearest
one through edges within the radius (:meth:`ClothEnv._grasp`); its wrench is what it
exerts on the cloth. Two held pickers are never moved farther apart than the rest
distance between the vertices they pinched (:meth:`ClothEnv._reach`): a cloth pulled
longer than it is would tear, which this model does not do.

* ``action_mode='pick_place'`` (default): per picker ``[pick_x, pick_y, place_x, place_y]``
  in [-1, 1], world x, y = value times ``cloth_size`` about the cloth's start centre
  (the workspace is twice the cloth's size). Each picker grasps the top-most vertex
  within its radius under its pick point (the nearest one if none is), lifts it by
  :data:`LIFT`, carries it along an arc (:func:`carry_arc`) to :data:`LIFT` above its
  place point or above the cloth there, lowers it by half the lift and releases it,
  every leg at :data:`SPEED`; then the cloth settles (its fastest vertex
  below :data:`SETTLED_SPEED`, checked every :data:`SETTLE_CHECK` s) or
  :data:`SETTLE_LIMIT` s pass. In ClothDrop the pickers hold the two corners already,
  and the pick values are a via point: the corners are carried at their height over
  the via points, then in one straight leg to the place points, :data:`DROP_HEIGHT`
  above the ground, and released (a cloth lowered while it is carried towards its
  held edge lies down behind it, from where its lowest point touched).
* ``action_mode='handle_delta'``: per picker ``[dx, dy, dz, grip]`` in [-1, 1], one step
  :data:`CONTROL_PERIOD` s (10 Hz): the picker moves by (dx, dy, dz) times
  ``max_delta`` [m] (default :data:`MAX_DELTA`), not below the ground; ``grip > 0`` holds
  (pinching the layer at the picker when it held nothing), ``grip <= 0`` releases.

Observations
------------
``obs_mode='state'`` (default): ``positions`` and ``velocities`` (n, 3), ``pickers`` (k, 4:
position and grip 0/1), ``wrenches`` (k, 6: force [N] and torque [N m] about the picker
on the cloth), all float32. ``'keypoints'``: ``keypoints`` (8, 3), the four corners and
the four edge midpoints, and ``pickers``. ``'depth'``: ``depth`` (h, w, 1) float32 [m]
of a top-down camera (:class:`~cosserat_ros.camera.Camera`) :data:`CAMERA_HEIGHT` above
the origin seeing the workspace about it (+-1.05 cloth_size), the camera's far distance
where nothing is seen; ``'rgbd'``: ``rgb`` (h, w, 3) uint8 and ``depth``. ``camera_size``
(default 64) is h = w. Every call returns fresh arrays. ClothDrop adds ``target`` (2,): the
target square's offset [m] from the origin (the start does not show it).

Reproducibility
---------------
``reset(seed=s)`` draws everything random from ``self.np_random`` (Gymnasium's
generator seeded by s): the same seed and actions give the same observations, rewards
and infos to the bit (whatever the numba thread count: the step's sums are ordered),
in one process and with one numba cache: a cache whose kernels were first compiled
for other argument types may compute other bits (docs/performance.md, "Environments").
A divergence of the simulator ends the episode as truncated with
``info['sim_failure']`` (the reason); ``step`` raises nothing for it.
"""
from __future__ import annotations

import dataclasses
import math
from typing import Dict, Optional

import gymnasium as gym
import numpy as np
from gymnasium import spaces

from ..batch.episode import coverage, top_vertex
from ..camera import Camera
from ..core.material import Material
from ..core.mesh import grid_mesh
from ..core.simulator import ClothSimulator, SimulationDiverged

__all__ = ['ClothEnv', 'DEFAULT_MATERIAL', 'LIFT', 'SPEED', 'SETTLE_LIMIT', 'MAX_DELTA',
           'CONTROL_PERIOD', 'ACTION_MODES', 'OBS_MODES']

#: the default fabric: the node's default material, damped as config/table.yaml's
DEFAULT_MATERIAL = dict(zeta=50.0, xi=2e-5, phi=1e-6, density=0.2, damping=0.3)
#: pick-and-place: lift [m], the speed of every leg [m/s]
LIFT, SPEED = 0.05, 0.5
#: settling after a release: the fastest vertex below this [m/s], checked every
#: SETTLE_CHECK s, at most SETTLE_LIMIT s
SETTLED_SPEED, SETTLE_CHECK, SETTLE_LIMIT = 0.05, 0.05, 1.5
#: handle_delta: one action's simulated time [s] and the largest move per action [m]
CONTROL_PERIOD, MAX_DELTA = 0.1, 0.03
ACTION_MODES = ('pick_place', 'handle_delta')
OBS_MODES = ('state', 'keypoints', 'depth', 'rgbd')
#: the ground's friction and the contact thickness [m]. At 0.5 a pick-and-place drags a
#: crumpled 0.4 m cloth whole across the ground and the scripted flatten stalls below
#: 0.3 normalized coverage; at 1.0 (cloth on a rubber mat or a rough table) the cloth
#: unfolds under the same pulls (measured: docs/performance.md, "Environments")
GROUND_FRICTION, THICKNESS = 1.0, 0.002
#: ClothDrop's pick-and-place: the height [m] the held corners are carried down to
DROP_HEIGHT = 0.01
#: the top-down camera: height above the origin [m], far distance [m]
CAMERA_HEIGHT, CAMERA_FAR = 1.0, 2.0


def material_params(material) -> dict:
    """``material`` (module docstring) as the node's ``material.*`` parameters."""
    if material is None:
        return {f'material.{k}': v for k, v in DEFAULT_MATERIAL.items()}
    if isinstance(material, Material):
        return {f'material.{f.name}': getattr(material, f.name)
                for f in dataclasses.fields(material)}
    if isinstance(material, str):
        return {'material.preset': material, 'material.damping': DEFAULT_MATERIAL['damping']}
    if isinstance(material, dict):
        return {f'material.{k}': v for k, v in {**DEFAULT_MATERIAL, **material}.items()}
    raise ValueError(f'material must be a preset name, a dict of Material arguments or '
                     f'None, got {material!r}')


def build_material(given: dict) -> Material:
    """The Material of node parameters ``given``, through the node's own checks
    (:func:`cosserat_ros.ros.scene.initial_material`); ValueError with the reason."""
    from ..ros.params import ConfigError
    from ..ros.scene import check_parameters, initial_material
    try:
        return initial_material(check_parameters(given), given)
    except ConfigError as exc:
        raise ValueError(str(exc)) from None


def check_randomize(randomize, given: dict) -> dict:
    """``randomize``: {node parameter: distribution} in the batch spec's vocabulary
    (``{uniform: [lo, hi]}``, ``{loguniform: [lo, hi]}``, ``{choice: [...]}``; checked
    by the batch's own code, each bound against the node's declarations); only
    ``material.*`` parameters. ValueError (a SpecError) with the key and why."""
    from ..batch.spec import SpecError, _check_values
    from ..batch.spec import check_randomize as check_form
    randomize = check_form({} if randomize is None else randomize)
    for k in randomize:
        if not (isinstance(k, str) and k.startswith('material.')):
            raise SpecError(f'randomize.{k}: an environment draws material.* parameters '
                            f'only')
    _check_values({'scene': given, 'randomize': randomize})
    return randomize


class ClothEnv(gym.Env):
    """The scene, pickers, actions and observations of every cloth task (module
    docstring); a task subclass gives ``_start``, ``_reward`` and ``_success``."""

    metadata = {'render_modes': ['rgb_array'], 'render_fps': 10}
    #: the task's default number of pickers and horizon per action mode
    default_pickers = 1
    default_horizon = {'pick_place': 20, 'handle_delta': 200}

    def __init__(self, action_mode: str = 'pick_place', obs_mode: str = 'state',
                 num_pickers: Optional[int] = None, cloth_size: float = 0.4,
                 resolution: int = 16, material=None, horizon: Optional[int] = None,
                 picker_radius: float = 0.03, max_delta: float = MAX_DELTA,
                 camera_size: int = 64, self_collision: bool = True,
                 randomize: Optional[dict] = None, render_mode: Optional[str] = None):
        if action_mode not in ACTION_MODES:
            raise ValueError(f'action_mode must be one of {ACTION_MODES}, got {action_mode!r}')
        if obs_mode not in OBS_MODES:
            raise ValueError(f'obs_mode must be one of {OBS_MODES}, got {obs_mode!r}')
        k = self.default_pickers if num_pickers is None else num_pickers
        if k not in (1, 2):
            raise ValueError(f'num_pickers must be 1 or 2, got {num_pickers!r}')
        if not (isinstance(resolution, int) and 2 <= resolution <= 128):
            raise ValueError(f'resolution must be an integer in [2, 128], got {resolution!r}')
        for name, v, hi in (('cloth_size', cloth_size, 10.0), ('picker_radius', picker_radius,
                                                               1.0),
                            ('max_delta', max_delta, 1.0)):
            if not (isinstance(v, (int, float)) and 0 < v <= hi):
                raise ValueError(f'{name} must be in (0, {hi}], got {v!r}')
        if render_mode not in (None, 'rgb_array'):
            raise ValueError(f"render_mode must be None or 'rgb_array', got {render_mode!r}")
        self.action_mode, self.obs_mode, self.num_pickers = action_mode, obs_mode, k
        self.cloth_size, self.resolution = float(cloth_size), resolution
        self.picker_radius, self.max_delta = float(picker_radius), float(max_delta)
        self.horizon = self.default_horizon[action_mode] if horizon is None else int(horizon)
        if self.horizon < 1:
            raise ValueError(f'horizon must be >= 1, got {horizon!r}')
        self.render_mode = render_mode
        mesh = grid_mesh(resolution, resolution, self.cloth_size, self.cloth_size)
        self.material_given = material_params(material)
        self.randomize = check_randomize(randomize, self.material_given)
        self.sim = ClothSimulator(mesh, build_material(self.material_given), dt=1e-5,
                                  check_dt=False)
        self.sim.dt = 0.9 * self.sim.critical_dt()
        self.sim.gravity = (0.0, 0.0, -9.81)
        self.sim.contact_thickness = THICKNESS
        self.sim.add_obstacle('plane', friction=GROUND_FRICTION, name='ground')
        self.sim.self_collision = self_collision      # ValueError if not a bool
        n, r = mesh.n_vertices, resolution
        self.keypoint_ids = np.array([0, r // 2, r, (r // 2) * (r + 1), (r // 2) * (r + 1) + r,
                                      r * (r + 1), r * (r + 1) + r // 2, n - 1])
        self.rest = mesh.vertices.copy()
        self.camera = Camera(camera_size, camera_size, 2 * math.degrees(math.atan(
            1.05 * self.cloth_size / CAMERA_HEIGHT)), (0.0, 0.0, CAMERA_HEIGHT),
            (1.0, 0.0, 0.0, 0.0), far=CAMERA_FAR)
        self._render_camera = None
        a = spaces.Box(-1.0, 1.0, (k, 4), np.float32)
        self.action_space = a
        self.observation_space = self._obs_space(n, k, camera_size)
        self.pickers = np.zeros((k, 3))
        self.grip = np.zeros(k, bool)
        self._hid = [None] * k
        self._seed = [0] * k
        self.centre0 = np.zeros(2)
        self.t = 0
        self.failure: Optional[str] = None

    # ------------------------------------------------------------------ spaces
    @staticmethod
    def _box(shape):
        return spaces.Box(-np.inf, np.inf, shape, np.float32)

    def _obs_space(self, n, k, size):
        pick = self._box((k, 4))
        if self.obs_mode == 'state':
            d = {'positions': self._box((n, 3)), 'velocities': self._box((n, 3)),
                 'pickers': pick, 'wrenches': self._box((k, 6))}
        elif self.obs_mode == 'keypoints':
            d = {'keypoints': self._box((8, 3)), 'pickers': pick}
        else:
            d = {'depth': spaces.Box(0.0, CAMERA_FAR, (size, size, 1), np.float32),
                 'pickers': pick}
            if self.obs_mode == 'rgbd':
                d['rgb'] = spaces.Box(0, 255, (size, size, 3), np.uint8)
        d.update(self._task_space())
        return spaces.Dict(d)

    def _task_space(self) -> dict:
        """The task's own observations' spaces (ClothDrop's target)."""
        return {}

    def _task_obs(self) -> dict:
        """The task's own observations, fresh arrays."""
        return {}

    # ------------------------------------------------------------------ episodes
    def reset(self, *, seed: Optional[int] = None, options: Optional[dict] = None):
        super().reset(seed=seed)
        sim = self.sim
        self._release_all()
        sim.reset()
        if self.randomize:
            from ..batch.spec import draw_randomized
            given = dict(self.material_given)
            if 'material.preset' in self.randomize:     # a drawn fabric's own constants
                for k in ('zeta', 'xi', 'phi', 'density'):
                    given.pop(f'material.{k}', None)
            given.update(draw_randomized(self.randomize, self.np_random))
            sim.material = build_material(given)
            sim.dt = 0.9 * sim.critical_dt()
        self.pickers[:] = 0.0
        self.pickers[:, 2] = LIFT
        self.t = 0
        self.failure = None
        try:
            self._start(self.np_random, options or {})
        except SimulationDiverged as exc:              # a start no seed should give
            raise RuntimeError(f'the start diverged: {exc}') from None
        x = sim.positions
        self.centre0 = 0.5 * (x[:, :2].min(axis=0) + x[:, :2].max(axis=0))
        self.x0 = x
        self._begin()
        return self._obs(), self._info()

    def step(self, action):
        a = np.asarray(action, dtype=np.float64).reshape(self.num_pickers, 4)
        if not np.all(np.isfinite(a)):
            raise ValueError(f'action must be finite, got {action!r}')
        a = np.clip(a, -1.0, 1.0)
        before = self._metric()
        truncated = False
        self.failure = None
        try:
            if self.action_mode == 'pick_place':
                self._pick_place(a)
            else:
                self._delta(a)
        except SimulationDiverged as exc:
            self.failure = str(exc)
            truncated = True
            self._release_all()
        self.t += 1
        reward = float(self._reward(before))
        terminated = bool(self._success()) and self.failure is None
        truncated = truncated or self.t >= self.horizon
        return self._obs(), reward, terminated, truncated, self._info()

    def render(self):
        if self.render_mode != 'rgb_array':
            return None
        if self._render_camera is None:
            c = self.camera
            self._render_camera = Camera(256, 256, c.fov, c.position, c.orientation,
                                         far=CAMERA_FAR)
        return self._render_camera.render(self.sim)[1]

    # ------------------------------------------------------------------ task hooks
    def _start(self, rng: np.random.Generator, options: dict) -> None:
        """Put the cloth where the task starts (at rest)."""

    def _begin(self) -> None:
        """After the start: what the task holds (ClothDrop's corners)."""

    def _metric(self) -> float:
        """The task's measure before a step (for a reward of its change)."""
        return 0.0

    def _reward(self, before: float) -> float:
        raise NotImplementedError

    def _success(self) -> bool:
        return False

    def _task_info(self) -> Dict[str, object]:
        return {}

    # ------------------------------------------------------------------ helpers
    def _info(self) -> dict:
        info = {'sim_time': self.sim.time, 'success': bool(self._success())}
        info.update(self._task_info())
        if self.failure is not None:
            info['sim_failure'] = self.failure
        return info

    def _obs(self) -> dict:
        k = self.num_pickers
        pick = np.zeros((k, 4), np.float32)
        pick[:, :3] = self.pickers
        pick[:, 3] = self.grip
        x = self.sim.positions
        if self.obs_mode == 'state':
            w = np.zeros((k, 6), np.float32)
            for i, hid in enumerate(self._hid):
                if hid is not None and hid in self.sim.handles:
                    f, t = self.sim.handle_wrench(hid)
                    w[i, :3], w[i, 3:] = f, t
            return {'positions': x.astype(np.float32),
                    'velocities': self.sim.velocities.astype(np.float32),
                    'pickers': pick, 'wrenches': w, **self._task_obs()}
        if self.obs_mode == 'keypoints':
            return {'keypoints': x[self.keypoint_ids].astype(np.float32), 'pickers': pick,
                    **self._task_obs()}
        depth, rgb = self.camera.render(self.sim)
        depth = np.where(np.isnan(depth), np.float32(CAMERA_FAR), depth)[:, :, None]
        if self.obs_mode == 'depth':
            return {'depth': depth, 'pickers': pick, **self._task_obs()}
        return {'rgb': rgb, 'depth': depth, 'pickers': pick, **self._task_obs()}

    def _run(self, seconds: float) -> None:
        self.sim.step(max(1, int(round(seconds / self.sim.dt))))

    def _move(self, targets: np.ndarray) -> None:
        """Carry the held pickers to ``targets`` (k, 3) at :data:`SPEED`, every picker
        arriving together; the free ones are placed there."""
        targets = self._reach(targets)
        far = float(np.max(np.linalg.norm(targets - self.pickers, axis=1)))
        seconds = max(far / SPEED, self.sim.dt)
        for i, hid in enumerate(self._hid):
            if hid is not None:
                self.sim.move_handle(hid, targets[i], duration=seconds)
        self._run(seconds)
        self.pickers = targets.copy()

    def _reach(self, targets: np.ndarray) -> np.ndarray:
        """``targets`` with two held pickers no farther apart than the rest distance
        between the vertices they pinched (the cloth between them cannot be pulled
        longer than it is: the targets are drawn in symmetrically about their midpoint)."""
        held = [i for i, h in enumerate(self._hid) if h is not None]
        if len(held) < 2:
            return targets
        i, j = held[:2]
        length = float(np.linalg.norm(self.rest[self._seed[i]] - self.rest[self._seed[j]]))
        d = float(np.linalg.norm(targets[i] - targets[j]))
        if d <= length:
            return targets
        out = targets.copy()
        mid = 0.5 * (targets[i] + targets[j])
        out[i] = mid + (targets[i] - mid) * (length / d)
        out[j] = mid + (targets[j] - mid) * (length / d)
        out[:, 2] = np.maximum(out[:, 2], THICKNESS)
        return out

    def _grasp(self, i: int, point) -> None:
        """Picker ``i`` pinches the layer at ``point``: the vertex nearest to it within
        the picker's radius and the vertices within the radius connected to it through
        edges within the radius (a pinch holds one layer: the layers folded under it
        are joined to it only outside the ball, and a free layer squeezed between two
        held ones could not be kept apart). Nothing within the radius: no grasp."""
        x, mesh = self.sim.positions, self.sim.mesh
        d = np.linalg.norm(x - np.asarray(point, dtype=float), axis=1)
        inside = (d <= self.picker_radius) & ~self._held_mask()
        if not inside.any():
            self._hid[i] = None
            self.grip[i] = False
            return
        seed = int(np.flatnonzero(inside)[np.argmin(d[inside])])
        held, todo = {seed}, [seed]
        while todo:
            v = todo.pop()
            for w in mesh.ring1[mesh.ring1_ptr[v]:mesh.ring1_ptr[v + 1]]:
                w = int(w)
                if inside[w] and w not in held:
                    held.add(w)
                    todo.append(w)
        self._hid[i] = self.sim.grasp(point=point, vertices=sorted(held),
                                      name=f'picker{i}')
        self._seed[i] = seed
        self.grip[i] = True

    def _held_mask(self) -> np.ndarray:
        """(n,) bool: the vertices the pickers hold."""
        held = np.zeros(self.sim.mesh.n_vertices, bool)
        for hid in self._hid:
            if hid is not None and hid in self.sim.handles:
                held[self.sim.handles[hid]['vertices']] = True
        return held

    def _release(self, i: int) -> None:
        """Picker ``i`` lets go (if it holds anything)."""
        hid = self._hid[i]
        if hid is not None and hid in self.sim.handles:
            self.sim.release(hid)
        self._hid[i] = None
        self.grip[i] = False

    def _release_all(self) -> None:
        for i in range(self.num_pickers):
            self._release(i)

    def _top_under(self, xy) -> float:
        """The highest free vertex [m] within twice the picker's radius of ``xy`` seen
        from above (the ground if none)."""
        x = self.sim.positions
        near = ~self._held_mask() & (np.linalg.norm(x[:, :2] - np.asarray(xy), axis=1)
                       <= 2 * self.picker_radius)
        return float(x[near, 2].max()) if near.any() else 0.0

    def _settle(self) -> None:
        waited = 0.0
        while waited < SETTLE_LIMIT:
            self._run(SETTLE_CHECK)
            waited += SETTLE_CHECK
            if np.max(np.linalg.norm(self.sim.velocities, axis=1)) < SETTLED_SPEED:
                return

    def _pick_place(self, a: np.ndarray) -> None:
        x = self.sim.positions
        place = self.centre0 + a[:, 2:] * self.cloth_size
        if not any(h is not None for h in self._hid):
            pick = self.centre0 + a[:, :2] * self.cloth_size
            for i in range(self.num_pickers):
                v = top_vertex(x, pick[i], self.picker_radius)
                self.pickers[i] = x[v]
                self._grasp(i, x[v])
            self._move(self.pickers + (0.0, 0.0, LIFT))
            # over the place point: a lift above the cloth there (the held patch must
            # not be pushed into a layer it cannot leave), lowered by half of it
            end = np.column_stack([place, self.pickers[:, 2]])
            for i in range(self.num_pickers):
                end[i, 2] = max(end[i, 2], self._top_under(place[i]) + LIFT)
            for targets in carry_arc(self.pickers, end, LIFT):
                self._move(targets)
            self._move(self.pickers - (0.0, 0.0, 0.5 * LIFT))
        else:          # corners held (ClothDrop): over the via point, then to the ground
            via = self.centre0 + a[:, :2] * self.cloth_size
            self._move(np.column_stack([via, self.pickers[:, 2]]))
            self._move(np.column_stack([place, np.full(len(place), DROP_HEIGHT)]))
        self._release_all()
        self._settle()

    def _delta(self, a: np.ndarray) -> None:
        targets = self.pickers + a[:, :3] * self.max_delta
        targets[:, 2] = np.maximum(targets[:, 2], THICKNESS)
        for i in range(self.num_pickers):
            if a[i, 3] > 0 and self._hid[i] is None:
                self._grasp(i, self.pickers[i])
            elif a[i, 3] <= 0:
                self._release(i)
        targets = self._reach(targets)
        for i, hid in enumerate(self._hid):
            if hid is not None:
                self.sim.move_handle(hid, targets[i], duration=CONTROL_PERIOD)
        self._run(CONTROL_PERIOD)
        self.pickers = targets


#: the chords of a carry's arc, and its rise over the lift as a share of half the
#: carried distance
ARC_SEGMENTS, ARC_RISE = 16, 0.5


def carry_arc(lifted: np.ndarray, place: np.ndarray, lift: float,
              segments: int = ARC_SEGMENTS, rise: float = ARC_RISE) -> np.ndarray:
    """The waypoints (segments, k, 3) of each picker's carry from ``lifted`` (k, 3) to
    ``place`` (k, 3): half an ellipse in the vertical plane through both, about the
    chord's point c(theta) = s + (1 - cos(theta)) / 2 (p - s) moved by -lift e_z,
    p(theta) = c(theta) + (lift + rise (d/2) sin(theta)) e_z, theta from 0 to pi (s, p
    the two points, d their horizontal distance). Relative to the crease, which lies
    about midway, the picked point then stays nearer than d/2 with rise < 1 (a half folded
    over keeps slack), so the carry neither drags the cloth over the crease nor, lifted,
    over the rest (a straight carry does one or the other)."""
    k = len(lifted)
    out = np.empty((segments, k, 3))
    for i in range(k):
        start = np.asarray(lifted[i], dtype=float)
        end = np.asarray(place[i], dtype=float)
        half = 0.5 * float(np.linalg.norm(end[:2] - start[:2]))
        for s in range(segments):
            th = math.pi * (s + 1) / segments
            out[s, i] = start + 0.5 * (1 - math.cos(th)) * (end - start) + \
                (0.0, 0.0, rise * half * math.sin(th))
    return out


def env_coverage(env: ClothEnv) -> float:
    """The cloth's projection on the ground [m^2] (the batch's :func:`coverage`)."""
    return coverage(env.sim.positions, env.sim.mesh.faces)
