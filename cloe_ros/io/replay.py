"""A recorded bag through the inference engine, as ``cloe infer`` runs it, for the evaluation.

:func:`replay_flights` feeds every vehicle's ``odom``, ``reference`` (and ``reference_plan``)
messages, decoded by :mod:`cloe_ros.io.messages`, to a :class:`~cloe_ros.core.engine.
VehicleEngine` per vehicle (one :class:`~cloe_ros.core.fleet.Fleet`) in the bag's order, exactly
as ``cloe infer`` and the node do, and keeps
what the corpus evaluation scores (:class:`~cloe_ros.core.evaluation.FlightRecord`): the
published predictions and their radii at the horizons, the state and the trust at each issue
time, and the odometry and references that were received.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from cloe_ros.core.engine import NS, Estimate, VehicleEngine
from cloe_ros.core.evaluation import HORIZONS, FlightRecord
from cloe_ros.core.fleet import Fleet, RecordingBatches
from cloe_ros.io import messages
from cloe_ros.io.config import build_configs
from cloe_ros.io.dataset import ODOM, REFERENCE, feed, input_routes, vehicle_namespaces
from cloe_ros.io.errors import BagError
from cloe_ros.io.reader import BagReader


class _Collector:
    """The arrays of one vehicle's replay."""

    def __init__(self, step: float, horizons: tuple[float, ...]) -> None:
        self.k = [round(h / step) for h in horizons]
        self.odom: list[tuple[int, np.ndarray]] = []
        self.refs: list[tuple[int, np.ndarray]] = []
        self.issue: list[int] = []
        self.state: list[np.ndarray] = []
        self.predicted: list[np.ndarray] = []
        self.radius: list[np.ndarray] = []
        self.tracked: list[np.ndarray] = []

    def take(self, estimates: list[Estimate]) -> None:
        for e in estimates:
            if e.prediction is None:
                continue
            states = e.prediction[1]
            n = len(states)
            pos = np.full((len(self.k), 3), np.nan)
            rad = np.full(len(self.k), np.nan)
            for j, k in enumerate(self.k):
                if 1 <= k <= n:
                    pos[j] = states[k - 1][[0, 4, 10]]
                    rad[j] = e.prediction_radius[k - 1]
            self.issue.append(e.stamp_ns)
            self.state.append(e.measured)
            self.predicted.append(pos)
            self.radius.append(rad)
            self.tracked.append(np.ones(4, bool) if e.trust is None else e.trust.tracked)

    def record(self, name: str, horizons: tuple[float, ...]) -> FlightRecord:
        odom_ns = np.array([s for s, _ in self.odom], dtype=np.int64)
        t0_ns = int(odom_ns[0]) if len(odom_ns) else 0

        def rel(stamps) -> np.ndarray:
            return (np.asarray(stamps, dtype=np.int64) - t0_ns) / NS

        ref_ns = [s for s, _ in self.refs]
        return FlightRecord(
            name=name,
            t0=t0_ns / NS,
            odom_t=rel(odom_ns),
            odom_p=np.array([p for _, p in self.odom]).reshape(-1, 3),
            ref_t=rel(ref_ns),
            ref_p=np.array([p for _, p in self.refs]).reshape(-1, 3),
            issue_t=rel(self.issue),
            state=np.array(self.state).reshape(-1, 12),
            predicted=np.array(self.predicted).reshape(-1, len(horizons), 3),
            radius=np.array(self.radius).reshape(-1, len(horizons)),
            tracked=np.array(self.tracked).reshape(-1, 4),
            horizons=horizons,
        )


def replay_flights(
    path: str | Path, settings: dict | None = None, horizons: tuple[float, ...] = HORIZONS,
    only: list[str] | None = None,
) -> list[FlightRecord]:  # fmt: skip
    """One :class:`FlightRecord` per vehicle of the bag at ``path`` (named by the bag, with the
    namespace when there are several vehicles), inferred with the node's ``settings``; of the
    vehicles ``only`` (namespaces as :func:`bag_vehicles` gives them) if given (each vehicle's
    record is the same whichever vehicles are replayed with it)."""
    path = Path(path)
    engine_config, _ = build_configs(dict(settings or {}))
    if not engine_config.prediction.enabled:
        raise BagError(f'{path}: predictions are off (prediction_horizon 0): nothing to score')
    with BagReader(path) as reader:
        topics = {name: info.msgtype for name, info in reader.topics.items()}
        vehicles = vehicle_namespaces(topics)
        if not vehicles:
            raise BagError(f'{path}: no vehicle with <ns>/{ODOM} and <ns>/{REFERENCE} topics')
        several = len(vehicles) > 1
        if only is not None:
            vehicles = [v for v in vehicles if v in only]
        fleet = Fleet()  # (stepped in batches of one grid step of recording time, as infer)
        engines = {v: fleet.add(VehicleEngine(engine_config, name=v)) for v in vehicles}
        collectors = {v: _Collector(engine_config.prediction.step, horizons) for v in vehicles}
        route = input_routes(topics, vehicles)
        batches = RecordingBatches(fleet, engine_config.step_ns)

        def take(estimates: dict[str, list[Estimate]]) -> None:
            for v, of_vehicle in estimates.items():
                collectors[v].take(of_vehicle)

        for topic, log_ns, raw in reader.messages(set(route)):
            vehicle, kind = route[topic]
            engine, col = engines[vehicle], collectors[vehicle]
            take(batches.before(log_ns))
            try:
                sample, rejected = feed(engine, kind, raw)
            except messages.MessageError:
                continue
            if rejected is None and kind in (ODOM, REFERENCE):
                received = col.odom if kind == ODOM else col.refs
                received.append((sample.stamp_ns, np.asarray(sample.position, float)))
            batches.fed(vehicle, log_ns)
        take(batches.flush())
        for v in vehicles:
            collectors[v].take(engines[v].finish())
    return [
        collectors[v].record(f'{path.name}{v}' if several else path.name, horizons)
        for v in vehicles
    ]


def bag_vehicles(path: str | Path) -> list[str]:
    """The vehicle namespaces of the bag at ``path`` that :func:`replay_flights` replays."""
    with BagReader(Path(path)) as reader:
        return vehicle_namespaces({name: info.msgtype for name, info in reader.topics.items()})
