"""Solvers step a model's state: :mod:`.explicit` (symplectic Euler, the default; its
compiled passes are ``cosserat_ros.fast``, the per-vertex update ``core/update.py``, which
the solvers and the fast passes import, never the other way round), :mod:`.implicit`, and
the stability limit of :mod:`.stability`."""
