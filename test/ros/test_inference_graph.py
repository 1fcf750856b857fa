"""cloe_inference as a process on a domain of its own, seen through DDS: what it loses is counted
(``message_lost``), which vehicles it takes (listed, discovered, its shard), and what it says
about vehicles nothing publishes for.

Every wait is on a condition the node reports, with a timeout a loaded machine meets; nothing is
timed.
"""

from __future__ import annotations

import contextlib
import os
import signal
import zlib
from pathlib import Path

import pytest
from diagnostic_msgs.msg import DiagnosticArray
from nav_msgs.msg import Odometry
from rclpy.qos import QoSProfile, ReliabilityPolicy
from ros_helpers import (
    private_domain,
    reserve_domain_id,
    shared_memory_segments,
    spin_until,
    start_node,
)

from cloe_ros.io.messages import decode_diagnostics
from cloe_ros.ros.fleet import check_shard, shard_of

pytestmark = pytest.mark.ros


@pytest.fixture
def ros():
    with private_domain('inference_graph_test') as ros:
        yield ros


class Diagnostics:
    """The last status per name on /diagnostics, each message decoded once."""

    def __init__(self, ros) -> None:
        self.statuses: dict[str, object] = {}
        ros.node.create_subscription(DiagnosticArray, '/diagnostics', self._take, 100, raw=True)

    def _take(self, raw: bytes) -> None:
        for status in decode_diagnostics(raw)[1]:
            self.statuses[status.name] = status

    def values(self, name: str) -> dict[str, str]:
        status = self.statuses.get(name)
        return {} if status is None else dict(status.values)


def odometry(k: int) -> Odometry:
    m = Odometry()
    m.header.stamp.sec, m.header.stamp.nanosec = 1000 + k // 100, (k % 100) * 10_000_000
    m.header.frame_id, m.child_frame_id = 'world', 'base_link'
    m.pose.pose.position.z = 1.0
    m.pose.pose.orientation.w = 1.0
    return m


def test_messages_lost_in_dds_are_counted_per_topic(ros, tmp_path: Path) -> None:
    """The node is stopped (SIGSTOP) while a reliable publisher whose history holds 10 messages
    publishes 3000 odometry messages; the ones overwritten before the node took them are lost.
    Once it runs again, /diagnostics counts them under odom_lost, and what it received plus what
    it lost is what was published (reliable delivery: every other message arrives)."""
    n = 3000
    pub = ros.node.create_publisher(
        Odometry, '/odom', QoSProfile(depth=10, reliability=ReliabilityPolicy.RELIABLE)
    )
    diagnostics = Diagnostics(ros)
    node = start_node('cloe_inference', {'diagnostics_period': 0.2}, ros.domain, tmp_path,
                      udp_only=True)  # fmt: skip
    name = 'cloe_inference: /'
    try:
        assert spin_until(ros.executor, lambda: pub.get_subscription_count() >= 1, 60), (
            node.output()
        )
        assert spin_until(ros.executor, lambda: diagnostics.values(name), 60), node.output()
        assert not shared_memory_segments(node.proc.pid)  # (udp_only: what stops is not in them)
        os.kill(node.proc.pid, signal.SIGSTOP)
        try:
            for k in range(n):
                pub.publish(odometry(k))
        finally:
            os.kill(node.proc.pid, signal.SIGCONT)

        def counts() -> tuple[int, int]:
            values = diagnostics.values(name)
            return int(values['odom_received']), int(values['odom_lost'])

        assert spin_until(ros.executor, lambda: sum(counts()) >= n, 120), (counts(), node.output())
        received, lost = counts()
        print(f'published {n}: the node received {received} and counts {lost} lost')
        assert lost > 0 and received + lost == n
        values = diagnostics.values(name)
        assert values['reference_lost'] == '0' and values['reference_plan_lost'] == '0'
        assert diagnostics.statuses[name].level == 1  # WARN
        assert f'lost in DDS: {lost} odom' in diagnostics.statuses[name].message
        assert node.stop(signal.SIGINT) == 0
    finally:
        if node.proc.poll() is None:
            os.kill(node.proc.pid, signal.SIGCONT)
        node.stop(signal.SIGKILL)


def test_what_the_subscription_history_overwrites_is_counted_by_the_stamps(ros, tmp_path):
    """The node (qos_depth 100) is stopped (SIGSTOP) while a reliable publisher whose history
    holds all 3000 messages publishes them. When it runs again, DDS resends them; where its
    threads take them faster than the node handles them, the node's own history overwrites
    some, and DDS reports none of that (``odom_lost`` 0): the odometry's stamps show the hole,
    and ``odom_missing`` counts it. Whether the history overwrites any depends on the pace of
    the resends against the node's speed, which this test must not depend on (a faster node
    took them all, on a loaded machine); either way what was received plus what is missing is
    what was published. (test/core/test_hostile_inputs.py counts such a hole exactly.)"""
    n = 3000
    pub = ros.node.create_publisher(
        Odometry, '/odom', QoSProfile(depth=n, reliability=ReliabilityPolicy.RELIABLE)
    )
    diagnostics = Diagnostics(ros)
    node = start_node('cloe_inference', {'diagnostics_period': 0.2, 'qos_depth': 100},
                      ros.domain, tmp_path, udp_only=True)  # fmt: skip
    name = 'cloe_inference: /'

    def counts() -> tuple[int, int, int]:
        values = diagnostics.values(name)
        return tuple(int(values.get(k, 0)) for k in ('odom_received', 'odom_missing',
                                                     'odom_lost'))  # fmt: skip

    try:
        assert spin_until(ros.executor, lambda: pub.get_subscription_count() >= 1, 60), (
            node.output()
        )
        first = 50  # a regular start, taken before the stop
        for k in range(first):
            pub.publish(odometry(k))
        assert spin_until(ros.executor, lambda: counts()[0] >= first, 60), node.output()
        os.kill(node.proc.pid, signal.SIGSTOP)
        try:
            for k in range(first, n):
                pub.publish(odometry(k))
        finally:
            os.kill(node.proc.pid, signal.SIGCONT)
        assert spin_until(ros.executor, lambda: sum(counts()[:2]) >= n, 120), (
            counts(), node.output())  # fmt: skip
        received, missing, lost = counts()
        print(f'published {n}: received {received}, missing {missing}, lost in DDS {lost}')
        assert received + missing == n and lost == 0
        assert node.stop(signal.SIGINT) == 0
    finally:
        if node.proc.poll() is None:
            os.kill(node.proc.pid, signal.SIGCONT)
        node.stop(signal.SIGKILL)


# -- vehicles: listed, discovered, sharded -------------------------------------------------------


@pytest.fixture
def context():
    import rclpy

    ctx = rclpy.Context()
    rclpy.init(context=ctx, domain_id=reserve_domain_id())
    try:
        yield ctx
    finally:
        rclpy.try_shutdown(context=ctx)


def _inference(context, **params):
    from rclpy.parameter import Parameter

    from cloe_ros.ros.inference_node import InferenceNode

    overrides = [Parameter(k, value=v) for k, v in params.items()]
    return InferenceNode(context=context, parameter_overrides=overrides)


def _executor(context, *nodes):
    from rclpy.executors import SingleThreadedExecutor

    ex = SingleThreadedExecutor(context=context)
    for n in nodes:
        ex.add_node(n)
    return ex


@contextlib.contextmanager
def _spinning(context, *nodes):
    """An executor of ``nodes`` for the ``with`` block; then it shuts down and the nodes are
    destroyed, however the block ended."""
    ex = _executor(context, *nodes)
    try:
        yield ex
    finally:
        ex.shutdown()
        for n in nodes:
            n.destroy_node()


class Stderr:
    """What this test's processes wrote to stderr (pytest's ``capfd``), gathered as it comes."""

    def __init__(self, capfd) -> None:
        self._capfd, self.text = capfd, ''

    def has(self, words: str) -> bool:
        """Whether ``words`` is in what was written so far."""
        self.text += self._capfd.readouterr().err
        return words in self.text


def _vehicle_publishers(node, namespace: str) -> list:
    from geometry_msgs.msg import PoseStamped

    return [node.create_publisher(Odometry, f'{namespace}/odom', 10),
            node.create_publisher(PoseStamped, f'{namespace}/reference', 10)]  # fmt: skip


def test_shards_are_a_stable_hash_of_the_namespace():
    """crc32 of the namespace's UTF-8 bytes, mod the count: the same in every process (Python's
    own str hash is salted per process)."""
    assert zlib.crc32(b'/uav1') == 3103547451
    assert [shard_of(f'/uav{k}', 3) for k in range(1, 13)] == [0, 0, 1, 0, 0, 2, 1, 0, 0, 2, 0, 1]
    assert {shard_of(f'/uav{k}', 1) for k in range(100)} == {0}
    assert check_shard(2, 3) is None
    assert check_shard(3, 3).startswith('must be below shard_count (3), got 3')


@pytest.mark.parametrize(('index', 'count'), [(3, 3), (1, 1)])
def test_a_shard_index_beyond_the_count_is_a_startup_error(context, index, count):
    from cloe_ros.ros.common import ParameterError

    with pytest.raises(ParameterError) as info:
        _inference(context, shard_index=index, shard_count=count)
    assert str(info.value).startswith(
        f"parameter 'shard_index': must be below shard_count ({count}), got {index}"
    )


def test_shards_without_a_list_or_discovery_are_a_startup_error(context):
    """Without ``vehicles`` or ``discover`` a node infers the one un-namespaced vehicle: every
    shard but one would sit idle, so each is refused and says why."""
    from cloe_ros.ros.common import ParameterError

    for index in range(3):
        with pytest.raises(ParameterError) as info:
            _inference(context, shard_index=index, shard_count=3)
        assert str(info.value).startswith(
            "parameter 'shard_count': 3 shards split the vehicles listed (vehicles:=[...]) or "
            'discovered (discover:=true)')  # fmt: skip


def test_listed_vehicles_outside_the_shard_are_left_to_the_others(context):
    vehicles = [f'/uav{k}' for k in range(1, 13)]
    nodes = [_inference(context, vehicles=vehicles, shard_index=i, shard_count=3)
             for i in range(3)]  # fmt: skip
    try:
        taken = [sorted(n.vehicle_ns.values()) for n in nodes]
        assert sorted(ns for names in taken for ns in names) == sorted(vehicles)  # once each
        for i, names in enumerate(taken):
            assert all(shard_of(ns, 3) == i for ns in names)
    finally:
        for n in nodes:
            n.destroy_node()


def test_a_shard_with_none_of_the_listed_vehicles_says_it_infers_nothing(context, capfd):
    """/uav1 and /uav2 both belong to shard 0 of 3: shard 1, with no discovery to take up a
    vehicle later, would infer nothing ever. It starts (the list may be the whole swarm's, given
    to every node) but warns, and its status is WARN."""
    from cloe_ros.ros.inference_node import KERNELS_NOTE

    inf = _inference(context, vehicles=['/uav1', '/uav2'], shard_index=1, shard_count=3)
    try:
        assert inf.vehicles == [] and inf.idle
        status = inf.node_status()
        assert status.level == 1, status.message
        assert 'none of the listed vehicles is in this shard' in status.message
        err = capfd.readouterr().err
        # (this process's kernels: numba's JIT, test/conftest.py)
        assert ('for no vehicle (shard 1 of 3: 0 of the 2 listed vehicles; '
                f"{KERNELS_NOTE['jit']})") in err
        assert 'none of the 2 listed vehicles belongs to shard 1 of 3' in err
    finally:
        inf.destroy_node()
    discovering = _inference(context, vehicles=['/uav1'], shard_index=1, shard_count=3,
                             discover=True)  # fmt: skip
    try:  # with discovery a vehicle of its shard may still appear: no warning
        assert not discovering.idle and discovering.node_status().level == 0
    finally:
        discovering.destroy_node()


def test_two_nodes_inferring_one_vehicle_are_warned_of(context, capfd):
    """Two nodes given the same shard (here: no shards at all) both publish /uav1/cloe/state:
    each says so in its log and in /diagnostics, and stops saying it when the other leaves."""
    first = _inference(context, vehicles=['/uav1'], discovery_period=0.1)
    second = _inference(context, vehicles=['/uav1'], discovery_period=0.1,
                        cli_args=['--ros-args', '-r', '__node:=cloe_inference_copy'])  # fmt: skip
    ex = _executor(context, first, second)
    try:
        def doubled(node) -> str:
            return dict(node.node_status().values)['published_elsewhere_too']

        assert spin_until(ex, lambda: doubled(first) == doubled(second) == '/uav1', 30)
        assert first.node_status().level == 1
        assert 'cloe/state also published by another node: /uav1' in first.node_status().message
        spin_until(ex, lambda: False, 0.3)  # (let the log lines reach stderr)
        err = capfd.readouterr().err
        assert err.count('/uav1: 1 other publisher(s) of /uav1/cloe/state') == 2, err
        ex.remove_node(second)
        second.destroy_node()
        second = None
        assert spin_until(ex, lambda: doubled(first) == '', 30)
    finally:
        ex.shutdown()
        for n in (first, second):
            if n is not None:
                n.destroy_node()


def test_publishers_missing_waits_for_the_timeout_as_the_warning_does(context):
    """Before publisher_timeout, a vehicle without publishers is neither WARN nor listed in its
    publishers_missing (the value agrees with the status and the node's without_publishers)."""
    inf = _inference(context, vehicles=['/uav9'], discovery_period=0.1, publisher_timeout=600.0)
    with _spinning(context, inf) as ex:
        assert spin_until(ex, lambda: inf._missing['/uav9'] == ['odom', 'reference'], 30)
        status = inf.vehicle_status('/uav9', 0.0)
        assert dict(status.values)['publishers_missing'] == ''
        assert 'nothing publishes' not in status.message
        assert dict(inf.node_status().values)['without_publishers'] == ''


def test_a_listed_vehicle_without_publishers_is_warned_of(context, capfd):
    """/uav1 has publishers, /uav9 has none: after publisher_timeout, /uav9 is WARN in
    /diagnostics and the log says what nothing publishes."""
    inf = _inference(context, vehicles=['/uav1', '/uav9'], discovery_period=0.1,
                     publisher_timeout=0.5)  # fmt: skip
    helper = rclpy_node(context)
    _vehicle_publishers(helper, '/uav1')  # (the helper node holds them)
    with _spinning(context, inf, helper) as ex:
        assert spin_until(ex, lambda: inf.node_status().level == 1, 30)
        assert dict(inf.node_status().values)['without_publishers'] == '/uav9'
        statuses = {v: inf.vehicle_status(v, 0.0) for v in inf.vehicles}
        assert dict(statuses['/uav9'].values)['publishers_missing'] == 'odom, reference'
        assert 'nothing publishes odom and reference' in statuses['/uav9'].message
        assert dict(statuses['/uav1'].values)['publishers_missing'] == ''
        assert 'nothing publishes' not in statuses['/uav1'].message
        spin_until(ex, lambda: False, 0.3)  # (let the log line reach stderr)
        err = capfd.readouterr().err
        assert '/uav9: nothing publishes /uav9/odom and /uav9/reference' in err
        assert 'discover:=true' in err and '/uav1: nothing' not in err


def test_inputs_published_as_another_type_are_warned_of(context, capfd):
    """/uav1's odom and reference are both published as PoseStamped: a publisher of the wrong
    type never matches the node's subscription, so the odometry is as missing as if nothing
    published it, and the warning and /diagnostics say what it is published as (before: the
    node counted the publishers, whatever their type, and waited with status OK, saying
    nothing)."""
    import rclpy
    from geometry_msgs.msg import PoseStamped

    # (in a participant of its own: one participant holds a topic with one type only)
    other = rclpy.Context()
    rclpy.init(context=other, domain_id=context.get_domain_id())
    try:
        helper = rclpy.create_node('wrong_types', context=other)
        for name in ('odom', 'reference'):
            helper.create_publisher(PoseStamped, f'/uav1/{name}', 10)
        _warned_of_the_wrong_type(context, capfd)
    finally:
        rclpy.try_shutdown(context=other)


def _warned_of_the_wrong_type(context, capfd) -> None:
    inf = _inference(context, vehicles=['/uav1'], discovery_period=0.1, publisher_timeout=0.5)
    with _spinning(context, inf) as ex:

        def status():  # (once the other participant's publishers are discovered)
            return inf.vehicle_status('/uav1', 0.0)

        assert spin_until(ex, lambda: dict(status().values)['publishers_missing'] == 'odom', 30)
        assert status().level == inf.node_status().level == 1
        assert dict(inf.node_status().values)['without_publishers'] == '/uav1'
        assert ('odom is published as geometry_msgs/msg/PoseStamped, not as '
                'nav_msgs/msg/Odometry for') in status().message  # fmt: skip
        err = Stderr(capfd)
        wrong = ('/uav1: /uav1/odom is published as geometry_msgs/msg/PoseStamped, not as '
                 'nav_msgs/msg/Odometry (for ')  # fmt: skip
        assert spin_until(ex, lambda: err.has(wrong), 30), err.text
        assert 'nothing publishes' not in err.text and 'discover:=true' not in err.text


def test_a_listed_vehicle_that_stops_fell_silent(context, capfd):
    """/uav1 is listed, publishes odometry that the node receives, then its publishers go: the
    warning says it fell silent, as for a discovered vehicle (before: it asked whether /uav1 was
    the namespace of a vehicle that flies, the hint for a namespace nothing ever published)."""
    inf = _inference(context, vehicles=['/uav1'], discovery_period=0.1, publisher_timeout=0.5)
    helper = rclpy_node(context)
    odom, reference = _vehicle_publishers(helper, '/uav1')
    with _spinning(context, inf, helper) as ex:
        assert spin_until(ex, lambda: odom.get_subscription_count() > 0, 30)
        message = Odometry()
        message.header.frame_id, message.child_frame_id = 'world', 'base_link'
        message.pose.pose.orientation.w = 1.0
        odom.publish(message)
        assert spin_until(ex, lambda: '/uav1' in inf._odom_heard, 30)
        helper.destroy_publisher(odom)
        helper.destroy_publisher(reference)
        err = Stderr(capfd)
        assert spin_until(ex, lambda: err.has('the vehicle fell silent'), 30), err.text
        assert '/uav1: nothing publishes /uav1/odom and /uav1/reference' in err.text
        assert 'namespace of a vehicle that flies' not in err.text


def test_no_list_while_namespaced_vehicles_fly_gives_a_hint(context, capfd):
    inf = _inference(context, discovery_period=0.1, publisher_timeout=0.5)
    helper = rclpy_node(context)
    for namespace in ('/uav1', '/uav2'):
        _vehicle_publishers(helper, namespace)  # (the helper node holds them)
    with _spinning(context, inf, helper) as ex:
        hint = 'set vehicles:=[/uav1, /uav2] or discover:=true'
        err = Stderr(capfd)
        assert spin_until(ex, lambda: err.has(hint), 30), err.text
        assert 'nothing publishes /odom and /reference' in err.text


def test_no_list_gives_the_hint_when_the_vehicles_take_off_after_the_warning(context, capfd):
    """A node started with no list before the vehicles fly warns that nothing publishes /odom;
    when namespaced vehicles take off later, it says so too (once), with the hint."""
    inf = _inference(context, discovery_period=0.1, publisher_timeout=0.5)
    helper = rclpy_node(context)
    with _spinning(context, inf, helper) as ex:
        err = Stderr(capfd)
        assert spin_until(ex, lambda: err.has('no vehicles:=[...] given'), 30), err.text
        assert 'nothing publishes /odom and /reference' in err.text and 'uav' not in err.text
        for namespace in ('/uav1', '/uav2'):
            _vehicle_publishers(helper, namespace)
        hint = 'set vehicles:=[/uav1, /uav2] or discover:=true'
        assert spin_until(ex, lambda: err.has(hint), 30), err.text
        spin_until(ex, lambda: False, 1.0)  # (more polls of the graph: no second hint)
        err.has('')
        assert err.text.count(hint) == 1, err.text


def test_a_best_effort_publisher_is_named_with_the_setting_that_matches_it(context, capfd):
    """A reliable subscription matches no best-effort publisher: the node names the topic, the
    policy in words and the setting that fixes it."""
    inf = _inference(context, vehicles=['/uav1'])
    helper = rclpy_node(context)
    offered = QoSProfile(depth=10, reliability=ReliabilityPolicy.BEST_EFFORT)
    helper.create_publisher(Odometry, '/uav1/odom', offered)
    with _spinning(context, inf, helper) as ex:
        err = Stderr(capfd)
        # (the helper's own publisher logs an incompatible QoS too: wait for the node's words)
        words = 'a publisher offers a QoS incompatible'
        assert spin_until(ex, lambda: err.has(words), 30), err.text
        assert ('/uav1/odom: a publisher offers a QoS incompatible with the subscription '
                '(reliability); for a best-effort publisher set qos_reliability:=best_effort'
                in err.text), err.text  # fmt: skip


def test_discovery_takes_up_vehicles_that_appear_and_reports_those_that_fall_silent(context):
    inf = _inference(context, discover=True, discovery_period=0.1, publisher_timeout=0.5)
    helper = rclpy_node(context)
    with _spinning(context, inf, helper) as ex:
        assert inf.vehicles == []  # nothing flies yet: no vehicle, not even the root one
        pubs = _vehicle_publishers(helper, '/uav3')
        # a namespace with odometry but no reference is not a vehicle
        lone = helper.create_publisher(Odometry, '/uav4/odom', 10)
        assert spin_until(ex, lambda: '/uav3' in inf.vehicles, 30)
        assert dict(inf.node_status().values)['vehicles'] == '/uav3'
        assert inf.vehicle_status('/uav3', 0.0).name == 'cloe_inference: /uav3'
        for pub in pubs:
            helper.destroy_publisher(pub)
        assert spin_until(
            ex, lambda: dict(inf.node_status().values)['without_publishers'] == '/uav3', 30
        )
        assert inf.vehicles == ['/uav3'] and lone is not None


def test_load_is_the_share_of_wall_time_in_callbacks_the_worst_timer_delay_and_the_longest():
    import time

    from cloe_ros.ros.inference_node import Load

    load = Load()
    nap = load.timed(lambda s: time.sleep(s) or 'slept')
    assert nap(0.05) == 'slept' and load.seconds >= 0.05
    assert nap(0.0) == 'slept'
    busy, late, longest = load.read()
    assert 0.0 < busy <= 1.0 and late == 0.0
    assert longest >= 0.05  # the longer of the two callbacks
    assert load.read() == (0.0, 0.0, 0.0)  # nothing ran since the last reading
    with pytest.raises(ZeroDivisionError):  # what a callback raises goes through
        load.timed(lambda: 1 / 0)()
    # a 1 s timer: on time, then 0.25 s late (its next deadline stays on the grid)
    load.heartbeat(1.0, now=10.0)
    load.heartbeat(1.0, now=11.0)
    load.heartbeat(0.75, now=12.25)
    assert load.read(now=12.5)[1] == 0.25
    assert load.read(now=12.9)[1] == 0.25  # no heartbeat since: the last one's lateness
    assert load.read(now=15.5)[1] == 2.5  # the deadline of 13.0 passed, the timer not run
    load.heartbeat(0.5, now=16.5)
    assert load.read(now=16.75)[1] == 3.5
    load.heartbeat(1.0, now=17.0)  # on time again
    assert load.read(now=17.25)[1] == 0.0
    load.heartbeat(None, now=18.0)  # (a cancelled timer: no next deadline)
    assert load.read(now=30.0)[1] == 0.0


@pytest.mark.parametrize('where', ['odometry callback', 'batch timer'])
def test_a_node_at_its_limit_says_so_and_recovers(context, capfd, where):
    """Each odometry message is made to take 1 s of the node's time (a sleep, so what the node
    measures is the same on any machine), in its odometry callback or in the batch its timer
    steps (two vehicles, one of them silent, so no batch is ever complete at once), and one
    arrives at every turn of the executor: the node works back to back and its 0.2 s
    graph-poll timer waits behind, so its own status turns WARN, busy at its limit and behind
    its inputs, with a warning in the log. Once the messages stop, the next period finds it
    idle and on time: OK again, and logged."""
    import time

    from cloe_ros.ros.inference_node import BUSY_WARN, LATE_WARN

    batched = where == 'batch timer'
    inf = _inference(context, vehicles=['/uav1', '/uav2'] if batched else ['/uav1'],
                     diagnostics_period=0.5, discovery_period=0.2, publisher_timeout=600.0,
                     batch_period=0.005 if batched else 0.0)  # fmt: skip
    helper = rclpy_node(context)
    odom, _ = _vehicle_publishers(helper, '/uav1')
    owner, name = (inf.fleet, 'advance') if batched else (inf.engines['/uav1'], 'add_odometry')
    fast = getattr(owner, name)

    def slow(*args):
        time.sleep(1.0)
        return fast(*args)

    setattr(owner, name, slow)
    sent = [0]

    def overload_reported() -> bool:
        odom.publish(odometry(sent[0]))
        sent[0] += 1
        status = inf.node_status()
        return (status.level == 1 and 'at its limit' in status.message
                and 'behind its inputs' in status.message)  # fmt: skip

    with _spinning(context, inf, helper) as ex:
        assert spin_until(ex, lambda: odom.get_subscription_count() >= 1, 30)
        assert spin_until(ex, overload_reported, 60), inf.node_status()
        status = inf.node_status()
        values = dict(status.values)
        assert float(values['busy']) >= BUSY_WARN and float(values['late_s']) >= LATE_WARN
        assert float(values['longest_callback_s']) >= 1.0  # (each of those callbacks slept 1 s)
        assert 'shard_count' in status.message
        assert spin_until(ex, lambda: inf.node_status().level == 0, 60), inf.node_status()
        values = dict(inf.node_status().values)
        assert float(values['busy']) < BUSY_WARN and float(values['late_s']) < LATE_WARN
        err = capfd.readouterr().err
        assert f'{len(inf.vehicles)} vehicle(s):' in err and 'at its limit' in err
        assert 'keeps up with its inputs again' in err


def rclpy_node(context):
    import rclpy

    return rclpy.create_node('graph_test_helper', context=context)


def test_three_shards_split_twelve_simulated_vehicles(ros, tmp_path: Path) -> None:
    """One simulator flies 12 vehicles; 3 inference nodes (discover, shard_count 3) split them:
    every vehicle's cloe/state has exactly one publisher, the node of its shard, and reaches us;
    the nodes' reported vehicle lists are a partition of the 12."""
    vehicles = [f'/uav{k}' for k in range(1, 13)]
    states: dict[str, int] = dict.fromkeys(vehicles, 0)
    for v in vehicles:
        ros.node.create_subscription(
            Odometry, f'{v}/cloe/state',
            lambda raw, v=v: states.__setitem__(v, states[v] + 1), 100, raw=True,
        )  # fmt: skip
    diagnostics = Diagnostics(ros)
    # light on CPU: 20 Hz odometry and inference, no predictions, half real time
    shards = [
        start_node('cloe_inference', {
            'discover': True, 'shard_index': i, 'shard_count': 3, 'discovery_period': 0.2,
            'rate': 20.0, 'algorithm': 'cloe_sm', 'prediction_horizon': 0.0,
            'diagnostics_period': 0.5,
        }, ros.domain, tmp_path, ['-r', f'__node:=shard{i}'])
        for i in range(3)
    ]  # fmt: skip
    sim = start_node('quadrotor_sim', {
        'vehicles': vehicles, 'scenario': 'hover', 'sim_rate': 200.0, 'odom_rate': 20.0,
        'reference_rate': 20.0, 'real_time_factor': 0.5, 'publish_truth': False,
    }, ros.domain, tmp_path)  # fmt: skip
    procs = [*shards, sim]
    try:
        def everything() -> bool:
            return all(states.values()) and all(
                len(diagnostics.values(f'shard{i}').get('vehicles', '').split())
                == sum(shard_of(v, 3) == i for v in vehicles)
                for i in range(3)
            )

        assert spin_until(ros.executor, everything, 180), (
            states, {i: diagnostics.values(f'shard{i}') for i in range(3)},
            '\n'.join(p.output()[-2000:] for p in procs),
        )
        reported = {i: set(diagnostics.values(f'shard{i}')['vehicles'].split()) for i in range(3)}

        def named() -> bool:
            # a publisher's endpoint can be discovered before its node's name ('_NODE_NAME_
            # UNKNOWN_' until then): wait for the names, then look
            return all(p.node_name != '_NODE_NAME_UNKNOWN_' for v in vehicles
                       for p in ros.node.get_publishers_info_by_topic(f'{v}/cloe/state'))

        assert spin_until(ros.executor, named, 60)
        for v in vehicles:
            publishers = ros.node.get_publishers_info_by_topic(f'{v}/cloe/state')
            assert [p.node_name for p in publishers] == [f'shard{shard_of(v, 3)}'], v
            assert [i for i in range(3) if v in reported[i]] == [shard_of(v, 3)], v
        assert set().union(*reported.values()) == set(vehicles)
    finally:
        for p in procs:
            p.stop(signal.SIGINT)
