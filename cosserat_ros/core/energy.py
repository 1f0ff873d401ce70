"""The energy report: every term's energy and density, the kinetic and gravity energy.

One evaluation of the elastic fields at the current positions (the terms' own kernels,
energies only: face strains, strain averages, curvature changes, hourglass residuals)
gives

* per vertex [J/m^2] (the seed's Fig. 4): ``stretching`` (dual-area average of the
  incident triangles' ``W_m``), ``bending`` (``xi B(kap, kap)`` and the hourglass energy
  over ``A_i``), ``coupling`` (``phi B(epsbar, kap)``) and their ``total``;
* in total [J]: those three summed with the dual areas, ``kinetic`` (the leapfrog velocity
  carried to the positions' time, ``1/2 sum m |v + dt/2 a|^2``, with the internal force
  the caller computed at those positions: the solver's own), ``gravity``
  (``-sum m g . x``), and the running balance of :class:`.state.State`
  (``external_work``, ``dissipated``).

``total = kinetic + elastic + gravity``; an undamped, unforced run keeps it to O(dt^2).
"""
from __future__ import annotations

from typing import Dict, Tuple

import numba as nb
import numpy as np

from .compiled import kernel
from .material import bilinear
from .terms import bending, coupling, jet, membrane

__all__ = ['report', 'elastic_energy', 'ENERGY_KEYS']

#: the keys of the report's totals, in the order the node publishes them
ENERGY_KEYS = ('kinetic', 'stretching', 'bending', 'coupling', 'elastic', 'gravity',
               'external_work', 'dissipated', 'total')


@kernel(parallel=True)
def densities(face_energy, kap, epsbar, estab, vf_ptr, vf_face, dual_area, ainv, xi, phi, out):
    """Per-vertex energy densities [J/m^2] in out[:, 0:3] (out (n,4)): stretching
    (``sum_t area_t W_m / 3`` over the incident faces, over A_i), bending, coupling."""
    for i in nb.prange(out.shape[0]):
        s = 0.0
        for q in range(vf_ptr[i], vf_ptr[i + 1]):
            s += face_energy[vf_face[q]] / 3.0
        a = dual_area[i]
        out[i, 0] = s / a
        i11 = ainv[i, 0]
        i12 = ainv[i, 1]
        i22 = ainv[i, 2]
        out[i, 1] = xi * bilinear(i11, i12, i22, kap[i, 0], kap[i, 1], kap[i, 2],
                                  kap[i, 0], kap[i, 1], kap[i, 2]) + estab[i] / a
        out[i, 2] = phi * bilinear(i11, i12, i22, epsbar[i, 0], epsbar[i, 1], epsbar[i, 2],
                                   kap[i, 0], kap[i, 1], kap[i, 2])


@kernel()
def totals(dens, dual_area, force, f_applied, mass, damp, v, x, pinned, gravity, dt, out):
    """The sums of the report in one pass, from the densities ``dens`` (n,4) of
    :func:`densities` in its first three columns:

    * ``dens[:, 3]`` = their sum per vertex (the total density);
    * ``out[0:3]`` = sum_i A_i dens_i: the stretching, bending and coupling energy [J];
    * ``out[3]`` = kinetic energy 1/2 sum_i m_i |v_i + dt/2 a_i|^2 of the leapfrog velocity
      carried to the positions' time, with ``m_i a_i = f_i + f_applied_i + m_i g - c_i v_i``
      (the step's acceleration, ``update.py``); at a pinned or held vertex
      1/2 m_i |v_i|^2, its prescribed velocity (0 for a pin);
    * ``out[4]`` = -sum_i m_i g . x_i, the gravity potential [J].

    Serial, in vertex order: the sums are the same numbers on any thread count."""
    n = dens.shape[0]
    s0 = 0.0
    s1 = 0.0
    s2 = 0.0
    kin = 0.0
    pot = 0.0
    g0 = gravity[0]
    g1 = gravity[1]
    g2 = gravity[2]
    h = 0.5 * dt
    for i in range(n):
        a = dual_area[i]
        d0 = dens[i, 0]
        d1 = dens[i, 1]
        d2 = dens[i, 2]
        dens[i, 3] = d0 + d1 + d2
        s0 += a * d0
        s1 += a * d1
        s2 += a * d2
        m = mass[i]
        pot -= m * (x[i, 0] * g0 + x[i, 1] * g1 + x[i, 2] * g2)
        if not pinned[i]:
            c = damp[i]
            w0 = v[i, 0] + h * (force[i, 0] + f_applied[i, 0] + m * g0 - c * v[i, 0]) / m
            w1 = v[i, 1] + h * (force[i, 1] + f_applied[i, 1] + m * g1 - c * v[i, 1]) / m
            w2 = v[i, 2] + h * (force[i, 2] + f_applied[i, 2] + m * g2 - c * v[i, 2]) / m
            kin += m * (w0 * w0 + w1 * w1 + w2 * w2)
        else:           # a held vertex moves with its handle's velocity (a pin's is 0)
            kin += m * (v[i, 0] * v[i, 0] + v[i, 1] * v[i, 1] + v[i, 2] * v[i, 2])
    out[0] = s0
    out[1] = s1
    out[2] = s2
    out[3] = 0.5 * kin
    out[4] = pot


def elastic_fields(model, coeff, x: np.ndarray, scratch: np.ndarray):
    """The fields of the three elastic terms at x: (face energies (m,), kap (n,3),
    epsbar (n,3), estab (n,))."""
    f, vf, j = model.faces, model.vertex_faces, model.jets
    n, m = len(x), len(f.corners)
    face_energy = np.empty(m)
    membrane.face_energies(x, f.corners, f.dinv, f.area, coeff.zeta, np.empty((m, 3)),
                           face_energy)
    eb = np.zeros((n, 3))
    if coeff.phi != 0.0:
        coupling.strain_average(x, f.corners, f.dinv, vf.ptr, vf.face, vf.K, eb)
    kap = np.empty((n, 3))
    estab = np.empty(n)
    jet.vertex_energies(x, j, model.vertices, coeff.stab, coeff.xi, coeff.phi, eb, scratch,
                        kap, estab)
    return face_energy, kap, eb, estab


def elastic_energy(model, coeff, x: np.ndarray, scratch: np.ndarray) -> float:
    """E_m + E_b + E_c [J] at x (n,3): the sum of the terms' ``energy``, from the one
    evaluation of their fields the report makes (:func:`elastic_fields`: one vertex pass
    for the bending's and the coupling's curvature changes, the strain averages only with
    phi != 0), half the time of the terms' own three (the bench's square sheet at 80 x 80: 0.66
    against 1.33 ms; the implicit solver's line search takes ~5 a step)."""
    face_energy, kap, eb, estab = elastic_fields(model, coeff, x, scratch)
    return (float(face_energy.sum()) + bending.energy_from_fields(model, coeff, kap, estab)
            + (coupling.energy_from_fields(model, coeff, eb, kap) if coeff.phi != 0.0
               else 0.0))


def report(model, coeff, state, control, dt: float, scratch: np.ndarray,
           force: np.ndarray) -> Tuple[Dict[str, float], Dict[str, np.ndarray]]:
    """(energies [J], densities [J/m^2]) of ``state`` (module docstring), with the internal
    force ``force`` (n,3) [N] at its positions."""
    x = state.x
    face_energy, kap, eb, estab = elastic_fields(model, coeff, x, scratch)
    v = model.vertices
    vf = model.vertex_faces
    out = np.empty((len(x), 4))
    densities(face_energy, kap, eb, estab, vf.ptr, vf.face, v.dual_area, v.ainv, coeff.xi,
              coeff.phi, out)
    sums = np.empty(5)
    totals(out, v.dual_area, force, control.f_applied, coeff.mass, coeff.damp, state.v, x,
           control.pinned, control.gravity, dt, sums)
    stretching, bending, coupling_, kinetic, gravity = (float(e) for e in sums)
    elastic = stretching + bending + coupling_
    energy = {'kinetic': kinetic, 'stretching': stretching, 'bending': bending,
              'coupling': coupling_, 'elastic': elastic, 'gravity': gravity,
              'external_work': float(state.acc[0]), 'dissipated': float(state.acc[1]),
              'total': kinetic + elastic + gravity}
    dens = {'stretching': out[:, 0], 'bending': out[:, 1], 'coupling': out[:, 2],
            'total': out[:, 3]}
    return energy, dens
