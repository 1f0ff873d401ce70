"""``make bench``, part ``batch``: the batch engine's throughput and overhead, in one run.

On the first example spec (``config/batch/table_drop.yaml``: 24 x 24, 4 s episodes, a
table drop and two pick-and-place moves), the same first ``k`` episodes, each run below
once per round, the rounds one after the other (so the host's drift over the minutes
falls on every run alike):

* ``loop``: :func:`..batch.run_episode` in a plain loop in this process (no Ray), on
  one numba thread;
* ``1 worker``: ``run_batch(workers=1, threads=1)`` on a private Ray instance: the Ray
  overhead is its wall time over the loop's, with and without the instance's start and
  stop;
* ``2 workers``: ``run_batch(workers=2)`` (one thread each, the default on 2 cores):
  the speed-up over one worker, and episodes per core-hour;
* ``1 worker x all cores``: ``run_batch(workers=1)`` (the default threads: every core
  on one episode), for what the threads buy an episode of this size;
* time to the first finished episode: the installed ``batch run`` of the spec's first
  episodes (one per core, the default workers), from the process's start to its first
  progress line, with a warm compile cache (Ray's start included).

Each run writes into a fresh temporary directory; its Ray temporary directory is its own.
"""
from __future__ import annotations

import json
import os
from pathlib import Path
import shutil
import subprocess
import sys
import tempfile
import time

__all__ = ['part_batch']

SPEC = 'config/batch/table_drop.yaml'


def _spec_path() -> Path:
    here = Path(__file__).resolve().parents[2] / SPEC
    if here.exists():
        return here
    from ..ros.scene import resolve_path
    return Path(resolve_path(SPEC))


def part_batch(episodes: int = 8, rounds: int = 2) -> dict:
    """Print the table of the part (module docstring) and return its figures."""
    import numba
    import yaml
    from ..batch import load_spec, plan, run_batch, run_episode
    cores = os.cpu_count() or 1
    spec = load_spec(_spec_path())
    spec['episodes'] = episodes
    eps = plan(spec)
    tmp = Path(tempfile.mkdtemp(prefix='cosbench'))
    ray_tmp = tempfile.mkdtemp(prefix='cosray', dir='/tmp')
    old_cwd = os.getcwd()
    os.chdir(tmp)                 # Ray's workers import what this process imports
    out = {}
    try:
        run_episode(eps[0], tmp / 'warm')           # the kernels compiled or loaded
        was = numba.get_num_threads()
        runs = (('ray1', 1, 1), ('ray2', 2, 1), ('ray1all', 1, None))
        for key in ('loop',) + tuple(r[0] for r in runs):
            out[key] = out[f'{key}_episodes'] = 0.0
        # rounds in alternation: a host's drift over the minutes falls on every run alike
        for rnd in range(rounds):
            numba.set_num_threads(1)
            t0 = time.perf_counter()
            for ep in eps:
                out['loop_episodes'] += run_episode(ep, tmp / f'loop{rnd}')['wall_time']
            out['loop'] += time.perf_counter() - t0
            numba.set_num_threads(was)
            for key, w, th in runs:
                t0 = time.perf_counter()
                s = run_batch(spec, tmp / f'{key}_{rnd}', workers=w, threads=th,
                              ray_temp_dir=ray_tmp)
                out[key] += time.perf_counter() - t0
                lines = [json.loads(ln) for ln in open(tmp / f'{key}_{rnd}' / 'manifest.jsonl')]
                out[f'{key}_episodes'] += sum(ln['wall_time'] for ln in lines)
                assert s['ok'] == len(eps), f'{key}: {s}'
        # a run of the spec's first episodes, one per core (what the default runs at once)
        first = dict(spec, episodes=cores)
        path = tmp / 'first.yaml'
        path.write_text(yaml.safe_dump(first))
        exe = Path(sys.prefix) / 'lib' / 'cosserat_ros' / 'batch'
        cmd = ([str(exe)] if exe.exists() else [sys.executable, '-m', 'cosserat_ros.batch.cli'])
        t0 = time.perf_counter()
        proc = subprocess.Popen(cmd + ['run', str(path), '-o', str(tmp / 'first'),
                                       '--progress', 'jsonl'], stdout=subprocess.PIPE,
                                stderr=subprocess.DEVNULL, text=True,
                                env=dict(os.environ, RAY_TMPDIR=ray_tmp))
        proc.stdout.readline()
        out['first'] = time.perf_counter() - t0
        proc.wait(timeout=300)
    finally:
        os.chdir(old_cwd)
        shutil.rmtree(tmp, ignore_errors=True)
        shutil.rmtree(ray_tmp, ignore_errors=True)
    n = len(eps) * rounds
    print(f'\n## batch: {SPEC}, its first {len(eps)} episodes ({spec["duration"]:g} s each, '
          f'{spec["scene"]["mesh.nx"]} x {spec["scene"]["mesh.ny"]}), {rounds} rounds of '
          f'the runs in alternation, {cores} cores\n')
    print('| run | wall s | episodes/s | vs loop | episodes per core-hour |')
    print('|---|---|---|---|---|')
    for key, label in (('loop', 'plain loop, 1 numba thread'),
                       ('ray1', 'Ray, 1 worker x 1 thread'),
                       ('ray2', 'Ray, 2 workers x 1 thread'),
                       ('ray1all', f'Ray, 1 worker x {cores} threads')):
        wall = out[key]
        print(f'| {label} | {wall:.1f} | {n / wall:.3f} | {wall / out["loop"]:.3f} | '
              f'{n / wall / cores * 3600:.0f} |')
    # the episodes' own time inside Ray, without the instance's start and stop
    print(f'\nRay overhead, one worker against the loop: {out["ray1"] / out["loop"] - 1:+.1%} '
          f'of wall time with the instance\'s start and stop, '
          f'{out["ray1_episodes"] / out["loop_episodes"] - 1:+.1%} in the episodes themselves '
          f'(their own timings, a worker\'s first kernel load included)')
    print(f'two workers against one: {out["ray1"] / out["ray2"]:.2f}x')
    print(f'time to the first finished episode (warm cache, Ray\'s start included): '
          f'{out["first"]:.1f} s')
    return out


if __name__ == '__main__':
    import argparse
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument('--episodes', type=int, default=8)
    ap.add_argument('--rounds', type=int, default=2)
    a = ap.parse_args()
    part_batch(a.episodes, a.rounds)
