"""The one reviewed set of numba options for the kernels of the step.

* ``cache=True``: compiled code is stored beside the package and reused by the next process
  (start-up cost).
* ``error_model='numpy'``: a division by zero gives inf/NaN as in numpy instead of raising
  from inside a parallel kernel. The step's divergence check (non-finite or impossible
  speed) catches it and restores the state. Dropping the Python-semantics checks also lets
  LLVM schedule the inner loops freely (a much faster vertex pass).
* ``fastmath={'contract'}`` (:data:`STRICT`): LLVM may fuse ``a * b + c`` into one FMA.
  This changes rounding only; none of the flags that assume no NaN or infinity (``nnan``,
  ``ninf``) is set, so the NaN checks stay valid, and summation order is kept.
* :data:`REDUCTION` adds ``reassoc`` for the few stencil sums of the vertex pass (short
  helper functions in ``core/terms/bending.py``), so that LLVM can split them over SIMD
  lanes. It changes the summation order of those sums only (results move by ~1e-15
  relative, and stay deterministic); a NaN or inf still propagates.

Indices in the hot loops are cast to ``nb.uint64`` before they index an array (and loop
ranges over index arrays run over unsigned bounds): through a signed index numba adds its
negative-index wrap-around to every load and store, four integer instructions that slow
the gather of the step (docs/performance.md). Mixing uint64 with int64 in
arithmetic gives a float in numba, so the casts stay next to the loads.

Stale caches
------------
numba keys a cached function by the time stamp of its own source file only. A kernel that
calls kernels of another file (the step in ``fast/step.py`` inlines the terms of
``core/terms/``) keeps its cached machine code when only the callee's file changes, and an
install that preserves time stamps (``setup.py install`` copies them) can leave such a
stale step behind. On import, :func:`invalidate_stale_cache` therefore hashes every Python
file of the sub-packages that hold kernels (:data:`KERNEL_DIRS`; a test checks that no
other file compiles anything) and, when the hash differs from the one stored beside the
cache, removes the package's cached kernels (every ``__pycache__`` of the package: numba
caches beside each source file). An edit to the ROS layer or the tools keeps the cache.
"""
from __future__ import annotations

import hashlib
import os

import numba as nb

__all__ = ['kernel', 'invalidate_stale_cache', 'PACKAGE_DIR', 'KERNEL_DIRS']

#: the package's top directory (cosserat_ros/)
PACKAGE_DIR = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))

#: the sub-packages whose files hold (or are inlined into) compiled kernels
KERNEL_DIRS = ('core', 'fast')

#: fast-math flags of the kernels: fused multiply-add only
STRICT = frozenset({'contract'})
#: fast-math flags of the stencil reductions: the sum may be reordered into SIMD lanes
REDUCTION = frozenset({'contract', 'reassoc'})


def kernel(refcount: bool = True, **options):
    """``numba.njit`` with the options above; ``options`` adds ``parallel``, ``inline``
    (numba IR), ``forceinline`` (LLVM) or replaces ``fastmath`` (:data:`REDUCTION`).

    ``refcount=False`` compiles without numba's reference counting (its private
    ``_nrt=False``, numba is pinned), for the kernels called once per vertex or pair, or
    looping over such calls, that allocate nothing (a compile error says so if one does)
    and return no array (a counting caller would release one it was never given). With
    counting, every call increments and decrements the count of each array argument, an
    atomic operation on a count that both threads share, and numba does not remove the
    pairs around a call (what that cost the contact pass and the tiled step:
    docs/performance.md). The caller holds references to every array for the call's
    duration, so none is freed under it."""
    options['fastmath'] = set(options.get('fastmath', STRICT))
    if not refcount:
        options['_nrt'] = False
    return nb.njit(cache=True, error_model='numpy', **options)


def kernel_sources(package_dir: str = PACKAGE_DIR):
    """Every Python file of :data:`KERNEL_DIRS`, relative to the package, sorted."""
    out = []
    for root, dirs, files in (w for d in KERNEL_DIRS
                              for w in os.walk(os.path.join(package_dir, d))):
        dirs[:] = sorted(d for d in dirs if d != '__pycache__')
        out += [os.path.relpath(os.path.join(root, f), package_dir)
                for f in files if f.endswith('.py')]
    return sorted(out)


def invalidate_stale_cache(package_dir: str = PACKAGE_DIR) -> bool:
    """Remove the cached kernels of every ``__pycache__`` under ``package_dir`` when the
    package's sources changed since they were written; returns True if it removed them. A
    read-only install is left alone (numba then caches per user)."""
    digest = hashlib.sha256()
    for name in kernel_sources(package_dir):
        with open(os.path.join(package_dir, name), 'rb') as fh:
            digest.update(name.encode() + b'\0' + fh.read())
    stamp = os.path.join(package_dir, '__pycache__', 'kernels.sha256')
    try:
        with open(stamp) as fh:
            if fh.read().strip() == digest.hexdigest():
                return False
    except OSError:
        pass
    try:
        os.makedirs(os.path.dirname(stamp), exist_ok=True)
        for root, dirs, files in os.walk(package_dir):
            if os.path.basename(root) == '__pycache__':
                for name in files:
                    if name.endswith(('.nbi', '.nbc')):
                        os.remove(os.path.join(root, name))
        with open(stamp, 'w') as fh:
            fh.write(digest.hexdigest())
    except OSError:
        return False
    return True


invalidate_stale_cache()
