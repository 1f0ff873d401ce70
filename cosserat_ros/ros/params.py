"""The node's parameters: declarations, defaults, and validation as pure functions.

:data:`DECLARATIONS` is the one source of truth for every parameter's name, type,
default, unit, range, whether it can change at run time, its check and where an accepted
value goes (:class:`Param`); the node declares, validates and applies its parameters by
looping over it, and the manual's table (doc/node.md) is generated from it. The validators
here take values and return values or raise :class:`ConfigError` with a one-line reason;
nothing in this module touches a node or a simulator, so they are tested without spinning
anything.
"""
from __future__ import annotations

from dataclasses import dataclass, replace
import math
from typing import Callable, Dict, List, Optional, Tuple

import numpy as np
from rcl_interfaces.msg import FloatingPointRange, IntegerRange, ParameterDescriptor

from ..core.fabrics import PRESETS
from ..core.mesh import GRID_PATTERNS
from ..core.solvers.explicit import DISCRETISATIONS

__all__ = ['PARAMETERS', 'DECLARATIONS', 'Param', 'check_value', 'ConfigError', 'COLORINGS',
           'PIN_SETS', 'MATERIAL_KEYS', 'AIR_KEYS', 'pin_set', 'wind', 'pinned_indices',
           'vec3', 'check_choice', 'check_dt',
           'OBSTACLE_KEYS', 'obstacle_geometry', 'HANDLE_KEYS', 'MIN_DT', 'OBSERVER_RUNTIME',
           'unknown_parameters', 'params_files', 'node_sections', 'group_names', 'check_names',
           'term_declarations', 'RENAMED', 'carry_renamed']

COLORINGS = ('energy', 'stretch', 'speed', 'none')
PIN_SETS = ('none', 'corners', 'top_corners', 'top_edge', 'bottom_edge', 'left_edge',
            'right_edge', 'boundary')
MATERIAL_KEYS = ('zeta', 'xi', 'phi', 'density', 'damping')
#: the coefficients of the air, air.<key> (core.air.Air's fields)
AIR_KEYS = ('density', 'drag', 'lift')
#: [s] the smallest time step: below it sim time would crawl at any real-time factor
MIN_DT = 1e-6


class ConfigError(ValueError):
    """A parameter value the node cannot start with; the message is the reason."""


@dataclass(frozen=True)
class Param:
    """One parameter's declaration: everything the node, its manual and its checks know
    about it.

    ``default`` fixes the type (a float parameter takes floats only, as rclpy declares
    it); ``low``/``high`` its range (rclpy's descriptor range, also checked by
    :func:`check_value`); ``runtime`` whether it can change while the node runs (else
    read-only); ``check(name, value)`` any further check of a run-time value (raises
    :class:`ConfigError` with the reason); ``apply`` where an accepted run-time value goes,
    an attribute path on the node (``'sim.dt'``: ``node.sim.dt = value``); ``group``
    values that are applied together after the others (``'material'``: a new
    :class:`Material`, ``'air'``: a new :class:`Air`, ``'limits'``: what stands above a
    lowered limit is dropped); ``implicit`` a control of the implicit solver only;
    ``observer`` one an ``observe_only`` node still lets change."""

    default: object
    text: str
    unit: str = ''
    runtime: bool = False
    low: Optional[float] = None
    high: Optional[float] = None
    check: Optional[Callable[[str, object], None]] = None
    apply: Optional[str] = None
    group: Optional[str] = None
    implicit: bool = False
    observer: bool = False

    @property
    def description(self) -> str:
        return f'{self.text} [{self.unit}]' if self.unit else self.text

    @property
    def descriptor(self) -> ParameterDescriptor:
        """The rclpy descriptor: description, read-only and range."""
        d = ParameterDescriptor(description=self.description, read_only=not self.runtime)
        if self.low is not None and isinstance(self.default, bool):
            raise TypeError('a bool has no range')
        if self.low is not None and isinstance(self.default, int):
            d.integer_range = [IntegerRange(from_value=int(self.low), to_value=int(self.high),
                                            step=1)]
        elif self.low is not None:
            d.floating_point_range = [FloatingPointRange(from_value=float(self.low),
                                                         to_value=float(self.high), step=0.0)]
        return d


def _vec3(name: str, value) -> None:
    vec3(value, name)


def _min_dt(name: str, value) -> None:
    if not value >= MIN_DT:
        raise ConfigError(f'dt must be a float of at least {MIN_DT:g} s')


def _coloring(name: str, value) -> None:
    if value not in COLORINGS:
        raise ConfigError(f'coloring must be one of {COLORINGS}')


def _material(text: str, default: float, unit: str, high: float) -> Param:
    return Param(default, text, unit, True, 0.0, high, group='material')


def _air(text: str, default: float, unit: str = '-') -> Param:
    return Param(default, text, unit, True, 0.0, 100.0, group='air')


#: name -> declaration, in the manual's order. The one source of truth for every
#: parameter's type, default, unit, range, run-time behaviour and documentation.
DECLARATIONS: Dict[str, Param] = {
    'mesh.file': Param('', 'Mesh file (any format trimesh reads); empty for a grid. '
                           'Relative paths resolve against the working directory.'),
    'mesh.nx': Param(40, 'Grid segments along X', low=1, high=2000),
    'mesh.ny': Param(40, 'Grid segments along Y', low=1, high=2000),
    'mesh.width': Param(1.0, 'Grid size along X', 'm', low=1e-6, high=1e4),
    'mesh.height': Param(1.0, 'Grid size along Y', 'm', low=1e-6, high=1e4),
    'mesh.pattern': Param('regular', 'Grid triangulation: ' + ', '.join(GRID_PATTERNS)),
    'mesh.seed': Param(0, 'Random seed of the irregular pattern'),
    'material.preset': Param('', 'A measured fabric: ' + ', '.join(PRESETS) + ' (sources: '
                                 'core/fabrics.py); sets zeta, xi, phi and density, and any '
                                 'material.* given too overrides it; empty: none'),
    'material.zeta': _material('Stretching coefficient zeta (E h = 16 zeta/3)', 50.0, 'N/m',
                               1e9),
    'material.xi': _material('Bending coefficient xi (D = 6 xi)', 2e-5, 'N m', 1e6),
    'material.phi': _material('Stretch-bend coupling phi; phi^2 < 4 zeta xi', 1e-6, 'N', 1e6),
    'material.density': _material('Mass per unit area mu', 0.2, 'kg/m^2', 1e6),
    'material.damping': _material('Damping rho (Eq. 1)', 0.1, 'kg/(m^2 s)', 1e6),
    'dt': Param(2e-4, 'Time step, at least 1e-6; must not exceed the critical step of the '
                      'mesh and material', 's', True, 0.0, 1.0, _min_dt, 'sim.dt'),
    'publish_rate': Param(30.0, 'Ticks per second: mesh, energy and /clock are published '
                                'every tick', '1/s', low=0.1, high=1000.0),
    'gravity': Param([0.0, 0.0, -9.81], 'Gravitational acceleration, 3 values', 'm/s^2', True,
                     check=_vec3, apply='sim.gravity'),
    'pinned.indices': Param([-1], 'Pinned vertex indices ([-1]: none)'),
    'pinned.sets': Param(['top_corners'], 'Named pinned sets: ' + ', '.join(PIN_SETS)),
    'discretisation': Param('variational', 'Internal force discretisation: '
                                           + ', '.join(DISCRETISATIONS)),
    'divergence': Param('', 'Deprecated: the name of discretisation before 0.2 (taken, '
                            'with a warning, until 0.3; empty: not set)'),
    'solver': Param('explicit', 'Time integrator: explicit (symplectic Euler, dt below the '
                                'critical step) or implicit (backward Euler by Newton-CG, any '
                                'dt up to 1 s, dissipative)'),
    'solver.iterations': Param(20, 'Most Newton iterations per implicit step (solver: '
                                   'implicit only); 1 = linearised backward Euler (one Newton '
                                   'step, tolerance not asked for)', runtime=True, low=1,
                               high=1000, apply='sim.solver_iterations', implicit=True),
    'solver.tolerance': Param(1e-3, 'Implicit convergence: every vertex residual force '
                                    'relative to the larger of the step start residual and '
                                    'the vertex load (weight, applied force)', '-', True, 1e-12,
                              0.5, apply='sim.solver_tolerance', implicit=True),
    'real_time_factor': Param(1.0, 'Simulation seconds the node aims to advance per wall '
                                   'second (1: real time); it runs slower when the host '
                                   'cannot keep up. Clients that pace on /clock give the '
                                   'same result at any factor', '-', True, 1e-3, 100.0,
                              apply='pacer.factor'),
    'frame_id': Param('world', 'Frame of the published mesh and accepted commands'),
    'publish_clock': Param(True, 'Publish simulation time on /clock'),
    'force_timeout': Param(1.0, 'Forces, force field and wind lapse after this many seconds '
                                'of simulation time without a new message (0 = hold)', 's',
                           True, 0.0, 1e6, apply='inputs.force_timeout'),
    'max_force': Param(10.0, 'Largest force on one vertex: per row, and summed over the rows '
                             'and topics that load the vertex', 'N', True, 0.0, 1e9,
                       apply='inputs.max_force', group='limits'),
    'max_acceleration': Param(100.0, 'Largest accepted force field', 'm/s^2', True, 0.0, 1e9,
                              apply='inputs.max_acceleration', group='limits'),
    'air.enabled': Param(False, 'Aerodynamic drag and lift on every triangle from its '
                                'velocity relative to the wind (air.wind, ~/wind)',
                         runtime=True, group='air'),
    'air.density': _air('Air density (sea level)', 1.225, 'kg/m^3'),
    'air.drag': _air('Drag coefficient C_D (a flat plate: 1.17)', 1.17),
    'air.lift': _air('Lift coefficient C_L', 0.0),
    'air.wind': Param([0.0, 0.0, 0.0], 'Steady wind, 3 values in frame_id; ~/wind overrides '
                                       'it until the message lapses', 'm/s', True,
                      check=_vec3, apply='inputs.steady_wind'),
    'max_wind': Param(50.0, 'Largest accepted wind speed (air.wind and ~/wind)', 'm/s', True,
                      0.0, 1e4, apply='inputs.max_wind', group='limits'),
    'coloring': Param('energy', 'Mesh colouring: ' + ', '.join(COLORINGS), runtime=True,
                      check=_coloring, apply='coloring', observer=True),
    'wireframe': Param(False, 'Publish a LINE_LIST wireframe too', runtime=True,
                       apply='wireframe', observer=True),
    'status_period': Param(1.0, 'Seconds between one-line status logs (0 = off)', 's', True,
                           0.0, 3600.0, apply='status_period', observer=True),
    'contact.thickness': Param(0.002, 'Distance the cloth keeps from every obstacle', 'm',
                               True, 1e-5, 0.1, apply='sim.contact_thickness'),
    'contact.self': Param(False, 'Self-collision: the cloth keeps contact.thickness from '
                                 'itself (vertex-triangle and edge-edge) and never passes '
                                 'through; costs a response after every step', runtime=True,
                          apply='sim.self_collision'),
    'contact.self_friction': Param(0.5, 'Coulomb friction coefficient between two layers of '
                                        'the cloth', '-', True, 0.0, 100.0,
                                   apply='sim.self_friction'),
    'handles.names': Param([''], 'Grasp handles, each with ~/handles/<name>/grasp, /target '
                                 'and /wrench; handles.<name>.radius [m] and '
                                 "handles.<name>.break_force [N] (0 = none); [''] for none"),
    'handles.max_speed': Param(2.0, 'Fastest accepted motion of a held handle: a target '
                                    'further from where the handle is, its turn counted at '
                                    'the grasp radius, is refused', 'm/s', True, 1e-3, 100.0,
                               apply='handles.max_speed'),
    'publish.points': Param(False, 'Publish ~/points: sensor_msgs/PointCloud2, one point per '
                                   'vertex, float32 x y z vx vy vz, every tick'),
    'publish.shape': Param(False, 'Publish ~/shape: shape_msgs/Mesh of the cloth (for MoveIt '
                                  'collision objects), every tick'),
    'foxglove.port': Param(0, 'Port of the live view, a Foxglove WebSocket server in the '
                              'node (needs foxglove-sdk: the viz extra); 0 = off',
                           low=0, high=65535),
    'foxglove.host': Param('127.0.0.1', 'Address the live view listens on (0.0.0.0: every '
                                        'interface)'),
    'observe_only': Param(False, 'Serve the cloth read-only: no command topics, no '
                                 'reset/pause/grasp services, and no run-time change of any '
                                 'parameter but '),             # + OBSERVER_RUNTIME, below
    'obstacles.names': Param([''], 'Obstacles declared in the parameters, each with '
                                   'obstacles.<name>.shape and its geometry (doc/contact.md); '
                                   "[''] for none"),
    'cameras.names': Param([''], 'Virtual RGB-D cameras, each with '
                                 '~/cameras/<name>/{depth,color}/image_raw, camera_info, '
                                 'pose_out, pose (in) and with cameras.<name>.points points; '
                                 'cameras.<name>.width, height, fov, position, orientation, '
                                 "rate, near, far (doc/viewing.md); [''] for none"),
}

#: the run-time parameters an ``observe_only`` node still lets change (they touch only how
#: it draws and logs, not the physics or what it accepts)
OBSERVER_RUNTIME = tuple(n for n, d in DECLARATIONS.items() if d.observer)
DECLARATIONS['observe_only'] = replace(DECLARATIONS['observe_only'], text=DECLARATIONS[
    'observe_only'].text + ', '.join(OBSERVER_RUNTIME))
#: name -> (default, rclpy descriptor), the view of :data:`DECLARATIONS` rclpy and the
#: scene builder (:func:`.scene.check_parameters`) read
PARAMETERS: Dict[str, Tuple[object, ParameterDescriptor]] = {
    name: (d.default, d.descriptor) for name, d in DECLARATIONS.items()}


def term_declarations() -> Dict[str, Param]:
    """``terms.<name>.<coefficient>`` for each coefficient of every registered term
    besides the built-ins (:mod:`cosserat_ros.core.terms.registry`): its default, unit,
    range and text, changeable at run time (``ClothSimulator.set_term``)."""
    from ..core.terms.registry import extra_terms
    out = {}
    for term in extra_terms():
        for c in term.coefficients:
            bounded = math.isfinite(c.low) and math.isfinite(c.high)

            def check(name, value, c=c, term=term.name):
                try:
                    c.check(value, term)
                except ValueError as exc:
                    raise ConfigError(f'{name}: {exc}') from None
            out[f'terms.{term.name}.{c.name}'] = Param(
                float(c.default), c.text or f'term {term.name}: {c.name}', c.unit, True,
                c.low if bounded else None, c.high if bounded else None, check,
                group='terms')
    return out


def check_value(name: str, value, d: Optional[Param] = None) -> None:
    """A run-time value of declared parameter ``name`` (declaration ``d``, default: from
    :data:`DECLARATIONS`) against its declaration: its type (a float parameter takes a
    finite float), its range and its own check; ConfigError with the reason."""
    d = DECLARATIONS[name] if d is None else d
    if isinstance(d.default, float):
        if not isinstance(value, float) or not math.isfinite(value):
            raise ConfigError(f'{name} must be a finite float, got {value!r}')
    if d.low is not None and not d.low <= value <= d.high:
        raise ConfigError(f'{name} must lie in [{d.low:g}, {d.high:g}], got {value!r}')
    if d.check is not None:
        d.check(name, value)


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


#: parameters renamed, kept working for one release: old name -> new name
RENAMED = {'divergence': 'discretisation'}


def carry_renamed(p: Dict[str, object], warn: Callable[[str], None]) -> None:
    """Each deprecated name of :data:`RENAMED` set in ``p`` (not empty): its value is
    carried to the new name, with ``warn(reason)``; ConfigError if the new name was set
    to something else too."""
    for old, new in RENAMED.items():
        if p.get(old, '') in ('', None):
            continue
        if p[new] != DECLARATIONS[new].default and p[new] != p[old]:
            raise ConfigError(f'{old} (deprecated) and {new} disagree ({p[old]!r}, '
                              f'{p[new]!r}): set {new} only')
        warn(f'{old} is deprecated: it is {new} now ({old} goes in 0.3)')
        p[new] = p[old]


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



def group_names(group: str, names) -> List[str]:
    """The non-empty names of ``<group>.names``, refused if one repeats."""
    names = [n for n in names if n]
    if len(set(names)) != len(names):
        raise ConfigError(f'{group}.names has duplicates: {names}')
    return names


def check_names(p: dict, given, declared, argv, fqn: str) -> None:
    """Refuse the names in ``given`` (the overrides of a node ``fqn``) that are not
    ``declared`` nor of a declared obstacle, handle or camera (a typo would otherwise
    start a default cloth), and params files in ``argv`` with no section for the node.
    ``p``: the node's values of :data:`DECLARATIONS`."""
    known = set(declared)
    for group, keys in (('obstacles', OBSTACLE_KEYS), ('handles', HANDLE_KEYS),
                        ('cameras', CAMERA_KEYS)):
        known |= {f'{group}.{n}.{k}' for n in p[f'{group}.names'] if n for k in keys}
    bad = unknown_parameters(given, known)
    if bad:
        raise ConfigError(f'unknown parameter{"s" if len(bad) > 1 else ""} '
                          f'{", ".join(bad)} for {fqn} (doc/node.md lists them all)')
    files = params_files(argv)
    if files and not any(node_sections(path, fqn)[0] for path in files):
        name = fqn.rsplit('/', 1)[-1]
        raise ConfigError(f'{", ".join(files)}: no section for node {fqn} (a file for this '
                          f'node starts with "{name}:" or "/**:", then "ros__parameters:")')


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
