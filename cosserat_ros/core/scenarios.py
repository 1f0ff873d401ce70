"""Analytic validation systems shared by the tests and ``make validate``.

Each function builds a simulator, runs it, and returns the measured quantity beside its
closed-form reference. Plate theory with the model's constants (``material.py``): bending
stiffness D = 6 xi, Poisson ratio nu = 1/3, uniform load q = mu g.

* Kirchhoff square plate of side a, centre deflection under q: simply supported
  ``0.0040624 q a^4 / D``; clamped ``0.0012653 q a^4 / D`` (Timoshenko & Woinowsky-Krieger,
  Tables 8 and 35). Fundamental frequency of the simply supported plate
  ``omega_1 = 2 pi^2 / a^2 sqrt(D / mu)``.
* Cantilever strip of length L under its own weight: tip ``q L^4 / (8 D_eff)`` with
  ``D (1 - nu^2) <= D_eff <= D`` (beam to cylindrical bending).

Supports: "simple" pins the boundary ring (positions only); "clamped" pins the two
outermost rings, whose mid-line is the clamped edge, so the mesh is made one half spacing
wider on each side (side ``a N / (N - 1)`` for N segments).
"""
from __future__ import annotations

import math
from typing import Dict, Optional

import numpy as np

from .mesh import grid_mesh
from .simulator import ClothSimulator, Material

SS_COEFF = 0.0040624
CLAMPED_COEFF = 0.0012653
NU = 1.0 / 3.0

#: Plate set-up: D = 1 N m, mu = 1 kg/m^2, a stiff membrane and a tiny load keep the
#: response linear (w / sqrt(D / (E h)) ~ 1e-5).
PLATE_D = 1.0
PLATE_MU = 1.0
PLATE_ZETA = 10.0
PLATE_G = 1e-3


def plate_material(damping: float = 0.0) -> Material:
    """The plate's material: D = 6 xi = 1 N m, mu = 1 kg/m^2, zeta = 10 N/m."""
    return Material(zeta=PLATE_ZETA, xi=PLATE_D / 6.0, phi=0.0, density=PLATE_MU,
                    damping=damping)


def _support_mask(mesh, support: str, n: int, side: float) -> np.ndarray:
    X = mesh.vertices
    if support == 'simple':
        return mesh.boundary_vertices.copy()
    if support == 'clamped':
        h = side / n
        edge = 0.5 * side - 1.01 * h
        return (np.abs(X[:, 0]) >= edge) | (np.abs(X[:, 1]) >= edge)
    raise ValueError(f'support must be "simple" or "clamped", got {support!r}')


def relax(sim: ClothSimulator, duration: float, chunk: int = 500) -> None:
    """Run ``duration`` seconds of (damped) dynamics in chunks."""
    steps = int(math.ceil(duration / sim.dt))
    while steps > 0:
        k = min(chunk, steps)
        sim.step(k)
        steps -= k


def plate_deflection(n: int, pattern: str = 'regular', support: str = 'simple',
                     seed: int = 2, divergence: str = 'variational',
                     dt_factor: float = 0.9) -> Dict[str, float]:
    """Static centre deflection of a square plate (side a = 1 m) under its own weight,
    by dynamic relaxation at critical damping of the fundamental mode."""
    a = 1.0
    side = a * n / (n - 1) if support == 'clamped' else a
    mesh = grid_mesh(n, n, width=side, height=side, pattern=pattern, seed=seed)
    omega1 = 2 * math.pi ** 2 / a ** 2 * math.sqrt(PLATE_D / PLATE_MU)
    sim = ClothSimulator(mesh, plate_material(damping=2 * omega1 * PLATE_MU), dt=1e-5,
                         divergence=divergence, check_dt=False)
    sim.dt = dt_factor * sim.critical_dt()
    sim.pin(_support_mask(mesh, support, n, side))
    sim.gravity = (0.0, 0.0, -PLATE_G)
    relax(sim, 14.0 / omega1)
    centre = int(np.argmin(np.linalg.norm(mesh.vertices[:, :2], axis=1)))
    w = -float(sim.positions[centre, 2])
    coeff = SS_COEFF if support == 'simple' else CLAMPED_COEFF
    ref = coeff * PLATE_MU * PLATE_G * a ** 4 / PLATE_D
    return {'n': n, 'w': w, 'reference': ref, 'error': w / ref - 1.0, 'dt': sim.dt,
            'steps': sim.step_count, 'residual_speed': float(np.abs(sim.velocities).max())}


def zero_crossings(t: np.ndarray, y: np.ndarray) -> np.ndarray:
    """Times where y changes sign, by linear interpolation."""
    s = np.flatnonzero(np.sign(y[:-1]) * np.sign(y[1:]) < 0)
    return t[s] - y[s] * (t[s + 1] - t[s]) / (y[s + 1] - y[s])


def plate_frequency(n: int, pattern: str = 'regular', seed: int = 2,
                    amplitude: float = 1e-6) -> Dict[str, float]:
    """Fundamental angular frequency of the simply supported plate from free vibration:
    released from the first mode shape, undamped; period from zero crossings."""
    mesh = grid_mesh(n, n, pattern=pattern, seed=seed)
    sim = ClothSimulator(mesh, plate_material(), dt=1e-5, check_dt=False)
    sim.dt = 0.9 * sim.critical_dt()
    sim.pin(mesh.boundary_vertices)
    X = mesh.vertices
    x = X.copy()
    x[:, 2] = amplitude * np.sin(np.pi * (X[:, 0] + 0.5)) * np.sin(np.pi * (X[:, 1] + 0.5))
    sim.set_positions(x)
    omega_ref = 2 * math.pi ** 2 * math.sqrt(PLATE_D / PLATE_MU)
    period = 2 * math.pi / omega_ref
    centre = int(np.argmin(np.linalg.norm(X[:, :2], axis=1)))
    every = max(1, int(period / 200 / sim.dt))
    t, w = [0.0], [x[centre, 2]]
    while sim.time < 2.6 * period:
        sim.step(every)
        t.append(sim.time)
        w.append(sim.positions[centre, 2])
    zc = zero_crossings(np.array(t), np.array(w))
    measured_period = 2.0 * float(np.mean(np.diff(zc)))
    omega = 2 * math.pi / measured_period
    return {'n': n, 'omega': omega, 'reference': omega_ref, 'error': omega / omega_ref - 1,
            'dt': sim.dt}


def cantilever(n_along: int = 40, length: float = 1.0, width: float = 0.25,
               pattern: str = 'regular', seed: int = 2) -> Dict[str, float]:
    """Tip sag of a strip clamped at x = -L/2 (two columns pinned; the clamp is their
    mid-line) and free on its other three edges, under its own weight."""
    h = length / (n_along - 0.5)          # spacing: clamp mid-line h/2 in from the end
    n_across = max(2, int(round(width / h)))
    total = n_along * h
    mesh = grid_mesh(n_along, n_across, width=total, height=width, pattern=pattern,
                     seed=seed)
    X = mesh.vertices
    L = length
    omega1 = 3.516 / L ** 2 * math.sqrt(PLATE_D / PLATE_MU)
    sim = ClothSimulator(mesh, plate_material(damping=2 * omega1 * PLATE_MU), dt=1e-5,
                         check_dt=False)
    sim.dt = 0.9 * sim.critical_dt()
    sim.pin(X[:, 0] <= -0.5 * total + 1.01 * h)
    sim.gravity = (0.0, 0.0, -PLATE_G)
    relax(sim, 16.0 / omega1)
    tip = X[:, 0] >= 0.5 * total - 1e-9
    w = -float(sim.positions[tip, 2].mean())
    q = PLATE_MU * PLATE_G
    w_plate = q * L ** 4 / (8 * PLATE_D)
    w_beam = q * L ** 4 / (8 * PLATE_D * (1 - NU ** 2))
    return {'w': w, 'w_plate': w_plate, 'w_beam': w_beam,
            'd_eff_over_d': q * L ** 4 / (8 * w) / PLATE_D}


#: Cloth-like constants [SI]: 200 g/m^2, E h = 16 zeta / 3 ~ 270 N/m, D = 6 xi = 1.2e-4 N m.
CLOTH = Material(zeta=50.0, xi=2e-5, phi=1e-6, density=0.2, damping=0.1)


def hanging_cloth(n: int = 20, pattern: str = 'regular', duration: float = 4.0,
                  material: Optional[Material] = None, seed: int = 1) -> ClothSimulator:
    """A 1 m square pinned at the two corners of its top edge (y = +0.5), starting flat
    and horizontal, falling and swinging under gravity."""
    mesh = grid_mesh(n, n, pattern=pattern, seed=seed)
    sim = ClothSimulator(mesh, material or CLOTH, dt=1e-5, check_dt=False)
    sim.dt = min(2e-4, 0.9 * sim.critical_dt())
    sim.pin([n * (n + 1), n * (n + 1) + n])
    sim.gravity = (0.0, 0.0, -9.81)
    relax(sim, duration)
    return sim
