"""The one reviewed set of numba options for the kernels of the step.

* ``cache=True``: compiled code is stored beside the package and reused by the next process
  (start-up cost, issue 6).
* ``error_model='numpy'``: a division by zero gives inf/NaN as in numpy instead of raising
  from inside a parallel kernel. The step's divergence check (non-finite or impossible
  speed) catches it and restores the state. Dropping the Python-semantics checks also lets
  LLVM schedule the inner loops freely: the vertex pass runs ~1.5x faster.
* ``fastmath={'contract'}``: LLVM may fuse ``a * b + c`` into one FMA. This changes rounding
  only; none of the flags that assume no NaN or infinity (``nnan``, ``ninf``) is set, so the
  NaN checks stay valid, and summation order is kept (no ``reassoc``).
"""
from __future__ import annotations

import numba as nb

__all__ = ['kernel']


def kernel(**options):
    """``numba.njit`` with the options above; ``options`` adds ``parallel``/``inline``."""
    return nb.njit(cache=True, error_model='numpy', fastmath={'contract'}, **options)
