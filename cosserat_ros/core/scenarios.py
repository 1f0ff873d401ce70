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

import dataclasses
import math
from typing import Dict, Optional

import numpy as np

from .compiled import kernel
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
                     seed: int = 2, discretisation: str = 'variational',
                     dt_factor: float = 0.9, solver: str = 'explicit') -> Dict[str, float]:
    """Static centre deflection of a square plate (side a = 1 m) under its own weight,
    by dynamic relaxation at critical damping of the fundamental mode: explicit at
    ``dt_factor`` of the stable step, or (``solver='implicit'``) backward Euler at a
    twentieth of the fundamental period, solved to 1e-9 edge lengths."""
    a = 1.0
    side = a * n / (n - 1) if support == 'clamped' else a
    mesh = grid_mesh(n, n, width=side, height=side, pattern=pattern, seed=seed)
    omega1 = 2 * math.pi ** 2 / a ** 2 * math.sqrt(PLATE_D / PLATE_MU)
    sim = ClothSimulator(mesh, plate_material(damping=2 * omega1 * PLATE_MU), dt=1e-5,
                         discretisation=discretisation, check_dt=False, solver=solver)
    if solver == 'implicit':
        sim.dt = 2 * math.pi / omega1 / 20.0
        sim.solver_tolerance = 1e-9
        sim.solver_iterations = 50
    else:
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


# ---------------------------------------------------------------- ASTM D1388 cantilever
#: ASTM D1388 option A: the strip is pushed over the ledge until the line from the ledge
#: edge to its tip falls this far below the horizontal
D1388_ANGLE = math.radians(41.5)
#: the standard's specimen width [m]
D1388_WIDTH = 0.025


@kernel()
def _elastica(lam, k0, nsteps):
    """The heavy elastica theta'' = -lam (1 - s) cos(theta) on s in [0, 1] from
    theta(0) = 0, theta'(0) = k0 (RK4): returns (theta'(1), x(1), z(1)) of the unit strip
    (theta the slope below the horizontal, z down)."""
    h = 1.0 / nsteps
    th = 0.0
    k = k0
    x = 0.0
    z = 0.0
    for i in range(nsteps):
        s = i * h
        a1, b1 = k, -lam * (1.0 - s) * math.cos(th)
        a2, b2 = k + 0.5 * h * b1, -lam * (1.0 - s - 0.5 * h) * math.cos(th + 0.5 * h * a1)
        a3, b3 = k + 0.5 * h * b2, -lam * (1.0 - s - 0.5 * h) * math.cos(th + 0.5 * h * a2)
        a4, b4 = k + h * b3, -lam * (1.0 - s - h) * math.cos(th + h * a3)
        # x' = cos(theta), z' = sin(theta): Simpson with the stage slopes
        t2 = th + 0.5 * h * (a1 + a2) * 0.5
        t4 = th + h * (a1 + 2 * a2 + 2 * a3 + a4) / 6.0
        x += h / 6.0 * (math.cos(th) + 4.0 * math.cos(t2) + math.cos(t4))
        z += h / 6.0 * (math.sin(th) + 4.0 * math.sin(t2) + math.sin(t4))
        th = t4
        k += h * (b1 + 2 * b2 + 2 * b3 + b4) / 6.0
    return k, x, z


def elastica_chord_angle(lam: float, nsteps: int = 2000) -> float:
    """The angle [rad] below the horizontal of the chord from the clamp to the tip of a
    cantilever of length L, rigidity G per unit width, under its weight w per unit area
    (``lam = w L^3 / G``), at large deflection: the heavy elastica ``G theta'' = -w (L -
    s) cos theta``, theta(0) = 0, theta'(L) = 0, shot on theta'(0) in [0, lam / 2] (the
    small-deflection value) by bisection."""
    lo, hi = 0.0, 0.5 * lam
    for _ in range(100):
        mid = 0.5 * (lo + hi)
        if _elastica(lam, mid, nsteps)[0] < 0.0:
            lo = mid
        else:
            hi = mid
    _, x, z = _elastica(lam, 0.5 * (lo + hi), nsteps)
    return math.atan2(z, x)


def elastica_load(angle: float = D1388_ANGLE) -> float:
    """``lam = w L^3 / G`` at which the heavy cantilever's chord falls ``angle`` (the
    inverse of :func:`elastica_chord_angle`, by bisection: the angle grows with lam).
    Peirce's formula ``G = w L^3 cos(angle / 2) / (8 tan(angle))`` is the small-deflection
    approximation, and the standard's ``G = w (L / 2)^3`` uses lam = 8."""
    lo, hi = 1e-6, 1e4
    for _ in range(80):
        mid = math.sqrt(lo * hi)
        if elastica_chord_angle(mid) < angle:
            lo = mid
        else:
            hi = mid
    return math.sqrt(lo * hi)


def bending_length_test(material: Material, n_along: int = 40,
                        width: float = D1388_WIDTH, pattern: str = 'regular',
                        g: float = 9.81) -> Dict[str, float]:
    """ASTM D1388 option A on the simulator: a strip of ``width`` (the standard's 25 mm)
    overhanging a ledge, under its own weight, run to rest; from the angle of its chord,
    the flexural rigidity it shows.

    The part of the strip on the platform is held flat by its weight, so the ledge is a
    clamp: two columns of vertices pinned, the clamp their mid-line (as
    :func:`cantilever`), ``n_along`` segments over the overhang. The overhang L is the one
    at which the exact elastica of the material's rigidity ``G = 6 xi`` falls 41.5 degrees
    (``L = (lam* G / w)^(1/3)``, ``lam* = elastica_load()``), i.e. where the standard stops
    pushing. Measured: the chord angle ``beta`` from the ledge edge to the tip (the free
    edge's mean position). Recovered: ``G_exact = w L^3 / lam(beta)`` (the elastica
    inverted at the measured angle); the standard's reading ``G_d1388 = w c^3`` with the
    bending length ``c = L* / 2``, ``L*`` the overhang at which this strip falls 41.5
    degrees (``L* = L (lam* / lam(beta))^(1/3)``, since the angle depends on ``w L^3 / G``
    only), so ``G_d1388 / G_exact = lam* / 8``: the error of the standard's formula."""
    G = material.bending_rigidity
    w = material.density * g
    lam_star = elastica_load(D1388_ANGLE)
    L = (lam_star * G / w) ** (1.0 / 3.0)
    h = L / (n_along - 0.5)
    n_across = max(2, int(round(width / h)))
    total = n_along * h
    mesh = grid_mesh(n_along, n_across, width=total, height=width, pattern=pattern, seed=2)
    X = mesh.vertices
    omega1 = 3.516 / L ** 2 * math.sqrt(G / material.density)
    mat = dataclasses.replace(material, damping=2.0 * omega1 * material.density)
    sim = ClothSimulator(mesh, mat, dt=1e-6, check_dt=False)
    sim.dt = 0.9 * sim.critical_dt()
    clamp_x = -0.5 * total + 0.5 * h
    sim.pin(X[:, 0] <= -0.5 * total + 1.01 * h)
    sim.gravity = (0.0, 0.0, -g)
    tip = X[:, 0] >= 0.5 * total - 1e-9

    def chord():
        p = sim.positions[tip].mean(axis=0)
        return math.atan2(-p[2], p[0] - clamp_x)

    beta, t = chord(), 0.0
    while t < 60.0 / omega1:
        relax(sim, 2.0 / omega1)
        t += 2.0 / omega1
        b = chord()
        if abs(b - beta) < 1e-5 and t > 8.0 / omega1:
            beta = b
            break
        beta = b
    lam = elastica_load(beta)
    g_exact = w * L ** 3 / lam
    return {'overhang': L, 'beta': beta, 'lam': lam, 'G': G, 'G_exact': g_exact,
            'error': g_exact / G - 1.0, 'G_d1388': g_exact * lam_star / 8.0,
            'bending_length': 0.5 * L * (lam_star / lam) ** (1.0 / 3.0),
            'lam_star': lam_star, 'n_across': n_across, 'dt': sim.dt, 'time': t}


# ---------------------------------------------------------------- Cusick drape
#: the Cusick drape tester (BS 5058 / ISO 9073-9): a 30 cm specimen on an 18 cm support
CUSICK_SPECIMEN_RADIUS = 0.15
CUSICK_SUPPORT_RADIUS = 0.09


@kernel()
def _shadow_fill(p, faces, x0, y0, pixel, mask):
    """Set mask[j, i] where the pixel centre (x0 + (i + 1/2) pixel, y0 + (j + 1/2) pixel)
    lies in a triangle (barycentric l1, l2 >= 0, l1 + l2 <= 1; degenerate triangles
    skipped), each triangle over the pixels of its bounding box."""
    ny, nx = mask.shape
    for t in range(faces.shape[0]):
        ax, ay = p[faces[t, 0], 0], p[faces[t, 0], 1]
        bx, by = p[faces[t, 1], 0], p[faces[t, 1], 1]
        cx, cy = p[faces[t, 2], 0], p[faces[t, 2], 1]
        det = (bx - ax) * (cy - ay) - (cx - ax) * (by - ay)
        if det == 0.0:
            continue
        i0 = max(int(math.floor((min(ax, bx, cx) - x0) / pixel)), 0)
        j0 = max(int(math.floor((min(ay, by, cy) - y0) / pixel)), 0)
        i1 = min(int(math.ceil((max(ax, bx, cx) - x0) / pixel)), nx)
        j1 = min(int(math.ceil((max(ay, by, cy) - y0) / pixel)), ny)
        for j in range(j0, j1):
            Y = y0 + (j + 0.5) * pixel
            for i in range(i0, i1):
                X = x0 + (i + 0.5) * pixel
                l1 = ((bx - X) * (cy - Y) - (cx - X) * (by - Y)) / det
                l2 = ((cx - X) * (ay - Y) - (ax - X) * (cy - Y)) / det
                if l1 >= 0.0 and l2 >= 0.0 and l1 + l2 <= 1.0:
                    mask[j, i] = True


def shadow(points2: np.ndarray, faces: np.ndarray, pixel: float = 1e-3):
    """The area [m^2] of the union of the triangles (points2 (n,2) [m], faces (m,3)) seen
    from above, on a raster of ``pixel`` [m] (a pixel counts when its centre is in a
    triangle), and the raster itself (mask, x0, y0) for the outline."""
    lo = points2.min(axis=0) - pixel
    hi = points2.max(axis=0) + pixel
    nx, ny = (np.ceil((hi - lo) / pixel)).astype(int)
    mask = np.zeros((ny, nx), dtype=bool)
    _shadow_fill(np.ascontiguousarray(points2, dtype=np.float64),
                 np.ascontiguousarray(faces, dtype=np.int64), lo[0], lo[1], pixel, mask)
    return float(mask.sum()) * pixel ** 2, (mask, lo[0], lo[1], pixel)


def count_folds(raster, bins: int = 360, smooth_deg: float = 10.0,
                prominence: float = 0.2, relief: float = 0.01) -> int:
    """The number of folds (nodes) of a drape shadow: the maxima of its outline's radius
    r(angle) about the centre (the largest shadow radius in each of ``bins`` sectors,
    circularly smoothed over ``smooth_deg``) that rise above both neighbouring minima by
    ``prominence`` of the outline's total range; none if that range is below twice
    ``relief`` of the mean radius (a round shadow, a pixel's noise)."""
    mask, x0, y0, pixel = raster
    j, i = np.nonzero(mask)
    x = x0 + (i + 0.5) * pixel
    y = y0 + (j + 0.5) * pixel
    ang = np.floor((np.arctan2(y, x) + np.pi) / (2 * np.pi) * bins).astype(int) % bins
    r = np.zeros(bins)
    np.maximum.at(r, ang, np.hypot(x, y))
    k = max(1, int(round(smooth_deg / 360.0 * bins)))
    r = np.convolve(np.concatenate([r[-k:], r, r[:k]]), np.ones(2 * k + 1) / (2 * k + 1),
                    mode='same')[k:-k]
    span = r.max() - r.min()
    if span <= 0 or span < 2.0 * relief * r.mean():
        return 0
    # walk the circle from the global minimum: a fold is a rise and fall of > prominence
    start = int(np.argmin(r))
    seq = np.roll(r, -start)
    folds, low, high, rising = 0, seq[0], seq[0], True
    for val in seq[1:]:
        if rising:
            high = max(high, val)
            if high - val > prominence * span and high - low > prominence * span:
                folds += 1
                rising, low = False, val
        else:
            low = min(low, val)
            if val - low > prominence * span:
                rising, high = True, val
    return folds


def drape_test(material: Material, rings: int = 25, duration: float = 3.0,
               seed: int = 0, thickness: float = 1e-3) -> Dict[str, float]:
    """The Cusick drape test on the simulator: a disc of radius 0.15 m (:func:`..mesh.
    disc_mesh`, ``rings`` rings) laid centred on a support disc of radius 0.09 m (a
    cylinder obstacle, contact thickness ``thickness``), released under gravity, run
    ``duration`` seconds with damping near the skirt's pendulum rate and measured from
    above: the drape coefficient ``DC = (A_shadow - A_support) / (A_specimen -
    A_support)`` (1: stays flat, 0: hangs straight down) and the number of folds
    (:func:`count_folds`). The specimen starts flat with 0.1 mm of random height noise,
    which breaks the ring mesh's six-fold symmetry as a real specimen's irregularities
    do."""
    from .mesh import disc_mesh
    mesh = disc_mesh(CUSICK_SPECIMEN_RADIUS, rings)
    rate = math.sqrt(9.81 / (CUSICK_SPECIMEN_RADIUS - CUSICK_SUPPORT_RADIUS))
    mat = dataclasses.replace(material, damping=rate * material.density)
    sim = ClothSimulator(mesh, mat, dt=1e-6, check_dt=False)
    sim.dt = 0.9 * sim.critical_dt()
    sim.contact_thickness = thickness
    sim.add_obstacle('cylinder', center=(0.0, 0.0, -0.05), radius=CUSICK_SUPPORT_RADIUS,
                     half_length=0.05, friction=0.5, name='support')
    x = mesh.vertices.copy()
    x[:, 2] = thickness + 1e-4 * np.random.default_rng(seed).random(len(x))
    sim.set_positions(x)
    sim.gravity = (0.0, 0.0, -9.81)
    relax(sim, duration)
    p = sim.positions
    area, raster = shadow(p[:, :2], mesh.faces)
    a_d = math.pi * CUSICK_SUPPORT_RADIUS ** 2
    a_s = math.pi * CUSICK_SPECIMEN_RADIUS ** 2
    kinetic = sim.energy()['kinetic']
    return {'dc': (area - a_d) / (a_s - a_d), 'folds': count_folds(raster),
            'shadow_area': area, 'kinetic': kinetic, 'dt': sim.dt,
            'lowest': float(p[:, 2].min()), 'sim': sim}
