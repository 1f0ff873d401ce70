"""The compiled kernels of the virtual camera (:mod:`cosserat_ros.camera`): a ray cast of
triangles and analytic obstacles, binned so that its cost grows with pixels plus triangles.

Conventions
-----------
Everything here is in the camera's optical frame (z forward, x right, y down, as ROS
camera optical frames are). Pixel ``(u, v)`` (column, row; centres at integer coordinates,
as OpenCV and ROS) is the ray from the optical centre through ``d = ((u - cx) / fx,
(v - cy) / fy, 1)``; a hit at ``t d`` has depth ``t`` along the optical axis (``d_z = 1``).
A surface is seen when ``near <= t <= far``; the nearest one wins.

Triangles (the cloth, both sides, and mesh obstacles): the exact ray-triangle
intersection of Moeller and Trumbore (1997, "Fast, minimum storage ray-triangle
intersection"), in float64: ``e1 = b - a``, ``e2 = c - a``, ``p = d x e2``, ``det = e1 . p``,
``s = -a``, barycentrics ``beta = (s . p) / det``, ``gamma = (d . (s x e1)) / det`` (the hit
is inside when both are >= 0 and ``beta + gamma <= 1``), ``t = (e2 . (s x e1)) / det``.
Triangles are binned by the image rows their projection covers (bands of :data:`BAND`
rows), and each band, in parallel, tests only the pixels of its triangles' bounding boxes:
the work is the sum of the triangles' projected areas plus their number, not pixels times
triangles. A triangle with a vertex at or behind the camera's plane (``z <= 0``) has no
bounded projection; it is tested over the whole image (rare: a camera inside the cloth).

Analytic obstacles (the shapes of :mod:`.contact`) in their own frame, ray ``o + t d_l``
with ``o = R^T (0 - c)``, ``d_l = R^T d`` (``R`` the obstacle's rotation in the camera
frame, ``c`` its centre): the plane ``z = 0`` at ``t = -o_z / d_z``; the sphere ``|o + t d|
= r``, the smallest root ``t = (-b -+ sqrt(b^2 - a (|o|^2 - r^2))) / a``; the box by slabs
(Kay and Kajiya 1986), entry ``max_k min(t1_k, t2_k)``, exit ``min_k max(...)``; the
cylinder (axis z, half length l) as the side ``x^2 + y^2 = r^2`` with ``|z| <= l`` and the
caps ``z = +-l`` with ``x^2 + y^2 <= r^2``; the capsule as its side and the spheres at
``+-l``. Of each shape the first crossing at ``t >= near`` is taken (a camera inside a
solid sees its inside wall). The outward normal at the hit shades the colour image.

This module imports no ROS package.
"""
from __future__ import annotations

import math

import numba as nb
import numpy as np

from .compiled import kernel

__all__ = ['BAND', 'KIND_PLANE', 'KIND_SPHERE', 'KIND_BOX', 'KIND_CAPSULE', 'KIND_CYLINDER',
           'OB_WIDTH', 'cast', 'shade', 'vertex_normals']

#: rows of one band of the image (the unit of parallel work)
BAND = 8

#: analytic obstacle rows: kind, the camera's origin in the obstacle's frame (3), the
#: rotation camera -> obstacle row-major (9), params (3: radius / half extents / radius and
#: half length), the pixel box it may cover (u0, u1, v0, v1, inclusive)
KIND_PLANE, KIND_SPHERE, KIND_BOX, KIND_CAPSULE, KIND_CYLINDER = 0, 1, 2, 3, 4
OB_KIND, OB_O, OB_R, OB_P, OB_BOX = 0, 1, 4, 13, 16
OB_WIDTH = 20

#: hit codes: >= 0 a triangle, NO_HIT none, <= -2 analytic obstacle -2 - k
NO_HIT = -1


@kernel()
def _triangle_t(d0, d1, d2, a0, a1, a2, b0, b1, b2, c0, c1, c2):
    """(t, beta, gamma) of the ray ``t d`` from the origin through triangle abc, t = inf
    if it misses (Moeller-Trumbore, module docstring)."""
    e10, e11, e12 = b0 - a0, b1 - a1, b2 - a2
    e20, e21, e22 = c0 - a0, c1 - a1, c2 - a2
    p0 = d1 * e22 - d2 * e21
    p1 = d2 * e20 - d0 * e22
    p2 = d0 * e21 - d1 * e20
    det = e10 * p0 + e11 * p1 + e12 * p2
    if det == 0.0:
        return math.inf, 0.0, 0.0
    inv = 1.0 / det
    s0, s1, s2 = -a0, -a1, -a2
    beta = (s0 * p0 + s1 * p1 + s2 * p2) * inv
    if beta < 0.0 or beta > 1.0:
        return math.inf, 0.0, 0.0
    q0 = s1 * e12 - s2 * e11
    q1 = s2 * e10 - s0 * e12
    q2 = s0 * e11 - s1 * e10
    gamma = (d0 * q0 + d1 * q1 + d2 * q2) * inv
    if gamma < 0.0 or beta + gamma > 1.0:
        return math.inf, 0.0, 0.0
    return (e20 * q0 + e21 * q1 + e22 * q2) * inv, beta, gamma


@kernel()
def _first(t1, t2, near):
    """The smaller of two crossings that is >= near, else inf."""
    lo, hi = min(t1, t2), max(t1, t2)
    if lo >= near:
        return lo
    if hi >= near:
        return hi
    return math.inf


@kernel()
def _sphere(o0, o1, o2, d0, d1, d2, r, near):
    a = d0 * d0 + d1 * d1 + d2 * d2
    b = o0 * d0 + o1 * d1 + o2 * d2
    c = o0 * o0 + o1 * o1 + o2 * o2 - r * r
    disc = b * b - a * c
    if disc < 0.0:
        return math.inf
    s = math.sqrt(disc)
    return _first((-b - s) / a, (-b + s) / a, near)


@kernel()
def _slab(o, d, h, t_in, t_out):
    """The slab |p_k| <= h narrowing the interval (t_in, t_out); empty: t_in > t_out."""
    if d == 0.0:
        if abs(o) > h:
            return math.inf, -math.inf
        return t_in, t_out
    ta, tb = (-h - o) / d, (h - o) / d
    return max(t_in, min(ta, tb)), min(t_out, max(ta, tb))


@kernel()
def _box(o0, o1, o2, d0, d1, d2, h0, h1, h2, near):
    """Slab test (Kay and Kajiya): the first crossing >= near."""
    t_in, t_out = _slab(o0, d0, h0, -math.inf, math.inf)
    t_in, t_out = _slab(o1, d1, h1, t_in, t_out)
    t_in, t_out = _slab(o2, d2, h2, t_in, t_out)
    if t_in > t_out:
        return math.inf
    return _first(t_in, t_out, near)


@kernel()
def _side(o0, o1, o2, d0, d1, d2, r, l, near):
    """The side of the cylinder x^2 + y^2 = r^2, |z| <= l: its first crossing >= near."""
    a = d0 * d0 + d1 * d1
    if a == 0.0:
        return math.inf
    b = o0 * d0 + o1 * d1
    c = o0 * o0 + o1 * o1 - r * r
    disc = b * b - a * c
    if disc < 0.0:
        return math.inf
    s = math.sqrt(disc)
    best = math.inf
    for t in ((-b - s) / a, (-b + s) / a):
        if t >= near and t < best and abs(o2 + t * d2) <= l:
            best = t
    return best


@kernel()
def _cap(o0, o1, o2, d0, d1, d2, z, r, near):
    """The disc z = const, x^2 + y^2 <= r^2."""
    if d2 == 0.0:
        return math.inf
    t = (z - o2) / d2
    if t < near:
        return math.inf
    x, y = o0 + t * d0, o1 + t * d1
    if x * x + y * y > r * r:
        return math.inf
    return t


@kernel(refcount=False, forceinline=True)
def _obstacle(ob, k, d0, d1, d2, near):
    """Ray ``t d`` against analytic obstacle row ``k``: its first crossing t >= near
    (inf: none)."""
    kind = int(ob[k, OB_KIND])
    o0, o1, o2 = ob[k, OB_O], ob[k, OB_O + 1], ob[k, OB_O + 2]
    # R: camera -> local, row-major (scalars: a slice would be a counted array)
    R0, R1, R2 = ob[k, OB_R], ob[k, OB_R + 1], ob[k, OB_R + 2]
    R3, R4, R5 = ob[k, OB_R + 3], ob[k, OB_R + 4], ob[k, OB_R + 5]
    R6, R7, R8 = ob[k, OB_R + 6], ob[k, OB_R + 7], ob[k, OB_R + 8]
    l0 = R0 * d0 + R1 * d1 + R2 * d2
    l1 = R3 * d0 + R4 * d1 + R5 * d2
    l2 = R6 * d0 + R7 * d1 + R8 * d2
    p0, p1 = ob[k, OB_P], ob[k, OB_P + 1]
    if kind == KIND_PLANE:
        if l2 == 0.0:
            return math.inf
        t = -o2 / l2
        return t if t >= near else math.inf
    if kind == KIND_SPHERE:
        return _sphere(o0, o1, o2, l0, l1, l2, p0, near)
    if kind == KIND_BOX:
        return _box(o0, o1, o2, l0, l1, l2, p0, p1, ob[k, OB_P + 2], near)
    t = _side(o0, o1, o2, l0, l1, l2, p0, p1, near)
    if kind == KIND_CYLINDER:
        return min(t, _cap(o0, o1, o2, l0, l1, l2, p1, p0, near),
                   _cap(o0, o1, o2, l0, l1, l2, -p1, p0, near))
    return min(t, _sphere(o0, o1, o2 - p1, l0, l1, l2, p0, near),
               _sphere(o0, o1, o2 + p1, l0, l1, l2, p0, near))


@kernel(refcount=False, forceinline=True)
def _obstacle_normal(ob, k, t, d0, d1, d2):
    """The outward normal (camera frame, not unit) of obstacle row ``k`` where the ray
    ``t d`` meets it: the plane's z; the sphere's ``q``; the box's face of the largest
    ``|q_k| / h_k``; the cylinder's cap (``|q_z| / l >= |q_xy| / r``) or side; the
    capsule's ``q - clamp(q_z, -l, l) e_z`` (``q`` the hit in the obstacle's frame)."""
    kind = int(ob[k, OB_KIND])
    R0, R1, R2 = ob[k, OB_R], ob[k, OB_R + 1], ob[k, OB_R + 2]
    R3, R4, R5 = ob[k, OB_R + 3], ob[k, OB_R + 4], ob[k, OB_R + 5]
    R6, R7, R8 = ob[k, OB_R + 6], ob[k, OB_R + 7], ob[k, OB_R + 8]
    if kind == KIND_PLANE:                          # local z in the camera frame
        return R6, R7, R8
    q0 = ob[k, OB_O] + t * (R0 * d0 + R1 * d1 + R2 * d2)
    q1 = ob[k, OB_O + 1] + t * (R3 * d0 + R4 * d1 + R5 * d2)
    q2 = ob[k, OB_O + 2] + t * (R6 * d0 + R7 * d1 + R8 * d2)
    p0, p1, p2 = ob[k, OB_P], ob[k, OB_P + 1], ob[k, OB_P + 2]
    n0, n1, n2 = q0, q1, q2
    if kind == KIND_BOX:
        a0, a1, a2 = abs(q0) / p0, abs(q1) / p1, abs(q2) / p2
        if a0 >= a1 and a0 >= a2:
            n0, n1, n2 = q0, 0.0, 0.0
        elif a1 >= a2:
            n0, n1, n2 = 0.0, q1, 0.0
        else:
            n0, n1, n2 = 0.0, 0.0, q2
    elif kind == KIND_CYLINDER:
        if abs(q2) / p1 >= math.sqrt(q0 * q0 + q1 * q1) / p0:
            n0, n1 = 0.0, 0.0
        else:
            n2 = 0.0
    elif kind == KIND_CAPSULE:
        n2 = q2 - min(p1, max(-p1, q2))
    # back to the camera frame: R^T n (R is camera -> local)
    return (R0 * n0 + R3 * n1 + R6 * n2, R1 * n0 + R4 * n1 + R7 * n2,
            R2 * n0 + R5 * n1 + R8 * n2)


#: a prime above any row or band count (MAX_SIDE = 4096 rows): j -> j P mod n permutes
SPREAD = 7919


@kernel()
def _spread(j, n):
    """The j-th of n rows (or bands) in an order that deals neighbours out far apart,
    ``j P mod n`` (P prime > n: a permutation). prange hands each thread one contiguous
    run of j, and an image's work sits in neighbouring rows (the cloth, the table), so
    that each thread then gets its share of them."""
    return (j * SPREAD) % n


@kernel()
def _bounds(verts, tris, fx, fy, cx, cy, width, height, near, far, box):
    """Per triangle its pixel bounding box (u0, u1, v0, v1), inclusive, clipped to the
    image; u0 > u1 when it cannot be seen (behind ``near``, beyond ``far`` or off the
    image)."""
    eps = 1e-9
    for f in range(tris.shape[0]):
        zmin, zmax = math.inf, -math.inf
        for j in range(3):
            z = verts[tris[f, j], 2]
            zmin = min(zmin, z)
            zmax = max(zmax, z)
        box[f, 0], box[f, 1], box[f, 2], box[f, 3] = 1, 0, 1, 0
        if not (zmax >= near and zmin <= far):      # NaN too
            continue
        if zmin <= 0.0:                             # no bounded projection: all of it
            box[f, 0], box[f, 1], box[f, 2], box[f, 3] = 0, width - 1, 0, height - 1
            continue
        umin, umax, vmin, vmax = math.inf, -math.inf, math.inf, -math.inf
        for j in range(3):
            i = tris[f, j]
            z = verts[i, 2]
            u = fx * verts[i, 0] / z + cx
            v = fy * verts[i, 1] / z + cy
            umin, umax = min(umin, u), max(umax, u)
            vmin, vmax = min(vmin, v), max(vmax, v)
        u0 = max(0.0, math.ceil(umin - eps))
        u1 = min(width - 1.0, math.floor(umax + eps))
        v0 = max(0.0, math.ceil(vmin - eps))
        v1 = min(height - 1.0, math.floor(vmax + eps))
        if u0 <= u1 and v0 <= v1:
            box[f, 0], box[f, 1], box[f, 2], box[f, 3] = int(u0), int(u1), int(v0), int(v1)


@kernel()
def _bin(box, nbands):
    """Counting sort of the triangles by the bands their boxes cover: (start (nbands + 1),
    triangle ids)."""
    count = np.zeros(nbands + 1, np.int64)
    for f in range(box.shape[0]):
        if box[f, 0] <= box[f, 1]:
            for b in range(box[f, 2] // BAND, box[f, 3] // BAND + 1):
                count[b + 1] += 1
    for b in range(nbands):
        count[b + 1] += count[b]
    ids = np.empty(count[nbands], np.int64)
    fill = count[:nbands].copy()
    for f in range(box.shape[0]):
        if box[f, 0] <= box[f, 1]:
            for b in range(box[f, 2] // BAND, box[f, 3] // BAND + 1):
                ids[fill[b]] = f
                fill[b] += 1
    return count, ids


@kernel(parallel=True)
def cast(verts, tris, obstacles, fx, fy, cx, cy, near, far, depth, hit, bary):
    """Ray-cast every pixel (module docstring). In: ``verts`` (n, 3) and ``tris`` (m, 3)
    in the camera frame, ``obstacles`` (k, :data:`OB_WIDTH`) rows. Out (the image's shape
    (h, w)): ``depth`` (inf where nothing is hit), ``hit`` (triangle index, NO_HIT or
    -2 - obstacle row), ``bary`` (h, w, 2) the hit triangle's (beta, gamma)."""
    height, width = depth.shape
    box = np.empty((tris.shape[0], 4), np.int64)
    _bounds(verts, tris, fx, fy, cx, cy, width, height, near, far, box)
    nbands = (height + BAND - 1) // BAND
    start, ids = _bin(box, nbands)
    for j in nb.prange(nbands):
        b = _spread(j, nbands)
        r0 = b * BAND
        r1 = min(height, r0 + BAND)
        for v in range(r0, r1):
            d1 = (v - cy) / fy
            for u in range(width):
                depth[v, u] = math.inf
                hit[v, u] = NO_HIT
            for k in range(obstacles.shape[0]):
                if not obstacles[k, OB_BOX + 2] <= v <= obstacles[k, OB_BOX + 3]:
                    continue
                u0, u1 = int(obstacles[k, OB_BOX]), int(obstacles[k, OB_BOX + 1])
                if int(obstacles[k, OB_KIND]) == KIND_PLANE:
                    # t = -o_z / (R_z . d), the row's constants out of the pixel loop
                    o2 = obstacles[k, OB_O + 2]
                    r6, r7, r8 = (obstacles[k, OB_R + 6], obstacles[k, OB_R + 7],
                                  obstacles[k, OB_R + 8])
                    row = r7 * d1 + r8
                    for u in range(u0, u1 + 1):
                        den = r6 * ((u - cx) / fx) + row
                        if den != 0.0:
                            t = -o2 / den
                            if near <= t <= far and t < depth[v, u]:
                                depth[v, u] = t
                                hit[v, u] = -2 - k
                    continue
                for u in range(u0, u1 + 1):
                    t = _obstacle(obstacles, k, (u - cx) / fx, d1, 1.0, near)
                    if t < depth[v, u] and t <= far:
                        depth[v, u] = t
                        hit[v, u] = -2 - k
        for m in range(start[b], start[b + 1]):
            f = ids[m]
            ia, ib, ic = tris[f, 0], tris[f, 1], tris[f, 2]
            a0, a1, a2 = verts[ia, 0], verts[ia, 1], verts[ia, 2]
            b0, b1, b2 = verts[ib, 0], verts[ib, 1], verts[ib, 2]
            c0, c1, c2 = verts[ic, 0], verts[ic, 1], verts[ic, 2]
            for v in range(max(r0, box[f, 2]), min(r1 - 1, box[f, 3]) + 1):
                d1 = (v - cy) / fy
                for u in range(box[f, 0], box[f, 1] + 1):
                    d0 = (u - cx) / fx
                    t, beta, gamma = _triangle_t(d0, d1, 1.0, a0, a1, a2, b0, b1, b2,
                                                 c0, c1, c2)
                    if near <= t <= far and t < depth[v, u]:
                        depth[v, u] = t
                        hit[v, u] = f
                        bary[v, u, 0] = beta
                        bary[v, u, 1] = gamma


@kernel()
def vertex_normals(verts, tris, n_cloth_tris, out):
    """Area-weighted unit normals (n, 3) of the vertices of the first ``n_cloth_tris``
    triangles (the cloth), in ``out``; others stay zero."""
    out[:] = 0.0
    for f in range(n_cloth_tris):
        ia, ib, ic = tris[f, 0], tris[f, 1], tris[f, 2]
        e10, e11, e12 = (verts[ib, 0] - verts[ia, 0], verts[ib, 1] - verts[ia, 1],
                         verts[ib, 2] - verts[ia, 2])
        e20, e21, e22 = (verts[ic, 0] - verts[ia, 0], verts[ic, 1] - verts[ia, 1],
                         verts[ic, 2] - verts[ia, 2])
        c0 = e11 * e22 - e12 * e21
        c1 = e12 * e20 - e10 * e22
        c2 = e10 * e21 - e11 * e20
        for i in (ia, ib, ic):
            out[i, 0] += c0
            out[i, 1] += c1
            out[i, 2] += c2
    for i in range(out.shape[0]):
        s = math.sqrt(out[i, 0] ** 2 + out[i, 1] ** 2 + out[i, 2] ** 2)
        if s > 0.0:
            out[i, 0] /= s
            out[i, 1] /= s
            out[i, 2] /= s


@kernel(parallel=True)
def shade(verts, tris, n_cloth_tris, vnormals, colors, ob_gray, tri_gray, fx, fy, cx, cy,
          obstacles, depth, hit, bary, background, ambient, rgb):
    """The colour image (h, w, 3) uint8 into ``rgb``: the cloth's per-vertex ``colors``
    (n, 3) in [0, 1] interpolated at the hit, obstacles ``ob_gray[k]`` (analytic row k)
    or ``tri_gray[f]`` (a mesh obstacle's triangle f), lit by a light at the camera on
    both sides of every surface: ``c (ambient + (1 - ambient) |n . d| / |d|)``; nothing
    hit: ``background`` (3) in [0, 1]."""
    height, width = hit.shape
    for j in nb.prange(height):
        v = _spread(j, height)
        d1 = (v - cy) / fy
        for u in range(width):
            code = hit[v, u]
            if code == NO_HIT:
                for c in range(3):
                    rgb[v, u, c] = np.uint8(255.0 * background[c] + 0.5)
                continue
            d0 = (u - cx) / fx
            r, g, b = 0.0, 0.0, 0.0
            n0, n1, n2 = 0.0, 0.0, 1.0
            if code <= -2:
                k = -2 - code
                r = g = b = ob_gray[k]
                n0, n1, n2 = _obstacle_normal(obstacles, k, depth[v, u], d0, d1, 1.0)
            else:
                ia, ib, ic = tris[code, 0], tris[code, 1], tris[code, 2]
                if code < n_cloth_tris:
                    be, ga = bary[v, u, 0], bary[v, u, 1]
                    al = 1.0 - be - ga
                    r = al * colors[ia, 0] + be * colors[ib, 0] + ga * colors[ic, 0]
                    g = al * colors[ia, 1] + be * colors[ib, 1] + ga * colors[ic, 1]
                    b = al * colors[ia, 2] + be * colors[ib, 2] + ga * colors[ic, 2]
                    n0 = al * vnormals[ia, 0] + be * vnormals[ib, 0] + ga * vnormals[ic, 0]
                    n1 = al * vnormals[ia, 1] + be * vnormals[ib, 1] + ga * vnormals[ic, 1]
                    n2 = al * vnormals[ia, 2] + be * vnormals[ib, 2] + ga * vnormals[ic, 2]
                else:
                    r = g = b = tri_gray[code]
                    e10 = verts[ib, 0] - verts[ia, 0]
                    e11 = verts[ib, 1] - verts[ia, 1]
                    e12 = verts[ib, 2] - verts[ia, 2]
                    e20 = verts[ic, 0] - verts[ia, 0]
                    e21 = verts[ic, 1] - verts[ia, 1]
                    e22 = verts[ic, 2] - verts[ia, 2]
                    n0 = e11 * e22 - e12 * e21
                    n1 = e12 * e20 - e10 * e22
                    n2 = e10 * e21 - e11 * e20
            nn = math.sqrt(n0 * n0 + n1 * n1 + n2 * n2)
            dd = math.sqrt(d0 * d0 + d1 * d1 + 1.0)
            lam = abs(n0 * d0 + n1 * d1 + n2) / (nn * dd) if nn > 0.0 else 1.0
            s = 255.0 * (ambient + (1.0 - ambient) * lam)
            rgb[v, u, 0] = np.uint8(min(255.0, max(0.0, r * s)) + 0.5)
            rgb[v, u, 1] = np.uint8(min(255.0, max(0.0, g * s)) + 0.5)
            rgb[v, u, 2] = np.uint8(min(255.0, max(0.0, b * s)) + 0.5)
