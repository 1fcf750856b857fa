"""What the golden test compares (scripts/golden.py writes it): a bag's published numbers."""

from __future__ import annotations

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
