"""Sharp obstacle features: the corners and edges of boxes, cylinders and meshes
against the cloth's triangles and edges.

Why
---
Vertex contact (:mod:`.contact`) keeps every *vertex* of the cloth off every obstacle.
On a smooth obstacle whose radius of curvature is well above the cloth's edge length,
that keeps the triangles off it too. A box is not smooth: with cloth edges longer than
the box the box passes through a triangle between its vertices, a table edge cuts into
every triangle that crosses it, and so do a cylinder's rims and a side bent tighter
than the triangles (doc/contact.md has the depths measured without this module). What
is missing are the pairs of a mesh against a mesh, those of self-collision
(:mod:`.self_contact`), with one side rigid and moved by the user:

* corner-triangle: obstacle corner ``p`` and cloth triangle (a, b, c), closest point
  ``q = u x_a + v x_b + w x_c`` (Ericson 5.1.5);
* edge-edge: obstacle edge (p0, p1) and cloth edge (a0, a1), closest points
  ``p = (1 - t) p0 + t p1`` and ``q = (1 - s) x_a0 + s x_a1`` (Ericson 5.1.9).

A box's faces against the cloth's vertices are vertex contact; the three kinds together
are every closest-feature pair of two triangle meshes. The corners and edges of each
shape (a box's, a cylinder's prism, a mesh's sharp edges) are :mod:`.feature_shapes`'.

Constraint and response
-----------------------
Each pair is one constraint on the cloth's vertices k with weights ``w_k`` (u, v, w or
1 - s, s), unit normal ``n = (q - p) / |q - p|`` from the obstacle to the cloth and
distance ``d = |q - p|``, both where the step began, and the obstacle point's
displacement over the step ``o = dt (v_lin + omega x (p - c))`` (the pose of its row is
the pose at the step's start, as for vertex contact)::

    g = d + n . (sum_k w_k (x_k - x0_k) - o)

This is self-collision's gap with side B rigid, so the response is self-collision's
(:func:`.self_contact.respond`). Every pair must end the step at ``g >= th``; a pair that
began inside the layer moves back out at most at :data:`.self_contact.SEP_SPEED`. The
correction is inelastic, a Gauss-Seidel projection; the obstacle has zero inverse mass,
so the cloth takes all of it. Coulomb friction acts on the slip relative to the obstacle,
with mu the obstacle's kinetic coefficient. A pair that acted is projected once more from the
exact geometry at the step's end. A step whose motion exceeds ``STAGE th`` (the implicit
solver's) is answered in stages, as in self-collision. A pair that ends every step at
``g >= th`` along its own normal cannot cross within a step whose relative motion is
below th. A box placed through the cloth is not pulled back out: that pair's normal
already points the wrong way.

The cloth's momentum change over the response is the force on the obstacle. It is reported
with vertex contact's, in :meth:`.simulator.ClothSimulator.contact_forces`. The energy
the response removes (:func:`.self_contact._ledger`) counts as dissipation.

Candidates: the pairs that can come within ``th + m`` in a step (m the step's largest
motion) are found and kept over steps as :mod:`.feature_candidates` describes.

This module imports no ROS package.
"""
from __future__ import annotations

import math
from typing import NamedTuple

import numpy as np

from .compiled import kernel
from .contact import MU_K, PARAM, POS, ROT, SHAPE, SPEED, _point_velocity, distance
from .feature_candidates import SKIN, candidates, fresh, largest_motion
from .feature_shapes import (BOX, BOX_EDGES, FEATURED, FM_NCORNER,
                             MESH, RIM_SIDES_MAX, Shapes, box_corners, edge_ends,
                             feature_corners, n_features, no_shapes, rim_sides)
from .self_contact import (SEP_SPEED, STAGE, _deficit, _inverse_mass, _ledger, in_stages,
                           overrun_speed, respond, set_normal)
from .surface_query import point_triangle_sq, segment_segment
from .terms.jet import cross

__all__ = ['FeatureContact', 'box_corners', 'feature_corners', 'BOX_EDGES', 'FEATURED',
           'rim_sides', 'warm']


#: a pair short of its target by less than this fraction of th counts as satisfied. Ten
#: times below self-collision's: a cloth resting on an edge sinks by g dt^2 per step
#: (5e-4 th at the explicit step of config/table.yaml) and the edge takes its share of
#: the weight in the steps where that adds up to the slack, so the force over one step
#: flickers; :attr:`FeatureContact.forces` is therefore the mean over a call's steps
SLACK = 1e-3
#: [m/s] the least speed a cloth is assumed to reach when the steps it may take without
#: the response are counted (:meth:`FeatureContact.free_steps`)
FREE_SPEED = 1.0


@kernel()
def geometry(cand, nc, xs, x, ob, faces, edges, sh, dt, shift, part, corners, gi,
             gw, gn, gd, go, g0, first, th, sep, slack, flag):
    """The constraint of each pair ``cand[:nc]`` (module docstring) linearised at the
    cloth's positions ``xs``, with the box moved on by ``shift`` of its step's
    displacement and moving ``part`` of it in what is left to answer (the whole step: 0
    and 1; its end: 1 and 0; a stage j of m: j / m and 1 / m): vertices gi (P,4), weights
    gw (P,4), normal gn (P,3) from the box to the cloth, distance gd (P,), the box's
    displacement go (P,3). A pair at zero distance takes the triangle's normal (or the
    edges' cross product) turned away from the obstacle's centre. ``first``: g0 takes gd
    (the distance that sets each pair's target). flag[p]: 1 if short at x by more
    than ``slack`` [m]."""
    last = -1
    ncorner = 0
    for p in range(nc):
        k = cand[p, 0]
        f = cand[p, 1]
        e = cand[p, 2]
        if k != last:
            feature_corners(ob, k, th, sh, corners)
            ncorner = n_features(ob, k, th, sh)[0]
            last = k
        if f < ncorner:
            a = faces[e, 0]
            b = faces[e, 1]
            c = faces[e, 2]
            dd, u, v, w = point_triangle_sq(corners[f, 0], corners[f, 1], corners[f, 2],
                                            xs[a], xs[b], xs[c])
            p0 = corners[f, 0]
            p1 = corners[f, 1]
            p2 = corners[f, 2]
            gi[p, 0] = a
            gi[p, 1] = b
            gi[p, 2] = c
            gi[p, 3] = a
            gw[p, 0] = u
            gw[p, 1] = v
            gw[p, 2] = w
            gw[p, 3] = 0.0
            f0, f1, f2 = cross(xs[b, 0] - xs[a, 0], xs[b, 1] - xs[a, 1], xs[b, 2] - xs[a, 2],
                               xs[c, 0] - xs[a, 0], xs[c, 1] - xs[a, 1], xs[c, 2] - xs[a, 2])
        else:
            a = edges[e, 0]
            b = edges[e, 1]
            c0, c1 = edge_ends(ob, k, f - ncorner, ncorner, sh)
            dd, s, t = segment_segment(xs[a], xs[b], corners[c0], corners[c1])
            p0 = corners[c0, 0] + t * (corners[c1, 0] - corners[c0, 0])
            p1 = corners[c0, 1] + t * (corners[c1, 1] - corners[c0, 1])
            p2 = corners[c0, 2] + t * (corners[c1, 2] - corners[c0, 2])
            gi[p, 0] = a
            gi[p, 1] = b
            gi[p, 2] = a
            gi[p, 3] = b
            gw[p, 0] = 1.0 - s
            gw[p, 1] = s
            gw[p, 2] = 0.0
            gw[p, 3] = 0.0
            f0, f1, f2 = cross(xs[b, 0] - xs[a, 0], xs[b, 1] - xs[a, 1], xs[b, 2] - xs[a, 2],
                               corners[c1, 0] - corners[c0, 0], corners[c1, 1] - corners[c0, 1],
                               corners[c1, 2] - corners[c0, 2])
        o0, o1, o2 = _point_velocity(ob, k, p0, p1, p2)
        p0 += shift * dt * o0
        p1 += shift * dt * o1
        p2 += shift * dt * o2
        go[p, 0] = part * dt * o0
        go[p, 1] = part * dt * o1
        go[p, 2] = part * dt * o2
        # the cloth's point q less the box's point (moved on by shift, with dd at the
        # unmoved box: recomputed here)
        r0 = -p0
        r1 = -p1
        r2 = -p2
        for j in range(4):
            r0 += gw[p, j] * xs[gi[p, j], 0]
            r1 += gw[p, j] * xs[gi[p, j], 1]
            r2 += gw[p, j] * xs[gi[p, j], 2]
        # the fallback direction turned away from the box's centre
        sg = 1.0 if ((p0 - ob[k, POS]) * f0 + (p1 - ob[k, POS + 1]) * f1
                     + (p2 - ob[k, POS + 2]) * f2) >= 0.0 else -1.0
        set_normal(p, r0, r1, r2, sg * f0, sg * f1, sg * f2, gw, gn, gd, g0, first)
        flag[p] = 1 if _deficit(p, x, xs, gi, gw, gn, gd, go, g0, th, sep) > slack else 0


@kernel()
def _impulse(x, v, v_before, c_before, contact, mass, dt, ob, k, out):
    """The force and torque (about its position) that the cloth exerted on box row k
    through the response that took the velocities from ``v_before`` to ``v``: minus the
    cloth's momentum change over dt, less what vertex contact recorded meanwhile in
    ``contact`` (the response's pushes back onto obstacle layers; ``c_before`` before
    it); added to ``out`` (6,)."""
    for i in range(x.shape[0]):
        if v[i, 0] == v_before[i, 0] and v[i, 1] == v_before[i, 1] and v[i, 2] == v_before[i, 2]:
            continue
        f0 = (contact[i, 0] - c_before[i, 0]) - mass[i] * (v[i, 0] - v_before[i, 0]) / dt
        f1 = (contact[i, 1] - c_before[i, 1]) - mass[i] * (v[i, 1] - v_before[i, 1]) / dt
        f2 = (contact[i, 2] - c_before[i, 2]) - mass[i] * (v[i, 2] - v_before[i, 2]) / dt
        out[0] += f0
        out[1] += f1
        out[2] += f2
        t0, t1, t2 = cross(x[i, 0] - ob[k, POS], x[i, 1] - ob[k, POS + 1],
                           x[i, 2] - ob[k, POS + 2], f0, f1, f2)
        out[3] += t0
        out[4] += t1
        out[5] += t2


@kernel()
def clearance(x, v, edges, ob, meta, data, th, sh):
    """(how far every obstacle with corners and edges is from the cloth beyond its
    longest edge plus ``th`` [m], the fastest any such obstacle's surface moves [m/s],
    the fastest vertex [m/s]):
    :meth:`FeatureContact.free_steps`."""
    fastest = 0.0
    for i in range(x.shape[0]):
        fastest = max(fastest, v[i, 0] * v[i, 0] + v[i, 1] * v[i, 1] + v[i, 2] * v[i, 2])
    longest = 0.0
    for e in range(edges.shape[0]):
        a = edges[e, 0]
        b = edges[e, 1]
        d0 = x[a, 0] - x[b, 0]
        d1 = x[a, 1] - x[b, 1]
        d2 = x[a, 2] - x[b, 2]
        longest = max(longest, d0 * d0 + d1 * d1 + d2 * d2)
    near = np.inf
    speed = 0.0
    for k in range(ob.shape[0]):
        if n_features(ob, k, th, sh)[0] == 0:
            continue
        speed = max(speed, ob[k, SPEED])
        for i in range(x.shape[0]):
            d, n0, n1, n2 = distance(ob, meta, data, k, x[i, 0], x[i, 1], x[i, 2])
            near = min(near, d)
    return near - math.sqrt(longest) - th, speed, math.sqrt(fastest)


class Pairs(NamedTuple):
    """Candidate pairs (rows p) and each one's constraint (module docstring): ``cand``
    (box row, feature, cloth element), then what :func:`geometry` writes: vertices
    ``gi``, weights ``gw``, normal ``gn``, distance ``gd``, the box's displacement
    ``go``, the distance that sets the target ``g0``, short ``flag``; ``active``: the
    projection's list of short pairs."""
    cand: np.ndarray
    gi: np.ndarray
    gw: np.ndarray
    gn: np.ndarray
    gd: np.ndarray
    go: np.ndarray
    g0: np.ndarray
    flag: np.ndarray
    active: np.ndarray

    @staticmethod
    def zeros(p: int) -> 'Pairs':
        return Pairs(np.zeros((p, 3), np.int64), np.zeros((p, 4), np.int64),
                     np.zeros((p, 4)), np.zeros((p, 3)), np.zeros(p), np.zeros((p, 3)),
                     np.zeros(p), np.zeros(p, np.int64), np.zeros(p, np.int64))


class Scratch(NamedTuple):
    """Per-vertex (n, 3) arrays of a step's response: where the step began ``x0``, ``v0``;
    where the response began ``xs``, ``vs``; the base of its last pass ``xe``; the
    velocities and contact forces before a box's projection ``vb``, ``cb``; inverse masses
    ``inv`` (n,); an obstacle's ``corners`` (at most 2 :data:`RIM_SIDES_MAX`, 3); the
    projection's ``stats`` (5,)."""
    x0: np.ndarray
    v0: np.ndarray
    xs: np.ndarray
    vs: np.ndarray
    xe: np.ndarray
    vb: np.ndarray
    cb: np.ndarray
    inv: np.ndarray
    corners: np.ndarray
    stats: np.ndarray

    @staticmethod
    def zeros(n: int) -> 'Scratch':
        z = [np.zeros((n, 3)) for _ in range(7)]
        return Scratch(*z, np.zeros(n), np.zeros((2 * RIM_SIDES_MAX, 3)),
                       np.zeros(5))


@kernel()
def respond_boxes(pairs, nc, base, x, v, ob, meta, data, contact, faces, edges, sh,
                  dt, shift, part, first, friction, s, mass, th, sep, slack, forces):
    """One pass of the response (module docstring): the constraints of ``pairs[:nc]``
    linearised at ``base`` (:func:`geometry`), then self-collision's projection box by
    box, each with its own kinetic mu (none if not ``friction``), and each box's force
    and torque added to ``forces[k]`` (:func:`_impulse`). Returns how many pairs
    acted."""
    P = pairs
    geometry(P.cand, nc, base, x, ob, faces, edges, sh, dt, shift, part, s.corners,
             P.gi, P.gw, P.gn, P.gd, P.go, P.g0, first, th, sep, slack, P.flag)
    acted = 0
    a = 0
    while a < nc:
        k = P.cand[a, 0]
        b = a
        while b < nc and P.cand[b, 0] == k:
            b += 1
        mu = ob[k, MU_K] if friction else 0.0
        s.vb[:] = v
        s.cb[:] = contact[:, :3]
        respond(x, base, v, s.inv, mass, P.gi[a:b], P.gw[a:b], P.gn[a:b], P.gd[a:b],
                P.go[a:b], P.g0[a:b], b - a, th, mu, dt, sep, slack, P.flag[a:b],
                P.active[a:b], ob, meta, data, contact, s.stats)
        if s.stats[0] > 0:
            acted += int(s.stats[0])
            _impulse(x, v, s.vb, s.cb, contact, mass, dt, ob, k, forces[k])
        a = b
    return acted


@kernel()
def _within(pairs, nc, ob, dt, reach, late):
    """The pairs of ``pairs[:nc]`` (their distance ``gd`` where the first pass
    linearised them, at the step's start with the box unmoved) that may still be short
    of their target once the cloth has moved up to ``reach`` [m] and each box its
    step's travel ``dt SPEED``: into ``late`` (cand and g0), in order; returns how many.
    A point's distance to a triangle or a segment changes by no more than its vertices
    move, and no target exceeds th, so a pair left out is not short."""
    m = 0
    for p in range(nc):
        k = pairs.cand[p, 0]
        if pairs.gd[p] < reach + dt * ob[k, SPEED]:
            for j in range(3):
                late.cand[m, j] = pairs.cand[p, j]
            late.g0[m] = pairs.g0[p]
            m += 1
    return m


@kernel()
def respond_step(pairs, late, nc, s, x, v, ob, meta, data, contact, faces, edges,
                 sh, mass, pinned, dt, th, sep, slack, forces, out):
    """The response to one step from ``s.x0, s.v0`` to (x, v), in place and in one
    stage: a pass from the step's start with friction, and if a pair acted or began
    inside the layer, a pass from the geometry at its end over the pairs that can still
    be short (:func:`_within`). Returns how many pairs acted; ``out[0]``: the energy the
    response removed [J] (:func:`_ledger`)."""
    _inverse_mass(mass, pinned, s.inv)
    s.xs[:] = x
    s.vs[:] = v
    # the passes' shift, part and flags as values, not literals: numba compiles a callee
    # once per distinct literal argument (respond_boxes three times: docs/performance.md),
    # and once for all values of the same type
    zero = 0.0 * dt
    one = zero + 1.0
    yes = nc >= 0
    acted = respond_boxes(pairs, nc, s.x0, x, v, ob, meta, data, contact, faces, edges,
                          sh, dt, zero, one, yes, yes, s, mass, th, sep, slack,
                          forces)
    inside = False
    for p in range(nc):
        if pairs.g0[p] < th:
            inside = True
            break
    if acted > 0 or inside:
        s.xe[:] = x
        m = _within(pairs, nc, ob, dt, th + slack + largest_motion(x, s.x0), late)
        acted += respond_boxes(late, m, s.xe, x, v, ob, meta, data, contact, faces, edges,
                               sh, dt, one, zero, not yes, not yes, s, mass, th, sep,
                               slack, forces)
    out[0] = _ledger(x, s.xs, v, s.vs, s.v0, mass, dt) if acted > 0 else 0.0
    return acted


class FeatureContact:
    """The corners and edges of the boxes, cylinders and meshes with sharp edges among
    a simulator's obstacles against its cloth (module docstring); the meshes' features
    come through :meth:`set_shapes`.

    ``start()`` before a call's steps, ``begin(x, v)`` before each step,
    ``after_step(state, control, coeff, dt)`` after it, while one is present
    (:meth:`present`): the response, in place; returns the energy it removed [J].
    :attr:`forces` (obstacle rows, 6): the force and torque each obstacle took through its
    features, the mean over the steps since ``start()``.

    The candidate pairs are a Verlet list: found within ``th + skin`` where a step
    began, kept while no vertex has moved more than half the skin since and no box has
    moved or changed (module docstring)."""

    def __init__(self, mesh):
        n = mesh.n_vertices
        self.faces = np.ascontiguousarray(mesh.faces, dtype=np.int64)
        self.edges = np.ascontiguousarray(mesh.edges, dtype=np.int64)
        self.s = Scratch.zeros(n)
        self.sh = no_shapes()
        self.xt = np.zeros((n, 3))
        self.xb = np.zeros((n, 3))
        self.loc = np.zeros((n, 3))
        self.move = np.zeros(1)
        self.scratch = np.zeros(2)
        self.out = np.zeros(1)
        self.sums = np.zeros((0, 6))
        self.steps = 0
        self.built = None                  # the obstacle rows of the last build
        self.built_th = 0.0                # and its contact thickness
        self.skin = 0.0
        self.builds = 0
        self.pairs = 0
        self.acted = 0
        self.gap = 0.0
        self.overrun_speed = 0.0           # [m/s] (overran)
        self._alloc(64)

    def _alloc(self, p):
        self.p = Pairs.zeros(p)
        self.late = Pairs.zeros(p)         # the second pass's (:func:`_within`)

    def present(self, control) -> bool:
        """Whether any obstacle is a box, a cylinder or a mesh with sharp edges (else
        nothing to do)."""
        return bool(self._featured(control.obstacles).any())

    def _featured(self, ob: np.ndarray) -> np.ndarray:
        """Which obstacle rows have corners and edges (:func:`n_features` > 0): boxes,
        cylinders, meshes with sharp edges."""
        shape = ob[:, SHAPE]
        rows = shape == FEATURED[0]
        for k in FEATURED[1:]:                 # (np.isin sorts: 40 us on every step call)
            rows |= shape == k
        fm = self.sh.fmeta
        if fm.shape[0] == ob.shape[0]:
            rows |= (ob[:, SHAPE] == MESH) & (fm[:, FM_NCORNER] > 0)
        return rows

    def set_shapes(self, fmeta: np.ndarray, fcorner: np.ndarray, fedge: np.ndarray) -> None:
        """The mesh obstacles' sharp features, per obstacle row (:class:`Shapes`): after
        any change of the obstacles (the candidate list is built again)."""
        self.sh = Shapes(BOX_EDGES, np.ascontiguousarray(fmeta, dtype=np.float64),
                         np.ascontiguousarray(fcorner, dtype=np.float64).reshape(-1, 3),
                         np.ascontiguousarray(fedge, dtype=np.int64).reshape(-1, 2))
        most = int(fmeta[:, FM_NCORNER].max()) if len(fmeta) else 0
        if most > self.s.corners.shape[0]:
            self.s = self.s._replace(corners=np.zeros((most, 3)))
        self.built = None

    def start(self) -> None:
        self.sums[:] = 0.0
        self.steps = 0

    @property
    def forces(self) -> np.ndarray:
        """(obstacle rows, 6): force and torque on each box, the mean over the steps
        since :meth:`start`."""
        return self.sums / max(1, self.steps)

    def begin(self, x: np.ndarray, v: np.ndarray) -> None:
        self.s.x0[:] = x
        self.s.v0[:] = v

    def free_steps(self, x: np.ndarray, v: np.ndarray, control, dt: float) -> int:
        """How many steps the cloth can probably take from (x, v) before any of its
        triangles could come within the thickness of a box, so that no response is
        needed after them (fewer than 2: answer each step). A triangle that near has a
        vertex within its longest edge plus th of the box; the steps are those in which
        the fastest vertex, at its present speed but at least :data:`FREE_SPEED`, and the
        box's surface together cover half that gap. :meth:`overran` then checks the call
        (a cloth can speed up). While the last step had candidate pairs: 0 without
        looking."""
        if self.pairs:
            return 0
        gap, speed, fastest = clearance(x, v, self.edges, control.obstacles,
                                        control.sdf_meta, control.sdf_data,
                                        float(control.contact_params[0]), self.sh)
        self.gap = gap
        if gap <= 0.0:
            return 0
        return int(min(0.5 * gap / ((max(fastest, FREE_SPEED, self.overrun_speed) + speed)
                                    * dt), 2.0 ** 62))

    def overran(self, x_start: np.ndarray, x: np.ndarray, control, dt: float,
                steps: int) -> bool:
        """Whether a call of ``steps`` steps allowed by :meth:`free_steps` moved some
        vertex, together with the surface of an obstacle with features, further than the
        gap it was given (then it must be stepped again one step per call, with the
        response), and the speed the next calls assume
        (:func:`.self_contact.overrun_speed`)."""
        ob = control.obstacles
        speed = float(ob[self._featured(ob), SPEED].max(initial=0.0))
        moved = largest_motion(x, x_start)
        over = moved + speed * steps * dt >= self.gap
        self.overrun_speed = overrun_speed(self.overrun_speed, over, moved, steps, dt)
        return over

    def _candidates(self, x, ob, th, dt) -> None:
        """The Verlet list (class docstring), built again where this step began if it
        is stale; then ``self.pairs`` = its length and ``self.move[0]`` the step's
        largest motion of a vertex."""
        s = self.s
        if (self.built is not None and self.built.shape == ob.shape and self.built_th == th
                and fresh(x, s.x0, self.xb, self.skin, ob, self.built, self.move)):
            return
        move = largest_motion(x, s.x0)
        self.move[0] = move
        self.skin = max(SKIN * th, 2.5 * move)
        self.scratch[1] = th                 # the features' own thickness (rim polygons)
        while True:
            nc = candidates(s.x0, s.x0, self.faces, self.edges, ob, th + self.skin, dt,
                            self.sh, self.loc, s.corners, self.p.cand, self.scratch)
            if nc <= len(self.p.cand):
                break
            self._alloc(2 * nc)
        self.pairs = nc
        self.xb[:] = s.x0
        self.built = ob.copy()
        self.built_th = th
        self.builds += 1

    def _pass(self, base, x, v, control, mass, th, dt, shift, part, first, friction):
        """:func:`respond_boxes` at ``base`` over every pair (its arguments from this
        object)."""
        return respond_boxes(self.p, self.pairs, base, x, v, control.obstacles,
                             control.sdf_meta, control.sdf_data, control.contact,
                             self.faces, self.edges, self.sh, dt, shift, part, first,
                             friction, self.s, mass, th, SEP_SPEED * dt, SLACK * th,
                             self.sums)

    def after_step(self, state, control, coeff, dt: float) -> float:
        ob = control.obstacles
        if self.sums.shape[0] != ob.shape[0]:
            self.sums = np.zeros((ob.shape[0], 6))
        self.steps += 1
        self.acted = 0
        th = float(control.contact_params[0])
        x, v = state.x, state.v
        s = self.s
        self._candidates(x, ob, th, dt)
        nc = self.pairs
        if nc == 0:
            return 0.0
        stages = max(1, int(math.ceil(float(self.move[0]) / (STAGE * th))))
        if stages == 1:
            self.acted = respond_step(self.p, self.late, nc, s, x, v, ob, control.sdf_meta,
                                      control.sdf_data, control.contact, self.faces,
                                      self.edges, self.sh, coeff.mass, control.pinned,
                                      dt, th, SEP_SPEED * dt, SLACK * th, self.sums,
                                      self.out)
            return float(self.out[0])
        # a step longer than STAGE th (the implicit solver's): the solver's displacement
        # in equal parts, each linearised where the last one ended (self-collision's
        # stages), then once more from the exact geometry at the step's end
        _inverse_mass(coeff.mass, control.pinned, s.inv)
        s.xs[:] = x
        s.vs[:] = v
        acted = in_stages(x, v, s.x0, s.xe, self.xt, stages,
                          lambda start, j: self._pass(start, x, v, control, coeff.mass, th,
                                                      dt, j / stages, 1.0 / stages,
                                                      j == 0, True),
                          s.inv, coeff.mass, control, th, dt)
        if acted > 0 or self.p.g0[:nc].min() < th:
            s.xe[:] = x
            acted += self._pass(s.xe, x, v, control, coeff.mass, th, dt, 1.0, 0.0, False,
                                False)
        self.acted = acted
        if acted == 0:
            return 0.0
        return _ledger(x, s.xs, v, s.vs, s.v0, coeff.mass, dt)


def warm() -> None:
    """Compile this module's kernels (into numba's cache): a triangle falling onto a box
    corner, in one step and in stages."""
    from types import SimpleNamespace
    from .contact import WIDTH
    from .mesh import ClothMesh
    from .state import Control, State
    rest = np.array([[-1.0, -1.0, 0.0], [1.0, -1.0, 0.0], [0.0, 1.0, 0.0]])
    fc = FeatureContact(ClothMesh(rest, np.array([[0, 1, 2]])))
    box = np.zeros((1, WIDTH))
    box[0, SHAPE] = BOX
    box[0, ROT:ROT + 9] = np.eye(3).reshape(-1)
    box[0, POS + 2] = -0.2
    box[0, PARAM:PARAM + 3] = 0.1
    box[0, MU_K] = 0.5
    control = Control.empty(3).with_obstacles(box, np.zeros((0, 8)), np.zeros(0))
    coeff = SimpleNamespace(mass=np.full(3, 0.01))
    for fall in (0.0005, 0.004):                 # one step; a staged one
        x = rest.copy()
        x[:, 2] = -0.097
        v = np.zeros((3, 3))
        v[:, 2] = -1.0
        fc.begin(x, v)
        x += fall * v
        fc.after_step(State(x, v, np.zeros(2)), control, coeff, fall)
