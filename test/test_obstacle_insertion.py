"""Obstacles placed through the cloth (cosserat_ros/core/contact.py, "Obstacles
placed through the cloth"): the vertices an obstacle is added or posed through are
released from it until they come out of its contact layer, so the placement adds no
energy beyond the push of the vertices it finds in its layer but outside its solid.

Each scene is built twice, the same way (the step is deterministic), and the twin gets
an obstacle far from the cloth where the other gets the placement: both then take the
same path through the step, and the energy a placement adds is measured against the
same step without it. The bound on that difference: the placement pushes only the
vertices found at 0 <= d < th (the
others are outside, or released), each by at most th along the normal, with no
velocity. For a push dx of those vertices the potential energy (elastic + gravity)
changes by at most

    sum_i |f_i| |dx_i| + 1/2 omega_max^2 sum_i m_i |dx_i|^2,   |dx_i| <= th

(f_i the vertex's force before it, elastic, weight and applied; omega_max^2 the
largest eigenvalue of M^-1 K, :meth:`ClothSimulator.max_eigenvalue`, bounds the
Hessian's quadratic form by M omega_max^2), and the kinetic energy not at all (the
push is a position change; the contact response only removes normal approach and
tangential slip, which lowers it). :func:`_push_bound` doubles it for the terms beyond
second order and the synchronised kinetic energy's dependence on the force. Before the
release, the README's library cloth with a ground added under it gained 2.2 J in one
step (-0.36 J to +1.81 J), and the ball of the lying-cloth test below 41 J (explicit;
17.7 J implicit) against a bound of 13 mJ; the ground test's cloth stood up on it."""
import numpy as np
import pytest

from cosserat_ros.core import contact as C
from test_contact import _sim as _contact_sim, SOLVERS

#: the ball put through the lying cloth (``_lying``: vertices every 5 cm at z = th = 2
#: mm): centred 3 cm above the ground on the middle vertex, radius such that the 9
#: vertices within 7.1 cm of the axis are inside it and the 4 at 10 cm in its layer
#: but outside it (d = 0.85 mm): the placement pushes those 4
BALL = dict(center=(0.0, 0.0, 0.03), radius=0.103)


def _sim(n=12, side=0.6, solver='explicit'):
    """test_contact's cloth (its material; the explicit step at 0.9 of its critical dt,
    the implicit one at 1/60 s) as a 0.6 m square of 12 x 12 cells."""
    return _contact_sim(n, side, solver=solver)


def _hanging(solver='explicit', n=12):
    """The README's library scene at a smaller size: a square pinned at its two corners
    of largest y, let go flat at z = 0 and hanging for 1 s (down to z ~ -0.3 m)."""
    sim = _sim(n, solver=solver)
    sim.pin([n * (n + 1), n * (n + 1) + n])
    sim.step(int(round(1.0 / sim.dt)))
    return sim


def _lying(solver='explicit'):
    """A square lying flat on the ground (z = 0), settled for 0.2 s."""
    sim = _sim(solver=solver)
    sim.add_obstacle('plane', name='ground')
    x = sim.positions.copy()
    x[:, 2] = sim.contact_thickness
    sim.set_positions(x)
    sim.step(int(round(0.2 / sim.dt)))
    return sim


def _balance(sim):
    """total - external work + dissipated [J]: constant but for the integration error."""
    e = sim.energy()
    return e['total'] - e['external_work'] + e['dissipated']


def _push_bound(sim, d):
    """Twice the most a placement's push can add to the energy [J] (module docstring),
    for the vertices' distances ``d`` from the new obstacle; and how many it pushes."""
    th = sim.contact_thickness
    ring = (d >= 0.0) & (d < th) & ~sim.pinned
    if not ring.any():
        return 0.0, 0
    m = sim.coefficients.mass
    f = sim.internal_forces() + m[:, None] * sim.gravity + sim.vertex_forces
    w2 = sim.max_eigenvalue(at=sim.positions)
    push = th - d[ring]
    bound = (np.linalg.norm(f[ring], axis=1) @ push + 0.5 * w2 * m[ring] @ push ** 2)
    return 2.0 * float(bound), int(ring.sum())


def _distances(sim, oid):
    return sim._obstacles.distances(oid, sim.positions)


@pytest.mark.slow
@SOLVERS
def test_ground_added_under_a_hanging_cloth_leaves_it_hanging_through(solver):
    """A ground added at z = 0 under a cloth hanging below it. Every
    free vertex is inside the ground's solid, so each is released from it and nothing
    pushes: the cloth moves on exactly as its twin without the ground (positions within
    1e-9 m), the energy after one step and after 0.2 s is the twin's within 1e-9 J (the
    bound of the module docstring is 0: no vertex lies in the layer but outside), no
    vertex is in contact, none came up through the ground (not pulled back out), and
    the balance total - external + dissipated moves no more than the twin's."""
    sim, twin = _hanging(solver), _hanging(solver)
    free = ~sim.pinned
    assert sim.positions[free, 2].max() < 0.0            # hanging below the ground-to-be
    np.testing.assert_array_equal(sim.positions, twin.positions)
    e0, b0, tb0 = sim.energy()['total'], _balance(sim), _balance(twin)
    ground = sim.add_obstacle('plane', name='ground')
    twin.add_obstacle('plane', point=(0, 0, -10.0), name='ground')
    d = _distances(sim, ground)
    bound, pushed = _push_bound(sim, d)
    assert pushed == 0 and bound == 0.0
    assert sim.contact_state()['released'] == int(free.sum())
    for steps in (1, int(round(0.2 / sim.dt))):
        sim.step(steps)
        twin.step(steps)
        x, tx = sim.positions, twin.positions
        assert np.all(np.isfinite(x)) and np.all(np.isfinite(sim.velocities))
        np.testing.assert_allclose(x, tx, rtol=0, atol=1e-9)
        e, te = sim.energy(), twin.energy()
        assert abs(e['total'] - te['total']) <= 1e-9, (e['total'], te['total'], e0)
        assert abs((_balance(sim) - b0) - (_balance(twin) - tb0)) <= 1e-9
        assert e['external_work'] == pytest.approx(te['external_work'], abs=1e-9)
        state = sim.contact_state()
        assert state['contacts'] == 0 and state['deepest'] == 0.0
        assert state['released'] == int(free.sum())
        assert x[free, 2].max() < 0.0                    # still through the ground


def test_a_released_vertex_out_of_the_layer_is_held_from_then_on():
    """The release ends where the vertex comes out: the ground lowered at 1 m/s to 1.2 m
    (below the cloth, which hangs to ~0.6 m) passes every vertex, which is then released
    no more (cleared in the step that starts with it out of the layer, never before: a
    vertex still inside stays released), and the ground then put 1 cm below the cloth
    and raised at 0.05 m/s for 0.6 s pushes the cloth as any obstacle coming from
    outside: no free vertex is found deeper in its layer than the quarter thickness the
    ground may move in a call of the step (core/obstacles.py), and the rising ground
    does positive external work."""
    sim = _hanging()
    ground = sim.add_obstacle('plane', name='ground')
    free = ~sim.pinned
    n = int(free.sum())
    assert sim.contact_state()['released'] == n
    sim.set_obstacle_pose(ground, (0, 0, 0), (0, 0, 0, 1), linear_velocity=(0, 0, -1.0))
    counts = []
    while sim.obstacles[ground]['position'][2] > -1.2:
        sim.step(int(round(0.02 / sim.dt)))
        top = sim.obstacles[ground]['position'][2]
        counts.append(sim.contact_state()['released'])
        # a vertex still inside the ground, which only moves away from it, was inside
        # at the last step's start too: still released
        still = free & (sim.positions[:, 2] < top)
        assert np.all(C.released_rows(sim.control.contact)[still] == 1)
    assert counts[0] < n and counts[-1] == 0 and counts == sorted(counts, reverse=True)
    low = sim.positions[:, 2].min() - 0.01
    sim.set_obstacle_pose(ground, (0, 0, low), (0, 0, 0, 1))     # a jump: through nothing
    assert sim.contact_state()['released'] == 0
    w0 = sim.energy()['external_work']
    sim.set_obstacle_pose(ground, (0, 0, low), (0, 0, 0, 1), linear_velocity=(0, 0, 0.05))
    lowest = []
    for _ in range(30):
        sim.step(int(round(0.02 / sim.dt)))
        top = sim.obstacles[ground]['position'][2]
        lowest.append(float((sim.positions[free, 2] - top).min()))
    assert top == pytest.approx(low + 0.03, abs=1e-3)
    assert np.all(np.isfinite(sim.positions))
    # a call of the step moves the ground by at most th / 4 after its last step
    assert min(lowest) >= 0.75 * sim.contact_thickness, lowest
    assert sim.contact_state()['contacts'] > 0 and sim.contact_state()['released'] == 0
    assert sim.energy()['external_work'] - w0 > 0.0


@SOLVERS
def test_sphere_added_through_a_lying_cloth_stays_through_it(solver):
    """A ball (:data:`BALL`) added through the middle of a cloth lying on the ground:
    the 9 vertices inside it are released from it (the ground still holds them), the 4
    in its layer but outside it are pushed onto it (by 1.15 mm each). The energy after
    the placement step differs from the twin's without the ball by no more than the
    push bound of the module docstring, nothing becomes NaN, and after 0.3 s the
    released vertices are still inside the ball where they were (not pushed out: moved
    less than the push of their 4 neighbours, which stretches the cloth round them),
    the rest of the cloth outside its layer."""
    sim, twin = _lying(solver), _lying(solver)
    np.testing.assert_array_equal(sim.positions, twin.positions)
    e0, te0 = sim.energy()['total'], twin.energy()['total']
    ball = sim.add_obstacle('sphere', name='ball', **BALL)
    twin.add_obstacle('sphere', center=(5.0, 0.0, 0.03), radius=BALL['radius'],
                      name='ball')
    d = _distances(sim, ball)
    inside = d < 0.0
    assert inside.sum() == 9                              # the middle of the cloth
    assert sim.contact_state()['released'] == 9
    bound, pushed = _push_bound(sim, d)
    assert pushed == 4 and bound > 0.0
    push = (sim.contact_thickness - d[(d >= 0.0) & (d < sim.contact_thickness)]).max()
    x0 = sim.positions.copy()
    sim.step(1)
    twin.step(1)
    jump = (sim.energy()['total'] - e0) - (twin.energy()['total'] - te0)
    assert abs(jump) <= bound + 1e-9, (jump, bound, pushed)
    sim.step(int(round(0.3 / sim.dt)))
    x = sim.positions
    assert np.all(np.isfinite(x)) and np.all(np.isfinite(sim.velocities))
    d = _distances(sim, ball)
    assert np.all(d[inside] < 0.0)                        # still through the cloth
    # moved only by the 4 pushed neighbours' pull, by less than their push
    assert np.abs(x[inside] - x0[inside]).max() < push
    assert d[~inside].min() >= 0.99 * sim.contact_thickness
    assert sim.contact_state()['released'] == int(inside.sum())


def test_sphere_lifted_out_of_the_cloth_lets_the_vertices_go():
    """The ball of the test above, raised at 0.2 m/s by 8 cm (its lowest point then 5
    mm above the cloth): the vertices inside it come out through its bottom and are
    released no more, and the cloth lies flat on the ground as before the ball (every
    vertex within 0.1 th of its height before), the ball lifting nothing."""
    sim = _lying()
    ball = sim.add_obstacle('sphere', name='ball', **BALL)
    assert sim.contact_state()['released'] == 9
    z0 = sim.positions[:, 2].copy()
    sim.set_obstacle_pose(ball, BALL['center'], (0, 0, 0, 1), linear_velocity=(0, 0, 0.2))
    sim.step(int(round(0.4 / sim.dt)))
    assert sim.obstacles[ball]['position'][2] == pytest.approx(0.11, abs=1e-3)
    assert sim.contact_state()['released'] == 0
    assert np.abs(sim.positions[:, 2] - z0).max() < 0.1 * sim.contact_thickness


def test_a_pose_jump_releases_what_it_lands_on_and_carries_what_was_on_it():
    """set_obstacle_pose is a placement too. A ball moved by a jump from beside the
    cloth to through it releases the vertices it lands on (as if added there); the
    ground moved up by a jump of 1 cm under the cloth lying on it carries the cloth
    (every vertex was on its layer: none is released, the next step puts them on the
    layer at the new height, as before the release rule)."""
    sim = _lying()
    ball = sim.add_obstacle('sphere', center=(2.0, 0.0, 0.03), radius=BALL['radius'],
                            name='ball')
    assert sim.contact_state()['released'] == 0
    sim.set_obstacle_pose(ball, BALL['center'], (0, 0, 0, 1))
    inside = _distances(sim, ball) < 0.0
    assert inside.sum() == 9 and sim.contact_state()['released'] == 9
    sim.step(10)
    assert np.all(_distances(sim, ball)[inside] < 0.0)
    # the ball away again (a jump off the cloth: nothing inside, nothing released)
    sim.set_obstacle_pose(ball, (2.0, 0.0, 0.03), (0, 0, 0, 1))
    assert sim.contact_state()['released'] == 0
    ground = sim.find_obstacle('ground')
    sim.set_obstacle_pose(ground, (0, 0, 0.01), (0, 0, 0, 1))
    assert sim.contact_state()['released'] == 0
    sim.step(1)
    z = sim.positions[:, 2]
    assert z.min() >= 0.01 + 0.99 * sim.contact_thickness


def test_the_release_follows_its_obstacle_when_the_set_changes():
    """The masks are per table row: removing an obstacle before the ground moves the
    ground to row 0, and its released vertices with it (the cloth still hangs through
    it after a step: nothing pushed); removing the ground drops them."""
    sim = _hanging()
    box = sim.add_obstacle('box', center=(3.0, 0, 0), half_extents=(0.1, 0.1, 0.1))
    ground = sim.add_obstacle('plane', name='ground')
    n = sim.contact_state()['released']
    assert n == int((~sim.pinned).sum())
    assert np.all(C.released_rows(sim.control.contact)[~sim.pinned] == 2)   # row 1
    sim.remove_obstacle(box)
    assert np.all(C.released_rows(sim.control.contact)[~sim.pinned] == 1)   # row 0
    sim.step(1)
    assert sim.contact_state()['released'] == n and sim.contact_state()['contacts'] == 0
    assert sim.positions[~sim.pinned, 2].max() < 0.0     # none pushed up onto it
    sim.remove_obstacle(ground)
    assert sim.contact_state()['released'] == 0


@SOLVERS
def test_the_cloth_placed_anew_is_released_from_nothing(solver):
    """set_positions places the cloth, not an obstacle: a vertex it moves loses its
    release. The cloth hanging through a ground added under it (every free vertex
    released), laid flat on the ground at the thickness, rests on it (none falls
    through, every vertex held on the layer after 0.2 s); a vertex it does not move
    (the pins, and here the whole cloth set where it is) keeps what it had."""
    sim = _hanging(solver)
    sim.add_obstacle('plane', name='ground')
    n = sim.contact_state()['released']
    assert n == int((~sim.pinned).sum())
    sim.set_positions(sim.positions)                      # moves nothing: keeps them
    assert sim.contact_state()['released'] == n
    x = sim.mesh.vertices.copy()
    x[:, 2] = sim.contact_thickness
    sim.set_positions(x)
    assert sim.contact_state()['released'] == 0
    sim.step(int(round(0.2 / sim.dt)))
    z = sim.positions[:, 2]
    assert np.all(np.isfinite(z))
    assert z.min() >= 0.9 * sim.contact_thickness
