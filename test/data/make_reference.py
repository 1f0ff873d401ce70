"""Record the reference trajectories of ``test_reference_trajectories.py``.

Run once, on the commit before the core was restructured (6a1f975, issue 23), with
``python test/data/make_reference.py``; its output ``reference_trajectories.npz`` is
committed. The restructured core must reproduce these positions and velocities after 500
steps to 1e-9 relative. The script uses only the documented public API
(``cosserat_ros.mesh``, ``cosserat_ros.simulator``), so it still runs on later commits
(where it would record the new code's trajectories: do not re-run it to make a failing
test pass).
"""
import os
import sys

import numpy as np
import trimesh

from cosserat_ros.mesh import ClothMesh, grid_mesh, load_mesh
from cosserat_ros.simulator import ClothSimulator, Material

STEPS = 500
HERE = os.path.dirname(os.path.abspath(__file__))
ROOT = os.path.dirname(os.path.dirname(HERE))


def coupled(zeta, xi, fraction=0.5):
    """A coupling at ``fraction`` of its admissible limit 2 sqrt(zeta xi)."""
    return fraction * 2.0 * np.sqrt(zeta * xi)


def cases():
    """name -> (mesh, material, dt, discretisation, set-up function)."""
    out = {}
    base = dict(zeta=50.0, xi=2e-5, density=0.2, damping=0.1)

    def top_corners(sim, rng):
        m = sim.mesh
        x = m.vertices
        top = np.flatnonzero(np.isclose(x[:, 1], x[:, 1].max()))
        sim.pin([top[np.argmin(x[top, 0])], top[np.argmax(x[top, 0])]])
        sim.gravity = (0.0, 0.0, -9.81)

    def shaken(sim, rng):
        top_corners(sim, rng)
        sim.set_velocities(0.05 * rng.standard_normal((sim.n_vertices, 3)))

    def forced(sim, rng):
        shaken(sim, rng)
        idx = rng.choice(sim.n_vertices, 6, replace=False)
        sim.set_vertex_forces(idx, 0.02 * rng.standard_normal((6, 3)))
        sim.force_field = (1.0, 0.5, -0.3)

    def left_edge(sim, rng):
        x = sim.mesh.vertices
        sim.pin(np.flatnonzero(np.isclose(x[:, 0], x[:, 0].min())))
        sim.gravity = (0.0, 0.0, -9.81)
        sim.set_velocities(0.05 * rng.standard_normal((sim.n_vertices, 3)))
        sim.set_vertex_forces([3, 3, 40], [[0.0, 0.0, 0.01], [0.01, 0.0, 0.0],
                                           [0.0, -0.02, 0.0]])

    def closed(sim, rng):
        sim.pin([0])
        sim.gravity = (0.0, 0.0, -9.81)
        sim.force_field = (0.3, 0.0, 0.0)
        sim.set_velocities(0.05 * rng.standard_normal((sim.n_vertices, 3)))
        sim.set_vertex_forces([5, 17], [[0.0, 0.0, 0.05], [0.02, 0.0, 0.0]])

    def boundary(sim, rng):
        sim.pin(sim.mesh.boundary_vertices)
        sim.gravity = (0.0, 0.0, -9.81)
        sim.set_velocities(0.01 * rng.standard_normal((sim.n_vertices, 3)))

    g = grid_mesh(12, 12)
    out['regular_phi0'] = (g, Material(phi=0.0, **base), 2e-4, 'variational', shaken)
    out['regular_coupled'] = (g, Material(phi=coupled(50.0, 2e-5), **base), 2e-4,
                              'variational', forced)
    out['regular_shipped_phi'] = (g, Material(phi=1e-6, **base), 2e-4, 'variational',
                                  forced)
    out['alternating_coupled'] = (grid_mesh(12, 10, 1.2, 1.0, 'alternating'),
                                  Material(phi=coupled(50.0, 2e-5, 0.7), **base), 2e-4,
                                  'variational', left_edge)
    out['irregular_coupled'] = (grid_mesh(12, 12, pattern='irregular', seed=3),
                                Material(phi=coupled(50.0, 2e-5), **base), 1.5e-4,
                                'variational', forced)
    out['irregular_phi0'] = (grid_mesh(12, 12, pattern='irregular', seed=3),
                             Material(phi=0.0, **base), 1.5e-4, 'variational', forced)
    sphere = trimesh.creation.icosphere(subdivisions=2, radius=0.3)
    sm = ClothMesh(sphere.vertices, sphere.faces)
    soft = dict(zeta=10.0, xi=1e-4, density=0.2, damping=0.05)
    out['sphere_closed_coupled'] = (sm, Material(phi=coupled(10.0, 1e-4), **soft), 1e-4,
                                    'variational', closed)
    out['sphere_closed_phi0'] = (sm, Material(phi=0.0, **soft), 1e-4, 'variational', closed)
    dome = load_mesh(os.path.join(ROOT, 'config', 'meshes', 'dome_with_hole.obj'))
    out['dome_coupled'] = (dome, Material(zeta=10.0, xi=1e-3, phi=coupled(10.0, 1e-3),
                                          density=0.2, damping=0.5), 1e-4, 'variational',
                           boundary)
    big = grid_mesh(64, 64)
    out['tiled_phi0'] = (big, Material(phi=0.0, **base), 1e-4, 'variational', shaken)
    out['tiled_coupled'] = (big, Material(phi=coupled(50.0, 2e-5), **base), 1e-4,
                            'variational', shaken)
    out['covariant_membrane'] = (grid_mesh(10, 10, pattern='alternating'),
                                 Material(zeta=0.1, xi=1e-4, phi=1e-6, density=1e-3,
                                          damping=2e-3), 1e-4, 'covariant', boundary)
    return out


def run(name, spec):
    sim = simulator(name, spec)
    sim.step(STEPS)
    e = sim.energy()
    return {f'{name}/x': sim.positions, f'{name}/v': sim.velocities,
            f'{name}/energy': np.array([e[k] for k in ENERGY_KEYS])}


def rng_for(name):
    """The random generator of a case's set-up (initial velocities, forces)."""
    return np.random.default_rng(sum(map(ord, name)))


def simulator(name, spec):
    """The case's simulator, set up and not yet stepped."""
    mesh, mat, dt, div, setup = spec
    sim = ClothSimulator(mesh, mat, dt=dt, discretisation=div, check_dt=False)
    setup(sim, rng_for(name))
    return sim


ENERGY_KEYS = ('kinetic', 'stretching', 'bending', 'coupling', 'elastic', 'gravity',
               'external_work', 'dissipated', 'total')


def main():
    data = {}
    for name, spec in cases().items():
        data.update(run(name, spec))
        print(name, 'max |x - X|', float(np.abs(data[f'{name}/x'] - spec[0].vertices).max()))
    np.savez_compressed(os.path.join(HERE, 'reference_trajectories.npz'), **data)
    return 0


if __name__ == '__main__':
    sys.exit(main())
