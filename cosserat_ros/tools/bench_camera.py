"""``make bench``, part ``camera``: what the virtual camera costs, in one run.

* ``config/table.yaml`` as shipped (40 x 40 cloth, a box and a plane), the cloth dropped
  and landed (1 s), its camera ``side`` (640 x 480): depth + colour, the median of
  repeated renders on the numba threads of this process, in ms and as a share of one
  publish tick of the node (1 / publish_rate);
* growth: the table's obstacles and camera with an n x n sheet of one waved shape over
  the table at every n (20 and 80), at 320 x 240, 640 x 480 and 1280 x 960: the ratio of
  the 80 x 80 cost to the 20 x 20 cost at each image size (16 if the cost were pixels
  times triangles, near 1 for the binned ray cast of :mod:`cosserat_ros.core.raster`)
  and the cost per megapixel;
* the node: the installed ``cloth_node`` on ``config/cloth.yaml`` without a camera and
  with one 640 x 480 camera at 15 Hz, alternated over three rounds (after one unmeasured
  start that warms the compile caches), each watched for the same time: the real-time
  factors and their ratio (target >= 0.95).
"""
from __future__ import annotations

import os
import statistics
import tempfile
import time

import numpy as np

__all__ = ['part_camera']

RESOLUTIONS = ((320, 240), (640, 480), (1280, 960))
CLOTHS = (20, 80)


def _share(name: str) -> str:
    from ament_index_python.packages import get_package_share_directory
    return os.path.join(get_package_share_directory('cosserat_ros'), 'config', name)


def _table_scene(n: int = 0):
    """config/table.yaml's simulator (its mesh n x n when given), landed for 1 s, and its
    camera spec."""
    from ..ros.cameras import camera_specs
    from ..ros.scene import build_simulator, check_parameters, read_params_file
    given = read_params_file(_share('table.yaml'))
    if n:           # the shipped dt is 0.9 of the critical step at 40 x 40: scaled by h
        given.update({'mesh.nx': n, 'mesh.ny': n, 'dt': given['dt'] * 40 / n})
    p = check_parameters(given)
    sim = build_simulator(p, given)
    sim.step(int(round(1.0 / sim.dt)))
    return sim, camera_specs(p)['side'], p


def _waved(table_sim, n: int):
    """An n x n 1 m sheet over ``table_sim``'s obstacles, waved over the table top."""
    from ..core.contact import rotation_matrix
    from ..core.mesh import grid_mesh
    from ..core.simulator import ClothSimulator
    sim = ClothSimulator(grid_mesh(n, n), table_sim.material, dt=1e-5, check_dt=False)
    for oid, d in table_sim.obstacles.items():
        geometry = {k: d[k] for k in ('half_extents', 'radius', 'half_length') if k in d}
        if d['shape'] == 'plane':
            sim.add_obstacle('plane', point=d['position'],
                             normal=rotation_matrix(d['orientation'])[:, 2])
        else:
            sim.add_obstacle(d['shape'], center=d['position'], orientation=d['orientation'],
                             **geometry)
    x = sim.positions
    x[:, 2] = -0.298 + 0.03 * np.sin(2 * np.pi * x[:, 0]) * np.cos(2 * np.pi * x[:, 1])
    sim.set_positions(x)
    return sim


def _render_ms(cam, sim, colors=None, repeats: int = 15) -> float:
    cam.render(sim, colors)                                  # compiled, scratch allocated
    times = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        cam.render(sim, colors)
        times.append(time.perf_counter() - t0)
    return 1e3 * statistics.median(times)


def part_camera(watch_s: float = 6.0) -> None:
    import numba
    from ..camera import Camera
    from ..ros.conversions import vertex_colors
    print('\n## camera: the virtual RGB-D camera (cosserat_ros.camera)\n')
    sim, spec, p = _table_scene()
    cam = spec['camera']
    colors = vertex_colors(p['coloring'], sim, sim.energy_and_densities()[1])
    ms = _render_ms(cam, sim, colors)
    tick = 1e3 / p['publish_rate']
    print(f'config/table.yaml, its camera "side" ({cam.width} x {cam.height}), the cloth '
          f'landed: depth + colour {ms:.2f} ms on {numba.get_num_threads()} numba threads '
          f'(median of 15), {ms / tick:.1%} of one publish tick ({tick:.1f} ms); at the '
          f'camera\'s {spec["rate"]:g} Hz, {ms * spec["rate"] / 1e3:.1%} of one core.\n')
    print('Growth: config/table.yaml\'s obstacles and camera pose, its cloth replaced by an '
          'n x n sheet of one shape at every n (the table top, waved: z = -0.298 + 0.03 '
          'sin(2 pi x) cos(2 pi y)), so that every case sees the same surfaces (ms, median '
          'of 15 renders).\n')
    print('| cloth | triangles | ' + ' | '.join(f'{w} x {h}' for w, h in RESOLUTIONS) + ' |')
    print('|---' * (2 + len(RESOLUTIONS)) + '|')
    by_n = {}
    for n in CLOTHS:
        s = _waved(sim, n)
        line = []
        for w, h in RESOLUTIONS:
            c = Camera(w, h, cam.fov, cam.position, cam.orientation)
            t = _render_ms(c, s)
            line.append(t)
        by_n[n] = line
        print(f'| {n} x {n} | {s.mesh.n_faces} | ' + ' | '.join(f'{t:.2f}' for t in line)
              + ' |', flush=True)
    a, b = CLOTHS
    print(f'| {b} x {b} / {a} x {a} | {(b / a) ** 2:.0f} | ' + ' | '.join(
        f'{y / x:.2f}' for x, y in zip(by_n[a], by_n[b])) + ' |')
    print('| ms per megapixel, ' + f'{b} x {b}' + ' | | ' + ' | '.join(
        f'{t / (w * h / 1e6):.1f}' for t, (w, h) in zip(by_n[b], RESOLUTIONS)) + ' |')
    print(f'\nPixels times triangles would make the ratio row {(b / a) ** 2:.0f} at every '
          'image size; pixels plus triangles keeps it near 1, and the cost per megapixel '
          'near constant.', flush=True)
    if watch_s > 0:
        _node_with_camera(watch_s)


def _node_with_camera(watch_s: float) -> None:
    import yaml
    from .bench_node import run_node
    os.environ.setdefault('ROS_DOMAIN_ID', str(100 + os.getpid() % 100))
    os.environ.setdefault('ROS_AUTOMATIC_DISCOVERY_RANGE', 'LOCALHOST')
    with open(_share('cloth.yaml')) as fh:
        tree = yaml.safe_load(fh)
    with tempfile.TemporaryDirectory() as tmp:
        plain = os.path.join(tmp, 'plain.yaml')
        with open(plain, 'w') as fh:
            yaml.safe_dump(tree, fh)
        params = tree['cloth_node']['ros__parameters']
        params['cameras'] = {'names': ['front'], 'front': {
            'width': 640, 'height': 480, 'fov': 60.0, 'rate': 15.0,
            'position': [0.0, -2.2, -0.4],
            # looking along +y at the hanging cloth: optical z = y, x = x, y down = -z
            'orientation': [-0.7071067811865476, 0.0, 0.0, 0.7071067811865476]}}
        camera = os.path.join(tmp, 'camera.yaml')
        with open(camera, 'w') as fh:
            yaml.safe_dump(tree, fh)
        print('\nThe installed node on config/cloth.yaml, without a camera and with one '
              f'640 x 480 camera at 15 Hz, alternated, {watch_s:g} s each (target: the '
              'RTF with the camera at least 0.95 of the RTF without).\n')
        run_node(camera, 2.0)             # compile caches warm, not measured
        print('| round | RTF without | RTF with | with / without |')
        print('|---|---|---|---|')
        ratios = []
        for k in range(3):
            _, _, rtf0, _ = run_node(plain, watch_s)
            _, _, rtf1, _ = run_node(camera, watch_s)
            ratios.append(rtf1 / rtf0)
            print(f'| {k + 1} | {rtf0:.3f} | {rtf1:.3f} | {rtf1 / rtf0:.3f} |', flush=True)
        print(f'\nMean with / without: {np.mean(ratios):.3f}.', flush=True)


if __name__ == '__main__':
    part_camera()
