"""An MCAP writer whose message path is one precompiled :mod:`struct` call.

:class:`McapWriter` writes, call for call, the file the ``mcap`` library's writer
(:class:`mcap.writer.Writer`) writes with chunks, zstd or no compression, every index, the
statistics, the summary offsets and the CRCs (of each chunk's records, of the data section, of the
summary): test/io/test_mcap_writer.py checks that the two files are equal byte for byte.

The library's record classes still write every record but the messages and their indexes. The
library builds a record object for each message and writes it field by field, and packs each
entry of a message index by itself. Here a message is packed into the chunk's buffer with one
call, and its index entry is two ints in a list; the chunk's times and the statistics' counts are
worked out from those lists when the chunk is written. ``cloe infer`` writes some 22000 messages
for a 50 s flight: :class:`~cloe_ros.io.writer.BagWriter` took 14–16 µs per message on the
library's writer, 5 µs on this one, zstd compression included (``scripts/benchmark.py --writer``,
EVALUATION.md, section 4).

Writes go to the stream where the library's go: the magic and header at construction, a chunk
and its message indexes once its records pass ``chunk_size`` bytes or on :meth:`flush`, a
metadata record as it comes, the summary and the footer on :meth:`finish`. An ``OSError`` of the
stream reaches the caller.

Specification: https://mcap.dev/spec. No rclpy here.
"""

from __future__ import annotations

import struct
import zlib
from typing import BinaryIO

from mcap.data_stream import RecordBuilder
from mcap.records import (
    Channel,
    Chunk,
    ChunkIndex,
    DataEnd,
    Footer,
    Header,
    Metadata,
    MetadataIndex,
    Schema,
    Statistics,
    SummaryOffset,
)

from cloe_ros.io import mcap_records as mr
from cloe_ros.io.mcap_records import Opcode, record_bytes

__all__ = ['McapWriter']

# the layouts of mcap_records, bound here for the message path
_MESSAGE, _MESSAGE_BODY = mr.MESSAGE_HEAD, mr.MESSAGE_PREFIX_SIZE
_INDEX_HEAD = mr.MESSAGE_INDEX_HEAD
_INDEX_BODY = _INDEX_HEAD.size - mr.RECORD_HEAD_SIZE  # a message index's fields before entries
_FOOTER_BODY = mr.FOOTER_SIZE - mr.RECORD_HEAD_SIZE


class McapWriter:
    """Write an MCAP file to ``stream`` (binary, writable): the magic and header at once.

    Args:
        stream: where the file goes; it is not closed here.
        chunk_size: a chunk is written once its records pass this many bytes.
        compression: ``'zstd'`` or ``''`` (none), per chunk.
        profile, library: the header's fields.
    """

    def __init__(
        self, stream: BinaryIO, chunk_size: int, compression: str, profile: str, library: str
    ) -> None:
        if compression not in ('zstd', ''):
            msg = f"compression must be 'zstd' or '', got {compression!r}"
            raise ValueError(msg)
        if compression:
            import zstandard  # the library's writer uses the same function, at its default level

            self._compress = zstandard.compress
        self._stream = stream
        self._chunk_size = chunk_size
        self._compression = compression
        self._data_crc = 0  # of every byte of the data section written so far
        self._schemas: list[Schema] = []
        self._channels: list[Channel] = []
        self._chunk = bytearray()  # the pending chunk's records
        self._index: dict[int, list[int]] = {}  # channel -> log time, offset, log time, ...
        self._chunk_indexes: list[ChunkIndex] = []
        self._metadata_indexes: list[MetadataIndex] = []
        self._message_counts: dict[int, int] = {}  # per channel, in order of first message
        self._start_ns = self._end_ns = 0
        self._write(mr.MAGIC)
        self._write_record(Header(profile, library))

    # -- what the library's writer does, with the same results ---------------------------------

    def register_schema(self, name: str, encoding: str, data: bytes) -> int:
        schema = Schema(id=len(self._schemas) + 1, name=name, encoding=encoding, data=data)
        self._schemas.append(schema)
        self._add_to_chunk(schema)
        return schema.id

    def register_channel(
        self, topic: str, message_encoding: str, schema_id: int, metadata: dict[str, str]
    ) -> int:
        channel = Channel(id=len(self._channels) + 1, topic=topic,
                          message_encoding=message_encoding, schema_id=schema_id,
                          metadata=metadata)  # fmt: skip
        self._channels.append(channel)
        self._add_to_chunk(channel)
        return channel.id

    def add_message(self, channel_id: int, log_time: int, data: bytes | memoryview) -> bool:
        """One message, its publish time its log time, sequence 0; True if it filled the chunk
        and the chunk was written."""
        chunk = self._chunk
        index = self._index.get(channel_id)
        if index is None:
            index = self._index[channel_id] = []
        index += (log_time, len(chunk))
        chunk += _MESSAGE.pack(Opcode.MESSAGE, _MESSAGE_BODY + len(data), channel_id, 0,
                               log_time, log_time)  # fmt: skip
        chunk += data
        if len(chunk) > self._chunk_size:
            self._write_chunk()
            return True
        return False

    def add_metadata(self, name: str, data: dict[str, str]) -> None:
        offset = self._stream.tell()
        length = self._write_record(Metadata(name=name, metadata=data))
        self._metadata_indexes.append(MetadataIndex(offset=offset, length=length, name=name))

    def flush(self) -> None:
        """Write the pending chunk if it holds a message, and flush the stream."""
        self._write_chunk()
        self._stream.flush()

    def finish(self) -> None:
        """The pending chunk, the data section's end, the summary and the footer; the stream
        stays open."""
        self._write_chunk()
        self._write_record(DataEnd(self._data_crc))
        summary_start = self._stream.tell()
        builder = RecordBuilder()
        offsets = []
        groups = (
            (Opcode.SCHEMA, self._schemas),
            (Opcode.CHANNEL, self._channels),
            (Opcode.STATISTICS, [self._statistics()]),
            (Opcode.CHUNK_INDEX, self._chunk_indexes),
            (Opcode.ATTACHMENT_INDEX, []),
            (Opcode.METADATA_INDEX, self._metadata_indexes),
        )
        for opcode, records in groups:
            group_start = builder.count
            for record in records:
                record.write(builder)
            length = builder.count - group_start
            offsets.append(SummaryOffset(opcode, summary_start + group_start, length))
        offsets_start = summary_start + builder.count
        for offset in offsets:
            offset.write(builder)
        summary = builder.end()
        crc = zlib.crc32(summary)
        crc = zlib.crc32(mr.FOOTER_CRC_HEAD.pack(Opcode.FOOTER, _FOOTER_BODY, summary_start,
                                                 offsets_start), crc)  # fmt: skip
        self._stream.write(summary)
        footer = Footer(summary_start=summary_start, summary_offset_start=offsets_start,
                        summary_crc=crc)  # fmt: skip
        self._write_record(footer)
        self._stream.write(mr.MAGIC)

    # -- internals -----------------------------------------------------------------------------

    def _write(self, data: bytes) -> None:
        self._data_crc = zlib.crc32(data, self._data_crc)
        self._stream.write(data)

    def _write_record(self, record) -> int:
        """Write ``record`` (one of the library's) to the data section; its length in bytes."""
        data = record_bytes(record)
        self._write(data)
        return len(data)

    def _add_to_chunk(self, record) -> None:
        self._chunk += record_bytes(record)
        if len(self._chunk) > self._chunk_size and self._index:
            self._write_chunk()

    def _write_chunk(self) -> None:
        """The pending chunk and its message indexes, if it holds a message (declarations alone
        wait for the next one, as in the library's writer)."""
        if not self._index:
            return
        records = bytes(self._chunk)
        times = [t for flat in self._index.values() for t in flat[::2]]
        start, end = min(times), max(times)
        data = self._compress(records) if self._compression else records
        chunk = Chunk(compression=self._compression, data=data, message_start_time=start,
                      message_end_time=end, uncompressed_crc=zlib.crc32(records),
                      uncompressed_size=len(records))  # fmt: skip
        chunk_offset = self._stream.tell()
        chunk_length = self._write_record(chunk)
        index_offset = chunk_offset + chunk_length
        offsets, pieces = {}, []
        position = index_offset
        for channel_id, flat in self._index.items():
            offsets[channel_id] = position
            entries = struct.pack(f'<{len(flat)}Q', *flat)
            head = _INDEX_HEAD.pack(Opcode.MESSAGE_INDEX, _INDEX_BODY + len(entries), channel_id,
                                    len(entries))  # fmt: skip
            piece = head + entries
            pieces.append(piece)
            position += len(piece)
        self._write(b''.join(pieces))
        self._chunk_indexes.append(ChunkIndex(
            message_start_time=start, message_end_time=end, chunk_start_offset=chunk_offset,
            chunk_length=chunk_length, message_index_offsets=offsets,
            message_index_length=position - index_offset, compression=self._compression,
            compressed_size=len(data), uncompressed_size=len(records)))  # fmt: skip
        counts = self._message_counts
        if counts:
            self._start_ns, self._end_ns = min(self._start_ns, start), max(self._end_ns, end)
        else:
            self._start_ns, self._end_ns = start, end
        for channel_id, flat in self._index.items():
            counts[channel_id] = counts.get(channel_id, 0) + len(flat) // 2
        self._chunk = bytearray()
        self._index = {}

    def _statistics(self) -> Statistics:
        return Statistics(
            message_count=sum(self._message_counts.values()),
            schema_count=len(self._schemas),
            channel_count=len(self._channels),
            attachment_count=0,
            metadata_count=len(self._metadata_indexes),
            chunk_count=len(self._chunk_indexes),
            message_start_time=self._start_ns,
            message_end_time=self._end_ns,
            channel_message_counts=dict(self._message_counts),
        )
