"""What acts around the solver's calls of a step: moving obstacles, grasp handles, the
corners and edges of obstacles, and self-collision, each a pass of one small protocol
that :meth:`.simulator.ClothSimulator.step` loops over.

A call of :meth:`~.simulator.ClothSimulator.step` (``n`` steps) runs the solver in calls
of ``k <= n`` steps. Around each call, every active pass, in the order of
:func:`step_passes` (rigid obstacles first, the cloth's own contact after them, the
handles last):

* ``limit(k, t, overran)``: the most steps the next call may take from sim time ``t``
  (a moving obstacle: a quarter of the contact thickness per call; a handle: up to its
  next waypoint; contact: one while a pair is near, else the steps no pair can come
  near in), and what the call needs set up (a handle's prescribed velocity);
  ``overran``: the last call was undone;
* ``needs_start(k)``: whether the state where the call begins must be kept, to step
  again from it if the call ``overran``;
* after a call of all its ``k`` steps: ``overran(start, k)``, whether it went further
  than its limit allowed (then the state goes back to ``start`` and the call is done
  again, one step at a time, in the passes' order: the first that says so decides);
  then ``answer(k)`` in the reverse order, so that the first passes, the rigid ones,
  have the last word: the response, in place, returning the energy it removed [J]
  (non-finite: the step diverged; None: it had nothing to answer); and ``follow()``,
  the state having changed under it;
* ``end_call(got, k, t_end)``: the call is over, ``got`` of its ``k`` steps done (fewer:
  it diverged), at sim time ``t_end`` if all were (settle a handle's pose, move an
  obstacle, drop the vertices that slipped out of a handle).

``finish(t)`` after the last call, at sim time ``t`` (a handle at rest keeps no
prescribed velocity). ``snapshot()`` / ``restore(snap)`` before and after a failed
:meth:`step`: the state and every pass go back to where the call began (a pass whose
data is a cache of the state, validated against it each step, keeps nothing).
``start()`` at the beginning of every :meth:`step`, active or not.

This module imports no ROS package.
"""
from __future__ import annotations

import math
from typing import Optional

__all__ = ['StepPass', 'ObstacleMotion', 'FeaturePass', 'SelfPass', 'HandlePass',
           'step_passes', 'run_calls']


class StepPass:
    """A pass of the step pipeline (module docstring): the defaults do nothing."""

    def __init__(self, sim):
        self.sim = sim

    def active(self) -> bool:
        return False

    def start(self) -> None:
        pass

    def snapshot(self):
        return None

    def restore(self, snap) -> None:
        pass

    def limit(self, k: int, t: float, overran: bool) -> int:
        return k

    def needs_start(self, k: int) -> bool:
        return False

    def overran(self, start, k: int) -> bool:
        return False

    def answer(self, k: int) -> Optional[float]:
        return None

    def follow(self) -> None:
        pass

    def end_call(self, got: int, k: int, t_end: float) -> None:
        pass

    def finish(self, t: float) -> None:
        pass


class ObstacleMotion(StepPass):
    """Moving obstacles (:mod:`.obstacles`): a pose per call, each call short enough that
    they move at most a quarter of the contact thickness; their poses are what a failed
    step puts back."""

    def active(self) -> bool:
        sim = self.sim
        self.cap = sim._obstacles.max_steps(sim.dt, sim.contact_thickness)
        return self.cap > 0

    def snapshot(self):
        return self.sim._obstacles.poses()

    def restore(self, poses) -> None:
        self.sim._obstacles.restore(poses)
        self.sim._sync_obstacles()

    def limit(self, k: int, t: float, overran: bool) -> int:
        return min(self.cap, k)

    def end_call(self, got: int, k: int, t_end: float) -> None:
        if got == k:
            self.sim._obstacles.advance(k * self.sim.dt)
            self.sim._sync_obstacles()


class FeaturePass(StepPass):
    """The corners and edges of boxes, cylinders and meshes (:mod:`.features`): a
    response after each step while the cloth can reach them; until then calls that
    cannot, each checked afterwards (``overran``)."""

    def active(self) -> bool:
        return self.sim._features.present(self.sim.control)

    def start(self) -> None:
        self.sim._features.start()
        self.near = False
        self.answered = False

    def limit(self, k: int, t: float, overran: bool) -> int:
        sim, f = self.sim, self.sim._features
        free = 0 if overran else f.free_steps(sim.state.x, sim.state.v, sim.control, sim.dt)
        self.near = free < 2
        if self.near:
            f.begin(sim.state.x, sim.state.v)
            return 1
        return min(k, free)

    def needs_start(self, k: int) -> bool:
        return not self.near

    def overran(self, start, k: int) -> bool:
        sim = self.sim
        return not self.near and sim._features.overran(start.x, sim.state.x, sim.control,
                                                       sim.dt, k)

    def answer(self, k: int) -> Optional[float]:
        if not self.near:
            return None
        self.answered = True
        sim = self.sim
        return sim._features.after_step(sim.state, sim.control, sim.coefficients, sim.dt)

    def end_call(self, got: int, k: int, t_end: float) -> None:
        if not self.answered:
            self.sim._features.steps += got        # steps without a feature's force
        self.answered = False


class SelfPass(StepPass):
    """Self-collision (:mod:`.self_contact`): a response after every step while pairs
    are near, calls of several steps while none can come near, each checked afterwards
    (``overran``). Its candidate list is a cache of the state, checked every step: a
    failed step leaves it as it is."""

    def active(self) -> bool:
        return self.sim._self_on

    def start(self) -> None:
        if self.sim._self_on:
            self.sim._self.begin(self.sim.state.x, self.sim.state.v)

    def limit(self, k: int, t: float, overran: bool) -> int:
        sim = self.sim
        free = 0 if overran else sim._self.free_steps(sim.state.x, sim.state.v,
                                                      sim.contact_thickness, sim.dt)
        return min(k, max(1, free))

    def needs_start(self, k: int) -> bool:
        return k > 1

    def overran(self, start, k: int) -> bool:
        return k > 1 and self.sim._self.overran(start.x, self.sim.state.x, k, self.sim.dt)

    def answer(self, k: int) -> Optional[float]:
        if k > 1:
            return None                             # no pair came near in the call
        sim = self.sim
        return sim._self.after_step(sim.state, sim.control, sim.coefficients, sim.dt)

    def follow(self) -> None:
        # the next step starts where the call (and any later answer) left the cloth
        self.sim._self.begin(self.sim.state.x, self.sim.state.v)


class HandlePass(StepPass):
    """Grasp handles (:mod:`.handles`): a prescribed velocity per call that ends it on
    their path, their poses settled after it, and the vertices pulled harder than their
    share of a break force dropped; their poses, paths and held vertices are what a failed
    step puts back."""

    def active(self) -> bool:
        return len(self.sim._handles) > 0

    def snapshot(self):
        return self.sim._handles.snapshot(), self.sim.control.pin_velocity.copy()

    def restore(self, snap) -> None:
        self.sim._handles.restore_snapshot(snap[0])
        self.sim._sync_pins()
        self.sim.control.pin_velocity[:] = snap[1]

    def limit(self, k: int, t: float, overran: bool) -> int:
        sim, h = self.sim, self.sim._handles
        if len(h):
            k = h.plan(t, sim.dt, k)
        h.prescribe(sim.state.x, t, sim.dt, k, sim.control.pin_velocity)
        return k

    def end_call(self, got: int, k: int, t_end: float) -> None:
        if got != k:
            return
        h = self.sim._handles
        h.settle(t_end)
        if len(h) and len(h.broken(self.sim.control.reaction)):
            self.sim._sync_pins()

    def finish(self, t: float) -> None:
        if not self.sim._handles.moving(t):
            self.sim.control.pin_velocity[:] = 0.0  # at rest after the call: no motion left


def step_passes(sim) -> list:
    """The passes of simulator ``sim``, in the pipeline's order (module docstring)."""
    return [ObstacleMotion(sim), FeaturePass(sim), SelfPass(sim), HandlePass(sim)]


def run_calls(sim, passes, n: int) -> int:
    """``n`` steps of ``sim`` as calls of its solver with the active ``passes`` around
    each (module docstring); the steps done (fewer: a divergence, which the caller
    rolls back)."""
    start = None                                    # what an overrun call goes back to
    answering = passes[::-1]
    overran = False
    done = 0
    while done < n:
        t = sim.time + done * sim.dt
        k = n - done
        for p in passes:
            k = p.limit(k, t, overran)
        if any(p.needs_start(k) for p in passes):
            if start is None:
                start = sim.state.copy()
            else:
                start.assign(sim.state)
        overran = False
        got = sim._solve(k)
        if got == k and any(p.overran(start, k) for p in passes):
            sim.state.assign(start)                 # again, one step per call
            overran = True
            continue
        if got == k:
            for p in answering:
                removed = p.answer(k)
                if removed is None:
                    continue
                if not math.isfinite(removed):
                    got = 0                         # a non-finite response: it diverged
                    break
                sim.state.acc[1] += removed
            else:
                for p in passes:
                    p.follow()
        for p in passes:
            p.end_call(got, k, t + k * sim.dt)
        done += got
        if got < k:
            break
    for p in passes:
        p.finish(sim.time + done * sim.dt)
    return done
