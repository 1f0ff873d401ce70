"""record and render against a live cloth_node, read back with an independent reader."""
import os
import signal
import subprocess
import time
import warnings

from ament_index_python.packages import get_package_prefix

import numpy as np
import pytest
from PIL import Image
from rosbags.highlevel import AnyReader
from rosbags.typesys import get_typestore, Stores

RATE = 20.0
NX = 10


def exe(name):
    return os.path.join(get_package_prefix('cosserat_ros'), 'lib', 'cosserat_ros', name)


@pytest.fixture(scope='module')
def node(tmp_path_factory):
    d = tmp_path_factory.mktemp('node')
    params = d / 'p.yaml'
    params.write_text(f'cloth_node:\n  ros__parameters:\n    mesh: {{nx: {NX}, ny: {NX}}}\n'
                      f'    publish_rate: {RATE}\n    status_period: 0.0\n'
                      '    cameras: {names: [top], top: {width: 24, height: 16, rate: 10.0}}\n')
    proc = subprocess.Popen([exe('cloth_node'), '--ros-args', '--params-file', str(params)],
                            stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True)
    yield proc
    proc.send_signal(signal.SIGINT)
    proc.communicate(timeout=20)


def record(out, *args, **kw):
    # --wait: a node started with a cold numba cache compiles its kernels first
    return subprocess.run([exe('record'), '-o', str(out), '--wait', '150', *args],
                          capture_output=True, text=True, timeout=kw.get('timeout', 240))


@pytest.fixture(scope='module')
def bag(node, tmp_path_factory):
    out = tmp_path_factory.mktemp('bags') / 'cloth'
    res = record(out, '--duration', '4')
    assert res.returncode == 0, res.stderr
    return out


def assert_logged_on_the_sim_clock(log_t, stamp):
    """Each message of a topic published once per tick is logged at the recorder's sim
    time of arrival: not before the previous tick (the recorder's clock may not yet have
    taken this tick's /clock), not after a period past the next tick (the recorder is at
    most one tick behind). Not 'within two periods of its own stamp': the latched first
    message is the last one published before the recorder subscribed, and on a loaded
    2-core host the node's next tick can come late (a CI run saw a first mesh at
    144.4 ms, the next at 267.4 ms, every later one logged at its stamp exactly)."""
    log_t, stamp = np.asarray(log_t), np.asarray(stamp)
    early = np.flatnonzero(log_t[1:] < stamp[:-1]) + 1
    late = np.flatnonzero(log_t[:-1] > stamp[1:] + 1e9 / RATE)
    assert not len(early) and not len(late), [(i, log_t[i], stamp[i]) for i in [*early, *late]]
    assert stamp[0] - 1e9 / RATE <= log_t[0] and log_t[-1] <= stamp[-1] + 2e9 / RATE


def test_recorded_bag_reads_back_with_an_independent_reader(bag):
    assert (bag / 'metadata.yaml').is_file() and (bag / 'cloth.mcap').is_file()
    store = get_typestore(Stores.ROS2_JAZZY)
    stamps = {}
    sim_stamps = {'/cloth_node/mesh': [], '/cloth_node/energy': []}
    with AnyReader([bag], default_typestore=store) as reader:
        topics = {c.topic: c.msgtype for c in reader.connections}
        assert topics['/cloth_node/mesh'] == 'visualization_msgs/msg/MarkerArray'
        assert topics['/cloth_node/energy'] == 'diagnostic_msgs/msg/DiagnosticArray'
        assert topics['/diagnostics'] == 'diagnostic_msgs/msg/DiagnosticArray'
        assert topics['/clock'] == 'rosgraph_msgs/msg/Clock'
        for conn, t, raw in reader.messages():
            msg = reader.deserialize(raw, conn.msgtype)       # every message, its own type
            stamps.setdefault(conn.topic, []).append(t)
            if conn.topic == '/cloth_node/mesh':
                tri = msg.markers[0]
                assert len(tri.points) == 3 * 2 * NX * NX     # 3 corners x faces
                assert len(tri.colors) == len(tri.points)
                head = tri.header
            elif conn.topic == '/cloth_node/energy':
                head = msg.header
            if conn.topic in sim_stamps:
                sim_stamps[conn.topic].append(head.stamp.sec * 10 ** 9 + head.stamp.nanosec)
        duration = (reader.end_time - reader.start_time) * 1e-9
    for topic, ts in stamps.items():
        assert np.all(np.diff(ts) >= 0), topic                # sim time, no reset: monotonic
    # log times are simulation time: each mesh is logged within two publish periods of
    # its header stamp (the node publishes /clock first, so mostly at the stamp itself)
    n_mesh = len(stamps['/cloth_node/mesh'])
    # each tick publishes a mesh and an energy message with the same simulation-time stamp;
    # the two subscriptions match the publisher at slightly different moments, so compare
    # the ticks inside the window both topics cover
    mesh_t, energy_t = (np.array(sim_stamps[t]) for t in sim_stamps)
    lo, hi = max(mesh_t.min(), energy_t.min()), min(mesh_t.max(), energy_t.max())
    inside = [set(a[(a >= lo) & (a <= hi)].tolist()) for a in (mesh_t, energy_t)]
    assert inside[0] == inside[1]
    assert len(inside[0]) >= min(len(mesh_t), len(energy_t)) - 5
    log_t = np.array(stamps['/cloth_node/mesh'])
    assert_logged_on_the_sim_clock(log_t, mesh_t)
    assert 0.6 * RATE * duration <= n_mesh <= 1.2 * RATE * duration + 2, (n_mesh, duration)
    assert 1 <= len(stamps['/diagnostics']) <= duration + 2


def test_bag_crcs_check_out_with_the_mcap_reader(bag):
    # Foxglove's own reader, with CRC validation: every chunk, the data section and the
    # summary carry a CRC (a bag with zeros would pass unchecked), and a flipped byte fails
    import io
    from mcap.reader import make_reader
    from mcap.records import DataEnd, Footer
    from mcap.stream_reader import CRCValidationError, StreamReader
    data = (bag / 'cloth.mcap').read_bytes()
    reader = make_reader(io.BytesIO(data), validate_crcs=True)
    n = sum(1 for _ in reader.iter_messages())
    summary = reader.get_summary()
    assert n == summary.statistics.message_count > 0
    assert {c.topic for c in summary.channels.values()} >= {'/cloth_node/mesh', '/clock'}
    records = list(StreamReader(io.BytesIO(data), validate_crcs=True).records)
    assert [r.data_section_crc for r in records if isinstance(r, DataEnd)][0] != 0
    assert [r.summary_crc for r in records if isinstance(r, Footer)][0] != 0
    bad = bytearray(data)
    bad[len(data) // 3] ^= 0xFF
    with pytest.raises(CRCValidationError):
        list(make_reader(io.BytesIO(bytes(bad)), validate_crcs=True).iter_messages())


def test_every_message_decodes_with_mcap_ros2_support(bag):
    # mcap-ros2-support decodes CDR from the schema text in the file alone (no ROS types):
    # the ros2msg definitions the recorder writes are complete
    from mcap.reader import make_reader
    from mcap_ros2.decoder import DecoderFactory
    with AnyReader([bag]) as reader:
        expected = reader.message_count
    count, kinds = 0, {}
    with open(bag / 'cloth.mcap', 'rb') as fh:
        reader = make_reader(fh, decoder_factories=[DecoderFactory()])
        clocks = []
        for _, channel, message, ros_msg in reader.iter_decoded_messages():
            count += 1
            kinds.setdefault(channel.topic, type(ros_msg).__name__)
            if channel.topic == '/cloth_node/mesh':
                assert len(ros_msg.markers[0].points) == 3 * 2 * NX * NX
            elif channel.topic == '/clock':
                clocks.append((message.log_time,
                               ros_msg.clock.sec * 10 ** 9 + ros_msg.clock.nanosec))
    log_t, t = np.array(clocks).T
    assert_logged_on_the_sim_clock(log_t, t)
    assert count == expected > 0
    assert set(kinds) == {'/cloth_node/mesh', '/cloth_node/energy', '/diagnostics', '/clock'}


def test_a_camera_is_recorded_when_asked(node, tmp_path):
    out = tmp_path / 'cam'
    res = record(out, '--duration', '3', '--camera', 'top', '/clock')
    assert res.returncode == 0, res.stderr
    base = '/cloth_node/cameras/top'
    stamps = {}
    with AnyReader([out]) as reader:
        topics = {c.topic: c.msgtype for c in reader.connections}
        assert topics == {'/clock': 'rosgraph_msgs/msg/Clock',
                          f'{base}/depth/image_raw': 'sensor_msgs/msg/Image',
                          f'{base}/color/image_raw': 'sensor_msgs/msg/Image',
                          f'{base}/camera_info': 'sensor_msgs/msg/CameraInfo',
                          f'{base}/pose_out': 'geometry_msgs/msg/PoseStamped'}
        for conn, t, raw in reader.messages():
            if conn.topic == '/clock':
                continue
            msg = reader.deserialize(raw, conn.msgtype)
            stamps.setdefault(conn.topic, []).append(msg.header.stamp.sec * 10 ** 9
                                                     + msg.header.stamp.nanosec)
            if conn.topic.endswith('depth/image_raw'):
                assert (msg.width, msg.height, msg.encoding, len(msg.data)) == \
                    (24, 16, '32FC1', 24 * 16 * 4)
    assert len(stamps[f'{base}/depth/image_raw']) >= 5
    # the images, their info and the pose of one instant carry one stamp
    common = set.intersection(*(set(v) for v in stamps.values()))
    assert len(common) >= len(stamps[f'{base}/depth/image_raw']) - 2
    res = record(tmp_path / 'bad', '--camera', 'a/b')
    assert res.returncode == 2 and res.stderr.count('\n') == 1, res.stderr


def test_metadata_follows_rosbag2_version_9(bag, node):
    # field by field, as rosbag2 Jazzy writes and reads it; type hashes equal to what
    # rclpy reports for the node's publishers
    import rclpy
    import yaml
    from rclpy.context import Context
    meta = yaml.safe_load((bag / 'metadata.yaml').read_text())['rosbag2_bagfile_information']
    assert meta['version'] == 9 and meta['storage_identifier'] == 'mcap'
    assert meta['relative_file_paths'] == ['cloth.mcap']
    assert meta['compression_format'] == '' and meta['compression_mode'] == ''
    (f,) = meta['files']
    assert f['path'] == 'cloth.mcap' and f['message_count'] == meta['message_count']
    assert f['starting_time'] == meta['starting_time'] and f['duration'] == meta['duration']
    topics = {t['topic_metadata']['name']: t for t in meta['topics_with_message_count']}
    assert sum(t['message_count'] for t in topics.values()) == meta['message_count']
    from mcap.reader import make_reader
    with open(bag / 'cloth.mcap', 'rb') as fh:
        summary = make_reader(fh).get_summary()
    stats = summary.statistics
    counts = {summary.channels[cid].topic: n
              for cid, n in stats.channel_message_counts.items()}
    assert {k: v['message_count'] for k, v in topics.items()} == counts
    assert meta['starting_time']['nanoseconds_since_epoch'] == stats.message_start_time
    assert meta['duration']['nanoseconds'] == (stats.message_end_time
                                               - stats.message_start_time)
    qos_keys = {'history', 'depth', 'reliability', 'durability', 'deadline', 'lifespan',
                'liveliness', 'liveliness_lease_duration', 'avoid_ros_namespace_conventions'}
    ctx = Context()
    rclpy.init(context=ctx)
    peer = rclpy.create_node('meta_check', context=ctx)
    try:
        for name, t in topics.items():
            md = t['topic_metadata']
            assert md['serialization_format'] == 'cdr'
            (qos,) = md['offered_qos_profiles']
            assert set(qos) == qos_keys and qos['reliability'] == 'reliable'
            assert qos['durability'] == ('transient_local' if name == '/clock' else 'volatile')
            end = time.monotonic() + 10
            infos = []
            while not infos and time.monotonic() < end:
                infos = [i for i in peer.get_publishers_info_by_topic(name)
                         if i.node_name == 'cloth_node']
                time.sleep(0.1)
            assert infos, name
            assert md['type'] == infos[0].topic_type
            assert md['type_description_hash'] == str(infos[0].topic_type_hash), name
    finally:
        peer.destroy_node()
        rclpy.shutdown(context=ctx)


def test_a_message_larger_than_a_chunk(tmp_path):
    # a 160 x 160 cloth's mesh message (~6 MB) is one message in a chunk of its own
    import io
    from mcap.reader import make_reader
    from rclpy.serialization import deserialize_message
    from visualization_msgs.msg import MarkerArray
    from cosserat_ros.mesh import grid_mesh
    from cosserat_ros.ros.conversions import colormap, mesh_marker_array
    from cosserat_ros.tools.bagfile import BagWriter, CHUNK_BYTES
    m = grid_mesh(160, 160)
    colors = colormap(m.vertices[:, 0], 0.0, 1.0)
    out = tmp_path / 'bags' / 'big'          # a parent that does not exist yet, as bags/ in
    w = BagWriter(out)                       # the README's `record -o bags/...` on a clone
    w.add('/cloth_node/mesh', 'visualization_msgs/msg/MarkerArray')
    sizes = []
    for k in range(3):
        data = mesh_marker_array(m.vertices + k, m.faces, colors, k * 10 ** 8, 'world')
        sizes.append(len(data))
        w.write('/cloth_node/mesh', k * 10 ** 8, data)
    w.close()
    assert min(sizes) > CHUNK_BYTES
    raw = (out / 'big.mcap').read_bytes()
    with pytest.raises(FileExistsError):      # never over an existing bag
        BagWriter(out)
    reader = make_reader(io.BytesIO(raw), validate_crcs=True)
    got = [(msg.log_time, msg.data) for _, _, msg in reader.iter_messages()]
    assert [t for t, _ in got] == [0, 10 ** 8, 2 * 10 ** 8]
    assert len(reader.get_summary().chunk_indexes) == 3
    for k, (_, data) in enumerate(got):
        tri = deserialize_message(data, MarkerArray).markers[0]
        assert len(tri.points) == 3 * m.n_faces and tri.points[0].x == pytest.approx(
            m.vertices[m.faces[0, 0], 0] + k)
    with AnyReader([out]) as reader:
        assert reader.message_count == 3


def test_a_write_failure_stops_the_recorder_with_a_readable_bag(node, tmp_path):
    # a file-size limit stands in for a full disk: the recorder stops with one line and
    # exit 1, and what it wrote before is a complete bag (metadata.yaml included)
    import resource
    from mcap.reader import make_reader
    out = tmp_path / 'limited'

    def limit():
        resource.setrlimit(resource.RLIMIT_FSIZE, (1_500_000, 1_500_000))
    res = subprocess.run([exe('record'), '-o', str(out), '--wait', '150', '--duration', '60'],
                         capture_output=True, text=True, timeout=120, preexec_fn=limit)
    assert res.returncode == 1, res.stderr
    assert 'Traceback' not in res.stderr
    errors = [ln for ln in res.stderr.splitlines() if 'error' in ln.lower()]
    assert len(errors) == 1 and 'File too large' in errors[0], res.stderr
    assert (out / 'metadata.yaml').is_file()
    with AnyReader([out]) as reader:
        count = reader.message_count
        got = sum(1 for _ in reader.messages())
    assert count == got > 0
    with open(out / 'limited.mcap', 'rb') as fh:
        assert sum(1 for _ in make_reader(fh, validate_crcs=True).iter_messages()) == count


def test_clock_is_in_every_default_recording(node, tmp_path):
    # /clock used to be left out of a recording now and then (7 of 23) when discovery
    # showed it a moment after the other topics: 10 of 10 must have it
    outs = [tmp_path / f'r{i}' for i in range(10)]
    for batch in (outs[:5], outs[5:]):
        procs = [subprocess.Popen([exe('record'), '-o', str(o), '--wait', '150',
                                   '--duration', '1'], stdout=subprocess.DEVNULL,
                                  stderr=subprocess.PIPE, text=True) for o in batch]
        for p in procs:
            _, err = p.communicate(timeout=120)
            assert p.returncode == 0, err
    for o in outs:
        with AnyReader([o]) as reader:
            counts = {c.topic: c.msgcount for c in reader.connections}
        assert counts.get('/clock', 0) > 0 and counts.get('/cloth_node/mesh', 0) > 0, \
            (o.name, counts)


def test_existing_bag_is_never_overwritten(bag):
    before = sorted(os.listdir(bag)), (bag / 'cloth.mcap').stat().st_size
    res = record(bag, '--duration', '1')
    assert res.returncode == 2 and 'already exists' in res.stderr
    assert (sorted(os.listdir(bag)), (bag / 'cloth.mcap').stat().st_size) == before


def recording(out):
    """A recorder to ``out``, once it records (a fixed 4 s sleep raced the recorder's
    start-up and discovery on a slow host: SIGINT came before any message, so no bag was
    written) and a second later."""
    p = subprocess.Popen([exe('record'), '-o', str(out), '--wait', '150'],
                         stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    end = time.monotonic() + 60
    while time.monotonic() < end and not (out / f'{out.name}.mcap').exists():
        time.sleep(0.1)
    time.sleep(1.0)
    return p


def test_sigint_closes_and_a_crash_is_recoverable(node, tmp_path):
    out = tmp_path / 'interrupted'
    p = recording(out)
    p.send_signal(signal.SIGINT)
    _, err = p.communicate(timeout=30)
    assert p.returncode == 0 and 'Traceback' not in err
    with AnyReader([out]) as reader:
        assert reader.message_count > 0
    crashed = tmp_path / 'crashed'
    p = subprocess.Popen([exe('record'), '-o', str(crashed), '--wait', '150'],
                         stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    mcap = crashed / 'crashed.mcap'
    end = time.monotonic() + 60
    while time.monotonic() < end and (not mcap.exists() or mcap.stat().st_size < 3 << 20):
        time.sleep(0.2)                                       # a few 1 MiB chunks on disk
    p.kill()
    p.wait()
    assert not (crashed / 'metadata.yaml').exists()
    res = subprocess.run([exe('record'), '--recover', str(crashed)], capture_output=True,
                         text=True, timeout=60)
    assert res.returncode == 0, res.stderr
    with AnyReader([crashed]) as reader:
        msgs = [reader.deserialize(raw, c.msgtype) for c, _, raw in reader.messages()]
    assert len(msgs) >= 3
    from mcap.reader import make_reader
    with open(crashed / 'crashed.mcap', 'rb') as fh:                # the rebuilt file
        assert sum(1 for _ in make_reader(fh, validate_crcs=True).iter_messages()) == \
            len(msgs)
    # each topic keeps the QoS it was recorded with: /clock latched, depth 1 (the
    # recovery had written every topic as reliable, volatile, depth 5)
    import yaml
    meta = yaml.safe_load((crashed / 'metadata.yaml').read_text())['rosbag2_bagfile_information']
    qos = {t['topic_metadata']['name']: t['topic_metadata']['offered_qos_profiles']
           for t in meta['topics_with_message_count']}
    clock = qos['/clock'][0] if isinstance(qos['/clock'], list) else yaml.safe_load(
        qos['/clock'])[0]
    assert clock['durability'] == 'transient_local' and clock['depth'] == 1, qos['/clock']


def test_repeated_sigint_leaves_a_consistent_bag(node, tmp_path):
    """Ctrl-C only asks the recorder to stop: a burst of them (one landing inside a
    chunk's write or fsync, another inside the close) still ends in a bag whose index,
    statistics and metadata.yaml count the same messages, and no traceback."""
    import yaml
    from mcap.reader import make_reader
    out = tmp_path / 'burst'
    p = recording(out)
    for _ in range(20):
        p.send_signal(signal.SIGINT)
        time.sleep(0.002)
    _, err = p.communicate(timeout=30)
    # (one that comes while the interpreter exits, the bag written, meets Python's
    # default action again: -2)
    assert p.returncode in (0, -signal.SIGINT) and 'Traceback' not in err, err
    meta = yaml.safe_load((out / 'metadata.yaml').read_text())
    counted = meta['rosbag2_bagfile_information']['message_count']
    with open(out / 'burst.mcap', 'rb') as fh:
        read = sum(1 for _ in make_reader(fh, validate_crcs=True).iter_messages())
    with AnyReader([out]) as reader:
        assert reader.message_count == read == counted > 0


def test_record_refuses_a_place_it_cannot_write_in_one_line(node, tmp_path):
    blocked = tmp_path / 'file'
    blocked.write_text('not a directory')
    res = record(blocked / 'bag', '--duration', '1')
    assert res.returncode == 2 and 'Traceback' not in res.stderr, res.stderr
    assert 'cannot create' in res.stderr


def test_render_refuses_what_it_cannot_draw_in_one_line(tmp_path):
    empty = tmp_path / 'empty'
    empty.mkdir()
    for args, why in (([str(empty), '--frames', '0'], 'at least 1'),
                      ([str(empty)], 'cannot read')):
        res = subprocess.run([exe('render'), *args, '-o', str(tmp_path / 'o')],
                             capture_output=True, text=True, timeout=120)
        assert res.returncode == 2 and 'Traceback' not in res.stderr, res.stderr
        assert why in res.stderr


def test_render_a_recorded_bag(bag, tmp_path):
    out = tmp_path / 'pictures'
    res = subprocess.run([exe('render'), str(bag), '-o', str(out), '--frames', '12'],
                         capture_output=True, text=True, timeout=300)
    assert res.returncode == 0, res.stderr
    pngs = sorted(out.glob('cloth_*s.png'))
    assert len(pngs) == 3
    imgs = [np.asarray(Image.open(p).convert('RGB'), dtype=float) for p in pngs]
    for im in imgs:
        assert im.shape[0] > 100 and im.std() > 10                  # not blank
    assert np.abs(imgs[0] - imgs[-1]).mean() > 1.0                  # the cloth moved
    gif = Image.open(out / 'cloth.gif')
    assert gif.n_frames >= 2
    energy = np.asarray(Image.open(out / 'energy.png').convert('RGB'), dtype=float)
    assert energy.std() > 10
    res = subprocess.run([exe('render'), str(out / 'nope'), '-o', str(out)],
                         capture_output=True, text=True, timeout=60)
    assert res.returncode == 2 and 'not a bag directory' in res.stderr


def test_render_live_topics(node, bag, tmp_path):
    # `bag` first: it guarantees the node is up and publishing
    out = tmp_path / 'live'
    res = subprocess.run([exe('render'), '--live', '3', '-o', str(out), '--frames', '6'],
                         capture_output=True, text=True, timeout=300)
    assert res.returncode == 0, res.stderr
    pngs = sorted(out.glob('cloth_*s.png'))
    assert pngs and (out / 'cloth.gif').exists() and (out / 'energy.png').exists()
    assert np.asarray(Image.open(pngs[-1]).convert('RGB'), dtype=float).std() > 10
    # a node that is not there: a clear error, not an empty picture
    res = subprocess.run([exe('render'), '--live', '1', '--wait', '2', '--node', 'nobody',
                          '-o', str(tmp_path / 'none')], capture_output=True, text=True,
                         timeout=60)
    assert res.returncode == 1 and 'no mesh from /nobody/mesh' in res.stderr


def test_obstacles_are_drawn_where_the_markers_put_them(tmp_path):
    from geometry_msgs.msg import Point
    from rclpy.serialization import serialize_message
    from visualization_msgs.msg import Marker, MarkerArray
    from cosserat_ros.mesh import grid_mesh
    from cosserat_ros.ros.conversions import colormap, mesh_marker_array
    from cosserat_ros.tools.render import obstacle_polygons, render

    def marker(kind, pos, scale, q=(0.0, 0.0, 0.0, 1.0)):
        m = Marker(type=kind, action=Marker.ADD)
        m.pose.position.x, m.pose.position.y, m.pose.position.z = pos
        (m.pose.orientation.x, m.pose.orientation.y, m.pose.orientation.z,
         m.pose.orientation.w) = q
        m.scale.x, m.scale.y, m.scale.z = scale
        return m
    s = np.sqrt(0.5)
    tri = marker(Marker.TRIANGLE_LIST, (0.0, 0.0, 1.0), (1.0, 1.0, 1.0))
    tri.points = [Point(x=0.0, y=0.0, z=0.0), Point(x=0.1, y=0.0, z=0.0),
                  Point(x=0.0, y=0.1, z=0.0)]
    arr = MarkerArray(markers=[
        Marker(action=Marker.DELETEALL),
        marker(Marker.CUBE, (1.0, 2.0, 3.0), (0.2, 0.4, 0.6), (0.0, 0.0, s, s)),  # 90 deg
        marker(Marker.SPHERE, (0.0, 0.0, 0.5), (0.5, 0.5, 0.5)),
        marker(Marker.CUBE, (0.0, 0.0, -0.01), (10.0, 10.0, 0.001)),      # the plane
        marker(Marker.CYLINDER, (0.0, 1.0, 0.0), (0.2, 0.2, 1.0)), tri,
        marker(Marker.SPHERE, (50.0, 0.0, 0.0), (1.0, 1.0, 1.0))])       # out of view
    raw = serialize_message(arr)
    box, ball, plane, cyl, mesh = obstacle_polygons(raw, np.array([0.5, 1.0, 1.5]), 2.0)
    pts = box.reshape(-1, 3)
    np.testing.assert_allclose(pts.min(axis=0), [0.8, 1.9, 2.7], atol=1e-12)   # turned
    np.testing.assert_allclose(pts.max(axis=0), [1.2, 2.1, 3.3], atol=1e-12)
    np.testing.assert_allclose(np.linalg.norm(ball.reshape(-1, 3) - [0, 0, 0.5], axis=1),
                               0.25)
    p = plane.reshape(-1, 3)                               # cut to the view round (0.5, 1)
    np.testing.assert_allclose([p[:, 0].min(), p[:, 0].max(), p[:, 1].min(), p[:, 1].max()],
                               [-1.5, 2.5, -1.0, 3.0], atol=1e-12)
    c = cyl.reshape(-1, 3)
    np.testing.assert_allclose(np.hypot(c[:, 0], c[:, 1] - 1.0), 0.1)
    assert c[:, 2].min() == pytest.approx(-0.5) and c[:, 2].max() == pytest.approx(0.5)
    np.testing.assert_allclose(mesh[0], [[0, 0, 1], [0.1, 0, 1], [0, 0.1, 1]])
    # the pictures draw them beside the cloth
    m = grid_mesh(4, 4)
    meshes = [mesh_marker_array(m.vertices, m.faces, colormap(m.vertices[:, 0], 0, 1),
                                k * 10 ** 8, 'world') for k in range(3)]
    written = render(meshes, [], tmp_path, frames=3, obstacles=[(0, raw)])
    assert {p.name for p in written} >= {'cloth.gif', 'cloth_0.000s.png'}


def test_render_follows_a_reset_by_recording_order(tmp_path, monkeypatch):
    """A bag spanning ~/reset has the node's times twice: each picture is drawn with the
    obstacles recorded before it (not those of the first run's same time), its file is
    not written over by the second run's picture of the same time, and the energy plot
    draws each run as a line of its own."""
    from rclpy.serialization import serialize_message
    from visualization_msgs.msg import Marker, MarkerArray
    from cosserat_ros.mesh import grid_mesh
    from cosserat_ros.ros.conversions import colormap, mesh_marker_array
    from cosserat_ros.tools import render as rd

    def ball(z):
        m = Marker(type=Marker.SPHERE, action=Marker.ADD)
        m.pose.position.z, m.pose.orientation.w = z, 1.0
        m.scale.x = m.scale.y = m.scale.z = 0.2
        return serialize_message(MarkerArray(markers=[m]))
    m = grid_mesh(4, 4)
    # times 0, 0.1 | reset | 0, 0.1 | reset | 0: five meshes, a ball at a new height each run
    meshes = [mesh_marker_array(m.vertices, m.faces, colormap(m.vertices[:, 0], 0, 1),
                                k % 2 * 10 ** 8, 'world') for k in range(5)]
    drawn = []
    real = rd.render_frame
    monkeypatch.setattr(rd, 'render_frame', lambda ax, *a: (drawn.append(
        (a[0], [float(np.mean(p.reshape(-1, 3)[:, 2])) for p in a[-1]])), real(ax, *a)))
    written = rd.render(meshes, [], tmp_path, frames=5,
                        obstacles=[(0, ball(0.1)), (2, ball(0.2)), (4, ball(0.3))])
    stills = drawn[:3]                        # meshes 0, 2, 4, all at t = 0
    assert [t for t, _ in stills] == [0.0, 0.0, 0.0]
    assert [z for _, z in stills] == [pytest.approx([0.1]), pytest.approx([0.2]),
                                      pytest.approx([0.3])]
    pngs = [p for p in written if p.suffix == '.png']
    assert len(set(pngs)) == 3 and all(p.exists() for p in pngs)
    lines = []
    real_plot = rd.plt.Axes.plot
    monkeypatch.setattr(rd.plt.Axes, 'plot', lambda self, x, y, **kw: (
        lines.append(x), real_plot(self, x, y, **kw))[1])
    from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus, KeyValue
    energies = [serialize_message(DiagnosticArray(status=[DiagnosticStatus(values=[
        KeyValue(key='sim_time', value=str(t)), KeyValue(key='kinetic', value='1.0')])]))
        for t in (0.0, 0.1, 0.0, 0.1)]
    rd.energy_plot(energies, tmp_path / 'energy.png')
    assert lines and np.isnan(lines[0]).sum() == 1        # two runs, one break
    # messages without any energy: an empty plot, without a legend of nothing
    bare = [serialize_message(DiagnosticArray(status=[DiagnosticStatus(values=[
        KeyValue(key='sim_time', value='0.0')])]))]
    with warnings.catch_warnings():
        warnings.simplefilter('error')
        rd.energy_plot(bare, tmp_path / 'bare.png')
    assert (tmp_path / 'bare.png').exists()


def test_a_best_effort_publisher_is_recorded(tmp_path):
    """A topic whose publisher is best-effort (a sensor driver's usual QoS): the recorder
    subscribes best-effort too (a reliable subscription hears nothing from it)."""
    import rclpy
    from rclpy.context import Context
    from rclpy.qos import QoSProfile, ReliabilityPolicy
    from std_msgs.msg import String
    ctx = Context()
    rclpy.init(context=ctx)
    node = rclpy.create_node('best_effort_talker', context=ctx)
    pub = node.create_publisher(String, '/best_effort_chatter',
                                QoSProfile(depth=10, reliability=ReliabilityPolicy.BEST_EFFORT))
    out = tmp_path / 'best_effort'
    try:
        p = subprocess.Popen([exe('record'), '-o', str(out), '--wait', '60', '--wall-time',
                              '--duration', '2', '/best_effort_chatter'],
                             stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
        end = time.monotonic() + 90
        while p.poll() is None and time.monotonic() < end:
            pub.publish(String(data='hello'))
            time.sleep(0.02)
        _, err = p.communicate(timeout=30)
    finally:
        node.destroy_node()
        rclpy.shutdown(context=ctx)
    assert p.returncode == 0, err
    with AnyReader([out]) as reader:
        assert reader.message_count > 10


def test_a_reset_while_recording_keeps_the_log_times_going_forward(node, tmp_path):
    """~/reset sends the node's /clock back to 0: the recorder's log times continue from
    where they were (a player sorts by log time, and would interleave the two runs), while
    the recorded /clock messages themselves go back."""
    import rclpy
    from rclpy.context import Context
    from rclpy.executors import SingleThreadedExecutor
    from std_srvs.srv import Trigger
    from mcap.reader import make_reader
    out = tmp_path / 'reset'
    p = recording(out)
    ctx = Context()
    rclpy.init(context=ctx)
    client_node = rclpy.create_node('resetter', context=ctx)
    try:
        cli = client_node.create_client(Trigger, '/cloth_node/reset')
        assert cli.wait_for_service(timeout_sec=30)
        time.sleep(1.0)                          # the clock well past the reset's 0
        fut = cli.call_async(Trigger.Request())
        executor = SingleThreadedExecutor(context=ctx)
        executor.add_node(client_node)
        executor.spin_until_future_complete(fut, timeout_sec=30)
        assert fut.result() is not None and fut.result().success
        time.sleep(1.5)
    finally:
        client_node.destroy_node()
        rclpy.shutdown(context=ctx)
    p.send_signal(signal.SIGINT)
    _, err = p.communicate(timeout=30)
    assert p.returncode == 0, err
    store = get_typestore(Stores.ROS2_JAZZY)
    log_times, clock = [], []
    with open(out / 'reset.mcap', 'rb') as fh:
        for _, channel, message in make_reader(fh).iter_messages(log_time_order=False):
            log_times.append(message.log_time)
            if channel.topic == '/clock':
                msg = store.deserialize_cdr(message.data, 'rosgraph_msgs/msg/Clock')
                clock.append(msg.clock.sec * 10 ** 9 + msg.clock.nanosec)
    assert np.all(np.diff(log_times) >= 0)                   # in the file's own order
    assert np.any(np.diff(clock) < -5e8), clock              # the reset is in the bag
