"""``batch``: randomized cloth episodes on Ray, and what to look at afterwards::

    batch run SPEC.yaml -o OUT [--workers N] [--threads T] [--address ADDR] [--resume]
              [--max-retries K] [--episode-timeout S] [--startup-timeout S]
              [--progress bar|jsonl|none]
    batch status OUT                 # counts by status, rate, what failed and why
    batch verify OUT                 # exit 0 only if every ok episode's bag is sound
    batch montage OUT -o FILE.png    # the episodes' last frames in a grid

``run`` without ``--address`` starts a private Ray instance for the run and stops it at
the end; ``--address auto`` / ``HOST:PORT`` / ``ray://...`` joins a running cluster. A bad
spec, option or directory is refused before any work: one line on stderr, exit 2.
Exit 1 if an episode failed, 0 if every one is ok. (:mod:`cosserat_ros.batch`)
"""
from __future__ import annotations

import argparse
import collections
import json
import math
from pathlib import Path
import sys
from typing import List, Optional

__all__ = ['main', 'status', 'verify', 'montage']


class _Parser(argparse.ArgumentParser):
    def error(self, message):                       # one line, exit 2
        print(f'batch: {message}', file=sys.stderr)
        raise SystemExit(2)


def _parser() -> argparse.ArgumentParser:
    p = _Parser(prog='batch', description='Randomized cloth episodes on Ray.')
    sub = p.add_subparsers(dest='command', required=True, parser_class=_Parser)
    r = sub.add_parser('run', help='run (or with --resume finish) a spec')
    r.add_argument('spec')
    r.add_argument('-o', '--out', required=True, help='the run directory')
    r.add_argument('--workers', type=int, default=None,
                   help='episodes at once (default: the CPUs Ray has)')
    r.add_argument('--threads', type=int, default=None,
                   help='numba threads per worker (default: the CPUs over the workers)')
    r.add_argument('--address', default=None,
                   help='a Ray cluster to join: auto, HOST:PORT or ray://...')
    r.add_argument('--resume', action='store_true',
                   help='finish the run in OUT without redoing its finished episodes')
    r.add_argument('--max-retries', type=int, default=2,
                   help='more attempts of an episode whose worker or node died or that '
                   'timed out (default 2)')
    r.add_argument('--episode-timeout', type=float, default=None,
                   help='wall-clock seconds an episode may run, counted from its start '
                   'in its worker, after the worker\'s start-up and kernel loading '
                   '(default: no limit)')
    r.add_argument('--startup-timeout', type=float, default=None,
                   help='wall-clock seconds from an attempt\'s submission to its '
                   'episode\'s start: the wait for a CPU, the worker\'s start, its '
                   'imports and kernels (default: 1800 with --episode-timeout, else no '
                   'limit)')
    r.add_argument('--progress', default='bar', choices=('bar', 'jsonl', 'none'))
    s = sub.add_parser('status', help='counts by status, rate, failures')
    s.add_argument('out')
    v = sub.add_parser('verify', help='check every ok episode\'s bag')
    v.add_argument('out')
    m = sub.add_parser('montage', help='a grid of the episodes\' last frames')
    m.add_argument('out')
    m.add_argument('-o', '--output', required=True, help='the PNG to write')
    m.add_argument('--max', type=int, default=36, help='at most this many episodes')
    return p


def _lines(out: str) -> List[dict]:
    from .engine import MANIFEST, read_manifest
    if not (Path(out) / MANIFEST).exists():
        raise SystemExit(f'batch: {out} has no {MANIFEST}: not a batch run directory')
    return read_manifest(out)


def _planned(out: str) -> Optional[int]:
    """How many episodes the run's spec (``OUT/spec.json``) plans, None without one."""
    from .engine import SPEC_FILE
    try:
        return json.loads((Path(out) / SPEC_FILE).read_text())['episodes']
    except (OSError, ValueError, KeyError):
        return None


def status(out: str) -> int:
    """Print the counts by status, the rate and each failure's reason; 0 if all ok."""
    lines = _lines(out)
    total = _planned(out)
    total = len(lines) if total is None else total
    counts = collections.Counter(ln['status'] for ln in lines)
    wall = sum(ln.get('wall_time') or 0.0 for ln in lines)
    sim = sum(ln.get('sim_time') or 0.0 for ln in lines)
    nodes = collections.Counter(ln.get('node') for ln in lines if ln.get('node'))
    print(f'{out}: {total} episodes: {counts.get("ok", 0)} ok, {counts.get("failed", 0)} '
          f'failed, {total - len(lines)} not run')
    if wall > 0:
        print(f'  {len(lines) / wall * 3600:.0f} episodes per worker-hour; simulated '
              f'{sim:.1f} s in {wall:.1f} s of episode time (RTF {sim / wall:.2f})')
    if nodes:
        print(f'  on {len(nodes)} Ray node(s): ' + ', '.join(
            f'{n[:8]} {c}' for n, c in nodes.most_common()))
    retried = [ln for ln in lines if (ln.get('attempts') or 1) > 1]
    if retried:
        print('  retried: ' + ', '.join(f'{ln["id"]} ({ln["attempts"]} attempts)'
                                         for ln in retried))
    for ln in lines:
        if ln['status'] != 'ok':
            print(f'  failed {ln["id"]}: {ln["error"]}')
    return 0 if counts.get('ok', 0) == total else 1


def verify(out: str) -> int:
    """Check every ``ok`` episode: its bag complete (metadata.yaml, the MCAP read to
    its end with every CRC validated, the message counts as listed), its sha256 as in
    the manifest; and one line per planned episode. Prints each problem; 0 if none."""
    from .episode import file_sha256
    try:
        from mcap.reader import make_reader
    except ImportError:
        print('batch: verify needs the mcap package (the batch extra)', file=sys.stderr)
        return 2
    import yaml
    lines = _lines(out)
    problems = []
    ids = collections.Counter(ln['id'] for ln in lines)
    problems += [f'{i}: {c} manifest lines' for i, c in ids.items() if c > 1]
    total = _planned(out)
    if total is None:
        problems.append('no spec.json')
    elif len(ids) != total:
        problems.append(f'{total - len(ids)} of {total} episodes have no manifest line')
    checked = 0
    for ln in lines:
        if ln['status'] != 'ok':
            continue
        bag = Path(out) / 'episodes' / ln['id'] / 'bag'
        mcap = bag / 'bag.mcap'
        try:
            meta = yaml.safe_load((bag / 'metadata.yaml').read_text())
            info = meta['rosbag2_bagfile_information']
            if file_sha256(mcap) != ln['bag_sha256']:
                problems.append(f'{ln["id"]}: sha256 differs from the manifest')
                continue
            counts = collections.Counter()
            with open(mcap, 'rb') as fh:
                reader = make_reader(fh, validate_crcs=True)
                for _schema, channel, _message in reader.iter_messages():
                    counts[channel.topic] += 1
                summary = reader.get_summary()
            if summary is None:
                problems.append(f'{ln["id"]}: the MCAP has no summary (not closed)')
                continue
            listed = {t['topic_metadata']['name']: t['message_count']
                      for t in info['topics_with_message_count']}
            if dict(counts) != {k: v for k, v in listed.items() if v}:
                problems.append(f'{ln["id"]}: messages {dict(counts)} but metadata.yaml '
                                f'lists {listed}')
                continue
            checked += 1
        except Exception as exc:                   # noqa: BLE001 (reported per episode)
            problems.append(f'{ln["id"]}: {type(exc).__name__}: {exc}')
    for p in problems:
        print(f'  {p}')
    print(f'{out}: {checked} ok bags verified, {len(problems)} problem(s)')
    return 0 if not problems else 1


def montage(out: str, output: str, most: int = 36) -> int:
    """A grid of the last mesh of each ``ok`` episode (up to ``most``), drawn as
    ``render`` draws a frame (with the obstacles of the time), titled with the id."""
    from ..tools.render import (_decode_mesh, _limits, obstacle_polygons, plt,
                                read_bag, render_frame)
    lines = sorted((ln for ln in _lines(out) if ln['status'] == 'ok'),
                   key=lambda ln: ln['index'])[:most]
    if not lines:
        print(f'batch: {out} has no ok episode to draw', file=sys.stderr)
        return 1
    cols = math.ceil(math.sqrt(len(lines)))
    rows = math.ceil(len(lines) / cols)
    fig = plt.figure(figsize=(3.2 * cols, 3.2 * rows))
    from .episode import NODE
    for k, ln in enumerate(lines):
        meshes, _e, obstacles = read_bag(Path(out) / 'episodes' / ln['id'] / 'bag',
                                         f'/{NODE}/mesh', f'/{NODE}/energy',
                                         f'/{NODE}/obstacle_markers')
        frame = _decode_mesh(meshes[-1])
        centre, radius = _limits([frame])
        polys = obstacle_polygons(obstacles[-1][1], centre, radius) if obstacles else []
        ax = fig.add_subplot(rows, cols, k + 1, projection='3d')
        render_frame(ax, *frame, centre, radius, polys)
        ax.set_title(f'{ln["id"]}  t = {frame[0]:.2f} s', fontsize=8)
        for axis in (ax.xaxis, ax.yaxis, ax.zaxis):
            axis.set_ticklabels([])
            axis.label.set_visible(False)
    fig.tight_layout()
    Path(output).parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(output, dpi=80)
    plt.close(fig)
    print(f'{output}: {len(lines)} episodes')
    return 0


def _interrupt(signum, frame):
    raise KeyboardInterrupt


def main(argv=None) -> int:
    args = _parser().parse_args(argv)
    from .spec import SpecError
    try:
        if args.command == 'run':
            import signal
            signal.signal(signal.SIGTERM, _interrupt)     # stop as on Ctrl-C: cleanly
            from .engine import run_batch
            summary = run_batch(args.spec, args.out, workers=args.workers,
                                threads=args.threads,
                                address=args.address, resume=args.resume,
                                max_retries=args.max_retries,
                                episode_timeout=args.episode_timeout,
                                startup_timeout=args.startup_timeout,
                                progress=args.progress)
            print(f'batch: {summary["episodes"]} episodes in {summary["out"]}: '
                  f'{summary["ok"]} ok, {summary["failed"]} failed ({summary["ran"]} run '
                  f'now, {summary["wall_time"]:.1f} s); see batch status {summary["out"]}',
                  file=sys.stderr)
            return 0 if summary['failed'] == 0 else 1
        if args.command == 'status':
            return status(args.out)
        if args.command == 'verify':
            return verify(args.out)
        return montage(args.out, args.output, args.max)
    except SpecError as exc:
        print(f'batch: {exc}', file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print(f'batch: interrupted; what finished is in {args.out}/manifest.jsonl, and '
              '`batch run ... --resume` finishes the run', file=sys.stderr)
        return 130


if __name__ == '__main__':
    sys.exit(main())
