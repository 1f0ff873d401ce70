"""How many threads the compiled step runs on: all of numba's or one, whichever the
measured cost per step says is faster, measured again as the load changes.

Why: the parallel step (``fast/step.py``, one parallel region per call) meets its threads
at a barrier a few times per step. On a shared machine the OS takes one of them off its
CPU for a time slice now and then, and the others wait at the barrier until it comes back
(they sleep after a short spin, ``fast/workshare.arrive``, so they no longer burn the CPU
the busy process shares), while one thread waits for nobody. Which count is faster
depends on the load and changes from run to run (docs/performance.md, "A busy machine"),
so it is measured, not guessed: :class:`ThreadTuner` runs each count once, then the
faster, and the other once every :data:`PROBE_PERIOD` s of wall time, so the choice
follows the load both ways. A trial is at least :data:`PROBE_STEPS` timed steps and
:data:`PROBE_SECONDS` of wall time at the count on trial, over one call or several (the
rest of a call at the best), or :data:`PROBE_ENOUGH` s of fewer steps when steps are
long, so that trying a count that has become slow costs little (a share of about
``PROBE_SECONDS / PROBE_PERIOD`` of the time, at most about ``PROBE_ENOUGH /
PROBE_PERIOD``). Calls much longer or shorter than the ones the counts were compared in
have them compared again (:data:`CALL_RATIO`).

Every thread count gives the same numbers to the bit (``fast/workshare.py``), so the
choice changes the speed only, never the trajectory.
"""
from __future__ import annotations

import math
import time
from dataclasses import dataclass
from typing import Callable, Optional, Tuple

import numba

__all__ = ['ThreadTuner', 'PROBE_PERIOD', 'PROBE_STEPS', 'PROBE_SECONDS', 'PROBE_ENOUGH',
           'CALL_RATIO', 'run_tuned']

#: [s] wall time between two measurements of the count not in use
PROBE_PERIOD = 2.0
#: the fewest timed steps of a trial of one count
PROBE_STEPS = 20
#: [s] the least timed wall time of a trial of one count: a trial of a few steps is a
#: few ms, as short as a stall of a thread the OS or the hypervisor takes off its CPU
#: (docs/performance.md, "Trials over calls"), which would stand for the count's cost
PROBE_SECONDS = 0.03
#: [s] a trial this long is whole with fewer than PROBE_STEPS steps: at the implicit
#: solver's 5-30 ms steps, 20 of the slower count every PROBE_PERIOD cost 5-10% of the
#: time, and 20 of the 120 steps of the bench's window (docs/performance.md, "Trials of
#: long steps")
PROBE_ENOUGH = 0.05
#: a call this many times longer, or shorter, than the one the counts were last compared
#: in has them compared again at once (at most once per PROBE_PERIOD): all threads pay for
#: opening a parallel region per call (waking the pool's other threads: a 4-5 ms stall
#: now and then on a virtual machine), which calls of a few steps feel and long ones do
#: not, so the faster count depends on the calls' length (the same section)
CALL_RATIO = 8


@dataclass
class _Trial:
    """A trial under way: its count, whether it answers a trial of the other count, and
    its timed steps and their wall time [s] so far."""
    count: int
    paired: bool
    steps: int = 0
    seconds: float = 0.0

    def add(self, steps: int, seconds: float) -> bool:
        """Adds ``steps`` that took ``seconds``; whether the steps so far are enough to
        stand for the count's cost: PROBE_STEPS steps and PROBE_SECONDS, or PROBE_ENOUGH
        of fewer."""
        self.steps += steps
        self.seconds += seconds
        return self.seconds >= PROBE_SECONDS and (self.steps >= PROBE_STEPS
                                                  or self.seconds >= PROBE_ENOUGH)


class ThreadTuner:
    """The thread count for the next steps: ``most`` or 1, the one with the lower measured
    cost per step (module docstring). :meth:`plan` says which count to run and for how
    many steps at most, :meth:`record` takes what they cost.

    A trial is at least :data:`PROBE_STEPS` timed steps and :data:`PROBE_SECONDS` of one
    count (or :data:`PROBE_ENOUGH` of fewer, long steps), summed over as many calls as it
    takes, and counts only once whole: a trial of all threads in calls of a few steps
    (the bench's warm-up, a node's short ticks) would otherwise be cut short, and its few
    steps right after the change of count, the dearest, would stand for that count's
    cost. A trial of one count is followed by a trial of the other (:func:`run_tuned`).
    The steps at the best between trials set its cost the same way, once as many."""

    def __init__(self, most: int, period: float = PROBE_PERIOD):
        self.most = most
        self.choices = (most, 1) if most > 1 else (1,)
        self.cost = {k: None for k in self.choices}      # [s] per step, latest whole
        self.period = period
        self._probe_at: Optional[float] = None
        self.last: Optional[int] = None                   # the count the last steps ran on
        self._trial: Optional[_Trial] = None              # the trial under way
        self._window: Optional[_Trial] = None             # the best's steps since its cost
        self._call_n = 0                                  # the steps of the call under way
        self._measured_n: Optional[int] = None            # ... of the one the last trial ended in
        self._recall_at = -math.inf                       # the earliest re-comparison by length

    @property
    def best(self) -> int:
        known = [k for k in self.choices if self.cost[k] is not None]
        return min(known, key=lambda k: self.cost[k]) if known else self.choices[0]

    def threads(self, now: float) -> int:
        """The count to run at wall time ``now`` [s]: a trial under way first, then each
        count once, then the faster, and the other once every ``period``."""
        if len(self.choices) == 1:
            return 1
        if self._trial is not None:
            return self._trial.count
        for k in self.choices:
            if self.cost[k] is None:
                return k
        if self._probe_at is None:
            self._probe_at = now + self.period
        if now >= self._probe_at:
            self._probe_at = now + self.period
            return next(k for k in self.choices if k != self.best)
        return self.best

    def call(self, n: int, now: float) -> None:
        """A call of ``n`` steps starts at wall time ``now``: one :data:`CALL_RATIO` times
        longer or shorter than the call the last trial ended in has the counts compared
        again now (at most once per ``period``)."""
        self._call_n = n
        m = self._measured_n
        if (self._trial is None and m is not None and now >= self._recall_at
                and (n >= CALL_RATIO * m or CALL_RATIO * n <= m)):
            self._recall_at = now + self.period
            self._probe_at = now

    def plan(self, now: float) -> Tuple[int, Optional[int]]:
        """(count, the most timed steps to run at it: what its trial still lacks while it
        is on trial, by its steps so far and their cost, None when it is the best)."""
        k = self.threads(now)
        if self._trial is None and len(self.choices) > 1 and (
                self.cost[k] is None or k != self.best):
            self._trial = _Trial(k, paired=False)
        if self._trial is None:
            return k, None
        steps, seconds = self._trial.steps, self._trial.seconds
        if steps == 0 or seconds <= 0.0:
            # its first batch, before any of its steps was timed: as many as the fastest
            # known cost says fill PROBE_ENOUGH, at most PROBE_STEPS (a count that has
            # become slow runs no longer than PROBE_STEPS of its own)
            known = [c for c in self.cost.values() if c is not None and c > 0.0]
            if not known:
                return k, PROBE_STEPS
            return k, max(min(PROBE_STEPS, math.ceil(PROBE_ENOUGH / min(known))), 1)
        per = seconds / steps
        short = max(PROBE_STEPS - steps, math.ceil((PROBE_SECONDS - seconds) / per))
        return k, max(min(short, math.ceil((PROBE_ENOUGH - seconds) / per)), 1)

    def record(self, threads: int, steps: int, seconds: float) -> None:
        """``steps`` timed steps on ``threads`` threads took ``seconds`` of wall time. A
        trial's steps are summed until it is whole; it then sets its count's cost, and a
        trial that answered none starts one of the other count, so that the two compare
        alike. Steps outside a trial are summed the same way before they set their
        count's cost."""
        trial = self._trial
        if trial is None or trial.count != threads:
            # steps at the best, outside a trial: summed as a trial is, so that one short
            # call that stalled (a 5-step call at 0.65 ms instead of 0.3) does not stand
            # for the count's cost and switch it
            if threads not in self.cost:
                return
            if self._window is None or self._window.count != threads:
                self._window = _Trial(threads, paired=False)
            w = self._window
            if w.add(steps, seconds):
                self.cost[threads] = w.seconds / w.steps
                self._window = None
            return
        self._window = None
        if not trial.add(steps, seconds):
            return
        self.cost[threads] = trial.seconds / trial.steps
        self._trial = None
        self._measured_n = self._call_n
        other = [c for c in self.choices if c != threads]
        if not trial.paired and other and self.cost[other[0]] is not None:
            self._trial = _Trial(other[0], paired=True)


def run_tuned(tuner: ThreadTuner, step: Callable[[int], int], n: int) -> int:
    """``step(k)`` (returns the steps done, fewer on a failure) over ``n`` steps, each
    batch on the count ``tuner`` plans, numba's thread count restored afterwards. Returns
    the steps done. The first step after a change of count is not timed: the threading
    layer resizes its team of threads then. A trial of one count is followed by a trial
    of the other, as long and also right after its change of count, so that the two are
    compared alike: a trial of all threads right after their partners were parked reads
    slower than their long-run cost, and compared with one thread's long-run cost it kept
    one thread on a quiet machine (docs/performance.md, "make bench against 30fd1ab")."""
    was = numba.get_num_threads()
    done = 0
    tuner.call(n, time.perf_counter())
    try:
        while done < n:
            k, most = tuner.plan(time.perf_counter())
            numba.set_num_threads(k)
            if k != tuner.last:
                tuner.last = k
                got = step(1)                       # the change of count, untimed
                done += got
                if got < 1:
                    break
                continue
            m = n - done if most is None else min(most, n - done)
            t0 = time.perf_counter()
            got = step(m)
            tuner.record(k, got, time.perf_counter() - t0)
            done += got
            if got < m:
                break
    finally:
        numba.set_num_threads(was)
    return done
