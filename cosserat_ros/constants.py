"""Tolerances and default values used across the simulator core (one source of truth)."""

#: A triangle whose area is below this fraction of (mean edge length)^2 is degenerate.
DEGENERATE_AREA_RTOL = 1e-12

#: Jet fits: a stencil whose scaled normal matrix has a reciprocal condition number below
#: this is grown by one more ring (up to JET_MAX_RINGS).
JET_RCOND_MIN = 1e-6
JET_MAX_RINGS = 4

#: Safety factor applied to the linear stability limit 2/omega_max in `critical_dt`.
CRITICAL_DT_SAFETY = 1.0

#: A step is declared diverged when a particle speed exceeds this multiple of the membrane
#: wave speed (elastic particle speeds stay far below it) or any value is non-finite.
DIVERGENCE_SPEED_FACTOR = 50.0

#: Largest Green strain component that is still a physical state; beyond it the run is
#: treated as a numerical blow-up (a stretch of sqrt(1 + 2*20) ~ 6.4x).
DIVERGENCE_STRAIN_MAX = 20.0
