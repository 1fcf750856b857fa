"""Node ``bag_player``: publish a recorded bag with its original timing.

A recording replayed through the inference node (or anything else) sees the same messages, byte for
byte, spaced as they were recorded: message *i* goes out at wall time
``t_start + (log_time_i - bag_start) / rate``. Messages are published in log-time order, so every
topic keeps its recorded order. Optionally ``/clock`` carries the bag's log time, like
``ros2 bag play --clock``. As ``ros2 bag play`` it can start ``start_offset`` seconds into the
bag, ``loop`` (every pass from the same start), and pause and resume by service (``~/pause``,
``~/resume``, ``~/toggle_paused``, ``~/is_paused``, std_srvs/Trigger: rosbag2's names, with
std_srvs types instead of rosbag2_interfaces). See docs/player.md for the parameters, what
``/clock`` does on a loop or a pause, and the measured timing jitter.

Threads: the executor (parameters, services) spins in the main thread; one thread reads the bag
ahead into a bounded buffer and one publishes on schedule (rclpy publishers are thread-safe). The
reader runs ahead so that decoding a chunk never delays a publication.
"""

from __future__ import annotations

import gc
import importlib
import math
import sys
import threading
import time
from array import array
from collections import deque
from typing import TYPE_CHECKING

import numpy as np
import rclpy
from rclpy.duration import Duration
from rclpy.node import Node
from rclpy.parameter import Parameter
from rosbags.interfaces import QosDurability, QosReliability
from rosgraph_msgs.msg import Clock
from std_srvs.srv import Trigger

from cloe_ros.io.messages import encode_clock
from cloe_ros.io.reader import BagError, BagReader, qos_profiles
from cloe_ros.ros import common

if TYPE_CHECKING:
    from collections.abc import Sequence

    from rcl_interfaces.msg import SetParametersResult
    from rclpy.publisher import Publisher
    from rosbags.interfaces import Qos

NS = common.NS
#: Messages (and payload bytes) read ahead of the publisher: several MCAP chunks (1 MiB each), so
#: the next chunk is decoded while the buffer still holds the previous ones.
READ_AHEAD_MESSAGES = 20_000
READ_AHEAD_BYTES = 64 * 2**20
#: Waits longer than this sleep on the condition (woken by a rate change or shutdown); the rest is
#: one short ``time.sleep``.
COARSE_WAIT_S = 0.002
#: How long the end of playback waits for reliable subscribers to acknowledge the last messages
#: (the default of ``ack_timeout``): longer than Fast DDS's default heartbeat period (3 s).
ACK_TIMEOUT_S = 3.5
_END = object()
#: Between two passes of a looping player: the next pass starts again from ``start_offset``.
_PASS_END = object()
#: Longest single wait while paused (a resume, a rate change or a stop wakes it earlier).
PAUSED_WAIT_S = 0.5


def message_class(msgtype: str):
    """The Python class of ``pkg/msg/Name`` (None when its package is not installed)."""
    parts = msgtype.split('/')
    if len(parts) == 2:  # ROS 1 style pkg/Name
        parts = [parts[0], 'msg', parts[1]]
    if len(parts) != 3:
        return None
    try:
        module = importlib.import_module(f'{parts[0]}.{parts[1]}')
    except ImportError:
        return None
    return getattr(module, parts[2], None)


def playback_qos(profiles: Sequence[Qos]) -> tuple[bool, bool]:
    """``(reliable, transient_local)`` to offer, adapted to the recorded publishers' QoS like
    ``ros2 bag play``: best effort if any recorded publisher was, transient local only if all
    were. Without recorded profiles: reliable, volatile."""
    if not profiles:
        return True, False
    reliable = all(p.reliability != QosReliability.BEST_EFFORT for p in profiles)
    transient_local = all(p.durability == QosDurability.TRANSIENT_LOCAL for p in profiles)
    return reliable, transient_local


class ReadAhead:
    """FIFO between the reading and the publishing thread, bounded in messages and bytes.

    Once full, the reader waits until the buffer is half empty, so it refills in bursts instead of
    waking for every message taken. ``get`` returns the end marker once closed.
    """

    def __init__(self, max_items: int, max_bytes: int) -> None:
        self.max_items, self.max_bytes = max_items, max_bytes
        self._items: deque = deque()
        self._bytes = 0
        self._refill = True
        self._closed = False
        self._cond = threading.Condition()

    def put(self, item, size: int) -> bool:
        """Append ``item`` of ``size`` bytes; False when closed."""
        with self._cond:
            while not self._closed and self._items and not self._room(size):
                self._cond.wait()
            if self._closed:
                return False
            self._items.append((item, size))
            self._bytes += size
            self._cond.notify_all()
            return True

    def _room(self, size: int) -> bool:
        if len(self._items) >= self.max_items or self._bytes + size > self.max_bytes:
            self._refill = False
        elif 2 * len(self._items) <= self.max_items and 2 * self._bytes <= self.max_bytes:
            self._refill = True
        return self._refill

    def get(self):
        with self._cond:
            while not self._closed and not self._items:
                self._cond.wait()
            if self._closed:
                return _END
            item, size = self._items.popleft()
            self._bytes -= size
            if not self._refill and 2 * len(self._items) <= self.max_items:
                self._cond.notify_all()
            return item

    def close(self) -> None:
        with self._cond:
            self._closed = True
            self._cond.notify_all()


class PlayerNode(Node):
    """Publishes a bag. ``finished`` is set when playback has ended (or stopped), ``failed`` when
    it stopped because of a damaged bag, ``published`` counts the messages sent so far (over
    every pass), ``passes`` the passes begun (more than one with ``loop``)."""

    @common.destroyed_if_init_fails
    def __init__(self, **kwargs) -> None:
        super().__init__('bag_player', **kwargs)
        self.failed = False
        self.finished = threading.Event()
        self.published = 0
        self.passes = 0
        self._cond = threading.Condition()
        self._stopping = False
        self._playing = False
        self._paused = False
        self._paused_at = 0  # bag log time (ns) where a pause holds playback
        self._rate = 1.0
        self._anchor = (0.0, 0)  # (wall time perf_counter s, bag log time ns) while playing
        self._exit_when_done = True
        self._bag: BagReader | None = None
        self._threads: list[threading.Thread] = []
        self.add_on_set_parameters_callback(self._check_parameters)
        self.add_post_set_parameters_callback(self._apply_parameters)
        self._declare_parameters()
        self._open_bag()
        self._create_publishers()
        for name, handler in (
            ('pause', self._pause_service),
            ('resume', self._resume_service),
            ('toggle_paused', self._toggle_service),
            ('is_paused', self._is_paused_service),
        ):
            self.create_service(Trigger, f'~/{name}', handler)
        if self._start_paused:
            self._pause()
        self._buffer = ReadAhead(READ_AHEAD_MESSAGES, READ_AHEAD_BYTES)
        for target, name in ((self._read, 'bag_reader'), (self._play, 'bag_publisher')):
            thread = threading.Thread(target=target, name=name, daemon=True)
            self._threads.append(thread)
            thread.start()

    # -- parameters ----------------------------------------------------------------------------

    def _declare_parameters(self) -> None:
        d, ro = common.describe, True
        self.bag_path = common.declare(
            self, 'bag', '', d('rosbag2 directory (or .mcap file) to play; required', read_only=ro)
        )
        common.declare(
            self,
            'rate',
            1.0,
            d(
                'playback speed factor: 2.0 plays twice as fast; may be changed while playing',
                float_range=(0.0, 100.0),
                additional_constraints='0 < rate <= 100',
            ),
        )
        topics = common.declare(
            self,
            'topics',
            Parameter.Type.STRING_ARRAY,
            d('topics to play; empty: all topics of the bag', read_only=ro),
        )
        self.topic_names = list(topics or [])
        self.publish_clock = common.declare(
            self,
            'publish_clock',
            False,
            d('publish /clock (rosgraph_msgs/Clock) with the bag log time', read_only=ro),
        )
        self.clock_rate = common.declare(
            self,
            'clock_rate',
            100.0,
            d('/clock publishing rate, Hz (wall time)', read_only=ro, float_range=(1.0, 1000.0)),
        )
        self.wait_for_subscribers = common.declare(
            self,
            'wait_for_subscribers',
            0,
            d(
                'before playing, wait until every played topic has this many matched '
                'subscriptions',
                read_only=ro,
                int_range=(0, 100),
            ),
        )
        self.wait_timeout = common.declare(
            self,
            'wait_timeout',
            10.0,
            d(
                'longest wait for subscribers, s; then play anyway with a warning',
                read_only=ro,
                float_range=(0.0, 3600.0),
            ),
        )
        self.start_delay = common.declare(
            self,
            'start_delay',
            0.0,
            d(
                'delay before playing (after the wait for subscribers), s',
                read_only=ro,
                float_range=(0.0, 3600.0),
            ),
        )
        self.loop = common.declare(
            self,
            'loop',
            False,
            d(
                'play the bag again and again (every pass from start_offset) until stopped; '
                '/clock jumps back at each new pass',
                read_only=ro,
            ),
        )
        self.start_offset = common.declare(
            self,
            'start_offset',
            0.0,
            d(
                'start playing this many s into the bag (log time after its first message); '
                'earlier messages are skipped',
                read_only=ro,
                float_range=(0.0, 1e9),
            ),
        )
        self._start_paused = common.declare(
            self,
            'start_paused',
            False,
            d(
                'start paused: nothing is published until ~/resume (or ~/toggle_paused)',
                read_only=ro,
            ),
        )
        common.declare(
            self,
            'exit_when_done',
            True,
            d('shut the process down (status 0) when the bag is finished'),
        )
        self.qos_depth = common.declare(
            self,
            'qos_depth',
            1000,
            d('history depth of the publishers', read_only=ro, int_range=(1, 1_000_000)),
        )
        self.ack_timeout = common.declare(
            self,
            'ack_timeout',
            ACK_TIMEOUT_S,
            d(
                'at the end of playback (also of a damaged bag), the longest wait for reliable '
                'subscribers to acknowledge the last messages, s',
                read_only=ro,
                float_range=(0.0, 3600.0),
            ),
        )
        if not isinstance(self.bag_path, str) or not self.bag_path.strip():
            # -p "bag:=  " reaches rclpy as YAML null: a parameter without a value
            raise common.ParameterError(
                "parameter 'bag' is required: pass the bag to play, e.g. -p bag:=/path/to/bag"
            )

    def _check_parameters(self, params: list[Parameter]) -> SetParametersResult:
        for p in params:
            if p.name == 'rate' and not (0.0 < p.value <= 100.0):
                return common.refuse(
                    f'rate must be in (0, 100] (a speed factor, 1.0 = recorded speed), '
                    f'got {p.value}'
                )
        return common.accept()

    def _apply_parameters(self, params: list[Parameter]) -> None:
        for p in params:
            if p.name == 'rate':
                self._set_rate(float(p.value))
            elif p.name == 'exit_when_done':
                self._exit_when_done = bool(p.value)

    def _set_rate(self, rate: float) -> None:
        """Change the speed; while playing, the bag time reached now stays where it is."""
        with self._cond:
            if self._playing:
                now = time.perf_counter()
                self._anchor = (now, self._bag_time(now))
            self._rate = rate
            self._cond.notify_all()

    # -- set-up --------------------------------------------------------------------------------

    def _open_bag(self) -> None:
        bag = BagReader(self.bag_path)
        try:
            bag.open()
        except BagError as err:
            raise common.ParameterError(str(err)) from err
        self._bag = bag
        if self.topic_names:
            unknown = [t for t in self.topic_names if t not in bag.topics]
            if unknown:
                bag.close()
                reason = (
                    f'{", ".join(unknown)} not in {bag.path} (it has '
                    f'{", ".join(bag.topics) or "no topics"})'
                )
                raise common.ParameterError(reason, 'topics')
        if bag.message_count and self.start_offset > bag.duration_s:
            bag.close()
            reason = (
                f'{self.start_offset:g} s is past the end of {bag.path} (it spans '
                f'{bag.duration_s:.3f} s)'
            )
            raise common.ParameterError(reason, 'start_offset')
        self._first_ns = bag.start_ns + round(self.start_offset * NS)

    def _create_publishers(self) -> None:
        bag = self._bag
        assert bag is not None
        self._publishers_by_topic: dict[str, Publisher] = {}
        for name in self.topic_names or list(bag.topics):
            info = bag.topics[name]
            cls = message_class(info.msgtype)
            if cls is None:
                self.get_logger().warning(
                    f'skipping {name}: the Python package of {info.msgtype} is not installed'
                )
                continue
            try:
                reliable, transient_local = playback_qos(qos_profiles(info.offered_qos))
            except BagError as err:
                self.get_logger().warning(f'{name}: {err}; offering reliable, volatile')
                reliable, transient_local = True, False
            qos = common.qos(reliable, self.qos_depth, transient_local)
            self._publishers_by_topic[name] = self.create_publisher(cls, name, qos)
        if not bag.topics:
            bag.close()
            raise common.ParameterError(f'{bag.path}: nothing to play: the bag has no topics')
        if not self._publishers_by_topic:
            bag.close()
            raise common.ParameterError(f'{bag.path}: nothing to play (no topic can be published)')
        self._played = sorted(self._publishers_by_topic)
        self._clock_pub = (
            self.create_publisher(Clock, '/clock', common.qos(True, 100))
            if self.publish_clock
            else None
        )

    # -- the reading thread --------------------------------------------------------------------

    def _read(self) -> None:
        """Every pass of the bag into the buffer (messages before ``start_offset`` skipped), with
        ``_PASS_END`` between passes when looping, then ``_END``."""
        assert self._bag is not None
        first = self._first_ns
        try:
            while True:
                played = 0
                for item in self._bag.messages(self._played):
                    if item[1] < first:
                        continue
                    if not self._buffer.put(item, len(item[2])):
                        return
                    played += 1
                if not (self.loop and played):  # (a pass without messages would spin)
                    break
                if not self._buffer.put(_PASS_END, 0):
                    return
            self._buffer.put(_END, 0)
        except BagError as err:
            self._buffer.put(err, 0)

    # -- the publishing thread -----------------------------------------------------------------

    def _bag_time(self, wall: float) -> int:
        """The bag log time reached at ``wall`` (held where it is while paused)."""
        if self._paused:
            return self._paused_at
        wall0, bag0 = self._anchor
        return bag0 + round((wall - wall0) * self._rate * NS)

    def _wall_time(self, log_ns: int) -> float:
        """When ``log_ns`` is due (never, while paused)."""
        if self._paused:
            return math.inf
        wall0, bag0 = self._anchor
        return wall0 + (log_ns - bag0) / (self._rate * NS)

    # -- pause and resume ----------------------------------------------------------------------

    def _pause(self) -> bool:
        """Hold playback at the bag time reached now; False if it was paused already."""
        with self._cond:
            if self._paused:
                return False
            self._paused_at = self._bag_time(time.perf_counter()) if self._playing else 0
            self._paused = True
            self._cond.notify_all()
            return True

    def _resume(self) -> bool:
        """Go on from the bag time where the pause held; False if it was not paused."""
        with self._cond:
            if not self._paused:
                return False
            self._paused = False
            if self._playing:
                self._anchor = (time.perf_counter(), self._paused_at)
            self._cond.notify_all()
            return True

    def _where(self) -> str:
        with self._cond:
            if not self._playing:
                return 'before the first message'
            reached = self._bag_time(time.perf_counter())
        assert self._bag is not None
        return f'at {(reached - self._bag.start_ns) / NS:.3f} s into the bag'

    def _pause_service(self, request, response):
        changed = self._pause()
        response.success = True
        response.message = ('paused ' if changed else 'already paused ') + self._where()
        if changed:
            self.get_logger().info(response.message)
        return response

    def _resume_service(self, request, response):
        where = self._where()
        changed = self._resume()
        response.success = True
        response.message = f'resumed {where}' if changed else f'not paused (playing {where})'
        if changed:
            self.get_logger().info(response.message)
        return response

    def _toggle_service(self, request, response):
        if self._paused:
            return self._resume_service(request, response)
        return self._pause_service(request, response)

    def _is_paused_service(self, request, response):
        response.success = True
        response.message = 'paused' if self._paused else 'playing'
        return response

    def _wait_until(self, target) -> bool:
        """Wait until ``target()`` (a wall time, re-evaluated after a rate change); False when
        the node is stopping."""
        while True:
            with self._cond:
                if self._stopping:
                    return False
                remaining = target() - time.perf_counter()
                if remaining <= 0.0:
                    return True
                if math.isinf(remaining):  # paused
                    self._cond.wait(PAUSED_WAIT_S)
                    continue
                if remaining > COARSE_WAIT_S:
                    self._cond.wait(remaining - COARSE_WAIT_S / 2)
                    continue
            time.sleep(remaining)
            return not self._stopping

    def _wait_for_subscribers(self) -> None:
        need = self.wait_for_subscribers
        if need <= 0:
            return
        self.get_logger().info(f'waiting for {need} subscriber(s) on {", ".join(self._played)}')
        deadline = time.monotonic() + self.wait_timeout
        while True:
            short = {
                t: n
                for t, p in self._publishers_by_topic.items()
                if (n := p.get_subscription_count()) < need
            }
            if not short:
                return
            if time.monotonic() >= deadline:
                counts = ', '.join(f'{t} has {n}' for t, n in short.items())
                self.get_logger().warning(
                    f'playing without waiting longer than {self.wait_timeout:g} s for '
                    f'{need} subscriber(s): {counts}'
                )
                return
            with self._cond:
                if self._stopping:
                    return
                self._cond.wait(0.02)

    def _play(self) -> None:
        try:
            self._wait_for_subscribers()
            if self.start_delay > 0.0:
                t_end = time.perf_counter() + self.start_delay
                self._wait_until(lambda: t_end)
            if not self._stopping:
                self._publish_all()
        except Exception as err:  # a damaged bag, or a bug: say so and stop with status 1
            if not self._interrupted():  # else: Ctrl-C / SIGTERM tore the context down
                self.failed = True
                text = repr(err)
                if isinstance(err, BagError):
                    text = str(err)
                    if 'cloe bag recover' not in text:
                        text += (
                            f' `cloe bag recover {self.bag_path}` writes a bag with every message '
                            'that can still be read.'
                        )
                self.get_logger().error(text)
                self._wait_for_acks()  # what was played reaches the subscribers all the same
        finally:
            self.finished.set()
        if not self._interrupted() and (self.failed or self._exit_when_done):
            rclpy.try_shutdown(context=self.context)

    def _wait_for_acks(self) -> None:
        """Give reliable subscribers time to acknowledge the last messages before shutdown (Fast
        DDS asks for acknowledgements with its periodic heartbeat, every 3 s by default)."""
        deadline = time.monotonic() + self.ack_timeout
        unacked = []
        for topic, pub in self._publishers_by_topic.items():
            remaining = max(0.0, deadline - time.monotonic())
            if not pub.wait_for_all_acked(Duration(nanoseconds=int(remaining * NS))):
                unacked.append(topic)
        if unacked:
            self.get_logger().warning(
                f'not acknowledged by every subscriber within {self.ack_timeout:g} s: '
                f'{", ".join(unacked)} (the last messages may not have arrived)'
            )

    def _interrupted(self) -> bool:
        return self._stopping or not self.context.ok()

    def _publish_all(self) -> None:
        bag = self._bag
        assert bag is not None
        log = self.get_logger()
        clock = self._clock_pub
        period = 1.0 / self.clock_rate
        first = self._first_ns
        lateness = array('d')
        tick_lateness = array('d')  # /clock's ticks, behind their wall times
        item = self._buffer.get()  # the first chunk is decoded before the clock starts
        offset = f' from {self.start_offset:g} s' if self.start_offset else ''
        looping = ', looping' if self.loop else ''
        log.info(
            f'playing {bag.path}: {", ".join(self._played)}, {bag.duration_s:.3f} s at rate '
            f'{self._rate:g}{offset}{looping}'
        )
        wall_start = time.perf_counter()
        count = 0
        while True:
            with self._cond:
                self._anchor = (time.perf_counter(), first)
                if self._paused:
                    self._paused_at = first
                self._playing = True
            self.passes += 1
            next_tick = self._anchor[0]
            # a tick published late, after a resume or a rate change moved the anchor past its
            # wall time, would map to a bag time before the last one: /clock never goes back
            # within a pass (it jumps back only at the start of the next)
            last_clock_ns = first
            while item is not _END and item is not _PASS_END:
                if isinstance(item, BaseException):
                    raise item
                topic, log_ns, raw = item
                if clock is not None:
                    # the next tick or the message, whichever is due first (while paused, the
                    # message never is: the ticks go on with the bag time held)
                    due = lambda t=log_ns, k=next_tick: min(k, self._wall_time(t))  # noqa: E731
                    if not self._wait_until(due):
                        return
                    if next_tick <= self._wall_time(log_ns):
                        with self._cond:
                            now_ns = min(max(self._bag_time(next_tick), last_clock_ns), bag.end_ns)
                        last_clock_ns = now_ns
                        clock.publish(encode_clock(now_ns))
                        tick_lateness.append(time.perf_counter() - next_tick)
                        next_tick += period
                        continue
                elif not self._wait_until(lambda t=log_ns: self._wall_time(t)):
                    return
                self._publishers_by_topic[topic].publish(raw)
                # from the wall time it was due to the publish's return: its send time (the
                # publish's DDS source timestamp) is no later than that
                late = time.perf_counter() - self._wall_time(log_ns)
                if math.isfinite(late):  # (not paused between the wait and now)
                    lateness.append(late)
                count += 1
                self.published = count
                item = self._buffer.get()
            if clock is not None and bag.message_count:  # no messages, no bag time to publish
                clock.publish(encode_clock(bag.end_ns))
            if item is _END:
                break
            log.info(f'pass {self.passes} done ({count} messages so far); playing again{offset}')
            item = self._buffer.get()
        elapsed = time.perf_counter() - wall_start
        self._wait_for_acks()
        ticks = (
            f'; /clock: {len(tick_lateness)} ticks, {_lateness_summary(tick_lateness)}'
            if clock is not None
            else ''
        )
        log.info(
            f'done: {count} messages in {elapsed:.3f} s; {_lateness_summary(lateness)}{ticks}'
        )
        with self._cond:
            self._playing = False

    # -- shutdown ------------------------------------------------------------------------------

    def destroy_node(self) -> None:
        with self._cond:
            self._stopping = True
            self._cond.notify_all()
        if hasattr(self, '_buffer'):
            self._buffer.close()
        for thread in self._threads:
            if thread is not threading.current_thread():
                thread.join(timeout=5.0)
        if self._bag is not None:
            self._bag.close()
            self._bag = None
        super().destroy_node()


def _lateness_summary(lateness: array) -> str:
    """Publications behind schedule, from their due wall times to the returns of their publish
    calls: median, 99th percentile and max, ms."""
    if not lateness:
        return 'nothing published'
    ms = np.asarray(lateness) * 1e3
    return (
        f'behind schedule by median {np.median(ms):.3f} ms, 99th percentile '
        f'{np.percentile(ms, 99):.3f} ms, max {ms.max():.3f} ms'
    )


def main(args: Sequence[str] | None = None) -> int:
    # Low jitter in this process: the reader thread hands the interpreter to the publisher every
    # 0.5 ms (instead of 5 ms), and the objects of the set-up (rclpy, numpy, ...) are frozen out
    # of the garbage collector, whose full collections otherwise stall publishing for ~30 ms.
    sys.setswitchinterval(0.0005)
    nodes: list[PlayerNode] = []

    def make() -> PlayerNode:
        nodes.append(PlayerNode())
        gc.collect()
        gc.freeze()
        return nodes[-1]

    status = common.run_node(make, args)
    if status == 0 and nodes and nodes[0].failed:
        status = 1
    return status


if __name__ == '__main__':
    sys.exit(main())
