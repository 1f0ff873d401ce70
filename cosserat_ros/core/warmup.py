"""Cold start on two cores: compile the kernels that are off the start-up's critical path
in a second process, while the first compiles the rest.

With an empty compile cache numba compiles every kernel once, single-threaded. The node's
start-up (``ClothNode.__init__``) compiles, in this order: the model's set-up kernels, one
step (``fast/step.py``), the energy report (``core/energy.py`` and the terms' kernels)
and the force behind the critical dt. Most of the step's compile is its vertex pass, which
the small meshes' one-region step shares with the critical dt's force (one step of
dt = 0); the tiled step (large meshes) has a vertex pass of its own. :func:`start` has a
second process compile, meanwhile, what does not depend on the step: the contact pass
that every step calls (a kernel of its own), the energy report, and the tiled step's
critical-dt force.

numba looks a kernel up in its cache whenever it is about to compile it, for itself or as
the callee of another kernel, so the node loads what the second process finished in
time (docs/performance.md has the cold-start figures).

This module imports no ROS package.
"""
from __future__ import annotations

import ctypes
import os
import signal
import subprocess
import sys
import time
from typing import Optional

import numpy as np

__all__ = ['kernels_cached', 'start', 'main']


#: a warm-up younger than this holds the cache's lock file; an older lock is stale
LOCK_SECONDS = 600.0


def _index_path() -> Optional[str]:
    """The energy report's vertex kernel's cache index file; where numba keeps it is not
    public API, so None if that lookup fails."""
    from .terms.jet import vertex_energies
    try:
        return vertex_energies._cache._cache_file._index_path
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


def start(tiled: bool = False, coupled: bool = True) -> Optional[subprocess.Popen]:
    """Start :func:`main` in a background process if the cache is cold and no other
    warm-up is running; ``tiled``: the node's mesh steps tiled; ``coupled``: its material
    has a coupling (phi != 0). Returns the process (or None). It runs the package this
    process imported (its parent directory as the working directory, which ``-m`` puts
    first on the path), with the same environment (so the same
    ``NUMBA_CACHE_DIR``), and its output goes nowhere: a caller that reads this process's
    pipes must not wait for it. It ends with this process (:func:`_end_with_parent`): a
    node stopped during its cold start leaves no compiler behind on a core (one did, and
    the next node's spin-barrier step on that core ran 50x slower)."""
    if kernels_cached():
        return None
    lock = _index_path() + '.warmup'
    try:
        os.makedirs(os.path.dirname(lock), exist_ok=True)
    except OSError:
        return None
    if not _take_lock(lock):
        return None
    root = os.path.dirname(os.path.dirname(os.path.dirname(os.path.abspath(__file__))))
    try:
        args = ([sys.executable, '-m', 'cosserat_ros.core.warmup', lock]
                + (['tiled'] if tiled else []) + (['coupled'] if coupled else [])
                + ['--parent', str(os.getpid())])
        return subprocess.Popen(args, cwd=root, stdin=subprocess.DEVNULL,
                                stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL,
                                preexec_fn=_end_with_parent)
    except OSError:
        os.remove(lock)
        return None


def _end_with_parent() -> None:
    """In the child, before it runs Python: ask the kernel for SIGTERM when the parent
    ends (Linux ``prctl(PR_SET_PDEATHSIG)``; elsewhere nothing), and hold SIGTERM back
    (the mask survives ``exec``) until :func:`main` has its handler, which removes the
    lock."""
    signal.pthread_sigmask(signal.SIG_BLOCK, {signal.SIGTERM})
    try:
        ctypes.CDLL(None, use_errno=True).prctl(1, int(signal.SIGTERM), 0, 0, 0)
    except (OSError, AttributeError):
        pass


def main(lock: Optional[str] = None, tiled: bool = False, coupled: bool = True,
         parent: Optional[int] = None) -> int:
    """Compile into the cache, with the argument types of the node's start-up (a small
    sheet has the same types as any other), what the node needs besides its step: the
    energy report, and for the tiled step the critical dt's force (the two-pass vertex
    pass, which the tiled step does not share); where the one-region step does not apply
    (more threads than CPUs) the two-pass step's update pass, which its compile would
    otherwise reach last; first what the node needs first, then what its commands and
    other configs need (the energy report had come after those, and the node of
    config/cloth.yaml, needing none of them, compiled it itself). Then remove the lock
    file ``lock`` that :func:`start` took; also when SIGTERM ends it (its parent ended),
    so the next start can warm up again.
    ``parent``: the pid of the process that started it; gone already: nothing to do."""
    signal.signal(signal.SIGTERM, lambda *_: _end(lock))
    try:
        signal.pthread_sigmask(signal.SIG_UNBLOCK, {signal.SIGTERM})
        if parent is not None and os.getppid() != parent:
            return 1
        _compile(tiled, coupled)
    finally:
        if lock is not None and os.path.exists(lock):
            os.remove(lock)
    return 0


def _end(lock: Optional[str]) -> None:
    """SIGTERM's handler: remove the lock and end the process at once. Not by raising
    SystemExit: a signal handler runs wherever the interpreter is, and an exception it
    raises inside a ``__del__`` or a weakref callback (llvmlite disposes of its objects in
    those while numba compiles) is printed and dropped, and the compile went on (a
    warm-up outlived its killed parent by more than 30 s in CI)."""
    if lock is not None:
        try:
            os.remove(lock)
        except OSError:
            pass
    os._exit(1)


#: a closed mesh of four faces (vertices, faces): compiles the mesh distance field cheaply
TETRAHEDRON = (np.array([[0.0, 0.0, 0.0], [1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]]),
               np.array([[0, 2, 1], [0, 1, 3], [0, 3, 2], [1, 2, 3]]))


def _compile(tiled: bool, coupled: bool):
    from ..fast import step as fast_step
    from .material import Material
    from .mesh import grid_mesh
    from .simulator import ClothSimulator
    from . import energy
    sim = ClothSimulator(grid_mesh(4, 4), Material(zeta=50.0, xi=2e-5,
                                                   phi=1e-6 if coupled else 0.0,
                                                   density=0.2, damping=0.1),
                         dt=1e-5, check_dt=False)
    # the contact pass, which every step calls (a kernel of its own, int64 bounds)
    from .update import contact_range
    contact_range(np.int64(0), np.int64(0), sim.state.x, sim.state.v,
                  np.zeros((sim.n_vertices, 3)), sim.control, sim.coefficients, sim.dt)
    # the report's own kernels (its internal force is the step's, which the node compiles)
    energy.report(sim.model, sim.coefficients, sim.state, sim.control, sim.dt, sim._scratch,
                  np.zeros((sim.n_vertices, 3)))
    s, m = sim.solver, sim.model
    if tiled:
        run = fast_step.elastic_forces_coupled if coupled else fast_step.elastic_forces
        run(sim.state.x, sim.coefficients, m.faces, m.vertex_faces, m.vertices, m.jets.tr_ptr,
            s.lanes, s.plan, s.work, np.zeros((sim.n_vertices, 3)))
    elif not s._share_threads():
        fast_step.integrate(m.jets.tr_ptr, m.vertex_faces.ptr, s.plan, s.work,
                            sim.state.x.copy(), sim.state.v.copy(), sim.control,
                            sim.coefficients, sim.dt, 1.0, np.zeros(2))
    # then, while the node steps, what its commands call (the closest point of
    # ~/point_forces, the distance field of a mesh obstacle from ~/obstacles) and what
    # only some configs need: the implicit solver's contact kernels, its CG's vector
    # work and its preconditioner's solve (the rest of that solver is the step's
    # force), self-collision's kernels and the corners and edges of boxes, cylinders
    # and meshes (both called from Python after each step)
    from .contact import mesh_distance_field
    from .surface_query import closest_points
    closest_points(sim.state.x, sim.model.mesh.faces, np.zeros((1, 3)))
    mesh_distance_field(*TETRAHEDRON, 0.25, 0.1)
    from .solvers.implicit_contact import warm as warm_implicit_contact
    warm_implicit_contact(sim.state.x, sim.control)
    from .solvers.vectors import warm as warm_vectors
    warm_vectors()
    from .solvers.ldl import warm as warm_ldl
    warm_ldl()
    from .self_contact import warm
    warm()
    from .features import warm as warm_features
    warm_features()


if __name__ == '__main__':
    _args = sys.argv[1:]
    _parent = None
    if '--parent' in _args:
        _k = _args.index('--parent')
        _parent = int(_args[_k + 1])
        del _args[_k:_k + 2]
    sys.exit(main(_args[0] if _args else None, 'tiled' in _args[1:], 'coupled' in _args[1:],
                  _parent))
