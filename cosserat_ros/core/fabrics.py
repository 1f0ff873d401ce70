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
isotropic, linear sheet with the mean small-strain stiffness. ``cotton_twill``'s C11 and
C22 sit at ~2000 N/m in every row, as do white-dots-on-blk's: possibly a bound of the fit
rather than a measurement.
"""
from __future__ import annotations

from typing import Dict, NamedTuple

__all__ = ['Fabric', 'PRESETS', 'NU_TOLERANCE', 'ARCSIM_SOURCE', 'tensile_stiffness']

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


def tensile_stiffness(c11: float, c12: float, c22: float) -> float:
    """E h [N/m] of ARCSim's first stretching row ``C11, C12, C22``: the mean of the two
    texture directions' uniaxial-stress stiffnesses, ``E_1 = 2 (C11 - C12^2 / C22)`` and
    ``E_2 = 2 (C22 - C12^2 / C11)``, C12 clamped at 0 as ARCSim does (module docstring)."""
    c12 = max(c12, 0.0)
    return (c11 - c12 * c12 / c22) + (c22 - c12 * c12 / c11)


def _wang(name: str, density: float, c11: float, c12: float, c22: float, b0: float,
          b90: float, description: str) -> Fabric:
    """A preset from ARCSim's copy of the Wang et al. 2011 file ``name`` (module
    docstring): E h = :func:`tensile_stiffness`, G = (b_0 + b_90) / 16."""
    return Fabric(density, tensile_stiffness(c11, c12, c22), (b0 + b90) / 16.0,
                  f'{ARCSIM_SOURCE}{name}.json', description)


#: name -> Fabric; the numbers are the files' own (module docstring): density, the first
#: stretching row's C11, C12, C22, the first bending column at 0 and 90 degrees
PRESETS: Dict[str, Fabric] = {
    'denim': _wang('11oz-black-denim', 0.324, 205.352005, 10.234077, 1013.88629,
                   64.196457e-6, 96.951576e-6, '11 oz denim, 99% cotton 1% spandex (jeans)'),
    'cotton_twill': _wang('royal-target', 0.220, 2016.55456, 9.170511, 2034.97644,
                          125.409805e-6, 125.409805e-6,
                          'twill, 65% cotton 35% polyester (pants)'),
    'jersey': _wang('gray-interlock', 0.187, 16.593832, -14.695990, 34.477123,
                    23.191698e-6, 14.267624e-6,
                    'interlock knit, 60% cotton 40% polyester (t-shirt)'),
    'rib_knit': _wang('ivory-rib-knit', 0.276, 42.871021, -0.234556, 65.166023,
                      46.237591e-6, 32.243889e-6,
                      'rib knit, 95% cotton 5% spandex (underwear)'),
    'polyester': _wang('tango-red-jet-set', 0.113, 43.067627, 54.373299, 171.424835,
                       14.293814e-6, 20.345654e-6, 'woven, 100% polyester (jacket)'),
    'fleece': _wang('pink-ribbon-brown', 0.228, 151.503906, 106.028160, 244.830673,
                    117.070122e-6, 59.774277e-6, '100% polyester (blanket)'),
    'swimwear': _wang('white-swim-solid', 0.204, 47.971176, 6.834521, 104.615456,
                      60.237942e-6, 51.018833e-6, 'knit, 87% nylon 13% spandex (swimsuit)'),
}
