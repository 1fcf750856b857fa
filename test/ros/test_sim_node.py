"""``quadrotor_sim`` as a process under ``use_sim_time``: it is the clock source, so it must run
on its own pace, not wait for the /clock only it would publish."""

from __future__ import annotations

import signal
import time

import pytest
from diagnostic_msgs.msg import DiagnosticArray
from geometry_msgs.msg import PoseStamped
from nav_msgs.msg import Odometry
from rclpy.parameter import Parameter
from ros_helpers import private_domain, reserve_domain_id, spin_until, start_node
from rosgraph_msgs.msg import Clock

from cloe_ros.ros.common import qos
from cloe_ros.ros.sim_node import WARN, RealTimeMonitor, SimulatorNode

pytestmark = pytest.mark.ros

NS = 1_000_000_000
DURATION = 1.0  # simulated s
ODOM_RATE = 50.0
N_ODOM = round(DURATION * ODOM_RATE) + 1


def _ns(stamp) -> int:
    return stamp.sec * NS + stamp.nanosec


def test_sim_with_use_sim_time_publishes_its_clock_and_finishes(tmp_path) -> None:
    """use_sim_time + publish_clock: /odom and /clock come (same stamps, simulated time from a
    system-time origin) and shutdown_when_done ends the process after the duration."""
    with private_domain('sim_time_probe') as ros:
        odom, clock = [], []
        ros.node.create_subscription(Odometry, '/odom', odom.append, qos(depth=1000))
        ros.node.create_subscription(Clock, '/clock', clock.append, qos(depth=1000))
        ros.node.create_subscription(PoseStamped, '/reference', lambda _: None, qos(depth=1000))
        sim = start_node('quadrotor_sim', {
            'use_sim_time': True, 'publish_clock': True, 'duration': DURATION,
            'shutdown_when_done': True, 'real_time_factor': 4.0, 'sim_rate': 500.0,
            'odom_rate': ODOM_RATE, 'reference_rate': ODOM_RATE, 'publish_truth': False,
            'wait_for_subscribers': 1,
        }, ros.domain, tmp_path)  # fmt: skip
        try:
            done = spin_until(ros.executor, lambda: sim.proc.poll() is not None, 120.0)
            assert done, sim.output()
            # (the simulator exits once its samples are acknowledged: they are in this
            # process's queue, the executor may not have taken them yet)
            spin_until(ros.executor, lambda: len(odom) >= N_ODOM and clock and
                       _ns(clock[-1].clock) == _ns(odom[-1].header.stamp), 60.0)  # fmt: skip
            assert sim.proc.returncode == 0, sim.output()
            output = sim.output()
        finally:
            sim.stop(signal.SIGKILL)
    assert f'done: {DURATION:g} s simulated in ' in output
    assert 'real-time factor ' in output and 'asked 4)' in output
    stamps = [_ns(m.header.stamp) for m in odom]
    ticks = [_ns(m.clock) for m in clock]
    assert len(stamps) == N_ODOM
    # /clock ticks with every odometry sample, from the first tick this subscription got on: the
    # simulator waits for the subscribers of /odom and /reference, and under load the /clock
    # subscription can be matched some ticks later (a volatile topic keeps nothing for it)
    print(f'/clock: {len(ticks)} ticks of {len(stamps)} odometry stamps')
    assert ticks and ticks == stamps[len(stamps) - len(ticks):]
    assert stamps[0] > 1_600_000_000 * NS  # origin: the system time at start, not 0
    assert stamps[-1] - stamps[0] == round(DURATION * NS)


def test_sim_refuses_use_sim_time_without_publish_clock(tmp_path) -> None:
    """Nobody would publish /clock: refused at start-up in the documented form."""
    sim = start_node(
        'quadrotor_sim', {'use_sim_time': True, 'duration': 1.0}, reserve_domain_id(), tmp_path
    )
    try:
        status = sim.wait(120.0)
    finally:
        sim.stop(signal.SIGKILL)
    err = sim.errors()
    assert status == 1, err
    expected = "ERROR: parameter 'use_sim_time': use_sim_time is true but publish_clock is false"
    assert expected in err


# -- real-time factor --------------------------------------------------------------------------


def test_real_time_monitor_episodes() -> None:
    """Synthetic clocks: the factor over the window, one 'behind' per episode, 'recovered' when
    it holds again; nothing judged before the window is spanned or when asked for 0."""
    m = RealTimeMonitor(target=2.0, window_s=1.0)
    events = []
    wall = sim = 0.0
    for rate, seconds in ((2.0, 3.0), (1.0, 3.0), (2.0, 3.0), (0.5, 3.0)):
        for _ in range(round(seconds / 0.1)):
            wall += 0.1
            sim += 0.1 * rate
            events.append((round(wall, 1), m.update(wall, sim)))
    happened = [(w, e) for w, e in events if e]
    assert [e for _, e in happened] == ['behind', 'recovered', 'behind']
    assert m.episodes == 2 and m.behind
    assert m.achieved == pytest.approx(0.5)
    assert m.overall == pytest.approx((sim - 0.2) / (wall - 0.1))  # from the first sample
    assert all(e is None for w, e in events if w < 1.0)  # the window is not spanned yet
    # as fast as possible: measured, never judged
    fast = RealTimeMonitor(target=0.0, window_s=1.0)
    assert all(fast.update(0.1 * k, 0.01 * k) is None for k in range(50))
    assert fast.achieved == pytest.approx(0.1) and not fast.behind


def level(status) -> int:
    """DiagnosticStatus.level (a byte in rclpy's message)."""
    value = status.level
    return int.from_bytes(value, 'little') if isinstance(value, bytes) else int(value)


def test_sim_that_cannot_hold_its_factor_warns_and_reports_it(monkeypatch, capfd) -> None:
    """Each step made slower than real time (2 ms of sleep per 1 ms step, whatever the machine):
    one warning, WARN in /diagnostics with the achieved factor, the factor in the done line."""
    with private_domain('rtf_probe') as ros:
        diagnostics = []
        ros.node.create_subscription(
            DiagnosticArray, '/diagnostics', diagnostics.append, qos(depth=100)
        )
        sim = SimulatorNode(
            context=ros.ctx,
            parameter_overrides=[
                Parameter('duration', value=3.0),
                Parameter('real_time_factor', value=1.0),
                Parameter('rtf_window', value=0.5),
                Parameter('diagnostics_period', value=0.2),
                Parameter('publish_truth', value=False),
            ],
        )
        step = sim.sim.step
        monkeypatch.setattr(sim.sim, 'step', lambda: (time.sleep(0.002), step()))
        ros.executor.add_node(sim)
        try:

            def reported() -> bool:
                return any(level(s) == WARN for d in diagnostics for s in d.status)

            assert spin_until(ros.executor, reported, timeout=60.0)
            assert spin_until(ros.executor, lambda: sim.done, timeout=120.0)
        finally:
            ros.executor.remove_node(sim)
            sim.destroy_node()
    log = capfd.readouterr().err
    warnings = [line for line in log.splitlines() if 'cannot hold' in line]
    assert len(warnings) == 1, log  # once per episode
    assert 'cannot hold real_time_factor 1: achieved 0.' in warnings[0]
    assert sim.monitor.episodes == 1
    assert 'done: 3 s simulated in ' in log
    status = next(s for d in diagnostics for s in d.status if level(s) == WARN)
    values = {kv.key: kv.value for kv in status.values}
    assert status.name == 'quadrotor_sim' and status.message.startswith('falling behind')
    assert float(values['real_time_factor']) == 1.0
    assert float(values['real_time_factor_achieved']) < 0.5  # at most 1 ms simulated per 2 ms
    assert float(values['lag_s']) > 0.0 and values['behind_episodes'] == '1'
    assert sim.monitor.overall < 0.5
