"""``cloe live``'s relay: ROS 2 topics to the Foxglove app over its WebSocket protocol.

A node (``cloe_live``) discovers the topics of its DDS domain every ``discovery_period`` (wall
time) and subscribes to every topic with a publisher (or to the ones asked for), as raw CDR. Each
becomes a channel of a Foxglove WebSocket server (``foxglove-sdk``): message encoding ``cdr``,
schema encoding ``ros2msg`` with the type's full message definition (the text MCAP embeds), so
the app decodes the messages as it does a bag's. Messages are relayed as they arrive, stamped
with their receive time (the wall clock; the app's 3D panel uses the header stamps).

The subscription's QoS follows the publishers', as the recorder's does: reliable unless one of
them is best effort, transient local if all of them are (a latched ``true_parameters`` arrives).
The WebSocket protocol has no latching: the last message of a transient-local topic is sent again
whenever a client subscribes to its channel (:class:`Latch`), so a client that connects late still
gets it.
"""

from __future__ import annotations

import threading
import time
from collections.abc import Callable, Iterable

import foxglove
from foxglove.websocket import ServerListener
from rclpy.clock import Clock, ClockType
from rclpy.node import Node
from rclpy.qos import DurabilityPolicy, ReliabilityPolicy

from cloe_ros.io.messages import typestore
from cloe_ros.ros import common
from cloe_ros.ros.player_node import message_class

#: Topics of the ROS graph itself, never relayed unless asked for.
SKIPPED = ('/rosout', '/parameter_events')


def message_definition(msgtype: str) -> str | None:
    """The ``ros2msg`` definition of ``msgtype`` with its dependencies (None: type unknown)."""
    try:
        text, _ = typestore().generate_msgdef(msgtype, ros_version=2)
    except Exception:  # rosbags raises its own errors for types it does not know
        return None
    return text


class Latch(ServerListener):
    """The last message of each transient-local topic, sent again when a client subscribes.

    Pass it as the server's ``server_listener``; the relay's timer calls :meth:`resend`, so
    nothing is logged from inside the server's callback."""

    def __init__(self) -> None:
        self._last: dict[str, tuple[foxglove.Channel, bytes]] = {}
        self._due: list[str] = []
        self._lock = threading.Lock()

    def keep(self, topic: str, channel: foxglove.Channel, raw: bytes) -> None:
        with self._lock:
            self._last[topic] = (channel, raw)

    def on_subscribe(self, client, channel) -> None:
        with self._lock:
            self._due.append(channel.topic)

    def resend(self) -> None:
        with self._lock:
            due, self._due = self._due, []
            last = [self._last[t] for t in due if t in self._last]
        for channel, raw in last:
            channel.log(raw, log_time=time.time_ns())


class LiveRelay(Node):
    """Relays topics into the channels of ``server_context`` (a ``foxglove.Context`` served by a
    WebSocket server). ``topics``: the topics to relay (None: every topic with a publisher,
    except /rosout and /parameter_events). ``latch``: the server's listener that repeats
    transient-local messages to late subscribers. ``on_channel(topic, msgtype)`` is called for
    every channel made. ``relayed`` counts the messages per topic."""

    @common.destroyed_if_init_fails
    def __init__(
        self,
        server_context: foxglove.Context,
        topics: Iterable[str] | None = None,
        discovery_period: float = 1.0,
        latch: Latch | None = None,
        on_channel: Callable[[str, str], None] | None = None,
        **kwargs,
    ) -> None:
        super().__init__('cloe_live', **kwargs)
        self._fox = server_context
        self._wanted = None if topics is None else set(topics)
        self._on_channel = on_channel
        self.channels: dict[str, foxglove.Channel] = {}
        self.relayed: dict[str, int] = {}
        self._skipped: set[str] = set()
        self._latch = latch
        steady = Clock(clock_type=ClockType.STEADY_TIME)
        self._timer = self.create_timer(discovery_period, self._discover, clock=steady)
        if latch is not None:
            self._latch_timer = self.create_timer(0.05, latch.resend, clock=steady)
        self._discover()

    def _discover(self) -> None:
        for name, types in self.get_topic_names_and_types():
            if name in self.channels or name in self._skipped:
                continue
            if self._wanted is None and name in SKIPPED:
                continue
            if self._wanted is not None and name not in self._wanted:
                continue
            publishers = self.get_publishers_info_by_topic(name)
            if not publishers:
                continue  # subscribers only: wait for a publisher, and follow its QoS
            if len(types) != 1:
                self._skip(name, f'published with several types ({", ".join(types)})')
                continue
            msgtype = types[0]
            definition = message_definition(msgtype)
            cls = message_class(msgtype)
            if definition is None or cls is None:
                self._skip(name, f'{msgtype} is not a type this relay knows')
                continue
            self._relay(name, msgtype, definition, cls, publishers)

    def _skip(self, name: str, reason: str) -> None:
        self._skipped.add(name)
        self.get_logger().warning(f'not relaying {name}: {reason}')

    def _relay(self, name: str, msgtype: str, definition: str, cls, publishers) -> None:
        reliable = all(
            p.qos_profile.reliability != ReliabilityPolicy.BEST_EFFORT for p in publishers
        )
        latched = all(
            p.qos_profile.durability == DurabilityPolicy.TRANSIENT_LOCAL for p in publishers
        )
        schema = foxglove.Schema(name=msgtype, encoding='ros2msg', data=definition.encode())
        channel = foxglove.Channel(name, schema=schema, message_encoding='cdr', context=self._fox)
        self.channels[name] = channel
        self.relayed[name] = 0

        latch = self._latch if latched else None

        def forward(raw: bytes) -> None:
            data = bytes(raw)
            channel.log(data, log_time=time.time_ns())
            self.relayed[name] += 1
            if latch is not None:
                latch.keep(name, channel, data)

        self.create_subscription(cls, name, forward, common.qos(reliable, 10, latched), raw=True)
        if self._on_channel is not None:
            self._on_channel(name, msgtype)


def serve(host: str, port: int, topics: list[str] | None, print_line=print) -> int:
    """Start the WebSocket server and the relay on the domain of ``ROS_DOMAIN_ID``; relay until
    Ctrl-C / SIGTERM. Returns the exit status. ``OSError`` when the port cannot be served."""
    import rclpy
    from rclpy.executors import ExternalShutdownException, SingleThreadedExecutor

    context = foxglove.Context()
    latch = Latch()
    try:
        server = foxglove.start_server(
            name='cloe live', host=host, port=port, context=context, server_listener=latch
        )
    except Exception as err:  # the SDK raises its own error for a port in use
        raise OSError(f'cannot serve on {host}:{port}: {err}') from err
    rclpy.init(args=['cloe_live'])
    relay = None
    try:
        relay = LiveRelay(
            context, topics, latch=latch,
            on_channel=lambda name, msgtype: print_line(f'relaying {name} ({msgtype})'),
        )  # fmt: skip
        print_line(
            f'serving ws://{host}:{server.port} (in the Foxglove app: Open connection, Foxglove '
            'WebSocket); Ctrl-C stops'
        )
        executor = SingleThreadedExecutor()
        executor.add_node(relay)
        executor.spin()
    except (KeyboardInterrupt, ExternalShutdownException):
        pass
    finally:
        if relay is not None:
            counts = ', '.join(f'{t} {n}' for t, n in sorted(relay.relayed.items()))
            print_line(f'relayed: {counts or "nothing"}')
            relay.destroy_node()
        rclpy.try_shutdown()
        server.stop()
    return 0
