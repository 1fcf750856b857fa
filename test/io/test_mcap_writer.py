"""McapWriter writes, call for call, the bytes the ``mcap`` library's writer writes (chunked, zstd
or none, every index, statistics, summary offsets, the chunk, data and summary CRCs)."""

from __future__ import annotations

import io

import numpy as np
import pytest
from mcap.reader import make_reader
from mcap.writer import CompressionType
from mcap.writer import Writer as LibraryWriter

from cloe_ros.io.mcap_writer import McapWriter

PROFILE, LIBRARY = 'ros2', 'cloe_ros-test'


def _library_writer(stream, chunk_size, compression):
    writer = LibraryWriter(stream, chunk_size=chunk_size, enable_crcs=True, enable_data_crcs=True,
                           compression=CompressionType.ZSTD if compression else
                           CompressionType.NONE)  # fmt: skip
    writer.start(profile=PROFILE, library=LIBRARY)
    return writer


def _play(writer, calls, library: bool) -> None:
    """Make ``calls`` on ``writer``: the library's signature for its messages if ``library``."""
    for name, *args in calls:
        if name == 'message' and library:
            channel_id, log_time, data = args
            writer.add_message(channel_id, log_time, data, log_time)
        elif name == 'message':
            writer.add_message(*args)
        else:
            getattr(writer, name)(*args)


def _calls(seed: int, messages: int) -> list:
    """Schemas and channels declared before and between messages of random sizes and channels,
    log times out of order, flushes and a metadata record."""
    rng = np.random.default_rng(seed)
    calls = [('register_schema', 'nav_msgs/msg/Odometry', 'ros2msg', b'float64 x\n'),
             ('register_channel', '/uav1/odom', 'cdr', 1, {'offered_qos_profiles': ''}),
             ('register_channel', '/uav1/reference', 'cdr', 1, {})]  # fmt: skip
    channels = 2
    for k in range(messages):
        if k == messages // 3:
            calls.append(('register_schema', 'std_msgs/msg/String', 'ros2msg', b'string data\n'))
            calls.append(('register_channel', '/uav1/cloe/state', 'cdr', 2, {'a': 'b'}))
            channels += 1
        if k == messages // 2:
            calls.append(('flush',))
        size = int(rng.integers(0, 700))
        data = rng.integers(0, 256, size, dtype=np.uint8).tobytes()
        log_time = 10**9 + 10**7 * k + int(rng.integers(-3 * 10**7, 3 * 10**7))
        calls.append(('message', int(rng.integers(1, channels + 1)), log_time, data))
    calls.append(('flush',))
    calls.append(('add_metadata', 'rosbag2', {'serialized_metadata': 'version: 9'}))
    calls.append(('finish',))
    return calls


@pytest.mark.parametrize('compression', ['zstd', ''])
@pytest.mark.parametrize(('seed', 'messages', 'chunk_size'),
                         [(0, 2000, 1 << 14), (1, 300, 1 << 20), (2, 0, 1 << 14),
                          (3, 1, 1), (4, 50, 100)])  # fmt: skip
def test_the_file_is_the_librarys_byte_for_byte(compression, seed, messages, chunk_size):
    calls = _calls(seed, messages)
    theirs, ours = io.BytesIO(), io.BytesIO()
    _play(_library_writer(theirs, chunk_size, compression), calls, library=True)
    _play(McapWriter(ours, chunk_size, compression, PROFILE, LIBRARY), calls, library=False)
    assert ours.getvalue() == theirs.getvalue()
    if messages:  # and the library's reader reads it, CRCs checked
        read = list(make_reader(io.BytesIO(ours.getvalue()), validate_crcs=True)
                    .iter_messages(log_time_order=False))  # fmt: skip
        sent = [c[1:] for c in calls if c[0] == 'message']
        assert [(ch.id, m.log_time, m.data) for _, ch, m in read] == sent


def test_add_message_says_when_it_wrote_the_chunk():
    stream = io.BytesIO()
    writer = McapWriter(stream, 150, '', PROFILE, LIBRARY)
    writer.register_schema('a', 'ros2msg', b'')  # a record of 31 bytes
    writer.register_channel('/a', 'cdr', 1, {})  # 30 bytes
    written, grew = [], []
    for k in range(6):  # records of 31 + 30 bytes: the chunk passes 150 bytes at 183
        size = stream.tell()
        written.append(writer.add_message(1, k, bytes(30)))
        grew.append(stream.tell() > size)
    assert written == grew == [False, True, False, False, True, False]


def test_an_unknown_compression_is_refused():
    with pytest.raises(ValueError, match="compression must be 'zstd' or ''"):
        McapWriter(io.BytesIO(), 100, 'lz4', PROFILE, LIBRARY)
