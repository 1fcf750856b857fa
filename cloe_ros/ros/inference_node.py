"""``cloe_inference``: CLOE / CLOE-SM trajectory inference for one or many vehicles.

Per vehicle namespace ``<ns>`` (none for a single vehicle):

* subscribes ``<ns>/odom`` (nav_msgs/Odometry), ``<ns>/reference`` (geometry_msgs/PoseStamped)
  and, optionally, ``<ns>/reference_plan`` (nav_msgs/Path, planned future references), as raw CDR
  decoded by the same code as ``cloe infer``;
* runs a :class:`cloe_ros.core.engine.VehicleEngine` in fixed steps of message time (header
  stamps; never the wall clock);
* publishes ``<ns>/<output_ns>/state`` (nav_msgs/Odometry) every step,
  ``<ns>/<output_ns>/parameters`` (std_msgs/Float64MultiArray, labelled) at ``parameters_rate`` and
  ``<ns>/<output_ns>/prediction`` (nav_msgs/Path, poses at future stamps) at ``prediction_rate``;
* publishes ``/diagnostics`` every ``diagnostics_period`` and serves ``~/reset``
  (std_srvs/Trigger).
"""

from __future__ import annotations

import math
import time
from dataclasses import replace

from diagnostic_msgs.msg import DiagnosticArray
from geometry_msgs.msg import PoseStamped
from nav_msgs.msg import Odometry, Path
from rcl_interfaces.msg import FloatingPointRange, ParameterEvent
from rclpy.event_handler import SubscriptionEventCallbacks
from rclpy.node import Node
from std_msgs.msg import Float64MultiArray, String
from std_srvs.srv import Trigger
from visualization_msgs.msg import MarkerArray

from cloe_ros.core.anticipation import CHANNELS
from cloe_ros.core.engine import NS, EngineConfig, VehicleEngine
from cloe_ros.core.identifier import ROW_NAMES, STATUS_NAMES
from cloe_ros.io import messages
from cloe_ros.io.config import ALGORITHMS, DEFAULTS, RANGES, SettingsError, build_configs
from cloe_ros.io.messages import MessageError, Status, encode_diagnostics
from cloe_ros.io.outputs import OutputConfig, OutputEncoder
from cloe_ros.ros.common import (
    STRING_ARRAY,
    ParameterError,
    accept,
    check_vehicles,
    declare,
    describe,
    qos,
    refuse,
    run_node,
    vehicle_topic,
)

#: The message class of each output type.
OUTPUT_TYPES = {
    messages.ODOMETRY: Odometry,
    messages.FLOAT64_MULTI_ARRAY: Float64MultiArray,
    messages.PATH: Path,
    messages.MARKER_ARRAY: MarkerArray,
    messages.STRING: String,
    messages.PARAMETER_EVENT: ParameterEvent,
}
#: Parameters whose change restarts the estimators (the identified model is forgotten).
RESTARTING = ('algorithm', 'rate')
#: Wall-clock seconds without odometry after which a started vehicle's status turns WARN.
STALE_AFTER = 2.0


class InferenceNode(Node):
    """The inference node; see the module docstring and the README for its interface."""

    def __init__(self, **kwargs) -> None:
        super().__init__('cloe_inference', **kwargs)
        declared = self._declare_parameters()
        self.engine_config, self.output_config = self._configs(self._values())
        vehicles = check_vehicles(declared['vehicles'])
        self.vehicles = vehicles or ['']
        reliable = self.get_parameter('qos_reliability').value == 'reliable'
        depth = self.get_parameter('qos_depth').value
        in_qos = qos(reliable=reliable, depth=depth)
        out_qos = qos(reliable=True, depth=depth)
        self.engines: dict[str, VehicleEngine] = {}
        self.encoders: dict[str, OutputEncoder] = {}
        self.publishers_: dict[str, object] = {}
        self.malformed: dict[str, int] = {}
        self.vehicle_ns: dict[str, str] = {}
        self._odom_heard: dict[str, float] = {}  # wall (monotonic) time of the last odometry
        for v in self.vehicles:
            self._make_vehicle(v)
            events = SubscriptionEventCallbacks(incompatible_qos=self._incompatible_qos(v))
            self.create_subscription(
                Odometry, vehicle_topic(v, 'odom'), self._odometry_callback(v), in_qos,
                raw=True, event_callbacks=events,
            )  # fmt: skip
            self.create_subscription(
                PoseStamped, vehicle_topic(v, 'reference'), self._reference_callback(v), in_qos,
                raw=True, event_callbacks=events,
            )  # fmt: skip
            self.create_subscription(
                Path, vehicle_topic(v, 'reference_plan'), self._plan_callback(v), in_qos,
                raw=True,
            )  # fmt: skip
            for topic, msgtype in self.encoders[v].topics.items():
                if topic not in self.encoders[v].latched_topics:
                    self.publishers_[topic] = self.create_publisher(
                        OUTPUT_TYPES[msgtype], topic, out_qos
                    )
            self._latch_parameter_labels(v)
        self.diagnostics_pub = self.create_publisher(
            DiagnosticArray, '/diagnostics', qos(depth=10)
        )
        self._diag_timer = self.create_timer(
            self.get_parameter('diagnostics_period').value, self._publish_diagnostics
        )
        self._last_diag = (time.monotonic(), {v: 0 for v in self.vehicles})
        self.create_service(Trigger, '~/reset', self._reset_service)
        self.add_on_set_parameters_callback(self._on_set_parameters)
        self._warned: set[tuple[str, str]] = set()
        self._last_rejected: dict[str, str] = {}  # per vehicle: the last rejection, in words
        self._last_estimate: dict[str, object] = {}
        self._last_prediction_note: dict[str, str] = {}
        names = ', '.join(v or '/' for v in self.vehicles)
        self.get_logger().info(
            f'ready: {self.engine_config.estimator.algorithm} at {self.engine_config.rate:g} Hz '
            f'for {names}'
        )

    def _latch_parameter_labels(self, vehicle: str) -> None:
        """Publish ``<out>/parameter_labels`` once, latched (reliable, transient local, depth 1),
        so a viewer that connects later still gets the names of ``<out>/parameters``."""
        topic, data = self.encoders[vehicle].take_labels()
        publisher = self.create_publisher(String, topic, qos(depth=1, transient_local=True))
        self.publishers_[topic] = publisher
        publisher.publish(data)

    # ------------------------------------------------------------------------- parameters

    def _declare_parameters(self) -> dict:
        ro = {'read_only': True}
        p = [
            ('vehicles', [], describe(
                'vehicle namespaces, e.g. [/uav1, /uav2]; empty: one vehicle, topics relative to '
                'the node namespace', parameter_type=STRING_ARRAY, **ro)),
            ('algorithm', DEFAULTS['algorithm'], describe(
                'estimator: ' + ' | '.join(ALGORITHMS) + ' (cloe and cloe_sm as the paper states '
                'them; cloe_iv identifies with instrumental variables); changing it restarts',
                additional_constraints='one of ' + ', '.join(ALGORITHMS))),
            ('rate', DEFAULTS['rate'], describe(
                'estimator steps per second of message time, Hz (changing it restarts)')),
            ('gamma_theta', DEFAULTS['gamma_theta'], describe(
                'cloe, cloe_sm: identifier gain Gamma (paper: 400)')),
            ('gamma_l', DEFAULTS['gamma_l'], describe(
                'adaptive observer-gain rate gamma (paper: 400)')),
            ('l_initial', DEFAULTS['l_initial'], describe(
                'initial observer gain L(0), 1/s (cloe_iv: at least l_min)')),
            ('sm_gains', DEFAULTS['sm_gains'], describe(
                'sliding-mode gains alpha, one per state (paper Table 1)',
                additional_constraints='12 values >= 0')),
            ('sm_exponents', DEFAULTS['sm_exponents'], describe(
                'sliding-mode exponents p, one per state',
                additional_constraints='12 values in [0, 1)')),
            ('reference_timeout', DEFAULTS['reference_timeout'], describe(
                'odometry lead (s) after which a missing newer reference is held')),
            ('max_gap', DEFAULTS['max_gap'], describe(
                'odometry gap (s) treated as a time jump: the estimator re-initialises')),
            ('world_frame', DEFAULTS['world_frame'], describe(
                'required header.frame_id of odom and reference; empty: the first one seen',
                **ro)),
            ('output_ns', DEFAULTS['output_ns'], describe(
                'namespace of the outputs under each vehicle namespace', **ro)),
            ('parameters_rate', DEFAULTS['parameters_rate'], describe(
                'parameters messages per second of message time, Hz')),
            ('prediction_horizon', DEFAULTS['prediction_horizon'], describe(
                'anticipated path length, s (0: no predictions)',
                **ro)),
            ('prediction_step', DEFAULTS['prediction_step'], describe(
                'spacing of the predicted poses, s', **ro)),
            ('prediction_rate', DEFAULTS['prediction_rate'], describe(
                'predictions per second of message time, Hz',
                **ro)),
            ('prediction_disturbance_time', DEFAULTS['prediction_disturbance_time'], describe(
                'window of the recent model-error fit and its fading time over the horizon, s '
                '(0: steady-state offsets only)', **ro)),
            ('l_leak', DEFAULTS['l_leak'], describe(
                'cloe_iv: leakage of the observer gain L, 1/s')),
            ('gamma_d', DEFAULTS['gamma_d'], describe(
                "cloe_iv: rate of the observer's model-error state on the unknown rows, 1/s^2")),
            ('l_min', DEFAULTS['l_min'], describe(
                'cloe_iv: lower bound of L, 1/s')),
            ('l_max', DEFAULTS['l_max'], describe(
                'cloe_iv: upper bound of L, 1/s')),
            ('id_bandwidth', DEFAULTS['id_bandwidth'], describe(
                "cloe_iv: identifier's filter bandwidth, rad/s")),
            ('id_highpass', DEFAULTS['id_highpass'], describe(
                "cloe_iv: identifier's high-pass corner, rad/s")),
            ('id_window', DEFAULTS['id_window'], describe(
                'cloe_iv: forgetting time constant of the estimate, s')),
            ('id_excitation_window', DEFAULTS['id_excitation_window'], describe(
                'cloe_iv: time constant of the excitation measure, s')),
            ('id_excitation_threshold', DEFAULTS['id_excitation_threshold'], describe(
                'cloe_iv: smallest canonical correlation counted as excited')),
            ('estimate_coupling', DEFAULTS['estimate_coupling'], describe(
                'cloe_iv: identify the tilt couplings (the paper fixes them at +-g)')),
            ('ground_altitude', DEFAULTS['ground_altitude'], describe(
                'cloe_iv: identification pauses while the commanded altitude is at or below '
                'this, m (below every commanded altitude: never); predictions then do not rely '
                'on the reference')),
            ('prediction_intent', DEFAULTS['prediction_intent'], describe(
                'without a plan, predict where the reference goes from its recent past (else: '
                'held)', **ro)),
            ('prediction_guard', DEFAULTS['prediction_guard'], describe(
                'publish, per horizon, the combination of the closed loop and model-free '
                'predictors that did best recently (else: the closed loop alone)', **ro)),
            ('prediction_coverage', DEFAULTS['prediction_coverage'], describe(
                'probability the published prediction radius is meant to hold', **ro)),
            ('reference_trust', DEFAULTS['reference_trust'], describe(
                'check whether the vehicle tracks each reference channel; a channel it does '
                'not track is replaced by the reference its motion implies (else: always '
                'trusted)', **ro)),
            ('reference_trust_ratio', DEFAULTS['reference_trust_ratio'], describe(
                'a reference channel is not tracked when the model driven by it misses the last '
                'second by more than this many times constant velocity (and by more than '
                'reference_trust_floor)', **ro)),
            ('reference_trust_floor', DEFAULTS['reference_trust_floor'], describe(
                'the least miss of the model driven by a reference channel over the last second '
                'that makes it not tracked, m (rad for yaw)', **ro)),
            ('diagnostics_period', 1.0, describe(
                '/diagnostics period, s', float_range=(0.05, 60.0), **ro)),
            ('qos_reliability', 'reliable', describe(
                'QoS reliability of the subscriptions: reliable | best_effort', **ro,
                additional_constraints='reliable or best_effort')),
            ('qos_depth', 1000, describe(
                'QoS history depth of the subscriptions (10 s of 100 Hz odometry: a node starved '
                'of CPU for a moment loses nothing)', int_range=(1, 100000), **ro)),
        ]  # fmt: skip
        for name, _, d in p:  # one range per setting, the one `cloe infer` checks too
            if name in RANGES:
                low, high = RANGES[name]
                d.floating_point_range = [FloatingPointRange(from_value=low, to_value=high)]
        values = {name: declare(self, name, default, d) for name, default, d in p}
        if values['qos_reliability'] not in ('reliable', 'best_effort'):
            reason = f'must be reliable or best_effort, got {values["qos_reliability"]!r}'
            raise ParameterError(reason, 'qos_reliability')
        return values

    def _values(self, overrides: dict | None = None) -> dict:
        values = {n: self.get_parameter(n).value for n in DEFAULTS}
        values.update(overrides or {})
        return values

    @staticmethod
    def _configs(values: dict) -> tuple[EngineConfig, OutputConfig]:
        """Build the configs; ``ParameterError`` naming the parameter if a value cannot be used."""
        try:
            return build_configs(values)
        except SettingsError as err:
            raise ParameterError(err.reason, err.name) from err

    def _on_set_parameters(self, params):
        changes = {p.name: p.value for p in params}
        try:
            engine_config, output_config = build_configs(self._values(changes))
        except SettingsError as err:
            return refuse(str(err))
        restart = any(
            n in changes and changes[n] != self.get_parameter(n).value for n in RESTARTING
        )
        self.engine_config, self.output_config = engine_config, output_config
        for v, engine in self.engines.items():
            if restart:
                self._make_vehicle(v, keep_stats=True)
            else:
                # timing tolerances at once; the estimator keeps its state and model unless an
                # identifier setting of cloe_iv changed (VehicleEngine.update_estimator)
                engine.config = replace(engine_config, estimator=engine.config.estimator)
                engine.update_estimator(engine_config.estimator)
            if 'parameters_rate' in changes:
                self.encoders[v] = OutputEncoder(output_config, v, self.encoders[v].predictions)
        if restart:
            self.get_logger().info(
                f'restarted the estimators: {engine_config.estimator.algorithm} at '
                f'{engine_config.rate:g} Hz'
            )
        return accept()

    def _make_vehicle(self, vehicle: str, keep_stats: bool = False) -> None:
        old = self.engines.get(vehicle)
        engine = VehicleEngine(self.engine_config, name=vehicle)
        if keep_stats and old is not None:
            engine.stats = old.stats
            engine.stats.resets += 1
        self.engines[vehicle] = engine
        self.encoders[vehicle] = OutputEncoder(
            self.output_config, vehicle, self.engine_config.prediction.enabled
        )
        self.malformed.setdefault(vehicle, 0)
        # the vehicle's namespace as a recording shows it ('/' for the root): what /diagnostics
        # reports, and how a report of the recording finds which algorithm made each output
        odom = self.resolve_topic_name(vehicle_topic(vehicle, 'odom'), only_expand=True)
        self.vehicle_ns[vehicle] = odom[: -len('/odom')] or '/'

    # -------------------------------------------------------------------------- callbacks

    def _odometry_callback(self, vehicle: str):
        engine = self.engines

        def callback(raw: bytes) -> None:
            try:
                sample = messages.decode_odometry(raw)
            except MessageError as err:
                self._malformed(vehicle, 'odom', err)
                return
            self._odom_heard[vehicle] = time.monotonic()
            engine[vehicle].add_odometry(sample)
            self._warn_rejections(vehicle)
            self._publish(vehicle)

        return callback

    def _reference_callback(self, vehicle: str):
        engine = self.engines

        def callback(raw: bytes) -> None:
            try:
                sample = messages.decode_pose_stamped(raw)
            except MessageError as err:
                self._malformed(vehicle, 'reference', err)
                return
            engine[vehicle].add_reference(sample)
            self._warn_rejections(vehicle)
            self._publish(vehicle)

        return callback

    def _plan_callback(self, vehicle: str):
        engine = self.engines

        def callback(raw: bytes) -> None:
            try:
                sample = messages.decode_path(raw)
            except MessageError as err:
                self._malformed(vehicle, 'reference_plan', err)
                return
            engine[vehicle].add_plan(sample)
            self._warn_rejections(vehicle)

        return callback

    def _malformed(self, vehicle: str, topic: str, err: Exception) -> None:
        self.malformed[vehicle] += 1
        self._warn_once(vehicle, f'malformed {topic}: {err}')

    def _warn_rejections(self, vehicle: str) -> None:
        """Warn of what the engine rejected (also a held input found to be an outlier later),
        with what was wrong."""
        for rejection in self.engines[vehicle].take_rejections():
            self._warn_once(vehicle, rejection.describe())

    def _warn_once(self, vehicle: str, reason: str) -> None:
        self._last_rejected[vehicle] = reason
        key = (vehicle, reason.split(':')[0])
        if key not in self._warned:
            self._warned.add(key)
            self.get_logger().warning(
                f'{vehicle or "/"}: rejected input ({reason}); further ones are only counted '
                'in /diagnostics'
            )

    def _incompatible_qos(self, vehicle: str):
        def callback(event) -> None:
            self.get_logger().warning(
                f'{vehicle or "/"}: a publisher offers an incompatible QoS '
                f'({event.last_policy_kind}); for best-effort sensors set '
                'qos_reliability:=best_effort'
            )

        return callback

    def _identification_values(self, vehicle: str) -> list[tuple[str, str]]:
        """The identifier's status (per row: excitation, uncertainty, status), the prediction's."""
        last = self._last_estimate.get(vehicle)
        if last is None:
            return []
        out = [('prediction', self._last_prediction_note.get(vehicle, 'none yet'))]
        if last.identification is None:
            out.append(('identifier', 'gradient (paper): identifiability not measured'))
            return out
        exc, unc, status = last.identification
        for name, e, u, st in zip(ROW_NAMES, exc, unc, status):
            out.append(
                (
                    f'identifier: {name}',
                    f'{STATUS_NAMES[int(st)]} (excitation {e:.3f}, uncertainty '
                    f'{f"{u:.1%}" if math.isfinite(u) else "not measured yet"})',
                )
            )
        return out

    def _publish(self, vehicle: str) -> None:
        engine = self.engines[vehicle]
        estimates = engine.advance()
        if not estimates:
            return
        self._last_estimate[vehicle] = estimates[-1]
        for est in estimates:
            if est.prediction_note:
                self._last_prediction_note[vehicle] = est.prediction_note
        encoder = self.encoders[vehicle]
        frame, child = engine.world_frame or '', engine.child_frame
        for est in estimates:
            for topic, _, data in encoder.encode(est, frame, child):
                self.publishers_[topic].publish(data)

    def _reset_service(self, request, response):
        for v, engine in self.engines.items():
            engine.reset()
            self.encoders[v].reset()
        response.success = True
        response.message = f'reset {len(self.engines)} vehicle(s): model forgotten'
        self.get_logger().info(response.message)
        return response

    # ------------------------------------------------------------------------ diagnostics

    def vehicle_status(self, vehicle: str, steps_per_s: float) -> Status:
        engine = self.engines[vehicle]
        s = engine.stats
        rejected = sum(s.rejected.values()) + self.malformed[vehicle]
        last = self._last_rejected.get(vehicle, '')
        if not engine.started:
            level, message = messages.WARN, 'waiting for odom and reference'
            if rejected:
                message += f'; {rejected} input(s) rejected, the last: {last}'
        elif s.diverged:
            level, message = messages.WARN, f'running; the estimator diverged {s.diverged} time(s)'
        elif rejected:
            level = messages.WARN
            message = f'running; {rejected} input(s) rejected, the last: {last}'
        else:
            level, message = messages.OK, 'running'
        heard = self._odom_heard.get(vehicle)
        silent = None if heard is None else time.monotonic() - heard
        if engine.started and silent is not None and silent > STALE_AFTER:
            level = messages.WARN
            message = f'{message}; no odometry for {silent:.1f} s'
        note = self._last_prediction_note.get(vehicle, '')
        if engine.started and note and not note.startswith('identified'):
            message += f'; prediction {note}'
        last = self._last_estimate.get(vehicle)
        trust = None if last is None else last.trust
        untracked = [] if trust is None else [
            (c, why) for c, ok, why in zip(CHANNELS, trust.tracked, trust.reasons) if not ok]
        if engine.started and untracked:
            level = max(level, messages.WARN)
            message += '; reference not tracked: ' + ', '.join(c for c, _ in untracked)
        values = [
            ('algorithm', engine.config.estimator.algorithm),
            ('output_ns', self.output_config.output_ns),
            *self._identification_values(vehicle),
            ('reference', 'not decided yet' if trust is None else
             'tracked' if not untracked else
             'not tracked: ' + '; '.join(f'{c} ({why})' for c, why in untracked)),
            ('untracked_steps', str(s.untracked_steps)),
            ('rate_hz', f'{engine.config.rate:g}'),
            ('odom_silent_s', '' if silent is None else f'{silent:.1f}'),
            ('steps_per_s', f'{steps_per_s:.1f}'),
            ('steps', str(s.steps)),
            ('odom_received', str(s.odom_received)),
            ('odom_accepted', str(s.odom_accepted)),
            ('reference_received', str(s.reference_received)),
            ('reference_accepted', str(s.reference_accepted)),
            ('rejected', str(rejected)),
            ('malformed', str(self.malformed[vehicle])),
            *[(f'rejected: {k}', str(n)) for k, n in sorted(s.rejected.items())],
            ('time_jumps', str(s.time_jumps)),
            ('position_jumps', str(s.position_jumps)),
            ('frames_relearnt', str(s.frames_relearnt)),
            ('resets', str(s.resets)),
            ('diverged', str(s.diverged)),
            ('error_norm', f'{s.last_error_norm:.6g}' if math.isfinite(s.last_error_norm)
             else 'no step yet'),
            ('last_stamp', '' if s.last_stamp_ns is None else f'{s.last_stamp_ns / NS:.3f}'),
            ('predictions', str(s.predictions)),
            ('predictions_withheld', str(s.predictions_withheld)),
            ('plans_accepted', str(s.plans_accepted)),
        ]
        ns = self.vehicle_ns[vehicle]
        return Status(level, f'{self.get_name()}: {ns}', message, ns, tuple(values))

    def _publish_diagnostics(self) -> None:
        now = time.monotonic()
        t_prev, steps_prev = self._last_diag
        dt = max(now - t_prev, 1e-9)
        statuses = []
        for v, engine in self.engines.items():
            statuses.append(
                self.vehicle_status(v, (engine.stats.steps - steps_prev.get(v, 0)) / dt)
            )
        self._last_diag = (now, {v: e.stats.steps for v, e in self.engines.items()})
        stamp = self.get_clock().now().nanoseconds
        self.diagnostics_pub.publish(encode_diagnostics(stamp, statuses))


def main(args=None) -> int:
    return run_node(InferenceNode, args)


if __name__ == '__main__':
    raise SystemExit(main())
