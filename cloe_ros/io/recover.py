"""Recover bags whose recorder died or whose files are damaged.

A recorder killed with SIGKILL (or a machine that lost power) leaves a rosbag2 directory whose
``.mcap`` has no summary section and no footer, and no ``metadata.yaml`` (or a stale one): readers
that seek to the footer refuse it. :func:`recover_bag` reads such a file from the start, record by
record (:class:`McapScan`), and writes a complete bag with every message that was fully on disk
and intact. A damaged record is stepped over and reported when readable records follow it (its
length leads to them, or the summary of a file that still has one says where the next chunk
starts); reading stops where nothing readable follows: a cut, or zeros or garbage up to the end.

Records are decoded by the ``mcap`` library (:mod:`cloe_ros.io.mcap_records`: its record classes,
opcodes and data streams, bounded by the bytes on disk); what is this module's own is the salvage
loop the library's readers cannot do, which never reads or allocates past the end of the file, so
a cut at any byte (or garbage after the last good record) ends the scan instead of raising.

MCAP (https://mcap.dev/spec): a chunk holds schema, channel and message records, compressed with
zstd or lz4 or not at all, and is followed by message index records (channel, log time and offset
of each of its messages). Messages of a chunk whose end is missing (cut off, or zero-filled) are
recovered when their bytes are complete inside the part that is on disk (a compressed chunk is
decompressed as far as its data go). A complete chunk is checked against its CRC where it has one
(bags this package writes do); a chunk whose CRC fails is left out whole unless the damage is
located (a record that does not parse or that its message index contradicts), and then, in an
uncompressed chunk, the messages found where the index puts them are kept. A chunk without CRC
(rosbags writes none) whose messages differ from its message index counts as damaged. The data
section CRC (``DataEnd``) is checked too: it tells of damage outside the chunks' records.

``cloe bag info`` (:mod:`cloe_ros.io.bag_info`) uses the same scan to check a bag's data.
"""

from __future__ import annotations

import re
import sys
import zlib
from collections.abc import Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import BinaryIO

from mcap.records import (
    Channel,
    Chunk,
    ChunkIndex,
    DataEnd,
    Footer,
    Header,
    Message,
    MessageIndex,
    Schema,
    Statistics,
)
from rosbags.rosbag2.errors import ReaderError
from rosbags.rosbag2.metadata import parse_qos
from rosbags.typesys import Stores, get_types_from_idl, get_types_from_msg, get_typestore

from cloe_ros.io import mcap_records as mr
from cloe_ros.io.errors import RecoverError, WriterError
from cloe_ros.io.reader import missing_message
from cloe_ros.io.writer import BagWriter

__all__ = [
    'FileRecovery',
    'McapChannel',
    'McapMessage',
    'McapScan',
    'McapSchema',
    'RecoverError',
    'RecoveryReport',
    'SkippedRecord',
    'default_output',
    'mcap_files',
    'recover_bag',
]

Op = mr.Opcode
MAGIC = mr.MAGIC
_HEAD = mr.RECORD_HEAD_SIZE
#: the body of a footer record
_FOOTER_BODY = mr.FOOTER_SIZE - _HEAD

#: The records a scan yields: the mcap library's classes.
McapSchema = Schema
McapChannel = Channel
McapMessage = Message


class _Corrupt(Exception):
    """Bytes that do not parse as the record they claim to be (internal)."""


class _CrcMismatch(_Corrupt):
    """A complete chunk whose records do not match its CRC; ``located`` when a record that does
    not parse, or that the message index contradicts, shows where the damage is (internal)."""

    def __init__(self, msg: str, located: bool) -> None:
        super().__init__(msg)
        self.located = located


def _parse(op: int, body: bytes | memoryview):
    """The record (mcap library class) of ``op`` with ``body``; :class:`_Corrupt` if it does not
    parse."""
    try:
        return mr.parse_record(op, body)
    except mr.RecordError as err:
        raise _Corrupt(str(err)) from err


def _head(data: bytes | memoryview, at: int = 0) -> tuple[int, int]:
    """``(opcode, length)`` of the record head at ``at`` of ``data`` (9 bytes there)."""
    return mr.read_head(memoryview(data)[at : at + _HEAD])


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


def _chunk_head(body: bytes | memoryview, complete: bool) -> Chunk:
    """The chunk record of ``body``; for a chunk not ``complete`` on disk, its fields and as much
    of its compressed records as ``body`` holds (the library reads whole records only, so the
    fields are read here, in the specification's order, from the library's bounded stream)."""
    if complete:
        chunk = _parse(Op.CHUNK, body)
        assert isinstance(chunk, Chunk)
        return chunk
    try:
        stream = mr.bounded_stream(body)
        start, end, size, crc = stream.read8(), stream.read8(), stream.read8(), stream.read4()
        compression = stream.read_prefixed_string()
        length = stream.read8()
    except mr.RecordError as err:
        raise _Corrupt(str(err)) from err
    except UnicodeDecodeError as err:
        raise _Corrupt('the compression name is not UTF-8') from err
    data = bytes(memoryview(body)[stream.count : stream.count + length])
    return Chunk(compression, data, end, start, crc, size)


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

    Iterating yields :class:`McapSchema`, :class:`McapChannel` and :class:`McapMessage` records
    (the mcap library's classes) in file order (chunk contents in place of their chunks). A
    damaged record is stepped over when reading can go on after it: its length leads to
    plausible records, or (in a file that still has its footer) the summary's chunk index says
    where the next chunk starts. It is listed in ``skipped``. A chunk is damaged when it does not
    decompress or parse, when its records do not match its CRC, when a message's log time lies
    outside the chunk's time range, or (a chunk without CRC) when its messages differ from the
    message index written after it. Of an uncompressed damaged chunk the messages that match the
    index are kept, unless its CRC fails and nothing locates the damage; a compressed one is left
    out whole (past the damage its decompressed bytes cannot be trusted). When the iteration ends:

    * ``end`` is the offset just past the last record read in full (``file_size`` for a good file),
    * ``complete`` says whether the footer and the closing magic were found,
    * ``reason`` says why reading stopped, with the offset, in words,
    * ``skipped`` lists the damaged records stepped over (:class:`SkippedRecord`),
    * ``partial_chunk_messages`` counts messages taken from a last chunk whose end is missing: cut
      off by the end of the file, or (``damaged_tail``) followed by nothing readable (zero-filled
      or garbage up to the end of the file); its complete messages are kept as for a cut file,
    * ``expected_messages`` is the message count of the file's statistics (None without summary),
    * ``data_crc_mismatch`` says whether the file's ``DataEnd`` record holds a data section CRC
      that the bytes before it do not match,
    * ``chunks`` and ``chunks_without_crc`` count the whole chunks read and those that carry no
      CRC (0: none computed, which the format allows), whose bytes nothing can vouch for; a
      message index checks their records' places and times, not their contents; and
      ``data_crc`` says whether a ``DataEnd`` record held a data section CRC.

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
        self.data_crc_mismatch = False
        self.chunks = self.chunks_without_crc = 0
        self.data_crc = False
        self.skipped: list[SkippedRecord] = []
        self.expected_messages: int | None = None
        self.schemas: dict[int, McapSchema] = {}
        self.channels: dict[int, McapChannel] = {}
        self.profile = ''
        self._summary_schemas: dict[int, McapSchema] = {}
        self._summary_channels: dict[int, McapChannel] = {}
        self._resync_points: list[int] = []
        self._chunk_infos: dict[int, ChunkIndex] = {}  # chunk offset -> the summary's index

    @property
    def damaged(self) -> bool:
        """Whether damage was found (skipped records, a damaged last chunk, a data section that
        does not match its CRC)."""
        return bool(self.skipped) or self.damaged_tail or self.data_crc_mismatch

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
        magic = fh.read(mr.MAGIC_SIZE)
        if not magic:
            msg = (
                f'{self.path} is empty: the recorder stopped before writing anything, '
                'there is nothing to recover'
            )
            raise RecoverError(msg)
        if magic != MAGIC[: len(magic)]:
            msg = f'{self.path} is not an MCAP file (it does not start with the MCAP magic bytes)'
            raise RecoverError(msg)
        if len(magic) < mr.MAGIC_SIZE:
            self.end = 0
            self._stop(len(magic), 'file cut inside the MCAP magic')
            return
        self._read_summary(fh)
        pos = self.end = mr.MAGIC_SIZE
        first = True
        while True:
            fh.seek(pos)
            head = fh.read(_HEAD)
            if not head:
                self._stop(pos, 'file ends after a complete record, without footer')
                return
            if len(head) < _HEAD:
                self._stop(pos, 'file cut inside a record header')
                return
            op, length = _head(head)
            name = mr.opcode_name(op)
            body_start = pos + _HEAD
            available = self.file_size - body_start
            problem = ''
            if not mr.known_opcode(op):
                what = 'zero bytes' if op == 0 else f'invalid opcode 0x{op:02x}'
                problem = f'corrupt data: {what} where a record should start'
            elif first and op != Op.HEADER:
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
                what = 'record' if not mr.known_opcode(op) else f'{name} record'
                self.skipped.append(SkippedRecord(pos, resume - pos, what, problem, None))
                pos = self.end = resume
                first = False
                continue
            if length > available:
                if op == Op.CHUNK:
                    yield from self._partial_chunk(fh, pos, length, available)
                else:
                    self._stop(pos, f'file cut inside a {name} record ({length} bytes)')
                return
            body = fh.read(length)
            if len(body) != length:  # the file shrank while we read it
                self._stop(pos, f'file cut inside a {name} record ({length} bytes)')
                return
            after = body_start + length
            if op == Op.CHUNK:
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
                    records = self._record(fh, pos, op, body)
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
            if op == Op.FOOTER:
                fh.seek(pos)
                tail = fh.read(mr.MAGIC_SIZE)
                if tail == MAGIC:
                    self.end = pos + mr.MAGIC_SIZE
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
            head = fh.read(_HEAD)
            if len(head) < _HEAD:
                return i > 0  # the file ends (or is cut) after a plausible record
            op, length = _head(head)
            if not Op.FOOTER <= op <= Op.DATA_END:
                return False
            if length > self.file_size - offset - _HEAD:
                return op == Op.CHUNK
            if op == Op.FOOTER:
                return length == _FOOTER_BODY and offset + mr.FOOTER_SIZE + mr.MAGIC_SIZE == (
                    self.file_size
                )
            offset += _HEAD + length
        return True

    def _resume(self, fh: BinaryIO, pos: int, length: int) -> int | None:
        """Where reading goes on after the damaged record at ``pos`` (None: nowhere): after it, if
        its length leads to plausible records; else at the next chunk the summary knows of."""
        after = pos + _HEAD + length
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
        footer_at = self.file_size - mr.MAGIC_SIZE - mr.FOOTER_SIZE
        if footer_at <= mr.MAGIC_SIZE:
            return
        fh.seek(footer_at)
        tail = fh.read(mr.FOOTER_SIZE + mr.MAGIC_SIZE)
        if tail[-mr.MAGIC_SIZE :] != MAGIC or _head(tail) != (Op.FOOTER, _FOOTER_BODY):
            return
        try:
            footer = _parse(Op.FOOTER, tail[_HEAD : mr.FOOTER_SIZE])
        except _Corrupt:  # pragma: no cover - a footer of the right length always parses
            return
        assert isinstance(footer, Footer)
        summary_start = footer.summary_start
        if not mr.MAGIC_SIZE < summary_start < footer_at:
            return
        fh.seek(summary_start)
        data = memoryview(fh.read(footer_at - summary_start))
        points = []
        pos = 0
        while pos + _HEAD <= len(data):
            op, length = _head(data, pos)
            if length > len(data) - pos - _HEAD:
                break
            try:
                record = _parse(op, data[pos + _HEAD : pos + _HEAD + length])
            except _Corrupt:
                record = None
            if isinstance(record, Schema):
                self._summary_schemas[record.id] = record
            elif isinstance(record, Channel):
                self._summary_channels[record.id] = record
            elif isinstance(record, ChunkIndex):
                self._chunk_infos[record.chunk_start_offset] = record
                points.append(record.chunk_start_offset)
            elif isinstance(record, Statistics):
                self.expected_messages = record.message_count
            pos += _HEAD + length
        self._resync_points = sorted({p for p in points if mr.MAGIC_SIZE < p < summary_start})
        self._resync_points.append(summary_start)

    def _message_index(self, fh: BinaryIO, offset: int) -> dict[int, set[tuple[int, int]]] | None:
        """The message index records after a chunk: channel -> {(log time, offset)}; None when
        there are none or one does not parse."""
        index: dict[int, set[tuple[int, int]]] = {}
        while True:
            fh.seek(offset)
            head = fh.read(_HEAD)
            if len(head) < _HEAD:
                break
            op, length = _head(head)
            if op != Op.MESSAGE_INDEX or length > self.file_size - offset - _HEAD:
                break
            try:
                record = _parse(op, fh.read(length))
            except _Corrupt:
                return None
            assert isinstance(record, MessageIndex)
            index.setdefault(record.channel_id, set()).update(record.records)
            offset += _HEAD + length
        return index or None

    # -- records --------------------------------------------------------------------------------

    def _emit(self, records: list) -> Iterator[McapSchema | McapChannel | McapMessage]:
        """Yield ``records``, registering schemas and channels; a message of a channel not
        declared so far (its declaration was in a damaged chunk) gets the summary's."""
        for rec in records:
            if isinstance(rec, Schema):
                self.schemas[rec.id] = rec
            elif isinstance(rec, Channel):
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

    def _record(
        self, fh: BinaryIO, pos: int, op: int, body: bytes
    ) -> list[McapSchema | McapChannel | McapMessage]:
        """A top-level record other than a chunk: declarations and messages are yielded, the
        header gives the profile, ``DataEnd`` the data section CRC (checked here)."""
        if op not in (Op.HEADER, Op.SCHEMA, Op.CHANNEL, Op.MESSAGE, Op.DATA_END):
            return []
        record = _parse(op, body)
        if isinstance(record, Header):
            self.profile = record.profile
            return []
        if isinstance(record, DataEnd):
            self.data_crc = bool(record.data_section_crc)
            if record.data_section_crc and not self.skipped:
                crc = mr.crc_of_range(fh, 0, pos)
                self.data_crc_mismatch = crc != record.data_section_crc
            return []
        return [record]

    @staticmethod
    def _inner_records(data: bytes, head: Chunk) -> tuple[list, str, int]:
        """The records of a chunk's uncompressed ``data`` with their offsets, up to the first
        one that is cut or does not parse or (a message) lies outside the chunk's time range;
        what stopped the parse ('' when all of ``data`` parsed); and where it stopped."""
        out: list[tuple[int, object]] = []
        inner = memoryview(data)
        pos = 0
        start, end = head.message_start_time, head.message_end_time
        while pos < len(inner):
            if pos + _HEAD > len(inner):
                return out, 'chunk ends inside a record header', pos
            op, length = _head(inner, pos)
            if not mr.known_opcode(op):
                return out, f'invalid opcode 0x{op:02x} inside the chunk', pos
            if length > len(inner) - pos - _HEAD:
                return out, 'chunk ends inside a record', pos
            if op in (Op.SCHEMA, Op.CHANNEL, Op.MESSAGE):
                try:
                    rec = _parse(op, inner[pos + _HEAD : pos + _HEAD + length])
                except _Corrupt as err:
                    why = f'corrupt {mr.opcode_name(op)} record inside the chunk: {err}'
                    return out, why, pos
                if isinstance(rec, Message) and not start <= rec.log_time <= end:
                    why = (
                        f"a message logged at {rec.log_time} ns lies outside the chunk's time "
                        f'range {start}-{end} ns'
                    )
                    return out, why, pos
                out.append((pos, rec))
            pos += _HEAD + length
        return out, '', pos

    def _chunk(self, body: bytes, index: dict[int, set[tuple[int, int]]] | None) -> list:
        """The records of a chunk that is whole on disk; :class:`_Corrupt` if it is damaged
        (:class:`_CrcMismatch` if it does not match its CRC)."""
        head = _chunk_head(body, complete=True)
        self.chunks += 1
        self.chunks_without_crc += not head.uncompressed_crc
        try:
            data = mr.decompress_chunk(head)
        except mr.RecordError as err:
            raise _Corrupt(str(err)) from err
        records, problem, _ = self._inner_records(data, head)
        if head.uncompressed_crc and zlib.crc32(data) != head.uncompressed_crc:
            if not problem and index is not None:  # where the damage is, if the index tells
                try:
                    _check_index(records, index)
                except _Corrupt as err:
                    problem = str(err)
            why = 'chunk CRC does not match its data' + (f'; {problem}' if problem else '')
            raise _CrcMismatch(why, located=bool(problem))
        if problem:
            raise _Corrupt(problem)
        if index is not None and not head.uncompressed_crc:  # a matching CRC vouches for it
            _check_index(records, index)
        return [rec for _, rec in records]

    def _chunk_from_summary(self, fh: BinaryIO, pos: int) -> tuple[list, int] | None:
        """The records of the chunk at ``pos`` read with what the summary's chunk index says of
        it (length, compression, sizes, time range) instead of its own, damaged header, and the
        offset after it; None unless they are vouched for: by the chunk's CRC where its header
        still holds one that matches, else by the message index after it."""
        info = self._chunk_infos.get(pos)
        if info is None:
            return None
        after = pos + info.chunk_length
        if not pos + _HEAD < after <= self.file_size:
            return None
        index = self._message_index(fh, after)
        fh.seek(pos + _HEAD)
        body = fh.read(info.chunk_length - _HEAD)
        try:  # the fields before the compression name have fixed places: the CRC may be intact
            crc = _chunk_head(body, complete=False).uncompressed_crc
        except _Corrupt:
            crc = 0
        skip = mr.chunk_data_offset(info.compression)
        compressed = body[skip : skip + info.compressed_size]
        head = Chunk(
            info.compression, compressed, info.message_end_time, info.message_start_time, 0,
            info.uncompressed_size,
        )  # fmt: skip
        try:
            data = mr.decompress_chunk(head)
        except mr.RecordError:
            return None
        records, problem, _ = self._inner_records(data, head)
        if problem:
            return None
        if crc:
            if zlib.crc32(data) != crc:
                return None
        else:
            if index is None:
                return None
            try:
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
            skip = mr.chunk_data_offset(info.compression)
            head = Chunk(
                info.compression, bytes(body[skip:][: info.compressed_size]),
                info.message_end_time, info.message_start_time, 0, info.uncompressed_size,
            )  # fmt: skip
        data = _readable_prefix(head.compression, head.data)
        if cut:
            data = data[: head.uncompressed_size]
        records, _, stop = self._inner_records(data, head)
        return head, records, data, stop

    def _read_with_summary(self, pos: int, found: tuple[list, int], problem: str) -> Iterator:
        records, after = found
        n = sum(isinstance(r, Message) for r in records)
        reason = f'{problem}; read with the chunk index of the summary instead'
        self.skipped.append(SkippedRecord(pos, after - pos, 'Chunk', reason, 0, n))
        yield from self._emit(records)

    def _skip_chunk(self, pos, resume, body, index, err, length_ok) -> Iterator:
        """Step over a damaged chunk that has readable records after it. Of an uncompressed one
        (its records are the bytes on disk) keep the declarations before the damage and every
        message found where the index after the chunk puts it, with the channel and log time the
        index gives; none if its CRC fails and nothing shows where the damage is."""
        kept: list = []
        trusted = not (isinstance(err, _CrcMismatch) and not err.located)
        if length_ok and index is not None:
            try:
                head, records, _, _ = self._salvage(pos, body)
            except _Corrupt:
                pass
            else:
                if head.compression == '':
                    kept = [(o, r) for o, r in records if not isinstance(r, Message)]
                    if trusted:
                        kept += self._indexed_messages(head, index)
                    kept.sort(key=lambda item: item[0])
        n_kept = sum(isinstance(r, Message) for _, r in kept)
        lost = sum(map(len, index.values())) - n_kept if index is not None else None
        reason = f'corrupt Chunk record: {err}'
        if not trusted:
            reason += ', and nothing shows which of its messages changed'
        self.skipped.append(SkippedRecord(pos, resume - pos, 'Chunk', reason, lost, n_kept))
        yield from self._emit([r for _, r in kept])

    @staticmethod
    def _indexed_messages(head: Chunk, index) -> list[tuple[int, Message]]:
        """The intact message records of uncompressed chunk data at the offsets of ``index``: a
        message record with the channel and log time the index gives, ending where the next
        indexed message starts, or before a plausible record, or at the end of the data."""
        data = memoryview(head.data)
        starts = sorted({offset for entries in index.values() for _, offset in entries})
        following = dict(zip(starts, [*starts[1:], None]))
        out = []
        for channel, entries in index.items():
            for log_time, offset in entries:
                if offset + _HEAD > len(data):
                    continue
                op, length = _head(data, offset)
                start = offset + _HEAD
                end = start + length
                nxt = following[offset]
                if op != Op.MESSAGE or end > len(data) or (nxt is not None and end > nxt):
                    continue
                if end not in (nxt, len(data)):
                    if end + _HEAD > len(data):
                        continue
                    op_after, length_after = _head(data, end)
                    if op_after not in (Op.SCHEMA, Op.CHANNEL, Op.MESSAGE) or (
                        length_after > len(data) - end - _HEAD
                    ):
                        continue
                try:
                    msg = _parse(Op.MESSAGE, data[start:end])
                except _Corrupt:
                    continue
                if (msg.channel_id, msg.log_time) == (channel, log_time) and (
                    head.message_start_time <= log_time <= head.message_end_time
                ):
                    out.append((offset, msg))
        return out

    def _damaged_last_chunk(self, pos, length, body, err) -> Iterator:
        """A chunk whole on disk that is damaged and followed by nothing readable (zero-filled or
        garbage up to the end of the file): its end was never written, so its complete records
        are taken as for a chunk cut by the end of the file (none if its CRC fails and nothing
        shows where the damage is)."""
        reason = (
            f'damaged Chunk record ({length} bytes) followed by nothing readable up to the end '
            f'of the file: {err}'
        )
        try:
            head, records, data, stop = self._salvage(pos, body)
        except _Corrupt:
            records = []
        else:
            if isinstance(err, _CrcMismatch) and not err.located:
                records = [(o, r) for o, r in records if not isinstance(r, Message)]
            elif head.compression == '' and data[stop : stop + 1] == b'\0':
                # zeros where the next record should be: the file's end was never written, and
                # the zeros may begin inside the last record read: keep none that reaches them
                zeros = len(data[:stop]) - len(data[:stop].rstrip(b'\0'))
                ends = [offset for offset, _ in records[1:]] + [stop]
                records = [r for r, e in zip(records, ends) if e <= stop - zeros]
        n = sum(isinstance(r, Message) for _, r in records)
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
        fh.seek(pos + _HEAD)
        body = fh.read(available)
        try:
            _, records, _, _ = self._salvage(pos, body, cut=True)
        except _Corrupt as err:
            self._stop(pos, f'{reason}; its start is corrupt too: {err}')
            return
        records = [r for _, r in records]
        n = sum(isinstance(r, Message) for r in records)
        self.partial_chunk_messages = n
        yield from self._emit(records)
        if n:
            reason += f'; {n} complete messages taken from the part on disk'
        self._stop(pos, reason)


# -- recovery ----------------------------------------------------------------------------------


#: What a data section CRC that fails while every chunk read matched its own says.
DATA_CRC_MISMATCH = (
    'its data section does not match its CRC, although every chunk matched its own: bytes '
    'outside the messages were changed (a message index, a chunk header, a declaration); the '
    'messages are intact'
)


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
    data_crc_mismatch: bool = False

    @property
    def damaged(self) -> bool:
        return bool(self.skipped) or self.damaged_tail or self.data_crc_mismatch

    def lines(self) -> list[str]:
        """How the file was read: one line, then one per damaged record stepped over."""
        reason = _without_offset(self.reason)
        n = f'{self.messages} messages read'
        if self.complete and (self.skipped or self.data_crc_mismatch):
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
        out = [first] + [f'  {s.line()}' for s in self.skipped]
        if self.data_crc_mismatch:
            out.append(f'  {DATA_CRC_MISMATCH}')
        return out


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
        raise RecoverError(missing_message(bag))
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

    try:
        writer = BagWriter(output, compression)
    except WriterError as err:
        msg = f'cannot create {output}: {err.reason or err}'
        raise RecoverError(msg) from err

    types = _TypeInfo()
    counts: dict[str, int] = {}
    msgtypes: dict[str, str] = {}
    skipped: dict[str, str] = {}
    orphans = 0
    results = []
    try:
        for path in files:
            scan = McapScan(path)
            # channel id -> output topic (None: skipped) for this file
            routes: dict[int, str | None] = {}
            n_file = 0
            for rec in scan:
                if isinstance(rec, McapChannel):
                    routes[rec.id] = _route(rec, scan, writer, types, skipped)
                    if routes[rec.id] is not None:
                        counts.setdefault(rec.topic, 0)
                        msgtypes[rec.topic] = scan.schemas[rec.schema_id].name
                    continue
                if not isinstance(rec, McapMessage):
                    continue
                if rec.channel_id not in routes:
                    orphans += 1
                    continue
                n_file += 1
                topic = routes[rec.channel_id]
                if topic is None:
                    continue
                writer.write(topic, rec.log_time, rec.data)
                counts[topic] += 1
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
                    scan.data_crc_mismatch,
                )
            )
        if not counts:
            raise RecoverError(_nothing_to_recover(bag, results, skipped))
        if not sum(counts.values()) and any(f.skipped for f in results):
            # every message there was is damaged (a cut file with topics and no message yet
            # gives an empty bag with its topics: all it ever held)
            raise RecoverError(_nothing_to_recover(bag, results, skipped, list(counts)))
        writer.close()
    except BaseException as err:
        writer.discard()
        if isinstance(err, WriterError):
            msg = (
                f'cannot write {output}: {err.reason or err}; nothing recovered ({output} removed)'
            )
            raise RecoverError(msg) from err
        raise
    return RecoveryReport(output, tuple(results), counts, msgtypes, skipped, orphans)


def _nothing_to_recover(bag: Path, results: list[FileRecovery], skipped: dict[str, str],
                        declared: list[str] | None = None) -> str:  # fmt: skip
    """Why a bag without one usable message gives no output."""
    why = '; '.join(f'{f.path} ({f.size} bytes): {_without_offset(f.reason)}' for f in results)
    topics = ''.join(f'; topic {t} unusable: {w}' for t, w in sorted(skipped.items()))
    what = (f'no message of its {len(declared)} topic(s) is intact on disk' if declared
            else 'no topic and no message is complete on disk')  # fmt: skip
    return f'nothing to recover from {bag}: {what} ({why}{topics}); no output written'



def _route(
    channel: Channel, scan: McapScan, writer: BagWriter, types: _TypeInfo, skipped: dict[str, str]
) -> str | None:
    """The output topic of an input channel, added to ``writer`` on first sight (a later channel
    of the same topic adds its publishers' QoS profiles); None if unusable, and why in
    ``skipped``."""
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
    known = writer.topics.get(topic)
    if known is not None and known != schema.name:
        skipped[f'{topic} ({schema.name})'] = (
            f'channel {channel.id} of {scan.path} has type {schema.name}, the topic is '
            f'recovered as {known}'
        )
        return None
    if known is None:
        writer.add_topic(topic, schema.name, qos, msgdef=msgdef, rihs01=rihs01)
    else:
        writer.add_offered_qos(topic, qos)
    skipped.pop(topic, None)
    return topic
