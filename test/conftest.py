"""Test-session set-up: every run gets its own ROS domain and keeps discovery on localhost,
so parallel runs (and other ROS graphs on the machine) never see each other.

On a cold compile cache most of the suite's time is numba compiling the step's kernels,
one core at a time. The session therefore starts ``precompile.py`` in a second process
and runs first the modules that step no cloth (meshes, messages, terms, the integrator,
geometry), so that the other core compiles the steps meanwhile (a warm cache: it loads
them in a few seconds and ends), and the warm-up's tests last."""
import os
import subprocess
import sys

os.environ['ROS_DOMAIN_ID'] = str(1 + os.getpid() % 100)
os.environ['ROS_AUTOMATIC_DISCOVERY_RANGE'] = 'LOCALHOST'
os.environ.setdefault('RCUTILS_COLORIZED_OUTPUT', '0')

#: the modules that step no cloth, run first in this order; the rest keep pytest's order
FIRST = ('test_mesh.py', 'test_messages.py', 'test_terms.py', 'test_integrator.py',
         'test_geometry.py')
#: ... and last: the warm-up's tests load every kernel the warm-up and the node's start-up
#: ask for, which the other modules (and precompile.py) have compiled by then
LAST = ('test_compiled.py',)
#: the modules that count a running node's messages per second: they start once
#: precompile.py has ended, since its compiler on the other core slows the node's
#: two-thread step (spin barriers) far below its rate, as any busy core does until the
#: node's thread tuner reacts
TIMED = ('test_node.py', 'test_node_process.py', 'test_record_render.py',
         'test_live_view.py')

_precompile = None


def pytest_sessionstart(session):
    global _precompile
    if os.environ.get('COSSERAT_TEST_PRECOMPILE', '1') == '0':
        return
    from cosserat_ros.core.warmup import _end_with_parent
    here = os.path.dirname(os.path.abspath(__file__))
    _precompile = subprocess.Popen(
        [sys.executable, os.path.join(here, 'precompile.py')], cwd=here,
        stdin=subprocess.DEVNULL, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL,
        preexec_fn=_end_with_parent)


def pytest_collection_modifyitems(session, config, items):
    def rank(item):
        name = os.path.basename(str(item.fspath))
        if name in LAST:
            return len(FIRST) + 1 + LAST.index(name)
        return FIRST.index(name) if name in FIRST else len(FIRST)
    items.sort(key=rank)                  # stable: pytest's order within each rank


def pytest_runtest_setup(item):
    if (_precompile is not None and _precompile.poll() is None
            and os.path.basename(str(item.fspath)) in TIMED):
        try:
            _precompile.wait(600)
        except subprocess.TimeoutExpired:
            pass


def pytest_sessionfinish(session, exitstatus):
    if _precompile is not None and _precompile.poll() is None:
        _precompile.terminate()
        try:
            _precompile.wait(10)
        except subprocess.TimeoutExpired:
            _precompile.kill()
