"""bag_player: real node processes on a domain of their own, a subscriber in this process.

Every message of the bag must arrive, decode to what the bag holds, in per-topic order, spaced by
the recorded log times divided by the rate; bad parameters and bad bags end the process with
status 1 and a message saying what is wrong.
"""

from __future__ import annotations

import itertools
import signal
import time
from collections.abc import Callable
from pathlib import Path

import numpy as np
import pytest
from geometry_msgs.msg import PoseStamped
from mcap.reader import make_reader
from nav_msgs.msg import Odometry
from rclpy.parameter import Parameter
from rclpy.qos import DurabilityPolicy, ReliabilityPolicy
from ros_helpers import NodeProcess, private_domain, reserve_domain_id, spin_until, start_node
from rosbags.interfaces import (
    Qos,
    QosDurability,
    QosHistory,
    QosLiveliness,
    QosReliability,
    QosTime,
)
from rosbags.rosbag2 import StoragePlugin, Writer
from rosgraph_msgs.msg import Clock
from std_srvs.srv import Trigger

from cloe_ros.core.samples import OdometrySample
from cloe_ros.io.messages import (
    ODOMETRY,
    TYPESTORE,
    decode_clock,
    decode_odometry,
    decode_pose_stamped,
    encode_odometry,
)
from cloe_ros.io.reader import BagReader
from cloe_ros.ros import player_node
from cloe_ros.ros.common import ParameterError, qos
from cloe_ros.ros.player_node import PlayerNode, playback_qos

pytestmark = pytest.mark.ros

from corpus import B2  # noqa: E402

PLANE = 'shape_msgs/msg/Plane'  # its Python package is not installed here
#: Player parameters of every test that counts what arrives: the publishers keep more than a whole
#: bag until acknowledged (a subscriber short of CPU falls behind, it loses nothing), and the
#: player waits as long as it takes for the acknowledgements before it exits (Fast DDS repairs a
#: loss at its heartbeat, every 3 s: on a loaded machine that can take more than one round).
DELIVERY = {'qos_depth': 10_000, 'ack_timeout': 60.0}
#: Generous waits (s) for what takes a fraction of that on an idle machine.
TIMEOUT = 60.0
#: Send times (the middleware's source timestamps, system clock) against the player's schedule
#: (steady clock): besides the lateness the player reports, the time between its reading of the
#: clock and the middleware's stamp, and the two clocks' drift over a few seconds.
SEND_SLACK_S = 0.05
needs_b2 = pytest.mark.skipif(not B2.is_dir(), reason=f'{B2} not available')


@pytest.fixture(scope='module')
def b2_messages() -> dict[str, list[tuple[int, bytes]]]:
    if not B2.is_dir():
        pytest.skip(f'{B2} not available')
    out: dict[str, list[tuple[int, bytes]]] = {'/odom': [], '/reference': []}
    with BagReader(B2) as bag:
        for topic, log_ns, raw in bag.messages():
            out[topic].append((log_ns, raw))
    return out


@pytest.fixture
def ros():
    """An rclpy context of our own on a domain of our own, with a node and an executor."""
    with private_domain('player_test') as ros:
        yield ros


class Arrivals:
    """Raw subscriptions keeping every message with the time it was sent (s, the middleware's
    source timestamp: the player's timing, whatever the delay until this process takes it)."""

    def __init__(self, node, topics: dict[str, type]) -> None:
        self.msgs: dict[str, list[tuple[float, bytes]]] = {t: [] for t in topics}
        self.subs = {
            topic: node.create_subscription(
                cls,
                topic,
                lambda raw, info, t=topic: self.msgs[t].append(
                    (info['source_timestamp'] / 1e9, raw)
                ),
                qos(reliable=True, depth=10_000),
                raw=True,
            )
            for topic, cls in topics.items()
        }

    def count(self, topic: str) -> int:
        return len(self.msgs[topic])


def drain(ros, seconds: float = 0.3) -> None:
    spin_until(ros.executor, lambda: False, timeout=seconds)


def play_to_end(
    ros, player: NodeProcess, until: Callable[[], bool] = lambda: True, timeout: float = 120.0
) -> int:
    """Spin until the player process has exited and ``until()`` holds; its status. The player
    exits once its messages are acknowledged, that is once they are in this process's queues,
    not yet taken by its executor: a test waits with ``until`` for the messages it expects (on a
    loaded machine, taking a few thousand can take seconds)."""
    try:
        spin_until(
            ros.executor, lambda: player.proc.poll() is not None and until(), timeout=timeout
        )
        drain(ros)
        return player.wait(1.0)
    finally:
        player.stop()


def output(player: NodeProcess) -> str:
    return player.output()


def max_lateness_s(out: str, of: str = 'messages') -> float:
    """The largest lateness behind its schedule the player reports, s, for a message or (``of``
    ``'clock'``) a ``/clock`` tick. Its ``done:`` line: ``behind schedule by median .. ms, 99th
    percentile .. ms, max .. ms``, then, with ``publish_clock``, ``; /clock: <n> ticks, behind
    schedule by ...`` in the same words."""
    (line,) = [x for x in out.splitlines() if 'done: ' in x and 'behind schedule' in x]
    messages, _, ticks = line.partition('; /clock: ')
    part = {'messages': messages, 'clock': ticks}[of]
    return float(part.rsplit('max ', 1)[1].split(' ms')[0]) / 1e3


def assert_on_schedule(sent: np.ndarray, due: np.ndarray, late_s: float) -> None:
    """Send times ``sent`` (s) follow the schedule ``due`` (s, any origin): each is as much after
    the first as its due time is after the first's, to within the lateness the player reports
    (whatever the machine's load) and SEND_SLACK_S."""
    offset = (sent - sent[0]) - (due - due[0])
    worst = float(np.abs(offset).max())
    assert worst <= late_s + SEND_SLACK_S, (
        f'{int(np.argmax(np.abs(offset)))}: {worst * 1e3:.1f} ms off schedule; the player reports '
        f'at most {late_s * 1e3:.1f} ms of lateness'
    )


def assert_same_odometry(raw_a: bytes, raw_b: bytes) -> None:
    a, b = decode_odometry(raw_a), decode_odometry(raw_b)
    assert (a.stamp_ns, a.frame_id, a.child_frame_id) == (b.stamp_ns, b.frame_id, b.child_frame_id)
    for field in ('position', 'orientation', 'linear', 'angular'):
        np.testing.assert_array_equal(getattr(a, field), getattr(b, field))
    np.testing.assert_array_equal(a.pose_covariance, b.pose_covariance)
    np.testing.assert_array_equal(a.twist_covariance, b.twist_covariance)


def assert_same_pose(raw_a: bytes, raw_b: bytes) -> None:
    a, b = decode_pose_stamped(raw_a), decode_pose_stamped(raw_b)
    assert (a.stamp_ns, a.frame_id) == (b.stamp_ns, b.frame_id)
    np.testing.assert_array_equal(a.position, b.position)
    np.testing.assert_array_equal(a.orientation, b.orientation)


# -- playing the real flight ---------------------------------------------------------------------


@needs_b2
def test_plays_every_message_with_recorded_timing(ros, tmp_path, b2_messages):
    """Every message, decoded to what the bag holds, in order, and sent at its log time divided
    by the rate: to within the lateness the player reports, so the check holds on a loaded
    machine too (how late a busy machine makes it is a speed: scripts/benchmark_ros.py)."""
    rate = 10.0
    arrivals = Arrivals(ros.node, {'/odom': Odometry, '/reference': PoseStamped})
    player = start_node(
        'bag_player',
        {'bag': str(B2), 'rate': rate, 'wait_for_subscribers': 1, **DELIVERY},
        ros.domain,
        tmp_path,
    )
    n_odom, n_ref = len(b2_messages['/odom']), len(b2_messages['/reference'])
    status = play_to_end(
        ros,
        player,
        until=lambda: arrivals.count('/odom') >= n_odom and arrivals.count('/reference') >= n_ref,
    )
    out = output(player)
    assert status == 0, out
    assert f'playing {B2}' in out
    assert f'done: {n_odom + n_ref} messages' in out

    # every message, decoding to the bag's values, in the recorded per-topic order
    assert arrivals.count('/odom') == n_odom and arrivals.count('/reference') == n_ref, out
    for (_, got), (_, want) in zip(arrivals.msgs['/odom'], b2_messages['/odom']):
        assert_same_odometry(got, want)
    for (_, got), (_, want) in zip(arrivals.msgs['/reference'], b2_messages['/reference']):
        assert_same_pose(got, want)

    # timing: send time against log time / rate, over both topics
    log = np.array(
        [t for tp in ('/odom', '/reference') for t, _ in b2_messages[tp]], dtype=np.int64
    )
    sent = np.array([t for tp in ('/odom', '/reference') for t, _ in arrivals.msgs[tp]])
    order = np.argsort(log, kind='stable')
    bag_s = (log[order] - log.min()) / 1e9
    late = max_lateness_s(out)
    assert_on_schedule(sent[order], bag_s / rate, late)
    recorded = bag_s.max() / rate  # 27.25 s / 10
    print(
        f'send time vs log time / rate: span {sent.max() - sent.min():.3f} s (recorded '
        f'{recorded:.3f} s), at most {late * 1e3:.1f} ms late as the player reports'
    )


@needs_b2
def test_publishes_clock(ros, tmp_path, b2_messages):
    """/clock ticks every 1/clock_rate s of wall time (the player's schedule), the bag time
    advancing by rate / clock_rate per tick; each tick sent on that schedule to within the
    lateness the player reports for its ticks."""
    rate, clock_rate = 10.0, 100.0
    arrivals = Arrivals(ros.node, {'/clock': Clock})
    player = start_node(
        'bag_player',
        {
            'bag': str(B2),
            'rate': rate,
            'topics': ['/reference'],
            'publish_clock': True,
            'clock_rate': clock_rate,
            'wait_for_subscribers': 1,
            **DELIVERY,
        },
        ros.domain,
        tmp_path,
    )
    # /clock is not waited for: match it before the subscriber the player waits for exists
    matched = spin_until(
        ros.executor, lambda: arrivals.subs['/clock'].get_publisher_count() >= 1, timeout=TIMEOUT
    )
    ref = Arrivals(ros.node, {'/reference': PoseStamped})
    with BagReader(B2) as bag:
        start_ns, end_ns = bag.start_ns, bag.end_ns

    def all_in() -> bool:  # the last tick, at the bag's end, comes after every other
        last = arrivals.msgs['/clock'][-1:]
        done = bool(last) and decode_clock(last[0][1]) == end_ns
        return done and ref.count('/reference') >= len(b2_messages['/reference'])

    status = play_to_end(ros, player, until=all_in)
    assert matched and status == 0, output(player)
    sent = np.array([t for t, _ in arrivals.msgs['/clock']])
    clock = np.array([decode_clock(raw) for _, raw in arrivals.msgs['/clock']], dtype=np.int64)
    assert ref.count('/reference') == len(b2_messages['/reference'])
    # one tick per 1/clock_rate of scheduled wall time over the bag's duration / rate (a late
    # player catches up with the ticks it owes: the count does not depend on its speed)
    ticks = (end_ns - start_ns) / 1e9 / rate * clock_rate
    assert 0.9 * ticks <= len(clock) <= 1.1 * ticks + 2
    assert np.all(np.diff(clock) >= 0)  # monotonic
    assert clock[0] == start_ns and clock[-1] == end_ns  # spans the bag's log times
    assert np.all(np.diff(clock)[:-1] > 0)  # advancing (only the final tick may repeat)
    # bag seconds per wall second: rate / clock_rate of bag time per tick (to the nanosecond
    # rounding of each), except the last tick, the bag's end
    step_ns = rate / clock_rate * 1e9
    assert np.all(np.abs(np.diff(clock)[:-1] - step_ns) <= 1), np.diff(clock)[:5]
    # ... and sent on that schedule (the last tick, the bag's end, comes with the last message)
    assert_on_schedule(
        sent[:-1], (clock[:-1] - start_ns) / 1e9 / rate, max_lateness_s(output(player), 'clock')
    )


@needs_b2
def test_plays_only_selected_topics(ros, tmp_path, b2_messages):
    arrivals = Arrivals(ros.node, {'/odom': Odometry, '/reference': PoseStamped})
    player = start_node(
        'bag_player',
        {'bag': str(B2), 'rate': 20.0, 'topics': ['/odom'], 'wait_for_subscribers': 1, **DELIVERY},
        ros.domain,
        tmp_path,
    )
    n_odom = len(b2_messages['/odom'])
    status = play_to_end(ros, player, until=lambda: arrivals.count('/odom') >= n_odom)
    assert status == 0, output(player)
    assert arrivals.count('/odom') == n_odom
    assert arrivals.count('/reference') == 0
    assert arrivals.subs['/reference'].get_publisher_count() == 0
    assert f'done: {n_odom} messages' in output(player)


def write_small_bag(path: Path, topics: dict[str, str], n: int = 50, qos_profiles=()) -> None:
    """``n`` messages per topic at 100 Hz; types from the Jazzy type store."""
    with Writer(path, version=9, storage_plugin=StoragePlugin.MCAP) as writer:
        conns = {
            t: writer.add_connection(
                t, msgtype, typestore=TYPESTORE, offered_qos_profiles=qos_profiles
            )
            for t, msgtype in topics.items()
        }
        for i in range(n):
            stamp_ns = 10**18 + i * 10**7
            for topic, msgtype in topics.items():
                if msgtype == ODOMETRY:
                    raw = encode_odometry(
                        OdometrySample(stamp_ns, 'world', 'body', np.array([i, 0.0, 0.0]),
                                       np.array([0.0, 0.0, 0.0, 1.0]), np.zeros(3), np.zeros(3))
                    )  # fmt: skip
                else:
                    msg = TYPESTORE.types[PLANE](coef=np.array([0.0, 0.0, 1.0, -float(i)]))
                    raw = TYPESTORE.serialize_cdr(msg, PLANE)
                writer.write(conns[topic], stamp_ns, raw)


def test_skips_types_without_python_package(ros, tmp_path):
    bag = tmp_path / 'bag'
    write_small_bag(bag, {'/odom': ODOMETRY, '/plane': PLANE})
    arrivals = Arrivals(ros.node, {'/odom': Odometry})
    player = start_node(
        'bag_player',
        {'bag': str(bag), 'rate': 5.0, 'wait_for_subscribers': 1, **DELIVERY},
        ros.domain,
        tmp_path,
    )
    status = play_to_end(ros, player, until=lambda: arrivals.count('/odom') >= 50)
    out = output(player)
    assert status == 0, out
    assert 'skipping /plane: the Python package of shape_msgs/msg/Plane is not installed' in out
    assert 'done: 50 messages' in out
    assert [decode_odometry(raw).position[0] for _, raw in arrivals.msgs['/odom']] == list(
        map(float, range(50))
    )


def test_damaged_chunk_mid_play(ros, tmp_path):
    """The messages before a corrupt chunk are played, then the process ends with status 1. The
    damage leaves every record readable (a message's log time overwritten with the next one's):
    only the message index after the chunk tells, and rosbags alone played on silently."""
    bag = tmp_path / 'bag'
    write_small_bag(bag, {'/odom': ODOMETRY}, n=3000)  # 30 s, more than one 1 MiB chunk
    mcap = bag / 'bag.mcap'
    with open(mcap, 'rb') as fh:
        chunks = sorted(
            make_reader(fh).get_summary().chunk_indexes, key=lambda c: c.chunk_start_offset
        )
    assert len(chunks) >= 2
    before = round((chunks[1].message_start_time - 10**18) / 10**7)  # messages of chunk 0
    data = bytearray(mcap.read_bytes())
    first = chunks[1].chunk_start_offset + 9 + 40  # its first record (uncompressed, a message)
    assert data[first] == 0x05
    second = first + 9 + int.from_bytes(data[first + 1 : first + 9], 'little')
    data[first + 15 : first + 23] = data[second + 15 : second + 23]  # log time
    mcap.write_bytes(bytes(data))
    arrivals = Arrivals(ros.node, {'/odom': Odometry})
    # the publisher keeps every message until acknowledged (at 100x, a subscriber short of CPU
    # falls more than the default 1000 messages behind), and the failing player waits for the
    # acknowledgements as long as they take (with the default 3.5 s, a loaded machine lost the
    # last 487 messages)
    player = start_node(
        'bag_player',
        {'bag': str(bag), 'rate': 100.0, 'wait_for_subscribers': 1, **DELIVERY},
        ros.domain,
        tmp_path,
    )
    status = play_to_end(ros, player, until=lambda: arrivals.count('/odom') >= before)
    err = player.errors()
    assert status == 1, output(player)
    assert 'not acknowledged' not in err, err
    assert f'{mcap}: corrupt chunk at byte offset {chunks[1].chunk_start_offset}' in err
    assert 'differ from the message index' in err and f'cloe bag recover {bag}' in err
    assert 'Traceback' not in err
    assert 'done:' not in output(player)
    assert 0 < before < 3000
    assert [decode_odometry(raw).position[0] for _, raw in arrivals.msgs['/odom']] == list(
        map(float, range(before))
    )


@needs_b2
def test_stops_cleanly_on_sigint(ros, tmp_path):
    player = start_node('bag_player', {'bag': str(B2)}, ros.domain, tmp_path)
    try:
        assert player.wait_for('playing', timeout=TIMEOUT), output(player)
    finally:
        status = player.stop(signal.SIGINT, timeout=TIMEOUT)
    err = player.errors()
    assert status == 0, output(player)
    assert 'Traceback' not in err and 'ERROR' not in err
    assert 'done:' not in output(player)


def test_wait_timeout_and_start_delay(ros, tmp_path):
    """Nobody subscribes: after wait_timeout the player warns and, after start_delay, plays."""
    bag = tmp_path / 'bag'
    write_small_bag(bag, {'/odom': ODOMETRY}, n=20)
    params = {'bag': str(bag), 'wait_for_subscribers': 2, 'wait_timeout': 0.5, 'start_delay': 0.5}
    player = start_node('bag_player', params, ros.domain, tmp_path)
    status = play_to_end(ros, player)
    out = output(player)
    assert status == 0, out
    assert 'playing without waiting longer than 0.5 s for 2 subscriber(s): /odom has 0' in out
    assert 'done: 20 messages' in out

    def stamp(text: str) -> float:  # rcutils log line: [LEVEL] [seconds.nanoseconds] [node]: text
        line = next(x for x in out.splitlines() if text in x)
        return float(line.split('] [')[1].split(']')[0])

    assert stamp('playing /') - stamp('waiting for 2 subscriber(s)') >= 1.0


# -- refusing to start ---------------------------------------------------------------------------


def truncated_bag(tmp_path: Path) -> Path:
    bag = tmp_path / 'cut'
    write_small_bag(bag, {'/odom': ODOMETRY}, n=200)
    mcap = bag / 'cut.mcap'
    mcap.write_bytes(mcap.read_bytes()[:5000])
    return bag


@pytest.mark.parametrize(
    ('params', 'expected'),
    [
        ({}, "ERROR: parameter 'bag' is required"),
        ({'bag': "''"}, "ERROR: parameter 'bag' is required"),
        ({'bag': '/no/such/bag'}, 'ERROR: /no/such/bag does not exist'),
        ({'bag': 'TRUNCATED'}, 'cut.mcap is truncated: it ends without the MCAP footer'),
        ({'bag': str(B2), 'rate': 0.0}, "ERROR: parameter 'rate'"),
        ({'bag': str(B2), 'rate': -1}, "ERROR: parameter 'rate'"),
        ({'bag': str(B2), 'rate': 101.0}, "ERROR: parameter 'rate'"),
        ({'bag': str(B2), 'topics': ['/odm']}, "ERROR: parameter 'topics': /odm not in"),
        ({'bag': 'UNKNOWN_TYPES'}, 'nothing to play (no topic can be published)'),
        ({'bag': 'SMALL', 'start_offset': 5.0}, "ERROR: parameter 'start_offset': 5 s is past"),
    ],
    ids=[
        'no-bag',
        'empty-bag',
        'missing',
        'truncated',
        'rate-0',
        'rate-neg',
        'rate-101',
        'topic',
        'no-known-type',
        'offset-past-end',
    ],
)
def test_refuses_to_start(tmp_path, params, expected):
    params = dict(params)
    if params.get('bag') == 'TRUNCATED':
        params['bag'] = str(truncated_bag(tmp_path))
    elif params.get('bag') == 'SMALL':
        params['bag'] = str(tmp_path / 'small')
        write_small_bag(tmp_path / 'small', {'/odom': ODOMETRY}, n=50)  # 0.49 s
    elif params.get('bag') == 'UNKNOWN_TYPES':
        params['bag'] = str(tmp_path / 'plane')
        write_small_bag(tmp_path / 'plane', {'/plane': PLANE}, n=5)
    elif str(B2) in params.values() and not B2.is_dir():
        pytest.skip(f'{B2} not available')
    player = start_node('bag_player', params, reserve_domain_id(), tmp_path)
    try:
        status = player.wait(TIMEOUT)
    finally:
        player.stop()
    err = player.errors()
    assert status == 1, output(player)
    assert expected in err
    assert 'Traceback' not in err
    if 'rate' in params:
        assert '(0, 100]' in err or 'out of range' in err
    if params.get('bag', '').endswith('cut'):
        assert f'cloe bag recover {params["bag"]}' in err


# -- in-process: parameters at run time, QoS -----------------------------------------------------


def test_playback_qos():
    zero = QosTime(0, 0)

    def profile(rel, dur):
        return Qos(
            QosHistory.KEEP_LAST, 10, rel, dur, zero, zero, QosLiveliness.AUTOMATIC, zero, False
        )

    rel, be = QosReliability.RELIABLE, QosReliability.BEST_EFFORT
    tl, vol = QosDurability.TRANSIENT_LOCAL, QosDurability.VOLATILE
    assert playback_qos([]) == (True, False)
    assert playback_qos([profile(rel, tl)]) == (True, True)
    assert playback_qos([profile(rel, tl), profile(rel, vol)]) == (True, False)
    assert playback_qos([profile(rel, tl), profile(be, tl)]) == (False, True)


def test_runtime_parameters_and_recorded_qos(ros, tmp_path):
    zero = QosTime(0, 0)
    latched = Qos(
        QosHistory.KEEP_LAST, 1, QosReliability.RELIABLE, QosDurability.TRANSIENT_LOCAL,
        zero, zero, QosLiveliness.AUTOMATIC, zero, False,
    )  # fmt: skip
    bag = tmp_path / 'bag'
    write_small_bag(bag, {'/odom': ODOMETRY}, n=300, qos_profiles=[latched])  # 3 s
    player = PlayerNode(
        context=ros.ctx,
        parameter_overrides=[
            Parameter('bag', value=str(bag)),
            Parameter('exit_when_done', value=False),
        ],
    )
    ros.executor.add_node(player)
    try:
        info = ros.node.get_publishers_info_by_topic('/odom')
        assert [(i.qos_profile.reliability, i.qos_profile.durability) for i in info] == [
            (ReliabilityPolicy.RELIABLE, DurabilityPolicy.TRANSIENT_LOCAL)
        ]
        for value in (0.0, -2.0, 150.0):
            (result,) = player.set_parameters([Parameter('rate', value=value)])
            assert not result.successful
            assert '(0, 100]' in result.reason or 'out of range' in result.reason
        (result,) = player.set_parameters([Parameter('bag', value='/elsewhere')])
        assert not result.successful and 'read-only' in result.reason
        # speeding up while playing: the remaining ~3 s of bag are due within 30 ms (the
        # player's schedule: how soon they go out depends on the machine's speed)
        assert spin_until(ros.executor, lambda: player.published >= 10, timeout=TIMEOUT)
        assert player.published < 300
        (result,) = player.set_parameters([Parameter('rate', value=100.0)])
        assert result.successful
        with player._cond:
            due_in = player._wall_time(player._bag.end_ns) - time.perf_counter()
        assert due_in <= 3.0 / 100.0, due_in  # at rate 1: about 2.9 s
        assert spin_until(ros.executor, player.finished.is_set, timeout=TIMEOUT)
        assert player.published == 300 and not player.failed
        assert ros.ctx.ok()  # exit_when_done: false keeps the node (and its context) alive
    finally:
        ros.executor.remove_node(player)
        player.destroy_node()


def test_in_process_refusals(ros, tmp_path):
    with pytest.raises(ParameterError, match="parameter 'bag' is required"):
        PlayerNode(context=ros.ctx)
    # -p "bag:=  " is YAML null: rclpy gives the parameter no value
    with pytest.raises(ParameterError, match="parameter 'bag' is required"):
        PlayerNode(context=ros.ctx, parameter_overrides=[Parameter('bag', Parameter.Type.NOT_SET)])
    with Writer(tmp_path / 'empty', version=9, storage_plugin=StoragePlugin.MCAP):
        pass
    with pytest.raises(ParameterError, match='nothing to play: the bag has no topics'):
        PlayerNode(
            context=ros.ctx, parameter_overrides=[Parameter('bag', value=str(tmp_path / 'empty'))]
        )
    with pytest.raises(ParameterError, match=r'rate must be in \(0, 100\]'):
        PlayerNode(
            context=ros.ctx,
            parameter_overrides=[Parameter('bag', value=str(B2)), Parameter('rate', value=0.0)],
        )


def test_no_clock_for_a_bag_without_messages(ros, tmp_path, monkeypatch):
    """Topics but no messages: there is no bag time, so no /clock (it was 0)."""
    bag = tmp_path / 'bag'
    write_small_bag(bag, {'/odom': ODOMETRY}, n=0)
    sent: list[int] = []
    monkeypatch.setattr(player_node, 'encode_clock', lambda ns: sent.append(ns) or Clock())
    player = PlayerNode(
        context=ros.ctx,
        parameter_overrides=[
            Parameter('bag', value=str(bag)),
            Parameter('publish_clock', value=True),
            Parameter('exit_when_done', value=False),
        ],
    )
    try:
        assert player.finished.wait(TIMEOUT)
        assert not player.failed and player.published == 0
        assert sent == []
    finally:
        player.destroy_node()


# -- ros2 bag play's conveniences: start offset, loop, pause / resume ----------------------------

BAG_START_NS = 10**18  # write_small_bag's first log time


def positions(arrivals: Arrivals) -> list[float]:
    return [decode_odometry(raw).position[0] for _, raw in arrivals.msgs['/odom']]


def test_start_offset(ros, tmp_path):
    """Messages before start_offset are skipped; /clock starts at the offset."""
    bag = tmp_path / 'bag'
    write_small_bag(bag, {'/odom': ODOMETRY}, n=50)  # message i at i * 10 ms
    arrivals = Arrivals(ros.node, {'/odom': Odometry, '/clock': Clock})
    params = {'bag': str(bag), 'start_offset': 0.2, 'publish_clock': True, 'rate': 2.0,
              'wait_for_subscribers': 1, **DELIVERY}  # fmt: skip
    player = start_node('bag_player', params, ros.domain, tmp_path)
    matched = spin_until(
        ros.executor, lambda: arrivals.subs['/clock'].get_publisher_count() >= 1, timeout=TIMEOUT
    )
    last_tick = BAG_START_NS + 49 * 10**7

    def all_in() -> bool:  # every message, and the last tick (after them)
        last = arrivals.msgs['/clock'][-1:]
        done = bool(last) and decode_clock(last[0][1]) == last_tick
        return done and arrivals.count('/odom') >= 30

    status = play_to_end(ros, player, until=all_in)
    out = output(player)
    assert matched and status == 0, out
    assert 'from 0.2 s' in out and 'done: 30 messages' in out
    assert positions(arrivals) == list(map(float, range(20, 50)))
    clock = [decode_clock(raw) for _, raw in arrivals.msgs['/clock']]
    assert clock[0] == BAG_START_NS + 20 * 10**7
    assert clock[-1] == last_tick
    assert all(b >= a for a, b in itertools.pairwise(clock))


def test_loop_plays_every_pass_from_the_offset(ros, tmp_path):
    """With loop, the bag plays again and again from start_offset until stopped; /clock jumps
    back to the offset at the start of every pass."""
    bag = tmp_path / 'bag'
    write_small_bag(bag, {'/odom': ODOMETRY}, n=50)
    arrivals = Arrivals(ros.node, {'/odom': Odometry, '/clock': Clock})
    params = {'bag': str(bag), 'loop': True, 'start_offset': 0.3, 'publish_clock': True,
              'rate': 5.0, 'wait_for_subscribers': 1}  # fmt: skip
    player = start_node('bag_player', params, ros.domain, tmp_path)
    try:
        matched = spin_until(
            ros.executor,
            lambda: arrivals.subs['/clock'].get_publisher_count() >= 1,
            timeout=TIMEOUT,
        )
        passes = spin_until(ros.executor, lambda: arrivals.count('/odom') >= 60, timeout=TIMEOUT)
    finally:
        status = player.stop(signal.SIGINT)
    out = output(player)
    assert matched and passes, out
    assert status == 0 and 'Traceback' not in out, out
    assert 'looping' in out and 'pass 2 done' in out
    assert 'done:' not in out  # a looping player ends only when stopped
    got = positions(arrivals)
    one_pass = list(map(float, range(30, 50)))
    assert got == (one_pass * (len(got) // 20 + 1))[: len(got)]
    clock = [decode_clock(raw) for _, raw in arrivals.msgs['/clock']]
    start, end = BAG_START_NS + 30 * 10**7, BAG_START_NS + 49 * 10**7
    backwards = [(a, b) for a, b in itertools.pairwise(clock) if b < a]
    assert len(backwards) >= 2  # two passes completed at least
    assert all(a == end and b == start for a, b in backwards)
    assert min(clock) == start and max(clock) == end


def call(ros, service: str) -> Trigger.Response:
    client = ros.node.create_client(Trigger, service)
    try:
        assert client.wait_for_service(timeout_sec=TIMEOUT), service
        future = client.call_async(Trigger.Request())
        assert spin_until(ros.executor, future.done, timeout=TIMEOUT), service
        return future.result()
    finally:
        ros.node.destroy_client(client)


def test_pause_and_resume_by_service(ros, tmp_path):
    """start_paused holds everything back; ~/resume plays, ~/pause holds playback and /clock at
    the bag time reached, ~/toggle_paused and ~/is_paused as rosbag2's services; nothing is lost
    or reordered across pauses."""
    bag = tmp_path / 'bag'
    write_small_bag(bag, {'/odom': ODOMETRY}, n=300)  # 3 s
    arrivals = Arrivals(ros.node, {'/odom': Odometry, '/clock': Clock})
    player = PlayerNode(
        context=ros.ctx,
        parameter_overrides=[
            Parameter('bag', value=str(bag)),
            Parameter('start_paused', value=True),
            Parameter('publish_clock', value=True),
            Parameter('wait_for_subscribers', value=1),
            Parameter('exit_when_done', value=False),
        ],
    )
    ros.executor.add_node(player)
    try:
        assert call(ros, '/bag_player/is_paused').message == 'paused'
        drain(ros, 0.5)
        assert player.published == 0 and arrivals.count('/odom') == 0
        assert call(ros, '/bag_player/resume').message.startswith('resumed')
        assert spin_until(ros.executor, lambda: player.published >= 20, timeout=TIMEOUT)
        paused = call(ros, '/bag_player/pause')
        assert paused.success and paused.message.startswith('paused at ')
        held = player.published
        assert held < 300
        assert call(ros, '/bag_player/is_paused').message == 'paused'
        assert call(ros, '/bag_player/pause').message.startswith('already paused')
        ticks_before = arrivals.count('/clock')
        # ten ticks (0.1 s at clock_rate 100) after the pause have come
        assert spin_until(
            ros.executor, lambda: arrivals.count('/clock') >= ticks_before + 10, timeout=TIMEOUT
        )
        assert player.published <= held + 1  # at most the one on its way as the pause came
        # /clock goes on ticking, holding the bag time where the pause came
        later = [decode_clock(raw) for _, raw in arrivals.msgs['/clock'][ticks_before:]]
        assert later and later[-1] == player._paused_at
        assert all(t <= player._paused_at for t in later)
        assert call(ros, '/bag_player/toggle_paused').message.startswith('resumed')
        assert call(ros, '/bag_player/is_paused').message == 'playing'
        (result,) = player.set_parameters([Parameter('rate', value=20.0)])
        assert result.successful
        assert spin_until(ros.executor, player.finished.is_set, timeout=TIMEOUT)
        assert spin_until(ros.executor, lambda: arrivals.count('/odom') == 300, timeout=TIMEOUT)
        assert positions(arrivals) == list(map(float, range(300)))
        assert not player.failed and player.published == 300
        clock = [decode_clock(raw) for _, raw in arrivals.msgs['/clock']]
        assert all(b >= a for a, b in itertools.pairwise(clock))
        assert call(ros, '/bag_player/resume').message.startswith('not paused')
    finally:
        ros.executor.remove_node(player)
        player.destroy_node()
