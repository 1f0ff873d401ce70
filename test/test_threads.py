"""The step's thread count (cosserat_ros.core.threads): the faster of all threads and one,
measured on a fake clock; trial runs kept short; the trajectory the same to the bit on any
count."""
import math

import numba
import numpy as np
import pytest

from cosserat_ros.core import threads as T
from cosserat_ros.mesh import grid_mesh
from cosserat_ros.simulator import ClothSimulator, Material

needs_two = pytest.mark.skipif(numba.config.NUMBA_NUM_THREADS < 2,
                               reason='numba runs one thread here')


class _Clock:
    def __init__(self):
        self.t = 0.0

    def perf_counter(self):
        return self.t


def _stepper(clock, cost, runs):
    """A fake ``step(m)``: m steps at ``cost[k]`` s each on numba's current count k,
    each call logged as (k, m) in ``runs``."""
    def step(m):
        k = numba.get_num_threads()
        runs.append((k, m))
        clock.t += m * cost[k]
        return m
    return step


@needs_two
def test_run_tuned_takes_the_faster_count_and_keeps_trials_short(monkeypatch):
    """A host where two threads cost 0.3 ms a step alone and 3 ms beside a busy process
    (one thread: 0.5 and 0.6 ms): calls of 500 steps run on the faster count, each trial
    of the other count lasts PROBE_STEPS steps or PROBE_SECONDS, whichever is longer, and
    little more, the choice follows the load both ways, and numba's thread count is what
    it was after every call."""
    clock = _Clock()
    monkeypatch.setattr(T, 'time', clock)
    cost = {2: 0.3e-3, 1: 0.5e-3}
    runs = []
    step = _stepper(clock, cost, runs)
    numba.set_num_threads(2)
    tuner = T.ThreadTuner(2)
    for _ in range(20):
        assert T.run_tuned(tuner, step, 500) == 500
        assert numba.get_num_threads() == 2
    assert tuner.best == 2
    # the trials of one thread: a step where the count changed (untimed), then timed
    # batches until PROBE_SECONDS (more than PROBE_STEPS steps at 0.5 ms), by at most
    # one step more
    trials, k0 = [], None
    for k, m in runs:
        if k == 1:
            if k0 != 1:
                trials.append([])
            trials[-1].append(m)
        k0 = k
    assert trials and all(t[0] == 1 for t in trials)
    for t in trials:
        timed = sum(t[1:]) * cost[1]
        assert T.PROBE_SECONDS <= timed < T.PROBE_SECONDS + 2 * cost[1]
    cost[2], cost[1] = 3e-3, 0.6e-3                    # one busy process beside it
    runs.clear()
    for _ in range(20):
        T.run_tuned(tuner, step, 500)
    assert tuner.best == 1
    # the first call ran on the count that was best; once measured slow, that count
    # runs only trials, at most PROBE_STEPS steps each, one per PROBE_PERIOD
    assert runs[0] == (2, 500)
    twos = [m for k, m in runs[1:] if k == 2]
    t_busy = 19 * 500 * cost[1]
    assert twos and max(twos) <= T.PROBE_STEPS
    # each trial: PROBE_STEPS timed steps, after one untimed step where the count
    # changed (the threading layer resizes its team then)
    trials = [m for k, m in runs[1:] if k == 2 and m > 1]
    assert set(trials) == {T.PROBE_STEPS} and set(twos) == {1, T.PROBE_STEPS}
    assert len(trials) <= t_busy / T.PROBE_PERIOD + 2
    cost[2], cost[1] = 0.3e-3, 0.5e-3                  # the load goes away
    for _ in range(40):
        T.run_tuned(tuner, step, 500)
    assert tuner.best == 2
    # a step that fails part way ends the call with the steps done
    assert T.run_tuned(tuner, lambda m: m - 1, 100) <= 99
    assert numba.get_num_threads() == 2



@needs_two
def test_a_trial_spans_short_calls_and_counts_only_when_whole(monkeypatch):
    """Calls of 5 steps (the bench's warm-up, a node's short ticks) on a host where two
    threads cost 0.07 ms a step and one 0.12 ms, but the first 3 steps on two threads
    after one cost 0.3 ms (its partner wakes from its sleep): a trial cut to one call's 4
    timed steps would read two threads at 0.19 ms and keep one. Summed over calls to
    PROBE_STEPS steps, each trial is whole and two threads win; every step is run once,
    none lost or repeated."""
    clock = _Clock()
    monkeypatch.setattr(T, 'time', clock)
    steady = {2: 0.07e-3, 1: 0.12e-3}
    since = {'k': None, 'steps': 0}
    total = [0]

    def step(m):
        k = numba.get_num_threads()
        if k != since['k']:
            since['k'], since['steps'] = k, 0
        for _ in range(m):
            clock.t += 0.3e-3 if k == 2 and since['steps'] < 3 else steady[k]
            since['steps'] += 1
        total[0] += m
        return m
    numba.set_num_threads(2)
    tuner = T.ThreadTuner(2)
    calls = 0
    while clock.t < 0.3:                    # within one PROBE_PERIOD: no probe yet
        assert T.run_tuned(tuner, step, 5) == 5
        calls += 1
    assert total[0] == 5 * calls
    assert tuner.cost[1] is not None and tuner.best == 2
    assert tuner.cost[2] < tuner.cost[1]


@needs_two
def test_calls_of_another_length_have_the_counts_compared_again(monkeypatch):
    """Two threads pay 2 ms per parallel region (a call, or a batch of one) and 0.15 ms a
    step, one thread 0.26 ms a step: over calls of 5 steps one thread is the faster, over
    calls of 400 two. After 0.3 s of short calls the tuner keeps one; the first long call
    has the counts compared again (well within PROBE_PERIOD), and the long calls after it
    run on two threads."""
    clock = _Clock()
    monkeypatch.setattr(T, 'time', clock)
    runs = []

    def step(m):
        k = numba.get_num_threads()
        runs.append((k, m))
        clock.t += (2e-3 + 0.15e-3 * m) if k == 2 else 0.26e-3 * m
        return m
    numba.set_num_threads(2)
    tuner = T.ThreadTuner(2)
    while clock.t < 0.3:
        T.run_tuned(tuner, step, 5)
    assert tuner.best == 1
    start = clock.t
    T.run_tuned(tuner, step, 400)
    assert tuner.best == 2
    runs.clear()
    for _ in range(4):
        assert T.run_tuned(tuner, step, 400) == 400
    assert runs == [(2, 400)] * 4 and clock.t - start < T.PROBE_PERIOD


@needs_two
def test_a_trial_of_long_steps_ends_at_probe_enough(monkeypatch):
    """The implicit solver's steps: 17 ms on two threads, 26 ms on one, in calls of one
    step (the bench's window) and of 100. Each trial of one thread ends once PROBE_ENOUGH
    of wall time is timed, well before PROBE_STEPS steps (2 steps of 26 ms, after the
    untimed one where the count changed), so that over 4 s of calls one thread ran 3
    steps in each trial: the first compare and one per PROBE_PERIOD. The choice is two
    threads."""
    clock = _Clock()
    monkeypatch.setattr(T, 'time', clock)
    cost = {2: 17e-3, 1: 26e-3}
    runs = []
    step = _stepper(clock, cost, runs)
    numba.set_num_threads(2)
    for n in (1, 100):
        clock.t = 0.0
        runs.clear()
        tuner = T.ThreadTuner(2)
        while clock.t < 4.0:
            assert T.run_tuned(tuner, step, n) == n
        assert tuner.best == 2
        ones = sum(m for k, m in runs if k == 1)
        timed = math.ceil(T.PROBE_ENOUGH / cost[1])
        assert timed < T.PROBE_STEPS
        assert 0 < ones <= (1 + timed) * (clock.t / T.PROBE_PERIOD + 1)


@needs_two
def test_one_stalled_call_does_not_switch_the_count(monkeypatch):
    """Calls of 5 steps, two threads 0.06 ms a step and one 0.07 ms, and one call in 40
    on two threads stalls 0.35 ms (its region waking a parked thread). Within one
    PROBE_PERIOD, one thread runs only its trial: a stalled call's 0.13 ms a step, read
    alone, would switch the count until the next probe."""
    clock = _Clock()
    monkeypatch.setattr(T, 'time', clock)
    calls = [0]
    ones = [0]

    def step(m):
        k = numba.get_num_threads()
        if k == 1:
            ones[0] += m
            clock.t += 0.07e-3 * m
        else:
            calls[0] += 1
            clock.t += 0.06e-3 * m + (0.35e-3 if calls[0] % 40 == 0 else 0.0)
        return m
    numba.set_num_threads(2)
    tuner = T.ThreadTuner(2)
    while clock.t < 0.9 * T.PROBE_PERIOD:
        assert T.run_tuned(tuner, step, 5) == 5
    assert tuner.best == 2
    trial = math.ceil(T.PROBE_SECONDS / 0.07e-3) + 5
    assert 0 < ones[0] <= trial


def _sim():
    sim = ClothSimulator(grid_mesh(12, 12), Material(zeta=50.0, xi=2e-5, phi=1e-6,
                                                     density=0.2, damping=0.1), dt=2e-4)
    sim.pin([0, 12])
    sim.gravity = (0.0, 0.0, -9.81)
    return sim


@needs_two
def test_the_trajectory_is_the_same_to_the_bit_on_any_thread_count():
    out = []
    for threads in ('auto', 1, 2):
        sim = _sim()
        sim.threads = threads
        for k in (1, 7, 300, 45):
            sim.step(k)
        out.append(sim.positions.copy())
    for x in out[1:]:
        assert np.array_equal(x, out[0])


def test_a_bad_thread_count_is_refused():
    sim = _sim()
    for bad in (0, -1, True, 1.5, 'two', numba.config.NUMBA_NUM_THREADS + 1):
        with pytest.raises(ValueError, match='threads must be'):
            sim.threads = bad
    assert sim.threads == 'auto'
