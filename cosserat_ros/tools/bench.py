"""``make bench`` / ``python -m cosserat_ros.tools.bench``: what a step costs, as tables.

Two scenes (:data:`.peer_mujoco.SCENES`): ``issue6`` (a 1 m square sheet, N x N
grid, all four edges pinned, gravity, density 0.1 kg/m^2, E h = 500 N/m, nu = 1/3,
D = 1e-4 N m, no coupling) and the shipped ``config/cloth.yaml`` (its material, coupling
phi = 1e-6 N included, pinned at the two top corners). Shared machines are noisy: compare
ratios measured in one run. Parts (the later ones each print a table of their own:
``contact``, ``air``, ``implicit``, ``self`` -- the shipped cloth dropped and lying
crumpled on the ground, then folded in layers on it, the step with self-collision on and
off, and how its extra cost grows with N):

1. ``ours``, per scene: for each N, the median ms/step of repeated batches after warm-up
   (forces + integration, no publishing), the cost per vertex, steps/s, the largest stable
   dt (``critical_dt``), the real-time factor at 0.9 of it, the ratio to the seed's Table
   1 (7.52 / 24.97 / 70.87 ms at 20 / 40 / 80), the cost of building one mesh message
   and of the energy report, the first-call (compile or cache load) time, memory of state
   and operators per vertex, threads.
2. ``peer`` (needs the ``mujoco`` wheel), per scene: MuJoCo's flex on the same scene,
   Euler (and on the square sheet ``discrete``), at our dt and at its own largest stable
   dt, beside ours, with the ratio of step times measured in alternating batches; and the
   settled centre sag of both on the square sheet (about 0.0354 m), ours with each
   solver. The part ``implicit`` sets our implicit solver at 1/60 s, converged and
   linearised (``solver_iterations`` 1), beside our explicit one and MuJoCo's
   ``discrete`` at 1/60 s, on the square and the stiff (E h = 2e3 N/m) sheets.
3. ``node`` (:mod:`.bench_node`): the installed ``cloth_node`` started as ``ros2 run``
   starts it: process start to first mesh message with a cold and a warm compile cache,
   and the real-time factor of a 40 x 40 cloth publishing at 30 Hz, beside the real-time
   factor of the same cloth stepped alone in this process right before (what its step
   allowed in that minute);
   and the shipped ``config/cloth.yaml`` alone, beside one busy process, and paused (its
   CPU use).
4. ``batch`` (:mod:`.bench_batch`): the batch engine on the first example spec, a plain
   loop against Ray with one and two workers, and the time to the first episode.
"""
from __future__ import annotations

import argparse
import math
import os
import platform
import sys
import time

import numba
import numpy as np

from . import peer_mujoco as peer
from ..core.mesh import ClothMesh, grid_mesh
from ..core.simulator import ClothSimulator, Material
from ..ros.conversions import colormap, mesh_marker_array

SEED_MS = {20: 7.52, 40: 24.97, 80: 70.87}


def scene_material(scene: peer.Scene, damping=None) -> Material:
    """Our material for a benchmark scene (``damping``: instead of the scene's own)."""
    return Material.from_plate(youngs_2d=scene.youngs_2d, bending=scene.bending,
                               density=scene.density, phi=scene.phi,
                               damping=scene.damping if damping is None else damping)


ISSUE6 = peer.SCENES['issue6']
CLOTH = peer.SCENES['cloth']
SCENE = scene_material(ISSUE6)
#: damping rate [1/s] used to settle the sheet for the sag comparison (both engines)
SETTLE_RATE = 20.0
SETTLE_TIME = 2.0      # [s]
#: the explicit runs step at this fraction of our critical dt
DT_FRACTION = 0.9


def _bytes(sim: ClothSimulator) -> int:
    """Bytes of every array the simulator holds: model, solver (lanes, plans, work),
    state, controls, coefficients (shared arrays counted once)."""
    m, s = sim.model, sim.solver
    parts = [m.faces, m.vertex_faces, m.vertices, m.jets, (m.st_T,), s.lanes, s.plan,
             s.force_plan, s.work, sim.state, sim.control, sim.coefficients,
             (sim._scratch,)]
    seen = {}
    for part in parts:
        for a in part:
            if isinstance(a, np.ndarray):
                seen[id(a)] = a.nbytes
    return sum(seen.values())


def scene_pins(mesh, scene: peer.Scene) -> np.ndarray:
    """The pinned vertices of a scene on our grid (the same as MuJoCo's pins)."""
    from ..ros.params import pin_set
    return pin_set(mesh, scene.pins)


def scene_simulator(n: int, damping=None, scene: peer.Scene = ISSUE6,
                    solver: str = 'explicit') -> ClothSimulator:
    """A benchmark sheet, pinned and under gravity: on the explicit solver at DT_FRACTION
    of its critical dt, on the implicit one at 1/60 s."""
    mesh = grid_mesh(n, n)
    sim = ClothSimulator(mesh, scene_material(scene, damping), dt=1.0 / 60.0,
                         check_dt=False, solver=solver)
    sim.pin(scene_pins(mesh, scene))
    sim.gravity = (0.0, 0.0, -peer.GRAVITY)
    if solver == 'explicit':
        sim.dt = DT_FRACTION * sim.critical_dt()
    return sim


def _batch_size(run, warmup_s: float, batch_s: float) -> int:
    """Steps per timed batch of about ``batch_s`` seconds for ``run(k)`` (k steps), after
    running it for ``warmup_s``: warm up for half a second, not a few steps (with a 5-step
    warm-up one full run reported 0.103 ms at N = 20 right after a cold compile, where
    reruns give 0.06 ms). The first call is left out of the rate: it may compile, and a
    5 s compile in the timed warm-up once made every batch one step long, so that the
    contact scene's per-call checks read as a 7.8x cost of contact."""
    run(5)
    t = time.perf_counter()
    done = 0
    while done == 0 or time.perf_counter() - t < warmup_s:
        run(5)
        done += 5
    return max(1, int(batch_s * done / (time.perf_counter() - t)))


def step_rtf(sim: ClothSimulator, batch_s: float = 0.1, repeats: int = 5,
             warmup_s: float = 0.3):
    """Real-time factor of ``sim`` stepped alone, as fast as it goes: (dt over the median
    seconds per step of ``repeats`` batches of about ``batch_s`` s, that median in ms).
    The bench measures it right before each node run, so that the node's RTF can be read
    against what its step allowed in the same minute."""
    k = _batch_size(sim.step, warmup_s, batch_s)
    times = []
    for _ in range(repeats):
        t = time.perf_counter()
        sim.step(k)
        times.append((time.perf_counter() - t) / k)
    sec = float(np.median(times))
    return sim.dt / sec, 1e3 * sec


def sustained_rtf(sim: ClothSimulator, seconds: float, frame_s: float = 1.0 / 30.0) -> float:
    """Real-time factor of ``sim`` stepped alone for ``seconds`` of wall time in calls of
    one published frame's steps (``frame_s`` of sim time), as the node's ticks step it;
    after one such call of warm-up. The bench brackets each node run with it: on a shared
    host the step's rate drifts by +-30% within a minute, and a median of short batches
    (:func:`step_rtf`) reads the host's best moments, not the sustained rate the node
    gets."""
    k = max(1, int(round(frame_s / sim.dt)))
    sim.step(k)
    steps = 0
    t0 = time.perf_counter()
    while steps == 0 or time.perf_counter() - t0 < seconds:
        sim.step(k)
        steps += k
    return steps * sim.dt / (time.perf_counter() - t0)


def bench(n: int, pattern: str = 'regular', batch_s: float = 0.2, repeats: int = 7,
          warmup_s: float = 0.5, scene: peer.Scene = ISSUE6):
    """Our step cost on a scene (see the module docstring, part 1)."""
    mesh = grid_mesh(n, n, pattern=pattern, seed=0)
    t0 = time.perf_counter()
    sim = ClothSimulator(mesh, scene_material(scene), dt=1e-5, check_dt=False)
    sim.pin(scene_pins(mesh, scene))
    sim.gravity = (0.0, 0.0, -peer.GRAVITY)
    sim.step(1)
    first = time.perf_counter() - t0
    crit = sim.critical_dt()
    sim.dt = DT_FRACTION * crit
    rtf, ms = step_rtf(sim, batch_s, repeats, warmup_s)
    col = colormap(np.zeros(mesh.n_vertices), 0, 1)
    mesh_marker_array(sim.positions, mesh.faces, col, 0, 'world')
    t = time.perf_counter()
    for _ in range(5):
        mesh_marker_array(sim.positions, mesh.faces, col, 0, 'world')
    pub_ms = 1e3 * (time.perf_counter() - t) / 5
    sim.energy_and_densities()
    t = time.perf_counter()
    for _ in range(5):
        sim.energy_and_densities()
    energy_ms = 1e3 * (time.perf_counter() - t) / 5
    return {'N': n, 'vertices': mesh.n_vertices, 'pattern': pattern, 'ms': ms,
            'ns_vertex': 1e6 * ms / mesh.n_vertices, 'energy_ms': energy_ms,
            'steps_s': 1e3 / ms, 'crit_dt': crit, 'dt': sim.dt,
            'rtf': rtf,
            'seed_ratio': SEED_MS[n] / ms if n in SEED_MS else float('nan'),
            'publish_ms': pub_ms, 'first_call_s': first,
            'bytes_per_vertex': _bytes(sim) / mesh.n_vertices}


def paired_ratio(n: int, pairs: int = 9, batch_s: float = 0.1,
                 scene: peer.Scene = ISSUE6) -> float:
    """MuJoCo Euler's ms/step over ours at our dt, both on the scene, as the median over
    ``pairs`` pairs of back-to-back batches (the order alternating): the load of a shared
    machine drifts over minutes, which a ratio of two separate medians would take in.
    nan if MuJoCo goes bad at our dt."""
    sim = scene_simulator(n, scene=scene)
    theirs = peer.stepper(n, 'Euler', sim.dt, scene)
    runners = (sim.step, theirs)
    ks = [_batch_size(run, 0.3, batch_s) for run in runners]
    ratios = []
    for p in range(pairs):
        per = [0.0, 0.0]
        for j in ((0, 1) if p % 2 == 0 else (1, 0)):
            t = time.perf_counter()
            runners[j](ks[j])
            per[j] = (time.perf_counter() - t) / ks[j]
        ratios.append(per[1] / per[0])
    return float('nan') if theirs.bad() else float(np.median(ratios))


def settled_sag(n: int, solver: str = 'explicit', iterations: int = 20) -> float:
    """Our centre sag [m] on the square sheet after SETTLE_TIME s of damped settling (the
    explicit solver at DT_FRACTION of its critical dt, the implicit one at 1/60 s with
    ``iterations`` Newton iterations at most, 1: linearised)."""
    sim = scene_simulator(n, damping=SETTLE_RATE * peer.DENSITY, solver=solver)
    if solver == 'implicit':
        sim.solver_iterations = iterations
    sim.step(int(round(SETTLE_TIME / sim.dt)))
    return -float(sim.positions[:, 2].min())


def machine() -> str:
    cpu = platform.processor()
    try:
        with open('/proc/cpuinfo') as fh:
            cpu = next(ln.split(':', 1)[1].strip() for ln in fh if ln.startswith('model name'))
    except (OSError, StopIteration):
        pass
    return (f'{cpu}; {os.cpu_count()} cores; numba {numba.__version__} '
            f'({numba.get_num_threads()} threads, layer set on first parallel call)')


def _table(head):
    print('| ' + ' | '.join(head) + ' |')
    print('|' + '---|' * len(head), flush=True)


def _f(x: float, fmt: str) -> str:
    return '-' if x != x else format(x, fmt)


def part_ours(sizes, pattern, scene=ISSUE6):
    print(f'\n## ours: scene {scene.name}\n')
    _table(('N', 'vertices', 'pattern', 'ms/step', 'ns/vertex', 'steps/s', 'crit dt [s]',
            f'RTF@{DT_FRACTION}crit', 'x seed', 'publish ms', 'energy ms', 'first call s',
            'B/vertex', 'threads'))
    rows = {}
    for n in sizes:
        r = bench(n, pattern, scene=scene)
        rows[n] = r
        print(f"| {r['N']} | {r['vertices']} | {r['pattern']} | {r['ms']:.3f} | "
              f"{r['ns_vertex']:.0f} | {r['steps_s']:.0f} | {r['crit_dt']:.2e} | "
              f"{r['rtf']:.2f} | {_f(r['seed_ratio'], '.0f')} | {r['publish_ms']:.2f} | "
              f"{r['energy_ms']:.2f} | {r['first_call_s']:.1f} | "
              f"{r['bytes_per_vertex']:.0f} | {numba.get_num_threads()} |", flush=True)
    big = [n for n in sizes if n >= 40]
    if len(big) > 1:
        per = [rows[n]['ns_vertex'] for n in big if n <= 160]
        print(f'\nCost per vertex from N = {big[0]} to {min(max(big), 160)}: '
              f'max / min = {max(per) / min(per):.2f}', flush=True)
    return rows


def part_peer(ours, sizes, sag_sizes, scene=ISSUE6, discrete=True):
    version = peer.available()
    if version is None:
        print('\n## peer\n\nmujoco is not installed (pip install -r requirements-bench.txt); '
              'skipped.')
        return
    print(f'\n## peer: MuJoCo {version} flex, one thread, on scene {scene.name}\n')
    print('"at our dt": stepping at our dt (0.9 of our critical dt); "own stable dt": the '
          'largest dt of a 1.25x ladder that stays bounded from noise (400 steps for Euler, '
          '60 for `discrete`, which is tried from 1/60 s down). "x ours" = its ms/step / '
          'our ms/step (part 1) at the same dt; "paired" measures that ratio again in '
          'alternating back-to-back batches (median of 9 pairs), which a shared machine\'s '
          'drifting load cannot skew.\n')
    _table(('N', 'engine', 'ms/step at our dt', 'x ours', 'x ours, paired',
            'own stable dt [s]', 'ms/step there', 'RTF there'))
    for n in sizes:
        r = ours[n]
        print(f"| {n} | ours (explicit, {numba.get_num_threads()} threads) | {r['ms']:.3f} | 1 "
              f"| 1 | {r['crit_dt']:.2e} | {r['ms']:.3f} | "
              f"{r['crit_dt'] / (r['ms'] * 1e-3):.2f} |", flush=True)
        engines = (('Euler', r['crit_dt'] / 0.8 * 1.25 ** 2),) + (
            (('discrete', 1 / 60),) if discrete else ())
        for integ, start in engines:
            stable = peer.stable(n, integ, r['dt'], scene=scene)
            same = (peer.ms_per_step(n, integ, r['dt'], scene=scene) if stable
                    else float('nan'))
            paired = (paired_ratio(n, scene=scene) if stable and integ == 'Euler'
                      else float('nan'))
            dt = peer.largest_stable_dt(n, integ, start, scene=scene)
            there = peer.ms_per_step(n, integ, dt, scene=scene) if dt == dt else float('nan')
            print(f"| {n} | MuJoCo {integ} | {_f(same, '.3f')} | {_f(same / r['ms'], '.2f')} "
                  f"| {_f(paired, '.2f')} | {_f(dt, '.2e')} | {_f(there, '.3f')} | "
                  f"{_f(dt / (there * 1e-3), '.2f')} |", flush=True)
    if not sag_sizes:
        return
    print(f'\nCentre sag after {SETTLE_TIME} s of settling with damping rate '
          f'{SETTLE_RATE} 1/s (mass-proportional in both engines):\n')
    _table(('N', 'ours [m]', 'ours, implicit at 1/60 s [m]',
            'ours, implicit linearised at 1/60 s [m]', 'MuJoCo Euler [m]',
            'MuJoCo discrete at 1/60 s [m]'))
    for n in sag_sizes:
        dt = scene_simulator(n).dt
        euler_dt = peer.largest_stable_dt(n, 'Euler', dt)
        print(f'| {n} | {settled_sag(n):.5f} | {settled_sag(n, "implicit"):.5f} | '
              f'{settled_sag(n, "implicit", 1):.5f} | '
              f"{_f(peer.settled_sag(n, 'Euler', euler_dt, SETTLE_TIME, SETTLE_RATE), '.5f')}"
              f" | {_f(peer.settled_sag(n, 'discrete', 1 / 60, SETTLE_TIME, SETTLE_RATE), '.5f')}"
              ' |', flush=True)


# --------------------------------------------------------------------------- contact

def contact_scene(n: int, obstacles: bool) -> ClothSimulator:
    """The shipped cloth (``config/cloth.yaml``'s material, no pins) resting on the ground
    (laid on its contact layer), with five primitives and a 5,120-triangle mesh beside it
    (near, not touching) when ``obstacles``; without them, the same cloth in free fall."""
    import trimesh
    mesh = grid_mesh(n, n)
    sim = ClothSimulator(mesh, scene_material(CLOTH), dt=1e-5, check_dt=False)
    sim.gravity = (0.0, 0.0, -peer.GRAVITY)
    sim.dt = DT_FRACTION * sim.critical_dt()
    x = mesh.vertices.copy()
    x[:, 2] = sim.contact_thickness
    sim.set_positions(x)
    if obstacles:
        sim.add_obstacle('plane')
        sim.add_obstacle('sphere', center=(0.8, 0.0, 0.2), radius=0.2)
        sim.add_obstacle('box', center=(-0.8, 0.0, 0.2), half_extents=(0.2, 0.2, 0.2))
        sim.add_obstacle('capsule', center=(0.0, 0.8, 0.3), radius=0.1, half_length=0.2)
        sim.add_obstacle('cylinder', center=(0.0, -0.8, 0.3), radius=0.1, half_length=0.2)
        sim.add_obstacle('box', center=(0.8, 0.8, 0.1), half_extents=(0.1, 0.1, 0.1),
                         orientation=(0.0, 0.0, 0.3826834, 0.9238795))
        ico = trimesh.creation.icosphere(subdivisions=4, radius=0.2)
        sim.add_obstacle('mesh', vertices=ico.vertices, faces=ico.faces,
                         center=(-0.8, -0.8, 0.25))
    return sim


def part_contact(sizes, pairs: int = 9, batch_s: float = 0.1):
    print('\n## contact: the shipped cloth resting on the ground, five primitives and a '
          '5,120-triangle mesh beside it\n')
    print('"with / without": ms per step of the same cloth with those obstacles and with '
          'none (in free fall), in alternating back-to-back batches, median of the '
          'ratios; "field s": building the mesh obstacle\'s distance field. MuJoCo: the '
          'same scene in its flex (Euler, our dt, flex radius = our contact thickness, '
          'the icosphere as a mesh geom), with and without contact, and our step with '
          'contact over its.\n')
    mj = peer.available()
    head = ['N', 'vertices', 'ms/step without', 'ms/step with', 'with / without',
            'contacts', 'field s']
    if mj:
        head += ['MuJoCo ms without', 'MuJoCo ms with', 'MuJoCo with / without',
                 'MuJoCo with / ours with']
    _table(tuple(head))
    for n in sizes:
        import trimesh
        ico = trimesh.creation.icosphere(subdivisions=4, radius=0.2)
        from ..core.contact import mesh_distance_field
        t = time.perf_counter()
        mesh_distance_field(ico.vertices, ico.faces, 0.01, 0.04)
        field_s = time.perf_counter() - t
        sims = (contact_scene(n, False), contact_scene(n, True))
        ms0, ms1, ratio = paired_ms(sims, pairs, batch_s)
        row = (f'| {n} | {sims[0].n_vertices} | {ms0:.3f} | {ms1:.3f} | {ratio:.2f} | '
               f'{sims[1].contact_state()["contacts"]} | {field_s:.2f} |')
        if mj:
            off = peer.median_ms(peer.contact_stepper(n, sims[1].dt, False), batch_s)
            on = peer.median_ms(peer.contact_stepper(n, sims[1].dt, True), batch_s)
            row += f' {off:.3f} | {on:.3f} | {on / off:.2f} | {on / ms1:.2f} |'
        print(row, flush=True)


def paired_ms(sims, pairs: int = 9, batch_s: float = 0.1, warmup_s: float = 0.3):
    """(ms per step of sims[0], of sims[1], median ratio 1 / 0) from ``pairs`` pairs of
    back-to-back batches, the order alternating (a shared host's load hits both), after
    ``warmup_s`` of each."""
    ks = [_batch_size(sim.step, warmup_s, batch_s) for sim in sims]
    ratios, per = [], [[], []]
    for p in range(pairs):
        got = [0.0, 0.0]
        for j in ((0, 1) if p % 2 == 0 else (1, 0)):
            t = time.perf_counter()
            sims[j].step(ks[j])
            got[j] = (time.perf_counter() - t) / ks[j]
            per[j].append(got[j])
        ratios.append(got[1] / got[0])
    return 1e3 * float(np.median(per[0])), 1e3 * float(np.median(per[1])), float(
        np.median(ratios))


# --------------------------------------------------------------------------- air

def air_scene(n: int, air: bool) -> ClothSimulator:
    """config/flag.yaml's flag (the polyester preset, held along one edge, gravity) as an
    N x N grid of a 1.5 m x 1 m upright sheet, in a 6 m/s wind when ``air``.

    The wind blows 20 degrees off the flag's plane (flag_demo's largest swing): exactly
    along the plane, the flat sheet would feel no air force at all (u . n = 0)."""
    from ..core.air import Air
    mesh = grid_mesh(n, n, width=1.5, height=1.0)
    x = mesh.vertices
    upright = ClothMesh(np.stack([x[:, 0], np.zeros(len(x)), x[:, 1]], axis=1), mesh.faces)
    sim = ClothSimulator(upright, Material.preset('polyester', damping=0.02), dt=1e-5,
                         check_dt=False)
    sim.dt = DT_FRACTION * sim.critical_dt()
    sim.pin(x[:, 0] <= x[:, 0].min() + 1e-9)
    sim.gravity = (0.0, 0.0, -peer.GRAVITY)
    if air:
        sim.air = Air()
        swing = math.radians(20.0)
        sim.wind = (6.0 * math.cos(swing), 6.0 * math.sin(swing), 0.0)
    sim.step(200)
    return sim


def part_air(sizes, pairs: int = 9, batch_s: float = 0.1):
    print('\n## air: config/flag.yaml\'s flag (polyester, held along its pole) in a 6 m/s '
          'wind, with air and without\n')
    print('ms per step with the air model on and off, in alternating back-to-back batches, '
          'median of the ratios.\n')
    _table(('N', 'vertices', 'ms/step without', 'ms/step with', 'with / without'))
    for n in sizes:
        sims = (air_scene(n, False), air_scene(n, True))
        ms0, ms1, ratio = paired_ms(sims, pairs, batch_s)
        print(f'| {n} | {sims[0].n_vertices} | {ms0:.3f} | {ms1:.3f} | {ratio:.2f} |',
              flush=True)


# --------------------------------------------------------------------------- self-collision

#: pleats of the folded cloth of the self-collision part
PLEATS = 8


def pleated_positions(mesh: ClothMesh, thickness: float, pleats: int = PLEATS) -> np.ndarray:
    """The flat N x N sheet folded along x into ``pleats`` layers stacked 1.5 contact
    thicknesses apart, each fold a half circle (radius 0.75 thicknesses) laid out by arc
    length, so that no edge is longer than at rest (an edge across a fold is the chord
    of the path it spans): a cloth lying folded on the ground, its lowest layer at the
    height of its thickness."""
    X = mesh.vertices
    u = X[:, 0] - X[:, 0].min()
    r = 0.75 * thickness
    period = (u.max() + 1e-12) / pleats
    flat = period - math.pi * r
    p = np.minimum(np.floor(u / period), pleats - 1)
    s = u - p * period
    theta = np.clip((s - flat) / r, 0.0, math.pi)
    xl = np.where(s < flat, s, flat + r * np.sin(theta))
    zl = np.where(s < flat, 0.0, r * (1.0 - np.cos(theta)))
    x = np.where(p % 2 == 0, xl, flat - xl)
    return np.stack([x, X[:, 1], thickness + 2.0 * r * p + zl], axis=1)


def folded_scene(n: int, self_collision: bool, settle_s: float = 0.03) -> ClothSimulator:
    """The shipped cloth (``config/cloth.yaml``'s material, no pins) folded in
    :data:`PLEATS` layers (:func:`pleated_positions`) on the ground under gravity, with
    self-collision on or off, after ``settle_s`` of simulation (the layers settle onto
    each other)."""
    mesh = grid_mesh(n, n)
    sim = ClothSimulator(mesh, scene_material(CLOTH), dt=1e-5, check_dt=False)
    sim.gravity = (0.0, 0.0, -peer.GRAVITY)
    # half the critical step of the flat sheet: folded without self-collision, its layers
    # pass through each other, and at 0.9 of it that crumpled state diverged at 0.48 s
    sim.dt = 0.5 * sim.critical_dt()
    sim.set_positions(pleated_positions(mesh, sim.contact_thickness))
    sim.add_obstacle('plane')
    sim.self_collision = self_collision
    sim.step(max(1, int(round(settle_s / sim.dt))))
    return sim


#: [s] how long the crumpled scene's cloth falls and folds before it is measured
CRUMPLE_S = 1.5


def crumpled_scenes(n: int, seconds: float = CRUMPLE_S):
    """The crumpled cloth: the shipped cloth (``config/cloth.yaml``'s material, 1 m,
    no pins), nearly upright (80 degrees) with its lower edge 0.5 m above the ground,
    dropped with self-collision on and stepped at 0.9 of its critical dt for ``seconds``:
    it falls, folds onto itself and lies crumpled on the ground. Returns two simulators
    in that state, self-collision off and on."""
    def make(own):
        sim = ClothSimulator(grid_mesh(n, n), scene_material(CLOTH), dt=1e-5,
                             check_dt=False)
        sim.gravity = (0.0, 0.0, -peer.GRAVITY)
        sim.dt = 0.9 * sim.critical_dt()
        sim.add_obstacle('plane')
        sim.self_collision = own
        return sim
    on = make(True)
    X = on.mesh.vertices
    y = X[:, 1] - X[:, 1].min()
    a = math.radians(80.0)
    # a small wrinkle across the sheet, so that it does not fall as one flat plane
    on.set_positions(np.stack([X[:, 0] + 2e-3 * np.sin(14.0 * y), y * math.cos(a),
                               0.5 + y * math.sin(a)], 1))
    on.step(max(1, int(round(seconds / on.dt))))
    off = make(False)
    off.set_positions(on.state.x)
    off.state.v[:] = on.state.v
    return off, on


def part_self(sizes, crumpled=(40, 80), pairs: int = 5, batch_s: float = 0.1,
              warmup_s: float = 0.3):
    print('\n## self-collision: a crumpled cloth on the ground\n')
    print(f'The shipped cloth dropped nearly upright from 0.5 m with self-collision on, '
          f'after {CRUMPLE_S} s of falling and folding (it lies crumpled on the ground: the '
          'issue\'s scene), then ms per step with self-collision on and off from that '
          'state, in alternating back-to-back batches, median of the ratios. "extra / '
          'step": what self-collision adds over the step without it (target <= 1 at 80, '
          'growing as n log n or slower); '
          '"builds": full builds of the candidate list in the batches, "refreshes": '
          'partial ones around the vertices that moved, "rebases": the candidates\' '
          'distances taken again.\n')
    _table(('N', 'vertices', 'ms/step without', 'ms/step with', 'with / without',
            'extra / step', 'candidates', 'live', 'pairs', 'builds', 'refreshes',
            'rebases'))
    nv, extra = [], []
    for n in crumpled:
        sims = crumpled_scenes(n)
        s0 = sims[1].self_contact_state()
        ms0, ms1, ratio = paired_ms(sims, pairs, batch_s, warmup_s)
        st = sims[1].self_contact_state()
        print(f'| {n} | {sims[0].n_vertices} | {ms0:.3f} | {ms1:.3f} | {ratio:.2f} | '
              f'{ratio - 1:.2f} | {st["candidates"]} | {st["live"]} | {st["active"]} | '
              f'{st["builds"] - s0["builds"]} | {st["refreshes"] - s0["refreshes"]} | '
              f'{st["rebases"] - s0["rebases"]} |', flush=True)
        nv.append(sims[0].n_vertices)
        extra.append(max((ratio - 1.0) * ms0, 1e-9))
    _growth(nv, extra)
    print(f'\n## self-collision: the shipped cloth folded in {PLEATS} layers on the '
          'ground\n')
    print('ms per step with self-collision on and off (the same folded cloth, settled '
          '0.03 s at half the flat sheet\'s critical step: the layers fall the half thickness '
          'between them), in alternating '
          'back-to-back batches, median of the ratios; "extra": '
          'what self-collision adds, per vertex; pairs: vertex-triangle and edge-edge '
          'pairs within the thickness after the batches. The growth of the extra cost is '
          'fitted as vertices^k over the sizes.\n')
    _table(('N', 'vertices', 'ms/step without', 'ms/step with', 'with / without',
            'extra us/vertex', 'pairs', 'builds', 'refreshes'))
    nv, extra = [], []
    for n in sizes:
        sims = (folded_scene(n, False), folded_scene(n, True))
        ms0, ms1, ratio = paired_ms(sims, pairs, batch_s, warmup_s)
        st = sims[1].self_contact_state()
        v = sims[0].n_vertices
        nv.append(v)
        extra.append(max(ms1 - ms0, 1e-9))
        print(f'| {n} | {v} | {ms0:.3f} | {ms1:.3f} | {ratio:.2f} | '
              f'{1e3 * (ms1 - ms0) / v:.3f} | {st["active"]} | {st["builds"]} | '
              f'{st["refreshes"]} |', flush=True)
    _growth(nv, extra)


def _growth(nv, extra) -> None:
    """Prints the fit of the extra cost [ms a step] as vertices^k over the sizes."""
    if len(nv) > 1:
        k = np.polyfit(np.log(nv), np.log(extra), 1)[0]
        print(f'\nextra cost ~ vertices^{k:.2f} from {nv[0]} to {nv[-1]} vertices '
              '(n log n over this range: ~1.1)')


#: the implicit sweep's stiff sheet: the square sheet with E h = 2e3 N/m
STIFF = peer.Scene('stiff', 2e3, 1e-4, 0.1, 0.0, 0.0, 'boundary')


#: the implicit part's window: this much simulated time after the first 2 steps, the
#: same at every N and for both engines (the sheet falls and settles in it; the sag of
#: part 1 is read at 2 s too)
IMPLICIT_WINDOW_S = 2.0
#: and its first steps, the fall from flat (the hard part for Newton), shown apart
FALL_STEPS = 10


def part_implicit(sizes, window_s: float = IMPLICIT_WINDOW_S):
    print('\n## implicit solver at 1/60 s against the explicit one at 0.9 of its critical '
          'dt\n')
    print(f'Each sheet falls from flat (pins and gravity as in part 1) and settles; timed '
          f'step by step over its first {window_s:g} s simulated after 2 steps, the same '
          f'at every N. MuJoCo discrete at 1/60 s on the same sheet, timed over the same '
          f'steps of its own fall from flat; "x MuJoCo" = our implicit RTF / its RTF over '
          f'them, and over the first {FALL_STEPS} of them alone (the fall, the hard part '
          f'for Newton). "linearised": our implicit solver with solver.iterations 1 (one '
          f'Newton step a step, as config/denim.yaml runs it), the same class of scheme as '
          f'MuJoCo discrete (one linear solve a step in M + h D + h^2 K), over the same '
          f'steps of its own fall.\n')
    _table(('scene', 'N', 'explicit ms/step', 'explicit RTF', 'implicit ms/step',
            'implicit RTF', 'Newton its/step', 'CG its/step', 'unconverged steps',
            'MuJoCo discrete ms/step', 'MuJoCo discrete RTF', 'x MuJoCo',
            f'first {FALL_STEPS} steps: ours / MuJoCo ms', f'first {FALL_STEPS}: x MuJoCo',
            'linearised ms/step', 'linearised x MuJoCo'))
    mujoco = peer.available() is not None
    for scene in (ISSUE6, STIFF):
        for n in sizes:
            ex = scene_simulator(n, scene=scene)
            ex.step(10)
            k = _batch_size(ex.step, 0.3, 0.5)
            t = time.perf_counter()
            ex.step(k)
            tex = (time.perf_counter() - t) / k
            im, its, cg, ours = _implicit_window(n, scene, window_s)
            steps = len(ours)
            tim, fall = ours.mean(), ours[:FALL_STEPS].mean()
            lin = _implicit_window(n, scene, window_s, iterations=1)[3].mean()
            mj = mj_fall = float('nan')
            if mujoco and peer.stable(n, 'discrete', im.dt, scene=scene):
                # over the same steps of the same fall: a settling sheet is cheaper a step
                # for both engines, so a window of other steps would not compare like
                # with like
                run = peer.stepper(n, 'discrete', im.dt, scene)
                run(2)
                theirs = np.empty(steps)
                for i in range(steps):
                    t = time.perf_counter()
                    run(1)
                    theirs[i] = time.perf_counter() - t
                if not run.bad():
                    mj, mj_fall = theirs.mean(), theirs[:FALL_STEPS].mean()
            print(f'| {scene.name} | {n} | {tex * 1e3:.3f} | {ex.dt / tex:.2f} | '
                  f'{tim * 1e3:.1f} | {im.dt / tim:.2f} | {its / steps:.1f} | '
                  f'{cg / steps:.1f} | {im.solve_report["unconverged_steps"]} | '
                  f"{_f(mj * 1e3, '.1f')} | {_f(im.dt / mj, '.2f')} | {_f(mj / tim, '.3g')} | "
                  f"{fall * 1e3:.3g} / {_f(mj_fall * 1e3, '.3g')} | "
                  f"{_f(mj_fall / fall, '.3g')} | "
                  f"{lin * 1e3:.3g} | {_f(mj / lin, '.3g')} |", flush=True)


def _implicit_window(n: int, scene: peer.Scene, window_s: float, iterations: int = 20):
    """Our implicit solver on the scene's N x N sheet at 1/60 s with ``iterations``
    Newton iterations at most, timed step by step over ``window_s`` simulated after its
    first 2 steps: (simulator, Newton iterations, CG iterations, seconds of each step)."""
    im = scene_simulator(n, scene=scene, solver='implicit')
    im.solver_iterations = iterations
    im.step(2)
    ours = np.empty(int(round(window_s / im.dt)))
    its = cg = 0
    for i in range(len(ours)):
        t = time.perf_counter()
        im.step(1)
        ours[i] = time.perf_counter() - t
        r = im.solve_report
        its, cg = its + r['iterations'], cg + r['cg_iterations']
    return im, its, cg, ours


def main(argv=None):
    ap = argparse.ArgumentParser(description='Step cost of the cloth simulator, beside '
                                 'MuJoCo flex, and the node start-up and real-time factor.')
    ap.add_argument('--sizes', type=int, nargs='*', default=[20, 40, 80, 160, 320])
    ap.add_argument('--pattern', default='regular')
    ap.add_argument('--peer-sizes', type=int, nargs='*', default=[20, 40, 80, 160],
                    help='N for the MuJoCo comparison (subset of --sizes)')
    ap.add_argument('--sag-sizes', type=int, nargs='*', default=[20, 40])
    ap.add_argument('--node-seconds', type=float, default=6.0,
                    help='how long each node case is watched (0 = skip the node part)')
    ap.add_argument('--scenes', nargs='*', default=list(peer.SCENES),
                    choices=list(peer.SCENES))
    ap.add_argument('--contact-sizes', type=int, nargs='*', default=[40, 80],
                    help='N for the contact part (none: skip it)')
    ap.add_argument('--air-sizes', type=int, nargs='*', default=[40, 80],
                    help='N for the air part (none: skip it)')
    ap.add_argument('--implicit-sizes', type=int, nargs='*', default=[20, 40, 80, 160],
                    help='N for the implicit-solver part (none: skip it)')
    ap.add_argument('--self-sizes', type=int, nargs='*', default=[40, 80, 160],
                    help='N for the self-collision part\'s folded stack (none: skip the '
                    'part)')
    ap.add_argument('--batch-episodes', type=int, default=8,
                    help='episodes of the batch part (tools/bench_batch.py; 0: skip it; '
                    'needs the batch extra)')
    ap.add_argument('--camera-seconds', type=float, default=6.0,
                    help='how long each node case of the camera part is watched '
                    '(tools/bench_camera.py; 0: the renders only; negative: skip the part)')
    ap.add_argument('--envs-steps', type=int, default=20,
                    help='handle_delta steps per case of the envs part '
                    '(tools/bench_envs.py; 0: skip it; needs the envs extra)')
    ap.add_argument('--crumpled-sizes', type=int, nargs='*', default=[40, 80],
                    help='N for the self-collision part\'s crumpled cloth (160 adds ~10 '
                    'minutes: its 1.5 s drop); the extra cost\'s growth is fitted over them')
    a = ap.parse_args(argv)
    print(f'# machine: {machine()}; python {platform.python_version()}')
    for name in a.scenes:
        scene = peer.SCENES[name]
        # the shipped scene up to N = 160 (its 320 x 320 adds minutes and nothing new)
        ours = part_ours([n for n in a.sizes if scene is ISSUE6 or n <= 160], a.pattern, scene)
        peer_sizes = [n for n in a.peer_sizes if n in ours]
        sag = a.sag_sizes if scene is ISSUE6 else []
        if peer_sizes or sag:
            part_peer(ours, peer_sizes, sag, scene, discrete=scene is ISSUE6)
    if a.contact_sizes:
        part_contact(a.contact_sizes)
    if a.air_sizes:
        part_air(a.air_sizes)
    if a.implicit_sizes:
        part_implicit(a.implicit_sizes)
    if a.self_sizes:
        part_self(a.self_sizes, a.crumpled_sizes)
    if a.node_seconds > 0:
        from .bench_node import part_node
        part_node(a.node_seconds)
    if a.camera_seconds >= 0:
        from .bench_camera import part_camera
        part_camera(a.camera_seconds)
    if a.envs_steps > 0:
        from .bench_envs import part_envs
        part_envs(a.envs_steps)
    if a.batch_episodes > 0:
        from .bench_batch import part_batch
        part_batch(a.batch_episodes)
    print(f'\n# threading layer: {numba.threading_layer()}')
    return 0


if __name__ == '__main__':
    sys.exit(main())
