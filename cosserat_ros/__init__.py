"""cosserat_ros: cloth simulation on the elastic Cosserat surface, served as a ROS 2 node.

Sub-packages (reading order for a newcomer in the manual's ``doc/architecture.md``):

* ``core``: the simulator, no ROS import: mesh, geometry, material, the model (frozen rest
  data), state and controls, the energy terms (``core/terms``: one module each), the
  solvers (``core/solvers``) and the ``ClothSimulator`` facade;
* ``fast``: the compiled step of the elastic terms (SIMD lanes, work sharing, tiles),
  tested against the terms of ``core/terms``;
* ``ros``: the ``cloth_node`` executable (parameters, commands, pacing, messages);
* ``tools``: ``record``, ``render``, ``make bench`` and ``make validate``;
* ``batch``: randomized episodes on Ray; ``envs``: the Gymnasium tasks (``camera``: the
  virtual RGB-D camera both use).

``cosserat_ros.mesh`` and ``cosserat_ros.simulator`` are the documented entry points of the
library; they re-export the core. Importing the package imports nothing else, so that the
executables' entry points (:mod:`.entry`) can catch a Ctrl-C that lands while numba and
rclpy load; every module that compiles kernels imports ``core/compiled.py`` first, which
drops stale kernel caches.
"""

__version__ = '0.1.0'
