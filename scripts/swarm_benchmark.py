"""Swarm load on one inference node, as a ratio to a do-nothing subscriber under the same load.

    .venv/bin/python scripts/swarm_benchmark.py --vehicles 10 100 --duration 20 [--batch-period S]

For each N: one process publishes N vehicles' ``/uavK/odom`` at 100 Hz and ``/uavK/reference`` at
10 Hz (a circle, raw CDR, stamped with the wall clock; each tick's messages computed for all
vehicles at once, so that the load generator takes little of the machine). It is received first by
a do-nothing subscriber (raw subscriptions on rclpy's EventsExecutor: the floor of receiving them
in Python), then by one ``cloe_inference`` node (this checkout's package, cloe_iv, ``vehicles``
listing them, ``reference_timeout`` 5 s instead of the default 0.25 s, as in every run of
EVALUATION.md; ``--param NAME:=VALUE``, repeatable, sets another of its parameters, these two
included). A node that exits (a parameter it refuses) stops the benchmark with its error. Printed
per run: messages received of those sent, CPU time of the receiving process per message sent (from
/proc; every receiver's is divided by the messages sent, the same load, so that one that misses
messages does not look cheaper), and for the node the share of the odometry that became a published
``cloe/state`` and the latency of the states of every vehicle (wall clock at reception minus stamp,
p50 and p99, over all the states received; until 2026-12-06 it was the first vehicle's alone, which
the node steps and publishes first of a batch), and what the node says of its load in /diagnostics:
how many reports it published (with ``--shards``, the sum over the shards), the largest ``busy``
(the share of wall time in its callbacks; WARN from 0.8) and the largest ``late_s`` (how long after
its deadline its steady timer ran; WARN from 0.5 s) and the largest ``longest_callback_s`` (its
longest single callback, which every input arriving meanwhile waits for). Speeds depend on the
machine and its load: compare the node's column with the floor's in the same run (EVALUATION.md,
section 4). Uses ROS_DOMAIN_ID 91 unless one is set. ``--shards K`` splits the vehicles over K
nodes (``shard_index`` / ``shard_count``, each its own process, as across hosts): the node's
columns are then the K nodes together (CPU and reports summed, the largest ``busy``, ``late_s``
and ``longest_callback_s`` of any).
``--relay`` also runs, under the same load, a node that only receives and publishes each odometry
message back as the vehicle's ``cloe/state`` (no estimation): what an inference node whose engine
cost nothing would deliver, and its CPU per message; then that relay publishing the node's other
outputs too (parameters, named parameters, prediction, its radius and markers, real bytes at the
default rates): what the node's output contract alone costs on DDS.

    .venv/bin/python scripts/swarm_benchmark.py --offline bags/position [--repeat 3]

``cloe infer --jobs 1`` on a bag beside the I/O floor: reading, decoding and rewriting the same
bag with rosbags (AnyReader, deserialize, serialize, Writer), CPU seconds of each, median of the
repeats. ``--jobs 1`` because the target is one vehicle in one process: by default ``cloe infer``
splits a bag of several vehicles over processes, which costs CPU of its own. The checkout's
modules are compiled to bytecode first, as ``pip install`` compiles an installed package's: in a
shell with ``PYTHONDONTWRITEBYTECODE`` set, each run would otherwise compile them all from source
(0.2 s of CPU), which a user's ``cloe infer`` never does.
"""

from __future__ import annotations

import argparse
import math
import os
import pickle
import struct
import subprocess
import sys
import time
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
CLK_TCK = os.sysconf('SC_CLK_TCK')


def cpu_seconds(pid: int) -> float:
    fields = Path(f'/proc/{pid}/stat').read_text().rsplit(')', 1)[1].split()
    return (int(fields[11]) + int(fields[12])) / CLK_TCK


def publish(n: int, duration: float) -> None:
    """The load: N vehicles, odometry 100 Hz, reference 10 Hz, for ``duration`` s. The
    messages of a tick are computed for all vehicles at once and their bytes assembled from a
    fixed head, so that the load generator takes little of the machine the node runs on."""
    import numpy as np
    import rclpy
    from geometry_msgs.msg import PoseStamped
    from nav_msgs.msg import Odometry

    from cloe_ros.core.kinematics import state_to_odometry
    from cloe_ros.io import cdr
    from cloe_ros.ros.common import qos

    rclpy.init()
    node = rclpy.create_node('swarm_load')
    odom = [node.create_publisher(Odometry, f'/uav{k}/odom', qos(depth=100)) for k in range(n)]
    ref = [node.create_publisher(PoseStamped, f'/uav{k}/reference', qos(depth=100))
           for k in range(n)]  # fmt: skip
    deadline = time.monotonic() + 30.0
    while time.monotonic() < deadline and min(p.get_subscription_count() for p in odom) == 0:
        rclpy.spin_once(node, timeout_sec=0.05)
    time.sleep(1.0)  # let every subscription match
    frames = cdr._odometry_frames('world', 'base_link')
    pose_frame = cdr.encode_pose_stamped(cdr.PoseSample(0, 'world', np.zeros(3),
                                                        np.array([0.0, 0.0, 0.0, 1.0])))
    phase = 2 * np.pi * np.arange(n) / max(n, 1)
    w = 0.5
    zeta = np.zeros((n, 12))
    zeta[:, 0] = 2 * np.arange(n)
    zeta[:, 10] = 1.0
    values = np.zeros((n, 85))
    start = time.monotonic()
    tick = 0
    sent = 0
    while (t := tick * 0.01) < duration:
        delay = start + t - time.monotonic()
        if delay > 0:
            time.sleep(delay)
        stamp = time.time_ns()
        zeta[:, 0] = 2 * np.arange(n) + np.cos(w * t + phase)
        zeta[:, 1] = -w * np.sin(w * t + phase)
        zeta[:, 4], zeta[:, 5] = np.sin(w * t + phase), w * np.cos(w * t + phase)
        p, q, v, a = state_to_odometry(zeta)
        values[:, 0:3], values[:, 3:7], values[:, 43:46], values[:, 46:49] = p, q, v, a
        head = cdr.LITTLE + cdr._time_bytes(stamp) + frames
        for k in range(n):
            odom[k].publish(head + values[k].tobytes())
        sent += n
        if tick % 10 == 0:
            pose = np.zeros((n, 7))
            pose[:, 0:3], pose[:, 6] = p, 1.0
            for k in range(n):  # (the pose's doubles are the message's last 56 bytes)
                ref[k].publish(cdr.LITTLE + cdr._time_bytes(stamp) + pose_frame[12:-56]
                               + pose[k].tobytes())  # fmt: skip
            sent += n
        tick += 1
    print(f'sent {sent}', flush=True)
    time.sleep(2.0)  # (let the last messages be delivered)
    node.destroy_node()
    rclpy.shutdown()


def _serve(node, duration: float, count: list[int]) -> None:
    """Spin ``node`` on an EventsExecutor until the run is done (``SWARM_DONE`` exists, or
    ``duration`` + 40 s), print how many messages ``count`` counted, and shut rclpy down."""
    import rclpy
    from rclpy.experimental import EventsExecutor

    from cloe_ros.ros.common import spin_while

    executor = EventsExecutor()
    executor.add_node(node)
    end = time.monotonic() + duration + 40.0
    spin_while(executor, lambda: time.monotonic() < end
               and not Path(os.environ['SWARM_DONE']).exists(), period=0.1)  # fmt: skip
    print(f'received {count[0]}', flush=True)
    node.destroy_node()
    rclpy.shutdown()


def floor(n: int, duration: float) -> None:
    """The do-nothing subscriber: counts what it receives, prints the count at the end."""
    import rclpy
    from geometry_msgs.msg import PoseStamped
    from nav_msgs.msg import Odometry

    from cloe_ros.ros.common import qos

    rclpy.init()
    node = rclpy.create_node('swarm_floor')
    count = [0]

    def callback(_raw: bytes) -> None:
        count[0] += 1

    subs = [node.create_subscription(Odometry, f'/uav{k}/odom', callback, qos(depth=100),
                                     raw=True) for k in range(n)]  # fmt: skip
    subs += [node.create_subscription(PoseStamped, f'/uav{k}/reference', callback,
                                      qos(depth=100), raw=True) for k in range(n)]  # fmt: skip
    _serve(node, duration, count)


def relay(n: int, duration: float, outputs: Path | None = None) -> None:
    """The least an inference node does on DDS: per odometry message received, one Odometry
    published on the vehicle's ``cloe/state`` (the received bytes, so the stamp is the
    odometry's); the references are received and dropped. No estimation: what receiving and
    publishing cost, and how late the states come, with an engine that costs nothing.

    ``outputs`` (a file of :func:`_output_samples`' messages, pickled): the relay also keeps
    the node's other topics and their rates, at the defaults. It subscribes to ``reference_plan``
    as well, and publishes, beside each state, the node's ``parameters`` and
    ``parameters_named`` every 10th odometry message (``parameters_rate`` 10 Hz) and its
    ``prediction``, ``prediction_radius`` and ``prediction_markers`` every 20th
    (``prediction_rate`` 5 Hz), reliable as the node's: the bytes the node's encoder gives for a
    real estimate, as they are. What any node that keeps the output contract pays on DDS, whatever
    its engine costs. (/diagnostics, once a second, is left out.)"""
    import rclpy
    from geometry_msgs.msg import PoseStamped
    from nav_msgs.msg import Odometry
    from nav_msgs.msg import Path as PathMsg

    from cloe_ros.ros.common import qos
    from cloe_ros.ros.inference_node import OUTPUT_TYPES

    rclpy.init()
    node = rclpy.create_node('swarm_relay')
    count = [0]
    samples = pickle.loads(outputs.read_bytes()) if outputs else {}
    every = {'parameters': 10, 'parameters_named': 10, 'prediction': 20,
             'prediction_radius': 20, 'prediction_markers': 20}  # fmt: skip

    def forward(pub, others: list):
        seen = [0]  # (every vehicle on the same ticks, as the node's defaults have it)

        def callback(raw: bytes) -> None:
            count[0] += 1
            pub.publish(raw)
            seen[0] += 1
            for period, other, data in others:
                if seen[0] % period == 0:
                    other.publish(data)

        return callback

    def drop(_raw: bytes) -> None:
        count[0] += 1

    for k in range(n):
        pub = node.create_publisher(Odometry, f'/uav{k}/cloe/state', qos(depth=100))
        others = [(every[name], node.create_publisher(OUTPUT_TYPES[msgtype],
                                                      f'/uav{k}/cloe/{name}', qos(depth=100)),
                   data) for name, (msgtype, data) in samples.items()]  # fmt: skip
        node.create_subscription(Odometry, f'/uav{k}/odom', forward(pub, others),
                                 qos(depth=1000), raw=True)  # fmt: skip
        node.create_subscription(PoseStamped, f'/uav{k}/reference', drop, qos(depth=1000),
                                 raw=True)  # fmt: skip
        if outputs:
            node.create_subscription(PathMsg, f'/uav{k}/reference_plan', drop,
                                     qos(depth=1000), raw=True)  # fmt: skip
    _serve(node, duration, count)


def _output_samples() -> dict[str, tuple[str, bytes]]:
    """The node's outputs other than the state, one message of each (output name -> (message
    type, CDR)), as its encoder gives them for an estimate of the simulated position flight that
    holds a prediction (default settings)."""
    sys.path.insert(0, str(REPO))
    from cloe_ros.core.engine import VehicleEngine
    from cloe_ros.io.config import DEFAULTS, build_configs
    from cloe_ros.io.outputs import OutputEncoder
    from test.core.test_engine import in_time_order, simulated_flight
    from test.core.test_engine import messages as flight_messages

    engine_config, output_config = build_configs(dict(DEFAULTS))
    engine = VehicleEngine(engine_config, name='/uav0')
    encoder = OutputEncoder(output_config, '/uav0', engine_config.prediction.enabled)
    types = encoder.topics
    found: dict[str, tuple[str, bytes]] = {}
    for kind, message in in_time_order(*flight_messages(simulated_flight())):
        if kind == 'odom':
            engine.add_odometry(message)
        else:
            engine.add_reference(message)
        for estimate in engine.advance():
            for topic, _stamp, data in encoder.encode(estimate, 'world', 'base_link'):
                name = topic.rsplit('/', 1)[1]
                if name not in ('state', 'parameter_labels'):
                    found[name] = (types[topic], data)
        if len(found) == 5:
            return found
    raise RuntimeError(f'the simulated flight gave only these outputs: {sorted(found)}')


def listen(n: int, watch: str) -> None:
    """Counts the node's states of every vehicle and their latency (reception minus stamp, every
    vehicle's); the node's own ``busy`` share from its /diagnostics."""
    import numpy as np
    import rclpy
    from diagnostic_msgs.msg import DiagnosticArray
    from nav_msgs.msg import Odometry
    from rclpy.experimental import EventsExecutor

    from cloe_ros.io.messages import decode_diagnostics
    from cloe_ros.ros.common import qos, spin_while

    rclpy.init()
    node = rclpy.create_node('swarm_listener')
    count = [0]
    lat: list[float] = []

    stamp = struct.Struct('<iI')  # header.stamp, after the 4-byte CDR header

    def state(raw: bytes) -> None:
        now = time.time_ns()
        count[0] += 1
        sec, nanosec = stamp.unpack_from(raw, 4)
        lat.append((now - (sec * 1_000_000_000 + nanosec)) / 1e9)

    busy: list[float] = []
    late: list[float] = []
    longest: list[float] = []

    def diagnostics(raw: bytes) -> None:
        for status in decode_diagnostics(raw)[1]:
            values = dict(status.values)
            if status.name.startswith('cloe_inference') and 'busy' in values:  # (a node's own)
                busy.append(float(values['busy']))
                late.append(float(values['late_s']))
                longest.append(float(values['longest_callback_s']))

    node.create_subscription(DiagnosticArray, '/diagnostics', diagnostics, qos(depth=100),
                             raw=True)  # fmt: skip

    for k in range(n):
        node.create_subscription(Odometry, f'/uav{k}/cloe/state', state, qos(depth=1000),
                                 raw=True)  # fmt: skip
    executor = EventsExecutor()
    executor.add_node(node)
    spin_while(executor, lambda: not Path(watch).exists(), period=0.1)
    end = time.monotonic() + 3.0
    spin_while(executor, lambda: time.monotonic() < end, period=0.1)
    p50, p99 = (np.percentile(lat, [50, 99]) if lat else (math.nan, math.nan))
    # (the largest of the reports: those before the load, and the last, are of an idle node)
    print(f'states {count[0]} latency_p50 {p50:.4f} latency_p99 {p99:.4f} '
          f'busy {max(busy, default=0.0):.3f} late {max(late, default=0.0):.3f} '
          f'reports {len(busy)} longest {max(longest, default=0.0):.3f}',
          flush=True)  # fmt: skip
    node.destroy_node()
    rclpy.shutdown()


def run(n: int, duration: float, receiver: str, tmp: Path, params: list[str] = (),
        shards: int = 1) -> dict[str, float]:  # fmt: skip
    """One load of ``n`` vehicles received by ``receiver`` (floor, relay or node; the node with
    the parameters ``params``, ``NAME:=VALUE`` each, in ``shards`` processes)."""
    env = {**os.environ, 'PYTHONPATH': str(REPO)}
    env.setdefault('ROS_DOMAIN_ID', '91')
    env.setdefault('ROS_AUTOMATIC_DISCOVERY_RANGE', 'LOCALHOST')
    done = tmp / f'done-{receiver}-{n}'
    env['SWARM_DONE'] = str(done)
    me = [sys.executable, __file__]
    procs = {}
    errors = {}  # per node (shard): its stderr, to say why it stopped if it did
    if receiver == 'floor':
        procs['rx'] = subprocess.Popen([*me, '_floor', str(n), str(duration)], env=env,
                                       stdout=subprocess.PIPE, text=True)  # fmt: skip
    else:
        vehicles = '[' + ','.join(f"'/uav{k}'" for k in range(n)) + ']'
        procs['listen'] = subprocess.Popen([*me, '_listen', str(n), str(done)], env=env,
                                           stdout=subprocess.PIPE, text=True)  # fmt: skip
    if receiver in ('relay', 'relay_outputs'):
        samples = []
        if receiver == 'relay_outputs':  # (computed here, so as not to count in its CPU time)
            samples = [str(tmp / 'outputs.pickle')]
            Path(samples[0]).write_bytes(pickle.dumps(_output_samples()))
        procs['rx'] = subprocess.Popen([*me, f'_{receiver}', str(n), str(duration), *samples],
                                       env=env, stdout=subprocess.PIPE, text=True)  # fmt: skip
    elif receiver == 'node':
        for k in range(shards):  # (one node, or one per shard: each its own process)
            shard = (['-p', f'shard_index:={k}', '-p', f'shard_count:={shards}', '-r',
                      f'__node:=cloe_inference_{k}'] if shards > 1 else [])  # fmt: skip
            errors[k] = (tmp / f'node{k}.err').open('w+')
            procs[f'rx{k}'] = subprocess.Popen(
                [sys.executable, '-m', 'cloe_ros.ros.inference_node', '--ros-args', '-p',
                 f'vehicles:={vehicles}', '-p', 'algorithm:=cloe_iv', '-p',
                 'reference_timeout:=5.0', *shard,
                 *(word for param in params for word in ('-p', param))],
                env=env, stdout=subprocess.DEVNULL, stderr=errors[k])  # fmt: skip
    receivers = [p for name, p in procs.items() if name.startswith('rx')]
    time.sleep(3.0)  # (discovery)
    _check_running(procs, errors)
    cpu0 = sum(cpu_seconds(p.pid) for p in receivers)
    pub = subprocess.Popen([*me, '_publish', str(n), str(duration)], env=env,
                           stdout=subprocess.PIPE, text=True)  # fmt: skip
    out, _ = pub.communicate()
    sent = int(out.split()[-1])
    time.sleep(2.0)
    _check_running(procs, errors)
    cpu = sum(cpu_seconds(p.pid) for p in receivers) - cpu0
    done.touch()
    result = {'sent': sent, 'cpu_s': cpu}
    if receiver == 'floor':
        result['received'] = int(procs['rx'].communicate()[0].split()[-1])
    else:
        words = procs['listen'].communicate()[0].split()
        result.update(states=int(words[1]), p50=float(words[3]), p99=float(words[5]),
                      busy=float(words[7]), late=float(words[9]),
                      reports=int(words[11]), longest=float(words[13]))  # fmt: skip
        if receiver != 'node':
            procs['rx'].communicate()
        for p in receivers:
            p.terminate()
        for p in receivers:
            p.wait(30)
    for err in errors.values():
        err.close()
    return result


def _check_running(procs: dict, errors: dict) -> None:
    """Stop the benchmark, with the node's own words, if a node has exited (a parameter it
    refused, say): its row would otherwise read as a node that published nothing."""
    for k, err in errors.items():
        proc = procs[f'rx{k}']
        if proc.poll() is not None:
            for p in procs.values():
                if p.poll() is None:
                    p.kill()
            err.seek(0)
            lines = err.read().strip().splitlines()[-5:]
            raise SystemExit(f'the inference node (shard {k}) exited with status '
                             f'{proc.returncode}:\n' + '\n'.join(lines))  # fmt: skip


def io_floor(bag: Path, out: Path) -> None:
    """Read, decode, re-encode and write every message of ``bag`` with rosbags."""
    from rosbags.highlevel import AnyReader
    from rosbags.rosbag2 import StoragePlugin, Writer
    from rosbags.typesys import Stores, get_typestore

    store = get_typestore(Stores.ROS2_JAZZY)
    with AnyReader([bag], default_typestore=store) as reader:
        with Writer(out, version=9, storage_plugin=StoragePlugin.MCAP) as writer:
            conns = {c.id: writer.add_connection(c.topic, c.msgtype, typestore=store)
                     for c in reader.connections}  # fmt: skip
            for conn, stamp, raw in reader.messages():
                msg = reader.deserialize(raw, conn.msgtype)
                writer.write(conns[conn.id], stamp, store.serialize_cdr(msg, conn.msgtype))


def offline(bag: Path, repeat: int) -> None:
    import compileall
    import statistics
    import tempfile

    compileall.compile_dir(REPO / 'cloe_ros', quiet=1)  # (the bytecode an installed package has)
    env = {**os.environ, 'PYTHONPATH': str(REPO)}
    floor_s, infer_s = [], []
    for k in range(repeat):
        with tempfile.TemporaryDirectory() as tmp:
            for what, times in (('_io_floor', floor_s), ('infer', infer_s)):
                out = Path(tmp) / f'{what}{k}'
                cmd = ([sys.executable, __file__, '_io_floor', str(bag), str(out)]
                       if what == '_io_floor'
                       else [sys.executable, '-m', 'cloe_ros.cli.main', 'infer', '-q', str(bag),
                             '-o', str(out), '--jobs', '1'])  # fmt: skip
                before = os.times()
                subprocess.run(cmd, env=env, check=True, capture_output=True)
                after = os.times()
                times.append(after.children_user + after.children_system
                             - before.children_user - before.children_system)  # fmt: skip
    f, i = statistics.median(floor_s), statistics.median(infer_s)
    print(
        f'| `cloe infer --jobs 1` {bag.name} | I/O floor (rosbags read, decode, encode, write) '
        f'{f:.2f} s CPU | cloe infer {i:.2f} s CPU | {i / f:.1f}x |'
    )


def main() -> int:
    if len(sys.argv) > 1 and sys.argv[1].startswith('_'):
        {'_publish': lambda: publish(int(sys.argv[2]), float(sys.argv[3])),
         '_floor': lambda: floor(int(sys.argv[2]), float(sys.argv[3])),
         '_relay': lambda: relay(int(sys.argv[2]), float(sys.argv[3])),
         '_relay_outputs': lambda: relay(int(sys.argv[2]), float(sys.argv[3]),
                                         Path(sys.argv[4])),
         '_listen': lambda: listen(int(sys.argv[2]), sys.argv[3]),
         '_io_floor': lambda: io_floor(Path(sys.argv[2]), Path(sys.argv[3]))}[sys.argv[1]]()
        return 0
    parser = argparse.ArgumentParser(description=__doc__.split('\n\n')[0])
    parser.add_argument('--vehicles', type=int, nargs='+', default=[10, 100])
    parser.add_argument('--duration', type=float, default=20.0)
    parser.add_argument('--offline', type=Path, metavar='BAG',
                        help='instead: cloe infer on BAG beside the I/O floor')
    parser.add_argument(
        '--repeat',
        type=int,
        default=3,
        help='with --offline: runs of each, the median printed (default: 3)',
    )
    parser.add_argument('--batch-period', type=float, default=None,
                        help="the node's batch_period, s (default: the node's default)")
    parser.add_argument('--qos-depth', type=int, default=None,
                        help="the node's qos_depth, the history of its subscriptions (default: "
                             "the node's default)")  # fmt: skip
    parser.add_argument('--qos-reliability', choices=('reliable', 'best_effort'), default=None,
                        help="the node's qos_reliability, of its subscriptions (default: the "
                             "node's default; the publisher offers reliable either way)")
    parser.add_argument('--shards', type=int, default=1,
                        help='split the vehicles over this many inference nodes (shard_index / '
                             'shard_count), each its own process; CPU is their sum')  # fmt: skip
    parser.add_argument('--param', action='append', default=[], metavar='NAME:=VALUE',
                        help="another of the node's parameters (repeatable), e.g. "
                             "prediction_rate:=1.0")  # fmt: skip
    parser.add_argument('--relay', action='store_true',
                        help='also run, under the same load, the relay (receive, publish one '
                             'state per odometry, no estimation: what an engine that costs '
                             'nothing would deliver on this machine) and the relay with the '
                             "node's other outputs at their default rates (what keeping the "
                             'output contract costs on DDS)')  # fmt: skip
    args = parser.parse_args()
    if args.shards < 1:
        parser.error(f'--shards must be at least 1, got {args.shards}')
    if args.repeat < 1:
        parser.error(f'--repeat must be at least 1, got {args.repeat}')
    if args.offline and not args.offline.exists():
        parser.error(f'--offline {args.offline} does not exist')
    if args.offline:
        offline(args.offline, args.repeat)
        return 0
    import tempfile

    # the node's parameters: those with options of their own, then --param's
    params = [f'{name}:={value}' for name, value in (
        ('batch_period', args.batch_period), ('qos_depth', args.qos_depth),
        ('qos_reliability', args.qos_reliability)) if value is not None] + args.param  # fmt: skip
    reports = 'reports (summed over the shards)' if args.shards > 1 else 'reports'
    print(
        '| vehicles | do-nothing subscriber: received, CPU per message sent | cloe_inference: '
        'states of odometry, CPU per message sent, ratio to the floor, latency p50 / p99 | '
        f"the node's /diagnostics: {reports}, busy (max), late_s (max), longest_callback_s (max) |"
    )
    print('|---|---|---|---|')
    with tempfile.TemporaryDirectory() as tmp:
        for n in args.vehicles:
            f = run(n, args.duration, 'floor', Path(tmp))
            floor_us = 1e6 * f['cpu_s'] / f['sent']  # (per message sent, as the node's)
            odom = round(args.duration * 100) * n
            for relay_kind, what in (('relay', 'relay: no estimation'),
                                     ('relay_outputs', "relay with the node's outputs: no "
                                                       'estimation')) if args.relay else ():
                r = run(n, args.duration, relay_kind, Path(tmp))
                relay_us = 1e6 * r['cpu_s'] / r['sent']
                print(f"| {n} ({what}) | {f['received']} of {f['sent']}, "
                      f"{floor_us:.0f} us | {r['states']} of {odom} "
                      f"({100 * r['states'] / odom:.1f} %), {relay_us:.0f} us, "
                      f"{relay_us / floor_us:.1f}x, {1e3 * r['p50']:.0f} / "
                      f"{1e3 * r['p99']:.0f} ms | |", flush=True)  # fmt: skip
            c = run(n, args.duration, 'node', Path(tmp), params, args.shards)
            node_us = 1e6 * c['cpu_s'] / c['sent']
            print(f"| {n} | {f['received']} of {f['sent']}, {floor_us:.0f} us | "
                  f"{c['states']} of {odom} ({100 * c['states'] / odom:.1f} %), {node_us:.0f} us, "
                  f"{node_us / floor_us:.1f}x, {1e3 * c['p50']:.0f} / {1e3 * c['p99']:.0f} ms | "
                  f"{c['reports']}, {c['busy']:.2f}, {c['late']:.1f} s, "
                  f"{1e3 * c['longest']:.0f} ms |",
                  flush=True)  # fmt: skip
    return 0


if __name__ == '__main__':
    sys.exit(main())
