"""Replay the attacks of issue 15 against the installed package; one row per attack, HELD / BROKE.

    .venv/bin/python scripts/attacks.py [--quick] [--domain 77] [--keep DIR]

Run it from the repository (it reads the sample bags in ``bags/``) with the environment of the
README (``ROS_AUTOMATIC_DISCOVERY_RANGE=LOCALHOST`` is forced, DDS stays on this machine). It uses
the package installed next to this Python (``.venv``), not the source tree: the console scripts
``cloe`` and ``cloe_inference`` of ``.venv/bin`` and ``import cloe_ros`` from site-packages.

**Node attacks.** Each attack starts a fresh ``cloe_inference`` process (renamed
``attack_<n>``, ``diagnostics_period:=0.2``) on ``ROS_DOMAIN_ID`` ``--domain`` and feeds it raw CDR
from an rclpy node of this script, encoded with ``cloe_ros.io.messages``: the first seconds of
the flight in ``bags/trajectory`` (``/odom`` and ``/reference`` at 100 Hz), with the attack's
messages in the middle. The feed waits, block by block, until the node's ``/diagnostics`` count
what was sent, so nothing is lost on the way but in the burst attack. The script reads back
``cloe/state``, ``cloe/parameters``, ``cloe/prediction``, ``cloe/prediction_radius`` and the node's
``/diagnostics``, and compares the states with those of the same package's ``VehicleEngine`` run
in this process on the clean flight (a glitch that costs one sample stays within 5 mm of it). It
then stops the node with SIGINT: the node must still be running, exit 0 and print no traceback.

**File attacks.** Copies of the first 12 s of ``bags/position`` (rewritten by the package's
``BagWriter``, so they carry MCAP CRCs: the reader checks CRCs only where a file has them), damaged
or lying, given to ``cloe bag info``, ``cloe infer``, ``cloe report`` and ``cloe bag recover``; and
``cloe_inference --ros-args --params-file`` with a missing or malformed file. A failure must be one
``ERROR:`` line, exit status 1 and no partial output.

A traceback anywhere is BROKE. A row is ``n/a`` where this build does not have what the attack
checks (lost inputs counted in ``/diagnostics``: a key with ``lost`` in its name); it is detected,
not assumed. The table is printed as Markdown; the exit status is 1 when a row BROKE.

``--quick`` feeds 3 s of flight instead of 6 s, 1000 messages after the stray frame instead of
4000, a burst of 3000 instead of 10000, and 3 plans of 20000 poses instead of 20; the file attacks
are the same (on 12 s of ``bags/position``). ``--keep DIR`` keeps the work files (node logs, bags)
in DIR. A full run took 11 minutes on 2 cores shared with other work (load 12), --quick about 8.
"""

from __future__ import annotations

import argparse
import dataclasses
import itertools
import math
import os
import shutil
import signal
import subprocess
import sys
import tempfile
import time
from collections.abc import Callable
from pathlib import Path

import numpy as np
import yaml

REPO = Path(__file__).resolve().parent.parent
BIN = Path(sys.executable).parent
NS = 1_000_000_000
TRACEBACK = 'Traceback (most recent call last)'


@dataclasses.dataclass
class Row:
    attack: str
    expectation: str
    observed: str
    verdict: str  # HELD, BROKE or n/a


def verdict(checks: list[tuple[bool, str]]) -> tuple[str, str]:
    """(observed, verdict) of ``(ok, what was seen)`` checks: the failed ones first."""
    failed = list(dict.fromkeys(text for ok, text in checks if not ok))
    passed = list(dict.fromkeys(text for ok, text in checks if ok))
    observed = '; '.join([*(f'**{t}**' for t in failed), *passed])
    return observed, 'BROKE' if failed else 'HELD'


def wait_until(condition: Callable[[], bool], timeout: float, step: Callable[[], None]) -> bool:
    """Call ``step`` until ``condition()`` holds; False after ``timeout`` seconds."""
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        if condition():
            return True
        step()
    return condition()


# ------------------------------------------------------------------------------- the flight


def flight(seconds: float) -> list[tuple[str, object]]:
    """The first ``seconds`` of ``bags/trajectory``: ``('odom', OdometrySample)`` and
    ``('reference', PoseSample)`` in log-time order, references up to the last odometry."""
    from cloe_ros.io import messages
    from cloe_ros.io.reader import BagReader

    out: list[tuple[str, object]] = []
    with BagReader(REPO / 'bags' / 'trajectory') as bag:
        end = bag.start_ns + int(seconds * NS)
        for topic, t, raw in bag.messages(['/odom', '/reference']):
            if t > end:
                break
            if topic == '/odom':
                out.append(('odom', messages.decode_odometry(raw)))
            else:
                out.append(('reference', messages.decode_pose_stamped(raw)))
    last_odom = max(i for i, (k, _) in enumerate(out) if k == 'odom')
    return out[: last_odom + 1]


def encode(kind: str, sample) -> bytes:
    from cloe_ros.io import messages

    return (messages.encode_odometry if kind == 'odom' else messages.encode_pose_stamped)(sample)


def restamped(seq: list[tuple[str, object]], shift_ns: int) -> list[tuple[str, object]]:
    return [(k, dataclasses.replace(s, stamp_ns=s.stamp_ns + shift_ns)) for k, s in seq]


def offline_states(seq: list[tuple[str, object]], algorithm: str) -> dict[int, np.ndarray]:
    """Stamp -> estimated position of the package's engine, in this process, on ``seq`` (the
    node's configuration: the defaults)."""
    from cloe_ros.core.engine import VehicleEngine
    from cloe_ros.io.config import DEFAULTS, build_configs

    engine_config, _ = build_configs({**DEFAULTS, 'algorithm': algorithm})
    engine = VehicleEngine(engine_config)
    out: dict[int, np.ndarray] = {}
    for kind, sample in seq:
        (engine.add_odometry if kind == 'odom' else engine.add_reference)(sample)
        for e in engine.advance():
            out[e.stamp_ns] = e.zeta_hat[[0, 4, 10]].copy()
    return out


# ------------------------------------------------------------------------ the node's side


class Client:
    """This script's rclpy node: raw publishers of the node's inputs, raw subscriptions of its
    outputs and of /diagnostics; every output message checked for finite values."""

    OUTPUTS = ('/cloe/state', '/cloe/parameters', '/cloe/prediction', '/cloe/prediction_radius')

    def __init__(self, domain: int) -> None:
        import rclpy
        from diagnostic_msgs.msg import DiagnosticArray
        from geometry_msgs.msg import PoseStamped
        from nav_msgs.msg import Odometry
        from nav_msgs.msg import Path as PathMessage
        from rclpy.executors import SingleThreadedExecutor
        from rclpy.qos import HistoryPolicy, QoSProfile, ReliabilityPolicy
        from std_msgs.msg import Float64MultiArray

        self.rclpy = rclpy
        self.ctx = rclpy.Context()
        rclpy.init(context=self.ctx, domain_id=domain)
        self.node = rclpy.create_node('cloe_attacker', context=self.ctx)
        self.executor = SingleThreadedExecutor(context=self.ctx)
        self.executor.add_node(self.node)

        def reliable(depth: int) -> QoSProfile:
            return QoSProfile(history=HistoryPolicy.KEEP_LAST, depth=depth,
                              reliability=ReliabilityPolicy.RELIABLE)  # fmt: skip

        self.pubs = {
            'odom': self.node.create_publisher(Odometry, '/odom', reliable(1000)),
            'reference': self.node.create_publisher(PoseStamped, '/reference', reliable(1000)),
            'plan': self.node.create_publisher(PathMessage, '/reference_plan', reliable(1000)),
        }
        types = dict(zip(self.OUTPUTS, (Odometry, Float64MultiArray, PathMessage,
                                        Float64MultiArray)))  # fmt: skip
        self.got: dict[str, list[bytes]] = {t: [] for t in self.OUTPUTS}
        self.subs = [
            self.node.create_subscription(cls, topic, lambda raw, t=topic: self.got[t].append(raw),
                                          reliable(100000), raw=True)
            for topic, cls in types.items()
        ]  # fmt: skip
        self.subs.append(self.node.create_subscription(
            DiagnosticArray, '/diagnostics', self._on_diagnostics, reliable(100), raw=True))
        self.watch = ''  # the status name prefix of the node under attack
        self.diagnostics: list[dict[str, str]] = []  # its statuses' values, as they come
        self.finite = {t: [0, 0] for t in self.OUTPUTS}  # topic -> [messages, non-finite]

    def _on_diagnostics(self, raw: bytes) -> None:
        from cloe_ros.io import messages

        _, statuses = messages.decode_diagnostics(raw)
        for s in statuses:
            if self.watch and s.name.startswith(self.watch):
                self.diagnostics.append({**dict(s.values), '_message': s.message})

    def spin(self, seconds: float = 0.02) -> None:
        self.executor.spin_once(timeout_sec=seconds)

    def last(self) -> dict[str, str]:
        return self.diagnostics[-1] if self.diagnostics else {}

    def clear(self, watch: str) -> None:
        self.watch = watch
        self.diagnostics = []
        for t in self.OUTPUTS:
            self.got[t] = []

    def matched(self) -> bool:
        return all(p.get_subscription_count() >= 1 for p in self.pubs.values()) and all(
            s.get_publisher_count() >= 1 for s in self.subs
        )

    def unmatched(self) -> bool:
        return all(p.get_subscription_count() == 0 for p in self.pubs.values())

    def account_finite(self) -> None:
        """Decode every output message received and count those with a non-finite value."""
        from cloe_ros.io import messages

        for topic in self.OUTPUTS:
            for raw in self.got[topic]:
                try:
                    if topic == '/cloe/state':
                        s = messages.decode_odometry(raw)
                        values = [s.position, s.orientation, s.linear, s.angular,
                                  s.pose_covariance, s.twist_covariance]  # fmt: skip
                    elif topic == '/cloe/prediction':
                        p = messages.decode_path(raw)
                        values = [p.positions, p.orientations]
                    else:
                        values = [messages.decode_float64_multi_array(raw)[1]]
                    ok = all(np.isfinite(v).all() for v in values)
                except messages.MessageError:
                    ok = False
                self.finite[topic][0] += 1
                self.finite[topic][1] += not ok

    def close(self) -> None:
        self.executor.shutdown()
        self.node.destroy_node()
        self.rclpy.try_shutdown(context=self.ctx)


def ros_env(domain: int, workdir: Path) -> dict[str, str]:
    env = {k: v for k, v in os.environ.items() if k != 'PYTHONPATH'}
    env.update(ROS_DOMAIN_ID=str(domain), ROS_AUTOMATIC_DISCOVERY_RANGE='LOCALHOST',
               ROS_LOG_DIR=str(workdir / 'ros_log'), PYTHONUNBUFFERED='1')  # fmt: skip
    return env


class NodeRun:
    """A ``cloe_inference`` process under attack, fed by the :class:`Client`."""

    counter = 0

    def __init__(self, client: Client, domain: int, workdir: Path, **params) -> None:
        NodeRun.counter += 1
        self.client = client
        self.name = f'attack_{NodeRun.counter}'
        self.log = workdir / f'{self.name}.log'
        wait_until(client.unmatched, 20, client.spin)  # the previous node has gone
        client.clear(f'{self.name}: ')
        args = ['-r', f'__node:={self.name}', '-p', 'diagnostics_period:=0.2']
        for k, v in params.items():
            args += ['-p', f'{k}:={v}']
        self._out = self.log.open('w')
        self.proc = subprocess.Popen(
            [str(BIN / 'cloe_inference'), '--ros-args', *args], env=ros_env(domain, workdir),
            stdout=self._out, stderr=subprocess.STDOUT, cwd=workdir, start_new_session=True,
        )  # fmt: skip
        self.sent = {'odom_received': 0, 'reference_received': 0, 'malformed': 0}
        self.ready = wait_until(
            lambda: client.matched() and bool(client.diagnostics), 60, client.spin
        )

    def counted(self, key: str) -> int:
        value = self.client.last().get(key, '-1')
        return int(value) if value.lstrip('-').isdigit() else -1

    def caught_up(self, extra: dict[str, int] | None = None) -> bool:
        wanted = {**self.sent, **(extra or {})}
        return all(self.counted(k) >= n for k, n in wanted.items())

    def publish(self, topic: str, raw: bytes, counter: str | None) -> None:
        self.client.pubs[topic].publish(raw)
        if counter:
            self.sent[counter] += 1

    def feed(self, items: list[tuple[str, bytes, str | None]], block: int = 40) -> bool:
        """Publish ``(topic, cdr, diagnostics counter)`` items, waiting after each ``block``
        until the node has counted them. False if it stopped counting (60 s).

        A block is 0.2 s of the flight (odometry and references at 100 Hz), less than the node's
        ``reference_timeout`` (0.25 s): the two topics are delivered on their own, and odometry
        taken more than that ahead of the references would step on a held reference, so the
        states would differ from the in-process run for a reason other than the attack."""
        for i, (topic, raw, counter) in enumerate(items, start=1):
            self.publish(topic, raw, counter)
            if i % block == 0 and not wait_until(self.caught_up, 60, self.client.spin):
                return False
        return self.settle()

    def settle(self, extra: dict[str, int] | None = None, timeout: float = 60) -> bool:
        """Wait until the node has counted everything sent, then for two more reports (its
        outputs published before them have arrived by then)."""
        ok = wait_until(lambda: self.caught_up(extra), timeout, self.client.spin)
        n = len(self.client.diagnostics)
        wait_until(lambda: len(self.client.diagnostics) >= n + 2, 10, self.client.spin)
        return ok

    def reset(self) -> bool:
        from std_srvs.srv import Trigger

        cli = self.client.node.create_client(Trigger, f'/{self.name}/reset')
        try:
            if not wait_until(cli.service_is_ready, 20, self.client.spin):
                return False
            future = cli.call_async(Trigger.Request())
            wait_until(future.done, 20, self.client.spin)
            return future.done() and future.result().success
        finally:
            self.client.node.destroy_client(cli)

    def stop(self) -> tuple[bool, int | None, str]:
        """(was it still running, exit status after SIGINT, its output)."""
        alive = self.proc.poll() is None
        if alive:
            self.proc.send_signal(signal.SIGINT)
        try:
            self.proc.wait(30)
        except subprocess.TimeoutExpired:
            os.killpg(self.proc.pid, signal.SIGKILL)
            self.proc.wait(10)
        self._out.close()
        self.client.account_finite()
        return alive, self.proc.returncode, self.log.read_text(errors='replace')


def states(client: Client) -> list:
    from cloe_ros.io import messages

    return [messages.decode_odometry(r) for r in client.got['/cloe/state']]


def compare(node_states: list, clean: dict[int, np.ndarray]) -> tuple[int, float]:
    """(states the node published, largest position difference from the clean run, m, over the
    stamps both have)."""
    diffs = [float(np.linalg.norm(s.position - clean[s.stamp_ns])) for s in node_states
             if s.stamp_ns in clean]  # fmt: skip
    return len(node_states), max(diffs) if diffs else math.inf


def envelope(client: Client, node_states: list) -> tuple[int, int, float]:
    """(predictions checked, poses beyond the physical envelope of the estimate, farthest pose
    from the estimate in m). The envelope: ``min(|v| h + a h^2 / 2, v_max h)``, ``|v|`` the
    estimate's speed (the norm of the body twist is the world speed's), ``a`` 100 m/s^2, ``v_max``
    150 m/s (``cloe_ros.core.model``)."""
    from cloe_ros.core.model import QUADROTOR_MAX_ACCELERATION, QUADROTOR_MAX_SPEED
    from cloe_ros.io import messages

    at = {s.stamp_ns: s for s in node_states}
    checked = beyond = 0
    farthest = 0.0
    for raw in client.got['/cloe/prediction']:
        p = messages.decode_path(raw)
        s = at.get(p.stamp_ns)
        if s is None:
            continue
        h = (p.stamps_ns - p.stamp_ns) / NS
        speed = min(float(np.linalg.norm(s.linear)), QUADROTOR_MAX_SPEED)
        reach = np.minimum(speed * h + 0.5 * QUADROTOR_MAX_ACCELERATION * h**2,
                           QUADROTOR_MAX_SPEED * h)  # fmt: skip
        d = np.linalg.norm(p.positions - s.position, axis=1)
        checked += 1
        beyond += int(np.sum(d > reach + 1e-6))
        farthest = max(farthest, float(d.max(initial=0.0)))
    return checked, beyond, farthest


def ended_cleanly(run: NodeRun) -> list[tuple[bool, str]]:
    alive, status, output = run.stop()
    checks = [(alive, 'node alive' if alive else 'node died'),
              (status == 0, f'exit {status}')]  # fmt: skip
    if TRACEBACK in output:
        line = [x for x in output.splitlines() if x.strip()][-1]
        checks.append((False, f'traceback: {line[:120]}'))
    return checks


class NodeAttacks:
    """The attacks on ``cloe_inference``; each method returns its :class:`Row`."""

    def __init__(self, domain: int, workdir: Path, quick: bool) -> None:
        self.domain, self.workdir, self.quick = domain, workdir, quick
        workdir.mkdir(parents=True, exist_ok=True)
        self.client = Client(domain)
        self.seq = flight(3.0 if quick else 6.0)
        self.odom_at = [i for i, (k, _) in enumerate(self.seq) if k == 'odom']
        self.mid = self.odom_at[len(self.odom_at) // 2]  # index in seq of the middle odometry
        self._clean: dict[str, dict[int, np.ndarray]] = {}

    def clean(self, algorithm: str = 'cloe_iv') -> dict[int, np.ndarray]:
        if algorithm not in self._clean:
            self._clean[algorithm] = offline_states(self.seq, algorithm)
        return self._clean[algorithm]

    def start(self, **params) -> NodeRun:
        return NodeRun(self.client, self.domain, self.workdir, **params)

    @staticmethod
    def items(seq: list[tuple[str, object]]) -> list[tuple[str, bytes, str]]:
        counter = {'odom': 'odom_received', 'reference': 'reference_received'}
        return [(k, encode(k, s), counter[k]) for k, s in seq]

    def attacked(self, insert: list[tuple[str, bytes, str | None]], replace_mid=None):
        """The flight's items with ``insert`` after the middle odometry (which ``replace_mid``,
        a function of its sample, may replace first)."""
        items = self.items(self.seq)
        at = self.mid
        if replace_mid is not None:
            items[at] = ('odom', encode('odom', replace_mid(self.seq[at][1])), 'odom_received')
        return items[: at + 1] + insert + items[at + 1:]

    def mid_sample(self, offset_ns: int = 0, **changes):
        s = self.seq[self.mid][1]
        return dataclasses.replace(s, stamp_ns=s.stamp_ns + offset_ns, **changes)

    def common(self, run: NodeRun, fed: bool, tolerance: float, algorithm: str = 'cloe_iv',
               rejected: dict[str, int] | None = None) -> list[tuple[bool, str]]:  # fmt: skip
        """Checks every attack makes: fed and counted, the rejections expected (exactly), the
        states against the clean run's."""
        checks = [(run.ready, 'node ready' if run.ready else 'node not ready in 60 s'),
                  (fed, 'all counted' if fed else 'node stopped counting')]  # fmt: skip
        last = run.client.last()
        got = {k[len('rejected: '):]: int(v) for k, v in last.items()
               if k.startswith('rejected: ')}  # fmt: skip
        if rejected is not None:
            ok = got == rejected
            text = ', '.join(f'{k} {v}' for k, v in sorted(got.items())) or 'nothing rejected'
            checks.append((ok, f'rejected: {text}' + ('' if ok else f' (expected {rejected})')))
        if last.get('malformed', '0') != '0':
            checks.append((True, f'malformed {last["malformed"]}'))
        n, diff = compare(states(run.client), self.clean(algorithm))
        clean_n = len(self.clean(algorithm))
        checks.append((n >= clean_n - 2 and diff <= tolerance,
                       f'{n}/{clean_n} states, max {diff * 1e3:.3g} mm from the clean run'))
        return checks

    # -- the attacks -------------------------------------------------------------------------

    def clean_flight(self, algorithm: str) -> Row:
        run = self.start(algorithm=algorithm)
        fed = run.feed(self.items(self.seq))
        checks = self.common(run, fed, 1e-9, algorithm, rejected={})
        checks += ended_cleanly(run)
        return Row(f'clean flight ({algorithm}), baseline',
                   'nothing rejected; states equal the in-process engine\'s', *verdict(checks))

    def non_finite(self) -> Row:
        nan, inf = math.nan, math.inf
        bad_odom = [self.mid_sample(5_000_000, position=np.array([nan, 0.0, 1.0])),
                    self.mid_sample(5_000_001, linear=np.array([inf, 0.0, 0.0])),
                    self.mid_sample(5_000_002, orientation=np.array([nan, 0.0, 0.0, 1.0])),
                    self.mid_sample(5_000_003, angular=np.array([0.0, -inf, 0.0]))]  # fmt: skip
        ref = next(s for k, s in self.seq[self.mid:] if k == 'reference')
        bad_ref = [dataclasses.replace(ref, stamp_ns=ref.stamp_ns + 1, position=np.full(3, nan)),
                   dataclasses.replace(ref, stamp_ns=ref.stamp_ns + 2,
                                       orientation=np.array([0.0, 0.0, inf, 1.0]))]  # fmt: skip
        insert = [('odom', encode('odom', s), 'odom_received') for s in bad_odom]
        insert += [('reference', encode('reference', s), 'reference_received') for s in bad_ref]
        run = self.start()
        fed = run.feed(self.attacked(insert))
        checks = self.common(run, fed, 1e-9, rejected={'non-finite odometry': 4,
                                                       'non-finite reference': 2})
        checks += ended_cleanly(run)
        return Row('NaN / inf in odometry (position, velocity, orientation, rate) and reference',
                   'each rejected and counted; states as the clean run\'s', *verdict(checks))

    def bad_quaternion(self) -> Row:
        ref = next(s for k, s in self.seq[self.mid:] if k == 'reference')
        insert = [
            ('odom', encode('odom', self.mid_sample(5_000_000, orientation=np.array(
                [0.0, 0.0, 0.0, 2.0]))), 'odom_received'),
            ('odom', encode('odom', self.mid_sample(5_000_001, orientation=np.zeros(4))),
             'odom_received'),
            ('reference', encode('reference', dataclasses.replace(
                ref, stamp_ns=ref.stamp_ns + 1, orientation=np.array([0.0, 0.0, 0.3, 0.3]))),
             'reference_received'),
        ]  # fmt: skip
        run = self.start()
        fed = run.feed(self.attacked(insert))
        checks = self.common(run, fed, 1e-9, rejected={'invalid quaternion': 2,
                                                       'invalid reference quaternion': 1})
        checks += ended_cleanly(run)
        return Row('bad quaternion (norm 2, norm 0; reference norm 0.42)',
                   'rejected and counted; states as the clean run\'s', *verdict(checks))

    def backward_and_duplicate(self) -> Row:
        s = self.seq[self.mid][1]
        ref = next(r for k, r in reversed(self.seq[: self.mid]) if k == 'reference')
        insert = [
            ('odom', encode('odom', s), 'odom_received'),  # duplicate
            ('odom', encode('odom', self.mid_sample(-5_000_000)), 'odom_received'),  # backward
            ('reference', encode('reference', ref), 'reference_received'),  # duplicate
            ('reference', encode('reference', dataclasses.replace(
                ref, stamp_ns=ref.stamp_ns - 5_000_000)), 'reference_received'),
        ]  # fmt: skip
        run = self.start()
        fed = run.feed(self.attacked(insert))
        checks = self.common(run, fed, 1e-9, rejected={
            'duplicate stamp': 1, 'out-of-order stamp': 1, 'reference duplicate stamp': 1,
            'reference out-of-order stamp': 1})  # fmt: skip
        stamps = [x.stamp_ns for x in states(run.client)]
        increasing = all(b > a for a, b in itertools.pairwise(stamps))
        checks.append((increasing, 'published stamps increase' if increasing
                       else 'published stamps go back'))  # fmt: skip
        checks += ended_cleanly(run)
        return Row('backward (-5 ms) and duplicate stamps, odometry and reference',
                   'rejected and counted; published stamps only increase', *verdict(checks))

    def glitched_stamp(self, offset_s: float) -> Row:
        offset = round(offset_s * NS)
        run = self.start()
        fed = run.feed(self.attacked([], replace_mid=lambda s: dataclasses.replace(
            s, stamp_ns=s.stamp_ns + offset)))  # fmt: skip
        checks = self.common(run, fed, 5e-3, rejected={'stamp outlier': 1})
        last = run.client.last()
        accepted = int(last.get('odom_accepted', -1))
        n_odom = len(self.odom_at)
        checks.append((accepted == n_odom - 1, f'{accepted}/{n_odom} odometry accepted'))
        jumps = last.get('time_jumps')
        checks.append((jumps == '0', f'time_jumps {jumps}'))
        true_end = self.seq[self.odom_at[-1]][1].stamp_ns
        latest = max((x.stamp_ns for x in states(run.client)), default=0)
        checks.append((latest <= true_end, 'no state beyond the flight' if latest <= true_end
                       else f'a state {(latest - true_end) / NS:.3g} s beyond the flight'))
        checks += ended_cleanly(run)
        return Row(f'odometry stamp glitched {offset_s:+g} s (one message)',
                   'costs that one sample (stamp outlier); no time jump', *verdict(checks))

    def position_jump(self) -> Row:
        run = self.start()
        fed = run.feed(self.attacked([], replace_mid=lambda s: dataclasses.replace(
            s, position=s.position + np.array([99e3, 0.0, 0.0]))))  # fmt: skip
        checks = self.common(run, fed, 5e-3, rejected={'position outlier': 1})
        jumps = run.client.last().get('position_jumps')
        checks.append((jumps == '0', f'position_jumps {jumps}'))
        checks.append(self.envelope_check(run))
        checks += ended_cleanly(run)
        return Row('position jump of 99 km (one message)',
                   'position outlier, one sample; no prediction beyond the physical envelope',
                   *verdict(checks))

    def envelope_check(self, run: NodeRun) -> tuple[bool, str]:
        checked, beyond, farthest = envelope(run.client, states(run.client))
        return (checked > 0 and beyond == 0,
                f'{checked} predictions, {beyond} poses beyond the envelope '
                f'(farthest {farthest:.3g} m from the estimate)')

    def fast(self) -> Row:
        insert = [('odom', encode('odom', self.mid_sample(5_000_000, angular=np.array(
            [0.0, 0.0, 999.0]))), 'odom_received')]  # fmt: skip
        run = self.start()
        fed = run.feed(self.attacked(insert, replace_mid=lambda s: dataclasses.replace(
            s, linear=np.array([999.0, 0.0, 0.0]))))  # fmt: skip
        checks = self.common(run, fed, 5e-3, rejected={
            'velocity beyond 150 m/s': 1, 'angular rate beyond 100 rad/s': 1})
        checks.append(self.envelope_check(run))
        checks += ended_cleanly(run)
        return Row('999 m/s body velocity (and 999 rad/s body rate)',
                   'rejected beyond the bounds; no prediction beyond the envelope',
                   *verdict(checks))

    def int32_limit(self) -> Row:
        from cloe_ros.core.samples import MAX_STAMP_NS
        from cloe_ros.io import messages

        seq = self.seq[: self.mid + 1]
        shift = MAX_STAMP_NS - NS - seq[-1][1].stamp_ns  # last odometry 1 s before the limit
        seq = restamped(seq, shift)
        last = seq[-1][1]
        # the last representable stamp itself: sec 2**31 - 1, nanosec 999999999
        seq.append(('odom', dataclasses.replace(last, stamp_ns=MAX_STAMP_NS)))
        run = self.start()
        fed = run.feed(self.items(seq))
        checks = [(run.ready, 'node ready'), (fed, 'all counted' if fed else
                                               'node stopped counting')]  # fmt: skip
        got = states(run.client)
        checks.append((len(got) > 0, f'{len(got)} states'))
        beyond = sum(x.stamp_ns > MAX_STAMP_NS for x in got)
        cut = poses = 0
        for raw in run.client.got['/cloe/prediction']:
            p = messages.decode_path(raw)
            beyond += int(np.sum(p.stamps_ns > MAX_STAMP_NS)) + (p.stamp_ns > MAX_STAMP_NS)
            cut += len(p.stamps_ns) < 50
            poses += len(p.stamps_ns)
        for raw in run.client.got['/cloe/prediction_radius']:
            rows = messages.decode_float64_multi_array(raw)[1].reshape(-1, 2)
            beyond += int(np.sum(rows[:, 0] > MAX_STAMP_NS / NS + 1e-3))
        n_pred = len(run.client.got['/cloe/prediction'])
        checks.append((beyond == 0, f'{beyond} stamps beyond 2038-01-19T03:14:07.999999999'))
        checks.append((True, f'{n_pred} predictions, {cut} cut at the limit'))
        checks += ended_cleanly(run)
        return Row('stamps up to the int32 limit (2038-01-19T03:14:07.999999999)',
                   'node lives; nothing stamped beyond the limit', *verdict(checks))

    def nanosec(self) -> Row:
        from cloe_ros.io import messages

        def with_stamp(sample, sec: int, nanosec: int) -> bytes:
            raw = encode('odom', dataclasses.replace(sample, stamp_ns=0))
            msg = messages.TYPESTORE.deserialize_cdr(raw, messages.ODOMETRY)
            msg.header.stamp = messages.Time(sec=sec, nanosec=nanosec)
            return bytes(messages.TYPESTORE.serialize_cdr(msg, messages.ODOMETRY))

        s = self.seq[self.mid][1]
        sec = s.stamp_ns // NS
        ref = next(r for k, r in self.seq[self.mid:] if k == 'reference')
        raw_ref = messages.TYPESTORE.deserialize_cdr(encode('reference', ref),
                                                     messages.POSE_STAMPED)  # fmt: skip
        raw_ref.header.stamp = messages.Time(sec=int(ref.stamp_ns // NS), nanosec=1_000_000_000)
        insert = [
            ('odom', with_stamp(s, sec, 1_500_000_000), 'malformed'),
            ('odom', with_stamp(s, 2**31 - 1, 2**32 - 1), 'malformed'),
            ('reference', bytes(messages.TYPESTORE.serialize_cdr(raw_ref, messages.POSE_STAMPED)),
             'malformed'),
        ]  # fmt: skip
        run = self.start()
        fed = run.feed(self.attacked(insert))
        checks = self.common(run, fed, 1e-9, rejected={})
        malformed = run.client.last().get('malformed')
        checks.append((malformed == '3', f'malformed {malformed} of 3'))
        checks += ended_cleanly(run)
        return Row('nanosec >= 1e9 (1.5e9; 2**32-1 at sec 2**31-1; reference 1e9)',
                   'malformed, counted; nothing carried into sec', *verdict(checks))

    def stray_frame(self) -> Row:
        n = 1000 if self.quick else 4000
        seq = flight(n / 100 + 0.005)
        seq = seq[: [i for i, (k, _) in enumerate(seq) if k == 'odom'][n - 1] + 1]
        first = seq[0][1] if seq[0][0] == 'odom' else next(s for k, s in seq if k == 'odom')
        stray = dataclasses.replace(first, frame_id='map', stamp_ns=first.stamp_ns - NS // 100)
        run = self.start()
        # the stray one alone first, counted before the others are sent: DDS keeps no order
        # across topics, and a world reference could otherwise come before it
        fed = run.feed([('odom', encode('odom', stray), 'odom_received')], block=1)
        fed = fed and run.feed(self.items(seq), block=500)
        got = states(run.client)
        last = run.client.last()
        relearnt = last.get('frames_relearnt')
        wrong = int(last.get('rejected: wrong frame', 0)) + int(
            last.get('rejected: wrong reference frame', 0))
        checks = [(run.ready, 'node ready'), (fed, 'all counted' if fed else
                                               'node stopped counting')]  # fmt: skip
        checks.append((len(got) >= n - 50, f'{len(got)} states from {n} odometry in world'))
        checks.append((relearnt == '1', f'frames_relearnt {relearnt}, {wrong} wrong frame'))
        reset = run.reset()
        checks.append((reset, '~/reset answered' if reset else '~/reset failed'))
        before = len(run.client.got['/cloe/state'])
        t_end = seq[-1][1].stamp_ns
        tail = restamped(flight(0.5), t_end + NS // 100 - self.seq[0][1].stamp_ns)
        tail = [(k, dataclasses.replace(s, frame_id='odom')) for k, s in tail]
        fed = run.feed(self.items(tail))
        after = states(run.client)[before:]
        in_odom = sum(x.frame_id == 'odom' for x in after)
        wrong_after = int(run.client.last().get('rejected: wrong frame', 0)) + int(
            run.client.last().get('rejected: wrong reference frame', 0))
        checks.append((in_odom > 0 and wrong_after == wrong,
                       f'after reset: {in_odom} states in odom, '
                       f'{wrong_after - wrong} more wrong frame'))
        checks += ended_cleanly(run)
        return Row(f'first odometry in a stray frame (map), then {n} in world; then ~/reset and '
                   'inputs in odom', 'frame learnt again after 20 inputs; reset forgets it',
                   *verdict(checks))

    def big_plans(self) -> Row:
        from cloe_ros.io import messages

        count = 3 if self.quick else 20
        n = 20_000
        t = self.seq[self.mid][1].stamp_ns
        stamps = t + NS // 100 * np.arange(1, n + 1, dtype=np.int64)
        plan = messages.encode_path(messages.PathSample(
            t, 'world', stamps, np.tile([0.0, 0.0, 1.0], (n, 1)),
            np.tile([0.0, 0.0, 0.0, 1.0], (n, 1))))  # fmt: skip
        items = self.items(self.seq)
        at = self.mid
        every = max(1, (len(items) - at) // (count + 1))
        attacked = items[:at + 1]
        plans = 0
        for i, item in enumerate(items[at + 1:]):
            if i % every == 0 and plans < count:
                attacked.append(('plan', plan, None))
                plans += 1
            attacked.append(item)
        run = self.start()
        fed = run.feed(attacked)
        key = 'plan longer than 10000 poses'
        fed = run.settle({f'rejected: {key}': count}) and fed
        checks = self.common(run, fed, 1e-9, rejected={key: count})
        odom = run.client.last().get('odom_received')
        checks.append((odom == str(len(self.odom_at)), f'{odom}/{len(self.odom_at)} odometry '
                       f'received ({len(plan) / 1e6:.1f} MB plans)'))  # fmt: skip
        checks += ended_cleanly(run)
        return Row(f'{count} plans of 20000 poses among the odometry',
                   'refused (> 10000 poses); no odometry lost, states as clean',
                   *verdict(checks))

    def malformed(self) -> Row:
        good = encode('odom', self.seq[self.mid][1])
        insert = [('odom', b'\x00\x01\x00\x00garbage', 'malformed'),
                  ('odom', good[: len(good) // 2], 'malformed'),
                  ('odom', b'\x00\x01\x00\x00', 'malformed'),
                  ('reference', b'\x00\x01\x00\x00\xff\xff\xff\x7f', 'malformed'),
                  ('plan', b'\x00\x01\x00\x00\x05\x00\x00\x00world\x00\x00\x00\xff\xff\xff\x7f',
                   'malformed')]  # fmt: skip
        run = self.start()
        fed = run.feed(self.attacked(insert))
        checks = self.common(run, fed, 1e-9, rejected={})
        malformed = run.client.last().get('malformed')
        checks.append((malformed == '5', f'malformed {malformed} of 5'))
        checks += ended_cleanly(run)
        return Row('malformed CDR (garbage, a cut message, a header only; reference; plan with '
                   'a 2**31 count)', 'counted as malformed; states as the clean run\'s',
                   *verdict(checks))

    def burst(self) -> Row:
        from cloe_ros.core.kinematics import state_to_odometry
        from cloe_ros.io import messages

        n = 3000 if self.quick else 10_000
        zeta = np.zeros(12)
        zeta[10] = 1.0
        p, q, v, w = state_to_odometry(zeta)
        t0 = 1_000_000 * NS
        run = self.start()
        for k in range(n):
            t = t0 + k * NS // 100
            run.publish('odom', messages.encode_odometry(messages.OdometrySample(
                t, 'world', 'base_link', p, q, v, w)), 'odom_received')
            run.publish('reference', messages.encode_pose_stamped(messages.PoseSample(
                t, 'world', np.array([0.0, 0.0, 1.0]), np.array([0.0, 0.0, 0.0, 1.0]))),
                'reference_received')  # fmt: skip
            if k % 100 == 0:
                self.client.spin(0)
        # wait until the node has counted everything, or its counts stop moving: its last 25
        # reports (5 s) say the same, longer than Fast DDS's heartbeat period (3 s), after which
        # a reliable writer resends what the subscription has not acknowledged
        reports = len(self.client.diagnostics)

        def settled() -> bool:
            recent = self.client.diagnostics[reports:][-25:]
            counts = {(d.get('odom_received'), d.get('reference_received')) for d in recent}
            return run.caught_up() or (len(recent) == 25 and len(counts) == 1)

        wait_until(settled, 300, self.client.spin)
        last = self.client.last()
        received = int(last.get('odom_received', -1))
        # odometry lost in DDS (message_lost) or missing by its stamps (lost in the node's own
        # queue, which DDS does not report)
        lost_keys = {k: v for k, v in last.items()
                     if 'lost' in k.lower() or k == 'odom_missing'}  # fmt: skip
        lost = sum(int(v) for k, v in lost_keys.items() if v.isdigit() and k.startswith('odom'))
        checks = ended_cleanly(run)
        where = f'{received}/{n} odometry received'
        if not lost_keys:
            observed, result = verdict(checks)
            return Row(f'burst of {n} odometry + {n} references, as fast as they go',
                       'every lost input counted (message_lost) in /diagnostics',
                       f'not counted on this build (no lost key in /diagnostics); {where}; '
                       + observed, 'n/a' if result == 'HELD' else 'BROKE')
        keys = ', '.join(f'{k} {v}' for k, v in lost_keys.items())
        checks.append((received + lost >= n, f'{where}, {keys}'))
        return Row(f'burst of {n} odometry + {n} references, as fast as they go',
                   'every lost odometry message counted in /diagnostics (message_lost, or '
                   'missing by its stamps)', *verdict(checks))

    def finite_row(self) -> Row:
        total = sum(n for n, _ in self.client.finite.values())
        bad = {t: b for t, (_, b) in self.client.finite.items() if b}
        counts = ', '.join(f'{t.rsplit("/", 1)[1]} {n}' for t, (n, _) in
                           self.client.finite.items())  # fmt: skip
        text = (f'{total} messages of all runs decoded ({counts}); '
                + (f'non-finite: {bad}' if bad else 'all finite'))
        ok = not bad and all(n > 0 for n, _ in self.client.finite.values())
        return Row('every published value finite (state, parameters, prediction, '
                   'prediction_radius; every run above)', 'no NaN / inf anywhere (-1: not '
                   'measured)', text if ok else f'**{text}**', 'HELD' if ok else 'BROKE')

    def all(self) -> list[Row]:
        rows = [self.clean_flight('cloe_iv'), self.clean_flight('cloe_sm'), self.non_finite(),
                self.bad_quaternion(), self.backward_and_duplicate(), self.glitched_stamp(0.9),
                self.glitched_stamp(100.0), self.position_jump(), self.fast(),
                self.int32_limit(), self.nanosec(), self.stray_frame(), self.big_plans(),
                self.malformed(), self.burst()]  # fmt: skip
        rows.append(self.finite_row())
        self.client.close()
        return rows


# ------------------------------------------------------------------------------ the files


def cloe(workdir: Path, *args: object, timeout: float = 600) -> tuple[int, str, str]:
    proc = subprocess.run([str(BIN / 'cloe'), *map(str, args)], capture_output=True, text=True,
                          cwd=workdir, timeout=timeout,
                          env={k: v for k, v in os.environ.items() if k != 'PYTHONPATH'})
    return proc.returncode, proc.stdout, proc.stderr


def one_error(status: int, out: str, err: str, *wanted: str) -> list[tuple[bool, str]]:
    """Exit 1, no traceback, one ``ERROR:`` line holding every ``wanted`` text."""
    lines = [x for x in err.splitlines() if x.startswith('ERROR:')]
    checks = [(status == 1, f'exit {status}')]
    if TRACEBACK in out + err:
        checks.append((False, 'traceback: ' + (err.strip().splitlines() or [''])[-1][:120]))
    if len(lines) != 1:
        checks.append((False, f'{len(lines)} ERROR lines: {err.strip()[:200]!r}'))
    else:
        missing = [w for w in wanted if w not in lines[0]]
        text = lines[0] if len(lines[0]) <= 160 else lines[0][:157] + '...'
        checks.append((not missing, f'`{text}`' + (f' (lacks {missing})' if missing else '')))
    return checks


def no_traceback(out: str, err: str) -> tuple[bool, str]:
    tb = TRACEBACK in out + err
    return not tb, 'traceback: ' + err.strip().splitlines()[-1][:120] if tb else 'no traceback'


def package_copy(source: Path, target: Path, seconds: float, transform=None) -> Path:
    """The first ``seconds`` of ``source`` written by the package's ``BagWriter`` (zstd chunks
    with CRCs); ``transform(topic, raw)`` may change (or drop: None) each message."""
    from cloe_ros.io.reader import BagReader
    from cloe_ros.io.writer import BagWriter

    with BagReader(source) as reader, BagWriter(target) as writer:
        for name, info in reader.topics.items():
            writer.add_topic(name, info.msgtype)
        end = reader.start_ns + int(seconds * NS)
        for topic, t, raw in reader.messages():
            if t > end:
                break
            raw = bytes(raw) if transform is None else transform(topic, bytes(raw))
            if raw is not None:
                writer.write(topic, t, raw)
    return target


def flip_inside_compressed_chunk(mcap_file: Path) -> tuple[int, int, int]:
    """Flip one bit inside the zstd data of a chunk (the second, or the only one) so that the
    data still decompress to records of the same layout, one message's bytes changed: damage only
    the chunk's CRC can tell. Returns (chunk number from 1, its offset, chunks in the file)."""
    import zstandard
    from mcap.reader import make_reader
    from mcap.records import Chunk
    from mcap.stream_reader import breakup_chunk

    with mcap_file.open('rb') as fh:
        indexes = sorted(make_reader(fh).get_summary().chunk_indexes,
                         key=lambda c: c.chunk_start_offset)  # fmt: skip
    k = min(1, len(indexes) - 1)
    index = indexes[k]
    content = bytearray(mcap_file.read_bytes())
    # opcode, length; start, end, uncompressed size, crc; compression name; data length
    start = index.chunk_start_offset + 9 + 28 + 4 + len(index.compression) + 8
    data = bytes(content[start: start + index.compressed_size])

    def layout(raw: bytes) -> list:
        return [(type(r), getattr(r, 'channel_id', None), getattr(r, 'log_time', None),
                 len(getattr(r, 'data', b''))) for r in breakup_chunk(Chunk('', raw, 0, 0, 0,
                                                                          len(raw)))]  # fmt: skip

    original = zstandard.ZstdDecompressor().decompress(data)
    expected = layout(original)
    for at in range(len(data) // 2, len(data)):
        for bit in (0x01, 0x10, 0x80):
            flipped = bytearray(data)
            flipped[at] ^= bit
            try:
                out = zstandard.ZstdDecompressor().decompress(bytes(flipped))
                if len(out) != len(original) or out == original or layout(out) != expected:
                    continue
            except Exception:  # the flip broke the frame: try another
                continue
            content[start + at] ^= bit
            mcap_file.write_bytes(bytes(content))
            return k + 1, index.chunk_start_offset, len(indexes)
    raise RuntimeError(f'no bit flip in {mcap_file} leaves its chunk decompressible')


def edit_metadata(bag: Path, edit: Callable[[dict], None]) -> None:
    path = bag / 'metadata.yaml'
    meta = yaml.safe_load(path.read_text())
    edit(meta['rosbag2_bagfile_information'])
    path.write_text(yaml.safe_dump(meta))


def mcap_lib_file(path: Path, source: Path, message_encoding: str, schema_encoding: str) -> Path:
    """A ROS 2 MCAP file of the mcap library: /odom and /reference of ``source`` (100 of each),
    /odom's channel in the given encodings."""
    from mcap.writer import Writer

    from cloe_ros.io import messages
    from cloe_ros.io.reader import BagReader

    with path.open('wb') as fh, BagReader(source) as reader:
        w = Writer(fh)
        w.start(profile='ros2', library='attacks.py')
        channels = {}
        for topic, msgtype in (('/odom', messages.ODOMETRY),
                               ('/reference', messages.POSE_STAMPED)):  # fmt: skip
            odom = topic == '/odom'
            msgdef = messages.TYPESTORE.generate_msgdef(msgtype)[0]
            sid = w.register_schema(msgtype, schema_encoding if odom else 'ros2msg',
                                    msgdef.encode())  # fmt: skip
            channels[topic] = w.register_channel(topic, message_encoding if odom else 'cdr', sid,
                                                 {'offered_qos_profiles': ''})  # fmt: skip
        n = 0
        for topic, t, raw in reader.messages(['/odom', '/reference']):
            w.add_message(channels[topic], log_time=t, data=bytes(raw), publish_time=t)
            n += 1
            if n >= 200:
                break
        w.finish()
    return path


class FileAttacks:
    """The attacks on the ``cloe`` command and on the node's start-up; each returns a Row."""

    def __init__(self, domain: int, workdir: Path, quick: bool) -> None:
        self.domain, self.workdir = domain, workdir
        self.seconds = 12.0  # two chunks: the flipped one, and one before it to recover
        self.base = package_copy(REPO / 'bags' / 'position', workdir / 'position_crc',
                                 self.seconds)  # fmt: skip
        from cloe_ros.io.reader import BagReader

        with BagReader(self.base) as bag:
            self.counts = {n: i.count for n, i in bag.topics.items()}

    def fresh(self, name: str) -> Path:
        path = self.workdir / name
        shutil.copytree(self.base, path)
        return path

    def bit_flip(self) -> list[Row]:
        from cloe_ros.io.reader import BagReader

        bag = self.fresh('flipped')
        mcap = next(bag.glob('*.mcap'))
        number, offset, chunks = flip_inside_compressed_chunk(mcap)
        named = f'corrupt chunk at byte offset {offset}'
        attack = f'bit flip inside zstd data of chunk {number} of {chunks} (CRC bag)'
        rows = []
        status, out, err = cloe(self.workdir, 'bag', 'info', bag)
        said = next((x.strip() for x in out.splitlines() if x.startswith('damaged:')), '')
        found = f'Chunk at byte {offset}' in said and 'CRC does not match' in said
        checks = [(status == 1, f'exit {status}'),
                  (found, f'`{said[:160]}`' if said else (out + err).strip()[-200:])]
        checks.append(no_traceback(out, err))
        rows.append(Row(f'{attack}: `cloe bag info`', 'damage found, the chunk named, exit 1',
                        *verdict(checks)))
        out_bag = self.workdir / 'flipped_inferred'
        status, out, err = cloe(self.workdir, 'infer', bag, '-o', out_bag, '-q')
        checks = one_error(status, out, err, named, 'Chunk checksum mismatch')
        checks.append((not out_bag.exists(), 'no output left' if not out_bag.exists()
                       else 'output left behind'))  # fmt: skip
        rows.append(Row(f'{attack}: `cloe infer`', 'one ERROR naming the chunk; no output',
                        *verdict(checks)))
        report = self.workdir / 'flipped_report'
        status, out, err = cloe(self.workdir, 'report', bag, '-o', report, '-q')
        checks = one_error(status, out, err, named)
        checks.append((not report.exists(), 'no folder left' if not report.exists()
                       else f'folder left: {sorted(p.name for p in report.iterdir())}'))
        rows.append(Row(f'{attack}: `cloe report`', 'one ERROR naming the chunk; no folder',
                        *verdict(checks)))
        recovered = self.workdir / 'flipped_recovered'
        status, out, err = cloe(self.workdir, 'bag', 'recover', bag, '-o', recovered)
        checks = [(status in (0, 1), f'exit {status}'), no_traceback(out, err)]
        said = f'chunk {number}' in out + err or str(offset) in out + err
        checks.append((said, 'the chunk named' if said else 'chunk not named: '
                       + (out + err).strip()[-200:]))  # fmt: skip
        if recovered.exists():
            with BagReader(self.base) as reader:
                original = {(tp, t): bytes(raw) for tp, t, raw in reader.messages()}
            with BagReader(recovered) as reader:
                got = [(tp, t, bytes(raw)) for tp, t, raw in reader.messages()]
            changed = sum(original.get((tp, t)) != raw for tp, t, raw in got)
            checks.append((changed == 0, f'{len(got)}/{len(original)} messages recovered, '
                           f'{changed} differ from the original'))
        rows.append(Row(f'{attack}: `cloe bag recover`',
                        'the chunk named and left out; no changed message recovered',
                        *verdict(checks)))
        return rows

    def lying_counts(self) -> Row:
        bag = self.fresh('lying')
        edit_metadata(bag, lambda m: m['topics_with_message_count'][[
            e['topic_metadata']['name'] for e in m['topics_with_message_count']].index(
                '/odom')].update(message_count=10))  # fmt: skip
        status, out, err = cloe(self.workdir, 'bag', 'info', bag)
        n = self.counts['/odom']
        line = next((x for x in out.splitlines() if '/odom' in x and 'warning' not in x), '')
        warning = next((x for x in (out + err).splitlines() if x.startswith('warning:')), '')
        checks = [(status == 0, f'exit {status}'), no_traceback(out, err),
                  (str(n) in line and ' 10 ' not in f' {line} ', f'/odom line: `{line.strip()}`'),
                  ('10' in warning and str(n) in warning, f'`{warning.strip()}`')]  # fmt: skip
        return Row('metadata.yaml says /odom has 10 messages: `cloe bag info`',
                   'counts from the file; the mismatch reported', *verdict(checks))

    def zero_count(self) -> Row:
        bag = self.fresh('zero_count')

        def zero(m: dict) -> None:
            m['message_count'] = 0
            for e in m['topics_with_message_count']:
                e['message_count'] = 0

        edit_metadata(bag, zero)
        status, out, err = cloe(self.workdir, 'infer', bag, '-o', self.workdir / 'zero_out', '-q')
        checks = [(status == 0, f'exit {status}'), no_traceback(out, err),
                  ('steps' in out and not out.startswith('/: 0 steps'),
                   f'`{out.strip().splitlines()[0] if out.strip() else err.strip()[-160:]}`')]
        return Row('metadata.yaml says message_count 0: `cloe infer`',
                   'the file\'s messages inferred, exit 0', *verdict(checks))

    def encoding(self, message_encoding: str, schema_encoding: str) -> Row:
        path = mcap_lib_file(self.workdir / f'{message_encoding}_{schema_encoding}.mcap',
                             self.base, message_encoding, schema_encoding)  # fmt: skip
        wanted = f"'{message_encoding}'" if message_encoding != 'cdr' else f"'{schema_encoding}'"
        checks = []
        for args in (('bag', 'info', path),
                     ('infer', path, '-o', self.workdir / f'{path.stem}_out', '-q')):
            status, out, err = cloe(self.workdir, *args)
            checks += one_error(status, out, err, '/odom', wanted)
        what = (f'{message_encoding}-encoded channel' if message_encoding != 'cdr'
                else f'unknown schema encoding {schema_encoding}')  # fmt: skip
        return Row(f'{what} (/odom): `cloe bag info`, `cloe infer`',
                   'refused: one ERROR naming the topic and the encoding', *verdict(checks))

    def rewritten(self, how: str) -> Path:
        from cloe_ros.io import messages

        def transform(topic: str, raw: bytes) -> bytes:
            if topic != '/odom':
                return raw
            if how == 'malformed':
                return b'\x00\x01\x00\x00' + bytes(12)
            nan = np.full(3, np.nan)
            return messages.encode_odometry(dataclasses.replace(
                messages.decode_odometry(raw), position=nan, linear=nan))  # fmt: skip

        return package_copy(REPO / 'bags' / 'position', self.workdir / f'odom_{how}',
                            self.seconds, transform)  # fmt: skip

    def no_usable_input(self, how: str) -> Row:
        bag = self.rewritten(how)
        out_bag = self.workdir / f'odom_{how}_out'
        status, out, err = cloe(self.workdir, 'infer', bag, '-o', out_bag, '-q')
        checks = one_error(status, out, err, str(bag), 'no usable input', '/odom')
        checks.append((not out_bag.exists(), 'no output left' if not out_bag.exists()
                       else 'output left behind'))  # fmt: skip
        return Row(f'all odometry {"malformed CDR" if how == "malformed" else "NaN"}: '
                   '`cloe infer`', 'exit 1 with the reason, naming bag and topics; no output',
                   *verdict(checks))

    def report_malformed(self) -> Row:
        bag = self.workdir / 'odom_malformed'
        if not bag.exists():
            self.rewritten('malformed')
        report = self.workdir / 'malformed_report'
        status, out, err = cloe(self.workdir, 'report', bag, '-o', report, '-q')
        checks = one_error(status, out, err, str(bag), '/odom')
        left = report.exists()
        checks.append((not left, 'no folder left' if not left else
                       f'left: {sorted(str(p.relative_to(report)) for p in report.rglob("*"))}'))
        return Row('`cloe report` on the all-malformed bag',
                   'one ERROR naming the bag and topic; no partial folder', *verdict(checks))

    def int32_limit(self) -> list[Row]:
        from cloe_ros.core.samples import MAX_STAMP_NS
        from cloe_ros.io import messages
        from cloe_ros.io.reader import BagReader

        with BagReader(self.base) as reader:
            last = max(messages.decode_odometry(raw).stamp_ns
                       for _, _, raw in reader.messages(['/odom']))  # fmt: skip
        shift = MAX_STAMP_NS - NS // 2 - last

        def transform(topic: str, raw: bytes) -> bytes:
            if topic in ('/odom', '/ground_truth'):
                s = messages.decode_odometry(raw)
                return messages.encode_odometry(dataclasses.replace(
                    s, stamp_ns=s.stamp_ns + shift))  # fmt: skip
            if topic == '/reference':
                s = messages.decode_pose_stamped(raw)
                return messages.encode_pose_stamped(dataclasses.replace(
                    s, stamp_ns=s.stamp_ns + shift))  # fmt: skip
            return raw

        bag = package_copy(self.base, self.workdir / 'near_2038', self.seconds + 1, transform)
        out_bag = self.workdir / 'near_2038_out'
        status, out, err = cloe(self.workdir, 'infer', bag, '-o', out_bag, '-q')
        checks = [(status == 0, f'exit {status}'), no_traceback(out, err)]
        if status == 0:
            beyond = poses = 0
            with BagReader(out_bag) as reader:
                for _, _, raw in reader.messages(['/cloe/prediction']):
                    p = messages.decode_path(raw)
                    beyond += int(np.sum(p.stamps_ns > MAX_STAMP_NS))
                    poses += len(p.stamps_ns)
            checks.append((beyond == 0, f'{poses} predicted poses, {beyond} beyond the limit'))
        rows = [Row('stamps up to 0.5 s before the int32 limit: `cloe infer`',
                    'exit 0, no traceback, no pose beyond the limit', *verdict(checks))]
        report = self.workdir / 'near_2038_report'
        status, out, err = cloe(self.workdir, 'report', bag, '-o', report, '-q')
        checks = [(status == 0, f'exit {status}'), no_traceback(out, err),
                  ((report / 'index.html').exists(), 'index.html written')]  # fmt: skip
        rows.append(Row('stamps up to 0.5 s before the int32 limit: `cloe report`',
                        'exit 0, no traceback, the report written', *verdict(checks)))
        return rows

    def params_file(self, how: str) -> Row:
        if how == 'missing':
            path = self.workdir / 'nonexistent.yaml'
        else:
            path = self.workdir / 'malformed.yaml'
            path.write_text('cloe_inference:\n  ros__parameters: {rate: [100,\n')
        proc = subprocess.run(
            [str(BIN / 'cloe_inference'), '--ros-args', '--params-file', str(path)],
            capture_output=True, text=True, timeout=60, cwd=self.workdir,
            env=ros_env(self.domain, self.workdir),
        )  # fmt: skip
        lines = [x for x in (proc.stdout + proc.stderr).splitlines() if x.strip()]
        checks = [(proc.returncode == 1, f'exit {proc.returncode}')]
        if TRACEBACK in proc.stdout + proc.stderr:
            checks.append((False, 'traceback: ' + lines[-1][:120]))
        ok = len(lines) == 1 and lines[0].startswith(f'ERROR: parameter file {path}')
        checks.append((ok, f'`{lines[0]}`' if len(lines) == 1 else f'{len(lines)} lines: '
                       f'{lines[:3]}'))  # fmt: skip
        return Row(f'`cloe_inference --ros-args --params-file` {how} file',
                   'one ERROR line naming the file, exit 1', *verdict(checks))

    def symlink_loop(self) -> Row:
        loop = self.workdir / 'loop'
        loop.symlink_to(loop)
        checks = []
        for args in (('bag', 'info', loop), ('infer', loop, '-o', self.workdir / 'loop_out'),
                     ('bag', 'recover', loop, '-o', self.workdir / 'loop_rec')):  # fmt: skip
            status, out, err = cloe(self.workdir, *args)
            checks += one_error(status, out, err, 'symbolic link loop')
        return Row('symlink loop as the bag: `cloe bag info`, `infer`, `bag recover`',
                   'one ERROR saying it is a symbolic link loop', *verdict(checks))

    def all(self) -> list[Row]:
        rows = self.bit_flip()
        rows += [self.lying_counts(), self.zero_count(), self.encoding('json', 'ros2msg'),
                 self.encoding('cdr', 'x-unknown'), self.no_usable_input('malformed'),
                 self.no_usable_input('nan'), self.report_malformed()]  # fmt: skip
        rows += self.int32_limit()
        rows += [self.params_file('missing'), self.params_file('malformed'),
                 self.symlink_loop()]  # fmt: skip
        return rows


# ----------------------------------------------------------------------------------- main


def guarded(group: str, fn: Callable[[], list[Row]]) -> list[Row]:
    """The rows of ``fn``; an exception of this script (not of the package) is a BROKE row
    saying where, so one broken attack does not hide the others."""
    try:
        return fn()
    except Exception as err:
        import traceback

        where = traceback.extract_tb(err.__traceback__)[-1]
        return [Row(f'{group}: the script itself', 'runs to the end', f'**{type(err).__name__}: '
                    f'{err} (line {where.lineno})**', 'BROKE')]  # fmt: skip


def table(rows: list[Row]) -> str:
    def cell(text: str) -> str:
        return text.replace('|', '\\|').replace('\n', ' ')

    out = ['| # | attack | expectation | observed | result |', '|---|---|---|---|---|']
    out += [f'| {i} | {cell(r.attack)} | {cell(r.expectation)} | {cell(r.observed)} | '
            f'{r.verdict} |' for i, r in enumerate(rows, start=1)]  # fmt: skip
    return '\n'.join(out)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split('\n\n')[0])
    parser.add_argument('--quick', action='store_true', help='shorter feeds and bags')
    parser.add_argument('--domain', type=int, default=77, help='ROS_DOMAIN_ID (default 77)')
    parser.add_argument('--keep', type=Path, help='keep the work files in this folder')
    parser.add_argument('--only', choices=('node', 'files'), help='one group of attacks')
    args = parser.parse_args(argv)
    if not (BIN / 'cloe_inference').exists():
        print(f'ERROR: cloe_inference is not installed next to {sys.executable}; run '
              '`make install`', file=sys.stderr)  # fmt: skip
        return 1
    os.environ['ROS_AUTOMATIC_DISCOVERY_RANGE'] = 'LOCALHOST'
    os.environ.setdefault('AMENT_PREFIX_PATH', str(BIN.parent))
    os.environ.setdefault('MPLBACKEND', 'Agg')
    workdir = Path(tempfile.mkdtemp(prefix='cloe_attacks_')) if args.keep is None else args.keep
    workdir.mkdir(parents=True, exist_ok=True)
    os.environ.setdefault('ROS_LOG_DIR', str(workdir / 'ros_log'))
    import cloe_ros

    started = time.monotonic()
    print(f'cloe_ros {getattr(cloe_ros, "__version__", "?")} from '
          f'{Path(cloe_ros.__file__).parent}; work files in {workdir}', flush=True)  # fmt: skip
    rows: list[Row] = []
    try:
        if args.only in (None, 'node'):
            rows += guarded('node', lambda: NodeAttacks(args.domain, workdir / 'node',
                                                        args.quick).all())  # fmt: skip
            print(f'node attacks done ({time.monotonic() - started:.0f} s)', flush=True)
        if args.only in (None, 'files'):
            (workdir / 'files').mkdir(exist_ok=True)
            rows += guarded('files', lambda: FileAttacks(args.domain, workdir / 'files',
                                                         args.quick).all())  # fmt: skip
    finally:
        if args.keep is None:
            shutil.rmtree(workdir, ignore_errors=True)
    print()
    print(table(rows))
    counts = {v: sum(r.verdict == v for r in rows) for v in ('HELD', 'BROKE', 'n/a')}
    print(f'\n{counts["HELD"]} HELD, {counts["BROKE"]} BROKE, {counts["n/a"]} n/a '
          f'({time.monotonic() - started:.0f} s{", --quick" if args.quick else ""})')
    return 1 if counts['BROKE'] else 0


if __name__ == '__main__':
    raise SystemExit(main())
