"""Compile, in a process of its own, the kernels that the stepping tests load, while the
first test modules (meshes, messages, terms, the integrator, geometry: no step) run on
the other core. Started by conftest.py at the start of the session; numba's cache
(beside the installed package) is shared, so the tests then load what this compiled.
It only calls the public API, on tiny sheets: the kernels' types do not depend on size.
A compile that a test reaches first happens there instead, as without this process."""
import signal

import numpy as np
import trimesh

from cosserat_ros.mesh import grid_mesh
from cosserat_ros.simulator import ClothSimulator, Material


def _sim(n, phi, **kw):
    sim = ClothSimulator(grid_mesh(n, n), Material(zeta=50.0, xi=2e-5, phi=phi,
                                                   density=0.2, damping=0.1),
                         dt=1e-5, check_dt=False, **kw)
    sim.gravity = (0.0, 0.0, -9.81)
    return sim


def main():
    for phi in (0.0, 1e-6):                      # the one-region steps, the energy report
        s = _sim(6, phi)
        s.step(1)
        s.energy()
        s.critical_dt()
    s = _sim(6, 1e-6)                            # contact, the mesh distance field
    s.add_obstacle('plane')
    ico = trimesh.creation.icosphere(subdivisions=1, radius=0.2)
    s.add_obstacle('mesh', vertices=ico.vertices, faces=ico.faces, center=(0, 0, -1))
    s.step(1)
    s.contact_forces()
    from cosserat_ros.camera import Camera       # the camera's ray cast and shading
    Camera(4, 3, 60.0, (0, 0, 1), (1, 0, 0, 0)).render(s)
    from cosserat_ros.core.self_contact import warm
    warm()                                       # self-collision's kernels
    from cosserat_ros.core.features import warm as warm_features
    warm_features()                              # a box's corners and edges
    for phi in (0.0, 1e-6):                      # the implicit solver's kernels
        s = _sim(6, phi, solver='implicit')
        s.dt = 1.0 / 60.0
        s.step(1)
    s.add_obstacle('plane', point=(0, 0, -0.1))  # ... and its contact
    s.step(2)
    for phi in (0.0, 1e-6):                      # the scalar vertex pass
        _sim(6, phi, simd=False).step(1)
    s = ClothSimulator(grid_mesh(6, 6), Material(zeta=10.0, xi=1e-3, phi=1e-4,
                                                 density=0.2), dt=1e-6, check_dt=False,
                       discretisation='covariant')
    s.pin(s.mesh.boundary_vertices)
    s.step(1)
    for phi in (0.0, 1e-6):                      # the tiled step (4096 vertices and more)
        s = _sim(64, phi)
        s.step(1)
        s.critical_dt()
    np.zeros(1)


if __name__ == '__main__':
    # started with SIGTERM held back (warmup._end_with_parent): take it as it comes
    signal.pthread_sigmask(signal.SIG_UNBLOCK, {signal.SIGTERM})
    main()
