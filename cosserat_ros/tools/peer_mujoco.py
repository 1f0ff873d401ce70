"""The benchmark scenes, and the peer engine on them: MuJoCo's 2-D flex.

MuJoCo (the ``mujoco`` wheel) is a dev-only extra (``requirements-bench.txt``, installed
by ``make bench``); nothing in the simulator or the node imports it, and this module
imports it only inside the functions that run it. Two scenes (:data:`SCENES`), each a 1 m
square on an N x N grid under gravity:

* ``issue6``: all four edges pinned, areal density 0.1 kg/m^2, E h = 500 N/m, nu = 1/3,
  D = 1e-4 N m (the square sheet, ``issue6``);
* ``cloth``: the shipped ``config/cloth.yaml`` (zeta = 50 N/m, xi = 2e-5 N m, i.e.
  E h = 266.7 N/m and D = 1.2e-4 N m, density 0.2 kg/m^2, damping 0.1 kg/(m^2 s)), pinned
  at the two top corners, falling and swinging (MuJoCo has no stretch-bend coupling; our
  side keeps the shipped phi = 1e-6 N).

MuJoCo takes a 3-D Young's modulus and a thickness, so ``h = sqrt(12 (1 - nu^2) D / (E h))``
(1.46 mm for the square sheet) and ``E = (E h) / h``.

Every vertex of MuJoCo's grid carries mass ``density * spacing^2`` (the flexcomp ``mass``
is spread evenly over the grid), which is what the lumped dual areas of our regular grid
give the interior vertices; the pinned edge carries no dof. Damping, where asked for,
is per-dof damping ``gamma * m`` (the same mass-proportional damping as our ``damping``).
"""
from __future__ import annotations

from dataclasses import dataclass
import functools
import math
import time
from typing import Optional

import numpy as np

@dataclass(frozen=True)
class Scene:
    """A benchmark sheet: E h [N/m], D [N m], density [kg/m^2], damping rho
    [kg/(m^2 s)], phi [N] (ours only), and its pins: ``boundary`` or ``top_corners``."""

    name: str
    youngs_2d: float
    bending: float
    density: float
    damping: float
    phi: float
    pins: str


#: the scenes of the module docstring
SCENES = {'issue6': Scene('issue6', 500.0, 1e-4, 0.1, 0.0, 0.0, 'boundary'),
          'cloth': Scene('cloth', 16.0 * 50.0 / 3.0, 6.0 * 2e-5, 0.2, 0.1, 1e-6,
                         'top_corners')}

#: the square sheet's constants (bench and tests read these)
YOUNGS_2D = SCENES['issue6'].youngs_2d      # E h [N/m]
BENDING = SCENES['issue6'].bending          # D [N m]
POISSON = 1.0 / 3.0
DENSITY = SCENES['issue6'].density          # [kg/m^2]
GRAVITY = 9.81                              # [m/s^2]

#: a probe diverged when a speed exceeds this [m/s] (the membrane wave speed is 75 m/s)
PROBE_VMAX = 100.0
#: probe length [steps]: an explicit scheme above its limit blows up from 1 um/s noise
#: within a few hundred steps; the implicit ones are checked over one simulated second
#: at 1/60 s
PROBE_STEPS = {'Euler': 400, 'discrete': 60, 'implicit': 60, 'implicitfast': 60}


def available() -> Optional[str]:
    """The mujoco version, or None when the wheel is not installed."""
    try:
        import mujoco
    except ImportError:
        return None
    return mujoco.__version__


def scene_xml(n: int, integrator: str, dt: float, scene: Scene = SCENES['issue6']) -> str:
    """MJCF of a benchmark sheet: flexcomp grid, dim 2, elastic2d stretch + bend."""
    dt = float(dt)
    thickness = math.sqrt(12.0 * (1.0 - POISSON ** 2) * scene.bending / scene.youngs_2d)
    young = scene.youngs_2d / thickness
    h = 1.0 / n
    mass = scene.density * h * h * (n + 1) ** 2
    ranges = ((f'0 0 {n} 0', f'0 {n} {n} {n}', f'0 0 0 {n}', f'{n} 0 {n} {n}')
              if scene.pins == 'boundary' else (f'0 {n} 0 {n}', f'{n} {n} {n} {n}'))
    pins = ''.join(f'<pin gridrange="{a}"/>' for a in ranges)
    return f"""<mujoco model="sheet{n}">
  <option timestep="{dt!r}" integrator="{integrator}" gravity="0 0 {-GRAVITY}"/>
  <worldbody>
    <flexcomp name="sheet" type="grid" count="{n + 1} {n + 1} 1" spacing="{h!r} {h!r} 1"
              dim="2" radius="0.001" mass="{mass!r}">
      <elasticity young="{young!r}" poisson="{POISSON!r}" thickness="{thickness!r}"
                  elastic2d="both"/>
      <contact contype="0" conaffinity="0"/>
      <edge equality="false"/>
      {pins}
    </flexcomp>
  </worldbody>
</mujoco>"""


def contact_xml(n: int, dt: float, obstacles: bool, thickness: float = 0.002,
                scene: Scene = SCENES['cloth']) -> str:
    """MJCF of the contact benchmark (``bench.contact_scene``): the sheet, no pins, lying
    on the ground (its vertices ``thickness`` above it, the flex radius), with the same
    five primitives and a 5,120-triangle icosphere beside it when ``obstacles``; without
    them, the same sheet with contact off (in free fall)."""
    import trimesh
    dt = float(dt)
    t_h = math.sqrt(12.0 * (1.0 - POISSON ** 2) * scene.bending / scene.youngs_2d)
    h = 1.0 / n
    mass = scene.density * h * h * (n + 1) ** 2
    geoms = asset = ''
    contact = '<contact contype="0" conaffinity="0"/>'
    if obstacles:
        ico = trimesh.creation.icosphere(subdivisions=4, radius=0.2)
        verts = ' '.join(f'{v:.6f}' for v in ico.vertices.ravel())
        faces = ' '.join(str(int(i)) for i in ico.faces.ravel())
        asset = f'<asset><mesh name="ico" vertex="{verts}" face="{faces}"/></asset>'
        geoms = '\n    '.join((
            '<geom type="plane" size="5 5 0.1"/>',
            '<geom type="sphere" pos="0.8 0 0.2" size="0.2"/>',
            '<geom type="box" pos="-0.8 0 0.2" size="0.2 0.2 0.2"/>',
            '<geom type="capsule" pos="0 0.8 0.3" size="0.1 0.2"/>',
            '<geom type="cylinder" pos="0 -0.8 0.3" size="0.1 0.2"/>',
            '<geom type="box" pos="0.8 0.8 0.1" size="0.1 0.1 0.1" '
            'quat="0.9238795 0 0 0.3826834"/>',
            '<geom type="mesh" mesh="ico" pos="-0.8 -0.8 0.25"/>'))
        contact = '<contact condim="3" friction="0.5" selfcollide="none"/>'
    return f"""<mujoco model="contact{n}">
  <option timestep="{dt!r}" integrator="Euler" gravity="0 0 {-GRAVITY}"/>
  {asset}
  <worldbody>
    {geoms}
    <flexcomp name="sheet" type="grid" count="{n + 1} {n + 1} 1" spacing="{h!r} {h!r} 1"
              pos="0 0 {thickness!r}" dim="2" radius="{thickness!r}" mass="{mass!r}">
      <elasticity young="{scene.youngs_2d / t_h!r}" poisson="{POISSON!r}"
                  thickness="{t_h!r}" elastic2d="both"/>
      {contact}
      <edge equality="false"/>
    </flexcomp>
  </worldbody>
</mujoco>"""


def contact_stepper(n: int, dt: float, obstacles: bool, scene: Scene = SCENES['cloth']):
    """``run(k)`` for the contact benchmark scene (:func:`contact_xml`), with the scene's
    mass-proportional damping; ``run.bad()`` and ``run.contacts()`` (MuJoCo's contact
    count now)."""
    import mujoco
    mujoco.set_mju_user_warning(_count_warning)
    model = mujoco.MjModel.from_xml_string(contact_xml(n, dt, obstacles, scene=scene))
    model.dof_damping[:] = scene.damping / n ** 2
    data = mujoco.MjData(model)

    def run(k: int) -> None:
        mujoco.mj_step(model, data, nstep=k)
    run.bad = lambda: _bad(model, data)
    run.contacts = lambda: int(data.ncon)
    return run


def _count_warning(message: str) -> None:
    """MuJoCo's warning handler for the probes: an unstable probe is expected, its
    warning is read from ``data.warning`` instead of printed."""


@functools.lru_cache(maxsize=4)
def _compiled(n: int, scene: Scene):
    """The scene's MjModel for N = n, compiled once: MuJoCo's compile of a flexcomp grid
    grows about as the square of the vertex count (0.4 / 6 / 15 s at N = 40 / 80 / 100 on
    a slow 2-core machine, minutes at 160), while the integrator, the time step and the
    damping are run-time fields of the model that :func:`build` sets per run."""
    import mujoco
    return mujoco.MjModel.from_xml_string(scene_xml(n, 'Euler', 1e-4, scene))


def build(n: int, integrator: str, dt: float, damping_rate: Optional[float] = None,
          scene: Scene = SCENES['issue6']):
    """(model, data) of the scene, fresh data from rest; ``damping_rate`` gamma [1/s] adds
    dof damping gamma m (None: the scene's own, damping / density). The model is shared
    between runs of the same n and scene (see :func:`_compiled`); every call sets all the
    fields a run depends on, so a run must be over before the next build of the same
    n."""
    import mujoco
    mujoco.set_mju_user_warning(_count_warning)
    model = _compiled(n, scene)
    model.opt.timestep = float(dt)
    model.opt.integrator = getattr(mujoco.mjtIntegrator, 'mjINT_' + integrator.upper())
    gamma = scene.damping / scene.density if damping_rate is None else damping_rate
    model.dof_damping[:] = gamma * scene.density / n ** 2
    return model, mujoco.MjData(model)


def _bad(model, data) -> bool:
    import mujoco
    v = data.qvel
    return (not np.all(np.isfinite(data.qpos)) or not np.all(np.isfinite(v))
            or float(np.abs(v).max(initial=0.0)) > PROBE_VMAX
            or data.warning[mujoco.mjtWarning.mjWARN_BADQACC].number > 0)


def stable(n: int, integrator: str, dt: float, steps: Optional[int] = None,
           scene: Scene = SCENES['issue6']) -> bool:
    """Does the sheet stay bounded for ``steps`` steps (PROBE_STEPS by default) from rest,
    seeded with 1 um/s noise on every dof (so an unstable mode has something to grow
    from)?"""
    import mujoco
    steps = PROBE_STEPS.get(integrator, 400) if steps is None else steps
    model, data = build(n, integrator, dt, scene=scene)
    data.qvel[:] = 1e-6 * np.random.default_rng(0).standard_normal(model.nv)
    done = 0
    while done < steps:
        k = min(20, steps - done)
        mujoco.mj_step(model, data, nstep=k)
        done += k
        if _bad(model, data):
            return False
    return True


def largest_stable_dt(n: int, integrator: str, start: float, factor: float = 1.25,
                      tries: int = 10, scene: Scene = SCENES['issue6']) -> float:
    """Largest dt of the ladder ``start * factor**-k`` (k = 0, 1, ...) that is stable; nan
    if none of ``tries`` rungs is."""
    dt = start
    for _ in range(tries):
        if stable(n, integrator, dt, scene=scene):
            return dt
        dt /= factor
    return float('nan')


def stepper(n: int, integrator: str, dt: float, scene: Scene = SCENES['issue6']):
    """``run(k)``: advance a fresh scene by k steps (the sheet falling from rest), for
    timing in alternation with our simulator; ``run.bad()`` tells if it went bad."""
    import mujoco
    model, data = build(n, integrator, dt, scene=scene)

    def run(k: int) -> None:
        mujoco.mj_step(model, data, nstep=k)
    run.bad = lambda: _bad(model, data)
    return run


def ms_per_step(n: int, integrator: str, dt: float, batch_s: float = 0.2,
                repeats: int = 5, scene: Scene = SCENES['issue6']) -> float:
    """Median wall time of one step [ms] over ``repeats`` batches (the sheet falling from
    rest under gravity, as our own benchmark), nan if the run goes bad."""
    return median_ms(stepper(n, integrator, dt, scene), batch_s, repeats)


def median_ms(run, batch_s: float = 0.2, repeats: int = 5) -> float:
    """Median wall time of one step [ms] of stepper ``run`` (:func:`stepper`,
    :func:`contact_stepper`) over ``repeats`` batches of about ``batch_s`` s each, nan if
    the run goes bad."""
    run(2)
    t = time.perf_counter()
    run(3)
    per = (time.perf_counter() - t) / 3
    k = max(1, int(batch_s / per))
    times = []
    for _ in range(repeats):
        t = time.perf_counter()
        run(k)
        times.append((time.perf_counter() - t) / k)
    if run.bad():
        return float('nan')
    return 1e3 * float(np.median(times))


def settled_sag(n: int, integrator: str, dt: float, duration: float = 2.0,
                damping_rate: float = 20.0) -> float:
    """Centre sag [m] after ``duration`` s of damped settling (-min z of the sheet)."""
    import mujoco
    model, data = build(n, integrator, dt, damping_rate)
    mujoco.mj_step(model, data, nstep=max(1, int(round(duration / dt))))
    if _bad(model, data):
        return float('nan')
    return -float(data.flexvert_xpos[:, 2].min())
