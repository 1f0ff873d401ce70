"""The strain-stiffening term (core/terms/stiffening.py), registered like any other:
its gradient and blocks against finite differences, its stated law W = k <|eps| -
knee>^2 through a simulated strip's pin reactions, and off by default (the trajectories
of test_reference_trajectories are today's)."""
import numpy as np
import pytest

from cosserat_ros.core.terms import check_term, registered
from cosserat_ros.core.terms.stiffening import Stiffening
from cosserat_ros.mesh import grid_mesh
from cosserat_ros.simulator import ClothSimulator, Material

MAT = Material(zeta=50.0, xi=2e-5, phi=1e-6, density=0.2, damping=0.0)


def test_it_is_registered_and_off_by_default():
    assert 'stiffening' in registered()
    sim = ClothSimulator(grid_mesh(4, 4), MAT)
    assert sim.terms['stiffening'] == {'stiffness': 0.0, 'knee': 0.03}
    assert sim.energy()['stiffening'] == 0.0


@pytest.mark.parametrize('pattern', ['regular', 'irregular'])
def test_gradient_and_blocks_match_finite_differences(pattern):
    """In a stretched state past the knee (every triangle's stress positive: the
    blocks are exact there), and the gradient also in a crumpled one (blocks PSD)."""
    sim = ClothSimulator(grid_mesh(5, 4, pattern=pattern, seed=2), MAT)
    rng = np.random.default_rng(1)
    c = {'stiffness': 300.0, 'knee': 0.02}
    x = sim.positions * np.array([1.08, 1.03, 1.0]) + rng.normal(0, 1e-3, sim.positions.shape)
    check_term(Stiffening(), sim.model, x, c)
    crumpled = sim.positions * 0.9 + rng.normal(0, 0.02, sim.positions.shape)
    term = Stiffening()
    from cosserat_ros.core.terms.registry import Values
    v = Values(c)
    g = term.gradient(sim.model, crumpled, v)
    h = 1e-6
    for i, a in ((3, 0), (7, 2), (11, 1)):
        xp, xm = crumpled.copy(), crumpled.copy()
        xp[i, a] += h
        xm[i, a] -= h
        fd = (term.energy(sim.model, xp, v) - term.energy(sim.model, xm, v)) / (2 * h)
        assert g[i, a] == pytest.approx(fd, rel=1e-5, abs=1e-9)
    blocks = term.hessian_blocks(sim.model, crumpled, v)
    assert np.all(np.linalg.eigvalsh(blocks) >= -1e-9 * np.abs(blocks).max())


@pytest.mark.slow
@pytest.mark.parametrize('stretch', [1.01, 1.05, 1.10, 1.20])
def test_a_stretched_strip_pulls_its_pins_with_the_stated_law(stretch):
    """A 0.2 m x 0.05 m strip held at both ends at ``stretch`` times its length, a soft
    membrane (zeta = 0.05 N/m: its share of the pull below 0.1% past the knee) and the
    stiffening on (k = 500 N/m past a knee of 0.03): backward Euler brings it to rest
    from a perturbed start, and the pins of the right end pull with the law's tension,
    per unit width T = dW/dlambda = 2 k <e - knee> lambda (e = (lambda^2 - 1) / 2, the
    Green strain along the strip; the stiffening holds e22 near 0: its pull on e22 is
    k / zeta = 1e4 times the membrane's), within 1%; below the knee only the membrane's
    small pull is left."""
    k, knee, L, H = 500.0, 0.03, 0.2, 0.05
    mesh = grid_mesh(20, 5, width=L, height=H)
    soft = Material(zeta=0.05, xi=1e-8, phi=0.0, density=0.2, damping=2.0)
    sim = ClothSimulator(mesh, soft, dt=1.0 / 60.0, solver='implicit',
                         terms={'stiffening': {'stiffness': k, 'knee': knee}})
    X = mesh.vertices
    left = np.flatnonzero(np.isclose(X[:, 0], X[:, 0].min()))
    right = np.flatnonzero(np.isclose(X[:, 0], X[:, 0].max()))
    x = X.copy()
    x[:, 0] = X[:, 0].min() + stretch * (X[:, 0] - X[:, 0].min())
    inner = np.setdiff1d(np.arange(len(X)), np.concatenate([left, right]))
    x[inner] += np.random.default_rng(0).normal(0, 5e-5, (len(inner), 3))
    sim.set_positions(x)
    sim.pin(np.concatenate([left, right]))
    for _ in range(120):
        sim.step(1)
    e = (stretch ** 2 - 1) / 2
    tension = 2 * k * max(e - knee, 0.0) * stretch
    pull = float(np.sum(sim.control.reaction[right, 0]))
    if tension == 0.0:
        assert abs(pull) < 1e-3                   # the membrane's: 1.4e-4 N at 1.01
    else:
        assert pull == pytest.approx(tension * H, rel=0.01)
        assert float(np.sum(sim.control.reaction[left, 0])) == pytest.approx(-tension * H,
                                                                             rel=0.01)
