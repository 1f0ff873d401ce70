"""The node against its declarations (cosserat_ros/ros/params.py, ros/interfaces.py):
every declared parameter's bad value is refused with its reason, at start-up for the
read-only ones and at run time for the others (the value kept, the cloth running);
every accepted run-time value has somewhere to go; and the node's graph is exactly the
declared topics and services."""
import math

import pytest
import rclpy
from rclpy.context import Context
from rclpy.parameter import Parameter

from cosserat_ros.ros.interfaces import INTERFACES
from cosserat_ros.ros.node import ClothNode, ConfigError
from cosserat_ros.ros.params import DECLARATIONS

from test_node import Harness, OVERRIDES

NAN = math.nan

#: declared parameter -> (bad value, what the reason says). Every declared parameter has
#: one (the first test fails for a new declaration without), and the run-time ones a
#: value their range or check refuses, not only a wrong type.
BAD = {
    'mesh.file': ('no/such/cloth.obj', 'no/such/cloth.obj'),
    'mesh.nx': (0, 'mesh.nx'),
    'mesh.ny': (3000, 'mesh.ny'),
    'mesh.width': (-1.0, 'mesh.width'),
    'mesh.height': (0.0, 'mesh.height'),
    'mesh.pattern': ('zigzag', 'mesh.pattern'),
    'mesh.seed': ('seven', 'mesh.seed'),
    'material.preset': ('velvet', 'material preset must be one of'),
    'material.zeta': (-5.0, 'material.zeta'),
    'material.xi': (NAN, 'material.xi'),
    'material.phi': (1.0, 'indefinite'),
    'material.density': (1e-160, 'wave speed'),
    'material.damping': (-1.0, 'material.damping'),
    'dt': (1e-9, 'at least'),
    'publish_rate': (0.0, 'publish_rate'),
    'gravity': ([0.0, 1.0], '3 finite numbers'),
    'pinned.indices': ([99999], 'pinned.indices'),
    'pinned.sets': (['middle'], 'pinned.sets'),
    'discretisation': ('magic', 'discretisation'),
    'divergence': ('magic', 'discretisation must be one of'),     # deprecated, carried
    'solver': ('runge_kutta', 'solver'),
    'solver.iterations': (0, 'solver.iterations'),
    'solver.tolerance': (2.0, 'solver.tolerance'),
    'real_time_factor': (0.0, 'real_time_factor'),
    'frame_id': (5, 'frame_id'),
    'publish_clock': ('yes', 'publish_clock'),
    'force_timeout': (-1.0, 'force_timeout'),
    'max_force': (-1.0, 'max_force'),
    'max_acceleration': (NAN, 'max_acceleration'),
    'air.enabled': ('yes', ''),
    'air.density': (-1.0, 'air.density'),
    'air.drag': (NAN, 'air.drag'),
    'air.lift': (1e3, 'air.lift'),
    'air.wind': ([0.0, 0.0, 80.0], 'max_wind'),
    'max_wind': (-1.0, 'max_wind'),
    'coloring': ('rainbow', 'coloring'),
    'wireframe': ('yes', ''),
    'status_period': (-1.0, 'status_period'),
    'contact.thickness': (1.0, 'contact.thickness'),
    'contact.self': (1, ''),
    'contact.self_friction': (-0.5, 'contact.self_friction'),
    'handles.names': (['left', 'left'], 'handles.names'),
    'handles.max_speed': (0.0, 'handles.max_speed'),
    'publish.points': ('yes', 'publish.points'),
    'publish.shape': (1, 'publish.shape'),
    'foxglove.port': (70000, 'foxglove.port'),
    'foxglove.host': (8765, 'foxglove.host'),
    'observe_only': ('no', 'observe_only'),
    'obstacles.names': (['floor'], 'obstacles.floor.shape'),
    'cameras.names': (['top', 'top'], 'cameras.names'),
}


def test_every_declared_parameter_has_a_bad_value_here():
    assert sorted(BAD) == sorted(DECLARATIONS)


def test_every_run_time_parameter_goes_somewhere_when_accepted():
    """A run-time declaration says where an accepted value goes (an attribute of the node,
    or a group applied together); a read-only one says nothing of the kind."""
    for name, d in DECLARATIONS.items():
        if d.runtime:
            assert d.apply is not None or d.group is not None, name
        else:
            assert d.apply is None and d.group is None and d.check is None, name


@pytest.mark.parametrize('name', [n for n, d in DECLARATIONS.items() if not d.runtime])
def test_a_bad_start_up_value_is_refused_with_its_reason(name):
    value, why = BAD[name]
    ctx = Context()
    rclpy.init(context=ctx)
    node = None
    try:
        with pytest.raises(ConfigError) as err:
            node = ClothNode(context=ctx, argv=[], parameter_overrides=[
                Parameter(k, value=v) for k, v in dict(OVERRIDES, **{name: value}).items()])
        assert why in str(err.value) and '\n' not in str(err.value), str(err.value)
    finally:
        if node is not None:
            node.destroy_node()
        rclpy.shutdown(context=ctx)


def test_a_bad_run_time_value_is_refused_with_its_reason_and_changes_nothing():
    h = Harness()
    try:
        assert h.spin_until(lambda: len(h.meshes) > 0, 30)
        for name, d in DECLARATIONS.items():
            if not d.runtime:
                continue
            value, why = BAD[name]
            before = h.node.get_parameter(name).value
            res = h.node.set_parameters([Parameter(name, value=value)])[0]
            assert not res.successful and res.reason and why in res.reason, (name, res.reason)
            assert h.node.get_parameter(name).value == before, name
        t = h.node.sim.time
        assert h.spin_until(lambda: h.node.sim.time > t, 10)       # still stepping
        assert h.node.diverged is None
    finally:
        h.close()


def test_each_accepted_run_time_value_reaches_where_its_declaration_says():
    """A good value of every run-time parameter with an attribute to go to is found
    there after the set (the explicit node: the implicit solver's controls are refused)."""
    good = {'dt': 1e-4, 'gravity': [0.0, 0.0, -1.0], 'real_time_factor': 0.5,
            'force_timeout': 2.0, 'max_force': 5.0, 'max_acceleration': 50.0,
            'air.wind': [0.5, 0.0, 0.0], 'max_wind': 20.0, 'coloring': 'speed',
            'wireframe': True, 'status_period': 2.0, 'contact.thickness': 0.003,
            'contact.self': True, 'contact.self_friction': 0.3, 'handles.max_speed': 1.0}
    h = Harness()
    try:
        for name, d in DECLARATIONS.items():
            if d.apply is None or d.implicit:
                continue
            res = h.node.set_parameters([Parameter(name, value=good[name])])[0]
            assert res.successful, (name, res.reason)
            target = h.node
            for part in d.apply.split('.'):
                target = getattr(target, part)
            got = list(target) if isinstance(good[name], list) else target
            assert got == good[name], (name, got)
    finally:
        h.close()


def _graph(node):
    """(publishers, subscriptions, services) of ``node`` as {name: 'pkg/Type'}."""
    def flat(pairs):
        return {n: t[0].replace('/msg/', '/').replace('/srv/', '/') for n, t in pairs}
    name, ns = node.get_name(), node.get_namespace()
    return (flat(node.get_publisher_names_and_types_by_node(name, ns)),
            flat(node.get_subscriber_names_and_types_by_node(name, ns)),
            flat(node.get_service_names_and_types_by_node(name, ns)))


def _declared(observe_only: bool, names: dict):
    """The declared interfaces a node with ``names`` (group -> the one name) has."""
    out = ({}, {}, {})
    kinds = ('publisher', 'subscription', 'service')
    for i in INTERFACES:
        if observe_only and 'commands' in i.when.split():
            continue
        group = next((g for g in names if i.name.startswith(f'~/{g}/')), None)
        if i.name.startswith('~/contact/'):
            group = 'obstacles'
        topic = i.name.replace('~', '/cloth_node').replace('<name>', names.get(group, ''))
        out[kinds.index(i.kind)][topic] = i.type
    return out


#: rclpy's own interfaces of every node (parameters, logging, type descriptions)
def _rclpy_own(name: str) -> bool:
    return (name in ('/rosout', '/parameter_events')
            or name.rsplit('/', 1)[-1] in ('describe_parameters', 'get_parameter_types',
                                           'get_parameters', 'list_parameters',
                                           'set_parameters', 'set_parameters_atomically',
                                           'get_type_description'))


@pytest.mark.parametrize('observe_only', [False, True])
def test_the_node_graph_is_the_declared_interfaces(observe_only):
    params = {'publish.points': True, 'publish.shape': True, 'publish_clock': True,
              'observe_only': observe_only, 'handles.names': ['left'],
              'obstacles.names': ['floor'], 'obstacles.floor.shape': 'plane',
              'obstacles.floor.point': [0.0, 0.0, -2.0], 'cameras.names': ['top'],
              'cameras.top.width': 32, 'cameras.top.height': 24, 'cameras.top.points': True}
    h = Harness(**params)
    try:
        want = _declared(observe_only, {'handles': 'left', 'cameras': 'top',
                                        'obstacles': 'floor'})
        got = None

        def same():
            nonlocal got
            got = tuple({k: v for k, v in part.items() if not _rclpy_own(k)}
                        for part in _graph(h.node))
            return got == want
        assert h.spin_until(same, 10), (got, want)
    finally:
        h.close()
