"""BagReader: round trips over every storage mode, the real flights, and every broken bag a user
can hand it (each must give a BagError saying what is wrong, never a rosbags traceback)."""

from __future__ import annotations

import os
import signal
import struct
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest
import yaml
from corpus import FLIGHTS
from mcap.reader import make_reader
from rosbags.interfaces import (
    Qos,
    QosDurability,
    QosHistory,
    QosLiveliness,
    QosReliability,
    QosTime,
)
from rosbags.rosbag2 import CompressionFormat, CompressionMode, StoragePlugin, Writer

from cloe_ros.core.samples import OdometrySample, PoseSample
from cloe_ros.io.messages import (
    ODOMETRY,
    POSE_STAMPED,
    TYPESTORE,
    decode_odometry,
    decode_pose_stamped,
    encode_odometry,
    encode_pose_stamped,
)
from cloe_ros.io.reader import BagError, BagReader, TopicInfo, qos_profiles
from cloe_ros.io.writer import BagWriter

REAL = {
    'nanobench_B2_circle_medium_rep1': {'/odom': 2725, '/reference': 2527},
    'nanobench_B3_figure8_medium_rep1': {'/odom': 2476, '/reference': 2275},
}
T0 = 1_700_000_000_000_000_000
ODOM_DT = 2_000_000  # 500 Hz
REF_DT = 5_000_000  # 200 Hz


def _odom(i: int, stamp_ns: int) -> bytes:
    return encode_odometry(
        OdometrySample(
            stamp_ns=stamp_ns,
            frame_id='world',
            child_frame_id='body',
            position=np.array([i, 2.0 * i, 0.5]),
            orientation=np.array([0.0, 0.0, 0.0, 1.0]),
            linear=np.array([0.1 * i, 0.0, 0.0]),
            angular=np.array([0.0, 0.0, 0.01 * i]),
        )
    )


def _ref(i: int, stamp_ns: int) -> bytes:
    return encode_pose_stamped(
        PoseSample(stamp_ns, 'world', np.array([-i, 0.0, 1.0]), np.array([0.0, 0.0, 0.0, 1.0]))
    )


def write_bag(
    path: Path,
    n_odom: int = 3000,
    storage: StoragePlugin = StoragePlugin.MCAP,
    compression: CompressionMode = CompressionMode.NONE,
    qos: list[Qos] | None = None,
) -> list[tuple[str, int, int]]:
    """A bag with /odom (500 Hz) and /reference (200 Hz, two messages at one log time now and
    then); returns the expected ``(topic, log_ns, index)`` in log-time order. 3000 odometry
    messages (~0.7 kB each) fill more than one 1 MiB MCAP chunk."""
    expected = []
    writer = Writer(path, version=9, storage_plugin=storage)
    if compression != CompressionMode.NONE:
        writer.set_compression(compression, CompressionFormat.ZSTD)
    with writer:
        odom = writer.add_connection(
            '/odom', ODOMETRY, typestore=TYPESTORE, offered_qos_profiles=qos or ()
        )
        ref = writer.add_connection('/reference', POSE_STAMPED, typestore=TYPESTORE)
        events = [('/odom', T0 + i * ODOM_DT, i) for i in range(n_odom)]
        n_ref = n_odom * ODOM_DT // REF_DT
        events += [('/reference', T0 + (i - i % 7 // 6) * REF_DT, i) for i in range(n_ref)]
        events.sort(key=lambda e: (e[1], e[0] != '/odom', e[2]))
        for topic, log_ns, i in events:
            if topic == '/odom':
                writer.write(odom, log_ns, _odom(i, log_ns))
            else:
                writer.write(ref, log_ns, _ref(i, log_ns))
            expected.append((topic, log_ns, i))
    return expected


def check_messages(got: list[tuple[str, int, bytes]], expected: list[tuple[str, int, int]]):
    assert len(got) == len(expected)
    times = [t for _, t, _ in got]
    assert times == sorted(times)
    assert sorted((topic, t) for topic, t, _ in got) == sorted((tp, t) for tp, t, _ in expected)
    for topic in ('/odom', '/reference'):
        mine = [(t, raw) for tp, t, raw in got if tp == topic]
        want = [(t, i) for tp, t, i in expected if tp == topic]
        for (t, raw), (t_want, i) in zip(mine, want):
            assert t == t_want
            if topic == '/odom':
                sample = decode_odometry(raw)
                assert sample.position[0] == i
            else:
                sample = decode_pose_stamped(raw)
                assert sample.position[0] == -i  # per-topic recorded order kept
            assert sample.stamp_ns == t


# -- happy paths ---------------------------------------------------------------------------------


@pytest.mark.parametrize(
    ('storage', 'compression'),
    [
        (StoragePlugin.MCAP, CompressionMode.NONE),
        (StoragePlugin.MCAP, CompressionMode.STORAGE),
        (StoragePlugin.MCAP, CompressionMode.MESSAGE),
        (StoragePlugin.MCAP, CompressionMode.FILE),
        (StoragePlugin.SQLITE3, CompressionMode.NONE),
    ],
    ids=['mcap', 'mcap-chunk-zstd', 'mcap-message-zstd', 'mcap-file-zstd', 'sqlite3'],
)
def test_round_trip(tmp_path, storage, compression):
    expected = write_bag(tmp_path / 'bag', storage=storage, compression=compression)
    with BagReader(tmp_path / 'bag') as bag:
        assert bag.path == tmp_path / 'bag'
        assert bag.message_count == len(expected)
        assert bag.topics['/odom'] == TopicInfo('/odom', ODOMETRY, 3000, '')
        assert bag.topics['/reference'].count == len(expected) - 3000
        assert bag.start_ns == expected[0][1]
        assert bag.end_ns == expected[-1][1]
        assert bag.duration_s == pytest.approx((expected[-1][1] - expected[0][1]) / 1e9)
        check_messages(list(bag.messages()), expected)


def test_several_chunks(tmp_path):
    write_bag(tmp_path / 'bag')
    with open(tmp_path / 'bag' / 'bag.mcap', 'rb') as fh:
        assert len(make_reader(fh).get_summary().chunk_indexes) >= 2


def test_single_mcap_file(tmp_path):
    expected = write_bag(tmp_path / 'bag')
    with BagReader(tmp_path / 'bag' / 'bag.mcap') as bag:
        assert set(bag.topics) == {'/odom', '/reference'}
        assert bag.topics['/odom'].offered_qos == ''
        check_messages(list(bag.messages()), expected)


def test_topic_selection(tmp_path):
    expected = write_bag(tmp_path / 'bag', n_odom=500)
    with BagReader(tmp_path / 'bag') as bag:
        odom = list(bag.messages(['/odom', '/not_recorded']))
        assert [(t, s) for t, s, _ in odom] == [(t, s) for t, s, _ in expected if t == '/odom']
        assert list(bag.messages([])) == []
        assert len(list(bag.messages())) == len(expected)  # can iterate again


def test_offered_qos_as_stored(tmp_path):
    zero = QosTime(0, 0)
    qos = Qos(
        QosHistory.KEEP_LAST,
        5,
        QosReliability.BEST_EFFORT,
        QosDurability.TRANSIENT_LOCAL,
        zero,
        zero,
        QosLiveliness.AUTOMATIC,
        zero,
        False,
    )
    write_bag(tmp_path / 'bag', n_odom=10, qos=[qos])
    for path in (tmp_path / 'bag', tmp_path / 'bag' / 'bag.mcap'):
        with BagReader(path) as bag:
            assert bag.topics['/reference'].offered_qos == ''
            profiles = qos_profiles(bag.topics['/odom'].offered_qos)
            assert [(p.reliability, p.durability, p.depth) for p in profiles] == [
                (QosReliability.BEST_EFFORT, QosDurability.TRANSIENT_LOCAL, 5)
            ]


def test_empty_bag(tmp_path):
    write_bag(tmp_path / 'bag', n_odom=0)
    with BagReader(tmp_path / 'bag') as bag:
        assert bag.message_count == 0
        assert (bag.start_ns, bag.end_ns, bag.duration_s) == (0, 0, 0.0)
        assert list(bag.messages()) == []


@pytest.mark.parametrize('name', sorted(REAL))
def test_real_flight(name):
    path = FLIGHTS / name
    if not path.is_dir():
        pytest.skip(f'{path} not available')
    with BagReader(path) as bag:
        assert {k: (v.msgtype, v.count) for k, v in bag.topics.items()} == {
            '/odom': (ODOMETRY, REAL[name]['/odom']),
            '/reference': (POSE_STAMPED, REAL[name]['/reference']),
        }
        assert bag.message_count == sum(REAL[name].values())
        got = list(bag.messages())
    # independent reader: the mcap library, in the file's own order
    with open(path / f'{name}.mcap', 'rb') as fh:
        theirs = [(ch.topic, m.log_time, m.data) for _, ch, m in make_reader(fh).iter_messages()]
    assert sorted(got) == sorted(theirs)
    times = [t for _, t, _ in got]
    assert times == sorted(times)
    assert (bag.start_ns, bag.end_ns) == (times[0], times[-1])
    for topic in REAL[name]:
        assert [t for tp, t, _ in got if tp == topic] == [t for tp, t, _ in theirs if tp == topic]
    odom = [decode_odometry(raw) for topic, _, raw in got if topic == '/odom']
    assert len(odom) == REAL[name]['/odom']
    assert all(np.isfinite(s.position).all() and np.isfinite(s.linear).all() for s in odom)
    assert all(s.frame_id and s.child_frame_id for s in odom)


# -- broken bags ---------------------------------------------------------------------------------


def error_of(path: Path, read: bool = False) -> str:
    with pytest.raises(BagError) as info:
        with BagReader(path) as bag:
            if read:
                for _ in bag.messages():
                    pass
    return str(info.value)


def test_path_does_not_exist(tmp_path):
    assert error_of(tmp_path / 'nope') == f'{tmp_path / "nope"} does not exist'


def test_a_plain_file(tmp_path):
    (tmp_path / 'notes.txt').write_text('hello')
    text = error_of(tmp_path / 'notes.txt')
    assert text.startswith(f'{tmp_path / "notes.txt"} is a file, not a bag')
    assert 'metadata.yaml' in text


def test_metadata_file_instead_of_directory(tmp_path):
    write_bag(tmp_path / 'bag', n_odom=10)
    text = error_of(tmp_path / 'bag' / 'metadata.yaml')
    assert f'pass its directory {tmp_path / "bag"} instead' in text


def test_directory_without_metadata(tmp_path):
    (tmp_path / 'empty').mkdir()
    text = error_of(tmp_path / 'empty')
    assert text.startswith(f'{tmp_path / "empty"} is not a rosbag2 bag: it has no metadata.yaml')


def test_folder_of_bags(tmp_path):
    write_bag(tmp_path / 'a', n_odom=10)
    write_bag(tmp_path / 'b', n_odom=10)
    assert error_of(tmp_path).endswith('folder of bags: pass one of a, b')


def test_metadata_deleted(tmp_path):
    """A complete .mcap without metadata.yaml: it can be read as a file, and the error says so."""
    expected = write_bag(tmp_path / 'bag', n_odom=10)
    (tmp_path / 'bag' / 'metadata.yaml').unlink()
    text = error_of(tmp_path / 'bag')
    assert 'has no metadata.yaml but holds bag.mcap' in text
    assert f'pass the .mcap file itself ({tmp_path / "bag" / "bag.mcap"})' in text
    assert f'cloe bag recover {tmp_path / "bag"}' in text
    with BagReader(tmp_path / 'bag' / 'bag.mcap') as bag:
        assert len(list(bag.messages())) == len(expected)


def test_mcap_of_magic_bytes_only(tmp_path):
    write_bag(tmp_path / 'bag', n_odom=10)
    mcap = tmp_path / 'bag' / 'bag.mcap'
    mcap.write_bytes(mcap.read_bytes()[:8])
    assert error_of(tmp_path / 'bag') == (
        f'{mcap} holds the MCAP magic bytes and no record (8 bytes): nothing was recorded; '
        f'remove the bag {tmp_path / "bag"}'
    )


def test_metadata_unreadable(tmp_path):
    write_bag(tmp_path / 'bag', n_odom=10)
    meta = tmp_path / 'bag' / 'metadata.yaml'
    meta.unlink()
    meta.mkdir()  # unreadable as a file even for root
    assert error_of(tmp_path / 'bag').startswith(f'cannot read {meta}: Is a directory')


def test_metadata_binary(tmp_path):
    write_bag(tmp_path / 'bag', n_odom=10)
    meta = tmp_path / 'bag' / 'metadata.yaml'
    meta.write_bytes(b'\xff\xfe\x00garbage')
    assert error_of(tmp_path / 'bag').startswith(f'{meta} is not a text file')


def test_metadata_not_yaml(tmp_path):
    write_bag(tmp_path / 'bag', n_odom=10)
    meta = tmp_path / 'bag' / 'metadata.yaml'
    meta.write_text('rosbag2_bagfile_information: [version: 9\n')
    assert error_of(tmp_path / 'bag') == (
        f"{meta} is not valid YAML (line 2, column 1): expected ',' or ']', but got '<stream end>'"
    )


@pytest.mark.parametrize('content', ['just a string\n', 'other_tool: {version: 1}\n', ''])
def test_metadata_not_rosbag2(tmp_path, content):
    write_bag(tmp_path / 'bag', n_odom=10)
    meta = tmp_path / 'bag' / 'metadata.yaml'
    meta.write_text(content)
    assert error_of(tmp_path / 'bag') == (
        f'{meta} is not rosbag2 metadata: it has no rosbag2_bagfile_information mapping'
    )


def edit_metadata(bag: Path, edit) -> Path:
    meta = bag / 'metadata.yaml'
    dct = yaml.safe_load(meta.read_text())
    edit(dct['rosbag2_bagfile_information'])
    meta.write_text(yaml.safe_dump(dct))
    return meta


@pytest.mark.parametrize(
    ('key', 'delete'),
    [
        ('duration', lambda m: m.pop('duration')),
        ('starting_time.nanoseconds_since_epoch', lambda m: m['starting_time'].clear()),
        ('relative_file_paths', lambda m: m.pop('relative_file_paths')),
        (
            'topics_with_message_count[1].topic_metadata.type',
            lambda m: m['topics_with_message_count'][1]['topic_metadata'].pop('type'),
        ),
    ],
)
def test_metadata_missing_key(tmp_path, key, delete):
    write_bag(tmp_path / 'bag', n_odom=10)
    meta = edit_metadata(tmp_path / 'bag', delete)
    expected_key = 'duration.nanoseconds' if key == 'duration' else key
    assert error_of(tmp_path / 'bag') == (
        f'{meta} is missing the key rosbag2_bagfile_information.{expected_key}: '
        'the metadata is incomplete'
    )


def test_metadata_wrong_type(tmp_path):
    write_bag(tmp_path / 'bag', n_odom=10)
    meta = edit_metadata(tmp_path / 'bag', lambda m: m.update(message_count='many'))
    assert error_of(tmp_path / 'bag') == (
        f"{meta}: rosbag2_bagfile_information.message_count is 'many', expected int"
    )


def test_metadata_newer_version(tmp_path):
    write_bag(tmp_path / 'bag', n_odom=10)
    edit_metadata(tmp_path / 'bag', lambda m: m.update(version=10))
    assert 'rosbag2 format version 10 is newer than this reader knows' in error_of(
        tmp_path / 'bag'
    )


def test_unknown_storage(tmp_path):
    write_bag(tmp_path / 'bag', n_odom=10)
    edit_metadata(tmp_path / 'bag', lambda m: m.update(storage_identifier='hdf5'))
    assert error_of(tmp_path / 'bag').startswith(
        f"{tmp_path / 'bag'}: storage 'hdf5' is not supported (expected mcap or sqlite3)"
    )


def test_unknown_serialization_format(tmp_path):
    write_bag(tmp_path / 'bag', n_odom=10)

    def to_json(meta):
        meta['topics_with_message_count'][0]['topic_metadata']['serialization_format'] = 'json'

    edit_metadata(tmp_path / 'bag', to_json)
    assert error_of(tmp_path / 'bag') == (
        f"{tmp_path / 'bag'}: topic /odom is serialized as 'json'; only cdr (the ROS 2 default) "
        'can be read'
    )


def test_storage_file_missing(tmp_path):
    write_bag(tmp_path / 'bag', n_odom=10)
    (tmp_path / 'bag' / 'bag.mcap').unlink()
    assert error_of(tmp_path / 'bag') == (
        f'{tmp_path / "bag"}: storage file bag.mcap listed in metadata.yaml is missing '
        '(was the bag copied incompletely?)'
    )


@pytest.mark.parametrize('fraction', [0.5, 0.999, 0.0001])
def test_truncated_mcap(tmp_path, fraction):
    write_bag(tmp_path / 'bag')
    mcap = tmp_path / 'bag' / 'bag.mcap'
    data = mcap.read_bytes()
    mcap.write_bytes(data[: int(len(data) * fraction)])
    for path in (tmp_path / 'bag', mcap):
        text = error_of(path)
        assert text.startswith(f'{mcap} is truncated: it ends without the MCAP footer')
        assert f'cloe bag recover {path}' in text


def test_mcap_without_summary(tmp_path):
    """A file cut exactly where the summary starts: every chunk complete, no index, no footer."""
    write_bag(tmp_path / 'bag')
    mcap = tmp_path / 'bag' / 'bag.mcap'
    with open(mcap, 'rb') as fh:
        summary_start = make_reader(fh).get_summary().chunk_indexes[-1].chunk_start_offset
    data = mcap.read_bytes()
    mcap.write_bytes(data[:summary_start])
    assert 'is truncated' in error_of(tmp_path / 'bag')


def test_recorder_killed(tmp_path):
    """A writer process killed with SIGKILL mid-recording: no metadata.yaml, no MCAP footer."""
    script = (
        'import sys, itertools\n'
        'from rosbags.rosbag2 import Writer, StoragePlugin\n'
        'from cloe_ros.io.messages import TYPESTORE\n'
        'S = TYPESTORE.types["std_msgs/msg/String"]\n'
        'w = Writer(sys.argv[1], version=9, storage_plugin=StoragePlugin.MCAP)\n'
        'w.open()\n'
        'c = w.add_connection("/chatter", "std_msgs/msg/String", typestore=TYPESTORE)\n'
        'raw = TYPESTORE.serialize_cdr(S(data="x" * 1000), "std_msgs/msg/String")\n'
        'for i in itertools.count():\n'
        '    w.write(c, i, raw)\n'
        '    if i % 1000 == 0: w.storage.bio.flush()\n'
    )
    bag = tmp_path / 'bag'
    env = dict(os.environ, PYTHONPATH=str(Path(__file__).resolve().parents[2]))
    proc = subprocess.Popen([sys.executable, '-c', script, str(bag)], env=env)
    try:
        deadline = time.monotonic() + 20
        while time.monotonic() < deadline and proc.poll() is None:
            mcap = bag / 'bag.mcap'
            if mcap.exists() and mcap.stat().st_size > 3_000_000:
                break
            time.sleep(0.02)
        assert proc.poll() is None, 'the writer ended by itself'
        proc.send_signal(signal.SIGKILL)
    finally:
        proc.kill()
        proc.wait(10)
    text = error_of(bag)
    assert 'has no metadata.yaml but holds bag.mcap' in text
    assert 'recorder killed' in text
    assert f'cloe bag recover {bag}' in text
    text = error_of(bag / 'bag.mcap')
    assert text.startswith(f'{bag / "bag.mcap"} is truncated')


def test_empty_mcap(tmp_path):
    write_bag(tmp_path / 'bag', n_odom=10)
    (tmp_path / 'bag' / 'bag.mcap').write_bytes(b'')
    assert error_of(tmp_path / 'bag') == (
        f'{tmp_path / "bag" / "bag.mcap"} is empty: nothing was recorded; remove the bag '
        f'{tmp_path / "bag"}'
    )


def test_not_an_mcap(tmp_path):
    write_bag(tmp_path / 'bag', n_odom=10)
    (tmp_path / 'bag' / 'bag.mcap').write_bytes(b'PK\x03\x04' + bytes(100))
    assert error_of(tmp_path / 'bag') == (
        f'{tmp_path / "bag" / "bag.mcap"} is not an MCAP file (it does not start with the MCAP '
        'magic bytes)'
    )


def chunk_offsets(mcap: Path) -> list[int]:
    with open(mcap, 'rb') as fh:
        return [c.chunk_start_offset for c in make_reader(fh).get_summary().chunk_indexes]


def read_until_error(path: Path) -> tuple[list[tuple[str, int, bytes]], str]:
    got: list[tuple[str, int, bytes]] = []
    with pytest.raises(BagError) as info:
        with BagReader(path) as bag:
            for item in bag.messages():
                got.append(item)
    return got, str(info.value)


def test_chunk_bad_crc(tmp_path):
    expected = write_bag(tmp_path / 'bag')
    mcap = tmp_path / 'bag' / 'bag.mcap'
    offsets = chunk_offsets(mcap)
    data = bytearray(mcap.read_bytes())
    crc_at = offsets[1] + 1 + 8 + 24  # opcode, length, start, end, uncompressed size
    data[crc_at : crc_at + 4] = (12345).to_bytes(4, 'little')
    mcap.write_bytes(bytes(data))
    got, text = read_until_error(tmp_path / 'bag')
    assert text.startswith(f'{mcap}: corrupt chunk at byte offset {offsets[1]} (messages of ')
    assert '/odom' in text
    assert 'Chunk checksum mismatch.' in text
    # everything before the damaged chunk came out, in order
    assert 0 < len(got) < len(expected)
    assert [(t, s) for t, s, _ in got] == [(t, s) for t, s, _ in expected[: len(got)]]


def test_chunk_undecompressable(tmp_path):
    write_bag(tmp_path / 'bag', compression=CompressionMode.STORAGE)
    mcap = tmp_path / 'bag' / 'bag.mcap'
    offsets = chunk_offsets(mcap)
    data = bytearray(mcap.read_bytes())
    middle = (offsets[0] + offsets[1]) // 2
    data[middle : middle + 64] = bytes(64)
    mcap.write_bytes(bytes(data))
    got, text = read_until_error(tmp_path / 'bag')
    assert text.startswith(f'{mcap}: corrupt chunk at byte offset {offsets[0]} (messages of ')
    assert 'The file is damaged' in text
    assert got == []


def message_records(data: bytes, start: int, end: int) -> list[int]:
    """Offsets of the message records between ``start`` and ``end`` of uncompressed records."""
    out, pos = [], start
    while pos < end:
        op, length = struct.unpack_from('<BQ', data, pos)
        if op == 0x05:
            out.append(pos)
        pos += 9 + length
    return out


def test_chunk_whose_messages_differ_from_its_index(tmp_path):
    """A message's log time overwritten by another one of the same chunk: every record still
    parses and lies in the chunk's time range, but the message index after the chunk disagrees
    (rosbags writes no chunk CRC). Delivered silently with a wrong time before."""
    expected = write_bag(tmp_path / 'bag')
    mcap = tmp_path / 'bag' / 'bag.mcap'
    with open(mcap, 'rb') as fh:
        chunk = sorted(
            make_reader(fh).get_summary().chunk_indexes, key=lambda c: c.chunk_start_offset
        )[1]
    data = bytearray(mcap.read_bytes())
    records = chunk.chunk_start_offset + 9 + 40  # uncompressed: no compression name
    first, *others = message_records(data, records, chunk.chunk_start_offset + chunk.chunk_length)

    def log_time(at: int) -> bytes:  # after opcode, length, channel id, sequence
        return bytes(data[at + 15 : at + 23])

    second = next(at for at in others if log_time(at) != log_time(first))
    data[second + 15 : second + 23] = log_time(first)
    mcap.write_bytes(bytes(data))
    got, text = read_until_error(tmp_path / 'bag')
    assert text.startswith(f'{mcap}: corrupt chunk at byte offset {chunk.chunk_start_offset} (')
    assert 'differ from the message index' in text
    assert [(t, s) for t, s, _ in got] == [(t, s) for t, s, _ in expected[: len(got)]]
    assert len(got) >= sum(s < chunk.message_start_time for _, s, _ in expected)


def test_fewer_messages_than_the_metadata_lists(tmp_path):
    """Messages the storage does not give although metadata.yaml lists them: an error at the
    end, naming the topics, instead of a bag that silently plays short."""
    expected = write_bag(tmp_path / 'bag', n_odom=20)

    def more(meta):
        meta['topics_with_message_count'][0]['message_count'] += 2
        meta['message_count'] += 2

    edit_metadata(tmp_path / 'bag', more)
    got, text = read_until_error(tmp_path / 'bag')
    assert len(got) == len(expected)
    assert text == (
        f'{tmp_path / "bag"}: 2 of the messages metadata.yaml lists could not be read (/odom 20 '
        'of 22 read): the bag is damaged. `cloe bag recover` writes a bag with every message '
        'that can still be read.'
    )


def test_messages_before_a_damaged_chunk_sharing_its_start_time(tmp_path):
    """The last message of a good chunk has the log time the next, damaged chunk starts with:
    it is delivered before the error (the merge by log time held it back, waiting for the
    damaged chunk)."""
    bag = tmp_path / 'bag'
    with BagWriter(bag, compression='none') as writer:
        writer.add_topic('/odom', ODOMETRY)
        for i in range(100):
            writer.write('/odom', T0 + i * ODOM_DT, _odom(i, T0 + i * ODOM_DT))
        writer.flush()  # closes the first chunk
        for i in range(99, 200):  # the second chunk starts at the first one's last log time
            writer.write('/odom', T0 + i * ODOM_DT, _odom(1000 + i, T0 + i * ODOM_DT))
    mcap = next(bag.glob('*.mcap'))
    offsets = sorted(chunk_offsets(mcap))
    assert len(offsets) == 2
    data = bytearray(mcap.read_bytes())
    crc_at = offsets[1] + 1 + 8 + 24
    data[crc_at : crc_at + 4] = (12345).to_bytes(4, 'little')
    mcap.write_bytes(bytes(data))
    got, text = read_until_error(bag)
    assert f'corrupt chunk at byte offset {offsets[1]}' in text
    assert [decode_odometry(raw).position[0] for _, _, raw in got] == list(range(100))


def test_corrupt_unindexed_message_compressed(tmp_path):
    """Per-message compression goes through rosbags' own iteration: still a BagError."""
    write_bag(tmp_path / 'bag', n_odom=500, compression=CompressionMode.MESSAGE)
    mcap = tmp_path / 'bag' / 'bag.mcap'
    offsets = chunk_offsets(mcap)
    data = bytearray(mcap.read_bytes())
    crc_at = offsets[0] + 1 + 8 + 24
    data[crc_at : crc_at + 4] = (12345).to_bytes(4, 'little')
    mcap.write_bytes(bytes(data))
    got, text = read_until_error(tmp_path / 'bag')
    assert text.startswith(f'{tmp_path / "bag"}: damaged data before the first message:')
    assert 'checksum' in text
    assert got == []


def test_messages_needs_open(tmp_path):
    write_bag(tmp_path / 'bag', n_odom=10)
    bag = BagReader(tmp_path / 'bag')
    with pytest.raises(BagError, match='is not open'):
        bag.messages()


# -- CRCs, what the file says against metadata.yaml, encodings -----------------------------------


def package_bag(path: Path, n_odom: int = 3000) -> list[tuple[str, int, int]]:
    """write_bag's messages written by the package's BagWriter (zstd chunks with CRCs)."""
    expected = []
    with BagWriter(path) as writer:
        writer.add_topic('/odom', ODOMETRY)
        writer.add_topic('/reference', POSE_STAMPED)
        for i in range(n_odom):
            t = T0 + i * ODOM_DT
            writer.write('/odom', t, _odom(i, t))
            expected.append(('/odom', t, i))
            if i % 2 == 0:
                writer.write('/reference', t, _ref(i // 2, t))
                expected.append(('/reference', t, i // 2))
    return expected


def test_a_bit_flipped_inside_compressed_chunk_data_is_found(tmp_path):
    """One bit flipped in a zstd chunk: the data still decompress and parse, one message changed
    (it was delivered silently before). The chunk's CRC finds it and the error names the file, the
    chunk (number and offset) and its topics; the messages before it come out first."""
    import bag_fixtures

    expected = package_bag(tmp_path / 'bag')
    mcap = tmp_path / 'bag' / 'bag.mcap'
    with open(mcap, 'rb') as fh:
        n_chunks = len(make_reader(fh).get_summary().chunk_indexes)
    offset, _ = bag_fixtures.flip_inside_compressed_chunk(mcap, chunk=1)
    for path in (tmp_path / 'bag', mcap):
        got, text = read_until_error(path)
        assert text.startswith(f'{mcap}: corrupt chunk at byte offset {offset} (messages of ')
        assert '/odom' in text
        assert 'Chunk checksum mismatch.' in text
        assert f'It is chunk 2 of {n_chunks} in the file.' in text
        assert 0 < len(got) < len(expected)
        assert [(t, s) for t, s, _ in got] == [(t, s) for t, s, _ in expected[: len(got)]]


def test_damage_outside_the_chunks_is_found_by_the_data_section_crc(tmp_path):
    """A byte changed in the copy of metadata.yaml the file holds (an MCAP metadata record,
    outside every chunk): only the data section CRC covers it. Every message is delivered, then
    the error."""
    expected = package_bag(tmp_path / 'bag', n_odom=50)
    mcap = tmp_path / 'bag' / 'bag.mcap'
    data = bytearray(mcap.read_bytes())
    at = data.index(b'serialized_metadata') + 40
    data[at] ^= 0x20
    mcap.write_bytes(bytes(data))
    got, text = read_until_error(tmp_path / 'bag')
    assert len(got) == len(expected)
    assert text.startswith(f'{mcap}: its data section does not match its CRC')
    assert 'cloe bag recover' in text


def test_a_damaged_summary_is_found_when_the_bag_is_opened(tmp_path):
    """A byte changed in the summary (the repeated schema at the end of the file), which the
    reader uses for topics, counts and chunks: its CRC refuses it at once."""
    package_bag(tmp_path / 'bag', n_odom=50)
    mcap = tmp_path / 'bag' / 'bag.mcap'
    data = bytearray(mcap.read_bytes())
    at = data.rindex(b'nav_msgs/msg/Odometry') + 3
    data[at] ^= 0x01
    mcap.write_bytes(bytes(data))
    text = error_of(tmp_path / 'bag')
    assert text.startswith(f'{mcap}: its summary (the index at the end of the file) does not')
    assert f'cloe bag recover {tmp_path / "bag"}' in text


def test_counts_come_from_the_file(tmp_path):
    """metadata.yaml claiming 10 messages of /odom and none in all: the counts are the file's,
    every message is read, and the mismatch is said."""
    expected = package_bag(tmp_path / 'bag', n_odom=100)
    n_ref = sum(t == '/reference' for t, _, _ in expected)

    def lie(meta):
        meta['topics_with_message_count'][0]['message_count'] = 10
        meta['message_count'] = 0
        meta['duration']['nanoseconds'] = 0

    edit_metadata(tmp_path / 'bag', lie)
    with BagReader(tmp_path / 'bag') as bag:
        assert bag.topics['/odom'].count == 100
        assert bag.topics['/reference'].count == n_ref
        assert bag.message_count == len(expected)
        assert (bag.start_ns, bag.end_ns) == (expected[0][1], expected[-1][1])
        assert bag.metadata_mismatch == [
            'metadata.yaml lists 10 messages of /odom, bag.mcap holds 100'
        ]
        assert len(list(bag.messages())) == len(expected)

    edit_metadata(tmp_path / 'bag', lambda m: m['topics_with_message_count'][0].update(
        message_count=100))  # fmt: skip
    with BagReader(tmp_path / 'bag') as bag:
        assert bag.metadata_mismatch == [
            f'metadata.yaml lists 0 messages in all, bag.mcap holds {len(expected)}'
        ]


def test_a_bag_written_by_the_package_agrees_with_its_metadata(tmp_path):
    package_bag(tmp_path / 'bag', n_odom=10)
    with BagReader(tmp_path / 'bag') as bag:
        assert bag.metadata_mismatch == []


def mcap_lib_file(path: Path, message_encoding: str = 'cdr', schema_encoding: str = 'ros2msg',
                  n: int = 10) -> Path:  # fmt: skip
    """A ROS 2 MCAP file written by the mcap library, its /odom channel in the given encodings."""
    from mcap.writer import Writer as McapLibWriter

    with path.open('wb') as fh:
        w = McapLibWriter(fh)
        w.start(profile='ros2', library='test')
        msgdef = TYPESTORE.generate_msgdef(ODOMETRY)[0]
        sid = w.register_schema(ODOMETRY, schema_encoding, msgdef.encode())
        cid = w.register_channel('/odom', message_encoding, sid, {'offered_qos_profiles': ''})
        for i in range(n):
            t = T0 + i * ODOM_DT
            w.add_message(cid, log_time=t, data=_odom(i, t), publish_time=t)
        w.finish()
    return path


def test_a_channel_not_in_cdr_is_refused(tmp_path):
    """A json channel (decoded as CDR before): refused, naming the topic and the encoding, as a
    single file and inside a bag whose metadata.yaml says cdr."""
    mcap = mcap_lib_file(tmp_path / 'json.mcap', message_encoding='json')
    assert error_of(mcap) == (
        f"{mcap}: topic /odom is encoded as 'json'; only cdr (ROS 2 CDR, what rosbag2 records) "
        'can be read'
    )
    package_bag(tmp_path / 'bag', n_odom=10)
    mcap_lib_file(tmp_path / 'bag' / 'bag.mcap', message_encoding='json')
    assert "topic /odom is encoded as 'json'" in error_of(tmp_path / 'bag')


def test_an_unknown_schema_encoding_is_refused_clearly(tmp_path):
    """Before: `cannot open the bag: 'x-unknown'.`"""
    mcap = mcap_lib_file(tmp_path / 'x.mcap', schema_encoding='x-unknown')
    assert error_of(mcap) == (
        f"{mcap}: topic /odom has a schema (nav_msgs/msg/Odometry) in encoding 'x-unknown'; "
        'expected a ROS 2 message definition (ros2msg, ros2idl, omgidl)'
    )


def test_a_file_of_the_mcap_library_is_read(tmp_path):
    mcap = mcap_lib_file(tmp_path / 'lib.mcap', n=30)
    with BagReader(mcap) as bag:
        assert bag.topics['/odom'].count == 30
        got = list(bag.messages())
    assert [decode_odometry(raw).position[0] for _, _, raw in got] == list(range(30))


def test_a_symlink_loop_is_said_to_be_one(tmp_path):
    loop = tmp_path / 'loop'
    loop.symlink_to(tmp_path / 'loop')
    assert error_of(loop) == f'{loop}: too many levels of symbolic links (a symbolic link loop)'
    broken = tmp_path / 'broken'
    broken.symlink_to(tmp_path / 'gone')
    assert error_of(broken) == (
        f'{broken} is a broken symbolic link (to {tmp_path / "gone"}, which does not exist)'
    )
