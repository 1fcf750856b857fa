"""Recover bags whose recorder died, and summarize bags.

A recorder killed with SIGKILL (or a machine that lost power) leaves a rosbag2 directory whose
``.mcap`` has no summary section and no footer, and no ``metadata.yaml`` (or a stale one): readers
that seek to the footer refuse it. :func:`recover_bag` reads such a file from the start, record by
record (:class:`McapScan`), stops cleanly at the first truncated or corrupt record, and writes a
complete bag with every message that was fully on disk.

The parser is a small one of our own, bounded by the file size at every step, so a cut at any byte
(or garbage after the last good record) ends the scan instead of raising or allocating.

MCAP records (https://mcap.dev/spec): ``opcode u8, length u64, body``; integers little-endian,
strings ``u32 length + UTF-8``. A chunk holds schema, channel and message records, compressed with
zstd or lz4 or not at all. Messages of a chunk whose end is missing are recovered when their bytes
are complete inside the part that is on disk (a compressed chunk is decompressed as far as its
data goes).
"""

from __future__ import annotations

import re
import shutil
import struct
import sys
import zlib
from collections.abc import Iterator
from dataclasses import dataclass, field
from datetime import datetime, timezone
from pathlib import Path
from typing import BinaryIO

import yaml
from rosbags.rosbag2 import Reader, Writer
from rosbags.rosbag2.enums import CompressionFormat, CompressionMode, StoragePlugin
from rosbags.rosbag2.errors import ReaderError
from rosbags.rosbag2.errors import WriterError as RosbagsWriterError
from rosbags.rosbag2.metadata import parse_qos
from rosbags.typesys import Stores, get_types_from_idl, get_types_from_msg, get_typestore

from cloe_ros.errors import CloeError

MAGIC = b'\x89MCAP0\r\n'

OP_HEADER = 0x01
OP_FOOTER = 0x02
OP_SCHEMA = 0x03
OP_CHANNEL = 0x04
OP_MESSAGE = 0x05
OP_CHUNK = 0x06
OP_DATA_END = 0x0F
#: Opcodes the MCAP specification defines (0x01-0x10); 0x80-0xFF are user extensions.
_KNOWN_OPCODES = range(0x01, 0x11)
_OPCODE_NAMES = {
    0x01: 'Header',
    0x02: 'Footer',
    0x03: 'Schema',
    0x04: 'Channel',
    0x05: 'Message',
    0x06: 'Chunk',
    0x07: 'MessageIndex',
    0x08: 'ChunkIndex',
    0x09: 'Attachment',
    0x0A: 'AttachmentIndex',
    0x0B: 'Statistics',
    0x0C: 'Metadata',
    0x0D: 'MetadataIndex',
    0x0E: 'SummaryOffset',
    0x0F: 'DataEnd',
    0x10: 'SummaryOffset',
}

_U16 = struct.Struct('<H')
_U32 = struct.Struct('<I')
_U64 = struct.Struct('<Q')
_RECORD_HEAD = struct.Struct('<BQ')
_MESSAGE_HEAD = struct.Struct('<HIQQ')  # channel id, sequence, log time, publish time
_CHUNK_HEAD = struct.Struct('<QQQI')  # start, end, uncompressed size, uncompressed crc


class RecoverError(CloeError):
    """A bag that cannot be recovered or read (not a bag, no MCAP file, output exists, ...)."""


class _Corrupt(Exception):
    """Bytes that do not parse as the record they claim to be (internal)."""


@dataclass(frozen=True)
class McapSchema:
    id: int
    name: str
    encoding: str
    data: bytes


@dataclass(frozen=True)
class McapChannel:
    id: int
    schema_id: int
    topic: str
    message_encoding: str
    metadata: tuple[tuple[str, str], ...]


@dataclass(frozen=True)
class McapMessage:
    channel_id: int
    sequence: int
    log_time: int
    publish_time: int
    data: bytes


# -- record bodies -----------------------------------------------------------------------------


class _Body:
    """A cursor over one record's body that never reads past its end."""

    def __init__(self, data: bytes | memoryview) -> None:
        self.data = memoryview(data)
        self.pos = 0

    def take(self, n: int) -> memoryview:
        if n < 0 or self.pos + n > len(self.data):
            raise _Corrupt(f'field of {n} bytes at {self.pos} overruns the record')
        out = self.data[self.pos : self.pos + n]
        self.pos += n
        return out

    def u16(self) -> int:
        return _U16.unpack(self.take(2))[0]

    def u32(self) -> int:
        return _U32.unpack(self.take(4))[0]

    def u64(self) -> int:
        return _U64.unpack(self.take(8))[0]

    def string(self) -> str:
        try:
            return str(self.take(self.u32()), 'utf-8')
        except UnicodeDecodeError as err:
            raise _Corrupt(f'string is not UTF-8: {err}') from err

    def rest(self) -> memoryview:
        return self.take(len(self.data) - self.pos)


def _parse_schema(body: bytes | memoryview) -> McapSchema:
    b = _Body(body)
    sid = b.u16()
    name = b.string()
    encoding = b.string()
    data = bytes(b.take(b.u32()))
    if sid == 0:
        raise _Corrupt('schema id 0 is reserved')
    return McapSchema(sid, name, encoding, data)


def _parse_channel(body: bytes | memoryview) -> McapChannel:
    b = _Body(body)
    cid = b.u16()
    schema_id = b.u16()
    topic = b.string()
    encoding = b.string()
    meta = _Body(b.take(b.u32()))
    pairs = []
    while meta.pos < len(meta.data):
        pairs.append((meta.string(), meta.string()))
    return McapChannel(cid, schema_id, topic, encoding, tuple(pairs))


def _parse_message(body: bytes | memoryview) -> McapMessage:
    if len(body) < _MESSAGE_HEAD.size:
        raise _Corrupt(f'message record of {len(body)} bytes is shorter than its header')
    cid, seq, log_time, publish_time = _MESSAGE_HEAD.unpack_from(body)
    return McapMessage(cid, seq, log_time, publish_time, bytes(body[_MESSAGE_HEAD.size :]))


# -- decompression -----------------------------------------------------------------------------


def _zstd_prefix(data: bytes, complete: bool) -> bytes:
    """Decompress a zstd frame, or as much of it as ``data`` holds when ``complete`` is False."""
    if sys.version_info >= (3, 14):  # pragma: no cover - standard library from 3.14
        from compression import zstd
    else:
        try:
            from backports import zstd
        except ImportError:  # pragma: no cover - older rosbags depend on zstandard instead
            zstd = None
    if zstd is not None:
        dec = zstd.ZstdDecompressor()
        out = dec.decompress(data)
        if complete and not dec.eof:
            raise _Corrupt('zstd frame ends early')
        return out
    import zstandard  # pragma: no cover

    dobj = zstandard.ZstdDecompressor().decompressobj()  # pragma: no cover
    return dobj.decompress(data)  # pragma: no cover


def _lz4_prefix(data: bytes, complete: bool) -> bytes:
    from lz4.frame import LZ4FrameDecompressor

    dec = LZ4FrameDecompressor()
    out = dec.decompress(data)
    if complete and not dec.eof:
        raise _Corrupt('lz4 frame ends early')
    return out


def _decompress(compression: str, data: bytes, complete: bool) -> bytes:
    """The uncompressed chunk records, or (``complete`` False) a prefix of them."""
    if compression == '':
        return data
    try:
        if compression == 'zstd':
            return _zstd_prefix(data, complete)
        if compression == 'lz4':
            return _lz4_prefix(data, complete)
    except _Corrupt:
        raise
    except Exception as err:  # any codec failure means corrupt data
        raise _Corrupt(f'{compression} data do not decompress: {err}') from err
    raise _Corrupt(f'unsupported chunk compression {compression!r}')


# -- the scan ----------------------------------------------------------------------------------


class McapScan:
    """Read one MCAP file sequentially, tolerating a cut or corruption anywhere.

    Iterating yields :class:`McapSchema`, :class:`McapChannel` and :class:`McapMessage` records in
    file order (chunk contents in place of their chunks). When the iteration ends:

    * ``end`` is the offset just past the last record read in full (``file_size`` for a good file),
    * ``complete`` says whether the footer and the closing magic were found,
    * ``reason`` says why reading stopped, with the offset, in words,
    * ``partial_chunk_messages`` counts messages taken from a chunk whose end is missing.

    ``source`` is a path or a seekable binary file object. Raises :class:`RecoverError` only when
    the file is not MCAP at all (or is empty).
    """

    def __init__(self, source: Path | str | BinaryIO) -> None:
        if isinstance(source, (str, Path)):
            self.path: Path | str = Path(source)
            self._stream: BinaryIO | None = None
        else:
            self.path = getattr(source, 'name', '<stream>')
            self._stream = source
        self.file_size = 0
        self.end = 0
        self.complete = False
        self.reason = ''
        self.partial_chunk_messages = 0
        self.schemas: dict[int, McapSchema] = {}
        self.channels: dict[int, McapChannel] = {}
        self.profile = ''

    def __iter__(self) -> Iterator[McapSchema | McapChannel | McapMessage]:
        if self._stream is not None:
            self.file_size = self._stream.seek(0, 2)
            self._stream.seek(0)
            yield from self._scan(self._stream)
            return
        try:
            fh = self.path.open('rb')
        except OSError as err:
            msg = f'cannot read {self.path}: {err.strerror}'
            raise RecoverError(msg) from err
        with fh:
            self.file_size = fh.seek(0, 2)
            fh.seek(0)
            yield from self._scan(fh)

    def _stop(self, offset: int, reason: str) -> None:
        self.reason = f'{reason} (offset {offset} of {self.file_size} bytes)'

    def _scan(self, fh: BinaryIO) -> Iterator[McapSchema | McapChannel | McapMessage]:
        magic = fh.read(len(MAGIC))
        if not magic:
            msg = (
                f'{self.path} is empty: the recorder stopped before writing anything, '
                'there is nothing to recover'
            )
            raise RecoverError(msg)
        if magic != MAGIC[: len(magic)]:
            msg = f'{self.path} is not an MCAP file (it does not start with the MCAP magic bytes)'
            raise RecoverError(msg)
        if len(magic) < len(MAGIC):
            self.end = 0
            self._stop(len(magic), 'file cut inside the MCAP magic')
            return
        pos = self.end = len(MAGIC)
        first = True
        while True:
            head = fh.read(_RECORD_HEAD.size)
            if not head:
                self._stop(pos, 'file ends after a complete record, without footer')
                return
            if len(head) < _RECORD_HEAD.size:
                self._stop(pos, 'file cut inside a record header')
                return
            op, length = _RECORD_HEAD.unpack(head)
            name = _OPCODE_NAMES.get(op, f'opcode 0x{op:02x}')
            if op not in _KNOWN_OPCODES and op < 0x80:
                what = 'zero bytes' if op == 0 else f'invalid opcode 0x{op:02x}'
                self._stop(pos, f'corrupt data: {what} where a record should start')
                return
            if first and op != OP_HEADER:
                self._stop(pos, f'corrupt data: first record is {name}, not Header')
                return
            body_start = pos + _RECORD_HEAD.size
            available = self.file_size - body_start
            if length > available:
                if op == OP_CHUNK:
                    yield from self._partial_chunk(fh, pos, length, available)
                else:
                    self._stop(pos, f'file cut inside a {name} record ({length} bytes)')
                return
            body = fh.read(length)
            if len(body) != length:  # the file shrank while we read it
                self._stop(pos, f'file cut inside a {name} record ({length} bytes)')
                return
            try:
                records = self._record(op, body)
            except _Corrupt as err:
                self._stop(pos, f'corrupt {name} record: {err}')
                return
            yield from records
            first = False
            pos = self.end = body_start + length
            if op == OP_FOOTER:
                tail = fh.read(len(MAGIC))
                if tail == MAGIC:
                    self.end = pos + len(MAGIC)
                    self.complete = True
                    self.reason = 'complete file (footer found)'
                else:
                    self._stop(pos, 'footer without the closing magic bytes')
                return

    def _record(self, op: int, body: bytes) -> list[McapSchema | McapChannel | McapMessage]:
        if op == OP_HEADER:
            b = _Body(body)
            self.profile = b.string()
            b.string()  # library
            return []
        if op == OP_CHUNK:
            return self._chunk(body, complete=True)
        if op in (OP_SCHEMA, OP_CHANNEL, OP_MESSAGE):
            return [self._inner(op, body)]
        return []

    def _inner(self, op: int, body: bytes | memoryview) -> McapSchema | McapChannel | McapMessage:
        if op == OP_SCHEMA:
            schema = _parse_schema(body)
            self.schemas[schema.id] = schema
            return schema
        if op == OP_CHANNEL:
            channel = _parse_channel(body)
            self.channels[channel.id] = channel
            return channel
        return _parse_message(body)

    def _chunk(self, body: bytes, complete: bool) -> list[McapSchema | McapChannel | McapMessage]:
        """The records of a chunk; of the complete ones in its prefix if ``complete`` is False."""
        b = _Body(body)
        _start, _end, size, crc = _CHUNK_HEAD.unpack(b.take(_CHUNK_HEAD.size))
        compression = b.string()
        records_len = b.u64()
        if complete:
            compressed = bytes(b.take(records_len))
        else:
            compressed = bytes(b.take(min(records_len, len(b.data) - b.pos)))
        data = _decompress(compression, compressed, complete)
        if complete:
            if len(data) != size:
                msg = f'chunk holds {len(data)} bytes once uncompressed, its header says {size}'
                raise _Corrupt(msg)
            if crc and zlib.crc32(data) != crc:
                raise _Corrupt('chunk CRC does not match its data')
        data = data[:size]
        out: list[McapSchema | McapChannel | McapMessage] = []
        inner = memoryview(data)
        pos = 0
        while pos < len(inner):
            if pos + _RECORD_HEAD.size > len(inner):
                if complete:
                    raise _Corrupt('chunk ends inside a record header')
                break
            op, length = _RECORD_HEAD.unpack_from(inner, pos)
            if op not in _KNOWN_OPCODES and op < 0x80:
                raise _Corrupt(f'invalid opcode 0x{op:02x} inside the chunk')
            if pos + _RECORD_HEAD.size + length > len(inner):
                if complete:
                    raise _Corrupt('chunk ends inside a record')
                break
            body_view = inner[pos + _RECORD_HEAD.size : pos + _RECORD_HEAD.size + length]
            if op in (OP_SCHEMA, OP_CHANNEL, OP_MESSAGE):
                out.append(self._inner(op, body_view))
            pos += _RECORD_HEAD.size + length
        return out

    def _partial_chunk(
        self, fh: BinaryIO, pos: int, length: int, available: int
    ) -> Iterator[McapSchema | McapChannel | McapMessage]:
        reason = f'file cut inside a Chunk record ({length} bytes, {available} on disk)'
        body = fh.read(available)
        try:
            records = self._chunk(body, complete=False)
        except _Corrupt as err:
            self._stop(pos, f'{reason}; its start is corrupt too: {err}')
            return
        except (struct.error, IndexError) as err:  # pragma: no cover - defensive
            self._stop(pos, f'{reason}; its start is unreadable: {err}')
            return
        n = sum(isinstance(r, McapMessage) for r in records)
        self.partial_chunk_messages = n
        yield from records
        if n:
            reason += f'; {n} complete messages taken from the part on disk'
        self._stop(pos, reason)


# -- recovery ----------------------------------------------------------------------------------


@dataclass(frozen=True)
class FileRecovery:
    """What was read from one ``.mcap`` file."""

    path: Path
    size: int
    end: int
    complete: bool
    reason: str
    messages: int
    partial_chunk_messages: int


@dataclass(frozen=True)
class RecoveryReport:
    """Result of :func:`recover_bag`: where the bag went and what it holds."""

    output: Path
    files: tuple[FileRecovery, ...]
    counts: dict[str, int]
    types: dict[str, str]
    skipped: dict[str, str] = field(default_factory=dict)
    orphan_messages: int = 0

    @property
    def message_count(self) -> int:
        return sum(self.counts.values())

    def lines(self) -> list[str]:
        """A human-readable summary."""
        out = []
        for f in self.files:
            if f.complete:
                out.append(f'{f.path}: complete file; {f.messages} messages read')
            else:
                out.append(
                    f'{f.path}: incomplete, {f.end} of {f.size} bytes usable: {f.reason}; '
                    f'{f.messages} messages read'
                )
        width = max((len(t) for t in self.counts), default=0)
        tw = max((len(t) for t in self.types.values()), default=0)
        for topic in sorted(self.counts):
            n = self.counts[topic]
            out.append(f'  {topic:<{width}}  {self.types[topic]:<{tw}}  {n} messages')
        for topic, why in sorted(self.skipped.items()):
            out.append(f'  skipped {topic}: {why}')
        if self.orphan_messages:
            out.append(f'  skipped {self.orphan_messages} messages of undeclared channels')
        out.append(f'recovered {self.message_count} messages into {self.output}')
        return out


def _natural_key(path: Path) -> list:
    return [int(t) if t.isdigit() else t for t in re.split(r'(\d+)', path.name)]


def mcap_files(bag: Path | str) -> list[Path]:
    """The ``.mcap`` files of a bag directory in recording order (or ``[bag]`` for a file)."""
    bag = Path(bag)
    if not bag.exists():
        msg = f'{bag} does not exist'
        raise RecoverError(msg)
    if bag.is_file():
        if bag.suffix != '.mcap':
            msg = (
                f'{bag} is neither a bag directory nor an .mcap file; give the directory '
                'that holds the .mcap'
            )
            raise RecoverError(msg)
        return [bag]
    files = sorted((p for p in bag.glob('*.mcap') if p.is_file()), key=_natural_key)
    if not files:
        others = sorted(p.name for p in bag.iterdir())
        hint = ''
        if any(n.endswith('.db3') for n in others):
            hint = ' (it holds SQLite3 .db3 storage, which this tool does not recover)'
        elif any(n.endswith('.mcap.zstd') for n in others):
            hint = ' (whole-file compressed .mcap.zstd: decompress it with `zstd -d` first)'
        msg = f'no .mcap file in {bag}{hint}'
        raise RecoverError(msg)
    return files


def default_output(bag: Path | str) -> Path:
    """``<BAG>_recovered`` beside the bag (for a file ``x.mcap``: ``x_recovered``)."""
    bag = Path(bag)
    base = bag.with_suffix('') if bag.is_file() else bag
    return base.parent / f'{base.name}_recovered'


class _TypeInfo:
    """Message definition and RIHS01 hash of each schema, computed from the schema itself."""

    def __init__(self) -> None:
        self._cache: dict[tuple[str, str, bytes], tuple[str, str] | str] = {}

    def get(self, schema: McapSchema) -> tuple[str, str] | str:
        """``(msgdef, rihs01)``, or the reason why this schema cannot be used."""
        key = (schema.name, schema.encoding, schema.data)
        if key not in self._cache:
            self._cache[key] = self._compute(schema)
        return self._cache[key]

    @staticmethod
    def _compute(schema: McapSchema) -> tuple[str, str] | str:
        try:
            text = schema.data.decode()
        except UnicodeDecodeError:
            return f'schema of {schema.name} is not text'
        try:
            if schema.encoding == 'ros2msg':
                typs = get_types_from_msg(text, schema.name)
            elif schema.encoding == 'ros2idl':
                typs = {}
                sep = '=' * 80 + '\n'
                parts = text.split(sep)[1:] if text.startswith(f'{sep}IDL: ') else [text]
                for part in parts:
                    idl = part.split('\n', 1)[1] if part.startswith('IDL: ') else part
                    typs.update(get_types_from_idl(idl))
            else:
                return f'schema encoding {schema.encoding!r} is not a ROS 2 message definition'
            store = get_typestore(Stores.EMPTY)
            store.register(typs)
            return text, store.hash_rihs01(schema.name)
        except Exception as err:  # any parser failure: unusable schema
            return f'schema of {schema.name} cannot be parsed: {err}'


def _qos_of(channel: McapChannel) -> list:
    text = dict(channel.metadata).get('offered_qos_profiles', '')
    try:
        return parse_qos(text) if text else []
    except (ReaderError, KeyError, TypeError, AttributeError):
        return []


def recover_bag(
    bag: Path | str, output: Path | str | None = None, compression: str = 'zstd'
) -> RecoveryReport:
    """Write every message fully on disk in ``bag`` into a new, complete bag ``output``.

    ``bag`` is a rosbag2 directory with MCAP storage (or one ``.mcap`` file); ``output`` defaults
    to ``<BAG>_recovered`` and must not exist. Schemas, topics, types and offered QoS profiles are
    kept as recorded; each message keeps its log time (its publish time becomes the log time, as
    rosbags writes it). Raises :class:`RecoverError` with what to do when there is nothing to
    recover from.
    """
    bag = Path(bag)
    files = mcap_files(bag)
    output = Path(output) if output is not None else default_output(bag)
    if output.exists():
        msg = f'{output} exists already, not overwriting; choose another output with -o'
        raise RecoverError(msg)
    if compression not in ('zstd', 'none'):
        msg = f'compression must be zstd or none, got {compression!r}'
        raise RecoverError(msg)

    writer = Writer(output, version=9, storage_plugin=StoragePlugin.MCAP)
    if compression == 'zstd':
        writer.set_compression(CompressionMode.STORAGE, CompressionFormat.ZSTD)
    try:
        writer.open()
    except (RosbagsWriterError, OSError) as err:
        msg = f'cannot create {output}: {err}'
        raise RecoverError(msg) from err

    types = _TypeInfo()
    connections: dict[tuple, object] = {}
    counts: dict[str, int] = {}
    msgtypes: dict[str, str] = {}
    skipped: dict[str, str] = {}
    orphans = 0
    results = []
    try:
        for path in files:
            scan = McapScan(path)
            # channel id -> output connection (None: skipped) for this file
            routes: dict[int, object] = {}
            n_file = 0
            for rec in scan:
                if isinstance(rec, McapChannel):
                    routes[rec.id] = _route(rec, scan, writer, types, connections, skipped)
                    if routes[rec.id] is not None:
                        counts.setdefault(rec.topic, 0)
                        msgtypes[rec.topic] = scan.schemas[rec.schema_id].name
                    continue
                if not isinstance(rec, McapMessage):
                    continue
                conn = routes.get(rec.channel_id)
                if rec.channel_id not in routes:
                    orphans += 1
                    continue
                n_file += 1
                if conn is None:
                    continue
                writer.write(conn, rec.log_time, rec.data)
                counts[conn.topic] += 1
            results.append(
                FileRecovery(
                    path,
                    scan.file_size,
                    scan.end,
                    scan.complete,
                    scan.reason,
                    n_file,
                    scan.partial_chunk_messages,
                )
            )
        writer.close()
    except BaseException:
        try:
            writer.abort()
        finally:
            shutil.rmtree(output, ignore_errors=True)
        raise
    return RecoveryReport(output, tuple(results), counts, msgtypes, skipped, orphans)


def _route(channel, scan, writer, types, connections, skipped):
    """The output connection of an input channel, added on first sight; None if unusable."""
    schema = scan.schemas.get(channel.schema_id)
    topic = channel.topic
    if schema is None:
        skipped[topic] = f'channel {channel.id} refers to unknown schema {channel.schema_id}'
        return None
    if channel.message_encoding != 'cdr':
        skipped[topic] = f'message encoding {channel.message_encoding!r} is not ROS 2 CDR'
        return None
    info = types.get(schema)
    if isinstance(info, str):
        skipped[topic] = info
        return None
    msgdef, rihs01 = info
    qos = _qos_of(channel)
    key = (topic, schema.name, msgdef, tuple(qos))
    if key not in connections:
        connections[key] = writer.add_connection(
            topic, schema.name, msgdef=msgdef, rihs01=rihs01, offered_qos_profiles=qos
        )
    skipped.pop(topic, None)
    return connections[key]


# -- info --------------------------------------------------------------------------------------


@dataclass(frozen=True)
class TopicSummary:
    topic: str
    msgtype: str
    count: int


@dataclass(frozen=True)
class BagInfo:
    """What ``cloe bag info`` shows. Times are int ns (log time)."""

    path: Path
    files: tuple[str, ...]
    storage: str
    topics: tuple[TopicSummary, ...]
    message_count: int
    start_ns: int
    end_ns: int

    @property
    def duration_ns(self) -> int:
        return max(0, self.end_ns - self.start_ns) if self.message_count else 0

    def lines(self) -> list[str]:
        def stamp(ns: int) -> str:
            t = datetime.fromtimestamp(ns / 1e9, tz=timezone.utc)
            return f'{t.isoformat(timespec="milliseconds")} ({ns / 1e9:.3f} s)'

        out = [
            f'bag:       {self.path}',
            f'files:     {", ".join(self.files)} ({self.storage})',
            f'messages:  {self.message_count}',
        ]
        if self.message_count:
            out += [
                f'duration:  {self.duration_ns / 1e9:.3f} s',
                f'start:     {stamp(self.start_ns)}',
                f'end:       {stamp(self.end_ns)}',
            ]
        out.append('topics:')
        width = max((len(t.topic) for t in self.topics), default=0)
        tw = max((len(t.msgtype) for t in self.topics), default=0)
        out += [f'  {t.topic:<{width}}  {t.msgtype:<{tw}}  {t.count}' for t in self.topics]
        return out


def bag_info(bag: Path | str) -> BagInfo:
    """Topics, types, counts and time span of a complete rosbag2 bag (from its metadata)."""
    bag = Path(bag)
    if not bag.is_dir():
        msg = f'{bag} is not a bag directory'
        raise RecoverError(msg)
    if not (bag / 'metadata.yaml').exists():
        hint = (
            f'; its recorder probably died: run `cloe bag recover {bag}`'
            if any(bag.glob('*.mcap'))
            else ''
        )
        msg = f'{bag} has no metadata.yaml{hint}'
        raise RecoverError(msg)
    try:
        with Reader(bag) as reader:
            topics = tuple(
                TopicSummary(name, info.msgtype or '?', info.msgcount)
                for name, info in sorted(reader.topics.items())
            )
            count = reader.message_count
            start = reader.start_time if count else 0
            # rosbags reports the end as the last log time + 1 ns
            end = reader.end_time - 1 if count else 0
        meta = yaml.safe_load((bag / 'metadata.yaml').read_text())['rosbag2_bagfile_information']
        files = tuple(Path(p).name for p in meta['relative_file_paths'])
        storage = str(meta['storage_identifier'])
    except (ReaderError, FileNotFoundError, KeyError, TypeError, yaml.YAMLError) as err:
        msg = f'cannot read bag {bag}: {err} (if its recorder died, try `cloe bag recover {bag}`)'
        raise RecoverError(msg) from err
    return BagInfo(bag, files, storage, topics, count, start, end)
