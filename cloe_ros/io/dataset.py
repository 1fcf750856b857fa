"""A bag as per-vehicle time series: what reports, the demo and the evaluation work on.

For every vehicle namespace with ``odom`` and ``reference`` topics (README, "Interface
contract"): the measured states, the references, and when present the ground truth and true
parameters of a simulation (``ground_truth``, ``true_parameters``) and the outputs of inference
runs (``<output_ns>/state``, ``<output_ns>/parameters``, ``<output_ns>/prediction``) found under
the vehicle's namespace.
"""

from __future__ import annotations

import re
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from cloe_ros.core.kinematics import odometry_to_state, quaternion_yaw, unwrap_near
from cloe_ros.io import messages
from cloe_ros.io.reader import BagError, BagReader

ODOM, REFERENCE, PLAN = 'odom', 'reference', 'reference_plan'
DIAGNOSTICS = '/diagnostics'


@dataclass
class Series:
    """Samples ``values[i]`` at ``t_ns[i]`` (header stamps)."""

    t_ns: np.ndarray
    values: np.ndarray

    def __len__(self) -> int:
        return len(self.t_ns)

    @property
    def t(self) -> np.ndarray:
        """Seconds (float) since the epoch of the stamps."""
        return self.t_ns * 1e-9


@dataclass
class Predictions:
    """Anticipated paths: issue time (P,), per path the stamps (P, K) and positions (P, K, 3);
    paths shorter than K are padded with NaN."""

    t_ns: np.ndarray
    stamps_ns: np.ndarray
    positions: np.ndarray
    flags: list[str] = field(default_factory=list)


@dataclass
class InferenceOutput:
    """One inference run's outputs for a vehicle."""

    name: str
    state: Series | None = None
    parameters: Series | None = None
    labels: list[str] = field(default_factory=list)
    prediction: Predictions | None = None
    algorithm: str | None = None  # from the custom data of `cloe infer`, else /diagnostics

    @property
    def label(self) -> str:
        """How to name this output: its namespace, and the algorithm when that is known and
        differs (``cloe (cloe_iv)``: `cloe infer` writes every algorithm to ``cloe`` by default,
        which is also the name of the paper's algorithm)."""
        if self.algorithm and self.algorithm != self.name:
            return f'{self.name} ({self.algorithm})'
        return self.name


@dataclass
class VehicleData:
    """Everything the bag holds for one vehicle (time series sorted by stamp)."""

    namespace: str
    odom: Series
    reference: Series
    ground_truth: Series | None = None
    true_parameters: np.ndarray | None = None
    outputs: dict[str, InferenceOutput] = field(default_factory=dict)


def vehicle_namespaces(topics: dict[str, str]) -> list[str]:
    """Namespaces with an ``odom`` (Odometry) and a ``reference`` (PoseStamped) topic."""
    out = []
    for name, msgtype in topics.items():
        if name.endswith('/' + ODOM) and msgtype == messages.ODOMETRY:
            ns = name[: -len(ODOM) - 1]
            if topics.get(f'{ns}/{REFERENCE}') == messages.POSE_STAMPED:
                out.append(ns)
    return sorted(out)


def input_routes(topics: dict[str, str], vehicles: list[str]) -> dict[str, tuple[str, str]]:
    """Each input topic of ``vehicles`` in a bag of ``topics`` -> ``(vehicle, ODOM | REFERENCE |
    PLAN)``; a plan only where the bag has one of its type."""
    route = {}
    for v in vehicles:
        route[f'{v}/{ODOM}'] = (v, ODOM)
        route[f'{v}/{REFERENCE}'] = (v, REFERENCE)
        if topics.get(f'{v}/{PLAN}') == messages.PATH:
            route[f'{v}/{PLAN}'] = (v, PLAN)
    return route


def feed(engine, kind: str, raw: bytes):
    """Decode ``raw``, an input of ``kind`` (``ODOM``, ``REFERENCE`` or ``PLAN``), into a sample
    and give it to ``engine`` (a :class:`~cloe_ros.core.engine.VehicleEngine`), as ``cloe infer``
    and the node do: ``(sample, rejection or None)``; malformed bytes raise MessageError."""
    if kind == ODOM:
        sample = messages.decode_odometry(raw)
        return sample, engine.add_odometry(sample)
    if kind == REFERENCE:
        sample = messages.decode_pose_stamped(raw)
        return sample, engine.add_reference(sample)
    sample = messages.decode_path(raw)
    return sample, engine.add_plan(sample)


def states_from_odometry(raws: list[bytes]) -> Series:
    """Model states with continuous yaw from raw Odometry messages."""
    return _states([messages.decode_odometry(r) for r in raws])


def _states(samples: list) -> Series:
    """Model states with continuous yaw from decoded Odometry samples, sorted by stamp."""
    if not samples:
        return Series(np.zeros(0, dtype=np.int64), np.zeros((0, 12)))
    t = np.array([s.stamp_ns for s in samples], dtype=np.int64)
    zeta = odometry_to_state(
        np.array([s.position for s in samples]),
        np.array([s.orientation for s in samples]),
        np.array([s.linear for s in samples]),
        np.array([s.angular for s in samples]),
    )
    order = np.argsort(t, kind='stable')
    t, zeta = t[order], zeta[order]
    zeta[:, 8] = np.unwrap(zeta[:, 8])
    return Series(t, zeta)


def references_from_poses(raws: list[bytes]) -> Series:
    """References ``[x_d, y_d, psi_d, z_d]`` with continuous yaw from raw PoseStamped messages."""
    samples = [messages.decode_pose_stamped(r) for r in raws]
    if not samples:
        return Series(np.zeros(0, dtype=np.int64), np.zeros((0, 4)))
    t = np.array([s.stamp_ns for s in samples], dtype=np.int64)
    p = np.array([s.position for s in samples])
    yaw = quaternion_yaw(np.array([s.orientation for s in samples]))
    r = np.column_stack([p[:, 0], p[:, 1], yaw, p[:, 2]])
    order = np.argsort(t, kind='stable')
    t, r = t[order], r[order]
    r[:, 2] = np.unwrap(r[:, 2])
    return Series(t, r)


def align_yaw(series: Series, like: Series) -> Series:
    """Shift ``series``' continuous yaw by a multiple of 2 pi to sit near ``like``'s."""
    if not len(series) or not len(like):
        return series
    ref = np.interp(series.t_ns[0], like.t_ns, like.values[:, 8 if like.values.shape[1] == 12
                                                             else 2])  # fmt: skip
    col = 8 if series.values.shape[1] == 12 else 2
    values = series.values.copy()
    values[:, col] += unwrap_near(values[0, col], ref) - values[0, col]
    return Series(series.t_ns, values)


def _message_time(
    log_ns: np.ndarray, state_stamps: np.ndarray | None, state_log_ns: list[int] | None
) -> np.ndarray:
    """Message times of an output that has no header (``parameters``: Float64MultiArray).

    Its only time is the bag's log time: the estimate time in bags written by ``cloe infer``, but
    the reception time in recordings, which runs at the wall clock's pace (a simulation at 2x real
    time is recorded in half its duration). The output's ``state`` (Odometry, stamped with the
    estimate time and published at the same steps; ``state_stamps`` in the order of
    ``state_log_ns``) maps one to the other; without it the log time is all there is.
    """
    if state_stamps is None or len(state_stamps) < 2:
        return log_ns
    logs = np.asarray(state_log_ns, dtype=np.int64)
    order = np.argsort(logs, kind='stable')
    logs, stamps = logs[order], state_stamps[order]
    if np.any(np.diff(stamps) < 0):  # not a monotone map: keep the log time
        return log_ns
    base = logs[0]  # interpolate in float64 relative to an origin, keeping ns resolution
    return stamps[0] + np.round(np.interp(log_ns - base, logs - base, stamps - stamps[0])).astype(
        np.int64
    )


def _algorithms_from_diagnostics(raws: list[bytes]) -> dict[tuple[str, str], str]:
    """``(vehicle ns, output ns) -> algorithm`` from recorded ``/diagnostics``: an inference
    node reports both per vehicle (``hardware_id`` its namespace as recorded, '/' for the
    root). The last report wins (an algorithm can be changed at runtime); undecodable messages
    are skipped."""
    found: dict[tuple[str, str], str] = {}
    for raw in raws:
        try:
            _, statuses = messages.decode_diagnostics(raw)
        except Exception:  # any codec failure: a malformed diagnostic must not lose the flight
            continue
        for status in statuses:
            values = dict(status.values)
            if 'algorithm' in values and 'output_ns' in values:
                vehicle = '' if status.hardware_id == '/' else status.hardware_id
                found[(vehicle, values['output_ns'])] = values['algorithm']
    return found


def load_flight(path: str | Path) -> dict[str, VehicleData]:
    """Every vehicle of the bag at ``path``, by namespace ('' for un-namespaced topics).

    Raises :class:`BagError` when the bag cannot be read or holds no odom/reference pair.
    """
    with BagReader(path) as reader:
        topics = {name: info.msgtype for name, info in reader.topics.items()}
        namespaces = vehicle_namespaces(topics)
        if not namespaces:
            found = ', '.join(f'{n} ({t})' for n, t in sorted(topics.items())) or 'no topics'
            msg = (
                f'{path}: no vehicle found: expected <ns>/odom (nav_msgs/msg/Odometry) and '
                f'<ns>/reference (geometry_msgs/msg/PoseStamped); the bag has {found}'
            )
            raise BagError(msg)
        wanted: dict[str, list[bytes]] = {}
        log_times: dict[str, list[int]] = {}
        patterns = []
        for ns in namespaces:
            for suffix in (ODOM, REFERENCE, 'ground_truth', 'true_parameters'):
                wanted[f'{ns}/{suffix}'] = []
            patterns.append(
                (ns, re.compile(rf'^{re.escape(ns)}/(.+)/(state|parameters|prediction)$'))
            )
        outputs: set[tuple[str, str, str]] = set()  # (vehicle ns, output ns, kind)
        for name in topics:
            for ns, pattern in patterns:
                m = pattern.match(name)
                if m and m.group(1) not in (ODOM, REFERENCE):
                    outputs.add((ns, m.group(1), m.group(2)))
                    wanted[name] = []
        custom = dict(reader.custom_data)
        if topics.get(DIAGNOSTICS) == messages.DIAGNOSTIC_ARRAY:
            wanted[DIAGNOSTICS] = []
        for topic, log_ns, raw in reader.messages([t for t in wanted if t in topics]):
            wanted[topic].append(bytes(raw))
            log_times.setdefault(topic, []).append(log_ns)

    producers = _algorithms_from_diagnostics(wanted.get(DIAGNOSTICS, []))
    vehicles = {}
    for ns in namespaces:
        odom = states_from_odometry(wanted[f'{ns}/{ODOM}'])
        data = VehicleData(ns, odom, references_from_poses(wanted[f'{ns}/{REFERENCE}']))
        if wanted.get(f'{ns}/ground_truth') and topics[f'{ns}/ground_truth'] == messages.ODOMETRY:
            data.ground_truth = align_yaw(states_from_odometry(wanted[f'{ns}/ground_truth']), odom)
        if wanted.get(f'{ns}/true_parameters'):
            _, values = messages.decode_float64_multi_array(wanted[f'{ns}/true_parameters'][-1])
            data.true_parameters = values
        # each output's state first: its stamps place the parameters (see _message_time)
        state_stamps: dict[str, np.ndarray] = {}
        for vns, out_ns, kind in sorted(outputs, key=lambda o: (o[:2], o[2] != 'state')):
            if vns != ns:
                continue
            raws = wanted[f'{ns}/{out_ns}/{kind}']
            algorithm = custom.get(f'cloe_ros.{out_ns}.algorithm',
                                   producers.get((ns, out_ns)))  # fmt: skip
            out = data.outputs.setdefault(out_ns, InferenceOutput(out_ns, algorithm=algorithm))
            if kind == 'state' and topics[f'{ns}/{out_ns}/state'] == messages.ODOMETRY:
                samples = [messages.decode_odometry(r) for r in raws]
                state_stamps[out_ns] = np.array([m.stamp_ns for m in samples], dtype=np.int64)
                out.state = align_yaw(_states(samples), odom)
            elif kind == 'parameters' and raws:
                decoded = [messages.decode_float64_multi_array(r) for r in raws]
                out.labels = decoded[-1][0]
                t = _message_time(
                    np.array(log_times[f'{ns}/{out_ns}/parameters'], dtype=np.int64),
                    state_stamps.get(out_ns),
                    log_times.get(f'{ns}/{out_ns}/state'),
                )
                out.parameters = Series(t, np.array([d[1] for d in decoded]))
            elif kind == 'prediction' and raws and topics[f'{ns}/{out_ns}/prediction'] == (
                    messages.PATH):  # fmt: skip
                out.prediction = _predictions(raws)
        vehicles[ns] = data
    return vehicles


def _predictions(raws: list[bytes]) -> Predictions:
    paths = [messages.decode_path(r) for r in raws]
    k = max(len(p.stamps_ns) for p in paths)
    stamps = np.full((len(paths), k), -1, dtype=np.int64)
    positions = np.full((len(paths), k, 3), np.nan)
    for i, p in enumerate(paths):
        stamps[i, : len(p.stamps_ns)] = p.stamps_ns
        positions[i, : len(p.stamps_ns)] = p.positions
    return Predictions(np.array([p.stamp_ns for p in paths], dtype=np.int64), stamps, positions)
