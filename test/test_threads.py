"""The step's thread count (cosserat_ros.core.threads): the faster of all threads and one,
measured on a fake clock; trial runs kept short; the trajectory the same to the bit on any
count."""
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


@needs_two
def test_run_tuned_takes_the_faster_count_and_keeps_trials_short(monkeypatch):
    """A host where two threads cost 0.3 ms a step alone and 3 ms beside a busy process
    (one thread: 0.5 and 0.6 ms): calls of 500 steps run on the faster count, each trial
    of the other count is at most PROBE_STEPS steps, the choice follows the load both
    ways, and numba's thread count is what it was after every call."""
    clock = _Clock()
    monkeypatch.setattr(T, 'time', clock)
    cost = {2: 0.3e-3, 1: 0.5e-3}
    runs = []

    def step(m):
        k = numba.get_num_threads()
        runs.append((k, m))
        clock.t += m * cost[k]
        return m
    numba.set_num_threads(2)
    tuner = T.ThreadTuner(2)
    for _ in range(20):
        assert T.run_tuned(tuner, step, 500) == 500
        assert numba.get_num_threads() == 2
    assert tuner.best == 2
    ones = [m for k, m in runs if k == 1]
    assert ones and max(ones) <= T.PROBE_STEPS
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
    # each trial: PROBE_STEPS steps, the first untimed after a change of count (the
    # threading layer resizes its team then)
    trials = [m for k, m in runs[1:] if k == 2 and m > 1]
    assert sum(twos) == len(trials) * T.PROBE_STEPS and 1 in twos
    assert len(trials) <= t_busy / T.PROBE_PERIOD + 2
    cost[2], cost[1] = 0.3e-3, 0.5e-3                  # the load goes away
    for _ in range(40):
        T.run_tuned(tuner, step, 500)
    assert tuner.best == 2
    # a step that fails part way ends the call with the steps done
    assert T.run_tuned(tuner, lambda m: m - 1, 100) <= 99
    assert numba.get_num_threads() == 2


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
