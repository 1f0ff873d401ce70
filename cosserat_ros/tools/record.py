"""``record``: write the cloth's topics to a rosbag2 directory (MCAP storage, Jazzy default).

    record -o DIR [--duration S] [--timeout S] [--wait S] [--node cloth_node] [--wall-time]
           [--compress {zstd,none}] [--camera NAME ...] [TOPIC ...]

Default topics: the node's ``~/mesh``, ``~/energy`` and ``~/obstacle_markers`` (which
``render`` draws), ``/diagnostics`` and ``/clock``. ``--camera NAME`` (repeatable) adds a
camera's images, ``camera_info`` and ``pose_out`` (:data:`CAMERA_TOPICS`) to them, or to
the TOPICs given.
Messages are subscribed with their real types and written as the serialised bytes that
arrive (no deserialise / re-serialise round trip) by :mod:`.bagfile` (``metadata.yaml``
plus ``DIR/DIR.mcap``, CRCs written), so ``ros2 bag info``, ``ros2 bag play``, Foxglove and
the ``mcap`` libraries open the result.

Compression: the chunks are compressed with zstd by default (``--compress zstd``, as
``ros2 bag record -s mcap --storage-preset-profile zstd_fast`` does), which makes the
cloth's recording about five times smaller for about 2 ms of CPU per MB of messages (some
2 % of a core at the node's full rate); ``--compress none`` writes them as they are
(doc/viewing.md has the measurements); :func:`recover` reads either. The last line says
how large the bag came out: ``record: wrote N messages to DIR (X MB, Y MB per second of
simulation time, zstd: R times smaller than uncompressed); ...``. On a terminal, a
progress line on stderr shows the simulation seconds recorded and the MB written so far
(nothing of it in a pipe or a file).

Log times are simulation time, as ``ros2 bag record --use-sim-time`` gives: the recorder
follows ``/clock`` (the node publishes it before the state of the same instant, so a mesh
is logged at its header stamp, until a reset) and the bag plays back on its own clock.
When ``/clock`` goes back (``~/reset`` restarts the node at t = 0) the log times continue
from where they were, so that the bag still plays in the order it was recorded; the
messages' own stamps keep the node's time. ``--wall-time`` logs receive times instead;
without a ``/clock`` publisher the recorder says so and logs wall time.

Durations: ``--duration S`` counts *simulation* seconds, whatever the node's speed (a busy
host, a paused node): the bag holds the messages whose simulation times lie within S of
the first message's, and the recorder stops at the first message past that (not written).
A message's simulation time is its own stamp (a header's, ``/clock``'s; :func:`stamp_reader`)
or, for a type without one, the ``/clock`` time it arrives at; each topic's time counts
forward from its first message and a reset (its time going back) does not undo what was
counted (:class:`SimSpan`). The wall-clock options are separate: ``--timeout S`` stops the
recording after S wall-clock seconds however far the simulation got (default: no limit),
and ``--wait S`` is how long the recorder waits for the node (wall clock, below).

Topics: every requested topic's publisher is waited for up to ``--wait`` seconds (wall
clock); one still missing then is a warning naming it, and it is recorded from when it
appears (the graph is looked at twice a second), so a topic that shows up late (``/clock``
does, now and then, by a few hundred ms of discovery) is not lost. Nothing recorded is an
error (one line on stderr, exit 1, no bag left behind): no publisher of any topic within
``--wait`` seconds, or publishers but no message within ``--wait`` seconds more.

Safety: an existing DIR is never overwritten or appended to; SIGINT, SIGTERM and the end of
``--duration`` flush and close the bag; every completed 1 MiB chunk is synced to disk at
once. A write that fails (full disk, file-size limit) stops the recorder with a one-line
reason and exit 1 after closing the bag readable with every complete chunk
(:mod:`.bagfile`); a bag cut off by a crash keeps its complete chunks too (``record
--recover DIR`` rebuilds the file from them, compressed as they were, and writes the
missing ``metadata.yaml``).
"""
from __future__ import annotations

import argparse
import importlib
from pathlib import Path
import re
import sys
import time
from typing import Callable, Dict, List, Optional

__all__ = ['main', 'recover', 'stamp_reader', 'SimSpan', 'DEFAULT_TOPICS',
           'CAMERA_TOPICS']

DEFAULT_TOPICS = ('~/mesh', '~/energy', '~/obstacle_markers', '/diagnostics', '/clock')
#: a camera's topics under ``~/cameras/<name>/`` that ``--camera <name>`` records
CAMERA_TOPICS = ('depth/image_raw', 'color/image_raw', 'camera_info', 'pose_out')


def message_class(type_name: str):
    """'visualization_msgs/msg/MarkerArray' -> the rclpy message class."""
    pkg, kind, name = type_name.split('/')
    return getattr(importlib.import_module(f'{pkg}.{kind}'), name)


def resolve(topic: str, node_name: str) -> str:
    if topic.startswith('~/'):
        return f'/{node_name}/{topic[2:]}'
    return topic if topic.startswith('/') else '/' + topic


def stamp_reader(type_name: str) -> Optional[Callable[[bytes], Optional[int]]]:
    """A function that reads the stamp [ns] of a serialised (CDR) message of ``type_name``
    ('pkg/msg/Name') without deserialising it, or None if the type has no stamp there.

    The stamp is the ``builtin_interfaces/Time`` reached by following first fields: a
    ``std_msgs/Header``'s stamp, ``rosgraph_msgs/Clock``'s clock, a ``MarkerArray``'s first
    marker's header (through a sequence's first element; an empty sequence: None). Every
    step of that path is 4-byte aligned (the 4-byte encapsulation header, uint32 sequence
    lengths, int32 seconds), so the offsets need no padding. The function returns None for
    a message too short to hold the stamp."""
    import struct
    seqs = 0                         # sequence lengths on the way (each 4 bytes, not 0)
    t = type_name
    for _ in range(16):              # nesting deeper than this is no stamp path
        if t in ('builtin_interfaces/Time', 'builtin_interfaces/msg/Time'):
            break
        m = re.fullmatch(r'sequence<([^,>]+)(?:,\s*\d+)?>', t)
        if m:
            seqs += 1
            t = m.group(1)
            continue
        m = re.fullmatch(r'(.+)\[\d+\]', t)       # a fixed array: its first element, in place
        if m:
            t = m.group(1)
            continue
        parts = t.split('/')
        if len(parts) == 2:
            parts = [parts[0], 'msg', parts[1]]
        if len(parts) != 3:
            return None                                    # a primitive, a string
        try:
            fields = message_class('/'.join(parts)).get_fields_and_field_types()
        except (ImportError, AttributeError):
            return None
        if not fields:
            return None
        t = next(iter(fields.values()))
    else:
        return None
    need = 4 + 4 * seqs + 8

    def read(raw: bytes) -> Optional[int]:
        if len(raw) < need:
            return None
        endian = '<' if raw[1] & 1 else '>'          # CDR_LE (0x0001) or CDR_BE (0x0000)
        for k in range(seqs):
            if struct.unpack_from(endian + 'I', raw, 4 + 4 * k)[0] == 0:
                return None
        sec, nsec = struct.unpack_from(endian + 'iI', raw, 4 + 4 * seqs)
        return sec * 10 ** 9 + nsec
    return read


class SimSpan:
    """How much simulation time [ns] a stream of messages covers, per source (a topic):
    the sum of its forward steps from its first message, so that a reset (the source's time
    going back, as ``~/reset`` sends the node to t = 0) starts a new stretch instead of
    undoing what was counted. :meth:`elapsed` without a source is the longest of them
    (``/clock``, first latched and then every tick, is normally that one)."""

    def __init__(self):
        self._last: Dict[str, int] = {}
        self._run: Dict[str, int] = {}

    def after(self, source: str, t: int) -> int:
        """``elapsed(source)`` [ns] if a message of ``source`` at simulation time ``t``
        [ns] were added."""
        last = self._last.get(source)
        return self._run.get(source, 0) + (t - last if last is not None and t > last else 0)

    def peek(self, source: str, t: int) -> int:
        """:meth:`elapsed` [ns] (the longest source) if a message of ``source`` at
        simulation time ``t`` [ns] were added."""
        return max(self.elapsed(), self.after(source, t))

    def add(self, source: str, t: int) -> None:
        """Count a message of ``source`` at simulation time ``t`` [ns]."""
        self._run[source] = self.after(source, t)
        self._last[source] = t

    def elapsed(self, source: Optional[str] = None) -> int:
        """Simulation time [ns] covered by ``source``, or by the longest source."""
        if source is not None:
            return self._run.get(source, 0)
        return max(self._run.values(), default=0)

    def __bool__(self) -> bool:
        return bool(self._run)


def scan_mcap(path: Path, compressions: Optional[set] = None,
              topics: Optional[list] = None):
    """Messages of an MCAP file up to its last complete record, tolerating a torn tail
    (and stopping at a corrupt record as at a torn one).

    Yields (topic, msgtype, offered QoS profiles (the channel's metadata, or None),
    log_time_ns, data). Reads the top-level records (op, uint64
    length, body) and the schema (0x03), channel (0x04) and message (0x05) records inside
    chunks (0x06), uncompressed or zstd-compressed, which is what this recorder writes. A
    chunk is used only whole and sound: its records decompress to its
    ``uncompressed_size`` and match its ``uncompressed_crc`` (when not 0); the first that
    does not ends the scan, as a torn record does. ``compressions``: a set that receives
    the compression of every complete chunk ('' for none) before the first message is
    yielded; ``topics``: a list that receives (topic, msgtype, QoS) of every channel
    recorded outside chunks (as this recorder writes them), in file order, also before the
    first message. A chunk compressed otherwise (lz4, from another writer) is refused with
    SystemExit."""
    import struct
    import zlib

    def u16(b, o):
        return struct.unpack_from('<H', b, o)[0], o + 2

    def u32(b, o):
        return struct.unpack_from('<I', b, o)[0], o + 4

    def u64(b, o):
        return struct.unpack_from('<Q', b, o)[0], o + 8

    def string(b, o):
        n, o = u32(b, o)
        if o + n > len(b):
            raise ValueError('a string runs past the file')
        return bytes(b[o:o + n]).decode(), o + n

    data = Path(path).read_bytes()
    if not data.startswith(b'\x89MCAP0\r\n'):
        raise SystemExit(f'record: {path} is not an MCAP file')
    data = memoryview(data)
    schemas, channels = {}, {}

    def records(buf, off, end):
        while off + 9 <= end:
            op = buf[off]
            size, body = u64(buf, off + 1)
            if body + size > end:
                return                        # torn record: stop at the last complete one
            yield op, buf, body, body + size
            off = body + size

    def handle(op, buf, o, end):
        if op == 0x03:
            sid, o = u16(buf, o)
            name, o = string(buf, o)
            schemas[sid] = name
        elif op == 0x04:
            cid, o = u16(buf, o)
            sid, o = u16(buf, o)
            topic, o = string(buf, o)
            _, o = string(buf, o)                 # the message encoding (cdr)
            size, o = u32(buf, o)                 # the metadata map, in bytes
            meta, stop = {}, min(o + size, end)
            while o < stop:
                key, o = string(buf, o)
                meta[key], o = string(buf, o)
            channels[cid] = (topic, schemas.get(sid, ''), meta.get('offered_qos_profiles'))
        elif op == 0x05:
            cid, o = u16(buf, o)
            _, o = u32(buf, o)
            log_time, o = u64(buf, o)
            _, o = u64(buf, o)
            if cid in channels:
                return channels[cid] + (log_time, bytes(buf[o:end]))
        return None

    codec = []                        # the zstd module, once a chunk needs it

    def chunk(buf, o, end):
        """(compression, the chunk's records, uncompressed and checked)."""
        _, o = u64(buf, o)
        _, o = u64(buf, o)
        size, o = u64(buf, o)
        crc, o = u32(buf, o)
        comp, o = string(buf, o)
        n, o = u64(buf, o)
        if o + n > end:
            raise ValueError('a chunk runs past its record')
        body = buf[o:o + n]
        if comp == 'zstd':
            if not codec:
                from .bagfile import zstd_codec
                codec.append(zstd_codec())
            try:
                body = memoryview(codec[0].decompress(body))
            except codec[0].ZstdError as exc:
                raise ValueError(f'a zstd chunk does not decompress: {exc}') from exc
        elif comp:
            raise SystemExit(f'record: cannot recover {comp}-compressed chunks (this '
                             'recorder writes uncompressed and zstd chunks)')
        if len(body) != size or (crc and zlib.crc32(body) != crc):
            raise ValueError('a chunk whose size or CRC does not match its records')
        return comp, body

    def messages():
        for op, buf, o, end in records(data, 8, len(data)):
            if op == 0x06:
                _, body = chunk(buf, o, end)
                for iop, ibuf, io, iend in records(body, 0, len(body)):
                    msg = handle(iop, ibuf, io, iend)
                    if msg:
                        yield msg
            else:
                msg = handle(op, buf, o, end)
                if msg:
                    yield msg

    if compressions is not None or topics is not None:   # headers first, none decompressed
        try:
            for op, buf, o, end in records(data, 8, len(data)):
                if op in (0x03, 0x04):
                    handle(op, buf, o, end)         # the channels, in file order
                elif op == 0x06 and compressions is not None:
                    o += 8 + 8 + 8 + 4
                    comp, o = string(buf, o)
                    n, o = u64(buf, o)
                    if o + n <= end:
                        compressions.add(comp)
        except (struct.error, UnicodeDecodeError, ValueError):
            pass
        if topics is not None:
            topics.extend(channels.values())
    try:
        yield from messages()
    except (struct.error, UnicodeDecodeError, ValueError):
        return                        # a corrupt record: stop at the last good one


def recover(path: Path) -> int:
    """Rebuild a bag whose recorder was killed: every message of its complete chunks is
    rewritten into a valid rosbag2 directory, each topic with the QoS its channel was
    recorded with, compressed with zstd if its chunks were (the torn file is kept as
    ``*.mcap.partial``)."""
    import itertools
    import shutil
    from .progress import Progress
    path = Path(path)
    mcap = path / f'{path.name}.mcap'
    if (path / 'metadata.yaml').exists():
        print(f'record: error: {path} already has metadata.yaml; nothing to recover',
              file=sys.stderr)
        return 2
    if not mcap.exists():
        print(f'record: error: {mcap} not found', file=sys.stderr)
        return 2
    from .bagfile import BagWriter
    tmp = path.parent / f'.{path.name}.recovering'
    if tmp.exists():
        shutil.rmtree(tmp)
    compressions: set = set()
    topics: list = []
    messages = scan_mcap(mcap, compressions, topics)
    first = next(messages, None)          # the chunks' compressions and topics are known now
    bag = BagWriter(tmp, compression='zstd' if 'zstd' in compressions else '')
    for topic, msgtype, qos in topics:    # all first: adding one later cuts a chunk short
        if topic not in bag.topics:
            bag.add(topic, msgtype, qos)
    progress = Progress('record')
    n = 0
    for topic, msgtype, qos, stamp, data in itertools.chain([first] if first else [],
                                                            messages):
        if topic not in bag.topics:
            bag.add(topic, msgtype, qos)
        bag.write(topic, stamp, data)
        n += 1
        progress.update(f'recovering {mcap.name}: {n} messages, {bag.size / 1e6:.1f} MB')
    progress.done()
    bag.close()
    mcap.rename(path / f'{path.name}.mcap.partial')
    (tmp / f'{tmp.name}.mcap').rename(mcap)
    meta = (tmp / 'metadata.yaml').read_text().replace(f'{tmp.name}.mcap', mcap.name)
    (path / 'metadata.yaml').write_text(meta)
    shutil.rmtree(tmp)
    total = sum(bag.counts.values())
    print(f'record: recovered {total} messages into {path} '
          f'({", ".join(f"{t}: {c}" for t, c in bag.counts.items())})')
    return 0


def _qos_of(node, topic: str):
    """(the QoS to subscribe ``topic`` with, its metadata text): keep-last 100, what every
    publisher can serve (as ros2 bag does): reliable unless one publisher is best-effort
    (a reliable subscription would hear nothing from it), transient-local only if all
    publishers latch (it would hear nothing from a volatile one)."""
    from rclpy.qos import DurabilityPolicy, QoSProfile, ReliabilityPolicy
    from .bagfile import qos_yaml
    infos = node.get_publishers_info_by_topic(topic)
    latched = bool(infos) and all(
        i.qos_profile.durability == DurabilityPolicy.TRANSIENT_LOCAL for i in infos)
    reliable = all(i.qos_profile.reliability == ReliabilityPolicy.RELIABLE for i in infos)
    depth = max([i.qos_profile.depth for i in infos] + [1])
    return (QoSProfile(depth=100, reliability=ReliabilityPolicy.RELIABLE if reliable
                       else ReliabilityPolicy.BEST_EFFORT,
                       durability=DurabilityPolicy.TRANSIENT_LOCAL if latched
                       else DurabilityPolicy.VOLATILE),
            qos_yaml(reliable, latched, depth))


def _remove_empty_bag(out: Path) -> None:
    """Remove the bag directory this run created and wrote no message to (its two files;
    ``rmdir`` leaves a directory that holds anything else)."""
    for f in (out / 'metadata.yaml', out / f'{out.name}.mcap'):
        try:
            f.unlink()
        except FileNotFoundError:
            pass
    try:
        out.rmdir()
    except OSError:
        pass


def wrote_line(bag, out: Path, sim_seconds: float) -> str:
    """The recorder's last line: how many messages, how large the file came out, per second
    of simulation time (if any was covered), and how much smaller compression made it."""
    n = sum(bag.counts.values())
    mb = bag.size / 1e6
    size = f'{mb:.1f} MB'
    if sim_seconds > 0:
        size += f', {mb / sim_seconds:.2f} MB per second of simulation time'
    if bag.compression and bag.size:
        size += (f', {bag.compression}: {bag.uncompressed_size / bag.size:.1f} times smaller '
                 'than uncompressed')
    covered = f'; {sim_seconds:.3f} s of simulation time' if sim_seconds > 0 else ''
    counts = ', '.join(f'{t}: {c}' for t, c in bag.counts.items())
    return f'record: wrote {n} messages to {out} ({size}){covered}; {counts}'


def main(argv: List[str] = None) -> int:
    """The ``record`` command (module docstring). Exit codes: 0 recorded; 1 nothing
    recorded (no publisher, or no message, within ``--wait``), or a write failed; 2 a usage
    error or a place it cannot write; 130 interrupted (Ctrl-C, SIGTERM) before the first
    message."""
    argv = sys.argv[1:] if argv is None else argv
    import signal
    import rclpy
    from rclpy.executors import ExternalShutdownException
    from rclpy.parameter import Parameter
    from .bagfile import BagWriter, BagWriteError
    from .progress import Progress
    args_ros = rclpy.utilities.remove_ros_args(['record'] + list(argv))[1:]
    ap = argparse.ArgumentParser(
        prog='record', description='Record the cloth to a rosbag2 directory (MCAP). '
        'Durations are simulation time (the messages\' stamps and /clock); the wall-clock '
        'limits are --timeout and --wait.')
    ap.add_argument('topics', nargs='*', help=f'topics (default: {" ".join(DEFAULT_TOPICS)})')
    ap.add_argument('-o', '--output', help='bag directory to create (must not exist)')
    ap.add_argument('--duration', type=float, default=0.0, metavar='S',
                    help='stop once the recording spans S seconds of SIMULATION time (the '
                    "messages' stamps, or /clock, from the first message; a ~/reset does "
                    'not restart the count), however long that takes on the wall clock; '
                    '0 (default): until Ctrl-C or SIGTERM')
    ap.add_argument('--timeout', type=float, default=0.0, metavar='S',
                    help='WALL-CLOCK limit: stop S seconds after the recording starts, '
                    'however far the simulation got; 0 (default): none')
    ap.add_argument('--node', default='cloth_node', help='node whose ~/ topics to record')
    ap.add_argument('--wait', type=float, default=30.0, metavar='S',
                    help='WALL-CLOCK seconds to wait for the node: for the topics\' '
                    'publishers to appear, then for the first message; nothing by then '
                    'ends the recorder with exit 1 (default 30)')
    ap.add_argument('--camera', action='append', default=[], metavar='NAME',
                    help="also record camera NAME's images, camera_info and pose_out "
                    '(repeatable)')
    ap.add_argument('--wall-time', action='store_true',
                    help='log receive (wall-clock) times instead of simulation time '
                    '(--duration still counts simulation time)')
    ap.add_argument('--compress', choices=('zstd', 'none'), default='zstd',
                    help="compress the bag's chunks with zstd (default; about five times "
                    'smaller for the cloth, as ros2 bag\'s mcap preset zstd_fast), or '
                    'not: none')
    ap.add_argument('--recover', metavar='DIR', help='write metadata.yaml for a bag cut off '
                    'by a crash, then exit')
    a = ap.parse_args(args_ros)
    if a.recover:
        return recover(Path(a.recover))
    if not a.output:
        ap.error('-o/--output is required')
    out = Path(a.output)
    if out.exists():
        print(f'record: error: {out} already exists; bags are never overwritten or appended '
              'to, choose a new directory', file=sys.stderr)
        return 2
    for name in ('duration', 'timeout', 'wait'):
        if getattr(a, name) < 0:
            print(f'record: error: --{name} must be >= 0 [s], got {getattr(a, name):g}',
                  file=sys.stderr)
            return 2
    # past a file-size limit a write then fails (EFBIG) instead of killing the process
    signal.signal(signal.SIGXFSZ, signal.SIG_IGN)
    bad = [c for c in a.camera if not c or '/' in c]
    if bad:
        print(f'record: error: --camera takes a camera name, got {bad[0]!r}', file=sys.stderr)
        return 2
    cameras = [f'~/cameras/{c}/{t}' for c in a.camera for t in CAMERA_TOPICS]
    requested = [resolve(t, a.node) for t in list(a.topics or DEFAULT_TOPICS) + cameras]
    # Ctrl-C and SIGTERM only ask the loop to stop: an exception raised wherever the
    # signal lands (inside a chunk's write or its fsync) would leave the bag's index
    # short of what its statistics count, and a second Ctrl-C would break the close
    from rclpy.signals import SignalHandlerOptions
    rclpy.init(args=['record'] + list(argv), signal_handler_options=SignalHandlerOptions.NO)
    stop: List[int] = []
    stop_signals = (signal.SIGINT, signal.SIGTERM)
    for sig in stop_signals:
        signal.signal(sig, lambda signum, frame: stop.append(signum))
    # the node's clock follows /clock whatever the log times: --duration counts simulation
    # time, and a message without a stamp of its own is at the /clock time it arrives at
    node = rclpy.create_node('cloth_recorder', parameter_overrides=[
        Parameter('use_sim_time', value=True)])
    log = node.get_logger()
    progress = Progress('record')          # on a terminal only

    def info(text: str) -> None:
        progress.clear()                   # a log line, not one drawn over the progress
        log.info(text)

    def warning(text: str) -> None:
        progress.clear()
        log.warning(text)
    bag = None
    code = 0
    nothing = ''                         # why nothing was recorded, if nothing was
    try:
        deadline = time.monotonic() + a.wait
        types: Dict[str, str] = {}
        clock_wanted = not a.wall_time

        def published(names) -> Dict[str, str]:
            """Those of ``names`` that have a publisher (a topic with only subscribers, an
            RViz waiting for the node, sends nothing), and their types."""
            graph = dict(node.get_topic_names_and_types())
            return {t: graph[t][0] for t in names if t in graph and node.count_publishers(t)}
        waiting = time.monotonic()
        while time.monotonic() < deadline and not stop:
            graph = published(requested + ['/clock'])
            types = {t: graph[t] for t in requested if t in graph}
            # on sim time, /clock too (it can come up after the topics asked for)
            if len(types) == len(requested) and (not clock_wanted or '/clock' in graph):
                break
            progress.update(f'waiting for the node: {len(types)} of {len(requested)} '
                            f'topics published after {time.monotonic() - waiting:.0f} s '
                            f'(--wait {a.wait:g})')
            rclpy.spin_once(node, timeout_sec=0.1)
        progress.clear()
        if stop:
            print('record: nothing recorded: interrupted while waiting for the node',
                  file=sys.stderr)
            return 130
        if not types:
            print(f'record: error: nothing recorded: no publisher of {", ".join(requested)} '
                  f'within {a.wait:g} s (--wait, wall clock); is the node running, on this '
                  'ROS_DOMAIN_ID?', file=sys.stderr)
            return 1
        missing = [t for t in requested if t not in types]
        if missing:
            warning(f'no publisher of {", ".join(missing)} after {a.wait:g} s: recording '
                    'the others, and these from when they appear')
        clock_up = '/clock' in published(['/clock'])
        readers = {t: stamp_reader(ty) for t, ty in types.items()}
        if a.duration > 0 and not clock_up and not any(readers.values()):
            print(f'record: error: --duration counts simulation seconds, but there is no '
                  f'/clock publisher and none of {", ".join(types)} carries a stamp; use '
                  '--timeout S for a wall-clock limit', file=sys.stderr)
            return 2
        sim_time = not a.wall_time and clock_up
        clock = node.get_clock()
        if clock_up:                 # the latched /clock first: log times start right
            end = time.monotonic() + a.wait
            while clock.now().nanoseconds == 0 and time.monotonic() < end and not stop:
                rclpy.spin_once(node, timeout_sec=0.05)
        # [the offset added to the sim clock, the last sim time read]: a ~/reset sends
        # the node's clock back to 0, and the log times continue from where they were
        back = [0, 0]

        def stamp() -> int:
            if not sim_time:
                return time.time_ns()
            now = clock.now().nanoseconds
            if now < back[1]:
                back[0] += back[1] - now
                info(f'/clock went back from {back[1] * 1e-9:.3f} s to '
                     f'{now * 1e-9:.3f} s (a reset?): log times continue from '
                     f'{(now + back[0]) * 1e-9:.3f} s')
            back[1] = now
            return now + back[0]
        try:
            bag = BagWriter(out, compression='' if a.compress == 'none' else a.compress)
        except OSError as exc:                 # an unwritable place, a bad path
            print(f'record: error: cannot create {out}: {exc.strerror or exc}',
                  file=sys.stderr)
            return 2
        except ImportError as exc:             # no zstd codec (not with rosbags installed)
            print(f'record: error: --compress {a.compress}: {exc}; or --compress none',
                  file=sys.stderr)
            return 2
        failure: List[str] = []
        span = SimSpan()                       # the simulation time the bag covers
        limit = int(round(a.duration * 1e9)) if a.duration > 0 else None
        finished: List[bool] = []              # --duration reached

        def subscribe(topic: str, type_name: str):
            qos, text = _qos_of(node, topic)
            try:
                bag.add(topic, type_name, text)
            except BagWriteError:
                raise
            except Exception as exc:          # a type rosbags does not know
                warning(f'{topic}: not recorded, its type {type_name} is unknown to the '
                        f'bag writer ({type(exc).__name__}: {exc})')
                return
            read = readers.get(topic) or stamp_reader(type_name)

            def on_message(data, t=topic):
                if failure or finished:
                    return
                sim = None
                if read is not None:
                    try:
                        sim = read(data)
                    except Exception:         # noqa: BLE001 (a malformed message: no stamp)
                        sim = None
                if sim is None and clock_up:
                    sim = clock.now().nanoseconds or None
                if sim is not None:
                    if limit is not None and span.peek(t, sim) > limit:
                        finished.append(True)  # the first message past the end: not kept
                        return
                    span.add(t, sim)
                try:
                    bag.write(t, stamp(), data)
                except BagWriteError as exc:
                    failure.append(str(exc))
            node.create_subscription(message_class(type_name), topic, on_message, qos,
                                     raw=True)
        for topic, type_name in types.items():
            subscribe(topic, type_name)
        start = time.monotonic()
        first_by = start + a.wait              # the first message, or nothing is recorded
        end = start + a.timeout if a.timeout > 0 else None
        next_look = start + 0.5
        said = False                           # the first message's log lines
        timed_out = False
        while rclpy.ok() and not stop and not failure and not finished:
            now = time.monotonic()
            if end is not None and now >= end:
                timed_out = True
                break
            got = sum(bag.counts.values())
            if not got and now >= first_by:
                break
            if got and not said:         # said once something is recorded, not before
                said = True
                info(f'recording {", ".join(types)} to {out}'
                     f' ({"simulation" if sim_time else "wall-clock"} log times'
                     + (f', {a.duration:g} s of simulation time' if limit else '')
                     + (f', at most {a.timeout:g} s of wall time' if a.timeout > 0
                        else '') + ')')
                if not a.wall_time and not sim_time:
                    warning('no /clock publisher: logging wall-clock receive times')
            if got:
                progress.update(f'{span.elapsed() * 1e-9:.1f}'
                                + (f' of {a.duration:g}' if limit else '')
                                + f' s of simulation time, {got} messages, '
                                f'{bag.size / 1e6:.1f} MB')
            rclpy.spin_once(node, timeout_sec=0.05)
            if missing and time.monotonic() >= next_look:
                next_look = time.monotonic() + 0.5
                graph = published(missing)
                for t in [t for t in missing if t in graph]:
                    subscribe(t, graph[t])
                    missing.remove(t)
                    info(f'{t} appeared: recording it too')
        if failure:
            print(f'record: error: writing {out} failed: {failure[0]}', file=sys.stderr)
            code = 1
        elif not sum(bag.counts.values()):
            if stop:
                nothing = 'record: nothing recorded: interrupted before the first message'
                code = 130
            else:
                why = (f'no message within --timeout {a.timeout:g} s (wall clock)'
                       if timed_out else
                       f'the publishers of {", ".join(types)} sent no message within '
                       f'{a.wait:g} s (--wait, wall clock); is the node stuck?')
                nothing = f'record: error: nothing recorded: {why}'
                code = 1
        elif timed_out and limit is not None:
            warning(f'stopped by --timeout {a.timeout:g} s (wall clock) after '
                    f'{span.elapsed() * 1e-9:.3f} s of the {a.duration:g} s of '
                    'simulation time asked (--duration)')
    except BagWriteError as exc:                      # while adding a topic
        print(f'record: error: writing {out} failed: {exc}', file=sys.stderr)
        code = 1
    except (KeyboardInterrupt, ExternalShutdownException):
        pass
    finally:
        progress.done()                        # the last progress line stays, ended
        if bag is not None:
            try:
                bag.close()
            except BagWriteError as exc:
                print(f'record: error: closing {out} failed: {exc}', file=sys.stderr)
                code = 1
            if nothing:
                _remove_empty_bag(out)
                print(nothing, file=sys.stderr)
            else:
                print(wrote_line(bag, out, span.elapsed() * 1e-9 if span else 0.0))
        node.destroy_node()
        # rclpy's shutdown puts back the signals' default action (ending the process
        # with -2 on one more Ctrl-C): held back over it, then answered by nothing
        signal.pthread_sigmask(signal.SIG_BLOCK, stop_signals)
        rclpy.try_shutdown()
        for sig in stop_signals:
            signal.signal(sig, lambda signum, frame: None)
        signal.pthread_sigmask(signal.SIG_UNBLOCK, stop_signals)
    return code

if __name__ == '__main__':
    sys.exit(main())
