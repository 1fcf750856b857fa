"""``quadrotor_sim`` as a process under ``use_sim_time``: it is the clock source, so it must run
on its own pace, not wait for the /clock only it would publish."""

from __future__ import annotations

import signal

import pytest
from geometry_msgs.msg import PoseStamped
from nav_msgs.msg import Odometry
from ros_helpers import NodeProcess, private_domain, reserve_domain_id, spin_until
from rosgraph_msgs.msg import Clock

from cloe_ros.ros.common import qos

pytestmark = pytest.mark.ros

NS = 1_000_000_000
DURATION = 1.0  # simulated s
ODOM_RATE = 50.0
N_ODOM = round(DURATION * ODOM_RATE) + 1


def test_sim_with_use_sim_time_publishes_its_clock_and_finishes(tmp_path) -> None:
    """use_sim_time + publish_clock: /odom and /clock come (same stamps, simulated time from a
    system-time origin) and shutdown_when_done ends the process after the duration."""
    with private_domain('sim_time_probe') as ros:
        odom, clock = [], []
        ros.node.create_subscription(Odometry, '/odom', odom.append, qos(depth=1000))
        ros.node.create_subscription(Clock, '/clock', clock.append, qos(depth=1000))
        ros.node.create_subscription(PoseStamped, '/reference', lambda _: None, qos(depth=1000))
        sim = NodeProcess('quadrotor_sim', {
            'use_sim_time': True, 'publish_clock': True, 'duration': DURATION,
            'shutdown_when_done': True, 'real_time_factor': 4.0, 'sim_rate': 500.0,
            'odom_rate': ODOM_RATE, 'reference_rate': ODOM_RATE, 'publish_truth': False,
            'wait_for_subscribers': 1,
        }, ros.domain, tmp_path)  # fmt: skip
        try:
            done = spin_until(ros.executor, lambda: sim.proc.poll() is not None, 30.0)
            assert done, sim.output()
            spin_until(ros.executor, lambda: len(odom) >= N_ODOM, 2.0)
            assert sim.proc.returncode == 0, sim.output()
            output = sim.output()
        finally:
            sim.stop(signal.SIGKILL)
    assert f'done: {DURATION:g} s simulated' in output
    stamps = [m.header.stamp.sec * NS + m.header.stamp.nanosec for m in odom]
    ticks = [m.clock.sec * NS + m.clock.nanosec for m in clock]
    assert len(stamps) == N_ODOM
    assert ticks == stamps  # /clock ticks with every odometry sample
    assert stamps[0] > 1_600_000_000 * NS  # origin: the system time at start, not 0
    assert stamps[-1] - stamps[0] == round(DURATION * NS)


def test_sim_refuses_use_sim_time_without_publish_clock(tmp_path) -> None:
    """Nobody would publish /clock: refused at start-up in the documented form."""
    sim = NodeProcess(
        'quadrotor_sim', {'use_sim_time': True, 'duration': 1.0}, reserve_domain_id(), tmp_path
    )
    try:
        status = sim.wait(30.0)
    finally:
        sim.stop(signal.SIGKILL)
    err = sim.stderr_path.read_text()
    assert status == 1, err
    expected = "ERROR: parameter 'use_sim_time': use_sim_time is true but publish_clock is false"
    assert expected in err
