"""The batch engine without Ray: specs, plans, and episodes run in a plain loop.

(test_batch_ray.py runs the same episodes on real Ray instances and clusters.)"""
import hashlib
import json
from pathlib import Path
import subprocess
import time
import sys

import numpy as np
import pytest
import yaml

from cosserat_ros.batch import SpecError, load_spec, plan, run_episode
from cosserat_ros.batch.episode import coverage, support_height
from cosserat_ros.ros.scene import build_simulator, check_parameters, read_params_file

HERE = Path(__file__).resolve().parent
ROOT = HERE.parent
#: the venv the tests run in (make's VENV, .venv by default), where make installed the package
PREFIX = Path(sys.prefix)
BATCH = PREFIX / 'lib' / 'cosserat_ros' / 'batch'


def small_spec(**over):
    spec = {'batch': 1, 'seed': 3, 'episodes': 4, 'duration': 0.3,
            'base': str(ROOT / 'config' / 'table.yaml'),
            'scene': {'mesh.nx': 8, 'mesh.ny': 8},
            'randomize': {'material.damping': {'uniform': [0.1, 0.3]},
                          'obstacles.table.center': {
                              'uniform': [[-0.05, -0.05, -0.35], [0.05, 0.05, -0.3]]}},
            'init': {'drop': {'height': {'uniform': [0.02, 0.05]},
                              'tilt_deg': {'uniform': [0, 20]}}},
            'policy': 'none', 'record': {'mesh_hz': 20, 'points_hz': 10}}
    spec.update(over)
    return spec


# ---------------------------------------------------------------- specs
def test_the_issue_example_spec_loads_and_its_keys_mean_what_they_say():
    spec = load_spec({
        'batch': 1, 'seed': 7, 'episodes': 200, 'duration': 4.0,
        'base': 'config/table.yaml', 'scene': {'mesh.nx': 24, 'mesh.ny': 24},
        'randomize': {'material.preset': {'choice': ['denim', 'jersey', 'polyester']},
                      'material.damping': {'uniform': [0.05, 0.3]},
                      'obstacles.table.center': {'uniform': [[-0.1, -0.1, 0.35],
                                                             [0.1, 0.1, 0.45]]}},
        'init': {'drop': {'height': {'uniform': [0.1, 0.4]},
                          'tilt_deg': {'uniform': [0, 40]}}},
        'policy': {'pick_place': {'handles': 1, 'moves': 2}},
        'record': {'mesh_hz': 10, 'points_hz': 30}})
    eps = plan(spec)
    assert len(eps) == 200
    for ep in eps:
        assert ep.params['mesh.nx'] == 24
        assert ep.params['obstacles.table.shape'] == 'box'          # from the base file
        assert ep.params['material.preset'] in ('denim', 'jersey', 'polyester')
        assert 0.05 <= ep.params['material.damping'] <= 0.3
        c = np.array(ep.params['obstacles.table.center'])
        assert np.all(c >= [-0.1, -0.1, 0.35]) and np.all(c <= [0.1, 0.1, 0.45])
        assert 0.1 <= ep.init['height'] <= 0.4 and 0 <= ep.init['tilt_deg'] <= 40
        assert len(ep.policy['picks']) == 2 and len(ep.policy['picks'][0]) == 1
    # element-wise draws: the three coordinates are not one number scaled
    cs = np.array([ep.params['obstacles.table.center'] for ep in eps])
    assert abs(np.corrcoef(cs[:, 0], cs[:, 1])[0, 1]) < 0.3
    assert {ep.params['material.preset'] for ep in eps} == {'denim', 'jersey', 'polyester'}
    assert len({ep.seed for ep in eps}) == 200


def test_a_plan_is_pure_and_an_episode_does_not_depend_on_the_others():
    a = plan(load_spec(small_spec()))
    b = plan(load_spec(small_spec()))
    assert [e.to_dict() for e in a] == [e.to_dict() for e in b]
    longer = plan(load_spec(small_spec(episodes=10)))
    for x, y in zip(a, longer):                      # the same draws, not re-spread
        assert (x.seed, x.params, x.init, x.policy) == (y.seed, y.params, y.init, y.policy)
    other = plan(load_spec(small_spec(seed=4)))
    assert a[0].params != other[0].params


@pytest.mark.parametrize('change, words', [
    ({'bogus': 1}, 'bogus: unknown key'),
    ({'batch': 2}, 'batch: the schema version'),
    ({'episodes': 0}, 'episodes must be an integer'),
    ({'duration': -1}, 'duration must be a number'),
    ({'scene': {'mesh.nz': 3}}, 'mesh.nz: not a parameter'),
    ({'scene': {'dt': 'fast'}}, 'dt must be a float'),
    ({'scene': {'mesh.nx': 0}}, 'mesh.nx must lie in'),
    ({'randomize': {'material.damping': {'uniform': [0.3, 0.1]}}}, 'lo <= hi'),
    ({'randomize': {'material.damping': {'loguniform': [0.0, 0.1]}}}, '0 < lo'),
    ({'randomize': {'material.damping': {'gauss': [0.0, 0.1]}}}, 'randomize.material.damping'),
    ({'randomize': {'material.preset': {'choice': ['denim', 'chainmail']}}},
     'material preset must be one of'),
    ({'randomize': {'obstacles.table.center': {'uniform': [[0, 0], [1, 1, 1]]}}},
     'same length'),
    ({'randomize': {'obstacles.shelf.center': {'uniform': [[0, 0, 0], [1, 1, 1]]}}},
     'obstacles.shelf.center: not a parameter'),
    ({'policy': {'script': 'no_such_module_here:go'}}, "cannot import 'no_such_module_here'"),
    ({'policy': {'script': 'json:no_such_function'}}, "'json' has no 'no_such_function'"),
    ({'policy': {'pick_place': {'handles': 3}}}, 'handles must be 1 or 2'),
    ({'init': {'fling': {}}}, "unknown kind 'fling'"),
    ({'init': {'drop': {'hieght': 0.1}}}, "unknown key 'hieght'"),
    ({'record': {'mesh_hz': 0}}, 'record.mesh_hz must be positive'),
    ({'base': 'config/no_such.yaml'}, "base: no params file"),
])
def test_a_bad_spec_is_refused_with_the_key_and_why(change, words):
    with pytest.raises(SpecError) as exc:
        load_spec(small_spec(**change))
    assert words in str(exc.value)
    assert '\n' not in str(exc.value)


@pytest.mark.parametrize('change', [
    {'bogus': 1},
    {'randomize': {'material.damping': {'uniform': [0.3, 0.1]}}},
    {'randomize': {'material.preset': {'choice': ['chainmail']}}},
    {'policy': {'script': 'no_such_module_here:go'}},
])
@pytest.mark.process
def test_the_command_refuses_a_bad_spec_with_one_line_exit_2_and_leaves_nothing(tmp_path,
                                                                                change):
    spec = tmp_path / 'spec.yaml'
    spec.write_text(yaml.safe_dump(small_spec(**change)))
    out = tmp_path / 'out'
    r = subprocess.run([str(BATCH), 'run', str(spec), '-o', str(out)], capture_output=True,
                       text=True, timeout=120)
    assert r.returncode == 2, r.stderr
    assert r.stderr.startswith('batch: ') and r.stderr.count('\n') == 1, r.stderr
    assert not out.exists()
    assert sorted(p.name for p in tmp_path.iterdir()) == ['spec.yaml']


# ---------------------------------------------------------------- episodes
@pytest.fixture(scope='module')
def done(tmp_path_factory):
    """Two episodes of the small spec, run in a plain loop."""
    out = tmp_path_factory.mktemp('batch')
    eps = plan(load_spec(small_spec()))
    return out, eps, [run_episode(ep, out) for ep in eps[:2]]


def _messages(bag: Path):
    from rosbags.highlevel import AnyReader
    with AnyReader([bag]) as reader:
        return [(c.topic, t, reader.deserialize(raw, c.msgtype))
                for c, t, raw in reader.messages()]


def test_an_episode_writes_its_bag_params_and_result(done):
    out, eps, results = done
    ep, res = eps[0], results[0]
    assert res['status'] == 'ok' and res['error'] is None
    d = out / 'episodes' / ep.id
    assert sorted(p.name for p in d.iterdir()) == ['bag', 'params.yaml', 'result.json']
    assert not any((out / '.tmp').iterdir())
    assert json.loads((d / 'result.json').read_text()) == res
    mcap = d / 'bag' / 'bag.mcap'
    assert res['bag_sha256'] == hashlib.sha256(mcap.read_bytes()).hexdigest()
    msgs = _messages(d / 'bag')
    topics = {t for t, _, _ in msgs}
    assert topics == {'/clock', '/cloth_node/mesh', '/cloth_node/energy',
                      '/cloth_node/points', '/cloth_node/obstacle_markers',
                      '/cloth_node/contact/table', '/cloth_node/contact/ground',
                      # the base's (table.yaml's) camera, at its rate
                      *(f'/cloth_node/cameras/side/{t}' for t in (
                          'depth/image_raw', 'color/image_raw', 'camera_info', 'pose_out'))}
    # log times are simulation time: the mesh at 20 Hz over 0.3 s, stamped as logged
    meshes = [(t, m) for topic, t, m in msgs if topic == '/cloth_node/mesh']
    assert len(meshes) == 7
    dt = ep.params['dt']
    for k, (t, m) in enumerate(meshes):
        step = min(round(k / (20 * dt)), round(0.3 / dt))     # the end's, at most
        assert t == round(step * dt * 1e9)
        stamp = m.markers[0].header.stamp
        assert stamp.sec * 10 ** 9 + stamp.nanosec == t
    points = [m for topic, _, m in msgs if topic == '/cloth_node/points']
    assert len(points) == 4 and points[0].width == 81
    energies = [m for topic, _, m in msgs if topic == '/cloth_node/energy']
    vals = {kv.key: float(kv.value) for kv in energies[-1].status[0].values}
    assert vals['sim_time'] == pytest.approx(res['sim_time'])
    assert vals['kinetic'] == pytest.approx(res['metrics']['kinetic_energy'])


def test_params_yaml_reproduces_the_scene(done):
    out, eps, results = done
    ep = eps[1]
    given = read_params_file(out / 'episodes' / ep.id / 'params.yaml')
    assert given == {k: (list(v) if isinstance(v, tuple) else v)
                     for k, v in ep.params.items()}
    a = build_simulator(check_parameters(given), given)
    b = build_simulator(check_parameters(ep.params), ep.params)
    assert a.material == b.material and a.dt == b.dt
    assert a.obstacles == b.obstacles
    table = a.obstacles[a.find_obstacle('table')]
    assert list(table['position']) == pytest.approx(ep.params['obstacles.table.center'])


@pytest.mark.process
def test_the_node_accepts_an_episode_params_file(done, tmp_path):
    """``cloth_node --params-file params.yaml`` starts (as ``ros2 run`` would) with the
    episode's material and obstacles."""
    import rclpy
    from rcl_interfaces.srv import GetParameters
    out, eps, _ = done
    ep = eps[1]
    node_exe = PREFIX / 'lib' / 'cosserat_ros' / 'cloth_node'
    proc = subprocess.Popen([str(node_exe), '--ros-args', '--params-file',
                             str(out / 'episodes' / ep.id / 'params.yaml'),
                             '-p', 'status_period:=0.0'],
                            stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
    rclpy.init()
    node = rclpy.create_node('batch_params_check')
    try:
        cli = node.create_client(GetParameters, '/cloth_node/get_parameters')
        # rclpy's parameter services exist from the node's construction, before it has
        # loaded its kernels and spins; its topics come after (the node's start-up): wait
        # for them. A safety net only: the first node of a session compiles on a cold
        # cache, which beside busy processes took more than 120 s
        deadline = time.monotonic() + 600
        while node.count_publishers('/cloth_node/mesh') == 0 and proc.poll() is None:
            assert time.monotonic() < deadline, 'the node did not start within 600 s'
            rclpy.spin_once(node, timeout_sec=0.1)
        assert cli.wait_for_service(timeout_sec=60), proc.stdout.read() if proc.poll() else ''
        fut = cli.call_async(GetParameters.Request(
            names=['material.damping', 'obstacles.table.center']))
        rclpy.spin_until_future_complete(node, fut, timeout_sec=30)
        damping, centre = fut.result().values
        assert damping.double_value == ep.params['material.damping']
        assert list(centre.double_array_value) == ep.params['obstacles.table.center']
    finally:
        node.destroy_node()
        rclpy.shutdown()
        proc.terminate()
        proc.wait(timeout=30)


def test_the_drop_places_the_cloth_above_the_table_and_it_lands_there(done):
    out, eps, results = done
    for ep, res in zip(eps, results):
        msgs = _messages(out / 'episodes' / ep.id / 'bag')
        first = next(m for t, _, m in msgs if t == '/cloth_node/mesh')
        z = np.array([[p.z for p in first.markers[0].points]])
        top = ep.params['obstacles.table.center'][2] + 0.02
        assert z.min() == pytest.approx(top + ep.init['height'], abs=1e-9)
        # tilted about a horizontal axis at the azimuth: the unit square's extent across
        # that axis, |sin az| + |cos az|, rises by sin(tilt)
        az = np.radians(ep.init['azimuth_deg'])
        assert z.max() - z.min() == pytest.approx(
            np.sin(np.radians(ep.init['tilt_deg'])) * (abs(np.sin(az)) + abs(np.cos(az))),
            rel=1e-6)
        table = [m for t, _, m in msgs if t == '/cloth_node/contact/table']
        assert table[-1].wrench.force.z < 0           # it pushes the table down
    sim = build_simulator(check_parameters(eps[0].params), eps[0].params)
    assert support_height(sim, (-0.1, -0.1), (0.1, 0.1)) == pytest.approx(
        eps[0].params['obstacles.table.center'][2] + 0.02)
    assert support_height(sim, (2.0, 2.0), (3.0, 3.0)) == pytest.approx(-1.0)  # ground


def test_an_episode_gives_the_same_bytes_again_and_on_one_or_two_threads(done, tmp_path):
    import numba
    out, eps, results = done
    was = numba.get_num_threads()
    shas = []
    try:
        for threads in (1, 2):
            numba.set_num_threads(min(threads, numba.config.NUMBA_NUM_THREADS))
            shas.append(run_episode(eps[0], tmp_path / f't{threads}')['bag_sha256'])
    finally:
        numba.set_num_threads(was)
    assert shas == [results[0]['bag_sha256']] * 2


def test_a_second_attempt_finds_its_place_taken_and_keeps_the_first(done):
    out, eps, results = done
    again = run_episode(eps[0], out)
    assert again == results[0]
    assert len(list((out / 'episodes').iterdir())) == 2
    assert not any((out / '.tmp').iterdir())


def test_a_diverging_episode_fails_with_its_reason_and_leaves_no_bag(tmp_path):
    sys.path.insert(0, str(HERE / 'data'))
    try:
        spec = small_spec(episodes=1, policy={'script': 'batch_script:blow_up'})
        ep = plan(load_spec(spec))[0]
        res = run_episode(ep, tmp_path)
    finally:
        sys.path.remove(str(HERE / 'data'))
    assert res['error'].startswith('simulation diverged at step'), res['error']
    assert res['status'] == 'failed' and res['deterministic'], res
    assert res['error'] and '\n' not in res['error']
    d = tmp_path / 'episodes' / ep.id
    assert sorted(p.name for p in d.iterdir()) == ['params.yaml', 'result.json']


def test_a_refused_sample_is_a_failure_with_the_node_s_reason(tmp_path):
    # dt above the critical step of the drawn stiffness: the node refuses it at start
    spec = small_spec(episodes=1, randomize={'material.zeta': {'uniform': [1e6, 1e6]}})
    res = run_episode(plan(load_spec(spec))[0], tmp_path)
    assert res['status'] == 'failed'
    assert res['error'].startswith('refused: dt = ') and 'critical step' in res['error']


def test_an_episode_records_its_cameras_the_same_bytes_again(tmp_path):
    """A camera of the scene (cameras.*, as the node's) is recorded at its rate of
    simulation time on the node's topics; the bag is the same bytes again."""
    cam = {'cameras.names': ['top'], 'cameras.top.width': 32, 'cameras.top.height': 24,
           'cameras.top.rate': 10.0, 'cameras.top.points': True,
           'cameras.top.position': [0.0, 0.0, 1.5]}
    spec = small_spec(episodes=1, scene={'mesh.nx': 8, 'mesh.ny': 8, **cam})
    ep = plan(load_spec(spec))[0]
    res = run_episode(ep, tmp_path / 'a')
    assert res['status'] == 'ok', res['error']
    msgs = _messages(tmp_path / 'a' / 'episodes' / ep.id / 'bag')
    base = '/cloth_node/cameras/top'
    by = {}
    for topic, t, m in msgs:
        by.setdefault(topic, []).append((t, m))
    depth = by[f'{base}/depth/image_raw']
    assert len(depth) == 4                                  # t = 0, 0.1, 0.2, 0.3 s
    dt = ep.params['dt']
    assert [t for t, _ in depth] == [round(min(round(k / (10 * dt)), round(0.3 / dt)) * dt
                                           * 1e9) for k in range(4)]
    t, img = depth[-1]
    assert (img.width, img.height, img.encoding, img.header.frame_id) == \
        (32, 24, '32FC1', 'top_optical_frame')
    z = np.frombuffer(bytes(img.data), dtype='<f4').reshape(24, 32)
    assert np.isfinite(z).any()                             # the table or the cloth
    for topic in ('color/image_raw', 'camera_info', 'points', 'pose_out'):
        assert [s for s, _ in by[f'{base}/{topic}']] == [s for s, _ in depth], topic
    again = run_episode(ep, tmp_path / 'b')
    assert again['bag_sha256'] == res['bag_sha256']
    # the scene's cameras.names replaced the base's set: table.yaml's 'side' is gone
    assert not any(k.startswith('cameras.side') for k in ep.params)
    assert not any('/cameras/side/' in topic for topic in by)
    bad = small_spec(episodes=1, scene={**spec['scene'], 'cameras.top.fov': 0.0})
    with pytest.raises(SpecError, match='cameras.top: fov must be in'):
        load_spec(bad)


def test_pick_and_place_grasps_the_top_and_moves_it(tmp_path):
    spec = small_spec(episodes=1, duration=2.5, init='flat', base='',
                      scene={'mesh.nx': 8, 'mesh.ny': 8, 'pinned.sets': ['none'],
                             'obstacles.names': ['ground'],
                             'obstacles.ground.shape': 'plane',
                             'obstacles.ground.point': [0.0, 0.0, -0.005]},
                      randomize={},
                      policy={'pick_place': {'handles': 2, 'moves': 1, 'radius': 0.08,
                                             'lift': 0.2, 'speed': 1.0}})
    ep = plan(load_spec(spec))[0]
    res = run_episode(ep, tmp_path)
    assert res['status'] == 'ok', res['error']
    msgs = _messages(tmp_path / 'episodes' / ep.id / 'bag')
    for name in ('h0', 'h1'):
        w = [m.wrench.force.z for t, _, m in msgs if t == f'/cloth_node/handles/{name}/wrench']
        assert max(w) > 0.0 and w[0] == 0.0 and w[-1] == 0.0    # held, then let go
    # lifted 0.2 m at 1 m/s: up by 0.2 s (and the mesh at 20 Hz)
    meshes = [m for t, _, m in msgs if t == '/cloth_node/mesh']
    assert max(p.z for p in meshes[4].markers[0].points) > 0.15
    # the handles' path was planned from the places drawn up front
    assert len(ep.policy['places'][0]) == 2
    assert res['metrics']['peak_handle_force'] > 0


def test_a_script_policy_gets_the_simulator_and_the_episode_generator(tmp_path,
                                                                    monkeypatch):
    monkeypatch.setenv('BATCH_SCRIPT_OUT', str(tmp_path))
    sys.path.insert(0, str(HERE / 'data'))
    try:
        spec = small_spec(episodes=2, policy={'script': 'batch_script:push_up'},
                          randomize={})
        eps = plan(load_spec(spec))
        res = [run_episode(ep, tmp_path) for ep in eps]
    finally:
        sys.path.remove(str(HERE / 'data'))
    assert [r['status'] for r in res] == ['ok', 'ok']
    for ep in eps:
        marks = json.loads((tmp_path / f'script_{ep.id}.json').read_text())
        assert marks['seed'] == ep.seed and marks['steps'] == round(0.3 / ep.params['dt'])
        assert marks['draw'] == np.random.default_rng(ep.seed).random()
        msgs = _messages(tmp_path / 'episodes' / ep.id / 'bag')
        z = [np.mean([p.z for p in m.markers[0].points]) for t, _, m in msgs
             if t == '/cloth_node/mesh']
        assert len(z) == 7                      # recorded at the spec's rate meanwhile
        assert z[-1] > z[0] + 0.01              # the script's push lifted it
    assert res[0]['sim_time'] == pytest.approx(0.3, abs=1e-3)


def test_coverage_of_a_flat_cloth_is_its_area():
    from cosserat_ros.core.mesh import grid_mesh
    m = grid_mesh(20, 20, 0.7, 0.5)
    assert coverage(m.vertices, m.faces) == pytest.approx(0.35, rel=0.01)
    folded = m.vertices.copy()
    c = folded[:, 0].mean()
    folded[:, 0] = c + np.abs(folded[:, 0] - c)                 # the left half folded over
    assert coverage(folded, m.faces) == pytest.approx(0.175, rel=0.02)


def test_a_loaded_spec_loads_again_to_itself():
    s = load_spec(small_spec(policy={'pick_place': {'handles': 2}}))
    assert load_spec(s) == s
    assert load_spec(json.loads(json.dumps(s))) == s
    s = load_spec(small_spec(init='flat', policy={'script': 'json:dumps'}))
    assert load_spec(s) == s


@pytest.mark.slow
@pytest.mark.parametrize('name', ['table_drop', 'pick_place', 'flag_gusts'])
def test_the_shipped_example_specs_load_and_their_first_episode_runs(name, tmp_path):
    """The examples of config/batch/, as installed (their ``base`` resolves beside
    them), each with its first episode cut to 0.2 s."""
    share = PREFIX / 'share' / 'cosserat_ros' / 'config' / 'batch'
    spec = load_spec(share / f'{name}.yaml')
    assert spec['episodes'] >= 50
    spec['duration'] = 0.2
    res = run_episode(plan(spec)[0], tmp_path)
    assert res['status'] == 'ok', res['error']


def test_crumple_lifts_the_cloth_at_random_points_and_drops_it(tmp_path):
    spec = small_spec(episodes=1, duration=2.0, base='', randomize={},
                      scene={'mesh.nx': 8, 'mesh.ny': 8, 'pinned.sets': ['none'],
                             'obstacles.names': ['ground'],
                             'obstacles.ground.shape': 'plane'},
                      init={'crumple': {'height': 0.3, 'lifts': 1}})
    ep = plan(load_spec(spec))[0]
    assert len(ep.init['picks']) == 1
    res = run_episode(ep, tmp_path)
    assert res['status'] == 'ok', res['error']
    msgs = _messages(tmp_path / 'episodes' / ep.id / 'bag')
    z = [np.array([p.z for p in m.markers[0].points]) for t, _, m in msgs
         if t == '/cloth_node/mesh']
    assert max(zi.max() for zi in z) > 0.5          # lifted from 0.3 m by 0.3 m
    assert np.median(z[-1]) < 0.03                  # and fallen back onto the ground
    assert res['metrics']['coverage'] < 0.95        # no longer a flat square metre
