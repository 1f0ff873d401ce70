"""Grasp handles (cosserat_ros.core.handles): the reaction wrench against the static balance,
prescribed motion, release and break force."""
import math

import numpy as np
import pytest

from cosserat_ros.mesh import grid_mesh
from cosserat_ros.simulator import ClothSimulator, Material, SimulationDiverged

G = 9.81


def _sim(n=12, side=0.5, damping=1.0, phi=1e-6):
    sim = ClothSimulator(grid_mesh(n, n, width=side, height=side),
                         Material(zeta=50.0, xi=2e-5, phi=phi, density=0.2,
                                  damping=damping), dt=1e-5, check_dt=False)
    sim.dt = 0.9 * sim.critical_dt()
    sim.gravity = (0.0, 0.0, -G)
    return sim


def _corners(sim):
    X = sim.mesh.vertices
    top = X[:, 1].max()
    return [np.array([X[:, 0].min(), top, 0.0]), np.array([X[:, 0].max(), top, 0.0])]


def test_hanging_cloth_handles_carry_its_weight_and_balance_its_moment():
    """At rest from two handles at the top corners: the wrench forces add up to the
    weight, and with their torques they balance the moment of the weight about the
    origin (the static balance of the whole cloth)."""
    sim = _sim()
    hs = [sim.grasp(point=c, radius=0.03) for c in _corners(sim)]
    sim.step(int(round(6.0 / sim.dt)))
    assert np.abs(sim.velocities).max() < 1e-4               # at rest
    m = sim.coefficients.mass
    weight = m.sum() * G
    F = sum(sim.handle_wrench(h)[0] for h in hs)
    assert F[2] == pytest.approx(weight, rel=0.01)
    assert np.abs(F[:2]).max() < 1e-3 * weight
    gravity_moment = np.cross(sim.positions, m[:, None] * np.array([0, 0, -G])).sum(0)
    handles_moment = sum(np.cross(np.array(sim.handles[h]['position']),
                                  sim.handle_wrench(h)[0]) + sim.handle_wrench(h)[1]
                         for h in hs)
    scale = np.abs(gravity_moment).max()
    assert np.abs(handles_moment + gravity_moment).max() < 0.01 * scale


def test_a_handle_at_constant_velocity_carries_its_vertices_rigidly():
    """1 m/s on the shipped material: the held vertices keep their offsets to 1e-9, the
    rest follows without blow-up."""
    sim = _sim(20, 1.0, damping=0.1)
    c = _corners(sim)[0]
    h = sim.grasp(point=c, radius=0.06)
    idx = sim.handles[h]['vertices']
    offsets = sim.positions[idx] - c
    target = c + np.array([0.3, 0.0, 0.4])          # 0.5 m in 0.5 s
    sim.move_handle(h, target, duration=0.5)
    for k in range(10):
        sim.step(int(round(0.05 / sim.dt)))
        p = np.array(sim.handles[h]['position'])
        np.testing.assert_allclose(sim.positions[idx] - p, offsets, atol=1e-9)
    assert np.linalg.norm(np.array(sim.handles[h]['position']) - target) < 1e-9
    assert not sim.handles[h]['moving']
    assert np.all(np.isfinite(sim.positions))


def test_a_turning_handle_keeps_the_offsets_turned():
    sim = _sim()
    c = _corners(sim)[0]
    h = sim.grasp(point=c, radius=0.05)
    idx = sim.handles[h]['vertices']
    off = sim.positions[idx] - c
    a = 0.5
    q = (0.0, 0.0, math.sin(a / 2), math.cos(a / 2))            # 0.5 rad about z
    sim.move_handle(h, c, q, duration=0.2)
    sim.step(int(round(0.3 / sim.dt)))
    Rz = np.array([[math.cos(a), -math.sin(a), 0], [math.sin(a), math.cos(a), 0], [0, 0, 1]])
    np.testing.assert_allclose(sim.positions[idx] - c, off @ Rz.T, atol=1e-9)


def test_accelerating_handle_reports_weight_times_one_plus_a_over_g():
    """A handle holding the whole top edge accelerates upwards at a = 2 m/s^2 (poses
    streamed at 100 Hz along z = a t^2 / 2); once the transients have decayed its force,
    averaged over every step of the last 0.3 s, is the rigid balance m (g + a) + C v: the
    weight times (1 + a/g), plus the mass-proportional damping C = sum rho A_i on the
    absolute velocity v = a t (zero with no damping; here it keeps the transients
    short). The inertia m a is 8% of the total: the 2% bound sees it."""
    sim = _sim(10, 0.3, damping=1.0)
    X = sim.mesh.vertices
    top = np.flatnonzero(np.isclose(X[:, 1], X[:, 1].max()))
    h = sim.grasp(vertices=top, point=(0.0, X[:, 1].max(), 0.0))
    sim.step(int(round(2.0 / sim.dt)))                   # hang at rest first
    a, rate = 2.0, 100.0
    p0 = np.array(sim.handles[h]['position'])
    forces, expected, t0 = [], [], sim.time
    mass, damp = sim.coefficients.mass.sum(), sim.coefficients.damp.sum()
    for k in range(1, 151):                               # 1.5 s
        t = k / rate
        sim.move_handle(h, p0 + [0.0, 0.0, 0.5 * a * t * t], duration=1 / rate)
        steps = int(round(1 / rate / sim.dt))
        if t <= 1.2:
            sim.step(steps)
            continue
        for _ in range(steps):
            sim.step(1)
            forces.append(sim.handle_wrench(h)[0][2])
            expected.append(mass * (G + a) + damp * a * (sim.time - t0))
    assert np.mean(forces) == pytest.approx(np.mean(expected), rel=0.02)
    assert mass * a > 0.05 * np.mean(expected)


def test_release_keeps_the_momentum_and_the_cloth_falls():
    sim = _sim(10, 0.3, damping=0.0)
    h = sim.grasp(point=_corners(sim)[0], radius=0.05)
    sim.step(int(round(0.5 / sim.dt)))
    c = np.array(sim.handles[h]['position'])
    sim.move_handle(h, c + [0.5, 0.0, 0.0], duration=0.5)      # 1 m/s sideways
    sim.step(int(round(0.25 / sim.dt)))
    m = sim.coefficients.mass[:, None]
    before = (m * sim.velocities).sum(0)
    sim.release(h)
    assert not sim.pinned.any()
    sim.step(1)
    after = (m * sim.velocities).sum(0)
    # one step of gravity between the two
    after_no_g = after - np.array([0, 0, -G]) * m.sum() * sim.dt
    assert np.linalg.norm(after_no_g - before) < 0.01 * np.linalg.norm(before)
    z = sim.positions[:, 2].mean()
    sim.step(int(round(0.3 / sim.dt)))
    assert sim.positions[:, 2].mean() < z - 0.3           # free fall, ~0.44 m in 0.3 s


def test_a_break_force_below_the_weight_drops_the_cloth():
    sim = _sim()
    weight = sim.coefficients.mass.sum() * G
    hs = [sim.grasp(point=c, radius=0.03, break_force=0.3 * weight) for c in _corners(sim)]
    sim.step(int(round(1.0 / sim.dt)))
    assert not sim.handles and not sim.pinned.any()
    assert sim.positions[:, 2].max() < -0.5                 # falling
    strong = _sim()
    hs = [strong.grasp(point=c, radius=0.03, break_force=2 * weight)
          for c in _corners(strong)]
    strong.step(int(round(1.0 / strong.dt)))
    assert set(strong.handles) == set(hs)


def test_handle_api_refusals():
    sim = _sim(6, 0.2)
    with pytest.raises(ValueError, match='no vertex within'):
        sim.grasp(point=(5.0, 5.0, 5.0), radius=0.01)
    h = sim.grasp(vertices=[0, 1], name='left')
    with pytest.raises(ValueError, match='held by another handle'):
        sim.grasp(vertices=[1, 2])
    with pytest.raises(ValueError, match='exists already'):
        sim.grasp(vertices=[5], name='left')
    with pytest.raises(ValueError, match='unit quaternion'):
        sim.move_handle(h, (0, 0, 0), (0, 0, 0, 2))
    with pytest.raises(ValueError, match='finite'):
        sim.move_handle(h, (0, 0, float('nan')))
    with pytest.raises(ValueError, match='no handle'):
        sim.release(42)
    sim.pin([3])
    sim.release(h)
    assert sorted(np.flatnonzero(sim.pinned)) == [3]      # a pin stays a pin
    h1 = sim.grasp(vertices=[10])
    for bad in (str(h1), float(h1), h1 + 0.5):          # not turned into handle h1
        with pytest.raises(ValueError, match='no handle'):
            sim.release(bad)
    assert h1 in sim.handles
    # a boolean mask or float indices as pin() takes them, not cast to 0 and 1
    mask = np.zeros(sim.n_vertices, dtype=bool)
    mask[[20, 21, 22]] = True
    h2 = sim.grasp(vertices=mask)
    assert sim.handles[h2]['vertices'].tolist() == [20, 21, 22]
    with pytest.raises(ValueError, match='integers'):
        sim.grasp(vertices=[1.7])


def test_a_pin_a_handle_let_go_of_stays_where_it_is():
    """A pinned vertex grabbed by a moving handle and let go keeps no velocity of the
    handle's (README: such vertices stay pinned after the release)."""
    sim = _sim(6, 0.2)
    sim.pin([0])
    h = sim.grasp(vertices=[0, 1])
    p = np.array(sim.handles[h]['position'])
    sim.move_handle(h, p + [0.0, 0.0, 0.1], duration=1.0)
    sim.step(100)
    sim.release(h)
    at = sim.positions[0]
    sim.step(500)
    assert np.array_equal(sim.positions[0], at)
    assert not sim.control.pin_velocity.any()


def test_set_positions_moves_what_a_handle_holds_with_the_cloth():
    """set_positions with a handle: the handle holds its vertices where they are set (its
    offsets taken again), not pulled back to where they were in one step."""
    sim = _sim(6, 0.2)
    h = sim.grasp(vertices=[0, 1, 2])
    p = np.array(sim.handles[h]['position'])
    sim.set_positions(sim.positions + [0.0, 0.0, 0.3])
    sim.move_handle(h, p + [0.01, 0.0, 0.0], duration=0.002)
    sim.step(1)
    assert np.abs(sim.velocities[[0, 1, 2], 2]).max() < 1.0
    assert np.all(sim.positions[[0, 1, 2], 2] > 0.29)


@pytest.mark.parametrize('solver', ['explicit', 'implicit'])
def test_the_energy_balance_closes_for_a_moving_handle(solver):
    """A handle carrying the whole cloth up at 1 m/s against gravity, a force field and
    damping: over the steady motion the report's total changes by external_work -
    dissipated, and the kinetic energy is the held mass's. (The held vertices' kinetic
    energy, the applied force's work and the damping on them were not booked.) The
    start of the motion is left out: a velocity prescribed from 0 to u in one step
    takes m u^2 of work for 1/2 m u^2 of kinetic energy, as any impulsive start."""
    mesh = grid_mesh(6, 6, width=0.2, height=0.2)
    mat = Material(zeta=50.0, xi=2e-5, phi=0.0, density=0.2, damping=1.0)
    if solver == 'implicit':
        sim = ClothSimulator(mesh, mat, dt=1e-3, solver='implicit')
    else:
        sim = ClothSimulator(mesh, mat, dt=1e-5, check_dt=False)
        sim.dt = 0.9 * sim.critical_dt()
    sim.gravity = (0.0, 0.0, -G)
    sim.force_field = (0.0, 0.0, 20.0)
    h = sim.grasp(vertices=np.arange(sim.n_vertices))
    p = np.array(sim.handles[h]['position'])
    sim.move_handle(h, p + [0.0, 0.0, 0.1], duration=0.1)
    sim.step(int(round(0.02 / sim.dt)))
    e0 = sim.energy()
    sim.step(int(round(0.05 / sim.dt)))
    e1 = sim.energy()
    change = e1['total'] - e0['total']
    ledger = (e1['external_work'] - e1['dissipated']) - (e0['external_work'] - e0['dissipated'])
    mass = 0.2 * 0.2 * 0.2
    assert e1['kinetic'] == pytest.approx(0.5 * mass * 1.0 ** 2, rel=1e-6)
    assert abs(change - ledger) < 1e-3 * abs(change), (change, ledger)


def test_waypoints_streamed_ahead_are_each_reached_on_time():
    """Waypoints given ahead of sim time (``move_handle(..., at=)``): the handle is at each
    when sim time first reaches it (within one step's motion), moves linearly in between,
    and a later waypoint given before an earlier one's time drops the ones after it."""
    sim = _sim(12, 0.5, damping=0.5)
    c = _corners(sim)[0]
    h = sim.grasp(point=c, radius=0.03)
    dt = sim.dt
    times = [0.013, 0.05, 0.0777, 0.11]
    points = [c + [0.0, 0.0, 0.02], c + [0.03, 0.0, 0.02], c + [0.03, 0.01, 0.0],
              c + [0.0, 0.0, 0.0]]
    for t, p in zip(times, points):
        sim.move_handle(h, p, at=t)
    assert len(sim.handle_waypoints(h)) == 1 + len(times)
    for t, p in zip(times, points):
        sim.step(int(math.ceil((t - sim.time) / dt - 1e-9)))
        assert t <= sim.time < t + dt
        after = sim.time - t
        wp = sim.handle_waypoints(h)
        nxt = wp[1] if len(wp) > 1 else None
        speed = 0.0 if nxt is None else np.linalg.norm(nxt[1] - p) / (nxt[0] - t)
        got = np.array(sim.handles[h]['position'])
        assert np.linalg.norm(got - p) <= speed * after + 1e-12, (t, got, p)
    assert not sim.handles[h]['moving']
    # half way along a segment: the linear interpolation
    sim.move_handle(h, c + [0.04, 0.0, 0.0], at=sim.time + 0.04)
    t0, p0 = sim.time, np.array(sim.handles[h]['position'])
    sim.step(int(round(0.02 / dt)))
    s = (sim.time - t0) / 0.04
    np.testing.assert_allclose(sim.handles[h]['position'], p0 + s * (c + [0.04, 0, 0] - p0),
                               atol=1e-12)
    # a waypoint before the last one given drops the later ones
    sim.step(int(math.ceil((t0 + 0.04 - sim.time) / dt - 1e-9)))
    now = sim.time
    sim.move_handle(h, c + [0.0, 0.05, 0.0], at=now + 0.05)
    sim.move_handle(h, c + [0.0, 0.02, 0.0], at=now + 0.03)
    wp = sim.handle_waypoints(h)
    assert [w[0] for w in wp] == [now, now + 0.03]


def test_waypoints_in_the_past_or_beyond_the_bound_are_refused():
    from cosserat_ros.core.handles import MAX_WAYPOINTS
    sim = _sim()
    c = _corners(sim)[0]
    h = sim.grasp(point=c, radius=0.03)
    sim.step(10)
    with pytest.raises(ValueError, match='after the present'):
        sim.move_handle(h, c, at=sim.time)
    with pytest.raises(ValueError, match='not both'):
        sim.move_handle(h, c, duration=0.1, at=sim.time + 1)
    for k in range(MAX_WAYPOINTS):
        sim.move_handle(h, c, at=sim.time + 1 + k)
    with pytest.raises(ValueError, match='waypoints ahead'):
        sim.move_handle(h, c, at=sim.time + 1e4)
    sim.move_handle(h, c, duration=0.1)                # a duration replaces the path
    assert len(sim.handle_waypoints(h)) == 2


# ------------------------------------------------------------------ a failed step rolls back

def _equal_handles(a, b):
    assert a.keys() == b.keys()
    for hid in a:
        for key in a[hid]:
            assert np.array_equal(a[hid][key], b[hid][key]), (hid, key)


def _moving_handles(sim, break_force=None):
    """Two top-corner handles with a waypoint every 3 steps ahead (the step's calls end at
    each), the cloth hanging from them for 0.05 s."""
    hs = [sim.grasp(point=c, radius=0.03, break_force=break_force) for c in _corners(sim)]
    sim.step(int(round(0.05 / sim.dt)))
    for h, c in zip(hs, _corners(sim)):
        for k in range(1, 40):
            sim.move_handle(h, c + (0.0, 0.0, 0.002 * k), at=sim.time + 3 * k * sim.dt)
    return hs


def _before(sim, hs):
    return (sim.positions, sim.velocities, sim.handles,
            [sim.handle_waypoints(h) for h in hs], sim.control.pinned.copy(),
            sim.control.pin_velocity.copy(), sim.time)


def _assert_as_before(sim, hs, before):
    x, v, handles, waypoints, pinned, pin_velocity, t = before
    assert np.array_equal(sim.positions, x) and np.array_equal(sim.velocities, v)
    assert sim.time == t
    _equal_handles(sim.handles, handles)
    for h, w in zip(hs, waypoints):
        got = sim.handle_waypoints(h)
        assert len(got) == len(w)
        assert all(a[0] == b[0] and np.array_equal(a[1], b[1]) and np.array_equal(a[2], b[2])
                   for a, b in zip(got, w))
    assert np.array_equal(sim.control.pinned, pinned)
    assert np.array_equal(sim.control.pin_velocity, pin_velocity)


def test_a_divergence_in_a_later_call_puts_the_handles_back_too():
    """``step(n)`` with moving handles runs calls of a few steps; when a later
    call diverges, the cloth goes back to the start of ``step`` and so do the handles
    (their poses and paths, which the calls that succeeded had moved on, and the held
    vertices' prescribed velocities), so that stepping on from there is the same as if the
    failed call had never been made."""
    sims = [_sim(), _sim()]
    hss = [_moving_handles(s) for s in sims]
    sim, hs = sims[0], hss[0]
    before = _before(sim, hs)
    free = int(np.flatnonzero(~sim.control.pinned)[sim.n_vertices // 2])
    m = float(sim.coefficients.mass[free])
    sim.set_vertex_forces([free], [[0.0, 0.0, m * sim._vmax / (15 * sim.dt)]])
    with pytest.raises(SimulationDiverged) as err:
        sim.step(100)
    assert err.value.step - sim.step_count > 3          # after a call that succeeded
    _assert_as_before(sim, hs, before)
    sim.set_vertex_forces([], np.zeros((0, 3)))
    for s in sims:
        s.step(60)
    assert np.array_equal(sims[0].positions, sims[1].positions)
    _equal_handles(sims[0].handles, sims[1].handles)


def test_a_divergence_gives_back_the_vertices_that_slipped_before_it():
    """Vertices that slipped out of a handle (break force) in the calls that succeeded are
    held again after the failed step, as they were at its start. The failure is the
    solver's (fewer steps done than asked, as a divergence reports it) in the sixth call,
    after a pull of five times the cloth's weight on the free vertex next to a handle has
    torn vertices out of it."""
    sim = _sim()
    weight = float(sim.coefficients.mass.sum()) * G
    hs = _moving_handles(sim, break_force=weight)
    before = _before(sim, hs)
    x = sim.positions
    free = np.flatnonzero(~sim.control.pinned)
    near = int(free[np.argmin(np.linalg.norm(x[free] - _corners(sim)[0], axis=1))])
    sim.set_vertex_forces([near], [[0.0, 0.0, -5.0 * weight]])
    held = sum(len(d['vertices']) for d in before[2].values())
    slipped = []
    broken = sim._handles.broken

    def watched(reaction):
        out = broken(reaction)
        slipped.append(len(out))
        return out
    sim._handles.broken = watched
    solve = sim._solve
    calls = []

    def failing(k):
        calls.append(k)
        return 0 if len(calls) == 6 else solve(k)
    sim._solve = failing
    with pytest.raises(SimulationDiverged):
        sim.step(100)
    assert len(calls) == 6 and sum(slipped) > 0         # vertices slipped before it failed
    _assert_as_before(sim, hs, before)
    assert sum(len(d['vertices']) for d in sim.handles.values()) == held


def test_an_interrupted_step_puts_back_the_cloth_the_handles_and_the_obstacles():
    """Any exception inside ``step`` (here a KeyboardInterrupt from the third call of the
    compiled step) leaves the cloth, the handles and a moving obstacle as they were at
    the start of the call."""
    sim = _sim()
    hs = _moving_handles(sim)
    ball = sim.add_obstacle('sphere', radius=0.05, center=(0.0, 0.0, -0.5))
    sim.set_obstacle_pose(ball, (0.0, 0.0, -0.5), linear_velocity=(0.0, 0.0, 0.2))
    before = _before(sim, hs)
    pose = sim.obstacles[ball]
    solve = sim._solve
    calls = []

    def interrupted(k):
        calls.append(k)
        if len(calls) == 3:
            raise KeyboardInterrupt
        return solve(k)
    sim._solve = interrupted
    with pytest.raises(KeyboardInterrupt):
        sim.step(50)
    _assert_as_before(sim, hs, before)
    got = sim.obstacles[ball]
    assert np.array_equal(got['position'], pose['position'])
    assert np.array_equal(got['orientation'], pose['orientation'])
