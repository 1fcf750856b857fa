"""Speed of the package's hot paths, written as a Markdown table (see EVALUATION.md).

    .venv/bin/python scripts/benchmark.py [--writer]

Measures, on this machine: writing a bag (``BagWriter`` beside the ``mcap`` library's writer; only
that with ``--writer``), one estimator step (core, batched over N vehicles), one engine step
(validation + step + output encoding, as the node does it), the CDR decode/encode of the
contract's messages, and `cloe infer` on the sample bags and on the corpus of real flights, when
it is there (the folder ``CLOE_FLIGHTS`` names, else ``shared/data/flights`` beside the checkout,
as for the tests: test/corpus.py), in ms per flight-second.
"""

from __future__ import annotations

import functools
import os
import platform
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(REPO))

from cloe_ros.core.algorithms import make_estimator  # noqa: E402
from cloe_ros.core.engine import NS, EngineConfig, VehicleEngine  # noqa: E402
from cloe_ros.core.estimator import EstimatorConfig  # noqa: E402
from cloe_ros.core.kinematics import state_to_odometry, yaw_quaternion  # noqa: E402
from cloe_ros.core.samples import OdometrySample, PoseSample  # noqa: E402
from cloe_ros.io import messages  # noqa: E402
from cloe_ros.io.outputs import OutputConfig, OutputEncoder  # noqa: E402
from cloe_ros.threads import limit_blas_threads  # noqa: E402


def best_of(fn, repeat: int = 3) -> float:
    return min(fn() for _ in range(repeat))


def core_step(algorithm: str, n: int, steps: int = 2000) -> float:
    rng = np.random.default_rng(0)
    zeta = np.zeros((n, 12))
    zeta[:, 10] = 1.0
    r = np.tile([0.0, 0.0, 0.0, 1.0], (n, 1))
    est = make_estimator(EstimatorConfig(algorithm), zeta, r, 0.01)
    data = zeta + 0.01 * rng.normal(size=(steps, n, 12))
    refs = r + 0.01 * rng.normal(size=(steps, n, 4))

    def run():
        start = time.perf_counter()
        for k in range(steps):
            est.step(data[k], refs[k], 0.01)
        return (time.perf_counter() - start) / steps

    return best_of(run)


def engine_step(algorithm: str, steps: int = 2000) -> float:
    """Per odometry sample at 100 Hz (reference at 100 Hz): add both, advance, encode."""
    t = np.arange(steps) * 0.01
    zeta = np.zeros((steps, 12))
    zeta[:, 10] = 1.0 + 0.05 * np.sin(2.0 * t)
    zeta[:, 0] = 0.1 * np.sin(1.3 * t)
    samples = []
    for k in range(steps):
        stamp = 10**18 + k * NS // 100
        p, q, v, w = state_to_odometry(zeta[k])
        odom = messages.encode_odometry(OdometrySample(stamp, 'world', 'base', p, q, v, w))
        ref = messages.encode_pose_stamped(
            PoseSample(stamp, 'world', np.array([zeta[k, 0], 0.0, 1.0]), yaw_quaternion(0.0))
        )
        samples.append((odom, ref))

    def run():
        engine = VehicleEngine(EngineConfig(estimator=EstimatorConfig(algorithm)))
        encoder = OutputEncoder(OutputConfig(), '')
        start = time.perf_counter()
        for odom, ref in samples:
            engine.add_odometry(messages.decode_odometry(odom))
            engine.add_reference(messages.decode_pose_stamped(ref))
            for est in engine.advance():
                encoder.encode(est, 'world', 'base')
        return (time.perf_counter() - start) / steps

    return best_of(run, 2)


def codec() -> dict[str, float]:
    p, q, v, w = state_to_odometry(np.zeros(12))
    sample = OdometrySample(1, 'world', 'base', p, q, v, w)
    raw = messages.encode_odometry(sample)
    out = {}
    for name, fn in (
        ('decode Odometry', lambda: messages.decode_odometry(raw)),
        ('encode Odometry', lambda: messages.encode_odometry(sample)),
    ):
        start = time.perf_counter()
        for _ in range(5000):
            fn()
        out[name] = (time.perf_counter() - start) / 5000
    return out


def bag_writing() -> dict[str, float]:
    """Seconds per message of writing the messages of bags/position, twice over, with zstd and
    without: through ``BagWriter`` (cloe_ros/io/mcap_writer.py) and, in the same run, through the
    ``mcap`` library's writer making the same file (the writer the package used before)."""
    from mcap.writer import CompressionType
    from mcap.writer import Writer as LibraryWriter

    from cloe_ros.io.reader import BagReader
    from cloe_ros.io.writer import CHUNK_SIZE, BagWriter

    with BagReader(REPO / 'bags' / 'position') as bag:
        topics = {name: info.msgtype for name, info in bag.topics.items()}
        written = [(t, ns, bytes(raw)) for t, ns, raw in bag.messages(set(topics))] * 2

    def per_message(write, compression: str) -> float:
        """CPU seconds per message of ``write(folder, compression)`` into a new folder."""
        with tempfile.TemporaryDirectory() as tmp:
            start = time.process_time()
            write(Path(tmp), compression)
            return (time.process_time() - start) / len(written)

    def ours(folder: Path, compression: str) -> None:
        with BagWriter(folder / 'bag', compression=compression) as writer:
            for name, msgtype in topics.items():
                writer.add_topic(name, msgtype)
            for topic, ns, raw in written:
                writer.write(topic, ns, raw)

    def library(folder: Path, compression: str) -> None:
        with open(folder / 'bag.mcap', 'wb') as f:
            kind = CompressionType.ZSTD if compression == 'zstd' else CompressionType.NONE
            writer = LibraryWriter(f, chunk_size=CHUNK_SIZE, compression=kind,
                                   enable_crcs=True, enable_data_crcs=True)  # fmt: skip
            writer.start(profile='ros2', library='benchmark')
            channels = {}
            for name, msgtype in topics.items():
                schema = writer.register_schema(msgtype, 'ros2msg', b'')
                channels[name] = writer.register_channel(name, 'cdr', schema, {})
            for topic, ns, raw in written:
                writer.add_message(channels[topic], ns, raw, ns)
            writer.finish()

    out = {}
    for compression in ('zstd', 'none'):
        for who, fn in (('BagWriter', ours), ("the mcap library's writer", library)):
            out[f'{who}, {compression}, {len(written)} messages'] = best_of(
                functools.partial(per_message, fn, compression))
    return out


def infer(bag: Path) -> tuple[float, float]:
    """Median of 3 `cloe infer` runs: (wall s, ms per flight-second as printed)."""
    walls, per = [], []
    for _ in range(3):
        with tempfile.TemporaryDirectory() as tmp:
            start = time.perf_counter()
            out = subprocess.run(
                [sys.executable, '-m', 'cloe_ros.cli.main', 'infer', '-q', str(bag), '-o',
                 f'{tmp}/out'], capture_output=True, text=True, check=True,
                env={**os.environ, 'PYTHONPATH': str(REPO)},
            )  # fmt: skip
            walls.append(time.perf_counter() - start)
            per.append(float(out.stdout.split('(')[-1].split(' ms')[0]))
    return float(np.median(walls)), float(np.median(per))


def main() -> int:
    import argparse

    parser = argparse.ArgumentParser(description=__doc__.split('\n\n')[0])
    parser.add_argument('--writer', action='store_true', help='only the bag writing')
    args = parser.parse_args()
    limit_blas_threads()  # as the nodes and `cloe` do (cloe_ros/threads.py)
    print(f'machine: {platform.processor() or platform.machine()}, {os.cpu_count()} cores, '
          f'Python {platform.python_version()}, numpy {np.__version__}\n')  # fmt: skip
    print('| what | time |')
    print('|---|---|')
    for name, sec in bag_writing().items():
        print(f'| writing a bag, {name} | {1e6 * sec:.1f} us per message (CPU, best of 3) |')
    if args.writer:
        return 0
    for algorithm in ('cloe', 'cloe_sm', 'cloe_iv'):
        for n in (1, 10, 100):
            us = 1e6 * core_step(algorithm, n)
            print(f'| core step, {algorithm}, N = {n} vehicles | {us:.0f} us '
                  f'({us / n:.1f} us per vehicle) |')  # fmt: skip
    for algorithm in ('cloe_sm', 'cloe_iv'):
        us = 1e6 * engine_step(algorithm)
        print(f'| engine per 100 Hz odometry + reference sample, {algorithm} (decode, validate, '
              f'step, encode outputs) | {us:.0f} us |')  # fmt: skip
    for name, sec in codec().items():
        print(f'| {name} (lean CDR, io/cdr.py) | {1e6 * sec:.1f} us |')
    flights = Path(os.environ.get('CLOE_FLIGHTS', REPO.parent / 'shared' / 'data' / 'flights'))
    bags = [REPO / 'bags' / 'position', REPO / 'bags' / 'trajectory']
    bags += sorted(flights.glob('nanobench_*')) if flights.exists() else []
    for bag in bags:
        if bag.exists():
            wall, per = infer(bag)
            print(f'| `cloe infer` {bag.name} (cloe_iv, 100 Hz) | {per:.0f} ms per flight-second '
                  f'({wall:.1f} s wall, median of 3) |')  # fmt: skip
    return 0


if __name__ == '__main__':
    raise SystemExit(main())
