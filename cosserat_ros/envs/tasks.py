"""The three tasks: where the cloth starts, the reward, the success (SoftGym's metrics).

* :class:`ClothFlatten` -- ``cosserat_ros/ClothFlatten-v0``.
* :class:`ClothFold` -- ``cosserat_ros/ClothFold-v0``.
* :class:`ClothDrop` -- ``cosserat_ros/ClothDrop-v0``.

The metrics follow SoftGym (Lin et al., "SoftGym: Benchmarking Deep Reinforcement
Learning for Deformable Object Manipulation", CoRL 2020; its ``cloth_flatten.py``,
``cloth_fold.py`` and ``cloth_drop.py`` compute the same quantities), so that numbers
compare; the thresholds of success are this package's and stated on each class.
"""
from __future__ import annotations

import math
from typing import Dict

import numpy as np
from gymnasium import spaces

from .cloth import LIFT, THICKNESS, ClothEnv, env_coverage

__all__ = ['ClothFlatten', 'ClothFold', 'ClothDrop', 'fold_groups', 'fold_distance']


# ---------------------------------------------------------------- ClothFlatten
class ClothFlatten(ClothEnv):
    """Flatten a crumpled cloth.

    Start: the flat cloth, picked at a vertex drawn from the seed, lifted to
    :data:`CRUMPLE_HEIGHT` x cloth_size over a point drawn within a quarter of the
    cloth's size of the pick, dropped and let settle; again (at most
    :data:`CRUMPLE_LIFTS` times) until its coverage is at most :data:`CRUMPLED` of the
    flat area.

    Coverage: the area [m^2] of the cloth's projection on the ground on a fixed raster
    (:func:`.env_coverage`). Reward: the step's change of coverage. ``info``:
    ``coverage``, ``normalized_coverage`` = (coverage - start) / (flat area - start)
    (SoftGym's), success (terminated) at normalized coverage >= :data:`SUCCESS`.
    """

    default_pickers = 1
    CRUMPLE_HEIGHT = 1.0
    CRUMPLED, CRUMPLE_LIFTS = 0.6, 4
    SUCCESS = 0.9

    def _start(self, rng, options):
        L = self.cloth_size
        for _ in range(self.CRUMPLE_LIFTS):
            x = self.sim.positions
            v = int(rng.integers(len(x)))
            self.pickers[0] = x[v]
            self._grasp(0, x[v])
            up = np.array([*(x[v, :2] + rng.uniform(-0.25, 0.25, 2) * L),
                           self.CRUMPLE_HEIGHT * L])
            targets = self.pickers.copy()
            targets[0] = up
            self._move(targets)
            self._release_all()
            self._settle()
            if self.coverage() <= self.CRUMPLED * L ** 2:
                break
        self.pickers[:] = 0.0
        self.pickers[:, 2] = LIFT

    def coverage(self) -> float:
        """:func:`.env_coverage` now, computed once per cloth configuration (a step asks
        for it for its reward, success and info)."""
        key = self.sim.positions.tobytes()
        if getattr(self, '_cached', (None,))[0] != key:
            self._cached = (key, env_coverage(self))
        return self._cached[1]

    def _begin(self):
        self.start_coverage = self.coverage()
        self.flat = self.cloth_size ** 2

    def _metric(self):
        return self.coverage()

    def _reward(self, before):
        return self.coverage() - before

    def normalized_coverage(self) -> float:
        c = self.coverage()
        return (c - self.start_coverage) / max(self.flat - self.start_coverage, 1e-12)

    def _success(self):
        return self.normalized_coverage() >= self.SUCCESS

    def _task_info(self):
        return {'coverage': self.coverage(), 'start_coverage': self.start_coverage,
                'normalized_coverage': self.normalized_coverage()}


# ---------------------------------------------------------------- ClothFold
def fold_groups(resolution: int):
    """SoftGym's halves on the (r+1) x (r+1) grid, vertex (i, j) at j (r+1) + i: ``a``
    the vertices with i < r/2 (x < 0, the half to fold), ``b`` their mirrors (r - i, j)
    (the half that stays). The middle column of an even grid is in neither."""
    r = resolution
    i, j = np.meshgrid(np.arange(r + 1), np.arange(r + 1))
    left = (2 * i < r)
    a = (j * (r + 1) + i)[left]
    b = (j * (r + 1) + (r - i))[left]
    return a, b


def fold_distance(x: np.ndarray, x0: np.ndarray, a: np.ndarray, b: np.ndarray) -> float:
    """SoftGym's fold distance [m]: mean |x_a - x_b| over the mirrored pairs plus 1.2
    times the mean displacement |x_b - x0_b| of the half that stays."""
    return float(np.mean(np.linalg.norm(x[a] - x[b], axis=1))
                 + 1.2 * np.mean(np.linalg.norm(x[b] - x0[b], axis=1)))


class ClothFold(ClothEnv):
    """Fold the half of the cloth at x < 0 onto the half at x > 0.

    Start: the cloth flat, centred at the origin, its first grid axis along x, dropped
    from a height drawn in :data:`DROP` [m] and settled (so seeds differ); with
    ``rotate=True`` turned in the plane by an angle drawn from the seed
    (``info['rotation']`` [rad], 0 otherwise; the halves are the grid's halves).

    Reward: minus :func:`fold_distance`; ``info['fold_distance']``; success (terminated)
    when it is below :data:`SUCCESS` x cloth_size (0.16 m for the default 0.4 m cloth,
    whose flat start measures 0.5625 x cloth_size = 0.225 m; the scripted fold of
    ``examples/cloth_tasks.py``, corners of one edge onto the other two, ends at
    0.10-0.15 m: its crease slides by about two rows towards the carried half, which
    SoftGym's particles, pinned to the ground by their friction, do not).
    """

    default_pickers = 2
    SUCCESS = 0.4
    DROP = (0.0, 0.02)

    def __init__(self, *args, rotate: bool = False, **kwargs):
        super().__init__(*args, **kwargs)
        if not isinstance(rotate, bool):
            raise ValueError(f'rotate must be a bool, got {rotate!r}')
        self.rotate = rotate
        self.groups = fold_groups(self.resolution)
        self.rotation = 0.0

    def _start(self, rng, options):
        self.rotation = float(rng.uniform(0.0, 2 * math.pi)) if self.rotate else 0.0
        c, s = math.cos(self.rotation), math.sin(self.rotation)
        x = self.rest @ np.array([[c, s, 0.0], [-s, c, 0.0], [0.0, 0.0, 1.0]])
        x[:, 2] += THICKNESS + rng.uniform(*self.DROP)
        self.sim.set_positions(x)
        self.sim.set_velocities(np.zeros_like(x))
        self._settle()

    def _distance(self):
        return fold_distance(self.sim.positions, self.x0, *self.groups)

    def _reward(self, before):
        return -self._distance()

    def _success(self):
        return self._distance() < self.SUCCESS * self.cloth_size

    def _task_info(self):
        return {'fold_distance': self._distance(), 'rotation': self.rotation}


# ---------------------------------------------------------------- ClothDrop
class ClothDrop(ClothEnv):
    """Lay a cloth held by two corners flat onto a target square on the ground.

    Start: the cloth hangs from its two corners (0, 0) and (r, 0) held by the two pickers
    (``num_pickers`` is 2), the held edge along x at height :data:`HANG` x cloth_size,
    in the plane y = 0. Target: the flat cloth on the ground (its rest grid), its
    near edge (j = 0) ... far edge along +y, shifted in the plane by a draw within
    :data:`SHIFT` x cloth_size from the seed (the observation's ``target`` and
    ``info['target_offset']``).

    Reward: minus the mean distance [m] of the vertices to their target positions
    (SoftGym's); ``info['mean_distance']``; success (terminated) below :data:`SUCCESS` x
    cloth_size. In ``pick_place`` the pick values are a via point (:mod:`.cloth`): the
    held corners are carried over it, then in one straight leg to the place points on
    the ground, and released.
    """

    default_pickers = 2
    HANG = 1.25
    SHIFT = 0.25
    SUCCESS = 0.1

    def __init__(self, *args, **kwargs):
        if kwargs.get('num_pickers', 2) != 2:
            raise ValueError(f'ClothDrop holds two corners: num_pickers must be 2, got '
                             f'{kwargs["num_pickers"]!r}')
        super().__init__(*args, **kwargs)
        self.target = self.rest.copy()
        self.offset = np.zeros(2)

    def _start(self, rng, options):
        L = self.cloth_size
        self.offset = rng.uniform(-self.SHIFT, self.SHIFT, 2) * L
        self.target = self.rest.copy()
        self.target[:, :2] += self.offset
        self.target[:, 2] = THICKNESS
        # the rest grid turned about the x axis: y (from the j = 0 edge) hangs down -z
        x = self.rest.copy()
        y0 = x[:, 1].min()
        x[:, 2] = self.HANG * L - (x[:, 1] - y0)
        x[:, 1] = 0.0
        self.sim.set_positions(x)
        self.sim.set_velocities(np.zeros_like(x))

    def _begin(self):
        x = self.sim.positions
        r = self.resolution
        for i, v in enumerate((0, r)):
            self.pickers[i] = x[v]
            self._grasp(i, x[v])

    def _task_space(self):
        return {'target': spaces.Box(-np.inf, np.inf, (2,), np.float32)}

    def _task_obs(self):
        return {'target': self.offset.astype(np.float32)}

    def _distance(self):
        return float(np.mean(np.linalg.norm(self.sim.positions - self.target, axis=1)))

    def _reward(self, before):
        return -self._distance()

    def _success(self):
        return self._distance() < self.SUCCESS * self.cloth_size

    def _task_info(self) -> Dict[str, object]:
        return {'mean_distance': self._distance(), 'target_offset': self.offset.copy()}
