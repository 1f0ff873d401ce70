"""``render``: pictures of a recorded (or live) cloth, offscreen, without RViz.

    render BAG -o OUT [--times T ...] [--frames N] [--node cloth_node]
    render --live SECONDS -o OUT [--wait S] [--timeout S]   # the running node instead

Writes into OUT: ``cloth_<t>s.png`` (shaded, coloured like the marker, one per chosen
simulation time; default first, middle and last), ``cloth.gif`` (and ``cloth.mp4`` when
ffmpeg is on the PATH), and ``energy.png`` (every energy term against simulation time).
The obstacles of ``~/obstacle_markers`` (spheres, boxes, cylinders, meshes; a plane as a
square patch under the view) are drawn in grey with each frame, as they were at its time.
Uses matplotlib's Agg backend: no display needed.

Times are simulation time, the meshes' header stamps [s]. ``--times T`` draws the mesh
nearest T; a T more than half a mesh interval past the last mesh (or before the first) is
refused with one line naming the meshes' time range and exit 2, not drawn as the nearest
frame. ``--live SECONDS`` collects SECONDS of simulation time from the first mesh (the
meshes stamped within SECONDS of it; a ``~/reset`` does not restart the count), however
long that takes on the wall clock; ``--wait`` (for the first mesh) and ``--timeout`` (the
whole collection) are the wall-clock limits.

On a terminal, a progress line on stderr counts what is done (messages read, meshes
decoded, pictures and animation frames drawn of how many, simulation seconds collected);
a pipe or a file gets none of it (:mod:`.progress`).
"""
from __future__ import annotations

import argparse
import os
from pathlib import Path
import shutil
import sys
import time
from typing import List, Tuple

import matplotlib
matplotlib.use('Agg')
import matplotlib.pyplot as plt  # noqa: E402
from mpl_toolkits.mplot3d.art3d import Poly3DCollection  # noqa: E402
import numpy as np  # noqa: E402

__all__ = ['main', 'read_bag', 'render', 'render_frame', 'energy_plot', 'obstacle_polygons',
           'mesh_times', 'check_times', 'TimesOutsideBag']

ENERGY_KEYS = ('kinetic', 'stretching', 'bending', 'coupling', 'gravity', 'total',
               'external_work', 'dissipated')


def _decode_mesh(raw: bytes) -> Tuple[float, np.ndarray, np.ndarray]:
    """(sim time [s], triangles (m, 3, 3), corner colours (m, 3, 4)) of a MarkerArray."""
    from rclpy.serialization import deserialize_message
    from visualization_msgs.msg import Marker, MarkerArray
    msg = deserialize_message(raw, MarkerArray)
    tri = next((m for m in msg.markers if m.type == Marker.TRIANGLE_LIST), None)
    if tri is None:
        raise SystemExit('render: a mesh message has no TRIANGLE_LIST marker (is this the '
                         "cloth node's ~/mesh?)")
    pts = np.array([(p.x, p.y, p.z) for p in tri.points]).reshape(-1, 3, 3)
    if tri.colors:
        col = np.array([(c.r, c.g, c.b, c.a) for c in tri.colors]).reshape(-1, 3, 4)
    else:
        col = np.tile([tri.color.r, tri.color.g, tri.color.b, tri.color.a], (len(pts), 3, 1))
    return tri.header.stamp.sec + 1e-9 * tri.header.stamp.nanosec, pts, col


def _decode_energy(raw: bytes) -> Tuple[float, dict]:
    from rclpy.serialization import deserialize_message
    from diagnostic_msgs.msg import DiagnosticArray
    msg = deserialize_message(raw, DiagnosticArray)
    vals = {}
    for kv in msg.status[0].values if msg.status else []:
        try:
            vals[kv.key] = float(kv.value)
        except ValueError:
            pass
    return vals.get('sim_time', msg.header.stamp.sec + 1e-9 * msg.header.stamp.nanosec), vals



class TimesOutsideBag(ValueError):
    """A time asked for (``--times``) lies outside the meshes' time range."""


def mesh_times(meshes: List[bytes]) -> np.ndarray:
    """The simulation times [s] of serialised ``~/mesh`` MarkerArrays (their first marker's
    header stamp), read without deserialising them; NaN for a message without a marker."""
    from .record import stamp_reader
    read = stamp_reader('visualization_msgs/msg/MarkerArray')
    ts = [read(raw) for raw in meshes]
    return np.array([np.nan if t is None else t * 1e-9 for t in ts], dtype=float)


def check_times(times, ts: np.ndarray) -> None:
    """Raise :class:`TimesOutsideBag` if a time of ``times`` [s] lies more than half the
    median mesh interval past the last of the mesh times ``ts`` [s] or before the first
    (its nearest mesh would not be the cloth at that time)."""
    ts = ts[np.isfinite(ts)]
    if not len(ts) or not times:
        return
    steps = np.diff(np.sort(np.unique(ts)))
    slack = 0.5 * float(np.median(steps)) if len(steps) else 0.0
    lo, hi = float(ts.min()), float(ts.max())
    late = [t for t in times if t > hi + slack]
    early = [t for t in times if t < lo - slack]
    if late or early:
        which = (f'{", ".join(f"{t:g}" for t in late)} s past the last mesh' if late else
                 f'{", ".join(f"{t:g}" for t in early)} s before the first mesh')
        raise TimesOutsideBag(f'--times {which}: the meshes span {lo:.3f} s to {hi:.3f} s '
                              'of simulation time')

def read_bag(path: Path, mesh_topic: str, energy_topic: str, obstacle_topic: str = '',
             progress=None):
    """Raw mesh and energy messages of a rosbag2 directory, in recording order, and the
    obstacle marker arrays as (the index of the first mesh recorded after it, raw): a
    mesh is drawn with the last array recorded before it. By recording order, not by
    time: a bag spanning a ``~/reset`` has the node's times twice (``record`` keeps its
    log times going forward, the messages keep their stamps). ``progress``: a
    :class:`.progress.Progress` told how many messages were read."""
    from rosbags.highlevel import AnyReader
    meshes, energies, obstacles = [], [], []
    with AnyReader([Path(path)]) as reader:
        conns = [c for c in reader.connections
                 if c.topic in (mesh_topic, energy_topic, obstacle_topic)]
        if not any(c.topic == mesh_topic for c in conns):
            raise SystemExit(f'render: {path} has no {mesh_topic} messages')
        total = sum(c.msgcount for c in conns)
        for conn, t, raw in reader.messages(connections=conns):
            if conn.topic == obstacle_topic:
                obstacles.append((len(meshes), bytes(raw)))
            else:
                (meshes if conn.topic == mesh_topic else energies).append(bytes(raw))
            if progress is not None:
                progress.update(f'reading {Path(path).name}: message '
                                f'{len(meshes) + len(energies) + len(obstacles)} of {total}')
    return meshes, energies, obstacles


def _quat_matrix(q) -> np.ndarray:
    x, y, z, w = q
    return np.array([[1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
                     [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
                     [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)]])


def _unit_sphere(k: int = 12) -> np.ndarray:
    """Quads (m, 4, 3) of a unit sphere, k bands of latitude."""
    th = np.linspace(0, np.pi, k + 1)
    ph = np.linspace(0, 2 * np.pi, 2 * k + 1)
    p = np.stack([np.outer(np.sin(th), np.cos(ph)), np.outer(np.sin(th), np.sin(ph)),
                  np.outer(np.cos(th), np.ones_like(ph))], axis=-1)
    return np.stack([p[:-1, :-1], p[1:, :-1], p[1:, 1:], p[:-1, 1:]], axis=2).reshape(-1, 4, 3)


def _unit_box() -> np.ndarray:
    """Quads (6, 4, 3) of the cube [-1, 1]^3."""
    quads = []
    for axis in range(3):
        for side in (-1.0, 1.0):
            u, v = [a for a in range(3) if a != axis]
            q = np.zeros((4, 3))
            q[:, axis] = side
            q[:, u] = (-1, 1, 1, -1)
            q[:, v] = (-1, -1, 1, 1)
            quads.append(q)
    return np.array(quads)


def _unit_cylinder(k: int = 24) -> np.ndarray:
    """Quads (k, 4, 3) of the side of a cylinder of radius 1 from z = -1 to 1."""
    a = np.linspace(0, 2 * np.pi, k + 1)
    c, s = np.cos(a), np.sin(a)
    return np.stack([np.stack([c[:-1], s[:-1], -np.ones(k)], -1),
                     np.stack([c[1:], s[1:], -np.ones(k)], -1),
                     np.stack([c[1:], s[1:], np.ones(k)], -1),
                     np.stack([c[:-1], s[:-1], np.ones(k)], -1)], axis=1)


def obstacle_polygons(raw: bytes, centre: np.ndarray, radius: float) -> List[np.ndarray]:
    """The obstacles of a serialised ``~/obstacle_markers`` MarkerArray as lists of
    polygons (k, n, 3) in the world frame. A marker wider than the view (the node draws a
    plane as a 10 m thin CUBE) is cut to the view's size around the point of it nearest
    the view's centre. Polygons wholly outside the view cube are left out."""
    from rclpy.serialization import deserialize_message
    from visualization_msgs.msg import Marker, MarkerArray
    out = []
    for m in deserialize_message(raw, MarkerArray).markers:
        if m.action != Marker.ADD:
            continue
        p = np.array([m.pose.position.x, m.pose.position.y, m.pose.position.z])
        R = _quat_matrix((m.pose.orientation.x, m.pose.orientation.y, m.pose.orientation.z,
                          m.pose.orientation.w))
        half = 0.5 * np.array([m.scale.x, m.scale.y, m.scale.z])
        local_centre = R.T @ (centre - p)
        shift = np.zeros(3)
        for k in range(3):                                # too wide: a patch of the view
            if half[k] > 2 * radius:
                half[k] = radius
                shift[k] = local_centre[k]
        if m.type == Marker.SPHERE:
            unit = _unit_sphere()
        elif m.type == Marker.CUBE:
            unit = _unit_box()
        elif m.type == Marker.CYLINDER:
            unit = _unit_cylinder()
        elif m.type == Marker.TRIANGLE_LIST and m.points:
            pts = np.array([(q.x, q.y, q.z) for q in m.points]).reshape(-1, 3, 3)
            out.append(pts * np.array([m.scale.x, m.scale.y, m.scale.z]) @ R.T + p)
            continue
        else:
            continue
        out.append((unit * half + shift) @ R.T + p)
    # polygons wholly outside the view cube would be drawn outside the axes: left out
    lo, hi = centre - radius, centre + radius
    kept = []
    for polys in out:
        outside = np.any(np.all(polys < lo, axis=1) | np.all(polys > hi, axis=1), axis=1)
        if not outside.all():
            kept.append(polys[~outside])
    return kept


def _limits(frames):
    pts = np.concatenate([f[1].reshape(-1, 3) for f in frames])
    lo, hi = pts.min(axis=0), pts.max(axis=0)
    c, r = 0.5 * (lo + hi), 0.5 * float((hi - lo).max()) * 1.05 + 1e-9
    return c, r


def render_frame(ax, t, tris, cols, centre, radius, obstacles=()):
    """Draw one cloth state: corner colours averaged per face, Lambert-shaded; the
    obstacles (:func:`obstacle_polygons`) in translucent grey."""
    ax.clear()
    for polys in obstacles:
        ax.add_collection3d(Poly3DCollection(polys, facecolors=(0.55, 0.55, 0.58, 0.35),
                                             edgecolors=(0.4, 0.4, 0.45, 0.25),
                                             linewidths=0.3))
    n = np.cross(tris[:, 1] - tris[:, 0], tris[:, 2] - tris[:, 0])
    n /= np.linalg.norm(n, axis=1, keepdims=True).clip(1e-300)
    light = np.array([0.3, -0.5, 0.8]) / np.linalg.norm([0.3, -0.5, 0.8])
    shade = 0.35 + 0.65 * np.abs(n @ light)
    face = cols.mean(axis=1)
    face[:, :3] *= shade[:, None]
    ax.add_collection3d(Poly3DCollection(tris, facecolors=np.clip(face, 0, 1),
                                         edgecolors='none'))
    for set_lim, k in ((ax.set_xlim, 0), (ax.set_ylim, 1), (ax.set_zlim, 2)):
        set_lim(centre[k] - radius, centre[k] + radius)
    ax.set_box_aspect((1, 1, 1))
    ax.view_init(elev=22, azim=-60)
    ax.set_xlabel('x [m]')
    ax.set_ylabel('y [m]')
    ax.set_zlabel('z [m]')
    ax.set_title(f't = {t:.3f} s')


def energy_plot(energies, path: Path):
    data = [_decode_energy(r) for r in energies]
    fig, ax = plt.subplots(figsize=(7, 4))
    t = np.array([d[0] for d in data], dtype=float)
    # a reset starts the time again: each run its own line, not one drawn back over it
    cut = np.flatnonzero(np.diff(t) < 0) + 1
    drawn = 0
    for key in ENERGY_KEYS:
        vals = [d[1].get(key) for d in data]
        if all(v is not None for v in vals) and vals:
            ax.plot(np.insert(t, cut, np.nan), np.insert(np.array(vals, dtype=float), cut,
                                                         np.nan), label=key)
            drawn += 1
    ax.set_xlabel('simulation time [s]')
    ax.set_ylabel('energy [J]')
    ax.set_title('Cloth energies')
    ax.grid(alpha=0.3)
    if drawn:                                   # no energy in every message: no legend
        ax.legend(fontsize=8, ncol=2)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def render(meshes: List[bytes], energies: List[bytes], out: Path, times=None,
           frames: int = 60, obstacles=(), progress=None) -> List[Path]:
    """Pictures, animation and energy plot of the mesh messages (module docstring);
    ``times``: the simulation times [s] to draw (the nearest mesh each; one outside the
    meshes' range raises :class:`TimesOutsideBag` before anything is written; None: first,
    middle and last); ``obstacles``: (index of the first mesh it applies to, raw
    ~/obstacle_markers) in recording order (:func:`read_bag`); ``progress``: a
    :class:`.progress.Progress` told what is being drawn, of how many."""
    if not meshes:
        raise SystemExit('render: no mesh messages to draw')

    def say(text):
        if progress is not None:
            progress.update(text)
    if times:
        ts = mesh_times(meshes)
        check_times(times, ts)            # before anything is written
        ts = np.where(np.isfinite(ts), ts, np.inf)
    out.mkdir(parents=True, exist_ok=True)
    pick = np.unique(np.linspace(0, len(meshes) - 1, min(frames, len(meshes))).astype(int))
    decoded = {}
    for k, i in enumerate(pick):
        say(f'decoding mesh {k + 1} of {len(pick)}')
        decoded[i] = _decode_mesh(meshes[i])
    written = []
    if times:                             # the nearest of all meshes, not only the frames'
        chosen = sorted({int(np.argmin(np.abs(ts - t))) for t in times})
    else:
        chosen = sorted({int(pick[0]), int(pick[len(pick) // 2]), int(pick[-1])})
    for i in chosen:
        if i not in decoded:
            decoded[i] = _decode_mesh(meshes[i])
    centre, radius = _limits([decoded[i] for i in decoded])
    starts = [i for i, _ in obstacles]
    shapes: dict = {}

    def at(i):                    # the obstacles of the last marker array before mesh i
        k = int(np.searchsorted(starts, i, side='right')) - 1
        if k < 0 and starts:
            k = 0                 # before the first (1 Hz) array: the first one
        if k < 0:
            return []
        if k not in shapes:
            shapes[k] = obstacle_polygons(obstacles[k][1], centre, radius)
        return shapes[k]
    for k, i in enumerate(chosen):
        say(f'picture {k + 1} of {len(chosen)}')
        fig = plt.figure(figsize=(6, 6))
        ax = fig.add_subplot(projection='3d')
        render_frame(ax, *decoded[i], centre, radius, at(i))
        p = out / f'cloth_{decoded[i][0]:.3f}s.png'
        if p in written:          # the same time again, after a reset: the index too
            p = out / f'cloth_{i}_{decoded[i][0]:.3f}s.png'
        fig.savefig(p, dpi=100)
        plt.close(fig)
        written.append(p)
    from matplotlib.animation import FuncAnimation, PillowWriter
    fig = plt.figure(figsize=(5, 5))
    ax = fig.add_subplot(projection='3d')
    seq = [decoded[i] for i in pick]
    anim = FuncAnimation(fig, lambda k: render_frame(ax, *seq[k], centre, radius,
                                                     at(pick[k])), frames=len(seq))
    gif = out / 'cloth.gif'
    anim.save(gif, writer=PillowWriter(fps=12), dpi=70,
              progress_callback=lambda k, n: say(f'GIF frame {k + 1} of {n}'))
    written.append(gif)
    if shutil.which('ffmpeg'):
        mp4 = out / 'cloth.mp4'
        anim.save(mp4, writer='ffmpeg', fps=12, dpi=90,
                  progress_callback=lambda k, n: say(f'MP4 frame {k + 1} of {n}'))
        written.append(mp4)
    plt.close(fig)
    if energies:
        say(f'energy plot of {len(energies)} messages')
        energy_plot(energies, out / 'energy.png')
        written.append(out / 'energy.png')
    return written


def live(seconds: float, node_name: str, wait: float = 60.0, timeout: float = 0.0,
         progress=None):
    """Collect raw mesh and energy messages from the running node: those stamped within
    ``seconds`` of SIMULATION time from the first mesh (the count goes on across a
    ``~/reset``: :class:`.record.SimSpan`); the first mesh past that ends the collection
    and is left out. Wall-clock limits: up to ``wait`` seconds for the first mesh
    (discovery, a node starting), and ``timeout`` seconds (0: none) for the whole
    collection. Returns (meshes, energies, simulation seconds collected); empty lists if
    no mesh came. ``progress``: a :class:`.progress.Progress` told how far it got."""
    import rclpy
    from diagnostic_msgs.msg import DiagnosticArray
    from visualization_msgs.msg import MarkerArray
    from .record import SimSpan, stamp_reader
    limit = int(round(seconds * 1e9))
    read = {'mesh': stamp_reader('visualization_msgs/msg/MarkerArray'),
            'energy': stamp_reader('diagnostic_msgs/msg/DiagnosticArray')}
    span = SimSpan()
    meshes, energies, done = [], [], []

    def keep(kind, into):
        def on_message(raw):
            if done:
                return
            t = read[kind](raw)
            if t is not None:
                if kind == 'mesh' and span.peek(kind, t) > limit:
                    done.append(True)             # the first mesh past the end
                    return
                if kind == 'energy' and (not meshes or span.after(kind, t) > limit):
                    return                        # before the first mesh, or past the end
                span.add(kind, t)
            into.append(raw)
        return on_message
    rclpy.init()
    node = rclpy.create_node('cloth_render')
    node.create_subscription(MarkerArray, f'/{node_name}/mesh', keep('mesh', meshes), 10,
                             raw=True)
    node.create_subscription(DiagnosticArray, f'/{node_name}/energy',
                             keep('energy', energies), 10, raw=True)
    start = time.monotonic()
    end = start + wait
    try:
        while not meshes and time.monotonic() < end:
            if progress is not None:
                progress.update(f'waiting for /{node_name}/mesh '
                                f'({time.monotonic() - start:.0f} s of --wait {wait:g})')
            rclpy.spin_once(node, timeout_sec=0.05)
        end = time.monotonic() + timeout if timeout > 0 else None
        while meshes and not done and (end is None or time.monotonic() < end):
            if progress is not None:
                progress.update(f'collected {span.elapsed("mesh") * 1e-9:.1f} of '
                                f'{seconds:g} s of simulation time, {len(meshes)} meshes')
            rclpy.spin_once(node, timeout_sec=0.05)
    finally:
        node.destroy_node()
        rclpy.try_shutdown()
    return meshes, energies, span.elapsed('mesh') * 1e-9


def main(argv=None) -> int:
    """The ``render`` command (module docstring). Exit codes: 0 drawn; 1 no mesh came
    (``--live``); 2 a usage error, a bag it cannot read, ``--times`` outside the meshes'
    time range."""
    ap = argparse.ArgumentParser(
        prog='render', description='Pictures of the cloth. Times are simulation time (the '
        "meshes' stamps); the wall-clock limits of --live are --wait and --timeout.")
    ap.add_argument('bag', nargs='?', help='rosbag2 directory')
    ap.add_argument('-o', '--output', required=True, help='output directory')
    ap.add_argument('--times', type=float, nargs='*', metavar='T',
                    help='simulation times to draw [s], each as the nearest mesh; a time '
                    'more than half a mesh interval past the last mesh (or before the '
                    'first) is an error (exit 2)')
    ap.add_argument('--frames', type=int, default=60, help='frames in the animation')
    ap.add_argument('--node', default='cloth_node', help='node whose topics to draw')
    ap.add_argument('--live', type=float, metavar='SECONDS',
                    help='subscribe to the running node instead of reading a bag, for '
                    'SECONDS of SIMULATION time from its first mesh (however long that '
                    'takes on the wall clock)')
    ap.add_argument('--wait', type=float, default=60.0, metavar='S',
                    help='with --live: WALL-CLOCK seconds to wait for the first mesh '
                    '(default 60)')
    ap.add_argument('--timeout', type=float, default=0.0, metavar='S',
                    help='with --live: WALL-CLOCK limit on the collection, however far the '
                    'simulation got; 0 (default): none')
    a = ap.parse_args(argv)
    if a.frames < 1:
        ap.error(f'--frames must be at least 1, got {a.frames}')
    if a.live is not None and a.live <= 0:
        ap.error(f'--live takes a positive number of simulation seconds, got {a.live:g}')
    if a.wait < 0 or a.timeout < 0:
        ap.error('--wait and --timeout must be >= 0 [s]')
    from .progress import Progress
    progress = Progress('render')            # on a terminal only
    obstacles = ()
    if a.live is not None:
        meshes, energies, got = live(a.live, a.node, a.wait, a.timeout, progress)
        progress.clear()
        if not meshes:
            print(f'render: error: no mesh from /{a.node}/mesh within {a.wait:g} s (--wait, '
                  'wall clock); is the node running (same ROS_DOMAIN_ID)?', file=sys.stderr)
            return 1
        if got < a.live and a.timeout > 0:
            print(f'render: warning: stopped by --timeout {a.timeout:g} s (wall clock) '
                  f'after {got:.3f} of the {a.live:g} s of simulation time asked',
                  file=sys.stderr)
    elif a.bag:
        if not os.path.isdir(a.bag):
            print(f'render: error: {a.bag} is not a bag directory', file=sys.stderr)
            return 2
        try:
            meshes, energies, obstacles = read_bag(Path(a.bag), f'/{a.node}/mesh',
                                                   f'/{a.node}/energy',
                                                   f'/{a.node}/obstacle_markers', progress)
        except SystemExit:                   # a bag without meshes: its one line
            progress.clear()
            raise
        except Exception as exc:             # not a rosbag2 directory, a broken file
            progress.clear()
            print(f'render: error: cannot read {a.bag}: {type(exc).__name__}: {exc}',
                  file=sys.stderr)
            return 2
    else:
        ap.error('give a BAG directory or --live SECONDS')
    try:
        written = render(meshes, energies, Path(a.output), a.times, a.frames, obstacles,
                         progress)
    except TimesOutsideBag as exc:
        progress.clear()
        print(f'render: error: {exc}', file=sys.stderr)
        return 2
    except SystemExit:                       # a mesh message without a triangle list
        progress.clear()
        raise
    progress.done(f'drew {len(written)} files into {a.output}')
    for p in written:
        print(f'render: wrote {p}')
    return 0

if __name__ == '__main__':
    sys.exit(main())
