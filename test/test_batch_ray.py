"""The batch engine on real Ray: a private instance, and a two-node cluster on this
machine (Ray's own ``ray.cluster_utils.Cluster``); workers, nodes and the driver really
killed. Each test gives Ray its own temporary directory and checks that no process of it
is left.

The tests run from a temporary working directory: Ray puts the driver's working directory
on its workers' path, and from the repository's root they would import the working tree
instead of the installed package whose kernels the suite has compiled."""
import json
import os
from pathlib import Path
import shutil
import signal
import subprocess
import tempfile
import threading
import time

import pytest
import yaml

from cosserat_ros.batch import load_spec, plan, read_manifest, run_batch, run_episode
from cosserat_ros.batch.engine import SYSTEM_CONFIG
from cosserat_ros.batch.spec import SpecError

# real Ray instances and clusters, and the batch command (make test, not test-fast)
pytestmark = [pytest.mark.ray, pytest.mark.process]

ROOT = Path(__file__).resolve().parent.parent
BATCH = ROOT / '.venv' / 'lib' / 'cosserat_ros' / 'batch'


def spec(episodes=4, duration=0.4, **over):
    s = {'batch': 1, 'seed': 11, 'episodes': episodes, 'duration': duration,
         'base': str(ROOT / 'config' / 'table.yaml'),
         'scene': {'mesh.nx': 10, 'mesh.ny': 10},
         'randomize': {'material.damping': {'uniform': [0.1, 0.3]},
                       'obstacles.table.center': {
                           'uniform': [[-0.05, -0.05, -0.35], [0.05, 0.05, -0.3]]}},
         'init': {'drop': {'height': {'uniform': [0.02, 0.1]},
                           'tilt_deg': {'uniform': [0, 30]}}},
         'policy': {'pick_place': {'handles': 1, 'moves': 1}},
         'record': {'mesh_hz': 20, 'points_hz': 10}}
    s.update(over)
    return s


def _ray_processes(tag: str):
    """Pids of processes of this test's Ray: a command line naming its temporary
    directory, or a Ray worker's or agent's title (``ray::...``)."""
    out = []
    for name in os.listdir('/proc'):
        if not name.isdigit() or int(name) == os.getpid():
            continue
        try:
            cmd = Path(f'/proc/{name}/cmdline').read_bytes().replace(b'\0', b' ').decode()
        except OSError:
            continue
        if tag in cmd or cmd.startswith('ray::'):
            out.append((int(name), cmd[:100]))
    return out


def _no_ray_left(tag: str, wait: float = 20.0):
    deadline = time.monotonic() + wait
    while time.monotonic() < deadline:
        left = _ray_processes(tag)
        if not left:
            return
        time.sleep(0.5)
    raise AssertionError(f'Ray processes left: {left}')


def _every_episode_ok_once(out: Path, n: int):
    lines = read_manifest(out)
    ids = [ln['id'] for ln in lines]
    assert sorted(ids) == [f'{i:06d}' for i in range(n)], ids
    bad = [(ln['id'], ln['error']) for ln in lines if ln['status'] != 'ok']
    assert not bad, bad
    assert sorted(p.name for p in (out / 'episodes').iterdir()) == sorted(ids)
    assert not (out / '.tmp').exists() or not any((out / '.tmp').iterdir())
    r = subprocess.run([str(BATCH), 'verify', str(out)], capture_output=True, text=True,
                       timeout=300)
    assert r.returncode == 0, r.stdout + r.stderr
    return lines


@pytest.fixture
def raytmp(tmp_path, monkeypatch):
    """A short temporary directory of Ray's own (its sockets live there) and a working
    directory outside the repository; nothing of Ray's left afterwards."""
    d = tempfile.mkdtemp(prefix='cosray', dir='/tmp')
    os.mkdir(os.path.join(d, 'ray'))
    monkeypatch.chdir(tmp_path)
    monkeypatch.setenv('RAY_TMPDIR', d)           # Ray's own variable: <d>/ray
    yield d
    try:
        _no_ray_left(d)
    finally:
        shutil.rmtree(d, ignore_errors=True)


@pytest.fixture(scope='module', autouse=True)
def warm(tmp_path_factory):
    """One episode in this process first: the kernels the workers load are compiled."""
    run_episode(plan(load_spec(spec(episodes=1)))[0], tmp_path_factory.mktemp('warm'))


@pytest.fixture
def cluster(raytmp, monkeypatch):
    """Two nodes of one CPU each on this machine, on the loopback address (Ray's switch
    for a single-machine cluster: a driver joining 127.0.0.1 would otherwise go to the
    machine's own network address)."""
    import ray._private.ray_constants as rc
    from ray.cluster_utils import Cluster
    monkeypatch.setenv('RAY_ENABLE_WINDOWS_OR_OSX_CLUSTER', '0')
    monkeypatch.setattr(rc, 'ENABLE_RAY_CLUSTER', False)
    args = {'num_cpus': 1, 'temp_dir': os.path.join(raytmp, 'ray'),
            'node_ip_address': '127.0.0.1',
            'include_dashboard': False, '_system_config': SYSTEM_CONFIG}
    c = Cluster(initialize_head=True, head_node_args=args)
    # the head holds the cluster's system config; the other node takes it from there
    worker = c.add_node(**{k: v for k, v in args.items() if k not in ('temp_dir',
                                                                      '_system_config')})
    c.wait_for_nodes()
    yield c, worker
    c.shutdown()


# ---------------------------------------------------------------- a private instance
def test_a_private_instance_runs_its_workers_at_the_driver_s_priority(raytmp):
    """Ray nices its workers to 15 by default; beside busy processes at nice 0 they then
    crawl (engine.SYSTEM_CONFIG). The private instance's workers run at the driver's."""
    import ray
    from cosserat_ros.batch import engine, reaper
    watcher = engine._ray_init(None, os.path.join(raytmp, 'ray'))
    try:
        worker_nice = ray.get(ray.remote(num_cpus=1)(lambda: os.nice(0)).remote())
    finally:
        ray.shutdown()
        reaper.stop(watcher)
    assert worker_nice == os.nice(0)


def test_one_worker_and_two_give_the_same_bytes_and_one_line_each(raytmp, tmp_path):
    s = load_spec(spec(episodes=4))
    one = run_batch(s, tmp_path / 'one', workers=1)       # 1 worker x 2 numba threads
    two = run_batch(s, tmp_path / 'two', workers=2)       # 2 workers x 1 thread
    assert (one['ok'], two['ok'], one['failed'], two['failed']) == (4, 4, 0, 0)
    a = _every_episode_ok_once(tmp_path / 'one', 4)
    b = _every_episode_ok_once(tmp_path / 'two', 4)
    assert {ln['numba_threads'] for ln in a} == {min(2, os.cpu_count())}
    assert {ln['numba_threads'] for ln in b} == {1}
    sha = {ln['id']: ln['bag_sha256'] for ln in a}
    assert sha == {ln['id']: ln['bag_sha256'] for ln in b}
    for i in sha:
        assert ((tmp_path / 'one' / 'episodes' / i / 'bag' / 'bag.mcap').read_bytes()
                == (tmp_path / 'two' / 'episodes' / i / 'bag' / 'bag.mcap').read_bytes())
    # and the same as a plain loop over run_episode, without Ray
    ep = plan(s)[2]
    assert run_episode(ep, tmp_path / 'loop')['bag_sha256'] == sha[ep.id]
    for ln in a:
        for key in ('id', 'seed', 'params', 'status', 'error', 'attempts', 'metrics',
                    'sim_time', 'wall_time', 'host', 'node', 'bag_sha256', 'version',
                    'cpu'):
            assert key in ln, key
        assert ln['attempts'] == 1 and ln['node']
        assert set(ln['metrics']) >= {'kinetic_energy', 'elastic_energy', 'max_edge_strain',
                                      'peak_handle_force', 'peak_contact_force', 'coverage'}
    import pyarrow.parquet as pq
    table = pq.read_table(tmp_path / 'one' / 'manifest.parquet')
    assert table.num_rows == 4 and 'metric_coverage' in table.column_names


def test_an_environment_s_episodes_run_on_ray_as_they_do_alone(raytmp, tmp_path):
    """An ``env`` spec (a Gymnasium task and an agent) on two workers: every episode once,
    each the same bytes and metrics as the same episode run in this process."""
    pytest.importorskip('gymnasium')
    s = load_spec({'batch': 1, 'seed': 2, 'episodes': 3,
                   'env': {'id': 'cosserat_ros/ClothFold-v0', 'agent': 'random',
                           'options': {'resolution': 6, 'horizon': 2}}})
    res = run_batch(s, tmp_path / 'ray', workers=2)
    assert (res['ok'], res['failed']) == (3, 0)
    lines = _every_episode_ok_once(tmp_path / 'ray', 3)
    ep = plan(s)[1]
    alone = run_episode(ep, tmp_path / 'alone')
    line = next(ln for ln in lines if ln['id'] == ep.id)
    assert line['bag_sha256'] == alone['bag_sha256']
    assert line['metrics'] == alone['metrics'] and line['metrics']['actions'] == 2


#: a sitecustomize (Python imports it at every start of an interpreter that has its
#: directory on the path): a Ray worker process (default_worker.py) notes its pid in that
#: directory, then sleeps $COSSERAT_TEST_SLOW_START seconds before it runs anything, as
#: a busy host or a cold cache stretches a worker's start-up
SLOW_START = """import os
import time

if b'default_worker.py' in open('/proc/self/cmdline', 'rb').read():
    open(os.path.join(os.path.dirname(__file__), 'started.%d' % os.getpid()), 'w').close()
    time.sleep(float(os.environ['COSSERAT_TEST_SLOW_START']))
"""


def _slow_worker_start(tmp_path: Path, monkeypatch, seconds: float) -> Path:
    """Every Ray worker this test's Ray starts sleeps ``seconds`` first (SLOW_START, on
    PYTHONPATH); returns the directory where each notes its pid. Also puts test/data
    (the scripts of batch_script.py) on the path. Ray starts its workers when a task
    needs one, not ahead at ``ray.init`` (which would wait for them), and gives them
    more than its default 60 s to register."""
    monkeypatch.setenv('RAY_prestart_worker_first_driver', '0')
    monkeypatch.setenv('RAY_enable_worker_prestart', '0')
    monkeypatch.setenv('RAY_worker_register_timeout_seconds', '600')
    slow = tmp_path / 'slow_start'
    slow.mkdir()
    (slow / 'sitecustomize.py').write_text(SLOW_START)
    data = str(Path(__file__).resolve().parent / 'data')
    monkeypatch.syspath_prepend(data)
    monkeypatch.setenv('PYTHONPATH', os.pathsep.join(
        [str(slow), data] + [p for p in [os.environ.get('PYTHONPATH')] if p]))
    monkeypatch.setenv('COSSERAT_TEST_SLOW_START', str(seconds))
    return slow


def test_a_timed_out_episode_is_retried_then_given_up_with_the_reason(raytmp, tmp_path,
                                                                      monkeypatch):
    """A policy that hangs (a user's script) is cancelled at the timeout, tried again
    --max-retries times, then recorded failed; the other episodes are not held up. The
    timeout counts from the episode's start in its worker, after the worker's start-up:
    here every worker starts 25 s late (as on a busy host), and the episodes
    that do not hang still run at their first attempt (counted from the submission, as
    the timeout was, the first attempts ran past it). The 20 s are the episode's own,
    generous on a busy host for an episode that runs in about a second."""
    slow = _slow_worker_start(tmp_path, monkeypatch, 25.0)
    s = load_spec(spec(episodes=3, policy={'script': 'batch_script:hang_first'}))
    summary = run_batch(s, tmp_path / 'out', workers=2, max_retries=1, episode_timeout=20.0)
    lines = {ln['id']: ln for ln in read_manifest(tmp_path / 'out')}
    # the others ran at their first attempt, late start and all
    assert [(lines[i]['status'], lines[i]['attempts']) for i in ('000001', '000002')] == [
        ('ok', 1), ('ok', 1)], lines
    assert summary['ok'] == 2 and summary['failed'] == 1
    hung = lines['000000']
    assert hung['status'] == 'failed' and hung['attempts'] == 2
    assert hung['error'] == 'gave up after 2 attempts: ran past the episode timeout of 20 s'
    assert not hung['deterministic']
    assert not (tmp_path / 'out' / 'episodes' / '000000').exists()
    assert len(list(slow.glob('started.*'))) >= 2        # the workers did start late


def test_a_worker_stuck_in_its_start_up_is_caught_at_the_start_up_limit(raytmp, tmp_path,
                                                                        monkeypatch):
    """An attempt whose worker does not get ready within the start-up limit is cancelled
    and retried like one past the episode timeout (the default limit is 1800 s; 5 s
    here, against workers that take 120 s to start)."""
    _slow_worker_start(tmp_path, monkeypatch, 120.0)
    summary = run_batch(spec(episodes=2), tmp_path / 'out', workers=2, max_retries=1,
                        episode_timeout=60.0, startup_timeout=5.0)
    assert summary['ok'] == 0 and summary['failed'] == 2
    for ln in read_manifest(tmp_path / 'out'):
        assert ln['attempts'] == 2 and not ln['deterministic']
        assert ln['error'] == ('gave up after 2 attempts: did not start within the '
                               'start-up limit of 5 s')
    assert not any((tmp_path / 'out' / 'episodes').iterdir())


@pytest.mark.parametrize('bad', [{'episode_timeout': 0}, {'startup_timeout': -1.0},
                                 {'startup_timeout': float('inf')}])
def test_a_bad_timeout_is_refused_before_any_work(tmp_path, bad):
    with pytest.raises(SpecError, match='timeout must be positive seconds'):
        run_batch(spec(episodes=1), tmp_path / 'out', **bad)
    assert not (tmp_path / 'out').exists()


def test_the_driver_killed_leaves_no_ray_process_and_resume_finishes(raytmp, tmp_path):
    path = tmp_path / 'spec.yaml'
    path.write_text(yaml.safe_dump(spec(episodes=6, duration=1.0)))
    out = tmp_path / 'out'
    driver = subprocess.Popen([str(BATCH), 'run', str(path), '-o', str(out), '--workers',
                               '2', '--progress', 'jsonl'], stdout=subprocess.PIPE,
                              stderr=subprocess.STDOUT, text=True)
    first = driver.stdout.readline()                     # one episode finished
    assert json.loads(first)['status'] == 'ok', first
    driver.send_signal(signal.SIGKILL)
    driver.wait(timeout=30)
    _no_ray_left(raytmp)
    done = read_manifest(out)
    assert 1 <= len(done) < 6
    r = subprocess.run([str(BATCH), 'run', str(path), '-o', str(out), '--resume',
                        '--progress', 'none'], capture_output=True, text=True, timeout=600)
    assert r.returncode == 0, r.stderr
    lines = _every_episode_ok_once(out, 6)
    before = {ln['id']: ln for ln in done}
    for ln in lines:                                     # the ok ones were not redone
        if ln['id'] in before:
            assert ln == before[ln['id']]
    # a different spec in the same directory is refused; so is a run without --resume
    other = tmp_path / 'other.yaml'
    other.write_text(yaml.safe_dump(spec(episodes=7, duration=1.0)))
    for args, words in (([str(other), '--resume'], 'another spec'),
                        ([str(path)], 'exists and is not empty')):
        r = subprocess.run([str(BATCH), 'run', *args, '-o', str(out)], capture_output=True,
                           text=True, timeout=120)
        assert r.returncode == 2 and words in r.stderr and r.stderr.count('\n') == 1


def test_status_and_montage_show_the_run(raytmp, tmp_path):
    out = tmp_path / 'out'
    run_batch(spec(episodes=3), out, workers=2)
    r = subprocess.run([str(BATCH), 'status', str(out)], capture_output=True, text=True,
                       timeout=60)
    assert r.returncode == 0 and '3 episodes: 3 ok, 0 failed, 0 not run' in r.stdout
    png = tmp_path / 'montage.png'
    r = subprocess.run([str(BATCH), 'montage', str(out), '-o', str(png)],
                       capture_output=True, text=True, timeout=300)
    assert r.returncode == 0, r.stderr
    assert png.read_bytes()[:8] == b'\x89PNG\r\n\x1a\n' and png.stat().st_size > 20_000
    # a bag spoilt after the run: verify says which and fails
    mcap = out / 'episodes' / '000001' / 'bag' / 'bag.mcap'
    data = bytearray(mcap.read_bytes())
    data[len(data) // 2] ^= 0xFF
    mcap.write_bytes(bytes(data))
    r = subprocess.run([str(BATCH), 'verify', str(out)], capture_output=True, text=True,
                       timeout=120)
    assert r.returncode == 1 and '000001' in r.stdout


# ---------------------------------------------------------------- a two-node cluster
def test_episodes_land_on_both_nodes_of_a_cluster(cluster, tmp_path):
    c, _ = cluster
    run_batch(spec(episodes=6, duration=0.8), tmp_path / 'out', address=c.address)
    lines = _every_episode_ok_once(tmp_path / 'out', 6)
    import ray
    assert not ray.is_initialized()                      # the driver let go of it
    assert len({ln['node'] for ln in lines}) == 2


def _kill_when(predicate, act, timeout=120.0):
    """Run ``act()`` once ``predicate()`` holds (polled), in a thread."""
    fired = {}

    def loop():
        deadline = time.monotonic() + timeout
        while time.monotonic() < deadline:
            got = predicate()
            if got:
                fired['what'] = act(got)
                return
            time.sleep(0.05)
    t = threading.Thread(target=loop, daemon=True)
    t.start()
    return t, fired


def _episode_workers():
    """Pids of Ray workers running an episode now (Ray titles a busy worker with its
    task's name, an idle one ``ray::IDLE``)."""
    return [pid for pid, cmd in _ray_processes('ray::cosserat_episode')
            if cmd.startswith('ray::cosserat_episode')]


def test_a_worker_killed_mid_episode_is_retried(cluster, tmp_path):
    c, _ = cluster
    out = tmp_path / 'out'

    def kill(pids):
        os.kill(pids[0], signal.SIGKILL)
        return pids[0]
    t, fired = _kill_when(lambda: len(read_manifest(out)) >= 1 and _episode_workers(),
                          kill)
    run_batch(spec(episodes=6, duration=1.5), out, address=c.address, max_retries=2)
    t.join(timeout=5)
    assert 'what' in fired, 'no worker was caught mid-episode'
    lines = _every_episode_ok_once(out, 6)
    assert max(ln['attempts'] for ln in lines) == 2


def test_a_node_removed_mid_batch_loses_no_episode(cluster, tmp_path):
    c, worker = cluster
    out = tmp_path / 'out'
    t, fired = _kill_when(lambda: len(read_manifest(out)) >= 2,
                          lambda _: c.remove_node(worker, allow_graceful=False) or True)
    run_batch(spec(episodes=6, duration=1.5), out, address=c.address, max_retries=3)
    t.join(timeout=30)
    assert 'what' in fired
    lines = _every_episode_ok_once(out, 6)
    nodes = {ln['node'] for ln in lines}
    assert len(nodes) == 2                              # some ran there before it went


def test_a_driver_killed_on_a_cluster_is_resumed_there(cluster, tmp_path):
    """The driver joined a running cluster (``--address``) and is SIGKILLed: the cluster
    is not its to stop, its tasks die with it, and ``--resume`` finishes the run there."""
    c, _ = cluster
    path = tmp_path / 'spec.yaml'
    path.write_text(yaml.safe_dump(spec(episodes=5, duration=1.0)))
    out = tmp_path / 'out'
    args = [str(BATCH), 'run', str(path), '-o', str(out), '--address', c.address,
            '--progress', 'jsonl']
    env = dict(os.environ, RAY_ENABLE_WINDOWS_OR_OSX_CLUSTER='0')
    driver = subprocess.Popen(args, stdout=subprocess.PIPE, stderr=subprocess.DEVNULL,
                              text=True, env=env)
    assert json.loads(driver.stdout.readline())['status'] == 'ok'
    driver.send_signal(signal.SIGKILL)
    driver.wait(timeout=30)
    time.sleep(1.0)
    assert not _episode_workers() or _wait_idle()
    r = subprocess.run(args[:-2] + ['--resume', '--progress', 'none'], capture_output=True,
                       text=True, timeout=600, env=env)
    assert r.returncode == 0, r.stderr
    _every_episode_ok_once(out, 5)


def _wait_idle(timeout: float = 30.0) -> bool:
    """Whether the killed driver's tasks stop running within ``timeout`` (Ray cancels
    the tasks of a job whose driver died)."""
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        if not _episode_workers():
            return True
        time.sleep(0.5)
    return False
