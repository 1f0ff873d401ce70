"""Fabrics: the Cosserat constants from a fabric's datasheet quantities, and named presets.

From fabric quantities to zeta, xi, phi (:meth:`.material.Material.from_fabric`)
-------------------------------------------------------------------------------
A fabric test reports the areal density ``mu`` [kg/m^2], the tensile stiffness ``E h``
[N/m] (force per unit width over strain of a strip pulled in uniaxial stress), the Poisson
ratio ``nu`` and the flexural rigidity per unit width ``G`` [N m] (ASTM D1388, or KES-F
B: the moment per unit width over the curvature of a strip bent in one direction).

For a flat rest sheet the energy of Eq. 18-19 with ``Phi = C(zeta)``, ``Psi = C(xi)`` is
(:mod:`.material`)::

    zeta B(eps, eps) = lambda_2 / 2 tr(eps)^2 + mu_2 eps:eps,  lambda_2 = mu_2 = 2 zeta
    xi B(kap, kap)   = D / 2 [tr(kap)^2 - 2 (1 - nu) det kap],   D = 6 xi, nu = 1/3

* Tensile stiffness. In uniaxial stress (``N_22 = 0``) the membrane gives
  ``N_11 = E_2 eps_11`` with ``E_2 = 4 mu_2 (lambda_2 + mu_2) / (lambda_2 + 2 mu_2) =
  16 zeta / 3``, so ``zeta = 3 E h / 16``.
* Flexural rigidity. A strip bent about its width into a cylinder of curvature ``k``
  (``kap_11 = k``; ``kap_22 = 0``: a strip much wider than ``sqrt(R h)``, as every fabric
  strip is, cannot curl anticlastically without stretching, Searle's parameter ``b^2 / (R
  h) >> 1``) stores ``D k^2 / 2`` per unit area, a moment ``D k`` per unit width:
  ``G = D = 6 xi``, so ``xi = G / 6``. (A narrow beam would give ``D (1 - nu^2)``; the
  cantilever test of ``make validate`` measures which one the simulated strip shows.)
* Coupling. ``phi`` couples stretch and bending: a sheet whose two faces are alike (every
  woven or knitted fabric, to the accuracy of these tests) has none, by symmetry through
  the thickness, and none of the tests measures it: ``phi = 0``.
* Poisson ratio. Eq. 19 gives one constant per tensor, so the seed's law has ``nu = 1/3``
  whatever the constants: with ``E h`` and ``G`` matched, a fabric's own ``nu`` cannot be.
  What changes is the lateral contraction (1/3 instead of ``nu``) and the in-plane shear
  stiffness (``mu_2 = 3 E h / 8`` instead of ``E h / (2 (1 + nu))``: +12% for ``nu =
  0.5``, -25% for ``nu = 0``); :meth:`~.material.Material.from_fabric` warns when ``nu``
  is further than :data:`NU_TOLERANCE` from 1/3. (Woven fabrics shear far more easily
  than either: an isotropic sheet cannot have that.)

Presets (:data:`PRESETS`, :meth:`.material.Material.preset`)
-----------------------------------------------------------
Measured fabrics of the database of Wang, O'Brien and Ramamoorthi 2011 ("Data-driven
elastic models for cloth: modeling and measurement", ACM Trans. Graph. 30(4), 71), as
distributed with ARCSim 0.3.1 (``materials/<name>.json``; its README names the fabrics
and cites the paper). Each file holds ``density`` [kg/m^2], ``stretching`` rows ``[C11,
C12, C22, C33]`` [N/m] and ``bending`` rows for 0, 45 and 90 degrees, columns by
curvature [N m]. The conversions, from ARCSim's source (``src/dde.cpp``,
``src/physics.cpp``):

* ``mu`` = ``density``.
* ``E h = (E_1 + E_2) / 2`` from the first row (zero strain): ARCSim clamps every
  tabulated coefficient at 0 and doubles it (``evaluate_stretching_sample``), and takes
  the stress ``sigma_11 = k_0 G_11 + k_1 G_22``, ``sigma_22 = k_1 G_11 + k_2 G_22`` of
  the Green strain with energy ``a sigma:G / 2`` (``material_model``,
  ``stretching_energy``). A strip pulled along direction 1 in uniaxial stress
  (``sigma_22 = 0``: it contracts by ``G_22 = -C12 G_11 / C22``) has the tensile
  stiffness ``E_1 = 2 (C11 - C12^2 / C22)``, along direction 2 ``E_2 = 2 (C22 - C12^2 /
  C11)`` (C12 clamped at 0); the preset takes their mean. For the woven fabrics C12 is
  small against C11 and C22 (``E h`` within 1% of ``C11 + C22``), not for
  ``polyester`` (C12 = 54 N/m against C11 = 43) and ``fleece`` (106 against 152), whose
  ``E h`` is 40% and 30% below ``C11 + C22``.
* ``G = (b_0 + b_90) / 16`` (first column: lowest curvature; mean of 0 and 90 degrees,
  divided by 8): ARCSim's hinge energy is ``b l^2 theta^2 / (8 a)`` per edge (``l`` its
  length, ``a`` the two faces' area, ``theta`` the dihedral angle: ``bending_coeff``,
  ``bending_energy``). Bending a mesh of equilateral triangles of edge ``l`` into a
  cylinder of curvature ``k``: an edge whose normal in the plane makes the angle ``p``
  with the bending direction has ``theta = k (l / sqrt 3) cos^2 p``; with ``2 sqrt 3 /
  l^2`` edges per unit area, ``a = sqrt 3 l^2 / 2`` and the mean of ``cos^4`` over three
  directions 3/8, the energy per unit area is ``b k^2 / 16 = G k^2 / 2``: ``G = b / 8``.
  Cross-check: KES-F B of six denims, 0.144-0.227 gf cm^2/cm = 1.4-2.2e-5 N m (Kumari and
  Khurana 2016, J. Textiles 4614168, Table 5), against 1.0e-5 N m here for 11 oz denim.

The numbers (the arithmetic in ``test/test_fabrics.py``):

=================  ============================  ======  =======  =========  =========
preset             ARCSim file (fabric, use)     mu      E h      G          c = (G /
                                                 kg/m^2  N/m      N m        mu g)^1/3
=================  ============================  ======  =======  =========  =========
``denim``          11oz-black-denim (99% cotton  0.324   1218.6   1.0072e-5  1.47 cm
                   1% spandex, jeans)
``cotton_twill``   royal-target (65% cotton 35%  0.220   4051.4   1.5676e-5  1.94 cm
                   polyester, pants)
``jersey``         gray-interlock (60% cotton    0.187   51.1     2.3412e-6  1.08 cm
                   40% polyester, t-shirt)
``rib_knit``       ivory-rib-knit (95% cotton    0.276   108.0    4.9051e-6  1.22 cm
                   5% spandex, underwear)
``polyester``      tango-red-jet-set (100%       0.113   128.6    2.1650e-6  1.25 cm
                   polyester, jacket)
``fleece``         pink-ribbon-brown (100%       0.228   276.2    1.1053e-5  1.70 cm
                   polyester, blanket)
``swimwear``       white-swim-solid (87% nylon   0.204   151.2    6.9535e-6  1.51 cm
                   13% spandex, swimsuit)
=================  ============================  ======  =======  =========  =========

Caveats: the database is anisotropic (denim: ``2 C11`` = 411 N/m across, ``2 C22`` = 2028
N/m along) and non-linear (stiffening with strain; the knits most); a preset is the
isotropic, linear sheet with the mean small-strain stiffness, and carries the
``stiffening`` term fitted to the data's mean stretching curve (:func:`fit_stiffening`,
:func:`preset_terms`; doc/fabrics.md, "Strain stiffening"), which it does not turn on.
``cotton_twill``'s C11 and C22 sit at ~2000 N/m in every row, as do white-dots-on-blk's:
possibly a bound of the fit rather than a measurement.
"""
from __future__ import annotations

import math
from typing import Dict, NamedTuple, Optional, Tuple

import numpy as np

__all__ = ['Fabric', 'PRESETS', 'NU_TOLERANCE', 'ARCSIM_SOURCE', 'STRETCHED_ROWS',
           'FIT_STRAIN', 'tensile_stiffness', 'data_tension', 'model_tension',
           'fit_stiffening', 'preset_terms']

#: |nu - 1/3| beyond which Material.from_fabric warns that nu cannot be matched
NU_TOLERANCE = 0.05

ARCSIM_SOURCE = ('Wang, O\'Brien and Ramamoorthi 2011, ACM TOG 30(4) 71, via ARCSim 0.3.1 '
                 'materials/')


class Fabric(NamedTuple):
    """A measured fabric: the quantities :meth:`.material.Material.from_fabric` takes, and
    where they come from."""

    areal_density: float        # kg/m^2
    tensile_stiffness: float    # N/m (E h)
    bending_rigidity: float     # N m per unit width (G)
    source: str
    description: str
    #: the ``stiffening`` term's (stiffness [N/m], knee [-]) fitted to the data's
    #: stretching curve (:func:`fit_stiffening`), None where the data does not stiffen
    stiffening: Optional[Tuple[float, float]] = None


def tensile_stiffness(c11: float, c12: float, c22: float) -> float:
    """E h [N/m] of ARCSim's first stretching row ``C11, C12, C22``: the mean of the two
    texture directions' uniaxial-stress stiffnesses, ``E_1 = 2 (C11 - C12^2 / C22)`` and
    ``E_2 = 2 (C22 - C12^2 / C11)``, C12 clamped at 0 as ARCSim does (module docstring)."""
    c12 = max(c12, 0.0)
    return (c11 - c12 * c12 / c22) + (c22 - c12 * c12 / c11)


#: ARCSim's stretching rows ``C11, C12, C22`` [N/m, halved] of each preset's file: the
#: first (zero strain), and those of the stretch along texture direction 1 (0 degrees, the
#: file's second row) and 2 (90 degrees, its sixth) at the largest principal stretch 7/6
#: (Green strain 0.18). ARCSim 0.3.1's ``evaluate_stretching_sample`` (``src/dde.cpp``)
#: interpolates each coefficient linearly in ``w = clamp(6 (lambda_max - 1), 0, 1)`` between
#: the first row and the direction's row, clamps it at 0 and doubles it (:func:`data_tension`)
STRETCHED_ROWS: Dict[str, Tuple[Tuple[float, float, float], ...]] = {
    'denim': ((205.352005, 10.234077, 1013.88629), (232.027634, 40.646339, 1052.84289),
              (225.767487, 40.917892, 1051.55712)),
    'cotton_twill': ((2016.55456, 9.170511, 2034.97644), (2109.51684, 38.604588, 2173.93969),
                     (2109.52612, 63.424015, 2152.73852)),
    'jersey': ((16.593832, -14.695990, 34.477123), (46.364765, 53.694656, 261.013855),
               (127.443810, 85.848587, 405.872833)),
    'rib_knit': ((42.871021, -0.234556, 65.166023), (52.422512, 7.219094, 245.337158),
                 (105.649139, 0.416488, 254.593491)),
    'polyester': ((43.067627, 54.373299, 171.424835), (75.151695, 82.195221, 236.163773),
                  (227.028687, -21.865427, 404.867188)),
    'fleece': ((151.503906, 106.028160, 244.830673), (164.124344, 33.689709, 268.195221),
               (96.805817, 54.626881, 359.792633)),
    'swimwear': ((47.971176, 6.834521, 104.615456), (40.369045, 23.092957, 169.666290),
                 (68.621185, 40.131950, 124.468513)),
}

#: the Green strains [-] over which :func:`fit_stiffening` matches the data's curve
FIT_STRAIN = (0.0, 0.1)


def data_tension(name: str, e) -> np.ndarray:
    """The measured fabric ``name``'s tension [N/m] (second Piola-Kirchhoff, per unit
    rest width) in uniaxial stress at Green strain ``e`` along the stretch, in ARCSim's
    model of the Wang et al. data (:data:`STRETCHED_ROWS`), the mean of the two texture
    directions as the presets' ``E h`` is::

        S_1 = 2 (C11 - C12^2 / C22) e,   S_2 = 2 (C22 - C12^2 / C11) e

    each coefficient at ``w = clamp(6 (sqrt(1 + 2 e) - 1), 0, 1)`` between the zero-strain
    row and the direction's row, C12 clamped at 0 (ARCSim's ``stretching_force``: S =
    k(G) G with the transverse stress zero; G12 = 0, so only the 0 and 90 degree rows
    enter). ARCSim itself reads the coefficients off a 30^3 grid of precomputed samples;
    this is the continuous law the grid samples."""
    e = np.atleast_1d(np.asarray(e, dtype=float))
    row0, *along = (np.array(r) for r in STRETCHED_ROWS[name])
    w = np.clip(6.0 * (np.sqrt(1.0 + 2.0 * e) - 1.0), 0.0, 1.0)[:, None]
    out = np.zeros_like(e)
    for d, row in enumerate(along):
        c11, c12, c22 = (2.0 * np.maximum(row0 * (1.0 - w) + row * w, 0.0)).T
        out += 0.5 * e * ((c11 - c12 ** 2 / c22) if d == 0 else (c22 - c12 ** 2 / c11))
    return out


def model_tension(tensile_stiffness: float, stiffness: float, knee: float, e) -> np.ndarray:
    """The tension [N/m] (per unit rest width, conjugate to the Green strain) of this
    package's sheet in uniaxial stress at Green strain ``e``: the seed's membrane of a
    preset (``lambda_2 = mu_2 = 2 zeta``, ``zeta = 3 E h / 16``) plus the ``stiffening``
    term ``W = k <s - s0>^2`` (:mod:`.terms.stiffening`, ``s = sqrt(e11^2 + e22^2)``), the
    transverse strain ``e22`` where its stress is zero (a stretch: ``e > 0``; 0 is returned
    for ``e <= 0``)::

        S_22 = lambda_2 (e + e22) + 2 mu_2 e22 + 2 k <s - s0> e22 / s = 0
        S_11 = lambda_2 (e + e22) + 2 mu_2 e   + 2 k <s - s0> e   / s

    (without the term: ``e22 = -e / 3``, ``S_11 = 16 zeta e / 3 = E h e``)."""
    from scipy.optimize import brentq
    lam = mu = 2.0 * 3.0 * tensile_stiffness / 16.0

    def pull(e11, e22):
        s = math.hypot(e11, e22)
        return 2.0 * stiffness * max(s - knee, 0.0) / s if s > 0.0 else 0.0

    out = []
    for ei in np.atleast_1d(np.asarray(e, dtype=float)):
        if ei <= 0.0:
            out.append(0.0)
            continue
        e22 = brentq(lambda t, ei=ei: lam * (ei + t) + 2.0 * mu * t + pull(ei, t) * t,
                     -ei, 0.0, xtol=1e-15, rtol=1e-13)
        out.append(lam * (ei + e22) + 2.0 * mu * ei + pull(ei, e22) * ei)
    return np.array(out)


def fit_stiffening(name: str, strain=FIT_STRAIN, samples: int = 41):
    """(stiffness [N/m], knee [-], error) of the ``stiffening`` term that brings the preset
    ``name``'s :func:`model_tension` to its :func:`data_tension` at ``samples`` Green strains
    over ``strain``: least squares of the difference over the data's tension at the range's
    end (``error`` the largest such difference, a fraction). The start's knees 0, 0.01,
    0.02, 0.04 and 0.06 are each tried, the best kept."""
    from scipy.optimize import least_squares
    eh = PRESETS[name].tensile_stiffness
    e = np.linspace(strain[0], strain[1], samples)
    target = data_tension(name, e)
    scale = target[-1]

    def residual(p):
        return (model_tension(eh, p[0], p[1], e) - target) / scale

    best = min((least_squares(residual, [0.5 * eh, knee], bounds=([0.0, 0.0], [1e6, 1.0]),
                              xtol=1e-12, ftol=1e-12)
                for knee in (0.0, 0.01, 0.02, 0.04, 0.06)), key=lambda r: r.cost)
    return float(best.x[0]), float(best.x[1]), float(np.abs(residual(best.x)).max())


def preset_terms(name: str) -> dict:
    """The terms a preset carries beyond its constants, for ``ClothSimulator(...,
    terms=...)``: ``{'stiffening': {'stiffness': k, 'knee': s0}}`` from its fit, or ``{}``
    where its data does not stiffen. ``ValueError`` for an unknown name."""
    if name not in PRESETS:
        raise ValueError(f'material preset must be one of {", ".join(PRESETS)}, got '
                         f'{name!r}')
    st = PRESETS[name].stiffening
    return {} if st is None else {'stiffening': {'stiffness': st[0], 'knee': st[1]}}


def _wang(preset: str, name: str, density: float, b0: float, b90: float, description: str,
          stiffening: Optional[Tuple[float, float]] = None) -> Fabric:
    """A preset from ARCSim's copy of the Wang et al. 2011 file ``name`` (module
    docstring): E h = :func:`tensile_stiffness` of its first stretching row
    (:data:`STRETCHED_ROWS`), G = (b_0 + b_90) / 16."""
    return Fabric(density, tensile_stiffness(*STRETCHED_ROWS[preset][0]), (b0 + b90) / 16.0,
                  f'{ARCSIM_SOURCE}{name}.json', description, stiffening)


#: name -> Fabric; the numbers are the files' own (module docstring): density, the first
#: bending column at 0 and 90 degrees (the stretching rows: :data:`STRETCHED_ROWS`); the
#: stiffening fitted to the stretching rows by :func:`fit_stiffening` (4 digits)
PRESETS: Dict[str, Fabric] = {
    'denim': _wang('denim', '11oz-black-denim', 0.324, 64.196457e-6, 96.951576e-6,
                   '11 oz denim, 99% cotton 1% spandex (jeans)',
                   stiffening=(19.38, 0.02977)),
    'cotton_twill': _wang('cotton_twill', 'royal-target', 0.220, 125.409805e-6,
                          125.409805e-6, 'twill, 65% cotton 35% polyester (pants)',
                          stiffening=(70.07, 0.0302)),
    'jersey': _wang('jersey', 'gray-interlock', 0.187, 23.191698e-6, 14.267624e-6,
                    'interlock knit, 60% cotton 40% polyester (t-shirt)',
                    stiffening=(126.5, 0.02701)),
    'rib_knit': _wang('rib_knit', 'ivory-rib-knit', 0.276, 46.237591e-6, 32.243889e-6,
                      'rib knit, 95% cotton 5% spandex (underwear)',
                      stiffening=(70.62, 0.0301)),
    'polyester': _wang('polyester', 'tango-red-jet-set', 0.113, 14.293814e-6, 20.345654e-6,
                       'woven, 100% polyester (jacket)',
                       stiffening=(123.3, 0.02269)),
    'fleece': _wang('fleece', 'pink-ribbon-brown', 0.228, 117.070122e-6, 59.774277e-6,
                    '100% polyester (blanket)',
                    stiffening=(77.35, 0.0295)),
    # its data softens a little (0.97 of the linear tension at e = 0.1): no stiffening
    'swimwear': _wang('swimwear', 'white-swim-solid', 0.204, 60.237942e-6, 51.018833e-6,
                      'knit, 87% nylon 13% spandex (swimsuit)'),
}
