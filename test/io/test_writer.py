"""BagWriter: round trips read back by independent readers (mcap + mcap_ros2, rosbags AnyReader).

The durability claim is tested on the bytes of the file: a copy taken after ``flush()`` and before
``close()`` holds every message written so far (read with mcap's stream reader, which stops where
the file ends), a copy taken before ``flush()`` holds none of the pending chunk.
"""

from __future__ import annotations

import errno
import io
import os
import shutil
import sys
import zlib
from pathlib import Path

import numpy as np
import pytest
import yaml
from mcap.exceptions import EndOfFile
from mcap.reader import make_reader
from mcap.records import Channel, Chunk, DataEnd, Footer, Message
from mcap.stream_reader import StreamReader
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
from rosbags.rosbag2 import Reader as RosbagsReader

from cloe_ros.core.samples import OdometrySample, PoseSample
from cloe_ros.io import messages
from cloe_ros.io.messages import (
    ODOMETRY,
    POSE_STAMPED,
    decode_odometry,
    decode_pose_stamped,
    encode_odometry,
    encode_pose_stamped,
)
from cloe_ros.io.msgdefs import MSGDEFS
from cloe_ros.io.writer import BagWriter, WriterError

QOS = Qos(
    QosHistory.KEEP_LAST,
    10,
    QosReliability.BEST_EFFORT,
    QosDurability.VOLATILE,
    QosTime(9223372036, 854775807),
    QosTime(9223372036, 854775807),
    QosLiveliness.AUTOMATIC,
    QosTime(9223372036, 854775807),
    False,
)


def odometry(k: int) -> bytes:
    return encode_odometry(
        OdometrySample(
            stamp_ns=k * 10_000_000,
            frame_id='world',
            child_frame_id='body',
            position=np.array([0.5 * k, -1.0, 2.0]),
            orientation=np.array([0.0, 0.0, 0.0, 1.0]),
            linear=np.array([k, 0.0, 0.0]),
            angular=np.array([0.0, 0.0, 0.01 * k]),
        )
    )


def pose(k: int) -> bytes:
    return encode_pose_stamped(
        PoseSample(
            k * 100_000_000,
            'world',
            np.array([0.0, float(k), 1.0]),
            np.array([0.0, 0.0, 0.0, 1.0]),
        )
    )


def write_sample_bag(path: Path, compression: str, n: int = 40) -> dict[str, list[int]]:
    """``n`` odometry and ``n // 4`` poses; returns the log times written per topic."""
    times: dict[str, list[int]] = {'/odom': [], '/reference': []}
    with BagWriter(path, compression) as w:
        w.add_topic('/odom', ODOMETRY, [QOS])
        w.add_topic('/reference', POSE_STAMPED)
        for k in range(n):
            t = 1_000_000_000 + k * 10_000_000
            w.write('/odom', t, odometry(k))
            times['/odom'].append(t)
            if k % 4 == 0:
                w.write('/reference', t + 1, pose(k // 4))
                times['/reference'].append(t + 1)
    return times


def stream_messages(mcap_file: Path) -> list[tuple[str, int, bytes]]:
    """(topic, log time, data) of every message mcap's stream reader finds before the file ends."""
    channels: dict[int, str] = {}
    out = []
    with mcap_file.open('rb') as fh:
        try:
            for rec in StreamReader(fh, skip_magic=False).records:
                if isinstance(rec, Channel):
                    channels[rec.id] = rec.topic
                elif isinstance(rec, Message):
                    out.append((channels[rec.channel_id], rec.log_time, rec.data))
        except EndOfFile:
            pass
    return out


@pytest.mark.parametrize('compression', ['zstd', 'none'])
def test_round_trip_is_read_back_by_mcap_and_rosbags(tmp_path: Path, compression: str) -> None:
    bag = tmp_path / 'bag'
    times = write_sample_bag(bag, compression)
    assert (bag / 'metadata.yaml').is_file()
    mcap_file = bag / 'bag.mcap'

    # independent reader: mcap + mcap_ros2 decoding from the embedded schemas
    with mcap_file.open('rb') as fh:
        reader = make_reader(fh, decoder_factories=[DecoderFactory()])
        summary = reader.get_summary()
        assert summary is not None and summary.statistics.message_count == 50
        chunk_compressions = {c.compression for c in summary.chunk_indexes}
        assert chunk_compressions == ({'zstd'} if compression == 'zstd' else {''})
        odom, ref = [], []
        for schema, channel, message, decoded in reader.iter_decoded_messages():
            assert channel.message_encoding == 'cdr'
            if channel.topic == '/odom':
                assert schema.name == ODOMETRY
                odom.append((message.log_time, decoded))
            else:
                assert (channel.topic, schema.name) == ('/reference', POSE_STAMPED)
                ref.append((message.log_time, decoded))
    assert [t for t, _ in odom] == times['/odom']
    assert [t for t, _ in ref] == times['/reference']
    for k, (_, msg) in enumerate(odom):
        assert msg.pose.pose.position.x == 0.5 * k
        assert msg.twist.twist.angular.z == pytest.approx(0.01 * k)
        assert (msg.header.frame_id, msg.child_frame_id) == ('world', 'body')
    assert [m.pose.position.y for _, m in ref] == [float(k) for k in range(10)]

    # rosbags: metadata, types, counts, QoS and the same messages
    with AnyReader([bag]) as reader:
        assert {c.topic: (c.msgtype, c.msgcount) for c in reader.connections} == {
            '/odom': (ODOMETRY, 40),
            '/reference': (POSE_STAMPED, 10),
        }
        conn = next(c for c in reader.connections if c.topic == '/odom')
        assert conn.ext.offered_qos_profiles == [QOS]
        got = [(c.topic, t, bytes(raw)) for c, t, raw in reader.messages()]
    assert [
        (t, decode_odometry(raw).position[0]) for topic, t, raw in got if topic == '/odom'
    ] == [(t, 0.5 * k) for k, t in enumerate(times['/odom'])]
    assert [decode_pose_stamped(raw).position[1] for topic, _, raw in got if topic != '/odom'] == [
        float(k) for k in range(10)
    ]


@pytest.mark.parametrize('compression', ['zstd', 'none'])
def test_bags_carry_mcap_crcs(tmp_path: Path, compression: str) -> None:
    """Every chunk has the CRC of its records, the data section its CRC in DataEnd, the summary
    its CRC in the footer; the mcap library's reader validates them (rosbags wrote none)."""
    bag = tmp_path / 'bag'
    write_sample_bag(bag, compression, n=6000)  # several chunks
    mcap_file = bag / 'bag.mcap'
    content = mcap_file.read_bytes()
    with mcap_file.open('rb') as fh:
        records = list(StreamReader(fh, emit_chunks=True, validate_crcs=True).records)
    chunks = [r for r in records if isinstance(r, Chunk)]
    assert len(chunks) >= 2
    assert all(c.uncompressed_crc != 0 for c in chunks)
    (data_end,) = [r for r in records if isinstance(r, DataEnd)]
    (footer,) = [r for r in records if isinstance(r, Footer)]
    # independently: the DataEnd record (13 bytes) sits right before the summary
    assert data_end.data_section_crc == zlib.crc32(content[: footer.summary_start - 13])
    assert content[footer.summary_start - 13] == 0x0F
    footer_at = len(content) - 8 - 29
    assert footer.summary_crc == zlib.crc32(content[footer.summary_start : footer_at + 25])
    # the library's own checks pass: chunk CRCs on every message read, the data section CRC
    with mcap_file.open('rb') as fh:
        n = sum(1 for _ in make_reader(fh, validate_crcs=True).iter_messages())
    assert n == 6000 + 1500
    with mcap_file.open('rb') as fh:
        records = StreamReader(fh, validate_crcs=True).records
        assert sum(isinstance(r, Message) for r in records) == n


def test_metadata_says_jazzy(tmp_path: Path) -> None:
    """rosbag2 writes the distribution of the message types (rosbags wrote 'rosbags'); the file
    carries the same metadata, as rosbag2's MCAP storage does."""
    bag = tmp_path / 'bag'
    write_sample_bag(bag, 'zstd', n=4)
    meta = yaml.safe_load((bag / 'metadata.yaml').read_text())['rosbag2_bagfile_information']
    assert (meta['ros_distro'], meta['version']) == ('jazzy', 9)
    assert meta['storage_identifier'] == 'mcap'
    assert meta['message_count'] == 5
    with RosbagsReader(bag) as reader:
        assert reader.ros_distro == 'jazzy'
    with (bag / 'bag.mcap').open('rb') as fh:
        reader = make_reader(fh)
        assert reader.get_header().profile == 'ros2'
        (record,) = list(reader.iter_metadata())
    assert record.name == 'rosbag2'
    inner = yaml.safe_load(record.metadata['serialized_metadata'])
    assert inner == meta


def test_counts_and_properties(tmp_path: Path) -> None:
    with BagWriter(tmp_path / 'b') as w:
        w.add_topic('/odom', ODOMETRY)
        w.add_topic('/odom', ODOMETRY)  # idempotent
        w.add_topic('/reference', POSE_STAMPED, '')
        for k in range(3):
            w.write('/odom', k, odometry(k))
        w.write('/reference', 5, pose(0))
        assert w.message_count == 4
        assert w.topic_counts == {'/odom': 3, '/reference': 1}
        assert w.topics == {'/odom': ODOMETRY, '/reference': POSE_STAMPED}
        assert w.payload_bytes == sum(len(odometry(k)) for k in range(3)) + len(pose(0))
    assert w.closed
    w.close()  # idempotent


def test_flush_makes_written_messages_survive_a_kill(tmp_path: Path) -> None:
    bag = tmp_path / 'bag'
    w = BagWriter(bag)
    w.add_topic('/odom', ODOMETRY)
    for k in range(20):
        w.write('/odom', 1000 + k, odometry(k))
    before_flush = tmp_path / 'before.mcap'
    shutil.copy(bag / 'bag.mcap', before_flush)
    w.flush()
    flush1 = w.chunk_count
    after_flush = tmp_path / 'after.mcap'
    shutil.copy(bag / 'bag.mcap', after_flush)
    for k in range(20, 30):
        w.write('/odom', 1000 + k, odometry(k))
    w.flush()
    w.flush()  # nothing pending: no empty chunk
    assert (flush1, w.chunk_count) == (1, 2)
    after_second = tmp_path / 'second.mcap'
    shutil.copy(bag / 'bag.mcap', after_second)
    w.close()

    assert stream_messages(before_flush) == []  # the chunk was still in memory
    got = stream_messages(after_flush)
    assert [(t, data) for _, t, data in got] == [(1000 + k, odometry(k)) for k in range(20)]
    assert len(stream_messages(after_second)) == 30
    assert not (tmp_path / 'metadata.yaml').exists()
    # the completed bag holds the same messages
    assert len(stream_messages(bag / 'bag.mcap')) == 30


def test_refuses_an_existing_path(tmp_path: Path) -> None:
    (tmp_path / 'bag').mkdir()
    with pytest.raises(WriterError, match=r'bag exists already, not overwriting\.'):
        BagWriter(tmp_path / 'bag')
    (tmp_path / 'file').write_text('x')
    with pytest.raises(WriterError, match='exists already'):
        BagWriter(tmp_path / 'file')
    assert (tmp_path / 'file').read_text() == 'x'


def test_unknown_and_conflicting_types(tmp_path: Path) -> None:
    with BagWriter(tmp_path / 'b') as w:
        with pytest.raises(WriterError, match='my_pkg/msg/Thing'):
            w.add_topic('/thing', 'my_pkg/msg/Thing')
        w.add_topic('/odom', ODOMETRY)
        with pytest.raises(WriterError, match='/odom is recorded as nav_msgs/msg/Odometry'):
            w.add_topic('/odom', POSE_STAMPED)
        with pytest.raises(WriterError, match='add_topic'):
            w.write('/thing', 0, b'')
        with pytest.raises(WriterError, match='offered QoS'):
            w.add_topic('/x', POSE_STAMPED, [1, 2])
        w.write('/odom', 1, odometry(1))
    with pytest.raises(WriterError, match='closed'):
        w.write('/odom', 2, odometry(2))
    w.flush()  # closed: nothing to flush, no error
    with AnyReader([tmp_path / 'b']) as reader:
        assert [c.topic for c in reader.connections] == ['/odom']


def test_bad_compression_is_refused_before_creating_anything(tmp_path: Path) -> None:
    with pytest.raises(WriterError, match='compression must be one of zstd, none'):
        BagWriter(tmp_path / 'b', 'lz4')
    assert not (tmp_path / 'b').exists()


def test_every_chunk_written_is_counted(tmp_path: Path) -> None:
    with BagWriter(tmp_path / 'b', 'none') as w:
        w.add_topic('/odom', ODOMETRY)
        for k in range(4):  # 1.2 MB: rosbags writes the chunk on reaching 1 MiB
            w.write('/odom', k, bytes(300_000))
        assert w.chunk_count == 1
        w.write('/odom', 4, odometry(4))
        w.flush()
        assert w.chunk_count == 2
    assert len(stream_messages(tmp_path / 'b' / 'b.mcap')) == 5


class SmallDisk(io.FileIO):
    """A file on a disk with ``room`` bytes: writes beyond fail with ENOSPC, as on a full disk
    (a partial write first, then the error)."""

    room = 1 << 40

    def write(self, data) -> int:
        free = self.room - self.tell()
        if free <= 0:
            raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC))
        return super().write(memoryview(data)[:free])


def test_a_write_failure_stops_the_writer(tmp_path: Path, monkeypatch) -> None:
    """A full disk: the writer stops at the first failed write, keeps nothing in memory, counts
    the messages that reached the file, and close() says the bag is not finished."""
    disk: list[SmallDisk] = []
    path_open = Path.open

    def small_disk_open(self, mode='r', *args, **kwargs):
        if self.suffix != '.mcap':
            return path_open(self, mode, *args, **kwargs)
        disk.append(SmallDisk(self, mode.replace('b', '')))
        return io.BufferedWriter(disk[-1])

    monkeypatch.setattr(Path, 'open', small_disk_open)
    bag = tmp_path / 'bag'
    w = BagWriter(bag, 'none')
    monkeypatch.undo()
    w.add_topic('/odom', ODOMETRY, [QOS])
    for k in range(20):
        w.write('/odom', 1000 + k, odometry(k))
    w.flush()
    disk[0].room = disk[0].tell() + 1000  # the disk fills up
    for k in range(20, 40):
        w.write('/odom', 1000 + k, odometry(k))
    with pytest.raises(WriterError, match='No space left on device'):
        w.flush()
    assert 'No space left on device' in w.error
    assert (w.message_count, w.topic_counts) == (20, {'/odom': 20})  # what reached the file
    assert disk[0].closed  # given up: later messages are refused, not buffered
    for k in range(40, 50):
        with pytest.raises(WriterError, match=r'failed already: .*No space left'):
            w.write('/odom', 1000 + k, odometry(k))
    w.flush()  # nothing to flush
    with pytest.raises(WriterError, match=r'cannot finish bag .*No space left.*cloe bag recover'):
        w.close()
    assert w.closed and w.message_count == 20
    w.close()  # idempotent
    assert not (bag / 'metadata.yaml').exists()
    got = stream_messages(bag / 'bag.mcap')
    assert [(t, data) for _, t, data in got] == [(1000 + k, odometry(k)) for k in range(20)]


def test_offered_qos_of_later_publishers_go_into_the_metadata(tmp_path: Path) -> None:
    reliable = QOS._replace(reliability=QosReliability.RELIABLE)
    with BagWriter(tmp_path / 'b') as w:
        w.add_topic('/odom', ODOMETRY, [QOS])
        w.write('/odom', 1, odometry(1))
        w.add_offered_qos('/odom', [QOS, reliable])  # QOS is there already
        with pytest.raises(WriterError, match='add_topic'):
            w.add_offered_qos('/other', [QOS])
    with AnyReader([tmp_path / 'b']) as reader:
        (conn,) = reader.connections
        assert conn.ext.offered_qos_profiles == [QOS, reliable]


def test_the_stored_definitions_are_rosbags():
    """io/msgdefs.py (what the writer uses for the package's own types, without rosbags' type
    store) is what scripts/make_msgdefs.py writes from the type store now."""
    sys.path.insert(0, str(Path(__file__).resolve().parents[2] / 'scripts'))
    import make_msgdefs

    assert make_msgdefs.render() == Path(make_msgdefs.OUT).read_text(), (
        'cloe_ros/io/msgdefs.py is out of date: run python scripts/make_msgdefs.py'
    )
    store = messages.TYPESTORE
    for msgtype, (text, rihs01) in MSGDEFS.items():
        assert text == store.generate_msgdef(msgtype, ros_version=2)[0]
        assert rihs01 == store.hash_rihs01(msgtype)
