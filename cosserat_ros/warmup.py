"""Cold start on two cores: compile the kernels that are off the start-up's critical path
in a second process, while the first compiles the rest.

With an empty compile cache numba compiles every kernel once, single-threaded. The node's
start-up (``ClothNode.__init__``) compiles, in this order: the mesh's set-up kernels
(~7 s on the 2-core test machine), one step, the energy report (``vertex_fields``, ~8 s)
and the force behind the critical dt (``variational_forces``). Most of the step's
compile is its big vertex pass. What comes after it depends on the step's kind:

* the two-pass step (small meshes, or a coupling) shares its vertex pass with the
  critical dt's force: without coupling both run ``run_fused`` (all steps of a call in
  one parallel region; the force is one step of dt = 0), with a coupling (or a threading
  layer ``run_fused`` cannot use) ``run_variational`` and ``variational_forces`` share
  ``vertex_pass``. The energy report and the coupled step's update pass ``integrate``
  (~5 s) do not depend on it: :func:`start` has a second process compile those two.
* the tiled step (``run_tiled``, :func:`simulator.steps_tiled`) has a vertex pass of its
  own, so the critical dt's force compiles a second big vertex pass (~30 s) after it;
  the second process compiles that force, then the energy report.

numba looks a kernel up in its cache whenever it is about to compile it, for itself or as
the callee of another kernel, so the node loads what the second process finished in
time. Measured on a 40 x 40 sheet (in-process, set-up, critical dt, step and energy):
65.2 -> 39.0 s; the installed node to its first mesh 39-41 s cold.

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


def start(tiled: bool = False) -> Optional[subprocess.Popen]:
    """Start :func:`main` in a background process if the cache is cold and no other
    warm-up is running; ``tiled``: the node's mesh steps tiled. Returns the process (or
    None). It runs the package this process imported (its parent directory as the working
    directory, which ``-m`` puts first on the path), with the same environment (so the same
    ``NUMBA_CACHE_DIR``), and its output goes nowhere: a caller that reads this process's
    pipes must not wait for it."""
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
        return subprocess.Popen([sys.executable, '-m', 'cosserat_ros.warmup', lock]
                                + (['tiled'] if tiled else []),
                                cwd=root, stdin=subprocess.DEVNULL,
                                stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    except OSError:
        os.remove(lock)
        return None


def main(lock: Optional[str] = None, tiled: bool = False) -> int:
    """Compile into the cache, with the argument types of the node's start-up (a small
    sheet has the same types as any other), what the node needs after its step's vertex
    pass: for the two-pass step the energy report and the coupled step's update pass (a
    coupling phi != 0 adds the faces' coupling kernel), for the tiled step the critical dt's force
    and the energy report. Then remove the lock file ``lock`` that :func:`start` took."""
    try:
        _compile_tiled() if tiled else _compile()
    finally:
        if lock is not None and os.path.exists(lock):
            os.remove(lock)
    return 0


def _sheet(side: int, phi: float):
    from .material import Material
    from .mesh import grid_mesh
    from .simulator import ClothSimulator
    return ClothSimulator(grid_mesh(side, side), Material(zeta=50.0, xi=2e-5, phi=phi,
                                                          density=0.2, damping=0.1),
                          dt=1e-5, check_dt=False)


def _compile_tiled():
    # the tiled and the two-pass step's operators have the same types: a small sheet does
    from .integrator import variational_forces
    sim = _sheet(4, 0.0)
    # the tiled step's critical dt's force (a small sheet's goes through its step kernel)
    variational_forces(sim._x, sim._ops, sim._mat, sim._work, sim._force.copy())
    sim.energy_and_densities()


def _compile():
    from .integrator import integrate
    sim = _sheet(4, 1e-6)
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
    sys.exit(main(sys.argv[1] if len(sys.argv) > 1 else None, sys.argv[2:3] == ['tiled']))
