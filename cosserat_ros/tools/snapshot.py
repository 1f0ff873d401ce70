"""``python -m cosserat_ros.tools.snapshot``: a params file's scene, simulated for a while
without ROS, seen by one of its cameras: the depth and colour images side by side in a
PNG (the README's picture), and optionally the raw arrays in an ``.npz``.

    python -m cosserat_ros.tools.snapshot config/table.yaml --camera side --seconds 2 \\
        -o docs/camera_table.png

A bad argument or params file exits 2 with one line saying why.
"""
from __future__ import annotations

import argparse
import sys

import numpy as np

__all__ = ['main', 'snapshot']


def snapshot(params_file: str, camera: str, seconds: float):
    """(depth, rgb, camera, p) of ``camera`` over the scene of ``params_file`` after
    ``seconds`` of simulation, coloured as the node's ``coloring`` colours it."""
    from ..ros.cameras import camera_specs
    from ..ros.conversions import vertex_colors
    from ..ros.params import ConfigError
    from ..ros.scene import build_simulator, check_parameters, read_params_file
    given = read_params_file(params_file)
    p = check_parameters(given)
    specs = camera_specs(p)
    if camera not in specs:
        raise ConfigError(f'{params_file} has no camera {camera!r} (cameras.names: '
                          f'{sorted(specs) or "none"})')
    sim = build_simulator(p, given)
    sim.step(int(round(seconds / sim.dt)))
    cam = specs[camera]['camera']
    densities = sim.energy_and_densities()[1]
    depth, rgb = cam.render(sim, vertex_colors(p['coloring'], sim, densities))
    return depth, rgb, cam, p


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(prog='snapshot', description=__doc__.split('\n\n')[0])
    ap.add_argument('params', help='a params file with cameras.* (e.g. config/table.yaml)')
    ap.add_argument('--camera', required=True, help='the camera (one of cameras.names)')
    ap.add_argument('--seconds', type=float, default=2.0, help='simulated time first [s]')
    ap.add_argument('-o', '--output', required=True, help='the PNG to write')
    ap.add_argument('--npz', help='also write depth and rgb to this .npz')
    a = ap.parse_args(argv)
    from ..ros.params import ConfigError
    if not (a.seconds >= 0 and np.isfinite(a.seconds)):
        print(f'snapshot: --seconds must be >= 0, got {a.seconds}', file=sys.stderr)
        return 2
    try:
        depth, rgb, cam, _ = snapshot(a.params, a.camera, a.seconds)
    except (ConfigError, OSError) as exc:
        print(f'snapshot: {exc}', file=sys.stderr)
        return 2
    import matplotlib
    matplotlib.use('Agg')
    import matplotlib.pyplot as plt
    fig, ax = plt.subplots(1, 2, figsize=(11, 4.3), constrained_layout=True)
    im = ax[0].imshow(np.ma.masked_invalid(depth), cmap='viridis')
    ax[0].set_title(f'depth/image_raw (32FC1), {cam.width} x {cam.height}')
    fig.colorbar(im, ax=ax[0], shrink=0.85, label='depth along the optical axis [m]')
    ax[1].imshow(rgb)
    ax[1].set_title('color/image_raw (rgb8)')
    for a_ in ax:
        a_.set_xticks([])
        a_.set_yticks([])
    fig.savefig(a.output, dpi=80)
    if a.npz:
        np.savez_compressed(a.npz, depth=depth, rgb=rgb, K=cam.intrinsics)
    print(f'{a.output}: camera {a.camera} after {a.seconds:g} s')
    return 0


if __name__ == '__main__':
    sys.exit(main())
