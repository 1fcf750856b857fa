"""Node ``bag_recorder``: record topics into a rosbag2 bag (MCAP, Jazzy types) that survives kills.

Every ``discovery_period`` the node looks at the ROS graph; each wanted topic whose type is a ROS 2
Jazzy type (and has Python type support installed) gets a raw subscription whose QoS matches its
publishers, and every message goes into the bag as received (CDR bytes, log time = this node's
clock at reception, so ``use_sim_time`` gives sim-time bags). Every ``flush_period`` the pending
chunk goes to the file: a SIGKILL loses at most that much. SIGINT / SIGTERM close the bag
completely. ``/diagnostics`` reports counts every second. A failed write (a full disk) ends the
writing for good: the node keeps counting what it drops, reports ERROR and exits with status 1 when
stopped. See docs/recorder.md.
"""

from __future__ import annotations

import functools
import importlib
import math
import time
from dataclasses import dataclass
from pathlib import Path

from diagnostic_msgs.msg import DiagnosticArray
from rcl_interfaces.msg import SetParametersResult
from rclpy.clock import Clock, ClockType
from rclpy.event_handler import SubscriptionEventCallbacks
from rclpy.node import Node
from rclpy.parameter import Parameter
from rclpy.qos import DurabilityPolicy, QoSProfile, ReliabilityPolicy
from rosbags.interfaces import (
    Qos,
    QosDurability,
    QosHistory,
    QosLiveliness,
    QosReliability,
    QosTime,
)

from cloe_ros.io import messages
from cloe_ros.io.writer import COMPRESSIONS, BagWriter, WriterError
from cloe_ros.ros import common

NODE_NAME = 'bag_recorder'
#: Topics never recorded unless listed in ``topics``.
EXCLUDED_TOPICS = ('/rosout', '/parameter_events')
#: (min, max) of the period parameters, s.
DISCOVERY_RANGE = (0.05, 10.0)
FLUSH_RANGE = (0.05, 1.0)
QOS_DEPTH_RANGE = (1, 100_000)
DIAGNOSTICS_PERIOD = 1.0  # s


def default_output() -> str:
    """``cloe_bag_<YYYYmmdd_HHMMSS>`` (local time), relative to the working directory."""
    return time.strftime('cloe_bag_%Y%m%d_%H%M%S')


def message_class(msgtype: str):
    """The rclpy message class of ``pkg/msg/Name``, or None if it is not installed."""
    parts = msgtype.split('/')
    if len(parts) != 3 or parts[1] != 'msg':
        return None
    try:
        return getattr(importlib.import_module(f'{parts[0]}.msg'), parts[2], None)
    except ImportError:
        return None


def _qos_time(duration) -> QosTime:
    sec, nsec = divmod(int(duration.nanoseconds), 1_000_000_000)
    return QosTime(sec, nsec)


def offered_qos(profile: QoSProfile) -> Qos:
    """A publisher's QoS profile (as the graph reports it) in rosbags' form, for the metadata."""

    def enum(cls, value, unknown):
        try:
            return cls(int(value))
        except ValueError:
            return unknown

    return Qos(
        history=enum(QosHistory, profile.history, QosHistory.UNKNOWN),
        depth=int(profile.depth),
        reliability=enum(QosReliability, profile.reliability, QosReliability.UNKNOWN),
        durability=enum(QosDurability, profile.durability, QosDurability.UNKNOWN),
        deadline=_qos_time(profile.deadline),
        lifespan=_qos_time(profile.lifespan),
        liveliness=enum(QosLiveliness, profile.liveliness, QosLiveliness.UNKNOWN),
        liveliness_lease_duration=_qos_time(profile.liveliness_lease_duration),
        avoid_ros_namespace_conventions=bool(profile.avoid_ros_namespace_conventions),
    )


def matched_qos(profiles) -> tuple[bool, bool]:
    """(reliable, transient_local) of a subscription that matches every one of ``profiles``.

    Reliable only if all publishers are reliable (a reliable subscription does not match a
    best-effort publisher); transient-local only if all are (same rule for durability).
    """
    profiles = list(profiles)
    reliable = bool(profiles) and all(
        p.reliability == ReliabilityPolicy.RELIABLE for p in profiles
    )
    transient_local = bool(profiles) and all(
        p.durability == DurabilityPolicy.TRANSIENT_LOCAL for p in profiles
    )
    return reliable, transient_local


@dataclass
class TopicStats:
    """Counters of one recorded topic."""

    msgtype: str
    reliable: bool
    transient_local: bool
    received: int = 0
    lost: int = 0
    errors: int = 0
    bytes: int = 0  # CDR bytes received


def check_period(value, bounds: tuple[float, float]) -> str | None:
    """Why ``value`` is not a valid period (s), said after the parameter's name, or None."""
    if not isinstance(value, float) or isinstance(value, bool):
        return f'must be a double (seconds), got {value!r}'
    low, high = bounds
    if not math.isfinite(value) or not low <= value <= high:
        return f'must be in [{low}, {high}] s, got {value}'
    return None


class BagRecorder(Node):
    """Record topics into a crash-safe rosbag2 bag. Parameters: see :func:`_declare`."""

    @common.destroyed_if_init_fails
    def __init__(self, **kwargs) -> None:
        super().__init__(NODE_NAME, **kwargs)
        self._writer: BagWriter | None = None
        self._closed = False
        #: why the bag is not complete (a write failure, or closing it failed), or None
        self.failed: str | None = None
        self._declare()
        self._stats: dict[str, TopicStats] = {}
        self._recorded_subs: dict[str, object] = {}
        self._skipped: dict[str, str] = {}
        self._type_conflicts: set[str] = set()
        self._publisher_gids: dict[str, set[tuple]] = {}  # endpoint GIDs seen per recorded topic
        self._flush_errors = 0
        try:
            self._writer = BagWriter(Path(self.output), self.compression)
        except WriterError as err:
            raise common.ParameterError(str(err), 'output') from err
        self._steady = Clock(clock_type=ClockType.STEADY_TIME)
        self._diag_pub = self.create_publisher(DiagnosticArray, '/diagnostics', 10)
        self._discovery_timer = self._wall_timer(self.discovery_period, self._discover)
        self._flush_timer = self._wall_timer(self.flush_period, self._flush)
        self._diag_timer = self._wall_timer(DIAGNOSTICS_PERIOD, self._publish_diagnostics)
        self.add_on_set_parameters_callback(self._on_set_parameters)
        self.add_post_set_parameters_callback(self._after_set_parameters)
        wanted = ', '.join(self.topics) if self.topics else 'all topics'
        self.get_logger().info(
            f'recording to {self.output} ({wanted}; compression {self.compression}; '
            f'flush every {self.flush_period} s)'
        )
        self._discover()

    def _wall_timer(self, period: float, callback):
        """A timer on the steady clock: discovery, flushing and diagnostics go on when the ROS
        clock is simulated and stands still (use_sim_time with a paused simulation or player)."""
        return self.create_timer(period, callback, clock=self._steady)

    # -- parameters ----------------------------------------------------------------------------

    def _declare(self) -> None:
        d = common.describe
        self.output = common.declare(
            self,
            'output',
            default_output(),
            d(
                'bag directory to create (relative to the working directory); must not exist. '
                'Default cloe_bag_<YYYYmmdd_HHMMSS>',
                read_only=True,
            ),
        )
        topics = common.declare(
            self,
            'topics',
            Parameter.Type.STRING_ARRAY,
            d(
                'topics to record (relative names resolve in the node namespace); '
                'empty or unset = every topic except /rosout and /parameter_events',
                read_only=True,
            ),
        )
        self.discovery_period = common.declare(
            self,
            'discovery_period',
            0.2,
            d('period of the topic discovery, s', float_range=DISCOVERY_RANGE),
        )
        self.flush_period = common.declare(
            self,
            'flush_period',
            0.5,
            d(
                'period of flushing the bag to the OS, s: the most data a SIGKILL can lose',
                float_range=FLUSH_RANGE,
            ),
        )
        self.compression = common.declare(
            self,
            'compression',
            'zstd',
            d(
                'MCAP chunk compression',
                read_only=True,
                additional_constraints='one of: zstd, none',
            ),
        )
        self.qos_depth = common.declare(
            self,
            'qos_depth',
            1000,
            d(
                'history depth (messages) of each subscription',
                read_only=True,
                int_range=QOS_DEPTH_RANGE,
            ),
        )
        if not isinstance(self.output, str) or not self.output.strip():
            # `output:="  "` reaches rclpy as YAML null: no value at all
            raise common.ParameterError('must name a bag directory', 'output')
        if self.compression not in COMPRESSIONS:
            reason = f'{self.compression!r} is not one of {", ".join(COMPRESSIONS)}'
            raise common.ParameterError(reason, 'compression')
        for name, bounds in (('discovery_period', DISCOVERY_RANGE), ('flush_period', FLUSH_RANGE)):
            reason = check_period(getattr(self, name), bounds)
            if reason:
                raise common.ParameterError(reason, name)
        self.topics: list[str] = []
        for t in topics or []:
            try:
                self.topics.append(self.resolve_topic_name(t))
            except Exception as err:  # rclpy raises several types for invalid names
                reason = f'{t!r} is not a valid topic name: {err}'
                raise common.ParameterError(reason, 'topics') from err

    def _on_set_parameters(self, params: list[Parameter]) -> SetParametersResult:
        # read-only parameters never get here: rclpy refuses them first (their descriptors say so)
        for p in params:
            if p.name == 'discovery_period':
                reason = check_period(p.value, DISCOVERY_RANGE)
            elif p.name == 'flush_period':
                reason = check_period(p.value, FLUSH_RANGE)
            else:
                reason = None
            if reason:
                return common.refuse(f'{p.name} {reason}')
        return common.accept()

    def _after_set_parameters(self, params: list[Parameter]) -> None:
        for p in params:
            if p.name == 'discovery_period':
                self.discovery_period = p.value
                self.destroy_timer(self._discovery_timer)
                self._discovery_timer = self._wall_timer(p.value, self._discover)
            elif p.name == 'flush_period':
                self.flush_period = p.value
                self.destroy_timer(self._flush_timer)
                self._flush_timer = self._wall_timer(p.value, self._flush)

    # -- discovery and subscriptions -----------------------------------------------------------

    def _wanted(self, topic: str) -> bool:
        if self.topics:
            return topic in self.topics
        return topic not in EXCLUDED_TOPICS

    def _skip(self, topic: str, reason: str) -> None:
        if topic not in self._skipped:
            self._skipped[topic] = reason
            self.get_logger().warning(f'not recording {topic}: {reason}')

    def _discover(self) -> None:
        if self._closed or self._writer.error is not None:
            return
        for topic, types in self.get_topic_names_and_types():
            if not self._wanted(topic) or topic in self._skipped:
                continue
            stats = self._stats.get(topic)
            if stats is None and len(types) != 1:
                self._skip(topic, f'published with several types {", ".join(types)}')
                continue
            msgtype = stats.msgtype if stats is not None else types[0]
            if len(types) > 1 and topic not in self._type_conflicts:
                self._type_conflicts.add(topic)
                self.get_logger().warning(
                    f'{topic} is now also published as '
                    f'{", ".join(t for t in types if t != msgtype)}: recording only {msgtype}'
                )
            pubs = [p for p in self.get_publishers_info_by_topic(topic) if p.topic_type == msgtype]
            if not pubs:
                continue  # only subscribers so far
            profiles = [p.qos_profile for p in pubs]
            reliable, transient_local = matched_qos(profiles)
            if stats is None:
                self._subscribe(topic, msgtype, profiles, reliable, transient_local)
                if topic in self._stats:
                    self._publisher_gids[topic] = {tuple(p.endpoint_gid) for p in pubs}
                continue
            self._note_publishers(topic, pubs)
            if (stats.reliable and not reliable) or (
                stats.transient_local and not transient_local
            ):
                # a publisher with weaker QoS joined: a stricter subscription would not match it
                self.get_logger().info(
                    f'{topic}: resubscribing as {"reliable" if reliable else "best effort"}, '
                    f'{"transient local" if transient_local else "volatile"} to match a new '
                    'publisher'
                )
                self.destroy_subscription(self._recorded_subs.pop(topic))
                self._subscribe(topic, msgtype, profiles, reliable, transient_local)

    def _note_publishers(self, topic: str, pubs) -> None:
        """Offered QoS of publishers that joined a recorded topic, for metadata.yaml."""
        seen = self._publisher_gids.setdefault(topic, set())
        new = [p for p in pubs if tuple(p.endpoint_gid) not in seen]
        if new:
            seen.update(tuple(p.endpoint_gid) for p in new)
            self._writer.add_offered_qos(topic, [offered_qos(p.qos_profile) for p in new])

    def _subscribe(self, topic, msgtype, profiles, reliable: bool, transient_local: bool) -> None:
        if msgtype not in messages.typestore().types:
            self._skip(topic, f'type {msgtype} is not a ROS 2 Jazzy type known to rosbags')
            return
        cls = message_class(msgtype)
        if cls is None:
            self._skip(topic, f'no Python type support for {msgtype} is installed')
            return
        if topic not in self._stats:
            try:
                self._writer.add_topic(topic, msgtype, [offered_qos(p) for p in profiles])
            except WriterError as err:
                self._skip(topic, str(err))
                return
            self._stats[topic] = TopicStats(msgtype, reliable, transient_local)
        stats = self._stats[topic]
        stats.reliable, stats.transient_local = reliable, transient_local
        qos = common.qos(reliable=reliable, depth=self.qos_depth, transient_local=transient_local)
        events = SubscriptionEventCallbacks(message_lost=functools.partial(self._on_lost, topic))
        self._recorded_subs[topic] = self.create_subscription(
            cls,
            topic,
            functools.partial(self._on_message, topic),
            qos,
            raw=True,
            event_callbacks=events,
        )
        self.get_logger().info(
            f'recording {topic} ({msgtype}, {"reliable" if reliable else "best effort"}, '
            f'{"transient local" if transient_local else "volatile"})'
        )

    # -- callbacks -----------------------------------------------------------------------------

    def _on_message(self, topic: str, data: bytes) -> None:
        stats = self._stats[topic]
        stats.received += 1
        stats.bytes += len(data)
        if self._closed or self._writer.error is not None:
            return  # after a write failure: dropped, counted as received - written
        try:
            self._writer.write(topic, self.get_clock().now().nanoseconds, data)
        except WriterError as err:
            stats.errors += 1
            self._write_failed(f'cannot write a message of {topic}: {err}')

    def _on_lost(self, topic: str, info) -> None:
        self._stats[topic].lost += int(info.total_count_change)

    def _flush(self) -> None:
        if self._closed:
            return
        try:
            self._writer.flush()
        except WriterError as err:
            self._flush_errors += 1
            self._write_failed(f'cannot flush the bag: {err}')

    def _write_failed(self, text: str) -> None:
        if self._writer.error is None:  # one message refused (not a failure of the file)
            self.get_logger().error(text, throttle_duration_sec=5.0)
            return
        # the file failed (a full disk): the writer stopped for good and holds nothing any more
        self.failed = f'cannot write bag {self.output}: {self._writer.error}'
        self.get_logger().error(
            f'{text}. Messages received from now on are dropped (counted in /diagnostics); stop '
            f'the recorder, free space and run `cloe bag recover {self.output}`'
        )

    def _diagnostics(self) -> messages.Status:
        """The recorder's DiagnosticStatus: counts per topic and in total."""
        values: list[tuple[str, str]] = []
        dropped = self._dropped()
        for topic in sorted(self._stats):
            s = self._stats[topic]
            values += [
                (f'{topic} received', str(s.received)),
                (f'{topic} lost', str(s.lost)),
                (f'{topic} dropped', str(dropped[topic])),
                (f'{topic} bytes', str(s.bytes)),
            ]
        written = self._writer.message_count if self._writer else 0
        lost = sum(s.lost for s in self._stats.values())
        errors = sum(s.errors for s in self._stats.values()) + self._flush_errors
        values += [
            ('messages', str(written)),
            ('lost', str(lost)),
            ('dropped', str(sum(dropped.values()))),
            ('write errors', str(errors)),
            ('bytes', str(sum(s.bytes for s in self._stats.values()))),
            ('chunks', str(self._writer.chunk_count if self._writer else 0)),
            ('skipped topics', str(len(self._skipped))),
        ]
        if self.failed:
            values.append(('failure', self.failed))
        if self._skipped:
            values.append(('skipped', '; '.join(f'{t}: {r}' for t, r in self._skipped.items())))
        missing = [t for t in self.topics if t not in self._stats and t not in self._skipped]
        if missing:
            values.append(('waiting for', ', '.join(missing)))
        if self.failed:
            level = messages.ERROR
            text = f'not writing: {self.failed}; {sum(dropped.values())} messages dropped'
        elif errors:
            level, text = messages.ERROR, f'{errors} write errors'
        elif lost or self._skipped or missing:
            level, text = messages.WARN, f'recording {len(self._stats)} topics with warnings'
        else:
            level, text = messages.OK, f'recording {len(self._stats)} topics'
        return messages.Status(level, f'{NODE_NAME}: {self.output}', text, '', tuple(values))

    def _publish_diagnostics(self) -> None:
        if self._closed:
            return
        stamp = self.get_clock().now().nanoseconds
        self._diag_pub.publish(messages.encode_diagnostics(stamp, [self._diagnostics()]))

    def _dropped(self) -> dict[str, int]:
        """Messages received but not in the bag, per topic: refused by the writer, or lost with
        the file after a write failure."""
        written = self._writer.topic_counts if self._writer else {}
        return {t: max(s.received - written.get(t, 0), 0) for t, s in self._stats.items()}

    def summary(self) -> str:
        """One line: messages received, written, lost in DDS and dropped, per topic and in total.
        After a write failure "written" counts the messages that reached the file before it."""
        written = self._writer.topic_counts if self._writer else {}
        dropped = self._dropped()
        parts = [
            f'{t} {s.received} received/{written.get(t, 0)} written'
            + (f'/{s.lost} lost' if s.lost else '')
            + (f'/{dropped[t]} dropped' if dropped[t] else '')
            for t, s in sorted(self._stats.items())
        ]
        total = sum(written.values())
        lost = sum(s.lost for s in self._stats.values())
        n_dropped = sum(dropped.values())
        counts = f'{lost} lost' + (f', {n_dropped} dropped' if n_dropped else '')
        return f'recorded {total} messages ({counts}) to {self.output}: ' + (
            ', '.join(parts) if parts else 'no topics'
        )

    # -- shutdown ------------------------------------------------------------------------------

    def close(self) -> str | None:
        """Finish the bag (pending chunk, summary, metadata.yaml). Idempotent.

        Returns the summary line (None if already closed). If the bag could not be finished
        (a write failure before, or now), :attr:`failed` says why.
        """
        if self._closed or self._writer is None:
            return None
        self._closed = True
        try:
            self._writer.close()
        except WriterError as err:
            self.failed = str(err)
        return self.summary()

    def destroy_node(self) -> None:
        logger = self.get_logger()
        line = self.close()
        super().destroy_node()
        # logged once the node is gone: after SIGINT the context is shut down already and the
        # node's /rosout publisher could not take the line
        if line and self.failed:
            logger.error(self.failed)
        if line:
            logger.info(line)


def main(args: list[str] | None = None) -> int:
    """Run the node; exit status 1 also when the bag could not be finished (:attr:`failed`)."""
    nodes: list[BagRecorder] = []

    def make() -> BagRecorder:
        nodes.append(BagRecorder())
        return nodes[-1]

    status = common.run_node(make, args)
    if status == 0 and nodes and nodes[0].failed:
        status = 1
    return status


if __name__ == '__main__':
    raise SystemExit(main())
