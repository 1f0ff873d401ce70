"""How many steps a tick takes, and in what batches, so that sim time keeps wall time.

:class:`Pacer` holds the pacing state of the node's timer; it calls nothing but the step
function it is given and ``time.perf_counter``, so tests drive it on a fake clock
(``monkeypatch.setattr(pacing, 'time', fake)``).

Per tick:

* :meth:`Pacer.wanted`: the wall time since the last tick (at most 4 periods) plus what
  earlier ticks fell short by, in whole steps (at least one);
* :meth:`Pacer.advance`: the steps end where the timer's next call is due, less the
  publishing that follows them (its cost smoothed over ticks) and :data:`TICK_MARGIN`;
  never less than a third of the period. The first batch takes at most 3/4 of what the
  smoothed step cost says fits; the rest is sized on that batch's own cost, measured in
  this tick, so a host that slows down between ticks does not push the tick past its
  period;
* :meth:`Pacer.carry`: what the tick still owes is carried to the next: the rounding to
  whole steps (a period of 199.6 steps, rounded alone, gains 0.2%) and what a tick that
  could not keep up fell short by, at most one period of it, so a host that is slow for
  a moment catches up and one that is always too slow does not pile up a debt.

:class:`ThreadTuner` picks the thread count of each tick's steps: all of numba's threads
or one, whichever its measured cost per step says is faster. On a shared machine a thread
of the parallel step that the OS takes off its CPU holds the others at the next barrier
(the one-region step waits for every thread a few times per step), and the step that ran
0.29 ms alone took 30 ms beside one busy process; one thread then does better. Each count
is measured again every :data:`PROBE_PERIOD` s (one tick at the other count), so the
choice follows the load both ways.
"""
from __future__ import annotations

import time
from typing import Callable, Optional

__all__ = ['Pacer', 'TICK_MARGIN', 'ThreadTuner', 'PROBE_PERIOD']

#: [s] what each tick leaves free before the next is due, beyond its publishing: the
#: executor's latency and the scatter of the publish cost
TICK_MARGIN = 0.5e-3
#: [s] wall time between two ticks that measure the thread count not in use
PROBE_PERIOD = 2.0


class Pacer:
    """The pacing state of a timer of period ``period`` [s] (module docstring)."""

    def __init__(self, period: float):
        self.period = period
        self.step_cost = 0.0        # smoothed seconds per step
        self.publish_cost = 0.0     # smoothed seconds per publish
        self.last_tick: Optional[float] = None
        self.owed = 0.0             # sim seconds the ticks so far fell short of wall time
        self.lagging = False

    def restart(self) -> None:
        """Forget the last tick (start, reset, pause): the next tick owes one period."""
        self.last_tick = None
        self.owed = 0.0

    def wanted(self, now: float, dt: float) -> int:
        """The steps of size ``dt`` this tick owes at wall time ``now`` [s]."""
        if self.last_tick is None:
            elapsed, owed = self.period, 0.0
        else:
            elapsed, owed = now - self.last_tick, self.owed
        self._owed = owed + min(elapsed, 4 * self.period)
        return max(1, int(round(self._owed / dt)))

    def carry(self, done: int, wanted: int, dt: float, now: float) -> None:
        """After a tick that took ``done`` of its ``wanted`` steps: owe the rest, at most
        one period."""
        self.lagging = done < wanted
        self.owed = min(self._owed - done * dt, self.period)
        self.last_tick = now

    def advance(self, step: Callable[[int], bool], wanted: int,
                left: Optional[float]) -> int:
        """Run ``step(k)`` in batches up to ``wanted`` steps within the time ``left`` [s]
        until the timer's next call (None: a period); ``step`` returns False to stop
        (a divergence). Returns the steps taken."""
        left = self.period if left is None else left
        end = time.perf_counter() + max(self.period / 3,
                                        left - self.publish_cost - TICK_MARGIN)
        done, cost = 0, self.step_cost
        while done < wanted:
            if cost <= 0:
                n = 1                                    # no estimate yet: one step
            else:
                fit = (end - time.perf_counter()) / cost
                n = min(wanted - done, int(0.75 * fit if done == 0 else fit))
                if n <= 0:
                    if done:
                        break
                    n = 1                                # every tick takes a step
            t0 = time.perf_counter()
            if not step(n):
                break
            cost = (time.perf_counter() - t0) / n
            self.step_cost = cost if self.step_cost == 0 else (
                0.8 * self.step_cost + 0.2 * cost)
            done += n
        return done

    def note_publish(self, cost: float) -> None:
        """Smooth the publish cost [s] of a tick."""
        self.publish_cost = cost if self.publish_cost == 0 else (
            0.8 * self.publish_cost + 0.2 * cost)


class ThreadTuner:
    """The thread count for the next tick's steps: ``most`` or 1, the one with the lower
    measured cost per step (module docstring). :meth:`threads` says which count to run,
    :meth:`record` takes what the tick's steps cost."""

    def __init__(self, most: int, period: float = PROBE_PERIOD):
        self.choices = (most, 1) if most > 1 else (1,)
        self.cost = {k: None for k in self.choices}      # [s] per step, latest
        self.period = period
        self._probe_at: Optional[float] = None

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

    def record(self, threads: int, steps: int, seconds: float) -> None:
        """``steps`` steps on ``threads`` threads took ``seconds`` of wall time."""
        if steps > 0 and threads in self.cost:
            self.cost[threads] = seconds / steps
