"""``quadrotor_sim``: the nonlinear quadrotor simulator as a node.

Per vehicle namespace ``<ns>`` (none for a single vehicle) it publishes ``<ns>/odom``
(nav_msgs/Odometry, REP-105: twist in the body frame, covariances from the noise model),
``<ns>/reference`` (geometry_msgs/PoseStamped: the reference tracked, probing included), and, with
``publish_truth``, ``<ns>/ground_truth`` (noise-free Odometry) and ``<ns>/true_parameters``
(Float64MultiArray, transient local: the Theta of the hover linearization, labelled like
``cloe/parameters``). Stamps are simulation time from an origin taken at start; with
``publish_clock`` the same time goes to ``/clock`` so other nodes can run with ``use_sim_time``.

Time: the simulator is the clock source, so it paces itself on the steady (wall) clock, never on
its node clock; the origin of the stamps is the system time at start. ``use_sim_time:=true`` is
accepted with ``publish_clock:=true`` (the node's own clock then follows the ``/clock`` it
publishes) and refused at start-up without it: the other nodes would wait for a ``/clock`` that
nobody publishes.

Real time: with ``real_time_factor`` > 0 the node measures the factor it achieves over the last
``rtf_window`` s of wall time. When that falls below ``RTF_TOLERANCE`` of the factor asked for,
it warns once (per episode: once it holds the factor again it says so, and a later fall warns
again), and ``/diagnostics`` (every ``diagnostics_period``) reports WARN with the factor asked for,
the factor achieved over the window and since the start, and how far simulated time lags behind.
"""

from __future__ import annotations

import time
from collections import deque

import numpy as np
from diagnostic_msgs.msg import DiagnosticArray
from geometry_msgs.msg import PoseStamped
from nav_msgs.msg import Odometry
from rclpy.clock import Clock as RosClock
from rclpy.clock import ClockType
from rclpy.duration import Duration
from rclpy.node import Node
from rosgraph_msgs.msg import Clock
from std_msgs.msg import Float64MultiArray

from cloe_ros.core.kinematics import state_to_odometry, yaw_quaternion
from cloe_ros.core.model import PARAMETER_NAMES
from cloe_ros.core.samples import OdometrySample, PoseSample
from cloe_ros.core.simulator import (
    NO_PROBING,
    SCENARIOS,
    ControllerGains,
    MeasurementNoise,
    NoDisturbance,
    PaperDisturbance,
    ProbingSignal,
    QuadrotorParams,
    QuadrotorSimulator,
    true_parameters,
)
from cloe_ros.io.messages import (
    Status,
    encode_clock,
    encode_diagnostics,
    encode_float64_multi_array,
    encode_odometry,
    encode_pose_stamped,
)
from cloe_ros.ros.common import (
    NS,
    STRING_ARRAY,
    ParameterError,
    accept,
    check_same_namespaces,
    check_vehicles,
    declare,
    describe,
    destroyed_if_init_fails,
    qos,
    refuse,
    run_node,
    vehicle_topic,
)

GAIN_NAMES = tuple(ControllerGains.__dataclass_fields__)
#: The simulator is behind when it achieves less than this fraction of the factor asked for.
RTF_TOLERANCE = 0.9
#: Longest a tick steps the simulation (wall s) before it lets the executor run other callbacks.
MAX_TICK_S = 0.1
#: diagnostic_msgs/DiagnosticStatus levels.
OK, WARN = 0, 1


class RealTimeMonitor:
    """The real-time factor achieved over a sliding window of wall time, and episodes of falling
    behind the factor asked for.

    ``update(wall_s, sim_s)`` after every tick (wall clock and simulated time, s) returns
    ``'behind'`` when an episode starts (the factor over the last ``window_s`` is below
    ``tolerance * target``), ``'recovered'`` when it ends, else None. Nothing is judged before the
    samples span the window, nor with ``target`` 0 (as fast as possible).
    """

    def __init__(self, target: float, window_s: float, tolerance: float = RTF_TOLERANCE) -> None:
        self.target, self.window_s, self.tolerance = target, window_s, tolerance
        self.behind = False
        self.episodes = 0
        self._samples: deque[tuple[float, float]] = deque()
        self._first: tuple[float, float] | None = None

    def update(self, wall_s: float, sim_s: float) -> str | None:
        if self._first is None:
            self._first = (wall_s, sim_s)
        self._samples.append((wall_s, sim_s))
        while len(self._samples) > 2 and wall_s - self._samples[1][0] >= self.window_s:
            self._samples.popleft()
        achieved = self.achieved
        if achieved is None or self.target <= 0:
            return None
        if not self.behind and achieved < self.tolerance * self.target:
            self.behind = True
            self.episodes += 1
            return 'behind'
        if self.behind and achieved >= self.tolerance * self.target:
            self.behind = False
            return 'recovered'
        return None

    @property
    def achieved(self) -> float | None:
        """Simulated s per wall s over the last window (None until the samples span it)."""
        if len(self._samples) < 2:
            return None
        (w0, s0), (w1, s1) = self._samples[0], self._samples[-1]
        if w1 - w0 < self.window_s:
            return None
        return (s1 - s0) / (w1 - w0)

    @property
    def overall(self) -> float | None:
        """Simulated s per wall s since the first sample."""
        if self._first is None or not self._samples:
            return None
        (w0, s0), (w1, s1) = self._first, self._samples[-1]
        return (s1 - s0) / (w1 - w0) if w1 > w0 else None


class SimulatorNode(Node):
    """The simulator node; see the module docstring and the README for its interface."""

    @destroyed_if_init_fails
    def __init__(self, **kwargs) -> None:
        super().__init__('quadrotor_sim', **kwargs)
        values = self._declare_parameters()
        get = values.__getitem__
        scenario = SCENARIOS[get('scenario')]
        self.vehicles = check_vehicles(get('vehicles') or []) or ['']
        check_same_namespaces(self, self.vehicles)
        n = len(self.vehicles)
        offsets = np.zeros((n, 3))
        offsets[:, 1] = get('spacing') * np.arange(n)
        quad = QuadrotorParams(mass=get('mass'), inertia=tuple(get('inertia')))
        gains = ControllerGains(**{g: get(f'controller.{g}') for g in GAIN_NAMES})
        self.noise = MeasurementNoise(
            get('noise_position'), get('noise_velocity'), get('noise_angle'), get('noise_rate')
        )
        probing = ProbingSignal().scaled(get('probing_scale')) if get('probing') else NO_PROBING
        self.sim = QuadrotorSimulator(
            scenario,
            n_vehicles=n,
            quad=quad,
            gains=gains,
            disturbance=PaperDisturbance() if get('disturbance') else NoDisturbance(),
            probing=probing,
            noise=self.noise,
            dt=1.0 / get('sim_rate'),
            offsets=offsets,
            rng=np.random.default_rng(get('seed')),
        )
        self.duration = get('duration') or scenario.duration
        self.rtf = get('real_time_factor')
        self.world_frame, self.body_frame = get('world_frame'), get('body_frame')
        # one body frame per vehicle when there are several (TF frame ids: no leading slash)
        self.body_frames = {v: f'{v.strip("/")}/{self.body_frame}' if v else self.body_frame
                            for v in self.vehicles}  # fmt: skip
        sim_rate = get('sim_rate')
        self.odom_every = self._divisor(sim_rate, get('odom_rate'), 'odom_rate')
        self.ref_every = self._divisor(sim_rate, get('reference_rate'), 'reference_rate')
        self.publish_clock = get('publish_clock')
        self.publish_truth = get('publish_truth')
        self.shutdown_when_done = get('shutdown_when_done')
        self.wait_for_subscribers = get('wait_for_subscribers')
        self.wait_timeout = get('wait_timeout')
        self.monitor = RealTimeMonitor(self.rtf, get('rtf_window'))
        if self.get_parameter('use_sim_time').value and not self.publish_clock:
            raise ParameterError(
                'use_sim_time is true but publish_clock is false: the simulator is the clock '
                'source, and without publish_clock nobody publishes /clock; set '
                'publish_clock:=true (or use_sim_time:=false)',
                'use_sim_time',
            )

        depth = get('qos_depth')
        self.pubs = {}
        for v in self.vehicles:
            self.pubs[(v, 'odom')] = self.create_publisher(
                Odometry, vehicle_topic(v, 'odom'), qos(depth=depth)
            )
            self.pubs[(v, 'reference')] = self.create_publisher(
                PoseStamped, vehicle_topic(v, 'reference'), qos(depth=depth)
            )
            if self.publish_truth:
                self.pubs[(v, 'ground_truth')] = self.create_publisher(
                    Odometry, vehicle_topic(v, 'ground_truth'), qos(depth=depth)
                )
                self.pubs[(v, 'true_parameters')] = self.create_publisher(
                    Float64MultiArray, vehicle_topic(v, 'true_parameters'),
                    qos(depth=1, transient_local=True),
                )  # fmt: skip
        self.clock_pub = (
            self.create_publisher(Clock, '/clock', qos(depth=10)) if self.publish_clock else None
        )
        self.diagnostics_pub = self.create_publisher(
            DiagnosticArray, '/diagnostics', qos(depth=10)
        )
        self._diag_timer = self.create_timer(
            get('diagnostics_period'),
            self._publish_diagnostics,
            clock=RosClock(clock_type=ClockType.STEADY_TIME),
        )
        self.add_on_set_parameters_callback(self._on_set_parameters)
        self.theta_true = true_parameters(quad, gains)
        self.origin_ns: int | None = None
        self.wall_start: float | None = None
        self._started: float | None = None  # wall (monotonic) time of the first sample
        self._wait_start = time.monotonic()
        self._step = 0
        self.done = False
        period = 1.0 / get('odom_rate') if self.rtf > 0 else 0.001
        # paced on the steady clock: with use_sim_time the node clock only moves with the /clock
        # this node itself publishes
        self.timer = self.create_timer(
            period, self._tick, clock=RosClock(clock_type=ClockType.STEADY_TIME)
        )
        self.get_logger().info(
            f'simulating {scenario.name} for {self.duration:g} s, {n} vehicle(s), '
            f'real-time factor {self.rtf:g}'
        )

    def _declare_parameters(self) -> dict:
        ro = {'read_only': True}
        defaults = ControllerGains()
        p = [
            ('scenario', 'position', describe(
                'scenario: ' + ' | '.join(SCENARIOS), **ro,
                additional_constraints='one of ' + ', '.join(SCENARIOS))),
            ('vehicles', [], describe(
                'vehicle namespaces, e.g. [/uav1, /uav2]; empty: one vehicle, no namespace',
                parameter_type=STRING_ARRAY, **ro)),
            ('spacing', 2.0, describe('y offset between vehicles, m', float_range=(0.0, 100.0),
                                      **ro)),
            ('duration', 0.0, describe(
                'simulated time, s; 0: the scenario length', float_range=(0.0, 1e6), **ro)),
            ('real_time_factor', 1.0, describe(
                'simulated seconds per wall-clock second; 0: as fast as possible',
                float_range=(0.0, 100.0))),
            ('sim_rate', 1000.0, describe('integration rate (RK4), Hz',
                                          float_range=(100.0, 10000.0), **ro)),
            ('odom_rate', 100.0, describe('odom rate, Hz (must divide sim_rate)',
                                          float_range=(1.0, 1000.0), **ro)),
            ('reference_rate', 100.0, describe(
                'reference rate, Hz (must divide sim_rate; estimators hold the reference between '
                'samples, so a slow rate biases identification of the fast loops)',
                float_range=(1.0, 1000.0), **ro)),
            ('publish_clock', False, describe('publish /clock with the simulation time', **ro)),
            ('publish_truth', True, describe(
                'publish ground_truth and true_parameters per vehicle', **ro)),
            ('disturbance', True, describe('the paper §6.1 disturbances', **ro)),
            ('probing', True, describe('add the probing signal to the reference', **ro)),
            ('probing_scale', 1.0, describe('probing amplitude factor',
                                            float_range=(0.0, 10.0), **ro)),
            ('noise_position', 0.0, describe('odom position noise sigma, m',
                                             float_range=(0.0, 10.0), **ro)),
            ('noise_velocity', 0.0, describe('odom velocity noise sigma, m/s',
                                             float_range=(0.0, 10.0), **ro)),
            ('noise_angle', 0.0, describe('odom attitude noise sigma, rad',
                                          float_range=(0.0, 1.0), **ro)),
            ('noise_rate', 0.0, describe('odom body-rate noise sigma, rad/s',
                                         float_range=(0.0, 10.0), **ro)),
            ('seed', 0, describe('noise random seed', int_range=(0, 2**31 - 1), **ro)),
            ('mass', 0.52, describe('vehicle mass, kg', float_range=(0.01, 100.0), **ro)),
            ('inertia', [0.01, 0.01, 0.02], describe(
                'Jx, Jy, Jz, kg m^2', additional_constraints='3 values > 0', **ro)),
            ('world_frame', 'world', describe('header.frame_id of odom and reference', **ro)),
            ('body_frame', 'base_link', describe(
                'child_frame_id of odom (with vehicles: <vehicle>/<body_frame>)', **ro)),
            ('wait_for_subscribers', 0, describe(
                'wait until every odom and reference topic has this many subscribers before '
                'starting',
                int_range=(0, 100), **ro)),
            ('wait_timeout', 30.0, describe('then start anyway after this many s',
                                            float_range=(0.0, 3600.0), **ro)),
            ('shutdown_when_done', False, describe('exit when the duration is over', **ro)),
            ('rtf_window', 5.0, describe(
                'window of wall time over which the achieved real-time factor is measured, s '
                f'(below {RTF_TOLERANCE:g} of real_time_factor: a warning and WARN in '
                '/diagnostics)', float_range=(0.1, 600.0), **ro)),
            ('diagnostics_period', 1.0, describe(
                '/diagnostics period, s (wall time)', float_range=(0.05, 60.0), **ro)),
            ('qos_depth', 1000, describe(
                'QoS history depth of the publishers (10 s of 100 Hz: a subscriber starved of CPU '
                'for a moment loses nothing)', int_range=(1, 100000), **ro)),
        ] + [
            (f'controller.{g}', float(getattr(defaults, g)), describe(
                f'controller gain {g} (see docs/method.md)', float_range=(0.0, 1e5), **ro))
            for g in GAIN_NAMES
        ]  # fmt: skip
        values = {name: declare(self, name, default, d) for name, default, d in p}
        if values['scenario'] not in SCENARIOS:
            reason = f'{values["scenario"]!r} is not one of {", ".join(SCENARIOS)}'
            raise ParameterError(reason, 'scenario')
        inertia = values['inertia']
        if len(inertia) != 3 or min(inertia) <= 0:
            raise ParameterError(f'needs 3 values > 0, got {list(inertia)}', 'inertia')
        return values

    def _on_set_parameters(self, params):
        for p in params:
            if p.name == 'real_time_factor' and (p.value > 0) != (self.rtf > 0):
                return refuse('real_time_factor cannot switch between 0 and > 0 while running')
        for p in params:
            if p.name == 'real_time_factor':
                if self.wall_start is not None:  # keep the simulated time continuous
                    elapsed = time.monotonic() - self.wall_start
                    self.wall_start = time.monotonic() - elapsed * self.rtf / max(p.value, 1e-9)
                self.rtf = p.value
                self.monitor = RealTimeMonitor(p.value, self.monitor.window_s)
        return accept()

    @staticmethod
    def _divisor(sim_rate: float, rate: float, name: str) -> int:
        every = sim_rate / rate
        if abs(every - round(every)) > 1e-9 or round(every) < 1:
            raise ParameterError(f'{rate:g} Hz does not divide sim_rate {sim_rate:g} Hz', name)
        return round(every)

    # --------------------------------------------------------------------------- running

    def _ready(self) -> bool:
        if self.wait_for_subscribers <= 0:
            return True
        counts = [
            self.pubs[(v, topic)].get_subscription_count()
            for v in self.vehicles
            for topic in ('odom', 'reference')
        ]
        if min(counts) >= self.wait_for_subscribers:
            return True
        if time.monotonic() - self._wait_start > self.wait_timeout:
            self.get_logger().warning(
                f'starting with {min(counts)} subscriber(s) after {self.wait_timeout:g} s'
            )
            return True
        return False

    def _tick(self) -> None:
        if self.done:
            return
        if self.origin_ns is None:
            if not self._ready():
                return
            self.origin_ns = time.time_ns()  # system time, whatever the node clock
            self.wall_start = self._started = time.monotonic()
            if self.publish_truth:
                for v in self.vehicles:
                    labels = [f'theta.{n}' for n in PARAMETER_NAMES]
                    self.pubs[(v, 'true_parameters')].publish(
                        encode_float64_multi_array(labels, self.theta_true)
                    )
            self._publish_samples()
            self.get_logger().info('started')
        if self.rtf > 0:
            target = (time.monotonic() - self.wall_start) * self.rtf
        else:
            target = self.sim.t + 0.05
        target = min(target, self.duration)
        tick_end = time.monotonic() + MAX_TICK_S
        while self.sim.t + 0.5 * self.sim.dt < target:
            self.sim.step()
            self._step += 1
            self._publish_samples()
            if time.monotonic() > tick_end:
                break  # behind: let the executor serve diagnostics and parameters meanwhile
        self._watch_real_time()
        if self.sim.t + 0.5 * self.sim.dt >= self.duration:
            self.done = True
            wall = time.monotonic() - self._started
            achieved = f'{self.sim.t / wall:.3g}' if wall > 0 else 'inf'
            asked = f'{self.rtf:g}' if self.rtf > 0 else 'as fast as possible'
            self.get_logger().info(
                f'done: {self.duration:g} s simulated in {wall:.2f} s of wall time '
                f'(real-time factor {achieved}, asked {asked})'
            )
            if self.shutdown_when_done:
                self._wait_for_acks()
                self.context.try_shutdown()

    def _lag_s(self) -> float:
        """How far simulated time is behind the wall clock scaled by the factor asked for, s."""
        if self.rtf <= 0 or self.wall_start is None or self.done:
            return 0.0
        wanted = min((time.monotonic() - self.wall_start) * self.rtf, self.duration)
        return max(0.0, wanted - self.sim.t)

    def _watch_real_time(self) -> None:
        event = self.monitor.update(time.monotonic(), self.sim.t)
        if event == 'behind':
            self.get_logger().warning(
                f'cannot hold real_time_factor {self.rtf:g}: achieved {self.monitor.achieved:.3g} '
                f'over the last {self.monitor.window_s:g} s of wall time; simulated time lags '
                f'{self._lag_s():.1f} s behind (a busy machine? lower real_time_factor, sim_rate '
                'or the number of vehicles)'
            )
        elif event == 'recovered':
            self.get_logger().info(
                f'real_time_factor {self.rtf:g} held again (achieved {self.monitor.achieved:.3g} '
                f'over the last {self.monitor.window_s:g} s)'
            )

    def _publish_diagnostics(self) -> None:
        m = self.monitor

        def number(value: float | None) -> str:
            return '' if value is None else f'{value:.4g}'

        if self.origin_ns is None:
            level, message = OK, 'waiting for subscribers'
        elif self.done:
            level, message = OK, f'done: {self.duration:g} s simulated'
        elif m.behind:
            level = WARN
            message = f'falling behind: real-time factor {number(m.achieved)} of {self.rtf:g}'
        elif self.rtf > 0:
            level, message = OK, f'real-time factor {self.rtf:g}'
        else:
            level, message = OK, 'as fast as possible'
        values = (
            ('scenario', self.sim.scenario.name),
            ('vehicles', str(len(self.vehicles))),
            ('sim_time_s', f'{self.sim.t:.3f}'),
            ('duration_s', f'{self.duration:g}'),
            ('real_time_factor', f'{self.rtf:g}'),
            ('real_time_factor_achieved', number(m.achieved)),
            ('real_time_factor_overall', number(m.overall)),
            ('rtf_window_s', f'{m.window_s:g}'),
            ('lag_s', f'{self._lag_s():.3f}'),
            ('behind_episodes', str(m.episodes)),
        )
        stamp = self.origin_ns + round(self.sim.t * NS) if self.origin_ns else time.time_ns()
        status = Status(level, self.get_name(), message, 'quadrotor_sim', values)
        self.diagnostics_pub.publish(encode_diagnostics(stamp, [status]))

    def _wait_for_acks(self, timeout: float = 3.5) -> None:
        """Before exiting, let reliable subscribers acknowledge the last samples (Fast DDS asks
        with its heartbeat, every 3 s by default); a subscriber short of CPU at the end would
        otherwise lose them."""
        deadline = time.monotonic() + timeout
        for (vehicle, topic), pub in self.pubs.items():
            remaining = max(0.0, deadline - time.monotonic())
            if not pub.wait_for_all_acked(Duration(nanoseconds=int(remaining * NS))):
                self.get_logger().warning(
                    f'{vehicle or "/"} {topic}: not acknowledged by every subscriber within '
                    f'{timeout:g} s (the last samples may not have arrived)'
                )

    def _publish_samples(self) -> None:
        k = self._step
        send_odom, send_ref = k % self.odom_every == 0, k % self.ref_every == 0
        if not (send_odom or send_ref):
            return
        stamp = self.origin_ns + round(self.sim.t * NS)
        if self.clock_pub is not None and send_odom:
            self.clock_pub.publish(encode_clock(stamp))
        if send_odom:
            truth = self.sim.zeta
            measured = self.sim.add_noise(truth)
            for i, v in enumerate(self.vehicles):
                self.pubs[(v, 'odom')].publish(self._odometry(stamp, measured[i], v, noisy=True))
                if self.publish_truth:
                    self.pubs[(v, 'ground_truth')].publish(
                        self._odometry(stamp, truth[i], v, noisy=False)
                    )
        if send_ref:
            ref = self.sim.reference(self.sim.t)
            for i, v in enumerate(self.vehicles):
                r = ref[i]
                sample = PoseSample(
                    stamp, self.world_frame, np.array([r[0], r[1], r[3]]), yaw_quaternion(r[2])
                )
                self.pubs[(v, 'reference')].publish(encode_pose_stamped(sample))

    def _odometry(self, stamp: int, zeta: np.ndarray, vehicle: str, noisy: bool) -> bytes:
        position, quaternion, v_body, w_body = state_to_odometry(zeta)
        pose_cov = twist_cov = None
        if noisy and self.noise.enabled:
            n = self.noise
            pose_cov = np.diag([n.position**2] * 3 + [n.angle**2] * 3).ravel()
            twist_cov = np.diag([n.velocity**2] * 3 + [n.rate**2] * 3).ravel()
        return encode_odometry(
            OdometrySample(
                stamp,
                self.world_frame,
                self.body_frames[vehicle],
                position,
                quaternion,
                v_body,
                w_body,
                pose_cov,
                twist_cov,
            )
        )


def main(args=None) -> int:
    return run_node(SimulatorNode, args)


if __name__ == '__main__':
    raise SystemExit(main())
