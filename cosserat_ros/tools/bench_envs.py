"""``make bench``, part ``envs``: what the Gymnasium tasks (:mod:`cosserat_ros.envs`) cost,
in one run.

* per task at its default options (16 x 16 cloth of 0.4 m), on one numba thread (one
  core, as a vector's worker): ``handle_delta`` steps per second (0.1 s of simulation
  each) and seconds per ``pick_place`` step (a pick, a carry and the settle: about 1-2.5
  s of simulation), and the share of the step's wall time spent outside the simulator's
  ``step`` (observations, rewards, metrics, bookkeeping; target below 10 %);
* :func:`cosserat_ros.envs.make_vector_env`: 2 environments (one worker process and one
  thread each) against 1, ``handle_delta`` on ClothFold, steps of all environments per
  second: the ratio (target >= 1.6 on 2 cores), with equal work in both workers and with
  each its own seed and random actions (a vector steps in lock-step, so unequal work
  waits for the slower worker).
"""
from __future__ import annotations

import time

import numpy as np

__all__ = ['part_envs']

TASKS = ('cosserat_ros/ClothFlatten-v0', 'cosserat_ros/ClothFold-v0',
         'cosserat_ros/ClothDrop-v0')


def _timed_env(env_id: str, mode: str):
    """The environment with its simulator's ``step`` timed (the seconds it took, summed in
    ``box[0]``)."""
    import gymnasium as gym
    env = gym.make(env_id, action_mode=mode)
    sim = env.unwrapped.sim
    inner = sim.step
    box = [0.0]

    def step(*args, **kwargs):
        t0 = time.perf_counter()
        try:
            return inner(*args, **kwargs)
        finally:
            box[0] += time.perf_counter() - t0
    sim.step = step
    return env, box


def _run(env_id: str, mode: str, steps: int, seed: int = 0):
    """(wall seconds per step, share outside the simulator's step) over ``steps`` random
    actions after a reset (the reset not counted)."""
    env, box = _timed_env(env_id, mode)
    env.reset(seed=seed)
    rng = np.random.default_rng(seed)
    box[0] = 0.0
    t0 = time.perf_counter()
    for _ in range(steps):
        a = rng.uniform(-1, 1, env.action_space.shape).astype(np.float32)
        _, _, term, trunc, _ = env.step(a)
        if term or trunc:
            env.reset(seed=seed + 1)
    wall = time.perf_counter() - t0
    env.close()
    return wall / steps, max(0.0, 1.0 - box[0] / wall)


def _vector_rate(n: int, steps: int, same: bool) -> float:
    """Steps of all environments per second of a vector of ``n`` (the first step, which
    loads the workers' kernels, not counted): ``same``: every environment the same seed
    and actions (equal work: the parallel efficiency); else seeds 0..n-1 and each its own
    random actions (unequal work: the vector steps in lock-step, at its slowest
    environment's pace)."""
    from ..envs import make_vector_env
    vec = make_vector_env('cosserat_ros/ClothFold-v0', n, action_mode='handle_delta')
    try:
        vec.reset(seed=[0] * n if same else list(range(n)))
        rng = np.random.default_rng(0)
        shape = vec.action_space.shape

        def action():
            if same:
                return np.repeat(rng.uniform(-1, 1, (1, *shape[1:])), n, 0).astype(np.float32)
            return rng.uniform(-1, 1, shape).astype(np.float32)
        vec.step(action())
        t0 = time.perf_counter()
        for _ in range(steps):
            vec.step(action())
        return n * steps / (time.perf_counter() - t0)
    finally:
        vec.close()


def part_envs(steps: int = 20) -> None:
    """Print the part's figures (module docstring); ``steps`` handle_delta steps per
    case (pick_place: a quarter of them, at least 2)."""
    import numba
    import cosserat_ros.envs  # noqa: F401  (registers the ids)
    threads = numba.get_num_threads()
    numba.set_num_threads(1)
    print('\n== envs: the Gymnasium tasks (one numba thread, default options) ==')
    print(f'{"task":28} {"handle_delta":>16} {"outside sim":>12} {"pick_place":>14} '
          f'{"outside sim":>12}')
    try:
        for env_id in TASKS:
            _run(env_id, 'handle_delta', 1)                  # compile / load caches
            d, d_out = _run(env_id, 'handle_delta', steps)
            p, p_out = _run(env_id, 'pick_place', max(2, steps // 4))
            print(f'{env_id:28} {1 / d:11.1f} st/s {100 * d_out:11.1f}% '
                  f'{p:11.2f} s/st {100 * p_out:11.1f}%', flush=True)
    finally:
        numba.set_num_threads(threads)
    one = _vector_rate(1, 2 * steps, True)
    for same, what in ((True, 'equal work (same seed and actions)'),
                       (False, 'unequal work (own seeds and random actions)')):
        two = _vector_rate(2, 2 * steps, same)
        print(f'AsyncVectorEnv, ClothFold handle_delta, 1 thread per worker, {what}: '
              f'1 env {one:.1f} st/s, 2 envs {two:.1f} st/s: {two / one:.2f}x (target '
              f'>= 1.6 on 2 cores)', flush=True)

if __name__ == '__main__':
    part_envs()
