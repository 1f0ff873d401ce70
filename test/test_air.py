"""Air (core/air.py): the compiled force against its numpy reference and against the
closed forms of a flat plate: terminal velocity, edge-on flow, drag and lift directions."""
import numpy as np
import pytest

from cosserat_ros.core.air import air_forces
from cosserat_ros.core.solvers import explicit
from cosserat_ros.mesh import grid_mesh
from cosserat_ros.simulator import Air, ClothSimulator, Material

RHO_S = 0.1                                     # kg/m^2


def _sheet(n=12, width=1.0, **kw):
    mat = Material.from_plate(500.0, 1e-2, density=RHO_S, **kw)
    return ClothSimulator(grid_mesh(n, n, width=width, height=width), mat, dt=1e-4,
                          check_dt=False)


def _rotated_y(x, angle):
    c, s = np.cos(angle), np.sin(angle)
    R = np.array([[c, 0.0, s], [0.0, 1.0, 0.0], [-s, 0.0, c]])
    return x @ R.T


def test_the_compiled_air_force_is_the_numpy_reference():
    sim = _sheet(n=9)
    rng = np.random.default_rng(3)
    sim.set_positions(sim.mesh.vertices + 0.05 * rng.standard_normal((sim.n_vertices, 3)))
    sim.set_velocities(rng.standard_normal((sim.n_vertices, 3)))
    sim.set_vertex_forces([4], [[0.0, 0.3, 0.0]])
    sim.air = Air(density=1.2, drag=1.1, lift=0.7)
    sim.wind = (3.0, -1.0, 0.5)
    ref = air_forces(sim.model, sim.positions, sim.velocities, sim.air, sim.wind)
    got = sim.control.f_applied - sim.control.f_external
    assert np.abs(ref).max() > 0.01
    assert np.abs(got - ref).max() <= 1e-13 * np.abs(ref).max()
    sim.air = None                                  # off: the users' forces alone
    assert np.array_equal(sim.control.f_applied, sim.control.f_external)


@pytest.mark.parametrize('route', ['fast', 'reference', 'covariant'])
def test_one_step_with_air_changes_each_velocity_by_dt_f_air_over_m(route):
    """Every step route applies the air force of the state it starts from (the one-region
    and tiled steps are checked against these in test_fast.py)."""
    div = 'covariant' if route == 'covariant' else 'variational'
    out = []
    for air in (None, Air(lift=0.5)):
        mat = Material.from_plate(500.0, 1e-2, density=RHO_S)
        sim = ClothSimulator(grid_mesh(10, 10), mat, dt=1e-4, discretisation=div,
                             check_dt=False)
        sim.pin(np.flatnonzero(sim.mesh.boundary_vertices))
        rng = np.random.default_rng(1)
        sim.set_positions(sim.mesh.vertices + 1e-3 * rng.standard_normal((121, 3)))
        sim.set_velocities(2.0 * rng.standard_normal((121, 3)))
        sim.air = air
        sim.wind = (4.0, 0.0, 1.0)
        x0, v0 = sim.positions, sim.velocities
        if route == 'reference':
            assert explicit.reference_step(sim.model, sim.coefficients, sim.state,
                                           sim.control, sim.dt) == 1
        else:
            sim.step(1)
        out.append(sim.velocities)
    free = ~sim.pinned
    want = sim.dt * air_forces(sim.model, x0, v0, Air(lift=0.5), (4.0, 0.0, 1.0))
    dv = (out[1] - out[0]) * sim.coefficients.mass[:, None]
    assert np.abs(want[free]).max() > 1e-6
    assert np.abs(dv[free] - want[free]).max() <= 1e-9 * np.abs(want[free]).max()


def test_a_flat_sheet_falls_at_the_terminal_velocity():
    """v_t = sqrt(2 rho_s g / (rho C_D)): a stiff flat sheet falling in still air."""
    sim = _sheet()
    sim.gravity = (0.0, 0.0, -9.81)
    sim.air = Air(density=1.225, drag=1.17)
    vt = np.sqrt(2 * RHO_S * 9.81 / (1.225 * 1.17))
    sim.step(15000)                                 # 1.5 s, ~5 time constants vt/g
    v = sim.velocities
    assert np.allclose(v[:, :2], 0.0, atol=1e-9)
    assert -v[:, 2].mean() == pytest.approx(vt, rel=0.03)
    assert np.ptp(v[:, 2]) < 1e-6 * vt             # flat: every vertex alike
    # drag took energy out: the balance counts it as (negative) external work
    e = sim.energy()
    assert e['external_work'] < -0.5 * sim.coefficients.mass.sum() * 9.81 * 1.0


def test_a_sheet_moving_edge_on_feels_no_air_without_lift():
    sim = _sheet(n=8)
    sim.set_velocities(np.tile([3.0, -1.0, 0.0], (sim.n_vertices, 1)))
    for lift in (0.0, 1.0):
        sim.air = Air(drag=1.17, lift=lift)
        sim.wind = (0.0, 2.0, 0.0)                  # in the plane too
        assert np.abs(sim.control.f_applied).max() < 1e-15


@pytest.mark.parametrize('angle', [np.radians(15.0), np.radians(30.0), np.radians(60.0)])
def test_an_inclined_plate_is_pushed_downwind_and_across_the_wind(angle):
    """A plate of area A at rest with normal n = (sin a, 0, cos a) in a wind U along +x:
    the air is deflected downwards by the face that sees it, so the plate is pushed up and
    downwind: F_drag = 1/2 rho C_D A U^2 sin(a) n, F_lift = 1/2 rho C_L A U^2 sin(a) cos(a)
    e_z (across the wind, towards the side it deflects the air from)."""
    U, rho, cd, cl = 5.0, 1.225, 1.17, 0.6
    sim = _sheet(n=8)
    sim.set_positions(_rotated_y(sim.mesh.vertices, angle))
    n = np.array([np.sin(angle), 0.0, np.cos(angle)])
    q = 0.5 * rho * 1.0 * U ** 2                    # A = 1 m^2
    forces = {}
    for lift in (0.0, cl):
        sim.air = Air(density=rho, drag=cd, lift=lift)
        sim.wind = (U, 0.0, 0.0)
        forces[lift] = sim.control.f_applied.sum(axis=0)
    drag, lift = forces[0.0], forces[cl] - forces[0.0]
    np.testing.assert_allclose(drag, q * cd * np.sin(angle) * n, rtol=1e-12, atol=1e-12)
    np.testing.assert_allclose(lift, [0.0, 0.0, q * cl * np.sin(angle) * np.cos(angle)],
                               rtol=1e-12, atol=1e-12)
    assert drag[0] > 0 and drag[2] > 0 and lift[2] > 0


def test_air_and_wind_refuse_bad_values():
    for bad in (dict(density=-1.0), dict(drag=float('nan')), dict(lift='x'),
                dict(density=True)):
        with pytest.raises(ValueError, match='air.'):
            Air(**bad)
    sim = _sheet(n=4)
    with pytest.raises(ValueError, match='Air or None'):
        sim.air = 1.0
    with pytest.raises(ValueError, match='wind'):
        sim.wind = (1.0, float('inf'), 0.0)
    assert sim.air is None and np.array_equal(sim.wind, np.zeros(3))


@pytest.mark.parametrize('flow', ['along the normal', 'across it'])
def test_drag_blocks_are_the_drag_derivative_for_a_sheet_moving_as_a_whole(flow):
    # the implicit solver's D (core.air.drag_blocks): minus the derivative of the total
    # drag for a uniform velocity change, exact for flow along and across the normal
    from cosserat_ros.core.air import air_row, drag_blocks
    from cosserat_ros.core.model import Model
    mesh = grid_mesh(6, 5, pattern='irregular', seed=2)
    model = Model.from_mesh(mesh)
    x = mesh.vertices
    air, wind = Air(), np.zeros(3)
    v0 = np.tile([0.0, 0.0, 3.0] if flow == 'along the normal' else [3.0, 0.0, 0.0],
                 (len(x), 1))
    D = drag_blocks(model, x, v0, air_row(air, wind)).sum(axis=0)
    for e in np.eye(3):
        h = 1e-6
        df = (air_forces(model, x, v0 + h * e, air, wind)
              - air_forces(model, x, v0 - h * e, air, wind)).sum(axis=0) / (2 * h)
        if flow == 'along the normal' or e[2] == 1.0:    # the normal component
            assert np.allclose(-df, D @ e, rtol=1e-6, atol=1e-12), (e, -df, D @ e)
    assert np.all(np.linalg.eigvalsh(drag_blocks(model, x, v0, air_row(air, wind))) >= 0)


def test_an_implicit_step_takes_a_strong_wind_at_one_thirtieth():
    # a free polyester sheet in a 30 m/s wind along its normal: dv/dt = k (w - v)^2 with
    # k = rho C_D / (2 mu), a rate k w ~ 190 1/s (an explicit drag would need dt < 10 ms);
    # with the drag's derivative in the solve, dt = 1/30 s approaches v(t) = w - 1 / (1 / w
    # + k t) without overshoot
    mat = Material.preset('polyester')
    sim = ClothSimulator(grid_mesh(8, 8), mat, dt=1.0 / 30.0, check_dt=False,
                         solver='implicit')
    sim.solver_tolerance = 1e-9                  # the drag's time law, not the tolerance
    sim.air = Air()
    sim.wind = (0.0, 0.0, 30.0)
    k = 1.225 * 1.17 / (2 * mat.density)
    vz = []
    for _ in range(30):
        sim.step(1)
        vz.append(sim.state.v[:, 2].mean())
        assert np.ptp(sim.state.v[:, 2]) < 1e-6 * 30.0      # it moves as a whole
    vz = np.array(vz)
    assert np.all(np.diff(vz) > 0) and vz.max() < 30.0
    t = np.arange(1, 31) / 30.0
    exact = 30.0 - 1.0 / (1.0 / 30.0 + k * t)
    # backward Euler lags the exact law while the step is many time constants long, and
    # catches it up as the rate k (w - v) falls below 1 / dt
    err = np.abs(vz - exact)
    assert np.all(np.diff(err[3:]) < 0)
    assert err[14] < 0.01 * 30.0 and err[-1] < 0.002 * 30.0, np.c_[vz, exact]
