"""Cold start on two cores: compile the kernels that are off the start-up's critical path
in a second process, while the first compiles the rest.

With an empty compile cache, numba compiles every kernel once, single-threaded, and the
node's start-up runs them in this order (N = 40, one run on the 2-core test machine):
the mesh's set-up kernels (~7 s), the force the critical dt needs
(``variational_forces``, ~35 s), the step (``run_variational``: ~10 s more, mostly its
update pass ``integrate``) and the energy report (``vertex_fields``, ~8 s). The last two
do not depend on the force's big vertex pass, so :func:`start` runs :func:`main` in a
second process that compiles them (and the faces' kernels the force also calls) into
the shared cache, on the other core. numba looks a kernel up in its cache whenever it is
about to compile it, for itself or as the callee of another kernel, so the node then
loads them instead of compiling them: first mesh after 37 s instead of 60 s in one A/B.

This module imports no ROS package.
"""
from __future__ import annotations

import os
import subprocess
import sys
import time
from typing import Optional

import numba as nb

__all__ = ['kernels_cached', 'start', 'main']


#: a warm-up younger than this holds the cache's lock file; an older lock is stale
LOCK_SECONDS = 600.0


def _index_path() -> Optional[str]:
    """The energy kernel's cache index file; where numba keeps it is not public API, so
    None if that lookup fails."""
    from .forces import vertex_fields
    try:
        return vertex_fields._cache._cache_file._index_path
    except AttributeError:
        return None


def kernels_cached() -> bool:
    """Whether the energy kernel's cache index exists (a warm cache: nothing to do); yes
    if it cannot be found out."""
    path = _index_path()
    return path is None or os.path.exists(path)


def _take_lock(path: str) -> bool:
    """Create the lock file ``path`` unless a warm-up younger than :data:`LOCK_SECONDS`
    holds it (a node started again while the first one's warm-up still runs must not
    start a second one)."""
    for _ in range(2):
        try:
            os.close(os.open(path, os.O_CREAT | os.O_EXCL | os.O_WRONLY))
            return True
        except FileExistsError:
            try:
                if time.time() - os.path.getmtime(path) < LOCK_SECONDS:
                    return False
                os.remove(path)                     # stale: its warm-up died
            except OSError:
                return False
        except OSError:                             # e.g. a read-only cache
            return False
    return False


def start() -> Optional[subprocess.Popen]:
    """Start :func:`main` in a background process if the cache is cold and no other
    warm-up is running; returns it (or None). It runs the package this process imported
    (its parent directory as the working directory, which ``-m`` puts first on the path),
    with the same environment (so the same ``NUMBA_CACHE_DIR``), and its output goes
    nowhere: a caller that reads this process's pipes must not wait for it."""
    if kernels_cached():
        return None
    lock = _index_path() + '.warmup'
    try:
        os.makedirs(os.path.dirname(lock), exist_ok=True)
    except OSError:
        return None
    if not _take_lock(lock):
        return None
    root = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
    try:
        return subprocess.Popen([sys.executable, '-m', 'cosserat_ros.warmup', lock],
                                cwd=root, stdin=subprocess.DEVNULL,
                                stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    except OSError:
        os.remove(lock)
        return None


def main(lock: Optional[str] = None) -> int:
    """Compile, into the cache, the energy report's kernels and the step's update pass
    with the argument types the node's start-up uses (a small sheet has the same types as
    any other; a coupling phi != 0 adds the faces' coupling kernel); then remove the lock
    file ``lock`` that :func:`start` took."""
    try:
        _compile()
    finally:
        if lock is not None and os.path.exists(lock):
            os.remove(lock)
    return 0


def _compile():
    from .integrator import integrate
    from .material import Material
    from .mesh import grid_mesh
    from .simulator import ClothSimulator
    sim = ClothSimulator(grid_mesh(4, 4), Material(zeta=50.0, xi=2e-5, phi=1e-6,
                                                   density=0.2, damping=0.1),
                         dt=1e-5, check_dt=False)
    sim.energy_and_densities()

    # the step calls integrate with a literal True (its own signature, which a call from
    # Python would not give); this wrapper is not cached, integrate is
    @nb.njit
    def update(ops, work, x, v, force, f_applied, mass, damp, pinned, gravity, dt, vmax2,
               acc):
        return integrate(ops, work, True, x, v, force, f_applied, mass, damp, pinned,
                         gravity, dt, vmax2, acc)

    update(sim._ops, sim._work, sim._x.copy(), sim._v.copy(), sim._force.copy(),
           sim._f_applied, sim._mass, sim._damp, sim._pinned, sim._gravity, sim._dt, 1.0,
           sim._acc.copy())


if __name__ == '__main__':
    sys.exit(main(sys.argv[1] if len(sys.argv) > 1 else None))
