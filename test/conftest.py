"""Test-session set-up: every run gets its own ROS domain (one no other run on the machine
holds) and keeps discovery on localhost, so parallel runs (and other ROS graphs on the
machine) never see each other.

On a cold compile cache most of the suite's time is numba compiling the step's kernels,
one core at a time. The session therefore starts ``precompile.py`` in a second process
and runs first the modules that step no cloth (meshes, messages, terms, the integrator,
geometry), so that the other core compiles the steps meanwhile (a warm cache: it loads
them in a few seconds and ends), and the warm-up's tests last."""
import os
import subprocess
import sys

import pytest


def _own_domain() -> int:
    """A ROS domain no other test run on this machine holds: the first of 1..100 (from
    one the process id picks) whose lock file this session can lock; the lock is held
    until the session's process ends. The domain exported in ROS_DOMAIN_ID, if any, is
    skipped (it may be a live graph's) and then replaced by this one. The lock files are
    opened read-only (flock needs no more), so that another user's can be locked too."""
    import fcntl
    import tempfile
    try:
        exported = int(os.environ.get('ROS_DOMAIN_ID', ''))
    except ValueError:
        exported = None
    for k in range(100):
        domain = 1 + (os.getpid() + k) % 100
        if domain == exported:
            continue
        try:
            fd = os.open(os.path.join(tempfile.gettempdir(),
                                      f'cosserat_ros_test_domain_{domain}.lock'),
                         os.O_CREAT | os.O_RDONLY, 0o666)
        except OSError:
            continue
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except OSError:
            os.close(fd)
            continue
        _own_domain.lock = fd                      # held open: the lock lasts the session
        return domain
    raise RuntimeError('every ROS domain 1..100 is held by another test run')


os.environ['ROS_DOMAIN_ID'] = str(_own_domain())
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


class _Tracked(subprocess.Popen):
    """subprocess.Popen that remembers its processes, so that the session's end can stop
    any a failed test left running (a node that outlived its test would stay on this
    run's ROS domain, and past the run)."""

    started: list = []

    def __init__(self, *args, **kwargs):
        super().__init__(*args, **kwargs)
        _Tracked.started.append(self)


subprocess.Popen = _Tracked            # the tests' modules call subprocess.Popen / run


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


def _stop(procs) -> None:
    """Terminate, then kill what is still running after 10 s."""
    for p in procs:                    # a chance to clean up first
        p.terminate()
    for p in procs:
        try:
            p.wait(10)
        except subprocess.TimeoutExpired:
            p.kill()
            p.wait(10)


def _names(procs) -> str:
    return ', '.join(str(p.args[0] if isinstance(p.args, (list, tuple)) else p.args)
                     for p in procs)


@pytest.hookimpl(hookwrapper=True)
def pytest_runtest_call(item):
    """A process a test's body started and left running (a failed assertion or a timeout
    before its clean-up) is stopped when the test ends, not at the session's: a node left
    on the run's ROS domain would answer the next tests' subscriptions (seen: a node that
    ignored a Ctrl-C while starting failed ten later tests). Fixtures' processes, started
    in the set-up, are not touched."""
    before = len(_Tracked.started)
    yield
    left = [p for p in _Tracked.started[before:] if p.poll() is None]
    if left:
        _stop(left)
        print(f'\nconftest: stopped {len(left)} process(es) {item.name} left running: '
              + _names(left))


def pytest_sessionfinish(session, exitstatus):
    if _precompile is not None and _precompile.poll() is None:
        _precompile.terminate()
        try:
            _precompile.wait(10)
        except subprocess.TimeoutExpired:
            _precompile.kill()
    left = [p for p in _Tracked.started if p is not _precompile and p.poll() is None]
    _stop(left)
    if left:
        print('\nconftest: stopped {} process(es) a test left running: {}'.format(
            len(left), _names(left)))
