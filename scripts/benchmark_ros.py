"""Real-time behaviour of the nodes on this machine, written as a Markdown table.

    .venv/bin/python scripts/benchmark_ros.py [--repeat N]

These are speeds, which depend on the machine and on how busy it is, so the test suite does not
assert them (it checks what does not depend on speed: every message arrives, on the player's
schedule to within the lateness it reports, log times on /clock ticks). Measured here:

* ``bag_player`` pacing: the sample bag ``bags/position`` played at rate 4 to a subscriber in
  this process; the span of the send times (the middleware's source timestamps) against the
  recorded span / rate, the slope of send time against log time (x rate, 1 = exact), the
  residual of that fit, and the lateness the player reports. (The suite asserted the span and
  the slope to within 10 % before; a loaded machine broke that.)
* ``use_sim_time`` lag: ``quadrotor_sim`` (``publish_clock``, real-time factor 2, 8 s) ->
  ``cloe_inference`` and ``bag_recorder``, both on ``use_sim_time``; how far the recorder's log
  time (the /clock time at reception) trails each message's stamp, for ``/odom`` and
  ``/cloe/state``. (The suite asserted a median of at most 0.1 s for ``/cloe/state`` before: it
  measured 0.15-0.59 s on a loaded machine.)

Each runs on a DDS domain of its own (localhost only), with the package's own
:class:`~cloe_ros.cli.processes.NodeProcess`.
"""

from __future__ import annotations

import argparse
import os
import platform
import signal
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(REPO))

from cloe_ros.cli.processes import NodeProcess, reserve_domain_id, ros_env  # noqa: E402
from cloe_ros.io.reader import BagReader  # noqa: E402

NS = 1_000_000_000
BAG = REPO / 'bags' / 'position'


def start(name: str, params: dict, env: dict, folder: Path, node_name: str | None = None):
    proc = NodeProcess(name, params, env, folder / f'{node_name or name}.log', node_name)
    return proc


def wait_for(proc: NodeProcess, text: str, timeout: float = 120.0) -> None:
    if not proc.wait_for(text, timeout):
        raise RuntimeError(f'{proc.name} did not log {text!r}:\n{proc.output()}')


def player_pacing(folder: Path, rate: float = 4.0) -> dict[str, float]:
    import rclpy
    from geometry_msgs.msg import PoseStamped
    from nav_msgs.msg import Odometry
    from rclpy.executors import SingleThreadedExecutor

    from cloe_ros.ros.common import qos

    with BagReader(BAG) as bag:
        log = {t: [] for t in bag.topics}
        for topic, log_ns, _ in bag.messages():
            log[topic].append(log_ns)
    played = ['/odom', '/reference']
    domain = reserve_domain_id()
    ctx = rclpy.Context()
    rclpy.init(context=ctx, domain_id=domain)
    node = rclpy.create_node('pacing_probe', context=ctx)
    sent: dict[str, list[float]] = {t: [] for t in played}
    for topic, cls in (('/odom', Odometry), ('/reference', PoseStamped)):
        node.create_subscription(
            cls, topic, lambda _, info, t=topic: sent[t].append(info['source_timestamp'] / 1e9),
            qos(depth=20_000), raw=True,
        )  # fmt: skip
    executor = SingleThreadedExecutor(context=ctx)
    executor.add_node(node)
    player = start('bag_player', {
        'bag': str(BAG), 'rate': rate, 'topics': played, 'wait_for_subscribers': 1,
        'qos_depth': 20_000, 'ack_timeout': 60.0,
    }, ros_env(domain, folder / 'ros_log'), folder)  # fmt: skip
    try:
        expected = sum(len(log[t]) for t in played)
        deadline = time.monotonic() + 300.0
        while time.monotonic() < deadline:
            executor.spin_once(timeout_sec=0.05)
            if player.proc.poll() is not None and sum(map(len, sent.values())) >= expected:
                break
        status = player.stop()
    finally:
        executor.shutdown()
        node.destroy_node()
        rclpy.try_shutdown(context=ctx)
    if status != 0:
        raise RuntimeError(f'bag_player exited with status {status}:\n{player.output()}')
    log_s = np.array([t for tp in played for t in log[tp]], dtype=np.int64)
    send = np.array([t for tp in played for t in sent[tp]])
    bag_s = (log_s - log_s.min()) / NS
    slope, intercept = np.polyfit(bag_s, send, 1)
    residual = send - (slope * bag_s + intercept)
    line = next(x for x in player.output().splitlines() if 'done: ' in x)
    return {
        'span_ratio': (send.max() - send.min()) / (bag_s.max() / rate),
        'slope': slope * rate,
        'residual_std_ms': residual.std() * 1e3,
        'residual_max_ms': np.abs(residual).max() * 1e3,
        'reported_max_late_ms': float(line.rsplit('max ', 1)[1].split(' ms')[0]),
    }


def sim_time_lag(folder: Path) -> dict[str, tuple[float, float]]:
    """(median, max) of log time - stamp, s, per topic."""
    from mcap.reader import make_reader
    from mcap_ros2.decoder import DecoderFactory

    domain = reserve_domain_id()
    env = ros_env(domain, folder / 'ros_log')
    bag = folder / 'bag'
    topics = ['/odom', '/reference', '/cloe/state']
    recorder = start('bag_recorder', {
        'output': str(bag), 'topics': topics, 'use_sim_time': True, 'qos_depth': 2000,
    }, env, folder)  # fmt: skip
    inference = start('cloe_inference', {'use_sim_time': True, 'qos_depth': 2000}, env, folder)
    procs = [recorder, inference]
    try:
        wait_for(inference, 'ready:')
        # (the simulator's topics are subscribed once it runs: it waits for both subscribers)
        wait_for(recorder, 'recording /cloe/state (')
        sim = start('quadrotor_sim', {
            'duration': 8.0, 'real_time_factor': 2.0, 'sim_rate': 500.0, 'publish_clock': True,
            'wait_for_subscribers': 2, 'qos_depth': 2000, 'shutdown_when_done': True,
        }, env, folder)  # fmt: skip
        procs.append(sim)
        wait_for(sim, 'done: ')
        sim.wait(60.0)
        time.sleep(2.0)  # the last states reach the recorder (a benchmark may sleep)
    finally:
        for proc in reversed(procs):
            proc.stop(signal.SIGINT)
    (mcap_file,) = bag.glob('*.mcap')
    lags: dict[str, list[float]] = {t: [] for t in topics}
    with mcap_file.open('rb') as fh:
        reader = make_reader(fh, decoder_factories=[DecoderFactory()])
        for _, channel, message, msg in reader.iter_decoded_messages():
            stamp = msg.header.stamp.sec * NS + msg.header.stamp.nanosec
            lags[channel.topic].append((message.log_time - stamp) / NS)
    return {t: (float(np.median(v)), float(np.max(v))) for t, v in lags.items() if v}


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split('\n\n')[0])
    parser.add_argument('--repeat', type=int, default=1, help='runs of each (default: 1)')
    args = parser.parse_args(argv)
    os.environ.setdefault('ROS_LOG_DIR', str(Path(tempfile.gettempdir()) / 'cloe_ros_bench'))
    load = os.getloadavg()[0]
    print(f'machine: {platform.processor() or platform.machine()}, {os.cpu_count()} cores, '
          f'load average {load:.1f}, Python {platform.python_version()}\n')  # fmt: skip
    print('| what | measured |')
    print('|---|---|')
    for run in range(args.repeat):
        with tempfile.TemporaryDirectory() as tmp:
            p = player_pacing(Path(tmp))
        print(f'| bag_player pacing, bags/position at rate 4 (run {run + 1}) | span '
              f'{p["span_ratio"]:.4f} x recorded / rate, slope {p["slope"]:.4f} x 1 / rate, '
              f'residual std {p["residual_std_ms"]:.2f} ms, max {p["residual_max_ms"]:.2f} ms; '
              f'player reports at most {p["reported_max_late_ms"]:.1f} ms late |')  # fmt: skip
        with tempfile.TemporaryDirectory() as tmp:
            lag = sim_time_lag(Path(tmp))
        text = ', '.join(f'{t} median {m:.3f} s, max {x:.3f} s' for t, (m, x) in lag.items())
        print(f'| use_sim_time: recorder log time - stamp (run {run + 1}) | {text} |')
    return 0


if __name__ == '__main__':
    raise SystemExit(main())
