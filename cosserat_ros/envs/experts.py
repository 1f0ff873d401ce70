"""Scripted experts and a random agent for the cloth tasks, and the command that runs
them over seeds and prints each task's metric::

    python -m cosserat_ros.envs.experts [--task fold|flatten|drop|all] [--seeds 20]

An expert is ``f(env) -> action`` for the unwrapped environment in ``pick_place`` mode
(it reads the simulator's state, as a privileged teacher does).
"""
from __future__ import annotations

import argparse
import sys
import time

import numpy as np

__all__ = ['fold_expert', 'flatten_expert', 'flat_pose', 'drop_expert', 'random_agent', 'EXPERTS',
           'METRICS', 'evaluate', 'main']


def _to_action(env, xy) -> np.ndarray:
    """World x, y [m] as the action's [-1, 1] values (about the start centre)."""
    return np.clip((np.asarray(xy, dtype=float) - env.centre0) / env.cloth_size, -1.0, 1.0)


def fold_expert(env) -> np.ndarray:
    """Pick the two corners of the grid's edge i = 0 (x < 0 at the start) and place them
    on the corners of the edge i = r (each picker one pair): one action."""
    x, r = env.sim.positions, env.resolution
    pairs = ((0, r), (r * (r + 1), r * (r + 1) + r))
    a = np.zeros((env.num_pickers, 4), np.float32)
    for k in range(env.num_pickers):
        src, dst = pairs[k]
        a[k, :2] = _to_action(env, x[src, :2])
        a[k, 2:] = _to_action(env, x[dst, :2])
    return a


def flat_pose(rest_xy: np.ndarray, xy: np.ndarray, centre) -> np.ndarray:
    """The flat cloth turned as ``xy`` (n, 2) lies, centred at ``centre``: the rest grid
    under the orthogonal Q (a rotation, or a reflection for a cloth lying upside down)
    minimising sum |Q X - x|^2 over the centred points (orthogonal Procrustes: Q = U V^T
    from the SVD U S V^T of the cross-covariance sum x X^T; Schoenemann 1966)."""
    X = rest_xy - rest_xy.mean(axis=0)
    Y = xy - xy.mean(axis=0)
    U, _, Vt = np.linalg.svd(Y.T @ X)
    return X @ (U @ Vt).T + np.asarray(centre, dtype=float)


#: the flatten expert rolls a flap out when the farthest vertex the pickers can reach
#: is less than this share of the farthest vertex's distance from its flat position
HIDDEN_SHARE = 0.5
#: ... and weighs a candidate's distance across the pull's line by this against its
#: distance along it
ACROSS_WEIGHT = 2.0


def flatten_expert(env) -> np.ndarray:
    """Pick the vertex farthest from its flat position (:func:`flat_pose`, centred where
    the crumpled cloth started: the workspace's centre) and place it there. The picker
    grasps the top-most vertex under its pick point, so a vertex is picked through the
    one on top of it: the pick is the point whose grasped vertex is the farthest from its
    flat position, and the place puts that vertex there.

    A flap folded under the top layer cannot be picked. When the farthest vertex h the
    pickers can reach is less than :data:`HIDDEN_SHARE` of h's displacement d = flat - x
    (h lies under the top layer), the expert rolls the fold out instead: a layer lying
    on a flap, dragged away from the crease, takes the crease along at half its own
    speed (the flap, held by the ground's friction under both layers' weight, peels
    into the top layer), so that moving the top layer by 2 s unfolds a flap of depth s.
    h, mirrored across the crease, is 2 s from its flat position: the pull is by -d,
    from the top-layer vertex farthest from h along -d (less :data:`ACROSS_WEIGHT` times
    its distance across that line, so that the pull runs through the flap)."""
    from ..batch.episode import top_vertex
    x = env.sim.positions
    flat = flat_pose(env.rest[:, :2], x[:, :2], env.centre0)
    far = np.linalg.norm(x[:, :2] - flat, axis=1)
    a = np.zeros((env.num_pickers, 4), np.float32)
    grasped = np.array([top_vertex(x, x[v, :2], env.picker_radius) for v in range(len(x))])
    h = int(np.argmax(far))
    if env.num_pickers == 1 and far[grasped].max() < HIDDEN_SHARE * far[h]:
        d = flat[h] - x[h, :2]
        e = -d / np.linalg.norm(d)
        top = np.unique(grasped)
        r = x[top, :2] - x[h, :2]
        p = top[np.argmax(r @ e - ACROSS_WEIGHT * np.abs(r[:, 0] * e[1] - r[:, 1] * e[0]))]
        a[0, :2] = _to_action(env, x[p, :2])
        a[0, 2:] = _to_action(env, x[p, :2] - d)
        return a
    taken = []
    for v in np.argsort(-far[grasped], kind='stable'):
        g = grasped[v]
        # two pickers on one patch would stretch it between them: a quarter cloth apart
        if any(np.linalg.norm(x[g, :2] - x[t, :2]) < 0.25 * env.cloth_size or
               np.linalg.norm(flat[g] - flat[t]) < 0.25 * env.cloth_size for t in taken):
            continue
        taken.append(g)
        k = len(taken) - 1
        a[k, :2] = _to_action(env, x[v, :2])
        a[k, 2:] = _to_action(env, flat[g] + (x[v, :2] - x[g, :2]))
        if len(taken) == env.num_pickers:
            break
    return a


def drop_expert(env) -> np.ndarray:
    """Carry the two held corners (the edge j = 0) over the target's far corners (the
    edge j = r), so that the hanging cloth's lowest edge is above where it must lie,
    then down to their own targets on the ground: the cloth lies down behind them."""
    r = env.resolution
    a = np.zeros((2, 4), np.float32)
    for k, (v, far) in enumerate(((0, r * (r + 1)), (r, r * (r + 1) + r))):
        a[k, :2] = _to_action(env, env.target[far, :2])
        a[k, 2:] = _to_action(env, env.target[v, :2])
    return a


def random_agent(env) -> np.ndarray:
    """Uniform in the action space, from the environment's own generator."""
    return env.np_random.uniform(-1.0, 1.0, env.action_space.shape).astype(np.float32)


EXPERTS = {'fold': fold_expert, 'flatten': flatten_expert, 'drop': drop_expert}
#: the task's id and the info key of its metric
METRICS = {'fold': ('cosserat_ros/ClothFold-v0', 'fold_distance'),
           'flatten': ('cosserat_ros/ClothFlatten-v0', 'normalized_coverage'),
           'drop': ('cosserat_ros/ClothDrop-v0', 'mean_distance')}


def evaluate(task: str, agent, seeds, actions: int, **options):
    """Per seed: (metric after the episode, success, steps) of ``agent`` on ``task``,
    at most ``actions`` actions (stopping at success or truncation)."""
    import gymnasium as gym
    env_id, key = METRICS[task]
    env = gym.make(env_id, **options)
    out = []
    try:
        for seed in seeds:
            _, info = env.reset(seed=int(seed))
            steps = 0
            for steps in range(1, actions + 1):
                _, _, term, trunc, info = env.step(agent(env.unwrapped))
                if term or trunc:
                    break
            out.append((float(info[key]), bool(info['success']), steps))
    finally:
        env.close()
    return out


def main(argv=None) -> int:
    p = argparse.ArgumentParser(prog='python -m cosserat_ros.envs.experts',
                                description='The scripted expert and a random agent of '
                                            'each cloth task over seeds: the metric.')
    p.add_argument('--task', choices=['all', *EXPERTS], default='all')
    p.add_argument('--seeds', type=int, default=20)
    p.add_argument('--actions', type=int, default=None,
                   help='actions per episode (default: 1 for fold and drop, 10 for flatten)')
    args = p.parse_args(argv)
    if args.seeds < 1:
        print('experts: --seeds must be >= 1', file=sys.stderr)
        return 2
    tasks = list(EXPERTS) if args.task == 'all' else [args.task]
    print(f'{"task":8} {"agent":7} {"metric":20} {"mean":>8} {"min":>8} {"max":>8} '
          f'{"success":>8} {"s/episode":>10}')
    for task in tasks:
        n = args.actions or (10 if task == 'flatten' else 1)
        for name, agent in (('expert', EXPERTS[task]), ('random', random_agent)):
            t0 = time.perf_counter()
            res = evaluate(task, agent, range(args.seeds), n)
            wall = (time.perf_counter() - t0) / args.seeds
            m = np.array([r[0] for r in res])
            ok = sum(r[1] for r in res)
            print(f'{task:8} {name:7} {METRICS[task][1]:20} {m.mean():8.4f} {m.min():8.4f} '
                  f'{m.max():8.4f} {ok:>4}/{len(res):<3} {wall:10.2f}', flush=True)
    return 0


if __name__ == '__main__':
    sys.exit(main())
