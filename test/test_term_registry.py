"""A new physical effect registered from outside the package (cosserat_ros.core.terms's
registry): a tether of every vertex to its rest position,

    E = 1/2 k sum_i A_i |x_i - X_i|^2        (A_i the dual area, k [N/m^3]),

whose force per unit area is -k (x - X). A sheet moved rigidly by d (no strain, no
bending) then feels -k d per unit area against its inertia mu per unit area: it
oscillates at omega = sqrt(k / mu), on any mesh, and under gravity g it hangs at
d = mu g / k. Nothing of the package is edited for it: the explicit step, the implicit
solver, the energy report and the node carry it from its registration."""
import math

import numpy as np
import pytest

from cosserat_ros.core.terms import Coefficient, check_term, register, registered, unregister
from cosserat_ros.mesh import grid_mesh
from cosserat_ros.simulator import ClothSimulator, Material


class Tether:
    """E = 1/2 k sum_i A_i |x_i - X_i|^2 (module docstring)."""
    name = 'tether'
    coefficients = (Coefficient('k', default=0.0, unit='N/m^3', low=0.0, high=1e12,
                                text='stiffness of each vertex\'s tie to its rest place'),)

    def energy(self, model, x, c):
        d = x - model.mesh.vertices
        return 0.5 * c.k * float(np.sum(model.vertices.dual_area[:, None] * d * d))

    def gradient(self, model, x, c):
        return c.k * model.vertices.dual_area[:, None] * (x - model.mesh.vertices)

    def hessian_blocks(self, model, x, c):
        return c.k * model.vertices.dual_area[:, None, None] * np.eye(3)[None]


MU = 0.2                 # [kg/m^2]
MAT = Material(zeta=50.0, xi=2e-5, phi=1e-6, density=MU, damping=0.0)


@pytest.fixture
def tether():
    term = register(Tether())
    yield term
    unregister('tether')
    assert 'tether' not in registered()


def _sheet(k, **kw):
    mesh = grid_mesh(8, 8, width=0.4, height=0.4, pattern='irregular', seed=3)
    return ClothSimulator(mesh, MAT, terms={'tether': {'k': k}}, **kw)


def test_the_tether_s_gradient_and_blocks_match_finite_differences(tether):
    sim = _sheet(30.0)
    x = sim.positions + np.random.default_rng(0).normal(0, 0.01, sim.positions.shape)
    eg, eb = check_term(tether, sim.model, x, {'k': 30.0})
    assert eg < 1e-6 and eb < 1e-6


def test_a_registered_term_needs_its_methods_and_a_free_name():
    class Nameless:
        name = 'Bad Name'
    with pytest.raises(ValueError, match='name'):
        register(Nameless())

    class Builtinish(Tether):
        name = 'bending'
    with pytest.raises(ValueError, match='registered already'):
        register(Builtinish())

    class NoBlocks:
        name = 'noblocks'
        coefficients = ()

        def energy(self, model, x, c):
            return 0.0

        def gradient(self, model, x, c):
            return 0.0 * x
    with pytest.raises(ValueError, match='hessian_blocks'):
        register(NoBlocks())


def test_unknown_terms_and_bad_coefficients_are_refused(tether):
    mesh = grid_mesh(4, 4)
    with pytest.raises(ValueError, match='no registered term'):
        ClothSimulator(mesh, MAT, terms={'tethers': {'k': 1.0}})
    with pytest.raises(ValueError, match='no coefficient'):
        ClothSimulator(mesh, MAT, terms={'tether': {'stiffness': 1.0}})
    sim = ClothSimulator(mesh, MAT)                       # defaults: k = 0
    assert sim.terms['tether'] == {'k': 0.0}
    for bad in (-1.0, math.nan, 'stiff', True):
        with pytest.raises(ValueError, match='tether.k'):
            sim.set_term('tether', k=bad)
    assert sim.terms['tether'] == {'k': 0.0}              # nothing changed
    with pytest.raises(ValueError, match='no term'):
        sim.set_term('rope', k=1.0)


def _period(t, z):
    """The mean period of z(t) from its upward zero crossings (linear interpolation)."""
    s = np.flatnonzero((z[:-1] < 0) & (z[1:] >= 0))
    tc = t[s] - z[s] * (t[s + 1] - t[s]) / (z[s + 1] - z[s])
    return float(np.mean(np.diff(tc)))


def test_the_explicit_step_oscillates_at_the_tether_s_frequency_and_keeps_its_energy(tether):
    """omega = sqrt(k / mu) within 1% (symplectic Euler's own error, (omega dt)^2 / 24, is
    1e-7 here); the energy report lists the tether and its total stays within 1e-4 of
    the energy in play (undamped, no gravity)."""
    k = 200.0
    sim = _sheet(k)
    sim.set_positions(sim.positions + np.array([0.0, 0.0, 0.01]))      # a rigid lift
    e0 = sim.energy()
    assert e0['tether'] == pytest.approx(0.5 * k * 0.4 * 0.4 * 0.01 ** 2, rel=1e-12)
    dt = sim.dt
    omega = math.sqrt(k / MU)
    t, z, totals = [], [], []
    for i in range(int(3 * 2 * math.pi / omega / dt / 50)):
        sim.step(50)
        t.append(sim.time)
        z.append(float(np.mean(sim.positions[:, 2])))
        totals.append(sim.energy()['total'])
    period = _period(np.array(t), np.array(z))
    assert period == pytest.approx(2 * math.pi / omega, rel=0.01)
    assert np.max(np.abs(np.array(totals) - e0['total'])) < 1e-4 * e0['tether']
    assert sim.energy()['external_work'] == pytest.approx(0.0, abs=1e-12)


def test_set_term_changes_the_frequency_at_the_next_step(tether):
    sim = _sheet(50.0)
    sim.set_term('tether', k=450.0)                       # three times the frequency
    sim.set_positions(sim.positions + np.array([0.0, 0.0, 0.01]))
    omega = math.sqrt(450.0 / MU)
    t, z = [], []
    for _ in range(int(3 * 2 * math.pi / omega / sim.dt / 20)):
        sim.step(20)
        t.append(sim.time)
        z.append(float(np.mean(sim.positions[:, 2])))
    assert _period(np.array(t), np.array(z)) == pytest.approx(2 * math.pi / omega, rel=0.01)


def test_the_implicit_solver_converges_with_the_tether_and_hangs_the_sheet_where_it_must(
        tether):
    """Backward Euler at 1/60 s with the tether and gravity: every solve converges, and
    the sheet comes to rest at the analytic sag mu g / k (a rigid translation: the
    membrane and the bending take nothing)."""
    k = 100.0
    sim = _sheet(k, solver='implicit', dt=1.0 / 60.0)
    sim.material = Material(zeta=50.0, xi=2e-5, phi=1e-6, density=MU, damping=0.5)
    sim.gravity = (0.0, 0.0, -9.81)
    for _ in range(240):                                  # 4 s
        sim.step(1)
        assert sim.solve_report['converged'], sim.solve_report
    sag = MU * 9.81 / k
    z = sim.positions[:, 2] - sim.model.mesh.vertices[:, 2]
    assert np.allclose(z, -sag, rtol=1e-3, atol=0.0), (z.min(), z.max(), -sag)
    assert sim.energy()['tether'] == pytest.approx(0.5 * k * 0.16 * sag ** 2, rel=2e-3)


def test_the_node_declares_the_term_s_coefficient_as_a_parameter(tether):
    """terms.tether.k: declared from the coefficient (default, range), set at start-up
    and at run time, a bad value refused with the reason; ~/energy lists the tether."""
    from rclpy.parameter import Parameter
    from test_node import Harness
    h = Harness(**{'terms.tether.k': 40.0})
    try:
        assert h.node.sim.terms['tether'] == {'k': 40.0}
        res = h.node.set_parameters([Parameter('terms.tether.k', value=80.0)])[0]
        assert res.successful, res.reason
        assert h.node.sim.terms['tether'] == {'k': 80.0}
        res = h.node.set_parameters([Parameter('terms.tether.k', value=-1.0)])[0]
        assert not res.successful and 'terms.tether.k' in res.reason
        assert h.node.sim.terms['tether'] == {'k': 80.0}
        assert h.spin_until(lambda: h.energies and any(
            kv.key == 'tether' for kv in h.energies[-1].status[0].values), 10)
    finally:
        h.close()
