"""Online equals offline: a recorded flight replayed through ``cloe_inference`` nodes gives exactly
what ``cloe infer`` (:func:`cloe_ros.cli.infer.infer_bag`) computes from the same bag.

1. ``quadrotor_sim`` -> ``bag_recorder``: an input bag as a user records one (log times are the
   recorder's reception times, so odometry and reference interleave as they arrived).
2. ``bag_player`` (``rate`` 4) -> two ``cloe_inference`` nodes (the default algorithm, cloe_iv, and
   cloe_sm) -> ``bag_recorder`` recording their outputs; ``infer_bag`` on the same bag with the
   same settings.
3. Every output message compared, decoded with ``mcap_ros2`` from both bags: the same count, the
   same header stamps in the same order, floats equal to 1e-9 (CDR carries float64; the padding
   bytes of CDR are not initialised, so bytes are never compared).

What could make them differ, and how the test rules it out by construction:

* messages lost before the nodes listen: the player waits until both inference nodes' subscriptions
  match every played topic (``wait_for_subscribers``), the recorder has subscribed to every output
  before the player starts (its log line, and this process sees the subscription in the graph);
* messages lost on the way: reliable QoS everywhere, and histories (``qos_depth``) deeper than the
  number of messages of any topic, so no writer drops a message a slow reader has not acknowledged
  and no reader's queue overflows;
  the player exits only once its messages are acknowledged (it warns otherwise: checked); the
  nodes are stopped only when the recorder has as many outputs as the offline run produced;
* arrival order: each topic arrives in order (DDS, per writer) and the engine's result depends on
  the stamps alone, except for one documented rule: a step runs without a newer reference once the
  odometry is ``reference_timeout`` (default 0.25 s of message time, 62 ms of wall time at rate 4)
  ahead. Online that depends on how the two topics' deliveries interleave, so both runs use
  ``reference_timeout`` 60 s here: the comparison is about the engine and the transport, not the
  scheduler. (Offline, with the reference at the odometry's rate and both ending at the same stamp,
  the rule never triggers either: checked on the input bag.)
"""

from __future__ import annotations

import signal
from pathlib import Path
from types import SimpleNamespace

import numpy as np
import pytest
from ros_helpers import NodeProcess, private_domain, spin_until, start_node

from cloe_ros.cli.infer import infer_bag
from cloe_ros.io.outputs import PARAMETER_LABELS

from .test_system import (
    TIMEOUT,
    RecorderCounts,
    assert_exited_cleanly,
    gate,
    interrupt,
    logs,
    read_bag,
    stamp,
    wait_for_lines,
)

pytestmark = [pytest.mark.ros, pytest.mark.slow]

DURATION = 10.0  # simulated s
N_INPUT = round(DURATION * 100) + 1  # odom and reference samples, 100 Hz
RATE = 4.0  # playback speed
ALGORITHMS = ('cloe_iv', 'cloe_sm')  # the default algorithm first
ATOL = 1e-9
DEPTH = 2000  # history depth of every publisher and subscription: > N_INPUT


@pytest.fixture
def ros(tmp_path: Path):
    """A domain of our own with an rclpy context on it (for /diagnostics and the graph), and
    ``start`` for node processes (killed at the end if still running)."""
    procs: list[NodeProcess] = []
    with private_domain('online_offline_test') as ros:

        def start(name: str, params: dict, node_name: str | None = None) -> NodeProcess:
            proc = start_node(name, params, ros.domain, tmp_path / 'logs', node_name=node_name)
            procs.append(proc)
            return proc

        try:
            yield SimpleNamespace(node=ros.node, executor=ros.executor,
                                  counts=RecorderCounts(ros.node), start=start)  # fmt: skip
        finally:
            for proc in reversed(procs):
                proc.stop(signal.SIGKILL)


def settings(algorithm: str) -> dict:
    """The inference settings of both runs (node parameters = ``infer_bag`` settings)."""
    return {'algorithm': algorithm, 'output_ns': algorithm, 'reference_timeout': 60.0}


def wait_for_counts(ros, wanted: dict[str, int], timeout: float = TIMEOUT) -> None:
    """Until the recorder's reports show ``wanted`` received counts twice in a row."""
    reports = ros.counts.reports
    first = len(reports)

    def reached() -> bool:
        last = reports[first:][-2:]
        return len(last) == 2 and all(r.get(t, 0) == n for r in last for t, n in wanted.items())

    assert spin_until(ros.executor, reached, timeout), (wanted, reports[-1:])


def record_input_bag(ros, bag: Path) -> None:
    """Simulator -> recorder: odom, reference, ground_truth (stopped once all is recorded; the
    simulator starts once the recorder listens to all three, see test_system.gate)."""
    topics = ['/odom', '/reference', '/ground_truth']
    recorder = ros.start(
        'bag_recorder', {'output': str(bag), 'topics': topics, 'qos_depth': DEPTH}
    )
    wait_for_lines(recorder, 'recording to')
    sim = ros.start('quadrotor_sim', {
        'duration': DURATION, 'real_time_factor': 4.0, 'sim_rate': 500.0,
        'reference_rate': 100.0, 'wait_for_subscribers': 2, 'seed': 3, 'qos_depth': DEPTH,
        'noise_position': 0.002, 'noise_velocity': 0.01, 'noise_angle': 0.002,
        'noise_rate': 0.01,
    })  # fmt: skip
    gated = gate(ros.node, recorder, sim, topics)  # the 2nd subscribers, once all are heard
    wait_for_lines(sim, 'done: ', timeout=DURATION + TIMEOUT)
    wait_for_counts(ros, dict.fromkeys(topics, N_INPUT))
    stopped = {'bag_recorder': recorder, 'quadrotor_sim': sim}
    assert_exited_cleanly(interrupt(stopped), stopped)
    for sub in gated:  # (the player must count only the inference nodes' subscriptions)
        ros.node.destroy_subscription(sub)


def decoded(bag: Path, topics) -> dict[str, list]:
    got = read_bag(bag)
    return {t: [m for _, _, m in got.get(t, [])] for t in topics}


def odometry_values(m) -> np.ndarray:
    p, q = m.pose.pose.position, m.pose.pose.orientation
    v, w = m.twist.twist.linear, m.twist.twist.angular
    return np.array([
        p.x, p.y, p.z, q.x, q.y, q.z, q.w, v.x, v.y, v.z, w.x, w.y, w.z,
        *m.pose.covariance, *m.twist.covariance,
    ])  # fmt: skip


def path_values(m) -> np.ndarray:
    return np.array([
        [p.pose.position.x, p.pose.position.y, p.pose.position.z, p.pose.orientation.x,
         p.pose.orientation.y, p.pose.orientation.z, p.pose.orientation.w]
        for p in m.poses
    ])  # fmt: skip


def compare(online: dict[str, list], offline: dict[str, list]) -> dict[str, float]:
    """Assert the outputs are the same; returns the largest difference per topic."""
    worst = {}
    for topic, off in offline.items():
        on = online[topic]
        assert len(on) == len(off), f'{topic}: {len(on)} online, {len(off)} offline'
        diff = 0.0
        for a, b in zip(on, off):
            if topic.endswith('/parameters'):
                assert [d.label for d in a.layout.dim] == [d.label for d in b.layout.dim]
                x, y = np.array(a.data), np.array(b.data)
            else:
                assert stamp(a) == stamp(b) and a.header.frame_id == b.header.frame_id
                if topic.endswith('/state'):
                    assert a.child_frame_id == b.child_frame_id
                    x, y = odometry_values(a), odometry_values(b)
                else:
                    assert [stamp(p) for p in a.poses] == [stamp(p) for p in b.poses]
                    x, y = path_values(a), path_values(b)
            assert x.shape == y.shape
            np.testing.assert_allclose(x, y, rtol=0, atol=ATOL, equal_nan=True, err_msg=topic)
            both = np.isfinite(x) & np.isfinite(y)
            diff = max(diff, float(np.max(np.abs(x[both] - y[both]), initial=0.0)))
        worst[topic] = diff
    return worst


def test_replayed_bag_gives_the_offline_result(ros, tmp_path: Path) -> None:
    bag = tmp_path / 'input'
    record_input_bag(ros, bag)
    inputs = read_bag(bag)
    odom = [stamp(m) for _, _, m in inputs['/odom']]
    ref = [stamp(m) for _, _, m in inputs['/reference']]
    assert len(odom) == len(ref) == N_INPUT and ref[-1] == odom[-1]

    # offline, same settings
    offline = {}
    for alg in ALGORITHMS:
        out = tmp_path / f'offline_{alg}'
        result = infer_bag(bag, out, settings(alg), copy_inputs=False)
        assert result.steps == {'': N_INPUT} and not result.rejected['']
        offline.update(decoded(out, [f'/{alg}/{t}' for t in ('state', 'parameters',
                                                              'prediction')]))  # fmt: skip
    counts = {t: len(m) for t, m in offline.items()}
    print('offline: ' + ', '.join(f'{t} {n}' for t, n in counts.items()))
    outputs = sorted(counts)

    # online: player -> two inference nodes -> recorder
    recorder = ros.start(
        'bag_recorder', {'output': str(tmp_path / 'online'), 'topics': outputs, 'qos_depth': DEPTH}
    )
    nodes = {
        f'inference_{alg}': ros.start('cloe_inference', {**settings(alg), 'qos_depth': DEPTH},
                                      node_name=f'inference_{alg}')
        for alg in ALGORITHMS
    }  # fmt: skip
    for proc in nodes.values():
        wait_for_lines(proc, 'ready:')
    wait_for_lines(recorder, *[f'recording {t} (' for t in outputs])
    assert spin_until(
        ros.executor, lambda: all(ros.node.count_subscribers(t) >= 1 for t in outputs), TIMEOUT
    )
    player = ros.start('bag_player', {
        'bag': str(bag), 'rate': RATE, 'topics': ['/odom', '/reference'],
        'wait_for_subscribers': len(ALGORITHMS), 'wait_timeout': TIMEOUT, 'qos_depth': DEPTH,
        'ack_timeout': TIMEOUT,
    })  # fmt: skip
    wait_for_lines(player, 'done: ', timeout=DURATION / RATE + 2 * TIMEOUT)
    assert player.wait(TIMEOUT) == 0, logs(player)
    played = logs(player)
    assert f'done: {2 * N_INPUT} messages' in played  # every odom and reference of the bag
    assert 'not acknowledged' not in played and 'playing without' not in played, played
    wait_for_counts(ros, counts)
    stopped = {**nodes, 'bag_recorder': recorder}
    assert_exited_cleanly(interrupt(stopped), stopped)

    online = decoded(tmp_path / 'online', outputs)
    worst = compare(online, offline)
    print('largest |online - offline|: ' + ', '.join(f'{t} {d:.3g}' for t, d in worst.items()))
    # the comparison compared something: every step, parameters and (cloe_iv) predictions
    assert counts['/cloe_iv/state'] == counts['/cloe_sm/state'] == N_INPUT
    assert counts['/cloe_iv/parameters'] >= DURATION * 10 and counts['/cloe_iv/prediction'] > 0
    labels = [d.label for d in online['/cloe_iv/parameters'][0].layout.dim]
    assert labels == list(PARAMETER_LABELS)
    assert [stamp(m) for m in online['/cloe_iv/state']] == odom
