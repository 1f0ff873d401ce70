"""The batch driver: episodes as Ray tasks, exactly one manifest line each.

Ray is the engine (its scheduler, its cluster; no pool or protocol of ours). Without an
address the driver starts a private Ray instance for the run (``ray.init`` with the
machine's cores, its own temporary directory, no dashboard) and shuts it down at the end;
Ray starts its processes sharing the driver's fate, so a driver killed outright takes them
with it. With ``address`` (``auto``, ``HOST:PORT`` or ``ray://...``) it joins that cluster,
whose nodes have the package installed.

**Workers.** Ray reuses its worker processes from task to task, so each compiles (or loads
from the compile cache beside the installed package) the kernels once. Each task asks Ray
for ``threads`` CPUs and runs numba on that many threads: ``workers x threads`` never
exceeds the CPUs Ray has (``threads = CPUs // workers``, at most the smallest node's).
A task runs :func:`.episode.run_episode` into a temporary directory on its own node and
returns the episode's files; the driver writes them, so the cluster needs no shared file
system.

**Timeouts.** An episode's task (a Ray streaming generator task) first readies its
worker (below), then yields :data:`STARTED`, then the episode's result.
``episode_timeout`` counts from the driver's receipt of that marker: it bounds the
episode's own run, not the wait for a CPU, a fresh worker's start, its imports and its
kernels' loading, which on a busy host take a minute or more and had timed out episodes
that had not begun. Those have a limit of their own, ``startup_timeout``, from
the submission to the marker, so that a worker stuck in its start-up is caught too. Its
default, :data:`STARTUP_TIMEOUT`, applies when an episode timeout is set (with neither
limit set nothing is timed): 1800 s, generous because a cold compile cache means
compiling every kernel, which took 12 minutes on a 2-core host under a load of 8. An
attempt past either limit is cancelled (its worker killed) and run again as below; what
a killed worker had compiled stays in the cache. Ray Client (``ray://``) runs no
streaming task, so there the driver cannot see an episode start: an attempt may take the
start-up limit plus the episode timeout from its submission.

**Readying a worker.** Before its first episode a worker imports what an episode runs
and loads (or compiles) its kernels, by running that episode's scene for two steps
without its policy into a throwaway directory (once per worker process: about the cost
of building the scene once more), and imports a script policy's module; what fails there
is left for the episode itself to meet.

**Exactly once.** Only the driver writes ``OUT``: it stages an episode's files under
``OUT/.tmp/``, renames the directory into ``OUT/episodes/<id>`` (atomic), then appends the
episode's line to ``OUT/manifest.jsonl`` (flushed and synced), and never a second line for
an id that has one. A task whose worker died, whose node was lost or that ran past
a timeout (then cancelled) is submitted again, up to ``max_retries`` more times,
and the line says how many ``attempts`` it took; a failure any attempt would meet (a
refused parameter, a diverged simulation) is recorded at once, not retried. ``resume``
reads the manifest (a torn last line is dropped), adopts an episode directory that was
renamed but not yet listed, removes what was left in ``.tmp`` and runs the rest; a
different spec in the same directory is refused.
"""
from __future__ import annotations

import fcntl
import json
import math
import os
from pathlib import Path
import shutil
import sys
import tempfile
import time
from typing import Dict, List, Optional
import uuid

from .episode import commit_directory, result_line
from .spec import Episode, SpecError, check_episode, load_spec, plan, spec_digest

__all__ = ['run_batch', 'read_manifest', 'MANIFEST', 'Progress']

MANIFEST = 'manifest.jsonl'
SPEC_FILE = 'spec.json'
#: [s] how long the driver waits on Ray between looks at the timeouts and the progress
POLL = 0.5
#: [s] the start-up limit with an episode timeout and no ``startup_timeout`` of its own:
#: from an attempt's submission to its episode's start in a worker (module docstring)
STARTUP_TIMEOUT = 1800.0
#: what an episode's task yields once its worker is ready, before the episode runs
STARTED = 'started'


def read_manifest(out_dir, repair: bool = False) -> List[dict]:
    """The lines of ``OUT/manifest.jsonl``; a torn last line (a driver killed while
    writing it) is skipped, and with ``repair`` cut from the file."""
    path = Path(out_dir) / MANIFEST
    if not path.exists():
        return []
    data = path.read_bytes()
    end = data.rfind(b'\n') + 1
    if repair and end < len(data):
        with open(path, 'r+b') as fh:
            fh.truncate(end)
    out = []
    for line in data[:end].splitlines():
        if line.strip():
            out.append(json.loads(line))
    return out


class Progress:
    """Episodes done / failed, rate and ETA: a bar on a terminal (``bar``), one JSON
    object per finished episode on stdout (``jsonl``), or nothing (``none``)."""

    def __init__(self, mode: str, total: int, done: int, failed: int):
        if mode not in ('bar', 'jsonl', 'none'):
            raise SpecError(f'--progress must be bar, jsonl or none, got {mode!r}')
        self.mode = mode if (mode != 'bar' or sys.stderr.isatty()) else 'none'
        self.total, self.done, self.failed = total, done, failed
        self.start = time.monotonic()
        self.new = 0

    def update(self, line: Optional[dict] = None) -> None:
        if line is not None:
            self.new += 1
            if line['status'] == 'ok':
                self.done += 1
            else:
                self.failed += 1
        elapsed = time.monotonic() - self.start
        rate = self.new / elapsed if elapsed > 0 else 0.0
        left = self.total - self.done - self.failed
        eta = left / rate if rate > 0 else None
        if self.mode == 'jsonl' and line is not None:
            print(json.dumps({'id': line['id'], 'status': line['status'],
                              'done': self.done, 'failed': self.failed,
                              'total': self.total, 'rate_per_s': round(rate, 4),
                              'eta_s': None if eta is None else round(eta, 1)}),
                  flush=True)
        elif self.mode == 'bar':
            width = 30
            k = int(width * (self.done + self.failed) / max(1, self.total))
            eta_s = '?' if eta is None else f'{eta:.0f} s'
            sys.stderr.write(f'\r[{"#" * k}{"." * (width - k)}] {self.done + self.failed}'
                             f'/{self.total}  ok {self.done}  failed {self.failed}  '
                             f'{rate * 60:.1f}/min  ETA {eta_s}   ')
            sys.stderr.flush()

    def close(self) -> None:
        if self.mode == 'bar':
            sys.stderr.write('\n')


# ---------------------------------------------------------------- the task
_worker_ready = False          # in a Ray worker: whether _ready_worker has run there


def _ready_worker(episode: dict) -> None:
    """Once per worker process, before its first episode: import what an episode runs
    and load (or compile) its kernels by running ``episode``'s scene for two steps
    without its policy into a throwaway directory; import a script policy's module.
    A failure here is left for the episode itself to meet."""
    global _worker_ready
    if _worker_ready:
        return
    _worker_ready = True
    from ..ros.scene import check_parameters
    from .episode import run_episode
    from .spec import resolve_script
    policy = episode['policy']
    if policy.get('kind') == 'script':
        try:
            resolve_script(policy['target'])
        except Exception:                          # noqa: BLE001 (the episode says why)
            pass
    if policy.get('kind') == 'env':                # build and reset the environment
        try:
            from .env_episode import make_env
            env = make_env(policy)
            try:
                env.reset(seed=0)
            finally:
                env.close()
        except Exception:                          # noqa: BLE001 (the episode says why)
            pass
        return
    tmp = Path(tempfile.mkdtemp(prefix='cosserat_ready_'))
    try:
        dt = float(check_parameters(episode['params'])['dt'])
        run_episode(dict(episode, duration=2 * dt, policy={'kind': 'none'}), tmp)
    except Exception:                              # noqa: BLE001 (the episode says why)
        pass
    finally:
        shutil.rmtree(tmp, ignore_errors=True)


def _episode_task(episode: dict, threads: int):
    """In a Ray worker, a streaming generator task: with ``threads`` numba threads, ready
    the worker (:func:`_ready_worker`), yield :data:`STARTED`, then run the episode into a
    local temporary directory and yield (result, {relative path: bytes})."""
    import numba
    import ray
    from .episode import run_episode
    numba.set_num_threads(max(1, min(int(threads), numba.config.NUMBA_NUM_THREADS)))
    _ready_worker(episode)
    yield STARTED
    tmp = Path(tempfile.mkdtemp(prefix='cosserat_batch_'))
    try:
        result = run_episode(episode, tmp)
        root = tmp / 'episodes' / episode['id']
        files = {str(p.relative_to(root)): p.read_bytes()
                 for p in sorted(root.rglob('*')) if p.is_file()}
        result['node'] = ray.get_runtime_context().get_node_id()
        result['numba_threads'] = numba.get_num_threads()
    finally:
        shutil.rmtree(tmp, ignore_errors=True)
    yield result, files


def _episode_task_whole(episode: dict, threads: int):
    """:func:`_episode_task` as a plain task returning its last item (Ray Client runs no
    streaming generator task)."""
    *_, last = _episode_task(episode, threads)
    return last


# ---------------------------------------------------------------- the run directory
def _prepare(out: Path, spec: dict, resume: bool):
    digest = spec_digest(spec)
    if out.exists() and any(out.iterdir()):
        if not resume:
            raise SpecError(f'{out} exists and is not empty: --resume to finish its run, '
                            'or choose another directory')
        try:
            stored = json.loads((out / SPEC_FILE).read_text())
        except (OSError, ValueError):
            raise SpecError(f'{out}: no {SPEC_FILE}; not a batch run directory') from None
        if spec_digest(stored) != digest:
            raise SpecError(f'{out} holds a run of another spec (its {SPEC_FILE} differs); '
                            'resume it with the same spec, or choose another directory')
    else:
        out.mkdir(parents=True, exist_ok=True)
        tmp = out / (SPEC_FILE + '.tmp')
        tmp.write_text(json.dumps(spec, sort_keys=True, indent=1) + '\n')
        tmp.replace(out / SPEC_FILE)
    (out / 'episodes').mkdir(exist_ok=True)
    shutil.rmtree(out / '.tmp', ignore_errors=True)
    (out / '.tmp').mkdir()
    lock = open(out / '.lock', 'w')
    try:
        fcntl.flock(lock, fcntl.LOCK_EX | fcntl.LOCK_NB)
    except OSError:
        lock.close()
        raise SpecError(f'{out}: another batch driver is running on it') from None
    return lock


class _Manifest:
    """The manifest file, written by this driver only: one line per id, synced."""

    def __init__(self, out: Path):
        self.out = out
        self.lines = {ln['id']: ln for ln in read_manifest(out, repair=True)}
        self._fh = open(out / MANIFEST, 'a')

    def add(self, line: dict) -> bool:
        if line['id'] in self.lines:
            return False
        self._fh.write(json.dumps(line, sort_keys=True) + '\n')
        self._fh.flush()
        os.fsync(self._fh.fileno())
        self.lines[line['id']] = line
        return True

    def close(self):
        self._fh.close()


def _commit(out: Path, result: dict, files: Dict[str, bytes]) -> dict:
    """Stage the episode's files, with its final result.json, and rename them into
    place; the result of whichever attempt got there first."""
    staged = out / '.tmp' / f'{result["id"]}.{uuid.uuid4().hex}'
    for rel, data in files.items():
        p = staged / rel
        p.parent.mkdir(parents=True, exist_ok=True)
        p.write_bytes(data)
    (staged / 'result.json').write_text(json.dumps(result, sort_keys=True) + '\n')
    final = out / 'episodes' / result['id']
    if commit_directory(staged, final):
        return result
    return json.loads((final / 'result.json').read_text())


def write_parquet(out: Path) -> Optional[Path]:
    """``OUT/manifest.parquet``: the manifest as a table (nested fields as JSON text,
    metrics as columns ``metric_<name>``); None if pyarrow is missing."""
    try:
        import pyarrow as pa
        import pyarrow.parquet as pq
    except ImportError:
        return None
    lines = sorted(read_manifest(out), key=lambda ln: ln['index'])
    rows = []
    for ln in lines:
        row = {k: (json.dumps(v, sort_keys=True) if isinstance(v, (dict, list)) else v)
               for k, v in ln.items() if k != 'metrics'}
        for k, v in (ln.get('metrics') or {}).items():
            row[f'metric_{k}'] = v
        rows.append(row)
    keys = sorted({k for r in rows for k in r})
    table = pa.table({k: [r.get(k) for r in rows] for k in keys})
    tmp = out / 'manifest.parquet.tmp'
    pq.write_table(table, tmp)
    tmp.replace(out / 'manifest.parquet')
    return out / 'manifest.parquet'


# ---------------------------------------------------------------- the run
#: Ray's settings for a private instance. ``worker_niceness``: Ray runs its workers at
#: nice 15 by default (so that its own GCS and raylet come first); beside busy processes
#: at nice 0 a worker then has a CFS weight of 36 against their 1024 each, and the
#: episodes, the user's own work, crawl (docs/performance.md, "make test beside two busy
#: processes"). They run at the driver's priority. A cluster joined by address keeps its
#: own setting (``ray start --head --system-config='{"worker_niceness": 0}'``).
SYSTEM_CONFIG = {'worker_niceness': 0}


def _ray_init(address: Optional[str], temp_dir: Optional[str]):
    """Join ``address``, or start a private instance on this machine's loopback address
    (in ``temp_dir`` if given, else Ray's default: ``$RAY_TMPDIR/ray``, ``/tmp/ray``).
    Returns the reaper of a private instance (None when joining; :mod:`.reaper`)."""
    import ray
    if address:
        ray.init(address=address, log_to_driver=False, logging_level='ERROR',
                 configure_logging=True)
        return None
    kwargs = dict(num_cpus=os.cpu_count() or 1, include_dashboard=False,
                  log_to_driver=False, logging_level='ERROR', configure_logging=True,
                  _node_ip_address='127.0.0.1', _system_config=SYSTEM_CONFIG)
    if temp_dir:
        kwargs['_temp_dir'] = temp_dir
    from . import reaper
    before = set(reaper.descendants(os.getpid())) if os.path.isdir('/proc') else set()
    watcher = reaper.start()
    try:
        ray.init(**kwargs)
    finally:
        if watcher is not None:
            reaper.watch(watcher, sorted(set(reaper.descendants(os.getpid())) - before
                                         - {watcher.pid}))
    return watcher


def _threads(workers: int, asked: Optional[int] = None) -> int:
    """numba threads per worker: ``asked``, or the CPUs over the workers; at most the
    smallest node's CPUs (a task must fit on one node)."""
    import ray
    nodes = [n for n in ray.nodes() if n.get('Alive')]
    cpus = [int(n['Resources'].get('CPU', 0)) for n in nodes]
    cpus = [c for c in cpus if c > 0] or [1]
    want = asked if asked is not None else sum(cpus) // max(1, workers)
    return max(1, min(want, min(cpus)))


def run_batch(spec, out_dir, workers: Optional[int] = None, address: Optional[str] = None,
              resume: bool = False, max_retries: int = 2,
              episode_timeout: Optional[float] = None, progress: str = 'none',
              ray_temp_dir: Optional[str] = None, threads: Optional[int] = None,
              startup_timeout: Optional[float] = None) -> dict:
    """Run every episode of ``spec`` (a path, a dict or :func:`.spec.load_spec`'s result)
    into ``out_dir`` on Ray (module docstring); returns the summary (counts, paths).
    ``workers``: episodes at once (default: the cluster's CPUs); ``threads``: numba
    threads of each (default: the CPUs over the workers). ``episode_timeout`` [s]: how
    long an episode may run, counted from its start in its worker (after the worker's
    start-up and kernel loading); ``startup_timeout`` [s]: how long an attempt may take
    from its submission to that start (default :data:`STARTUP_TIMEOUT` with an episode
    timeout, else no limit). An attempt past either is cancelled and retried, up to
    ``max_retries`` more times. :class:`.spec.SpecError` for a bad spec, option or
    directory, before any work."""
    spec = load_spec(spec)
    if workers is not None and (not isinstance(workers, int) or workers < 1):
        raise SpecError(f'--workers must be a positive integer, got {workers!r}')
    if threads is not None and (not isinstance(threads, int) or threads < 1):
        raise SpecError(f'--threads must be a positive integer, got {threads!r}')
    if not isinstance(max_retries, int) or max_retries < 0:
        raise SpecError(f'--max-retries must be an integer >= 0, got {max_retries!r}')
    if episode_timeout is not None and not (episode_timeout > 0
                                            and math.isfinite(episode_timeout)):
        raise SpecError(f'--episode-timeout must be positive seconds, got '
                        f'{episode_timeout!r}')
    if startup_timeout is not None and not (startup_timeout > 0
                                            and math.isfinite(startup_timeout)):
        raise SpecError(f'--startup-timeout must be positive seconds, got '
                        f'{startup_timeout!r}')
    if startup_timeout is None and episode_timeout is not None:
        startup_timeout = STARTUP_TIMEOUT
    episodes = plan(spec)
    out = Path(out_dir)
    lock = _prepare(out, spec, resume)
    manifest = _Manifest(out)
    t_start = time.monotonic()
    try:
        # renamed into place but not listed (the driver died in between): adopt
        for ep in episodes:
            res = out / 'episodes' / ep.id / 'result.json'
            if ep.id not in manifest.lines and res.exists():
                manifest.add(json.loads(res.read_text()))
        todo: List[Episode] = []
        for ep in episodes:
            if ep.id in manifest.lines:
                continue
            reason = check_episode(ep)
            if reason is not None:      # the node would refuse it: deterministic
                manifest.add(_failed_line(ep, f'refused: {reason}', attempts=0))
            else:
                todo.append(ep)
        prog = Progress(progress, len(episodes),
                        sum(ln['status'] == 'ok' for ln in manifest.lines.values()),
                        sum(ln['status'] != 'ok' for ln in manifest.lines.values()))
        if todo:
            _run_on_ray(todo, out, manifest, prog, workers, threads, address, max_retries,
                        episode_timeout, startup_timeout, ray_temp_dir)
        prog.close()
    finally:
        manifest.close()
        shutil.rmtree(out / '.tmp', ignore_errors=True)
        lock.close()
    write_parquet(out)
    lines = read_manifest(out)
    return {'out': str(out), 'episodes': len(episodes),
            'ok': sum(ln['status'] == 'ok' for ln in lines),
            'failed': sum(ln['status'] != 'ok' for ln in lines),
            'ran': len(todo), 'wall_time': time.monotonic() - t_start,
            'manifest': str(out / MANIFEST)}


def _failed_line(ep: Episode, error: str, attempts: int, deterministic: bool = True) -> dict:
    return result_line(ep, status='failed', error=error, deterministic=deterministic,
                       attempts=attempts, node=None)


def _run_on_ray(todo, out, manifest, prog, workers, threads, address, max_retries, timeout,
                startup, ray_temp_dir):
    import ray
    from ray import exceptions as rex
    from ray.util.client import ray as client
    from . import reaper
    watcher = _ray_init(address, ray_temp_dir)
    try:
        if workers is None:
            workers = max(1, int(ray.cluster_resources().get('CPU', 1)))
        threads = _threads(workers, threads)
        options = dict(num_cpus=threads, max_retries=0, name='cosserat_episode')
        streaming = not client.is_connected()
        if streaming:
            task = ray.remote(_episode_task).options(num_returns='streaming', **options)
            why_start = (f'did not start within the start-up limit of {startup:g} s'
                         if startup is not None else '')
        else:       # Ray Client streams nothing: one limit for both, from the submission
            task = ray.remote(_episode_task_whole).options(**options)
            if timeout is not None:
                why_start = (f'ran past the start-up limit plus the episode timeout '
                             f'({startup:g} s + {timeout:g} s)')
                startup += timeout
            else:
                startup = None
        pending = list(reversed(todo))          # popped from the end: in index order
        attempts: Dict[str, int] = {}
        # a task (generator) -> (episode, started, since: submitted or started at)
        inflight: Dict[object, tuple] = {}

        def submit(ep):
            attempts[ep.id] = attempts.get(ep.id, 0) + 1
            inflight[task.remote(ep.to_dict(), threads)] = (ep, False, time.monotonic())

        def retry_or_fail(ep, why: str):
            if attempts[ep.id] <= max_retries:
                pending.append(ep)
            else:
                line = _failed_line(ep, f'gave up after {attempts[ep.id]} attempts: {why}',
                                    attempts[ep.id], deterministic=False)
                if manifest.add(line):
                    prog.update(line)

        while pending or inflight:
            while pending and len(inflight) < workers:
                submit(pending.pop())
            ready, _ = ray.wait(list(inflight), num_returns=1, timeout=POLL)
            for ref in ready:
                ep = inflight[ref][0]
                try:
                    item = ray.get(next(ref) if streaming else ref)
                except StopIteration:
                    del inflight[ref]
                    retry_or_fail(ep, 'its task ended without a result')
                    continue
                except (rex.WorkerCrashedError, rex.NodeDiedError, rex.TaskCancelledError,
                        rex.ObjectLostError, rex.RaySystemError, rex.OutOfMemoryError,
                        rex.RayTaskError) as exc:
                    del inflight[ref]
                    retry_or_fail(ep, str(exc).strip().splitlines()[0] if str(exc).strip()
                                  else type(exc).__name__)
                    continue
                if isinstance(item, str) and item == STARTED:
                    inflight[ref] = (ep, True, time.monotonic())    # the episode's clock
                    continue
                del inflight[ref]
                result, files = item
                result['attempts'] = attempts[ep.id]
                result = _commit(out, result, files)
                if manifest.add(result):
                    prog.update(result)
            now = time.monotonic()
            for ref, (ep, started, since) in list(inflight.items()):
                limit = timeout if started else startup
                if limit is not None and now - since > limit:
                    ray.cancel(ref, force=True)
                    del inflight[ref]
                    retry_or_fail(ep, f'ran past the episode timeout of {timeout:g} s'
                                  if started else why_start)
            if not ready:
                prog.update()
    finally:
        if ray.is_initialized():
            ray.shutdown()
        reaper.stop(watcher)
