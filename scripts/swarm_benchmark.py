"""Swarm load on one inference node, as a ratio to a do-nothing subscriber under the same load.

    .venv/bin/python scripts/swarm_benchmark.py --vehicles 10 100 --duration 20 [--batch-period S]

For each N: one process publishes N vehicles' ``/uavK/odom`` at 100 Hz and ``/uavK/reference`` at
10 Hz (a circle, raw CDR, stamped with the wall clock). It is received first by a do-nothing
subscriber (raw subscriptions on rclpy's EventsExecutor: the floor of receiving them in Python),
then by one ``cloe_inference`` node (the installed package, cloe_iv, ``vehicles`` listing them).
Printed per run: messages received of those sent, CPU time of the receiving process per message
(from /proc), and for the node the share of the odometry that became a published ``cloe/state``
and the latency of the states of the first vehicle (wall clock at reception minus stamp, p50 and
p99), and what the node says of its load in /diagnostics: how many reports it published, the
largest ``busy`` (the share of wall time in its callbacks; WARN from 0.8) and the largest
``late_s`` (how long after its deadline its steady timer ran; WARN from 0.5 s). Speeds depend
on the machine and its load: compare the node's column with the floor's in the same run
(EVALUATION.md, section 4). Uses ROS_DOMAIN_ID 91 unless one is set.

    .venv/bin/python scripts/swarm_benchmark.py --offline bags/position [--repeat 3]

``cloe infer`` on a bag beside the I/O floor: reading, decoding and rewriting the same bag with
rosbags (AnyReader, deserialize, serialize, Writer), CPU seconds of each, median of the repeats.
"""

from __future__ import annotations

import argparse
import math
import os
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
    """The load: N vehicles, odometry 100 Hz, reference 10 Hz, for ``duration`` s."""
    import numpy as np
    import rclpy
    from geometry_msgs.msg import PoseStamped
    from nav_msgs.msg import Odometry

    from cloe_ros.core.kinematics import state_to_odometry_one, yaw_quaternion
    from cloe_ros.core.samples import OdometrySample, PoseSample
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
    start = time.monotonic()
    tick = 0
    sent = 0
    while (t := tick * 0.01) < duration:
        now = start + t
        delay = now - time.monotonic()
        if delay > 0:
            time.sleep(delay)
        stamp = time.time_ns()
        for k in range(n):
            phase = 2 * math.pi * k / max(n, 1)
            w = 0.5
            zeta = np.zeros(12)
            zeta[0], zeta[1] = 2 * k + math.cos(w * t + phase), -w * math.sin(w * t + phase)
            zeta[4], zeta[5] = math.sin(w * t + phase), w * math.cos(w * t + phase)
            zeta[10] = 1.0
            p, q, v, a = state_to_odometry_one(zeta)
            odom[k].publish(cdr.encode_odometry(OdometrySample(stamp, 'world', 'base_link',
                                                               p, q, v, a)))  # fmt: skip
            sent += 1
            if tick % 10 == 0:
                ref[k].publish(cdr.encode_pose_stamped(PoseSample(
                    stamp, 'world', p.copy(), yaw_quaternion(0.0))))  # fmt: skip
                sent += 1
        tick += 1
    print(f'sent {sent}', flush=True)
    time.sleep(2.0)  # (let the last messages be delivered)
    node.destroy_node()
    rclpy.shutdown()


def floor(n: int, duration: float) -> None:
    """The do-nothing subscriber: counts what it receives, prints the count at the end."""
    import rclpy
    from geometry_msgs.msg import PoseStamped
    from nav_msgs.msg import Odometry
    from rclpy.experimental import EventsExecutor

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
    executor = EventsExecutor()
    executor.add_node(node)
    end = time.monotonic() + duration + 40.0
    while time.monotonic() < end and not Path(os.environ['SWARM_DONE']).exists():
        executor.spin_once(timeout_sec=0.1)
    print(f'received {count[0]}', flush=True)
    node.destroy_node()
    rclpy.shutdown()


def listen(n: int, watch: str) -> None:
    """Counts the node's states of every vehicle; latency of the first vehicle's; the node's
    own ``busy`` share from its /diagnostics."""
    import numpy as np
    import rclpy
    from diagnostic_msgs.msg import DiagnosticArray
    from nav_msgs.msg import Odometry
    from rclpy.experimental import EventsExecutor

    from cloe_ros.io import cdr
    from cloe_ros.io.messages import decode_diagnostics
    from cloe_ros.ros.common import qos

    rclpy.init()
    node = rclpy.create_node('swarm_listener')
    count = [0]
    lat: list[float] = []

    def first(raw: bytes) -> None:
        count[0] += 1
        lat.append((time.time_ns() - cdr.decode_odometry(raw).stamp_ns) / 1e9)

    def other(_raw: bytes) -> None:
        count[0] += 1

    busy: list[float] = []
    late: list[float] = []

    def diagnostics(raw: bytes) -> None:
        for status in decode_diagnostics(raw)[1]:
            if status.name == 'cloe_inference':
                values = dict(status.values)
                busy.append(float(values['busy']))
                late.append(float(values['late_s']))

    node.create_subscription(DiagnosticArray, '/diagnostics', diagnostics, qos(depth=100),
                             raw=True)  # fmt: skip

    for k in range(n):
        node.create_subscription(Odometry, f'/uav{k}/cloe/state', first if k == 0 else other,
                                 qos(depth=1000), raw=True)  # fmt: skip
    executor = EventsExecutor()
    executor.add_node(node)
    while not Path(watch).exists():
        executor.spin_once(timeout_sec=0.1)
    end = time.monotonic() + 3.0
    while time.monotonic() < end:
        executor.spin_once(timeout_sec=0.1)
    p50, p99 = (np.percentile(lat, [50, 99]) if lat else (math.nan, math.nan))
    # (the largest of the reports: those before the load, and the last, are of an idle node)
    print(f'states {count[0]} latency_p50 {p50:.4f} latency_p99 {p99:.4f} '
          f'busy {max(busy, default=0.0):.3f} late {max(late, default=0.0):.3f} '
          f'reports {len(busy)}', flush=True)  # fmt: skip
    node.destroy_node()
    rclpy.shutdown()


def run(n: int, duration: float, receiver: str, tmp: Path, batch: float | None = None,
        qos_depth: int | None = None) -> dict[str, float]:  # fmt: skip
    env = {**os.environ, 'PYTHONPATH': str(REPO)}
    env.setdefault('ROS_DOMAIN_ID', '91')
    env.setdefault('ROS_AUTOMATIC_DISCOVERY_RANGE', 'LOCALHOST')
    done = tmp / f'done-{receiver}-{n}'
    env['SWARM_DONE'] = str(done)
    me = [sys.executable, __file__]
    procs = {}
    if receiver == 'floor':
        procs['rx'] = subprocess.Popen([*me, '_floor', str(n), str(duration)], env=env,
                                       stdout=subprocess.PIPE, text=True)  # fmt: skip
    else:
        vehicles = '[' + ','.join(f"'/uav{k}'" for k in range(n)) + ']'
        procs['listen'] = subprocess.Popen([*me, '_listen', str(n), str(done)], env=env,
                                           stdout=subprocess.PIPE, text=True)  # fmt: skip
        procs['rx'] = subprocess.Popen(
            [sys.executable, '-m', 'cloe_ros.ros.inference_node', '--ros-args', '-p',
             f'vehicles:={vehicles}', '-p', 'algorithm:=cloe_iv', '-p', 'reference_timeout:=5.0',
             *(['-p', f'batch_period:={batch}'] if batch is not None else []),
             *(['-p', f'qos_depth:={qos_depth}'] if qos_depth is not None else [])],
            env=env, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)  # fmt: skip
    time.sleep(3.0)  # (discovery)
    cpu0 = cpu_seconds(procs['rx'].pid)
    pub = subprocess.Popen([*me, '_publish', str(n), str(duration)], env=env,
                           stdout=subprocess.PIPE, text=True)  # fmt: skip
    out, _ = pub.communicate()
    sent = int(out.split()[-1])
    time.sleep(2.0)
    cpu = cpu_seconds(procs['rx'].pid) - cpu0
    done.touch()
    result = {'sent': sent, 'cpu_s': cpu}
    if receiver == 'floor':
        result['received'] = int(procs['rx'].communicate()[0].split()[-1])
    else:
        words = procs['listen'].communicate()[0].split()
        result.update(states=int(words[1]), p50=float(words[3]), p99=float(words[5]),
                      busy=float(words[7]), late=float(words[9]),
                      reports=int(words[11]))  # fmt: skip
        procs['rx'].terminate()
        procs['rx'].wait(30)
    return result


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
    import statistics
    import tempfile

    env = {**os.environ, 'PYTHONPATH': str(REPO)}
    floor_s, infer_s = [], []
    for k in range(repeat):
        with tempfile.TemporaryDirectory() as tmp:
            for what, times in (('_io_floor', floor_s), ('infer', infer_s)):
                out = Path(tmp) / f'{what}{k}'
                cmd = ([sys.executable, __file__, '_io_floor', str(bag), str(out)]
                       if what == '_io_floor'
                       else [sys.executable, '-m', 'cloe_ros.cli.main', 'infer', '-q', str(bag),
                             '-o', str(out)])  # fmt: skip
                before = os.times()
                subprocess.run(cmd, env=env, check=True, capture_output=True)
                after = os.times()
                times.append(after.children_user + after.children_system
                             - before.children_user - before.children_system)  # fmt: skip
    f, i = statistics.median(floor_s), statistics.median(infer_s)
    print(f'| `cloe infer` {bag.name} | I/O floor (rosbags read, decode, encode, write) '
          f'{f:.2f} s CPU | cloe infer {i:.2f} s CPU | {i / f:.1f}x |')


def main() -> int:
    if len(sys.argv) > 1 and sys.argv[1].startswith('_'):
        {'_publish': lambda: publish(int(sys.argv[2]), float(sys.argv[3])),
         '_floor': lambda: floor(int(sys.argv[2]), float(sys.argv[3])),
         '_listen': lambda: listen(int(sys.argv[2]), sys.argv[3]),
         '_io_floor': lambda: io_floor(Path(sys.argv[2]), Path(sys.argv[3]))}[sys.argv[1]]()
        return 0
    parser = argparse.ArgumentParser(description=__doc__.split('\n\n')[0])
    parser.add_argument('--vehicles', type=int, nargs='+', default=[10, 100])
    parser.add_argument('--duration', type=float, default=20.0)
    parser.add_argument('--offline', type=Path, metavar='BAG',
                        help='instead: cloe infer on BAG beside the I/O floor')
    parser.add_argument('--repeat', type=int, default=3)
    parser.add_argument('--batch-period', type=float, default=None,
                        help="the node's batch_period, s (default: the node's default)")
    parser.add_argument('--qos-depth', type=int, default=None,
                        help="the node's qos_depth, the history of its subscriptions (default: "
                             "the node's default)")  # fmt: skip
    args = parser.parse_args()
    if args.offline:
        offline(args.offline, args.repeat)
        return 0
    import tempfile

    print('| vehicles | do-nothing subscriber: received, CPU per message | cloe_inference: '
          'states of odometry, CPU per message, ratio to the floor, latency p50 / p99 | '
          "the node's /diagnostics: reports, busy (max), late_s (max) |")
    print('|---|---|---|---|')
    with tempfile.TemporaryDirectory() as tmp:
        for n in args.vehicles:
            f = run(n, args.duration, 'floor', Path(tmp))
            c = run(n, args.duration, 'node', Path(tmp), args.batch_period, args.qos_depth)
            odom = round(args.duration * 100) * n
            floor_us = 1e6 * f['cpu_s'] / max(f['received'], 1)
            node_us = 1e6 * c['cpu_s'] / c['sent']
            print(f"| {n} | {f['received']} of {f['sent']}, {floor_us:.0f} us | "
                  f"{c['states']} of {odom} ({100 * c['states'] / odom:.0f} %), {node_us:.0f} us, "
                  f"{node_us / floor_us:.1f}x, {1e3 * c['p50']:.0f} / {1e3 * c['p99']:.0f} ms | "
                  f"{c['reports']}, {c['busy']:.2f}, {c['late']:.1f} s |",
                  flush=True)  # fmt: skip
    return 0


if __name__ == '__main__':
    sys.exit(main())
