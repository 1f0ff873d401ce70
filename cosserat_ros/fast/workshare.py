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

:func:`arrive` is a barrier on an atomic count, for a region that runs several passes one
after the other (``run_region`` in ``fast/step.py``): its waiters spin a little, then
sleep (Linux futex), so that on a busy machine a waiting thread frees its CPU.
"""
from __future__ import annotations

import functools
import os
import platform
import sys

import numba as nb
import numpy as np
from llvmlite import ir
from numba.core import cgutils, types
from numba.extending import intrinsic

from ..core.compiled import kernel

__all__ = ['split', 'take', 'claim', 'arrive', 'usable_cpus', 'start_threads', 'SPIN']

_LOW = 0xFFFFFFFF

#: Linux's futex system call number on this machine (x86-64: 202, arm64: 98); 0 where there
#: is none (another OS or machine, or a big-endian one: the wait compares the count's low
#: 32 bits, at its address only on a little-endian machine), and :func:`arrive` then spins
_SYS_FUTEX = ({'x86_64': 202, 'AMD64': 202, 'aarch64': 98, 'arm64': 98}.get(platform.machine(), 0)
              if sys.platform.startswith('linux') and sys.byteorder == 'little' else 0)
_FUTEX_WAIT = 128           # FUTEX_WAIT | FUTEX_PRIVATE_FLAG (linux/futex.h)
_FUTEX_WAKE = 129           # FUTEX_WAKE | FUTEX_PRIVATE_FLAG
_WAKE_ALL = 0x7FFFFFFF

#: spins (reads of the count, each with :func:`relax`) a thread waits at :func:`arrive`
#: before it sleeps: a few microseconds, chosen by measurement (docs/performance.md,
#: "Barriers that sleep": no slower alone than spinning longer, fastest beside busy
#: processes)
SPIN = 200


def _check_state(a):
    if not (isinstance(a, types.Array) and a.dtype == types.int64 and a.ndim == 1):
        raise TypeError(f'the work-sharing state must be a 1-D int64 array, got {a}')


def _element_pointer(context, builder, sig, args):
    arr = context.make_array(sig.args[0])(context, builder, args[0])
    return cgutils.get_item_pointer(context, builder, sig.args[0], arr, [args[1]])


def _atomic_load(ordering):
    """The intrinsic ``a[i]`` of an int64 array, read atomically with ``ordering``."""
    def load(typingctx, a, i):
        _check_state(a)

        def codegen(context, builder, sig, args):
            return builder.load_atomic(_element_pointer(context, builder, sig, args),
                                       ordering, 8)
        return types.int64(a, i), codegen
    load.__name__ = f'atomic_load_{ordering}'
    return intrinsic(load)


#: ``a[i]`` of an int64 array, read atomically: acquire (enough for the work sharing),
#: sequentially consistent (the barrier's sleeper handshake, :func:`arrive`)
atomic_load = _atomic_load('acquire')
atomic_load_sc = _atomic_load('seq_cst')


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


@intrinsic
def atomic_add(typingctx, a, i, d):
    """``a[i] += d`` of an int64 array, atomically (sequentially consistent); returns the
    value before."""
    _check_state(a)

    def codegen(context, builder, sig, args):
        return builder.atomic_rmw('add', _element_pointer(context, builder, sig, args),
                                  args[2], 'seq_cst')
    return types.int64(a, i, types.int64), codegen


@intrinsic
def futex(typingctx, a, i, op, val):
    """Linux ``futex(&a[i], op, val, NULL, NULL, 0)`` on the low 32 bits of ``a[i]``
    (int64, little-endian): wait while they hold ``val`` (op :data:`_FUTEX_WAIT`) or wake
    ``val`` waiters (:data:`_FUTEX_WAKE`). Through libc's ``syscall``, which the compiled
    code links to like libm's functions (so the kernel stays cacheable)."""
    _check_state(a)

    def codegen(context, builder, sig, args):
        i64 = ir.IntType(64)
        if not _SYS_FUTEX:              # no futex here: nothing to link to (never called)
            return ir.Constant(i64, -1)
        fn = cgutils.get_or_insert_function(builder.module,
                                            ir.FunctionType(i64, [i64], var_arg=True),
                                            'syscall')
        addr = builder.ptrtoint(_element_pointer(context, builder, sig, args), i64)
        zero = ir.Constant(i64, 0)
        return builder.call(fn, [ir.Constant(i64, _SYS_FUTEX), addr, args[2], args[3],
                                 zero, zero, zero])
    return types.int64(a, i, types.int64, types.int64), codegen


#: the spin-wait hint of this machine's instruction set, an LLVM intrinsic: it lets a
#: waiting thread give way to its core's other hardware thread and saves power (x86
#: ``pause``; Arm ``yield``, hint 1)
_RELAX = {'x86_64': 'llvm.x86.sse2.pause', 'AMD64': 'llvm.x86.sse2.pause',
          'aarch64': 'llvm.aarch64.hint', 'arm64': 'llvm.aarch64.hint'}.get(platform.machine(), '')


@intrinsic
def relax(typingctx):
    """One spin-wait hint (:data:`_RELAX`), nothing where there is none."""
    def codegen(context, builder, sig, args):
        if _RELAX.startswith('llvm.x86'):
            fn = cgutils.get_or_insert_function(builder.module,
                                                ir.FunctionType(ir.VoidType(), []), _RELAX)
            builder.call(fn, [])
        elif _RELAX:
            i32 = ir.IntType(32)
            fn = cgutils.get_or_insert_function(builder.module,
                                                ir.FunctionType(ir.VoidType(), [i32]), _RELAX)
            builder.call(fn, [ir.Constant(i32, 1)])
        return context.get_dummy_value()
    return types.none(), codegen


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
    region, counts the arrivals (one atomic add each) and never goes back, so no sense
    flag is needed. It is an order of magnitude cheaper than opening a parallel region
    (docs/performance.md). Every one of the n threads must be running at once: the
    caller's ``prange`` has exactly as many iterations as the threads numba runs, one per
    thread, each on a CPU of its own (:func:`usable_cpus`).

    A waiting thread spins ``sync[3]`` reads of the count (:data:`SPIN`, set by the
    solver), each with the spin-wait hint (:func:`relax`), then sleeps on a futex of the
    count's low 32 bits, ``sync[2]`` counting the sleepers, until the last arrival wakes
    them (on Linux; elsewhere it spins). Returns how many times the thread slept. Why: on
    a shared machine the thread it waits for may have been taken off its CPU for a time
    slice (ms); a spinning waiter holds its own CPU meanwhile, a sleeping one frees it, and
    the scheduler can run the late thread there (docs/performance.md, "A busy machine"). The
    last arrival adds to the count, then reads the sleepers; a sleeper adds to the sleepers,
    then reads the count, and the futex sleeps only if the count is still what it read: with
    both in one sequentially consistent order, either the sleeper sees the count complete or
    the last arrival sees the sleeper and wakes it, so no wake-up is lost."""
    target = k * n
    spin = sync[3]
    if atomic_add(sync, 0, 1) + 1 >= target:
        if _SYS_FUTEX != 0 and atomic_load_sc(sync, 2) > 0:
            futex(sync, 0, _FUTEX_WAKE, _WAKE_ALL)
        return 0
    spins = 0
    slept = 0
    while True:
        if atomic_load(sync, 0) >= target:
            return slept
        relax()
        spins += 1
        if _SYS_FUTEX != 0 and spins >= spin:
            atomic_add(sync, 2, 1)
            w = atomic_load_sc(sync, 0)
            if w < target:
                futex(sync, 0, _FUTEX_WAIT, w & _LOW)
                slept += 1
            atomic_add(sync, 2, -1)
            spins = 0


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
