"""The step pipeline (core/passes.py): ClothSimulator.step is a loop over passes of one
protocol. A pass written here, outside the package's four, is driven like them: it
limits the calls, may make one be done again, answers after it, and is put back with
the cloth when a step fails."""
import math

import numpy as np
import pytest

from cosserat_ros.core.passes import StepPass
from cosserat_ros.mesh import grid_mesh
from cosserat_ros.simulator import ClothSimulator, Material, SimulationDiverged

MAT = Material(zeta=100.0, xi=1e-5, phi=0.0, density=0.2, damping=0.01)


def cloth():
    sim = ClothSimulator(grid_mesh(8, 8, 0.3, 0.3), MAT, dt=1e-4, check_dt=False)
    sim.dt = 0.5 * sim.critical_dt()
    sim.gravity = (0.0, 0.0, -9.81)
    sim.pin([0, 7])
    return sim


class Probe(StepPass):
    """Calls of at most ``most`` steps; ``overrun_once``: says the first call overran;
    ``blow_at``: answers NaN after that call; its snapshot is a counter it restores."""

    def __init__(self, sim, most, overrun_once=False, blow_at=None):
        super().__init__(sim)
        self.most, self.overrun_once, self.blow_at = most, overrun_once, blow_at
        self.log, self.calls, self.value = [], 0, 0

    def active(self):
        return True

    def snapshot(self):
        return self.value

    def restore(self, snap):
        self.value = snap
        self.log.append(('restore', snap))

    def limit(self, k, t, overran):
        self.log.append(('limit', k, round(t / self.sim.dt), overran))
        return min(k, self.most)

    def needs_start(self, k):
        return self.overrun_once

    def overran(self, start, k):
        if self.overrun_once:
            self.overrun_once = False
            return True
        return False

    def answer(self, k):
        self.calls += 1
        self.value += k
        return math.nan if self.calls == self.blow_at else 0.0

    def end_call(self, got, k, t_end):
        self.log.append(('end', got, k, round(t_end / self.sim.dt)))

    def finish(self, t):
        self.log.append(('finish', round(t / self.sim.dt)))


def test_a_pass_cuts_the_step_into_calls_and_the_trajectory_stays_the_same():
    plain, piped = cloth(), cloth()
    probe = Probe(piped, 7)
    piped._passes.append(probe)
    plain.step(20)
    piped.step(20)
    assert [e for e in probe.log if e[0] == 'end'] == [('end', 7, 7, 7), ('end', 7, 7, 14),
                                                      ('end', 6, 6, 20)]
    assert probe.log[-1] == ('finish', 20) and probe.value == 20
    # the explicit step does not depend on how the steps are cut into calls
    assert np.array_equal(plain.positions, piped.positions)
    assert np.array_equal(plain.velocities, piped.velocities)
    assert plain.time == piped.time and piped.step_count == 20


def test_an_overrun_call_is_done_again_from_its_start():
    plain, piped = cloth(), cloth()
    probe = Probe(piped, 5, overrun_once=True)
    piped._passes.append(probe)
    plain.step(10)
    piped.step(10)
    limits = [e for e in probe.log if e[0] == 'limit']
    # the first call (5 steps) overran: the next limit starts again at step 0, told so
    assert limits[:2] == [('limit', 10, 0, False), ('limit', 10, 0, True)]
    assert np.array_equal(plain.positions, piped.positions)
    assert probe.value == 10                        # the undone call was not answered


def test_a_non_finite_answer_puts_the_cloth_and_every_pass_back():
    sim = cloth()
    sim.step(3)
    x, v, t = sim.positions.copy(), sim.velocities.copy(), sim.time
    probe = Probe(sim, 4, blow_at=2)
    sim._passes.append(probe)
    with pytest.raises(SimulationDiverged):
        sim.step(12)
    assert ('restore', 0) in probe.log and probe.value == 0
    assert np.array_equal(sim.positions, x) and np.array_equal(sim.velocities, v)
    assert sim.time == t and sim.step_count == 3
