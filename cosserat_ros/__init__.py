"""cosserat_ros: cloth simulation on the elastic Cosserat surface, served as a ROS 2 node.

The simulator core (``mesh``, ``geometry``, ``material``, ``forces``, ``integrator``,
``simulator``, ``scenarios``) imports no ROS module; ``node`` and the tools built on it do.
"""

from . import compiled as _compiled  # noqa: F401  (drops stale kernel caches first)

__version__ = '0.1.0'
