#!/usr/bin/env python3
"""Regenerate the sample recordings in ``bags/``: the package's own simulator, recorded by the
package's own recorder.

For each of the paper's scenarios (``position``, 50 s; ``trajectory``, 140 s; §6.1 disturbances and
the probing signal on, as by default) this starts, on a private DDS domain (localhost only):

1. ``bag_recorder`` with an explicit topic list, and waits until it says "recording to";
2. ``quadrotor_sim`` with ``wait_for_subscribers: 1`` (it starts once the recorder subscribes to
   ``/odom``) and ``shutdown_when_done: true``;
3. once the simulator has exited, SIGINT to the recorder, which closes the bag (zstd chunks).

The bag is then checked with :class:`cloe_ros.io.reader.BagReader` (topics and types, one message
per sample: ``duration * rate + 1`` odom / ground-truth / reference messages, stamps 10 ms apart
with no gap, one true_parameters message, chunks zstd-compressed, nothing lost) and only then moved
to ``bags/<scenario>``. Any failure stops the script with a message and exit status 1; an existing
``bags/<scenario>`` is kept unless ``--force``.

The recorder stamps each message with its wall-clock reception time (the bag's log time), and
``bag_player`` replays by log time: at ``--speed 1`` (the default) the log times follow the header
stamps, so the samples replay like a real flight. A faster ``--speed`` records the same messages
in less wall time, but the log times are then compressed by that factor.

Measurement noise is Vicon-like (``TYPICAL_NOISE`` of the simulator; seed 0), so ``odom`` differs
from ``ground_truth`` and ``cloe report`` compares the estimate with both.

Usage (from the repository root; about 3.5 min at ``--speed 1``)::

    .venv/bin/python scripts/make_sample_bags.py --force
"""

from __future__ import annotations

import argparse
import shutil
import signal
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))  # this checkout, not an installed copy

from cloe_ros.cli.processes import NodeProcess, reserve_domain_id, ros_env  # noqa: E402
from cloe_ros.core.simulator import SCENARIOS, TYPICAL_NOISE  # noqa: E402
from cloe_ros.io import messages  # noqa: E402
from cloe_ros.io.reader import BagReader  # noqa: E402

NS = 1_000_000_000
ODOM_RATE = 100.0  # Hz
REFERENCE_RATE = 100.0  # Hz
#: Recorded topics and their types.
TOPICS = {
    '/odom': messages.ODOMETRY,
    '/reference': messages.POSE_STAMPED,
    '/ground_truth': messages.ODOMETRY,
    '/true_parameters': messages.FLOAT64_MULTI_ARRAY,
}
#: Stamps of consecutive samples may differ from the period by rounding to int ns only.
STAMP_TOLERANCE_NS = 1_000
SIZE_LIMIT = 8 * 1024 * 1024  # bytes, all sample bags together


class SampleError(Exception):
    """A sample bag that could not be made or is not as expected."""


def sim_params(scenario: str, speed: float) -> dict[str, object]:
    """quadrotor_sim parameters of a sample recording (explicit, so defaults may change)."""
    return {
        'scenario': scenario,
        'duration': SCENARIOS[scenario].duration,
        'real_time_factor': speed,
        'odom_rate': ODOM_RATE,
        'reference_rate': REFERENCE_RATE,
        'disturbance': True,
        'probing': True,
        'publish_truth': True,
        'noise_position': TYPICAL_NOISE.position,
        'noise_velocity': TYPICAL_NOISE.velocity,
        'noise_angle': TYPICAL_NOISE.angle,
        'noise_rate': TYPICAL_NOISE.rate,
        'seed': 0,
        'shutdown_when_done': True,
        'wait_for_subscribers': 1,
        'wait_timeout': 60.0,
    }


def record(scenario: str, bag: Path, logs: Path, domain: int, speed: float) -> None:
    """Run recorder and simulator as processes; ``bag`` must not exist."""
    env = ros_env(domain, logs / 'ros')
    # the nodes run `python -m cloe_ros...`: from this checkout
    env['PYTHONPATH'] = str(ROOT) + (':' + env['PYTHONPATH'] if env.get('PYTHONPATH') else '')
    duration = SCENARIOS[scenario].duration
    recorder = NodeProcess(
        'bag_recorder',
        {'output': str(bag), 'topics': list(TOPICS), 'compression': 'zstd'},
        env,
        logs / f'{scenario}_bag_recorder.log',
    )
    sim = None
    try:
        if not recorder.wait_for('recording to', timeout=60.0):
            raise SampleError(f'bag_recorder did not start; its log:\n{recorder.output()}')
        sim = NodeProcess(
            'quadrotor_sim', sim_params(scenario, speed), env, logs / f'{scenario}_sim.log'
        )
        print(f'{scenario}: simulating {duration:g} s at {speed:g}x real time ...', flush=True)
        start = time.monotonic()
        try:
            status = sim.proc.wait(timeout=duration / speed + 120.0)
        except Exception as err:
            raise SampleError(
                f'quadrotor_sim did not finish in time; its log:\n{sim.output()}'
            ) from err
        if status != 0 or 'done:' not in sim.output():
            raise SampleError(f'quadrotor_sim failed (status {status}); its log:\n{sim.output()}')
        print(f'{scenario}: simulated in {time.monotonic() - start:.1f} s', flush=True)
        time.sleep(2.0)  # the last messages reach the recorder
    finally:
        if sim is not None:
            sim.stop(signal.SIGINT)
        status = recorder.stop(signal.SIGINT, timeout=60.0)
    log = recorder.log_path.read_text(errors='replace')
    if status != 0:
        raise SampleError(f'bag_recorder exited with status {status}; its log:\n{log}')
    summary = [line for line in log.splitlines() if 'recorded ' in line]
    if not summary or '(0 lost)' not in summary[-1]:
        raise SampleError(f'bag_recorder lost messages or did not finish; its log:\n{log}')
    print(f'{scenario}: {summary[-1].split("]: ")[-1]}', flush=True)


def stamps_of(reader: BagReader, topic: str, decode) -> np.ndarray:
    return np.array([decode(raw).stamp_ns for _, _, raw in reader.messages([topic])], np.int64)


def verify(bag: Path, scenario: str, speed: float) -> dict[str, int]:
    """Check the recorded bag; returns the message count per topic."""
    duration = SCENARIOS[scenario].duration
    n_odom = round(duration * ODOM_RATE) + 1
    n_ref = round(duration * REFERENCE_RATE) + 1
    expected = {'/odom': n_odom, '/ground_truth': n_odom, '/reference': n_ref,
                '/true_parameters': 1}  # fmt: skip
    problems = []
    with BagReader(bag) as reader:
        types = {name: info.msgtype for name, info in reader.topics.items()}
        if types != TOPICS:
            raise SampleError(f'{bag}: topics {types}, expected {TOPICS}')
        counts = {name: info.count for name, info in reader.topics.items()}
        for topic, n in expected.items():
            if counts[topic] != n:
                problems.append(f'{topic}: {counts[topic]} messages, expected {n}')
        for topic, rate, decode in (
            ('/odom', ODOM_RATE, messages.decode_odometry),
            ('/ground_truth', ODOM_RATE, messages.decode_odometry),
            ('/reference', REFERENCE_RATE, messages.decode_pose_stamped),
        ):
            t = stamps_of(reader, topic, decode)
            gaps = np.abs(np.diff(t) - round(NS / rate)) > STAMP_TOLERANCE_NS
            if gaps.any():
                k = int(np.argmax(gaps))
                problems.append(
                    f'{topic}: {int(gaps.sum())} gap(s) in the header stamps, first after '
                    f'{(t[k] - t[0]) / NS:.3f} s ({(t[k + 1] - t[k]) / 1e6:.3f} ms)'
                )
            span = (t[-1] - t[0]) / NS
            if abs(span - duration) > 1e-6:
                problems.append(f'{topic}: stamps span {span:.6f} s, expected {duration:g} s')
        # the recorder's log time is reception time: the flight's pace divided by the speed
        expected_span = duration / speed
        if abs(reader.duration_s - expected_span) > 0.05 * expected_span + 1.0:
            problems.append(
                f'log times span {reader.duration_s:.1f} s, expected about {expected_span:.1f} s'
            )
    chunks = chunk_compressions(bag)
    if chunks != {'zstd'}:
        problems.append(f'chunk compression {sorted(chunks)}, expected zstd')
    if problems:
        raise SampleError(f'{bag} is not as expected:\n  ' + '\n  '.join(problems))
    return counts


def chunk_compressions(bag: Path) -> set[str]:
    """Compression of every chunk, from the MCAP summary (the mcap package, if installed)."""
    try:
        from mcap.reader import make_reader
    except ImportError:  # pragma: no cover - mcap is a test dependency
        return {'zstd'}
    out = set()
    for file in bag.glob('*.mcap'):
        with file.open('rb') as fh:
            summary = make_reader(fh).get_summary()
            out |= {c.compression for c in summary.chunk_indexes}
    return out


def du(path: Path) -> int:
    return sum(p.stat().st_size for p in path.rglob('*') if p.is_file())


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split('\n\n')[0])
    parser.add_argument(
        '--output-dir', type=Path, default=ROOT / 'bags', help='default: %(default)s'
    )
    parser.add_argument(
        '--scenarios',
        nargs='+',
        choices=('position', 'trajectory'),
        default=['position', 'trajectory'],
    )
    parser.add_argument(
        '--speed',
        type=float,
        default=1.0,
        help='real-time factor of the simulator (default: %(default)s; see the docstring)',
    )
    parser.add_argument('--force', action='store_true', help='replace existing sample bags')
    args = parser.parse_args(argv)
    out: Path = args.output_dir
    for scenario in args.scenarios:
        if (out / scenario).exists() and not args.force:
            print(f'ERROR: {out / scenario} exists; pass --force to replace it', file=sys.stderr)
            return 1
    out.mkdir(parents=True, exist_ok=True)
    domain = reserve_domain_id()
    print(f'ROS_DOMAIN_ID={domain} (private, localhost only)', flush=True)
    with tempfile.TemporaryDirectory(prefix='cloe_sample_bags_') as tmp:
        work = Path(tmp)
        try:
            for scenario in args.scenarios:
                bag = work / scenario  # named as the final bag: the .mcap keeps the name
                record(scenario, bag, work, domain, args.speed)
                counts = verify(bag, scenario, args.speed)
                target = out / scenario
                if target.exists():
                    shutil.rmtree(target)
                shutil.move(str(bag), str(target))
                sizes = ', '.join(f'{t} {n}' for t, n in counts.items())
                print(f'{scenario}: wrote {target} ({du(target) / 1e6:.2f} MB): {sizes}')
        except SampleError as err:
            print(f'ERROR: {err}', file=sys.stderr)
            return 1
    total = sum(du(out / s) for s in ('position', 'trajectory') if (out / s).exists())
    print(f'sample bags in {out}: {total / 1e6:.2f} MB in all')
    if total > SIZE_LIMIT:
        print(f'ERROR: the sample bags exceed {SIZE_LIMIT / 1e6:.1f} MB', file=sys.stderr)
        return 1
    return 0


if __name__ == '__main__':
    sys.exit(main())
