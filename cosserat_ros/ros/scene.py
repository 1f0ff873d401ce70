"""A scene from the node's parameters, without a node: check them and build the simulator.

The node (:mod:`.node`) and the batch engine (:mod:`cosserat_ros.batch`) both turn the
parameters of :data:`.params.PARAMETERS` into a cloth. This module holds the part that
needs no ROS graph, so that a batch worker builds exactly the scene a node would:

* :func:`check_parameters` checks a flat ``{name: value}`` dict as rclpy checks a params
  file against the node's declarations (known names, the declared type, the declared
  range) and fills in the defaults; the groups ``obstacles.<name>.<key>`` and
  ``handles.<name>.<key>`` are known once their name is in ``obstacles.names`` /
  ``handles.names``.
* :func:`build_mesh`, :func:`initial_material` and :func:`build_air` are the node's own
  start-up steps (the node calls them).
* :func:`build_simulator` builds the whole simulator of a checked dict, with the node's
  further checks (solver and discretisation, the critical step, the pinned sets, the
  obstacles' geometry); every refusal is a :class:`.params.ConfigError` with one line.
* :func:`params_file_tree` / :func:`read_params_file` write and read a params file
  (``cloth_node: ros__parameters: ...``) that ``cloth_node --params-file`` accepts.
"""
from __future__ import annotations

import math
import os
import warnings
from typing import Dict, Iterable, NamedTuple, Optional

import numpy as np

from ..core.air import Air
from ..core.material import Material
from ..core.mesh import GRID_PATTERNS, MeshError, grid_mesh, load_mesh
from ..core.simulator import ClothSimulator
from ..core.solvers.explicit import DISCRETISATIONS
from .params import (AIR_KEYS, CAMERA_KEYS, HANDLE_KEYS, MATERIAL_KEYS, OBSTACLE_KEYS, PARAMETERS,
                     ConfigError, carry_renamed, check_choice, check_dt, group_names,
                     obstacle_geometry, pinned_indices, vec3, wind)

__all__ = ['check_parameters', 'build_mesh', 'initial_material', 'build_air',
           'Settings', 'checked_settings', 'apply_settings', 'build_simulator', 'resolve_path',
           'flatten', 'params_file_tree',
           'read_params_file', 'NODE_NAME']

#: the node name a params file written here is for
NODE_NAME = 'cloth_node'


def resolve_path(path: str) -> str:
    """A relative path resolves against the working directory, then against the
    package's installed share directory (so configs can name ``config/meshes/...``)."""
    if os.path.isabs(path) or os.path.exists(path):
        return path
    try:
        from ament_index_python.packages import get_package_share_directory
        shared = os.path.join(get_package_share_directory('cosserat_ros'), path)
    except Exception:       # package not installed through an ament index
        return path
    return shared if os.path.exists(shared) else path


def flatten(tree, prefix: str = '') -> Dict[str, object]:
    """``{'mesh': {'nx': 24}}`` -> ``{'mesh.nx': 24}`` (a params file's nesting)."""
    out = {}
    for key, value in tree.items():
        name = f'{prefix}.{key}' if prefix else str(key)
        if isinstance(value, dict):
            out.update(flatten(value, name))
        else:
            out[name] = value
    return out


def params_file_tree(values: Dict[str, object], node: str = NODE_NAME) -> dict:
    """The YAML tree of a params file for ``node`` holding ``values`` (flat names)."""
    root: dict = {}
    for name, value in sorted(values.items()):
        d = root
        parts = name.split('.')
        for p in parts[:-1]:
            d = d.setdefault(p, {})
        d[parts[-1]] = value
    return {node: {'ros__parameters': root}}


def read_params_file(path: str, node: str = NODE_NAME) -> Dict[str, object]:
    """The flat parameters a params file gives ``node`` (sections ``/**``, ``node`` and
    ``/node`` merged in file order), else ConfigError."""
    import yaml
    from .params import node_sections
    sections, _ = node_sections(path, '/' + node)
    with open(path) as fh:
        tree = yaml.safe_load(fh)
    out: Dict[str, object] = {}
    for section in sections:
        d = tree
        for key in [k for k in section.split('/') if k]:
            d = d.get(key) if key in d else d.get('/' + key)
        out.update(flatten(d['ros__parameters'] or {}))
    return out


# ---------------------------------------------------------------- checking
def _kind(default) -> str:
    if isinstance(default, bool):
        return 'bool'
    if isinstance(default, int):
        return 'int'
    if isinstance(default, float):
        return 'float'
    if isinstance(default, str):
        return 'str'
    return {bool: 'bool[]', int: 'int[]', float: 'float[]', str: 'str[]'}[type(default[0])]


def _typed(name: str, value, kind: str):
    """``value`` as a parameter of ``kind``, else ConfigError. An int is taken for a
    float (and written back as a float), as a YAML author means it."""
    def scalar(v, k):
        if k == 'bool' and isinstance(v, bool):
            return v
        if k == 'int' and isinstance(v, (int, np.integer)) and not isinstance(v, bool):
            return int(v)
        if (k == 'float' and isinstance(v, (int, float, np.integer, np.floating))
                and not isinstance(v, bool)):
            return float(v)
        if k == 'str' and isinstance(v, str):
            return v
        raise TypeError
    try:
        if kind.endswith('[]'):
            if isinstance(value, (str, bytes)) or not hasattr(value, '__iter__'):
                raise TypeError
            out = [scalar(v, kind[:-2]) for v in value]
            if not out:
                raise TypeError
            return out
        return scalar(value, kind)
    except TypeError:
        what = f'a list of {kind[:-2]}' if kind.endswith('[]') else f'a {kind}'
        raise ConfigError(f'{name} must be {what}, got {value!r}') from None


def _in_range(name: str, value, desc) -> None:
    for r in list(desc.floating_point_range) + list(desc.integer_range):
        if not (r.from_value <= value <= r.to_value):
            raise ConfigError(f'{name} must lie in [{r.from_value:g}, {r.to_value:g}], '
                              f'got {value!r}')
    if isinstance(value, float) and not math.isfinite(value):
        raise ConfigError(f'{name} must be finite, got {value!r}')


def check_parameters(given: Dict[str, object]) -> Dict[str, object]:
    """Every parameter of the node: ``given`` (flat names, e.g. a params file's or a batch
    spec's) checked against the declarations and the defaults for the rest.
    ConfigError names the first unknown or bad one."""
    out = {name: default for name, (default, _) in PARAMETERS.items()}
    groups = {}
    for group, keys in (('obstacles', OBSTACLE_KEYS), ('handles', HANDLE_KEYS),
                        ('cameras', CAMERA_KEYS)):
        names = given.get(f'{group}.names', PARAMETERS[f'{group}.names'][0])
        names = group_names(group, _typed(f'{group}.names', names, 'str[]'))
        for n in names:
            for key, default in keys.items():
                groups[f'{group}.{n}.{key}'] = default
    out.update(groups)
    for name, value in given.items():
        if name in ('use_sim_time',):
            continue
        if name not in out:
            raise ConfigError(f'{name}: not a parameter of the node (see the manual\'s '
                              'doc/node.md; obstacles.<name>.*, handles.<name>.* and '
                              'cameras.<name>.* need the name in obstacles.names, '
                              'handles.names or cameras.names)')
        value = _typed(name, value, _kind(out[name]))
        if name in PARAMETERS:
            _in_range(name, value, PARAMETERS[name][1])
        elif isinstance(value, list):
            for v in value:
                if isinstance(v, float) and not math.isfinite(v):
                    raise ConfigError(f'{name} must be finite, got {value!r}')
        out[name] = value
    carry_renamed(out, lambda reason: warnings.warn(reason, FutureWarning, stacklevel=3))
    from .cameras import camera_specs
    camera_specs(out)                     # the cameras' sizes, fields of view and budget
    return out


# ---------------------------------------------------------------- building
def build_mesh(p: dict):
    """The cloth's rest mesh of ``mesh.*``, else ConfigError."""
    try:
        if p['mesh.file']:
            return load_mesh(resolve_path(p['mesh.file']))
        check_choice(p['mesh.pattern'], GRID_PATTERNS, 'mesh.pattern')
        return grid_mesh(p['mesh.nx'], p['mesh.ny'], p['mesh.width'], p['mesh.height'],
                         p['mesh.pattern'], p['mesh.seed'])
    except (MeshError, ValueError) as exc:
        if isinstance(exc, ConfigError):
            raise
        raise ConfigError(f'mesh: {exc}') from None


def initial_material(p: dict, given: Iterable[str]) -> Material:
    """The material.* parameters, on top of material.preset when one is named: the preset
    gives zeta, xi, phi and density, a material.* parameter in ``given`` (the names set
    explicitly) overrides it, and damping is always material.damping. ConfigError if
    bad."""
    name = p['material.preset']
    given = set(given)
    try:
        if not name:
            return Material(**{k: p['material.' + k] for k in MATERIAL_KEYS})
        kept = {k: p['material.' + k] for k in MATERIAL_KEYS
                if 'material.' + k in given or k == 'damping'}
        return Material.preset(name, **kept)
    except ValueError as exc:
        raise ConfigError(str(exc)) from None


def build_air(enabled: bool, coefficients: dict) -> Optional[Air]:
    """The simulator's air from the air.* parameters (None: off), else ConfigError."""
    try:
        air = Air(**coefficients)
    except ValueError as exc:
        raise ConfigError(str(exc)) from None
    return air if enabled else None


def check_solver(p: dict) -> None:
    """The solver and discretisation choices and their combination, else ConfigError."""
    check_choice(p['discretisation'], DISCRETISATIONS, 'discretisation')
    check_choice(p['solver'], ClothSimulator.SOLVERS, 'solver')
    if p['solver'] == 'implicit' and p['discretisation'] != 'variational':
        raise ConfigError("solver: implicit needs discretisation: variational (the seed's "
                          'covariant route has no energy to minimise)')


def add_declared_obstacles(sim: ClothSimulator, p: dict) -> None:
    """The obstacles of ``obstacles.names`` with their ``obstacles.<name>.*``."""
    for name in [n for n in p['obstacles.names'] if n]:
        values = {k: p[f'obstacles.{name}.{k}'] for k in OBSTACLE_KEYS}
        shape, friction, geometry = obstacle_geometry(name, values)
        if 'file' in geometry:
            geometry['file'] = resolve_path(geometry['file'])
        try:
            sim.add_obstacle(shape, friction=friction, name=name, **geometry)
        except ValueError as exc:
            raise ConfigError(f'obstacle {name}: {exc}') from None


class Settings(NamedTuple):
    """What the simulator gets beside its mesh and material, checked before it is built
    (a bad value fails before any kernel compiles)."""
    gravity: np.ndarray          # [m/s^2]
    air: Optional[Air]
    wind: np.ndarray             # the steady wind [m/s]
    pins: np.ndarray             # pinned vertex indices


def checked_settings(p: dict, mesh) -> Settings:
    """The gravity, air, steady wind and pinned vertices of ``p`` on ``mesh``, else
    ConfigError."""
    return Settings(gravity=vec3(p['gravity'], 'gravity'),
                    air=build_air(bool(p['air.enabled']),
                                  {k: p['air.' + k] for k in AIR_KEYS}),
                    wind=wind(p['air.wind'], p['max_wind']),
                    pins=pinned_indices(mesh, p['pinned.indices'], p['pinned.sets']))


def apply_settings(sim: ClothSimulator, settings: Settings, p: dict) -> None:
    """Give ``sim`` the checked ``settings`` and the contact parameters of ``p``
    (thickness, self-collision and its friction)."""
    sim.gravity = settings.gravity
    sim.air = settings.air
    sim.wind = settings.wind
    if len(settings.pins):
        sim.pin(settings.pins)
    sim.contact_thickness = p['contact.thickness']
    sim.self_friction = p['contact.self_friction']
    sim.self_collision = bool(p['contact.self'])


def build_simulator(p: dict, given: Iterable[str] = ()) -> ClothSimulator:
    """The simulator of checked parameters ``p`` (:func:`check_parameters`) as the node
    starts it: mesh, material (``given``: the names set explicitly, for a preset's
    overrides), solver, dt (at most the critical step for the explicit solver), gravity,
    air and steady wind, pins, contact and the declared obstacles. Handles are declared
    only (``handles.names``: the node's topics grasp them). ConfigError if any is bad."""
    mesh = build_mesh(p)
    material = initial_material(p, given)
    check_solver(p)
    settings = checked_settings(p, mesh)
    check_dt(p['dt'])
    sim = ClothSimulator(mesh, material, dt=p['dt'], discretisation=p['discretisation'],
                         check_dt=False, solver=p['solver'])
    if p['solver'] == 'implicit':
        sim.solver_iterations = p['solver.iterations']
        sim.solver_tolerance = p['solver.tolerance']
    else:
        check_dt(p['dt'], sim.critical_dt())
    apply_settings(sim, settings, p)
    add_declared_obstacles(sim, p)
    return sim
