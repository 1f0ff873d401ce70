"""Work sharing between the threads of a parallel pass: each thread its own range of work
items first, then it takes the others' remaining items from their far ends.

Why: numba splits a ``prange`` statically, one equal run of iterations per thread, so a pass
lasts as long as its slowest thread, and on a shared host the worker thread runs the same
chunks slower than the calling thread. numba's own dynamic schedule
(``set_parallel_chunksize``) hands out every chunk through the threading layer, which costs
more than it balances (both measured: docs/performance.md).

Here a pass over ``n`` items runs ``prange(T)`` over T ranges (:func:`split`: T equal runs,
as the static split would give each thread). ``state[0]`` holds T, which the caller sets
from Python (``numba.get_num_threads()``: called in compiled code, it makes numba refuse to
cache the kernel). Range r's state ``state[1 + r]`` is one int64, the run still to do:
``front | back << 32``. The thread of range r takes items from its front (:func:`take`
with ``front``) in order; when its range is empty it goes round the other ranges and takes
their items from the back (:func:`claim` does both). A pass reads::

    nr = split(state, n)
    for t in prange(nr):
        c, k = claim(state, t, nr, 0)
        while c >= 0:
            ...                            # item c
            c, k = claim(state, t, nr, k)

A take is one compare-and-swap of that range's state, so every item is taken exactly once,
and a thread keeps to its own part of the arrays unless it has run out of work. Any T >= 1
gives the same results; T = the threads numba runs is the fastest.

Which thread runs an item changes from call to call; what the item computes does not. A
pass that writes each item's results to places of their own (and sums per item, not per
thread: see ``integrate`` in ``fast/step.py``) therefore gives the same numbers to the bit
as the static split. The intrinsics work only in compiled code.

:func:`arrive` is a barrier on the same compare-and-swap, for a region that runs several
passes one after the other (``run_region`` in ``fast/step.py``).
"""
from __future__ import annotations

import functools
import os

import numba as nb
import numpy as np
from numba.core import cgutils, types
from numba.extending import intrinsic

from ..core.compiled import kernel

__all__ = ['split', 'take', 'claim', 'arrive', 'usable_cpus', 'start_threads']

_LOW = 0xFFFFFFFF


def _check_state(a):
    if not (isinstance(a, types.Array) and a.dtype == types.int64 and a.ndim == 1):
        raise TypeError(f'the work-sharing state must be a 1-D int64 array, got {a}')


def _element_pointer(context, builder, sig, args):
    arr = context.make_array(sig.args[0])(context, builder, args[0])
    return cgutils.get_item_pointer(context, builder, sig.args[0], arr, [args[1]])


@intrinsic
def atomic_load(typingctx, a, i):
    """``a[i]`` of an int64 array, read atomically (acquire)."""
    _check_state(a)

    def codegen(context, builder, sig, args):
        return builder.load_atomic(_element_pointer(context, builder, sig, args), 'acquire', 8)
    return types.int64(a, i), codegen


@intrinsic
def atomic_cas(typingctx, a, i, old, new):
    """Compare and swap ``a[i]`` (int64): if it still holds ``old``, write ``new``; returns
    whether it did (acquire-release on success)."""
    _check_state(a)

    def codegen(context, builder, sig, args):
        res = builder.cmpxchg(_element_pointer(context, builder, sig, args), args[2], args[3],
                              'acq_rel', 'monotonic')
        return builder.extract_value(res, 1)
    return types.boolean(a, i, old, new), codegen


@kernel(inline='always')
def split(state, n):
    """Split the items 0..n-1 (n < 2**31) into ``state[0]`` equal runs (at least one, at most
    ``len(state) - 1``), set their states and return their number; call it before the
    parallel loop, in the calling thread."""
    nr = max(1, min(state[0], state.shape[0] - 1))
    for r in range(nr):
        state[1 + r] = ((n * (r + 1) // nr) << 32) | (n * r // nr)
    return nr


@kernel(inline='always')
def take(state, r, front):
    """The next item of range r, from its front (its own thread) or its back (another
    thread, whose own range is done); -1 if the range is empty."""
    k = 1 + r
    while True:
        w = atomic_load(state, k)
        f = w & _LOW
        b = w >> 32
        if f >= b:
            return -1
        if front:
            if atomic_cas(state, k, w, (b << 32) | (f + 1)):
                return f
        elif atomic_cas(state, k, w, ((b - 1) << 32) | f):
            return b - 1


@kernel(inline='always')
def claim(state, t, nr, k):
    """The next item for the thread of range t: from the k-th range on, counting from its
    own (k = 0, taken from the front) round the others (taken from the back). Returns
    (item, the k it came from), to pass back in; item -1 when every range is empty."""
    while k < nr:
        c = take(state, (t + k) % nr, k == 0)
        if c >= 0:
            return c, k
        k += 1
    return -1, k


@kernel(inline='always')
def arrive(sync, k, n):
    """Barrier of ``n`` threads inside one parallel region: the k-th time (from 1) a thread
    calls it, it returns once all n have called it k times. ``sync[0]``, zero before the
    region, counts the arrivals (one compare-and-swap each) and never goes back, so no
    sense flag is needed. It is an order of magnitude cheaper than opening a parallel
    region (docs/performance.md). Every one of the n threads must be running at once: the caller's ``prange``
    has exactly as many iterations as the threads numba runs, one per thread, each on a
    CPU of its own (:func:`usable_cpus`)."""
    while True:
        w = atomic_load(sync, 0)
        if atomic_cas(sync, 0, w, w + 1):
            break
    target = k * n
    while atomic_load(sync, 0) < target:
        pass


@functools.lru_cache(maxsize=None)
def usable_cpus() -> int:
    """The CPUs this process can run on at once (read once): its affinity mask, capped by
    a cgroup v2 CPU quota (``/sys/fs/cgroup/cpu.max``, rounded down). A spin barrier
    (:func:`arrive`) is only for threads that each have a CPU of their own: with more
    threads than CPUs a spinning thread holds the CPU that the thread it waits for needs,
    where a parallel region's OpenMP barrier goes to sleep."""
    try:
        n = len(os.sched_getaffinity(0))
    except AttributeError:                      # not on Linux
        n = os.cpu_count() or 1
    try:
        with open('/sys/fs/cgroup/cpu.max') as fh:
            quota, period = fh.read().split()[:2]
        if quota != 'max':
            n = min(n, max(1, int(quota) // int(period)))
    except (OSError, ValueError):
        pass
    return n


@kernel(parallel=True)
def _first_region(a):
    for i in nb.prange(a.shape[0]):
        a[i] = i


def start_threads() -> str:
    """numba's threading layer, which it picks when the process first runs a parallel
    region: one of two iterations is run here if none has run yet."""
    try:
        return nb.threading_layer()
    except ValueError:
        _first_region(np.zeros(2))
        return nb.threading_layer()
