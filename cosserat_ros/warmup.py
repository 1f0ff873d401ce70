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
from typing import Optional

import numba as nb

__all__ = ['kernels_cached', 'start', 'main']


def kernels_cached() -> bool:
    """Whether the energy kernel's cache index exists (a warm cache: nothing to do).
    Where numba keeps it is not public API; if that lookup fails, say yes."""
    from .forces import vertex_fields
    try:
        return os.path.exists(vertex_fields._cache._cache_file._index_path)
    except AttributeError:
        return True


def start() -> Optional[subprocess.Popen]:
    """Start :func:`main` in a background process if the cache is cold; returns it (or
    None). It runs the package this process imported (its parent directory as the working
    directory, which ``-m`` puts first on the path), with the same environment (so the same
    ``NUMBA_CACHE_DIR``), and its output goes nowhere: a caller that reads this process's
    pipes must not wait for it."""
    if kernels_cached():
        return None
    root = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
    try:
        return subprocess.Popen([sys.executable, '-m', 'cosserat_ros.warmup'], cwd=root,
                                stdin=subprocess.DEVNULL, stdout=subprocess.DEVNULL,
                                stderr=subprocess.DEVNULL)
    except OSError:
        return None


def main() -> int:
    """Compile, into the cache, the energy report's kernels and the step's update pass
    with the argument types the node's start-up uses (a small sheet has the same types as
    any other; a coupling phi != 0 adds the faces' coupling kernel)."""
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
    return 0


if __name__ == '__main__':
    sys.exit(main())
