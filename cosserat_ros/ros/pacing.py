"""How many steps a tick takes, and in what batches, so that sim time keeps wall time.

:class:`Pacer` holds the pacing state of the node's timer; it calls nothing but the step
function it is given and ``time.perf_counter``, so tests drive it on a fake clock
(``monkeypatch.setattr(pacing, 'time', fake)``).

Per tick:

* :meth:`Pacer.wanted`: the wall time since the last tick (at most 4 periods) times the
  real-time factor asked for (:attr:`Pacer.factor`, sim seconds per wall second) plus
  what earlier ticks fell short by, in whole steps (none when that rounds to zero: a
  step longer than the period, or a small factor, takes a step every few ticks);
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

The thread count of the steps is the simulator's own choice
(:mod:`cosserat_ros.core.threads`, re-exported here).
"""
from __future__ import annotations

import time
from typing import Callable, Optional

from ..core.threads import PROBE_PERIOD, ThreadTuner

__all__ = ['Pacer', 'TICK_MARGIN', 'ThreadTuner', 'PROBE_PERIOD']

#: [s] what each tick leaves free before the next is due, beyond its publishing: the
#: executor's latency and the scatter of the publish cost
TICK_MARGIN = 0.5e-3


class Pacer:
    """The pacing state of a timer of period ``period`` [s] (module docstring)."""

    def __init__(self, period: float, factor: float = 1.0):
        self.period = period
        self.factor = factor        # sim seconds asked for per wall second
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
        self._owed = owed + self.factor * min(elapsed, 4 * self.period)
        return max(0, int(round(self._owed / dt)))

    def carry(self, done: int, wanted: int, dt: float, now: float) -> None:
        """After a tick that took ``done`` of its ``wanted`` steps: owe the rest, at most
        one period's worth (or one step, if longer)."""
        self.lagging = done < wanted
        self.owed = min(self._owed - done * dt, max(self.factor * self.period, dt))
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
