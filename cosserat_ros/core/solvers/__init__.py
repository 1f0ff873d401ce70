"""Solvers step a model's state: :mod:`.explicit` (symplectic Euler, the default), with the
per-vertex update of :mod:`.update` and the stability limit of :mod:`.stability`."""
