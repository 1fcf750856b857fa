"""``cloe_inference``: CLOE / CLOE-SM trajectory inference for one or many vehicles.

Per vehicle namespace ``<ns>`` (none for a single vehicle):

* subscribes ``<ns>/odom`` (nav_msgs/Odometry), ``<ns>/reference`` (geometry_msgs/PoseStamped)
  and, optionally, ``<ns>/reference_plan`` (nav_msgs/Path, planned future references), as raw CDR
  decoded by the same code as ``cloe infer``;
* runs a :class:`cloe_ros.core.engine.VehicleEngine` in fixed steps of message time (header
  stamps; never the wall clock). The engines are one :class:`cloe_ros.core.fleet.Fleet`: the
  vehicles with new input step together, one batched estimator call per grid step, as soon as
  every vehicle has new input (or twice as many inputs as vehicles have come: some are silent)
  and at the latest 1.5 ``batch_period`` of wall time after the
  first input (the batch timer runs every ``batch_period`` and steps a batch whose first input
  has waited half of it; ``batch_period`` 0: each vehicle alone at each of its messages; the
  estimates are the same either way);
* publishes ``<ns>/<output_ns>/state`` (nav_msgs/Odometry) every step,
  ``<ns>/<output_ns>/parameters`` (std_msgs/Float64MultiArray, labelled) and ``parameters_named``
  at ``parameters_rate``, ``parameter_labels`` once (latched), and ``<ns>/<output_ns>/prediction``
  (nav_msgs/Path, poses at future stamps), ``prediction_radius`` and ``prediction_markers`` at
  ``prediction_rate`` (docs/outputs.md);
* publishes ``/diagnostics`` every ``diagnostics_period`` (on its timer, or from its inputs when
  the timer's turn is held up behind them, a tenth of a period overdue: a node behind its inputs
  still reports about on time) and
  serves ``~/reset`` (std_srvs/Trigger).
"""

from __future__ import annotations

import functools
import time

from diagnostic_msgs.msg import DiagnosticArray
from geometry_msgs.msg import PoseStamped
from nav_msgs.msg import Odometry, Path
from rcl_interfaces.msg import ParameterEvent, ParameterType
from rclpy.clock import Clock, ClockType
from rclpy.event_handler import SubscriptionEventCallbacks
from rclpy.node import Node
from std_msgs.msg import Float64MultiArray, String
from std_srvs.srv import Trigger
from visualization_msgs.msg import MarkerArray

from cloe_ros.core import ahead
from cloe_ros.core.engine import NS, EngineConfig, VehicleEngine
from cloe_ros.core.fleet import Fleet
from cloe_ros.io import messages
from cloe_ros.io.config import DEFAULTS, SettingsError, build_configs, node_values
from cloe_ros.io.diagnostics import DIAGNOSTICS_TOPIC, STALE_AFTER, Link, vehicle_status
from cloe_ros.io.messages import MessageError, Status, encode_diagnostics
from cloe_ros.io.outputs import OutputConfig, OutputEncoder
from cloe_ros.ros.common import (
    STRING_ARRAY,
    ParameterError,
    accept,
    check_same_namespaces,
    check_vehicles,
    declare,
    describe,
    destroyed_if_init_fails,
    incompatible_policy,
    qos,
    refuse,
    resolved_namespace,
    run_node,
    vehicle_topic,
)
from cloe_ros.ros.fleet import check_shard, graph_namespaces, shard_of
from cloe_ros.settings import RESTARTS, SETTINGS, engine_settings

#: The message class of each output type.
OUTPUT_TYPES = {
    messages.ODOMETRY: Odometry,
    messages.FLOAT64_MULTI_ARRAY: Float64MultiArray,
    messages.PATH: Path,
    messages.MARKER_ARRAY: MarkerArray,
    messages.STRING: String,
    messages.PARAMETER_EVENT: ParameterEvent,
}
#: The inputs of a vehicle, each counted in /diagnostics when DDS loses some.
INPUTS = ('odom', 'reference', 'reference_plan')
#: The inputs a vehicle needs, and the type the node subscribes to each with.
INPUT_TYPES = {'odom': messages.ODOMETRY, 'reference': messages.POSE_STAMPED}
#: The node's status turns WARN when, over a diagnostics period, its callbacks took this share
#: of the wall time (at its limit), or its steady timer ran this late, s (behind its inputs); see
#: :class:`Load`.
BUSY_WARN = 0.8
LATE_WARN = 0.5
#: The start-up log's words for the kernels the node runs (its status key ``kernels``): the ones
#: built ahead, or numba's JIT (cloe_ros/core/ahead.py).
KERNELS_NOTE = {'ahead': 'kernels built ahead', 'jit': "kernels compiled by numba's JIT"}
#: The diagnostics timer publishes a report once this share of ``diagnostics_period`` (node clock)
#: has passed since the last one (less than all of it, so that the timer's jitter does not skip a
#: period); the inputs publish it once this other share has passed (more than all of it: the
#: timer's turn is held up behind them).
DIAGNOSTICS_DUE, DIAGNOSTICS_OVERDUE = 0.9, 1.1
#: The inputs look whether a report is due at most this often, s of wall time (and at most four
#: times a ``diagnostics_period``).
DIAGNOSTICS_POLL = 0.1


class Load:
    """How loaded the node's thread is, between two readings:

    * ``busy``: the wall time its callbacks (inputs, batches, the graph poll, the diagnostics)
      took, as a share of the wall time. The executor's own work (taking the messages) is not
      in it, so a node at its limit reads less than 1 (about 0.8 to 0.9 under the load of
      EVALUATION.md section 4). Wall time: a node slowed by other processes on its core counts
      as busy too.
    * ``late``: how long after its deadline a steady-clock timer of the node ran, at worst, s.
      Each :meth:`heartbeat` (the timer's callback) gives the timer's next deadline (rcl keeps
      the deadlines on a fixed grid, so the time between two callbacks would not show a timer
      that is always late); a deadline passed at a reading counts too, so a timer that could
      not run yet shows. rclpy's EventsExecutor queues a timer's turn behind the messages
      already waiting, so a node behind its inputs runs its timers about as late as its inputs
      wait: its states are that stale, and what the subscriptions' histories overwrite
      meanwhile is missed (each vehicle's ``odom_missing``). A reading without a heartbeat
      since the last one keeps the last heartbeat's lateness.
    * ``longest``: the wall time of the longest single callback, s. Every input that arrives
      meanwhile waits for it, so it bounds from below how late some states come: at 100
      vehicles, the round in which their predictions fall due together (EVALUATION.md section 4).
    """

    def __init__(self) -> None:
        self.seconds = 0.0  # in the timed callbacks, since the start
        self._read = (time.perf_counter(), 0.0)
        self._due: float | None = None  # the timer's next deadline (perf_counter time)
        self._late = 0.0  # the worst lateness of the heartbeats since the last reading
        self._beats = 0  # the heartbeats since the last reading
        self._last_late = 0.0  # the last heartbeat's lateness
        self._longest = 0.0  # the longest callback since the last reading

    def timed(self, fn):
        """``fn`` with its wall time added to :attr:`seconds`."""
        clock = time.perf_counter

        @functools.wraps(fn)
        def timed(*args):
            t0 = clock()
            try:
                return fn(*args)
            finally:
                spent = clock() - t0
                self.seconds += spent
                if spent > self._longest:
                    self._longest = spent

        return timed

    def heartbeat(self, next_in: float | None, now: float | None = None) -> None:
        """The timer ran (at ``now``, ``time.perf_counter()`` if None); its next deadline is
        ``next_in`` s ahead (``Timer.time_until_next_call()``; None: not known)."""
        now = time.perf_counter() if now is None else now
        if self._due is not None:
            self._last_late = max(0.0, now - self._due)
            self._late = max(self._late, self._last_late)
            self._beats += 1
        self._due = None if next_in is None else now + next_in

    def read(self, now: float | None = None) -> tuple[float, float, float]:
        """``(busy, late, longest)`` since the last reading (since the start for the first);
        busy in [0, 1], late in s (0 when on time), longest in s."""
        now = time.perf_counter() if now is None else now
        then = self._read
        self._read = (now, self.seconds)
        busy = min(1.0, max(0.0, (self.seconds - then[1]) / max(now - then[0], 1e-9)))
        late = self._late if self._beats else self._last_late
        if self._due is not None:
            late = max(late, now - self._due)  # (a deadline passed, the timer not run yet)
        longest, self._longest = self._longest, 0.0
        self._late, self._beats = 0.0, 0
        # (to the digits /diagnostics shows, so that what it shows decides the status)
        return round(busy, 3), round(late, 3), round(longest, 3)


class InferenceNode(Node):
    """The inference node; see the module docstring and the README for its interface."""

    @destroyed_if_init_fails
    def __init__(self, **kwargs) -> None:
        super().__init__('cloe_inference', **kwargs)
        declared = self._declare_parameters()
        self.engine_config, self.output_config = self._configs(self._values())
        self.listed = check_vehicles(declared['vehicles'])
        self.discover = declared['discover']
        self.kernels = 'ahead' if ahead.MODULE is not None else 'jit'
        self.shard_index, self.shard_count = declared['shard_index'], declared['shard_count']
        reason = check_shard(self.shard_index, self.shard_count)
        if reason:
            raise ParameterError(reason, 'shard_index')
        if self.shard_count > 1 and not self.listed and not self.discover:
            raise ParameterError(
                f'{self.shard_count} shards split the vehicles listed (vehicles:=[...]) or '
                'discovered (discover:=true); with neither, the node infers the one '
                'un-namespaced vehicle, which cannot be split', 'shard_count')  # fmt: skip
        self.publisher_timeout = declared['publisher_timeout']
        self.vehicles: list[str] = []
        reliable = declared['qos_reliability'] == 'reliable'
        depth = declared['qos_depth']
        in_qos = qos(reliable=reliable, depth=depth)
        out_qos = qos(reliable=True, depth=depth)
        self.batch_period = declared['batch_period']
        # every vehicle's engine, their estimators batched (unless each steps on its messages)
        self.fleet = Fleet(pooled=self.batch_period > 0)
        self.engines: dict[str, VehicleEngine] = self.fleet.engines
        # the vehicles with input since the last batch (a dict: in order of arrival), and the
        # inputs since then
        self._due: dict[str, None] = {}
        self._inputs = 0
        self._due_since = 0.0  # wall (monotonic) time of the first input of this batch
        self.encoders: dict[str, OutputEncoder] = {}
        self.publishers_: dict[str, object] = {}
        self.malformed: dict[str, int] = {}
        self.vehicle_ns: dict[str, str] = {}
        self._odom_heard: dict[str, float] = {}  # wall (monotonic) time of the last odometry
        self.lost: dict[str, dict[str, int]] = {}  # per vehicle and input: DDS message_lost
        self._in_qos, self._out_qos = in_qos, out_qos
        self._started = time.monotonic()
        self.load = Load()
        self._load = (0.0, 0.0, 0.0)  # (busy, late, longest) over the last diagnostics period
        self._overloaded = False  # as that load said (logged when it changes)
        # per vehicle: the inputs without a publisher, and since when (wall, monotonic)
        self._missing: dict[str, list[str]] = {}
        self._missing_since: dict[str, float] = {}
        self._warned_missing: set[str] = set()
        self._hinted: set[str] = set()  # of those, the ones warned with the hint of the others
        self._discovered: set[str] = set()
        # the vehicles whose cloe/state something else publishes too (another node's shard)
        self._doubled: set[str] = set()
        check_same_namespaces(self, self.listed)
        for v in self.listed or ([] if self.discover else ['']):
            if self._ours(self._namespace(v)):  # (a listed vehicle of another shard: not ours)
                self._add_vehicle(v)
        steady = Clock(clock_type=ClockType.STEADY_TIME)
        self._batch_timer = (
            self.create_timer(self.batch_period, self.load.timed(self._step_waiting),
                              clock=steady)
            if self.batch_period > 0 else None
        )  # fmt: skip
        self._graph_timer = self.create_timer(
            declared['discovery_period'], self.load.timed(self._poll_graph), clock=steady
        )
        self.diagnostics_pub = self.create_publisher(
            DiagnosticArray, DIAGNOSTICS_TOPIC, qos(depth=10)
        )
        self._diag_period_ns = round(declared['diagnostics_period'] * NS)
        self._diag_timer = self.create_timer(
            declared['diagnostics_period'], self.load.timed(self._diagnostics_if_due)
        )
        self._last_diag = (time.monotonic(), {v: 0 for v in self.vehicles})
        self._diag_stamp_ns = self.get_clock().now().nanoseconds  # the last report's (node clock)
        self._diag_poll = min(DIAGNOSTICS_POLL, 0.25 * declared['diagnostics_period'])
        self._diag_poll_at = time.monotonic() + self._diag_poll  # when the inputs next look
        self.create_service(Trigger, '~/reset', self._reset_service)
        self._applied = self._settings()
        self.add_on_set_parameters_callback(self._on_set_parameters)
        self.add_post_set_parameters_callback(self._apply_parameters)
        self._warned: set[tuple[str, str]] = set()
        self._last_rejected: dict[str, str] = {}  # per vehicle: the last rejection, in words
        self._last_estimate: dict[str, object] = {}
        self._last_prediction_note: dict[str, str] = {}
        names = ', '.join(self.vehicle_ns[v] for v in self.vehicles) or (
            'no vehicle' if self.idle else 'no vehicle yet')
        notes = []
        if self.shard_count > 1:
            notes.append(
                f'shard {self.shard_index} of {self.shard_count}'
                + (f': {len(self.vehicles)} of the {len(self.listed)} listed vehicles'
                   if self.listed else '')
            )  # fmt: skip
        if self.discover:
            notes.append('discovering vehicles')
        notes.append(KERNELS_NOTE[self.kernels])
        self.get_logger().info(
            f'ready: {self.engine_config.estimator.algorithm} at {self.engine_config.rate:g} Hz '
            f'for {names}' + (f' ({"; ".join(notes)})' if notes else '')
        )
        if self.idle:
            self.get_logger().warning(
                f'none of the {len(self.listed)} listed vehicles belongs to shard '
                f'{self.shard_index} of {self.shard_count}: this node infers nothing (each '
                'vehicle goes to shard crc32(namespace) mod shard_count; fewer shards, or '
                'discover:=true, which also takes vehicles that appear later)'
            )

    @property
    def idle(self) -> bool:
        """A shard that can never infer a vehicle: a list, no discovery, none of it ours."""
        return bool(self.listed) and not self.discover and not self.vehicles

    def _latch_parameter_labels(self, vehicle: str) -> None:
        """Publish ``<out>/parameter_labels`` once, latched (reliable, transient local, depth 1),
        so a viewer that connects later still gets the names of ``<out>/parameters``."""
        topic, data = self.encoders[vehicle].take_labels()
        publisher = self.create_publisher(String, topic, qos(depth=1, transient_local=True))
        self.publishers_[topic] = publisher
        publisher.publish(data)

    # ------------------------------------------------------------------------- parameters

    def _declare_parameters(self) -> dict:
        """Declare every setting of :data:`cloe_ros.settings.SETTINGS` (type, range, read-only,
        description); returns the node's own settings, checked."""
        values = {}
        for s in SETTINGS.values():
            d = describe(
                s.full_description(),
                read_only=s.read_only,
                float_range=s.range if s.kind is float else None,
                int_range=s.range if s.kind is int else None,
                additional_constraints=s.constraints(),
                parameter_type=STRING_ARRAY if s.kind is list else ParameterType.PARAMETER_NOT_SET,
            )
            default = list(s.default) if isinstance(s.default, (tuple, list)) else s.default
            values[s.name] = declare(self, s.name, default, d)
        try:
            return node_values(values)
        except SettingsError as err:
            raise ParameterError(err.reason, err.name) from err

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

    def _settings(self) -> dict:
        """The engine's settings as the parameters hold them now, each of its own type."""
        return {s.name: s.coerce(self.get_parameter(s.name).value) for s in engine_settings()}

    def _on_set_parameters(self, params):
        """Validate: refuse, with the reason, changes the engine cannot use (applied after they
        are set, in :meth:`_apply_parameters`)."""
        try:
            build_configs(self._values({p.name: p.value for p in params}))
        except SettingsError as err:
            return refuse(str(err))
        return accept()

    def _apply_parameters(self, params) -> None:
        """Apply what has been set, as each setting's ``on_change`` says: a change of a
        restarting setting restarts the estimators; every other one applies at once (the
        engine itself restarts cloe_iv for a change of its identifier's settings)."""
        engine_config, output_config = self._configs(self._values())
        settings = self._settings()
        changed = {n for n, v in settings.items() if v != self._applied.get(n)}
        self._applied = settings
        if not changed:
            return
        restart = any(SETTINGS[n].on_change == RESTARTS for n in changed)
        self.engine_config, self.output_config = engine_config, output_config
        for v, engine in list(self.engines.items()):
            if restart:
                self._make_vehicle(v, keep_stats=True)
            else:
                # timing tolerances at once; the estimator keeps its state and model unless an
                # identifier setting of cloe_iv changed (VehicleEngine.update_estimator)
                engine.update_config(engine_config)
            if 'parameters_rate' in changed:
                self._new_encoder(v, self.encoders[v].predictions)
        if restart:
            self.get_logger().info(
                f'restarted the estimators: {engine_config.estimator.algorithm} at '
                f'{engine_config.rate:g} Hz'
            )

    def _add_vehicle(self, v: str) -> None:
        """Engine, subscriptions and publishers of vehicle ``v``. Every subscription counts the
        messages DDS reports lost (``message_lost``: overwritten in the publisher's history
        before this node took them, or gaps seen by a best-effort subscription)."""
        self._make_vehicle(v)
        self.vehicles.append(v)
        self.lost[v] = dict.fromkeys(INPUTS, 0)
        self._missing[v] = []
        self._missing_since[v] = time.monotonic()  # until its publishers are seen
        callbacks = {
            'odom': (Odometry, self._odometry_callback(v)),
            'reference': (PoseStamped, self._reference_callback(v)),
            'reference_plan': (Path, self._plan_callback(v)),
        }
        for name, (msgtype, callback) in callbacks.items():
            events = SubscriptionEventCallbacks(
                incompatible_qos=self._incompatible_qos(vehicle_topic(v, name)),
                message_lost=functools.partial(self._on_lost, v, name),
            )
            self.create_subscription(
                msgtype, vehicle_topic(v, name), self.load.timed(callback), self._in_qos, raw=True,
                event_callbacks=events,
            )  # fmt: skip
        for topic, msgtype in self.encoders[v].topics.items():
            if topic not in self.encoders[v].latched_topics:
                self.publishers_[topic] = self.create_publisher(
                    OUTPUT_TYPES[msgtype], topic, self._out_qos
                )
        self._latch_parameter_labels(v)

    def _on_lost(self, vehicle: str, name: str, info) -> None:
        self.lost[vehicle][name] += int(info.total_count_change)

    def _make_vehicle(self, vehicle: str, keep_stats: bool = False) -> None:
        old = self.engines.get(vehicle)
        self.vehicle_ns[vehicle] = namespace = self._namespace(vehicle)
        stats = old.stats if keep_stats and old is not None else None
        engine = VehicleEngine(self.engine_config, name=vehicle, namespace=namespace, stats=stats)
        if stats is not None:
            stats.resets += 1
        self.fleet.add(engine)  # (replacing the old engine, whose estimator leaves its pool)
        self._new_encoder(vehicle, self.engine_config.prediction.enabled)
        self.malformed.setdefault(vehicle, 0)

    def _new_encoder(self, vehicle: str, predictions: bool) -> None:
        """The output encoder of ``vehicle``, new (at its start, or for new settings). Where its
        ``parameter_labels`` are latched already (:meth:`_latch_parameter_labels`), the new one
        does not send them again: they are published once."""
        encoder = self.encoders[vehicle] = OutputEncoder(self.output_config, vehicle, predictions)
        if encoder.labels_topic in self.publishers_:
            encoder.take_labels()

    def _namespace(self, vehicle: str) -> str:
        """The vehicle's namespace as a recording shows it ('/' for the root): what /diagnostics
        reports, how a report of the recording finds which algorithm made each output, what the
        shards hash, and what places the vehicle's predictions with ``prediction_phase`` 'spread'
        (as ``cloe infer`` places them for the vehicle of that namespace in a bag)."""
        return resolved_namespace(self, vehicle)

    def _ours(self, namespace: str) -> bool:
        """Whether the vehicle of ``namespace`` belongs to this node's shard."""
        return shard_of(namespace, self.shard_count) == self.shard_index

    # ---------------------------------------------------------------------------- the graph

    def _poll_graph(self) -> None:
        """On a steady-clock timer: take up the vehicles discovery finds (``discover``), and
        check that every vehicle has publishers of odom and reference; warn of a vehicle without
        them for ``publisher_timeout`` (with a hint when the un-namespaced vehicle waits while
        namespaced ones fly). Also the heartbeat of :attr:`load`."""
        next_in = self._graph_timer.time_until_next_call()
        self.load.heartbeat(None if next_in is None else next_in / NS)
        now = time.monotonic()
        topics = self.get_topic_names_and_types()
        types = dict(topics)
        if self.discover:
            known = {self.vehicle_ns[v] for v in self.vehicles}
            for ns in graph_namespaces(topics):
                if ns in known or not self._ours(ns) or self._missing_inputs(ns, types):
                    continue
                if ns == '/' and self.get_namespace() != '/':
                    continue  # (un-namespaced topics outside the node's namespace: not a vehicle)
                self._add_vehicle('' if ns == '/' else ns)
                self._discovered.add('' if ns == '/' else ns)
                shard = f' (shard {self.shard_index})' if self.shard_count > 1 else ''
                self.get_logger().info(f'discovered {ns}: inferring it{shard}')
        for v in self.vehicles:
            self._check_doubled(v)
            ns = self.vehicle_ns[v]
            missing = self._missing[v] = self._missing_inputs(ns, types)
            if 'odom' in missing:
                self.engines[v].odometry_unpublished()
            if not missing:
                self._missing_since.pop(v, None)
                self._hinted.discard(v)
                if v in self._warned_missing:
                    self._warned_missing.discard(v)
                    again = ' again' if v in self._odom_heard else ''
                    self.get_logger().info(f'{ns}: odom and reference are published{again}')
                continue
            since = self._missing_since.setdefault(v, now)
            if now - since < self.publisher_timeout or v in self._hinted:
                continue
            flying = self._flying_elsewhere(ns, types)
            if v in self._warned_missing and not flying:
                continue  # (warned; warned again, once, with the hint if vehicles take off)
            self._warned_missing.add(v)
            self.get_logger().warning(self._missing_warning(v, missing, now - since, flying))

    def _check_doubled(self, v: str) -> None:
        """Warn (once, and in /diagnostics) while something else publishes vehicle ``v``'s
        ``cloe/state`` too: another inference node whose shard covers it (two nodes given the
        same ``shard_index``, or different ``shard_count``), or a bag replayed with its outputs."""
        topic = self.encoders[v].state_topic
        others = self.count_publishers(topic) - 1
        if others > 0 and v not in self._doubled:
            self._doubled.add(v)
            self.get_logger().warning(
                f'{self.vehicle_ns[v]}: {others} other publisher(s) of {topic}: is another '
                'inference node inferring this vehicle too? (the nodes of one swarm need the '
                'same shard_count and each its own shard_index)'
            )
        elif others <= 0 and v in self._doubled:
            self._doubled.discard(v)
            self.get_logger().info(f'{self.vehicle_ns[v]}: this node alone publishes {topic}')

    def _missing_inputs(self, namespace: str, types: dict[str, list[str]]) -> list[str]:
        """The inputs of the vehicle of ``namespace`` that nothing publishes as the type the node
        subscribes with (a publisher of another type never matches: :meth:`_wrong_types`).
        ``types``: each topic's types in the graph (``get_topic_names_and_types``), which count
        the subscriptions too; a topic's publishers are asked for theirs only where it has
        another type than the one the node takes."""
        base = namespace.rstrip('/')
        missing = []
        for name, msgtype in INPUT_TYPES.items():
            topic = f'{base}/{name}'
            if types.get(topic) == [msgtype]:
                published = self.count_publishers(topic) > 0
            else:
                published = msgtype in self._publisher_types(topic)
            if not published:
                missing.append(name)
        return missing

    def _publisher_types(self, topic: str) -> set[str]:
        """The types that ``topic`` is published as."""
        return {info.topic_type for info in self.get_publishers_info_by_topic(topic)}

    def _wrong_types(self, v: str, missing: list[str]) -> dict[str, list[str]]:
        """Of vehicle ``v``'s ``missing`` inputs, those published as other types than the node
        takes (a sender of the wrong message), and those types."""
        base = self.vehicle_ns[v].rstrip('/')
        wrong = {}
        for name in missing:
            other = self._publisher_types(f'{base}/{name}') - {INPUT_TYPES[name]}
            if other:
                wrong[name] = sorted(other)
        return wrong

    def _unpublished(
        self, v: str, missing: list[str], wrong: dict[str, list[str]], topics: bool = True
    ) -> str:
        """What vehicle ``v``'s ``missing`` inputs lack: nothing publishes them, or they are
        published as the ``wrong`` types (:meth:`_wrong_types`). Named by their topics, or by the
        inputs' names alone (in the vehicle's own status)."""
        base = self.vehicle_ns[v].rstrip('/')
        absent, parts = [], []
        for name in missing:
            shown = f'{base}/{name}' if topics else name
            if name in wrong:
                parts.append(f'{shown} is published as {" and ".join(wrong[name])}, not as '
                             f'{INPUT_TYPES[name]}')  # fmt: skip
            else:
                absent.append(shown)
        if absent:
            parts.insert(0, f'nothing publishes {" and ".join(absent)}')
        return '; '.join(parts)

    def _missing_warning(self, v: str, missing: list[str], for_s: float, flying: list[str]) -> str:
        """The warning of vehicle ``v``, whose ``missing`` inputs nothing has published for
        ``for_s`` s, with the hint of the namespaces ``flying`` (:meth:`_flying_elsewhere`)."""
        ns = self.vehicle_ns[v]
        wrong = self._wrong_types(v, missing)
        text = f'{ns}: {self._unpublished(v, missing, wrong)} (for {for_s:.0f} s)'
        if len(wrong) == len(missing):
            return text  # (published, as another type: neither hint applies)
        if v in self._discovered or v in self._odom_heard:
            return text + ': the vehicle fell silent'
        if flying:
            self._hinted.add(v)
            shown = ', '.join(flying[:5]) + (', ...' if len(flying) > 5 else '')
            return (
                f'{text}; odom and reference are published under {shown}: set '
                f'vehicles:=[{", ".join(flying)}] or discover:=true'
            )
        given = (f'vehicles: [{", ".join(n or "/" for n in self.listed)}]' if self.listed
                 else 'no vehicles:=[...] given')  # fmt: skip
        return text + (
            f'; is {ns} the namespace of a vehicle that flies? ({given}'
            + ('' if self.discover else '; discover:=true takes the namespaces that publish')
            + ')'
        )

    def _flying_elsewhere(self, ns: str, types: dict[str, list[str]]) -> list[str]:
        """With no ``vehicles`` list and no discovery: the other namespaces that publish odom
        and reference (the vehicles the user likely meant), else []. ``types``: the graph's
        types of each topic."""
        if self.listed or self.discover:
            return []
        return [n for n in graph_namespaces(types.items())
                if n != ns and not self._missing_inputs(n, types)]  # fmt: skip

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
            self._input(vehicle)

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
            self._input(vehicle)

        return callback

    def _plan_callback(self, vehicle: str):
        engine = self.engines

        def callback(raw: bytes) -> None:
            try:
                # the pose count first: a plan beyond the bound is refused undecoded
                too_long = engine[vehicle].refuse_long_plan(messages.path_length(raw))
                if too_long:
                    self._warn_rejections(vehicle)
                    return
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

    def _incompatible_qos(self, topic: str):
        def callback(event) -> None:
            policy = incompatible_policy(event.last_policy_kind)
            self.get_logger().warning(
                f'{self.resolve_topic_name(topic)}: a publisher offers a QoS incompatible with '
                f'the subscription ({policy})'
                + ('; for a best-effort publisher set qos_reliability:=best_effort'
                   if policy == 'reliability' else '')
            )  # fmt: skip

        return callback

    def _input(self, vehicle: str) -> None:
        """Vehicle ``vehicle`` has new input: step it now, or with the others at the next batch.
        Also publishes /diagnostics if a report is due (:meth:`_diagnostics_if_due`)."""
        if time.monotonic() >= self._diag_poll_at:
            self._diag_poll_at = time.monotonic() + self._diag_poll
            self._diagnostics_if_due(DIAGNOSTICS_OVERDUE)
        if self._batch_timer is None:
            self._publish_all(self.fleet.advance([vehicle]))
        else:
            if not self._due:
                self._due_since = time.monotonic()
            self._due[vehicle] = None
            self._inputs += 1
            # a batch at once when every vehicle has new input (or twice as many inputs came as
            # there are vehicles: some are silent), so what waits for the timer stays bounded
            # when the executor serves the inputs before the timer (a node behind its inputs)
            if len(self._due) == len(self.engines) or self._inputs >= 2 * len(self.engines):
                self._step_due()

    def _step_waiting(self) -> None:
        """The batch timer: step the vehicles with new input if the first has waited half a
        ``batch_period`` (so that a tick in the middle of a burst of inputs, the vehicles'
        messages of one instant, does not split it: a vehicle stepped without the others of
        its pool costs a copy of its estimator out of the pool and back)."""
        if self._due and time.monotonic() - self._due_since >= 0.5 * self.batch_period:
            self._step_due()

    def _step_due(self) -> None:
        """The batch: step every vehicle with new input together (Fleet.advance), publish."""
        self._inputs = 0
        if self._due:
            due, self._due = list(self._due), {}
            self._publish_all(self.fleet.advance(due))

    def _publish_all(self, estimates: dict[str, list]) -> None:
        for vehicle, of_vehicle in estimates.items():
            self._publish(vehicle, of_vehicle)

    def _publish(self, vehicle: str, estimates: list) -> None:
        engine = self.engines[vehicle]
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
        """``vehicle``'s status (:func:`~cloe_ros.io.diagnostics.vehicle_status`), with what DDS
        says of its inputs: lost messages, publishers missing for ``publisher_timeout``, how
        long its odometry has been silent."""
        now = time.monotonic()
        missing = self._missing.get(vehicle, [])
        since = self._missing_since.get(vehicle)
        words = ''
        if since is None or now - since < self.publisher_timeout:
            missing = []  # (not for publisher_timeout yet: as the warning and the node's status)
        if missing:
            wrong = self._wrong_types(vehicle, missing)
            words = (f'{self._unpublished(vehicle, missing, wrong, topics=False)} for '
                     f'{now - since:.0f} s')  # fmt: skip
        heard = self._odom_heard.get(vehicle)
        silent = None if heard is None else now - heard
        link = Link(self.lost[vehicle], missing, words, silent, STALE_AFTER)
        ns = self.vehicle_ns[vehicle]
        return vehicle_status(
            f'{self.get_name()}: {ns}', ns, self.engines[vehicle], self.output_config.output_ns,
            last=self._last_estimate.get(vehicle),
            prediction_note=self._last_prediction_note.get(vehicle, ''),
            malformed=self.malformed[vehicle], last_rejected=self._last_rejected.get(vehicle, ''),
            steps_per_s=steps_per_s, link=link,
        )  # fmt: skip

    def node_status(self) -> Status:
        """The node's own status: which vehicles it infers (its shard), those without
        publishers for ``publisher_timeout``, those whose ``cloe/state`` another node publishes
        too, and its load over the last diagnostics period. WARN for any of those, for a shard
        with none of the listed vehicles and no discovery (:attr:`idle`), and from ``BUSY_WARN``
        or ``LATE_WARN``: at its limit, or behind its inputs."""
        now = time.monotonic()
        silent = [self.vehicle_ns[v] for v in self.vehicles if self._missing.get(v)
                  and now - self._missing_since.get(v, now) >= self.publisher_timeout]  # fmt: skip
        names = [self.vehicle_ns[v] for v in self.vehicles]
        message = f'{len(names)} vehicle(s)'
        if self.shard_count > 1:
            message += f', shard {self.shard_index} of {self.shard_count}'
        if self.discover:
            message += ', discovering'
        if silent:
            message += '; without publishers: ' + ', '.join(silent)
        doubled = [self.vehicle_ns[v] for v in self.vehicles if v in self._doubled]
        if doubled:
            message += '; cloe/state also published by another node: ' + ', '.join(doubled)
        if self.idle:
            message += '; none of the listed vehicles is in this shard'
        busy, late, longest = self._load
        overload = self._overload()
        if overload:
            message += '; ' + overload
        values = (
            ('vehicles', ' '.join(names)),
            ('vehicle_count', str(len(names))),
            ('discover', str(self.discover).lower()),
            ('shard_index', str(self.shard_index)),
            ('shard_count', str(self.shard_count)),
            ('without_publishers', ' '.join(silent)),
            ('published_elsewhere_too', ' '.join(doubled)),
            ('busy', f'{busy:.3f}'),
            ('late_s', f'{late:.3f}'),
            ('longest_callback_s', f'{longest:.3f}'),
            ('kernels', self.kernels),
        )
        level = messages.WARN if silent or doubled or self.idle or overload else messages.OK
        return Status(level, self.get_name(), message, self.get_fully_qualified_name(), values)

    def _overload(self) -> str:
        """What the load of the last diagnostics period says, in words ('' if it is fine)."""
        busy, late, _ = self._load
        words = []
        if late >= LATE_WARN:
            words.append(f'behind its inputs by up to {late:.1f} s (its timer ran that late)')
        if busy >= BUSY_WARN:
            words.append(f'busy {busy:.0%} of the time: at its limit')
        if not words:
            return ''
        return '; '.join(words) + (', states come late or are missed (fewer vehicles per node: '
                                   'shard_count)')  # fmt: skip

    def _diagnostics_if_due(self, share: float = DIAGNOSTICS_DUE) -> None:
        """Publish /diagnostics if ``share`` of a ``diagnostics_period`` of the node's clock has
        passed since the last report (or its clock went back). The diagnostics timer calls it
        (``DIAGNOSTICS_DUE``), and so do the inputs (:meth:`_input`, ``DIAGNOSTICS_OVERDUE``):
        rclpy's EventsExecutor queues a timer's turn behind the messages already waiting, so a
        node behind its inputs, whose load is the news, would otherwise report seconds late and
        skip many periods."""
        since = self.get_clock().now().nanoseconds - self._diag_stamp_ns
        if since >= share * self._diag_period_ns or since < 0:
            self._publish_diagnostics()

    def _publish_diagnostics(self) -> None:
        # stamped when it starts, so that the time a report of many vehicles takes to build does
        # not shift the next one
        stamp = self._diag_stamp_ns = self.get_clock().now().nanoseconds
        now = time.monotonic()
        t_prev, steps_prev = self._last_diag
        dt = max(now - t_prev, 1e-9)
        statuses = []
        for v, engine in self.engines.items():
            statuses.append(
                self.vehicle_status(v, (engine.stats.steps - steps_prev.get(v, 0)) / dt)
            )
        self._last_diag = (now, {v: e.stats.steps for v, e in self.engines.items()})
        self._load = self.load.read()
        overload = self._overload()
        if overload and not self._overloaded:
            self.get_logger().warning(f'{len(self.vehicles)} vehicle(s): {overload}')
        elif self._overloaded and not overload:
            self.get_logger().info('keeps up with its inputs again')
        self._overloaded = bool(overload)
        statuses.append(self.node_status())
        self.diagnostics_pub.publish(encode_diagnostics(stamp, statuses))


def main(args=None) -> int:
    return run_node(InferenceNode, args, events=True)


if __name__ == '__main__':
    raise SystemExit(main())
