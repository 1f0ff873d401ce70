"""Self-collision: the cloth folds onto itself without passing through.

Contacts
--------
Two kinds of pair, each within the contact thickness ``th`` (the same as obstacle
contact's, ``Control.contact_params[0]``):

* vertex-triangle: vertex i and a triangle (a, b, c) that does not hold i, closest point
  ``q = u x_a + v x_b + w x_c`` (Ericson 5.1.5, :func:`.surface_query.point_triangle_sq`);
* edge-edge: edges (a0, a1) and (b0, b1) that share no vertex, closest points
  ``p = (1 - s) x_a0 + s x_a1`` and ``q = (1 - t) x_b0 + t x_b1`` (Ericson 5.1.9,
  :func:`segment_segment`).

Pairs that lie within ``th`` of each other in the rest shape (a sliver triangle's vertex
next to its neighbour) are topology, not contact, and are left out.

Both are one constraint on up to four vertices k with weights ``w_k`` (side A positive,
side B negative: (1, -u, -v, -w) and (1 - s, s, -(1 - t), -t)), the unit normal ``n``
from B to A and the distance d, all taken at the positions ``x0`` where the step began::

    g = d + n . sum_k w_k (x_k - x0_k)          the gap at the step's end, to first order

Response: inelastic, on positions and velocities together (Bridson, Fedkiw and Anderson
2002, Sec. 7.1-7.2, as a Gauss-Seidel projection)
-----------------------------------------------------------------------------------
After every step (explicit or implicit) each pair must end with ``g >= target`` where
``target = th`` for a pair that began outside the layer and ``d + min(th - d, S dt)``
for one that began inside it (back to the layer at most at the speed :data:`SEP_SPEED`;
drift of second order, never a kick). A pair short of its target gets the impulse that
closes the gap exactly, shared by inverse mass (a pinned or held vertex has none)::

    lam  = (target - g) / W,     W = sum_k w_k^2 / m_k
    dx_k = w_k lam n / m_k                      (x_k += dx_k,  v_k += dx_k / dt)

which conserves momentum (sum_k m_k dx_k = lam n sum_k w_k = 0 since the weights of
each side sum to one) and removes the pair's approach velocity (inelastic). Coulomb
friction between the layers follows on the pair's relative tangential motion of the
step ``r_t = (I - n n^T) sum_k w_k (x_k - x0_k)``: it stops if ``|r_t| <= mu (target -
g)`` (static: the tangential correction bounded by mu times the normal one, in the same
units) and is otherwise reduced by that much. Pairs share vertices, so the corrections
are swept (Gauss-Seidel) over the pairs that were short until none moves, at most
:data:`SWEEPS` sweeps, then every live pair is checked again and the rounds repeat (at
most :data:`ROUNDS`; what is still short by more than :data:`SLACK` of th is reported
and kept from approaching further by the next step). A vertex the response pushes into
an obstacle's contact layer is put back on it at once (position and velocity, the
obstacle's impulse added to its contact force), so a layer pressed onto the ground stays
on it and the ground carries the weight of both.

Sliding contacts: the gap above is linear in the step's displacement, so a vertex sliding
over a curved or kinked layer sees it drift by about ``|slip|^2 / d``. Whenever a pair
acted or began the step within ``th``, the response therefore runs once more from the
exact geometry at the step's end (closest points and normals there; friction already
applied), against the same targets, which every pass takes from the pair's distance
where the step began: a pair that began outside the layer ends on it, not inside by the
drift, and one that began inside ends no closer than it began. Only when that drift can
exceed the slack (:func:`drifts`: (2 step)^2 / d > SLACK th, with step the step's
relative motion and d the closest live pair's distance where it began); a layer at rest
on another or sliding slowly over it, whose gap the first pass then holds to within
twice the slack (its own tolerance and the drift), skips it (half the cost of a folded
cloth's response).

Energy: the response removes the energy :func:`_ledger` measures (kinetic, and the
potential change over its displacement), counted as dissipation in ``State.acc``.

Why no crossing: a pair that ends every step at ``g >= th`` along its own normal cannot
change sides within a step whose relative motion is below ``th`` (the explicit step
moves a vertex far less: a 5 m/s fall at dt = 3e-4 s is 1.5 mm). A larger step (the
implicit solver's: 1 m/s relative at 1/60 s is 17 mm) is answered in stages: the
solver's displacement is split into the fewest equal parts that each move a vertex at
most :data:`STAGE` th relative to the others, and each part's constraints are linearised
where the previous part ended (the response so far included); velocities change by the
positions' change over the whole step (backward Euler's x1 = x0 + dt v1 still holds).

Candidates: the pairs that can come within ``th`` are kept in a Verlet list, built,
refreshed in part and re-measured as :mod:`.self_candidates` describes.

This module imports no ROS package.
"""
from __future__ import annotations

import math
from typing import Dict

import numba as nb
import numpy as np

from .compiled import kernel
from .contact import C_FORCE, C_FORCE2, C_ID, C_ID2, _bit, distance, released
from .self_candidates import (PAIR_CHUNK, REBASE_LIVE, REFRESH_MOST, REFRESH_SKIN, SKIN,
                              SKIN_EDGE, STEPS_PER_BUILD, _displacement, _displacements,
                              _distances, _keep_untouched, _renew, _room, _select,
                              build_candidates, first_vertex_lists, scan_candidates)
from .surface_query import point_triangle_sq, segment_segment
from .terms.jet import cross

__all__ = ['SelfCollision', 'segment_segment', 'build_candidates', 'warm', 'SWEEPS',
           'ROUNDS', 'SEP_SPEED', 'DEFAULT_FRICTION']

#: Gauss-Seidel sweeps over the pairs short of their target, per round
SWEEPS = 16
#: rounds of (check every live pair, sweep the short ones)
ROUNDS = 4
#: [m/s] the fastest a pair that began inside the layer is moved back out to it
SEP_SPEED = 0.05
#: a step whose relative motion exceeds this many thicknesses is answered in stages
#: (module docstring: the implicit solver's large steps)
STAGE = 0.5
#: a pair short of its target by less than this fraction of th counts as satisfied
SLACK = 1e-2
#: friction coefficient between two layers of the cloth (static = kinetic)
DEFAULT_FRICTION = 0.5
#: [m/s] the relative speed a cloth is assumed to have at least when the steps it can
#: take without a response are counted (:meth:`SelfCollision.free_steps`)
FREE_SPEED = 0.25


@kernel(inline='always')
def _gap(p, x, x0, gi, gw, gn, gd, go):
    """Gap of pair p at the step's end, along its normal at the start; ``go[p]``: side
    B's own displacement over the step when it is not the cloth (a moving obstacle's
    point, :mod:`.features`; zero here)."""
    g = gd[p] - (gn[p, 0] * go[p, 0] + gn[p, 1] * go[p, 1] + gn[p, 2] * go[p, 2])
    for k in range(4):
        j = gi[p, k]
        g += gw[p, k] * (gn[p, 0] * (x[j, 0] - x0[j, 0]) + gn[p, 1] * (x[j, 1] - x0[j, 1])
                         + gn[p, 2] * (x[j, 2] - x0[j, 2]))
    return g


@kernel(inline='always')
def _deficit(p, x, x0, gi, gw, gn, gd, go, g0, th, sep):
    """How far pair p falls short of its target at the step's end [m]: the target from
    its distance ``g0[p]`` where the whole step began, the gap linearised at x0; the pair
    is short when this exceeds the slack ``SLACK th``."""
    return _target(g0[p], th, sep) - _gap(p, x, x0, gi, gw, gn, gd, go)


@kernel(inline='always')
def _target(d, th, sep):
    """The gap a pair must end the step with (module docstring)."""
    # inside the layer: back out by sep beyond the slack that counts as satisfied, so a
    # pair inside does climb back (a slack larger than sep would let it stay and drift)
    return th if d >= th else d + min(th - d, sep + SLACK * th)


@kernel(parallel=True)
def _pair_geometry(x0, x, faces, edges, vt, nvt, ee, live, nlive, gi, gw, gn, gd, go, g0,
                   first, th, sep, flag):
    """The constraint of each live candidate ``live[:nlive]`` (an index into the
    vertex-triangle pairs, then the edge-edge pairs) at the step's start x0 (module
    docstring), in slot p of: vertices
    gi (P,4), weights gw (P,4), normal gn (P,3) from side B to side A, distance gd (P,).
    A pair at zero distance takes the triangle's normal (or the edges' cross product)
    turned towards A's side; if that too is undefined it gets weight 0 (skipped).
    ``first``: x0 is where the step began, and g0 (each pair's distance there, which
    sets its target: :func:`_deficit`) takes gd. flag[p]: 1 if the pair is short of its
    target at the step's end x (:func:`_short`). In chunks of :data:`PAIR_CHUNK` pairs
    (:func:`_pair_range`: the arrays' reference counts change once a chunk)."""
    for c in nb.prange((nlive + PAIR_CHUNK - 1) // PAIR_CHUNK):
        _pair_range(c * PAIR_CHUNK, min(nlive, (c + 1) * PAIR_CHUNK), x0, x, faces, edges,
                    vt, nvt, ee, live, gi, gw, gn, gd, go, g0, first, th, sep, flag)


@kernel(refcount=False)
def _pair_range(lo, hi, x0, x, faces, edges, vt, nvt, ee, live, gi, gw, gn, gd, go, g0,
                first, th, sep, flag):
    """:func:`_pair_geometry` for the live pairs lo..hi-1, without reference counting
    (:func:`.compiled.kernel`: the rows of x0 it passes on are views)."""
    for p in range(lo, hi):
        cand = live[p]
        if cand < nvt:
            i = vt[cand, 0]
            t = vt[cand, 1]
            a = faces[t, 0]
            b = faces[t, 1]
            c = faces[t, 2]
            dd, u, v, w = point_triangle_sq(x0[i, 0], x0[i, 1], x0[i, 2], x0[a], x0[b],
                                            x0[c])
            gi[p, 0] = i
            gi[p, 1] = a
            gi[p, 2] = b
            gi[p, 3] = c
            gw[p, 0] = 1.0
            gw[p, 1] = -u
            gw[p, 2] = -v
            gw[p, 3] = -w
            # the fallback direction: the triangle's normal, (b - a) x (c - a)
            p1, q1, p2, q2 = a, b, a, c
        else:
            q = cand - nvt
            e = ee[q, 0]
            f = ee[q, 1]
            a0 = edges[e, 0]
            a1 = edges[e, 1]
            b0 = edges[f, 0]
            b1 = edges[f, 1]
            dd, s, t = segment_segment(x0[a0], x0[a1], x0[b0], x0[b1])
            gi[p, 0] = a0
            gi[p, 1] = a1
            gi[p, 2] = b0
            gi[p, 3] = b1
            gw[p, 0] = 1.0 - s
            gw[p, 1] = s
            gw[p, 2] = t - 1.0
            gw[p, 3] = -t
            # the fallback direction: the edges' cross product
            p1, q1, p2, q2 = a0, a1, b0, b1
        f0, f1, f2 = cross(x0[q1, 0] - x0[p1, 0], x0[q1, 1] - x0[p1, 1], x0[q1, 2] - x0[p1, 2],
                           x0[q2, 0] - x0[p2, 0], x0[q2, 1] - x0[p2, 1], x0[q2, 2] - x0[p2, 2])
        # the vector from side B's point to side A's: sum_k w_k x0_k
        r0 = 0.0
        r1 = 0.0
        r2 = 0.0
        for k in range(4):
            j = gi[p, k]
            r0 += gw[p, k] * x0[j, 0]
            r1 += gw[p, k] * x0[j, 1]
            r2 += gw[p, k] * x0[j, 2]
        set_normal(p, r0, r1, r2, f0, f1, f2, gw, gn, gd, g0, first)
        flag[p] = 1 if _deficit(p, x, x0, gi, gw, gn, gd, go, g0, th, sep) > SLACK * th else 0


@kernel(inline='always')
def set_normal(p, r0, r1, r2, f0, f1, f2, gw, gn, gd, g0, first):
    """Pair p's normal gn[p] = r / |r| (r: from side B's point to side A's) and distance
    gd[p] = |r|; at zero distance the fallback direction f normalised, and if that too is
    zero the pair gets weight 0 (skipped). ``first``: g0[p] (the distance that sets the
    pair's target) takes gd[p] too."""
    d = math.sqrt(r0 * r0 + r1 * r1 + r2 * r2)
    if d > 1e-12:
        gn[p, 0] = r0 / d
        gn[p, 1] = r1 / d
        gn[p, 2] = r2 / d
    else:
        fn = math.sqrt(f0 * f0 + f1 * f1 + f2 * f2)
        if fn > 0.0:
            gn[p, 0] = f0 / fn
            gn[p, 1] = f1 / fn
            gn[p, 2] = f2 / fn
        else:
            for k in range(gw.shape[1]):
                gw[p, k] = 0.0
            gn[p, 0] = 0.0
            gn[p, 1] = 0.0
            gn[p, 2] = 1.0
    gd[p] = d
    if first:
        g0[p] = d


@kernel(refcount=False)
def _short(x, x0, gi, gw, gn, gd, go, g0, npair, th, sep, slack, flag):
    """flag[p] = 1 for every pair short of its target by more than ``slack`` [m];
    returns how many."""
    k = 0
    for p in range(npair):
        f = 1 if _deficit(p, x, x0, gi, gw, gn, gd, go, g0, th, sep) > slack else 0
        flag[p] = f
        k += f
    return k


@kernel(inline='always')
def _kick(j, x, v, dt, c0, c1, c2):
    """Move vertex j by c (c0, c1, c2) [m] and its velocity by c / dt."""
    x[j, 0] += c0
    x[j, 1] += c1
    x[j, 2] += c2
    v[j, 0] += c0 / dt
    v[j, 1] += c1 / dt
    v[j, 2] += c2 / dt


@kernel(refcount=False)
def _onto_obstacles(j, x, v, dt, mass, ob, meta, data, th, contact):
    """Vertex j, just moved by the response, back onto the contact layer of every
    obstacle it entered (position and velocity, as an impulse of the obstacle: its force
    is added to ``Control.contact``), but those it is released from (placed through it:
    :func:`.contact.released`)."""
    free = released(contact, j)
    for k in range(ob.shape[0]):
        if free & _bit(k):
            continue
        d, n0, n1, n2 = distance(ob, meta, data, k, x[j, 0], x[j, 1], x[j, 2])
        if d >= th:
            continue
        c = th - d
        _kick(j, x, v, dt, c * n0, c * n1, c * n2)
        f = mass[j] * c / (dt * dt)
        contact[j, C_FORCE] += f * n0
        contact[j, C_FORCE + 1] += f * n1
        contact[j, C_FORCE + 2] += f * n2
        if contact[j, C_ID] < 0.0 or contact[j, C_ID] == k:
            contact[j, C_ID] = k
        else:                                   # the step's second obstacle: its share
            contact[j, C_FORCE2] += f * n0
            contact[j, C_FORCE2 + 1] += f * n1
            contact[j, C_FORCE2 + 2] += f * n2
            contact[j, C_ID2] = k


@kernel()
def _all_onto_obstacles(x, v, dt, inv, mass, ob, meta, data, th, contact):
    """:func:`_onto_obstacles` for every free vertex."""
    for j in range(x.shape[0]):
        if inv[j] > 0.0:
            _onto_obstacles(j, x, v, dt, mass, ob, meta, data, th, contact)


@kernel(refcount=False)
def _project(p, x, x0, v, inv, mass, gi, gw, gn, gd, go, g0, th, sep, slack, mu, dt, ob,
             meta, data, contact):
    """The impulse of pair p (module docstring) if it is short of its target; returns 1
    if it acted, else 0 (also for a pair without weight: degenerate, or all pinned)."""
    short = _deficit(p, x, x0, gi, gw, gn, gd, go, g0, th, sep)
    if short <= slack:
        return 0
    W = 0.0
    for k in range(4):
        W += gw[p, k] * gw[p, k] * inv[gi[p, k]]
    if W <= 0.0:
        return 0
    lam = short / W
    n0 = gn[p, 0]
    n1 = gn[p, 1]
    n2 = gn[p, 2]
    # relative tangential motion of the step (before this normal correction)
    r0 = -go[p, 0]
    r1 = -go[p, 1]
    r2 = -go[p, 2]
    for k in range(4):
        j = gi[p, k]
        r0 += gw[p, k] * (x[j, 0] - x0[j, 0])
        r1 += gw[p, k] * (x[j, 1] - x0[j, 1])
        r2 += gw[p, k] * (x[j, 2] - x0[j, 2])
    rn = r0 * n0 + r1 * n1 + r2 * n2
    t0 = r0 - rn * n0
    t1 = r1 - rn * n1
    t2 = r2 - rn * n2
    rt = math.sqrt(t0 * t0 + t1 * t1 + t2 * t2)
    # friction: remove up to mu (target - g) of the tangential slip, in the same units
    fl = 0.0
    if rt > 0.0 and mu > 0.0:
        fl = min(rt, mu * short) / (W * rt)
    for k in range(4):
        j = gi[p, k]
        s = gw[p, k] * inv[j]
        if s == 0.0:
            continue
        _kick(j, x, v, dt, s * (lam * n0 - fl * t0), s * (lam * n1 - fl * t1),
              s * (lam * n2 - fl * t2))
        if ob.shape[0] > 0:
            _onto_obstacles(j, x, v, dt, mass, ob, meta, data, th, contact)
    return 1


@kernel()
def _inverse_mass(mass, pinned, inv):
    """inv[i] = 1 / m_i, 0 for a pinned or held vertex."""
    for i in range(mass.shape[0]):
        inv[i] = 0.0 if pinned[i] else 1.0 / mass[i]


@kernel(refcount=False)
def respond(x, x0, v, inv, mass, gi, gw, gn, gd, go, g0, npair, th, mu, dt, sep, slack,
            flag, active, ob, meta, data, contact, stats):
    """The response of the module docstring over the live pairs' constraints (from
    :func:`_pair_geometry`, which also flagged the short ones); x and v in place; inverse
    masses ``inv`` (:func:`_inverse_mass`). ``stats``: (pairs that acted, rounds, sweeps,
    pairs still short at the end, the closest gap at the end [m]); ``sep``: how far a
    pair inside the layer moves back out (:func:`_target`)."""
    acted = 0
    sweeps = 0
    rounds = 0
    na = 0
    for rnd in range(ROUNDS):
        # the first round's flags come with the geometry (:func:`_pair_geometry`)
        if rnd > 0 and _short(x, x0, gi, gw, gn, gd, go, g0, npair, th, sep, slack, flag) == 0:
            break
        na = 0
        for p in range(npair):
            if flag[p]:
                active[na] = p
                na += 1
        if na == 0:
            break
        rounds += 1
        for sw in range(SWEEPS):
            sweeps += 1
            moved = 0
            for q in range(na):
                moved += _project(active[q], x, x0, v, inv, mass, gi, gw, gn, gd, go, g0,
                                  th, sep, slack, mu, dt, ob, meta, data, contact)
            if sw == 0:
                acted += moved
            if moved == 0:
                break
    # the last check found every pair satisfied, or the rounds ran out: count what is
    # short and the closest gap among the pairs of the last round
    left = 0
    closest = np.inf
    if rounds > 0:
        for q in range(na):
            p = active[q]
            closest = min(closest, _gap(p, x, x0, gi, gw, gn, gd, go))
            left += 1 if _deficit(p, x, x0, gi, gw, gn, gd, go, g0, th, sep) > slack else 0
    stats[0] = acted
    stats[1] = rounds
    stats[2] = sweeps
    stats[3] = left
    stats[4] = closest


@kernel()
def _ledger(x, xs, v, vs, v0, mass, dt):
    """The energy the response removed [J]: minus the change of kinetic energy and of
    potential energy, the latter as minus the work of the step's force ``f_i = m_i (vs_i
    - v0_i) / dt`` over the response's displacement ``x_i - xs_i`` by the trapezoid rule
    (the force falls from f to what the contact balances; xs, vs: position and velocity
    before the response, v0: velocity before the step). In a resting contact, where a
    force pushes a vertex into the layer each step and the response takes it back, this
    reads zero; a collision without force reads its lost kinetic energy."""
    out = 0.0
    for i in range(x.shape[0]):
        m = mass[i]
        for k in range(3):
            c = x[i, k] - xs[i, k]
            if c == 0.0 and v[i, k] == vs[i, k]:
                continue
            out -= 0.5 * m * (v[i, k] * v[i, k] - vs[i, k] * vs[i, k])
            out += 0.5 * m * (vs[i, k] - v0[i, k]) / dt * c
    return out


def overrun_speed(speed: float, overran: bool, moved: float, steps: int,
                  dt: float) -> float:
    """The least speed [m/s] the next calls of several steps assume, after a call of
    ``steps`` steps that moved the cloth ``moved`` [m] and ``overran`` (or not) the room
    it was given, where they assumed at least ``speed`` before: a cloth that speeds up
    within calls would overrun each, so an overrun's speed, doubled, becomes the floor,
    halved after each call that did not overrun (here and in :mod:`.features`)."""
    return max(speed, 2.0 * moved / (steps * dt)) if overran else 0.5 * speed


def drifts(step: float, th: float, d: float) -> bool:
    """Whether a step whose relative motion is ``step`` [m] (the most any vertex moved
    relative to the others) can make the gap of a pair at distance ``d`` (the least
    among the live pairs where the step began), linearised there, drift by more than the
    slack: two vertices of a pair moving apart tangentially by up to 2 step drift by
    about (2 step)^2 / d (module docstring). A layer resting on another (d about th) or
    sliding slowly over it (on fold.yaml's 2 mm layer at dt = 2e-4 s: below ~0.5 m/s)
    skips the second pass; a pair deep inside the layer makes every moving step take it."""
    return (2.0 * step) ** 2 > SLACK * th * max(d, 0.0)


def in_stages(x, v, x0, xe, xt, stages, answer, inv, mass, control, th, dt):
    """The response to a step from ``x0`` to ``x`` whose relative motion exceeds
    :data:`STAGE` th, in ``stages`` equal parts of the solver's displacement, each
    answered by ``answer(start, j)`` linearised where the last one ended (``start``:
    ``x0`` for the first, then ``xe``; ``xt``: room for where the solver took the
    cloth); x and v in place. Returns the sum of what the answers returned (the pairs
    that acted). A vertex pushed towards an obstacle in an early stage went on along
    the solver's path, which ended on the contact layer: it is put back onto it. Used
    by self-collision and by the obstacles' corners and edges (:mod:`.features`)."""
    xt[:] = x
    x[:] = x0
    acted = 0
    for j in range(stages):
        start = x0 if j == 0 else xe
        xe[:] = x
        x += (xt - x0) / stages
        acted += answer(start, j)
    if control.obstacles.shape[0] > 0:
        _all_onto_obstacles(x, v, dt, inv, mass, control.obstacles, control.sdf_meta,
                            control.sdf_data, th, control.contact)
    return acted


class SelfCollision:
    """The self-collision of one simulator's cloth (module docstring).

    ``begin(x, v)`` before a run of steps (the state the first step starts from),
    ``after_step(state, control, coeff, dt)`` after each step: the response, in place;
    returns the energy it removed [J] (:func:`_ledger`; the balance's dissipation). While
    no pair is near, a call of several steps (:meth:`free_steps`, checked by
    :meth:`overran`) takes no response and ends with ``begin`` instead."""

    def __init__(self, mesh):
        n = mesh.n_vertices
        self.rest = np.ascontiguousarray(mesh.vertices, dtype=np.float64)
        self.faces = np.ascontiguousarray(mesh.faces, dtype=np.int64)
        self.edges = np.ascontiguousarray(mesh.edges, dtype=np.int64)
        # the mean rest edge: the skin grows to it at most, unless one step moves further
        self.edge = float(mesh.mean_edge_length)
        self.friction = DEFAULT_FRICTION
        self.x0 = np.zeros((n, 3))
        self.v0 = np.zeros((n, 3))               # velocities where the step began
        self.xs = np.zeros((n, 3))               # before the response
        self.vs = np.zeros((n, 3))
        self.xe = np.zeros((n, 3))               # after the first response
        self.xt = np.zeros((n, 3))               # where a staged step's solver ended
        self.xb = np.zeros((n, 3))              # the list's references (module docstring)
        self.skin = 0.0
        self.vt = np.zeros((max(64, n), 2), np.int64)
        self.ee = np.zeros((max(64, 2 * n), 2), np.int64)
        self.vtd = np.zeros(len(self.vt))
        self.eed = np.zeros(len(self.ee))
        self.nvt = 0
        self.nee = 0
        self.nlive = 0
        self._alloc(len(self.vt) + len(self.ee))
        self.moved = np.zeros(n)                # relative displacement since xb
        self.step_moved = np.zeros(n)           # ... and in this step
        self.xd = np.zeros((n, 3))              # where the candidates' distances were taken
        self.dmoved = np.zeros(n)               # relative displacement since then
        self.rebases = 0                        # their distances taken again (_rebase)
        self.live_based = -1                    # live pairs on the first step after that
        self.since_based = 0                    # steps since
        self.reach = np.zeros(n)
        self.inv = np.zeros(n)
        self.stats = np.zeros(5)
        self.stats[4] = np.inf
        self.builds = 0
        self.room = 0.0                          # what free_steps allowed the last call
        self.still = np.zeros((n, 3))            # zero velocities (free_steps)
        self.speeds = np.zeros(n)
        self.overrun_speed = 0.0                 # [m/s] (overran)
        self.built_th = 0.0                      # the thickness of the last build
        self.refreshes = 0                       # partial refreshes (_refresh)
        self.fresh = np.zeros(n, np.bool_)
        self.tfresh = np.zeros(len(self.faces), np.bool_)
        self.efresh = np.zeros(len(self.edges), np.bool_)
        self.first, self.fstart = first_vertex_lists(self.faces, n)

    def _alloc(self, p):
        self.live = np.zeros(p, np.int64)
        self.gi = np.zeros((p, 4), np.int64)
        self.gw = np.zeros((p, 4))
        self.gn = np.zeros((p, 3))
        self.gd = np.zeros(p)
        self.go = np.zeros((p, 3))            # side B is the cloth: it moves itself
        self.g0 = np.zeros(p)
        self.flag = np.zeros(p, np.int64)
        self.active = np.zeros(p, np.int64)

    def begin(self, x: np.ndarray, v: np.ndarray) -> None:
        self.x0[:] = x
        self.v0[:] = v

    def free_steps(self, x: np.ndarray, v: np.ndarray, th: float, dt: float) -> int:
        """How many steps the cloth can probably take from (x, v) with no pair coming
        within ``th`` (so without a response after each; fewer than 2: answer each
        step): none while the last step had live pairs or before the first list; else
        the steps in which the fastest vertex relative to the others, at its present
        speed but at least :data:`FREE_SPEED`, covers half the room the list leaves
        (:func:`_room`). :meth:`overran` then checks the call (a cloth can speed up)."""
        self.room = 0.0
        if self.builds == 0 or self.nlive or th != self.built_th:
            return 0
        _displacement(x, self.xb, self.moved)
        _displacement(x, self.xd, self.dmoved)
        room = _room(self.vt, self.vtd, self.nvt, self.edges, self.ee, self.eed, self.nee,
                     self.faces, th, self.moved, self.dmoved, 0.5 * self.skin)
        if room <= 0.0:
            return 0
        self.room = room
        # the fastest vertex relative to the cloth's mean motion (a rigid translation
        # brings no pair closer): v's displacement from rest, the mean taken out
        speed = max(_displacement(v, self.still, self.speeds), FREE_SPEED,
                    self.overrun_speed)
        return int(min(0.5 * room / (speed * dt), 2.0 ** 62))

    def overran(self, x_start: np.ndarray, x: np.ndarray, steps: int, dt: float) -> bool:
        """Whether a call of ``steps`` steps allowed by :meth:`free_steps` moved some
        vertex, relative to the others, as far as the room it was given (then it is
        stepped again, one step per call with the response), and the speed the next
        calls assume (:func:`overrun_speed`)."""
        moved = _displacement(x, x_start, self.step_moved)
        over = moved >= self.room
        self.overrun_speed = overrun_speed(self.overrun_speed, over, moved, steps, dt)
        return over

    def _build(self, x: np.ndarray, th: float, skin: float) -> None:
        while True:
            nvt, nee = build_candidates(x, self.rest, self.faces, self.edges, th + skin, th,
                                        self.vt, self.ee, self.vtd, self.eed)
            if nvt <= len(self.vt) and nee <= len(self.ee):
                break
            if nvt > len(self.vt):
                self.vt = np.zeros((2 * nvt, 2), np.int64)
                self.vtd = np.zeros(2 * nvt)
            if nee > len(self.ee):
                self.ee = np.zeros((2 * nee, 2), np.int64)
                self.eed = np.zeros(2 * nee)
        self.nvt, self.nee = nvt, nee
        if len(self.gd) < nvt + nee:
            self._alloc(2 * (nvt + nee))
        self.xb[:] = x
        self.xd[:] = x
        self.skin = skin
        self.built_th = th
        self.builds += 1
        self.live_based = -1
        self.since_based = 0

    def _swollen(self) -> bool:
        """Whether taking every candidate's distance again now costs less than what the
        live pairs added since the distances were last taken cost over those steps
        (:data:`REBASE_LIVE`): each step checks every pair whose vertices' displacement
        since then may have brought it within th, and a cloth in motion moves every
        vertex, so the live pairs grow though few pairs come closer."""
        extra = (self.nlive - self.live_based) * self.since_based
        return extra > REBASE_LIVE * (self.nvt + self.nee)

    def _rebase(self, x0: np.ndarray) -> None:
        """Every candidate's distance taken again at ``x0`` (where the step began): the
        live pairs are then those that can come within th from there."""
        self.xd[:] = x0
        _distances(x0, self.faces, self.edges, self.vt, self.nvt, self.ee, self.nee,
                   self.vtd, self.eed)
        self.rebases += 1
        self.live_based = -1
        self.since_based = 0

    def _refresh(self, x0: np.ndarray, x: np.ndarray, th: float) -> bool:
        """A partial refresh of the list (module docstring), where the step began (``x0``;
        ``x``: where it ended): the vertices that moved more than :data:`REFRESH` of the
        skin since their references or would soon run out of room (:func:`_renew`) take
        ``x0`` as their reference, and every candidate that holds one of them is found
        again there.
        Returns False, and the list must be built anew, when they are more than
        :data:`REFRESH_MOST` of the vertices or some vertex is still more than half the
        skin from its reference."""
        _displacement(x, self.xb, self.moved)
        if _renew(x0, self.xb, self.moved, self.step_moved, self.skin,
                  REFRESH_MOST * len(x0), self.fresh) > REFRESH_MOST * len(x0):
            return False
        kv, ke, tris, verts, eds = _keep_untouched(
            self.fresh, self.faces, self.edges, self.vt, self.vtd, self.nvt, self.ee,
            self.eed, self.nee, self.tfresh, self.efresh)
        while True:
            nv, ne = scan_candidates(self.xb, self.rest, self.faces, self.edges,
                                     th + self.skin, th, tris, verts, self.tfresh,
                                     self.first, self.fstart, eds, self.efresh, self.vt[kv:],
                                     self.ee[ke:], self.vtd[kv:], self.eed[ke:])
            if kv + nv <= len(self.vt) and ke + ne <= len(self.ee):
                break
            if kv + nv > len(self.vt):
                self.vt = np.concatenate([self.vt[:kv], np.zeros((2 * (kv + nv), 2), np.int64)])
                self.vtd = np.concatenate([self.vtd[:kv], np.zeros(2 * (kv + nv))])
            if ke + ne > len(self.ee):
                self.ee = np.concatenate([self.ee[:ke], np.zeros((2 * (ke + ne), 2), np.int64)])
                self.eed = np.concatenate([self.eed[:ke], np.zeros(2 * (ke + ne))])
        self.nvt, self.nee = kv + nv, ke + ne
        if len(self.gd) < self.nvt + self.nee:
            self._alloc(2 * (self.nvt + self.nee))
        self.refreshes += 1
        return _displacement(x, self.xb, self.moved) <= 0.5 * self.skin

    def _respond(self, start, x, v, control, mass, th, mu, dt) -> None:
        """The live pairs' constraints linearised at ``start`` (the step's start x0 the
        first time, which sets each pair's target), and the response to them."""
        sep = SEP_SPEED * dt
        _pair_geometry(start, x, self.faces, self.edges, self.vt, self.nvt, self.ee,
                       self.live, self.nlive, self.gi, self.gw, self.gn, self.gd, self.go,
                       self.g0, start is self.x0, th, sep, self.flag)
        respond(x, start, v, self.inv, mass, self.gi, self.gw, self.gn, self.gd, self.go,
                self.g0, self.nlive, th, mu, dt, sep, SLACK * th, self.flag, self.active,
                control.obstacles, control.sdf_meta, control.sdf_data, control.contact,
                self.stats)

    def _staged(self, x, v, control, mass, th, dt, stages) -> None:
        """The response to a step whose relative motion exceeds :data:`STAGE` th
        (:func:`in_stages`)."""
        def answer(start, j):
            self._respond(start, x, v, control, mass, th, self.friction, dt)
            return self.stats[0]
        self.stats[0] = in_stages(x, v, self.x0, self.xe, self.xt, stages, answer,
                                  self.inv, mass, control, th, dt)

    def after_step(self, state, control, coeff, dt: float) -> float:
        th = float(control.contact_params[0])
        x = state.x
        step, far = _displacements(x, self.x0, self.xb, self.xd, self.step_moved,
                                   self.dmoved)
        skin = max(SKIN * th, SKIN_EDGE * self.edge, 2.5 * step,
                   min(STEPS_PER_BUILD * step, self.edge))
        out = self.builds == 0 or th != self.built_th or far > 0.5 * self.skin
        if out and not (self.builds and th == self.built_th
                        and REFRESH_SKIN * self.skin <= skin <= self.skin
                        and self._refresh(self.x0, x, th)):
            self._build(self.x0, th, skin)
            self.dmoved[:] = self.step_moved        # built where this step began
        elif out or self._swollen():
            # refreshed (the new candidates' distances are at their references) or
            # swollen: every distance taken again where this step began
            self._rebase(self.x0)
            self.dmoved[:] = self.step_moved
        self.nlive = _select(self.vt, self.vtd, self.nvt, self.edges, self.ee, self.eed,
                             self.nee, self.faces, th, self.dmoved, self.step_moved,
                             self.reach, self.live)
        self.since_based += 1
        if self.live_based < 0:
            self.live_based = self.nlive          # the first step after a rebase
        diss = 0.0
        if self.nlive:
            _inverse_mass(coeff.mass, control.pinned, self.inv)
            self.xs[:] = x
            self.vs[:] = state.v
            stages = int(math.ceil(step / (STAGE * th)))
            if stages > 1:
                self._staged(x, state.v, control, coeff.mass, th, dt, stages)
            else:
                self._respond(self.x0, x, state.v, control, coeff.mass, th, self.friction,
                              dt)
            closest = self.g0[:self.nlive].min()
            if (self.stats[0] > 0 or closest < th) and drifts(step, th, closest):
                # pairs in contact: once more from the exact geometry at the step's end
                # (the linearised gap drifts by |slip|^2 / d under a sliding contact;
                # module docstring), friction already applied
                acted = self.stats[0]
                self.xe[:] = x
                self._respond(self.xe, x, state.v, control, coeff.mass, th, 0.0, dt)
                self.stats[0] += acted
            if self.stats[0] > 0:
                diss = _ledger(x, self.xs, state.v, self.vs, self.v0, coeff.mass, dt)
        else:
            self.stats[:4] = 0.0
            self.stats[4] = np.inf
        self.x0[:] = x
        self.v0[:] = state.v
        return diss

    def report(self) -> Dict[str, float]:
        """The last step's self-contact: candidates (vertex-triangle, edge-edge), the
        live ones (that could touch this step), pairs that acted, rounds and sweeps of
        the projection, pairs left short, the closest gap [m] along the live pairs'
        normals, and the candidate builds and partial refreshes so far."""
        s = self.stats
        return {'candidates': int(self.nvt + self.nee), 'live': int(self.nlive),
                'active': int(s[0]), 'rounds': int(s[1]), 'sweeps': int(s[2]),
                'left_short': int(s[3]), 'closest_gap': float(s[4]),
                'builds': int(self.builds), 'refreshes': int(self.refreshes),
                'rebases': int(self.rebases)}


def warm() -> None:
    """Compile every kernel of this module (into numba's cache) on two triangles, one
    falling onto the other just above a plane: the candidates, the live pairs, the staged
    response with an obstacle, the ledger and a partial refresh."""
    from types import SimpleNamespace
    from .contact import WIDTH
    from .mesh import ClothMesh
    from .state import Control, State
    rest = np.array([[0.0, 0.0, 0.0], [1.0, 0.0, 0.0], [0.0, 1.0, 0.0],
                     [0.2, 0.2, 5.0], [0.6, 0.2, 5.0], [0.2, 0.6, 5.0]])
    sc = SelfCollision(ClothMesh(rest, np.array([[0, 1, 2], [3, 4, 5]])))
    x = rest.copy()
    x[3:, 2] = 0.003
    v = np.zeros((6, 3))
    v[3:, 2] = -1.0
    plane = np.zeros((1, WIDTH))
    plane[0, 4:13] = np.eye(3).reshape(-1)
    plane[0, 2] = -1.0
    control = Control.empty(6).with_obstacles(plane, np.zeros((0, 8)), np.zeros(0))
    sc.begin(x, v)
    x += 0.004 * v                      # 2 mm relative: a staged response (STAGE)
    sc.after_step(State(x, v, np.zeros(2)), control, SimpleNamespace(mass=np.full(6, 0.01)),
                  0.002)
    sc.moved[:] = 0.0
    sc.moved[3] = sc.skin                 # one vertex ran out of room: a partial refresh
    sc._refresh(x, x, sc.built_th)
