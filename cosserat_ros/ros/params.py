"""The node's parameters: declarations, defaults, and validation as pure functions.

:data:`PARAMETERS` is the one source of truth for every parameter's name, default, range
and description (the manual's table, doc/node.md, is generated from it). The validators
here take values and return values or raise :class:`ConfigError` with a one-line reason;
nothing in this module touches a node or a simulator, so they are tested without spinning
anything.
"""
from __future__ import annotations

import math
from typing import Dict, List, Tuple

import numpy as np
from rcl_interfaces.msg import FloatingPointRange, IntegerRange, ParameterDescriptor

from ..core.fabrics import PRESETS
from ..core.mesh import GRID_PATTERNS
from ..core.solvers.explicit import DIVERGENCE_METHODS

__all__ = ['PARAMETERS', 'ConfigError', 'COLORINGS', 'PIN_SETS', 'MATERIAL_KEYS', 'AIR_KEYS',
           'pin_set', 'wind',
           'pinned_indices', 'vec3', 'check_choice', 'check_dt', 'RUNTIME_FLOATS',
           'OBSTACLE_KEYS', 'obstacle_geometry', 'HANDLE_KEYS', 'MIN_DT', 'OBSERVER_RUNTIME',
           'unknown_parameters', 'params_files', 'node_sections']

COLORINGS = ('energy', 'stretch', 'speed', 'none')
PIN_SETS = ('none', 'corners', 'top_corners', 'top_edge', 'bottom_edge', 'left_edge',
            'right_edge', 'boundary')
MATERIAL_KEYS = ('zeta', 'xi', 'phi', 'density', 'damping')
#: the coefficients of the air, air.<key> (core.air.Air's fields)
AIR_KEYS = ('density', 'drag', 'lift')
#: run-time parameters that must be non-negative floats
RUNTIME_FLOATS = ('force_timeout', 'max_force', 'max_acceleration', 'status_period',
                  'max_wind', 'contact.self_friction')
#: the run-time parameters an ``observe_only`` node still lets change (they touch only how
#: it draws and logs, not the physics or what it accepts)
OBSERVER_RUNTIME = ('coloring', 'wireframe', 'status_period')
#: [s] the smallest time step: below it sim time would crawl at any real-time factor
MIN_DT = 1e-6


class ConfigError(ValueError):
    """A parameter value the node cannot start with; the message is the reason."""


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
    'material.preset': ('', _desc('A measured fabric: ' + ', '.join(PRESETS) + ' (sources: '
                                  'core/fabrics.py); sets zeta, xi, phi and density, and '
                                  'any material.* given too overrides it; empty: none',
                                  True)),
    'material.zeta': (50.0, _desc('Stretching coefficient zeta [N/m] (E h = 16 zeta/3)',
                                  fp=_fp(0.0, 1e9))),
    'material.xi': (2e-5, _desc('Bending coefficient xi [N m] (D = 6 xi)', fp=_fp(0.0, 1e6))),
    'material.phi': (1e-6, _desc('Stretch-bend coupling phi [N]; phi^2 < 4 zeta xi',
                                 fp=_fp(0.0, 1e6))),
    'material.density': (0.2, _desc('Mass per unit area mu [kg/m^2]', fp=_fp(0.0, 1e6))),
    'material.damping': (0.1, _desc('Damping rho [kg/(m^2 s)] (Eq. 1)', fp=_fp(0.0, 1e6))),
    'dt': (2e-4, _desc('Time step [s], at least 1e-6; must not exceed the critical step '
                       'of the mesh and material', fp=_fp(0.0, 1.0))),
    'publish_rate': (30.0, _desc('Ticks per second: mesh, energy and /clock are published '
                                 'every tick', True, fp=_fp(0.1, 1000.0))),
    'gravity': ([0.0, 0.0, -9.81], _desc('Gravitational acceleration [m/s^2], 3 values')),
    'pinned.indices': ([-1], _desc('Pinned vertex indices ([-1]: none)', True)),
    'pinned.sets': (['top_corners'], _desc('Named pinned sets: ' + ', '.join(PIN_SETS),
                                           True)),
    'divergence': ('variational', _desc('Internal force discretisation: '
                                        + ', '.join(DIVERGENCE_METHODS), True)),
    'solver': ('explicit', _desc('Time integrator: explicit (symplectic Euler, dt below the '
                                 'critical step) or implicit (backward Euler by Newton-CG, '
                                 'any dt up to 1 s, dissipative)', True)),
    'solver.iterations': (20, _desc('Most Newton iterations per implicit step (solver: '
                                    'implicit only); 1 = linearised backward Euler (one '
                                    'Newton step, tolerance not asked for)',
                                    ip=[IntegerRange(from_value=1, to_value=1000, step=1)])),
    'solver.tolerance': (1e-3, _desc('Implicit convergence: every vertex residual force '
                                     'relative to the larger of the step start residual '
                                     'and the vertex load (weight, applied force)',
                                     fp=_fp(1e-12, 0.5))),
    'real_time_factor': (1.0, _desc('Simulation seconds the node aims to advance per wall '
                                    'second (1: real time); it runs slower when the host '
                                    'cannot keep up. Clients that pace on /clock give the '
                                    'same result at any factor', fp=_fp(1e-3, 100.0))),
    'frame_id': ('world', _desc('Frame of the published mesh and accepted commands', True)),
    'publish_clock': (True, _desc('Publish simulation time on /clock', True)),
    'force_timeout': (1.0, _desc('Forces, force field and wind lapse after this many '
                                 'seconds of simulation time without a new message (0 = '
                                 'hold) [s]', fp=_fp(0.0, 1e6))),
    'max_force': (10.0, _desc('Largest force on one vertex [N]: per row, and summed over '
                              'the rows and topics that load the vertex', fp=_fp(0.0, 1e9))),
    'max_acceleration': (100.0, _desc('Largest accepted force field [m/s^2]',
                                      fp=_fp(0.0, 1e9))),
    'air.enabled': (False, _desc('Aerodynamic drag and lift on every triangle from its '
                                 'velocity relative to the wind (air.wind, ~/wind)')),
    'air.density': (1.225, _desc('Air density [kg/m^3] (sea level)', fp=_fp(0.0, 100.0))),
    'air.drag': (1.17, _desc('Drag coefficient C_D [-] (a flat plate: 1.17)',
                             fp=_fp(0.0, 100.0))),
    'air.lift': (0.0, _desc('Lift coefficient C_L [-]', fp=_fp(0.0, 100.0))),
    'air.wind': ([0.0, 0.0, 0.0], _desc('Steady wind [m/s], 3 values in frame_id; ~/wind '
                                        'overrides it until the message lapses')),
    'max_wind': (50.0, _desc('Largest accepted wind speed [m/s] (air.wind and ~/wind)',
                             fp=_fp(0.0, 1e4))),
    'coloring': ('energy', _desc('Mesh colouring: ' + ', '.join(COLORINGS))),
    'wireframe': (False, _desc('Publish a LINE_LIST wireframe too')),
    'status_period': (1.0, _desc('Seconds between one-line status logs (0 = off)',
                                 fp=_fp(0.0, 3600.0))),
    'contact.thickness': (0.002, _desc('Distance the cloth keeps from every obstacle [m]',
                                       fp=_fp(1e-5, 0.1))),
    'contact.self': (False, _desc('Self-collision: the cloth keeps contact.thickness from '
                                  'itself (vertex-triangle and edge-edge) and never passes '
                                  'through; costs a response after every step')),
    'contact.self_friction': (0.5, _desc('Coulomb friction coefficient between two layers '
                                         'of the cloth [-]', fp=_fp(0.0, 100.0))),
    'handles.names': ([''], _desc('Grasp handles, each with ~/handles/<name>/grasp, '
                                  '/target and /wrench; handles.<name>.radius [m] and '
                                  "handles.<name>.break_force [N] (0 = none); [''] for none",
                                  True)),
    'handles.max_speed': (2.0, _desc('Fastest accepted motion of a held handle [m/s]: a '
                                     'target further from where the handle is, its turn '
                                     'counted at the grasp radius, is refused',
                                     fp=_fp(1e-3, 100.0))),
    'publish.points': (False, _desc('Publish ~/points: sensor_msgs/PointCloud2, one point '
                                    'per vertex, float32 x y z vx vy vz, every tick', True)),
    'publish.shape': (False, _desc('Publish ~/shape: shape_msgs/Mesh of the cloth (for '
                                   'MoveIt collision objects), every tick', True)),
    'foxglove.port': (0, _desc('Port of the live view, a Foxglove WebSocket server in the '
                               'node (needs foxglove-sdk: the viz extra); 0 = off', True,
                               ip=[IntegerRange(from_value=0, to_value=65535, step=1)])),
    'foxglove.host': ('127.0.0.1', _desc('Address the live view listens on (0.0.0.0: '
                                         'every interface)', True)),
    'observe_only': (False, _desc('Serve the cloth read-only: no command topics, no '
                                  'reset/pause/grasp services, and no run-time change of '
                                  'any parameter but ' + ', '.join(OBSERVER_RUNTIME), True)),
    'obstacles.names': ([''], _desc('Obstacles declared in the parameters, each with '
                                    'obstacles.<name>.shape and its geometry (doc/contact.md); '
                                    "[''] for none", True)),
    'cameras.names': ([''], _desc('Virtual RGB-D cameras, each with '
                                  '~/cameras/<name>/{depth,color}/image_raw, camera_info, '
                                  'pose_out, pose (in) and with cameras.<name>.points '
                                  'points; cameras.<name>.width, height, fov, position, '
                                  "orientation, rate, near, far (doc/viewing.md); [''] for none",
                                  True)),
}

#: the parameters of each camera, cameras.<name>.<key>: key -> default (a camera 2 m
#: above the origin looking straight down, image x along the world's x;
#: :mod:`.cameras`)
CAMERA_KEYS = {
    'width': 640, 'height': 480, 'fov': 60.0, 'position': [0.0, 0.0, 2.0],
    'orientation': [1.0, 0.0, 0.0, 0.0], 'rate': 15.0, 'points': False,
    'near': 0.01, 'far': 10.0,
}

#: the parameters of each declared handle, handles.<name>.<key>: key -> default
HANDLE_KEYS = {'radius': 0.03, 'break_force': 0.0}

#: the parameters of each declared obstacle, obstacles.<name>.<key>: key -> default
OBSTACLE_KEYS = {
    'shape': '', 'point': [0.0, 0.0, 0.0], 'normal': [0.0, 0.0, 1.0],
    'center': [0.0, 0.0, 0.0], 'radius': 0.0, 'half_extents': [0.0, 0.0, 0.0],
    'half_length': 0.0, 'orientation': [0.0, 0.0, 0.0, 1.0], 'file': '',
    'friction': [0.5], 'spacing': 0.01,
}


def obstacle_geometry(name: str, values: dict):
    """The ``add_obstacle`` arguments of declared obstacle ``name`` from its parameter
    values (key -> value): (shape, friction, geometry), else ConfigError."""
    from ..core.obstacles import SHAPE_ARGS
    shape = values['shape']
    if shape not in SHAPE_ARGS:
        raise ConfigError(f'obstacles.{name}.shape must be one of {", ".join(SHAPE_ARGS)}, '
                          f'got {shape!r}')
    keys = [k for k in SHAPE_ARGS[shape] if k in values and k not in ('vertices', 'faces')]
    geometry = {k: values[k] for k in keys}
    if shape == 'mesh' and not geometry.get('file'):
        raise ConfigError(f'obstacles.{name}.file: a mesh obstacle needs a file')
    friction = list(values['friction'])
    if len(friction) not in (1, 2):
        raise ConfigError(f'obstacles.{name}.friction must be [mu] or [mu_static, '
                          f'mu_kinetic], got {friction}')
    return shape, friction[0] if len(friction) == 1 else tuple(friction), geometry


def check_choice(value, choices, name: str):
    """``value`` if it is one of ``choices``, else ConfigError."""
    if value not in choices:
        raise ConfigError(f'{name} must be one of {", ".join(choices)}, got {value!r}')
    return value


def vec3(value, name: str) -> np.ndarray:
    """Three finite numbers as a (3,) array, else ConfigError."""
    try:
        arr = np.asarray(list(value), dtype=np.float64)
    except (TypeError, ValueError):
        raise ConfigError(f'{name} must be 3 finite numbers, got {value!r}') from None
    if arr.shape != (3,) or not np.all(np.isfinite(arr)):
        raise ConfigError(f'{name} must be 3 finite numbers, got {list(value)!r}')
    return arr


def wind(value, max_wind: float, name: str = 'air.wind') -> np.ndarray:
    """A wind velocity [m/s] no faster than ``max_wind``, else ConfigError."""
    w = vec3(value, name)
    speed = float(np.linalg.norm(w))
    if speed > max_wind:
        raise ConfigError(f'{name}: {speed:.4g} m/s is above max_wind {max_wind:.4g} m/s')
    return w


def check_dt(dt: float, critical: float = math.inf) -> float:
    """``dt`` if it is at least :data:`MIN_DT` and within the critical step, else
    ConfigError."""
    if not (dt > 0 and math.isfinite(dt)):
        raise ConfigError(f'dt must be positive, got {dt!r}')
    if dt < MIN_DT:
        raise ConfigError(f'dt = {dt:.3g} s is below {MIN_DT:g} s: simulation time would '
                          'hardly move')
    if dt > critical:
        raise ConfigError(f'dt = {dt:.3g} s exceeds the critical step {critical:.3g} s '
                          'of this mesh and material (the membrane wave speed over the '
                          'shortest edge limits it): lower dt, zeta or the resolution')
    return dt


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


def pinned_indices(mesh, indices, sets) -> np.ndarray:
    """The pinned vertices of ``pinned.indices`` (``[-1]``: none) and ``pinned.sets``."""
    idx = [int(i) for i in indices if i != -1]
    n = mesh.n_vertices
    bad = [i for i in idx if not 0 <= i < n]
    if bad:
        raise ConfigError(f'pinned.indices must lie in [0, {n - 1}] (or be [-1] for '
                          f'none), got {bad}')
    for s in (s for s in sets if s):
        check_choice(s, PIN_SETS, 'pinned.sets entries')
        idx.extend(pin_set(mesh, s).tolist())
    return np.unique(np.array(idx, dtype=np.int64))



def unknown_parameters(given, known) -> List[str]:
    """The names in ``given`` (a params file's or the command line's) that ``known`` (the
    node's declarations, with ``use_sim_time`` and the other names rclpy declares) does
    not have, sorted."""
    return sorted(set(given) - set(known))


def params_files(argv) -> List[str]:
    """The ``--params-file`` paths of the ROS arguments in ``argv``."""
    out, ros = [], False
    args = list(argv or [])
    for i, a in enumerate(args):
        if a == '--ros-args':
            ros = True
        elif a == '--':
            ros = False
        elif ros and a == '--params-file' and i + 1 < len(args):
            out.append(args[i + 1])
    return out


def _sections(tree, prefix=''):
    """The node paths of a params file's tree: every key path whose value holds
    ``ros__parameters``."""
    if not isinstance(tree, dict):
        return []
    out = []
    for key, value in tree.items():
        path = (prefix + '/' + str(key).strip('/')).replace('//', '/')
        if isinstance(value, dict) and 'ros__parameters' in value:
            out.append(path)
        out += _sections(value, path)
    return out


def _matches(pattern: str, fqn: str) -> bool:
    """rcl's node-name wildcards: ``*`` is one token, ``**`` any number of them; a name
    without a leading slash is in the root namespace (as rcl reads it)."""
    import re
    if pattern.strip('/') == '**':
        return True
    tokens = [t for t in pattern.strip('/').split('/') if t]
    regex = '/'.join('.*' if t == '**' else '[^/]*' if t == '*' else re.escape(t)
                     for t in tokens)
    return re.fullmatch('/' + regex.replace('.*/', '(.*/)?'), fqn) is not None


def node_sections(path: str, fqn: str) -> Tuple[List[str], List[str]]:
    """(the sections of params file ``path`` that apply to node ``fqn``, all its
    sections); ConfigError if it cannot be read."""
    import yaml
    try:
        with open(path) as fh:
            tree = yaml.safe_load(fh)
    except (OSError, yaml.YAMLError) as exc:
        raise ConfigError(f'{path}: {str(exc).splitlines()[0]}') from None
    every = _sections(tree)
    return [s for s in every if _matches(s, fqn)], every
