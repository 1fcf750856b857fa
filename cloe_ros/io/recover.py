"""Recover bags whose recorder died or whose files are damaged, and summarize bags.

A recorder killed with SIGKILL (or a machine that lost power) leaves a rosbag2 directory whose
``.mcap`` has no summary section and no footer, and no ``metadata.yaml`` (or a stale one): readers
that seek to the footer refuse it. :func:`recover_bag` reads such a file from the start, record by
record (:class:`McapScan`), and writes a complete bag with every message that was fully on disk
and intact. A damaged record is stepped over and reported when readable records follow it (its
length leads to them, or the summary of a file that still has one says where the next chunk
starts); reading stops where nothing readable follows: a cut, or zeros or garbage up to the end.

The parser is a small one of our own, bounded by the file size at every step, so a cut at any byte
(or garbage after the last good record) ends the scan instead of raising or allocating.

MCAP records (https://mcap.dev/spec): ``opcode u8, length u64, body``; integers little-endian,
strings ``u32 length + UTF-8``. A chunk holds schema, channel and message records, compressed with
zstd or lz4 or not at all, and is followed by message index records (channel, log time and offset
of each of its messages). Messages of a chunk whose end is missing (cut off, or zero-filled) are
recovered when their bytes are complete inside the part that is on disk (a compressed chunk is
decompressed as far as its data go). rosbags writes no chunk CRC, so a chunk whose messages differ
from its message index counts as damaged.
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

from cloe_ros.io.errors import RecoverError
from cloe_ros.io.reader import BagError, check_bag

MAGIC = b'\x89MCAP0\r\n'

OP_HEADER = 0x01
OP_FOOTER = 0x02
OP_SCHEMA = 0x03
OP_CHANNEL = 0x04
OP_MESSAGE = 0x05
OP_CHUNK = 0x06
OP_MESSAGE_INDEX = 0x07
OP_CHUNK_INDEX = 0x08
OP_STATISTICS = 0x0B
OP_DATA_END = 0x0F
#: The opcodes the MCAP specification defines are 0x01-0x0F; 0x80-0xFF are user extensions.
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
}

_U16 = struct.Struct('<H')
_U32 = struct.Struct('<I')
_U64 = struct.Struct('<Q')
_RECORD_HEAD = struct.Struct('<BQ')
_MESSAGE_HEAD = struct.Struct('<HIQQ')  # channel id, sequence, log time, publish time
_CHUNK_HEAD = struct.Struct('<QQQI')  # start, end, uncompressed size, uncompressed crc


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


def _parse_inner(op: int, body: bytes | memoryview) -> McapSchema | McapChannel | McapMessage:
    """A schema, channel or message record (``op``) from its body."""
    if op == OP_SCHEMA:
        return _parse_schema(body)
    if op == OP_CHANNEL:
        return _parse_channel(body)
    return _parse_message(body)


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


def _readable_prefix(compression: str, data: bytes) -> bytes:
    """What the start of a chunk's data gives before the decoder meets bytes it rejects (zeros or
    garbage where the rest of the data should be): the output of the longest prefix of ``data``
    that decompresses without an error, found by bisection (a decoder that raises loses what it
    decoded in that call)."""
    try:
        return _decompress(compression, data, complete=False)
    except _Corrupt:
        pass
    good, bad = 0, len(data)  # data[:good] decompresses, data[:bad] does not
    while bad - good > 1:
        mid = (good + bad) // 2
        try:
            _decompress(compression, data[:mid], complete=False)
        except _Corrupt:
            bad = mid
        else:
            good = mid
    return _decompress(compression, data[:good], complete=False) if good else b''


# -- the scan ----------------------------------------------------------------------------------


def _known(op: int) -> bool:
    """An opcode the specification defines (0x01-0x0F), or a user extension (0x80-0xFF)."""
    return OP_HEADER <= op <= OP_DATA_END or op >= 0x80


@dataclass(frozen=True)
class _ChunkHead:
    start: int  # log time of the first and last message
    end: int
    size: int  # uncompressed size
    crc: int  # CRC-32 of the uncompressed records, 0 when not computed
    compression: str
    data: bytes  # the compressed records (their part on disk for a cut chunk)


def _check_index(
    records: list[tuple[int, object]], index: dict[int, set[tuple[int, int]]]
) -> None:
    """:class:`_Corrupt` unless a chunk's messages (``(offset, record)``) are those the message
    index records after it list, channel by channel."""
    got: dict[int, set[tuple[int, int]]] = {}
    for offset, rec in records:
        if isinstance(rec, McapMessage):
            got.setdefault(rec.channel_id, set()).add((rec.log_time, offset))
    for channel, entries in sorted(index.items()):
        mine = got.get(channel, set())
        if mine != entries:
            msg = (
                f'its messages differ from the message index after it (channel {channel}: '
                f'{len(entries - mine)} of {len(entries)} indexed messages not found)'
            )
            raise _Corrupt(msg)


def _chunk_head(body: bytes | memoryview, complete: bool) -> _ChunkHead:
    b = _Body(body)
    start, end, size, crc = _CHUNK_HEAD.unpack(b.take(_CHUNK_HEAD.size))
    compression = b.string()
    records_len = b.u64()
    if complete:
        data = bytes(b.take(records_len))
    else:
        data = bytes(b.take(min(records_len, len(b.data) - b.pos)))
    return _ChunkHead(start, end, size, crc, compression, data)


@dataclass(frozen=True)
class SkippedRecord:
    """A damaged record the scan stepped over (the records after it were read)."""

    offset: int
    length: int  # bytes stepped over, from ``offset``
    what: str  # the record type, as far as it can be told
    reason: str
    lost: int | None  # messages it held that were not taken (None: unknown)
    kept: int = 0  # messages taken from it all the same (their records match the file's index)

    def line(self) -> str:
        if self.lost is None:
            held = 'how many messages it held is unknown'
        elif self.kept and not self.lost:
            held = f'all its {self.kept} messages kept (they match the message index)'
        elif self.kept:
            held = (
                f'{self.kept} of its messages kept (they match the message index), '
                f'{self.lost} lost'
            )
        else:
            held = f'{self.lost} messages lost'
        where = f'at byte {self.offset} ({self.length} bytes)'
        return f'damaged {self.what} {where}: {self.reason}; {held}'


class McapScan:
    """Read one MCAP file sequentially, tolerating a cut or corruption anywhere.

    Iterating yields :class:`McapSchema`, :class:`McapChannel` and :class:`McapMessage` records in
    file order (chunk contents in place of their chunks). A damaged record is stepped over when
    reading can go on after it: its length leads to plausible records, or (in a file that still
    has its footer) the summary's chunk index says where the next chunk starts. It is listed in
    ``skipped``. A chunk is damaged when it does not decompress or parse, when a message's log
    time lies outside the chunk's time range, or when its messages differ from the message index
    written after it (rosbags writes no chunk CRC, so the index is the check); of an uncompressed
    damaged chunk the messages that match the index are kept, a compressed one is left out whole
    (past the damage its decompressed bytes cannot be trusted). When the iteration ends:

    * ``end`` is the offset just past the last record read in full (``file_size`` for a good file),
    * ``complete`` says whether the footer and the closing magic were found,
    * ``reason`` says why reading stopped, with the offset, in words,
    * ``skipped`` lists the damaged records stepped over (:class:`SkippedRecord`),
    * ``partial_chunk_messages`` counts messages taken from a last chunk whose end is missing: cut
      off by the end of the file, or (``damaged_tail``) followed by nothing readable (zero-filled
      or garbage up to the end of the file); its complete messages are kept as for a cut file,
    * ``expected_messages`` is the message count of the file's statistics (None without summary).

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
        self.damaged_tail = False
        self.skipped: list[SkippedRecord] = []
        self.expected_messages: int | None = None
        self.schemas: dict[int, McapSchema] = {}
        self.channels: dict[int, McapChannel] = {}
        self.profile = ''
        self._summary_schemas: dict[int, McapSchema] = {}
        self._summary_channels: dict[int, McapChannel] = {}
        self._resync_points: list[int] = []
        # chunk offset -> (start, end, length, compression, compressed size, uncompressed size)
        self._chunk_infos: dict[int, tuple[int, int, int, str, int, int]] = {}

    @property
    def damaged(self) -> bool:
        """Whether damage was found (skipped records, or a damaged last chunk)."""
        return bool(self.skipped) or self.damaged_tail

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
        self._read_summary(fh)
        pos = self.end = len(MAGIC)
        first = True
        while True:
            fh.seek(pos)
            head = fh.read(_RECORD_HEAD.size)
            if not head:
                self._stop(pos, 'file ends after a complete record, without footer')
                return
            if len(head) < _RECORD_HEAD.size:
                self._stop(pos, 'file cut inside a record header')
                return
            op, length = _RECORD_HEAD.unpack(head)
            name = _OPCODE_NAMES.get(op, f'opcode 0x{op:02x}')
            body_start = pos + _RECORD_HEAD.size
            available = self.file_size - body_start
            problem = ''
            if not _known(op):
                what = 'zero bytes' if op == 0 else f'invalid opcode 0x{op:02x}'
                problem = f'corrupt data: {what} where a record should start'
            elif first and op != OP_HEADER:
                problem = f'corrupt data: first record is {name}, not Header'
            elif length > available and self._resync_points:
                problem = f'corrupt {name} record: its length ({length} bytes) overruns the file'
            if problem and (found := self._chunk_from_summary(fh, pos)):
                yield from self._read_with_summary(pos, found, problem)
                pos = self.end = found[1]
                first = False
                continue
            if problem:
                resume = self._resume(fh, pos, length)
                if resume is None:
                    self._stop(pos, problem)
                    return
                what = 'record' if not _known(op) else f'{name} record'
                self.skipped.append(SkippedRecord(pos, resume - pos, what, problem, None))
                pos = self.end = resume
                first = False
                continue
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
            after = body_start + length
            if op == OP_CHUNK:
                index = self._message_index(fh, after)
                try:
                    records = self._chunk(body, index)
                except _Corrupt as err:
                    if found := self._chunk_from_summary(fh, pos):
                        yield from self._read_with_summary(
                            pos, found, f'corrupt Chunk record: {err}'
                        )
                        pos = self.end = found[1]
                        first = False
                        continue
                    resume = self._resume(fh, pos, length)
                    if resume is None:
                        yield from self._damaged_last_chunk(pos, length, body, err)
                        return
                    yield from self._skip_chunk(pos, resume, body, index, err, resume == after)
                    pos = self.end = resume
                    first = False
                    continue
            else:
                try:
                    records = self._record(op, body)
                except _Corrupt as err:
                    problem = f'corrupt {name} record: {err}'
                    resume = self._resume(fh, pos, length)
                    if resume is None:
                        self._stop(pos, problem)
                        return
                    self.skipped.append(SkippedRecord(pos, resume - pos, name, problem, None))
                    pos = self.end = resume
                    first = False
                    continue
            yield from self._emit(records)
            first = False
            pos = self.end = after
            if op == OP_FOOTER:
                fh.seek(pos)
                tail = fh.read(len(MAGIC))
                if tail == MAGIC:
                    self.end = pos + len(MAGIC)
                    self.complete = True
                    self.reason = 'complete file (footer found)'
                else:
                    self._stop(pos, 'footer without the closing magic bytes')
                return

    # -- reading on past damage ---------------------------------------------------------------

    def _valid_at(self, fh: BinaryIO, offset: int) -> bool:
        """Whether reading can go on at ``offset``: a plausible record there (a known opcode other
        than Header, a length that fits in the file, or a chunk cut by the end of the file),
        followed by the end of the file or by another plausible record."""
        for i in range(2):
            if offset > self.file_size:
                return False
            fh.seek(offset)
            head = fh.read(_RECORD_HEAD.size)
            if len(head) < _RECORD_HEAD.size:
                return i > 0  # the file ends (or is cut) after a plausible record
            op, length = _RECORD_HEAD.unpack(head)
            if not OP_FOOTER <= op <= OP_DATA_END:
                return False
            if length > self.file_size - offset - _RECORD_HEAD.size:
                return op == OP_CHUNK
            if op == OP_FOOTER:
                return length == 20 and offset + _RECORD_HEAD.size + 20 + len(MAGIC) == (
                    self.file_size
                )
            offset += _RECORD_HEAD.size + length
        return True

    def _resume(self, fh: BinaryIO, pos: int, length: int) -> int | None:
        """Where reading goes on after the damaged record at ``pos`` (None: nowhere): after it, if
        its length leads to plausible records; else at the next chunk the summary knows of."""
        after = pos + _RECORD_HEAD.size + length
        if after <= self.file_size and self._valid_at(fh, after):
            return after
        for point in self._resync_points:
            if point > pos and self._valid_at(fh, point):
                return point
        return None

    def _read_summary(self, fh: BinaryIO) -> None:
        """From the summary section of a file that ends with its footer: schemas and channels
        (for messages whose declaration was in a damaged chunk), where the chunks start (to read
        on after a record whose length is damaged) and the message count of the statistics."""
        footer = self.file_size - len(MAGIC) - _RECORD_HEAD.size - 20
        if footer <= len(MAGIC):
            return
        fh.seek(footer)
        tail = fh.read(_RECORD_HEAD.size + 20 + len(MAGIC))
        if tail[-len(MAGIC) :] != MAGIC or tail[:9] != _RECORD_HEAD.pack(OP_FOOTER, 20):
            return
        (summary_start,) = _U64.unpack_from(tail, 9)
        if not len(MAGIC) < summary_start < footer:
            return
        fh.seek(summary_start)
        data = memoryview(fh.read(footer - summary_start))
        points = []
        pos = 0
        while pos + _RECORD_HEAD.size <= len(data):
            op, length = _RECORD_HEAD.unpack_from(data, pos)
            if length > len(data) - pos - _RECORD_HEAD.size:
                break
            body = data[pos + _RECORD_HEAD.size : pos + _RECORD_HEAD.size + length]
            try:
                if op == OP_SCHEMA:
                    schema = _parse_schema(body)
                    self._summary_schemas[schema.id] = schema
                elif op == OP_CHANNEL:
                    channel = _parse_channel(body)
                    self._summary_channels[channel.id] = channel
                elif op == OP_CHUNK_INDEX:
                    b = _Body(body)
                    start, end, offset, chunk_length = (b.u64() for _ in range(4))
                    b.take(b.u32())  # message index offsets
                    b.u64()  # message index length
                    compression = b.string()
                    self._chunk_infos[offset] = (
                        start, end, chunk_length, compression, b.u64(), b.u64()
                    )  # fmt: skip
                    points.append(offset)
                elif op == OP_STATISTICS:
                    self.expected_messages = _U64.unpack_from(body, 0)[0]
            except (_Corrupt, struct.error):
                pass
            pos += _RECORD_HEAD.size + length
        self._resync_points = sorted({p for p in points if len(MAGIC) < p < summary_start})
        self._resync_points.append(summary_start)

    def _message_index(self, fh: BinaryIO, offset: int) -> dict[int, set[tuple[int, int]]] | None:
        """The message index records after a chunk: channel -> {(log time, offset)}; None when
        there are none or one does not parse."""
        index: dict[int, set[tuple[int, int]]] = {}
        while True:
            fh.seek(offset)
            head = fh.read(_RECORD_HEAD.size)
            if len(head) < _RECORD_HEAD.size:
                break
            op, length = _RECORD_HEAD.unpack(head)
            if op != OP_MESSAGE_INDEX or length > self.file_size - offset - _RECORD_HEAD.size:
                break
            b = _Body(fh.read(length))
            try:
                channel = b.u16()
                entries = _Body(b.take(b.u32()))
                mine = index.setdefault(channel, set())
                while entries.pos < len(entries.data):
                    mine.add((entries.u64(), entries.u64()))
            except _Corrupt:
                return None
            offset += _RECORD_HEAD.size + length
        return index or None

    # -- records --------------------------------------------------------------------------------

    def _emit(self, records: list) -> Iterator[McapSchema | McapChannel | McapMessage]:
        """Yield ``records``, registering schemas and channels; a message of a channel not
        declared so far (its declaration was in a damaged chunk) gets the summary's."""
        for rec in records:
            if isinstance(rec, McapSchema):
                self.schemas[rec.id] = rec
            elif isinstance(rec, McapChannel):
                self.channels[rec.id] = rec
            elif rec.channel_id not in self.channels and rec.channel_id in self._summary_channels:
                channel = self._summary_channels[rec.channel_id]
                schema = self._summary_schemas.get(channel.schema_id)
                if schema is not None and schema.id not in self.schemas:
                    self.schemas[schema.id] = schema
                    yield schema
                self.channels[channel.id] = channel
                yield channel
            yield rec

    def _record(self, op: int, body: bytes) -> list[McapSchema | McapChannel | McapMessage]:
        if op == OP_HEADER:
            b = _Body(body)
            self.profile = b.string()
            b.string()  # library
            return []
        if op in (OP_SCHEMA, OP_CHANNEL, OP_MESSAGE):
            return [_parse_inner(op, body)]
        return []

    @staticmethod
    def _inner_records(data: bytes, head: _ChunkHead) -> tuple[list, str, int]:
        """The records of a chunk's uncompressed ``data`` with their offsets, up to the first
        one that is cut or does not parse or (a message) lies outside the chunk's time range;
        what stopped the parse ('' when all of ``data`` parsed); and where it stopped."""
        out: list[tuple[int, object]] = []
        inner = memoryview(data)
        pos = 0
        while pos < len(inner):
            if pos + _RECORD_HEAD.size > len(inner):
                return out, 'chunk ends inside a record header', pos
            op, length = _RECORD_HEAD.unpack_from(inner, pos)
            if not _known(op):
                return out, f'invalid opcode 0x{op:02x} inside the chunk', pos
            if length > len(inner) - pos - _RECORD_HEAD.size:
                return out, 'chunk ends inside a record', pos
            if op in (OP_SCHEMA, OP_CHANNEL, OP_MESSAGE):
                body = inner[pos + _RECORD_HEAD.size : pos + _RECORD_HEAD.size + length]
                try:
                    rec = _parse_inner(op, body)
                except _Corrupt as err:
                    why = f'corrupt {_OPCODE_NAMES[op]} record inside the chunk: {err}'
                    return out, why, pos
                if isinstance(rec, McapMessage) and not head.start <= rec.log_time <= head.end:
                    why = (
                        f"a message logged at {rec.log_time} ns lies outside the chunk's time "
                        f'range {head.start}-{head.end} ns'
                    )
                    return out, why, pos
                out.append((pos, rec))
            pos += _RECORD_HEAD.size + length
        return out, '', pos

    def _chunk(self, body: bytes, index: dict[int, set[tuple[int, int]]] | None) -> list:
        """The records of a chunk that is whole on disk; :class:`_Corrupt` if it is damaged."""
        head = _chunk_head(body, complete=True)
        data = _decompress(head.compression, head.data, complete=True)
        if len(data) != head.size:
            msg = f'chunk holds {len(data)} bytes once uncompressed, its header says {head.size}'
            raise _Corrupt(msg)
        records, problem, _ = self._inner_records(data, head)
        if head.crc and zlib.crc32(data) != head.crc:
            if not problem and index is not None:  # where the damage is, if the index tells
                try:
                    _check_index(records, index)
                except _Corrupt as err:
                    problem = str(err)
            raise _Corrupt('chunk CRC does not match its data' + (f'; {problem}' if problem else ''))
        if problem:
            raise _Corrupt(problem)
        if index is not None and not head.crc:  # a matching CRC vouches for the data
            _check_index(records, index)
        return [rec for _, rec in records]

    def _chunk_from_summary(self, fh: BinaryIO, pos: int) -> tuple[list, int] | None:
        """The records of the chunk at ``pos`` read with what the summary's chunk index says of
        it (length, compression, sizes, time range) instead of its own, damaged header, and the
        offset after it; None unless its messages are exactly those of the message index after
        it."""
        info = self._chunk_infos.get(pos)
        if info is None:
            return None
        start, end, length, compression, compressed_size, size = info
        after = pos + length
        if not pos + _RECORD_HEAD.size < after <= self.file_size:
            return None
        index = self._message_index(fh, after)
        if index is None:
            return None
        skip = _CHUNK_HEAD.size + 4 + len(compression.encode()) + 8
        fh.seek(pos + _RECORD_HEAD.size + skip)
        compressed = fh.read(compressed_size)
        head = _ChunkHead(start, end, size, 0, compression, compressed)
        try:
            data = _decompress(compression, compressed, complete=True)
            records, problem, _ = self._inner_records(data, head)
            if problem or len(data) != size:
                return None
            _check_index(records, index)
        except _Corrupt:
            return None
        return [rec for _, rec in records], after

    def _salvage(self, pos: int, body: bytes | memoryview, cut: bool = False):
        """``(head, records, data, stop)``: the chunk's records up to the first one that cannot be
        read, its data decompressed as far as the decoder accepts them (and, for a ``cut``
        chunk, as far as its header's uncompressed size: past it lie no records), and where the
        parse stopped. A damaged header is replaced by the summary's chunk index if known."""
        try:
            head = _chunk_head(body, complete=False)
        except _Corrupt:
            info = self._chunk_infos.get(pos)
            if info is None:
                raise
            start, end, _, compression, compressed_size, size = info
            skip = _CHUNK_HEAD.size + 4 + len(compression.encode()) + 8
            head = _ChunkHead(
                start, end, size, 0, compression, bytes(body[skip:][:compressed_size])
            )
        data = _readable_prefix(head.compression, head.data)
        if cut:
            data = data[: head.size]
        records, _, stop = self._inner_records(data, head)
        return head, records, data, stop

    def _read_with_summary(self, pos: int, found: tuple[list, int], problem: str) -> Iterator:
        records, after = found
        n = sum(isinstance(r, McapMessage) for r in records)
        reason = f'{problem}; read with the chunk index of the summary instead'
        self.skipped.append(SkippedRecord(pos, after - pos, 'Chunk', reason, 0, n))
        yield from self._emit(records)

    def _skip_chunk(self, pos, resume, body, index, err, length_ok) -> Iterator:
        """Step over a damaged chunk that has readable records after it. Of an uncompressed one
        (its records are the bytes on disk) keep the declarations before the damage and every
        message found where the index after the chunk puts it, with the channel and log time the
        index gives."""
        kept: list = []
        if length_ok and index is not None:
            try:
                head, records, _, _ = self._salvage(pos, body)
            except _Corrupt:
                pass
            else:
                if head.compression == '':
                    kept = [(o, r) for o, r in records if not isinstance(r, McapMessage)]
                    kept += self._indexed_messages(head, index)
                    kept.sort(key=lambda item: item[0])
        n_kept = sum(isinstance(r, McapMessage) for _, r in kept)
        lost = sum(map(len, index.values())) - n_kept if index is not None else None
        reason = f'corrupt Chunk record: {err}'
        self.skipped.append(SkippedRecord(pos, resume - pos, 'Chunk', reason, lost, n_kept))
        yield from self._emit([r for _, r in kept])

    @staticmethod
    def _indexed_messages(head: _ChunkHead, index) -> list[tuple[int, McapMessage]]:
        """The intact message records of uncompressed chunk data at the offsets of ``index``: a
        message record with the channel and log time the index gives, ending where the next
        indexed message starts, or before a plausible record, or at the end of the data."""
        data = memoryview(head.data)
        starts = sorted({offset for entries in index.values() for _, offset in entries})
        following = dict(zip(starts, [*starts[1:], None]))
        out = []
        for channel, entries in index.items():
            for log_time, offset in entries:
                if offset + _RECORD_HEAD.size > len(data):
                    continue
                op, length = _RECORD_HEAD.unpack_from(data, offset)
                start = offset + _RECORD_HEAD.size
                end = start + length
                nxt = following[offset]
                if op != OP_MESSAGE or end > len(data) or (nxt is not None and end > nxt):
                    continue
                if end not in (nxt, len(data)):
                    if end + _RECORD_HEAD.size > len(data):
                        continue
                    op_after, length_after = _RECORD_HEAD.unpack_from(data, end)
                    if op_after not in (OP_SCHEMA, OP_CHANNEL, OP_MESSAGE) or (
                        length_after > len(data) - end - _RECORD_HEAD.size
                    ):
                        continue
                try:
                    msg = _parse_message(data[start:end])
                except _Corrupt:
                    continue
                if (msg.channel_id, msg.log_time) == (channel, log_time) and (
                    head.start <= log_time <= head.end
                ):
                    out.append((offset, msg))
        return out

    def _damaged_last_chunk(self, pos, length, body, err) -> Iterator:
        """A chunk whole on disk that is damaged and followed by nothing readable (zero-filled or
        garbage up to the end of the file): its end was never written, so its complete records
        are taken as for a chunk cut by the end of the file."""
        reason = (
            f'damaged Chunk record ({length} bytes) followed by nothing readable up to the end '
            f'of the file: {err}'
        )
        try:
            head, records, data, stop = self._salvage(pos, body)
        except _Corrupt:
            records = []
        else:
            if head.compression == '' and data[stop : stop + 1] == b'\0':
                # zeros where the next record should be: the file's end was never written, and
                # the zeros may begin inside the last record read: keep none that reaches them
                zeros = len(data[:stop]) - len(data[:stop].rstrip(b'\0'))
                ends = [offset for offset, _ in records[1:]] + [stop]
                records = [r for r, e in zip(records, ends) if e <= stop - zeros]
        n = sum(isinstance(r, McapMessage) for _, r in records)
        self.partial_chunk_messages = n
        self.damaged_tail = True
        yield from self._emit([r for _, r in records])
        if n:
            reason += f'; {n} complete messages taken from its readable part'
        self._stop(pos, reason)

    def _partial_chunk(
        self, fh: BinaryIO, pos: int, length: int, available: int
    ) -> Iterator[McapSchema | McapChannel | McapMessage]:
        reason = f'file cut inside a Chunk record ({length} bytes, {available} on disk)'
        fh.seek(pos + _RECORD_HEAD.size)
        body = fh.read(available)
        try:
            _, records, _, _ = self._salvage(pos, body, cut=True)
        except _Corrupt as err:
            self._stop(pos, f'{reason}; its start is corrupt too: {err}')
            return
        records = [r for _, r in records]
        n = sum(isinstance(r, McapMessage) for r in records)
        self.partial_chunk_messages = n
        yield from self._emit(records)
        if n:
            reason += f'; {n} complete messages taken from the part on disk'
        self._stop(pos, reason)


# -- recovery ----------------------------------------------------------------------------------


def _without_offset(reason: str) -> str:
    """A scan's reason without its closing ``(offset N of M bytes)``."""
    return re.sub(r' \(offset \d+ of \d+ bytes\)$', '', reason)


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
    skipped: tuple[SkippedRecord, ...] = ()
    damaged_tail: bool = False
    expected_messages: int | None = None

    @property
    def damaged(self) -> bool:
        return bool(self.skipped) or self.damaged_tail

    def lines(self) -> list[str]:
        """How the file was read: one line, then one per damaged record stepped over."""
        reason = _without_offset(self.reason)
        n = f'{self.messages} messages read'
        if self.complete and self.skipped:
            if self.expected_messages is not None:
                n += f' of the {self.expected_messages} its statistics count'
            first = f'{self.path}: damaged (its footer is there); {n}'
        elif self.complete:
            first = f'{self.path}: complete file; {n}'
        elif self.damaged_tail:
            first = (
                f'{self.path}: incomplete ({self.size} bytes), complete records up to byte '
                f'{self.end}, then {reason}; {n}'
            )
        elif self.partial_chunk_messages:
            # the messages taken from the cut chunk lie past ``end`` (where the last complete
            # record ends), so ``end`` is not the number of usable bytes
            first = (
                f'{self.path}: incomplete ({self.size} bytes), complete records up to byte '
                f'{self.end}, then a chunk cut off by the end of the file: {reason}; {n}'
            )
        else:
            first = (
                f'{self.path}: incomplete, {self.end} of {self.size} bytes usable: '
                f'{self.reason}; {n}'
            )
        return [first] + [f'  {s.line()}' for s in self.skipped]


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

    @property
    def damaged(self) -> bool:
        """Whether a file had damaged records (skipped, or a damaged last chunk)."""
        return any(f.damaged for f in self.files)

    def lines(self) -> list[str]:
        """A human-readable summary."""
        out = [line for f in self.files for line in f.lines()]
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
                    tuple(scan.skipped),
                    scan.damaged_tail,
                    scan.expected_messages,
                )
            )
        if not counts:
            raise RecoverError(_nothing_to_recover(bag, results, skipped))
        writer.close()
    except BaseException:
        try:
            writer.abort()
        finally:
            shutil.rmtree(output, ignore_errors=True)
        raise
    return RecoveryReport(output, tuple(results), counts, msgtypes, skipped, orphans)


def _nothing_to_recover(bag: Path, results: list[FileRecovery], skipped: dict[str, str]) -> str:
    """Why a bag without one usable topic gives no output."""
    why = '; '.join(f'{f.path} ({f.size} bytes): {_without_offset(f.reason)}' for f in results)
    topics = ''.join(f'; topic {t} unusable: {w}' for t, w in sorted(skipped.items()))
    return (
        f'nothing to recover from {bag}: no topic and no message is complete on disk ({why}'
        f'{topics}); no output written'
    )


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
    #: what is wrong with the data (:func:`mcap_damage`); empty for a good bag
    damage: tuple[str, ...] = ()

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
        for i, problem in enumerate(self.damage):
            out.append(f'{"damaged:" if i == 0 else "":<11}{problem}')
        return out


def mcap_damage(files: list[Path], counts: dict[str, int]) -> list[str]:
    """What is wrong with the data of complete ``.mcap`` files, read record by record as
    :func:`recover_bag` reads them (``[]`` for good files): damaged records, a file that ends
    early, and topics with fewer messages than ``counts`` (the bag's metadata or summary) lists."""
    problems = []
    found: dict[str, int] = {}
    for path in files:
        scan = McapScan(path)
        for rec in scan:
            if isinstance(rec, McapMessage) and rec.channel_id in scan.channels:
                topic = scan.channels[rec.channel_id].topic
                found[topic] = found.get(topic, 0) + 1
        problems += [f'{path.name}: {s.line()}' for s in scan.skipped]
        if not scan.complete:
            problems.append(f'{path.name}: {scan.reason}')
    for topic, n in sorted(counts.items()):
        if found.get(topic, 0) < n:
            problems.append(
                f'{topic}: {found.get(topic, 0)} of the {n} messages listed are readable'
            )
    return problems


def bag_info(bag: Path | str) -> BagInfo:
    """Topics, types, counts and time span of a complete rosbag2 bag (from its metadata), and
    (MCAP storage) what :func:`mcap_damage` finds wrong with its data."""
    bag = Path(bag)
    if not bag.is_dir():
        msg = f'{bag} is not a bag directory'
        raise RecoverError(msg)
    try:
        check_bag(bag)
    except BagError as err:
        raise RecoverError(str(err)) from err
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
            compression_mode = reader.compression_mode
        meta = yaml.safe_load((bag / 'metadata.yaml').read_text())['rosbag2_bagfile_information']
        files = tuple(Path(p).name for p in meta['relative_file_paths'])
        storage = str(meta['storage_identifier'])
    except (ReaderError, FileNotFoundError, KeyError, TypeError, yaml.YAMLError) as err:
        msg = f'cannot read bag {bag}: {err} (if its recorder died, try `cloe bag recover {bag}`)'
        raise RecoverError(msg) from err
    damage: list[str] = []
    if storage == 'mcap' and compression_mode != 'file':
        damage = mcap_damage([bag / f for f in files], {t.topic: t.count for t in topics})
    return BagInfo(bag, files, storage, topics, count, start, end, tuple(damage))
