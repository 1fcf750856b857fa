"""Estimates -> output messages of the interface contract, shared by the node and ``cloe infer``.

Both call :meth:`OutputEncoder.encode` on the same sequence of estimates, so they emit the same
messages with the same stamps: ``<ns>/<output_ns>/state`` at every step, ``<ns>/<output_ns>/
parameters`` whenever the estimate time crosses a multiple of the parameter period (message time),
with the same values named, ``<ns>/<output_ns>/parameters_named`` (rcl_interfaces/ParameterEvent,
for viewers that pick values by name), ``<ns>/<output_ns>/parameter_labels`` once (std_msgs/String,
the labels as JSON; latched), and, whenever the engine attached an anticipated path,
``<ns>/<output_ns>/prediction``, its 95 % radii ``<ns>/<output_ns>/prediction_radius`` and the
markers that draw both ``<ns>/<output_ns>/prediction_markers``.
"""

from __future__ import annotations

import json
from dataclasses import dataclass

import numpy as np

from cloe_ros.core import kernels
from cloe_ros.core.anticipation import CHANNELS
from cloe_ros.core.engine import NS, Estimate
from cloe_ros.core.identifier import ROW_NAMES
from cloe_ros.core.kinematics import euler_to_quaternion
from cloe_ros.core.model import COUPLED_BLOCKS, PARAMETER_NAMES, STATE_NAMES
from cloe_ros.core.samples import PathSample
from cloe_ros.errors import ConfigError
from cloe_ros.io.cdr import encode_odometry_values
from cloe_ros.io.errors import OutputConfigError
from cloe_ros.io.messages import (
    FLOAT64_MULTI_ARRAY,
    MARKER_ARRAY,
    ODOMETRY,
    PARAMETER_EVENT,
    PATH,
    STRING,
    encode_float64_multi_array,
    encode_multi_array,
    encode_named_values,
    encode_path,
    encode_prediction_markers,
    encode_string,
)
from cloe_ros.settings import check_fields, default

#: Labels of ``cloe/parameters``: ``layout.dim[i].label`` names ``data[i]``. Theta_hat (16),
#: L (12), the tilt couplings (2), then per identified row its excitation, relative uncertainty
#: and status (0 not identifiable, 1 converging, 2 identified; -1 when the algorithm does not
#: measure them), the status of the last prediction (0 withheld, 1 provisional, 2 identified), and
#: the model the observer runs on and the predictions integrate (``model.theta.*`` (16),
#: ``model.coupling.*`` (2); see :attr:`~cloe_ros.core.engine.Estimate.model`), and whether the
#: vehicle tracks each reference channel (``reference.tracked.*``: 1 tracked, 0 not tracked, -1
#: not decided yet; see :mod:`cloe_ros.core.anticipation`).
PARAMETER_LABELS: tuple[str, ...] = tuple(
    [f'theta_hat.{name}' for name in PARAMETER_NAMES]
    + [f'L.{name}' for name in STATE_NAMES]
    + [f'coupling.{b.name}' for b in COUPLED_BLOCKS]
    + [f'excitation.{row}' for row in ROW_NAMES]
    + [f'uncertainty.{row}' for row in ROW_NAMES]
    + [f'status.{row}' for row in ROW_NAMES]
    + ['prediction.status']
    + [f'model.theta.{name}' for name in PARAMETER_NAMES]
    + [f'model.coupling.{b.name}' for b in COUPLED_BLOCKS]
    + [f'reference.tracked.{c}' for c in CHANNELS]
)
#: Layout of ``<output_ns>/prediction_radius``: one row per pose of the prediction of the same
#: stamp, holding the pose's stamp (s since the epoch) and its 95 % radius (m).
RADIUS_COLUMNS = 'stamp_s,radius_m'
#: QoS of the latched ``<output_ns>/parameter_labels`` (as a bag's offered_qos_profiles entry):
#: reliable, transient local, depth 1, so a viewer that connects later still gets it.
LATCHED_QOS = {
    'history': 'keep_last', 'depth': 1, 'reliability': 'reliable',
    'durability': 'transient_local', 'deadline': {'sec': 0, 'nsec': 0},
    'lifespan': {'sec': 0, 'nsec': 0}, 'liveliness': 'automatic',
    'liveliness_lease_duration': {'sec': 0, 'nsec': 0}, 'avoid_ros_namespace_conventions': False,
}  # fmt: skip


def parameter_labels_text() -> str:
    """``<output_ns>/parameter_labels``: ``PARAMETER_LABELS`` as a JSON array, in the order of
    ``parameters``' ``data`` (``data[i]`` is named by element ``i``)."""
    return json.dumps(list(PARAMETER_LABELS))


def join_topic(*parts: str) -> str:
    """Join namespace parts into a topic name (relative if the first part is)."""
    text = '/'.join(p.strip('/') for p in parts if p and p.strip('/'))
    return ('/' if parts and parts[0].startswith('/') else '') + text


@dataclass(frozen=True)
class OutputConfig:
    """What is published for each vehicle.

    Attributes:
        output_ns: Namespace of the outputs under the vehicle's (``cloe`` in the contract).
        parameters_rate: ``parameters`` messages per second of message time, Hz.

    """

    output_ns: str = default('output_ns')
    parameters_rate: float = default('parameters_rate')

    def __post_init__(self) -> None:
        try:
            check_fields(self, 'output')  # defaults and ranges: cloe_ros.settings
        except OutputConfigError:
            raise
        except ConfigError as err:
            raise OutputConfigError(err.reason, err.name) from err
        ns = self.output_ns.strip('/')
        if not ns or any(not (c.isalnum() or c in '_/') for c in ns):
            msg = f'{self.output_ns!r} is not a valid namespace'
            raise OutputConfigError(msg, 'output_ns')


class OutputEncoder:
    """Turns one vehicle's estimates into ``(topic, stamp_ns, cdr)`` records."""

    def __init__(self, config: OutputConfig, vehicle: str = '', predictions: bool = True) -> None:
        self.config = config
        self.vehicle = vehicle
        self.predictions = predictions
        self.state_topic = join_topic(vehicle, config.output_ns, 'state')
        self.parameters_topic = join_topic(vehicle, config.output_ns, 'parameters')
        self.prediction_topic = join_topic(vehicle, config.output_ns, 'prediction')
        self.radius_topic = join_topic(vehicle, config.output_ns, 'prediction_radius')
        self.markers_topic = join_topic(vehicle, config.output_ns, 'prediction_markers')
        self.labels_topic = join_topic(vehicle, config.output_ns, 'parameter_labels')
        self.named_topic = join_topic(vehicle, config.output_ns, 'parameters_named')
        self._labels_due = True  # the labels go out with the first parameters (bags)
        self._period_ns = round(NS / config.parameters_rate)
        #: How long a prediction's markers stay drawn: until the next one, and some.
        self.marker_lifetime_ns = NS
        self._last_slot: int | None = None
        self._prediction_status = 0

    @property
    def latched_topics(self) -> dict[str, str]:
        """Output topics published once, latched (``LATCHED_QOS``), and their message types."""
        return {self.labels_topic: STRING}

    def take_labels(self) -> tuple[str, bytes]:
        """``(topic, cdr)`` of ``parameter_labels``, which :meth:`encode` then no longer emits
        (the node publishes it at start-up on a latched publisher)."""
        self._labels_due = False
        return self.labels_topic, encode_string(parameter_labels_text())

    @property
    def topics(self) -> dict[str, str]:
        """Output topic names and their message types (every one :meth:`encode` emits, the
        latched ones too)."""
        topics = {self.state_topic: ODOMETRY, self.parameters_topic: FLOAT64_MULTI_ARRAY,
                  self.named_topic: PARAMETER_EVENT, **self.latched_topics}  # fmt: skip
        if self.predictions:
            topics[self.prediction_topic] = PATH
            topics[self.radius_topic] = FLOAT64_MULTI_ARRAY
            topics[self.markers_topic] = MARKER_ARRAY
        return topics

    def encode(
        self, estimate: Estimate, world_frame: str, child_frame: str
    ) -> list[tuple[str, int, bytes]]:
        out = [(self.state_topic, estimate.stamp_ns, encode_state(estimate, world_frame,
                                                                   child_frame))]  # fmt: skip
        if estimate.prediction is not None or estimate.prediction_note:
            self._prediction_status = estimate.prediction_status
        if estimate.prediction is not None:
            stamp = estimate.stamp_ns
            out.append((self.prediction_topic, stamp, encode_prediction(estimate, world_frame)))
            if estimate.prediction_radius is not None:
                out.append((self.radius_topic, stamp, encode_radius(estimate)))
                markers = encode_markers(estimate, world_frame, self.marker_lifetime_ns)
                out.append((self.markers_topic, stamp, markers))
        slot = estimate.stamp_ns // self._period_ns
        if self._last_slot is None or slot > self._last_slot:
            self._last_slot = slot
            if self._labels_due:
                topic, labels = self.take_labels()
                out.append((topic, estimate.stamp_ns, labels))
            values = parameter_vector(estimate, self._prediction_status)
            out.append((self.parameters_topic, estimate.stamp_ns,
                        encode_float64_multi_array(PARAMETER_LABELS, values)))
            out.append((self.named_topic, estimate.stamp_ns,
                        encode_named_values(estimate.stamp_ns, self.parameters_topic,
                                            PARAMETER_LABELS, values)))
        return out

    def reset(self) -> None:
        self._last_slot = None


def encode_state(estimate: Estimate, world_frame: str, child_frame: str) -> bytes:
    """``cloe/state``: the estimated state as Odometry (pose in world, twist in body, REP-105),
    with the estimate's error covariances (6x6 row-major each,
    :func:`~cloe_ros.core.covariance.odometry_covariance`; zeros without ``error_variance``),
    its 85 doubles computed in one compiled call (:func:`~cloe_ros.core.kernels.state_message`)."""
    values = np.empty(85)
    zeta = np.asarray(estimate.zeta_hat, dtype=float)
    variance = estimate.error_variance
    kernels.state_message(zeta, zeta if variance is None else np.asarray(variance, dtype=float),
                          variance is not None, values)  # fmt: skip
    return encode_odometry_values(estimate.stamp_ns, world_frame, child_frame, values)


#: ``excitation.*`` / ``uncertainty.*`` when there is no finite value: not measured (the paper's
#: algorithms), or not yet (``cloe_iv`` before its first check, or a row not excited: infinite
#: uncertainty). Both are non-negative otherwise, so the sentinel cannot be mistaken for a value.
NOT_MEASURED = -1.0


def parameter_vector(estimate: Estimate, prediction_status: int = 0) -> np.ndarray:
    """The values of ``cloe/parameters`` in ``PARAMETER_LABELS`` order, all finite."""
    n_rows = len(ROW_NAMES)
    if estimate.identification is None:
        ident = np.full(3 * n_rows, NOT_MEASURED)
    else:
        exc, unc, status = estimate.identification
        measured = np.concatenate([exc, unc])
        measured[~np.isfinite(measured)] = NOT_MEASURED
        ident = np.concatenate([measured, status.astype(float)])
    coupling = (
        estimate.coupling if estimate.coupling is not None
        else np.array([b.coupling for b in COUPLED_BLOCKS])
    )  # fmt: skip
    model_theta, model_coupling = (
        estimate.model if estimate.model is not None else (estimate.theta_hat, coupling)
    )
    tracked = (np.full(4, -1.0) if estimate.trust is None
               else estimate.trust.tracked.astype(float))  # fmt: skip
    return np.concatenate([
        estimate.theta_hat, estimate.gain_l, coupling, ident, [float(prediction_status)],
        model_theta, model_coupling, tracked,
    ])  # fmt: skip


def encode_parameters(estimate: Estimate, prediction_status: int = 0) -> bytes:
    """``cloe/parameters``, labelled (see ``PARAMETER_LABELS``)."""
    return encode_float64_multi_array(
        PARAMETER_LABELS, parameter_vector(estimate, prediction_status)
    )


def encode_prediction(estimate: Estimate, world_frame: str) -> bytes:
    """``cloe/prediction``: the anticipated path, poses stamped at their future times."""
    stamps, states = estimate.prediction
    positions = states[:, [0, 4, 10]]
    orientations = euler_to_quaternion(states[:, 6], states[:, 2], states[:, 8])
    return encode_path(PathSample(estimate.stamp_ns, world_frame, stamps, positions, orientations))


def encode_radius(estimate: Estimate) -> bytes:
    """``cloe/prediction_radius``: per pose of the prediction, its stamp (s), 95 % radius (m)."""
    stamps, _ = estimate.prediction
    rows = np.column_stack([np.asarray(stamps) / NS, estimate.prediction_radius])
    return encode_multi_array([('pose', len(rows)), (RADIUS_COLUMNS, 2)], rows)


def encode_markers(estimate: Estimate, world_frame: str, lifetime_ns: int) -> bytes:
    """``cloe/prediction_markers``: the predicted path and its 95 % spheres for RViz / Foxglove."""
    _, states = estimate.prediction
    return encode_prediction_markers(estimate.stamp_ns, world_frame, states[:, [0, 4, 10]],
                                     estimate.prediction_radius, lifetime_ns)  # fmt: skip
