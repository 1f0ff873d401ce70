"""cosserat_ros: cloth simulation on the elastic Cosserat surface, served as a ROS 2 node.

The simulator core (``mesh``, ``geometry``, ``material``, ``forces``, ``integrator``,
``simulator``, ``scenarios``) imports no ROS module; ``node`` and the tools built on it do.
"""

__version__ = '0.1.0'
