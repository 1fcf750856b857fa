"""The system as users run it: quadrotor_sim -> cloe_inference -> bag_recorder, separate processes.

Every test starts the nodes with ``test/ros_helpers.NodeProcess`` on a DDS domain of its own, flies
a short simulation, stops the nodes once the recorder has everything, and reads the bag back with
an independent reader (``mcap`` + ``mcap_ros2``'s decoder, from the schemas embedded in the file):
topics and types, message counts, stamps, the labelled parameter layout, predictions in the future,
and the inferred states against the simulator's noise-free ``ground_truth``.

Waiting is on conditions, never on sleeps: log lines (``ready:``, ``recording <topic> (``,
``started``, ``done:``), the simulator's ``wait_for_subscribers`` (it starts once every ``odom``
and ``reference`` has that many subscriptions) and the recorder's ``/diagnostics`` counts, heard
by a subscriber in this process. What could lose messages, and how it is ruled out:

* the start: the simulator counts only ``odom`` and ``reference`` subscriptions, and the
  recorder subscribes topic by topic, alphabetically, 4-35 ms apart, while the simulator started
  as soon as 40 ms after the recorder's ``/odom`` subscription; so it waits for one more
  subscription on each than the nodes make, this process's, created once the recorder has
  subscribed to every simulator topic (:func:`gate`);
* a node falling behind: every history (``qos_depth``) holds more than a whole flight, so a
  reliable writer never drops what a slow reader has not acknowledged (with the simulator's
  depth at 100, its default before e32b90c, a recorder stalled under a full-suite load lost 14
  consecutive samples; DDS reported them lost);
* the end: the simulator stays up until the recorder has every sample it published and is
  stopped with the others. With ``shutdown_when_done`` it exits right after its last publication
  without waiting for acknowledgements, and a subscriber short of CPU at that moment loses the
  last samples (measured: 14 and 28 of 201 /odom samples lost in 2 of 6 runs where the recorder
  was stalled (SIGSTOP) across the simulator's end; none in 3 such runs when the simulator waited
  for acknowledgements first).

Measured with the seeds below (the simulation and the engine are deterministic, the numbers repeat
exactly from run to run; DDS timing does not change them because every message arrives):

* odom (Vicon-like noise) vs truth: position error max 8.4 mm, rms 3.5 mm;
* cloe_sm (the paper's observer, L(0) = 0 growing slowly): max 19.1 mm, rms 15.6 mm after 0.5 s,
  a lag of ~1.5 cm in x/y while the vehicle moves;
* cloe_iv (as committed in 6cdabe6/c917453): max 29.7 mm during the take-off (1.5-2.5 s, while
  its identifier starts), rms 7.3 mm after 0.5 s; after the take-off (t >= 3 s) rms 2.3 mm, below
  the measurement noise's 3.4 mm; two vehicles: max 29.4 and 29.1 mm, each ~2 m from the other's
  truth. With the model-error state being added to cloe_iv (working tree, not committed when this
  was written): max 13.1 mm, rms 2.4 mm, 1.5 mm after 3 s; two vehicles max 13.0 and 13.4 mm.
"""

from __future__ import annotations

import signal
import subprocess
from pathlib import Path
from types import SimpleNamespace

import numpy as np
import pytest
from diagnostic_msgs.msg import DiagnosticArray
from geometry_msgs.msg import PoseStamped
from mcap.reader import make_reader
from mcap_ros2.decoder import DecoderFactory
from nav_msgs.msg import Odometry
from ros_helpers import NodeProcess, private_domain, spin_until, start_node

from cloe_ros.core.model import PARAMETER_NAMES
from cloe_ros.io.dataset import load_flight
from cloe_ros.io.messages import decode_diagnostics
from cloe_ros.io.outputs import PARAMETER_LABELS
from cloe_ros.ros.common import qos
from cloe_ros.ros.inference_node import STALE_AFTER

pytestmark = [pytest.mark.ros, pytest.mark.slow]

NS = 1_000_000_000
DURATION = 8.0  # simulated s: take-off (z_d 0.05 -> 1 m on [1, 3] s), then x/y start moving at 4 s
RTF = 2.0  # simulated s per wall-clock s
ODOM_RATE = 100.0  # Hz, odom, ground_truth and reference alike
STEP_NS = NS // 100
N_ODOM = round(DURATION * ODOM_RATE) + 1  # samples at t = 0, 0.01, ..., DURATION
#: History depth of every publisher and subscription: more than a whole flight's messages per
#: topic, so a node that falls behind (the recorder, on a loaded machine) still gets every one.
#: (KEEP_LAST: with a depth of 100, 0.5 s at RTF 2, a recorder stalled under a full-suite load
#: lost 14 consecutive odometry samples in one run.)
DEPTH = 2000
SIM = {
    'duration': DURATION, 'real_time_factor': RTF, 'reference_rate': ODOM_RATE,
    'sim_rate': 500.0,  # RK4 at 2 ms: half the CPU of the default 1 kHz on this 2-core machine
    'seed': 1,
    'qos_depth': DEPTH,
    # Vicon-like noise (cloe_ros.core.simulator.TYPICAL_NOISE): odom is not the truth
    'noise_position': 0.002, 'noise_velocity': 0.01, 'noise_angle': 0.002, 'noise_rate': 0.01,
}  # fmt: skip
#: Every inference node's settings besides its own. ``reference_timeout`` 60 s: the engine waits
#: for the reference of each step, as it always does when odometry and reference come together;
#: with the default 0.25 s, a node short of CPU that takes a burst of odometry before the
#: references sent with it steps on the held reference, and its estimates then depend on the
#: scheduler (the rule is tested in test/core/test_engine.py).
INFERENCE = {'qos_depth': DEPTH, 'reference_timeout': 60.0}
ODOMETRY, POSE = 'nav_msgs/msg/Odometry', 'geometry_msgs/msg/PoseStamped'
ARRAY, PATH = 'std_msgs/msg/Float64MultiArray', 'nav_msgs/msg/Path'
DIAGNOSTICS = 'diagnostic_msgs/msg/DiagnosticArray'
#: Position error bounds (m) of the inferred states against the truth, after the first 0.5 s of
#: estimates (the start-up from the first measurement): the measured values (module docstring)
#: with about 30 % margin. They fail if an algorithm's estimate drifts, lags more or is offset.
MAX_POSITION_ERROR = {'cloe_sm': 0.025, 'cloe_iv': 0.04}
RMS_POSITION_ERROR = {'cloe_sm': 0.02, 'cloe_iv': 0.01}
SKIP_S = 0.5
#: Generous waits (s): a node's start-up or the recorder's last reports take a fraction of that
#: on an idle machine, and several times more on a loaded one.
TIMEOUT = 120.0
#: cloe_iv after the take-off (t >= 3 s): rms position error below that of the odometry it filters.
STEADY_S = 3.0


# -- fixtures and helpers ----------------------------------------------------------------------


class RecorderCounts:
    """Every ``/diagnostics`` report of the recorder: its per-topic ``received`` counts."""

    def __init__(self, node) -> None:
        self.reports: list[dict[str, int]] = []
        self.sub = node.create_subscription(
            DiagnosticArray, '/diagnostics', self._on, qos(reliable=True, depth=100), raw=True
        )

    def _on(self, raw: bytes) -> None:
        _, statuses = decode_diagnostics(raw)
        for s in statuses:
            if s.name.startswith('bag_recorder: '):
                self.reports.append(
                    {
                        k[: -len(' received')]: int(v)
                        for k, v in s.values
                        if k.endswith(' received')
                    }
                )


@pytest.fixture
def system(tmp_path: Path):
    """A domain of our own, an rclpy context on it (to hear /diagnostics), and ``start`` for
    node processes (killed at the end if still running)."""
    procs: list[NodeProcess] = []
    with private_domain('system_test') as ros:

        def start(name: str, params: dict, node_name: str | None = None) -> NodeProcess:
            proc = start_node(name, params, ros.domain, tmp_path / 'logs', node_name=node_name)
            procs.append(proc)
            return proc

        try:
            yield SimpleNamespace(
                node=ros.node,
                executor=ros.executor,
                counts=RecorderCounts(ros.node),
                start=start,
                bag=tmp_path / 'bag',
            )
        finally:
            for proc in reversed(procs):
                proc.stop(signal.SIGKILL)  # (does nothing to a process that has exited)


def logs(proc: NodeProcess) -> str:
    """Everything the process wrote (also after stop(), which closes its files)."""
    return proc.output()


def wait_for_lines(proc: NodeProcess, *lines: str, timeout: float = TIMEOUT) -> None:
    for line in lines:
        if not proc.wait_for(line, timeout):
            pytest.fail(f'{proc.name} did not log {line!r}:\n{logs(proc)}')


def fly(system, subscribers: int, sim_params: dict, inference: dict[str, dict],
        topics: list[str], recorder_params: dict | None = None) -> None:  # fmt: skip
    """Record ``topics`` of a simulated flight with inference nodes ``{node name: params}``.

    The recorder and the inference nodes start first; the simulator once the recorder has
    subscribed to every inference output (so it records them from the first message), and it waits
    for ``subscribers`` subscriptions on each ``odom`` and ``reference``, and the gate's
    (:func:`gate`). The nodes are stopped with SIGINT (all must exit with status 0) once the
    recorder has received every sample of every simulator topic and one state per odometry sample
    from each inference node, and its counts have not changed for a report period (1 s: the last
    parameters and predictions are in)."""
    recorder = system.start('bag_recorder', {
        'output': str(system.bag), 'topics': topics, 'qos_depth': DEPTH, **(recorder_params or {})
    })  # fmt: skip
    procs = {
        name: system.start('cloe_inference', {**INFERENCE, **params}, node_name=name)
        for name, params in inference.items()
    }
    for proc in procs.values():
        wait_for_lines(proc, 'ready:')
    outputs = [t for t in topics if t.rsplit('/', 1)[-1] in ('state', 'parameters', 'prediction')]
    wait_for_lines(recorder, *[f'recording {t} (' for t in outputs])
    sim = system.start(
        'quadrotor_sim', {**SIM, **sim_params, 'wait_for_subscribers': subscribers + 1}
    )
    gate(system.node, recorder, sim, topics)
    wait_for_lines(sim, 'done: ', timeout=DURATION / RTF + TIMEOUT)
    counts = system.counts
    sim_topics = [t for t in topics if t.rsplit('/', 1)[-1] in ('odom', 'reference',
                                                                 'ground_truth')]  # fmt: skip
    watched = [t for t in topics if t not in ('/diagnostics', '/true_parameters')]

    state_topics = [t for t in topics if t.endswith('/state')]

    def settled() -> bool:
        if len(counts.reports) < 2:
            return False
        last, before = counts.reports[-1], counts.reports[-2]
        complete = all(last.get(t, 0) == N_ODOM for t in sim_topics + state_topics)
        return complete and all(last.get(t, 0) == before.get(t, 0) for t in watched)

    assert spin_until(system.executor, settled, timeout=TIMEOUT), counts.reports[-2:]
    procs['bag_recorder'], procs['quadrotor_sim'] = recorder, sim
    assert_exited_cleanly(interrupt(procs), procs)


def gate(node, recorder: NodeProcess, sim: NodeProcess, topics: list[str]) -> list:
    """Once the recorder has subscribed to every simulator topic in ``topics``, subscribe to each
    ``odom`` and ``reference`` in ``node``: the last subscriptions the simulator waits for (it
    counts both). Returns the subscriptions (never spun while the simulator runs; their queue
    holds a whole flight)."""
    names = ('odom', 'reference', 'ground_truth', 'true_parameters')
    from_sim = [t for t in topics if t.rsplit('/', 1)[-1] in names]
    wait_for_lines(recorder, *[f'recording {t} (' for t in from_sim])
    types = {'odom': Odometry, 'reference': PoseStamped}
    subs = [
        node.create_subscription(types[name], t, lambda _: None, qos(depth=DEPTH), raw=True)
        for t in topics
        if (name := t.rsplit('/', 1)[-1]) in types
    ]
    wait_for_lines(sim, 'started')
    return subs


def interrupt(procs: dict[str, NodeProcess], timeout: float = 60.0) -> dict[str, int]:
    """SIGINT to every process at once (one signal each), then their exit statuses; a process
    still running after ``timeout`` is killed (status -9)."""
    for proc in procs.values():
        proc.proc.send_signal(signal.SIGINT)
    statuses = {}
    for name, proc in procs.items():
        try:
            proc.wait(timeout)
        except subprocess.TimeoutExpired:
            pass
        statuses[name] = proc.stop(signal.SIGKILL)
    return statuses


def assert_exited_cleanly(statuses: dict[str, int], procs: dict[str, NodeProcess]) -> None:
    """Every process exited with status 0 and printed no traceback; else the test fails with
    each one's status and whole output (an assertion's message would be cut to a few lines)."""
    out = {name: logs(proc) for name, proc in procs.items()}
    bad = [name for name in procs if statuses.get(name) != 0 or 'Traceback' in out[name]]
    if bad:
        pytest.fail('\n'.join(f'--- {name}: exit status {statuses.get(name)}, output:\n{out[name]}'
                               for name in bad))  # fmt: skip


def read_bag(bag: Path) -> dict[str, list[tuple[int, str, object]]]:
    """``{topic: [(log time ns, schema name, decoded message)]}`` with mcap's own reader."""
    (mcap_file,) = bag.glob('*.mcap')
    out: dict[str, list] = {}
    with mcap_file.open('rb') as fh:
        reader = make_reader(fh, decoder_factories=[DecoderFactory()])
        for schema, channel, message, decoded in reader.iter_decoded_messages():
            out.setdefault(channel.topic, []).append((message.log_time, schema.name, decoded))
    return out


def stamp(msg) -> int:
    return msg.header.stamp.sec * NS + msg.header.stamp.nanosec


def stamps_of(records) -> list[int]:
    return [stamp(m) for _, _, m in records]


def positions(records) -> dict[int, np.ndarray]:
    """Odometry messages by header stamp: position (3,) m."""
    out = {}
    for _, _, m in records:
        p = m.pose.pose.position
        out[stamp(m)] = np.array([p.x, p.y, p.z])
    return out


def position_errors(states, truth, t0: int, skip_s: float) -> np.ndarray:
    """|inferred - true position| (m) at every state stamp ``skip_s`` or more after ``t0``. Every
    state must have the truth at its stamp (the engine's grid falls on the odometry samples)."""
    est, true = positions(states), positions(truth)
    assert set(est) <= set(true), 'estimates stamped off the simulation grid'
    return np.array(
        [np.linalg.norm(est[s] - true[s]) for s in sorted(est) if s >= t0 + skip_s * NS]
    )


def slot_starts(stamps: list[int], period_ns: int) -> list[int]:
    """The first of ``stamps`` in each period of message time (multiples of ``period_ns``)."""
    out, last = [], None
    for s in stamps:
        if last is None or s // period_ns > last:
            out.append(s)
            last = s // period_ns
    return out


def check_sim_topics(bag: dict, ns: str = '') -> list[int]:
    """Every simulated sample of ``<ns>/odom``, ``ground_truth`` and ``reference``, on the
    100 Hz grid; returns the odometry stamps."""
    odom = stamps_of(bag[f'{ns}/odom'])
    assert len(odom) == N_ODOM
    assert np.all(np.diff(odom) == STEP_NS)
    assert stamps_of(bag[f'{ns}/ground_truth']) == odom
    if f'{ns}/reference' in bag:
        assert stamps_of(bag[f'{ns}/reference']) == odom
    return odom


def check_states(states, odom: list[int], body: str = 'base_link') -> list[int]:
    """One estimate per odometry sample, on its stamp (the engine steps at the odometry's 100 Hz
    from the first sample, which has a reference at the same stamp), in order, in the frames of
    the odometry (child ``body``). Returns the state stamps."""
    st = stamps_of(states)
    assert st == odom, (
        f'{len(st)} states from {(st[0] - odom[0]) / NS} s to {(st[-1] - odom[0]) / NS} s, '
        f'{len(odom)} odometry samples'
    )
    assert {(m.header.frame_id, m.child_frame_id) for _, _, m in states} == {('world', body)}
    return st


def types_of(bag: dict) -> dict[str, set[str]]:
    return {t: {name for _, name, _ in msgs} for t, msgs in bag.items()}


# -- tests ---------------------------------------------------------------------------------------


def test_sim_inference_recorder(system) -> None:
    """Two inference nodes side by side (cloe_sm and cloe_iv, outputs under their own namespaces)
    on the simulator's topics, everything recorded; the bag holds what the contract says."""
    algorithms = ('cloe_sm', 'cloe_iv')
    topics = ['/odom', '/reference', '/ground_truth', '/true_parameters', '/diagnostics']
    for alg in algorithms:
        topics += [f'/{alg}/state', f'/{alg}/parameters', f'/{alg}/prediction']
    inference = {f'inference_{alg}': {'algorithm': alg, 'output_ns': alg} for alg in algorithms}
    # the simulator's /odom subscribers: both inference nodes and the recorder
    fly(system, 3, {}, inference, topics)
    bag = read_bag(system.bag)
    print('recorded: ' + ', '.join(f'{t} {len(m)}' for t, m in sorted(bag.items())))
    types = types_of(bag)
    expected = {
        '/odom': {ODOMETRY}, '/ground_truth': {ODOMETRY}, '/reference': {POSE},
        '/true_parameters': {ARRAY}, '/diagnostics': {DIAGNOSTICS},
        '/cloe_sm/state': {ODOMETRY}, '/cloe_sm/parameters': {ARRAY},
        '/cloe_iv/state': {ODOMETRY}, '/cloe_iv/parameters': {ARRAY},
        '/cloe_iv/prediction': {PATH},
    }  # fmt: skip
    # cloe_sm's predictions are withheld while its identified model is unstable (the paper's
    # identifier does not converge, docs/method.md): its topic may hold nothing
    assert {t: types[t] for t in types if t != '/cloe_sm/prediction'} == expected
    assert types.get('/cloe_sm/prediction', {PATH}) == {PATH}

    odom = check_sim_topics(bag)
    (true_params,) = bag['/true_parameters']
    assert [d.label for d in true_params[2].layout.dim] == [f'theta.{n}' for n in PARAMETER_NAMES]
    assert len(true_params[2].data) == len(PARAMETER_NAMES)

    truth = bag['/ground_truth']
    odom_err = position_errors(bag['/odom'], truth, odom[0], SKIP_S)
    print(f'odom vs truth: max {odom_err.max():.4f} m, rms {np.sqrt(np.mean(odom_err**2)):.4f} m')
    for alg in algorithms:
        states = bag[f'/{alg}/state']
        st = check_states(states, odom)
        # parameters (no header: counted): with the first estimate in each 100 ms of message
        # time (parameters_rate 10 Hz), labelled entry by entry
        params = bag[f'/{alg}/parameters']
        assert len(params) == len(slot_starts(st, NS // 10))
        for _, _, p in params:
            assert [d.label for d in p.layout.dim] == list(PARAMETER_LABELS)
            assert len(p.data) == len(PARAMETER_LABELS)
        err = position_errors(states, truth, st[0], SKIP_S)
        rms = float(np.sqrt(np.mean(err**2)))
        print(f'{alg}: {len(states)} states, {len(params)} parameters, position error vs truth '
              f'max {err.max():.4f} m, rms {rms:.4f} m over {len(err)} stamps')  # fmt: skip
        assert err.max() < MAX_POSITION_ERROR[alg] and rms < RMS_POSITION_ERROR[alg]

    # after the take-off, cloe_iv's estimate is closer to the truth than the odometry it is given
    steady = position_errors(bag['/cloe_iv/state'], truth, odom[0], STEADY_S)
    noise = position_errors(bag['/odom'], truth, odom[0], STEADY_S)
    rms_iv, rms_odom = np.sqrt(np.mean(steady**2)), np.sqrt(np.mean(noise**2))
    print(f'after {STEADY_S:g} s: cloe_iv rms {rms_iv:.4f} m, odom rms {rms_odom:.4f} m')
    assert rms_iv < rms_odom

    # cloe_iv anticipates: 5 s paths of poses every 0.1 s, stamped after their header stamp; one
    # with the first estimate of each 200 ms of message time (prediction_rate 5 Hz), withheld while
    # the identified model is unstable (measured: none withheld, 41 of 41)
    iv = stamps_of(bag['/cloe_iv/state'])
    predictions = bag['/cloe_iv/prediction']
    pred = stamps_of(predictions)
    slots = slot_starts(iv, NS // 5)
    print(f'cloe_iv: {len(pred)} predictions of {len(slots)} slots')
    assert pred == sorted(pred) and set(pred) <= set(slots)
    assert len(pred) >= 0.9 * len(slots)
    for _, _, path in predictions:
        t0 = stamp(path)
        assert [stamp(p) - t0 for p in path.poses] == [k * NS // 10 for k in range(1, 51)]
        assert path.header.frame_id == 'world'
        assert {p.header.frame_id for p in path.poses} == {'world'}

    # /diagnostics: each inference node reports its algorithm, OK (no input rejected) while the
    # odometry flows (once it has stopped for STALE_AFTER s, the status says so with a WARN)
    last = {}
    for _, _, msg in bag['/diagnostics']:
        for s in msg.status:
            values = {kv.key: kv.value for kv in s.values}
            if 'algorithm' in values and float(values['odom_silent_s'] or 0) < STALE_AFTER:
                last[values['algorithm']] = (s, values)
    assert set(last) == set(algorithms)
    for alg, (status, values) in last.items():
        level = status.level if isinstance(status.level, int) else status.level[0]
        assert level == 0 and values['rejected'] == '0', (alg, status.message, values)
        assert status.hardware_id == '/'
        assert values['output_ns'] == alg
    # ... which is how a report of this recording (no custom data) knows which algorithm made
    # each output
    assert {alg: out.algorithm for alg, out in load_flight(system.bag)[''].outputs.items()} == {
        alg: alg for alg in algorithms}  # fmt: skip


def test_use_sim_time(system) -> None:
    """The simulator publishes /clock; inference and recorder run on it. Outputs still come, and
    the recorder's log times are simulation times: the simulator ticks /clock at each odometry
    stamp (every 10 ms of simulated time), and a node on ``use_sim_time`` reads the latest tick, so
    every log time lies on that 10 ms grid, which a wall-clock time would hit with probability
    about 1e-7 per message. How far the log time trails the stamp depends on how busy the machine
    is (measured idle: medians 0.00-0.01 s; loaded: up to 0.6 s); that is a speed, reported by the
    benchmark, not tested here. What does not depend on speed: a message is logged no earlier than
    about its own stamp (the tick before it arrives first), never seconds before it as the wall
    clock of a simulator running at RTF = 2 would give."""
    topics = ['/odom', '/reference', '/ground_truth', '/cloe/state', '/cloe/parameters']
    fly(system, 2, {'publish_clock': True},
        {'cloe_inference': {'use_sim_time': True}}, topics,
        recorder_params={'use_sim_time': True})  # fmt: skip
    bag = read_bag(system.bag)
    odom = check_sim_topics(bag)
    check_states(bag['/cloe/state'], odom)
    assert len(bag['/cloe/parameters']) == len(
        slot_starts(stamps_of(bag['/cloe/state']), NS // 10)
    )
    origin = stamps_of(bag['/odom'])[0]
    tick = NS // 100
    for topic in ('/odom', '/cloe/state'):
        log = np.array([t for t, _, _ in bag[topic]], dtype=np.int64)
        lag = (log - np.array(stamps_of(bag[topic]), dtype=np.int64)) / NS
        print(f'{topic}: log time - stamp in [{lag.min():.3f}, {lag.max():.3f}] s, median '
              f'{np.median(lag):.3f} s')  # fmt: skip
        off_grid = np.count_nonzero((log - origin) % tick)
        assert off_grid == 0, f'{off_grid} of {len(log)} {topic} log times are not /clock ticks'
        assert lag.min() >= -1.0


def test_two_vehicles(system) -> None:
    """``vehicles: [/uav1, /uav2]`` on both nodes: each vehicle's state tracks its own vehicle (the
    simulator places them ``spacing`` = 2 m apart in y)."""
    vehicles = ['/uav1', '/uav2']
    names = ('odom', 'reference', 'ground_truth', 'cloe/state')
    topics = [f'{v}/{name}' for v in vehicles for name in names]
    # each /uavN/odom and /uavN/reference has two subscribers: the inference node and the recorder
    fly(system, 2, {'vehicles': vehicles},
        {'cloe_inference': {'vehicles': vehicles}}, topics)  # fmt: skip
    bag = read_bag(system.bag)
    print('recorded: ' + ', '.join(f'{t} {len(m)}' for t, m in sorted(bag.items())))
    assert set(bag) == set(topics)
    odom = check_sim_topics(bag, '/uav1')
    assert check_sim_topics(bag, '/uav2') == odom  # one simulation clock
    truth = {v: positions(bag[f'{v}/ground_truth']) for v in vehicles}
    offset = np.array([truth['/uav2'][s] - truth['/uav1'][s] for s in odom])
    assert np.allclose(offset[0], [0.0, 2.0, 0.0])  # both start at rest, 2 m apart in y
    for v, other in zip(vehicles, reversed(vehicles)):
        states = bag[f'{v}/cloe/state']
        st = check_states(states, odom, body=f'{v.strip("/")}/base_link')  # one body per vehicle
        err = position_errors(states, bag[f'{v}/ground_truth'], st[0], SKIP_S)
        wrong = position_errors(states, bag[f'{other}/ground_truth'], st[0], SKIP_S)
        print(f'{v}: position error max {err.max():.4f} m (to the other vehicle: min '
              f'{wrong.min():.3f} m)')  # fmt: skip
        assert err.max() < MAX_POSITION_ERROR['cloe_iv']
        assert wrong.min() > 1.5
