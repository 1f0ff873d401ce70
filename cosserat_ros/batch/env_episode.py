"""A batch episode that is one episode of a Gymnasium environment of :mod:`cosserat_ros.envs`
driven by an agent: the evaluation of a policy over thousands of seeds, on a cluster.

In a spec, ``env`` replaces the scene, its start and its policy::

    batch: 1
    seed: 7
    episodes: 1000
    env:
      id: cosserat_ros/ClothFold-v0     # one of cosserat_ros.envs.ENV_IDS
      options: {num_pickers: 2}         # gymnasium.make's keywords (the env's options)
      agent: expert                     # expert | random | 'module:function'

``agent``: ``expert`` (the task's scripted expert, :data:`cosserat_ros.envs.experts.EXPERTS`;
``pick_place`` actions), ``random`` (uniform actions from the environment's generator), or
``'module:function'``, a function ``f(env, observation) -> action`` importable on every
worker (``env`` the unwrapped environment, ``observation`` the last one).

Episode ``i`` resets the environment with the episode's seed (``reset(seed=episode.seed)``,
the seed :func:`.spec.plan` draws for it) and steps the agent's actions until the
environment ends it (terminated, or truncated at its ``horizon``). Its bag holds the
state after the reset and after every action (the mesh, the energies, the ground's and
the pickers' wrenches, stamped with the simulation time), and its metrics the
episode's return, its number of actions, whether it terminated or was truncated, the
final ``info``'s numbers (``success``, the task's metric: ``fold_distance``,
``normalized_coverage`` or ``mean_distance``) and the final energies. A divergence (the
environment's ``info['sim_failure']``, or a start that fails) fails the episode with that
reason; an agent that raises or returns an action the environment refuses fails it with
the error. Only what the machine may cause another time (``MemoryError``, an ``OSError``
other than a missing or forbidden file) propagates, for the engine to retry.
"""
from __future__ import annotations

import json
from pathlib import Path
from typing import Dict, Optional

import numpy as np

from .spec import SpecError, _one_line, resolve_script

__all__ = ['ENV_KEYS', 'load_env', 'make_env', 'resolve_agent', 'simulate_env']

#: the keys of a spec's ``env``, with their defaults (``id`` has none)
ENV_KEYS = {'id': None, 'options': {}, 'agent': 'expert'}
#: the spec keys an ``env`` spec does not take: the environment sets them
SCENE_KEYS = ('duration', 'base', 'scene', 'randomize', 'init', 'policy', 'record')
#: the normalised ``env`` specs this process has built and checked (canonical JSON): a
#: spec loaded again (:func:`.spec.plan` loads what it is given) is not built again
_CHECKED: set = set()


def _the_machine_s(exc: BaseException) -> bool:
    """Whether ``exc`` is what the machine may cause another time (a full disk, no memory),
    not what the episode's code or data does every time."""
    if isinstance(exc, MemoryError):
        return True
    return isinstance(exc, OSError) and not isinstance(
        exc, (FileNotFoundError, PermissionError, IsADirectoryError, NotADirectoryError))


def make_env(env: dict):
    """The environment of a normalised ``env`` (``gymnasium.make(id, **options)``);
    ValueError or TypeError with the reason for options it refuses."""
    import gymnasium as gym

    import cosserat_ros.envs  # noqa: F401 (registers the ids)
    return gym.make(env['id'], **env['options'])


def resolve_agent(env: dict, unwrapped):
    """``f(env, observation) -> action`` for ``env['agent']`` on the environment
    ``unwrapped``; ValueError with the reason."""
    from ..envs.experts import EXPERTS, METRICS, random_agent
    agent = env['agent']
    if agent == 'random':
        return lambda e, obs: random_agent(e)
    if agent == 'expert':
        task = next((t for t, (i, _) in METRICS.items() if i == env['id']), None)
        if task is None or task not in EXPERTS:
            raise ValueError(f'env.agent: {env["id"]} has no scripted expert')
        if unwrapped.action_mode != 'pick_place':
            raise ValueError(f"env.agent: the expert acts in action_mode 'pick_place', "
                             f"not {unwrapped.action_mode!r}")
        expert = EXPERTS[task]
        return lambda e, obs: expert(e)
    return resolve_script(agent, key='env.agent')


def load_env(raw: dict, v) -> dict:
    """The ``env`` of a spec ``raw``, checked and normalised (module docstring): an id
    that is registered, options the environment takes (it is built and reset once, here),
    an agent that exists; :class:`.spec.SpecError` with one line otherwise."""
    given = sorted(k for k in SCENE_KEYS if k in raw)
    if given:
        raise SpecError(f'{given[0]}: a spec with env takes its scene, start, duration '
                        f'and recording from the environment (env.options); drop '
                        f'{given[0]}')
    if not isinstance(v, dict):
        raise SpecError(f'env must be a mapping (id, options, agent), got {v!r}')
    bad = sorted(set(v) - set(ENV_KEYS))
    if bad:
        raise SpecError(f'env.{bad[0]}: unknown key; known: {", ".join(ENV_KEYS)}')
    try:
        from ..envs import ENV_IDS
    except ImportError as exc:
        raise SpecError(f'env: needs the envs extra (pip install -r '
                        f'requirements-envs.txt): {_one_line(exc)}') from None
    out = {k: v.get(k, d) for k, d in ENV_KEYS.items()}
    if out['id'] not in ENV_IDS:
        raise SpecError(f'env.id must be one of {", ".join(sorted(ENV_IDS))}, got '
                        f'{out["id"]!r}')
    options = out['options'] if out['options'] is not None else {}
    if not isinstance(options, dict) or not all(isinstance(k, str) for k in options):
        raise SpecError(f'env.options must be a mapping of the environment\'s options, '
                        f'got {options!r}')
    if 'render_mode' in options:
        raise SpecError('env.options.render_mode: an episode records its bag, it does '
                        'not render')
    try:
        options = json.loads(json.dumps(options))
    except (TypeError, ValueError):
        raise SpecError(f'env.options must be plain data (numbers, strings, lists, '
                        f'mappings), got {options!r}') from None
    out['options'] = options
    if not isinstance(out['agent'], str):
        raise SpecError(f"env.agent must be expert, random or 'module:function', got "
                        f"{out['agent']!r}")
    key = json.dumps(out, sort_keys=True)
    if key in _CHECKED:
        return out
    try:
        e = make_env(out)
    except (ValueError, TypeError) as exc:
        raise SpecError(f'env.options: {_one_line(exc)}') from None
    try:
        resolve_agent(out, e.unwrapped)
        e.reset(seed=0)
    except ValueError as exc:
        raise SpecError(_one_line(exc)) from None
    except Exception as exc:                 # noqa: BLE001 (a start the options break)
        raise SpecError(f'env.options: the environment\'s start failed: '
                        f'{type(exc).__name__}: {_one_line(exc)}') from None
    finally:
        e.close()
    _CHECKED.add(key)
    return out


def _number_items(info: dict) -> Dict[str, object]:
    """The JSON numbers and booleans of ``info``."""
    out: Dict[str, object] = {}
    for k, val in info.items():
        if isinstance(val, (bool, np.bool_)):
            out[k] = bool(val)
        elif isinstance(val, (int, float, np.integer, np.floating)):
            out[k] = float(val)
    return out


def simulate_env(episode, bag_dir: Path, recorder) -> tuple:
    """Run the env ``episode`` (module docstring), recording into ``bag_dir`` with
    ``recorder(bag_dir, sim, handle_names)`` (the batch's own recorder); returns
    (metrics, simulation time). Raises :class:`.episode.EpisodeFailed` for what any
    attempt would meet."""
    from .episode import EpisodeFailed
    env_spec = {k: episode.policy[k] for k in ENV_KEYS}
    env = None
    try:
        try:
            env = make_env(env_spec)
            agent = resolve_agent(env_spec, env.unwrapped)
            obs, info = env.reset(seed=int(episode.seed))
        except Exception as exc:             # noqa: BLE001 (the same every attempt)
            if _the_machine_s(exc):
                raise
            raise EpisodeFailed(f'the environment\'s start failed: {type(exc).__name__}: '
                                f'{_one_line(exc)}') from None
        u = env.unwrapped
        names = [f'p{i}' for i in range(u.num_pickers)]
        rec = recorder(bag_dir, u.sim, names)
        last: Optional[int] = None

        def record() -> None:
            nonlocal last
            stamp = int(round(u.sim.time * 1e9))
            if last is not None and stamp <= last:
                return
            last = stamp
            rec.obstacles(stamp)
            rec.state(stamp, {n: u._hid[i] for i, n in enumerate(names)})

        try:
            record()
            ret, actions, terminated, truncated = 0.0, 0, False, False
            while not (terminated or truncated):
                try:
                    action = agent(u, obs)
                    obs, reward, terminated, truncated, info = env.step(action)
                except Exception as exc:     # noqa: BLE001 (the user's code, or a refusal)
                    if _the_machine_s(exc):
                        raise
                    raise EpisodeFailed(f'agent {env_spec["agent"]} at action {actions}: '
                                        f'{type(exc).__name__}: {_one_line(exc)}') from None
                ret += float(reward)
                actions += 1
                record()
        finally:
            rec.bag.close()
        if 'sim_failure' in info:
            raise EpisodeFailed(f'the simulation diverged at action {actions}: '
                                f'{(str(info["sim_failure"]).splitlines() or [""])[0]}')
        metrics = {'return': ret, 'actions': actions, 'terminated': bool(terminated),
                   'truncated': bool(truncated), **_number_items(info),
                   'kinetic_energy': rec.energy.get('kinetic', 0.0),
                   'elastic_energy': rec.energy.get('elastic', 0.0)}
        return metrics, float(u.sim.time)
    finally:
        if env is not None:
            env.close()
