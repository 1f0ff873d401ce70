"""Public entry point: the cloth simulator (see :mod:`cosserat_ros.core.simulator`)."""
from .core.air import Air  # noqa: F401
from .core.material import Material  # noqa: F401
from .core.simulator import (ClothSimulator, DIVERGENCE_METHODS, SimulationDiverged,  # noqa: F401
                             steps_tiled)

__all__ = ['ClothSimulator', 'Material', 'Air', 'SimulationDiverged', 'DIVERGENCE_METHODS',
           'steps_tiled']
