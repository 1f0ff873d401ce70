"""A batch spec: what to simulate, checked whole before any work, and its plan.

A spec is YAML (or the same dict)::

    batch: 1                       # schema version
    seed: 7
    episodes: 200
    duration: 4.0                  # simulated seconds per episode
    base: config/table.yaml        # optional: a node params file (its parameters)
    scene: {mesh.nx: 24}           # node parameters over base (a set's names, e.g.
                                   # cameras.names, replace the base's set)
    randomize:                     # node parameters drawn per episode
      material.preset: {choice: [denim, jersey, polyester]}
      material.damping: {uniform: [0.05, 0.3]}
      obstacles.table.center: {uniform: [[-0.1, -0.1, -0.35], [0.1, 0.1, -0.25]]}
    init: {drop: {height: {uniform: [0.1, 0.4]}, tilt_deg: {uniform: [0, 40]}}}
    policy: {pick_place: {handles: 1, moves: 2}}
    record: {mesh_hz: 10, points_hz: 30}

Distributions: ``{uniform: [lo, hi]}``, ``{loguniform: [lo, hi]}`` (0 < lo), ``{choice:
[a, b, ...]}``; a vector is drawn element by element from vectors ``lo`` and ``hi``.
``init``: ``flat`` (the mesh as given, or ``{flat: {height: h}}``: lifted by h), ``{drop:
{height, tilt_deg, azimuth_deg}}`` (the cloth tilted by tilt_deg about a horizontal axis at
azimuth_deg, default drawn in [0, 360), its lowest point ``height`` above the highest
obstacle under it), or ``{crumple: {height, lifts}}`` (dropped, then picked at a random
point, lifted and let fall ``lifts`` times before the episode's time counts). ``policy``:
``none``, ``{pick_place: {handles: 1|2, moves, radius, lift, speed, settle, start}}`` (from
``start`` [s], one move after the other at ``speed`` [m/s], ``settle`` [s] between them:
:func:`.episode.pick_place`)
or ``{script:
'module:function'}``, a function ``f(sim, rng, episode)`` called with the simulator, the
episode's generator (``numpy.random.default_rng(episode.seed)``) and the episode; it steps
the simulator itself (``sim.step`` records at the spec's rates and stops at the episode's
end; whatever it leaves of the duration is stepped after it returns; see
:mod:`.episode`).

A spec with ``env: {id, options, agent}`` instead of the scene, its start, policy,
duration and recording runs episodes of a Gymnasium environment of
:mod:`cosserat_ros.envs` driven by an agent (:mod:`.env_episode`).

:func:`plan` resolves every draw up front: episode ``i``'s values come from
``numpy.random.default_rng(SeedSequence([seed, i]))`` alone, so the plan of a spec does not
depend on how many episodes it has, in which order they run or where.
"""
from __future__ import annotations

import copy
from dataclasses import dataclass, field
import hashlib
import importlib
import json
import math
import os
from typing import Dict, List, Optional

import numpy as np

__all__ = ['SpecError', 'Episode', 'load_spec', 'plan', 'spec_digest', 'SCHEMA',
           'MAX_EPISODES', 'check_episode']

#: the schema version this code reads
SCHEMA = 1
#: the most episodes one spec may ask for
MAX_EPISODES = 1_000_000
#: the longest episode [s of simulation]
MAX_DURATION = 3600.0
#: the highest recording rate [Hz]
MAX_RATE = 1000.0

TOP_KEYS = ('batch', 'seed', 'episodes', 'duration', 'base', 'scene', 'randomize', 'init',
            'policy', 'record', 'name', 'env')
RECORD_KEYS = {'mesh_hz': 10.0, 'points_hz': 0.0}
INIT_KINDS = {'flat': {'height': 0.0},
              'drop': {'height': 0.2, 'tilt_deg': 0.0, 'azimuth_deg': None},
              'crumple': {'height': 0.2, 'lifts': 1}}
PICK_PLACE = {'handles': 1, 'moves': 1, 'radius': 0.03, 'lift': 0.2, 'speed': 0.5,
              'settle': 0.5, 'start': 0.0}


class SpecError(ValueError):
    """A spec that cannot run; the message is one line naming the key and why."""


@dataclass
class Episode:
    """One planned episode: everything it needs, resolved (JSON-serialisable fields)."""
    index: int
    id: str
    seed: int
    duration: float
    params: Dict[str, object]          # the node parameters given (flat names)
    init: Dict[str, object]            # {'kind': ..., resolved values}
    policy: Dict[str, object]          # {'kind': ..., resolved values}
    record: Dict[str, float]
    spec_digest: str = ''
    extra: Dict[str, object] = field(default_factory=dict)

    def to_dict(self) -> dict:
        return {'index': self.index, 'id': self.id, 'seed': self.seed,
                'duration': self.duration, 'params': self.params, 'init': self.init,
                'policy': self.policy, 'record': self.record,
                'spec_digest': self.spec_digest}


# ---------------------------------------------------------------- distributions
def _is_dist(v) -> bool:
    return isinstance(v, dict) and len(v) == 1 and next(iter(v)) in (
        'uniform', 'loguniform', 'choice')


def _check_dist(key: str, v) -> None:
    kind, arg = next(iter(v.items()))
    if kind == 'choice':
        if not isinstance(arg, list) or not arg:
            raise SpecError(f'{key}: choice needs a non-empty list, got {arg!r}')
        return
    if not isinstance(arg, list) or len(arg) != 2:
        raise SpecError(f'{key}: {kind} needs [lo, hi], got {arg!r}')
    lo, hi = arg
    try:
        lo_a = np.asarray(lo, dtype=float)
        hi_a = np.asarray(hi, dtype=float)
    except (TypeError, ValueError):
        raise SpecError(f'{key}: {kind} bounds must be numbers or equal-length lists of '
                        f'numbers, got {arg!r}') from None
    if lo_a.shape != hi_a.shape or lo_a.ndim > 1:
        raise SpecError(f'{key}: {kind} bounds must have the same length, got {arg!r}')
    if not (np.all(np.isfinite(lo_a)) and np.all(np.isfinite(hi_a))):
        raise SpecError(f'{key}: {kind} bounds must be finite, got {arg!r}')
    if np.any(lo_a > hi_a):
        raise SpecError(f'{key}: {kind} needs lo <= hi, got {arg!r}')
    if kind == 'loguniform' and np.any(lo_a <= 0):
        raise SpecError(f'{key}: loguniform needs 0 < lo, got {arg!r}')


def _draw(v, rng: np.random.Generator):
    """A value of distribution ``v`` (or ``v`` itself when it is none); floats, lists of
    floats, or the chosen item."""
    if not _is_dist(v):
        return v
    kind, arg = next(iter(v.items()))
    if kind == 'choice':
        return copy.deepcopy(arg[int(rng.integers(len(arg)))])
    lo, hi = (np.asarray(a, dtype=float) for a in arg)
    if kind == 'uniform':
        x = lo + (hi - lo) * rng.random(lo.shape)
    else:
        x = np.exp(np.log(lo) + (np.log(hi) - np.log(lo)) * rng.random(lo.shape))
    return x.tolist() if x.ndim else float(x)


# ---------------------------------------------------------------- loading
def _one_line(exc: BaseException) -> str:
    return str(exc).strip().splitlines()[0] if str(exc).strip() else type(exc).__name__


def _number(key: str, v, lo: float, hi: float, integer: bool = False):
    ok = isinstance(v, (int, float)) and not isinstance(v, bool)
    if integer:
        ok = ok and float(v) == int(v)
    if not ok or not (math.isfinite(float(v)) and lo <= v <= hi):
        kind = 'an integer' if integer else 'a number'
        raise SpecError(f'{key} must be {kind} in [{lo:g}, {hi:g}], got {v!r}')
    return int(v) if integer else float(v)


def _read(path_or_dict):
    import yaml
    if isinstance(path_or_dict, dict):
        return copy.deepcopy(path_or_dict), os.getcwd()
    path = os.fspath(path_or_dict)
    try:
        with open(path) as fh:
            spec = yaml.safe_load(fh)
    except OSError as exc:
        raise SpecError(f'{path}: {exc.strerror or exc}') from None
    except yaml.YAMLError as exc:
        raise SpecError(f'{path}: not YAML: {_one_line(exc)}') from None
    if not isinstance(spec, dict):
        raise SpecError(f'{path}: a spec is a mapping of keys (batch, seed, episodes, ...)')
    return spec, os.path.dirname(os.path.abspath(path))


def _resolve_base(base: str, here: str) -> str:
    """``base`` as given if it exists, else beside the spec, else in the package's
    share directory (``config/...``)."""
    from ..ros.scene import resolve_path
    for cand in (base, os.path.join(here, base)):
        if os.path.exists(cand):
            return os.path.abspath(cand)
    found = resolve_path(base)
    if os.path.exists(found):
        return os.path.abspath(found)
    raise SpecError(f'base: no params file {base!r} (looked in the working directory, '
                    f'beside the spec and in the package\'s share directory)')


def _kind_and_args(key: str, v, kinds: Dict[str, dict]):
    if isinstance(v, str):
        v = {v: {}}
    if isinstance(v, dict) and 'kind' in v:          # the normalised form load_spec gives
        v = {v['kind']: {k: a for k, a in v.items() if k != 'kind'}}
    if not isinstance(v, dict) or len(v) != 1:
        raise SpecError(f'{key} must be one of {", ".join(kinds)} (a name, or {{name: '
                        f'{{...}}}}), got {v!r}')
    kind, args = next(iter(v.items()))
    if kind not in kinds:
        raise SpecError(f'{key}: unknown kind {kind!r}; one of {", ".join(kinds)}')
    args = {} if args is None else args
    if not isinstance(args, dict):
        raise SpecError(f'{key}.{kind} must be a mapping, got {args!r}')
    bad = sorted(set(args) - set(kinds[kind]))
    if bad:
        raise SpecError(f'{key}.{kind}: unknown key {bad[0]!r}; known: '
                        f'{", ".join(kinds[kind]) or "none"}')
    for k, a in args.items():
        if _is_dist(a):
            _check_dist(f'{key}.{kind}.{k}', a)
    return kind, args


def load_spec(path_or_dict) -> dict:
    """The spec of a YAML file (or a dict), checked and normalised: every key known, the
    ranges sound, the base params file read, the scene and every randomized parameter
    known to the node with a value of its type, presets and scripts that exist. A
    :class:`SpecError` with one line otherwise. The result is plain JSON data
    (:func:`spec_digest` identifies it), and loads again to itself."""
    raw, here = _read(path_or_dict)
    bad = sorted(set(raw) - set(TOP_KEYS))
    if bad:
        raise SpecError(f'{bad[0]}: unknown key; a spec has {", ".join(TOP_KEYS)}')
    if raw.get('batch') != SCHEMA:
        raise SpecError(f'batch: the schema version must be {SCHEMA}, got '
                        f'{raw.get("batch")!r}')
    for key in ('seed', 'episodes') if 'env' in raw else ('seed', 'episodes', 'duration'):
        if key not in raw:
            raise SpecError(f'{key}: missing')
    if 'env' in raw:                   # an environment's episodes: .env_episode
        from .env_episode import load_env
        return {'batch': SCHEMA, 'name': str(raw.get('name', '')),
                'seed': _number('seed', raw['seed'], 0, 2 ** 63 - 1, integer=True),
                'episodes': _number('episodes', raw['episodes'], 1, MAX_EPISODES,
                                    integer=True),
                'env': load_env(raw, raw['env'])}
    spec = {'batch': SCHEMA, 'name': str(raw.get('name', '')),
            'seed': _number('seed', raw['seed'], 0, 2 ** 63 - 1, integer=True),
            'episodes': _number('episodes', raw['episodes'], 1, MAX_EPISODES, integer=True),
            'duration': _number('duration', raw['duration'], 1e-6, MAX_DURATION)}
    from ..ros.params import ConfigError
    from ..ros.scene import read_params_file
    base = {}
    if raw.get('base'):
        if not isinstance(raw['base'], str):
            raise SpecError(f'base must be a path, got {raw["base"]!r}')
        path = _resolve_base(raw['base'], here)
        try:
            base = read_params_file(path)
        except (ConfigError, OSError, KeyError, TypeError, AttributeError) as exc:
            raise SpecError(f'base: {path}: {_one_line(exc)}') from None
    scene = raw.get('scene') or {}
    if not isinstance(scene, dict):
        raise SpecError(f'scene must be a mapping of node parameters, got {scene!r}')
    from ..ros.scene import flatten
    scene = flatten(scene)
    for k, v in scene.items():
        if _is_dist(v):
            raise SpecError(f'scene.{k}: a distribution belongs under randomize')
    spec['scene'] = merge_scene(base, scene)
    spec['randomize'] = check_randomize(raw.get('randomize') or {})
    kind, args = _kind_and_args('init', raw.get('init', 'flat'), INIT_KINDS)
    spec['init'] = {'kind': kind, **{k: args.get(k, d) for k, d in INIT_KINDS[kind].items()}}
    spec['policy'] = _load_policy(raw.get('policy', 'none'))
    rec = raw.get('record') or {}
    if not isinstance(rec, dict):
        raise SpecError(f'record must be a mapping (mesh_hz, points_hz), got {rec!r}')
    bad = sorted(set(rec) - set(RECORD_KEYS))
    if bad:
        raise SpecError(f'record.{bad[0]}: unknown key; known: {", ".join(RECORD_KEYS)}')
    spec['record'] = {k: _number(f'record.{k}', rec.get(k, d), 0.0, MAX_RATE)
                      for k, d in RECORD_KEYS.items()}
    if spec['record']['mesh_hz'] <= 0:
        raise SpecError('record.mesh_hz must be positive (the mesh is what every episode '
                        'is for)')
    _check_values(spec)
    return spec


def _load_policy(v) -> dict:
    kinds = {'none': {}, 'pick_place': PICK_PLACE, 'script': {}}
    if isinstance(v, dict) and v.get('kind') == 'script':  # the normalised form
        v = {'script': v.get('target')}
    if isinstance(v, dict) and set(v) == {'script'} and isinstance(v['script'], str):
        target = v['script']
        resolve_script(target)
        return {'kind': 'script', 'target': target}
    if v is None:
        v = 'none'
    kind, args = _kind_and_args('policy', v, kinds)
    if kind == 'script':
        raise SpecError("policy.script must be 'module:function'")
    out = {'kind': kind, **{k: args.get(k, d) for k, d in kinds[kind].items()}}
    if kind == 'pick_place':
        if out['handles'] not in (1, 2):
            raise SpecError(f'policy.pick_place.handles must be 1 or 2, got '
                            f'{out["handles"]!r}')
        _number('policy.pick_place.moves', out['moves'], 1, 100, integer=True)
        for k, lo, hi in (('radius', 1e-4, 10.0), ('lift', 0.0, 10.0),
                          ('speed', 1e-3, 100.0), ('settle', 0.0, 3600.0),
                          ('start', 0.0, MAX_DURATION)):
            if not _is_dist(out[k]):
                _number(f'policy.pick_place.{k}', out[k], lo, hi)
    return out


def resolve_script(target: str, key: str = 'policy.script'):
    """The function of ``'module:function'``, else SpecError naming ``key``."""
    mod, _, fn = str(target).partition(':')
    if not mod or not fn:
        raise SpecError(f"{key} must be 'module:function', got {target!r}")
    try:
        f = getattr(importlib.import_module(mod), fn)
    except ImportError as exc:
        raise SpecError(f'{key}: cannot import {mod!r}: {_one_line(exc)}') from None
    except AttributeError:
        raise SpecError(f'{key}: {mod!r} has no {fn!r}') from None
    if not callable(f):
        raise SpecError(f'{key}: {target!r} is not callable')
    return f


def _check_values(spec: dict) -> None:
    """The scene and every randomized parameter against the node's declarations: the
    scene alone, then each randomized name at each of its bounds or choices (so a bad
    preset or an out-of-range bound is refused before any episode)."""
    from ..ros.params import ConfigError
    from ..ros.scene import check_parameters, initial_material
    try:
        initial_material(check_parameters(spec['scene']), spec['scene'])
    except ConfigError as exc:
        raise SpecError(f'scene: {exc}') from None
    for key, dist in spec['randomize'].items():
        for value in next(iter(dist.values())):      # [lo, hi], or the choices
            given = {**spec['scene'], key: value}
            try:
                p = check_parameters(given)
                if key.startswith('material.'):
                    initial_material(p, given)
            except ConfigError as exc:
                raise SpecError(f'randomize.{key}: {exc}') from None


def check_randomize(randomize) -> dict:
    """``randomize`` ({node parameter: distribution}) with every distribution's form
    checked (its values against the node: :func:`_check_values`); SpecError if bad."""
    if not isinstance(randomize, dict):
        raise SpecError(f'randomize must be a mapping of node parameters, got '
                        f'{randomize!r}')
    for k, v in randomize.items():
        if not _is_dist(v):
            raise SpecError(f'randomize.{k}: must be {{uniform: [lo, hi]}}, '
                            f'{{loguniform: [lo, hi]}} or {{choice: [...]}}, got {v!r}')
        _check_dist(f'randomize.{k}', v)
    return dict(randomize)


def draw_randomized(randomize: dict, rng: np.random.Generator) -> dict:
    """One draw of every randomized parameter, in the order of their names (so a draw
    does not depend on the spec's key order)."""
    return {key: _draw(randomize[key], rng) for key in sorted(randomize)}


NAMED_SETS = ('obstacles', 'handles', 'cameras')


def merge_scene(base: dict, scene: dict) -> dict:
    """``scene`` over ``base``; where the scene lists a set's names (``obstacles.names``,
    ``handles.names``, ``cameras.names``) it replaces the base's set, so the base's
    parameters of a member it leaves out (``cameras.side.*``) are dropped with it."""
    out = dict(base)
    for group in NAMED_SETS:
        if f'{group}.names' in scene:
            keep = set(scene[f'{group}.names'] or ())
            for k in list(out):
                parts = k.split('.')
                if (parts[0] == group and len(parts) > 2 and parts[1] != 'names'
                        and parts[1] not in keep):
                    del out[k]
    out.update(scene)
    return out


def spec_digest(spec: dict) -> str:
    """sha256 of the normalised spec's canonical JSON: the identity of a run."""
    return hashlib.sha256(json.dumps(spec, sort_keys=True, separators=(',', ':'))
                          .encode()).hexdigest()


# ---------------------------------------------------------------- planning
def episode_rng(seed: int, index: int) -> np.random.Generator:
    """The generator of episode ``index`` of a spec with ``seed``."""
    return np.random.default_rng(np.random.SeedSequence([seed, index]))


def plan(spec) -> List[Episode]:
    """Every episode of ``spec`` (a dict from :func:`load_spec`, or what it takes) with
    its parameters resolved: pure, the same for the same spec."""
    spec = load_spec(spec)
    digest = spec_digest(spec)
    width = max(6, len(str(spec['episodes'] - 1)))
    out = []
    for i in range(spec['episodes']):
        rng = episode_rng(spec['seed'], i)
        seed = int(rng.integers(0, 2 ** 63 - 1))
        if 'env' in spec:              # the environment draws the rest from the seed
            out.append(Episode(index=i, id=f'{i:0{width}d}', seed=seed, duration=0.0,
                               params={}, init={'kind': 'env'},
                               policy={'kind': 'env', **spec['env']}, record={},
                               spec_digest=digest))
            continue
        params = {**spec['scene'], **draw_randomized(spec['randomize'], rng)}
        init = {k: _draw(v, rng) for k, v in spec['init'].items()}
        if init['kind'] == 'drop' and init.get('azimuth_deg') is None:
            init['azimuth_deg'] = float(360.0 * rng.random())
        if init['kind'] == 'crumple':
            init['picks'] = [rng.uniform(-1.0, 1.0, 2).tolist()
                             for _ in range(int(init['lifts']))]
        policy = {k: _draw(v, rng) for k, v in spec['policy'].items()}
        if policy['kind'] == 'pick_place':
            policy['picks'] = [[rng.uniform(-1.0, 1.0, 2).tolist()
                                for _ in range(policy['handles'])]
                               for _ in range(policy['moves'])]
            policy['places'] = [[rng.uniform(-1.0, 1.0, 2).tolist()
                                 for _ in range(policy['handles'])]
                                for _ in range(policy['moves'])]
        out.append(Episode(index=i, id=f'{i:0{width}d}', seed=seed,
                           duration=spec['duration'], params=params, init=init,
                           policy=policy, record=dict(spec['record']),
                           spec_digest=digest))
    return out


def check_episode(episode: Episode) -> Optional[str]:
    """The reason the node would refuse this episode's parameters, or None (cheap: no
    simulator is built)."""
    from ..ros.params import ConfigError
    from ..ros.scene import check_parameters, initial_material
    try:
        p = check_parameters(episode.params)
        initial_material(p, episode.params)
    except ConfigError as exc:
        return str(exc)
    return None
