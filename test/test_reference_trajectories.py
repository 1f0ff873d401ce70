"""The restructured core reproduces the trajectories of the core before it.

``data/reference_trajectories.npz`` holds positions, velocities and energies after 500
steps of twelve cases, written by ``data/make_reference.py`` on commit 6a1f975 (the last
commit before the restructure): every grid pattern, phi = 0, the shipped phi and a coupling
at half its limit, a closed icosphere, the dome with its hole, the tiled step on a 64 x 64
sheet, the seed's covariant route; pins, vertex forces, a force field and shaken starts.
"""
import os
import sys

import numpy as np
import pytest

HERE = os.path.join(os.path.dirname(os.path.abspath(__file__)), 'data')
sys.path.insert(0, HERE)
import make_reference as ref  # noqa: E402

DATA = np.load(os.path.join(HERE, 'reference_trajectories.npz'))
CASES = ref.cases()


@pytest.mark.slow
@pytest.mark.parametrize('name', sorted(CASES))
def test_500_steps_match_the_core_before_the_restructure(name):
    sim = ref.simulator(name, CASES[name])
    sim.step(ref.STEPS)
    x, v = DATA[f'{name}/x'], DATA[f'{name}/v']
    assert np.abs(x - sim.mesh.vertices).max() > 1e-3           # the case moves
    assert np.abs(sim.positions - x).max() <= 1e-9 * np.abs(x).max()
    assert np.abs(sim.velocities - v).max() <= 1e-9 * np.abs(v).max()
    e = sim.energy()
    want = DATA[f'{name}/energy']
    got = np.array([e[k] for k in ref.ENERGY_KEYS])
    assert np.abs(got - want).max() <= 1e-9 * np.abs(want).max()
