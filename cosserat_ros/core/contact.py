"""Contact and Coulomb friction of the cloth's vertices with rigid obstacles.

Obstacles are kinematic: the user sets their pose and velocity (a table, a robot link);
the cloth pushes back on nothing but reports the force it exerts on each.

Geometry
--------
Every obstacle is a signed distance ``d(x)`` with outward unit normal ``n(x) = grad d``,
evaluated in the obstacle's frame ``p = R^T (x - c)`` (``c`` its position, ``R`` its
orientation): the plane ``d = p_z`` (the half space below local z is solid), the sphere
``|p| - r``, the box (half extents ``h``) ``|max(q, 0)| + min(max_k q_k, 0)`` with
``q = |p| - h``, the capsule (axis local z, half length ``l``) ``|p - clamp(p_z, -l, l)
e_z| - r``, the cylinder ``|max(w, 0)| + min(max(w_1, w_2), 0)`` with ``w = (|p_xy| - r,
|p_z| - l)``, and a triangle mesh as a signed distance field sampled on a grid in its own
frame and interpolated trilinearly (:func:`mesh_distance_field`). The cloth keeps a
contact thickness ``th`` from every surface: a vertex is in contact when it would come
closer than ``th``.

Response: a velocity-level Coulomb law (the update of Bridson, Fedkiw and Anderson 2002,
"Robust treatment of collisions, contact and friction for cloth animation", Sec. 7.2, on
one vertex at a time)
-------------------------------------------------------------------------------------------
After the explicit update has given a vertex its new velocity ``v`` (``core/solvers/
update.py``), for each obstacle, with ``d`` and ``n`` at the vertex's old position ``x``
and the obstacle's velocity at that point ``v_o = v_lin + w x (x - c)``::

    u    = v - v_o                       relative velocity
    u_min = -(d - th) / dt  if d > th    the approach that ends the step on the layer
            0               otherwise    (already in the layer: no approach at all)
    if u . n < u_min:                    contact
        j  = u_min - u . n               normal velocity change (> 0, inelastic)
        u += j n
        u_t = u - (u . n) n
        |u_t| <= mu_s j:  u_t -> 0       stick (static friction)
        else:             u_t -> u_t (1 - mu_k j / |u_t|)     kinetic friction
    v = v_o + u

so a vertex moves at most to the layer in one step whatever its speed (no tunnelling
through a surface it was outside of: ``u_min`` comes from the old position), and the
tangential impulse is bounded by ``mu`` times the normal one. On a plane tilted by theta
under gravity the normal change per step is ``g cos(theta) dt`` and the tangential
velocity gained ``g sin(theta) dt``: the vertex sticks exactly when ``tan(theta) <= mu_s``
and otherwise slides with ``a = g (sin(theta) - mu_k cos(theta))``. After the position
update ``x += dt v``, a vertex still inside the layer (a curved surface under a tangential
motion, an obstacle moved onto it) is put back on it along the normal, a position change
without velocity, so contact creates no kinetic energy.

The change of velocity is the contact impulse: ``f = m (v_after - v_before) / dt`` is the
force on the vertex over the step (the obstacle feels ``-f``). The energy it removes is
counted as dissipation: the kinetic energy it removes in the obstacle's frame, ``m/2
(|u_before|^2 - |u_after|^2) >= 0``, less the potential energy the step's force ``f_s =
m (v_before - v_start) / dt`` gains over the displacement the response takes from it,
``f_s . dt (v_after - v_before) / 2`` (the trapezoid rule: the force falls from f_s to
what the contact balances; in a resting contact the two cancel, in a collision without
force the first is what is lost). The obstacle's work on the cloth, the kinetic energy's
change less the first, is external work (``State.acc``), so the energy balance of the
report still closes, at rest too (with the update's own ledger corrected to the
displacement after contact: :func:`.update.contact_vertex`).

Obstacles placed through the cloth
----------------------------------
The response above keeps out a vertex that comes from outside: the step ends it at
``d >= th`` up to the push out, which moves it by the little a curved surface or the
obstacle's own travel (at most th / 4 a call, :mod:`.obstacles`) left it inside the
layer. A vertex inside the solid itself (``d < 0``: a penetration beyond the contact
thickness) was put there by no step but by the user: an obstacle added, or given a new
pose, through the cloth. Pushing it out would move it by ``th - d`` in one step, a
position change without velocity whose work nobody books, and the step cannot tell to
which side it belongs, as it came from neither. Measured on the README's library
example (the 1 m cloth hanging from two corners to z = -0.47 m) with a ground added at
z = 0: the cloth stood up on the ground in one step, its total energy went from -0.36 J
to +1.81 J (+1.10 J after 1000 steps), 2.2 J that neither the external work nor the
dissipation booked.

Such a vertex is therefore *released* from that obstacle: neither its response, nor its
push out, nor self-collision's pushes onto the obstacles (:mod:`.self_contact`) act on
it, until a step starts with it out of the obstacle's layer (``d >= th``, or beyond its
reach), from which on it is in contact as any vertex that comes from outside (its
obstacle's next approach is cut at the layer). An obstacle placed through the cloth so
stays through it, as its corners and edges do (:mod:`.features`), and the placement adds
no energy beyond what pushes the vertices found in its layer but outside its solid
(``0 <= d_i < th``) onto the layer, by ``delta_i = th - d_i <= th`` along the normal
with no velocity, as a resting contact's push: with ``f_i`` the force on vertex i
(elastic, weight, applied) and ``omega_max^2`` the largest eigenvalue of ``M^-1 K``
(:meth:`.simulator.ClothSimulator.max_eigenvalue`), which bounds the stiffness's
quadratic form by the mass's, the potential energy rises by at most::

    dE <= sum_i |f_i| delta_i + 1/2 omega_max^2 sum_i m_i delta_i^2     [J]

to second order in delta (the kinetic energy does not rise: the response only removes
approach and slip). The cloth hanging through a ground added under it hangs on exactly
as without the ground (no vertex of it is in contact, none in the layer: dE = 0); when a
released vertex comes out of the layer (the ground lowered below it, say), the ground
holds it from then on.

Which vertices: an obstacle added, every vertex inside its solid (``d < 0``). An obstacle
given a new pose (``ClothSimulator.set_obstacle_pose``): the vertices inside it at the
new pose, but those within ``2 th`` of it at the old one, which the pose carries (a
cloth lying on a table moved by a jump: the next step's push out puts them back on its
layer, position without velocity, as before this rule; stream poses with velocities,
or a jump of more than the layer moves them unbooked), and those released before and
still in its layer stay released. A pinned or held vertex is in no contact: it has no
release (a vertex let go inside an obstacle is pushed out, as before); a vertex that a
reset or ``set_positions`` moves has none any more (the cloth placed anew, not the
obstacle: inside one, it is pushed out, as before); nor have the obstacles from the
65th table row on a bit (pushed out).

The release is a mask of obstacle rows per vertex (two columns of ``Control.contact``,
:data:`C_FREE`, bits 0-31 and 32-63 as exact integers) that the simulator sets when it
places an obstacle (:meth:`.obstacles.ObstacleSet.release`) and moves with the rows when
the set changes; :func:`resolve` (and the implicit step's constraints) clear a bit where
they test the obstacle from the vertex's position at the step's start and find it
outside the layer, or where the broad phase leaves it out (:func:`near_mask`: every
vertex of the group starts more than ``2 th`` plus the step's travel away from it).

Layout: the obstacles are rows of :data:`WIDTH` floats in ``Control.obstacles`` (the
fields of :data:`OBSTACLE`, :mod:`.obstacle_table`), mesh fields in ``Control.sdf_meta``
/ ``Control.sdf_data``; per vertex, the last step's contact in ``Control.contact`` (force
on the vertex (3), obstacle row or -1, gap ``d - th`` at its old position, and where a
second obstacle acted in the step, its part of the force (3) and row; then the release
mask; the columns ``C_*`` below). This module imports no ROS package.
"""
from __future__ import annotations

import math

import numba as nb
import numpy as np
from llvmlite import ir
from numba.core import types
from numba.extending import intrinsic

from .compiled import kernel
from .obstacle_table import (FIELD, MU_K, MU_S, OBSTACLE, OMEGA, PARAM, POS, REACH, ROT,
                             SHAPE, SHAPES, SPEED, VEL, WIDTH, records)
from .surface_query import point_triangle_sq

__all__ = ['SHAPES', 'OBSTACLE', 'WIDTH', 'records', 'resolve', 'distance', 'rotation_matrix',
           'mesh_distance_field']

# Control.contact columns: the vertex's whole contact force over the step (3), the row of
# the obstacle it touched (-1: none), its gap at the step's start, and where it touched a
# second obstacle in the step (a corner), the part of the force that one took (3) and its
# row (-1: none); more than two in one step count with the second; then the rows of the
# obstacles it is released from (module docstring, "Obstacles placed through the cloth"):
# bits 0-31 and 32-63 of that mask, each an integer held exactly by a float
C_FORCE = 0
C_ID = 3
C_GAP = 4
C_FORCE2 = 5
C_ID2 = 8
C_FREE = 9
C_WIDTH = 11

#: distance reported where a mesh's field has no sample (outside its grid): no contact
FAR = 1e30

#: a vertex's ``Control.contact`` row without contact: no force, no obstacle (-1), no gap
#: (FAR); where a step starts, a reset and a pinned vertex write it
NO_CONTACT = np.zeros(C_WIDTH)
NO_CONTACT[[C_ID, C_ID2]] = -1.0
NO_CONTACT[C_GAP] = FAR

#: most pushes of one vertex back onto contact layers after its move (:func:`push_out`):
#: in a corner each push off one surface takes the vertex back into the other's layer by
#: a fraction of what it moved (the alternating projections onto two half-spaces: cos^2 of
#: the angle between their normals a round, 1/2 in a 45 degree wedge, where 32 pushes
#: leave 6e-5 of the first depth)
PUSHES = 32

#: obstacles a group of vertices can leave out together (:func:`near_mask`: the bits of a
#: uint64); every further obstacle is tested for each vertex alone
MASK_BITS = 64
#: the mask that keeps every obstacle
ALL = np.uint64(0xFFFFFFFFFFFFFFFF)
#: the low 32 bits of a mask (:data:`C_FREE`)
_LOW = np.uint64(0xFFFFFFFF)


def rotation_matrix(q) -> np.ndarray:
    """The rotation matrix of a unit quaternion (x, y, z, w)."""
    x, y, z, w = (float(c) for c in q)
    return np.array([
        [1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
        [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
        [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)]])


@kernel(refcount=False)
def _field(meta, data, k, p0, p1, p2):
    """Trilinear interpolation of mesh field ``k`` at local point p: (d, gradient)."""
    off = int(meta[k, 0])
    nx = int(meta[k, 1])
    ny = int(meta[k, 2])
    nz = int(meta[k, 3])
    h = meta[k, 7]
    gx = (p0 - meta[k, 4]) / h
    gy = (p1 - meta[k, 5]) / h
    gz = (p2 - meta[k, 6]) / h
    if not (gx >= 0.0 and gy >= 0.0 and gz >= 0.0 and gx <= nx - 1 and gy <= ny - 1
            and gz <= nz - 1):
        return FAR, 0.0, 0.0, 1.0
    i = min(int(gx), nx - 2)
    j = min(int(gy), ny - 2)
    l = min(int(gz), nz - 2)
    tx = gx - i
    ty = gy - j
    tz = gz - l
    base = off + (i * ny + j) * nz + l
    sx = ny * nz
    c0_ = data[base]
    c1_ = data[base + 1]
    c2_ = data[base + nz]
    c3_ = data[base + nz + 1]
    c4_ = data[base + sx]
    c5_ = data[base + sx + 1]
    c6_ = data[base + sx + nz]
    c7_ = data[base + sx + nz + 1]
    # trilinear value and its exact gradient (corner a b e at index 4a + 2b + e)
    c00 = c0_ * (1 - tz) + c1_ * tz
    c01 = c2_ * (1 - tz) + c3_ * tz
    c10 = c4_ * (1 - tz) + c5_ * tz
    c11 = c6_ * (1 - tz) + c7_ * tz
    c0 = c00 * (1 - ty) + c01 * ty
    c1 = c10 * (1 - ty) + c11 * ty
    d = c0 * (1 - tx) + c1 * tx
    ddx = (c1 - c0) / h
    ddy = ((c01 - c00) * (1 - tx) + (c11 - c10) * tx) / h
    z0 = (c1_ - c0_) * (1 - ty) + (c3_ - c2_) * ty
    z1 = (c5_ - c4_) * (1 - ty) + (c7_ - c6_) * ty
    ddz = (z0 * (1 - tx) + z1 * tx) / h
    return d, ddx, ddy, ddz


@kernel(refcount=False, forceinline=True)
def _local(ob, k, x0, x1, x2):
    """The point in obstacle k's frame: p = R^T (x - c)."""
    r0 = x0 - ob[k, POS]
    r1 = x1 - ob[k, POS + 1]
    r2 = x2 - ob[k, POS + 2]
    p0 = ob[k, ROT] * r0 + ob[k, ROT + 3] * r1 + ob[k, ROT + 6] * r2
    p1 = ob[k, ROT + 1] * r0 + ob[k, ROT + 4] * r1 + ob[k, ROT + 7] * r2
    p2 = ob[k, ROT + 2] * r0 + ob[k, ROT + 5] * r1 + ob[k, ROT + 8] * r2
    return p0, p1, p2


@kernel(refcount=False, forceinline=True)
def _sign(a):
    return 1.0 if a >= 0.0 else -1.0


@kernel(refcount=False, forceinline=True)
def distance(ob, meta, data, k, x0, x1, x2):
    """Signed distance [m] of world point x from obstacle k's surface and the outward
    unit normal in the world frame (module docstring): (d, n0, n1, n2)."""
    shape = int(ob[k, SHAPE])
    if shape == 0:                  # plane z = 0, solid below: d = n . (x - c), n = R e_z
        n0 = ob[k, ROT + 2]
        n1 = ob[k, ROT + 5]
        n2 = ob[k, ROT + 8]
        d = n0 * (x0 - ob[k, POS]) + n1 * (x1 - ob[k, POS + 1]) + n2 * (x2 - ob[k, POS + 2])
        return d, n0, n1, n2
    p0, p1, p2 = _local(ob, k, x0, x1, x2)
    g0 = 0.0
    g1 = 0.0
    g2 = 1.0
    if shape == 1:                                   # sphere
        r = math.sqrt(p0 * p0 + p1 * p1 + p2 * p2)
        d = r - ob[k, PARAM]
        if r > 0.0:
            g0 = p0 / r
            g1 = p1 / r
            g2 = p2 / r
    elif shape == 2:                                 # box
        q0 = abs(p0) - ob[k, PARAM]
        q1 = abs(p1) - ob[k, PARAM + 1]
        q2 = abs(p2) - ob[k, PARAM + 2]
        if q0 > 0.0 or q1 > 0.0 or q2 > 0.0:
            a0 = max(q0, 0.0)
            a1 = max(q1, 0.0)
            a2 = max(q2, 0.0)
            d = math.sqrt(a0 * a0 + a1 * a1 + a2 * a2)
            g0 = _sign(p0) * a0 / d
            g1 = _sign(p1) * a1 / d
            g2 = _sign(p2) * a2 / d
        else:                                        # inside: the nearest face
            g2 = 0.0
            if q0 >= q1 and q0 >= q2:
                d = q0
                g0 = _sign(p0)
            elif q1 >= q2:
                d = q1
                g1 = _sign(p1)
            else:
                d = q2
                g2 = _sign(p2)
    elif shape == 3:                                 # capsule along local z
        s = min(max(p2, -ob[k, PARAM + 1]), ob[k, PARAM + 1])
        w2 = p2 - s
        r = math.sqrt(p0 * p0 + p1 * p1 + w2 * w2)
        d = r - ob[k, PARAM]
        if r > 0.0:
            g0 = p0 / r
            g1 = p1 / r
            g2 = w2 / r
    elif shape == 4:                                 # cylinder along local z
        rho = math.sqrt(p0 * p0 + p1 * p1)
        wr = rho - ob[k, PARAM]
        wz = abs(p2) - ob[k, PARAM + 1]
        e0 = p0 / rho if rho > 0.0 else 1.0
        e1 = p1 / rho if rho > 0.0 else 0.0
        if wr > 0.0 or wz > 0.0:
            a = max(wr, 0.0)
            b = max(wz, 0.0)
            d = math.sqrt(a * a + b * b)
            g0 = e0 * a / d
            g1 = e1 * a / d
            g2 = _sign(p2) * b / d
        elif wr >= wz:
            d = wr
            g0 = e0
            g1 = e1
            g2 = 0.0
        else:
            d = wz
            g2 = _sign(p2)
    else:                                            # mesh: sampled field
        d, g0, g1, g2 = _field(meta, data, int(ob[k, FIELD]), p0, p1, p2)
        gn = math.sqrt(g0 * g0 + g1 * g1 + g2 * g2)
        if gn > 0.0:
            g0 /= gn
            g1 /= gn
            g2 /= gn
        else:
            g2 = 1.0
    n0 = ob[k, ROT] * g0 + ob[k, ROT + 1] * g1 + ob[k, ROT + 2] * g2
    n1 = ob[k, ROT + 3] * g0 + ob[k, ROT + 4] * g1 + ob[k, ROT + 5] * g2
    n2 = ob[k, ROT + 6] * g0 + ob[k, ROT + 7] * g1 + ob[k, ROT + 8] * g2
    return d, n0, n1, n2


@kernel(refcount=False, forceinline=True)
def _point_velocity(ob, k, x0, x1, x2):
    """The obstacle's velocity at world point x: v_lin + w x (x - c)."""
    r0 = x0 - ob[k, POS]
    r1 = x1 - ob[k, POS + 1]
    r2 = x2 - ob[k, POS + 2]
    w0 = ob[k, OMEGA]
    w1 = ob[k, OMEGA + 1]
    w2 = ob[k, OMEGA + 2]
    return (ob[k, VEL] + w1 * r2 - w2 * r1, ob[k, VEL + 1] + w2 * r0 - w0 * r2,
            ob[k, VEL + 2] + w0 * r1 - w1 * r0)


@kernel(inline='always')
def _far(ob, k, x0, x1, x2, margin):
    """Broad phase: x is further than ``margin`` from obstacle k's bounding sphere (never
    for a plane), so neither contact nor a push is possible this step."""
    reach = ob[k, REACH]
    if reach <= 0.0:
        return False
    r0 = x0 - ob[k, POS]
    r1 = x1 - ob[k, POS + 1]
    r2 = x2 - ob[k, POS + 2]
    lim = reach + margin
    return r0 * r0 + r1 * r1 + r2 * r2 > lim * lim


@intrinsic
def _trailing_zeros(typingctx, m):
    """The index of the lowest bit set in uint64 m (one instruction: LLVM's cttz)."""
    if m != types.uint64:
        return None

    def codegen(context, builder, signature, args):
        return builder.cttz(args[0], ir.Constant(ir.IntType(1), 1))
    return types.uint64(types.uint64), codegen


@kernel(refcount=False, forceinline=True)
def _bits(k0, k1):
    """The mask with bits k0..min(k1, 64)-1 set."""
    hi = ALL if k1 >= MASK_BITS else (nb.uint64(1) << nb.uint64(k1)) - nb.uint64(1)
    lo = ALL if k0 >= MASK_BITS else (nb.uint64(1) << nb.uint64(k0)) - nb.uint64(1)
    return hi & ~lo


@kernel(refcount=False, forceinline=True)
def _next(m, k, nob):
    """The obstacle after k to visit and the bits still to visit: the lowest bit set in m
    (an obstacle below 64 that the mask keeps), then each of the obstacles from the 65th
    on; k = -1 at the end. Starts from m = mask & _bits(0, nob), k = -1."""
    if m != nb.uint64(0):
        return nb.int64(_trailing_zeros(m)), m & (m - nb.uint64(1))
    j = max(k + 1, MASK_BITS)
    return (j if j < nob else nb.int64(-1)), m


@kernel(refcount=False, forceinline=True)
def _bit(k):
    """The mask bit of obstacle row k (0 from the 65th row on: no bit)."""
    return nb.uint64(1) << nb.uint64(k) if k < MASK_BITS else nb.uint64(0)


@kernel(refcount=False, forceinline=True)
def released(contact, i):
    """The mask of the obstacle rows vertex i is released from (module docstring,
    "Obstacles placed through the cloth"), from its ``Control.contact`` row."""
    return (nb.uint64(contact[i, C_FREE])
            | (nb.uint64(contact[i, C_FREE + 1]) << nb.uint64(32)))


@kernel(refcount=False, forceinline=True)
def _store_released(contact, i, free):
    contact[i, C_FREE] = float(free & nb.uint64(_LOW))
    contact[i, C_FREE + 1] = float(free >> nb.uint64(32))


def released_rows(contact: np.ndarray) -> np.ndarray:
    """Every vertex's release mask, (n,) uint64 (:func:`released`)."""
    return (contact[:, C_FREE].astype(np.uint64)
            | (contact[:, C_FREE + 1].astype(np.uint64) << np.uint64(32)))


def store_released_rows(contact: np.ndarray, masks: np.ndarray) -> None:
    """Write every vertex's release mask (n,) uint64 into ``contact``, in place."""
    masks = np.asarray(masks, dtype=np.uint64)
    contact[:, C_FREE] = (masks & _LOW).astype(np.float64)
    contact[:, C_FREE + 1] = (masks >> np.uint64(32)).astype(np.float64)


@kernel(refcount=False, forceinline=True)
def near_mask(lo0, lo1, lo2, hi0, hi1, hi2, vmax, ob, th, dt):
    """Broad phase of a group of vertices (a chunk or a tile of the step) whose old
    positions lie in the box [lo, hi] and whose speeds before contact are at most vmax:
    (mask, V^2): a bit mask with bit k set when obstacle k may act on one of them this
    step (obstacles from the 65th on have no bit: always kept), and the squared speed V
    below which a vertex must end the response for the mask to hold (a faster one is
    pushed out against every obstacle). Exact, not a heuristic: :func:`resolve` and
    :func:`push_out` skip the cleared obstacles and give the same result as with all.

    Every vertex ends the contact response slower than ``V = vmax + 2 S`` (S the sum of
    the obstacles' :data:`SPEED`): a response changes only the velocity relative to the
    obstacle, u = v - v_o, and never lengthens it, so each obstacle adds at most twice its
    speed (the caller checks each vertex against V all the same).
    Then an obstacle with bounding sphere (c, reach) is cleared when ``dist(c, box) >
    reach + 2 th + dt V``: every vertex starts further from it than the reach
    :func:`resolve` tests, and ends further than the one :func:`push_out` tests (the
    spare th covers rounding). A plane that does not rotate (its points all move at
    ``SPEED``) is cleared when its signed distance is above ``2 th + dt V`` over the whole
    box: ``min d = n . (m - c) - sum_j |n_j| h_j`` with m the box's centre and h its half
    sizes. A rotating plane keeps every bit set (its points' speed has no bound)."""
    nob = ob.shape[0]
    s = 0.0
    rotating = False
    for k in range(nob):
        s += ob[k, SPEED]
        rotating |= ob[k, REACH] <= 0.0 and (ob[k, OMEGA] != 0.0 or ob[k, OMEGA + 1] != 0.0
                                             or ob[k, OMEGA + 2] != 0.0)
    speed = vmax + 2.0 * s
    if rotating:
        return ALL, speed * speed
    margin = 2.0 * th + dt * speed
    m0 = 0.5 * (lo0 + hi0)
    m1 = 0.5 * (lo1 + hi1)
    m2 = 0.5 * (lo2 + hi2)
    h0 = 0.5 * (hi0 - lo0)
    h1 = 0.5 * (hi1 - lo1)
    h2 = 0.5 * (hi2 - lo2)
    mask = ALL
    for k in range(min(nob, MASK_BITS)):
        reach = ob[k, REACH]
        if reach <= 0.0:
            n0 = ob[k, ROT + 2]
            n1 = ob[k, ROT + 5]
            n2 = ob[k, ROT + 8]
            d = (n0 * (m0 - ob[k, POS]) + n1 * (m1 - ob[k, POS + 1])
                 + n2 * (m2 - ob[k, POS + 2]) - abs(n0) * h0 - abs(n1) * h1 - abs(n2) * h2)
            cut = d > margin
        else:
            e0 = max(lo0 - ob[k, POS], ob[k, POS] - hi0, 0.0)
            e1 = max(lo1 - ob[k, POS + 1], ob[k, POS + 1] - hi1, 0.0)
            e2 = max(lo2 - ob[k, POS + 2], ob[k, POS + 2] - hi2, 0.0)
            lim = reach + margin
            cut = e0 * e0 + e1 * e1 + e2 * e2 > lim * lim
        if cut:
            mask &= ~(nb.uint64(1) << nb.uint64(k))
    return mask, speed * speed


@kernel(refcount=False, forceinline=True)
def resolve(i, x0, x1, x2, v0, v1, v2, fs0, fs1, fs2, m, dt, ob, meta, data, th, out, mask):
    """The contact response of vertex i (module docstring) at old position x for its new
    velocity v (before the position update) and the step's force on it fs [N] (``m (v -
    v_start) / dt``: internal, applied, weight, damping), with obstacles ``ob`` (their
    fields ``meta``, ``data``) and thickness ``th``; writes row i of ``out``
    (``Control.contact``) and returns (v0, v1, v2, external work [J], dissipation [J])
    with v the velocity after contact. The caller then moves the vertex and puts it back
    on the layer (:func:`push_out`). An obstacle whose bounding sphere is beyond the
    vertex's reach this step (thickness plus the step's travel of both) is skipped
    before its distance is evaluated, and so is every obstacle k < 64 whose bit is clear
    in ``mask`` (:func:`near_mask`). An obstacle the vertex is released from (row i's
    :func:`released` mask) is skipped while the vertex starts the step inside its layer
    (d < th); found outside it (tested, beyond its reach, or left out by ``mask``), the
    vertex is released no more, and the mask is written back to row i (module
    docstring). Only scalars and the contact arrays come in, so the step's position and
    velocity arrays stay private to its loop (no aliasing for LLVM to assume)."""
    b0 = v0
    b1 = v1
    b2 = v2
    hit = -1.0
    hit2 = -1.0
    s0 = 0.0            # the velocity change of the obstacles after the first
    s1 = 0.0
    s2 = 0.0
    gap = FAR
    work = 0.0
    diss = 0.0
    speed = math.sqrt(v0 * v0 + v1 * v1 + v2 * v2)
    # an obstacle the mask leaves out is one the vertex starts out of the layer of
    free = released(out, i) & nb.uint64(mask)
    nob = ob.shape[0]
    left = nb.uint64(mask) & _bits(0, nob)
    k = nb.int64(-1)
    while True:
        k, left = _next(left, k, nob)
        if k < 0:
            break
        bit = _bit(k)
        if _far(ob, k, x0, x1, x2, th + dt * (speed + ob[k, SPEED])):
            free &= ~bit                        # far outside it: released no more
            continue
        d, n0, n1, n2 = distance(ob, meta, data, k, x0, x1, x2)
        if free & bit != nb.uint64(0):
            if d < th:
                continue                        # still inside: it does not act
            free &= ~bit                        # outside: in contact as any vertex
        gap = min(gap, d - th)
        o0, o1, o2 = _point_velocity(ob, k, x0, x1, x2)
        u0 = v0 - o0
        u1 = v1 - o1
        u2 = v2 - o2
        un = u0 * n0 + u1 * n1 + u2 * n2
        umin = -(d - th) / dt if d > th else 0.0
        if un >= umin:
            continue
        before = u0 * u0 + u1 * u1 + u2 * u2
        j = umin - un
        u0 += j * n0
        u1 += j * n1
        u2 += j * n2
        un = umin
        t0 = u0 - un * n0
        t1 = u1 - un * n1
        t2 = u2 - un * n2
        ut = math.sqrt(t0 * t0 + t1 * t1 + t2 * t2)
        if ut <= ob[k, MU_S] * j:
            s = 1.0
        else:
            s = ob[k, MU_K] * j / ut
        u0 -= s * t0
        u1 -= s * t1
        u2 -= s * t2
        w0 = o0 + u0
        w1 = o1 + u1
        w2 = o2 + u2
        after = u0 * u0 + u1 * u1 + u2 * u2
        kin = 0.5 * m * (before - after)
        # the potential energy the response's displacement c = dt (w - v) takes from the
        # step's force, by the trapezoid rule (the force falls from fs to what the
        # contact balances): a vertex resting on the obstacle, pushed into the layer and
        # taken back each step, loses nothing (its velocity change's kinetic energy
        # alone read m (g dt)^2 / 2 a step, a drift of m g^2 dt / 2 a second)
        pot = 0.5 * dt * (fs0 * (w0 - v0) + fs1 * (w1 - v1) + fs2 * (w2 - v2))
        diss += kin + pot
        work += 0.5 * m * ((w0 * w0 + w1 * w1 + w2 * w2) - (v0 * v0 + v1 * v1 + v2 * v2)) + kin
        if hit < 0.0:
            hit = float(k)
        else:                                   # a second obstacle (a corner)
            hit2 = float(k)
            s0 += w0 - v0
            s1 += w1 - v1
            s2 += w2 - v2
        v0 = w0
        v1 = w1
        v2 = w2
    out[i, C_FORCE] = m * (v0 - b0) / dt
    out[i, C_FORCE + 1] = m * (v1 - b1) / dt
    out[i, C_FORCE + 2] = m * (v2 - b2) / dt
    out[i, C_ID] = hit
    out[i, C_GAP] = gap
    out[i, C_FORCE2] = m * s0 / dt
    out[i, C_FORCE2 + 1] = m * s1 / dt
    out[i, C_FORCE2 + 2] = m * s2 / dt
    out[i, C_ID2] = hit2
    _store_released(out, i, free)
    return v0, v1, v2, work, diss


@kernel(refcount=False, forceinline=True)
def push_out(x0, x1, x2, ob, meta, data, th, mask, free=0):
    """A vertex just moved to x, put back on the contact layer of every obstacle it is
    inside (along the normal; no velocity change): the corrected (x0, x1, x2). Obstacles
    whose bit is clear in ``mask`` (:func:`near_mask`) are skipped until a push has moved
    the vertex: the mask holds for the position the step moved it to, not beyond. After
    a push every obstacle is checked again, the earlier ones too (a push off a wall can
    take the vertex back into the floor's layer, in a corner) and the same one (whose
    distance, deep inside a mesh or on a curved surface, is not exact along the push),
    up to :data:`PUSHES` pushes: in a wedge narrower than the layer no position is
    outside both, and the vertex ends on the layer of the last obstacle that pushed it.
    The obstacles whose bits are set in ``free`` (the vertex's :func:`released` mask)
    never push it."""
    nob = ob.shape[0]
    keep = ~nb.uint64(free)
    left = nb.uint64(mask) & _bits(0, nob) & keep
    k = nb.int64(-1)
    pushes = 0
    while True:
        k, left = _next(left, k, nob)
        if k < 0:
            break
        if _far(ob, k, x0, x1, x2, th):
            continue
        d, n0, n1, n2 = distance(ob, meta, data, k, x0, x1, x2)
        if d < th:
            x0 += (th - d) * n0
            x1 += (th - d) * n1
            x2 += (th - d) * n2
            pushes += 1
            if pushes < PUSHES:                 # every obstacle again, this one too
                left = _bits(0, nob) & keep
                k = nb.int64(-1)
            else:                               # the last pass: the later ones only
                left = _bits(k + 1, nob) & keep
    return x0, x1, x2


@kernel(parallel=True)
def distances(ob, meta, data, k, pts):
    """Signed distances and normals of points (m,3) from obstacle k: (m,4)."""
    out = np.empty((pts.shape[0], 4))
    for a in nb.prange(pts.shape[0]):
        d, n0, n1, n2 = distance(ob, meta, data, k, pts[a, 0], pts[a, 1], pts[a, 2])
        out[a, 0] = d
        out[a, 1] = n0
        out[a, 2] = n1
        out[a, 3] = n2
    return out


@kernel(refcount=False)
def _point_triangle(p0, p1, p2, a, b, c):
    """Distance from point p to triangle (a, b, c)
    (:func:`.surface_query.point_triangle_sq`)."""
    return math.sqrt(point_triangle_sq(p0, p1, p2, a, b, c)[0])


@kernel()
def _band_distances(verts, faces, origin, shape, h, band, out):
    """Unsigned distance to the mesh at every grid sample within ``band`` of a triangle
    (each triangle visits the samples of its bounding box grown by ``band``); samples
    further away keep ``band``."""
    ny = shape[1]
    nz = shape[2]
    for t in range(faces.shape[0]):
        a = verts[faces[t, 0]]
        b = verts[faces[t, 1]]
        c = verts[faces[t, 2]]
        lo = np.empty(3, np.int64)
        hi = np.empty(3, np.int64)
        for k in range(3):
            mn = min(a[k], b[k], c[k]) - band
            mx = max(a[k], b[k], c[k]) + band
            lo[k] = max(0, int(math.floor((mn - origin[k]) / h)))
            hi[k] = min(shape[k] - 1, int(math.ceil((mx - origin[k]) / h)))
        for i in range(lo[0], hi[0] + 1):
            for j in range(lo[1], hi[1] + 1):
                for l in range(lo[2], hi[2] + 1):
                    d = _point_triangle(origin[0] + i * h, origin[1] + j * h,
                                        origin[2] + l * h, a, b, c)
                    idx = (i * ny + j) * nz + l
                    if d < out[idx]:
                        out[idx] = d


@kernel()
def _inside(verts, faces, origin, shape, h, inside):
    """Inside a closed mesh, by the parity of the crossings of each grid column (a line
    along z through the samples, shifted by a tiny irrational fraction of a cell so that
    it never meets an edge or a vertex exactly) with the triangles."""
    nx = shape[0]
    ny = shape[1]
    nz = shape[2]
    sx = 0.3183098861837907e-6 * h
    sy = 0.2718281828459045e-6 * h
    crossings = np.zeros(nx * ny, np.int64)
    # pass 1 counts, pass 2 stores the crossing heights per column
    total = 0
    for pass_ in range(2):
        if pass_ == 1:
            start = np.zeros(nx * ny + 1, np.int64)
            for q in range(nx * ny):
                start[q + 1] = start[q] + crossings[q]
            zval = np.empty(start[-1])
            fill = start[:-1].copy()
        for t in range(faces.shape[0]):
            a = verts[faces[t, 0]]
            b = verts[faces[t, 1]]
            c = verts[faces[t, 2]]
            i0 = max(0, int(math.ceil((min(a[0], b[0], c[0]) - origin[0] - sx) / h)))
            i1 = min(nx - 1, int(math.floor((max(a[0], b[0], c[0]) - origin[0] - sx) / h)))
            j0 = max(0, int(math.ceil((min(a[1], b[1], c[1]) - origin[1] - sy) / h)))
            j1 = min(ny - 1, int(math.floor((max(a[1], b[1], c[1]) - origin[1] - sy) / h)))
            den = (b[1] - c[1]) * (a[0] - c[0]) + (c[0] - b[0]) * (a[1] - c[1])
            if den == 0.0:
                continue                                   # a vertical triangle
            for i in range(i0, i1 + 1):
                px = origin[0] + i * h + sx
                for j in range(j0, j1 + 1):
                    py = origin[1] + j * h + sy
                    l1 = ((b[1] - c[1]) * (px - c[0]) + (c[0] - b[0]) * (py - c[1])) / den
                    l2 = ((c[1] - a[1]) * (px - c[0]) + (a[0] - c[0]) * (py - c[1])) / den
                    l3 = 1.0 - l1 - l2
                    if l1 < 0.0 or l2 < 0.0 or l3 < 0.0:
                        continue
                    q = i * ny + j
                    if pass_ == 0:
                        crossings[q] += 1
                        total += 1
                    else:
                        zval[fill[q]] = l1 * a[2] + l2 * b[2] + l3 * c[2]
                        fill[q] += 1
    for q in range(nx * ny):
        zc = np.sort(zval[start[q]:start[q + 1]])
        for l in range(nz):
            z = origin[2] + l * h
            below = 0
            for m in range(zc.shape[0]):
                if zc[m] < z:
                    below += 1
            inside[q * nz + l] = below % 2 == 1


def mesh_distance_field(vertices: np.ndarray, faces: np.ndarray, spacing: float,
                        margin: float):
    """A signed distance field of a closed triangle mesh (in its own frame) on a regular
    grid of ``spacing`` [m] covering its bounds plus ``margin``: (origin (3,), shape (3,),
    values flat, C order (x, y, z)). Exact distances (closest point on each triangle,
    Ericson 5.1.5) at the samples within ``margin`` of the surface, ``margin`` beyond
    (contact needs only the layer near the surface); the sign from the parity of each
    grid column's crossings with the surface. Between samples trilinear interpolation:
    exact where the distance is linear over a cell (near a face), within ``spacing^2 /
    (8 R)`` of a surface of curvature radius R. Inside, deeper than ``margin``, the depth
    is the Euclidean distance transform's (to the nearest sample outside, less half a
    spacing: within about half a spacing), at least ``margin``: a vertex found that deep
    (a mesh posed onto the cloth) is pushed out by the way nearest the surface, where a
    constant depth had no gradient and its normal was the mesh's +z. Cost: each triangle
    visits the samples within ``margin`` of its bounding box."""
    from scipy.ndimage import distance_transform_edt
    v = np.ascontiguousarray(vertices, dtype=np.float64)
    f = np.ascontiguousarray(faces, dtype=np.int64)
    lo = v.min(0) - margin
    hi = v.max(0) + margin
    shape = np.maximum(2, np.ceil((hi - lo) / spacing).astype(np.int64) + 1)
    dist = np.full(int(np.prod(shape)), float(margin))
    _band_distances(v, f, lo, shape, float(spacing), float(margin), dist)
    inside = np.zeros(len(dist), dtype=np.bool_)
    _inside(v, f, lo, shape, float(spacing), inside)
    deep = inside & (dist >= margin)
    if deep.any():
        # to the nearest sample outside, which lies up to a spacing beyond the surface:
        # half a spacing less, within half a spacing of the depth
        depth = distance_transform_edt(inside.reshape(tuple(shape))).reshape(-1) * spacing
        dist[deep] = np.maximum(depth[deep] - 0.5 * spacing, margin)
    return lo, shape, np.where(inside, -dist, dist)
