"""MCAP records decoded by the ``mcap`` library, bounded by the bytes at hand.

The record classes, opcodes and data streams are the library's (:mod:`mcap.records`,
:mod:`mcap.opcode`, :mod:`mcap.data_stream`). What this module adds is what reading damaged or
cut files needs and the library's readers do not do: every field is read from the record's own
bytes and a field that would run past them raises :class:`RecordError` (the library's stream
would return the bytes that are there), and the CRCs MCAP defines are checked where a file has
them:

* a chunk's ``uncompressed_crc`` (CRC-32 of its uncompressed records),
* the data section CRC of the ``DataEnd`` record (CRC-32 of every byte before it),
* the footer's ``summary_crc`` (CRC-32 of the summary section and the footer's first fields).

A CRC of 0 means "not computed" (the specification's convention; rosbags writes none).

The records read once per message or chunk (a message's fields, :func:`message_fields`; a
record's head; a message index) are unpacked with one precompiled :mod:`struct` call each, in the
specification's layout, where the library's stream reads each field by itself: a chunk holds
thousands of messages. test/io/test_mcap_records.py checks that they equal the library's readers.

Specification: https://mcap.dev/spec. No rclpy here.
"""

from __future__ import annotations

import io
import struct
import zlib
from collections.abc import Iterator
from typing import BinaryIO

from mcap.data_stream import ReadDataStream, RecordBuilder
from mcap.exceptions import EndOfFile, McapError
from mcap.opcode import Opcode
from mcap.reader import FOOTER_SIZE
from mcap.records import (
    Channel,
    Chunk,
    ChunkIndex,
    DataEnd,
    Footer,
    Header,
    McapRecord,
    Message,
    MessageIndex,
    Schema,
    Statistics,
)
from mcap.stream_reader import MAGIC_SIZE, get_chunk_data_stream
from mcap.writer import MCAP0_MAGIC

__all__ = [
    'COMPRESSIONS',
    'FOOTER_CRC_HEAD',
    'FOOTER_SIZE',
    'MAGIC',
    'MAGIC_SIZE',
    'MESSAGE_HEAD',
    'MESSAGE_INDEX_HEAD',
    'RECORD_HEAD_SIZE',
    'Opcode',
    'RecordError',
    'bounded_stream',
    'check_chunk_crc',
    'chunk_data_offset',
    'chunk_records',
    'crc_of_range',
    'decompress_chunk',
    'iter_records',
    'known_opcode',
    'message_fields',
    'opcode_name',
    'parse_record',
    'read_head',
    'record_bytes',
]

MAGIC = MCAP0_MAGIC
#: Chunk compressions the library decodes ('' is none).
COMPRESSIONS = ('', 'zstd', 'lz4')


def record_bytes(record: McapRecord) -> bytes:
    """The record as the library writes it into a file, head included."""
    builder = RecordBuilder()
    record.write(builder)
    return builder.end()


def _size_of(record: McapRecord) -> int:
    """Bytes the record occupies in a file (head included), as the library writes it."""
    return len(record_bytes(record))


def _head_size() -> int:
    builder = RecordBuilder()
    builder.start_record(Opcode.HEADER)
    return builder.count


#: opcode (u8) and length (u64) before every record's body
RECORD_HEAD_SIZE = _head_size()
#: a message record's fields before its data (channel id, sequence, log and publish time)
MESSAGE_PREFIX_SIZE = _size_of(Message(0, 0, b'', 0, 0)) - RECORD_HEAD_SIZE
#: a DataEnd record, head included
DATA_END_SIZE = _size_of(DataEnd(0))
#: the fields of a footer the summary CRC covers (head, summary start, summary offset start)
FOOTER_CRC_PREFIX = FOOTER_SIZE - 4


#: a record head, and a message record's fields before its data, as the specification lays
#: them out (little-endian; test/io/test_mcap_records.py checks them against the library's)
_HEAD = struct.Struct('<BQ')
_MESSAGE = struct.Struct('<HIQQ')
_INDEX_HEAD = struct.Struct('<HI')
#: the same as written in one call (:mod:`~cloe_ros.io.mcap_writer`): a message record's head and
#: fields before its data, a message index's head and fields before its entries
MESSAGE_HEAD = struct.Struct(_HEAD.format + _MESSAGE.format.lstrip('<'))
MESSAGE_INDEX_HEAD = struct.Struct(_HEAD.format + _INDEX_HEAD.format.lstrip('<'))
#: the footer's fields the summary CRC covers (:data:`FOOTER_CRC_PREFIX` bytes): its head, the
#: summary's start and the summary offsets' start
FOOTER_CRC_HEAD = struct.Struct(_HEAD.format + 'QQ')


class RecordError(ValueError):
    """Bytes that do not parse as the record they claim to be."""


def opcode_name(op: int) -> str:
    try:
        return ''.join(w.capitalize() for w in Opcode(op).name.split('_'))
    except ValueError:
        return f'opcode 0x{op:02x}'


_FIRST_OPCODE, _LAST_OPCODE = min(Opcode), max(Opcode)


def known_opcode(op: int) -> bool:
    """An opcode the specification defines (0x01-0x0F), or a user extension (0x80-0xFF)."""
    return _FIRST_OPCODE <= op <= _LAST_OPCODE or op >= 0x80


class _Bounded(ReadDataStream):
    """The library's data stream over one record's bytes, refusing to read past them."""

    def __init__(self, data: bytes | memoryview) -> None:
        super().__init__(io.BytesIO(data))
        self.size = len(data)

    def read(self, length: int) -> bytes:
        if length < 0 or self.count + length > self.size:
            msg = f'a field of {length} bytes at {self.count} overruns the record'
            raise RecordError(msg)
        return super().read(length)


_READERS = {
    Opcode.HEADER: Header.read,
    Opcode.FOOTER: Footer.read,
    Opcode.SCHEMA: Schema.read,
    Opcode.CHANNEL: Channel.read,
    Opcode.CHUNK: Chunk.read,
    Opcode.MESSAGE_INDEX: MessageIndex.read,
    Opcode.CHUNK_INDEX: ChunkIndex.read,
    Opcode.STATISTICS: Statistics.read,
    Opcode.DATA_END: DataEnd.read,
}


def parse_record(op: int, body: bytes | memoryview) -> McapRecord | None:
    """The record with opcode ``op`` and ``body`` (its bytes after the head), decoded by the
    library; None for a record this package does not use (attachments, metadata, ...).
    :class:`RecordError` when the body does not parse: a field runs past it, a string is not
    UTF-8, a schema has the reserved id 0."""
    try:
        if op == Opcode.MESSAGE:
            channel_id, sequence, log_time, publish_time = _message_prefix(body)
            return Message(channel_id, log_time, bytes(body[MESSAGE_PREFIX_SIZE:]), publish_time,
                           sequence)  # fmt: skip
        if op == Opcode.MESSAGE_INDEX:  # read for every chunk of a file without chunk CRCs
            return _message_index(body)
        reader = _READERS.get(op)
        if reader is None:
            return None
        record = reader(_Bounded(body))
    except (EndOfFile, struct.error) as err:  # pragma: no cover - _Bounded raises first
        raise RecordError(f'{opcode_name(op)} record is cut: {err}') from err
    except UnicodeDecodeError as err:
        raise RecordError(f'a string of the {opcode_name(op)} record is not UTF-8') from err
    if isinstance(record, Schema) and record.id == 0:
        raise RecordError('schema id 0 is reserved')
    return record


def _message_index(body: bytes | memoryview) -> MessageIndex:
    """:meth:`MessageIndex.read <mcap.records.MessageIndex.read>`, its entries unpacked in one
    call: the (log time, offset) pairs that start before the end its length gives."""
    if len(body) < _INDEX_HEAD.size:
        msg = f'message index record of {len(body)} bytes is shorter than its header'
        raise RecordError(msg)
    channel_id, length = _INDEX_HEAD.unpack_from(body)
    pairs = -(-length // 16)
    if _INDEX_HEAD.size + 16 * pairs > len(body):
        msg = f'the {length} bytes of entries of a message index overrun its record'
        raise RecordError(msg)
    flat = struct.unpack_from(f'<{2 * pairs}Q', body, _INDEX_HEAD.size)
    return MessageIndex(channel_id, list(zip(flat[::2], flat[1::2])))


def read_head(data: bytes | memoryview) -> tuple[int, int]:
    """``(opcode, length)`` of a record head (``RECORD_HEAD_SIZE`` bytes)."""
    if len(data) < RECORD_HEAD_SIZE:
        msg = f'a record head of {RECORD_HEAD_SIZE} bytes overruns the {len(data)} bytes at hand'
        raise RecordError(msg)
    return _HEAD.unpack_from(data)


def message_fields(body: bytes | memoryview) -> tuple[int, int, bytes]:
    """``(channel id, log time, data)`` of a message record's ``body``: the fields
    :class:`~mcap.records.Message` reads, unpacked in one call (a chunk holds thousands of
    messages, and the library's stream reads each field by itself). :class:`RecordError` when
    the body is shorter than the fields before the data."""
    channel_id, _sequence, log_time, _publish_time = _message_prefix(body)
    return channel_id, log_time, bytes(body[MESSAGE_PREFIX_SIZE:])


def _message_prefix(body: bytes | memoryview) -> tuple[int, int, int, int]:
    """``(channel id, sequence, log time, publish time)``, the fields of a message record's
    ``body`` before its data; :class:`RecordError` when the body is shorter than them."""
    if len(body) < MESSAGE_PREFIX_SIZE:
        msg = f'message record of {len(body)} bytes is shorter than its header'
        raise RecordError(msg)
    return _MESSAGE.unpack_from(body)


def iter_records(data: bytes | memoryview) -> Iterator[tuple[int, int, memoryview]]:
    """``(offset, opcode, body)`` of the records that fill ``data`` (a chunk's uncompressed
    records, a summary section); :class:`RecordError` when a head or a body is cut."""
    view = memoryview(data)
    pos = 0
    while pos < len(view):
        if pos + RECORD_HEAD_SIZE > len(view):
            raise RecordError(f'the data end inside a record header (at {pos})')
        op, length = _HEAD.unpack_from(view, pos)
        start = pos + RECORD_HEAD_SIZE
        if length > len(view) - start:
            raise RecordError(f'the {opcode_name(op)} record at {pos} overruns the data')
        yield pos, op, view[start : start + length]
        pos = start + length


def chunk_data_offset(compression: str) -> int:
    """Where a chunk's compressed records start in its body, for a chunk of ``compression`` (the
    fixed fields and the compression name before them)."""
    empty = _size_of(Chunk(compression, b'', 0, 0, 0, 0))
    return empty - RECORD_HEAD_SIZE


def decompress_chunk(chunk: Chunk) -> bytes:
    """The uncompressed records of a complete ``chunk``, checked against its size (not its CRC:
    :func:`check_chunk_crc`); :class:`RecordError` saying what failed."""
    if chunk.compression not in COMPRESSIONS:
        raise RecordError(f'unsupported chunk compression {chunk.compression!r}')
    try:
        stream, size = get_chunk_data_stream(chunk, validate_crc=False)
        data = stream.read(size) if size else b''
    except McapError as err:
        raise RecordError(f'{chunk.compression} is not installed: {err}') from err
    except Exception as err:  # any codec failure means corrupt data
        msg = f'its {chunk.compression} data do not decompress: {err}'
        raise RecordError(msg) from err
    if len(data) != chunk.uncompressed_size:
        msg = (
            f'Chunk size mismatch: {len(data)} bytes once uncompressed, its header says '
            f'{chunk.uncompressed_size}.'
        )
        raise RecordError(msg)
    return data


def chunk_records(chunk: Chunk) -> bytes:
    """The uncompressed records of a complete ``chunk``, checked against its size and, when it has
    one, its CRC (:class:`RecordError` saying which check failed)."""
    data = decompress_chunk(chunk)
    check_chunk_crc(chunk, data)
    return data


def bounded_stream(data: bytes | memoryview) -> ReadDataStream:
    """The library's data stream over ``data``, raising :class:`RecordError` instead of reading
    past their end (for reading the fields of a record that is cut)."""
    return _Bounded(data)


def check_chunk_crc(chunk: Chunk, data: bytes) -> None:
    """:class:`RecordError` if ``chunk`` has a CRC that its uncompressed ``data`` do not match."""
    if not chunk.uncompressed_crc:
        return
    actual = zlib.crc32(data)
    if actual != chunk.uncompressed_crc:
        msg = (
            f'Chunk checksum mismatch. Its uncompressed records have CRC-32 {actual:#010x}, '
            f'its header records {chunk.uncompressed_crc:#010x}.'
        )
        raise RecordError(msg)


def crc_of_range(fh: BinaryIO, start: int, end: int, block: int = 1 << 20) -> int:
    """CRC-32 of the bytes ``[start, end)`` of ``fh``."""
    crc = 0
    fh.seek(start)
    left = end - start
    while left > 0:
        data = fh.read(min(block, left))
        if not data:
            break
        crc = zlib.crc32(data, crc)
        left -= len(data)
    return crc
