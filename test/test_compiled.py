"""The numba set-up: one option set, stale caches of cross-file kernels dropped, and the
cold-start warm-up process compiling what the node then loads from the cache."""
import os
import subprocess
import sys
import time

import pytest

from cosserat_ros.core import compiled


def test_every_file_that_can_hold_a_kernel_is_hashed():
    files = compiled.kernel_sources()
    for name in ('core/terms/jet.py', 'core/update.py', 'fast/step.py',
                 'fast/lanes.py', 'core/compiled.py'):
        assert name in files
    assert not any('__pycache__' in f for f in files)
    # the files left out (ROS layer, tools, re-exports) compile nothing
    for root, dirs, names in os.walk(compiled.PACKAGE_DIR):
        dirs[:] = [d for d in dirs if d != '__pycache__']
        for n in names:
            rel = os.path.relpath(os.path.join(root, n), compiled.PACKAGE_DIR)
            if n.endswith('.py') and rel not in files:
                text = open(os.path.join(root, n)).read()
                assert not any(k in text for k in ('njit', 'kernel(', 'numba.jit',
                                                   '@nb.', 'vectorize')), rel


_STARTS = """
import os, sys
from cosserat_ros.core import warmup
assert not warmup.kernels_cached()
first = warmup.start(sys.argv[1] == 'tiled', sys.argv[2] == 'coupled')
second = warmup.start()
assert first is not None and second is None
assert first.wait(600) == 0
assert warmup.kernels_cached() and not os.path.exists(warmup._index_path() + '.warmup')
print('ok')
"""

#: the signatures of the kernels the node needs besides its step, as JSON: after the
#: warm-up's compile (argv[1] == 'warmup') or after the calls of the node's start-up
_SIGNATURES = """
import json, sys
import numpy as np
from cosserat_ros.core import energy, warmup
from cosserat_ros.core.update import contact_range
from cosserat_ros.core.terms import jet
from cosserat_ros.fast import step
from cosserat_ros.mesh import grid_mesh
from cosserat_ros.simulator import ClothSimulator, Material
tiled, coupled = sys.argv[2] == 'tiled', sys.argv[3] == 'coupled'
kernels = [jet.vertex_energies, energy.densities, energy.totals, contact_range]
kernels.append((step.elastic_forces_coupled if coupled else step.elastic_forces)
               if tiled else step.integrate)
if sys.argv[1] == 'warmup':
    warmup._compile(tiled, coupled)
else:
    s = ClothSimulator(grid_mesh(6, 5), Material(zeta=93.75, xi=1e-4 / 6,
                                                 phi=1e-6 if coupled else 0.0, density=0.1),
                       dt=1e-5, check_dt=False)
    energy.report(s.model, s.coefficients, s.state, s.control, s.dt, s._scratch,
                  s.state.x * 0)
    contact_range(np.int64(0), np.int64(0), s.state.x, s.state.v, s.state.x * 0, s.control,
                  s.coefficients, s.dt)
    m, v = s.model, s.solver
    if tiled:
        kernels[-1](s.state.x, s.coefficients, m.faces, m.vertex_faces, m.vertices,
                    m.jets.tr_ptr, v.lanes, v.plan, v.work, s.state.x.copy())
    elif not v._share_threads():
        step.integrate(m.jets.tr_ptr, m.vertex_faces.ptr, v.plan, v.work, s.state.x,
                       s.state.v, s.control, s.coefficients, s.dt, 1e6, s.state.acc)
    else:
        kernels.pop()             # the one-region step: its own compile, not the warm-up's
print(json.dumps({k.py_func.__qualname__: sorted(map(str, k.signatures)) for k in kernels}))
"""


@pytest.mark.parametrize('plan', ['two-pass', 'tiled'])
@pytest.mark.process
def test_warmup_compiles_the_signatures_the_node_then_asks_for(tmp_path, plan):
    # cosserat_ros.core.warmup, the node's second process on a cold start, compiles what
    # the node needs besides its step (the energy kernels, the contact pass, and the
    # tiled step's critical-dt force) with the argument types the node asks for: numba
    # keys its cache by those, and a warm-up of other types (an int for an int64, a
    # read-only or non-contiguous array) would compile for nobody. Both processes use
    # the suite's cache, so they load rather than compile
    import json
    run = dict(cwd=tmp_path, capture_output=True, text=True, timeout=600)
    out = {}
    for who in ('warmup', 'node'):
        done = subprocess.run([sys.executable, '-c', _SIGNATURES, who, plan, 'coupled'], **run)
        assert done.returncode == 0, done.stderr
        out[who] = json.loads(done.stdout.strip().splitlines()[-1])
    assert len(out['node']) >= 4
    for name, signatures in out['node'].items():
        assert signatures and set(signatures) <= set(out['warmup'][name]), name


def _copy_cache_but_the_energy_kernel(dst):
    """Copy the package's compiled kernels (numba caches them beside each source file)
    into ``dst`` laid out as numba's NUMBA_CACHE_DIR locator lays them out, leaving out
    the energy report's vertex kernel: :func:`warmup.kernels_cached` then says cold, and
    a warm-up compiles that kernel alone and loads the rest."""
    import shutil
    from numba.core.caching import _CacheLocator
    for root, dirs, names in os.walk(compiled.PACKAGE_DIR):
        if os.path.basename(root) != '__pycache__':
            continue
        source_dir = os.path.dirname(root)
        sub = _CacheLocator.get_suitable_cache_subpath(os.path.join(source_dir, 'x.py'))
        os.makedirs(os.path.join(dst, sub), exist_ok=True)
        for n in names:
            if n.endswith(('.nbi', '.nbc')) and not n.startswith('jet.vertex_energies-'):
                shutil.copy2(os.path.join(root, n), os.path.join(dst, sub, n))


@pytest.mark.process
def test_warmup_process_starts_once_and_fills_the_cache(tmp_path):
    # on a cold cache (here: all but the energy kernel, which says whether it is cold)
    # the first start runs the warm-up, a second start while it runs starts no other,
    # and the warm-up ends having filled the cache and removed its lock
    _copy_cache_but_the_energy_kernel(str(tmp_path / 'cache'))
    env = dict(os.environ, NUMBA_CACHE_DIR=str(tmp_path / 'cache'))
    run = dict(env=env, cwd=tmp_path, capture_output=True, text=True, timeout=600)
    cold = subprocess.run([sys.executable, '-c', _STARTS, 'two-pass', 'coupled'], **run)
    assert cold.stdout.strip() == 'ok', cold.stderr


_ORPHAN = """
import sys, time
from cosserat_ros.core import warmup
child = warmup.start(False, True)
print(child.pid, warmup._index_path() + '.warmup', flush=True)
time.sleep(600)
"""


def _alive(pid):
    try:
        with open(f'/proc/{pid}/status') as fh:
            return 'State:\tZ' not in fh.read()
    except FileNotFoundError:
        return False


def _catches_sigterm(pid):
    with open(f'/proc/{pid}/status') as fh:
        caught = next(int(line.split()[1], 16) for line in fh if line.startswith('SigCgt'))
    return bool(caught & (1 << (15 - 1)))


@pytest.mark.process
def test_warmup_process_ends_with_the_process_that_started_it(tmp_path):
    # a node killed during its cold start (here SIGKILL: no handler of its own runs)
    # leaves no compiler behind on a core, and no lock that would stop the next start's
    # warm-up for LOCK_SECONDS. The parent is killed once the child compiles, long before
    # its compile could end by itself
    env = dict(os.environ, NUMBA_CACHE_DIR=str(tmp_path / 'cache'))
    parent = subprocess.Popen([sys.executable, '-c', _ORPHAN], env=env, cwd=tmp_path,
                              stdout=subprocess.PIPE, text=True)
    try:
        pid, lock = parent.stdout.readline().split()
        pid = int(pid)
        assert _alive(pid) and os.path.exists(lock)
        # the child is past its imports and compiling: its SIGTERM handler is set
        end = time.monotonic() + 120
        while not _catches_sigterm(pid) and time.monotonic() < end:
            time.sleep(0.05)
        assert _catches_sigterm(pid)
    finally:
        parent.kill()
        parent.wait()
    end = time.monotonic() + 30
    while _alive(pid) and time.monotonic() < end:
        time.sleep(0.05)
    assert not _alive(pid)
    assert not os.path.exists(lock)
    # and it was stopped, not done: the energy kernel it compiles first is not in the cache
    assert not os.path.exists(lock[:-len('.warmup')])


def test_warmup_lock_is_taken_once_and_a_stale_one_replaced(tmp_path):
    from cosserat_ros.core import warmup
    lock = str(tmp_path / 'x.nbi.warmup')
    assert warmup._take_lock(lock) and not warmup._take_lock(lock)
    old = time.time() - warmup.LOCK_SECONDS - 1          # its warm-up died long ago
    os.utime(lock, (old, old))
    assert warmup._take_lock(lock) and not warmup._take_lock(lock)
    assert not warmup._take_lock(str(tmp_path / 'missing' / 'x.warmup'))


def test_stale_cache_is_removed_when_any_source_changes(tmp_path):
    pkg = tmp_path / 'pkg'
    (pkg / 'core' / 'terms').mkdir(parents=True)
    (pkg / 'ros').mkdir()
    (pkg / 'ros' / 'node.py').write_text('# node\n')
    (pkg / 'fast').mkdir()
    for name in ('core/terms/jet.py', 'fast/step.py', 'core/compiled.py'):
        (pkg / name).write_text(f'# {name}\n')
    assert compiled.invalidate_stale_cache(str(pkg))       # first sight: wiped
    cached = [pkg / 'fast' / '__pycache__' / 'step.run_two_pass-1.py311.nbi',
              pkg / 'fast' / '__pycache__' / 'step.run_two_pass-1.py311.1.nbc']
    cached[0].parent.mkdir()
    for f in cached:
        f.write_bytes(b'x')
    (cached[0].parent / 'other.pyc').write_bytes(b'x')
    assert not compiled.invalidate_stale_cache(str(pkg))   # unchanged: kept
    assert all(f.exists() for f in cached)
    (pkg / 'ros' / 'node.py').write_text('# no kernel here\n')
    assert not compiled.invalidate_stale_cache(str(pkg))   # the ROS layer: kept
    # only the callee's file changes (the case numba's own check misses)
    (pkg / 'core' / 'terms' / 'jet.py').write_text('# changed\n')
    assert compiled.invalidate_stale_cache(str(pkg))
    assert not any(f.exists() for f in cached)
    assert (cached[0].parent / 'other.pyc').exists()


def test_unwritable_cache_is_left_alone(tmp_path):
    (tmp_path / 'core').mkdir()
    (tmp_path / 'core' / 'a.py').write_text('\n')
    (tmp_path / '__pycache__').write_text('not a directory')   # cannot hold a cache
    assert not compiled.invalidate_stale_cache(str(tmp_path))
    assert (tmp_path / '__pycache__').read_text() == 'not a directory'


_REFCOUNT = """
import numba as nb
import numpy as np
from cosserat_ros.core.compiled import kernel
from cosserat_ros.core.surface_query import segment_segment


def closest(x, out):
    # rows of x passed on as views to a kernel that is not inlined: the contact pass's
    # and the pair geometry's pattern
    for i in range(x.shape[0] - 3):
        out[i] = segment_segment(x[i], x[i + 1], x[i + 2], x[i + 3])[0]


x, out = np.random.default_rng(0).random((8, 3)), np.zeros(5)
# the counted twin uncached: numba's cache key has no _nrt, it would load the first
for k in (kernel(refcount=False)(closest), nb.njit(error_model='numpy')(closest)):
    k(x, out)
    ir = k.inspect_llvm(k.signatures[0])
    print(ir.count('call void @NRT_incref') + ir.count('call void @NRT_decref'))
"""


@pytest.mark.process
def test_refcount_false_compiles_without_reference_counting(tmp_path):
    # kernel(refcount=False) maps to numba's private _nrt=False (numba is pinned): a loop
    # that passes rows of an array to another kernel, compiled into an empty cache, has
    # no reference counting in its code; the same function compiled the default way
    # increments and decrements the array's count around every call. A numba that
    # dropped or renamed the option fails here.
    (tmp_path / 'refcount.py').write_text(_REFCOUNT)
    env = dict(os.environ, NUMBA_CACHE_DIR=str(tmp_path / 'cache'))
    out = subprocess.run([sys.executable, 'refcount.py'], env=env, cwd=tmp_path,
                         capture_output=True, text=True, timeout=300)
    assert out.returncode == 0, out.stderr
    without, counted = (int(w) for w in out.stdout.split())
    assert without == 0 and counted > 0


def test_the_per_vertex_kernels_count_no_references():
    # the kernels called once per vertex, pair, tile or lane group from the step's loops
    from cosserat_ros.core import contact
    from cosserat_ros.core import update
    from cosserat_ros.core.terms import jet
    from cosserat_ros.fast import lanes, step
    for k in (update.contact_range, update.contact_list, contact.resolve, contact.push_out,
              contact.distance, step._gather_update, lanes._coupling_group,
              lanes.vertex_chunk, jet.vertex_range, jet.normal_jet, jet.weighted_offsets):
        assert k.targetoptions.get('_nrt') is False, k
