"""Public entry point: triangle meshes for the cloth (see :mod:`cosserat_ros.core.mesh`)."""
from .core.mesh import (ClothMesh, csr_from_pairs, GRID_PATTERNS, grid_mesh, k_ring,  # noqa: F401
                        load_mesh, MeshError)

__all__ = ['ClothMesh', 'MeshError', 'grid_mesh', 'load_mesh', 'csr_from_pairs', 'k_ring',
           'GRID_PATTERNS']
