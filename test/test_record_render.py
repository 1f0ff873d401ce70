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

# the record and render executables against a node process (make test, not test-fast)
pytestmark = pytest.mark.process

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
def bag_run(node, tmp_path_factory):
    """A default recording (zstd-compressed chunks) of 4 s of simulation time, and its
    completed process (output piped: no progress line in it)."""
    out = tmp_path_factory.mktemp('bags') / 'cloth'
    res = record(out, '--duration', '4')
    assert res.returncode == 0, res.stderr
    return out, res


@pytest.fixture(scope='module')
def bag(bag_run):
    return bag_run[0]


#: [s] the most simulation time one tick of the node can advance: a period of wall time
#: since the last tick (at most 4 periods) plus what earlier ticks fell short by (at most
#: one period; cosserat_ros.ros.pacing). On a busy host the ticks come late and each
#: advances more: a bound on simulation time, whatever the host's speed.
MAX_TICK = 5.0 / RATE


#: [ns] how far a message's log time may lie from its stamp: the recorder's lag behind the
#: node (its clock is the last /clock it took), in simulation time. Generous: a safety net
#: for a loaded host, still nine orders of magnitude below a wall-clock log time.
MAX_LAG = 2 * 10 ** 9


def assert_logged_on_the_sim_clock(log_t, stamp):
    """Each message is logged at the recorder's simulation time when it took it (the last
    /clock it received), not at a wall-clock time: the log times never go back, each lies
    within MAX_LAG of the message's stamp, and their median offset is within one period
    (the node publishes /clock before the state of the same tick: mostly logged at the
    stamp itself). No tighter bound per message: how far behind the recorder runs is the
    host's load (a first mesh logged 123 ms before its stamp, the latched /clock it
    started on, and ticks that came late on a loaded 2-core CI host)."""
    log_t, stamp = np.asarray(log_t, dtype=np.int64), np.asarray(stamp, dtype=np.int64)
    off = log_t - stamp
    assert np.all(np.diff(log_t) >= 0)
    far = np.flatnonzero(np.abs(off) > MAX_LAG)
    assert not len(far), [(i, log_t[i], stamp[i]) for i in far[:5]]
    assert abs(np.median(off)) <= 1e9 / RATE, np.median(off)


def sim_stamp(msg):
    """The simulation time [ns] of a deserialised message (a header's stamp, a Clock's,
    a MarkerArray's first marker's)."""
    stamp = (msg.clock if hasattr(msg, 'clock') else
             msg.markers[0].header.stamp if hasattr(msg, 'markers') else msg.header.stamp)
    return stamp.sec * 10 ** 9 + stamp.nanosec


def test_recorded_bag_reads_back_with_an_independent_reader(bag):
    assert (bag / 'metadata.yaml').is_file() and (bag / 'cloth.mcap').is_file()
    store = get_typestore(Stores.ROS2_JAZZY)
    stamps = {}
    sim_stamps = {'/cloth_node/mesh': [], '/cloth_node/energy': [], '/clock': []}
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
            if conn.topic in sim_stamps:
                sim_stamps[conn.topic].append(sim_stamp(msg))
    for topic, ts in stamps.items():
        assert np.all(np.diff(ts) >= 0), topic                # sim time, no reset: monotonic
    # each tick publishes a mesh and an energy message with the same simulation-time stamp;
    # the two subscriptions match the publisher at slightly different moments, so compare
    # the ticks inside the window both topics cover
    mesh_t, energy_t, clock_t = (np.array(sim_stamps[t]) for t in sim_stamps)
    lo, hi = max(mesh_t.min(), energy_t.min()), min(mesh_t.max(), energy_t.max())
    inside = [set(a[(a >= lo) & (a <= hi)].tolist()) for a in (mesh_t, energy_t)]
    assert inside[0] == inside[1]
    assert len(inside[0]) >= min(len(mesh_t), len(energy_t)) - 5
    assert np.all(np.diff(mesh_t) > 0)                    # one mesh per tick, none twice
    assert_logged_on_the_sim_clock(stamps['/cloth_node/mesh'], mesh_t)
    # --duration 4 is simulation time: every topic's stamps span at most 4 s, and the
    # longest within a tick of it (the recorder stops at the first message past the end,
    # a tick after its topic's last); a tick advances at most MAX_TICK, so 4 s hold that
    # many meshes at least, however slow the node ran
    spans = [ts.max() - ts.min() for ts in (mesh_t, energy_t, clock_t)]
    assert max(spans) <= 4 * 10 ** 9 and max(spans) > (4 - MAX_TICK) * 1e9, spans
    assert len(mesh_t) >= (4 - MAX_TICK) / MAX_TICK, len(mesh_t)
    # /diagnostics comes once a second of wall time: how many depends on the node's speed
    assert len(stamps['/diagnostics']) >= 1


def test_bag_crcs_check_out_with_the_mcap_reader(bag):
    # Foxglove's own reader, with CRC validation: every chunk, the data section and the
    # summary carry a CRC (a bag with zeros would pass unchecked), and a flipped byte fails
    # (inside a zstd chunk, the decoder notices it first; test_bag_compression.py flips
    # one in a chunk stored uncompressed too)
    import io
    import zstandard
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
    with pytest.raises((CRCValidationError, zstandard.ZstdError)):
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
                clocks.append((message.log_time, sim_stamp(ros_msg)))
    log_t, t = np.array(clocks).T
    assert_logged_on_the_sim_clock(log_t, t)
    assert count == expected > 0
    assert set(kinds) == {'/cloth_node/mesh', '/cloth_node/energy', '/diagnostics', '/clock'}


def test_the_recorder_compresses_with_zstd_and_says_how_much(bag_run):
    """By default every chunk is zstd-compressed: three independent readers (mcap with
    every CRC checked, rosbags, the recovery's own scan) read the same messages, bit for
    bit; the last line gives the size, per second of simulation time, and the ratio; a
    pipe gets no progress line."""
    import io
    import re
    from mcap.reader import make_reader
    from cosserat_ros.tools.record import scan_mcap
    bag, res = bag_run
    data = (bag / 'cloth.mcap').read_bytes()
    reader = make_reader(io.BytesIO(data), validate_crcs=True)
    got = [(c.topic, m.log_time, bytes(m.data))
           for _, c, m in reader.iter_messages(log_time_order=False)]
    chunks = reader.get_summary().chunk_indexes
    assert chunks and {c.compression for c in chunks} == {'zstd'}
    assert all(c.compressed_size < c.uncompressed_size for c in chunks)
    with AnyReader([bag]) as r:
        assert [(c.topic, t, bytes(raw)) for c, t, raw in r.messages()] == got
    assert [(topic, t, raw) for topic, _, _, t, raw in scan_mcap(bag / 'cloth.mcap')] == got
    assert len(got) > 100
    m = re.search(r'^record: wrote (\d+) messages to \S+ \(([\d.]+) MB, ([\d.]+) MB per second '
                  r'of simulation time, zstd: ([\d.]+) times smaller than uncompressed\); '
                  r'([\d.]+) s of simulation time; ', res.stdout, re.M)
    assert m, res.stdout
    n, mb, rate, ratio, sim = (float(g) for g in m.groups())
    assert n == len(got) and mb == round(len(data) / 1e6, 1)
    assert rate == pytest.approx(mb / sim, abs=0.01 + 0.05 * mb / sim)
    stored = sum(c.compressed_size for c in chunks)
    plain = sum(c.uncompressed_size for c in chunks)
    assert ratio > 2 and ratio == pytest.approx((len(data) - stored + plain) / len(data),
                                                abs=0.06)
    assert '\r' not in res.stdout + res.stderr and ' MB\n' not in res.stderr


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


def test_nothing_recorded_is_an_error_in_one_line(tmp_path):
    """No publisher of the topics within --wait (wall clock), or publishers that send
    nothing within --wait more: exit 1, one line on stderr saying nothing was recorded and
    why, no 'wrote 0 messages' and no empty bag left behind (the recorder used to wait,
    write an empty bag and exit 0)."""
    import rclpy
    from rclpy.context import Context
    from visualization_msgs.msg import MarkerArray
    out = tmp_path / 'none'
    res = subprocess.run([exe('record'), '-o', str(out), '--wait', '2', '--node', 'nobody',
                          '~/mesh', '~/energy'], capture_output=True, text=True, timeout=60)
    assert res.returncode == 1, (res.stdout, res.stderr)
    assert res.stderr.count('\n') == 1 and 'Traceback' not in res.stderr, res.stderr
    assert 'nothing recorded: no publisher of /nobody/mesh, /nobody/energy within 2 s' \
        in res.stderr
    assert not out.exists() and 'wrote' not in res.stdout
    # the topic has a publisher (its node is up) that sends nothing
    ctx = Context()
    rclpy.init(context=ctx)
    silent = rclpy.create_node('silent', context=ctx)
    silent.create_publisher(MarkerArray, '/nobody/mesh', 5)
    try:
        res = subprocess.run([exe('record'), '-o', str(out), '--wait', '15', '--node',
                              'nobody', '~/mesh'], capture_output=True, text=True, timeout=120)
    finally:
        silent.destroy_node()
        rclpy.shutdown(context=ctx)
    assert res.returncode == 1, (res.stdout, res.stderr)
    assert res.stderr.count('\n') == 1 and 'Traceback' not in res.stderr, res.stderr
    assert 'nothing recorded: the publishers of /nobody/mesh sent no message within 15 s' \
        in res.stderr
    assert not out.exists() and 'wrote' not in res.stdout


def stamps_of(bag_dir, topic):
    """The simulation times [ns] of ``topic``'s messages in a bag, in recording order."""
    with AnyReader([bag_dir]) as reader:
        conns = [c for c in reader.connections if c.topic == topic]
        return np.array([sim_stamp(reader.deserialize(raw, c.msgtype))
                         for c, _, raw in reader.messages(connections=conns)])


def _run_through_pause(cmd, name, timeout):
    """Start ``cmd`` (a tool that subscribes as node ``name``), pause the node for 4 s of
    wall time once it has subscribed, and let it finish; returns (the process, its
    ``poll()`` at the end of the pause: None while it still runs, its stderr)."""
    pauser = Pauser()
    p = subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    try:
        pauser.wait_for_subscriber(name, p)
        pauser.pause(True)
        try:
            time.sleep(4.0)                      # wall time, no simulation time
            during = p.poll()
        finally:
            pauser.pause(False)
        _, err = p.communicate(timeout=timeout)
    except BaseException:
        p.kill()
        p.communicate()
        raise
    finally:
        pauser.close()
    return p, during, err


def test_duration_counts_simulation_time_through_a_pause(node, bag, tmp_path):
    """--duration is simulation time: with the node paused right after the recorder
    subscribed (its clock stands still for 4 s of wall time), the recorder is still
    recording at the end of the pause, and the bag's stamps span the duration within a
    tick, as they would with the node at full speed. A wall-clock duration ended during the
    pause with a fraction of it. (``bag`` first: the node is up and publishing.)"""
    out = tmp_path / 'paused'
    p, during, err = _run_through_pause(
        [exe('record'), '-o', str(out), '--wait', '150', '--duration', '3', '--ros-args',
         '-r', '__node:=paused_rec'], 'paused_rec', timeout=180)
    assert during is None, err                  # still recording through the pause
    assert p.returncode == 0, err
    clock = stamps_of(out, '/clock')
    mesh = stamps_of(out, '/cloth_node/mesh')
    # the pause is inside the recording: the paused node sent its state again, same stamp
    assert np.sum(np.diff(clock) == 0) >= 2, np.diff(clock)
    spans = [clock.max() - clock.min(), mesh.max() - mesh.min()]
    assert max(spans) <= 3 * 10 ** 9 and max(spans) > (3 - MAX_TICK) * 1e9, spans


def recording(out, *args):
    """A recorder to ``out``, once it has recorded a message: it logs 'recording ...' on
    stderr when the first one is written (a fixed 4 s sleep, then a second after the
    bag's file appeared, raced the recorder's start-up and discovery on a slow host: a
    SIGINT before any message leaves nothing recorded). What it wrote to stderr until
    then is ``p.early_err``."""
    import select
    p = subprocess.Popen([exe('record'), '-o', str(out), '--wait', '150', *args],
                         stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    seen = b''
    end = time.monotonic() + 180                                  # a safety net only
    while b'recording ' not in seen and p.poll() is None and time.monotonic() < end:
        if select.select([p.stderr.fileno()], [], [], 0.5)[0]:
            seen += os.read(p.stderr.fileno(), 4096)
    p.early_err = seen.decode(errors='replace')
    assert b'recording ' in seen, (p.poll(), p.early_err)
    return p


class Pauser:
    """Pauses and resumes the test's cloth node through ``~/pause`` (its simulation clock
    then stands still; it sends its state again once a second), and sees who subscribes
    to its ``~/mesh`` (to start a pause once a recorder has subscribed)."""

    def __init__(self):
        import rclpy
        from rclpy.context import Context
        from rclpy.executors import SingleThreadedExecutor
        from std_srvs.srv import SetBool
        self.ctx = Context()
        rclpy.init(context=self.ctx)
        self.node = rclpy.create_node('pauser', context=self.ctx)
        self.cli = self.node.create_client(SetBool, '/cloth_node/pause')
        self.executor = SingleThreadedExecutor(context=self.ctx)
        self.executor.add_node(self.node)
        self.request = SetBool.Request
        assert self.cli.wait_for_service(timeout_sec=60)

    def pause(self, on: bool):
        fut = self.cli.call_async(self.request(data=on))
        self.executor.spin_until_future_complete(fut, timeout_sec=30)
        assert fut.result() is not None and fut.result().success, on

    def wait_for_subscriber(self, node_name: str, proc):
        """Until node ``node_name`` (``proc``'s) subscribes to ``~/mesh``."""
        end = time.monotonic() + 120                              # a safety net only
        while proc.poll() is None and node_name not in [
                i.node_name for i in self.node.get_subscriptions_info_by_topic(
                    '/cloth_node/mesh')]:
            assert time.monotonic() < end
            time.sleep(0.05)

    def close(self):
        import rclpy
        self.node.destroy_node()
        rclpy.shutdown(context=self.ctx)


def test_sigint_closes_the_bag(node, tmp_path):
    out = tmp_path / 'interrupted'
    p = recording(out)
    p.send_signal(signal.SIGINT)
    _, err = p.communicate(timeout=30)
    assert p.returncode == 0 and 'Traceback' not in err
    with AnyReader([out]) as reader:
        assert reader.message_count > 0


def complete_chunks(mcap):
    """The compressions of the complete chunk records of a (growing) MCAP file."""
    import struct
    data = mcap.read_bytes() if mcap.exists() else b''
    found, off = [], 8
    while off + 9 <= len(data):
        op, n = struct.unpack_from('<BQ', data, off)
        if off + 9 + n > len(data):
            break
        if op == 0x06:
            k = struct.unpack_from('<I', data, off + 9 + 28)[0]
            found.append(data[off + 9 + 32:off + 9 + 32 + k].decode())
        off += 9 + n
    return found


@pytest.mark.parametrize('compress', ['zstd', 'none'])
def test_a_killed_recording_is_recoverable(node, tmp_path, compress):
    """SIGKILL once a few 1 MiB chunks are on disk (the next one maybe half written):
    ``record --recover`` rebuilds a valid bag of the complete chunks, compressed as they
    were."""
    crashed = tmp_path / 'crashed'
    p = subprocess.Popen([exe('record'), '-o', str(crashed), '--wait', '150', '--compress',
                          compress], stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    mcap = crashed / 'crashed.mcap'
    end = time.monotonic() + 240                                  # a safety net only
    try:
        while time.monotonic() < end and len(complete_chunks(mcap)) < 3:
            time.sleep(0.2)                                   # a few 1 MiB chunks on disk
    finally:
        p.kill()
        p.wait()
    written = complete_chunks(mcap)
    assert len(written) >= 3
    assert set(written) == ({'zstd'} if compress == 'zstd' else {''}), written
    assert not (crashed / 'metadata.yaml').exists()
    res = subprocess.run([exe('record'), '--recover', str(crashed)], capture_output=True,
                         text=True, timeout=120)
    assert res.returncode == 0, res.stderr
    assert '\r' not in res.stdout + res.stderr                 # piped: no progress line
    with AnyReader([crashed]) as reader:
        msgs = [reader.deserialize(raw, c.msgtype) for c, _, raw in reader.messages()]
    assert len(msgs) >= 3
    from mcap.reader import make_reader
    with open(crashed / 'crashed.mcap', 'rb') as fh:                # the rebuilt file
        reader = make_reader(fh, validate_crcs=True)
        assert sum(1 for _ in reader.iter_messages()) == len(msgs)
        assert {c.compression for c in reader.get_summary().chunk_indexes} == set(written)
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
    # a pipe gets no progress line: the stdout lines are the files, stderr is empty
    assert res.stderr == '' and '\r' not in res.stdout, res.stderr
    assert all(ln.startswith('render: wrote ') for ln in res.stdout.splitlines())
    res = subprocess.run([exe('render'), str(out / 'nope'), '-o', str(out)],
                         capture_output=True, text=True, timeout=60)
    assert res.returncode == 2 and 'not a bag directory' in res.stderr


def test_render_refuses_times_past_the_bag_in_one_line(bag, tmp_path):
    """A --times beyond the bag's last mesh is refused with one line naming the meshes'
    time range and exit 2 (it used to draw the last frame as if it were that time);
    nothing is written. Within half a mesh interval of the ends a time is the end frame."""
    from cosserat_ros.tools.render import (TimesOutsideBag, check_times, mesh_times,
                                           read_bag)
    meshes, _, _ = read_bag(bag, '/cloth_node/mesh', '/cloth_node/energy')
    ts = mesh_times(meshes)
    np.testing.assert_array_equal(ts, stamps_of(bag, '/cloth_node/mesh') * 1e-9)
    last = float(ts.max())
    out = tmp_path / 'late'
    res = subprocess.run([exe('render'), str(bag), '-o', str(out), '--times',
                          f'{ts.min():.3f}', f'{last + 100:.3f}'],
                         capture_output=True, text=True, timeout=120)
    assert res.returncode == 2, (res.stdout, res.stderr)
    assert res.stderr.count('\n') == 1 and 'Traceback' not in res.stderr, res.stderr
    assert 'past the last mesh' in res.stderr and f'to {last:.3f} s' in res.stderr
    assert not out.exists()
    grid = np.array([0.0, 0.1, 0.2])
    check_times([0.0, 0.24, -0.04], grid)             # within half an interval: the ends
    for t in (0.26, -0.06):
        with pytest.raises(TimesOutsideBag):
            check_times([0.1, t], grid)


def test_render_live_topics(node, bag, tmp_path):
    """render --live SECONDS collects SECONDS of simulation time from the first mesh:
    with the node paused for 4 s of wall time once render has subscribed, it is still
    collecting at the end of the pause, and its pictures span the 2 s within a tick (a
    wall-clock collection ended during the pause, on copies of one state). ``bag`` first:
    the node is up and publishing."""
    import re
    out = tmp_path / 'live'
    p, during, err = _run_through_pause(
        [exe('render'), '--live', '2', '-o', str(out), '--frames', '6'], 'cloth_render',
        timeout=300)
    assert during is None, err
    assert p.returncode == 0, err
    pngs = sorted(out.glob('cloth_*s.png'))
    assert pngs and (out / 'cloth.gif').exists() and (out / 'energy.png').exists()
    assert np.asarray(Image.open(pngs[-1]).convert('RGB'), dtype=float).std() > 10
    times = sorted(float(re.fullmatch(r'cloth_(.*)s\.png', p.name).group(1)) for p in pngs)
    assert 2 - MAX_TICK - 1e-3 < times[-1] - times[0] <= 2 + 1e-3, times
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
    subscribes best-effort too (a reliable subscription hears nothing from it). The talker
    stamps its headers on a simulation clock of its own, 20 ms a message, and --duration
    counts on those stamps (there is no /clock to follow here, whatever the wall clock
    does): the bag spans the 2 s within a message or two."""
    import rclpy
    from rclpy.context import Context
    from rclpy.qos import QoSProfile, ReliabilityPolicy
    from std_msgs.msg import Header
    ctx = Context()
    rclpy.init(context=ctx)
    node = rclpy.create_node('best_effort_talker', context=ctx)
    pub = node.create_publisher(Header, '/best_effort_chatter',
                                QoSProfile(depth=10, reliability=ReliabilityPolicy.BEST_EFFORT))
    out = tmp_path / 'best_effort'
    try:
        p = subprocess.Popen([exe('record'), '-o', str(out), '--wait', '60', '--wall-time',
                              '--duration', '2', '/best_effort_chatter'],
                             stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
        end = time.monotonic() + 90                               # a safety net only
        k = 0
        while p.poll() is None and time.monotonic() < end:
            msg = Header(frame_id='talker')
            msg.stamp.sec, msg.stamp.nanosec = divmod(k * 20_000_000, 10 ** 9)
            pub.publish(msg)
            k += 1
            time.sleep(0.02)
        _, err = p.communicate(timeout=30)
    finally:
        node.destroy_node()
        rclpy.shutdown(context=ctx)
    assert p.returncode == 0, err
    with AnyReader([out]) as reader:
        assert reader.message_count > 10
        t = np.array([m.stamp.sec * 10 ** 9 + m.stamp.nanosec
                      for m in (reader.deserialize(raw, c.msgtype)
                                for c, _, raw in reader.messages())])
    assert 1.9e9 <= t.max() - t.min() <= 2e9, (t.min(), t.max())


def test_a_reset_while_recording_keeps_the_log_times_going_forward(node, tmp_path):
    """~/reset sends the node's /clock back to 0: the recorder's log times continue from
    where they were (a player sorts by log time, and would interleave the two runs), while
    the recorded /clock messages themselves go back."""
    import rclpy
    from rclpy.context import Context
    from rclpy.executors import SingleThreadedExecutor
    from std_srvs.srv import Trigger
    from mcap.reader import make_reader
    from rclpy.qos import DurabilityPolicy, QoSProfile
    from rosgraph_msgs.msg import Clock
    out = tmp_path / 'reset'
    p = recording(out)
    ctx = Context()
    rclpy.init(context=ctx)
    client_node = rclpy.create_node('resetter', context=ctx)
    now = []                                     # the node's /clock [ns], as it comes
    client_node.create_subscription(
        Clock, '/clock', lambda m: now.append(m.clock.sec * 10 ** 9 + m.clock.nanosec),
        QoSProfile(depth=10, durability=DurabilityPolicy.TRANSIENT_LOCAL))
    executor = SingleThreadedExecutor(context=ctx)
    executor.add_node(client_node)

    def until(done):
        """Spin until ``done()`` (simulation time: however long the node takes)."""
        end = time.monotonic() + 120                              # a safety net only
        while not done():
            assert time.monotonic() < end, now[-3:]
            executor.spin_once(timeout_sec=0.1)
    try:
        cli = client_node.create_client(Trigger, '/cloth_node/reset')
        assert cli.wait_for_service(timeout_sec=30)
        until(lambda: now and now[-1] >= 10 ** 9)      # the clock well past the reset's 0
        seen = len(now)
        fut = cli.call_async(Trigger.Request())
        executor.spin_until_future_complete(fut, timeout_sec=30)
        assert fut.result() is not None and fut.result().success
        # half a second of simulation after the reset (many ticks the recorder takes too)
        until(lambda: any(b < a for a, b in zip(now[seen - 1:], now[seen:]))
              and now[-1] >= 5 * 10 ** 8)
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


def run_on_a_terminal(cmd, timeout):
    """Run ``cmd`` with its stderr on a pseudo-terminal (as in a shell) and its stdout on
    a pipe; returns (exit code, stdout, what the terminal received). The terminal does
    not turn newlines into CR LF (``onlcr`` off), so that a carriage return in what it
    received is one the program wrote."""
    import pty
    import select
    import termios
    master, slave = pty.openpty()
    attrs = termios.tcgetattr(slave)
    attrs[1] &= ~termios.ONLCR
    termios.tcsetattr(slave, termios.TCSANOW, attrs)
    p = subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=slave,
                         stdin=subprocess.DEVNULL)
    os.close(slave)
    out_fd = p.stdout.fileno()
    got = {out_fd: b'', master: b''}
    open_fds = set(got)
    end = time.monotonic() + timeout                              # a safety net only
    try:
        while open_fds:
            assert time.monotonic() < end, got[master][-500:]
            for fd in select.select(list(open_fds), [], [], 1.0)[0]:
                try:
                    data = os.read(fd, 65536)
                except OSError:                 # EIO: the last writer closed the terminal
                    data = b''
                if data:
                    got[fd] += data
                else:
                    open_fds.discard(fd)
        p.wait(timeout=60)
    finally:
        if p.poll() is None:
            p.kill()
            p.wait()
        os.close(master)
        p.stdout.close()
    return (p.returncode, got[out_fd].decode(errors='replace'),
            got[master].decode(errors='replace'))


def test_progress_lines_on_a_terminal(node, bag, tmp_path):
    """On a terminal, record and render show one progress line each on stderr, rewritten
    in place (a carriage return before each update), ended with a newline, with log lines
    starting on lines of their own; their stdout (a pipe) has none of it."""
    import re
    out = tmp_path / 'tty_bag'
    code, stdout, tty = run_on_a_terminal(
        [exe('record'), '-o', str(out), '--wait', '150', '--duration', '2'], timeout=240)
    assert code == 0, tty
    updates = re.findall(r'\rrecord: ([\d.]+) of 2 s of simulation time, (\d+) messages, '
                         r'([\d.]+) MB *(?=\r|\n)', tty)
    assert updates, tty
    assert updates[-1][0] != '0.0' and int(updates[-1][1]) > 0
    seconds = [float(u[0]) for u in updates]
    assert seconds == sorted(seconds) and seconds[-1] <= 2.0
    # the progress line ends with a newline before the recorder's own lines
    last = tty.rindex('\rrecord: ')
    assert '\n' in tty[last:] and '\r' not in tty[last + 1:], tty[last:]
    assert not re.search(r'[^\r\n]\[(INFO|WARN)\]', tty), tty       # log lines start a line
    assert stdout.startswith('record: wrote ') and '\r' not in stdout, stdout
    with AnyReader([out]) as reader:
        assert reader.message_count > 0
    pictures = tmp_path / 'tty_pictures'
    code, stdout, tty = run_on_a_terminal(
        [exe('render'), str(bag), '-o', str(pictures), '--frames', '6'], timeout=300)
    assert code == 0, tty
    # the first update and the last are always drawn; between them at most four a
    # second, so of the six GIF frames (more than a quarter of a second of drawing) one
    # at least
    assert tty.startswith('\rrender: reading cloth: message 1 of '), tty[:200]
    assert re.search(r'\rrender: GIF frame [1-6] of 6 *\r', tty), tty
    assert re.search(r'\rrender: drew \d+ files into \S+ *\n$', tty), tty[-300:]
    assert '\r' not in stdout and stdout.count('render: wrote ') >= 5, stdout

