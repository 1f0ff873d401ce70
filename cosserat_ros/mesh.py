"""Public entry point: triangle meshes for the cloth (see :mod:`cosserat_ros.core.mesh`)."""
from .core.mesh import (ClothMesh, csr_from_pairs, disc_mesh, GRID_PATTERNS,  # noqa: F401
                        grid_mesh, k_ring, load_mesh, MeshError)

__all__ = ['ClothMesh', 'MeshError', 'grid_mesh', 'disc_mesh', 'load_mesh', 'csr_from_pairs',
           'k_ring',
           'GRID_PATTERNS']
