"""Air: the aerodynamic force on each triangle from its velocity relative to the wind.

Model (Wilson, Mitchell, Kaur, Dutt and Kautz 2014, "Simulating wind effects on cloth and
hair in Disney's Frozen", SIGGRAPH Talks; Keckeisen et al. 2004): each triangle t, of
current area ``A_t`` and unit normal ``n`` (either orientation: every formula below is even
in n), moving with the mean velocity ``v_t`` of its three corners through air of density
``rho`` blowing with the wind ``w``, has the relative velocity ``u = v_t - w``, its speed
``|u|`` and ``c = n . u / |u|`` (the cosine between the normal and the flow). It feels::

    f_drag = -1/2 rho C_D A_t |u|^2 c n              pressure drag, along the normal
    f_lift = -1/2 rho C_L A_t |u|^2 c (n - c u/|u|)  lift, across the flow

* The drag is the pressure on a flat plate: it pushes along the face normal against the
  face's motion through the air, with the magnitude ``1/2 rho C_D A |u|^2 |cos|`` of the
  plate's projected area. A sheet falling flat at speed s feels ``1/2 rho C_D A s^2``
  upwards, so its terminal velocity is ``v_t = sqrt(2 rho_s g / (rho C_D))`` (``rho_s``
  the mass per area); a sheet moving edge-on (``c = 0``) feels nothing.
* ``n - c u/|u|`` is the normal's part across the flow, of length ``sin``: the lift is
  perpendicular to the flow, in the plane of flow and normal, of magnitude ``1/2 rho C_L A
  |u|^2 |cos sin|`` (Wilson et al.'s lift), and for ``C_L > 0`` it points the same way as
  the drag's cross-flow part: a plate inclined to the wind is pushed across the wind
  towards the side it deflects the air away from (a kite rises), and downwind by the drag.
  It is zero for flow along the normal or along the plate.
* Each corner of t takes a third of ``f_drag + f_lift``; both vanish smoothly at ``u = 0``
  (they are quadratic in u), and a degenerate triangle (``A_t = 0``) feels nothing.

The force is not conservative and is not an energy term (``core/terms``): it depends on
the velocities. In the explicit update (``core/update.py``) it is part of the
applied force ``Control.f_applied``, so its work is counted as external work
(``State.acc``): drag in still air removes energy, wind puts it in. Its velocity
derivative is at most ``rho C |u| A_t`` per triangle (``rho (C_D + C_L) |u| / rho_s`` per
unit mass: 1.225 x 1.2 x 20 m/s / 0.1 kg/m^2 ~ 300 1/s at 20 m/s), so the explicit drag
is stable below ``dt ~ 2 / 300 s``, far above the elastic step: air never limits dt.

Coefficients: a flat square plate normal to the flow has ``C_D = 1.17`` (Hoerner 1965,
"Fluid-Dynamic Drag", ch. 3; 1.17-1.18 in most tables), the default here. The normal
pressure of that plate already has the cross-flow part of an inclined plate's force (its
"lift"); ``C_L`` adds circulation lift on top and defaults to 0 (Wilson et al. tune it per
shot). Air density at sea level and 15 C: 1.225 kg/m^3 (ISO 2533 standard atmosphere).

Layout: ``Control.air`` (:data:`AIR_WIDTH`,) = (on, 1/2 rho C_D, 1/2 rho C_L, w_x, w_y,
w_z); each step, before the update, :func:`air_faces` writes each face's force to
``Control.air_face`` (m,3) and :func:`air_gather` each vertex's ``f_applied = f_external
+ f_air`` (a third of its faces'): one evaluation per face. With air off
``Control.f_applied`` is ``Control.f_external`` and no step computes anything here. This
module imports no ROS package.
"""
from __future__ import annotations

from dataclasses import dataclass
import math

import numba as nb
import numpy as np

from .compiled import kernel
from .material import finite_non_negative

__all__ = ['Air', 'AIR_WIDTH', 'air_row', 'air_faces', 'air_gather', 'air_pass', 'air_forces',
           'face_air_force', 'drag_blocks']

#: columns of ``Control.air``
AIR_WIDTH = 6


@dataclass(frozen=True)
class Air:
    """Still or moving air around the cloth (module docstring).

    ``density`` [kg/m^3] (default 1.225, sea level), ``drag`` C_D (default 1.17, a flat
    plate normal to the flow) and ``lift`` C_L (default 0) [-], all finite and
    non-negative; ``ValueError`` names a bad one. The wind is set apart, on the simulator
    (``sim.wind``), since it changes while the air stays.
    """

    density: float = 1.225
    drag: float = 1.17
    lift: float = 0.0

    def __post_init__(self):
        for name in ('density', 'drag', 'lift'):
            object.__setattr__(self, name,
                               finite_non_negative(getattr(self, name), 'air.' + name))


def air_row(air, wind) -> np.ndarray:
    """``Control.air`` for ``air`` (an :class:`Air` or None: off) and the wind (3,) [m/s]."""
    row = np.zeros(AIR_WIDTH)
    if air is not None:
        row[0] = 1.0
        row[1] = 0.5 * air.density * air.drag
        row[2] = 0.5 * air.density * air.lift
    row[3:6] = wind
    return row


@kernel(inline='always')
def face_air_force(x, v, a, b, c, air):
    """``f_drag + f_lift`` [N] (module docstring) of the triangle with corners a, b, c."""
    e10 = x[b, 0] - x[a, 0]
    e11 = x[b, 1] - x[a, 1]
    e12 = x[b, 2] - x[a, 2]
    e20 = x[c, 0] - x[a, 0]
    e21 = x[c, 1] - x[a, 1]
    e22 = x[c, 2] - x[a, 2]
    n0 = e11 * e22 - e12 * e21          # 2 A n
    n1 = e12 * e20 - e10 * e22
    n2 = e10 * e21 - e11 * e20
    nn = math.sqrt(n0 * n0 + n1 * n1 + n2 * n2)
    third = 1.0 / 3.0
    u0 = (v[a, 0] + v[b, 0] + v[c, 0]) * third - air[3]
    u1 = (v[a, 1] + v[b, 1] + v[c, 1]) * third - air[4]
    u2 = (v[a, 2] + v[b, 2] + v[c, 2]) * third - air[5]
    uu = u0 * u0 + u1 * u1 + u2 * u2
    if nn == 0.0 or uu == 0.0:
        return 0.0, 0.0, 0.0
    area = 0.5 * nn
    n0 /= nn
    n1 /= nn
    n2 /= nn
    s = math.sqrt(uu)
    un = n0 * u0 + n1 * u1 + n2 * u2        # |u| c
    # -1/2 rho C A |u|^2 c = -k A |u| (n . u)
    kd = -air[1] * area * s * un
    kl = -air[2] * area * s * un
    cs = un / uu                            # c / |u|
    return (kd * n0 + kl * (n0 - cs * u0), kd * n1 + kl * (n1 - cs * u1),
            kd * n2 + kl * (n2 - cs * u2))


@kernel(inline='always')
def air_faces(t0, t1, x, v, corners, control):
    """The air force of faces t0..t1-1 (:func:`face_air_force`) into
    ``Control.air_face``."""
    air = control.air
    out = control.air_face
    for t in range(t0, t1):
        f0, f1, f2 = face_air_force(x, v, corners[t, 0], corners[t, 1], corners[t, 2], air)
        out[t, 0] = f0
        out[t, 1] = f1
        out[t, 2] = f2


@kernel(inline='always')
def air_gather(i0, i1, vf_ptr, vf_face, control):
    """``f_applied = f_external + f_air`` for vertices i0..i1-1: a third of the force of
    each incident face (``Control.air_face``)."""
    fe = control.f_external
    fa = control.f_applied
    af = control.air_face
    third = 1.0 / 3.0
    for i in range(i0, i1):
        s0 = 0.0
        s1 = 0.0
        s2 = 0.0
        for q in range(vf_ptr[i], vf_ptr[i + 1]):
            t = vf_face[q]
            s0 += af[t, 0]
            s1 += af[t, 1]
            s2 += af[t, 2]
        fa[i, 0] = fe[i, 0] + third * s0
        fa[i, 1] = fe[i, 1] + third * s1
        fa[i, 2] = fe[i, 2] + third * s2


@kernel(parallel=True)
def air_pass(x, v, corners, vf_ptr, vf_face, control, nchunks):
    """The air force of every face, then every vertex's ``f_applied``, each in
    ``nchunks`` parallel chunks (one call per step, before the update; a no-op with air
    off)."""
    if control.air[0] == 0.0:
        return
    m = corners.shape[0]
    fsize = (m + nchunks - 1) // nchunks
    for c in nb.prange(nchunks):
        air_faces(nb.int64(c * fsize), nb.int64(min(m, (c + 1) * fsize)), x, v, corners,
                  control)
    n = x.shape[0]
    size = (n + nchunks - 1) // nchunks
    for c in nb.prange(nchunks):
        air_gather(nb.int64(c * size), nb.int64(min(n, (c + 1) * size)), vf_ptr, vf_face,
                   control)


def air_forces(model, x: np.ndarray, v: np.ndarray, air, wind) -> np.ndarray:
    """The air force on every vertex (n,3) [N] at positions x and velocities v, in plain
    numpy (the reference for the compiled pass: ``test/test_air.py``)."""
    row = air_row(air, np.asarray(wind, dtype=np.float64))
    f = model.faces.corners
    n2 = np.cross(x[f[:, 1]] - x[f[:, 0]], x[f[:, 2]] - x[f[:, 0]])
    nn = np.linalg.norm(n2, axis=1)
    u = v[f].mean(axis=1) - row[3:6]
    s = np.linalg.norm(u, axis=1)
    ok = (nn > 0) & (s > 0)
    out = np.zeros_like(x)
    if not ok.any():
        return out
    nrm = n2[ok] / nn[ok, None]
    area = 0.5 * nn[ok]
    uo, so = u[ok], s[ok]
    c = np.einsum('ij,ij->i', nrm, uo) / so
    q = 0.5 * area * so ** 2 * c
    ff = (-(2 * row[1]) * q)[:, None] * nrm - ((2 * row[2]) * q)[:, None] * (
        nrm - (c / so)[:, None] * uo)
    for k in range(3):
        np.add.at(out, f[ok, k], ff / 3.0)
    return out


def drag_blocks(model, x: np.ndarray, v: np.ndarray, row: np.ndarray) -> np.ndarray:
    """Per-vertex blocks (n,3,3) [N s/m] of minus the drag's velocity derivative, for the
    implicit solver (``solvers/implicit.py``), at positions x and velocities v with
    ``Control.air`` row ``row``.

    The drag of a face, ``f = -k A |u| (n . u) n`` (k = 1/2 rho C_D), has ``df/du = -k A
    (|u| n n^T + (n . u) n u^T / |u|)``. Its symmetric positive semi-definite stand-in
    ``D_t = k A (|u| + |n . u|) n n^T`` is exact for flow along the normal (``2 k A |u| n
    n^T``) and across it (``k A |u| n n^T``). A corner takes a third of the force, and the
    face's velocity is the mean of its corners', so row-sum lumping gives vertex i
    ``D_i = sum over its faces of D_t / 3`` (exact for a sheet moving as a whole). The lift
    (C_L) is left explicit.
    """
    f = model.faces.corners
    out = np.zeros((len(x), 3, 3))
    if row[0] == 0.0 or row[1] == 0.0:
        return out
    n2 = np.cross(x[f[:, 1]] - x[f[:, 0]], x[f[:, 2]] - x[f[:, 0]])
    nn = np.linalg.norm(n2, axis=1)
    ok = nn > 0
    u = v[f].mean(axis=1) - row[3:6]
    s = np.linalg.norm(u, axis=1)
    nrm = np.zeros_like(n2)
    nrm[ok] = n2[ok] / nn[ok, None]
    un = np.abs(np.einsum('ij,ij->i', nrm, u))
    w = row[1] * 0.5 * nn * (s + un) / 3.0
    blk = w[:, None, None] * np.einsum('ti,tj->tij', nrm, nrm)
    for k in range(3):
        np.add.at(out, f[:, k], blk)
    return out
