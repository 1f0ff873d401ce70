"""A live view in the browser: a Foxglove WebSocket server inside the node (``foxglove.port``).

Needs the optional ``foxglove-sdk`` (``pip install .[viz]``). Open the Foxglove app (web
or desktop), *Open connection*, ``ws://localhost:PORT``, and the shipped layout
``config/foxglove_layout.json``. The server (subprotocol ``foxglove.sdk.v1``) offers:

=========================  ==============================  =================================
channel / service          schema                          content
=========================  ==============================  =================================
``/cloth_node/scene``      foxglove.SceneUpdate (protobuf)  entity ``cloth``: one triangle
                                                            list, shared vertices sent once
                                                            (``indices``), a colour per
                                                            vertex (the ``coloring``);
                                                            entity ``obstacles`` (cubes,
                                                            spheres, cylinders, triangles)
                                                            and ``handles`` (spheres)
``/cloth_node/energy``     JSON                            the energy terms [J], sim time
``/cloth_node/cameras/``   foxglove.RawImage,              per camera (``cameras.names``):
``<name>/color``,          foxglove.CameraCalibration      ``rgb8`` colour, ``32FC1`` depth
``<name>/depth``,                                          [m], K and P, in frame
``<name>/calibration``                                     ``<name>_optical_frame``
``/cloth_node/reset``      service std_srvs/srv/Trigger,   as ``~/reset``
                           JSON ``{}``
``/cloth_node/pause``      service std_srvs/srv/SetBool,   as ``~/pause``
                           JSON ``{"data": b}``
=========================  ==============================  =================================

Log times are simulation time, which the server also broadcasts (the *Time* capability),
so the app's clock is the cloth's. A channel is built only while a client subscribes to it.

Threads: the SDK calls the service handlers on its own thread; they queue the request and
wait (at most :data:`SERVICE_TIMEOUT` s) for the node's tick to run it (:meth:`serve`), so
the simulator is only ever touched from the node's thread.
"""
from __future__ import annotations

import json
import queue
import threading
from typing import Callable, Dict, Optional

import numpy as np

__all__ = ['LiveView', 'open_live_view', 'SERVICE_TIMEOUT', 'ENERGY_KEYS', 'SERVICE_TYPES']

#: each service's ROS type and its request's JSON schema, as the node's own services
#: (``~/reset`` std_srvs/Trigger, ``~/pause`` std_srvs/SetBool), so that a client fills
#: in the right request; both answer a Trigger's / SetBool's response
SERVICE_TYPES = {
    'reset': ('std_srvs/srv/Trigger', {'type': 'object'}),
    'pause': ('std_srvs/srv/SetBool', {'type': 'object', 'required': ['data'],
                                       'properties': {'data': {'type': 'boolean'}}}),
}
RESPONSE = {'type': 'object', 'properties': {'success': {'type': 'boolean'},
                                             'message': {'type': 'string'}}}

#: [s] how long a service call waits for the node's next tick
SERVICE_TIMEOUT = 2.0
#: the largest service request read [bytes] (a reset or a pause is a few bytes; a larger
#: one is refused before it is parsed, which would hold the interpreter's lock)
MAX_REQUEST_BYTES = 4096
#: the most calls waiting for the node's thread; more are refused as busy
MAX_PENDING = 16
#: the scene's entities besides the cloth, deleted in each frame that does not show them
OPTIONAL_ENTITIES = frozenset(('handles', 'obstacles'))
#: messages the server keeps for a client that does not read (the SDK's default, 1024,
#: is ~1 GB of scenes at 160 x 160)
BACKLOG = 16
#: the energy terms sent on /cloth_node/energy
ENERGY_KEYS = ('kinetic', 'stretching', 'bending', 'coupling', 'gravity', 'external_work',
               'dissipated', 'total')


class LiveView:
    """The Foxglove server of one node (module docstring). ``handlers`` maps ``'reset'``
    and ``'pause'`` to functions of the request (a dict) returning (success, message)."""

    def __init__(self, port: int, host: str, prefix: str,
                 handlers: Dict[str, Callable[[dict], tuple]]):
        try:
            import foxglove
            from foxglove.channels import SceneUpdateChannel
        except ImportError:
            raise ImportError('foxglove.port needs the foxglove-sdk package: pip install '
                              "'cosserat_ros[viz]' (or pip install foxglove-sdk)") from None
        self._fg = foxglove
        self._prefix = prefix
        self._handlers = handlers
        self._requests: 'queue.Queue' = queue.Queue(maxsize=MAX_PENDING)
        self._meshes: dict = {}
        self.context = foxglove.Context()
        def schema(name):
            kind, request = SERVICE_TYPES[name]
            return foxglove.ServiceSchema(
                kind,
                request=foxglove.MessageSchema(encoding='json', schema=foxglove.Schema(
                    name=f'{kind}_Request', encoding='jsonschema',
                    data=json.dumps(request).encode())),
                response=foxglove.MessageSchema(encoding='json', schema=foxglove.Schema(
                    name=f'{kind}_Response', encoding='jsonschema',
                    data=json.dumps(RESPONSE).encode())))
        services = [foxglove.Service(f'{prefix}/{name}', schema=schema(name),
                                     handler=lambda req, n=name: self._call(n, req))
                    for name in handlers]
        self.server = foxglove.start_server(
            name=prefix.strip('/'), host=host, port=port, context=self.context,
            capabilities=[foxglove.Capability.Time, foxglove.Capability.Services],
            supported_encodings=['json'], services=services, message_backlog_size=BACKLOG)
        self.scene = SceneUpdateChannel(f'{prefix}/scene', context=self.context)
        self._cameras: Dict[str, tuple] = {}
        self.energy = foxglove.Channel(
            f'{prefix}/energy', message_encoding='json', context=self.context,
            schema={'type': 'object', 'properties': {
                k: {'type': 'number'} for k in ENERGY_KEYS + ('sim_time',)}})

    @property
    def port(self) -> int:
        return self.server.port

    # ------------------------------------------------------------------ services
    def _call(self, name: str, request) -> bytes:
        """On the SDK's thread: queue the call for the node's thread and wait for it.
        Refused before the node sees it: a request over :data:`MAX_REQUEST_BYTES`, not a
        JSON object, or with :data:`MAX_PENDING` calls already waiting. A call that times
        out is withdrawn: the node skips it, so what the caller was told failed does not
        happen later."""
        payload = bytes(request.payload)
        if len(payload) > MAX_REQUEST_BYTES:
            raise ValueError(f'the request has {len(payload)} bytes, at most '
                             f'{MAX_REQUEST_BYTES}')
        try:
            args = json.loads(payload or b'{}')
        except ValueError:
            raise ValueError('the request is not JSON') from None
        if not isinstance(args, dict):
            raise ValueError('the request is not a JSON object')
        done = threading.Event()
        box: list = []
        try:
            self._requests.put_nowait((name, args, done, box))
        except queue.Full:
            raise RuntimeError(f'busy: {MAX_PENDING} calls are waiting for the node') from None
        if not done.wait(SERVICE_TIMEOUT):
            box.append(None)                     # withdrawn: serve() skips it
            if not done.is_set():
                raise TimeoutError(f'the node did not answer within {SERVICE_TIMEOUT} s')
        success, message = next(b for b in box if b is not None)
        return json.dumps({'success': bool(success), 'message': str(message)}).encode()

    def serve(self, limit: int = 8) -> None:
        """On the node's thread (each tick): run at most ``limit`` queued service calls."""
        for _ in range(limit):
            try:
                name, args, done, box = self._requests.get_nowait()
            except queue.Empty:
                return
            if box:                                  # withdrawn by a caller that timed out
                continue
            try:
                box.append(self._handlers[name](args))
            except Exception as exc:                 # reported to the caller, not raised
                box.append((False, f'{type(exc).__name__}: {exc}'))
            done.set()

    # ------------------------------------------------------------------ publishing
    def publish(self, stamp_ns: int, frame_id: str, positions: np.ndarray,
                faces: np.ndarray, colors: np.ndarray, energy: dict,
                obstacles: Optional[Callable[[], list]] = None,
                handles: Optional[np.ndarray] = None):
        """One frame at sim time ``stamp_ns``: the time, and each channel a client
        watches. ``obstacles``: a function giving (shape, description, mesh or None) per
        obstacle, called only when a client watches the scene."""
        self.server.broadcast_time(int(stamp_ns))
        if self.energy.has_sinks():
            msg = {k: float(energy[k]) for k in ENERGY_KEYS if k in energy}
            msg['sim_time'] = stamp_ns * 1e-9
            self.energy.log(msg, log_time=int(stamp_ns))
        if not self.scene.has_sinks():
            return
        m = self._fg.messages
        sec, nsec = divmod(int(stamp_ns), 1_000_000_000)
        ts = m.Timestamp(sec, nsec)
        cloth = m.TriangleListPrimitive(
            points=[m.Point3(x=a, y=b, z=c) for a, b, c in positions.tolist()],
            colors=[m.Color(r=r, g=g, b=b, a=a) for r, g, b, a in colors.tolist()],
            indices=faces.reshape(-1).tolist(), color=m.Color(r=1.0, g=1.0, b=1.0, a=1.0))
        entities = [m.SceneEntity(timestamp=ts, frame_id=frame_id, id='cloth',
                                  triangles=[cloth])]
        shown = {'cloth'}
        listed = obstacles() if obstacles is not None else []
        if listed:
            entities.append(self._obstacles(m, ts, frame_id, listed))
            shown.add('obstacles')
        if handles is not None and len(handles):
            shown.add('handles')
            green = m.Color(r=0.1, g=0.8, b=0.3, a=1.0)
            entities.append(m.SceneEntity(timestamp=ts, frame_id=frame_id, id='handles',
                                          spheres=[m.SpherePrimitive(
                                              pose=m.Pose(position=m.Vector3(x=a, y=b, z=c)),
                                              size=m.Vector3(x=0.03, y=0.03, z=0.03),
                                              color=green)
                                              for a, b, c in np.asarray(handles).tolist()]))
        # an entity this frame does not show (no obstacle, no grasp) is deleted, in every
        # frame: a viewer keeps it until then, and a client that lags loses frames
        gone = [m.SceneEntityDeletion(timestamp=ts, type=m.SceneEntityDeletionType.MatchingId,
                                      id=i) for i in sorted(OPTIONAL_ENTITIES - shown)]
        self.scene.log(m.SceneUpdate(deletions=gone, entities=entities),
                       log_time=int(stamp_ns))

    def publish_camera(self, name: str, stamp_ns: int, frame_id: str, depth: np.ndarray,
                       rgb: np.ndarray, K: np.ndarray) -> None:
        """One camera's images (:mod:`.cameras`) on its channels a client watches (each
        built at the camera's first image)."""
        if name not in self._cameras:
            from foxglove.channels import CameraCalibrationChannel, RawImageChannel
            base = f'{self._prefix}/cameras/{name}'
            self._cameras[name] = (
                RawImageChannel(f'{base}/color', context=self.context),
                RawImageChannel(f'{base}/depth', context=self.context),
                CameraCalibrationChannel(f'{base}/calibration', context=self.context))
        color, dep, calib = self._cameras[name]
        m = self._fg.messages
        sec, nsec = divmod(int(stamp_ns), 1_000_000_000)
        ts = m.Timestamp(sec, nsec)
        h, w = depth.shape
        if color.has_sinks():
            color.log(m.RawImage(timestamp=ts, frame_id=frame_id, width=w, height=h,
                                 encoding='rgb8', step=3 * w, data=rgb.tobytes()),
                      log_time=int(stamp_ns))
        if dep.has_sinks():
            dep.log(m.RawImage(timestamp=ts, frame_id=frame_id, width=w, height=h,
                               encoding='32FC1', step=4 * w,
                               data=depth.astype('<f4', copy=False).tobytes()),
                    log_time=int(stamp_ns))
        if calib.has_sinks():
            P = np.hstack([K, np.zeros((3, 1))])
            calib.log(m.CameraCalibration(
                timestamp=ts, frame_id=frame_id, width=w, height=h,
                distortion_model='plumb_bob', D=[0.0] * 5, K=K.reshape(-1).tolist(),
                R=np.eye(3).reshape(-1).tolist(), P=P.reshape(-1).tolist()),
                log_time=int(stamp_ns))

    def _mesh_lists(self, m, verts, faces):
        """A mesh obstacle's points and indices as the primitive takes them, built once
        per mesh (held with it: its arrays never change) instead of every frame."""
        hit = self._meshes.get(id(verts))
        if hit is None or hit[0] is not verts:
            hit = (verts, [m.Point3(x=a, y=b, z=c) for a, b, c in verts.tolist()],
                   np.asarray(faces).reshape(-1).tolist())
            if len(self._meshes) >= 16:
                self._meshes.clear()
            self._meshes[id(verts)] = hit
        return hit[1], hit[2]

    def _obstacles(self, m, ts, frame_id, obstacles):
        grey = m.Color(r=0.6, g=0.6, b=0.6, a=0.8)
        cubes, spheres, cylinders, triangles = [], [], [], []
        for shape, d, mesh in obstacles:
            (px, py, pz), (qx, qy, qz, qw) = d['position'], d['orientation']
            pose = m.Pose(position=m.Vector3(x=px, y=py, z=pz),
                          orientation=m.Quaternion(x=qx, y=qy, z=qz, w=qw))
            if shape == 'sphere':
                s = 2 * d['radius']
                spheres.append(m.SpherePrimitive(pose=pose, size=m.Vector3(x=s, y=s, z=s),
                                                 color=grey))
            elif shape == 'box':
                hx, hy, hz = d['half_extents']
                cubes.append(m.CubePrimitive(pose=pose, color=grey,
                                             size=m.Vector3(x=2 * hx, y=2 * hy, z=2 * hz)))
            elif shape == 'plane':
                cubes.append(m.CubePrimitive(pose=pose, color=grey,
                                             size=m.Vector3(x=10.0, y=10.0, z=1e-3)))
            elif shape in ('cylinder', 'capsule'):
                r, h = d['radius'], 2 * d['half_length'] + (
                    2 * d['radius'] if shape == 'capsule' else 0.0)
                cylinders.append(m.CylinderPrimitive(
                    pose=pose, size=m.Vector3(x=2 * r, y=2 * r, z=h), bottom_scale=1.0,
                    top_scale=1.0, color=grey))
            elif mesh is not None:
                points, indices = self._mesh_lists(m, *mesh)
                triangles.append(m.TriangleListPrimitive(pose=pose, color=grey, points=points,
                                                         indices=indices))
        return m.SceneEntity(timestamp=ts, frame_id=frame_id, id='obstacles', cubes=cubes,
                             spheres=spheres, cylinders=cylinders, triangles=triangles)

    def close(self) -> None:
        self.server.stop()


def open_live_view(node, port: int, host: str) -> LiveView:
    """The live view of ``node`` (a :class:`.node.ClothNode`) on ``host:port``, its
    services wired to the node's reset and pause unless it is ``observe_only``; a
    :class:`.params.ConfigError` with the reason if it cannot open."""
    from .params import ConfigError
    if not 0 < port < 65536:
        raise ConfigError(f'foxglove.port must be in [1, 65535] (0: off), got {port}')

    def pause(args: dict):
        # a std_srvs/SetBool: {"data": true} pauses, false resumes; anything else (no
        # data, "false", which is a true string) is refused, not read as a truth value
        data = args.get('data')
        if not isinstance(data, bool):
            return False, f'data must be true or false, got {data!r}'
        return node.pause(data)
    handlers = {} if node.observe_only else {'reset': lambda args: node.reset(),
                                             'pause': pause}
    try:
        live = LiveView(port, host, node.get_fully_qualified_name(), handlers)
    except ImportError as exc:
        raise ConfigError(str(exc)) from None
    except Exception as exc:                     # e.g. the port is taken
        raise ConfigError(f'foxglove.port {port}: {exc}') from None
    node.get_logger().info(f'live view: open ws://{host}:{live.port} in the Foxglove app')
    return live
