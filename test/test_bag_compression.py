"""zstd-compressed chunks in the bag writer (cosserat_ros/tools/bagfile.py): independent
readers get every message back bit-equal, render draws from such a bag, the recovery of a
killed recording reads compressed chunks up to a torn or corrupt one. No process is
started here: the recorder's own runs are in test_record_render.py."""
import io
import struct
import zlib

import numpy as np
import pytest
import yaml
from rosbags.highlevel import AnyReader

from cosserat_ros.tools.bagfile import BagWriter, CHUNK_BYTES, zstd_codec

MESH = '/cloth_node/mesh'
CLOCK = '/clock'
ENERGY = '/cloth_node/energy'
NOISE = '/noise/image_raw'


def _messages(n_ticks=40, nx=24):
    """(topic, type, log time [ns], serialised message) of ``n_ticks`` ticks of a moving
    cloth: mesh, energy and /clock each tick, and now and then an image of random pixels
    (which zstd cannot make smaller), larger than a chunk every tenth tick."""
    from rclpy.serialization import serialize_message
    from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus, KeyValue
    from builtin_interfaces.msg import Time
    from rosgraph_msgs.msg import Clock
    from cosserat_ros.mesh import grid_mesh
    from cosserat_ros.ros.conversions import colormap, image, mesh_marker_array
    rng = np.random.default_rng(7)
    m = grid_mesh(nx, nx)
    out = []
    for k in range(n_ticks):
        t = k * 33_333_333
        v = m.vertices.copy()
        v[:, 2] -= 0.02 * k * v[:, 0] ** 2                     # the cloth sags as it goes
        out.append((CLOCK, 'rosgraph_msgs/msg/Clock', t, serialize_message(
            Clock(clock=Time(sec=t // 10 ** 9, nanosec=t % 10 ** 9)))))
        out.append((MESH, 'visualization_msgs/msg/MarkerArray', t, mesh_marker_array(
            v, m.faces, colormap(v[:, 2], -0.5, 0.0), t, 'world')))
        out.append((ENERGY, 'diagnostic_msgs/msg/DiagnosticArray', t, serialize_message(
            DiagnosticArray(status=[DiagnosticStatus(name='energy', values=[
                KeyValue(key='sim_time', value=repr(t * 1e-9)),
                KeyValue(key='kinetic', value=repr(0.01 * k))])]))))
        if k % 10 == 5:
            side = 700 if k % 20 == 5 else 64              # 1.5 MB: a chunk of its own
            pixels = rng.integers(0, 256, (side, side, 3), dtype=np.uint8)
            out.append((NOISE, 'sensor_msgs/msg/Image', t, image(pixels, t, 'cam')))
    return out


def _write(path, messages, compression='zstd', close=True):
    """A bag of ``messages``; returns the writer and, after each message, how many of
    the messages lay in complete chunks on disk then."""
    w = BagWriter(path, compression=compression)
    done, flushed = [], 0
    for k, (topic, type_name, t, data) in enumerate(messages):
        if topic not in w.topics:
            w.add(topic, type_name)
        size = w.size
        w.write(topic, t, data)
        if w.size != size:                       # a chunk was written: all up to this one
            flushed = k + 1
        done.append(flushed)
    if close:
        w.close()
    return w, done


@pytest.fixture(scope='module')
def messages():
    return _messages()


@pytest.fixture(scope='module')
def zbag(messages, tmp_path_factory):
    path = tmp_path_factory.mktemp('z') / 'cloth'
    w, _ = _write(path, messages)
    return path, w


def test_every_reader_gets_every_message_back_bit_equal(zbag, messages):
    from mcap.reader import make_reader
    from mcap.records import Chunk
    from mcap.stream_reader import StreamReader
    from cosserat_ros.tools.record import scan_mcap
    path, w = zbag
    mcap = path / 'cloth.mcap'
    expected = [(topic, t, bytes(data)) for topic, _, t, data in messages]
    # Foxglove's reader, every CRC checked (chunks: of the uncompressed records)
    with open(mcap, 'rb') as fh:
        reader = make_reader(fh, validate_crcs=True)
        got = [(c.topic, m.log_time, bytes(m.data))
               for _, c, m in reader.iter_messages(log_time_order=False)]
        summary = reader.get_summary()
    assert got == expected
    assert summary.statistics.message_count == len(expected)
    # the Chunk Index: compression and both sizes; a chunk of noise is stored as it is
    kinds = [(ci.compression, ci.compressed_size, ci.uncompressed_size)
             for ci in summary.chunk_indexes]
    zipped = [k for k in kinds if k[0] == 'zstd']
    assert len(zipped) >= 3 and all(c < u for _, c, u in zipped), kinds
    assert any(k[0] == '' and k[1] == k[2] for k in kinds), kinds
    # each chunk record: compression, sizes and the CRC of its uncompressed records
    codec = zstd_codec()
    chunks = [r for r in StreamReader(io.BytesIO(mcap.read_bytes()), validate_crcs=True,
                                      emit_chunks=True).records if isinstance(r, Chunk)]
    assert len(chunks) == len(kinds)
    for c, (how, csize, usize) in zip(chunks, kinds):
        assert (c.compression, len(c.data), c.uncompressed_size) == (how, csize, usize)
        body = codec.decompress(c.data) if how == 'zstd' else c.data
        assert len(body) == usize and zlib.crc32(body) == c.uncompressed_crc != 0
    # a flipped byte in a chunk stored as it is fails its CRC; in a zstd chunk, the
    # decoder or the CRC
    import zstandard
    from mcap.stream_reader import CRCValidationError
    data = mcap.read_bytes()
    for how, errors in (('', CRCValidationError), ('zstd', (CRCValidationError,
                                                            zstandard.ZstdError))):
        ci = max((ci for ci in summary.chunk_indexes if ci.compression == how),
                 key=lambda ci: ci.chunk_length)      # its middle: in the records
        bad = bytearray(data)
        bad[ci.chunk_start_offset + ci.chunk_length // 2] ^= 0x55
        with pytest.raises(errors):
            list(make_reader(io.BytesIO(bytes(bad)), validate_crcs=True).iter_messages())
    # rosbags' reader (the one render uses), and the recovery's own scan
    with AnyReader([path]) as reader:
        assert [(c.topic, t, bytes(raw)) for c, t, raw in reader.messages()] == expected
    assert [(topic, t, data) for topic, _, _, t, data in scan_mcap(mcap)] == expected
    # storage-level compression: rosbag2's own compression fields stay empty, as ros2
    # bag's MCAP writes them
    meta = yaml.safe_load((path / 'metadata.yaml').read_text())['rosbag2_bagfile_information']
    assert meta['compression_format'] == '' and meta['compression_mode'] == ''
    assert meta['message_count'] == len(expected)
    # the sizes the recorder reports
    assert w.size == mcap.stat().st_size
    assert w.uncompressed_size > 1.5 * w.size


def test_compression_is_the_only_difference(zbag, messages, tmp_path):
    """The same messages uncompressed: the same chunks (times, sizes, CRCs), the one bag
    about as large as the other says it would be."""
    from mcap.reader import make_reader
    path, w = zbag
    plain, _ = _write(tmp_path / 'plain', messages, compression='')
    with open(path / 'cloth.mcap', 'rb') as a, open(tmp_path / 'plain' / 'plain.mcap',
                                                    'rb') as b:
        za, pb = make_reader(a).get_summary(), make_reader(b).get_summary()
    assert [(c.message_start_time, c.message_end_time, c.uncompressed_size)
            for c in za.chunk_indexes] == [(c.message_start_time, c.message_end_time,
                                            c.uncompressed_size) for c in pb.chunk_indexes]
    assert {c.compression for c in pb.chunk_indexes} == {''}
    assert plain.size == plain.uncompressed_size
    # 'zstd' in each chunk record and chunk index is the only other difference in bytes
    assert w.uncompressed_size - plain.size == 8 * sum(
        c.compression == 'zstd' for c in za.chunk_indexes)


@pytest.mark.slow
def test_render_draws_from_a_compressed_bag(zbag, tmp_path):
    from PIL import Image
    from cosserat_ros.tools.render import read_bag, render
    path, _ = zbag
    meshes, energies, _ = read_bag(path, MESH, ENERGY)
    assert len(meshes) == 40 and len(energies) == 40
    written = render(meshes, energies, tmp_path / 'out', frames=4)
    names = {p.name for p in written}
    assert {'cloth.gif', 'energy.png', 'cloth_0.000s.png', 'cloth_1.300s.png'} <= names
    first, last = (np.asarray(Image.open(tmp_path / 'out' / n).convert('RGB'), dtype=float)
                   for n in ('cloth_0.000s.png', 'cloth_1.300s.png'))
    assert first.std() > 10 and np.abs(first - last).mean() > 0.5     # drawn, and it sagged


def test_recovery_reads_zstd_chunks_up_to_a_torn_or_corrupt_one(messages, tmp_path):
    """A recording killed mid-way (the writer never closed: no summary, the last chunk
    maybe half written) is rebuilt from its complete compressed chunks, bit-equal, and
    compressed again; a chunk whose bytes were damaged ends the recovery before it."""
    from mcap.reader import make_reader
    from cosserat_ros.tools.record import recover
    w, done = _write(tmp_path / 'live', messages, close=False)
    data = (tmp_path / 'live' / 'live.mcap').read_bytes()
    w._f.close()
    chunks = []                                 # (offset, length) of each chunk record
    off = 8
    while off + 9 <= len(data):
        op, n = struct.unpack_from('<BQ', data, off)
        if op == 0x06:
            chunks.append((off, 9 + n))
        off += 9 + n
    assert len(chunks) >= 4
    # the chunks' compression strings: zstd, and none for the chunk of noise
    how = [struct.unpack_from('<I', data, o + 9 + 28)[0] for o, _ in chunks]
    assert 4 in how and 0 in how, how

    def rebuilt(name, blob):
        d = tmp_path / name
        d.mkdir()
        (d / f'{name}.mcap').write_bytes(blob)
        assert recover(d) == 0
        assert (d / f'{name}.mcap.partial').read_bytes() == blob
        with open(d / f'{name}.mcap', 'rb') as fh:
            reader = make_reader(fh, validate_crcs=True)
            got = [(c.topic, m.log_time, bytes(m.data))
                   for _, c, m in reader.iter_messages(log_time_order=False)]
            comps = {ci.compression for ci in reader.get_summary().chunk_indexes}
        with AnyReader([d]) as reader:
            assert reader.message_count == len(got)
        return got, comps
    expected = [(topic, t, bytes(m)) for topic, _, t, m in messages]
    # killed after the last complete chunk: all of them
    got, comps = rebuilt('whole', data)
    assert got == expected[:done[-1]] and comps >= {'zstd'}
    # killed in the middle of the writing of a compressed chunk: those before it
    k = max(i for i, h in enumerate(how) if h == 4)
    o, n = chunks[k]
    got, _ = rebuilt('torn', data[:o + n // 2])
    assert got == expected[:_count_before(data, o)] and len(got) > 0
    # a byte flipped inside an earlier compressed chunk's zstd frame: those before it
    j = min(i for i, h in enumerate(how) if h == 4 and i > 0)
    o, n = chunks[j]
    bad = bytearray(data)
    bad[o + n // 2] ^= 0x55
    got, _ = rebuilt('damaged', bytes(bad))
    assert got == expected[:_count_before(data, o)] and len(got) > 0
    # ... and inside the chunk of noise, stored uncompressed: its CRC says so
    j = how.index(0)
    o, n = chunks[j]
    bad = bytearray(data)
    bad[o + n // 2] ^= 0x55
    got, _ = rebuilt('damaged_raw', bytes(bad))
    assert got == expected[:_count_before(data, o)] and len(got) > 0


def _count_before(data: bytes, end: int) -> int:
    """How many message records the chunks before byte ``end`` of an MCAP file hold (read
    from their message indexes, which follow each chunk)."""
    off, n = 8, 0
    while off + 9 <= end:
        op, size = struct.unpack_from('<BQ', data, off)
        if op == 0x07:                                  # Message Index: 16 bytes a row
            n += struct.unpack_from('<I', data, off + 9 + 2)[0] // 16
        off += 9 + size
    return n


def test_a_chunk_larger_than_chunk_bytes_is_one_compressed_chunk(tmp_path):
    """A message above the chunk size (a fine cloth's mesh) is a chunk of its own,
    compressed whole."""
    from mcap.reader import make_reader
    from cosserat_ros.mesh import grid_mesh
    from cosserat_ros.ros.conversions import colormap, mesh_marker_array
    m = grid_mesh(120, 120)
    data = [mesh_marker_array(m.vertices + 0.1 * k, m.faces,
                              colormap(m.vertices[:, 0], 0.0, 1.0), k, 'world')
            for k in range(2)]
    assert min(map(len, data)) > CHUNK_BYTES
    w, _ = _write(tmp_path / 'big', [(MESH, 'visualization_msgs/msg/MarkerArray', k, d)
                                     for k, d in enumerate(data)])
    with open(tmp_path / 'big' / 'big.mcap', 'rb') as fh:
        reader = make_reader(fh, validate_crcs=True)
        assert [bytes(msg.data) for _, _, msg in reader.iter_messages()] == data
        assert [ci.compression for ci in reader.get_summary().chunk_indexes] == ['zstd'] * 2
    assert w.uncompressed_size > 3 * w.size
