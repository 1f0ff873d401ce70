"""``make bench`` / ``python -m cosserat_ros.bench``: cost of a step, printed as a table.

The scene of issue 6: a 1 m square sheet, N x N grid, all four edges pinned, gravity,
density 0.1 kg/m^2, E h = 500 N/m, nu = 1/3, D = 1e-4 N m (zeta = 3 E h / 16, xi = D / 6).
For each N: median ms/step of repeated batches after warm-up (forces + integration, no
publishing), steps/s, the largest stable dt (``critical_dt``), the real-time factor at that
dt, the ratio to the seed's Table 1 (7.52 / 24.97 / 70.87 ms at 20 / 40 / 80), the cost of
building one mesh message, first-call (compile or cache load) time, threads, and memory of
the state and precomputed operators per vertex. Shared machines are noisy: compare ratios
measured in one run.
"""
from __future__ import annotations

import argparse
import os
import platform
import time

import numba
import numpy as np

from .mesh import grid_mesh
from .messages import colormap, mesh_marker_array
from .simulator import ClothSimulator, Material

SEED_MS = {20: 7.52, 40: 24.97, 80: 70.87}
SCENE = Material.from_plate(youngs_2d=500.0, bending=1e-4, density=0.1)


def _bytes(sim: ClothSimulator) -> int:
    arrays = list(sim._ops) + list(sim._work) + list(sim._cwork) + [
        sim._x, sim._v, sim._force, sim._mass, sim._damp, sim._f_applied, sim._st_T]
    return sum(a.nbytes for a in arrays if isinstance(a, np.ndarray))


def bench(n: int, pattern: str = 'regular', batch_s: float = 0.2, repeats: int = 7):
    mesh = grid_mesh(n, n, pattern=pattern, seed=0)
    t0 = time.perf_counter()
    sim = ClothSimulator(mesh, SCENE, dt=1e-5, check_dt=False)
    sim.pin(mesh.boundary_vertices)
    sim.gravity = (0.0, 0.0, -9.81)
    sim.step(1)
    first = time.perf_counter() - t0
    crit = sim.critical_dt()
    sim.dt = 0.9 * crit
    t = time.perf_counter()
    sim.step(5)
    per = (time.perf_counter() - t) / 5
    k = max(1, int(batch_s / per))
    times = []
    for _ in range(repeats):
        t = time.perf_counter()
        sim.step(k)
        times.append((time.perf_counter() - t) / k)
    ms = 1e3 * float(np.median(times))
    col = colormap(np.zeros(mesh.n_vertices), 0, 1)
    mesh_marker_array(sim.positions, mesh.faces, col, 0, 'world')
    t = time.perf_counter()
    for _ in range(5):
        mesh_marker_array(sim.positions, mesh.faces, col, 0, 'world')
    pub_ms = 1e3 * (time.perf_counter() - t) / 5
    return {'N': n, 'vertices': mesh.n_vertices, 'pattern': pattern, 'ms': ms,
            'steps_s': 1e3 / ms, 'crit_dt': crit, 'rtf': 0.9 * crit / (ms * 1e-3),
            'seed_ratio': SEED_MS[n] / ms if n in SEED_MS else float('nan'),
            'publish_ms': pub_ms, 'first_call_s': first,
            'bytes_per_vertex': _bytes(sim) / mesh.n_vertices,
            'sag': -float(sim.positions[:, 2].min())}


def machine() -> str:
    cpu = platform.processor()
    try:
        with open('/proc/cpuinfo') as fh:
            cpu = next(ln.split(':', 1)[1].strip() for ln in fh if ln.startswith('model name'))
    except (OSError, StopIteration):
        pass
    return (f'{cpu}; {os.cpu_count()} cores; numba {numba.__version__} '
            f'({numba.get_num_threads()} threads, layer set on first parallel call)')


def main(argv=None):
    ap = argparse.ArgumentParser(description='Step cost of the cloth simulator.')
    ap.add_argument('--sizes', type=int, nargs='*', default=[20, 40, 80, 160, 320])
    ap.add_argument('--pattern', default='regular')
    a = ap.parse_args(argv)
    print(f'# machine: {machine()}')
    head = ('N', 'vertices', 'pattern', 'ms/step', 'steps/s', 'crit dt [s]', 'RTF@0.9crit',
            'x seed', 'publish ms', 'first call s', 'B/vertex', 'threads')
    print('| ' + ' | '.join(head) + ' |')
    print('|' + '---|' * len(head))
    for n in a.sizes:
        r = bench(n, a.pattern)
        print(f"| {r['N']} | {r['vertices']} | {r['pattern']} | {r['ms']:.3f} | "
              f"{r['steps_s']:.0f} | {r['crit_dt']:.2e} | {r['rtf']:.2f} | "
              f"{r['seed_ratio']:.0f} | {r['publish_ms']:.2f} | {r['first_call_s']:.1f} | "
              f"{r['bytes_per_vertex']:.0f} | {numba.get_num_threads()} |", flush=True)
    print(f'# threading layer: {numba.threading_layer()}')


if __name__ == '__main__':
    main()
