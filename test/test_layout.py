"""The package's layering, read from its source (doc/architecture.md): the simulator core
imports nothing above it and no ROS module, ``fast/`` sits below the solvers, and the
imports a module runs when it loads form no cycle."""
import ast
import os

import pytest

import cosserat_ros

PACKAGE = os.path.dirname(os.path.abspath(cosserat_ros.__file__))
#: the layers above the core (a core module importing one of them is an upward import)
ABOVE_CORE = ('cosserat_ros.ros', 'cosserat_ros.tools', 'cosserat_ros.batch',
              'cosserat_ros.envs', 'cosserat_ros.entry')
ROS = ('rclpy', 'rcl_interfaces', 'builtin_interfaces', 'rosgraph_msgs', 'std_msgs',
       'std_srvs', 'geometry_msgs', 'sensor_msgs', 'shape_msgs', 'visualization_msgs',
       'diagnostic_msgs', 'ament_index_python')


def _modules():
    """{dotted name: path} of every module of the package."""
    out = {}
    for dirpath, _, files in os.walk(PACKAGE):
        for f in files:
            if f.endswith('.py'):
                path = os.path.join(dirpath, f)
                rel = os.path.relpath(path, os.path.dirname(PACKAGE))[:-3].replace(os.sep, '.')
                out[rel[:-len('.__init__')] if rel.endswith('.__init__') else rel] = path
    return out


MODULES = _modules()


def _imports(name: str, top_level_only: bool):
    """(the package's modules, the other top-level packages) that module ``name`` imports;
    ``top_level_only``: only the imports that run when it loads (not those inside a function
    or class body, which run when called)."""
    path = MODULES[name]
    package = name if path.endswith('__init__.py') else name.rsplit('.', 1)[0]
    tree = ast.parse(open(path).read())
    nodes = []

    def collect(body):
        for n in body:
            if isinstance(n, (ast.Import, ast.ImportFrom)):
                nodes.append(n)
            elif isinstance(n, (ast.If, ast.Try)):            # guarded imports still load
                for part in ('body', 'orelse', 'finalbody'):
                    collect(getattr(n, part, []))
                for h in getattr(n, 'handlers', []):
                    collect(h.body)
    if top_level_only:
        collect(tree.body)
    else:
        nodes = [n for n in ast.walk(tree) if isinstance(n, (ast.Import, ast.ImportFrom))]
    ours, others = set(), set()
    for n in nodes:
        if isinstance(n, ast.Import):
            targets = [a.name for a in n.names]
        else:
            if n.level:
                parts = package.split('.')
                base = '.'.join(parts[:len(parts) - n.level + 1])
                base = base + '.' + n.module if n.module else base
            else:
                base = n.module
            targets = [f'{base}.{a.name}' if f'{base}.{a.name}' in MODULES else base
                       for a in n.names]
        for t in targets:
            if t.split('.')[0] != 'cosserat_ros':
                others.add(t.split('.')[0])
                continue
            while t not in MODULES and '.' in t:
                t = t.rsplit('.', 1)[0]
            if t != name:
                ours.add(t)
    return ours, others


def test_the_walk_sees_the_imports():
    ours, others = _imports('cosserat_ros.ros.node', top_level_only=True)
    assert 'cosserat_ros.core.simulator' in ours and 'rclpy' in others
    assert len(MODULES) > 80


@pytest.mark.parametrize('name', sorted(m for m in MODULES if m.startswith('cosserat_ros.core')))
def test_the_core_imports_nothing_above_it_and_no_ros(name):
    ours, others = _imports(name, top_level_only=False)
    assert not [m for m in ours if m.startswith(ABOVE_CORE)], ours
    assert not others & set(ROS), others & set(ROS)


@pytest.mark.parametrize('name', sorted(m for m in MODULES if m.startswith('cosserat_ros.fast')))
def test_fast_sits_below_the_solvers(name):
    ours, _ = _imports(name, top_level_only=False)
    assert not [m for m in ours if m.startswith(('cosserat_ros.core.solvers',) + ABOVE_CORE)]


def test_the_imports_at_load_form_no_cycle():
    """A depth-first walk of the load-time import graph finds no back edge."""
    graph = {m: _imports(m, top_level_only=True)[0] for m in MODULES}
    state = {}                                   # 1: on the walk's path, 2: done

    def visit(m, path):
        state[m] = 1
        for d in sorted(graph[m]):
            if state.get(d) == 1:
                cycle = path[path.index(d):] + [d]
                raise AssertionError('import cycle: ' + ' -> '.join(cycle))
            if d not in state:
                visit(d, path + [d])
        state[m] = 2
    for m in sorted(graph):
        if m not in state:
            visit(m, [m])


#: the longest a module may grow before it is split by what its parts do
MOST_LINES = 800


def test_no_module_is_over_eight_hundred_lines():
    long = {m: n for m, n in ((m, sum(1 for _ in open(p))) for m, p in MODULES.items())
            if n > MOST_LINES}
    assert not long, f'split these by what their parts do: {long}'
