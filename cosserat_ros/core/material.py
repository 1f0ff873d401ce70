"""Material of the elastic Cosserat surface: constants, tensors and resultants (Eq. 18-22, 27).

Energy per unit rest area (Eq. 18) with the tensors of Eq. 19::

    W = Phi^abgd eps_ab eps_gd + Psi^abgd kap_ab kap_gd + Theta^abgd eps_ab kap_gd
    C^abgd(c) = c [A^ab A^gd + A^ag A^bd + A^ad A^bg],  Phi = C(zeta), Psi = C(xi), Theta = C(phi)

For symmetric 2x2 tensors ``e, k`` and ``Ai = A^-1`` this is the bilinear form
``C(c)[e, k] = c B(e, k)`` with ``B(e, k) = tr(Ai e) tr(Ai k) + 2 tr(Ai e Ai k)``, so
``W = zeta B(eps, eps) + xi B(kap, kap) + phi B(eps, kap)``; and the contraction
``C(c)^abgd T_gd = c [Ai tr(Ai T) + 2 Ai T Ai]^ab``.

Resultants (Eq. 22, keeping the factor 2 that Eq. 27 omits, see doc/theory.md section 2)::

    N*^ab = dW/d eps_ab = 2 Phi eps + Theta kap
    M^ab  = dW/d kap_ab = 2 Psi kap + Theta eps

W is positive definite iff ``zeta > 0``, ``xi > 0`` and ``phi^2 < 4 zeta xi`` (B is).
For a flat rest sheet (A = I) this is an isotropic sheet with Poisson ratio 1/3, bending
stiffness ``D = 6 xi`` and membrane Lame constants ``lambda_2 = mu_2 = 2 zeta`` (2-D Young's
modulus ``16 zeta / 3``): ``zeta B(eps, eps) = lambda_2/2 tr(eps)^2 + mu_2 eps:eps`` and
``xi B(kap, kap) = D/2 [tr(kap)^2 - 2 (1 - nu) det kap]``.

==========  =======  ============  ==========================================
code        symbol   unit          meaning
==========  =======  ============  ==========================================
zeta        zeta     N/m           stretching coefficient
xi          xi       N m           bending coefficient
phi         phi      N             stretch-bend (wrinkle) coupling
density     mu       kg/m^2        mass per unit area
damping     rho      kg/(m^2 s)    velocity damping coefficient of Eq. 1
==========  =======  ============  ==========================================
"""
from __future__ import annotations

import dataclasses
from dataclasses import dataclass
import math
import warnings

import numpy as np

from .compiled import kernel

__all__ = ['Material', 'material_tensor', 'bilinear', 'bilinear_forms', 'contract']


def finite_non_negative(val, name: str) -> float:
    """``val`` as a float if it is a finite, non-negative number (not a bool), else
    ``ValueError`` naming ``name``."""
    if isinstance(val, bool) or not isinstance(val, (int, float, np.floating, np.integer)):
        raise ValueError(f'{name} must be a number, got {val!r}')
    if not math.isfinite(val) or val < 0:
        raise ValueError(f'{name} must be finite and not negative, got {val!r}')
    return float(val)


#: the largest membrane wave speed sqrt(6 zeta / density) a Material accepts [m/s]
MAX_WAVE_SPEED = 1e6
#: the largest damping rate damping / density a Material accepts [1/s]
MAX_DAMPING_RATE = 1e9


@dataclass(frozen=True)
class Material:
    """Material constants in SI units (see the module table). Validated on construction.

    Raises ``ValueError`` naming the constant for non-finite or negative values, zero
    stiffness or mass, or a coupling ``phi`` so large that the energy is indefinite
    (``phi**2 >= 4 zeta xi``).
    """

    zeta: float
    xi: float
    phi: float = 0.0
    density: float = 0.2
    damping: float = 0.0

    def __post_init__(self):
        for name in ('zeta', 'xi', 'phi', 'density', 'damping'):
            val = getattr(self, name)
            if isinstance(val, bool) or not isinstance(val, (int, float, np.floating,
                                                             np.integer)):
                raise ValueError(f'material.{name} must be a number, got {val!r}')
            if not math.isfinite(val):
                raise ValueError(f'material.{name} must be finite, got {val!r}')
            if val < 0:
                raise ValueError(f'material.{name} must not be negative, got {val!r}')
            object.__setattr__(self, name, float(val))
        if self.zeta <= 0:
            raise ValueError('material.zeta (stretching) must be positive, got 0')
        if self.xi <= 0:
            raise ValueError('material.xi (bending) must be positive, got 0')
        if self.density <= 0:
            raise ValueError('material.density must be positive, got 0')
        # the rates a step squares (the stability limit, the divergence check): a density
        # so small against the stiffness or the damping that they leave every material
        # (steel's membrane wave speed is ~5.4 km/s) has no motion to resolve, and its
        # squares overflow a float
        c = math.sqrt(6.0 * self.zeta / self.density)
        if not c <= MAX_WAVE_SPEED:
            raise ValueError(f'material.density = {self.density:g} kg/m^2 with zeta = '
                             f'{self.zeta:g} N/m gives a membrane wave speed of {c:.3g} m/s, '
                             f'above {MAX_WAVE_SPEED:g} m/s: no time step resolves it')
        rate = self.damping / self.density
        if not rate <= MAX_DAMPING_RATE:
            raise ValueError(f'material.density = {self.density:g} kg/m^2 with damping = '
                             f'{self.damping:g} kg/(m^2 s) gives a damping rate of '
                             f'{rate:.3g} 1/s, above {MAX_DAMPING_RATE:g} 1/s')
        if self.phi ** 2 >= 4.0 * self.zeta * self.xi:
            raise ValueError(f'material.phi = {self.phi:g} N makes the energy indefinite: '
                             f'it needs phi^2 < 4 zeta xi = {4 * self.zeta * self.xi:g} N^2')

    @property
    def lame(self):
        """Membrane Lame constants (lambda_2, mu_2) of a flat sheet [N/m]: both 2 zeta."""
        return 2.0 * self.zeta, 2.0 * self.zeta

    @property
    def youngs_modulus_2d(self) -> float:
        """2-D Young's modulus E h = 16 zeta / 3 [N/m] (flat rest sheet)."""
        return 16.0 * self.zeta / 3.0

    @property
    def poisson_ratio(self) -> float:
        """Poisson ratio of the model, 1/3 for every choice of constants."""
        return 1.0 / 3.0

    @property
    def bending_stiffness(self) -> float:
        """Plate bending stiffness D = 6 xi [N m] (flat rest sheet)."""
        return 6.0 * self.xi

    @property
    def wave_speed(self) -> float:
        """Membrane P-wave speed c = sqrt((lambda_2 + 2 mu_2) / mu) = sqrt(6 zeta / mu) [m/s]."""
        return math.sqrt(6.0 * self.zeta / self.density)

    @classmethod
    def from_fabric(cls, areal_density: float, tensile_stiffness: float,
                    poisson_ratio: float, bending_rigidity: float,
                    damping: float = 0.0) -> 'Material':
        """Material from a fabric's datasheet (derivation: :mod:`.fabrics`)::

            zeta = 3 E h / 16,   xi = G / 6,   phi = 0,   density = mu

        ``areal_density`` mu [kg/m^2], ``tensile_stiffness`` E h [N/m] (uniaxial, per unit
        width), ``poisson_ratio`` nu [-] (0 <= nu < 1; the model's is 1/3 whatever the
        constants: a ``UserWarning`` says so when nu is further than 0.05 from it),
        ``bending_rigidity`` G [N m] (flexural rigidity per unit width, ASTM D1388 or
        KES-F B), ``damping`` [kg/(m^2 s)]. ``ValueError`` names a bad value."""
        from .fabrics import NU_TOLERANCE
        vals = {'areal_density': areal_density, 'tensile_stiffness': tensile_stiffness,
                'poisson_ratio': poisson_ratio, 'bending_rigidity': bending_rigidity}
        for name, val in vals.items():
            finite_non_negative(val, name)
        for name in ('areal_density', 'tensile_stiffness', 'bending_rigidity'):
            if vals[name] == 0:
                raise ValueError(f'{name} must be positive, got 0')
        if poisson_ratio >= 1.0:
            raise ValueError(f'poisson_ratio must be below 1, got {poisson_ratio!r}')
        if abs(poisson_ratio - 1.0 / 3.0) > NU_TOLERANCE:
            warnings.warn(f'poisson_ratio {poisson_ratio:g}: the Cosserat law of the seed '
                          'has nu = 1/3 for every choice of constants; E h and G are '
                          'matched, the lateral contraction stays 1/3 and the shear '
                          f'stiffness is 3 E h / 8 instead of E h / (2 (1 + nu))',
                          UserWarning, stacklevel=2)
        return cls(zeta=3.0 * tensile_stiffness / 16.0, xi=bending_rigidity / 6.0, phi=0.0,
                   density=areal_density, damping=damping)

    @classmethod
    def preset(cls, name: str, **overrides) -> 'Material':
        """A measured fabric by name (:data:`.fabrics.PRESETS`: ``denim``,
        ``cotton_twill``, ``jersey``, ``rib_knit``, ``polyester``, ``fleece``,
        ``swimwear``; sources and conversions in :mod:`.fabrics`) through
        :meth:`from_fabric`. ``overrides`` replace any of the resulting ``zeta``, ``xi``,
        ``phi``, ``density``, ``damping`` (default damping 0)."""
        from .fabrics import PRESETS
        if name not in PRESETS:
            raise ValueError(f'material preset must be one of {", ".join(PRESETS)}, '
                             f'got {name!r}')
        bad = sorted(set(overrides) - {'zeta', 'xi', 'phi', 'density', 'damping'})
        if bad:
            raise ValueError(f'preset overrides must be material constants, got {bad}')
        f = PRESETS[name]
        base = cls.from_fabric(f.areal_density, f.tensile_stiffness, 1.0 / 3.0,
                               f.bending_rigidity)
        return dataclasses.replace(base, **overrides)

    @property
    def bending_rigidity(self) -> float:
        """Flexural rigidity per unit width G [N m] of a strip in cylindrical bending:
        D = 6 xi (:mod:`.fabrics`)."""
        return 6.0 * self.xi

    @classmethod
    def from_plate(cls, youngs_2d: float, bending: float, density: float,
                   damping: float = 0.0, phi: float = 0.0) -> 'Material':
        """Material from a sheet's E h [N/m] and D [N m] (its Poisson ratio is 1/3)."""
        return cls(zeta=3.0 * youngs_2d / 16.0, xi=bending / 6.0, phi=phi, density=density,
                   damping=damping)


def material_tensor(c: float, rest_metric: np.ndarray) -> np.ndarray:
    """C^abgd(c) of Eq. 19 for every vertex: (n, 2, 2, 2, 2) from A_ab (n, 2, 2)."""
    ai = np.linalg.inv(rest_metric)
    return c * (np.einsum('nab,ngd->nabgd', ai, ai) + np.einsum('nag,nbd->nabgd', ai, ai)
                + np.einsum('nad,nbg->nabgd', ai, ai))


def bilinear_forms(ainv: np.ndarray, e: np.ndarray, k: np.ndarray) -> np.ndarray:
    """B(e_i, k_i) per row (n,) for inverse metrics ``ainv`` and symmetric tensors ``e``,
    ``k``, each (n,3) as (11, 12, 22): numpy twin of :func:`bilinear`."""
    i11, i12, i22 = ainv[:, 0], ainv[:, 1], ainv[:, 2]
    p11 = i11 * e[:, 0] + i12 * e[:, 1]
    p12 = i11 * e[:, 1] + i12 * e[:, 2]
    p21 = i12 * e[:, 0] + i22 * e[:, 1]
    p22 = i12 * e[:, 1] + i22 * e[:, 2]
    q11 = i11 * k[:, 0] + i12 * k[:, 1]
    q12 = i11 * k[:, 1] + i12 * k[:, 2]
    q21 = i12 * k[:, 0] + i22 * k[:, 1]
    q22 = i12 * k[:, 1] + i22 * k[:, 2]
    return (p11 + p22) * (q11 + q22) + 2.0 * (p11 * q11 + p12 * q21 + p21 * q12 + p22 * q22)


@kernel(inline='always')
def bilinear(i11, i12, i22, e11, e12, e22, k11, k12, k22):
    """B(e, k) = tr(Ai e) tr(Ai k) + 2 tr(Ai e Ai k) for symmetric 2x2 tensors."""
    # Ai e (rows): [[i11 e11 + i12 e12, i11 e12 + i12 e22], [i12 e11 + i22 e12, ...]]
    p11 = i11 * e11 + i12 * e12
    p12 = i11 * e12 + i12 * e22
    p21 = i12 * e11 + i22 * e12
    p22 = i12 * e12 + i22 * e22
    q11 = i11 * k11 + i12 * k12
    q12 = i11 * k12 + i12 * k22
    q21 = i12 * k11 + i22 * k12
    q22 = i12 * k12 + i22 * k22
    return (p11 + p22) * (q11 + q22) + 2.0 * (p11 * q11 + p12 * q21 + p21 * q12 + p22 * q22)


@kernel(inline='always')
def contract(c, i11, i12, i22, t11, t12, t22):
    """C(c)^abgd T_gd = c [Ai tr(Ai T) + 2 Ai T Ai] for symmetric T: returns (11, 12, 22)."""
    tr = i11 * t11 + 2.0 * i12 * t12 + i22 * t22
    # Ai T Ai
    p11 = i11 * t11 + i12 * t12
    p12 = i11 * t12 + i12 * t22
    p21 = i12 * t11 + i22 * t12
    p22 = i12 * t12 + i22 * t22
    s11 = p11 * i11 + p12 * i12
    s12 = p11 * i12 + p12 * i22
    s22 = p21 * i12 + p22 * i22
    return (c * (i11 * tr + 2.0 * s11), c * (i12 * tr + 2.0 * s12),
            c * (i22 * tr + 2.0 * s22))
