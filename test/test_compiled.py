"""The numba set-up: one option set, and stale caches of cross-file kernels are dropped."""
import pathlib
import re

import cosserat_ros
from cosserat_ros import compiled


def test_every_kernel_module_is_hashed():
    pkg = pathlib.Path(cosserat_ros.__file__).parent
    with_kernels = {p.name for p in pkg.glob('*.py')
                    if re.search(r'@(nb\.njit|kernel)\(', p.read_text())}
    # compiled.py holds the options every kernel is compiled with
    assert with_kernels | {'compiled.py'} == set(compiled.KERNEL_MODULES)


def test_stale_cache_is_removed_when_a_kernel_source_changes(tmp_path):
    for name in compiled.KERNEL_MODULES:
        (tmp_path / name).write_text(f'# {name}\n')
    cache = tmp_path / '__pycache__'
    assert compiled.invalidate_stale_cache(str(tmp_path))       # first sight: wiped
    cached = [cache / 'integrator.run_steps-1.py311.nbi',
              cache / 'integrator.run_steps-1.py311.1.nbc']
    for f in cached:
        f.write_bytes(b'x')
    (cache / 'other.pyc').write_bytes(b'x')
    assert not compiled.invalidate_stale_cache(str(tmp_path))   # unchanged: kept
    assert all(f.exists() for f in cached)
    # only the callee's file changes (the case numba's own check misses)
    (tmp_path / 'forces.py').write_text('# changed\n')
    assert compiled.invalidate_stale_cache(str(tmp_path))
    assert not any(f.exists() for f in cached)
    assert (cache / 'other.pyc').exists()


def test_unwritable_cache_is_left_alone(tmp_path):
    for name in compiled.KERNEL_MODULES:
        (tmp_path / name).write_text('\n')
    (tmp_path / '__pycache__').write_text('not a directory')   # cannot hold a cache
    assert not compiled.invalidate_stale_cache(str(tmp_path))
    assert (tmp_path / '__pycache__').read_text() == 'not a directory'
