"""A rosbag2 directory with MCAP storage, written here: CRCs on, chunks compressed with zstd
if asked, and readable after a failed write.

``DIR/metadata.yaml`` + ``DIR/DIR.mcap``, as ``ros2 bag record -s mcap`` lays them out
(metadata version 9; profile ``ros2``; schemas ``ros2msg`` with the full message definition;
channels ``cdr`` with their ``offered_qos_profiles``). The MCAP file follows the
specification (https://mcap.dev/spec): messages in chunks of about 1 MiB (uncompressed),
each chunk with the CRC-32 of its uncompressed records and followed by its message indexes;
the data section's CRC in Data End; the summary (schemas, channels, chunk indexes,
statistics, summary offsets) and its CRC in the footer. Readers that validate CRCs
(``mcap``'s ``make_reader(..., validate_crcs=True)``, ``mcap doctor``) therefore have
something to check.

Compression (``BagWriter(path, compression='zstd')``) is per chunk, as ``ros2 bag record -s
mcap --storage-preset-profile zstd_fast`` writes it: the chunk's records compressed as one
zstd frame at level :data:`ZSTD_LEVEL` (the preset's "Fastest"), its ``compression``
``"zstd"``, ``uncompressed_size`` and ``uncompressed_crc`` those of the records, and the
Chunk Index giving the compression and both sizes; a chunk that compression would not make
smaller is written uncompressed (as the mcap writers do unless forced). The message indexes
and the summary are not compressed, and ``metadata.yaml`` keeps ``compression_format: ''``
(compression inside the storage, not rosbag2's file or message compression), so every
MCAP reader (``ros2 bag``, Foxglove, ``mcap``, ``rosbags``) opens the bag as it is. The
zstd codec is the standard library's ``compression.zstd`` (Python >= 3.14) or its backport
``backports.zstd``, which ``rosbags`` installs (:func:`zstd_codec`).

A write that fails (a full disk, a file-size limit) raises :class:`BagWriteError` after the
bag was closed readable: the file is cut back to the end of its last complete chunk, which
was flushed and synced when it completed, and ends there with Data End and a footer
without summary (readers then scan it); ``metadata.yaml`` describes what the kept chunks
hold. If even those few bytes do not fit, it steps back one chunk more (freeing a chunk's
worth of space). The schema and channel of each topic are written to the file, outside
chunks, when the topic is added, so every kept chunk's messages have theirs.
"""
from __future__ import annotations

from dataclasses import dataclass
import io
import os
from pathlib import Path
import struct
from typing import Dict, List, Optional
import zlib

__all__ = ['BagWriter', 'BagWriteError', 'qos_yaml', 'zstd_codec', 'MAGIC', 'COMPRESSIONS',
           'ZSTD_LEVEL']

MAGIC = b'\x89MCAP0\r\n'
CHUNK_BYTES = 1 << 20
_LIBRARY = 'cosserat_ros record'
#: the chunk compressions the writer offers ('': none)
COMPRESSIONS = ('', 'zstd')
#: zstd's level: -5, what ``--storage-preset-profile zstd_fast`` asks for (the mcap C++
#: writer's "Fastest"); on the cloth's topics level 1 is 4 % smaller and costs 40 % more
#: time (doc/viewing.md)
ZSTD_LEVEL = -5


def zstd_codec():
    """The zstd module of PEP 784: ``compression.zstd`` (Python >= 3.14) or its backport
    ``backports.zstd`` (a requirement of rosbags, hence installed with this package); an
    ImportError naming them if neither is there."""
    try:
        from compression import zstd
    except ImportError:
        try:
            from backports import zstd
        except ImportError as exc:
            raise ImportError('zstd compression needs compression.zstd (Python >= 3.14) or '
                              'backports.zstd (pip install backports.zstd; rosbags '
                              'requires it)') from exc
    return zstd


class BagWriteError(OSError):
    """A write failed; the bag was closed readable with what came before (the message
    says how much)."""


def _str(s: str) -> bytes:
    b = s.encode()
    return struct.pack('<I', len(b)) + b


def _map(d: Dict[str, str]) -> bytes:
    body = b''.join(_str(k) + _str(v) for k, v in d.items())
    return struct.pack('<I', len(body)) + body


def _record(op: int, body: bytes) -> bytes:
    return struct.pack('<BQ', op, len(body)) + body


def qos_yaml(reliable: bool = True, latched: bool = False, depth: int = 5) -> str:
    """``offered_qos_profiles`` of metadata version 9 for one publisher (what ``ros2 bag
    play`` offers again)."""
    inf = '{sec: 9223372036, nsec: 854775807}'
    return (f'- history: keep_last\n  depth: {depth}\n'
            f'  reliability: {"reliable" if reliable else "best_effort"}\n'
            f'  durability: {"transient_local" if latched else "volatile"}\n'
            f'  deadline: {inf}\n  lifespan: {inf}\n  liveliness: automatic\n'
            f'  liveliness_lease_duration: {inf}\n  avoid_ros_namespace_conventions: false')


@dataclass
class _Topic:
    cid: int
    name: str
    type_name: str
    qos: str
    digest: str
    count: int = 0


@dataclass
class _Mark:
    """A point up to which the file is complete: its offset, the data CRC there, and the
    statistics of what lies before it."""
    offset: int
    crc: int
    counts: Dict[int, int]
    start: int
    end: int
    chunks: int                # how many of the writer's chunk indexes lie before it
    saved: int = 0             # bytes compression kept out of the file before it


class BagWriter:
    """Writes one rosbag2 directory (module docstring). ``add`` a topic, ``write`` its
    serialised messages with their log times [ns], ``close`` it. ``compression``: '' (none)
    or 'zstd', chunk by chunk; :attr:`size` and :attr:`uncompressed_size` say how much
    was written so far."""

    def __init__(self, path, typestore=None, compression: str = ''):
        from rosbags.typesys import get_typestore, Stores
        if compression not in COMPRESSIONS:
            raise ValueError(f'compression must be one of {COMPRESSIONS}, got '
                             f'{compression!r}')
        # the codec first: a missing module is no half-made bag directory
        self._zstd = zstd_codec() if compression == 'zstd' else None
        self.compression = compression
        self._saved = 0                 # bytes compression kept out of the file so far
        self.path = Path(path)
        self.path.parent.mkdir(parents=True, exist_ok=True)    # `record -o bags/run1`
        self.path.mkdir(exist_ok=False)
        self.file = self.path / f'{self.path.name}.mcap'
        try:
            self._f = open(self.file, 'xb', buffering=0)    # raw: nothing held back to fail
        except OSError:
            self.path.rmdir()                   # no empty directory left in the way
            raise
        self._ts = typestore or get_typestore(Stores.ROS2_JAZZY)
        self._crc = 0
        self._pos = 0
        self.topics: Dict[str, _Topic] = {}
        self._schemas: Dict[str, int] = {}
        self._summary_records: List[bytes] = []      # schema and channel records
        self._chunk = io.BytesIO()
        self._index: Dict[int, List[bytes]] = {}
        self._chunk_start = self._chunk_end = None
        self._start, self._end = 2 ** 63 - 1, 0
        self._closed = False
        self._chunk_indexes: List[bytes] = []          # one Chunk Index record per chunk
        self._emit(MAGIC + _record(0x01, _str('ros2') + _str(_LIBRARY)))
        self._marks = [self._mark()]

    # ------------------------------------------------------------------ writing
    def _write(self, data: bytes):
        view = memoryview(data)
        while view:
            view = view[self._f.write(view):]

    def _emit(self, data: bytes):
        self._write(data)
        self._crc = zlib.crc32(data, self._crc)
        self._pos += len(data)

    def _mark(self) -> _Mark:
        return _Mark(self._pos, self._crc, {t.cid: t.count for t in self.topics.values()},
                     self._start, self._end, len(self._chunk_indexes), self._saved)

    def _durable(self):
        """Flush and sync what was written and remember the point."""
        os.fsync(self._f.fileno())
        self._marks.append(self._mark())
        del self._marks[:-3]                         # a few points back are enough

    def add(self, topic: str, type_name: str, qos: Optional[str] = None) -> None:
        """A topic of ``type_name`` ('pkg/msg/Name'), offered with ``qos``
        (:func:`qos_yaml`): its schema and channel go to the file at once."""
        if topic in self.topics:
            return
        try:
            self._flush_chunk()
            if type_name not in self._schemas:
                sid = len(self._schemas) + 1
                text, _ = self._ts.generate_msgdef(type_name, ros_version=2)
                rec = _record(0x03, struct.pack('<H', sid) + _str(type_name) + _str('ros2msg')
                              + _str(text))
                self._schemas[type_name] = sid
                self._summary_records.append(rec)
                self._emit(rec)
            cid = len(self.topics) + 1
            t = _Topic(cid, topic, type_name, qos or qos_yaml(),
                       self._ts.hash_rihs01(type_name))
            rec = _record(0x04, struct.pack('<HH', cid, self._schemas[type_name])
                          + _str(topic) + _str('cdr')
                          + _map({'offered_qos_profiles': t.qos}))
            self.topics[topic] = t
            self._summary_records.append(rec)
            self._emit(rec)
            self._durable()
        except OSError as exc:
            self._fail(exc)

    def write(self, topic: str, log_time: int, data: bytes) -> None:
        """One serialised message of ``topic`` at ``log_time`` [ns]; BagWriteError if the
        write failed (the bag is then closed, readable)."""
        t = self.topics[topic]
        offset = self._chunk.tell()
        self._chunk.write(_record(0x05, struct.pack('<HIQQ', t.cid, t.count, log_time,
                                                    log_time) + bytes(data)))
        self._index.setdefault(t.cid, []).append(struct.pack('<QQ', log_time, offset))
        t.count += 1
        if self._chunk_start is None:
            self._chunk_start = self._chunk_end = log_time
        self._chunk_start = min(self._chunk_start, log_time)
        self._chunk_end = max(self._chunk_end, log_time)
        if self._chunk.tell() >= CHUNK_BYTES:
            try:
                self._flush_chunk()
            except OSError as exc:
                self._fail(exc)

    def _flush_chunk(self):
        if not self._chunk.tell():
            return
        data = self._chunk.getvalue()
        start, end = self._chunk_start, self._chunk_end
        chunk_at = self._pos
        stored, how = data, ''
        if self._zstd is not None:
            packed = self._zstd.compress(data, ZSTD_LEVEL)
            if len(packed) < len(data):       # else stored as it is (the mcap writers too)
                stored, how = packed, 'zstd'
        self._emit(_record(0x06, struct.pack('<QQQI', start, end, len(data), zlib.crc32(data))
                           + _str(how) + struct.pack('<Q', len(stored)) + stored))
        chunk_len = self._pos - chunk_at
        offsets = {}
        for cid, rows in self._index.items():
            offsets[cid] = self._pos
            body = b''.join(rows)
            self._emit(_record(0x07, struct.pack('<HI', cid, len(body)) + body))
        idx_len = self._pos - chunk_at - chunk_len
        omap = b''.join(struct.pack('<HQ', c, o) for c, o in offsets.items())
        self._chunk_indexes.append(_record(
            0x08, struct.pack('<QQQQ', start, end, chunk_at, chunk_len)
            + struct.pack('<I', len(omap)) + omap + struct.pack('<Q', idx_len) + _str(how)
            + struct.pack('<QQ', len(stored), len(data))))
        self._saved += len(data) - len(stored)
        self._start, self._end = min(self._start, start), max(self._end, end)
        self._chunk = io.BytesIO()
        self._index = {}
        self._chunk_start = self._chunk_end = None
        self._durable()

    # ------------------------------------------------------------------ closing
    def close(self) -> None:
        """Write the last chunk, the summary and metadata.yaml."""
        if self._closed:
            return
        try:
            self._flush_chunk()
            mark = self._marks[-1]
            self._emit(_record(0x0F, struct.pack('<I', self._crc)))
            summary = io.BytesIO()
            at = self._pos
            groups = []

            def group(op, records):
                if records:
                    groups.append((op, at + summary.tell(), sum(len(r) for r in records)))
                    for r in records:
                        summary.write(r)
            group(0x03, [r for r in self._summary_records if r[0] == 0x03])
            group(0x04, [r for r in self._summary_records if r[0] == 0x04])
            group(0x08, self._chunk_indexes[:mark.chunks])
            counts = b''.join(struct.pack('<HQ', t.cid, t.count) for t in self.topics.values())
            group(0x0B, [_record(0x0B, struct.pack(
                '<QHIIIIQQ', sum(t.count for t in self.topics.values()), len(self._schemas),
                len(self.topics), 0, 0, mark.chunks,
                self._start if self._end else 0, self._end)
                + struct.pack('<I', len(counts)) + counts)])
            offsets_at = at + summary.tell()
            for op, start, length in groups:
                summary.write(_record(0x0E, struct.pack('<BQQ', op, start, length)))
            body = summary.getvalue()
            crc = zlib.crc32(struct.pack('<BQQQ', 0x02, 20, at, offsets_at),
                             zlib.crc32(body))
            tail = body + _record(0x02, struct.pack('<QQI', at, offsets_at, crc)) + MAGIC
            self._write(tail)
            self._pos += len(tail)
            os.fsync(self._f.fileno())
            self._f.close()
            self._closed = True
            self._metadata(mark)
        except OSError as exc:
            self._fail(exc)

    def _fail(self, exc: OSError):
        """Close the bag readable at its last complete point, then raise BagWriteError."""
        if self._closed:
            raise BagWriteError(str(exc)) from exc
        self._closed = True
        kept = None
        for mark in reversed(self._marks):
            try:
                self._f.truncate(mark.offset)
                self._f.seek(mark.offset)
                tail = (_record(0x0F, struct.pack('<I', mark.crc))
                        + _record(0x02, struct.pack('<QQI', 0, 0, 0)) + MAGIC)
                self._write(tail)
                os.fsync(self._f.fileno())
                kept = mark
                self._pos, self._saved = mark.offset + len(tail), mark.saved
                break
            except OSError:
                continue
        try:
            self._f.close()
        except OSError:
            pass
        if kept is None:
            raise BagWriteError(f'{exc}; nothing could be kept') from exc
        for t in self.topics.values():
            t.count = kept.counts.get(t.cid, 0)
        try:
            self._metadata(kept)
        except OSError as exc2:
            raise BagWriteError(f'{exc}; metadata.yaml could not be written either: '
                                f'{exc2}') from exc
        raise BagWriteError(f'{exc.strerror or exc}; closed with the '
                            f'{sum(t.count for t in self.topics.values())} messages written '
                            'before it') from exc

    def _metadata(self, mark: _Mark):
        # the topics whose channel record lies before the mark (add() marks after it)
        topics = [t for t in self.topics.values() if t.cid in mark.counts]
        count = sum(t.count for t in topics)
        start = mark.start if count else 0
        duration = max(0, mark.end - mark.start) if count else 0
        lines = ['rosbag2_bagfile_information:', '  version: 9',
                 '  storage_identifier: mcap',
                 f'  duration:\n    nanoseconds: {duration}',
                 f'  starting_time:\n    nanoseconds_since_epoch: {start}',
                 f'  message_count: {count}', '  topics_with_message_count:']
        for t in topics:
            qos = '\n'.join('        ' + ln for ln in t.qos.splitlines())
            lines += ['    - topic_metadata:', f'        name: {t.name}',
                      f'        type: {t.type_name}', '        serialization_format: cdr',
                      '        offered_qos_profiles:', qos,
                      f'        type_description_hash: {t.digest}',
                      f'      message_count: {t.count}']
        lines += ["  compression_format: ''", "  compression_mode: ''",
                  '  relative_file_paths:', f'    - {self.file.name}', '  files:',
                  f'    - path: {self.file.name}',
                  f'      starting_time:\n        nanoseconds_since_epoch: {start}',
                  f'      duration:\n        nanoseconds: {duration}',
                  f'      message_count: {count}', '  custom_data: ~',
                  '  ros_distro: jazzy', '']
        tmp = self.path / 'metadata.yaml.tmp'
        tmp.write_text('\n'.join(lines))
        tmp.replace(self.path / 'metadata.yaml')

    @property
    def typestore(self):
        """The rosbags type store the schemas come from (it serialises too)."""
        return self._ts

    @property
    def counts(self) -> Dict[str, int]:
        return {t.name: t.count for t in self.topics.values()}

    @property
    def size(self) -> int:
        """Bytes written to the MCAP file so far (the completed chunks; the summary once
        closed)."""
        return self._pos

    @property
    def uncompressed_size(self) -> int:
        """What :attr:`size` would be with every chunk stored uncompressed (but for the
        word 'zstd' each compressed chunk names in its record and its index: 8 bytes)."""
        return self._pos + self._saved
