"""What the golden test compares (scripts/golden.py writes it): a bag's published numbers,
computed with the same numeric kernels on every x86-64 machine.

numpy and OpenBLAS pick their kernels by the CPU they run on, and the kernels differ in the last
bit. The identifier carries that up to 3e-8 in ``cloe/parameters`` (5 of the 17 corpus flights,
between OpenBLAS's Haswell and SkylakeX kernels on one machine), more than the test's 1e-9. So the
numbers are computed in a process whose kernels are pinned (:data:`PINNED_KERNELS`), which every
x86-64 CPU that runs numpy 2.4 can run: OpenBLAS's Nehalem kernels, numpy's baseline (x86-64-v2)
loops, and glibc's libm without its AVX2 and FMA variants (these move the numbers by at most
4e-13). Run as ``python -m test.golden_outputs BAG OUT.npz``, it writes :func:`golden_outputs` of
``BAG`` after checking that the pin holds.
"""

from __future__ import annotations

import os
import subprocess
import sys
import tempfile
from pathlib import Path

import numpy as np

from cloe_ros.core.engine import VehicleEngine
from cloe_ros.core.fleet import Fleet
from cloe_ros.io import messages
from cloe_ros.io.config import build_configs
from cloe_ros.io.dataset import feed, input_routes, vehicle_namespaces
from cloe_ros.io.outputs import parameter_vector
from cloe_ros.io.reader import BagReader
from test.corpus import FLIGHTS

REPO = Path(__file__).resolve().parents[1]
GOLDEN = REPO / 'test' / 'golden'
EVERY = 50  # estimates
EVERY_PREDICTION = 5
HORIZON_POSES = np.array([5, 10, 20, 50, 100])  # 0.5, 1, 2, 5, 10 s at the default 0.1 s


PINNED_KERNELS = {
    'OPENBLAS_CORETYPE': 'Nehalem',
    'NPY_ENABLE_CPU_FEATURES': 'X86_V2',  # numpy's baseline; no dispatched loop above it
    'GLIBC_TUNABLES': 'glibc.cpu.hwcaps=-AVX2,-FMA,-AVX512F',
    'OPENBLAS_NUM_THREADS': '1',
}


def bags() -> list[Path]:
    corpus = sorted(FLIGHTS.glob('nanobench_*')) if FLIGHTS.is_dir() else []
    return [REPO / 'bags' / 'position', REPO / 'bags' / 'trajectory', *corpus]


def golden_outputs(bag: Path) -> dict[str, np.ndarray]:
    """Every vehicle's estimates of ``bag`` with the default settings, fed message by message in
    the bag's order as ``cloe infer`` feeds them, stepped by a fleet (arrays keyed ``<what>`` for
    one vehicle)."""
    engine_config, _ = build_configs({})
    with BagReader(bag) as reader:
        topics = {name: info.msgtype for name, info in reader.topics.items()}
        (vehicle,) = vehicle_namespaces(topics)
        # (in a fleet, its estimator a row of a pool, as the node and cloe infer run it)
        fleet = Fleet()
        engine = fleet.add(VehicleEngine(engine_config, name=vehicle))
        route = input_routes(topics, [vehicle])
        estimates = []
        for topic, _, raw in reader.messages(set(route)):
            try:
                feed(engine, route[topic][1], raw)
            except messages.MessageError:
                continue
            estimates.extend(fleet.advance().get(vehicle, []))
        estimates.extend(engine.finish())
    return summarise(estimates)


def pinned_golden_outputs(bag: Path, **env: str) -> dict[str, np.ndarray]:
    """:func:`golden_outputs` of ``bag``, computed in a child process with :data:`PINNED_KERNELS`
    (and ``env``) and the ``cloe_ros`` this process imports; ``kernels_ahead`` says whether it
    ran the kernels built ahead (:mod:`cloe_ros.core.ahead`) or numba's JIT."""
    with tempfile.TemporaryDirectory() as tmp:
        out = Path(tmp) / 'outputs.npz'
        run_golden_process(bag, out, {**PINNED_KERNELS, **env}, check=True)
        with np.load(out) as saved:
            return dict(saved)


def run_golden_process(bag: Path | str, out: Path | str, kernels: dict[str, str] = PINNED_KERNELS,
                       **run_args) -> subprocess.CompletedProcess:
    """Run ``python -m test.golden_outputs BAG OUT`` with ``kernels`` in its environment and the
    ``cloe_ros`` this process imports (``run_args`` go to :func:`subprocess.run`)."""
    import cloe_ros

    paths = [str(REPO), str(Path(cloe_ros.__file__).resolve().parents[1])]
    old = os.environ.get('PYTHONPATH')
    env = {**os.environ, **kernels, 'PYTHONPATH': os.pathsep.join(paths + ([old] if old else []))}
    return subprocess.run([sys.executable, '-m', 'test.golden_outputs', str(bag), str(out)],
                          env=env, cwd=REPO, **run_args)


def run_pinned_script(code: str, *args: str, timeout: float = 600) -> subprocess.CompletedProcess:
    """Run ``python -c code args...`` with :data:`PINNED_KERNELS` in its environment and this
    checkout first on its path, from the checkout; its output captured as text. The scripts
    call the kernels' helpers, which only numba's JIT compiles alone: they run the JIT
    (``CLOE_ROS_KERNELS=jit``), as the suite's own processes do (test/conftest.py)."""
    env = {**os.environ, **PINNED_KERNELS, 'PYTHONPATH': str(REPO), 'CLOE_ROS_KERNELS': 'jit'}
    return subprocess.run([sys.executable, '-c', code, *args], env=env, cwd=REPO,
                          capture_output=True, text=True, timeout=timeout)  # fmt: skip


def check_pinned_kernels() -> None:
    """Raise unless this process runs the pinned kernels: OpenBLAS's Nehalem kernels in every
    OpenBLAS loaded, and no numpy loop dispatched above its baseline."""
    import scipy.linalg  # noqa: F401  (loads scipy's own OpenBLAS)
    from numpy._core._multiarray_umath import __cpu_dispatch__, __cpu_features__
    from threadpoolctl import threadpool_info

    dispatched = [name for name in __cpu_dispatch__ if __cpu_features__.get(name)]
    cores = {info['filepath']: info.get('architecture') for info in threadpool_info()
             if info['internal_api'] == 'openblas'}
    if dispatched or not cores or set(cores.values()) != {PINNED_KERNELS['OPENBLAS_CORETYPE']}:
        raise RuntimeError(f'the kernels are not pinned: numpy dispatches {dispatched}, '
                           f'OpenBLAS runs {cores}')


def summarise(estimates) -> dict[str, np.ndarray]:
    status = 0
    params = []
    for e in estimates:
        if e.prediction is not None or e.prediction_note:
            status = e.prediction_status
        params.append(parameter_vector(e, status))
    params = np.array(params)
    zeta = np.array([e.zeta_hat for e in estimates])
    stamps = np.array([e.stamp_ns for e in estimates], dtype=np.int64)
    pred = [e for e in estimates if e.prediction is not None]
    pick = pred[::EVERY_PREDICTION]
    positions = np.full((len(pick), len(HORIZON_POSES), 3), np.nan)
    radius = np.full((len(pick), len(HORIZON_POSES)), np.nan)
    for i, e in enumerate(pick):
        states = e.prediction[1]
        ok = HORIZON_POSES <= len(states)
        positions[i, ok] = states[HORIZON_POSES[ok] - 1][:, [0, 4, 10]]
        radius[i, ok] = e.prediction_radius[HORIZON_POSES[ok] - 1]
    all_positions = [e.prediction[1][:, [0, 4, 10]] for e in pred]
    return {
        'stamps': stamps[::EVERY],
        'state': zeta[::EVERY],
        'parameters': params[::EVERY],
        'prediction_stamps': np.array([e.stamp_ns for e in pick], dtype=np.int64),
        'prediction_positions': positions,
        'prediction_radius': radius,
        'counts': np.array([len(estimates), len(pred)], dtype=np.int64),
        'state_sum': zeta.sum(axis=0) if len(zeta) else np.zeros(12),
        'parameters_sum': params.sum(axis=0) if len(params) else np.zeros(0),
        'prediction_sum': (np.sum([p.sum(axis=0) for p in all_positions], axis=0)
                           if all_positions else np.zeros(3)),
        'radius_sum': np.array([sum(float(e.prediction_radius.sum()) for e in pred)]),
    }


def compare(golden: dict[str, np.ndarray], got: dict[str, np.ndarray]) -> dict[str, float]:
    """The largest difference per array, relative to the array's scale (1 below), inf where the
    shapes, stamps or counts differ."""
    out = {}
    for key, want in golden.items():
        have = got.get(key)
        if have is None or have.shape != want.shape:
            out[key] = np.inf
        elif want.dtype.kind == 'i':
            out[key] = 0.0 if np.array_equal(have, want) else np.inf
        elif want.size == 0:
            out[key] = 0.0
        elif not np.array_equal(np.isnan(want), np.isnan(have)):
            out[key] = np.inf
        else:
            scale = max(1.0, float(np.nanmax(np.abs(want))))
            out[key] = float(np.nanmax(np.abs(have - want), initial=0.0)) / scale
    return out


if __name__ == '__main__':
    check_pinned_kernels()
    bag, out = map(Path, sys.argv[1:3])
    from cloe_ros.core import ahead

    np.savez(out, **golden_outputs(bag), kernels_ahead=np.array(ahead.MODULE is not None))
