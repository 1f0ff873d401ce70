"""How many threads the compiled step runs on: all of numba's or one, whichever the
measured cost per step says is faster, measured again as the load changes.

Why: the parallel step (``fast/step.py``, one parallel region per call) meets its threads
at a barrier a few times per step. On a shared machine the OS takes one of them off its
CPU for a time slice now and then, and the others wait at the barrier until it comes back
(they sleep after a short spin, ``fast/workshare.arrive``, so they no longer burn the CPU
the busy process shares), while one thread waits for nobody. Which count is faster
depends on the load and changes from run to run (docs/performance.md, "A busy machine"),
so it is measured, not guessed: :class:`ThreadTuner` runs each count once, then the faster,
and the other once every :data:`PROBE_PERIOD` s of wall time, so the choice follows the load
both ways. A measuring call runs at most :data:`PROBE_STEPS` steps at the count on trial
(the rest of the call at the best), so that trying a count that has become slow costs
little.

Every thread count gives the same numbers to the bit (``fast/workshare.py``), so the
choice changes the speed only, never the trajectory.
"""
from __future__ import annotations

import time
from typing import Callable, Optional, Tuple

import numba

__all__ = ['ThreadTuner', 'PROBE_PERIOD', 'PROBE_STEPS', 'run_tuned']

#: [s] wall time between two measurements of the count not in use
PROBE_PERIOD = 2.0
#: the most steps a call runs at a count on trial
PROBE_STEPS = 20


class ThreadTuner:
    """The thread count for the next steps: ``most`` or 1, the one with the lower measured
    cost per step (module docstring). :meth:`threads` says which count to run (and
    :meth:`plan` for how many steps at most), :meth:`record` takes what they cost."""

    def __init__(self, most: int, period: float = PROBE_PERIOD):
        self.most = most
        self.choices = (most, 1) if most > 1 else (1,)
        self.cost = {k: None for k in self.choices}      # [s] per step, latest
        self.period = period
        self._probe_at: Optional[float] = None
        self.last: Optional[int] = None                   # the count the last steps ran on

    @property
    def best(self) -> int:
        known = [k for k in self.choices if self.cost[k] is not None]
        return min(known, key=lambda k: self.cost[k]) if known else self.choices[0]

    def threads(self, now: float) -> int:
        """The count to run at wall time ``now`` [s]: each count once first, then the
        faster, and the other once every ``period``."""
        if len(self.choices) == 1:
            return 1
        for k in self.choices:
            if self.cost[k] is None:
                return k
        if self._probe_at is None:
            self._probe_at = now + self.period
        if now >= self._probe_at:
            self._probe_at = now + self.period
            return next(k for k in self.choices if k != self.best)
        return self.best

    def plan(self, now: float) -> Tuple[int, Optional[int]]:
        """(count, the most steps to run at it: :data:`PROBE_STEPS` while it is on trial,
        None when it is the best)."""
        k = self.threads(now)
        trial = len(self.choices) > 1 and (self.cost[k] is None or k != self.best)
        return k, (PROBE_STEPS if trial else None)

    def record(self, threads: int, steps: int, seconds: float) -> None:
        """``steps`` steps on ``threads`` threads took ``seconds`` of wall time."""
        if steps > 0 and threads in self.cost:
            self.cost[threads] = seconds / steps


def run_tuned(tuner: ThreadTuner, step: Callable[[int], int], n: int) -> int:
    """``step(k)`` (returns the steps done, fewer on a failure) over ``n`` steps, each
    batch on the count ``tuner`` plans, numba's thread count restored afterwards. Returns
    the steps done. The first step after a change of count is not timed: the threading
    layer resizes its team of threads then (measured here: a 20-step trial on 2 threads
    right after 1 read 30% slower than the same steps later, and the tuner kept the slower
    count on a quiet machine). A trial of one count is followed by a trial of the other,
    of the same length and also right after its change of count, so that the two are
    compared alike: a short trial of all threads right after their partners were parked
    reads slower than their long-run cost (N = 40: 0.35-0.49 against 0.28 ms a step), and
    against one thread's long-run cost it kept one thread on a quiet machine, at 0.46 ms
    (docs/performance.md, "make bench against 30fd1ab")."""
    was = numba.get_num_threads()
    done = 0
    retrial: Optional[int] = None
    try:
        while done < n:
            if retrial is not None:         # the count a trial is compared with, alike
                k, most, paired, retrial = retrial, PROBE_STEPS, True, None
            else:
                k, most = tuner.plan(time.perf_counter())
                paired = False
            m = n - done if most is None else min(most, n - done)
            numba.set_num_threads(k)
            if k != tuner.last and m > 1:
                tuner.last = k
                got = step(1)                       # the change of count, untimed
                done += got
                m -= 1
                if got < 1:
                    break
            tuner.last = k
            t0 = time.perf_counter()
            got = step(m)
            tuner.record(k, got, time.perf_counter() - t0)
            done += got
            if got < m:
                break
            if most is not None and not paired:
                other = [c for c in tuner.choices if c != k]
                if other and tuner.cost[other[0]] is not None:
                    retrial = other[0]
    finally:
        numba.set_num_threads(was)
    return done
