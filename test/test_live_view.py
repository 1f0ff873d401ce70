"""The live view (foxglove.port) seen by an independent client: a plain WebSocket client
(the ``websockets`` package, not the SDK) speaking the Foxglove WebSocket protocol, which
decodes the advertised protobuf schema with protobuf's own descriptor machinery."""
import base64
import json
import os
import signal
import socket
import struct
import subprocess
import time

from ament_index_python.packages import get_package_prefix
import pytest

pytest.importorskip('foxglove', reason='the live view is the viz extra (foxglove-sdk)')
from google.protobuf import descriptor_pb2, descriptor_pool, message_factory  # noqa: E402
from websockets.sync.client import connect  # noqa: E402

NX, NY = 10, 8


def free_port() -> int:
    with socket.socket() as s:
        s.bind(('127.0.0.1', 0))
        return s.getsockname()[1]


def protobuf_class(channel):
    fds = descriptor_pb2.FileDescriptorSet.FromString(base64.b64decode(channel['schema']))
    pool = descriptor_pool.DescriptorPool()
    for fd in fds.file:
        pool.Add(fd)
    return message_factory.GetMessageClass(pool.FindMessageTypeByName(channel['schemaName']))


class Client:
    def __init__(self, port):
        end = time.monotonic() + 120
        while True:
            try:
                self._conn = connect(f'ws://127.0.0.1:{port}',
                                     subprotocols=['foxglove.sdk.v1'], open_timeout=5)
                self.ws = self._conn.__enter__()
                break
            except OSError:
                if time.monotonic() > end:
                    raise
                time.sleep(0.5)
        assert self.ws.subprotocol == 'foxglove.sdk.v1'
        self.channels, self.services, self.info = {}, {}, None
        self.messages, self.times, self.responses = [], [], []

    def pump(self, seconds, until=lambda: False):
        end = time.monotonic() + seconds
        while time.monotonic() < end and not until():
            try:
                frame = self.ws.recv(timeout=0.2)
            except TimeoutError:
                continue
            if isinstance(frame, str):
                msg = json.loads(frame)
                if msg['op'] == 'serverInfo':
                    self.info = msg
                elif msg['op'] == 'advertise':
                    self.channels.update({c['topic']: c for c in msg['channels']})
                elif msg['op'] == 'advertiseServices':
                    self.services.update({s['name']: s for s in msg['services']})
                elif msg['op'] == 'serviceCallFailure':
                    self.responses.append((msg['callId'], {'failure': msg['message']}))
            elif frame[0] == 0x01:                              # message data
                sub, log_time = struct.unpack_from('<IQ', frame, 1)
                self.messages.append((sub, log_time, bytes(frame[13:])))
            elif frame[0] == 0x02:                              # time
                self.times.append(struct.unpack_from('<Q', frame, 1)[0])
            elif frame[0] == 0x03:                              # service call response
                sid, call, n = struct.unpack_from('<III', frame, 1)
                self.responses.append((call, json.loads(bytes(frame[13 + n:]))))
        return until()

    def call(self, name, request, call_id):
        sid = self.services[name]['id']
        enc = b'json'
        self.ws.send(struct.pack('<BIII', 0x02, sid, call_id, len(enc)) + enc
                     + json.dumps(request).encode())
        assert self.pump(10, lambda: any(c == call_id for c, _ in self.responses)), name
        return next(r for c, r in self.responses if c == call_id)


@pytest.fixture
def node(tmp_path):
    port = free_port()
    params = tmp_path / 'p.yaml'
    params.write_text(f'cloth_node:\n  ros__parameters:\n    mesh: {{nx: {NX}, ny: {NY}}}\n'
                      f'    publish_rate: 20.0\n    status_period: 0.0\n'
                      f'    foxglove: {{port: {port}}}\n'
                      '    obstacles:\n      names: [ball]\n'
                      '      ball: {shape: sphere, center: [0.5, 0.5, -0.4], radius: 0.1}\n'
                      '    cameras:\n      names: [top]\n'
                      '      top: {width: 32, height: 24, rate: 10.0}\n')
    exe = os.path.join(get_package_prefix('cosserat_ros'), 'lib', 'cosserat_ros',
                       'cloth_node')
    proc = subprocess.Popen([exe, '--ros-args', '--params-file', str(params)],
                            stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True)
    yield port, proc
    proc.send_signal(signal.SIGINT)
    _, err = proc.communicate(timeout=20)
    assert proc.returncode == 0 and 'Traceback' not in err, err


@pytest.mark.process
def test_an_independent_client_sees_the_cloth_and_resets_it(node):
    port, proc = node
    c = Client(port)
    assert c.pump(30, lambda: '/cloth_node/scene' in c.channels
                  and '/cloth_node/reset' in c.services), (c.channels, proc.poll())
    assert 'time' in c.info['capabilities'] and 'services' in c.info['capabilities']
    # each service advertised as the node's own ROS service, its request's schema with it
    pause, reset = c.services['/cloth_node/pause'], c.services['/cloth_node/reset']
    assert (pause['type'], reset['type']) == ('std_srvs/srv/SetBool', 'std_srvs/srv/Trigger')
    request = json.loads(pause['request']['schema'])
    assert request['properties']['data'] == {'type': 'boolean'} and request['required'] == ['data']
    assert 'properties' not in json.loads(reset['request']['schema'])
    scene = c.channels['/cloth_node/scene']
    assert scene['encoding'] == 'protobuf' and scene['schemaName'] == 'foxglove.SceneUpdate'
    SceneUpdate = protobuf_class(scene)
    c.ws.send(json.dumps({'op': 'subscribe', 'subscriptions': [
        {'id': 7, 'channelId': scene['id']},
        {'id': 8, 'channelId': c.channels['/cloth_node/energy']['id']}]}))
    assert c.pump(20, lambda: sum(1 for m in c.messages if m[0] == 7) >= 10)
    n_vertices, n_faces = (NX + 1) * (NY + 1), 2 * NX * NY
    frames = [(t, SceneUpdate.FromString(data)) for s, t, data in c.messages if s == 7]
    for _, upd in frames:
        ents = {e.id: e for e in upd.entities}
        cloth = ents['cloth'].triangles[0]
        assert len(cloth.points) == n_vertices                      # shared vertices once
        assert len(cloth.indices) == 3 * n_faces
        assert max(cloth.indices) == n_vertices - 1 and min(cloth.indices) == 0
        assert len(cloth.colors) == n_vertices
        assert all(0.0 <= col.r <= 1.0 and col.a == 1.0 for col in cloth.colors)
        assert len({(col.r, col.g, col.b) for col in cloth.colors}) > 1   # energy colours
        assert ents['cloth'].frame_id == 'world'
        assert len(ents['obstacles'].spheres) == 1
        assert ents['obstacles'].spheres[0].size.x == pytest.approx(0.2)
    times = [t for t, _ in frames]
    assert all(b > a for a, b in zip(times, times[1:])), times        # sim time, increasing
    energy = [json.loads(d) for s, _, d in c.messages if s == 8]
    assert energy and {'kinetic', 'stretching', 'total', 'sim_time'} <= set(energy[-1])
    assert c.times and c.times[-1] >= times[0]                        # the broadcast clock
    before = times[-1]
    assert c.call('/cloth_node/pause', {'data': True}, 1)['success']
    res = c.call('/cloth_node/reset', {}, 2)
    assert res['success'] and 'rest shape' in res['message']
    c.messages.clear()
    assert c.pump(10, lambda: any(s == 7 for s, _, _ in c.messages))
    after = min(t for s, t, _ in c.messages if s == 7)
    assert after < before and after < 0.5e9                          # back near t = 0
    # bad calls are refused, not read: "false" is not false (a true string), a request
    # that is not a JSON object, one over MAX_REQUEST_BYTES (refused before parsing)
    res = c.call('/cloth_node/pause', {'data': 'false'}, 3)
    assert not res.get('success') and 'true or false' in res['message'], res
    res = c.call('/cloth_node/pause', {}, 7)          # SetBool: no default to guess
    assert not res.get('success') and 'true or false' in res['message'], res
    assert 'not a JSON object' in c.call('/cloth_node/pause', [1, 2], 4)['failure']
    assert 'at most' in c.call('/cloth_node/reset', {'pad': 'x' * 5000}, 5)['failure']
    assert c.call('/cloth_node/pause', {'data': False}, 6)['success']    # still served
    c._conn.__exit__(None, None, None)
    # the shipped layout shows what the server offers
    from ament_index_python.packages import get_package_share_directory
    layout = json.load(open(os.path.join(get_package_share_directory('cosserat_ros'),
                                         'config', 'foxglove_layout.json')))
    panels = layout['configById']
    assert set(panels['3D!cloth']['topics']) <= set(c.channels)
    assert panels['3D!cloth']['followTf'] == 'world'
    for path in panels['Plot!energy']['paths']:
        topic, key = path['value'].rsplit('.', 1)
        assert topic in c.channels and key in energy[-1], path
    for key in ('CallService!reset', 'CallService!pause', 'CallService!resume'):
        assert panels[key]['serviceName'] in c.services
    # pause and resume: SetBool requests the node accepts (data true / false)
    assert [json.loads(panels[f'CallService!{k}']['requestPayload'])
            for k in ('pause', 'resume')] == [{'data': True}, {'data': False}]
    assert json.dumps(layout['layout']).count('CallService!') == 3     # all three shown


@pytest.mark.process
def test_the_cameras_images_and_calibration_are_shown(node):
    port, proc = node
    c = Client(port)
    base = '/cloth_node/cameras/top'
    kinds = ('color', 'depth', 'calibration')        # advertised one after the other
    assert c.pump(30, lambda: all(f'{base}/{k}' in c.channels for k in kinds)), \
        (c.channels, proc.poll())
    chans = {k: c.channels[f'{base}/{k}'] for k in kinds}
    assert chans['color']['schemaName'] == 'foxglove.RawImage'
    assert chans['calibration']['schemaName'] == 'foxglove.CameraCalibration'
    c.ws.send(json.dumps({'op': 'subscribe', 'subscriptions': [
        {'id': i, 'channelId': chans[k]['id']} for i, k in
        ((1, 'color'), (2, 'depth'), (3, 'calibration'))]}))
    assert c.pump(20, lambda: {1, 2, 3} <= {m[0] for m in c.messages})
    Image, Calibration = protobuf_class(chans['color']), protobuf_class(chans['calibration'])
    color = Image.FromString(next(d for s, _, d in c.messages if s == 1))
    depth = Image.FromString(next(d for s, _, d in c.messages if s == 2))
    cal = Calibration.FromString(next(d for s, _, d in c.messages if s == 3))
    assert (color.width, color.height, color.encoding, len(color.data)) == \
        (32, 24, 'rgb8', 32 * 24 * 3)
    assert (depth.encoding, depth.step, len(depth.data)) == ('32FC1', 128, 32 * 24 * 4)
    assert color.frame_id == depth.frame_id == cal.frame_id == 'top_optical_frame'
    assert (cal.width, cal.height, cal.distortion_model) == (32, 24, 'plumb_bob')
    assert cal.K[2] == pytest.approx(15.5) and cal.K[5] == pytest.approx(11.5)
    c._conn.__exit__(None, None, None)


def test_an_entity_the_last_frame_showed_is_deleted_when_it_goes():
    """The handles' spheres (and the obstacles) are left out of a frame once the last
    grasp is released (or obstacle removed); a viewer keeps a scene entity until it is
    replaced or deleted, so every frame without one carries a deletion of it (by id; a
    lagging client loses frames)."""
    import numpy as np
    from cosserat_ros.ros.live_view import LiveView
    view = LiveView(free_port(), '127.0.0.1', '/t', {})
    logged = []

    class Sink:                                   # the scene channel, with a watcher
        def has_sinks(self):
            return True

        def log(self, msg, log_time):
            logged.append(msg)
    try:
        view.scene = Sink()
        x = np.array([[0.0, 0, 0], [1, 0, 0], [0, 1, 0]])
        faces, colors = np.array([[0, 1, 2]]), np.ones((3, 4), np.float32)
        ball = [('sphere', {'position': (0, 0, 0), 'orientation': (0, 0, 0, 1),
                            'radius': 0.1}, None)]
        view.publish(1, 'world', x, faces, colors, {}, lambda: ball, np.zeros((1, 3)))
        view.publish(2, 'world', x, faces, colors, {}, lambda: [], np.zeros((0, 3)))
        view.publish(3, 'world', x, faces, colors, {}, lambda: [], None)
        schema = view._fg.messages.SceneUpdate.get_schema()
        SceneUpdate = protobuf_class({'schema': base64.b64encode(schema.data),
                                      'schemaName': schema.name})
        got = [SceneUpdate.FromString(msg.encode()) for msg in logged]
        d = [[(e.id, e.type) for e in u.deletions] for u in got]
        match = int(view._fg.messages.SceneEntityDeletionType.MatchingId)
        gone = [('handles', match), ('obstacles', match)]
        assert d == [[], gone, gone], d
        assert [sorted(e.id for e in u.entities) for u in got] == [
            ['cloth', 'handles', 'obstacles'], ['cloth'], ['cloth']]
    finally:
        view.close()
