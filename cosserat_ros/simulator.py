"""Public entry point: the cloth simulator (see :mod:`cosserat_ros.core.simulator`)."""
from .core.air import Air  # noqa: F401
from .core.material import Material  # noqa: F401
from .core.simulator import (ClothSimulator, DISCRETISATIONS, DIVERGENCE_METHODS,  # noqa: F401
                             SimulationDiverged, steps_tiled)

__all__ = ['ClothSimulator', 'Material', 'Air', 'SimulationDiverged', 'DISCRETISATIONS',
           'DIVERGENCE_METHODS', 'steps_tiled']
