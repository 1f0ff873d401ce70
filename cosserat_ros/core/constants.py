"""Tolerances and default values used across the simulator core (one source of truth)."""

#: A triangle whose area is below this fraction of (mean edge length)^2 is degenerate.
DEGENERATE_AREA_RTOL = 1e-12

#: Stencil templates: two stencils with the same chart coordinates, in the same order, to
#: this fraction of the stencil radius share one set of jet weights (geometry.py).
JET_TEMPLATE_TOL = 1e-9

#: Jet fits: a stencil whose scaled normal matrix has a reciprocal condition number below
#: this is grown by one more ring (up to JET_MAX_RINGS).
JET_RCOND_MIN = 1e-6
JET_MAX_RINGS = 4
#: The least-squares jet is cubic (geometry.NJET = 9 coefficients): second derivatives are
#: O(h^2) on any stencil, boundary included (a quadratic jet is only O(h) on one-sided or
#: irregular stencils). The fast vertex pass (``fast/lanes.py``) is written for exactly nine.

#: Safety factor applied to the linear stability limit 2/omega_max in `critical_dt`. Near
#: omega dt = 2 the explicit update lets strained states pump energy into the highest modes:
#: white position noise of 1.6% of the spacing on an irregular 16x16 sheet diverged at 0.85
#: and 0.8 of the linear limit and ran stably at 0.75 and below, so the estimate is 0.8 of
#: the limit and a run at 0.9x the estimate (0.72x) is stable.
CRITICAL_DT_SAFETY = 0.8

#: A step is declared diverged when a particle speed exceeds this multiple of the membrane
#: wave speed (elastic particle speeds stay far below it) or any value is non-finite.
DIVERGENCE_SPEED_FACTOR = 50.0

#: Hourglass control of the bending jet: weight s of the least-squares residual energy
#: s xi A_i / h_i^4 sum_k omega_k |rho_k|^2 (``core/terms/jet.py``). The residual of the cubic
#: fit is O(h^4) for smooth fields, so the term vanishes with refinement, while the oscillating
#: patterns that a least-squares fit cannot see get a bending-like stiffness. Without it the
#: simply supported plate on irregular meshes stalls near +3% (20/40/80: 4.1, 2.9, ...);
#: with s = 1000 it converges (2.3, 0.8, 0.3%) at an ~8% smaller stable step.
JET_STABILIZATION = 1000.0

#: The jet's normal is a_1 x a_2 / s(|a_1 x a_2|) (``core/terms/jet.py``, ``floored_normal``):
#: s(r) = r while the area ratio r = |a_1 x a_2| (1 at rest: the chart is orthonormal; 0.9999
#: to 1.0009 on every shipped mesh) is at least this floor, and (r^2 + f^2) / (2 f) below it.
#: A stencil crumpled inside itself (a fold across it) can make the fitted tangents parallel
#: while every edge keeps its length; a unit normal's derivative then grows as 1/r (on the
#: drape of test_self_contact, r = 1.7e-5: a bending force of 90 N where the median was
#: 0.005 N, and the explicit step blew up). With the floor the derivative is bounded by 2/f
#: times its value at rest (there: 0.035 N), and the energy is C1 and unchanged wherever
#: r >= f. Below f the curvature fades with the normal's length, so the floor is low: on
#: the bench's crumpled 40 x 40 cloth (4 drops each) the vertices left with r < 0.5 were
#: 134 / 114 / 136 for f = 0.02 / 0.05 / 0.1 (79 with no floor, whose unbounded forces
#: kick crumpled stencils apart) but 211 for f = 0.5, where the fading feeds the crumpling.
JET_AREA_FLOOR = 0.1

#: Vertices per work item of the parallel vertex pass: each chunk owns one scratch row, so
#: the pass allocates nothing and shares no writes; small enough to balance two threads on
#: a 20x20 sheet.
VERTEX_CHUNK = 16

#: Vertices per tile of the step (``fast.step.vertex_parts``): each thread runs the vertex pass
#: over its part of the mesh tile by tile and gathers and updates the vertices a tile
#: completes right after it, while their gradients are still in the core's cache (the
#: size chosen by paired A/B runs at N = 160: docs/performance.md).
TILE_VERTICES = 256

#: Meshes with fewer vertices gather and update in a pass of their own after the vertex pass
#: (the step of a small mesh is in cache anyway; the fused step pays only once the state
#: leaves the cache: docs/performance.md).
FUSE_MIN_VERTICES = 4096
