"""Simulator and inference nodes spun by rclpy executors in one process, a context per test."""

from __future__ import annotations

import array
import math
import os
import time
from pathlib import Path

import numpy as np
import pytest
import rclpy
from diagnostic_msgs.msg import DiagnosticArray
from geometry_msgs.msg import PoseStamped
from nav_msgs.msg import Odometry
from nav_msgs.msg import Path as PathMessage
from rclpy.executors import SingleThreadedExecutor
from rclpy.parameter import Parameter
from rclpy.parameter_client import AsyncParameterClient
from ros_helpers import spin_until
from std_msgs.msg import Float64MultiArray
from std_srvs.srv import Trigger

from cloe_ros.core.engine import NS, VehicleEngine
from cloe_ros.core.fleet import PooledEstimator
from cloe_ros.core.kinematics import state_to_odometry
from cloe_ros.core.model import PARAMETER_NAMES
from cloe_ros.core.samples import OdometrySample
from cloe_ros.core.simulator import QuadrotorSimulator, get_scenario, true_parameters
from cloe_ros.io import messages
from cloe_ros.io.config import RANGES
from cloe_ros.io.outputs import PARAMETER_LABELS
from cloe_ros.ros import inference_node
from cloe_ros.ros.common import ParameterError, qos
from cloe_ros.ros.inference_node import DIAGNOSTICS_OVERDUE, InferenceNode
from cloe_ros.ros.sim_node import SimulatorNode

pytestmark = pytest.mark.ros

REPO = Path(__file__).resolve().parents[2]
#: History depth of the tests' publishers and subscriptions: more than any topic's messages in a
#: test, so a reliable writer never drops what a reader short of CPU has not taken yet.
DEPTH = 2000
#: Generous waits (s) for what takes a fraction of that on an idle machine.
TIMEOUT = 60.0


@pytest.fixture
def context():
    ctx = rclpy.Context()
    rclpy.init(context=ctx)
    try:
        yield ctx
    finally:
        rclpy.try_shutdown(context=ctx)


class Collector:
    """Raw subscriptions that keep every message of some topics: reliable, with a history deeper
    than any test's messages per topic (a test process short of CPU falls behind, it loses
    nothing); ``latched`` topics are subscribed transient local, so their message arrives even if
    it was published before the subscription matched."""

    def __init__(self, ctx, topics: dict[str, type], latched: tuple[str, ...] = ()):
        self.node = rclpy.create_node('collector', context=ctx)
        self.msgs: dict[str, list[bytes]] = {t: [] for t in topics}
        for topic, cls in topics.items():
            self.node.create_subscription(
                cls, topic, lambda raw, t=topic: self.msgs[t].append(raw),
                qos(depth=DEPTH, transient_local=topic in latched), raw=True,
            )  # fmt: skip


def _executor(ctx, *nodes):
    ex = SingleThreadedExecutor(context=ctx)
    for n in nodes:
        ex.add_node(n)
    return ex


def test_sim_and_inference_infer_the_simulated_state(context):
    """Real time, one executor serving all three nodes. Nothing is lost whatever the load: every
    history (the nodes' ``qos_depth``, the collector's) holds the whole flight (401 samples per
    topic), the collector subscribes to the latched ``true_parameters`` transient local, and the
    inference node waits for the reference (``reference_timeout`` 60 s: a test process short of
    CPU may take a burst of odometry before the references that came with it, and the engine
    would then step on the held reference; that rule is tested in test/core/test_engine.py)."""
    sim = SimulatorNode(context=context, parameter_overrides=[
        Parameter('duration', value=4.0), Parameter('real_time_factor', value=1.0),
        Parameter('wait_for_subscribers', value=1),
        Parameter('qos_depth', value=DEPTH)])  # fmt: skip
    inf = InferenceNode(context=context, parameter_overrides=[
        Parameter('algorithm', value='cloe_sm'), Parameter('qos_depth', value=DEPTH),
        Parameter('reference_timeout', value=60.0)])  # fmt: skip
    col = Collector(context, {
        'cloe/state': Odometry, 'cloe/parameters': Float64MultiArray, 'ground_truth': Odometry,
        '/diagnostics': DiagnosticArray, 'true_parameters': Float64MultiArray},
        latched=('true_parameters',))  # fmt: skip
    ex = _executor(context, sim, inf, col.node)
    try:
        assert spin_until(ex, lambda: sim.done, timeout=TIMEOUT)
        # every odometry sample taken by the node, and every estimate it made taken here
        stats = inf.engines[''].stats
        assert spin_until(ex, lambda: stats.odom_received == 401, timeout=TIMEOUT), stats
        assert spin_until(
            ex, lambda: len(col.msgs['cloe/state']) == stats.steps, timeout=TIMEOUT
        ), (len(col.msgs['cloe/state']), stats)
        decoded: list = []  # the inference node's statuses (the simulator publishes there too)

        def inference_diagnostics() -> list:  # decodes each message once: the wait stays cheap
            raws = col.msgs['/diagnostics']
            while inference_diagnostics.seen < len(raws):
                _, statuses = messages.decode_diagnostics(raws[inference_diagnostics.seen])
                inference_diagnostics.seen += 1
                if statuses[0].name.startswith('cloe_inference'):
                    decoded.append(statuses)
            return decoded

        inference_diagnostics.seen = 0

        n_diag = len(inference_diagnostics())
        assert spin_until(ex, lambda: len(inference_diagnostics()) > n_diag, timeout=TIMEOUT)
        states = [messages.decode_odometry(r) for r in col.msgs['cloe/state']]
        truth = {m.stamp_ns: m for m in map(messages.decode_odometry, col.msgs['ground_truth'])}
        # every step of 4 s at 100 Hz (the last ones may wait for the next odometry)
        assert len(states) >= 395
        stamps = np.array([s.stamp_ns for s in states])
        assert np.all(np.diff(stamps) == 10_000_000)
        # the inferred position follows the true one (odom is noise-free here)
        err = [np.linalg.norm(s.position - truth[s.stamp_ns].position) for s in states
               if s.stamp_ns in truth and s.stamp_ns > stamps[0] + 2_000_000_000]  # fmt: skip
        assert len(err) > 150 and max(err) < 0.02
        labels, data = messages.decode_float64_multi_array(col.msgs['cloe/parameters'][-1])
        assert tuple(labels) == PARAMETER_LABELS and data.shape == (len(PARAMETER_LABELS),)
        assert labels[27] == 'L.z_dot' and data[28] == pytest.approx(9.81)  # coupling +g
        # ~10 Hz of message time
        assert 38 <= len(col.msgs['cloe/parameters']) <= 42
        tlabels, theta = messages.decode_float64_multi_array(col.msgs['true_parameters'][0])
        assert tlabels == [f'theta.{n}' for n in PARAMETER_NAMES]
        np.testing.assert_allclose(theta, true_parameters())
        (status,) = _vehicles(inference_diagnostics()[-1])
        values = dict(status.values)
        assert status.name == 'cloe_inference: /'
        # OK, unless the odometry has already been silent for STALE_AFTER s (then it says so)
        assert status.level == messages.OK or (
            status.level == messages.WARN and status.message.startswith('running; no odometry for')
        ), status.message
        assert int(values['steps']) == len(states) and values['rejected'] == '0'
    finally:
        ex.shutdown()
        for n in (sim, inf, col.node):
            n.destroy_node()


def _odom_bytes(stamp_ns, zeta, frame='world'):
    p, q, v, w = state_to_odometry(zeta)
    return messages.encode_odometry(OdometrySample(stamp_ns, frame, 'base_link', p, q, v, w))


def _diagnosed(ex, col: Collector, timeout: float = TIMEOUT, **counts: int) -> bool:
    """Spin until the last /diagnostics report heard (one vehicle) counts at least ``counts``
    (``odom_received=204``: the node's counters of that name)."""

    def counted():
        if not col.msgs['/diagnostics']:
            return False
        (st,) = _vehicles(messages.decode_diagnostics(col.msgs['/diagnostics'][-1])[1])
        values = dict(st.values)
        return all(int(values[key]) >= n for key, n in counts.items())

    return spin_until(ex, counted, timeout=timeout)


def _vehicles(statuses: list) -> list:
    """The vehicles' statuses of an inference node's /diagnostics (not the node's own one)."""
    return [s for s in statuses if 'algorithm' in dict(s.values)]


def _ref_bytes(stamp_ns, r):
    return messages.encode_pose_stamped(
        messages.PoseSample(stamp_ns, 'world', np.array([r[0], r[1], r[3]]),
                            np.array([0, 0, math.sin(r[2] / 2), math.cos(r[2] / 2)]))
    )  # fmt: skip


def test_bad_inputs_are_rejected_counted_and_reported(context):
    inf = InferenceNode(
        context=context,
        parameter_overrides=[
            Parameter('vehicles', value=['/uav1']),
            Parameter('diagnostics_period', value=0.2),
        ],
    )
    pub_node = rclpy.create_node('source', context=context)
    odom = pub_node.create_publisher(Odometry, '/uav1/odom', qos(depth=DEPTH))
    ref = pub_node.create_publisher(messages_pose_type(), '/uav1/reference', qos(depth=DEPTH))
    col = Collector(context, {'/uav1/cloe/state': Odometry, '/diagnostics': DiagnosticArray})
    ex = _executor(context, inf, pub_node, col.node)
    try:
        assert spin_until(ex, lambda: odom.get_subscription_count() >= 1, timeout=TIMEOUT)
        assert spin_until(ex, lambda: ref.get_subscription_count() >= 1, timeout=TIMEOUT)
        t0 = 1_000_000_000_000
        zeta = np.zeros(12)
        zeta[10] = 1.0
        r = np.array([0.0, 0.0, 0.0, 1.0])
        good = 0
        for k in range(200):
            stamp = t0 + k * 10_000_000
            odom.publish(_odom_bytes(stamp, zeta))
            ref.publish(_ref_bytes(stamp, r))
            good += 1
            if k == 50:
                bad = zeta.copy()
                bad[0] = math.nan
                odom.publish(_odom_bytes(stamp + 5_000_000, bad))  # non-finite
                odom.publish(_odom_bytes(stamp, zeta))  # duplicate stamp
                odom.publish(_odom_bytes(stamp - 5_000_000, zeta))  # out of order
                odom.publish(_odom_bytes(stamp + 5_000_000, zeta, frame='map'))  # wrong frame
                odom.publish(b'\x00\x01\x00\x00garbage')  # malformed CDR
            spin_until(ex, lambda: False, timeout=0.002)

        # a report counting everything sent: 200 good and 4 bad odometry messages, 1 malformed
        assert _diagnosed(ex, col, odom_received=204, malformed=1)
        (status,) = _vehicles(messages.decode_diagnostics(col.msgs['/diagnostics'][-1])[1])
        values = dict(status.values)
        assert status.level == messages.WARN and 'rejected' in status.message
        assert values['rejected: non-finite odometry'] == '1'
        assert values['rejected: duplicate stamp'] == '1'
        assert values['rejected: out-of-order stamp'] == '1'
        assert values['rejected: wrong frame'] == '1'
        assert values['malformed'] == '1'
        assert values['odom_accepted'] == str(good)
        # (the states come on their own topic: they may be taken after the report)
        assert spin_until(ex, lambda: len(col.msgs['/uav1/cloe/state']) >= 190, timeout=TIMEOUT)
        states = [messages.decode_odometry(b) for b in col.msgs['/uav1/cloe/state']]
        # nothing bad reached the estimator: the hover estimate stays exactly on the data
        assert all(np.all(np.isfinite(s.position)) for s in states)
        assert max(abs(s.position[2] - 1.0) for s in states) < 1e-9
    finally:
        ex.shutdown()
        for n in (inf, pub_node, col.node):
            n.destroy_node()


def test_a_plan_before_the_odometry_does_not_set_the_world_frame(context):
    """world_frame '': a reference_plan in 'map' that arrives first used to lock the frame to
    'map', and every odometry and reference in 'world' was then rejected as the wrong frame."""
    inf = InferenceNode(context=context, parameter_overrides=[
        Parameter('diagnostics_period', value=0.2)])  # fmt: skip
    pub_node = rclpy.create_node('source', context=context)
    odom = pub_node.create_publisher(Odometry, 'odom', qos(depth=DEPTH))
    ref = pub_node.create_publisher(messages_pose_type(), 'reference', qos(depth=DEPTH))
    plan = pub_node.create_publisher(PathMessage, 'reference_plan', qos(depth=DEPTH))
    col = Collector(context, {'cloe/state': Odometry, '/diagnostics': DiagnosticArray})
    ex = _executor(context, inf, pub_node, col.node)
    try:
        for pub in (plan, odom, ref):
            assert spin_until(ex, lambda p=pub: p.get_subscription_count() >= 1, timeout=TIMEOUT)
        t0 = 1_000_000_000_000
        stamps = t0 + np.arange(1, 11) * 100_000_000
        plan.publish(messages.encode_path(messages.PathSample(
            t0, 'map', stamps, np.tile([0.0, 0.0, 1.0], (10, 1)),
            np.tile([0.0, 0.0, 0.0, 1.0], (10, 1)))))  # fmt: skip
        # the plan is in (and refused) before the first odometry is sent
        stats = inf.engines[''].stats
        assert spin_until(ex, lambda: stats.plans_received == 1, timeout=TIMEOUT)
        zeta = np.zeros(12)
        zeta[10] = 1.0
        for k in range(100):
            stamp = t0 + k * 10_000_000
            odom.publish(_odom_bytes(stamp, zeta))
            ref.publish(_ref_bytes(stamp, np.array([0.0, 0.0, 0.0, 1.0])))
            spin_until(ex, lambda: False, timeout=0.002)

        assert _diagnosed(ex, col, odom_received=100)
        (status,) = _vehicles(messages.decode_diagnostics(col.msgs['/diagnostics'][-1])[1])
        values = dict(status.values)
        assert values['rejected: plan before the world frame'] == '1'
        assert values['odom_accepted'] == '100' and values['reference_accepted'] == '100'
        assert "the last: plan before the world frame: plan in 'map'" in status.message
        assert spin_until(ex, lambda: len(col.msgs['cloe/state']) >= 90, timeout=TIMEOUT)
        assert messages.decode_odometry(col.msgs['cloe/state'][-1]).frame_id == 'world'
    finally:
        ex.shutdown()
        for n in (inf, pub_node, col.node):
            n.destroy_node()


def messages_pose_type():
    from geometry_msgs.msg import PoseStamped

    return PoseStamped


def test_reset_service_forgets_the_model(context):
    sim = SimulatorNode(context=context, parameter_overrides=[
        Parameter('duration', value=6.0), Parameter('real_time_factor', value=0.0),
        Parameter('wait_for_subscribers', value=1)])  # fmt: skip
    inf = InferenceNode(context=context, parameter_overrides=[
        Parameter('algorithm', value='cloe_sm')])  # fmt: skip
    client_node = rclpy.create_node('client', context=context)
    client = client_node.create_client(Trigger, '/cloe_inference/reset')
    col = Collector(context, {'cloe/parameters': Float64MultiArray})
    ex = _executor(context, sim, inf, client_node, col.node)
    try:
        assert spin_until(ex, lambda: len(col.msgs['cloe/parameters']) >= 20, timeout=TIMEOUT)
        _, before = messages.decode_float64_multi_array(col.msgs['cloe/parameters'][-1])
        assert np.any(before[:16] != 0)
        assert client.wait_for_service(timeout_sec=TIMEOUT)
        # every message taken before the request was published before the reset
        n_before = len(col.msgs['cloe/parameters'])
        future = client.call_async(Trigger.Request())
        assert spin_until(ex, future.done, timeout=TIMEOUT)
        assert future.result().success and 'reset 1 vehicle' in future.result().message
        n = len(col.msgs['cloe/parameters'])
        assert spin_until(ex, lambda: len(col.msgs['cloe/parameters']) > n + 5, timeout=TIMEOUT)
        after = [messages.decode_float64_multi_array(m)[1] for m in col.msgs['cloe/parameters']]
        # the first estimate after the reset is published at once, with the model at zero
        # (index 0 is the very first estimate, which also starts from zero); it comes after
        # every message taken before the request (how many more were in flight as the reset came
        # depends on the scheduler, not on the node)
        restarted = [k for k, d in enumerate(after) if k > 0 and not np.any(d[:16])]
        assert len(restarted) == 1 and restarted[0] >= n_before
        assert inf.engines[''].stats.resets == 1
    finally:
        ex.shutdown()
        for n in (sim, inf, client_node, col.node):
            n.destroy_node()


@pytest.mark.parametrize(
    'name, value, reason',
    [
        ('rate', 0.5, 'Parameter rate out of range'),
        ('rate', 'fast', "expecting type 'DOUBLE'"),
        ('algorithm', 'kalman', "'kalman' is not one of cloe, cloe_sm, cloe_iv"),
        ('gamma_theta', -1.0, 'Parameter gamma_theta out of range'),
        ('sm_exponents', [1.5] * 12, 'must lie in [0, 1), got 1.5 at index 0'),
        ('sm_gains', [0.1] * 3, 'needs 12 numbers, one per state, got 3'),
        ('l_min', 60.0, 'must be at most l_max (50), got 60.0'),
        ('vehicles', ['/a b'], "vehicle namespace '/a b' is not valid"),
        ('qos_reliability', 'sometimes', "'sometimes' is not one of reliable, best_effort"),
    ],
)
def test_invalid_startup_parameters_are_refused_with_a_reason(context, name, value, reason):
    """The documented form: ``parameter '<name>': <reason>`` (printed after ``ERROR: ``); the
    refused node is not left in the ROS graph."""
    unique, renamed = unique_node_name()
    with pytest.raises(ParameterError) as info:
        InferenceNode(context=context, parameter_overrides=[Parameter(name, value=value)],
                      cli_args=renamed)  # fmt: skip
    assert str(info.value).startswith(f"parameter '{name}': ")
    assert reason in str(info.value)
    assert not in_graph(context, unique)  # the refused node was destroyed


def unique_node_name() -> tuple[str, list[str]]:
    """A name no other node of the domain has, and the arguments that give it to a node (a node
    of a test's context stays in the graph until the context is gone: another test's would
    count)."""
    name = f'refused_{os.getpid()}_{time.monotonic_ns()}'
    return name, ['--ros-args', '-r', f'__node:={name}']


def in_graph(context, name: str) -> bool:
    """Whether a node called ``name`` is in the graph of ``context`` (its own nodes are in it
    at once)."""
    probe = rclpy.create_node('graph_probe', context=context)
    try:
        return any(n == name for n, _ in probe.get_node_names_and_namespaces())
    finally:
        probe.destroy_node()


@pytest.mark.parametrize(
    ('node', 'overrides', 'expected'),
    [
        ('bag_recorder', {'compression': 'lz4'},
         "parameter 'compression': 'lz4' is not one of zstd, none"),
        ('bag_recorder', {'output': ' '}, "parameter 'output': must name a bag directory"),
        ('bag_player', {'topics': ['/odm']}, "parameter 'topics': /odm not in "),
        ('quadrotor_sim', {'inertia': [0.01, 0.02]},
         "parameter 'inertia': needs 3 values > 0, got [0.01, 0.02]"),
        ('quadrotor_sim', {'scenario': 'loop'},
         "parameter 'scenario': 'loop' is not one of position, trajectory, hover"),
        ('quadrotor_sim', {'vehicles': ['/1a']},
         "parameter 'vehicles': vehicle namespace '/1a' must not start with a digit"),
        ('cloe_inference', {'vehicles': ['uav1', 'fleet/2b']},
         "parameter 'vehicles': vehicle namespace 'fleet/2b' must not start with a digit (nor "
         "any part of it: '2b')"),
        ('quadrotor_sim', {'vehicles': ['/\u00fcav1']},
         "parameter 'vehicles': vehicle namespace '/\u00fcav1' is not valid"),
        ('quadrotor_sim', {'vehicles': ['/uav1', 'uav1']},
         "parameter 'vehicles': vehicles '/uav1' and 'uav1' are the same namespace, /uav1"),
        ('cloe_inference', {'vehicles': ['uav2', '/uav2/']},
         "parameter 'vehicles': vehicles 'uav2' and '/uav2' are the same namespace, /uav2"),
    ],
)  # fmt: skip
def test_every_node_refuses_a_startup_parameter_in_the_documented_form(
    context, tmp_path, node, overrides, expected
):
    from cloe_ros.ros.player_node import PlayerNode
    from cloe_ros.ros.recorder_node import BagRecorder

    cls, params = {
        'bag_recorder': (BagRecorder, {'output': str(tmp_path / 'bag')}),
        'bag_player': (PlayerNode, {'bag': str(REPO / 'bags' / 'position')}),
        'quadrotor_sim': (SimulatorNode, {}),
        'cloe_inference': (InferenceNode, {}),
    }[node]
    overrides = [Parameter(k, value=v) for k, v in {**params, **overrides}.items()]
    unique, renamed = unique_node_name()
    with pytest.raises(ParameterError) as info:
        cls(context=context, parameter_overrides=overrides, cli_args=renamed)
    assert str(info.value).startswith(expected), str(info.value)
    assert not in_graph(context, unique)  # the refused node was destroyed


def test_invalid_runtime_parameters_are_refused_with_a_reason(context):
    inf = InferenceNode(context=context)
    try:
        cases = [
            (Parameter('rate', value=5000.0), 'out of range'),
            (Parameter('rate', value='x'), 'Wrong parameter type'),
            (Parameter('algorithm', value='ekf'), "'ekf' is not one of"),
            (Parameter('vehicles', value=['/x']), 'read-only'),
            (Parameter('sm_gains', value=[-1.0] * 12), 'sm_gains must be finite and >= 0'),
            (Parameter('max_gap', value=0.0), 'out of range'),
            (Parameter('l_min', value=60.0), 'l_min must be at most l_max (50), got 60.0'),
            # the frame is fixed when the node starts: refused rather than silently ignored
            (Parameter('world_frame', value='map'), 'read-only parameter: world_frame'),
        ]
        for param, reason in cases:
            (result,) = inf.set_parameters([param])
            assert not result.successful and reason in result.reason, (param.name, result)
        # valid changes apply: gains live, algorithm restarts
        (ok,) = inf.set_parameters([Parameter('gamma_theta', value=10.0)])
        assert ok.successful and inf.engines[''].config.estimator.gamma_theta == 10.0
        (ok,) = inf.set_parameters([Parameter('algorithm', value='cloe')])
        assert ok.successful and inf.engines[''].config.estimator.algorithm == 'cloe'
    finally:
        inf.destroy_node()


def test_integer_overrides_for_float_parameters_are_accepted(context):
    inf = InferenceNode(context=context, parameter_overrides=[
        Parameter('rate', value=50), Parameter('sm_gains', value=[0, 1] * 6)])  # fmt: skip
    try:
        assert inf.engine_config.rate == 50.0
        assert inf.get_parameter('rate').type_ == Parameter.Type.DOUBLE
        assert inf.engine_config.estimator.sm_gains == (0.0, 1.0) * 6
        assert inf.get_parameter('sm_gains').type_ == Parameter.Type.DOUBLE_ARRAY
    finally:
        inf.destroy_node()


def test_the_parameter_service_sets_arrays_and_integers_for_floats(context):
    """Through the parameter service, as ``ros2 param set`` does: rclpy hands double arrays over
    as array.array, and an integer for a double is taken as at start-up, the type kept DOUBLE."""
    inf = InferenceNode(context=context)
    client_node = rclpy.create_node('client', context=context)
    client = AsyncParameterClient(client_node, 'cloe_inference')
    ex = _executor(context, inf, client_node)

    def set_parameters(*params):
        future = client.set_parameters(list(params))
        assert spin_until(ex, future.done, timeout=10)
        return future.result().results

    try:
        assert client.wait_for_services(timeout_sec=10)
        gains, exponents = [0.2] * 12, [0.5] * 12
        results = set_parameters(
            Parameter('sm_gains', value=gains), Parameter('sm_exponents', value=exponents)
        )
        assert all(r.successful for r in results), results
        config = inf.engines[''].config.estimator
        assert (config.sm_gains, config.sm_exponents) == (tuple(gains), tuple(exponents))
        (result,) = set_parameters(Parameter('sm_gains', value=[0.2] * 3))
        assert not result.successful
        assert result.reason == 'sm_gains needs 12 numbers, one per state, got 3'
        (result,) = set_parameters(Parameter('rate', value=50))
        assert result.successful, result.reason
        assert inf.get_parameter('rate').type_ == Parameter.Type.DOUBLE
        assert inf.get_parameter('rate').value == 50.0 and inf.engines[''].config.rate == 50.0
        (result,) = set_parameters(Parameter('sm_gains', value=[1, 0] * 6))
        assert result.successful, result.reason
        assert inf.get_parameter('sm_gains').type_ == Parameter.Type.DOUBLE_ARRAY
        assert inf.engines[''].config.estimator.sm_gains == (1.0, 0.0) * 6
        (result,) = set_parameters(Parameter('rate', value=5000))  # still checked, as a double
        assert not result.successful and 'out of range' in result.reason
    finally:
        ex.shutdown()
        for n in (inf, client_node):
            n.destroy_node()


def test_the_node_declares_the_ranges_cloe_infer_checks(context):
    """One range per setting (cloe_ros.io.config.RANGES), for the node and ``cloe infer``."""
    inf = InferenceNode(context=context)
    try:
        for name, (low, high) in RANGES.items():
            (declared,) = inf.describe_parameter(name).floating_point_range
            assert (declared.from_value, declared.to_value) == (low, high), name
    finally:
        inf.destroy_node()


T0 = 1_000_000_000_000


@pytest.fixture(scope='module')
def flight():
    """8 s of the position scenario at 100 Hz: enough for cloe_iv's identifier to have state."""
    res = QuadrotorSimulator(get_scenario('position'), dt=1e-3).run(8.0)
    return res.t[::10], res.zeta[::10, 0], res.reference[::10, 0]


def _feed(node, flight, ks, replica):
    """Samples ``ks`` of ``flight`` into the node's callbacks as raw CDR (what DDS delivers), each
    pair stepped as the batch timer does, and the same samples into ``replica``, an engine no
    parameter change reaches."""
    t, zeta, r = flight
    odom_cb, ref_cb = node._odometry_callback(''), node._reference_callback('')
    out = []
    for k in ks:
        stamp = T0 + round(t[k] * 1e9)
        raw_odom, raw_ref = _odom_bytes(stamp, zeta[k]), _ref_bytes(stamp, r[k])
        odom_cb(raw_odom)
        ref_cb(raw_ref)
        node._step_due()  # (the batch timer's call)
        replica.add_odometry(messages.decode_odometry(raw_odom))
        replica.add_reference(messages.decode_pose_stamped(raw_ref))
        out.extend(replica.advance())
    return out


def test_a_restart_for_a_new_algorithm_goes_on_counting_every_input(context, flight):
    """A change of algorithm makes new engines that keep the vehicles' counters: the inputs
    accepted after it are counted with those before, in /diagnostics' counters."""
    inf = InferenceNode(context=context)
    replica = VehicleEngine(inf.engine_config)
    try:
        _feed(inf, flight, range(100), replica)
        old = inf.engines['']
        (result,) = inf.set_parameters([Parameter('algorithm', value='cloe_sm')])
        assert result.successful, result.reason
        assert inf.engines[''] is not old
        _feed(inf, flight, range(100, 250), replica)
        s = inf.engines[''].stats
        assert s.resets == 1 and s.odom_received == s.odom_accepted == 250
        assert s.reference_received == s.reference_accepted == 250
        values = dict(inf.vehicle_status('', 0.0).values)
        assert values['resets'] == '1'
    finally:
        inf.destroy_node()


def test_the_parameter_labels_are_published_once_whatever_changes(context, flight):
    """``cloe/parameter_labels`` is latched once (README, docs/outputs.md): a change that makes
    new output encoders (``parameters_rate``, a restart for a new algorithm) does not send it
    again."""
    inf = InferenceNode(context=context)
    replica = VehicleEngine(inf.engine_config)
    sent = {'labels': 0, 'parameters': 0}
    encoder = inf.encoders['']
    topics = {'labels': encoder.labels_topic, 'parameters': encoder.parameters_topic}
    for what, topic in topics.items():
        publisher = inf.publishers_[topic]

        def counted(data, what=what, publish=publisher.publish):
            sent[what] += 1
            publish(data)

        publisher.publish = counted
    try:
        _feed(inf, flight, range(50), replica)
        for k, param in enumerate((Parameter('parameters_rate', value=20.0),
                                   Parameter('algorithm', value='cloe_sm'))):  # fmt: skip
            (result,) = inf.set_parameters([param])
            assert result.successful, (param.name, result.reason)
            before = sent['parameters']
            _feed(inf, flight, range(50 + 100 * k, 150 + 100 * k), replica)
            assert sent['parameters'] > before, param.name  # (new encoders at work)
        assert sent['labels'] == 0  # (latched at the start, before the counters)
    finally:
        inf.destroy_node()


def test_runtime_changes_keep_the_identified_model(context, flight):
    """cloe_iv (the default): a change that does not concern the identifier keeps its state and
    model; an identifier setting restarts the estimator (README, "The nodes")."""
    inf = InferenceNode(context=context)
    replica = VehicleEngine(inf.engine_config)
    try:
        engine = inf.engines['']
        _feed(inf, flight, range(400), replica)
        est = engine._est
        assert est is not None and est.identifier.status.any()  # the identifier has state
        for param in (
            Parameter('max_gap', value=2.0),
            Parameter('parameters_rate', value=20.0),
            Parameter('reference_timeout', value=0.5),
            Parameter('gamma_theta', value=10.0),  # (the paper's identifier gain: not cloe_iv's)
        ):
            (result,) = inf.set_parameters([param])
            assert result.successful, (param.name, result.reason)
        assert engine.config.max_gap == 2.0 and engine.config.reference_timeout == 0.5
        assert inf.encoders[''].config.parameters_rate == 20.0
        expected = _feed(inf, flight, range(400, 800), replica)
        # (the same state; the estimator may have moved, as a fleet's row, to another pool)
        assert inf.engines[''] is engine and engine.stats.resets == 0
        last = inf._last_estimate['']
        assert last.stamp_ns == expected[-1].stamp_ns
        np.testing.assert_array_equal(last.theta_hat, expected[-1].theta_hat)
        np.testing.assert_array_equal(last.zeta_hat, expected[-1].zeta_hat)
        assert dict(inf.vehicle_status('', 0.0).values)['resets'] == '0'
        # the observer's gains apply at once, to the same estimator
        gains = array.array('d', [0.3] * 12)
        theta, status = engine._est.theta_hat.copy(), engine._est.identifier.status.copy()
        (result,) = inf.set_parameters([Parameter('sm_gains', value=gains)])
        assert result.successful, result.reason
        assert engine.stats.resets == 0
        np.testing.assert_array_equal(engine._est.lambda_[0], gains)
        np.testing.assert_array_equal(engine._est.theta_hat, theta)
        np.testing.assert_array_equal(engine._est.identifier.status, status)
        # an identifier setting restarts it: the model is forgotten
        (result,) = inf.set_parameters([Parameter('id_window', value=30.0)])
        assert result.successful, result.reason
        assert engine.stats.resets == 1 and engine._est is None and engine._model is None
    finally:
        inf.destroy_node()


@pytest.mark.parametrize(('namespace', 'vehicles', 'expected'), [
    ('/', [], ['/']),
    ('/cf1', [], ['/cf1']),  # `__ns:=/cf1`, no vehicles
    ('/', ['uav1', '/uav2'], ['/uav1', '/uav2']),
    ('/fleet', ['uav1', '/uav2'], ['/fleet/uav1', '/uav2']),
])  # fmt: skip
def test_diagnostics_name_each_vehicle_by_its_recorded_namespace(context, namespace, vehicles,
                                                                  expected):  # fmt: skip
    """/diagnostics reports each vehicle under the namespace its topics have in a recording, which
    is how a report of the recording finds the algorithm behind each output."""
    overrides = [Parameter('vehicles', value=vehicles)] if vehicles else []
    inf = InferenceNode(context=context, namespace=namespace, parameter_overrides=overrides)
    try:
        statuses = [inf.vehicle_status(v, 0.0) for v in inf.vehicles]
        assert [s.hardware_id for s in statuses] == expected
        assert [s.name for s in statuses] == [f'cloe_inference: {ns}' for ns in expected]
        # (and each engine has it: it places the vehicle's predictions with prediction_phase
        # 'spread', as `cloe infer` does for the vehicle of that namespace in a recording)
        assert [inf.engines[v].namespace for v in inf.vehicles] == expected
        assert {dict(s.values)['prediction_phase'] for s in statuses} == {'aligned'}
        # (the node's own subscriptions reach its graph cache asynchronously: wait for them.
        # Asked per topic, not per node: a query by node name takes the first node of that name
        # in the graph, which may be another test's that has not left it yet)
        wanted = {f'{ns.rstrip("/")}/odom' for ns in expected}

        def subscribed() -> set[str]:
            return {topic for topic in wanted
                    if any((e.node_name, e.node_namespace) == ('cloe_inference', namespace)
                           for e in inf.get_subscriptions_info_by_topic(topic))}  # fmt: skip

        ex = _executor(context, inf)
        try:
            assert spin_until(ex, lambda: wanted <= subscribed(), TIMEOUT), (wanted, subscribed())
        finally:
            ex.shutdown()
    finally:
        inf.destroy_node()


def test_a_vehicle_whose_odometry_stops_is_reported_silent(context, monkeypatch):
    """Once a started vehicle has had no odometry for STALE_AFTER s of wall time, its status
    turns WARN and says for how long; it is OK while the odometry flows. (While it flows,
    STALE_AFTER is 60 s: a test process short of CPU may be held for longer than 0.3 s between the
    last odometry and the status; the silence it reports is checked against the wall time the
    test measured around it.)"""
    monkeypatch.setattr(inference_node, 'STALE_AFTER', 60.0)
    inf = InferenceNode(context=context)
    try:
        zeta, r = np.zeros(12), np.array([0.0, 0.0, 0.0, 1.0])
        zeta[10] = 1.0
        odom_cb, ref_cb = inf._odometry_callback(''), inf._reference_callback('')
        for k in range(20):
            stamp = 1_000_000_000_000 + k * 10_000_000
            ref_cb(_ref_bytes(stamp, r))
            before_last = time.monotonic()
            odom_cb(_odom_bytes(stamp, zeta))
        inf._step_due()  # (the batch timer's call)
        flowing = inf.vehicle_status('', 0.0)
        since_last = time.monotonic() - before_last
        assert inf.engines[''].started
        assert flowing.level == messages.OK, flowing.message
        # (reported to 0.1 s)
        assert 0.0 <= float(dict(flowing.values)['odom_silent_s']) <= since_last + 0.05
        monkeypatch.setattr(inference_node, 'STALE_AFTER', 0.3)
        time.sleep(0.4)
        silent = inf.vehicle_status('', 0.0)
        assert silent.level == messages.WARN
        assert silent.message.startswith('running; no odometry for ')
        assert float(dict(silent.values)['odom_silent_s']) >= 0.4
    finally:
        inf.destroy_node()


def test_diagnostics_go_out_from_the_inputs_when_the_timer_is_held_up(context, monkeypatch):
    """A node behind its inputs runs its timers late (rclpy's EventsExecutor queues their turn
    behind the messages waiting), so its inputs publish the /diagnostics report that is due.
    Here no executor spins, so no timer runs: the inputs, fed to the callbacks, publish the
    reports, each once the timer's turn is overdue (``DIAGNOSTICS_OVERDUE`` of a period since
    the last: a timer on time publishes them before the inputs do)."""
    period = 0.05
    inf = InferenceNode(context=context, parameter_overrides=[
        Parameter('diagnostics_period', value=period)])  # fmt: skip
    sent: list[bytes] = []
    monkeypatch.setattr(inf.diagnostics_pub, 'publish', sent.append)
    try:
        zeta, r = np.zeros(12), np.array([0.0, 0.0, 0.0, 1.0])
        zeta[10] = 1.0
        odom_cb, ref_cb = inf._odometry_callback(''), inf._reference_callback('')
        k = 0
        deadline = time.monotonic() + TIMEOUT
        while len(sent) < 3 and time.monotonic() < deadline:
            stamp = T0 + k * 10_000_000
            if k % 10 == 0:
                ref_cb(_ref_bytes(stamp, r))
            odom_cb(_odom_bytes(stamp, zeta))
            k += 1
        assert len(sent) >= 3, f'{len(sent)} reports after {k} odometry messages'
        reports = [messages.decode_diagnostics(raw) for raw in sent]
        stamps = [stamp for stamp, _ in reports]
        assert min(np.diff(stamps)) >= DIAGNOSTICS_OVERDUE * period * NS
        names = {status.name for status in reports[-1][1]}
        assert names == {'cloe_inference', 'cloe_inference: /'}
    finally:
        inf.destroy_node()


def test_each_simulated_vehicle_has_its_own_body_frame(context):
    sim = SimulatorNode(context=context, parameter_overrides=[
        Parameter('vehicles', value=['/uav1', '/uav2']), Parameter('duration', value=0.2),
        Parameter('real_time_factor', value=0.0),
        Parameter('wait_for_subscribers', value=1)])  # fmt: skip
    checked = ('/uav1/odom', '/uav2/odom', '/uav2/ground_truth')
    # the simulator starts once every odom and reference has a subscriber: the collector's
    col = Collector(context, {**dict.fromkeys(checked, Odometry), '/uav1/reference': PoseStamped,
                              '/uav2/reference': PoseStamped})  # fmt: skip
    ex = _executor(context, sim, col.node)
    try:
        assert spin_until(ex, lambda: sim.done, timeout=TIMEOUT)
        # 0.2 s at 100 Hz: 21 samples per topic
        assert spin_until(
            ex, lambda: all(len(col.msgs[t]) == 21 for t in checked), timeout=TIMEOUT
        ), {t: len(col.msgs[t]) for t in checked}
        frames = {topic: {(m.frame_id, m.child_frame_id)
                          for m in map(messages.decode_odometry, col.msgs[topic])}
                  for topic in checked}  # fmt: skip
        assert frames == {'/uav1/odom': {('world', 'uav1/base_link')},
                          '/uav2/odom': {('world', 'uav2/base_link')},
                          '/uav2/ground_truth': {('world', 'uav2/base_link')}}  # fmt: skip
    finally:
        ex.shutdown()
        for n in (sim, col.node):
            n.destroy_node()


def test_vehicles_step_in_batches_as_each_alone(context, flight):
    """Three vehicles: a batch runs as soon as each has new input (the batch timer, never
    spun here, is only the bound for silent ones), with one batched step per grid step; once
    one falls silent the others step after twice as many inputs as there are vehicles. Every
    state equals that of an engine fed alone; batch_period 0 keeps one estimator per vehicle."""
    t, zeta, r = flight
    names = ['/a', '/b', '/c']
    overrides = [Parameter('vehicles', value=names)]
    inf = InferenceNode(context=context, parameter_overrides=overrides)
    alone = InferenceNode(context=context, parameter_overrides=[
        *overrides, Parameter('batch_period', value=0.0)])  # fmt: skip
    try:
        replicas = {v: VehicleEngine(inf.engine_config, name=v) for v in names}
        expected = {v: [] for v in names}
        for k in range(600):
            stamp = T0 + round(t[k] * 1e9)
            for i, v in enumerate(names):
                if v == '/c' and k >= 300:
                    continue  # (falls silent)
                shifted = zeta[k].copy()
                shifted[0] += i  # (1 m apart)
                raw_odom = _odom_bytes(stamp, shifted)
                raw_ref = _ref_bytes(stamp, r[k] + np.array([i, 0, 0, 0]))
                for node in (inf, alone):
                    node._reference_callback(v)(raw_ref)
                    node._odometry_callback(v)(raw_odom)
                replicas[v].add_reference(messages.decode_pose_stamped(raw_ref))
                replicas[v].add_odometry(messages.decode_odometry(raw_odom))
                expected[v] += replicas[v].advance()
            if k in (100, 299):
                # a batch ran once every vehicle had new input: what came after it waits
                assert len(inf._due) < len(names)
                for v in names:
                    assert inf._last_estimate[v].stamp_ns >= stamp - NS // 100
            if k == 310:  # (with /c silent: a batch at least every six inputs)
                assert inf._last_estimate['/a'].stamp_ns >= stamp - 2 * NS // 100
        for node in (inf, alone):
            for v in names:
                last = node._last_estimate[v]
                want = next(e for e in expected[v] if e.stamp_ns == last.stamp_ns)
                np.testing.assert_allclose(last.zeta_hat, want.zeta_hat, rtol=1e-9, atol=1e-12)
                np.testing.assert_allclose(last.theta_hat, want.theta_hat, rtol=1e-9, atol=1e-12)
        pool = inf.engines['/a'].estimator.pool
        assert pool is inf.engines['/b'].estimator.pool and len(pool.keys) == 3
        assert not any(isinstance(e.estimator, PooledEstimator) for e in alone.engines.values())
        assert all(e.started for e in alone.engines.values())
    finally:
        inf.destroy_node()
        alone.destroy_node()
