"""The explicit update (``core/update.py``) alone, against closed-form solutions of
its own discrete map: free fall under gravity, a single-DOF oscillator with and without
damping, and the energy bookkeeping; the internal force is supplied by the test."""
import numpy as np
import pytest

from cosserat_ros.core.model import Coefficients
from cosserat_ros.core.solvers.explicit import advance_all
from cosserat_ros.core.state import Control, State


def _system(n=3, mass=0.5, damping=0.0):
    coeff = Coefficients(1.0, 1.0, 0.0, np.full(n, mass), np.full(n, damping), np.zeros(n))
    return coeff, Control.empty(n)


def _step(state, control, coeff, dt, force):
    part = np.zeros((2, 3))
    return advance_all(state.x, state.v, force, control, coeff, dt, np.inf, part, state.acc)


def test_free_fall_is_the_discrete_map_exactly():
    # v_n = v_0 + n g dt, x_n = x_0 + n dt v_0 + g dt^2 n (n + 1) / 2 (velocity first)
    coeff, control = _system()
    control.gravity[:] = (0.3, 0.0, -9.81)
    state = State(np.array([[0.0, 0.0, 1.0], [1.0, 2.0, 3.0], [-1.0, 0.5, 0.0]]),
                  np.array([[0.1, 0.0, 0.0], [0.0, -0.2, 0.5], [0.0, 0.0, 0.0]]), np.zeros(2))
    x0, v0 = state.x.copy(), state.v.copy()
    dt, n = 1e-3, 700
    for _ in range(n):
        assert _step(state, control, coeff, dt, np.zeros((3, 3))) == 0
    g = control.gravity
    assert np.allclose(state.v, v0 + n * dt * g, rtol=1e-12, atol=1e-12)
    assert np.allclose(state.x, x0 + n * dt * v0 + g * dt ** 2 * n * (n + 1) / 2,
                       rtol=1e-11, atol=1e-11)


def test_pinned_vertices_stay_put_and_applied_work_is_booked():
    coeff, control = _system()
    control.pinned[1] = True
    control.f_applied[:] = [[0.0, 0.0, 2.0], [5.0, 5.0, 5.0], [1.0, 0.0, 0.0]]
    state = State.at_rest(np.eye(3))
    x_pinned = state.x[1].copy()
    dt = 1e-2
    for _ in range(50):
        _step(state, control, coeff, dt, np.zeros((3, 3)))
    assert np.array_equal(state.x[1], x_pinned) and np.all(state.v[1] == 0)
    # constant forces from rest: the work is f . (x - x0), only on the free vertices
    want = np.sum(control.f_applied[[0, 2]] * (state.x[[0, 2]] - np.eye(3)[[0, 2]]))
    assert state.acc[0] == pytest.approx(want, rel=1e-12) and state.acc[1] == 0.0


@pytest.mark.parametrize('gamma', [0.0, 0.7])
def test_oscillator_follows_its_discrete_eigenvalues_and_converges(gamma):
    # m x'' = -k x - c x': symplectic Euler is the linear map z_{n+1} = A z_n, z = (x, v),
    # A = [[1 - w^2 dt^2, dt (1 - gamma dt)], [-w^2 dt, 1 - gamma dt]], whose powers the
    # update must reproduce; its eigenvalues exp(s dt) approach the continuous
    # s = -gamma/2 +- i sqrt(w^2 - gamma^2/4) with first order in dt (second for the
    # frequency when gamma = 0)
    m, k = 0.5, 8.0
    w2 = k / m
    coeff, control = _system(1, m, gamma * m)
    errors = []
    dts = (0.02, 0.01, 0.005)
    for dt in dts:
        state = State(np.array([[0.1, 0.0, 0.0]]), np.array([[0.0, 0.3, 0.0]]), np.zeros(2))
        A = np.array([[1 - w2 * dt ** 2, dt * (1 - gamma * dt)], [-w2 * dt, 1 - gamma * dt]])
        n = int(round(3.0 / dt))
        for _ in range(n):
            _step(state, control, coeff, dt, -k * state.x)
        An = np.linalg.matrix_power(A, n)
        for axis, z0 in ((0, (0.1, 0.0)), (1, (0.0, 0.3))):
            zn = An @ np.array(z0)
            assert state.x[0, axis] == pytest.approx(zn[0], rel=1e-9, abs=1e-13)
            assert state.v[0, axis] == pytest.approx(zn[1], rel=1e-9, abs=1e-13)
        lam = np.linalg.eigvals(A)
        s = np.log(lam[np.argmax(lam.imag)]) / dt
        exact = complex(-gamma / 2, np.sqrt(w2 - gamma ** 2 / 4))
        errors.append(abs(s - exact) / abs(exact))
    order = np.polyfit(np.log(dts), np.log(errors), 1)[0]
    assert order == pytest.approx(2.0 if gamma == 0 else 1.0, abs=0.1)
    # undamped, the map is area-preserving: |lambda| = 1 while w dt < 2
    if gamma == 0:
        assert np.allclose(np.abs(np.linalg.eigvals(A)), 1.0, atol=1e-12)


def test_damping_dissipation_is_booked():
    # no other force: the kinetic energy lost is what acc[1] books, to O(dt)
    coeff, control = _system(1, 0.5, 0.4)
    state = State(np.zeros((1, 3)), np.array([[1.0, 0.0, 0.0]]), np.zeros(2))
    dt = 1e-4
    for _ in range(5000):
        _step(state, control, coeff, dt, np.zeros((1, 3)))
    lost = 0.5 * 0.5 * (1.0 - state.v[0, 0] ** 2)
    assert state.acc[1] == pytest.approx(lost, rel=1e-3)
    assert state.v[0, 0] == pytest.approx(np.exp(-0.8 * 0.5), rel=1e-3)
