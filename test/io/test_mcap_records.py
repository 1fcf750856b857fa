"""The MCAP records cloe_ros unpacks itself (message records and message indexes, read for every
message of a bag) give what the ``mcap`` library's readers give, and refuse what they refuse."""

from __future__ import annotations

import numpy as np
import pytest
from mcap.data_stream import RecordBuilder
from mcap.records import Message, MessageIndex

from cloe_ros.io import mcap_records as mr


def _body(record) -> bytes:
    """A record as the library writes it, without its head."""
    builder = RecordBuilder()
    record.write(builder)
    return bytes(builder.end()[mr.RECORD_HEAD_SIZE :])


def test_layouts_are_the_librarys():
    assert mr._HEAD.size == mr.RECORD_HEAD_SIZE
    assert mr._MESSAGE.size == mr.MESSAGE_PREFIX_SIZE
    builder = RecordBuilder()
    Message(7, 11, b'xyz', 13, 17).write(builder)
    data = builder.end()
    assert mr.read_head(data) == (mr.Opcode.MESSAGE, len(data) - mr.RECORD_HEAD_SIZE)
    # the layouts the writer packs in one call: the library's bytes
    assert mr.record_bytes(Message(7, 11, b'xyz', 13, 17)) == data
    assert mr.MESSAGE_HEAD.pack(mr.Opcode.MESSAGE, mr.MESSAGE_PREFIX_SIZE + 3, 7, 17, 11,
                                13) + b'xyz' == data  # fmt: skip
    index = mr.record_bytes(MessageIndex(5, [(1, 2), (3, 4)]))
    head = mr.MESSAGE_INDEX_HEAD.pack(mr.Opcode.MESSAGE_INDEX, len(index) - mr.RECORD_HEAD_SIZE,
                                      5, 32)  # fmt: skip
    assert index.startswith(head) and len(head) == mr.MESSAGE_INDEX_HEAD.size
    assert mr.FOOTER_CRC_HEAD.size == mr.FOOTER_CRC_PREFIX


@pytest.mark.parametrize('size', [0, 1, 100, 4096])
def test_message_fields_are_the_librarys(size):
    rng = np.random.default_rng(size)
    data = rng.integers(0, 256, size, dtype=np.uint8).tobytes()
    message = Message(channel_id=65535, log_time=2**64 - 1, data=data, publish_time=5,
                      sequence=2**32 - 1)  # fmt: skip
    body = _body(message)
    expected = Message.read(mr.bounded_stream(body), len(body))
    for view in (body, memoryview(body)):
        channel_id, log_time, got = mr.message_fields(view)
        assert (channel_id, log_time, got) == (expected.channel_id, expected.log_time,
                                                expected.data)  # fmt: skip
        assert type(got) is bytes  # a copy: the chunk's buffer can go
        assert mr.parse_record(mr.Opcode.MESSAGE, view) == expected


def test_a_cut_message_is_refused():
    body = _body(Message(1, 2, b'', 3, 4))
    with pytest.raises(mr.RecordError, match='shorter than its header'):
        mr.message_fields(body[:-1])
    with pytest.raises(mr.RecordError, match='shorter than its header'):
        mr.parse_record(mr.Opcode.MESSAGE, body[:-1])
    with pytest.raises(mr.RecordError):
        mr.read_head(b'\x05' * (mr.RECORD_HEAD_SIZE - 1))


@pytest.mark.parametrize('entries', [0, 1, 3, 1000])
def test_message_index_is_the_librarys(entries):
    rng = np.random.default_rng(entries)
    pairs = [(int(t), int(o)) for t, o in rng.integers(0, 2**63, (entries, 2), dtype=np.int64)]
    body = _body(MessageIndex(channel_id=3, records=pairs))
    expected = MessageIndex.read(mr.bounded_stream(body))
    got = mr.parse_record(mr.Opcode.MESSAGE_INDEX, body)
    assert got == expected
    assert got.records == pairs


@pytest.mark.parametrize('declared', [0, 8, 16, 20, 32, 48])
@pytest.mark.parametrize('extra', [0, 8, 16])
def test_message_index_of_odd_lengths_reads_as_the_library(declared, extra):
    """A damaged index (entries' length not a multiple of 16, or past the record's end): the
    library reads a pair while the entries' end is not reached, and a pair past the record
    raises; the package's reading does the same."""
    body = (
        (9).to_bytes(2, 'little') + declared.to_bytes(4, 'little')
        + bytes(range(256))[: 32 + extra]
    )  # fmt: skip
    try:
        expected = MessageIndex.read(mr.bounded_stream(body))
    except mr.RecordError:
        with pytest.raises(mr.RecordError):
            mr.parse_record(mr.Opcode.MESSAGE_INDEX, body)
    else:
        assert mr.parse_record(mr.Opcode.MESSAGE_INDEX, body) == expected
    with pytest.raises(mr.RecordError):
        mr.parse_record(mr.Opcode.MESSAGE_INDEX, body[:5])
