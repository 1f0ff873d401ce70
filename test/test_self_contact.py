"""Self-collision (cosserat_ros.core.self_contact): its geometry against brute force, and
scenes where the cloth folds onto itself, checked at every frame (30 Hz) by an
independent test (test/cloth_check.py, numpy only): no two triangles that share no vertex
intersect, and no vertex comes closer than half the thickness to a triangle that does not
hold it."""
import math
import os
from pathlib import Path
import sys

import numpy as np
import pytest

from cosserat_ros.core import self_candidates as CAND, self_contact as SC
from cosserat_ros.core.surface_query import segment_segment
from cosserat_ros.core.terms import TERMS
from cosserat_ros.mesh import ClothMesh, grid_mesh
from cosserat_ros.simulator import ClothSimulator, Material

sys.path.insert(0, os.path.dirname(__file__))
import cloth_check  # noqa: E402

G = 9.81
CLOTH = Material(zeta=50.0, xi=2e-5, phi=1e-6, density=0.2, damping=0.1)
FRAME = 1.0 / 30.0


def _sim(nx, ny, width, height, material=CLOTH):
    sim = ClothSimulator(grid_mesh(nx, ny, width=width, height=height), material, dt=1e-5,
                         check_dt=False)
    sim.dt = 0.9 * sim.critical_dt()
    sim.gravity = (0.0, 0.0, -G)
    sim.self_collision = True
    return sim


def _frames(sim, seconds, each=None):
    """Step ``seconds`` in frames of 1/30 s; after each frame check the cloth (the
    independent test) and call ``each(k)``; returns the closest vertex-triangle distance
    seen."""
    th = sim.contact_thickness
    per = max(1, int(round(FRAME / sim.dt)))
    closest = np.inf
    for k in range(int(round(seconds / FRAME))):
        if each is not None:
            each(k)
        sim.step(per)
        x = sim.positions
        hits = cloth_check.intersecting_pairs(x, sim.mesh.faces)
        assert len(hits) == 0, f'frame {k}: triangles {hits[:5].tolist()} intersect'
        closest = min(closest, cloth_check.closest_vertex_triangle(x, sim.mesh.faces, th))
        assert closest >= 0.5 * th, (f'frame {k}: a vertex {closest:.2e} m from a triangle; '
                                     f'{sim.self_contact_state()}')
    return closest


# ---------------------------------------------------------------- geometry

def test_segment_segment_is_the_closest_pair_of_points():
    """Ericson's closest points of two segments against a dense sampling of both."""
    rng = np.random.default_rng(4)
    s = np.linspace(0, 1, 401)
    for _ in range(40):
        p0, p1, q0, q1 = rng.normal(size=(4, 3))
        if _ % 5 == 0:
            q1 = q0 + 0.5 * (p1 - p0)                       # parallel
        dd, a, b = segment_segment(p0, p1, q0, q1)
        P = p0 + s[:, None] * (p1 - p0)
        Q = q0 + s[:, None] * (q1 - q0)
        brute = ((P[:, None] - Q[None]) ** 2).sum(-1).min()
        assert dd <= brute + 1e-12
        assert dd >= brute - 2e-5 * (1 + brute)
        d = p0 + a * (p1 - p0) - (q0 + b * (q1 - q0))
        assert d @ d == pytest.approx(dd, abs=1e-12)


@pytest.mark.slow
def test_candidates_are_every_pair_within_the_radius():
    """The spatial hash finds exactly the brute force's vertex-triangle and edge-edge
    pairs within the radius (incident pairs left out) on a cloth folded onto itself."""
    mesh = grid_mesh(10, 10, width=0.3, height=0.3)
    X = mesh.vertices
    # fold the sheet about y = 0 onto itself, 4 mm apart, with a wrinkle
    y = X[:, 1]
    x = np.stack([X[:, 0] + 0.003 * np.sin(40 * y), np.abs(y),
                  np.where(y > 0, 0.004, 0.0) + 0.001 * np.cos(30 * X[:, 0])], 1)
    radius, th = 0.008, 1e-4
    vt = np.zeros((10000, 2), np.int64)
    ee = np.zeros((40000, 2), np.int64)
    nvt, nee = CAND.build_candidates(x, X, mesh.faces, mesh.edges, radius, th, vt, ee,
                                   np.zeros(10000), np.zeros(40000))
    assert 0 < nvt <= len(vt) and 0 < nee <= len(ee)
    got_vt = {tuple(p) for p in vt[:nvt]}
    got_ee = {tuple(p) for p in ee[:nee]}
    F, E = mesh.faces, mesh.edges
    want_vt = set()
    for t in range(len(F)):
        others = np.setdiff1d(np.arange(len(x)), F[t])
        d = cloth_check.point_triangle_distance(
            x[others], *(np.repeat(x[F[t, k]][None], len(others), 0) for k in range(3)))
        want_vt |= {(int(i), t) for i in others[d < radius]}
    assert got_vt == want_vt
    s = np.linspace(0, 1, 41)
    want_ee = set()
    P = x[E[:, 0]][:, None] + s[None, :, None] * (x[E[:, 1]] - x[E[:, 0]])[:, None]
    for e in range(len(E)):
        f = np.arange(e + 1, len(E))
        f = f[~np.isin(E[f], E[e]).any(1)]
        dd = ((P[e][None, :, None] - P[f][:, None]) ** 2).sum(-1).min(axis=(1, 2))
        want_ee |= {(e, int(j)) for j in f[np.sqrt(dd) < radius * 0.999]}
    # sampled distances are upper bounds: every sampled pair is found, and every pair found
    # is within the radius by the exact test
    assert want_ee <= got_ee
    for e, f in got_ee:
        assert segment_segment(x[E[e, 0]], x[E[e, 1]], x[E[f, 0]], x[E[f, 1]])[0] \
            < radius ** 2
    # arrays too short: counts above their lengths, then at those lengths the same lists
    # in the same order (the parallel build's slabs put back in the serial order)
    short = CAND.build_candidates(x, X, mesh.faces, mesh.edges, radius, th,
                                np.zeros((8, 2), np.int64), np.zeros((8, 2), np.int64),
                                np.zeros(8), np.zeros(8))
    assert short[0] > 8 and short[1] > 8
    vt2, ee2 = np.zeros((short[0], 2), np.int64), np.zeros((short[1], 2), np.int64)
    vtd2, eed2 = np.zeros(short[0]), np.zeros(short[1])
    assert CAND.build_candidates(x, X, mesh.faces, mesh.edges, radius, th, vt2, ee2, vtd2,
                               eed2) == (nvt, nee)
    np.testing.assert_array_equal(vt2[:nvt], vt[:nvt])
    np.testing.assert_array_equal(ee2[:nee], ee[:nee])
    slabs = np.arange(-(-len(F) // CAND.BUILD_BLOCK)) % CAND.BUILD_SLABS
    assert len(set(slabs)) > 1                  # the triangles fill more than one slab


def _folded(n=12, size=0.3):
    """A sheet folded about y = 0 onto itself, 4 mm apart, with a wrinkle."""
    mesh = grid_mesh(n, n, width=size, height=size)
    X = mesh.vertices
    y = X[:, 1]
    x = np.stack([X[:, 0] + 0.003 * np.sin(40 * y), np.abs(y),
                  np.where(y > 0, 0.004, 0.0) + 0.001 * np.cos(30 * X[:, 0])], 1)
    return mesh, x


def _pairs(rows, dist, count):
    return {tuple(int(k) for k in r): float(d) for r, d in zip(rows[:count], dist[:count])}


def test_a_partial_refresh_finds_what_a_full_build_finds_at_its_references():
    """After a partial refresh the list holds exactly the pairs, with the same distances,
    that a full build finds at the positions it now refers to (the moved vertices where
    they are, the others where the list was built): the list's bound stays true for every
    pair it leaves out. Three refreshes in a row, each moving a patch of vertices (part of
    both layers) and the whole cloth rigidly, the last with the arrays too short."""
    mesh, x = _folded()
    th = 1e-4
    sc = SC.SelfCollision(mesh)
    sc._build(x, th, 0.006)
    rng = np.random.default_rng(7)
    for trial in range(3):
        x0 = sc.xb.copy()
        c = x0[rng.integers(len(x0))]
        patch = np.linalg.norm(x0[:, :2] - c[:2], axis=1) < 0.05
        assert 0 < patch.sum() < 0.25 * len(x0)
        x0[patch] += rng.normal(scale=0.002, size=(patch.sum(), 3))
        x0 += [0.02, -0.01, 0.03]                       # rigid: moves no pair
        if trial == 2:
            sc.vt, sc.vtd = sc.vt[:sc.nvt + 2].copy(), sc.vtd[:sc.nvt + 2].copy()
            sc.ee, sc.eed = sc.ee[:sc.nee + 2].copy(), sc.eed[:sc.nee + 2].copy()
        CAND._displacement(x0, sc.xb, sc.moved)
        CAND._displacement(x0, x0, sc.step_moved)          # no motion in this step
        far = sc.moved > CAND.REFRESH * sc.skin
        xb = sc.xb.copy()
        assert sc._refresh(x0, x0, th)
        # the vertices that moved furthest took new references, where all of them have
        # moved alike (the mean's shift); the others keep theirs
        assert np.all(sc.fresh[far]) and sc.fresh.sum() >= patch.sum() // 2
        assert np.ptp(sc.moved[sc.fresh]) < 1e-12
        np.testing.assert_array_equal(sc.xb[~sc.fresh], xb[~sc.fresh])
        n = 4 * (sc.nvt + sc.nee) + 64
        vt, ee = np.zeros((n, 2), np.int64), np.zeros((n, 2), np.int64)
        vtd, eed = np.zeros(n), np.zeros(n)
        nvt, nee = CAND.build_candidates(sc.xb, mesh.vertices, mesh.faces, mesh.edges,
                                       th + sc.skin, th, vt, ee, vtd, eed)
        assert nvt <= n and nee <= n
        for got, want in ((_pairs(sc.vt, sc.vtd, sc.nvt), _pairs(vt, vtd, nvt)),
                          (_pairs(sc.ee, sc.eed, sc.nee), _pairs(ee, eed, nee))):
            assert got.keys() == want.keys()
            assert all(got[k] == want[k] for k in want)
        assert len(_pairs(sc.vt, sc.vtd, sc.nvt)) == sc.nvt > 0
        assert len(_pairs(sc.ee, sc.eed, sc.nee)) == sc.nee > 0
    # most of the vertices moved: no partial refresh, the list is built anew
    x0 = sc.xb + rng.normal(scale=0.01, size=sc.xb.shape)
    CAND._displacement(x0, sc.xb, sc.moved)
    xb = sc.xb.copy()
    assert not sc._refresh(x0, x0, th)
    np.testing.assert_array_equal(sc.xb, xb)


def test_a_sliding_layer_has_its_candidates_distances_taken_again():
    """The upper layer of a folded sheet slides over the lower one: every vertex moves
    relative to the others, so the live pairs' bound (distance where it was taken, less
    the displacement since) loosens for every pair though none comes closer. Once the
    live pairs added, times the steps since, outnumber the candidates
    (SelfCollision._swollen), every candidate's distance is taken again where that step
    began (_rebase): their distances there, for the same list (no build, no refresh),
    and fewer pairs live."""
    from types import SimpleNamespace
    from cosserat_ros.core.state import Control, State
    from cosserat_ros.core.surface_query import point_triangle_sq
    mesh, x = _folded()
    n = len(x)
    sc = SC.SelfCollision(mesh)
    control = Control.empty(n)
    coeff = SimpleNamespace(mass=np.full(n, 1e-3))
    state = State(x.copy(), np.zeros((n, 3)), np.zeros(2))
    sc.begin(state.x, state.v)
    sc.after_step(state, control, coeff, 1e-4)             # the first list
    upper = x[:, 2] > 0.002
    live = []
    for _ in range(1000):
        start = state.x.copy()
        state.x[upper, 0] += 2e-5                          # 0.2 m/s, well within the skin
        sc.after_step(state, control, coeff, 1e-4)
        live.append(sc.nlive)
        if sc.rebases:
            break
    assert sc.rebases == 1 and sc.builds == 1 and sc.refreshes == 0
    assert len(live) > 2 and live[-1] < max(live[:-1])     # the live pairs swelled, then fell
    np.testing.assert_array_equal(sc.xd, start)
    # every candidate's distance is the one there
    E = mesh.edges
    for p in range(sc.nvt):
        i, t = sc.vt[p]
        a, b, c = mesh.faces[t]
        assert sc.vtd[p] == pytest.approx(math.sqrt(point_triangle_sq(
            *start[i], start[a], start[b], start[c])[0]), rel=1e-12)
    for q in range(sc.nee):
        e, f = sc.ee[q]
        assert sc.eed[q] == pytest.approx(math.sqrt(segment_segment(
            start[E[e, 0]], start[E[e, 1]], start[E[f, 0]], start[E[f, 1]])[0]), rel=1e-12)


def test_switches_and_their_checks():
    sim = ClothSimulator(grid_mesh(4, 4), CLOTH, dt=1e-5, check_dt=False)
    assert sim.self_collision is False
    assert sim.self_contact_state()['active'] == 0
    with pytest.raises(ValueError, match='True or False'):
        sim.self_collision = 'yes'
    with pytest.raises(ValueError, match='>= 0'):
        sim.self_friction = -0.1
    with pytest.raises(ValueError, match='number'):
        sim.self_friction = 'high'
    sim.self_friction = 0.8
    sim.self_collision = True
    assert sim.self_friction == 0.8 and sim.self_collision


def test_a_cloth_that_cannot_touch_itself_steps_many_steps_per_call():
    # a flat cloth lying on the ground has no pair near: the steps go in calls of many
    # (no response after each) and end where the same cloth without self-collision ends,
    # to the bit
    sims = []
    for on in (False, True):
        sim = _sim(12, 12, 0.4, 0.4)
        sim.set_positions(sim.mesh.vertices + [0.0, 0.0, 0.01])
        sim.add_obstacle('plane')
        sim.self_collision = on
        sims.append(sim)
    calls = []
    step = sims[1].solver.step
    sims[1].solver.step = lambda k, *a: calls.append(k) or step(k, *a)
    for sim in sims:
        sim.step(400)
    assert np.array_equal(sims[0].state.x, sims[1].state.x)
    assert np.array_equal(sims[0].state.v, sims[1].state.v)
    assert sum(calls) == 400 and len(calls) < 40, calls


def test_a_call_that_moves_further_than_its_room_is_an_overrun():
    sim = _sim(8, 8, 0.3, 0.3)
    sim.step(1)                                        # the first list
    own = sim._self
    x, v = sim.state.x.copy(), sim.state.v.copy()
    th = sim.contact_thickness
    free = own.free_steps(x, v, th, sim.dt)
    # the list's skin bounds the room: half the skin at most, and a fast cloth
    # (FREE_SPEED at the least) takes fewer steps
    assert 0.0 < own.room <= 0.5 * own.skin and free >= 2
    assert free <= 0.5 * own.room / (SC.FREE_SPEED * sim.dt) + 1
    moved = x.copy()
    moved[0] += [0.0, 0.0, 0.9 * own.room]
    assert not own.overran(x, moved, free, sim.dt)
    moved[0] += [0.0, 0.0, 0.2 * own.room]
    assert own.overran(x, moved, free, sim.dt)
    # the next calls take the cloth to be twice as fast as that overrun (not the same
    # call again and again, each overrunning)
    assert own.free_steps(x, v, th, sim.dt) < free / 2
    # a rigid translation moves no vertex relative to the others
    assert not own.overran(x, x + [0.0, 0.0, 10.0 * own.room], free, sim.dt)
    # a thicker layer than the list was built for: one step per call (and a new list)
    sim.contact_thickness = 2.0 * th
    assert own.free_steps(x, v, 2.0 * th, sim.dt) == 0
    sim.step(1)
    assert own.built_th == 2.0 * th
    sim.contact_thickness = th
    # a pair near: one step per call
    own.nlive = 1
    assert own.free_steps(x, v, th, sim.dt) == 0


# ---------------------------------------------------------------- scenes

@pytest.mark.slow
@pytest.mark.parametrize('solver', ['explicit', 'implicit'])
def test_a_dropped_cloth_crumples_onto_the_ground_without_passing_through_itself(solver):
    """A 0.5 m cloth, nearly upright, its lower edge 0.5 m above the ground, falls and
    folds onto itself; with the explicit solver the energy never rises above its start.
    The implicit solver at dt = 1/30 s (a relative motion of ~10 thicknesses a step: the
    response in stages), 12 x 12, until it lies crumpled (0.9 s); its energy is not
    checked here:
    the ground's contact is part of its solve (without self-collision the same drop
    never gains energy: test_contact.py), but self-collision answers after the solve and
    fights it, so its solves hit the iteration limit and the energy rises to 2.5 times
    its start."""
    if solver == 'explicit':
        sim = _sim(16, 16, 0.5, 0.5)
    else:
        # 12 x 12: at 16 x 16 the solves' fight with the response after them (below)
        # took 25-100 s of stepping, depending on the last bits of the arithmetic
        sim = ClothSimulator(grid_mesh(12, 12, width=0.5, height=0.5), CLOTH, dt=1 / 30,
                             solver='implicit')
        sim.gravity = (0.0, 0.0, -G)
        sim.self_collision = True
    X = sim.mesh.vertices
    y = X[:, 1] - X[:, 1].min()
    a = math.radians(80)
    x = np.stack([X[:, 0] + 2e-3 * np.sin(7 * y), y * math.cos(a), 0.5 + y * math.sin(a)],
                 1)
    sim.set_positions(x)
    sim.add_obstacle('plane', name='ground')
    e0 = sim.energy()['total']
    folded = []

    def each(k):
        folded.append(sim.self_contact_state()['active'])
        if solver == 'explicit':
            assert sim.energy()['total'] <= e0 * 1.005
    _frames(sim, 1.5 if solver == 'explicit' else 0.9, each)
    assert max(folded) > 0                                  # it did touch itself
    if solver == 'explicit':
        # the list was refreshed in part around the vertices that moved, and the check
        # above held through those refreshes
        assert sim.self_contact_state()['refreshes'] > 0
    assert sim.positions[:, 2].max() < 0.15                 # and lies crumpled
    assert sim.positions[:, 2].min() > 0.9 * sim.contact_thickness


@pytest.mark.slow
def test_a_cloth_draped_over_a_sphere_lets_its_edges_fall_onto_each_other():
    """A 0.9 m cloth dropped from 1 m onto a sphere of radius 0.15 m: its sides hang and
    fold into one another, never through."""
    sim = _sim(18, 18, 0.9, 0.9)
    sim.set_positions(sim.mesh.vertices + np.array([0.0, 0.0, 1.0]))
    sim.add_obstacle('sphere', center=(0, 0, 0.0), radius=0.15, name='ball')
    touched = []
    _frames(sim, 1.6, lambda k: touched.append(sim.self_contact_state()['active']))
    assert max(touched) > 0
    assert sim.positions[:, 2].min() < -0.15                # the sides hang down


def test_the_drape_steps_on_from_the_state_where_a_crumpled_stencil_blew_it_up():
    """test/data/drape_pinch.npz: positions and velocities of the drape above at 1.5 s,
    from a run that diverged in the next step (one vertex from 1.8 to 116 m/s). The cloth
    is crumpled inside vertex 279's jet stencil: every edge near its rest length, but the
    fitted tangents a_1, a_2 parallel (|a_1 x a_2| 1.7e-5 of rest), and a unit normal's
    derivative gave its neighbours a bending force of 90 N (median 0.005 N). The floored
    normal (jet.floored_normal) bounds it; the drape goes on."""
    sim = _sim(18, 18, 0.9, 0.9)
    sim.add_obstacle('sphere', center=(0, 0, 0.0), radius=0.15, name='ball')
    data = np.load(Path(__file__).parent / 'data' / 'drape_pinch.npz')
    f = np.linalg.norm(TERMS['bending'].gradient(sim.model, sim.coefficients, data['x']), axis=1)
    weight = sim.coefficients.mass.max() * G
    assert f.max() < 10 * weight, f'bending force {f.max():.3g} N, weight {weight:.3g} N'
    sim.set_positions(data['x'])
    sim.set_velocities(data['v'])
    for _ in range(6):
        sim.step(max(1, int(round(FRAME / sim.dt))))
        assert np.linalg.norm(sim.velocities, axis=1).max() < 5.0     # free fall from 1 m: 4.4


@pytest.mark.slow
def test_two_handles_fold_a_cloth_in_half_on_the_ground():
    """Two handles lift one edge of a cloth lying on the ground, carry it over in an
    arc, lay it on the other half and let go: the halves end on top of each other."""
    sim = _sim(14, 14, 0.4, 0.4)
    th = sim.contact_thickness
    sim.set_positions(sim.mesh.vertices + np.array([0.0, 0.0, th]))
    sim.add_obstacle('plane', name='ground')
    X = sim.positions
    top = X[:, 1].max()
    hs = [sim.grasp(point=(xc, top, th), radius=0.02) for xc in (X[:, 0].min(),
                                                                 X[:, 0].max())]
    R, K = top, 36

    def each(k):
        if k < K:
            t = math.pi * (k + 1) / K
            for h, xc in zip(hs, (X[:, 0].min(), X[:, 0].max())):
                sim.move_handle(h, (xc, R * math.cos(t), 4 * th + 0.7 * R * math.sin(t)),
                                duration=FRAME)
        elif k == K + 3:
            for h in hs:
                sim.release(h)
    _frames(sim, (K + 15) * FRAME, each)
    x = sim.positions
    lifted = X[:, 1] > 0.02                    # the half that was carried over
    assert np.all(x[lifted, 1] < 0.05)
    assert x[lifted, 2].mean() > x[~lifted, 2].mean() + th


@pytest.mark.slow
@pytest.mark.parametrize('mu', [0.0, 0.8])
def test_an_upper_layer_pulled_over_a_lower_one_drags_it_only_with_friction(mu):
    """Two equal 0.3 m sheets, one lying on the other on a ground of mu = 0.3; a handle
    pulls the upper sheet's edge 6 cm along the ground. Without friction between the
    layers the lower sheet stays; with mu = 0.8 (0.8 of the upper sheet's weight against
    0.3 of both sheets') it is dragged along."""
    sheet = grid_mesh(12, 12, width=0.3, height=0.3)
    n = sheet.n_vertices
    rest = np.concatenate([sheet.vertices, sheet.vertices + np.array([0.0, 0.0, 1.0])])
    mesh = ClothMesh(rest, np.concatenate([sheet.faces, sheet.faces + n]))
    sim = ClothSimulator(mesh, CLOTH, dt=1e-5, check_dt=False)
    sim.dt = 0.9 * sim.critical_dt()
    sim.gravity = (0.0, 0.0, -G)
    sim.self_collision = True
    sim.self_friction = mu
    th = sim.contact_thickness
    x = rest.copy()
    x[:n, 2] = th
    x[n:, 2] = 2 * th + 5e-4
    sim.set_positions(x)
    sim.add_obstacle('plane', friction=0.3, name='ground')
    sim.step(int(round(0.2 / sim.dt)))                  # the upper sheet settles
    lower = np.arange(n)
    start = sim.positions[lower].mean(0)
    upper = n + np.arange(n)
    edge = upper[rest[upper, 1] >= rest[:, 1].max() - 1e-9]
    c = sim.positions[edge].mean(0)
    h = sim.grasp(vertices=edge, point=c)
    sim.move_handle(h, c + np.array([0.0, 0.06, 0.0]), duration=0.5)
    _frames(sim, 0.6)
    moved = np.linalg.norm(sim.positions[lower].mean(0) - start)
    slid = sim.positions[upper, 1].mean() - sim.positions[lower, 1].mean()
    if mu == 0.0:
        assert moved < 0.003
        assert slid > 0.04                              # the upper sheet slid over it
    else:
        assert moved > 0.02


@pytest.mark.slow
def test_a_strip_twisted_by_two_handles_touches_itself_without_crossing():
    """A 0.6 x 0.06 m strip held at both ends, one end turned by 360 degrees about the
    strip's axis while the ends come 0.4 m apart: the twisted strip sags and coils onto
    itself (its buckling seeded by a small bow). The independent check sees it come
    within the contact layer of itself and never closer than half of it."""
    sim = _sim(30, 3, 0.6, 0.06)
    th = sim.contact_thickness
    X = sim.mesh.vertices
    bow = X.copy()
    bow[:, 2] += 0.01 * np.sin(math.pi * (X[:, 0] - X[:, 0].min()) / 0.6)
    sim.set_positions(bow)
    left = np.flatnonzero(X[:, 0] <= X[:, 0].min() + 1e-9)
    right = np.flatnonzero(X[:, 0] >= X[:, 0].max() - 1e-9)
    xl, xr = X[:, 0].min(), X[:, 0].max()
    hl = sim.grasp(vertices=left, point=(xl, 0.0, 0.0))
    hr = sim.grasp(vertices=right, point=(xr, 0.0, 0.0))
    K = 60

    def each(k):
        if k < K:
            t = 2 * math.pi * (k + 1) / K
            q = (math.sin(t / 2), 0.0, 0.0, math.cos(t / 2))
            sim.move_handle(hr, (xr - 0.1 * (k + 1) / K, 0.0, 0.0), q, duration=FRAME)
            sim.move_handle(hl, (xl + 0.1 * (k + 1) / K, 0.0, 0.0), duration=FRAME)
    assert _frames(sim, (K + 15) * FRAME, each) < 1.5 * th


def test_the_closest_point_of_a_triangle_without_area_is_finite():
    """Two corners at one point (a degenerate triangle of a crumpled or scripted cloth):
    the closest point is the nearest point of its edges, not the 0 / 0 of the edge
    region's ratio (surface_query.triangle_barycentric), NaN before."""
    from cosserat_ros.core.surface_query import point_triangle_sq
    o, c = np.zeros(3), np.array([1.0, 0.0, 0.0])
    for a, b, cc, want in [(o, o, c, (0.5, 0.0, 0.0)), (o, c, o, (0.5, 0.0, 0.0)),
                           (c, o, o, (0.5, 0.0, 0.0)), (o, o, o, (0.0, 0.0, 0.0)),
                           (o, 0.5 * c, c, (0.5, 0.0, 0.0))]:
        d2, u, v, w = point_triangle_sq(0.5, 1.0, 0.0, a, b, cc)
        assert u + v + w == pytest.approx(1.0) and min(u, v, w) >= 0.0
        q = u * a + v * b + w * cc
        np.testing.assert_allclose(q, want, atol=1e-15)
        assert d2 == pytest.approx(np.sum((np.array([0.5, 1.0, 0.0]) - q) ** 2))
