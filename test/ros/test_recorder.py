"""bag_recorder: a real recorder process, real DDS, our publishers in this process, own domain.

Bags are read back with independent readers: mcap (+ mcap_ros2 decoding from the embedded
schemas) and rosbags' AnyReader. Every Odometry carries its sequence number k in its header stamp
(k * 10 ms) and in pose.position.x (0.5 k), every PoseStamped its own j in stamp and position.y,
so a bag can be checked message by message: nothing missing, nothing extra, values right.
Counting starts once the recorder's subscriptions match our publishers (they only publish then).
"""

from __future__ import annotations

import itertools
import math
import os
import re
import resource
import signal
import struct
import time
from pathlib import Path

import pytest
import rclpy
import zstandard
from diagnostic_msgs.msg import DiagnosticArray
from geometry_msgs.msg import PoseStamped
from mcap.exceptions import McapError
from mcap.reader import make_reader
from mcap.records import Channel, Message, Schema
from mcap.stream_reader import StreamReader
from mcap_ros2.decoder import DecoderFactory
from nav_msgs.msg import Odometry
from rclpy.duration import Duration
from rclpy.parameter import Parameter
from rclpy.parameter_client import AsyncParameterClient
from rclpy.qos import DurabilityPolicy, QoSProfile, ReliabilityPolicy
from ros_helpers import NodeProcess, private_domain, reserve_domain_id, spin_until, start_node
from rosbags.highlevel import AnyReader
from rosbags.interfaces import QosDurability, QosReliability
from rosgraph_msgs.msg import Clock

from cloe_ros.cli.main import main as cloe
from cloe_ros.io.messages import TYPESTORE, decode_diagnostics
from cloe_ros.ros.common import ParameterError, qos
from cloe_ros.ros.recorder_node import BagRecorder, matched_qos, message_class

pytestmark = pytest.mark.ros

RATE = 100.0  # Hz
STEP_NS = 10_000_000  # stamp step of one odometry message
#: Generous waits (s) for what takes a fraction of that on an idle machine.
TIMEOUT = 60.0


@pytest.fixture
def ros():
    """An rclpy context of our own on a domain of our own, with a node and an executor."""
    with private_domain('recorder_test') as ros:
        yield ros


# -- messages --------------------------------------------------------------------------------


def odometry(k: int) -> Odometry:
    m = Odometry()
    m.header.stamp.sec, m.header.stamp.nanosec = divmod(k * STEP_NS, 1_000_000_000)
    m.header.frame_id, m.child_frame_id = 'world', 'body'
    m.pose.pose.position.x = 0.5 * k
    m.pose.pose.orientation.w = 1.0
    m.twist.twist.angular.z = -0.25 * k
    return m


def pose(j: int) -> PoseStamped:
    m = PoseStamped()
    m.header.stamp.sec = j
    m.header.frame_id = 'world'
    m.pose.position.y = 2.0 * j
    m.pose.orientation.w = 1.0
    return m


def odom_seq(msg) -> int:
    """k of a decoded odometry message, checking every value that encodes it."""
    k = (msg.header.stamp.sec * 1_000_000_000 + msg.header.stamp.nanosec) // STEP_NS
    assert msg.pose.pose.position.x == 0.5 * k
    assert msg.twist.twist.angular.z == -0.25 * k
    assert (msg.header.frame_id, msg.child_frame_id) == ('world', 'body')
    return k


def pose_seq(msg) -> int:
    j = msg.header.stamp.sec
    assert msg.pose.position.y == 2.0 * j and msg.header.frame_id == 'world'
    return j


# -- helpers ---------------------------------------------------------------------------------


class Diagnostics:
    """The recorder's latest /diagnostics status, as a dict of its key/values (``history``: every
    one heard, in order, and ``stamps``: their header stamps, ns of the recorder's clock)."""

    def __init__(self, node) -> None:
        self.values: dict[str, str] = {}
        self.history: list[dict[str, str]] = []
        self.stamps: list[int] = []
        self.names: set[str] = set()
        self.sub = node.create_subscription(
            DiagnosticArray,
            '/diagnostics',
            self._on,
            qos(reliable=True, depth=100),
            raw=True,
        )

    def _on(self, raw: bytes) -> None:
        stamp, statuses = decode_diagnostics(raw)
        for s in statuses:
            if s.name.startswith('bag_recorder: '):
                self.names.add(s.name)
                self.values = dict(s.values)
                self.history.append(self.values)
                self.stamps.append(stamp)

    def count(self, key: str) -> int:
        return int(self.values.get(key, '-1'))


def logs(rec: NodeProcess) -> str:
    """Everything the process wrote (also after stop(), which closes its files)."""
    return rec.output()


def start_recorder(ros, tmp_path: Path, udp_only: bool = False, **params) -> NodeProcess:
    params.setdefault('output', str(tmp_path / 'bag'))
    rec = start_node('bag_recorder', params, ros.domain, tmp_path, udp_only=udp_only)
    if not rec.wait_for('recording to', timeout=TIMEOUT):
        rec.stop(signal.SIGKILL)
        pytest.fail(f'recorder did not start:\n{logs(rec)}')
    return rec


def wait_matched(ros, *publishers, timeout: float = TIMEOUT) -> None:
    ok = spin_until(
        ros.executor, lambda: all(p.get_subscription_count() >= 1 for p in publishers), timeout
    )
    assert ok, 'the recorder did not subscribe to our publishers'


def publish(odom_pub, ref_pub, n: int, on_step=None) -> float:
    """Publish odometry k = 0..n-1 at RATE (and a pose every 10th); returns the start time.
    ``on_step(k)`` runs after odometry k went out and may return True to stop early."""
    t0 = time.monotonic()
    for k in range(n):
        delay = t0 + k / RATE - time.monotonic()
        if delay > 0:
            time.sleep(delay)
        odom_pub.publish(odometry(k))
        if ref_pub is not None and k % 10 == 0:
            ref_pub.publish(pose(k // 10))
        if on_step is not None and on_step(k):
            break
    return t0


def read_with_mcap(mcap_file: Path) -> dict[str, list[tuple[int, object]]]:
    """(log time, decoded message) per topic, with mcap's seeking reader (summary required)."""
    out: dict[str, list] = {}
    with mcap_file.open('rb') as fh:
        reader = make_reader(fh, decoder_factories=[DecoderFactory()])
        for schema, channel, message, decoded in reader.iter_decoded_messages():
            out.setdefault(channel.topic, []).append((message.log_time, schema.name, decoded))
    return out


def stream_read(mcap_file: Path):
    """Messages mcap's non-seeking stream reader finds before the file stops making sense.

    Returns ({topic: [(schema name, data)]}, the exception that ended the stream or None)."""
    schemas, channels, out = {}, {}, {}
    stopped = None
    with mcap_file.open('rb') as fh:
        try:
            for rec in StreamReader(fh).records:
                if isinstance(rec, Schema):
                    schemas[rec.id] = rec.name
                elif isinstance(rec, Channel):
                    channels[rec.id] = (rec.topic, schemas[rec.schema_id])
                elif isinstance(rec, Message):
                    topic, name = channels[rec.channel_id]
                    out.setdefault(topic, []).append((name, rec.data))
        except (McapError, struct.error, zstandard.ZstdError) as err:
            stopped = err
    return out, stopped


def decode(name: str, data: bytes):
    return TYPESTORE.deserialize_cdr(data, name)


def assert_complete_bag(bag: Path, n_odom: int, n_ref: int, t0_ns: int, t1_ns: int) -> None:
    """metadata.yaml + an MCAP with summary holding exactly odometry 0..n-1 and poses 0..m-1."""
    assert (bag / 'metadata.yaml').is_file()
    got = read_with_mcap(bag / f'{bag.name}.mcap')
    assert set(got) == {'/odom', '/reference', '/diagnostics'}
    assert {name for _, name, _ in got['/odom']} == {'nav_msgs/msg/Odometry'}
    assert {name for _, name, _ in got['/reference']} == {'geometry_msgs/msg/PoseStamped'}
    assert [odom_seq(m) for _, _, m in got['/odom']] == list(range(n_odom))
    assert [pose_seq(m) for _, _, m in got['/reference']] == list(range(n_ref))
    times = [t for t, _, _ in got['/odom']]
    # log time = the recorder's clock (system time here) at reception
    assert times == sorted(times) and t0_ns <= times[0] and times[-1] <= t1_ns
    with AnyReader([bag]) as reader:
        counts = {c.topic: (c.msgtype, c.msgcount) for c in reader.connections}
        assert counts['/odom'] == ('nav_msgs/msg/Odometry', n_odom)
        assert counts['/reference'] == ('geometry_msgs/msg/PoseStamped', n_ref)
        seqs = [
            odom_seq(reader.deserialize(raw, c.msgtype))
            for c, _, raw in reader.messages()
            if c.topic == '/odom'
        ]
    assert seqs == list(range(n_odom))


# -- process-level tests ---------------------------------------------------------------------


@pytest.mark.parametrize('sig', [signal.SIGINT, signal.SIGTERM], ids=['SIGINT', 'SIGTERM'])
def test_signal_gives_a_complete_bag(ros, tmp_path: Path, sig: int) -> None:
    odom_pub = ros.node.create_publisher(Odometry, '/odom', qos(depth=1000))
    ref_pub = ros.node.create_publisher(PoseStamped, '/reference', qos(depth=1000))
    diag = Diagnostics(ros.node)
    rec = start_recorder(ros, tmp_path)
    try:
        wait_matched(ros, odom_pub, ref_pub)
        t0_ns = time.time_ns()
        n = 200
        publish(odom_pub, ref_pub, n)
        assert odom_pub.wait_for_all_acked(Duration(seconds=TIMEOUT))
        assert ref_pub.wait_for_all_acked(Duration(seconds=TIMEOUT))
        # the recorder says it has them all (diagnostics come every second), in 2 chunks at
        # least (2 s of publishing, a flush every 0.5 s)
        assert spin_until(
            ros.executor,
            lambda: (
                diag.count('/odom received') == n
                and diag.count('/reference received') == 20
                and diag.count('chunks') >= 2
            ),
            timeout=TIMEOUT,
        ), diag.values
        t1_ns = time.time_ns()
        status = rec.stop(sig)
    finally:
        rec.stop(signal.SIGKILL)
    assert status == 0, logs(rec)
    out = logs(rec)
    assert 'recorded' in out and '/odom 200 received/200 written,' in out, out
    # the documented order: where to, then the topics (its own /diagnostics is there at once)
    assert out.index('recording to ') < out.index('recording /diagnostics ('), out
    assert diag.names == {f'bag_recorder: {tmp_path / "bag"}'}
    for key in ('/odom lost', '/odom dropped', '/odom bytes', 'bytes', 'chunks', 'dropped'):
        assert key in diag.values
    assert diag.count('/odom lost') == 0 and diag.count('/odom dropped') == 0
    assert diag.count('chunks') >= 2  # 2 s of publishing, a flush every 0.5 s
    assert_complete_bag(tmp_path / 'bag', n, 20, t0_ns, t1_ns)


def test_sigkill_loses_at_most_a_flush_period(ros, tmp_path: Path) -> None:
    """SIGKILL while publishing: the bag on disk holds a gap-free prefix with every message the
    recorder had received before its last flush. Which flush that is comes from its reports: a
    report counting R received messages followed by one counting more chunks means a flush
    after the first report wrote those R (what a loaded machine changes is only how many
    messages were still on their way or pending when the kill came: printed, not asserted)."""
    odom_pub = ros.node.create_publisher(Odometry, '/odom', qos(depth=1000))
    ref_pub = ros.node.create_publisher(PoseStamped, '/reference', qos(depth=1000))
    diag = Diagnostics(ros.node)
    bag = tmp_path / 'bag'
    rec = start_recorder(ros, tmp_path)
    n = 560  # 5.6 s at 100 Hz at least; the kill comes while publishing

    def flushed() -> int:
        """Odometry messages the recorder's reports show flushed to the file: R of the last
        report followed by a report with more chunks (0 if none)."""
        h = [(int(v.get('/odom received', 0)), int(v.get('chunks', 0))) for v in diag.history]
        return max((r for (r, c), (_, c2) in itertools.pairwise(h) if c2 > c), default=0)

    try:
        wait_matched(ros, odom_pub, ref_pub)
        published = []

        def kill_once_flushed(k: int) -> bool:
            published.append(k)
            ros.executor.spin_once(timeout_sec=0)  # hear the recorder's reports
            if k >= n - 1 and flushed() >= 100:
                os.kill(rec.proc.pid, signal.SIGKILL)
                return True
            return False

        publish(odom_pub, ref_pub, 100_000, kill_once_flushed)
        assert rec.stop(signal.SIGKILL) == -signal.SIGKILL
    finally:
        rec.stop(signal.SIGKILL)
    assert len(published) >= n
    saved = flushed()
    assert not (bag / 'metadata.yaml').exists()

    # mcap's stream reader, stopping at the cut (no summary, no footer)
    msgs, stopped = stream_read(bag / 'bag.mcap')
    assert stopped is not None  # the file does not end properly
    odom = [odom_seq(decode(name, data)) for name, data in msgs['/odom']]
    ref = [pose_seq(decode(name, data)) for name, data in msgs['/reference']]
    assert odom == list(range(len(odom)))  # a gap-free prefix of what was published
    assert ref == list(range(len(ref)))
    assert saved <= len(odom) <= len(published)  # what was flushed survived the kill

    # cloe bag recover: a complete bag with those messages (maybe more, from a partial chunk)
    assert cloe(['bag', 'recover', str(bag)]) == 0
    fixed = tmp_path / 'bag_recovered'
    got = read_with_mcap(fixed / 'bag_recovered.mcap')
    recovered = [odom_seq(m) for _, _, m in got['/odom']]
    assert recovered == list(range(len(recovered))) and len(recovered) >= len(odom)
    print(
        f'SIGKILL after {len(published)} odometry messages ({saved} reported flushed): '
        f'{len(odom)} read by mcap, {len(recovered)} recovered, '
        f'{len(published) - len(recovered)} lost'
    )
    assert [pose_seq(m) for _, _, m in got['/reference']] == list(range(len(ref)))
    with AnyReader([fixed]) as reader:
        counts = {c.topic: c.msgcount for c in reader.connections}
    assert counts['/odom'] == len(recovered) and counts['/reference'] == len(ref)


def test_best_effort_and_transient_local_publishers_are_matched(ros, tmp_path: Path) -> None:
    best_effort = QoSProfile(depth=100, reliability=ReliabilityPolicy.BEST_EFFORT)
    odom_pub = ros.node.create_publisher(Odometry, '/odom', best_effort)
    latched = QoSProfile(
        depth=1,
        reliability=ReliabilityPolicy.RELIABLE,
        durability=DurabilityPolicy.TRANSIENT_LOCAL,
    )
    latched_pub = ros.node.create_publisher(PoseStamped, '/latched', latched)
    latched_pub.publish(pose(7))  # before the recorder exists
    diag = Diagnostics(ros.node)
    rec = start_recorder(ros, tmp_path, topics=['/odom', 'latched'])
    try:
        wait_matched(ros, odom_pub, latched_pub)
        n = 100
        publish(odom_pub, None, n)
        end_ns = time.time_ns()
        # best effort: what DDS did not deliver never comes; the recorder's counts settle
        # once it has taken what did (two reports made after the publishing the same)

        def settled() -> bool:
            after = [v for t, v in zip(diag.stamps, diag.history) if t > end_ns]
            return len(after) >= 2 and after[-1] == after[-2]

        assert spin_until(ros.executor, settled, timeout=TIMEOUT), diag.values
        assert diag.count('/latched received') == 1
        received = diag.count('/odom received')
        status = rec.stop(signal.SIGINT)
    finally:
        rec.stop(signal.SIGKILL)
    assert status == 0
    out = logs(rec)
    assert 'recording /odom (nav_msgs/msg/Odometry, best effort, volatile)' in out
    assert 'recording /latched (geometry_msgs/msg/PoseStamped, reliable, transient local)' in out
    with AnyReader([tmp_path / 'bag']) as reader:
        conns = {c.topic: c for c in reader.connections}
        assert set(conns) == {'/odom', '/latched'}  # only the topics asked for
        (offered,) = conns['/odom'].ext.offered_qos_profiles
        assert offered.reliability == QosReliability.BEST_EFFORT
        (offered,) = conns['/latched'].ext.offered_qos_profiles
        assert (offered.reliability, offered.durability) == (
            QosReliability.RELIABLE,
            QosDurability.TRANSIENT_LOCAL,
        )
        odom = [
            odom_seq(reader.deserialize(raw, c.msgtype))
            for c, _, raw in reader.messages()
            if c.topic == '/odom'
        ]
        latched_msgs = [
            pose_seq(reader.deserialize(raw, c.msgtype))
            for c, _, raw in reader.messages()
            if c.topic == '/latched'
        ]
    # best effort may drop on a loaded machine (how many: a delivery rate, not asserted); a
    # reliable-only subscription would record nothing. Every one received is in the bag.
    assert 0 < len(odom) == received and odom == sorted(set(odom)) and set(odom) <= set(range(n))
    print(f'best effort: {len(odom)} of {n} recorded')
    assert len(odom) == conns['/odom'].msgcount
    assert latched_msgs == [7]


def test_messages_lost_in_dds_are_counted(ros, tmp_path: Path) -> None:
    """A recorder frozen (SIGSTOP) under a best-effort flood: DDS reports the lost messages.
    Best effort tells of a loss only when a message after the hole arrives, and a recorder slowed
    by a loaded machine may still be draining what came before it: after the flood, one more
    message goes out at a time until the recorder's /diagnostics count the loss (a wait on that
    condition, not on the machine's speed)."""
    diag = Diagnostics(ros.node)
    odom_pub = ros.node.create_publisher(
        Odometry, '/odom', QoSProfile(depth=10, reliability=ReliabilityPolicy.BEST_EFFORT)
    )
    rec = start_recorder(ros, tmp_path, udp_only=True, topics=['/odom'])  # it is stopped
    try:
        wait_matched(ros, odom_pub)
        n, stop_at, cont_at = 3000, 500, 2500
        for k in range(n):
            if k == stop_at:
                os.kill(rec.proc.pid, signal.SIGSTOP)
            if k == cont_at:
                os.kill(rec.proc.pid, signal.SIGCONT)
            odom_pub.publish(odometry(k))
            time.sleep(0.0005)
        deadline = time.monotonic() + TIMEOUT
        while diag.count('/odom lost') <= 0 and time.monotonic() < deadline:
            odom_pub.publish(odometry(n))
            n += 1
            spin_until(ros.executor, lambda: diag.count('/odom lost') > 0, 1.0)
        status = rec.stop(signal.SIGINT)
    finally:
        if rec.proc.poll() is None:
            os.kill(rec.proc.pid, signal.SIGCONT)
        rec.stop(signal.SIGKILL)
    assert status == 0
    m = re.search(r'/odom (\d+) received/(\d+) written(?:/(\d+) lost)?', logs(rec))
    assert m, logs(rec)
    received, written, lost = int(m[1]), int(m[2]), int(m[3] or 0)
    print(
        f'flood of {n}, recorder frozen for {cont_at - stop_at}: {received} received, {lost} lost'
    )
    assert lost > 0 and received + lost <= n and received == written
    with AnyReader([tmp_path / 'bag']) as reader:
        assert {c.topic: c.msgcount for c in reader.connections} == {'/odom': written}


def test_a_full_disk_ends_with_status_1_and_what_was_written(ros, tmp_path: Path) -> None:
    """The recorder's files may grow to 40 kB (RLIMIT_FSIZE: writes beyond fail as on a full
    disk). It stops writing at the first failure, keeps counting, reports ERROR, and SIGINT ends it
    with status 1 and a summary whose written messages are those `cloe bag recover` gets back."""
    odom_pub = ros.node.create_publisher(Odometry, '/odom', qos(depth=1000))
    diag = Diagnostics(ros.node)
    limit = resource.getrlimit(resource.RLIMIT_FSIZE)
    resource.setrlimit(resource.RLIMIT_FSIZE, (40_000, limit[1]))  # inherited by the recorder
    try:
        rec = start_recorder(ros, tmp_path, topics=['/odom'], compression='none')
    finally:
        resource.setrlimit(resource.RLIMIT_FSIZE, limit)
    failed_at = []

    def after_failure(k: int) -> bool:
        if not failed_at and 'nothing more is written' in rec.output():
            failed_at.append(k)
        return bool(failed_at) and k >= failed_at[0] + 20

    try:
        wait_matched(ros, odom_pub)
        publish(odom_pub, None, 1000, after_failure)  # ~750 B each: 40 kB in 0.6 s
        assert failed_at, logs(rec)
        assert odom_pub.wait_for_all_acked(Duration(seconds=TIMEOUT))
        n = failed_at[0] + 21
        assert spin_until(
            ros.executor,
            lambda: diag.count('/odom received') == n and 'failure' in diag.values,
            TIMEOUT,
        ), diag.values
        status = rec.stop(signal.SIGINT)
    finally:
        rec.stop(signal.SIGKILL)
    out = logs(rec)
    assert status == 1, out
    assert 'File too large' in diag.values['failure']
    assert diag.count('dropped') >= 20 and diag.count('write errors') >= 1
    assert re.search(r'cannot finish bag .*File too large; try `cloe bag recover', out), out
    m = re.search(rf'recorded (\d+) messages \(0 lost, (\d+) dropped\) to .*: /odom {n} received/'
                  r'(\d+) written/(\d+) dropped$', out, re.M)  # fmt: skip
    assert m, out
    written, dropped = int(m[1]), int(m[2])
    assert m[3] == m[1] and m[4] == m[2] and written + dropped == n and dropped >= 20
    assert not (tmp_path / 'bag' / 'metadata.yaml').exists()
    assert cloe(['bag', 'recover', str(tmp_path / 'bag')]) == 0
    got = read_with_mcap(tmp_path / 'bag_recovered' / 'bag_recovered.mcap')
    recovered = [odom_seq(m) for _, _, m in got['/odom']]
    # written = surely in the file; recover may find a few more in the chunk cut by the failure
    assert recovered == list(range(len(recovered))) and written <= len(recovered) < n


@pytest.mark.parametrize(
    ('params', 'reason'),
    [
        ({'flush_period': 2.0}, r'flush_period.*(range|out of)'),
        ({'flush_period': 'often'}, r'flush_period.*type'),
        ({'discovery_period': 0.01}, r'discovery_period'),
        ({'qos_depth': 0}, r'qos_depth'),
        ({'compression': 'lz4'}, r"parameter 'compression': 'lz4' is not one of zstd, none"),
        ({'topics': ['/ok', 'not valid!']}, r'topics.*not a valid topic name'),
    ],
    ids=['flush-range', 'flush-type', 'discovery-range', 'depth-range', 'compression', 'topics'],
)
def test_invalid_parameters_stop_the_node_with_a_reason(
    tmp_path: Path, params: dict, reason: str
) -> None:
    domain = reserve_domain_id()
    rec = start_node('bag_recorder', {'output': str(tmp_path / 'bag'), **params}, domain, tmp_path)
    try:
        status = rec.wait(TIMEOUT)
    finally:
        rec.stop(signal.SIGKILL)
    out = logs(rec)
    assert status == 1, out
    assert re.search(reason, out) and 'ERROR:' in out and 'Traceback' not in out, out
    assert not (tmp_path / 'bag').exists()


def test_existing_output_stops_the_node(tmp_path: Path) -> None:
    (tmp_path / 'bag').mkdir()
    (tmp_path / 'bag' / 'keep').write_text('x')
    rec = start_node('bag_recorder', {'output': 'bag'}, reserve_domain_id(), tmp_path)
    try:
        status = rec.wait(TIMEOUT)
    finally:
        rec.stop(signal.SIGKILL)
    assert status == 1
    assert 'bag exists already, not overwriting' in logs(rec)
    assert sorted(p.name for p in (tmp_path / 'bag').iterdir()) == ['keep']


# -- in-process tests ------------------------------------------------------------------------


@pytest.fixture
def recorder(ros, tmp_path: Path):
    """A BagRecorder in the test's context, spun by the test's executor."""
    nodes = []

    def make(**params):
        params.setdefault('output', str(tmp_path / 'bag'))
        node = BagRecorder(
            context=ros.ctx,
            parameter_overrides=[Parameter(k, value=v) for k, v in params.items()],
        )
        ros.executor.add_node(node)
        nodes.append(node)
        return node

    yield make
    for node in nodes:
        ros.executor.remove_node(node)
        node.destroy_node()


def test_runtime_parameter_sets_are_validated(ros, recorder) -> None:
    node = recorder()
    client = AsyncParameterClient(ros.node, 'bag_recorder')
    assert client.wait_for_services(timeout_sec=10)

    def set_one(name, value):
        future = client.set_parameters([Parameter(name, value=value)])
        assert spin_until(ros.executor, future.done, timeout=TIMEOUT)
        (result,) = future.result().results
        return result

    for name, value in (
        ('output', '/tmp/elsewhere'),
        ('topics', ['/a']),
        ('compression', 'none'),
        ('qos_depth', 10),
    ):
        result = set_one(name, value)
        assert not result.successful and 'read-only' in result.reason and name in result.reason
    for value in (5.0, 0.0, math.nan):
        result = set_one('flush_period', value)
        assert not result.successful and 'flush_period' in result.reason
    result = set_one('flush_period', 'fast')
    assert not result.successful and 'type' in result.reason
    assert node.flush_period == 0.5
    # a valid set takes effect: the flush timer runs at the new period
    result = set_one('flush_period', 0.2)
    assert result.successful
    assert node.flush_period == 0.2 and node._flush_timer.timer_period_ns == 200_000_000
    result = set_one('discovery_period', 1.0)
    assert result.successful and node._discovery_timer.timer_period_ns == 1_000_000_000
    # the node's own callback refuses what the descriptors would let through
    own = node._on_set_parameters([Parameter('discovery_period', value=20.0)])
    assert not own.successful and 'discovery_period must be in [0.05, 10.0] s' in own.reason


def test_invalid_overrides_raise_parameter_error(ros, tmp_path: Path) -> None:
    for overrides, reason in (
        ({'flush_period': 1.5}, 'flush_period'),
        ({'compression': 'gzip'}, 'compression'),
        ({'output': ''}, 'output'),
        ({'output': None}, "parameter 'output': must name a bag directory"),  # -p "output:=  "
        ({'qos_depth': 'deep'}, 'qos_depth'),
    ):
        params = {'output': str(tmp_path / 'never'), **overrides}
        with pytest.raises(ParameterError, match=reason):
            BagRecorder(
                context=ros.ctx,
                parameter_overrides=[Parameter(k, value=v) for k, v in params.items()],
            )
    assert not (tmp_path / 'never').exists()


def test_sim_time_skip_and_diagnostics_in_process(ros, recorder, tmp_path: Path) -> None:
    """use_sim_time: log time from /clock. A topic with two types is skipped with a reason."""
    clock_pub = ros.node.create_publisher(Clock, '/clock', 10)
    odom_pub = ros.node.create_publisher(Odometry, '/odom', qos(depth=100))
    dual_a = ros.node.create_publisher(Odometry, '/dual', 10)
    # DDS wants one type per topic in a participant: the second type comes from another one
    other_ctx = rclpy.Context()
    rclpy.init(context=other_ctx, domain_id=ros.domain)
    try:
        other = rclpy.create_node('other_participant', context=other_ctx)
        dual_b = other.create_publisher(PoseStamped, '/dual', 10)

        def dual_types() -> int:
            return len(dict(ros.node.get_topic_names_and_types()).get('/dual', []))

        # the recorder shares this node's graph: it will see both types at its first look
        assert spin_until(ros.executor, lambda: dual_types() == 2, timeout=TIMEOUT)
        _check_sim_time_and_skip(ros, recorder, tmp_path, clock_pub, odom_pub, dual_a, dual_b)
    finally:
        rclpy.try_shutdown(context=other_ctx)


def _check_sim_time_and_skip(ros, recorder, tmp_path, clock_pub, odom_pub, dual_a, dual_b):
    node = recorder(use_sim_time=True, topics=['/odom', '/dual', '/clock'])
    assert node.topics == ['/odom', '/dual', '/clock']
    sim_ns = 42_000_000_123
    clock = Clock()
    clock.clock.sec, clock.clock.nanosec = divmod(sim_ns, 1_000_000_000)

    def tick() -> bool:
        clock_pub.publish(clock)
        return node.get_clock().now().nanoseconds == sim_ns

    assert spin_until(ros.executor, tick, timeout=TIMEOUT)
    assert spin_until(ros.executor, lambda: odom_pub.get_subscription_count() >= 1, TIMEOUT)
    for k in range(5):
        odom_pub.publish(odometry(k))
    assert spin_until(ros.executor, lambda: node._writer.topic_counts.get('/odom') == 5, TIMEOUT)
    # the sim clock stands still; flushing (steady clock) goes on: the messages reach the file
    flushes = node._writer.chunk_count
    assert spin_until(ros.executor, lambda: node._writer.chunk_count > flushes, timeout=TIMEOUT)
    on_disk, _ = stream_read(tmp_path / 'bag' / 'bag.mcap')
    assert [odom_seq(decode(name, data)) for name, data in on_disk['/odom']] == list(range(5))
    assert '/dual' in node._skipped and 'several types' in node._skipped['/dual']
    assert dual_a.get_subscription_count() == 0 and dual_b.get_subscription_count() == 0
    status = node._diagnostics()
    values = dict(status.values)
    assert values['/odom received'] == '5' and values['skipped topics'] == '1'
    assert status.name == f'bag_recorder: {tmp_path / "bag"}' and status.level == 1  # WARN
    node.close()  # what destroy_node() does first
    got = read_with_mcap(tmp_path / 'bag' / 'bag.mcap')
    assert [(t, odom_seq(m)) for t, _, m in got['/odom']] == [(sim_ns, k) for k in range(5)]
    assert '/dual' not in got


def test_offered_qos_of_every_publisher_is_stored(ros, recorder, tmp_path: Path) -> None:
    reliable_pub = ros.node.create_publisher(Odometry, '/q', qos(reliable=True, depth=10))
    node = recorder(topics=['/q'])
    assert spin_until(ros.executor, lambda: reliable_pub.get_subscription_count() >= 1, TIMEOUT)
    best_effort_pub = ros.node.create_publisher(Odometry, '/q', qos(reliable=False, depth=10))
    assert spin_until(ros.executor, lambda: best_effort_pub.get_subscription_count() >= 1, TIMEOUT)
    assert not node._stats['/q'].reliable  # resubscribed to match both
    node.close()
    with AnyReader([tmp_path / 'bag']) as reader:
        (conn,) = reader.connections
        offered = [q.reliability for q in conn.ext.offered_qos_profiles]
    assert offered == [QosReliability.RELIABLE, QosReliability.BEST_EFFORT]


def test_qos_matching_rule() -> None:
    reliable = QoSProfile(depth=1, reliability=ReliabilityPolicy.RELIABLE)
    best_effort = QoSProfile(depth=1, reliability=ReliabilityPolicy.BEST_EFFORT)
    latched = QoSProfile(
        depth=1,
        reliability=ReliabilityPolicy.RELIABLE,
        durability=DurabilityPolicy.TRANSIENT_LOCAL,
    )
    assert matched_qos([reliable]) == (True, False)
    assert matched_qos([reliable, best_effort]) == (False, False)
    assert matched_qos([latched]) == (True, True)
    assert matched_qos([latched, reliable]) == (True, False)
    assert message_class('nav_msgs/msg/Odometry') is Odometry
    assert message_class('shape_msgs/msg/Plane') is None  # not installed here
    assert message_class('not a type') is None
