"""Bags of simulated flights for tests, written without ROS, as the ``quadrotor_sim`` node would.

:func:`write_sim_bag` simulates a scenario with :class:`QuadrotorSimulator` and writes the samples
as a rosbag2/MCAP bag in the layout of the interface contract (README): ``<ns>/odom`` (noisy),
``<ns>/reference``, ``<ns>/ground_truth`` (noise-free) and ``<ns>/true_parameters`` (labels
``theta.<name>``).
"""

from __future__ import annotations

import errno
import io
import os
from collections.abc import Iterable, Sequence
from pathlib import Path

import numpy as np

from cloe_ros.core.kinematics import state_to_odometry, yaw_quaternion
from cloe_ros.core.model import PARAMETER_NAMES
from cloe_ros.core.samples import OdometrySample, PathSample, PoseSample
from cloe_ros.core.simulator import (
    SCENARIOS,
    TYPICAL_NOISE,
    PaperDisturbance,
    QuadrotorSimulator,
    SimulationResult,
)
from cloe_ros.io import messages
from cloe_ros.io.reader import BagReader
from cloe_ros.io.writer import BagWriter

NS = 1_000_000_000
#: Stamp of the simulation's t = 0 (an arbitrary wall-clock-like epoch).
ORIGIN_NS = 1_700_000_000 * NS


def simulate(
    duration: float = 15.0, scenario: str = 'position', seed: int = 0
) -> SimulationResult:
    """The scenario with the paper's disturbances and Vicon-like noise, 2 ms RK4 steps."""
    sim = QuadrotorSimulator(
        SCENARIOS[scenario],
        disturbance=PaperDisturbance(),
        noise=TYPICAL_NOISE,
        dt=2e-3,
        rng=np.random.default_rng(seed),
    )
    return sim.run(duration)


def _odometry(stamp: int, zeta: np.ndarray) -> bytes:
    position, quaternion, v_body, w_body = state_to_odometry(zeta)
    return messages.encode_odometry(
        OdometrySample(stamp, 'world', 'base_link', position, quaternion, v_body, w_body)
    )


def stamps(result: SimulationResult) -> np.ndarray:
    """Header stamps (ns) of the simulation's samples."""
    return ORIGIN_NS + np.round(result.t * NS).astype(np.int64)


def write_sim_bag(
    path: Path,
    result: SimulationResult | None = None,
    namespaces: Sequence[str] = ('',),
    odom_rate: float = 100.0,
    ref_rate: float = 50.0,
    truth: bool = True,
) -> Path:
    """Write ``result`` (a 15 s position-control flight by default) as a bag at ``path``, the
    i-th vehicle of the simulation under ``namespaces[i]`` (the first one for all when the
    simulation has a single vehicle)."""
    result = simulate() if result is None else result
    dt = float(result.t[1] - result.t[0])
    odom_every = max(1, round(1.0 / (odom_rate * dt)))
    ref_every = max(1, round(1.0 / (ref_rate * dt)))
    t_ns = stamps(result)
    labels = [f'theta.{n}' for n in PARAMETER_NAMES]
    with BagWriter(path) as writer:
        for ns in namespaces:
            writer.add_topic(f'{ns}/odom', messages.ODOMETRY)
            writer.add_topic(f'{ns}/reference', messages.POSE_STAMPED)
            if truth:
                writer.add_topic(f'{ns}/ground_truth', messages.ODOMETRY)
                writer.add_topic(f'{ns}/true_parameters', messages.FLOAT64_MULTI_ARRAY)
                writer.write(
                    f'{ns}/true_parameters',
                    int(t_ns[0]),
                    messages.encode_float64_multi_array(labels, result.theta_true),
                )
        for k, stamp in enumerate(t_ns):
            stamp = int(stamp)
            for i, ns in enumerate(namespaces):
                v = min(i, result.zeta.shape[1] - 1)
                if k % odom_every == 0:
                    writer.write(f'{ns}/odom', stamp, _odometry(stamp, result.measured[k, v]))
                    if truth:
                        writer.write(
                            f'{ns}/ground_truth', stamp, _odometry(stamp, result.zeta[k, v])
                        )
                if k % ref_every == 0:
                    r = result.reference[k, v]
                    pose = PoseSample(
                        stamp, 'world', np.array([r[0], r[1], r[3]]), yaw_quaternion(r[2])
                    )
                    writer.write(f'{ns}/reference', stamp, messages.encode_pose_stamped(pose))
    return path


def oracle_predictions(
    result: SimulationResult, every_s: float = 0.5, step_s: float = 0.1, horizon_s: float = 5.0
) -> list[tuple[int, bytes]]:
    """``nav_msgs/Path`` messages (log time, CDR) predicting the true future positions exactly:
    issued every ``every_s``, poses every ``step_s`` up to ``horizon_s`` (cut at the end)."""
    t_ns = stamps(result)
    position = result.zeta[:, 0][:, [0, 4, 10]]
    dt = float(result.t[1] - result.t[0])
    out = []
    for i in range(0, len(t_ns), max(1, round(every_s / dt))):
        ks = i + np.arange(0, round(horizon_s / dt) + 1, max(1, round(step_s / dt)))
        ks = ks[ks < len(t_ns)]
        path = PathSample(
            int(t_ns[i]),
            'world',
            t_ns[ks],
            position[ks],
            np.tile([0.0, 0.0, 0.0, 1.0], (len(ks), 1)),
        )
        out.append((int(t_ns[i]), messages.encode_path(path)))
    return out


def copy_bag(
    source: Path, target: Path, extra: Iterable[tuple[str, str, list[tuple[int, bytes]]]] = ()
) -> Path:
    """Copy every message of ``source`` (and its metadata's ``custom_data``) into a new bag
    ``target``, adding ``extra`` topics given as ``(name, msgtype, [(log_time_ns, cdr), ...])``
    (one the source has too replaces the source's)."""
    records: list[tuple[int, str, bytes]] = []
    replaced = {name for name, _, _ in extra}
    with BagReader(source) as reader, BagWriter(target) as writer:
        for key, value in reader.custom_data.items():
            writer.set_custom_data(key, value)
        kept = [name for name in reader.topics if name not in replaced]
        for name in kept:
            writer.add_topic(name, reader.topics[name].msgtype)
        for name, msgtype, msgs in extra:
            writer.add_topic(name, msgtype)
            records += [(t, name, raw) for t, raw in msgs]
        records += [(t, topic, bytes(raw)) for topic, t, raw in reader.messages(kept)]
        for t, topic, raw in sorted(records, key=lambda r: r[0]):
            writer.write(topic, t, raw)
    return target


def read_topics(bag: Path, names: Iterable[str]) -> list[tuple[str, str, list[tuple[int, bytes]]]]:
    """``(name, msgtype, [(log_time_ns, cdr), ...])`` of the named topics of ``bag``, for
    :func:`copy_bag`'s ``extra``."""
    with BagReader(bag) as reader:
        wanted = [n for n in names if n in reader.topics]
        msgs: dict[str, list[tuple[int, bytes]]] = {n: [] for n in wanted}
        for topic, t, raw in reader.messages(wanted):
            msgs[topic].append((t, bytes(raw)))
        return [(n, reader.topics[n].msgtype, msgs[n]) for n in wanted]


def flip_inside_compressed_chunk(mcap_file: Path, chunk: int = 1) -> tuple[int, int]:
    """Flip one bit inside the zstd data of the ``chunk``-th chunk (file order) so that the data
    still decompress to records of the same layout and size, one message's bytes changed: damage
    only a CRC can tell. Returns ``(chunk offset, offset of the flipped byte)``; the chunk and its
    records are found with the mcap library, the data's place from the specification's layout."""
    import zstandard
    from mcap.reader import make_reader
    from mcap.records import Chunk, Message
    from mcap.stream_reader import breakup_chunk

    with mcap_file.open('rb') as fh:
        index = sorted(
            make_reader(fh).get_summary().chunk_indexes, key=lambda c: c.chunk_start_offset
        )[chunk]
    assert index.compression == 'zstd'
    content = bytearray(mcap_file.read_bytes())
    # opcode, length; start, end, uncompressed size, crc; compression name; data length
    start = index.chunk_start_offset + 9 + 28 + 4 + len(index.compression) + 8
    data = bytes(content[start : start + index.compressed_size])

    def records(raw: bytes) -> list:
        head = Chunk('', raw, 0, 0, 0, len(raw))
        return [(type(r), getattr(r, 'channel_id', None), getattr(r, 'log_time', None),
                 len(getattr(r, 'data', b''))) for r in breakup_chunk(head)]  # fmt: skip

    original = zstandard.ZstdDecompressor().decompress(data)
    layout = records(original)
    for at in range(len(data) // 2, len(data)):
        for bit in (0x01, 0x10, 0x80):
            flipped = bytearray(data)
            flipped[at] ^= bit
            try:
                out = zstandard.ZstdDecompressor().decompress(bytes(flipped))
            except zstandard.ZstdError:
                continue
            if len(out) != len(original) or out == original:
                continue
            try:
                if records(out) != layout:
                    continue
            except Exception:
                continue
            assert any(t is Message for t, *_ in layout)
            content[start + at] ^= bit
            mcap_file.write_bytes(bytes(content))
            return index.chunk_start_offset, start + at
    raise AssertionError('no bit flip found that leaves the chunk decompressible')


class _SmallDisk(io.FileIO):
    """A file on a disk with ``room`` bytes left: writes beyond fail with ENOSPC, as on a full
    disk (a partial write first, then the error)."""

    room = 1 << 40

    def write(self, data) -> int:
        free = self.room - self.tell()
        if free <= 0:
            raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC))
        return super().write(memoryview(data)[:free])


def fill_disk_under(monkeypatch, directory: Path, room: int) -> None:
    """``.mcap`` files opened under ``directory`` (with ``Path.open``, as BagWriter does) get
    ``room`` bytes before writes fail with ENOSPC."""
    path_open = Path.open
    directory = Path(directory)

    def small_disk_open(self, mode='r', *args, **kwargs):
        if self.suffix != '.mcap' or directory not in self.parents or 'r' in mode:
            return path_open(self, mode, *args, **kwargs)
        raw = _SmallDisk(self, mode.replace('b', ''))
        raw.room = room
        return io.BufferedWriter(raw)

    monkeypatch.setattr(Path, 'open', small_disk_open)


def run_on_small_disk(mountpoint: Path, size: str, *cloe_args: str) -> tuple[int, str, str, str]:
    """``cloe *cloe_args`` (this source tree's) with a tmpfs of ``size`` (e.g. ``64k``) mounted at
    ``mountpoint`` in a mount namespace of its own (``unshare -rm``): a real full disk. Returns
    (status, stdout, stderr, what is left on the disk); skips the test where such a namespace
    cannot be made."""
    import shutil
    import subprocess
    import sys

    import pytest

    if shutil.which('unshare') is None:
        pytest.skip('no unshare: cannot mount a small disk')
    mountpoint.mkdir(exist_ok=True)
    script = (
        'mnt="$1"; shift; mount -t tmpfs -o size="$1" tmpfs "$mnt" || exit 99; shift; '
        '"$@"; rc=$?; echo "LEFT:$(ls -A "$mnt")" >&2; exit $rc'
    )
    root = Path(__file__).resolve().parents[1]
    env = dict(os.environ, PYTHONPATH=str(root))
    command = [sys.executable, '-m', 'cloe_ros.cli.main', *cloe_args]
    proc = subprocess.run(
        ['unshare', '-rm', 'sh', '-c', script, 'sh', str(mountpoint), size, *command],
        capture_output=True, text=True, env=env, timeout=300,
    )  # fmt: skip
    if proc.returncode == 99 or 'LEFT:' not in proc.stderr:
        pytest.skip(f'cannot mount a tmpfs in a private namespace: {proc.stderr.strip()}')
    err, _, left = proc.stderr.rpartition('LEFT:')
    return proc.returncode, proc.stdout, err, left.strip()
