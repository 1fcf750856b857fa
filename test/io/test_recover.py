"""Bag recovery: files cut at every byte offset, corrupt tails, files from another MCAP writer.

Truth comes from outside the parser under test: the messages the test wrote, the chunk layout
mcap's own reader reports, and (for uncompressed chunks) where each message record's bytes sit in
the file according to the MCAP specification. A recovered message must be byte-identical to one
that was written, in order (never a message that was not fully on disk), and every message fully
on disk must be recovered.
"""

from __future__ import annotations

import io
import random
import shutil
import struct
from pathlib import Path

import numpy as np
import pytest
import zstandard
from mcap.reader import make_reader
from mcap.writer import CompressionType
from mcap.writer import Writer as McapLibWriter
from mcap_ros2.decoder import DecoderFactory
from rosbags.highlevel import AnyReader
from rosbags.interfaces import (
    Qos,
    QosDurability,
    QosHistory,
    QosLiveliness,
    QosReliability,
    QosTime,
)

from cloe_ros.cli.main import main as cloe
from cloe_ros.core.samples import OdometrySample, PoseSample
from cloe_ros.io.bag_info import bag_info
from cloe_ros.io.messages import (
    ODOMETRY,
    POSE_STAMPED,
    TYPESTORE,
    decode_pose_stamped,
    encode_odometry,
    encode_pose_stamped,
)
from cloe_ros.io.recover import (
    McapMessage,
    McapScan,
    RecoverError,
    default_output,
    recover_bag,
)
from cloe_ros.io.writer import BagWriter

FLUSH_EVERY = 4


def pose(k: int) -> bytes:
    return encode_pose_stamped(
        PoseSample(k, 'world', np.array([float(k), 2.0 * k, 1.0]), np.array([0, 0, 0, 1.0]))
    )


def odometry(k: int) -> bytes:
    z3 = np.zeros(3)
    return encode_odometry(
        OdometrySample(k, 'world', 'body', np.array([k, 0, 0.0]), np.array([0, 0, 0, 1.0]), z3, z3)
    )


def write_flushed_bag(bag: Path, compression: str, n: int = 16):
    """A bag flushed every FLUSH_EVERY messages; (the complete file, the unfinished file as it
    was on disk before close(), [(topic, log time, data), ...] written)."""
    written = []
    w = BagWriter(bag, compression)
    w.add_topic('/reference', POSE_STAMPED)
    w.add_topic('/odom', ODOMETRY)
    for k in range(n):
        topic, data = ('/odom', odometry(k)) if k % 8 == 7 else ('/reference', pose(k))
        w.write(topic, 1_000 + k, data)
        written.append((topic, 1_000 + k, data))
        if (k + 1) % FLUSH_EVERY == 0:
            w.flush()
    unfinished = bag.parent / f'{bag.name}_unfinished.mcap'
    shutil.copy(bag / f'{bag.name}.mcap', unfinished)
    w.close()
    return bag / f'{bag.name}.mcap', unfinished, written


def scan(source: Path | bytes):
    """The scan and its messages as (topic, log time, data); bytes are read as a file cut there."""
    s = McapScan(io.BytesIO(source) if isinstance(source, bytes) else source)
    topics = {}
    out = []
    for rec in s:
        if hasattr(rec, 'topic'):
            topics[rec.id] = rec.topic
        elif isinstance(rec, McapMessage):
            out.append((topics[rec.channel_id], rec.log_time, rec.data))
    return s, out


def chunk_ends(mcap_file: Path) -> list[int]:
    """End offsets of the chunks, from mcap's own reader (the summary of the complete file)."""
    with mcap_file.open('rb') as fh:
        summary = make_reader(fh).get_summary()
    return sorted(c.chunk_start_offset + c.chunk_length for c in summary.chunk_indexes)


def message_record_ends(content: bytes, written, channel_ids) -> list[int]:
    """Where each written message's record ends in an uncompressed MCAP file (spec layout:
    opcode 0x05, u64 length, u16 channel, u32 sequence, u64 log time, u64 publish time, data)."""
    ends = []
    for topic, t, data in written:
        rec = struct.pack('<BQHIQQ', 0x05, 22 + len(data), channel_ids[topic], 0, t, t) + data
        at = content.find(rec)
        assert at > 0 and content.find(rec, at + 1) == -1
        ends.append(at + len(rec))
    return ends


@pytest.mark.parametrize('compression', ['none', 'zstd'])
def test_cut_at_every_byte(tmp_path: Path, compression: str) -> None:
    complete, unfinished, written = write_flushed_bag(tmp_path / 'bag', compression)
    content = complete.read_bytes()
    assert unfinished.read_bytes() == content[: unfinished.stat().st_size]
    ends = chunk_ends(complete)
    assert len(ends) == len(written) // FLUSH_EVERY
    record_ends = (
        message_record_ends(content, written, {'/reference': 1, '/odom': 2})
        if compression == 'none'
        else None
    )
    previous = 0
    for offset in range(1, len(content) + 1):
        s, got = scan(content[:offset])
        # only messages that were written, in order, byte for byte
        assert got == written[: len(got)], offset
        # every message of a chunk that is fully on disk
        complete_chunks = sum(end <= offset for end in ends)
        assert len(got) >= complete_chunks * FLUSH_EVERY, offset
        if record_ends is not None:  # uncompressed: exactly the records fully on disk
            assert len(got) == sum(end <= offset for end in record_ends), offset
        assert len(got) >= previous
        previous = len(got)
        assert s.complete == (offset == len(content))
        assert 0 <= s.end <= offset and s.reason
    assert previous == len(written)


def test_empty_and_foreign_files_are_refused_with_a_reason(tmp_path: Path) -> None:
    (tmp_path / 'empty').mkdir()
    (tmp_path / 'empty' / 'empty.mcap').write_bytes(b'')
    with pytest.raises(RecoverError, match='is empty'):
        recover_bag(tmp_path / 'empty')
    (tmp_path / 'text').mkdir()
    (tmp_path / 'text' / 'x.mcap').write_text('hello, not a bag\n')
    with pytest.raises(RecoverError, match='not an MCAP file'):
        recover_bag(tmp_path / 'text')
    (tmp_path / 'nomcap').mkdir()
    (tmp_path / 'nomcap' / 'bag_0.db3').write_bytes(b'')
    with pytest.raises(RecoverError, match=r'no \.mcap file .*SQLite3'):
        recover_bag(tmp_path / 'nomcap')
    with pytest.raises(RecoverError, match='does not exist'):
        recover_bag(tmp_path / 'missing')
    (tmp_path / 'notes.txt').write_text('x')
    with pytest.raises(RecoverError, match=r'neither a bag directory nor an \.mcap file'):
        recover_bag(tmp_path / 'notes.txt')
    # nothing was created for the refused inputs
    assert not any(p.name.endswith('_recovered') for p in tmp_path.iterdir())


@pytest.mark.parametrize('compression', ['none', 'zstd'])
def test_recovered_bag_is_complete_for_many_cuts(tmp_path: Path, compression: str) -> None:
    complete, _, _ = write_flushed_bag(tmp_path / 'bag', compression)
    content = complete.read_bytes()
    for i, offset in enumerate([9, 40, *range(100, len(content), 293), len(content)]):
        src = tmp_path / f'src{i}'
        src.mkdir()
        (src / 'src.mcap').write_bytes(content[:offset])
        s, expected = scan(src / 'src.mcap')
        if not s.channels:  # not even a topic: an error, and no output
            with pytest.raises(RecoverError, match='nothing to recover'):
                recover_bag(src, compression=compression)
            assert not (tmp_path / f'src{i}_recovered').exists()
            continue
        report = recover_bag(src, compression=compression)
        assert report.output == tmp_path / f'src{i}_recovered'
        assert report.message_count == len(expected)
        assert report.files[0].complete == (offset == len(content))
        with (report.output / f'{report.output.name}.mcap').open('rb') as fh:
            reader = make_reader(fh, decoder_factories=[DecoderFactory()])
            got = [(c.topic, m.log_time, m.data) for _, c, m in reader.iter_messages()]
        assert sorted(got, key=lambda x: x[1]) == expected
        if expected:
            with AnyReader([report.output]) as reader:
                counts = {c.topic: c.msgcount for c in reader.connections}
                assert sum(counts.values()) == len(expected)
                types = {c.topic: c.msgtype for c in reader.connections}
                assert types == {'/reference': POSE_STAMPED, '/odom': ODOMETRY}
                for conn, _, raw in reader.messages():
                    msg = reader.deserialize(raw, conn.msgtype)
                    k = msg.header.stamp.nanosec
                    if conn.topic == '/reference':
                        assert (msg.pose.position.x, msg.pose.position.y) == (k, 2.0 * k)
                    else:
                        assert msg.pose.pose.position.x == k
        # the source is never modified
        assert (src / 'src.mcap').read_bytes() == content[:offset]


def test_zero_filled_and_garbage_tails_stop_cleanly(tmp_path: Path) -> None:
    _, unfinished, written = write_flushed_bag(tmp_path / 'bag', 'zstd')
    n = len(scan(unfinished)[1])
    assert n == len(written)
    good = unfinished.read_bytes()
    zeros = tmp_path / 'zeros.mcap'
    zeros.write_bytes(good + bytes(4096))
    s, got = scan(zeros)
    assert got == written and 'zero bytes' in s.reason and s.end == len(good)
    rng = random.Random(7)
    for trial in range(50):
        junk = tmp_path / f'junk{trial}.mcap'
        junk.write_bytes(good + rng.randbytes(rng.randrange(1, 3000)))
        s, got = scan(junk)  # must not raise
        assert got[:n] == written
        assert not s.complete


def chunk_starts(mcap_file: Path) -> list[int]:
    """Start offsets of the chunks, from mcap's own reader."""
    with mcap_file.open('rb') as fh:
        summary = make_reader(fh).get_summary()
    return sorted(c.chunk_start_offset for c in summary.chunk_indexes)


def read_back(bag: Path) -> list[tuple[str, int, bytes]]:
    """The messages of a bag as mcap's own reader gives them, in file order."""
    with next(bag.glob('*.mcap')).open('rb') as fh:
        reader = make_reader(fh, decoder_factories=[DecoderFactory()])
        return [(c.topic, m.log_time, m.data) for _, c, m in reader.iter_messages()]


@pytest.mark.parametrize('compression', ['none', 'zstd'])
def test_a_damaged_chunk_header_is_stepped_over(tmp_path: Path, compression: str) -> None:
    """Bytes flipped in the header of the third chunk (compression name and data length). The
    chunk's record length still leads to the message index after it: the chunk is reported and
    stepped over, every other chunk read. With the summary (a complete file) the chunk itself is
    read with the summary's chunk index instead of its header."""
    complete, unfinished, written = write_flushed_bag(tmp_path / 'bag', compression)
    third = chunk_starts(complete)[2]
    lost = set(range(2 * FLUSH_EVERY, 3 * FLUSH_EVERY))
    for source, kept in ((unfinished, False), (complete, True)):
        content = bytearray(source.read_bytes())
        flip = third + 9 + 28  # opcode, length; start, end, uncompressed size, crc
        n = 4 + len(compression.replace('none', '')) + 8  # name length, name, data length
        content[flip : flip + n] = bytes(b ^ 0xFF for b in content[flip : flip + n])
        src = tmp_path / f'src_{kept}'
        src.mkdir()
        (src / 'src.mcap').write_bytes(bytes(content))
        s, got = scan(src / 'src.mcap')
        want = written if kept else [m for k, m in enumerate(written) if k not in lost]
        assert got == want
        assert s.complete == kept
        (skip,) = s.skipped
        assert (skip.offset, skip.what) == (third, 'Chunk')
        assert skip.length == chunk_ends(complete)[2] - third
        assert (skip.kept, skip.lost) == ((FLUSH_EVERY, 0) if kept else (0, FLUSH_EVERY))
        report = recover_bag(src)
        assert report.damaged and report.message_count == len(want)
        assert read_back(report.output) == want
        assert f'damaged Chunk at byte {third} ({skip.length} bytes): corrupt Chunk' in (
            '\n'.join(report.lines())
        )


def test_damaged_records_inside_an_uncompressed_chunk(tmp_path: Path) -> None:
    """Uncompressed chunks are the bytes on disk: a damaged message record costs that message
    only, the others are found where the message index after the chunk puts them. A message
    moved to another channel (the records still parse) contradicts the index: found too."""
    _, unfinished, written = write_flushed_bag(tmp_path / 'bag', 'none')
    content = unfinished.read_bytes()
    channel_ids = {'/reference': 1, '/odom': 2}
    ends = message_record_ends(content, written, channel_ids)
    starts = [end - 31 - len(data) for end, (_, _, data) in zip(ends, written)]
    assert all(content[at] == 0x05 for at in starts)
    opcode = bytearray(content)
    opcode[starts[9]] = 0  # the second message of the third chunk: no record any more
    channel = bytearray(content)
    assert written[5][0] == '/reference'
    struct.pack_into('<H', channel, starts[5] + 9, channel_ids['/odom'])
    for damaged, k in ((opcode, 9), (channel, 5)):
        s, got = scan(bytes(damaged))
        assert got == written[:k] + written[k + 1 :]
        (skip,) = s.skipped
        assert (skip.kept, skip.lost) == (FLUSH_EVERY - 1, 1)
        assert skip.offset == max(c for c in chunk_starts_of(content) if c < starts[k])


def chunk_starts_of(content: bytes) -> list[int]:
    """Chunk offsets of an MCAP file without summary, walking its top-level records."""
    out, pos = [], 8
    while pos + 9 <= len(content):
        op, length = struct.unpack_from('<BQ', content, pos)
        if op == 0x06:
            out.append(pos)
        pos += 9 + length
    return out


def test_a_compressed_chunk_contradicting_its_index_is_left_out(tmp_path: Path) -> None:
    """A zstd chunk that decompresses and parses, but a message moved to another channel: past
    the damage its bytes cannot be trusted, the chunk is left out whole and said so."""
    _, unfinished, written = write_flushed_bag(tmp_path / 'bag', 'zstd')
    content = unfinished.read_bytes()
    second = chunk_starts_of(content)[1]
    (length,) = struct.unpack_from('<Q', content, second + 1)
    body = content[second + 9 : second + 9 + length]
    head = body[: 28 + 4 + 4 + 8]
    assert head[28:36] == struct.pack('<I', 4) + b'zstd'
    records = bytearray(zstandard.ZstdDecompressor().decompress(body[len(head) :]))
    at = records.index(struct.pack('<BQ', 0x05, 22 + len(written[4][2])) + b'\x01\x00')
    struct.pack_into('<H', records, at + 9, 2)  # /reference -> /odom
    data = zstandard.ZstdCompressor().compress(bytes(records))
    body = head[:36] + struct.pack('<Q', len(data)) + data
    damaged = content[:second] + struct.pack('<BQ', 0x06, len(body)) + body
    damaged += content[second + 9 + length :]
    s, got = scan(damaged)
    assert got == written[:FLUSH_EVERY] + written[2 * FLUSH_EVERY :]
    (skip,) = s.skipped
    assert (skip.offset, skip.kept, skip.lost) == (second, 0, FLUSH_EVERY)
    assert 'differ from the message index' in skip.reason


def test_unreadable_chunk_length_resumes_at_the_next_chunk_of_the_summary(tmp_path: Path) -> None:
    """The first chunk's length overruns the file and its first record is zeroed: its end is
    unknown and it cannot be read with the summary's chunk index either. Reading goes on at the
    next chunk the summary lists; the channels declared in the lost chunk come from the
    summary."""
    complete, _, written = write_flushed_bag(tmp_path / 'bag', 'none')
    content = bytearray(complete.read_bytes())
    first = chunk_starts(complete)[0]
    struct.pack_into('<Q', content, first + 1, 2**60)
    content[first + 9 + 40] = 0  # the first record inside the (uncompressed) chunk
    s, got = scan(bytes(content))
    assert got == written[FLUSH_EVERY:]
    assert s.complete
    (skip,) = s.skipped
    assert (skip.offset, skip.lost) == (first, None)
    assert skip.offset + skip.length == chunk_starts(complete)[1]


@pytest.mark.parametrize('compression', ['none', 'zstd'])
def test_zero_filled_tail_keeps_what_a_cut_keeps(tmp_path: Path, compression: str) -> None:
    """A file whose end was never written but is there, full of zeros (its length kept): the last
    chunk's length fits in the file, yet its complete messages are kept as if the file were cut
    where the zeros start (a message reaching into them may have zeros that were never its
    bytes)."""
    bag = tmp_path / 'bag'
    rng = np.random.default_rng(3)
    with BagWriter(bag, compression) as w:
        w.add_topic('/reference', POSE_STAMPED)
        for k in range(3000):  # random positions: a zstd chunk of several blocks
            data = encode_pose_stamped(
                PoseSample(k, 'world', rng.normal(size=3), np.array([0, 0, 0, 1.0]))
            )
            w.write('/reference', 1_000 + k, data)
        w.flush()
        content = (bag / 'bag.mcap').read_bytes()
    (start,) = chunk_starts_of(content)
    end = start + 9 + struct.unpack_from('<Q', content, start + 1)[0]
    most = 0
    for cut in reversed(range(start + 100, end, (end - start) // 7)):
        _, want = scan(content[:cut].rstrip(b'\0'))
        s, got = scan(content[:cut] + bytes(len(content) - cut))
        assert got == want, cut
        assert s.damaged_tail and not s.skipped and s.end == start
        assert s.partial_chunk_messages == len(want)
        most = max(most, len(want))
    assert most > 1000


def test_nothing_to_recover_is_an_error_without_output(tmp_path: Path, capsys) -> None:
    complete, _, _ = write_flushed_bag(tmp_path / 'bag', 'zstd')
    content = complete.read_bytes()
    for cut in (5, 8, 100):
        src = tmp_path / f'cut{cut}'
        src.mkdir()
        (src / 'cut.mcap').write_bytes(content[:cut])
        with pytest.raises(RecoverError, match=r'nothing to recover .*no output written'):
            recover_bag(src)
        assert not default_output(src).exists()
    assert cloe(['bag', 'recover', str(tmp_path / 'cut100')]) == 1
    assert 'nothing to recover' in capsys.readouterr().err
    assert not default_output(tmp_path / 'cut100').exists()


def test_a_bag_whose_only_chunk_is_damaged_recovers_nothing_and_says_so(tmp_path: Path) -> None:
    """One zstd chunk, a bit flipped inside its compressed data (its CRC no longer matches): the
    chunk is left out, which leaves the topics without a message. That used to write an empty bag
    with status 0; it is an error naming the bag, and no output."""
    bag = tmp_path / 'one_chunk'
    with BagWriter(bag, 'zstd') as w:
        w.add_topic('/reference', POSE_STAMPED)
        w.add_topic('/odom', ODOMETRY)
        for k in range(40):
            w.write('/reference', 1_000 + k, pose(k))
            w.write('/odom', 1_000 + k, odometry(k))
    file = bag / 'one_chunk.mcap'
    content = bytearray(file.read_bytes())
    (start,) = chunk_starts(file)
    content[start + 9 + 100] ^= 0x10  # inside the compressed records
    file.write_bytes(bytes(content))
    with pytest.raises(RecoverError, match=r'nothing to recover .*no message of its 2 topic'):
        recover_bag(bag)
    assert not default_output(bag).exists()


def test_opcode_0x10_is_not_a_record(tmp_path: Path) -> None:
    """The MCAP specification defines opcodes 0x01-0x0F; 0x10 is no record."""
    _, unfinished, written = write_flushed_bag(tmp_path / 'bag', 'none')
    s, got = scan(unfinished.read_bytes() + struct.pack('<BQ', 0x10, 0))
    assert got == written
    assert 'invalid opcode 0x10' in s.reason


@pytest.mark.parametrize(
    ('compression', 'chunked'),
    [(CompressionType.LZ4, True), (CompressionType.ZSTD, True), (CompressionType.NONE, False)],
)
def test_files_of_another_writer(tmp_path: Path, compression, chunked: bool) -> None:
    """MCAP files written by the mcap library: chunked (lz4, zstd) and unchunked records."""
    path = tmp_path / 'other.mcap'
    written = []
    with path.open('wb') as fh:
        w = McapLibWriter(fh, chunk_size=600, compression=compression, use_chunking=chunked)
        w.start(profile='ros2', library='test')
        msgdef = TYPESTORE.generate_msgdef(POSE_STAMPED)[0]
        sid = w.register_schema(POSE_STAMPED, 'ros2msg', msgdef.encode())
        cid = w.register_channel('/reference', 'cdr', sid)
        for k in range(30):
            w.add_message(cid, log_time=10 + k, data=pose(k), publish_time=10 + k)
            written.append(('/reference', 10 + k, pose(k)))
        w.finish()
    content = path.read_bytes()
    for offset in range(1, len(content) + 1):
        _, got = scan(content[:offset])
        assert got == written[: len(got)], offset
    s, got = scan(path)
    assert s.complete and got == written
    # recover a cut file and read it back
    src = tmp_path / 'src'
    src.mkdir()
    (summary_start,) = struct.unpack_from('<Q', content, len(content) - 8 - 20)
    (src / 'a.mcap').write_bytes(content[: summary_start // 2])
    report = recover_bag(src, tmp_path / 'out')
    assert 0 < report.message_count < 30
    with AnyReader([tmp_path / 'out']) as reader:
        got = [decode_pose_stamped(raw).position[0] for _, _, raw in reader.messages()]
    assert got == [float(k) for k in range(report.message_count)]


def test_offered_qos_and_schemas_are_kept(tmp_path: Path) -> None:
    qos = Qos(
        QosHistory.KEEP_LAST,
        7,
        QosReliability.RELIABLE,
        QosDurability.TRANSIENT_LOCAL,
        QosTime(0, 0),
        QosTime(0, 0),
        QosLiveliness.AUTOMATIC,
        QosTime(0, 0),
        False,
    )
    bag = tmp_path / 'bag'
    w = BagWriter(bag)
    w.add_topic('/reference', POSE_STAMPED, [qos])
    w.write('/reference', 5, pose(1))
    w.flush()
    # simulate the kill: drop the writer without closing it
    report = recover_bag(bag)
    assert report.output == tmp_path / 'bag_recovered' == default_output(bag)
    with AnyReader([report.output]) as reader:
        (conn,) = reader.connections
        assert conn.ext.offered_qos_profiles == [qos]
        assert conn.digest == TYPESTORE.hash_rihs01(POSE_STAMPED)
    w.close()


def test_output_is_never_overwritten(tmp_path: Path) -> None:
    write_flushed_bag(tmp_path / 'bag', 'zstd')
    (tmp_path / 'bag_recovered').mkdir()
    (tmp_path / 'bag_recovered' / 'keep').write_text('mine')
    with pytest.raises(RecoverError, match='exists already, not overwriting'):
        recover_bag(tmp_path / 'bag')
    assert (tmp_path / 'bag_recovered' / 'keep').read_text() == 'mine'


def test_cli_recover_and_info(tmp_path: Path, capsys) -> None:
    complete, _, written = write_flushed_bag(tmp_path / 'bag', 'zstd')
    dead = tmp_path / 'dead'
    dead.mkdir()
    content = complete.read_bytes()
    cut_at = chunk_ends(complete)[2] + 5  # inside the message index after the third chunk
    (dead / 'dead.mcap').write_bytes(content[:cut_at])

    assert cloe(['bag', 'info', str(dead)]) == 1
    assert 'cloe bag recover' in capsys.readouterr().err

    assert cloe(['bag', 'recover', str(dead), '-o', str(tmp_path / 'fixed')]) == 0
    out = capsys.readouterr().out
    n = 3 * FLUSH_EVERY
    n_odom = sum(t == '/odom' for t, _, _ in written[:n])
    assert f'/reference  geometry_msgs/msg/PoseStamped  {n - n_odom} messages' in out
    assert f'/odom       nav_msgs/msg/Odometry          {n_odom} messages' in out
    assert f'incomplete, {chunk_ends(complete)[2]} of {cut_at} bytes usable' in out
    assert f'recovered {n} messages into {tmp_path / "fixed"}' in out

    assert cloe(['bag', 'info', str(tmp_path / 'fixed')]) == 0
    out = capsys.readouterr().out
    assert f'messages:  {n}' in out
    assert 'duration:  0.000 s' in out  # log times 1000 ns .. 1015 ns
    info = bag_info(tmp_path / 'fixed')
    assert (info.start_ns, info.end_ns, info.message_count) == (1000, 1000 + n - 1, n)
    assert {t.topic: t.count for t in info.topics} == {'/reference': n - n_odom, '/odom': n_odom}

    assert cloe(['bag', 'recover', str(dead), '-o', str(tmp_path / 'fixed')]) == 1
    assert 'ERROR:' in capsys.readouterr().err
    assert cloe(['bag', 'recover', str(tmp_path / 'nothing')]) == 1
    err = capsys.readouterr().err
    assert err.startswith('ERROR:') and 'does not exist' in err
